use std::collections::HashMap;

use glam::{IVec3, Vec3};
use rayon::prelude::*;
use sgam_core::TriMesh;

/// A float type [`median`] works on (`f32`, `f64`).
pub trait Sortable: Copy {
    /// IEEE total order (NaNs last).
    fn total_order(&self, other: &Self) -> std::cmp::Ordering;
    /// The mean of `a` and `b`.
    fn mean_of(a: Self, b: Self) -> Self;
}

impl Sortable for f32 {
    fn total_order(&self, other: &Self) -> std::cmp::Ordering {
        self.total_cmp(other)
    }
    fn mean_of(a: Self, b: Self) -> Self {
        0.5 * (a + b)
    }
}

impl Sortable for f64 {
    fn total_order(&self, other: &Self) -> std::cmp::Ordering {
        self.total_cmp(other)
    }
    fn mean_of(a: Self, b: Self) -> Self {
        0.5 * (a + b)
    }
}

/// Median of a slice (NaNs sorted last; the mean of the middle two for an even count); `None`
/// when empty. The workspace's one median (timings, distances, heights).
pub fn median<T: Sortable>(values: &[T]) -> Option<T> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(T::total_order);
    let n = v.len();
    Some(if n % 2 == 1 { v[n / 2] } else { T::mean_of(v[n / 2 - 1], v[n / 2]) })
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

/// Most grid cells one triangle is entered into: a larger triangle (a stray vertex far away)
/// goes to a list every query searches, so memory stays proportional to the mesh.
const MAX_CELLS_PER_TRIANGLE: f64 = 64.0;
/// Grid coordinates beyond this (in cells) are not hashed (they would overflow `i32`).
const MAX_CELL_COORD: f32 = (1 << 30) as f32;

/// Distance (m) from each query point to the nearest point of `mesh`'s surface, searching at
/// most `max_distance_m` away (points farther get `f32::INFINITY`). Uses a uniform grid of
/// triangles with cell size `max_distance_m`; triangles spanning more than 64 cells are checked
/// against every point instead of filling the grid. Triangles with a non-finite vertex are
/// ignored and non-finite points are unmatched; with a `max_distance_m` that is not a positive
/// number every point is unmatched.
pub fn point_to_mesh_distances(points: &[Vec3], mesh: &TriMesh, max_distance_m: f32) -> Vec<f32> {
    if !(max_distance_m.is_finite() && max_distance_m > 0.0) {
        return vec![f32::INFINITY; points.len()];
    }
    let cell = max_distance_m;
    let key = |p: Vec3| {
        let k = (p / cell).floor();
        (k.is_finite() && k.abs().max_element() < MAX_CELL_COORD).then(|| k.as_ivec3())
    };
    let corners = |tri: &[u32; 3]| tri.map(|i| mesh.positions.get(i as usize).copied().unwrap_or(Vec3::NAN));
    let mut grid: HashMap<IVec3, Vec<u32>> = HashMap::new();
    let mut large: Vec<u32> = Vec::new();
    for (t, tri) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = corners(tri);
        if !(a.is_finite() && b.is_finite() && c.is_finite()) {
            continue;
        }
        let (Some(lo), Some(hi)) = (key(a.min(b).min(c)), key(a.max(b).max(c))) else {
            large.push(t as u32);
            continue;
        };
        let span = (hi - lo).as_dvec3() + 1.0;
        if span.x * span.y * span.z > MAX_CELLS_PER_TRIANGLE {
            large.push(t as u32);
            continue;
        }
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
            if !p.is_finite() {
                return f32::INFINITY;
            }
            let mut best = f32::INFINITY;
            let mut visit = |t: u32| {
                let [a, b, c] = corners(&mesh.triangles[t as usize]);
                best = best.min((closest_on_triangle(*p, a, b, c) - *p).length());
            };
            if let Some(k) = key(*p) {
                for dz in -1..=1 {
                    for dy in -1..=1 {
                        for dx in -1..=1 {
                            let Some(tris) = grid.get(&(k + IVec3::new(dx, dy, dz))) else { continue };
                            tris.iter().for_each(|&t| visit(t));
                        }
                    }
                }
            }
            large.iter().for_each(|&t| visit(t));
            if best <= max_distance_m {
                best
            } else {
                f32::INFINITY
            }
        })
        .collect()
}

/// Nearest-neighbour distances from each point of `from` to the set `to`, searching at most
/// `max_distance_m` (farther, non-finite or with a bad `max_distance_m`: `f32::INFINITY`).
fn nn_distances(from: &[Vec3], to: &[Vec3], max_distance_m: f32) -> Vec<f32> {
    if !(max_distance_m.is_finite() && max_distance_m > 0.0) {
        return vec![f32::INFINITY; from.len()];
    }
    let cell = max_distance_m;
    let key = |p: Vec3| {
        let k = (p / cell).floor();
        (k.is_finite() && k.abs().max_element() < MAX_CELL_COORD).then(|| k.as_ivec3())
    };
    let mut grid: HashMap<IVec3, Vec<u32>> = HashMap::new();
    let mut far: Vec<u32> = Vec::new();
    for (i, p) in to.iter().enumerate() {
        match key(*p) {
            Some(k) => grid.entry(k).or_default().push(i as u32),
            None if p.is_finite() => far.push(i as u32),
            None => {}
        }
    }
    from.par_iter()
        .map(|p| {
            if !p.is_finite() {
                return f32::INFINITY;
            }
            let mut best = f32::INFINITY;
            if let Some(k) = key(*p) {
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
            }
            for &i in &far {
                best = best.min((to[i as usize] - *p).length());
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
    fn stray_far_non_finite_vertices_and_bad_distances_stay_bounded_and_exact() {
        // a triangle from the origin to 10 km away spans 10^15 cells of 0.1 m: it must not be
        // binned cell by cell, and it is still found by a point next to its near corner
        let far = 1e4;
        let mesh = TriMesh {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::splat(far), Vec3::new(f32::NAN, 0.0, 0.0), Vec3::Y],
            colours: vec![],
            triangles: vec![[0, 1, 2], [0, 3, 4], [0, 1, 9]],
        };
        let p = Vec3::new(0.5, 0.0, 0.05);
        let d = point_to_mesh_distances(&[p, Vec3::NAN, Vec3::splat(1e12)], &mesh, 0.1);
        // the triangle's plane holds the x axis and (1, 1, 1): distance 0.05 / sqrt(2)
        assert!((d[0] - 0.05 / 2f32.sqrt()).abs() < 1e-5, "{d:?}");
        assert!(d[1].is_infinite() && d[2].is_infinite(), "{d:?}");
        for bad in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            assert!(point_to_mesh_distances(&[Vec3::ZERO], &mesh, bad)[0].is_infinite());
        }
        let c = chamfer(&[Vec3::ZERO, Vec3::splat(1e12)], &[Vec3::ZERO, Vec3::splat(1e12)], 0.1).unwrap();
        assert!(c < 1e-9, "{c}");
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
