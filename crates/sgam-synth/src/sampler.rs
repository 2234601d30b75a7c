//! On-the-fly training sampler: random scene, target camera and nearby source cameras, rendered
//! without touching the disk; scenes are cached (LRU).

use std::sync::Arc;

use glam::{Vec2, Vec3};
use rand::Rng;
use serde::{Deserialize, Serialize};
use sgam_core::{Camera, RgbdFrame};

use crate::cameras::{blender_camera, dataset_intrinsics, grid_coordinate_m};
use crate::render::{RenderConfig, Renderer};
use crate::scene::{Scene, SceneConfig};
use crate::{SynthError, CAMERA_HEIGHT_M, CAMERA_PITCH_RAD, GRID_HALF_EXTENT_M};

/// Random perturbation of a camera pose; each value is the half-width of a uniform draw.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct CameraJitter {
    /// Horizontal position jitter (m), applied per axis.
    pub position_m: f32,
    /// Height jitter (m) around the camera plane `z = 0`.
    pub height_m: f32,
    /// Blender pitch jitter (rad) around 0.3.
    pub pitch_rad: f32,
    /// Yaw jitter (rad) around 0 (rotation about world +z).
    pub yaw_rad: f32,
}

/// Parameters of the training sampler.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SamplerConfig {
    /// Scene seeds to draw from (uniformly).
    pub scene_seeds: Vec<u64>,
    /// Scene generator parameters.
    pub scene: SceneConfig,
    /// Square image size in pixels (intrinsics scale with it: `fx = 355.5555 * res / 256`).
    pub res: u32,
    /// Number of source cameras per sample.
    pub k_sources: usize,
    /// Sources lie within this horizontal distance of the target (m).
    pub radius_m: f32,
    /// Snap cameras to the dataset grid (`grid x grid` over [-20, 20]^2) before jitter; else
    /// positions are continuous (target uniform over the grid square, sources uniform in the
    /// disk of `radius_m`).
    pub on_grid: bool,
    /// Dataset grid size (50 in the paper).
    pub grid: usize,
    /// Jitter of the target pose.
    pub target_jitter: CameraJitter,
    /// Jitter of each source pose.
    pub source_jitter: CameraJitter,
    /// Rendering options.
    pub render: RenderConfig,
    /// Number of (scene, renderer) pairs kept in the LRU cache (at least 1).
    pub cache_scenes: usize,
}

impl Default for SamplerConfig {
    fn default() -> Self {
        Self {
            scene_seeds: (0..72).collect(),
            scene: SceneConfig::default(),
            res: 256,
            k_sources: 5,
            radius_m: 1.0,
            on_grid: true,
            grid: 50,
            target_jitter: CameraJitter::default(),
            source_jitter: CameraJitter::default(),
            render: RenderConfig::default(),
            cache_scenes: 4,
        }
    }
}

/// One training sample: a target view and `k` source views of the same scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// Seed of the scene.
    pub scene_seed: u64,
    /// Target camera and its rendered RGB-D frame.
    pub target: (Camera, RgbdFrame),
    /// Source cameras and frames (within `radius_m` of the target, before jitter).
    pub sources: Vec<(Camera, RgbdFrame)>,
}

/// The training sampler. Deterministic given the rng passed to [`Sampler::sample`].
#[derive(Debug)]
pub struct Sampler {
    config: SamplerConfig,
    /// Most recently used last.
    cache: Vec<(u64, Arc<(Scene, Renderer)>)>,
}

impl Sampler {
    /// Checks the config: non-empty seeds, `res > 0`, `grid > 0`, finite non-negative radius.
    pub fn try_new(config: SamplerConfig) -> Result<Self, SynthError> {
        if config.scene_seeds.is_empty() {
            return Err(SynthError::InvalidConfig("scene_seeds is empty".into()));
        }
        if config.res == 0 || config.grid == 0 {
            return Err(SynthError::InvalidConfig(format!("res {} and grid {} must be > 0", config.res, config.grid)));
        }
        if !(config.radius_m.is_finite() && config.radius_m >= 0.0) {
            return Err(SynthError::InvalidConfig(format!("radius_m {} must be >= 0", config.radius_m)));
        }
        Ok(Self { config, cache: Vec::new() })
    }

    /// Like [`Sampler::try_new`] but repairs a bad config instead of failing: empty seeds become
    /// `[0]`, zero `res`/`grid` become 256/50, a bad radius becomes 1 m.
    pub fn new(mut config: SamplerConfig) -> Self {
        if config.scene_seeds.is_empty() {
            config.scene_seeds = vec![0];
        }
        if config.res == 0 {
            config.res = 256;
        }
        if config.grid == 0 {
            config.grid = 50;
        }
        if !(config.radius_m.is_finite() && config.radius_m >= 0.0) {
            config.radius_m = 1.0;
        }
        Self { config, cache: Vec::new() }
    }

    /// The configuration in use.
    pub fn config(&self) -> &SamplerConfig {
        &self.config
    }

    /// The scene of `seed` and its renderer, from the cache or freshly generated.
    pub fn scene(&mut self, seed: u64) -> Arc<(Scene, Renderer)> {
        if let Some(pos) = self.cache.iter().position(|(s, _)| *s == seed) {
            let entry = self.cache.remove(pos);
            let value = entry.1.clone();
            self.cache.push(entry);
            return value;
        }
        let scene = Scene::generate(seed, &self.config.scene);
        let renderer = Renderer::new(&scene);
        let value = Arc::new((scene, renderer));
        self.cache.push((seed, value.clone()));
        while self.cache.len() > self.config.cache_scenes.max(1) {
            self.cache.remove(0);
        }
        value
    }

    /// Draws a scene seed, a target camera and `k_sources` source cameras, and renders them.
    pub fn sample(&mut self, rng: &mut impl Rng) -> Sample {
        let seeds = &self.config.scene_seeds;
        let scene_seed = seeds[rng.random_range(0..seeds.len())];
        let (target_xy, sources_xy) = self.draw_positions(rng);
        let c = &self.config;
        let intrinsics = dataset_intrinsics(c.res);
        let target_camera = jittered_camera(target_xy, &c.target_jitter, intrinsics, rng);
        let source_cameras: Vec<Camera> =
            sources_xy.iter().map(|xy| jittered_camera(*xy, &c.source_jitter, intrinsics, rng)).collect();
        let render = c.render.clone();
        let entry = self.scene(scene_seed);
        let renderer = &entry.1;
        let target = (target_camera, renderer.render(&target_camera, &render).frame);
        let sources = source_cameras.into_iter().map(|cam| (cam, renderer.render(&cam, &render).frame)).collect();
        Sample { scene_seed, target, sources }
    }

    /// Target and source horizontal positions (before jitter).
    fn draw_positions(&self, rng: &mut impl Rng) -> (Vec2, Vec<Vec2>) {
        let c = &self.config;
        let h = GRID_HALF_EXTENT_M;
        let disk = |rng: &mut dyn rand::RngCore, centre: Vec2| {
            let r = c.radius_m * rng.random::<f32>().sqrt();
            let a = rng.random_range(0.0..std::f32::consts::TAU);
            centre + Vec2::new(a.cos(), a.sin()) * r
        };
        if !c.on_grid {
            let target = Vec2::new(rng.random_range(-h..=h), rng.random_range(-h..=h));
            let sources = (0..c.k_sources).map(|_| disk(rng, target)).collect();
            return (target, sources);
        }
        let node =
            |i: usize, j: usize| Vec2::new(grid_coordinate_m(j, c.grid) as f32, grid_coordinate_m(i, c.grid) as f32);
        let (ti, tj) = (rng.random_range(0..c.grid), rng.random_range(0..c.grid));
        let target = node(ti, tj);
        // Grid nodes within the radius, in a fixed order, then a partial Fisher-Yates shuffle.
        let mut near: Vec<Vec2> = Vec::new();
        for i in 0..c.grid {
            for j in 0..c.grid {
                let p = node(i, j);
                if (i, j) != (ti, tj) && (p - target).length() <= c.radius_m + 1e-4 {
                    near.push(p);
                }
            }
        }
        let mut sources = Vec::with_capacity(c.k_sources);
        for k in 0..c.k_sources {
            if k < near.len() {
                let pick = rng.random_range(k..near.len());
                near.swap(k, pick);
                sources.push(near[k]);
            } else {
                sources.push(disk(rng, target));
            }
        }
        (target, sources)
    }
}

fn jittered_camera(xy: Vec2, jitter: &CameraJitter, intrinsics: sgam_core::Intrinsics, rng: &mut impl Rng) -> Camera {
    let mut u = |half: f32| if half > 0.0 { rng.random_range(-half..=half) } else { 0.0 };
    let dx = u(jitter.position_m);
    let dy = u(jitter.position_m);
    let dz = u(jitter.height_m);
    let pitch = CAMERA_PITCH_RAD + u(jitter.pitch_rad);
    let yaw = u(jitter.yaw_rad);
    let centre = Vec3::new(xy.x + dx, xy.y + dy, CAMERA_HEIGHT_M + dz);
    blender_camera(centre, pitch, yaw, intrinsics)
}
