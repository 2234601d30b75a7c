//! `sgam synth`: render the procedural CLEVR-Infinite dataset in the SGAM authors' layout.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use sgam_io::{ClevrFrameMeta, DepthType};
use sgam_synth::{dataset_cameras, RenderConfig, Renderer, Scene, SceneConfig, CAMERA_FOV_X_RAD};

use crate::progress;

/// Arguments of `sgam synth`.
#[derive(Debug, Args)]
#[command(
    after_help = "Example (the paper's 72/8 split, 2,500 frames per scene):\n  sgam synth --scenes 80 --split 72/8 --res 256 --grid 50 --seed 0 --out clevr-infinite\n\nEach scene folder holds transforms.json (Blender camera-to-world, camera_angle_x, grid_i/grid_j,\ndepth_type), im_NNNNN.png, dm_NNNNN.npy and scene.json (the object list). Finished scenes are\nskipped, so an interrupted run continues where it stopped."
)]
pub struct SynthArgs {
    /// Output folder (gets train/ and test/ sub-folders).
    #[arg(long)]
    pub out: PathBuf,
    /// Number of scenes.
    #[arg(long, default_value_t = 80)]
    pub scenes: usize,
    /// Train/test split as TRAIN/TEST scene counts (must add up to --scenes).
    #[arg(long, default_value = "72/8")]
    pub split: String,
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

fn parse_split(split: &str, scenes: usize) -> Result<(usize, usize)> {
    let (a, b) = split.split_once('/').with_context(|| format!("--split '{split}' is not TRAIN/TEST"))?;
    let (a, b): (usize, usize) =
        (a.trim().parse().context("--split train count")?, b.trim().parse().context("--split test count")?);
    if a + b != scenes {
        bail!("--split {a}/{b} adds up to {} but --scenes is {scenes}", a + b);
    }
    Ok((a, b))
}

/// Renders one scene into `dir` (skipped when `transforms.json` already exists).
fn render_scene(dir: &Path, seed: u64, args: &SynthArgs, pb: &indicatif::ProgressBar) -> Result<bool> {
    if dir.join("transforms.json").exists() {
        return Ok(false);
    }
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
    let (n_train, _) = parse_split(&args.split, args.scenes)?;
    if args.grid == 0 || args.res < 8 {
        bail!("--grid must be >= 1 and --res >= 8");
    }
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
