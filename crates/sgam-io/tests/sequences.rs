//! Each sequence layout on a tiny generated fixture, writer/reader round trips, seeds.
#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

mod common;

use common::*;
use sgam_core::{Image, Intrinsics, Rigid3, Vec2, Vec3};
use sgam_io::*;

#[test]
fn seven_scenes_layout_in_rgbd_frames_with_jpeg_colour() {
    let dir = tempfile::tempdir().unwrap();
    write_seven_scenes(dir.path(), "rgbd-frames", &[12, 3, 7], 8, 6);
    // frame 7's colour as JPEG instead of PNG
    let frames = dir.path().join("rgbd-frames");
    let c = read_rgb(&frames.join("frame-000007.color.png")).unwrap();
    std::fs::remove_file(frames.join("frame-000007.color.png")).unwrap();
    let raw: Vec<u8> = c.data.iter().flat_map(|p| p.map(to_srgb8)).collect();
    image::RgbImage::from_raw(8, 6, raw).unwrap().save(frames.join("frame-000007.color.jpg")).unwrap();

    assert_eq!(detect_layout(dir.path()).unwrap(), Layout::SevenScenes);
    let seq = Sequence::open(dir.path()).unwrap();
    assert_eq!(seq.layout, Layout::SevenScenes);
    assert_eq!(seq.root, frames);
    assert_eq!(seq.len(), 3);
    let names: Vec<String> = (0..3).map(|i| seq.frame_name(i)).collect();
    assert_eq!(names, ["frame-000003", "frame-000007", "frame-000012"]);
    for (i, n) in [3u32, 7, 12].iter().enumerate() {
        let cam = seq.camera(i);
        assert_eq!(cam.intrinsics, test_intrinsics(8, 6));
        assert!(pose_diff(&cam.world_from_camera, &test_pose(*n)) < 1e-6);
        let f = seq.read_frame(i).unwrap();
        let truth = test_frame(8, 6, *n);
        assert!(max_abs_diff(&f.depth_m.data, &truth.depth_m.data) < 1e-6);
        if *n == 7 {
            assert!(seq.frame_paths(i).unwrap().0.to_string_lossy().ends_with(".color.jpg"));
        } else {
            assert_eq!(f.colour, truth.colour);
        }
        assert!(f.depth_m.data[0] == 0.0, "pixel (0,0) is invalid in the fixture");
    }
    assert!(seq.get_camera(3).is_none());
    assert!(seq.read_frame(3).is_err());
}

#[test]
fn seven_scenes_layout_flat_and_in_seq_folder_with_parent_intrinsics() {
    let dir = tempfile::tempdir().unwrap();
    write_seven_scenes(dir.path(), ".", &[0, 1], 8, 6);
    assert_eq!(Sequence::open(dir.path()).unwrap().len(), 2);
    let dir = tempfile::tempdir().unwrap();
    write_seven_scenes(dir.path(), "seq-01", &[0, 116, 2], 8, 6);
    let seq = Sequence::open(dir.path()).unwrap();
    assert_eq!(seq.frame_name(2), "frame-000116");
    // opening the seq folder directly finds the intrinsics in the parent
    let seq2 = Sequence::open(&dir.path().join("seq-01")).unwrap();
    assert_eq!(seq2.len(), 3);
    assert_eq!(seq2.camera(0).intrinsics.fx, 9.5);
    // a frame whose depth image is gone is an error naming it, not a frame silently dropped
    let gone = dir.path().join("seq-01").join("frame-000002.depth.png");
    std::fs::remove_file(&gone).unwrap();
    let err = Sequence::open(dir.path()).unwrap_err();
    assert_names(&err, &gone);
}

/// Authors'-style CLEVR fixture: json without depth_type, Blender file paths, ray length in
/// `dm_NNNNN_00_00.npy` computed with Blender's pixel-edge principal point.
fn write_authors_clevr(dir: &std::path::Path, fov_x: f64) -> (Vec<Rigid3>, Image<f32>) {
    let (w, h) = (8u32, 6u32);
    let poses: Vec<Rigid3> = (0..3).map(test_pose).collect();
    let frames: Vec<serde_json::Value> = poses
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let rows = p.to_opengl_camera().to_rows();
            serde_json::json!({
                "file_path": format!("/data/easy_world_dataset/diffuse_scene_1647996146/{i:05}.exr"),
                "grid_i": -20.0, "grid_j": -20.0 + i as f64 * 0.8163,
                "transform_matrix": rows,
            })
        })
        .collect();
    let json = serde_json::json!({"camera_angle_x": fov_x, "frames": frames});
    std::fs::write(dir.join("transforms.json"), serde_json::to_string_pretty(&json).unwrap()).unwrap();
    // Only frames 0 and 2 have images; frame 0's depth has the template's suffix.
    let planar = test_frame(w, h, 0).depth_m;
    let f = 0.5 * w as f64 / (0.5 * fov_x).tan();
    let mut ray = planar.clone();
    for v in 0..h {
        for u in 0..w {
            let (du, dv) = (u as f64 + 0.5 - w as f64 / 2.0, v as f64 + 0.5 - h as f64 / 2.0);
            *ray.at_mut(u, v) = (*planar.at(u, v) as f64 * (f * f + du * du + dv * dv).sqrt() / f) as f32;
        }
    }
    *ray.at_mut(1, 0) = f32::NAN; // sky
    *ray.at_mut(2, 0) = f32::INFINITY; // sky
    for (i, dm) in [(0u32, "dm_00000_00_00.npy"), (2, "dm_00002.npy")] {
        write_rgb_png(&dir.join(format!("im_{i:05}.png")), &test_frame(w, h, i).colour).unwrap();
        write_npy_f32(&dir.join(dm), &ray).unwrap();
    }
    let mut truth = planar;
    *truth.at_mut(1, 0) = 0.0;
    *truth.at_mut(2, 0) = 0.0;
    (poses, truth)
}

#[test]
fn clevr_authors_layout_skips_frames_without_images_and_converts_ray_length() {
    let dir = tempfile::tempdir().unwrap();
    let fov_x = 0.69111;
    let (poses, truth) = write_authors_clevr(dir.path(), fov_x);
    assert_eq!(detect_layout(dir.path()).unwrap(), Layout::ClevrAuthors);
    let seq = Sequence::open(dir.path()).unwrap();
    assert_eq!(seq.len(), 2);
    assert_eq!(seq.frame_name(0), "00000");
    assert_eq!(seq.frame_name(1), "00002");
    assert!(seq.frame_paths(0).unwrap().1.ends_with("dm_00000_00_00.npy"));
    let k = seq.camera(0).intrinsics;
    let f = 4.0 / (0.5 * fov_x as f32).tan();
    assert!((k.fx - f).abs() < 1e-4 && k.fx == k.fy);
    assert_eq!((k.cx, k.cy), (3.5, 2.5), "Blender's centre in the OpenCV convention");
    assert!(pose_diff(&seq.camera(1).world_from_camera, &poses[2]) < 1e-6);
    let frame = seq.read_frame(0).unwrap();
    assert!(max_abs_diff(&frame.depth_m.data, &truth.data) < 1e-5);
    assert_eq!(frame.colour, test_frame(8, 6, 0).colour);
    // Every valid planar depth unprojects to a point whose distance from the camera is the ray
    // length stored in the file (f32 rounding of metre-scale values: 1e-5 m).
    let ray = read_npy_f32(&dir.path().join("dm_00000_00_00.npy")).unwrap();
    for v in 0..6 {
        for u in 0..8 {
            let r = *ray.at(u, v);
            if !r.is_finite() || *truth.at(u, v) <= 0.0 {
                continue;
            }
            let p = k.unproject(Vec2::new(u as f32, v as f32), *frame.depth_m.at(u, v));
            assert!((p.length() - r).abs() < 1e-5, "({u}, {v}): |p| {} vs ray length {r}", p.length());
        }
    }
}

#[test]
fn clevr_writer_round_trip_ray_length_and_planar() {
    for depth_type in [DepthType::RayLength, DepthType::Planar] {
        let dir = tempfile::tempdir().unwrap();
        let fov_x = 0.69111f32;
        let k = Intrinsics::from_fov_x(8, 6, fov_x);
        let metas: Vec<ClevrFrameMeta> = (0..3)
            .map(|i| ClevrFrameMeta {
                index: i * 2,
                grid_i: i as f64,
                grid_j: -(i as f64),
                world_from_camera: test_pose(i),
            })
            .collect();
        for m in &metas {
            write_clevr_frame(dir.path(), m.index, &test_frame(8, 6, m.index), &k, depth_type).unwrap();
        }
        write_clevr_transforms(dir.path(), fov_x as f64, &metas, depth_type).unwrap();
        let t = read_clevr_transforms(&dir.path().join("transforms.json")).unwrap();
        assert_eq!(t.depth_type, Some(depth_type));
        assert_eq!(t.frames.len(), 3);
        assert_eq!(t.frames[2].index, 4);
        assert_eq!((t.frames[2].grid_i, t.frames[2].grid_j), (2.0, -2.0));
        let seq = Sequence::open(dir.path()).unwrap();
        assert_eq!(seq.layout, Layout::ClevrAuthors);
        assert_eq!(seq.len(), 3);
        for (i, m) in metas.iter().enumerate() {
            let cam = seq.camera(i);
            assert_eq!(cam.intrinsics, k, "our files are read with from_fov_x intrinsics");
            assert!(pose_diff(&cam.world_from_camera, &m.world_from_camera) < 1e-6);
            let f = seq.read_frame(i).unwrap();
            let truth = test_frame(8, 6, m.index);
            assert_eq!(f.colour, truth.colour);
            let err = f
                .depth_m
                .data
                .iter()
                .zip(&truth.depth_m.data)
                .map(|(a, b)| (a - b).abs() / b.max(1e-3))
                .fold(0.0, f32::max);
            assert!(err < 1e-6, "{depth_type:?}: relative depth error {err}");
        }
        if depth_type == DepthType::RayLength {
            let raw = read_npy_f32(&clevr_depth_path(dir.path(), 0)).unwrap();
            let corner = *raw.at(7, 5);
            assert!(corner > *test_frame(8, 6, 0).depth_m.at(7, 5), "stored ray length exceeds planar depth");
        }
    }
}

#[test]
fn nerf_transforms_round_trip_with_pose_convention() {
    let dir = tempfile::tempdir().unwrap();
    let k = test_intrinsics(8, 6);
    let k_other = Intrinsics::try_new(8, 6, 11.0, 11.0, 4.0, 3.0).unwrap();
    let mut frames = Vec::new();
    for i in 0..3u32 {
        let f = test_frame(8, 6, i);
        let rgb = format!("rgb/{i:05}.png");
        let depth = if i == 1 { format!("depth/{i:05}.npy") } else { format!("depth/{i:05}.png") };
        write_rgb_png(&dir.path().join(&rgb), &f.colour).unwrap();
        if i == 1 {
            write_npy_f32(&dir.path().join(&depth), &f.depth_m).unwrap();
        } else {
            write_depth_png_mm(&dir.path().join(&depth), &f.depth_m).unwrap();
        }
        frames.push(NerfFrame {
            file_path: rgb,
            depth_file_path: Some(depth),
            world_from_camera: test_pose(i),
            intrinsics: (i == 2).then_some(k_other),
        });
    }
    let t = NerfTransforms { intrinsics: k, frames, depth_png_metres_per_unit: 1e-3 };
    let path = dir.path().join("transforms.json");
    write_nerf_transforms(&path, &t).unwrap();

    // The file holds OpenGL camera-to-world and the pixel-edge principal point.
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    assert_eq!(json["camera_model"], "OPENCV");
    assert_eq!(json["w"], 8.0);
    assert!((json["cx"].as_f64().unwrap() - (k.cx as f64 + 0.5)).abs() < 1e-6);
    let m = &json["frames"][0]["transform_matrix"];
    let cv = test_pose(0);
    // OpenGL camera z axis (column 2) points backwards: minus our optical axis
    let fwd = cv.transform_vector(Vec3::Z);
    for r in 0..3 {
        assert!((m[r][2].as_f64().unwrap() + fwd[r] as f64).abs() < 1e-6);
        assert!((m[r][3].as_f64().unwrap() - cv.translation[r] as f64).abs() < 1e-6);
    }
    assert_eq!(json["frames"][1]["depth_path"], "depth/00001.npy");

    let back = read_nerf_transforms(&path).unwrap();
    assert_eq!(back.intrinsics, t.intrinsics);
    assert_eq!(back.depth_png_metres_per_unit, t.depth_png_metres_per_unit);
    assert_eq!(back.frames.len(), 3);
    for (a, b) in back.frames.iter().zip(&t.frames) {
        assert_eq!((&a.file_path, &a.depth_file_path, a.intrinsics), (&b.file_path, &b.depth_file_path, b.intrinsics));
        assert!(pose_diff(&a.world_from_camera, &b.world_from_camera) < 1e-6);
    }
    assert_eq!(detect_layout(dir.path()).unwrap(), Layout::NerfTransforms);
    for open_path in [dir.path().to_path_buf(), path.clone()] {
        let seq = Sequence::open(&open_path).unwrap();
        assert_eq!(seq.layout, Layout::NerfTransforms);
        assert_eq!(seq.len(), 3);
        assert_eq!(seq.frame_name(1), "00001");
        for i in 0..3 {
            let cam = seq.camera(i);
            assert_eq!(cam.intrinsics, if i == 2 { k_other } else { k });
            assert!(pose_diff(&cam.world_from_camera, &test_pose(i as u32)) < 1e-6);
            let f = seq.read_frame(i).unwrap();
            let truth = test_frame(8, 6, i as u32);
            assert_eq!(f.colour, truth.colour);
            assert!(max_abs_diff(&f.depth_m.data, &truth.depth_m.data) < 1e-6);
        }
    }
}

#[test]
fn nerf_instant_ngp_style_with_camera_angle_only() {
    let dir = tempfile::tempdir().unwrap();
    let f = test_frame(8, 6, 0);
    write_rgb_png(&dir.path().join("images/r_0.png"), &f.colour).unwrap();
    write_depth_png_mm(&dir.path().join("images/r_0_depth.png"), &f.depth_m).unwrap();
    let json = serde_json::json!({
        "camera_angle_x": 1.0,
        "integer_depth_scale": 0.0005,
        "frames": [{"file_path": "./images/r_0", "depth_path": "images/r_0_depth.png",
                    "transform_matrix": Rigid3::IDENTITY.to_rows()}]
    });
    std::fs::write(dir.path().join("transforms.json"), json.to_string()).unwrap();
    let seq = Sequence::open(dir.path()).unwrap();
    let k = seq.camera(0).intrinsics;
    assert_eq!((k.width, k.height, k.cx, k.cy), (8, 6, 3.5, 2.5));
    assert!((k.fx - 4.0 / 0.5f32.tan()).abs() < 1e-4);
    // OpenGL identity: the camera looks down world -z
    assert!((seq.camera(0).world_from_camera.transform_vector(Vec3::Z) - Vec3::NEG_Z).length() < 1e-6);
    // depth scale from integer_depth_scale: stored mm read at half scale
    let d = seq.read_frame(0).unwrap().depth_m;
    assert!((d.data[5] - 0.5 * f.depth_m.data[5]).abs() < 1e-6);
}

#[test]
fn seeds_from_rgbd_files_template_and_google_earth_layouts() {
    let dir = tempfile::tempdir().unwrap();
    let f = test_frame(8, 6, 5);
    let rgb = dir.path().join("seed.png");
    let dpng = dir.path().join("seed_depth.png");
    let dnpy = dir.path().join("seed_depth.npy");
    write_rgb_png(&rgb, &f.colour).unwrap();
    write_depth_png_mm(&dpng, &f.depth_m).unwrap();
    write_npy_f32(&dnpy, &f.depth_m).unwrap();
    let k_full = Intrinsics::try_new(16, 12, 20.0, 20.0, 8.0, 6.0).unwrap();
    for d in [&dpng, &dnpy] {
        let s = read_seed_rgbd(&rgb, d, k_full).unwrap();
        assert_eq!(s.camera.world_from_camera, Rigid3::IDENTITY);
        assert_eq!(s.camera.intrinsics, k_full.resized(8, 6));
        assert!(max_abs_diff(&s.frame.depth_m.data, &f.depth_m.data) < 1e-6);
    }
    let wrong_aspect = Intrinsics::try_new(8, 8, 20.0, 20.0, 4.0, 4.0).unwrap();
    assert_names(&read_seed_rgbd(&rgb, &dpng, wrong_aspect).unwrap_err(), &rgb);

    // CLEVR template = the authors' layout, frame 0
    let cdir = dir.path().join("clevr");
    std::fs::create_dir_all(&cdir).unwrap();
    let (poses, truth) = write_authors_clevr(&cdir, 0.69111);
    let s = read_clevr_template(&cdir).unwrap();
    assert!(pose_diff(&s.camera.world_from_camera, &poses[0]) < 1e-6);
    assert!(max_abs_diff(&s.frame.depth_m.data, &truth.data) < 1e-5);

    // Google Earth: 65504 marks sky; intrinsics scale with the resolution
    let gdir = dir.path().join("seed0");
    let mut depth = f.depth_m.clone();
    depth.data[3] = 65504.0;
    write_rgb_png(&gdir.join("im_00000.png"), &f.colour).unwrap();
    write_npy_f32(&gdir.join("dm_00000.npy"), &depth).unwrap();
    let s = read_google_earth_seed(&gdir).unwrap();
    // the folder of seeds (the authors' layout) instead of one seed: the error lists the seeds
    let e = read_google_earth_seed(dir.path()).unwrap_err().to_string();
    assert!(e.contains("holds 1 Google Earth seed (seed0)") && e.contains(&gdir.display().to_string()), "{e}");
    assert_eq!(s.frame.depth_m.data[3], 0.0);
    assert_eq!(s.frame.depth_m.data[4], depth.data[4]);
    let k = s.camera.intrinsics;
    assert!((k.fx - 497.77774 * 8.0 / 512.0).abs() < 1e-5 && (k.cx - 4.0).abs() < 1e-6 && (k.cy - 3.0).abs() < 1e-6);
}
