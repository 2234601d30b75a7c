//! The generative sensing model of SGAM: a VQGAN-style encoder -> codebook -> decoder that
//! completes an incomplete RGB-D guidance image in one shot, its losses, trainers and the
//! [`VqRefiner`] the generator calls.
//!
//! # Concepts
//! - **Backend**: burn 0.22's dynamic [`Device`](burn::tensor::Device); [`default_device`] is the
//!   `flex` CPU backend, or `wgpu` with the `wgpu` cargo feature. Training runs the same modules
//!   after [`Module::train`](burn::module::Module::train) (autodiff).
//! - **Tensors** are `[B, C, H, W]`. Network input has 5 channels (RGB in `[-1, 1]`, normalised
//!   disparity `2s - 1`, missing mask), output 4 ([`packing`]).
//! - **Presets**: [`ModelConfig::paper`] (the authors' architecture, state-dict names equal to
//!   their Lightning keys) and [`ModelConfig::compact`] (our CPU design). The config travels with
//!   every checkpoint and weight file.
//! - **Weights** are safetensors files keyed by parameter path ([`params`]); f16 for shipping.
//! - **Quantizer** ([`quantize`]): argmin + straight-through, temperature sampling only in missing
//!   cells, usage statistics, k-means revival of dead codes.
//! - **Generative stage 2** ([`generative`]): the encoder trained with cross-entropy over the
//!   codes the frozen encoder gives the clean target, logits `-||z - e_k||^2 / tau`; the refiner
//!   samples `softmax(-d / (T tau))` in missing cells, iteratively for large holes.
//! - **Checkpoints** ([`checkpoint`]) are folders committed as a whole (written beside, swapped in
//!   by renames) with a manifest of sizes and CRC-32s checked on resume; weights with a
//!   non-finite value are neither loaded ([`params::load_named`]) nor written.
//! - **Determinism**: weights are initialised from a seed; sampling and training draw from a
//!   seeded `ChaCha8Rng` passed in.

pub mod blocks;
pub mod checkpoint;
pub mod config;
pub mod context;
pub mod context_train;
pub mod convert;
pub mod decoder_tune;
pub mod features;
pub mod flops;
pub mod generative;
pub mod loss;
pub mod lpips;
pub mod model;
pub mod packing;
pub mod params;
pub mod quantize;
pub mod refiner;
pub mod train;

pub use burn;
pub use config::{DepthCoding, ModelConfig};
pub use model::VqModel;
pub use quantize::Sampling;
pub use refiner::{RefinerOptions, VqRefiner};
pub use train::{train, PairSource, Stage, TrainConfig, TrainPair, TrainProgress, Trainer};

use thiserror::Error;

/// Errors of the model crate; messages name the offending file or value.
#[derive(Debug, Error)]
pub enum ModelError {
    /// An unusable model configuration.
    #[error("invalid model config: {0}")]
    Config(String),
    /// Bad input data (sizes, empty batches).
    #[error("invalid input: {0}")]
    Input(String),
    /// Weights that do not fit the model (names, shapes, non-finite values).
    #[error("weights: {0}")]
    Weights(String),
    /// Reading, creating or removing a file or folder failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or folder.
        path: std::path::PathBuf,
        /// The operating system's error.
        #[source]
        source: std::io::Error,
    },
    /// An atomic write (`sgam_io::write_atomic`) failed; the error names the file.
    #[error(transparent)]
    Write(#[from] sgam_io::IoError),
    /// A checkpoint file that exists but cannot be read or resumed.
    #[error("{}: {msg}", path.display())]
    Checkpoint {
        /// The file or folder.
        path: std::path::PathBuf,
        /// What is wrong with it.
        msg: String,
    },
    /// Training state (JSON, optimizer records) that cannot be serialised.
    #[error("{what}")]
    State {
        /// Which state.
        what: String,
        /// Why.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

impl ModelError {
    /// An [`ModelError::Io`] error on `path`.
    pub fn io(path: &std::path::Path, source: std::io::Error) -> Self {
        ModelError::Io { path: path.to_path_buf(), source }
    }

    /// A [`ModelError::Checkpoint`] error on `path`.
    pub fn checkpoint(path: &std::path::Path, msg: impl Into<String>) -> Self {
        ModelError::Checkpoint { path: path.to_path_buf(), msg: msg.into() }
    }

    /// A [`ModelError::State`] error: `what` could not be serialised because of `source`.
    pub fn state(what: impl Into<String>, source: impl std::fmt::Display) -> Self {
        ModelError::State { what: what.into(), source: source.to_string().into() }
    }
}

/// The default compute device: burn `flex` (CPU), or the default `wgpu` adapter when built with
/// the `wgpu` feature.
pub fn default_device() -> burn::tensor::Device {
    #[cfg(feature = "wgpu")]
    {
        burn::tensor::Device::wgpu(burn::tensor::DeviceKind::DefaultDevice)
    }
    #[cfg(not(feature = "wgpu"))]
    {
        burn::tensor::Device::flex()
    }
}
