//! How deep an invented object is behind the surface the refiner drew.
//!
//! A completed frame gives one view's surface. Fused alone, an invented object is a shell as
//! thick as the TSDF's truncation band (25 cm on CLEVR-Infinite); later views see it from the
//! side as a thin sheet and keep it, because observed pixels are kept. The true world is fused
//! from many views of each object and is solid. [`object_thickness`] gives every invented object
//! pixel a depth behind its surface, up to a back as far behind the object's front as the object
//! is wide (CLEVR's primitives are about as deep as wide), for the map's `integrate_behind`.

use glam::Vec2;

use crate::ground::GroundPlane;
use crate::{is_valid_depth, Camera, RgbdFrame};

/// Parameters of [`object_thickness`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolidConfig {
    /// Pixels at least this high above the ground plane are object pixels, metres.
    pub min_height_m: f32,
    /// Thinnest object, metres (at least twice the map's truncation, so the front band and the
    /// back face do not overlap).
    pub min_thickness_m: f32,
    /// Thickest object, metres (0 = no solids).
    pub max_thickness_m: f32,
    /// Neighbouring pixels of one object differ in depth by less than this share of the depth.
    pub max_depth_step: f32,
}

impl SolidConfig {
    /// Objects from 10 cm above the plane, `min_thickness_m` to `max_thickness_m` deep, a run
    /// broken where the depth steps by more than 5 %.
    pub fn new(min_thickness_m: f32, max_thickness_m: f32) -> Self {
        Self { min_height_m: 0.1, min_thickness_m, max_thickness_m, max_depth_step: 0.05 }
    }
}

/// Thickness behind the surface (planar depth, metres) of every pixel marked in `missing` that
/// belongs to an object: valid depth, at least `min_height_m` above `plane`. Object pixels
/// (observed ones included) are grouped into objects: 4-connected, a step in depth of at most
/// `max_depth_step` of it. An object is as deep as it is wide: its width `W` is its horizontal
/// extent in pixels at its median depth (metres), clamped to `min_thickness_m ..=
/// max_thickness_m`, and its back is the plane at planar depth `nearest + W`. An invented pixel
/// at depth `d` gets `nearest + W - d`, or 0 where that is under `min_thickness_m` (the back
/// face would fall inside the front's band). Every other pixel gets 0; with `max_thickness_m
/// <= 0`, all are 0.
///
/// Extruding each pixel by the object's width instead would carry the rays through the top of
/// an object far beyond its back, sloping down into a low tail that reads as rough ground.
pub fn object_thickness(
    frame: &RgbdFrame,
    missing: &[bool],
    camera: &Camera,
    plane: &GroundPlane,
    cfg: &SolidConfig,
) -> Vec<f32> {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    let mut out = vec![0.0f32; w * h];
    let depth = &frame.depth_m.data;
    let on = cfg.max_thickness_m > 0.0;
    if !on || depth.len() != w * h || missing.len() != w * h {
        return out;
    }
    let fx = camera.intrinsics.fx;
    let lo = cfg.min_thickness_m.min(cfg.max_thickness_m);
    let mut depths = Vec::new();
    let heights = pixel_heights(frame, camera, plane);
    for members in object_groups(frame, &heights, cfg.min_height_m, cfg.max_depth_step) {
        if !members.iter().any(|&i| missing[i]) {
            continue;
        }
        depths.clear();
        depths.extend(members.iter().map(|&i| depth[i]));
        let mid = depths.len() / 2;
        let median = *depths.select_nth_unstable_by(mid, f32::total_cmp).1;
        let nearest = depths.iter().copied().fold(f32::INFINITY, f32::min);
        let (u0, u1) = members.iter().fold((usize::MAX, 0), |(a, b), &i| (a.min(i % w), b.max(i % w)));
        let width = ((u1 - u0 + 1) as f32 * median / fx).clamp(lo, cfg.max_thickness_m);
        for &i in &members {
            let t = nearest + width - depth[i];
            if missing[i] && t >= lo {
                out[i] = t;
            }
        }
    }
    out
}

/// Per pixel of `frame`, the height of its point above `plane`, metres (NaN without valid
/// depth).
pub fn pixel_heights(frame: &RgbdFrame, camera: &Camera, plane: &GroundPlane) -> Vec<f32> {
    let w = frame.width() as usize;
    frame
        .depth_m
        .data
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            let uv = Vec2::new((i % w) as f32, (i / w) as f32);
            if is_valid_depth(d) {
                plane.height(camera.unproject_world(uv, d))
            } else {
                f32::NAN
            }
        })
        .collect()
}

/// The objects of `frame`: pixels whose height ([`pixel_heights`]) is at least `min_height_m`,
/// grouped 4-connected where neighbouring depths differ by at most `max_depth_step` of the depth
/// (each group's pixels in flood-fill order; groups in order of their first pixel).
pub fn object_groups(frame: &RgbdFrame, heights: &[f32], min_height_m: f32, max_depth_step: f32) -> Vec<Vec<usize>> {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    let depth = &frame.depth_m.data;
    if depth.len() != w * h || heights.len() != w * h {
        return Vec::new();
    }
    // (NaN, no valid depth, is never at least the minimum)
    let object: Vec<bool> = heights.iter().map(|&z| z >= min_height_m).collect();
    let joined = |a: usize, b: usize| object[b] && (depth[a] - depth[b]).abs() <= max_depth_step * depth[a];
    let mut seen = vec![false; w * h];
    let mut groups = Vec::new();
    let mut stack = Vec::new();
    for start in 0..w * h {
        if !object[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut members = Vec::new();
        while let Some(i) = stack.pop() {
            members.push(i);
            let (u, v) = (i % w, i / w);
            let mut visit = |j: usize| {
                if !seen[j] && joined(i, j) {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if u > 0 {
                visit(i - 1);
            }
            if u + 1 < w {
                visit(i + 1);
            }
            if v > 0 {
                visit(i - w);
            }
            if v + 1 < h {
                visit(i + w);
            }
        }
        groups.push(members);
    }
    groups
}

/// Parameters of [`cap_invented_objects`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObjectCapConfig {
    /// Largest footprint an object with invented pixels may have, square metres (0 = no cap).
    pub max_footprint_m2: f32,
    /// Longest footprint an object with invented pixels may have, metres (0 = no cap): the
    /// length along its footprint's principal axis, `sqrt(12 lambda_max)` of its cells'
    /// covariance (a bar's length, a square's side, 1.73 r for a disk of radius r).
    pub max_length_m: f32,
    /// Side of the ground cells a footprint is counted in, metres.
    pub cell_m: f32,
    /// Pixels at least this high above the ground plane are object pixels, metres.
    pub min_height_m: f32,
    /// Neighbouring pixels of one object differ in depth by less than this share of the depth.
    pub max_depth_step: f32,
}

impl ObjectCapConfig {
    /// Objects as [`SolidConfig::new`] groups them (10 cm above the plane, 5 % depth steps),
    /// footprints counted in 10 cm cells (as `eval world` counts them).
    pub fn new(max_footprint_m2: f32) -> Self {
        Self { max_footprint_m2, max_length_m: 0.0, cell_m: 0.1, min_height_m: 0.1, max_depth_step: 0.05 }
    }
}

/// A guard rail on the size of invented objects. Invented colour at a frame's border is
/// re-rendered at the next step and continued, step after step, into a mound many times the
/// size of any object of the world. Every object of `frame` (observed pixels included: the
/// part of a mound the map already holds) that has invented pixels (`missing`) and whose
/// footprint (its pixels' ground cells, `cell_m` a side, counted on the plane) exceeds
/// `max_footprint_m2` has its invented pixels put on the ground plane along their rays, in the
/// colour of the frame's observed ground (the median of observed pixels on the ground; the
/// pixel's own colour where there is none): the invented part of an oversized object becomes
/// floor. With `max_length_m`, so does the invented part of an object whose footprint is
/// longer than that (a streak that each step continues along the path stays under the area
/// cap for long). Returns the number of pixels put on the ground.
pub fn cap_invented_objects(
    frame: &mut RgbdFrame,
    missing: &[bool],
    camera: &Camera,
    plane: &GroundPlane,
    cfg: &ObjectCapConfig,
) -> usize {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    let (area_cap, length_cap) = (cfg.max_footprint_m2 > 0.0, cfg.max_length_m > 0.0);
    if !(area_cap || length_cap) || missing.len() != w * h || cfg.cell_m.is_nan() || cfg.cell_m <= 0.0 {
        return 0;
    }
    let heights = pixel_heights(frame, camera, plane);
    let groups = object_groups(frame, &heights, cfg.min_height_m, cfg.max_depth_step);
    // two axes in the plane: footprints are counted on the ground, whatever its tilt
    let n = plane.normal.normalize_or_zero();
    if n == glam::Vec3::ZERO {
        return 0;
    }
    let a = n.any_orthonormal_vector();
    let b = n.cross(a);
    let cell_area = cfg.cell_m * cfg.cell_m;
    let mut capped: Vec<usize> = Vec::new();
    let mut cells = std::collections::HashSet::new();
    for members in &groups {
        if !members.iter().any(|&i| missing[i]) {
            continue;
        }
        cells.clear();
        for &i in members {
            let p = camera.unproject_world(Vec2::new((i % w) as f32, (i / w) as f32), frame.depth_m.data[i]);
            cells.insert(((p.dot(a) / cfg.cell_m).floor() as i64, (p.dot(b) / cfg.cell_m).floor() as i64));
        }
        let too_large = area_cap && cells.len() as f32 * cell_area > cfg.max_footprint_m2;
        if too_large || (length_cap && footprint_length_m(&cells, cfg.cell_m) > cfg.max_length_m) {
            capped.extend(members.iter().copied().filter(|&i| missing[i]));
        }
    }
    if capped.is_empty() {
        return 0;
    }
    let floor = observed_ground_colour(frame, missing, &heights, cfg.min_height_m);
    put_on_ground(frame, &capped, camera, plane, floor);
    capped.len()
}

/// The observed ground's colour: per channel, the median over the observed pixels (not
/// `missing`) less than `min_height_m` from the plane (`heights`, [`pixel_heights`]); `None`
/// when there are none.
fn observed_ground_colour(frame: &RgbdFrame, missing: &[bool], heights: &[f32], min_height_m: f32) -> Option<[f32; 3]> {
    let mut ground: [Vec<f32>; 3] = Default::default();
    for i in (0..missing.len()).filter(|&i| !missing[i]) {
        if heights[i].abs() < min_height_m {
            for (c, v) in ground.iter_mut().zip(frame.colour.data[i]) {
                c.push(v);
            }
        }
    }
    (!ground[0].is_empty()).then(|| {
        ground.map(|mut c| {
            let mid = c.len() / 2;
            *c.select_nth_unstable_by(mid, f32::total_cmp).1
        })
    })
}

/// Puts `pixels` of `frame` on the ground plane along their rays, in colour `floor` (their own
/// colour where `None`); a ray that never meets the plane loses its depth (nothing is fused).
fn put_on_ground(
    frame: &mut RgbdFrame,
    pixels: &[usize],
    camera: &Camera,
    plane: &GroundPlane,
    floor: Option<[f32; 3]>,
) {
    let w = frame.width() as usize;
    for &i in pixels {
        let uv = Vec2::new((i % w) as f32, (i / w) as f32);
        match plane.depth_at(camera, uv) {
            Some(d) => {
                frame.depth_m.data[i] = d;
                if let Some(f) = floor {
                    frame.colour.data[i] = f;
                }
            }
            None => frame.depth_m.data[i] = 0.0,
        }
    }
}

/// Parameters of [`unify_object_colours`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObjectColourConfig {
    /// How far an invented pixel's colour moves to its object's colour and smoothed shading
    /// (0 = not at all, 1 = all the way).
    pub strength: f32,
    /// Pixels at least this high above the ground plane are object pixels, metres.
    pub min_height_m: f32,
    /// Neighbouring pixels of one object differ in depth by less than this share of the depth.
    pub max_depth_step: f32,
    /// An object with at least this share of its pixels observed (the map's, re-rendered; and
    /// at least [`MIN_OBSERVED`] of them) takes the colour they vote for: an object the map
    /// already holds keeps its colour.
    pub observed_share: f32,
    /// Grey wins a vote only with this many times the votes of the best hue.
    pub grey_majority: f32,
    /// Shading is smoothed over the object's pixels within this many pixels (0 = kept as drawn).
    pub shading_radius: usize,
}

impl ObjectColourConfig {
    /// Objects as [`ObjectCapConfig::new`] groups them (10 cm above the plane, 5 % depth steps);
    /// an object a quarter observed keeps its colour; grey needs 8 times the best hue's votes
    /// (one CLEVR-Infinite object in eight is grey, and a mottled invented one's dull pixels
    /// turned many more grey at 3); shading smoothed over 5 x 5 pixels.
    pub fn new(strength: f32) -> Self {
        Self {
            strength,
            min_height_m: 0.1,
            max_depth_step: 0.05,
            observed_share: 0.25,
            grey_majority: 8.0,
            shading_radius: 2,
        }
    }
}

/// Observed pixels an object needs before they alone vote for its colour.
const MIN_OBSERVED: usize = 32;
/// Hue sectors of the vote in [`unify_object_colours`].
const HUE_BINS: usize = 12;
/// A pixel whose channels' spread is below this share of its brightest channel votes grey.
const GREY_SPREAD: f32 = 0.2;

fn luma(c: [f32; 3]) -> f32 {
    0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2]
}

/// The hue sector of a coloured pixel, or `None` for a grey one (spread below [`GREY_SPREAD`]).
fn hue_bin(c: [f32; 3]) -> Option<usize> {
    let (max, min) = (c[0].max(c[1]).max(c[2]), c[0].min(c[1]).min(c[2]));
    // (NaN votes grey)
    if max.is_nan() || max <= 0.0 || max - min < GREY_SPREAD * max.max(0.05) {
        return None;
    }
    // the hexagonal hue, 0..6
    let d = max - min;
    let h = if max == c[0] {
        ((c[1] - c[2]) / d).rem_euclid(6.0)
    } else if max == c[1] {
        (c[2] - c[0]) / d + 2.0
    } else {
        (c[0] - c[1]) / d + 4.0
    };
    Some(((h / 6.0 * HUE_BINS as f32) as usize).min(HUE_BINS - 1))
}

/// The chromaticity (`rgb / luma`, grey: equal channels) the `voters` of an object vote for:
/// each votes for its hue sector or grey; the two neighbouring sectors with the most votes win
/// unless grey has `grey_majority` times their votes; the chromaticity is the mean over the
/// winning pixels. `None` when nothing can vote.
fn voted_chromaticity(colour: &[[f32; 3]], voters: &[usize], grey_majority: f32) -> Option<[f32; 3]> {
    let mut votes = [0usize; HUE_BINS];
    let mut grey = 0usize;
    for &i in voters {
        match hue_bin(colour[i]) {
            Some(b) => votes[b] += 1,
            None => grey += 1,
        }
    }
    // the best pair of neighbouring sectors (a hue on a sector's edge splits its votes)
    let (best, best_votes) =
        (0..HUE_BINS)
            .map(|b| (b, votes[b] + votes[(b + 1) % HUE_BINS]))
            .fold((0, 0), |a, x| if x.1 > a.1 { x } else { a });
    if best_votes == 0 || grey as f32 >= grey_majority * best_votes as f32 {
        return (grey > 0).then_some([1.0; 3]);
    }
    let mut sum = [0.0f64; 3];
    let mut n = 0usize;
    for &i in voters {
        let c = colour[i];
        let y = luma(c);
        if y > 0.02 && matches!(hue_bin(c), Some(b) if b == best || b == (best + 1) % HUE_BINS) {
            for k in 0..3 {
                sum[k] += (c[k] / y) as f64;
            }
            n += 1;
        }
    }
    (n > 0).then(|| sum.map(|v| (v / n as f64) as f32))
}

/// One colour per invented object. The refiner draws an object cell by cell, and its cells
/// disagree: an invented object comes out mottled in several hues and streaked in brightness
/// (each code's decoded texture), where a CLEVR-Infinite object is one material under smooth
/// shading. Every object of `frame` (pixels `min_height_m` above the plane, connected as
/// [`object_groups`] joins them; observed pixels included) that has invented pixels (`missing`)
/// gets one chromaticity by vote ([`voted_chromaticity`]): its observed pixels' vote when they
/// are `observed_share` of it (an object the map holds keeps its colour), else all its
/// pixels', where grey needs `grey_majority` times the best hue's votes (a mottled object's
/// dull pixels would otherwise turn it grey). Each invented pixel moves `strength` of the way
/// to that chromaticity at its shading, the mean luma of the object's pixels within
/// `shading_radius`. Returns the number of pixels recoloured.
pub fn unify_object_colours(
    frame: &mut RgbdFrame,
    missing: &[bool],
    camera: &Camera,
    plane: &GroundPlane,
    cfg: &ObjectColourConfig,
) -> usize {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    if cfg.strength.is_nan() || cfg.strength <= 0.0 || missing.len() != w * h {
        return 0;
    }
    let strength = cfg.strength.min(1.0);
    let heights = pixel_heights(frame, camera, plane);
    let groups = object_groups(frame, &heights, cfg.min_height_m, cfg.max_depth_step);
    let colour = &mut frame.colour.data;
    // each pixel's object (usize::MAX: none), for the shading's window
    let mut group_of = vec![usize::MAX; w * h];
    for (g, members) in groups.iter().enumerate() {
        for &i in members {
            group_of[i] = g;
        }
    }
    let lumas: Vec<f32> = colour.iter().map(|&c| luma(c)).collect();
    let r = cfg.shading_radius;
    let mut recoloured = 0;
    for (g, members) in groups.iter().enumerate() {
        if !members.iter().any(|&i| missing[i]) {
            continue;
        }
        let observed: Vec<usize> = members.iter().copied().filter(|&i| !missing[i]).collect();
        let by_observed =
            observed.len() >= MIN_OBSERVED && observed.len() as f32 >= cfg.observed_share * members.len() as f32;
        let chroma = if by_observed {
            voted_chromaticity(colour, &observed, 1.0)
        } else {
            voted_chromaticity(colour, members, cfg.grey_majority)
        };
        let Some(chroma) = chroma else { continue };
        for &i in members.iter().filter(|&&i| missing[i]) {
            let (u, v) = (i % w, i / w);
            let (mut sum, mut n) = (0.0f32, 0u32);
            for y in v.saturating_sub(r)..(v + r + 1).min(h) {
                for x in u.saturating_sub(r)..(u + r + 1).min(w) {
                    let j = y * w + x;
                    if group_of[j] == g {
                        sum += lumas[j];
                        n += 1;
                    }
                }
            }
            let shade = sum / n.max(1) as f32;
            let c = colour[i];
            colour[i] = std::array::from_fn(|k| (c[k] + strength * (chroma[k] * shade - c[k])).clamp(0.0, 1.0));
            recoloured += 1;
        }
    }
    recoloured
}

/// The length of a footprint along its principal axis, metres: `sqrt(12 lambda_max)` of the
/// covariance of its cells' centres (`cell_m` a side), the length of a uniform bar.
fn footprint_length_m(cells: &std::collections::HashSet<(i64, i64)>, cell_m: f32) -> f32 {
    if cells.len() < 2 {
        return cell_m;
    }
    let [lambda, _] = principal_variances(cells.iter().map(|&(a, b)| [a, b])).unwrap_or_default();
    ((12.0 * lambda).sqrt() * cell_m as f64) as f32
}

/// The principal variances `[lambda_max, lambda_min]` of lattice cells' centres: the
/// eigenvalues of their 2x2 covariance (population, in cells squared); `None` without cells.
/// The size cap's footprint length ([`cap_invented_objects`]) and `eval world`'s elongation
/// (`sgam_metrics::world::object_shape`) both read a footprint's shape from it.
pub fn principal_variances<I>(cells: I) -> Option<[f64; 2]>
where
    I: Iterator<Item = [i64; 2]> + Clone,
{
    let n = cells.clone().count() as f64;
    if n == 0.0 {
        return None;
    }
    let (sx, sy) = cells.clone().fold((0.0, 0.0), |(x, y), [a, b]| (x + a as f64, y + b as f64));
    let (mx, my) = (sx / n, sy / n);
    let (mut xx, mut xy, mut yy) = (0.0, 0.0, 0.0);
    for [a, b] in cells {
        let (dx, dy) = (a as f64 - mx, b as f64 - my);
        xx += dx * dx;
        xy += dx * dy;
        yy += dy * dy;
    }
    let (xx, xy, yy) = (xx / n, xy / n, yy / n);
    let (half_trace, radius) = (0.5 * (xx + yy), (0.25 * (xx - yy) * (xx - yy) + xy * xy).sqrt());
    Some([half_trace + radius, half_trace - radius])
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;
    use crate::{Image, Intrinsics, Rigid3};

    /// A camera 2 m above the plane y = 0 (OpenCV: y down, so "up" is -y), looking along +z.
    fn setup(w: u32, h: u32) -> (Camera, GroundPlane) {
        let k = Intrinsics { width: w, height: h, fx: 100.0, fy: 100.0, cx: w as f32 / 2.0, cy: h as f32 / 2.0 };
        let camera = Camera { intrinsics: k, world_from_camera: Rigid3::IDENTITY };
        // ground 2 m below the camera: height = -y + 2
        let plane = GroundPlane { normal: Vec3::new(0.0, -1.0, 0.0), offset: 2.0, inlier_fraction: 1.0 };
        (camera, plane)
    }

    fn frame(w: u32, h: u32, depth: f32) -> RgbdFrame {
        RgbdFrame { colour: Image::filled(w, h, [0.5; 3]), depth_m: Image::filled(w, h, depth) }
    }

    #[test]
    fn an_invented_object_takes_one_colour_by_vote_and_smooth_shading() {
        let (w, h) = (84, 32);
        let (camera, plane) = setup(w, h);
        // four walls 10 m away, 3 m above the ground (rows 2..8), apart from each other:
        // A (u 2..20): observed red on u 2..8, invented blue and dark red mottling on u 8..20;
        // B (u 24..40): invented, 10 columns green and 6 magenta; C (u 44..60): invented, 15
        // columns grey and 1 blue; D (u 64..80): invented, 10 columns grey and 6 yellow
        let mut f = frame(w, h, f32::NAN);
        let mut missing = vec![false; (w * h) as usize];
        let (red, blue, dark_red) = ([0.8, 0.2, 0.2], [0.2, 0.2, 0.8], [0.4, 0.1, 0.1]);
        let (green, magenta, grey, yellow) = ([0.2, 0.7, 0.2], [0.7, 0.2, 0.7], [0.5, 0.5, 0.5], [0.7, 0.7, 0.1]);
        let walls = || (2..20).chain(24..40).chain(44..60).chain(64..80);
        for v in 2..8 {
            for u in walls() {
                *f.depth_m.at_mut(u, v) = 10.0;
                missing[(v * w + u) as usize] = u >= 8;
                *f.colour.at_mut(u, v) = match u {
                    2..8 => red,
                    8..20 if u % 3 == 0 => blue,
                    8..20 => dark_red,
                    24..34 => green,
                    34..40 => magenta,
                    50 => blue,
                    44..60 => grey,
                    64..74 => grey,
                    _ => yellow,
                };
            }
        }
        let before = f.clone();
        let chroma = |c: [f32; 3]| c.map(|x| x / luma(c));
        let close = |a: [f32; 3], b: [f32; 3]| (0..3).all(|k| (a[k] - b[k]).abs() < 2e-3);
        let sharp = ObjectColourConfig { shading_radius: 0, ..ObjectColourConfig::new(1.0) };
        // strength 0: nothing moves
        let zero = ObjectColourConfig::new(0.0);
        assert_eq!(unify_object_colours(&mut f.clone(), &missing, &camera, &plane, &zero), 0);
        let n = unify_object_colours(&mut f, &missing, &camera, &plane, &sharp);
        assert_eq!(n, 6 * (12 + 16 + 16 + 16));
        for v in 2..8 {
            for u in walls() {
                let (old, new) = (*before.colour.at(u, v), *f.colour.at(u, v));
                // shading kept without smoothing: each pixel's luma is its own (none clipped here)
                assert!((luma(new) - luma(old)).abs() < 2e-3, "({u}, {v}): luma {} -> {}", luma(old), luma(new));
                let want = match u {
                    2..8 => {
                        assert_eq!(new, old, "observed pixels keep their colour");
                        continue;
                    }
                    // the observed red (a third of the object) decides; dark red is red's hue
                    8..20 => chroma(red),
                    24..40 => chroma(green),
                    // grey with 15 times the blue's votes; not with 10 to 6 over yellow
                    44..60 => [1.0; 3],
                    _ => chroma(yellow),
                };
                assert!(close(chroma(new), want), "({u}, {v}): {old:?} -> {new:?}, chromaticity wanted {want:?}");
            }
        }
        // half the way at strength 0.5
        let mut half = before.clone();
        let half_cfg = ObjectColourConfig { strength: 0.5, ..sharp };
        unify_object_colours(&mut half, &missing, &camera, &plane, &half_cfg);
        let (old, full, mid) = (*before.colour.at(36, 4), *f.colour.at(36, 4), *half.colour.at(36, 4));
        assert!(close(mid, std::array::from_fn(|k| (old[k] + full[k]) / 2.0)), "{old:?} -> {mid:?} (full: {full:?})");
        // smoothed shading: the mean luma of the object's pixels within 2 px (the wall's
        // first column sees 3 columns of itself and none of the gap beside it)
        let mut smooth = before.clone();
        unify_object_colours(&mut smooth, &missing, &camera, &plane, &ObjectColourConfig::new(1.0));
        let window = |u: u32, v: u32| -> f32 {
            let pixels: Vec<f32> = (v.saturating_sub(2).max(2)..(v + 3).min(8))
                .flat_map(|y| (u - 2..=u + 2).filter(|&x| (24..40).contains(&x)).map(move |x| (x, y)))
                .map(|(x, y)| luma(*before.colour.at(x, y)))
                .collect();
            pixels.iter().sum::<f32>() / pixels.len() as f32
        };
        for (u, v) in [(24, 2), (30, 4), (33, 5), (35, 7), (39, 3)] {
            let got = luma(*smooth.colour.at(u, v));
            assert!((got - window(u, v)).abs() < 2e-3, "({u}, {v}): luma {got}, window mean {}", window(u, v));
        }
        // between green and magenta the shading steps by less than it did
        let step = |fr: &RgbdFrame| (luma(*fr.colour.at(33, 4)) - luma(*fr.colour.at(34, 4))).abs();
        assert!(step(&smooth) < 0.5 * step(&before), "{} -> {}", step(&before), step(&smooth));
        // the ground and an object without invented pixels are left alone
        let mut observed_only = before.clone();
        let none = vec![false; (w * h) as usize];
        assert_eq!(unify_object_colours(&mut observed_only, &none, &camera, &plane, &ObjectColourConfig::new(1.0)), 0);
        assert_eq!(observed_only.colour.data, before.colour.data);
    }

    #[test]
    fn an_object_is_as_deep_as_it_is_wide() {
        let (w, h) = (64, 32);
        let (camera, plane) = setup(w, h);
        // a wall 10 m away at the camera's height (2 m above the ground): all object pixels
        // in the upper half; pixels 10..40 of row 5 are one run 30 px = 3 m wide
        let mut f = frame(w, h, f32::NAN);
        for u in 10..40 {
            *f.depth_m.at_mut(u, 5) = 10.0;
        }
        let mut missing = vec![false; (w * h) as usize];
        for u in 20..40 {
            missing[(5 * w + u) as usize] = true;
        }
        let t = object_thickness(&f, &missing, &camera, &plane, &SolidConfig::new(0.5, 2.0));
        // the observed part counts towards the width but gets no thickness
        assert_eq!(t[(5 * w + 15) as usize], 0.0);
        // 3 m wide, clamped to 2 m
        assert_eq!(t[(5 * w + 25) as usize], 2.0);
        let t = object_thickness(&f, &missing, &camera, &plane, &SolidConfig::new(0.5, 4.0));
        assert!((t[(5 * w + 25) as usize] - 3.0).abs() < 1e-4);
        // off
        let t = object_thickness(&f, &missing, &camera, &plane, &SolidConfig::new(0.5, 0.0));
        assert!(t.iter().all(|&x| x == 0.0));
    }

    #[test]
    fn every_pixel_of_an_object_reaches_one_back_plane() {
        let (w, h) = (64, 32);
        let (camera, plane) = setup(w, h);
        // a block 10 px wide (1 m at 10 m) in rows 2..=6, its upper rows further away, like a
        // top face: depth 10.00 (row 6) to 10.08 (row 2)
        let mut f = frame(w, h, f32::NAN);
        for v in 2..=6 {
            for u in 10..20 {
                *f.depth_m.at_mut(u, v) = 10.0 + 0.02 * (6 - v) as f32;
            }
        }
        let missing = vec![true; (w * h) as usize];
        let t = object_thickness(&f, &missing, &camera, &plane, &SolidConfig::new(0.5, 2.0));
        // width 10 px at the median depth 10.04 m: the back at 10 + 1.004 m
        let at = |t: &[f32], v: u32| t[(v * w + 15) as usize];
        assert!((at(&t, 6) - 1.004).abs() < 1e-4, "{}", at(&t, 6));
        assert!((at(&t, 2) - 0.924).abs() < 1e-4, "{}", at(&t, 2));
        // a pixel whose back would be nearer than the minimum gets none
        let t = object_thickness(&f, &missing, &camera, &plane, &SolidConfig::new(0.95, 2.0));
        assert_eq!(at(&t, 2), 0.0);
        assert!(at(&t, 6) > 0.95);
    }

    #[test]
    fn depth_steps_split_objects_and_ground_pixels_are_not_objects() {
        let (w, h) = (64, 32);
        let (camera, plane) = setup(w, h);
        let mut f = frame(w, h, f32::NAN);
        // two objects side by side in row 5: 8 px at 10 m, then 8 px at 12 m
        for u in 0..8 {
            *f.depth_m.at_mut(u, 5) = 10.0;
            *f.depth_m.at_mut(u + 8, 5) = 12.0;
        }
        // row 31 (below the centre): the ground, 0 m high where the ray meets it
        let ground_row = 31;
        let ray_y = (ground_row as f32 - 16.0) / 100.0;
        for u in 0..w {
            *f.depth_m.at_mut(u, ground_row) = 2.0 / ray_y;
        }
        let missing = vec![true; (w * h) as usize];
        let t = object_thickness(&f, &missing, &camera, &plane, &SolidConfig::new(0.1, 5.0));
        assert!((t[(5 * w + 3) as usize] - 0.8).abs() < 1e-4, "{}", t[(5 * w + 3) as usize]);
        assert!((t[(5 * w + 12) as usize] - 0.96).abs() < 1e-4, "{}", t[(5 * w + 12) as usize]);
        assert!(t[(ground_row * w) as usize..((ground_row + 1) * w) as usize].iter().all(|&x| x == 0.0));
        // the minimum thickness applies to a single pixel
        let t = object_thickness(&f, &missing, &camera, &plane, &SolidConfig::new(1.5, 5.0));
        assert_eq!(t[(5 * w + 3) as usize], 1.5);
    }

    #[test]
    fn a_footprints_length_is_a_bars_length_a_squares_side_and_turns_with_it() {
        let cells = |v: Vec<(i64, i64)>| v.into_iter().collect::<std::collections::HashSet<_>>();
        let bar = cells((0..30).map(|x| (x, 0)).collect());
        assert!((footprint_length_m(&bar, 0.1) - 3.0).abs() < 0.01, "{}", footprint_length_m(&bar, 0.1));
        let diagonal = cells((0..30).map(|x| (x, x)).collect());
        assert!((footprint_length_m(&diagonal, 0.1) - 3.0 * 2f32.sqrt()).abs() < 0.02);
        let square = cells((0..20).flat_map(|x| (0..20).map(move |y| (x, y))).collect());
        assert!((footprint_length_m(&square, 0.1) - 2.0).abs() < 0.01, "{}", footprint_length_m(&square, 0.1));
        assert_eq!(footprint_length_m(&cells(vec![(3, 4)]), 0.1), 0.1);
    }

    #[test]
    fn the_invented_part_of_an_oversized_object_becomes_floor_and_a_small_one_stays() {
        let (w, h) = (64, 32);
        let (camera, plane) = setup(w, h);
        let mut f = frame(w, h, f32::NAN);
        // the observed ground in row 31, grey
        let ground_row = 31;
        let ray_y = (ground_row as f32 - 16.0) / 100.0;
        for u in 0..w {
            *f.depth_m.at_mut(u, ground_row) = 2.0 / ray_y;
            *f.colour.at_mut(u, ground_row) = [0.3, 0.3, 0.3];
        }
        // a wide object (60 px = 6 m at 10 m; rows 2..=6 stepping 4 cm in depth: 3 ground
        // cells deep, about 1.8 m2), its left half observed and its right half invented, and
        // a small invented one (3 px) far from it in row 12, 12 m away
        for v in 2..=6 {
            for u in 0..60 {
                *f.depth_m.at_mut(u, v) = 10.0 + 0.04 * (6 - v) as f32;
                *f.colour.at_mut(u, v) = [1.0, 0.0, 0.0];
            }
        }
        for u in 0..3 {
            *f.depth_m.at_mut(u, 12) = 12.0;
            *f.colour.at_mut(u, 12) = [0.0, 0.0, 1.0];
        }
        let mut missing = vec![false; (w * h) as usize];
        for v in 2..=6 {
            for u in 30..60 {
                missing[(v * w + u) as usize] = true;
            }
        }
        for u in 0..3 {
            missing[(12 * w + u) as usize] = true;
        }
        let at =
            |f: &RgbdFrame, u: u32, v: u32| (f.depth_m.data[(v * w + u) as usize], f.colour.data[(v * w + u) as usize]);
        // a degenerate plane (no normal) moves nothing
        let flat = GroundPlane { normal: glam::Vec3::ZERO, ..plane };
        assert_eq!(cap_invented_objects(&mut f.clone(), &missing, &camera, &flat, &ObjectCapConfig::new(1.0)), 0);
        // no cap, or a cap above the wide object's footprint: nothing moves
        for cap in [0.0, 5.0] {
            let mut g = f.clone();
            assert_eq!(cap_invented_objects(&mut g, &missing, &camera, &plane, &ObjectCapConfig::new(cap)), 0);
            assert!(g.depth_m.data.iter().zip(&f.depth_m.data).all(|(a, b)| a.to_bits() == b.to_bits()), "cap {cap}");
        }
        // the wide object is a bar about 6 m long: a length cap alone stops it at 3 m, not at 8 m
        let length = |m: f32| ObjectCapConfig { max_length_m: m, ..ObjectCapConfig::new(0.0) };
        assert_eq!(cap_invented_objects(&mut f.clone(), &missing, &camera, &plane, &length(8.0)), 0);
        assert_eq!(cap_invented_objects(&mut f.clone(), &missing, &camera, &plane, &length(3.0)), 5 * 30);
        let mut g = f.clone();
        let moved = cap_invented_objects(&mut g, &missing, &camera, &plane, &ObjectCapConfig::new(1.0));
        assert_eq!(moved, 5 * 30, "the wide object's invented pixels, not the small one's");
        for v in 2..=6 {
            // observed: kept
            assert_eq!(at(&g, 10, v), at(&f, 10, v));
            // invented: on the plane (these rows look above the horizon: the ray never meets
            // it, so nothing is fused there)
            assert_eq!(at(&g, 40, v).0, 0.0, "row {v}");
        }
        assert_eq!(at(&g, 1, 12), at(&f, 1, 12), "the small invented object stays");
        // below the horizon an oversized object's invented pixels land on the plane in the
        // observed ground's colour
        let mut f2 = frame(w, h, f32::NAN);
        for u in 0..w {
            *f2.depth_m.at_mut(u, ground_row) = 2.0 / ray_y;
            *f2.colour.at_mut(u, ground_row) = [0.3, 0.3, 0.3];
        }
        // rows 20..=24 look down at 0.04-0.08: the ground is 25-50 m away; an object 1 m high
        // at 10-11 m
        let mut missing2 = vec![false; (w * h) as usize];
        for v in 20..=24 {
            for u in 0..60 {
                *f2.depth_m.at_mut(u, v) = 10.0 + 0.2 * (24 - v) as f32;
                *f2.colour.at_mut(u, v) = [1.0, 0.0, 0.0];
                missing2[(v * w + u) as usize] = u >= 30;
            }
        }
        let moved = cap_invented_objects(&mut f2, &missing2, &camera, &plane, &ObjectCapConfig::new(1.0));
        assert_eq!(moved, 5 * 30);
        for v in 20..=24 {
            let (d, c) = at(&f2, 45, v);
            let want = plane.depth_at(&camera, Vec2::new(45.0, v as f32)).unwrap();
            assert!((d - want).abs() < 1e-4 && c == [0.3, 0.3, 0.3], "row {v}: {d} vs {want}, {c:?}");
            assert_eq!(at(&f2, 10, v).1, [1.0, 0.0, 0.0], "observed pixels keep their colour");
        }
    }
}
