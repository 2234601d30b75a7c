//! The ray tracer: analytic primitives in a uniform 2-D grid over the ground, sun light with soft
//! shadows, sky/ambient term, stratified anti-aliasing, planar depth and object ids.

use glam::{Mat3, Vec2, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sgam_core::{linear_to_srgb, srgb_to_linear, Camera, Image, RgbdFrame};

use crate::scene::{Material, Scene, Shape};

/// Object id of the ground in [`SynthFrame::object_id`].
pub const GROUND_ID: u32 = 0;
/// Object id of the sky (no hit) in [`SynthFrame::object_id`].
pub const SKY_ID: u32 = u32::MAX;

/// Rendering options.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderConfig {
    /// Colour samples per pixel (stratified sub-pixel jitter); at least 1.
    pub samples_per_pixel: u32,
    /// Trace shadow rays towards the sun.
    pub shadows: bool,
    /// Shadow rays per colour sample, each towards a random point of the sun disk (soft
    /// shadows); 0 = a single ray to the sun centre (hard shadows).
    pub soft_shadow_samples: u32,
    /// Multiplier on all radiance before the sRGB transfer.
    pub exposure: f32,
    /// Seed of the per-pixel sample pattern (hashed with pixel and sample index; rendering is
    /// deterministic for a given seed).
    pub noise_seed: u32,
}

impl Default for RenderConfig {
    fn default() -> Self {
        Self { samples_per_pixel: 4, shadows: true, soft_shadow_samples: 1, exposure: 1.0, noise_seed: 0 }
    }
}

/// A rendered frame: sRGB colour and planar depth (from the pixel-centre ray), plus object ids.
#[derive(Debug, Clone, PartialEq)]
pub struct SynthFrame {
    /// Colour (sRGB `[0, 1]`, averaged over samples in linear space) and planar depth in metres
    /// (0 where the pixel-centre ray hits nothing).
    pub frame: RgbdFrame,
    /// Id of what the pixel-centre ray hit: [`GROUND_ID`], an object's `id`, or [`SKY_ID`].
    pub object_id: Image<u32>,
}

/// A ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Ray parameter: the hit is at `origin + t * dir` (for camera rays with `dir` = world
    /// direction of `(x, y, 1)` in the camera frame, `t` is the planar depth in metres).
    pub t: f32,
    /// World hit point (m).
    pub point: Vec3,
    /// Unit outward surface normal (world).
    pub normal: Vec3,
    /// [`GROUND_ID`] or the object's id.
    pub object_id: u32,
}

/// One primitive, prepared for intersection.
#[derive(Debug, Clone, Copy)]
struct Prim {
    centre: Vec3,
    object_from_world: Mat3,
    scale: f32,
    /// Squared radius of the bounding sphere about `centre`.
    bound_r2: f32,
    shape: Shape,
    albedo: Vec3,
    material: Material,
    id: u32,
}

/// Uniform 2-D grid over the objects' footprint bounds; each cell lists the primitives whose
/// bounding box overlaps it (CSR layout) and the highest point among them.
#[derive(Debug, Clone)]
struct Grid {
    origin: Vec2,
    cell_m: f32,
    inv_cell: f32,
    nx: i32,
    ny: i32,
    cell_start: Vec<u32>,
    items: Vec<u32>,
    cell_top_z: Vec<f32>,
}

/// The ray tracer of one [`Scene`]; owns its acceleration structure (built once in `new`).
#[derive(Debug, Clone)]
pub struct Renderer {
    prims: Vec<Prim>,
    grid: Grid,
    /// Per cell, the primitives that can block a sun ray (any direction of the sun disk)
    /// starting anywhere in the cell's column of the object slab; `None` for a low sun.
    shadow_grid: Option<Grid>,
    ground_z: f32,
    ground_half: f32,
    top_z: f32,
    sun_dir: Vec3,
    sun_tan_radius: f32,
    /// 64 directions spread uniformly over the sun disk (golden-angle spiral).
    sun_disk: [Vec3; 64],
    /// xy bounds `(min, max)` of each primitive.
    prim_xy_box: Vec<(Vec2, Vec2)>,
    /// `srgb[i]` = sRGB of linear `i / SRGB_LUT_MAX`.
    srgb_lut: Vec<f32>,
    sun_irradiance: f32,
    sky_irradiance: f32,
    ground_bounce_irradiance: f32,
    ground_albedo: Vec3,
    sky_radiance: Vec3,
}

const NO_PRIM: u32 = u32::MAX;
const GRID_CELL_M: f32 = 1.0;

/// Integer hash (lowbias32 by Chris Wellons), for per-pixel sample patterns.
#[inline]
fn hash32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

#[inline]
fn unit_float(h: u32) -> f32 {
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

impl Renderer {
    /// Prepares the primitives and builds the grid (about a millisecond for 882 objects).
    pub fn new(scene: &Scene) -> Self {
        let prims: Vec<Prim> = scene
            .objects
            .iter()
            .map(|o| Prim {
                centre: o.world_from_object.translation,
                object_from_world: o.world_from_object.rotation.transpose(),
                scale: o.scale,
                bound_r2: o.scale
                    * o.scale
                    * match o.shape {
                        Shape::Sphere => 1.0,
                        Shape::Cube => 3.0001,
                        Shape::Cylinder | Shape::Cone => 2.0001,
                    },
                shape: o.shape,
                albedo: Vec3::from_array(o.colour.map(srgb_to_linear)),
                material: o.material,
                id: o.id,
            })
            .collect();
        let boxes: Vec<(Vec3, Vec3)> = scene.objects.iter().map(|o| o.aabb()).collect();
        let grid = Grid::build(&boxes, scene.ground_z_m);
        let top_z = boxes.iter().map(|b| b.1.z).fold(scene.ground_z_m, f32::max) + 1e-3;
        let sun_dir = scene.sun_dir.try_normalize().unwrap_or(Vec3::Z);
        let helper = if sun_dir.x.abs() < 0.9 { Vec3::X } else { Vec3::Y };
        let sun_u = sun_dir.cross(helper).normalize();
        let sun_v = sun_dir.cross(sun_u);
        let sun_tan_radius = scene.sun_angular_radius_rad.max(0.0).tan();
        let shadow_grid =
            shadow_sweep(sun_dir, sun_u, sun_v, sun_tan_radius, top_z - scene.ground_z_m).map(|(lo, hi)| {
                let swept: Vec<(Vec3, Vec3)> = boxes.iter().map(|(a, b)| (*a + lo, *b + hi)).collect();
                Grid::build(&swept, scene.ground_z_m)
            });
        Self {
            prims,
            grid,
            shadow_grid,
            ground_z: scene.ground_z_m,
            ground_half: scene.ground_half_extent_m,
            top_z,
            sun_dir,
            sun_tan_radius,
            sun_disk: std::array::from_fn(|k| {
                let r = ((k as f32 + 0.5) / 64.0).sqrt() * sun_tan_radius;
                let a = k as f32 * 2.399_963;
                (sun_dir + sun_u * (r * a.cos()) + sun_v * (r * a.sin())).normalize()
            }),
            prim_xy_box: boxes.iter().map(|(a, b)| (a.truncate(), b.truncate())).collect(),
            srgb_lut: (0..=SRGB_LUT_MAX).map(|i| linear_to_srgb(i as f32 / SRGB_LUT_MAX as f32)).collect(),
            sun_irradiance: scene.sun_irradiance,
            sky_irradiance: scene.sky_irradiance,
            ground_bounce_irradiance: scene.ground_bounce_irradiance,
            ground_albedo: Vec3::from_array(scene.ground_colour.map(srgb_to_linear)),
            sky_radiance: Vec3::from_array(scene.sky_colour),
        }
    }

    /// Closest hit of the ray `origin + t * dir`, `t > 0` (objects and the ground square), or
    /// `None` (sky). `dir` need not be unit; `t` is in units of `dir`.
    pub fn ray_hit(&self, origin: Vec3, dir: Vec3) -> Option<Hit> {
        let (t, prim) = self.trace(origin, dir, f32::INFINITY, false);
        if prim != NO_PRIM {
            let p = &self.prims[prim as usize];
            let point = origin + dir * t;
            let normal = p.object_from_world.transpose() * local_normal(p, p.object_from_world * (point - p.centre));
            return Some(Hit { t, point, normal, object_id: p.id });
        }
        self.ground_hit(origin, dir).map(|t| Hit { t, point: origin + dir * t, normal: Vec3::Z, object_id: GROUND_ID })
    }

    #[inline]
    fn ground_hit(&self, origin: Vec3, dir: Vec3) -> Option<f32> {
        if dir.z >= 0.0 || origin.z <= self.ground_z {
            return None;
        }
        let t = (self.ground_z - origin.z) / dir.z;
        let p = origin + dir * t;
        (p.x.abs() <= self.ground_half && p.y.abs() <= self.ground_half).then_some(t)
    }

    /// Traverses the grid; returns the closest object hit `(t, prim)` with `t < t_max`, or
    /// `(t_max, NO_PRIM)`. With `any_hit` it stops at the first hit found.
    #[inline]
    fn trace(&self, o: Vec3, d: Vec3, t_max: f32, any_hit: bool) -> (f32, u32) {
        let g = &self.grid;
        let mut best_t = t_max;
        let mut best = NO_PRIM;
        if self.prims.is_empty() {
            return (best_t, best);
        }
        // Clip the ray to the object slab z in [ground, top] and to the grid's xy box.
        let mut t0 = 0.0f32;
        let mut t1 = t_max;
        let inv = d.recip();
        {
            let (ta, tb) = ((self.ground_z - o.z) * inv.z, (self.top_z - o.z) * inv.z);
            if d.z == 0.0 {
                if o.z < self.ground_z || o.z > self.top_z {
                    return (best_t, best);
                }
            } else {
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
            let lo = g.origin;
            let hi = g.origin + Vec2::new(g.nx as f32, g.ny as f32) * g.cell_m;
            for (oa, da, ia, l, h) in [(o.x, d.x, inv.x, lo.x, hi.x), (o.y, d.y, inv.y, lo.y, hi.y)] {
                if da == 0.0 {
                    if oa < l || oa > h {
                        return (best_t, best);
                    }
                } else {
                    let (a, b) = ((l - oa) * ia, (h - oa) * ia);
                    t0 = t0.max(a.min(b));
                    t1 = t1.min(a.max(b));
                }
            }
            if t0 >= t1 {
                return (best_t, best);
            }
        }
        // 2-D DDA over the cells between t0 and t1.
        let p0 = (Vec2::new(o.x, o.y) + Vec2::new(d.x, d.y) * t0 - g.origin) * g.inv_cell;
        let mut ix = fast_floor(p0.x).clamp(0, g.nx - 1);
        let mut iy = fast_floor(p0.y).clamp(0, g.ny - 1);
        let (step_x, step_y) = (if d.x > 0.0 { 1 } else { -1 }, if d.y > 0.0 { 1 } else { -1 });
        let cell_x = |i: i32| g.origin.x + i as f32 * g.cell_m;
        let cell_y = |i: i32| g.origin.y + i as f32 * g.cell_m;
        let mut t_next_x = if d.x == 0.0 { f32::INFINITY } else { (cell_x(ix + i32::from(d.x > 0.0)) - o.x) * inv.x };
        let mut t_next_y = if d.y == 0.0 { f32::INFINITY } else { (cell_y(iy + i32::from(d.y > 0.0)) - o.y) * inv.y };
        let dt_x = (g.cell_m * inv.x).abs();
        let dt_y = (g.cell_m * inv.y).abs();
        let mut t_enter = t0;
        loop {
            let t_exit = t_next_x.min(t_next_y).min(t1);
            let cell = (iy * g.nx + ix) as usize;
            let z_low = (o.z + d.z * t_enter).min(o.z + d.z * t_exit);
            if z_low <= g.cell_top_z[cell] {
                let (s, e) = (g.cell_start[cell] as usize, g.cell_start[cell + 1] as usize);
                for &pi in &g.items[s..e] {
                    let p = &self.prims[pi as usize];
                    let t = intersect(p, o, d, best_t);
                    if t < best_t {
                        best_t = t;
                        best = pi;
                        if any_hit {
                            return (best_t, best);
                        }
                    }
                }
            }
            if best_t <= t_exit || t_exit >= t1 {
                break;
            }
            t_enter = t_exit;
            if t_next_x < t_next_y {
                ix += step_x;
                if ix < 0 || ix >= g.nx {
                    break;
                }
                t_next_x += dt_x;
            } else {
                iy += step_y;
                if iy < 0 || iy >= g.ny {
                    break;
                }
                t_next_y += dt_y;
            }
        }
        (best_t, best)
    }

    /// True when the unit-direction ray from `o` towards the sky is blocked by an object.
    #[inline]
    fn occluded(&self, o: Vec3, d: Vec3) -> bool {
        match &self.shadow_grid {
            Some(g) => match g.cell_of(o) {
                Some(cell) => g
                    .cell_items(cell)
                    .iter()
                    .any(|&pi| intersect(&self.prims[pi as usize], o, d, f32::INFINITY) < f32::INFINITY),
                None => false,
            },
            None => self.trace(o, d, f32::INFINITY, true).1 != NO_PRIM,
        }
    }

    /// Direction to a point of the sun disk; `(a, b)` uniform in `[0, 1)^2`.
    #[inline]
    fn sun_sample(&self, h: u32) -> Vec3 {
        self.sun_disk[(h >> 26) as usize]
    }

    /// Direct + ambient radiance leaving a diffuse point.
    #[inline]
    fn diffuse_radiance(&self, point: Vec3, n: Vec3, albedo: Vec3, cfg: &RenderConfig, h: u32) -> Vec3 {
        let mut sun = 0.0;
        let ndl0 = n.dot(self.sun_dir);
        if ndl0 > -self.sun_tan_radius {
            let rays = cfg.soft_shadow_samples.max(1);
            let mut acc = 0.0;
            for k in 0..rays {
                let l = if cfg.soft_shadow_samples == 0 {
                    self.sun_dir
                } else {
                    self.sun_sample(hash32(h ^ k.wrapping_mul(0x9e37_79b9)))
                };
                let ndl = n.dot(l);
                if ndl > 0.0 && !(cfg.shadows && self.occluded(point + n * 1e-3, l)) {
                    acc += ndl;
                }
            }
            sun = acc / rays as f32;
        }
        let up = 0.5 + 0.5 * n.z;
        albedo * (self.sun_irradiance * sun + self.sky_irradiance * up + self.ground_bounce_irradiance * (1.0 - up))
    }

    /// Radiance along one camera (or reflected) ray; `depth` counts reflections left.
    fn radiance(&self, o: Vec3, d: Vec3, cfg: &RenderConfig, h: u32, depth: u32) -> Vec3 {
        let hit = self.trace(o, d, f32::INFINITY, false);
        self.shade(o, d, hit, cfg, h, depth)
    }

    /// Radiance along a ray whose closest object hit `(t, prim)` is known.
    fn shade(&self, o: Vec3, d: Vec3, (t, prim): (f32, u32), cfg: &RenderConfig, h: u32, depth: u32) -> Vec3 {
        if prim == NO_PRIM {
            return match self.ground_hit(o, d) {
                Some(tg) => self.diffuse_radiance(o + d * tg, Vec3::Z, self.ground_albedo, cfg, h),
                None => self.sky_radiance,
            };
        }
        let p = &self.prims[prim as usize];
        let point = o + d * t;
        let n = p.object_from_world.transpose() * local_normal(p, p.object_from_world * (point - p.centre));
        let diffuse = || self.diffuse_radiance(point, n, p.albedo, cfg, h);
        match p.material {
            Material::Diffuse => diffuse(),
            Material::Glossy | Material::Metal => {
                let dn = d.normalize();
                let r = dn - n * (2.0 * dn.dot(n));
                let reflected = if depth > 0 {
                    self.radiance(point + n * 1e-3, r, cfg, hash32(h ^ 0x5bd1_e995), depth - 1)
                } else {
                    self.sky_radiance
                };
                let highlight = r.dot(self.sun_dir).max(0.0).powi(64) * self.sun_irradiance * 2.0;
                if p.material == Material::Metal {
                    p.albedo * (reflected * 0.9 + Vec3::splat(highlight))
                } else {
                    diffuse() * 0.92 + reflected * 0.08 + Vec3::splat(highlight * 0.3)
                }
            }
        }
    }

    /// Renders `camera` (any intrinsics, any pose): colour averaged over stratified sub-pixel
    /// samples in linear space then converted to sRGB; depth and id from the pixel-centre ray.
    /// Deterministic: the same scene, camera and config give identical bytes.
    pub fn render(&self, camera: &Camera, config: &RenderConfig) -> SynthFrame {
        let k = &camera.intrinsics;
        let (w, h) = (k.width as usize, k.height as usize);
        let rot = camera.world_from_camera.rotation;
        let o = camera.world_from_camera.translation;
        let spp = config.samples_per_pixel.max(1);
        let strata = (spp as f32).sqrt().ceil() as u32;
        let inv_spp = 1.0 / spp as f32;
        let exposure = config.exposure;
        let mut colour = vec![[0.0f32; 3]; w * h];
        let mut depth = vec![0.0f32; w * h];
        let mut ids = vec![SKY_ID; w * h];
        colour
            .par_chunks_mut(w.max(1))
            .zip(depth.par_chunks_mut(w.max(1)))
            .zip(ids.par_chunks_mut(w.max(1)))
            .enumerate()
            .for_each(|(v, ((crow, drow), irow))| {
                // Ray direction at continuous pixel (u, v): base + u * du + v * dv (linear in u, v).
                let du = rot * Vec3::new(1.0 / k.fx, 0.0, 0.0);
                let dv = rot * Vec3::new(0.0, 1.0 / k.fy, 0.0);
                let base = rot * Vec3::new(-k.cx / k.fx, -k.cy / k.fy, 1.0);
                let vf = v as f32;
                let above = o.z > self.top_z;
                let mut cand = [0u32; MAX_CANDIDATES];
                let mut n_cand = None;
                for u in 0..w {
                    let uf = u as f32;
                    let d = base + du * uf + dv * vf;
                    // Candidates of the footprint of the next PIXEL_GROUP pixels (all rays
                    // through those pixel squares, clipped to the object slab), when the camera
                    // is above the slab.
                    if u % PIXEL_GROUP == 0 {
                        n_cand = if above {
                            let span = du * (PIXEL_GROUP.min(w - u) as f32 - 1.0);
                            let (lo, hi) = (d - (du + dv) * 0.5, d + span + (du + dv) * 0.5);
                            let corners = [lo, hi, lo + dv, hi - dv];
                            self.bundle_candidates(o, &corners, &mut cand)
                        } else {
                            None
                        };
                    }
                    let closest = |dir: Vec3| match n_cand {
                        Some(n) => {
                            let mut best = (f32::INFINITY, NO_PRIM);
                            for &pi in &cand[..n] {
                                let t = intersect(&self.prims[pi as usize], o, dir, best.0);
                                if t < best.0 {
                                    best = (t, pi);
                                }
                            }
                            best
                        }
                        None => self.trace(o, dir, f32::INFINITY, false),
                    };
                    let centre_hit = closest(d);
                    if centre_hit.1 != NO_PRIM {
                        drow[u] = centre_hit.0;
                        irow[u] = self.prims[centre_hit.1 as usize].id;
                    } else if let Some(t) = self.ground_hit(o, d) {
                        drow[u] = t;
                        irow[u] = GROUND_ID;
                    }
                    let pixel_hash =
                        hash32(config.noise_seed ^ hash32((v as u32).wrapping_mul(0x0001_0000) ^ u as u32));
                    let mut acc = Vec3::ZERO;
                    for s in 0..spp {
                        let hs = hash32(pixel_hash ^ s.wrapping_mul(0x68e3_1da4));
                        let cell = s % (strata * strata);
                        let (sx, sy) = ((cell % strata) as f32, (cell / strata) as f32);
                        let ju = (sx + unit_float(hs)) / strata as f32 - 0.5;
                        let jv = (sy + unit_float(hash32(hs))) / strata as f32 - 0.5;
                        let ds = d + du * ju + dv * jv;
                        acc += self.shade(o, ds, closest(ds), config, hash32(hs ^ 0x27d4_eb2f), 1);
                    }
                    let c = acc * (inv_spp * exposure);
                    crow[u] = [self.encode_srgb(c.x), self.encode_srgb(c.y), self.encode_srgb(c.z)];
                }
            });
        let (wu, hu) = (k.width, k.height);
        SynthFrame {
            frame: RgbdFrame {
                colour: Image { width: wu, height: hu, data: colour },
                depth_m: Image { width: wu, height: hu, data: depth },
            },
            object_id: Image { width: wu, height: hu, data: ids },
        }
    }

    /// Gathers the primitives of the grid cells that rays between the given corner directions
    /// can visit inside the object slab (camera above the slab). `None` when the bundle does not
    /// descend or has more candidates than fit.
    #[inline]
    fn bundle_candidates(&self, o: Vec3, corners: &[Vec3; 4], out: &mut [u32; MAX_CANDIDATES]) -> Option<usize> {
        let (mut lo, mut hi) = (Vec2::splat(f32::INFINITY), Vec2::splat(f32::NEG_INFINITY));
        for c in corners {
            if c.z >= 0.0 {
                return None;
            }
            let inv = 1.0 / c.z;
            for z in [self.top_z, self.ground_z] {
                let t = (z - o.z) * inv;
                let p = Vec2::new(o.x + c.x * t, o.y + c.y * t);
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        let g = &self.grid;
        let a = (lo - g.origin) * g.inv_cell;
        let b = (hi - g.origin) * g.inv_cell;
        if b.x < 0.0 || b.y < 0.0 || a.x >= g.nx as f32 || a.y >= g.ny as f32 {
            return Some(0);
        }
        let (x0, y0) = (fast_floor(a.x).max(0), fast_floor(a.y).max(0));
        let (x1, y1) = (fast_floor(b.x).min(g.nx - 1), fast_floor(b.y).min(g.ny - 1));
        let mut n = 0;
        for y in y0..=y1 {
            for x in x0..=x1 {
                let cell = (y * g.nx + x) as usize;
                // Cells whose objects are all below the bundle's lowest point cannot be hit,
                // but a descending bundle always reaches the ground: no height skip here.
                for &pi in g.cell_items(cell) {
                    let (bl, bh) = self.prim_xy_box[pi as usize];
                    if bl.x > hi.x || bl.y > hi.y || bh.x < lo.x || bh.y < lo.y {
                        continue;
                    }
                    if !out[..n].contains(&pi) {
                        if n == MAX_CANDIDATES {
                            return None;
                        }
                        out[n] = pi;
                        n += 1;
                    }
                }
            }
        }
        Some(n)
    }

    /// Linear to sRGB through the lookup table (linear interpolation; clamps to `[0, 1]`).
    #[inline]
    fn encode_srgb(&self, c: f32) -> f32 {
        let x = c.clamp(0.0, 1.0) * SRGB_LUT_MAX as f32;
        let i = (x as usize).min(SRGB_LUT_MAX - 1);
        let f = x - i as f32;
        self.srgb_lut[i] * (1.0 - f) + self.srgb_lut[i + 1] * f
    }

    /// Number of primitives.
    pub fn object_count(&self) -> usize {
        self.prims.len()
    }
}

/// Horizontal offsets `(lo, hi)` to add to an object's box so that it covers every start point
/// (in a slab of height `slab_m`) whose ray towards any point of the sun disk can hit the box;
/// `None` when the sun is too low for this to pay off.
fn shadow_sweep(sun_dir: Vec3, sun_u: Vec3, sun_v: Vec3, tan_radius: f32, slab_m: f32) -> Option<(Vec3, Vec3)> {
    let (mut lo, mut hi) = (Vec3::ZERO, Vec3::ZERO);
    // Directions on the boundary of the sun disk, slightly enlarged (a 32-gon inscribed in the
    // circle would miss a sliver).
    let r = tan_radius * 1.01 + 1e-4;
    for k in 0..32 {
        let a = k as f32 * std::f32::consts::TAU / 32.0;
        let l = (sun_dir + sun_u * (r * a.cos()) + sun_v * (r * a.sin())).normalize();
        if l.z < 0.2 {
            return None;
        }
        let disp = Vec3::new(l.x, l.y, 0.0) * (slab_m / l.z);
        let m = Vec3::splat(0.02);
        lo = lo.min(-disp - m);
        hi = hi.max(-disp + m);
    }
    if (hi - lo).max_element() > 12.0 {
        return None;
    }
    Some((lo, hi))
}

const MAX_CANDIDATES: usize = 48;
/// Pixels of a row that share one candidate list.
const PIXEL_GROUP: usize = 4;
const SRGB_LUT_MAX: usize = 4096;

/// `floor` without a libm call (the baseline x86-64 target has no `roundss`).
#[inline]
fn fast_floor(x: f32) -> i32 {
    let i = x as i32;
    i - i32::from(x < i as f32)
}

impl Grid {
    /// The cell containing world point `p` (its x, y), or `None` outside the grid.
    #[inline]
    fn cell_of(&self, p: Vec3) -> Option<usize> {
        let x = (p.x - self.origin.x) * self.inv_cell;
        let y = (p.y - self.origin.y) * self.inv_cell;
        if !(x >= 0.0 && y >= 0.0 && x < self.nx as f32 && y < self.ny as f32) {
            return None;
        }
        Some(y as usize * self.nx as usize + x as usize)
    }

    /// Primitive indices listed in `cell`.
    #[inline]
    fn cell_items(&self, cell: usize) -> &[u32] {
        &self.items[self.cell_start[cell] as usize..self.cell_start[cell + 1] as usize]
    }

    fn build(boxes: &[(Vec3, Vec3)], ground_z: f32) -> Self {
        let cell_m = GRID_CELL_M;
        let (mut lo, mut hi) = (Vec2::splat(f32::INFINITY), Vec2::splat(f32::NEG_INFINITY));
        for (a, b) in boxes {
            lo = lo.min(a.truncate());
            hi = hi.max(b.truncate());
        }
        if boxes.is_empty() {
            lo = Vec2::ZERO;
            hi = Vec2::ONE;
        }
        let origin = lo - Vec2::splat(0.5 * cell_m);
        let nx = (((hi.x - origin.x) / cell_m).ceil() as i32 + 1).max(1);
        let ny = (((hi.y - origin.y) / cell_m).ceil() as i32 + 1).max(1);
        let cells = (nx * ny) as usize;
        let range = |a: Vec3, b: Vec3| {
            let f = |x: f32, o: f32, n: i32| (((x - o) / cell_m).floor() as i32).clamp(0, n - 1);
            (f(a.x, origin.x, nx), f(b.x, origin.x, nx), f(a.y, origin.y, ny), f(b.y, origin.y, ny))
        };
        let mut counts = vec![0u32; cells + 1];
        let mut cell_top_z = vec![ground_z - 1.0; cells];
        for (a, b) in boxes {
            let (x0, x1, y0, y1) = range(*a, *b);
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let c = (y * nx + x) as usize;
                    counts[c + 1] += 1;
                    cell_top_z[c] = cell_top_z[c].max(b.z + 1e-3);
                }
            }
        }
        for c in 0..cells {
            counts[c + 1] += counts[c];
        }
        let mut fill = counts.clone();
        let mut items = vec![0u32; counts[cells] as usize];
        for (i, (a, b)) in boxes.iter().enumerate() {
            let (x0, x1, y0, y1) = range(*a, *b);
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let c = (y * nx + x) as usize;
                    items[fill[c] as usize] = i as u32;
                    fill[c] += 1;
                }
            }
        }
        Self { origin, cell_m, inv_cell: 1.0 / cell_m, nx, ny, cell_start: counts, items, cell_top_z }
    }
}

/// Smallest root `t` in `(T_MIN, t_max)` of the primitive along the world ray, or `t_max` /
/// larger when missed.
#[inline]
fn intersect(p: &Prim, o: Vec3, d: Vec3, t_max: f32) -> f32 {
    const T_MIN: f32 = 1e-5;
    // Bounding-sphere rejection (exact test for spheres is below).
    let oc = o - p.centre;
    let b = oc.dot(d);
    let cc = oc.length_squared() - p.bound_r2;
    if (cc > 0.0 && b > 0.0) || b * b < d.length_squared() * cc {
        return f32::INFINITY;
    }
    if p.shape == Shape::Sphere {
        let a = d.length_squared();
        let sq = (b * b - a * cc).sqrt();
        let t = (-b - sq) / a;
        if t > T_MIN && t < t_max {
            return t;
        }
        let t = (-b + sq) / a;
        return if t > T_MIN && t < t_max { t } else { f32::INFINITY };
    }
    let ol = p.object_from_world * oc;
    let dl = p.object_from_world * d;
    let s = p.scale;
    let miss = f32::INFINITY;
    match p.shape {
        Shape::Sphere => miss, // handled above in world space
        Shape::Cube => {
            let inv = dl.recip();
            let ta = (Vec3::splat(-s) - ol) * inv;
            let tb = (Vec3::splat(s) - ol) * inv;
            let tn = ta.min(tb).max_element();
            let tf = ta.max(tb).min_element();
            if tn > tf {
                return miss;
            }
            if tn > T_MIN && tn < t_max {
                tn
            } else if tf > T_MIN && tf < t_max && tn <= T_MIN {
                tf
            } else {
                miss
            }
        }
        Shape::Cylinder => {
            let mut best = miss;
            // Side.
            let a = dl.x * dl.x + dl.y * dl.y;
            if a > 0.0 {
                let b = ol.x * dl.x + ol.y * dl.y;
                let c = ol.x * ol.x + ol.y * ol.y - s * s;
                let disc = b * b - a * c;
                if disc >= 0.0 {
                    let sq = disc.sqrt();
                    for t in [(-b - sq) / a, (-b + sq) / a] {
                        if t > T_MIN && t < t_max.min(best) && (ol.z + dl.z * t).abs() <= s {
                            best = t;
                            break;
                        }
                    }
                }
            }
            // Caps.
            if dl.z != 0.0 {
                for zc in [-s, s] {
                    let t = (zc - ol.z) / dl.z;
                    if t > T_MIN && t < t_max.min(best) {
                        let x = ol.x + dl.x * t;
                        let y = ol.y + dl.y * t;
                        if x * x + y * y <= s * s {
                            best = t;
                        }
                    }
                }
            }
            best
        }
        Shape::Cone => {
            let mut best = miss;
            // Side: x^2 + y^2 = k^2 (s - z)^2 with k = 1/2, z in [-s, s].
            let k2 = 0.25f32;
            let hz = s - ol.z;
            let a = dl.x * dl.x + dl.y * dl.y - k2 * dl.z * dl.z;
            let b = ol.x * dl.x + ol.y * dl.y + k2 * hz * dl.z;
            let c = ol.x * ol.x + ol.y * ol.y - k2 * hz * hz;
            let disc = b * b - a * c;
            if disc >= 0.0 && a != 0.0 {
                let sq = disc.sqrt();
                let (r0, r1) = ((-b - sq) / a, (-b + sq) / a);
                let (r0, r1) = if r0 < r1 { (r0, r1) } else { (r1, r0) };
                for t in [r0, r1] {
                    if t > T_MIN && t < t_max.min(best) {
                        let z = ol.z + dl.z * t;
                        if z >= -s && z <= s {
                            best = t;
                            break;
                        }
                    }
                }
            }
            // Base cap at z = -s.
            if dl.z != 0.0 {
                let t = (-s - ol.z) / dl.z;
                if t > T_MIN && t < t_max.min(best) {
                    let x = ol.x + dl.x * t;
                    let y = ol.y + dl.y * t;
                    if x * x + y * y <= s * s {
                        best = t;
                    }
                }
            }
            best
        }
    }
}

/// Unit outward normal at a surface point given in the primitive's local frame.
#[inline]
fn local_normal(p: &Prim, q: Vec3) -> Vec3 {
    let s = p.scale;
    match p.shape {
        Shape::Sphere => q.normalize_or(Vec3::Z),
        Shape::Cube => {
            let a = q.abs();
            if a.x >= a.y && a.x >= a.z {
                Vec3::new(q.x.signum(), 0.0, 0.0)
            } else if a.y >= a.z {
                Vec3::new(0.0, q.y.signum(), 0.0)
            } else {
                Vec3::new(0.0, 0.0, q.z.signum())
            }
        }
        Shape::Cylinder => {
            let r = (q.x * q.x + q.y * q.y).sqrt();
            // Distance to the side vs to the caps decides which surface the point is on.
            if (s - q.z.abs()) < (s - r).abs() {
                Vec3::new(0.0, 0.0, q.z.signum())
            } else {
                Vec3::new(q.x, q.y, 0.0).normalize_or(Vec3::X)
            }
        }
        Shape::Cone => {
            let r = (q.x * q.x + q.y * q.y).sqrt();
            let side_dist = ((s - q.z) * 0.5 - r).abs();
            if (q.z + s).abs() < side_dist {
                Vec3::NEG_Z
            } else {
                // Gradient of x^2 + y^2 - (s - z)^2 / 4.
                Vec3::new(q.x, q.y, 0.25 * (s - q.z)).normalize_or(Vec3::Z)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_round_trip() {
        // IEC 61966-2-1 values worked out in f64: ((0.5 + 0.055) / 1.055)^2.4 = 0.2140411405;
        // the knee sits at sRGB 0.04045 = linear 0.04045 / 12.92 = 0.0031308, where the linear
        // and power segments meet (0.0031308050 vs 0.0031308073).
        assert!((srgb_to_linear(0.5) - 0.214_041_14).abs() < 1e-6, "{}", srgb_to_linear(0.5));
        assert!((linear_to_srgb(0.214_041_14) - 0.5).abs() < 1e-6);
        assert!((srgb_to_linear(0.04045) - 0.003_130_805).abs() < 1e-8);
        assert!((linear_to_srgb(0.003_130_8) - 0.040_449_94).abs() < 1e-7);
        assert!((srgb_to_linear(0.04046) - 0.003_131_6).abs() < 1e-7, "power segment just above the knee");
        assert!((srgb_to_linear(0.02) - 0.02 / 12.92).abs() < 1e-9, "linear segment below the knee");
        for (end, srgb) in [(0.0, srgb_to_linear(0.0)), (1.0, srgb_to_linear(1.0)), (0.0, linear_to_srgb(0.0))] {
            assert!((srgb - end).abs() < 1e-6);
        }
        assert!((linear_to_srgb(1.0) - 1.0).abs() < 1e-6);
        for i in 0..=100 {
            let c = i as f32 / 100.0;
            assert!((linear_to_srgb(srgb_to_linear(c)) - c).abs() < 1e-5);
        }
    }
}
