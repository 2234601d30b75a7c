//! The world's ground plane: found once in the seed frame, then used as a prior on the depth of
//! invented pixels.
//!
//! A generated world grows one frame at a time, and every frame's invented depth is fused and
//! then kept as "observed" by every later step. A decoder that reads the ground a few centimetres
//! too high at a frame's far border therefore raises the ground step after step, and nothing
//! pulls it back. The ground is the one surface the seed frame shows for sure, so we fit it there
//! ([`fit_ground_plane`]: RANSAC over the seed's back-projected pixels, then a least-squares
//! refit on the inliers) and, at every step, put back on it the invented pixels that the refiner
//! placed within a tolerance above it or anywhere below it ([`snap_to_ground`]). Pixels higher
//! than the tolerance (objects) keep the refiner's depth, so objects still start, end and stand
//! on the ground; only the ground's height stops being the refiner's guess.

use glam::{DVec3, Vec2, Vec3};

use crate::image::marked_depths;
use crate::{is_valid_depth, Camera, RgbdFrame};

/// A plane `normal . p + offset = 0` in world coordinates (metres); `normal` has unit length and
/// points to the side the seed camera was on, so [`GroundPlane::height`] is positive above
/// the ground.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundPlane {
    /// Unit normal, pointing up (towards the seed camera).
    pub normal: Vec3,
    /// Offset: `normal . p + offset` is the signed height of `p` above the plane.
    pub offset: f32,
    /// Share of the seed's sampled valid pixels within the inlier distance of the plane.
    pub inlier_fraction: f32,
}

impl GroundPlane {
    /// Signed height of `p` above the plane, metres.
    #[inline]
    pub fn height(&self, p: Vec3) -> f32 {
        self.normal.dot(p) + self.offset
    }

    /// Planar depth at which pixel `uv` of `camera` meets the plane, if it does in front of the
    /// camera (a ray parallel to the plane or pointing away from it has none).
    #[inline]
    pub fn depth_at(&self, camera: &Camera, uv: Vec2) -> Option<f32> {
        let origin = camera.centre_world();
        // the point at planar depth 1 on the pixel's ray: depth d is origin + d * dir
        let dir = camera.unproject_world(uv, 1.0) - origin;
        let denom = self.normal.dot(dir);
        if denom.abs() < 1e-9 {
            return None;
        }
        let d = -self.height(origin) / denom;
        (d.is_finite() && d > 0.0).then_some(d)
    }
}

/// Parameters of [`fit_ground_plane`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundFitConfig {
    /// Pixels sampled from the frame (on a regular grid), at most.
    pub samples: usize,
    /// RANSAC hypotheses.
    pub iterations: usize,
    /// A point is an inlier within this distance of the plane, metres.
    pub inlier_m: f32,
    /// The plane is accepted only when at least this share of the samples are inliers.
    pub min_inlier_fraction: f32,
    /// Seed of the hypothesis draw (the fit is deterministic for a given seed).
    pub seed: u64,
}

impl Default for GroundFitConfig {
    fn default() -> Self {
        Self { samples: 4096, iterations: 256, inlier_m: 0.03, min_inlier_fraction: 0.2, seed: 0 }
    }
}

/// The dominant plane of `frame` seen from `camera` (RANSAC, then a least-squares refit on its
/// inliers), oriented towards the camera; `None` when fewer than `min_inlier_fraction` of the
/// sampled valid pixels lie on one plane (no ground to trust) or the frame has too few valid
/// pixels.
pub fn fit_ground_plane(camera: &Camera, frame: &RgbdFrame, cfg: &GroundFitConfig) -> Option<GroundPlane> {
    let (w, h) = (frame.width(), frame.height());
    let stride = (((w as usize * h as usize) as f64 / cfg.samples.max(1) as f64).sqrt().ceil() as u32).max(1);
    let mut points = Vec::new();
    for v in (0..h).step_by(stride as usize) {
        for u in (0..w).step_by(stride as usize) {
            let d = *frame.depth_m.at(u, v);
            if is_valid_depth(d) {
                points.push(camera.unproject_world(Vec2::new(u as f32, v as f32), d));
            }
        }
    }
    if points.len() < 16 {
        return None;
    }
    // splitmix64: a deterministic index stream (this crate takes no RNG dependency for it)
    let mut state = cfg.seed;
    let mut next = |n: usize| {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) % n as u64) as usize
    };
    let mut best: Option<(usize, Vec3, f32)> = None;
    for _ in 0..cfg.iterations {
        let [a, b, c] = [0; 3].map(|_| points[next(points.len())]);
        let n = (b - a).cross(c - a);
        if n.length_squared() < 1e-12 {
            continue;
        }
        let n = n.normalize();
        let off = -n.dot(a);
        let count = points.iter().filter(|p| (n.dot(**p) + off).abs() <= cfg.inlier_m).count();
        if best.is_none_or(|(k, _, _)| count > k) {
            best = Some((count, n, off));
        }
    }
    let (_, n, off) = best?;
    let inliers: Vec<Vec3> = points.iter().copied().filter(|p| (n.dot(*p) + off).abs() <= cfg.inlier_m).collect();
    let (n, off) = refit(&inliers).unwrap_or((n, off));
    // the refit may move a few points across the band: count the final plane's inliers
    let count = points.iter().filter(|p| (n.dot(**p) + off).abs() <= cfg.inlier_m).count();
    let inlier_fraction = count as f32 / points.len() as f32;
    if inlier_fraction < cfg.min_inlier_fraction {
        return None;
    }
    // orient the normal towards the camera
    let (n, off) = if n.dot(camera.centre_world()) + off < 0.0 { (-n, -off) } else { (n, off) };
    Some(GroundPlane { normal: n, offset: off, inlier_fraction })
}

/// Least-squares plane through `points`: through their mean, normal along the covariance's
/// smallest eigenvector (power iteration on `trace * I - C`, whose largest eigenvector it is).
fn refit(points: &[Vec3]) -> Option<(Vec3, f32)> {
    if points.len() < 3 {
        return None;
    }
    let mean = points.iter().map(|p| p.as_dvec3()).sum::<DVec3>() / points.len() as f64;
    let mut c = [[0.0f64; 3]; 3];
    for p in points {
        let d = (p.as_dvec3() - mean).to_array();
        for (i, row) in c.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                *x += d[i] * d[j];
            }
        }
    }
    let trace = c[0][0] + c[1][1] + c[2][2];
    let apply = |v: DVec3| {
        let a = v.to_array();
        DVec3::from_array([0, 1, 2].map(|i| trace * a[i] - (c[i][0] * a[0] + c[i][1] * a[1] + c[i][2] * a[2])))
    };
    // start from the axis with the smallest variance: it is closest to the normal
    let axis = (0..3).min_by(|&i, &j| c[i][i].total_cmp(&c[j][j]))?;
    let mut v = DVec3::from_array([0, 1, 2].map(|i| if i == axis { 1.0 } else { 0.0 }));
    for _ in 0..64 {
        let next = apply(v);
        let len = next.length();
        if !(len.is_finite() && len > 0.0) {
            return None;
        }
        v = next / len;
    }
    let n = v.as_vec3().normalize_or_zero();
    (n != Vec3::ZERO).then(|| (n, -n.dot(mean.as_vec3())))
}

/// Parameters of [`snap_to_ground`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundSnapConfig {
    /// Ground-like invented pixels less than this above the plane (or anywhere below it) are
    /// put on it, metres.
    pub tolerance_m: f32,
    /// A pixel is ground-like when the surface around it (its neighbours `normal_stride_px`
    /// away) faces within this angle of the plane's normal, degrees; walls and object sides
    /// (vertical) never are.
    pub max_tilt_deg: f32,
    /// Distance of the neighbours that give a pixel's surface normal, pixels.
    pub normal_stride_px: u32,
    /// Pixels whose ray meets the plane beyond this are left alone, metres (the map's depth cut).
    pub max_depth_m: f32,
    /// Invented pixels less than this above the plane (or below it) are put on it whatever the
    /// surface around them looks like, metres (0 = off). Where new ground meets observed ground
    /// the refiner's depth steps by a few centimetres: the surface there is tilted, fails the
    /// up-facing test, and fuses into ridges 5-25 cm high along the frame's far border.
    pub flatten_below_m: f32,
}

impl GroundSnapConfig {
    /// Tolerance `tolerance_m`, surfaces within 60 degrees of the plane, normals over 2 pixels.
    pub fn new(tolerance_m: f32, max_depth_m: f32) -> Self {
        Self { tolerance_m, max_tilt_deg: 60.0, normal_stride_px: 2, max_depth_m, flatten_below_m: 0.0 }
    }
}

/// Puts back on `plane` every pixel marked in `missing` that the refiner made ground-like: its
/// depth places it less than `tolerance_m` above the plane (or anywhere below it) and the surface
/// around it faces up (within `max_tilt_deg` of the plane's normal, so an object's side, however
/// low, keeps its depth), or it lies less than `flatten_below_m` above the plane whatever the
/// surface around it. Only where the pixel's ray meets the plane within `max_depth_m`.
/// Observed pixels are never changed. Returns how many pixels moved.
pub fn snap_to_ground(
    frame: &mut RgbdFrame,
    missing: &[bool],
    camera: &Camera,
    plane: &GroundPlane,
    cfg: &GroundSnapConfig,
) -> usize {
    let (w, h) = (frame.width(), frame.height());
    let s = cfg.normal_stride_px.max(1);
    let min_cos = cfg.max_tilt_deg.to_radians().cos();
    let depth = &frame.depth_m;
    let point = |u: u32, v: u32| {
        let d = *depth.at(u, v);
        is_valid_depth(d).then(|| camera.unproject_world(Vec2::new(u as f32, v as f32), d))
    };
    // decide on the refiner's depth first, then write (a snapped pixel must not change its
    // neighbours' normals)
    let mut snapped = Vec::new();
    for (u, v, i, z) in marked_depths(depth, missing) {
        let uv = Vec2::new(u as f32, v as f32);
        let height = plane.height(camera.unproject_world(uv, z));
        if height >= cfg.tolerance_m {
            continue;
        }
        if height < cfg.flatten_below_m {
            if let Some(g) = plane.depth_at(camera, uv).filter(|g| *g <= cfg.max_depth_m) {
                snapped.push((i, g));
            }
            continue;
        }
        let (u0, u1, v0, v1) = (u.saturating_sub(s), (u + s).min(w - 1), v.saturating_sub(s), (v + s).min(h - 1));
        let (Some(a), Some(b), Some(c), Some(d)) = (point(u0, v), point(u1, v), point(u, v0), point(u, v1)) else {
            continue;
        };
        let n = (b - a).cross(d - c);
        let len = n.length();
        if !(len > 0.0 && (n.dot(plane.normal) / len).abs() >= min_cos) {
            continue;
        }
        if let Some(g) = plane.depth_at(camera, uv).filter(|g| *g <= cfg.max_depth_m) {
            snapped.push((i, g));
        }
    }
    let mut moved = 0;
    for (i, g) in snapped {
        if frame.depth_m.data[i] != g {
            frame.depth_m.data[i] = g;
            moved += 1;
        }
    }
    moved
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Image, Intrinsics, Rigid3};

    /// A camera 2 m above the plane z = -1, looking along +y and pitched 20 degrees down.
    fn camera() -> Camera {
        // OpenCV axes: z forward, y down. Start looking along world +y with image y = world -z.
        let base = glam::Mat3::from_cols(Vec3::X, Vec3::NEG_Z, Vec3::Y);
        let pitch = glam::Mat3::from_axis_angle(Vec3::X, -20f32.to_radians());
        Camera::new(
            Intrinsics::from_fov_x(64, 48, 60f32.to_radians()),
            Rigid3 { rotation: pitch * base, translation: Vec3::new(0.5, -0.3, 1.0) },
        )
    }

    /// The planar depth image of the plane z = -1 with a 0.6 m box-like bump where `bump` says.
    fn frame(cam: &Camera, bump: impl Fn(u32, u32) -> bool) -> RgbdFrame {
        let plane = GroundPlane { normal: Vec3::Z, offset: 1.0, inlier_fraction: 1.0 };
        let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
        let mut depth = Image::filled(w, h, 0.0f32);
        for v in 0..h {
            for u in 0..w {
                if let Some(d) = plane.depth_at(cam, Vec2::new(u as f32, v as f32)).filter(|d| *d < 30.0) {
                    *depth.at_mut(u, v) = if bump(u, v) { d * 0.8 } else { d };
                }
            }
        }
        RgbdFrame::try_new(Image::filled(w, h, [0.5; 3]), depth).unwrap()
    }

    #[test]
    fn fits_the_ground_despite_an_object_and_orients_it_up() {
        let cam = camera();
        let f = frame(&cam, |u, v| (20..40).contains(&u) && v > 30);
        let p = fit_ground_plane(&cam, &f, &GroundFitConfig::default()).expect("a plane");
        assert!((p.normal - Vec3::Z).length() < 1e-3, "normal {:?}", p.normal);
        assert!((p.offset - 1.0).abs() < 1e-3, "offset {}", p.offset);
        assert!(p.inlier_fraction > 0.5 && p.inlier_fraction < 1.0, "{}", p.inlier_fraction);
        assert!((p.height(cam.centre_world()) - 2.0).abs() < 1e-3);
    }

    #[test]
    fn an_objects_low_side_keeps_its_depth() {
        // a wall facing the camera, 0.1 m tall band of it low above the ground: vertical, so
        // not ground-like whatever its height
        let cam = camera();
        let plane = GroundPlane { normal: Vec3::Z, offset: 1.0, inlier_fraction: 1.0 };
        let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
        let mut depth = Image::filled(w, h, 0.0f32);
        let wall_y = 6.0; // world y of the wall
        for v in 0..h {
            for u in 0..w {
                let uv = Vec2::new(u as f32, v as f32);
                let o = cam.centre_world();
                let dir = cam.unproject_world(uv, 1.0) - o;
                let d_wall = (wall_y - o.y) / dir.y;
                let d_ground = plane.depth_at(&cam, uv).unwrap_or(f32::INFINITY);
                *depth.at_mut(u, v) = d_wall.min(d_ground);
            }
        }
        let mut f = RgbdFrame::try_new(Image::filled(w, h, [0.5; 3]), depth).unwrap();
        let before = f.clone();
        let missing = vec![true; (w * h) as usize];
        snap_to_ground(&mut f, &missing, &cam, &plane, &GroundSnapConfig::new(1.5, 100.0));
        let mut wall_low = 0;
        for v in 2..h - 2 {
            for u in 2..w - 2 {
                let d = *before.depth_m.at(u, v);
                let p = cam.unproject_world(Vec2::new(u as f32, v as f32), d);
                let on_wall = (p.y - wall_y).abs() < 1e-3;
                // inside the wall, away from its foot (whose normal straddles the corner)
                if on_wall && plane.height(p) < 1.5 && plane.height(p) > 0.3 {
                    assert_eq!(*f.depth_m.at(u, v), d, "wall pixel ({u}, {v}) at height {}", plane.height(p));
                    wall_low += 1;
                }
            }
        }
        assert!(wall_low > 20, "the test must see the wall's low band ({wall_low} px)");
    }

    #[test]
    fn a_low_seam_with_holes_is_flattened_only_with_flatten_below() {
        // new ground 12 cm above the plane, drawn with holes (every fourth column has no
        // depth): a pixel whose normal needs a hole fails the up-facing test and keeps its
        // height; the flattening band takes every low pixel back to the plane, holes stay holes
        let cam = camera();
        let plane = GroundPlane { normal: Vec3::Z, offset: 1.0, inlier_fraction: 1.0 };
        let truth = frame(&cam, |_, _| false);
        let (w, h) = (truth.width(), truth.height());
        let mut f = truth.clone();
        let mut missing = vec![false; (w * h) as usize];
        let o = cam.centre_world();
        for v in 0..h / 2 {
            for u in 0..w {
                let (i, d) = ((v * w + u) as usize, *truth.depth_m.at(u, v));
                if d <= 0.0 {
                    continue;
                }
                let p = cam.unproject_world(Vec2::new(u as f32, v as f32), d);
                f.depth_m.data[i] =
                    if u % 4 == 0 { 0.0 } else { d * (plane.height(o) - 0.12) / (plane.height(o) - plane.height(p)) };
                missing[i] = true;
            }
        }
        let lumps = |g: &RgbdFrame| {
            (0..(w * h) as usize)
                .filter(|&i| missing[i] && g.depth_m.data[i] > 0.0)
                .filter(|&i| {
                    let (u, v) = (i as u32 % w, i as u32 / w);
                    plane.height(cam.unproject_world(Vec2::new(u as f32, v as f32), g.depth_m.data[i])) > 0.05
                })
                .count()
        };
        let before = lumps(&f);
        let mut plain = f.clone();
        snap_to_ground(&mut plain, &missing, &cam, &plane, &GroundSnapConfig::new(1.0, 40.0));
        let mut flat = f.clone();
        let cfg = GroundSnapConfig { flatten_below_m: 0.3, ..GroundSnapConfig::new(1.0, 40.0) };
        snap_to_ground(&mut flat, &missing, &cam, &plane, &cfg);
        assert!(before > 300, "{before} lump pixels");
        assert!(lumps(&plain) * 4 > before, "the up-facing test alone took {} of {before}", before - lumps(&plain));
        assert_eq!(lumps(&flat), 0);
        let holes = |g: &RgbdFrame| g.depth_m.data.iter().filter(|d| **d <= 0.0).count();
        assert_eq!(holes(&flat), holes(&f), "flattening filled a hole");
    }

    #[test]
    fn no_plane_in_a_frame_without_one() {
        let cam = camera();
        // depth that is no plane: a random-looking field
        let mut f = frame(&cam, |_, _| false);
        for (i, d) in f.depth_m.data.iter_mut().enumerate() {
            *d = 1.0 + ((i * 7919) % 97) as f32 * 0.1;
        }
        assert_eq!(fit_ground_plane(&cam, &f, &GroundFitConfig::default()), None);
    }

    #[test]
    fn snaps_low_missing_pixels_only() {
        let cam = camera();
        let plane = GroundPlane { normal: Vec3::Z, offset: 1.0, inlier_fraction: 1.0 };
        let truth = frame(&cam, |_, _| false);
        let mut f = truth.clone();
        let (w, h) = (f.width(), f.height());
        // raise the ground 0.1 m in the top half (missing), keep an observed raised pixel, and
        // put an object (0.8x depth, well above the tolerance) in the missing bottom half
        let mut missing = vec![false; (w * h) as usize];
        for v in 0..h {
            for u in 0..w {
                let i = (v * w + u) as usize;
                let d = *truth.depth_m.at(u, v);
                if d <= 0.0 {
                    continue;
                }
                let uv = Vec2::new(u as f32, v as f32);
                let raised = |dz: f32| {
                    let o = cam.centre_world();
                    let p = cam.unproject_world(uv, d);
                    // the ray's point 0.1 m above the plane: scale towards the camera
                    d * (plane.height(o) - dz) / (plane.height(o) - plane.height(p))
                };
                if v < h / 2 {
                    f.depth_m.data[i] = raised(0.1);
                    missing[i] = u != 5;
                } else if u > 40 {
                    f.depth_m.data[i] = d * 0.6;
                    missing[i] = true;
                }
            }
        }
        let before = f.clone();
        let moved = snap_to_ground(&mut f, &missing, &cam, &plane, &GroundSnapConfig::new(0.2, 40.0));
        assert!(moved > 0);
        for v in 0..h {
            for u in 0..w {
                let (got, was, t) = (*f.depth_m.at(u, v), *before.depth_m.at(u, v), *truth.depth_m.at(u, v));
                let i = (v * w + u) as usize;
                if !missing[i] || t <= 0.0 {
                    assert_eq!(got, was, "unchanged at ({u}, {v})");
                } else if v < h / 2 {
                    // pixels whose normal can be taken (neighbours 2 px away inside the plane's
                    // valid region) are snapped
                    let ok = |a: i64, b: i64| {
                        (0..w as i64).contains(&a)
                            && (0..h as i64).contains(&b)
                            && *truth.depth_m.at(a as u32, b as u32) > 0.0
                    };
                    let (a, b) = (u as i64, v as i64);
                    if ok(a, b - 2) && (a < 2 || a + 2 >= w as i64 || (ok(a - 2, b) && ok(a + 2, b))) {
                        assert!((got - t).abs() < 1e-3 * t, "snapped at ({u}, {v}): {got} vs {t}");
                    }
                } else {
                    let p = cam.unproject_world(Vec2::new(u as f32, v as f32), was);
                    if plane.height(p) >= 0.2 {
                        assert_eq!(got, was, "object kept at ({u}, {v})");
                    }
                }
            }
        }
        assert_eq!(*f.depth_m.at(5, 2), *before.depth_m.at(5, 2), "observed pixel kept");
    }
}
