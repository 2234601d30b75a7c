//! Round trips of a seed (cyclic virtual cameras, as InfiniteNature-Zero learns from single
//! images): the seed is fused into a map and rendered at a virtual camera `via` on the run's
//! planned path; that view, only what the seed gave it, is fused into a fresh map and rendered
//! back at the seed's camera. What the trip lost (the seed's surfaces `via` did not see:
//! disocclusions behind relief, the part of the frame `via` left behind) is missing in the
//! guidance it returns, and the seed itself is the truth there. So a seed without a true world
//! still gives completion problems with real holes, made by the very renderer generation uses
//! ([`render_guidance`]): to score a refiner on ([`evaluate`], `sgam eval seed`) and to adapt
//! one on (`--adapt`, [`crate::adapt`]).

use std::path::Path;

use sgam_core::{is_valid_depth, Camera, Guidance, Image, Refiner, RgbdFrame};
use sgam_map::{SourceView, TsdfMap};

use crate::{build_refiner, render_guidance, GeneratorConfig, NullRefiner, PipelineError, Result, RunConfig, Seed};
use crate::{RefinerSpec, TrajectorySpec};

/// A round trip's share of the seed's pixels (with depth) that must be missing for it to be a
/// completion problem: fewer is no hole, more leaves too little to continue.
pub const HOLE_SHARE: std::ops::RangeInclusive<f64> = 0.03..=0.5;

/// Below this share of a trip's holes filled, [`TripScore::filled_psnr_db`] is not given (a few
/// pixels say nothing).
pub const MIN_FILLED_SHARE: f64 = 0.05;

/// Steps of the planned path tried as the virtual camera, nearest first (spread so the trips
/// differ; a path shorter than a step leaves it out).
const VIA_STEPS: [usize; 12] = [2, 4, 6, 9, 12, 16, 20, 25, 30, 40, 50, 60];

/// One round trip: the virtual camera and the seed's view brought back through it.
#[derive(Debug, Clone)]
pub struct RoundTrip {
    /// The step of the planned path the trip went to.
    pub via_step: usize,
    /// The virtual camera.
    pub via: Camera,
    /// At the seed's camera: what came back, missing where the trip lost the seed.
    pub guidance: Guidance,
}

impl RoundTrip {
    /// The holes the seed can judge: missing after the trip, with the seed's depth there.
    pub fn judged(&self, seed: &RgbdFrame) -> Vec<bool> {
        self.guidance.missing.iter().zip(&seed.depth_m.data).map(|(m, d)| *m && is_valid_depth(*d)).collect()
    }

    /// Share of the seed's pixels with depth that the trip lost.
    pub fn hole_share(&self, seed: &RgbdFrame) -> f64 {
        let with_depth = seed.depth_m.data.iter().filter(|d| is_valid_depth(**d)).count();
        self.judged(seed).iter().filter(|j| **j).count() as f64 / with_depth.max(1) as f64
    }

    /// The seed without what the trip lost: no depth and black there (what a bank built from
    /// it may take, [`crate::bank::seed_bank`], so the holes' own pixels are not in it).
    pub fn seed_with_holes(&self, seed: &RgbdFrame) -> RgbdFrame {
        let mut f = seed.clone();
        for (i, m) in self.guidance.missing.iter().enumerate() {
            if *m {
                f.depth_m.data[i] = 0.0;
                f.colour.data[i] = [0.0; 3];
            }
        }
        f
    }
}

/// The seed `frame` at `camera`, out to `via` and back, with the map and warp of `g`.
pub fn round_trip(camera: &Camera, frame: &RgbdFrame, via: &Camera, g: &GeneratorConfig, seed: u64) -> Guidance {
    let mut out = TsdfMap::new(g.tsdf);
    out.integrate(frame, camera);
    let (there, _) = render_guidance(&mut out, via, &[SourceView { camera, frame }], &g.warp, seed);
    drop(out);
    // only what the seed gave the virtual view goes back
    let mut seen = there.frame;
    for (i, m) in there.missing.iter().enumerate() {
        if *m {
            seen.depth_m.data[i] = 0.0;
        }
    }
    let mut back = TsdfMap::new(g.tsdf);
    back.integrate(&seen, via);
    let (guidance, _) = render_guidance(&mut back, camera, &[SourceView { camera: via, frame: &seen }], &g.warp, seed);
    guidance
}

/// Up to `count` round trips of the seed `frame` at `camera` through cameras of the path
/// `trajectory` (a greedy run's zig-zag grid), each losing a share of the seed within
/// [`HOLE_SHARE`]; the nearest steps first, among the first `steps`.
pub fn round_trips(
    camera: &Camera,
    frame: &RgbdFrame,
    trajectory: &TrajectorySpec,
    steps: usize,
    g: &GeneratorConfig,
    count: usize,
) -> Result<Vec<RoundTrip>> {
    let path = match *trajectory {
        TrajectorySpec::Greedy { side, step_m } => TrajectorySpec::Zigzag { side, step_m },
        ref t => t.clone(),
    };
    let last = VIA_STEPS.iter().copied().filter(|s| *s <= steps.max(1)).max().unwrap_or(1);
    let cameras = path.cameras(camera, last)?;
    let mut trips = Vec::new();
    for &k in VIA_STEPS.iter().filter(|k| **k < cameras.len()) {
        if trips.len() >= count {
            break;
        }
        let via = cameras[k];
        let guidance = round_trip(camera, frame, &via, g, g.seed ^ k as u64);
        let trip = RoundTrip { via_step: k, via, guidance };
        if HOLE_SHARE.contains(&trip.hole_share(frame)) {
            trips.push(trip);
        }
    }
    Ok(trips)
}

/// How well a completion of a round trip gives the seed back, on the trip's holes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TripScore {
    /// Colour PSNR on the holes, dB (8-bit scale).
    pub psnr_db: f64,
    /// Mean absolute colour error on the holes (of `[0, 1]`).
    pub colour_l1: f64,
    /// Mean `|d - d_seed| / d_seed` on the holes where the completion has a depth.
    pub depth_abs_rel: Option<f64>,
    /// Share of the holes the completion left without depth.
    pub no_depth_share: f64,
    /// Colour PSNR on the holes the completion gave a depth (what it did fill), dB; `None` when
    /// it filled less than [`MIN_FILLED_SHARE`] of them.
    pub filled_psnr_db: Option<f64>,
}

/// Scores `completed` against the seed `frame` on the holes of `trip`; `None` when it has none.
pub fn score(trip: &RoundTrip, frame: &RgbdFrame, completed: &RgbdFrame) -> Option<TripScore> {
    let holes = trip.judged(frame);
    let n = holes.iter().filter(|h| **h).count();
    let psnr_db = sgam_metrics::psnr(&completed.colour, &frame.colour, Some(&holes))?;
    let (mut l1, mut rel, mut with_depth) = (0.0f64, 0.0f64, 0usize);
    for (i, _) in holes.iter().enumerate().filter(|(_, h)| **h) {
        let (a, b) = (completed.colour.data[i], frame.colour.data[i]);
        l1 += (0..3).map(|c| f64::from((a[c] - b[c]).abs())).sum::<f64>() / 3.0;
        let (d, t) = (completed.depth_m.data[i], frame.depth_m.data[i]);
        if is_valid_depth(d) {
            rel += f64::from((d - t).abs() / t);
            with_depth += 1;
        }
    }
    let filled: Vec<bool> = holes.iter().zip(&completed.depth_m.data).map(|(h, d)| *h && is_valid_depth(*d)).collect();
    Some(TripScore {
        filled_psnr_db: (with_depth as f64 >= MIN_FILLED_SHARE * n as f64)
            .then(|| sgam_metrics::psnr(&completed.colour, &frame.colour, Some(&filled)))
            .flatten(),
        psnr_db,
        colour_l1: l1 / n as f64,
        depth_abs_rel: (with_depth > 0).then(|| rel / with_depth as f64),
        no_depth_share: 1.0 - with_depth as f64 / n as f64,
    })
}

/// One trip of [`evaluate`]: its virtual camera's step, the share lost, and the scores of the
/// run's refiner and of push-pull filling ([`NullRefiner`]) on it.
#[derive(Debug, Clone, PartialEq)]
pub struct TripResult {
    /// [`RoundTrip::via_step`].
    pub via_step: usize,
    /// [`RoundTrip::hole_share`].
    pub hole_share: f64,
    /// The run's refiner.
    pub refiner: TripScore,
    /// Push-pull filling, the reference without a model.
    pub push_pull: TripScore,
    /// The trip's colour as it came back (black where lost), the refiner's completion and
    /// push-pull's, for a picture.
    pub colours: [Image<[f32; 3]>; 3],
}

/// Round trips of a run's seed scored with the run's own refiner (`config`, the run folder
/// `dir` for adapted weights): the seed's first frame and camera, its path and map settings.
/// A bank built from the seed (`--bank seed`) is built from the seed without each trip's holes
/// ([`RoundTrip::seed_with_holes`]), so the holes' true pixels are not in it. An adapted model (`--adapt`) was tuned on the whole seed,
/// holes included: its score is an upper bound, and [`RoundTripReport::adapted_saw_holes`] says
/// so.
pub fn evaluate(
    dir: &Path,
    config: &RunConfig,
    camera: &Camera,
    seed: &RgbdFrame,
    count: usize,
) -> Result<RoundTripReport> {
    let g = config.generator_config();
    let trips = round_trips(camera, seed, &config.trajectory, config.steps, &g, count)?;
    let spec = crate::adapt::adapted_spec(dir, &config.refiner);
    let mut results = Vec::new();
    for trip in &trips {
        let as_seed =
            Seed { camera: *camera, frame: trip.seed_with_holes(seed), renderer: None, name: "round trip".into() };
        let mut refiner = build_refiner(&spec, &as_seed)?;
        let completed = refiner.refine(&trip.guidance).map_err(|e| PipelineError::Refiner(Box::new(e)))?;
        let Ok(pushed) = NullRefiner { fill: true }.refine(&trip.guidance);
        if let (Some(r), Some(p)) = (score(trip, seed, &completed), score(trip, seed, &pushed)) {
            results.push(TripResult {
                via_step: trip.via_step,
                hole_share: trip.hole_share(seed),
                refiner: r,
                push_pull: p,
                colours: [trip.guidance.frame.colour.clone(), completed.colour, pushed.colour],
            });
        }
    }
    Ok(RoundTripReport {
        trips: results,
        adapted_saw_holes: matches!(config.refiner, RefinerSpec::Model { adapt_s, .. } if adapt_s > 0.0),
        bank_without_holes: matches!(&config.refiner, RefinerSpec::Model { bank: crate::BankSpec::Seed, .. }),
    })
}

/// What [`evaluate`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct RoundTripReport {
    /// One per trip scored.
    pub trips: Vec<TripResult>,
    /// The run's model was adapted on the whole seed, the trips' holes included.
    pub adapted_saw_holes: bool,
    /// The run quilts holes from the seed (`--bank seed`), and here from the seed without the
    /// trip's holes: a hole whose every match would take lost cells stays partly empty
    /// ([`TripScore::no_depth_share`]), where in the run the bank holds the whole seed.
    pub bank_without_holes: bool,
}

impl RoundTripReport {
    /// Median over the trips of `f` (`None` without trips or values).
    pub fn median(&self, f: impl Fn(&TripResult) -> Option<f64>) -> Option<f64> {
        let mut v: Vec<f64> = self.trips.iter().filter_map(f).collect();
        v.sort_by(f64::total_cmp);
        (!v.is_empty()).then(|| v[v.len() / 2])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sgam_core::{Intrinsics, Rigid3};

    /// A floor 2 m below a camera looking straight down, with a box 0.6 m high in the middle:
    /// moving sideways disoccludes floor behind the box's side.
    fn scene() -> (Camera, RgbdFrame) {
        let (w, h) = (96u32, 96u32);
        let k = Intrinsics::try_new(w, h, 80.0, 80.0, 47.5, 47.5).unwrap();
        let camera = Camera::new(k, Rigid3::IDENTITY);
        let mut depth = Vec::new();
        let mut colour = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let in_box = (36..60).contains(&x) && (36..60).contains(&y);
                depth.push(if in_box { 1.4 } else { 2.0 });
                let checker = ((x / 8 + y / 8) % 2) as f32;
                colour.push(if in_box { [0.9, 0.2, 0.1] } else { [0.2 + 0.5 * checker, 0.6, 0.3] });
            }
        }
        let frame = RgbdFrame {
            colour: Image::try_from_vec(w, h, colour).unwrap(),
            depth_m: Image::try_from_vec(w, h, depth).unwrap(),
        };
        (camera, frame)
    }

    fn config() -> GeneratorConfig {
        let mut g = crate::clevr_generator_config(7);
        g.tsdf.voxel_size_m = 0.02;
        g.tsdf.trunc_voxels = 3.0;
        g
    }

    #[test]
    fn a_round_trip_loses_what_the_virtual_camera_did_not_see_and_keeps_the_rest() {
        let (camera, frame) = scene();
        let g = config();
        // the same camera: nothing is lost but the map's own edge
        let still = round_trip(&camera, &frame, &camera, &g, 1);
        let still_trip = RoundTrip { via_step: 0, via: camera, guidance: still };
        let still_share = still_trip.hole_share(&frame);
        assert!(still_share < 0.1, "{still_share}");
        // 0.3 m sideways: the frame's far side leaves the view and floor behind the box is disoccluded
        let mut pose = Rigid3::IDENTITY;
        pose.translation.x = 0.3;
        let via = Camera::new(camera.intrinsics, pose);
        let trip = RoundTrip { via_step: 1, via, guidance: round_trip(&camera, &frame, &via, &g, 1) };
        let share = trip.hole_share(&frame);
        assert!(HOLE_SHARE.contains(&share) && share > still_share + 0.05, "{share} vs {still_share}");
        // what came back is the seed: colour within a few levels, depth within a voxel
        let kept: Vec<bool> = trip.guidance.missing.iter().map(|m| !m).collect();
        let psnr = sgam_metrics::psnr(&trip.guidance.frame.colour, &frame.colour, Some(&kept)).unwrap();
        assert!(psnr > 20.0, "{psnr}");
        let near = (0..kept.len())
            .filter(|&i| kept[i] && (trip.guidance.frame.depth_m.data[i] - frame.depth_m.data[i]).abs() < 0.05)
            .count();
        let n_kept = kept.iter().filter(|k| **k).count();
        assert!(near as f64 >= 0.95 * n_kept as f64, "{near} of {n_kept} within 5 cm");
        // the floor beside the box, on the side the camera moved away from, is a hole: the box
        // hid it from `via` (columns just left of the box, rows through it)
        let w = frame.width() as usize;
        let hidden = (40..56).filter(|y| (30..36).any(|x| trip.guidance.missing[y * w + x])).count();
        assert!(hidden > 8, "{hidden} rows of the box's shadow missing");
        // and the holes are scored against the seed: the seed itself scores perfectly
        let s = score(&trip, &frame, &frame).unwrap();
        assert_eq!(s.psnr_db, f64::INFINITY);
        assert_eq!(s.depth_abs_rel, Some(0.0));
        assert_eq!((s.no_depth_share, s.filled_psnr_db), (0.0, Some(f64::INFINITY)));
        // what came back, holes left as they are: nothing filled, and scored as such
        let unfilled = score(&trip, &frame, &trip.seed_with_holes(&frame)).unwrap();
        assert_eq!((unfilled.no_depth_share, unfilled.filled_psnr_db, unfilled.depth_abs_rel), (1.0, None, None));
        // black against the floor's and the box's colours
        assert!(unfilled.psnr_db < 15.0, "{}", unfilled.psnr_db);
        let Ok(pushed) = NullRefiner { fill: true }.refine(&trip.guidance);
        let p = score(&trip, &frame, &pushed).unwrap();
        assert!(p.psnr_db.is_finite() && p.colour_l1 > 0.0);
    }

    #[test]
    fn round_trips_follow_the_planned_path_and_keep_only_real_holes() {
        let (camera, frame) = scene();
        let g = config();
        let trips = round_trips(&camera, &frame, &TrajectorySpec::Line { step_m: 0.05 }, 30, &g, 3).unwrap();
        assert!(!trips.is_empty());
        assert!(trips.len() <= 3);
        for t in &trips {
            assert!(HOLE_SHARE.contains(&t.hole_share(&frame)));
            assert!(t.via_step <= 30);
            // the seed without the trip's holes has no depth there
            let f = t.seed_with_holes(&frame);
            assert!(t.guidance.missing.iter().zip(&f.depth_m.data).all(|(m, d)| !m || *d == 0.0));
        }
        let steps: Vec<usize> = trips.iter().map(|t| t.via_step).collect();
        assert!(steps.windows(2).all(|w| w[0] < w[1]), "{steps:?}");
    }
}
