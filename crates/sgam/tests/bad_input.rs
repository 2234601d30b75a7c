//! The bad-input suite, by class: corrupt files per format, bad options per kind,
//! interrupted writes, concurrent runs, resume mismatches, non-finite weights. Every failing case
//! asserts a non-zero exit code (not a signal), no "panicked at" in stderr, and a message that
//! names the option or the file. Sizes are tiny (32 px worlds, the tiny model) so the suite
//! stays fast.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

fn sgam(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sgam")).args(args).output().expect("run sgam")
}

fn spawn(args: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_sgam"))
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn sgam")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs `sgam args`; asserts a clean failure (exit code 1 or 2, no panic) whose message holds
/// every one of `names`; returns stderr.
fn fails(args: &[&str], names: &[&str]) -> String {
    let out = sgam(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        matches!(out.status.code(), Some(1 | 2)),
        "sgam {args:?}: expected a clean failure, got {:?}:\n{err}",
        out.status
    );
    assert!(!err.contains("panicked at"), "sgam {args:?} panicked:\n{err}");
    for n in names {
        assert!(err.contains(n), "sgam {args:?}: the message does not name '{n}':\n{err}");
    }
    err
}

/// Runs `sgam args`; asserts success; returns stderr.
fn ok(args: &[&str]) -> String {
    let out = sgam(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "sgam {args:?} failed:\n{err}");
    err
}

/// Arguments of a tiny world: 32 px, push-pull stand-in, no GIF.
fn world(out: &Path, steps: &str) -> Vec<String> {
    ["generate", "--res", "32", "--refiner", "null", "--no-video", "--steps", steps, "--out", s(out)]
        .map(String::from)
        .to_vec()
}

/// `base` with the options of `extra` appended; an option of `base` that `extra` sets again
/// (also as `--opt=value`) is dropped with its value first (clap refuses repeats).
fn with(mut base: Vec<String>, extra: &[&str]) -> Vec<String> {
    for opt in extra.iter().filter(|x| x.starts_with("--")).map(|x| x.split('=').next().unwrap_or(x)) {
        if let Some(i) = base.iter().position(|x| x == opt) {
            base.drain(i..(i + 2).min(base.len()));
        }
    }
    base.extend(extra.iter().map(|x| x.to_string()));
    base
}

fn refs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

/// Tiny stage-1 training arguments for `run` (one checkpoint per step).
fn tiny_training(run: &Path, steps: &str) -> Vec<String> {
    let a = ["train", "stage1", "--run", s(run), "--steps", steps, "--preset", "tiny", "--batch", "1", "--crop", "32"];
    let b = ["--scenes", "2", "--ckpt-every", "1", "--val-every", "1000"];
    a.iter().chain(b.iter()).map(|x| x.to_string()).collect()
}

/// A tiny model file (f32, config embedded) with `value` written over its first weight.
fn tiny_model(path: &Path, seed: u64, value: Option<f32>) {
    let cfg = sgam_model::ModelConfig::tiny();
    let model = sgam_model::VqModel::new(&cfg, seed, &sgam_model::default_device()).unwrap();
    sgam_model::refiner::save_model(&model, &cfg, path, sgam_model::params::WeightPrecision::F32).unwrap();
    if let Some(v) = value {
        let mut bytes = std::fs::read(path).unwrap();
        let header = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        bytes[8 + header..12 + header].copy_from_slice(&v.to_le_bytes());
        std::fs::write(path, bytes).unwrap();
    }
}

fn rgb_count(run: &Path) -> usize {
    std::fs::read_dir(run.join("rgb")).map(|d| d.count()).unwrap_or(0)
}

fn transforms_frames(run: &Path) -> usize {
    sgam_io::read_nerf_transforms(&run.join("transforms.json")).unwrap().frames.len()
}

fn temp_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if e.path().is_dir() {
                stack.push(e.path());
            } else if name.contains(".tmp-") {
                out.push(e.path());
            }
        }
    }
    out
}

/// Waits (at most 120 s) until `path` exists.
fn wait_for(path: &Path, child: &mut Child) {
    let start = Instant::now();
    while !path.exists() {
        assert!(child.try_wait().unwrap().is_none(), "the process ended before {} appeared", path.display());
        assert!(start.elapsed() < Duration::from_secs(120), "{} never appeared", path.display());
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn corrupt_files_per_format_are_clean_errors_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let out = t.join("w");
    // colour PNG, depth NPY / PNG of an RGB seed
    let junk_png = t.join("junk.png");
    std::fs::write(&junk_png, b"\x89PNG\r\n\x1a\n not really").unwrap();
    let good_png = t.join("rgb.png");
    sgam_io::write_rgb_png(&good_png, &sgam_core::Image::filled(32, 32, [0.5f32; 3])).unwrap();
    let junk_npy = t.join("depth.npy");
    std::fs::write(&junk_npy, b"\x93NUMPY\x01\x00garbage").unwrap();
    let seed = |rgb: &Path, depth: &Path| {
        // --res applies to synthetic seeds only: the world's options without it
        let mut a: Vec<String> = world(&out, "1");
        let res = a.iter().position(|x| x == "--res").unwrap();
        a.drain(res..res + 2);
        a.extend(["--seed-rgb", s(rgb), "--seed-depth", s(depth), "--intrinsics", "30,30,16,16"].map(String::from));
        a
    };
    fails(&refs(&seed(&junk_png, &junk_npy)), &["junk.png"]);
    fails(&refs(&seed(&good_png, &junk_npy)), &["depth.npy"]);
    // a run that failed before writing anything leaves no folder behind
    assert!(!out.exists(), "{} was left behind", out.display());
    fails(&refs(&seed(&good_png, &junk_png)), &["junk.png"]);
    // PLY: garbage, a non-finite vertex
    let ok_ply = t.join("ok.ply");
    let tri = |p: &Path, c: &str| {
        let text = format!(
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
             element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n{c} 1 0\n3 0 1 2\n"
        );
        std::fs::write(p, text).unwrap();
    };
    tri(&ok_ply, "0");
    let nan_ply = t.join("nan.ply");
    tri(&nan_ply, "nan");
    let junk_ply = t.join("junk.ply");
    std::fs::write(&junk_ply, b"ply\nformat ascii 1.0\nelement vertex 99\n").unwrap();
    fails(&["eval", "mesh", s(&junk_ply), s(&ok_ply)], &["junk.ply"]);
    fails(&["eval", "mesh", s(&nan_ply), s(&ok_ply)], &["nan.ply", "non-finite"]);
    fails(&["eval", "mesh", s(t), s(&ok_ply)], &[s(t)]);
    // safetensors: garbage, NaN weights (generate, export, stage-2 --init)
    let junk_model = t.join("junk.safetensors");
    std::fs::write(&junk_model, b"{\"not\": \"weights\"}").unwrap();
    let nan_model = t.join("nan.safetensors");
    tiny_model(&nan_model, 1, Some(f32::NAN));
    for m in [&junk_model, &nan_model] {
        let a = ["generate", "--res", "32", "--steps", "1", "--out", s(&out), "--refiner", "model", "--model", s(m)];
        fails(&a, &[m.file_name().unwrap().to_str().unwrap()]);
    }
    let e = fails(&["train", "export", s(&nan_model), s(&t.join("e.safetensors"))], &["nan.safetensors", "NaN"]);
    assert!(e.contains("non-finite"), "{e}");
    assert!(!t.join("e.safetensors").exists());
    let mut a = tiny_training(&t.join("s2"), "1");
    a[1] = "stage2".into();
    a.extend(["--init".to_string(), s(&nan_model).to_string()]);
    fails(&refs(&a), &["nan.safetensors", "NaN"]);
    // a model configuration beyond memory
    let huge = t.join("huge.json");
    let mut cfg = serde_json::to_value(sgam_model::ModelConfig::tiny()).unwrap();
    cfg["ch"] = serde_json::json!(1_000_000);
    std::fs::write(&huge, serde_json::to_vec(&cfg).unwrap()).unwrap();
    let mut a = tiny_training(&t.join("huge"), "1");
    a.extend(["--model-config".to_string(), s(&huge).to_string()]);
    fails(&refs(&a), &["huge.json", "ch 1000000"]);
    // pose files
    let poses = t.join("poses.txt");
    std::fs::write(&poses, "1 2 3\nnot a pose\n").unwrap();
    let mut a = world(&out, "2");
    a.extend(["--trajectory", "file", "--trajectory-file", s(&poses)].map(String::from));
    fails(&refs(&a), &["poses.txt"]);
    // a checkpoint to convert that is a folder, or garbage
    fails(&["convert-checkpoint", s(t), s(&t.join("c.safetensors"))], &["is a folder"]);
    let junk_ckpt = t.join("junk.ckpt");
    std::fs::write(&junk_ckpt, b"PK\x03\x04 garbage").unwrap();
    fails(&["convert-checkpoint", s(&junk_ckpt), s(&t.join("c.safetensors"))], &["junk.ckpt"]);
}

#[test]
fn corrupt_run_states_are_refused_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("run");
    let mut a = world(&run, "4");
    a.extend(["--stop-after", "2"].map(String::from));
    ok(&refs(&a));
    let snap = run.join("snapshot.bin");
    let good = std::fs::read(&snap).unwrap();
    // one flipped bit in the state's JSON (the resolution), in the map, the file cut short,
    // and the first format (no version, no checksum)
    let at = good.windows(8).position(|w| w == b"\"res\":32").unwrap() + 7;
    let cases: Vec<(Vec<u8>, &str)> = vec![
        (
            {
                let mut b = good.clone();
                b[at] ^= 1;
                b
            },
            "checksum",
        ),
        (
            {
                let mut b = good.clone();
                let n = b.len();
                b[n - 100] ^= 0x10;
                b
            },
            "checksum",
        ),
        (good[..good.len() / 2].to_vec(), "snapshot.bin"),
        (
            {
                let mut b = good[..8].to_vec();
                b.extend(13u64.to_le_bytes());
                b.extend(b"{\"abc\":12345}");
                b
            },
            "format 1",
        ),
        (b"not a snapshot at all".to_vec(), "not an sgam snapshot"),
    ];
    for (bytes, what) in cases {
        std::fs::write(&snap, &bytes).unwrap();
        fails(&["generate", "--resume", s(&run)], &["snapshot.bin", what]);
    }
    std::fs::write(&snap, &good).unwrap();
    // a keyframe the snapshot lists but the folder lost
    std::fs::remove_file(run.join("depth/00001.npy")).unwrap();
    fails(&["generate", "--resume", s(&run)], &["00001.npy"]);

    // training checkpoints: a flipped byte in any file, a state whose usage record is cut short
    // (with a manifest rewritten to match), the first layout
    let t = tmp.path().join("s1");
    ok(&refs(&tiny_training(&t, "1")));
    let model = t.join("ckpt/model.safetensors");
    let weights = std::fs::read(&model).unwrap();
    let mut flipped = weights.clone();
    let n = flipped.len();
    flipped[n - 3] ^= 0x40;
    std::fs::write(&model, &flipped).unwrap();
    fails(&refs(&tiny_training(&t, "2")), &["model.safetensors", "CRC-32"]);
    std::fs::write(&model, &weights).unwrap();
    let state_path = t.join("ckpt/state.json");
    let mut state: serde_json::Value = serde_json::from_slice(&std::fs::read(&state_path).unwrap()).unwrap();
    state["usage"]["counts"] = serde_json::json!([0, 1]);
    let bytes = serde_json::to_vec(&state).unwrap();
    std::fs::write(&state_path, &bytes).unwrap();
    let manifest_path = t.join("ckpt/manifest.json");
    let mut manifest: serde_json::Value = serde_json::from_slice(&std::fs::read(&manifest_path).unwrap()).unwrap();
    manifest["files"]["state.json"] = serde_json::json!({"bytes": bytes.len(), "crc32": crc32fast::hash(&bytes)});
    std::fs::write(&manifest_path, serde_json::to_vec(&manifest).unwrap()).unwrap();
    fails(&refs(&tiny_training(&t, "2")), &["state.json", "usage"]);
    let legacy = tmp.path().join("legacy");
    std::fs::create_dir_all(&legacy).unwrap();
    std::fs::write(legacy.join("optim_model.bpk"), b"x").unwrap();
    std::fs::write(legacy.join("config.json"), b"{}").unwrap();
    fails(&refs(&tiny_training(&legacy, "2")), &["older sgam", "--init"]);
    // a dataset folder's record of its options
    let ds = tmp.path().join("ds");
    std::fs::create_dir_all(&ds).unwrap();
    std::fs::write(ds.join("synth.json"), b"[1, 2").unwrap();
    fails(
        &["synth", "--out", s(&ds), "--scenes", "1", "--res", "16", "--grid", "1", "--objects", "5"],
        &["synth.json"],
    );
}

#[test]
fn bad_options_are_refused_before_work_naming_the_option() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let out = t.join("w");
    let file = t.join("file");
    std::fs::write(&file, b"x").unwrap();
    let png = t.join("rgb.png");
    sgam_io::write_rgb_png(&png, &sgam_core::Image::filled(32, 32, [0.5f32; 3])).unwrap();
    let npy = t.join("d.npy");
    sgam_io::write_npy_f32(&npy, &sgam_core::Image::filled(32, 32, 2.0f32)).unwrap();
    let generator = |extra: &[&str]| -> Vec<String> { with(world(&out, "2"), extra) };
    let cases: Vec<(Vec<String>, &str)> = vec![
        // generate: every numeric option, with an upper bound where memory grows with it
        (generator(&["--res", "0"]), "--res 0"),
        (generator(&["--res", "100000"]), "--res 100000"),
        (generator(&["--steps", "1000000000000"]), "--steps"),
        (generator(&["--steps", "0"]), "--steps 0"),
        (generator(&["--grid", "100000"]), "--grid"),
        (generator(&["--step", "1e30"]), "--step"),
        (generator(&["--step", "NaN"]), "--step NaN"),
        (generator(&["--radius=-1"]), "--radius -1"),
        (generator(&["--radius", "inf"]), "--radius inf"),
        (generator(&["--temperature", "NaN"]), "--temperature NaN"),
        (generator(&["--temperature=-1"]), "--temperature -1"),
        (generator(&["--temperature", "inf"]), "--temperature inf"),
        (generator(&["--ground-snap", "NaN"]), "--ground-snap NaN"),
        (generator(&["--ground-snap=-0.5"]), "--ground-snap -0.5"),
        (generator(&["--top-k", "10000000"]), "--top-k"),
        (generator(&["--within-temperature", "NaN"]), "--within-temperature NaN"),
        (generator(&["--within-temperature=-1"]), "--within-temperature -1"),
        (generator(&["--k-sources", "0"]), "--k-sources 0"),
        (generator(&["--source-radius=-1"]), "--source-radius -1"),
        (generator(&["--source-radius", "NaN"]), "--source-radius NaN"),
        (generator(&["--voxel-size", "1e-9"]), "--voxel-size"),
        (generator(&["--trunc-voxels", "0"]), "--trunc-voxels 0"),
        (generator(&["--depth-max", "NaN"]), "--depth-max NaN"),
        (generator(&["--weight-cap", "0.5"]), "--weight-cap 0.5"),
        (generator(&["--snapshot-every", "0"]), "--snapshot-every 0"),
        (generator(&["--depth-png", "--depth-max", "100"]), "--depth-png"),
        // generate: combinations that would be silently ignored
        (generator(&["--seed-depth", s(&npy)]), "--seed-rgb"),
        (generator(&["--intrinsics", "30,30,16,16"]), "--seed-rgb"),
        (generator(&["--seed-template", s(t), "--seed-google-earth", s(t)]), "--seed-template and --seed-google-earth"),
        (generator(&["--trajectory", "file"]), "--trajectory-file"),
        (generator(&["--trajectory-file", s(&file)]), "--trajectory file"),
        (generator(&["--model", s(&file)]), "--model"),
        (generator(&["--bank", "bundled"]), "--bank is used only by the learned refiner"),
        (
            ["generate", "--steps", "2", "--out", s(&out), "--seed-rgb", s(&png), "--seed-depth", s(&npy)]
                .iter()
                .chain(&["--intrinsics", "30,30,16,16", "--bank", "bundled"])
                .map(|a| a.to_string())
                .collect(),
            "--bank bundled",
        ),
        (
            ["generate", "--res", "32", "--steps", "2", "--out", s(&out), "--bank", s(&t.join("no-such.bin"))]
                .map(String::from)
                .to_vec(),
            "--bank",
        ),
        (generator(&["--seed-rgb", s(&png), "--seed-depth", s(&npy), "--intrinsics", "1e-30,30,16,16"]), "fx"),
        (generator(&["--seed-rgb", s(&png), "--seed-depth", s(&npy), "--intrinsics", "30,30,16,1e6"]), "cy"),
        // fuse
        (
            vec![
                "fuse".into(),
                s(t).into(),
                "--out".into(),
                s(&t.join("m.ply")).into(),
                "--voxel-size".into(),
                "1e-9".into(),
            ],
            "--voxel-size",
        ),
        (
            vec![
                "fuse".into(),
                s(t).into(),
                "--out".into(),
                s(&t.join("m.ply")).into(),
                "--voxel-size".into(),
                "NaN".into(),
            ],
            "--voxel-size NaN",
        ),
        (
            vec![
                "fuse".into(),
                s(t).into(),
                "--out".into(),
                s(&t.join("m.ply")).into(),
                "--depth-min".into(),
                "5".into(),
            ],
            "--depth-min 5",
        ),
        (
            vec![
                "fuse".into(),
                s(t).into(),
                "--out".into(),
                s(&t.join("m.ply")).into(),
                "--save-map".into(),
                s(&file.join("map.bin")).into(),
            ],
            "--save-map",
        ),
        (vec!["fuse".into(), s(t).into(), "--out".into(), s(&t.join("m.xyz")).into()], "--out"),
        // two outputs on one file: the map would replace the mesh
        (
            vec![
                "fuse".into(),
                s(t).into(),
                "--out".into(),
                s(&t.join("m.ply")).into(),
                "--save-map".into(),
                s(&t.join(".").join("m.ply")).into(),
            ],
            "is the same file as --out",
        ),
        // options of the synthetic seed with a seed read from files
        (
            vec![
                "generate".into(),
                "--seed-template".into(),
                s(t).into(),
                "--res".into(),
                "64".into(),
                "--out".into(),
                s(&out).into(),
            ],
            "--res applies to synthetic seeds only",
        ),
        // synth
        (
            vec!["synth".into(), "--out".into(), s(&t.join("ds")).into(), "--objects".into(), "1000000000".into()],
            "--objects",
        ),
        (vec!["synth".into(), "--out".into(), s(&t.join("ds")).into(), "--res".into(), "100000".into()], "--res"),
        (vec!["synth".into(), "--out".into(), s(&t.join("ds")).into(), "--grid".into(), "0".into()], "--grid 0"),
        (vec!["synth".into(), "--out".into(), s(&t.join("ds")).into(), "--spp".into(), "0".into()], "--spp 0"),
        (
            vec![
                "synth".into(),
                "--out".into(),
                s(&t.join("ds")).into(),
                "--scenes".into(),
                "1".into(),
                "--split".into(),
                "1/1".into(),
            ],
            "--split",
        ),
        // eval
        (vec!["eval".into(), "one-step".into(), "--res".into(), "0".into()], "--res 0"),
        (vec!["eval".into(), "one-step".into(), "--views".into(), "0".into()], "--views 0"),
        // convert-checkpoint, bench
        (
            vec![
                "convert-checkpoint".into(),
                s(&file).into(),
                s(&t.join("o.safetensors")).into(),
                "--codebook".into(),
                "1000000000000".into(),
            ],
            "--codebook",
        ),
        (
            vec![
                "convert-checkpoint".into(),
                s(&file).into(),
                s(&t.join("o.safetensors")).into(),
                "--codebook".into(),
                "0".into(),
            ],
            "--codebook 0",
        ),
        (vec!["bench".into(), "integrate".into(), "--iterations".into(), "1000000000".into()], "--iterations"),
        (vec!["bench".into(), "integrate".into(), "--res".into(), "100000".into()], "--res"),
    ];
    for (a, name) in &cases {
        fails(&refs(a), &[name]);
    }
    for md in ["0", "NaN", "-1", "inf"] {
        let m = t.join("m.ply");
        let ply = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
                   element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
        std::fs::write(&m, ply).unwrap();
        fails(&["eval", "mesh", s(&m), s(&m), &format!("--max-distance={md}")], &["--max-distance"]);
    }
    // training: crops the model cannot take (these panicked), rates and weights
    let train = |extra: &[&str]| -> Vec<String> { with(tiny_training(&t.join("tr"), "2"), extra) };
    let train_cases: Vec<(Vec<String>, &str)> = vec![
        (train(&["--crop", "0"]), "--crop 0"),
        (train(&["--crop", "1"]), "--crop 1"),
        (train(&["--crop", "7"]), "--crop 7"),
        (train(&["--crop", "1000"]), "--crop 1000"),
        (train(&["--lr", "NaN"]), "--lr NaN"),
        (train(&["--lr=-1"]), "--lr -1"),
        (train(&["--lr", "0"]), "--lr 0"),
        (train(&["--lr", "inf"]), "--lr inf"),
        (train(&["--perceptual-weight=-1"]), "--perceptual-weight -1"),
        (train(&["--missing-weight", "0"]), "--missing-weight 0"),
        (train(&["--wide-holes", "2"]), "--wide-holes 2"),
        (train(&["--wide-holes", "0.5"]), "--wide-holes shapes stage 2's guidance"),
        (train(&["--batch", "0"]), "--batch 0"),
        (train(&["--lr-decay-from", "5"]), "--lr-decay-from 5"),
    ];
    for (a, name) in &train_cases {
        fails(&refs(a), &[name]);
    }
    let mut a = tiny_training(&t.join("tr"), "0");
    a.truncate(6);
    fails(&refs(&a), &["--steps 0"]);
    // nothing was created by the refused runs
    assert!(!out.exists() && !t.join("ds").exists() && !t.join("tr").join("ckpt").exists());
}

#[test]
fn non_finite_values_are_caught_where_they_enter_and_leave() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    // export to f16 refuses a value f16 cannot hold; 32-bit export keeps it
    let big = t.join("big.safetensors");
    tiny_model(&big, 2, Some(1e6));
    let e = fails(&["train", "export", s(&big), s(&t.join("b16.safetensors"))], &["overflows f16"]);
    assert!(e.contains("big.safetensors") || e.contains("b16.safetensors"), "{e}");
    assert!(!t.join("b16.safetensors").exists());
    ok(&["train", "export", s(&big), s(&t.join("b32.safetensors")), "--f32"]);
    // an infinite weight is refused like NaN
    let inf = t.join("inf.safetensors");
    tiny_model(&inf, 3, Some(f32::INFINITY));
    fails(&["train", "export", s(&inf), s(&t.join("i.safetensors")), "--f32"], &["inf.safetensors", "inf"]);
}

#[test]
fn interrupted_writes_leave_resumable_runs_and_no_temporary_files() {
    let tmp = tempfile::tempdir().unwrap();
    // generation killed (SIGKILL) mid-run: the early snapshot makes it resumable; temporary
    // files of killed writers are removed; outputs agree with each other
    let run = tmp.path().join("w");
    let args = world(&run, "40");
    let mut child = spawn(&refs(&args));
    wait_for(&run.join("snapshot.bin"), &mut child);
    std::thread::sleep(Duration::from_millis(300));
    child.kill().unwrap();
    child.wait().unwrap();
    std::fs::write(run.join(".snapshot.bin.tmp-99999-0"), b"half").unwrap();
    std::fs::write(run.join("rgb/.00007.png.tmp-99999-1"), b"half").unwrap();
    ok(&["generate", "--resume", s(&run)]);
    assert!(temp_files(&run).is_empty(), "{:?}", temp_files(&run));
    assert_eq!(rgb_count(&run), 41);
    assert_eq!(transforms_frames(&run), 41);

    // training killed repeatedly, at different moments (some during a checkpoint): every
    // resume finds a whole checkpoint and continues
    let t = tmp.path().join("s1");
    for delay_ms in [0u64, 150, 400] {
        let mut child = spawn(&refs(&tiny_training(&t, "400")));
        wait_for(&t.join("ckpt/manifest.json"), &mut child);
        std::thread::sleep(Duration::from_millis(delay_ms));
        child.kill().unwrap();
        child.wait().unwrap();
    }
    // the committed step (RUN/config.json may lag one commit behind when killed in between)
    let committed = ["ckpt", "ckpt.old"].iter().map(|d| t.join(d).join("state.json")).find(|p| p.exists()).unwrap();
    let state: serde_json::Value = serde_json::from_slice(&std::fs::read(committed).unwrap()).unwrap();
    let done = state["step"].as_u64().unwrap();
    let target = (done + 2).to_string();
    ok(&refs(&tiny_training(&t, &target)));
    let state: serde_json::Value = serde_json::from_slice(&std::fs::read(t.join("config.json")).unwrap()).unwrap();
    assert_eq!(state["step"].as_u64(), Some(done + 2));
    assert!(temp_files(&t).is_empty(), "{:?}", temp_files(&t));
    assert!(!t.join("ckpt.new").exists() && !t.join("ckpt.old").exists());

    // a save interrupted between its two renames: only ckpt.old is whole, ckpt.new is half
    std::fs::rename(t.join("ckpt"), t.join("ckpt.old")).unwrap();
    std::fs::create_dir_all(t.join("ckpt.new")).unwrap();
    std::fs::write(t.join("ckpt.new/model.safetensors"), b"half").unwrap();
    let target = (done + 3).to_string();
    ok(&refs(&tiny_training(&t, &target)));
    let state: serde_json::Value = serde_json::from_slice(&std::fs::read(t.join("ckpt/state.json")).unwrap()).unwrap();
    assert_eq!(state["step"].as_u64(), Some(done + 3));
}

#[test]
fn a_run_folder_is_owned_by_one_process_naming_the_holder() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("w");
    let mut holder = spawn(&refs(&world(&run, "2000")));
    wait_for(&run.join("snapshot.bin"), &mut holder);
    let pid = format!("pid {}", holder.id());
    // a second run on the folder, a resume of it, a forced run: all refused while it runs
    let e = fails(&refs(&world(&run, "3")), &["in use by another sgam process", &pid]);
    assert!(e.contains(s(&run)), "{e}");
    fails(&["generate", "--resume", s(&run)], &[&pid]);
    let mut forced = world(&run, "3");
    forced.push("--force".into());
    fails(&refs(&forced), &[&pid]);
    holder.kill().unwrap();
    holder.wait().unwrap();
    assert!(rgb_count(&run) >= 1);

    // training runs, and a synth dataset folder, likewise
    let t = tmp.path().join("s1");
    let mut trainer = spawn(&refs(&tiny_training(&t, "100000")));
    wait_for(&t.join("ckpt/manifest.json"), &mut trainer);
    fails(&refs(&tiny_training(&t, "100000")), &["in use", &format!("pid {}", trainer.id())]);
    let mut s2 = tiny_training(&t, "100000");
    s2[1] = "stage2".into();
    fails(&refs(&s2), &["in use"]);
    trainer.kill().unwrap();
    trainer.wait().unwrap();
}

#[test]
fn resume_mismatches_and_earlier_outputs_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    // a finished run whose snapshot was deleted is not overwritten without --force; with it,
    // no stale frame of the old run is left beside the new transforms.json
    let run = t.join("w");
    ok(&refs(&world(&run, "6")));
    // a finished run leaves no lock file
    assert!(!run.join(".sgam-lock").exists());
    std::fs::remove_file(run.join("snapshot.bin")).unwrap();
    fails(&refs(&world(&run, "2")), &["already holds files", "--force", s(&run)]);
    assert_eq!(rgb_count(&run), 7);
    let mut forced = world(&run, "2");
    forced.push("--force".into());
    ok(&refs(&forced));
    assert_eq!((rgb_count(&run), transforms_frames(&run)), (3, 3));
    // a run that holds a snapshot points at --resume
    fails(&refs(&world(&run, "2")), &["--resume"]);
    // options given with --resume are not silently dropped
    fails(&["generate", "--resume", s(&run), "--steps", "9", "--res", "64"], &["--steps", "--res"]);
    // the model file changed since the run started
    let m = t.join("m.safetensors");
    tiny_model(&m, 1, None);
    let mw = t.join("mw");
    let mut a = world(&mw, "3");
    let pos = a.iter().position(|x| x == "null").unwrap();
    a[pos] = "model".into();
    a.extend(["--model", s(&m), "--stop-after", "1"].map(String::from));
    ok(&refs(&a));
    tiny_model(&m, 2, None);
    fails(&["generate", "--resume", s(&mw)], &["m.safetensors", "not the file this run started with"]);

    // training: other options than the run's, stage 2 on a stage-1 run
    let s1 = t.join("s1");
    ok(&refs(&tiny_training(&s1, "1")));
    let mut a = tiny_training(&s1, "2");
    a[9] = "2".into(); // --batch 2
    assert_eq!(a[8], "--batch");
    fails(&refs(&a), &["--batch 1 (asked 2)"]);
    let mut a = tiny_training(&s1, "2");
    a.extend(["--lr", "0.001"].map(String::from));
    fails(&refs(&a), &["--lr"]);
    let mut a = tiny_training(&s1, "2");
    a[1] = "stage2".into();
    fails(&refs(&a), &["stage-1 run", "--init"]);
    // the same command resumes; steps a killed run logged after its checkpoint are logged once
    let log = s1.join("log.jsonl");
    let mut text = std::fs::read_to_string(&log).unwrap();
    text.push_str("{\"step\": 2, \"total\": 1.0}\n");
    std::fs::write(&log, text).unwrap();
    ok(&refs(&tiny_training(&s1, "2")));
    let steps: Vec<u64> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()?["step"].as_u64())
        .collect();
    assert_eq!(steps, vec![1, 2], "log.jsonl steps");
    // a run whose checkpoint is gone is not restarted over its weights
    let weights = std::fs::read(s1.join("model.safetensors")).unwrap();
    std::fs::remove_dir_all(s1.join("ckpt")).unwrap();
    fails(&refs(&tiny_training(&s1, "3")), &["model.safetensors", "no checkpoint to resume from"]);
    assert_eq!(std::fs::read(s1.join("model.safetensors")).unwrap(), weights);
    // a generate run folder is no training run
    fails(&refs(&tiny_training(&run, "1")), &["sgam generate` run folder", s(&run)]);
    assert!(!run.join("ckpt").exists());

    // synth: other render options than the folder's scenes; an empty transforms.json is not a
    // finished scene; one scene needs no --split
    let ds = t.join("ds");
    let synth = |res: &'static str| {
        ["synth", "--out", s(&ds), "--scenes", "1", "--res", res, "--grid", "2", "--objects", "10", "--spp", "1"]
    };
    let log = ok(&synth("16"));
    assert!(log.contains("1 scenes rendered"), "{log}");
    fails(&synth("24"), &["synth.json", "\"res\":16", "\"res\":24"]);
    let mut planar = synth("16").to_vec();
    planar.push("--planar-depth");
    fails(&planar, &["planar_depth"]);
    let scene = ds.join("train/scene_000000");
    std::fs::write(scene.join("transforms.json"), b"").unwrap();
    let log = ok(&synth("16"));
    assert!(log.contains("1 scenes rendered"), "an empty transforms.json counted as finished: {log}");
    assert_eq!(sgam_io::read_clevr_transforms(&scene.join("transforms.json")).unwrap().frames.len(), 4);
    let log = ok(&synth("16"));
    assert!(log.contains("1 already finished"), "{log}");
    // a deleted frame makes the scene unfinished: that frame is rendered again
    let frame = sgam_io::clevr_colour_path(&scene, 2);
    std::fs::remove_file(&frame).unwrap();
    let log = ok(&synth("16"));
    assert!(log.contains("1 scenes rendered"), "a scene with a deleted frame counted as finished: {log}");
    assert!(frame.exists());
    let legacy = t.join("legacy-ds");
    std::fs::create_dir_all(legacy.join("train/scene_000000")).unwrap();
    fails(&["synth", "--out", s(&legacy), "--scenes", "1", "--res", "16", "--grid", "1"], &["synth.json"]);
}

#[test]
fn error_messages_say_each_cause_once_and_name_targets_not_temporary_files() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    // a missing model: one "No such file", the path named
    let e = fails(
        &["eval", "one-step", "--refiner", "model", "--model", s(&t.join("absent.safetensors"))],
        &["absent.safetensors"],
    );
    assert!(e.matches("os error").count() <= 1 && e.contains("no such file"), "{e}");
    // a folder where a file is expected is called a folder, not missing
    for args in [
        vec!["eval", "one-step", "--refiner", "model", "--model", s(t)],
        vec!["train", "export", s(t), s(&t.join("x.safetensors"))],
    ] {
        let e = fails(&args, &["is a folder"]);
        assert!(!e.contains("no such"), "{e}");
    }
    // a write that fails names its target, not a temporary file
    let blocker = t.join("blocker");
    std::fs::write(&blocker, b"x").unwrap();
    let m = t.join("m.safetensors");
    tiny_model(&m, 1, None);
    let e = fails(&["train", "export", s(&m), s(&blocker.join("out.safetensors"))], &["out.safetensors"]);
    assert!(!e.contains(".tmp-"), "{e}");
    let e =
        fails(&["fuse", s(t), "--out", s(&t.join("m.ply")), "--save-map", s(&blocker.join("map.bin"))], &["map.bin"]);
    assert!(e.matches("os error").count() <= 1, "the cause is repeated: {e}");
    assert!(!t.join("m.ply").exists(), "the mesh was written before the bad --save-map was found");
}

#[test]
fn export_takes_a_decoder_only_from_a_model_with_the_same_codebook() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let cfg = sgam_model::ModelConfig::tiny();
    let dev = sgam_model::default_device();
    let f32w = sgam_model::params::WeightPrecision::F32;
    let sampler = sgam_model::VqModel::new(&cfg, 1, &dev).unwrap();
    // a decoder tuned for the sampler's codes: same codebook, other decoder weights
    let mut tuned = sgam_model::VqModel::new(&cfg, 2, &dev).unwrap();
    tuned.quantize = sampler.quantize.clone();
    let stranger = sgam_model::VqModel::new(&cfg, 3, &dev).unwrap();
    let (a, b, c) = (t.join("sampler.safetensors"), t.join("tuned.safetensors"), t.join("stranger.safetensors"));
    for (m, p) in [(&sampler, &a), (&tuned, &b), (&stranger, &c)] {
        sgam_model::refiner::save_model(m, &cfg, p, f32w).unwrap();
    }
    let out = t.join("out.safetensors");
    ok(&["train", "export", s(&a), s(&out), "--f32", "--decoder-from", s(&b)]);
    let read = |p: &Path| sgam_model::params::from_safetensors_bytes(&std::fs::read(p).unwrap()).unwrap().0;
    let (o, sa, tu) = (read(&out), read(&a), read(&b));
    let mut decoder = 0;
    for (name, v) in &o {
        let from_tuned = name.starts_with("decoder.") || name.starts_with("post_quant_conv.");
        let want = if from_tuned { &tu[name] } else { &sa[name] };
        assert_eq!(v, want, "{name}");
        decoder += from_tuned as usize;
    }
    assert!(decoder > 0 && o.keys().any(|n| n.starts_with("encoder.")));
    assert_ne!(o["decoder.conv_out.weight"], sa["decoder.conv_out.weight"]);
    // a decoder trained on other codes is refused, and nothing is written
    let refused = t.join("refused.safetensors");
    fails(&["train", "export", s(&a), s(&refused), "--decoder-from", s(&c)], &["stranger.safetensors", "codebook"]);
    assert!(!refused.exists());
}

#[test]
fn a_damaged_or_foreign_code_bank_is_refused_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let good = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/bank.bin")).unwrap();
    let damaged = t.join("damaged.bin");
    let mut b = good.clone();
    b[1000] ^= 1;
    std::fs::write(&damaged, &b).unwrap();
    let not_a_bank = t.join("not-a-bank.bin");
    std::fs::write(&not_a_bank, b"SGAMTSDF and more").unwrap();
    // the bundled bank holds 256 px frames
    let small = t.join("small");
    fails(
        &["generate", "--res", "128", "--steps", "2", "--no-video", "--out", s(&small), "--bank", "bundled"],
        &["--bank bundled", "256x256", "128x128"],
    );
    for (file, why) in [(&damaged, "checksum"), (&not_a_bank, "not a code bank")] {
        let out = t.join(file.file_stem().unwrap());
        fails(
            &["generate", "--res", "32", "--steps", "2", "--no-video", "--out", s(&out), "--bank", s(file)],
            &[s(file), why],
        );
    }
}
