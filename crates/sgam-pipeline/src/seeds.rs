//! The seed of a run: the first camera and RGB-D frame, plus the synthetic world when there is
//! one, and the dataset preset (the SGAM authors' values) that goes with it.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use sgam_core::{Camera, Intrinsics, RgbdFrame, Vec3};
use sgam_synth::{blender_camera, dataset_intrinsics, RenderConfig, Renderer, Scene, SceneConfig};

use crate::error::config_error;
use crate::Result;

/// First scene seed reserved for evaluation and generation; training never uses seeds at or
/// above it.
pub const HELD_OUT_SEED_BASE: u64 = 1_000_000;

/// Dataset-specific defaults (the SGAM authors' values).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Preset {
    /// Distance between neighbouring poses, metres.
    pub step_m: f32,
    /// Source keyframes per step.
    pub k_sources: usize,
    /// Sources must lie within this distance, metres.
    pub source_radius_m: f32,
    /// Voxel size, metres.
    pub voxel_size_m: f32,
    /// Truncation, voxels.
    pub trunc_voxels: f32,
    /// Invented objects fused as solids up to this deep, metres (0 = off; `--solid-objects`).
    pub solid_objects_m: f32,
    /// Guard rail on invented objects' footprints, m² (0 = off; `--max-object-m2`).
    pub max_object_m2: f32,
    /// Guard rail on invented objects' length, metres (0 = off; `--max-object-length`).
    pub max_object_length_m: f32,
    /// Invented objects take one colour by vote, this share of the way (0 = off;
    /// `--object-colour`).
    pub object_colour: f32,
    /// Quilting the seed's own pixels (`--bank seed`): a hole wider than this many latent cells
    /// is quilted as tiles of this side (`--quilt-tile`).
    pub quilt_tile: usize,
    /// Quilting the seed's own pixels: the thin bands a moving camera uncovers wait until they
    /// reach this many latent cells into the frame (`--bands-wait auto`).
    pub quilt_bands_wait: usize,
}

/// CLEVR-Infinite: 0.408 m steps (half the dataset spacing), 5 sources within 1 m, 5 cm voxels,
/// truncation 5 voxels (0.25 m). The SGAM authors truncate at 10 voxels; 0.5 m fattens the
/// world's 1-2 m objects in the map itself (the oracle's objects merge: 11.8 instead of 13.5
/// per 100 m², p90 footprint 6.2 instead of 4.8 m²) and lets an invented object's inconsistent
/// views average into a skirt on the ground around it (docs/MODEL.md, session 11).
/// Invented objects are fused as solids up to 1 m deep and capped at 6 m² of footprint
/// (CLEVR-Infinite's objects: median about 2 m², 90th percentile 4-6 m²): with the bundled
/// context model they keep the spiral's new area from collapsing into mounds (docs/MODEL.md,
/// sessions 29-30).
pub const CLEVR: Preset = Preset {
    step_m: 0.408,
    k_sources: 5,
    source_radius_m: 1.0,
    voxel_size_m: 0.05,
    trunc_voxels: 5.0,
    solid_objects_m: 1.0,
    max_object_m2: 6.0,
    max_object_length_m: 0.0,
    object_colour: 0.0,
    quilt_tile: crate::settings::DEFAULT_QUILT_TILE,
    quilt_bands_wait: sgam_model::refiner::DEFAULT_BANDS_WAIT,
};
/// Google Earth: 2 cm steps, 3 sources within 0.3, 1 cm voxels, truncation 3 voxels. No solids
/// and no size cap: a Google Earth seed's units are not metres, and its buildings are not
/// CLEVR's primitives. The seed's pixels are quilted in 12-cell tiles, and the band the camera
/// uncovers waits until it is 8 cells (64 px) deep: each piece then holds whole houses and
/// trees, not a strip of road continued step after step into slanted streaks (docs/STATUS.md,
/// session 31; chosen on the preset's own path, the line; on the spiral too it scored closer to
/// the seed, 0.29 against 0.69 on GE seed 0 at 40 steps). Along a zig-zag of the preset's
/// 0.02-unit steps the bands never reach 8 cells and stay unfilled (`--bands-wait 3` fills them).
pub const GOOGLE_EARTH: Preset = Preset {
    step_m: 0.02,
    k_sources: 3,
    source_radius_m: 0.3,
    voxel_size_m: 0.01,
    trunc_voxels: 3.0,
    solid_objects_m: 0.0,
    max_object_m2: 0.0,
    max_object_length_m: 0.0,
    object_colour: 0.0,
    quilt_tile: 12,
    quilt_bands_wait: 8,
};
/// A user's RGB-D frame: CLEVR's map, sources and quilting (the step follows the seed's depth,
/// `sgam generate --help`), without solids or the size cap, which are sized for
/// CLEVR-Infinite's objects. (Google Earth's longer wait and larger tiles scored worse on the
/// 7-Scenes frame, whose forward path uncovers bands on every side: docs/STATUS.md, session 31.)
pub const RGBD: Preset =
    Preset { solid_objects_m: 0.0, max_object_m2: 0.0, max_object_length_m: 0.0, object_colour: 0.0, ..CLEVR };

/// Where a run's seed frame comes from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum SeedSpec {
    /// A procedural CLEVR-Infinite scene rendered at `res x res` from [`synthetic_seed_camera`].
    Synthetic {
        /// Scene seed (held-out seeds start at [`HELD_OUT_SEED_BASE`]).
        scene: u64,
        /// Image side, pixels.
        res: u32,
    },
    /// Any RGB image with planar depth (16-bit PNG in millimetres or NPY in metres).
    Rgbd {
        /// Colour image.
        rgb: PathBuf,
        /// Depth image.
        depth: PathBuf,
        /// `fx, fy, cx, cy` in pixels.
        intrinsics: [f32; 4],
    },
    /// The SGAM authors' CLEVR-Infinite template folder (ray-length depth).
    ClevrTemplate {
        /// The folder.
        dir: PathBuf,
    },
    /// An SGAM Google Earth seed folder (planar depth).
    GoogleEarth {
        /// The folder.
        dir: PathBuf,
    },
}

impl SeedSpec {
    /// The dataset preset of this seed.
    pub fn preset(&self) -> Preset {
        match self {
            SeedSpec::GoogleEarth { .. } => GOOGLE_EARTH,
            SeedSpec::Rgbd { .. } => RGBD,
            SeedSpec::Synthetic { .. } | SeedSpec::ClevrTemplate { .. } => CLEVR,
        }
    }

    /// Loads the seed frame (renders it for a synthetic seed).
    pub fn load(&self) -> Result<Seed> {
        match self {
            SeedSpec::Rgbd { rgb, depth, intrinsics: [fx, fy, cx, cy] } => {
                let (w, h) = sgam_io::image_size(rgb)?;
                let k = match Intrinsics::try_new(w, h, *fx, *fy, *cx, *cy) {
                    Ok(k) => k,
                    Err(e) => config_error!("--intrinsics: {e}"),
                };
                let s = sgam_io::read_seed_rgbd(rgb, depth, k)?;
                Ok(Seed { camera: s.camera, frame: s.frame, renderer: None, name: rgb.display().to_string() })
            }
            SeedSpec::ClevrTemplate { dir } => {
                let s = sgam_io::read_clevr_template(dir)?;
                Ok(Seed { camera: s.camera, frame: s.frame, renderer: None, name: dir.display().to_string() })
            }
            SeedSpec::GoogleEarth { dir } => {
                let s = sgam_io::read_google_earth_seed(dir)?;
                Ok(Seed { camera: s.camera, frame: s.frame, renderer: None, name: dir.display().to_string() })
            }
            SeedSpec::Synthetic { scene, res } => {
                let renderer = Renderer::new(&Scene::generate(*scene, &SceneConfig::default()));
                let camera = synthetic_seed_camera(*res);
                let frame = renderer.render(&camera, &RenderConfig::default()).frame;
                Ok(Seed { camera, frame, renderer: Some(renderer), name: format!("synthetic scene {scene}") })
            }
        }
    }
}

/// The seed: first camera and frame, plus the synthetic world when there is one.
#[derive(Debug, Clone)]
pub struct Seed {
    /// The seed camera (keyframe 0).
    pub camera: Camera,
    /// The seed frame.
    pub frame: RgbdFrame,
    /// The synthetic world's renderer (synthetic seeds only; what the oracle refiner renders).
    pub renderer: Option<Renderer>,
    /// A name for messages (the file or the scene).
    pub name: String,
}

/// The camera of synthetic seeds: the dataset's first grid camera (-20, -20), looking down at
/// the dataset's pitch, `res x res` pixels. Evaluation derives the seed's footprint from it.
pub fn synthetic_seed_camera(res: u32) -> Camera {
    blender_camera(
        Vec3::new(-20.0, -20.0, sgam_synth::CAMERA_HEIGHT_M),
        sgam_synth::CAMERA_PITCH_RAD,
        0.0,
        dataset_intrinsics(res),
    )
}

/// `intrinsics` (`fx, fy, cx, cy`) must describe a real camera for a `w x h` image: fields of
/// view between 0.1 and 179 degrees (focal lengths `0.005..=500` times the image side) and the
/// principal point on the image.
pub fn check_intrinsics([fx, fy, cx, cy]: [f32; 4], w: u32, h: u32) -> Result<()> {
    let (w, h) = (w as f32, h as f32);
    for (name, f, side) in [("fx", fx, w), ("fy", fy, h)] {
        let range = sgam_core::Intrinsics::plausible_focal_px(side);
        if !range.contains(&f) {
            config_error!(
                "--intrinsics {name} {f} is out of range for a {side} px image side: accepted {}..={} px \
                 (fields of view from 0.1 to 179 degrees)",
                range.start(),
                range.end()
            );
        }
    }
    for (name, c, side) in [("cx", cx, w), ("cy", cy, h)] {
        if !(0.0..=side).contains(&c) {
            config_error!("--intrinsics {name} {c} puts the principal point off the image: accepted 0..={side} px");
        }
    }
    Ok(())
}
