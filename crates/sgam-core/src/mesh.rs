use glam::Vec3;
use serde::{Deserialize, Serialize};

/// An indexed triangle mesh with per-vertex colour (sRGB, `[0, 1]`), in world coordinates.
/// Triangles wind counter-clockwise seen from outside (normals point out of the surface, towards
/// free space).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TriMesh {
    /// Vertex positions, metres, world frame.
    pub positions: Vec<Vec3>,
    /// Per-vertex colour, sRGB `[0, 1]`; empty or same length as `positions`.
    pub colours: Vec<[f32; 3]>,
    /// Vertex indices of each triangle.
    pub triangles: Vec<[u32; 3]>,
}

impl TriMesh {
    /// Total surface area (m^2).
    pub fn area(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.positions[i as usize]);
                0.5 * (b - a).cross(c - a).length() as f64
            })
            .sum()
    }

    /// Appends another mesh, offsetting its indices.
    pub fn append(&mut self, other: &TriMesh) {
        let base = self.positions.len() as u32;
        self.positions.extend_from_slice(&other.positions);
        self.colours.extend_from_slice(&other.colours);
        self.triangles.extend(other.triangles.iter().map(|t| [t[0] + base, t[1] + base, t[2] + base]));
    }

    /// Number of vertices.
    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    /// A coarser mesh by vertex clustering (Rossignac & Borrel): the vertices in each cube of
    /// side `cell_m` become one, at the cube's centre, with their mean colour; triangles whose
    /// corners fall in fewer than three cubes, and repeats, are dropped. The grid is anchored at
    /// the origin and a vertex's place depends only on its cube, so pieces of one surface
    /// clustered apart (tiles) still meet without cracks. Deterministic (first appearance
    /// order). A cell that is not finite and positive returns the mesh as it is.
    pub fn clustered(&self, cell_m: f32) -> TriMesh {
        if !(cell_m.is_finite() && cell_m > 0.0) {
            return self.clone();
        }
        let mut cluster_of: std::collections::HashMap<[i32; 3], u32> = std::collections::HashMap::new();
        let mut remap = Vec::with_capacity(self.positions.len());
        let mut sums: Vec<([i32; 3], [f32; 3], u32)> = Vec::new();
        let coloured = self.colours.len() == self.positions.len();
        for (i, p) in self.positions.iter().enumerate() {
            let key = (*p / cell_m).floor().as_ivec3().to_array();
            let next = sums.len() as u32;
            let c = *cluster_of.entry(key).or_insert(next);
            if c == next {
                sums.push((key, [0.0; 3], 0));
            }
            let s = &mut sums[c as usize];
            if coloured {
                for k in 0..3 {
                    s.1[k] += self.colours[i][k];
                }
            }
            s.2 += 1;
            remap.push(c);
        }
        let mut seen = std::collections::HashSet::new();
        let mut triangles = Vec::new();
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| remap[i as usize]);
            if a == b || b == c || a == c {
                continue;
            }
            // one rotation for each triangle, so a repeat is found whatever corner it starts at
            let r = if a < b && a < c {
                [a, b, c]
            } else if b < c {
                [b, c, a]
            } else {
                [c, a, b]
            };
            if seen.insert(r) {
                triangles.push([a, b, c]);
            }
        }
        let positions = sums.iter().map(|s| (glam::IVec3::from_array(s.0).as_vec3() + 0.5) * cell_m).collect();
        let colours = if coloured { sums.iter().map(|s| s.1.map(|x| x / s.2 as f32)).collect() } else { Vec::new() };
        TriMesh { positions, colours, triangles }
    }

    /// Axis-aligned bounds `(min, max)`, `None` when empty.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let first = *self.positions.first()?;
        Some(self.positions.iter().fold((first, first), |(lo, hi), p| (lo.min(*p), hi.max(*p))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat grid of `n x n` quads of side `step` at height `z`, coloured by x.
    fn grid(n: u32, step: f32, z: f32) -> TriMesh {
        let mut m = TriMesh::default();
        for j in 0..=n {
            for i in 0..=n {
                m.positions.push(Vec3::new(i as f32 * step, j as f32 * step, z));
                m.colours.push([i as f32 / n as f32, 0.5, 0.5]);
            }
        }
        let at = |i: u32, j: u32| j * (n + 1) + i;
        for j in 0..n {
            for i in 0..n {
                m.triangles.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                m.triangles.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
        m
    }

    #[test]
    fn clustering_keeps_a_surface_with_fewer_triangles_and_its_winding() {
        let fine = grid(40, 0.05, 0.3);
        let coarse = fine.clustered(0.2);
        assert!(
            coarse.triangles.len() * 10 < fine.triangles.len(),
            "{} of {}",
            coarse.triangles.len(),
            fine.triangles.len()
        );
        // the same surface: close in area, on the same plane, normals still up
        let (a, b) = (fine.area(), coarse.area());
        assert!((b / a - 1.0).abs() < 0.15, "area {a} -> {b}");
        // (0.3 is the centre of the cubes' layer [0.2, 0.4))
        assert!(coarse.positions.iter().all(|p| (p.z - 0.3).abs() < 1e-5));
        // two halves clustered apart meet: the vertices on their seam are the same points
        let (left, right) = (grid(20, 0.05, 0.3), {
            let mut r = grid(20, 0.05, 0.3);
            r.positions.iter_mut().for_each(|p| p.x += 1.0);
            r
        });
        let (l, r) = (left.clustered(0.2), right.clustered(0.2));
        let seam = |m: &TriMesh| {
            let mut v: Vec<[i32; 2]> = m
                .positions
                .iter()
                .filter(|p| (p.x - 1.1).abs() < 1e-4)
                .map(|p| [(p.y * 1e4) as i32, (p.z * 1e4) as i32])
                .collect();
            v.sort_unstable();
            v
        };
        assert!(!seam(&l).is_empty() && seam(&l) == seam(&r), "the halves' seam vertices differ");
        for t in &coarse.triangles {
            let [p, q, r] = t.map(|i| coarse.positions[i as usize]);
            assert!((q - p).cross(r - p).z > 0.0, "a triangle turned over");
        }
        assert_eq!(coarse.colours.len(), coarse.positions.len());
        assert!(coarse.triangles.iter().flatten().all(|&i| (i as usize) < coarse.positions.len()));
        // a cell finer than the mesh changes nothing but the vertex order's gaps (none here)
        let same = fine.clustered(0.01);
        assert_eq!(same.triangles.len(), fine.triangles.len());
        assert_eq!(fine.clustered(f32::NAN), fine);
    }
}
