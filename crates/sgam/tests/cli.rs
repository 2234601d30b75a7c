//! CLI wiring: training, the model refiner in generation, fusion errors.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;
use common::{ok, sgam};

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
    // The validation strip: four held-out pairs, one row each, input | output | target at the
    // 32-pixel crop.
    let strip = sgam_io::read_rgb(&run.join("val/step-000002.png")).unwrap();
    assert_eq!((strip.width, strip.height), (3 * 32, 4 * 32));
    // same command with more steps resumes
    let mut a = vec!["train", "stage1", "--run", r, "--steps", "3"];
    a.extend(common);
    ok(&a);
    let cfg: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("config.json")).unwrap()).unwrap();
    assert_eq!(cfg["step"], 3);
    let log = std::fs::read_to_string(run.join("log.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 3, "{log}");
    // Validation every 2 steps: only step 2's line has a PSNR, and it is one (colours in [0, 1]
    // put it at 0 dB or more).
    for (k, line) in log.lines().enumerate() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!(v["step"], k as u64 + 1);
        let val = v["val_psnr"].as_f64();
        assert_eq!(val.is_some(), k + 1 == 2, "{line}");
        assert!(val.is_none_or(|p| p.is_finite() && p >= 0.0), "{line}");
    }
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
    // Three 32 x 32 frames (the seed and two steps) with their depth; the strip shows all three
    // side by side, 4 px apart, pixel for pixel; the overview is 1280 x 800 and shows a mesh (not
    // one flat colour).
    let frames: Vec<_> = (0..3).map(|i| sgam_io::read_rgb(&world.join(format!("rgb/{i:05}.png"))).unwrap()).collect();
    for (i, f) in frames.iter().enumerate() {
        assert_eq!((f.width, f.height), (32, 32), "frame {i}");
        let depth = sgam_io::read_npy_f32(&world.join(format!("depth/{i:05}.npy"))).unwrap();
        assert_eq!((depth.width, depth.height), (32, 32), "depth {i}");
    }
    let strip = sgam_io::read_rgb(&world.join("strip.png")).unwrap();
    assert_eq!((strip.width, strip.height), (3 * 32 + 2 * 4, 32));
    for (k, f) in frames.iter().enumerate() {
        for v in 0..32 {
            for u in 0..32 {
                assert_eq!(strip.at(k as u32 * 36 + u, v), f.at(u, v), "strip tile {k} at ({u}, {v})");
            }
        }
    }
    let overview = sgam_io::read_rgb(&world.join("overview.png")).unwrap();
    assert_eq!((overview.width, overview.height), (1280, 800));
    assert!(overview.data.iter().any(|p| p != &overview.data[0]), "the overview is one flat colour");
    // one-step evaluation in its three modes: the missing pixels get the same model output
    // whether observed pixels are kept or regenerated; kept observed pixels score higher
    let eval = |mode: &[&str]| -> serde_json::Value {
        let mut a = vec!["eval", "one-step", "--refiner", "model", "--model", model.to_str().unwrap()];
        a.extend(["--scenes", "1", "--views", "2", "--res", "32", "--json"]);
        a.extend(mode);
        let out = sgam(&a);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_slice(&out.stdout).unwrap()
    };
    let keep = eval(&[]);
    let regen = eval(&["--regenerate-observed"]);
    let auto = eval(&["--autoencode"]);
    assert_eq!(keep["mode"], "keep-observed");
    assert_eq!(auto["mode"], "autoencode");
    assert_eq!(keep["psnr_missing"], regen["psnr_missing"]);
    assert!(keep["psnr_visible"].as_f64().unwrap() > regen["psnr_visible"].as_f64().unwrap());
    // Autoencoding hides nothing: every pixel is visible, so the whole-image PSNR is the
    // visible-pixel PSNR (the same sum) and there is no missing-pixel score; colours in [0, 1]
    // bound any PSNR below by 0 dB, and a model's output is never bit-identical (infinite).
    assert_eq!(auto["missing_fraction"].as_f64(), Some(0.0));
    let psnr = auto["psnr"].as_f64().unwrap();
    assert!(psnr.is_finite() && psnr >= 0.0, "{auto}");
    assert_eq!(auto["psnr"], auto["psnr_visible"]);
    assert!(auto["psnr_missing"].is_null(), "{auto}");
    assert!(keep["missing_fraction"].as_f64().unwrap() > 0.0, "{keep}");
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

#[test]
fn greedy_trajectory_steps_to_neighbouring_cells() {
    let tmp = tempfile::tempdir().unwrap();
    let world = tmp.path().join("g");
    let w = world.to_str().unwrap();
    ok(&["generate", "--out", w, "--res", "32", "--steps", "5", "--trajectory", "greedy", "--refiner", "null"]);
    let t: serde_json::Value = serde_json::from_slice(&std::fs::read(world.join("transforms.json")).unwrap()).unwrap();
    let frames = t["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 6);
    let xy: Vec<(f64, f64)> = frames
        .iter()
        .map(|f| (f["transform_matrix"][0][3].as_f64().unwrap(), f["transform_matrix"][1][3].as_f64().unwrap()))
        .collect();
    for (k, p) in xy.iter().enumerate().skip(1) {
        assert!(!xy[..k].contains(p), "pose {k} revisits {p:?}");
        // within one grid step (0.408 m, diagonals included) of an earlier pose
        assert!(xy[..k].iter().any(|q| (p.0 - q.0).abs() < 0.41 && (p.1 - q.1).abs() < 0.41), "pose {k} jumps");
    }
}
