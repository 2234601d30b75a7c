//! Adapting the refiner to a seed (`--adapt SECONDS`): before the loop, the whole autoencoder
//! (encoder, codebook with the revival of unused codes, decoder) is fine-tuned on crops of the
//! seed and its mirror image (stage 1's losses: L1 and the gradient term on colour and
//! depth, the quantizer's), within a wall-time budget.
//!
//! Why the whole autoencoder: the bundled model has only seen the synthetic world. Its code head
//! gives a Google Earth seed a handful of CLEVR codes, and the encoder's nearest codes are not
//! much richer, so no decoder can draw the seed back from them (tuning the decoder alone for 60 s
//! gave blurred blobs). Adapting the codebook to the seed's patches is what lets its codes hold
//! the seed: 12.8 dB -> 24 dB in a minute on two cores (docs/STATUS.md).
//!
//! The adapted model has no code head (the head was trained on the old encoder's features): the
//! refiner gives every observed cell its nearest code. With `--bank seed` the seed's codes under
//! the adapted encoder fill the holes, the adapted decoder colours them (it sees the whole code
//! grid, so a quilted piece is drawn continuing its surroundings) and the seed's pixels give
//! their depth.
//!
//! Half of each batch are round trips of the seed ([`crate::roundtrip`]): the seed brought back
//! through a camera of the run's own path, so its holes are real disocclusions and the frame's
//! far edge, and the target there is the seed's own pixels (cyclic virtual cameras, as
//! InfiniteNature-Zero learns from single images). The encoder learns what the seed's holes
//! hold from around them, which is what a model drawing the new area (`--bank none`) uses.
//!
//! The weights are written to the run folder ([`ADAPTED_FILE`]) and a resumed run loads them.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_core::{Intrinsics, RgbdFrame};
use sgam_model::params::{save_safetensors, WeightPrecision};
use sgam_model::train::{Stage, TrainConfig, TrainPair, Trainer};

use crate::bank::mirrored;
use crate::roundtrip::RoundTrip;
use crate::{PipelineError, Result, Seed, BUNDLED_MODEL};

/// The adapted weights in a run folder.
pub const ADAPTED_FILE: &str = "adapted.safetensors";

/// Side of the square crops the autoencoder is tuned on (the seed's shorter side when smaller).
pub const ADAPT_CROP_PX: usize = 256;

/// Crops per step.
const BATCH: usize = 2;

/// Adam's learning rate: a few hundred steps is all a budget of minutes buys on two cores.
const LR: f64 = 5e-4;

/// Round trips of the seed adapted on (the nearest steps of the path that lose part of it).
pub const ADAPT_TRIPS: usize = 6;

/// Random crop positions tried for a round trip's crop; the one with the most holes is taken.
const TRIP_CROP_TRIES: usize = 8;

/// Steps a code may go unused before the revival may give it a feature of the seed.
const REVIVAL_WINDOW: u64 = 20;

/// Where a run's adapted weights are.
pub fn adapted_path(run_dir: &Path) -> PathBuf {
    run_dir.join(ADAPTED_FILE)
}

/// The refiner a run in `dir` with `spec` completes holes with: with `--adapt` (`adapt_s > 0`)
/// the run folder's adapted weights ([`adapted_path`]) in place of the model, else `spec`.
pub fn adapted_spec(dir: &Path, spec: &crate::RefinerSpec) -> crate::RefinerSpec {
    match spec {
        crate::RefinerSpec::Model { options, bank, adapt_s, .. } if *adapt_s > 0.0 => crate::RefinerSpec::Model {
            model: Some(adapted_path(dir)),
            options: *options,
            bank: bank.clone(),
            adapt_s: *adapt_s,
        },
        other => other.clone(),
    }
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
    /// PSNR of the last step's reconstruction (dB).
    pub psnr_db: f32,
}

/// What an adaptation did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdaptOutcome {
    /// Optimisation steps.
    pub steps: u64,
    /// Wall time, seconds.
    pub seconds: f64,
    /// PSNR of the seed's colour through the autoencoder (encoder, nearest codes, decoder),
    /// before and after (dB).
    pub psnr_before_db: f64,
    /// See `psnr_before_db`.
    pub psnr_after_db: f64,
    /// Round trips of the seed in the batches.
    pub trips: usize,
}

/// Fine-tunes the autoencoder of `model` (the bundled model when `None`) on `seed` and its
/// round `trips` for `budget` (at least one step) and writes it, without its code head, to `out`
/// (f32, config embedded, atomically). `progress` is called after every step.
pub fn adapt_to_seed(
    model: Option<&Path>,
    seed: &Seed,
    trips: &[RoundTrip],
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
    let (before, config) = sgam_model::refiner::load_model_bytes(&bytes, None, &device).map_err(model_error)?;
    let f = config.downsample_factor();
    let (w, h) = (seed.frame.width() as usize, seed.frame.height() as usize);
    let side = ADAPT_CROP_PX.min(w).min(h) / f * f;
    if side == 0 {
        return Err(PipelineError::Config(format!(
            "--adapt: the seed is {w}x{h} px; adapting needs at least {f} px each way"
        )));
    }
    let tc = TrainConfig {
        batch: BATCH,
        crop: side as u32,
        lr: LR,
        kmeans_window: REVIVAL_WINDOW,
        ckpt_every: 0,
        val_every: 0,
        ..TrainConfig::new(Stage::One, u64::MAX / 2)
    };
    let k = seed.camera.intrinsics;
    let bases = [(seed.frame.clone(), k), (mirrored(&seed.frame), Intrinsics { cx: w as f32 - 1.0 - k.cx, ..k })];
    // the seed through the autoencoder, whole, before and after
    let whole = crops_of(&(&bases[0].0, bases[0].1), w / f * f, h / f * f, [0, 0]);
    let psnr_before_db = whole.as_ref().map_or(Ok(0.0), |x| psnr(&before, &config, x))?;
    // the depth coding follows the seed's depths: the bundled model codes 7-16 m, so a seed a
    // few units away would sit beyond its nearest code and every depth it draws at 7 m or more
    let config = sgam_model::ModelConfig { depth: seed_depth_coding(&seed.frame).unwrap_or(config.depth), ..config };
    let mut trainer = Trainer::from_model(&config, &tc, before);
    let mut rng = ChaCha8Rng::seed_from_u64(0x000A_DA97);
    let start = Instant::now();
    loop {
        let mut ks = Vec::with_capacity(BATCH);
        let mut pairs = Vec::with_capacity(BATCH);
        for b in 0..BATCH {
            let at = |rng: &mut ChaCha8Rng| {
                [rng.random_range(0..=(w - side) / f) * f, rng.random_range(0..=(h - side) / f) * f]
            };
            if b % 2 == 1 && !trips.is_empty() {
                // a round trip: the crop with the most holes of a few
                let trip = &trips[rng.random_range(0..trips.len())];
                let crop_mask = |at| crop(&trip.guidance.missing, w, side, side, at);
                let holes = |at| crop_mask(at).iter().filter(|m| **m).count();
                let Some(best) = (0..TRIP_CROP_TRIES).map(|_| at(&mut rng)).max_by_key(|p| holes(*p)) else { continue };
                let (Some((input, k_crop)), Some((target, _))) = (
                    crops_of(&(&trip.guidance.frame, k), side, side, best),
                    crops_of(&(&bases[0].0, bases[0].1), side, side, best),
                ) else {
                    continue;
                };
                let missing = crop_mask(best);
                ks.push(k_crop);
                pairs.push(TrainPair { missing, input, target });
            } else {
                let (frame, k_base) = &bases[rng.random_range(0..bases.len())];
                let Some((frame, k_crop)) = crops_of(&(frame, *k_base), side, side, at(&mut rng)) else { continue };
                ks.push(k_crop);
                pairs.push(TrainPair { missing: vec![false; side * side], input: frame.clone(), target: frame });
            }
        }
        let r = trainer.step_on_at(&pairs, &ks).map_err(|e| PipelineError::Refiner(Box::new(e)))?;
        let elapsed = start.elapsed();
        progress(AdaptProgress {
            step: r.step,
            elapsed_s: elapsed.as_secs_f64(),
            budget_s: budget.as_secs_f64(),
            psnr_db: r.psnr,
        });
        if elapsed >= budget {
            break;
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    // the code head read the old encoder's features: the adapted model gives each cell its
    // nearest code instead, and the context (which adds to the head's logits) goes with it
    let mut adapted = trainer.inference_model();
    adapted.code_head = None;
    adapted.context = None;
    let adapted_config = sgam_model::ModelConfig { code_head: false, code_tau: None, context: None, ..config.clone() };
    let psnr_after_db = whole.as_ref().map_or(Ok(0.0), |x| psnr(&adapted, &adapted_config, x))?;
    let meta = sgam_model::refiner::weight_metadata(&adapted_config).map_err(model_error)?;
    save_safetensors(&adapted, out, WeightPrecision::F32, Some(meta))
        .map_err(|source| PipelineError::ModelLoad { path: Some(out.to_path_buf()), source })?;
    Ok(AdaptOutcome { steps: trainer.step, seconds, psnr_before_db, psnr_after_db, trips: trips.len() })
}

/// A depth coding spanning `frame`'s depths: nearest at 0.8 x its 1st percentile, farthest at
/// 1.5 x its 99th (room for what the new area holds beyond), at least 1.5 x the nearest apart.
/// `None` without valid depth.
pub fn seed_depth_coding(frame: &RgbdFrame) -> Option<sgam_model::DepthCoding> {
    let mut d: Vec<f32> = frame.depth_m.data.iter().copied().filter(|d| sgam_core::is_valid_depth(*d)).collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f32::total_cmp);
    let near_m = 0.8 * d[d.len() / 100];
    let far_m = (1.5 * d[d.len() - 1 - d.len() / 100]).max(1.5 * near_m);
    Some(sgam_model::DepthCoding { near_m, far_m, offset_m: 0.0 })
}

/// The `cw x ch` crop of `frame` at `[x, y]`, with its intrinsics.
fn crops_of(
    (frame, k): &(&RgbdFrame, Intrinsics),
    cw: usize,
    ch: usize,
    at @ [x0, y0]: [usize; 2],
) -> Option<(RgbdFrame, Intrinsics)> {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    if x0 + cw > w || y0 + ch > h {
        return None;
    }
    let (iw, ih) = (cw as u32, ch as u32);
    let out = RgbdFrame {
        colour: sgam_core::Image { width: iw, height: ih, data: crop(&frame.colour.data, w, cw, ch, at) },
        depth_m: sgam_core::Image { width: iw, height: ih, data: crop(&frame.depth_m.data, w, cw, ch, at) },
    };
    Some((out, Intrinsics { cx: k.cx - x0 as f32, cy: k.cy - y0 as f32, ..*k }))
}

/// The `cw x ch` crop at `[x, y]` of row-major `data`, `w` wide (the caller keeps it inside).
fn crop<T: Copy>(data: &[T], w: usize, cw: usize, ch: usize, [x0, y0]: [usize; 2]) -> Vec<T> {
    (y0..y0 + ch).flat_map(|y| data[y * w + x0..y * w + x0 + cw].iter().copied()).collect()
}

/// PSNR (dB) of the colour `model` draws from the frame's nearest codes.
fn psnr(
    model: &sgam_model::VqModel,
    config: &sgam_model::ModelConfig,
    (frame, k): &(RgbdFrame, Intrinsics),
) -> Result<f64> {
    let device = sgam_model::default_device();
    let decoded = sgam_model::generative::autoencode(model, config, &[frame], &[*k], &device)
        .map_err(|source| PipelineError::ModelLoad { path: None, source })?;
    Ok(decoded.first().and_then(|d| sgam_metrics::psnr(&d.colour, &frame.colour, None)).unwrap_or(0.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_seed_s_depth_coding_spans_its_depths_with_room_beyond() {
        let mut frame = RgbdFrame::empty(10, 10);
        for (i, d) in frame.depth_m.data.iter_mut().enumerate() {
            *d = 1.5 + 0.02 * i as f32; // 1.5 .. 3.48
        }
        frame.depth_m.data[0] = 0.0; // no depth: not counted
        let c = seed_depth_coding(&frame).unwrap();
        assert!((c.near_m - 0.8 * 1.52).abs() < 1e-4 && (c.far_m - 1.5 * 3.48).abs() < 1e-4, "{c:?}");
        // every depth of the seed codes inside [-1, 1], and back
        for d in &frame.depth_m.data[1..] {
            let v = c.encode(*d);
            assert!((-1.0..=1.0).contains(&v), "{d} -> {v}");
            assert!((c.decode(v) - d).abs() < 1e-3);
        }
        // a flat seed still gets a range; none without depth
        frame.depth_m.data.iter_mut().for_each(|d| *d = 2.0);
        let flat = seed_depth_coding(&frame).unwrap();
        assert!(flat.far_m >= 1.5 * flat.near_m);
        frame.depth_m.data.iter_mut().for_each(|d| *d = 0.0);
        assert!(seed_depth_coding(&frame).is_none());
    }
}
