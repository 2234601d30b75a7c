//! Helpers shared by the CLI integration tests: run the built `sgam` binary.
#![allow(dead_code, clippy::expect_used)]

use std::process::{Command, Output};

/// Runs `sgam` with `args`.
pub fn sgam(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sgam")).args(args).output().expect("run sgam")
}

/// Runs `sgam` with `args`, asserts success and returns its stderr.
pub fn ok(args: &[&str]) -> String {
    let out = sgam(args);
    assert!(out.status.success(), "sgam {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stderr).into_owned()
}
