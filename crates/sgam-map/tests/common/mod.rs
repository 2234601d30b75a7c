//! Analytic scenes rendered by ray-primitive intersection (test fixtures).
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use sgam_core::{Camera, Image, Intrinsics, RgbdFrame, Rigid3, Vec2, Vec3};

/// An analytic primitive with a procedural colour.
#[derive(Debug, Clone, Copy)]
pub enum Shape {
    /// Plane `n . p = d`, textured with a smooth pattern.
    Plane {
        normal: Vec3,
        offset: f32,
    },
    Sphere {
        centre: Vec3,
        radius: f32,
        colour: [f32; 3],
    },
    Cuboid {
        min: Vec3,
        max: Vec3,
        colour: [f32; 3],
    },
}

/// Smooth texture of world position (used on planes): values in [0.1, 0.9].
pub fn texture(p: Vec3) -> [f32; 3] {
    [0.5 + 0.4 * (p.x * 2.0).sin(), 0.5 + 0.4 * (p.y * 2.5).cos(), 0.5 + 0.4 * ((p.x + p.y) * 1.5).sin()]
}

impl Shape {
    /// Smallest ray parameter `t > 0` where `origin + t dir` hits the shape.
    pub fn hit(&self, origin: Vec3, dir: Vec3) -> Option<f32> {
        match *self {
            Shape::Plane { normal, offset } => {
                let den = normal.dot(dir);
                if den.abs() < 1e-9 {
                    return None;
                }
                let t = (offset - normal.dot(origin)) / den;
                (t > 0.0).then_some(t)
            }
            Shape::Sphere { centre, radius, .. } => {
                let oc = origin - centre;
                let a = dir.dot(dir);
                let b = oc.dot(dir);
                let c = oc.dot(oc) - radius * radius;
                let disc = b * b - a * c;
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                let t0 = (-b - s) / a;
                let t1 = (-b + s) / a;
                if t0 > 0.0 {
                    Some(t0)
                } else if t1 > 0.0 {
                    Some(t1)
                } else {
                    None
                }
            }
            Shape::Cuboid { min, max, .. } => {
                let inv = dir.recip();
                let ta = (min - origin) * inv;
                let tb = (max - origin) * inv;
                let tmin = ta.min(tb).max_element();
                let tmax = ta.max(tb).min_element();
                if tmax < tmin.max(0.0) {
                    return None;
                }
                if tmin > 0.0 {
                    Some(tmin)
                } else {
                    Some(tmax)
                }
            }
        }
    }

    pub fn colour(&self, p: Vec3) -> [f32; 3] {
        match *self {
            Shape::Plane { .. } => texture(p),
            Shape::Sphere { colour, .. } | Shape::Cuboid { colour, .. } => colour,
        }
    }
}

/// Nearest hit of the scene along a world ray: `(t, colour)`.
pub fn trace(scene: &[Shape], origin: Vec3, dir: Vec3) -> Option<(f32, [f32; 3])> {
    let mut best: Option<(f32, usize)> = None;
    for (i, s) in scene.iter().enumerate() {
        if let Some(t) = s.hit(origin, dir) {
            if best.is_none_or(|(bt, _)| t < bt) {
                best = Some((t, i));
            }
        }
    }
    best.map(|(t, i)| (t, scene[i].colour(origin + dir * t)))
}

/// Renders planar depth and colour of the scene at `camera` (invalid depth = 0 where no hit).
pub fn render_analytic(scene: &[Shape], camera: &Camera) -> RgbdFrame {
    let k = camera.intrinsics;
    let mut frame = RgbdFrame::empty(k.width, k.height);
    let origin = camera.centre_world();
    for v in 0..k.height {
        for u in 0..k.width {
            let dir = camera.world_from_camera.transform_vector(k.ray_z1(Vec2::new(u as f32, v as f32)));
            if let Some((t, c)) = trace(scene, origin, dir) {
                // dir has camera z = 1, so t is the planar depth.
                *frame.depth_m.at_mut(u, v) = t;
                *frame.colour.at_mut(u, v) = c;
            }
        }
    }
    frame
}

pub fn camera(eye: Vec3, target: Vec3, width: u32, height: u32, fx: f32) -> Camera {
    let up = if (target - eye).normalize().cross(Vec3::Z).length() < 1e-3 { Vec3::Y } else { Vec3::Z };
    let k = Intrinsics::try_new(width, height, fx, fx, width as f32 / 2.0, height as f32 / 2.0).unwrap();
    Camera::new(k, Rigid3::look_at(eye, target, up).unwrap())
}

/// `n` directions spread evenly over the unit sphere (Fibonacci lattice).
pub fn fibonacci_directions(n: usize) -> Vec<Vec3> {
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f32;
            Vec3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect()
}

pub fn depth_image_max_abs_diff(a: &Image<f32>, b: &Image<f32>, mask: &[bool]) -> f32 {
    a.data.iter().zip(&b.data).zip(mask).filter(|(_, m)| **m).map(|((x, y), _)| (x - y).abs()).fold(0.0, f32::max)
}
