//! The scene-wide context: windows that cover a hole, a fresh context that changes nothing, a
//! trained one that sees its whole window, training that learns, and checkpoints that resume.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sgam_core::{Intrinsics, RgbdFrame};
use sgam_model::burn::tensor::{Tensor, TensorData};
use sgam_model::context::{CellState, ContextConfig, ContextInput};
use sgam_model::context_train::{draw_states, ContextEngine, ContextPair, ContextTrainConfig, ContextTrainer};
use sgam_model::params::named_tensors;
use sgam_model::refiner::context_windows;
use sgam_model::{ModelConfig, RefinerOptions, Sampling, VqModel, VqRefiner};

fn tiny_context_config() -> ModelConfig {
    ModelConfig {
        code_head: true,
        code_tau: Some(1.0),
        context: Some(ContextConfig { dim: 16, layers: 2, heads: 2, mlp_ratio: 2, window_cells: 8, margin_cells: 2 }),
        ..ModelConfig::tiny()
    }
}

#[test]
fn windows_cover_every_missing_cell_once_and_see_their_margin() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for case in 0..40 {
        let (rows, cols) = (rng.random_range(1..40usize), rng.random_range(1..40usize));
        let p = rng.random_range(0.0..1.0f64);
        let missing: Vec<bool> = (0..rows * cols).map(|_| rng.random_bool(p)).collect();
        let (window, margin) = (16, 3);
        let wins = context_windows(&missing, [rows, cols], window, margin);
        let mut covered = vec![0u32; rows * cols];
        for w in &wins {
            let [cy, cx, ch, cw] = w.core;
            let [wy, wx, wh, ww] = w.window;
            assert!(ch <= window - 2 * margin && cw <= window - 2 * margin, "case {case}: core {:?}", w.core);
            assert!(wy + wh <= rows && wx + ww <= cols, "case {case}: window {:?} leaves the grid", w.window);
            assert!(wh <= window && ww <= window, "case {case}: window {:?} too large", w.window);
            assert!(wy <= cy && cy + ch <= wy + wh && wx <= cx && cx + cw <= wx + ww, "case {case}: core outside");
            // a margin on every side the grid allows
            assert!(cy - wy >= margin.min(cy) && cx - wx >= margin.min(cx), "case {case}: no margin before {w:?}");
            assert!(
                wy + wh - (cy + ch) >= margin.min(rows - cy - ch) && wx + ww - (cx + cw) >= margin.min(cols - cx - cw),
                "case {case}: no margin after {w:?}"
            );
            for y in cy..cy + ch {
                for x in cx..cx + cw {
                    covered[y * cols + x] += 1;
                }
            }
        }
        for i in 0..rows * cols {
            assert!(covered[i] <= 1, "case {case}: cell {i} in two cores");
            if missing[i] {
                assert_eq!(covered[i], 1, "case {case}: missing cell {i} in no core");
            }
        }
    }
    assert!(context_windows(&[false; 12], [3, 4], 16, 3).is_empty());
}

fn random_input(cfg: &ModelConfig, states: &[CellState], shape: [usize; 3], seed: u64) -> ContextInput {
    let device = sgam_model::default_device();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n = states.len();
    let feats: Vec<f32> = (0..n * cfg.z_channels).map(|_| rng.random_range(-1.0..1.0)).collect();
    let codebook: Vec<f32> = (0..cfg.n_embed * cfg.embed_dim).map(|_| rng.random_range(-1.0..1.0)).collect();
    let feats = Tensor::<2>::from_data(TensorData::new(feats, [n, cfg.z_channels]), &device);
    let codebook = Tensor::<2>::from_data(TensorData::new(codebook, [cfg.n_embed, cfg.embed_dim]), &device);
    ContextInput::new(feats, states, &codebook, shape)
}

fn host(t: Tensor<2>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().unwrap_or_default()
}

#[test]
fn a_fresh_context_adds_nothing_and_a_trained_one_sees_its_whole_window() {
    let cfg = tiny_context_config();
    let device = sgam_model::default_device();
    let model = VqModel::new(&cfg, 1, &device).expect("model");
    let context = model.context.expect("context");
    let states = vec![CellState::Open; 64];
    let residual = host(context.forward(random_input(&cfg, &states, [1, 8, 8], 5)));
    assert_eq!(residual.len(), 64 * cfg.n_embed);
    assert!(residual.iter().all(|v| *v == 0.0), "a fresh context must leave the head's logits alone");

    // with a non-zero output, a change at one corner reaches the opposite corner (attention),
    // though the positional convolution alone reaches one cell per block
    let mut weights = named_tensors(&context);
    for (name, t) in weights.iter_mut() {
        if name.starts_with("out.") {
            let mut rng = ChaCha8Rng::seed_from_u64(9);
            t.values.iter_mut().for_each(|v| *v = rng.random_range(-0.5..0.5));
        }
    }
    let context = sgam_model::params::load_named(context, &weights, false, false).expect("load");
    let before = host(context.forward(random_input(&cfg, &states, [1, 8, 8], 5)));
    let mut changed = states.clone();
    changed[0] = CellState::Revealed(7);
    let after = host(context.forward(random_input(&cfg, &changed, [1, 8, 8], 5)));
    let k = cfg.n_embed;
    let far = 63 * k..64 * k;
    let diff: f32 = before[far.clone()].iter().zip(&after[far]).map(|(a, b)| (a - b).abs()).sum();
    assert!(diff > 1e-4, "revealing cell (0, 0) must change cell (7, 7)'s logits (diff {diff})");
}

fn toy_pairs(cfg: &ModelConfig, n: usize, seed: u64) -> Vec<ContextPair> {
    // a learnable rule only the context can use: every missing cell's code is the code of the
    // pair (one per pair, shared by all its cells); features carry nothing about it
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let code = rng.random_range(0..4u32);
            let missing: Vec<bool> = (0..16).map(|i| i % 4 >= 1).collect();
            ContextPair {
                features: (0..16 * cfg.z_channels).map(|_| rng.random_range(-0.1..0.1)).collect(),
                codes: vec![code; 16],
                missing,
                shape: [4, 4],
            }
        })
        .collect()
}

#[test]
fn training_uses_revealed_cells_and_resumes_where_it_stopped() {
    let cfg = tiny_context_config();
    let device = sgam_model::default_device();
    let init = named_tensors(&VqModel::new(&ModelConfig { context: None, ..cfg.clone() }, 2, &device).expect("model"));
    let tc = ContextTrainConfig {
        steps: 200,
        batch: 8,
        lr: 3e-3,
        warmup: 10,
        whole_hole: 0.0,
        target_smoothing: 0.0,
        ckpt_every: 1000,
        ..ContextTrainConfig::default()
    };
    let mut trainer = ContextTrainer::new(&cfg, &init, &tc).expect("trainer");
    let pairs = toy_pairs(&cfg, 64, 1);
    let val = toy_pairs(&cfg, 32, 2);
    let start = trainer.evaluate(&val, 0.0, 8).expect("eval");
    assert!((start.ce - start.ce_head).abs() < 1e-4, "a fresh context changes the head's CE: {start:?}");
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for _ in 0..120 {
        let batch: Vec<&ContextPair> = (0..8).map(|_| &pairs[rng.random_range(0..pairs.len())]).collect();
        trainer.step_on(&batch).expect("step");
    }
    let end = trainer.evaluate(&val, 0.0, 8).expect("eval");
    // with revealed cells the pair's code is known: the CE falls far below the head's
    assert!(end.ce < 0.5 * start.ce_head, "context CE {} against the head's {}", end.ce, start.ce_head);
    // nothing revealed: the code cannot be known, the CE stays near a uniform guess over the 4
    let whole = trainer.evaluate(&val, 1.0, 8).expect("eval");
    assert!(whole.ce > 0.8 * (4f32).ln(), "first-pass CE {} below what the data allows", whole.ce);

    let dir = tempfile::tempdir().expect("tempdir");
    trainer.save(dir.path()).expect("save");
    let resumed = ContextTrainer::resume(dir.path(), None, None).expect("resume");
    assert_eq!(resumed.step, trainer.step);
    assert_eq!(resumed.weights(), trainer.weights());
    // a damaged checkpoint is refused, naming the file
    let weights = dir.path().join("ckpt/model.safetensors");
    let mut bytes = std::fs::read(&weights).expect("read");
    let last = bytes.len() - 1;
    bytes[last] ^= 0xff;
    std::fs::write(&weights, bytes).expect("write");
    let err = ContextTrainer::resume(dir.path(), None, None).expect_err("damaged").to_string();
    assert!(err.contains("model.safetensors"), "{err}");
}

#[test]
fn the_kernels_train_as_burns_autodiff_does_and_resume_across_engines() {
    let cfg = tiny_context_config();
    let device = sgam_model::default_device();
    let init = named_tensors(&VqModel::new(&ModelConfig { context: None, ..cfg.clone() }, 2, &device).expect("model"));
    // soft targets (the default), a decaying learning rate
    let tc = ContextTrainConfig {
        steps: 30,
        batch: 8,
        lr: 2e-3,
        warmup: 5,
        ckpt_every: 1000,
        ..ContextTrainConfig::default()
    };
    let pairs = toy_pairs(&cfg, 64, 5);
    let val = toy_pairs(&cfg, 32, 6);
    let mut a = ContextTrainer::new_on(&cfg, &init, &tc, ContextEngine::Kernels).expect("kernels");
    let mut b = ContextTrainer::new_on(&cfg, &init, &tc, ContextEngine::Burn).expect("burn");
    assert_eq!((a.engine(), b.engine()), (ContextEngine::Kernels, ContextEngine::Burn));
    let (va, vb) = (a.evaluate(&val, 0.0, 8).expect("eval"), b.evaluate(&val, 0.0, 8).expect("eval"));
    assert_eq!(va.open_cells, vb.open_cells);
    assert!((va.ce - vb.ce).abs() < 1e-4 && (va.ce_head - vb.ce_head).abs() < 1e-4, "{va:?} vs {vb:?}");
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for step in 0..30 {
        let batch: Vec<&ContextPair> = (0..8).map(|_| &pairs[rng.random_range(0..pairs.len())]).collect();
        let (ra, rb) = (a.step_on(&batch).expect("step"), b.step_on(&batch).expect("step"));
        assert_eq!((ra.step, ra.open_cells), (rb.step, rb.open_cells), "the same states drawn");
        // Adam moves every weight by about the learning rate whatever the gradient's size, so
        // the two drift apart by rounding; the losses stay together
        assert!((ra.ce - rb.ce).abs() < 0.02 * rb.ce.max(1.0), "step {step}: CE {} against burn's {}", ra.ce, rb.ce);
    }
    let (va, vb) = (a.evaluate(&val, 0.0, 8).expect("eval"), b.evaluate(&val, 0.0, 8).expect("eval"));
    assert!(va.ce < va.ce_head - 0.05, "the kernels learned nothing: {va:?}");
    assert!((va.ce - vb.ce).abs() < 0.02 * vb.ce, "after 30 steps: {va:?} against burn's {vb:?}");
    // each engine resumes the other's checkpoint: same weights and step, fresh optimizer
    let dir = tempfile::tempdir().expect("tempdir");
    a.save(dir.path()).expect("save");
    assert!(dir.path().join("ckpt/optim.safetensors").exists());
    let same = ContextTrainer::resume_on(dir.path(), None, None, ContextEngine::Kernels).expect("resume");
    let other = ContextTrainer::resume_on(dir.path(), None, None, ContextEngine::Burn).expect("resume");
    assert_eq!((same.step, other.step), (30, 30));
    assert_eq!(same.weights(), a.weights());
    let close = |x: &std::collections::BTreeMap<String, sgam_model::params::NamedTensor>| {
        x.iter().all(|(k, t)| t.values.iter().zip(&a.weights()[k].values).all(|(p, q)| (p - q).abs() < 1e-6))
    };
    assert!(close(&other.weights()), "burn resumed other weights");
    // the kernels' moments came back: the next steps equal the uninterrupted run's
    let batch: Vec<&ContextPair> = (0..8).map(|i| &pairs[i]).collect();
    let mut same = same;
    let (r1, r2) = (a.step_on(&batch).expect("step"), same.step_on(&batch).expect("step"));
    assert_eq!(r1, r2);
    assert_eq!(a.weights(), same.weights());
}

#[test]
fn states_keep_observed_cells_and_leave_one_open() {
    let cfg = tiny_context_config();
    let pairs = toy_pairs(&cfg, 1, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for _ in 0..200 {
        let s = draw_states(&pairs[0], 0.0, &mut rng);
        for (i, st) in s.iter().enumerate() {
            assert_eq!(*st == CellState::Observed, !pairs[0].missing[i]);
            if let CellState::Revealed(c) = st {
                assert_eq!(*c, pairs[0].codes[i]);
            }
        }
        assert!(s.contains(&CellState::Open));
    }
    let whole = draw_states(&pairs[0], 1.0, &mut rng);
    assert!(!whole.iter().any(|s| matches!(s, CellState::Revealed(_))));
}

#[test]
fn the_refiner_with_a_context_draws_every_missing_cell_once_and_keeps_observed_pixels() {
    let cfg = tiny_context_config();
    let device = sgam_model::default_device();
    let model = VqModel::new(&cfg, 3, &device).expect("model");
    let options = RefinerOptions {
        sampling: Sampling::Temperature { temperature: 1.0, top_k: 0 },
        cells_per_pass: 3,
        max_passes: 4,
        ..RefinerOptions::default()
    };
    let mut refiner = VqRefiner::new(model, cfg.clone(), options, device);
    let (w, h) = (32u32, 32u32);
    let mut frame = RgbdFrame::empty(w, h);
    for (i, c) in frame.colour.data.iter_mut().enumerate() {
        *c = [(i % 7) as f32 / 7.0, 0.5, 0.2];
    }
    frame.depth_m.data.iter_mut().for_each(|d| *d = 10.0);
    // the right half missing
    let missing: Vec<bool> = (0..(w * h) as usize).map(|i| i % w as usize >= 16).collect();
    let out = refiner.complete_at(&frame, &missing, Some(&Intrinsics::from_fov_x(w, h, 1.0))).expect("refine");
    let trace = refiner.trace().clone();
    let committed: Vec<usize> = trace.passes.iter().flatten().copied().collect();
    let mut sorted = committed.clone();
    sorted.sort_unstable();
    sorted.dedup();
    assert_eq!(sorted.len(), committed.len(), "a cell committed twice");
    let want: Vec<usize> = (0..trace.missing_cells.len()).filter(|&i| trace.missing_cells[i]).collect();
    assert_eq!(sorted, want, "every missing cell committed once");
    // Per window, in order: the MaskGIT schedule over its core's missing cells (ceil(open /
    // (passes - p)) on pass p, the rest on the last), passes = ceil(cells / cells_per_pass) at
    // most max_passes, each pass committing cells of that core only. Here: 8 x 8 cells of 4
    // pixels, the right half (4 columns) missing, cores of 8 - 2 x 2 = 4 cells per side: two
    // cores of 16 cells, each ceil(16 / 3) = 6 -> 4 passes of 4.
    let (cells, cols) = (&trace.missing_cells, 8usize);
    let windows = context_windows(cells, [8, cols], 8, 2);
    let mut schedule: Vec<(usize, [usize; 4])> = Vec::new();
    for win in &windows {
        let [y0, x0, h, w] = win.core;
        let mut open = (y0..y0 + h).flat_map(|y| (x0..x0 + w).map(move |x| y * cols + x)).filter(|&i| cells[i]).count();
        let passes = open.div_ceil(3).clamp(1, 4);
        for p in 0..passes {
            let n = if p + 1 == passes { open } else { open.div_ceil(passes - p) };
            schedule.push((n, win.core));
            open -= n;
        }
    }
    assert_eq!(schedule.iter().map(|s| s.0).collect::<Vec<_>>(), [4; 8]);
    assert_eq!(trace.passes.iter().map(Vec::len).collect::<Vec<_>>(), [4; 8], "cells committed per pass");
    for (pass, (_, [y0, x0, h, w])) in trace.passes.iter().zip(&schedule) {
        assert!(
            pass.iter().all(|&i| (*y0..y0 + h).contains(&(i / cols)) && (*x0..x0 + w).contains(&(i % cols))),
            "{pass:?} outside its window's core {:?}",
            [y0, x0, h, w]
        );
    }
    for i in (0..(w * h) as usize).filter(|&i| !missing[i]) {
        assert_eq!(out.colour.data[i], frame.colour.data[i]);
    }
}

#[test]
fn a_thin_band_at_the_border_waits_without_depth_and_a_deeper_hole_is_drawn() {
    let cfg = tiny_context_config();
    let device = sgam_model::default_device();
    let (w, h) = (32u32, 32u32);
    let mut frame = RgbdFrame::empty(w, h);
    for (i, c) in frame.colour.data.iter_mut().enumerate() {
        *c = [(i % 7) as f32 / 7.0, 0.5, 0.2];
    }
    frame.depth_m.data.iter_mut().for_each(|d| *d = 10.0);
    // 8 x 8 cells of 4 pixels: a band of 2 cells along the left side, and a hole of 3 x 3 cells
    // in the middle that touches no side
    let band = |x: usize| x < 8;
    let middle = |x: usize, y: usize| (12..24).contains(&x) && (12..24).contains(&y);
    let missing: Vec<bool> =
        (0..(w * h) as usize).map(|i| band(i % w as usize) || middle(i % w as usize, i / w as usize)).collect();
    let k = Intrinsics::from_fov_x(w, h, 1.0);
    // (not given: the model's own draws do not wait)
    for bands_wait in [None, Some(0), Some(2), Some(3)] {
        let options = RefinerOptions {
            sampling: Sampling::Temperature { temperature: 1.0, top_k: 0 },
            bands_wait,
            ..RefinerOptions::default()
        };
        let model = VqModel::new(&cfg, 3, &device).expect("model");
        let mut refiner = VqRefiner::new(model, cfg.clone(), options, device.clone());
        let out = refiner.complete_at(&frame, &missing, Some(&k)).expect("refine");
        let drawn = refiner.trace().missing_cells.clone();
        let band_cells: Vec<usize> = (0..64).filter(|c| c % 8 < 2).collect();
        let middle_cells: Vec<usize> =
            (0..64).filter(|c| (3..6).contains(&(c % 8)) && (3..6).contains(&(c / 8))).collect();
        let waits = bands_wait.unwrap_or(0) > 2;
        assert!(band_cells.iter().all(|&c| drawn[c] != waits), "bands_wait {bands_wait:?}: band drawn {}", !waits);
        assert!(middle_cells.iter().all(|&c| drawn[c]), "bands_wait {bands_wait:?}: the middle hole is always drawn");
        for i in 0..(w * h) as usize {
            let (x, y) = (i % w as usize, i / w as usize);
            if band(x) {
                assert_eq!(out.depth_m.data[i] == 0.0, waits, "bands_wait {bands_wait:?}: band pixel {x},{y} depth");
            } else if middle(x, y) {
                assert!(out.depth_m.data[i] > 0.0, "the middle hole's pixel {x},{y} has depth");
            } else {
                assert_eq!(out.colour.data[i], frame.colour.data[i], "observed pixels kept");
            }
        }
    }
}
