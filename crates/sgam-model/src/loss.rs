//! Losses: L1 reconstruction, a weight-free perceptual term (image-gradient L1), the hinge
//! PatchGAN discriminator (pix2pix NLayer) and the adaptive GAN weight.
//!
//! Perceptual term: LPIPS needs ImageNet VGG16 weights we cannot fetch, so training uses the L1
//! distance between the finite-difference image gradients (x and y) of prediction and target over
//! all 4 channels. It penalises blurred edges that plain L1 tolerates, needs no pretrained
//! network and costs a few element-wise ops.

use burn::module::Module;
use burn::nn::conv::Conv2d;
use burn::nn::{BatchNorm, BatchNormConfig};
use burn::tensor::activation::{leaky_relu, relu};
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::blocks::conv;

/// Mean absolute error over every element: `[1]`.
pub fn l1(pred: Tensor<4>, target: Tensor<4>) -> Tensor<1> {
    (pred - target).abs().mean()
}

/// Image-gradient L1: mean |dx(pred) - dx(target)| + mean |dy(pred) - dy(target)|, `[1]`.
pub fn gradient_l1(pred: Tensor<4>, target: Tensor<4>) -> Tensor<1> {
    let [b, c, h, w] = pred.dims();
    let dx = |t: Tensor<4>| t.clone().slice([0..b, 0..c, 0..h, 1..w]) - t.slice([0..b, 0..c, 0..h, 0..w - 1]);
    let dy = |t: Tensor<4>| t.clone().slice([0..b, 0..c, 1..h, 0..w]) - t.slice([0..b, 0..c, 0..h - 1, 0..w]);
    let ex = (dx(pred.clone()) - dx(target.clone())).abs().mean();
    let ey = (dy(pred) - dy(target)).abs().mean();
    ex + ey
}

/// Discriminator hyper-parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiscriminatorConfig {
    /// Input channels (4: RGB + disparity).
    pub in_channels: usize,
    /// Base width (pix2pix: 64).
    pub ndf: usize,
    /// Number of strided layers after the first conv (pix2pix: 3).
    pub n_layers: usize,
}

impl DiscriminatorConfig {
    /// pix2pix NLayer with ndf 64, 3 layers, 4 input channels (the authors').
    pub fn paper() -> Self {
        Self { in_channels: 4, ndf: 64, n_layers: 3 }
    }

    /// The narrower discriminator used with the compact model (ndf 32).
    pub fn compact() -> Self {
        Self { in_channels: 4, ndf: 32, n_layers: 3 }
    }
}

/// A conv + BatchNorm + LeakyReLU(0.2) layer of the discriminator.
#[derive(Module, Debug)]
pub struct DiscLayer {
    /// 4x4 convolution without bias.
    pub conv: Conv2d,
    /// Batch normalisation.
    pub norm: BatchNorm,
}

/// pix2pix NLayer PatchGAN discriminator: `[B, 4, H, W] -> [B, 1, h, w]` logits.
#[derive(Module, Debug)]
pub struct Discriminator {
    /// First 4x4 stride-2 conv (with bias, no norm).
    pub conv_first: Conv2d,
    /// Normalised layers.
    pub layers: Vec<DiscLayer>,
    /// Final 4x4 stride-1 conv to one channel.
    pub conv_last: Conv2d,
}

fn conv_nobias(c_in: usize, c_out: usize, stride: usize, device: &Device) -> Conv2d {
    use burn::nn::conv::Conv2dConfig;
    use burn::nn::PaddingConfig2d;
    Conv2dConfig::new([c_in, c_out], [4, 4])
        .with_stride([stride, stride])
        .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
        .with_bias(false)
        .init(device)
}

impl Discriminator {
    /// Builds the discriminator with deterministic weights from `seed`.
    pub fn new(cfg: &DiscriminatorConfig, seed: u64, device: &Device) -> Self {
        let conv_first = conv(cfg.in_channels, cfg.ndf, 4, 2, 1, device);
        let mut layers = Vec::new();
        let mut mult = 1;
        for n in 1..=cfg.n_layers {
            let prev = mult;
            mult = (1usize << n).min(8);
            let stride = if n == cfg.n_layers { 1 } else { 2 };
            layers.push(DiscLayer {
                conv: conv_nobias(cfg.ndf * prev, cfg.ndf * mult, stride, device),
                norm: BatchNormConfig::new(cfg.ndf * mult).init(device),
            });
        }
        let conv_last = conv(cfg.ndf * mult, 1, 4, 1, 1, device);
        crate::params::init_params(Self { conv_first, layers, conv_last }, seed ^ 0xD15C)
    }

    /// Patch logits.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let mut h = leaky_relu(self.conv_first.forward(x), 0.2);
        for layer in &self.layers {
            h = leaky_relu(layer.norm.forward(layer.conv.forward(h)), 0.2);
        }
        self.conv_last.forward(h)
    }
}

/// Hinge discriminator loss `0.5 (mean relu(1 - D(real)) + mean relu(1 + D(fake)))`.
pub fn hinge_d_loss(logits_real: Tensor<4>, logits_fake: Tensor<4>) -> Tensor<1> {
    let real = relu(logits_real.neg().add_scalar(1.0)).mean();
    let fake = relu(logits_fake.add_scalar(1.0)).mean();
    (real + fake).mul_scalar(0.5)
}

/// Generator adversarial loss `-mean D(fake)`.
pub fn generator_loss(logits_fake: Tensor<4>) -> Tensor<1> {
    logits_fake.mean().neg()
}

/// Adaptive GAN weight `scale * clamp(|g_rec| / (|g_gan| + 1e-4), 0, 1e4)` from the gradient
/// norms of the two losses at the decoder's last layer weight.
pub fn adaptive_weight(grad_rec_norm: f32, grad_gan_norm: f32, scale: f32) -> f32 {
    let w = grad_rec_norm / (grad_gan_norm + 1e-4);
    scale * if w.is_finite() { w.clamp(0.0, 1e4) } else { 0.0 }
}
