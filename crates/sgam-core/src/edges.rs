//! Flying pixels: invented depth that lies between two surfaces.
//!
//! A decoder that upsamples from a coarse latent grid cannot draw a depth step: where an invented
//! object's silhouette meets the ground behind it, its depth ramps over several pixels.
//! Back-projected, those pixels hang in the air between the object's top and the ground, and
//! fused they become a sloped skirt around the object (docs/MODEL.md, session 11). Depth sensors
//! have the same artefact at depth edges ("flying pixels") and it is found the same way: a pixel
//! whose neighbourhood spans a depth range far larger than a surface's own slope could explain.
//!
//! Dropping such pixels (depth 0) removes the skirt but leaves a gap in the map that every later
//! step sees as missing and invents again (measured: 18x the missing pixels per step, twice the
//! step time). So each flying pixel is given to one of the two surfaces instead: the nearer one
//! (the window's smallest depth) when its depth is closer to it, else the surface behind, which
//! is the ground plane where the window's farthest depth lies on it, and the farthest depth
//! otherwise (another object behind). Colour is kept.

use glam::Vec2;

use crate::ground::GroundPlane;
use crate::image::marked_depths;
use crate::{is_valid_depth, Camera, RgbdFrame};

/// Parameters of [`snap_flying_pixels`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlyingPixelConfig {
    /// Half side of the square neighbourhood, pixels (its side is `2 r + 1`).
    pub radius_px: u32,
    /// A pixel flies when the valid depths in its neighbourhood span more than this share of its
    /// own depth. It is also the tolerance of "the farthest depth lies on the plane".
    pub max_relative_range: f32,
    /// The plane is used only where the pixel's ray meets it within this depth, metres.
    pub max_depth_m: f32,
}

impl FlyingPixelConfig {
    /// 9 x 9 pixels (the decoder's ramps are about one 8-pixel latent cell wide) and 5 % of the
    /// depth: the shortest object of the synthetic world (1.4 m) seen from its 12 m spans about
    /// 12 %, the ground across 9 pixels of its 40-degree view under 2 %.
    pub fn new(max_depth_m: f32) -> Self {
        Self { radius_px: 4, max_relative_range: 0.05, max_depth_m }
    }
}

/// Gives every flying pixel marked in `missing` to the nearer or the farther surface of its
/// neighbourhood (see the module docs); `plane` (with `camera`) says where the ground behind is.
/// Decisions are taken on the input depth, so the result does not depend on the scan order.
/// Observed pixels, invalid depth and colour are never changed. Returns how many pixels moved.
pub fn snap_flying_pixels(
    frame: &mut RgbdFrame,
    missing: &[bool],
    camera: &Camera,
    plane: Option<&GroundPlane>,
    cfg: &FlyingPixelConfig,
) -> usize {
    let (w, h) = (frame.width(), frame.height());
    let (r, rel) = (cfg.radius_px, cfg.max_relative_range);
    let depth = &frame.depth_m;
    let mut moves = Vec::new();
    for (u, v, i, d) in marked_depths(depth, missing) {
        let (mut lo, mut hi) = (d, d);
        for y in v.saturating_sub(r)..=(v + r).min(h - 1) {
            for x in u.saturating_sub(r)..=(u + r).min(w - 1) {
                let e = *depth.at(x, y);
                if is_valid_depth(e) {
                    (lo, hi) = (lo.min(e), hi.max(e));
                }
            }
        }
        if hi - lo <= rel * d {
            continue;
        }
        let to = if d - lo <= hi - d {
            lo
        } else {
            let ground = plane
                .and_then(|p| p.depth_at(camera, Vec2::new(u as f32, v as f32)))
                .filter(|g| *g <= cfg.max_depth_m && hi > g * (1.0 - rel));
            ground.unwrap_or(hi)
        };
        if to != d {
            moves.push((i, to));
        }
    }
    for &(i, to) in &moves {
        frame.depth_m.data[i] = to;
    }
    moves.len()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Image, Intrinsics, Rigid3};
    use glam::Vec3;

    /// A camera 12 m above the plane z = 0, looking straight down.
    fn camera(w: u32, h: u32) -> Camera {
        let down = glam::Mat3::from_cols(Vec3::X, Vec3::NEG_Y, Vec3::NEG_Z);
        Camera::new(
            Intrinsics::from_fov_x(w, h, 40f32.to_radians()),
            Rigid3 { rotation: down, translation: Vec3::new(0.0, 0.0, 12.0) },
        )
    }

    fn plane() -> GroundPlane {
        GroundPlane { normal: Vec3::Z, offset: 0.0, inlier_fraction: 1.0 }
    }

    /// The ground (12 m) with a 2 m tall box (10 m) left of column `edge`, joined by a linear
    /// depth ramp `ramp` pixels wide, as a decoder draws it.
    fn ramp_frame(w: u32, h: u32, edge: u32, ramp: u32) -> RgbdFrame {
        let mut depth = Image::filled(w, h, 0.0f32);
        for v in 0..h {
            for u in 0..w {
                let t = ((u as f32 - edge as f32) / ramp.max(1) as f32).clamp(0.0, 1.0);
                *depth.at_mut(u, v) = 10.0 + 2.0 * t;
            }
        }
        RgbdFrame::try_new(Image::filled(w, h, [0.3, 0.6, 0.9]), depth).unwrap()
    }

    #[test]
    fn the_ramp_goes_to_the_box_or_to_the_ground_and_the_surfaces_stay() {
        let (w, h) = (48, 16);
        let cam = camera(w, h);
        let mut f = ramp_frame(w, h, 20, 8);
        let before = f.clone();
        let missing = vec![true; (w * h) as usize];
        let n = snap_flying_pixels(&mut f, &missing, &cam, Some(&plane()), &FlyingPixelConfig::new(40.0));
        assert!(n > 0);
        for v in 0..h {
            for u in 0..w {
                let (got, was) = (*f.depth_m.at(u, v), *before.depth_m.at(u, v));
                let ground = plane().depth_at(&cam, Vec2::new(u as f32, v as f32)).unwrap();
                if was > 10.0 + 1e-3 && was < 12.0 - 1e-3 {
                    // no pixel is left between the two surfaces
                    let on_box = got == 10.0;
                    let on_ground = (got - ground).abs() < 1e-4;
                    assert!(on_box || on_ground, "ramp pixel ({u}, {v}) at {was} m -> {got} m");
                    assert_eq!(on_box, was - 10.0 <= 12.0 - was, "({u}, {v}): {was} m went to the wrong side");
                }
                if !(20 - 5..=28 + 5).contains(&u) {
                    assert_eq!(got, was, "surface pixel ({u}, {v}) changed");
                }
                assert_eq!(f.colour.at(u, v), before.colour.at(u, v), "colour changed");
            }
        }
    }

    #[test]
    fn without_a_plane_the_far_side_takes_the_farthest_depth() {
        let (w, h) = (48, 8);
        let cam = camera(w, h);
        let mut f = ramp_frame(w, h, 20, 8);
        let missing = vec![true; (w * h) as usize];
        snap_flying_pixels(&mut f, &missing, &cam, None, &FlyingPixelConfig::new(40.0));
        for v in 0..h {
            for u in 0..w {
                let got = *f.depth_m.at(u, v);
                assert!(got == 10.0 || got == 12.0, "({u}, {v}) left at {got} m");
            }
        }
    }

    #[test]
    fn a_sloped_ground_and_observed_pixels_are_left_alone() {
        // the ground seen obliquely: depth grows 0.2 % per row, 1.8 % across the window
        let (w, h) = (40, 40);
        let cam = camera(w, h);
        let mut depth = Image::filled(w, h, 0.0f32);
        for v in 0..h {
            for u in 0..w {
                *depth.at_mut(u, v) = 12.0 * (1.0 + 0.002 * v as f32);
            }
        }
        let mut f = RgbdFrame::try_new(Image::filled(w, h, [0.5; 3]), depth).unwrap();
        let before = f.clone();
        let all = vec![true; (w * h) as usize];
        assert_eq!(snap_flying_pixels(&mut f, &all, &cam, Some(&plane()), &FlyingPixelConfig::new(40.0)), 0);
        assert_eq!(f, before);
        // a ramp that is observed everywhere stays as it is
        let mut g = ramp_frame(w, h, 20, 8);
        let before = g.clone();
        let none = vec![false; (w * h) as usize];
        assert_eq!(snap_flying_pixels(&mut g, &none, &cam, Some(&plane()), &FlyingPixelConfig::new(40.0)), 0);
        assert_eq!(g, before);
    }

    #[test]
    fn an_invented_pixel_is_judged_with_its_observed_neighbours() {
        // observed box on the left (10 m), invented ground on the right (12 m): the invented
        // pixels next to the step fly but already lie on the far side, so they stay; an invented
        // column at 11.5 m among them goes to the far side (no plane: the farthest depth)
        let (w, h) = (32, 8);
        let cam = camera(w, h);
        let mut f = ramp_frame(w, h, 16, 1);
        let missing: Vec<bool> = (0..w * h).map(|i| i % w >= 17).collect();
        for v in 0..h {
            *f.depth_m.at_mut(18, v) = 11.5;
        }
        let cfg = FlyingPixelConfig { radius_px: 2, ..FlyingPixelConfig::new(40.0) };
        let n = snap_flying_pixels(&mut f, &missing, &cam, None, &cfg);
        assert_eq!(n, h as usize);
        for v in 0..h {
            assert_eq!(*f.depth_m.at(18, v), 12.0);
            assert_eq!(*f.depth_m.at(16, v), 10.0, "observed box kept");
        }
    }
}
