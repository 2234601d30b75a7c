//! Atomic writes leave either the previous complete file or the new complete file, never a
//! partial one, and no temporary files behind.
#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::io::Write;

use sgam_io::{write_atomic, write_npy_f32, IoError};

fn entries(dir: &std::path::Path) -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

#[test]
fn successful_write_creates_parents_and_leaves_no_temp_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a/b/out.txt");
    write_atomic(&p, |w| w.write_all(b"complete")).unwrap();
    assert_eq!(std::fs::read(&p).unwrap(), b"complete");
    assert_eq!(entries(&dir.path().join("a/b")), vec!["out.txt"]);
    write_atomic(&p, |w| w.write_all(b"second")).unwrap();
    assert_eq!(std::fs::read(&p).unwrap(), b"second");
    assert_eq!(entries(&dir.path().join("a/b")), vec!["out.txt"]);
}

#[test]
fn failing_writer_never_leaves_a_partial_target() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("out.bin");
    // no previous file: nothing appears
    let e = write_atomic(&p, |w| {
        w.write_all(&[7u8; 100_000])?;
        Err(std::io::Error::other("simulated crash mid-write"))
    })
    .unwrap_err();
    assert!(matches!(e, IoError::Io { .. }));
    assert!(e.to_string().contains("out.bin") && e.to_string().contains("simulated crash"), "{e}");
    assert!(entries(dir.path()).is_empty(), "{:?}", entries(dir.path()));
    // a previous complete file stays intact
    std::fs::write(&p, b"old complete").unwrap();
    let _ = write_atomic(&p, |w| {
        w.write_all(b"new but partial")?;
        Err(std::io::Error::other("boom"))
    });
    assert_eq!(std::fs::read(&p).unwrap(), b"old complete");
    assert_eq!(entries(dir.path()), vec!["out.bin"]);
}

#[test]
fn unwritable_targets_are_errors_naming_the_path() {
    let dir = tempfile::tempdir().unwrap();
    // the parent "folder" is a file
    let blocker = dir.path().join("blocker");
    std::fs::write(&blocker, b"x").unwrap();
    let p = blocker.join("depth.npy");
    let e = write_npy_f32(&p, &sgam_core::Image::filled(2, 2, 1.0)).unwrap_err();
    assert!(e.to_string().contains("blocker"), "{e}");
    // a target that is a folder: the rename fails, the temp file is cleaned up
    let target = dir.path().join("is_a_dir");
    std::fs::create_dir(&target).unwrap();
    let e = write_atomic(&target, |w| w.write_all(b"x")).unwrap_err();
    assert!(e.to_string().contains("is_a_dir"), "{e}");
    assert_eq!(entries(dir.path()), vec!["blocker", "is_a_dir"]);
}
