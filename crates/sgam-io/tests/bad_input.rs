//! One test per bad-input class: each returns an error (never a panic) whose message names the
//! offending file.
#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

mod common;

use std::path::Path;

use common::*;
use sgam_core::Rigid3;
use sgam_io::*;

fn seven_scenes_fixture() -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    write_seven_scenes(dir.path(), "rgbd-frames", &[0, 1, 2], 8, 6);
    let frames = dir.path().join("rgbd-frames");
    (dir, frames)
}

#[test]
fn missing_files() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("nope.png");
    for e in [
        read_rgb(&p).unwrap_err(),
        read_depth_png_mm(&p).unwrap_err(),
        read_npy_f32(&p.with_extension("npy")).unwrap_err(),
        read_pose_txt(&p.with_extension("txt")).unwrap_err(),
        read_ply(&p.with_extension("ply")).unwrap_err(),
    ] {
        assert!(matches!(e, IoError::Io { .. }), "{e}");
        assert!(e.to_string().contains("nope."), "{e}");
    }
    // a missing pose in a sequence
    let (_d, frames) = seven_scenes_fixture();
    let pose = frames.join("frame-000001.pose.txt");
    std::fs::remove_file(&pose).unwrap();
    assert_names(&Sequence::open(_d.path()).unwrap_err(), &pose);
    // a missing colour image
    let (_d, frames) = seven_scenes_fixture();
    let colour = frames.join("frame-000002.color.png");
    std::fs::remove_file(&colour).unwrap();
    let e = Sequence::open(_d.path()).unwrap_err();
    assert_names(&e, &colour);
    assert!(e.to_string().contains(".color.jpg"), "says what was looked for: {e}");
    // missing intrinsics
    let (_d, _frames) = seven_scenes_fixture();
    std::fs::remove_file(_d.path().join("camera-intrinsics.txt")).unwrap();
    assert!(Sequence::open(_d.path()).unwrap_err().to_string().contains("camera-intrinsics.txt"));
    // a file deleted after opening: read_frame reports it
    let (_d, frames) = seven_scenes_fixture();
    let seq = Sequence::open(_d.path()).unwrap();
    let depth = frames.join("frame-000000.depth.png");
    std::fs::remove_file(&depth).unwrap();
    assert_names(&seq.read_frame(0).unwrap_err(), &depth);
}

#[test]
fn corrupt_png() {
    let (_d, frames) = seven_scenes_fixture();
    let seq = Sequence::open(_d.path()).unwrap();
    let colour = frames.join("frame-000001.color.png");
    let mut bytes = std::fs::read(&colour).unwrap();
    bytes.truncate(bytes.len() / 2);
    std::fs::write(&colour, &bytes).unwrap();
    let e = seq.read_frame(1).unwrap_err();
    assert_names(&e, &colour);
    let garbage = frames.join("frame-000002.depth.png");
    std::fs::write(&garbage, b"this is not a png").unwrap();
    let e = seq.read_frame(2).unwrap_err();
    assert_names(&e, &garbage);
    assert!(matches!(e, IoError::Format { .. }), "{e:?}");
}

#[test]
fn truncated_and_corrupt_npy() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("depth.npy");
    write_npy_f32(&p, &test_frame(8, 6, 0).depth_m).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() - 5]).unwrap();
    let e = read_npy_f32(&p).unwrap_err();
    assert_names(&e, &p);
    assert!(e.to_string().contains("truncated"), "{e}");
    for cut in [3, 9, 40] {
        std::fs::write(&p, &bytes[..cut]).unwrap();
        assert_names(&read_npy_f32(&p).unwrap_err(), &p);
    }
    std::fs::write(&p, b"\x93NUMPY\x01\x00\x20\x00{'descr': '<f4', 'shape': (2, 2)}           ").unwrap();
    assert!(read_npy_f32(&p).unwrap_err().to_string().contains("fortran_order"));
    // an absurd shape does not allocate or overflow
    std::fs::write(&p, npy_bytes("<f4", false, "(18446744073709551615, 4)", &[0; 16])).unwrap();
    assert_names(&read_npy_f32(&p).unwrap_err(), &p);
}

#[test]
fn colour_depth_size_mismatch_names_both_files() {
    let (_d, frames) = seven_scenes_fixture();
    let colour = frames.join("frame-000001.color.png");
    write_rgb_png(&colour, &test_frame(7, 6, 1).colour).unwrap();
    let seq = Sequence::open(_d.path()).unwrap();
    let e = seq.read_frame(1).unwrap_err();
    let depth = frames.join("frame-000001.depth.png");
    assert_names(&e, &colour);
    assert_names(&e, &depth);
    // colour and depth agree but differ from the intrinsics (taken from the first frame)
    write_depth_png_mm(&depth, &test_frame(7, 6, 1).depth_m).unwrap();
    let e = seq.read_frame(1).unwrap_err();
    assert_names(&e, &colour);
    assert!(e.to_string().contains("intrinsics"), "{e}");
    // seeds too
    let dir = tempfile::tempdir().unwrap();
    let rgb = dir.path().join("a.png");
    let d = dir.path().join("b.npy");
    write_rgb_png(&rgb, &test_frame(8, 6, 0).colour).unwrap();
    write_npy_f32(&d, &test_frame(6, 8, 0).depth_m).unwrap();
    let e = read_seed_rgbd(&rgb, &d, test_intrinsics(8, 6)).unwrap_err();
    assert_names(&e, &rgb);
    assert_names(&e, &d);
}

/// NaN/inf in float depth are the legitimate "no measurement" encoding (CLEVR sky) and become
/// invalid; negative depth is an error; a frame with no valid pixel is an error.
#[test]
fn nan_inf_negative_and_all_invalid_depth() {
    let dir = tempfile::tempdir().unwrap();
    let rgb = dir.path().join("c.png");
    write_rgb_png(&rgb, &test_frame(8, 6, 0).colour).unwrap();
    let d = dir.path().join("d.npy");
    let k = test_intrinsics(8, 6);

    let mut depth = test_frame(8, 6, 0).depth_m;
    depth.data[1] = f32::NAN;
    depth.data[2] = f32::INFINITY;
    depth.data[3] = f32::NEG_INFINITY;
    depth.data[4] = 1e10;
    write_npy_f32(&d, &depth).unwrap();
    let s = read_seed_rgbd(&rgb, &d, k).unwrap();
    assert_eq!(&s.frame.depth_m.data[..5], &[0.0; 5]);
    assert_eq!(s.frame.depth_m.data[5], depth.data[5]);

    depth.data[9] = -0.5;
    write_npy_f32(&d, &depth).unwrap();
    let e = read_seed_rgbd(&rgb, &d, k).unwrap_err();
    assert_names(&e, &d);
    assert!(e.to_string().contains("negative depth -0.5 at pixel (u=1, v=1)"), "{e}");

    write_npy_f32(&d, &sgam_core::Image::filled(8, 6, f32::NAN)).unwrap();
    let e = read_seed_rgbd(&rgb, &d, k).unwrap_err();
    assert_names(&e, &d);
    assert!(e.to_string().contains("no valid depth"), "{e}");

    // a 7-Scenes frame whose depth PNG is all zero
    let (_d, frames) = seven_scenes_fixture();
    let depth_png = frames.join("frame-000002.depth.png");
    write_depth_png_mm(&depth_png, &sgam_core::Image::filled(8, 6, 0.0)).unwrap();
    let seq = Sequence::open(_d.path()).unwrap();
    assert_names(&seq.read_frame(2).unwrap_err(), &depth_png);
}

#[test]
fn non_rigid_pose() {
    let (_d, frames) = seven_scenes_fixture();
    let pose = frames.join("frame-000001.pose.txt");
    std::fs::write(&pose, "2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n").unwrap();
    let e = Sequence::open(_d.path()).unwrap_err();
    assert_names(&e, &pose);
    assert!(e.to_string().contains("orthonormal"), "{e}");
    // a reflection
    std::fs::write(&pose, "1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n").unwrap();
    assert_names(&Sequence::open(_d.path()).unwrap_err(), &pose);
    // wrong count
    std::fs::write(&pose, "1 0 0 0\n0 1 0 0\n0 0\n").unwrap();
    assert_names(&read_pose_txt(&pose).unwrap_err(), &pose);
    // in a NeRF transforms.json
    let dir = tempfile::tempdir().unwrap();
    let mut rows = Rigid3::IDENTITY.to_rows();
    rows[0][1] = 0.5;
    let json = serde_json::json!({"fl_x": 5.0, "w": 8, "h": 6,
        "frames": [{"file_path": "a.png", "depth_file_path": "a.npy", "transform_matrix": rows}]});
    let path = dir.path().join("transforms.json");
    std::fs::write(&path, json.to_string()).unwrap();
    let e = Sequence::open(dir.path()).unwrap_err();
    assert_names(&e, &path);
    assert!(e.to_string().contains("frames[0]"), "{e}");
}

#[test]
fn non_finite_pose() {
    let (_d, frames) = seven_scenes_fixture();
    let pose = frames.join("frame-000000.pose.txt");
    std::fs::write(&pose, "1 0 0 nan\n0 1 0 0\n0 0 1 0\n0 0 0 1\n").unwrap();
    let e = Sequence::open(_d.path()).unwrap_err();
    assert_names(&e, &pose);
    assert!(e.to_string().contains("non-finite"), "{e}");
    std::fs::write(&pose, "-inf -inf -inf -inf\n-inf -inf -inf -inf\n-inf -inf -inf -inf\n0 0 0 1\n").unwrap();
    assert_names(&Sequence::open(_d.path()).unwrap_err(), &pose);
    let dir = tempfile::tempdir().unwrap();
    let tum = dir.path().join("t.txt");
    std::fs::write(&tum, "0 1 2 inf 0 0 0 1\n").unwrap();
    assert_names(&read_tum_trajectory(&tum).unwrap_err(), &tum);
    std::fs::write(&tum, "0 1 2 3 0 0 0 2\n").unwrap();
    assert!(read_tum_trajectory(&tum).unwrap_err().to_string().contains("quaternion"));
}

#[test]
fn empty_sequence() {
    // a CLEVR json whose frames all lack images
    let dir = tempfile::tempdir().unwrap();
    let json = serde_json::json!({"camera_angle_x": 0.69, "frames": [
        {"file_path": "/x/00000.exr", "grid_i": 0.0, "grid_j": 0.0, "transform_matrix": Rigid3::IDENTITY.to_rows()}]});
    std::fs::write(dir.path().join("transforms.json"), json.to_string()).unwrap();
    let e = Sequence::open(dir.path()).unwrap_err();
    assert!(matches!(e, IoError::EmptySequence { .. }), "{e}");
    assert_names(&e, dir.path());
    // a NeRF json without frames
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("transforms.json"), r#"{"fl_x": 5, "w": 8, "h": 6, "frames": []}"#).unwrap();
    let e = Sequence::open(dir.path()).unwrap_err();
    assert!(matches!(e, IoError::EmptySequence { .. }), "{e}");
}

#[test]
fn unknown_layout() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("readme.txt"), "hello").unwrap();
    std::fs::create_dir(dir.path().join("images")).unwrap();
    let e = Sequence::open(dir.path()).unwrap_err();
    assert!(matches!(e, IoError::UnknownLayout { .. }), "{e}");
    assert_names(&e, dir.path());
    let msg = e.to_string();
    assert!(msg.contains("transforms.json") && msg.contains("frame-NNNNNN.depth.png"), "{msg}");
    // a missing folder
    let e = detect_layout(&dir.path().join("missing")).unwrap_err();
    assert!(e.to_string().contains("missing"), "{e}");
    // a transforms.json of neither kind, and a malformed one
    let json = dir.path().join("transforms.json");
    std::fs::write(&json, r#"{"frames": []}"#).unwrap();
    assert_names(&detect_layout(dir.path()).unwrap_err(), &json);
    std::fs::write(&json, r#"{"frames": [ }"#).unwrap();
    let e = detect_layout(dir.path()).unwrap_err();
    assert_names(&e, &json);
    assert!(e.to_string().contains("line 1"), "serde's position is kept: {e}");
}

#[test]
fn corrupt_ply_and_nerf_distortion() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("m.ply");
    let mesh = sgam_core::TriMesh {
        positions: vec![sgam_core::Vec3::ZERO, sgam_core::Vec3::X, sgam_core::Vec3::Y],
        colours: vec![],
        triangles: vec![[0, 1, 2]],
    };
    write_ply(&p, &mesh).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() - 3]).unwrap();
    let e = read_ply(&p).unwrap_err();
    assert_names(&e, &p);
    assert!(e.to_string().contains("truncated"), "{e}");
    let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n\
element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n3 0 0 5\n";
    std::fs::write(&p, text).unwrap();
    assert!(read_ply(&p).unwrap_err().to_string().contains("indexes past"));
    std::fs::write(&p, "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n").unwrap();
    assert_names(&read_ply(&p).unwrap_err(), &p);
    std::fs::write(&p, "solid stl\n").unwrap();
    assert_names(&read_ply(&p).unwrap_err(), &p);

    let json = dir.path().join("transforms.json");
    std::fs::write(&json, r#"{"camera_model": "OPENCV", "fl_x": 5, "w": 8, "h": 6, "k1": 0.1, "frames": []}"#).unwrap();
    let e = read_nerf_transforms(&json).unwrap_err();
    assert_names(&e, &json);
    assert!(e.to_string().contains("distortion"), "{e}");
}

#[test]
fn nerf_dataset_without_depth_is_named_as_such() {
    let dir = tempfile::tempdir().unwrap();
    let json = serde_json::json!({"camera_angle_x": 0.7,
        "frames": [{"file_path": "./train/r_0", "transform_matrix": Rigid3::IDENTITY.to_rows()}]});
    let path = dir.path().join("transforms.json");
    std::fs::write(&path, json.to_string()).unwrap();
    write_rgb_png(&dir.path().join("train/r_0.png"), &test_frame(8, 6, 0).colour).unwrap();
    assert_eq!(detect_layout(dir.path()).unwrap(), Layout::NerfTransforms);
    let e = Sequence::open(dir.path()).unwrap_err();
    assert_names(&e, &path);
    assert!(e.to_string().contains("no depth_file_path"), "{e}");
}

#[test]
fn errors_expose_their_path() {
    let p = Path::new("/definitely/not/here.png");
    assert_eq!(read_rgb(p).unwrap_err().path(), p);
}
