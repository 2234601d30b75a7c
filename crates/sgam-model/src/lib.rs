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

pub mod bank;
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
pub mod nhwc;
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
    /// A model, context or training configuration outside its valid range.
    #[error("invalid {what} config: {problem}")]
    Config {
        /// Which configuration (a preset's name, "context", "training").
        what: String,
        /// What is wrong with it.
        problem: String,
    },
    /// The model lacks a part an operation needs (a code head, a context, ray intrinsics).
    #[error("{operation} needs {part}, which this model or call does not have")]
    MissingPart {
        /// The part, e.g. "a code head".
        part: &'static str,
        /// What needs it.
        operation: &'static str,
    },
    /// Inputs whose sizes do not fit together.
    #[error("{what}: expected {expected}, got {got}")]
    Shape {
        /// Which input.
        what: &'static str,
        /// The size it must have.
        expected: String,
        /// The size it has.
        got: String,
    },
    /// A call with nothing to work on.
    #[error("{0}: empty batch")]
    EmptyBatch(&'static str),
    /// Training diverged: the loss is not finite.
    #[error("the loss became {loss} at step {step}")]
    Diverged {
        /// The loss value.
        loss: f32,
        /// The step (1-based) whose loss it is.
        step: u64,
    },
    /// A tensor could not be read back from the device.
    #[error("reading a tensor back from the device: {0}")]
    TensorRead(String),
    /// A tensor the operation needs is not in the weights.
    #[error("the weights have no tensor {0}")]
    MissingTensor(String),
    /// Tensors that do not fit the model (names, shapes, non-finite values), one line each.
    #[error("weights: {} problem(s): {}", problems.len(), problems.join("; "))]
    WeightsMismatch {
        /// One line per tensor.
        problems: Vec<String>,
    },
    /// A tensor that cannot be stored as asked (non-finite values, f16 overflow).
    #[error("tensor {name}: {problem}; refusing to write it")]
    Unwritable {
        /// The tensor.
        name: String,
        /// Why.
        problem: String,
    },
    /// Bytes that do not parse (safetensors, the embedded config JSON).
    #[error("{what}: {msg}")]
    Format {
        /// What was being parsed.
        what: &'static str,
        /// The parser's message.
        msg: String,
    },
    /// An error about the contents of a named file.
    #[error("{}: {error}", path.display())]
    InFile {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong with it.
        error: Box<ModelError>,
    },
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
    /// A [`ModelError::Config`] error of configuration `what`.
    pub fn config(what: impl Into<String>, problem: impl Into<String>) -> Self {
        ModelError::Config { what: what.into(), problem: problem.into() }
    }

    /// A [`ModelError::Shape`] error.
    pub fn shape(what: &'static str, expected: impl std::fmt::Display, got: impl std::fmt::Display) -> Self {
        ModelError::Shape { what, expected: expected.to_string(), got: got.to_string() }
    }

    /// This error, said of the file at `path` (an error already about a file is kept as it is).
    pub fn in_file(self, path: &std::path::Path) -> Self {
        match self {
            e @ (ModelError::InFile { .. } | ModelError::Io { .. } | ModelError::Checkpoint { .. }) => e,
            e => ModelError::InFile { path: path.to_path_buf(), error: Box::new(e) },
        }
    }

    /// The error beneath any [`ModelError::InFile`] wrappers.
    pub fn innermost(&self) -> &ModelError {
        match self {
            ModelError::InFile { error, .. } => error.innermost(),
            e => e,
        }
    }

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

#[cfg(test)]
mod error_tests {
    use super::ModelError;
    use std::path::Path;

    #[test]
    fn in_file_names_the_file_once_and_keeps_the_kind() {
        let e = ModelError::MissingTensor("code_head.weight".into()).in_file(Path::new("a/m.safetensors"));
        assert_eq!(e.to_string(), "a/m.safetensors: the weights have no tensor code_head.weight");
        assert!(matches!(e.innermost(), ModelError::MissingTensor(n) if n == "code_head.weight"));
        // wrapping again (an outer loader) keeps the first, more precise file
        let again = e.in_file(Path::new("b.safetensors"));
        assert_eq!(again.to_string(), "a/m.safetensors: the weights have no tensor code_head.weight");
        // errors that already name their file are not wrapped
        let io = ModelError::io(Path::new("c.bin"), std::io::Error::other("gone")).in_file(Path::new("d"));
        assert!(matches!(io, ModelError::Io { ref path, .. } if path == Path::new("c.bin")), "{io}");
    }

    #[test]
    fn typed_errors_say_what_was_expected_and_what_came() {
        let e = ModelError::shape("the missing mask", "65536 values for a 256x256 frame", 12);
        assert_eq!(e.to_string(), "the missing mask: expected 65536 values for a 256x256 frame, got 12");
        let e = ModelError::WeightsMismatch { problems: vec!["unused tensor x".into(), "missing y".into()] };
        assert_eq!(e.to_string(), "weights: 2 problem(s): unused tensor x; missing y");
        let e = ModelError::Diverged { loss: f32::NAN, step: 7 };
        assert_eq!(e.to_string(), "the loss became NaN at step 7");
    }
}
