//! Training the scene-wide context ([`crate::context`]) MaskGIT-style on cached encoder features.
//!
//! Everything but the context transformer is frozen: the generative encoder, its code head,
//! the codebook and the decoder. So each training pair's encoder features are computed once
//! ([`context_pairs`]) and training runs at the transformer's speed. Each step, every pair's
//! missing cells are split at random into *revealed* ones (given their target code, as earlier
//! passes of generation give the cells they committed) and *open* ones (to predict). The
//! revealed share follows MaskGIT's cosine schedule (`1 - cos(pi u / 2)`, `u` uniform), and a
//! share [`ContextTrainConfig::whole_hole`] of the pairs reveals nothing (the first pass, which
//! decides the most). The loss is the soft-target cross-entropy of the generative stage 2 (credit
//! spread over codes within a codebook spacing of the target) over the open cells; logits are
//! the frozen head's plus the context's residual, which starts at zero.
//!
//! Checkpoints are one folder, `RUN/ckpt`, committed by [`crate::checkpoint::commit_folder`]
//! (CRC manifest): `model.safetensors` (the whole model with its context, loadable by
//! [`crate::refiner::load_model`] and exportable by `sgam train export`), `optim.bpk`,
//! `state.json`.

use std::collections::BTreeMap;
use std::path::Path;

use burn::module::Module;
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::activation::{log_softmax, softmax};
use burn::tensor::{Device, Int, Tensor, TensorData};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sgam_core::{Intrinsics, RgbdFrame};

use crate::checkpoint::{commit_folder, committed_folder, verify_folder};
use crate::config::ModelConfig;
use crate::context::{CellState, CodeContext, ContextInput};
use crate::generative::{codebook_spacing, CodePair};
use crate::model::VqModel;
use crate::nhwc::train::{HostBatch, HostContext};
use crate::packing::{missing_cells, pack_input};
use crate::params::{load_named, named_tensors, to_safetensors_bytes, write_atomic, NamedTensor, WeightPrecision};
use crate::quantize::{squared_distances, to_host};
use crate::ModelError;

/// One training example: the frozen encoder's features of a guidance crop and its targets.
#[derive(Debug, Clone)]
pub struct ContextPair {
    /// Features `[h * w, z]`, row-major cells.
    pub features: Vec<f32>,
    /// Target code per cell.
    pub codes: Vec<u32>,
    /// Missing cells (the refiner's rule: more than the threshold of their pixels missing).
    pub missing: Vec<bool>,
    /// Latent rows and columns.
    pub shape: [usize; 2],
}

/// Encoder features of `pairs` under `model` (frozen), `batch` crops per call; pairs without a
/// missing cell are dropped (nothing to learn from them).
pub fn context_pairs(
    model: &VqModel,
    config: &ModelConfig,
    pairs: &[CodePair],
    missing_cell_threshold: f32,
    batch: usize,
    progress: &mut dyn FnMut(usize),
) -> Result<Vec<ContextPair>, ModelError> {
    let device = crate::default_device();
    let f = config.downsample_factor();
    let mut out = Vec::with_capacity(pairs.len());
    let mut done = 0;
    for chunk in pairs.chunks(batch.max(1)) {
        // pairs of one call must share a size
        let mut groups: BTreeMap<(u32, u32), Vec<&CodePair>> = BTreeMap::new();
        for p in chunk {
            groups.entry((p.input.width(), p.input.height())).or_default().push(p);
        }
        for ((w, h), group) in groups {
            let (w, h) = (w as usize, h as usize);
            if !w.is_multiple_of(f) || !h.is_multiple_of(f) {
                return Err(ModelError::shape(
                    "a pair's size",
                    format!("a multiple of {f} pixels"),
                    format!("{w}x{h}"),
                ));
            }
            let frames: Vec<&RgbdFrame> = group.iter().map(|p| &p.input).collect();
            let masks: Vec<Option<&[bool]>> = group.iter().map(|p| Some(p.missing.as_slice())).collect();
            let intr: Vec<Intrinsics> = group.iter().map(|p| p.intrinsics).collect();
            let x = pack_input(&frames, &masks, &intr, config, &device)?;
            let feats = model.features(x);
            let [b, z, zh, zw] = feats.dims();
            let host = to_host(feats.permute([0, 2, 3, 1]))?;
            for (i, p) in group.iter().enumerate() {
                if p.codes.len() != zh * zw {
                    return Err(ModelError::shape(
                        "a pair's target codes",
                        format!("{} for {w}x{h} pixels", zh * zw),
                        p.codes.len(),
                    ));
                }
                let missing = missing_cells(&p.missing, w, h, f, missing_cell_threshold);
                if missing.iter().any(|m| *m) {
                    out.push(ContextPair {
                        features: host[i * zh * zw * z..(i + 1) * zh * zw * z].to_vec(),
                        codes: p.codes.clone(),
                        missing,
                        shape: [zh, zw],
                    });
                }
            }
            debug_assert_eq!(b, group.len());
        }
        done += chunk.len();
        progress(done);
    }
    Ok(out)
}

/// Hyper-parameters of the context training (stored in every checkpoint).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContextTrainConfig {
    /// Total optimisation steps.
    pub steps: u64,
    /// Pairs per step.
    pub batch: usize,
    /// Adam learning rate.
    pub lr: f64,
    /// Half-cosine decay from `lr` between this step and `steps` (None: constant).
    pub lr_decay_from: Option<u64>,
    /// Linear warm-up of the learning rate over this many steps.
    pub warmup: u64,
    /// Share of the pairs whose hole is shown whole (nothing revealed).
    pub whole_hole: f32,
    /// Soft targets' width in codebook spacings (0 = one-hot).
    pub target_smoothing: f32,
    /// Checkpoint every N steps.
    pub ckpt_every: u64,
    /// RNG seed (batch order, reveals).
    pub seed: u64,
}

impl Default for ContextTrainConfig {
    fn default() -> Self {
        Self {
            steps: 20_000,
            batch: 16,
            lr: 5e-4,
            lr_decay_from: None,
            warmup: 200,
            whole_hole: 0.3,
            target_smoothing: 1.0,
            ckpt_every: 250,
            seed: 0,
        }
    }
}

impl ContextTrainConfig {
    /// Learning rate of the step after `step` steps (warm-up, then the crate's half cosine).
    pub fn lr_at(&self, step: u64) -> f64 {
        let base = crate::train::half_cosine_lr(self.lr, self.steps, self.lr_decay_from, step);
        if step < self.warmup {
            base * (step + 1) as f64 / self.warmup as f64
        } else {
            base
        }
    }
}

/// Figures of one step or evaluation (open cells only).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ContextReport {
    /// Completed steps.
    pub step: u64,
    /// Cross-entropy (nats) of the exact target code over open cells.
    pub ce: f32,
    /// Top-1 accuracy over open cells.
    pub acc: f32,
    /// Open cells counted.
    pub open_cells: usize,
    /// The same for the frozen head alone (what the context improves on).
    pub ce_head: f32,
}

#[derive(Debug, Serialize, Deserialize)]
struct ContextState {
    version: u32,
    model_config: ModelConfig,
    train_config: ContextTrainConfig,
    step: u64,
    rng_seed: [u8; 32],
    rng_stream: u64,
    rng_word_pos: u128,
    /// Adam steps behind the kernels' moments (`optim.safetensors`); absent in burn's.
    #[serde(default)]
    adam_steps: Option<u64>,
}

const STATE_VERSION: u32 = 1;

/// The kernels' Adam moments in a checkpoint folder.
const OPTIM_MOMENTS: &str = "optim.safetensors";

/// A context training session.
pub struct ContextTrainer {
    /// Architecture (with its context).
    pub model_config: ModelConfig,
    /// Hyper-parameters.
    pub train_config: ContextTrainConfig,
    /// The trained part, and what trains it.
    engine: Engine,
    /// Frozen weights of everything else (saved with the context).
    base: BTreeMap<String, NamedTensor>,
    head_weight: Vec<f32>,
    head_bias: Vec<f32>,
    codebook: Vec<f32>,
    spacing: f32,
    /// Completed steps.
    pub step: u64,
    /// Batch and reveal RNG.
    pub rng: ChaCha8Rng,
    device: Device,
}

impl std::fmt::Debug for ContextTrainer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ContextTrainer")
            .field("step", &self.step)
            .field("config", &self.train_config)
            .field("engine", &self.engine())
            .finish()
    }
}

/// What computes a context training step's gradients.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ContextEngine {
    /// The model's own CPU kernels, gradients written out by hand ([`crate::nhwc`]; about 2.5x
    /// burn's autodiff on this project's 2-core machine). The default of CPU builds.
    #[cfg_attr(not(feature = "wgpu"), default)]
    Kernels,
    /// burn's autodiff on the crate's default device (the GPU in a `wgpu` build).
    #[cfg_attr(feature = "wgpu", default)]
    Burn,
}

// one trainer per process: the variants' sizes do not matter
#[allow(clippy::large_enum_variant)]
enum Engine {
    Burn { context: CodeContext, optim: ModuleOptimizer },
    Kernels(Box<HostContext>),
}

fn adam() -> ModuleOptimizer {
    crate::train::adam_with(0.9, 0.98)
}

/// Random states of one pair's cells: observed stay observed; missing cells are revealed (with
/// their target code) or open, at least one open.
pub fn draw_states(pair: &ContextPair, whole_hole: f32, rng: &mut ChaCha8Rng) -> Vec<CellState> {
    let mut missing: Vec<usize> = (0..pair.missing.len()).filter(|&i| pair.missing[i]).collect();
    let n_reveal = if rng.random::<f32>() < whole_hole {
        0
    } else {
        let u: f32 = rng.random();
        (((1.0 - (std::f32::consts::FRAC_PI_2 * u).cos()) * missing.len() as f32) as usize)
            .min(missing.len().saturating_sub(1))
    };
    let mut states: Vec<CellState> =
        pair.missing.iter().map(|&m| if m { CellState::Open } else { CellState::Observed }).collect();
    missing.shuffle(rng);
    for &i in missing.iter().take(n_reveal) {
        states[i] = CellState::Revealed(pair.codes[i]);
    }
    states
}

/// Soft targets `[m, K]` around `targets`: a softmax of minus the squared codebook distances
/// over `width` (the smoothing in codebook spacings times the spacing).
fn soft_targets(codebook: &[f32], [k, e]: [usize; 2], width: f32, targets: &[u32], dev: &Device) -> Tensor<2> {
    let codebook = Tensor::<2>::from_data(TensorData::new(codebook.to_vec(), [k, e]), dev);
    let idx = Tensor::<1, Int>::from_data(
        TensorData::new(targets.iter().map(|&c| c as i64).collect::<Vec<_>>(), [targets.len()]),
        dev,
    );
    let rows = codebook.clone().select(0, idx);
    softmax(squared_distances(rows, codebook).neg().mul_scalar(1.0 / width), 1)
}

/// A batch for the kernels: features, states and target codes of every cell, and `[b, h, w]`.
#[allow(clippy::type_complexity)]
fn host_batch(
    batch: &[&ContextPair],
    states: &[Vec<CellState>],
) -> Result<(Vec<f32>, Vec<CellState>, Vec<u32>, [usize; 3]), ModelError> {
    let [h, w] = batch.first().map(|p| p.shape).ok_or(ModelError::EmptyBatch("context batch"))?;
    if batch.iter().any(|p| p.shape != [h, w] || p.codes.len() != h * w) {
        return Err(ModelError::shape(
            "the pairs of one batch",
            format!("{h}x{w} cells each"),
            "pairs of several sizes",
        ));
    }
    let features = batch.iter().flat_map(|p| p.features.iter().copied()).collect();
    let states = states.iter().flatten().copied().collect();
    let codes = batch.iter().flat_map(|p| p.codes.iter().copied()).collect();
    Ok((features, states, codes, [batch.len(), h, w]))
}

impl ContextTrainer {
    /// A new session: `init` holds a generative model with a code head (its context, when
    /// present, warm-starts this one; else the context starts fresh, adding nothing);
    /// `model_config` is `init`'s config with the context to train.
    pub fn new(
        model_config: &ModelConfig,
        init: &BTreeMap<String, NamedTensor>,
        train_config: &ContextTrainConfig,
    ) -> Result<Self, ModelError> {
        Self::new_on(model_config, init, train_config, ContextEngine::default())
    }

    /// [`Self::new`] with the gradients computed by `engine`.
    pub fn new_on(
        model_config: &ModelConfig,
        init: &BTreeMap<String, NamedTensor>,
        train_config: &ContextTrainConfig,
        engine: ContextEngine,
    ) -> Result<Self, ModelError> {
        if model_config.context.is_none() || !model_config.code_head {
            return Err(ModelError::MissingPart { part: "a code head and a context", operation: "context training" });
        }
        let device = crate::default_device();
        let fresh = VqModel::new(model_config, train_config.seed, &device)?;
        let has_context = init.keys().any(|k| k.starts_with("context."));
        if !has_context {
            // a fresh context: everything else must come from `init`
            if let Some(name) =
                named_tensors(&fresh).keys().find(|k| !k.starts_with("context.") && !init.contains_key(*k))
            {
                return Err(ModelError::MissingTensor(name.clone()));
            }
        }
        let model = load_named(fresh, init, !has_context, false)?;
        let base: BTreeMap<String, NamedTensor> =
            named_tensors(&model).into_iter().filter(|(k, _)| !k.starts_with("context.")).collect();
        let get = |name: &str| {
            base.get(name).map(|t| t.values.clone()).ok_or_else(|| ModelError::MissingTensor(name.to_string()))
        };
        let (head_weight, head_bias, codebook) =
            (get("code_head.weight")?, get("code_head.bias")?, get("quantize.embedding.weight")?);
        let spacing = codebook_spacing(&model)?;
        let context =
            model.context.ok_or(ModelError::MissingPart { part: "a context", operation: "context training" })?;
        let engine = match engine {
            ContextEngine::Burn => Engine::Burn { context: context.train(), optim: adam() },
            ContextEngine::Kernels => {
                let cfg = model_config
                    .context
                    .as_ref()
                    .ok_or(ModelError::MissingPart { part: "a context", operation: "context training" })?;
                Engine::Kernels(Box::new(HostContext::new(
                    cfg,
                    &named_tensors(&context),
                    head_weight.clone(),
                    head_bias.clone(),
                    codebook.clone(),
                    model_config.z_channels,
                    train_config.target_smoothing,
                    spacing,
                )?))
            }
        };
        Ok(Self {
            model_config: model_config.clone(),
            train_config: train_config.clone(),
            engine,
            base,
            head_weight,
            head_bias,
            codebook,
            spacing,
            step: 0,
            rng: ChaCha8Rng::seed_from_u64(train_config.seed),
            device,
        })
    }

    /// Head and total log-probabilities of the open cells `[m, K]`, and their targets.
    fn forward_with(
        config: &ModelConfig,
        (head_weight, head_bias, codebook): (&[f32], &[f32], &[f32]),
        context: &CodeContext,
        batch: &[&ContextPair],
        states: &[Vec<CellState>],
        dev: &Device,
    ) -> Result<(Tensor<2>, Tensor<2>, Vec<u32>), ModelError> {
        let constant = |values: &[f32], shape: [usize; 2], dev: &Device| -> Tensor<2> {
            Tensor::from_data(TensorData::new(values.to_vec(), shape), dev)
        };
        let (k, z, e) = (config.n_embed, config.z_channels, config.embed_dim);
        let [h, w] = batch[0].shape;
        if batch.iter().any(|p| p.shape != [h, w]) {
            return Err(ModelError::shape(
                "the pairs of one batch",
                format!("{h}x{w} cells each"),
                "pairs of several sizes",
            ));
        }
        let n = batch.len() * h * w;
        let feats: Vec<f32> = batch.iter().flat_map(|p| p.features.iter().copied()).collect();
        if feats.len() != n * z {
            return Err(ModelError::shape(
                "the batch's features",
                format!("{n} cells x {z} channels"),
                format!("{} values", feats.len()),
            ));
        }
        let feats = constant(&feats, [n, z], dev);
        let all_states: Vec<CellState> = states.iter().flatten().copied().collect();
        let codebook = constant(codebook, [k, e], dev);
        let input = ContextInput::new(feats.clone(), &all_states, &codebook, [batch.len(), h, w]);
        let open: Vec<usize> = (0..n).filter(|&i| all_states[i] == CellState::Open).collect();
        let targets: Vec<u32> = open.iter().map(|&i| batch[i / (h * w)].codes[i % (h * w)]).collect();
        let idx = Tensor::<1, Int>::from_data(
            TensorData::new(open.iter().map(|&i| i as i64).collect::<Vec<_>>(), [open.len()]),
            dev,
        );
        let head_w = constant(head_weight, [k, z], dev);
        let head_b = constant(head_bias, [1, k], dev);
        let head = feats.select(0, idx.clone()).matmul(head_w.transpose()) + head_b;
        let residual = context.out.forward(context.tokens(input).select(0, idx));
        let total = log_softmax(head.clone() + residual, 1);
        Ok((log_softmax(head, 1), total, targets))
    }

    fn report(head: &[f32], total: &[f32], targets: &[u32], k: usize) -> ContextReport {
        let mut r = ContextReport { open_cells: targets.len(), ..ContextReport::default() };
        for (i, &t) in targets.iter().enumerate() {
            let row = &total[i * k..(i + 1) * k];
            r.ce -= row[t as usize];
            r.ce_head -= head[i * k + t as usize];
            let best = (0..k).fold(0, |b, j| if row[j] > row[b] { j } else { b });
            r.acc += (best == t as usize) as u8 as f32;
        }
        let m = targets.len().max(1) as f32;
        r.ce /= m;
        r.ce_head /= m;
        r.acc /= m;
        r
    }

    /// What computes this trainer's gradients.
    pub fn engine(&self) -> ContextEngine {
        match self.engine {
            Engine::Burn { .. } => ContextEngine::Burn,
            Engine::Kernels(_) => ContextEngine::Kernels,
        }
    }

    /// One optimisation step on `batch` (pairs of one size).
    pub fn step_on(&mut self, batch: &[&ContextPair]) -> Result<ContextReport, ModelError> {
        if batch.is_empty() {
            return Err(ModelError::EmptyBatch("context training step"));
        }
        let whole = self.train_config.whole_hole;
        let states: Vec<Vec<CellState>> = batch.iter().map(|p| draw_states(p, whole, &mut self.rng)).collect();
        let lr = self.train_config.lr_at(self.step);
        let mut r = match &mut self.engine {
            Engine::Kernels(host) => {
                let (features, states, targets, shape) = host_batch(batch, &states)?;
                let r =
                    host.train_step(&HostBatch { features: &features, states: &states, targets: &targets, shape }, lr)?;
                if !r.loss.is_finite() {
                    return Err(ModelError::Diverged { loss: r.loss, step: self.step + 1 });
                }
                ContextReport { step: 0, ce: r.ce, acc: r.acc, open_cells: r.open, ce_head: r.ce_head }
            }
            Engine::Burn { context, optim } => {
                let dev = self.device.clone().autodiff();
                let (head, total, targets) = Self::forward_with(
                    &self.model_config,
                    (&self.head_weight, &self.head_bias, &self.codebook),
                    context,
                    batch,
                    &states,
                    &dev,
                )?;
                let loss = if self.train_config.target_smoothing > 0.0 {
                    (soft_targets(
                        &self.codebook,
                        [self.model_config.n_embed, self.model_config.embed_dim],
                        self.train_config.target_smoothing.max(1e-6) * self.spacing,
                        &targets,
                        &dev,
                    ) * total.clone())
                    .sum_dim(1)
                    .mean()
                    .neg()
                } else {
                    let idx = Tensor::<2, Int>::from_data(
                        TensorData::new(targets.iter().map(|&c| c as i64).collect::<Vec<_>>(), [targets.len(), 1]),
                        &dev,
                    );
                    total.clone().gather(1, idx).mean().neg()
                };
                let loss_value = to_host(loss.clone().detach())?.first().copied().unwrap_or(f32::NAN);
                if !loss_value.is_finite() {
                    return Err(ModelError::Diverged { loss: loss_value, step: self.step + 1 });
                }
                let mut grads = loss.backward();
                let g = GradientsParams::from_module(&mut grads, &*context);
                *context = optim.step(lr, context.clone(), g);
                let k = self.model_config.n_embed;
                Self::report(&to_host(head.detach())?, &to_host(total.detach())?, &targets, k)
            }
        };
        self.step += 1;
        r.step = self.step;
        Ok(r)
    }

    /// Cross-entropy on held-out pairs with a fixed draw of states (`whole_hole` = 1: nothing
    /// revealed, the first pass; 0: MaskGIT's reveal schedule).
    pub fn evaluate(&self, pairs: &[ContextPair], whole_hole: f32, batch: usize) -> Result<ContextReport, ModelError> {
        let mut rng = ChaCha8Rng::seed_from_u64(0x0c0_7e47);
        let k = self.model_config.n_embed;
        let (mut head, mut total, mut targets) = (Vec::new(), Vec::new(), Vec::new());
        let mut sums = ContextReport::default();
        let mut by_size: BTreeMap<[usize; 2], Vec<&ContextPair>> = BTreeMap::new();
        for p in pairs {
            by_size.entry(p.shape).or_default().push(p);
        }
        let burn = match &self.engine {
            Engine::Burn { context, .. } => Some(context.valid()),
            Engine::Kernels(_) => None,
        };
        for group in by_size.values() {
            for chunk in group.chunks(batch.max(1)) {
                let states: Vec<Vec<CellState>> = chunk.iter().map(|p| draw_states(p, whole_hole, &mut rng)).collect();
                match (&self.engine, &burn) {
                    (Engine::Kernels(host), _) => {
                        let (features, states, codes, shape) = host_batch(chunk, &states)?;
                        let r = host.forward_only(&HostBatch {
                            features: &features,
                            states: &states,
                            targets: &codes,
                            shape,
                        })?;
                        let m = r.open as f32;
                        sums.ce += r.ce * m;
                        sums.ce_head += r.ce_head * m;
                        sums.acc += r.acc * m;
                        sums.open_cells += r.open;
                    }
                    (Engine::Burn { .. }, Some(context)) => {
                        let (h, t, c) = Self::forward_with(
                            &self.model_config,
                            (&self.head_weight, &self.head_bias, &self.codebook),
                            context,
                            chunk,
                            &states,
                            &self.device,
                        )?;
                        head.extend(to_host(h)?);
                        total.extend(to_host(t)?);
                        targets.extend(c);
                    }
                    (Engine::Burn { .. }, None) => unreachable!("burn's context is taken above"),
                }
            }
        }
        let mut r = if burn.is_some() {
            Self::report(&head, &total, &targets, k)
        } else {
            let m = sums.open_cells.max(1) as f32;
            ContextReport { ce: sums.ce / m, ce_head: sums.ce_head / m, acc: sums.acc / m, ..sums }
        };
        r.step = self.step;
        Ok(r)
    }

    /// The whole model's weights: the frozen parts and the current context.
    pub fn weights(&self) -> BTreeMap<String, NamedTensor> {
        let mut all = self.base.clone();
        let context = match &self.engine {
            Engine::Burn { context, .. } => named_tensors(&context.valid()),
            Engine::Kernels(host) => host.named(),
        };
        for (name, t) in context {
            all.insert(format!("context.{name}"), t);
        }
        all
    }

    /// Commits `run_dir/ckpt` (weights, optimizer, state) atomically. The optimizer's state is
    /// `optim.bpk` (burn's record) or `optim.safetensors` (the kernels' Adam moments).
    pub fn save(&self, run_dir: &Path) -> Result<(), ModelError> {
        let weights = self.weights();
        let meta = crate::refiner::weight_metadata(&self.model_config)?;
        let bytes = to_safetensors_bytes(&weights, WeightPrecision::F32, Some(meta))?;
        let (optim_name, optim, adam_steps) = match &self.engine {
            Engine::Burn { optim, .. } => {
                ("optim.bpk", optim.into_bytes().map_err(|e| ModelError::state("optimizer", e))?.to_vec(), None)
            }
            Engine::Kernels(host) => (
                OPTIM_MOMENTS,
                to_safetensors_bytes(&host.moments(), WeightPrecision::F32, None)?,
                Some(host.adam_steps),
            ),
        };
        let (rng_seed, rng_stream, rng_word_pos) = crate::checkpoint::rng_position(&self.rng);
        let state = ContextState {
            version: STATE_VERSION,
            model_config: self.model_config.clone(),
            train_config: self.train_config.clone(),
            step: self.step,
            rng_seed,
            rng_stream,
            rng_word_pos,
            adam_steps,
        };
        let json = serde_json::to_vec_pretty(&state).map_err(|e| ModelError::state("state", e))?;
        commit_folder(run_dir, "ckpt", |dir| {
            write_atomic(&dir.join("model.safetensors"), &bytes)?;
            write_atomic(&dir.join(optim_name), &optim)?;
            write_atomic(&dir.join("state.json"), &json)
        })?;
        Ok(())
    }

    /// Whether `run_dir` holds a committed checkpoint.
    pub fn has_checkpoint(run_dir: &Path) -> bool {
        committed_folder(run_dir, "ckpt").is_some()
    }

    /// Resumes from `run_dir`'s checkpoint (manifest verified); `steps` and `lr_decay_from`
    /// override the stored values when given.
    pub fn resume(run_dir: &Path, steps: Option<u64>, lr_decay_from: Option<u64>) -> Result<Self, ModelError> {
        Self::resume_on(run_dir, steps, lr_decay_from, ContextEngine::default())
    }

    /// [`Self::resume`] with the gradients computed by `engine`. A checkpoint written by the
    /// other engine resumes its weights, step and batch order with a fresh optimizer (the two
    /// keep Adam's moments in different files).
    pub fn resume_on(
        run_dir: &Path,
        steps: Option<u64>,
        lr_decay_from: Option<u64>,
        engine: ContextEngine,
    ) -> Result<Self, ModelError> {
        let dir = committed_folder(run_dir, "ckpt")
            .ok_or_else(|| ModelError::checkpoint(run_dir, "no committed checkpoint (ckpt/ with a manifest)"))?;
        verify_folder(&dir)?;
        let (state, tensors): (ContextState, _) =
            crate::checkpoint::read_trainer_state(&dir, "context training", STATE_VERSION)?;
        let mut train_config = state.train_config;
        if let Some(s) = steps {
            train_config.steps = s;
        }
        if lr_decay_from.is_some() {
            train_config.lr_decay_from = lr_decay_from;
        }
        let mut t = Self::new_on(&state.model_config, &tensors, &train_config, engine)?;
        match &mut t.engine {
            Engine::Burn { optim, .. } => {
                let path = dir.join("optim.bpk");
                if path.exists() {
                    *optim = crate::train::load_optimizer(&path, |p| adam().load(p))?;
                }
            }
            Engine::Kernels(host) => {
                let path = dir.join(OPTIM_MOMENTS);
                if path.exists() {
                    let bytes = std::fs::read(&path).map_err(|e| ModelError::io(&path, e))?;
                    let moments = crate::params::from_safetensors_bytes(&bytes).map_err(|e| e.in_file(&path))?.0;
                    host.set_moments(&moments, state.adam_steps.unwrap_or(state.step)).map_err(|e| e.in_file(&path))?;
                }
            }
        }
        t.step = state.step;
        t.rng = crate::checkpoint::rng_at(state.rng_seed, state.rng_stream, state.rng_word_pos);
        Ok(t)
    }
}
