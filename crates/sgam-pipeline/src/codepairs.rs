//! Training pairs for the generative stage 2, taken from the generation regime itself.
//!
//! A short run of the real generator ([`WorldGenerator`]) on a *training* scene, with the oracle
//! (ground truth) as its refiner, produces at every step exactly the guidance that generation
//! sees: the map fused from the poses the trajectory visited before, rasterized and warped by
//! the generator's own code, with the holes of that trajectory. Each step's guidance, missing
//! mask and clean target become a pair; the target's codes come from the frozen encoder.
//!
//! Runs mix the trajectories generation uses: the authors' zig-zag at its step (0.408 m; each
//! step's hole is a small corner), the zig-zag at twice that step, straight lines (a band at
//! the top of the frame) and spirals (turning views). A crop of `crop x crop` pixels, aligned
//! to latent cells, is cut around each hole, so training runs at the encoder's speed on the
//! pixels that matter; the crop's intrinsics keep the shifted principal point (ray channels).

use std::sync::{Arc, Mutex};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use sgam_core::{trajectory, Camera, Guidance, Image, Intrinsics, Refiner, RgbdFrame, Vec3};
use sgam_map::TsdfMap;
use sgam_model::generative::{target_codes, CodePair};
use sgam_model::{ModelConfig, VqModel};
use sgam_synth::{blender_camera, dataset_intrinsics, RenderConfig, Renderer, Scene, SceneConfig};

use crate::generator::{clevr_generator_config, GeneratorConfig, WorldGenerator};
use crate::keyframes::Keyframes;
use crate::{PipelineError, Result};

/// One recorded generation step: guidance and the oracle's answer.
struct Recorded {
    guidance: Guidance,
    truth: RgbdFrame,
}

/// The refiner of a recorded run: records what it was asked and the truth, and answers with the
/// truth (the oracle), or with a model's completion when the run is closed-loop.
struct Recorder {
    renderer: Arc<Renderer>,
    log: Arc<Mutex<Vec<Recorded>>>,
    model: Option<ModelSteps>,
    /// Whether the last step was the model's (the generator's filters apply to it only).
    model_answered: bool,
}

/// The model of a closed-loop run and the share of its steps it completes (the oracle the rest).
struct ModelSteps {
    refiner: sgam_model::VqRefiner,
    share: f32,
    rng: ChaCha8Rng,
}

impl Refiner for Recorder {
    type Error = sgam_model::ModelError;

    fn refine(&mut self, guidance: &Guidance) -> Result<RgbdFrame, Self::Error> {
        let truth = self.renderer.render(&guidance.camera, &RenderConfig::default()).frame;
        if let Ok(mut log) = self.log.lock() {
            log.push(Recorded { guidance: guidance.clone(), truth: truth.clone() });
        }
        let model = match &mut self.model {
            // (a share of 1 draws nothing: runs recorded before the share existed stay as they were)
            Some(m) if m.share >= 1.0 => Some(m),
            Some(m) => (m.rng.random::<f32>() < m.share).then_some(m),
            None => None,
        };
        self.model_answered = model.is_some();
        match model {
            Some(m) => m.refiner.refine(guidance),
            None => Ok(truth),
        }
    }

    fn last_invented(&self) -> bool {
        self.model_answered
    }
}

/// Closed-loop recording: a share of the recorded runs grows its map with a model's own
/// completions (the truth is still each pair's target), so the pairs hold the guidance
/// generation really sees — its earlier inventions re-rendered, smears and all — and not only
/// the oracle's clean maps (exposure bias: a model trained on clean guidance only learns to
/// continue whatever the guidance shows).
#[derive(Debug, Clone, Copy)]
pub struct ClosedLoop<'a> {
    /// Share of the runs (0-1) whose map grows with the model's completions.
    pub share: f32,
    /// Share of such a run's steps (0-1] the model completes; the oracle completes the others,
    /// so the map keeps the true world around scattered inventions and the truth beyond an
    /// invention stays a continuation of what the guidance shows (1: every step, the world
    /// drifts from the truth and so does what the target can be predicted from).
    pub steps: f32,
    /// The model (safetensors bytes, config embedded).
    pub weights: &'a [u8],
    /// Its sampling options (generation's; the seed is drawn per run).
    pub options: sgam_model::RefinerOptions,
    /// The closed-loop runs treat the model's completions as generation does before fusing them
    /// (the CLEVR preset's invented-pixel policy: ground prior, flying pixels, free-space
    /// carving, solids, the size cap), so the guidance holds what `sgam generate` would leave in
    /// its map; without it they are fused as drawn (pairs recorded before session 30).
    pub filters: bool,
}

/// The trajectory shapes pairs are drawn from.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Shape {
    Zigzag(f32),
    Boustrophedon(f32),
    Line(f32),
    /// Radius; poses about 0.4 m apart along the circle.
    Circle(f32),
    Spiral(f32),
}

fn draw_shape(rng: &mut ChaCha8Rng) -> Shape {
    // every trajectory `eval world` knows, so no path's holes are new to the model (greedy walks
    // the zig-zag's grid; boustrophedon rows are zig-zags without the diagonal)
    match rng.random_range(0..20) {
        0..=4 => Shape::Zigzag(0.408),
        5..=6 => Shape::Zigzag(0.816),
        7..=8 => Shape::Boustrophedon(0.408),
        9..=11 => Shape::Line(rng.random_range(0.4..1.2)),
        12..=14 => Shape::Circle(rng.random_range(2.0..8.0)),
        _ => Shape::Spiral(rng.random_range(0.4..0.8)),
    }
}

/// Runs the generator with the oracle for `steps` steps on training scene `scene_seed` from a
/// random start, returning every step's guidance and truth (the exact generation path). With
/// `model`, the generator's map grows with the model's completions instead of the truth, and
/// with `filters` those pass generation's invented-pixel policy first ([`ClosedLoop::filters`]).
fn record_run(
    scene_seed: u64,
    steps: usize,
    res: u32,
    rng: &mut ChaCha8Rng,
    model: Option<(sgam_model::VqRefiner, f32)>,
    filters: bool,
) -> Result<Vec<Recorded>> {
    let renderer = Arc::new(Renderer::new(&Scene::generate(scene_seed, &SceneConfig::default())));
    let start = Vec3::new(rng.random_range(-26.0..2.0), rng.random_range(-26.0..2.0), sgam_synth::CAMERA_HEIGHT_M);
    let seed_camera = blender_camera(start, sgam_synth::CAMERA_PITCH_RAD, 0.0, dataset_intrinsics(res));
    let s = &seed_camera.world_from_camera;
    let poses = match draw_shape(rng) {
        Shape::Zigzag(step) => {
            let side = ((steps + 1) as f64).sqrt().ceil() as usize + 1;
            let cells: Vec<_> = trajectory::zigzag_cells(side, side).into_iter().take(steps + 1).collect();
            trajectory::grid_poses(s, &cells, step)
        }
        Shape::Boustrophedon(step) => {
            let side = ((steps + 1) as f64).sqrt().ceil() as usize + 1;
            let cells: Vec<_> = trajectory::boustrophedon_cells(side, side).into_iter().take(steps + 1).collect();
            trajectory::grid_poses(s, &cells, step)
        }
        Shape::Line(step) => trajectory::line_poses(s, steps + 1, step),
        Shape::Circle(radius) => {
            let around = ((std::f32::consts::TAU * radius / 0.4).ceil() as usize).max(steps + 1);
            trajectory::circle_poses(s, around, radius).into_iter().take(steps + 1).collect()
        }
        Shape::Spiral(step) => trajectory::spiral_poses(s, steps + 1, step, 4.0),
    };
    let dir = tempfile::tempdir().map_err(|e| sgam_io::IoError::Io { path: std::env::temp_dir(), source: e })?;
    let config = match (&model, filters) {
        (Some(_), true) => {
            GeneratorConfig { seed: scene_seed, ..crate::RunConfig::clevr(scene_seed).generator_config() }
        }
        _ => clevr_generator_config(scene_seed),
    };
    let log = Arc::new(Mutex::new(Vec::new()));
    let model =
        model.map(|(refiner, share)| ModelSteps { refiner, share, rng: ChaCha8Rng::seed_from_u64(rng.random()) });
    let oracle = Recorder { renderer: renderer.clone(), log: log.clone(), model, model_answered: false };
    let keyframes = Keyframes::new(dir.path(), config.source_radius_m, 16);
    let mut generator = WorldGenerator::new(TsdfMap::new(config.tsdf), keyframes, oracle, config);
    let seed_frame = renderer.render(&seed_camera, &RenderConfig::default()).frame;
    generator.seed(&seed_camera, seed_frame)?;
    for pose in poses.iter().skip(1) {
        generator.step(&Camera::new(seed_camera.intrinsics, *pose))?;
    }
    drop(generator);
    // the oracle never panics while holding the lock; a poisoned lock still holds whole records
    let recorded = std::mem::take(&mut *log.lock().unwrap_or_else(std::sync::PoisonError::into_inner));
    Ok(recorded)
}

/// Cuts a `crop x crop` window (aligned to `factor`) around a random missing pixel of `rec`.
fn crop_pair(rec: &Recorded, codes: &[u32], crop: u32, factor: u32, rng: &mut ChaCha8Rng) -> Option<CodePair> {
    let k = rec.guidance.camera.intrinsics;
    let (w, h) = (k.width, k.height);
    let crop = crop.min(w).min(h) / factor * factor;
    let missing: Vec<usize> = (0..rec.guidance.missing.len()).filter(|&i| rec.guidance.missing[i]).collect();
    if missing.is_empty() || crop == 0 {
        return None;
    }
    let p = missing[rng.random_range(0..missing.len())];
    let (pu, pv) = ((p as u32) % w, (p as u32) / w);
    // the crop's corner: at most crop - factor pixels before the hole pixel, inside the frame,
    // on the latent grid
    let mut corner = |c: u32, size: u32| -> u32 {
        let lo = c.saturating_sub(crop - factor);
        let v = rng.random_range(lo..=c);
        v.min((size - crop) / factor * factor) / factor * factor
    };
    let (u0, v0) = (corner(pu, w), corner(pv, h));
    // the window's pixels, row-major in the frame
    let window: Vec<usize> = (v0..v0 + crop).flat_map(|v| (u0..u0 + crop).map(move |u| (v * w + u) as usize)).collect();
    let frame = &rec.guidance.frame;
    let colour = window.iter().map(|&i| frame.colour.data[i].map(|x| (x.clamp(0.0, 1.0) * 255.0).round() / 255.0));
    let colour = Image { width: crop, height: crop, data: colour.collect() };
    let depth_m = Image { width: crop, height: crop, data: window.iter().map(|&i| frame.depth_m.data[i]).collect() };
    let mask = window.iter().map(|&i| rec.guidance.missing[i]).collect();
    let (cw, c0, r0, cc) =
        ((w / factor) as usize, (u0 / factor) as usize, (v0 / factor) as usize, (crop / factor) as usize);
    let crop_codes = (r0..r0 + cc).flat_map(|r| (c0..c0 + cc).map(move |c| r * cw + c)).map(|i| codes[i]).collect();
    Some(CodePair {
        input: RgbdFrame { colour, depth_m },
        missing: mask,
        intrinsics: Intrinsics { width: crop, height: crop, cx: k.cx - u0 as f32, cy: k.cy - v0 as f32, ..k },
        codes: crop_codes,
    })
}

/// Collects `n` pairs from runs on random scenes below `scene_limit` (training scenes only),
/// with target codes from the frozen `target` model. Each run's length is drawn from
/// `steps_per_run` (one value: every run; repeats weight a length); pairs of long runs hold the
/// guidance of a long horizon (a map grown over many steps, the spiral's turned views).
/// `progress` is called with the number of pairs so far.
pub fn collect(
    n: usize,
    steps_per_run: &[usize],
    crop: u32,
    scene_limit: u64,
    target: (&VqModel, &ModelConfig),
    closed_loop: Option<ClosedLoop<'_>>,
    rng: &mut ChaCha8Rng,
    progress: &mut dyn FnMut(usize),
) -> Result<Vec<CodePair>> {
    let device = sgam_model::default_device();
    let factor = target.1.downsample_factor() as u32;
    let mut pairs = Vec::with_capacity(n);
    while pairs.len() < n {
        // a batch of runs is drawn in order from `rng` (scene, own stream, closed loop or not),
        // recorded in parallel, then cropped in order: the pairs do not depend on the threads
        // (no more runs than the pairs still wanted need, at one pair a step at best)
        let shortest = steps_per_run.iter().copied().min().unwrap_or(1).max(1);
        let batch = (n - pairs.len()).div_ceil(shortest).clamp(1, RUNS_PER_BATCH);
        let runs: Vec<(u64, u64, Option<u64>, usize)> = (0..batch)
            .map(|_| {
                let scene = rng.random_range(0..scene_limit);
                let stream = rng.random::<u64>();
                // drawn only when closed-loop recording is asked for, so the oracle's pairs stay as they were
                let model_seed = match closed_loop {
                    Some(c) if c.share > 0.0 && rng.random::<f32>() < c.share => Some(rng.random::<u64>()),
                    _ => None,
                };
                // drawn only for a mix of lengths, so one length's pairs stay as they were
                let steps = match steps_per_run {
                    [] => 1,
                    [one] => *one,
                    many => many[rng.random_range(0..many.len())],
                };
                (scene, stream, model_seed, steps)
            })
            .collect();
        let recorded: Vec<Result<Vec<Recorded>>> = runs
            .par_iter()
            .map(|&(scene, stream, model_seed, steps)| {
                let model = match (closed_loop, model_seed) {
                    (Some(c), Some(seed)) => {
                        let options = sgam_model::RefinerOptions { seed, ..c.options };
                        // on the CPU kernels in any build: 16 runs at once would queue on one GPU
                        // in a wgpu build (the lent machine's), where each run has a core
                        Some((
                            sgam_model::VqRefiner::from_bytes_cpu(c.weights, None, options)
                                .map_err(|source| PipelineError::ModelLoad { path: None, source })?,
                            c.steps,
                        ))
                    }
                    _ => None,
                };
                let filters = closed_loop.is_some_and(|c| c.filters);
                record_run(scene, steps, 256, &mut ChaCha8Rng::seed_from_u64(stream), model, filters)
            })
            .collect();
        for recorded in recorded {
            let recorded = recorded?;
            if pairs.len() >= n {
                break;
            }
            for chunk in recorded.chunks(8) {
                let truths: Vec<&RgbdFrame> = chunk.iter().map(|r| &r.truth).collect();
                let intr: Vec<Intrinsics> = chunk.iter().map(|r| r.guidance.camera.intrinsics).collect();
                let codes = target_codes(target.0, target.1, &truths, &intr, &device)?;
                for (rec, codes) in chunk.iter().zip(&codes) {
                    if pairs.len() < n {
                        if let Some(p) = crop_pair(rec, codes, crop, factor, rng) {
                            pairs.push(p);
                        }
                    }
                }
            }
            progress(pairs.len());
        }
    }
    Ok(pairs)
}

/// Generator runs recorded at once ([`collect`]); fixed, so the pairs of a seed are the same on
/// any number of cores (session 23: 50 pairs/s on a lent machine's 16 cores, 16.5 on this
/// project's 2, where one run at a time recorded 6.5).
const RUNS_PER_BATCH: usize = 16;

/// Version of the pairs' stream and cache format (4: closed-loop runs may pass generation's
/// invented-pixel filters, [`CacheKey::closed_loop_filters`], a field a binary before it would
/// ignore and so take a filtered cache for an unfiltered one; 3: runs recorded in parallel
/// batches, each run on its own stream; 2: all six trajectory shapes).
pub const CACHE_VERSION: u32 = 4;

/// What a pair cache was recorded with; a cache is used only when all of it matches.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CacheKey {
    /// Format version.
    pub version: u32,
    /// Pairs recorded.
    pub pairs: usize,
    /// Steps per generator run (the first length of a mix).
    pub steps_per_run: usize,
    /// The run lengths drawn from when they are a mix ([`collect`]); empty for one length
    /// (and in caches recorded before mixes).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub steps_per_run_mix: Vec<usize>,
    /// Crop side, pixels.
    pub crop: u32,
    /// Training scenes 0..scenes.
    pub scenes: u64,
    /// RNG seed and stream.
    pub seed: u64,
    /// RNG stream.
    pub stream: u64,
    /// Share of closed-loop runs ([`ClosedLoop`]; absent in caches recorded before it: 0).
    #[serde(default)]
    pub closed_loop: f32,
    /// Share of a closed-loop run's steps the model completes ([`ClosedLoop::steps`]; absent in
    /// caches recorded before it: 1).
    #[serde(default = "all_steps")]
    pub closed_loop_steps: f32,
    /// CRC-32 of the closed-loop model's weights ([`ClosedLoop::weights`]; `None` for the
    /// oracle's runs and in caches recorded before it). Asked for as `None` by [`read_cache`], it
    /// matches any model: a resumed run reads back its own pairs, whose recording model was its
    /// starting point, not the weights it resumes with.
    #[serde(default)]
    pub recorded_with: Option<u32>,
    /// Closed-loop runs passed generation's invented-pixel policy ([`ClosedLoop::filters`];
    /// absent in caches recorded before it: false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub closed_loop_filters: bool,
}

const CACHE_MAGIC: &[u8; 8] = b"SGAMPAIR";

fn all_steps() -> f32 {
    1.0
}

impl CacheKey {
    /// The key's run-length fields for the lengths `collect` draws from.
    pub fn run_lengths(steps_per_run: &[usize]) -> (usize, Vec<usize>) {
        match steps_per_run {
            [one] => (*one, Vec::new()),
            many => (many.first().copied().unwrap_or(0), many.to_vec()),
        }
    }
}

/// Writes pairs atomically: magic, key JSON length + JSON, then per pair its size, intrinsics,
/// 8-bit colour, f32 depth, mask bytes and u32 codes; a CRC-32 of everything before it last.
/// Colour is stored as 8 bits ([`crop_pair`] rounds it so, so recorded and cached pairs are the
/// same; the warp's bilinear colour is within half a level of it).
pub fn write_cache(path: &std::path::Path, key: &CacheKey, pairs: &[CodePair]) -> Result<()> {
    let mut b: Vec<u8> = Vec::new();
    b.extend_from_slice(CACHE_MAGIC);
    let json =
        serde_json::to_vec(key).map_err(|e| PipelineError::Corrupt { path: path.to_path_buf(), msg: e.to_string() })?;
    b.extend_from_slice(&(json.len() as u64).to_le_bytes());
    b.extend_from_slice(&json);
    b.extend_from_slice(&(pairs.len() as u64).to_le_bytes());
    for p in pairs {
        let k = p.intrinsics;
        for v in [k.width, k.height] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        for v in [k.fx, k.fy, k.cx, k.cy] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend(p.input.colour.data.iter().flat_map(|c| c.map(|x| (x.clamp(0.0, 1.0) * 255.0).round() as u8)));
        b.extend(p.input.depth_m.data.iter().flat_map(|d| d.to_le_bytes()));
        b.extend(p.missing.iter().map(|m| *m as u8));
        b.extend_from_slice(&(p.codes.len() as u64).to_le_bytes());
        b.extend(p.codes.iter().flat_map(|c| c.to_le_bytes()));
    }
    let crc = crc32fast::hash(&b);
    b.extend_from_slice(&crc.to_le_bytes());
    sgam_io::write_atomic(path, |w| std::io::Write::write_all(w, &b))?;
    Ok(())
}

/// Reads a cache written by [`write_cache`]; `Ok(None)` when it was recorded with another key
/// (a key asking for no [`CacheKey::recorded_with`] takes a cache recorded with any model).
pub fn read_cache(path: &std::path::Path, key: &CacheKey) -> Result<Option<Vec<CodePair>>> {
    let bytes = std::fs::read(path).map_err(|e| sgam_io::IoError::Io { path: path.to_path_buf(), source: e })?;
    let bad = |what: &str| PipelineError::Corrupt { path: path.to_path_buf(), msg: what.to_string() };
    if bytes.len() < 20 || &bytes[..8] != CACHE_MAGIC {
        return Err(bad("not a pair cache"));
    }
    let (body, crc) = bytes.split_at(bytes.len() - 4);
    if crc32fast::hash(body) != u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]) {
        return Err(bad("checksum mismatch (corrupt or truncated); delete it to record again"));
    }
    let mut at = 8usize;
    let mut take = |n: usize| -> Result<&[u8]> {
        let end = at.checked_add(n).ok_or_else(|| bad("truncated"))?;
        let s = body.get(at..end).ok_or_else(|| bad("truncated"))?;
        at = end;
        Ok(s)
    };
    let u64_of = |s: &[u8]| u64::from_le_bytes(s.try_into().unwrap_or([0; 8]));
    let json_len = u64_of(take(8)?) as usize;
    let mut stored: CacheKey = serde_json::from_slice(take(json_len)?).map_err(|e| bad(&format!("key: {e}")))?;
    if key.recorded_with.is_none() {
        stored.recorded_with = None;
    }
    if &stored != key {
        return Ok(None);
    }
    let n = u64_of(take(8)?) as usize;
    // a record takes at least 32 bytes: never reserve more than the file can hold
    let mut pairs = Vec::with_capacity(n.min(body.len() / 32));
    for _ in 0..n {
        let u32_of = |s: &[u8]| u32::from_le_bytes(s.try_into().unwrap_or([0; 4]));
        let (w, h) = (u32_of(take(4)?), u32_of(take(4)?));
        let f: Vec<f32> = (0..4)
            .map(|_| take(4).map(|s| f32::from_le_bytes(s.try_into().unwrap_or([0; 4]))))
            .collect::<Result<_>>()?;
        let hw = (w as usize).checked_mul(h as usize).filter(|&x| x <= 1 << 24).ok_or_else(|| bad("bad size"))?;
        let colour = take(hw * 3)?
            .chunks_exact(3)
            .map(|c| [c[0] as f32 / 255.0, c[1] as f32 / 255.0, c[2] as f32 / 255.0])
            .collect();
        let depth = take(hw * 4)?.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let missing = take(hw)?.iter().map(|m| *m != 0).collect();
        let nc = u64_of(take(8)?) as usize;
        if nc > hw {
            return Err(bad("bad code count"));
        }
        let codes = take(nc * 4)?.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let intrinsics =
            Intrinsics::try_new(w, h, f[0], f[1], f[2], f[3]).map_err(|e| bad(&format!("intrinsics: {e}")))?;
        pairs.push(CodePair {
            input: RgbdFrame {
                colour: Image { width: w, height: h, data: colour },
                depth_m: Image { width: w, height: h, data: depth },
            },
            missing,
            intrinsics,
            codes,
        });
    }
    Ok(Some(pairs))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use sgam_map::SourceView;

    #[test]
    fn recorded_guidance_is_the_one_guidance_function_of_the_same_map_and_sources() {
        // a generator run records what it handed the refiner; rebuilding the map from the same
        // frames and calling render_guidance with the same sources must give the same image
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let recorded = record_run(11, 4, 64, &mut rng, None, false).unwrap();
        assert_eq!(recorded.len(), 4);
        let config = clevr_generator_config(11);
        // replay: the map holds the seed and steps 1..3; the guidance of step 4 comes from it
        let renderer = Renderer::new(&Scene::generate(11, &SceneConfig::default()));
        let mut map = TsdfMap::new(config.tsdf);
        let first = &recorded[0].guidance.camera;
        // the seed camera: record_run's first draws are the start position
        let seed_cam = {
            let mut rng2 = ChaCha8Rng::seed_from_u64(4);
            let start =
                Vec3::new(rng2.random_range(-26.0..2.0), rng2.random_range(-26.0..2.0), sgam_synth::CAMERA_HEIGHT_M);
            blender_camera(start, sgam_synth::CAMERA_PITCH_RAD, 0.0, first.intrinsics)
        };
        let seed_frame = renderer.render(&seed_cam, &RenderConfig::default()).frame;
        let mut frames: Vec<(Camera, RgbdFrame)> = vec![(seed_cam, seed_frame)];
        for r in &recorded[..3] {
            frames.push((r.guidance.camera, r.truth.clone()));
        }
        for (c, f) in &frames {
            let mut f = f.clone();
            crate::quantise_colour(&mut f.colour);
            map.integrate(&f, c);
            map.update_mesh();
        }
        let target = &recorded[3].guidance;
        // sources: the nearest 5 within 1 m of the target, nearest first (the keyframe rule)
        let mut near: Vec<(f32, usize)> = frames
            .iter()
            .enumerate()
            .map(|(i, (c, _))| ((c.centre_world() - target.camera.centre_world()).length(), i))
            .filter(|(d, _)| *d <= config.source_radius_m)
            .collect();
        near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let quantised: Vec<(Camera, RgbdFrame)> = frames
            .iter()
            .map(|(c, f)| {
                let mut f = f.clone();
                crate::quantise_colour(&mut f.colour);
                (*c, f)
            })
            .collect();
        let views: Vec<SourceView<'_>> = near
            .iter()
            .take(config.k_sources)
            .map(|(_, i)| SourceView { camera: &quantised[*i].0, frame: &quantised[*i].1 })
            .collect();
        let (g, _) = crate::render_guidance(&mut map, &target.camera, &views, &config.warp, target.seed);
        assert_eq!(g.missing, target.missing);
        assert_eq!(g.frame, target.frame);
        assert!(target.missing.iter().any(|m| !m), "the guidance shows the map");
    }

    #[test]
    fn collected_pairs_do_not_depend_on_the_number_of_threads() {
        let device = sgam_model::default_device();
        let (model, config) = sgam_model::refiner::load_model_bytes(crate::BUNDLED_MODEL, None, &device).unwrap();
        let collect_on = |threads: usize, lengths: &[usize]| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let mut rng = ChaCha8Rng::seed_from_u64(5);
                collect(10, lengths, 64, 1000, (&model, &config), None, &mut rng, &mut |_| {}).unwrap()
            })
        };
        let (one, two) = (collect_on(1, &[4]), collect_on(2, &[4]));
        assert_eq!(one.len(), 10);
        assert_eq!(one, two, "the pairs changed with the thread count");
        // pairs of several runs (a batch of 3 runs of 4 steps): not all from one scene's frames
        assert!(one.iter().any(|p| p.codes != one[0].codes));
        // a mix of run lengths: its own pairs, as independent of the threads
        let (mix_one, mix_two) = (collect_on(1, &[2, 6]), collect_on(2, &[2, 6]));
        assert_eq!(mix_one.len(), 10);
        assert_eq!(mix_one, mix_two, "the mixed pairs changed with the thread count");
        assert_ne!(mix_one, one, "a mix of lengths recorded the one length's pairs");
    }

    #[test]
    fn a_closed_loop_run_grows_its_map_with_the_model_and_keeps_the_truth_as_target() {
        let options = crate::settings::SamplingSettings::default().refiner_options();
        let model = sgam_model::VqRefiner::from_bytes(crate::BUNDLED_MODEL, None, options).unwrap();
        let oracle = record_run(11, 6, 64, &mut ChaCha8Rng::seed_from_u64(4), None, false).unwrap();
        let closed = record_run(11, 6, 64, &mut ChaCha8Rng::seed_from_u64(4), Some((model, 1.0)), false).unwrap();
        assert_eq!(closed.len(), oracle.len());
        // the same path and the same true frames: only the map differs
        for (a, b) in oracle.iter().zip(&closed) {
            assert_eq!(a.guidance.camera, b.guidance.camera);
            assert_eq!(a.truth, b.truth);
        }
        // the first step sees the seed alone, in both
        assert_eq!(oracle[0].guidance.frame, closed[0].guidance.frame);
        // later steps see the model's inventions re-rendered: some guidance differs
        let differing = oracle.iter().zip(&closed).filter(|(a, b)| a.guidance.frame != b.guidance.frame).count();
        assert!(differing > 0, "every closed-loop guidance equals the oracle's");
        assert!(oracle.iter().any(|r| r.guidance.missing.iter().any(|m| *m)), "the path uncovers nothing");
    }

    #[test]
    fn a_filtered_closed_loop_run_fuses_what_generation_would_and_an_oracle_run_ignores_filters() {
        let options = crate::settings::SamplingSettings::default().refiner_options();
        let model = || sgam_model::VqRefiner::from_bytes(crate::BUNDLED_MODEL, None, options).unwrap();
        let run = |m, filters| record_run(11, 8, 128, &mut ChaCha8Rng::seed_from_u64(4), m, filters).unwrap();
        let (raw, filtered) = (run(Some((model(), 1.0)), false), run(Some((model(), 1.0)), true));
        assert_eq!(raw.len(), filtered.len());
        assert!(raw.iter().zip(&filtered).all(|(a, b)| a.truth == b.truth), "the targets are the truth either way");
        let differing = raw.iter().zip(&filtered).filter(|(a, b)| a.guidance.frame != b.guidance.frame).count();
        assert!(differing > 0, "the invented-pixel policy changed no later guidance");
        // the oracle's steps invent nothing: the filters are not applied to them, in an oracle
        // run or in a closed-loop run whose share gives the model no step
        let oracle = run(None, false);
        for other in [run(None, true), run(Some((model(), 0.0)), true)] {
            assert!(oracle.iter().zip(&other).all(|(a, b)| a.guidance.frame == b.guidance.frame));
        }
    }

    #[test]
    fn a_closed_loop_run_leaves_the_steps_outside_its_share_to_the_oracle() {
        let options = crate::settings::SamplingSettings::default().refiner_options();
        let model = || sgam_model::VqRefiner::from_bytes(crate::BUNDLED_MODEL, None, options).unwrap();
        let run = |m| record_run(11, 6, 64, &mut ChaCha8Rng::seed_from_u64(4), m, false).unwrap();
        let (oracle, none, half) = (run(None), run(Some((model(), 0.0))), run(Some((model(), 0.5))));
        // no step of the model's: the oracle's run exactly
        assert_eq!(none.len(), oracle.len());
        for (a, b) in oracle.iter().zip(&none) {
            assert_eq!(a.guidance.frame, b.guidance.frame);
        }
        // half of them: the model's inventions show in some later guidance, the truth stays
        let differing = oracle.iter().zip(&half).filter(|(a, b)| a.guidance.frame != b.guidance.frame).count();
        assert!(differing > 0, "no step of the half-share run was the model's");
        assert!(oracle.iter().zip(&half).all(|(a, b)| a.truth == b.truth));
    }

    #[test]
    fn pairs_come_from_every_trajectory_shape_in_the_stated_shares() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut counts = [0usize; 5];
        let n = 20_000;
        for _ in 0..n {
            let k = match draw_shape(&mut rng) {
                Shape::Zigzag(_) => 0,
                Shape::Boustrophedon(_) => 1,
                Shape::Line(_) => 2,
                Shape::Circle(r) => {
                    assert!((2.0..8.0).contains(&r), "circle radius {r}");
                    3
                }
                Shape::Spiral(_) => 4,
            };
            counts[k] += 1;
        }
        // zig-zag 7/20, boustrophedon 2/20, line 3/20, circle 3/20, spiral 5/20
        for (c, want) in counts.iter().zip([0.35, 0.10, 0.15, 0.15, 0.25]) {
            let share = *c as f64 / n as f64;
            assert!((share - want).abs() < 0.015, "share {share} against {want} ({counts:?})");
        }
    }

    #[test]
    fn pair_cache_round_trips_and_rejects_other_keys_and_corruption() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let k = Intrinsics::from_fov_x(16, 16, 1.0);
        let pairs: Vec<CodePair> = (0..3)
            .map(|i| {
                let colour = (0..256).map(|_| [rng.random_range(0..=255) as f32 / 255.0, 128.0 / 255.0, 1.0]).collect();
                let depth = (0..256).map(|_| rng.random_range(7.0..16.0)).collect();
                CodePair {
                    input: RgbdFrame {
                        colour: Image { width: 16, height: 16, data: colour },
                        depth_m: Image { width: 16, height: 16, data: depth },
                    },
                    missing: (0..256).map(|p| (p + i) % 3 == 0).collect(),
                    intrinsics: Intrinsics { cx: 3.0 - i as f32, ..k },
                    codes: (0..4).map(|c| c * 100 + i as u32).collect(),
                }
            })
            .collect();
        let key = CacheKey {
            version: 1,
            pairs: 3,
            steps_per_run: 5,
            steps_per_run_mix: Vec::new(),
            crop: 16,
            scenes: 10,
            seed: 2,
            stream: 1,
            closed_loop: 0.0,
            closed_loop_steps: 1.0,
            recorded_with: None,
            closed_loop_filters: false,
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pairs.bin");
        write_cache(&path, &key, &pairs).unwrap();
        let back = read_cache(&path, &key).unwrap().unwrap();
        assert_eq!(back.len(), 3);
        for (a, b) in pairs.iter().zip(&back) {
            assert_eq!(a.input, b.input);
            assert_eq!(a.missing, b.missing);
            assert_eq!(a.intrinsics, b.intrinsics);
            assert_eq!(a.codes, b.codes);
        }
        assert!(read_cache(&path, &CacheKey { seed: 3, ..key.clone() }).unwrap().is_none());
        assert!(read_cache(&path, &CacheKey { closed_loop_steps: 0.5, ..key.clone() }).unwrap().is_none());
        assert!(read_cache(&path, &CacheKey { closed_loop_filters: true, ..key.clone() }).unwrap().is_none());
        // a mix of run lengths is another recording than its first length alone
        let (first, mix) = CacheKey::run_lengths(&[5, 120]);
        assert!(read_cache(&path, &CacheKey { steps_per_run: first, steps_per_run_mix: mix, ..key.clone() })
            .unwrap()
            .is_none());
        // pairs recorded with one closed-loop model: another model's run refuses them, a resumed
        // run (asking for none) takes them
        let closed = CacheKey { closed_loop: 0.5, recorded_with: Some(7), ..key.clone() };
        let closed_path = dir.path().join("closed.bin");
        write_cache(&closed_path, &closed, &pairs).unwrap();
        assert!(read_cache(&closed_path, &closed).unwrap().is_some());
        assert!(read_cache(&closed_path, &CacheKey { recorded_with: Some(8), ..closed.clone() }).unwrap().is_none());
        assert!(read_cache(&closed_path, &CacheKey { recorded_with: None, ..closed.clone() }).unwrap().is_some());
        // a cache written before the closed-loop options existed reads as the oracle's, every step
        let old: CacheKey = serde_json::from_str(
            r#"{"version":1,"pairs":3,"steps_per_run":5,"crop":16,"scenes":10,"seed":2,"stream":1}"#,
        )
        .unwrap();
        assert_eq!(old, key);
        let mut bytes = std::fs::read(&path).unwrap();
        let mid = bytes.len() / 2;
        bytes[mid] ^= 0x10;
        std::fs::write(&path, &bytes).unwrap();
        let err = read_cache(&path, &key).unwrap_err().to_string();
        assert!(err.contains("checksum") && err.contains("pairs.bin"), "{err}");
    }
}
