//! Decoder fine-tuning on whole frames: the frozen codes of full-size clean frames are decoded
//! and only `post_quant_conv` and the decoder train.
//!
//! Why: stage 1 trains the decoder on crops (128 px of 256), whose borders fall at every depth
//! of the frame. At a *frame's* border (where generation always decodes) the decoder therefore
//! cannot tell how far the ground is and decodes it towards the mean: on clean frames' own
//! codes the top rows' ground came out 0.45-0.5 m too near at 13.7 m, and the top and side
//! borders are exactly where the zig-zag adds each step's new strip, so the generated ground
//! rose step after step. Decoding whole frames lets the decoder learn the frame border (its
//! zero padding) as a position cue, as it is used at inference.
//!
//! The encoder, codebook and code head are untouched, so the code distribution a sampler
//! learned stays valid: only what the codes decode to improves. Checkpoints are one folder,
//! `RUN/ckpt`, committed as a whole with a manifest ([`crate::checkpoint`]).

use std::path::Path;

use burn::module::Module;
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};
use sgam_core::{Intrinsics, RgbdFrame};

use crate::config::ModelConfig;
use crate::generative::{decode_rows, target_codes};
use crate::model::VqModel;
use crate::packing::{pack_target, unpack};
use crate::params::{load_named, named_tensors, save_safetensors, NamedTensor, WeightPrecision};
use crate::quantize::to_host;
use crate::ModelError;

/// Hyper-parameters of a decoder fine-tune (stored in every checkpoint).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecoderTuneConfig {
    /// Total optimisation steps.
    pub steps: u64,
    /// Adam learning rate.
    pub lr: f64,
    /// Half-cosine decay from `lr` to 5 % of it between this step and `steps` (None: constant).
    pub lr_decay_from: Option<u64>,
    /// Weight of the L1 on the disparity channel relative to the colour L1.
    pub depth_weight: f32,
}

impl DecoderTuneConfig {
    /// Learning rate after `step` steps.
    pub fn lr_at(&self, step: u64) -> f64 {
        crate::train::half_cosine_lr(self.lr, self.steps, self.lr_decay_from, step)
    }
}

/// Losses of one step or of an evaluation pass.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DecoderReport {
    /// Step number after a training step; 0 for evaluation.
    pub step: u64,
    /// Mean L1 of the colour channels (packed units, `[-1, 1]`).
    pub l1_colour: f32,
    /// Mean L1 of the disparity channel over valid depth (packed units).
    pub l1_disparity: f32,
    /// Mean signed depth error (decoded - true, metres) over the top `BORDER_ROWS` rows where
    /// depth is valid: negative = the far edge decoded too near.
    pub top_rows_bias_m: f32,
    /// Mean absolute depth error (metres) over all valid pixels.
    pub depth_mae_m: f32,
    /// The weighted loss.
    pub loss: f32,
}

/// Rows at the frame's top edge whose bias [`DecoderReport::top_rows_bias_m`] reports.
pub const BORDER_ROWS: usize = 16;

#[derive(Debug, Serialize, Deserialize)]
struct TuneState {
    version: u32,
    model_config: ModelConfig,
    config: DecoderTuneConfig,
    step: u64,
}

const STATE_VERSION: u32 = 1;

/// A decoder fine-tuning session.
pub struct DecoderTuner {
    /// Architecture of the tuned model (saved in its weights).
    pub model_config: ModelConfig,
    /// Hyper-parameters.
    pub config: DecoderTuneConfig,
    /// The model (autodiff; only `post_quant_conv` and `decoder` require gradients).
    pub model: VqModel,
    encoder: VqModel,
    encoder_config: ModelConfig,
    optim: ModuleOptimizer,
    /// Completed steps.
    pub step: u64,
    device: Device,
}

impl std::fmt::Debug for DecoderTuner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DecoderTuner").field("step", &self.step).finish_non_exhaustive()
    }
}

fn adam() -> ModuleOptimizer {
    crate::train::adam_with(0.9, 0.99)
}

fn freeze_all_but_decoder(model: VqModel) -> VqModel {
    let mut m = model;
    m.conv_in = m.conv_in.no_grad();
    m.encoder = m.encoder.no_grad();
    m.quant_conv = m.quant_conv.no_grad();
    m.quantize = m.quantize.no_grad();
    m.code_head = m.code_head.map(|h| h.no_grad());
    m
}

impl DecoderTuner {
    /// A new session: `tensors` (with `model_config`) is the model whose decoder is tuned;
    /// `encoder` (with `encoder_config`) gives the codes and must share its codebook.
    pub fn new(
        model_config: &ModelConfig,
        tensors: &std::collections::BTreeMap<String, NamedTensor>,
        encoder: VqModel,
        encoder_config: &ModelConfig,
        config: &DecoderTuneConfig,
    ) -> Result<Self, ModelError> {
        let device = crate::default_device();
        let model = load_named(VqModel::new(model_config, 0, &device)?, tensors, false, false)?;
        let (a, b) =
            (to_host(model.quantize.embedding.weight.val())?, to_host(encoder.quantize.embedding.weight.val())?);
        if a.len() != b.len() || a.iter().zip(&b).any(|(x, y)| (x - y).abs() > 1e-3 * y.abs().max(1.0)) {
            return Err(ModelError::WeightsMismatch {
                problems: vec![
                    "the encoder's codebook differs from the tuned model's: its codes would decode to other pixels"
                        .into(),
                ],
            });
        }
        Ok(Self {
            model_config: model_config.clone(),
            config: config.clone(),
            model: freeze_all_but_decoder(model).train(),
            encoder: encoder.valid(),
            encoder_config: encoder_config.clone(),
            optim: adam(),
            step: 0,
            device,
        })
    }

    fn codes(&self, frames: &[&RgbdFrame], intrinsics: &[Intrinsics]) -> Result<Vec<u32>, ModelError> {
        Ok(target_codes(&self.encoder, &self.encoder_config, frames, intrinsics, &self.device)?.concat())
    }

    fn latent_shape(&self, frames: &[&RgbdFrame]) -> Result<[usize; 3], ModelError> {
        let f = self.model_config.downsample_factor();
        let (w, h) = (frames[0].width() as usize, frames[0].height() as usize);
        if w % f != 0 || h % f != 0 || frames.iter().any(|x| x.width() as usize != w || x.height() as usize != h) {
            return Err(ModelError::shape(
                "the frames of one batch",
                format!("one size, a multiple of {f} pixels"),
                format!("{w}x{h} first"),
            ));
        }
        Ok([frames.len(), h / f, w / f])
    }

    /// Loss terms of decoding `frames`' codes with `model`: (loss, colour L1, disparity L1, output).
    fn losses(
        &self,
        model: &VqModel,
        frames: &[&RgbdFrame],
        codes: &[u32],
        dev: &Device,
    ) -> Result<(Tensor<1>, Tensor<1>, Tensor<1>, Tensor<4>), ModelError> {
        let shape = self.latent_shape(frames)?;
        let out = decode_rows(model, model.quantize.lookup(codes, dev).detach(), shape);
        let target = pack_target(frames, &self.model_config.depth, dev)?;
        let [b, _, h, w] = out.dims();
        let colour = |t: Tensor<4>| t.slice([0..b, 0..3, 0..h, 0..w]);
        let disparity = |t: Tensor<4>| t.slice([0..b, 3..4, 0..h, 0..w]);
        let valid = disparity(target.clone()).greater_elem(-1.5).float();
        let l1_colour = (colour(out.clone()) - colour(target.clone())).abs().mean();
        let n = valid.clone().sum().clamp_min(1.0);
        let l1_disparity = ((disparity(out.clone()) - disparity(target)).abs() * valid).sum() / n;
        let loss = l1_colour.clone() + l1_disparity.clone().mul_scalar(self.config.depth_weight);
        Ok((loss, l1_colour, l1_disparity, out))
    }

    fn depth_errors(&self, out: Tensor<4>, frames: &[&RgbdFrame]) -> Result<(f32, f32), ModelError> {
        let decoded = unpack(out.detach(), &self.model_config.depth)?;
        let (mut top, mut nt, mut all, mut na) = (0.0f64, 0usize, 0.0f64, 0usize);
        for (d, t) in decoded.iter().zip(frames) {
            let w = t.width() as usize;
            for (i, (&a, &b)) in d.depth_m.data.iter().zip(&t.depth_m.data).enumerate() {
                if !sgam_core::is_valid_depth(b) {
                    continue;
                }
                all += (a - b).abs() as f64;
                na += 1;
                if i / w < BORDER_ROWS {
                    top += (a - b) as f64;
                    nt += 1;
                }
            }
        }
        Ok(((top / nt.max(1) as f64) as f32, (all / na.max(1) as f64) as f32))
    }

    /// One optimisation step on whole clean frames (all the same size).
    pub fn step_on(&mut self, frames: &[&RgbdFrame], intrinsics: &[Intrinsics]) -> Result<DecoderReport, ModelError> {
        if frames.is_empty() {
            return Err(ModelError::EmptyBatch("decoder tuning step"));
        }
        let codes = self.codes(frames, intrinsics)?;
        let dev = self.device.clone().autodiff();
        let (loss, l1c, l1d, out) = self.losses(&self.model, frames, &codes, &dev)?;
        let value = to_host(loss.clone().detach())?[0];
        if !value.is_finite() {
            return Err(ModelError::Diverged { loss: value, step: self.step + 1 });
        }
        let mut grads = loss.backward();
        let g = GradientsParams::from_module(&mut grads, &self.model);
        self.model = self.optim.step(self.config.lr_at(self.step), self.model.clone(), g);
        self.step += 1;
        let (top, mae) = self.depth_errors(out, frames)?;
        Ok(DecoderReport {
            step: self.step,
            l1_colour: to_host(l1c.detach())?[0],
            l1_disparity: to_host(l1d.detach())?[0],
            top_rows_bias_m: top,
            depth_mae_m: mae,
            loss: value,
        })
    }

    /// Losses on held-out frames (no update), in batches of `batch`.
    pub fn evaluate(
        &self,
        frames: &[RgbdFrame],
        intrinsics: &[Intrinsics],
        batch: usize,
    ) -> Result<DecoderReport, ModelError> {
        let model = self.model.valid();
        let mut sum = DecoderReport::default();
        let mut n = 0.0f32;
        for (chunk, k) in frames.chunks(batch.max(1)).zip(intrinsics.chunks(batch.max(1))) {
            let refs: Vec<&RgbdFrame> = chunk.iter().collect();
            let codes = self.codes(&refs, k)?;
            let (loss, l1c, l1d, out) = self.losses(&model, &refs, &codes, &self.device)?;
            let (top, mae) = self.depth_errors(out, &refs)?;
            let w = refs.len() as f32;
            sum.loss += to_host(loss)?[0] * w;
            sum.l1_colour += to_host(l1c)?[0] * w;
            sum.l1_disparity += to_host(l1d)?[0] * w;
            sum.top_rows_bias_m += top * w;
            sum.depth_mae_m += mae * w;
            n += w;
        }
        let n = n.max(1.0);
        Ok(DecoderReport {
            step: self.step,
            loss: sum.loss / n,
            l1_colour: sum.l1_colour / n,
            l1_disparity: sum.l1_disparity / n,
            top_rows_bias_m: sum.top_rows_bias_m / n,
            depth_mae_m: sum.depth_mae_m / n,
        })
    }

    /// Writes `run_dir/ckpt` (model with its config embedded, optimizer, state) as a whole,
    /// with a manifest of sizes and CRC-32s ([`crate::checkpoint::commit_folder`]).
    pub fn save(&self, run_dir: &Path) -> Result<(), ModelError> {
        crate::checkpoint::commit_folder(run_dir, "ckpt", |new| {
            let meta = crate::refiner::weight_metadata(&self.model_config)?;
            save_safetensors(&self.model, &new.join("model.safetensors"), WeightPrecision::F32, Some(meta))?;
            let bytes = self.optim.into_bytes().map_err(|e| ModelError::state("optimizer", e))?;
            crate::params::write_atomic(&new.join("optim.bpk"), &bytes)?;
            let state = TuneState {
                version: STATE_VERSION,
                model_config: self.model_config.clone(),
                config: self.config.clone(),
                step: self.step,
            };
            let json = serde_json::to_vec_pretty(&state).map_err(|e| ModelError::state("state", e))?;
            crate::params::write_atomic(&new.join("state.json"), &json)
        })?;
        Ok(())
    }

    /// The committed checkpoint folder to resume from (`ckpt`, or `ckpt.old` after a save
    /// interrupted between its renames); `None` when the run has none.
    pub fn checkpoint_dir(run_dir: &Path) -> Option<std::path::PathBuf> {
        crate::checkpoint::committed_folder(run_dir, "ckpt")
    }

    /// Resumes from `run_dir`'s checkpoint; `steps` overrides the stored total.
    pub fn resume(
        run_dir: &Path,
        encoder: VqModel,
        encoder_config: &ModelConfig,
        steps: Option<u64>,
    ) -> Result<Self, ModelError> {
        let dir = Self::checkpoint_dir(run_dir)
            .ok_or_else(|| ModelError::checkpoint(run_dir, "no checkpoint (ckpt/state.json)"))?;
        crate::checkpoint::verify_folder(&dir)?;
        let (state, tensors): (TuneState, _) =
            crate::checkpoint::read_trainer_state(&dir, "decoder-tuning", STATE_VERSION)?;
        let mut config = state.config;
        if let Some(s) = steps {
            config.steps = s;
        }
        let mut t = Self::new(&state.model_config, &tensors, encoder, encoder_config, &config)?;
        let optim = dir.join("optim.bpk");
        t.optim = crate::train::load_optimizer(&optim, |p| adam().load(p))?;
        t.step = state.step;
        Ok(t)
    }

    /// Named f32 weights of the tuned model.
    pub fn weights(&self) -> std::collections::BTreeMap<String, NamedTensor> {
        named_tensors(&self.model)
    }
}
