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
    // each seed's own ratios to its oracle; one seed pooled is that seed
    let per_seed = &n["per_seed"][0];
    let (g, o) = (&per_seed["generated"], &per_seed["oracle"]);
    let area = |w: &serde_json::Value| w["new_area_m2"].as_f64().unwrap();
    let density = |w: &serde_json::Value| w["objects"].as_f64().unwrap() / area(w) * 100.0;
    let want = density(g) / density(o);
    let got = per_seed["ratio_to_oracle"]["objects_per_100m2"].as_f64().unwrap();
    assert!((got - want).abs() < 1e-6 * want.abs().max(1.0), "per seed {got} vs {want}: {per_seed}");
    assert_eq!(per_seed["ratio_to_oracle"], n["ratio_to_oracle"], "one seed pooled is that seed");
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
    // a 24-step world is too small to judge: the summary says so and gives no bar verdicts
    // (eval_report's unit test shows the bars of a world large enough)
    assert!(n["warning"].as_str().is_some_and(|w| w.contains("too small")), "{n}");
    let text = ok(&[&common_args[..8], &["--refiner", "null"]].concat());
    assert!(text.contains("objects per 100 m2") && text.contains("warning: these worlds are too small"), "{text}");
    assert!(!text.contains("(bar"), "{text}");
}

#[test]
fn eval_world_grows_its_model_world_with_the_within_temperature() {
    // `eval world` resolves its sampling options the way `generate` does (whose test shows the
    // option changes the draws): the model's world, and its loop run, are grown with the
    // within-class temperature given, the oracle's without any refiner options
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().to_str().unwrap();
    let v = eval_json(&[
        "eval",
        "world",
        "--seeds",
        "1",
        "--steps",
        "10",
        "--within-temperature",
        "0.25",
        "--out",
        out,
        "--json",
    ]);
    assert_eq!(v["within_temperature"].as_f64(), Some(0.25), "{v}");
    let seed_dir = std::path::Path::new(out).join("seed-1000000");
    let mut grown: Vec<String> =
        std::fs::read_dir(&seed_dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    grown.sort();
    let model: Vec<&String> = grown.iter().filter(|n| n.starts_with("model")).collect();
    assert_eq!(model.len(), 2, "the model's world and its loop run: {grown:?}");
    for name in model {
        let run: serde_json::Value =
            serde_json::from_slice(&std::fs::read(seed_dir.join(name).join("run.json")).unwrap()).unwrap();
        let options = &run["config"]["refiner"]["options"];
        let within = options["within_class_temperature"].as_f64().unwrap();
        assert!((within - 0.25).abs() < 1e-6, "{name}: {options}");
    }
    let oracle: serde_json::Value =
        serde_json::from_slice(&std::fs::read(seed_dir.join("oracle").join("run.json")).unwrap()).unwrap();
    assert_eq!(oracle["config"]["refiner"]["kind"], "oracle");
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
