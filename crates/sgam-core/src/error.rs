use thiserror::Error;

/// Errors raised when a value violates a core invariant.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum CoreError {
    /// A 4x4 matrix that should be a rigid transform is not one.
    #[error("not a rigid transform: {0}")]
    NotRigid(String),
    /// Camera intrinsics are unusable (non-positive focal length, zero size, non-finite).
    #[error("invalid intrinsics: {0}")]
    InvalidIntrinsics(String),
    /// Two images that must have the same size do not.
    #[error("size mismatch: {0}")]
    SizeMismatch(String),
}
