//! Model configuration: architecture hyper-parameters, named presets and the depth coding.

use serde::{Deserialize, Serialize};

use crate::ModelError;

/// How planar depth is coded as one network channel (the SGAM authors' normalised disparity, or
/// alternatives).
///
/// `s = (1/(z + offset) - 1/far) / (1/near - 1/far)`, channel `c = 2 s - 1`. `near_m` and `far_m`
/// are in the offset space (i.e. compared with `z + offset`), as in the authors' code.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DepthCoding {
    /// Nearest depth (after adding `offset_m`), metres; maps to `c = +1`.
    pub near_m: f32,
    /// Farthest depth (after adding `offset_m`), metres; maps to `c = -1`.
    pub far_m: f32,
    /// Added to planar depth before inverting, metres (Google Earth: 10).
    pub offset_m: f32,
}

impl DepthCoding {
    /// CLEVR-Infinite: near 7 m, far 16 m, no offset.
    pub fn clevr() -> Self {
        Self { near_m: 7.0, far_m: 16.0, offset_m: 0.0 }
    }

    /// Google Earth: depth + 10, near 10.1, far 14.77.
    pub fn google_earth() -> Self {
        Self { near_m: 10.1, far_m: 14.77, offset_m: 10.0 }
    }
}

/// Largest channel count of any layer [`ModelConfig::validate`] accepts.
pub const MAX_CHANNELS: usize = 4096;
/// Largest codebook [`ModelConfig::validate`] accepts.
pub const MAX_CODEBOOK: usize = 65536;
/// Largest (approximate) parameter count [`ModelConfig::validate`] accepts: 300 million, 1.2 GB
/// of f32 weights (the paper preset has about 68 million).
pub const MAX_PARAMETERS: u64 = 300_000_000;

/// Architecture of the VQ autoencoder (taming-transformers VQGAN, generalised with a patch stem).
///
/// Layout of every tensor inside the model is `[B, C, H, W]`. The encoder maps an `H x W` image to
/// an `H / (patch_size * 2^(len(ch_mult)-1))` latent grid; the decoder mirrors it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    /// Preset name, informational (`paper`, `compact`, `custom`).
    pub name: String,
    /// Base channel count (`ch`).
    pub ch: usize,
    /// Channel multiplier per resolution level (`ch_mult`).
    pub ch_mult: Vec<usize>,
    /// Residual blocks per encoder level (the decoder uses one more, as taming does).
    pub num_res_blocks: usize,
    /// Feature-map sizes (in pixels, at the reference `resolution`) where attention is used.
    pub attn_resolutions: Vec<usize>,
    /// Reference input resolution used to decide where attention goes (256).
    pub resolution: usize,
    /// Patch stem: the encoder's `conv_in` is a `patch x patch` conv with stride `patch`, and the
    /// decoder's `conv_out` predicts `4 * patch^2` channels rearranged by pixel shuffle. `1` means
    /// the taming 3x3 `conv_in`/`conv_out`.
    pub patch_size: usize,
    /// GroupNorm group count (taming: 32). Must divide every channel count.
    pub norm_groups: usize,
    /// GroupNorm epsilon (taming: 1e-6).
    pub norm_eps: f64,
    /// Whether the mid blocks (at the latent resolution) use self-attention.
    pub mid_attn: bool,
    /// Encoder output / decoder input channels.
    pub z_channels: usize,
    /// Codebook vector size.
    pub embed_dim: usize,
    /// Number of codebook entries.
    pub n_embed: usize,
    /// Weight of the codebook term `||z_q - sg(z)||^2` (the commitment term has weight 1; the
    /// authors' effective weighting, see [`crate::quantize`]); 0.25.
    pub beta: f32,
    /// Depth coding of the disparity channel.
    pub depth: DepthCoding,
    /// Two extra input channels with each pixel's viewing ray, `2 (u - cx) / fx` and
    /// `2 (v - cy) / fy` (OpenCV pixel centres): a conv net cannot otherwise tell which image
    /// row it looks at, and the ground's depth is fixed by the row. Models trained before this
    /// option have 5 input channels (`false`).
    #[serde(default)]
    pub ray_channels: bool,
    /// Calibrated code temperature `tau` of a generative (cross-entropy trained) encoder: the
    /// model's distribution over codes in a latent cell is `softmax(-||z - e_k||^2 / tau)`, and
    /// sampling at temperature `T` uses `T * tau`. `None` for regression-trained encoders, whose
    /// distances are not a distribution.
    #[serde(default)]
    pub code_tau: Option<f32>,
    /// A learned code head: a 1x1 conv from the encoder's output to one logit per code, so the
    /// distribution over codes can be multimodal (ground *or* an object's edge). The paper's
    /// distance logits `-||z - e_k||^2 / tau` are linear in `z` with weights tied to the
    /// codebook and can only put mass on codes around one point; the head starts equal to them
    /// (see `generative::head_from_codebook`) and is trained free.
    #[serde(default)]
    pub code_head: bool,
    /// Scene-wide context: a transformer over the latent code grid that adds to the code head's
    /// logits in missing cells ([`crate::context`]); needs a code head. Models before it have
    /// none.
    #[serde(default)]
    pub context: Option<crate::context::ContextConfig>,
}

impl ModelConfig {
    /// The authors' taming VQGAN exactly (~68M parameters at codebook 16384): ch 128,
    /// ch_mult [1,1,2,2,4], 2 res blocks, attention at 16x16, z 256, embed 256, codebook 16384.
    pub fn paper() -> Self {
        Self {
            name: "paper".into(),
            ch: 128,
            ch_mult: vec![1, 1, 2, 2, 4],
            num_res_blocks: 2,
            attn_resolutions: vec![16],
            resolution: 256,
            patch_size: 1,
            norm_groups: 32,
            norm_eps: 1e-6,
            mid_attn: true,
            z_channels: 256,
            embed_dim: 256,
            n_embed: 16384,
            beta: 0.25,
            depth: DepthCoding::clevr(),
            ray_channels: false,
            code_tau: None,
            code_head: false,
            context: None,
        }
    }

    /// Our CPU design: a 4x4 stride-4 patch stem (256 -> 64x64), levels at 64/32 with 32/64
    /// channels, one residual block per encoder level, no attention anywhere, a 32x32 latent of
    /// 64-d codes from 1024 (downsampling 8: a 16x16 latent could not reconstruct the synthetic
    /// world's sharp edges at 30 dB), pixel-shuffle output head.
    pub fn compact() -> Self {
        Self {
            name: "compact".into(),
            ch: 32,
            ch_mult: vec![1, 2],
            num_res_blocks: 1,
            attn_resolutions: vec![],
            resolution: 256,
            patch_size: 4,
            norm_groups: 8,
            norm_eps: 1e-6,
            mid_attn: false,
            z_channels: 64,
            embed_dim: 64,
            n_embed: 1024,
            beta: 0.25,
            depth: DepthCoding::clevr(),
            ray_channels: false,
            code_tau: None,
            code_head: false,
            context: None,
        }
    }

    /// A very small model for tests (8/16 channels, 2 levels, 32-entry codebook).
    pub fn tiny() -> Self {
        Self {
            name: "tiny".into(),
            ch: 8,
            ch_mult: vec![1, 2],
            num_res_blocks: 1,
            attn_resolutions: vec![],
            resolution: 32,
            patch_size: 2,
            norm_groups: 4,
            norm_eps: 1e-6,
            mid_attn: true,
            z_channels: 16,
            embed_dim: 8,
            n_embed: 32,
            beta: 0.25,
            depth: DepthCoding::clevr(),
            ray_channels: false,
            code_tau: None,
            code_head: false,
            context: None,
        }
    }

    /// Input channels of the network: RGB, disparity, mask, and the two ray channels when
    /// [`Self::ray_channels`] is set.
    pub fn input_channels(&self) -> usize {
        if self.ray_channels {
            7
        } else {
            5
        }
    }

    /// Total downsampling factor from image to latent grid.
    pub fn downsample_factor(&self) -> usize {
        self.patch_size * (1usize << (self.ch_mult.len().saturating_sub(1)))
    }

    /// Rough parameter count (3x3 convs of the residual blocks, resampling and mid blocks; within
    /// a factor of about 1.5 of the real count), used to bound a configuration's memory before any
    /// tensor is allocated.
    pub fn approx_parameters(&self) -> u128 {
        // saturating: any configuration (even one validate would refuse) gives a number
        let mul = |a: u128, b: u128| a.saturating_mul(b);
        let nrb = self.num_res_blocks as u128;
        let convs = mul(2, nrb).saturating_add(mul(2, nrb.saturating_add(1))).saturating_add(2);
        let mut n: u128 = 0;
        for m in &self.ch_mult {
            let c = mul(self.ch as u128, *m as u128);
            // encoder: nrb blocks of 2 convs; decoder: nrb + 1 blocks of 2 convs; one resampling conv each
            n = n.saturating_add(mul(mul(9, mul(c, c)), convs));
        }
        let last = mul(self.ch as u128, self.ch_mult.last().copied().unwrap_or(1) as u128);
        n = n.saturating_add(mul(72, mul(last, last))); // mid blocks of encoder and decoder
        n = n.saturating_add(mul(2, mul(self.n_embed as u128, self.embed_dim as u128))); // codebook (+ code head)
        n.saturating_add(mul(18, mul(last, self.z_channels as u128)))
    }

    /// Checks the configuration is buildable (non-empty levels, group counts dividing channels)
    /// and within memory: every size has an upper bound ([`MAX_CHANNELS`], [`MAX_CODEBOOK`],
    /// [`MAX_PARAMETERS`], ...). Errors name the field and the accepted range.
    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |msg: String| Err(ModelError::config(&self.name, msg));
        if self.ch_mult.is_empty() || self.ch == 0 || self.patch_size == 0 {
            return bad("ch, ch_mult and patch_size must be non-zero".into());
        }
        if self.n_embed == 0 || self.embed_dim == 0 || self.z_channels == 0 {
            return bad("codebook and latent sizes must be non-zero".into());
        }
        let sizes = [
            ("ch", self.ch, MAX_CHANNELS),
            ("z_channels", self.z_channels, MAX_CHANNELS),
            ("embed_dim", self.embed_dim, MAX_CHANNELS),
            ("n_embed", self.n_embed, MAX_CODEBOOK),
            ("patch_size", self.patch_size, 64),
            ("num_res_blocks", self.num_res_blocks, 16),
            ("resolution", self.resolution, 8192),
            ("ch_mult levels", self.ch_mult.len(), 8),
            ("norm_groups", self.norm_groups, MAX_CHANNELS),
        ];
        for (name, value, max) in sizes {
            if value > max {
                return bad(format!("{name} {value} is out of range (at most {max})"));
            }
        }
        for m in &self.ch_mult {
            let c = self.ch.saturating_mul(*m);
            if *m == 0 || c > MAX_CHANNELS {
                return bad(format!("ch_mult {m} gives {c} channels (each level needs 1..={MAX_CHANNELS} channels)"));
            }
        }
        let params = self.approx_parameters();
        if params > MAX_PARAMETERS as u128 {
            return bad(format!(
                "about {params} parameters, beyond the {MAX_PARAMETERS} this build accepts (the paper preset has \
                 about 68 million)"
            ));
        }
        if !(self.norm_eps.is_finite() && self.norm_eps > 0.0 && self.norm_eps < 1.0) {
            return bad(format!("norm_eps {} must be in (0, 1)", self.norm_eps));
        }
        if !(self.beta.is_finite() && (0.0..=10.0).contains(&self.beta)) {
            return bad(format!("beta {} must be in 0..=10", self.beta));
        }
        for m in &self.ch_mult {
            let c = self.ch * m;
            if self.norm_groups == 0 || !c.is_multiple_of(self.norm_groups) {
                return bad(format!("norm_groups {} does not divide {c} channels", self.norm_groups));
            }
        }
        if let Some(c) = &self.context {
            if !self.code_head {
                return bad("a context transformer needs a code head (code_head: true)".into());
            }
            c.validate()?;
        }
        if let Some(tau) = self.code_tau {
            if !(tau.is_finite() && tau > 0.0) {
                return bad(format!("code_tau {tau} must be a positive number"));
            }
        }
        let d = &self.depth;
        if !(d.near_m.is_finite() && d.far_m.is_finite() && d.offset_m.is_finite())
            || d.near_m <= 0.0
            || d.far_m <= d.near_m
            || d.far_m > 1e6
        {
            return bad(format!("depth near {} / far {} invalid", self.depth.near_m, self.depth.far_m));
        }
        Ok(())
    }
}
