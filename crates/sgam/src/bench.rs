//! `sgam bench`: time one hot path on a built-in synthetic scene; print one JSON line.

use std::time::Instant;

use anyhow::Result;
use clap::{Args, ValueEnum};
use serde_json::json;
use sgam_core::{trajectory, Camera, RgbdFrame};
use sgam_map::{warp_colour, SourceView, TsdfConfig, TsdfMap, WarpConfig};
use sgam_synth::{RenderConfig, Renderer, Scene, SceneConfig};

/// What to time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Subject {
    /// TSDF integration of one new frame into a map of its neighbours.
    Integrate,
    /// Incremental re-meshing of the blocks one frame changed.
    Mesh,
    /// Rasterizing the map's mesh at a new camera (guidance depth, as the generator does).
    Render,
    /// TSDF ray-cast at a new camera (alternative guidance depth).
    RayCast,
    /// Inverse warping from 5 source keyframes.
    Warp,
    /// integrate + re-mesh + rasterize + warp together (the map's share of one step).
    MapStep,
    /// Ray tracing one synthetic frame (4 spp, soft shadows).
    Synth,
    /// One completion by the bundled model (its context draws the hole; or --model), a
    /// quarter of the frame missing; on the CPU its kernels (sgam_model::nhwc) against burn's
    /// pass of the same model, interleaved.
    Refine,
    /// One full generation step (sources + render + warp + refine + integrate + re-mesh +
    /// write) with the bundled model; prints the per-stage split.
    Step,
}

/// Arguments of `sgam bench`.
#[derive(Debug, Args)]
#[command(
    after_help = "Example:\n  sgam bench integrate --res 256 --json\n\nThe scene is the built-in CLEVR-Infinite world (seed 1); frames follow the authors' zig-zag\ntrajectory (step 0.408 m), 5 cm voxels; the map\nsubjects truncate at 0.5 m (the authors' 10 voxels, as the Open3D peer in bench/), `step` runs\ngeneration's own settings (0.25 m)."
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
    /// Model file for `refine` and `step` (default: the bundled model).
    #[arg(long, value_name = "FILE")]
    pub model: Option<std::path::PathBuf>,
    /// Code bank for `refine` and `step`, as `sgam generate --bank` (auto, none, bundled, FILE).
    #[arg(long, value_name = "none|bundled|FILE", default_value_t = sgam_pipeline::BankSpec::Auto)]
    pub bank: sgam_pipeline::BankSpec,
}

/// Renders `n` frames along the zig-zag from the dataset's first camera.
pub fn synthetic_sequence(res: u32, n: usize) -> (Renderer, Vec<(Camera, RgbdFrame)>) {
    let scene = Scene::generate(1, &SceneConfig::default());
    let renderer = Renderer::new(&scene);
    let seed = sgam_pipeline::synthetic_seed_camera(res);
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

/// `(median, mean, min)` of a non-empty list of timings.
fn stats(ms: &[f64]) -> (f64, f64, f64) {
    let min = ms.iter().copied().fold(f64::INFINITY, f64::min);
    (sgam_metrics::median(ms).unwrap_or(0.0), ms.iter().sum::<f64>() / ms.len() as f64, min)
}

/// The bundled model with `sgam generate`'s default sampling (the refiner `sgam
/// generate` builds with no options), for timing.
fn compact_refiner(model: Option<&std::path::Path>, bank: &sgam_pipeline::BankSpec) -> Result<sgam_model::VqRefiner> {
    if let Some(p) = model {
        crate::guard::check_input_file("--model", p)?;
    }
    let mut run = sgam_pipeline::RunSettings::default();
    run.refiner.model = model.map(|p| p.to_path_buf());
    run.refiner.bank = bank.clone();
    crate::generate::model_refiner(&run)?.ok_or_else(|| anyhow::anyhow!("the default refiner is not the model"))
}

fn print_line(args: &BenchArgs, subject: &str, ms: &[f64], extra: serde_json::Value) {
    let (median, mean, min) = stats(ms);
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
}

fn bench_refine(args: &BenchArgs) -> Result<()> {
    let mut refiner = compact_refiner(args.model.as_deref(), &args.bank)?;
    let (_, seq) = synthetic_sequence(args.res, 1);
    let (cam, frame) = &seq[0];
    let n = frame.depth_m.len();
    let missing: Vec<bool> = (0..n).map(|i| (i % args.res as usize) > args.res as usize * 3 / 4).collect();
    let g = sgam_core::Guidance { camera: *cam, frame: frame.clone(), missing, seed: 0 };
    // the CPU kernels (sgam_model::nhwc) against burn's own pass of the same model, interleaved
    let compare = refiner.uses_cpu_kernels();
    sgam_core::Refiner::refine(&mut refiner, &g)?; // warm-up
    let (mut ms, mut burn_ms) = (Vec::new(), Vec::new());
    for _ in 0..args.iterations {
        let t = Instant::now();
        std::hint::black_box(sgam_core::Refiner::refine(&mut refiner, &g)?);
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        if compare {
            refiner.set_cpu_kernels(false);
            let t = Instant::now();
            std::hint::black_box(sgam_core::Refiner::refine(&mut refiner, &g)?);
            burn_ms.push(t.elapsed().as_secs_f64() * 1e3);
            refiner.set_cpu_kernels(true);
        }
    }
    let cfg = refiner.config().clone();
    let trace = refiner.trace().clone();
    // work of one refine: with a context, one encoder and one decoder pass plus the transformer's
    // passes; without, an encoder and a decoder pass per sampling pass
    let pass = sgam_model::flops::pass_macs(&cfg, args.res as usize, args.res as usize);
    let passes = trace.passes.len().max(1) as u64;
    let context_macs: u64 = match &cfg.context {
        Some(c) => trace
            .context_tokens
            .iter()
            .map(|&t| sgam_model::context::multiply_adds(c, cfg.z_channels, cfg.embed_dim, cfg.n_embed, t, t))
            .sum(),
        None => 0,
    };
    let (enc, dec) = if cfg.context.is_some() {
        (pass.encoder, pass.decoder)
    } else {
        (passes * pass.encoder, passes * pass.decoder)
    };
    let gflop = 2.0 * (enc + dec + context_macs) as f64 / 1e9;
    let median = sgam_metrics::median(&ms).unwrap_or(f64::NAN);
    let burn_median = sgam_metrics::median(&burn_ms);
    let gemm = gemm_gflops(1024, 5);
    print_line(
        args,
        "refine",
        &ms,
        json!({"preset": cfg.name, "embed_dim": cfg.embed_dim, "n_embed": cfg.n_embed,
               "context": cfg.context, "passes": trace.passes.len(), "missing_fraction": 0.25,
               "gflop_per_refine": gflop,
               "gflop_encoder_pass": 2.0 * pass.encoder as f64 / 1e9,
               "gflop_decoder_pass": 2.0 * pass.decoder as f64 / 1e9,
               "gflop_context": 2.0 * context_macs as f64 / 1e9,
               "achieved_gflops": gflop / (median / 1e3),
               "gemm_1024_gflops": gemm,
               "share_of_gemm": gflop / (median / 1e3) / gemm,
               "cpu_kernels": compare,
               "burn_median_ms": burn_median,
               "burn_share_of_gemm": burn_median.map(|b| gflop / (b / 1e3) / gemm),
               "time_vs_burn": burn_median.map(|b| median / b)}),
    );
    Ok(())
}

/// GFLOP/s of the backend's f32 `n x n` matrix product (median of `reps`), the yardstick the
/// model's achieved rate is compared with (bench/gemm_peer.py gives numpy/OpenBLAS's beside it).
fn gemm_gflops(n: usize, reps: usize) -> f64 {
    use sgam_model::burn::tensor::{Distribution, Tensor};
    let device = sgam_model::default_device();
    let a = Tensor::<2>::random([n, n], Distribution::Uniform(-1.0, 1.0), &device);
    let b = Tensor::<2>::random([n, n], Distribution::Uniform(-1.0, 1.0), &device);
    let mut times = Vec::new();
    for _ in 0..=reps {
        let t = Instant::now();
        let c = a.clone().matmul(b.clone());
        std::hint::black_box(c.into_data());
        times.push(t.elapsed().as_secs_f64());
    }
    times.remove(0); // warm-up
    2.0 * (n as f64).powi(3) / sgam_metrics::median(&times).unwrap_or(f64::NAN) / 1e9
}

fn bench_step(args: &BenchArgs) -> Result<()> {
    use sgam_pipeline::WorldGenerator;
    let refiner = compact_refiner(args.model.as_deref(), &args.bank)?;
    let (_, seq) = synthetic_sequence(args.res, 1);
    let dir = tempfile::tempdir()?;
    // the loop exactly as `sgam generate` resolves it by default (map, sources, ground prior,
    // flying pixels)
    let config = sgam_pipeline::RunConfig::clevr(1).generator_config();
    let keyframes = sgam_pipeline::Keyframes::new(dir.path(), 1.0, 96);
    let mut generator = WorldGenerator::new(TsdfMap::new(config.tsdf), keyframes, refiner, config);
    let (seed_cam, seed_frame) = &seq[0];
    generator.seed(seed_cam, seed_frame.clone())?;
    let side = ((args.iterations + 4) as f32).sqrt().ceil() as usize + 1;
    let cells = trajectory::zigzag_cells(side, side);
    let poses = trajectory::grid_poses(&seed_cam.world_from_camera, &cells, 0.408);
    let warm = 3;
    let mut all = Vec::new();
    for p in poses.iter().skip(1).take(warm + args.iterations) {
        all.push(generator.step(&Camera::new(seed_cam.intrinsics, *p))?);
    }
    let timed = &all[warm..];
    let med = |f: fn(&sgam_pipeline::StepTimings) -> f64| {
        sgam_metrics::median(&timed.iter().map(f).collect::<Vec<f64>>()).unwrap_or(0.0)
    };
    let ms: Vec<f64> = timed.iter().map(|t| t.total_ms).collect();
    let split = json!({
        "sources_ms": med(|t| t.sources_ms), "render_ms": med(|t| t.render_ms), "warp_ms": med(|t| t.warp_ms),
        "refine_ms": med(|t| t.refine_ms), "integrate_ms": med(|t| t.integrate_ms), "mesh_ms": med(|t| t.mesh_ms),
        "write_ms": med(|t| t.write_ms), "blocks": generator.map.block_count(),
    });
    print_line(args, "step", &ms, split);
    Ok(())
}

/// Runs `sgam bench`.
pub fn run(args: BenchArgs) -> Result<()> {
    // frames are rendered up front and held in memory: both bounds keep that within the machine
    crate::guard::in_range("--iterations", args.iterations, 1..=1000)?;
    crate::guard::in_range("--res", args.res, 16..=crate::generate::MAX_RES)?;
    match args.subject {
        Subject::Refine => return bench_refine(&args),
        Subject::Step => return bench_step(&args),
        _ => {}
    }
    let warm = 6usize;
    let (renderer, seq) = synthetic_sequence(args.res, warm + args.iterations + 1);
    let mut map = TsdfMap::new(TsdfConfig::default());
    // the generator's warp policy (nearest source camera first)
    let warp = WarpConfig { selection: sgam_map::SourceSelection::NearestCamera, ..WarpConfig::default() };
    for (c, f) in &seq[..warm] {
        map.integrate(f, c);
    }
    map.update_mesh();
    let mut ms = Vec::with_capacity(args.iterations);
    // map-step: per-stage times (render, warp, integrate, mesh)
    let mut split: [Vec<f64>; 4] = Default::default();
    // Work done per timed frame (integration and re-meshing), reported as means.
    let (mut touched, mut updated, mut voxels, mut remeshed, mut counted) = (0usize, 0usize, 0usize, 0usize, 0usize);
    let mut count = |s: sgam_map::IntegrateStats, m: usize| {
        touched += s.blocks_touched;
        updated += s.blocks_updated;
        voxels += s.voxels_updated;
        remeshed += m;
        counted += 1;
    };
    for k in 0..args.iterations {
        let (cam, frame) = &seq[warm + k];
        let sources: Vec<SourceView<'_>> =
            seq[k + 1..warm + k].iter().rev().take(5).map(|(c, f)| SourceView { camera: c, frame: f }).collect();
        let t = Instant::now();
        match args.subject {
            Subject::Integrate => {
                count(map.integrate(frame, cam), 0);
            }
            Subject::Mesh => {
                let s = map.integrate(frame, cam);
                let t1 = Instant::now();
                let m = map.update_mesh();
                ms.push(t1.elapsed().as_secs_f64() * 1e3);
                count(s, m);
                continue;
            }
            Subject::Render => {
                std::hint::black_box(map.remesh_and_rasterize_depth(cam));
            }
            Subject::RayCast => {
                std::hint::black_box(map.ray_cast(cam));
            }
            Subject::Warp => {
                let depth = map.remesh_and_rasterize_depth(cam);
                let t1 = Instant::now();
                std::hint::black_box(warp_colour(cam, &depth, &sources, &warp));
                ms.push(t1.elapsed().as_secs_f64() * 1e3);
                map.integrate(frame, cam);
                map.update_mesh();
                continue;
            }
            Subject::MapStep => {
                let depth = map.remesh_and_rasterize_depth(cam);
                let t1 = Instant::now();
                std::hint::black_box(warp_colour(cam, &depth, &sources, &warp));
                let t2 = Instant::now();
                let s = map.integrate(frame, cam);
                let t3 = Instant::now();
                let m = map.update_mesh();
                let t4 = Instant::now();
                for (stage, (a, b)) in split.iter_mut().zip([(t, t1), (t1, t2), (t2, t3), (t3, t4)]) {
                    stage.push((b - a).as_secs_f64() * 1e3);
                }
                count(s, m);
            }
            Subject::Synth => {
                std::hint::black_box(renderer.render(cam, &RenderConfig::default()));
            }
            Subject::Refine | Subject::Step => {} // timed by bench_refine / bench_step above
        }
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        if matches!(args.subject, Subject::Render | Subject::RayCast | Subject::Synth) {
            map.integrate(frame, cam);
            map.update_mesh();
        }
    }
    let subject = format!("{:?}", args.subject).to_lowercase();
    let mut extra = json!({ "blocks": map.block_count() });
    if !split[0].is_empty() {
        for (name, v) in ["render_ms", "warp_ms", "integrate_ms", "mesh_ms"].iter().zip(&split) {
            extra[*name] = json!(sgam_metrics::median(v).unwrap_or(0.0));
        }
    }
    if counted > 0 {
        let mean = |x: usize| (x as f64 / counted as f64).round();
        extra["blocks_touched"] = json!(mean(touched));
        extra["blocks_updated"] = json!(mean(updated));
        extra["voxels_updated"] = json!(mean(voxels));
        if remeshed > 0 {
            extra["blocks_remeshed"] = json!(mean(remeshed));
        }
    }
    print_line(&args, &subject, &ms, extra);
    Ok(())
}
