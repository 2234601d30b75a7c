//! Free space: invented depth that earlier views saw through.
//!
//! A voxel-hashed TSDF stores only a band around surfaces, so the space a view saw as empty
//! between its camera and its surfaces is not in the map: rendered from elsewhere, a ray through
//! it that meets no surface comes back missing, and the refiner may put an object anywhere along
//! it — in front of the seed's own surfaces, seen from the seed pose (docs/MODEL.md, session
//! 12: on a 3 m loop back to the seed, invented surfaces covered a third of the seed frame).
//!
//! The test is the one a depth camera's free-space carving makes: an invented point `X` is
//! inconsistent with a view when it projects inside that view's image in front of the view's
//! depth there (by more than a margin), since the view would have seen `X` instead. Such a
//! pixel is put on the ground plane behind it when that ground point is itself consistent with
//! every view, and dropped (depth 0, not fused) otherwise. Colour is kept.

use glam::Vec2;

use crate::ground::GroundPlane;
use crate::image::marked_depths;
use crate::{is_valid_depth, Camera, RgbdFrame, Rigid3};

/// Parameters of [`carve_invented`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FreeSpaceConfig {
    /// A view sees through a point when its depth there exceeds the point's by more than
    /// `max(margin_m, margin_rel * depth)`.
    pub margin_m: f32,
    /// Relative part of the margin.
    pub margin_rel: f32,
    /// Half side of the window of view pixels whose nearest depth is compared (1: 3 x 3), so a
    /// point at a view's depth edge is not called seen through.
    pub window_px: u32,
    /// The ground plane is used only within this depth, metres.
    pub max_depth_m: f32,
}

impl FreeSpaceConfig {
    /// Margins of 3 voxels of the CLEVR map (0.15 m) or 5 % of the depth, whichever is larger, and
    /// a 3 x 3 window.
    pub fn new(max_depth_m: f32) -> Self {
        Self { margin_m: 0.15, margin_rel: 0.05, window_px: 1, max_depth_m }
    }
}

/// A view the invented points are checked against: its camera, the inverse of its pose, its
/// frame.
struct View<'a> {
    camera: &'a Camera,
    camera_from_world: Rigid3,
    frame: &'a RgbdFrame,
}

impl View<'_> {
    /// Whether this view saw through the world point `p`.
    fn sees_through(&self, p: glam::Vec3, cfg: &FreeSpaceConfig) -> bool {
        let Some((uv, z)) = self.camera.project_world(&self.camera_from_world, p) else {
            return false;
        };
        let (w, h) = (self.frame.width() as i64, self.frame.height() as i64);
        let (u, v) = (uv.x.round() as i64, uv.y.round() as i64);
        if z <= 0.0 || u < 0 || v < 0 || u >= w || v >= h {
            return false;
        }
        let r = cfg.window_px as i64;
        let mut nearest = f32::INFINITY;
        for y in (v - r).max(0)..=(v + r).min(h - 1) {
            for x in (u - r).max(0)..=(u + r).min(w - 1) {
                let d = *self.frame.depth_m.at(x as u32, y as u32);
                // a pixel without depth saw nothing it can vouch for
                nearest = nearest.min(if is_valid_depth(d) { d } else { 0.0 });
            }
        }
        nearest > z + cfg.margin_m.max(cfg.margin_rel * z)
    }
}

/// Checks every pixel marked in `missing` (invented) with valid depth against `views` (camera,
/// frame): one that some view saw through goes to the ground plane behind it when that ground
/// point is seen through by none, else its depth becomes 0 (not fused). Observed pixels and
/// colour are never changed. Returns `(moved to the ground, dropped)`.
pub fn carve_invented(
    frame: &mut RgbdFrame,
    missing: &[bool],
    camera: &Camera,
    views: &[(&Camera, &RgbdFrame)],
    plane: Option<&GroundPlane>,
    cfg: &FreeSpaceConfig,
) -> (usize, usize) {
    let views: Vec<View<'_>> = views
        .iter()
        .map(|(c, f)| View { camera: c, camera_from_world: c.world_from_camera.inverse(), frame: f })
        .collect();
    let seen_through = |uv: Vec2, d: f32| {
        let p = camera.unproject_world(uv, d);
        views.iter().any(|v| v.sees_through(p, cfg))
    };
    // decide on the refiner's depth, then write (0 = dropped)
    let moves: Vec<(usize, f32)> = marked_depths(&frame.depth_m, missing)
        .filter_map(|(u, v, i, d)| {
            let uv = Vec2::new(u as f32, v as f32);
            seen_through(uv, d).then(|| {
                let ground = plane
                    .and_then(|p| p.depth_at(camera, uv))
                    .filter(|g| *g > d && *g <= cfg.max_depth_m && !seen_through(uv, *g));
                (i, ground.unwrap_or(0.0))
            })
        })
        .collect();
    for &(i, to) in &moves {
        frame.depth_m.data[i] = to;
    }
    let dropped = moves.iter().filter(|(_, to)| *to == 0.0).count();
    (moves.len() - dropped, dropped)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Image, Intrinsics};
    use glam::Vec3;

    /// A camera at `x` looking along +y (world z up), 1 m above the plane z = 0.
    fn camera(x: f32) -> Camera {
        let rot = glam::Mat3::from_cols(Vec3::X, Vec3::NEG_Z, Vec3::Y);
        Camera::new(Intrinsics::from_fov_x(32, 32, 1.0), Rigid3::new(rot, Vec3::new(x, 0.0, 1.0)))
    }

    fn frame(depth: f32) -> RgbdFrame {
        RgbdFrame { colour: Image::filled(32, 32, [0.5; 3]), depth_m: Image::filled(32, 32, depth) }
    }

    #[test]
    fn invented_points_a_view_saw_through_are_grounded_or_dropped_and_the_rest_kept() {
        // the view saw a wall 10 m ahead everywhere; the new frame (same pose) invents a wall at
        // 4 m (inconsistent) on its missing left half and observes 4 m on the right half
        let cam = camera(0.0);
        let view = frame(10.0);
        let mut f = frame(4.0);
        let missing: Vec<bool> = (0..32 * 32).map(|i| i % 32 < 16).collect();
        let plane = GroundPlane { normal: Vec3::Z, offset: 0.0, inlier_fraction: 1.0 };
        let (grounded, dropped) =
            carve_invented(&mut f, &missing, &cam, &[(&cam, &view)], Some(&plane), &FreeSpaceConfig::new(20.0));
        assert_eq!(grounded + dropped, 16 * 32, "every invented pixel moves");
        let cfg = FreeSpaceConfig::new(20.0);
        for v in 0..32u32 {
            for u in 0..32u32 {
                let d = *f.depth_m.at(u, v);
                if u >= 16 {
                    assert_eq!(d, 4.0, "observed pixels are never changed");
                    continue;
                }
                // the ground behind is taken where it lies within 20 m and the view, which saw
                // 10 m, did not see through it (rows just below the horizon); elsewhere dropped
                let g = plane.depth_at(&cam, Vec2::new(u as f32, v as f32));
                let consistent = |g: f32| g > 4.0 && g <= 20.0 && 10.0 <= g + cfg.margin_m.max(cfg.margin_rel * g);
                match g.filter(|g| consistent(*g)) {
                    Some(g) => assert!((d - g).abs() < 1e-4, "({u},{v}): {d}, ground {g}"),
                    None => assert_eq!(d, 0.0, "({u},{v})"),
                }
            }
        }
        assert!(dropped > 0 && grounded > 0, "{grounded} grounded, {dropped} dropped");
        assert!(f.colour.data.iter().all(|c| *c == [0.5; 3]), "colour is kept");
    }

    #[test]
    fn points_behind_a_views_surface_or_outside_its_image_are_consistent() {
        // the view saw a wall at 3 m: invented points at 5 m lie behind it (unseen), kept
        let cam = camera(0.0);
        let view = frame(3.0);
        let mut f = frame(5.0);
        let missing = vec![true; 32 * 32];
        let out = carve_invented(&mut f, &missing, &cam, &[(&cam, &view)], None, &FreeSpaceConfig::new(20.0));
        assert_eq!(out, (0, 0));
        assert!(f.depth_m.data.iter().all(|d| *d == 5.0));
        // a view 100 m to the side looking the same way never sees these points
        let far = camera(100.0);
        let view = frame(50.0);
        let mut f = frame(5.0);
        assert_eq!(carve_invented(&mut f, &missing, &cam, &[(&far, &view)], None, &FreeSpaceConfig::new(20.0)), (0, 0));
        // within the margin of the view's depth is the same surface, not free space
        let view = frame(5.2);
        let mut f = frame(5.0);
        assert_eq!(carve_invented(&mut f, &missing, &cam, &[(&cam, &view)], None, &FreeSpaceConfig::new(20.0)), (0, 0));
    }

    #[test]
    fn a_view_pixel_without_depth_vouches_for_nothing() {
        let cam = camera(0.0);
        let view = frame(0.0);
        let mut f = frame(4.0);
        let missing = vec![true; 32 * 32];
        assert_eq!(carve_invented(&mut f, &missing, &cam, &[(&cam, &view)], None, &FreeSpaceConfig::new(20.0)), (0, 0));
    }
}
