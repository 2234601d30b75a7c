//! Camera trajectories: sequences of `world_from_camera` poses (OpenCV axes).
//!
//! Grid trajectories translate the seed camera in the world's horizontal plane (x, y; world up
//! is +z) and keep its orientation, as the SGAM authors' CLEVR-Infinite trajectories do.

use glam::{Mat3, Vec3};

use crate::Rigid3;

/// The SGAM authors' anti-diagonal zig-zag over an `n_i x n_j` grid starting at grid cell
/// (0, 0) = the seed: diagonals `s = i + j = 0, 1, 2, ...`; on even `s` `i` descends, on odd `s`
/// it ascends. Returns the `(i, j)` cells in visiting order; every cell exactly once, and
/// consecutive cells are grid neighbours or diagonal neighbours.
pub fn zigzag_cells(n_i: usize, n_j: usize) -> Vec<(usize, usize)> {
    let mut out = Vec::with_capacity(n_i * n_j);
    if n_i == 0 || n_j == 0 {
        return out;
    }
    for s in 0..(n_i + n_j - 1) {
        let i_lo = s.saturating_sub(n_j - 1);
        let i_hi = s.min(n_i - 1);
        if s % 2 == 0 {
            for i in (i_lo..=i_hi).rev() {
                out.push((i, s - i));
            }
        } else {
            for i in i_lo..=i_hi {
                out.push((i, s - i));
            }
        }
    }
    out
}

/// Boustrophedon (lawn-mower) order over an `n_i x n_j` grid: rows of `j`, alternating direction.
pub fn boustrophedon_cells(n_i: usize, n_j: usize) -> Vec<(usize, usize)> {
    let mut out = Vec::with_capacity(n_i * n_j);
    for i in 0..n_i {
        if i % 2 == 0 {
            out.extend((0..n_j).map(|j| (i, j)));
        } else {
            out.extend((0..n_j).rev().map(|j| (i, j)));
        }
    }
    out
}

/// Places grid cells as poses: cell `(i, j)` is the seed translated by `step_m * (i, j, 0)` in
/// world x (i) and y (j); orientation is the seed's.
pub fn grid_poses(seed: &Rigid3, cells: &[(usize, usize)], step_m: f32) -> Vec<Rigid3> {
    cells.iter().map(|&(i, j)| grid_pose(seed, i as i32, j as i32, step_m)).collect()
}

/// The pose of grid cell `(i, j)`: the seed moved `i * step_m` along world x and `j * step_m`
/// along world y, same orientation. The one cell -> pose mapping of the grid trajectories and
/// the greedy planner.
pub fn grid_pose(seed: &Rigid3, i: i32, j: i32, step_m: f32) -> Rigid3 {
    Rigid3::new(seed.rotation, seed.translation + Vec3::new(i as f32 * step_m, j as f32 * step_m, 0.0))
}

/// `n` poses along a straight line from the seed: the horizontal projection of the seed's optical
/// axis (or world +x when the camera looks straight down), `step_m` apart.
pub fn line_poses(seed: &Rigid3, n: usize, step_m: f32) -> Vec<Rigid3> {
    let fwd = horizontal_forward(seed);
    (0..n).map(|k| Rigid3::new(seed.rotation, seed.translation + fwd * (k as f32 * step_m))).collect()
}

/// `n` poses on a circle of radius `radius_m` in the horizontal plane, starting at the seed and
/// turning the camera about world up so its view turns with the path (one full turn).
pub fn circle_poses(seed: &Rigid3, n: usize, radius_m: f32) -> Vec<Rigid3> {
    let fwd = horizontal_forward(seed);
    let centre = seed.translation + Vec3::new(-fwd.y, fwd.x, 0.0) * radius_m;
    let n_f = n.max(1) as f32;
    (0..n)
        .map(|k| {
            let angle = std::f32::consts::TAU * k as f32 / n_f;
            let rot = Mat3::from_rotation_z(angle);
            let p = centre + rot * (seed.translation - centre);
            Rigid3::new(rot * seed.rotation, p)
        })
        .collect()
}

/// `n` poses on an outward Archimedean spiral in the horizontal plane starting at the seed;
/// consecutive poses are about `step_m` apart and the radius grows by `pitch_m` per turn.
/// Orientation is the seed's (the view keeps its heading, like the grid trajectories).
pub fn spiral_poses(seed: &Rigid3, n: usize, step_m: f32, pitch_m: f32) -> Vec<Rigid3> {
    let b = pitch_m.max(1e-3) / std::f32::consts::TAU;
    let mut theta = 0.0f32;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let r = b * theta;
        let p = seed.translation + Vec3::new(r * theta.cos(), r * theta.sin(), 0.0);
        out.push(Rigid3::new(seed.rotation, p));
        // arc length ds = sqrt(r^2 + b^2) dtheta
        theta += step_m / (r * r + b * b).sqrt().max(1e-3);
    }
    out
}

fn horizontal_forward(seed: &Rigid3) -> Vec3 {
    let z = seed.transform_vector(Vec3::Z);
    Vec3::new(z.x, z.y, 0.0).try_normalize().unwrap_or(Vec3::X)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zigzag_visits_every_cell_once_with_neighbour_steps() {
        for (ni, nj) in [(1, 1), (3, 5), (20, 20), (30, 30), (7, 2)] {
            let cells = zigzag_cells(ni, nj);
            assert_eq!(cells.len(), ni * nj);
            let mut seen = std::collections::BTreeSet::new();
            for c in &cells {
                assert!(seen.insert(*c), "cell {c:?} twice");
            }
            assert_eq!(cells[0], (0, 0));
            for w in cells.windows(2) {
                let di = w[0].0.abs_diff(w[1].0);
                let dj = w[0].1.abs_diff(w[1].1);
                assert!(di <= 1 && dj <= 1, "jump {:?} -> {:?}", w[0], w[1]);
            }
        }
        // first diagonals as in the authors' code: s=1 ascending i, s=2 descending i
        assert_eq!(&zigzag_cells(4, 4)[..6], &[(0, 0), (0, 1), (1, 0), (2, 0), (1, 1), (0, 2)]);
    }

    #[test]
    fn boustrophedon_is_contiguous() {
        let cells = boustrophedon_cells(4, 6);
        assert_eq!(cells.len(), 24);
        for w in cells.windows(2) {
            assert_eq!(w[0].0.abs_diff(w[1].0) + w[0].1.abs_diff(w[1].1), 1);
        }
    }

    #[test]
    fn circle_closes_and_spiral_steps_evenly() {
        let seed = Rigid3::look_at(Vec3::ZERO, Vec3::new(1.0, 0.0, -3.0), Vec3::Z).unwrap();
        // The seed looks along +x, so the circle turns left about the centre (0, 5, 0): every
        // pose is 5 m from it, consecutive poses are one chord 2 r sin(pi / n) apart, the last
        // pose is one chord short of the seed (the turn closes), a quarter turn is at (5, 5, 0),
        // and each camera's horizontal view direction is the path's tangent (cos a, sin a, 0).
        let (n, radius) = (40usize, 5.0f32);
        let c = circle_poses(&seed, n, radius);
        assert_eq!(c.len(), n);
        assert!((c[0].translation - seed.translation).length() < 1e-5);
        let centre = Vec3::new(0.0, radius, 0.0);
        let chord = 2.0 * radius * (std::f32::consts::PI / n as f32).sin();
        for (k, p) in c.iter().enumerate() {
            assert!(p.translation.z.abs() < 1e-5);
            let r = (p.translation - centre).length();
            assert!((r - radius).abs() < 1e-4, "pose {k}: radius {r}");
            let next = c[(k + 1) % n].translation;
            let step = (next - p.translation).length();
            assert!((step - chord).abs() < 1e-4, "pose {k} -> {}: step {step}, chord {chord}", (k + 1) % n);
            let a = std::f32::consts::TAU * k as f32 / n as f32;
            let fwd = horizontal_forward(p);
            assert!((fwd - Vec3::new(a.cos(), a.sin(), 0.0)).length() < 1e-4, "pose {k}: forward {fwd}");
            // The tilt below the horizon is the seed's (the turn is about world up only).
            let tilt = p.transform_vector(Vec3::Z).z;
            assert!((tilt - seed.transform_vector(Vec3::Z).z).abs() < 1e-5);
        }
        assert!((c[n / 4].translation - Vec3::new(radius, radius, 0.0)).length() < 1e-4, "{}", c[n / 4].translation);
        assert!((c[n / 2].translation - Vec3::new(0.0, 2.0 * radius, 0.0)).length() < 1e-4);
        let s = spiral_poses(&seed, 200, 0.4, 2.0);
        for w in s.windows(2).skip(5) {
            let d = (w[1].translation - w[0].translation).length();
            assert!((d - 0.4).abs() < 0.05, "spiral step {d}");
        }
        let l = line_poses(&seed, 10, 0.5);
        assert!((l[9].translation - Vec3::new(4.5, 0.0, 0.0)).length() < 1e-4);
    }
}
