//! The generative stage 2: the encoder learns a *distribution* over codebook indices per latent
//! cell, so that sampling draws plausible completions instead of averaging them.
//!
//! A stage-2 encoder trained with L1 through the frozen decoder predicts the mean of everything
//! that could fill a missing cell: grey ground, or the neighbouring colour continued (measured
//! on our first models: objects never start or end, the ground drifts). Here the target is the
//! code the frozen stage-1 encoder assigns to the clean target
//! ([`target_codes`]), and the loss is the cross-entropy of that index under
//!
//! `p(k | guidance) = softmax_k(-||z - e_k||^2 / tau)`
//!
//! with `z` the encoder's output in the cell, `e_k` the frozen codebook and `tau` a learned
//! temperature: the paper's own sampling formula, now trained to be calibrated, so sampling at
//! `T = 1` (`softmax(-d / (T tau))`) draws from the model's estimate of `p(code | context)` and
//! `T -> 0` is the usual argmin quantizer (the decoder is unchanged). Missing cells weigh
//! [`CodeTrainConfig::observed_weight`]^-1 times more than observed ones: only they are sampled.
//!
//! Only the mask fusion `conv_in` and the `encoder` train; `quant_conv`, the codebook,
//! `post_quant_conv` and the decoder stay bit-identical, so the decoder still turns codes into
//! the stage-1 autoencoder's pixels. Training needs no decoder pass (it runs at encoder speed).
//!
//! **MaskGIT training** ([`CodeTrainConfig::reveal`]): generation fills a large hole in passes,
//! each committing some cells and pasting their decoded pixels in as observed before the next.
//! To train for that, a share of the pairs have a random part of their missing cells revealed
//! first, with the frozen decoder's pixels of the target codes ([`reveal_cells`]), so the
//! encoder learns to complete a hole around cells already drawn, not only from its rim.
//!
//! Checkpoints ([`CodeTrainer::save`]) are one folder, `RUN/ckpt`, replaced as a whole: written
//! to `RUN/ckpt.new`, then swapped in by renames, so a kill at any moment leaves either the old
//! or the new checkpoint, never a mix.

use std::path::Path;

use burn::module::{Module, Param};
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::activation::{log_softmax, softmax};
use burn::tensor::{Device, Int, Tensor, TensorData};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sgam_core::{Intrinsics, RgbdFrame};

use crate::config::ModelConfig;
use crate::model::VqModel;
use crate::packing::{missing_cells, pack_input, unpack};
use crate::params::{load_named, named_tensors, param_id_for_path, write_atomic, NamedTensor, WeightPrecision};
use crate::quantize::{argmin, select_codes, squared_distances, to_host, Sampling};
use crate::ModelError;

/// One training example of the generative stage 2.
#[derive(Debug, Clone, PartialEq)]
pub struct CodePair {
    /// Incomplete guidance (what the generator renders + warps).
    pub input: RgbdFrame,
    /// Row-major, `true` = missing pixel of `input`.
    pub missing: Vec<bool>,
    /// Intrinsics of `input` (a crop carries its shifted principal point).
    pub intrinsics: Intrinsics,
    /// Target code per latent cell, row-major `[H / f, W / f]`: the frozen encoder's argmin on
    /// the clean target.
    pub codes: Vec<u32>,
}

/// Argmin code index per latent cell of each clean frame under `model` (nothing missing):
/// the cross-entropy targets. One `Vec` per frame, row-major `[H / f, W / f]`.
pub fn target_codes(
    model: &VqModel,
    config: &ModelConfig,
    frames: &[&RgbdFrame],
    intrinsics: &[Intrinsics],
    device: &Device,
) -> Result<Vec<Vec<u32>>, ModelError> {
    let x = pack_input(frames, &vec![None; frames.len()], intrinsics, config, device)?;
    let z = model.encode(x);
    let [b, d, h, w] = z.dims();
    let rows = z.permute([0, 2, 3, 1]).reshape([b * h * w, d]);
    let dist = to_host(squared_distances(rows, model.quantize.embedding.weight.val().detach()))?;
    let k = config.n_embed;
    let idx: Vec<u32> = dist.chunks_exact(k).map(|row| argmin(row) as u32).collect();
    Ok(idx.chunks(h * w).map(<[u32]>::to_vec).collect())
}

/// The learned code temperature, stored as `log tau`.
#[derive(Module, Debug)]
pub struct CodeTemperature {
    /// `ln tau`, shape `[1]`.
    pub log_tau: Param<Tensor<1>>,
}

impl CodeTemperature {
    fn new(tau: f32, device: &Device) -> Self {
        Self::from_log(tau.ln(), device)
    }

    fn from_log(log_tau: f32, device: &Device) -> Self {
        let mut log_tau = Param::from_tensor(Tensor::from_data(TensorData::new(vec![log_tau], [1]), device));
        // a fixed id, so the optimizer state saved with a checkpoint finds it again
        log_tau.id = param_id_for_path("code_temperature.log_tau");
        Self { log_tau }
    }

    fn log(&self) -> Result<f32, ModelError> {
        Ok(to_host(self.log_tau.val().detach())?.first().copied().unwrap_or(f32::NAN))
    }

    fn tau(&self) -> Result<f32, ModelError> {
        Ok(self.log()?.exp())
    }
}

/// Hyper-parameters of the generative stage 2 (stored in every checkpoint).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CodeTrainConfig {
    /// Total optimisation steps.
    pub steps: u64,
    /// Pairs per step.
    pub batch: usize,
    /// Adam learning rate (encoder and `log tau`).
    pub lr: f64,
    /// Half-cosine decay from `lr` to 5 % of it between this step and `steps` (None: constant).
    pub lr_decay_from: Option<u64>,
    /// Loss weight of observed cells relative to missing ones (their codes matter for the
    /// decoder's context but are rarely in doubt).
    pub observed_weight: f32,
    /// A latent cell counts as missing when more than this fraction of its pixels is missing
    /// (the refiner's rule).
    pub missing_cell_threshold: f32,
    /// Checkpoint every N steps.
    pub ckpt_every: u64,
    /// RNG seed (batch order).
    pub seed: u64,
    /// Learning rate of `log tau` relative to `lr`: Adam moves a parameter by about its rate
    /// per step, and `log tau` must travel several units early on (the first run, at 1x, took
    /// 300 steps to move it by 0.08 while the missing cells' cross-entropy stayed near 30 nats).
    #[serde(default = "default_tau_lr_scale")]
    pub tau_lr_scale: f64,
    /// Soft targets: the target distribution puts `exp(-||e_k - e_t||^2 / (s * spacing))` on
    /// code `k` around the target code `t` (`spacing` = [`codebook_spacing`]), so codes that
    /// decode alike share the credit; 0 = one-hot targets. The codebook is dense: on the
    /// generator's guidance of *observed* cells the target's exact code is the argmin only
    /// about one time in five (the first run), and with one-hot targets the missing cells'
    /// cross-entropy stayed above that of a uniform guess (7.5 nats for 1024 codes).
    #[serde(default = "default_target_smoothing")]
    pub target_smoothing: f32,
    /// Weight of the depth term: L1 (packed disparity units, `[-1, 1]` over near..far) between
    /// the frozen decoder's disparity for codes *drawn* from the predicted distribution
    /// (`T = 1`, straight-through gradient) and for the target codes, over missing pixels where
    /// the drawn colour agrees with the target's (see [`DEPTH_GATE_COLOUR`]).
    /// Cross-entropy alone treats every wrong code alike; in the ground's codes a neighbour's
    /// code is "almost right" in colour but one cell off in perspective depth, and a sampler that
    /// prefers it raises the generated ground (measured: 0.45 m too near at 13 m on the frame's
    /// far edge). 0 = cross-entropy only (the first generative run).
    #[serde(default)]
    pub depth_weight: f32,
    /// MaskGIT training: the probability that a training pair has a random share of its
    /// missing cells revealed ([`reveal_cells`]) before the step; the revealed share follows
    /// MaskGIT's cosine schedule (`1 - cos(pi u / 2)`, `u` uniform), and at least one cell
    /// stays missing. 0 = the hole as recorded (runs before this option).
    #[serde(default)]
    pub reveal: f32,
}

fn default_target_smoothing() -> f32 {
    1.0
}

fn default_tau_lr_scale() -> f64 {
    30.0
}

impl Default for CodeTrainConfig {
    fn default() -> Self {
        Self {
            steps: 20_000,
            batch: 8,
            lr: 3e-4,
            lr_decay_from: None,
            observed_weight: 0.2,
            missing_cell_threshold: 0.5,
            ckpt_every: 250,
            seed: 0,
            tau_lr_scale: default_tau_lr_scale(),
            target_smoothing: default_target_smoothing(),
            depth_weight: 0.0,
            reveal: 0.0,
        }
    }
}

impl CodeTrainConfig {
    /// Learning rate after `step` steps.
    pub fn lr_at(&self, step: u64) -> f64 {
        crate::train::half_cosine_lr(self.lr, self.steps, self.lr_decay_from, step)
    }
}

/// Losses and accuracies of one step (or of an evaluation pass).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CodeReport {
    /// Step number (1-based) of a training step; 0 for evaluation.
    pub step: u64,
    /// Mean cross-entropy (nats) of the exact target code over missing cells (the loss itself
    /// uses the soft targets of [`CodeTrainConfig::target_smoothing`]).
    pub ce_missing: f32,
    /// Mean cross-entropy of the exact target code over observed cells.
    pub ce_observed: f32,
    /// Share of missing cells whose most likely code is the target.
    pub acc_missing: f32,
    /// Share of observed cells whose most likely code is the target.
    pub acc_observed: f32,
    /// Missing cells in the batch.
    pub missing_cells: usize,
    /// The code temperature after the step.
    pub tau: f32,
    /// Weighted loss that was minimised.
    pub loss: f32,
    /// Mean |disparity of drawn codes - disparity of target codes| over the missing pixels whose
    /// drawn colour agrees with the target's ([`DEPTH_GATE_COLOUR`]; packed units, `[-1, 1]`
    /// spans near..far), codes drawn at `T = 1`; `None` when not measured.
    #[serde(default)]
    pub depth_l1_missing: Option<f32>,
    /// Mean signed (drawn - target) disparity over the same pixels: positive = the drawn surface
    /// is nearer than the target's (a raised ground); `None` when not measured.
    #[serde(default)]
    pub depth_bias_missing: Option<f32>,
}

#[derive(Debug, Serialize, Deserialize)]
struct CodeState {
    version: u32,
    model_config: ModelConfig,
    train_config: CodeTrainConfig,
    step: u64,
    log_tau: f32,
    rng_seed: [u8; 32],
    rng_stream: u64,
    rng_word_pos: u128,
}

const STATE_VERSION: u32 = 1;

/// A generative stage-2 training session.
pub struct CodeTrainer {
    /// Architecture (with `code_tau` kept up to date in saved weights).
    pub model_config: ModelConfig,
    /// Hyper-parameters.
    pub train_config: CodeTrainConfig,
    /// The model (autodiff; only `conv_in` and `encoder` require gradients).
    pub model: VqModel,
    temperature: CodeTemperature,
    optim: ModuleOptimizer,
    optim_tau: ModuleOptimizer,
    /// Completed steps.
    pub step: u64,
    /// Batch-order RNG.
    pub rng: ChaCha8Rng,
    spacing: f32,
    device: Device,
}

impl std::fmt::Debug for CodeTrainer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CodeTrainer").field("step", &self.step).finish_non_exhaustive()
    }
}

fn adam() -> ModuleOptimizer {
    crate::train::adam_with(0.9, 0.99)
}

fn freeze(model: VqModel) -> VqModel {
    let mut m = model;
    m.quant_conv = m.quant_conv.no_grad();
    m.quantize = m.quantize.no_grad();
    m.post_quant_conv = m.post_quant_conv.no_grad();
    m.decoder = m.decoder.no_grad();
    m
}

/// Median over codes of the squared distance to the nearest other code: the scale at which
/// `softmax(-d / tau)` starts to tell neighbouring codes apart (the initial `tau`).
pub fn codebook_spacing(model: &VqModel) -> Result<f32, ModelError> {
    let e = model.quantize.embedding.weight.val().detach();
    let [k, _] = e.dims();
    let d = to_host(squared_distances(e.clone(), e))?;
    let mut nn: Vec<f32> = (0..k)
        .map(|i| (0..k).filter(|&j| j != i).map(|j| d[i * k + j]).fold(f32::INFINITY, f32::min))
        .filter(|v| v.is_finite())
        .collect();
    if nn.is_empty() {
        return Err(ModelError::WeightsMismatch { problems: vec!["the codebook has fewer than two codes".into()] });
    }
    let mid = nn.len() / 2;
    nn.select_nth_unstable_by(mid, f32::total_cmp);
    Ok(nn[mid].max(1e-6))
}

/// One code per latent cell: in missing cells a draw from `softmax(logp)` (`T = 1`, as
/// generation samples), elsewhere the target code (what the decoder sees around a hole).
fn draw_codes(logp: &[f32], k: usize, targets: &[u32], missing: &[bool], rng: &mut ChaCha8Rng) -> Vec<u32> {
    let neg: Vec<f32> = logp.iter().map(|v| -v).collect();
    let sampling = Sampling::Temperature { temperature: 1.0, top_k: k };
    let drawn = select_codes(&neg, targets.len(), k, Some(missing), sampling, rng);
    drawn.iter().zip(targets).zip(missing).map(|((&d, &t), &m)| if m { d } else { t }).collect()
}

/// Colour agreement (mean absolute difference over the three packed colour channels, `[-1, 1]`
/// units) below which a drawn pixel counts as "the same kind of surface" as the target's.
pub const DEPTH_GATE_COLOUR: f32 = 0.1;

/// `pair` with the latent cells `cells` (row-major indices) revealed: their missing pixels
/// take `decoded`'s colour and depth (the decoder's pixels of the target codes, what generation
/// pastes for a committed cell) and count as observed. Observed pixels and the other cells are
/// unchanged; the targets stay the same.
pub fn reveal_cells(pair: &CodePair, decoded: &RgbdFrame, cells: &[usize], factor: usize) -> CodePair {
    let (w, h) = (pair.input.width() as usize, pair.input.height() as usize);
    let cw = w / factor.max(1);
    let mut out = pair.clone();
    for &i in cells {
        let (cy, cx) = (i / cw.max(1), i % cw.max(1));
        for y in cy * factor..((cy + 1) * factor).min(h) {
            for x in cx * factor..((cx + 1) * factor).min(w) {
                let p = y * w + x;
                if out.missing[p] {
                    out.input.colour.data[p] = decoded.colour.data[p];
                    out.input.depth_m.data[p] = decoded.depth_m.data[p];
                    out.missing[p] = false;
                }
            }
        }
    }
    out
}

/// `frames` drawn by `model` from their own nearest codes (encoder, argmin over the codebook,
/// decoder): the autoencoder's reconstruction.
pub fn autoencode(
    model: &VqModel,
    config: &ModelConfig,
    frames: &[&RgbdFrame],
    intrinsics: &[Intrinsics],
    device: &Device,
) -> Result<Vec<RgbdFrame>, ModelError> {
    let codes = target_codes(model, config, frames, intrinsics, device)?.concat();
    let f = config.downsample_factor();
    let [h, w] = frames.first().map_or([0, 0], |fr| [fr.height() as usize / f, fr.width() as usize / f]);
    let z = model.quantize.lookup(&codes, device);
    unpack(decode_rows(model, z, [frames.len(), h, w]), &config.depth)
}

/// The frozen decoder's output `[B, 4, H, W]` for codebook rows `[B h w, D]` (row-major cells)
/// of latent shape `[B, h, w]`.
pub(crate) fn decode_rows(model: &VqModel, rows: Tensor<2>, [b, h, w]: [usize; 3]) -> Tensor<4> {
    let [_, d] = rows.dims();
    model.decode(rows.reshape([b, h, w, d]).permute([0, 3, 1, 2]))
}

/// Disparity difference `[B, 1, H, W]` (drawn - target) and the depth term's pixel weights:
/// missing pixels where the drawn colour agrees with the target's to [`DEPTH_GATE_COLOUR`].
/// The gate keeps the depth term from punishing a drawn object where the target has ground (or
/// the reverse): that choice is the cross-entropy's to calibrate; the depth term only asks that
/// a surface drawn right is drawn at the right depth.
fn gated_disparity_diff(drawn: Tensor<4>, target: Tensor<4>, missing: Tensor<4>) -> (Tensor<4>, Tensor<4>) {
    let [b, _, h, w] = drawn.dims();
    let colour = |t: &Tensor<4>| t.clone().slice([0..b, 0..3, 0..h, 0..w]);
    let disparity = |t: Tensor<4>| t.slice([0..b, 3..4, 0..h, 0..w]);
    let agree = (colour(&drawn).detach() - colour(&target)).abs().mean_dim(1).lower_elem(DEPTH_GATE_COLOUR).float();
    (disparity(drawn) - disparity(target), agree * missing)
}

/// Missing pixels of a batch as `[B, 1, H, W]` (1 = missing).
fn pixel_mask(batch: &[CodePair], dev: &Device) -> Tensor<4> {
    let (h, w) = (batch[0].input.height() as usize, batch[0].input.width() as usize);
    let values: Vec<f32> = batch.iter().flat_map(|p| p.missing.iter().map(|&m| m as u8 as f32)).collect();
    Tensor::from_data(TensorData::new(values, [batch.len(), 1, h, w]), dev)
}

/// Widens a 5-channel mask-fusion `conv_in.weight` `[4, 5, 1, 1]` to `channels` inputs with zero
/// weights on the new (ray) channels, so a model trained without them starts out unchanged.
pub fn widen_conv_in(tensors: &mut std::collections::BTreeMap<String, NamedTensor>, channels: usize) {
    let Some(t) = tensors.get_mut("conv_in.weight") else { return };
    let (out, inp) = (t.shape[0], t.shape.get(1).copied().unwrap_or(0));
    if inp >= channels || out == 0 {
        return;
    }
    let mut values = vec![0.0f32; out * channels];
    for o in 0..out {
        values[o * channels..o * channels + inp].copy_from_slice(&t.values[o * inp..(o + 1) * inp]);
    }
    *t = NamedTensor { shape: vec![out, channels, 1, 1], values };
}

/// Initial temperature of a code head, in codebook spacings (see [`CodeTrainer::new`]).
pub const HEAD_INIT_SPACINGS: f32 = 16.0;

/// Weights of a code head equal to the distance logits `-||quant_conv(h) - e_k||^2 / tau` up to
/// a per-cell constant (which softmax ignores): with `quant_conv(h) = Q h + q`, the logit of
/// code `k` is `(2 e_k . (Q h + q) - ||e_k||^2) / tau`, i.e. weight `2 e_k Q / tau` and bias
/// `(2 e_k . q - ||e_k||^2) / tau`. Adds `code_head.weight` `[K, z, 1, 1]` and
/// `code_head.bias` `[K]` to `tensors`.
pub fn head_from_codebook(
    tensors: &mut std::collections::BTreeMap<String, NamedTensor>,
    tau: f32,
) -> Result<(), ModelError> {
    let get = |name: &str| tensors.get(name).cloned().ok_or_else(|| ModelError::MissingTensor(name.to_string()));
    let (e, q, qb) = (get("quantize.embedding.weight")?, get("quant_conv.weight")?, get("quant_conv.bias")?);
    let (k, d) = (e.shape[0], e.shape[1]);
    let z = q.shape.get(1).copied().unwrap_or(0);
    if q.shape[0] != d || qb.values.len() != d || q.values.len() != d * z {
        return Err(ModelError::WeightsMismatch {
            problems: vec![format!("quant_conv {:?} does not match the codebook {:?}", q.shape, e.shape)],
        });
    }
    let mut w = vec![0.0f32; k * z];
    let mut b = vec![0.0f32; k];
    for c in 0..k {
        let ec = &e.values[c * d..(c + 1) * d];
        for j in 0..z {
            w[c * z + j] = 2.0 * (0..d).map(|i| ec[i] * q.values[i * z + j]).sum::<f32>() / tau;
        }
        let dot: f32 = (0..d).map(|i| ec[i] * qb.values[i]).sum();
        let norm: f32 = ec.iter().map(|x| x * x).sum();
        b[c] = (2.0 * dot - norm) / tau;
    }
    tensors.insert("code_head.weight".into(), NamedTensor { shape: vec![k, z, 1, 1], values: w });
    tensors.insert("code_head.bias".into(), NamedTensor { shape: vec![k], values: b });
    Ok(())
}

impl CodeTrainer {
    /// A new session warm-started from `init` (weights of a trained model, typically the
    /// stage-1 / stage-2 model whose codebook and decoder are kept). `model_config` may add
    /// ray channels to `init`'s architecture; everything else must match.
    pub fn new(
        model_config: &ModelConfig,
        init: &std::collections::BTreeMap<String, NamedTensor>,
        train_config: &CodeTrainConfig,
    ) -> Result<Self, ModelError> {
        let device = crate::default_device();
        let mut tensors = init.clone();
        widen_conv_in(&mut tensors, model_config.input_channels());
        if model_config.code_head && !tensors.contains_key("code_head.weight") {
            // start from the distance logits, softened: at the codebook's own spacing they are
            // so sharp that the missing cells' cross-entropy starts above 40 nats, and the
            // distance-logit run's tau grew by 15x in its first 400 steps
            let base = load_named(
                VqModel::new(&ModelConfig { code_head: false, ..model_config.clone() }, 0, &device)?,
                &tensors,
                false,
                true,
            )?;
            head_from_codebook(&mut tensors, HEAD_INIT_SPACINGS * codebook_spacing(&base)?)?;
        }
        let model = load_named(VqModel::new(model_config, train_config.seed, &device)?, &tensors, false, false)?;
        let spacing = codebook_spacing(&model)?;
        let tau = model_config.code_tau.unwrap_or(spacing);
        let model = freeze(model).train();
        Ok(Self {
            model_config: model_config.clone(),
            train_config: train_config.clone(),
            model,
            temperature: CodeTemperature::new(tau, &device).train(),
            optim: adam(),
            optim_tau: adam(),
            step: 0,
            rng: ChaCha8Rng::seed_from_u64(train_config.seed),
            spacing,
            device,
        })
    }

    /// The current code temperature `tau`.
    pub fn tau(&self) -> Result<f32, ModelError> {
        self.temperature.tau()
    }

    /// The model config with the current `tau` as `code_tau` (what saved weights carry; 1 for
    /// a model with a code head, whose logits carry their own scale).
    pub fn exported_config(&self) -> Result<ModelConfig, ModelError> {
        let tau = if self.model_config.code_head { 1.0 } else { self.tau()? };
        Ok(ModelConfig { code_tau: Some(tau), ..self.model_config.clone() })
    }

    fn batch_tensors(
        &self,
        batch: &[CodePair],
        device: &Device,
    ) -> Result<(Tensor<4>, Vec<u32>, Vec<bool>), ModelError> {
        let f = self.model_config.downsample_factor();
        let inputs: Vec<&RgbdFrame> = batch.iter().map(|p| &p.input).collect();
        let masks: Vec<Option<&[bool]>> = batch.iter().map(|p| Some(p.missing.as_slice())).collect();
        let intr: Vec<Intrinsics> = batch.iter().map(|p| p.intrinsics).collect();
        let x = pack_input(&inputs, &masks, &intr, &self.model_config, device)?;
        let mut codes = Vec::new();
        let mut miss = Vec::new();
        for p in batch {
            let (w, h) = (p.input.width() as usize, p.input.height() as usize);
            if p.codes.len() != (w / f) * (h / f) || w % f != 0 || h % f != 0 {
                return Err(ModelError::shape(
                    "a pair's target codes",
                    format!("{} for {w}x{h} pixels (a multiple of {f})", (w / f) * (h / f)),
                    p.codes.len(),
                ));
            }
            if let Some(&bad) = p.codes.iter().find(|&&c| c as usize >= self.model_config.n_embed) {
                return Err(ModelError::shape("a target code", format!("below {}", self.model_config.n_embed), bad));
            }
            codes.extend_from_slice(&p.codes);
            miss.extend(missing_cells(&p.missing, w, h, f, self.train_config.missing_cell_threshold));
        }
        Ok((x, codes, miss))
    }

    /// Per-cell log-probabilities `[N, K]` of the codes and the loss weights, on `device`.
    fn forward(&self, model: &VqModel, x: Tensor<4>, log_tau: Tensor<1>) -> Tensor<2> {
        if let Some(logits) = model.code_logits(x.clone()) {
            let [b, k, h, w] = logits.dims();
            return log_softmax(logits.permute([0, 2, 3, 1]).reshape([b * h * w, k]), 1);
        }
        let z = model.encode(x);
        let [b, d, h, w] = z.dims();
        let rows = z.permute([0, 2, 3, 1]).reshape([b * h * w, d]);
        let e = model.quantize.embedding.weight.val().detach();
        let inv_tau = log_tau.neg().exp().reshape([1, 1]);
        log_softmax(squared_distances(rows, e).neg() * inv_tau, 1)
    }

    /// Per-cell `sum_k q_k log p_k` `[N, 1]` for the (soft) targets `q` around `codes`.
    fn target_log_likelihood(&self, logp: Tensor<2>, codes: &[u32], dev: &Device) -> Tensor<2> {
        let n = codes.len();
        let idx: Vec<i64> = codes.iter().map(|&c| c as i64).collect();
        if self.train_config.target_smoothing <= 0.0 {
            let idx = Tensor::<2, Int>::from_data(TensorData::new(idx, [n, 1]), dev);
            return logp.gather(1, idx);
        }
        let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [n]), dev);
        let e = self.model.quantize.embedding.weight.val().detach();
        let rows = e.clone().select(0, idx);
        let scale = 1.0 / (self.train_config.target_smoothing * self.spacing);
        let q = softmax(squared_distances(rows, e).neg().mul_scalar(scale), 1);
        (q * logp).sum_dim(1)
    }

    /// `[batch, latent rows, latent columns]` of a batch of equal-size pairs.
    fn latent_shape(&self, batch: &[CodePair]) -> [usize; 3] {
        let f = self.model_config.downsample_factor();
        let first = &batch[0].input;
        [batch.len(), first.height() as usize / f, first.width() as usize / f]
    }

    fn report(&self, logp: &[f32], codes: &[u32], miss: &[bool]) -> CodeReport {
        let k = self.model_config.n_embed;
        let mut r = CodeReport::default();
        let (mut nm, mut no) = (0usize, 0usize);
        for (i, row) in logp.chunks_exact(k).enumerate() {
            let t = codes[i] as usize;
            let best = row
                .iter()
                .enumerate()
                .fold((0usize, f32::NEG_INFINITY), |a, (j, &v)| if v > a.1 { (j, v) } else { a })
                .0;
            if miss[i] {
                nm += 1;
                r.ce_missing -= row[t];
                r.acc_missing += (best == t) as u8 as f32;
            } else {
                no += 1;
                r.ce_observed -= row[t];
                r.acc_observed += (best == t) as u8 as f32;
            }
        }
        let norm = |v: &mut f32, n: usize| *v = if n > 0 { *v / n as f32 } else { f32::NAN };
        norm(&mut r.ce_missing, nm);
        norm(&mut r.acc_missing, nm);
        norm(&mut r.ce_observed, no);
        norm(&mut r.acc_observed, no);
        r.missing_cells = nm;
        r
    }

    /// MaskGIT training: each pair, with probability [`CodeTrainConfig::reveal`], gets a random
    /// share of its missing cells revealed with the decoded target codes.
    fn reveal_batch(&mut self, batch: &[CodePair]) -> Result<Vec<CodePair>, ModelError> {
        let f = self.model_config.downsample_factor();
        let threshold = self.train_config.missing_cell_threshold;
        let mut out = batch.to_vec();
        let mut chosen: Vec<(usize, Vec<usize>)> = Vec::new();
        for (b, p) in batch.iter().enumerate() {
            if self.rng.random::<f32>() >= self.train_config.reveal {
                continue;
            }
            let (w, h) = (p.input.width() as usize, p.input.height() as usize);
            let mut open: Vec<usize> = missing_cells(&p.missing, w, h, f, threshold)
                .iter()
                .enumerate()
                .filter(|c| *c.1)
                .map(|c| c.0)
                .collect();
            let u: f32 = self.rng.random();
            let n = (((1.0 - (std::f32::consts::FRAC_PI_2 * u).cos()) * open.len() as f32) as usize)
                .min(open.len().saturating_sub(1));
            if n == 0 {
                continue;
            }
            open.shuffle(&mut self.rng);
            open.truncate(n);
            chosen.push((b, open));
        }
        if chosen.is_empty() {
            return Ok(out);
        }
        let model = self.model.valid();
        let picked: Vec<CodePair> = chosen.iter().map(|(b, _)| batch[*b].clone()).collect();
        let codes: Vec<u32> = picked.iter().flat_map(|p| p.codes.iter().copied()).collect();
        let shape = self.latent_shape(&picked);
        let decoded =
            unpack(decode_rows(&model, model.quantize.lookup(&codes, &self.device), shape), &self.model_config.depth)?;
        for ((b, cells), d) in chosen.iter().zip(&decoded) {
            out[*b] = reveal_cells(&batch[*b], d, cells, f);
        }
        Ok(out)
    }

    /// One optimisation step on `batch` (all pairs the same size).
    pub fn step_on(&mut self, batch: &[CodePair]) -> Result<CodeReport, ModelError> {
        if batch.is_empty() {
            return Err(ModelError::EmptyBatch("sampler training step"));
        }
        let revealed;
        let batch = if self.train_config.reveal > 0.0 {
            revealed = self.reveal_batch(batch)?;
            revealed.as_slice()
        } else {
            batch
        };
        let dev = self.device.clone().autodiff();
        let (x, codes, miss) = self.batch_tensors(batch, &dev)?;
        let n = codes.len();
        let logp = self.forward(&self.model, x, self.temperature.log_tau.val());
        let (nm, no) = (miss.iter().filter(|m| **m).count(), miss.iter().filter(|m| !**m).count());
        // per-cell weights: missing cells average to 1, observed cells to observed_weight
        let w: Vec<f32> = miss
            .iter()
            .map(|&m| if m { 1.0 / nm.max(1) as f32 } else { self.train_config.observed_weight / no.max(1) as f32 })
            .collect();
        let w = Tensor::<2>::from_data(TensorData::new(w, [n, 1]), &dev);
        let mut loss = (self.target_log_likelihood(logp.clone(), &codes, &dev) * w).sum().neg();
        let host = to_host(logp.clone().detach())?;
        let mut depth_stats = (None, None);
        if self.train_config.depth_weight > 0.0 {
            let k = self.model_config.n_embed;
            let drawn = draw_codes(&host, k, &codes, &miss, &mut self.rng);
            let mut onehot = vec![0.0f32; n * k];
            for (i, &c) in drawn.iter().enumerate() {
                onehot[i * k + c as usize] = 1.0;
            }
            let onehot = Tensor::<2>::from_data(TensorData::new(onehot, [n, k]), &dev);
            let rows_missing: Vec<f32> = miss.iter().map(|&m| m as u8 as f32).collect();
            let rows_missing = Tensor::<2>::from_data(TensorData::new(rows_missing, [n, 1]), &dev);
            // straight-through: the forward pass decodes the drawn codes, the gradient reaches
            // the logits through the probabilities (missing cells only)
            let p = logp.exp();
            let st = onehot + (p.clone() - p.detach()) * rows_missing;
            let e = self.model.quantize.embedding.weight.val().detach();
            let shape = self.latent_shape(batch);
            let drawn_out = decode_rows(&self.model, st.matmul(e), shape);
            let target_out = decode_rows(&self.model, self.model.quantize.lookup(&codes, &dev), shape).detach();
            let (diff, gate) = gated_disparity_diff(drawn_out, target_out, pixel_mask(batch, &dev));
            let count = to_host(gate.clone().sum())?[0];
            let l1 = (diff.clone().abs() * gate.clone()).sum().div_scalar(count.max(1.0));
            let bias = (diff.detach() * gate).sum().div_scalar(count.max(1.0));
            if count > 0.0 {
                depth_stats = (Some(to_host(l1.clone().detach())?[0]), Some(to_host(bias)?[0]));
                loss = loss + l1.mul_scalar(self.train_config.depth_weight);
            }
        }
        let loss_value = to_host(loss.clone().detach())?.first().copied().unwrap_or(f32::NAN);
        if !loss_value.is_finite() {
            return Err(ModelError::Diverged { loss: loss_value, step: self.step + 1 });
        }
        let mut grads = loss.backward();
        let lr = self.train_config.lr_at(self.step);
        let g_model = GradientsParams::from_module(&mut grads, &self.model);
        let g_tau = GradientsParams::from_module(&mut grads, &self.temperature);
        self.model = self.optim.step(lr, self.model.clone(), g_model);
        self.temperature = self.optim_tau.step(lr * self.train_config.tau_lr_scale, self.temperature.clone(), g_tau);
        self.step += 1;
        let mut r = self.report(&host, &codes, &miss);
        r.step = self.step;
        r.loss = loss_value;
        r.tau = self.tau()?;
        (r.depth_l1_missing, r.depth_bias_missing) = depth_stats;
        Ok(r)
    }

    /// Cross-entropy and accuracy on held-out pairs (inference mode, no update).
    pub fn evaluate(&self, pairs: &[CodePair], batch: usize) -> Result<CodeReport, ModelError> {
        let model = self.model.valid();
        let log_tau = self.temperature.valid().log_tau.val();
        let (mut logp, mut codes, mut miss) = (Vec::new(), Vec::new(), Vec::new());
        // depth of codes drawn at T = 1, from a fixed stream so that evaluations compare
        let mut rng = ChaCha8Rng::seed_from_u64(0x5eed_de97);
        let (mut l1, mut bias, mut count) = (0.0f64, 0.0f64, 0.0f64);
        let k = self.model_config.n_embed;
        for chunk in pairs.chunks(batch.max(1)) {
            let (x, c, m) = self.batch_tensors(chunk, &self.device)?;
            let lp = to_host(self.forward(&model, x, log_tau.clone()))?;
            let drawn = draw_codes(&lp, k, &c, &m, &mut rng);
            let shape = self.latent_shape(chunk);
            let drawn_out = decode_rows(&model, model.quantize.lookup(&drawn, &self.device), shape);
            let target_out = decode_rows(&model, model.quantize.lookup(&c, &self.device), shape);
            let (diff, gate) = gated_disparity_diff(drawn_out, target_out, pixel_mask(chunk, &self.device));
            count += to_host(gate.clone().sum())?[0] as f64;
            l1 += to_host((diff.clone().abs() * gate.clone()).sum())?[0] as f64;
            bias += to_host((diff * gate).sum())?[0] as f64;
            logp.extend(lp);
            codes.extend(c);
            miss.extend(m);
        }
        let mut r = self.report(&logp, &codes, &miss);
        r.tau = self.tau()?;
        let per = |v: f64| (count > 0.0).then(|| (v / count) as f32);
        (r.depth_l1_missing, r.depth_bias_missing) = (per(l1), per(bias));
        Ok(r)
    }

    /// Commits the checkpoint folder `run_dir/ckpt` as a whole, with a manifest of sizes and
    /// CRC-32s ([`crate::checkpoint::commit_folder`]); `model.safetensors` carries the current
    /// `tau` in its embedded config.
    pub fn save(&self, run_dir: &Path) -> Result<(), ModelError> {
        let config = self.exported_config()?;
        let meta = crate::refiner::weight_metadata(&config)?;
        let weights =
            crate::params::to_safetensors_bytes(&named_tensors(&self.model), WeightPrecision::F32, Some(meta))?;
        let optim = self.optim.into_bytes().map_err(|e| ModelError::state("optimizer", e))?;
        let optim_tau = self.optim_tau.into_bytes().map_err(|e| ModelError::state("optimizer", e))?;
        let (rng_seed, rng_stream, rng_word_pos) = crate::checkpoint::rng_position(&self.rng);
        let state = CodeState {
            version: STATE_VERSION,
            model_config: self.model_config.clone(),
            train_config: self.train_config.clone(),
            step: self.step,
            log_tau: self.temperature.log()?,
            rng_seed,
            rng_stream,
            rng_word_pos,
        };
        let json = serde_json::to_vec_pretty(&state).map_err(|e| ModelError::state("state", e))?;
        crate::checkpoint::commit_folder(run_dir, "ckpt", |dir| {
            write_atomic(&dir.join("model.safetensors"), &weights)?;
            write_atomic(&dir.join("optim.bpk"), &optim)?;
            write_atomic(&dir.join("optim_tau.bpk"), &optim_tau)?;
            write_atomic(&dir.join("state.json"), &json)
        })?;
        Ok(())
    }

    /// The committed checkpoint folder to resume from (`run_dir/ckpt`, or `ckpt.old` when a
    /// commit was interrupted between its two renames); `None` when the run has none.
    pub fn checkpoint_dir(run_dir: &Path) -> Option<std::path::PathBuf> {
        crate::checkpoint::committed_folder(run_dir, "ckpt")
    }

    /// Resumes from `run_dir`'s checkpoint (manifest verified first); `steps` (and
    /// `lr_decay_from` when given) override the stored values.
    pub fn resume(run_dir: &Path, steps: Option<u64>, lr_decay_from: Option<u64>) -> Result<Self, ModelError> {
        let dir = Self::checkpoint_dir(run_dir)
            .ok_or_else(|| ModelError::checkpoint(run_dir, "no committed checkpoint (ckpt/ with a manifest)"))?;
        crate::checkpoint::verify_folder(&dir)?;
        let (state, tensors): (CodeState, _) =
            crate::checkpoint::read_trainer_state(&dir, "generative stage-2", STATE_VERSION)?;
        if !state.log_tau.is_finite() {
            return Err(ModelError::checkpoint(&dir.join("state.json"), format!("log_tau is {}", state.log_tau)));
        }
        let mut train_config = state.train_config;
        if let Some(s) = steps {
            train_config.steps = s;
        }
        if lr_decay_from.is_some() {
            train_config.lr_decay_from = lr_decay_from;
        }
        let mut t = Self::new(&state.model_config, &tensors, &train_config)?;
        let optim = dir.join("optim.bpk");
        t.optim = crate::train::load_optimizer(&optim, |p| adam().load(p))?;
        let optim_tau = dir.join("optim_tau.bpk");
        t.optim_tau = crate::train::load_optimizer(&optim_tau, |p| adam().load(p))?;
        t.temperature = CodeTemperature::from_log(state.log_tau, &t.device).train();
        t.step = state.step;
        t.rng = crate::checkpoint::rng_at(state.rng_seed, state.rng_stream, state.rng_word_pos);
        Ok(t)
    }

    /// Named f32 weights of the model (for tests comparing frozen parts).
    pub fn weights(&self) -> std::collections::BTreeMap<String, NamedTensor> {
        named_tensors(&self.model)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `[1, 4, 1, 4]` packed output from per-pixel (grey level, disparity).
    fn out(px: [(f32, f32); 4], dev: &Device) -> Tensor<4> {
        let mut v = vec![0.0f32; 16];
        for (i, (c, d)) in px.iter().enumerate() {
            for ch in 0..3 {
                v[ch * 4 + i] = *c;
            }
            v[12 + i] = *d;
        }
        Tensor::from_data(TensorData::new(v, [1, 4, 1, 4]), dev)
    }

    #[test]
    fn the_depth_term_counts_only_missing_pixels_drawn_as_the_targets_kind_of_surface() {
        let dev = crate::default_device();
        // pixel 0: same grey, drawn 0.2 nearer; 1: same grey within the gate, drawn 0.1 farther;
        // 2: an object's colour where the target is ground; 3: same surface but observed
        let drawn = out([(0.3, 0.5), (0.3 + 0.9 * DEPTH_GATE_COLOUR, 0.2), (-0.8, 0.9), (0.3, 0.7)], &dev);
        let target = out([(0.3, 0.3), (0.3, 0.3), (0.3, 0.3), (0.3, 0.3)], &dev);
        let missing = Tensor::<4>::from_data(TensorData::new(vec![1.0f32, 1.0, 1.0, 0.0], [1, 1, 1, 4]), &dev);
        let (diff, gate) = gated_disparity_diff(drawn, target, missing);
        let diff = to_host(diff).unwrap();
        let gate = to_host(gate).unwrap();
        assert_eq!(gate, vec![1.0, 1.0, 0.0, 0.0]);
        let expect = [0.2f32, -0.1, 0.6, 0.4];
        for (d, e) in diff.iter().zip(expect) {
            assert!((d - e).abs() < 1e-6, "{diff:?} vs {expect:?}");
        }
    }

    #[test]
    fn draws_keep_the_targets_in_observed_cells_and_follow_the_probabilities_in_missing_ones() {
        // two cells, three codes: cell 0 observed (target 2), cell 1 missing with p = (0, 0.8, 0.2)
        let ln = |p: f32| p.max(1e-30).ln();
        let logp = [ln(1.0 / 3.0), ln(1.0 / 3.0), ln(1.0 / 3.0), ln(0.0), ln(0.8), ln(0.2)];
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let n = 2000;
        let mut ones = 0;
        for _ in 0..n {
            let d = draw_codes(&logp, 3, &[2, 0], &[false, true], &mut rng);
            assert_eq!(d[0], 2);
            assert_ne!(d[1], 0, "a code of probability 0 was drawn");
            ones += (d[1] == 1) as usize;
        }
        // binomial sd at n = 2000, p = 0.8: 0.009; 4 sd
        let share = ones as f32 / n as f32;
        assert!((share - 0.8).abs() < 0.036, "code 1 drawn {share}");
    }
}
