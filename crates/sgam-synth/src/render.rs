//! The ray tracer: analytic primitives in a uniform 2-D grid over the ground, sun light with soft
//! shadows, sky/ambient term, stratified anti-aliasing, planar depth and object ids.

use glam::{Mat3, Vec2, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sgam_core::{Camera, Image, RgbdFrame};

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
    ground_z: f32,
    ground_half: f32,
    top_z: f32,
    sun_dir: Vec3,
    sun_u: Vec3,
    sun_v: Vec3,
    sun_tan_radius: f32,
    sun_irradiance: f32,
    sky_irradiance: f32,
    ground_albedo: Vec3,
    sky_radiance: Vec3,
}

const NO_PRIM: u32 = u32::MAX;
const GRID_CELL_M: f32 = 1.0;

fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

fn linear_to_srgb(c: f32) -> f32 {
    let c = c.clamp(0.0, 1.0);
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

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
        Self {
            prims,
            grid,
            ground_z: scene.ground_z_m,
            ground_half: scene.ground_half_extent_m,
            top_z,
            sun_dir,
            sun_u,
            sun_v,
            sun_tan_radius: scene.sun_angular_radius_rad.max(0.0).tan(),
            sun_irradiance: scene.sun_irradiance,
            sky_irradiance: scene.sky_irradiance,
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
        let mut ix = (p0.x.floor() as i32).clamp(0, g.nx - 1);
        let mut iy = (p0.y.floor() as i32).clamp(0, g.ny - 1);
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
        self.trace(o, d, f32::INFINITY, true).1 != NO_PRIM
    }

    /// Direction to a point of the sun disk; `(a, b)` uniform in `[0, 1)^2`.
    #[inline]
    fn sun_sample(&self, a: f32, b: f32) -> Vec3 {
        let r = a.sqrt() * self.sun_tan_radius;
        let phi = b * std::f32::consts::TAU;
        let (s, c) = phi.sin_cos();
        (self.sun_dir + self.sun_u * (r * c) + self.sun_v * (r * s)).normalize()
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
                    let hk = hash32(h ^ k.wrapping_mul(0x9e37_79b9));
                    self.sun_sample(unit_float(hk), unit_float(hash32(hk)))
                };
                let ndl = n.dot(l);
                if ndl > 0.0 && !(cfg.shadows && self.occluded(point + n * 1e-3, l)) {
                    acc += ndl;
                }
            }
            sun = acc / rays as f32;
        }
        let sky = 0.5 + 0.5 * n.z;
        albedo * (self.sun_irradiance * sun + self.sky_irradiance * sky)
    }

    /// Radiance along one camera (or reflected) ray; `depth` counts reflections left.
    fn radiance(&self, o: Vec3, d: Vec3, cfg: &RenderConfig, h: u32, depth: u32) -> Vec3 {
        let (t, prim) = self.trace(o, d, f32::INFINITY, false);
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
                for u in 0..w {
                    let uf = u as f32;
                    let d = base + du * uf + dv * vf;
                    if let Some(hit) = self.ray_hit(o, d) {
                        drow[u] = hit.t;
                        irow[u] = hit.object_id;
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
                        acc += self.radiance(o, ds, config, hash32(hs ^ 0x27d4_eb2f), 1);
                    }
                    let c = acc * (inv_spp * exposure);
                    crow[u] = [linear_to_srgb(c.x), linear_to_srgb(c.y), linear_to_srgb(c.z)];
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

    /// Number of primitives.
    pub fn object_count(&self) -> usize {
        self.prims.len()
    }
}

impl Grid {
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
    let ol = p.object_from_world * (o - p.centre);
    let dl = p.object_from_world * d;
    let s = p.scale;
    let miss = f32::INFINITY;
    match p.shape {
        Shape::Sphere => {
            let a = dl.length_squared();
            let b = ol.dot(dl);
            let c = ol.length_squared() - s * s;
            let disc = b * b - a * c;
            if disc < 0.0 {
                return miss;
            }
            let sq = disc.sqrt();
            let t = (-b - sq) / a;
            if t > T_MIN && t < t_max {
                return t;
            }
            let t = (-b + sq) / a;
            if t > T_MIN && t < t_max {
                t
            } else {
                miss
            }
        }
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
        for i in 0..=100 {
            let c = i as f32 / 100.0;
            assert!((linear_to_srgb(srgb_to_linear(c)) - c).abs() < 1e-5);
        }
    }
}
