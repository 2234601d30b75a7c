use glam::{Vec2, Vec3};
use serde::{Deserialize, Serialize};

use crate::{CoreError, Rigid3};

/// Pinhole intrinsics in pixels, OpenCV convention: pixel `(u, v)`'s centre is at continuous
/// `(u, v)`; a camera-frame point `p` projects to `(fx * p.x / p.z + cx, fy * p.y / p.z + cy)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, pixels.
    pub fx: f32,
    /// Focal length along y, pixels.
    pub fy: f32,
    /// Principal point x, pixels.
    pub cx: f32,
    /// Principal point y, pixels.
    pub cy: f32,
}

impl Intrinsics {
    /// Focal lengths, in pixels, that a real camera has for an image side of `side_px` pixels:
    /// 0.005-500 times the side, fields of view from about 0.1 to 179 degrees. Outside it the
    /// map's frustum spans thousands of voxels per pixel (or none); every reader of intrinsics
    /// (command-line options, pose and calibration files) refuses focal lengths outside it.
    pub fn plausible_focal_px(side_px: f32) -> std::ops::RangeInclusive<f32> {
        0.005 * side_px..=500.0 * side_px
    }

    /// Checked constructor: positive finite focal lengths, non-zero size, finite centre.
    pub fn try_new(width: u32, height: u32, fx: f32, fy: f32, cx: f32, cy: f32) -> Result<Self, CoreError> {
        if width == 0 || height == 0 {
            return Err(CoreError::InvalidIntrinsics(format!("image size {width}x{height} is empty")));
        }
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
            return Err(CoreError::InvalidIntrinsics(format!("focal lengths fx={fx}, fy={fy} must be positive")));
        }
        if !(cx.is_finite() && cy.is_finite()) {
            return Err(CoreError::InvalidIntrinsics(format!("principal point ({cx}, {cy}) is not finite")));
        }
        Ok(Self { width, height, fx, fy, cx, cy })
    }

    /// Square pixels from a horizontal field of view (radians), principal point at the image
    /// centre as Blender places it (`cx = width / 2`).
    pub fn from_fov_x(width: u32, height: u32, fov_x_rad: f32) -> Self {
        let f = 0.5 * width as f32 / (0.5 * fov_x_rad).tan();
        Self { width, height, fx: f, fy: f, cx: width as f32 * 0.5, cy: height as f32 * 0.5 }
    }

    /// Horizontal field of view in radians.
    pub fn fov_x_rad(&self) -> f32 {
        2.0 * (0.5 * self.width as f32 / self.fx).atan()
    }

    /// Intrinsics of the same camera at another image size (all four parameters scale).
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        Self { width, height, fx: self.fx * sx, fy: self.fy * sy, cx: self.cx * sx, cy: self.cy * sy }
    }

    /// Projects a camera-frame point to continuous pixel coordinates; `None` behind the camera
    /// (`z <= 0`).
    #[inline]
    pub fn project(&self, p_camera: Vec3) -> Option<Vec2> {
        if p_camera.z <= 0.0 {
            return None;
        }
        let iz = 1.0 / p_camera.z;
        Some(Vec2::new(self.fx * p_camera.x * iz + self.cx, self.fy * p_camera.y * iz + self.cy))
    }

    /// Back-projects continuous pixel `(u, v)` with planar depth `depth_m` to the camera frame.
    #[inline]
    pub fn unproject(&self, uv: Vec2, depth_m: f32) -> Vec3 {
        Vec3::new((uv.x - self.cx) / self.fx * depth_m, (uv.y - self.cy) / self.fy * depth_m, depth_m)
    }

    /// The camera-frame ray direction through continuous pixel `(u, v)` with `z = 1`.
    #[inline]
    pub fn ray_z1(&self, uv: Vec2) -> Vec3 {
        Vec3::new((uv.x - self.cx) / self.fx, (uv.y - self.cy) / self.fy, 1.0)
    }

    /// Converts Euclidean ray length to planar depth at pixel `(u, v)`:
    /// `z = r / |ray_z1(u, v)|`.
    #[inline]
    pub fn ray_length_to_planar(&self, uv: Vec2, ray_length_m: f32) -> f32 {
        ray_length_m / self.ray_z1(uv).length()
    }

    /// True when continuous pixel `(u, v)` lies inside the image's pixel area
    /// `[-0.5, w - 0.5) x [-0.5, h - 0.5)`.
    #[inline]
    pub fn contains(&self, uv: Vec2) -> bool {
        uv.x >= -0.5 && uv.y >= -0.5 && uv.x < self.width as f32 - 0.5 && uv.y < self.height as f32 - 0.5
    }

    /// Number of pixels.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// A posed pinhole camera: intrinsics and `world_from_camera` (OpenCV axes).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Pinhole intrinsics.
    pub intrinsics: Intrinsics,
    /// Camera-to-world rigid transform (OpenCV axes: x right, y down, z forward).
    pub world_from_camera: Rigid3,
}

impl Camera {
    /// Bundles intrinsics and pose.
    pub fn new(intrinsics: Intrinsics, world_from_camera: Rigid3) -> Self {
        Self { intrinsics, world_from_camera }
    }

    /// Camera centre in world coordinates.
    pub fn centre_world(&self) -> Vec3 {
        self.world_from_camera.translation
    }

    /// Projects a world point to continuous pixel coordinates and its planar depth.
    #[inline]
    pub fn project_world(&self, camera_from_world: &Rigid3, p_world: Vec3) -> Option<(Vec2, f32)> {
        let pc = camera_from_world.transform_point(p_world);
        self.intrinsics.project(pc).map(|uv| (uv, pc.z))
    }

    /// Back-projects pixel `(u, v)` at planar depth into the world.
    #[inline]
    pub fn unproject_world(&self, uv: Vec2, depth_m: f32) -> Vec3 {
        self.world_from_camera.transform_point(self.intrinsics.unproject(uv, depth_m))
    }

    /// The eight world-space corners of the view frustum between `near_m` and `far_m`.
    pub fn frustum_corners_world(&self, near_m: f32, far_m: f32) -> [Vec3; 8] {
        let k = &self.intrinsics;
        let (w, h) = (k.width as f32 - 0.5, k.height as f32 - 0.5);
        let uvs = [Vec2::new(-0.5, -0.5), Vec2::new(w, -0.5), Vec2::new(w, h), Vec2::new(-0.5, h)];
        let mut out = [Vec3::ZERO; 8];
        for (i, uv) in uvs.iter().enumerate() {
            out[i] = self.unproject_world(*uv, near_m);
            out[i + 4] = self.unproject_world(*uv, far_m);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn pixel_world_pixel_round_trip() {
        let k = Intrinsics::try_new(256, 192, 355.5555, 350.0, 128.0, 96.0).unwrap();
        let cam = Camera::new(
            k,
            Rigid3::look_at(Vec3::new(-20.0, -20.0, 0.0), Vec3::new(-20.0, -16.0, -11.0), Vec3::Z).unwrap(),
        );
        let cfw = cam.world_from_camera.inverse();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for _ in 0..500 {
            let uv = Vec2::new(rng.random_range(-0.5..255.5), rng.random_range(-0.5..191.5));
            // f32 world coordinates ~30 m carry ~4e-6 m of rounding: ~0.01 px at 0.5 m depth.
            let d = rng.random_range(0.5..40.0);
            let pw = cam.unproject_world(uv, d);
            let (uv2, d2) = cam.project_world(&cfw, pw).unwrap();
            assert!((uv2 - uv).length() < 1e-2, "{uv} -> {uv2}");
            assert!((d2 - d).abs() < 1e-3 * d);
        }
    }

    #[test]
    fn fov_and_resize() {
        let k = Intrinsics::from_fov_x(256, 256, 0.69111);
        assert!((k.fx - 355.5555).abs() < 0.01, "fx {}", k.fx);
        assert!((k.fov_x_rad() - 0.69111).abs() < 1e-5);
        let k2 = k.resized(512, 512);
        assert!((k2.fx - 2.0 * k.fx).abs() < 1e-3 && (k2.cx - 256.0).abs() < 1e-4);
        assert!(Intrinsics::try_new(0, 5, 1.0, 1.0, 0.0, 0.0).is_err());
        assert!(Intrinsics::try_new(5, 5, -1.0, 1.0, 0.0, 0.0).is_err());
    }

    #[test]
    fn ray_length_conversion_at_centre_and_corner() {
        let k = Intrinsics::from_fov_x(256, 256, 0.69111);
        let z = k.ray_length_to_planar(Vec2::new(k.cx, k.cy), 10.0);
        assert!((z - 10.0).abs() < 1e-6);
        // Corner values worked by hand on a camera with fx != fy and cx != cy, so a swapped or
        // wrong principal point or focal length shows: z = r / sqrt(1 + (du / fx)^2 + (dv / fy)^2).
        let k = Intrinsics::try_new(640, 480, 500.0, 400.0, 300.0, 250.0).unwrap();
        // (0, 0): (300 / 500)^2 + (250 / 400)^2 = 0.36 + 0.390625
        let z = k.ray_length_to_planar(Vec2::new(0.0, 0.0), 7.0);
        assert!((z as f64 - 7.0 / 1.750625f64.sqrt()).abs() < 1e-5, "z {z}");
        // (639, 479): (339 / 500)^2 + (229 / 400)^2 = 0.459684 + 0.32775625
        let z = k.ray_length_to_planar(Vec2::new(639.0, 479.0), 7.0);
        assert!((z as f64 - 7.0 / 1.78744025f64.sqrt()).abs() < 1e-5, "z {z}");
        // The planar depth unprojects to a point whose distance from the camera is the ray length.
        let r = k.unproject(Vec2::new(639.0, 479.0), z).length();
        assert!((r - 7.0).abs() < 1e-5, "ray length {r}");
    }
}
