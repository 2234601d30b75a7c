use thiserror::Error;

/// Errors of the synthetic world.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum SynthError {
    /// A configuration value is unusable; the message names it.
    #[error("invalid synth configuration: {0}")]
    InvalidConfig(String),
}
