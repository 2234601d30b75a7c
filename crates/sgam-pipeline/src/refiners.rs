//! The refiners of a run: the learned model, and stand-ins so the pipeline runs end to end
//! without weights. [`build_refiner`] is the one place a [`RefinerSpec`] becomes a refiner.
//!
//! - [`NullRefiner`]: returns the guidance with holes filled naively (push-pull: missing pixels
//!   take the average of valid pixels at coarser scales). With `fill = false` it returns the
//!   guidance unchanged (the `--no-refine` ablation).
//! - [`OracleRefiner`]: returns the ground-truth render of the synthetic world at the target
//!   camera (an upper bound for any model; used by end-to-end tests).

use std::convert::Infallible;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sgam_core::{is_valid_depth, Guidance, Refiner, RgbdFrame};
use sgam_model::{ModelError, RefinerOptions, Sampling, VqRefiner};
use sgam_synth::{RenderConfig, Renderer};

use crate::error::config_error;
use crate::BankSpec;
use crate::{PipelineError, Result, Seed};

/// The bundled model (f16 safetensors, config embedded; see docs/MODEL.md): the compact VQ
/// autoencoder and code head with the context transformer CL2 (session 28) over its code grid,
/// compiled into the library so an installed `sgam` needs no files next to it.
pub const BUNDLED_MODEL: &[u8] = include_bytes!("../../../models/compact.safetensors");

/// The code bank built with the bundled model's encoder (`sgam train bank`, 4,096 frames of
/// training scenes; see docs/MODEL.md), compiled in like the model; used when named
/// (`--bank bundled`): the default for CLEVR seeds is the model's own draws since session 30.
pub const BUNDLED_BANK: &[u8] = include_bytes!("../../../models/bank.bin");

/// Which refiner completes the guidance, resolved.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum RefinerSpec {
    /// The learned VQ refiner: the weights at `model`, else [`BUNDLED_MODEL`].
    Model {
        /// Model weights (safetensors); `None` = the bundled model.
        model: Option<PathBuf>,
        /// Sampling, seed and what to keep from the guidance.
        options: RefinerOptions,
        /// The code bank that completes holes instead of sampling (runs before the bank
        /// existed had none).
        #[serde(default)]
        bank: BankSpec,
        /// Seconds of adapting the autoencoder to the seed before the loop ([`crate::adapt`]; 0
        /// = none). The adapted weights are the run folder's [`crate::adapt::ADAPTED_FILE`].
        #[serde(default)]
        adapt_s: f32,
    },
    /// [`NullRefiner`]: holes filled by push-pull (`fill`), or the guidance as it is.
    Null {
        /// Fill missing pixels; `false` is the `--no-refine` ablation.
        fill: bool,
    },
    /// [`OracleRefiner`]: ground truth of the synthetic world (synthetic seeds only).
    Oracle,
}

impl RefinerSpec {
    /// CRC-32 of the model file the refiner loads, and of its code bank when it has one
    /// (`None` for the stand-ins): a resumed run refuses a file that changed since it started.
    pub fn model_crc32(&self) -> Result<Option<u32>> {
        Ok(match self {
            RefinerSpec::Model { model, bank, .. } => {
                let bytes = match model {
                    Some(p) => std::fs::read(p).map_err(|e| sgam_io::IoError::Io { path: p.clone(), source: e })?,
                    None => BUNDLED_MODEL.to_vec(),
                };
                let mut h = crc32fast::Hasher::new();
                h.update(&bytes);
                // a run without a bank keeps the model file's own CRC
                if let Some(b) = bank.crc32()? {
                    h.update(&b.to_le_bytes());
                }
                Some(h.finalize())
            }
            RefinerSpec::Null { .. } | RefinerSpec::Oracle => None,
        })
    }
}

/// The code selection for a sampling temperature and a top-k (0 = all codes): temperature
/// sampling when both allow a choice, argmin otherwise.
pub fn sampling(temperature: f32, top_k: usize) -> Sampling {
    let top_k = if top_k == 0 { usize::MAX } else { top_k };
    if temperature > 0.0 && top_k > 1 {
        Sampling::Temperature { temperature, top_k }
    } else {
        Sampling::Argmin
    }
}

/// The learned refiner with the weights at `model` (the bundled model when `None`).
pub fn model_refiner(model: Option<&Path>, options: RefinerOptions) -> Result<VqRefiner> {
    match model {
        Some(path) => VqRefiner::from_files(path, None, options)
            .map_err(|source| PipelineError::ModelLoad { path: Some(path.to_path_buf()), source }),
        None => VqRefiner::from_bytes(BUNDLED_MODEL, None, options)
            .map_err(|source| PipelineError::ModelLoad { path: None, source }),
    }
}

/// The refiner factory: the refiner `spec` names, for a run from `seed` (the oracle renders
/// the seed's synthetic world).
pub fn build_refiner(spec: &RefinerSpec, seed: &Seed) -> Result<AnyRefiner> {
    Ok(match spec {
        RefinerSpec::Model { model, options, bank, adapt_s } => {
            let mut refiner = model_refiner(model.as_deref(), *options)?;
            bank.load_into(&mut refiner, Some(seed))?;
            // an autoencoder adapted to the seed draws its look: it colours the quilted holes
            refiner.set_bank_colour_from_decoder(*adapt_s > 0.0 && *bank == BankSpec::Seed);
            if let Some(b) = refiner.bank() {
                let f = refiner.config().downsample_factor();
                let (w, h) = (seed.frame.width() as usize, seed.frame.height() as usize);
                if (b.cols * f, b.rows * f) != (w, h) {
                    config_error!(
                        "--bank {bank}: the bank holds {}x{} px frames and this run's are {w}x{h} (leave out --bank, or build a \
                         bank at this size with `sgam train bank --res`)",
                        b.cols * f,
                        b.rows * f
                    );
                }
            }
            AnyRefiner::Model(Box::new(refiner))
        }
        RefinerSpec::Null { fill } => AnyRefiner::Null(NullRefiner { fill: *fill }),
        RefinerSpec::Oracle => {
            let Some(renderer) = seed.renderer.clone() else {
                config_error!(
                    "--refiner oracle needs a synthetic seed (no --seed-rgb / --seed-template / --seed-google-earth)"
                );
            };
            AnyRefiner::Oracle(Box::new(OracleRefiner::new(renderer, RenderConfig::default())))
        }
    })
}

/// One of the refiners [`build_refiner`] makes.
#[derive(Debug)]
pub enum AnyRefiner {
    /// The learned VQ refiner.
    Model(Box<VqRefiner>),
    /// Push-pull hole filling, or pass-through.
    Null(NullRefiner),
    /// Ground truth of the synthetic world.
    Oracle(Box<OracleRefiner>),
}

impl Refiner for AnyRefiner {
    type Error = ModelError;

    fn refine(&mut self, guidance: &Guidance) -> std::result::Result<RgbdFrame, ModelError> {
        match self {
            AnyRefiner::Model(r) => r.refine(guidance),
            AnyRefiner::Null(r) => r.refine(guidance).map_err(|e| match e {}),
            AnyRefiner::Oracle(r) => r.refine(guidance).map_err(|e| match e {}),
        }
    }
}

/// Guidance with holes filled by push-pull interpolation (or not at all).
#[derive(Debug, Clone, Copy)]
pub struct NullRefiner {
    /// Fill missing pixels; `false` passes the guidance through (`--no-refine`).
    pub fill: bool,
}

impl Refiner for NullRefiner {
    type Error = Infallible;

    fn refine(&mut self, guidance: &Guidance) -> std::result::Result<RgbdFrame, Infallible> {
        let mut frame = guidance.frame.clone();
        if self.fill {
            push_pull_fill(&mut frame, &guidance.missing);
        } else {
            for (i, m) in guidance.missing.iter().enumerate() {
                if *m {
                    frame.depth_m.data[i] = 0.0;
                }
            }
        }
        Ok(frame)
    }
}

/// Fills pixels where `missing` (or depth invalid) from a pyramid of averages of the valid ones.
/// Colour and depth are filled together so filled geometry and colour stay consistent.
pub fn push_pull_fill(frame: &mut RgbdFrame, missing: &[bool]) {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    // level 0: value * weight
    let mut levels: Vec<(usize, usize, Vec<[f32; 5]>)> = Vec::new();
    let mut cur: Vec<[f32; 5]> = (0..w * h)
        .map(|i| {
            let d = frame.depth_m.data[i];
            if missing[i] || !is_valid_depth(d) {
                [0.0; 5]
            } else {
                let c = frame.colour.data[i];
                [c[0], c[1], c[2], d, 1.0]
            }
        })
        .collect();
    let (mut cw, mut ch) = (w, h);
    levels.push((cw, ch, cur.clone()));
    while cw > 1 || ch > 1 {
        let (nw, nh) = (cw.div_ceil(2), ch.div_ceil(2));
        let mut next = vec![[0.0f32; 5]; nw * nh];
        for y in 0..ch {
            for x in 0..cw {
                let s = cur[y * cw + x];
                let t = &mut next[(y / 2) * nw + x / 2];
                for k in 0..5 {
                    t[k] += s[k];
                }
            }
        }
        cur = next;
        (cw, ch) = (nw, nh);
        levels.push((cw, ch, cur.clone()));
    }
    if levels.last().is_some_and(|l| l.2[0][4] == 0.0) {
        return; // nothing valid to fill from
    }
    // pull: from coarse to fine, fill zero-weight cells with the parent's normalised value
    for li in (0..levels.len() - 1).rev() {
        let (pw, _, parent) = {
            let p = &levels[li + 1];
            (p.0, p.1, p.2.clone())
        };
        let (lw, lh, lv) = &mut levels[li];
        for y in 0..*lh {
            for x in 0..*lw {
                let v = &mut lv[y * *lw + x];
                if v[4] == 0.0 {
                    let p = parent[(y / 2) * pw + x / 2];
                    if p[4] > 0.0 {
                        *v = [p[0] / p[4], p[1] / p[4], p[2] / p[4], p[3] / p[4], 1.0];
                    }
                }
            }
        }
    }
    let base = &levels[0].2;
    for i in 0..w * h {
        if missing[i] || !is_valid_depth(frame.depth_m.data[i]) {
            let v = base[i];
            if v[4] > 0.0 {
                frame.colour.data[i] = [v[0] / v[4], v[1] / v[4], v[2] / v[4]];
                frame.depth_m.data[i] = v[3] / v[4];
            }
        }
    }
}

/// Ground truth from the synthetic world.
#[derive(Debug)]
pub struct OracleRefiner {
    renderer: Renderer,
    config: RenderConfig,
}

impl OracleRefiner {
    /// Renders `renderer`'s scene with `config` at every guidance camera.
    pub fn new(renderer: Renderer, config: RenderConfig) -> Self {
        Self { renderer, config }
    }
}

impl Refiner for OracleRefiner {
    type Error = Infallible;

    fn refine(&mut self, guidance: &Guidance) -> std::result::Result<RgbdFrame, Infallible> {
        Ok(self.renderer.render(&guidance.camera, &self.config).frame)
    }
}

/// Colour PSNR (dB) below which a seed counts as far from the bundled model's training data:
/// the model reconstructs held-out synthetic CLEVR frames at about 30 dB (docs/MODEL.md,
/// "autoencode"), and a seed it cannot reconstruct within 5 dB of that is not what it learned.
/// Measured with the bundled model: the CLEVR template seed 30.3 dB, the three shared Google Earth
/// seeds 12.7-12.8 dB, a 7-Scenes kitchen frame 13.7 dB. (At the model's 256 px; a CLEVR frame
/// of 64 px, whose objects are a few pixels, reconstructs at about 21 dB.)
pub const DOMAIN_PSNR_DB: f64 = 25.0;

/// How far `seed` is from what the model at `model` (`None`: the bundled one) was trained on:
/// the colour PSNR (dB) of its reconstruction of the whole seed frame (nothing missing, every
/// pixel regenerated, argmin codes). Compare with [`DOMAIN_PSNR_DB`].
pub fn seed_reconstruction_psnr(model: Option<&Path>, seed: &Seed) -> Result<f64> {
    let options = RefinerOptions { sampling: Sampling::Argmin, keep_observed: false, ..RefinerOptions::default() };
    let mut refiner = model_refiner(model, options)?;
    let frame = &seed.frame;
    let nothing = vec![false; frame.colour.data.len()];
    let out = refiner
        .complete_at(frame, &nothing, Some(&seed.camera.intrinsics))
        .map_err(|e| PipelineError::Refiner(Box::new(e)))?;
    // the output has the seed's size, so a PSNR is always defined
    Ok(sgam_metrics::psnr(&out.colour, &frame.colour, None).unwrap_or(0.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use sgam_core::{Camera, Intrinsics, Rigid3};

    fn guidance(frame: RgbdFrame, missing: Vec<bool>) -> Guidance {
        let (w, h) = (frame.width(), frame.height());
        Guidance { camera: Camera::new(Intrinsics::from_fov_x(w, h, 1.0), Rigid3::IDENTITY), frame, missing, seed: 0 }
    }

    #[test]
    fn push_pull_fills_every_hole_with_nearby_values() {
        // Two regions of a 16 x 12 frame: columns 0..4 at 2 m (colour a), 12..16 at 8 m (colour
        // b), a hole between. The pyramid (16 -> 8 -> 4 -> 2 -> 1 columns) keeps the two apart
        // until the 2-column level, so each hole column takes the value of the nearer region:
        // columns 4..8 get a and 2 m, 8..12 get b and 8 m (not their 5 m mean).
        let (w, h) = (16u32, 12u32);
        let (a, b) = ([0.2, 0.4, 0.6], [0.9, 0.1, 0.3]);
        let mut frame = RgbdFrame::empty(w, h);
        let mut missing = vec![true; (w * h) as usize];
        for v in 0..h {
            for u in (0..4).chain(12..16) {
                let i = (v * w + u) as usize;
                (frame.colour.data[i], frame.depth_m.data[i]) = if u < 4 { (a, 2.0) } else { (b, 8.0) };
                missing[i] = false;
            }
        }
        let g = guidance(frame.clone(), missing.clone());
        let out = NullRefiner { fill: true }.refine(&g).unwrap();
        for v in 0..h {
            for u in 0..w {
                let i = (v * w + u) as usize;
                let (colour, depth) = if u < 8 { (a, 2.0) } else { (b, 8.0) };
                assert!((out.depth_m.data[i] - depth).abs() < 1e-5, "({u}, {v}): {}", out.depth_m.data[i]);
                assert!((0..3).all(|c| (out.colour.data[i][c] - colour[c]).abs() < 1e-5), "({u}, {v})");
            }
        }
        let raw = NullRefiner { fill: false }.refine(&g).unwrap();
        assert_eq!(raw.depth_m.data[(w - 1) as usize], 8.0);
        assert_eq!(raw.depth_m.data[(w / 2) as usize], 0.0);

        // A lone hole in a depth ramp d = 1 + 0.1 u + 0.05 v takes the mean of the valid pixels
        // of its 2 x 2 block: at (9, 6) those are (8, 6), (8, 7), (9, 7), so 1 + 0.1 * 25 / 3 +
        // 0.05 * 20 / 3 = 13 / 6 (the true 2.2 is one ramp step away); valid pixels are kept.
        let mut frame = RgbdFrame::empty(w, h);
        for v in 0..h {
            for u in 0..w {
                let d = 1.0 + 0.1 * u as f32 + 0.05 * v as f32;
                *frame.depth_m.at_mut(u, v) = d;
                *frame.colour.at_mut(u, v) = [d / 4.0; 3];
            }
        }
        let mut missing = vec![false; (w * h) as usize];
        missing[(6 * w + 9) as usize] = true;
        let out = NullRefiner { fill: true }.refine(&guidance(frame.clone(), missing)).unwrap();
        assert!((*out.depth_m.at(9, 6) - 13.0 / 6.0).abs() < 1e-5, "{}", out.depth_m.at(9, 6));
        assert!((out.colour.at(9, 6)[0] - 13.0 / 24.0).abs() < 1e-5);
        let mut kept = out.depth_m.clone();
        *kept.at_mut(9, 6) = *frame.depth_m.at(9, 6);
        assert_eq!(kept, frame.depth_m);
    }
}
