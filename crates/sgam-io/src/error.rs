use std::path::{Path, PathBuf};

use thiserror::Error;

/// Every error of this crate names the file it concerns and what is wrong with it.
#[derive(Debug, Error)]
pub enum IoError {
    /// The operating system refused an operation (missing file, permission, disk full, ...).
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or folder concerned.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The file exists but cannot be decoded (corrupt PNG, truncated NPY, malformed JSON, ...).
    #[error("{}: {msg}", path.display())]
    Format {
        /// The file concerned.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// The file decodes but its content breaks a contract (non-rigid pose, colour/depth size
    /// mismatch, negative depth, a frame with no valid depth, ...).
    #[error("{}: {msg}", path.display())]
    Invalid {
        /// The file concerned.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// A folder matches none of the known sequence layouts.
    #[error("{}: unknown sequence layout; looked for {looked_for}", path.display())]
    UnknownLayout {
        /// The folder concerned.
        path: PathBuf,
        /// The files that were looked for.
        looked_for: String,
    },
    /// A sequence folder has a known layout but no usable frame.
    #[error("{}: empty sequence: {msg}", path.display())]
    EmptySequence {
        /// The folder concerned.
        path: PathBuf,
        /// What was looked for.
        msg: String,
    },
}

impl IoError {
    /// The file or folder the error concerns.
    pub fn path(&self) -> &Path {
        match self {
            IoError::Io { path, .. }
            | IoError::Format { path, .. }
            | IoError::Invalid { path, .. }
            | IoError::UnknownLayout { path, .. }
            | IoError::EmptySequence { path, .. } => path,
        }
    }

    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        IoError::Io { path: path.to_path_buf(), source }
    }

    pub(crate) fn format(path: &Path, msg: impl Into<String>) -> Self {
        IoError::Format { path: path.to_path_buf(), msg: msg.into() }
    }

    pub(crate) fn invalid(path: &Path, msg: impl Into<String>) -> Self {
        IoError::Invalid { path: path.to_path_buf(), msg: msg.into() }
    }
}
