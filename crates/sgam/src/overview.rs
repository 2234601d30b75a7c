//! End-of-run pictures: an overview render of the whole world mesh and a strip of frames.

use std::path::Path;

use anyhow::{Context, Result};
use sgam_core::{Camera, Image, Intrinsics, Rigid3, TriMesh, Vec2, Vec3};
use sgam_map::TsdfMap;

use sgam_pipeline::Keyframes;

/// Horizontal field of view of the overview camera.
const OVERVIEW_FOV_X_RAD: f32 = 1.2;

/// A camera with the seed's orientation, backed off along its optical axis until the whole
/// mesh's bounding box is in view; returns the camera and the depth range to rasterize.
pub fn overview_camera(mesh: &TriMesh, seed: &Camera, width: u32, height: u32) -> Option<(Camera, f32, f32)> {
    let first = *mesh.positions.first()?;
    let (lo, hi) = mesh.positions.iter().fold((first, first), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
    let centre = (lo + hi) * 0.5;
    let k = Intrinsics::from_fov_x(width, height, OVERVIEW_FOV_X_RAD);
    let (tx, ty) = (0.5 * width as f32 / k.fx, 0.5 * height as f32 / k.fy);
    let rot = seed.world_from_camera.rotation;
    let camera_from_world = rot.transpose();
    // distance back along the optical axis so that every bbox corner projects inside (with a
    // 5 % margin): |x| <= tx (z + d) and |y| <= ty (z + d)
    let mut back = 0.0f32;
    let mut zs = Vec::with_capacity(8);
    for c in 0..8 {
        let corner = Vec3::new(
            if c & 1 == 0 { lo.x } else { hi.x },
            if c & 2 == 0 { lo.y } else { hi.y },
            if c & 4 == 0 { lo.z } else { hi.z },
        );
        let p = camera_from_world * (corner - centre);
        back = back.max(p.x.abs() / (0.95 * tx) - p.z).max(p.y.abs() / (0.95 * ty) - p.z);
        zs.push(p.z);
    }
    let back = back.max(1e-3);
    let eye = centre - rot.z_axis * back;
    let near = zs.iter().fold(f32::INFINITY, |a, z| a.min(z + back)).max(1e-3);
    let far = zs.iter().fold(0.0f32, |a, z| a.max(z + back)) * 1.01;
    Some((Camera::new(k, Rigid3::new(rot, eye)), near * 0.99, far))
}

/// The map's mesh rendered at `camera`, shaded by the rendered depth's normals (a light from
/// above the camera) on a white background.
pub fn render_overview(map: &TsdfMap, camera: &Camera, near: f32, far: f32) -> Image<[f32; 3]> {
    shade_overview(&map.rasterize_range(camera, near, far), camera)
}

/// A rendering at `camera` shaded as [`render_overview`] shades it.
pub fn shade_overview(r: &sgam_map::Rendered, camera: &Camera) -> Image<[f32; 3]> {
    let k = camera.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    let point = |u: usize, v: usize| -> Option<Vec3> {
        let d = r.depth_m.data[v * w + u];
        (r.covered[v * w + u] && d > 0.0).then(|| k.unproject(Vec2::new(u as f32, v as f32), d))
    };
    let light = Vec3::new(-0.3, -0.8, -0.5).normalize();
    let mut out = Image::filled(k.width, k.height, [1.0f32; 3]);
    for v in 0..h {
        for u in 0..w {
            let Some(p) = point(u, v) else { continue };
            let (ux, vy) = ((u + 1).min(w - 1), (v + 1).min(h - 1));
            let shade = match (point(ux, v), point(u, vy)) {
                (Some(a), Some(b)) if ux != u && vy != v => {
                    let n = (a - p).cross(b - p).normalize_or_zero();
                    0.55 + 0.45 * n.dot(light).abs()
                }
                _ => 0.8,
            };
            let c = r.colour.data[v * w + u];
            out.data[v * w + u] = c.map(|x| (x * shade).clamp(0.0, 1.0));
        }
    }
    out
}

/// `count` evenly spaced generated frames side by side (frame 0 is the seed).
pub fn frame_strip(dir: &Path, frames: usize, count: usize) -> Result<Image<[f32; 3]>> {
    let count = count.clamp(1, frames.max(1));
    let pick: Vec<usize> = (0..count).map(|k| k * (frames - 1) / (count - 1).max(1)).collect();
    let mut tiles = Vec::with_capacity(count);
    for &i in &pick {
        let (rgb, _) = Keyframes::frame_paths(dir, i);
        tiles.push(sgam_io::read_rgb(&rgb).with_context(|| format!("{}: cannot read frame", rgb.display()))?);
    }
    let (tw, th) = (tiles[0].width, tiles[0].height);
    let gap = 4u32;
    let mut out = Image::filled(count as u32 * (tw + gap) - gap, th, [1.0f32; 3]);
    for (k, t) in tiles.iter().enumerate() {
        for v in 0..th.min(t.height) {
            for u in 0..tw.min(t.width) {
                *out.at_mut(k as u32 * (tw + gap) + u, v) = *t.at(u, v);
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overview_camera_sees_every_bbox_corner() {
        let mesh = TriMesh {
            positions: vec![Vec3::new(-5.0, -3.0, -12.0), Vec3::new(7.0, 9.0, -11.0), Vec3::new(0.0, 0.0, -11.5)],
            colours: vec![[0.5; 3]; 3],
            triangles: vec![[0, 1, 2]],
        };
        let k = Intrinsics::from_fov_x(64, 64, 0.7);
        let seed = Camera::new(k, Rigid3::look_at(Vec3::ZERO, Vec3::new(0.0, 3.0, -11.0), Vec3::Z).unwrap());
        let (cam, near, far) = overview_camera(&mesh, &seed, 320, 200).unwrap();
        let cfw = cam.world_from_camera.inverse();
        for p in &mesh.positions {
            let pc = cfw.transform_point(*p);
            assert!(pc.z >= near && pc.z <= far, "{pc:?} outside {near}..{far}");
            let uv = cam.intrinsics.project(pc).unwrap();
            assert!(cam.intrinsics.contains(uv), "{p:?} projects to {uv:?}");
        }
    }
}
