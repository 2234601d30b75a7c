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
//!
//! What is let go of can be kept on disk as a *tile* ([`write_tile`], [`read_tile`]): one
//! super-block's blocks with their allocation order, voxels (only those that differ from an
//! unobserved voxel) and coloured meshes, in a versioned, checksummed format:
//! ```text
//! magic "SGAMTILE" | u32 version 1 | f32 voxel size | i32 x 3 super-block key | u32 blocks
//! per block: i32 x 3 key | u64 order | 8 x u64 mask of stored voxels
//!            | per stored voxel f32 tsdf, weight, r, g, b
//!            | u32 vertices | u32 triangles | u8 has colours | f32 x 3 per vertex
//!            | u16 edge slot per vertex | f32 x 3 colour per vertex (when it has them)
//!            | u32 x 3 per triangle
//! u32 CRC-32 (IEEE) of every preceding byte
//! ```

use std::io::Write;

use glam::{IVec3, Vec3};
use rustc_hash::FxHashSet;
use sgam_core::{Camera, TriMesh};

use crate::block::{Block, Voxel, BLOCK_VOXELS};
use crate::layer::{NONE, SUPER_SIZE};
use crate::mesh::{weld_block_meshes, BlockMesh};
use crate::{MapError, TsdfConfig, TsdfMap};

const TILE_MAGIC: &[u8; 8] = b"SGAMTILE";
const TILE_VERSION: u32 = 1;
/// Edge slots of a block mesh's vertices: `3 * 9^3`.
const EDGE_SLOTS: u16 = 3 * 729;

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

    /// Triangles of the block's mesh.
    pub fn triangle_count(&self) -> usize {
        self.mesh.triangles.len()
    }
}

/// The welded, coloured mesh of evicted `blocks` (sorted by key here): what
/// [`TsdfMap::extract_mesh`] gives for them, without the triangles of resident blocks that
/// read them.
pub fn blocks_mesh(blocks: &[EvictedBlock]) -> TriMesh {
    let mut sorted: Vec<&EvictedBlock> = blocks.iter().collect();
    sorted.sort_unstable_by_key(|b| (b.key.x, b.key.y, b.key.z));
    weld_block_meshes(sorted.into_iter().map(|b| (b.key, &b.mesh)), |_| true)
}

/// Writes the blocks of super-block `skey` let go of by [`TsdfMap::evict_super_blocks`] as a
/// tile (the format in this module's documentation) of a map with `config`'s voxels.
pub fn write_tile(
    w: &mut impl Write,
    config: &TsdfConfig,
    skey: IVec3,
    blocks: &[EvictedBlock],
) -> Result<(), MapError> {
    let mut buf = Vec::with_capacity(64 + blocks.len() * 4096);
    buf.extend_from_slice(TILE_MAGIC);
    buf.extend_from_slice(&TILE_VERSION.to_le_bytes());
    buf.extend_from_slice(&config.voxel_size_m.to_le_bytes());
    for v in skey.to_array() {
        buf.extend_from_slice(&v.to_le_bytes());
    }
    buf.extend_from_slice(&(blocks.len() as u32).to_le_bytes());
    let empty = Block::default();
    for b in blocks {
        if super_block_of(b.key) != skey {
            return Err(MapError::InvalidContent(format!("block {} is not in super-block {skey}", b.key)));
        }
        for v in b.key.to_array() {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        buf.extend_from_slice(&b.order.to_le_bytes());
        let stored: Vec<usize> = (0..BLOCK_VOXELS).filter(|&i| !same_bits(b.block.voxel(i), empty.voxel(i))).collect();
        let mut mask = [0u64; BLOCK_VOXELS / 64];
        for &i in &stored {
            mask[i / 64] |= 1 << (i % 64);
        }
        for m in mask {
            buf.extend_from_slice(&m.to_le_bytes());
        }
        for i in stored {
            let v = b.block.voxel(i);
            for x in [v.tsdf, v.weight, v.colour[0], v.colour[1], v.colour[2]] {
                buf.extend_from_slice(&x.to_le_bytes());
            }
        }
        let m = &b.mesh;
        buf.extend_from_slice(&(m.positions.len() as u32).to_le_bytes());
        buf.extend_from_slice(&(m.triangles.len() as u32).to_le_bytes());
        buf.push(m.has_colours() as u8);
        for p in &m.positions {
            for x in p.to_array() {
                buf.extend_from_slice(&x.to_le_bytes());
            }
        }
        for e in &m.edges {
            buf.extend_from_slice(&e.to_le_bytes());
        }
        if m.has_colours() {
            for c in &m.colours {
                for x in c {
                    buf.extend_from_slice(&x.to_le_bytes());
                }
            }
        }
        for t in &m.triangles {
            for x in t {
                buf.extend_from_slice(&x.to_le_bytes());
            }
        }
    }
    let crc = crc32fast::hash(&buf);
    buf.extend_from_slice(&crc.to_le_bytes());
    w.write_all(&buf)?;
    w.flush()?;
    Ok(())
}

fn same_bits(a: Voxel, b: Voxel) -> bool {
    a.tsdf.to_bits() == b.tsdf.to_bits()
        && a.weight.to_bits() == b.weight.to_bits()
        && (0..3).all(|c| a.colour[c].to_bits() == b.colour[c].to_bits())
}

/// Reads a tile written by [`write_tile`] for a map with `config`'s voxels: its super-block key
/// and blocks. Errors (never panics) on a foreign or damaged file (magic, version, checksum,
/// truncation), another voxel size, a block outside the super-block or given twice, a
/// non-finite value, or a mesh whose indices or edge slots are out of range.
pub fn read_tile(bytes: &[u8], config: &TsdfConfig) -> Result<(IVec3, Vec<EvictedBlock>), MapError> {
    if bytes.len() < 12 || &bytes[..8] != TILE_MAGIC {
        if bytes.len() >= 8 && &bytes[..8] != TILE_MAGIC {
            return Err(MapError::BadMagic { found: bytes[..8].to_vec(), expected: TILE_MAGIC.to_vec() });
        }
        return Err(MapError::Truncated(format!("{} bytes, shorter than a tile's header", bytes.len())));
    }
    let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
    if version != TILE_VERSION {
        return Err(MapError::UnsupportedVersion { found: version, supported: TILE_VERSION });
    }
    if bytes.len() < 32 + 4 {
        return Err(MapError::Truncated(format!("{} bytes, shorter than a tile's header", bytes.len())));
    }
    let body = bytes.len() - 4;
    let stored = u32::from_le_bytes([bytes[body], bytes[body + 1], bytes[body + 2], bytes[body + 3]]);
    let computed = crc32fast::hash(&bytes[..body]);
    if stored != computed {
        return Err(MapError::ChecksumMismatch { stored, computed });
    }
    let bad = |m: String| MapError::InvalidContent(m);
    let mut cur = TileCursor { bytes: &bytes[..body], at: 12 };
    let voxel = cur.f32()?;
    if voxel.to_bits() != config.voxel_size_m.to_bits() {
        return Err(bad(format!("a tile of {voxel} m voxels for a map of {} m voxels", config.voxel_size_m)));
    }
    let skey = IVec3::new(cur.i32()?, cur.i32()?, cur.i32()?);
    let count = cur.u32()? as usize;
    if count > (SUPER_SIZE * SUPER_SIZE * SUPER_SIZE) as usize {
        return Err(bad(format!("{count} blocks in one super-block")));
    }
    let mut keys = FxHashSet::default();
    let mut out = Vec::with_capacity(count);
    for _ in 0..count {
        let key = IVec3::new(cur.i32()?, cur.i32()?, cur.i32()?);
        if key.to_array().iter().any(|v| v.unsigned_abs() > crate::persist::MAX_BLOCK_KEY as u32) {
            return Err(bad(format!("block key {key} outside +-{}", crate::persist::MAX_BLOCK_KEY)));
        }
        if super_block_of(key) != skey || !keys.insert(key) {
            return Err(bad(format!("block {key} is outside super-block {skey} or given twice")));
        }
        let order = cur.u64()?;
        let mut mask = [0u64; BLOCK_VOXELS / 64];
        for m in &mut mask {
            *m = cur.u64()?;
        }
        let mut block = Block::default();
        for i in (0..BLOCK_VOXELS).filter(|&i| mask[i / 64] >> (i % 64) & 1 == 1) {
            let v = Voxel { tsdf: cur.f32()?, weight: cur.f32()?, colour: [cur.f32()?, cur.f32()?, cur.f32()?] };
            if !(v.tsdf.is_finite() && v.weight.is_finite() && v.colour.iter().all(|c| c.is_finite())) {
                return Err(bad(format!("block {key}, voxel {i}: non-finite value")));
            }
            block.set_voxel(i, v);
        }
        let (nv, nt) = (cur.u32()? as usize, cur.u32()? as usize);
        let has_colours = cur.u8()? != 0;
        // a block's mesh has at most one vertex per edge slot and 5 triangles per cell
        if nv > EDGE_SLOTS as usize || nt > 5 * BLOCK_VOXELS {
            return Err(bad(format!("block {key}: a mesh of {nv} vertices and {nt} triangles")));
        }
        let mut mesh = BlockMesh::default();
        for _ in 0..nv {
            let p = Vec3::new(cur.f32()?, cur.f32()?, cur.f32()?);
            if !p.is_finite() {
                return Err(bad(format!("block {key}: non-finite vertex")));
            }
            mesh.positions.push(p);
        }
        for _ in 0..nv {
            let e = cur.u16()?;
            if e >= EDGE_SLOTS {
                return Err(bad(format!("block {key}: edge slot {e} out of range")));
            }
            mesh.edges.push(e);
        }
        if has_colours {
            for _ in 0..nv {
                let c = [cur.f32()?, cur.f32()?, cur.f32()?];
                if !c.iter().all(|x| x.is_finite()) {
                    return Err(bad(format!("block {key}: non-finite vertex colour")));
                }
                mesh.colours.push(c);
            }
        }
        for _ in 0..nt {
            let t = [cur.u32()?, cur.u32()?, cur.u32()?];
            if t.iter().any(|&i| i as usize >= nv) {
                return Err(bad(format!("block {key}: a triangle indexes past its {nv} vertices")));
            }
            mesh.triangles.push(t);
        }
        out.push(EvictedBlock { key, order, block, mesh });
    }
    if cur.at != cur.bytes.len() {
        return Err(MapError::Truncated(format!("{} bytes after the last block", cur.bytes.len() - cur.at)));
    }
    Ok((skey, out))
}

struct TileCursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl TileCursor<'_> {
    fn take<const N: usize>(&mut self) -> Result<[u8; N], MapError> {
        let s = self
            .bytes
            .get(self.at..self.at + N)
            .ok_or_else(|| MapError::Truncated(format!("tile ends at byte {}", self.bytes.len())))?;
        self.at += N;
        let mut out = [0u8; N];
        out.copy_from_slice(s);
        Ok(out)
    }
    fn u8(&mut self) -> Result<u8, MapError> {
        Ok(self.take::<1>()?[0])
    }
    fn u16(&mut self) -> Result<u16, MapError> {
        Ok(u16::from_le_bytes(self.take()?))
    }
    fn u32(&mut self) -> Result<u32, MapError> {
        Ok(u32::from_le_bytes(self.take()?))
    }
    fn u64(&mut self) -> Result<u64, MapError> {
        Ok(u64::from_le_bytes(self.take()?))
    }
    fn f32(&mut self) -> Result<f32, MapError> {
        Ok(f32::from_le_bytes(self.take()?))
    }
    fn i32(&mut self) -> Result<i32, MapError> {
        Ok(i32::from_le_bytes(self.take()?))
    }
}

/// A convex region of space (a grown view frustum, [`TsdfMap::view_reach`]).
#[derive(Debug, Clone, Copy)]
pub struct ViewReach {
    /// Faces `(n, d)`, unit `n` pointing out: inside is `n . p <= d`.
    planes: [(Vec3, f32); 6],
    /// False when the camera gave no usable faces: then every box counts as inside.
    finite: bool,
}

impl ViewReach {
    /// Whether the box `(lo, hi)` may meet the region: false only when the whole box lies
    /// outside one face (conservative: a box beyond an edge of the region, outside no single
    /// face, counts as meeting it).
    pub fn touches(&self, (lo, hi): (Vec3, Vec3)) -> bool {
        !self.finite
            || self.planes.iter().all(|&(n, d)| {
                // the box's corner farthest against n
                let p = Vec3::select(n.cmpge(Vec3::ZERO), lo, hi);
                n.dot(p) <= d
            })
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
        self.config.depth_max_m * (1.0 + tx * tx + ty * ty).sqrt() + self.reach_beyond_surface_m()
    }

    /// How far beyond the surfaces it sees a step may read or write: the truncation band (an
    /// integration writes that far behind a surface) and two block diagonals (a changed block
    /// re-meshes its lower neighbours, whose meshes read their upper ones).
    fn reach_beyond_surface_m(&self) -> f32 {
        let c = &self.config;
        c.trunc_voxels * c.voxel_size_m + 2.0 * 3f32.sqrt() * c.block_size_m()
    }

    /// The part of space a step at `camera` may read or write, grown by `grow_m`: its frustum
    /// from the camera's centre to `depth_max_m` (planar), with every face moved out by the
    /// truncation band, two block diagonals (as in [`Self::reach_m`]) and `grow_m`. A step reads
    /// and writes only inside its frustum (a ray's band and an allocated block stay within the
    /// band and a block of it), so a map streamed by this region keeps what a step needs while
    /// letting go of everything behind and beside the view, which a sphere of [`Self::reach_m`]
    /// would hold.
    pub fn view_reach(&self, camera: &Camera, grow_m: f32) -> ViewReach {
        let k = camera.intrinsics;
        let c = &self.config;
        let band = c.trunc_voxels * c.voxel_size_m;
        let grow = self.reach_beyond_surface_m() + grow_m;
        let (fx, fy) = (k.fx.max(f32::MIN_POSITIVE), k.fy.max(f32::MIN_POSITIVE));
        let (left, right) = (k.cx / fx, (k.width as f32 - k.cx) / fx);
        let (top, bottom) = (k.cy / fy, (k.height as f32 - k.cy) / fy);
        // camera frame (OpenCV: x right, y down, z forward): inside is n . p <= d
        let camera_planes = [
            (Vec3::new(-1.0, 0.0, -left), 0.0),
            (Vec3::new(1.0, 0.0, -right), 0.0),
            (Vec3::new(0.0, -1.0, -top), 0.0),
            (Vec3::new(0.0, 1.0, -bottom), 0.0),
            (Vec3::new(0.0, 0.0, -1.0), 0.0),
            (Vec3::new(0.0, 0.0, 1.0), c.depth_max_m + band),
        ];
        let pose = &camera.world_from_camera;
        let planes = camera_planes.map(|(n, d)| {
            let n = pose.transform_vector(n.normalize_or_zero());
            (n, d + grow + n.dot(pose.translation))
        });
        let finite = planes.iter().all(|(n, d)| n.is_finite() && d.is_finite() && n.length_squared() > 0.5);
        ViewReach { planes, finite }
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

    /// A map that holds only `blocks` (from [`TsdfMap::evict_super_blocks`] or [`read_tile`]),
    /// with their meshes and allocation order, for looking at one tile: rendering it
    /// ([`TsdfMap::rasterize_range`]) or taking its mesh draws what those blocks drew in the map
    /// they came from. Refuses a key given twice.
    pub fn from_evicted(config: TsdfConfig, blocks: Vec<EvictedBlock>) -> Result<TsdfMap, MapError> {
        let mut map = TsdfMap::new(config);
        map.next_order = blocks.iter().map(|b| b.order.saturating_add(1)).max().unwrap_or(0);
        map.restore_blocks(blocks)?;
        Ok(map)
    }

    /// The welded, coloured mesh of the blocks of super-block `skey` (only the triangles of its
    /// own blocks' cells: the meshes of neighbouring super-blocks do not overlap it).
    pub fn super_block_mesh(&mut self, skey: IVec3) -> TriMesh {
        self.update_mesh();
        let mut ids: Vec<u32> = self.layer.super_block(skey).map(<[u32]>::to_vec).unwrap_or_default();
        self.fill_colours(&ids);
        ids.sort_unstable_by_key(|&i| {
            let k = self.layer.key(i);
            (k.x, k.y, k.z)
        });
        weld_block_meshes(ids.into_iter().map(|id| (self.layer.key(id), &self.meshes[id as usize])), |_| true)
    }

    /// Takes back blocks let go of by [`TsdfMap::evict_super_blocks`], with their meshes and
    /// allocation order. Nothing is re-meshed: the resident blocks whose meshes read them kept
    /// the meshes they had (re-meshing one now could lose its cells towards another neighbour
    /// still away). A map loaded from a file while they were away meshes its blocks anew:
    /// [`TsdfMap::remesh_dirty_only`] after taking the neighbours back gives them their
    /// meshes. Refuses a block that is resident, and an order not below the map's next one
    /// (not from this map).
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
