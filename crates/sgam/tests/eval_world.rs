//! `sgam eval world`: the instrument the refiner is judged by.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::ok;

fn eval_json(args: &[&str]) -> serde_json::Value {
    let out = common::sgam(args);
    assert!(out.status.success(), "sgam {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout.lines().last().expect("a JSON line");
    serde_json::from_str(line).expect("valid JSON")
}

#[test]
fn the_oracle_judged_against_itself_is_identical_and_the_null_fill_is_not() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().to_str().unwrap();
    let common_args = ["eval", "world", "--seeds", "1", "--steps", "24", "--out", out, "--json"];
    let v = eval_json(&[&common_args[..], &["--refiner", "oracle"]].concat());
    assert_eq!(v["generated"], v["oracle"], "the same world must give the same statistics");
    assert!(v["generated"]["new_area_m2"].as_f64().unwrap() > 1.0, "{v}");
    let scene = &v["scene"];
    assert!(scene["jsd"].as_f64().unwrap().abs() < 1e-12, "{scene}");
    // identical region sets: each region's nearest neighbour is its copy (see sgam-metrics)
    assert_eq!(scene["one_nna"].as_f64().unwrap(), 0.0);
    let kid_self = v["kid"].as_f64().unwrap();
    // the null stand-in on the same seed and trajectory: its own run, the oracle's reused
    let n = eval_json(&[&common_args[..], &["--refiner", "null"]].concat());
    assert_eq!(n["oracle"], v["oracle"], "the oracle world is grown once and reused");
    assert_ne!(n["generated"], n["oracle"]);
    assert!(n["kid"].as_f64().unwrap() > kid_self, "null KID {} vs oracle {kid_self}", n["kid"]);
    // the null's world is kept under its label (`null`, plus `-g<M>` with the ground prior)
    let seed_dir = std::path::Path::new(out).join("seed-1000000");
    let null_worlds: Vec<_> = std::fs::read_dir(&seed_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("null") && !n.ends_with("-loop"))
        .collect();
    assert_eq!(null_worlds.len(), 1, "{null_worlds:?}");
    assert!(seed_dir.join(&null_worlds[0]).join("mesh.ply").exists());
    // finished worlds keep what reuse needs, not their resume files
    for world in [seed_dir.join(&null_worlds[0]), seed_dir.join("oracle")] {
        assert!(world.join("run.json").exists() && world.join("rgb").exists(), "{}", world.display());
        assert!(!world.join("snapshot.bin").exists() && !world.join("map.bin").exists(), "{}", world.display());
    }
    // the plain-text summary names the bars
    let text = ok(&[&common_args[..8], &["--refiner", "null"]].concat());
    assert!(text.contains("objects per 100 m2") && text.contains("(bar 0.5-1.5x)"), "{text}");
}

#[test]
fn eval_world_rejects_bad_options_clearly() {
    for (args, needle) in [
        (vec!["eval", "world", "--seeds", "0"], "--seeds"),
        (vec!["eval", "world", "--temperature", "NaN"], "--temperature"),
        (vec!["eval", "world", "--region-size", "0"], "--region-size"),
        (vec!["eval", "world", "--steps", "3"], "--steps"),
    ] {
        let out = common::sgam(&args);
        assert!(!out.status.success(), "{args:?} succeeded");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
    }
}
