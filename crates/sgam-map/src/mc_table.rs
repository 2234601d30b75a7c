//! Marching-cubes case table, generated once at first use instead of transcribed.
//!
//! Why generated: a hand-typed 256 x 16 table is easy to get subtly wrong; generating it from
//! a face rule guarantees watertightness by construction. Each cube face decides its own
//! segments from its four corner signs only, so two cells sharing a face always agree:
//! a face with two crossing edges gets one segment; an ambiguous face (four crossings,
//! diagonal corners equal) separates its *inside* corners (each segment cuts off one inside
//! corner). Segments are oriented so the inside corner they cut off lies on their right seen
//! from outside the cube; they then chain into closed loops that are fanned into triangles
//! wound counter-clockwise seen from the outside (positive) side of the surface.
//!
//! Conventions: corner `c` has offset `(c & 1, (c >> 1) & 1, (c >> 2) & 1)`; edge
//! `e = 4 * axis + j` runs along `axis` from corner `start` (bit `axis` clear) to
//! `start | 1 << axis`, where `j = bit_b + 2 bit_c` with `b = (axis + 1) % 3`, `c = (axis + 2) % 3`.
//! Case index bit `c` is set when corner `c` is inside (tsdf < 0).

use std::sync::OnceLock;

use glam::Vec3;

/// Triangles of every case as edge triples.
pub(crate) struct McTable {
    /// `cases[i]` = triangles (three edge ids each) for case index `i`.
    pub cases: Vec<Vec<[u8; 3]>>,
}

/// Start corner of edge `e`.
#[inline]
pub(crate) const fn edge_start(e: usize) -> usize {
    let axis = e / 4;
    let j = e % 4;
    let (b, c) = ((axis + 1) % 3, (axis + 2) % 3);
    ((j & 1) << b) | ((j >> 1) << c)
}

/// Axis (0 = x, 1 = y, 2 = z) of edge `e`.
#[inline]
pub(crate) const fn edge_axis(e: usize) -> usize {
    e / 4
}

fn corner_pos(c: usize) -> Vec3 {
    Vec3::new((c & 1) as f32, ((c >> 1) & 1) as f32, ((c >> 2) & 1) as f32)
}

fn edge_mid(e: usize) -> Vec3 {
    let s = edge_start(e);
    0.5 * (corner_pos(s) + corner_pos(s | 1 << edge_axis(e)))
}

fn build_case(case: usize) -> Vec<[u8; 3]> {
    let inside = |c: usize| case >> c & 1 == 1;
    let crosses = |e: usize| {
        let s = edge_start(e);
        inside(s) != inside(s | 1 << edge_axis(e))
    };
    let mut next = [usize::MAX; 12];
    for face_axis in 0..3 {
        for side in 0..2usize {
            let normal = {
                let mut n = Vec3::ZERO;
                n[face_axis] = if side == 1 { 1.0 } else { -1.0 };
                n
            };
            let face_edges: Vec<usize> =
                (0..12).filter(|&e| edge_axis(e) != face_axis && (edge_start(e) >> face_axis & 1) == side).collect();
            let corners: Vec<usize> = (0..8).filter(|&c| (c >> face_axis & 1) == side).collect();
            let crossing: Vec<usize> = face_edges.iter().copied().filter(|&e| crosses(e)).collect();
            let mut segments: Vec<(usize, usize, usize)> = Vec::new(); // (edge a, edge b, cut-off inside corner)
            match crossing.len() {
                2 => {
                    let q = corners.iter().copied().find(|&c| inside(c)).unwrap_or(0);
                    segments.push((crossing[0], crossing[1], q));
                }
                4 => {
                    for &c in corners.iter().filter(|&&c| inside(c)) {
                        let incident: Vec<usize> = face_edges
                            .iter()
                            .copied()
                            .filter(|&e| edge_start(e) == c || (edge_start(e) | 1 << edge_axis(e)) == c)
                            .collect();
                        segments.push((incident[0], incident[1], c));
                    }
                }
                _ => {}
            }
            for (a, b, q) in segments {
                let (pa, pb, pq) = (edge_mid(a), edge_mid(b), corner_pos(q));
                let s = (pb - pa).cross(pq - pa).dot(normal);
                let (from, to) = if s < 0.0 { (a, b) } else { (b, a) };
                next[from] = to;
            }
        }
    }
    let mut tris = Vec::new();
    let mut visited = [false; 12];
    for start in 0..12 {
        if next[start] == usize::MAX || visited[start] {
            continue;
        }
        let mut ring = vec![start];
        visited[start] = true;
        let mut e = next[start];
        while e != start && e != usize::MAX && ring.len() < 12 {
            visited[e] = true;
            ring.push(e);
            e = next[e];
        }
        for i in 1..ring.len().saturating_sub(1) {
            tris.push([ring[0] as u8, ring[i] as u8, ring[i + 1] as u8]);
        }
    }
    tris
}

/// The table, built on first use.
pub(crate) fn table() -> &'static McTable {
    static TABLE: OnceLock<McTable> = OnceLock::new();
    TABLE.get_or_init(|| McTable { cases: (0..256).map(build_case).collect() })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    #[test]
    fn trivial_cases_are_empty_and_single_corner_is_one_triangle() {
        let t = table();
        assert!(t.cases[0].is_empty() && t.cases[255].is_empty());
        for c in 0..8 {
            assert_eq!(t.cases[1 << c].len(), 1, "corner {c}");
            assert_eq!(t.cases[255 ^ (1 << c)].len(), 1);
        }
        // Half cube split by a plane: a quad (two triangles).
        assert_eq!(t.cases[0b0000_1111].len(), 2);
    }

    /// The two cube faces `(axis, side)` that contain edge `e`.
    fn faces_of_edge(e: usize) -> Vec<(usize, usize)> {
        let s = edge_start(e);
        (0..3).filter(|&a| a != edge_axis(e)).map(|a| (a, s >> a & 1)).collect()
    }

    /// The directed polygon edges of `case` that no triangle traverses the other way: the
    /// surface's border inside the cell, which must run along the cube's faces.
    fn border(case: usize) -> Vec<(u8, u8)> {
        let mut directed = std::collections::HashSet::new();
        for tri in &table().cases[case] {
            for k in 0..3 {
                directed.insert((tri[k], tri[(k + 1) % 3]));
            }
        }
        let mut out: Vec<(u8, u8)> = directed.iter().copied().filter(|&(a, b)| !directed.contains(&(b, a))).collect();
        out.sort_unstable();
        out
    }

    #[test]
    fn every_case_is_a_closed_surface_inside_the_cube_boundary() {
        // Each crossing edge is used by the polygons; each non-crossing edge never; no directed
        // edge twice; every polygon edge either is shared with the opposite direction by another
        // triangle (interior) or lies on a cube face (border). On each face the border has one
        // segment per pair of crossing edges (2 crossings: 1 segment, 4: 2), so the surface
        // leaves the cube only through faces, where the neighbouring cell continues it (checked
        // in `neighbouring_cells_agree_on_their_shared_face`).
        let t = table();
        for case in 0..256usize {
            let inside = |c: usize| case >> c & 1 == 1;
            let mut used = [false; 12];
            let mut directed: HashMap<(u8, u8), i32> = HashMap::new();
            for tri in &t.cases[case] {
                for k in 0..3 {
                    used[tri[k] as usize] = true;
                    *directed.entry((tri[k], tri[(k + 1) % 3])).or_default() += 1;
                }
            }
            let crossing = |e: usize| {
                let s = edge_start(e);
                inside(s) != inside(s | 1 << edge_axis(e))
            };
            for e in 0..12 {
                assert_eq!(used[e], crossing(e), "case {case} edge {e}");
            }
            for (&(a, b), &n) in &directed {
                assert_eq!(n, 1, "case {case}: directed edge {a}->{b} used {n} times");
            }
            let border = border(case);
            for &(a, b) in &border {
                let (fa, fb) = (faces_of_edge(a as usize), faces_of_edge(b as usize));
                assert!(fa.iter().any(|f| fb.contains(f)), "case {case}: border {a}->{b} crosses the cube's inside");
            }
            for axis in 0..3 {
                for side in 0..2 {
                    let on_face = |e: u8| faces_of_edge(e as usize).contains(&(axis, side));
                    let n_cross = (0..12).filter(|&e| crossing(e) && on_face(e as u8)).count();
                    let n_border = border.iter().filter(|&&(a, b)| on_face(a) && on_face(b)).count();
                    assert_eq!(n_border, n_cross / 2, "case {case} face ({axis}, {side})");
                }
            }
        }
    }

    #[test]
    fn neighbouring_cells_agree_on_their_shared_face() {
        // Watertightness across cells: for every pair of cases whose corner signs agree on a
        // shared face (cell A's side 1 = cell B's side 0 along `axis`), A's border segments on
        // that face are B's, traversed the other way (consistent orientation across the face).
        let mirror = |e: u8, axis: usize| {
            // The edge of cell B at the same place as edge `e` of cell A on A's side-1 face.
            let s = edge_start(e as usize) & !(1 << axis);
            (0..12u8)
                .find(|&f| edge_axis(f as usize) == edge_axis(e as usize) && edge_start(f as usize) == s)
                .unwrap_or(u8::MAX)
        };
        let borders: Vec<Vec<(u8, u8)>> = (0..256).map(border).collect();
        for axis in 0..3 {
            let face_corners = |side: usize| (0..8usize).filter(move |c| c >> axis & 1 == side);
            for a in 0..256usize {
                for b in 0..256usize {
                    let agree = face_corners(1).all(|c| (a >> c & 1) == (b >> (c & !(1 << axis)) & 1));
                    if !agree {
                        continue;
                    }
                    let on = |e: u8, side: usize| faces_of_edge(e as usize).contains(&(axis, side));
                    let mut from_a: Vec<(u8, u8)> = borders[a]
                        .iter()
                        .filter(|&&(x, y)| on(x, 1) && on(y, 1))
                        .map(|&(x, y)| (mirror(y, axis), mirror(x, axis)))
                        .collect();
                    let mut from_b: Vec<(u8, u8)> =
                        borders[b].iter().copied().filter(|&(x, y)| on(x, 0) && on(y, 0)).collect();
                    from_a.sort_unstable();
                    from_b.sort_unstable();
                    assert_eq!(from_a, from_b, "cases {a} and {b} along axis {axis}");
                }
            }
        }
    }

    #[test]
    fn triangles_face_the_outside() {
        // Single inside corner 0: the normal must point away from corner 0.
        let t = table();
        let tri = t.cases[1][0];
        let p = tri.map(|e| edge_mid(e as usize));
        let n = (p[1] - p[0]).cross(p[2] - p[0]);
        assert!(n.dot(Vec3::ONE) > 0.0);
        // Every triangle of every case: each vertex sits on an edge from an inside corner to an
        // outside one, and the surface separates them, so the triangle's normal points along
        // those edges' inside-to-outside directions (summed over its three vertices). Triangles
        // lying in a cube face (fans of 6- and 7-gons whose three consecutive vertices share an
        // ambiguous face: 18 of the table's 820) have all three edges in that face, so the sum
        // is perpendicular to their normal and says nothing; they are counted, not judged.
        let mut in_face = 0;
        for case in 0..256usize {
            let inside = |c: usize| case >> c & 1 == 1;
            for tri in &t.cases[case] {
                let p = tri.map(|e| edge_mid(e as usize));
                let n = (p[1] - p[0]).cross(p[2] - p[0]);
                assert!(n.length() > 1e-6, "case {case}: degenerate triangle {tri:?}");
                if (0..3).any(|a| p[0][a] == p[1][a] && p[1][a] == p[2][a] && p[0][a] != 0.5) {
                    in_face += 1;
                    continue;
                }
                let outward: Vec3 = tri
                    .iter()
                    .map(|&e| {
                        let s = edge_start(e as usize);
                        let d = corner_pos(s | 1 << edge_axis(e as usize)) - corner_pos(s);
                        if inside(s) {
                            d
                        } else {
                            -d
                        }
                    })
                    .sum();
                assert!(n.dot(outward) > 0.0, "case {case}: triangle {tri:?} faces inwards");
            }
        }
        assert!(in_face <= 18, "{in_face} triangles lie in a cube face (measured 18; fewer is better)");
    }
}
