//! `sgam synth`: render the procedural CLEVR-Infinite dataset in the SGAM authors' layout.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use sgam_io::{ClevrFrameMeta, DepthType};
use sgam_synth::{dataset_cameras, RenderConfig, Renderer, Scene, SceneConfig, CAMERA_FOV_X_RAD};

use crate::guard::in_range;
use crate::progress;

/// Arguments of `sgam synth`.
#[derive(Debug, Args)]
#[command(
    after_help = "Example (the paper's 72/8 split, 2,500 frames per scene):\n  sgam synth --scenes 80 --split 72/8 --res 256 --grid 50 --seed 0 --out clevr-infinite\n\nEach scene folder holds transforms.json (Blender camera-to-world, camera_angle_x, grid_i/grid_j,\ndepth_type), im_NNNNN.png, dm_NNNNN.npy and scene.json (the object list). OUT/synth.json records\nthe render options: an interrupted run continues where it stopped (finished scenes are skipped)\nwhen given the same options, and refuses other ones."
)]
pub struct SynthArgs {
    /// Output folder (gets train/ and test/ sub-folders).
    #[arg(long)]
    pub out: PathBuf,
    /// Number of scenes.
    #[arg(long, default_value_t = 80)]
    pub scenes: usize,
    /// Train/test split as TRAIN/TEST scene counts (must add up to --scenes; default: a tenth
    /// of the scenes, rounded down, for test, as the paper's 72/8).
    #[arg(long)]
    pub split: Option<String>,
    /// Image resolution (square).
    #[arg(long, default_value_t = 256)]
    pub res: u32,
    /// Cameras per grid side (grid x grid frames per scene over x, y in [-20, 20]).
    #[arg(long, default_value_t = 50)]
    pub grid: usize,
    /// Base seed: scene k uses seed + k.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Colour samples per pixel.
    #[arg(long, default_value_t = 4)]
    pub spp: u32,
    /// Objects per scene (the paper: 882).
    #[arg(long, default_value_t = 882)]
    pub objects: usize,
    /// Store planar depth in dm_*.npy instead of the authors' ray length.
    #[arg(long)]
    pub planar_depth: bool,
}

/// Most scenes, objects per scene, grid side, resolution and samples per pixel `sgam synth`
/// accepts (memory stays bounded: one frame at a time, objects in RAM).
const MAX_SCENES: usize = 100_000;
const MAX_OBJECTS: usize = 100_000;
const MAX_GRID: usize = 1000;
const MAX_RES: u32 = 4096;
const MAX_SPP: u32 = 1024;

/// The options that decide what a scene's files hold, recorded as `OUT/synth.json`: an
/// interrupted run continues only with the same ones (so no folder mixes two renderings).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct RenderOptions {
    res: u32,
    grid: usize,
    spp: u32,
    objects: usize,
    planar_depth: bool,
    seed: u64,
}

impl SynthArgs {
    /// Checks every option (in range, memory bounded); returns the train/test split. Errors name
    /// the option and the accepted range.
    fn validate(&self) -> Result<(usize, usize)> {
        in_range("--scenes", self.scenes, 1..=MAX_SCENES)?;
        in_range("--res", self.res, 8..=MAX_RES)?;
        in_range("--grid", self.grid, 1..=MAX_GRID)?;
        in_range("--spp", self.spp, 1..=MAX_SPP)?;
        in_range("--objects", self.objects, 0..=MAX_OBJECTS)?;
        match &self.split {
            Some(split) => parse_split(split, self.scenes),
            None => Ok((self.scenes - self.scenes / 10, self.scenes / 10)),
        }
    }

    fn render_options(&self) -> RenderOptions {
        RenderOptions {
            res: self.res,
            grid: self.grid,
            spp: self.spp,
            objects: self.objects,
            planar_depth: self.planar_depth,
            seed: self.seed,
        }
    }
}

/// Records the render options in `OUT/synth.json`, or checks them against the recorded ones:
/// scenes rendered with other options are never continued or counted as done.
fn claim_output(out: &Path, options: &RenderOptions) -> Result<()> {
    let path = out.join("synth.json");
    if path.exists() {
        let bytes = std::fs::read(&path).with_context(|| format!("{}: cannot read", path.display()))?;
        let stored: RenderOptions = serde_json::from_slice(&bytes)
            .with_context(|| format!("{}: not the record of an sgam synth run", path.display()))?;
        if stored != *options {
            let json = |o: &RenderOptions| serde_json::to_string(o).unwrap_or_default();
            bail!(
                "{} holds scenes rendered with other options ({} records {}; asked {}); use those options, or \
                 another --out",
                out.display(),
                path.display(),
                json(&stored),
                json(options)
            );
        }
        return Ok(());
    }
    if ["train", "test"].iter().any(|s| out.join(s).exists()) {
        bail!(
            "{} holds scenes but no synth.json recording their options (an older sgam, or another tool), so they \
             cannot be continued safely; render into another --out",
            out.display()
        );
    }
    let json = serde_json::to_vec_pretty(options)?;
    sgam_io::write_atomic(&path, |w| std::io::Write::write_all(w, &json))?;
    Ok(())
}

/// True when `dir` holds a finished scene: a `transforms.json` that reads, with every camera of
/// the grid and the asked depth type (an empty or cut file is not finished), and every frame's
/// colour and depth files (a deleted frame is rendered again).
fn scene_finished(dir: &Path, args: &SynthArgs) -> bool {
    let want = if args.planar_depth { DepthType::Planar } else { DepthType::RayLength };
    sgam_io::read_clevr_transforms(&dir.join("transforms.json"))
        .is_ok_and(|t| t.frames.len() == args.grid * args.grid && t.effective_depth_type() == want)
        && dataset_cameras(args.grid, args.res).iter().all(|c| {
            let i = c.index as u32;
            sgam_io::clevr_colour_path(dir, i).exists() && sgam_io::clevr_depth_path(dir, i).exists()
        })
}

fn parse_split(split: &str, scenes: usize) -> Result<(usize, usize)> {
    let (a, b) = split.split_once('/').with_context(|| format!("--split '{split}' is not TRAIN/TEST"))?;
    let (a, b): (usize, usize) = (
        a.trim().parse().with_context(|| format!("--split '{split}': train count"))?,
        b.trim().parse().with_context(|| format!("--split '{split}': test count"))?,
    );
    if a.checked_add(b) != Some(scenes) {
        bail!("--split {a}/{b} does not add up to --scenes {scenes}");
    }
    Ok((a, b))
}

/// Renders one scene into `dir` (skipped when it is finished, see [`scene_finished`]).
fn render_scene(dir: &Path, seed: u64, args: &SynthArgs, pb: &indicatif::ProgressBar) -> Result<bool> {
    if scene_finished(dir, args) {
        return Ok(false);
    }
    crate::guard::remove_stale_temp_files(dir, &[])?;
    let config = SceneConfig { object_count: args.objects, ..SceneConfig::default() };
    let scene = Scene::generate(seed, &config);
    let renderer = Renderer::new(&scene);
    let render = RenderConfig { samples_per_pixel: args.spp.max(1), ..RenderConfig::default() };
    let depth_type = if args.planar_depth { DepthType::Planar } else { DepthType::RayLength };
    let cameras = dataset_cameras(args.grid, args.res);
    let mut metas = Vec::with_capacity(cameras.len());
    for cam in &cameras {
        let index = cam.index as u32;
        // a frame whose files both exist was finished by an earlier run (writes are atomic)
        if !(sgam_io::clevr_colour_path(dir, index).exists() && sgam_io::clevr_depth_path(dir, index).exists()) {
            let f = renderer.render(&cam.camera, &render);
            sgam_io::write_clevr_frame(dir, index, &f.frame, &cam.camera.intrinsics, depth_type)?;
        }
        metas.push(ClevrFrameMeta {
            index,
            grid_i: cam.grid_i_m,
            grid_j: cam.grid_j_m,
            world_from_camera: cam.camera.world_from_camera,
        });
        pb.inc(1);
    }
    let scene_json = serde_json::to_vec_pretty(&scene)?;
    sgam_io::write_atomic(&dir.join("scene.json"), |w| std::io::Write::write_all(w, &scene_json))?;
    // transforms.json last: its presence marks the scene finished
    sgam_io::write_clevr_transforms(dir, CAMERA_FOV_X_RAD as f64, &metas, depth_type)?;
    Ok(true)
}

/// Runs `sgam synth`.
pub fn run(args: SynthArgs) -> Result<()> {
    let (n_train, _) = args.validate()?;
    let _lock = crate::guard::RunLock::acquire(&args.out)?;
    claim_output(&args.out, &args.render_options())?;
    let per_scene = (args.grid * args.grid) as u64;
    let pb = progress::bar(per_scene * args.scenes as u64, "rendering");
    let start = Instant::now();
    let (mut rendered, mut skipped) = (0usize, 0usize);
    for k in 0..args.scenes {
        let split = if k < n_train { "train" } else { "test" };
        let seed = args.seed + k as u64;
        let dir = args.out.join(split).join(format!("scene_{seed:06}"));
        pb.set_message(format!("{split}/scene_{seed:06}"));
        if render_scene(&dir, seed, &args, &pb)? {
            rendered += 1;
        } else {
            skipped += 1;
            pb.inc(per_scene);
        }
    }
    pb.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    let frames = rendered as f64 * per_scene as f64;
    eprintln!(
        "{rendered} scenes rendered ({skipped} already finished) in {secs:.1} s ({:.1} frames/s) -> {}",
        frames / secs.max(1e-9),
        args.out.display()
    );
    Ok(())
}
