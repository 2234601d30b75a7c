//! The options every trainer shares (`sgam train stage1 | stage2 | sampler | context |
//! decoder`): one declaration, one check. Each trainer sets its own defaults for the steps, the
//! batch, the learning rate, the checkpoint interval and the scenes ([`with_loop_defaults`]), so
//! `--help` shows the default of the command it documents.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;
use sgam_pipeline::settings::in_range;
use sgam_pipeline::HELD_OUT_SEED_BASE;

/// The run folder, the length and pace of training, and its data.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct TrainLoopArgs {
    /// Run folder (created; holds the checkpoints and logs). Re-running the same command resumes
    /// it.
    #[arg(long)]
    pub run: PathBuf,
    /// Total optimisation steps (a resumed run continues up to this).
    #[arg(long)]
    pub steps: u64,
    /// Samples per step.
    #[arg(long)]
    pub batch: usize,
    /// Adam learning rate.
    #[arg(long)]
    pub lr: f64,
    /// Decay the learning rate along a half cosine from this step to 5 % of --lr at --steps
    /// (default: constant). Also applies when resuming: `--steps 9000 --lr-decay-from 6000`
    /// finishes a run with a decayed tail.
    #[arg(long, value_name = "STEP")]
    pub lr_decay_from: Option<u64>,
    /// Checkpoint every N steps.
    #[arg(long)]
    pub ckpt_every: u64,
    /// Training scenes: seeds 0..N (held-out evaluation seeds start at 1000000).
    #[arg(long)]
    pub scenes: u64,
    /// Seed of the data, the initialisation and the batch order.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Most steps any trainer accepts.
pub const MAX_STEPS: u64 = 10_000_000;

impl TrainLoopArgs {
    /// Checks every field; errors name the option and the accepted range.
    pub fn validate(&self) -> Result<()> {
        in_range("--steps", self.steps, 1..=MAX_STEPS)?;
        in_range("--batch", self.batch, 1..=sgam_model::train::MAX_BATCH)?;
        if !(self.lr.is_finite() && self.lr > 0.0 && self.lr <= 1.0) {
            bail!("--lr {} is out of range: accepted a positive number up to 1", self.lr);
        }
        if let Some(from) = self.lr_decay_from {
            in_range("--lr-decay-from", from, 0..=self.steps - 1)?;
        }
        in_range("--ckpt-every", self.ckpt_every, 1..=MAX_STEPS)?;
        in_range("--scenes", self.scenes, 1..=HELD_OUT_SEED_BASE - 1)?;
        Ok(())
    }
}

/// Each trainer's defaults of the shared options: (steps, batch, lr, ckpt_every, scenes).
fn loop_defaults(trainer: &str) -> Option<(&'static str, &'static str, &'static str, &'static str, &'static str)> {
    Some(match trainer {
        "stage1" | "stage2" => ("20000", "4", "0.0002", "250", "512"),
        "sampler" => ("12000", "8", "0.0003", "250", "100000"),
        "context" => ("8000", "16", "0.0005", "250", "100000"),
        "decoder" => ("1200", "4", "0.0001", "100", "100000"),
        _ => return None,
    })
}

/// A trainer's subcommand with [`loop_defaults`] set on the shared options (`sgam train`'s
/// `mut_subcommands`); other subcommands unchanged.
pub fn with_loop_defaults(cmd: clap::Command) -> clap::Command {
    let Some((steps, batch, lr, ckpt_every, scenes)) = loop_defaults(cmd.get_name()) else { return cmd };
    [("steps", steps), ("batch", batch), ("lr", lr), ("ckpt_every", ckpt_every), ("scenes", scenes)]
        .into_iter()
        .fold(cmd, |cmd, (id, v)| cmd.mut_arg(id, |a| a.default_value(v).required(false)))
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(subcommand)]
        train: crate::train::TrainCommand,
    }

    fn parse(args: &[&str]) -> crate::train_common::TrainLoopArgs {
        use crate::train::TrainCommand as T;
        match Cli::try_parse_from(args).unwrap().train {
            T::Stage1(a) | T::Stage2(a) => a.common,
            T::Sampler(a) => a.common,
            T::Context(a) => a.common,
            T::Decoder(a) => a.common,
            T::Export(_) | T::Bank(_) => unreachable!(),
        }
    }

    #[test]
    fn every_trainer_shares_the_loop_options_with_its_own_defaults() {
        // (steps, batch, lr, ckpt_every, scenes) as each trainer's --help states them
        for (cmd, want) in [
            ("stage1", (20_000, 4, 2e-4, 250, 512)),
            ("stage2", (20_000, 4, 2e-4, 250, 512)),
            ("sampler", (12_000, 8, 3e-4, 250, 100_000)),
            ("context", (8_000, 16, 5e-4, 250, 100_000)),
            ("decoder", (1_200, 4, 1e-4, 100, 100_000)),
        ] {
            let a = parse(&["t", cmd, "--run", "r"]);
            assert_eq!((a.steps, a.batch, a.lr, a.ckpt_every, a.scenes), want, "{cmd}");
            assert_eq!((a.seed, a.lr_decay_from), (0, None), "{cmd}");
            a.validate().unwrap();
            // the same flags parse on every trainer and the same check refuses the same values
            let a = parse(&["t", cmd, "--run", "r", "--steps", "10", "--lr-decay-from", "10"]);
            let e = a.validate().unwrap_err().to_string();
            assert!(e.contains("--lr-decay-from 10 is out of range"), "{cmd}: {e}");
            let e = parse(&["t", cmd, "--run", "r", "--scenes", "1000000"]).validate().unwrap_err().to_string();
            assert!(e.contains("--scenes 1000000 is out of range"), "{cmd}: {e}");
        }
    }
}
