//! The map's block storage (voxblox's "layer"): dense 8^3 [`Block`]s addressed by a dense id,
//! the key -> id index, the neighbour tables and the coarse super-block index. The fields are
//! private; integration, meshing, rendering and persistence use the methods, so the invariants
//! hold by construction: ids are `0..len` and never move; `key(id_of(k)) == k`; the `upper` /
//! `lower` tables agree with the index; every block is listed in its super-block.

use glam::IVec3;
use rustc_hash::FxHashMap;

use crate::block::Block;

/// Blocks per super-block edge: the coarse grid used to find the blocks inside a frustum or a
/// box without visiting the whole map.
pub(crate) const SUPER_SIZE: i32 = 8;

/// "No block" in the neighbour tables.
pub(crate) const NONE: u32 = u32::MAX;

/// Offset of corner `o` (`0..8`) of the unit cube: `(o & 1, o >> 1 & 1, o >> 2)`.
#[inline]
pub(crate) fn corner_offset(o: usize) -> IVec3 {
    IVec3::new((o & 1) as i32, ((o >> 1) & 1) as i32, (o >> 2) as i32)
}

/// Dense blocks by id, with their keys, neighbours and super-block lists.
#[derive(Debug, Clone, Default)]
pub(crate) struct BlockLayer {
    /// Block key -> block id.
    index: FxHashMap<IVec3, u32>,
    keys: Vec<IVec3>,
    blocks: Vec<Block>,
    /// Super-block key -> ids of its blocks (ascending).
    super_index: FxHashMap<IVec3, Vec<u32>>,
    /// Per block, the ids of the blocks at `key + offset(o)` / `key - offset(o)` for
    /// `offset(o) = (o & 1, o >> 1 & 1, o >> 2)`, `o` in `1..8` (`NONE` where unallocated; entry
    /// 0 is the block itself), so meshing never hashes.
    upper: Vec<[u32; 8]>,
    lower: Vec<[u32; 8]>,
}

impl BlockLayer {
    /// Number of blocks (ids are `0..len`).
    #[inline]
    pub(crate) fn len(&self) -> usize {
        self.blocks.len()
    }

    /// Blocks the storage holds room for.
    pub(crate) fn capacity(&self) -> usize {
        self.blocks.capacity().max(self.blocks.len())
    }

    /// Number of non-empty super-blocks.
    pub(crate) fn super_block_count(&self) -> usize {
        self.super_index.len()
    }

    /// The id of block `key`, if allocated.
    #[inline]
    pub(crate) fn id_of(&self, key: IVec3) -> Option<u32> {
        self.index.get(&key).copied()
    }

    /// Whether block `key` is allocated.
    #[inline]
    pub(crate) fn contains(&self, key: IVec3) -> bool {
        self.index.contains_key(&key)
    }

    /// The key of block `id`.
    #[inline]
    pub(crate) fn key(&self, id: u32) -> IVec3 {
        self.keys[id as usize]
    }

    /// Keys by id.
    #[inline]
    pub(crate) fn keys(&self) -> &[IVec3] {
        &self.keys
    }

    /// Block `id`.
    #[inline]
    pub(crate) fn block(&self, id: u32) -> &Block {
        &self.blocks[id as usize]
    }

    /// Block `id`, mutably.
    #[inline]
    pub(crate) fn block_mut(&mut self, id: u32) -> &mut Block {
        &mut self.blocks[id as usize]
    }

    /// The block with key `key`, if allocated.
    #[inline]
    pub(crate) fn block_at(&self, key: IVec3) -> Option<&Block> {
        self.index.get(&key).map(|&i| &self.blocks[i as usize])
    }

    /// Ids of the blocks at `key(id) + corner_offset(o)` (`NONE` where unallocated).
    #[inline]
    pub(crate) fn upper(&self, id: u32) -> [u32; 8] {
        self.upper[id as usize]
    }

    /// Ids of the blocks at `key(id) - corner_offset(o)` (`NONE` where unallocated).
    #[inline]
    pub(crate) fn lower(&self, id: u32) -> [u32; 8] {
        self.lower[id as usize]
    }

    /// Ids of the blocks of super-block `skey`, ascending.
    #[inline]
    pub(crate) fn super_block(&self, skey: IVec3) -> Option<&[u32]> {
        self.super_index.get(&skey).map(Vec::as_slice)
    }

    /// Every super-block with its block ids.
    pub(crate) fn super_blocks(&self) -> impl Iterator<Item = (IVec3, &[u32])> {
        self.super_index.iter().map(|(k, v)| (*k, v.as_slice()))
    }

    /// Mutable references to the blocks `ids` (sorted, unique), in O(ids) time, and the keys
    /// by id (read while the blocks are written).
    pub(crate) fn blocks_mut(&mut self, ids: &[u32]) -> (Vec<&mut Block>, &[IVec3]) {
        (disjoint_mut(&mut self.blocks, ids), &self.keys)
    }

    /// The keys and blocks by id, consuming the layer (the map rebuilds itself from them when
    /// it lets blocks go).
    pub(crate) fn into_parts(self) -> (Vec<IVec3>, Vec<Block>) {
        (self.keys, self.blocks)
    }

    /// Allocates block `key` (empty) if needed; returns its id and whether it is new.
    pub(crate) fn allocate(&mut self, key: IVec3) -> (u32, bool) {
        if let Some(&i) = self.index.get(&key) {
            return (i, false);
        }
        let id = self.blocks.len() as u32;
        self.index.insert(key, id);
        self.keys.push(key);
        self.blocks.push(Block::default());
        let sk = IVec3::new(key.x.div_euclid(SUPER_SIZE), key.y.div_euclid(SUPER_SIZE), key.z.div_euclid(SUPER_SIZE));
        self.super_index.entry(sk).or_default().push(id);
        let (mut upper, mut lower) = ([NONE; 8], [NONE; 8]);
        (upper[0], lower[0]) = (id, id);
        for o in 1..8 {
            let off = corner_offset(o);
            if let Some(&n) = self.index.get(&key.wrapping_add(off)) {
                upper[o] = n;
                self.lower[n as usize][o] = id;
            }
            if let Some(&n) = self.index.get(&key.wrapping_sub(off)) {
                lower[o] = n;
                self.upper[n as usize][o] = id;
            }
        }
        self.upper.push(upper);
        self.lower.push(lower);
        (id, true)
    }
}

/// Mutable references to `blocks[ids[i]]` for sorted, unique `ids`, in O(ids) time.
pub(crate) fn disjoint_mut<'a, T>(blocks: &'a mut [T], ids: &[u32]) -> Vec<&'a mut T> {
    let mut out = Vec::with_capacity(ids.len());
    let mut rest = blocks;
    let mut offset = 0usize;
    for &id in ids {
        let at = id as usize - offset;
        let (_, tail) = std::mem::take(&mut rest).split_at_mut(at);
        if let Some((first, tail)) = tail.split_first_mut() {
            out.push(first);
            rest = tail;
        }
        offset = id as usize + 1;
    }
    out
}
