//! Guards every command runs before it starts work: option ranges (errors name the option and
//! the accepted range), run folders owned by one process (an advisory lock naming its holder),
//! folders with earlier outputs never overwritten without `--force`, output paths checked before
//! hours of work are spent, and temporary files of killed writers removed.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

/// Option ranges: the library's checks (NaN is never in range), so a command line and a
/// program get the same errors.
pub use sgam_pipeline::settings::{in_range, positive};

/// Refuses two output options naming one file: the second write would replace the first
/// output, and the command would still exit 0. `files` are `(option, path)`.
pub fn distinct_outputs(files: &[(&str, &Path)]) -> Result<()> {
    let key = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    for (i, (a, pa)) in files.iter().enumerate() {
        for (b, pb) in &files[..i] {
            if key(pa) == key(pb) {
                bail!("{a} {} is the same file as {b}: give each output its own path", pa.display());
            }
        }
    }
    Ok(())
}

/// Refuses a training `--run` folder that cannot be resumed but holds something a new run would
/// overwrite or mix with: a `sgam generate` run (its frames and run.json), or weights and logs of
/// a training whose checkpoint (`ckpt/` with its manifest) is gone. Call it when no checkpoint
/// was found; `outputs` are the files this trainer writes.
pub fn refuse_unresumable_run(run: &Path, outputs: &[&str]) -> Result<()> {
    if ["run.json", "snapshot.bin", "rgb", "mesh.ply"].iter().any(|f| run.join(f).exists()) {
        bail!(
            "--run {}: is a `sgam generate` run folder, not a training run; give training a folder of its own",
            run.display()
        );
    }
    let found: Vec<&str> = outputs.iter().copied().filter(|f| run.join(f).exists()).collect();
    if !found.is_empty() {
        bail!(
            "--run {}: holds {} but no checkpoint to resume from (ckpt/ or its manifest.json is gone); a new run \
             would overwrite them: move them away or choose another --run",
            run.display(),
            found.join(", ")
        );
    }
    Ok(())
}

/// Opens a run's JSON-lines log `name` for appending, first dropping the lines of steps after
/// `step` (what a run killed after its last checkpoint logged, which a resume from that
/// checkpoint does again): each step is logged once. A line's step is its `step` or
/// `report.step`; lines without one are kept.
pub fn open_step_log(run: &Path, name: &str, step: u64) -> Result<File> {
    let path = run.join(name);
    if let Ok(text) = std::fs::read_to_string(&path) {
        let step_of = |line: &str| {
            let v: serde_json::Value = serde_json::from_str(line).ok()?;
            v["step"].as_u64().or_else(|| v["report"]["step"].as_u64())
        };
        let kept: Vec<&str> = text.lines().filter(|l| step_of(l).is_none_or(|s| s <= step)).collect();
        if kept.len() != text.lines().count() {
            sgam_io::write_atomic(&path, |w| kept.iter().try_for_each(|l| writeln!(w, "{l}")))?;
        }
    }
    OpenOptions::new().create(true).append(true).open(&path).with_context(|| format!("{}: cannot open", path.display()))
}

/// Name of the lock file inside a run folder.
pub const LOCK_FILE: &str = ".sgam-lock";

/// Ownership of a run folder for the life of this value: an advisory lock (`flock`) on
/// `RUN/.sgam-lock`, which holds the owner's pid and command line. The kernel releases it when
/// the process ends, however it ends, so a stale file never blocks.
#[derive(Debug)]
pub struct RunLock {
    file: File,
    path: PathBuf,
    /// The folder, when this lock created it (removed again if the run left it empty).
    created: Option<PathBuf>,
}

impl RunLock {
    /// Creates `dir` if needed and takes its lock; an error naming the holder (pid and command)
    /// when another process has it.
    pub fn acquire(dir: &Path) -> Result<Self> {
        if dir.exists() && !dir.is_dir() {
            bail!("{}: not a folder (a run needs a folder)", dir.display());
        }
        let created = (!dir.exists()).then(|| dir.to_path_buf());
        std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create the run folder", dir.display()))?;
        let path = dir.join(LOCK_FILE);
        loop {
            let lock = Self::try_acquire(dir, &path)?;
            // a holder that finished between our open and our lock removed the file we locked:
            // lock the path's file again
            if same_file(&lock, &path) {
                return Ok(Self { file: lock, path, created });
            }
        }
    }

    fn try_acquire(dir: &Path, path: &Path) -> Result<File> {
        let path = path.to_path_buf();
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .with_context(|| format!("{}: cannot open the run folder's lock", path.display()))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let holder = std::fs::read_to_string(&path).unwrap_or_default();
                let holder = holder.trim();
                let holder = if holder.is_empty() { "pid unknown".to_string() } else { holder.to_string() };
                bail!(
                    "{} is in use by another sgam process ({holder}); wait for it to finish, or choose another folder",
                    dir.display()
                );
            }
            Err(std::fs::TryLockError::Error(e)) => {
                return Err(e).with_context(|| format!("{}: cannot lock the run folder", path.display()));
            }
        }
        let command: Vec<String> = std::env::args().collect();
        file.set_len(0).and_then(|_| write!(file, "pid {}: {}", std::process::id(), command.join(" "))).ok();
        Ok(file)
    }
}

/// Whether `file` is the file now at `path` (same device and inode).
fn same_file(file: &File, path: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (file.metadata(), std::fs::metadata(path)) {
        (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
        _ => false,
    }
}

impl Drop for RunLock {
    /// A finished (or failed) run leaves no lock file, and a folder this lock created that the
    /// run left empty is removed: a run that failed before writing anything leaves nothing.
    fn drop(&mut self) {
        // removed while still locked, so a waiting process re-checks and locks a fresh file
        let _ = std::fs::remove_file(&self.path);
        let _ = self.file.unlock();
        if let Some(dir) = &self.created {
            let _ = std::fs::remove_dir(dir); // only succeeds when empty
        }
    }
}

/// True for the temporary files of atomic writers (`.name.tmp-PID-N` of `sgam_io::write_atomic`,
/// `name.tmp-write` of older builds).
fn is_temp_file(name: &str) -> bool {
    (name.starts_with('.') && name.contains(".tmp-")) || name.ends_with(".tmp-write")
}

/// Removes the temporary files that killed writers left in `dir` and its `subdirs`. Call it only
/// while holding the folder's [`RunLock`] (no other writer is active then).
pub fn remove_stale_temp_files(dir: &Path, subdirs: &[&str]) -> Result<usize> {
    let mut removed = 0;
    for d in std::iter::once(dir.to_path_buf()).chain(subdirs.iter().map(|s| dir.join(s))) {
        let Ok(entries) = std::fs::read_dir(&d) else { continue };
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            if is_temp_file(&name) && entry.path().is_file() {
                std::fs::remove_file(entry.path())
                    .with_context(|| format!("{}: cannot remove a stale temporary file", entry.path().display()))?;
                removed += 1;
            }
        }
    }
    Ok(removed)
}

/// The entries of `dir` other than its lock and temporary files, sorted.
fn contents(dir: &Path) -> Result<Vec<String>> {
    let mut names = Vec::new();
    if !dir.exists() {
        return Ok(names);
    }
    for entry in std::fs::read_dir(dir).with_context(|| format!("{}: cannot list", dir.display()))? {
        let name = entry.with_context(|| format!("{}: cannot list", dir.display()))?.file_name();
        let name = name.to_string_lossy().into_owned();
        if name != LOCK_FILE && !is_temp_file(&name) {
            names.push(name);
        }
    }
    names.sort();
    Ok(names)
}

/// Makes `dir` (locked by the caller) ready for a new run: it must hold nothing, unless `force`,
/// which first removes the entries named in `outputs` (the previous run's outputs, a trailing
/// `*` matching any ending; other files are left). Errors name the folder and a few of its
/// entries.
pub fn claim_empty_folder(dir: &Path, force: bool, outputs: &[&str], hint: &str) -> Result<()> {
    let names = contents(dir)?;
    if names.is_empty() {
        return Ok(());
    }
    if !force {
        let shown: Vec<&str> = names.iter().take(5).map(String::as_str).collect();
        let more = if names.len() > 5 { format!(" and {} more", names.len() - 5) } else { String::new() };
        bail!(
            "{} already holds files ({}{more}); {hint}choose another folder, or pass --force to replace the previous \
             outputs",
            dir.display(),
            shown.join(", ")
        );
    }
    let is_output =
        |name: &str| outputs.iter().any(|o| o.strip_suffix('*').map_or(*o == name, |p| name.starts_with(p)));
    for name in names.iter().filter(|n| is_output(n)) {
        let p = dir.join(name);
        let r = if p.is_dir() { std::fs::remove_dir_all(&p) } else { std::fs::remove_file(&p) };
        r.with_context(|| format!("{}: cannot remove the previous output (--force)", p.display()))?;
    }
    Ok(())
}

/// Checks that `path` (given as `option`) can be written before any work is done: it is not a
/// folder, and its folder exists (or can be created) and accepts new files.
pub fn check_output_file(option: &str, path: &Path) -> Result<()> {
    if path.is_dir() {
        bail!("{option} {}: is a folder, not a file", path.display());
    }
    if path.file_name().is_none() {
        bail!("{option} {}: has no file name", path.display());
    }
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("{option} {}: cannot create its folder", path.display()))?;
    let probe = dir.join(format!(".sgam-probe-{}", std::process::id()));
    File::create(&probe).with_context(|| format!("{option} {}: its folder cannot be written", path.display()))?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

/// Checks that `path` (given as `option`) is an existing file: a folder or a missing path is
/// reported as what it is.
pub fn check_input_file(option: &str, path: &Path) -> Result<()> {
    match std::fs::metadata(path) {
        Ok(m) if m.is_dir() => bail!("{option} {}: is a folder, not a file", path.display()),
        Ok(_) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => bail!("{option} {}: no such file", path.display()),
        Err(e) => Err(e).with_context(|| format!("{option} {}: cannot read", path.display())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_reject_nan_and_name_the_option() {
        assert!(in_range("--x", 3, 1..=5).is_ok());
        let e = in_range("--res", 0u32, 16..=2048).unwrap_err().to_string();
        assert!(e.contains("--res 0") && e.contains("16..=2048"), "{e}");
        let e = in_range("--temperature", f32::NAN, 0.0..=100.0).unwrap_err().to_string();
        assert!(e.contains("--temperature NaN"), "{e}");
        for bad in [0.0, -1.0, f32::NAN, f32::INFINITY, 2.0] {
            assert!(positive("--radius", bad, 1.0).is_err(), "{bad}");
        }
        assert!(positive("--radius", 1.0, 1.0).is_ok());
    }

    #[test]
    fn a_locked_folder_names_its_holder_and_is_free_again_after_drop() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("run");
        let lock = RunLock::acquire(&dir).unwrap();
        let e = RunLock::acquire(&dir).unwrap_err().to_string();
        assert!(e.contains(&format!("pid {}", std::process::id())) && e.contains("in use"), "{e}");
        drop(lock);
        RunLock::acquire(&dir).unwrap();
    }

    #[test]
    fn a_folder_with_files_is_claimed_only_with_force_and_only_outputs_go() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        claim_empty_folder(dir, false, &[], "").unwrap();
        std::fs::write(dir.join(".x.tmp-1-0"), b"").unwrap();
        std::fs::write(dir.join(LOCK_FILE), b"").unwrap();
        claim_empty_folder(dir, false, &[], "").unwrap();
        std::fs::create_dir(dir.join("rgb")).unwrap();
        std::fs::write(dir.join("mesh-00025.ply"), b"").unwrap();
        std::fs::write(dir.join("notes.txt"), b"mine").unwrap();
        let e = claim_empty_folder(dir, false, &["rgb", "mesh-*"], "").unwrap_err().to_string();
        assert!(e.contains("notes.txt") && e.contains("--force"), "{e}");
        claim_empty_folder(dir, true, &["rgb", "mesh-*"], "").unwrap();
        assert!(!dir.join("rgb").exists() && !dir.join("mesh-00025.ply").exists() && dir.join("notes.txt").exists());
        assert_eq!(remove_stale_temp_files(dir, &["rgb"]).unwrap(), 1);
    }

    #[test]
    fn output_and_input_paths_are_checked_before_work() {
        let tmp = tempfile::tempdir().unwrap();
        assert!(check_output_file("--out", &tmp.path().join("a/b/mesh.ply")).is_ok());
        let e = check_output_file("--out", tmp.path()).unwrap_err().to_string();
        assert!(e.contains("is a folder"), "{e}");
        let file = tmp.path().join("f");
        std::fs::write(&file, b"").unwrap();
        let e = format!("{:#}", check_output_file("--save-map", &file.join("x.bin")).unwrap_err());
        assert!(e.contains("--save-map"), "{e}");
        let e = check_input_file("--model", tmp.path()).unwrap_err().to_string();
        assert!(e.contains("is a folder"), "{e}");
        let e = check_input_file("--model", &tmp.path().join("absent")).unwrap_err().to_string();
        assert!(e.contains("no such file"), "{e}");
    }
}
