use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use crate::IoError;

static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Writes `path` atomically: `f` writes into a temporary file in the same folder
/// (`.<name>.tmp-<pid>-<n>`), which is flushed, fsynced and then renamed over `path`. Parent
/// folders are created. If `f` or any step fails the temporary file is removed and `path` is left
/// as it was (absent or the previous complete version), so a crash never leaves a half-written
/// file under the target name.
pub fn write_atomic(path: &Path, f: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>) -> Result<(), IoError> {
    let name = path
        .file_name()
        .ok_or_else(|| IoError::invalid(path, "cannot write: the path has no file name"))?
        .to_string_lossy()
        .into_owned();
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir).map_err(|e| IoError::io(&dir, e))?;
    let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}.tmp-{}-{n}", std::process::id()));
    let result = write_then_rename(&tmp, path, f);
    if result.is_err() {
        // Best effort: the temporary file may not exist if creating it failed.
        let _ = std::fs::remove_file(&tmp);
    } else if let Ok(d) = File::open(&dir) {
        // Persist the rename itself (directory entry); not all platforms support this.
        let _ = d.sync_all();
    }
    result
}

fn write_then_rename(
    tmp: &Path,
    path: &Path,
    f: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> Result<(), IoError> {
    let file = File::create(tmp).map_err(|e| IoError::io(tmp, e))?;
    let mut w = BufWriter::new(file);
    f(&mut w).map_err(|e| IoError::io(path, e))?;
    w.flush().map_err(|e| IoError::io(path, e))?;
    let file = w.into_inner().map_err(|e| IoError::io(path, e.into_error()))?;
    file.sync_all().map_err(|e| IoError::io(path, e))?;
    drop(file);
    std::fs::rename(tmp, path).map_err(|e| IoError::io(path, e))
}
