//! Block allocation for integration: which 8^3 blocks a frame's truncation bands cross
//! ([`touched_blocks`]). Steps: summarise pixel tiles ([`TileStats`]), cover a tile's tube of
//! corner rays by the blocks of its bounding box (`cover_tube`), split tiles with a depth edge
//! into truncation-wide depth bins, and walk single pixels' band segments ([`walk_cells`]) where
//! no tube fits.

use glam::{IVec3, Vec3};
use rayon::prelude::*;
use rustc_hash::FxHashSet;
use sgam_core::{Camera, Rigid3};
use wide::{bytemuck::cast, f32x8, i32x8};

use crate::block::floor_ivec3;
use crate::TsdfConfig;

/// Which depth readings integrate: valid (finite, positive) and inside the depth range. With
/// `lo >= f32::MIN_POSITIVE` and `hi <= f32::MAX`, NaN, infinities, zero, subnormal, negative and
/// out-of-range readings all fail the two comparisons (vectorisable), so the frame's depth is
/// read as it is, without a cleaned copy.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Usable {
    pub(crate) lo: f32,
    pub(crate) hi: f32,
}

impl Usable {
    pub(crate) fn new(cfg: &TsdfConfig) -> Self {
        Self { lo: cfg.depth_min_m.max(f32::MIN_POSITIVE), hi: cfg.depth_max_m.min(f32::MAX) }
    }

    #[inline(always)]
    pub(crate) fn ok(self, d: f32) -> bool {
        (d >= self.lo) & (d <= self.hi)
    }
}

/// Usable-depth summary of a pixel rectangle.
#[derive(Clone, Copy)]
pub(crate) struct TileStats {
    pub(crate) min: f32,
    pub(crate) max: f32,
    pub(crate) count: usize,
}

impl TileStats {
    pub(crate) const EMPTY: TileStats = TileStats { min: f32::INFINITY, max: f32::NEG_INFINITY, count: 0 };

    /// Over the usable `depth[v * w + u]` for `u in u0..u1`, `v in v0..v1`.
    pub(crate) fn of(
        depth: &[f32],
        usable: Usable,
        w: usize,
        (u0, u1): (usize, usize),
        (v0, v1): (usize, usize),
    ) -> Self {
        // Eight lanes of masked selects (`wide`); a comparison with NaN is false, so unusable
        // readings never enter the minimum or maximum.
        let (lo, hi) = (f32x8::splat(usable.lo), f32x8::splat(usable.hi));
        let (mut mn, mut mx) = (f32x8::splat(f32::INFINITY), f32x8::splat(f32::NEG_INFINITY));
        let mut n = i32x8::splat(0);
        let mut add = |d: f32x8| {
            let ok = d.simd_ge(lo) & d.simd_le(hi);
            mn = (ok & d.simd_lt(mn)).select(d, mn);
            mx = (ok & d.simd_gt(mx)).select(d, mx);
            n -= cast::<f32x8, i32x8>(ok);
        };
        for v in v0..v1 {
            let row = &depth[v * w + u0..v * w + u1];
            let mut chunks = row.chunks_exact(8);
            for c in &mut chunks {
                add(f32x8::new(c.try_into().unwrap_or([f32::NAN; 8])));
            }
            let rest = chunks.remainder();
            if !rest.is_empty() {
                let mut c = [f32::NAN; 8];
                c[..rest.len()].copy_from_slice(rest);
                add(f32x8::new(c));
            }
        }
        Self {
            min: mn.to_array().iter().fold(f32::INFINITY, |a, &b| a.min(b)),
            max: mx.to_array().iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b)),
            count: n.to_array().iter().map(|&c| c as usize).sum(),
        }
    }

    fn merge(self, o: Self) -> Self {
        Self { min: self.min.min(o.min), max: self.max.max(o.max), count: self.count + o.count }
    }
}

/// The block keys crossed by every usable pixel's truncation band (any order), plus the number of
/// usable pixels ([`Usable`]). `depth` is the frame's, `w x h`.
///
/// Pixels are handled in tiles. In a tile whose usable depths span at most the truncation
/// distance, every pixel's band segment lies inside the "tube" bounded by the four corner
/// pixels' rays between planar depths `min - trunc` and `max + trunc`; while the tube's
/// cross-section is at most half a block, the tube usually lies in few blocks. The tube is the
/// convex hull of its eight corners, so the blocks of the corners' bounding box (computed
/// directly, no walks) hold it: every block a tile pixel's band crosses is allocated, and
/// where the tube's edges cross exactly a box of cells those are the same blocks. Tiles are
/// `2s x 2s` pixels when their own far end allows it (near surfaces), else `s x s` with `s`
/// chosen for the depth range's far end. A tile whose depths span more (a depth edge, a
/// slanted surface) is covered by one tube per occupied truncation-wide depth bin when its bins
/// average 16 pixels or more. Every pixel's own segment is walked instead where there is no tiling (`s = 1`), where
/// bins hold fewer pixels, and where a tube would need more than 64 cells.
pub(crate) fn touched_blocks(
    depth: &[f32],
    w: usize,
    h: usize,
    camera: &Camera,
    cfg: &TsdfConfig,
) -> (Vec<IVec3>, usize) {
    let trunc = cfg.trunc_m();
    let inv_trunc = 1.0 / trunc;
    let usable = Usable::new(cfg);
    let inv_block = 1.0 / cfg.block_size_m();
    let k = camera.intrinsics;
    let wfc: Rigid3 = camera.world_from_camera;
    if depth.len() < w * h || w == 0 || h == 0 {
        return (Vec::new(), 0);
    }
    let origin = wfc.translation * inv_block;
    let r = wfc.rotation;
    let (inv_fx, inv_fy) = (1.0 / k.fx, 1.0 / k.fy);
    let half_block = 0.5 * cfg.block_size_m();
    // Spread of an `s`-pixel tile's corner rays at planar depth `far`.
    let spread_m = |s: usize, far: f32| (s - 1) as f32 * far / k.fx.min(k.fy);
    let far_end = cfg.depth_max_m + trunc;
    let tile = [8usize, 4, 2].into_iter().find(|&s| spread_m(s, far_end) <= half_block).unwrap_or(1);
    let big = 2 * tile;
    // World ray (camera z = 1, block units) of pixel (u, v).
    let ray =
        |u: f32, v: f32| (r.x_axis * ((u - k.cx) * inv_fx) + r.y_axis * ((v - k.cy) * inv_fy) + r.z_axis) * inv_block;
    let (set, used) = (0..h.div_ceil(big))
        .into_par_iter()
        .fold(
            || (FxHashSet::<IVec3>::default(), 0usize),
            |(mut set, mut used), big_row| {
                // Direct-mapped cache of recently inserted cells: neighbouring pixels cross the
                // same blocks, so most cells are rejected with one comparison.
                let mut recent = [IVec3::MAX; 64];
                let mut insert = |cell: IVec3| {
                    let slot = (cell.x.wrapping_mul(73_856_093)
                        ^ cell.y.wrapping_mul(19_349_663)
                        ^ cell.z.wrapping_mul(83_492_791)) as usize
                        & 63;
                    if recent[slot] != cell {
                        recent[slot] = cell;
                        set.insert(cell);
                    }
                };
                // Covers the tube of the pixel rectangle's corner rays between planar depths
                // `z0 .. z1`; false when it would take more than 64 cells (walk pixels instead).
                let cover_tube = |(u0, u1): (usize, usize),
                                  (v0, v1): (usize, usize),
                                  z0: f32,
                                  z1: f32,
                                  insert: &mut dyn FnMut(IVec3)| {
                    let (ua, ub, va, vb) = (u0 as f32, (u1 - 1) as f32, v0 as f32, (v1 - 1) as f32);
                    // The tube is the convex hull of its 8 corners (4 rays x 2 depths), so it lies
                    // in their bounding box, and the cells of that box are exactly the cells the
                    // 4 edges' walks would span (a segment's extreme cells are its end cells).
                    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
                    for (u, v) in [(ua, va), (ub, va), (ua, vb), (ub, vb)] {
                        let dir = ray(u, v);
                        for p in [origin + dir * z0, origin + dir * z1] {
                            lo = lo.min(p);
                            hi = hi.max(p);
                        }
                    }
                    if !(lo.is_finite() && hi.is_finite()) {
                        return false;
                    }
                    let (lo, hi) = (floor_ivec3(lo), floor_ivec3(hi));
                    // in i64: far-away (saturated) corners must not overflow
                    let extent = (hi.as_i64vec3() - lo.as_i64vec3()).max(glam::I64Vec3::ZERO) + glam::I64Vec3::ONE;
                    if extent.max_element() > 64 || extent.element_product() > 64 {
                        return false;
                    }
                    for z in lo.z..=hi.z {
                        for y in lo.y..=hi.y {
                            for x in lo.x..=hi.x {
                                insert(IVec3::new(x, y, z));
                            }
                        }
                    }
                    true
                };
                // Walks the own band segment of every usable pixel of the rectangle whose depth
                // passes `select`.
                let walk_pixels = |(u0, u1): (usize, usize),
                                   (v0, v1): (usize, usize),
                                   select: &dyn Fn(f32) -> bool,
                                   insert: &mut dyn FnMut(IVec3)| {
                    for v in v0..v1 {
                        for u in u0..u1 {
                            let d = depth[v * w + u];
                            if usable.ok(d) && select(d) {
                                let dir = ray(u as f32, v as f32);
                                walk_cells(
                                    origin + dir * (d - trunc).max(0.0),
                                    origin + dir * (d + trunc),
                                    &mut *insert,
                                );
                            }
                        }
                    }
                };
                let bv0 = big_row * big;
                for bu0 in (0..w).step_by(big) {
                    // the (up to) four s x s tiles of this 2s x 2s tile
                    let mut subs = [((0, 0), (0, 0), TileStats::EMPTY); 4];
                    let mut n_subs = 0;
                    for v0 in [bv0, bv0 + tile] {
                        for u0 in [bu0, bu0 + tile] {
                            if u0 < w && v0 < h {
                                let (us, vs) = ((u0, (u0 + tile).min(w)), (v0, (v0 + tile).min(h)));
                                subs[n_subs] = (us, vs, TileStats::of(depth, usable, w, us, vs));
                                n_subs += 1;
                            }
                        }
                    }
                    let all = subs[..n_subs].iter().fold(TileStats::EMPTY, |a, s| a.merge(s.2));
                    if all.count == 0 {
                        continue;
                    }
                    used += all.count;
                    let (us, vs) = ((bu0, (bu0 + big).min(w)), (bv0, (bv0 + big).min(h)));
                    if tile > 1
                        && all.max - all.min <= trunc
                        && spread_m(big, all.max + trunc) <= half_block
                        && cover_tube(us, vs, (all.min - trunc).max(0.0), all.max + trunc, &mut insert)
                    {
                        continue;
                    }
                    for &(us, vs, t) in &subs[..n_subs] {
                        if t.count == 0 {
                            continue;
                        }
                        if tile == 1 {
                            walk_pixels(us, vs, &|_| true, &mut insert);
                            continue;
                        }
                        // Bin the tile's depths by truncation-wide bins from its nearest one (the
                        // last bin takes the rest): each occupied bin's pixels lie in the tube of
                        // the tile's corner rays over the bin's range. A depth edge occupies two
                        // or three bins.
                        let bin_of = |d: f32| ((d - t.min) * inv_trunc).clamp(0.0, 63.0) as u32;
                        let mut bins = 1u64;
                        if t.max - t.min > trunc {
                            for v in vs.0..vs.1 {
                                for &d in &depth[v * w + us.0..v * w + us.1] {
                                    bins |= (usable.ok(d) as u64) << bin_of(d);
                                }
                            }
                        }
                        // A tube covers more blocks than its pixels' own segments do, and every
                        // extra block costs a block update: only bins of at least 16 pixels
                        // (on average) are worth a tube; otherwise walk the pixels.
                        if bins.count_ones() > 1 && t.count < 16 * bins.count_ones() as usize {
                            walk_pixels(us, vs, &|_| true, &mut insert);
                            continue;
                        }
                        // A depth on a bin border may round into either bin: widen each tube by
                        // a hair (more than the rounding of `t.min + b * trunc` at this depth).
                        let hair = 1e-3 * trunc + 1e-6 * t.max;
                        while bins != 0 {
                            let b = bins.trailing_zeros();
                            bins &= bins - 1;
                            let lo = t.min + b as f32 * trunc - hair;
                            let hi = if bins == 0 { t.max } else { t.min + (b + 1) as f32 * trunc + hair };
                            if !cover_tube(us, vs, (lo - trunc).max(0.0), hi + trunc, &mut insert) {
                                walk_pixels(us, vs, &|d| bin_of(d) == b, &mut insert);
                            }
                        }
                    }
                }
                (set, used)
            },
        )
        .reduce(
            || (FxHashSet::default(), 0),
            |(a, na), (b, nb)| {
                let (mut big, small) = if a.len() >= b.len() { (a, b) } else { (b, a) };
                big.extend(small);
                (big, na + nb)
            },
        );
    (set.into_iter().collect(), used)
}

/// Visits every unit grid cell crossed by the segment `a -> b` (grid units), in order
/// (Amanatides-Woo traversal). Short cut: when the end cells are equal or face neighbours, the
/// segment lies in their union (a box), so exactly those cells are visited.
#[inline]
pub(crate) fn walk_cells(a: Vec3, b: Vec3, mut visit: impl FnMut(IVec3)) {
    if !(a.is_finite() && b.is_finite()) {
        return;
    }
    let mut cell = floor_ivec3(a);
    let end = floor_ivec3(b);
    let gap = (end - cell).abs();
    if gap.element_sum() <= 1 {
        visit(cell);
        if cell != end {
            visit(end);
        }
        return;
    }
    let dir = b - a;
    let step = IVec3::new(sign(dir.x), sign(dir.y), sign(dir.z));
    let next_boundary = |p: f32, c: i32, s: i32| if s > 0 { (c + 1) as f32 - p } else { p - c as f32 };
    let t_of = |dist: f32, dv: f32| if dv != 0.0 { dist / dv.abs() } else { f32::INFINITY };
    let mut t_max = Vec3::new(
        t_of(next_boundary(a.x, cell.x, step.x), dir.x),
        t_of(next_boundary(a.y, cell.y, step.y), dir.y),
        t_of(next_boundary(a.z, cell.z, step.z), dir.z),
    );
    let t_delta = Vec3::new(t_of(1.0, dir.x), t_of(1.0, dir.y), t_of(1.0, dir.z));
    let max_steps = (end - cell).abs().element_sum() + 4;
    visit(cell);
    for _ in 0..max_steps {
        if cell == end {
            return;
        }
        let axis = if t_max.x <= t_max.y && t_max.x <= t_max.z {
            0
        } else if t_max.y <= t_max.z {
            1
        } else {
            2
        };
        if t_max[axis] > 1.0 {
            return;
        }
        cell[axis] += step[axis];
        t_max[axis] += t_delta[axis];
        visit(cell);
    }
}

#[inline]
fn sign(x: f32) -> i32 {
    if x > 0.0 {
        1
    } else if x < 0.0 {
        -1
    } else {
        0
    }
}
