use thiserror::Error;

/// Errors of the map crate (persistence and configuration).
#[derive(Debug, Error)]
pub enum MapError {
    /// The underlying reader or writer failed.
    #[error("map I/O failed: {0}")]
    Io(#[from] std::io::Error),
    /// The stream does not start with the map magic bytes.
    #[error("not an SGAM map: magic bytes {found:?} (expected {expected:?})")]
    BadMagic {
        /// The first bytes found.
        found: Vec<u8>,
        /// The expected magic.
        expected: Vec<u8>,
    },
    /// The format version is not one this build reads.
    #[error("unsupported map format version {found} (this build reads version {supported})")]
    UnsupportedVersion {
        /// Version in the stream.
        found: u32,
        /// Version this build reads.
        supported: u32,
    },
    /// The stream ended before the declared content.
    #[error("map stream truncated: {0}")]
    Truncated(String),
    /// The CRC-32 over the content does not match the stored one.
    #[error("map checksum mismatch: stored {stored:#010x}, computed {computed:#010x} (file corrupt)")]
    ChecksumMismatch {
        /// Checksum stored in the stream.
        stored: u32,
        /// Checksum of the bytes read.
        computed: u32,
    },
    /// A configuration value is out of range.
    #[error("invalid map configuration: {0}")]
    InvalidConfig(String),
    /// The stream is well formed but holds values no map can contain (a block key outside the
    /// supported range, a non-finite voxel).
    #[error("invalid map content: {0}")]
    InvalidContent(String),
}
