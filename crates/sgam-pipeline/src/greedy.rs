//! The greedy next-pose choice (`--trajectory greedy`).
//!
//! Definition (the paper names the strategy without pinning it down; this is ours): poses live
//! on the same `grid x grid` lattice as the zig-zag, `step` apart, starting at the seed's cell.
//! At every step the candidates are the unvisited lattice cells among the 8 neighbours of the
//! current cell; each candidate's camera renders the current map at low resolution (64 px wide),
//! and the candidate whose render covers the most pixels wins — the pose with the most context,
//! whose completion is therefore the best constrained. Ties go to the lower `(i, j)`. When every
//! neighbour is visited, the nearest unvisited cell that touches the visited region (a frontier
//! cell) is chosen instead, so the walk never stalls while the grid has room. Deterministic for a
//! given map, and resumable: the visited set is rebuilt from the poses generated so far.

use std::collections::HashSet;

use sgam_core::{Camera, Intrinsics, Rigid3};
use sgam_map::TsdfMap;

use crate::error::config_error;
use crate::poses::PoseSource;
use crate::Result;

/// Width of the coverage renders.
const SCORE_WIDTH: u32 = 64;

/// Chooses each next pose from the map as it grows.
#[derive(Debug, Clone)]
pub struct GreedyPlanner {
    seed: Rigid3,
    intrinsics: Intrinsics,
    step_m: f32,
    side: i32,
    visited: HashSet<(i32, i32)>,
    current: (i32, i32),
}

impl GreedyPlanner {
    /// A planner over a `side x side` lattice whose cell `(0, 0)` is the seed pose; `done` are
    /// the poses generated so far (seed first), used to restore the visited set on resume.
    pub fn new(seed: &Camera, step_m: f32, side: usize, done: &[Camera]) -> Result<Self> {
        if !(step_m.is_finite() && step_m > 0.0) {
            config_error!("--step {step_m} must be a positive distance in metres");
        }
        let mut p = Self {
            seed: seed.world_from_camera,
            intrinsics: seed.intrinsics,
            step_m,
            side: side.max(2) as i32,
            visited: HashSet::new(),
            current: (0, 0),
        };
        p.visited.insert((0, 0));
        for c in done.iter().skip(1) {
            let cell = p.cell_of(&c.world_from_camera);
            p.visited.insert(cell);
            p.current = cell;
        }
        Ok(p)
    }

    fn cell_of(&self, pose: &Rigid3) -> (i32, i32) {
        let d = (pose.translation - self.seed.translation) / self.step_m;
        (d.x.round() as i32, d.y.round() as i32)
    }

    fn pose_of(&self, (i, j): (i32, i32)) -> Rigid3 {
        sgam_core::trajectory::grid_pose(&self.seed, i, j, self.step_m)
    }

    fn in_grid(&self, (i, j): (i32, i32)) -> bool {
        (0..self.side).contains(&i) && (0..self.side).contains(&j)
    }

    fn free(&self, cell: (i32, i32)) -> bool {
        self.in_grid(cell) && !self.visited.contains(&cell)
    }

    /// Cells left to visit.
    #[cfg(test)]
    fn remaining(&self) -> usize {
        (self.side * self.side) as usize - self.visited.len()
    }

    /// Pixels of the map's render at `cell` (low resolution) that hit a front-facing surface.
    fn coverage(&self, map: &mut TsdfMap, cell: (i32, i32)) -> usize {
        let k = &self.intrinsics;
        let h = ((SCORE_WIDTH as f32 * k.height as f32 / k.width.max(1) as f32).round() as u32).max(1);
        let cam = Camera::new(k.resized(SCORE_WIDTH, h), self.pose_of(cell));
        let r = map.remesh_and_rasterize(&cam);
        r.covered.iter().zip(&r.back_facing).filter(|(c, b)| **c && !**b).count()
    }

    /// The next camera (full resolution), or `None` when the grid is exhausted.
    pub fn next(&mut self, map: &mut TsdfMap) -> Option<Camera> {
        let (ci, cj) = self.current;
        let mut neighbours: Vec<(i32, i32)> = (-1..=1)
            .flat_map(|di| (-1..=1).map(move |dj| (ci + di, cj + dj)))
            .filter(|&c| c != self.current && self.free(c))
            .collect();
        neighbours.sort_unstable();
        let choice = if neighbours.is_empty() {
            self.nearest_frontier()?
        } else {
            let mut best = (neighbours[0], self.coverage(map, neighbours[0]));
            for &c in &neighbours[1..] {
                let s = self.coverage(map, c);
                if s > best.1 {
                    best = (c, s);
                }
            }
            best.0
        };
        self.visited.insert(choice);
        self.current = choice;
        Some(Camera::new(self.intrinsics, self.pose_of(choice)))
    }

    /// The unvisited cell 4-adjacent to a visited one that lies nearest the current cell.
    fn nearest_frontier(&self) -> Option<(i32, i32)> {
        let mut frontier: Vec<(i32, i32)> = self
            .visited
            .iter()
            .flat_map(|&(i, j)| [(i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)])
            .filter(|&c| self.free(c))
            .collect();
        frontier.sort_unstable();
        frontier.dedup();
        let (ci, cj) = self.current;
        frontier.into_iter().min_by_key(|&(i, j)| ((i - ci).pow(2) + (j - cj).pow(2), i, j))
    }
}

impl PoseSource for GreedyPlanner {
    fn next_camera(&mut self, map: &mut TsdfMap) -> Option<Camera> {
        self.next(map)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sgam_map::TsdfConfig;

    fn seed_camera() -> Camera {
        let k = Intrinsics { width: 32, height: 32, fx: 30.0, fy: 30.0, cx: 16.0, cy: 16.0 };
        Camera::new(k, Rigid3::IDENTITY)
    }

    #[test]
    fn visits_every_cell_once_through_neighbours_or_the_frontier() {
        let mut map = TsdfMap::new(TsdfConfig::default());
        let seed = seed_camera();
        let mut p = GreedyPlanner::new(&seed, 0.5, 4, &[seed]).unwrap();
        let mut cells = vec![(0, 0)];
        while let Some(c) = p.next(&mut map) {
            let cell = p.cell_of(&c.world_from_camera);
            assert!(!cells.contains(&cell), "{cell:?} visited twice");
            // every new cell touches the region visited before it
            assert!(cells.iter().any(|&(i, j)| (i - cell.0).abs() <= 1 && (j - cell.1).abs() <= 1));
            cells.push(cell);
        }
        assert_eq!(cells.len(), 16);
        assert_eq!(p.remaining(), 0);
    }

    #[test]
    fn resuming_from_the_poses_so_far_continues_the_same_walk() {
        let mut map = TsdfMap::new(TsdfConfig::default());
        let seed = seed_camera();
        let mut a = GreedyPlanner::new(&seed, 0.5, 5, &[seed]).unwrap();
        let mut done = vec![seed];
        for _ in 0..7 {
            done.push(a.next(&mut map).unwrap());
        }
        let mut b = GreedyPlanner::new(&seed, 0.5, 5, &done).unwrap();
        for _ in 0..10 {
            assert_eq!(a.next(&mut map), b.next(&mut map));
        }
    }

    #[test]
    fn the_neighbour_with_the_most_context_wins() {
        // a plane 2 m ahead, observed only in the right half of the seed view (x > 0): moving
        // along +x keeps more of it in view than moving along +y, which comes first in the
        // tie-break order
        let seed = seed_camera();
        let mut map = TsdfMap::new(TsdfConfig { voxel_size_m: 0.05, ..TsdfConfig::default() });
        let mut frame = sgam_core::RgbdFrame {
            colour: sgam_core::Image::filled(32, 32, [0.5f32; 3]),
            depth_m: sgam_core::Image::filled(32, 32, 0.0f32),
        };
        for v in 0..32 {
            for u in 16..32 {
                *frame.depth_m.at_mut(u, v) = 2.0;
            }
        }
        map.integrate(&frame, &seed);
        let mut p = GreedyPlanner::new(&seed, 0.5, 4, &[seed]).unwrap();
        let first = p.next(&mut map).unwrap();
        assert_eq!(p.cell_of(&first.world_from_camera), (1, 0));
    }

    #[test]
    fn bad_step_is_an_error() {
        let seed = seed_camera();
        assert!(GreedyPlanner::new(&seed, 0.0, 5, &[seed]).is_err());
        assert!(GreedyPlanner::new(&seed, f32::NAN, 5, &[seed]).is_err());
    }
}
