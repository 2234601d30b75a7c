//! CLI wiring: training, the model refiner in generation, fusion errors.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::process::{Command, Output};

fn sgam(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sgam")).args(args).output().expect("run sgam")
}

fn ok(args: &[&str]) -> String {
    let out = sgam(args);
    assert!(out.status.success(), "sgam {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn tiny_training_run_resumes_and_its_model_drives_generation() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("s1");
    let r = run.to_str().unwrap();
    let common =
        ["--preset", "tiny", "--batch", "1", "--crop", "32", "--scenes", "2", "--ckpt-every", "1", "--val-every", "2"];
    let mut a = vec!["train", "stage1", "--run", r, "--steps", "2"];
    a.extend(common);
    ok(&a);
    let cfg: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("config.json")).unwrap()).unwrap();
    assert_eq!(cfg["step"], 2);
    assert!(run.join("val/step-000002.png").exists());
    // same command with more steps resumes
    let mut a = vec!["train", "stage1", "--run", r, "--steps", "3"];
    a.extend(common);
    ok(&a);
    let cfg: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("config.json")).unwrap()).unwrap();
    assert_eq!(cfg["step"], 3);
    let log = std::fs::read_to_string(run.join("log.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 3, "{log}");
    // stage 2 needs a starting model
    let out = sgam(&["train", "stage2", "--run", tmp.path().join("s2").to_str().unwrap(), "--steps", "1"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--init"));
    // the trained weights drive generation
    let model = run.join("model.safetensors");
    let world = tmp.path().join("world");
    ok(&[
        "generate",
        "--out",
        world.to_str().unwrap(),
        "--res",
        "32",
        "--steps",
        "2",
        "--refiner",
        "model",
        "--model",
        model.to_str().unwrap(),
        "--no-video",
    ]);
    assert!(world.join("rgb/00002.png").exists());
    // a corrupt model is a clear error
    let bad = tmp.path().join("bad.safetensors");
    std::fs::write(&bad, b"not a model").unwrap();
    let out = sgam(&[
        "generate",
        "--out",
        tmp.path().join("w2").to_str().unwrap(),
        "--res",
        "32",
        "--steps",
        "1",
        "--refiner",
        "model",
        "--model",
        bad.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("bad.safetensors"));
}

#[test]
fn fuse_rejects_bad_inputs_with_the_path() {
    let tmp = tempfile::tempdir().unwrap();
    let out = sgam(&["fuse", "/nonexistent/seq", "--out", tmp.path().join("m.ply").to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/seq"));
    let empty = tmp.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let out = sgam(&["fuse", empty.to_str().unwrap(), "--out", tmp.path().join("m.ply").to_str().unwrap()]);
    assert!(!out.status.success());
    let out = sgam(&["fuse", empty.to_str().unwrap(), "--out", tmp.path().join("m.xyz").to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("m.xyz"));
    assert!(!tmp.path().join("m.ply").exists(), "no output may be written on failure");
}
