//! Inverse warping of colour from source keyframes with a geometry (depth) check.

use rayon::prelude::*;

use crate::block::floor_i32;
use sgam_core::{is_valid_depth, Camera, Image, RgbdFrame, Rigid3, Vec2, Vec3};

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
/// `missing`. Deterministic; parallel over rows (rayon).
pub fn warp_colour(
    target: &Camera,
    target_depth_m: &Image<f32>,
    sources: &[SourceView<'_>],
    config: &WarpConfig,
) -> Warped {
    let (w, h) = (target_depth_m.width as usize, target_depth_m.height as usize);
    // Per source: index, source_from_target, camera distance to the target; nearest first, so
    // with `NearestCamera` the scan stops at the first source farther than an accepted one.
    let mut prepared: Vec<(usize, Rigid3, f32)> = sources
        .iter()
        .enumerate()
        .filter(|(_, s)| {
            let k = s.camera.intrinsics;
            s.frame.depth_m.size() == (k.width, k.height)
                && s.frame.colour.size() == (k.width, k.height)
                && s.camera.world_from_camera.is_finite()
        })
        .map(|(i, s)| {
            let dist = s.camera.centre_world().distance(target.centre_world());
            (i, s.camera.world_from_camera.inverse() * target.world_from_camera, dist)
        })
        .collect();
    prepared.sort_by(|a, b| a.2.total_cmp(&b.2).then(a.0.cmp(&b.0)));
    let nearest_wins = config.selection == SourceSelection::NearestCamera;
    let mut colour = vec![[0.0f32; 3]; w * h];
    let mut missing = vec![true; w * h];
    let mut index = vec![-1i32; w * h];
    let target_ok = target.world_from_camera.is_finite();
    colour
        .par_chunks_mut(w.max(1))
        .zip(missing.par_chunks_mut(w.max(1)))
        .zip(index.par_chunks_mut(w.max(1)))
        .enumerate()
        .for_each(|(v, ((crow, mrow), irow))| {
            if !target_ok {
                return;
            }
            let kt = target.intrinsics;
            // Target ray (z = 1) of pixel (u, v) = row_ray + u * du; in each source frame the
            // point at depth z is z * (R_st * ray) + t_st.
            let row_ray = kt.ray_z1(Vec2::new(0.0, v as f32));
            let du = Vec3::new(1.0 / kt.fx, 0.0, 0.0);
            for u in 0..w {
                let z_t = target_depth_m.data[v * w + u];
                if !is_valid_depth(z_t) {
                    continue;
                }
                let ray = row_ray + du * u as f32;
                // (key for comparison, source position in `prepared`, sample location)
                let mut best: Option<((f32, f32, usize), usize, Vec2)> = None;
                for (j, (i, source_from_target, dist)) in prepared.iter().enumerate() {
                    if nearest_wins && best.as_ref().is_some_and(|((d, _, _), _, _)| *dist > *d) {
                        break; // every later source is at least this far: none can win
                    }
                    let s = &sources[*i];
                    let pc = source_from_target.transform_point(ray * z_t);
                    let Some(uv) = s.camera.intrinsics.project(pc) else { continue };
                    if !s.camera.intrinsics.contains(uv) {
                        continue;
                    }
                    let Some(d_s) = sample_depth(&s.frame.depth_m, uv) else { continue };
                    let err = (d_s - pc.z).abs();
                    if err > config.depth_abs_tolerance_m + config.depth_rel_tolerance * pc.z {
                        continue;
                    }
                    let rel = err / pc.z;
                    let key = match config.selection {
                        SourceSelection::SmallestDepthError => (rel, *dist, *i),
                        SourceSelection::NearestCamera => (*dist, rel, *i),
                    };
                    if best.as_ref().is_none_or(|(k, _, _)| key < *k) {
                        best = Some((key, j, uv));
                    }
                }
                if let Some((_, j, uv)) = best {
                    let i = prepared[j].0;
                    crow[u] = sample_colour(&sources[i].frame.colour, uv);
                    mrow[u] = false;
                    irow[u] = i as i32;
                }
            }
        });
    Warped {
        colour: Image { width: w as u32, height: h as u32, data: colour },
        missing,
        source_index: Image { width: w as u32, height: h as u32, data: index },
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
