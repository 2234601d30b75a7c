//! Weights and training states under bad input: non-finite weights are neither
//! loaded nor written, f16 export refuses overflow, a diverging trainer stops with an error and
//! writes nothing, checkpoints commit as a whole and are verified on resume; property tests of
//! the safetensors parser, the checkpoint reader and the model configuration check.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;

use proptest::prelude::*;
use sgam_core::{Image, RgbdFrame};
use sgam_model::params::{from_safetensors_bytes, load_named, named_tensors, to_safetensors_bytes, WeightPrecision};
use sgam_model::train::{read_checkpoint, TrainError};
use sgam_model::{default_device, ModelConfig, ModelError, Stage, TrainConfig, TrainPair, Trainer, VqModel};

fn pairs(n: usize, size: u32) -> Vec<TrainPair> {
    (0..n)
        .map(|i| {
            let colour = Image::filled(size, size, [0.2 + 0.1 * i as f32, 0.5, 0.7]);
            let depth_m = Image {
                width: size,
                height: size,
                data: (0..size * size).map(|p| 8.0 + (p % size) as f32 * 0.1).collect(),
            };
            let f = RgbdFrame { colour, depth_m };
            TrainPair { input: f.clone(), missing: vec![false; (size * size) as usize], target: f }
        })
        .collect()
}

fn tiny_trainer(lr: f64) -> Trainer {
    let mut tc = TrainConfig::new(Stage::One, 10);
    tc.batch = 1;
    tc.crop = 32;
    tc.lr = lr;
    Trainer::new(&ModelConfig::tiny(), &tc).unwrap()
}

/// A run folder with one committed checkpoint of the tiny model, made once; copied per use.
fn checkpoint_template() -> &'static Path {
    static DIR: std::sync::OnceLock<tempfile::TempDir> = std::sync::OnceLock::new();
    DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let mut t = tiny_trainer(2e-4);
        t.step_on(&pairs(1, 32)).unwrap();
        t.save(dir.path()).unwrap();
        dir
    })
    .path()
}

fn copy_run(to: &Path) {
    for sub in ["", "ckpt"] {
        std::fs::create_dir_all(to.join(sub)).unwrap();
        for e in std::fs::read_dir(checkpoint_template().join(sub)).unwrap().flatten() {
            if e.path().is_file() {
                std::fs::copy(e.path(), to.join(sub).join(e.file_name())).unwrap();
            }
        }
    }
}

/// Rewrites `ckpt/manifest.json` to match the files now in `ckpt/` (as if they had been written
/// that way), so that the state's own checks are reached.
fn rewrite_manifest(run: &Path) {
    let dir = run.join("ckpt");
    let path = dir.join("manifest.json");
    let mut m: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let names: Vec<String> = m["files"].as_object().unwrap().keys().cloned().collect();
    for name in names {
        let bytes = std::fs::read(dir.join(&name)).unwrap();
        m["files"][&name] = serde_json::json!({"bytes": bytes.len(), "crc32": crc32(&bytes)});
    }
    std::fs::write(&path, serde_json::to_vec(&m).unwrap()).unwrap();
}

/// CRC-32 (IEEE), bitwise (the test does not depend on the crate's checksum code).
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

#[test]
fn non_finite_weights_are_neither_loaded_nor_written() {
    let device = default_device();
    let cfg = ModelConfig::tiny();
    let model = VqModel::new(&cfg, 1, &device).unwrap();
    let mut tensors = named_tensors(&model);
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let (name, t) = tensors.iter_mut().nth(3).unwrap();
        let name = name.clone();
        t.values[1] = bad;
        let e = load_named(VqModel::new(&cfg, 1, &device).unwrap(), &tensors, false, false).unwrap_err().to_string();
        assert!(e.contains(&name) && e.contains("index 1"), "{e}");
        let e = to_safetensors_bytes(&tensors, WeightPrecision::F32, None).unwrap_err().to_string();
        assert!(e.contains(&name) && e.contains("refusing"), "{e}");
        tensors.get_mut(&name).unwrap().values[1] = 0.0;
    }
    // f16: the largest finite value is written, one above it is refused (it would become inf)
    let (name, t) = tensors.iter_mut().next().unwrap();
    let name = name.clone();
    t.values[0] = 65504.0;
    let bytes = to_safetensors_bytes(&tensors, WeightPrecision::F16, None).unwrap();
    assert_eq!(from_safetensors_bytes(&bytes).unwrap().0[&name].values[0], 65504.0);
    tensors.get_mut(&name).unwrap().values[0] = -70000.0;
    let e = to_safetensors_bytes(&tensors, WeightPrecision::F16, None).unwrap_err().to_string();
    assert!(e.contains(&name) && e.contains("overflows f16"), "{e}");
    assert!(to_safetensors_bytes(&tensors, WeightPrecision::F32, None).is_ok());
}

#[test]
fn a_diverging_trainer_stops_with_an_error_and_writes_nothing() {
    // a NaN learning rate (the CLI refuses it; the library guards the values anyway)
    let mut t = tiny_trainer(f64::NAN);
    let batch = pairs(1, 32);
    let first = t.step_on(&batch).unwrap();
    assert!(first.total.is_finite(), "the first loss is computed before any update");
    let dir = tempfile::tempdir().unwrap();
    let e = t.save(dir.path()).unwrap_err();
    assert!(matches!(&e, TrainError::Diverged { what, .. } if what.contains("weight")), "{e}");
    assert!(!dir.path().join("ckpt").exists() && !dir.path().join("model.safetensors").exists());
    let e = t.step_on(&batch).unwrap_err();
    assert!(matches!(e, TrainError::Diverged { step: 2, .. }), "{e}");
    // train() validates its configuration first
    let mut tc = TrainConfig::new(Stage::One, 3);
    tc.lr = f64::NAN;
    let e = tc.validate(&ModelConfig::tiny()).unwrap_err().to_string();
    assert!(e.contains("lr NaN"), "{e}");
    tc.lr = 1e-4;
    tc.crop = 30;
    let e = tc.validate(&ModelConfig::tiny()).unwrap_err().to_string();
    assert!(e.contains("crop 30") && e.contains("multiple"), "{e}");
}

#[test]
fn checkpoints_are_verified_and_their_state_validated_on_resume() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("run");
    copy_run(&run);
    let (dir, state) = read_checkpoint(&run).unwrap().unwrap();
    assert!(dir.ends_with("ckpt") && state.step == 1);
    let t = Trainer::resume(&run, None).unwrap();
    assert_eq!(t.step, 1);
    // a short usage record (this panicked on resume), a feature buffer of the wrong width, a
    // future version: errors naming state.json
    let path = run.join("ckpt/state.json");
    let good: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    type Edit = fn(&mut serde_json::Value);
    let edits: [(&str, Edit); 4] = [
        ("usage", |s| s["usage"]["counts"] = serde_json::json!([1])),
        ("usage", |s| s["usage"]["last_used"] = serde_json::json!([])),
        ("feature buffer", |s| s["buffer"]["dim"] = serde_json::json!(3)),
        ("version", |s| s["version"] = serde_json::json!(99)),
    ];
    for (what, edit) in edits {
        let mut s = good.clone();
        edit(&mut s);
        std::fs::write(&path, serde_json::to_vec(&s).unwrap()).unwrap();
        rewrite_manifest(&run);
        let e = read_checkpoint(&run).unwrap_err().to_string();
        assert!(e.contains("state.json") && e.contains(what), "{what}: {e}");
        assert!(Trainer::resume(&run, None).is_err());
    }
}

/// Parameters of a model without code head or context, counted layer by layer from `cfg`: conv
/// `i o k^2 + o`, GroupNorm `2 c`, ResnetBlock two norms and two 3x3 convs (+ a 1x1 shortcut when
/// the width changes), AttnBlock a norm and four 1x1 convs; the stem is a `patch x patch` conv
/// (3x3 at patch 1) and the decoder's last conv has `4 patch^2` outputs; plus the mask-fusion
/// 1x1 conv `input_channels -> 4`, `quant_conv`, the codebook and `post_quant_conv`.
fn hand_count(cfg: &ModelConfig) -> usize {
    let conv = |i: usize, o: usize, k: usize| i * o * k * k + o;
    let norm = |c: usize| 2 * c;
    let res =
        |i: usize, o: usize| norm(i) + conv(i, o, 3) + norm(o) + conv(o, o, 3) + if i != o { conv(i, o, 1) } else { 0 };
    let attn = |c: usize| norm(c) + 4 * conv(c, c, 1);
    let mid = |c: usize| 2 * res(c, c) + if cfg.mid_attn { attn(c) } else { 0 };
    let (levels, p) = (cfg.ch_mult.len(), cfg.patch_size);
    assert!(cfg.attn_resolutions.is_empty() && !cfg.code_head && cfg.context.is_none(), "not counted here");
    let mut n = conv(cfg.input_channels(), 4, 1) + conv(4, cfg.ch, if p == 1 { 3 } else { p });
    let mut c = cfg.ch;
    for (i, m) in cfg.ch_mult.iter().enumerate() {
        for _ in 0..cfg.num_res_blocks {
            n += res(c, cfg.ch * m);
            c = cfg.ch * m;
        }
        if i + 1 < levels {
            n += conv(c, c, 3);
        }
    }
    n += mid(c) + norm(c) + conv(c, cfg.z_channels, 3);
    n += conv(cfg.z_channels, cfg.embed_dim, 1) + cfg.n_embed * cfg.embed_dim + conv(cfg.embed_dim, cfg.z_channels, 1);
    n += conv(cfg.z_channels, c, 3) + mid(c);
    for i in (0..levels).rev() {
        for _ in 0..=cfg.num_res_blocks {
            n += res(c, cfg.ch * cfg.ch_mult[i]);
            c = cfg.ch * cfg.ch_mult[i];
        }
        if i > 0 {
            n += conv(c, c, 3);
        }
    }
    n + norm(c) + conv(c, 4 * p * p, 3)
}

#[test]
fn the_parameter_estimate_bounds_real_models() {
    let device = default_device();
    // (config, exact count, estimate), both added up by hand:
    // tiny (ch 8, levels 1x/2x, 1 block, mid attention, patch 2, z 16, codebook 32 x 8):
    //   mask 24 + encoder 18,480 (stem 136, 8->8 block 1,200, downsample 584, 8->16 block
    //   3,680, mid 10,528, norm 32, conv_out 2,320) + quant 136 + codebook 256 + post 144 +
    //   decoder 28,888 (conv_in 2,320, mid 10,528, two 16->16 blocks 9,408, upsample 2,320,
    //   16->8 and 8->8 blocks 3,128, norm 16, conv_out 8->16 1,168) = 47,928;
    //   estimate: 9 c^2 x 8 convs per level (4,608 + 18,432) + mid 72 x 16^2 (18,432) +
    //   2 x 32 x 8 (512) + 18 x 16 x 16 (4,608) = 46,592.
    // compact (ch 32, levels 1x/2x, 1 block, no attention, patch 4, z 64, codebook 1024 x 64):
    //   mask 24 + encoder 272,960 + quant 4,160 + codebook 65,536 + post 4,160 + decoder
    //   437,472 = 784,312; estimate 73,728 + 294,912 + 294,912 + 131,072 + 73,728 = 868,352.
    for (cfg, exact, estimate) in [(ModelConfig::tiny(), 47_928, 46_592), (ModelConfig::compact(), 784_312, 868_352)] {
        let real = sgam_model::params::parameter_count(&VqModel::new(&cfg, 0, &device).unwrap());
        assert_eq!(hand_count(&cfg), exact, "{}: the layer-by-layer sum", cfg.name);
        assert_eq!(real, exact, "{}: built model", cfg.name);
        assert_eq!(cfg.approx_parameters(), estimate, "{}: estimate", cfg.name);
        // the estimate's documented promise: within a factor of about 1.5 of the real count
        let ratio = estimate as f64 / exact as f64;
        assert!((1.0 / 1.5..=1.5).contains(&ratio), "{}: estimate / real = {ratio:.3}", cfg.name);
    }
    let huge = ModelConfig { ch: 1_000_000, ..ModelConfig::tiny() };
    let e = huge.validate().unwrap_err().to_string();
    assert!(e.contains("ch 1000000") && e.contains("at most"), "{e}");
    let e = VqModel::new(&ModelConfig { n_embed: 1 << 40, ..ModelConfig::tiny() }, 0, &device).unwrap_err();
    assert!(matches!(e, ModelError::Config { .. }), "{e}");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn the_safetensors_parser_never_panics(
        bytes in prop::collection::vec(any::<u8>(), 0..300),
        header in 0u64..400,
        json in "\\{\"[a-z.]{1,8}\":\\{\"dtype\":\"(F32|F16|BF16|I8)\",\"shape\":\\[[0-9]{1,3}(,[0-9]{1,6}){0,3}\\],\"data_offsets\":\\[[0-9]{1,4},[0-9]{1,6}\\]\\}\\}",
    ) {
        let _ = from_safetensors_bytes(&bytes);
        let mut crafted = header.to_le_bytes().to_vec();
        crafted.extend(json.as_bytes());
        crafted.extend(&bytes);
        let _ = from_safetensors_bytes(&crafted);
        let mut exact = (json.len() as u64).to_le_bytes().to_vec();
        exact.extend(json.as_bytes());
        exact.extend(&bytes);
        if let Ok((tensors, _)) = from_safetensors_bytes(&exact) {
            for t in tensors.values() {
                prop_assert_eq!(t.values.len(), t.shape.iter().product::<usize>());
            }
        }
    }

    #[test]
    fn a_damaged_checkpoint_is_refused_and_a_damaged_state_never_panics(
        file in 0usize..5,
        pos in 0.0f64..1.0,
        x in 1u8..=255,
    ) {
        let tmp = tempfile::tempdir().unwrap();
        let run = tmp.path().join("run");
        copy_run(&run);
        let names = ["model.safetensors", "disc.safetensors", "optim_model.bpk", "optim_disc.bpk", "state.json"];
        let path = run.join("ckpt").join(names[file]);
        let mut bytes = std::fs::read(&path).unwrap();
        let i = ((bytes.len() - 1) as f64 * pos) as usize;
        bytes[i] ^= x;
        std::fs::write(&path, &bytes).unwrap();
        // the manifest catches any flipped byte, naming the file
        let e = read_checkpoint(&run).unwrap_err().to_string();
        prop_assert!(e.contains(names[file]), "{}", e);
        // written that way on purpose (manifest matching): the state's own checks, or the
        // weight and optimizer loaders, refuse or accept it, without panicking
        rewrite_manifest(&run);
        if let Ok(Some((_, state))) = read_checkpoint(&run) {
            prop_assert_eq!(state.usage.counts.len(), state.model_config.n_embed);
            let _ = Trainer::resume(&run, None);
        }
    }

    #[test]
    fn the_model_configuration_check_never_panics_and_bounds_memory(
        ch in 0usize..100_000,
        mult in prop::collection::vec(0usize..64, 0..10),
        nrb in 0usize..40,
        n_embed in 0usize..1_000_000,
        embed_dim in 0usize..10_000,
        eps in prop_oneof![Just(f64::NAN), Just(-1.0), 0.0f64..1.0],
    ) {
        let cfg = ModelConfig { ch, ch_mult: mult, num_res_blocks: nrb, n_embed, embed_dim, norm_eps: eps, ..ModelConfig::tiny() };
        if cfg.validate().is_ok() {
            prop_assert!(cfg.approx_parameters() <= sgam_model::config::MAX_PARAMETERS as u128);
            prop_assert!(cfg.n_embed <= sgam_model::config::MAX_CODEBOOK);
        }
    }
}
