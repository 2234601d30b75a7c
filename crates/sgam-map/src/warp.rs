//! Inverse warping of colour from source keyframes with a geometry (depth) check.

use rayon::prelude::*;

use crate::block::{floor_i32, floor_i32x8};
use sgam_core::{is_valid_depth, Camera, Image, RgbdFrame, Rigid3, Vec2, Vec3};
use wide::f32x8;

/// Tolerances and policy of [`warp_colour`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WarpConfig {
    /// Relative depth tolerance: accept when `|d_source - z| <= abs + rel * z`.
    pub depth_rel_tolerance: f32,
    /// Absolute depth tolerance in metres (see `depth_rel_tolerance`).
    pub depth_abs_tolerance_m: f32,
    /// How to choose among the sources that pass the depth check.
    pub selection: SourceSelection,
}

impl Default for WarpConfig {
    /// 2 % relative + 1 cm absolute; smallest depth disagreement wins.
    fn default() -> Self {
        Self { depth_rel_tolerance: 0.02, depth_abs_tolerance_m: 0.01, selection: SourceSelection::SmallestDepthError }
    }
}

/// Which accepted source supplies a pixel's colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SourceSelection {
    /// Smallest relative depth disagreement `|d_source - z| / z`; ties go to the source camera
    /// nearest the target camera, then to the lower index.
    #[default]
    SmallestDepthError,
    /// Source camera nearest the target camera (centre distance); ties go to the smaller depth
    /// disagreement, then to the lower index.
    NearestCamera,
}

/// One source keyframe: its camera and its RGB-D frame (sizes must match the intrinsics; a
/// mismatching source is ignored).
#[derive(Debug, Clone, Copy)]
pub struct SourceView<'a> {
    /// The source camera.
    pub camera: &'a Camera,
    /// The source frame (sRGB colour, planar depth in metres).
    pub frame: &'a RgbdFrame,
}

/// Output of [`warp_colour`], at the target camera's resolution.
#[derive(Debug, Clone, PartialEq)]
pub struct Warped {
    /// Warped sRGB colour in `[0, 1]`; black where missing.
    pub colour: Image<[f32; 3]>,
    /// Row-major `[H, W]`; true where the target has no valid depth or no source passed the check.
    pub missing: Vec<bool>,
    /// Index into `sources` of the source used per pixel; `-1` = none.
    pub source_index: Image<i32>,
}

/// Inverse warping with a geometry check.
///
/// For every target pixel `(u, v)` with valid depth `z_t` in `target_depth_m` (e.g. the map's
/// render): back-project to the world, project into every source camera (giving continuous
/// pixel `(us, vs)` and planar depth `z_s`), **sample the source depth at that location**
/// (bilinear over the 4 neighbouring pixels when all are valid, else the nearest pixel if
/// valid) and accept the source when `|d_source - z_s| <= depth_abs_tolerance_m +
/// depth_rel_tolerance * z_s`. Occluded or disoccluded points fail this test. Among accepted
/// sources the best is chosen per [`WarpConfig::selection`]; its colour is bilinearly sampled
/// at `(us, vs)` (edge-clamped). Pixels without depth or without an accepted source are
/// `missing`. Deterministic; parallel over rows (rayon), 8 target pixels at a time (SIMD,
/// `wide`): projection, depth test and source choice run lane-wise, only the source pixel
/// reads are scalar.
pub fn warp_colour(
    target: &Camera,
    target_depth_m: &Image<f32>,
    sources: &[SourceView<'_>],
    config: &WarpConfig,
) -> Warped {
    let (w, h) = (target_depth_m.width as usize, target_depth_m.height as usize);
    let mut colour = vec![[0.0f32; 3]; w * h];
    let mut missing = vec![true; w * h];
    let mut index = vec![-1i32; w * h];
    let target_ok = target.world_from_camera.is_finite() && target_depth_m.data.len() == w * h;
    // Per source: nearest camera first, so with `NearestCamera` a pixel stops looking at the
    // first source farther than an accepted one.
    let mut prepared: Vec<Prepared<'_>> = sources
        .iter()
        .enumerate()
        .filter(|(_, s)| {
            let k = s.camera.intrinsics;
            s.frame.depth_m.size() == (k.width, k.height)
                && s.frame.colour.size() == (k.width, k.height)
                && s.camera.world_from_camera.is_finite()
                && k.width > 0
                && k.height > 0
        })
        .map(|(i, s)| Prepared::new(i, s, target))
        .collect();
    prepared.sort_by(|a, b| a.dist.total_cmp(&b.dist).then(a.index.cmp(&b.index)));
    if target_ok && w > 0 && !prepared.is_empty() {
        let kernel = WarpKernel::new(target, &prepared, config);
        colour.par_chunks_mut(w).zip(missing.par_chunks_mut(w)).zip(index.par_chunks_mut(w)).enumerate().for_each(
            |(v, ((crow, mrow), irow))| {
                kernel.row(v, &target_depth_m.data[v * w..(v + 1) * w], crow, mrow, irow);
            },
        );
    }
    Warped {
        colour: Image { width: w as u32, height: h as u32, data: colour },
        missing,
        source_index: Image { width: w as u32, height: h as u32, data: index },
    }
}

/// One source, ready for the kernel: `source_from_target`, intrinsics, pixels.
struct Prepared<'a> {
    /// Index into the caller's `sources`.
    index: usize,
    /// Distance between the source and target camera centres.
    dist: f32,
    source_from_target: Rigid3,
    /// `source_from_target.rotation * (1 / fx_target, 0, 0)`: the step of a target ray (z = 1)
    /// from one pixel to the next along a row, in the source frame.
    ray_step: Vec3,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: usize,
    height: usize,
    depth: &'a Image<f32>,
    colour: &'a Image<[f32; 3]>,
}

impl<'a> Prepared<'a> {
    fn new(index: usize, s: &SourceView<'a>, target: &Camera) -> Self {
        let k = s.camera.intrinsics;
        let source_from_target = s.camera.world_from_camera.inverse() * target.world_from_camera;
        Self {
            index,
            dist: s.camera.centre_world().distance(target.centre_world()),
            source_from_target,
            ray_step: source_from_target.rotation * Vec3::new(1.0 / target.intrinsics.fx, 0.0, 0.0),
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            width: k.width as usize,
            height: k.height as usize,
            depth: &s.frame.depth_m,
            colour: &s.frame.colour,
        }
    }
}

/// Per-call constants of the 8-lane warp.
struct WarpKernel<'a, 'b> {
    sources: &'b [Prepared<'a>],
    /// Target intrinsics.
    fx: f32,
    cx: f32,
    fy: f32,
    cy: f32,
    nearest_wins: bool,
    abs_tol: f32,
    rel_tol: f32,
}

impl<'a, 'b> WarpKernel<'a, 'b> {
    fn new(target: &Camera, sources: &'b [Prepared<'a>], config: &WarpConfig) -> Self {
        let k = target.intrinsics;
        Self {
            sources,
            fx: k.fx,
            cx: k.cx,
            fy: k.fy,
            cy: k.cy,
            nearest_wins: config.selection == SourceSelection::NearestCamera,
            abs_tol: config.depth_abs_tolerance_m,
            rel_tol: config.depth_rel_tolerance,
        }
    }

    /// Warps target row `v` (`depth` is its depth row).
    fn row(&self, v: usize, depth: &[f32], crow: &mut [[f32; 3]], mrow: &mut [bool], irow: &mut [i32]) {
        // Target ray (z = 1) of pixel (u, v) is `(x0 + u / fx, y, 1)`; in each source frame the
        // point at planar depth z is `z * (a + u b) + t` with `a = R ray(0, v)`, `b = R e_x / fx`.
        let ray0 = Vec3::new(-self.cx / self.fx, (v as f32 - self.cy) / self.fy, 1.0);
        let rows: Vec<(Vec3, Vec3)> =
            self.sources.iter().map(|s| (s.source_from_target.rotation * ray0, s.ray_step)).collect();
        let lane = f32x8::new([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        let (zero, half) = (f32x8::splat(0.0), f32x8::splat(0.5));
        for u0 in (0..depth.len()).step_by(L) {
            let n = L.min(depth.len() - u0);
            let mut z = [0.0f32; L];
            z[..n].copy_from_slice(&depth[u0..u0 + n]);
            let z = f32x8::new(z);
            let valid = valid_depth8(z);
            if valid.to_bitmask() == 0 {
                continue;
            }
            let u = f32x8::splat(u0 as f32) + lane;
            // Per lane: best key so far (primary, secondary), source position, sample location.
            let mut has_best = f32x8::splat(0.0).simd_gt(zero); // all false
            let (mut best_p, mut best_s) = (f32x8::splat(f32::INFINITY), f32x8::splat(f32::INFINITY));
            let mut best_j = f32x8::splat(-1.0);
            let (mut best_us, mut best_vs) = (zero, zero);
            for (j, (s, &(a, b))) in self.sources.iter().zip(&rows).enumerate() {
                let dist = f32x8::splat(s.dist);
                // With `NearestCamera`, a lane that accepted a nearer source is done.
                let mut active = valid;
                if self.nearest_wins {
                    active &= !(has_best & dist.simd_gt(best_p));
                    if active.to_bitmask() == 0 {
                        break; // later sources are at least as far
                    }
                }
                let t = s.source_from_target.translation;
                let px = (f32x8::splat(a.x) + f32x8::splat(b.x) * u) * z + f32x8::splat(t.x);
                let py = (f32x8::splat(a.y) + f32x8::splat(b.y) * u) * z + f32x8::splat(t.y);
                let pz = (f32x8::splat(a.z) + f32x8::splat(b.z) * u) * z + f32x8::splat(t.z);
                let iz = f32x8::splat(1.0) / pz;
                let us = f32x8::splat(s.fx) * px * iz + f32x8::splat(s.cx);
                let vs = f32x8::splat(s.fy) * py * iz + f32x8::splat(s.cy);
                let inside = active
                    & pz.simd_gt(zero)
                    & us.simd_ge(-half)
                    & vs.simd_ge(-half)
                    & us.simd_lt(f32x8::splat(s.width as f32 - 0.5))
                    & vs.simd_lt(f32x8::splat(s.height as f32 - 0.5));
                let inside_bits = inside.to_bitmask();
                if inside_bits == 0 {
                    continue;
                }
                let (d_s, has_d) = s.sample_depth8(us, vs, inside_bits);
                let err = (d_s - pz).abs();
                let accept = inside & has_d & err.simd_le(f32x8::splat(self.abs_tol) + f32x8::splat(self.rel_tol) * pz);
                if accept.to_bitmask() == 0 {
                    continue;
                }
                let rel = err / pz;
                let (p, q) = if self.nearest_wins { (dist, rel) } else { (rel, dist) };
                // Sources come in (distance, index) order, so on equal (p, q) the earlier one
                // (lower index) stays.
                let better = accept & (!has_best | p.simd_lt(best_p) | (p.simd_eq(best_p) & q.simd_lt(best_s)));
                has_best |= better;
                best_p = better.select(p, best_p);
                best_s = better.select(q, best_s);
                best_j = better.select(f32x8::splat(j as f32), best_j);
                best_us = better.select(us, best_us);
                best_vs = better.select(vs, best_vs);
            }
            let bits = has_best.to_bitmask();
            if bits == 0 {
                continue;
            }
            let (bj, bu, bv) = (best_j.to_array(), best_us.to_array(), best_vs.to_array());
            for l in 0..n {
                if bits >> l & 1 == 1 {
                    let s = &self.sources[bj[l] as usize];
                    crow[u0 + l] = sample_colour(s.colour, Vec2::new(bu[l], bv[l]));
                    mrow[u0 + l] = false;
                    irow[u0 + l] = s.index as i32;
                }
            }
        }
    }
}

/// SIMD width of the warp kernel.
const L: usize = 8;

/// [`is_valid_depth`] of 8 lanes (all bits set where valid): NaN and infinities fail one of the
/// comparisons.
#[inline(always)]
fn valid_depth8(d: f32x8) -> f32x8 {
    d.simd_gt(f32x8::splat(0.0)) & d.simd_le(f32x8::splat(f32::MAX))
}

impl Prepared<'_> {
    /// [`sample_depth`] for the lanes in `lanes` (bit mask; their locations lie inside the
    /// image): the value and whether there is one. The four neighbours are read per lane, the
    /// rest runs lane-wise; border lanes (no full 2x2 neighbourhood) go through the scalar path.
    #[inline]
    fn sample_depth8(&self, us: f32x8, vs: f32x8, lanes: u32) -> (f32x8, f32x8) {
        let (w, h) = (self.width as i32, self.height as i32);
        let (x0, y0) = (floor_i32x8(us), floor_i32x8(vs));
        let (fx, fy) = (us - x0.round_float(), vs - y0.round_float());
        let (x0a, y0a) = (x0.to_array(), y0.to_array());
        let data = &self.depth.data;
        let mut q = [[0.0f32; L]; 4];
        // lanes answered by the scalar path: (value or NaN)
        let mut direct = [f32::NAN; L];
        let mut direct_bits = 0u32;
        let mut bits = lanes;
        while bits != 0 {
            let l = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let (x, y) = (x0a[l], y0a[l]);
            if x >= 0 && y >= 0 && x + 1 < w && y + 1 < h {
                let i = (y * w + x) as usize;
                let (top, bottom) = (&data[i..i + 2], &data[i + self.width..i + self.width + 2]);
                (q[0][l], q[1][l], q[2][l], q[3][l]) = (top[0], top[1], bottom[0], bottom[1]);
            } else {
                let uv = Vec2::new(us.to_array()[l], vs.to_array()[l]);
                direct[l] = sample_depth(self.depth, uv).unwrap_or(f32::NAN);
                direct_bits |= 1 << l;
            }
        }
        let ok = valid_depth8;
        let [d00, d10, d01, d11] = q.map(f32x8::new);
        let (v00, v10, v01, v11) = (ok(d00), ok(d10), ok(d01), ok(d11));
        let top = d00 + fx * (d10 - d00);
        let bottom = d01 + fx * (d11 - d01);
        let bilinear = top + fy * (bottom - top);
        // the nearest pixel is one of the four: (floor(us + 0.5), floor(vs + 0.5))
        let half = f32x8::splat(0.5);
        let (right, down) = (fx.simd_ge(half), fy.simd_ge(half));
        let near_top = right.select(d10, d00);
        let near_bottom = right.select(d11, d01);
        let nearest = down.select(near_bottom, near_top);
        let all4 = v00 & v10 & v01 & v11;
        let value = all4.select(bilinear, nearest);
        let has = all4 | ok(nearest);
        // scalar-path lanes
        let direct = f32x8::new(direct);
        let is_direct = f32x8::new(std::array::from_fn(|l| if direct_bits >> l & 1 == 1 { 1.0 } else { 0.0 }))
            .simd_gt(f32x8::splat(0.0));
        (is_direct.select(direct, value), is_direct.select(ok(direct), has))
    }
}

/// Source depth at continuous pixel `uv`: bilinear when the 4 neighbours are valid, else the
/// nearest pixel when valid.
fn sample_depth(depth: &Image<f32>, uv: Vec2) -> Option<f32> {
    let (w, h) = (depth.width as i32, depth.height as i32);
    let (x0, y0) = (floor_i32(uv.x), floor_i32(uv.y));
    let (fx, fy) = (uv.x - x0 as f32, uv.y - y0 as f32);
    if x0 >= 0 && y0 >= 0 && x0 + 1 < w && y0 + 1 < h {
        let at = |x: i32, y: i32| depth.data[(y * w + x) as usize];
        let d = [at(x0, y0), at(x0 + 1, y0), at(x0, y0 + 1), at(x0 + 1, y0 + 1)];
        if d.iter().all(|v| is_valid_depth(*v)) {
            let top = d[0] + fx * (d[1] - d[0]);
            let bottom = d[2] + fx * (d[3] - d[2]);
            return Some(top + fy * (bottom - top));
        }
    }
    let (xn, yn) = (floor_i32(uv.x + 0.5), floor_i32(uv.y + 0.5));
    if xn < 0 || yn < 0 || xn >= w || yn >= h {
        return None;
    }
    let d = depth.data[(yn * w + xn) as usize];
    is_valid_depth(d).then_some(d)
}

/// Bilinear colour at continuous pixel `uv`, clamped at the image border.
fn sample_colour(colour: &Image<[f32; 3]>, uv: Vec2) -> [f32; 3] {
    let (w, h) = (colour.width as i32, colour.height as i32);
    let x = uv.x.clamp(0.0, (w - 1) as f32);
    let y = uv.y.clamp(0.0, (h - 1) as f32);
    let (x0, y0) = (floor_i32(x), floor_i32(y));
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = |x: i32, y: i32| colour.data[(y * w + x) as usize];
    let (a, b, c, d) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
    std::array::from_fn(|ch| {
        let top = a[ch] + fx * (b[ch] - a[ch]);
        let bottom = c[ch] + fx * (d[ch] - c[ch]);
        top + fy * (bottom - top)
    })
}
