//! `sgam eval seed RUN`: no-reference checks of a world grown from a real seed (a Google Earth
//! view, a user's RGB-D frame), which has no true world to compare with. What the run invented
//! is judged against the seed itself ([`sgam_metrics::noref`]): the new area's look (KID of its
//! patches against the seed's), geometry floating outside the seed's heights, and how much of
//! each frame is new.

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
    points above the seed's highest or below its lowest (widened by a tenth of the seed's median depth).")]
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
    }))
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
             step median: {} ms",
            v["run"].as_str().unwrap_or(""),
            v["frames"],
            v["judged_frames"],
            f("new_area_share_last"),
            v["seed_patches"],
            v["new_patches"],
            f("kid_seed_vs_new"),
            f("floating_share"),
            f("step_ms_median"),
        );
    }
    println!("{v}");
    Ok(())
}
