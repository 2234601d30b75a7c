//! Two-stage training (stage 1: the VQ autoencoder on clean RGB-D; stage 2: the encoder on
//! incomplete -> complete pairs, codebook and decoder frozen) as library functions the CLI calls.
//!
//! - Stage 1: autoencode clean RGB-D (zero mask), optionally without quantization for the first
//!   `warmup_no_quant_steps`; L1 + gradient-L1 perceptual + quantizer loss, hinge PatchGAN from
//!   `disc_start` with the adaptive weight; dead codes revived by k-means.
//! - Stage 2: incomplete -> complete pairs; only the mask fusion `conv_in` and the `encoder` train.
//!   `quant_conv`, the codebook, `post_quant_conv` and the decoder are frozen (bit-identical).
//!
//! Data comes through [`PairSource`], so this crate knows nothing about maps or synthetic worlds.
//!
//! A checkpoint is one folder, `RUN/ckpt`, committed as a whole ([`crate::checkpoint`]: written
//! to `RUN/ckpt.new` with a manifest of sizes and CRC-32s, swapped in by renames):
//! `model.safetensors` (f32), `disc.safetensors`, `optim_model.bpk` / `optim_disc.bpk` (burn
//! optimizer records) and `state.json` ([`CheckpointState`]: format version, model config, train
//! config, step, RNG state, codebook usage, k-means buffer). After each commit the weights are
//! also published as `RUN/model.safetensors` (the file `--init` and `train export` take) and a
//! summary as `RUN/config.json` ([`RunSummary`]); resuming reads only `RUN/ckpt`. Training stops
//! with [`TrainError::Diverged`] when a loss or a weight becomes non-finite; a diverged model is
//! never written.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor, TensorData};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sgam_core::RgbdFrame;

use crate::blocks::pixel_shuffle;
use crate::checkpoint::{commit_folder, committed_folder, verify_folder};
use crate::config::ModelConfig;
use crate::loss::{adaptive_weight, generator_loss, gradient_l1, hinge_d_loss, l1, Discriminator, DiscriminatorConfig};
use crate::model::VqModel;
use crate::packing::{pack, pack_target, unpack};
use crate::params::{
    first_non_finite, from_safetensors_bytes, load_named, named_tensors, save_safetensors, write_atomic,
    WeightPrecision,
};
use crate::quantize::{
    codebook_values, kmeans_revive, quantize, set_codebook, to_host, CodebookUsage, FeatureBuffer, Sampling,
};
use crate::ModelError;

/// One training example: network input (with its missing mask) and the complete target.
/// Stage 1: `input == target`, `missing` all false.
#[derive(Debug, Clone)]
pub struct TrainPair {
    /// Incomplete (stage 2) or clean (stage 1) RGB-D input.
    pub input: RgbdFrame,
    /// Row-major, `true` = missing pixel of `input`.
    pub missing: Vec<bool>,
    /// Complete RGB-D target, same size.
    pub target: RgbdFrame,
}

/// Supplies training batches (random crops of size `crop` x `crop`), drawing randomness from `rng`.
pub trait PairSource {
    /// Error type of this source.
    type Error: std::error::Error + Send + Sync + 'static;

    /// Returns `batch` pairs of `crop x crop` pixels.
    fn next_batch(&mut self, batch: usize, crop: u32, rng: &mut ChaCha8Rng) -> Result<Vec<TrainPair>, Self::Error>;
}

/// Training stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Stage {
    /// Autoencoder on clean RGB-D.
    One,
    /// Encoder fine-tuning on incomplete -> complete pairs.
    Two,
}

/// Training hyper-parameters (serialised into every checkpoint).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Stage.
    pub stage: Stage,
    /// Total optimisation steps (a resumed run continues up to this).
    pub steps: u64,
    /// Images per step.
    pub batch: usize,
    /// Random crop size in pixels (the source crops).
    pub crop: u32,
    /// Adam learning rate. The paper uses 4.5e-6 x batch for a 68M model on GPUs; our default
    /// 2e-4 suits the compact model and short CPU budgets.
    pub lr: f64,
    /// Step from which the learning rate follows a half cosine from `lr` down to
    /// `lr * LR_FLOOR` at `steps` (None: constant). Fine-tuning the tail of a run this way is
    /// worth ~0.5 dB over a constant rate at the same step count.
    #[serde(default)]
    pub lr_decay_from: Option<u64>,
    /// Adam beta1 (paper 0.5).
    pub beta1: f32,
    /// Adam beta2 (paper 0.9).
    pub beta2: f32,
    /// Stage 1: first steps decode the encoder output directly (no quantizer), as the paper.
    pub warmup_no_quant_steps: u64,
    /// Step from which the discriminator and the adversarial term are active.
    pub disc_start: u64,
    /// Scale of the adaptive adversarial weight (0.8).
    pub disc_weight: f32,
    /// Weight of the gradient-L1 perceptual term (0.1; at 1.0 it stalls colour learning).
    pub perceptual_weight: f32,
    /// Weight of the L1 term on pixels missing in the input, relative to observed ones (1 =
    /// plain L1). Stage 2 raises it: the refiner keeps observed pixels at inference, and
    /// missing pixels are a few percent of a frame.
    #[serde(default = "one")]
    pub missing_weight: f32,
    /// Weight of the quantizer loss (1.0).
    pub codebook_weight: f32,
    /// Discriminator architecture.
    pub disc: DiscriminatorConfig,
    /// Steps a code may go unused before it counts as dead.
    pub kmeans_window: u64,
    /// Revive when more than this fraction of codes is dead (0.1).
    pub kmeans_dead_fraction: f32,
    /// Lloyd iterations per revival.
    pub kmeans_iters: usize,
    /// Encoder feature rows kept for k-means.
    pub feature_buffer: usize,
    /// Checkpoint every this many steps (0 = only at the end).
    pub ckpt_every: u64,
    /// Validate every this many steps (0 = never).
    pub val_every: u64,
    /// Seed of weights, batches and sampling.
    pub seed: u64,
    /// Weights to start from (stage 2: the stage-1 model). Read only by a new run; a resumed
    /// run must name the same file.
    pub init_weights: Option<PathBuf>,
    /// Options of the pair source (e.g. the scene count), recorded so that a resumed run can
    /// check it is fed the same data.
    #[serde(default)]
    pub data: BTreeMap<String, String>,
}

/// Largest batch [`TrainConfig::validate`] accepts.
pub const MAX_BATCH: usize = 256;
/// Largest crop side (pixels) [`TrainConfig::validate`] accepts.
pub const MAX_CROP: u32 = 4096;
/// Largest step count [`TrainConfig::validate`] accepts.
pub const MAX_STEPS: u64 = 1_000_000_000;

/// One field whose value a resumed run was asked to change.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfigDifference {
    /// Field name of [`TrainConfig`] (or `model_config`).
    pub field: &'static str,
    /// Value the run was started with.
    pub stored: String,
    /// Value asked for now.
    pub asked: String,
}

/// Fraction of `lr` that the cosine decay ends at.
pub const LR_FLOOR: f64 = 0.05;

/// The learning-rate schedule every trainer of this crate uses: `lr` until `decay_from`, then a
/// half cosine down to `lr * LR_FLOOR` at `steps` (constant when `decay_from` is `None` or not
/// before `steps`). The rate of the step that follows `step` optimisation steps.
pub fn half_cosine_lr(lr: f64, steps: u64, decay_from: Option<u64>, step: u64) -> f64 {
    match decay_from {
        Some(from) if step >= from && steps > from => {
            let t = ((step - from) as f64 / (steps - from) as f64).min(1.0);
            lr * (LR_FLOOR + (1.0 - LR_FLOOR) * 0.5 * (1.0 + (std::f64::consts::PI * t).cos()))
        }
        _ => lr,
    }
}

/// Adam with this crate's epsilon (1e-8) and the given betas.
pub(crate) fn adam_with(beta_1: f32, beta_2: f32) -> ModuleOptimizer {
    AdamConfig::new().with_beta_1(beta_1).with_beta_2(beta_2).with_epsilon(1e-8).init()
}

impl TrainConfig {
    /// Learning rate of the step that follows `step` optimisation steps.
    pub fn lr_at(&self, step: u64) -> f64 {
        half_cosine_lr(self.lr, self.steps, self.lr_decay_from, step)
    }

    /// Checks every field is finite and in range for `model` (the crop a positive multiple of its
    /// downsampling factor). Errors name the field and the accepted range.
    pub fn validate(&self, model: &ModelConfig) -> Result<(), ModelError> {
        let bad = |m: String| Err(ModelError::config("training", m));
        if self.steps > MAX_STEPS {
            return bad(format!("steps {} out of range 0..={MAX_STEPS}", self.steps));
        }
        if !(1..=MAX_BATCH).contains(&self.batch) {
            return bad(format!("batch {} out of range 1..={MAX_BATCH}", self.batch));
        }
        let f = model.downsample_factor() as u32;
        if !(f..=MAX_CROP).contains(&self.crop) || !self.crop.is_multiple_of(f) {
            return bad(format!(
                "crop {} must be a multiple of the model's downsampling factor {f} in {f}..={MAX_CROP}",
                self.crop
            ));
        }
        if !(self.lr.is_finite() && self.lr > 0.0 && self.lr <= 1.0) {
            return bad(format!("lr {} must be in (0, 1]", self.lr));
        }
        if let Some(from) = self.lr_decay_from {
            if from >= self.steps {
                return bad(format!("lr_decay_from {from} must be below steps {}", self.steps));
            }
        }
        for (name, v) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(v.is_finite() && (0.0..1.0).contains(&v)) {
                return bad(format!("{name} {v} must be in [0, 1)"));
            }
        }
        for (name, v) in [
            ("disc_weight", self.disc_weight),
            ("perceptual_weight", self.perceptual_weight),
            ("codebook_weight", self.codebook_weight),
            ("missing_weight", self.missing_weight),
        ] {
            if !(v.is_finite() && (0.0..=1000.0).contains(&v)) {
                return bad(format!("{name} {v} must be in 0..=1000"));
            }
        }
        if self.missing_weight <= 0.0 {
            return bad(format!("missing_weight {} must be positive", self.missing_weight));
        }
        if !(self.kmeans_dead_fraction.is_finite() && (0.0..=1.0).contains(&self.kmeans_dead_fraction)) {
            return bad(format!("kmeans_dead_fraction {} must be in 0..=1", self.kmeans_dead_fraction));
        }
        if self.kmeans_iters > 1000 || self.kmeans_window == 0 {
            return bad(format!(
                "kmeans_iters {} (at most 1000) / kmeans_window {} (at least 1) out of range",
                self.kmeans_iters, self.kmeans_window
            ));
        }
        if self.feature_buffer > 1 << 20 {
            return bad(format!("feature_buffer {} out of range 0..={}", self.feature_buffer, 1 << 20));
        }
        Ok(())
    }

    /// The fields a run resumed with `asked` would change. A resumed run keeps its configuration
    /// except `steps`, `lr_decay_from`, `ckpt_every` and `val_every`; anything else asked
    /// differently is a difference (stage first when it differs).
    pub fn resume_differences(&self, asked: &TrainConfig) -> Vec<ConfigDifference> {
        let mut out = Vec::new();
        let mut cmp = |field: &'static str, a: String, b: String| {
            if a != b {
                out.push(ConfigDifference { field, stored: a, asked: b });
            }
        };
        let stage = |s: Stage| if s == Stage::One { "1".to_string() } else { "2".to_string() };
        cmp("stage", stage(self.stage), stage(asked.stage));
        cmp("batch", self.batch.to_string(), asked.batch.to_string());
        cmp("crop", self.crop.to_string(), asked.crop.to_string());
        cmp("lr", self.lr.to_string(), asked.lr.to_string());
        cmp("beta1", self.beta1.to_string(), asked.beta1.to_string());
        cmp("beta2", self.beta2.to_string(), asked.beta2.to_string());
        cmp("warmup_no_quant_steps", self.warmup_no_quant_steps.to_string(), asked.warmup_no_quant_steps.to_string());
        cmp("disc_start", self.disc_start.to_string(), asked.disc_start.to_string());
        cmp("disc_weight", self.disc_weight.to_string(), asked.disc_weight.to_string());
        cmp("perceptual_weight", self.perceptual_weight.to_string(), asked.perceptual_weight.to_string());
        cmp("missing_weight", self.missing_weight.to_string(), asked.missing_weight.to_string());
        cmp("codebook_weight", self.codebook_weight.to_string(), asked.codebook_weight.to_string());
        cmp("seed", self.seed.to_string(), asked.seed.to_string());
        let path = |p: &Option<PathBuf>| p.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| "none".into());
        cmp("init_weights", path(&self.init_weights), path(&asked.init_weights));
        for key in self.data.keys().chain(asked.data.keys().filter(|k| !self.data.contains_key(*k))) {
            let get = |m: &BTreeMap<String, String>| m.get(key).cloned().unwrap_or_else(|| "unset".into());
            if get(&self.data) != get(&asked.data) {
                out.push(ConfigDifference {
                    field: "data",
                    stored: format!("{key} {}", get(&self.data)),
                    asked: format!("{key} {}", get(&asked.data)),
                });
            }
        }
        out
    }

    /// Defaults for a stage: batch 4, crop 128, lr 2e-4, Adam (0.5, 0.9), disc from step 10k.
    pub fn new(stage: Stage, steps: u64) -> Self {
        Self {
            stage,
            steps,
            batch: 4,
            crop: 128,
            lr: 2e-4,
            lr_decay_from: None,
            beta1: 0.5,
            beta2: 0.9,
            warmup_no_quant_steps: 0,
            disc_start: 10_000,
            disc_weight: 0.8,
            perceptual_weight: 0.1,
            missing_weight: 1.0,
            codebook_weight: 1.0,
            disc: DiscriminatorConfig::compact(),
            kmeans_window: 200,
            kmeans_dead_fraction: 0.1,
            kmeans_iters: 5,
            feature_buffer: 4096,
            ckpt_every: 500,
            val_every: 500,
            seed: 0,
            init_weights: None,
            data: BTreeMap::new(),
        }
    }
}

/// Losses and statistics of one step.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StepReport {
    /// Step number after this update (1-based).
    pub step: u64,
    /// Generator total loss.
    pub total: f32,
    /// L1 over 4 channels.
    pub l1: f32,
    /// Gradient-L1 perceptual term.
    pub perceptual: f32,
    /// Quantizer loss (0 without quantization).
    pub quant: f32,
    /// Generator adversarial loss (0 before `disc_start`).
    pub g_gan: f32,
    /// Discriminator hinge loss (0 before `disc_start`).
    pub d_loss: f32,
    /// Adaptive adversarial weight used.
    pub d_weight: f32,
    /// RGB PSNR of the batch reconstruction, dB (8-bit scale equivalent: peak 1.0).
    pub psnr: f32,
    /// Codes used in the last `kmeans_window` steps.
    pub active_codes: usize,
    /// Codes revived by k-means in this step.
    pub revived: usize,
}

/// One validation example's images (input, model output, target).
#[derive(Debug, Clone)]
pub struct ValidationImage {
    /// Network input.
    pub input: RgbdFrame,
    /// Model output.
    pub output: RgbdFrame,
    /// Target.
    pub target: RgbdFrame,
}

/// What the progress callback receives after each step.
#[derive(Debug, Clone)]
pub struct TrainProgress {
    /// The step's losses.
    pub report: StepReport,
    /// Total steps of the run.
    pub total_steps: u64,
    /// Training throughput over the run so far, images per second.
    pub images_per_s: f32,
    /// Mean validation RGB PSNR (dB) and images, on validation steps.
    pub validation: Option<(f32, Vec<ValidationImage>)>,
}

/// Format version of [`CheckpointState`] this build writes and reads.
pub const STATE_VERSION: u32 = 2;

/// Serialised trainer state (`RUN/ckpt/state.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointState {
    /// [`STATE_VERSION`] (absent in the first layout's `config.json`: 0).
    #[serde(default)]
    pub version: u32,
    /// Model architecture.
    pub model_config: ModelConfig,
    /// Training configuration.
    pub train_config: TrainConfig,
    /// Completed steps.
    pub step: u64,
    /// ChaCha8 RNG seed, stream and word position.
    pub rng_seed: [u8; 32],
    /// RNG stream.
    pub rng_stream: u64,
    /// RNG word position.
    pub rng_word_pos: u128,
    /// Codebook usage.
    pub usage: CodebookUsage,
    /// k-means feature buffer.
    pub buffer: FeatureBuffer,
}

/// What `RUN/config.json` holds: the run's configuration and last committed step, for people
/// and scripts (resuming reads `RUN/ckpt/state.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunSummary {
    /// Completed steps of the last committed checkpoint.
    pub step: u64,
    /// Model architecture.
    pub model_config: ModelConfig,
    /// Training configuration.
    pub train_config: TrainConfig,
}

/// Errors of training.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// A model error (weights, config, input, checkpoint).
    #[error(transparent)]
    Model(#[from] ModelError),
    /// The pair source failed.
    #[error("pair source")]
    Source(#[source] Box<dyn std::error::Error + Send + Sync>),
    /// A loss or a weight became non-finite; nothing was written after it.
    #[error("training diverged at step {step}: {what} (lower the learning rate); the last checkpoint is kept")]
    Diverged {
        /// The step that diverged.
        step: u64,
        /// The non-finite quantity.
        what: String,
    },
    /// A resumed run was asked for another configuration than the one it was started with.
    #[error("{}: resuming with other options than the run was started with ({}); resume with its options or start a new run", .run.display(), .differences.iter().map(|d| format!("{} {} (asked {})", d.field, d.stored, d.asked)).collect::<Vec<_>>().join(", "))]
    ResumeMismatch {
        /// The run folder.
        run: PathBuf,
        /// What differs (the stage first when it does).
        differences: Vec<ConfigDifference>,
    },
}

/// A training session: model, discriminator, optimizers, RNG and bookkeeping.
pub struct Trainer {
    /// Model architecture.
    pub model_config: ModelConfig,
    /// Training configuration.
    pub train_config: TrainConfig,
    /// The model (autodiff).
    pub model: VqModel,
    /// The discriminator (autodiff).
    pub disc: Discriminator,
    optim_model: ModuleOptimizer,
    optim_disc: ModuleOptimizer,
    /// Completed steps.
    pub step: u64,
    /// The run's RNG (batches).
    pub rng: ChaCha8Rng,
    /// Codebook usage statistics.
    pub usage: CodebookUsage,
    /// Recent encoder features for k-means.
    pub buffer: FeatureBuffer,
    device: Device,
}

impl std::fmt::Debug for Trainer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Trainer").field("step", &self.step).field("model_config", &self.model_config).finish()
    }
}

fn adam(cfg: &TrainConfig) -> ModuleOptimizer {
    adam_with(cfg.beta1, cfg.beta2)
}

/// Freezes everything but the mask fusion conv and the encoder (stage 2).
fn freeze_for_stage(model: VqModel, stage: Stage) -> VqModel {
    match stage {
        Stage::One => model,
        Stage::Two => {
            let mut m = model;
            m.quant_conv = m.quant_conv.no_grad();
            m.quantize = m.quantize.no_grad();
            m.post_quant_conv = m.post_quant_conv.no_grad();
            m.decoder = m.decoder.no_grad();
            m
        }
    }
}

fn read_weights(path: &Path) -> Result<std::collections::BTreeMap<String, crate::params::NamedTensor>, ModelError> {
    let bytes = std::fs::read(path).map_err(|e| ModelError::io(path, e))?;
    Ok(from_safetensors_bytes(&bytes).map_err(|e| e.in_file(path))?.0)
}

/// Loads the weights file `path` into `module` ([`load_named`]); errors name the file.
fn load_weights<M: Module>(module: M, path: &Path) -> Result<M, ModelError> {
    load_named(module, &read_weights(path)?, false, false).map_err(|e| e.in_file(path))
}

/// Folder of a run's committed checkpoint (`RUN/ckpt`).
pub const CHECKPOINT_DIR: &str = "ckpt";

/// Reads and validates the committed checkpoint of `run_dir`: its manifest (every file's size
/// and CRC-32), the state's version and contents (configurations in range, codebook usage and
/// feature buffer fitting the model). `Ok(None)` when the run has no checkpoint; an error for a
/// checkpoint in the first layout (five separate files, which a kill could leave mixed).
pub fn read_checkpoint(run_dir: &Path) -> Result<Option<(PathBuf, CheckpointState)>, ModelError> {
    let Some(dir) = committed_folder(run_dir, CHECKPOINT_DIR) else {
        if run_dir.join("optim_model.bpk").exists() {
            return Err(ModelError::checkpoint(
                run_dir,
                format!(
                    "a checkpoint in the layout of an older sgam (five separate files that an interrupted save \
                     could leave mixed); it cannot be verified, so it is not resumed: start a new run with \
                     --init {}",
                    run_dir.join("model.safetensors").display()
                ),
            ));
        }
        return Ok(None);
    };
    verify_folder(&dir)?;
    let path = dir.join("state.json");
    let bytes = std::fs::read(&path).map_err(|e| ModelError::io(&path, e))?;
    let state: CheckpointState = serde_json::from_slice(&bytes)
        .map_err(|e| ModelError::checkpoint(&path, format!("not a training state: {e}")))?;
    let bad = |m: String| ModelError::checkpoint(&path, m);
    if state.version != STATE_VERSION {
        return Err(bad(format!("state version {} (this build reads {STATE_VERSION})", state.version)));
    }
    state.model_config.validate().map_err(|e| bad(e.to_string()))?;
    state.train_config.validate(&state.model_config).map_err(|e| bad(e.to_string()))?;
    state.usage.check(state.model_config.n_embed).map_err(bad)?;
    state.buffer.check(state.model_config.embed_dim).map_err(bad)?;
    if state.step > state.train_config.steps.max(MAX_STEPS) {
        return Err(bad(format!("step {} out of range", state.step)));
    }
    Ok(Some((dir, state)))
}

fn psnr_rgb(pred: &[f32], target: &[f32], b: usize, hw: usize) -> f32 {
    let mut se = 0.0f64;
    let mut n = 0usize;
    for i in 0..b {
        for c in 0..3 {
            let off = (i * 4 + c) * hw;
            for p in 0..hw {
                let a = ((pred[off + p] + 1.0) * 0.5).clamp(0.0, 1.0);
                let t = ((target[off + p] + 1.0) * 0.5).clamp(0.0, 1.0);
                se += ((a - t) as f64).powi(2);
                n += 1;
            }
        }
    }
    let mse = (se / n.max(1) as f64).max(1e-12);
    sgam_metrics::psnr_db(mse, 1.0) as f32
}

impl Trainer {
    /// Starts a fresh session (weights from `seed`, or `train_config.init_weights`).
    pub fn new(model_config: &ModelConfig, train_config: &TrainConfig) -> Result<Self, ModelError> {
        let device = crate::default_device();
        let mut model = VqModel::new(model_config, train_config.seed, &device)?;
        if let Some(path) = &train_config.init_weights {
            model = load_weights(model, path)?;
        }
        Ok(Self::with_model(model_config, train_config, model, device))
    }

    /// A fresh session starting from `model` (of `model_config`; `train_config.init_weights` is
    /// not read).
    pub fn from_model(model_config: &ModelConfig, train_config: &TrainConfig, model: VqModel) -> Self {
        Self::with_model(model_config, train_config, model, crate::default_device())
    }

    fn with_model(model_config: &ModelConfig, train_config: &TrainConfig, model: VqModel, device: Device) -> Self {
        let model = freeze_for_stage(model, train_config.stage).train();
        let disc = Discriminator::new(&train_config.disc, train_config.seed, &device).train();
        Self {
            model_config: model_config.clone(),
            train_config: train_config.clone(),
            model,
            disc,
            optim_model: adam(train_config),
            optim_disc: adam(train_config),
            step: 0,
            rng: ChaCha8Rng::seed_from_u64(train_config.seed),
            usage: CodebookUsage::new(model_config.n_embed, 0),
            buffer: FeatureBuffer::new(model_config.embed_dim, train_config.feature_buffer),
            device,
        }
    }

    /// The model as trained so far, for inference (no gradients).
    pub fn inference_model(&self) -> VqModel {
        self.model.valid()
    }

    /// The first non-finite weight of the model or the discriminator, described.
    pub fn non_finite_weight(&self) -> Option<String> {
        let model = named_tensors(&self.model).into_iter().map(|(n, t)| (n, t, "model"));
        let disc = named_tensors(&self.disc).into_iter().map(|(n, t)| (n, t, "discriminator"));
        model
            .chain(disc)
            .find_map(|(name, t, which)| first_non_finite(&t.values).map(|b| format!("{which} weight {name}: {b}")))
    }

    /// Commits a checkpoint `run_dir/ckpt` as a whole (see the module docs), then publishes the
    /// weights as `run_dir/model.safetensors` and the summary as `run_dir/config.json`. Writes
    /// nothing when a weight is non-finite ([`TrainError::Diverged`]).
    pub fn save(&self, run_dir: &Path) -> Result<(), TrainError> {
        if let Some(what) = self.non_finite_weight() {
            return Err(TrainError::Diverged { step: self.step, what });
        }
        std::fs::create_dir_all(run_dir).map_err(|e| ModelError::io(run_dir, e))?;
        let meta = crate::refiner::weight_metadata(&self.model_config)?;
        let state = CheckpointState {
            version: STATE_VERSION,
            model_config: self.model_config.clone(),
            train_config: self.train_config.clone(),
            step: self.step,
            rng_seed: self.rng.get_seed(),
            rng_stream: self.rng.get_stream(),
            rng_word_pos: self.rng.get_word_pos(),
            usage: self.usage.clone(),
            buffer: self.buffer.clone(),
        };
        let json = serde_json::to_vec(&state).map_err(|e| ModelError::state("serialising state", e))?;
        let dir = commit_folder(run_dir, CHECKPOINT_DIR, |new| {
            save_safetensors(&self.model, &new.join("model.safetensors"), WeightPrecision::F32, Some(meta))?;
            save_safetensors(&self.disc, &new.join("disc.safetensors"), WeightPrecision::F32, None)?;
            for (optim, name) in [(&self.optim_model, "optim_model.bpk"), (&self.optim_disc, "optim_disc.bpk")] {
                let bytes = optim.into_bytes().map_err(|e| ModelError::state(format!("optimizer {name}"), e))?;
                write_atomic(&new.join(name), &bytes)?;
            }
            write_atomic(&new.join("state.json"), &json)
        })?;
        let weights = std::fs::read(dir.join("model.safetensors"))
            .map_err(|e| ModelError::io(&dir.join("model.safetensors"), e))?;
        write_atomic(&run_dir.join("model.safetensors"), &weights)?;
        let summary = RunSummary {
            step: self.step,
            model_config: self.model_config.clone(),
            train_config: self.train_config.clone(),
        };
        let json = serde_json::to_vec_pretty(&summary).map_err(|e| ModelError::state("serialising the summary", e))?;
        write_atomic(&run_dir.join("config.json"), &json)?;
        Ok(())
    }

    /// Resumes from the committed checkpoint of `run_dir` ([`read_checkpoint`]). `steps`
    /// overrides the stored total when given.
    pub fn resume(run_dir: &Path, steps: Option<u64>) -> Result<Self, ModelError> {
        let (dir, state) = read_checkpoint(run_dir)?
            .ok_or_else(|| ModelError::checkpoint(run_dir, format!("no checkpoint ({CHECKPOINT_DIR}/)")))?;
        let mut train_config = state.train_config.clone();
        if let Some(s) = steps {
            train_config.steps = s;
        }
        let device = crate::default_device();
        let model = VqModel::new(&state.model_config, train_config.seed, &device)?;
        let model = load_weights(model, &dir.join("model.safetensors"))?;
        let model = freeze_for_stage(model, train_config.stage).train();
        let disc = Discriminator::new(&train_config.disc, train_config.seed, &device);
        let disc = load_weights(disc, &dir.join("disc.safetensors"))?.train();
        let mut optims = Vec::new();
        for name in ["optim_model.bpk", "optim_disc.bpk"] {
            optims.push(load_optimizer(&dir.join(name), |p| adam(&train_config).load(p))?);
        }
        let optim_disc = optims.pop().ok_or_else(|| ModelError::checkpoint(&dir, "optimizer missing"))?;
        let optim_model = optims.pop().ok_or_else(|| ModelError::checkpoint(&dir, "optimizer missing"))?;
        let mut rng = ChaCha8Rng::from_seed(state.rng_seed);
        rng.set_stream(state.rng_stream);
        rng.set_word_pos(state.rng_word_pos);
        Ok(Self {
            model_config: state.model_config,
            train_config,
            model,
            disc,
            optim_model,
            optim_disc,
            step: state.step,
            rng,
            usage: state.usage,
            buffer: state.buffer,
            device,
        })
    }

    /// One optimisation step on a batch from `source`.
    pub fn step<S: PairSource + ?Sized>(&mut self, source: &mut S) -> Result<StepReport, TrainError> {
        let cfg = self.train_config.clone();
        let batch =
            source.next_batch(cfg.batch, cfg.crop, &mut self.rng).map_err(|e| TrainError::Source(Box::new(e)))?;
        self.step_on(&batch)
    }

    /// One optimisation step on the given pairs.
    pub fn step_on(&mut self, batch: &[TrainPair]) -> Result<StepReport, TrainError> {
        self.step_with(batch, None)
    }

    /// One optimisation step on pairs seen through `intrinsics` (one per pair): a model with
    /// ray channels ([`ModelConfig::ray_channels`]) needs them.
    pub fn step_on_at(
        &mut self,
        batch: &[TrainPair],
        intrinsics: &[sgam_core::Intrinsics],
    ) -> Result<StepReport, TrainError> {
        self.step_with(batch, Some(intrinsics))
    }

    fn step_with(
        &mut self,
        batch: &[TrainPair],
        intrinsics: Option<&[sgam_core::Intrinsics]>,
    ) -> Result<StepReport, TrainError> {
        let cfg = self.train_config.clone();
        let dev = self.device.clone().autodiff();
        let inputs: Vec<&RgbdFrame> = batch.iter().map(|p| &p.input).collect();
        let masks: Vec<Option<&[bool]>> = batch.iter().map(|p| Some(p.missing.as_slice())).collect();
        let targets: Vec<&RgbdFrame> = batch.iter().map(|p| &p.target).collect();
        let coding = self.model_config.depth;
        let x = match intrinsics {
            Some(k) => crate::packing::pack_input(&inputs, &masks, k, &self.model_config, &dev)?,
            None => pack(&inputs, &masks, &coding, &dev)?,
        };
        let target = pack_target(&targets, &coding, &dev)?;
        let step = self.step + 1;
        let use_quant = cfg.stage == Stage::Two || step > cfg.warmup_no_quant_steps;
        let use_disc = step > cfg.disc_start;

        // Generator forward.
        let z = self.model.encode(x);
        let mut report = StepReport { step, ..Default::default() };
        if use_quant
            && cfg.stage == Stage::One
            && cfg.warmup_no_quant_steps > 0
            && step == cfg.warmup_no_quant_steps + 1
        {
            // end of the warm-up: initialise the whole codebook by k-means on the encoder features
            // collected during it, so quantization starts from codes that span the features
            self.init_codebook_from_buffer(step)?;
        }
        let (z_q, quant_loss) = if use_quant {
            let q = quantize(&self.model, z, Sampling::Argmin, None, self.model_config.beta, &mut self.rng)?;
            self.usage.record(&q.indices, step);
            self.buffer.push(&q.features);
            (q.z_q, Some(q.loss))
        } else {
            if cfg.stage == Stage::One {
                let [b, d, h, w] = z.dims();
                self.buffer.push(&to_host(z.clone().detach().permute([0, 2, 3, 1]).reshape([b * h * w, d]))?);
            }
            (z, None)
        };
        let features = self.model.decode_features(z_q);
        let rec = self.model.decoder.forward_head(features.clone());
        let l1_loss = if cfg.missing_weight != 1.0 {
            let weights = missing_weights(batch, cfg.missing_weight, &dev);
            weighted_l1(rec.clone(), target.clone(), weights)
        } else {
            l1(rec.clone(), target.clone())
        };
        let perc = gradient_l1(rec.clone(), target.clone());
        report.l1 = scalar(&l1_loss)?;
        report.perceptual = scalar(&perc)?;
        let mut total = l1_loss + perc.mul_scalar(cfg.perceptual_weight);
        if let Some(ql) = quant_loss {
            report.quant = scalar(&ql)?;
            total = total + ql.mul_scalar(cfg.codebook_weight);
        }
        if use_disc {
            let g_loss = generator_loss(self.disc.forward(rec.clone()));
            let w = self.adaptive_gan_weight(features.detach(), &target, cfg.perceptual_weight, cfg.disc_weight)?;
            report.g_gan = scalar(&g_loss)?;
            report.d_weight = w;
            total = total + g_loss.mul_scalar(w);
        }
        report.total = scalar(&total)?;
        if !report.total.is_finite() {
            return Err(TrainError::Diverged { step, what: format!("the loss is {}", report.total) });
        }
        let grads = total.backward();
        let grads = GradientsParams::from_grads(grads, &self.model);
        self.model = self.optim_model.step(cfg.lr_at(self.step), self.model.clone(), grads);

        // Discriminator step.
        if use_disc {
            let logits_real = self.disc.forward(target.clone().detach());
            let logits_fake = self.disc.forward(rec.clone().detach());
            let d_loss = hinge_d_loss(logits_real, logits_fake);
            report.d_loss = scalar(&d_loss)?;
            if !report.d_loss.is_finite() {
                return Err(TrainError::Diverged {
                    step,
                    what: format!("the discriminator loss is {}", report.d_loss),
                });
            }
            let grads = GradientsParams::from_grads(d_loss.backward(), &self.disc);
            self.disc = self.optim_disc.step(cfg.lr_at(self.step), self.disc.clone(), grads);
        }

        // Statistics and codebook maintenance.
        let dims = rec.dims();
        let pred = to_host(rec.detach())?;
        let tgt = to_host(target.detach())?;
        report.psnr = psnr_rgb(&pred, &tgt, dims[0], dims[2] * dims[3]);
        if use_quant && cfg.stage == Stage::One {
            report.revived = self.maybe_revive(step)?;
        }
        report.active_codes = self.usage.active_count(step, cfg.kmeans_window);
        self.step = step;
        Ok(report)
    }

    /// Adaptive adversarial weight from gradient norms at the decoder's last conv weight. Computed
    /// on a fresh graph over the detached last-layer input: the weight gradient of a conv depends
    /// only on its input and the output gradient, so this equals the full graph's value.
    fn adaptive_gan_weight(
        &self,
        features: Tensor<4>,
        target: &Tensor<4>,
        perceptual_weight: f32,
        scale: f32,
    ) -> Result<f32, ModelError> {
        let head = &self.model.decoder.conv_out;
        let patch = self.model_config.patch_size;
        let norm_of = |loss_of: &dyn Fn(Tensor<4>) -> Tensor<1>| -> Result<f32, ModelError> {
            let w = head.weight.val().detach().require_grad();
            let b = head.bias.as_ref().map(|b| b.val().detach());
            let out = pixel_shuffle(
                conv2d(features.clone(), w.clone(), b, ConvOptions::new([1, 1], [1, 1], [1, 1], 1)),
                patch,
            );
            let grads = loss_of(out).backward();
            let g = w.grad(&grads).ok_or(ModelError::MissingPart {
                part: "a gradient at decoder.conv_out",
                operation: "the adaptive GAN weight",
            })?;
            Ok(scalar(&g.square().sum())?.sqrt())
        };
        let rec_norm = norm_of(&|out| {
            l1(out.clone(), target.clone()) + gradient_l1(out, target.clone()).mul_scalar(perceptual_weight)
        })?;
        let gan_norm = norm_of(&|out| generator_loss(self.disc.forward(out)))?;
        Ok(adaptive_weight(rec_norm, gan_norm, scale))
    }

    fn maybe_revive(&mut self, step: u64) -> Result<usize, ModelError> {
        let cfg = &self.train_config;
        let dead = self.usage.dead_codes(step, cfg.kmeans_window);
        let k = self.model_config.n_embed;
        if (dead.len() as f32) <= cfg.kmeans_dead_fraction * k as f32 || self.buffer.is_empty() {
            return Ok(0);
        }
        let mut codebook = codebook_values(&self.model)?;
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed ^ step);
        if kmeans_revive(&mut codebook, self.model_config.embed_dim, &dead, &self.buffer, cfg.kmeans_iters, &mut rng) {
            self.model = set_codebook(self.model.clone(), codebook, k, self.model_config.embed_dim)?;
            for &d in &dead {
                self.usage.last_used[d] = step;
            }
            return Ok(dead.len());
        }
        Ok(0)
    }

    /// Overwrites every codebook row by k-means over the feature buffer (end of the warm-up).
    fn init_codebook_from_buffer(&mut self, step: u64) -> Result<(), ModelError> {
        if self.buffer.is_empty() {
            return Ok(());
        }
        let k = self.model_config.n_embed;
        let all: Vec<usize> = (0..k).collect();
        let mut codebook = codebook_values(&self.model)?;
        let mut rng = ChaCha8Rng::seed_from_u64(self.train_config.seed ^ step);
        let iters = self.train_config.kmeans_iters;
        if kmeans_revive(&mut codebook, self.model_config.embed_dim, &all, &self.buffer, iters, &mut rng) {
            self.model = set_codebook(self.model.clone(), codebook, k, self.model_config.embed_dim)?;
            for u in &mut self.usage.last_used {
                *u = step;
            }
        }
        Ok(())
    }

    /// Runs the model (inference mode, argmin) on validation pairs; mean RGB PSNR and images.
    /// During the stage-1 warm-up the quantizer is bypassed, as in training.
    pub fn validate(&self, val: &[TrainPair]) -> Result<(f32, Vec<ValidationImage>), ModelError> {
        let model = self.model.valid();
        let dev = self.device.clone();
        let mut psnrs = Vec::new();
        let mut images = Vec::new();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        for pair in val {
            let x = pack(&[&pair.input], &[Some(pair.missing.as_slice())], &self.model_config.depth, &dev)?;
            let t = pack_target(&[&pair.target], &self.model_config.depth, &dev)?;
            let z = model.encode(x);
            let warmup = self.train_config.stage == Stage::One && self.step <= self.train_config.warmup_no_quant_steps;
            let z_q = if warmup {
                z
            } else {
                quantize(&model, z, Sampling::Argmin, None, self.model_config.beta, &mut rng)?.z_q
            };
            let out = model.decode(z_q);
            let dims = out.dims();
            psnrs.push(psnr_rgb(&to_host(out.clone())?, &to_host(t)?, 1, dims[2] * dims[3]));
            let output =
                unpack(out, &self.model_config.depth)?.pop().ok_or(ModelError::EmptyBatch("validation decode"))?;
            images.push(ValidationImage { input: pair.input.clone(), output, target: pair.target.clone() });
        }
        let mean = psnrs.iter().sum::<f32>() / psnrs.len().max(1) as f32;
        Ok((mean, images))
    }
}

fn one() -> f32 {
    1.0
}

/// Loads the optimizer state at `path` with `load` (burn's `load`), refusing first by name what
/// burn-optim would panic on ([`check_optimizer_state`]): every trainer's resume reads its
/// optimizers through this.
pub(crate) fn load_optimizer<O, E: std::fmt::Display>(
    path: &Path,
    load: impl FnOnce(&Path) -> Result<O, E>,
) -> Result<O, ModelError> {
    check_optimizer_state(path)?;
    load(path).map_err(|e| ModelError::checkpoint(path, format!("cannot read: {e}")))
}

/// Refuses an optimizer state burn-optim would panic on: every state tensor must carry the id of
/// its parameter (a damaged file can lose it while still parsing). Reads only the header.
fn check_optimizer_state(path: &Path) -> Result<(), ModelError> {
    let bad = |msg: String| ModelError::checkpoint(path, msg);
    let tensors = burn_pack::Reader::from_file(path)
        .and_then(burn_pack::Reader::into_tensors)
        .map_err(|e| bad(format!("cannot read: {e}")))?;
    match tensors.iter().find(|t| t.param_id.is_none()) {
        Some(t) => Err(bad(format!("state tensor '{}' has no parameter id", t.name))),
        None => Ok(()),
    }
}

/// Per-pixel loss weights `[B, 1, H, W]`: `missing_weight` where the input is missing, 1 elsewhere.
fn missing_weights(batch: &[TrainPair], missing_weight: f32, dev: &Device) -> Tensor<4> {
    let (h, w) = (batch[0].target.height() as usize, batch[0].target.width() as usize);
    let values: Vec<f32> =
        batch.iter().flat_map(|p| p.missing.iter().map(|&m| if m { missing_weight } else { 1.0 })).collect();
    Tensor::from_data(TensorData::new(values, [batch.len(), 1, h, w]), dev)
}

/// L1 over all channels with per-pixel weights, normalised by the weights' mean.
fn weighted_l1(pred: Tensor<4>, target: Tensor<4>, weights: Tensor<4>) -> Tensor<1> {
    let norm = weights.clone().mean();
    let weights = weights.expand(pred.dims());
    ((pred - target).abs() * weights).mean() / norm
}

fn scalar(t: &Tensor<1>) -> Result<f32, ModelError> {
    Ok(to_host(t.clone().detach())?.first().copied().unwrap_or(f32::NAN))
}

/// Summary of a finished [`train`] call.
#[derive(Debug, Clone)]
pub struct TrainSummary {
    /// Steps completed in total.
    pub steps: u64,
    /// Last step's report.
    pub last: Option<StepReport>,
    /// Images per second over this call.
    pub images_per_s: f32,
}

/// Trains (or resumes, when `run_dir` has a committed checkpoint) until `train_config.steps`,
/// writing checkpoints into `run_dir` and calling `progress` after every step. A resumed run
/// must be asked for its stored configuration ([`TrainError::ResumeMismatch`] otherwise) except
/// `steps`, `ckpt_every`, `val_every` and, when given, `lr_decay_from`.
pub fn train<S: PairSource + ?Sized>(
    run_dir: &Path,
    model_config: &ModelConfig,
    train_config: &TrainConfig,
    source: &mut S,
    val: &[TrainPair],
    progress: &mut dyn FnMut(&TrainProgress),
) -> Result<TrainSummary, TrainError> {
    model_config.validate()?;
    train_config.validate(model_config)?;
    let mut trainer = if let Some((_, state)) = read_checkpoint(run_dir)? {
        let mut differences = state.train_config.resume_differences(train_config);
        if state.model_config != *model_config {
            differences.push(ConfigDifference {
                field: "model_config",
                stored: state.model_config.name.clone(),
                asked: model_config.name.clone(),
            });
        }
        if !differences.is_empty() {
            return Err(TrainError::ResumeMismatch { run: run_dir.to_path_buf(), differences });
        }
        let mut t = Trainer::resume(run_dir, Some(train_config.steps))?;
        // a decay asked for on resume applies (the usual way to fine-tune a run's tail)
        if train_config.lr_decay_from.is_some() {
            t.train_config.lr_decay_from = train_config.lr_decay_from;
        }
        t.train_config.ckpt_every = train_config.ckpt_every;
        t.train_config.val_every = train_config.val_every;
        t
    } else {
        Trainer::new(model_config, train_config)?
    };
    let start = Instant::now();
    let mut images = 0usize;
    let mut last = None;
    while trainer.step < trainer.train_config.steps {
        let report = trainer.step(source)?;
        images += trainer.train_config.batch;
        let tc = &trainer.train_config;
        let validation = if tc.val_every > 0 && report.step % tc.val_every == 0 && !val.is_empty() {
            Some(trainer.validate(val)?)
        } else {
            None
        };
        let images_per_s = images as f32 / start.elapsed().as_secs_f32().max(1e-6);
        progress(&TrainProgress { report: report.clone(), total_steps: tc.steps, images_per_s, validation });
        if tc.ckpt_every > 0 && report.step % tc.ckpt_every == 0 {
            trainer.save(run_dir)?;
        }
        last = Some(report);
    }
    trainer.save(run_dir)?;
    Ok(TrainSummary {
        steps: trainer.step,
        last,
        images_per_s: images as f32 / start.elapsed().as_secs_f32().max(1e-6),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_optimizer_state_tensor_without_its_parameter_id_is_refused_by_name() {
        let tmp = tempfile::tempdir().unwrap();
        let write = |name: &str, id: Option<u64>| {
            let path = tmp.path().join(name);
            let bytes = burn::tensor::Bytes::from_elems(vec![1.0f32, 2.0]);
            let t = burn_pack::Tensor::new("7.moment_1".into(), burn::tensor::DType::F32, [2], id, bytes);
            burn_pack::Writer::new(vec![t]).write_to_file(&path).unwrap();
            path
        };
        assert!(check_optimizer_state(&write("good.bpk", Some(7))).is_ok());
        let e = check_optimizer_state(&write("bad.bpk", None)).unwrap_err().to_string();
        assert!(e.contains("bad.bpk") && e.contains("7.moment_1") && e.contains("parameter id"), "{e}");
        let e = check_optimizer_state(&tmp.path().join("none.bpk")).unwrap_err().to_string();
        assert!(e.contains("none.bpk"), "{e}");
    }
}
