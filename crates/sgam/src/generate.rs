//! `sgam generate`: its arguments, their checks and their resolution into the pipeline's
//! [`RunConfig`]; the run itself is [`sgam_pipeline::run::generate`], its outputs
//! [`crate::outputs`].

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::{Args, ValueEnum};
use serde::{Deserialize, Serialize};
use sgam_pipeline::snapshot::SNAPSHOT_FILE;
use sgam_pipeline::{
    check_intrinsics, OutputSettings, RefinerSpec, RunConfig, SeedSpec, TrajectorySpec, HELD_OUT_SEED_BASE,
    RUN_CONFIG_VERSION,
};

use crate::guard::{in_range, positive, RunLock};

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
/// object of the synthetic world (1.4 m), above the bundled model's ground error. Session 11
/// chose 1.2 m on training seeds 11-14 to take in the grey lumps plain sampling invented
/// (0.7-1.2 m high); with two-level sampling and free-space carving, 1.0 m keeps more objects
/// (0.69x against 0.61x of the true density on training seeds 11-18; docs/MODEL.md, session 12).
pub const DEFAULT_GROUND_SNAP_M: f32 = 1.0;

/// Default sampling temperature (generate, eval world, eval table, bench): chosen on training
/// seeds 11-14 between 1.0, 1.15, 1.3 and 1.5 (docs/MODEL.md); 1.0 under-starts objects, 1.5
/// washes out their colour.
pub const DEFAULT_TEMPERATURE: f32 = 1.3;

/// Default of `--cells-per-pass` (generate, eval world, eval table, bench): chosen on training
/// seeds 11-14 against the library's 48 (docs/MODEL.md). A zig-zag step's 20-60 new cells then
/// take 3-4 passes instead of one, so the cells of one new object see each other's draws.
pub const DEFAULT_CELLS_PER_PASS: usize = 8;

/// What `sgam generate` does with invented flying pixels (docs/MODEL.md, session 11).
pub const DEFAULT_FLYING_PIXELS: FlyingPixels = FlyingPixels::Snap;

/// `--flying-pixels`: invented pixels that hang between two surfaces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FlyingPixels {
    /// Give each to the nearer surface or to the ground behind it.
    Snap,
    /// Fuse them as the refiner drew them.
    Keep,
}

/// Snapshots written before `--flying-pixels` existed resume as they ran: keeping them.
fn flying_pixels_before_session_11() -> FlyingPixels {
    FlyingPixels::Keep
}

/// Default of `--within-temperature` (generate, eval world, eval table, bench): chosen on
/// training seeds 11-14 between 0 (off), 1.0, 0.6 and 0.4 (docs/MODEL.md, session 12). The
/// class of a missing cell keeps T = 1.3's odds, the code within it is drawn at 0.6: the objects'
/// colour saturation went from 0.62x to 0.89x of the true world's and KID from 0.028 to 0.010.
pub const DEFAULT_WITHIN_TEMPERATURE: f32 = 0.6;

/// What `sgam generate` does with invented pixels earlier views saw through (docs/MODEL.md,
/// session 12).
pub const DEFAULT_FREE_SPACE: FreeSpace = FreeSpace::Carve;

/// `--free-space`: invented pixels in space the seed frame or a source saw as empty.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FreeSpace {
    /// Put each on the ground plane behind it, or drop it (not fused).
    Carve,
    /// Fuse them as the refiner drew them.
    Keep,
}

/// Snapshots written before `--free-space` existed resume as they ran: keeping them.
fn free_space_before_session_12() -> FreeSpace {
    FreeSpace::Keep
}

/// Default of `--top-k` (generate, eval world): 0, all codes (the trained distribution).
pub const DEFAULT_TOP_K: usize = 0;

fn default_cells_per_pass() -> usize {
    DEFAULT_CELLS_PER_PASS
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
    #[arg(long, default_value_t = DEFAULT_TOP_K)]
    pub top_k: usize,
    /// Two-level sampling (0 = off): a missing cell first draws its class — plain (the grey
    /// ground's codes) or coloured (objects) — at --temperature, so objects start as often as
    /// before, then its code within that class at this lower temperature: the likeliest
    /// colours and shapes, the likeliest ground. Overrides --top-k.
    #[arg(long, default_value_t = DEFAULT_WITHIN_TEMPERATURE)]
    #[serde(default)]
    pub within_temperature: f32,
    /// Invented pixels that hang between two surfaces: where the refiner draws an object's
    /// silhouette against the ground behind as a depth ramp, the ramp's pixels float in the air
    /// and fuse into a sloped skirt around the object. `snap` gives each to the nearer surface
    /// or to the ground plane behind (a 9x9 neighbourhood spanning over 5 % of the depth);
    /// `keep` fuses them as drawn. The oracle's depth is never changed.
    #[arg(long, value_enum, default_value_t = DEFAULT_FLYING_PIXELS)]
    #[serde(default = "flying_pixels_before_session_11")]
    pub flying_pixels: FlyingPixels,
    /// Invented pixels in space that an earlier view saw as empty: the map keeps only a band
    /// around surfaces, so a ray through space the seed frame saw empty can come back missing,
    /// and the refiner may put an object there, in front of what the seed saw. `carve` checks
    /// every invented pixel against the seed frame and the step's sources and puts one they
    /// saw through on the ground plane behind it (or drops it); `keep` fuses them as drawn.
    /// The oracle's depth is never changed.
    #[arg(long, value_enum, default_value_t = DEFAULT_FREE_SPACE)]
    #[serde(default = "free_space_before_session_12")]
    pub free_space: FreeSpace,
    /// Iterative (MaskGIT-style) sampling: missing latent cells drawn per pass. A hole of more
    /// cells takes several passes (at most 4); each commits the most confident draws and
    /// re-encodes, so later cells see earlier ones. Larger = faster, less coherent.
    #[arg(long, default_value_t = DEFAULT_CELLS_PER_PASS)]
    #[serde(default = "default_cells_per_pass")]
    pub cells_per_pass: usize,
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

pub use sgam_pipeline::{MAX_GRID, MAX_RES, MAX_STEPS};
/// Largest depth a 16-bit millimetre PNG holds, metres.
pub const DEPTH_PNG_MAX_M: f32 = sgam_io::DEPTH_PNG_MAX_MM as f32 / 1000.0;

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
        in_range("--within-temperature", self.within_temperature, 0.0..=100.0)?;
        in_range("--cells-per-pass", self.cells_per_pass, 1..=4096)?;
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

/// Side of the square grid of the grid trajectories (zig-zag, boustrophedon, greedy): `--grid`,
/// enlarged when it has fewer cells than poses.
fn grid_side(args: &GenerateArgs) -> usize {
    args.grid.max(((args.steps + 1) as f64).sqrt().ceil() as usize)
}

/// The run the arguments describe, every default applied: the seed's preset (CLEVR or Google
/// Earth) fills the options left out.
pub fn resolve(args: &GenerateArgs) -> Result<RunConfig> {
    let seed = if let Some(rgb) = &args.seed_rgb {
        let (Some(depth), Some(intrinsics)) = (&args.seed_depth, args.intrinsics) else {
            bail!("--seed-rgb needs --seed-depth and --intrinsics");
        };
        SeedSpec::Rgbd { rgb: rgb.clone(), depth: depth.clone(), intrinsics }
    } else if let Some(dir) = &args.seed_template {
        SeedSpec::ClevrTemplate { dir: dir.clone() }
    } else if let Some(dir) = &args.seed_google_earth {
        SeedSpec::GoogleEarth { dir: dir.clone() }
    } else {
        SeedSpec::Synthetic { scene: args.seed_scene, res: args.res }
    };
    let preset = seed.preset();
    let (side, step_m) = (grid_side(args), args.step.unwrap_or(preset.step_m));
    let trajectory = match args.trajectory {
        TrajectoryKind::Zigzag => TrajectorySpec::Zigzag { side, step_m },
        TrajectoryKind::Boustrophedon => TrajectorySpec::Boustrophedon { side, step_m },
        TrajectoryKind::Line => TrajectorySpec::Line { step_m },
        TrajectoryKind::Circle => TrajectorySpec::Circle { radius_m: args.radius },
        TrajectoryKind::Spiral => TrajectorySpec::Spiral { step_m, radius_m: args.radius },
        TrajectoryKind::Greedy => TrajectorySpec::Greedy { side, step_m },
        TrajectoryKind::File => {
            let Some(path) = &args.trajectory_file else { bail!("--trajectory file needs --trajectory-file PATH") };
            TrajectorySpec::File { path: path.clone() }
        }
    };
    if !(step_m.is_finite() && step_m > 0.0) {
        bail!("--step {step_m} must be a positive distance in metres");
    }
    Ok(RunConfig {
        version: RUN_CONFIG_VERSION,
        seed,
        trajectory,
        steps: args.steps,
        refiner: refiner_spec(args),
        map: sgam_map::TsdfConfig {
            voxel_size_m: args.voxel_size.unwrap_or(preset.voxel_size_m),
            trunc_voxels: args.trunc_voxels.unwrap_or(preset.trunc_voxels),
            depth_min_m: 0.05,
            depth_max_m: args.depth_max,
            weight_cap: args.weight_cap,
            weight_threshold: 1.0,
        },
        k_sources: args.k_sources.unwrap_or(preset.k_sources),
        source_radius_m: args.source_radius.unwrap_or(preset.source_radius_m),
        no_map: args.no_map,
        run_seed: args.seed,
        // the oracle is the true world: never snapped
        ground_snap_m: (args.ground_snap > 0.0 && args.refiner != RefinerKind::Oracle).then_some(args.ground_snap),
        snap_flying_pixels: args.flying_pixels == FlyingPixels::Snap && args.refiner != RefinerKind::Oracle,
        carve_free_space: args.free_space == FreeSpace::Carve && args.refiner != RefinerKind::Oracle,
        outputs: OutputSettings {
            snapshot_every: args.snapshot_every,
            mesh_every: args.mesh_every,
            depth_png: args.depth_png,
            video: !args.no_video,
            mp4: !args.no_mp4,
            orbit_video: args.orbit_video,
        },
    })
}

/// The refiner the arguments name: `--no-refine` passes the guidance through, `--refiner null`
/// fills holes by push-pull, the model samples with `--temperature` / `--top-k` / `--seed`.
pub fn refiner_spec(args: &GenerateArgs) -> RefinerSpec {
    let kind = if args.no_refine { RefinerKind::Null } else { args.refiner };
    match kind {
        RefinerKind::Auto | RefinerKind::Model => RefinerSpec::Model {
            model: args.model.clone(),
            options: sgam_model::RefinerOptions {
                sampling: sgam_pipeline::sampling(args.temperature, args.top_k),
                seed: args.seed,
                keep_observed: !args.regenerate_observed,
                cells_per_pass: args.cells_per_pass,
                within_class_temperature: (args.within_temperature > 0.0).then_some(args.within_temperature),
                ..Default::default()
            },
        },
        RefinerKind::Null => RefinerSpec::Null { fill: !args.no_refine },
        RefinerKind::Oracle => RefinerSpec::Oracle,
    }
}

/// The learned refiner `args` name with refiner `kind` (`None` for the stand-ins), for the
/// evaluation commands that call a refiner directly.
pub fn model_refiner(kind: RefinerKind, args: &GenerateArgs) -> Result<Option<sgam_model::VqRefiner>> {
    let mut a = args.clone();
    a.refiner = kind;
    Ok(match refiner_spec(&a) {
        RefinerSpec::Model { model, options } => Some(sgam_pipeline::model_refiner(model.as_deref(), options)?),
        RefinerSpec::Null { .. } | RefinerSpec::Oracle => None,
    })
}

fn next_run_dir() -> PathBuf {
    (1..)
        .map(|i| PathBuf::from(format!("runs/world-{i:03}")))
        .find(|p| !p.exists())
        .unwrap_or_else(|| PathBuf::from("runs/world"))
}

/// CRC-32 of the model file the run's refiner loads (`--model`, or the bundled model); `None`
/// for the stand-ins.
fn model_crc32(refiner: &RefinerSpec) -> Result<Option<u32>> {
    if let RefinerSpec::Model { model: Some(p), .. } = refiner {
        crate::guard::check_input_file("--model", p)?;
    }
    Ok(refiner.model_crc32()?)
}

/// Runs `sgam generate`. The run folder is locked for the whole run; a new run needs an empty
/// folder (or `--force`); a resumed run checks its snapshot and that its model file is the same.
pub fn run(args: GenerateArgs) -> Result<()> {
    let (dir, resuming) = match &args.resume {
        Some(dir) => {
            if !dir.is_dir() {
                bail!("--resume {}: no such run folder", dir.display());
            }
            if !dir.join(SNAPSHOT_FILE).exists() {
                bail!("--resume {}: no snapshot.bin to resume from (is it a run folder?)", dir.display());
            }
            (dir.clone(), true)
        }
        None => {
            args.validate()?;
            (args.out.clone().unwrap_or_else(next_run_dir), false)
        }
    };
    let _lock = RunLock::acquire(&dir)?;
    crate::guard::remove_stale_temp_files(&dir, &["rgb", "depth"])?;
    let (config, resume, stamp) = if resuming {
        let (state, map) = sgam_pipeline::snapshot::read_snapshot(&dir)?;
        if let Some(n) = args.stop_after {
            in_range("--stop-after", n, 1..=MAX_STEPS)?;
        }
        if model_crc32(&state.config.refiner)? != state.model_crc32 {
            let model = match &state.config.refiner {
                RefinerSpec::Model { model: Some(p), .. } => p.display().to_string(),
                _ => "bundled".into(),
            };
            bail!(
                "{}: the model ({model}) is not the file this run started with; resume with that file, or start a new run",
                dir.display(),
            );
        }
        let stamp = state.model_crc32;
        (state.config.clone(), Some(sgam_pipeline::Resume { state, map }), stamp)
    } else {
        let hint = if dir.join(SNAPSHOT_FILE).exists() {
            format!("continue it with --resume {}, or ", dir.display())
        } else {
            String::new()
        };
        crate::guard::claim_empty_folder(&dir, args.force, RUN_OUTPUTS, &hint)?;
        let config = resolve(&args)?;
        let stamp = model_crc32(&config.refiner)?;
        (config, None, stamp)
    };
    let mut observer = crate::outputs::CliObserver::new(&dir, &config, (args.view, args.view_port, args.view_every));
    let generated = sgam_pipeline::run::generate(&dir, &config, resume, stamp, args.stop_after, &mut observer)?;
    observer.finish_progress();
    if !generated.finished {
        eprintln!(
            "stopped after {} steps; continue with: sgam generate --resume {}",
            generated.steps_this_run,
            dir.display()
        );
        return Ok(());
    }
    let mut generated = generated;
    crate::outputs::finish_outputs(&config, &dir, &mut generated)?;
    observer.finish_live(generated.generator.keyframes.cameras());
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

    #[test]
    fn default_arguments_are_valid_and_resolve_to_the_clevr_preset() {
        let args = GenerateArgs::for_refiner(RefinerKind::Null, None, false);
        args.validate().unwrap();
        let c = resolve(&args).unwrap();
        c.validate().unwrap();
        assert_eq!(c.trajectory, TrajectorySpec::Zigzag { side: 30, step_m: 0.408 });
        assert_eq!((c.map.voxel_size_m, c.map.trunc_voxels, c.k_sources), (0.05, 5.0, 5));
        assert_eq!(c.map, sgam_pipeline::clevr_generator_config(0).tsdf, "generation and training share the map");
        assert_eq!(c.refiner, RefinerSpec::Null { fill: true });
        // flying pixels are snapped by default, never the oracle's, and `keep` turns it off
        assert!(c.snap_flying_pixels);
        assert!(!resolve(&GenerateArgs::for_refiner(RefinerKind::Oracle, None, false)).unwrap().snap_flying_pixels);
        let keep = GenerateArgs { flying_pixels: FlyingPixels::Keep, ..args.clone() };
        assert!(!resolve(&keep).unwrap().snap_flying_pixels);
        // free space is carved by default, never the oracle's, and `keep` turns it off
        assert!(c.carve_free_space);
        assert!(!resolve(&GenerateArgs::for_refiner(RefinerKind::Oracle, None, false)).unwrap().carve_free_space);
        let keep = GenerateArgs { free_space: FreeSpace::Keep, ..args.clone() };
        assert!(!resolve(&keep).unwrap().carve_free_space);
        let mut ge = args.clone();
        ge.seed_google_earth = Some("seed0".into());
        let c = resolve(&ge).unwrap();
        assert_eq!((c.map.voxel_size_m, c.k_sources, c.source_radius_m), (0.01, 3, 0.3));
        ge.no_refine = true;
        assert_eq!(resolve(&ge).unwrap().refiner, RefinerSpec::Null { fill: false });
    }
}
