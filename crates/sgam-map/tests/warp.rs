//! Inverse warping between views of analytic scenes: colour reproduction and occlusion rejection.

mod common;

use common::*;
use sgam_core::{Camera, Vec2, Vec3};
use sgam_map::{warp_colour, SourceSelection, SourceView, WarpConfig};

fn scene() -> Vec<Shape> {
    vec![
        Shape::Plane { normal: Vec3::Z, offset: 0.0 },
        Shape::Cuboid { min: Vec3::new(-0.25, -0.25, 0.0), max: Vec3::new(0.25, 0.25, 0.6), colour: [0.1, 0.2, 0.9] },
    ]
}

/// Ground truth: is the world point visible from `cam` (not occluded)?
fn visible_from(cam: &Camera, p: Vec3) -> Option<bool> {
    let cfw = cam.world_from_camera.inverse();
    let (uv, z) = cam.project_world(&cfw, p)?;
    if !cam.intrinsics.contains(uv) {
        return None;
    }
    let dir = cam.world_from_camera.transform_vector(cam.intrinsics.ray_z1(uv));
    let (t, _) = trace(&scene(), cam.centre_world(), dir)?;
    Some((t - z).abs() < 1e-3)
}

#[test]
fn warping_reproduces_colour_and_rejects_occluded_pixels() {
    let s = scene();
    // The source sees the plane behind the box from an oblique angle; the target looks down.
    let source_cam = camera(Vec3::new(2.2, 0.0, 1.2), Vec3::new(-0.3, 0.0, 0.0), 160, 120, 120.0);
    let target_cam = camera(Vec3::new(0.3, 0.1, 2.5), Vec3::new(-0.2, 0.0, 0.0), 160, 120, 120.0);
    let source = render_analytic(&s, &source_cam);
    let target = render_analytic(&s, &target_cam);
    let warped = warp_colour(
        &target_cam,
        &target.depth_m,
        &[SourceView { camera: &source_cam, frame: &source }],
        &WarpConfig::default(),
    );
    let (w, h) = (160u32, 120u32);
    let (mut visible, mut visible_ok, mut occluded, mut occluded_rejected) = (0, 0, 0, 0);
    let mut worst_colour = 0.0f32;
    for v in 0..h {
        for u in 0..w {
            let i = (v * w + u) as usize;
            let z = target.depth_m.data[i];
            if z <= 0.0 {
                assert!(warped.missing[i]);
                continue;
            }
            let p = target_cam.unproject_world(Vec2::new(u as f32, v as f32), z);
            // Skip points within 2 source pixels of an occlusion boundary: ambiguous by construction.
            let Some(vis) = visible_from(&source_cam, p) else { continue };
            // ... and within 2 source pixels of a depth or colour edge (bilinear colour mixes there).
            let cfw = source_cam.world_from_camera.inverse();
            let (uv, _) = source_cam.project_world(&cfw, p).unwrap();
            let look = |q: Vec2| {
                let dir = source_cam.world_from_camera.transform_vector(source_cam.intrinsics.ray_z1(q));
                trace(&s, source_cam.centre_world(), dir).unwrap_or((0.0, [0.0; 3]))
            };
            let (d0, c0) = look(uv);
            let near_edge = [
                (-2.0f32, 0.0f32),
                (2.0, 0.0),
                (0.0, -2.0),
                (0.0, 2.0),
                (2.0, 2.0),
                (-2.0, 2.0),
                (2.0, -2.0),
                (-2.0, -2.0),
            ]
            .iter()
            .any(|(du, dv)| {
                let q = uv + Vec2::new(*du, *dv);
                if !source_cam.intrinsics.contains(q) {
                    return true;
                }
                let (d, c) = look(q);
                (d - d0).abs() > 0.1 || (0..3).any(|k| (c[k] - c0[k]).abs() > 0.1)
            });
            if near_edge {
                continue;
            }
            if vis {
                visible += 1;
                if !warped.missing[i] {
                    visible_ok += 1;
                    assert_eq!(warped.source_index.data[i], 0);
                    let truth = target.colour.data[i];
                    let c = warped.colour.data[i];
                    let e = (0..3).map(|k| (c[k] - truth[k]).abs()).fold(0.0, f32::max);
                    worst_colour = worst_colour.max(e);
                }
            } else {
                occluded += 1;
                if warped.missing[i] {
                    occluded_rejected += 1;
                }
                assert_eq!(warped.missing[i], warped.source_index.data[i] == -1);
            }
        }
    }
    assert!(occluded > 300, "fixture must have occluded pixels: {occluded}");
    assert!(visible > 5000, "{visible}");
    assert_eq!(occluded_rejected, occluded, "occluded pixels accepted");
    assert!(visible_ok as f32 >= 0.99 * visible as f32, "{visible_ok} of {visible} visible pixels filled");
    assert!(worst_colour < 0.03, "colour error {worst_colour}");
}

#[test]
fn best_source_is_chosen_and_occlusion_falls_back_to_another_source() {
    let s = scene();
    let target_cam = camera(Vec3::new(0.3, 0.1, 2.5), Vec3::new(-0.2, 0.0, 0.0), 96, 72, 72.0);
    let left = camera(Vec3::new(2.2, 0.0, 1.2), Vec3::new(-0.3, 0.0, 0.0), 96, 72, 72.0);
    let right = camera(Vec3::new(-2.2, 0.3, 1.2), Vec3::new(0.3, 0.0, 0.0), 96, 72, 72.0);
    let (fl, fr, ft) = (render_analytic(&s, &left), render_analytic(&s, &right), render_analytic(&s, &target_cam));
    let sources = [SourceView { camera: &left, frame: &fl }, SourceView { camera: &right, frame: &fr }];
    let one = warp_colour(&target_cam, &ft.depth_m, &sources[..1], &WarpConfig::default());
    let two = warp_colour(&target_cam, &ft.depth_m, &sources, &WarpConfig::default());
    let missing_one = one.missing.iter().filter(|m| **m).count();
    let missing_two = two.missing.iter().filter(|m| **m).count();
    assert!(missing_two < missing_one, "{missing_two} vs {missing_one}");
    assert!(two.source_index.data.contains(&1) && two.source_index.data.contains(&0));
    let nearest = WarpConfig { selection: SourceSelection::NearestCamera, ..WarpConfig::default() };
    let by_camera = warp_colour(&target_cam, &ft.depth_m, &sources, &nearest);
    // The left camera is nearer the target: wherever it passes the check it is used.
    for i in 0..one.missing.len() {
        if !one.missing[i] {
            assert_eq!(by_camera.source_index.data[i], 0);
        }
    }
    // Determinism.
    assert_eq!(two, warp_colour(&target_cam, &ft.depth_m, &sources, &WarpConfig::default()));
}

#[test]
fn mismatched_or_invalid_inputs_do_not_panic() {
    let s = scene();
    let cam = camera(Vec3::new(0.3, 0.1, 2.5), Vec3::ZERO, 32, 24, 30.0);
    let small = camera(Vec3::new(0.3, 0.1, 2.5), Vec3::ZERO, 16, 12, 15.0);
    let f = render_analytic(&s, &cam);
    let wrong = render_analytic(&s, &small);
    let mut nan_depth = f.depth_m.clone();
    nan_depth.data[0] = f32::NAN;
    nan_depth.data[1] = -1.0;
    let out = warp_colour(&cam, &nan_depth, &[SourceView { camera: &cam, frame: &wrong }], &WarpConfig::default());
    assert!(out.missing.iter().all(|m| *m));
    let out = warp_colour(&cam, &nan_depth, &[SourceView { camera: &cam, frame: &f }], &WarpConfig::default());
    assert!(out.missing[0] && out.missing[1] && !out.missing[100]);
}
