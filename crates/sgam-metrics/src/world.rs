//! World-level object statistics: a mesh (metres, world frame, z up)
//! becomes a 10 cm height field; the area outside the seed's footprint (the "new area") is split
//! into ground and objects, and we report object density, footprints, colour saturation and ground
//! roughness. One-step scores cannot see a degenerate world (all ground, or all blobs); these can.
//!
//! - Cells lie on the world lattice (multiples of `cell_m` in x and y), so two meshes over the
//!   same place share cells whatever their bounding boxes.
//! - A cell's height is the highest z of the mesh vertices, and of points sampled on its
//!   triangles at spacing <= `cell_m / 2`, that fall in it (so a large flat triangle fills every
//!   cell it covers). Cells nothing falls in are empty (NaN).
//! - Ground height = the DENSEST LEVEL of the occupied new-area cells: the median of the most
//!   cells that fit in one +-`ground_window_m` height band ([`ground_level`]). A median of all
//!   cells would assume the ground covers most of the area; a generated world whose invented
//!   lumps cover more of it than its ground would then get a "ground" in the lumps, and a flat
//!   true ground would count as rough.
//! - Objects = 8-connected components of occupied new-area cells more than `object_height_m`
//!   above the ground, of area >= `min_object_area_m2`. Smaller such components are neither
//!   objects nor ground: they count in no statistic except `new_area_m2`.
//! - Object shape ([`ObjectShape`]) is read from the object's cells alone: solidity (cells over
//!   the lattice cells in the convex hull of their centres) and elongation (the axis ratio of
//!   their covariance). Both are ratios, the same at any cell size; a `compact` object is solid
//!   and not elongated ([`COMPACT_MIN_SOLIDITY`], [`COMPACT_MAX_ELONGATION`]).

use crate::median;
use crate::scene::RegionSpec;
use glam::{Vec2, Vec3};
use serde::{Deserialize, Serialize};
use sgam_core::TriMesh;

/// Parameters of [`world_stats`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WorldStatsConfig {
    /// Side of a square height-field cell, metres (0.1).
    pub cell_m: f32,
    /// A cell is part of an object when it is more than this above the ground, metres (0.25).
    pub object_height_m: f32,
    /// Smallest footprint of an object, square metres (0.2).
    pub min_object_area_m2: f32,
    /// The seed footprint is grown by this before it is excluded, metres (1.0).
    pub exclusion_margin_m: f32,
    /// Half height of the band that finds the ground level, metres (0.1).
    pub ground_window_m: f32,
}

impl Default for WorldStatsConfig {
    fn default() -> Self {
        Self {
            cell_m: 0.1,
            object_height_m: 0.25,
            min_object_area_m2: 0.2,
            exclusion_margin_m: 1.0,
            ground_window_m: 0.1,
        }
    }
}

/// The area left out of the statistics: a convex polygon in the xy plane (world frame, metres;
/// the seed frame's ground footprint), vertices in either winding. Empty = nothing excluded; one
/// or two vertices exclude a disc or a capsule of the margin's radius.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Exclusion {
    /// Polygon vertices (x, y), metres, world frame.
    pub polygon_xy_m: Vec<Vec2>,
}

impl Exclusion {
    /// Excludes nothing.
    pub fn none() -> Self {
        Self::default()
    }

    /// True when `p` (x, y, metres) is inside the polygon (taken as convex) or within `margin_m`
    /// (metres) of its boundary.
    pub fn excludes(&self, p: Vec2, margin_m: f32) -> bool {
        let v = &self.polygon_xy_m;
        let edges = || (0..v.len()).map(|i| (v[i], v[(i + 1) % v.len()]));
        // inside a convex polygon of either winding: p is on the same side of every edge
        let (mut left, mut right) = (false, false);
        for (a, b) in edges() {
            let side = (b - a).perp_dot(p - a);
            (left, right) = (left || side > 0.0, right || side < 0.0);
        }
        if v.len() >= 3 && !(left && right) {
            return true;
        }
        edges().any(|(a, b)| {
            let ab = b - a;
            let t =
                if ab.length_squared() > 0.0 { ((p - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0) } else { 0.0 };
            p.distance(a + ab * t) <= margin_m
        })
    }
}

/// A 2-D grid of the highest surface point per cell.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightField {
    /// Lower corner (x, y) of cell (0, 0), metres, world frame; a multiple of `cell_m`.
    pub origin_m: Vec2,
    /// Cell side, metres.
    pub cell_m: f32,
    /// Cells along x.
    pub nx: usize,
    /// Cells along y.
    pub ny: usize,
    /// Highest z per cell (metres; NaN = empty), row-major: index `iy * nx + ix`.
    pub height_m: Vec<f32>,
}

impl HeightField {
    /// Index of the cell holding `p` (x, y, metres); `None` outside the grid.
    pub fn cell_of(&self, p: Vec2) -> Option<usize> {
        let rel = (p - self.origin_m) / self.cell_m;
        let (ix, iy) = (rel.x.floor(), rel.y.floor());
        let inside = ix >= 0.0 && iy >= 0.0 && (ix as usize) < self.nx && (iy as usize) < self.ny;
        inside.then(|| iy as usize * self.nx + ix as usize)
    }

    /// Centre (x, y, metres) of cell `index`.
    pub fn cell_centre(&self, index: usize) -> Vec2 {
        let (ix, iy) = (index % self.nx.max(1), index / self.nx.max(1));
        self.origin_m + (Vec2::new(ix as f32, iy as f32) + 0.5) * self.cell_m
    }
}

/// Rasterises `mesh` into cells of `cell_m` metres covering its xy bounding box (see the module
/// docs). Non-finite vertices are skipped; an empty grid when no vertex is finite or `cell_m` is
/// not positive. Memory: 4 bytes per cell of the bounding box (40 x 40 m: 160k cells, 640 kB), so
/// the caller keeps far outliers out of the mesh.
pub fn height_field(mesh: &TriMesh, cell_m: f32) -> HeightField {
    let finite = || mesh.positions.iter().filter(|p| p.is_finite());
    let (lo, hi) =
        finite().fold((Vec2::INFINITY, Vec2::NEG_INFINITY), |(lo, hi), p| (lo.min(p.truncate()), hi.max(p.truncate())));
    let usable = cell_m > 0.0 && cell_m.is_finite() && lo.is_finite();
    if !usable {
        return HeightField { origin_m: Vec2::ZERO, cell_m, nx: 0, ny: 0, height_m: Vec::new() };
    }
    let (first, last) = ((lo / cell_m).floor(), (hi / cell_m).floor());
    let (nx, ny) = ((last.x - first.x) as usize + 1, (last.y - first.y) as usize + 1);
    let mut height_m = vec![f32::NEG_INFINITY; nx * ny];
    let mut put = |p: Vec3| {
        // rounding may put an interpolated sample a hair outside the box: clamp it in
        let ix = ((p.x / cell_m).floor() - first.x).clamp(0.0, (nx - 1) as f32) as usize;
        let iy = ((p.y / cell_m).floor() - first.y).clamp(0.0, (ny - 1) as f32) as usize;
        let h = &mut height_m[iy * nx + ix];
        *h = h.max(p.z);
    };
    finite().for_each(|p| put(*p));
    let step = 0.5 * cell_m;
    for t in &mesh.triangles {
        let Some([a, b, c]) = vertices(mesh, t) else { continue };
        let longest = (b - a).length().max((c - a).length()).max((c - b).length());
        if longest.is_nan() || longest <= step {
            continue; // the corners alone are dense enough
        }
        let n = (longest / step).ceil() as u32;
        let (du, dv) = ((b - a) / n as f32, (c - a) / n as f32);
        for i in 0..=n {
            for j in 0..=n - i {
                if !matches!((i, j), (0, 0)) && i != n && j != n {
                    // a + du i + dv j keeps z exact on flat triangles (weights never re-summed)
                    put(a + du * i as f32 + dv * j as f32);
                }
            }
        }
    }
    height_m.iter_mut().filter(|h| **h == f32::NEG_INFINITY).for_each(|h| *h = f32::NAN);
    HeightField { origin_m: first * cell_m, cell_m, nx, ny, height_m }
}

/// The three finite corners of triangle `t`, or `None` (bad index or non-finite corner).
fn vertices(mesh: &TriMesh, t: &[u32; 3]) -> Option<[Vec3; 3]> {
    let p = |i: u32| mesh.positions.get(i as usize).copied().filter(|p| p.is_finite());
    Some([p(t[0])?, p(t[1])?, p(t[2])?])
}

/// World-level statistics of the new area (outside the exclusion). Areas in square metres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorldStats {
    /// Occupied cells outside the exclusion (by cell centre) times the cell area, m^2.
    pub new_area_m2: f32,
    /// Median height of the occupied new-area cells (mean of the two middle ones for an even
    /// count), metres; NaN when there are none.
    pub ground_height_m: f32,
    /// Number of objects.
    pub objects: usize,
    /// Objects per 100 m^2 of new area; 0 when the new area is empty.
    pub objects_per_100m2: f32,
    /// Median object footprint, m^2 (mean of the two middle ones for an even count); 0 when none.
    pub median_object_area_m2: f32,
    /// 90th percentile of the object footprints (linear between ranks), m^2; 0 when none.
    pub p90_object_area_m2: f32,
    /// Share of the new area covered by object cells, in `[0, 1]`; 0 when the new area is empty.
    pub object_cover: f32,
    /// Mean saturation (max - min of the sRGB channels, `[0, 1]`) over the coloured mesh
    /// vertices (real vertices only, never interpolated samples) lying in object cells more than
    /// `object_height_m` above the ground; 0 when there is none (or the mesh has no colours).
    pub object_saturation: f32,
    /// RMS of (cell height - ground) over the ground cells (occupied new-area cells neither in an
    /// object nor in a too-small raised component), millimetres; 0 when there are none.
    pub ground_rms_mm: f32,
    /// Footprint of every object, m^2, ascending.
    pub object_areas_m2: Vec<f32>,
    /// Median solidity, median elongation and compact share of the objects (each `None` when
    /// there are none); [`ShapeSummary::of`] over `object_shapes`.
    #[serde(default)]
    pub object_shape: ShapeSummary,
    /// Shape of every object, in the order of their lowest cell (row-major: y, then x); pooled
    /// figures over several worlds are [`ShapeSummary::of`] their concatenation.
    #[serde(default)]
    pub object_shapes: Vec<ObjectShape>,
}

/// An object is compact when its solidity is at least this and its elongation at most
/// [`COMPACT_MAX_ELONGATION`].
pub const COMPACT_MIN_SOLIDITY: f32 = 0.8;

/// An object is compact when its elongation is at most this and its solidity at least
/// [`COMPACT_MIN_SOLIDITY`].
pub const COMPACT_MAX_ELONGATION: f32 = 2.0;

/// Footprint shape of one object: ratios of its height-field cells, free of units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ObjectShape {
    /// Object cells / lattice cells whose centres lie inside or on the convex hull of the
    /// object's cell centres, in `(0, 1]`: 1 for a filled rectangle or a single row of cells.
    pub solidity: f32,
    /// `sqrt(lambda_max / lambda_min)` of the 2x2 covariance of the object's cell centres, with
    /// `cell_m^2 / 12` (the variance of a point uniform in one cell) added to both diagonal
    /// terms, so a single row stays finite; >= 1, and exactly the side ratio of a filled
    /// rectangle of cells.
    pub elongation: f32,
}

impl ObjectShape {
    /// True when solidity >= [`COMPACT_MIN_SOLIDITY`] and elongation <= [`COMPACT_MAX_ELONGATION`].
    pub fn is_compact(&self) -> bool {
        self.solidity >= COMPACT_MIN_SOLIDITY && self.elongation <= COMPACT_MAX_ELONGATION
    }
}

/// Summary of a set of object shapes (one world's, or several worlds' concatenated).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ShapeSummary {
    /// Median solidity (mean of the two middle ones for an even count); `None` without objects.
    pub median_solidity: Option<f32>,
    /// Median elongation (mean of the two middle ones for an even count); `None` without objects.
    pub median_elongation: Option<f32>,
    /// Compact objects / objects, in `[0, 1]`; `None` without objects.
    pub compact_share: Option<f32>,
}

impl ShapeSummary {
    /// The summary of `shapes`.
    pub fn of(shapes: &[ObjectShape]) -> Self {
        let solidity: Vec<f32> = shapes.iter().map(|s| s.solidity).collect();
        let elongation: Vec<f32> = shapes.iter().map(|s| s.elongation).collect();
        let compact = shapes.iter().filter(|s| s.is_compact()).count();
        Self {
            median_solidity: median(&solidity),
            median_elongation: median(&elongation),
            compact_share: (!shapes.is_empty()).then(|| compact as f32 / shapes.len() as f32),
        }
    }
}

/// Shape of the object made of `cells`, lattice indices `[ix, iy]` of square cells (duplicates
/// count once); `None` when `cells` is empty. Exact integer hull and cell count; the covariance
/// in f64.
pub fn object_shape(cells: &[[i64; 2]]) -> Option<ObjectShape> {
    let mut cells = cells.to_vec();
    cells.sort_unstable();
    cells.dedup();
    let n = cells.len() as f64;
    let hull_cells = lattice_points_in(&convex_hull(&cells));
    if cells.is_empty() || hull_cells <= 0 {
        return None;
    }
    // covariance in cell units plus the uniform cell's variance, 1/12 (cell_m^2 / 12 in metres;
    // the ratio of eigenvalues does not depend on the unit), which adds 1/12 to each eigenvalue
    let [major, minor] = sgam_core::solid::principal_variances(cells.iter().copied())?;
    let cell = 1.0 / 12.0;
    Some(ObjectShape {
        solidity: (n / hull_cells as f64) as f32,
        elongation: ((major + cell) / (minor + cell)).sqrt() as f32,
    })
}

/// Convex hull of sorted, distinct lattice points, counter-clockwise, without collinear
/// vertices (Andrew's monotone chain): one point for one point, the two ends for a segment.
fn convex_hull(sorted: &[[i64; 2]]) -> Vec<[i64; 2]> {
    if sorted.len() < 3 {
        return sorted.to_vec();
    }
    let mut hull = half_hull(sorted.iter().copied());
    hull.extend(half_hull(sorted.iter().rev().copied()));
    hull
}

/// The lower hull of points sorted by (x, y) (the upper one for them reversed), without its last
/// point, which starts the other half.
fn half_hull(points: impl Iterator<Item = [i64; 2]>) -> Vec<[i64; 2]> {
    let cross = |o: [i64; 2], a: [i64; 2], b: [i64; 2]| (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
    let mut h: Vec<[i64; 2]> = Vec::new();
    for p in points {
        while h.len() >= 2 && cross(h[h.len() - 2], h[h.len() - 1], p) <= 0 {
            h.pop();
        }
        h.push(p);
    }
    h.pop();
    h
}

/// Lattice points inside or on the closed lattice polygon `hull` (any winding), by Pick's
/// theorem: `I + B = A + B / 2 + 1`. It also holds for a segment taken as a polygon there and
/// back (A = 0, B = twice its lattice steps) and for a single point (1); 0 for no points.
fn lattice_points_in(hull: &[[i64; 2]]) -> i64 {
    if hull.is_empty() {
        return 0;
    }
    let gcd = |mut a: i64, mut b: i64| {
        while b != 0 {
            (a, b) = (b, a % b);
        }
        a
    };
    let (mut twice_area, mut boundary) = (0i64, 0i64);
    for (i, a) in hull.iter().enumerate() {
        let b = hull[(i + 1) % hull.len()];
        twice_area += a[0] * b[1] - a[1] * b[0];
        boundary += gcd((b[0] - a[0]).abs(), (b[1] - a[1]).abs());
    }
    (twice_area.abs() + boundary) / 2 + 1
}

/// Computes [`WorldStats`] of `mesh` (metres, world frame, z up) outside `exclusion` grown by
/// `cfg.exclusion_margin_m`.
pub fn world_stats(mesh: &TriMesh, exclusion: &Exclusion, cfg: &WorldStatsConfig) -> WorldStats {
    let hf = height_field(mesh, cfg.cell_m);
    let cell_area = cfg.cell_m * cfg.cell_m;
    let new: Vec<bool> = (0..hf.height_m.len())
        .map(|i| hf.height_m[i].is_finite() && !exclusion.excludes(hf.cell_centre(i), cfg.exclusion_margin_m))
        .collect();
    let new_heights: Vec<f32> = hf.height_m.iter().zip(&new).filter(|(_, n)| **n).map(|(h, _)| *h).collect();
    let new_area_m2 = new_heights.len() as f32 * cell_area;
    let ground = ground_level(&new_heights, cfg.ground_window_m).unwrap_or(f32::NAN);
    let threshold = ground + cfg.object_height_m;
    let raised: Vec<bool> = hf.height_m.iter().zip(&new).map(|(h, n)| *n && *h > threshold).collect();
    // components of raised cells; a component is an object when it has at least `min_cells`
    // cells (the 1e-4 absorbs an f32 ratio such as 0.2 / 0.1^2 rounding just above an integer)
    let min_cells = ((cfg.min_object_area_m2 / cell_area) - 1e-4).ceil().max(1.0) as usize;
    let mut object = vec![false; raised.len()];
    let mut object_areas_m2 = Vec::new();
    let mut object_shapes = Vec::new();
    let mut seen = vec![false; raised.len()];
    for start in 0..raised.len() {
        if !raised[start] || seen[start] {
            continue;
        }
        let component = flood_fill(&hf, &raised, &mut seen, start);
        if component.len() >= min_cells {
            component.iter().for_each(|&i| object[i] = true);
            object_areas_m2.push(component.len() as f32 * cell_area);
            let cells: Vec<[i64; 2]> = component.iter().map(|&i| [(i % hf.nx) as i64, (i / hf.nx) as i64]).collect();
            object_shapes.extend(object_shape(&cells));
        }
    }
    object_areas_m2.sort_by(f32::total_cmp);
    let sq: Vec<f64> =
        (0..new.len()).filter(|&i| new[i] && !raised[i]).map(|i| ((hf.height_m[i] - ground) as f64).powi(2)).collect();
    let ground_rms_mm =
        if sq.is_empty() { 0.0 } else { ((sq.iter().sum::<f64>() / sq.len() as f64).sqrt() * 1e3) as f32 };
    let (mut sat_sum, mut sat_n) = (0.0f64, 0usize);
    if mesh.colours.len() == mesh.positions.len() {
        for (p, c) in mesh.positions.iter().zip(&mesh.colours) {
            if p.z > threshold && hf.cell_of(p.truncate()).is_some_and(|i| object[i]) {
                sat_sum += (c[0].max(c[1]).max(c[2]) - c[0].min(c[1]).min(c[2])) as f64;
                sat_n += 1;
            }
        }
    }
    let per_area = |x: f32| if new_area_m2 > 0.0 { x / new_area_m2 } else { 0.0 };
    WorldStats {
        new_area_m2,
        ground_height_m: ground,
        objects: object_areas_m2.len(),
        objects_per_100m2: per_area(100.0 * object_areas_m2.len() as f32),
        median_object_area_m2: median(&object_areas_m2).unwrap_or(0.0),
        p90_object_area_m2: quantile(&object_areas_m2, 0.9),
        object_cover: per_area(object.iter().filter(|o| **o).count() as f32 * cell_area),
        object_saturation: if sat_n > 0 { (sat_sum / sat_n as f64) as f32 } else { 0.0 },
        ground_rms_mm,
        object_areas_m2,
        object_shape: ShapeSummary::of(&object_shapes),
        object_shapes,
    }
}

/// The ground level of a set of cell heights: the median of the cells in the densest height band
/// `[h, h + 2 half_window_m]`. Bands holding at least 95 % of the densest one's cells count as
/// tied, and the tie goes to the band nearest the median of all heights, so a ground without one
/// dominant level (a ramp, two equal terraces) falls back to the overall median. `None` when
/// `heights` holds no finite value.
pub fn ground_level(heights: &[f32], half_window_m: f32) -> Option<f32> {
    let mut h: Vec<f32> = heights.iter().copied().filter(|x| x.is_finite()).collect();
    h.sort_by(f32::total_cmp);
    let all = median(&h)?;
    let width = 2.0 * half_window_m.max(0.0);
    // bands starting at each cell: [start, end)
    let mut bands = Vec::with_capacity(h.len());
    let mut end = 0usize;
    for start in 0..h.len() {
        end = end.max(start);
        while end < h.len() && h[end] - h[start] <= width {
            end += 1;
        }
        bands.push((start, end));
    }
    let densest = bands.iter().map(|(a, b)| b - a).max()?;
    let centre = |&(a, b): &(usize, usize)| 0.5 * (h[a] + h[b - 1]);
    let (a, b) = bands
        .into_iter()
        .filter(|(a, b)| (b - a) as f64 >= 0.95 * densest as f64)
        .min_by(|x, y| (centre(x) - all).abs().total_cmp(&(centre(y) - all).abs()))?;
    median(&h[a..b])
}

/// The 8-connected component of `mask` cells holding `start`, marking them in `seen`.
fn flood_fill(hf: &HeightField, mask: &[bool], seen: &mut [bool], start: usize) -> Vec<usize> {
    let (mut stack, mut out) = (vec![start], Vec::new());
    seen[start] = true;
    while let Some(i) = stack.pop() {
        out.push(i);
        let (x, y) = ((i % hf.nx) as i64, (i / hf.nx) as i64);
        for (dx, dy) in [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)] {
            let (u, v) = (x + dx, y + dy);
            if u >= 0 && v >= 0 && (u as usize) < hf.nx && (v as usize) < hf.ny {
                let j = v as usize * hf.nx + u as usize;
                if mask[j] && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            }
        }
    }
    out
}

/// Statistics pooled over several worlds (the seeds of `sgam eval world`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PooledStats {
    /// Summed new area, m².
    pub new_area_m2: f64,
    /// Objects per 100 m² of new area (all seeds' objects over all seeds' area).
    pub objects_per_100m2: f64,
    /// Median object footprint over all seeds' objects, m².
    pub median_object_area_m2: f64,
    /// 90th percentile object footprint, m².
    pub p90_object_area_m2: f64,
    /// Share of new area covered by objects.
    pub object_cover: f64,
    /// Mean over seeds of the object colour saturation (seeds without objects skipped).
    pub object_saturation: f64,
    /// Root of the mean over seeds of the squared ground RMS, mm.
    pub ground_rms_mm: f64,
    /// Median solidity, median elongation and compact share over all seeds' objects.
    pub object_shape: ShapeSummary,
}

impl PooledStats {
    /// Pools `stats`: counts and areas summed, footprints and shapes over all worlds' objects,
    /// saturation averaged over the worlds with objects, ground RMS as a root mean square.
    pub fn of(stats: &[WorldStats]) -> Self {
        let area: f64 = stats.iter().map(|s| s.new_area_m2 as f64).sum();
        let objects: usize = stats.iter().map(|s| s.objects).sum();
        let mut areas: Vec<f32> = stats.iter().flat_map(|s| s.object_areas_m2.iter().copied()).collect();
        areas.sort_by(f32::total_cmp);
        let covered: f64 = stats.iter().map(|s| s.object_cover as f64 * s.new_area_m2 as f64).sum();
        let sats: Vec<f64> = stats
            .iter()
            .filter(|s| s.objects > 0 && s.object_saturation.is_finite())
            .map(|s| s.object_saturation as f64)
            .collect();
        let rms2: Vec<f64> =
            stats.iter().filter(|s| s.ground_rms_mm.is_finite()).map(|s| (s.ground_rms_mm as f64).powi(2)).collect();
        Self {
            new_area_m2: area,
            objects_per_100m2: if area > 0.0 { 100.0 * objects as f64 / area } else { 0.0 },
            median_object_area_m2: quantile(&areas, 0.5) as f64,
            p90_object_area_m2: quantile(&areas, 0.9) as f64,
            object_cover: if area > 0.0 { covered / area } else { 0.0 },
            object_saturation: if sats.is_empty() { 0.0 } else { sats.iter().sum::<f64>() / sats.len() as f64 },
            ground_rms_mm: if rms2.is_empty() {
                f64::NAN
            } else {
                (rms2.iter().sum::<f64>() / rms2.len() as f64).sqrt()
            },
            object_shape: ShapeSummary::of(&stats.iter().flat_map(|s| s.object_shapes.clone()).collect::<Vec<_>>()),
        }
    }
}

/// `q`-quantile of ascending `sorted`, linear between ranks; 0 when empty.
pub fn quantile(sorted: &[f32], q: f32) -> f32 {
    if sorted.is_empty() {
        return 0.0;
    }
    let pos = q.clamp(0.0, 1.0) * (sorted.len() - 1) as f32;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f32)
}

/// The finite mesh vertices (metres, world frame) outside `exclusion` grown by
/// `cfg.exclusion_margin_m`: the new area's points for [`crate::scene::region_histograms`].
pub fn new_area_points(mesh: &TriMesh, exclusion: &Exclusion, cfg: &WorldStatsConfig) -> Vec<Vec3> {
    mesh.positions
        .iter()
        .filter(|p| p.is_finite() && !exclusion.excludes(p.truncate(), cfg.exclusion_margin_m))
        .copied()
        .collect()
}

/// A [`RegionSpec`] over the xy bounding box of `points` (metres), regions of `region_size_m`
/// metres with `bins` voxels per axis, and a slab from `ground_height_m - 0.5` to
/// `ground_height_m + 3.0` metres. Why that slab: objects stand at most 2 m tall, so it holds the
/// ground with its dips and every object with headroom, while sky domes, far walls and deep
/// holes (which would squeeze the 15 height bins) fall outside; and being tied to each world's
/// own ground, a generated world and its oracle are voxelised alike even if their ground drifted
/// in absolute z. `None` when `points` is empty or an argument is not finite and positive.
pub fn new_area_region_spec(
    points: &[Vec3],
    ground_height_m: f32,
    region_size_m: f32,
    bins: usize,
) -> Option<RegionSpec> {
    let ok = !points.is_empty()
        && ground_height_m.is_finite()
        && region_size_m > 0.0
        && region_size_m.is_finite()
        && bins > 0;
    let (lo, hi) = points
        .iter()
        .filter(|p| p.is_finite())
        .fold((Vec2::INFINITY, Vec2::NEG_INFINITY), |(lo, hi), p| (lo.min(p.truncate()), hi.max(p.truncate())));
    (ok && lo.is_finite() && hi.is_finite()).then(|| RegionSpec {
        min: lo.extend(ground_height_m - 0.5),
        max: hi.extend(ground_height_m + 3.0),
        region_size_m,
        bins,
    })
}
