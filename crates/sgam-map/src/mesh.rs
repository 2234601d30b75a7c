//! Incremental marching cubes over the block grid, and welded mesh extraction.

use glam::{IVec3, Vec3};
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use sgam_core::TriMesh;

use crate::block::{Block, Voxel, BLOCK_SIZE};
use crate::layer::{NONE, SUPER_SIZE};
use crate::map::{TsdfMap, HAS_NEGATIVE, HAS_POSITIVE};
use crate::mc_table::{edge_axis, edge_start, table};
use wide::f32x8;

/// Global id of a mesh vertex: the marching-cubes edge from global voxel `g` to `g + e_axis`.
pub(crate) type EdgeKey = (IVec3, u8);

/// The marching-cubes mesh of the cells whose lowest corner lies in one block (so a block's
/// cells read the voxels of its +x/+y/+z neighbours). Each vertex remembers its edge in the
/// block's 9^3 gather grid, from which its global edge key (for welding block meshes into one
/// world mesh) and, lazily, its colour are derived.
#[derive(Debug, Clone, Default)]
pub(crate) struct BlockMesh {
    pub positions: Vec<Vec3>,
    /// Per vertex: `3 * (x + 9 y + 81 z) + axis`, the edge from grid point `(x, y, z)` (local,
    /// each in `0..=8`) along `axis`.
    pub edges: Vec<u16>,
    pub triangles: Vec<[u32; 3]>,
    /// Vertex colours, filled on demand ([`TsdfMap::fill_colours`], or computed on the fly by
    /// the shaded rasterizer): complete when as long as `positions`. Re-meshing empties them,
    /// so the generator's loop (depth-only rendering) never computes them.
    pub colours: Vec<[f32; 3]>,
}

impl BlockMesh {
    pub fn heap_bytes(&self) -> usize {
        self.positions.capacity() * 12
            + self.colours.capacity() * 12
            + self.edges.capacity() * 2
            + self.triangles.capacity() * 12
    }

    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// True when `colours` holds every vertex's colour.
    pub fn has_colours(&self) -> bool {
        self.colours.len() == self.positions.len()
    }

    /// Empties the mesh, keeping its buffers.
    pub fn clear(&mut self) {
        self.positions.clear();
        self.colours.clear();
        self.edges.clear();
        self.triangles.clear();
    }
}

/// Merges block meshes (`(block key, mesh)`, in the order given, colours filled), keeping
/// triangles that pass `keep`: vertices on an edge two blocks share become one.
pub(crate) fn weld_block_meshes<'a>(
    blocks: impl Iterator<Item = (IVec3, &'a BlockMesh)>,
    keep: impl Fn(&[Vec3; 3]) -> bool,
) -> TriMesh {
    let mut out = TriMesh::default();
    let mut global: FxHashMap<EdgeKey, u32> = FxHashMap::default();
    let mut local_to_global: Vec<u32> = Vec::new();
    for (key, m) in blocks {
        if m.is_empty() {
            continue;
        }
        let origin = key * BLOCK_SIZE;
        local_to_global.clear();
        local_to_global.resize(m.positions.len(), u32::MAX);
        for tri in &m.triangles {
            let p = tri.map(|i| m.positions[i as usize]);
            if !keep(&p) {
                continue;
            }
            let mut g = [0u32; 3];
            for k in 0..3 {
                let li = tri[k] as usize;
                if local_to_global[li] == u32::MAX {
                    let next = out.positions.len() as u32;
                    let (local, axis) = edge_of_slot(m.edges[li]);
                    let gi = *global.entry((origin + local, axis as u8)).or_insert(next);
                    if gi == next {
                        out.positions.push(m.positions[li]);
                        out.colours.push(m.colours.get(li).copied().unwrap_or(Voxel::EMPTY.colour));
                    }
                    local_to_global[li] = gi;
                }
                g[k] = local_to_global[li];
            }
            out.triangles.push(g);
        }
    }
    out
}

/// Grid point and axis of a vertex's edge slot ([`BlockMesh::edges`]).
#[inline]
fn edge_of_slot(slot: u16) -> (IVec3, usize) {
    let (g, axis) = (slot as i32 / 3, slot as usize % 3);
    (IVec3::new(g % GRID as i32, g / GRID as i32 % GRID as i32, g / (GRID * GRID) as i32), axis)
}

/// The voxels a block's cells read: the block and its `+x/+y/+z` neighbours (by corner offset).
struct Neighbourhood<'a> {
    blocks: [Option<&'a Block>; 8],
}

impl<'a> Neighbourhood<'a> {
    fn new(map: &'a TsdfMap, id: u32) -> Self {
        let ids = map.layer.upper(id);
        Self { blocks: std::array::from_fn(|o| (ids[o] != NONE).then(|| map.layer.block(ids[o]))) }
    }

    /// Block and (row, lane) of grid point `l` (each coordinate in `0..=8`).
    #[inline]
    fn locate(&self, l: IVec3) -> Option<(&'a Block, usize, usize)> {
        let o = (l.x >> 3 | (l.y >> 3) << 1 | (l.z >> 3) << 2) as usize;
        self.blocks[o].map(|b| (b, ((l.y & 7) + 8 * (l.z & 7)) as usize, (l.x & 7) as usize))
    }

    #[inline]
    fn tsdf(&self, l: IVec3) -> f32 {
        self.locate(l).map_or(Voxel::EMPTY.tsdf, |(b, r, x)| b.planes.tsdf[r][x])
    }

    #[inline]
    fn colour(&self, l: IVec3) -> [f32; 3] {
        self.locate(l).map_or(Voxel::EMPTY.colour, |(b, r, x)| std::array::from_fn(|ch| b.planes.colour[ch][r][x]))
    }

    /// Where along its edge (from grid point `local` along `axis`) a vertex lies: the fraction
    /// from the start point.
    #[inline]
    fn crossing(&self, local: IVec3, axis: usize) -> f32 {
        let (t0, t1) = (self.tsdf(local), self.tsdf(local + AXIS_STEP[axis]));
        t0 / (t0 - t1)
    }

    /// The colour of the vertex on edge `slot`: the two end voxels' colours, interpolated like
    /// the position.
    fn vertex_colour(&self, slot: u16) -> [f32; 3] {
        let (local, axis) = edge_of_slot(slot);
        let t = self.crossing(local, axis);
        let (c0, c1) = (self.colour(local), self.colour(local + AXIS_STEP[axis]));
        std::array::from_fn(|ch| c0[ch] + t * (c1[ch] - c0[ch]))
    }
}

/// Offsets of the 8 cube corners in the 9^3 gather grid.
const GRID: usize = 9;
const CORNER_OFFSET: [usize; 8] = {
    let mut o = [0usize; 8];
    let mut c = 0;
    while c < 8 {
        o[c] = (c & 1) + GRID * ((c >> 1) & 1) + GRID * GRID * (c >> 2);
        c += 1;
    }
    o
};

/// Per marching-cubes edge: its axis, the gather-grid offset of its start corner, and that
/// corner's offset from the cell.
const EDGES: [(usize, usize, IVec3); 12] = {
    let mut t = [(0usize, 0usize, IVec3::ZERO); 12];
    let mut e = 0;
    while e < 12 {
        let c = edge_start(e) as i32;
        t[e] = (edge_axis(e), CORNER_OFFSET[edge_start(e)], IVec3::new(c & 1, (c >> 1) & 1, c >> 2));
        e += 1;
    }
    t
};

/// Unit step along each axis.
const AXIS_STEP: [IVec3; 3] = [IVec3::X, IVec3::Y, IVec3::Z];

/// Per-thread working memory of [`TsdfMap::mesh_block`], reused across blocks.
struct MeshScratch {
    /// Vertex index per (grid point, axis) edge; `u32::MAX` = none. All `MAX` between blocks.
    cache: Box<[u32; GRID * GRID * GRID * 3]>,
    /// Slots of `cache` set by the current block (reset after it).
    used: Vec<u16>,
    /// Tsdf of the gather grid's points, `x + 9 (y + 9 z)`; valid in the grid rows the current
    /// block gathered (the only ones its crossing cells read).
    tsdf: Box<[f32; GRID * GRID * GRID]>,
}

impl MeshScratch {
    fn new() -> Self {
        Self {
            cache: Box::new([u32::MAX; GRID * GRID * GRID * 3]),
            used: Vec::new(),
            tsdf: Box::new([Voxel::EMPTY.tsdf; GRID * GRID * GRID]),
        }
    }
}

/// Gather-grid index step along each axis.
const GRID_STEP: [usize; 3] = [1, GRID, GRID * GRID];

impl TsdfMap {
    /// Re-meshes (marching cubes) the blocks whose cells may have changed since the last call:
    /// every dirty block and its seven lower neighbours (`-x`, `-y`, `-z` and diagonals), whose
    /// border cells read the dirty block's voxels. A cell is meshed when all eight corner voxels
    /// have `weight >= weight_threshold` (and `> 0`; the threshold is the map's
    /// [`TsdfConfig::weight_threshold`](crate::TsdfConfig::weight_threshold)). Runs in parallel
    /// over blocks; returns the number of blocks re-meshed.
    pub fn update_mesh(&mut self) -> usize {
        self.remesh(true)
    }

    /// Re-meshes exactly the dirty blocks, not their lower neighbours: for a map loaded from a
    /// file (every block dirty, no mesh) whose neighbours away in tiles were taken back first,
    /// so each loaded block is meshed with them and the blocks taken back keep their meshes.
    /// Returns the number of blocks re-meshed.
    pub fn remesh_dirty_only(&mut self) -> usize {
        self.remesh(false)
    }

    /// Re-meshes the dirty blocks and, with `spread`, their lower neighbours.
    fn remesh(&mut self, spread: bool) -> usize {
        let weight_threshold = self.config.weight_threshold;
        if self.dirty.is_empty() {
            return 0;
        }
        // The dirty blocks and their lower neighbours, each once (`is_dirty` marks what is
        // queued; no sort).
        let mut todo = std::mem::take(&mut self.dirty);
        for i in 0..if spread { todo.len() } else { 0 } {
            for &n in &self.layer.lower(todo[i])[1..] {
                if n != NONE && !self.is_dirty[n as usize] {
                    self.is_dirty[n as usize] = true;
                    todo.push(n);
                }
            }
        }
        for &id in &todo {
            self.is_dirty[id as usize] = false;
        }
        // Re-mesh into the blocks' own buffers (taken out, refilled, put back): no allocation
        // once a block's buffers have grown.
        let mut meshes: Vec<BlockMesh> = todo.iter().map(|&id| std::mem::take(&mut self.meshes[id as usize])).collect();
        let this = &*self;
        meshes
            .par_iter_mut()
            .zip(todo.par_iter())
            .for_each_init(MeshScratch::new, |scratch, (m, &id)| this.mesh_block(id, weight_threshold, m, scratch));
        for (&id, m) in todo.iter().zip(meshes) {
            self.meshes[id as usize] = m;
        }
        todo.len()
    }

    /// Sets the marching-cubes weight threshold; when it changes, every block is re-meshed on
    /// the next [`TsdfMap::update_mesh`].
    pub fn set_weight_threshold(&mut self, weight_threshold: f32) {
        if self.config.weight_threshold != weight_threshold {
            self.config.weight_threshold = weight_threshold;
            for id in 0..self.layer.len() as u32 {
                self.mark_dirty(id);
            }
        }
    }

    /// The welded world mesh: the union of all block meshes (after [`TsdfMap::update_mesh`])
    /// with vertices on shared edges merged, so no vertex is duplicated on block borders and
    /// the mesh has no cracks. Vertex order is deterministic (blocks in sorted key order).
    /// Triangles wind counter-clockwise seen from free space; colours are sRGB `[0, 1]`.
    pub fn extract_mesh(&mut self) -> TriMesh {
        self.update_mesh();
        let ids: Vec<u32> = (0..self.layer.len() as u32).collect();
        self.fill_colours(&ids);
        self.weld(ids, |_| true)
    }

    /// Computes the vertex colours of the block meshes of `ids` that lack them (in parallel).
    pub(crate) fn fill_colours(&mut self, ids: &[u32]) {
        let todo: Vec<u32> = ids.iter().copied().filter(|&id| !self.meshes[id as usize].has_colours()).collect();
        let colours: Vec<Vec<[f32; 3]>> = todo.par_iter().map(|&id| self.vertex_colours(id)).collect();
        for (id, c) in todo.into_iter().zip(colours) {
            self.meshes[id as usize].colours = c;
        }
    }

    /// The vertex colours of block `id`'s mesh, from the voxels.
    pub(crate) fn vertex_colours(&self, id: u32) -> Vec<[f32; 3]> {
        let hood = Neighbourhood::new(self, id);
        self.meshes[id as usize].edges.iter().map(|&slot| hood.vertex_colour(slot)).collect()
    }

    /// Like [`TsdfMap::extract_mesh`] but keeps only triangles with at least one vertex inside
    /// the world box `[min, max]` (metres); only blocks near the box are visited.
    pub fn extract_mesh_in_box(&mut self, min: Vec3, max: Vec3) -> TriMesh {
        self.update_mesh();
        let margin = Vec3::splat(self.config.voxel_size_m);
        let ids = self.blocks_where(min - margin, max + margin, |_, _| true);
        self.fill_colours(&ids);
        let inside = |p: Vec3| p.cmpge(min).all() && p.cmple(max).all();
        self.weld(ids, |tri| tri.iter().any(|p| inside(*p)))
    }

    /// Merges the meshes of `ids` (any order; sorted by key here; colours filled) keeping
    /// triangles that pass `keep`.
    fn weld(&self, mut ids: Vec<u32>, keep: impl Fn(&[Vec3; 3]) -> bool) -> TriMesh {
        ids.sort_unstable_by_key(|&i| {
            let k = self.layer.key(i);
            (k.x, k.y, k.z)
        });
        weld_block_meshes(ids.into_iter().map(|id| (self.layer.key(id), &self.meshes[id as usize])), keep)
    }

    /// Ids of blocks whose AABB intersects `[min, max]` and passes `pred(block_min, block_max)`
    /// (also applied to super-blocks to prune). Visits at most the super-blocks overlapping the
    /// box, or all super-blocks when that is fewer. Order: ascending id.
    pub(crate) fn blocks_where(&self, min: Vec3, max: Vec3, pred: impl Fn(Vec3, Vec3) -> bool) -> Vec<u32> {
        let mut out = Vec::new();
        // NaN bounds or an empty box select nothing; infinite bounds are clamped (and then
        // fall back to visiting every super-block).
        if min.is_nan() || max.is_nan() || min.cmpgt(max).any() {
            return out;
        }
        let bs = self.config.block_size_m();
        let ss = bs * SUPER_SIZE as f32;
        let clamp = |v: f32| v.clamp(-1.0e9, 1.0e9);
        let smin = (min.map(clamp) / ss).floor();
        let smax = (max.map(clamp) / ss).floor();
        let span = (smax - smin + Vec3::ONE).as_dvec3();
        let count = span.x * span.y * span.z;
        let kmin = (min.map(clamp) / bs).floor();
        let kmax = (max.map(clamp) / bs).floor();
        let mut visit_super = |skey: IVec3, ids: &[u32]| {
            let lo = (skey * SUPER_SIZE).as_vec3() * bs;
            if !pred(lo, lo + Vec3::splat(ss)) {
                return;
            }
            for &id in ids {
                let k = self.layer.key(id);
                let kf = k.as_vec3();
                if kf.cmplt(kmin).any() || kf.cmpgt(kmax).any() {
                    continue;
                }
                let lo = kf * bs;
                if pred(lo, lo + Vec3::splat(bs)) {
                    out.push(id);
                }
            }
        };
        if count > self.layer.super_block_count() as f64 {
            for (skey, ids) in self.layer.super_blocks() {
                visit_super(skey, ids);
            }
        } else {
            let (a, b) = (smin.as_ivec3(), smax.as_ivec3());
            for z in a.z..=b.z {
                for y in a.y..=b.y {
                    for x in a.x..=b.x {
                        if let Some(ids) = self.layer.super_block(IVec3::new(x, y, z)) {
                            visit_super(IVec3::new(x, y, z), ids);
                        }
                    }
                }
            }
        }
        out.sort_unstable();
        out
    }

    /// Marching cubes over the 8^3 cells of block `id`, into `mesh` (cleared first).
    ///
    /// Only the cell rows (8 cells along x) whose four grid rows hold observed voxels of both
    /// signs, by the per-row sign summaries, are gathered and visited: in a truncation band most
    /// rows lie wholly in front of or behind the surface.
    fn mesh_block(&self, id: u32, weight_threshold: f32, mesh: &mut BlockMesh, scratch: &mut MeshScratch) {
        mesh.clear();
        let key = self.layer.key(id);
        let ids = self.layer.upper(id);
        let flags = ids.iter().filter(|&&n| n != NONE).fold(0u8, |f, &n| f | self.sign_flags[n as usize]);
        // No observed voxel on one side of the surface: no zero crossing (skip the gather).
        if flags != HAS_POSITIVE | HAS_NEGATIVE {
            return;
        }
        // Sign summary per grid row (y, z): its 8 voxels' row in the block holding it, plus the
        // row of the +x neighbour holding its last point (a superset of that one voxel).
        let mut grid_flags = [0u8; GRID * GRID];
        for z in 0..GRID {
            for y in 0..GRID {
                let oyz = ((y == GRID - 1) as usize) << 1 | ((z == GRID - 1) as usize) << 2;
                let r = y % 8 + 8 * (z % 8);
                let f = |o: usize| if ids[o] == NONE { 0 } else { self.row_flags[ids[o] as usize][r] };
                grid_flags[y + GRID * z] = f(oyz) | f(oyz | 1);
            }
        }
        // Cell rows that may hold a crossing, and the grid rows they read.
        let mut cell_rows = [false; 64];
        let mut needed = [false; GRID * GRID];
        let mut any_cell = false;
        for z in 0..BLOCK_SIZE as usize {
            for y in 0..BLOCK_SIZE as usize {
                let rows = [y + GRID * z, y + 1 + GRID * z, y + GRID * (z + 1), y + 1 + GRID * (z + 1)];
                if rows.iter().fold(0, |a, &r| a | grid_flags[r]) == HAS_POSITIVE | HAS_NEGATIVE {
                    cell_rows[y + 8 * z] = true;
                    rows.iter().for_each(|&r| needed[r] = true);
                    any_cell = true;
                }
            }
        }
        if !any_cell {
            return;
        }
        // Per needed grid row (y, z): bit x set when grid point x is usable (observed, weight at
        // the threshold) / usable and inside (tsdf < 0); 8 voxels at a time.
        let hood = Neighbourhood::new(self, id);
        let mut valid_rows = [0u16; GRID * GRID];
        let mut neg_rows = [0u16; GRID * GRID];
        let usable = |w: f32| w > 0.0 && w >= weight_threshold;
        let (zero, threshold) = (f32x8::splat(0.0), f32x8::splat(weight_threshold));
        for z in 0..GRID {
            for y in 0..GRID {
                if !needed[y + GRID * z] {
                    continue;
                }
                let oyz = ((y == GRID - 1) as usize) << 1 | ((z == GRID - 1) as usize) << 2;
                let r = y % 8 + 8 * (z % 8);
                let (mut valid, mut neg) = (0u16, 0u16);
                let at = GRID * (y + GRID * z);
                if let Some(b) = hood.blocks[oyz] {
                    let (t, w) = (f32x8::new(b.planes.tsdf[r]), f32x8::new(b.planes.weight[r]));
                    let ok = w.simd_gt(zero) & w.simd_ge(threshold);
                    valid = ok.to_bitmask() as u16;
                    neg = (ok & t.simd_lt(zero)).to_bitmask() as u16;
                    scratch.tsdf[at..at + 8].copy_from_slice(&b.planes.tsdf[r]);
                }
                if let Some(b) = hood.blocks[oyz | 1] {
                    let (t, w) = (b.planes.tsdf[r][0], b.planes.weight[r][0]);
                    valid |= (usable(w) as u16) << 8;
                    neg |= ((usable(w) && t < 0.0) as u16) << 8;
                    scratch.tsdf[at + 8] = t;
                }
                valid_rows[y + GRID * z] = valid;
                neg_rows[y + GRID * z] = neg;
            }
        }
        let vs = self.config.voxel_size_m;
        let origin = key * BLOCK_SIZE;
        let cases = &table().cases;
        let MeshScratch { cache, used, tsdf } = scratch;
        for z in 0..BLOCK_SIZE as usize {
            for y in 0..BLOCK_SIZE as usize {
                if !cell_rows[y + 8 * z] {
                    continue;
                }
                let rows = [y + GRID * z, y + 1 + GRID * z, y + GRID * (z + 1), y + 1 + GRID * (z + 1)];
                let vm = rows.iter().fold(0x1FFu16, |m, &r| m & valid_rows[r]);
                let n = rows.map(|r| neg_rows[r]);
                let any = n[0] | n[1] | n[2] | n[3];
                let all = n[0] & n[1] & n[2] & n[3];
                // Cells whose 8 corners are usable and not all on one side.
                let mut crossing = vm & (vm >> 1) & (any | any >> 1) & !(all & all >> 1) & 0xFF;
                while crossing != 0 {
                    let x = crossing.trailing_zeros() as usize;
                    crossing &= crossing - 1;
                    let cell = IVec3::new(x as i32, y as i32, z as i32);
                    let base = x + GRID * (y + GRID * z);
                    // corner c = dx + 2 row: bit x + dx of row `row`
                    let case = (0..4).fold(0usize, |a, r| a | (((n[r] >> x) & 3) as usize) << (2 * r));
                    for tri in &cases[case] {
                        let mut idx = [0u32; 3];
                        for k in 0..3 {
                            let e = tri[k] as usize;
                            let (axis, start, corner) = EDGES[e];
                            let slot = (base + start) * 3 + axis;
                            if cache[slot] == u32::MAX {
                                cache[slot] = mesh.positions.len() as u32;
                                used.push(slot as u16);
                                let local = cell + corner;
                                // the edge's end points are usable grid points (gathered)
                                let (t0, t1) = (tsdf[base + start], tsdf[base + start + GRID_STEP[axis]]);
                                let t = t0 / (t0 - t1);
                                let mut p = ((origin + local).as_vec3() + Vec3::splat(0.5)) * vs;
                                p[axis] += t * vs;
                                mesh.positions.push(p);
                                mesh.edges.push(slot as u16);
                            }
                            idx[k] = cache[slot];
                        }
                        mesh.triangles.push(idx);
                    }
                }
            }
        }
        for &slot in used.iter() {
            cache[slot as usize] = u32::MAX;
        }
        used.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::block::BLOCK_VOXELS;
    use crate::TsdfConfig;
    use rand::{Rng, SeedableRng};
    use rustc_hash::FxHashSet;

    /// Voxels of a sphere's TSDF written directly (with unobserved and low-weight voxels
    /// sprinkled in), meshed incrementally, against dense marching cubes over every cell.
    #[test]
    fn block_meshes_equal_dense_marching_cubes() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let cfg = TsdfConfig { voxel_size_m: 0.1, trunc_voxels: 3.0, ..TsdfConfig::default() };
        let mut map = TsdfMap::new(cfg);
        let (centre, radius, trunc) = (Vec3::new(0.13, -0.21, 0.05), 1.1, 0.3);
        for z in -3..3 {
            for y in -3..3 {
                for x in -3..3 {
                    let key = IVec3::new(x, y, z);
                    let (id, _) = map.allocate(key);
                    let block = map.layer.block_mut(id);
                    for i in 0..BLOCK_VOXELS {
                        let l = IVec3::new(i as i32 % 8, i as i32 / 8 % 8, i as i32 / 64);
                        let p = ((key * BLOCK_SIZE + l).as_vec3() + Vec3::splat(0.5)) * cfg.voxel_size_m;
                        let sdf = p.distance(centre) - radius;
                        let weight = if sdf < -trunc || rng.random_bool(0.03) {
                            0.0
                        } else if rng.random_bool(0.05) {
                            0.5
                        } else {
                            rng.random_range(1.0..5.0)
                        };
                        let v = Voxel { tsdf: (sdf / trunc).min(1.0), weight, colour: [l.x as f32 / 8.0, 0.5, 0.25] };
                        block.set_voxel(i, v);
                    }
                    map.refresh_sign_flags(id);
                    // written directly, not by integrate: queue the block for meshing
                    map.mark_dirty(id);
                }
            }
        }
        let mesh = map.extract_mesh();
        // Dense reference: every cell whose 8 corners are observed with weight >= 1.
        let cases = &table().cases;
        let (mut triangles, mut edges) = (0usize, FxHashSet::default());
        for z in -24..24 {
            for y in -24..24 {
                for x in -24..24 {
                    let g = IVec3::new(x, y, z);
                    let corners: Option<Vec<Voxel>> = (0..8)
                        .map(|c| {
                            let v = map.voxel(g + IVec3::new(c & 1, (c >> 1) & 1, c >> 2))?;
                            (v.weight >= 1.0).then_some(v)
                        })
                        .collect();
                    let Some(corners) = corners else { continue };
                    let case = (0..8).fold(0, |a, c| a | ((corners[c].tsdf < 0.0) as usize) << c);
                    triangles += cases[case].len();
                    for tri in &cases[case] {
                        for &e in tri {
                            let o = edge_start(e as usize);
                            let s = g + IVec3::new(o as i32 & 1, (o as i32 >> 1) & 1, o as i32 >> 2);
                            edges.insert((s, edge_axis(e as usize) as u8));
                        }
                    }
                }
            }
        }
        assert!(triangles > 1000, "{triangles}");
        assert_eq!(mesh.triangles.len(), triangles);
        assert_eq!(mesh.positions.len(), edges.len());
        let got: FxHashSet<EdgeKey> = (0..map.layer.len())
            .flat_map(|id| {
                let origin = map.layer.key(id as u32) * BLOCK_SIZE;
                map.meshes[id].edges.iter().map(move |&s| {
                    let (l, axis) = edge_of_slot(s);
                    (origin + l, axis as u8)
                })
            })
            .collect();
        assert_eq!(got, edges);
    }
}
