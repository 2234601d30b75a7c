//! `sgam train decoder`: fine-tune the decoder on whole frames (see
//! `sgam_model::decoder_tune`).

use std::io::Write;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_core::{Intrinsics, RgbdFrame, Vec3};
use sgam_model::decoder_tune::{DecoderTuneConfig, DecoderTuner, BORDER_ROWS};
use sgam_model::params::from_safetensors_bytes;
use sgam_synth::{blender_camera, dataset_intrinsics, RenderConfig, Renderer, Scene, SceneConfig};

use crate::progress;
use sgam_model::features::FEATURE_MODEL;
use sgam_pipeline::BUNDLED_MODEL;

/// Arguments of `sgam train decoder`.
#[derive(Debug, Args)]
#[command(
    after_help = "Example (how the bundled model's decoder was tuned):\n  sgam train decoder --run runs/decoder --steps 1200\n  sgam train export runs/decoder/ckpt/model.safetensors models/compact.safetensors\n\nRe-running the same command resumes from RUN/ckpt."
)]
pub struct DecoderArgs {
    /// The run folder, steps, batch, learning rate, checkpoints, scenes and seed.
    #[command(flatten)]
    pub common: crate::train_common::TrainLoopArgs,
    /// Model whose decoder is tuned (default: the bundled model).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Model whose encoder gives the codes (default: `models/features.safetensors`, whose
    /// codes the bundled sampler predicts); must share --model's codebook.
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Frame size (square, the generator's: 256).
    #[arg(long, default_value_t = 256)]
    pub res: u32,
    /// Training frames rendered at the start (kept in memory).
    #[arg(long, default_value_t = 800)]
    pub frames: usize,
    /// Held-out frames (other training scenes) for the validation line.
    #[arg(long, default_value_t = 32)]
    pub val_frames: usize,
    /// Weight of the disparity L1 relative to the colour L1.
    #[arg(long, default_value_t = 4.0)]
    pub depth_weight: f32,
}

fn validate(a: &DecoderArgs) -> Result<()> {
    a.common.validate()?;
    if a.common.batch == 0 || a.common.batch > 64 {
        bail!("--batch {} must be in 1..=64", a.common.batch);
    }
    if !(16..=1024).contains(&a.res) {
        bail!("--res {} must be in 16..=1024", a.res);
    }
    if a.frames < a.common.batch || a.frames > 20_000 {
        bail!("--frames {} must be at least --batch ({}) and at most 20000", a.frames, a.common.batch);
    }
    if a.val_frames == 0 || a.val_frames > 2_000 {
        bail!("--val-frames {} must be in 1..=2000", a.val_frames);
    }
    if !(a.depth_weight.is_finite() && (0.0..=1000.0).contains(&a.depth_weight)) {
        bail!("--depth-weight {} must be between 0 and 1000", a.depth_weight);
    }
    Ok(())
}

/// `n` clean frames of the generator's camera (height, pitch, heading of the zig-zag) at random
/// places of training scenes, four per scene, drawn from stream `stream` of `seed`.
fn render_frames(n: usize, a: &DecoderArgs, stream: u64, what: &str) -> (Vec<RgbdFrame>, Vec<Intrinsics>) {
    let mut rng = ChaCha8Rng::seed_from_u64(a.common.seed);
    rng.set_stream(stream);
    let k = dataset_intrinsics(a.res);
    let pb = progress::bar(n as u64, what);
    let mut frames = Vec::with_capacity(n);
    while frames.len() < n {
        let scene = Scene::generate(rng.random_range(0..a.common.scenes), &SceneConfig::default());
        let renderer = Renderer::new(&scene);
        for _ in 0..4.min(n - frames.len()) {
            let centre = Vec3::new(rng.random_range(-20.0..20.0), rng.random_range(-20.0..20.0), 0.0);
            let camera = blender_camera(centre, sgam_synth::CAMERA_PITCH_RAD, 0.0, k);
            frames.push(renderer.render(&camera, &RenderConfig::default()).frame);
        }
        pb.set_position(frames.len() as u64);
    }
    pb.finish_and_clear();
    (frames, vec![k; n])
}

/// Runs `sgam train decoder`.
pub fn run(a: &DecoderArgs) -> Result<()> {
    validate(a)?;
    std::fs::create_dir_all(&a.common.run)
        .with_context(|| format!("{}: cannot create the run folder", a.common.run.display()))?;
    let device = sgam_model::default_device();
    let encoder_bytes = match &a.encoder {
        Some(p) => std::fs::read(p).with_context(|| format!("{}: cannot read --encoder", p.display()))?,
        None => FEATURE_MODEL.to_vec(),
    };
    let (encoder, encoder_config) = sgam_model::refiner::load_model_bytes(&encoder_bytes, None, &device)
        .context("the encoder model cannot be loaded")?;
    let mut tuner = if DecoderTuner::checkpoint_dir(&a.common.run).is_some() {
        let t = DecoderTuner::resume(&a.common.run, encoder, &encoder_config, Some(a.common.steps))?;
        eprintln!("resuming {} at step {}", a.common.run.display(), t.step);
        t
    } else {
        let bytes = match &a.model {
            Some(p) => std::fs::read(p).with_context(|| format!("{}: cannot read --model", p.display()))?,
            None => BUNDLED_MODEL.to_vec(),
        };
        let (tensors, meta) = from_safetensors_bytes(&bytes).context("--model is not a safetensors model")?;
        let config: sgam_model::ModelConfig = match meta.get("sgam_model_config") {
            Some(c) => serde_json::from_str(c).context("--model's embedded config cannot be read")?,
            None => bail!("--model has no embedded config (export it with `sgam train export`)"),
        };
        let tc = DecoderTuneConfig {
            steps: a.common.steps,
            lr: a.common.lr,
            lr_decay_from: a.common.lr_decay_from,
            depth_weight: a.depth_weight,
        };
        DecoderTuner::new(&config, &tensors, encoder, &encoder_config, &tc)?
    };
    let started = std::time::Instant::now();
    let (train, train_k) = render_frames(a.frames, a, 1, "rendering training frames");
    let (val, val_k) = render_frames(a.val_frames, a, 2, "rendering validation frames");
    eprintln!(
        "{} training + {} validation frames ready in {:.0} s",
        train.len(),
        val.len(),
        started.elapsed().as_secs_f64()
    );
    let mut log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(a.common.run.join("log.jsonl"))
        .with_context(|| format!("{}: cannot open log.jsonl", a.common.run.display()))?;
    let say = |line: String| eprintln!("{line}");
    let report = |tuner: &DecoderTuner, log: &mut std::fs::File| -> Result<()> {
        let v = tuner.evaluate(&val, &val_k, a.common.batch)?;
        say(format!(
            "step {}: validation colour L1 {:.4}, disparity L1 {:.4}, depth MAE {:.3} m, top {BORDER_ROWS} rows' \
             bias {:+.3} m",
            tuner.step, v.l1_colour, v.l1_disparity, v.depth_mae_m, v.top_rows_bias_m
        ));
        writeln!(log, "{}", serde_json::json!({ "validation": v }))?;
        Ok(())
    };
    if tuner.step == 0 {
        report(&tuner, &mut log)?;
    }
    let t0 = std::time::Instant::now();
    let first = tuner.step;
    while tuner.step < tuner.config.steps {
        // the batch of a step depends only on the seed and the step: a resumed run sees the
        // same batches as an uninterrupted one
        let mut rng = ChaCha8Rng::seed_from_u64(a.common.seed ^ tuner.step.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let idx: Vec<usize> = (0..a.common.batch).map(|_| rng.random_range(0..train.len())).collect();
        let frames: Vec<&RgbdFrame> = idx.iter().map(|&i| &train[i]).collect();
        let ks: Vec<Intrinsics> = idx.iter().map(|&i| train_k[i]).collect();
        let r = tuner.step_on(&frames, &ks)?;
        let rate = (tuner.step - first) as f64 * a.common.batch as f64 / t0.elapsed().as_secs_f64().max(1e-6);
        writeln!(log, "{}", serde_json::json!({ "report": r, "frames_per_s": rate }))?;
        if r.step % 20 == 0 {
            say(format!(
                "step {} loss {:.4} colour L1 {:.4} disparity L1 {:.4} top-rows bias {:+.3} m ({rate:.1} frames/s)",
                r.step, r.loss, r.l1_colour, r.l1_disparity, r.top_rows_bias_m
            ));
        }
        if r.step % a.common.ckpt_every == 0 {
            tuner.save(&a.common.run)?;
            report(&tuner, &mut log)?;
        }
    }
    tuner.save(&a.common.run)?;
    eprintln!(
        "tuned to step {}; weights: {} (export with: sgam train export {} models/compact.safetensors)",
        tuner.step,
        a.common.run.join("ckpt/model.safetensors").display(),
        a.common.run.join("ckpt/model.safetensors").display()
    );
    Ok(())
}
