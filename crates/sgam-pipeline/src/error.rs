use thiserror::Error;

/// Errors of the pipeline. Each names what failed; file errors carry their path (from
/// `sgam-io`).
#[derive(Debug, Error)]
pub enum PipelineError {
    /// Reading or writing a file (keyframes, seeds, pose files, snapshots, caches).
    #[error(transparent)]
    Io(#[from] sgam_io::IoError),
    /// The map refused its parameters or its stored state.
    #[error(transparent)]
    Map(#[from] sgam_map::MapError),
    /// The model (loading, inference, target codes).
    #[error(transparent)]
    Model(#[from] sgam_model::ModelError),
    /// The model file (or the bundled model, `path` = `None`) cannot be loaded.
    #[error("{}", match path { Some(p) => format!("{}: cannot load the model", p.display()), None => "the bundled model (models/compact.safetensors) cannot be loaded".to_string() })]
    ModelLoad {
        /// The model file; `None` for the bundled model.
        path: Option<std::path::PathBuf>,
        /// Why it cannot be loaded.
        #[source]
        source: sgam_model::ModelError,
    },
    /// A keyframe read back from the run folder is inconsistent.
    #[error("keyframe {index}")]
    Keyframe {
        /// Index of the keyframe.
        index: usize,
        /// What is wrong with it.
        #[source]
        source: sgam_core::CoreError,
    },
    /// A generation step failed.
    #[error("step {index}")]
    Step {
        /// The step (keyframe index).
        index: usize,
        /// What failed.
        #[source]
        source: Box<PipelineError>,
    },
    /// The refiner failed to complete a guidance image.
    #[error("refiner failed")]
    Refiner(#[source] Box<dyn std::error::Error + Send + Sync>),
    /// An option or a combination of options that cannot work; the message names the option
    /// and the accepted range.
    #[error("{0}")]
    Config(String),
    /// A caller's output or display failed (see [`crate::RunObserver`]).
    #[error(transparent)]
    Output(Box<dyn std::error::Error + Send + Sync>),
    /// A file that exists but does not hold what it should (a pair cache, a snapshot's state).
    #[error("{}: {msg}", path.display())]
    Corrupt {
        /// The file concerned.
        path: std::path::PathBuf,
        /// What is wrong.
        msg: String,
    },
}

/// Result of the pipeline's fallible functions.
pub type Result<T, E = PipelineError> = std::result::Result<T, E>;

/// `Err(PipelineError::Config(..))` from a format string.
macro_rules! config_error {
    ($($arg:tt)*) => {
        return Err($crate::PipelineError::Config(format!($($arg)*)))
    };
}
pub(crate) use config_error;
