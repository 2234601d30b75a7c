//! Adapting the refiner to a seed (`--adapt SECONDS`): before the loop, the decoder (and
//! `post_quant_conv`) is fine-tuned to draw the seed's own codes as the seed's pixels, within a
//! wall-time budget, on crops of the seed and its mirror image (colour and depth, L1).
//!
//! Why the decoder: the bundled model has only seen the synthetic world, and its decoder draws
//! a Google Earth seed at about 13 dB, so the seed's codes decoded are purple streaks. The
//! encoder, codebook and code head stay as they are, so the codes a hole is given (the seed
//! bank's, [`crate::bank::seed_bank`]) keep their meaning; only what they decode to changes.
//! With `--bank seed` the adapted decoder colours the holes (the decoder sees the whole code
//! grid, so a quilted piece is drawn continuing its surroundings) and the seed's pixels give
//! their depth.
//!
//! The weights are written to the run folder ([`ADAPTED_FILE`]) and a resumed run loads them.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_core::{Intrinsics, RgbdFrame};
use sgam_model::decoder_tune::{DecoderTuneConfig, DecoderTuner};
use sgam_model::params::{from_safetensors_bytes, save_safetensors, WeightPrecision};

use crate::bank::mirrored;
use crate::{PipelineError, Result, Seed, BUNDLED_MODEL};

/// The adapted weights in a run folder.
pub const ADAPTED_FILE: &str = "adapted.safetensors";

/// Side of the square crops the decoder is tuned on (the seed's shorter side when smaller).
pub const ADAPT_CROP_PX: usize = 256;

/// Crops per step.
const BATCH: usize = 2;

/// Adam's learning rate: a few hundred steps is all a budget of minutes buys on two cores.
const LR: f64 = 5e-4;

/// Where a run's adapted weights are.
pub fn adapted_path(run_dir: &Path) -> PathBuf {
    run_dir.join(ADAPTED_FILE)
}

/// Progress of an adaptation, reported after every step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdaptProgress {
    /// Steps done.
    pub step: u64,
    /// Seconds spent.
    pub elapsed_s: f64,
    /// The budget, seconds.
    pub budget_s: f64,
    /// Colour L1 of the last step (packed units, `[-1, 1]`).
    pub l1_colour: f32,
}

/// What an adaptation did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdaptOutcome {
    /// Optimisation steps.
    pub steps: u64,
    /// Wall time, seconds.
    pub seconds: f64,
    /// PSNR of the seed's colour decoded from its own codes, before and after (dB).
    pub psnr_before_db: f64,
    /// See `psnr_before_db`.
    pub psnr_after_db: f64,
}

/// Fine-tunes the decoder of `model` (the bundled model when `None`) on `seed` for `budget`
/// (at least one step) and writes the weights to `out` (f32, config embedded, atomically).
/// `progress` is called after every step.
pub fn adapt_to_seed(
    model: Option<&Path>,
    seed: &Seed,
    budget: Duration,
    out: &Path,
    progress: &mut dyn FnMut(AdaptProgress),
) -> Result<AdaptOutcome> {
    let model_error = |source| PipelineError::ModelLoad { path: model.map(Path::to_path_buf), source };
    let bytes = match model {
        Some(p) => std::fs::read(p).map_err(|e| sgam_io::IoError::Io { path: p.to_path_buf(), source: e })?,
        None => BUNDLED_MODEL.to_vec(),
    };
    let device = sgam_model::default_device();
    let (encoder, config) = sgam_model::refiner::load_model_bytes(&bytes, None, &device).map_err(model_error)?;
    let (tensors, _) = from_safetensors_bytes(&bytes).map_err(model_error)?;
    let tc = DecoderTuneConfig { steps: u64::MAX, lr: LR, lr_decay_from: None, depth_weight: 1.0 };
    let mut tuner = DecoderTuner::new(&config, &tensors, encoder, &config, &tc).map_err(model_error)?.with_head_codes();

    let f = config.downsample_factor();
    let (w, h) = (seed.frame.width() as usize, seed.frame.height() as usize);
    let side = ADAPT_CROP_PX.min(w).min(h) / f * f;
    if side == 0 {
        return Err(PipelineError::Config(format!(
            "--adapt: the seed is {w}x{h} px; adapting needs at least {f} px each way"
        )));
    }
    let k = seed.camera.intrinsics;
    let bases = [(seed.frame.clone(), k), (mirrored(&seed.frame), Intrinsics { cx: w as f32 - 1.0 - k.cx, ..k })];
    // the seed's own codes decoded, whole, before and after
    let whole: Vec<(RgbdFrame, Intrinsics)> = crops_of(&bases[0], w / f * f, h / f * f, [0, 0]).into_iter().collect();
    let psnr_before_db = psnr(&tuner, &whole)?;
    let mut rng = ChaCha8Rng::seed_from_u64(0x000A_DA97);
    let start = Instant::now();
    loop {
        let batch: Vec<(RgbdFrame, Intrinsics)> = (0..BATCH)
            .flat_map(|_| {
                let base = &bases[rng.random_range(0..bases.len())];
                let at = [rng.random_range(0..=(w - side) / f) * f, rng.random_range(0..=(h - side) / f) * f];
                crops_of(base, side, side, at)
            })
            .collect();
        let frames: Vec<&RgbdFrame> = batch.iter().map(|b| &b.0).collect();
        let ks: Vec<Intrinsics> = batch.iter().map(|b| b.1).collect();
        let r = tuner.step_on(&frames, &ks).map_err(model_error)?;
        let elapsed = start.elapsed();
        progress(AdaptProgress {
            step: tuner.step,
            elapsed_s: elapsed.as_secs_f64(),
            budget_s: budget.as_secs_f64(),
            l1_colour: r.l1_colour,
        });
        if elapsed >= budget {
            break;
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    let psnr_after_db = psnr(&tuner, &whole)?;
    let meta = sgam_model::refiner::weight_metadata(&config).map_err(model_error)?;
    save_safetensors(&tuner.model, out, WeightPrecision::F32, Some(meta))
        .map_err(|source| PipelineError::ModelLoad { path: Some(out.to_path_buf()), source })?;
    Ok(AdaptOutcome { steps: tuner.step, seconds, psnr_before_db, psnr_after_db })
}

/// The `cw x ch` crop of `base` at `[x, y]`, with its intrinsics.
fn crops_of(
    (frame, k): &(RgbdFrame, Intrinsics),
    cw: usize,
    ch: usize,
    [x0, y0]: [usize; 2],
) -> Option<(RgbdFrame, Intrinsics)> {
    let w = frame.width() as usize;
    if x0 + cw > w || y0 + ch > frame.height() as usize {
        return None;
    }
    let mut out = RgbdFrame::empty(cw as u32, ch as u32);
    for y in 0..ch {
        let src = (y0 + y) * w + x0;
        out.colour.data[y * cw..(y + 1) * cw].copy_from_slice(&frame.colour.data[src..src + cw]);
        out.depth_m.data[y * cw..(y + 1) * cw].copy_from_slice(&frame.depth_m.data[src..src + cw]);
    }
    Some((out, Intrinsics { cx: k.cx - x0 as f32, cy: k.cy - y0 as f32, ..*k }))
}

/// PSNR (dB) of the colour the tuner's decoder draws from each frame's own codes.
fn psnr(tuner: &DecoderTuner, frames: &[(RgbdFrame, Intrinsics)]) -> Result<f64> {
    let mut se = 0.0f64;
    let mut n = 0usize;
    for (frame, k) in frames {
        let decoded =
            tuner.decode_own_codes(frame, k).map_err(|source| PipelineError::ModelLoad { path: None, source })?;
        for (a, b) in decoded.colour.data.iter().zip(&frame.colour.data) {
            for c in 0..3 {
                se += f64::from(a[c] - b[c]).powi(2);
            }
            n += 3;
        }
    }
    let mse = se / n.max(1) as f64;
    Ok(if mse > 0.0 { 10.0 * (1.0 / mse).log10() } else { f64::INFINITY })
}
