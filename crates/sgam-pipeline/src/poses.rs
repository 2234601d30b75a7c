//! Where the camera goes next: a [`PoseSource`] gives the loop one camera per step, whether the
//! poses were computed before the run ([`PrecomputedPoses`]: zig-zag, lines, circles, spirals,
//! pose files) or are chosen from the map as it grows ([`crate::GreedyPlanner`]).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sgam_core::{trajectory, Camera, Rigid3};
use sgam_map::TsdfMap;

use crate::error::config_error;
use crate::{GreedyPlanner, Result};

/// Farthest a camera may get from the world origin, metres.
pub const MAX_EXTENT_M: f32 = 100_000.0;

/// Supplies the camera of each generation step.
pub trait PoseSource {
    /// The next camera, given the map as it stands; `None` when the path is exhausted.
    fn next_camera(&mut self, map: &mut TsdfMap) -> Option<Camera>;
}

/// Poses fixed before the run, handed out in order.
#[derive(Debug, Clone)]
pub struct PrecomputedPoses {
    cameras: Vec<Camera>,
    next: usize,
}

impl PrecomputedPoses {
    /// Hands out `cameras[start..]` (`start` = the keyframes done so far, seed included).
    pub fn new(cameras: Vec<Camera>, start: usize) -> Self {
        Self { cameras, next: start }
    }
}

impl PoseSource for PrecomputedPoses {
    fn next_camera(&mut self, _map: &mut TsdfMap) -> Option<Camera> {
        let c = self.cameras.get(self.next).copied();
        self.next += 1;
        c
    }
}

/// A camera path, resolved: every length is in metres and every default applied.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum TrajectorySpec {
    /// The SGAM authors' anti-diagonal zig-zag over a `side x side` grid, `step_m` apart.
    Zigzag {
        /// Grid side (cells).
        side: usize,
        /// Distance between neighbouring poses, metres.
        step_m: f32,
    },
    /// Lawn-mower rows over a `side x side` grid.
    Boustrophedon {
        /// Grid side (cells).
        side: usize,
        /// Distance between neighbouring poses, metres.
        step_m: f32,
    },
    /// Straight line along the seed camera's heading.
    Line {
        /// Distance between poses, metres.
        step_m: f32,
    },
    /// One full circle, turning the view with the path.
    Circle {
        /// Radius, metres.
        radius_m: f32,
    },
    /// Outward Archimedean spiral.
    Spiral {
        /// Distance between poses, metres.
        step_m: f32,
        /// Growth per turn, metres.
        radius_m: f32,
    },
    /// Poses from a file (our transforms.json, TUM or KITTI), used as given (`world_from_camera`).
    File {
        /// The pose file.
        path: PathBuf,
    },
    /// Greedy next-pose choice on the zig-zag's grid ([`GreedyPlanner`]).
    Greedy {
        /// Grid side (cells).
        side: usize,
        /// Distance between neighbouring poses, metres.
        step_m: f32,
    },
}

impl TrajectorySpec {
    /// Whether its pose source reads the map (the greedy planner renders views around the
    /// camera to choose the next pose); the others are fixed before the run.
    pub fn reads_map(&self) -> bool {
        matches!(self, TrajectorySpec::Greedy { .. })
    }

    /// The pose source of a run of `steps` steps from `seed` (index 0), continuing after the
    /// keyframes `done` (seed first; only the seed for a new run).
    pub fn pose_source(&self, seed: &Camera, steps: usize, done: &[Camera]) -> Result<Box<dyn PoseSource>> {
        if let TrajectorySpec::Greedy { side, step_m } = *self {
            return Ok(Box::new(GreedyPlanner::new(seed, step_m, side, done)?));
        }
        Ok(Box::new(PrecomputedPoses::new(self.cameras(seed, steps)?, done.len())))
    }

    /// Number of cameras of a run of `steps` steps, the seed included (a pose file may hold
    /// fewer).
    pub fn total_cameras(&self, seed: &Camera, steps: usize) -> Result<usize> {
        match self {
            TrajectorySpec::Greedy { .. } => Ok(steps + 1),
            _ => Ok(self.cameras(seed, steps)?.len()),
        }
    }

    /// The precomputed cameras: index 0 is the seed, 1..=steps are generated (greedy: only the
    /// seed; the rest are chosen while generating).
    pub fn cameras(&self, seed: &Camera, steps: usize) -> Result<Vec<Camera>> {
        let s = &seed.world_from_camera;
        if let Some(step) = self.step_m() {
            if !(step.is_finite() && step > 0.0) {
                config_error!("--step {step} must be a positive distance in metres");
            }
        }
        let n = steps + 1;
        let poses: Vec<Rigid3> = match self {
            TrajectorySpec::Zigzag { side, step_m } => {
                let cells: Vec<_> = trajectory::zigzag_cells(*side, *side).into_iter().take(n).collect();
                trajectory::grid_poses(s, &cells, *step_m)
            }
            TrajectorySpec::Boustrophedon { side, step_m } => {
                let cells: Vec<_> = trajectory::boustrophedon_cells(*side, *side).into_iter().take(n).collect();
                trajectory::grid_poses(s, &cells, *step_m)
            }
            TrajectorySpec::Greedy { .. } => return Ok(vec![*seed]),
            TrajectorySpec::Line { step_m } => trajectory::line_poses(s, n, *step_m),
            TrajectorySpec::Circle { radius_m } => trajectory::circle_poses(s, n, *radius_m),
            TrajectorySpec::Spiral { step_m, radius_m } => trajectory::spiral_poses(s, n, *step_m, *radius_m),
            TrajectorySpec::File { path } => {
                let mut poses = read_pose_file(path)?;
                if poses.is_empty() {
                    config_error!("{}: no poses", path.display());
                }
                poses.truncate(n);
                poses
            }
        };
        if poses.len() < 2 {
            config_error!("the trajectory has no pose after the seed (use --steps >= 1)");
        }
        if let Some((i, p)) = poses
            .iter()
            .enumerate()
            .find(|(_, p)| !(p.is_finite() && p.translation.abs().max_element() <= MAX_EXTENT_M))
        {
            config_error!(
                "pose {i} of the trajectory lies at {} m, beyond the {MAX_EXTENT_M} m the map covers; use a smaller \
                 --step, --radius or --steps",
                p.translation
            );
        }
        Ok(poses.into_iter().map(|p| Camera::new(seed.intrinsics, p)).collect())
    }

    fn step_m(&self) -> Option<f32> {
        match self {
            TrajectorySpec::Zigzag { step_m, .. }
            | TrajectorySpec::Boustrophedon { step_m, .. }
            | TrajectorySpec::Line { step_m }
            | TrajectorySpec::Spiral { step_m, .. }
            | TrajectorySpec::Greedy { step_m, .. } => Some(*step_m),
            TrajectorySpec::Circle { .. } | TrajectorySpec::File { .. } => None,
        }
    }
}

/// Reads a pose file: `.json` as transforms.json, otherwise TUM (8 columns) or KITTI (12
/// columns) text, told apart by the first data line.
pub fn read_pose_file(path: &Path) -> Result<Vec<Rigid3>> {
    if path.extension().is_some_and(|e| e == "json") {
        let t = sgam_io::read_nerf_transforms(path)?;
        return Ok(t.frames.iter().map(|f| f.world_from_camera).collect());
    }
    let text =
        std::fs::read_to_string(path).map_err(|e| sgam_io::IoError::Io { path: path.to_path_buf(), source: e })?;
    let cols = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| l.split_whitespace().count())
        .unwrap_or(0);
    Ok(match cols {
        8 => sgam_io::read_tum_trajectory(path)?,
        12 => sgam_io::read_kitti_trajectory(path)?,
        _ => config_error!(
            "{}: not a TUM (8 columns) or KITTI (12 columns) trajectory, nor a transforms.json",
            path.display()
        ),
    })
}
