//! A run's settings as a user states them, in groups, with their defaults: the one place where a
//! default is written. Each group is a clap [`Args`] that `sgam generate`, `sgam eval world`,
//! `sgam eval table` and `sgam bench` flatten into their command lines, and a plain struct whose
//! [`Default`] equals an empty command line (tested), so a program builds "the default run" with
//! [`RunSettings::clevr`] and changes what it needs. [`RunSettings::resolve`] applies the seed's
//! preset ([`crate::Preset`]) to the options left out and gives the versioned [`RunConfig`] a run
//! stores.
//!
//! How the defaults were chosen is in docs/MODEL.md (sampling, the invented-pixel policy) and
//! `crate::seeds` (map and sources).

use std::fmt::Display;
use std::ops::RangeInclusive;
use std::path::PathBuf;

use clap::{Args, ValueEnum};
use serde::{Deserialize, Serialize};

use crate::error::config_error;
use crate::BankSpec;
use crate::{
    check_intrinsics, OutputSettings, RefinerSpec, Result, RunConfig, SeedSpec, TrajectorySpec, HELD_OUT_SEED_BASE,
    MAX_GRID, MAX_RES, MAX_STEPS, RUN_CONFIG_VERSION,
};

/// Default of `--temperature`: chosen on training seeds 11-14 between 1.0, 1.15, 1.3 and 1.5;
/// 1.0 under-starts objects, 1.5 washes out their colour.
pub const DEFAULT_TEMPERATURE: f32 = 1.3;
/// Default of `--within-temperature`: chosen on training seeds 11-14 between 0 (off), 1.0, 0.6
/// and 0.4. The class of a missing cell keeps `--temperature`'s odds and its code within the
/// class is drawn at 0.6: objects' colour saturation went from 0.62x to 0.89x of the true
/// world's and KID from 0.028 to 0.010.
pub const DEFAULT_WITHIN_TEMPERATURE: f32 = 0.6;
/// Default of `--cells-per-pass`: chosen on training seeds 11-14 against 48. A zig-zag step's
/// 20-60 new cells take 3-4 passes instead of one, so the cells of one new object see each
/// other's draws.
pub const DEFAULT_CELLS_PER_PASS: usize = 8;
/// `--quilt-tile` of the CLEVR and RGB-D presets, latent cells: chosen between 0 (whole holes,
/// the stripes), 4 and 8 on the three Google Earth seeds and the 7-Scenes frame (60 steps, two
/// run seeds each; docs/MODEL.md, session 22). 4 let smooth textures (a road, a lawn) spread over
/// the new area. Chosen on the line, Google Earth's own path: on the zig-zag and the spiral
/// tiles score worse by KID, and on the spiral a roof grows step by step (docs/STATUS.md,
/// session 23). Superseded for Google Earth seeds in session 31: 12-cell tiles
/// ([`crate::seeds::GOOGLE_EARTH`]); the 7-Scenes frame kept 8.
pub const DEFAULT_QUILT_TILE: usize = 8;
/// Default of `--max-passes`: the refiner's own, 4 since session 10.
pub const DEFAULT_MAX_PASSES: usize = sgam_model::refiner::DEFAULT_MAX_PASSES;
/// Default of `--hue-coherence`: off.
pub const DEFAULT_HUE_COHERENCE: f32 = 0.0;
/// Default of `--class-coherence`: off (an experiment, docs/MODEL.md session 31).
pub const DEFAULT_CLASS_COHERENCE: f32 = 0.0;
/// Default of `--top-k`: 0, all codes (the trained distribution).
pub const DEFAULT_TOP_K: usize = 0;
/// Default of `--ground-snap`, metres: below the shortest object of the synthetic world
/// (1.4 m), above the bundled model's ground error; with two-level sampling and free-space
/// carving 1.0 m keeps more objects than 1.2 m (0.69x against 0.61x of the true density on
/// training seeds 11-18).
pub const DEFAULT_GROUND_SNAP_M: f32 = 1.0;
/// Default of `--ground-flatten`, metres: below the metric's object height (0.25 m above the
/// ground counts as raised) and far below the shortest object (1.4 m). On training seeds 11-12
/// (400 steps, the bank) it took the zig-zag's ground from 1.71x to 1.34x the true world's
/// roughness and the spiral's from 2.25x to 1.58x; 0.15 m did less (1.52x, 2.18x)
/// (docs/MODEL.md, session 17).
pub const DEFAULT_GROUND_FLATTEN_M: f32 = 0.3;
/// Default of `--flying-pixels`.
pub const DEFAULT_FLYING_PIXELS: FlyingPixels = FlyingPixels::Snap;
/// Default of `--free-space`.
pub const DEFAULT_FREE_SPACE: FreeSpace = FreeSpace::Carve;
/// Default of `--steps` for `sgam generate`.
pub const DEFAULT_STEPS: usize = 100;
/// Default of `--res` (synthetic seeds).
pub const DEFAULT_RES: u32 = 256;
/// Default of `--grid` (the paper's 30x30 zig-zag).
pub const DEFAULT_GRID: usize = 30;
/// Default of `--radius`, metres.
pub const DEFAULT_RADIUS_M: f32 = 4.0;
/// Default of `--depth-max`, metres.
pub const DEFAULT_DEPTH_MAX_M: f32 = 20.0;
/// Default of `--snapshot-every`.
pub const DEFAULT_SNAPSHOT_EVERY: usize = 25;

/// `option` must lie in `range`; the error names the option and the range.
pub fn in_range<T: PartialOrd + Display>(option: &str, value: T, range: RangeInclusive<T>) -> Result<()> {
    if !range.contains(&value) {
        config_error!("{option} {value} is out of range: accepted {}..={}", range.start(), range.end());
    }
    Ok(())
}

/// `value` must be a positive number no larger than `max`.
pub fn positive(option: &str, value: f32, max: f32) -> Result<()> {
    if !(value > 0.0 && value <= max) {
        config_error!("{option} {value} is out of range: accepted a positive number up to {max}");
    }
    Ok(())
}

/// Camera path shapes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
pub enum TrajectoryKind {
    /// The seed's own path (default): a CLEVR-Infinite seed (synthetic or template) takes the
    /// zig-zag, 0.408 m a step; a Google Earth seed a straight line forward, 0.059 units a step
    /// (the authors' preset); an RGB-D seed a straight line forward, each step 5 % of the
    /// seed's median depth, so every step uncovers new ground whatever the seed's scale.
    /// --step overrides the step.
    Auto,
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
    /// The VQ model: --model when given, else the bundled model (a compact VQ autoencoder with
    /// a context transformer over its code grid, trained on the synthetic CLEVR-Infinite world).
    Auto,
    /// Same as auto (kept for scripts that name it).
    Model,
    /// Stand-in: holes filled by push-pull interpolation.
    Null,
    /// Stand-in: ground truth of the synthetic world (synthetic seeds only).
    Oracle,
}

/// `--flying-pixels`: invented pixels that hang between two surfaces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FlyingPixels {
    /// Give each to the nearer surface or to the ground behind it.
    Snap,
    /// Fuse them as the refiner drew them.
    Keep,
}

/// `--free-space`: invented pixels in space the seed frame or a source saw as empty.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FreeSpace {
    /// Put each on the ground plane behind it, or drop it (not fused).
    Carve,
    /// Fuse them as the refiner drew them.
    Keep,
}

/// Where the seed frame comes from.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct SeedSettings {
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
    /// 1 cm voxels, 3 cm truncation, sources within 0.3, nearest 3; a straight line forward, 0.059 units a step).
    #[arg(long)]
    pub seed_google_earth: Option<PathBuf>,
    /// Image resolution of synthetic seeds (square).
    #[arg(long, default_value_t = DEFAULT_RES)]
    pub res: u32,
}

impl Default for SeedSettings {
    fn default() -> Self {
        Self::synthetic(HELD_OUT_SEED_BASE)
    }
}

impl SeedSettings {
    /// The synthetic CLEVR-Infinite scene `scene` at the default resolution.
    pub fn synthetic(scene: u64) -> Self {
        Self {
            seed_scene: scene,
            seed_rgb: None,
            seed_depth: None,
            intrinsics: None,
            seed_template: None,
            seed_google_earth: None,
            res: DEFAULT_RES,
        }
    }

    /// Checks the resolution, that one seed is named, and an RGB seed's intrinsics against its
    /// image.
    pub fn validate(&self) -> Result<()> {
        in_range("--res", self.res, 16..=MAX_RES)?;
        if let (Some(rgb), Some(k)) = (&self.seed_rgb, self.intrinsics) {
            let (w, h) = sgam_io::image_size(rgb)?;
            check_intrinsics(k, w, h)?;
        }
        if self.seed_rgb.is_none() {
            for (given, name) in
                [(self.seed_depth.is_some(), "--seed-depth"), (self.intrinsics.is_some(), "--intrinsics")]
            {
                if given {
                    config_error!("{name} describes an RGB seed: it needs --seed-rgb");
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
            config_error!("{} are different seeds: give one", seeds.join(" and "));
        }
        Ok(())
    }

    /// The seed these settings name.
    pub fn spec(&self) -> Result<SeedSpec> {
        Ok(if let Some(rgb) = &self.seed_rgb {
            let (Some(depth), Some(intrinsics)) = (&self.seed_depth, self.intrinsics) else {
                config_error!("--seed-rgb needs --seed-depth and --intrinsics");
            };
            SeedSpec::Rgbd { rgb: rgb.clone(), depth: depth.clone(), intrinsics }
        } else if let Some(dir) = &self.seed_template {
            SeedSpec::ClevrTemplate { dir: dir.clone() }
        } else if let Some(dir) = &self.seed_google_earth {
            SeedSpec::GoogleEarth { dir: dir.clone() }
        } else {
            SeedSpec::Synthetic { scene: self.seed_scene, res: self.res }
        })
    }
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

/// The camera path.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct PathSettings {
    /// Trajectory shape.
    #[arg(long, value_enum, default_value_t = TrajectoryKind::Auto)]
    pub trajectory: TrajectoryKind,
    /// Pose file for --trajectory file: transforms.json (ours / NeRF), TUM (.txt with 8 columns)
    /// or KITTI (12 columns). Poses are used as given (world_from_camera).
    #[arg(long)]
    pub trajectory_file: Option<PathBuf>,
    /// Grid side of zig-zag / boustrophedon / greedy trajectories (the paper: 30); enlarged
    /// when it has fewer cells than poses.
    #[arg(long, default_value_t = DEFAULT_GRID)]
    pub grid: usize,
    /// Distance between neighbouring poses, metres (default: the seed's preset; CLEVR 0.408,
    /// half the dataset spacing, as the authors).
    #[arg(long)]
    pub step: Option<f32>,
    /// Circle radius / spiral growth per turn, metres.
    #[arg(long, default_value_t = DEFAULT_RADIUS_M)]
    pub radius: f32,
}

impl Default for PathSettings {
    fn default() -> Self {
        Self::kind(TrajectoryKind::Auto)
    }
}

impl PathSettings {
    /// The path `kind` with the default grid, step and radius.
    pub fn kind(kind: TrajectoryKind) -> Self {
        Self { trajectory: kind, trajectory_file: None, grid: DEFAULT_GRID, step: None, radius: DEFAULT_RADIUS_M }
    }

    /// Checks the numbers and that a pose file goes with `--trajectory file` only.
    pub fn validate(&self) -> Result<()> {
        in_range("--grid", self.grid, 1..=MAX_GRID)?;
        if let Some(step) = self.step {
            positive("--step", step, 1000.0)?;
        }
        positive("--radius", self.radius, 10_000.0)?;
        match (self.trajectory, &self.trajectory_file) {
            (TrajectoryKind::File, None) => config_error!("--trajectory file needs --trajectory-file PATH"),
            (kind, Some(_)) if kind != TrajectoryKind::File => {
                config_error!("--trajectory-file is read only with --trajectory file")
            }
            _ => Ok(()),
        }
    }

    /// The path of `steps` steps from `seed`, with `preset_step_m` where `--step` is left out;
    /// [`TrajectoryKind::Auto`] becomes the seed's own path (an RGB-D seed's depth is read for
    /// its step).
    pub fn spec(&self, steps: usize, seed: &SeedSpec, preset_step_m: f32) -> Result<TrajectorySpec> {
        let (kind, preset_step_m) = match (self.trajectory, seed) {
            (TrajectoryKind::Auto, SeedSpec::GoogleEarth { .. }) => (TrajectoryKind::Line, GOOGLE_EARTH_LINE_STEP),
            (TrajectoryKind::Auto, SeedSpec::Rgbd { .. }) => {
                let step = match self.step {
                    Some(s) => s,
                    None => rgbd_seed_step_m(seed)?,
                };
                (TrajectoryKind::Line, step)
            }
            (TrajectoryKind::Auto, _) => (TrajectoryKind::Zigzag, preset_step_m),
            (kind, _) => (kind, preset_step_m),
        };
        // the grid trajectories need a cell per pose
        let side = self.grid.max(((steps + 1) as f64).sqrt().ceil() as usize);
        let step_m = self.step.unwrap_or(preset_step_m);
        if !(step_m.is_finite() && step_m > 0.0) {
            config_error!("--step {step_m} must be a positive distance in metres");
        }
        Ok(match kind {
            TrajectoryKind::Auto => unreachable!("resolved above"),
            TrajectoryKind::Zigzag => TrajectorySpec::Zigzag { side, step_m },
            TrajectoryKind::Boustrophedon => TrajectorySpec::Boustrophedon { side, step_m },
            TrajectoryKind::Line => TrajectorySpec::Line { step_m },
            TrajectoryKind::Circle => TrajectorySpec::Circle { radius_m: self.radius },
            TrajectoryKind::Spiral => TrajectorySpec::Spiral { step_m, radius_m: self.radius },
            TrajectoryKind::Greedy => TrajectorySpec::Greedy { side, step_m },
            TrajectoryKind::File => {
                let Some(path) = &self.trajectory_file else {
                    config_error!("--trajectory file needs --trajectory-file PATH")
                };
                TrajectorySpec::File { path: path.clone() }
            }
        })
    }
}

/// Step of a Google Earth seed's default straight line, in the seed's units: the SGAM
/// authors' preset (100 poses, 0.059 apart).
pub const GOOGLE_EARTH_LINE_STEP: f32 = 0.059;
/// Step of an RGB-D seed's default straight line, as a share of the seed's median depth.
pub const RGBD_STEP_OF_MEDIAN_DEPTH: f32 = 0.05;

/// The default step of an RGB-D seed's line: [`RGBD_STEP_OF_MEDIAN_DEPTH`] of its median valid
/// depth.
fn rgbd_seed_step_m(seed: &SeedSpec) -> Result<f32> {
    let frame = seed.load()?.frame;
    let mut d: Vec<f32> = frame.depth_m.data.iter().copied().filter(|d| sgam_core::is_valid_depth(*d)).collect();
    if d.is_empty() {
        config_error!("the seed's depth holds no valid pixel, so no step can follow its scale (give --step)");
    }
    let mid = d.len() / 2;
    let (_, median, _) = d.select_nth_unstable_by(mid, f32::total_cmp);
    Ok(*median * RGBD_STEP_OF_MEDIAN_DEPTH)
}

/// Which refiner completes each step's guidance.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct RefinerSettings {
    /// Refiner: the learned model (auto, model) or a stand-in (null, oracle).
    #[arg(long, value_enum, default_value_t = RefinerKind::Auto)]
    pub refiner: RefinerKind,
    /// Model weights for the learned refiner (default: the bundled model, models/compact.safetensors).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Ablation: no refinement; the guidance (with holes) is fused as it is.
    #[arg(long)]
    pub no_refine: bool,
    /// Complete each hole from a bank of true frames' codes instead of sampling it
    /// (auto, none, bundled, seed, or a file from `sgam train bank`): the hole takes the codes
    /// of the real frame whose cells around it look most like the visible ones, so it holds
    /// whole objects; thin bands along the frame's border wait (--bands-wait).
    /// auto: none for a CLEVR-Infinite seed (the bundled model's context draws the holes; it
    /// beat the bundled bank on the held-out worlds, docs/STATUS.md), seed for a Google Earth
    /// or RGB-D seed. The bank must come from the same model (checked). bundled
    /// and bank files hold synthetic CLEVR-Infinite frames, for those seeds only; seed builds
    /// the bank from the seed frame itself (and its mirror image), and a hole takes the seed's
    /// pixels, so the new area grows in the seed's own look (the model has only seen the
    /// synthetic world).
    #[arg(long, value_name = "none|bundled|seed|FILE", default_value_t = BankSpec::Auto)]
    pub bank: BankSpec,
    /// Adapt the refiner to the seed for this many seconds before generating (0 = off): its
    /// autoencoder (encoder, codebook, decoder) is fine-tuned on crops of the seed and its mirror
    /// image, so that the seed's codes hold the seed (a Google Earth seed through the autoencoder:
    /// 7-9 dB before, 24-27 dB after 60 s on two cores), and on round trips of the seed along
    /// this run's path (the seed rendered to a camera of the path and back: the holes are what
    /// that camera did not see, the seed is their truth), with its depth coded over the seed's
    /// own depths. With --bank seed the holes then take the seed's codes under the adapted
    /// encoder, coloured by the adapted decoder, which blends them into their surroundings, and
    /// the seed's pixels give their depth; with --bank none (and --temperature 0) the adapted
    /// model draws them itself. Softer than the seed's own pixels and not better on every seed
    /// (docs/STATUS.md), so off by default. The weights go to RUN/adapted.safetensors; --resume
    /// uses them.
    #[arg(long, value_name = "SECONDS", default_value_t = 0.0)]
    pub adapt: f32,
}

impl Default for RefinerSettings {
    fn default() -> Self {
        Self::kind(RefinerKind::Auto)
    }
}

impl RefinerSettings {
    /// The refiner `kind` (the bundled model for the learned one).
    pub fn kind(kind: RefinerKind) -> Self {
        Self { refiner: kind, model: None, no_refine: false, bank: BankSpec::Auto, adapt: 0.0 }
    }

    /// The refiner that runs: `--no-refine` makes it the stand-in that fills nothing.
    pub fn effective(&self) -> RefinerKind {
        if self.no_refine {
            RefinerKind::Null
        } else {
            self.refiner
        }
    }

    /// Whether a stand-in (null or oracle) runs instead of the model.
    pub fn is_stand_in(&self) -> bool {
        matches!(self.effective(), RefinerKind::Null | RefinerKind::Oracle)
    }

    /// Refuses `--model` and `--bank` with a stand-in refiner, which would ignore them.
    pub fn validate(&self) -> Result<()> {
        let stand_in = if self.no_refine {
            "--no-refine".to_string()
        } else {
            format!("--refiner {:?}", self.refiner).to_lowercase()
        };
        in_range("--adapt", self.adapt, 0.0..=3600.0)?;
        for (option, given) in
            [("--model", self.model.is_some()), ("--bank", self.bank.is_explicit()), ("--adapt", self.adapt > 0.0)]
        {
            if self.is_stand_in() && given {
                config_error!(
                    "{option} is used only by the learned refiner; this run uses a stand-in ({stand_in}) and would ignore it"
                );
            }
        }
        Ok(())
    }
}

/// `--bands-wait`: how deep a hole at the frame's border must be before it is filled.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BandsWait {
    /// The seed's preset with its own pixels, 3 cells for a code bank's holes, 0 for the model's own draws.
    Auto,
    /// This many cells for both (0: every hole is filled at once).
    Cells(usize),
}

impl std::fmt::Display for BandsWait {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BandsWait::Auto => f.write_str("auto"),
            BandsWait::Cells(n) => write!(f, "{n}"),
        }
    }
}

impl std::str::FromStr for BandsWait {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "auto" => Ok(BandsWait::Auto),
            _ => s.parse().map(BandsWait::Cells).map_err(|_| format!("{s:?} is neither auto nor a number of cells")),
        }
    }
}

/// How the learned refiner draws the missing latent cells.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct SamplingSettings {
    /// Sampling temperature in missing latent cells: 1 draws from the generative model's trained
    /// distribution over codes, higher starts more objects, lower is more conservative, 0 =
    /// argmin everywhere (the deterministic completion).
    #[arg(long, default_value_t = DEFAULT_TEMPERATURE)]
    pub temperature: f32,
    /// Codes considered when sampling: the k nearest (0 = all, the calibrated distribution).
    #[arg(long, default_value_t = DEFAULT_TOP_K)]
    pub top_k: usize,
    /// Two-level sampling (0 = off): a missing cell first draws its class — plain (the grey
    /// ground's codes) or coloured (objects) — at --temperature, so objects start as often as
    /// before, then its code within that class at this lower temperature: the likeliest
    /// colours and shapes, the likeliest ground. Overrides --top-k.
    #[arg(long, default_value_t = DEFAULT_WITHIN_TEMPERATURE)]
    pub within_temperature: f32,
    /// Iterative (MaskGIT-style) sampling: missing latent cells drawn per pass. A hole of more
    /// cells takes several passes (at most --max-passes); each commits the most confident
    /// draws, so later cells see earlier ones. Larger = faster, less coherent.
    #[arg(long, default_value_t = DEFAULT_CELLS_PER_PASS)]
    pub cells_per_pass: usize,
    /// Iterative sampling: at most this many passes per hole (per window of the context): the
    /// cells of a pass are drawn side by side, unaware of each other's draws. More = more
    /// coherent, and each pass costs a run of the model (the context's transformer).
    #[arg(long, default_value_t = DEFAULT_MAX_PASSES)]
    pub max_passes: usize,
    /// Hue coherence of a context model's draws (0 = off): with two-level sampling, a missing
    /// cell that draws a coloured code next to cells already coloured pays up to this much for
    /// a hue turned away from theirs, so an object keeps one colour across its cells. In the
    /// model's logit units, which --within-temperature divides. How often cells start objects
    /// is unchanged; a code bank, a model without a context or --within-temperature 0 ignore it.
    #[arg(long, default_value_t = DEFAULT_HUE_COHERENCE, value_name = "LOGITS")]
    pub hue_coherence: f32,
    /// Class coherence of a context model's draws (0 = off): with two-level sampling, a missing
    /// cell's odds of drawing a coloured (object) code rather than a plain (ground) one move by
    /// up to this many logits towards the class of its decided neighbours. An experiment: on
    /// training scenes it smoothed the ground and started fewer objects (docs/MODEL.md, session
    /// 31). A code bank, a model without a context or --within-temperature 0 ignore it.
    #[arg(long, default_value_t = DEFAULT_CLASS_COHERENCE, value_name = "LOGITS")]
    pub class_coherence: f32,
    /// Let the model regenerate observed pixels too (the paper's behaviour). By default the
    /// guidance is kept where it was observed and the model fills only the missing pixels.
    #[arg(long)]
    pub regenerate_observed: bool,
    /// With a code bank (--bank): an object of the matched bank frame that the ground already
    /// seen would cut is left out of the hole (its cells take the bank row's ground), so the
    /// hole holds whole objects, or objects that continue one already seen, and no fragments.
    /// The best matches also pay for the objects they would cut. An ablation: on training seeds
    /// it grew fewer and smaller objects than the bank alone (docs/MODEL.md, session 20).
    #[arg(long)]
    pub whole_objects: bool,
    /// With a seed's own pixels as the bank (--bank seed, the default for a Google Earth or
    /// RGB-D seed): a hole larger than N x N latent cells is quilted as N x N tiles, the tile
    /// with the most known surroundings first, each matched on the pixels around it (tiles
    /// quilted before it included) at pixel offsets of up to half a cell; the thin bands a
    /// moving camera uncovers wait, row by row and column by column (--bands-wait). A band then
    /// continues what borders it piece by piece, not as one long strip of one place. 0 = one
    /// piece per hole (vertical stripes on Google Earth seeds). Default: the seed's preset, 12
    /// for a Google Earth seed, 8 otherwise.
    #[arg(long, value_name = "CELLS")]
    pub quilt_tile: Option<usize>,
    /// A hole along the frame's border that reaches fewer than N latent cells (8 px each) into
    /// the frame waits: it keeps a provisional colour and no depth, nothing is fused there, and
    /// it widens step by step until a whole object fits, instead of committing a sliver of one
    /// that the next step must continue. auto: with the seed's own pixels (--bank seed), the
    /// seed's preset, 8 for a Google Earth seed (a piece then holds whole houses and trees, not a
    /// strip of road continued into slanted streaks), 3 otherwise; 3 for a code bank's holes; 0
    /// (fill at once) for the model's own draws, where waiting grew larger mounds (docs/MODEL.md,
    /// session 29).
    #[arg(long, default_value_t = BandsWait::Auto, value_name = "CELLS|auto")]
    pub bands_wait: BandsWait,
    /// Run seed (sampling in the refiner): another seed grows another world.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl Default for SamplingSettings {
    fn default() -> Self {
        Self {
            temperature: DEFAULT_TEMPERATURE,
            top_k: DEFAULT_TOP_K,
            within_temperature: DEFAULT_WITHIN_TEMPERATURE,
            cells_per_pass: DEFAULT_CELLS_PER_PASS,
            max_passes: DEFAULT_MAX_PASSES,
            hue_coherence: DEFAULT_HUE_COHERENCE,
            class_coherence: DEFAULT_CLASS_COHERENCE,
            regenerate_observed: false,
            whole_objects: false,
            quilt_tile: None,
            bands_wait: BandsWait::Auto,
            seed: 0,
        }
    }
}

impl SamplingSettings {
    /// Checks every number.
    pub fn validate(&self) -> Result<()> {
        in_range("--temperature", self.temperature, 0.0..=100.0)?;
        in_range("--top-k", self.top_k, 0..=sgam_model::config::MAX_CODEBOOK)?;
        in_range("--within-temperature", self.within_temperature, 0.0..=100.0)?;
        in_range("--cells-per-pass", self.cells_per_pass, 1..=4096)?;
        in_range("--max-passes", self.max_passes, 1..=64)?;
        in_range("--hue-coherence", self.hue_coherence, 0.0..=100.0)?;
        in_range("--class-coherence", self.class_coherence, 0.0..=100.0)?;
        if let Some(tile) = self.quilt_tile {
            in_range("--quilt-tile", tile, 0..=64)?;
        }
        if let BandsWait::Cells(n) = self.bands_wait {
            in_range("--bands-wait", n, 0..=16)?;
        }
        Ok(())
    }

    /// The learned refiner's options, with the CLEVR preset's quilting where the options leave
    /// it to the seed ([`RunSettings::resolve`] gives the seed's own).
    pub fn refiner_options(&self) -> sgam_model::RefinerOptions {
        sgam_model::RefinerOptions {
            sampling: crate::sampling(self.temperature, self.top_k),
            seed: self.seed,
            keep_observed: !self.regenerate_observed,
            cells_per_pass: self.cells_per_pass,
            max_passes: self.max_passes,
            hue_coherence: self.hue_coherence,
            class_coherence: self.class_coherence,
            within_class_temperature: (self.within_temperature > 0.0).then_some(self.within_temperature),
            whole_objects: self.whole_objects,
            quilt_tile: self.quilt_tile.unwrap_or(DEFAULT_QUILT_TILE),
            bands_wait: match self.bands_wait {
                BandsWait::Auto => None,
                BandsWait::Cells(n) => Some(n),
            },
            ..Default::default()
        }
    }
}

/// What happens to pixels the refiner invented before they are fused. None applies to the
/// oracle, whose pixels are the true world's.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct InventedPixelSettings {
    /// Ground prior, metres (0 = off): invented pixels the refiner puts less than this above
    /// the seed frame's ground plane, or anywhere below it, are put back on the plane. The
    /// plane is fitted once in the seed frame (RANSAC); a seed without a dominant plane gets no
    /// prior. Objects (higher than this) keep the refiner's depth.
    #[arg(long, default_value_t = DEFAULT_GROUND_SNAP_M)]
    pub ground_snap: f32,
    /// With the ground prior, metres (0 = off): invented pixels less than this above the plane
    /// go on it even where the surface around them does not face up. Where new ground meets
    /// the ground already seen, the refiner's depth steps by a few centimetres; the tilted
    /// seam fails --ground-snap's up-facing test and fuses into low ridges along the path.
    #[arg(long, default_value_t = DEFAULT_GROUND_FLATTEN_M)]
    pub ground_flatten: f32,
    /// Invented pixels that hang between two surfaces: where the refiner draws an object's
    /// silhouette against the ground behind as a depth ramp, the ramp's pixels float in the air
    /// and fuse into a sloped skirt around the object. `snap` gives each to the nearer surface
    /// or to the ground plane behind (a 9x9 neighbourhood spanning over 5 % of the depth);
    /// `keep` fuses them as drawn.
    #[arg(long, value_enum, default_value_t = DEFAULT_FLYING_PIXELS)]
    pub flying_pixels: FlyingPixels,
    /// Invented pixels in space that an earlier view saw as empty: the map keeps only a band
    /// around surfaces, so a ray through space the seed frame saw empty can come back missing,
    /// and the refiner may put an object there, in front of what the seed saw. `carve` checks
    /// every invented pixel against the seed frame and the step's sources and puts one they
    /// saw through on the ground plane behind it (or drops it); `keep` fuses them as drawn.
    #[arg(long, value_enum, default_value_t = DEFAULT_FREE_SPACE)]
    pub free_space: FreeSpace,
    /// Invented objects fused as solids, up to this deep, metres (0 = off). A completed frame
    /// shows one side of an object; fused alone it is a shell as thick as the truncation band,
    /// which later views see edge-on as a sheet. Invented pixels at least 10 cm above the
    /// ground plane are grouped into objects, and each object is filled behind its surface up
    /// to a back as far behind its front as it is wide (at most this), in space no view has
    /// seen yet, never under the ground. Needs the ground prior's plane. Default: the seed's
    /// preset, 1 for a CLEVR-Infinite seed, off for a Google Earth or RGB-D seed (sized for
    /// CLEVR's objects, in metres).
    #[arg(long, value_name = "M")]
    pub solid_objects: Option<f32>,
    /// Guard rail on invented objects, square metres (0 = off): an object of the completed
    /// frame (pixels 10 cm or more above the ground plane, connected; the part the map already
    /// holds included) with invented pixels and a footprint past this has its invented pixels
    /// put on the ground plane in the observed ground's colour. Invented colour at a frame's
    /// border is re-rendered and continued step after step into a mound many objects wide; this
    /// stops it growing. CLEVR-Infinite's objects: median about 2 m², 90th percentile 4-6 m²
    /// (10 cm cells, as `eval world` counts them). Needs the ground prior's plane. Default:
    /// the seed's preset, 6 for a CLEVR-Infinite seed, off for a Google Earth or RGB-D seed.
    #[arg(long, value_name = "M2")]
    pub max_object_m2: Option<f32>,
    /// Guard rail on invented objects' length, metres (0 = off): an object of the completed
    /// frame with invented pixels whose footprint is longer than this along its principal axis
    /// has its invented pixels put on the ground, as --max-object-m2 does. A streak that each
    /// step continues along the path stays under the area cap for long. CLEVR-Infinite's objects
    /// are at most 2 m across. Default: the seed's preset (off for every seed).
    #[arg(long, value_name = "M")]
    pub max_object_length: Option<f32>,
    /// Invented objects in one colour, this share of the way (0 = off, 1 = all the way): the
    /// refiner draws an object cell by cell and its cells disagree, so an invented object comes
    /// out mottled in several hues, where a CLEVR-Infinite object is one material under smooth
    /// shading. Each object of the completed frame with invented pixels (grouped as
    /// --max-object-m2 groups them) takes one colour by vote: its observed part's (the part
    /// the map already holds) when that is a quarter of it, else the hue most of its pixels
    /// have (grey only with 8 times the votes of any hue); its invented pixels take that colour
    /// at their shading, smoothed over 5 x 5 pixels of the object. Needs the ground prior's
    /// plane. Default: the seed's preset (off for every seed). Measured: docs/MODEL.md,
    /// session 32.
    #[arg(long, value_name = "SHARE")]
    pub object_colour: Option<f32>,
}

impl Default for InventedPixelSettings {
    fn default() -> Self {
        Self {
            ground_snap: DEFAULT_GROUND_SNAP_M,
            ground_flatten: DEFAULT_GROUND_FLATTEN_M,
            flying_pixels: DEFAULT_FLYING_PIXELS,
            free_space: DEFAULT_FREE_SPACE,
            solid_objects: None,
            max_object_m2: None,
            max_object_length: None,
            object_colour: None,
        }
    }
}

impl InventedPixelSettings {
    /// Checks the ground prior's tolerance.
    pub fn validate(&self) -> Result<()> {
        in_range("--ground-snap", self.ground_snap, 0.0..=10.0)?;
        // (with --ground-snap 0 the prior is off, and --ground-flatten with it)
        if self.ground_snap > 0.0 {
            in_range("--ground-flatten", self.ground_flatten, 0.0..=self.ground_snap)?;
        } else {
            in_range("--ground-flatten", self.ground_flatten, 0.0..=10.0)?;
        }
        if let Some(m) = self.solid_objects {
            in_range("--solid-objects", m, 0.0..=10.0)?;
        }
        if let Some(m2) = self.max_object_m2 {
            in_range("--max-object-m2", m2, 0.0..=10_000.0)?;
        }
        if let Some(m) = self.max_object_length {
            in_range("--max-object-length", m, 0.0..=1_000.0)?;
        }
        if let Some(s) = self.object_colour {
            in_range("--object-colour", s, 0.0..=1.0)?;
        }
        Ok(())
    }

    /// `--solid-objects` as given, else the seed's preset, metres (0 = off).
    pub fn solid_objects_m(&self, preset: &crate::Preset) -> f32 {
        self.solid_objects.unwrap_or(preset.solid_objects_m)
    }

    /// `--max-object-m2` as given, else the seed's preset, m² (0 = off).
    pub fn max_object_m2(&self, preset: &crate::Preset) -> f32 {
        self.max_object_m2.unwrap_or(preset.max_object_m2)
    }

    /// `--max-object-length` as given, else the seed's preset, metres (0 = off).
    pub fn max_object_length_m(&self, preset: &crate::Preset) -> f32 {
        self.max_object_length.unwrap_or(preset.max_object_length_m)
    }

    /// `--object-colour` as given, else the seed's preset (0 = off).
    pub fn object_colour(&self, preset: &crate::Preset) -> f32 {
        self.object_colour.unwrap_or(preset.object_colour)
    }
}

/// The map and the source keyframes of each step's guidance. Options left out take the seed's
/// preset ([`crate::CLEVR`], [`crate::GOOGLE_EARTH`]).
#[derive(Debug, Clone, PartialEq, Args)]
pub struct MapSettings {
    /// Voxel size, metres (default: the seed's preset; CLEVR 0.05).
    #[arg(long)]
    pub voxel_size: Option<f32>,
    /// Truncation in voxels (default: the seed's preset; CLEVR 5, i.e. 0.25 m).
    #[arg(long)]
    pub trunc_voxels: Option<f32>,
    /// Depth cut for integration and rendering, metres.
    #[arg(long, default_value_t = DEFAULT_DEPTH_MAX_M)]
    pub depth_max: f32,
    /// Cap on the per-voxel weight (keeps long runs adaptable; default: none).
    #[arg(long)]
    pub weight_cap: Option<f32>,
    /// Source keyframes per step (default: the seed's preset; CLEVR 5).
    #[arg(long)]
    pub k_sources: Option<usize>,
    /// Sources must lie within this distance, metres (default: the seed's preset; CLEVR 1.0).
    #[arg(long)]
    pub source_radius: Option<f32>,
    /// Ablation: no global map; the guidance is warped from the previous frame only.
    #[arg(long)]
    pub no_map: bool,
    /// Bound on the map's memory, MB. Beyond it, the parts of the world far from the camera
    /// (beyond what a step can see, plus a margin) are written to tiles in RUN/tiles and come
    /// back when the camera returns: a run of any length stays within it (the frames are the
    /// same as with no bound). 0 = no bound.
    #[arg(long, default_value_t = crate::tiles::DEFAULT_MAX_MAP_MB)]
    pub max_map_mb: usize,
}

impl Default for MapSettings {
    fn default() -> Self {
        Self {
            voxel_size: None,
            trunc_voxels: None,
            depth_max: DEFAULT_DEPTH_MAX_M,
            weight_cap: None,
            k_sources: None,
            source_radius: None,
            no_map: false,
            max_map_mb: crate::tiles::DEFAULT_MAX_MAP_MB,
        }
    }
}

impl MapSettings {
    /// Checks every number against the map's limits.
    pub fn validate(&self) -> Result<()> {
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
        if self.max_map_mb != 0 {
            in_range("--max-map-mb", self.max_map_mb, 16..=1 << 20)?;
        }
        Ok(())
    }
}

/// Largest depth a 16-bit millimetre PNG holds, metres.
pub const DEPTH_PNG_MAX_M: f32 = sgam_io::DEPTH_PNG_MAX_MM as f32 / 1000.0;

/// What a run writes besides its frames, poses and mesh.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct OutputArgs {
    /// Snapshot (map + keyframe index + cursor) every N steps, for --resume.
    #[arg(long, default_value_t = DEFAULT_SNAPSHOT_EVERY)]
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
    pub no_mp4: bool,
    /// Also write orbit.mp4: one turn around the final mesh.
    #[arg(long)]
    pub orbit_video: bool,
    /// Also write guidance/NNNNN.png per step: the guidance the refiner was given (holes in
    /// magenta), its raw completion, and the frame after the invented-pixel filters, side by side
    /// (to see where an invented object came from).
    #[arg(long)]
    pub guidance_png: bool,
    /// A world whose map went to tiles (--max-map-mb) is always written as mesh tiles; it is also
    /// written as one mesh.ply/mesh.glb when it has at most this many million triangles (0 =
    /// never; about 30 MB of memory per million to build).
    #[arg(long, default_value_t = DEFAULT_SINGLE_MESH_MAX_MTRI)]
    pub single_mesh_max_mtri: f32,
}

/// Default of `--single-mesh-max-mtri`: 4 million triangles (about 0.25 GB to build and write).
/// A 100,000-step world (15.3 million) built as one mesh took its run's peak memory from about
/// 0.53 GB to 1.38 GB; a 10,000-step one (2.0 million) stays one mesh.
pub const DEFAULT_SINGLE_MESH_MAX_MTRI: f32 = 4.0;

impl Default for OutputArgs {
    fn default() -> Self {
        Self {
            snapshot_every: DEFAULT_SNAPSHOT_EVERY,
            mesh_every: 0,
            depth_png: false,
            no_video: false,
            no_mp4: false,
            orbit_video: false,
            guidance_png: false,
            single_mesh_max_mtri: DEFAULT_SINGLE_MESH_MAX_MTRI,
        }
    }
}

impl OutputArgs {
    /// Checks the intervals.
    pub fn validate(&self) -> Result<()> {
        in_range("--snapshot-every", self.snapshot_every, 1..=MAX_STEPS)?;
        in_range("--mesh-every", self.mesh_every, 0..=MAX_STEPS)?;
        in_range("--single-mesh-max-mtri", self.single_mesh_max_mtri, 0.0..=1000.0)?;
        Ok(())
    }

    /// The stored form.
    pub fn settings(&self) -> OutputSettings {
        OutputSettings {
            snapshot_every: self.snapshot_every,
            mesh_every: self.mesh_every,
            depth_png: self.depth_png,
            video: !self.no_video,
            mp4: !self.no_mp4,
            orbit_video: self.orbit_video,
            guidance_png: self.guidance_png,
            single_mesh_max_triangles: (f64::from(self.single_mesh_max_mtri) * 1e6).round() as u64,
        }
    }
}

/// Everything that decides what a run grows and writes, as stated by the user: the seed, the
/// path and its length, the refiner and its sampling, the invented-pixel policy, the map and
/// the outputs. `sgam generate` flattens it whole; [`RunSettings::resolve`] gives the run.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct RunSettings {
    /// The seed frame.
    #[command(flatten)]
    pub seed: SeedSettings,
    /// The camera path.
    #[command(flatten)]
    pub path: PathSettings,
    /// Number of generation steps (poses after the seed).
    #[arg(long, default_value_t = DEFAULT_STEPS)]
    pub steps: usize,
    /// The refiner.
    #[command(flatten)]
    pub refiner: RefinerSettings,
    /// Its sampling.
    #[command(flatten)]
    pub sampling: SamplingSettings,
    /// The invented-pixel policy.
    #[command(flatten)]
    pub invented: InventedPixelSettings,
    /// The map and sources.
    #[command(flatten)]
    pub map: MapSettings,
    /// The outputs.
    #[command(flatten)]
    pub outputs: OutputArgs,
}

impl Default for RunSettings {
    fn default() -> Self {
        Self::clevr(HELD_OUT_SEED_BASE)
    }
}

impl RunSettings {
    /// The default run from synthetic scene `scene`: the bundled model with the default
    /// sampling along the zig-zag, [`DEFAULT_STEPS`] steps.
    pub fn clevr(scene: u64) -> Self {
        Self {
            seed: SeedSettings::synthetic(scene),
            path: PathSettings::default(),
            steps: DEFAULT_STEPS,
            refiner: RefinerSettings::default(),
            sampling: SamplingSettings::default(),
            invented: InventedPixelSettings::default(),
            map: MapSettings::default(),
            outputs: OutputArgs::default(),
        }
    }

    /// Checks every option and the combinations that would otherwise be silently ignored;
    /// errors name the option and the accepted range.
    pub fn validate(&self) -> Result<()> {
        self.seed.validate()?;
        self.path.validate()?;
        in_range("--steps", self.steps, 1..=MAX_STEPS)?;
        self.refiner.validate()?;
        self.sampling.validate()?;
        self.invented.validate()?;
        self.map.validate()?;
        self.outputs.validate()?;
        if self.outputs.depth_png && self.map.depth_max > DEPTH_PNG_MAX_M {
            config_error!(
                "--depth-png stores millimetres in 16 bits (at most {DEPTH_PNG_MAX_M} m) but --depth-max is {} m; \
                 lower --depth-max or leave out --depth-png (depth/NNNNN.npy holds every depth)",
                self.map.depth_max
            );
        }
        Ok(())
    }

    /// The refiner these settings name: `--no-refine` passes the guidance through, the null
    /// stand-in fills holes by push-pull, the model samples as [`SamplingSettings`] says.
    pub fn refiner_spec(&self) -> RefinerSpec {
        match self.refiner.effective() {
            RefinerKind::Auto | RefinerKind::Model => RefinerSpec::Model {
                model: self.refiner.model.clone(),
                options: self.sampling.refiner_options(),
                bank: self.refiner.bank.clone(),
                adapt_s: self.refiner.adapt,
            },
            RefinerKind::Null => RefinerSpec::Null { fill: !self.refiner.no_refine },
            RefinerKind::Oracle => RefinerSpec::Oracle,
        }
    }

    /// The run these settings describe, every default applied: the seed's preset (CLEVR, Google
    /// Earth or RGB-D) fills the map, path and invented-object options left out.
    pub fn resolve(&self) -> Result<RunConfig> {
        let seed = self.seed.spec()?;
        let preset = seed.preset();
        let uses_model = matches!(self.refiner.effective(), RefinerKind::Auto | RefinerKind::Model);
        let clevr_seed = matches!(seed, crate::SeedSpec::Synthetic { .. } | crate::SeedSpec::ClevrTemplate { .. });
        if uses_model && self.refiner.bank.is_synthetic() && !clevr_seed {
            config_error!(
                "--bank {}: this code bank holds frames of the synthetic CLEVR-Infinite world, and this seed is not \
                 one (leave out --bank, or --bank seed to quilt holes from the seed itself)",
                self.refiner.bank
            );
        }
        let trajectory = self.path.spec(self.steps, &seed, preset.step_m)?;
        let m = &self.map;
        // the oracle is the true world: its pixels are never changed
        let invents = self.refiner.effective() != RefinerKind::Oracle;
        let p = &self.invented;
        let refiner = match self.refiner_spec() {
            RefinerSpec::Model { model, mut options, bank, adapt_s } => {
                let bank = bank.resolve_for(&seed);
                // quilting the seed's pixels: its preset's tiles and bands (a preset that waits
                // as long as the refiner's own auto leaves it to the refiner, so such a run's
                // config is the one it had before presets said how to quilt)
                options.quilt_tile = self.sampling.quilt_tile.unwrap_or(preset.quilt_tile);
                let own_wait = preset.quilt_bands_wait != sgam_model::refiner::DEFAULT_BANDS_WAIT;
                if bank == BankSpec::Seed && self.sampling.bands_wait == BandsWait::Auto && own_wait {
                    options.bands_wait = Some(preset.quilt_bands_wait);
                }
                RefinerSpec::Model { model, options, bank, adapt_s }
            }
            other => other,
        };
        Ok(RunConfig {
            version: RUN_CONFIG_VERSION,
            seed,
            trajectory,
            steps: self.steps,
            refiner,
            map: sgam_map::TsdfConfig {
                voxel_size_m: m.voxel_size.unwrap_or(preset.voxel_size_m),
                trunc_voxels: m.trunc_voxels.unwrap_or(preset.trunc_voxels),
                depth_min_m: 0.05,
                depth_max_m: m.depth_max,
                weight_cap: m.weight_cap,
                weight_threshold: 1.0,
            },
            k_sources: m.k_sources.unwrap_or(preset.k_sources),
            source_radius_m: m.source_radius.unwrap_or(preset.source_radius_m),
            no_map: m.no_map,
            run_seed: self.sampling.seed,
            ground_snap_m: (invents && p.ground_snap > 0.0).then_some(p.ground_snap),
            ground_flatten_m: if invents && p.ground_snap > 0.0 { p.ground_flatten } else { 0.0 },
            snap_flying_pixels: invents && p.flying_pixels == FlyingPixels::Snap,
            carve_free_space: invents && p.free_space == FreeSpace::Carve,
            solid_max_m: if invents { p.solid_objects_m(&preset) } else { 0.0 },
            max_object_m2: if invents { p.max_object_m2(&preset) } else { 0.0 },
            max_object_length_m: if invents { p.max_object_length_m(&preset) } else { 0.0 },
            object_colour: if invents { p.object_colour(&preset) } else { 0.0 },
            outputs: self.outputs.settings(),
            max_map_mb: m.max_map_mb,
        })
    }
}

impl RunConfig {
    /// The default run from synthetic scene `scene` ([`RunSettings::clevr`], resolved).
    pub fn clevr(scene: u64) -> Self {
        match RunSettings::clevr(scene).resolve() {
            Ok(c) => c,
            // a synthetic seed along the zig-zag with every default: nothing to refuse
            Err(e) => unreachable!("the default run resolves: {e}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        run: RunSettings,
    }

    #[test]
    fn bands_wait_is_auto_or_a_number_of_cells_and_reaches_the_refiner() {
        let options = |args: &[&str]| {
            let mut v = vec!["sgam"];
            v.extend_from_slice(args);
            let s = Cli::try_parse_from(v).map_err(|e| e.to_string())?.run.sampling;
            s.validate().map_err(|e| e.to_string())?;
            Ok::<_, String>(s.refiner_options().bands_wait)
        };
        assert_eq!(options(&[]), Ok(None), "auto: the refiner picks per completion");
        assert_eq!(options(&["--bands-wait", "auto"]), Ok(None));
        assert_eq!(options(&["--bands-wait", "0"]), Ok(Some(0)));
        assert_eq!(options(&["--bands-wait", "5"]), Ok(Some(5)));
        for bad in ["17", "x", "2.5"] {
            let e = options(&["--bands-wait", bad]).expect_err(bad);
            assert!(e.contains("--bands-wait"), "{bad}: {e}");
        }
    }

    #[test]
    fn every_groups_default_is_the_empty_command_line() {
        let parsed = Cli::parse_from(["sgam"]).run;
        assert_eq!(parsed.seed, SeedSettings::default());
        assert_eq!(parsed.path, PathSettings::default());
        assert_eq!(parsed.refiner, RefinerSettings::default());
        assert_eq!(parsed.sampling, SamplingSettings::default());
        assert_eq!(parsed.invented, InventedPixelSettings::default());
        assert_eq!(parsed.map, MapSettings::default());
        assert_eq!(parsed.outputs, OutputArgs::default());
        assert_eq!(parsed, RunSettings::default());
        // and a changed option shows: the comparison is not vacuous
        let hot = Cli::parse_from(["sgam", "--temperature", "2"]).run;
        assert_ne!(hot, RunSettings::default());
        assert_eq!(hot.sampling.temperature, 2.0);
    }

    #[test]
    fn the_default_run_is_the_clevr_preset_with_every_invented_pixel_filter() {
        let c = RunConfig::clevr(7);
        c.validate().unwrap();
        assert_eq!(c.seed, SeedSpec::Synthetic { scene: 7, res: 256 });
        assert_eq!(c.trajectory, TrajectorySpec::Zigzag { side: 30, step_m: 0.408 });
        assert_eq!((c.map.voxel_size_m, c.map.trunc_voxels, c.k_sources), (0.05, 5.0, 5));
        assert_eq!(c.map, crate::clevr_generator_config(0).tsdf, "generation and training share the map");
        assert_eq!((c.ground_snap_m, c.snap_flying_pixels, c.carve_free_space), (Some(1.0), true, true));
        assert_eq!(c.solid_max_m, crate::CLEVR.solid_objects_m);
        assert_eq!(c.generator_config().solid_max_m, 1.0, "CLEVR's objects are fused as solids");
        assert_eq!(c.generator_config().max_object_m2, 6.0, "and capped at 6 m2");
        let RefinerSpec::Model { model: None, options, bank: BankSpec::None, adapt_s: 0.0 } = c.refiner else {
            panic!("{:?}", c.refiner)
        };
        assert_eq!((options.cells_per_pass, options.within_class_temperature), (8, Some(0.6)));
        assert_eq!(options.max_passes, 4);
        assert!(options.keep_observed);
        // the oracle's pixels are never changed, whatever the policy says
        let mut oracle = RunSettings::clevr(7);
        oracle.refiner = RefinerSettings::kind(RefinerKind::Oracle);
        oracle.invented.solid_objects = Some(1.5);
        oracle.invented.max_object_m2 = Some(6.0);
        oracle.invented.object_colour = Some(1.0);
        let c = oracle.resolve().unwrap();
        assert_eq!((c.ground_snap_m, c.snap_flying_pixels, c.carve_free_space), (None, false, false));
        assert_eq!(c.solid_max_m, 0.0, "the oracle's objects are the true world's");
        assert_eq!(c.max_object_m2, 0.0, "the oracle's objects are never capped");
        assert_eq!(c.max_object_length_m, 0.0);
        assert_eq!(c.object_colour, 0.0, "the oracle's colours are the true world's");
        assert_eq!(RunSettings::clevr(7).resolve().unwrap().object_colour, crate::CLEVR.object_colour);
        // a value given reaches the model's generator, over the preset
        let mut capped = RunSettings::clevr(7);
        capped.invented.max_object_m2 = Some(4.5);
        capped.invented.solid_objects = Some(0.0);
        capped.invented.max_object_length = Some(3.0);
        capped.invented.object_colour = Some(0.75);
        let c = capped.resolve().unwrap().generator_config();
        assert_eq!((c.max_object_m2, c.solid_max_m, c.max_object_length_m), (4.5, 0.0, 3.0));
        assert_eq!(c.object_colour, 0.75);
        // `keep` turns each filter off for the model
        let mut keep = RunSettings::clevr(7);
        keep.invented = InventedPixelSettings {
            ground_snap: 0.0,
            ground_flatten: 0.0,
            flying_pixels: FlyingPixels::Keep,
            free_space: FreeSpace::Keep,
            solid_objects: Some(0.0),
            max_object_m2: Some(0.0),
            max_object_length: Some(0.0),
            object_colour: Some(0.0),
        };
        let c = keep.resolve().unwrap();
        assert_eq!((c.ground_snap_m, c.snap_flying_pixels, c.carve_free_space), (None, false, false));
        assert_eq!((c.solid_max_m, c.max_object_m2), (0.0, 0.0));
        // --ground-snap 0 alone turns the prior off, its flattening with it
        let mut off = RunSettings::clevr(7);
        off.invented.ground_snap = 0.0;
        let c = off.resolve().unwrap();
        assert_eq!((c.ground_snap_m, c.ground_flatten_m), (None, 0.0));
        off.validate().unwrap();
        // with the prior on, flattening higher than it is refused by name
        let mut high = RunSettings::clevr(7);
        high.invented.ground_flatten = 1.5;
        assert!(high.validate().unwrap_err().to_string().contains("--ground-flatten"));
    }

    #[test]
    fn a_google_earth_seed_takes_its_preset_and_no_refine_fills_nothing() {
        let mut ge = RunSettings::default();
        ge.seed.seed_google_earth = Some("seed0".into());
        let c = ge.resolve().unwrap();
        assert_eq!((c.map.voxel_size_m, c.k_sources, c.source_radius_m), (0.01, 3, 0.3));
        // CLEVR's solids and size cap are in metres: off for a seed whose units are not
        assert_eq!((c.solid_max_m, c.max_object_m2), (0.0, 0.0));
        let mut rgbd = RunSettings::default();
        rgbd.seed.seed_rgb = Some("a.png".into());
        rgbd.seed.seed_depth = Some("a.npy".into());
        rgbd.seed.intrinsics = Some([30.0, 30.0, 16.0, 16.0]);
        assert_eq!(rgbd.seed.spec().unwrap().preset(), crate::RGBD);
        assert_eq!((crate::RGBD.solid_objects_m, crate::RGBD.max_object_m2), (0.0, 0.0));
        assert_eq!(crate::RGBD.voxel_size_m, crate::CLEVR.voxel_size_m);
        // the authors' Google Earth path: a straight line, 0.059 units a step
        assert_eq!(c.trajectory, TrajectorySpec::Line { step_m: GOOGLE_EARTH_LINE_STEP });
        ge.path.trajectory = TrajectoryKind::Zigzag;
        assert_eq!(ge.resolve().unwrap().trajectory, TrajectorySpec::Zigzag { side: 30, step_m: 0.02 });
        ge.path.trajectory = TrajectoryKind::Auto;
        ge.refiner.no_refine = true;
        assert_eq!(ge.resolve().unwrap().refiner, RefinerSpec::Null { fill: false });
        // an option given by the user wins over the preset
        ge.map.voxel_size = Some(0.02);
        assert_eq!(ge.resolve().unwrap().map.voxel_size_m, 0.02);
    }

    #[test]
    fn the_bank_is_the_seeds_own_outside_the_synthetic_world_and_none_in_it() {
        let bank = |s: &RunSettings| match s.resolve().unwrap().refiner {
            RefinerSpec::Model { bank, .. } => bank,
            other => panic!("{other:?}"),
        };
        let mut s = RunSettings::default();
        assert_eq!(bank(&s), BankSpec::None, "the bundled model's context draws CLEVR's holes");
        s.refiner.model = Some("other.safetensors".into());
        assert_eq!(bank(&s), BankSpec::None);
        s.refiner.bank = BankSpec::Bundled;
        assert_eq!(bank(&s), BankSpec::Bundled, "named, it is used (and checked when loaded)");
        // a seed from outside the synthetic world is quilted from itself, by any model
        for spec in [
            crate::SeedSpec::GoogleEarth { dir: "ge/seed0".into() },
            crate::SeedSpec::Rgbd { rgb: "a.png".into(), depth: "a.npy".into(), intrinsics: [30.0, 30.0, 16.0, 16.0] },
        ] {
            assert_eq!(BankSpec::Auto.resolve_for(&spec), BankSpec::Seed);
            assert_eq!(BankSpec::None.resolve_for(&spec), BankSpec::None, "--bank none draws with the model");
        }
        let template = crate::SeedSpec::ClevrTemplate { dir: "t".into() };
        assert_eq!(BankSpec::Auto.resolve_for(&template), BankSpec::None);
        assert_eq!(BankSpec::Bundled.resolve_for(&template), BankSpec::Bundled);
    }

    #[test]
    fn the_default_path_follows_the_seed() {
        assert_eq!(
            RunSettings::default().resolve().unwrap().trajectory,
            TrajectorySpec::Zigzag { side: 30, step_m: 0.408 }
        );
        // an RGB-D seed: a line, each step 5 % of its median valid depth (zeros are not depth)
        let dir = tempfile::tempdir().unwrap();
        let (rgb, depth) = (dir.path().join("rgb.png"), dir.path().join("d.npy"));
        sgam_io::write_rgb_png(&rgb, &sgam_core::Image::filled(32, 32, [0.5f32; 3])).unwrap();
        let mut d = sgam_core::Image::filled(32, 32, 3.0f32);
        for v in d.data.iter_mut().take(200) {
            *v = 1.0;
        }
        for v in d.data.iter_mut().skip(900) {
            *v = 0.0;
        }
        sgam_io::write_npy_f32(&depth, &d).unwrap();
        let mut user = RunSettings::default();
        (user.seed.seed_rgb, user.seed.seed_depth) = (Some(rgb), Some(depth));
        user.seed.intrinsics = Some([30.0, 30.0, 16.0, 16.0]);
        let TrajectorySpec::Line { step_m } = user.resolve().unwrap().trajectory else { panic!("not a line") };
        assert!((step_m - 3.0 * RGBD_STEP_OF_MEDIAN_DEPTH).abs() < 1e-6, "{step_m}");
        user.path.step = Some(0.25);
        assert_eq!(user.resolve().unwrap().trajectory, TrajectorySpec::Line { step_m: 0.25 });
        // the seed's pixels are quilted as tiles unless told otherwise
        let tile = |s: &RunSettings| match s.resolve().unwrap().refiner {
            RefinerSpec::Model { options, .. } => options.quilt_tile,
            other => panic!("{other:?}"),
        };
        assert_eq!(tile(&user), DEFAULT_QUILT_TILE);
        user.sampling.quilt_tile = Some(0);
        assert_eq!(tile(&user), 0, "given, it is used");
        user.sampling.quilt_tile = Some(65);
        assert!(user.validate().unwrap_err().to_string().contains("--quilt-tile"));
    }

    #[test]
    fn quilting_a_seeds_pixels_follows_its_preset() {
        let quilting = |s: &RunSettings| match s.resolve().unwrap().refiner {
            RefinerSpec::Model { options, .. } => (options.quilt_tile, options.bands_wait),
            other => panic!("{other:?}"),
        };
        let mut ge = RunSettings::default();
        ge.seed.seed_google_earth = Some("ge/seed0".into());
        assert_eq!(quilting(&ge), (12, Some(8)), "Google Earth: 12-cell tiles, bands wait until 8 cells deep");
        // given, the options win
        ge.sampling.quilt_tile = Some(4);
        ge.sampling.bands_wait = BandsWait::Cells(2);
        assert_eq!(quilting(&ge), (4, Some(2)));
        // the model's own draws (--bank none) keep the refiner's auto: no band waits for them
        ge.sampling.bands_wait = BandsWait::Auto;
        ge.refiner.bank = BankSpec::None;
        assert_eq!(quilting(&ge).1, None);
        // an RGB-D seed quilts in 8-cell tiles and leaves the wait to the refiner (3 cells)
        let dir = tempfile::tempdir().unwrap();
        let (rgb, depth) = (dir.path().join("rgb.png"), dir.path().join("d.npy"));
        sgam_io::write_rgb_png(&rgb, &sgam_core::Image::filled(32, 32, [0.5f32; 3])).unwrap();
        sgam_io::write_npy_f32(&depth, &sgam_core::Image::filled(32, 32, 2.0f32)).unwrap();
        let mut user = RunSettings::default();
        (user.seed.seed_rgb, user.seed.seed_depth) = (Some(rgb), Some(depth));
        user.seed.intrinsics = Some([30.0, 30.0, 16.0, 16.0]);
        assert_eq!(quilting(&user), (8, None));
        assert_eq!(sgam_model::refiner::DEFAULT_BANDS_WAIT, 3);
        // a CLEVR-Infinite seed keeps the refiner's auto too (3 cells with any bank, 0 without)
        let mut clevr = RunSettings::default();
        assert_eq!(quilting(&clevr), (DEFAULT_QUILT_TILE, None));
        for bank in [BankSpec::Bundled, BankSpec::Seed] {
            clevr.refiner.bank = bank;
            assert_eq!(quilting(&clevr).1, None);
        }
    }

    #[test]
    fn options_that_cannot_apply_are_refused_naming_them() {
        let err = |s: RunSettings| s.validate().unwrap_err().to_string();
        let s = RunSettings {
            refiner: RefinerSettings {
                refiner: RefinerKind::Null,
                model: Some("m.safetensors".into()),
                no_refine: false,
                bank: BankSpec::None,
                adapt: 0.0,
            },
            ..RunSettings::default()
        };
        assert!(err(s).contains("--model"));
        let mut s = RunSettings::default();
        s.path.trajectory_file = Some("poses.txt".into());
        assert!(err(s).contains("--trajectory-file"));
        for bad in [-1.0, f32::NAN, 11.0] {
            let mut s = RunSettings::default();
            s.invented.solid_objects = Some(bad);
            assert!(err(s).contains("--solid-objects"), "{bad}");
            let mut s = RunSettings::default();
            s.invented.max_object_m2 = Some(bad * 1000.0);
            assert!(err(s).contains("--max-object-m2"), "{bad}");
            let mut s = RunSettings::default();
            s.invented.max_object_length = Some(bad * 100.0);
            assert!(err(s).contains("--max-object-length"), "{bad}");
            let mut s = RunSettings::default();
            s.invented.object_colour = Some(bad / 5.0);
            assert!(err(s).contains("--object-colour"), "{bad}");
        }
        let mut s = RunSettings::default();
        s.seed.seed_template = Some("a".into());
        s.seed.seed_google_earth = Some("b".into());
        assert!(err(s).contains("different seeds"));
        let mut s = RunSettings::default();
        s.outputs.depth_png = true;
        s.map.depth_max = 100.0;
        assert!(err(s).contains("--depth-png"));
        let mut s = RunSettings::default();
        s.sampling.cells_per_pass = 0;
        assert!(err(s).contains("--cells-per-pass 0 is out of range"));
        for bad in [0, 65] {
            let mut s = RunSettings::default();
            s.sampling.max_passes = bad;
            assert!(err(s).contains(&format!("--max-passes {bad} is out of range")), "{bad}");
        }
        let mut s = RunSettings::default();
        s.sampling.max_passes = 12;
        assert_eq!(s.sampling.refiner_options().max_passes, 12, "--max-passes reaches the refiner");
        assert_eq!(s.sampling.refiner_options().class_coherence, 0.0, "--class-coherence is off by default");
        s.sampling.class_coherence = 1.5;
        assert_eq!(s.sampling.refiner_options().class_coherence, 1.5, "--class-coherence reaches the refiner");
        s.sampling.class_coherence = -1.0;
        assert!(err(s).contains("--class-coherence"));
        for bad in [-1.0, f32::NAN, 4000.0] {
            let mut s = RunSettings::default();
            s.refiner.adapt = bad;
            assert!(err(s).contains("--adapt"), "{bad}");
        }
    }
}
