//! Scene generation and rendering invariants.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use glam::{Mat3, Vec2, Vec3};
use rand::{Rng, SeedableRng};
use sgam_core::{Camera, Intrinsics, Rigid3};
use sgam_synth::*;

fn small_camera(res: u32) -> Camera {
    dataset_cameras(DATASET_GRID, res)[27 * DATASET_GRID + 23].camera
}

#[test]
fn same_seed_gives_identical_scene_and_bytes() {
    let config = SceneConfig::default();
    let a = Scene::generate(11, &config);
    let b = Scene::generate(11, &config);
    assert_eq!(a, b);
    let c = Scene::generate(12, &config);
    assert_ne!(a.objects, c.objects);
    // The scene description survives JSON.
    let json = serde_json::to_string(&a).unwrap();
    let back: Scene = serde_json::from_str(&json).unwrap();
    assert_eq!(a, back);

    let cam = small_camera(96);
    let cfg = RenderConfig::default();
    let fa = Renderer::new(&a).render(&cam, &cfg);
    let fb = Renderer::new(&b).render(&cam, &cfg);
    let bits = |f: &SynthFrame| {
        let mut v: Vec<u32> = f.frame.colour.data.iter().flat_map(|c| c.map(f32::to_bits)).collect();
        v.extend(f.frame.depth_m.data.iter().map(|d| d.to_bits()));
        v.extend(f.object_id.data.iter().copied());
        v
    };
    assert_eq!(bits(&fa), bits(&fb));
    let fc = Renderer::new(&c).render(&cam, &cfg);
    assert_ne!(bits(&fa), bits(&fc));
}

/// Independent reference for one object: march along the ray inside its bounding box and bisect
/// on `Object::contains_world`; the entry parameter `t`, or `None` when the ray misses it before
/// `t_max`.
fn marched_hit(obj: &Object, o: Vec3, d: Vec3, t_max: f32) -> Option<f32> {
    let (lo, hi) = obj.aabb();
    // slab test
    let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
    for k in 0..3 {
        let (a, b) = ((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    if t0 > t1 || t0 >= t_max {
        return None;
    }
    let step = 0.002;
    let mut t = t0;
    while t <= t1 {
        if obj.contains_world(o + d * t, 0.0) {
            let (mut a, mut b) = (t - step, t);
            for _ in 0..30 {
                let m = 0.5 * (a + b);
                if obj.contains_world(o + d * m, 0.0) {
                    b = m;
                } else {
                    a = m;
                }
            }
            return Some(b);
        }
        t += step;
    }
    None
}

/// Independent reference: the nearest marched hit over the ground and every object, with its id.
fn marched_depth(scene: &Scene, o: Vec3, d: Vec3) -> (f32, u32) {
    let t_ground = (scene.ground_z_m - o.z) / d.z;
    let mut best = (t_ground, GROUND_ID);
    for obj in &scene.objects {
        if let Some(t) = marched_hit(obj, o, d, best.0) {
            if t < best.0 {
                best = (t, obj.id);
            }
        }
    }
    best
}

#[test]
fn depth_equals_independent_ray_marching_at_random_pixels() {
    let scene = Scene::generate(5, &SceneConfig::default());
    let renderer = Renderer::new(&scene);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    let cams = dataset_cameras(DATASET_GRID, 64);
    let (mut object_pixels, mut id_mismatches) = (0, 0);
    for trial in 0..6 {
        let cam = cams[rng.random_range(0..cams.len())].camera;
        let frame = renderer.render(&cam, &RenderConfig { samples_per_pixel: 1, ..RenderConfig::default() });
        for _ in 0..60 {
            let (u, v) = (rng.random_range(0..64u32), rng.random_range(0..64u32));
            let o = cam.world_from_camera.translation;
            let d = cam.world_from_camera.transform_vector(cam.intrinsics.ray_z1(Vec2::new(u as f32, v as f32)));
            let (t, id) = marched_depth(&scene, o, d);
            let got = *frame.frame.depth_m.at(u, v);
            let got_id = *frame.object_id.at(u, v);
            // Planar depth = ray parameter for a z = 1 camera ray.
            assert!((got - t).abs() < 2e-3, "trial {trial} pixel ({u},{v}): rendered {got} vs marched {t}");
            if got_id != id {
                // Only allowed where two surfaces meet (an object touching the ground or another
                // object): the ray must then also reach the rendered id's surface at that depth.
                id_mismatches += 1;
                let t_other = if got_id == GROUND_ID {
                    Some((scene.ground_z_m - o.z) / d.z)
                } else {
                    let obj = scene.objects.get(got_id.wrapping_sub(1) as usize);
                    assert!(obj.is_some_and(|x| x.id == got_id), "pixel ({u},{v}): id {got_id} names no object");
                    obj.and_then(|x| marched_hit(x, o, d, f32::INFINITY))
                };
                let t_other = t_other.unwrap_or(f32::INFINITY);
                assert!(
                    (t_other - t).abs() < 2e-3,
                    "trial {trial} pixel ({u},{v}): rendered id {got_id} is {t_other} away, marched id {id} at {t}"
                );
            }
            if id != GROUND_ID {
                object_pixels += 1;
            }
        }
    }
    assert!(object_pixels > 40, "too few object pixels tested: {object_pixels}");
    eprintln!("{object_pixels} object pixels, {id_mismatches} id mismatches");
    // Contacts cover a sliver of the image: a handful of the 360 pixels at most (measured: 0).
    assert!(id_mismatches <= 3, "{id_mismatches} of 360 pixels carry another object's id");
}

fn single_object_scene(shape: Shape, rotation: Mat3, centre: Vec3) -> Scene {
    let mut scene = Scene::generate(0, &SceneConfig { object_count: 0, ..SceneConfig::default() });
    scene.objects.push(Object {
        shape,
        scale: 1.0,
        world_from_object: Rigid3::new(rotation, centre),
        colour: [0.8, 0.2, 0.2],
        material: Material::Diffuse,
        id: 1,
    });
    scene
}

#[test]
fn analytic_hits_of_each_primitive() {
    let down = Vec3::NEG_Z;
    let g = GROUND_Z_M;
    // Straight down onto a resting object at its centre: the hit is on top at ground + 2.
    for shape in Shape::ALL {
        let scene = single_object_scene(shape, Mat3::IDENTITY, Vec3::new(0.0, 0.0, g + 1.0));
        let r = Renderer::new(&scene);
        let hit = r.ray_hit(Vec3::new(0.0, 0.0, 0.0), down).unwrap();
        assert_eq!(hit.object_id, 1);
        assert!((hit.point.z - (g + 2.0)).abs() < 1e-4, "{shape:?}: {}", hit.point.z);
        assert!((hit.normal - Vec3::Z).length() < 1e-3, "{shape:?}: {}", hit.normal);
        // Off to the side at 0.5 m: sphere z = sqrt(1 - 0.25), cone z = g + 1 + (1 - 2*0.5).
        let hit = r.ray_hit(Vec3::new(0.5, 0.0, 0.0), down).unwrap();
        let expect = match shape {
            Shape::Sphere => g + 1.0 + 0.75f32.sqrt(),
            Shape::Cone => g + 1.0,
            _ => g + 2.0,
        };
        assert!((hit.point.z - expect).abs() < 1e-4, "{shape:?}: {} vs {expect}", hit.point.z);
        // Missing the object hits the ground.
        let hit = r.ray_hit(Vec3::new(3.0, 0.0, 0.0), down).unwrap();
        assert_eq!(hit.object_id, GROUND_ID);
        assert!((hit.t - 11.695).abs() < 1e-4);
    }
    // Horizontal rays against a cylinder lying along x (axis rotated to y by Rx(90deg)).
    let scene = single_object_scene(
        Shape::Cylinder,
        Mat3::from_rotation_x(std::f32::consts::FRAC_PI_2),
        Vec3::new(0.0, 0.0, g + 1.0),
    );
    let r = Renderer::new(&scene);
    // Rx(90deg) turns the local axis into world -y: the cylinder lies along y.
    let hit = r.ray_hit(Vec3::new(-5.0, 0.5, g + 1.5), Vec3::X).unwrap();
    assert!((hit.t - (5.0 - 0.75f32.sqrt())).abs() < 1e-4, "{}", hit.t);
    let hit = r.ray_hit(Vec3::new(0.3, -5.0, g + 1.2), Vec3::Y).unwrap();
    assert!((hit.t - 4.0).abs() < 1e-4 && (hit.normal - Vec3::NEG_Y).length() < 1e-3, "{hit:?}");
}

#[test]
fn no_interpenetration_over_many_seeds() {
    let configs =
        [SceneConfig::default(), SceneConfig { allow_stacking: true, stack_fraction: 0.5, ..SceneConfig::default() }];
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mut stacked = 0;
    for (ci, config) in configs.iter().enumerate() {
        for seed in 0..8u64 {
            let scene = Scene::generate(seed * 31 + ci as u64, config);
            assert_eq!(scene.objects.len(), 882);
            let boxes: Vec<(Vec3, Vec3)> = scene.objects.iter().map(|o| o.aabb()).collect();
            for (i, a) in scene.objects.iter().enumerate() {
                let (lo, hi) = boxes[i];
                if lo.z > scene.ground_z_m + 1e-3 {
                    stacked += 1;
                }
                // Points inside a (rejection sampling in its box).
                let mut pts = Vec::new();
                while pts.len() < 40 {
                    let p = Vec3::new(
                        rng.random_range(lo.x..hi.x),
                        rng.random_range(lo.y..hi.y),
                        rng.random_range(lo.z..hi.z),
                    );
                    if a.contains_world(p, 0.0) {
                        pts.push(p);
                    }
                }
                for (j, b) in scene.objects.iter().enumerate() {
                    if i == j {
                        continue;
                    }
                    let (blo, bhi) = boxes[j];
                    if blo.cmpgt(hi).any() || bhi.cmplt(lo).any() {
                        continue;
                    }
                    for p in &pts {
                        assert!(
                            !b.contains_world(*p, 1e-3),
                            "seed {seed} config {ci}: object {} intersects {} at {p}",
                            a.id,
                            b.id
                        );
                    }
                }
                assert!((lo.z - scene.ground_z_m) > -1e-4, "object {} below ground", a.id);
            }
        }
    }
    assert!(stacked > 0, "stacking config stacked nothing");
}

#[test]
fn shadows_fall_away_from_the_sun() {
    // A cube on the ground; the sun is towards -y and up, so the ground at +y behind the cube
    // is in shadow and the ground at -y in front of it is lit.
    let scene = single_object_scene(Shape::Cube, Mat3::IDENTITY, Vec3::new(0.0, 0.0, GROUND_Z_M + 1.0));
    let r = Renderer::new(&scene);
    let k = Intrinsics::from_fov_x(64, 64, 0.3);
    // Look at a ground point from above, from the side away from the cube.
    let look = |target: Vec3| {
        let eye = Vec3::new(target.x, target.y + target.y.signum(), 0.0);
        let cam = Camera::new(k, Rigid3::look_at(eye, target, Vec3::Z).unwrap());
        let f = r.render(&cam, &RenderConfig::default());
        f.frame.colour.at(32, 32)[0]
    };
    let g = GROUND_Z_M;
    let shadowed = look(Vec3::new(0.0, 1.6, g));
    let lit = look(Vec3::new(0.0, -1.6, g));
    let far = look(Vec3::new(4.0, 4.0, g));
    assert!(shadowed < 0.8 * lit, "shadow {shadowed} vs lit {lit}");
    assert!((far - lit).abs() < 0.02, "open ground {far} vs lit {lit}");
    let no_shadows = RenderConfig { shadows: false, ..RenderConfig::default() };
    let cam = Camera::new(k, Rigid3::look_at(Vec3::new(0.0, 2.6, 0.0), Vec3::new(0.0, 1.6, g), Vec3::Z).unwrap());
    let f = r.render(&cam, &no_shadows);
    assert!((f.frame.colour.at(32, 32)[0] - lit).abs() < 0.02);
}

/// Ray parameter range `(t0, t1)` where `o + t d` is inside the box, if any (slab test).
fn ray_box(o: Vec3, d: Vec3, (lo, hi): (Vec3, Vec3)) -> Option<(f32, f32)> {
    let (a, b) = ((lo - o) / d, (hi - o) / d);
    let (t0, t1) = (a.min(b).max_element().max(0.0), a.max(b).min_element());
    (t0 <= t1).then_some((t0, t1))
}

#[test]
fn sky_pixels_have_invalid_depth_and_sky_id() {
    let scene = Scene::generate(2, &SceneConfig { object_count: 10, ..SceneConfig::default() });
    let r = Renderer::new(&scene);
    // Looking at the horizon from 11.7 m above the ground: f = 16 / tan 0.5 = 29.3 px, rows
    // v <= 16 look up or level, and rows 17, 18, 19 meet the ground plane at y = 11.695 f /
    // (v - 16) = 342, 171 and 114 m, beyond the ground square (|x|, |y| <= 100 m): rows 0-19
    // are sky, rows 20-31 ground, unless an object is in the way.
    let k = Intrinsics::from_fov_x(32, 32, 1.0);
    let cam = Camera::new(k, Rigid3::look_at(Vec3::ZERO, Vec3::new(0.0, 1.0, 0.0), Vec3::Z).unwrap());
    let f = r.render(&cam, &RenderConfig::default());
    let boxes: Vec<(Vec3, Vec3)> = scene.objects.iter().map(|o| o.aabb()).collect();
    let (mut sky, mut ground, mut near_objects) = (0, 0, 0);
    for v in 0..32 {
        for u in 0..32 {
            let (id, depth) = (*f.object_id.at(u, v), *f.frame.depth_m.at(u, v));
            // every pixel: sky id exactly where the depth is invalid
            assert_eq!(id == SKY_ID, depth == 0.0, "({u}, {v}): id {id}, depth {depth}");
            let d = cam.world_from_camera.rotation * k.ray_z1(Vec2::new(u as f32, v as f32));
            if boxes.iter().any(|b| ray_box(Vec3::ZERO, d, *b).is_some()) {
                near_objects += 1;
                continue; // an object's box is on the ray: it may or may not be hit
            }
            let t = (d.z < 0.0).then(|| GROUND_Z_M / d.z);
            let on_ground =
                t.is_some_and(|t| (d * t).x.abs() <= GROUND_HALF_EXTENT_M && (d * t).y.abs() <= GROUND_HALF_EXTENT_M);
            if on_ground {
                let t = t.unwrap();
                assert_eq!(id, GROUND_ID, "({u}, {v})");
                assert!((depth - t).abs() <= 1e-4 * t, "({u}, {v}): depth {depth}, ground plane at {t}");
                ground += 1;
            } else {
                assert_eq!((id, depth), (SKY_ID, 0.0), "({u}, {v}) should see the sky");
                sky += 1;
            }
        }
    }
    assert_eq!(near_objects, 0, "no object box on any ray of this view: every pixel is checked");
    assert_eq!((sky, ground), (20 * 32, 12 * 32));
    // rows 0-15: every sub-pixel sample looks up, so the colour is the sky's alone, one value
    let first = *f.frame.colour.at(0, 0);
    for v in 0..16 {
        for u in 0..32 {
            assert_eq!(*f.frame.colour.at(u, v), first, "({u}, {v})");
        }
    }
}

#[test]
fn materials_render_deterministically() {
    let config = SceneConfig {
        object_count: 200,
        material_mix: MaterialMix { glossy_fraction: 0.3, metal_fraction: 0.3 },
        ..SceneConfig::default()
    };
    let scene = Scene::generate(4, &config);
    assert!(scene.objects.iter().any(|o| o.material == Material::Metal));
    let r = Renderer::new(&scene);
    let cam = small_camera(48);
    let a = r.render(&cam, &RenderConfig::default());
    let b = r.render(&cam, &RenderConfig::default());
    assert_eq!(a, b);
    assert!(a.frame.colour.data.iter().flatten().all(|c| (0.0..=1.0).contains(c)));
}
