use crate::MapError;

/// Parameters of a [`crate::TsdfMap`]. Defaults follow the SGAM authors' CLEVR-Infinite setup.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TsdfConfig {
    /// Edge length of one voxel, metres.
    pub voxel_size_m: f32,
    /// Truncation distance as a multiple of the voxel size (truncation in metres is
    /// `trunc_voxels * voxel_size_m`).
    pub trunc_voxels: f32,
    /// Depth readings below this planar depth (metres) are ignored when integrating; also the
    /// near plane of [`crate::TsdfMap::render`] and [`crate::TsdfMap::ray_cast`].
    pub depth_min_m: f32,
    /// Depth readings above this planar depth (metres) are ignored when integrating; also the far
    /// plane of [`crate::TsdfMap::render`] and [`crate::TsdfMap::ray_cast`].
    pub depth_max_m: f32,
    /// Optional cap on the per-voxel weight (`None` = the paper's unbounded running average).
    pub weight_cap: Option<f32>,
}

impl Default for TsdfConfig {
    /// CLEVR-Infinite: 0.05 m voxels, truncation 10 voxels (0.5 m), depth range 0.1..20 m.
    fn default() -> Self {
        Self { voxel_size_m: 0.05, trunc_voxels: 10.0, depth_min_m: 0.1, depth_max_m: 20.0, weight_cap: None }
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

    /// Checks ranges: positive finite voxel size and truncation, `0 <= depth_min < depth_max`,
    /// positive cap.
    pub fn validate(&self) -> Result<(), MapError> {
        let bad = |m: String| Err(MapError::InvalidConfig(m));
        if !(self.voxel_size_m.is_finite() && self.voxel_size_m > 0.0) {
            return bad(format!("voxel_size_m = {} must be positive", self.voxel_size_m));
        }
        if !(self.trunc_voxels.is_finite() && self.trunc_voxels > 0.0) {
            return bad(format!("trunc_voxels = {} must be positive", self.trunc_voxels));
        }
        if !(self.depth_min_m.is_finite() && self.depth_max_m.is_finite())
            || self.depth_min_m < 0.0
            || self.depth_min_m >= self.depth_max_m
        {
            return bad(format!("depth range {}..{} m is empty or invalid", self.depth_min_m, self.depth_max_m));
        }
        if let Some(cap) = self.weight_cap {
            if !(cap.is_finite() && cap >= 1.0) {
                return bad(format!("weight_cap = {cap} must be >= 1"));
            }
        }
        Ok(())
    }
}
