//! The SGAM unrolling loop: [`WorldGenerator::step`] reads like the paper's recipe.

use std::time::Instant;

use serde::{Deserialize, Serialize};
use sgam_core::edges::{snap_flying_pixels, FlyingPixelConfig};
use sgam_core::freespace::{carve_invented, FreeSpaceConfig};
use sgam_core::ground::{fit_ground_plane, snap_to_ground, GroundFitConfig, GroundPlane, GroundSnapConfig};
use sgam_core::solid::{
    cap_invented_objects, object_thickness, unify_object_colours, ObjectCapConfig, ObjectColourConfig, SolidConfig,
};
use sgam_core::{Camera, Guidance, Refiner, RgbdFrame};
use sgam_map::{warp_colour, SourceSelection, SourceView, TsdfConfig, TsdfMap, WarpConfig};

use crate::keyframes::{quantise_colour, Keyframes};
use crate::{PipelineError, Result};

/// Parameters of the loop (everything but the refiner and the trajectory).
#[derive(Debug, Clone)]
pub struct GeneratorConfig {
    /// The map's TSDF parameters.
    pub tsdf: TsdfConfig,
    /// Geometry check of the inverse warping.
    pub warp: WarpConfig,
    /// At most this many source keyframes per step (authors: 5 on CLEVR, 3 on Google Earth).
    pub k_sources: usize,
    /// Sources must lie within this distance of the target camera, metres (authors: 1.0 / 0.3).
    pub source_radius_m: f32,
    /// Ablation (InfiniteNature-style): no global map; the guidance comes from the previous
    /// frame only.
    pub no_map: bool,
    /// Run seed; the refiner's per-step seed is derived from it and the step index.
    pub seed: u64,
    /// Ground prior: invented pixels that the refiner puts less than this many metres above the
    /// seed frame's ground plane (or below it) are put back on the plane
    /// ([`sgam_core::ground::snap_to_ground`]). `None` = the refiner's depth as it is.
    pub ground_snap_m: Option<f32>,
    /// With the ground prior: invented pixels less than this above the plane go on it whatever
    /// the surface around them ([`GroundSnapConfig::flatten_below_m`]); 0 = off.
    pub ground_flatten_m: f32,
    /// Invented pixels that hang between two surfaces (a decoder's depth ramp at a silhouette)
    /// are given to the nearer surface or to the ground behind, before the ground prior
    /// ([`sgam_core::edges::snap_flying_pixels`]). Off = the refiner's depth as it is.
    pub snap_flying_pixels: bool,
    /// Invented pixels that the seed frame or a source saw through (free space the map does not
    /// store) go to the ground plane behind them, or are dropped, after the flying pixels and
    /// before the ground prior ([`sgam_core::freespace::carve_invented`]).
    pub carve_free_space: bool,
    /// Invented object pixels (at least 10 cm above the seed frame's ground plane) are fused
    /// as solids reaching a back as far behind the object's front as the object is wide, from
    /// twice the truncation up to this many metres ([`sgam_core::solid::object_thickness`], [`TsdfMap::integrate_behind`]);
    /// 0 = off (a one-view shell as thick as the truncation band).
    pub solid_max_m: f32,
    /// Guard rail: an object with invented pixels whose footprint passes this many square
    /// metres has its invented pixels put on the ground plane
    /// ([`sgam_core::solid::cap_invented_objects`]); 0 = off.
    pub max_object_m2: f32,
    /// Guard rail: an object with invented pixels whose footprint is longer than this many
    /// metres has its invented pixels put on the ground plane (the same rule); 0 = off.
    pub max_object_length_m: f32,
    /// Each invented object takes one colour by vote, its invented pixels moved this share of
    /// the way to it at their own shading ([`sgam_core::solid::unify_object_colours`]); 0 = off.
    pub object_colour: f32,
}

/// The loop's parameters for the CLEVR-Infinite world: the [`crate::seeds::CLEVR`] preset's voxels,
/// truncation and sources (5 cm voxels, truncation 5 voxels, the nearest 5 sources within 1 m),
/// depth 0.05-20 m, colour from the nearest source camera that passes the geometry check, weight
/// threshold 1.
/// Generation (`sgam generate`, whose options override fields of it) and the generative
/// stage-2 training pairs ([`crate::codepairs`]) both start from this one value.
pub fn clevr_generator_config(seed: u64) -> GeneratorConfig {
    GeneratorConfig {
        tsdf: TsdfConfig {
            voxel_size_m: crate::seeds::CLEVR.voxel_size_m,
            trunc_voxels: crate::seeds::CLEVR.trunc_voxels,
            depth_min_m: 0.05,
            depth_max_m: 20.0,
            weight_cap: None,
            weight_threshold: 1.0,
        },
        warp: WarpConfig { selection: SourceSelection::NearestCamera, ..WarpConfig::default() },
        k_sources: crate::seeds::CLEVR.k_sources,
        source_radius_m: crate::seeds::CLEVR.source_radius_m,
        no_map: false,
        seed,
        ground_snap_m: None,
        ground_flatten_m: 0.0,
        snap_flying_pixels: false,
        carve_free_space: false,
        solid_max_m: 0.0,
        max_object_m2: 0.0,
        max_object_length_m: 0.0,
        object_colour: 0.0,
    }
}

/// The guidance at `camera`: the map's mesh rasterized to depth, colour inverse-warped from
/// `sources` with the geometry check, missing where neither gives a value. The one function
/// that generation ([`WorldGenerator::step`]), the training pairs and the evaluation call, so
/// a model trains and is judged on exactly the guidance it will complete. Returns the guidance
/// and the rasterization's wall time (ms).
pub fn render_guidance(
    map: &mut TsdfMap,
    camera: &Camera,
    sources: &[SourceView<'_>],
    warp: &WarpConfig,
    seed: u64,
) -> (Guidance, f64) {
    let t = Instant::now();
    let depth_m = map.remesh_and_rasterize_depth(camera);
    let render_ms = t.elapsed().as_secs_f64() * 1e3;
    let warped = warp_colour(camera, &depth_m, sources, warp);
    let guidance = Guidance {
        camera: *camera,
        frame: RgbdFrame { colour: warped.colour, depth_m },
        missing: warped.missing,
        seed,
    };
    (guidance, render_ms)
}

/// Wall time of each stage of one step, milliseconds.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize)]
pub struct StepTimings {
    /// Choosing and loading source keyframes.
    pub sources_ms: f64,
    /// Rasterizing the map at the target camera.
    pub render_ms: f64,
    /// Inverse-warping colour from the sources.
    pub warp_ms: f64,
    /// Completing the guidance (the model).
    pub refine_ms: f64,
    /// TSDF integration of the new frame.
    pub integrate_ms: f64,
    /// Re-meshing the dirty blocks.
    pub mesh_ms: f64,
    /// Writing the frame (keyframe paging + outputs).
    pub write_ms: f64,
    /// Whole step.
    pub total_ms: f64,
    /// Fraction of guidance pixels the refiner had to invent.
    pub missing_fraction: f32,
}

struct Laps(Instant, Instant);
impl Laps {
    fn start() -> Self {
        let now = Instant::now();
        Self(now, now)
    }
    fn lap(&mut self) -> f64 {
        let now = Instant::now();
        let ms = (now - self.1).as_secs_f64() * 1e3;
        self.1 = now;
        ms
    }
    fn total(&self) -> f64 {
        self.0.elapsed().as_secs_f64() * 1e3
    }
}

/// Grows a world one camera at a time. Generic over the [`Refiner`] (the learned model or a
/// stand-in).
pub struct WorldGenerator<R: Refiner> {
    /// The global map (TSDF + block meshes).
    pub map: TsdfMap,
    /// Generated frames (cameras in RAM, pixels paged to the run folder).
    pub keyframes: Keyframes,
    refiner: R,
    config: GeneratorConfig,
    /// The seed frame's ground plane once fitted (`Some(None)`: the seed shows no plane).
    ground: Option<Option<GroundPlane>>,
    /// The last step's guidance and raw refiner output, kept when [`Self::keep_guidance`] is on.
    last_guidance: Option<Option<(Guidance, RgbdFrame)>>,
}

impl<R: Refiner> std::fmt::Debug for WorldGenerator<R> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorldGenerator").field("keyframes", &self.keyframes.len()).finish_non_exhaustive()
    }
}

impl<R: Refiner> WorldGenerator<R> {
    /// A generator over an existing map and keyframe store (empty for a new run, loaded from a
    /// snapshot when resuming).
    pub fn new(map: TsdfMap, keyframes: Keyframes, refiner: R, config: GeneratorConfig) -> Self {
        Self { map, keyframes, refiner, config, ground: None, last_guidance: None }
    }

    /// Keeps each step's guidance and raw refiner output for [`Self::last_guidance`] (off by
    /// default: two frames of copies per step).
    pub fn keep_guidance(&mut self, on: bool) {
        self.last_guidance = on.then_some(None);
    }

    /// The last step's guidance and the refiner's raw completion (before the invented-pixel
    /// filters), when [`Self::keep_guidance`] is on and a step has run.
    pub fn last_guidance(&self) -> Option<&(Guidance, RgbdFrame)> {
        self.last_guidance.as_ref().and_then(Option::as_ref)
    }

    /// The seed frame's ground plane (fitted on first use from keyframe 0, which is stored
    /// losslessly, so a resumed run fits exactly the plane the uninterrupted one did).
    pub fn ground_plane(&mut self) -> Result<Option<GroundPlane>> {
        if let Some(g) = self.ground {
            return Ok(g);
        }
        if self.keyframes.is_empty() {
            return Ok(None);
        }
        let seed = self.keyframes.frame(0)?;
        let plane = fit_ground_plane(&self.keyframes.cameras()[0], &seed, &GroundFitConfig::default());
        self.ground = Some(plane);
        Ok(plane)
    }

    /// Starts the world from a seed frame: it is fused and kept like a generated one.
    pub fn seed(&mut self, camera: &Camera, mut frame: RgbdFrame) -> Result<()> {
        quantise_colour(&mut frame.colour);
        self.map.integrate(&frame, camera);
        self.map.update_mesh();
        self.keyframes.push(*camera, frame)?;
        Ok(())
    }

    /// One SGAM step at `camera`: generative sensing, then mapping.
    pub fn step(&mut self, camera: &Camera) -> Result<StepTimings> {
        let mut t = Laps::start();
        let mut timings = StepTimings::default();
        // choose sources: the k nearest generated frames within the radius
        let sources = self.choose_sources(camera)?;
        timings.sources_ms = t.lap();
        // guidance: the map rasterized at the target camera, colour inverse-warped from the sources
        let views: Vec<SourceView<'_>> = sources.iter().map(|(c, f)| SourceView { camera: c, frame: f }).collect();
        let step_index = self.keyframes.len() as u64;
        let seed = self.config.seed ^ step_index.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let (guidance, render_ms) = render_guidance(&mut self.map, camera, &views, &self.config.warp, seed);
        timings.render_ms = render_ms;
        timings.warp_ms = t.lap() - render_ms;
        timings.missing_fraction = guidance.missing_fraction();
        // complete the incomplete RGB-D image in one shot
        let mut frame = self.refiner.refine(&guidance).map_err(|e| PipelineError::Refiner(Box::new(e)))?;
        quantise_colour(&mut frame.colour);
        // the invented-pixel policy: for what the refiner invented, not for a true frame
        let invented = self.refiner.last_invented();
        if let Some(kept) = &mut self.last_guidance {
            *kept = Some((guidance.clone(), frame.clone()));
        }
        if invented && self.config.snap_flying_pixels {
            let plane = self.ground_plane()?;
            let cfg = FlyingPixelConfig::new(self.config.tsdf.depth_max_m);
            snap_flying_pixels(&mut frame, &guidance.missing, camera, plane.as_ref(), &cfg);
        }
        if invented && self.config.carve_free_space {
            let plane = self.ground_plane()?;
            // the sources and the seed frame, the one real view
            let seed = match self.keyframes.cameras().first().copied() {
                Some(c) if !sources.iter().any(|(s, _)| *s == c) => Some((c, self.keyframes.frame(0)?)),
                _ => None,
            };
            let views: Vec<(&Camera, &RgbdFrame)> =
                sources.iter().chain(seed.iter()).map(|(c, f)| (c, f.as_ref())).collect();
            let cfg = FreeSpaceConfig::new(self.config.tsdf.depth_max_m);
            carve_invented(&mut frame, &guidance.missing, camera, &views, plane.as_ref(), &cfg);
        }
        if let Some(tolerance_m) = self.config.ground_snap_m.filter(|_| invented) {
            if let Some(plane) = self.ground_plane()? {
                let cfg = GroundSnapConfig {
                    flatten_below_m: self.config.ground_flatten_m,
                    ..GroundSnapConfig::new(tolerance_m, self.config.tsdf.depth_max_m)
                };
                snap_to_ground(&mut frame, &guidance.missing, camera, &plane, &cfg);
            }
        }
        if invented && (self.config.max_object_m2 > 0.0 || self.config.max_object_length_m > 0.0) {
            if let Some(plane) = self.ground_plane()? {
                let cfg = ObjectCapConfig {
                    max_length_m: self.config.max_object_length_m,
                    ..ObjectCapConfig::new(self.config.max_object_m2)
                };
                cap_invented_objects(&mut frame, &guidance.missing, camera, &plane, &cfg);
            }
        }
        if invented && self.config.object_colour > 0.0 {
            if let Some(plane) = self.ground_plane()? {
                let cfg = ObjectColourConfig::new(self.config.object_colour);
                unify_object_colours(&mut frame, &guidance.missing, camera, &plane, &cfg);
            }
        }
        timings.refine_ms = t.lap();
        // fuse the new frame into the map, once
        self.map.integrate(&frame, camera);
        if invented && self.config.solid_max_m > 0.0 {
            if let Some(plane) = self.ground_plane()? {
                let cfg = SolidConfig::new(2.0 * self.config.tsdf.trunc_m(), self.config.solid_max_m);
                let thickness = object_thickness(&frame, &guidance.missing, camera, &plane, &cfg);
                self.map.integrate_behind(&frame, camera, &thickness, Some(&plane));
            }
        }
        timings.integrate_ms = t.lap();
        // re-mesh only the blocks the frame changed
        self.map.update_mesh();
        timings.mesh_ms = t.lap();
        // keep it as a keyframe (written to the run folder)
        self.keyframes.push(*camera, frame)?;
        timings.write_ms = t.lap();
        timings.total_ms = t.total();
        Ok(timings)
    }

    /// Source keyframes for `camera`. With `no_map`, the previous frame only, and the map is
    /// rebuilt from it alone (so the guidance carries no long-term memory).
    fn choose_sources(&mut self, camera: &Camera) -> Result<Vec<(Camera, std::sync::Arc<RgbdFrame>)>> {
        let ids = if self.config.no_map {
            self.keyframes.len().checked_sub(1).into_iter().collect()
        } else {
            self.keyframes.nearest(camera, self.config.k_sources, self.config.source_radius_m)
        };
        let mut out = Vec::with_capacity(ids.len());
        for i in ids {
            out.push((self.keyframes.cameras()[i], self.keyframes.frame(i)?));
        }
        if self.config.no_map {
            self.map = TsdfMap::new(self.config.tsdf);
            if let Some((c, f)) = out.first() {
                self.map.integrate(f, c);
            }
        }
        Ok(out)
    }
}
