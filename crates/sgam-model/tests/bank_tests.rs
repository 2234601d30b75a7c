//! Completion from a code bank: a hole takes a bank frame's codes, a thin band at the border
//! waits (no depth), and a bank of another codebook is refused.

mod common;

use std::sync::Arc;

use common::frame;
use sgam_core::Intrinsics;
use sgam_model::bank::CodeBank;
use sgam_model::{default_device, ModelConfig, RefinerOptions, Sampling, VqModel, VqRefiner};

/// A tiny generative refiner and a bank of four random frames' codes.
#[allow(clippy::unwrap_used)] // a test helper: a failure fails the test
fn refiner_and_bank() -> (VqRefiner, CodeBank) {
    let device = default_device();
    let cfg = ModelConfig { code_tau: Some(0.5), ..ModelConfig::tiny() };
    let model = VqModel::new(&cfg, 5, &device).unwrap();
    let options = RefinerOptions {
        sampling: Sampling::Temperature { temperature: 1.0, top_k: usize::MAX },
        ..RefinerOptions::default()
    };
    let mut r = VqRefiner::new(model, cfg.clone(), options, device);
    let k = Intrinsics::from_fov_x(32, 32, 1.0);
    let mut codes = Vec::new();
    for s in 0..4 {
        codes.extend(r.frame_codes(&frame(32, 32, 100 + s), &k).unwrap().iter().map(|&c| c as u16));
    }
    let f = cfg.downsample_factor();
    let bank = CodeBank {
        rows: 32 / f,
        cols: 32 / f,
        n_embed: cfg.n_embed,
        codebook_crc32: r.codebook_crc32().unwrap(),
        codes,
    };
    (r, bank)
}

#[test]
fn a_hole_takes_a_bank_frames_codes_and_observed_pixels_stay() {
    let (mut r, bank) = refiner_and_bank();
    let cols = bank.cols;
    r.set_bank(Some(Arc::new(bank.clone()))).unwrap();
    let (w, h) = (32u32, 32u32);
    let g = frame(w, h, 7);
    // an interior hole of 3 x 3 cells (pixels 8..20)
    let missing: Vec<bool> = (0..w * h).map(|p| (8..20).contains(&(p % w)) && (8..20).contains(&(p / w))).collect();
    let out = r.complete(&g, &missing).unwrap();
    let t = r.trace();
    assert_eq!(t.bank_draws.len(), 1, "{:?}", t.bank_draws);
    let d = t.bank_draws[0];
    assert_eq!(d.cells, 9);
    let src = bank.frame(d.frame);
    for (i, m) in t.missing_cells.iter().enumerate() {
        if *m {
            let (y, x) = ((i / cols) as i32 + d.shift[0], (i % cols) as i32 + d.shift[1]);
            assert_eq!(t.codes[i], src[y as usize * cols + x as usize] as u32, "cell {i} of draw {d:?}");
        }
    }
    for p in 0..(w * h) as usize {
        if !missing[p] {
            assert_eq!(out.colour.data[p], g.colour.data[p]);
            assert_eq!(out.depth_m.data[p], g.depth_m.data[p]);
        } else {
            assert!(out.depth_m.data[p] > 0.0, "pixel {p} of a filled hole has no depth");
        }
    }
}

#[test]
fn a_thin_band_at_the_border_waits_with_no_depth() {
    let (mut r, bank) = refiner_and_bank();
    r.set_bank(Some(Arc::new(bank))).unwrap();
    let (w, h) = (32u32, 32u32);
    let g = frame(w, h, 8);
    // the two leftmost cell columns (8 px): thinner than 3 cells
    let missing: Vec<bool> = (0..w * h).map(|p| p % w < 8).collect();
    let out = r.complete(&g, &missing).unwrap();
    assert!(r.trace().bank_draws.is_empty(), "{:?}", r.trace().bank_draws);
    for p in 0..(w * h) as usize {
        assert_eq!(out.depth_m.data[p] == 0.0, missing[p], "pixel {p}");
    }
    // three columns reach in far enough: filled
    let missing: Vec<bool> = (0..w * h).map(|p| p % w < 12).collect();
    let out = r.complete(&g, &missing).unwrap();
    assert_eq!(r.trace().bank_draws.len(), 1);
    assert!(out.depth_m.data.iter().all(|d| *d > 0.0));
}

#[test]
fn a_bank_of_another_codebook_is_refused() {
    let (mut r, bank) = refiner_and_bank();
    let other = CodeBank { codebook_crc32: bank.codebook_crc32 ^ 1, ..bank.clone() };
    let e = r.set_bank(Some(Arc::new(other))).unwrap_err().to_string();
    assert!(e.contains("another model's codebook"), "{e}");
    let smaller = CodeBank { n_embed: bank.n_embed - 1, ..bank };
    assert!(r.set_bank(Some(Arc::new(smaller))).is_err());
    assert!(r.bank().is_none());
}
