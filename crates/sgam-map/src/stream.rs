//! Letting blocks go and taking them back: the primitives of a map whose memory does not grow
//! with the world (issue 29).
//!
//! The unit is the super-block (8^3 blocks, 3.2 m at 5 cm voxels). A super-block is let go
//! ([`TsdfMap::evict_super_blocks`]) with its blocks' voxels, their allocation order and their
//! meshes (coloured), and taken back unchanged ([`TsdfMap::restore_blocks`]). Nothing is
//! re-meshed either way: a block's mesh reads its upper neighbours, and a caller that only lets
//! go of super-blocks beyond [`TsdfMap::reach_m`] of every camera it still integrates, renders or
//! meshes at gets back, after a restore, exactly the map it would have had without eviction
//! (tested: renders are byte-identical).

use glam::{IVec3, Vec3};
use rustc_hash::FxHashSet;
use sgam_core::Camera;

use crate::block::Block;
use crate::layer::{NONE, SUPER_SIZE};
use crate::mesh::BlockMesh;
use crate::{MapError, TsdfMap};

/// One block let go of by [`TsdfMap::evict_super_blocks`].
#[derive(Debug, Clone)]
pub struct EvictedBlock {
    /// Block key.
    pub key: IVec3,
    /// Its place in allocation order (kept, so rendering's tie-breaks stay the same).
    pub order: u64,
    pub(crate) block: Block,
    pub(crate) mesh: BlockMesh,
}

impl EvictedBlock {
    /// The block's voxels.
    pub fn block(&self) -> &Block {
        &self.block
    }
}

/// The super-block holding block `key`.
pub fn super_block_of(key: IVec3) -> IVec3 {
    IVec3::new(key.x.div_euclid(SUPER_SIZE), key.y.div_euclid(SUPER_SIZE), key.z.div_euclid(SUPER_SIZE))
}

impl TsdfMap {
    /// Keys of the super-blocks that hold blocks, ascending.
    pub fn super_block_keys(&self) -> Vec<IVec3> {
        let mut k: Vec<IVec3> = self.layer.super_blocks().map(|(k, _)| k).collect();
        k.sort_unstable_by_key(|k| (k.x, k.y, k.z));
        k
    }

    /// World box `(min, max)` of super-block `skey`, metres.
    pub fn super_block_box(&self, skey: IVec3) -> (Vec3, Vec3) {
        let s = self.config.block_size_m() * SUPER_SIZE as f32;
        let lo = skey.as_vec3() * s;
        (lo, lo + Vec3::splat(s))
    }

    /// How far from `camera`'s centre a step at `camera` may read or write the map: the
    /// farthest point of its frustum at `depth_max_m` (planar), plus the truncation band (an
    /// integration writes that far behind a surface) and two block diagonals (a changed block
    /// re-meshes its lower neighbours, whose meshes read their upper ones). Super-blocks whose
    /// box lies farther than this from every camera still to come may be let go.
    pub fn reach_m(&self, camera: &Camera) -> f32 {
        let k = camera.intrinsics;
        let (tx, ty) = (
            (k.cx.max(k.width as f32 - k.cx)) / k.fx.max(f32::MIN_POSITIVE),
            (k.cy.max(k.height as f32 - k.cy)) / k.fy.max(f32::MIN_POSITIVE),
        );
        let c = &self.config;
        c.depth_max_m * (1.0 + tx * tx + ty * ty).sqrt()
            + c.trunc_voxels * c.voxel_size_m
            + 2.0 * 3f32.sqrt() * c.block_size_m()
    }

    /// Lets go of every block of the super-blocks `skeys`: re-meshes what is dirty first, colours
    /// the meshes of the blocks that go and of the resident blocks whose meshes read them, then
    /// returns the blocks (ascending allocation order) and rebuilds the map from the rest (their
    /// ids compacted in allocation order; nothing else changes).
    pub fn evict_super_blocks(&mut self, skeys: &[IVec3]) -> Vec<EvictedBlock> {
        let going_supers: FxHashSet<IVec3> = skeys.iter().copied().collect();
        if going_supers.is_empty() {
            return Vec::new();
        }
        self.update_mesh();
        let n = self.layer.len();
        let going: Vec<bool> =
            (0..n as u32).map(|id| going_supers.contains(&super_block_of(self.layer.key(id)))).collect();
        if !going.iter().any(|g| *g) {
            return Vec::new();
        }
        // meshes that read a block that goes: its own, and its resident lower neighbours'
        let mut colour: Vec<u32> = Vec::new();
        for id in (0..n as u32).filter(|&id| going[id as usize]) {
            colour.push(id);
            colour.extend(self.layer.lower(id)[1..].iter().copied().filter(|&l| l != NONE && !going[l as usize]));
        }
        colour.sort_unstable();
        colour.dedup();
        self.fill_colours(&colour);
        let old = std::mem::replace(self, TsdfMap::new(self.config));
        let next_order = old.next_order;
        let (keys, blocks) = old.layer.into_parts();
        let mut parts: Vec<(u64, usize, Block)> =
            blocks.into_iter().enumerate().map(|(id, b)| (old.order[id], id, b)).collect();
        parts.sort_unstable_by_key(|p| p.0);
        let mut meshes = old.meshes;
        let mut out = Vec::new();
        for (order, id, block) in parts {
            let mesh = std::mem::take(&mut meshes[id]);
            if going[id] {
                out.push(EvictedBlock { key: keys[id], order, block, mesh });
            } else {
                let (nid, _) = self.allocate(keys[id]);
                let nid = nid as usize;
                *self.layer.block_mut(nid as u32) = block;
                self.meshes[nid] = mesh;
                self.sign_flags[nid] = old.sign_flags[id];
                self.row_flags[nid] = old.row_flags[id];
                self.order[nid] = order;
            }
        }
        self.next_order = next_order;
        out
    }

    /// Takes back blocks let go of by [`TsdfMap::evict_super_blocks`], with their meshes (not
    /// re-meshed) and allocation order. Refuses a block that is resident, and an order not
    /// below the map's next one (not from this map).
    pub fn restore_blocks(&mut self, mut blocks: Vec<EvictedBlock>) -> Result<(), MapError> {
        blocks.sort_unstable_by_key(|b| b.order);
        for b in &blocks {
            if self.layer.contains(b.key) {
                return Err(MapError::InvalidContent(format!("block {} is already in the map", b.key)));
            }
            if b.order >= self.next_order {
                return Err(MapError::InvalidContent(format!(
                    "block {} comes from another map (allocation order {} of {})",
                    b.key, b.order, self.next_order
                )));
            }
        }
        let next_order = self.next_order;
        for b in blocks {
            let (id, _) = self.allocate(b.key);
            *self.layer.block_mut(id) = b.block;
            self.meshes[id as usize] = b.mesh;
            self.order[id as usize] = b.order;
            self.refresh_sign_flags(id);
        }
        self.next_order = next_order;
        Ok(())
    }
}
