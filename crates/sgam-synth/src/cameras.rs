//! The dataset's camera grid and pose conventions (authors' `transforms.json`).

use glam::{Mat3, Vec3};
use serde::{Deserialize, Serialize};
use sgam_core::{Camera, Intrinsics, Rigid3};

use crate::{CAMERA_FOV_X_RAD, CAMERA_HEIGHT_M, CAMERA_PITCH_RAD, GRID_HALF_EXTENT_M};

/// One camera of the dataset grid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DatasetCamera {
    /// Frame index `k = grid_i * grid + grid_j` (file `im_{k:05}.png`).
    pub index: usize,
    /// Grid row: indexes world **y** (`y = grid_i_m`).
    pub grid_i: usize,
    /// Grid column: indexes world **x** (`x = grid_j_m`).
    pub grid_j: usize,
    /// The value the authors store as `grid_i` in `transforms.json`: the world y of the camera
    /// (m), computed like `numpy.linspace(-20, 20, grid)`.
    pub grid_i_m: f64,
    /// The value stored as `grid_j`: the world x of the camera (m).
    pub grid_j_m: f64,
    /// The camera (OpenCV `world_from_camera`, intrinsics at the requested resolution).
    pub camera: Camera,
}

impl DatasetCamera {
    /// Blender/OpenGL camera-to-world as a row-major 4x4 (`transform_matrix` in the json).
    pub fn transform_matrix(&self) -> [[f64; 4]; 4] {
        self.camera.world_from_camera.to_opengl_camera().to_rows()
    }
}

/// Blender camera-to-world rotation of a camera with Euler XYZ `(pitch, 0, yaw)`:
/// `Rz(yaw) * Rx(pitch)`; the authors' dataset uses `pitch = 0.3`, `yaw = 0` (looking down and
/// towards +y).
pub fn blender_rotation(pitch_rad: f32, yaw_rad: f32) -> Mat3 {
    Mat3::from_rotation_z(yaw_rad) * Mat3::from_rotation_x(pitch_rad)
}

/// An OpenCV camera from a Blender-style pose: centre (m), Blender pitch/yaw (rad), square
/// pixels from the horizontal FOV, principal point at `(res/2, res/2)`.
pub fn blender_camera(centre_m: Vec3, pitch_rad: f32, yaw_rad: f32, intrinsics: Intrinsics) -> Camera {
    let world_from_gl = Rigid3::new(blender_rotation(pitch_rad, yaw_rad), centre_m);
    Camera::new(intrinsics, Rigid3::from_opengl_camera(world_from_gl))
}

/// The dataset intrinsics at `res x res` pixels (`fx = fy = 355.5555`, `cx = cy = 128` at 256).
pub fn dataset_intrinsics(res: u32) -> Intrinsics {
    Intrinsics::from_fov_x(res, res, CAMERA_FOV_X_RAD)
}

/// Grid coordinate `j` of `grid` evenly spaced values over `[-20, 20]` (numpy `linspace`).
pub fn grid_coordinate_m(j: usize, grid: usize) -> f64 {
    let h = GRID_HALF_EXTENT_M as f64;
    if grid <= 1 {
        return -h;
    }
    if j + 1 == grid {
        return h;
    }
    let step = 2.0 * h / (grid - 1) as f64;
    -h + j as f64 * step
}

/// The authors' camera grid: `grid x grid` cameras at height 0 over x, y in `[-20, 20]`, Blender
/// rotation `Rx(0.3)`, ordered `index = grid_i * grid + grid_j` with `grid_i` along y and
/// `grid_j` along x (frame 0 at (-20, -20, 0), frame 1 at (-19.18, -20, 0)).
pub fn dataset_cameras(grid: usize, res: u32) -> Vec<DatasetCamera> {
    let intrinsics = dataset_intrinsics(res);
    let mut out = Vec::with_capacity(grid * grid);
    for grid_i in 0..grid {
        for grid_j in 0..grid {
            let (y, x) = (grid_coordinate_m(grid_i, grid), grid_coordinate_m(grid_j, grid));
            let centre = Vec3::new(x as f32, y as f32, CAMERA_HEIGHT_M);
            out.push(DatasetCamera {
                index: grid_i * grid + grid_j,
                grid_i,
                grid_j,
                grid_i_m: y,
                grid_j_m: x,
                camera: blender_camera(centre, CAMERA_PITCH_RAD, 0.0, intrinsics),
            });
        }
    }
    out
}
