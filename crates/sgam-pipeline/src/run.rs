//! A whole generation run: seed, then one [`WorldGenerator::step`] per pose of the run's
//! [`PoseSource`](crate::PoseSource), with snapshots for resuming. Progress display and the
//! end-of-run outputs belong to the caller, through a [`RunObserver`].

use std::path::Path;
use std::time::Instant;

use sgam_map::TsdfMap;

use crate::snapshot::{write_snapshot, SnapshotState};
use crate::tiles::{MapStreaming, TileStore};
use crate::{
    build_refiner, AnyRefiner, Keyframes, PipelineError, Result, RunConfig, Seed, StepTimings, WorldGenerator,
};

/// The generator of a run.
pub type RunGenerator = WorldGenerator<AnyRefiner>;

/// What a resumed run restores from its snapshot.
#[derive(Debug)]
pub struct Resume {
    /// The state stored with the map.
    pub state: SnapshotState,
    /// The map.
    pub map: TsdfMap,
}

/// Hooks of a run: the caller's progress display and per-step outputs. Every method has a
/// stand-in default that does nothing.
pub trait RunObserver {
    /// After the seed is fused (new runs only).
    fn after_seed(&mut self, _gen: &mut RunGenerator) -> Result<()> {
        Ok(())
    }
    /// Before the first step of this invocation: `total` cameras (seed included), `done` already.
    fn started(&mut self, _resumed: bool, _total: usize, _done: usize, _seed: &Seed) -> Result<()> {
        Ok(())
    }
    /// After each step of adapting the refiner to the seed ([`crate::adapt`]; new runs only).
    fn adapting(&mut self, _progress: &crate::adapt::AdaptProgress) -> Result<()> {
        Ok(())
    }
    /// When the adaptation is done.
    fn adapted(&mut self, _outcome: &crate::adapt::AdaptOutcome) -> Result<()> {
        Ok(())
    }
    /// After step `index` (of `total` cameras) with its timings.
    fn after_step(&mut self, _index: usize, _total: usize, _gen: &mut RunGenerator, _t: &StepTimings) -> Result<()> {
        Ok(())
    }
}

/// A run observer that does nothing.
#[derive(Debug, Clone, Copy, Default)]
pub struct Quiet;
impl RunObserver for Quiet {}

/// The state at the end of [`generate`].
#[derive(Debug)]
pub struct Generated {
    /// The generator (map and keyframes).
    pub generator: RunGenerator,
    /// One per step done (all invocations).
    pub timings: Vec<StepTimings>,
    /// `false` when the run stopped early (`stop_after`) and stays resumable.
    pub finished: bool,
    /// Steps done by this invocation.
    pub steps_this_run: usize,
    /// Wall time of this invocation's steps, seconds.
    pub wall_s: f64,
    /// The map's far part on disk ([`crate::tiles`]): the world is `generator.map` plus these
    /// tiles.
    pub streaming: MapStreaming,
}

/// The refiner a run builds: with `adapt_s`, the model [`crate::adapt`] tuned to the seed, in the
/// run folder (adapted now for a new run, read back for a resumed one).
fn adapted(
    dir: &Path,
    config: &RunConfig,
    seed: &Seed,
    resumed: bool,
    observer: &mut dyn RunObserver,
) -> Result<crate::RefinerSpec> {
    let crate::RefinerSpec::Model { model, adapt_s, .. } = &config.refiner else {
        return Ok(config.refiner.clone());
    };
    if *adapt_s <= 0.0 {
        return Ok(config.refiner.clone());
    }
    let path = crate::adapt::adapted_path(dir);
    if resumed {
        if !path.is_file() {
            return Err(PipelineError::Config(format!(
                "{}: this run was adapted to its seed (--adapt {adapt_s}) and its adapted weights are missing; start a new run",
                path.display()
            )));
        }
    } else {
        let mut failed = None;
        // round trips of the seed along this run's own path
        let trips = crate::roundtrip::round_trips(
            &seed.camera,
            &seed.frame,
            &config.trajectory,
            config.steps,
            &config.generator_config(),
            crate::adapt::ADAPT_TRIPS,
        )?;
        let outcome = crate::adapt::adapt_to_seed(
            model.as_deref(),
            seed,
            &trips,
            std::time::Duration::from_secs_f32(*adapt_s),
            &path,
            &mut |p| {
                if failed.is_none() {
                    failed = observer.adapting(&p).err();
                }
            },
        )?;
        if let Some(e) = failed {
            return Err(e);
        }
        observer.adapted(&outcome)?;
    }
    Ok(crate::adapt::adapted_spec(dir, &config.refiner))
}

/// Runs (or, with `resume`, continues) `config` in the run folder `dir`, writing a snapshot after
/// the seed, every `snapshot_every` steps and at the end; `model_crc32` is stored with it.
/// Stops after `stop_after` steps of this invocation when given.
pub fn generate(
    dir: &Path,
    config: &RunConfig,
    resume: Option<Resume>,
    model_crc32: Option<u32>,
    stop_after: Option<usize>,
    observer: &mut dyn RunObserver,
) -> Result<Generated> {
    let seed = config.seed.load()?;
    // the path is checked before anything is written
    let total = config.trajectory.total_cameras(&seed.camera, config.steps)?;
    let refiner = build_refiner(&adapted(dir, config, &seed, resume.is_some(), observer)?, &seed)?;
    let gconfig = config.generator_config();
    gconfig.tsdf.validate()?;
    let mut keyframes = Keyframes::new(dir, gconfig.source_radius_m, 96);
    let resumed = resume.is_some();
    let (map, mut timings, tile_index) = match resume {
        Some(mut r) => {
            for c in &r.state.cameras {
                keyframes.push_camera(*c);
            }
            // the map file does not store the threshold: the run's configuration holds it
            r.map.set_weight_threshold(gconfig.tsdf.weight_threshold);
            (r.map, r.state.timings, r.state.tiles)
        }
        None => (TsdfMap::new(gconfig.tsdf), Vec::new(), Default::default()),
    };
    let tiles = TileStore::open(dir, gconfig.tsdf, &tile_index)?;
    // the no-map ablation rebuilds its map every step: nothing to bound
    let max_map_mb = if config.no_map { 0 } else { config.max_map_mb };
    let mut streaming = MapStreaming::new(max_map_mb, config.stream_margin_m(), !config.trajectory.reads_map(), tiles);
    let mut map = map;
    if resumed {
        streaming.mend_borders(&mut map)?;
    }
    let mut generator = WorldGenerator::new(map, keyframes, refiner, gconfig);
    generator.keep_guidance(config.outputs.guidance_png);
    // the map's state on disk: its resident part in the snapshot, the rest in the tiles it
    // names; the files of tiles taken back go once the snapshot no longer names them
    let snapshot = |generator: &RunGenerator, timings: &[StepTimings], streaming: &mut MapStreaming| {
        let state = SnapshotState {
            config: config.clone(),
            cameras: generator.keyframes.cameras().to_vec(),
            timings: timings.to_vec(),
            model_crc32,
            tiles: streaming.tiles.index(),
        };
        write_snapshot(dir, &state, &generator.map)?;
        streaming.tiles.committed()
    };
    if !resumed {
        generator.seed(&seed.camera, seed.frame.clone())?;
        observer.after_seed(&mut generator)?;
        // a snapshot from the start: a run killed before its first snapshot interval is resumable
        snapshot(&generator, &timings, &mut streaming)?;
    }
    let done = generator.keyframes.len();
    let mut poses = config.trajectory.pose_source(&seed.camera, config.steps, generator.keyframes.cameras())?;
    observer.started(resumed, total, done, &seed)?;
    let start = Instant::now();
    let mut this_run = 0usize;
    let mut finished = false;
    for i in done..total {
        // what the pose source may read around the last camera, then what the step may read
        // and write around the next, is in memory
        let last = generator.keyframes.cameras().last().copied();
        streaming.bring_near(&mut generator.map, &last.into_iter().collect::<Vec<_>>())?;
        let Some(camera) = poses.next_camera(&mut generator.map) else { break };
        streaming.bring_near(&mut generator.map, &[camera])?;
        let t = generator.step(&camera).map_err(|e| PipelineError::Step { index: i, source: Box::new(e) })?;
        streaming.let_go_far(&mut generator.map, &camera)?;
        timings.push(t);
        this_run += 1;
        observer.after_step(i, total, &mut generator, &t)?;
        finished = i + 1 == total;
        let stopping = stop_after.is_some_and(|n| this_run >= n);
        if finished || stopping || i % config.outputs.snapshot_every == 0 {
            snapshot(&generator, &timings, &mut streaming)?;
        }
        if stopping && !finished {
            break;
        }
    }
    // a greedy walk that ran out of cells ends the run too
    let stopped_early = stop_after.is_some_and(|n| this_run >= n) && !finished;
    Ok(Generated {
        generator,
        timings,
        finished: !stopped_early,
        steps_this_run: this_run,
        wall_s: start.elapsed().as_secs_f64(),
        streaming,
    })
}
