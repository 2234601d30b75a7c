//! `sgam generate`: the SGAM unrolling pipeline from a seed frame along a trajectory, with
//! snapshots for resuming, and the run's outputs (frames, poses, mesh, fly-through).

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
use crate::guard::{in_range, positive, RunLock};
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

/// Default of `--ground-snap` (generate, eval world, eval table), metres: below the shortest
/// object of the synthetic world (1.4 m), above the bundled model's ground error (docs/MODEL.md).
pub const DEFAULT_GROUND_SNAP_M: f32 = 0.8;

/// Default sampling temperature (generate, eval world, eval table, bench): chosen on training
/// seeds 11-14 between 1.0, 1.15, 1.3 and 1.5 (docs/MODEL.md); 1.0 under-starts objects, 1.5
/// washes out their colour.
pub const DEFAULT_TEMPERATURE: f32 = 1.3;

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
    /// distribution over codes, higher starts more objects, lower is more conservative, 0 =
    /// argmin everywhere (the deterministic completion).
    #[arg(long, default_value_t = DEFAULT_TEMPERATURE)]
    pub temperature: f32,
    /// Ground prior, metres (0 = off): invented pixels the refiner puts less than this above
    /// the seed frame's ground plane, or anywhere below it, are put back on the plane. The
    /// plane is fitted once in the seed frame (RANSAC); a seed without a dominant plane gets no
    /// prior. Objects (higher than this) keep the refiner's depth. The oracle is never snapped.
    #[arg(long, default_value_t = DEFAULT_GROUND_SNAP_M)]
    #[serde(default)]
    pub ground_snap: f32,
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
    /// Skip the fly-through videos (flythrough.gif and flythrough.mp4).
    #[arg(long)]
    pub no_video: bool,
    /// Skip flythrough.mp4 (H.264; see the README on licensing); the GIF is still written.
    #[arg(long)]
    #[serde(default)]
    pub no_mp4: bool,
    /// Also write orbit.mp4: one turn around the final mesh.
    #[arg(long)]
    #[serde(default)]
    pub orbit_video: bool,
    /// Serve the viewer on 127.0.0.1 while the world grows (mesh and poses refresh every
    /// --view-every steps; the results are unchanged).
    #[arg(long)]
    #[serde(skip)]
    pub view: bool,
    /// Port of --view (a taken port falls back to a free one).
    #[arg(long, default_value_t = crate::view::DEFAULT_PORT)]
    #[serde(skip)]
    pub view_port: u16,
    /// Steps between mesh refreshes of --view.
    #[arg(long, default_value_t = crate::live::DEFAULT_EVERY)]
    #[serde(skip)]
    pub view_every: usize,
    /// Stop after this many steps of this invocation (for tests of --resume; the run stays
    /// resumable).
    #[arg(long, hide = true)]
    #[serde(skip)]
    pub stop_after: Option<usize>,
    /// Replace the outputs of an earlier run in --out (by default a folder that holds files is
    /// refused).
    #[arg(long, conflicts_with = "resume")]
    #[serde(skip)]
    pub force: bool,
}

/// Largest image side of `sgam generate` (keyframe cache and model activations stay within a
/// few GB).
pub const MAX_RES: u32 = 2048;
/// Most generation steps of one run.
pub const MAX_STEPS: usize = 1_000_000;
/// Largest `--grid` side.
pub const MAX_GRID: usize = 1000;
/// Farthest a camera may get from the world origin, metres.
pub const MAX_EXTENT_M: f32 = 100_000.0;
/// Largest depth a 16-bit millimetre PNG holds, metres.
const DEPTH_PNG_MAX_M: f32 = sgam_io::DEPTH_PNG_MAX_MM as f32 / 1000.0;

/// The files and folders a run writes (what `--force` removes before a new run).
pub const RUN_OUTPUTS: &[&str] = &[
    "rgb",
    "depth",
    "snapshot.bin",
    "mesh.ply",
    "mesh.glb",
    "map.bin",
    "transforms.json",
    "flythrough.gif",
    "flythrough.mp4",
    "orbit.mp4",
    "world.html",
    "overview.png",
    "strip.png",
    "run.json",
    "mesh-*",
];

impl GenerateArgs {
    /// Checks every option: numbers finite and in range, with upper bounds that keep memory
    /// within the machine, and the combinations that would otherwise be silently ignored.
    /// Errors name the option and the accepted range. Runs for new runs and on the arguments a
    /// snapshot restores.
    pub fn validate(&self) -> Result<()> {
        in_range("--res", self.res, 16..=MAX_RES)?;
        in_range("--grid", self.grid, 1..=MAX_GRID)?;
        in_range("--steps", self.steps, 1..=MAX_STEPS)?;
        if let Some(step) = self.step {
            positive("--step", step, 1000.0)?;
        }
        positive("--radius", self.radius, 10_000.0)?;
        in_range("--temperature", self.temperature, 0.0..=100.0)?;
        in_range("--ground-snap", self.ground_snap, 0.0..=10.0)?;
        in_range("--top-k", self.top_k, 0..=sgam_model::config::MAX_CODEBOOK)?;
        if let Some(k) = self.k_sources {
            in_range("--k-sources", k, 1..=64)?;
        }
        if let Some(r) = self.source_radius {
            positive("--source-radius", r, 1000.0)?;
        }
        if let Some(v) = self.voxel_size {
            in_range("--voxel-size", v, sgam_map::MIN_VOXEL_M..=sgam_map::MAX_VOXEL_M)?;
        }
        if let Some(t) = self.trunc_voxels {
            positive("--trunc-voxels", t, sgam_map::MAX_TRUNC_VOXELS)?;
        }
        in_range("--depth-max", self.depth_max, 0.1..=sgam_map::MAX_DEPTH_M)?;
        if let Some(c) = self.weight_cap {
            in_range("--weight-cap", c, 1.0..=1e6)?;
        }
        in_range("--snapshot-every", self.snapshot_every, 1..=MAX_STEPS)?;
        in_range("--mesh-every", self.mesh_every, 0..=MAX_STEPS)?;
        if self.view {
            in_range("--view-every", self.view_every, 1..=MAX_STEPS)?;
        }
        if let Some(n) = self.stop_after {
            in_range("--stop-after", n, 1..=MAX_STEPS)?;
        }
        if self.depth_png && self.depth_max > DEPTH_PNG_MAX_M {
            bail!(
                "--depth-png stores millimetres in 16 bits (at most {DEPTH_PNG_MAX_M} m) but --depth-max is {} m; \
                 lower --depth-max or leave out --depth-png (depth/NNNNN.npy holds every depth)",
                self.depth_max
            );
        }
        if let (Some(rgb), Some(k)) = (&self.seed_rgb, self.intrinsics) {
            let (w, h) = sgam_io::image_size(rgb)?;
            check_intrinsics(k, w, h)?;
        }
        if self.seed_rgb.is_none() {
            for (given, name) in
                [(self.seed_depth.is_some(), "--seed-depth"), (self.intrinsics.is_some(), "--intrinsics")]
            {
                if given {
                    bail!("{name} describes an RGB seed: it needs --seed-rgb");
                }
            }
        }
        let seeds: Vec<&str> = [
            (self.seed_rgb.is_some(), "--seed-rgb"),
            (self.seed_template.is_some(), "--seed-template"),
            (self.seed_google_earth.is_some(), "--seed-google-earth"),
        ]
        .into_iter()
        .filter_map(|(given, name)| given.then_some(name))
        .collect();
        if seeds.len() > 1 {
            bail!("{} are different seeds: give one", seeds.join(" and "));
        }
        match (self.trajectory, &self.trajectory_file) {
            (TrajectoryKind::File, None) => bail!("--trajectory file needs --trajectory-file PATH"),
            (kind, Some(_)) if kind != TrajectoryKind::File => {
                bail!("--trajectory-file is read only with --trajectory file")
            }
            _ => {}
        }
        Ok(())
    }
}

/// Checks of the command line that the arguments alone cannot tell: options given with
/// `--resume` (a resumed run keeps its own) and `--model` with a stand-in refiner. `given` are
/// the options written on the command line. (Evaluation commands that build arguments
/// themselves skip this.)
pub fn check_command_line(args: &GenerateArgs, given: &[String]) -> Result<()> {
    if args.resume.is_some() {
        let ignored: Vec<&str> = given
            .iter()
            .map(String::as_str)
            .filter(|o| !matches!(*o, "--resume" | "--stop-after" | "--view" | "--view-port" | "--view-every"))
            .collect();
        if !ignored.is_empty() {
            bail!(
                "--resume continues a run with the options it was started with; {} cannot be changed (leave {} out, \
                 or start a new run)",
                ignored.join(", "),
                if ignored.len() == 1 { "it" } else { "them" }
            );
        }
    }
    let stand_in = args.no_refine || matches!(args.refiner, RefinerKind::Null | RefinerKind::Oracle);
    if stand_in && args.model.is_some() {
        bail!(
            "--model is used only by the learned refiner; this run uses a stand-in ({}) and would ignore it",
            if args.no_refine {
                "--no-refine".to_string()
            } else {
                format!("--refiner {:?}", args.refiner).to_lowercase()
            }
        );
    }
    Ok(())
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

/// `--intrinsics` must describe a real camera for a `w x h` image: fields of view between 0.1
/// and 179 degrees (focal lengths `0.005..=500` times the image side) and the principal point
/// on the image.
fn check_intrinsics([fx, fy, cx, cy]: [f32; 4], w: u32, h: u32) -> Result<()> {
    let (w, h) = (w as f32, h as f32);
    for (name, f, side) in [("fx", fx, w), ("fy", fy, h)] {
        if !(f >= 0.005 * side && f <= 500.0 * side) {
            bail!(
                "--intrinsics {name} {f} is out of range for a {side} px image side: accepted {}..={} px \
                 (fields of view from 0.1 to 179 degrees)",
                0.005 * side,
                500.0 * side
            );
        }
    }
    for (name, c, side) in [("cx", cx, w), ("cy", cy, h)] {
        if !(0.0..=side).contains(&c) {
            bail!("--intrinsics {name} {c} puts the principal point off the image: accepted 0..={side} px");
        }
    }
    Ok(())
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
    if let Some((i, p)) =
        poses.iter().enumerate().find(|(_, p)| !(p.is_finite() && p.translation.abs().max_element() <= MAX_EXTENT_M))
    {
        bail!(
            "pose {i} of the trajectory lies at {} m, beyond the {MAX_EXTENT_M} m the map covers; use a smaller \
             --step, --radius or --steps",
            p.translation
        );
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
    /// CRC-32 of the model file the run uses (`None` for the stand-ins): a resumed run refuses a
    /// file that changed since.
    #[serde(default)]
    model_crc32: Option<u32>,
}

const SNAPSHOT_MAGIC: &[u8; 8] = b"SGAMSNAP";
/// Format of `snapshot.bin`:
/// ```text
/// magic "SGAMSNAP" | u32 version (2) | u64 n | n bytes of SnapshotState JSON | map (sgam-map format)
/// | u32 CRC-32 (IEEE) of every preceding byte
/// ```
/// (Version 1 had no version field and no checksum over the state: a flipped bit changed the
/// run silently.)
const SNAPSHOT_VERSION: u32 = 2;

fn write_snapshot(dir: &Path, state: &SnapshotState, map: &TsdfMap) -> Result<()> {
    let json = serde_json::to_vec(state)?;
    let mut bytes = Vec::with_capacity(json.len() + 64);
    bytes.extend_from_slice(SNAPSHOT_MAGIC);
    bytes.extend_from_slice(&SNAPSHOT_VERSION.to_le_bytes());
    bytes.extend_from_slice(&(json.len() as u64).to_le_bytes());
    bytes.extend_from_slice(&json);
    map.write_to(&mut bytes).context("serialising the map")?;
    let crc = crc32fast::hash(&bytes);
    bytes.extend_from_slice(&crc.to_le_bytes());
    sgam_io::write_atomic(&dir.join("snapshot.bin"), |w| std::io::Write::write_all(w, &bytes))?;
    Ok(())
}

/// Parses `snapshot.bin` bytes (`path` names the file in errors): format version, checksum over
/// the whole file, the state's JSON, the map.
fn parse_snapshot(path: &Path, bytes: &[u8]) -> Result<(SnapshotState, TsdfMap)> {
    let bad = |what: String| anyhow::anyhow!("{}: {what}", path.display());
    if bytes.len() < 8 || &bytes[..8] != SNAPSHOT_MAGIC {
        return Err(bad("not an sgam snapshot".into()));
    }
    if bytes.len() < 24 {
        return Err(bad(format!("truncated ({} bytes)", bytes.len())));
    }
    let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
    if version != SNAPSHOT_VERSION {
        let v1 = u64::from_le_bytes(bytes[8..16].try_into()?) as usize + 16 <= bytes.len() && bytes[16] == b'{';
        return Err(bad(if v1 {
            format!(
                "snapshot format 1 (written by an older sgam, without a checksum over the run's state); this build \
                 resumes format {SNAPSHOT_VERSION} only"
            )
        } else {
            format!("snapshot format version {version} (this build reads {SNAPSHOT_VERSION})")
        }));
    }
    let body = bytes.len() - 4;
    let stored = u32::from_le_bytes(bytes[body..].try_into()?);
    let computed = crc32fast::hash(&bytes[..body]);
    if stored != computed {
        return Err(bad(format!(
            "checksum mismatch (stored {stored:#010x}, computed {computed:#010x}): the file is corrupt"
        )));
    }
    let len = u64::from_le_bytes(bytes[12..20].try_into()?);
    if len > (body - 20) as u64 {
        return Err(bad(format!("corrupt header (state of {len} bytes in a {} byte file)", bytes.len())));
    }
    let json_end = 20 + len as usize;
    let state: SnapshotState =
        serde_json::from_slice(&bytes[20..json_end]).map_err(|e| bad(format!("corrupt state: {e}")))?;
    let map = TsdfMap::read_from(&mut &bytes[json_end..body]).map_err(|e| bad(format!("corrupt map: {e}")))?;
    Ok((state, map))
}

/// Reads and validates `dir/snapshot.bin`: the file ([`parse_snapshot`]), then its content (the
/// arguments in range, rigid finite cameras of one size, one timing per step, the frames on
/// disk).
fn read_snapshot(dir: &Path) -> Result<(SnapshotState, TsdfMap)> {
    let path = dir.join("snapshot.bin");
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            bail!("{}: no snapshot to resume from (is {} a run folder?)", path.display(), dir.display())
        }
        Err(e) => return Err(e).with_context(|| format!("{}: cannot read", path.display())),
    };
    let (state, map) = parse_snapshot(&path, &bytes)?;
    let bad = |what: String| anyhow::anyhow!("{}: {what}", path.display());
    if state.version != SNAPSHOT_VERSION {
        return Err(bad(format!("state version {} (expected {SNAPSHOT_VERSION})", state.version)));
    }
    state.args.validate().map_err(|e| bad(format!("stored arguments: {e:#}")))?;
    let Some(first) = state.cameras.first() else { return Err(bad("no keyframe".into())) };
    if state.cameras.len() > state.args.steps + 1 || state.timings.len() + 1 != state.cameras.len() {
        return Err(bad(format!(
            "{} keyframes and {} step timings for a run of {} steps",
            state.cameras.len(),
            state.timings.len(),
            state.args.steps
        )));
    }
    for (i, c) in state.cameras.iter().enumerate() {
        let rigid = c.world_from_camera.is_finite()
            && sgam_core::Rigid3::try_from_rows(c.world_from_camera.to_rows()).is_ok()
            && c.world_from_camera.translation.abs().max_element() <= MAX_EXTENT_M;
        if !rigid || c.intrinsics != first.intrinsics {
            return Err(bad(format!("keyframe {i}: not a rigid pose in range, or another image size")));
        }
        let (rgb, depth) = Keyframes::frame_paths(dir, i);
        for f in [rgb, depth] {
            if !f.is_file() {
                return Err(bad(format!("keyframe {i}: {} is missing", f.display())));
            }
        }
    }
    Ok((state, map))
}

fn next_run_dir() -> PathBuf {
    (1..)
        .map(|i| PathBuf::from(format!("runs/world-{i:03}")))
        .find(|p| !p.exists())
        .unwrap_or_else(|| PathBuf::from("runs/world"))
}

/// CRC-32 of the model file the run's refiner loads (`--model`, or the bundled model); `None`
/// for the stand-ins.
fn model_crc32(args: &GenerateArgs) -> Result<Option<u32>> {
    if args.no_refine || matches!(args.refiner, RefinerKind::Null | RefinerKind::Oracle) {
        return Ok(None);
    }
    Ok(Some(match &args.model {
        Some(p) => {
            crate::guard::check_input_file("--model", p)?;
            crc32fast::hash(&std::fs::read(p).with_context(|| format!("--model {}: cannot read", p.display()))?)
        }
        None => crc32fast::hash(BUNDLED_MODEL),
    }))
}

/// Runs `sgam generate`. The run folder is locked for the whole run; a new run needs an empty
/// folder (or `--force`); a resumed run checks its snapshot and that its model file is the same.
pub fn run(args: GenerateArgs) -> Result<()> {
    let (args, dir, resumed) = match &args.resume {
        Some(dir) => {
            if !dir.is_dir() {
                bail!("--resume {}: no such run folder", dir.display());
            }
            if !dir.join("snapshot.bin").exists() {
                bail!("--resume {}: no snapshot.bin to resume from (is it a run folder?)", dir.display());
            }
            (args.clone(), dir.clone(), true)
        }
        None => {
            args.validate()?;
            let dir = args.out.clone().unwrap_or_else(next_run_dir);
            (args, dir, false)
        }
    };
    let _lock = RunLock::acquire(&dir)?;
    crate::guard::remove_stale_temp_files(&dir, &["rgb", "depth"])?;
    let (args, resumed) = if resumed {
        let (state, map) = read_snapshot(&dir)?;
        let mut a = state.args;
        if let Some(n) = args.stop_after {
            in_range("--stop-after", n, 1..=MAX_STEPS)?;
        }
        a.stop_after = args.stop_after;
        (a.view, a.view_port, a.view_every) = (args.view, args.view_port, args.view_every);
        if model_crc32(&a)? != state.model_crc32 {
            bail!(
                "{}: the model ({}) is not the file this run started with; resume with that file, or start a new run",
                dir.display(),
                a.model.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| "bundled".into())
            );
        }
        (a, Some(Resume { cameras: state.cameras, timings: state.timings, map, model_crc32: state.model_crc32 }))
    } else {
        let hint = if dir.join("snapshot.bin").exists() {
            format!("continue it with --resume {}, or ", dir.display())
        } else {
            String::new()
        };
        crate::guard::claim_empty_folder(&dir, args.force, RUN_OUTPUTS, &hint)?;
        (args, None)
    };
    let stamp = match &resumed {
        Some(r) => r.model_crc32,
        None => model_crc32(&args)?,
    };
    let seed = load_seed(&args)?;
    let refiner = if args.no_refine { RefinerKind::Null } else { args.refiner };
    match refiner {
        RefinerKind::Auto | RefinerKind::Null | RefinerKind::Model => match model_refiner(refiner, &args)? {
            Some(model) => run_with(&args, &dir, resumed, stamp, seed, model),
            None => run_with(&args, &dir, resumed, stamp, seed, NullRefiner { fill: !args.no_refine }),
        },
        RefinerKind::Oracle => {
            let Some(renderer) = seed.renderer.clone() else {
                bail!(
                    "--refiner oracle needs a synthetic seed (no --seed-rgb / --seed-template / --seed-google-earth)"
                );
            };
            run_with(&args, &dir, resumed, stamp, seed, OracleRefiner::new(renderer, RenderConfig::default()))
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
    model_crc32: Option<u32>,
}

/// Writes `depth/NNNNN.png` (millimetres) of keyframe `index`; depth beyond what 16 bits hold is
/// stored as invalid (0), not clipped to a wrong value.
fn write_depth_png(dir: &Path, index: usize, depth_m: &sgam_core::Image<f32>) -> Result<()> {
    let (_, path) = Keyframes::frame_paths(dir, index);
    let mut depth = depth_m.clone();
    for d in &mut depth.data {
        if *d > DEPTH_PNG_MAX_M {
            *d = 0.0;
        }
    }
    sgam_io::write_depth_png_mm(&path.with_extension("png"), &depth)?;
    Ok(())
}

fn run_with<R: Refiner>(
    args: &GenerateArgs,
    dir: &Path,
    resume: Option<Resume>,
    model_crc32: Option<u32>,
    seed: Seed,
    refiner: R,
) -> Result<()> {
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
        // the oracle is the true world: never snapped
        ground_snap_m: (args.ground_snap > 0.0 && args.refiner != RefinerKind::Oracle).then_some(args.ground_snap),
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
        (TsdfMap::new(tsdf), Vec::new())
    };
    let mut gen = WorldGenerator::new(map, keyframes, refiner, config);
    let snapshot = |gen: &WorldGenerator<R>, timings: &[StepTimings]| {
        let state = SnapshotState {
            version: SNAPSHOT_VERSION,
            args: args.clone(),
            cameras: gen.keyframes.cameras().to_vec(),
            timings: timings.to_vec(),
            model_crc32,
        };
        write_snapshot(dir, &state, &gen.map)
    };
    if !resumed {
        gen.seed(&cameras[0], seed.frame.clone())?;
        if args.depth_png {
            write_depth_png(dir, 0, &gen.keyframes.frame(0)?.depth_m)?;
        }
        // a snapshot from the start: a run killed before its first --snapshot-every is resumable
        snapshot(&gen, &timings)?;
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
    let mut live = crate::live::LiveView::start_if(args.view, dir, args.view_port, args.view_every)?;
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
        live.after_step(i, total, &mut gen.map, gen.keyframes.cameras());
        this_run += 1;
        pb.inc(1);
        pb.set_message(format!("{:.0} ms/step, {:.0}% invented", t.total_ms, 100.0 * t.missing_fraction));
        if args.depth_png {
            write_depth_png(dir, i, &gen.keyframes.frame(i)?.depth_m)?;
        }
        if args.mesh_every > 0 && i % args.mesh_every == 0 {
            write_mesh(&dir.join(format!("mesh-{i:05}.ply")), &gen.map.extract_mesh(1.0))?;
        }
        let finished = i + 1 == total;
        let stopping = args.stop_after.is_some_and(|n| this_run >= n);
        if finished || stopping || i % args.snapshot_every == 0 {
            snapshot(&gen, &timings)?;
        }
        if stopping && !finished {
            pb.finish_and_clear();
            eprintln!("stopped after {this_run} steps; continue with: sgam generate --resume {}", dir.display());
            return Ok(());
        }
    }
    pb.finish_and_clear();
    let wall_s = start.elapsed().as_secs_f64();
    finish_outputs(args, dir, &mut gen, &timings, wall_s)?;
    live.finish(gen.keyframes.cameras());
    Ok(())
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
    if !args.no_video && !args.no_mp4 {
        crate::video::write_flythrough_mp4(dir, cams.len())?;
    }
    if args.orbit_video {
        crate::video::write_orbit_mp4(&dir.join("orbit.mp4"), &gen.map, &mesh, crate::view::up_world(&cams[0]))?;
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
    let page = crate::view::write_world_html(dir, crate::view::DEFAULT_EMBED_LIMIT_BYTES)?;
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
    if !args.no_video && !args.no_mp4 {
        eprintln!("  video:       {}", dir.join("flythrough.mp4").display());
    }
    if args.orbit_video {
        eprintln!("  orbit:       {}", dir.join("orbit.mp4").display());
    }
    eprintln!(
        "  viewer:      {}  (open it in a browser{})",
        page.path.display(),
        if page.mesh_embedded { String::new() } else { format!("; large mesh: sgam view {} --serve", dir.display()) }
    );
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

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A valid `snapshot.bin` of a one-keyframe run, made once.
    fn valid_snapshot() -> &'static [u8] {
        static BYTES: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
        BYTES.get_or_init(|| {
            let tmp = tempfile::tempdir().unwrap();
            let state = SnapshotState {
                version: SNAPSHOT_VERSION,
                args: GenerateArgs::for_refiner(RefinerKind::Null, None, false),
                cameras: vec![synthetic_seed_camera(32)],
                timings: vec![],
                model_crc32: Some(7),
            };
            write_snapshot(tmp.path(), &state, &TsdfMap::new(TsdfConfig::default())).unwrap();
            std::fs::read(tmp.path().join("snapshot.bin")).unwrap()
        })
    }

    #[test]
    fn a_snapshot_round_trips_and_default_arguments_are_valid() {
        let (state, map) = parse_snapshot(Path::new("snapshot.bin"), valid_snapshot()).unwrap();
        assert_eq!((state.cameras.len(), state.model_crc32, map.block_count()), (1, Some(7), 0));
        state.args.validate().unwrap();
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

        #[test]
        fn arbitrary_bytes_never_panic(mut bytes in prop::collection::vec(any::<u8>(), 0..256), magic in any::<bool>()) {
            if magic && bytes.len() >= 12 {
                bytes[..8].copy_from_slice(SNAPSHOT_MAGIC);
                bytes[8..12].copy_from_slice(&SNAPSHOT_VERSION.to_le_bytes());
            }
            let _ = parse_snapshot(Path::new("snapshot.bin"), &bytes);
        }

        #[test]
        fn any_flipped_byte_or_cut_is_an_error(pos in 0.0f64..1.0, x in 1u8..=255, cut in 0.0f64..1.0) {
            let good = valid_snapshot();
            let mut bytes = good.to_vec();
            let i = ((bytes.len() - 1) as f64 * pos) as usize;
            bytes[i] ^= x;
            prop_assert!(parse_snapshot(Path::new("snapshot.bin"), &bytes).is_err(), "byte {} flipped was accepted", i);
            let short = &good[..((good.len() - 1) as f64 * cut) as usize];
            prop_assert!(parse_snapshot(Path::new("snapshot.bin"), short).is_err());
        }
    }
}
