//! The worlds `sgam eval world` judges: each grown once by `sgam generate` (the refiner's and the
//! oracle's, along the same path) into `OUT/seed-N/LABEL`, reused while complete and grown the
//! same way, and the loop-consistency runs.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use sgam_pipeline::settings::{OutputArgs, PathSettings, RefinerKind, RefinerSettings, TrajectoryKind};
use sgam_pipeline::RunSettings;

use crate::eval_world::WorldArgs;
use crate::generate::GenerateArgs;

/// The run of one of this evaluation's worlds: the refiner of `kind` with the evaluated options
/// (the oracle takes none of the refiner's), along the evaluated path, no fly-through.
fn run_settings(args: &WorldArgs, kind: RefinerKind, seed_scene: u64, steps: usize) -> RunSettings {
    let mut run = RunSettings {
        steps,
        path: args.path.clone(),
        map: args.map.clone(),
        outputs: OutputArgs { no_video: true, ..OutputArgs::default() },
        ..RunSettings::clevr(seed_scene)
    };
    if kind == RefinerKind::Oracle {
        run.refiner = RefinerSettings::kind(RefinerKind::Oracle);
        run.map.no_map = false; // an ablation of the refiner's world, not the true one
    } else {
        run.refiner = args.refiner.clone();
        run.sampling = args.sampling.clone();
        run.invented = args.invented.clone();
    }
    run
}

/// Grows (or reuses) one world; returns its folder.
pub fn grow(args: &WorldArgs, seed_scene: u64, kind: RefinerKind, label: &str, root: &Path) -> Result<PathBuf> {
    let (_, steps) = args.seeds_steps();
    let dir = root.join(format!("seed-{seed_scene}")).join(label);
    if dir.join("run.json").exists() && dir.join("mesh.ply").exists() {
        let run: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("run.json"))?)
            .with_context(|| format!("{}: corrupt run.json", dir.display()))?;
        // reuse only a world grown the same way: the resolved run (seed, trajectory, steps,
        // ablations, sampling) equal to the one these options give; the model file may differ
        let want = run_settings(args, kind, seed_scene, steps).resolve()?;
        let stored: Option<sgam_pipeline::RunConfig> = serde_json::from_value(run["config"].clone()).ok();
        if stored.is_none() {
            bail!(
                "{}: run.json holds no resolved run config (grown by an older sgam); remove the folder or choose another --out",
                dir.display()
            );
        }
        // the whole resolved run, but for the model file (the label names its weights), what
        // was written besides the frames, and the bound on the map's memory (the frames are the
        // same with any bound): a new field of the run is compared without a change here
        let comparable = |r: &sgam_pipeline::RunConfig| sgam_pipeline::RunConfig {
            refiner: match &r.refiner {
                sgam_pipeline::RefinerSpec::Model { options, bank, .. } => sgam_pipeline::RefinerSpec::Model {
                    model: None,
                    options: *options,
                    bank: bank.clone(),
                    adapt_s: 0.0,
                },
                other => other.clone(),
            },
            outputs: want.outputs,
            max_map_mb: want.max_map_mb,
            ..r.clone()
        };
        let same = run["steps"].as_u64() == Some(steps as u64)
            && stored.is_some_and(|got| comparable(&got) == comparable(&want));
        if same {
            if !args.keep_snapshots {
                drop_resume_files(&dir)?;
            }
            return Ok(dir);
        }
        bail!(
            "{} holds a world grown with other options (steps, trajectory, step, temperature, cells per pass, top-k, within-class temperature, ground prior, flying pixels, free space, map or ablations); \
             remove it or choose another --out",
            dir.display()
        );
    }
    if dir.join("snapshot.bin").exists() {
        crate::generate::run(GenerateArgs::resume(dir.clone()))?;
    } else {
        crate::generate::run(GenerateArgs::new(run_settings(args, kind, seed_scene, steps), Some(dir.clone())))?;
    }
    if !args.keep_snapshots {
        drop_resume_files(&dir)?;
    }
    Ok(dir)
}

/// Deletes a finished world's resume files (its snapshot and map); the world stays reusable
/// from its mesh, frames and run.json.
fn drop_resume_files(dir: &Path) -> Result<()> {
    if !dir.join("mesh.ply").exists() {
        return Ok(());
    }
    for name in [sgam_pipeline::snapshot::SNAPSHOT_FILE, "map.bin"] {
        match std::fs::remove_file(dir.join(name)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(e).with_context(|| format!("{}: cannot delete {name}", dir.display()))
            }
            _ => {}
        }
    }
    Ok(())
}

/// Steps of the loop trajectory of the consistency check.
pub const LOOP_STEPS: usize = 48;

/// Consistency on revisits: a circle of radius 3 m that starts at the seed and returns to it
/// (`LOOP_STEPS` poses around, then the seed pose again); PSNR and SSIM of the final frame,
/// generated at the seed pose after a full loop, against the seed frame.
pub fn loop_consistency(
    args: &WorldArgs,
    seed_scene: u64,
    kind: RefinerKind,
    label: &str,
    root: &Path,
) -> Result<(f64, f64)> {
    let dir = root.join(format!("seed-{seed_scene}")).join(format!("{label}-loop"));
    let last = sgam_pipeline::Keyframes::frame_paths(&dir, LOOP_STEPS).0;
    if !(dir.join("run.json").exists() && last.exists()) {
        if dir.exists() {
            std::fs::remove_dir_all(&dir)
                .with_context(|| format!("{}: cannot clear an unfinished loop run", dir.display()))?;
        }
        std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
        let seed = sgam_pipeline::synthetic_seed_camera(256);
        let mut poses = sgam_core::trajectory::circle_poses(&seed.world_from_camera, LOOP_STEPS, 3.0);
        poses.push(seed.world_from_camera);
        let traj = root.join(format!("seed-{seed_scene}")).join("loop-kitti.txt");
        sgam_io::write_kitti_trajectory(&traj, &poses)?;
        let mut run = run_settings(args, kind, seed_scene, LOOP_STEPS);
        run.path = PathSettings { trajectory_file: Some(traj), ..PathSettings::kind(TrajectoryKind::File) };
        crate::generate::run(GenerateArgs::new(run, Some(dir.join("run"))))?;
        for name in ["run.json", "rgb"] {
            std::fs::rename(dir.join("run").join(name), dir.join(name))
                .with_context(|| format!("{}: cannot keep the loop's {name}", dir.display()))?;
        }
        std::fs::remove_dir_all(dir.join("run")).with_context(|| format!("{}: cannot tidy", dir.display()))?;
    }
    let first = sgam_io::read_rgb(&sgam_pipeline::Keyframes::frame_paths(&dir, 0).0)?;
    let back = sgam_io::read_rgb(&last)?;
    Ok((
        sgam_metrics::psnr(&back, &first, None).unwrap_or(f64::NAN),
        sgam_metrics::ssim(&back, &first, None).unwrap_or(f64::NAN),
    ))
}
