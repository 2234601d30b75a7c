//! No-reference checks of a world grown from a real seed, which has no true world to compare
//! with (issue 28): what the run invented is judged against the seed itself.
//!
//! - **New area**: the pixels of a frame the seed did not see ([`unseen_by_seed`]): their
//!   point, projected into the seed's camera, falls outside its image, on a pixel without
//!   depth, or behind the surface the seed saw there.
//! - **Look**: colour and texture statistics of patches ([`patch_features`]: mean and spread
//!   of each colour channel, mean luminance gradients, a luminance histogram), new-area patches
//!   against the seed's, as KID ([`crate::kid::kid`]) after standardising both by the seed's
//!   spread ([`Standardise`]). A new area in the seed's palette scores near 0; magenta fringes
//!   and noise do not.
//! - **Floating geometry** ([`HeightRange`]): the share of new-area points whose height above
//!   the seed's ground plane lies outside the heights the seed itself holds, widened by a
//!   tolerance: stray lines and sheets in the air, or holes dug under the ground.

use sgam_core::ground::GroundPlane;
use sgam_core::{is_valid_depth as valid, Camera, RgbdFrame, Vec2};

/// Side of a square patch, pixels.
pub const PATCH_PX: usize = 32;
/// Patches are taken on a grid this many pixels apart.
pub const PATCH_STRIDE_PX: usize = 16;
/// A patch counts when at least this share of its pixels qualify (new, or valid for the seed).
pub const PATCH_SHARE: f32 = 0.75;
/// Luminance histogram bins of a patch's features.
const HIST_BINS: usize = 8;
/// Length of a patch's feature vector.
pub const FEATURE_LEN: usize = 3 + 3 + 2 + HIST_BINS;

/// Which pixels of `frame` (at `camera`) the seed (`seed` at `seed_camera`) did not see: a
/// pixel with depth whose point projects outside the seed's image, onto a seed pixel without
/// depth, or more than `tolerance_rel` (relative) behind the seed's depth there. Pixels without
/// depth are not new (nothing was put there).
pub fn unseen_by_seed(
    seed_camera: &Camera,
    seed: &RgbdFrame,
    camera: &Camera,
    frame: &RgbdFrame,
    tolerance_rel: f32,
) -> Vec<bool> {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    let (sw, sh) = (seed.width() as usize, seed.height() as usize);
    let seed_from_world = seed_camera.world_from_camera.inverse();
    let mut out = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let d = frame.depth_m.data[y * w + x];
            if !valid(d) {
                continue;
            }
            let p = camera.unproject_world(Vec2::new(x as f32, y as f32), d);
            out[y * w + x] = match seed_camera.project_world(&seed_from_world, p) {
                Some((uv, z)) => {
                    let (u, v) = (uv.x.round(), uv.y.round());
                    if u < 0.0 || v < 0.0 || u >= sw as f32 || v >= sh as f32 {
                        true
                    } else {
                        let s = seed.depth_m.data[v as usize * sw + u as usize];
                        !valid(s) || z > s * (1.0 + tolerance_rel)
                    }
                }
                None => true,
            };
        }
    }
    out
}

/// Features of the patches of `frame` (on a [`PATCH_STRIDE_PX`] grid of [`PATCH_PX`] squares)
/// where at least [`PATCH_SHARE`] of the pixels are selected by `select` (a pixel index) and
/// have depth: per patch the mean and standard deviation of R, G and B, the mean absolute
/// luminance difference to the right and below, and an 8-bin luminance histogram (shares).
pub fn patch_features(frame: &RgbdFrame, select: impl Fn(usize) -> bool) -> Vec<Vec<f32>> {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    let lum = |i: usize| {
        let [r, g, b] = frame.colour.data[i];
        0.299 * r + 0.587 * g + 0.114 * b
    };
    let mut out = Vec::new();
    if w < PATCH_PX || h < PATCH_PX {
        return out;
    }
    for y0 in (0..=h - PATCH_PX).step_by(PATCH_STRIDE_PX) {
        for x0 in (0..=w - PATCH_PX).step_by(PATCH_STRIDE_PX) {
            let pixels: Vec<usize> = (y0..y0 + PATCH_PX)
                .flat_map(|y| (x0..x0 + PATCH_PX).map(move |x| y * w + x))
                .filter(|&i| select(i) && valid(frame.depth_m.data[i]))
                .collect();
            if (pixels.len() as f32) < PATCH_SHARE * (PATCH_PX * PATCH_PX) as f32 {
                continue;
            }
            let n = pixels.len() as f32;
            let mut f = vec![0.0f32; FEATURE_LEN];
            for &i in &pixels {
                for c in 0..3 {
                    f[c] += frame.colour.data[i][c] / n;
                }
            }
            for &i in &pixels {
                for c in 0..3 {
                    f[3 + c] += (frame.colour.data[i][c] - f[c]).powi(2) / n;
                }
                let bin = ((lum(i).clamp(0.0, 1.0) * HIST_BINS as f32) as usize).min(HIST_BINS - 1);
                f[8 + bin] += 1.0 / n;
            }
            for c in 0..3 {
                f[3 + c] = f[3 + c].sqrt();
            }
            // gradients within the patch (all its pixels, which carry colour either way)
            let (mut gx, mut gy) = (0.0f32, 0.0f32);
            for y in y0..y0 + PATCH_PX {
                for x in x0..x0 + PATCH_PX - 1 {
                    gx += (lum(y * w + x + 1) - lum(y * w + x)).abs();
                }
            }
            for y in y0..y0 + PATCH_PX - 1 {
                for x in x0..x0 + PATCH_PX {
                    gy += (lum((y + 1) * w + x) - lum(y * w + x)).abs();
                }
            }
            let pairs = (PATCH_PX * (PATCH_PX - 1)) as f32;
            f[6] = gx / pairs;
            f[7] = gy / pairs;
            out.push(f);
        }
    }
    out
}

/// Per-dimension standardisation by a reference set's mean and spread (a dimension the
/// reference does not vary in is scaled by 1 / 0.01 of its units, not divided by zero).
#[derive(Debug, Clone)]
pub struct Standardise {
    mean: Vec<f32>,
    inv_std: Vec<f32>,
}

impl Standardise {
    /// From `reference` (vectors of one length; empty gives the identity on any length).
    pub fn new(reference: &[Vec<f32>]) -> Self {
        let d = reference.first().map_or(0, Vec::len);
        let n = reference.len().max(1) as f32;
        let mut mean = vec![0.0f32; d];
        for v in reference {
            for (m, x) in mean.iter_mut().zip(v) {
                *m += x / n;
            }
        }
        let mut var = vec![0.0f32; d];
        for v in reference {
            for ((s, x), m) in var.iter_mut().zip(v).zip(&mean) {
                *s += (x - m).powi(2) / n;
            }
        }
        let inv_std = var.iter().map(|v| 1.0 / v.sqrt().max(0.01)).collect();
        Self { mean, inv_std }
    }

    /// `v` standardised.
    pub fn apply(&self, v: &[f32]) -> Vec<f32> {
        v.iter()
            .enumerate()
            .map(|(i, x)| (x - self.mean.get(i).unwrap_or(&0.0)) * self.inv_std.get(i).unwrap_or(&1.0))
            .collect()
    }
}

/// The heights above a ground plane a seed holds, widened by a tolerance: a new-area point
/// outside it floats above everything the seed shows or lies under its ground.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeightRange {
    /// Lowest height allowed.
    pub lo: f32,
    /// Highest height allowed.
    pub hi: f32,
}

impl HeightRange {
    /// The 1st to 99th percentile of the heights of `seed`'s points above `plane`, widened by
    /// `tolerance` on each side; `None` when the seed has no valid depth.
    pub fn of_seed(camera: &Camera, seed: &RgbdFrame, plane: &GroundPlane, tolerance: f32) -> Option<Self> {
        let w = seed.width() as usize;
        let mut heights: Vec<f32> = seed
            .depth_m
            .data
            .iter()
            .enumerate()
            .filter(|(_, d)| valid(**d))
            .map(|(i, &d)| plane.height(camera.unproject_world(Vec2::new((i % w) as f32, (i / w) as f32), d)))
            .filter(|h| h.is_finite())
            .collect();
        if heights.is_empty() {
            return None;
        }
        heights.sort_by(f32::total_cmp);
        let at = |q: f32| heights[((heights.len() - 1) as f32 * q).round() as usize];
        Some(Self { lo: at(0.01) - tolerance, hi: at(0.99) + tolerance })
    }

    /// How many of the `select`ed pixels of `frame` (at `camera`) with depth lie outside the
    /// range, and how many were judged.
    pub fn outside(
        &self,
        camera: &Camera,
        frame: &RgbdFrame,
        plane: &GroundPlane,
        select: impl Fn(usize) -> bool,
    ) -> (usize, usize) {
        let w = frame.width() as usize;
        let (mut out, mut all) = (0, 0);
        for (i, &d) in frame.depth_m.data.iter().enumerate() {
            if !valid(d) || !select(i) {
                continue;
            }
            let h = plane.height(camera.unproject_world(Vec2::new((i % w) as f32, (i / w) as f32), d));
            all += 1;
            out += usize::from(!(h >= self.lo && h <= self.hi));
        }
        (out, all)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sgam_core::{Image, Intrinsics, Rigid3, Vec3};

    fn camera_at(x: f32) -> Camera {
        // looking along +z from (x, 0, 0)
        Camera {
            intrinsics: Intrinsics::try_new(64, 64, 64.0, 64.0, 32.0, 32.0).unwrap(),
            world_from_camera: Rigid3 { rotation: sgam_core::Mat3::IDENTITY, translation: Vec3::new(x, 0.0, 0.0) },
        }
    }

    fn wall(depth: f32, mut colour: impl FnMut(usize, usize) -> [f32; 3]) -> RgbdFrame {
        let mut c = Image::filled(64, 64, [0.0f32; 3]);
        for y in 0..64 {
            for x in 0..64 {
                c.data[y * 64 + x] = colour(x, y);
            }
        }
        RgbdFrame { colour: c, depth_m: Image::filled(64, 64, depth) }
    }

    #[test]
    fn a_view_moved_sideways_is_new_only_where_the_seed_did_not_look() {
        let seed = wall(4.0, |_, _| [0.5; 3]);
        // same wall from 1 m to the right: the right quarter of the view (32 px * 1 m / 4 m /
        // (1/64 px)) = 16 px lies beyond the seed's right border
        let moved = unseen_by_seed(&camera_at(0.0), &seed, &camera_at(1.0), &seed, 0.05);
        for y in [0, 31, 63] {
            let row = &moved[y * 64..(y + 1) * 64];
            assert!(row[..46].iter().all(|n| !n), "row {y}: {row:?}");
            assert!(row[50..].iter().all(|n| *n), "row {y}: {row:?}");
        }
        // the same view: nothing new; a surface far behind the seed's: all new (occluded)
        assert!(unseen_by_seed(&camera_at(0.0), &seed, &camera_at(0.0), &seed, 0.05).iter().all(|n| !n));
        let behind = wall(8.0, |_, _| [0.5; 3]);
        assert!(unseen_by_seed(&camera_at(0.0), &seed, &camera_at(0.0), &behind, 0.05).iter().all(|n| *n));
    }

    #[test]
    fn patches_in_the_seeds_palette_score_near_it_and_magenta_noise_far_from_it() {
        let grey = |x: usize, y: usize| {
            let v = 0.4 + 0.2 * (((x / 4 + y / 4) % 2) as f32);
            [v, v, v * 0.9]
        };
        let seed = wall(4.0, grey);
        let like = wall(4.0, |x, y| grey(x + 4, y));
        let mut s = 12345u32;
        let mut noise = || {
            s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (s >> 8) as f32 / (1u32 << 24) as f32
        };
        let magenta = wall(4.0, |_, _| {
            let n = noise();
            [0.6 + 0.4 * n, 0.1 * n, 0.7 + 0.3 * n]
        });
        let all = |_: usize| true;
        let f_seed = patch_features(&seed, all);
        assert_eq!(f_seed.len(), 9, "3 x 3 patches of 32 px, 16 px apart");
        assert!(f_seed.iter().all(|f| f.len() == FEATURE_LEN));
        let std = Standardise::new(&f_seed);
        let z = |f: Vec<Vec<f32>>| f.iter().map(|v| std.apply(v)).collect::<Vec<_>>();
        let kid = |a: &RgbdFrame| crate::kid::kid(&z(f_seed.clone()), &z(patch_features(a, all))).unwrap();
        let (near, far) = (kid(&like), kid(&magenta));
        assert!(near < 0.5 && far > 20.0 * near.max(0.01), "like the seed {near}, magenta noise {far}");
        // a selection that keeps too few pixels of every patch gives no patch
        assert!(patch_features(&seed, |i| i % 2 == 0).is_empty());
    }

    #[test]
    fn points_above_everything_the_seed_holds_float() {
        // a ground plane z = 0 seen from 2 m above, looking straight down (+z of the camera is
        // -z of the world)
        let down = Rigid3 {
            rotation: sgam_core::Mat3::from_cols(Vec3::X, -Vec3::Y, -Vec3::Z),
            translation: Vec3::new(0.0, 0.0, 2.0),
        };
        let cam = Camera {
            intrinsics: Intrinsics::try_new(64, 64, 64.0, 64.0, 32.0, 32.0).unwrap(),
            world_from_camera: down,
        };
        let plane = GroundPlane { normal: Vec3::Z, offset: 0.0, inlier_fraction: 1.0 };
        let seed = wall(2.0, |_, _| [0.5; 3]);
        let range = HeightRange::of_seed(&cam, &seed, &plane, 0.1).unwrap();
        assert!(range.lo.abs() < 0.2 && range.hi.abs() < 0.2, "{range:?}");
        assert_eq!(range.outside(&cam, &seed, &plane, |_| true), (0, 64 * 64));
        // a sheet 1 m above the ground in the left half
        let mut sheet = seed.clone();
        for y in 0..64 {
            for x in 0..32 {
                sheet.depth_m.data[y * 64 + x] = 1.0;
            }
        }
        assert_eq!(range.outside(&cam, &sheet, &plane, |_| true), (32 * 64, 64 * 64));
        assert_eq!(range.outside(&cam, &sheet, &plane, |i| i % 64 >= 32), (0, 32 * 64));
    }
}
