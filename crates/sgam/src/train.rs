//! `sgam train stage1|stage2`: train the VQ model on the synthetic world, on the fly.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sgam_core::{Image, RgbdFrame};
use sgam_model::train::ValidationImage;
use sgam_model::{ModelConfig, Stage, TrainConfig, TrainPair};

use crate::guard::{in_range, positive, RunLock};
use crate::progress;
use sgam_pipeline::SynthPairs;
use sgam_pipeline::HELD_OUT_SEED_BASE;

/// Model architecture presets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Preset {
    /// The CPU design (fast at 256x256 on 2 cores).
    Compact,
    /// The SGAM authors' VQGAN (~68M parameters; needs a GPU to train in reasonable time).
    Paper,
    /// A very small model for tests and smoke runs.
    Tiny,
}

/// `sgam train` stages.
#[derive(Debug, Subcommand)]
#[command(mut_subcommands(crate::train_common::with_loop_defaults))]
pub enum TrainCommand {
    /// Stage 1: autoencode clean RGB-D (codebook, encoder and decoder all train).
    Stage1(TrainArgs),
    /// Stage 2: fine-tune the encoder and mask conv on incomplete -> complete pairs built by the
    /// generator's own render + warp path; codebook, quant convs and decoder frozen.
    Stage2(TrainArgs),
    /// Generative stage 2: train the encoder to predict a distribution over codebook indices
    /// (cross-entropy against the codes the frozen encoder gives the clean target), on pairs
    /// recorded from the generator itself running with the oracle on training scenes.
    Sampler(crate::train_sampler::SamplerArgs),
    /// Scene-wide context: a transformer over the code grid that completes a hole knowing all of
    /// it (MaskGIT-style, on the frozen sampler's features); everything else stays.
    Context(crate::train_context::ContextArgs),
    /// Fine-tune the decoder on whole frames (the codes, encoder and codebook stay): a decoder
    /// trained on crops cannot tell how far the ground is at a frame's border.
    Decoder(crate::train_decoder::DecoderArgs),
    /// Build a code bank (`sgam generate --bank FILE`): true frames of training scenes, encoded
    /// by the model, that holes can be completed from.
    #[command(after_help = "Example (the bundled bank):\n  sgam train bank --out models/bank.bin --frames 4096")]
    Bank(crate::train_bank::BankArgs),
    /// Write a run's weights as a shippable model file (f16 by default, config embedded).
    #[command(
        after_help = "Example (the bundled model):\n  sgam train export runs/s2/model.safetensors models/compact.safetensors"
    )]
    Export(ExportArgs),
}

/// Arguments of `sgam train export`.
#[derive(Debug, Args)]
pub struct ExportArgs {
    /// Weights to export (a run's model.safetensors).
    pub input: PathBuf,
    /// Output safetensors file (written atomically).
    pub output: PathBuf,
    /// Keep 32-bit floats.
    #[arg(long)]
    pub f32: bool,
    /// Take `post_quant_conv` and the decoder from this model (same codebook required): pairs a
    /// newly trained sampler with a decoder tuned on whole frames (`sgam train decoder`).
    #[arg(long, value_name = "FILE")]
    pub decoder_from: Option<PathBuf>,
}

fn export(a: &ExportArgs) -> Result<()> {
    crate::guard::check_input_file("input", &a.input)?;
    crate::guard::check_output_file("output", &a.output)?;
    let device = sgam_model::default_device();
    let (mut model, config) = sgam_model::refiner::load_model(&a.input, None, &device)
        .with_context(|| format!("{}: cannot load the model", a.input.display()))?;
    if let Some(d) = &a.decoder_from {
        crate::guard::check_input_file("--decoder-from", d)?;
        let (other, other_config) = sgam_model::refiner::load_model(d, None, &device)
            .with_context(|| format!("{}: cannot load the model", d.display()))?;
        if (other_config.n_embed, other_config.embed_dim, other_config.z_channels)
            != (config.n_embed, config.embed_dim, config.z_channels)
        {
            bail!("{}: its codebook or latent size differs from {}'s", d.display(), a.input.display());
        }
        let host = |m: &sgam_model::VqModel| -> Result<Vec<f32>> {
            m.quantize.embedding.weight.val().into_data().try_to_vec::<f32>().map_err(|e| anyhow::anyhow!("{e:?}"))
        };
        let (mine, theirs) = (host(&model)?, host(&other)?);
        if mine.iter().zip(&theirs).any(|(x, y)| (x - y).abs() > 1e-3 * y.abs().max(1.0)) {
            bail!(
                "{}: its codebook differs from {}'s; a decoder only fits the codes it was trained on",
                d.display(),
                a.input.display()
            );
        }
        model.post_quant_conv = other.post_quant_conv;
        model.decoder = other.decoder;
    }
    let precision =
        if a.f32 { sgam_model::params::WeightPrecision::F32 } else { sgam_model::params::WeightPrecision::F16 };
    sgam_model::refiner::save_model(&model, &config, &a.output, precision)
        .with_context(|| format!("{}: cannot write the model", a.output.display()))?;
    let bytes = std::fs::metadata(&a.output).map(|m| m.len()).unwrap_or(0);
    eprintln!("{} -> {} ({} preset, {:.1} MB)", a.input.display(), a.output.display(), config.name, bytes as f64 / 1e6);
    Ok(())
}

/// Options shared by both stages.
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  sgam train stage1 --run runs/train-s1 --steps 20000\n  sgam train stage2 --run runs/train-s2 --init runs/train-s1/model.safetensors --steps 10000\n\nRe-running the same command resumes from the run folder's last checkpoint, RUN/ckpt (weights,\noptimizer state, step, RNG; committed as a whole and verified on resume); only --steps,\n--lr-decay-from, --ckpt-every and --val-every may change. RUN/model.safetensors holds the last\ncheckpoint's weights. Validation strips (input | output | target) go to RUN/val/."
)]
pub struct TrainArgs {
    /// The run folder, steps, batch, learning rate, checkpoints, scenes and seed.
    #[command(flatten)]
    pub common: crate::train_common::TrainLoopArgs,
    /// Architecture preset (new runs only).
    #[arg(long, value_enum, default_value_t = Preset::Compact)]
    pub preset: Preset,
    /// Architecture as a ModelConfig JSON file (the `model_config` object of a run's
    /// config.json has this form); overrides --preset. New runs only.
    #[arg(long, value_name = "JSON")]
    pub model_config: Option<PathBuf>,
    /// Random crop size in pixels (crops of 256x256 views).
    #[arg(long, default_value_t = 128)]
    pub crop: u32,
    /// Weight of the perceptual term (L1 between image gradients). At 1.0 it slowed a fixed-batch
    /// fit from 32 dB to 15 dB in 300 steps; 0.1 keeps its edge sharpening without that.
    #[arg(long, default_value_t = 0.1)]
    pub perceptual_weight: f32,
    /// Weight of the L1 loss on pixels missing in the input relative to observed ones
    /// (default: 1 in stage 1, 10 in stage 2, where missing pixels are a few percent of a crop
    /// and the only ones the refiner's output is used for).
    #[arg(long)]
    pub missing_weight: Option<f32>,
    /// Stage 2: share of pairs whose guidance comes from 1-2 views up to 3 grid steps away in
    /// a random direction (large holes, as at the zig-zag's turns); 0 = only the neighbours
    /// behind the target (the bundled model's training).
    #[arg(long, default_value_t = 0.0)]
    pub wide_holes: f64,
    /// Stage 1: steps without quantization first (the paper: 30k of 90k).
    #[arg(long, default_value_t = 0)]
    pub warmup_no_quant: u64,
    /// Step at which the PatchGAN discriminator starts.
    #[arg(long, default_value_t = 10_000)]
    pub disc_start: u64,
    /// Validate (and write a strip) every N steps.
    #[arg(long, default_value_t = 250)]
    pub val_every: u64,
    /// Weights to start from (stage 2: the stage-1 model.safetensors).
    #[arg(long)]
    pub init: Option<PathBuf>,
}

/// Validation pairs from held-out scenes (fixed).
pub fn validation_pairs(stage: Stage, n: usize, crop: u32) -> Vec<TrainPair> {
    let mut rng = ChaCha8Rng::seed_from_u64(12345);
    let mut src = SynthPairs::new(stage, (HELD_OUT_SEED_BASE + 500..HELD_OUT_SEED_BASE + 504).collect(), 256);
    (0..n).map(|_| src.pair(crop, &mut rng)).collect()
}

/// Side-by-side strip of frames' colour, one row per example.
pub fn write_strip(path: &Path, rows: &[Vec<&RgbdFrame>]) -> Result<()> {
    let (Some(first), true) = (rows.first().and_then(|r| r.first()), !rows.is_empty()) else { return Ok(()) };
    let (w, h) = (first.width(), first.height());
    let cols = rows[0].len() as u32;
    let mut img = Image::filled(w * cols, h * rows.len() as u32, [0.0f32; 3]);
    for (r, row) in rows.iter().enumerate() {
        for (c, f) in row.iter().enumerate() {
            for v in 0..h.min(f.height()) {
                for u in 0..w.min(f.width()) {
                    *img.at_mut(c as u32 * w + u, r as u32 * h + v) = *f.colour.at(u, v);
                }
            }
        }
    }
    sgam_io::write_rgb_png(path, &img)?;
    Ok(())
}

/// Reads and validates a ModelConfig JSON file (`--model-config`).
pub fn read_model_config(path: &Path) -> Result<ModelConfig> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let c: ModelConfig =
        serde_json::from_str(&text).with_context(|| format!("{}: not a model configuration", path.display()))?;
    c.validate().with_context(|| format!("{}: invalid model configuration", path.display()))?;
    Ok(c)
}

/// Side of the synthetic views training crops are cut from, pixels.
const VIEW_RES: u32 = 256;

impl TrainArgs {
    /// Checks every option of stages 1 and 2 (finite, in range, the crop a multiple of
    /// `model`'s downsampling factor within the 256-pixel views); errors name the option and
    /// the accepted range.
    pub fn validate(&self, stage: Stage, model: &ModelConfig) -> Result<()> {
        self.common.validate()?;
        let f = model.downsample_factor() as u32;
        if !(f..=VIEW_RES).contains(&self.crop) || !self.crop.is_multiple_of(f) {
            bail!(
                "--crop {} is out of range: accepted multiples of the model's downsampling factor {f} in {f}..={VIEW_RES}",
                self.crop
            );
        }
        in_range("--perceptual-weight", self.perceptual_weight, 0.0..=1000.0)?;
        if let Some(w) = self.missing_weight {
            positive("--missing-weight", w, 1000.0)?;
        }
        in_range("--wide-holes", self.wide_holes, 0.0..=1.0)?;
        // a stage's own options are refused on the other stage, which would ignore them
        if stage == Stage::One && self.wide_holes > 0.0 {
            bail!("--wide-holes shapes stage 2's guidance; stage 1 autoencodes clean frames and would ignore it");
        }
        if stage == Stage::Two && self.warmup_no_quant > 0 {
            bail!("--warmup-no-quant is stage 1's (the codebook is frozen in stage 2, which would ignore it)");
        }
        Ok(())
    }
}

/// The error of a resumed run asked for other options, in option names.
fn resume_mismatch(run: &Path, differences: &[sgam_model::train::ConfigDifference]) -> anyhow::Error {
    if let Some(d) = differences.iter().find(|d| d.field == "stage") {
        return anyhow::anyhow!(
            "{} is a stage-{} run; stage {} needs its own --run folder (start it with --init {})",
            run.display(),
            d.stored,
            d.asked,
            run.join("model.safetensors").display()
        );
    }
    let option = |field: &str| match field {
        "model_config" => "--preset/--model-config".to_string(),
        "init_weights" => "--init".to_string(),
        "warmup_no_quant_steps" => "--warmup-no-quant".to_string(),
        "data" => "--scenes/--wide-holes".to_string(),
        f => format!("--{}", f.replace('_', "-")),
    };
    let list: Vec<String> =
        differences.iter().map(|d| format!("{} {} (asked {})", option(d.field), d.stored, d.asked)).collect();
    anyhow::anyhow!(
        "{} was started with {}; resume it with those options (only --steps, --lr-decay-from, --ckpt-every and \
         --val-every may change), or start a new run",
        run.display(),
        list.join(", ")
    )
}

/// Runs `sgam train`.
pub fn run(cmd: TrainCommand) -> Result<()> {
    let (stage, args) = match cmd {
        TrainCommand::Stage1(a) => (Stage::One, a),
        TrainCommand::Stage2(a) => (Stage::Two, a),
        TrainCommand::Export(a) => return export(&a),
        TrainCommand::Bank(a) => return crate::train_bank::run(&a),
        TrainCommand::Sampler(a) => return crate::train_sampler::run(&a),
        TrainCommand::Context(a) => return crate::train_context::run(&a),
        TrainCommand::Decoder(a) => return crate::train_decoder::run(&a),
    };
    let model_config = match (&args.model_config, args.preset) {
        (Some(path), _) => read_model_config(path)?,
        (None, Preset::Compact) => ModelConfig::compact(),
        (None, Preset::Paper) => ModelConfig::paper(),
        (None, Preset::Tiny) => ModelConfig::tiny(),
    };
    args.validate(stage, &model_config)?;
    if let Some(init) = &args.init {
        crate::guard::check_input_file("--init", init)?;
    }
    let _lock = RunLock::acquire(&args.common.run)?;
    crate::guard::remove_stale_temp_files(&args.common.run, &["ckpt", "ckpt.old", "val"])?;
    let resumed_step = sgam_model::train::read_checkpoint(&args.common.run)?.map(|(_, state)| state.step);
    let resuming = resumed_step.is_some();
    if !resuming {
        crate::guard::refuse_unresumable_run(&args.common.run, &["model.safetensors"])?;
    }
    if stage == Stage::Two && args.init.is_none() && !resuming {
        bail!("stage 2 starts from a stage-1 model: pass --init RUN1/model.safetensors");
    }
    let mut cfg = TrainConfig::new(stage, args.common.steps);
    cfg.batch = args.common.batch;
    cfg.crop = args.crop;
    cfg.lr = args.common.lr;
    cfg.lr_decay_from = args.common.lr_decay_from;
    cfg.perceptual_weight = args.perceptual_weight;
    cfg.missing_weight = args.missing_weight.unwrap_or(if stage == Stage::Two { 10.0 } else { 1.0 });
    cfg.data = [
        ("scenes".to_string(), args.common.scenes.to_string()),
        ("wide_holes".to_string(), args.wide_holes.to_string()),
    ]
    .into_iter()
    .collect();
    cfg.warmup_no_quant_steps = args.warmup_no_quant;
    cfg.disc_start = args.disc_start;
    cfg.ckpt_every = args.common.ckpt_every;
    cfg.val_every = args.val_every;
    cfg.seed = args.common.seed;
    cfg.init_weights = args.init.clone();
    let mut source = SynthPairs::new(stage, (0..args.common.scenes).collect(), 256).with_wide_holes(args.wide_holes);
    let val = validation_pairs(stage, 4, args.crop);
    std::fs::create_dir_all(args.common.run.join("val"))
        .with_context(|| format!("{}: cannot create", args.common.run.display()))?;
    let pb = progress::bar(args.common.steps, "training");
    let run_dir = args.common.run.clone();
    // without a terminal (background runs) print a plain line every 50 steps instead of a bar
    let quiet_bar = std::io::IsTerminal::is_terminal(&std::io::stderr());
    // the loss log is append-only (one JSON object per line), written as training goes
    let mut log = crate::guard::open_step_log(&args.common.run, "log.jsonl", resumed_step.unwrap_or(0))?;
    let mut on_step = |p: &sgam_model::TrainProgress| {
        let r = &p.report;
        pb.set_position(r.step);
        pb.set_message(format!(
            "loss {:.4} l1 {:.4} psnr {:.2} codes {} {:.2} img/s",
            r.total, r.l1, r.psnr, r.active_codes, p.images_per_s
        ));
        let mut line = serde_json::json!({
            "step": r.step, "total": r.total, "l1": r.l1, "perceptual": r.perceptual, "quant": r.quant,
            "g_gan": r.g_gan, "d_loss": r.d_loss, "psnr": r.psnr, "active_codes": r.active_codes,
            "images_per_s": p.images_per_s,
        });
        if let Some((psnr, images)) = &p.validation {
            progress::println(&pb, format!("step {}: validation PSNR {psnr:.2} dB", r.step));
            let rows: Vec<Vec<&RgbdFrame>> =
                images.iter().map(|v: &ValidationImage| vec![&v.input, &v.output, &v.target]).collect();
            let _ = write_strip(&run_dir.join("val").join(format!("step-{:06}.png", r.step)), &rows);
            line["val_psnr"] = serde_json::json!(psnr);
        }
        let _ = writeln!(log, "{line}");
        if !quiet_bar && r.step.is_multiple_of(50) {
            eprintln!(
                "step {} loss {:.4} l1 {:.4} psnr {:.2} ({:.2} img/s)",
                r.step, r.total, r.l1, r.psnr, p.images_per_s
            );
        }
    };
    let summary = sgam_model::train(&args.common.run, &model_config, &cfg, &mut source, &val, &mut on_step).map_err(
        |e| match e {
            sgam_model::train::TrainError::ResumeMismatch { run, differences } => resume_mismatch(&run, &differences),
            other => anyhow::Error::new(other),
        },
    )?;
    pb.finish_and_clear();
    eprintln!(
        "trained to step {} ({:.2} images/s); weights: {}",
        summary.steps,
        summary.images_per_s,
        args.common.run.join("model.safetensors").display()
    );
    Ok(())
}
