//! World-level statistics on analytic worlds: flat/tilted/terraced grounds with axis-aligned boxes.
//!
//! Meshes are built here: grounds are grids of quads, boxes are closed meshes of six grid faces.
//! `Fine` puts a vertex every <= 5 cm (marching-cubes-like density), `Coarse` makes every face two
//! triangles (so only the triangle sampling of `height_field` can fill the cells).
//! Ground vertices sit at 0.025 + 0.05 k m, never on a 10 cm cell boundary, so which cell a ground
//! vertex falls in is never a matter of rounding.

use glam::{Vec2, Vec3};
use rand::{Rng, SeedableRng};
use sgam_core::TriMesh;
use sgam_metrics::scene::{cosine_distance, region_histograms, scene_metrics};
use sgam_metrics::world::{
    height_field, new_area_points, new_area_region_spec, object_shape, world_stats, Exclusion, ObjectShape,
    ShapeSummary, WorldStats, WorldStatsConfig,
};

const CELL: f32 = 0.1;
const GROUND_Z: f32 = -11.695;
/// Saturation (max - min) 0.1.
const GROUND_RGB: [f32; 3] = [0.5, 0.45, 0.4];

#[derive(Clone, Copy, PartialEq)]
enum Density {
    Fine,
    Coarse,
}

/// Parallelogram `o + s u + t v`, `s, t` in `[0, 1]`, cut into quads of side <= 5 cm (`Fine`) or
/// one quad (`Coarse`), two triangles each.
fn patch(o: Vec3, u: Vec3, v: Vec3, density: Density, rgb: [f32; 3]) -> TriMesh {
    let div = |e: Vec3| if density == Density::Fine { (e.length() / 0.05 - 1e-3).ceil().max(1.0) as u32 } else { 1 };
    let (nu, nv) = (div(u), div(v));
    let mut m = TriMesh::default();
    for j in 0..=nv {
        for i in 0..=nu {
            m.positions.push(o + u * (i as f32 / nu as f32) + v * (j as f32 / nv as f32));
            m.colours.push(rgb);
        }
    }
    let w = nu + 1;
    for j in 0..nv {
        for i in 0..nu {
            let a = j * w + i;
            m.triangles.push([a, a + 1, a + w + 1]);
            m.triangles.push([a, a + w + 1, a + w]);
        }
    }
    m
}

/// Horizontal ground `[x0, x1] x [y0, y1]` at height `z`.
fn ground(x0: f32, y0: f32, x1: f32, y1: f32, z: f32, density: Density) -> TriMesh {
    patch(Vec3::new(x0, y0, z), Vec3::X * (x1 - x0), Vec3::Y * (y1 - y0), density, GROUND_RGB)
}

/// Closed axis-aligned box, all six faces.
fn cuboid(min: Vec3, max: Vec3, rgb: [f32; 3], density: Density) -> TriMesh {
    let e = max - min;
    let (ex, ey, ez) = (Vec3::X * e.x, Vec3::Y * e.y, Vec3::Z * e.z);
    let mut m = TriMesh::default();
    for (o, u, v) in
        [(min, ex, ey), (min + ez, ex, ey), (min, ey, ez), (min + ex, ey, ez), (min, ex, ez), (min + ey, ex, ez)]
    {
        m.append(&patch(o, u, v, density, rgb));
    }
    m
}

/// A box standing on the flat ground: footprint `[x0, x1] x [y0, y1]`, `height` metres tall.
fn standing(x0: f32, y0: f32, x1: f32, y1: f32, height: f32, rgb: [f32; 3], density: Density) -> TriMesh {
    cuboid(Vec3::new(x0, y0, GROUND_Z), Vec3::new(x1, y1, GROUND_Z + height), rgb, density)
}

/// One cell ring around a `w x d` footprint: the cells a footprint touches cover it and exceed it
/// by at most one partial cell on each side, `(w + 2c)(d + 2c) - wd = perimeter * c + 4c^2`.
fn ring_tolerance(w: f32, d: f32) -> f32 {
    2.0 * (w + d) * CELL + 4.0 * CELL * CELL
}

/// Boxes (footprint, height) with saturation 0.6 each, > 0.3 m apart, on a 12 x 12 m ground.
const SIX_BOXES: [([f32; 4], f32, [f32; 3]); 6] = [
    ([1.03, 1.03, 2.03, 2.03], 0.7, [0.8, 0.2, 0.5]),
    ([4.03, 1.53, 6.03, 3.53], 2.0, [0.1, 0.7, 0.3]),
    ([8.03, 1.03, 8.73, 2.43], 1.2, [0.2, 0.4, 0.8]),
    ([1.53, 5.03, 3.03, 5.53], 0.9, [0.9, 0.3, 0.6]),
    ([5.03, 6.03, 6.23, 7.23], 1.5, [0.65, 0.05, 0.4]),
    // 0.225 m^2 and 0.3 m tall: just above both thresholds
    ([9.03, 6.03, 9.53, 6.48], 0.3, [0.3, 0.9, 0.9]),
];

fn six_box_world(density: Density) -> TriMesh {
    let mut m = ground(0.025, 0.025, 11.975, 11.975, GROUND_Z, density);
    for ([x0, y0, x1, y1], h, rgb) in SIX_BOXES {
        m.append(&standing(x0, y0, x1, y1, h, rgb, density));
    }
    m
}

fn sorted(mut v: Vec<f32>) -> Vec<f32> {
    v.sort_by(f32::total_cmp);
    v
}

/// Linear-between-ranks quantile, as documented for `p90_object_area_m2` / the median.
fn quantile(sorted: &[f32], q: f32) -> f32 {
    let pos = q * (sorted.len() - 1) as f32;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f32)
}

fn check_six_boxes(s: &WorldStats) {
    // the ground grid's cells are exactly 120 x 120 (vertices from 0.025 to 11.975 m)
    assert!((s.new_area_m2 - 144.0).abs() < 1e-2, "{s:?}");
    // every ground cell is at exactly GROUND_Z (flat triangles interpolate z exactly): the median
    // is it, and the ground has no roughness
    assert!((s.ground_height_m - GROUND_Z).abs() < 1e-6, "{s:?}");
    assert!(s.ground_rms_mm < 1.0, "{s:?}");
    assert_eq!(s.objects, SIX_BOXES.len(), "{s:?}");
    assert!((s.objects_per_100m2 - 600.0 / 144.0).abs() < 1e-3, "{s:?}");
    // measured footprint of each box in [true, true + ring]; sorting keeps elementwise bounds
    let truth: Vec<(f32, f32)> = SIX_BOXES
        .iter()
        .map(|([x0, y0, x1, y1], _, _)| ((x1 - x0) * (y1 - y0), ring_tolerance(x1 - x0, y1 - y0)))
        .collect();
    let lo = sorted(truth.iter().map(|t| t.0 - 1e-4).collect());
    let hi = sorted(truth.iter().map(|t| t.0 + t.1).collect());
    assert_eq!(s.object_areas_m2, sorted(s.object_areas_m2.clone()));
    for ((a, l), h) in s.object_areas_m2.iter().zip(&lo).zip(&hi) {
        assert!(*l <= *a && *a <= *h, "area {a} outside [{l}, {h}]: {:?}", s.object_areas_m2);
    }
    // median and p90 are monotone in every area, so they lie between their values on the bounds
    // (a nearest-rank p90 would give ~4.0 here, above the upper bound 3.4)
    for (got, q) in [(s.median_object_area_m2, 0.5), (s.p90_object_area_m2, 0.9)] {
        assert!(quantile(&lo, q) <= got && got <= quantile(&hi, q), "q{q}: {got} {lo:?} {hi:?}");
    }
    let cover = |b: &[f32]| b.iter().sum::<f32>() / 144.0;
    assert!(cover(&lo) <= s.object_cover && s.object_cover <= cover(&hi), "{s:?}");
    // only box vertices (saturation 0.6) stand above ground + 0.25 m; ground vertices (0.1) under
    // or beside a box lie in object cells but too low, and would pull the mean down
    assert!((s.object_saturation - 0.6).abs() < 1e-3, "{s:?}");
}

#[test]
fn boxes_on_flat_ground_are_counted_with_their_footprints() {
    check_six_boxes(&world_stats(&six_box_world(Density::Fine), &Exclusion::none(), &WorldStatsConfig::default()));
}

#[test]
fn two_triangle_faces_give_the_same_objects() {
    // only 4 corners per face: without triangle sampling the ground would be 4 occupied cells
    // and every box top 4 cells (0.04 m^2, below the 0.2 m^2 minimum)
    let coarse = world_stats(&six_box_world(Density::Coarse), &Exclusion::none(), &WorldStatsConfig::default());
    check_six_boxes(&coarse);
}

#[test]
fn coarse_triangle_fills_its_cells_with_plane_heights() {
    // one triangle on the plane z = 0.1 x + 0.2 y
    let plane = |p: Vec2| 0.1 * p.x + 0.2 * p.y;
    let corners = [Vec2::new(0.025, 0.025), Vec2::new(4.975, 0.025), Vec2::new(0.025, 2.975)];
    let mesh = TriMesh {
        positions: corners.iter().map(|c| c.extend(plane(*c))).collect(),
        colours: vec![],
        triangles: vec![[0, 1, 2]],
    };
    let hf = height_field(&mesh, CELL);
    assert_eq!((hf.nx, hf.ny), (50, 30));
    let occupied: Vec<usize> = (0..hf.height_m.len()).filter(|i| hf.height_m[*i].is_finite()).collect();
    // occupied area within the cells the boundary crosses: a convex outline crosses at most
    // (sum |dx| + |dy| along it) / c + 4 cells = 2 (4.95 + 2.95) / c + 4
    let area = 0.5 * 4.95 * 2.95;
    let tol = (2.0 * (4.95 + 2.95) / CELL + 4.0) * CELL * CELL;
    let got = occupied.len() as f32 * CELL * CELL;
    assert!((got - area).abs() <= tol, "occupied {got} m^2, triangle {area} m^2, tolerance {tol}");
    // every height is a point of the plane inside its cell: between the plane's min and max there
    for i in occupied {
        let lo = hf.cell_centre(i) - 0.5 * CELL;
        let (min, max) = (plane(lo), plane(lo + CELL));
        assert!(min - 1e-5 <= hf.height_m[i] && hf.height_m[i] <= max + 1e-5, "cell {i}: {}", hf.height_m[i]);
    }
}

#[test]
fn small_low_and_diagonal_boxes() {
    let rgb = [0.8, 0.2, 0.5];
    let mut m = ground(0.025, 0.025, 11.975, 11.975, GROUND_Z, Density::Fine);
    // 0.3 x 0.3 m: 4 x 4 cells = 0.16 m^2 < 0.2: not an object, and not ground either
    m.append(&standing(1.03, 1.03, 1.33, 1.33, 1.0, rgb, Density::Fine));
    // 1 x 1 m but 0.2 m tall (< 0.25): ground, 11 x 11 cells at +0.2 m
    m.append(&standing(8.03, 8.03, 9.03, 9.03, 0.2, rgb, Density::Fine));
    // cells 30..=39 and 40..=49 on both axes: they meet at one cell corner only (one object with
    // 8-connectivity, two with 4-connectivity)
    m.append(&standing(3.03, 3.03, 3.97, 3.97, 1.0, rgb, Density::Fine));
    m.append(&standing(4.03, 4.03, 4.97, 4.97, 1.0, rgb, Density::Fine));
    // 0.3 m apart (cells 60..=70 and 73..=83): two objects
    m.append(&standing(6.03, 1.03, 7.03, 2.03, 1.0, rgb, Density::Fine));
    m.append(&standing(7.33, 1.03, 8.33, 2.03, 1.0, rgb, Density::Fine));
    // cells 100..=104 x 100..=103: exactly 20 cells = 0.2 m^2, the minimum, so an object (the
    // rule is area >= minimum; `>` would drop it)
    m.append(&standing(10.03, 10.03, 10.47, 10.37, 1.0, rgb, Density::Fine));
    let s = world_stats(&m, &Exclusion::none(), &WorldStatsConfig::default());
    assert_eq!(s.objects, 4, "{s:?}");
    let want = [0.2, 1.21, 1.21, 2.0];
    assert!(s.object_areas_m2.iter().zip(want).all(|(a, w)| (a - w).abs() < 1e-3), "{s:?}");
    // ground = 14400 cells - 16 (small box) - 200 (diagonal pair) - 242 (the 0.3 m pair) - 20;
    // the low box's 121 cells sit 0.2 m above the median. Counting the small box as ground would
    // add 16 cells at 1 m (38.6 mm); dropping the low box would give 0 mm.
    let rms_mm = 200.0 * (121.0f32 / (14400 - 16 - 200 - 242 - 20) as f32).sqrt();
    assert!((s.ground_rms_mm - rms_mm).abs() < 0.1, "{} vs {rms_mm}", s.ground_rms_mm);
}

#[test]
fn tilted_ground_rms_is_the_ramp_rms() {
    // z = s x over 20 x 20 m (200 cell columns); heights span +-0.2 m about the median, under the
    // 0.25 m object height
    let (s, l) = (0.02f32, 20.0f32);
    let m = patch(
        Vec3::new(0.025, 0.025, s * 0.025),
        Vec3::new(l - 0.05, 0.0, s * (l - 0.05)),
        Vec3::Y * (l - 0.05),
        Density::Fine,
        GROUND_RGB,
    );
    let st = world_stats(&m, &Exclusion::none(), &WorldStatsConfig::default());
    assert_eq!(st.objects, 0, "{st:?}");
    // a uniform ramp about its median: s L / sqrt(12) = 115.5 mm. Each cell holds the highest
    // point of its 10 cm column, s (x_centre + b + e) with a common bias b (cancels against the
    // median) and |e| <= s c / 2; the median moves by at most s c / 2 too, so the RMS is off by
    // at most s c = 2 mm (the 200-column discretisation adds < 0.01 mm)
    let want_mm = s * l / 12f32.sqrt() * 1e3;
    assert!((st.ground_rms_mm - want_mm).abs() <= s * CELL * 1e3, "{} vs {want_mm}", st.ground_rms_mm);
}

#[test]
fn terraced_ground_rms_is_half_the_step() {
    // two 2 x 4 m levels 0.1 m apart, each exactly 20 x 40 cells (separate patches, so no triangle
    // reaches into the other's cells): the median is midway and every cell is 50 mm from it
    let mut m = ground(0.025, 0.025, 1.975, 3.975, 0.0, Density::Fine);
    m.append(&ground(2.025, 0.025, 3.975, 3.975, 0.1, Density::Fine));
    let s = world_stats(&m, &Exclusion::none(), &WorldStatsConfig::default());
    assert!((s.ground_height_m - 0.05).abs() < 1e-6, "{s:?}");
    // exact up to f32 rounding (a lower-middle median would give 70.7 mm)
    assert!((s.ground_rms_mm - 50.0).abs() < 0.01, "{s:?}");
    assert_eq!(s.objects, 0);
}

#[test]
fn exclusion_geometry() {
    let tri = [Vec2::new(0.0, 0.0), Vec2::new(4.0, 0.0), Vec2::new(0.0, 3.0)];
    for poly in [tri.to_vec(), tri.iter().rev().copied().collect()] {
        let e = Exclusion { polygon_xy_m: poly };
        assert!(e.excludes(Vec2::new(1.0, 1.0), 0.0), "inside");
        // (5, 0) is 1 m from the corner (4, 0); (-0.5, -0.5) is 0.71 m from (0, 0)
        assert!(e.excludes(Vec2::new(5.0, 0.0), 1.0) && !e.excludes(Vec2::new(5.0, 0.0), 0.99));
        assert!(e.excludes(Vec2::new(-0.5, -0.5), 0.75) && !e.excludes(Vec2::new(-0.5, -0.5), 0.7));
        // (3, 3) is |9 + 12 - 12| / 5 = 1.8 m from the hypotenuse 3x + 4y = 12
        assert!(e.excludes(Vec2::new(3.0, 3.0), 1.81) && !e.excludes(Vec2::new(3.0, 3.0), 1.79));
    }
    assert!(!Exclusion::none().excludes(Vec2::ZERO, 100.0));
    let dot = Exclusion { polygon_xy_m: vec![Vec2::new(1.0, 1.0)] };
    assert!(dot.excludes(Vec2::new(1.5, 1.0), 0.6) && !dot.excludes(Vec2::new(1.5, 1.0), 0.4));
}

#[test]
fn exclusion_removes_boxes_and_area() {
    let rgb = [0.8, 0.2, 0.5];
    let mut m = ground(0.025, 0.025, 15.975, 15.975, GROUND_Z, Density::Fine);
    m.append(&standing(7.03, 6.53, 8.03, 7.53, 1.0, rgb, Density::Fine)); // inside the polygon
    m.append(&standing(9.23, 6.53, 9.83, 7.53, 1.0, rgb, Density::Fine)); // inside the 1 m margin
    m.append(&standing(12.03, 12.03, 13.03, 13.03, 1.0, rgb, Density::Fine)); // outside
                                                                              // the rectangle [6, 9] x [6, 8] in clockwise order; grown by 1 m its straight edges lie on
                                                                              // cell boundaries (x = 5, 10; y = 5, 9), so only the rounded corners are approximate
    let (lo, hi) = (Vec2::new(6.0, 6.0), Vec2::new(9.0, 8.0));
    let ex = Exclusion { polygon_xy_m: vec![lo, Vec2::new(6.0, 8.0), hi, Vec2::new(9.0, 6.0)] };
    let cfg = WorldStatsConfig::default();
    let all = world_stats(&m, &Exclusion::none(), &cfg);
    let out = world_stats(&m, &ex, &cfg);
    assert_eq!(all.objects, 3, "{all:?}");
    assert_eq!(out.objects, 1, "{out:?}");
    assert!((out.object_areas_m2[0] - 1.0).abs() <= ring_tolerance(1.0, 1.0), "{out:?}");
    assert!(out.ground_rms_mm < 1.0 && (out.ground_height_m - GROUND_Z).abs() < 1e-6);
    // exactly the cells whose centre is within 1 m of the rectangle (an independent distance:
    // clamp to the axis-aligned rectangle) leave the new area
    let removed = (0..160 * 160)
        .map(|i| (Vec2::new((i % 160) as f32, (i / 160) as f32) + 0.5) * CELL)
        .filter(|c| c.distance(c.clamp(lo, hi)) <= 1.0)
        .count();
    let shrink = all.new_area_m2 - out.new_area_m2;
    assert!((shrink - removed as f32 * CELL * CELL).abs() < 1e-2, "{shrink} vs {removed} cells");
    // and that is the grown area W H + P r + pi r^2 = 6 + 10 + pi, up to the cells the four
    // quarter circles cross: at most 4 (2 r / c + 1) cells
    let grown = 6.0 + 10.0 + std::f32::consts::PI;
    let tol = 4.0 * (2.0 * 1.0 / CELL + 1.0) * CELL * CELL;
    assert!((shrink - grown).abs() <= tol, "shrink {shrink} vs grown area {grown} (tolerance {tol})");
    // new-area points: all vertices but those in the grown rectangle
    let pts = new_area_points(&m, &ex, &cfg);
    let inside = m.positions.iter().filter(|p| p.truncate().distance(p.truncate().clamp(lo, hi)) <= 1.0).count();
    assert_eq!(pts.len(), m.positions.len() - inside);
    assert!(pts.iter().all(|p| p.truncate().distance(p.truncate().clamp(lo, hi)) > 1.0));
}

/// A 16 x 16 m world with one random box in each 4 x 4 m region (so no two regions look alike).
fn random_world(seed: u64) -> TriMesh {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut m = ground(0.025, 0.025, 16.075, 16.075, GROUND_Z, Density::Fine);
    for r in 0..16 {
        let (w, d, h) = (rng.random_range(0.5..2.0), rng.random_range(0.5..2.0), rng.random_range(0.4..2.0));
        let x0 = (r % 4) as f32 * 4.0 + rng.random_range(0.3..3.5 - w);
        let y0 = (r / 4) as f32 * 4.0 + rng.random_range(0.3..3.5 - d);
        let rgb = [rng.random_range(0.0..1.0), rng.random_range(0.0..1.0), rng.random_range(0.0..1.0)];
        m.append(&standing(x0, y0, x0 + w, y0 + d, h, rgb, Density::Fine));
    }
    m
}

#[test]
fn identical_worlds_score_identically() {
    let cfg = WorldStatsConfig::default();
    let (a, b) = (random_world(7), random_world(7));
    let (sa, sb) = (world_stats(&a, &Exclusion::none(), &cfg), world_stats(&b, &Exclusion::none(), &cfg));
    assert_eq!(sa, sb);
    assert_eq!(sa.objects, 16, "{sa:?}");
    assert_ne!(sa, world_stats(&random_world(8), &Exclusion::none(), &cfg));

    let pts = new_area_points(&a, &Exclusion::none(), &cfg);
    let spec = new_area_region_spec(&pts, sa.ground_height_m, 4.0, 15).unwrap();
    assert!((spec.min.z - (GROUND_Z - 0.5)).abs() < 1e-5 && (spec.max.z - (GROUND_Z + 3.0)).abs() < 1e-5);
    assert!((spec.min.x - 0.025).abs() < 1e-5 && (spec.max.y - 16.075).abs() < 1e-3);
    assert!(new_area_region_spec(&[], 0.0, 4.0, 15).is_none());
    let hist = region_histograms(&pts, &spec);
    assert_eq!(hist.len(), 16);
    for i in 0..hist.len() {
        for j in 0..i {
            assert!(cosine_distance(&hist[i], &hist[j]) > 1e-3, "regions {i} and {j} alike");
        }
    }
    let m = scene_metrics(&hist, &hist).unwrap();
    assert!(m.jsd.abs() < 1e-12 && m.mmd < 1e-9 && m.min_dist < 1e-9 && m.cov == 1.0, "{m:?}");
    // 1-NNA is 0, not 0.5: leaving a region out, its nearest neighbour is its exact copy in the
    // other set (distance 0, while every other region is > 1e-3 away), which carries the other
    // label, so every region is misclassified. 0.5 is what two independent samples of one
    // distribution score; 0 is the memorisation extreme.
    assert_eq!(m.one_nna, 0.0, "{m:?}");
}

/// Distance (metres) from `p` to the triangle `t` in the xy plane: 0 inside, else to the nearest
/// edge. Written here apart from `Exclusion::excludes`, so the expected count does not reuse it.
fn distance_to_triangle(p: Vec2, t: &[Vec2; 3]) -> f32 {
    let side = |a: Vec2, b: Vec2| (b - a).perp_dot(p - a);
    let s = [side(t[0], t[1]), side(t[1], t[2]), side(t[2], t[0])];
    if s.iter().all(|x| *x >= 0.0) || s.iter().all(|x| *x <= 0.0) {
        return 0.0;
    }
    (0..3)
        .map(|i| {
            let (a, b) = (t[i], t[(i + 1) % 3]);
            let u = ((p - a).dot(b - a) / (b - a).length_squared()).clamp(0.0, 1.0);
            p.distance(a + (b - a) * u)
        })
        .fold(f32::INFINITY, f32::min)
}

#[test]
fn forty_metre_world_counts_its_cubes() {
    // 40 x 40 m ground at 5 cm (640k vertices) and 100 unit cubes (265k vertices), 4 m apart
    // (3 m of open ground between neighbours: no two cubes can merge into one object)
    let mut m = ground(0.025, 0.025, 39.975, 39.975, GROUND_Z, Density::Fine);
    let corners: Vec<(f32, f32)> =
        (0..100).map(|i| ((i % 10) as f32 * 4.0 + 1.03, (i / 10) as f32 * 4.0 + 1.03)).collect();
    for &(x, y) in &corners {
        m.append(&standing(x, y, x + 1.0, y + 1.0, 1.0, [0.8, 0.2, 0.5], Density::Fine));
    }
    let tri = [Vec2::new(18.0, 18.0), Vec2::new(22.0, 18.0), Vec2::new(20.0, 22.0)];
    let ex = Exclusion { polygon_xy_m: tri.to_vec() };
    let cfg = WorldStatsConfig::default();
    let t = std::time::Instant::now();
    let s = world_stats(&m, &ex, &cfg);
    let secs = t.elapsed().as_secs_f64();
    eprintln!("world_stats on {} vertices, {} triangles: {secs:.3} s", m.positions.len(), m.triangles.len());
    // Expected, cell by cell: a cube spanning [x, x + 1] with x = 1.03 + 4i raises the 11 x 11
    // cells floor(10 x) ..= floor(10 (x + 1)) (its walls sit 3 mm inside the outer ones; no
    // vertex lies on a cell boundary), 121 cells = 1.21 m^2. A cell is left out when its centre
    // lies within the 1 m margin of the triangle (no centre is within 6 mm of that margin, so
    // rounding cannot flip one). Only three cubes come that close: (4, 4) at [17.03, 18.03]^2
    // keeps the 21 cells more than 1 m from the vertex (18, 18) (its far corner, 1.37 m away),
    // (5, 5) at [21.03, 22.03]^2 keeps the 85 cells more than 1 m from the edge (22, 18)-(20, 22),
    // and (5, 4) at [21.03, 22.03] x [17.03, 18.03] lies within 1 m of the bottom edge and loses
    // all. Each remnant is one piece (a square less a disc at one corner, a square less a
    // half-plane), and an object needs 20 cells (0.2 m^2): 97 whole cubes + 2 remnants = 99.
    let kept_cells: Vec<usize> = corners
        .iter()
        .map(|&(x, y)| {
            let cells = |lo: f32| (lo / CELL).floor() as i32..=((lo + 1.0) / CELL).floor() as i32;
            cells(x)
                .flat_map(|i| cells(y).map(move |j| Vec2::new((i as f32 + 0.5) * CELL, (j as f32 + 0.5) * CELL)))
                .filter(|c| distance_to_triangle(*c, &tri) > cfg.exclusion_margin_m)
                .count()
        })
        .collect();
    let mut cut: Vec<(usize, usize)> = kept_cells.iter().copied().enumerate().filter(|(_, n)| *n != 121).collect();
    cut.sort_unstable();
    assert_eq!(cut, vec![(44, 21), (45, 0), (55, 85)], "cubes cut by the exclusion (index, cells kept)");
    let mut expected: Vec<f32> = kept_cells.iter().filter(|n| **n >= 20).map(|n| *n as f32 * CELL * CELL).collect();
    expected.sort_by(f32::total_cmp);
    assert_eq!(s.objects, 99, "{s:?}");
    assert_eq!(s.object_areas_m2.len(), expected.len());
    for (got, want) in s.object_areas_m2.iter().zip(&expected) {
        assert!((got - want).abs() < 1e-4, "areas {:?}, expected {expected:?}", s.object_areas_m2);
    }
}

#[test]
fn ground_level_is_the_densest_level_not_the_median() {
    use sgam_metrics::world::ground_level;
    // 40 % of the cells on a flat ground at 0, 60 % in lumps spread over 0.3..1.5 m: the median
    // (0.42 m) lies in the lumps; the ground level is the flat ground
    let mut h = vec![0.0f32; 400];
    h.extend((0..600).map(|i| 0.3 + 1.2 * i as f32 / 599.0));
    assert!(sgam_metrics::median(&h).unwrap() > 0.3);
    assert_eq!(ground_level(&h, 0.1), Some(0.0));
    // a uniform ramp has no dominant level: the band nearest the median wins
    let ramp: Vec<f32> = (0..1001).map(|i| i as f32 / 1000.0).collect();
    let g = ground_level(&ramp, 0.1).unwrap();
    assert!((g - 0.5).abs() < 0.02, "{g}");
    assert_eq!(ground_level(&[], 0.1), None);
    assert_eq!(ground_level(&[f32::NAN, 2.0], 0.1), Some(2.0));
}

#[test]
fn lumps_covering_most_of_the_area_leave_the_ground_on_the_ground() {
    // a flat 12 x 12 m ground under three 12 x 2.3 m slabs 0.5, 0.9 and 1.3 m tall, 0.3 m
    // apart: the slabs cover 57 % of the cells but no one level holds more than the ground's
    // 43 %, so the ground stays at GROUND_Z with no roughness and the slabs are 3 objects. (A
    // median over all cells lies on the 0.9 m slab: no ground would be found at all, the real
    // ground and the 0.5 m slab would count as 0.4-0.9 m rough.)
    let mut m = ground(0.025, 0.025, 11.975, 11.975, GROUND_Z, Density::Fine);
    for (i, height) in [0.5f32, 0.9, 1.3].into_iter().enumerate() {
        let y0 = 2.6 * i as f32;
        m.append(&standing(0.0, y0, 12.0, y0 + 2.3, height, [0.9, 0.2, 0.2], Density::Fine));
    }
    let s = world_stats(&m, &Exclusion::none(), &WorldStatsConfig::default());
    assert!((s.ground_height_m - GROUND_Z).abs() < 1e-6, "{s:?}");
    assert!(s.ground_rms_mm < 1.0, "{s:?}");
    assert_eq!(s.objects, 3, "{s:?}");
}

/// World statistics of a 12 x 12 m flat ground with 1 m tall boxes of the given footprints
/// `[x0, y0, x1, y1]`. Footprints from `a.03` to `b.97` m cover exactly the cells `a*10 ..= b*10+9`
/// (no vertex within 3 cm of a cell boundary), so each object's cells are known exactly.
fn boxes_world(footprints: &[[f32; 4]]) -> WorldStats {
    let mut m = ground(0.025, 0.025, 11.975, 11.975, GROUND_Z, Density::Fine);
    for [x0, y0, x1, y1] in footprints {
        m.append(&standing(*x0, *y0, *x1, *y1, 1.0, [0.8, 0.2, 0.5], Density::Fine));
    }
    world_stats(&m, &Exclusion::none(), &WorldStatsConfig::default())
}

const SQUARE: [f32; 4] = [1.03, 1.03, 2.97, 2.97]; // 20 x 20 cells
const STRIP: [f32; 4] = [4.03, 1.03, 4.97, 8.97]; // 10 x 80 cells: 1 x 8 m

#[test]
fn square_object_is_solid_round_and_compact() {
    let s = boxes_world(&[SQUARE]);
    assert_eq!(s.object_areas_m2.len(), 1, "{s:?}");
    assert!((s.object_areas_m2[0] - 4.0).abs() < 1e-4, "{s:?}");
    let shape = s.object_shapes[0];
    // a filled square of cells is its own hull; its covariance is isotropic
    assert_eq!(shape.solidity, 1.0, "{shape:?}");
    assert!((shape.elongation - 1.0).abs() < 1e-5, "{shape:?}");
    assert!(shape.is_compact());
    assert_eq!(s.object_shape.compact_share, Some(1.0));
}

#[test]
fn l_shaped_object_has_the_hand_counted_solidity() {
    // a 3 x 1 m bar and a 1 x 2 m bar on top of its left end: cells (ix, iy) of
    // [0, 29] x [0, 9] and [0, 9] x [10, 29] (taken from x = 1 m, y = 1 m): 300 + 200 = 500
    let s = boxes_world(&[[1.03, 1.03, 3.97, 1.97], [1.03, 2.03, 1.97, 3.97]]);
    assert_eq!(s.objects, 1, "{s:?}");
    assert!((s.object_areas_m2[0] - 5.0).abs() < 1e-4, "{s:?}");
    let shape = s.object_shapes[0];
    // hull of the centres: (0,0) (29,0) (29,9) (9,29) (0,29), the 30 x 30 square of centres
    // cut by x + y <= 38: 900 centres minus the 1 + 2 + ... + 20 = 210 beyond the cut = 690.
    // The counts are exact integers; only the division rounds (f32: ~1e-7), hence 1e-5.
    assert!((shape.solidity - 500.0 / 690.0).abs() < 1e-5, "{shape:?}");
    // covariance by hand (cell units): var x = var y = 72.25 + 1/12, cov = -36, so the
    // eigenvalues are 325/3 and 109/3. Not elongated: only its solidity makes it not compact.
    assert!((shape.elongation - (325.0f32 / 109.0).sqrt()).abs() < 1e-4, "{shape:?}");
    assert!(shape.elongation < 2.0 && !shape.is_compact(), "{shape:?}");
    assert_eq!(s.object_shape.compact_share, Some(0.0));
}

#[test]
fn strip_is_elongated_and_not_compact() {
    // a 1 x 8 m strip, and a single column of 1 x 30 cells (4 cm wide: one cell across)
    let s = boxes_world(&[STRIP, [6.03, 1.03, 6.07, 3.97]]);
    assert_eq!(s.objects, 2, "{s:?}");
    let (strip, row) = (s.object_shapes[0], s.object_shapes[1]);
    // variances (n^2 - 1)/12 + 1/12 = n^2/12 per axis: the elongation is the side ratio
    assert_eq!(strip.solidity, 1.0, "{strip:?}");
    assert!((strip.elongation - 8.0).abs() < 1e-3 && strip.elongation >= 2.0, "{strip:?}");
    assert!(!strip.is_compact());
    // one row: the hull is a segment holding every cell, and the guard keeps the ratio finite
    assert_eq!(row.solidity, 1.0, "{row:?}");
    assert!((row.elongation - 30.0).abs() < 1e-2, "{row:?}");
    assert_eq!(s.object_shape.compact_share, Some(0.0));
}

#[test]
fn square_and_strip_world_has_half_its_objects_compact() {
    let s = boxes_world(&[SQUARE, STRIP]);
    assert_eq!(s.objects, 2, "{s:?}");
    let summary = s.object_shape;
    assert_eq!(summary.compact_share, Some(0.5), "{summary:?}");
    assert_eq!(summary.median_solidity, Some(1.0), "{summary:?}");
    // the mean of the two middle values (1 and 8)
    assert!(summary.median_elongation.is_some_and(|e| (e - 4.5).abs() < 1e-3), "{summary:?}");
    // pooled over worlds: the objects concatenated, not the shares averaged (which gives 0.25)
    let l = boxes_world(&[[1.03, 1.03, 3.97, 1.97], [1.03, 2.03, 1.97, 3.97]]);
    let pooled: Vec<ObjectShape> = s.object_shapes.iter().chain(&l.object_shapes).copied().collect();
    let share = ShapeSummary::of(&pooled).compact_share;
    assert!(share.is_some_and(|c| (c - 1.0 / 3.0).abs() < 1e-6), "{share:?}");
    // no objects: no shape figures
    let empty = boxes_world(&[]);
    assert_eq!(empty.objects, 0);
    assert_eq!(
        empty.object_shape,
        ShapeSummary { median_solidity: None, median_elongation: None, compact_share: None }
    );
}

#[test]
fn object_shape_is_a_bounded_ratio_that_ignores_position_and_orientation() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(26);
    for case in 0..200 {
        let n = rng.random_range(1..60);
        let cells: Vec<[i64; 2]> = (0..n).map(|_| [rng.random_range(0..15), rng.random_range(0..15)]).collect();
        let Some(a) = object_shape(&cells) else { panic!("case {case}: no shape for {n} cells") };
        assert!(a.solidity > 0.0 && a.solidity <= 1.0 && a.elongation >= 1.0 - 1e-6, "case {case}: {a:?}");
        let moved: Vec<[i64; 2]> = cells.iter().map(|[x, y]| [x + 1000, y - 37]).collect();
        let turned: Vec<[i64; 2]> = cells.iter().map(|[x, y]| [-y, *x]).collect();
        let mirrored: Vec<[i64; 2]> = cells.iter().map(|[x, y]| [*y, *x]).collect();
        let doubled: Vec<[i64; 2]> = cells.iter().chain(&cells).copied().collect();
        for (name, other) in [("moved", moved), ("turned", turned), ("mirrored", mirrored), ("doubled", doubled)] {
            let Some(b) = object_shape(&other) else { panic!("case {case}: {name} has no shape") };
            // the hull count is exact integer arithmetic; the covariance is f64
            assert_eq!(a.solidity, b.solidity, "case {case} {name}");
            assert!((a.elongation - b.elongation).abs() <= 1e-5 * a.elongation, "case {case} {name}: {a:?} {b:?}");
        }
    }
    assert_eq!(object_shape(&[]), None);
    assert_eq!(object_shape(&[[3, 4]]), Some(ObjectShape { solidity: 1.0, elongation: 1.0 }));
    // a diagonal row of 8-connected cells is its own hull (a segment)
    assert_eq!(object_shape(&[[0, 0], [1, 1], [2, 2], [3, 3]]).map(|s| s.solidity), Some(1.0));
}

#[test]
fn pooled_statistics_sum_areas_pool_objects_and_average_per_world_figures() {
    use sgam_metrics::world::{PooledStats, ShapeSummary};
    let world = |area: f32, objects: Vec<f32>, cover: f32, saturation: f32, rms: f32| WorldStats {
        new_area_m2: area,
        ground_height_m: 0.0,
        objects: objects.len(),
        objects_per_100m2: 100.0 * objects.len() as f32 / area,
        median_object_area_m2: 0.0,
        p90_object_area_m2: 0.0,
        object_cover: cover,
        object_saturation: saturation,
        ground_rms_mm: rms,
        object_areas_m2: objects,
        object_shape: ShapeSummary::default(),
        object_shapes: Vec::new(),
    };
    // 100 m² with objects of 1 and 3 m², 300 m² with one of 2 m² and a flat world of 100 m²
    let stats = [
        world(100.0, vec![1.0, 3.0], 0.04, 0.5, 30.0),
        world(300.0, vec![2.0], 0.01, 0.7, 40.0),
        world(100.0, vec![], 0.0, f32::NAN, f32::NAN),
    ];
    let p = PooledStats::of(&stats);
    assert_eq!(p.new_area_m2, 500.0);
    // 3 objects over 500 m²; footprints pooled over worlds: 1, 2, 3
    assert!((p.objects_per_100m2 - 0.6).abs() < 1e-9, "{p:?}");
    assert_eq!(p.median_object_area_m2, 2.0);
    // linear between ranks: 2 + 0.8 * (3 - 2)
    assert!((p.p90_object_area_m2 - 2.8).abs() < 1e-6, "{p:?}");
    // cover weighted by area: (4 + 3) / 500
    assert!((p.object_cover - 0.014).abs() < 1e-6, "{p:?}");
    // saturation averaged over the worlds with objects; RMS over the worlds with a ground
    assert!((p.object_saturation - 0.6).abs() < 1e-6, "{p:?}");
    assert!((p.ground_rms_mm - ((900.0f64 + 1600.0) / 2.0).sqrt()).abs() < 1e-4, "{p:?}");
    assert_eq!(PooledStats::of(&[]).objects_per_100m2, 0.0);
}
