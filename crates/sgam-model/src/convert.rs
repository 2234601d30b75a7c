//! Import of the authors' PyTorch Lightning checkpoints (`last.ckpt`: zip + pickle, weights under
//! the `state_dict` key) into the `paper` preset.
//!
//! Keys are used as they are (our parameter paths equal the authors' state-dict keys); entries the
//! model does not have (the loss's discriminator / LPIPS weights under `loss.`) are skipped.

use std::collections::BTreeMap;
use std::path::Path;

use burn::store::pytorch_reader::{DType, PytorchReader};

use crate::config::ModelConfig;
use crate::model::VqModel;
use crate::params::{load_named, NamedTensor, WeightPrecision};
use crate::ModelError;

/// Reads the float tensors of a Lightning checkpoint's `state_dict` (or of a plain state dict when
/// the file has no such key).
pub fn read_lightning_state_dict(ckpt: &Path) -> Result<BTreeMap<String, NamedTensor>, ModelError> {
    let reader = PytorchReader::with_top_level_key(ckpt, "state_dict")
        .or_else(|_| PytorchReader::new(ckpt))
        .map_err(|e| ModelError::Format { what: "a PyTorch checkpoint", msg: e.to_string() }.in_file(ckpt))?;
    let mut out = BTreeMap::new();
    for (name, t) in reader.tensors() {
        let bytes = t.read().map_err(|e| {
            ModelError::Format { what: "a checkpoint tensor", msg: format!("{name}: {e}") }.in_file(ckpt)
        })?;
        let values: Vec<f32> = match t.dtype() {
            DType::F32 => bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect(),
            DType::F64 => bytes
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32)
                .collect(),
            DType::F16 => bytes.chunks_exact(2).map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32()).collect(),
            DType::BF16 => bytes.chunks_exact(2).map(|c| half::bf16::from_le_bytes([c[0], c[1]]).to_f32()).collect(),
            _ => continue, // integer buffers (e.g. BatchNorm's num_batches_tracked)
        };
        out.insert(name.clone(), NamedTensor { shape: t.shape().to_vec(), values });
    }
    Ok(out)
}

/// Converts an authors' checkpoint into a safetensors file of the `paper` preset (f32, config
/// embedded). `config` overrides the preset (e.g. a 4096-entry Google Earth codebook); when
/// `None`, the paper preset is used with the codebook size read from the checkpoint.
pub fn convert_lightning_checkpoint(
    ckpt: &Path,
    out: &Path,
    config: Option<&ModelConfig>,
) -> Result<ModelConfig, ModelError> {
    let mut tensors = read_lightning_state_dict(ckpt)?;
    tensors.retain(|k, _| !k.starts_with("loss."));
    let config = match config {
        Some(c) => c.clone(),
        None => {
            let mut c = ModelConfig::paper();
            if let Some(e) = tensors.get("quantize.embedding.weight") {
                if e.shape.len() == 2 {
                    c.n_embed = e.shape[0];
                    c.embed_dim = e.shape[1];
                }
            }
            c
        }
    };
    let device = crate::default_device();
    let model = VqModel::new(&config, 0, &device)?;
    let model = load_named(model, &tensors, false, true).map_err(|e| e.in_file(ckpt))?;
    crate::refiner::save_model(&model, &config, out, WeightPrecision::F32)?;
    Ok(config)
}
