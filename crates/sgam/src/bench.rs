//! `sgam bench`: time one hot path on a built-in synthetic scene; print one JSON line.

use std::time::Instant;

use anyhow::{bail, Result};
use clap::{Args, ValueEnum};
use serde_json::json;
use sgam_core::{trajectory, Camera, RgbdFrame};
use sgam_map::{warp_colour, SourceView, TsdfConfig, TsdfMap, WarpConfig};
use sgam_synth::{blender_camera, dataset_intrinsics, RenderConfig, Renderer, Scene, SceneConfig};

/// What to time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Subject {
    /// TSDF integration of one new frame into a map of its neighbours.
    Integrate,
    /// Incremental re-meshing of the blocks one frame changed.
    Mesh,
    /// Rasterizing the map's mesh at a new camera (guidance depth).
    Render,
    /// TSDF ray-cast at a new camera (alternative guidance depth).
    RayCast,
    /// Inverse warping from 5 source keyframes.
    Warp,
    /// integrate + re-mesh + rasterize + warp together (the map's share of one step).
    MapStep,
    /// Ray tracing one synthetic frame (4 spp, soft shadows).
    Synth,
}

/// Arguments of `sgam bench`.
#[derive(Debug, Args)]
#[command(
    after_help = "Example:\n  sgam bench integrate --res 256 --json\n\nThe scene is the built-in CLEVR-Infinite world (seed 1); frames follow the authors' zig-zag\ntrajectory (step 0.408 m), 5 cm voxels, 0.5 m truncation, as in generation."
)]
pub struct BenchArgs {
    /// Hot path to time.
    #[arg(value_enum)]
    pub subject: Subject,
    /// Image resolution (square).
    #[arg(long, default_value_t = 256)]
    pub res: u32,
    /// Timed repetitions (each on a new frame of the trajectory).
    #[arg(long, default_value_t = 30)]
    pub iterations: usize,
    /// Print only the JSON line (otherwise also a human summary on stderr).
    #[arg(long)]
    pub json: bool,
}

/// Renders `n` frames along the zig-zag from the dataset's first camera.
pub fn synthetic_sequence(res: u32, n: usize) -> (Renderer, Vec<(Camera, RgbdFrame)>) {
    let scene = Scene::generate(1, &SceneConfig::default());
    let renderer = Renderer::new(&scene);
    let seed = blender_camera(
        sgam_core::Vec3::new(-20.0, -20.0, sgam_synth::CAMERA_HEIGHT_M),
        sgam_synth::CAMERA_PITCH_RAD,
        0.0,
        dataset_intrinsics(res),
    );
    let side = (n as f32).sqrt().ceil() as usize + 1;
    let cells = trajectory::zigzag_cells(side, side);
    let poses = trajectory::grid_poses(&seed.world_from_camera, &cells, 0.408);
    let config = RenderConfig::default();
    let frames = poses
        .iter()
        .take(n)
        .map(|p| {
            let cam = Camera::new(seed.intrinsics, *p);
            (cam, renderer.render(&cam, &config).frame)
        })
        .collect();
    (renderer, frames)
}

fn stats(ms: &mut [f64]) -> (f64, f64, f64) {
    ms.sort_by(|a, b| a.total_cmp(b));
    let n = ms.len();
    let median = if n % 2 == 1 { ms[n / 2] } else { 0.5 * (ms[n / 2 - 1] + ms[n / 2]) };
    (median, ms.iter().sum::<f64>() / n as f64, ms[0])
}

/// Runs `sgam bench`.
pub fn run(args: BenchArgs) -> Result<()> {
    if args.iterations == 0 || args.res < 16 {
        bail!("need --iterations >= 1 and --res >= 16");
    }
    let warm = 6usize;
    let (renderer, seq) = synthetic_sequence(args.res, warm + args.iterations + 1);
    let mut map = TsdfMap::new(TsdfConfig::default());
    let warp = WarpConfig::default();
    for (c, f) in &seq[..warm] {
        map.integrate(f, c);
    }
    map.update_mesh(1.0);
    let mut ms = Vec::with_capacity(args.iterations);
    let mut extra = serde_json::Map::new();
    for k in 0..args.iterations {
        let (cam, frame) = &seq[warm + k];
        let sources: Vec<SourceView<'_>> =
            seq[k + 1..warm + k].iter().rev().take(5).map(|(c, f)| SourceView { camera: c, frame: f }).collect();
        let t = Instant::now();
        match args.subject {
            Subject::Integrate => {
                map.integrate(frame, cam);
            }
            Subject::Mesh => {
                let t0 = Instant::now();
                map.integrate(frame, cam);
                let integ = t0.elapsed();
                let t1 = Instant::now();
                map.update_mesh(1.0);
                ms.push(t1.elapsed().as_secs_f64() * 1e3);
                std::hint::black_box(integ);
                continue;
            }
            Subject::Render => {
                std::hint::black_box(map.render(cam));
            }
            Subject::RayCast => {
                std::hint::black_box(map.ray_cast(cam));
            }
            Subject::Warp => {
                let r = map.render(cam);
                let t1 = Instant::now();
                std::hint::black_box(warp_colour(cam, &r.depth_m, &sources, &warp));
                ms.push(t1.elapsed().as_secs_f64() * 1e3);
                map.integrate(frame, cam);
                map.update_mesh(1.0);
                continue;
            }
            Subject::MapStep => {
                let r = map.render(cam);
                std::hint::black_box(warp_colour(cam, &r.depth_m, &sources, &warp));
                map.integrate(frame, cam);
                map.update_mesh(1.0);
            }
            Subject::Synth => {
                std::hint::black_box(renderer.render(cam, &RenderConfig::default()));
            }
        }
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        if matches!(args.subject, Subject::Render | Subject::RayCast | Subject::Synth) {
            map.integrate(frame, cam);
            map.update_mesh(1.0);
        }
    }
    let (median, mean, min) = stats(&mut ms);
    extra.insert("blocks".into(), json!(map.block_count()));
    let subject = format!("{:?}", args.subject).to_lowercase();
    let line = json!({
        "subject": subject, "res": args.res, "iterations": args.iterations,
        "median_ms": median, "mean_ms": mean, "min_ms": min, "threads": rayon::current_num_threads(),
        "extra": extra,
    });
    if !args.json {
        eprintln!(
            "{subject} at {}x{}: median {median:.3} ms (mean {mean:.3}, min {min:.3}) over {} runs",
            args.res, args.res, args.iterations
        );
    }
    println!("{line}");
    Ok(())
}
