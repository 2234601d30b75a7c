//! Building blocks of the taming VQGAN: GroupNorm, residual block, attention, down/upsampling.
//!
//! Field names mirror the authors' PyTorch modules so state-dict keys line up
//! (`norm1`, `conv1`, `norm2`, `conv2`, `nin_shortcut`, `q`, `k`, `v`, `proj_out`, `conv`).

use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::tensor::activation::{silu, softmax};
use burn::tensor::ops::PadMode;
use burn::tensor::{Device, Tensor};

/// A `k x k` convolution `c_in -> c_out` with stride and symmetric zero padding.
pub(crate) fn conv(c_in: usize, c_out: usize, k: usize, stride: usize, pad: usize, device: &Device) -> Conv2d {
    Conv2dConfig::new([c_in, c_out], [k, k])
        .with_stride([stride, stride])
        .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
        .init(device)
}

/// Group normalisation with PyTorch parameter names (`weight`, `bias`), input `[B, C, H, W]`.
#[derive(Module, Debug)]
pub struct Norm {
    /// Per-channel scale `[C]`.
    pub weight: Param<Tensor<1>>,
    /// Per-channel shift `[C]`.
    pub bias: Param<Tensor<1>>,
    groups: usize,
    eps: f64,
}

impl Norm {
    pub(crate) fn new(channels: usize, groups: usize, eps: f64, device: &Device) -> Self {
        Self {
            weight: Param::from_tensor(Tensor::ones([channels], device)),
            bias: Param::from_tensor(Tensor::zeros([channels], device)),
            groups: groups.min(channels).max(1),
            eps,
        }
    }

    /// Groups of channels normalised together.
    pub(crate) fn groups(&self) -> usize {
        self.groups
    }

    /// The epsilon added to the variance.
    pub(crate) fn eps(&self) -> f64 {
        self.eps
    }

    /// Normalises over each group of channels and all pixels, then applies the affine map.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let [b, c, h, w] = x.dims();
        let g = self.groups;
        let grouped = x.reshape([b, g, (c / g) * h * w]);
        let mean = grouped.clone().mean_dim(2);
        let centred = grouped - mean;
        let var = centred.clone().square().mean_dim(2);
        let normed = (centred / var.add_scalar(self.eps).sqrt()).reshape([b, c, h, w]);
        normed * self.weight.val().reshape([1, c, 1, 1]) + self.bias.val().reshape([1, c, 1, 1])
    }
}

/// Residual block: norm1, swish, conv1 (3x3), norm2, swish, conv2 (3x3), plus a 1x1
/// `nin_shortcut` when the channel count changes.
#[derive(Module, Debug)]
pub struct ResnetBlock {
    /// First normalisation.
    pub norm1: Norm,
    /// First 3x3 convolution.
    pub conv1: Conv2d,
    /// Second normalisation.
    pub norm2: Norm,
    /// Second 3x3 convolution.
    pub conv2: Conv2d,
    /// 1x1 projection of the skip path when `c_in != c_out`.
    pub nin_shortcut: Option<Conv2d>,
}

impl ResnetBlock {
    pub(crate) fn new(c_in: usize, c_out: usize, groups: usize, eps: f64, device: &Device) -> Self {
        Self {
            norm1: Norm::new(c_in, groups, eps, device),
            conv1: conv(c_in, c_out, 3, 1, 1, device),
            norm2: Norm::new(c_out, groups, eps, device),
            conv2: conv(c_out, c_out, 3, 1, 1, device),
            nin_shortcut: (c_in != c_out).then(|| conv(c_in, c_out, 1, 1, 0, device)),
        }
    }

    /// `[B, c_in, H, W] -> [B, c_out, H, W]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let h = self.conv1.forward(silu(self.norm1.forward(x.clone())));
        let h = self.conv2.forward(silu(self.norm2.forward(h)));
        let skip = match &self.nin_shortcut {
            Some(proj) => proj.forward(x),
            None => x,
        };
        skip + h
    }
}

/// Single-head spatial self-attention with 1x1 `q`, `k`, `v` and `proj_out`.
#[derive(Module, Debug)]
pub struct AttnBlock {
    /// Normalisation before the projections.
    pub norm: Norm,
    /// Query projection.
    pub q: Conv2d,
    /// Key projection.
    pub k: Conv2d,
    /// Value projection.
    pub v: Conv2d,
    /// Output projection.
    pub proj_out: Conv2d,
}

impl AttnBlock {
    pub(crate) fn new(c: usize, groups: usize, eps: f64, device: &Device) -> Self {
        Self {
            norm: Norm::new(c, groups, eps, device),
            q: conv(c, c, 1, 1, 0, device),
            k: conv(c, c, 1, 1, 0, device),
            v: conv(c, c, 1, 1, 0, device),
            proj_out: conv(c, c, 1, 1, 0, device),
        }
    }

    /// `x + proj_out(softmax(q^T k / sqrt(C)) v)`, shape preserved.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let [b, c, h, w] = x.dims();
        let n = self.norm.forward(x.clone());
        let q = self.q.forward(n.clone()).reshape([b, c, h * w]).swap_dims(1, 2); // [B, HW, C]
        let k = self.k.forward(n.clone()).reshape([b, c, h * w]); // [B, C, HW]
        let v = self.v.forward(n).reshape([b, c, h * w]); // [B, C, HW]
        let attn = softmax(q.matmul(k).mul_scalar(1.0 / (c as f64).sqrt()), 2); // [B, HWq, HWk]
        let out = v.matmul(attn.swap_dims(1, 2)).reshape([b, c, h, w]);
        x + self.proj_out.forward(out)
    }
}

/// Downsampling: pad right/bottom by one, then a 3x3 stride-2 convolution (taming).
#[derive(Module, Debug)]
pub struct Downsample {
    /// The stride-2 convolution.
    pub conv: Conv2d,
}

impl Downsample {
    pub(crate) fn new(c: usize, device: &Device) -> Self {
        Self { conv: conv(c, c, 3, 2, 0, device) }
    }

    /// `[B, C, H, W] -> [B, C, H/2, W/2]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.conv.forward(x.pad((0, 1, 0, 1), PadMode::Constant(0.0)))
    }
}

/// Upsampling: nearest x2, then a 3x3 convolution (taming).
#[derive(Module, Debug)]
pub struct Upsample {
    /// The 3x3 convolution after nearest upsampling.
    pub conv: Conv2d,
}

impl Upsample {
    pub(crate) fn new(c: usize, device: &Device) -> Self {
        Self { conv: conv(c, c, 3, 1, 1, device) }
    }

    /// `[B, C, H, W] -> [B, C, 2H, 2W]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.conv.forward(nearest_up2(x))
    }
}

/// Nearest-neighbour x2 upsampling by broadcasting (differentiable everywhere).
pub(crate) fn nearest_up2(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    x.reshape([b, c, h, 1, w, 1]).expand([b, c, h, 2, w, 2]).reshape([b, c, 2 * h, 2 * w])
}

/// Pixel shuffle (depth to space), PyTorch channel order: `[B, C r^2, H, W] -> [B, C, H r, W r]`.
pub(crate) fn pixel_shuffle(x: Tensor<4>, r: usize) -> Tensor<4> {
    if r == 1 {
        return x;
    }
    let [b, crr, h, w] = x.dims();
    let c = crr / (r * r);
    x.reshape([b * c, r, r, h, w]).permute([0, 3, 1, 4, 2]).reshape([b, c, h * r, w * r])
}
