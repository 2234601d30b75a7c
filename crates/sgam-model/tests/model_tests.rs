//! Model crate tests: presets, packing, quantizer, training, checkpoints, refiner.

use std::collections::BTreeMap;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_core::{Image, RgbdFrame};
use sgam_model::burn::module::Module;
use sgam_model::burn::tensor::{Distribution, Tensor};
use sgam_model::context::ContextConfig;
use sgam_model::packing::{pack_values, unpack_values};
use sgam_model::params::{named_tensors, WeightPrecision};
use sgam_model::quantize::{kmeans_revive, quantize, select_codes, CodebookUsage, FeatureBuffer};
use sgam_model::train::{Stage, TrainConfig, TrainPair, Trainer};
use sgam_model::{default_device, DepthCoding, ModelConfig, PairSource, RefinerOptions, Sampling, VqModel, VqRefiner};

/// A smooth synthetic RGB-D frame (depth within CLEVR's [7, 16] m).
fn synthetic_frame(w: u32, h: u32, seed: u64) -> RgbdFrame {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (a, b, c): (f32, f32, f32) = (rng.random(), rng.random(), rng.random());
    let colour = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (u, v) = (x as f32 / w as f32, y as f32 / h as f32);
            [(a + u) * 0.5, (b + v) * 0.5, ((c + u * v) * 0.7).min(1.0)]
        })
        .collect();
    let depth = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| 8.0 + 6.0 * (x + y) as f32 / (w + h) as f32)
        .collect();
    RgbdFrame {
        colour: Image { width: w, height: h, data: colour },
        depth_m: Image { width: w, height: h, data: depth },
    }
}

struct FixedSource {
    pairs: Vec<TrainPair>,
}

impl PairSource for FixedSource {
    type Error = std::convert::Infallible;

    fn next_batch(&mut self, batch: usize, _crop: u32, rng: &mut ChaCha8Rng) -> Result<Vec<TrainPair>, Self::Error> {
        Ok((0..batch).map(|_| self.pairs[rng.random_range(0..self.pairs.len())].clone()).collect())
    }
}

fn stage1_pairs(n: usize, size: u32) -> Vec<TrainPair> {
    (0..n)
        .map(|i| {
            let f = synthetic_frame(size, size, i as u64);
            TrainPair { input: f.clone(), missing: vec![false; (size * size) as usize], target: f }
        })
        .collect()
}

fn stage2_pairs(n: usize, size: u32) -> Vec<TrainPair> {
    (0..n)
        .map(|i| {
            let f = synthetic_frame(size, size, i as u64);
            let missing: Vec<bool> = (0..size * size).map(|p| (p % size) >= size / 2).collect();
            TrainPair { input: f.clone(), missing, target: f }
        })
        .collect()
}

#[test]
fn compact_forward_shapes_and_ranges() {
    let cfg = ModelConfig::compact();
    let device = default_device();
    let model = VqModel::new(&cfg, 1, &device).unwrap();
    let x = Tensor::<4>::random([1, 5, 64, 64], Distribution::Uniform(-1.0, 1.0), &device);
    let z = model.encode(x);
    let f = cfg.downsample_factor();
    assert_eq!(z.dims(), [1, cfg.embed_dim, 64 / f, 64 / f]);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let q = quantize(&model, z, Sampling::Argmin, None, 0.25, &mut rng).unwrap();
    assert!(q.indices.iter().all(|&i| (i as usize) < cfg.n_embed));
    let y = model.decode(q.z_q);
    assert_eq!(y.dims(), [1, 4, 64, 64]);
    // The decoder's raw output (no activation: any real value) is finite, and the frame is its
    // documented reading, computed here from the raw values: colour (y + 1) / 2 clipped to [0, 1];
    // depth from disparity s = (y + 1) / 2 clipped to [0, 1] between far (s = 0) and near (1).
    let raw = y.clone().into_data().try_to_vec_as::<f32>().unwrap();
    assert!(raw.iter().all(|v| v.is_finite()));
    let frames = sgam_model::packing::unpack(y, &cfg.depth).unwrap();
    let f = &frames[0];
    let hw = 64 * 64;
    let (near, far) = (cfg.depth.near_m as f64, cfg.depth.far_m as f64);
    for p in 0..hw {
        for c in 0..3 {
            let expect = ((raw[c * hw + p] as f64 + 1.0) / 2.0).clamp(0.0, 1.0);
            assert!((f.colour.data[p][c] as f64 - expect).abs() < 1e-6, "pixel {p} channel {c}");
        }
        let s = ((raw[3 * hw + p] as f64 + 1.0) / 2.0).clamp(0.0, 1.0);
        let depth = 1.0 / (s / near + (1.0 - s) / far);
        assert!((f.depth_m.data[p] as f64 - depth).abs() < 1e-4 * depth, "pixel {p}: {} vs {depth}", f.depth_m.data[p]);
    }
    // Out-of-range outputs land on the range's ends: colour 0 and 1, depth near and far.
    let values = [-3.0f32, 5.0, -1.5, 1.5, 1e6, -3.0, 9.0, -9.0];
    let out = unpack_values(&values, [1, 4, 1, 2], &cfg.depth).unwrap().pop().unwrap();
    assert_eq!(out.colour.data, vec![[0.0, 0.0, 1.0], [1.0, 1.0, 0.0]]);
    assert!((out.depth_m.data[0] - 7.0).abs() < 1e-5 && (out.depth_m.data[1] - 16.0).abs() < 1e-4, "{:?}", out.depth_m);
}

#[test]
fn paper_preset_parameters_and_names() {
    let cfg = ModelConfig::paper();
    let device = default_device();
    let model = VqModel::new(&cfg, 0, &device).unwrap();
    let n = model.num_params();
    // The exact count, added up from taming-transformers' layer list (Encoder / Decoder of
    // `taming/modules/diffusionmodules/model.py`, no timestep embedding) for this config with 4
    // image channels in and out, plus SGAM's 1x1 mask-fusion conv 5 -> 4: 76,076,188, of which
    // 4,194,304 is the 16384 x 256 codebook.
    assert_eq!(n, taming_vq_parameters(&cfg), "paper preset");
    assert_eq!(n, 76_076_188);
    let names = named_tensors(&model);
    for key in [
        "conv_in.weight",
        "encoder.conv_in.weight",
        "encoder.down.2.block.0.norm1.weight",
        "encoder.down.2.block.0.nin_shortcut.weight",
        "encoder.down.4.attn.1.proj_out.weight",
        "encoder.down.0.downsample.conv.weight",
        "encoder.mid.attn_1.q.weight",
        "encoder.mid.block_2.conv2.bias",
        "encoder.norm_out.weight",
        "quant_conv.weight",
        "quantize.embedding.weight",
        "post_quant_conv.weight",
        "decoder.up.4.attn.2.k.weight",
        "decoder.up.1.upsample.conv.weight",
        "decoder.conv_out.weight",
    ] {
        assert!(names.contains_key(key), "missing {key}; have e.g. {:?}", names.keys().take(5).collect::<Vec<_>>());
    }
    assert_eq!(names["quantize.embedding.weight"].shape, vec![16384, 256]);
    assert!(!names.contains_key("decoder.up.0.upsample.conv.weight"));
    // A small forward pass runs (32x32 -> 2x2 latent).
    let x = Tensor::<4>::zeros([1, 5, 32, 32], &device);
    let z = model.encode(x);
    assert_eq!(z.dims(), [1, 256, 2, 2]);
    let y = model.decode(z);
    assert_eq!(y.dims(), [1, 4, 32, 32]);
}

/// Parameters of a taming-transformers VQModel (its `Encoder`, `Decoder`, `quant_conv`, codebook,
/// `post_quant_conv`) with 4 channels in and out, plus the 1x1 mask-fusion conv 5 -> 4, counted
/// layer by layer: conv `i * o * k * k + o`, GroupNorm `2 c`, ResnetBlock two norms and two 3x3
/// convs (+ a 1x1 `nin_shortcut` when the width changes), AttnBlock a norm and four 1x1 convs.
fn taming_vq_parameters(cfg: &ModelConfig) -> usize {
    let conv = |i: usize, o: usize, k: usize| i * o * k * k + o;
    let norm = |c: usize| 2 * c;
    let res =
        |i: usize, o: usize| norm(i) + conv(i, o, 3) + norm(o) + conv(o, o, 3) + if i != o { conv(i, o, 1) } else { 0 };
    let attn = |c: usize| norm(c) + 4 * conv(c, c, 1);
    let levels = cfg.ch_mult.len();
    let mid = |c: usize| 2 * res(c, c) + if cfg.mid_attn { attn(c) } else { 0 };
    // encoder: conv_in, levels (blocks, attention at attn_resolutions, downsample but on the last)
    let (mut n, mut c, mut r) = (conv(4, cfg.ch, 3), cfg.ch, cfg.resolution);
    for (i, m) in cfg.ch_mult.iter().enumerate() {
        for _ in 0..cfg.num_res_blocks {
            n += res(c, cfg.ch * m);
            c = cfg.ch * m;
            n += if cfg.attn_resolutions.contains(&r) { attn(c) } else { 0 };
        }
        if i + 1 < levels {
            n += conv(c, c, 3);
            r /= 2;
        }
    }
    n += mid(c) + norm(c) + conv(c, cfg.z_channels, 3);
    // decoder: conv_in, mid, levels in reverse with one block more, upsample but on level 0
    n += conv(cfg.z_channels, c, 3) + mid(c);
    for i in (0..levels).rev() {
        for _ in 0..=cfg.num_res_blocks {
            n += res(c, cfg.ch * cfg.ch_mult[i]);
            c = cfg.ch * cfg.ch_mult[i];
            n += if cfg.attn_resolutions.contains(&r) { attn(c) } else { 0 };
        }
        if i > 0 {
            n += conv(c, c, 3);
            r *= 2;
        }
    }
    n += norm(c) + conv(c, 4, 3);
    let quant =
        conv(cfg.z_channels, cfg.embed_dim, 1) + cfg.n_embed * cfg.embed_dim + conv(cfg.embed_dim, cfg.z_channels, 1);
    n + quant + conv(5, 4, 1)
}

#[test]
fn packing_round_trip() {
    let coding = DepthCoding::google_earth();
    let mut f = synthetic_frame(16, 8, 3);
    for (i, d) in f.depth_m.data.iter_mut().enumerate() {
        *d = 0.2 + 4.5 * (i as f32 / 128.0); // z + 10 within [10.1, 14.77]
    }
    let (values, shape) = pack_values(&[&f], &[None], &coding).unwrap();
    assert_eq!(shape, [1, 5, 8, 16]);
    let hw = 128;
    let out: Vec<f32> = values[..4 * hw].to_vec();
    let back = unpack_values(&out, [1, 4, 8, 16], &coding).unwrap().pop().unwrap();
    for (a, b) in f.colour.data.iter().flatten().zip(back.colour.data.iter().flatten()) {
        assert!((a - b).abs() < 1e-5);
    }
    for (a, b) in f.depth_m.data.iter().zip(&back.depth_m.data) {
        assert!((a - b).abs() < 1e-3, "{a} vs {b}");
    }
    // Near maps to +1, far to -1, missing to -2 with mask 1 and grey colour.
    assert!((coding.encode(0.1) - 1.0).abs() < 1e-5);
    assert!((coding.encode(4.77) + 1.0).abs() < 1e-5);
    let missing: Vec<bool> = (0..hw).map(|i| i == 5).collect();
    let (v, _) = pack_values(&[&f], &[Some(&missing)], &coding).unwrap();
    assert_eq!(v[3 * hw + 5], -2.0);
    assert_eq!(v[4 * hw + 5], 1.0);
    assert_eq!(v[5], 0.0);
    assert_eq!(v[4 * hw + 6], 0.0);
}

#[test]
fn straight_through_gradient_reaches_encoder() {
    let cfg = ModelConfig::tiny();
    let device = default_device();
    let model = VqModel::new(&cfg, 2, &device).unwrap().train();
    let x = Tensor::<4>::random([1, 5, 32, 32], Distribution::Uniform(-1.0, 1.0), &device.clone().autodiff());
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let q = quantize(&model, model.encode(x), Sampling::Argmin, None, 0.25, &mut rng).unwrap();
    // Only the reconstruction term: any encoder gradient must have passed the straight-through path.
    let loss = model.decode(q.z_q).square().mean();
    let grads = loss.backward();
    let g = model.encoder.conv_in.weight.val().grad(&grads).expect("encoder gradient");
    let norm: f32 = g.abs().sum().into_scalar();
    assert!(norm > 0.0, "encoder gradient is zero");
}

#[test]
fn temperature_to_zero_equals_argmin() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (n, k) = (200, 64);
    let dist: Vec<f32> = (0..n * k).map(|_| rng.random_range(0.0..10.0)).collect();
    let missing = vec![true; n];
    let argmin = select_codes(&dist, n, k, Some(&missing), Sampling::Argmin, &mut rng);
    let cold =
        select_codes(&dist, n, k, Some(&missing), Sampling::Temperature { temperature: 1e-6, top_k: 8 }, &mut rng);
    assert_eq!(argmin, cold);
    // A hot temperature samples other codes, but only in missing cells.
    let half: Vec<bool> = (0..n).map(|i| i % 2 == 0).collect();
    let hot = select_codes(&dist, n, k, Some(&half), Sampling::Temperature { temperature: 100.0, top_k: 8 }, &mut rng);
    assert!(hot.iter().zip(&argmin).enumerate().all(|(i, (h, a))| i % 2 == 0 || h == a));
    assert!(hot.iter().zip(&argmin).any(|(h, a)| h != a));
}

#[test]
fn kmeans_revives_dead_codes() {
    let (k, d) = (8, 2);
    // Codes 0..4 sit on data; codes 4..8 are far away and never used.
    let mut codebook: Vec<f32> = vec![0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 1.0];
    codebook.extend([100.0, 100.0, 100.0, 101.0, 101.0, 100.0, 101.0, 101.0]);
    let mut usage = CodebookUsage::new(k, 0);
    usage.record(&[0, 1, 2, 3], 50);
    let dead = usage.dead_codes(50, 10);
    assert_eq!(dead, vec![4, 5, 6, 7]);
    assert_eq!(usage.active_count(50, 10), 4);
    // Features around 4 new clusters at (5,5), (5,-5), (-5,5), (-5,-5).
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut buffer = FeatureBuffer::new(d, 1000);
    for i in 0..400 {
        let (cx, cy) = [(5.0, 5.0), (5.0, -5.0), (-5.0, 5.0), (-5.0, -5.0)][i % 4];
        buffer.push(&[cx + rng.random_range(-0.1f32..0.1), cy + rng.random_range(-0.1f32..0.1)]);
    }
    assert!(kmeans_revive(&mut codebook, d, &dead, &buffer, 10, &mut rng));
    assert_eq!(&codebook[..8], &[0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 1.0]);
    // Every cluster now has a revived code within 0.2 of its centre.
    for (cx, cy) in [(5.0f32, 5.0f32), (5.0, -5.0), (-5.0, 5.0), (-5.0, -5.0)] {
        let near = (4..8).any(|c| (codebook[c * 2] - cx).abs() < 0.2 && (codebook[c * 2 + 1] - cy).abs() < 0.2);
        assert!(near, "no revived code near ({cx}, {cy}): {codebook:?}");
    }
}

#[test]
fn tiny_model_overfits_one_batch() {
    let cfg = ModelConfig::tiny();
    let mut tc = TrainConfig::new(Stage::One, 0);
    tc.batch = 2;
    tc.lr = 3e-3;
    tc.disc_start = u64::MAX;
    tc.seed = 3;
    let pairs = stage1_pairs(2, 32);
    let mut trainer = Trainer::new(&cfg, &tc).unwrap();
    let first = trainer.step_on(&pairs).unwrap();
    let mut last = first.clone();
    for _ in 0..150 {
        last = trainer.step_on(&pairs).unwrap();
    }
    let rec = |r: &sgam_model::train::StepReport| r.l1 + r.perceptual;
    assert!(rec(&last) * 10.0 < rec(&first), "loss {} -> {}", rec(&first), rec(&last));
}

#[test]
fn missing_weight_reweights_only_the_missing_pixels() {
    // The first step's L1 (same weights, same batch) with missing weight 1 and 10: equal when
    // nothing is missing, different when half of every input is missing.
    let cfg = ModelConfig::tiny();
    let first_l1 = |pairs: &[TrainPair], w: f32| {
        let mut tc = TrainConfig::new(Stage::One, 0);
        tc.batch = pairs.len();
        tc.missing_weight = w;
        tc.warmup_no_quant_steps = 10;
        Trainer::new(&cfg, &tc).unwrap().step_on(pairs).unwrap().l1
    };
    let clean = stage1_pairs(2, 32);
    assert!((first_l1(&clean, 1.0) - first_l1(&clean, 10.0)).abs() < 1e-6);
    // Half of every input missing. The target enters only the loss, so changing it on one half
    // changes that half's mean error (by some db) and nothing else. For the weighted mean
    // L(w) = (a + w b) / (1 + w) (a, b: mean error over observed / missing pixels), a change on
    // the missing half moves L(w) by w db / (1 + w): the moves at w = 10 and w = 1 are in the
    // ratio (10 / 11) / (1 / 2) = 20 / 11. A change on the observed half moves it by
    // da / (1 + w): ratio 2 / 11. (Unnormalised weights would give 10 and 1; weights on the
    // wrong half would swap the two ratios.)
    let holes = stage2_pairs(2, 32);
    let changed = |observed_half: bool| -> Vec<TrainPair> {
        let mut pairs = holes.clone();
        for p in &mut pairs {
            for (i, m) in p.missing.iter().enumerate() {
                if *m != observed_half {
                    let c = &mut p.target.colour.data[i];
                    *c = [1.0 - c[0], 1.0 - c[1], 1.0 - c[2]];
                    p.target.depth_m.data[i] += 3.0;
                }
            }
        }
        pairs
    };
    let base = [first_l1(&holes, 1.0), first_l1(&holes, 10.0)];
    for (observed_half, ratio) in [(false, 20.0 / 11.0), (true, 2.0 / 11.0)] {
        let pairs = changed(observed_half);
        let moved = [first_l1(&pairs, 1.0) - base[0], first_l1(&pairs, 10.0) - base[1]];
        assert!(moved[0].abs() > 1e-2, "the changed target moved the loss by only {}", moved[0]);
        let got = moved[1] / moved[0];
        eprintln!("observed half {observed_half}: loss moved {moved:?}, ratio {got:.6} (expected {ratio:.6})");
        // f32 means over 8192 values: the ratio is good to ~1e-5; 1e-3 allowed.
        assert!((got - ratio).abs() < 1e-3, "observed half {observed_half}: ratio {got}, expected {ratio}");
    }
}

#[test]
fn stage2_freezes_codebook_and_decoder() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ModelConfig::tiny();
    let device = default_device();
    let stage1 = VqModel::new(&cfg, 7, &device).unwrap();
    let weights = dir.path().join("stage1.safetensors");
    sgam_model::refiner::save_model(&stage1, &cfg, &weights, WeightPrecision::F32).unwrap();
    let mut tc = TrainConfig::new(Stage::Two, 0);
    tc.batch = 2;
    tc.lr = 1e-3;
    tc.disc_start = 1; // exercise the adversarial path too
    tc.init_weights = Some(weights);
    let mut trainer = Trainer::new(&cfg, &tc).unwrap();
    let before = named_tensors(&trainer.model);
    let pairs = stage2_pairs(2, 32);
    for _ in 0..3 {
        let r = trainer.step_on(&pairs).unwrap();
        assert!(r.total.is_finite());
    }
    let after = named_tensors(&trainer.model);
    let mut changed = BTreeMap::new();
    for (name, t) in &before {
        changed.insert(name.clone(), t.values != after[name].values);
    }
    for (name, ch) in &changed {
        let trainable = name.starts_with("encoder.") || name.starts_with("conv_in.");
        if !trainable {
            assert!(!ch, "frozen parameter {name} changed");
        }
    }
    assert!(changed["encoder.conv_in.weight"], "encoder did not train");
    assert!(changed["conv_in.weight"], "mask fusion did not train");
}

#[test]
fn checkpoint_resume_gives_identical_steps() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ModelConfig::tiny();
    let mut tc = TrainConfig::new(Stage::One, 0);
    tc.batch = 2;
    tc.crop = 32;
    tc.disc_start = 2;
    tc.warmup_no_quant_steps = 1;
    tc.seed = 11;
    let mut source = FixedSource { pairs: stage1_pairs(3, 32) };
    let mut a = Trainer::new(&cfg, &tc).unwrap();
    for _ in 0..3 {
        a.step(&mut source).unwrap();
    }
    a.save(dir.path()).unwrap();
    let ra: Vec<f32> = (0..2).map(|_| a.step(&mut source).unwrap().total).collect();
    let mut b = Trainer::resume(dir.path(), None).unwrap();
    assert_eq!(b.step, 3);
    let rb: Vec<f32> = (0..2).map(|_| b.step(&mut source).unwrap().total).collect();
    assert_eq!(ra, rb);
    let (wa, wb) = (named_tensors(&a.model), named_tensors(&b.model));
    for (name, t) in &wa {
        assert_eq!(t.values, wb[name].values, "{name} differs after resume");
    }
}

#[test]
fn refiner_from_bytes_completes_frames() {
    let cfg = ModelConfig::tiny();
    let device = default_device();
    let model = VqModel::new(&cfg, 9, &device).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.safetensors");
    sgam_model::refiner::save_model(&model, &cfg, &path, WeightPrecision::F16).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let mut refiner = VqRefiner::from_bytes(&bytes, None, RefinerOptions::default()).unwrap();
    // 30x30 is padded to 32x32 internally and cropped back.
    let f = synthetic_frame(30, 30, 1);
    let missing: Vec<bool> = (0..900).map(|i| i % 30 > 20).collect();
    let out = refiner.complete(&f, &missing).unwrap();
    assert_eq!((out.width(), out.height()), (30, 30));
    // Observed pixels are the guidance's, bit for bit (keep_observed is the default).
    for (i, m) in missing.iter().enumerate() {
        if !m {
            assert_eq!((out.colour.data[i], out.depth_m.data[i]), (f.colour.data[i], f.depth_m.data[i]), "pixel {i}");
        }
    }
    // Temperature sampling with T -> 0 gives the argmin output; a seed reproduces.
    let argmin = refiner.complete(&f, &missing).unwrap();
    refiner.set_options(RefinerOptions {
        sampling: Sampling::Temperature { temperature: 1e-7, top_k: 4 },
        seed: 3,
        ..Default::default()
    });
    assert_eq!(refiner.complete(&f, &missing).unwrap(), argmin);
    refiner.set_options(RefinerOptions {
        sampling: Sampling::Temperature { temperature: 10.0, top_k: 4 },
        seed: 3,
        ..Default::default()
    });
    let s1 = refiner.complete(&f, &missing).unwrap();
    refiner.set_options(RefinerOptions {
        sampling: Sampling::Temperature { temperature: 10.0, top_k: 4 },
        seed: 3,
        ..Default::default()
    });
    assert_eq!(refiner.complete(&f, &missing).unwrap(), s1);
    assert_ne!(s1, argmin, "T = 10 must draw other codes than the argmin somewhere");

    // T = 10 follows the distribution: on a 32 x 32 frame (no padding: the refiner's distances
    // are the model's squared distances on the packed guidance, computed here the same way),
    // observed cells take the argmin, missing cells one of their 4 nearest codes, drawn with
    // p ~ exp(-(d - d_min) / 10) among them. Over 60 seeds, the counts of the four ranks pass a
    // chi-square test (3 degrees of freedom, 0.1 % critical value 16.27). This untrained model's
    // distance gaps are small against T = 10, so the four probabilities are all close to 1/4
    // (measured: 480 +- 1 expected draws of 1920 per rank): what this checks is the top-4
    // restriction and the spread; the softmax's shape at a low temperature is checked on known
    // distances in `generative_tests.rs`.
    let device = default_device();
    let (model, cfg) = sgam_model::refiner::load_model_bytes(&bytes, None, &device).unwrap();
    let f = synthetic_frame(32, 32, 4);
    let missing: Vec<bool> = (0..32 * 32).map(|i| i % 32 >= 16).collect();
    let k = sgam_core::Intrinsics::from_fov_x(32, 32, 1.0);
    let x = sgam_model::packing::pack_input(&[&f], &[Some(&missing)], &[k], &cfg, &device).unwrap();
    let z = model.encode(x);
    let [_, d, zh, zw] = z.dims();
    let rows = z.permute([0, 2, 3, 1]).reshape([zh * zw, d]);
    let codebook = model.quantize.embedding.weight.val();
    let dist = sgam_model::quantize::squared_distances(rows, codebook).into_data().try_to_vec_as::<f32>().unwrap();
    let n_codes = cfg.n_embed;
    // per cell: the 4 nearest codes (nearest first) and their probabilities at T = 10
    let top4: Vec<(Vec<usize>, Vec<f64>)> = (0..zh * zw)
        .map(|c| {
            let row = &dist[c * n_codes..(c + 1) * n_codes];
            let mut order: Vec<usize> = (0..n_codes).collect();
            order.sort_by(|a, b| row[*a].total_cmp(&row[*b]).then(a.cmp(b)));
            order.truncate(4);
            let w: Vec<f64> = order.iter().map(|&j| (-((row[j] - row[order[0]]) as f64) / 10.0).exp()).collect();
            let total: f64 = w.iter().sum();
            (order, w.iter().map(|x| x / total).collect())
        })
        .collect();
    let (mut observed, mut expected) = ([0.0f64; 4], [0.0f64; 4]);
    for seed in 0..60 {
        let options = RefinerOptions {
            sampling: Sampling::Temperature { temperature: 10.0, top_k: 4 },
            seed,
            ..Default::default()
        };
        refiner.set_options(options);
        refiner.complete(&f, &missing).unwrap();
        let trace = refiner.trace();
        assert_eq!(trace.codes.len(), zh * zw);
        assert_eq!(trace.missing_cells.iter().filter(|m| **m).count(), zh * zw / 2, "the right half of the cells");
        for (c, (&code, &m)) in trace.codes.iter().zip(&trace.missing_cells).enumerate() {
            let (order, p) = &top4[c];
            let rank = order.iter().position(|&j| j == code as usize);
            if !m {
                assert_eq!(rank, Some(0), "observed cell {c} did not take its argmin");
                continue;
            }
            let Some(rank) = rank else { panic!("cell {c}: code {code} is not among the 4 nearest {order:?}") };
            observed[rank] += 1.0;
            for r in 0..4 {
                expected[r] += p[r];
            }
        }
    }
    let chi2: f64 = (0..4).map(|r| (observed[r] - expected[r]).powi(2) / expected[r]).sum();
    eprintln!("T = 10 rank counts {observed:?}, expected {expected:?}, chi-square {chi2:.2}");
    assert!(observed[0] < 0.9 * observed.iter().sum::<f64>(), "T = 10 hardly leaves the argmin: {observed:?}");
    assert!(chi2 < 16.27, "rank counts {observed:?} vs expected {expected:?}: chi-square {chi2:.2}");
}

#[test]
fn refiner_keeps_observed_pixels_unless_asked_to_regenerate() {
    let cfg = ModelConfig::tiny();
    let device = default_device();
    let model = VqModel::new(&cfg, 4, &device).unwrap();
    let f = synthetic_frame(32, 32, 2);
    let missing: Vec<bool> = (0..32 * 32).map(|i| i % 32 >= 20).collect();
    let mut keep = VqRefiner::new(model.clone(), cfg.clone(), RefinerOptions::default(), device.clone());
    let kept = keep.complete(&f, &missing).unwrap();
    let options = RefinerOptions { keep_observed: false, ..Default::default() };
    let regenerated = VqRefiner::new(model, cfg, options, device).complete(&f, &missing).unwrap();
    for (i, &m) in missing.iter().enumerate() {
        let (u, v) = ((i % 32) as u32, (i / 32) as u32);
        if m {
            // the model's output where the guidance has a hole, in both modes
            assert_eq!(kept.colour.at(u, v), regenerated.colour.at(u, v));
        } else {
            assert_eq!(kept.colour.at(u, v), f.colour.at(u, v));
            assert_eq!(kept.depth_m.at(u, v), f.depth_m.at(u, v));
        }
    }
    // an untrained model does not reproduce the observed pixels by itself
    let differs = missing.iter().enumerate().filter(|(_, m)| !**m).any(|(i, _)| {
        let (u, v) = ((i % 32) as u32, (i / 32) as u32);
        regenerated.colour.at(u, v) != f.colour.at(u, v)
    });
    assert!(differs);
}

#[test]
fn warmup_end_initialises_the_codebook_from_encoder_features() {
    let cfg = ModelConfig::tiny();
    let mut tc = TrainConfig::new(Stage::One, 0);
    tc.batch = 2;
    tc.disc_start = u64::MAX;
    tc.warmup_no_quant_steps = 2;
    let pairs = stage1_pairs(2, 32);
    let mut trainer = Trainer::new(&cfg, &tc).unwrap();
    let random = sgam_model::quantize::codebook_values(&trainer.model).unwrap();
    for _ in 0..2 {
        let r = trainer.step_on(&pairs).unwrap();
        assert_eq!(r.quant, 0.0, "no quantizer during the warm-up");
    }
    // validation during the warm-up bypasses the quantizer, like training
    let (val_psnr_warm, _) = trainer.validate(&pairs).unwrap();
    assert!(val_psnr_warm.is_finite());
    let before = sgam_model::quantize::codebook_values(&trainer.model).unwrap();
    assert_eq!(before, random, "the codebook does not train during the warm-up");
    let r = trainer.step_on(&pairs).unwrap();
    assert!(r.quant > 0.0);
    let after = sgam_model::quantize::codebook_values(&trainer.model).unwrap();
    let changed = before.iter().zip(&after).filter(|(a, b)| a != b).count();
    assert!(
        changed > after.len() / 2,
        "k-means must overwrite the codebook ({changed} of {} values changed)",
        after.len()
    );
}

#[test]
fn learning_rate_is_constant_then_decays_along_a_cosine_to_the_floor() {
    let mut tc = TrainConfig::new(Stage::One, 1000);
    tc.lr = 1e-3;
    assert_eq!(tc.lr_at(0), 1e-3);
    assert_eq!(tc.lr_at(999), 1e-3, "no decay unless asked");
    tc.lr_decay_from = Some(600);
    assert_eq!(tc.lr_at(599), 1e-3);
    assert!((tc.lr_at(600) - 1e-3).abs() < 1e-12);
    let mid = tc.lr_at(800);
    let expected_mid = 1e-3 * (sgam_model::train::LR_FLOOR + (1.0 - sgam_model::train::LR_FLOOR) * 0.5);
    assert!((mid - expected_mid).abs() < 1e-12, "{mid} vs {expected_mid}");
    assert!((tc.lr_at(1000) - 1e-3 * sgam_model::train::LR_FLOOR).abs() < 1e-12);
    assert!((tc.lr_at(5000) - 1e-3 * sgam_model::train::LR_FLOOR).abs() < 1e-12, "clamped past the end");
    let lrs: Vec<f64> = (600..=1000).map(|s| tc.lr_at(s)).collect();
    assert!(lrs.windows(2).all(|w| w[1] <= w[0]), "decay is monotone");
}

/// The refiner's CPU kernels (`sgam_model::nhwc`) and burn's pass of the same model draw the
/// same codes and the same pixels, through one pass (argmin) and through sampling in passes, with
/// and without a code head, and with the scene-wide context.
#[test]
#[cfg(not(feature = "wgpu"))] // the CPU kernels run on the CPU backend only
fn the_cpu_kernels_complete_frames_as_burns_pass_does() {
    let device = default_device();
    let tiny = ModelConfig { mid_attn: false, ..ModelConfig::tiny() };
    let sampled = RefinerOptions {
        sampling: Sampling::Temperature { temperature: 1.0, top_k: usize::MAX },
        cells_per_pass: 4,
        ..RefinerOptions::default()
    };
    let cases = [
        (tiny.clone(), RefinerOptions { sampling: Sampling::Argmin, ..RefinerOptions::default() }),
        (ModelConfig { code_tau: Some(0.5), ..tiny.clone() }, sampled),
        (ModelConfig { code_head: true, code_tau: Some(1.0), ..tiny.clone() }, sampled),
        // the scene-wide context: the head's logits and the features it attends over
        (
            ModelConfig {
                code_head: true,
                code_tau: Some(1.0),
                context: Some(ContextConfig {
                    dim: 16,
                    layers: 1,
                    heads: 2,
                    mlp_ratio: 2,
                    window_cells: 8,
                    margin_cells: 2,
                }),
                ..tiny
            },
            sampled,
        ),
    ];
    let (w, h) = (40u32, 36u32); // not multiples of the downsampling factor: padded and cropped
    let f = synthetic_frame(w, h, 6);
    let missing: Vec<bool> = (0..w * h).map(|p| p % w >= 22 || p / w >= 30).collect();
    for (i, (cfg, options)) in cases.into_iter().enumerate() {
        let mut model = VqModel::new(&cfg, 10 + i as u64, &device).unwrap();
        if cfg.context.is_some() {
            // a fresh context adds nothing (zero output): move every one of its weights
            let mut tensors = named_tensors(&model);
            for (t, (name, v)) in tensors.iter_mut().enumerate() {
                if name.starts_with("context.") {
                    let spread = if name.starts_with("context.out") { 2.0 } else { 0.3 };
                    let mut rng = ChaCha8Rng::seed_from_u64(t as u64);
                    v.values.iter_mut().for_each(|x| *x += spread * rng.random_range(-1.0f32..1.0));
                }
            }
            model = sgam_model::params::load_named(model, &tensors, false, false).unwrap();
        }
        let mut ours = VqRefiner::new(model.clone(), cfg.clone(), options, device.clone());
        let mut burn = VqRefiner::new(model, cfg, options, device.clone());
        burn.set_cpu_kernels(false);
        assert!(ours.uses_cpu_kernels() && !burn.uses_cpu_kernels(), "case {i}");
        let a = ours.complete(&f, &missing).unwrap();
        let b = burn.complete(&f, &missing).unwrap();
        assert_eq!(ours.trace().codes, burn.trace().codes, "case {i}: codes");
        assert_eq!(ours.trace().passes, burn.trace().passes, "case {i}: passes");
        assert!(ours.trace().passes.len() > usize::from(i > 0), "case {i}: {:?}", ours.trace().passes);
        let colour =
            a.colour.data.iter().zip(&b.colour.data).flat_map(|(p, q)| (0..3).map(move |c| (p[c] - q[c]).abs()));
        let dc = colour.fold(0.0f32, f32::max);
        let dd = a
            .depth_m
            .data
            .iter()
            .zip(&b.depth_m.data)
            .map(|(p, q)| (p - q).abs() / q.abs().max(1e-3))
            .fold(0.0f32, f32::max);
        assert!(dc < 1e-3 && dd < 1e-3, "case {i}: colour differs by {dc}, depth by {dd} (relative)");
    }
    // a model with attention keeps burn's path
    let cfg = ModelConfig::tiny();
    let r = VqRefiner::new(VqModel::new(&cfg, 1, &device).unwrap(), cfg, RefinerOptions::default(), device);
    assert!(!r.uses_cpu_kernels());
}
