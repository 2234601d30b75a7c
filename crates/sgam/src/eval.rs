//! `sgam eval`: measurements of generated worlds and meshes.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use serde_json::json;

/// `sgam eval` subcommands.
#[derive(Debug, Subcommand)]
pub enum EvalCommand {
    /// Distances between two meshes: each one's vertices to the other's surface (metres).
    Mesh(MeshArgs),
    /// One-step completion quality (PSNR, SSIM, on visible and missing pixels) on held-out
    /// synthetic scenes, with guidance built exactly as generation builds it.
    OneStep(OneStepArgs),
    /// Grow worlds with a refiner and with the oracle on held-out seeds along the same
    /// trajectory and compare them: objects, footprints, colour, ground roughness, the paper's
    /// scene metrics and KID.
    World(Box<crate::eval_world::WorldArgs>),
    /// The baselines table: the bundled model (argmin and sampled), the null stand-in, the
    /// no-map and no-refine ablations and the oracle through `eval world` and `eval one-step`,
    /// as Markdown, plus the overview pictures side by side.
    Table(crate::eval_table::TableArgs),
    /// No-reference checks of a world grown from a real seed (Google Earth, a user's RGB-D),
    /// which has no true world: the new area's colour and texture against the seed's (KID of
    /// patches), geometry floating outside the seed's heights, and the new area per frame.
    Seed(crate::eval_seed::SeedArgs),
}

/// Arguments of `sgam eval mesh`.
#[derive(Debug, Args)]
#[command(after_help = "Example (our fused mesh against Open3D's):\n  sgam eval mesh sgam.ply open3d.ply --json")]
pub struct MeshArgs {
    /// Mesh A (PLY).
    pub a: PathBuf,
    /// Mesh B (PLY).
    pub b: PathBuf,
    /// Distances beyond this (metres) count as unmatched.
    #[arg(long, default_value_t = 0.1)]
    pub max_distance: f32,
    /// Print only the JSON line.
    #[arg(long)]
    pub json: bool,
}

fn summary(d: &[f32], max: f32) -> serde_json::Value {
    let matched: Vec<f32> = d.iter().copied().filter(|x| x.is_finite()).collect();
    let q = |p: f64| {
        if matched.is_empty() {
            return f32::NAN;
        }
        let mut s = matched.clone();
        s.sort_by(|a, b| a.total_cmp(b));
        s[((s.len() - 1) as f64 * p).round() as usize]
    };
    json!({
        "median_m": q(0.5), "p90_m": q(0.9), "mean_m": matched.iter().map(|x| *x as f64).sum::<f64>() / matched.len().max(1) as f64,
        "unmatched_fraction": 1.0 - matched.len() as f64 / d.len().max(1) as f64, "max_distance_m": max,
    })
}

/// Runs `sgam eval`.
pub fn run(cmd: EvalCommand) -> Result<()> {
    match cmd {
        EvalCommand::World(a) => {
            let mut v = crate::eval_world::evaluate(&a)?;
            // scripts reading the JSON see the same warning the text gives
            v["warning"] = crate::eval_report::too_short(&v).map_or(serde_json::Value::Null, |w| w.trim().into());
            if !a.json {
                eprint!("{}", crate::eval_report::summary_text(&v));
            }
            println!("{v}");
            Ok(())
        }
        EvalCommand::Table(a) => crate::eval_table::run(&a),
        EvalCommand::Seed(a) => crate::eval_seed::run(&a),
        EvalCommand::OneStep(a) => {
            a.validate()?;
            let line = match a.refiner {
                crate::generate::RefinerKind::Oracle => {
                    bail!("the oracle is exact by construction; evaluate null or a model")
                }
                kind => {
                    let mut run = sgam_pipeline::RunSettings {
                        refiner: sgam_pipeline::settings::RefinerSettings {
                            refiner: kind,
                            model: a.model.clone(),
                            no_refine: false,
                            bank: sgam_pipeline::BankSpec::Auto,
                            adapt: 0.0,
                        },
                        ..Default::default()
                    };
                    run.sampling.regenerate_observed = a.regenerate_observed || a.autoencode;
                    match crate::generate::model_refiner(&run)? {
                        Some(mut m) => one_step(&a, &mut m)?,
                        None => one_step(&a, &mut sgam_pipeline::NullRefiner { fill: true })?,
                    }
                }
            };
            if !a.json {
                eprintln!("{}", serde_json::to_string_pretty(&line)?);
            }
            println!("{line}");
            Ok(())
        }
        EvalCommand::Mesh(a) => {
            crate::guard::positive("--max-distance", a.max_distance, 1000.0)?;
            let ma = sgam_io::read_ply(&a.a)?;
            let mb = sgam_io::read_ply(&a.b)?;
            if ma.positions.is_empty() || mb.triangles.is_empty() || ma.triangles.is_empty() {
                bail!(
                    "both meshes need vertices and triangles ({}: {}, {}: {})",
                    a.a.display(),
                    ma.positions.len(),
                    a.b.display(),
                    mb.positions.len()
                );
            }
            let ab = sgam_metrics::point_to_mesh_distances(&ma.positions, &mb, a.max_distance);
            let ba = sgam_metrics::point_to_mesh_distances(&mb.positions, &ma, a.max_distance);
            let line = json!({
                "a": a.a.display().to_string(), "b": a.b.display().to_string(),
                "a_vertices": ma.positions.len(), "b_vertices": mb.positions.len(),
                "a_to_b": summary(&ab, a.max_distance), "b_to_a": summary(&ba, a.max_distance),
            });
            if !a.json {
                eprintln!("{}", serde_json::to_string_pretty(&line)?);
            }
            println!("{line}");
            Ok(())
        }
    }
}

/// Arguments of `sgam eval one-step`.
#[derive(Debug, Args)]
#[command(
    after_help = "Example:\n  sgam eval one-step --scenes 8 --json\n\nHeld-out scenes (seeds from 1000000, never used in training); per scene several target views whose\nguidance is built exactly as generation builds it (map of neighbouring views behind the target on\nthe zig-zag grid, rasterized, colour inverse-warped from the nearest 5), then completed by the\nrefiner and compared with the ground-truth render."
)]
pub struct OneStepArgs {
    /// Held-out scenes to use.
    #[arg(long, default_value_t = 8)]
    pub scenes: u64,
    /// Target views per scene.
    #[arg(long, default_value_t = 4)]
    pub views: usize,
    /// Image resolution (square).
    #[arg(long, default_value_t = 256)]
    pub res: u32,
    /// Refiner to evaluate.
    #[arg(long, value_enum, default_value_t = crate::generate::RefinerKind::Auto)]
    pub refiner: crate::generate::RefinerKind,
    /// Model weights (default: the bundled model).
    #[arg(long)]
    pub model: Option<std::path::PathBuf>,
    /// Score the model's own output on every pixel (the paper's protocol) instead of keeping
    /// the guidance where it was observed.
    #[arg(long)]
    pub regenerate_observed: bool,
    /// Stage-1 reconstruction instead of completion: the refiner gets the clean ground truth
    /// (nothing missing) and must reproduce it (implies --regenerate-observed).
    #[arg(long)]
    pub autoencode: bool,
    /// Print only the JSON line.
    #[arg(long)]
    pub json: bool,
}

impl OneStepArgs {
    /// Checks every option; errors name the option and the accepted range.
    pub fn validate(&self) -> Result<()> {
        use crate::guard::in_range;
        in_range("--scenes", self.scenes, 1..=10_000)?;
        in_range("--views", self.views, 1..=10_000)?;
        in_range("--res", self.res, 16..=crate::generate::MAX_RES)?;
        if let Some(m) = &self.model {
            crate::guard::check_input_file("--model", m)?;
        }
        Ok(())
    }
}

/// Accumulates per-image metrics.
#[derive(Debug, Default)]
struct Acc {
    psnr: Vec<f64>,
    ssim: Vec<f64>,
    psnr_visible: Vec<f64>,
    ssim_visible: Vec<f64>,
    psnr_missing: Vec<f64>,
    ssim_missing: Vec<f64>,
    disp_l1_visible: Vec<f64>,
    disp_l1_missing: Vec<f64>,
    missing_fraction: Vec<f64>,
}

fn mean(v: &[f64]) -> f64 {
    let f: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if f.is_empty() {
        f64::NAN
    } else {
        f.iter().sum::<f64>() / f.len() as f64
    }
}

/// One-step completion quality of `refiner` on held-out synthetic views.
pub fn one_step<R: sgam_core::Refiner>(args: &OneStepArgs, refiner: &mut R) -> Result<serde_json::Value> {
    use rand::SeedableRng;
    let mut acc = Acc::default();
    let mut times = Vec::new();
    for s in 0..args.scenes {
        let seed = sgam_pipeline::HELD_OUT_SEED_BASE + s;
        let mut pairs = sgam_pipeline::SynthPairs::new(sgam_model::Stage::Two, vec![seed], args.res);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        for v in 0..args.views {
            let (camera, mut pair) = pairs.sample(args.res, &mut rng);
            if args.autoencode {
                pair.input = pair.target.clone();
                pair.missing.fill(false);
            }
            let guidance = sgam_core::Guidance {
                camera,
                frame: pair.input.clone(),
                missing: pair.missing.clone(),
                seed: seed ^ v as u64,
            };
            let t = std::time::Instant::now();
            let out = refiner.refine(&guidance).map_err(anyhow::Error::new)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
            let visible: Vec<bool> = pair.missing.iter().map(|m| !m).collect();
            let (a, b) = (&out.colour, &pair.target.colour);
            acc.psnr.push(sgam_metrics::psnr(a, b, None).unwrap_or(f64::NAN));
            acc.ssim.push(sgam_metrics::ssim(a, b, None).unwrap_or(f64::NAN));
            acc.psnr_visible.push(sgam_metrics::psnr(a, b, Some(&visible)).unwrap_or(f64::NAN));
            acc.ssim_visible.push(sgam_metrics::ssim(a, b, Some(&visible)).unwrap_or(f64::NAN));
            acc.psnr_missing.push(sgam_metrics::psnr(a, b, Some(&pair.missing)).unwrap_or(f64::NAN));
            acc.ssim_missing.push(sgam_metrics::ssim(a, b, Some(&pair.missing)).unwrap_or(f64::NAN));
            let (da, db) = (&out.depth_m, &pair.target.depth_m);
            acc.disp_l1_visible.push(sgam_metrics::disparity_l1(da, db, Some(&visible)).unwrap_or(f64::NAN));
            acc.disp_l1_missing.push(sgam_metrics::disparity_l1(da, db, Some(&pair.missing)).unwrap_or(f64::NAN));
            acc.missing_fraction.push(pair.missing.iter().filter(|m| **m).count() as f64 / pair.missing.len() as f64);
        }
    }
    Ok(json!({
        "images": acc.psnr.len(), "scenes": args.scenes, "res": args.res,
        "mode": if args.autoencode { "autoencode" } else if args.regenerate_observed { "regenerate-observed" } else { "keep-observed" },
        "psnr": mean(&acc.psnr), "ssim": mean(&acc.ssim),
        "psnr_visible": mean(&acc.psnr_visible), "ssim_visible": mean(&acc.ssim_visible),
        "psnr_missing": mean(&acc.psnr_missing), "ssim_missing": mean(&acc.ssim_missing),
        "disparity_l1_visible": mean(&acc.disp_l1_visible), "disparity_l1_missing": mean(&acc.disp_l1_missing),
        "missing_fraction": mean(&acc.missing_fraction),
        "refine_ms_median": sgam_metrics::median(&times).unwrap_or(0.0),
    }))
}
