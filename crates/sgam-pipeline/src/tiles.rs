//! A run's map in bounded memory (issue 29): super-blocks far from the camera go to tiles on
//! disk (`RUN/tiles/`) and come back before a step can read or write them.
//!
//! - **When**: after a step, once the map's memory passes the run's bound (`--max-map-mb`),
//!   every super-block farther than two margins from what a step at the camera may read or
//!   write goes. That region is the step's view ([`TsdfMap::view_reach`]: its frustum out to
//!   `--depth-max`, grown by the truncation band and two block diagonals), or, when the poses
//!   read the map (the greedy planner renders views around the camera), the sphere of the map's
//!   [`TsdfMap::reach_m`]. Before a step, every tile within one margin of the region of the
//!   previous and of the next camera comes back. A step therefore reads and writes exactly what
//!   it would have with no bound: the frames are byte-identical (tested), and the mesh a revisit
//!   sees is the one it left.
//! - **Files**: one per tile, `X_Y_Z-G.tile` in the map's own checksummed tile format
//!   ([`sgam_map::write_tile`]), written atomically. A file is never overwritten: each
//!   eviction writes a new generation `G`. The snapshot stores the index of the tiles away
//!   ([`TileIndex`]); files a restore no longer needs are deleted only once a newer snapshot is
//!   on disk ([`TileStore::committed`]), and a resumed run deletes the files its snapshot does
//!   not name (written after it). So a run killed at any moment resumes with exactly the map
//!   its snapshot saw.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::IVec3;
use serde::{Deserialize, Serialize};
use sgam_core::Camera;
use sgam_map::{EvictedBlock, TsdfConfig, TsdfMap};

use crate::{PipelineError, Result};

/// The tiles' folder in the run folder.
pub const TILES_DIR: &str = "tiles";
/// Default bound on the map's memory, MB (`--max-map-mb`).
pub const DEFAULT_MAX_MAP_MB: usize = 512;

/// One tile away on disk.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileEntry {
    /// Super-block key.
    pub key: [i32; 3],
    /// Generation of its file (unique in the run).
    pub generation: u64,
    /// Blocks it holds.
    pub blocks: u32,
    /// Triangles of its blocks' meshes.
    pub triangles: u64,
    /// File size, bytes.
    pub bytes: u64,
}

impl TileEntry {
    /// The tile's file name.
    pub fn file_name(&self) -> String {
        let [x, y, z] = self.key;
        format!("{x}_{y}_{z}-{}.tile", self.generation)
    }
}

/// The tiles away from memory, as a snapshot stores them.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TileIndex {
    /// The next file's generation.
    pub next_generation: u64,
    /// The tiles, by key.
    pub tiles: Vec<TileEntry>,
}

/// The tiles of a run folder.
#[derive(Debug)]
pub struct TileStore {
    dir: PathBuf,
    config: TsdfConfig,
    entries: BTreeMap<[i32; 3], TileEntry>,
    next_generation: u64,
    /// Files no tile needs any more, deleted after the next snapshot.
    garbage: Vec<PathBuf>,
}

impl TileStore {
    /// The tiles of the run in `run_dir` for a map of `config`, as `index` (from the run's
    /// snapshot; empty for a new run) names them. Files in the folder that the index does not
    /// name (written after that snapshot, or left by a killed write) are deleted; a named file
    /// that is missing is an error naming it.
    pub fn open(run_dir: &Path, config: TsdfConfig, index: &TileIndex) -> Result<Self> {
        let dir = run_dir.join(TILES_DIR);
        let mut entries = BTreeMap::new();
        for e in &index.tiles {
            if e.generation >= index.next_generation || entries.insert(e.key, e.clone()).is_some() {
                return Err(PipelineError::Corrupt {
                    path: dir.clone(),
                    msg: format!("the snapshot's tile index names tile {:?} twice or out of order", e.key),
                });
            }
        }
        let store = Self { dir, config, entries, next_generation: index.next_generation, garbage: Vec::new() };
        if store.dir.is_dir() {
            let named: std::collections::HashSet<String> = store.entries.values().map(TileEntry::file_name).collect();
            let listing = std::fs::read_dir(&store.dir)
                .map_err(|e| sgam_io::IoError::Io { path: store.dir.clone(), source: e })?;
            for f in listing {
                let f = f.map_err(|e| sgam_io::IoError::Io { path: store.dir.clone(), source: e })?;
                let name = f.file_name().to_string_lossy().into_owned();
                let ours = name.ends_with(".tile") || name.contains(".tile.tmp-");
                if ours && !named.contains(&name) {
                    std::fs::remove_file(f.path()).map_err(|e| sgam_io::IoError::Io { path: f.path(), source: e })?;
                }
            }
        }
        for e in store.entries.values() {
            let path = store.dir.join(e.file_name());
            if !path.is_file() {
                return Err(PipelineError::Corrupt {
                    path,
                    msg: "a tile of the map that the snapshot names is missing; the run cannot resume".into(),
                });
            }
        }
        Ok(store)
    }

    /// The index to store in a snapshot.
    pub fn index(&self) -> TileIndex {
        TileIndex { next_generation: self.next_generation, tiles: self.entries.values().cloned().collect() }
    }

    /// Tiles away.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True when no tile is away.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The tiles away, by key.
    pub fn entries(&self) -> impl Iterator<Item = &TileEntry> {
        self.entries.values()
    }

    /// Bytes of the tiles away on disk.
    pub fn disk_bytes(&self) -> u64 {
        self.entries.values().map(|e| e.bytes).sum()
    }

    /// Writes super-block `skey`'s `blocks` (from [`TsdfMap::evict_super_blocks`]) to a new
    /// file.
    pub fn put(&mut self, skey: IVec3, blocks: &[EvictedBlock]) -> Result<()> {
        let key = skey.to_array();
        if self.entries.contains_key(&key) {
            return Err(PipelineError::Config(format!("tile {key:?} is already on disk")));
        }
        let entry = TileEntry {
            key,
            generation: self.next_generation,
            blocks: blocks.len() as u32,
            triangles: blocks.iter().map(|b| b.triangle_count() as u64).sum(),
            bytes: 0,
        };
        let mut bytes = Vec::new();
        sgam_map::write_tile(&mut bytes, &self.config, skey, blocks)?;
        let path = self.dir.join(entry.file_name());
        sgam_io::write_atomic(&path, |w| std::io::Write::write_all(w, &bytes))?;
        self.next_generation += 1;
        self.entries.insert(key, TileEntry { bytes: bytes.len() as u64, ..entry });
        Ok(())
    }

    /// The blocks of tile `entry`, read and checked (the file stays).
    pub fn read(&self, entry: &TileEntry) -> Result<Vec<EvictedBlock>> {
        let path = self.dir.join(entry.file_name());
        let bytes = std::fs::read(&path).map_err(|e| sgam_io::IoError::Io { path: path.clone(), source: e })?;
        let bad = |msg: String| PipelineError::Corrupt { path: path.clone(), msg };
        let (key, blocks) = sgam_map::read_tile(&bytes, &self.config).map_err(|e| bad(format!("damaged tile: {e}")))?;
        if key.to_array() != entry.key || blocks.len() != entry.blocks as usize {
            return Err(bad(format!(
                "holds super-block {key} with {} blocks, not the tile the index names",
                blocks.len()
            )));
        }
        Ok(blocks)
    }

    /// Takes tile `key` back from disk: its blocks, and the tile leaves the index (its file is
    /// deleted after the next snapshot).
    pub fn take(&mut self, key: [i32; 3]) -> Result<Option<Vec<EvictedBlock>>> {
        let Some(entry) = self.entries.get(&key).cloned() else { return Ok(None) };
        let blocks = self.read(&entry)?;
        self.entries.remove(&key);
        self.garbage.push(self.dir.join(entry.file_name()));
        Ok(Some(blocks))
    }

    /// After a snapshot that stores [`Self::index`] is on disk: deletes the files no tile needs.
    pub fn committed(&mut self) -> Result<()> {
        for path in self.garbage.drain(..) {
            match std::fs::remove_file(&path) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(sgam_io::IoError::Io { path: path.clone(), source: e }.into()),
            }
        }
        Ok(())
    }
}

/// Distance from `p` to the box `(lo, hi)`.
fn box_distance(p: glam::Vec3, (lo, hi): (glam::Vec3, glam::Vec3)) -> f32 {
    (p - p.clamp(lo, hi)).length()
}

/// The run's policy over its map's memory: what goes to tiles and what comes back.
#[derive(Debug)]
pub struct MapStreaming {
    max_bytes: usize,
    margin_m: f32,
    view_shaped: bool,
    /// The tiles on disk.
    pub tiles: TileStore,
    /// Memory at which the next eviction is tried.
    next_trigger: usize,
    /// Super-blocks written to tiles so far (this invocation).
    pub evicted: usize,
    /// Tiles taken back so far (this invocation).
    pub restored: usize,
    /// The map's largest memory after a step (this invocation), bytes.
    pub peak_bytes: usize,
    /// Tries to go under the bound that left the map above it, because everything it held was
    /// within reach of the camera (this invocation): the bound is then too low for the view's
    /// depth (`--depth-max`) and the world's density.
    pub over_bound: usize,
}

impl MapStreaming {
    /// A policy bounding the map to `max_mb` MB over `tiles`. `margin_m` is how far beyond its
    /// reach a camera may look before it comes back: more than any step moves the camera, and
    /// than a pose source looks around it (the greedy planner renders the next cells).
    /// `view_shaped`: the run's poses do not read the map, so what a step needs is its view
    /// ([`TsdfMap::view_reach`]), not the sphere around its camera.
    pub fn new(max_mb: usize, margin_m: f32, view_shaped: bool, tiles: TileStore) -> Self {
        let max_bytes = max_mb.saturating_mul(1 << 20);
        Self {
            max_bytes,
            margin_m,
            view_shaped,
            tiles,
            next_trigger: max_bytes,
            evicted: 0,
            restored: 0,
            peak_bytes: 0,
            over_bound: 0,
        }
    }

    /// Whether super-block box `bx` lies within `margin_m` of what a step at `camera` may read
    /// or write: its grown frustum when the run's poses do not read the map, else the sphere of
    /// its reach (a planner renders views around the camera in every direction).
    fn within(&self, map: &TsdfMap, camera: &Camera, margin_m: f32) -> impl Fn((glam::Vec3, glam::Vec3)) -> bool {
        let view = self.view_shaped.then(|| map.view_reach(camera, margin_m));
        let (centre, radius) = (camera.centre_world(), map.reach_m(camera) + margin_m);
        move |bx| match &view {
            Some(v) => v.touches(bx),
            None => box_distance(centre, bx) <= radius,
        }
    }

    /// Takes back every tile within one margin of what a step at one of `cameras` may read or
    /// write.
    pub fn bring_near(&mut self, map: &mut TsdfMap, cameras: &[Camera]) -> Result<()> {
        if self.tiles.is_empty() {
            return Ok(());
        }
        let tests: Vec<_> = cameras.iter().map(|c| self.within(map, c, self.margin_m)).collect();
        let near: Vec<[i32; 3]> = self
            .tiles
            .entries()
            .map(|e| e.key)
            .filter(|&k| {
                let bx = map.super_block_box(IVec3::from_array(k));
                tests.iter().any(|near| near(bx))
            })
            .collect();
        let mut blocks = Vec::new();
        for k in near {
            blocks.extend(self.tiles.take(k)?.unwrap_or_default());
            self.restored += 1;
        }
        if !blocks.is_empty() {
            map.restore_blocks(blocks)?;
        }
        Ok(())
    }

    /// After a resume: takes back the tiles next to a resident super-block on its `+x`/`+y`/`+z`
    /// sides, then meshes the loaded blocks (all without a mesh) with them. The map file holds
    /// no meshes: without this a block whose upper neighbours were in tiles would be meshed
    /// without them (tiles far away go again at the next eviction; the frames do not change,
    /// as these blocks lie beyond every step's reach).
    pub fn mend_borders(&mut self, map: &mut TsdfMap) -> Result<()> {
        if self.tiles.is_empty() {
            return Ok(());
        }
        let resident: std::collections::HashSet<[i32; 3]> =
            map.super_block_keys().into_iter().map(|k| k.to_array()).collect();
        let next_to: Vec<[i32; 3]> = self
            .tiles
            .entries()
            .map(|e| e.key)
            .filter(|&[x, y, z]| {
                (1..8).any(|o| {
                    let below = [x.wrapping_sub(o & 1), y.wrapping_sub(o >> 1 & 1), z.wrapping_sub(o >> 2 & 1)];
                    resident.contains(&below)
                })
            })
            .collect();
        let mut blocks = Vec::new();
        for k in next_to {
            blocks.extend(self.tiles.take(k)?.unwrap_or_default());
            self.restored += 1;
        }
        if !blocks.is_empty() {
            map.restore_blocks(blocks)?;
            // the loaded blocks (all dirty) with their neighbours back; the blocks taken back
            // keep their meshes (their own neighbours may still be away)
            map.remesh_dirty_only();
        }
        Ok(())
    }

    /// When the map holds more than the bound, sends to disk every super-block farther than two
    /// margins from what a step at `camera` may read or write (one margin more than a step's
    /// [`Self::bring_near`] takes back, so a tile does not go and come back every step). If what stays is still over the bound, the next
    /// try waits until the map has grown by an eighth of the bound (each eviction rebuilds the
    /// map's index).
    pub fn let_go_far(&mut self, map: &mut TsdfMap, camera: &Camera) -> Result<()> {
        let bytes = map.memory_bytes();
        self.peak_bytes = self.peak_bytes.max(bytes);
        if self.max_bytes == 0 || bytes <= self.next_trigger {
            return Ok(());
        }
        let keep = self.within(map, camera, 2.0 * self.margin_m);
        let far: Vec<IVec3> = map.super_block_keys().into_iter().filter(|&k| !keep(map.super_block_box(k))).collect();
        if !far.is_empty() {
            let mut by_super: BTreeMap<[i32; 3], Vec<EvictedBlock>> = BTreeMap::new();
            for b in map.evict_super_blocks(&far) {
                by_super.entry(sgam_map::super_block_of(b.key).to_array()).or_default().push(b);
            }
            for (k, blocks) in by_super {
                self.tiles.put(IVec3::from_array(k), &blocks)?;
                self.evicted += 1;
            }
        }
        let after = map.memory_bytes();
        if after > self.max_bytes {
            self.over_bound += 1;
        }
        self.next_trigger = self.max_bytes.max(after + self.max_bytes / 8);
        Ok(())
    }
}
