use crate::MapError;

/// Smallest voxel size [`TsdfConfig::validate`] accepts, metres (1 mm).
pub const MIN_VOXEL_M: f32 = 1e-3;
/// Largest voxel size [`TsdfConfig::validate`] accepts, metres.
pub const MAX_VOXEL_M: f32 = 10.0;
/// Largest truncation [`TsdfConfig::validate`] accepts, voxels.
pub const MAX_TRUNC_VOXELS: f32 = 64.0;
/// Largest depth cut [`TsdfConfig::validate`] accepts, metres.
pub const MAX_DEPTH_M: f32 = 10_000.0;

/// Parameters of a [`crate::TsdfMap`]. Defaults follow the SGAM authors' CLEVR-Infinite setup.
/// Serialisable: a run's resolved configuration stores it as its `map`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TsdfConfig {
    /// Edge length of one voxel, metres.
    pub voxel_size_m: f32,
    /// Truncation distance as a multiple of the voxel size (truncation in metres is
    /// `trunc_voxels * voxel_size_m`).
    pub trunc_voxels: f32,
    /// Depth readings below this planar depth (metres) are ignored when integrating; also the
    /// near plane of [`crate::TsdfMap::remesh_and_rasterize`] and [`crate::TsdfMap::ray_cast`].
    pub depth_min_m: f32,
    /// Depth readings above this planar depth (metres) are ignored when integrating; also the far
    /// plane of [`crate::TsdfMap::remesh_and_rasterize`] and [`crate::TsdfMap::ray_cast`].
    pub depth_max_m: f32,
    /// Optional cap on the per-voxel weight (`None` = the paper's unbounded running average).
    pub weight_cap: Option<f32>,
    /// Marching-cubes weight threshold (Open3D's `weight_threshold`): a cell is meshed when all
    /// eight corner voxels have `weight >= weight_threshold` (and `> 0`). Meshing, extraction and
    /// rendering all use it; change it with [`crate::TsdfMap::set_weight_threshold`]. Not stored
    /// by [`crate::TsdfMap::write_to`] (a loaded map meshes with the default, 1).
    pub weight_threshold: f32,
}

impl Default for TsdfConfig {
    /// The SGAM authors' CLEVR-Infinite fusion: 0.05 m voxels, truncation 10 voxels (0.5 m), depth
    /// range 0.1..20 m. (Generation's CLEVR preset, `sgam_pipeline::clevr_generator_config`,
    /// truncates at 5 voxels since session 11: docs/MODEL.md.)
    fn default() -> Self {
        Self {
            voxel_size_m: 0.05,
            trunc_voxels: 10.0,
            depth_min_m: 0.1,
            depth_max_m: 20.0,
            weight_cap: None,
            weight_threshold: 1.0,
        }
    }
}

impl TsdfConfig {
    /// Truncation distance in metres.
    pub fn trunc_m(&self) -> f32 {
        self.trunc_voxels * self.voxel_size_m
    }

    /// Edge length of one 8^3 block, metres.
    pub fn block_size_m(&self) -> f32 {
        self.voxel_size_m * crate::block::BLOCK_SIZE as f32
    }

    /// Checks ranges: voxel size in [`MIN_VOXEL_M`]..=[`MAX_VOXEL_M`], truncation in
    /// `(0, MAX_TRUNC_VOXELS]` voxels, `0 <= depth_min < depth_max <= MAX_DEPTH_M`, cap `>= 1`.
    /// The lower voxel bound keeps memory within a machine: below it every pixel of every frame
    /// allocates its own blocks. Errors name the field and the accepted range.
    pub fn validate(&self) -> Result<(), MapError> {
        let bad = |m: String| Err(MapError::InvalidConfig(m));
        if !(self.voxel_size_m.is_finite() && (MIN_VOXEL_M..=MAX_VOXEL_M).contains(&self.voxel_size_m)) {
            return bad(format!(
                "voxel_size_m = {} is out of range {MIN_VOXEL_M}..={MAX_VOXEL_M} m",
                self.voxel_size_m
            ));
        }
        if !(self.trunc_voxels.is_finite() && self.trunc_voxels > 0.0 && self.trunc_voxels <= MAX_TRUNC_VOXELS) {
            return bad(format!("trunc_voxels = {} is out of range (0, {MAX_TRUNC_VOXELS}]", self.trunc_voxels));
        }
        if !(self.depth_min_m.is_finite() && self.depth_max_m.is_finite())
            || self.depth_min_m < 0.0
            || self.depth_min_m >= self.depth_max_m
            || self.depth_max_m > MAX_DEPTH_M
        {
            return bad(format!(
                "depth range {}..{} m is empty or invalid (0 <= min < max <= {MAX_DEPTH_M})",
                self.depth_min_m, self.depth_max_m
            ));
        }
        if let Some(cap) = self.weight_cap {
            if !(cap.is_finite() && cap >= 1.0) {
                return bad(format!("weight_cap = {cap} must be >= 1"));
            }
        }
        if !(self.weight_threshold.is_finite() && self.weight_threshold >= 0.0) {
            return bad(format!("weight_threshold = {} must be a finite weight >= 0", self.weight_threshold));
        }
        Ok(())
    }
}
