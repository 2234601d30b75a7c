//! A short world per validation of a training run (`--world-steps`): the weights as they are
//! grown along each of a few paths from one held-out seed, judged against the true world of the
//! same path by `sgam eval world`'s statistics, one line per path in `RUN/world.jsonl`.
//! Validation cross-entropy says whether the model predicts codes; only a world says whether
//! its inventions stay objects when they are re-rendered step after step.

use std::io::Write;
use std::path::Path;

use anyhow::{Context, Result};
use serde_json::json;
use sgam_pipeline::settings::{
    InventedPixelSettings, MapSettings, PathSettings, RefinerKind, RefinerSettings, SamplingSettings, TrajectoryKind,
};
use sgam_pipeline::BankSpec;

use crate::eval_world::WorldArgs;

/// The seed scene of the training-time worlds: held out from training, and past the eight
/// held-out seeds (1,000,000-007) the bars are judged on, so choosing a checkpoint by its
/// world never tunes to them.
pub const WORLD_SEED: u64 = sgam_pipeline::HELD_OUT_SEED_BASE + 8;

/// What a training run grows at each validation (`--world-steps`, `--world-paths`).
#[derive(Debug, Clone, clap::Args)]
pub struct WorldCheck {
    /// At each validation, grow a world of this many steps with the weights as they are along
    /// each of --world-paths from one held-out seed (1,000,008: past the eight the bars are
    /// judged on) and log its statistics against the true world's in RUN/world.jsonl (density,
    /// footprints, ground, shapes, KID), without a code bank. 0: none. About 0.3 s a step on 2
    /// cores; 60-100 steps show a growing mound.
    #[arg(id = "world_steps", long = "world-steps", value_name = "STEPS", default_value_t = 0)]
    pub steps: usize,
    /// Scenes per path of --world-steps (held-out seeds 1,000,008 upward), pooled: one world's
    /// largest object is a draw (it moves 2-3x with the sampling seed), several rank checkpoints.
    #[arg(id = "world_scenes", long = "world-scenes", value_name = "N", default_value_t = 1)]
    pub scenes: u64,
    /// The paths of --world-steps, comma-separated.
    #[arg(id = "world_paths", long = "world-paths", value_name = "LIST", value_delimiter = ',', default_value = "zigzag,spiral", value_parser = crate::eval_trajectories::trajectory_parser())]
    pub paths: Vec<TrajectoryKind>,
}

impl WorldCheck {
    /// Opens the run's `world.jsonl` (lines after `step` dropped, as a resume logs them again)
    /// when worlds are grown.
    pub fn open_log(&self, run: &Path, step: u64) -> Result<Option<std::fs::File>> {
        if self.steps == 0 {
            return Ok(None);
        }
        crate::guard::open_step_log(run, "world.jsonl", step).map(Some)
    }

    /// Grows the worlds of `weights` (tensors and their model config) and prints the summary
    /// above `pb`: [`WorldCheck::run`] for a trainer's weights.
    pub fn run_weights(
        &self,
        run: &Path,
        weights: &std::collections::BTreeMap<String, sgam_model::params::NamedTensor>,
        config: &sgam_model::ModelConfig,
        step: u64,
        log: &mut impl Write,
        pb: &indicatif::ProgressBar,
    ) -> Result<()> {
        let bytes = sgam_model::params::to_safetensors_bytes(
            weights,
            sgam_model::params::WeightPrecision::F16,
            Some(sgam_model::refiner::weight_metadata(config)?),
        )?;
        let line = pb.suspend(|| self.run(run, &bytes, step, log))?;
        crate::progress::println(pb, line);
        Ok(())
    }

    /// Refuses steps `eval world` would refuse and an empty or repeated path list.
    pub fn validate(&self) -> Result<()> {
        if self.steps == 0 {
            return Ok(());
        }
        if !(10..=2000).contains(&self.steps) {
            anyhow::bail!("--world-steps {} must be 0 (none) or in 10..=2000", self.steps);
        }
        if !(1..=8).contains(&self.scenes) {
            anyhow::bail!("--world-scenes {} must be in 1..=8", self.scenes);
        }
        crate::eval_trajectories::check(&self.paths).context("--world-paths")
    }

    /// Grows this check's worlds with `weights` (a model file's bytes) at training step `step`,
    /// writes one line per path to `log` (the run's `world.jsonl`) and returns a one-line summary. The
    /// oracle's worlds are grown once and kept in `RUN/world/`; the model's are deleted once
    /// judged (each is some 20 MB of frames).
    pub fn run(&self, run: &Path, weights: &[u8], step: u64, log: &mut impl Write) -> Result<String> {
        let dir = run.join("world");
        std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
        let model = dir.join(format!("step-{step}.safetensors"));
        sgam_io::write_atomic(&model, |w| w.write_all(weights))?;
        let mut summary = Vec::new();
        for &kind in &self.paths {
            let out = dir.join(crate::eval_trajectories::name(kind));
            let args = WorldArgs {
                seeds: self.scenes,
                first_seed: WORLD_SEED,
                steps: self.steps,
                path: PathSettings::kind(kind),
                refiner: RefinerSettings {
                    model: Some(model.clone()),
                    bank: BankSpec::None,
                    ..RefinerSettings::kind(RefinerKind::Model)
                },
                sampling: SamplingSettings::default(),
                invented: InventedPixelSettings::default(),
                map: MapSettings::default(),
                paper: false,
                region_size: 5.0,
                out: Some(out.clone()),
                keep_snapshots: false,
                loop_out: None,
                no_loop: true,
                json: true,
            };
            let world = crate::eval_world::evaluate(&args)?;
            for seed in WORLD_SEED..WORLD_SEED + self.scenes {
                let generated = out.join(format!("seed-{seed}")).join(args.label());
                std::fs::remove_dir_all(&generated)
                    .with_context(|| format!("{}: cannot delete the judged world", generated.display()))?;
            }
            let line = world_line(step, kind, self.steps, self.scenes, &world);
            summary.push(format!(
                "{}: density {:.2}x, p90 footprint {:.2}x{}, ground {:.2}x, compact {:.2}/{:.2}, KID {:.4}",
                crate::eval_trajectories::name(kind),
                line["ratio"]["objects_per_100m2"].as_f64().unwrap_or(f64::NAN),
                line["ratio"]["p90_object_area"].as_f64().unwrap_or(f64::NAN),
                if self.scenes > 1 {
                    format!(" (over 2x in {}/{})", line["scenes_over_2x_p90"], self.scenes)
                } else {
                    String::new()
                },
                line["ratio"]["ground_rms"].as_f64().unwrap_or(f64::NAN),
                line["compact_share"]["generated"].as_f64().unwrap_or(f64::NAN),
                line["compact_share"]["oracle"].as_f64().unwrap_or(f64::NAN),
                line["kid"].as_f64().unwrap_or(f64::NAN),
            ));
            writeln!(log, "{line}").with_context(|| format!("{}: cannot write world.jsonl", run.display()))?;
        }
        std::fs::remove_file(&model).with_context(|| format!("{}: cannot delete", model.display()))?;
        let seeds = match self.scenes {
            1 => format!("seed {WORLD_SEED}"),
            n => format!("seeds {WORLD_SEED}-{}", WORLD_SEED + n - 1),
        };
        Ok(format!(
            "step {step}: {}-step world{} from {seeds}: {}",
            self.steps,
            if self.paths.len() > 1 || self.scenes > 1 { "s" } else { "" },
            summary.join("; ")
        ))
    }
}

/// One `world.jsonl` line: `eval world`'s ratios to the oracle (pooled over the scenes), the
/// shapes, KID, and how many scenes grew an object past twice the true world's p90 footprint.
fn world_line(
    step: u64,
    kind: TrajectoryKind,
    steps: usize,
    scenes: u64,
    world: &serde_json::Value,
) -> serde_json::Value {
    let (g, o) = (&world["generated"], &world["oracle"]);
    let over = world["per_seed"].as_array().map_or(0, |runs| {
        runs.iter().filter(|r| r["ratio_to_oracle"]["p90_object_area"].as_f64().is_some_and(|x| x > 2.0)).count()
    });
    json!({
        "step": step,
        "trajectory": crate::eval_trajectories::name(kind),
        "seed_scene": WORLD_SEED,
        "scenes": scenes,
        "scenes_over_2x_p90": over,
        "world_steps": steps,
        "ratio": world["ratio_to_oracle"],
        "median_solidity": { "generated": g["object_shape"]["median_solidity"], "oracle": o["object_shape"]["median_solidity"] },
        "compact_share": { "generated": g["object_shape"]["compact_share"], "oracle": o["object_shape"]["compact_share"] },
        "kid": world["kid"],
        "step_ms_median": world["step_ms_median"],
    })
}
