//! `sgam train bank`: the code bank a run can complete holes from (`--bank`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

use crate::guard::in_range;
use crate::progress;

/// Arguments of `sgam train bank`.
#[derive(Debug, Args)]
pub struct BankArgs {
    /// Output bank file (written atomically).
    #[arg(long)]
    pub out: PathBuf,
    /// True frames in the bank (2 bytes per latent cell each: 2 KB at 256 px).
    #[arg(long, default_value_t = 4096)]
    pub frames: usize,
    /// The model whose encoder gives the codes (default: the bundled model); a run uses the
    /// bank only with a model of the same codebook.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Frame size in pixels (square; the runs' --res).
    #[arg(long, default_value_t = 256)]
    pub res: u32,
    /// Which training scenes and poses (another seed, another bank).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Runs `sgam train bank`.
pub fn run(a: &BankArgs) -> Result<()> {
    in_range("--frames", a.frames, 1..=1_000_000)?;
    in_range("--res", a.res, 16..=sgam_pipeline::MAX_RES)?;
    crate::guard::check_output_file("--out", &a.out)?;
    if let Some(m) = &a.model {
        crate::guard::check_input_file("--model", m)?;
    }
    let options = sgam_pipeline::settings::SamplingSettings::default().refiner_options();
    let mut refiner = sgam_pipeline::model_refiner(a.model.as_deref(), options)?;
    let bar = progress::bar(a.frames as u64, "frames");
    let bank = sgam_pipeline::bank::build_bank(&mut refiner, a.frames, a.res, a.seed, |n| bar.set_position(n as u64))?;
    bar.finish_and_clear();
    sgam_pipeline::bank::write_bank(&a.out, &bank).with_context(|| format!("--out {}", a.out.display()))?;
    println!(
        "{} frames of {}x{} codes -> {} ({:.1} MB, codebook {:08x})",
        bank.len(),
        bank.rows,
        bank.cols,
        a.out.display(),
        (bank.codes.len() * 2) as f64 / 1e6,
        bank.codebook_crc32
    );
    Ok(())
}
