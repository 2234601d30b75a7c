//! A picture of one generation step, for `sgam generate --guidance-png`: what the refiner was
//! given, what it returned and what the invented-pixel filters made of it.

use sgam_core::{Guidance, Image, RgbdFrame};

/// Colour of a missing guidance pixel in [`step_panel`].
pub const HOLE_COLOUR: [f32; 3] = [1.0, 0.0, 1.0];

/// Three panels side by side over two rows: the guidance (holes in [`HOLE_COLOUR`]), the
/// refiner's raw completion and the final frame; colour on top, disparity below (white near,
/// black far, one scale for all three: the 2nd-98th percentile of the valid depths; a hole in the
/// guidance is magenta there too, a pixel without depth black).
///
/// # Panics
/// Never for frames of the guidance's size; other sizes are cropped or padded black.
pub fn step_panel(guidance: &Guidance, raw: &RgbdFrame, fin: &RgbdFrame) -> Image<[f32; 3]> {
    let (w, h) = (guidance.frame.width() as usize, guidance.frame.height() as usize);
    let frames = [&guidance.frame, raw, fin];
    let mut valid: Vec<f32> =
        frames.iter().flat_map(|f| f.depth_m.data.iter().copied()).filter(|d| d.is_finite() && *d > 0.0).collect();
    let (near, far) = if valid.is_empty() {
        (1.0, 2.0)
    } else {
        valid.sort_by(f32::total_cmp);
        let at = |q: f32| valid[((valid.len() - 1) as f32 * q).round() as usize];
        let (n, f) = (at(0.02), at(0.98));
        (n, if f > n { f } else { n * 1.01 + 1e-3 })
    };
    let shade = |d: f32| -> f32 {
        if !(d.is_finite() && d > 0.0) {
            return 0.0;
        }
        ((1.0 / d - 1.0 / far) / (1.0 / near - 1.0 / far)).clamp(0.0, 1.0)
    };
    let mut out = Image { width: (3 * w) as u32, height: (2 * h) as u32, data: vec![[0.0; 3]; 6 * w * h] };
    for (k, f) in frames.iter().enumerate() {
        let (fw, fh) = (f.width() as usize, f.height() as usize);
        for y in 0..h.min(fh) {
            for x in 0..w.min(fw) {
                let p = y * fw + x;
                let hole = k == 0 && guidance.missing.get(y * w + x).copied().unwrap_or(false);
                let c = if hole { HOLE_COLOUR } else { f.colour.data[p] };
                let d = if hole { HOLE_COLOUR } else { [shade(f.depth_m.data[p]); 3] };
                out.data[y * 3 * w + k * w + x] = c;
                out.data[(y + h) * 3 * w + k * w + x] = d;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use sgam_core::{Camera, Intrinsics};

    fn frame(w: u32, h: u32, colour: [f32; 3], depth: f32) -> RgbdFrame {
        RgbdFrame {
            colour: Image { width: w, height: h, data: vec![colour; (w * h) as usize] },
            depth_m: Image { width: w, height: h, data: vec![depth; (w * h) as usize] },
        }
    }

    #[test]
    fn panels_hold_guidance_holes_raw_and_final_with_one_depth_scale() {
        let (w, h) = (4u32, 2u32);
        let mut g = frame(w, h, [0.5, 0.5, 0.5], 2.0);
        g.depth_m.data[1] = 0.0; // a hole has no depth
        let mut missing = vec![false; 8];
        missing[1] = true;
        let camera = Camera::new(Intrinsics::from_fov_x(w, h, 1.0), Default::default());
        let guidance = Guidance { camera, frame: g, missing, seed: 0 };
        let raw = frame(w, h, [1.0, 0.0, 0.0], 4.0);
        let fin = frame(w, h, [0.0, 0.0, 1.0], 4.0);
        let p = step_panel(&guidance, &raw, &fin);
        assert_eq!((p.width, p.height), (12, 4));
        let at = |x: usize, y: usize| p.data[y * 12 + x];
        // colour row: guidance grey with its one hole magenta, raw red, final blue
        assert_eq!(at(0, 0), [0.5, 0.5, 0.5]);
        assert_eq!(at(1, 0), HOLE_COLOUR);
        assert_eq!(at(4, 1), [1.0, 0.0, 0.0]);
        assert_eq!(at(11, 1), [0.0, 0.0, 1.0]);
        // depth row: the near guidance (2 m) white, the far completions (4 m) black, the hole magenta
        assert_eq!(at(0, 2), [1.0; 3]);
        assert_eq!(at(1, 2), HOLE_COLOUR);
        assert_eq!(at(5, 3), [0.0; 3]);
        assert_eq!(at(8, 2), [0.0; 3]);
    }
}
