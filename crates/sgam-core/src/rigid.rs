use glam::{Mat3, Mat4, Vec3, Vec4};
use serde::{Deserialize, Serialize};

use crate::CoreError;

/// A rigid transform (rotation + translation), e.g. `world_from_camera`.
///
/// Name every value `a_from_b`: it maps coordinates expressed in frame `b` into frame `a`.
/// Compose right to left: `world_from_camera = world_from_body * body_from_camera`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Rigid3 {
    /// Orthonormal rotation with determinant +1.
    pub rotation: Mat3,
    /// Translation (the origin of frame `b` expressed in frame `a`).
    pub translation: Vec3,
}

impl Default for Rigid3 {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Rigid3 {
    /// The identity transform.
    pub const IDENTITY: Self = Self { rotation: Mat3::IDENTITY, translation: Vec3::ZERO };

    /// Builds from parts without checking (the caller guarantees `rotation` is a rotation).
    pub fn new(rotation: Mat3, translation: Vec3) -> Self {
        Self { rotation, translation }
    }

    /// A pure translation.
    pub fn from_translation(translation: Vec3) -> Self {
        Self { rotation: Mat3::IDENTITY, translation }
    }

    /// Checks that a row-major 4x4 matrix (`rows[r][c]`) is rigid (finite, orthonormal rotation
    /// with det +1 within `1e-3`, last row `0 0 0 1`) and converts it.
    pub fn try_from_rows(rows: [[f64; 4]; 4]) -> Result<Self, CoreError> {
        if rows.iter().flatten().any(|x| !x.is_finite()) {
            return Err(CoreError::NotRigid("matrix has non-finite entries".into()));
        }
        let last = rows[3];
        if last[0].abs() > 1e-6 || last[1].abs() > 1e-6 || last[2].abs() > 1e-6 || (last[3] - 1.0).abs() > 1e-6 {
            return Err(CoreError::NotRigid(format!("last row is {last:?}, expected [0, 0, 0, 1]")));
        }
        let col = |c: usize| Vec3::new(rows[0][c] as f32, rows[1][c] as f32, rows[2][c] as f32);
        let rotation = Mat3::from_cols(col(0), col(1), col(2));
        let translation = col(3);
        let rtr = rotation.transpose() * rotation;
        let err = (rtr - Mat3::IDENTITY).to_cols_array().iter().fold(0.0f32, |m, x| m.max(x.abs()));
        if err > 1e-3 {
            return Err(CoreError::NotRigid(format!("rotation part is not orthonormal (|R^T R - I| = {err:.2e})")));
        }
        let det = rotation.determinant();
        if (det - 1.0).abs() > 1e-3 {
            return Err(CoreError::NotRigid(format!("rotation determinant is {det:.4}, expected +1")));
        }
        Ok(Self { rotation, translation })
    }

    /// Row-major 4x4 matrix (`rows[r][c]`), as written in pose files.
    pub fn to_rows(&self) -> [[f64; 4]; 4] {
        let m = self.to_mat4();
        let mut rows = [[0.0f64; 4]; 4];
        for (r, row) in rows.iter_mut().enumerate() {
            for (c, x) in row.iter_mut().enumerate() {
                *x = m.col(c)[r] as f64;
            }
        }
        rows
    }

    /// The homogeneous 4x4 matrix.
    pub fn to_mat4(&self) -> Mat4 {
        Mat4::from_cols(
            self.rotation.x_axis.extend(0.0),
            self.rotation.y_axis.extend(0.0),
            self.rotation.z_axis.extend(0.0),
            Vec4::new(self.translation.x, self.translation.y, self.translation.z, 1.0),
        )
    }

    /// The inverse transform (`b_from_a` for `a_from_b`).
    pub fn inverse(&self) -> Self {
        let rt = self.rotation.transpose();
        Self { rotation: rt, translation: -(rt * self.translation) }
    }

    /// Maps a point of frame `b` into frame `a` (rotation and translation).
    #[inline]
    pub fn transform_point(&self, p: Vec3) -> Vec3 {
        self.rotation * p + self.translation
    }

    /// Maps a direction of frame `b` into frame `a` (rotation only).
    #[inline]
    pub fn transform_vector(&self, v: Vec3) -> Vec3 {
        self.rotation * v
    }

    /// Converts a Blender/OpenGL/NeRF camera-to-world (camera looks down -z, +y up) to the
    /// OpenCV `world_from_camera` used everywhere here (right-multiply by diag(1,-1,-1,1)).
    pub fn from_opengl_camera(world_from_gl_camera: Self) -> Self {
        let flip = Mat3::from_diagonal(Vec3::new(1.0, -1.0, -1.0));
        Self { rotation: world_from_gl_camera.rotation * flip, translation: world_from_gl_camera.translation }
    }

    /// Inverse of [`Rigid3::from_opengl_camera`]: OpenCV `world_from_camera` to the OpenGL /
    /// NeRF `transform_matrix` convention.
    pub fn to_opengl_camera(&self) -> Self {
        Self::from_opengl_camera(*self)
    }

    /// Rotation angle (radians) of `self.inverse() * other`, and translation distance.
    pub fn distance_to(&self, other: &Self) -> (f32, f32) {
        let rel = self.inverse() * *other;
        let cos =
            ((rel.rotation.x_axis.x + rel.rotation.y_axis.y + rel.rotation.z_axis.z - 1.0) * 0.5).clamp(-1.0, 1.0);
        (cos.acos(), rel.translation.length())
    }

    /// Builds a camera (`world_from_camera`, OpenCV axes) at `eye` looking at `target`, with
    /// `up` the world's up direction (the image's y axis points away from it).
    /// Returns `None` when `target == eye` or the view direction is parallel to `up`.
    pub fn look_at(eye: Vec3, target: Vec3, up: Vec3) -> Option<Self> {
        let z = (target - eye).try_normalize()?;
        let x = z.cross(up).try_normalize()?;
        let y = z.cross(x);
        Some(Self { rotation: Mat3::from_cols(x, y, z), translation: eye })
    }

    /// Re-orthonormalises the rotation (Gram-Schmidt), for poses accumulated over many steps.
    pub fn orthonormalized(&self) -> Self {
        let x = self.rotation.x_axis.normalize();
        let y = (self.rotation.y_axis - x * x.dot(self.rotation.y_axis)).normalize();
        let z = x.cross(y);
        Self { rotation: Mat3::from_cols(x, y, z), translation: self.translation }
    }

    /// True when all entries are finite.
    pub fn is_finite(&self) -> bool {
        self.rotation.is_finite() && self.translation.is_finite()
    }
}

impl std::ops::Mul for Rigid3 {
    type Output = Rigid3;
    /// `a_from_c = a_from_b * b_from_c`.
    fn mul(self, rhs: Rigid3) -> Rigid3 {
        Rigid3 {
            rotation: self.rotation * rhs.rotation,
            translation: self.rotation * rhs.translation + self.translation,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_rigid(rng: &mut impl Rng) -> Rigid3 {
        let axis = Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
        let axis = axis.try_normalize().unwrap_or(Vec3::Z);
        let rotation = Mat3::from_axis_angle(axis, rng.random_range(-3.0..3.0));
        let t = Vec3::new(rng.random_range(-50.0..50.0), rng.random_range(-50.0..50.0), rng.random_range(-5.0..5.0));
        Rigid3::new(rotation, t)
    }

    #[test]
    fn inverse_composes_to_identity_over_random_cases() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for _ in 0..200 {
            let a = random_rigid(&mut rng);
            let p = Vec3::new(rng.random_range(-9.0..9.0), rng.random_range(-9.0..9.0), rng.random_range(-9.0..9.0));
            let back = a.inverse().transform_point(a.transform_point(p));
            assert!((back - p).length() < 1e-3, "{back} vs {p}");
            let (ang, dist) = (a * a.inverse()).distance_to(&Rigid3::IDENTITY);
            assert!(ang < 1e-3 && dist < 1e-3);
        }
    }

    #[test]
    fn rows_round_trip_and_rigidity_check() {
        // Row-major layout against a matrix written by hand: a quarter turn about z maps x to y.
        let quarter = Rigid3::new(Mat3::from_rotation_z(std::f32::consts::FRAC_PI_2), Vec3::new(1.0, 2.0, 3.0));
        let expect = [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]];
        let rows = quarter.to_rows();
        for r in 0..4 {
            for c in 0..4 {
                assert!((rows[r][c] - expect[r][c]).abs() < 1e-7, "rows[{r}][{c}] = {}", rows[r][c]);
            }
        }
        assert_eq!(Rigid3::try_from_rows(expect).unwrap().transform_point(Vec3::X), Vec3::new(1.0, 3.0, 3.0));
        // Rotation and translation both survive the round trip, over random cases (f32 -> f64 -> f32
        // is exact, so they compare equal).
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let a = random_rigid(&mut rng);
        for _ in 0..100 {
            let x = random_rigid(&mut rng);
            assert_eq!(Rigid3::try_from_rows(x.to_rows()).unwrap(), x);
        }
        let mut rows = a.to_rows();
        rows[0][0] *= 2.0;
        assert!(matches!(Rigid3::try_from_rows(rows), Err(CoreError::NotRigid(_))));
        let mut rows = a.to_rows();
        rows[1][3] = f64::NAN;
        assert!(Rigid3::try_from_rows(rows).is_err());
        let mut rows = Rigid3::IDENTITY.to_rows();
        rows[2][2] = -1.0; // reflection
        assert!(Rigid3::try_from_rows(rows).is_err());
    }

    #[test]
    fn opengl_conversion_flips_view_direction() {
        // An OpenGL camera at the origin with identity rotation looks down world -z.
        let cv = Rigid3::from_opengl_camera(Rigid3::IDENTITY);
        let forward_world = cv.transform_vector(Vec3::Z);
        assert!((forward_world - Vec3::NEG_Z).length() < 1e-6);
        let back = cv.to_opengl_camera();
        assert!((back.rotation - Mat3::IDENTITY).abs_diff_eq(Mat3::ZERO, 1e-6));
    }

    #[test]
    fn look_at_points_optical_axis_at_target() {
        let cam = Rigid3::look_at(Vec3::new(1.0, 2.0, 3.0), Vec3::new(4.0, -2.0, 0.0), Vec3::Z).unwrap();
        let dir = (Vec3::new(4.0, -2.0, 0.0) - Vec3::new(1.0, 2.0, 3.0)).normalize();
        assert!((cam.transform_vector(Vec3::Z) - dir).length() < 1e-5);
        // image y (down) points away from world up
        assert!(cam.transform_vector(Vec3::Y).z < 0.0);
        assert!((cam.rotation.determinant() - 1.0).abs() < 1e-5);
        assert!(Rigid3::look_at(Vec3::ZERO, Vec3::ZERO, Vec3::Z).is_none());
    }
}
