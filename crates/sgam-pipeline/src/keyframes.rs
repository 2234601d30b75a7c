//! Generated frames kept as keyframes: cameras in RAM, pixels paged to the run folder.
//!
//! Frames are written once (`rgb/NNNNN.png`, `depth/NNNNN.npy`) and read back on demand through
//! a small LRU cache, so memory does not grow with the number of steps. Colour is quantised to
//! 8 bits before it is cached, so a cached frame equals the one read back from disk (a resumed
//! run sees exactly what an uninterrupted run saw).

use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use sgam_core::{Camera, Image, RgbdFrame};

use crate::{PipelineError, Result};

/// Quantises colour to 8 bits (what a saved PNG holds), so in-memory keyframes equal the ones
/// read back from disk after a resume.
pub fn quantise_colour(image: &mut Image<[f32; 3]>) {
    for p in &mut image.data {
        *p = p.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() / 255.0);
    }
}

/// Names of frame `index`'s colour PNG and depth NPY relative to the run folder
/// (`rgb/NNNNN.png`, `depth/NNNNN.npy`): the one place the run folder's frame layout is spelled
/// (`transforms.json` lists these names).
pub fn frame_file_names(index: usize) -> (String, String) {
    (format!("rgb/{index:05}.png"), format!("depth/{index:05}.npy"))
}

/// Keyframe index + paging cache.
#[derive(Debug)]
pub struct Keyframes {
    root: PathBuf,
    cameras: Vec<Camera>,
    cell_m: f32,
    grid: HashMap<(i32, i32), Vec<u32>>,
    cache: HashMap<usize, Arc<RgbdFrame>>,
    order: VecDeque<usize>,
    capacity: usize,
}

impl Keyframes {
    /// An empty store paging under `root`; `cell_m` sizes the spatial index (use the source
    /// radius); `capacity` frames stay cached.
    pub fn new(root: &Path, cell_m: f32, capacity: usize) -> Self {
        Self {
            root: root.to_path_buf(),
            cameras: Vec::new(),
            cell_m: cell_m.max(1e-3),
            grid: HashMap::new(),
            cache: HashMap::new(),
            order: VecDeque::new(),
            capacity: capacity.max(1),
        }
    }

    /// Paths of frame `index`'s colour PNG and depth NPY under the run folder `root`.
    pub fn frame_paths(root: &Path, index: usize) -> (PathBuf, PathBuf) {
        let (rgb, depth) = frame_file_names(index);
        (root.join(rgb), root.join(depth))
    }

    /// Number of keyframes.
    pub fn len(&self) -> usize {
        self.cameras.len()
    }

    /// Whether there is no keyframe yet (before the seed).
    pub fn is_empty(&self) -> bool {
        self.cameras.is_empty()
    }

    /// Cameras of all keyframes, in step order.
    pub fn cameras(&self) -> &[Camera] {
        &self.cameras
    }

    fn cell(&self, camera: &Camera) -> (i32, i32) {
        let p = camera.centre_world();
        ((p.x / self.cell_m).floor() as i32, (p.y / self.cell_m).floor() as i32)
    }

    /// Registers a keyframe whose pixels are already on disk (used when resuming).
    pub fn push_camera(&mut self, camera: Camera) {
        let idx = self.cameras.len();
        let c = self.cell(&camera);
        self.grid.entry(c).or_default().push(idx as u32);
        self.cameras.push(camera);
    }

    /// Writes a new keyframe's pixels and registers it; returns its index. Colour must already be
    /// quantised to 8 bits ([`quantise_colour`]) so the cached copy equals the file.
    pub fn push(&mut self, camera: Camera, frame: RgbdFrame) -> Result<usize> {
        let idx = self.cameras.len();
        let (rgb, depth) = Self::frame_paths(&self.root, idx);
        sgam_io::write_rgb_png(&rgb, &frame.colour)?;
        sgam_io::write_npy_f32(&depth, &frame.depth_m)?;
        self.push_camera(camera);
        self.insert_cache(idx, Arc::new(frame));
        Ok(idx)
    }

    /// The `k` keyframes whose camera centres lie within `radius_m` of `camera`'s, nearest first
    /// (ties by index). Looks only at nearby grid cells: cost does not grow with the run.
    pub fn nearest(&self, camera: &Camera, k: usize, radius_m: f32) -> Vec<usize> {
        let p = camera.centre_world();
        let (cx, cy) = self.cell(camera);
        let reach = (radius_m / self.cell_m).ceil() as i32;
        let mut found: Vec<(f32, usize)> = Vec::new();
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                for &i in self.grid.get(&(cx + dx, cy + dy)).map(Vec::as_slice).unwrap_or(&[]) {
                    let d = (self.cameras[i as usize].centre_world() - p).length();
                    if d <= radius_m {
                        found.push((d, i as usize));
                    }
                }
            }
        }
        found.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        found.into_iter().take(k).map(|(_, i)| i).collect()
    }

    /// The pixels of keyframe `index`, from the cache or the run folder.
    pub fn frame(&mut self, index: usize) -> Result<Arc<RgbdFrame>> {
        if let Some(f) = self.cache.get(&index).cloned() {
            // most recently used last
            if let Some(pos) = self.order.iter().position(|i| *i == index) {
                self.order.remove(pos);
                self.order.push_back(index);
            }
            return Ok(f);
        }
        let (rgb, depth) = Self::frame_paths(&self.root, index);
        let colour = sgam_io::read_rgb(&rgb)?;
        let depth_m = sgam_io::read_npy_f32(&depth)?;
        let frame =
            Arc::new(RgbdFrame::try_new(colour, depth_m).map_err(|source| PipelineError::Keyframe { index, source })?);
        self.insert_cache(index, frame.clone());
        Ok(frame)
    }

    fn insert_cache(&mut self, index: usize, frame: Arc<RgbdFrame>) {
        if self.cache.insert(index, frame).is_none() {
            self.order.push_back(index);
        }
        while self.order.len() > self.capacity {
            if let Some(old) = self.order.pop_front() {
                self.cache.remove(&old);
            }
        }
    }
}
