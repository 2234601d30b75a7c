//! A plain scalar reference integrator, written from the documented update rule, as the oracle of
//! the SIMD update in `TsdfMap::integrate`: every voxel of every block the map allocated must
//! hold what the scalar loop computes, and every voxel the scalar loop puts inside the truncation
//! band must lie in an allocated block.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::HashSet;

use glam::{IVec3, Vec3};
use sgam_core::{Camera, Image, Intrinsics, RgbdFrame, Rigid3};
use sgam_map::{TsdfConfig, TsdfMap};

const W: u32 = 64;
const H: u32 = 48;

fn intrinsics() -> Intrinsics {
    Intrinsics { width: W, height: H, fx: 60.0, fy: 60.0, cx: 32.0, cy: 24.0 }
}

/// Planar depth and colour of a tilted plane `z = 2 + 0.3 x + 0.1 y` (world) seen from a camera
/// at `t` looking along +z, with a few invalid or out-of-range readings.
fn frame(t: Vec3) -> RgbdFrame {
    let k = intrinsics();
    let mut f = RgbdFrame { colour: Image::filled(W, H, [0.0f32; 3]), depth_m: Image::filled(W, H, 0.0f32) };
    for v in 0..H {
        for u in 0..W {
            let (dx, dy) = ((u as f32 - k.cx) / k.fx, (v as f32 - k.cy) / k.fy);
            let s = (2.0 + 0.3 * t.x + 0.1 * t.y - t.z) / (1.0 - 0.3 * dx - 0.1 * dy);
            let i = (v * W + u) as usize;
            f.depth_m.data[i] = match (u * 7 + v * 13) % 97 {
                0 => 0.0,
                1 => f32::NAN,
                2 => 50.0, // beyond depth_max
                _ => s,
            };
            f.colour.data[i] = [u as f32 / W as f32, v as f32 / H as f32, (u + v) as f32 / (W + H) as f32];
        }
    }
    f
}

/// A voxel of the reference integrator; starts unobserved (`Voxel::EMPTY`: tsdf 1, weight 0).
#[derive(Clone, Copy)]
struct Ref {
    tsdf: f32,
    weight: f32,
    colour: [f32; 3],
}

impl Default for Ref {
    fn default() -> Self {
        let e = sgam_map::Voxel::EMPTY;
        Self { tsdf: e.tsdf, weight: e.weight, colour: e.colour }
    }
}

/// What one frame does to the voxel at `centre` by the documented rule: project to the nearest
/// pixel; `sdf = d - z`; take the reading when `sdf >= -trunc` and `d` is usable; running
/// average of `min(1, sdf / trunc)` and colour with the weight clamped to `cap - 1`.
/// Returns `None` when the projection lies within `1e-3` px of a pixel boundary (where the SIMD
/// path's rounding may pick the neighbour) or the reading within `1e-4` m of the band's edge.
fn reference_update(r: &mut Ref, centre: Vec3, camera: &Camera, f: &RgbdFrame, cfg: &TsdfConfig) -> Option<()> {
    let p = camera.world_from_camera.inverse().transform_point(centre);
    if p.z <= 1e-6 {
        return Some(());
    }
    let k = camera.intrinsics;
    let (u, v) = (k.fx * p.x / p.z + k.cx + 0.5, k.fy * p.y / p.z + k.cy + 0.5);
    let near_edge = |x: f32| (x - x.round()).abs() < 1e-3;
    if near_edge(u) || near_edge(v) {
        return None;
    }
    if u < 0.0 || v < 0.0 || u >= W as f32 || v >= H as f32 {
        return Some(());
    }
    let d = f.depth_m.data[(v as usize) * W as usize + u as usize];
    let trunc = cfg.trunc_m();
    let sdf = d - p.z;
    let usable = d >= cfg.depth_min_m && d <= cfg.depth_max_m;
    if !(usable && sdf >= -trunc) {
        return Some(());
    }
    if (sdf + trunc).abs() < 1e-4 {
        return None;
    }
    let obs = (sdf / trunc).min(1.0);
    let wp = r.weight.min(cfg.weight_cap.unwrap_or(f32::INFINITY) - 1.0);
    let c = f.colour.data[(v as usize) * W as usize + u as usize];
    r.tsdf = (r.tsdf * wp + obs) / (wp + 1.0);
    for ch in 0..3 {
        r.colour[ch] = (r.colour[ch] * wp + c[ch]) / (wp + 1.0);
    }
    r.weight = wp + 1.0;
    Some(())
}

#[test]
fn the_simd_update_equals_a_scalar_reference_integrator() {
    let cfg = TsdfConfig {
        voxel_size_m: 0.05,
        trunc_voxels: 4.0,
        depth_min_m: 0.1,
        depth_max_m: 3.0,
        weight_cap: Some(3.0),
        weight_threshold: 1.0,
    };
    let mut map = TsdfMap::new(cfg);
    let cameras: Vec<Camera> =
        [(0.0, 0.0, 0.0), (0.13, 0.05, 0.02), (-0.21, 0.11, -0.07), (0.3, -0.17, 0.1), (0.04, 0.2, 0.0)]
            .iter()
            .map(|&(x, y, z)| Camera::new(intrinsics(), Rigid3::new(glam::Mat3::IDENTITY, Vec3::new(x, y, z))))
            .collect();
    let frames: Vec<RgbdFrame> = cameras.iter().map(|c| frame(c.world_from_camera.translation)).collect();
    for (c, f) in cameras.iter().zip(&frames) {
        map.integrate(f, c);
    }
    let keys = map.block_keys();
    assert!(keys.len() > 100, "{} blocks", keys.len());
    let allocated: HashSet<IVec3> = keys.iter().copied().collect();
    // the blocks each frame updates: those a fresh map allocates for it alone
    let touched: Vec<HashSet<IVec3>> = cameras
        .iter()
        .zip(&frames)
        .map(|(c, f)| {
            let mut m = TsdfMap::new(cfg);
            m.integrate(f, c);
            m.block_keys().into_iter().collect()
        })
        .collect();
    assert_eq!(touched.iter().flatten().copied().collect::<HashSet<_>>(), allocated);
    let vs = cfg.voxel_size_m;
    let centre = |g: IVec3| (g.as_vec3() + Vec3::splat(0.5)) * vs;
    // 1. every voxel of every allocated block holds the reference value
    let (mut compared, mut observed) = (0usize, 0usize);
    for key in &keys {
        for z in 0..8 {
            for y in 0..8 {
                for x in 0..8 {
                    let g = *key * 8 + IVec3::new(x, y, z);
                    let mut r = Ref::default();
                    let ok = cameras.iter().zip(&frames).zip(&touched).all(|((c, f), t)| {
                        !t.contains(key) || reference_update(&mut r, centre(g), c, f, &cfg).is_some()
                    });
                    if !ok {
                        continue;
                    }
                    let got = map.voxel(g).unwrap();
                    compared += 1;
                    observed += (r.weight > 0.0) as usize;
                    assert_eq!(got.weight, r.weight, "voxel {g}: weight");
                    assert!((got.tsdf - r.tsdf).abs() <= 1e-5, "voxel {g}: tsdf {} vs {}", got.tsdf, r.tsdf);
                    for ch in 0..3 {
                        assert!((got.colour[ch] - r.colour[ch]).abs() <= 1e-5, "voxel {g}: colour {ch}");
                    }
                }
            }
        }
    }
    assert!(compared > 50_000 && observed > 20_000, "{compared} voxels compared, {observed} observed");
    // 2. allocation: every point of every usable pixel's band (its ray between planar depths
    //    d - trunc and d + trunc) lies in an allocated block
    let mut in_band = 0usize;
    for (c, f) in cameras.iter().zip(&frames) {
        let k = c.intrinsics;
        for v in 0..H {
            for u in 0..W {
                let d = f.depth_m.data[(v * W + u) as usize];
                if !(d >= cfg.depth_min_m && d <= cfg.depth_max_m) {
                    continue;
                }
                let ray = Vec3::new((u as f32 - k.cx) / k.fx, (v as f32 - k.cy) / k.fy, 1.0);
                for step in -9..=9 {
                    let z = d + step as f32 * 0.1 * cfg.trunc_m();
                    let p = c.world_from_camera.transform_point(ray * z);
                    let g = (p / vs).floor().as_ivec3();
                    in_band += 1;
                    assert!(
                        allocated.contains(&g.div_euclid(IVec3::splat(8))),
                        "pixel ({u}, {v}) at {z} m: block not allocated"
                    );
                }
            }
        }
    }
    assert!(in_band > 50_000, "{in_band} band points checked");
}
