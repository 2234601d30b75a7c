//! A run's snapshot (`RUN/snapshot.bin`): the resolved [`RunConfig`], the keyframe cameras, the
//! step timings and the model file's CRC-32 as JSON, then the map, in `sgam-io`'s versioned,
//! checksummed container ([`sgam_io::write_snapshot`]).

use std::path::Path;

use serde::{Deserialize, Serialize};
use sgam_core::Camera;
use sgam_map::TsdfMap;

use crate::config::MAX_STEPS;
use crate::poses::MAX_EXTENT_M;
use crate::{Keyframes, PipelineError, Result, RunConfig, StepTimings};

/// Format of `snapshot.bin`. Version 1 had no version field and no checksum over the state;
/// version 2 stored the command line's arguments; version 3 stores the resolved [`RunConfig`].
pub const SNAPSHOT_VERSION: u32 = 3;
/// The snapshot's file name in the run folder.
pub const SNAPSHOT_FILE: &str = "snapshot.bin";

/// What a snapshot holds besides the map.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SnapshotState {
    /// The run, resolved.
    pub config: RunConfig,
    /// Keyframes (= steps done + 1 for the seed).
    pub cameras: Vec<Camera>,
    /// One per step done.
    pub timings: Vec<StepTimings>,
    /// CRC-32 of the model file the run uses (`None` for the stand-ins): a resumed run refuses a
    /// file that changed since.
    pub model_crc32: Option<u32>,
    /// The map's tiles on disk ([`crate::tiles`]); none in runs written before they existed.
    #[serde(default)]
    pub tiles: crate::tiles::TileIndex,
}

/// Writes `dir/snapshot.bin` atomically.
pub fn write_snapshot(dir: &Path, state: &SnapshotState, map: &TsdfMap) -> Result<()> {
    let path = dir.join(SNAPSHOT_FILE);
    let json = serde_json::to_vec(state)
        .map_err(|e| PipelineError::Corrupt { path: path.clone(), msg: format!("serialising the state: {e}") })?;
    sgam_io::write_snapshot_with(&path, SNAPSHOT_VERSION, &json, |w| {
        map.write_to(&mut std::io::BufWriter::with_capacity(1 << 20, w)).map_err(std::io::Error::other)
    })?;
    Ok(())
}

/// Parses snapshot `bytes` (`path` names the file in errors): the container (format version,
/// checksum over the whole file), the state's JSON, the map.
pub fn parse_snapshot(path: &Path, bytes: &[u8]) -> Result<(SnapshotState, TsdfMap)> {
    let (json, payload) = sgam_io::parse_snapshot(path, bytes, SNAPSHOT_VERSION)?;
    let state = parse_state(path, json)?;
    let map = TsdfMap::read_from(&mut &payload[..])
        .map_err(|e| PipelineError::Corrupt { path: path.to_path_buf(), msg: format!("corrupt map: {e}") })?;
    Ok((state, map))
}

/// The state's JSON of the snapshot at `path`.
fn parse_state(path: &Path, json: &[u8]) -> Result<SnapshotState> {
    serde_json::from_slice(json)
        .map_err(|e| PipelineError::Corrupt { path: path.to_path_buf(), msg: format!("corrupt state: {e}") })
}

/// The resolved configuration of the run in `dir`, from its snapshot (checked as a whole; the
/// map is not parsed).
pub fn read_run_config(dir: &Path) -> Result<RunConfig> {
    let path = dir.join(SNAPSHOT_FILE);
    if !path.is_file() {
        return Err(PipelineError::Config(format!(
            "{}: no snapshot (is {} a run folder of sgam generate?)",
            path.display(),
            dir.display()
        )));
    }
    let (json, _) = sgam_io::read_snapshot(&path, SNAPSHOT_VERSION)?;
    let state = parse_state(&path, &json)?;
    state
        .config
        .validate()
        .map_err(|e| PipelineError::Corrupt { path: path.clone(), msg: format!("stored configuration: {e}") })?;
    Ok(state.config)
}

/// Reads and validates `dir/snapshot.bin`: the file ([`parse_snapshot`]), then its content (the
/// configuration, rigid finite cameras of one size, one timing per step, the frames on disk).
pub fn read_snapshot(dir: &Path) -> Result<(SnapshotState, TsdfMap)> {
    let path = dir.join(SNAPSHOT_FILE);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(PipelineError::Config(format!(
                "{}: no snapshot to resume from (is {} a run folder?)",
                path.display(),
                dir.display()
            )))
        }
        Err(e) => return Err(sgam_io::IoError::Io { path, source: e }.into()),
    };
    let (state, map) = parse_snapshot(&path, &bytes)?;
    let bad = |msg: String| PipelineError::Corrupt { path: path.clone(), msg };
    state.config.validate().map_err(|e| bad(format!("stored configuration: {e}")))?;
    let Some(first) = state.cameras.first() else { return Err(bad("no keyframe".into())) };
    let steps = state.config.steps.min(MAX_STEPS);
    if state.cameras.len() > steps + 1 || state.timings.len() + 1 != state.cameras.len() {
        return Err(bad(format!(
            "{} keyframes and {} step timings for a run of {} steps",
            state.cameras.len(),
            state.timings.len(),
            state.config.steps
        )));
    }
    for (i, c) in state.cameras.iter().enumerate() {
        let rigid = c.world_from_camera.is_finite()
            && sgam_core::Rigid3::try_from_rows(c.world_from_camera.to_rows()).is_ok()
            && c.world_from_camera.translation.abs().max_element() <= MAX_EXTENT_M;
        if !rigid || c.intrinsics != first.intrinsics {
            return Err(bad(format!("keyframe {i}: not a rigid pose in range, or another image size")));
        }
        let (rgb, depth) = Keyframes::frame_paths(dir, i);
        for f in [rgb, depth] {
            if !f.is_file() {
                return Err(bad(format!("keyframe {i}: {} is missing", f.display())));
            }
        }
    }
    Ok((state, map))
}

/// Saves `map` alone (the map's own versioned format) to `path`, atomically.
pub fn save_map(path: &Path, map: &TsdfMap) -> Result<()> {
    let mut bytes = Vec::new();
    map.write_to(&mut bytes)?;
    sgam_io::write_atomic(path, |w| std::io::Write::write_all(w, &bytes))?;
    Ok(())
}
