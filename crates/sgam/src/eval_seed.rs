//! `sgam eval seed RUN`: no-reference checks of a world grown from a real seed (a Google Earth
//! view, a user's RGB-D frame), which has no true world to compare with. What the run invented
//! is judged against the seed itself ([`sgam_metrics::noref`]): the new area's look (KID of its
//! patches against the seed's), geometry floating outside the seed's heights, and how much of
//! each frame is new. Round trips of the seed ([`sgam_pipeline::roundtrip`]) give the one
//! reference a single frame has: holes made by the run's own path whose truth is the seed.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;
use sgam_core::ground::{fit_ground_plane, GroundFitConfig};
use sgam_metrics::noref::{patch_features, unseen_by_seed, HeightRange, Standardise};

/// Arguments of `sgam eval seed`.
#[derive(Debug, Args)]
#[command(after_help = "Examples:\n  \
    sgam generate --seed-google-earth ../shared/data/sgam-google-earth-seeds/seed0 --steps 200 --out runs/ge0\n  \
    sgam eval seed runs/ge0\n  \
    sgam generate --seed-google-earth ../shared/data/sgam-google-earth-seeds/seed0 --steps 200 --bank seed --out runs/ge0-bank\n  \
    sgam eval seed runs/ge0-bank --json\n\n\
    Lower kid_seed_vs_new is a new area in the seed's palette and textures; floating_share counts new \
    points above the seed's highest or below its lowest (widened by a tenth of the seed's median depth). \
    The round trips take the seed out to cameras of the run's path and back: what those cameras did not \
    see comes back as holes whose truth is the seed, and the run's refiner completes them beside push-pull \
    filling (higher PSNR, lower depth abs-rel is closer to the seed).")]
pub struct SeedArgs {
    /// A run folder (`sgam generate --out`), finished or stopped: its first frame is the seed.
    pub run: PathBuf,
    /// Judge every Nth frame after the seed.
    #[arg(long, default_value_t = 5)]
    pub stride: usize,
    /// A point is new when it lies more than this share of its depth behind what the seed saw
    /// there (or outside the seed's view).
    #[arg(long, default_value_t = 0.05)]
    pub behind: f32,
    /// Round trips of the seed to score the run's refiner on: the seed out to a camera of the
    /// run's path and back, so the holes are the seed's own pixels that camera did not see; 0 =
    /// none.
    #[arg(long, default_value_t = 4)]
    pub round_trips: usize,
    /// Write a picture of each round trip here: what came back (black where lost), the run's
    /// refiner's completion, push-pull filling, and the seed.
    #[arg(long, value_name = "DIR")]
    pub round_trip_images: Option<PathBuf>,
    /// Print only the JSON line.
    #[arg(long)]
    pub json: bool,
}

/// At most this many new-area patches enter KID (evenly spaced over the run's).
const MAX_NEW_PATCHES: usize = 4000;

/// Judges the run of `a`; returns the JSON result.
pub fn evaluate(a: &SeedArgs) -> Result<serde_json::Value> {
    if a.stride == 0 {
        bail!("--stride 0: give 1 or more (every Nth frame is judged)");
    }
    if !(a.behind.is_finite() && a.behind > 0.0 && a.behind < 1.0) {
        bail!("--behind {}: give a share of the depth between 0 and 1 (e.g. 0.05)", a.behind);
    }
    let seq = sgam_io::Sequence::open(&a.run)
        .with_context(|| format!("{}: not a run folder with frames (sgam generate --out)", a.run.display()))?;
    if seq.len() < 2 {
        bail!("{}: holds only the seed frame; nothing was grown after it", a.run.display());
    }
    let seed_camera = seq.camera(0);
    let seed = seq.read_frame(0)?;
    let mut depths: Vec<f32> = seed.depth_m.data.iter().copied().filter(|d| sgam_core::is_valid_depth(*d)).collect();
    if depths.is_empty() {
        bail!("{}: the seed frame has no valid depth", a.run.display());
    }
    depths.sort_by(f32::total_cmp);
    let median_depth = depths[depths.len() / 2];
    // the seed's scale sets the tolerances: 1 % of its median depth (10 cm for CLEVR's 10 m,
    // where trees and roofs of an aerial view leave the ground a fifth of the points)
    let fit = GroundFitConfig { inlier_m: 0.01 * median_depth, min_inlier_fraction: 0.1, ..GroundFitConfig::default() };
    let plane = fit_ground_plane(&seed_camera, &seed, &fit);
    let range = plane.as_ref().and_then(|p| HeightRange::of_seed(&seed_camera, &seed, p, 0.1 * median_depth));
    let seed_patches = patch_features(&seed, |_| true);
    let standardise = Standardise::new(&seed_patches);
    let mut new_patches = Vec::new();
    let mut new_share = Vec::new();
    let (mut floating, mut judged_points) = (0usize, 0usize);
    let judged: Vec<usize> = (1..seq.len()).step_by(a.stride).collect();
    for &i in &judged {
        let camera = seq.camera(i);
        let frame = seq.read_frame(i)?;
        let new = unseen_by_seed(&seed_camera, &seed, &camera, &frame, a.behind);
        let with_depth = frame.depth_m.data.iter().filter(|d| sgam_core::is_valid_depth(**d)).count();
        new_share.push(new.iter().filter(|n| **n).count() as f64 / with_depth.max(1) as f64);
        new_patches.extend(patch_features(&frame, |p| new[p]));
        if let (Some(p), Some(r)) = (&plane, &range) {
            let (o, n) = r.outside(&camera, &frame, p, |q| new[q]);
            floating += o;
            judged_points += n;
        }
    }
    let kept: Vec<Vec<f32>> = if new_patches.len() > MAX_NEW_PATCHES {
        (0..MAX_NEW_PATCHES).map(|k| new_patches[k * new_patches.len() / MAX_NEW_PATCHES].clone()).collect()
    } else {
        new_patches.clone()
    };
    let z = |s: &[Vec<f32>]| s.iter().map(|v| standardise.apply(v)).collect::<Vec<_>>();
    let kid = sgam_metrics::kid::kid(&z(&seed_patches), &z(&kept));
    let run_json = read_json(&a.run.join("run.json"));
    let trips = if a.round_trips > 0 {
        let config = sgam_pipeline::snapshot::read_run_config(&a.run)?;
        let report = sgam_pipeline::roundtrip::evaluate(&a.run, &config, &seed_camera, &seed, a.round_trips)?;
        if let Some(dir) = &a.round_trip_images {
            write_trip_images(dir, &report, &seed.colour)?;
        }
        Some(report)
    } else {
        None
    };
    let grows = new_share.windows(2).filter(|w| w[1] + 0.01 >= w[0]).count();
    Ok(json!({
        "run": a.run.display().to_string(),
        "frames": seq.len(),
        "judged_frames": judged.len(),
        "stride": a.stride,
        "seed_median_depth": median_depth,
        "ground_plane_found": plane.is_some(),
        "seed_height_range": range.map(|r| [r.lo, r.hi]),
        "seed_patches": seed_patches.len(),
        "new_patches": new_patches.len(),
        "kid_seed_vs_new": kid,
        "floating_share": if judged_points > 0 { Some(floating as f64 / judged_points as f64) } else { None },
        "new_area_share": new_share,
        "new_area_share_last": new_share.last(),
        "new_area_steps_not_shrinking": format!("{grows}/{}", new_share.len().saturating_sub(1)),
        "median_missing_fraction": run_json.as_ref().and_then(|v| v["median_missing_fraction"].as_f64()),
        "step_ms_median": run_json.as_ref().and_then(|v| v["median_ms"]["total"].as_f64()),
        "round_trip": trips.as_ref().map(round_trip_json),
    }))
}

/// The round trips' medians (the run's refiner beside push-pull filling) and each trip.
fn round_trip_json(r: &sgam_pipeline::roundtrip::RoundTripReport) -> serde_json::Value {
    use sgam_pipeline::roundtrip::TripScore;
    let score = |s: &TripScore| {
        json!({"psnr_db": s.psnr_db, "colour_l1": s.colour_l1, "depth_abs_rel": s.depth_abs_rel,
               "no_depth_share": s.no_depth_share, "filled_psnr_db": s.filled_psnr_db})
    };
    let pick = |f: fn(&TripScore) -> Option<f64>| json!({"refiner": r.median(|t| f(&t.refiner)), "push_pull": r.median(|t| f(&t.push_pull))});
    json!({
        "trips": r.trips.len(),
        "adapted_saw_holes": r.adapted_saw_holes,
        "bank_without_holes": r.bank_without_holes,
        "filled_share": r.median(|t| Some(1.0 - t.refiner.no_depth_share)),
        "median_hole_share": r.median(|t| Some(t.hole_share)),
        "psnr_db": pick(|s| Some(s.psnr_db)),
        "colour_l1": pick(|s| Some(s.colour_l1)),
        "depth_abs_rel": pick(|s| s.depth_abs_rel),
        "filled_psnr_db": pick(|s| s.filled_psnr_db),
        "each": r.trips.iter().map(|t| json!({
            "via_step": t.via_step,
            "hole_share": t.hole_share,
            "refiner": score(&t.refiner),
            "push_pull": score(&t.push_pull),
        })).collect::<Vec<_>>(),
    })
}

/// One picture per trip in `dir`: what came back, the refiner's, push-pull's, the seed.
fn write_trip_images(
    dir: &Path,
    r: &sgam_pipeline::roundtrip::RoundTripReport,
    seed: &sgam_core::Image<[f32; 3]>,
) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create the folder", dir.display()))?;
    let (w, h) = (seed.width as usize, seed.height as usize);
    for t in &r.trips {
        let panels = [&t.colours[0], &t.colours[1], &t.colours[2], seed];
        let mut data = Vec::with_capacity(4 * w * h);
        for y in 0..h {
            for p in panels {
                data.extend_from_slice(&p.data[y * w..(y + 1) * w]);
            }
        }
        let strip = sgam_core::Image::try_from_vec(4 * w as u32, h as u32, data).context("a round trip's picture")?;
        sgam_io::write_rgb_png(&dir.join(format!("round-trip-{:02}.png", t.via_step)), &strip)?;
    }
    Ok(())
}

/// The round trips in a line or two of the summary ("" without them).
fn round_trip_summary(r: &serde_json::Value) -> String {
    if r.is_null() {
        return String::new();
    }
    let f = |v: &serde_json::Value| v.as_f64().map_or("n/a".to_string(), |x| format!("{x:.2}"));
    let g = |v: &serde_json::Value| v.as_f64().map_or("n/a".to_string(), |x| format!("{x:.3}"));
    if r["trips"].as_u64() == Some(0) {
        return "\n  round trips of the seed: none along this path loses 3-50 % of it (a map too coarse for the \
                seed loses more on the way: try a finer --voxel-size)"
            .to_string();
    }
    let mut caveat = String::new();
    if r["adapted_saw_holes"].as_bool() == Some(true) {
        caveat += "\n    (the adapted model was tuned on the whole seed, holes included: an upper bound)";
    }
    if r["bank_without_holes"].as_bool() == Some(true) {
        caveat += "\n    (the seed's bank is built here without the holes' own pixels, so where every match \
                   would take lost ones the paste leaves the hole empty; in the run it holds the whole seed)";
    }
    format!(
        "\n  round trips of the seed ({} trips, median {} of it lost), on the holes:\n    \
         colour PSNR {} dB (push-pull fill {} dB), depth abs-rel {} (push-pull {}), filled {} (there {} dB){caveat}",
        r["trips"],
        g(&r["median_hole_share"]),
        f(&r["psnr_db"]["refiner"]),
        f(&r["psnr_db"]["push_pull"]),
        g(&r["depth_abs_rel"]["refiner"]),
        g(&r["depth_abs_rel"]["push_pull"]),
        g(&r["filled_share"]),
        f(&r["filled_psnr_db"]["refiner"]),
    )
}

fn read_json(path: &Path) -> Option<serde_json::Value> {
    serde_json::from_slice(&std::fs::read(path).ok()?).ok()
}

/// Runs `sgam eval seed`: a short summary on stderr (unless `--json`), the JSON line on stdout.
pub fn run(a: &SeedArgs) -> Result<()> {
    let v = evaluate(a)?;
    if !a.json {
        let f = |k: &str| v[k].as_f64().map_or("n/a".to_string(), |x| format!("{x:.4}"));
        eprintln!(
            "{}: {} frames, {} judged\n  new area (share of the frame the seed did not see), last judged: {}\n  \
             KID, seed patches vs new-area patches ({} vs {}): {}\n  floating share of new points: {}\n  \
             step median: {} ms{}",
            v["run"].as_str().unwrap_or(""),
            v["frames"],
            v["judged_frames"],
            f("new_area_share_last"),
            v["seed_patches"],
            v["new_patches"],
            f("kid_seed_vs_new"),
            f("floating_share"),
            f("step_ms_median"),
            round_trip_summary(&v["round_trip"]),
        );
    }
    println!("{v}");
    Ok(())
}
