//! `sgam convert-checkpoint`: import the SGAM authors' PyTorch Lightning checkpoint into a
//! safetensors weight file that `sgam generate --model` loads.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use sgam_model::ModelConfig;

/// Arguments of `sgam convert-checkpoint`.
#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  sgam convert-checkpoint clevr/last.ckpt clevr.safetensors\n  sgam convert-checkpoint \
                  google_earth/last.ckpt ge.safetensors --codebook 4096\n  sgam generate --model clevr.safetensors \
                  --out world\n\nThe checkpoint is read without Python (zip + pickle, weights under `state_dict`); the \
                  discriminator and LPIPS weights under `loss.` are dropped. Without --codebook or --model-config the \
                  `paper` preset is used with the codebook size found in the checkpoint."
)]
pub struct ConvertArgs {
    /// The authors' Lightning checkpoint (`last.ckpt`) or a `torch.save`d state dict.
    pub input: PathBuf,
    /// Output safetensors file (f32, model config embedded).
    pub output: PathBuf,
    /// Codebook size of the `paper` preset (16384 for CLEVR, 4096 for Google Earth); default: read
    /// from the checkpoint.
    #[arg(long, value_name = "N", conflicts_with = "model_config")]
    pub codebook: Option<usize>,
    /// Architecture as a ModelConfig JSON file, for checkpoints of another architecture.
    #[arg(long, value_name = "JSON")]
    pub model_config: Option<PathBuf>,
}

/// Runs `sgam convert-checkpoint`.
pub fn run(args: ConvertArgs) -> Result<()> {
    crate::guard::check_input_file("checkpoint", &args.input)?;
    crate::guard::check_output_file("output", &args.output)?;
    let config = match (&args.model_config, args.codebook) {
        (Some(path), _) => Some(crate::train::read_model_config(path)?),
        (None, Some(n)) => {
            crate::guard::in_range("--codebook", n, 1..=sgam_model::config::MAX_CODEBOOK)?;
            Some(ModelConfig { n_embed: n, ..ModelConfig::paper() })
        }
        (None, None) => None,
    };
    // the library's errors name the checkpoint (or the output file)
    let used = sgam_model::convert::convert_lightning_checkpoint(&args.input, &args.output, config.as_ref())?;
    eprintln!(
        "wrote {} ({} preset, codebook {} x {}) from {}",
        args.output.display(),
        used.name,
        used.n_embed,
        used.embed_dim,
        args.input.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(input: PathBuf, output: PathBuf) -> ConvertArgs {
        ConvertArgs { input, output, codebook: None, model_config: None }
    }

    #[test]
    fn convert_checkpoint_errors_name_the_input() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("out.safetensors");
        let err = format!("{:#}", run(args(tmp.path().join("absent.ckpt"), out.clone())).unwrap_err());
        assert!(err.contains("absent.ckpt"), "{err}");
        let junk = tmp.path().join("junk.ckpt");
        std::fs::write(&junk, b"not a checkpoint").unwrap();
        let err = format!("{:#}", run(args(junk.clone(), out.clone())).unwrap_err());
        assert!(err.contains("junk.ckpt"), "{err}");
        let bad_cfg = tmp.path().join("cfg.json");
        std::fs::write(&bad_cfg, b"{}").unwrap();
        let err =
            format!("{:#}", run(ConvertArgs { model_config: Some(bad_cfg), ..args(junk, out.clone()) }).unwrap_err());
        assert!(err.contains("cfg.json"), "{err}");
        assert!(!out.exists());
    }
}
