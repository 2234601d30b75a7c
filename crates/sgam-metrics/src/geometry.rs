use std::collections::HashMap;

use glam::{IVec3, Vec3};
use rayon::prelude::*;
use sgam_core::TriMesh;

/// Median of a slice (NaNs sorted last); `None` when empty.
pub fn median(values: &[f32]) -> Option<f32> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    Some(if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) })
}

/// Closest point on triangle `abc` to `p` (Ericson, Real-Time Collision Detection, 5.1.5).
fn closest_on_triangle(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> Vec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

/// Distance (m) from each query point to the nearest point of `mesh`'s surface, searching at
/// most `max_distance_m` away (points farther get `f32::INFINITY`). Uses a uniform grid of
/// triangles with cell size `max_distance_m`.
pub fn point_to_mesh_distances(points: &[Vec3], mesh: &TriMesh, max_distance_m: f32) -> Vec<f32> {
    let cell = max_distance_m.max(1e-6);
    let key = |p: Vec3| (p / cell).floor().as_ivec3();
    let mut grid: HashMap<IVec3, Vec<u32>> = HashMap::new();
    for (t, tri) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = tri.map(|i| mesh.positions[i as usize]);
        let (lo, hi) = (key(a.min(b).min(c)), key(a.max(b).max(c)));
        for z in lo.z..=hi.z {
            for y in lo.y..=hi.y {
                for x in lo.x..=hi.x {
                    grid.entry(IVec3::new(x, y, z)).or_default().push(t as u32);
                }
            }
        }
    }
    points
        .par_iter()
        .map(|p| {
            let k = key(*p);
            let mut best = f32::INFINITY;
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let Some(tris) = grid.get(&(k + IVec3::new(dx, dy, dz))) else { continue };
                        for &t in tris {
                            let [a, b, c] = mesh.triangles[t as usize].map(|i| mesh.positions[i as usize]);
                            best = best.min((closest_on_triangle(*p, a, b, c) - *p).length());
                        }
                    }
                }
            }
            if best <= max_distance_m {
                best
            } else {
                f32::INFINITY
            }
        })
        .collect()
}

/// Nearest-neighbour distances from each point of `from` to the set `to`, searching at most
/// `max_distance_m` (farther: `f32::INFINITY`).
fn nn_distances(from: &[Vec3], to: &[Vec3], max_distance_m: f32) -> Vec<f32> {
    let cell = max_distance_m.max(1e-6);
    let key = |p: Vec3| (p / cell).floor().as_ivec3();
    let mut grid: HashMap<IVec3, Vec<u32>> = HashMap::new();
    for (i, p) in to.iter().enumerate() {
        grid.entry(key(*p)).or_default().push(i as u32);
    }
    from.par_iter()
        .map(|p| {
            let k = key(*p);
            let mut best = f32::INFINITY;
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        if let Some(ids) = grid.get(&(k + IVec3::new(dx, dy, dz))) {
                            for &i in ids {
                                best = best.min((to[i as usize] - *p).length());
                            }
                        }
                    }
                }
            }
            if best <= max_distance_m {
                best
            } else {
                f32::INFINITY
            }
        })
        .collect()
}

/// Symmetric Chamfer distance between point sets: mean NN distance a->b plus b->a (metres),
/// with distances capped at `max_distance_m`. `None` when either set is empty.
pub fn chamfer(a: &[Vec3], b: &[Vec3], max_distance_m: f32) -> Option<f64> {
    if a.is_empty() || b.is_empty() {
        return None;
    }
    let mean = |d: Vec<f32>| d.iter().map(|x| x.min(max_distance_m) as f64).sum::<f64>() / d.len() as f64;
    Some(mean(nn_distances(a, b, max_distance_m)) + mean(nn_distances(b, a, max_distance_m)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distances_to_a_unit_square() {
        let mesh = TriMesh {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y],
            colours: vec![],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        };
        let pts =
            [Vec3::new(0.5, 0.5, 0.3), Vec3::new(2.0, 0.5, 0.0), Vec3::new(0.2, 0.9, -0.1), Vec3::new(9.0, 9.0, 9.0)];
        let d = point_to_mesh_distances(&pts, &mesh, 1.5);
        assert!((d[0] - 0.3).abs() < 1e-6);
        assert!((d[1] - 1.0).abs() < 1e-6);
        assert!((d[2] - 0.1).abs() < 1e-6);
        assert!(d[3].is_infinite());
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
    }

    #[test]
    fn chamfer_of_shifted_grid() {
        let a: Vec<Vec3> = (0..100).map(|i| Vec3::new((i % 10) as f32, (i / 10) as f32, 0.0)).collect();
        let b: Vec<Vec3> = a.iter().map(|p| *p + Vec3::new(0.0, 0.0, 0.1)).collect();
        let c = chamfer(&a, &b, 1.0).unwrap();
        assert!((c - 0.2).abs() < 1e-5, "{c}");
        assert!(chamfer(&a, &a, 1.0).unwrap() < 1e-9);
    }
}
