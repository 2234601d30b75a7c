//! Scene-level metrics (SGAM Table 2): split a world into non-overlapping square regions in the
//! horizontal plane, voxelise each region into a `bins^3` occupancy histogram (15^3 in the paper),
//! compare histograms by cosine distance, and score the generated set against the reference set
//! with the point-cloud GAN metrics of Achlioptas et al. (2018) / PointFlow:
//!
//! - **JSD**: Jensen-Shannon divergence (natural log) between the two sets' mean normalised
//!   occupancy histograms. Lower is better.
//! - **MMD**: mean over reference regions of the distance to the closest generated region
//!   (fidelity). Lower is better.
//! - **COV**: fraction of reference regions that are the nearest neighbour of at least one
//!   generated region (coverage). Higher is better.
//! - **MinDist**: mean over generated regions of the distance to the closest reference region
//!   (our definition: MMD in the other direction, penalising implausible generated regions).
//! - **1-NNA**: leave-one-out 1-nearest-neighbour classification accuracy over the union of both
//!   sets; 0.5 means indistinguishable, 1.0 fully separable.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// How a world is cut into regions and voxelised.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RegionSpec {
    /// Lower corner of the area (x, y) and the bottom of the voxelised slab (z), metres.
    pub min: Vec3,
    /// Upper corner of the area and top of the slab, metres.
    pub max: Vec3,
    /// Side of a square region, metres.
    pub region_size_m: f32,
    /// Voxels per axis inside a region (15 in the paper).
    pub bins: usize,
}

/// Occupancy histograms (each normalised to sum 1; all-zero when the region is empty), one per
/// region, regions in row-major (y, then x) order. Points outside the slab are ignored.
pub fn region_histograms(points: &[Vec3], spec: &RegionSpec) -> Vec<Vec<f32>> {
    let nx = ((spec.max.x - spec.min.x) / spec.region_size_m).floor().max(0.0) as usize;
    let ny = ((spec.max.y - spec.min.y) / spec.region_size_m).floor().max(0.0) as usize;
    let b = spec.bins.max(1);
    let mut hist = vec![vec![0.0f32; b * b * b]; nx * ny];
    let zh = (spec.max.z - spec.min.z).max(1e-6);
    for p in points {
        let rel = *p - spec.min;
        if rel.x < 0.0 || rel.y < 0.0 || rel.z < 0.0 || rel.z >= zh {
            continue;
        }
        let (rx, ry) = ((rel.x / spec.region_size_m) as usize, (rel.y / spec.region_size_m) as usize);
        if rx >= nx || ry >= ny {
            continue;
        }
        let fx = rel.x / spec.region_size_m - rx as f32;
        let fy = rel.y / spec.region_size_m - ry as f32;
        let fz = rel.z / zh;
        let idx = |f: f32| ((f * b as f32) as usize).min(b - 1);
        hist[ry * nx + rx][(idx(fz) * b + idx(fy)) * b + idx(fx)] = 1.0;
    }
    for h in &mut hist {
        let s: f32 = h.iter().sum();
        if s > 0.0 {
            h.iter_mut().for_each(|v| *v /= s);
        }
    }
    hist
}

/// Cosine distance `1 - a.b / (|a||b|)`; 1 when either is all-zero (unless both are: 0).
pub fn cosine_distance(a: &[f32], b: &[f32]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum();
    let na: f64 = a.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    match (na > 0.0, nb > 0.0) {
        (false, false) => 0.0,
        (true, true) => (1.0 - dot / (na * nb)).max(0.0),
        _ => 1.0,
    }
}

/// The five scene metrics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SceneMetrics {
    /// Jensen-Shannon divergence of mean occupancy.
    pub jsd: f64,
    /// Minimum matching distance (reference -> generated).
    pub mmd: f64,
    /// Coverage in `[0, 1]`.
    pub cov: f64,
    /// Mean distance generated -> nearest reference.
    pub min_dist: f64,
    /// 1-nearest-neighbour accuracy in `[0, 1]`.
    pub one_nna: f64,
}

/// Scores `generated` against `reference` region histograms. `None` when either set is empty.
pub fn scene_metrics(generated: &[Vec<f32>], reference: &[Vec<f32>]) -> Option<SceneMetrics> {
    if generated.is_empty() || reference.is_empty() {
        return None;
    }
    let d_gr: Vec<Vec<f64>> =
        generated.iter().map(|g| reference.iter().map(|r| cosine_distance(g, r)).collect()).collect();
    let mmd = (0..reference.len()).map(|j| d_gr.iter().map(|row| row[j]).fold(f64::INFINITY, f64::min)).sum::<f64>()
        / reference.len() as f64;
    let min_dist =
        d_gr.iter().map(|row| row.iter().copied().fold(f64::INFINITY, f64::min)).sum::<f64>() / generated.len() as f64;
    let mut covered = vec![false; reference.len()];
    for row in &d_gr {
        let j = row.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1)).map(|(j, _)| j).unwrap_or(0);
        covered[j] = true;
    }
    let cov = covered.iter().filter(|c| **c).count() as f64 / reference.len() as f64;
    // 1-NNA over the union, leave-one-out
    let all: Vec<(&Vec<f32>, bool)> =
        generated.iter().map(|g| (g, true)).chain(reference.iter().map(|r| (r, false))).collect();
    let mut correct = 0usize;
    for (i, (a, label)) in all.iter().enumerate() {
        let mut best = (f64::INFINITY, *label);
        for (j, (b, lb)) in all.iter().enumerate() {
            if i != j {
                let d = cosine_distance(a, b);
                if d < best.0 {
                    best = (d, *lb);
                }
            }
        }
        correct += usize::from(best.1 == *label);
    }
    let one_nna = correct as f64 / all.len() as f64;
    let mean = |s: &[Vec<f32>]| {
        let mut m = vec![0.0f64; s[0].len()];
        for h in s {
            m.iter_mut().zip(h).for_each(|(a, b)| *a += *b as f64);
        }
        let t: f64 = m.iter().sum();
        if t > 0.0 {
            m.iter_mut().for_each(|a| *a /= t);
        }
        m
    };
    let (p, q) = (mean(generated), mean(reference));
    let kl =
        |a: &[f64], m: &[f64]| a.iter().zip(m).filter(|(x, _)| **x > 0.0).map(|(x, y)| x * (x / y).ln()).sum::<f64>();
    let mid: Vec<f64> = p.iter().zip(&q).map(|(a, b)| 0.5 * (a + b)).collect();
    let jsd = 0.5 * kl(&p, &mid) + 0.5 * kl(&q, &mid);
    Some(SceneMetrics { jsd, mmd, cov, min_dist, one_nna })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn world(seed: u64, tall: bool) -> Vec<Vec3> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut pts = Vec::new();
        for _ in 0..4000 {
            // ground
            pts.push(Vec3::new(rng.random_range(0.0..40.0), rng.random_range(0.0..40.0), 0.05));
        }
        for _ in 0..60 {
            let c = Vec3::new(rng.random_range(0.0..40.0), rng.random_range(0.0..40.0), 0.0);
            let h = if tall { 3.5 } else { 1.0 };
            for _ in 0..80 {
                pts.push(
                    c + Vec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), rng.random_range(0.0..h)),
                );
            }
        }
        pts
    }

    #[test]
    fn same_distribution_scores_better_than_different() {
        let spec = RegionSpec { min: Vec3::ZERO, max: Vec3::new(40.0, 40.0, 4.0), region_size_m: 8.0, bins: 15 };
        let r = region_histograms(&world(1, false), &spec);
        let g_same = region_histograms(&world(2, false), &spec);
        let g_diff = region_histograms(&world(3, true), &spec);
        assert_eq!(r.len(), 25);
        let s = scene_metrics(&g_same, &r).unwrap();
        let d = scene_metrics(&g_diff, &r).unwrap();
        assert!(s.jsd < d.jsd, "{s:?} {d:?}");
        assert!(s.mmd < d.mmd && s.min_dist < d.min_dist);
        assert!(s.one_nna < d.one_nna);
        // better than chance (0.5) at telling tall-object worlds from short-object ones
        assert!(d.one_nna > 0.6, "1-NNA of clearly different worlds {}", d.one_nna);
        let identical = scene_metrics(&r, &r).unwrap();
        assert!(identical.jsd.abs() < 1e-12 && identical.mmd < 1e-9 && identical.cov == 1.0);
    }

    #[test]
    fn hand_computed_sets_score_their_values() {
        // Disjoint supports: the mean histograms share no bin, so JSD = ln 2 (its maximum), every
        // cross distance is 1 (MMD = MinDist = 1), and each region's nearest other region (distance
        // < 1) is in its own set, so 1-NNA = 1.
        let g = vec![vec![1.0, 0.0, 0.0, 0.0], vec![0.6, 0.4, 0.0, 0.0]];
        let r = vec![vec![0.0, 0.0, 1.0, 0.0], vec![0.0, 0.0, 0.3, 0.7], vec![0.0, 0.0, 0.0, 1.0]];
        let m = scene_metrics(&g, &r).unwrap();
        assert!((m.jsd - std::f64::consts::LN_2).abs() < 1e-12, "{m:?}");
        assert!((m.mmd - 1.0).abs() < 1e-12 && (m.min_dist - 1.0).abs() < 1e-12, "{m:?}");
        assert_eq!(m.one_nna, 1.0, "{m:?}");

        // Coverage: three generated regions near the first two of four reference unit histograms
        // (cosine distance 1 - 0.9 / sqrt(0.82) to the nearer one, no ties): those two are covered,
        // COV = 2 / 4; MMD = (two near distances + 1 + 1) / 4.
        let e = |i: usize| (0..4).map(|k| if k == i { 1.0 } else { 0.0 }).collect::<Vec<f32>>();
        let g = vec![vec![0.9, 0.1, 0.0, 0.0], vec![0.1, 0.9, 0.0, 0.0], vec![0.8, 0.2, 0.0, 0.0]];
        let r = vec![e(0), e(1), e(2), e(3)];
        let m = scene_metrics(&g, &r).unwrap();
        let near = 1.0 - 0.9 / 0.82f64.sqrt();
        let third = 1.0 - 0.8 / 0.68f64.sqrt();
        assert_eq!(m.cov, 0.5, "{m:?}");
        // f32 histogram entries (0.9f32 != 0.9) limit agreement to ~1e-7.
        assert!((m.mmd - (2.0 * near + 2.0) / 4.0).abs() < 1e-6, "{m:?}");
        assert!((m.min_dist - (2.0 * near + third) / 3.0).abs() < 1e-6, "{m:?}");
    }
}
