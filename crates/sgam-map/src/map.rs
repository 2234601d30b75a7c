//! The voxel-hashed TSDF map and its integration.

use glam::{IVec3, Vec3};
use rayon::prelude::*;
use sgam_core::{Camera, RgbdFrame, Rigid3};
use wide::{bytemuck::cast, f32x8, i32x8};

use crate::allocate::{touched_blocks, Usable};
use crate::block::{Block, Voxel, BLOCK_SIZE, BLOCK_VOXELS, ROWS};
use crate::layer::{disjoint_mut, BlockLayer};
use crate::mesh::BlockMesh;
use crate::TsdfConfig;

/// What one [`TsdfMap::integrate`] call did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IntegrateStats {
    /// Blocks intersected by the frame's truncation band (existing and new).
    pub blocks_touched: usize,
    /// Blocks newly allocated by this frame.
    pub blocks_allocated: usize,
    /// Blocks in which at least one voxel changed (these are marked dirty for meshing).
    pub blocks_updated: usize,
    /// Voxels updated.
    pub voxels_updated: usize,
    /// Pixels with a usable depth (valid and inside the depth range).
    pub pixels_used: usize,
}

/// A sparse voxel-hashed colour TSDF: a hash map from block key (`IVec3`) to dense 8^3 blocks
/// ([`Block`]), plus a marching-cubes mesh cached per block.
///
/// Geometry: global voxel `g` (integer, world axes) has its centre at
/// `(g + 0.5) * voxel_size_m` in world coordinates; block key `k` holds voxels `8 k ..= 8 k + 7`.
#[derive(Debug, Clone)]
pub struct TsdfMap {
    pub(crate) config: TsdfConfig,
    /// The blocks, their keys and neighbours (ids index `meshes` and the per-block state
    /// below too).
    pub(crate) layer: BlockLayer,
    pub(crate) meshes: Vec<BlockMesh>,
    /// Blocks whose voxels changed since their neighbourhood was last meshed.
    pub(crate) dirty: Vec<u32>,
    pub(crate) is_dirty: Vec<bool>,
    /// Per block: [`HAS_POSITIVE`] / [`HAS_NEGATIVE`] over its observed voxels.
    pub(crate) sign_flags: Vec<u8>,
    /// Per block, per voxel row (`y + 8 z`): the same summary over the row, so that an
    /// integration which leaves a row alone need not read it to refresh `sign_flags`.
    pub(crate) row_flags: Vec<[u8; ROWS]>,
    /// Per block: its place in allocation order, kept when the block is evicted and restored
    /// ([`crate::stream`]), so the rasterizer's tie-breaks (earlier first) do not depend on
    /// where a block's id ended up.
    pub(crate) order: Vec<u64>,
    /// The next allocation's `order`.
    pub(crate) next_order: u64,
}

impl TsdfMap {
    /// An empty map. The configuration is used as given; call [`TsdfConfig::validate`] first for
    /// user input (a non-positive voxel size makes every integration a no-op).
    pub fn new(config: TsdfConfig) -> Self {
        Self {
            config,
            layer: BlockLayer::default(),
            meshes: Vec::new(),
            dirty: Vec::new(),
            is_dirty: Vec::new(),
            sign_flags: Vec::new(),
            row_flags: Vec::new(),
            order: Vec::new(),
            next_order: 0,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &TsdfConfig {
        &self.config
    }

    /// Number of allocated blocks.
    pub fn block_count(&self) -> usize {
        self.layer.len()
    }

    /// Approximate heap memory in bytes (voxels, hash indices and cached meshes).
    pub fn memory_bytes(&self) -> usize {
        let block = std::mem::size_of::<Voxel>() * BLOCK_VOXELS + std::mem::size_of::<Block>();
        let per_block = block
            + std::mem::size_of::<IVec3>() * 2
            + std::mem::size_of::<u32>() * 2
            + std::mem::size_of::<BlockMesh>()
            + std::mem::size_of::<bool>()
            + std::mem::size_of::<[u32; 8]>() * 2
            + std::mem::size_of::<[u8; ROWS]>()
            + std::mem::size_of::<u64>()
            + 1;
        let meshes: usize = self.meshes.iter().map(BlockMesh::heap_bytes).sum();
        self.layer.capacity() * per_block + meshes + self.layer.super_block_count() * 64
    }

    /// Sorted keys of all allocated blocks.
    pub fn block_keys(&self) -> Vec<IVec3> {
        let mut k = self.layer.keys().to_vec();
        k.sort_unstable_by_key(|k| (k.x, k.y, k.z));
        k
    }

    /// The block with key `key`, if allocated.
    pub fn block(&self, key: IVec3) -> Option<&Block> {
        self.layer.block_at(key)
    }

    /// The voxel at global voxel index `g`, if its block is allocated.
    #[inline]
    pub fn voxel(&self, g: IVec3) -> Option<Voxel> {
        let k = crate::block::block_of_voxel(g);
        let l = crate::block::voxel_in_block(g);
        self.block(k).map(|b| b.voxel(crate::block::local_index(l.x, l.y, l.z)))
    }

    /// Allocates the block `key` if needed and returns its id.
    pub(crate) fn allocate(&mut self, key: IVec3) -> (u32, bool) {
        let (id, new) = self.layer.allocate(key);
        if new {
            self.meshes.push(BlockMesh::default());
            self.is_dirty.push(false);
            self.sign_flags.push(0);
            self.row_flags.push([0; ROWS]);
            self.order.push(self.next_order);
            self.next_order += 1;
        }
        (id, new)
    }

    /// Recomputes the sign summary of block `id` from its voxels.
    pub(crate) fn refresh_sign_flags(&mut self, id: u32) {
        let rows = row_flags_of(self.layer.block(id));
        self.sign_flags[id as usize] = block_flags(&rows);
        self.row_flags[id as usize] = rows;
    }

    pub(crate) fn mark_dirty(&mut self, id: u32) {
        if !self.is_dirty[id as usize] {
            self.is_dirty[id as usize] = true;
            self.dirty.push(id);
        }
    }

    /// Fuses one RGB-D frame seen by `camera` (planar depth, metres; sRGB colour).
    ///
    /// 1. Allocation: every block crossed by some usable pixel's band segment (planar depth
    ///    `depth - trunc .. depth + trunc` along its ray; usable = valid and inside
    ///    `[depth_min_m, depth_max_m]`) is allocated. Smooth pixel tiles are handled through
    ///    their four corner rays (a small, conservative superset, see the coverage test); new
    ///    keys are allocated in sorted order.
    /// 2. In parallel over those blocks (rayon), each voxel centre is projected into the image;
    ///    with the depth `d` at the nearest pixel and the voxel's planar depth `z`,
    ///    `sdf = d - z`; voxels with `sdf < -trunc` are left alone, the others get
    ///    `o = min(1, sdf / trunc)` and the paper's running average
    ///    `tsdf = (w tsdf + o) / (w + 1)`, `w += 1` (colour the same way). With a weight cap
    ///    `c`, `w` is clamped to `c - 1` before the update so the weight never exceeds `c`.
    ///
    /// Cost depends on the frame only (pixels and touched blocks), never on the map size.
    /// Changed blocks are marked dirty for [`TsdfMap::update_mesh`]. A frame whose size differs
    /// from the intrinsics is read at its own size (projections outside it are skipped); a
    /// non-finite pose integrates nothing.
    pub fn integrate(&mut self, frame: &RgbdFrame, camera: &Camera) -> IntegrateStats {
        let cfg = self.config;
        let mut stats = IntegrateStats::default();
        let positive = |x: f32| x.is_finite() && x > 0.0;
        if !camera.world_from_camera.is_finite() || !positive(cfg.voxel_size_m) || !positive(cfg.trunc_voxels) {
            return stats;
        }
        let depth = &frame.depth_m.data[..];
        let (w, h) = (frame.depth_m.width as usize, frame.depth_m.height as usize);
        let (keys, pixels_used) = touched_blocks(depth, w, h, camera, &cfg);
        stats.pixels_used = pixels_used;
        stats.blocks_touched = keys.len();
        // Existing blocks are looked up in parallel; new keys are allocated in sorted order (ids
        // do not depend on the hash set's iteration order).
        let layer = &self.layer;
        let found: Vec<Option<u32>> = keys.par_iter().map(|k| layer.id_of(*k)).collect();
        let mut new_keys: Vec<IVec3> = keys.iter().zip(&found).filter(|(_, f)| f.is_none()).map(|(k, _)| *k).collect();
        new_keys.sort_unstable_by_key(|k| (k.x, k.y, k.z));
        let mut ids: Vec<u32> = found.into_iter().flatten().collect();
        for k in new_keys {
            ids.push(self.allocate(k).0);
            stats.blocks_allocated += 1;
        }
        ids.par_sort_unstable();
        let camera_from_world = camera.world_from_camera.inverse();
        let ctx = UpdateContext::new(frame, camera, &camera_from_world, &cfg);
        let updated: Vec<(u32, usize, u8)> = {
            let (blocks, keys_of) = self.layer.blocks_mut(&ids);
            let rows = disjoint_mut(&mut self.row_flags, &ids);
            // Visit the blocks in image order (Morton order of where their centres project), so
            // that the frame's depth and colour pixels read by consecutive blocks are cache-warm
            // and each thread's share covers one part of the image.
            let mut work: Vec<(u64, &mut Block, &mut [u8; ROWS], u32)> = blocks
                .into_par_iter()
                .zip(rows)
                .zip(&ids)
                .map(|((b, r), &id)| (ctx.image_order(keys_of[id as usize]), b, r, id))
                .collect();
            work.par_sort_unstable_by_key(|w| w.0);
            work.into_par_iter()
                .map(|(_, block, rows, id)| {
                    let (n, flags) = ctx.update_block(block, rows, keys_of[id as usize]);
                    (id, n, flags)
                })
                .collect()
        };
        for (id, n, flags) in updated {
            self.sign_flags[id as usize] = flags;
            if n > 0 {
                stats.blocks_updated += 1;
                stats.voxels_updated += n;
                self.mark_dirty(id);
            }
        }
        stats
    }
}

/// Per-frame constants of the voxel update.
struct UpdateContext<'a> {
    /// The frame's depth; only [`Usable`] readings integrate.
    depth: &'a [f32],
    usable: Usable,
    colour: &'a [[f32; 3]],
    width: usize,
    height: usize,
    camera_from_world: Rigid3,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    voxel_size_m: f32,
    trunc_m: f32,
    weight_cap: f32,
}

/// Sign summary bits of a block: some observed voxel is in front of / behind the surface.
pub(crate) const HAS_POSITIVE: u8 = 1;
pub(crate) const HAS_NEGATIVE: u8 = 2;

impl<'a> UpdateContext<'a> {
    fn new(frame: &'a RgbdFrame, camera: &'a Camera, camera_from_world: &Rigid3, cfg: &TsdfConfig) -> Self {
        let k = camera.intrinsics;
        let (width, height) = (frame.depth_m.width as usize, frame.depth_m.height as usize);
        let colour_ok = frame.colour.data.len() == width * height;
        Self {
            depth: &frame.depth_m.data,
            usable: Usable::new(cfg),
            colour: if colour_ok { &frame.colour.data } else { &[] },
            width,
            height,
            camera_from_world: *camera_from_world,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            voxel_size_m: cfg.voxel_size_m,
            trunc_m: cfg.trunc_m(),
            weight_cap: cfg.weight_cap.unwrap_or(f32::INFINITY),
        }
    }

    /// Sort key of block `key` in image order: the Morton code of the 16-pixel tile its centre
    /// projects into (`u64::MAX` behind the camera).
    fn image_order(&self, key: IVec3) -> u64 {
        let centre = (key.as_vec3() + Vec3::splat(0.5)) * (self.voxel_size_m * BLOCK_SIZE as f32);
        let p = self.camera_from_world.transform_point(centre);
        if p.z.is_nan() || p.z <= 0.0 {
            return u64::MAX;
        }
        let tile = |x: f32, extent: usize| ((x / 16.0).clamp(0.0, (extent / 16) as f32) as u32).min(0xFFFF);
        let u = tile(self.fx * p.x / p.z + self.cx, self.width);
        let v = tile(self.fy * p.y / p.z + self.cy, self.height);
        // interleave the bits of u and v
        let spread = |mut x: u64| {
            x = (x | x << 8) & 0x00FF_00FF;
            x = (x | x << 4) & 0x0F0F_0F0F;
            x = (x | x << 2) & 0x3333_3333;
            (x | x << 1) & 0x5555_5555
        };
        spread(u as u64) | spread(v as u64) << 1
    }

    /// Updates one block; returns the number of voxels changed and the block's sign summary
    /// (`rows` holds the per-row summaries and is kept up to date).
    ///
    /// Voxel centres along a block row are an arithmetic progression in camera space, so each
    /// row is projected in one branch-free pass over its 8 voxels (8-lane SIMD, `wide`).
    /// A row none of whose voxels takes the observation (behind the surface, outside the image)
    /// is not touched at all: no voxel memory is read or written, its summary is reused. In the
    /// other rows the update is branch-free (voxels that take no observation are rewritten with
    /// their own values), as surfaces make the in-band test unpredictable.
    #[inline(never)]
    fn update_block(&self, block: &mut Block, rows: &mut [u8; ROWS], key: IVec3) -> (usize, u8) {
        const N: usize = BLOCK_SIZE as usize;
        let depth = &self.depth[..self.width * self.height];
        if depth.is_empty() {
            return (0, block_flags(rows));
        }
        let vs = self.voxel_size_m;
        let origin = (key * BLOCK_SIZE).as_vec3() + Vec3::splat(0.5);
        let r = self.camera_from_world.rotation;
        let base = self.camera_from_world.transform_point(origin * vs);
        let (dx, dy, dz) = (r.x_axis * vs, r.y_axis * vs, r.z_axis * vs);
        let colour = self.colour;
        let has_colour = colour.len() == depth.len();
        let last = depth.len() - 1;
        let splat = f32x8::splat;
        let lane = f32x8::new([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        // Camera-space offsets of the 8 voxels of a row from its first.
        let (lx, ly, lz) = (lane * dx.x, lane * dx.y, lane * dx.z);
        let (fx, fy) = (splat(self.fx), splat(self.fy));
        // `+ 0.5` folded in: the pixel nearest to `u` is `trunc(u + 0.5)` for `u >= -0.5`.
        let (cx, cy) = (splat(self.cx + 0.5), splat(self.cy + 0.5));
        let (u_end, v_end) = (splat(self.width as f32), splat(self.height as f32));
        let width = i32x8::splat(self.width as i32);
        let (zero, one) = (splat(0.0), splat(1.0));
        let (lo, hi) = (splat(self.usable.lo), splat(self.usable.hi));
        let neg_trunc = splat(-self.trunc_m);
        let inv_trunc = splat(1.0 / self.trunc_m);
        let cap_prev = splat(self.weight_cap - 1.0);
        let nan = splat(f32::NAN);
        let mut n = 0usize;
        let mut flags = 0u8;
        let planes = &mut *block.planes;
        // Pass 1: project every row and gather its depth readings. It has no data-dependent
        // branch, so the gathers' cache misses overlap instead of each stalling a branch.
        let mut pixels = [[0u32; N]; ROWS];
        let mut depths = [zero; ROWS];
        let mut planar = [zero; ROWS];
        for row_index in 0..ROWS {
            let (y, z) = (row_index % N, row_index / N);
            let p = base + dy * y as f32 + dz * z as f32;
            // Projection of the row's voxel centres, 8 lanes at once: pixel index (0 outside
            // the image) and planar depth (NaN outside, so the take test fails).
            let pz = splat(p.z) + lz;
            let iz = one / pz;
            let u = fx * (splat(p.x) + lx) * iz + cx;
            let v = fy * (splat(p.y) + ly) * iz + cy;
            let inside = pz.simd_gt(zero) & u.simd_ge(zero) & v.simd_ge(zero) & u.simd_lt(u_end) & v.simd_lt(v_end);
            let at = (v.fast_trunc_int() * width + u.fast_trunc_int()) & cast::<f32x8, i32x8>(inside);
            let at = at.to_array();
            let mut d = [0.0f32; N];
            for i in 0..N {
                let pix = (at[i] as usize).min(last);
                pixels[row_index][i] = pix as u32;
                d[i] = depth[pix];
            }
            depths[row_index] = f32x8::new(d);
            planar[row_index] = inside.select(pz, nan);
        }
        // Pass 2: the updates.
        for row_index in 0..ROWS {
            let d = depths[row_index];
            let sdf = d - planar[row_index];
            let take = sdf.simd_ge(neg_trunc) & d.simd_ge(lo) & d.simd_le(hi);
            let bits = take.to_bitmask();
            if bits == 0 {
                flags |= rows[row_index];
                continue;
            }
            // The running averages; lanes that take no observation keep their values.
            let (tsdf, weight) = (&mut planes.tsdf[row_index], &mut planes.weight[row_index]);
            let (t_old, w_old) = (f32x8::new(*tsdf), f32x8::new(*weight));
            let obs = (sdf * inv_trunc).min(one);
            let wp = w_old.min(cap_prev);
            let inv = one / (wp + one);
            let t_new = take.select((t_old * wp + obs) * inv, t_old);
            let w_new = take.select(wp + one, w_old);
            *tsdf = t_new.to_array();
            *weight = w_new.to_array();
            if has_colour {
                let mut c = [[0.0f32; N]; 3];
                for i in 0..N {
                    let rgb = colour[pixels[row_index][i] as usize];
                    for ch in 0..3 {
                        c[ch][i] = rgb[ch];
                    }
                }
                for ch in 0..3 {
                    let plane = &mut planes.colour[ch][row_index];
                    let (old, c) = (f32x8::new(*plane), f32x8::new(c[ch]));
                    *plane = take.select((old * wp + c) * inv, old).to_array();
                }
            }
            n += bits.count_ones() as usize;
            rows[row_index] = row_flags(t_new, w_new);
            flags |= rows[row_index];
        }
        (n, flags)
    }
}

/// A block's sign summary from its rows' summaries.
fn block_flags(rows: &[u8; ROWS]) -> u8 {
    rows.iter().fold(0, |a, &r| a | r)
}

/// The sign summaries ([`HAS_POSITIVE`] / [`HAS_NEGATIVE`]) of a block's voxel rows.
fn row_flags_of(block: &Block) -> [u8; ROWS] {
    let p = &block.planes;
    std::array::from_fn(|r| row_flags(f32x8::new(p.tsdf[r]), f32x8::new(p.weight[r])))
}

/// The sign summary of one voxel row: some observed voxel (`weight > 0`) has `tsdf >= 0` /
/// `tsdf < 0`. (Voxel values are finite: integration keeps them so and loading checks.)
#[inline(always)]
fn row_flags(tsdf: f32x8, weight: f32x8) -> u8 {
    let zero = f32x8::splat(0.0);
    let observed = weight.simd_gt(zero).to_bitmask();
    let negative = tsdf.simd_lt(zero).to_bitmask();
    ((observed & !negative != 0) as u8 * HAS_POSITIVE) | ((observed & negative != 0) as u8 * HAS_NEGATIVE)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::allocate::{walk_cells, TileStats};
    use crate::layer::{corner_offset, NONE};
    use rand::{Rng, SeedableRng};
    use rustc_hash::FxHashSet;

    /// Brute force: cells containing dense samples of the segment.
    fn sampled_cells(a: Vec3, b: Vec3) -> FxHashSet<IVec3> {
        (0..=20_000).map(|i| (a + (b - a) * (i as f32 / 20_000.0)).floor().as_ivec3()).collect()
    }

    #[test]
    fn walk_cells_visits_the_cells_the_segment_crosses() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for _ in 0..2000 {
            let a = Vec3::new(rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0));
            let len = if rng.random_bool(0.5) { 0.9 } else { 3.0 };
            let d = Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
            let b = a + d * len;
            let mut visited = FxHashSet::default();
            walk_cells(a, b, |c| {
                visited.insert(c);
            });
            let sampled = sampled_cells(a, b);
            // Every sampled cell is visited; visited cells are face-connected neighbours of the
            // sampled ones (corner grazing within f32 rounding).
            assert!(sampled.is_subset(&visited), "{a} -> {b}: {sampled:?} vs {visited:?}");
            assert!(visited.len() <= sampled.len() + 2, "{a} -> {b}: {sampled:?} vs {visited:?}");
        }
    }

    #[test]
    fn tile_stats_match_a_scalar_fold() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let usable = Usable { lo: 0.1, hi: 4.0 };
        let specials = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1.0, 0.0, 0.1, 4.0, 4.0001, 1e-40];
        let (w, h) = (37usize, 11usize);
        let depth: Vec<f32> = (0..w * h)
            .map(|_| {
                if rng.random_bool(0.2) {
                    specials[rng.random_range(0..specials.len())]
                } else {
                    rng.random_range(0.0..5.0)
                }
            })
            .collect();
        // rectangles with and without a remainder after whole 8-pixel chunks, and empty ones
        for (us, vs) in
            [((0, 37), (0, 11)), ((3, 11), (2, 9)), ((8, 24), (0, 1)), ((5, 5), (0, 11)), ((36, 37), (10, 11))]
        {
            let t = TileStats::of(&depth, usable, w, us, vs);
            let (mut mn, mut mx, mut n) = (f32::INFINITY, f32::NEG_INFINITY, 0);
            for v in vs.0..vs.1 {
                for &d in &depth[v * w + us.0..v * w + us.1] {
                    if usable.ok(d) {
                        mn = mn.min(d);
                        mx = mx.max(d);
                        n += 1;
                    }
                }
            }
            assert_eq!((t.min, t.max, t.count), (mn, mx, n), "rectangle {us:?} x {vs:?}");
        }
    }

    #[test]
    fn tile_allocation_covers_every_pixel_band() {
        use sgam_core::{Image, Intrinsics, Vec2};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for (fx, voxel, trunc_voxels, depth_max) in [(585.0, 0.02, 4.0, 4.0), (355.0, 0.05, 10.0, 20.0)] {
            let (w, h) = (160u32, 120u32);
            let k = Intrinsics::try_new(w, h, fx, fx, 80.0, 60.0).unwrap();
            let cam =
                Camera::new(k, Rigid3::look_at(Vec3::new(0.3, -0.2, 0.1), Vec3::new(1.0, 2.0, 3.0), Vec3::Z).unwrap());
            // A tilted plane with a step (depth edge), noise and holes.
            let depth: Vec<f32> = (0..w * h)
                .map(|i| {
                    let (u, v) = ((i % w) as f32, (i / w) as f32);
                    if rng.random_bool(0.02) {
                        return 0.0;
                    }
                    let step = if (50.0..70.0).contains(&u) { -0.6 } else { 0.0 };
                    0.3 * depth_max + 0.004 * u + 0.002 * v + step + rng.random_range(-0.01..0.01)
                })
                .collect();
            let frame =
                RgbdFrame::try_new(Image::filled(w, h, [0.5; 3]), Image::try_from_vec(w, h, depth.clone()).unwrap())
                    .unwrap();
            let cfg = TsdfConfig {
                voxel_size_m: voxel,
                trunc_voxels,
                depth_min_m: 0.1,
                depth_max_m: depth_max,
                weight_cap: None,
                weight_threshold: 1.0,
            };
            let (keys, used) = touched_blocks(&frame.depth_m.data, w as usize, h as usize, &cam, &cfg);
            let got: FxHashSet<IVec3> = keys.iter().copied().collect();
            let trunc = cfg.trunc_m();
            let inv_block = 1.0 / cfg.block_size_m();
            let mut reference = FxHashSet::default();
            let mut n = 0;
            for (i, &d) in depth.iter().enumerate() {
                if !sgam_core::is_valid_depth(d) {
                    continue;
                }
                n += 1;
                let uv = Vec2::new((i as u32 % w) as f32, (i as u32 / w) as f32);
                let a = cam.unproject_world(uv, (d - trunc).max(0.0)) * inv_block;
                let b = cam.unproject_world(uv, d + trunc) * inv_block;
                walk_cells(a, b, |c| {
                    reference.insert(c);
                });
            }
            assert_eq!(used, n);
            let missing: Vec<_> = reference.difference(&got).collect();
            assert!(missing.is_empty(), "{} of {} blocks missed: {missing:?}", missing.len(), reference.len());
            assert!(got.len() <= reference.len() * 3 / 2, "{} vs {}", got.len(), reference.len());
        }
    }

    #[test]
    fn neighbour_tables_match_the_hash_index() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut map = TsdfMap::new(TsdfConfig::default());
        for _ in 0..400 {
            let k = IVec3::new(rng.random_range(-4..4), rng.random_range(-4..4), rng.random_range(-4..4));
            map.allocate(k);
        }
        let layer = &map.layer;
        for (id, &k) in layer.keys().iter().enumerate() {
            for o in 0..8 {
                let at = |key: IVec3| layer.id_of(key).unwrap_or(NONE);
                assert_eq!(layer.upper(id as u32)[o], at(k + corner_offset(o)), "{k} + {o}");
                assert_eq!(layer.lower(id as u32)[o], at(k - corner_offset(o)), "{k} - {o}");
            }
        }
    }

    #[test]
    fn disjoint_mut_returns_the_requested_blocks() {
        let mut blocks: Vec<Block> = (0..10)
            .map(|i| {
                let mut b = Block::default();
                b.set_voxel(0, Voxel { weight: i as f32, ..Voxel::EMPTY });
                b
            })
            .collect();
        let got = disjoint_mut(&mut blocks, &[0, 3, 4, 9]);
        let w: Vec<f32> = got.iter().map(|b| b.voxel(0).weight).collect();
        assert_eq!(w, vec![0.0, 3.0, 4.0, 9.0]);
    }
}
