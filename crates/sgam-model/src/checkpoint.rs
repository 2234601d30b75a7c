//! Multi-file checkpoints committed as a whole.
//!
//! A checkpoint is one folder, `RUN/<name>` (e.g. `RUN/ckpt`). [`commit_folder`] fills
//! `RUN/<name>.new`, writes its [`Manifest`] last (format version, and each file's size and
//! CRC-32), then swaps it in by renames: `<name>` -> `<name>.old`, `<name>.new` -> `<name>`,
//! `<name>.old` removed. A kill at any moment leaves either the previous or the new checkpoint
//! complete: [`committed_folder`] finds `<name>`, else `<name>.old` (a kill between the two
//! renames), and [`verify_folder`] checks every file against the manifest before anything is
//! read, so a folder mixed from two checkpoints, truncated or bit-flipped is an error, never a
//! silent resume.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::params::write_atomic;
use crate::ModelError;

/// The position of a trainer's random stream, as its state stores it (`rng_seed`, `rng_stream`,
/// `rng_word_pos`), so a resumed run draws what the uninterrupted run would have.
pub fn rng_position(rng: &rand_chacha::ChaCha8Rng) -> ([u8; 32], u64, u128) {
    (rng.get_seed(), rng.get_stream(), rng.get_word_pos())
}

/// A generator at a position [`rng_position`] gave.
pub fn rng_at(seed: [u8; 32], stream: u64, word_pos: u128) -> rand_chacha::ChaCha8Rng {
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::from_seed(seed);
    rng.set_stream(stream);
    rng.set_word_pos(word_pos);
    rng
}

/// Reads a trainer's committed checkpoint folder `dir` (already verified with
/// [`verify_folder`]): its `state.json` of format `version` (`what` names the trainer in errors)
/// and its `model.safetensors` weights.
pub fn read_trainer_state<S: serde::de::DeserializeOwned>(
    dir: &Path,
    what: &str,
    version: u32,
) -> Result<(S, BTreeMap<String, crate::params::NamedTensor>), ModelError> {
    let path = dir.join("state.json");
    let bytes = std::fs::read(&path).map_err(|e| ModelError::io(&path, e))?;
    // the version first: a state of another version may not parse as this one
    #[derive(Deserialize)]
    struct Versioned {
        version: u32,
    }
    let stored: Versioned = serde_json::from_slice(&bytes)
        .map_err(|e| ModelError::checkpoint(&path, format!("not a {what} state: {e}")))?;
    if stored.version != version {
        return Err(ModelError::checkpoint(
            &path,
            format!("state version {} (this build reads {version})", stored.version),
        ));
    }
    let state = serde_json::from_slice(&bytes)
        .map_err(|e| ModelError::checkpoint(&path, format!("not a {what} state: {e}")))?;
    let weights = dir.join("model.safetensors");
    let wbytes = std::fs::read(&weights).map_err(|e| ModelError::io(&weights, e))?;
    let tensors = crate::params::from_safetensors_bytes(&wbytes).map_err(|e| e.in_file(&weights))?.0;
    Ok((state, tensors))
}

/// File name of the manifest inside a checkpoint folder.
pub const MANIFEST: &str = "manifest.json";
/// Manifest format this build writes and reads.
pub const MANIFEST_VERSION: u32 = 1;
/// Manifests larger than this are not read (a corrupt or foreign file).
const MAX_MANIFEST_BYTES: u64 = 1 << 20;

/// Size and checksum of one file of a checkpoint.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileEntry {
    /// Length in bytes.
    pub bytes: u64,
    /// CRC-32 (IEEE) of the whole file.
    pub crc32: u32,
}

/// What `manifest.json` holds: written last, so its presence marks the folder complete.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always `"sgam-checkpoint"`.
    pub format: String,
    /// [`MANIFEST_VERSION`].
    pub version: u32,
    /// Every other file of the folder by name.
    pub files: BTreeMap<String, FileEntry>,
}

fn entry(path: &Path) -> Result<FileEntry, ModelError> {
    let bytes = std::fs::read(path).map_err(|e| ModelError::io(path, e))?;
    Ok(FileEntry { bytes: bytes.len() as u64, crc32: crc32fast::hash(&bytes) })
}

/// The folder `run_dir/<name>.<suffix>`.
fn sibling(run_dir: &Path, name: &str, suffix: &str) -> PathBuf {
    run_dir.join(format!("{name}.{suffix}"))
}

/// Writes the checkpoint folder `run_dir/<name>` as a whole: `fill` writes its files into the
/// folder it is given (`<name>.new`, empty), then the manifest is written and the folder swapped
/// in (see the module docs). Returns the committed folder.
pub fn commit_folder(
    run_dir: &Path,
    name: &str,
    fill: impl FnOnce(&Path) -> Result<(), ModelError>,
) -> Result<PathBuf, ModelError> {
    let (new, cur, old) = (sibling(run_dir, name, "new"), run_dir.join(name), sibling(run_dir, name, "old"));
    if new.exists() {
        std::fs::remove_dir_all(&new).map_err(|e| ModelError::io(&new, e))?;
    }
    std::fs::create_dir_all(&new).map_err(|e| ModelError::io(&new, e))?;
    fill(&new)?;
    let mut files = BTreeMap::new();
    for item in std::fs::read_dir(&new).map_err(|e| ModelError::io(&new, e))? {
        let item = item.map_err(|e| ModelError::io(&new, e))?;
        let file_name = item.file_name().to_string_lossy().into_owned();
        if file_name == MANIFEST || file_name.starts_with('.') {
            continue;
        }
        if !item.path().is_file() {
            return Err(ModelError::checkpoint(&item.path(), "checkpoints hold files only"));
        }
        files.insert(file_name, entry(&item.path())?);
    }
    let manifest = Manifest { format: "sgam-checkpoint".into(), version: MANIFEST_VERSION, files };
    let json = serde_json::to_vec_pretty(&manifest).map_err(|e| ModelError::state("serialising the manifest", e))?;
    write_atomic(&new.join(MANIFEST), &json)?;
    if cur.exists() {
        if old.exists() {
            std::fs::remove_dir_all(&old).map_err(|e| ModelError::io(&old, e))?;
        }
        std::fs::rename(&cur, &old).map_err(|e| ModelError::io(&cur, e))?;
    }
    std::fs::rename(&new, &cur).map_err(|e| ModelError::io(&new, e))?;
    if old.exists() {
        std::fs::remove_dir_all(&old).map_err(|e| ModelError::io(&old, e))?;
    }
    Ok(cur)
}

/// The committed checkpoint folder of `run_dir` to resume from: `<name>`, or `<name>.old` when a
/// commit was interrupted between its two renames; `None` when neither holds a manifest.
/// (`<name>.new` is never used: it may be unfinished.)
pub fn committed_folder(run_dir: &Path, name: &str) -> Option<PathBuf> {
    [run_dir.join(name), sibling(run_dir, name, "old")].into_iter().find(|p| p.join(MANIFEST).is_file())
}

/// Reads `dir`'s manifest and checks that every file it lists has its size and CRC-32, and that
/// no other file is present. Errors name the file.
pub fn verify_folder(dir: &Path) -> Result<Manifest, ModelError> {
    let path = dir.join(MANIFEST);
    let len = std::fs::metadata(&path).map_err(|e| ModelError::io(&path, e))?.len();
    if len > MAX_MANIFEST_BYTES {
        return Err(ModelError::checkpoint(&path, format!("{len} bytes, not a checkpoint manifest")));
    }
    let bytes = std::fs::read(&path).map_err(|e| ModelError::io(&path, e))?;
    let manifest: Manifest = serde_json::from_slice(&bytes)
        .map_err(|e| ModelError::checkpoint(&path, format!("not a checkpoint manifest: {e}")))?;
    if manifest.format != "sgam-checkpoint" || manifest.version != MANIFEST_VERSION {
        return Err(ModelError::checkpoint(
            &path,
            format!(
                "checkpoint format '{}' version {} (this build reads 'sgam-checkpoint' version {MANIFEST_VERSION})",
                manifest.format, manifest.version
            ),
        ));
    }
    for (name, want) in &manifest.files {
        if name.contains(['/', '\\']) || name.starts_with('.') {
            return Err(ModelError::checkpoint(&path, format!("bad file name '{name}'")));
        }
        let file = dir.join(name);
        if !file.is_file() {
            return Err(ModelError::checkpoint(&file, format!("missing (listed in {MANIFEST})")));
        }
        let got = entry(&file)?;
        if got != *want {
            return Err(ModelError::checkpoint(
                &file,
                format!(
                    "{} bytes, CRC-32 {:#010x}; the manifest records {} bytes, {:#010x} (the checkpoint is corrupt or \
                     mixed with another one)",
                    got.bytes, got.crc32, want.bytes, want.crc32
                ),
            ));
        }
    }
    for item in std::fs::read_dir(dir).map_err(|e| ModelError::io(dir, e))? {
        let item = item.map_err(|e| ModelError::io(dir, e))?;
        let file_name = item.file_name().to_string_lossy().into_owned();
        if file_name != MANIFEST && !file_name.starts_with('.') && !manifest.files.contains_key(&file_name) {
            return Err(ModelError::checkpoint(
                &item.path(),
                format!("not listed in {MANIFEST} (the checkpoint was changed after it was written)"),
            ));
        }
    }
    Ok(manifest)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), ModelError> {
        write_atomic(&dir.join(name), bytes)
    }

    #[test]
    fn a_commit_replaces_the_folder_as_a_whole_and_verifies() {
        let tmp = tempfile::tempdir().unwrap();
        commit_folder(tmp.path(), "ckpt", |d| write(d, "a.bin", b"one")).unwrap();
        let dir = committed_folder(tmp.path(), "ckpt").unwrap();
        assert_eq!(verify_folder(&dir).unwrap().files.len(), 1);
        commit_folder(tmp.path(), "ckpt", |d| {
            write(d, "a.bin", b"two")?;
            write(d, "b.bin", b"2")
        })
        .unwrap();
        let m = verify_folder(&tmp.path().join("ckpt")).unwrap();
        assert_eq!(m.files.keys().collect::<Vec<_>>(), ["a.bin", "b.bin"]);
        assert!(!tmp.path().join("ckpt.old").exists() && !tmp.path().join("ckpt.new").exists());
    }

    #[test]
    fn a_failed_fill_leaves_the_previous_checkpoint() {
        let tmp = tempfile::tempdir().unwrap();
        commit_folder(tmp.path(), "ckpt", |d| write(d, "a.bin", b"one")).unwrap();
        let err = commit_folder(tmp.path(), "ckpt", |d| {
            write(d, "a.bin", b"half")?;
            Err(ModelError::io(Path::new("a.bin"), std::io::Error::other("disk full")))
        })
        .unwrap_err();
        assert!(err.to_string().contains("disk full"));
        let dir = committed_folder(tmp.path(), "ckpt").unwrap();
        verify_folder(&dir).unwrap();
        assert_eq!(std::fs::read(dir.join("a.bin")).unwrap(), b"one");
    }

    #[test]
    fn an_interrupted_swap_resumes_from_the_old_folder() {
        let tmp = tempfile::tempdir().unwrap();
        commit_folder(tmp.path(), "ckpt", |d| write(d, "a.bin", b"one")).unwrap();
        // killed after the first rename: only ckpt.old (complete) and ckpt.new remain
        std::fs::rename(tmp.path().join("ckpt"), tmp.path().join("ckpt.old")).unwrap();
        std::fs::create_dir(tmp.path().join("ckpt.new")).unwrap();
        let dir = committed_folder(tmp.path(), "ckpt").unwrap();
        assert!(dir.ends_with("ckpt.old"));
        verify_folder(&dir).unwrap();
    }

    #[test]
    fn mixed_truncated_or_extra_files_are_errors_naming_the_file() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = commit_folder(tmp.path(), "ckpt", |d| {
            write(d, "model.bin", b"weights")?;
            write(d, "state.json", b"{}")
        })
        .unwrap();
        std::fs::write(dir.join("model.bin"), b"weightz").unwrap();
        let e = verify_folder(&dir).unwrap_err().to_string();
        assert!(e.contains("model.bin") && e.contains("CRC-32"), "{e}");
        std::fs::write(dir.join("model.bin"), b"weights").unwrap();
        verify_folder(&dir).unwrap();
        std::fs::write(dir.join("extra.bin"), b"x").unwrap();
        let e = verify_folder(&dir).unwrap_err().to_string();
        assert!(e.contains("extra.bin"), "{e}");
        std::fs::remove_file(dir.join("extra.bin")).unwrap();
        std::fs::remove_file(dir.join("state.json")).unwrap();
        let e = verify_folder(&dir).unwrap_err().to_string();
        assert!(e.contains("state.json") && e.contains("missing"), "{e}");
        std::fs::write(dir.join(MANIFEST), b"{\"format\": 1").unwrap();
        let e = verify_folder(&dir).unwrap_err().to_string();
        assert!(e.contains(MANIFEST), "{e}");
    }
}
