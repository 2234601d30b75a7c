//! The scene description and its deterministic generator (object placement without a physics
//! engine: stable resting poses, overlap resolution by rejection around the spawn point).

use glam::{Mat3, Vec2, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sgam_core::{linear_to_srgb, Rigid3};

use crate::{GROUND_HALF_EXTENT_M, GROUND_Z_M, SUN_EULER_X_RAD};

/// The four CLEVR primitive shapes. In the object's local frame each fits in `[-s, s]^3` (`s` =
/// scale, metres) with its axis along local `+z`: cone (base radius `s` at `z = -s`, apex at
/// `z = +s`), cube (edge `2s`), cylinder (radius `s`, `z` in `[-s, s]`), sphere (radius `s`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum Shape {
    /// Cone of base radius 1 and height 2 (at scale 1).
    Cone,
    /// Cube of edge 2 (at scale 1).
    Cube,
    /// Cylinder of radius 1 and height 2 (at scale 1).
    Cylinder,
    /// Sphere of radius 1 (at scale 1).
    Sphere,
}

impl Shape {
    /// All shapes, in a fixed order.
    pub const ALL: [Shape; 4] = [Shape::Cone, Shape::Cube, Shape::Cylinder, Shape::Sphere];

    /// Lower-case name as used in scene descriptions (`"cone"`, `"cube"`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Shape::Cone => "cone",
            Shape::Cube => "cube",
            Shape::Cylinder => "cylinder",
            Shape::Sphere => "sphere",
        }
    }

    /// True when a point given in the object's local frame (metres, unscaled local axes) lies
    /// inside the shape at `scale`, shrunk by `margin_m` (positive margin = strictly inside).
    pub fn contains_local(self, scale: f32, p_local: Vec3, margin_m: f32) -> bool {
        let s = scale - margin_m;
        if s <= 0.0 {
            return false;
        }
        match self {
            Shape::Sphere => p_local.length() <= s,
            Shape::Cube => p_local.abs().max_element() <= s,
            Shape::Cylinder => p_local.truncate().length() <= s && p_local.z.abs() <= s,
            Shape::Cone => {
                // Cone side distance: the side makes angle atan(1/2) with the axis.
                let r = p_local.truncate().length();
                let side = ((scale - p_local.z) * 0.5 - r) * (2.0 / 5.0f32.sqrt());
                p_local.z.abs() <= s && side >= margin_m
            }
        }
    }
}

/// Surface material of an object.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub enum Material {
    /// Lambertian (the paper's CLEVR-Infinite uses only this).
    #[default]
    Diffuse,
    /// Diffuse plus a weak mirror reflection and a sun highlight ("rubber/plastic").
    Glossy,
    /// Mirror reflection tinted by the object's colour plus a sun highlight.
    Metal,
}

/// Fractions of non-diffuse materials; the rest is diffuse. Default: all diffuse (the paper).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct MaterialMix {
    /// Fraction of glossy objects, `[0, 1]`.
    pub glossy_fraction: f32,
    /// Fraction of metal objects, `[0, 1]`.
    pub metal_fraction: f32,
}

/// Parameters of the scene generator. `Default` is the paper's CLEVR-Infinite.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneConfig {
    /// Number of objects to place (paper: 882 = 2 layers of a 21 x 21 spawn grid). Objects that
    /// find no free spot after many tries are dropped (never happens at the default density).
    pub object_count: usize,
    /// Shapes drawn uniformly; empty means all four.
    pub shapes: Vec<Shape>,
    /// Scales drawn uniformly (paper: 1.0 and 0.7); empty means `[1.0]`.
    pub scales: Vec<f32>,
    /// Material fractions.
    pub material_mix: MaterialMix,
    /// Allow objects to rest on the flat top of a cube or an upright cylinder.
    pub allow_stacking: bool,
    /// Fraction of second-layer objects that try to stack when `allow_stacking` is on.
    pub stack_fraction: f32,
    /// Probability that a cone or cylinder rests upright (else it lies on its side).
    pub upright_fraction: f32,
    /// Radius (m) of the random drop offset around the spawn point, per spawn layer (the last
    /// value is reused for further layers).
    pub spawn_jitter_m: Vec<f32>,
    /// Height of the ground plane (m, world z); the camera plane is `z = 0`.
    pub ground_z_m: f32,
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            object_count: 882,
            shapes: Shape::ALL.to_vec(),
            scales: vec![1.0, 0.7],
            material_mix: MaterialMix::default(),
            allow_stacking: false,
            stack_fraction: 0.2,
            upright_fraction: 0.5,
            spawn_jitter_m: vec![1.0, 2.0],
            ground_z_m: GROUND_Z_M,
        }
    }
}

/// One object of the scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Object {
    /// Primitive shape.
    pub shape: Shape,
    /// Uniform scale (1.0 or 0.7 in the paper): the shape spans `[-scale, scale]^3` locally.
    pub scale: f32,
    /// Pose of the object's local frame (origin at the shape's bounding-box centre, local `+z` =
    /// the shape's axis, cone apex at `+z`) in the world (+z up, metres).
    pub world_from_object: Rigid3,
    /// Base colour, sRGB `[0, 1]` (converted to linear albedo for shading).
    pub colour: [f32; 3],
    /// Surface material.
    pub material: Material,
    /// Object id, `1..=objects.len()` (0 is the ground, `u32::MAX` the sky in id images).
    pub id: u32,
}

impl Object {
    /// The shape's axis (local `+z`) in world coordinates.
    pub fn axis_world(&self) -> Vec3 {
        self.world_from_object.rotation.z_axis
    }

    /// Support function: `max over points p of the object of dir . (p - centre)` for a world
    /// direction `dir` (not necessarily unit; the result scales with `|dir|`).
    pub fn support(&self, dir: Vec3) -> f32 {
        let s = self.scale;
        let r = &self.world_from_object.rotation;
        match self.shape {
            Shape::Sphere => s * dir.length(),
            Shape::Cube => s * (r.x_axis.dot(dir).abs() + r.y_axis.dot(dir).abs() + r.z_axis.dot(dir).abs()),
            Shape::Cylinder => {
                let ad = r.z_axis.dot(dir);
                s * ad.abs() + s * (dir.length_squared() - ad * ad).max(0.0).sqrt()
            }
            Shape::Cone => {
                let ad = r.z_axis.dot(dir);
                (s * ad).max(-s * ad + s * (dir.length_squared() - ad * ad).max(0.0).sqrt())
            }
        }
    }

    /// World axis-aligned bounding box `(min, max)`, metres.
    pub fn aabb(&self) -> (Vec3, Vec3) {
        let c = self.world_from_object.translation;
        let hi = Vec3::new(self.support(Vec3::X), self.support(Vec3::Y), self.support(Vec3::Z));
        let lo = Vec3::new(self.support(Vec3::NEG_X), self.support(Vec3::NEG_Y), self.support(Vec3::NEG_Z));
        (c - lo, c + hi)
    }

    /// True when a world point lies inside the object, at least `margin_m` from its surface.
    pub fn contains_world(&self, p_world: Vec3, margin_m: f32) -> bool {
        let p_local = self.world_from_object.inverse().transform_point(p_world);
        self.shape.contains_local(self.scale, p_local, margin_m)
    }

    /// Volume in m^3.
    pub fn volume_m3(&self) -> f32 {
        let s3 = self.scale.powi(3);
        match self.shape {
            Shape::Sphere => 4.0 / 3.0 * std::f32::consts::PI * s3,
            Shape::Cube => 8.0 * s3,
            Shape::Cylinder => 2.0 * std::f32::consts::PI * s3,
            Shape::Cone => 2.0 / 3.0 * std::f32::consts::PI * s3,
        }
    }
}

/// A complete CLEVR-Infinite scene: ground, objects and lighting. World frame: +z up, camera
/// plane at `z = 0`, ground at `z = ground_z_m`; all lengths in metres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    /// The seed it was generated from.
    pub seed: u64,
    /// Ground plane height (world z, m).
    pub ground_z_m: f32,
    /// The ground is the square `|x|, |y| <= ground_half_extent_m` (m).
    pub ground_half_extent_m: f32,
    /// Ground colour, sRGB `[0, 1]` (white diffuse).
    pub ground_colour: [f32; 3],
    /// The objects, `objects[k].id == k + 1`.
    pub objects: Vec<Object>,
    /// Unit world direction from the scene towards the sun (light travels along `-sun_dir`).
    pub sun_dir: Vec3,
    /// Angular radius of the sun disk (rad), for soft shadows.
    pub sun_angular_radius_rad: f32,
    /// Sun irradiance on a surface facing the sun (linear units; 1 = white at exposure 1).
    pub sun_irradiance: f32,
    /// Sky (ambient) irradiance on an upward-facing surface (linear units).
    pub sky_irradiance: f32,
    /// Light bounced off the (white) ground onto a downward-facing surface (linear units); it
    /// stands in for Cycles' global illumination on the objects' lower sides.
    pub ground_bounce_irradiance: f32,
    /// Radiance seen in rays that hit nothing, linear RGB.
    pub sky_colour: [f32; 3],
}

/// The sun direction of the paper's Blender scene: the light's `-z` axis rotated by
/// `Rx(SUN_EULER_X_RAD)` is the direction light travels; returns the opposite (towards the sun).
pub fn paper_sun_dir() -> Vec3 {
    let travel = Mat3::from_rotation_x(SUN_EULER_X_RAD) * Vec3::NEG_Z;
    -travel
}

/// A 2-D footprint (projection on the ground plane) used for overlap tests; conservative.
#[derive(Debug, Clone, Copy)]
enum Footprint {
    Disk { centre: Vec2, radius: f32 },
    Rect { centre: Vec2, u: Vec2, half: Vec2 },
}

impl Footprint {
    fn bounding_radius(&self) -> f32 {
        match *self {
            Footprint::Disk { radius, .. } => radius,
            Footprint::Rect { half, .. } => half.length(),
        }
    }

    fn centre(&self) -> Vec2 {
        match *self {
            Footprint::Disk { centre, .. } | Footprint::Rect { centre, .. } => centre,
        }
    }

    /// True when the interiors overlap (touching is allowed).
    fn overlaps(&self, other: &Footprint) -> bool {
        match (*self, *other) {
            (Footprint::Disk { centre: a, radius: ra }, Footprint::Disk { centre: b, radius: rb }) => {
                (a - b).length_squared() < (ra + rb) * (ra + rb)
            }
            (Footprint::Disk { centre, radius }, Footprint::Rect { centre: rc, u, half })
            | (Footprint::Rect { centre: rc, u, half }, Footprint::Disk { centre, radius }) => {
                let w = u.perp();
                let d = centre - rc;
                let local = Vec2::new(d.dot(u), d.dot(w));
                let clamped = local.clamp(-half, half);
                (local - clamped).length_squared() < radius * radius
            }
            (Footprint::Rect { centre: ca, u: ua, half: ha }, Footprint::Rect { centre: cb, u: ub, half: hb }) => {
                let (wa, wb) = (ua.perp(), ub.perp());
                let d = cb - ca;
                for n in [ua, wa, ub, wb] {
                    let ra = ha.x * ua.dot(n).abs() + ha.y * wa.dot(n).abs();
                    let rb = hb.x * ub.dot(n).abs() + hb.y * wb.dot(n).abs();
                    if d.dot(n).abs() >= ra + rb {
                        return false;
                    }
                }
                true
            }
        }
    }
}

fn footprint(obj: &Object) -> Footprint {
    let c = obj.world_from_object.translation.truncate();
    let axis = obj.axis_world();
    let round_upright = matches!(obj.shape, Shape::Sphere)
        || (matches!(obj.shape, Shape::Cylinder | Shape::Cone) && axis.z.abs() > 0.999);
    if round_upright {
        return Footprint::Disk { centre: c, radius: obj.scale };
    }
    // Orientation of the rectangle: the cube's local x, or the lying shape's horizontal axis.
    let along = if obj.shape == Shape::Cube { obj.world_from_object.rotation.x_axis } else { axis };
    let u = along.truncate().try_normalize().unwrap_or(Vec2::X);
    let w = u.perp();
    let (u3, w3) = (u.extend(0.0), w.extend(0.0));
    let (hu, lu) = (obj.support(u3), obj.support(-u3));
    let (hw, lw) = (obj.support(w3), obj.support(-w3));
    let centre = c + u * 0.5 * (hu - lu) + w * 0.5 * (hw - lw);
    Footprint::Rect { centre, u, half: Vec2::new(0.5 * (hu + lu), 0.5 * (hw + lw)) }
}

/// A placed object's footprint and vertical extent.
#[derive(Debug, Clone, Copy)]
struct Placed {
    footprint: Footprint,
    z_min: f32,
    z_max: f32,
    /// `Some(scale)` when the top is flat and horizontal (face-down cube, upright cylinder).
    flat_top: bool,
}

/// Uniform 2-D bucket grid over the ground for placement queries.
struct Buckets {
    cell_m: f32,
    n: i32,
    half_m: f32,
    cells: Vec<Vec<u32>>,
}

impl Buckets {
    fn new(half_m: f32, cell_m: f32) -> Self {
        let n = ((2.0 * half_m) / cell_m).ceil() as i32;
        Self { cell_m, n, half_m, cells: vec![Vec::new(); (n * n) as usize] }
    }

    fn range(&self, centre: Vec2, radius: f32) -> (i32, i32, i32, i32) {
        let f = |x: f32| (((x + self.half_m) / self.cell_m).floor() as i32).clamp(0, self.n - 1);
        (f(centre.x - radius), f(centre.x + radius), f(centre.y - radius), f(centre.y + radius))
    }

    fn insert(&mut self, centre: Vec2, radius: f32, index: u32) {
        let (x0, x1, y0, y1) = self.range(centre, radius);
        for y in y0..=y1 {
            for x in x0..=x1 {
                self.cells[(y * self.n + x) as usize].push(index);
            }
        }
    }

    fn any(&self, centre: Vec2, radius: f32, mut f: impl FnMut(u32) -> bool) -> bool {
        let (x0, x1, y0, y1) = self.range(centre, radius);
        for y in y0..=y1 {
            for x in x0..=x1 {
                if self.cells[(y * self.n + x) as usize].iter().any(|&i| f(i)) {
                    return true;
                }
            }
        }
        false
    }
}

/// Spawn grid of the paper: 21 x 21 points, x = -38, -34, ..., 42 and y = -42, -38, ..., 38.
pub const SPAWN_GRID: usize = 21;
/// First spawn x (m); spawn points are 4 m apart.
pub const SPAWN_X0_M: f32 = -38.0;
/// First spawn y (m).
pub const SPAWN_Y0_M: f32 = -42.0;
/// Spawn spacing (m).
pub const SPAWN_SPACING_M: f32 = 4.0;

const MAX_ATTEMPTS: usize = 4000;

impl Scene {
    /// Generates the scene of `seed` (deterministic: same seed and config give the same scene).
    ///
    /// Objects are dropped layer by layer over the 21 x 21 spawn grid; each takes a stable
    /// resting pose (cubes on a face, spheres, cones and cylinders upright or on their side) with
    /// a random yaw, lands at a random offset around its spawn point, and is moved to another
    /// random spot (growing radius) while its ground footprint overlaps a placed object's
    /// footprint at overlapping heights. Footprints are exact for disks and cubes and
    /// conservative for lying shapes, so objects may touch but never interpenetrate.
    pub fn generate(seed: u64, config: &SceneConfig) -> Scene {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let shapes = if config.shapes.is_empty() { Shape::ALL.to_vec() } else { config.shapes.clone() };
        let scales: Vec<f32> = config.scales.iter().copied().filter(|s| s.is_finite() && *s > 0.0).collect();
        let scales = if scales.is_empty() { vec![1.0] } else { scales };
        let jitters = if config.spawn_jitter_m.is_empty() { vec![1.0] } else { config.spawn_jitter_m.clone() };
        let half_m = GROUND_HALF_EXTENT_M;
        let keep_in_m = half_m - 3.0;
        let mut buckets = Buckets::new(half_m, 2.0);
        let mut objects: Vec<Object> = Vec::with_capacity(config.object_count);
        let mut placed: Vec<Placed> = Vec::with_capacity(config.object_count);
        let per_layer = SPAWN_GRID * SPAWN_GRID;

        for n in 0..config.object_count {
            let layer = n / per_layer;
            let cell = n % per_layer;
            let spawn = Vec2::new(
                SPAWN_X0_M + SPAWN_SPACING_M * (cell % SPAWN_GRID) as f32,
                SPAWN_Y0_M + SPAWN_SPACING_M * (cell / SPAWN_GRID) as f32,
            );
            let jitter_m = jitters[layer.min(jitters.len() - 1)].max(0.0);
            let shape = shapes[rng.random_range(0..shapes.len())];
            let scale = scales[rng.random_range(0..scales.len())];
            // Blender-style random base colour: uniform in linear RGB, stored as sRGB.
            let colour = [rng.random::<f32>(), rng.random::<f32>(), rng.random::<f32>()].map(linear_to_srgb);
            let m: f32 = rng.random();
            let material = if m < config.material_mix.metal_fraction {
                Material::Metal
            } else if m < config.material_mix.metal_fraction + config.material_mix.glossy_fraction {
                Material::Glossy
            } else {
                Material::Diffuse
            };
            let upright = rng.random::<f32>() < config.upright_fraction;
            let yaw = rng.random_range(0.0..std::f32::consts::TAU);
            let tilt = match shape {
                Shape::Cube | Shape::Sphere => Mat3::IDENTITY,
                _ if upright => Mat3::IDENTITY,
                Shape::Cylinder => Mat3::from_rotation_x(std::f32::consts::FRAC_PI_2),
                // A cone on its side rests on a generatrix: axis pi/2 + atan(1/2) from vertical.
                Shape::Cone => Mat3::from_rotation_y(std::f32::consts::FRAC_PI_2 + 0.5f32.atan()),
            };
            let rotation = Mat3::from_rotation_z(yaw) * tilt;
            let mut obj = Object {
                shape,
                scale,
                world_from_object: Rigid3::new(rotation, Vec3::ZERO),
                colour,
                material,
                id: objects.len() as u32 + 1,
            };
            let rest_offset_m = obj.support(Vec3::NEG_Z);
            let height_m = rest_offset_m + obj.support(Vec3::Z);
            let stackable_shape = matches!(shape, Shape::Cube | Shape::Sphere)
                || (matches!(shape, Shape::Cylinder | Shape::Cone) && upright);
            let try_stack =
                config.allow_stacking && layer > 0 && stackable_shape && rng.random::<f32>() < config.stack_fraction;

            let mut accepted = None;
            for attempt in 0..MAX_ATTEMPTS {
                let mut base_z = config.ground_z_m;
                let radius = jitter_m + 0.02 * attempt as f32;
                let offset = random_in_disk(&mut rng) * radius;
                let mut xy = spawn + offset;
                if try_stack && attempt < 20 {
                    // Find a flat-topped supporter near the drop point, at least as large.
                    let mut best: Option<usize> = None;
                    buckets.any(xy, 2.0, |i| {
                        let p = &placed[i as usize];
                        let o = &objects[i as usize];
                        if p.flat_top && o.scale >= scale && (p.footprint.centre() - xy).length() < 2.0 {
                            best = Some(i as usize);
                            return true;
                        }
                        false
                    });
                    if let Some(i) = best {
                        let support = &objects[i];
                        let c = support.world_from_object.translation.truncate();
                        xy = c + random_in_disk(&mut rng) * (0.3 * support.scale);
                        base_z = placed[i].z_max;
                    }
                }
                if xy.abs().max_element() > keep_in_m {
                    continue;
                }
                obj.world_from_object.translation = xy.extend(base_z + rest_offset_m);
                let fp = footprint(&obj);
                let (z_min, z_max) = (base_z, base_z + height_m);
                let reach = fp.bounding_radius() + 3.0;
                let collides = buckets.any(fp.centre(), reach, |i| {
                    let p = &placed[i as usize];
                    z_min < p.z_max && p.z_min < z_max && p.footprint.overlaps(&fp)
                });
                if !collides {
                    let flat_top = matches!(shape, Shape::Cube) || (shape == Shape::Cylinder && upright);
                    accepted = Some(Placed { footprint: fp, z_min, z_max, flat_top });
                    break;
                }
            }
            if let Some(p) = accepted {
                let index = placed.len() as u32;
                buckets.insert(p.footprint.centre(), p.footprint.bounding_radius(), index);
                placed.push(p);
                objects.push(obj);
            }
        }

        Scene {
            seed,
            ground_z_m: config.ground_z_m,
            ground_half_extent_m: half_m,
            ground_colour: [1.0, 1.0, 1.0],
            objects,
            sun_dir: paper_sun_dir(),
            sun_angular_radius_rad: crate::SUN_ANGULAR_RADIUS_RAD,
            sun_irradiance: 0.47,
            sky_irradiance: 0.08,
            ground_bounce_irradiance: 0.3,
            sky_colour: [0.05, 0.05, 0.05],
        }
    }

    /// Highest point of any object (world z, m); the ground height when there are none.
    pub fn top_z_m(&self) -> f32 {
        self.objects.iter().map(|o| o.aabb().1.z).fold(self.ground_z_m, f32::max)
    }
}

fn random_in_disk(rng: &mut impl Rng) -> Vec2 {
    let r = rng.random::<f32>().sqrt();
    let a = rng.random_range(0.0..std::f32::consts::TAU);
    Vec2::new(a.cos(), a.sin()) * r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resting_objects_touch_the_ground_or_a_support() {
        // Without stacking every object stands on the ground.
        let scene = Scene::generate(3, &SceneConfig::default());
        assert_eq!(scene.objects.len(), 882);
        for (k, o) in scene.objects.iter().enumerate() {
            assert_eq!(o.id as usize, k + 1);
            let (lo, _) = o.aabb();
            assert!((lo.z - scene.ground_z_m).abs() < 1e-4, "object {k} floats: {}", lo.z);
        }
        // With stacking, an object off the ground rests on another: the point 1 mm below its
        // lowest point (every stackable shape's lowest point is under its centre) lies inside a
        // supporter whose top is at the object's bottom.
        let config = SceneConfig { allow_stacking: true, stack_fraction: 1.0, ..SceneConfig::default() };
        let mut stacked = 0;
        for seed in [3, 4] {
            let scene = Scene::generate(seed, &config);
            for o in &scene.objects {
                let (lo, _) = o.aabb();
                if (lo.z - scene.ground_z_m).abs() < 1e-4 {
                    continue;
                }
                stacked += 1;
                let below = o.world_from_object.translation.truncate().extend(lo.z - 1e-3);
                let supporter = scene.objects.iter().find(|s| s.id != o.id && s.contains_world(below, 0.0));
                let Some(s) = supporter else { panic!("seed {seed}: object {} floats at z = {}", o.id, lo.z) };
                let top = s.aabb().1.z;
                assert!(
                    (top - lo.z).abs() < 1e-4,
                    "seed {seed}: object {} at {} on {} topped at {top}",
                    o.id,
                    lo.z,
                    s.id
                );
            }
        }
        eprintln!("{stacked} stacked objects over two scenes");
        assert!(stacked > 20, "the stacking config stacked only {stacked} objects");
    }

    #[test]
    fn cone_on_its_side_rests_on_a_generatrix() {
        let rotation = Mat3::from_rotation_y(std::f32::consts::FRAC_PI_2 + 0.5f32.atan());
        let o = Object {
            shape: Shape::Cone,
            scale: 1.0,
            world_from_object: Rigid3::new(rotation, Vec3::ZERO),
            colour: [1.0; 3],
            material: Material::Diffuse,
            id: 1,
        };
        let low = -o.support(Vec3::NEG_Z);
        let apex = rotation * Vec3::Z;
        let rim = rotation * Vec3::new(1.0, 0.0, -1.0);
        // Both the apex and the lowest base-rim point touch the ground: the line between lies on it.
        assert!((apex.z - low).abs() < 1e-5 && (rim.z - low).abs() < 1e-5, "{apex} {rim} {low}");
    }

    #[test]
    fn footprint_overlap_cases() {
        let d = |x: f32, r: f32| Footprint::Disk { centre: Vec2::new(x, 0.0), radius: r };
        let r = |x: f32, a: f32| Footprint::Rect {
            centre: Vec2::new(x, 0.0),
            u: Vec2::new(a.cos(), a.sin()),
            half: Vec2::ONE,
        };
        assert!(d(0.0, 1.0).overlaps(&d(1.9, 1.0)));
        assert!(!d(0.0, 1.0).overlaps(&d(2.0, 1.0)));
        assert!(r(0.0, 0.0).overlaps(&r(1.9, 0.0)));
        assert!(!r(0.0, 0.0).overlaps(&r(2.01, 0.0)));
        assert!(r(0.0, 0.0).overlaps(&r(2.3, 0.785)));
        assert!(!r(0.0, 0.0).overlaps(&r(2.45, 0.785)));
        assert!(d(0.0, 1.0).overlaps(&r(1.9, 0.0)));
        assert!(!d(0.0, 1.0).overlaps(&r(2.0, 0.0)));
    }
}
