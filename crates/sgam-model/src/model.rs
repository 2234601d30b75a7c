//! The VQ autoencoder: mask fusion `conv_in` (5 -> 4), encoder, `quant_conv`, codebook
//! (`quantize.embedding.weight`), `post_quant_conv`, decoder. Parameter paths equal the authors'
//! Lightning state-dict keys for the `paper` preset; the mask fusion conv is the top-level
//! `conv_in` (SGAM's extra input conv).

use burn::module::{Module, Param};
use burn::nn::conv::Conv2d;
use burn::tensor::activation::silu;
use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::blocks::{conv, pixel_shuffle, AttnBlock, Downsample, Norm, ResnetBlock, Upsample};
use crate::config::ModelConfig;
use crate::context::CodeContext;
use crate::ModelError;

/// One encoder level: residual blocks, optional attention after each, optional downsample.
#[derive(Module, Debug)]
pub struct DownLevel {
    /// Residual blocks.
    pub block: Vec<ResnetBlock>,
    /// Attention blocks (empty where the level has none).
    pub attn: Vec<AttnBlock>,
    /// Stride-2 downsampling (absent on the last level).
    pub downsample: Option<Downsample>,
}

/// One decoder level: residual blocks, optional attention, optional upsample.
#[derive(Module, Debug)]
pub struct UpLevel {
    /// Residual blocks (`num_res_blocks + 1`).
    pub block: Vec<ResnetBlock>,
    /// Attention blocks (empty where the level has none).
    pub attn: Vec<AttnBlock>,
    /// Nearest x2 + conv upsampling (absent on level 0).
    pub upsample: Option<Upsample>,
}

/// The bottleneck: residual block, optional attention, residual block.
#[derive(Module, Debug)]
pub struct Mid {
    /// First residual block.
    pub block_1: ResnetBlock,
    /// Optional attention.
    pub attn_1: Option<AttnBlock>,
    /// Second residual block.
    pub block_2: ResnetBlock,
}

impl Mid {
    fn new(c: usize, cfg: &ModelConfig, device: &Device) -> Self {
        Self {
            block_1: ResnetBlock::new(c, c, cfg.norm_groups, cfg.norm_eps, device),
            attn_1: cfg.mid_attn.then(|| AttnBlock::new(c, cfg.norm_groups, cfg.norm_eps, device)),
            block_2: ResnetBlock::new(c, c, cfg.norm_groups, cfg.norm_eps, device),
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let mut h = self.block_1.forward(x);
        if let Some(attn) = &self.attn_1 {
            h = attn.forward(h);
        }
        self.block_2.forward(h)
    }
}

/// Image `[B, 4, H, W]` -> latent `[B, z_channels, H/f, W/f]`.
#[derive(Module, Debug)]
pub struct Encoder {
    /// Stem: 3x3 conv (paper) or `patch x patch` stride-`patch` conv (compact).
    pub conv_in: Conv2d,
    /// Levels, highest resolution first.
    pub down: Vec<DownLevel>,
    /// Bottleneck.
    pub mid: Mid,
    /// Final normalisation.
    pub norm_out: Norm,
    /// 3x3 conv to `z_channels`.
    pub conv_out: Conv2d,
}

impl Encoder {
    fn new(cfg: &ModelConfig, device: &Device) -> Self {
        let (g, eps) = (cfg.norm_groups, cfg.norm_eps);
        let conv_in = match cfg.patch_size {
            1 => conv(4, cfg.ch, 3, 1, 1, device),
            p => conv(4, cfg.ch, p, p, 0, device),
        };
        let mut down = Vec::new();
        let mut res = cfg.resolution / cfg.patch_size;
        let mut block_in = cfg.ch;
        for (i, m) in cfg.ch_mult.iter().enumerate() {
            let block_out = cfg.ch * m;
            let mut block = Vec::new();
            let mut attn = Vec::new();
            for _ in 0..cfg.num_res_blocks {
                block.push(ResnetBlock::new(block_in, block_out, g, eps, device));
                block_in = block_out;
                if cfg.attn_resolutions.contains(&res) {
                    attn.push(AttnBlock::new(block_in, g, eps, device));
                }
            }
            let last = i + 1 == cfg.ch_mult.len();
            let downsample = (!last).then(|| Downsample::new(block_in, device));
            if !last {
                res /= 2;
            }
            down.push(DownLevel { block, attn, downsample });
        }
        Self {
            conv_in,
            down,
            mid: Mid::new(block_in, cfg, device),
            norm_out: Norm::new(block_in, g, eps, device),
            conv_out: conv(block_in, cfg.z_channels, 3, 1, 1, device),
        }
    }

    /// `[B, 4, H, W] -> [B, z_channels, h, w]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let mut h = self.conv_in.forward(x);
        for level in &self.down {
            for (i, block) in level.block.iter().enumerate() {
                h = block.forward(h);
                if let Some(attn) = level.attn.get(i) {
                    h = attn.forward(h);
                }
            }
            if let Some(ds) = &level.downsample {
                h = ds.forward(h);
            }
        }
        let h = self.mid.forward(h);
        self.conv_out.forward(silu(self.norm_out.forward(h)))
    }
}

/// Latent `[B, z_channels, h, w]` -> image `[B, 4, H, W]` (pre-activation, the packed range).
#[derive(Module, Debug)]
pub struct Decoder {
    /// 3x3 conv from `z_channels`.
    pub conv_in: Conv2d,
    /// Bottleneck.
    pub mid: Mid,
    /// Levels indexed like the encoder's (`up.0` is the highest resolution), run in reverse.
    pub up: Vec<UpLevel>,
    /// Final normalisation.
    pub norm_out: Norm,
    /// Last layer: 3x3 conv to `4 * patch^2` channels (pixel-shuffled to 4 when `patch > 1`).
    pub conv_out: Conv2d,
    patch: usize,
}

impl Decoder {
    fn new(cfg: &ModelConfig, device: &Device) -> Self {
        let (g, eps) = (cfg.norm_groups, cfg.norm_eps);
        let levels = cfg.ch_mult.len();
        let mut block_in = cfg.ch * cfg.ch_mult[levels - 1];
        let mut res = cfg.resolution / cfg.downsample_factor();
        let conv_in = conv(cfg.z_channels, block_in, 3, 1, 1, device);
        let mid = Mid::new(block_in, cfg, device);
        let mut up_rev = Vec::new();
        for i in (0..levels).rev() {
            let block_out = cfg.ch * cfg.ch_mult[i];
            let mut block = Vec::new();
            let mut attn = Vec::new();
            for _ in 0..=cfg.num_res_blocks {
                block.push(ResnetBlock::new(block_in, block_out, g, eps, device));
                block_in = block_out;
                if cfg.attn_resolutions.contains(&res) {
                    attn.push(AttnBlock::new(block_in, g, eps, device));
                }
            }
            let upsample = (i != 0).then(|| Upsample::new(block_in, device));
            if i != 0 {
                res *= 2;
            }
            up_rev.push(UpLevel { block, attn, upsample });
        }
        up_rev.reverse();
        let p = cfg.patch_size;
        Self {
            conv_in,
            mid,
            up: up_rev,
            norm_out: Norm::new(block_in, g, eps, device),
            conv_out: conv(block_in, 4 * p * p, 3, 1, 1, device),
            patch: p,
        }
    }

    /// Everything up to (excluding) the last conv: `[B, z, h, w] -> [B, c, H/patch, W/patch]`.
    pub fn forward_features(&self, z: Tensor<4>) -> Tensor<4> {
        let mut h = self.mid.forward(self.conv_in.forward(z));
        for level in self.up.iter().rev() {
            for (i, block) in level.block.iter().enumerate() {
                h = block.forward(h);
                if let Some(attn) = level.attn.get(i) {
                    h = attn.forward(h);
                }
            }
            if let Some(us) = &level.upsample {
                h = us.forward(h);
            }
        }
        silu(self.norm_out.forward(h))
    }

    /// The last layer applied to [`Self::forward_features`]: `[B, c, .., ..] -> [B, 4, H, W]`.
    pub fn forward_head(&self, features: Tensor<4>) -> Tensor<4> {
        pixel_shuffle(self.conv_out.forward(features), self.patch)
    }

    /// `[B, z_channels, h, w] -> [B, 4, H, W]`.
    pub fn forward(&self, z: Tensor<4>) -> Tensor<4> {
        self.forward_head(self.forward_features(z))
    }
}

/// The codebook table, named like `nn.Embedding` (`embedding.weight`).
#[derive(Module, Debug)]
pub struct Embedding {
    /// Codebook rows `[n_embed, embed_dim]`.
    pub weight: Param<Tensor<2>>,
}

/// The vector quantizer's parameters (`quantize.embedding.weight`). Selection logic lives in
/// [`crate::quantize`].
#[derive(Module, Debug)]
pub struct Quantize {
    /// The codebook.
    pub embedding: Embedding,
}

impl Quantize {
    /// Codebook rows at `indices` (length `n`): `[n, embed_dim]`, differentiable w.r.t. the codebook.
    pub fn lookup(&self, indices: &[u32], device: &Device) -> Tensor<2> {
        let idx: Vec<i64> = indices.iter().map(|&i| i as i64).collect();
        let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [indices.len()]), device);
        self.embedding.weight.val().select(0, idx)
    }
}

/// The full generative sensing model. Input `[B, 5, H, W]` (RGB, disparity, mask; see
/// [`crate::packing`]), output `[B, 4, H, W]` in the packed range.
#[derive(Module, Debug)]
pub struct VqModel {
    /// Mask fusion, 1x1 conv 5 -> 4 (initialised to pass the 4 data channels through).
    pub conv_in: Conv2d,
    /// Encoder.
    pub encoder: Encoder,
    /// 1x1 conv `z_channels -> embed_dim`.
    pub quant_conv: Conv2d,
    /// Codebook.
    pub quantize: Quantize,
    /// 1x1 conv `embed_dim -> z_channels`.
    pub post_quant_conv: Conv2d,
    /// Decoder.
    pub decoder: Decoder,
    /// Learned code head (1x1 conv `z_channels -> n_embed`), present when
    /// [`ModelConfig::code_head`] is set.
    pub code_head: Option<Conv2d>,
    /// Scene-wide context over the code grid ([`crate::context`]), present when
    /// [`ModelConfig::context`] is set.
    pub context: Option<CodeContext>,
}

impl VqModel {
    /// Builds the model for `config` on `device` with deterministic weights drawn from `seed`
    /// (PyTorch default init: conv weights and biases U(±1/sqrt(fan_in)), norms 1/0, codebook
    /// U(±1/n_embed); mask fusion = identity on the data channels, zero on the mask).
    pub fn new(config: &ModelConfig, seed: u64, device: &Device) -> Result<Self, ModelError> {
        config.validate()?;
        let model = Self {
            conv_in: conv(config.input_channels(), 4, 1, 1, 0, device),
            encoder: Encoder::new(config, device),
            quant_conv: conv(config.z_channels, config.embed_dim, 1, 1, 0, device),
            quantize: Quantize {
                embedding: Embedding {
                    weight: Param::from_tensor(Tensor::zeros([config.n_embed, config.embed_dim], device)),
                },
            },
            post_quant_conv: conv(config.embed_dim, config.z_channels, 1, 1, 0, device),
            decoder: Decoder::new(config, device),
            code_head: config.code_head.then(|| conv(config.z_channels, config.n_embed, 1, 1, 0, device)),
            context: config
                .context
                .as_ref()
                .map(|c| CodeContext::new(c, config.z_channels, config.embed_dim, config.n_embed, device)),
        };
        let mut model = crate::params::init_params(model, seed);
        model.context = model.context.map(CodeContext::zero_output);
        Ok(model)
    }

    /// Mask fusion + encoder + quant_conv: `[B, 5, H, W] -> [B, embed_dim, h, w]` (pre-quantization).
    pub fn encode(&self, x: Tensor<4>) -> Tensor<4> {
        self.quant_conv.forward(self.encoder.forward(self.conv_in.forward(x)))
    }

    /// Code logits of the learned head: `[B, 5|7, H, W] -> [B, n_embed, h, w]`; `None` without
    /// a head.
    pub fn code_logits(&self, x: Tensor<4>) -> Option<Tensor<4>> {
        let head = self.code_head.as_ref()?;
        Some(head.forward(self.encoder.forward(self.conv_in.forward(x))))
    }

    /// Mask fusion + encoder (the code head's input): `[B, 5|7, H, W] -> [B, z_channels, h, w]`.
    pub fn features(&self, x: Tensor<4>) -> Tensor<4> {
        self.encoder.forward(self.conv_in.forward(x))
    }

    /// post_quant_conv + decoder: `[B, embed_dim, h, w] -> [B, 4, H, W]`.
    pub fn decode(&self, z_q: Tensor<4>) -> Tensor<4> {
        self.decoder.forward(self.post_quant_conv.forward(z_q))
    }

    /// Decoder up to its last layer (for the adaptive GAN weight): `[B, c, H/p, W/p]`.
    pub fn decode_features(&self, z_q: Tensor<4>) -> Tensor<4> {
        self.decoder.forward_features(self.post_quant_conv.forward(z_q))
    }
}

impl VqModel {
    /// Total number of scalar parameters.
    pub fn num_params_total(&self) -> usize {
        self.num_params()
    }
}
