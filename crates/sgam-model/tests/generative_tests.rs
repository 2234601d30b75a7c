//! The generative stage 2: cross-entropy targets, calibrated temperature sampling, iterative
//! (MaskGIT-style) sampling, ray channels, checkpoints, and a tiny model that learns a
//! two-pattern world in the right proportion.

mod common;

use std::collections::BTreeMap;

use common::frame;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_core::{Image, Intrinsics, RgbdFrame};
use sgam_model::decoder_tune::{DecoderTuneConfig, DecoderTuner};
use sgam_model::generative::{reveal_cells, target_codes, CodePair, CodeTrainConfig, CodeTrainer};
use sgam_model::packing::{pack_input, pack_values};
use sgam_model::params::{named_tensors, NamedTensor};
use sgam_model::quantize::{quantize, select_codes, select_codes_by_class};
use sgam_model::{default_device, ModelConfig, RefinerOptions, Sampling, VqModel, VqRefiner};

fn flat(w: u32, h: u32, top: [f32; 3], bottom: [f32; 3]) -> RgbdFrame {
    let colour = (0..w * h).map(|p| if p / w < h / 2 { top } else { bottom }).collect();
    RgbdFrame {
        colour: Image { width: w, height: h, data: colour },
        depth_m: Image { width: w, height: h, data: vec![10.0; (w * h) as usize] },
    }
}

#[test]
fn cross_entropy_targets_are_the_frozen_encoders_argmin_codes() {
    let device = default_device();
    let cfg = ModelConfig::tiny();
    let model = VqModel::new(&cfg, 3, &device).unwrap();
    let frames: Vec<RgbdFrame> = (0..3).map(|s| frame(16, 16, s)).collect();
    let refs: Vec<&RgbdFrame> = frames.iter().collect();
    let k = Intrinsics::from_fov_x(16, 16, 1.0);
    let targets = target_codes(&model, &cfg, &refs, &[k; 3], &device).unwrap();
    // the quantizer's own argmin on the same clean input
    let (values, shape) = pack_values(&refs, &[None, None, None], &cfg.depth).unwrap();
    let x =
        sgam_model::burn::tensor::Tensor::from_data(sgam_model::burn::tensor::TensorData::new(values, shape), &device);
    let q =
        quantize(&model, model.encode(x), Sampling::Argmin, None, cfg.beta, &mut ChaCha8Rng::seed_from_u64(0)).unwrap();
    let cells = (16 / cfg.downsample_factor()).pow(2);
    assert_eq!(targets.len(), 3);
    for (b, t) in targets.iter().enumerate() {
        assert_eq!(t.as_slice(), &q.indices[b * cells..(b + 1) * cells], "frame {b}");
    }
    // different frames give different codes somewhere (the targets carry information)
    assert_ne!(targets[0], targets[1]);
}

#[test]
fn temperature_sampling_follows_the_softmax_of_the_distances() {
    // one row of 6 codes; p_k = softmax(-d_k / T)
    let dist = [0.3f32, 0.0, 0.9, 0.5, 2.0, 0.1];
    let (n, k) = (20_000usize, dist.len());
    let table: Vec<f32> = (0..n).flat_map(|_| dist).collect();
    let missing = vec![true; n];
    let t = 0.4f64;
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let drawn = select_codes(
        &table,
        n,
        k,
        Some(&missing),
        Sampling::Temperature { temperature: t as f32, top_k: usize::MAX },
        &mut rng,
    );
    let z: f64 = dist.iter().map(|d| (-(*d as f64) / t).exp()).sum();
    let p: Vec<f64> = dist.iter().map(|d| (-(*d as f64) / t).exp() / z).collect();
    let chi2 = chi_square(&drawn, &p);
    // 5 degrees of freedom: the 0.1 % critical value is 20.5
    assert!(chi2 < 20.5, "chi-square {chi2:.2}");
    // T -> 0 is the argmin (code 1) in every row; observed rows always take the argmin
    let cold = select_codes(
        &table,
        n,
        k,
        Some(&missing),
        Sampling::Temperature { temperature: 1e-7, top_k: usize::MAX },
        &mut rng,
    );
    assert!(cold.iter().all(|&c| c == 1));
    let observed = vec![false; n];
    let kept = select_codes(
        &table,
        n,
        k,
        Some(&observed),
        Sampling::Temperature { temperature: t as f32, top_k: usize::MAX },
        &mut rng,
    );
    assert!(kept.iter().all(|&c| c == 1));
}

/// Chi-square statistic of `drawn` against the expected probabilities `p` of each code.
fn chi_square(drawn: &[u32], p: &[f64]) -> f64 {
    let n = drawn.len() as f64;
    p.iter()
        .enumerate()
        .filter(|(_, p)| **p > 0.0)
        .map(|(j, p)| {
            let observed = drawn.iter().filter(|&&c| c as usize == j).count() as f64;
            (observed - n * p).powi(2) / (n * p)
        })
        .sum()
}

#[test]
fn two_level_sampling_draws_the_class_at_the_temperature_and_the_code_at_the_within_temperature() {
    // 6 codes; 1, 4 and 5 are plain (ground), the rest coloured
    let dist = [0.3f32, 0.0, 0.9, 0.5, 2.0, 0.1];
    let plain = [false, true, false, false, true, true];
    let (n, k) = (20_000usize, dist.len());
    let table: Vec<f32> = (0..n).flat_map(|_| dist).collect();
    let missing = vec![true; n];
    let softmax = |t: f64, members: &dyn Fn(usize) -> bool| -> Vec<f64> {
        let w: Vec<f64> = (0..k).map(|j| if members(j) { (-(dist[j] as f64) / t).exp() } else { 0.0 }).collect();
        let z: f64 = w.iter().sum();
        w.iter().map(|x| x / z).collect()
    };
    let (t, within) = (0.8f64, 0.3f64);
    let whole = softmax(t, &|_| true);
    let p_plain: f64 = (0..k).filter(|&j| plain[j]).map(|j| whole[j]).sum();
    let in_plain = softmax(within, &|j| plain[j]);
    let in_coloured = softmax(within, &|j| !plain[j]);
    let expected: Vec<f64> =
        (0..k).map(|j| if plain[j] { p_plain * in_plain[j] } else { (1.0 - p_plain) * in_coloured[j] }).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let (drawn, probs) = select_codes_by_class(&table, n, k, &missing, t as f32, within as f32, &plain, None, &mut rng);
    // 5 degrees of freedom: the 0.1 % critical value is 20.5
    let chi2 = chi_square(&drawn, &expected);
    assert!(chi2 < 20.5, "chi-square {chi2:.2}");
    // the class keeps the whole softmax's share: how often objects start does not change
    let plain_share = drawn.iter().filter(|&&c| plain[c as usize]).count() as f64 / n as f64;
    assert!((plain_share - p_plain).abs() < 0.015, "plain drawn {plain_share:.3}, softmax gives {p_plain:.3}");
    // each draw reports its probability under the two-level distribution
    for (c, p) in drawn.iter().zip(&probs).take(50) {
        assert!((*p as f64 - expected[*c as usize]).abs() < 1e-5, "code {c}: {p} vs {}", expected[*c as usize]);
    }
    // within = temperature is plain temperature sampling
    let (same, _) = select_codes_by_class(&table, n, k, &missing, t as f32, t as f32, &plain, None, &mut rng);
    let chi2 = chi_square(&same, &whole);
    assert!(chi2 < 20.5, "within = T: chi-square {chi2:.2}");
    // within -> 0 takes the nearest code of the drawn class: codes 1 (plain) and 0 (coloured)
    let (cold, _) = select_codes_by_class(&table, n, k, &missing, t as f32, 0.0, &plain, None, &mut rng);
    assert!(cold.iter().all(|&c| c == 1 || c == 0));
    let cold_plain = cold.iter().filter(|&&c| c == 1).count() as f64 / n as f64;
    assert!((cold_plain - p_plain).abs() < 0.015, "{cold_plain:.3} vs {p_plain:.3}");
    // observed rows take the argmin
    let (kept, p) =
        select_codes_by_class(&table, n, k, &vec![false; n], t as f32, within as f32, &plain, None, &mut rng);
    assert!(kept.iter().all(|&c| c == 1) && p.iter().all(|&p| p == 1.0));
}

#[test]
fn a_within_class_bias_moves_the_code_but_not_the_class() {
    // 6 codes; 1, 4 and 5 plain, the rest coloured; the bias makes code 3 the coloured class's
    let dist = [0.3f32, 0.0, 0.9, 0.5, 2.0, 0.1];
    let plain = [false, true, false, false, true, true];
    let (n, k) = (4_000usize, dist.len());
    let table: Vec<f32> = (0..n).flat_map(|_| dist).collect();
    let missing = vec![true; n];
    let bias: Vec<f32> = (0..n).flat_map(|_| [20.0f32, 0.0, 20.0, 0.0, 0.0, 0.0]).collect();
    let draw = |bias: Option<&[f32]>| {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        select_codes_by_class(&table, n, k, &missing, 1.0, 0.5, &plain, bias, &mut rng).0
    };
    let (free, biased) = (draw(None), draw(Some(&bias)));
    let mut coloured = 0;
    for (a, b) in free.iter().zip(&biased) {
        // the same class in every row, drawn by the same uniforms
        assert_eq!(plain[*a as usize], plain[*b as usize], "{a} vs {b}");
        if plain[*a as usize] {
            assert_eq!(a, b, "plain rows carry no bias");
        } else {
            coloured += 1;
            assert_eq!(*b, 3, "the coloured draw follows the bias");
        }
    }
    assert!(coloured > 500, "{coloured} coloured rows");
    assert!(free.contains(&0), "without the bias code 0 is the likeliest coloured code");
}

#[test]
fn two_level_iterative_sampling_commits_every_missing_cell_once_and_keeps_observed_pixels() {
    let device = default_device();
    let cfg = ModelConfig { code_tau: Some(0.5), ..ModelConfig::tiny() };
    let model = VqModel::new(&cfg, 5, &device).unwrap();
    let options = RefinerOptions {
        sampling: Sampling::Temperature { temperature: 1.0, top_k: usize::MAX },
        cells_per_pass: 5,
        within_class_temperature: Some(0.5),
        ..RefinerOptions::default()
    };
    let mut r = VqRefiner::new(model, cfg.clone(), options, device);
    let plain = r.plain_codes().unwrap().to_vec();
    assert_eq!(plain.len(), cfg.n_embed);
    let (w, h) = (32u32, 32u32);
    let f = frame(w, h, 4);
    // a 20 x 12 pixel hole: 5 x 3 = 15 missing cells; ceil(15 / 5) = 3 passes of 5
    let missing: Vec<bool> = (0..w * h).map(|p| (4..24).contains(&(p % w)) && (8..20).contains(&(p / w))).collect();
    assert_passes_commit_each_cell_once(&mut r, &f, &missing, 15, 3);
    assert_eq!(r.trace().passes.iter().map(Vec::len).collect::<Vec<_>>(), [5, 5, 5]);
}

#[test]
fn ray_channels_carry_each_pixels_viewing_ray() {
    let device = default_device();
    let cfg = ModelConfig { ray_channels: true, ..ModelConfig::tiny() };
    let f = frame(8, 6, 1);
    // a crop's intrinsics: principal point shifted
    let k = Intrinsics { width: 8, height: 6, fx: 20.0, fy: 25.0, cx: -3.0, cy: 10.0 };
    let x = pack_input(&[&f], &[None], &[k], &cfg, &device).unwrap();
    assert_eq!(x.dims(), [1, 7, 6, 8]);
    let v = x.into_data().try_to_vec_as::<f32>().unwrap();
    let hw = 48;
    for (u, row) in [(0usize, 0usize), (7, 5), (3, 2)] {
        let ray_x = v[5 * hw + row * 8 + u];
        let ray_y = v[6 * hw + row * 8 + u];
        assert!((ray_x - 2.0 * (u as f32 + 3.0) / 20.0).abs() < 1e-6, "{u},{row}: {ray_x}");
        assert!((ray_y - 2.0 * (row as f32 - 10.0) / 25.0).abs() < 1e-6, "{u},{row}: {ray_y}");
    }
    // a ray model refuses to complete a frame without intrinsics
    let model = VqModel::new(&cfg, 0, &device).unwrap();
    let mut r = VqRefiner::new(model, cfg, RefinerOptions::default(), device);
    let f = frame(16, 16, 2);
    assert!(r.complete(&f, &vec![false; 256]).is_err());
    assert!(r.complete_at(&f, &vec![false; 256], Some(&Intrinsics::from_fov_x(16, 16, 1.0))).is_ok());
}

/// Completes `f` with `missing` through `r` and checks the iterative sampling: `cells` missing
/// cells, `passes` passes each committing at least one, every missing cell committed exactly
/// once, the observed pixels kept.
#[allow(clippy::unwrap_used)] // a test helper: a failed completion fails the test
fn assert_passes_commit_each_cell_once(
    r: &mut VqRefiner,
    f: &RgbdFrame,
    missing: &[bool],
    cells: usize,
    passes: usize,
) {
    let (w, h) = (f.width(), f.height());
    let out = r.complete_at(f, missing, Some(&Intrinsics::from_fov_x(w, h, 1.0))).unwrap();
    let trace = r.trace().clone();
    let expected: Vec<usize> = (0..trace.missing_cells.len()).filter(|&i| trace.missing_cells[i]).collect();
    assert_eq!(expected.len(), cells);
    assert_eq!(trace.passes.len(), passes, "{:?}", trace.passes);
    // the MaskGIT schedule: pass p commits ceil(open / (passes - p)) of the cells still open,
    // the last pass all of them
    let mut open = cells;
    let mut schedule = Vec::new();
    for p in 0..passes {
        let n = if p + 1 == passes { open } else { open.div_ceil(passes - p) };
        schedule.push(n);
        open -= n;
    }
    let committed: Vec<usize> = trace.passes.iter().map(Vec::len).collect();
    assert_eq!(committed, schedule, "cells committed per pass");
    let mut all: Vec<usize> = trace.passes.concat();
    all.sort_unstable();
    assert_eq!(all, expected, "every missing cell committed exactly once");
    for (i, m) in missing.iter().enumerate() {
        if !m {
            assert_eq!(out.colour.data[i], f.colour.data[i]);
            assert_eq!(out.depth_m.data[i], f.depth_m.data[i]);
        }
    }
}

#[test]
fn iterative_sampling_commits_every_missing_cell_once_and_keeps_observed_pixels() {
    let device = default_device();
    let cfg = ModelConfig { code_tau: Some(0.5), ..ModelConfig::tiny() };
    let model = VqModel::new(&cfg, 5, &device).unwrap();
    let options = RefinerOptions {
        sampling: Sampling::Temperature { temperature: 1.0, top_k: usize::MAX },
        cells_per_pass: 5,
        max_passes: 4,
        ..RefinerOptions::default()
    };
    let mut r = VqRefiner::new(model, cfg.clone(), options, device);
    let (w, h) = (32u32, 32u32);
    let f = frame(w, h, 9);
    // a 12 x 16 pixel hole: 3 x 4 = 12 missing cells of 4 x 4 pixels; ceil(12 / 5) = 3 passes,
    // spread evenly: ceil(12 / 3) = 4, ceil(8 / 2) = 4, the last 4 (not 5, 5, 2)
    let missing: Vec<bool> = (0..w * h).map(|p| (8..20).contains(&(p % w)) && (12..28).contains(&(p / w))).collect();
    assert_passes_commit_each_cell_once(&mut r, &f, &missing, 12, 3);
    assert_eq!(r.trace().passes.iter().map(Vec::len).collect::<Vec<_>>(), [4, 4, 4]);
    // 13 cells (the cell below the hole's left column too): ceil(13 / 5) = 3 passes of
    // ceil(13 / 3) = 5, ceil(8 / 2) = 4 and the last 4
    let mut thirteen = missing.clone();
    for y in 28..32 {
        for x in 8..12 {
            thirteen[(y * w + x) as usize] = true;
        }
    }
    assert_passes_commit_each_cell_once(&mut r, &f, &thirteen, 13, 3);
    assert_eq!(r.trace().passes.iter().map(Vec::len).collect::<Vec<_>>(), [5, 4, 4]);
    // max_passes caps the passes: 12 cells at 2 per pass would take 6; at most 4, of 3 each
    r.set_options(RefinerOptions { cells_per_pass: 2, ..options });
    assert_passes_commit_each_cell_once(&mut r, &f, &missing, 12, 4);
    assert_eq!(r.trace().passes.iter().map(Vec::len).collect::<Vec<_>>(), [3, 3, 3, 3]);
    // argmin is one pass and deterministic
    r.set_options(RefinerOptions { sampling: Sampling::Argmin, ..RefinerOptions::default() });
    let a = r.complete_at(&f, &missing, Some(&Intrinsics::from_fov_x(w, h, 1.0))).unwrap();
    assert_eq!(r.trace().passes.len(), 1);
    assert_eq!(r.complete_at(&f, &missing, Some(&Intrinsics::from_fov_x(w, h, 1.0))).unwrap(), a);
}

/// A codebook where codes 3 and 7 are Voronoi neighbours (at +-x) and every other code lies
/// far out in the orthogonal directions, so a distribution over just {3, 7} is expressible.
fn two_code_codebook(cfg: &ModelConfig) -> Vec<f32> {
    let d = cfg.embed_dim;
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut cb = vec![0.0f32; cfg.n_embed * d];
    for k in 0..cfg.n_embed {
        let row = &mut cb[k * d..(k + 1) * d];
        match k {
            3 => row[0] = 1.0,
            7 => row[0] = -1.0,
            _ => {
                let mut v: Vec<f32> = (1..d).map(|_| rng.random_range(-1.0..1.0)).collect();
                let n = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-3);
                v.iter_mut().for_each(|x| *x *= 3.0 / n);
                row[1..].copy_from_slice(&v);
            }
        }
    }
    cb
}

#[test]
fn a_tiny_sampler_learns_a_two_pattern_world_in_its_proportions() {
    // the world: the top half is grey and observed; the bottom half is missing and is pattern
    // A (code 3 everywhere) three times in four, pattern B (code 7) once in four
    let device = default_device();
    let cfg = ModelConfig { ray_channels: true, ..ModelConfig::tiny() };
    let base = VqModel::new(&ModelConfig::tiny(), 1, &device).unwrap();
    let mut tensors: BTreeMap<String, NamedTensor> = named_tensors(&base);
    tensors.insert(
        "quantize.embedding.weight".into(),
        NamedTensor { shape: vec![cfg.n_embed, cfg.embed_dim], values: two_code_codebook(&cfg) },
    );
    let (w, h) = (16u32, 16u32);
    let f = cfg.downsample_factor() as u32;
    let (cw, ch) = ((w / f) as usize, (h / f) as usize);
    let input = flat(w, h, [0.5, 0.5, 0.5], [0.0, 0.0, 0.0]);
    let missing: Vec<bool> = (0..w * h).map(|p| p / w >= h / 2).collect();
    let k = Intrinsics::from_fov_x(w, h, 1.0);
    let pattern = |code: u32| -> Vec<u32> { (0..cw * ch).map(|i| if i / cw >= ch / 2 { code } else { 0 }).collect() };
    let pairs: Vec<CodePair> = [3u32, 3, 3, 7]
        .iter()
        .map(|&c| CodePair { input: input.clone(), missing: missing.clone(), intrinsics: k, codes: pattern(c) })
        .collect();
    let tc = CodeTrainConfig {
        steps: 400,
        batch: 8,
        lr: 3e-2,
        lr_decay_from: Some(200),
        observed_weight: 0.2,
        tau_lr_scale: 1.0,
        target_smoothing: 0.0,
        ..CodeTrainConfig::default()
    };
    let mut trainer = CodeTrainer::new(&cfg, &tensors, &tc).unwrap();
    let first = trainer.evaluate(&pairs, 4).unwrap();
    // every batch holds the world's proportions exactly (6 A, 2 B), so the optimum is the
    // calibrated (3/4, 1/4) and not a batch's sampling noise
    let batch: Vec<CodePair> = pairs.iter().chain(&pairs).cloned().collect();
    for _ in 0..tc.steps {
        trainer.step_on(&batch).unwrap();
    }
    let last = trainer.evaluate(&pairs, 4).unwrap();
    // the best achievable cross-entropy on the missing cells is the entropy of (3/4, 1/4)
    let entropy = -(0.75f32 * 0.75f32.ln() + 0.25 * 0.25f32.ln());
    assert!(last.ce_missing < first.ce_missing, "{first:?} -> {last:?}");
    assert!(last.ce_missing < entropy + 0.05, "CE {} vs entropy {entropy}", last.ce_missing);
    // sampling at T = 1 through the refiner draws A and B in proportion
    let config = trainer.exported_config().unwrap();
    let options = RefinerOptions {
        sampling: Sampling::Temperature { temperature: 1.0, top_k: usize::MAX },
        ..RefinerOptions::default()
    };
    let mut refiner = VqRefiner::new(trainer.model.clone(), config, options, device);
    let cell = (ch - 1) * cw + 1; // a bottom cell
    let n = 400;
    let (mut a, mut b) = (0, 0);
    for s in 0..n {
        refiner.set_options(RefinerOptions { seed: s, ..options });
        refiner.complete_at(&input, &missing, Some(&k)).unwrap();
        let code = refiner.trace().codes[cell];
        a += (code == 3) as usize;
        b += (code == 7) as usize;
    }
    // a cross-entropy within 0.05 nats of the entropy leaves at most a few percent of the mass
    // on other codes
    assert!(a + b >= n as usize * 95 / 100, "only {} of {n} draws were pattern A or B", a + b);
    let share = a as f64 / (a + b) as f64;
    // binomial sd at n = 400 is 0.022; allow 3 sd plus the fit's own error
    assert!((share - 0.75).abs() < 0.1, "pattern A drawn {share:.3} of the A/B draws ({a} / {b})");
}

#[test]
fn revealing_cells_pastes_the_decoded_pixels_as_observed_and_leaves_the_rest() {
    // 8x8 pixels in cells of 4: cells 0 1 / 2 3; the right half (cells 1, 3) is missing, and
    // one pixel of cell 0
    let (input, decoded) = (frame(8, 8, 1), frame(8, 8, 2));
    let mut missing: Vec<bool> = (0..64).map(|p| p % 8 >= 4).collect();
    missing[0] = true;
    let pair = CodePair {
        input: input.clone(),
        missing: missing.clone(),
        intrinsics: Intrinsics::from_fov_x(8, 8, 1.0),
        codes: vec![0, 1, 2, 3],
    };
    let out = reveal_cells(&pair, &decoded, &[1], 4);
    for p in 0..64 {
        let in_cell_1 = p % 8 >= 4 && p / 8 < 4;
        let from = if in_cell_1 { &decoded } else { &input };
        assert_eq!(out.missing[p], missing[p] && !in_cell_1, "pixel {p}");
        assert_eq!(out.input.colour.data[p], from.colour.data[p], "pixel {p}");
        assert_eq!(out.input.depth_m.data[p], from.depth_m.data[p], "pixel {p}");
    }
    assert_eq!(out.codes, pair.codes);
    // revealing an observed cell changes nothing
    let same = reveal_cells(&pair, &decoded, &[2], 4);
    assert_eq!((same.input, same.missing), (pair.input, pair.missing));
}

#[test]
fn maskgit_training_reveals_part_of_a_hole_and_always_leaves_some_of_it_missing() {
    let device = default_device();
    let cfg = ModelConfig { ray_channels: true, ..ModelConfig::tiny() };
    let tensors = named_tensors(&VqModel::new(&ModelConfig::tiny(), 5, &device).unwrap());
    let k = Intrinsics::from_fov_x(16, 16, 1.0);
    // the bottom half missing: 8 of the 16 latent cells
    let pairs: Vec<CodePair> = (0..4)
        .map(|s| CodePair {
            input: frame(16, 16, s),
            missing: (0..256).map(|p| p / 16 >= 8).collect(),
            intrinsics: k,
            codes: (0..16).map(|i| (i * 3 + s as u32) % 32).collect(),
        })
        .collect();
    let counts = |reveal: f32| -> Vec<usize> {
        let tc = CodeTrainConfig { steps: 12, batch: 4, reveal, ..CodeTrainConfig::default() };
        let mut t = CodeTrainer::new(&cfg, &tensors, &tc).unwrap();
        (0..12).map(|_| t.step_on(&pairs).unwrap().missing_cells).collect()
    };
    assert!(counts(0.0).iter().all(|&n| n == 32), "without reveal every hole stays whole");
    let revealed = counts(1.0);
    assert!(revealed.iter().all(|&n| (4..=32).contains(&n)), "each pair keeps a missing cell: {revealed:?}");
    assert!(revealed.iter().any(|&n| n < 32), "no cell was ever revealed: {revealed:?}");
}

#[test]
fn checkpoints_resume_bit_identically_and_keep_the_decoder_frozen() {
    let device = default_device();
    let cfg = ModelConfig { ray_channels: true, ..ModelConfig::tiny() };
    let base = VqModel::new(&ModelConfig::tiny(), 4, &device).unwrap();
    let tensors = named_tensors(&base);
    let k = Intrinsics::from_fov_x(16, 16, 1.0);
    let pairs: Vec<CodePair> = (0..4)
        .map(|s| {
            let f = frame(16, 16, s);
            let missing: Vec<bool> = (0..256).map(|p| p % 16 >= 8).collect();
            CodePair { input: f, missing, intrinsics: k, codes: (0..16).map(|i| (i * 5 + s as u32) % 32).collect() }
        })
        .collect();
    let tc = CodeTrainConfig { steps: 6, batch: 2, ..CodeTrainConfig::default() };
    let dir = tempfile::tempdir().unwrap();
    let mut a = CodeTrainer::new(&cfg, &tensors, &tc).unwrap();
    for i in 0..3 {
        a.step_on(&pairs[i..i + 2]).unwrap();
    }
    a.save(dir.path()).unwrap();
    // the checkpoint is committed with a manifest, like the other trainers'; a corrupted copy of
    // it is refused naming the file, not resumed
    let manifest = sgam_model::checkpoint::verify_folder(&dir.path().join("ckpt")).unwrap();
    let listed: Vec<&str> = manifest.files.keys().map(String::as_str).collect();
    assert_eq!(listed, ["model.safetensors", "optim.bpk", "optim_tau.bpk", "state.json"]);
    let bad = tempfile::tempdir().unwrap();
    std::fs::create_dir(bad.path().join("ckpt")).unwrap();
    for name in listed.iter().chain(&["manifest.json"]) {
        std::fs::copy(dir.path().join("ckpt").join(name), bad.path().join("ckpt").join(name)).unwrap();
    }
    let mut bytes = std::fs::read(bad.path().join("ckpt/optim_tau.bpk")).unwrap();
    bytes[0] ^= 1;
    std::fs::write(bad.path().join("ckpt/optim_tau.bpk"), bytes).unwrap();
    let err = CodeTrainer::resume(bad.path(), None, None).unwrap_err().to_string();
    assert!(err.contains("optim_tau.bpk") && err.contains("CRC-32"), "{err}");
    let mut b = CodeTrainer::resume(dir.path(), None, None).unwrap();
    assert_eq!(b.step, 3);
    for i in 0..2 {
        let ra = a.step_on(&pairs[i..i + 2]).unwrap();
        let rb = b.step_on(&pairs[i..i + 2]).unwrap();
        assert_eq!(ra, rb);
    }
    let (wa, wb) = (a.weights(), b.weights());
    assert_eq!(wa, wb);
    // frozen parts are bit-identical to the starting model; the encoder moved
    for (name, t) in &tensors {
        if name.starts_with("decoder.") || name.starts_with("quantize.") || name.contains("quant_conv") {
            assert_eq!(&wa[name], t, "{name} changed");
        }
    }
    assert_ne!(wa["encoder.conv_out.weight"], tensors["encoder.conv_out.weight"]);
    // the ray channels start at zero weight: the widened conv_in equals the old one elsewhere
    let old = &tensors["conv_in.weight"].values;
    let fresh = CodeTrainer::new(&cfg, &tensors, &tc).unwrap().weights();
    let new = &fresh["conv_in.weight"].values;
    for o in 0..4 {
        assert_eq!(&new[o * 7..o * 7 + 5], &old[o * 5..o * 5 + 5]);
        assert_eq!(&new[o * 7 + 5..o * 7 + 7], &[0.0, 0.0]);
    }
}

/// A ground-like frame: depth from 13 m at the top row to 9 m at the bottom, colour by `seed`.
fn ground(w: u32, h: u32, seed: u64) -> RgbdFrame {
    let mut f = frame(w, h, seed);
    for (p, d) in f.depth_m.data.iter_mut().enumerate() {
        *d = 13.0 - 4.0 * (p as u32 / w) as f32 / (h - 1) as f32;
    }
    f
}

#[test]
fn decoder_tuning_moves_only_the_decoder_and_lowers_its_depth_error() {
    let device = default_device();
    let cfg = ModelConfig::tiny();
    let tensors = named_tensors(&VqModel::new(&cfg, 5, &device).unwrap());
    // the same seed builds the same codebook: the encoder's codes index the tuned model's codes
    let encoder = || VqModel::new(&cfg, 5, &device).unwrap();
    let frames: Vec<RgbdFrame> = (0..4).map(|s| ground(16, 16, s)).collect();
    let k = vec![Intrinsics::from_fov_x(16, 16, 1.0); 4];
    let tc = DecoderTuneConfig { steps: 80, lr: 3e-3, lr_decay_from: None, depth_weight: 4.0 };
    let mut tuner = DecoderTuner::new(&cfg, &tensors, encoder(), &cfg, &tc).unwrap();
    let before = tuner.evaluate(&frames, &k, 4).unwrap();
    let refs: Vec<&RgbdFrame> = frames.iter().collect();
    for _ in 0..40 {
        tuner.step_on(&refs, &k).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    tuner.save(dir.path()).unwrap();
    let mut resumed = DecoderTuner::resume(dir.path(), encoder(), &cfg, None).unwrap();
    for _ in 0..40 {
        let (a, b) = (tuner.step_on(&refs, &k).unwrap(), resumed.step_on(&refs, &k).unwrap());
        assert_eq!(a, b, "a resumed tuning must continue bit for bit");
    }
    let after = tuner.evaluate(&frames, &k, 4).unwrap();
    // an untrained decoder's disparity is unrelated to the ramp; 80 steps on four frames of one
    // geometry must at least halve its error
    assert!(
        after.l1_disparity < 0.5 * before.l1_disparity && after.depth_mae_m < 0.5 * before.depth_mae_m,
        "{before:?} -> {after:?}"
    );
    let w = tuner.weights();
    for (name, t) in &tensors {
        if name.starts_with("decoder.") || name.starts_with("post_quant_conv.") {
            continue;
        }
        assert_eq!(&w[name], t, "{name} changed: only the decoder may train");
    }
    assert_ne!(w["decoder.conv_out.weight"], tensors["decoder.conv_out.weight"]);
    // an encoder with another codebook is refused: its codes would decode to other pixels
    let other = VqModel::new(&cfg, 6, &device).unwrap();
    assert!(DecoderTuner::new(&cfg, &tensors, other, &cfg, &tc).is_err());
}

/// The draws of [`select_codes_by_class`] (computed in parallel, drawn in row order) equal those
/// of the plain sequential loop it replaced, value for value: same codes, same probabilities,
/// and the random stream left in the same place.
#[test]
fn two_level_draws_equal_the_sequential_reference() {
    fn draw_index(weights: &[f64], rng: &mut ChaCha8Rng) -> (usize, f64) {
        let total: f64 = weights.iter().sum();
        let mut u = rng.random::<f64>() * total;
        for (i, w) in weights.iter().enumerate() {
            if u < *w {
                return (i, total);
            }
            u -= w;
        }
        (0, total)
    }
    #[allow(clippy::too_many_arguments)]
    fn reference(
        dist: &[f32],
        n: usize,
        k: usize,
        missing: &[bool],
        temperature: f32,
        within: f32,
        plain: &[bool],
        rng: &mut ChaCha8Rng,
    ) -> (Vec<u32>, Vec<f32>) {
        let (mut codes, mut probs) = (Vec::new(), Vec::new());
        let t = temperature.max(1e-12) as f64;
        for i in 0..n {
            let row = &dist[i * k..(i + 1) * k];
            let nearest =
                row.iter().enumerate().fold((0, f32::INFINITY), |b, (j, &d)| if d < b.1 { (j, d) } else { b }).0;
            if !missing.get(i).copied().unwrap_or(false) || temperature <= 0.0 {
                codes.push(nearest as u32);
                probs.push(1.0);
                continue;
            }
            let in_plain = |j: usize| plain.get(j).copied().unwrap_or(false);
            let dmin = row[nearest] as f64;
            let mut mass = [0f64; 2];
            for (j, &d) in row.iter().enumerate() {
                mass[in_plain(j) as usize] += (-(d as f64 - dmin) / t).exp();
            }
            let total = mass[0] + mass[1];
            let class = rng.random::<f64>() * total >= mass[0];
            let p_class = mass[class as usize] / total.max(1e-300);
            let members = (0..k).filter(|&j| in_plain(j) == class);
            let (pick, p_within) = if within <= 0.0 {
                let best = members.fold(None, |b: Option<usize>, j| match b {
                    Some(b) if row[b] <= row[j] => Some(b),
                    _ => Some(j),
                });
                (best.unwrap_or(nearest), 1.0)
            } else {
                let tw = within as f64;
                let members: Vec<usize> = members.collect();
                let cmin = members.iter().map(|&j| row[j] as f64).fold(f64::INFINITY, f64::min);
                let weights: Vec<f64> = members.iter().map(|&j| (-(row[j] as f64 - cmin) / tw).exp()).collect();
                let (at, sum) = draw_index(&weights, rng);
                (members.get(at).copied().unwrap_or(nearest), weights.get(at).copied().unwrap_or(1.0) / sum.max(1e-300))
            };
            codes.push(pick as u32);
            probs.push((p_class * p_within) as f32);
        }
        (codes, probs)
    }
    let mut gen = ChaCha8Rng::seed_from_u64(5);
    let (n, k) = (300, 64);
    // ties included: distances on a coarse grid
    let table: Vec<f32> = (0..n * k).map(|_| (gen.random_range(0..40) as f32) * 0.25).collect();
    let missing: Vec<bool> = (0..n).map(|_| gen.random_bool(0.6)).collect();
    for plain in [(0..k).map(|j| j % 3 == 0).collect::<Vec<_>>(), vec![true; k], vec![false; 5]] {
        for (t, within) in [(1.0, 0.5), (2.0, 2.0), (1.0, 0.0), (0.0, 0.5), (f32::NAN, 0.5)] {
            let (mut a, mut b) = (ChaCha8Rng::seed_from_u64(9), ChaCha8Rng::seed_from_u64(9));
            let ours = select_codes_by_class(&table, n, k, &missing, t, within, &plain, None, &mut a);
            let theirs = reference(&table, n, k, &missing, t, within, &plain, &mut b);
            assert_eq!(ours, theirs, "t {t}, within {within}");
            assert_eq!(a.random::<u64>(), b.random::<u64>(), "t {t}, within {within}: the stream moved differently");
        }
    }
}

/// [`select_codes`] (rows computed in parallel, drawn in order) equals the sequential loop it
/// replaced, draw for draw, and leaves the random stream in the same place.
#[test]
fn temperature_draws_equal_the_sequential_reference() {
    fn reference(
        dist: &[f32],
        n: usize,
        k: usize,
        missing: Option<&[bool]>,
        sampling: Sampling,
        rng: &mut ChaCha8Rng,
    ) -> Vec<u32> {
        let mut out = Vec::with_capacity(n);
        for i in 0..n {
            let row = &dist[i * k..(i + 1) * k];
            let nearest =
                row.iter().enumerate().fold((0, f32::INFINITY), |b, (j, &d)| if d < b.1 { (j, d) } else { b }).0;
            let sample = missing.is_some_and(|m| m.get(i).copied().unwrap_or(false));
            let choice = match sampling {
                Sampling::Temperature { temperature, top_k } if sample && temperature > 0.0 && top_k > 1 => {
                    let mut order: Vec<usize> = (0..k).collect();
                    let top = top_k.min(k);
                    order.select_nth_unstable_by(top - 1, |a, b| row[*a].total_cmp(&row[*b]).then(a.cmp(b)));
                    let mut cand: Vec<usize> = order[..top].to_vec();
                    cand.sort_by(|a, b| row[*a].total_cmp(&row[*b]).then(a.cmp(b)));
                    let dmin = row[cand[0]];
                    let weights: Vec<f64> =
                        cand.iter().map(|&j| (-((row[j] - dmin) as f64) / temperature as f64).exp()).collect();
                    let total: f64 = weights.iter().sum();
                    let mut u = rng.random::<f64>() * total;
                    let mut at = 0;
                    for (i, w) in weights.iter().enumerate() {
                        if u < *w {
                            at = i;
                            break;
                        }
                        u -= w;
                    }
                    cand[at]
                }
                _ => nearest,
            };
            out.push(choice as u32);
        }
        out
    }
    let mut gen = ChaCha8Rng::seed_from_u64(8);
    let (n, k) = (200, 50);
    let table: Vec<f32> = (0..n * k).map(|_| (gen.random_range(0..30) as f32) * 0.3).collect();
    let missing: Vec<bool> = (0..n).map(|_| gen.random_bool(0.5)).collect();
    for sampling in [
        Sampling::Argmin,
        Sampling::Temperature { temperature: 1.0, top_k: usize::MAX },
        Sampling::Temperature { temperature: 0.5, top_k: 4 },
        Sampling::Temperature { temperature: 2.0, top_k: 1 },
    ] {
        for m in [Some(missing.as_slice()), None] {
            let (mut a, mut b) = (ChaCha8Rng::seed_from_u64(2), ChaCha8Rng::seed_from_u64(2));
            assert_eq!(
                select_codes(&table, n, k, m, sampling, &mut a),
                reference(&table, n, k, m, sampling, &mut b),
                "{sampling:?}"
            );
            assert_eq!(a.random::<u64>(), b.random::<u64>(), "{sampling:?}: the stream moved differently");
        }
    }
}
