//! Completion from a code bank: a hole takes a bank frame's codes, a thin band at the border
//! waits (no depth), a bank of another codebook is refused, and a bank with its frames' pixels
//! (a seed's own bank) pastes those pixels into every hole, however small, at the depth of what
//! surrounds it.

mod common;

use std::sync::Arc;

use common::frame;
use sgam_core::Intrinsics;
use sgam_model::bank::{BankPixels, CodeBank};
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

#[test]
fn a_rolled_bank_and_its_pixels_agree_cell_for_cell() {
    let (mut r, _) = refiner_and_bank();
    let k = Intrinsics::from_fov_x(32, 32, 1.0);
    let frames = [frame(32, 32, 40), frame(32, 32, 41)];
    let grids: Vec<Vec<u32>> = frames.iter().map(|f| r.frame_codes(f, &k).unwrap()).collect();
    let side = grids[0].len().isqrt();
    // rows rolled by 2, columns by 3
    let bank = CodeBank::rolled(&grids, [side, side], [2, 3], r.config().n_embed, r.codebook_crc32().unwrap());
    let rolls = side.div_ceil(2) * side.div_ceil(3);
    assert_eq!(bank.len(), 2 * rolls);
    let pixels = BankPixels { bases: frames.to_vec(), roll_cells: [2, 3] };
    let mut offsets = std::collections::HashSet::new();
    for f in 0..bank.len() {
        for cell in 0..side * side {
            let (base, [y, x]) = pixels.source(&bank, f, cell).unwrap();
            let g = if std::ptr::eq(base, &pixels.bases[0]) { 0 } else { 1 };
            assert_eq!(g, f / rolls, "frame {f}");
            assert_eq!(bank.frame(f)[cell] as u32, grids[g][y * side + x], "frame {f} cell {cell}");
            if cell == 0 {
                offsets.insert((g, y, x));
            }
        }
    }
    // every copy starts somewhere else: the rolls reach rows as well as columns
    assert_eq!(offsets.len(), bank.len());
    assert!(offsets.iter().any(|&(_, y, _)| y > 0) && offsets.iter().any(|&(_, _, x)| x > 0));
    assert!(pixels.source(&bank, bank.len(), 0).is_none());
}

#[test]
fn with_the_banks_pixels_every_hole_takes_them_even_one_pixel_at_its_surroundings_depth() {
    let (mut r, _) = refiner_and_bank();
    let (w, h) = (32u32, 32u32);
    let k = Intrinsics::from_fov_x(w, h, 1.0);
    // the bank's frames hold a surface 10 m away, the frame to complete one 12.5 m away: what
    // a hole takes from the bank is moved to the depth of what surrounds it (x 1.25)
    let mut frames = [frame(w, h, 50), frame(w, h, 51)];
    for fr in &mut frames {
        fr.depth_m.data.fill(10.0);
    }
    let grids: Vec<Vec<u32>> = frames.iter().map(|f| r.frame_codes(f, &k).unwrap()).collect();
    let side = grids[0].len().isqrt();
    let f = 32 / side;
    let bank =
        Arc::new(CodeBank::rolled(&grids, [side, side], [0, 2], r.config().n_embed, r.codebook_crc32().unwrap()));
    let pixels = Arc::new(BankPixels { bases: frames.to_vec(), roll_cells: [0, 2] });
    r.set_bank(Some(bank.clone())).unwrap();
    r.set_bank_pixels(Some(pixels.clone()));
    let mut g = frame(w, h, 9);
    g.depth_m.data.fill(12.5);
    // a 2 x 2-cell hole (cells 1..3) and, in a cell away from it and from the border, one
    // missing pixel: each is filled from the bank (without the bank's pixels a cell with one
    // missing pixel counts as observed, and its pixel gets the decoder's drawing)
    assert!(side >= 7, "{side} cells a side");
    let (fw, last) = (f as u32, (side - 3) as u32 * f as u32);
    let lone = (last + 1) * w + last + 2;
    let missing: Vec<bool> =
        (0..w * h).map(|p| ((fw..3 * fw).contains(&(p % w)) && (fw..3 * fw).contains(&(p / w))) || p == lone).collect();
    let out = r.complete(&g, &missing).unwrap();
    let t = r.trace();
    assert_eq!(t.bank_draws.len(), 2, "the hole and the lone pixel's cell: {:?}", t.bank_draws);
    let mut draws = t.bank_draws.iter();
    let mut checked = 0;
    for hole in sgam_model::bank::components(&t.missing_cells, side, side) {
        let d = draws.next().unwrap();
        for &cell in &hole {
            let (y, x) = ((cell / side) as i32 + d.shift[0], (cell % side) as i32 + d.shift[1]);
            let (base, [sy, sx]) = pixels.source(&bank, d.frame, y as usize * side + x as usize).unwrap();
            for dy in 0..f {
                for dx in 0..f {
                    let p = (cell / side * f + dy) * w as usize + cell % side * f + dx;
                    let q = (sy * f + dy) * w as usize + sx * f + dx;
                    if missing[p] {
                        assert_eq!(out.colour.data[p], base.colour.data[q], "pixel {p}");
                        assert!((out.depth_m.data[p] - 1.25 * base.depth_m.data[q]).abs() < 1e-4, "pixel {p}");
                        checked += 1;
                    } else {
                        assert_eq!(out.colour.data[p], g.colour.data[p], "observed pixel {p}");
                    }
                }
            }
        }
    }
    assert_eq!(checked, missing.iter().filter(|m| **m).count());
}

#[test]
fn with_the_banks_pixels_a_band_that_waits_is_coloured_from_them_with_no_depth() {
    let (mut r, _) = refiner_and_bank();
    let (w, h) = (32u32, 32u32);
    let k = Intrinsics::from_fov_x(w, h, 1.0);
    let frames = [frame(w, h, 60), frame(w, h, 61)];
    let grids: Vec<Vec<u32>> = frames.iter().map(|f| r.frame_codes(f, &k).unwrap()).collect();
    let side = grids[0].len().isqrt();
    let f = (w as usize / side) as u32;
    r.set_bank(Some(Arc::new(CodeBank::rolled(
        &grids,
        [side, side],
        [0, 2],
        r.config().n_embed,
        r.codebook_crc32().unwrap(),
    ))))
    .unwrap();
    r.set_bank_pixels(Some(Arc::new(BankPixels { bases: frames.to_vec(), roll_cells: [0, 2] })));
    let g = frame(w, h, 10);
    // the leftmost cell column: thinner than 3 cells, it waits
    let missing: Vec<bool> = (0..w * h).map(|p| p % w < f).collect();
    let out = r.complete(&g, &missing).unwrap();
    assert!(r.trace().bank_draws.is_empty());
    let palette: std::collections::HashSet<[u32; 3]> =
        frames.iter().flat_map(|fr| fr.colour.data.iter().map(|c| c.map(f32::to_bits))).collect();
    for p in 0..(w * h) as usize {
        if missing[p] {
            assert_eq!(out.depth_m.data[p], 0.0, "pixel {p}");
            assert!(palette.contains(&out.colour.data[p].map(f32::to_bits)), "pixel {p}: a colour from no bank frame");
        } else {
            assert_eq!((out.colour.data[p], out.depth_m.data[p]), (g.colour.data[p], g.depth_m.data[p]));
        }
    }
}

#[test]
fn quilting_tiles_a_thin_band_turning_a_corner_waits_and_one_piece_quilting_fills_it() {
    let (w, h) = (32u32, 32u32);
    let k = Intrinsics::from_fov_x(w, h, 1.0);
    let frames = [frame(w, h, 70), frame(w, h, 71)];
    let g = frame(w, h, 11);
    let run = |quilt_tile: usize| {
        let (mut r, _) = refiner_and_bank();
        r.set_options(RefinerOptions { quilt_tile, ..RefinerOptions::default() });
        let grids: Vec<Vec<u32>> = frames.iter().map(|f| r.frame_codes(f, &k).unwrap()).collect();
        let side = grids[0].len().isqrt();
        let f = w / side as u32;
        let bank = CodeBank::rolled(&grids, [side, side], [0, 2], r.config().n_embed, r.codebook_crc32().unwrap());
        r.set_bank(Some(Arc::new(bank))).unwrap();
        r.set_bank_pixels(Some(Arc::new(BankPixels { bases: frames.to_vec(), roll_cells: [0, 2] })));
        // the right cell column and the top cell row: an L, as one hole neither thin nor short
        let missing: Vec<bool> = (0..w * h).map(|p| p % w >= w - f || p / w < f).collect();
        let out = r.complete(&g, &missing).unwrap();
        (out, missing, r.trace().bank_draws.len())
    };
    let (out, missing, draws) = run(4);
    assert_eq!(draws, 0, "every run of the L from a side is thinner than 3 cells: it waits");
    for (p, m) in missing.iter().enumerate() {
        if *m {
            assert_eq!(out.depth_m.data[p], 0.0, "pixel {p} waits with no depth");
        }
    }
    let (out, missing, draws) = run(0);
    assert_eq!(draws, 1, "in one piece the L is one hole, filled");
    assert!(missing.iter().zip(&out.depth_m.data).all(|(m, d)| !m || *d > 0.0));
}
