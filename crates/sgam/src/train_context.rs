//! `sgam train context`: the scene-wide context transformer over the code grid (see
//! `sgam_model::context` and `sgam_model::context_train`).

use std::io::Write;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use rand::Rng;
use sgam_model::context::ContextConfig;
use sgam_model::context_train::{context_pairs, ContextEngine, ContextPair, ContextTrainConfig, ContextTrainer};
use sgam_model::params::from_safetensors_bytes;
use sgam_pipeline::BUNDLED_MODEL;

use crate::progress;
use sgam_model::features::FEATURE_MODEL;

/// Arguments of `sgam train context`.
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  sgam train context --run runs/context --steps 6000     # from the bundled model\n  sgam train context --run runs/context --steps 9000 --lr-decay-from 6000   # resume, decayed tail\n  sgam train export runs/context/ckpt/model.safetensors models/compact.safetensors\n\nEverything but the transformer is frozen: the training pairs are recorded from the generator\n(oracle refiner, training scenes) and the model's encoder features of each are computed once,\nso a step costs the transformer alone. Pairs are cached in the run folder (pairs-*.bin).\nRe-running the same command resumes from RUN/ckpt. RUN/log.jsonl has one line per step,\nRUN/val.jsonl the held-out cross-entropy of the first pass (nothing revealed) and of MaskGIT's\nreveal schedule, with the head alone beside them; with --world-steps, RUN/world.jsonl the\nstatistics of a short world grown with the weights of each validation (RUN/world/ keeps the\ntrue worlds it is judged against)."
)]
pub struct ContextArgs {
    /// The run folder, steps, batch, learning rate, checkpoints, scenes and seed.
    #[command(flatten)]
    pub common: crate::train_common::TrainLoopArgs,
    /// Generative model whose encoder, code head, codebook and decoder are kept (default: the
    /// bundled model). When it has a context (the bundled one does), that context is the
    /// starting point, unless --new-context.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Start a new context (--dim, --layers, --heads) even when the model has one: its
    /// context is left out and the new one trained on the same autoencoder.
    #[arg(long)]
    pub new_context: bool,
    /// Token width of a new context [default: 128].
    #[arg(long)]
    pub dim: Option<usize>,
    /// Transformer blocks of a new context [default: 4].
    #[arg(long)]
    pub layers: Option<usize>,
    /// Attention heads of a new context [default: 4].
    #[arg(long)]
    pub heads: Option<usize>,
    /// Linear learning-rate warm-up, steps.
    #[arg(long, default_value_t = 200)]
    pub warmup: u64,
    /// Share of the pairs shown with their whole hole open (generation's first pass).
    #[arg(long, default_value_t = 0.3)]
    pub whole_hole: f32,
    /// Training pairs to record.
    #[arg(long, default_value_t = 6000)]
    pub pairs: usize,
    /// Validation pairs (another stream of training scenes).
    #[arg(long, default_value_t = 256)]
    pub val_pairs: usize,
    /// Crop side of a pair, pixels (the transformer's window in training).
    #[arg(long, default_value_t = 128)]
    pub crop: u32,
    /// Steps of each recorded generator run; a comma-separated list draws each run's length
    /// from it (repeats weight a length: `40,40,120` mixes short runs with long ones, whose
    /// later steps show the guidance of a long horizon).
    #[arg(long, value_delimiter = ',', default_value = "40", value_name = "STEPS[,STEPS..]")]
    pub steps_per_run: Vec<usize>,
    /// Take the recorded pairs of another run folder (recorded with the same --pairs,
    /// --val-pairs, --crop, --scenes, --steps-per-run, --seed, --closed-loop and
    /// --closed-loop-filters) instead of
    /// recording them: ablations on the same data, at once. Closed-loop pairs must have been
    /// recorded by this run's starting model (--model), unless --pairs-from-any-model.
    #[arg(long, value_name = "RUN")]
    pub pairs_from: Option<PathBuf>,
    /// With --pairs-from: take closed-loop pairs whichever model recorded them, e.g. to train a
    /// context of another size (--dim, --layers) on exactly the pairs another run trained on.
    #[arg(long, requires = "pairs_from")]
    pub pairs_from_any_model: bool,
    /// Share of the training pairs' generator runs (0-1) that grow their map with the starting
    /// model's own completions (generation's default sampling) instead of the truth: the
    /// guidance then holds the model's earlier inventions, as in generation, and the target is
    /// still the true frame. Validation pairs stay the oracle's.
    #[arg(long, default_value_t = 0.0)]
    pub closed_loop: f32,
    /// Share of a closed-loop run's steps (0-1] that the model completes; the oracle completes
    /// the rest, so the map stays the true world around scattered inventions and the true frame
    /// beyond an invention is still what the guidance around it implies (1: every step, and the
    /// world drifts away from the truth the targets come from).
    #[arg(long, default_value_t = 1.0)]
    pub closed_loop_steps: f32,
    /// Closed-loop runs treat the model's completions as `sgam generate` does before fusing
    /// them (CLEVR's invented-pixel policy: ground prior, flying pixels, free-space carving,
    /// solids, the size cap), so the pairs hold the guidance generation really leaves; without
    /// it they are fused as drawn (pairs recorded before session 30).
    #[arg(long)]
    pub closed_loop_filters: bool,
    /// Validate every N steps (0 = only at the start).
    #[arg(long, default_value_t = 250)]
    pub val_every: u64,
    /// Short worlds grown at each validation.
    #[command(flatten)]
    pub world: crate::train_world::WorldCheck,
    /// Stop (checkpointed, resumable) after this many seconds of training, pairs excluded:
    /// fits a run to a session or a lent accelerator's minutes.
    #[arg(long, value_name = "SECONDS")]
    pub time_limit: Option<f64>,
    /// Compute the gradients with burn's autodiff instead of the model's own CPU kernels (the
    /// default of a CPU build; about 2.5x faster here). A `wgpu` build always uses burn's, on
    /// the GPU. Either resumes the other's checkpoint, with a fresh optimizer.
    #[arg(long)]
    pub burn_autodiff: bool,
}

fn validate(a: &ContextArgs) -> Result<()> {
    a.common.validate()?;
    if a.pairs < a.common.batch || a.pairs > 200_000 {
        bail!("--pairs {} must be at least --batch ({}) and at most 200000", a.pairs, a.common.batch);
    }
    if a.val_pairs == 0 || a.val_pairs > 20_000 {
        bail!("--val-pairs {} must be in 1..=20000", a.val_pairs);
    }
    if !(a.closed_loop.is_finite() && (0.0..=1.0).contains(&a.closed_loop)) {
        bail!("--closed-loop {} must be a share between 0 and 1", a.closed_loop);
    }
    if a.closed_loop_filters && a.closed_loop <= 0.0 {
        bail!("--closed-loop-filters applies to closed-loop runs: give --closed-loop SHARE too");
    }
    if !(a.closed_loop_steps.is_finite() && a.closed_loop_steps > 0.0 && a.closed_loop_steps <= 1.0) {
        bail!("--closed-loop-steps {} must be a share above 0 and at most 1", a.closed_loop_steps);
    }
    if !(a.whole_hole.is_finite() && (0.0..=1.0).contains(&a.whole_hole)) {
        bail!("--whole-hole {} must be a share between 0 and 1", a.whole_hole);
    }
    if let Some(t) = a.time_limit {
        if !(t.is_finite() && t > 0.0) {
            bail!("--time-limit {t} must be a positive number of seconds");
        }
    }
    a.world.validate()?;
    crate::train_sampler::validate_steps_per_run(&a.steps_per_run)?;
    if !(16..=256).contains(&a.crop) {
        bail!("--crop {} must be in 16..=256", a.crop);
    }
    Ok(())
}

/// Runs `sgam train context`.
pub fn run(a: &ContextArgs) -> Result<()> {
    validate(a)?;
    std::fs::create_dir_all(&a.common.run)
        .with_context(|| format!("{}: cannot create the run folder", a.common.run.display()))?;
    let _lock = crate::guard::RunLock::acquire(&a.common.run)?;
    crate::guard::remove_stale_temp_files(&a.common.run, &[])?;
    let device = sgam_model::default_device();
    let resuming = ContextTrainer::has_checkpoint(&a.common.run);
    if !resuming {
        // (a run killed before its first checkpoint restarts: only its logs are there)
        crate::guard::refuse_unresumable_run(&a.common.run, &[])?;
    }
    let engine = if a.burn_autodiff { ContextEngine::Burn } else { ContextEngine::default() };
    let mut trainer = if resuming {
        let t = ContextTrainer::resume_on(&a.common.run, Some(a.common.steps), a.common.lr_decay_from, engine)
            .with_context(|| format!("{}: cannot resume", a.common.run.display()))?;
        eprintln!("resuming {} at step {}", a.common.run.display(), t.step);
        t
    } else {
        let bytes = match &a.model {
            Some(p) => std::fs::read(p).with_context(|| format!("{}: cannot read --model", p.display()))?,
            None => BUNDLED_MODEL.to_vec(),
        };
        let what = a.model.as_ref().map_or("the bundled model".to_string(), |p| p.display().to_string());
        let (mut tensors, meta) = from_safetensors_bytes(&bytes).with_context(|| what.clone())?;
        let json = meta
            .get(sgam_model::refiner::CONFIG_METADATA_KEY)
            .with_context(|| format!("{what}: carries no model config"))?;
        let mut cfg: sgam_model::ModelConfig =
            serde_json::from_str(json).with_context(|| format!("{what}: its model config cannot be read"))?;
        if !cfg.code_head {
            bail!("{what}: not a generative model with a code head (train one with `sgam train sampler`)");
        }
        let sized = a.dim.is_some() || a.layers.is_some() || a.heads.is_some();
        if let (Some(c), false) = (&cfg.context, a.new_context) {
            if sized {
                bail!(
                    "{what} already has a context ({} wide, {} blocks, {} heads), which this run would continue: \
                     --dim / --layers / --heads size a new one (add --new-context to leave it out and start one)",
                    c.dim,
                    c.layers,
                    c.heads
                );
            }
        } else {
            // a new context on the model's autoencoder: the old one's weights are left out
            tensors.retain(|name, _| !name.starts_with("context."));
            let d = ContextConfig::default();
            let c = ContextConfig {
                dim: a.dim.unwrap_or(d.dim),
                layers: a.layers.unwrap_or(d.layers),
                heads: a.heads.unwrap_or(d.heads),
                ..d
            };
            c.validate().context("--dim / --layers / --heads")?;
            cfg.context = Some(c);
        }
        let tc = ContextTrainConfig {
            steps: a.common.steps,
            batch: a.common.batch,
            lr: a.common.lr,
            lr_decay_from: a.common.lr_decay_from,
            warmup: a.warmup,
            whole_hole: a.whole_hole,
            ckpt_every: a.common.ckpt_every,
            seed: a.common.seed,
            ..ContextTrainConfig::default()
        };
        ContextTrainer::new_on(&cfg, &tensors, &tc, engine).with_context(|| format!("{what}: cannot start training"))?
    };
    eprintln!(
        "gradients: {}",
        match trainer.engine() {
            ContextEngine::Kernels => "the model's CPU kernels",
            ContextEngine::Burn => "burn's autodiff (--burn-autodiff, or a wgpu build)",
        }
    );
    // the frozen encoder of the model being extended gives the features; the feature model
    // (the stage-1 encoder) gives the target codes, as for `sgam train sampler`
    let (target_model, target_config) = sgam_model::refiner::load_model_bytes(FEATURE_MODEL, None, &device)?;
    // the model as it starts (its frozen encoder gives the features; closed-loop recording runs
    // it as generation does)
    let start_bytes = sgam_model::params::to_safetensors_bytes(
        &trainer.weights(),
        sgam_model::params::WeightPrecision::F32,
        Some(sgam_model::refiner::weight_metadata(&trainer.model_config)?),
    )?;
    let (model, model_config) = sgam_model::refiner::load_model_bytes(&start_bytes, None, &device)?;
    if !(a.crop as usize).is_multiple_of(model_config.downsample_factor()) {
        bail!(
            "--crop {} must be a multiple of the model's downsampling factor {}",
            a.crop,
            model_config.downsample_factor()
        );
    }
    let spec = crate::train_sampler::PairSpec {
        run: &a.common.run,
        steps_per_run: &a.steps_per_run,
        crop: a.crop,
        scenes: a.common.scenes,
        seed: a.common.seed,
        closed_loop: (a.closed_loop > 0.0).then(|| sgam_pipeline::codepairs::ClosedLoop {
            share: a.closed_loop,
            steps: a.closed_loop_steps,
            weights: &start_bytes,
            options: sgam_pipeline::settings::SamplingSettings::default().refiner_options(),
            filters: a.closed_loop_filters,
        }),
        pairs_from: a.pairs_from.as_deref(),
        any_recorder: a.pairs_from_any_model,
    };
    let record = |n: usize, stream: u64, what: &str| -> Result<Vec<ContextPair>> {
        let pairs =
            crate::train_sampler::recorded_pairs(&spec, n, stream, what, (&target_model, &target_config), resuming)?;
        let pb = progress::bar(pairs.len() as u64, "encoder features");
        let out = context_pairs(&model, &model_config, &pairs, 0.5, 32, &mut |k| pb.set_position(k as u64))?;
        pb.finish_and_clear();
        Ok(out)
    };
    let started = std::time::Instant::now();
    let train_pairs = record(a.pairs, 1, "recording training pairs")?;
    let val_pairs = record(a.val_pairs, 2, "recording validation pairs")?;
    if train_pairs.is_empty() || val_pairs.is_empty() {
        bail!("no recorded pair has a missing cell; record more (--pairs, --val-pairs)");
    }
    eprintln!(
        "{} training + {} validation pairs with holes ready in {:.0} s",
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
    let t0 = std::time::Instant::now();
    let first = trainer.step;
    let mut world_log = a.world.open_log(&a.common.run, trainer.step)?;
    let mut validate = |trainer: &ContextTrainer, pb: &indicatif::ProgressBar| -> Result<()> {
        let whole = trainer.evaluate(&val_pairs, 1.0, 16)?;
        let reveal = trainer.evaluate(&val_pairs, 0.0, 16)?;
        let line = format!(
            "step {}: validation CE first pass {:.3} (head alone {:.3}, acc {:.3}); with reveals {:.3} (head {:.3}, acc {:.3})",
            trainer.step, whole.ce, whole.ce_head, whole.acc, reveal.ce, reveal.ce_head, reveal.acc
        );
        progress::println(pb, line);
        writeln!(
            val_log,
            "{}",
            serde_json::json!({ "step": trainer.step, "first_pass": whole, "reveal": reveal,
                "wall_s": t0.elapsed().as_secs_f64() })
        )?;
        if let Some(log) = world_log.as_mut() {
            a.world.run_weights(&a.common.run, &trainer.weights(), &trainer.model_config, trainer.step, log, pb)?;
        }
        Ok(())
    };
    if trainer.step == 0 {
        validate(&trainer, &pb)?;
    }
    // batches of one size: pairs grouped by their latent shape
    let mut by_shape: std::collections::BTreeMap<[usize; 2], Vec<usize>> = std::collections::BTreeMap::new();
    for (i, p) in train_pairs.iter().enumerate() {
        by_shape.entry(p.shape).or_default().push(i);
    }
    let groups: Vec<Vec<usize>> = by_shape.into_values().collect();
    let is_terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let mut mean = (0.0f64, 0.0f64, 0usize);
    while trainer.step < steps {
        if a.time_limit.is_some_and(|limit| t0.elapsed().as_secs_f64() >= limit) {
            eprintln!("--time-limit reached at step {}", trainer.step);
            break;
        }
        let g = &groups[trainer.rng.random_range(0..groups.len())];
        let batch: Vec<&ContextPair> =
            (0..trainer.train_config.batch).map(|_| &train_pairs[g[trainer.rng.random_range(0..g.len())]]).collect();
        let r = trainer.step_on(&batch)?;
        let rate =
            (trainer.step - first) as f64 * trainer.train_config.batch as f64 / t0.elapsed().as_secs_f64().max(1e-6);
        writeln!(log, "{}", serde_json::json!({ "report": r, "pairs_per_s": rate }))?;
        mean = (mean.0 + r.ce as f64, mean.1 + r.ce_head as f64, mean.2 + 1);
        pb.set_position(r.step);
        pb.set_message(format!("CE {:.3} (head {:.3}) {:.1} pairs/s", r.ce, r.ce_head, rate));
        if !is_terminal && r.step % 50 == 0 {
            eprintln!(
                "step {} CE {:.3} (head alone {:.3}) over the last {} steps, {:.1} pairs/s",
                r.step,
                mean.0 / mean.2.max(1) as f64,
                mean.1 / mean.2.max(1) as f64,
                mean.2,
                rate
            );
            mean = (0.0, 0.0, 0);
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
