//! `sgam generate`: the SGAM unrolling pipeline from a seed frame along a trajectory, with
//! snapshots for resuming, and the run's outputs (frames, poses, mesh, fly-through).

use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use serde::{Deserialize, Serialize};
use sgam_core::{trajectory, Camera, Intrinsics, Refiner, RgbdFrame, Rigid3, Vec3};
use sgam_map::{TsdfConfig, TsdfMap};
use sgam_synth::{blender_camera, dataset_intrinsics, RenderConfig, Renderer, Scene, SceneConfig};

use crate::fuse::{median, save_map, write_mesh};
use crate::generator::{GeneratorConfig, StepTimings, WorldGenerator};
use crate::keyframes::Keyframes;
use crate::progress;
use crate::refiners::{NullRefiner, OracleRefiner};

/// First scene seed reserved for evaluation and generation; training never uses seeds at or
/// above it.
pub const HELD_OUT_SEED_BASE: u64 = 1_000_000;

/// Camera path shapes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
pub enum TrajectoryKind {
    /// The SGAM authors' anti-diagonal zig-zag over a grid (--grid x --grid, --step apart).
    Zigzag,
    /// Lawn-mower rows over a grid.
    Boustrophedon,
    /// Straight line along the seed camera's heading.
    Line,
    /// One full circle (radius --radius), turning the view with the path.
    Circle,
    /// Outward Archimedean spiral (--step apart, --radius growth per turn).
    Spiral,
    /// Poses from --trajectory-file (our transforms.json, TUM or KITTI).
    File,
    /// Greedy next-pose choice on the zig-zag's grid: of the unvisited neighbouring cells, the
    /// one whose view of the current map is most complete (see docs/STATUS.md).
    Greedy,
}

/// Which refiner completes the guidance.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
pub enum RefinerKind {
    /// The VQ model: --model when given, else the bundled compact model (trained on the
    /// synthetic CLEVR-Infinite world).
    Auto,
    /// Same as auto (kept for scripts that name it).
    Model,
    /// Stand-in: holes filled by push-pull interpolation.
    Null,
    /// Stand-in: ground truth of the synthetic world (synthetic seeds only).
    Oracle,
}

/// Arguments of `sgam generate`.
#[derive(Debug, Clone, Args, Serialize, Deserialize)]
#[command(
    after_help = "Examples:\n  sgam generate                                  # 100 steps from a synthetic seed\n  sgam generate --steps 900 --out runs/big       # the paper's 30x30 zig-zag world\n  sgam generate --resume runs/big                # continue after an interruption\n  sgam generate --seed-template ../shared/data/sgam-clevr-template\n  sgam generate --seed-rgb im.png --seed-depth d.png --intrinsics 500,500,320,240 \\\n      --trajectory line --step 0.1 --steps 50\n\nOutputs in the run folder: rgb/NNNNN.png, depth/NNNNN.npy (+ .png in mm with --depth-png),\ntransforms.json (nerfstudio / instant-ngp), mesh.ply and mesh.glb, flythrough.gif, run.json\n(config, per-stage timings, map statistics) and snapshot.bin (for --resume)."
)]
pub struct GenerateArgs {
    /// Run folder (default: runs/world-NNN, the next free number).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Continue an interrupted run from its last snapshot (other options are taken from it).
    #[arg(long, conflicts_with = "out")]
    #[serde(skip)]
    pub resume: Option<PathBuf>,
    /// Synthetic seed: CLEVR-Infinite scene seed (held-out seeds start at 1000000).
    #[arg(long, default_value_t = HELD_OUT_SEED_BASE)]
    pub seed_scene: u64,
    /// Seed from an RGB image (needs --seed-depth and --intrinsics).
    #[arg(long, requires_all = ["seed_depth", "intrinsics"])]
    pub seed_rgb: Option<PathBuf>,
    /// Depth of the seed image: 16-bit PNG in millimetres or NPY in metres (planar).
    #[arg(long)]
    pub seed_depth: Option<PathBuf>,
    /// Intrinsics of the seed image: fx,fy,cx,cy in pixels.
    #[arg(long, value_parser = parse_intrinsics)]
    pub intrinsics: Option<[f32; 4]>,
    /// Seed from the SGAM authors' CLEVR-Infinite template folder (ray-length depth).
    #[arg(long)]
    pub seed_template: Option<PathBuf>,
    /// Seed from an SGAM Google Earth seed folder (planar depth; uses the Google Earth preset:
    /// 1 cm voxels, 3 cm truncation, sources within 0.3, nearest 3, straight line).
    #[arg(long)]
    pub seed_google_earth: Option<PathBuf>,
    /// Image resolution of synthetic seeds (square).
    #[arg(long, default_value_t = 256)]
    pub res: u32,
    /// Trajectory shape.
    #[arg(long, value_enum, default_value_t = TrajectoryKind::Zigzag)]
    pub trajectory: TrajectoryKind,
    /// Pose file for --trajectory file: transforms.json (ours / NeRF), TUM (.txt with 8 columns)
    /// or KITTI (12 columns). Poses are used as given (world_from_camera).
    #[arg(long)]
    pub trajectory_file: Option<PathBuf>,
    /// Grid side of zig-zag / boustrophedon trajectories (the paper: 30).
    #[arg(long, default_value_t = 30)]
    pub grid: usize,
    /// Distance between neighbouring poses, metres (the authors: 0.408, half the dataset spacing).
    #[arg(long)]
    pub step: Option<f32>,
    /// Circle radius / spiral growth per turn, metres.
    #[arg(long, default_value_t = 4.0)]
    pub radius: f32,
    /// Number of generation steps (poses after the seed).
    #[arg(long, default_value_t = 100)]
    pub steps: usize,
    /// Refiner.
    #[arg(long, value_enum, default_value_t = RefinerKind::Auto)]
    pub refiner: RefinerKind,
    /// Model weights for --refiner model (default: the bundled compact model).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Sampling temperature in missing latent cells: 1 draws from the generative model's trained
    /// distribution over codes, lower is more conservative, 0 = argmin everywhere (the
    /// deterministic completion).
    #[arg(long, default_value_t = 1.0)]
    pub temperature: f32,
    /// Codes considered when sampling: the k nearest (0 = all, the calibrated distribution).
    #[arg(long, default_value_t = 0)]
    pub top_k: usize,
    /// Let the model regenerate observed pixels too (the paper's behaviour). By default the
    /// guidance is kept where it was observed and the model fills only the missing pixels.
    #[arg(long)]
    pub regenerate_observed: bool,
    /// Ablation: no global map; the guidance is warped from the previous frame only.
    #[arg(long)]
    pub no_map: bool,
    /// Ablation: no refinement; the guidance (with holes) is fused as it is.
    #[arg(long)]
    pub no_refine: bool,
    /// Run seed (sampling in the refiner).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Source keyframes per step.
    #[arg(long)]
    pub k_sources: Option<usize>,
    /// Sources must lie within this distance, metres.
    #[arg(long)]
    pub source_radius: Option<f32>,
    /// Voxel size, metres.
    #[arg(long)]
    pub voxel_size: Option<f32>,
    /// Truncation in voxels.
    #[arg(long)]
    pub trunc_voxels: Option<f32>,
    /// Depth cut for integration and rendering, metres.
    #[arg(long, default_value_t = 20.0)]
    pub depth_max: f32,
    /// Cap on the per-voxel weight (keeps long runs adaptable).
    #[arg(long)]
    pub weight_cap: Option<f32>,
    /// Snapshot (map + keyframe index + cursor) every N steps, for --resume.
    #[arg(long, default_value_t = 25)]
    pub snapshot_every: usize,
    /// Also write the world mesh every N steps (0 = only at the end).
    #[arg(long, default_value_t = 0)]
    pub mesh_every: usize,
    /// Also write 16-bit PNG depth in millimetres (depth/NNNNN.png).
    #[arg(long)]
    pub depth_png: bool,
    /// Skip the fly-through GIF.
    #[arg(long)]
    pub no_video: bool,
    /// Stop after this many steps of this invocation (for tests of --resume; the run stays
    /// resumable).
    #[arg(long, hide = true)]
    #[serde(skip)]
    pub stop_after: Option<usize>,
}

fn parse_intrinsics(s: &str) -> std::result::Result<[f32; 4], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|x| x.trim().parse::<f32>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| format!("'{s}': {e}"))?;
    match v.as_slice() {
        [fx, fy, cx, cy] => Ok([*fx, *fy, *cx, *cy]),
        _ => Err(format!("'{s}': expected fx,fy,cx,cy")),
    }
}

/// Dataset-specific defaults (authors' values).
#[derive(Debug, Clone, Copy)]
struct Preset {
    step_m: f32,
    k_sources: usize,
    source_radius_m: f32,
    voxel_size_m: f32,
    trunc_voxels: f32,
}

const CLEVR: Preset =
    Preset { step_m: 0.408, k_sources: 5, source_radius_m: 1.0, voxel_size_m: 0.05, trunc_voxels: 10.0 };
const GOOGLE_EARTH: Preset =
    Preset { step_m: 0.02, k_sources: 3, source_radius_m: 0.3, voxel_size_m: 0.01, trunc_voxels: 3.0 };

/// The seed: first camera and frame, plus the synthetic world when there is one.
struct Seed {
    camera: Camera,
    frame: RgbdFrame,
    renderer: Option<Renderer>,
    preset: Preset,
    name: String,
}

fn load_seed(args: &GenerateArgs) -> Result<Seed> {
    if let Some(rgb) = &args.seed_rgb {
        let (Some(depth), Some([fx, fy, cx, cy])) = (&args.seed_depth, args.intrinsics) else {
            bail!("--seed-rgb needs --seed-depth and --intrinsics");
        };
        let (w, h) = sgam_io::image_size(rgb)?;
        let k = Intrinsics::try_new(w, h, fx, fy, cx, cy).context("--intrinsics")?;
        let s = sgam_io::read_seed_rgbd(rgb, depth, k)?;
        return Ok(Seed {
            camera: s.camera,
            frame: s.frame,
            renderer: None,
            preset: CLEVR,
            name: rgb.display().to_string(),
        });
    }
    if let Some(dir) = &args.seed_template {
        let s = sgam_io::read_clevr_template(dir)?;
        return Ok(Seed {
            camera: s.camera,
            frame: s.frame,
            renderer: None,
            preset: CLEVR,
            name: dir.display().to_string(),
        });
    }
    if let Some(dir) = &args.seed_google_earth {
        let s = sgam_io::read_google_earth_seed(dir)?;
        return Ok(Seed {
            camera: s.camera,
            frame: s.frame,
            renderer: None,
            preset: GOOGLE_EARTH,
            name: dir.display().to_string(),
        });
    }
    if args.res < 16 {
        bail!("--res {} is too small (at least 16)", args.res);
    }
    let scene = Scene::generate(args.seed_scene, &SceneConfig::default());
    let renderer = Renderer::new(&scene);
    let camera = synthetic_seed_camera(args.res);
    let frame = renderer.render(&camera, &RenderConfig::default()).frame;
    Ok(Seed {
        camera,
        frame,
        renderer: Some(renderer),
        preset: CLEVR,
        name: format!("synthetic scene {}", args.seed_scene),
    })
}

/// The camera of synthetic seeds: the dataset's first grid camera (-20, -20), looking down at
/// the dataset's pitch, `res x res` pixels. Evaluation derives the seed's footprint from it.
pub fn synthetic_seed_camera(res: u32) -> Camera {
    blender_camera(
        Vec3::new(-20.0, -20.0, sgam_synth::CAMERA_HEIGHT_M),
        sgam_synth::CAMERA_PITCH_RAD,
        0.0,
        dataset_intrinsics(res),
    )
}

/// Side of the square grid of the grid trajectories (zig-zag, boustrophedon, greedy): `--grid`,
/// enlarged when it has fewer cells than poses.
fn grid_side(args: &GenerateArgs) -> usize {
    args.grid.max(((args.steps + 1) as f64).sqrt().ceil() as usize)
}

/// Distance between neighbouring poses: `--step`, else the seed's preset.
fn grid_step(args: &GenerateArgs, seed: &Seed) -> f32 {
    args.step.unwrap_or(seed.preset.step_m)
}

/// The cameras of the run: index 0 is the seed, 1..=steps are generated (greedy: only the seed;
/// the rest are chosen while generating).
fn build_trajectory(args: &GenerateArgs, seed: &Seed) -> Result<Vec<Camera>> {
    let s = &seed.camera.world_from_camera;
    let step = grid_step(args, seed);
    if !(step.is_finite() && step > 0.0) {
        bail!("--step {step} must be a positive distance in metres");
    }
    let n = args.steps + 1;
    let poses: Vec<Rigid3> = match args.trajectory {
        TrajectoryKind::Zigzag | TrajectoryKind::Boustrophedon => {
            let side = grid_side(args);
            let cells = if args.trajectory == TrajectoryKind::Zigzag {
                trajectory::zigzag_cells(side, side)
            } else {
                trajectory::boustrophedon_cells(side, side)
            };
            let cells: Vec<_> = cells.into_iter().take(n).collect();
            trajectory::grid_poses(s, &cells, step)
        }
        TrajectoryKind::Greedy => return Ok(vec![seed.camera]),
        TrajectoryKind::Line => trajectory::line_poses(s, n, step),
        TrajectoryKind::Circle => trajectory::circle_poses(s, n, args.radius),
        TrajectoryKind::Spiral => trajectory::spiral_poses(s, n, step, args.radius),
        TrajectoryKind::File => {
            let Some(p) = &args.trajectory_file else { bail!("--trajectory file needs --trajectory-file PATH") };
            let mut poses = read_pose_file(p)?;
            if poses.is_empty() {
                bail!("{}: no poses", p.display());
            }
            poses.truncate(n);
            poses
        }
    };
    if poses.len() < 2 {
        bail!("the trajectory has no pose after the seed (use --steps >= 1)");
    }
    Ok(poses.into_iter().map(|p| Camera::new(seed.camera.intrinsics, p)).collect())
}

fn read_pose_file(path: &Path) -> Result<Vec<Rigid3>> {
    if path.extension().is_some_and(|e| e == "json") {
        let t = sgam_io::read_nerf_transforms(path)?;
        return Ok(t.frames.iter().map(|f| f.world_from_camera).collect());
    }
    let text = std::fs::read_to_string(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let cols = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| l.split_whitespace().count())
        .unwrap_or(0);
    Ok(match cols {
        8 => sgam_io::read_tum_trajectory(path)?,
        12 => sgam_io::read_kitti_trajectory(path)?,
        _ => bail!("{}: not a TUM (8 columns) or KITTI (12 columns) trajectory, nor a transforms.json", path.display()),
    })
}

/// What a snapshot holds besides the map.
#[derive(Debug, Serialize, Deserialize)]
struct SnapshotState {
    version: u32,
    args: GenerateArgs,
    /// Keyframes (= steps done + 1 for the seed).
    cameras: Vec<Camera>,
    timings: Vec<StepTimings>,
}

const SNAPSHOT_MAGIC: &[u8; 8] = b"SGAMSNAP";

fn write_snapshot(dir: &Path, state: &SnapshotState, map: &TsdfMap) -> Result<()> {
    let json = serde_json::to_vec(state)?;
    let mut map_bytes = Vec::new();
    map.write_to(&mut map_bytes).context("serialising the map")?;
    sgam_io::write_atomic(&dir.join("snapshot.bin"), |w| {
        use std::io::Write;
        w.write_all(SNAPSHOT_MAGIC)?;
        w.write_all(&(json.len() as u64).to_le_bytes())?;
        w.write_all(&json)?;
        w.write_all(&map_bytes)
    })?;
    Ok(())
}

fn read_snapshot(dir: &Path) -> Result<(SnapshotState, TsdfMap)> {
    let path = dir.join("snapshot.bin");
    let mut f = std::io::BufReader::new(
        std::fs::File::open(&path).with_context(|| format!("{}: no snapshot to resume from", path.display()))?,
    );
    let mut magic = [0u8; 8];
    f.read_exact(&mut magic).with_context(|| format!("{}: truncated", path.display()))?;
    if &magic != SNAPSHOT_MAGIC {
        bail!("{}: not an sgam snapshot", path.display());
    }
    let mut len = [0u8; 8];
    f.read_exact(&mut len).with_context(|| format!("{}: truncated", path.display()))?;
    let len = u64::from_le_bytes(len) as usize;
    if len > 1 << 30 {
        bail!("{}: corrupt header", path.display());
    }
    let mut json = vec![0u8; len];
    f.read_exact(&mut json).with_context(|| format!("{}: truncated", path.display()))?;
    let state: SnapshotState =
        serde_json::from_slice(&json).with_context(|| format!("{}: corrupt state", path.display()))?;
    let map = TsdfMap::read_from(&mut f).with_context(|| format!("{}: corrupt map", path.display()))?;
    Ok((state, map))
}

fn next_run_dir() -> PathBuf {
    (1..)
        .map(|i| PathBuf::from(format!("runs/world-{i:03}")))
        .find(|p| !p.exists())
        .unwrap_or_else(|| PathBuf::from("runs/world"))
}

/// Runs `sgam generate`.
pub fn run(args: GenerateArgs) -> Result<()> {
    let (args, dir, resumed) = match &args.resume {
        Some(dir) => {
            let (state, map) = read_snapshot(dir)?;
            let mut a = state.args;
            a.stop_after = args.stop_after;
            (a, dir.clone(), Some(Resume { cameras: state.cameras, timings: state.timings, map }))
        }
        None => {
            let dir = args.out.clone().unwrap_or_else(next_run_dir);
            if dir.join("snapshot.bin").exists() {
                bail!("{} already holds a run: continue it with --resume {0}, or choose another --out", dir.display());
            }
            (args, dir, None)
        }
    };
    let seed = load_seed(&args)?;
    let refiner = if args.no_refine { RefinerKind::Null } else { args.refiner };
    match refiner {
        RefinerKind::Auto | RefinerKind::Null | RefinerKind::Model => match model_refiner(refiner, &args)? {
            Some(model) => run_with(&args, &dir, resumed, seed, model),
            None => run_with(&args, &dir, resumed, seed, NullRefiner { fill: !args.no_refine }),
        },
        RefinerKind::Oracle => {
            let Some(renderer) = seed.renderer.clone() else {
                bail!(
                    "--refiner oracle needs a synthetic seed (no --seed-rgb / --seed-template / --seed-google-earth)"
                );
            };
            run_with(&args, &dir, resumed, seed, OracleRefiner::new(renderer, RenderConfig::default()))
        }
    }
}

/// The bundled compact model (f16 safetensors, config embedded; see docs/MODEL.md), compiled
/// into the binary so an installed `sgam` needs no files next to it.
pub const BUNDLED_MODEL: &[u8] = include_bytes!("../../../models/compact.safetensors");

/// The learned refiner for `kind` (`None` for the stand-ins).
pub fn model_refiner(kind: RefinerKind, args: &GenerateArgs) -> Result<Option<sgam_model::VqRefiner>> {
    let path = match (kind, &args.model) {
        (RefinerKind::Null | RefinerKind::Oracle, _) => return Ok(None),
        (_, Some(p)) => Some(p.clone()),
        (RefinerKind::Model | RefinerKind::Auto, None) => None,
    };
    if !(args.temperature.is_finite() && args.temperature >= 0.0) {
        bail!("--temperature {} must be a non-negative number", args.temperature);
    }
    let top_k = if args.top_k == 0 { usize::MAX } else { args.top_k };
    let sampling = if args.temperature > 0.0 && top_k > 1 {
        sgam_model::Sampling::Temperature { temperature: args.temperature, top_k }
    } else {
        sgam_model::Sampling::Argmin
    };
    let options = sgam_model::RefinerOptions {
        sampling,
        seed: args.seed,
        keep_observed: !args.regenerate_observed,
        ..Default::default()
    };
    let r = match path {
        Some(path) => sgam_model::VqRefiner::from_files(&path, None, options)
            .with_context(|| format!("{}: cannot load the model", path.display()))?,
        None => sgam_model::VqRefiner::from_bytes(BUNDLED_MODEL, None, options)
            .context("the bundled model (models/compact.safetensors) cannot be loaded")?,
    };
    Ok(Some(r))
}

/// What a snapshot restores (read once, when `--resume` starts).
struct Resume {
    cameras: Vec<Camera>,
    timings: Vec<StepTimings>,
    map: TsdfMap,
}

fn run_with<R: Refiner>(args: &GenerateArgs, dir: &Path, resume: Option<Resume>, seed: Seed, refiner: R) -> Result<()> {
    let cameras = build_trajectory(args, &seed)?;
    let p = seed.preset;
    let tsdf = TsdfConfig {
        voxel_size_m: args.voxel_size.unwrap_or(p.voxel_size_m),
        trunc_voxels: args.trunc_voxels.unwrap_or(p.trunc_voxels),
        depth_min_m: 0.05,
        depth_max_m: args.depth_max,
        weight_cap: args.weight_cap,
    };
    tsdf.validate().context("invalid map parameters")?;
    let config = GeneratorConfig {
        tsdf,
        k_sources: args.k_sources.unwrap_or(p.k_sources),
        source_radius_m: args.source_radius.unwrap_or(p.source_radius_m),
        no_map: args.no_map,
        ..crate::generator::clevr_generator_config(args.seed)
    };
    let mut keyframes = Keyframes::new(dir, config.source_radius_m, 96);
    let resumed = resume.is_some();
    let (map, mut timings) = if let Some(r) = resume {
        for c in &r.cameras {
            keyframes.push_camera(*c);
        }
        (r.map, r.timings)
    } else {
        std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create the run folder", dir.display()))?;
        (TsdfMap::new(tsdf), Vec::new())
    };
    let mut gen = WorldGenerator::new(map, keyframes, refiner, config);
    if !resumed {
        gen.seed(&cameras[0], seed.frame.clone())?;
    }
    let done = gen.keyframes.len();
    let (total, mut greedy) = if args.trajectory == TrajectoryKind::Greedy {
        let planner = crate::greedy::GreedyPlanner::new(
            &cameras[0],
            grid_step(args, &seed),
            grid_side(args),
            gen.keyframes.cameras(),
        )?;
        (args.steps + 1, Some(planner))
    } else {
        (cameras.len(), None)
    };
    eprintln!(
        "{} {}: {} steps from {} ({} x {} px) -> {}",
        if resumed { "resuming" } else { "generating" },
        format!("{:?}", args.trajectory).to_lowercase(),
        total - 1,
        seed.name,
        seed.camera.intrinsics.width,
        seed.camera.intrinsics.height,
        dir.display()
    );
    let pb = progress::bar(total as u64 - 1, "steps");
    pb.set_position((done - 1) as u64);
    let start = Instant::now();
    let mut this_run = 0usize;
    for i in done..total {
        let camera = match &mut greedy {
            Some(planner) => match planner.next(&mut gen.map) {
                Some(c) => c,
                None => break,
            },
            None => cameras[i],
        };
        let t = gen.step(&camera).with_context(|| format!("step {i}"))?;
        timings.push(t);
        this_run += 1;
        pb.inc(1);
        pb.set_message(format!("{:.0} ms/step, {:.0}% invented", t.total_ms, 100.0 * t.missing_fraction));
        if args.depth_png {
            let (_, depth) = Keyframes::frame_paths(dir, i);
            let f = gen.keyframes.frame(i)?;
            sgam_io::write_depth_png_mm(&depth.with_extension("png"), &f.depth_m)?;
        }
        if args.mesh_every > 0 && i % args.mesh_every == 0 {
            write_mesh(&dir.join(format!("mesh-{i:05}.ply")), &gen.map.extract_mesh(1.0))?;
        }
        let finished = i + 1 == total;
        let stopping = args.stop_after.is_some_and(|n| this_run >= n);
        if finished || stopping || i % args.snapshot_every.max(1) == 0 {
            let state = SnapshotState {
                version: 1,
                args: args.clone(),
                cameras: gen.keyframes.cameras().to_vec(),
                timings: timings.clone(),
            };
            write_snapshot(dir, &state, &gen.map)?;
        }
        if stopping && !finished {
            pb.finish_and_clear();
            eprintln!("stopped after {this_run} steps; continue with: sgam generate --resume {}", dir.display());
            return Ok(());
        }
    }
    pb.finish_and_clear();
    let wall_s = start.elapsed().as_secs_f64();
    finish_outputs(args, dir, &mut gen, &timings, wall_s)
}

/// Writes the end-of-run outputs: mesh (PLY + GLB), transforms.json, fly-through, run.json.
fn finish_outputs<R: Refiner>(
    args: &GenerateArgs,
    dir: &Path,
    gen: &mut WorldGenerator<R>,
    timings: &[StepTimings],
    wall_s: f64,
) -> Result<()> {
    let mesh = gen.map.extract_mesh(1.0);
    write_mesh(&dir.join("mesh.ply"), &mesh)?;
    write_mesh(&dir.join("mesh.glb"), &mesh)?;
    save_map(&dir.join("map.bin"), &gen.map)?;
    let cams = gen.keyframes.cameras();
    let frames = (0..cams.len())
        .map(|i| sgam_io::NerfFrame {
            file_path: format!("rgb/{i:05}.png"),
            depth_file_path: Some(format!("depth/{i:05}.npy")),
            world_from_camera: cams[i].world_from_camera,
            intrinsics: None,
        })
        .collect();
    let transforms =
        sgam_io::NerfTransforms { intrinsics: cams[0].intrinsics, frames, depth_png_metres_per_unit: 0.001 };
    sgam_io::write_nerf_transforms(&dir.join("transforms.json"), &transforms)?;
    if !args.no_video {
        write_flythrough(dir, cams.len())?;
    }
    if let Some((cam, near, far)) = crate::overview::overview_camera(&mesh, &cams[0], 1280, 800) {
        let img = crate::overview::render_overview(&gen.map, &cam, near, far);
        sgam_io::write_rgb_png(&dir.join("overview.png"), &img)?;
    }
    sgam_io::write_rgb_png(&dir.join("strip.png"), &crate::overview::frame_strip(dir, cams.len(), 6)?)?;
    let col = |f: fn(&StepTimings) -> f64| median(&timings.iter().map(f).collect::<Vec<_>>());
    let summary = serde_json::json!({
        "args": args,
        "steps": timings.len(),
        "keyframes": cams.len(),
        "wall_s_this_invocation": wall_s,
        "median_ms": {
            "total": col(|t| t.total_ms), "sources": col(|t| t.sources_ms), "render": col(|t| t.render_ms),
            "warp": col(|t| t.warp_ms), "refine": col(|t| t.refine_ms), "integrate": col(|t| t.integrate_ms),
            "mesh": col(|t| t.mesh_ms), "write": col(|t| t.write_ms),
        },
        "median_missing_fraction": median(&timings.iter().map(|t| t.missing_fraction as f64).collect::<Vec<_>>()),
        "map": { "blocks": gen.map.block_count(), "bytes": gen.map.memory_bytes(),
                 "vertices": mesh.positions.len(), "triangles": mesh.triangles.len() },
        "step_ms": timings.iter().map(|t| (t.total_ms * 1000.0).round() / 1000.0).collect::<Vec<_>>(),
    });
    let bytes = serde_json::to_vec_pretty(&summary)?;
    sgam_io::write_atomic(&dir.join("run.json"), |w| std::io::Write::write_all(w, &bytes))?;
    eprintln!(
        "done: {} steps, median {:.1} ms/step (refine {:.1}, map {:.1})",
        timings.len(),
        col(|t| t.total_ms),
        col(|t| t.refine_ms),
        col(|t| t.render_ms + t.warp_ms + t.integrate_ms + t.mesh_ms)
    );
    eprintln!("  mesh:        {}  ({} vertices)", dir.join("mesh.ply").display(), mesh.positions.len());
    eprintln!("  mesh (glTF): {}", dir.join("mesh.glb").display());
    if !args.no_video {
        eprintln!("  fly-through: {}", dir.join("flythrough.gif").display());
    }
    eprintln!("  overview:    {}  (and strip.png: 6 frames)", dir.join("overview.png").display());
    eprintln!("  poses:       {}  (nerfstudio / instant-ngp)", dir.join("transforms.json").display());
    eprintln!("  frames:      {}/rgb, {}/depth", dir.display(), dir.display());
    Ok(())
}

/// An animated GIF of (at most 200 evenly chosen) generated frames, 10 frames/s.
fn write_flythrough(dir: &Path, n: usize) -> Result<()> {
    use image::codecs::gif::{GifEncoder, Repeat};
    let stride = n.div_ceil(200).max(1);
    let path = dir.join("flythrough.gif");
    let mut frames = Vec::new();
    for i in (0..n).step_by(stride) {
        let (rgb, _) = Keyframes::frame_paths(dir, i);
        let img = image::open(&rgb).with_context(|| format!("{}: cannot read frame", rgb.display()))?.to_rgba8();
        frames.push(image::Frame::from_parts(img, 0, 0, image::Delay::from_numer_denom_ms(100, 1)));
    }
    sgam_io::write_atomic(&path, |w| {
        let mut enc = GifEncoder::new_with_speed(w, 20);
        enc.set_repeat(Repeat::Infinite).map_err(std::io::Error::other)?;
        enc.encode_frames(frames).map_err(std::io::Error::other)
    })?;
    Ok(())
}

impl GenerateArgs {
    /// Default arguments with a given refiner (for evaluation commands that reuse the loader).
    pub fn for_refiner(kind: RefinerKind, model: Option<PathBuf>, regenerate_observed: bool) -> Self {
        use clap::Parser;
        #[derive(Parser)]
        struct Wrap {
            #[command(flatten)]
            a: GenerateArgs,
        }
        let mut a = Wrap::parse_from(["sgam"]).a;
        a.refiner = kind;
        a.model = model;
        a.regenerate_observed = regenerate_observed;
        a
    }
}
