//! The procedural CLEVR-Infinite world of SGAM and a fast CPU ray tracer for it.
//!
//! # Concepts
//! - **World frame**: metres, `+z` up; the dataset cameras sit on the plane `z = 0`, the ground
//!   is the horizontal square `|x|, |y| <= 100` at `z = GROUND_Z_M = -11.695`.
//! - **[`Scene`]**: deterministic from a `u64` seed and a [`SceneConfig`] (default = the paper:
//!   882 cones, cubes, cylinders and spheres of scale 1.0 or 0.7, random colours, dropped from
//!   a 2-layer 21 x 21 spawn grid and resting on the ground without interpenetration), plus one
//!   sun (soft shadows) and a sky/ambient term. Serializable: it is the scene description.
//! - **[`Renderer`]**: built once per scene (a uniform 2-D grid over the ground: all objects
//!   lie in a thin slab above it); renders any [`Camera`](sgam_core::Camera) into a
//!   [`SynthFrame`]: sRGB colour (stratified anti-aliasing averaged in linear light), planar
//!   depth in metres and object ids, all from OpenCV cameras (`world_from_camera`).
//! - **Dataset cameras** ([`dataset_cameras`]): the authors' 50 x 50 grid over `[-20, 20]^2`,
//!   Blender rotation `Rx(0.3)`, `index = grid_i * 50 + grid_j` with `grid_i` along world y and
//!   `grid_j` along world x, exactly as in their `transforms.json`.
//! - Training pairs are built on this crate by `sgam-pipeline` (`SynthPairs`, `codepairs`),
//!   with the generator's own guidance function.
//! - Determinism: every random draw comes from a seeded RNG; rendering hashes pixel and sample
//!   indices, so output bytes do not depend on thread scheduling.

mod cameras;
mod render;
mod scene;

pub use cameras::{
    blender_camera, blender_rotation, dataset_cameras, dataset_intrinsics, grid_coordinate_m, DatasetCamera,
};
pub use render::{Hit, RenderConfig, Renderer, SynthFrame, GROUND_ID, SKY_ID};
pub use scene::{
    paper_sun_dir, Material, MaterialMix, Object, Scene, SceneConfig, Shape, SPAWN_GRID, SPAWN_SPACING_M, SPAWN_X0_M,
    SPAWN_Y0_M,
};

/// Horizontal field of view of the dataset cameras (rad): `fx = 355.5555` at 256 px.
pub const CAMERA_FOV_X_RAD: f32 = 0.69111;
/// Ground plane height in the world (m): 11.695 below the camera plane.
pub const GROUND_Z_M: f32 = -11.695;
/// Blender camera-to-world rotation of the dataset cameras: `Rx(CAMERA_PITCH_RAD)` (the optical
/// axis points 72.8 degrees below the horizon, towards +y).
pub const CAMERA_PITCH_RAD: f32 = 0.3;
/// Camera height (world z, m).
pub const CAMERA_HEIGHT_M: f32 = 0.0;
/// The camera grid spans `[-GRID_HALF_EXTENT_M, GRID_HALF_EXTENT_M]` in x and y (m).
pub const GRID_HALF_EXTENT_M: f32 = 20.0;
/// Cameras per grid side in the dataset.
pub const DATASET_GRID: usize = 50;
/// Dataset image size (px).
pub const DATASET_RES: u32 = 256;
/// Half side of the ground square (m).
pub const GROUND_HALF_EXTENT_M: f32 = 100.0;
/// Blender Euler x angle of the sun (rad): light travels along `Rx(0.5) * (0, 0, -1)`.
pub const SUN_EULER_X_RAD: f32 = 0.5;
/// Angular radius of the sun disk used for soft shadows (rad).
pub const SUN_ANGULAR_RADIUS_RAD: f32 = 0.03;

/// Timing of a full-scene render (see [`time_scene_render`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderTiming {
    /// Frames rendered.
    pub frames: usize,
    /// Scene generation + acceleration structure time (s).
    pub setup_s: f64,
    /// Rendering time (s).
    pub render_s: f64,
    /// `frames / render_s`.
    pub frames_per_s: f64,
}

/// Generates scene `seed`, then renders the first `frames` cameras of the `grid x grid` dataset
/// grid at `res` px with `config` (frames in parallel within each render), discarding the
/// output; returns the timing. For the speed bar (2,500 frames at 256 px, 4 spp, shadows).
pub fn time_scene_render(seed: u64, frames: usize, grid: usize, res: u32, config: &RenderConfig) -> RenderTiming {
    let start = std::time::Instant::now();
    let scene = Scene::generate(seed, &SceneConfig::default());
    let renderer = Renderer::new(&scene);
    let setup_s = start.elapsed().as_secs_f64();
    let cameras = dataset_cameras(grid, res);
    let start = std::time::Instant::now();
    let mut checksum = 0.0f64;
    for cam in cameras.iter().take(frames) {
        let f = renderer.render(&cam.camera, config);
        checksum += f.frame.depth_m.data[0] as f64;
    }
    let render_s = start.elapsed().as_secs_f64();
    std::hint::black_box(checksum);
    let n = frames.min(cameras.len());
    RenderTiming { frames: n, setup_s, render_s, frames_per_s: n as f64 / render_s.max(1e-9) }
}
