//! Training pairs from the synthetic world, built with the same render + warp path that
//! generation uses (so stage 2 trains on exactly the kind of guidance it will see).
//!
//! - Stage 1: a clean random crop of a synthetic view (input = target, nothing missing).
//! - Stage 2: a target crop, plus a map fused from neighbouring views *behind* it on the
//!   generation grid (offsets of 0.408 m within 1 m whose zig-zag diagonal precedes the target's,
//!   as the authors' trajectory sees them); the guidance is `map.render` at the target crop,
//!   coloured by `warp_colour` from the nearest 5 of those views; the target is the ground truth.
//!
//! A crop is rendered directly by shifting the principal point (a `crop x crop` camera whose
//! pixels are exactly the crop of the full `res x res` view), which is 4-16x cheaper than
//! rendering the whole view.

use std::sync::Arc;

use rand::seq::SliceRandom;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use sgam_core::{Camera, Intrinsics, RgbdFrame, Vec3};
use sgam_map::{SourceView, TsdfMap};
use sgam_model::{PairSource, Stage, TrainPair};
use sgam_synth::{blender_camera, dataset_intrinsics, RenderConfig, Renderer, Scene, SceneConfig};

/// Synthetic pair source for either stage.
#[derive(Debug)]
pub struct SynthPairs {
    stage: Stage,
    scene_seeds: Vec<u64>,
    res: u32,
    render: RenderConfig,
    cache: Vec<(u64, Arc<Renderer>)>,
    cache_size: usize,
    step_m: f32,
    source_radius_m: f32,
    k_sources: usize,
    wide_holes: f64,
}

impl SynthPairs {
    /// Pairs from scenes `scene_seeds` at full resolution `res` (crops are taken from it).
    pub fn new(stage: Stage, scene_seeds: Vec<u64>, res: u32) -> Self {
        Self {
            stage,
            scene_seeds,
            res,
            render: RenderConfig::default(),
            cache: Vec::new(),
            cache_size: 4,
            step_m: 0.408,
            source_radius_m: 1.0,
            k_sources: 5,
            wide_holes: 0.0,
        }
    }

    /// With probability `p`, a stage-2 pair's map comes from one or two views 1-3 grid steps
    /// away in a random direction instead of the neighbours behind the target: large holes,
    /// like those at the zig-zag's turns, which the neighbours behind never leave.
    pub fn with_wide_holes(mut self, p: f64) -> Self {
        self.wide_holes = p.clamp(0.0, 1.0);
        self
    }

    fn renderer(&mut self, seed: u64) -> Arc<Renderer> {
        if let Some(pos) = self.cache.iter().position(|(s, _)| *s == seed) {
            let entry = self.cache.remove(pos);
            let r = entry.1.clone();
            self.cache.push(entry);
            return r;
        }
        let r = Arc::new(Renderer::new(&Scene::generate(seed, &SceneConfig::default())));
        self.cache.push((seed, r.clone()));
        if self.cache.len() > self.cache_size {
            self.cache.remove(0);
        }
        r
    }

    /// One pair: target crop (and, for stage 2, its guidance).
    pub fn pair(&mut self, crop: u32, rng: &mut ChaCha8Rng) -> TrainPair {
        self.sample(crop, rng).1
    }

    /// One pair and the (crop) camera it was rendered at.
    pub fn sample(&mut self, crop: u32, rng: &mut ChaCha8Rng) -> (Camera, TrainPair) {
        let seed = self.scene_seeds[rng.random_range(0..self.scene_seeds.len())];
        let renderer = self.renderer(seed);
        let full = dataset_intrinsics(self.res);
        let centre = Vec3::new(rng.random_range(-20.0..20.0), rng.random_range(-20.0..20.0), 0.0);
        let target = blender_camera(centre, sgam_synth::CAMERA_PITCH_RAD, 0.0, full);
        let crop = crop.min(self.res);
        let (u0, v0) = (rng.random_range(0..=self.res - crop), rng.random_range(0..=self.res - crop));
        let crop_k = Intrinsics { width: crop, height: crop, cx: full.cx - u0 as f32, cy: full.cy - v0 as f32, ..full };
        let crop_cam = Camera::new(crop_k, target.world_from_camera);
        let truth = renderer.render(&crop_cam, &self.render).frame;
        if self.stage == Stage::One {
            let n = truth.depth_m.len();
            return (crop_cam, TrainPair { input: truth.clone(), missing: vec![false; n], target: truth });
        }
        // views behind the target on the zig-zag grid, within the source radius
        let mut offsets: Vec<(i32, i32)> = Vec::new();
        for di in -2i32..=2 {
            for dj in -2i32..=2 {
                let d = self.step_m * ((di * di + dj * dj) as f32).sqrt();
                if di + dj < 0 && d <= self.source_radius_m {
                    offsets.push((di, dj));
                }
            }
        }
        offsets.shuffle(rng);
        let keep = rng.random_range(2..=offsets.len());
        offsets.truncate(keep);
        if self.wide_holes > 0.0 && rng.random_bool(self.wide_holes) {
            let dirs = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)];
            let (a, b) = dirs[rng.random_range(0..dirs.len())];
            let k = rng.random_range(1..=3);
            offsets = vec![(a * k, b * k)];
            if rng.random_bool(0.5) {
                offsets.push((a * (k + 1), b * (k + 1)));
            }
        }
        offsets.sort_by_key(|(di, dj)| di * di + dj * dj);
        let config = crate::clevr_generator_config(0);
        let mut map = TsdfMap::new(config.tsdf);
        let views: Vec<(Camera, RgbdFrame)> = offsets
            .iter()
            .map(|(di, dj)| {
                let c = centre + Vec3::new(*di as f32 * self.step_m, *dj as f32 * self.step_m, 0.0);
                let cam = blender_camera(c, sgam_synth::CAMERA_PITCH_RAD, 0.0, full);
                let f = renderer.render(&cam, &self.render).frame;
                (cam, f)
            })
            .collect();
        for (cam, f) in &views {
            map.integrate(f, cam);
        }
        map.update_mesh();
        let sources: Vec<SourceView<'_>> =
            views.iter().take(self.k_sources).map(|(c, f)| SourceView { camera: c, frame: f }).collect();
        let (guidance, _) = crate::render_guidance(&mut map, &crop_cam, &sources, &config.warp, 0);
        let mut input = guidance.frame;
        for (i, m) in guidance.missing.iter().enumerate() {
            if *m {
                input.depth_m.data[i] = 0.0;
                input.colour.data[i] = [0.0; 3];
            }
        }
        (crop_cam, TrainPair { input, missing: guidance.missing, target: truth })
    }
}

impl PairSource for SynthPairs {
    type Error = std::convert::Infallible;

    fn next_batch(&mut self, batch: usize, crop: u32, rng: &mut ChaCha8Rng) -> Result<Vec<TrainPair>, Self::Error> {
        Ok((0..batch).map(|_| self.pair(crop, rng)).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// Missing share of `n` stage-2 pairs drawn with wide holes at probability `p`, from scenes
    /// 3 and 4 as generated, or (`flat`) with their objects removed.
    fn missing_shares(p: f64, flat: bool, n: usize) -> Vec<f64> {
        let mut pairs = SynthPairs::new(Stage::Two, vec![3, 4], 64).with_wide_holes(p);
        if flat {
            let config = SceneConfig { object_count: 0, ..SceneConfig::default() };
            pairs.cache = [3, 4].map(|s| (s, Arc::new(Renderer::new(&Scene::generate(s, &config))))).to_vec();
        }
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        (0..n)
            .map(|_| {
                let pair = pairs.pair(64, &mut rng);
                pair.missing.iter().filter(|m| **m).count() as f64 / pair.missing.len() as f64
            })
            .collect()
    }

    fn mean(v: &[f64]) -> f64 {
        v.iter().sum::<f64>() / v.len() as f64
    }

    /// Share of the target view (full 64-pixel view at the origin) that no source at `offsets`
    /// (grid steps) sees, on a flat ground without objects: all cameras share one orientation,
    /// so a pixel's ground point is seen from offset `s` when the point moved by `-s` projects
    /// inside the image within the map's depth range.
    fn flat_unseen(offsets: &[(i32, i32)]) -> f64 {
        let step_m = 0.408;
        let range = crate::clevr_generator_config(0).tsdf;
        let cam = blender_camera(Vec3::ZERO, sgam_synth::CAMERA_PITCH_RAD, 0.0, dataset_intrinsics(64));
        let from_world = cam.world_from_camera.inverse();
        let k = cam.intrinsics;
        let mut unseen = 0usize;
        for v in 0..k.height {
            for u in 0..k.width {
                let d = cam.world_from_camera.rotation * k.ray_z1(sgam_core::Vec2::new(u as f32, v as f32));
                let t = (sgam_synth::GROUND_Z_M - cam.centre_world().z) / d.z;
                let ground = cam.centre_world() + d * t;
                let seen = offsets.iter().any(|(di, dj)| {
                    let q = ground - Vec3::new(*di as f32 * step_m, *dj as f32 * step_m, 0.0);
                    cam.project_world(&from_world, q)
                        .is_some_and(|(uv, z)| k.contains(uv) && (range.depth_min_m..=range.depth_max_m).contains(&z))
                });
                unseen += usize::from(!seen);
            }
        }
        unseen as f64 / (k.width * k.height) as f64
    }

    #[test]
    fn wide_holes_leave_more_of_the_target_missing() {
        // Expected: the flat-ground share no source sees, averaged over the source sets each
        // mode draws. Wide holes: 8 directions x 1-3 steps x one or two views, equally likely
        // (48 sets, enumerated). Neighbours behind: a random subset (2 or more) of the offsets
        // behind the target within 1 m (2000 draws).
        let dirs = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)];
        let mut wide_sets = Vec::new();
        for (a, b) in dirs {
            for k in 1..=3 {
                wide_sets.push(vec![(a * k, b * k)]);
                wide_sets.push(vec![(a * k, b * k), (a * (k + 1), b * (k + 1))]);
            }
        }
        let behind: Vec<(i32, i32)> = (-2i32..=2)
            .flat_map(|i| (-2i32..=2).map(move |j| (i, j)))
            .filter(|(i, j)| i + j < 0 && 0.408 * ((i * i + j * j) as f32).sqrt() <= 1.0)
            .collect();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let narrow_sets: Vec<Vec<(i32, i32)>> = (0..2000)
            .map(|_| {
                let mut o = behind.clone();
                o.shuffle(&mut rng);
                o.truncate(rng.random_range(2..=behind.len()));
                o
            })
            .collect();
        let sd = |v: &[f64]| (v.iter().map(|x| (x - mean(v)).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt();
        let n = 48;
        for (p, sets, name) in [(0.0, &narrow_sets, "neighbours behind"), (1.0, &wide_sets, "wide holes")] {
            let per_set: Vec<f64> = sets.iter().map(|o| flat_unseen(o)).collect();
            let expected = mean(&per_set);
            // On the scenes with their objects removed the measured hole is the flat-ground one:
            // within 3 standard errors of drawing n source sets, plus 0.005 for the fused
            // surface's edges (measured: -0.002 behind, -0.003 wide).
            let flat = mean(&missing_shares(p, true, n));
            let tolerance = 3.0 * sd(&per_set) / (n as f64).sqrt() + 0.005;
            eprintln!("{name}: missing {flat:.4} on flat ground, expected {expected:.4} +- {tolerance:.4}");
            assert!((flat - expected).abs() <= tolerance, "{name}: missing {flat:.4}, expected {expected:.4}");
        }
        // on the scenes as generated (objects add disocclusions to both) the wide holes stay
        // the larger
        let (narrow, wide) = (mean(&missing_shares(0.0, false, 12)), mean(&missing_shares(1.0, false, 12)));
        eprintln!("mean missing fraction with objects: neighbours behind {narrow:.3}, wide holes {wide:.3}");
        assert!(wide > 2.0 * narrow && wide > 0.05, "missing fraction {narrow:.3} -> {wide:.3}");
    }
}
