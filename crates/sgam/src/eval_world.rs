//! `sgam eval world` and `sgam eval table`: judge generated worlds against the true world of
//! the same held-out seed along the same trajectory (world-level statistics, KID, loop
//! consistency).
//!
//! For each held-out seed scene (from 1,000,000; never used in training) the refiner and the
//! oracle (ground truth of the synthetic world) are unrolled along the same trajectory by the
//! real generator (`sgam generate`), and the two final meshes are compared over the area that
//! is *new* (outside the seed frame's ground footprint grown by 1 m):
//! - object statistics (`sgam_metrics::world`): objects per 100 m², footprints, cover, colour
//!   saturation, ground roughness;
//! - the paper's scene metrics (Table 2): the new area cut into square regions, each voxelised
//!   into a 15³ occupancy histogram; JSD / MMD / COV / MinDist / 1-NNA of the generated regions
//!   against the oracle's;
//! - KID between the generated frames and the oracle's frames (real renders of held-out
//!   scenes), on features of a frozen encoder shipped in the repo (`models/features.safetensors`:
//!   the stage-1/2 compact encoder trained on the synthetic world; per frame the mean and
//!   standard deviation of each of its 64 latent channels over the 32x32 cells).
//!
//! Runs are kept under the output folder (`seed-N/LABEL`) and reused when complete, so the
//! oracle worlds are grown once for every refiner of a table.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use serde::Serialize;
use serde_json::json;
use sgam_core::{TriMesh, Vec2, Vec3};
use sgam_metrics::world::{Exclusion, ShapeSummary, WorldStats, WorldStatsConfig};

use crate::generate::GenerateArgs;
use sgam_pipeline::settings::{
    FreeSpace, InventedPixelSettings, MapSettings, OutputArgs, PathSettings, RefinerKind, RefinerSettings,
    SamplingSettings, TrajectoryKind, DEFAULT_CELLS_PER_PASS, DEFAULT_FLYING_PIXELS, DEFAULT_TOP_K,
};
use sgam_pipeline::RunSettings;
use sgam_pipeline::HELD_OUT_SEED_BASE;

/// The frozen feature extractor of the image distribution metrics (KID): the compact encoder
/// as trained in sessions 2-3, kept apart from the bundled refiner so scores stay comparable
/// when the refiner is retrained.
pub const FEATURE_MODEL: &[u8] = include_bytes!("../../../models/features.safetensors");

/// Arguments of `sgam eval world`.
#[derive(Debug, Clone, Args)]
#[command(
    after_help = "Examples:\n  sgam eval world                         # 4 held-out seeds x 400-step zig-zag, bundled model\n  sgam eval world --refiner null --json   # the push-pull stand-in\n  sgam eval world --paper                 # the paper's 10 seeds x 900 steps\n  sgam eval world --first-seed 7 --seeds 2 # tune on training scenes, not held-out ones\n\nEach seed's world is grown twice along the same trajectory, by the refiner and by the oracle\n(ground truth); runs are kept in --out (seed-N/LABEL) and reused. Statistics are computed over\nthe area outside the seed frame's footprint grown by 1 m (the area the refiner invented)."
)]
pub struct WorldArgs {
    /// Held-out seed scenes (1000000, 1000001, ...).
    #[arg(long, default_value_t = 4)]
    pub seeds: u64,
    /// First seed scene. Judge on the held-out seeds (the default, 1000000); tune on training
    /// seeds (below 1000000) so the held-out ones stay unseen.
    #[arg(long, default_value_t = HELD_OUT_SEED_BASE)]
    pub first_seed: u64,
    /// Generation steps per world.
    #[arg(long, default_value_t = 400)]
    pub steps: usize,
    /// The camera path (the same for the refiner and the oracle).
    #[command(flatten)]
    pub path: PathSettings,
    /// The refiner judged.
    #[command(flatten)]
    pub refiner: RefinerSettings,
    /// Its sampling.
    #[command(flatten)]
    pub sampling: SamplingSettings,
    /// Its invented-pixel policy (never applied to the oracle).
    #[command(flatten)]
    pub invented: InventedPixelSettings,
    /// The map and sources (the same for the refiner and the oracle).
    #[command(flatten)]
    pub map: MapSettings,
    /// The paper's protocol: 10 seeds x 900 steps (overrides --seeds and --steps).
    #[arg(long)]
    pub paper: bool,
    /// Side of the square regions of the scene metrics, metres.
    #[arg(long, default_value_t = 5.0)]
    pub region_size: f32,
    /// Folder for the worlds (default runs/eval-world).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Keep each finished world's resume files (snapshot.bin, map.bin: half of a world's 360 MB).
    /// By default they are deleted once the world is finished: a finished world is reused from
    /// its mesh, frames and run.json, and never resumed.
    #[arg(long)]
    pub keep_snapshots: bool,
    /// Folder of the loop-consistency runs, which do not depend on the trajectory (default: the
    /// worlds' folder); eval table's trajectory rows share the zig-zag's.
    #[arg(skip)]
    pub loop_out: Option<PathBuf>,
    /// Print only the JSON line.
    #[arg(long)]
    pub json: bool,
}

impl WorldArgs {
    /// The folder name of this refiner's worlds: its weights (CRC-32) and every option that
    /// changes them, so worlds grown otherwise are never reused.
    pub fn label(&self) -> String {
        let r = &self.refiner;
        let kind = r.effective();
        let mut label = match kind {
            RefinerKind::Oracle => return self.oracle_label(),
            _ if r.no_refine => "no-refine".to_string(),
            RefinerKind::Null => "null".to_string(),
            // the model's weights name its runs: another model never reuses them
            _ => {
                let bytes = match &r.model {
                    Some(p) => std::fs::read(p).unwrap_or_default(),
                    None => sgam_pipeline::BUNDLED_MODEL.to_vec(),
                };
                let stem = match &r.model {
                    Some(p) => {
                        p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "model".into())
                    }
                    None => "model".to_string(),
                };
                format!("{stem}-{:08x}", crc32fast::hash(&bytes))
            }
        };
        let s = &self.sampling;
        if matches!(kind, RefinerKind::Auto | RefinerKind::Model) {
            label.push_str(&format!("-t{}", s.temperature));
            if s.cells_per_pass != DEFAULT_CELLS_PER_PASS {
                label.push_str(&format!("-c{}", s.cells_per_pass));
            }
            if s.top_k != DEFAULT_TOP_K {
                label.push_str(&format!("-k{}", s.top_k));
            }
            // always named when on, so worlds grown before it existed keep their folder
            if s.within_temperature > 0.0 {
                label.push_str(&format!("-w{}", s.within_temperature));
            }
            if s.seed != 0 {
                label.push_str(&format!("-s{}", s.seed));
            }
            if s.regenerate_observed {
                label.push_str("-regen");
            }
        }
        let p = &self.invented;
        if kind != RefinerKind::Oracle {
            if p.ground_snap > 0.0 {
                label.push_str(&format!("-g{}", p.ground_snap));
            }
            if p.flying_pixels != DEFAULT_FLYING_PIXELS {
                label.push_str(&format!("-f{:?}", p.flying_pixels).to_lowercase());
            }
            // always named when on, so worlds grown before it existed keep their folder
            if p.free_space == FreeSpace::Carve {
                label.push_str("-carve");
            }
        }
        if self.map.no_map {
            label.push_str("-nomap");
        }
        label + &self.map_suffix()
    }

    /// The oracle's folder name: the map options name it too.
    pub fn oracle_label(&self) -> String {
        format!("oracle{}", self.map_suffix())
    }

    /// Empty for the default map, else a hash of the map options given.
    fn map_suffix(&self) -> String {
        let map = MapSettings { no_map: false, ..self.map.clone() };
        if map == MapSettings::default() {
            return String::new();
        }
        format!("-map{:08x}", crc32fast::hash(format!("{map:?}").as_bytes()))
    }

    fn seeds_steps(&self) -> (u64, usize) {
        if self.paper {
            (10, 900)
        } else {
            (self.seeds, self.steps)
        }
    }

    fn validate(&self) -> Result<()> {
        let (seeds, steps) = self.seeds_steps();
        if seeds == 0 || seeds > 1000 {
            bail!("--seeds {seeds} must be in 1..=1000");
        }
        if self.first_seed > u64::MAX - seeds {
            bail!("--first-seed {} + --seeds {seeds} overflows the seed range", self.first_seed);
        }
        if !(10..=100_000).contains(&steps) {
            bail!("--steps {steps} must be in 10..=100000");
        }
        self.path.validate()?;
        self.refiner.validate()?;
        self.sampling.validate()?;
        self.invented.validate()?;
        self.map.validate()?;
        if !(self.region_size.is_finite() && self.region_size >= 1.0 && self.region_size <= 100.0) {
            bail!("--region-size {} must be between 1 and 100 metres", self.region_size);
        }
        if let Some(s) = self.path.step {
            if s >= 10.0 {
                bail!("--step {s} must be a positive distance below 10 m");
            }
        }
        Ok(())
    }
}

/// The run of one of this evaluation's worlds: the refiner of `kind` with the evaluated options
/// (the oracle takes none of the refiner's), along the evaluated path, no fly-through.
fn run_settings(args: &WorldArgs, kind: RefinerKind, seed_scene: u64, steps: usize) -> RunSettings {
    let mut run = RunSettings {
        steps,
        path: args.path.clone(),
        map: args.map.clone(),
        outputs: OutputArgs { no_video: true, ..OutputArgs::default() },
        ..RunSettings::clevr(seed_scene)
    };
    if kind == RefinerKind::Oracle {
        run.refiner = RefinerSettings::kind(RefinerKind::Oracle);
        run.map.no_map = false; // an ablation of the refiner's world, not the true one
    } else {
        run.refiner = args.refiner.clone();
        run.sampling = args.sampling.clone();
        run.invented = args.invented.clone();
    }
    run
}

/// Grows (or reuses) one world; returns its folder.
fn grow(args: &WorldArgs, seed_scene: u64, kind: RefinerKind, label: &str, root: &Path) -> Result<PathBuf> {
    let (_, steps) = args.seeds_steps();
    let dir = root.join(format!("seed-{seed_scene}")).join(label);
    if dir.join("run.json").exists() && dir.join("mesh.ply").exists() {
        let run: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("run.json"))?)
            .with_context(|| format!("{}: corrupt run.json", dir.display()))?;
        // reuse only a world grown the same way: the resolved run (seed, trajectory, steps,
        // ablations, sampling) equal to the one these options give; the model file may differ
        let want = run_settings(args, kind, seed_scene, steps).resolve()?;
        let stored: Option<sgam_pipeline::RunConfig> = serde_json::from_value(run["config"].clone()).ok();
        if stored.is_none() {
            bail!(
                "{}: run.json holds no resolved run config (grown by an older sgam); remove the folder or choose another --out",
                dir.display()
            );
        }
        // the whole resolved run, but for the model file (the label names its weights) and what
        // was written besides the frames: a new field of the run is compared without a change here
        let comparable = |r: &sgam_pipeline::RunConfig| sgam_pipeline::RunConfig {
            refiner: match &r.refiner {
                sgam_pipeline::RefinerSpec::Model { options, .. } => {
                    sgam_pipeline::RefinerSpec::Model { model: None, options: *options }
                }
                other => other.clone(),
            },
            outputs: want.outputs,
            ..r.clone()
        };
        let same = run["steps"].as_u64() == Some(steps as u64)
            && stored.is_some_and(|got| comparable(&got) == comparable(&want));
        if same {
            if !args.keep_snapshots {
                drop_resume_files(&dir)?;
            }
            return Ok(dir);
        }
        bail!(
            "{} holds a world grown with other options (steps, trajectory, step, temperature, cells per pass, top-k, within-class temperature, ground prior, flying pixels, free space, map or ablations); \
             remove it or choose another --out",
            dir.display()
        );
    }
    if dir.join("snapshot.bin").exists() {
        crate::generate::run(GenerateArgs::resume(dir.clone()))?;
    } else {
        crate::generate::run(GenerateArgs::new(run_settings(args, kind, seed_scene, steps), Some(dir.clone())))?;
    }
    if !args.keep_snapshots {
        drop_resume_files(&dir)?;
    }
    Ok(dir)
}

/// Deletes a finished world's resume files (its snapshot and map); the world stays reusable
/// from its mesh, frames and run.json.
fn drop_resume_files(dir: &Path) -> Result<()> {
    if !dir.join("mesh.ply").exists() {
        return Ok(());
    }
    for name in [sgam_pipeline::snapshot::SNAPSHOT_FILE, "map.bin"] {
        match std::fs::remove_file(dir.join(name)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(e).with_context(|| format!("{}: cannot delete {name}", dir.display()))
            }
            _ => {}
        }
    }
    Ok(())
}

/// Steps of the loop trajectory of the consistency check.
const LOOP_STEPS: usize = 48;

/// Consistency on revisits: a circle of radius 3 m that starts at the seed and returns to it
/// (`LOOP_STEPS` poses around, then the seed pose again); PSNR and SSIM of the final frame,
/// generated at the seed pose after a full loop, against the seed frame.
fn loop_consistency(
    args: &WorldArgs,
    seed_scene: u64,
    kind: RefinerKind,
    label: &str,
    root: &Path,
) -> Result<(f64, f64)> {
    let dir = root.join(format!("seed-{seed_scene}")).join(format!("{label}-loop"));
    let last = sgam_pipeline::Keyframes::frame_paths(&dir, LOOP_STEPS).0;
    if !(dir.join("run.json").exists() && last.exists()) {
        if dir.exists() {
            std::fs::remove_dir_all(&dir)
                .with_context(|| format!("{}: cannot clear an unfinished loop run", dir.display()))?;
        }
        std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
        let seed = sgam_pipeline::synthetic_seed_camera(256);
        let mut poses = sgam_core::trajectory::circle_poses(&seed.world_from_camera, LOOP_STEPS, 3.0);
        poses.push(seed.world_from_camera);
        let traj = root.join(format!("seed-{seed_scene}")).join("loop-kitti.txt");
        sgam_io::write_kitti_trajectory(&traj, &poses)?;
        let mut run = run_settings(args, kind, seed_scene, LOOP_STEPS);
        run.path = PathSettings { trajectory_file: Some(traj), ..PathSettings::kind(TrajectoryKind::File) };
        crate::generate::run(GenerateArgs::new(run, Some(dir.join("run"))))?;
        for name in ["run.json", "rgb"] {
            std::fs::rename(dir.join("run").join(name), dir.join(name))
                .with_context(|| format!("{}: cannot keep the loop's {name}", dir.display()))?;
        }
        std::fs::remove_dir_all(dir.join("run")).with_context(|| format!("{}: cannot tidy", dir.display()))?;
    }
    let first = sgam_io::read_rgb(&sgam_pipeline::Keyframes::frame_paths(&dir, 0).0)?;
    let back = sgam_io::read_rgb(&last)?;
    Ok((
        sgam_metrics::psnr(&back, &first, None).unwrap_or(f64::NAN),
        sgam_metrics::ssim(&back, &first, None).unwrap_or(f64::NAN),
    ))
}

/// The seed frame's footprint on the ground plane: its four corner rays cut with the plane
/// z = `sgam_synth::GROUND_Z_M`.
fn seed_footprint(res: u32) -> Vec<Vec2> {
    let camera = sgam_pipeline::synthetic_seed_camera(res);
    let k = camera.intrinsics;
    let (w, h) = (k.width as f32, k.height as f32);
    let corners = [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)];
    let origin = camera.world_from_camera.transform_point(Vec3::ZERO);
    corners
        .iter()
        .filter_map(|&(u, v)| {
            let dir = camera.world_from_camera.transform_vector(k.ray_z1(Vec2::new(u - 0.5, v - 0.5)));
            let t = (sgam_synth::GROUND_Z_M - origin.z) / dir.z;
            (t.is_finite() && t > 0.0).then(|| {
                let p = origin + dir * t;
                Vec2::new(p.x, p.y)
            })
        })
        .collect()
}

/// Image features of a run's frames for KID: per frame, the mean and standard deviation of each
/// latent channel of the frozen feature encoder (every `stride`-th frame, seed excluded).
fn frame_features(dir: &Path, frames: usize, stride: usize, extractor: &FeatureExtractor) -> Result<Vec<Vec<f32>>> {
    let mut out = Vec::new();
    for i in (1..frames).step_by(stride.max(1)) {
        let (rgb, depth) = sgam_pipeline::Keyframes::frame_paths(dir, i);
        let colour = sgam_io::read_rgb(&rgb)?;
        let depth_m = sgam_io::read_npy_f32(&depth)?;
        out.push(extractor.features(&sgam_core::RgbdFrame { colour, depth_m })?);
    }
    Ok(out)
}

/// The frozen encoder of [`FEATURE_MODEL`].
pub struct FeatureExtractor {
    model: sgam_model::VqModel,
    config: sgam_model::ModelConfig,
    device: sgam_model::burn::tensor::Device,
}

impl std::fmt::Debug for FeatureExtractor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FeatureExtractor").finish_non_exhaustive()
    }
}

impl FeatureExtractor {
    /// Loads the shipped feature encoder.
    pub fn new() -> Result<Self> {
        let device = sgam_model::default_device();
        let (model, config) = sgam_model::refiner::load_model_bytes(FEATURE_MODEL, None, &device)
            .context("the feature model (models/features.safetensors) cannot be loaded")?;
        Ok(Self { model, config, device })
    }

    /// 128 features of one frame: mean and standard deviation over latent cells of each of the
    /// encoder's 64 channels.
    pub fn features(&self, frame: &sgam_core::RgbdFrame) -> Result<Vec<f32>> {
        let f = self.config.downsample_factor();
        if !(frame.width() as usize).is_multiple_of(f) || !(frame.height() as usize).is_multiple_of(f) {
            bail!("frame of {}x{} is not a multiple of {f}", frame.width(), frame.height());
        }
        let k = sgam_core::Intrinsics::from_fov_x(frame.width(), frame.height(), 1.0);
        let x = sgam_model::packing::pack_input(&[frame], &[None], &[k], &self.config, &self.device)?;
        let z = self.model.encode(x);
        let [_, d, h, w] = z.dims();
        let v = z.into_data().try_to_vec_as::<f32>().map_err(|e| anyhow::anyhow!("reading features: {e:?}"))?;
        let n = (h * w) as f32;
        let mut out = Vec::with_capacity(2 * d);
        for c in 0..d {
            let s = &v[c * h * w..(c + 1) * h * w];
            let mean = s.iter().sum::<f32>() / n;
            let var = s.iter().map(|x| (x - mean) * (x - mean)).sum::<f32>() / n;
            out.push(mean);
            out.push(var.sqrt());
        }
        Ok(out)
    }
}

/// Pooled statistics over seeds.
#[derive(Debug, Clone, Serialize)]
pub struct Pooled {
    /// Summed new area, m².
    pub new_area_m2: f64,
    /// Objects per 100 m² of new area (all seeds' objects over all seeds' area).
    pub objects_per_100m2: f64,
    /// Median object footprint over all seeds' objects, m².
    pub median_object_area_m2: f64,
    /// 90th percentile object footprint, m².
    pub p90_object_area_m2: f64,
    /// Share of new area covered by objects.
    pub object_cover: f64,
    /// Mean over seeds of the object colour saturation (seeds without objects skipped).
    pub object_saturation: f64,
    /// Root of the mean over seeds of the squared ground RMS, mm.
    pub ground_rms_mm: f64,
    /// Median solidity, median elongation and compact share over all seeds' objects.
    pub object_shape: ShapeSummary,
}

fn quantile(v: &[f32], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mut s = v.to_vec();
    s.sort_by(f32::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize] as f64
}

fn pool(stats: &[WorldStats]) -> Pooled {
    let area: f64 = stats.iter().map(|s| s.new_area_m2 as f64).sum();
    let objects: usize = stats.iter().map(|s| s.objects).sum();
    let areas: Vec<f32> = stats.iter().flat_map(|s| s.object_areas_m2.iter().copied()).collect();
    let covered: f64 = stats.iter().map(|s| s.object_cover as f64 * s.new_area_m2 as f64).sum();
    let sats: Vec<f64> = stats
        .iter()
        .filter(|s| s.objects > 0 && s.object_saturation.is_finite())
        .map(|s| s.object_saturation as f64)
        .collect();
    let rms2: Vec<f64> =
        stats.iter().filter(|s| s.ground_rms_mm.is_finite()).map(|s| (s.ground_rms_mm as f64).powi(2)).collect();
    Pooled {
        new_area_m2: area,
        objects_per_100m2: if area > 0.0 { 100.0 * objects as f64 / area } else { 0.0 },
        median_object_area_m2: quantile(&areas, 0.5),
        p90_object_area_m2: quantile(&areas, 0.9),
        object_cover: if area > 0.0 { covered / area } else { 0.0 },
        object_saturation: if sats.is_empty() { 0.0 } else { sats.iter().sum::<f64>() / sats.len() as f64 },
        ground_rms_mm: if rms2.is_empty() { f64::NAN } else { (rms2.iter().sum::<f64>() / rms2.len() as f64).sqrt() },
        object_shape: ShapeSummary::of(&stats.iter().flat_map(|s| s.object_shapes.clone()).collect::<Vec<_>>()),
    }
}

/// One judged world pair.
struct SeedResult {
    generated: WorldStats,
    oracle: WorldStats,
    gen_regions: Vec<Vec<f32>>,
    ref_regions: Vec<Vec<f32>>,
    gen_features: Vec<Vec<f32>>,
    ref_features: Vec<Vec<f32>>,
    step_ms: f64,
    loop_psnr_ssim: (f64, f64),
}

fn read_mesh(dir: &Path) -> Result<TriMesh> {
    sgam_io::read_ply(&dir.join("mesh.ply")).with_context(|| format!("{}: cannot read the world mesh", dir.display()))
}

fn median_step_ms(dir: &Path) -> f64 {
    std::fs::read(dir.join("run.json"))
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| v["median_ms"]["total"].as_f64())
        .unwrap_or(f64::NAN)
}

/// Judges the refiner of `args` on every seed; returns the JSON result.
pub fn evaluate(args: &WorldArgs) -> Result<serde_json::Value> {
    args.validate()?;
    let (seeds, steps) = args.seeds_steps();
    let root = args.out.clone().unwrap_or_else(|| PathBuf::from("runs/eval-world"));
    let loop_root = args.loop_out.clone().unwrap_or_else(|| root.clone());
    let label = args.label();
    let cfg = WorldStatsConfig::default();
    let exclusion = Exclusion { polygon_xy_m: seed_footprint(256) };
    let extractor = FeatureExtractor::new()?;
    let stride = (steps / 100).max(1);
    let started = std::time::Instant::now();
    let mut results = Vec::new();
    for s in 0..seeds {
        let scene = args.first_seed + s;
        let oracle_dir = grow(args, scene, RefinerKind::Oracle, &args.oracle_label(), &root)?;
        let gen_dir = if args.refiner.effective() == RefinerKind::Oracle {
            oracle_dir.clone()
        } else {
            grow(args, scene, args.refiner.effective(), &label, &root)?
        };
        let (gm, om) = (read_mesh(&gen_dir)?, read_mesh(&oracle_dir)?);
        let generated = sgam_metrics::world::world_stats(&gm, &exclusion, &cfg);
        let oracle = sgam_metrics::world::world_stats(&om, &exclusion, &cfg);
        let (gp, op) = (
            sgam_metrics::world::new_area_points(&gm, &exclusion, &cfg),
            sgam_metrics::world::new_area_points(&om, &exclusion, &cfg),
        );
        // one region grid per seed: the oracle's new area and ground, shared by both worlds
        let (gen_regions, ref_regions) =
            match sgam_metrics::world::new_area_region_spec(&op, oracle.ground_height_m, args.region_size, 15) {
                Some(spec) => {
                    let nonempty =
                        |h: Vec<Vec<f32>>| h.into_iter().filter(|r| r.iter().any(|v| *v > 0.0)).collect::<Vec<_>>();
                    let g = sgam_metrics::scene::region_histograms(&gp, &spec);
                    let r = sgam_metrics::scene::region_histograms(&op, &spec);
                    (nonempty(g), nonempty(r))
                }
                None => (Vec::new(), Vec::new()),
            };
        let gen_features = frame_features(&gen_dir, steps + 1, stride, &extractor)?;
        let ref_features = frame_features(&oracle_dir, steps + 1, stride, &extractor)?;
        results.push(SeedResult {
            generated,
            oracle,
            gen_regions,
            ref_regions,
            gen_features,
            ref_features,
            step_ms: median_step_ms(&gen_dir),
            loop_psnr_ssim: loop_consistency(args, scene, args.refiner.effective(), &label, &loop_root)?,
        });
    }
    let gen_stats: Vec<WorldStats> = results.iter().map(|r| r.generated.clone()).collect();
    let ref_stats: Vec<WorldStats> = results.iter().map(|r| r.oracle.clone()).collect();
    let (gp, op) = (pool(&gen_stats), pool(&ref_stats));
    let gen_regions: Vec<Vec<f32>> = results.iter().flat_map(|r| r.gen_regions.clone()).collect();
    let ref_regions: Vec<Vec<f32>> = results.iter().flat_map(|r| r.ref_regions.clone()).collect();
    let scene = sgam_metrics::scene::scene_metrics(&gen_regions, &ref_regions);
    let gf: Vec<Vec<f32>> = results.iter().flat_map(|r| r.gen_features.clone()).collect();
    let rf: Vec<Vec<f32>> = results.iter().flat_map(|r| r.ref_features.clone()).collect();
    let kid = sgam_metrics::kid::kid(&gf, &rf);
    let ratio = |a: f64, b: f64| if b.abs() > 0.0 { a / b } else { f64::NAN };
    let step_ms: Vec<f64> = results.iter().map(|r| r.step_ms).collect();
    let loop_psnr: Vec<f64> = results.iter().map(|r| r.loop_psnr_ssim.0.min(99.0)).collect();
    let loop_ssim: Vec<f64> = results.iter().map(|r| r.loop_psnr_ssim.1).collect();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    Ok(json!({
        "refiner": label, "seeds": seeds, "steps": steps,
        "trajectory": format!("{:?}", args.path.trajectory).to_lowercase(),
        "temperature": args.sampling.temperature,
        "ground_snap_m": args.invented.ground_snap,
        "flying_pixels": args.invented.flying_pixels,
        "free_space": args.invented.free_space,
        "top_k": args.sampling.top_k,
        "within_temperature": args.sampling.within_temperature,
        "generated": gp, "oracle": op,
        "ratio_to_oracle": {
            "objects_per_100m2": ratio(gp.objects_per_100m2, op.objects_per_100m2),
            "median_object_area": ratio(gp.median_object_area_m2, op.median_object_area_m2),
            "object_saturation": ratio(gp.object_saturation, op.object_saturation),
            "ground_rms": ratio(gp.ground_rms_mm, op.ground_rms_mm),
            "compact_object_share": ratio(
                gp.object_shape.compact_share.map_or(f64::NAN, f64::from),
                op.object_shape.compact_share.map_or(f64::NAN, f64::from),
            ),
        },
        "scene": scene, "regions": { "generated": gen_regions.len(), "oracle": ref_regions.len(), "size_m": args.region_size },
        "kid": kid, "kid_frames": { "generated": gf.len(), "oracle": rf.len() },
        "per_seed": results.iter().enumerate().map(|(i, r)| json!({
            "seed_scene": args.first_seed + i as u64, "generated": r.generated, "oracle": r.oracle,
        })).collect::<Vec<_>>(),
        "loop": { "steps": LOOP_STEPS, "psnr": mean(&loop_psnr), "ssim": mean(&loop_ssim) },
        "step_ms_median": sgam_metrics::median(&step_ms).unwrap_or(0.0),
        "out": root.display().to_string(),
        "wall_s": started.elapsed().as_secs_f64(),
    }))
}

/// Plain-text summary of an [`evaluate`] result.
pub fn summary_text(v: &serde_json::Value) -> String {
    let row = |name: &str, key: &str, unit: &str| {
        format!(
            "  {name:<28} {:>10.3} {:>10.3} {:>8.2}x{unit}\n",
            v["generated"][key].as_f64().unwrap_or(f64::NAN),
            v["oracle"][key].as_f64().unwrap_or(f64::NAN),
            v["generated"][key].as_f64().unwrap_or(f64::NAN) / v["oracle"][key].as_f64().unwrap_or(f64::NAN),
        )
    };
    let mut s = format!(
        "world statistics: {} vs oracle, {} seeds x {} steps ({})\n  {:<28} {:>10} {:>10} {:>9}\n",
        v["refiner"].as_str().unwrap_or("?"),
        v["seeds"],
        v["steps"],
        v["trajectory"].as_str().unwrap_or("?"),
        "",
        "generated",
        "oracle",
        "ratio"
    );
    s += &row("new area (m2)", "new_area_m2", "");
    s += &row("objects per 100 m2", "objects_per_100m2", "   (bar 0.5-1.5x)");
    s += &row("median object footprint (m2)", "median_object_area_m2", "   (bar <= 2x)");
    s += &row("p90 object footprint (m2)", "p90_object_area_m2", "");
    s += &row("object cover", "object_cover", "");
    s += &row("object saturation", "object_saturation", "   (bar >= 0.6x)");
    s += &row("ground RMS (mm)", "ground_rms_mm", "   (bar <= 2x)");
    s += &shape_rows(v);
    let sc = &v["scene"];
    s += &format!(
        "scene metrics ({} vs {} regions of {} m): JSD {:.4}  MMD {:.4}  COV {:.3}  MinDist {:.4}  1-NNA {:.3}\n",
        v["regions"]["generated"],
        v["regions"]["oracle"],
        v["regions"]["size_m"],
        sc["jsd"].as_f64().unwrap_or(f64::NAN),
        sc["mmd"].as_f64().unwrap_or(f64::NAN),
        sc["cov"].as_f64().unwrap_or(f64::NAN),
        sc["min_dist"].as_f64().unwrap_or(f64::NAN),
        sc["one_nna"].as_f64().unwrap_or(f64::NAN),
    );
    s += &format!(
        "loop back to the seed after {} steps: PSNR {:.2} dB, SSIM {:.3} against the seed frame\n",
        v["loop"]["steps"],
        v["loop"]["psnr"].as_f64().unwrap_or(f64::NAN),
        v["loop"]["ssim"].as_f64().unwrap_or(f64::NAN),
    );
    s += &format!(
        "KID (frozen synthetic-world encoder features, {} vs {} frames): {:.5}\nmedian step {:.1} ms; wall {:.0} s; worlds in {}\n",
        v["kid_frames"]["generated"],
        v["kid_frames"]["oracle"],
        v["kid"].as_f64().unwrap_or(f64::NAN),
        v["step_ms_median"].as_f64().unwrap_or(f64::NAN),
        v["wall_s"].as_f64().unwrap_or(f64::NAN),
        v["out"].as_str().unwrap_or("?"),
    );
    s
}

/// The object shape rows of [`summary_text`]: pooled over seeds (the compact share with its
/// ratio to the oracle's), then one line per seed; "-" where a world has no objects.
fn shape_rows(v: &serde_json::Value) -> String {
    let num = |x: &serde_json::Value, digits: usize| x.as_f64().map_or("-".into(), |x| format!("{x:.digits$}"));
    let mut s = String::new();
    for (name, key) in [
        ("median object solidity", "median_solidity"),
        ("median object elongation", "median_elongation"),
        ("compact object share", "compact_share"),
    ] {
        let (g, o) = (&v["generated"]["object_shape"][key], &v["oracle"]["object_shape"][key]);
        let ratio = match (key, g.as_f64(), o.as_f64()) {
            ("compact_share", Some(g), Some(o)) => format!(" {:>8.2}x", g / o),
            _ => String::new(),
        };
        s += &format!("  {name:<28} {:>10} {:>10}{ratio}\n", num(g, 3), num(o, 3));
    }
    let triple = |w: &serde_json::Value| {
        let sh = &w["object_shape"];
        format!(
            "{} / {} / {}",
            num(&sh["median_solidity"], 2),
            num(&sh["median_elongation"], 2),
            num(&sh["compact_share"], 2)
        )
    };
    s += "  per seed, solidity / elongation / compact share: generated | oracle\n";
    for p in v["per_seed"].as_array().into_iter().flatten() {
        let seed = format!("seed {}", p["seed_scene"]);
        s += &format!("    {seed:<26} {} | {}\n", triple(&p["generated"]), triple(&p["oracle"]));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn features_tell_real_frames_from_smeared_ones() {
        // real frames of a held-out scene against the same frames with every colour replaced by
        // the frame's mean (a "smear"): KID between two real sets must be far below KID between
        // real and smeared
        let renderer = sgam_synth::Renderer::new(&sgam_synth::Scene::generate(
            HELD_OUT_SEED_BASE + 7,
            &sgam_synth::SceneConfig::default(),
        ));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let frames: Vec<sgam_core::RgbdFrame> = (0..24)
            .map(|_| {
                let c = Vec3::new(rng.random_range(-20.0..20.0), rng.random_range(-20.0..20.0), 0.0);
                let cam = sgam_synth::blender_camera(
                    c,
                    sgam_synth::CAMERA_PITCH_RAD,
                    0.0,
                    sgam_synth::dataset_intrinsics(128),
                );
                renderer.render(&cam, &sgam_synth::RenderConfig::default()).frame
            })
            .collect();
        let smeared: Vec<sgam_core::RgbdFrame> = frames
            .iter()
            .map(|f| {
                let n = f.colour.data.len() as f32;
                let mean =
                    f.colour.data.iter().fold([0.0f32; 3], |a, c| [a[0] + c[0] / n, a[1] + c[1] / n, a[2] + c[2] / n]);
                let mut g = f.clone();
                g.colour.data.iter_mut().for_each(|c| *c = mean);
                g
            })
            .collect();
        let x = FeatureExtractor::new().unwrap();
        let feats = |s: &[sgam_core::RgbdFrame]| s.iter().map(|f| x.features(f).unwrap()).collect::<Vec<_>>();
        let (a, b, c) = (feats(&frames[..12]), feats(&frames[12..]), feats(&smeared[12..]));
        assert_eq!(a[0].len(), 128);
        let (same, different) = (sgam_metrics::kid::kid(&a, &b).unwrap(), sgam_metrics::kid::kid(&a, &c).unwrap());
        eprintln!("KID real/real {same:.5}, real/smeared {different:.5}");
        assert!(different > 0.0 && different > 5.0 * same.abs(), "real/real {same}, real/smeared {different}");
    }

    #[test]
    fn the_seed_footprint_is_the_ground_quadrilateral_ahead_of_the_seed_camera() {
        let p = seed_footprint(256);
        assert_eq!(p.len(), 4);
        // the camera at (-20, -20), 11.695 m above the ground, looks towards +y, down at 72.8
        // degrees with a 40-degree field of view: the image's bottom edge looks 2.8 degrees
        // behind the vertical (y = -20 - 11.695 tan 2.8 deg = -20.6), its top edge 37.2
        // degrees ahead (y = -20 + 11.695 tan 37.2 deg = -11.1); a trapezoid wider far away
        let ys: Vec<f32> = p.iter().map(|v| v.y).collect();
        assert!((ys[0] + 11.1).abs() < 0.3 && (ys[2] + 20.6).abs() < 0.3, "{p:?}");
        let near = (p[3].x - p[2].x).abs();
        let far = (p[0].x - p[1].x).abs();
        assert!(far > near && near > 2.0 && far < 15.0, "{p:?}");
    }
}
