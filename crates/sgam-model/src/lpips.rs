//! LPIPS v0.1 (Zhang et al. 2018, VGG16 variant) with user-supplied weights: a learned perceptual
//! distance between two RGB images, usable as a metric or, being differentiable, as a loss.
//!
//! We cannot ship or download the ImageNet VGG16 weights, so LPIPS is optional (training uses the
//! weight-free perceptual term of [`crate::loss`]). A user who has the weights packs them into one
//! safetensors file holding
//! - the torchvision VGG16 convolutions `features.{0,2,5,7,10,12,14,17,19,21,24,26,28}.{weight,bias}`
//!   (weights `[C_out, C_in, 3, 3]`, biases `[C_out]`), and
//! - the LPIPS linear heads `lin{0..4}.model.1.weight`, `[1, C, 1, 1]` with C = 64, 128, 256, 512,
//!   512 (the `lpips` package's `weights/v0.1/vgg.pth`).
//!
//! Other tensors in the file (e.g. VGG's `classifier.*`) are ignored. F32, F16 and BF16 are read.
//! One way to write the file (Python, with `torch`, `torchvision`, `lpips` and `safetensors`):
//!
//! ```python
//! import os, torch, torchvision, lpips
//! from safetensors.torch import save_file
//! vgg = torchvision.models.vgg16(weights=torchvision.models.VGG16_Weights.IMAGENET1K_V1)
//! t = {f"features.{k}": v for k, v in vgg.features.state_dict().items()}
//! t.update(torch.load(os.path.join(os.path.dirname(lpips.__file__), "weights/v0.1/vgg.pth"),
//!                     map_location="cpu"))
//! save_file({k: v.float().contiguous() for k, v in t.items()}, "lpips_vgg.safetensors")
//! ```
//!
//! The network, exactly as `lpips.LPIPS(net='vgg', version='0.1')`: scaling layer
//! `(x - shift) / scale`; VGG16 features at relu1_2, relu2_2, relu3_3, relu4_3 and relu5_3 (3x3
//! convs with padding 1, 2x2 stride-2 max-pooling between stages); each feature unit-normalised
//! over channels (`f / (||f|| + 1e-10)`); squared difference; 1x1 linear head without bias; mean
//! over pixels; sum over the five layers. One deviation: the channel norm is `sqrt(sum f^2 + 1e-20)`
//! so that the gradient at an all-zero feature vector is 0 (PyTorch's is NaN there); the added
//! 1e-20 is lost in f32 rounding for any `sum f^2` above about 1e-13, so values do not change.

use std::collections::BTreeMap;
use std::path::Path;

use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::pool::MaxPool2dConfig;
use burn::nn::PaddingConfig2d;
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};

use crate::params::{from_safetensors_bytes, NamedTensor};
use crate::ModelError;

/// The VGG16 convolutions LPIPS uses: `(index in torchvision's vgg16().features, C_in, C_out)`.
pub const VGG16_CONVS: [(usize, usize, usize); 13] = [
    (0, 3, 64),
    (2, 64, 64),
    (5, 64, 128),
    (7, 128, 128),
    (10, 128, 256),
    (12, 256, 256),
    (14, 256, 256),
    (17, 256, 512),
    (19, 512, 512),
    (21, 512, 512),
    (24, 512, 512),
    (26, 512, 512),
    (28, 512, 512),
];

/// Convolutions per VGG16 stage (the stage's last ReLU is the tapped feature).
const STAGE_CONVS: [usize; 5] = [2, 2, 3, 3, 3];

/// Channels of the five tapped features (= input channels of the `lin{k}` heads).
pub const LPIPS_CHANNELS: [usize; 5] = [64, 128, 256, 512, 512];

/// LPIPS scaling layer shift (per RGB channel), applied to inputs in `[-1, 1]`.
pub const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];

/// LPIPS scaling layer scale (per RGB channel).
pub const SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// Smallest image side: four 2x2 poolings must leave at least one pixel.
pub const MIN_SIDE: usize = 16;

/// Every tensor an LPIPS weight file must hold, with its shape, in network order.
pub fn expected_tensors() -> Vec<(String, Vec<usize>)> {
    let mut out = Vec::with_capacity(2 * VGG16_CONVS.len() + LPIPS_CHANNELS.len());
    for (i, c_in, c_out) in VGG16_CONVS {
        out.push((format!("features.{i}.weight"), vec![c_out, c_in, 3, 3]));
        out.push((format!("features.{i}.bias"), vec![c_out]));
    }
    for (k, c) in LPIPS_CHANNELS.iter().enumerate() {
        out.push((format!("lin{k}.model.1.weight"), vec![1, *c, 1, 1]));
    }
    out
}

/// The LPIPS network (VGG16 trunk + linear heads), frozen: its parameters never require
/// gradients, but gradients flow through it to the images.
#[derive(Module, Debug)]
pub struct Lpips {
    /// The 13 VGG16 3x3 convolutions (torchvision `features.0` ... `features.28`), with bias.
    pub features: Vec<Conv2d>,
    /// The five 1x1 heads `lin0` ... `lin4` (`C -> 1`, no bias).
    pub lin: Vec<Conv2d>,
}

impl Lpips {
    /// Loads the weights from a safetensors file (names and shapes in the [module docs](self)) onto
    /// the default device. Errors name the file and the missing or mis-shaped tensor.
    pub fn load(path: &Path) -> Result<Self, ModelError> {
        Self::load_on(path, &crate::default_device())
    }

    /// [`Lpips::load`] onto `device`. For use as a loss inside a training step, load it onto the
    /// autodiff device the images live on (`device.autodiff()`); its weights stay frozen there.
    pub fn load_on(path: &Path, device: &Device) -> Result<Self, ModelError> {
        let bytes = std::fs::read(path).map_err(|e| ModelError::io(path, e))?;
        let (tensors, _) = from_safetensors_bytes(&bytes).map_err(|e| e.in_file(path))?;
        Self::from_tensors(&tensors, device).map_err(|e| e.in_file(path))
    }

    /// Builds the network from named tensors (see [`expected_tensors`]); extra names are ignored.
    pub fn from_tensors(tensors: &BTreeMap<String, NamedTensor>, device: &Device) -> Result<Self, ModelError> {
        let mut errors = Vec::new();
        let mut take = |name: &str, shape: &[usize]| -> Option<Tensor<1>> {
            let Some(t) = tensors.get(name) else {
                errors.push(format!("missing tensor {name} (shape {shape:?})"));
                return None;
            };
            if t.shape != shape || t.values.len() != shape.iter().product::<usize>() {
                errors.push(format!("tensor {name}: shape {:?} in file, expected {shape:?}", t.shape));
                return None;
            }
            Some(Tensor::from_data(TensorData::new(t.values.clone(), [t.values.len()]), device))
        };
        let mut features = Vec::with_capacity(VGG16_CONVS.len());
        for (i, c_in, c_out) in VGG16_CONVS {
            let weight = take(&format!("features.{i}.weight"), &[c_out, c_in, 3, 3]);
            let bias = take(&format!("features.{i}.bias"), &[c_out]);
            if let (Some(w), Some(b)) = (weight, bias) {
                let mut conv = Conv2dConfig::new([c_in, c_out], [3, 3])
                    .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                    .init(device);
                conv.weight = Param::from_tensor(w.reshape([c_out, c_in, 3, 3]));
                conv.bias = Some(Param::from_tensor(b));
                features.push(conv);
            }
        }
        let mut lin = Vec::with_capacity(LPIPS_CHANNELS.len());
        for (k, &c) in LPIPS_CHANNELS.iter().enumerate() {
            if let Some(w) = take(&format!("lin{k}.model.1.weight"), &[1, c, 1, 1]) {
                let mut conv = Conv2dConfig::new([c, 1], [1, 1]).with_bias(false).init(device);
                conv.weight = Param::from_tensor(w.reshape([1, c, 1, 1]));
                lin.push(conv);
            }
        }
        if !errors.is_empty() {
            let n = errors.len();
            errors.truncate(8);
            if n > errors.len() {
                errors.push(format!("and {} more", n - errors.len()));
            }
            return Err(ModelError::WeightsMismatch { problems: errors });
        }
        Ok(Self { features, lin }.freeze())
    }

    /// Checks that `a` and `b` fit [`Lpips::forward`] (same `[B, 3, H, W]`, `B >= 1`,
    /// `H, W >= 16`), then runs it.
    pub fn try_forward(&self, a: Tensor<4>, b: Tensor<4>) -> Result<Tensor<1>, ModelError> {
        let (da, db) = (a.dims(), b.dims());
        if da != db || da[0] == 0 || da[1] != 3 || da[2] < MIN_SIDE || da[3] < MIN_SIDE {
            return Err(ModelError::shape(
                "LPIPS's images",
                format!("two [B, 3, H, W] of one size with B >= 1 and H, W >= {MIN_SIDE}"),
                format!("{da:?} and {db:?}"),
            ));
        }
        Ok(self.forward(a, b))
    }

    /// LPIPS distance averaged over the batch: `[1]`. Inputs are RGB in `[-1, 1]`, `[B, 3, H, W]`
    /// of equal shape with `H, W >= 16`, on this module's device. Differentiable w.r.t. both inputs.
    pub fn forward(&self, a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
        self.forward_per_image(a, b).mean()
    }

    /// LPIPS distance of each image pair: `[B]` (what `lpips.LPIPS` returns, flattened).
    pub fn forward_per_image(&self, a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
        let [batch, _, _, _] = a.dims();
        // one trunk pass over both images
        let feats = self.vgg_features(scaling_layer(Tensor::cat(vec![a, b], 0)));
        let layers: Vec<Tensor<4>> = feats
            .into_iter()
            .zip(&self.lin)
            .map(|(f, lin)| {
                let [n, c, h, w] = f.dims();
                let f = unit_normalise(f);
                let (fa, fb) = (f.clone().slice([0..batch, 0..c, 0..h, 0..w]), f.slice([batch..n, 0..c, 0..h, 0..w]));
                lin.forward((fa - fb).square()).mean_dim(3).mean_dim(2) // [B, 1, 1, 1]
            })
            .collect();
        Tensor::cat(layers, 1).sum_dim(1).reshape([batch])
    }

    /// The five tapped VGG16 features (relu1_2 ... relu5_3) of a scaled image batch.
    fn vgg_features(&self, x: Tensor<4>) -> Vec<Tensor<4>> {
        let pool = MaxPool2dConfig::new([2, 2]).init();
        let mut convs = self.features.iter();
        let mut h = x;
        let mut out = Vec::with_capacity(STAGE_CONVS.len());
        for (stage, &n) in STAGE_CONVS.iter().enumerate() {
            if stage > 0 {
                h = pool.forward(h);
            }
            for conv in convs.by_ref().take(n) {
                h = relu(conv.forward(h));
            }
            out.push(h.clone());
        }
        out
    }
}

/// LPIPS scaling layer: `(x - shift) / scale` per RGB channel.
fn scaling_layer(x: Tensor<4>) -> Tensor<4> {
    let device = x.device();
    let shift = Tensor::<1>::from_floats(SHIFT, &device).reshape([1, 3, 1, 1]);
    let scale = Tensor::<1>::from_floats(SCALE, &device).reshape([1, 3, 1, 1]);
    (x - shift) / scale
}

/// `f / (||f||_channels + 1e-10)` with a gradient-safe norm (see the module docs).
fn unit_normalise(f: Tensor<4>) -> Tensor<4> {
    let norm = f.clone().square().sum_dim(1).add_scalar(1e-20).sqrt();
    f / norm.add_scalar(1e-10)
}
