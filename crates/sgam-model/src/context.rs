//! Scene-wide context for the sampler: a small bidirectional transformer over the latent code
//! grid that completes a hole knowing every cell of its window (MaskGIT's completion,
//! conditioned on the encoder's features of the guidance).
//!
//! The code head of the generative encoder ([`crate::generative`]) sees a few latent cells
//! around each cell: a cube spans 3-5 cells, and cells drawn independently, even in passes that
//! re-encode what earlier passes drew, do not know they are drawing one cube. Here each cell of
//! a window is a token:
//!
//! - its encoder feature (the head's own input: what the guidance shows there, with the mask),
//!   projected to `dim`;
//! - plus its *state*: observed, open (still to draw), or revealed (drawn in an earlier pass, or
//!   a target code during training), where a revealed cell also carries the codebook vector of
//!   its code (projected, so similar codes start alike).
//!
//! Each of `layers` pre-norm blocks adds a depthwise 3x3 convolution over the grid (relative
//! position, any window size), multi-head self-attention over all tokens of the window and an
//! MLP. The output adds to the code head's logits through a zero-initialised projection, so a
//! model with a fresh context equals the model without it.
//!
//! In generation ([`crate::refiner::VqRefiner`]) the encoder runs once; the transformer runs a
//! pass per share of the hole, each committing the most confident draws as revealed tokens; the
//! decoder runs once at the end.

use burn::module::{Module, Param};
use burn::tensor::activation::{gelu, softmax};
use burn::tensor::ops::PadMode;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::ModelError;

/// Architecture of the context transformer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContextConfig {
    /// Token width.
    pub dim: usize,
    /// Transformer blocks.
    pub layers: usize,
    /// Attention heads (divides `dim`).
    pub heads: usize,
    /// MLP hidden width as a multiple of `dim`.
    pub mlp_ratio: usize,
    /// Largest window side, latent cells, that one transformer call sees in generation (the
    /// training crops' side; a larger hole is covered by several windows in turn).
    pub window_cells: usize,
    /// Cells of context kept around a hole's cells inside a window.
    pub margin_cells: usize,
}

impl Default for ContextConfig {
    fn default() -> Self {
        Self { dim: 128, layers: 4, heads: 4, mlp_ratio: 2, window_cells: 16, margin_cells: 4 }
    }
}

impl ContextConfig {
    /// Checks the sizes (errors name the field).
    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |what: String| Err(ModelError::config("context", what));
        if self.dim == 0 || self.dim > 2048 {
            return bad(format!("dim {} must be in 1..=2048", self.dim));
        }
        if self.heads == 0 || !self.dim.is_multiple_of(self.heads) {
            return bad(format!("heads {} must divide dim {}", self.heads, self.dim));
        }
        if self.layers == 0 || self.layers > 64 {
            return bad(format!("layers {} must be in 1..=64", self.layers));
        }
        if self.mlp_ratio == 0 || self.mlp_ratio > 16 {
            return bad(format!("mlp_ratio {} must be in 1..=16", self.mlp_ratio));
        }
        if self.window_cells < 2 || self.window_cells > 256 {
            return bad(format!("window_cells {} must be in 2..=256", self.window_cells));
        }
        if self.margin_cells * 2 >= self.window_cells {
            return bad(format!(
                "margin_cells {} must be below half of window_cells {}",
                self.margin_cells, self.window_cells
            ));
        }
        Ok(())
    }
}

/// A cell's state as the transformer sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CellState {
    /// Seen in the guidance: its feature says what is there.
    Observed,
    /// Missing and not drawn yet: the transformer predicts its code.
    Open,
    /// Missing and already drawn (or, in training, given): carries its code.
    Revealed(u32),
}

impl CellState {
    fn kind(self) -> usize {
        match self {
            CellState::Observed => 0,
            CellState::Open => 1,
            CellState::Revealed(_) => 2,
        }
    }
}

/// A dense layer, PyTorch layout (`weight` `[out, in]`).
#[derive(Module, Debug)]
pub struct Dense {
    /// `[out, in]`.
    pub weight: Param<Tensor<2>>,
    /// `[out]`.
    pub bias: Param<Tensor<1>>,
}

impl Dense {
    fn new(c_in: usize, c_out: usize, device: &Device) -> Self {
        Self {
            weight: Param::from_tensor(Tensor::zeros([c_out, c_in], device)),
            bias: Param::from_tensor(Tensor::zeros([c_out], device)),
        }
    }

    /// `[n, in] -> [n, out]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let out = self.bias.val().dims()[0];
        x.matmul(self.weight.val().transpose()) + self.bias.val().reshape([1, out])
    }
}

/// Layer normalisation over the last dimension of `[n, c]` rows (PyTorch names).
#[derive(Module, Debug)]
pub struct RowNorm {
    /// Scale `[c]`.
    pub weight: Param<Tensor<1>>,
    /// Shift `[c]`.
    pub bias: Param<Tensor<1>>,
}

impl RowNorm {
    fn new(c: usize, device: &Device) -> Self {
        Self {
            weight: Param::from_tensor(Tensor::ones([c], device)),
            bias: Param::from_tensor(Tensor::zeros([c], device)),
        }
    }

    /// `[n, c] -> [n, c]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let [_, c] = x.dims();
        let mean = x.clone().mean_dim(1);
        let centred = x - mean;
        let var = centred.clone().square().mean_dim(1);
        centred / var.add_scalar(1e-5).sqrt() * self.weight.val().reshape([1, c]) + self.bias.val().reshape([1, c])
    }
}

/// Depthwise 3x3 convolution over the token grid (the blocks' relative position).
#[derive(Module, Debug)]
pub struct GridConv {
    /// Taps `[c, 3, 3]`.
    pub weight: Param<Tensor<3>>,
    /// `[c]`.
    pub bias: Param<Tensor<1>>,
}

impl GridConv {
    fn new(c: usize, device: &Device) -> Self {
        Self {
            weight: Param::from_tensor(Tensor::zeros([c, 3, 3], device)),
            bias: Param::from_tensor(Tensor::zeros([c], device)),
        }
    }

    /// Tokens `[b * h * w, c]` (row-major cells of `b` grids) -> the same shape.
    pub fn forward(&self, x: Tensor<2>, [b, h, w]: [usize; 3]) -> Tensor<2> {
        let [_, c] = x.dims();
        let grid = x.reshape([b, h, w, c]).permute([0, 3, 1, 2]);
        let padded = grid.pad((1, 1, 1, 1), PadMode::Constant(0.0));
        let taps = self.weight.val();
        let mut acc = self.bias.val().reshape([1, c, 1, 1]);
        for dy in 0..3 {
            for dx in 0..3 {
                let tap = taps.clone().slice([0..c, dy..dy + 1, dx..dx + 1]).reshape([1, c, 1, 1]);
                acc = padded.clone().slice([0..b, 0..c, dy..dy + h, dx..dx + w]) * tap + acc;
            }
        }
        acc.permute([0, 2, 3, 1]).reshape([b * h * w, c])
    }
}

/// One pre-norm transformer block with a positional convolution.
#[derive(Module, Debug)]
pub struct ContextBlock {
    /// Depthwise 3x3 over the grid.
    pub pos: GridConv,
    /// Norm before attention.
    pub norm1: RowNorm,
    /// Query, key and value projections, `[3 dim, dim]`.
    pub qkv: Dense,
    /// Attention output projection.
    pub proj: Dense,
    /// Norm before the MLP.
    pub norm2: RowNorm,
    /// MLP in.
    pub fc1: Dense,
    /// MLP out.
    pub fc2: Dense,
    heads: usize,
}

impl ContextBlock {
    fn new(cfg: &ContextConfig, device: &Device) -> Self {
        let d = cfg.dim;
        Self {
            pos: GridConv::new(d, device),
            norm1: RowNorm::new(d, device),
            qkv: Dense::new(d, 3 * d, device),
            proj: Dense::new(d, d, device),
            norm2: RowNorm::new(d, device),
            fc1: Dense::new(d, d * cfg.mlp_ratio, device),
            fc2: Dense::new(d * cfg.mlp_ratio, d, device),
            heads: cfg.heads,
        }
    }

    /// Tokens `[b * n, d]` of `b` windows of `h x w` cells -> the same shape.
    pub fn forward(&self, x: Tensor<2>, [b, h, w]: [usize; 3]) -> Tensor<2> {
        let [_, d] = x.dims();
        let n = h * w;
        let (heads, dh) = (self.heads, d / self.heads);
        let x = x.clone() + self.pos.forward(x, [b, h, w]);
        let qkv = self.qkv.forward(self.norm1.forward(x.clone())).reshape([b, n, 3 * d]);
        let split = |i: usize| qkv.clone().narrow(2, i * d, d).reshape([b, n, heads, dh]).swap_dims(1, 2);
        let (q, k, v) = (split(0), split(1), split(2));
        let scores = q.matmul(k.swap_dims(2, 3)).mul_scalar(1.0 / (dh as f64).sqrt());
        let att = softmax(scores, 3).matmul(v).swap_dims(1, 2).reshape([b * n, d]);
        let x = x + self.proj.forward(att);
        let hidden = gelu(self.fc1.forward(self.norm2.forward(x.clone())));
        x + self.fc2.forward(hidden)
    }
}

/// The context transformer (parameter paths under `context.` in a model file).
#[derive(Module, Debug)]
pub struct CodeContext {
    /// Encoder feature -> token.
    pub feature_in: Dense,
    /// Codebook vector of a revealed cell's code -> token.
    pub code_in: Dense,
    /// One learned vector per [`CellState`] kind (observed, open, revealed), `[3, dim]`.
    pub state: Param<Tensor<2>>,
    /// Transformer blocks.
    pub blocks: Vec<ContextBlock>,
    /// Final norm.
    pub norm_out: RowNorm,
    /// Token -> residual code logits (zero at initialisation).
    pub out: Dense,
}

/// Inputs of one [`CodeContext`] call: `b` windows of `h x w` cells.
#[derive(Debug, Clone)]
pub struct ContextInput {
    /// Encoder features `[b * h * w, z]`, row-major cells.
    pub features: Tensor<2>,
    /// One-hot state kinds `[b * h * w, 3]`.
    pub kinds: Tensor<2>,
    /// Codebook vectors of revealed cells, zero elsewhere, `[b * h * w, embed_dim]`.
    pub revealed: Tensor<2>,
    /// `[b, h, w]`.
    pub shape: [usize; 3],
}

impl ContextInput {
    /// Builds the state tensors from per-cell states; `codebook` is `[K, embed_dim]`.
    pub fn new(features: Tensor<2>, states: &[CellState], codebook: &Tensor<2>, shape: [usize; 3]) -> Self {
        let device = features.device();
        let n = states.len();
        let mut kinds = vec![0.0f32; n * 3];
        let mut picks = Vec::with_capacity(n);
        let mut keep = vec![0.0f32; n];
        for (i, s) in states.iter().enumerate() {
            kinds[i * 3 + s.kind()] = 1.0;
            match s {
                CellState::Revealed(c) => {
                    picks.push(*c as i64);
                    keep[i] = 1.0;
                }
                _ => picks.push(0),
            }
        }
        let kinds = Tensor::<2>::from_data(TensorData::new(kinds, [n, 3]), &device);
        let idx = Tensor::<1, burn::tensor::Int>::from_data(TensorData::new(picks, [n]), &device);
        let keep = Tensor::<2>::from_data(TensorData::new(keep, [n, 1]), &device);
        let revealed = codebook.clone().select(0, idx) * keep;
        Self { features, kinds, revealed, shape }
    }
}

impl CodeContext {
    /// A fresh context for a model with `z_channels` features, `embed_dim` codebook vectors and
    /// `n_embed` codes (weights zero until [`crate::params`] initialises them; the output
    /// projection is zeroed again by [`Self::zero_output`]).
    pub fn new(cfg: &ContextConfig, z_channels: usize, embed_dim: usize, n_embed: usize, device: &Device) -> Self {
        Self {
            feature_in: Dense::new(z_channels, cfg.dim, device),
            code_in: Dense::new(embed_dim, cfg.dim, device),
            state: Param::from_tensor(Tensor::zeros([3, cfg.dim], device)),
            blocks: (0..cfg.layers).map(|_| ContextBlock::new(cfg, device)).collect(),
            norm_out: RowNorm::new(cfg.dim, device),
            out: Dense::new(cfg.dim, n_embed, device),
        }
    }

    /// Zeroes the output projection: the context then adds nothing to the head's logits.
    pub fn zero_output(mut self) -> Self {
        let dev = self.out.weight.val().device();
        let [k, d] = self.out.weight.val().dims();
        self.out.weight = Param::from_tensor(Tensor::zeros([k, d], &dev));
        self.out.bias = Param::from_tensor(Tensor::zeros([k], &dev));
        self
    }

    /// Residual logits `[b * h * w, K]`.
    pub fn forward(&self, input: ContextInput) -> Tensor<2> {
        self.out.forward(self.tokens(input))
    }

    /// The normalised output tokens `[b * h * w, dim]` (before [`Self::out`]).
    pub fn tokens(&self, input: ContextInput) -> Tensor<2> {
        let mut x = self.feature_in.forward(input.features)
            + input.kinds.matmul(self.state.val())
            + self.code_in.forward(input.revealed);
        for block in &self.blocks {
            x = block.forward(x, input.shape);
        }
        self.norm_out.forward(x)
    }
}

/// Multiply-adds of one [`CodeContext::forward`] over `cells` tokens of windows of `window`
/// cells (`2 *` this = floating-point operations), for the benchmark's GFLOP figures.
pub fn multiply_adds(cfg: &ContextConfig, z: usize, embed: usize, k: usize, cells: usize, window: usize) -> u64 {
    let (d, n, w) = (cfg.dim as u64, cells as u64, window as u64);
    let per_block = n * (3 * d * d + d * d + 2 * d * d * cfg.mlp_ratio as u64 + 9 * d) + 2 * n * w * d;
    n * (z as u64 + embed as u64 + 3) * d + cfg.layers as u64 * per_block + n * d * k as u64
}
