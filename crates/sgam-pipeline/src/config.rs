//! The resolved configuration of a generation run: what a snapshot stores and a resumed run
//! continues with. Every default is applied and every length is in metres, so the run does not
//! depend on how the command line spelled it.

use serde::{Deserialize, Serialize};
use sgam_map::TsdfConfig;

use crate::error::config_error;
use crate::generator::{clevr_generator_config, GeneratorConfig};
use crate::{RefinerSpec, Result, SeedSpec, TrajectorySpec};

/// Version of [`RunConfig`]'s layout (a snapshot of another version is refused on resume).
pub const RUN_CONFIG_VERSION: u32 = 1;
/// Largest image side of a run (keyframe cache and model activations stay within a few GB).
pub const MAX_RES: u32 = 2048;
/// Most generation steps of one run.
pub const MAX_STEPS: usize = 1_000_000;
/// Largest grid side of the grid trajectories.
pub const MAX_GRID: usize = 1000;

/// What a run writes besides the frames (the pipeline writes snapshots; the caller the rest).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OutputSettings {
    /// Snapshot every N steps (and after the seed and the last step).
    pub snapshot_every: usize,
    /// Also write the world mesh every N steps (0 = only at the end).
    pub mesh_every: usize,
    /// Also write 16-bit PNG depth in millimetres.
    pub depth_png: bool,
    /// Write the fly-through GIF (and the MP4 unless `mp4` is false).
    pub video: bool,
    /// Write flythrough.mp4 (with `video`).
    pub mp4: bool,
    /// Write orbit.mp4.
    pub orbit_video: bool,
    /// Write guidance/NNNNN.png: what the refiner was given (holes magenta), what it returned,
    /// and the frame after the invented-pixel filters, side by side.
    #[serde(default)]
    pub guidance_png: bool,
    /// A tiled world is also written as one mesh when it has at most this many triangles
    /// (runs written before it existed read as the default, 4 million).
    #[serde(default = "default_single_mesh_max_triangles")]
    pub single_mesh_max_triangles: u64,
}

fn default_single_mesh_max_triangles() -> u64 {
    (f64::from(crate::settings::DEFAULT_SINGLE_MESH_MAX_MTRI) * 1e6).round() as u64
}

/// A generation run, resolved.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunConfig {
    /// [`RUN_CONFIG_VERSION`] when written.
    pub version: u32,
    /// The seed frame.
    pub seed: SeedSpec,
    /// The camera path.
    pub trajectory: TrajectorySpec,
    /// Generation steps (poses after the seed).
    pub steps: usize,
    /// The refiner.
    pub refiner: RefinerSpec,
    /// The map.
    pub map: TsdfConfig,
    /// Source keyframes per step.
    pub k_sources: usize,
    /// Sources must lie within this distance, metres.
    pub source_radius_m: f32,
    /// Ablation: no global map; guidance from the previous frame only.
    pub no_map: bool,
    /// Run seed; each step's refiner seed derives from it and the step index.
    pub run_seed: u64,
    /// Outputs.
    pub outputs: OutputSettings,
    /// Ground prior: invented ground-like pixels less than this above the seed frame's ground
    /// plane are put on it, metres ([`GeneratorConfig::ground_snap_m`]); `None` = off.
    #[serde(default)]
    pub ground_snap_m: Option<f32>,
    /// With the ground prior: invented pixels less than this above the plane go on it whatever
    /// the surface around them, metres ([`GeneratorConfig::ground_flatten_m`]); runs written
    /// before it existed read as 0 (off).
    #[serde(default)]
    pub ground_flatten_m: f32,
    /// Invented flying pixels are given to a surface ([`GeneratorConfig::snap_flying_pixels`]);
    /// runs written before it existed read as off.
    #[serde(default)]
    pub snap_flying_pixels: bool,
    /// Invented pixels that earlier views saw through are grounded or dropped
    /// ([`GeneratorConfig::carve_free_space`]); runs written before it existed read as off.
    #[serde(default)]
    pub carve_free_space: bool,
    /// Invented objects are fused as solids up to this deep, metres
    /// ([`GeneratorConfig::solid_max_m`]); 0 = off (runs written before it existed read as 0).
    #[serde(default)]
    pub solid_max_m: f32,
    /// Guard rail on invented objects' footprints, m² ([`GeneratorConfig::max_object_m2`]);
    /// 0 = off (runs written before it existed read as 0).
    #[serde(default)]
    pub max_object_m2: f32,
    /// Guard rail on invented objects' length, metres ([`GeneratorConfig::max_object_length_m`]);
    /// 0 = off (runs written before it existed read as 0).
    #[serde(default)]
    pub max_object_length_m: f32,
    /// Invented objects take one colour by vote, this share of the way
    /// ([`GeneratorConfig::object_colour`]); 0 = off (runs written before it existed read as 0).
    #[serde(default)]
    pub object_colour: f32,
    /// Bound on the map's memory, MB: beyond it, far super-blocks go to tiles on disk
    /// ([`crate::tiles`]). 0 = no bound (runs written before it existed read as 0).
    #[serde(default)]
    pub max_map_mb: usize,
}

impl RunConfig {
    /// The generator's parameters: the CLEVR loop ([`clevr_generator_config`]) with this run's
    /// map, sources and ablation.
    pub fn generator_config(&self) -> GeneratorConfig {
        GeneratorConfig {
            tsdf: self.map,
            k_sources: self.k_sources,
            source_radius_m: self.source_radius_m,
            no_map: self.no_map,
            ground_snap_m: self.ground_snap_m,
            ground_flatten_m: self.ground_flatten_m,
            snap_flying_pixels: self.snap_flying_pixels,
            carve_free_space: self.carve_free_space,
            solid_max_m: self.solid_max_m,
            max_object_m2: self.max_object_m2,
            max_object_length_m: self.max_object_length_m,
            object_colour: self.object_colour,
            ..clevr_generator_config(self.run_seed)
        }
    }

    /// How far beyond its reach a camera looks before far tiles come back
    /// ([`crate::tiles::MapStreaming::new`]): eight blocks, one and a half greedy steps more
    /// for the greedy planner, which renders the cells around the camera, and the deepest solid
    /// (`--solid-objects`), which is filled that far behind a surface at `--depth-max`.
    pub fn stream_margin_m(&self) -> f32 {
        let greedy = match self.trajectory {
            crate::TrajectorySpec::Greedy { step_m, .. } => 1.5 * step_m,
            _ => 0.0,
        };
        8.0 * self.map.block_size_m() + greedy + self.solid_max_m.max(0.0)
    }

    /// Checks a configuration read back from a snapshot: its version, counts within bounds, a
    /// valid map.
    pub fn validate(&self) -> Result<()> {
        if self.version != RUN_CONFIG_VERSION {
            config_error!("run config version {} (this build reads {RUN_CONFIG_VERSION})", self.version);
        }
        if !(1..=MAX_STEPS).contains(&self.steps) {
            config_error!("{} steps (accepted 1..={MAX_STEPS})", self.steps);
        }
        if !(1..=MAX_STEPS).contains(&self.outputs.snapshot_every) || self.outputs.mesh_every > MAX_STEPS {
            config_error!("snapshot / mesh interval out of range");
        }
        if !(1..=64).contains(&self.k_sources) || !(f32::MIN_POSITIVE..=1000.0).contains(&self.source_radius_m) {
            config_error!(
                "sources: {} within {} m (accepted 1..=64 within (0, 1000] m)",
                self.k_sources,
                self.source_radius_m
            );
        }
        if let SeedSpec::Synthetic { res, .. } = self.seed {
            if !(16..=MAX_RES).contains(&res) {
                config_error!("synthetic seed of {res} px (accepted 16..={MAX_RES})");
            }
        }
        match self.trajectory {
            TrajectorySpec::Zigzag { side, .. }
            | TrajectorySpec::Boustrophedon { side, .. }
            | TrajectorySpec::Greedy { side, .. }
                if !(1..=MAX_GRID.max(1 + MAX_STEPS.isqrt())).contains(&side) =>
            {
                config_error!("grid side {side} out of range")
            }
            _ => {}
        }
        if let Some(m) = self.ground_snap_m {
            if !(m > 0.0 && m <= 10.0) {
                config_error!("ground prior tolerance {m} m (accepted (0, 10] m)");
            }
        }
        self.map.validate()?;
        Ok(())
    }
}
