//! [`VqRefiner`]: the learned [`Refiner`] the generator calls (guidance in, complete frame out).
//!
//! Weight files are safetensors keyed by parameter path; the model config travels in the file's
//! metadata under [`CONFIG_METADATA_KEY`] (JSON), or as a separate JSON file.

use std::collections::HashMap;
use std::path::Path;

use burn::module::Module;
use burn::tensor::Device;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sgam_core::{Guidance, Image, Refiner, RgbdFrame};

use crate::config::ModelConfig;
use crate::model::VqModel;
use crate::packing::{missing_cells, pack, unpack};
use crate::params::{from_safetensors_bytes, load_named, save_safetensors, WeightPrecision};
use crate::quantize::{quantize, Sampling};
use crate::ModelError;

/// Safetensors metadata key holding the [`ModelConfig`] JSON.
pub const CONFIG_METADATA_KEY: &str = "sgam_model_config";

/// Metadata map carrying `config`.
pub fn weight_metadata(config: &ModelConfig) -> Result<HashMap<String, String>, ModelError> {
    let json = serde_json::to_string(config).map_err(|e| ModelError::Config(format!("serialising config: {e}")))?;
    Ok(HashMap::from([(CONFIG_METADATA_KEY.to_string(), json)]))
}

/// Saves a model with its config embedded (f16 halves the size; used for the shipped model).
pub fn save_model(
    model: &VqModel,
    config: &ModelConfig,
    path: &Path,
    precision: WeightPrecision,
) -> Result<(), ModelError> {
    save_safetensors(model, path, precision, Some(weight_metadata(config)?))
}

/// Loads a model from safetensors bytes; the config comes from `config_json` when given, else
/// from the file's metadata.
pub fn load_model_bytes(
    weights: &[u8],
    config_json: Option<&[u8]>,
    device: &Device,
) -> Result<(VqModel, ModelConfig), ModelError> {
    let (tensors, meta) = from_safetensors_bytes(weights)?;
    let config: ModelConfig = match config_json {
        Some(json) => {
            serde_json::from_slice(json).map_err(|e| ModelError::Config(format!("parsing config JSON: {e}")))?
        }
        None => {
            let json = meta.get(CONFIG_METADATA_KEY).ok_or_else(|| {
                ModelError::Config(format!("weights carry no '{CONFIG_METADATA_KEY}' metadata and no config was given"))
            })?;
            serde_json::from_str(json).map_err(|e| ModelError::Config(format!("parsing embedded config: {e}")))?
        }
    };
    let model = load_named(VqModel::new(&config, 0, device)?, &tensors, false, false)?;
    Ok((model, config))
}

/// Loads a model from a safetensors file and an optional config JSON file.
pub fn load_model(
    weights: &Path,
    config: Option<&Path>,
    device: &Device,
) -> Result<(VqModel, ModelConfig), ModelError> {
    let bytes = std::fs::read(weights).map_err(|e| ModelError::Io(format!("reading {}: {e}", weights.display())))?;
    let cfg = match config {
        Some(p) => Some(std::fs::read(p).map_err(|e| ModelError::Io(format!("reading {}: {e}", p.display())))?),
        None => None,
    };
    load_model_bytes(&bytes, cfg.as_deref(), device).map_err(|e| match e {
        ModelError::Weights(m) => ModelError::Weights(format!("{}: {m}", weights.display())),
        other => other,
    })
}

/// Sampling options of the refiner.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RefinerOptions {
    /// Code selection (argmin, or temperature + top-k in missing cells).
    pub sampling: Sampling,
    /// Seed of the sampling RNG.
    pub seed: u64,
    /// A latent cell counts as missing when more than this fraction of its pixels is missing.
    pub missing_cell_threshold: f32,
    /// Keep the guidance where it was observed and use the model's output only in missing
    /// pixels (default). The paper's model regenerates every pixel, which drifts the observed
    /// part of the frame away from the map; `false` reproduces that behaviour.
    #[serde(default = "default_true")]
    pub keep_observed: bool,
}

fn default_true() -> bool {
    true
}

impl Default for RefinerOptions {
    fn default() -> Self {
        Self { sampling: Sampling::Argmin, seed: 0, missing_cell_threshold: 0.5, keep_observed: true }
    }
}

/// The learned refiner: packs the guidance, encodes, quantizes (sampling in missing cells),
/// decodes and unpacks. Inputs of any size are padded (as missing) to a multiple of the
/// downsampling factor and the output cropped back.
#[derive(Debug)]
pub struct VqRefiner {
    model: VqModel,
    config: ModelConfig,
    options: RefinerOptions,
    rng: ChaCha8Rng,
    device: Device,
}

impl VqRefiner {
    /// Wraps a model.
    pub fn new(model: VqModel, config: ModelConfig, options: RefinerOptions, device: Device) -> Self {
        let rng = ChaCha8Rng::seed_from_u64(options.seed);
        Self { model: model.valid(), config, options, rng, device }
    }

    /// Loads from a safetensors file (+ optional config JSON file) on the default device.
    pub fn from_files(weights: &Path, config: Option<&Path>, options: RefinerOptions) -> Result<Self, ModelError> {
        let device = crate::default_device();
        let (model, config) = load_model(weights, config, &device)?;
        Ok(Self::new(model, config, options, device))
    }

    /// Loads from in-memory safetensors bytes (e.g. `include_bytes!`) on the default device.
    pub fn from_bytes(weights: &[u8], config_json: Option<&[u8]>, options: RefinerOptions) -> Result<Self, ModelError> {
        let device = crate::default_device();
        let (model, config) = load_model_bytes(weights, config_json, &device)?;
        Ok(Self::new(model, config, options, device))
    }

    /// The model configuration.
    pub fn config(&self) -> &ModelConfig {
        &self.config
    }

    /// Changes the sampling options and reseeds the RNG.
    pub fn set_options(&mut self, options: RefinerOptions) {
        self.rng = ChaCha8Rng::seed_from_u64(options.seed);
        self.options = options;
    }

    /// Completes one frame: `frame` + `missing` (row-major, true = missing) -> complete frame.
    pub fn complete(&mut self, frame: &RgbdFrame, missing: &[bool]) -> Result<RgbdFrame, ModelError> {
        let (w, h) = (frame.width() as usize, frame.height() as usize);
        if missing.len() != w * h {
            return Err(ModelError::Input(format!("mask has {} values for a {w}x{h} frame", missing.len())));
        }
        let f = self.config.downsample_factor();
        let (pw, ph) = (w.div_ceil(f) * f, h.div_ceil(f) * f);
        let (padded, mask) = pad_frame(frame, missing, pw, ph);
        let x = pack(&[&padded], &[Some(mask.as_slice())], &self.config.depth, &self.device)?;
        let cells = missing_cells(&mask, pw, ph, f, self.options.missing_cell_threshold);
        let z = self.model.encode(x);
        let q = quantize(&self.model, z, self.options.sampling, Some(&cells), self.config.beta, &mut self.rng)?;
        let out = self.model.decode(q.z_q);
        let full = unpack(out, &self.config.depth)?.pop().ok_or_else(|| ModelError::Input("empty output".into()))?;
        let mut out = crop_frame(&full, w, h);
        if self.options.keep_observed {
            keep_observed(&mut out, frame, missing);
        }
        Ok(out)
    }
}

/// Copies the observed pixels (`!missing`) of `guidance` into `out` (same size).
fn keep_observed(out: &mut RgbdFrame, guidance: &RgbdFrame, missing: &[bool]) {
    let colour = out.colour.data.iter_mut().zip(&guidance.colour.data);
    let depth = out.depth_m.data.iter_mut().zip(&guidance.depth_m.data);
    for ((c, d), _) in colour.zip(depth).zip(missing).filter(|(_, m)| !**m) {
        *c.0 = *c.1;
        *d.0 = *d.1;
    }
}

fn pad_frame(frame: &RgbdFrame, missing: &[bool], pw: usize, ph: usize) -> (RgbdFrame, Vec<bool>) {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    if (pw, ph) == (w, h) {
        return (frame.clone(), missing.to_vec());
    }
    let mut out = RgbdFrame::empty(pw as u32, ph as u32);
    let mut mask = vec![true; pw * ph];
    for y in 0..h {
        for x in 0..w {
            out.colour.data[y * pw + x] = frame.colour.data[y * w + x];
            out.depth_m.data[y * pw + x] = frame.depth_m.data[y * w + x];
            mask[y * pw + x] = missing[y * w + x];
        }
    }
    (out, mask)
}

fn crop_frame(frame: &RgbdFrame, w: usize, h: usize) -> RgbdFrame {
    let pw = frame.width() as usize;
    if pw == w && frame.height() as usize == h {
        return frame.clone();
    }
    let colour = (0..h).flat_map(|y| (0..w).map(move |x| (y, x))).map(|(y, x)| frame.colour.data[y * pw + x]).collect();
    let depth = (0..h).flat_map(|y| (0..w).map(move |x| (y, x))).map(|(y, x)| frame.depth_m.data[y * pw + x]).collect();
    RgbdFrame {
        colour: Image { width: w as u32, height: h as u32, data: colour },
        depth_m: Image { width: w as u32, height: h as u32, data: depth },
    }
}

impl Refiner for VqRefiner {
    type Error = ModelError;

    /// Sampling draws are seeded per frame from `options.seed ^ guidance.seed`, so a frame's
    /// result does not depend on what was refined before it (resumed runs equal uninterrupted ones).
    fn refine(&mut self, guidance: &Guidance) -> Result<RgbdFrame, ModelError> {
        self.rng = ChaCha8Rng::seed_from_u64(self.options.seed ^ guidance.seed);
        self.complete(&guidance.frame, &guidance.missing)
    }
}
