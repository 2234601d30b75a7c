//! `sgam train sampler`: the generative stage 2 (see `sgam_model::generative`).

use std::io::Write;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_model::generative::{CodeTrainConfig, CodeTrainer};
use sgam_model::params::from_safetensors_bytes;

use crate::progress;
use sgam_model::features::FEATURE_MODEL;

fn validate(a: &SamplerArgs) -> Result<()> {
    a.common.validate()?;
    a.world.validate()?;
    if a.pairs < a.common.batch || a.pairs > 200_000 {
        bail!("--pairs {} must be at least --batch ({}) and at most 200000", a.pairs, a.common.batch);
    }
    if !(a.observed_weight.is_finite() && a.observed_weight >= 0.0) {
        bail!("--observed-weight {} must be a non-negative number", a.observed_weight);
    }
    if !(a.target_smoothing.is_finite() && (0.0..=100.0).contains(&a.target_smoothing)) {
        bail!("--target-smoothing {} must be between 0 and 100", a.target_smoothing);
    }
    if !(a.depth_weight.is_finite() && (0.0..=1000.0).contains(&a.depth_weight)) {
        bail!("--depth-weight {} must be between 0 and 1000", a.depth_weight);
    }
    if !(a.reveal.is_finite() && (0.0..=1.0).contains(&a.reveal)) {
        bail!("--reveal {} must be a probability between 0 and 1", a.reveal);
    }
    validate_steps_per_run(&a.steps_per_run)?;
    if !(16..=256).contains(&a.crop) {
        bail!("--crop {} must be in 16..=256", a.crop);
    }
    Ok(())
}

/// Arguments of `sgam train sampler`.
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  sgam train sampler --run runs/sampler --steps 12000          # from the bundled model\n  sgam train sampler --run runs/sampler --steps 16000 --lr-decay-from 12000   # resume, decayed tail\n  sgam train export runs/sampler/ckpt/model.safetensors models/compact.safetensors\n\nThe training pairs are recorded from the generator (oracle refiner, training scenes) when the\nrun starts and kept in memory; the frozen target encoder is copied to RUN/target.safetensors so\na resumed run computes the same targets. RUN/log.jsonl has one line per step, RUN/val.jsonl the\nheld-out cross-entropy and accuracy."
)]
pub struct SamplerArgs {
    /// The run folder, steps, batch, learning rate, checkpoints, scenes and seed.
    #[command(flatten)]
    pub common: crate::train_common::TrainLoopArgs,
    /// Model whose codebook and decoder are kept and whose encoder gives the targets; also the
    /// starting point unless --warm-start is given (default: `models/features.safetensors`, the
    /// stage-2 regression model the bundled sampler was built on).
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Start from this sampler model (e.g. the bundled `models/compact.safetensors`) instead of
    /// --init; it must share --init's codebook and decoder (new runs only).
    #[arg(long)]
    pub warm_start: Option<PathBuf>,
    /// Weight of the depth term: L1 on the decoded disparity of codes drawn at T = 1 against
    /// the target codes', in missing pixels (0 = cross-entropy only).
    #[arg(long, default_value_t = 0.0)]
    pub depth_weight: f32,
    /// MaskGIT training: probability that a training pair has a random share of its missing
    /// cells revealed (with the decoded target codes) before the step, as generation's later
    /// passes see a hole around cells already drawn. 0 = the holes as recorded (the default:
    /// 0.5 for 5,000 steps did not grow better worlds, docs/MODEL.md).
    #[arg(long, default_value_t = 0.0)]
    pub reveal: f32,
    /// Do not add the two ray (pixel-direction) input channels.
    #[arg(long)]
    pub no_rays: bool,
    /// Use the paper's distance logits `-||z - e_k||^2 / tau` instead of a learned code head
    /// (a 1x1 conv to one logit per code, initialised equal to them; it can express
    /// multimodal distributions, the distances cannot).
    #[arg(long)]
    pub distance_logits: bool,
    /// Crop side in pixels (a multiple of the model's downsampling factor).
    #[arg(long, default_value_t = 128)]
    pub crop: u32,
    /// Training pairs recorded at the start (kept in memory, ~0.3 MB each at crop 128).
    #[arg(long, default_value_t = 6000)]
    pub pairs: usize,
    /// Held-out pairs (from other training scenes) for the validation line.
    #[arg(long, default_value_t = 256)]
    pub val_pairs: usize,
    /// Steps per recorded generator run; a comma-separated list draws each run's length from
    /// it (repeats weight a length: `40,40,120`).
    #[arg(long, value_delimiter = ',', default_value = "40", value_name = "STEPS[,STEPS..]")]
    pub steps_per_run: Vec<usize>,
    /// Take the recorded pairs of another run folder (recorded with the same --pairs,
    /// --val-pairs, --crop, --scenes, --steps-per-run and --seed) instead of recording them:
    /// ablations on the same data, at once.
    #[arg(long, value_name = "RUN")]
    pub pairs_from: Option<PathBuf>,
    /// Loss weight of observed latent cells relative to missing ones.
    #[arg(long, default_value_t = 0.2)]
    pub observed_weight: f32,
    /// Soft targets: credit spread over codes within this many codebook spacings of the
    /// target code (codes that decode alike); 0 = one-hot.
    #[arg(long, default_value_t = 1.0)]
    pub target_smoothing: f32,
    /// Validate every N steps.
    #[arg(long, default_value_t = 500)]
    pub val_every: u64,
    /// Short worlds grown at each validation.
    #[command(flatten)]
    pub world: crate::train_world::WorldCheck,
}

/// What a run's recorded pairs are drawn with (its options; the cache key of `RUN/pairs-*.bin`).
pub(crate) struct PairSpec<'a> {
    pub run: &'a std::path::Path,
    pub steps_per_run: &'a [usize],
    pub crop: u32,
    pub scenes: u64,
    pub seed: u64,
    /// Closed-loop recording of the training pairs (`sgam train context --closed-loop`).
    pub closed_loop: Option<sgam_pipeline::codepairs::ClosedLoop<'a>>,
    /// Another run folder whose recorded pairs (same options) this run takes instead of
    /// recording them (`--pairs-from`).
    pub pairs_from: Option<&'a std::path::Path>,
    /// Pairs recorded by any closed-loop model are taken (`--pairs-from-any-model`).
    pub any_recorder: bool,
}

/// The options a pair cache was recorded with (named by the errors when they differ).
const RECORDING_OPTIONS: &str =
    "--pairs / --val-pairs / --crop / --scenes / --steps-per-run / --seed / --closed-loop / --closed-loop-steps / \
     --closed-loop-filters / closed-loop --model";

/// `n` training pairs of stream `stream`, recorded from the generator with the oracle on
/// training scenes (targets from `target`), deterministic from the spec's seed; cached in
/// `RUN/pairs-{stream}.bin` so a restart or a resume trains at once. A resumed run refuses a
/// cache recorded with other options (that would silently change its data); a new run records
/// again.
pub(crate) fn recorded_pairs(
    spec: &PairSpec,
    n: usize,
    stream: u64,
    what: &str,
    target: (&sgam_model::VqModel, &sgam_model::ModelConfig),
    resuming: bool,
) -> Result<Vec<sgam_model::generative::CodePair>> {
    // validation pairs stay the oracle's: one fixed yardstick across runs
    let closed_loop = spec.closed_loop.filter(|_| stream == 1);
    let recorded_with = closed_loop.map(|c| crc32fast::hash(c.weights));
    let (steps_per_run, steps_per_run_mix) = sgam_pipeline::codepairs::CacheKey::run_lengths(spec.steps_per_run);
    let key = sgam_pipeline::codepairs::CacheKey {
        version: sgam_pipeline::codepairs::CACHE_VERSION,
        pairs: n,
        steps_per_run,
        steps_per_run_mix,
        crop: spec.crop,
        scenes: spec.scenes,
        seed: spec.seed,
        stream,
        closed_loop: closed_loop.map_or(0.0, |c| c.share),
        closed_loop_steps: closed_loop.map_or(1.0, |c| c.steps),
        closed_loop_filters: closed_loop.is_some_and(|c| c.filters),
        // a resumed run's pairs were recorded with its starting model, not the weights it
        // resumes with: any model's (the other options still must match)
        recorded_with: recorded_with.filter(|_| !resuming && !spec.any_recorder),
    };
    let path = spec.run.join(format!("pairs-{stream}.bin"));
    if let (false, Some(dir)) = (path.exists(), spec.pairs_from) {
        let src = dir.join(format!("pairs-{stream}.bin"));
        if !src.is_file() {
            bail!("{}: no recorded pairs there (--pairs-from names a run folder that recorded them)", src.display());
        }
        if sgam_pipeline::codepairs::read_cache(&src, &key)?.is_none() {
            bail!(
                "{}: recorded with other {RECORDING_OPTIONS}; --pairs-from needs the options it was recorded with",
                src.display()
            );
        }
        // a hard link costs nothing; another file system gets a copy
        if std::fs::hard_link(&src, &path).is_err() {
            std::fs::copy(&src, &path)
                .with_context(|| format!("{}: cannot copy the pairs of {}", path.display(), src.display()))?;
        }
        eprintln!("pairs taken from {} (--pairs-from)", src.display());
    }
    if path.exists() {
        match sgam_pipeline::codepairs::read_cache(&path, &key)? {
            Some(p) => return Ok(p),
            None if resuming => bail!(
                "{}: this run's pairs were recorded with other {RECORDING_OPTIONS}; resume with the options it started with",
                path.display()
            ),
            None => eprintln!("{}: recorded with other options; recording again", path.display()),
        }
    }
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    rng.set_stream(stream);
    let pb = progress::bar(n as u64, what);
    let pairs = sgam_pipeline::codepairs::collect(
        n,
        spec.steps_per_run,
        spec.crop,
        spec.scenes,
        target,
        closed_loop,
        &mut rng,
        &mut |k| pb.set_position(k as u64),
    )?;
    pb.finish_and_clear();
    // named by the model that recorded them, also when a resumed run records again
    let key = sgam_pipeline::codepairs::CacheKey { recorded_with, ..key };
    sgam_pipeline::codepairs::write_cache(&path, &key, &pairs)?;
    Ok(pairs)
}

/// Checks `--steps-per-run`: one length or a mix, each in 1..=1000.
pub(crate) fn validate_steps_per_run(lengths: &[usize]) -> Result<()> {
    if lengths.is_empty() {
        bail!("--steps-per-run needs at least one length");
    }
    if let Some(bad) = lengths.iter().find(|&&s| s == 0 || s > 1000) {
        bail!("--steps-per-run {bad} must be in 1..=1000");
    }
    Ok(())
}

/// Runs `sgam train sampler`.
pub fn run(a: &SamplerArgs) -> Result<()> {
    validate(a)?;
    std::fs::create_dir_all(&a.common.run)
        .with_context(|| format!("{}: cannot create the run folder", a.common.run.display()))?;
    let _lock = crate::guard::RunLock::acquire(&a.common.run)?;
    crate::guard::remove_stale_temp_files(&a.common.run, &[])?;
    let device = sgam_model::default_device();
    // the frozen target encoder: a copy of the starting model, kept with the run
    let target_path = a.common.run.join("target.safetensors");
    if !target_path.exists() {
        let bytes = match &a.init {
            Some(p) => std::fs::read(p).with_context(|| format!("{}: cannot read --init", p.display()))?,
            None => FEATURE_MODEL.to_vec(),
        };
        sgam_io::write_atomic(&target_path, |w| w.write_all(&bytes))?;
    }
    let (target_model, target_config) = sgam_model::refiner::load_model(&target_path, None, &device)
        .with_context(|| format!("{}: cannot load the target model", target_path.display()))?;
    if !(a.crop as usize).is_multiple_of(target_config.downsample_factor()) {
        bail!(
            "--crop {} must be a multiple of the model's downsampling factor {}",
            a.crop,
            target_config.downsample_factor()
        );
    }
    let resuming = CodeTrainer::checkpoint_dir(&a.common.run).is_some();
    if !resuming {
        // (a run killed before its first checkpoint restarts: only its logs are there)
        crate::guard::refuse_unresumable_run(&a.common.run, &[])?;
    }
    let mut trainer = if resuming {
        let t = CodeTrainer::resume(&a.common.run, Some(a.common.steps), a.common.lr_decay_from)?;
        if t.train_config.depth_weight != a.depth_weight {
            bail!(
                "{}: this run trains with --depth-weight {}; resume with it (or start a new run)",
                a.common.run.display(),
                t.train_config.depth_weight
            );
        }
        if t.train_config.reveal != a.reveal {
            bail!(
                "{}: this run trains with --reveal {}; resume with it (or start a new run)",
                a.common.run.display(),
                t.train_config.reveal
            );
        }
        eprintln!("resuming {} at step {}", a.common.run.display(), t.step);
        t
    } else {
        let tc = CodeTrainConfig {
            steps: a.common.steps,
            batch: a.common.batch,
            lr: a.common.lr,
            lr_decay_from: a.common.lr_decay_from,
            observed_weight: a.observed_weight,
            target_smoothing: a.target_smoothing,
            depth_weight: a.depth_weight,
            reveal: a.reveal,
            ckpt_every: a.common.ckpt_every,
            seed: a.common.seed,
            ..CodeTrainConfig::default()
        };
        let mut cfg = target_config.clone();
        cfg.ray_channels = !a.no_rays;
        cfg.code_head = !a.distance_logits;
        cfg.code_tau = None;
        let bytes = std::fs::read(&target_path).with_context(|| format!("{}: cannot read", target_path.display()))?;
        let mut tensors = from_safetensors_bytes(&bytes).with_context(|| format!("{}", target_path.display()))?.0;
        if let Some(w) = &a.warm_start {
            let bytes = std::fs::read(w).with_context(|| format!("{}: cannot read --warm-start", w.display()))?;
            let (start, meta) = from_safetensors_bytes(&bytes).with_context(|| format!("{}", w.display()))?;
            // the decoder turns codes into pixels: a start with another codebook or decoder
            // would be trained against targets it cannot decode
            for (name, t) in tensors.iter().filter(|(n, _)| {
                n.starts_with("quantize.") || n.starts_with("decoder.") || n.starts_with("post_quant_conv.")
            }) {
                let same = start.get(name).is_some_and(|s| {
                    s.shape == t.shape
                        && s.values.iter().zip(&t.values).all(|(x, y)| (x - y).abs() <= 1e-3 * y.abs().max(1.0))
                });
                if !same {
                    bail!("{}: its {name} differs from the target model's; --warm-start needs the same codebook and decoder", w.display());
                }
            }
            if let Some(c) = meta.get("sgam_model_config") {
                let warm: sgam_model::config::ModelConfig = serde_json::from_str(c)
                    .with_context(|| format!("{}: its embedded config cannot be read", w.display()))?;
                cfg.ray_channels = warm.ray_channels;
                cfg.code_head = warm.code_head;
            }
            tensors = start;
        }
        CodeTrainer::new(&cfg, &tensors, &tc)?
    };
    // pairs: recorded from the generator with the oracle, deterministic from --seed
    // recorded once per run folder and cached there (RUN/pairs-*.bin), so a restart or a resume
    // trains at once
    let spec = PairSpec {
        run: &a.common.run,
        steps_per_run: &a.steps_per_run,
        crop: a.crop,
        scenes: a.common.scenes,
        seed: a.common.seed,
        closed_loop: None,
        pairs_from: a.pairs_from.as_deref(),
        any_recorder: false,
    };
    let record = |n: usize, stream: u64, what: &str| {
        recorded_pairs(&spec, n, stream, what, (&target_model, &target_config), resuming)
    };
    let started = std::time::Instant::now();
    let train_pairs = record(a.pairs, 1, "recording training pairs")?;
    let val_pairs = record(a.val_pairs, 2, "recording validation pairs")?;
    eprintln!(
        "{} training + {} validation pairs ready in {:.0} s",
        train_pairs.len(),
        val_pairs.len(),
        started.elapsed().as_secs_f64()
    );
    let (mut log, mut val_log) = (
        crate::guard::open_step_log(&a.common.run, "log.jsonl", trainer.step)?,
        crate::guard::open_step_log(&a.common.run, "val.jsonl", trainer.step)?,
    );
    let steps = trainer.train_config.steps;
    let pb = progress::bar(steps, "training");
    pb.set_position(trainer.step);
    let is_terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let t0 = std::time::Instant::now();
    let first = trainer.step;
    let mut world_log = a.world.open_log(&a.common.run, trainer.step)?;
    let mut validate = |trainer: &CodeTrainer, pb: &indicatif::ProgressBar| -> Result<()> {
        let v = trainer.evaluate(&val_pairs, 16)?;
        let line = format!(
            "step {}: validation CE missing {:.3} (acc {:.3}), observed {:.3} (acc {:.3}), tau {:.4}; \
             drawn-code disparity L1 {:.4}, bias {:+.4}",
            trainer.step,
            v.ce_missing,
            v.acc_missing,
            v.ce_observed,
            v.acc_observed,
            v.tau,
            v.depth_l1_missing.unwrap_or(f32::NAN),
            v.depth_bias_missing.unwrap_or(f32::NAN)
        );
        progress::println(pb, line);
        writeln!(val_log, "{}", serde_json::json!({ "step": trainer.step, "report": v }))?;
        if let Some(log) = world_log.as_mut() {
            a.world.run_weights(&a.common.run, &trainer.weights(), &trainer.model_config, trainer.step, log, pb)?;
        }
        Ok(())
    };
    if trainer.step == 0 {
        validate(&trainer, &pb)?;
    }
    while trainer.step < steps {
        let batch: Vec<_> = (0..trainer.train_config.batch)
            .map(|_| train_pairs[trainer.rng.random_range(0..train_pairs.len())].clone())
            .collect();
        let r = trainer.step_on(&batch)?;
        let rate =
            (trainer.step - first) as f64 * trainer.train_config.batch as f64 / t0.elapsed().as_secs_f64().max(1e-6);
        writeln!(log, "{}", serde_json::json!({ "report": r, "pairs_per_s": rate }))?;
        pb.set_position(r.step);
        pb.set_message(format!(
            "CE missing {:.3} observed {:.3} tau {:.4} {:.1} pairs/s",
            r.ce_missing, r.ce_observed, r.tau, rate
        ));
        if !is_terminal && r.step % 50 == 0 {
            eprintln!(
                "step {} CE missing {:.3} (acc {:.2}) observed {:.3} (acc {:.2}) tau {:.4} disparity L1 {:.4} \
                 bias {:+.4} ({:.1} pairs/s)",
                r.step,
                r.ce_missing,
                r.acc_missing,
                r.ce_observed,
                r.acc_observed,
                r.tau,
                r.depth_l1_missing.unwrap_or(f32::NAN),
                r.depth_bias_missing.unwrap_or(f32::NAN),
                rate
            );
        }
        if r.step % trainer.train_config.ckpt_every.max(1) == 0 {
            trainer.save(&a.common.run)?;
        }
        if a.val_every > 0 && r.step % a.val_every == 0 {
            validate(&trainer, &pb)?;
        }
    }
    trainer.save(&a.common.run)?;
    pb.finish_and_clear();
    eprintln!(
        "trained to step {}; weights: {} (export with: sgam train export {} models/compact.safetensors)",
        trainer.step,
        a.common.run.join("ckpt/model.safetensors").display(),
        a.common.run.join("ckpt/model.safetensors").display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::validate_steps_per_run;

    #[test]
    fn a_bad_length_anywhere_in_a_mix_is_refused_by_name_and_value() {
        assert!(validate_steps_per_run(&[40]).is_ok());
        assert!(validate_steps_per_run(&[40, 40, 120]).is_ok());
        assert!(validate_steps_per_run(&[1, 1000]).is_ok());
        for (mix, bad) in [(vec![40, 0], "0"), (vec![0, 40], "0"), (vec![40, 40, 1001], "1001")] {
            let e = validate_steps_per_run(&mix).expect_err("a bad length is refused").to_string();
            assert!(e.contains("--steps-per-run") && e.contains(bad), "{mix:?}: {e}");
        }
        let e = validate_steps_per_run(&[]).expect_err("no length").to_string();
        assert!(e.contains("--steps-per-run"), "{e}");
    }
}
