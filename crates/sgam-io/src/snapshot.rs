//! Snapshot files: one versioned, checksummed container holding a run's state and its map, so an
//! interrupted run resumes exactly where it stopped.
//!
//! ```text
//! magic "SGAMSNAP" | u32 version | u64 n | n bytes of state (JSON) | payload (the map)
//! | u32 CRC-32 (IEEE) of every preceding byte
//! ```
//! The state's meaning belongs to the caller (the pipeline's run config); the payload is opaque
//! here (the map's own versioned format). The checksum covers the whole file, so a flipped bit
//! anywhere is an error, never a silently different run.

use std::io::Write;
use std::path::Path;

use crate::IoError;

/// The first bytes of every snapshot file.
pub const SNAPSHOT_MAGIC: &[u8; 8] = b"SGAMSNAP";

/// The bytes of a snapshot of format `version`.
pub fn encode_snapshot(version: u32, state_json: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(state_json.len() + payload.len() + 24);
    bytes.extend_from_slice(SNAPSHOT_MAGIC);
    bytes.extend_from_slice(&version.to_le_bytes());
    bytes.extend_from_slice(&(state_json.len() as u64).to_le_bytes());
    bytes.extend_from_slice(state_json);
    bytes.extend_from_slice(payload);
    let crc = crc32fast::hash(&bytes);
    bytes.extend_from_slice(&crc.to_le_bytes());
    bytes
}

/// Writes a snapshot atomically (see [`crate::write_atomic`]).
pub fn write_snapshot(path: &Path, version: u32, state_json: &[u8], payload: &[u8]) -> Result<(), IoError> {
    write_snapshot_with(path, version, state_json, |w| w.write_all(payload))
}

/// Writes a snapshot atomically whose payload `payload` writes, straight to the file through
/// the checksum: a large map is never held twice in memory.
pub fn write_snapshot_with(
    path: &Path,
    version: u32,
    state_json: &[u8],
    payload: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<(), IoError> {
    crate::write_atomic(path, |w| {
        let mut out = Crc32Writer { w, crc: crc32fast::Hasher::new() };
        out.write_all(SNAPSHOT_MAGIC)?;
        out.write_all(&version.to_le_bytes())?;
        out.write_all(&(state_json.len() as u64).to_le_bytes())?;
        out.write_all(state_json)?;
        payload(&mut out)?;
        let crc = out.crc.finalize();
        out.w.write_all(&crc.to_le_bytes())
    })
}

/// A writer that keeps the CRC-32 of what passes through it.
struct Crc32Writer<'a, W: Write> {
    w: &'a mut W,
    crc: crc32fast::Hasher,
}

impl<W: Write> Write for Crc32Writer<'_, W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.w.write(buf)?;
        self.crc.update(&buf[..n]);
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.w.flush()
    }
}

/// Splits snapshot `bytes` (`path` names the file in errors) into its state and payload after
/// checking the magic, that the format is `version` (an error names both versions otherwise)
/// and the checksum over the whole file.
pub fn parse_snapshot<'a>(path: &Path, bytes: &'a [u8], version: u32) -> Result<(&'a [u8], &'a [u8]), IoError> {
    let bad = |msg: String| IoError::Format { path: path.to_path_buf(), msg };
    if bytes.len() < 8 || &bytes[..8] != SNAPSHOT_MAGIC {
        return Err(bad("not an sgam snapshot".into()));
    }
    if bytes.len() < 24 {
        return Err(bad(format!("truncated ({} bytes)", bytes.len())));
    }
    let stored = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
    if stored != version {
        // format 1 had no version field: the state's length followed the magic, then its JSON
        let len =
            u64::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11], bytes[12], bytes[13], bytes[14], bytes[15]]);
        let v1 = len.checked_add(16).is_some_and(|end| end <= bytes.len() as u64) && bytes[16] == b'{';
        return Err(bad(if v1 {
            format!(
                "snapshot format 1 (written by an older sgam, without a checksum over the run's state); this build \
                 resumes format {version} only"
            )
        } else if stored < version {
            format!(
                "snapshot format version {stored} (written by an older sgam); this build resumes format {version} \
                 only: finish the run with the sgam that started it, or start a new run"
            )
        } else {
            format!("snapshot format version {stored} (this build reads {version}; written by a newer sgam?)")
        }));
    }
    let body = bytes.len() - 4;
    let stored_crc = u32::from_le_bytes([bytes[body], bytes[body + 1], bytes[body + 2], bytes[body + 3]]);
    let computed = crc32fast::hash(&bytes[..body]);
    if stored_crc != computed {
        return Err(bad(format!(
            "checksum mismatch (stored {stored_crc:#010x}, computed {computed:#010x}): the file is corrupt"
        )));
    }
    let mut len8 = [0u8; 8];
    len8.copy_from_slice(&bytes[12..20]);
    let len = u64::from_le_bytes(len8);
    if len > (body - 20) as u64 {
        return Err(bad(format!("corrupt header (state of {len} bytes in a {} byte file)", bytes.len())));
    }
    let state_end = 20 + len as usize;
    Ok((&bytes[20..state_end], &bytes[state_end..body]))
}

/// Reads `path` and splits it as [`parse_snapshot`] does, returning owned state and payload.
pub fn read_snapshot(path: &Path, version: u32) -> Result<(Vec<u8>, Vec<u8>), IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::Io { path: path.to_path_buf(), source: e })?;
    let (state, payload) = parse_snapshot(path, &bytes, version)?;
    Ok((state.to_vec(), payload.to_vec()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn valid() -> Vec<u8> {
        encode_snapshot(3, br#"{"steps":4}"#, &[9u8; 40])
    }

    #[test]
    fn a_snapshot_round_trips() {
        let bytes = valid();
        let (state, payload) = parse_snapshot(Path::new("s.bin"), &bytes, 3).unwrap();
        assert_eq!((state, payload), (&br#"{"steps":4}"#[..], &[9u8; 40][..]));
    }

    #[test]
    fn a_streamed_snapshot_has_the_bytes_of_an_encoded_one() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.bin");
        write_snapshot_with(&path, 3, br#"{"steps":4}"#, |w| {
            w.write_all(&[9u8; 15])?;
            w.write_all(&[9u8; 25])
        })
        .unwrap();
        assert!(std::fs::read(&path).unwrap() == valid());
    }

    #[test]
    fn another_version_is_refused_with_both_versions_named() {
        let bytes = encode_snapshot(2, b"{}", b"");
        let e = parse_snapshot(Path::new("s.bin"), &bytes, 3).unwrap_err().to_string();
        assert!(e.contains("s.bin") && e.contains("version 2") && e.contains("format 3"), "{e}");
        let mut v1 = SNAPSHOT_MAGIC.to_vec();
        v1.extend_from_slice(&2u64.to_le_bytes());
        v1.extend_from_slice(b"{}");
        v1.extend_from_slice(&[0u8; 8]);
        let e = parse_snapshot(Path::new("s.bin"), &v1, 3).unwrap_err().to_string();
        assert!(e.contains("format 1"), "{e}");
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

        #[test]
        fn arbitrary_bytes_never_panic(mut bytes in prop::collection::vec(any::<u8>(), 0..256), magic in any::<bool>()) {
            if magic && bytes.len() >= 12 {
                bytes[..8].copy_from_slice(SNAPSHOT_MAGIC);
                bytes[8..12].copy_from_slice(&3u32.to_le_bytes());
            }
            let _ = parse_snapshot(Path::new("snapshot.bin"), &bytes, 3);
        }

        #[test]
        fn any_flipped_byte_or_cut_is_an_error(pos in 0.0f64..1.0, x in 1u8..=255, cut in 0.0f64..1.0) {
            let good = valid();
            let mut bytes = good.clone();
            let i = ((bytes.len() - 1) as f64 * pos) as usize;
            bytes[i] ^= x;
            prop_assert!(parse_snapshot(Path::new("snapshot.bin"), &bytes, 3).is_err(), "byte {} flipped was accepted", i);
            let short = &good[..((good.len() - 1) as f64 * cut) as usize];
            prop_assert!(parse_snapshot(Path::new("snapshot.bin"), short, 3).is_err());
        }
    }
}
