//! Round trips and decoding details of the single-file formats.
#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

mod common;

use common::*;
use sgam_core::{Image, Rigid3, TriMesh, Vec3};
use sgam_io::*;

#[test]
fn rgb_png_round_trip_is_exact_for_8bit_values() {
    let dir = tempfile::tempdir().unwrap();
    let frame = test_frame(8, 6, 3);
    let p = dir.path().join("a/b/rgb.png");
    write_rgb_png(&p, &frame.colour).unwrap();
    let back = read_rgb(&p).unwrap();
    assert_eq!(back, frame.colour);
    assert_eq!(image_size(&p).unwrap(), (8, 6));
}

#[test]
fn rgb_writer_clamps_and_rounds() {
    let dir = tempfile::tempdir().unwrap();
    let img = Image::try_from_vec(3, 1, vec![[-0.5, 2.0, f32::NAN], [0.5, 0.1, 0.999], [1.0, 0.0, 0.002]]).unwrap();
    let p = dir.path().join("c.png");
    write_rgb_png(&p, &img).unwrap();
    let back = read_rgb(&p).unwrap();
    let as8: Vec<[u8; 3]> = back.data.iter().map(|c| c.map(|x| (x * 255.0).round() as u8)).collect();
    assert_eq!(as8, vec![[0, 255, 0], [128, 26, 255], [255, 0, 1]]);
}

#[test]
fn grey_rgba_and_jpeg_images_read_as_rgb() {
    let dir = tempfile::tempdir().unwrap();
    let grey = image::GrayImage::from_fn(4, 3, |u, v| image::Luma([(u * 40 + v) as u8]));
    let gp = dir.path().join("g.png");
    grey.save(&gp).unwrap();
    let g = read_rgb(&gp).unwrap();
    assert_eq!(*g.at(2, 1), [81.0 / 255.0; 3]);
    let rgba = image::RgbaImage::from_fn(4, 3, |u, _| image::Rgba([u as u8 * 10, 20, 30, 7]));
    let ap = dir.path().join("a.png");
    rgba.save(&ap).unwrap();
    assert_eq!(*read_rgb(&ap).unwrap().at(3, 2), [30.0 / 255.0, 20.0 / 255.0, 30.0 / 255.0]);
    let jp = dir.path().join("j.jpg");
    image::RgbImage::from_pixel(16, 8, image::Rgb([200, 100, 50])).save(&jp).unwrap();
    let j = read_rgb(&jp).unwrap();
    assert_eq!(j.size(), (16, 8));
    assert!((j.at(5, 5)[0] - 200.0 / 255.0).abs() < 0.03);
}

#[test]
fn depth_png_mm_round_trip_and_invalid_markers() {
    let dir = tempfile::tempdir().unwrap();
    let mut depth = test_frame(8, 6, 1).depth_m;
    // invalid encodings and clamping
    depth.data[1] = f32::NAN;
    depth.data[2] = -1.0;
    depth.data[3] = f32::INFINITY;
    depth.data[4] = 70.0; // clamps to 65.534 m
    depth.data[5] = 0.0001; // rounds to 0 mm: kept valid at 1 mm
    let p = dir.path().join("d.png");
    write_depth_png_mm(&p, &depth).unwrap();
    let back = read_depth_png_mm(&p).unwrap();
    assert_eq!(back.size(), (8, 6));
    assert_eq!(&back.data[..6], &[0.0, 0.0, 0.0, 0.0, 65.534, 0.001]);
    assert!(max_abs_diff(&back.data[6..], &depth.data[6..]) < 1e-6);
    // a raw 65535 reads as invalid
    let raw = image::ImageBuffer::<image::Luma<u16>, _>::from_raw(2, 1, vec![65535u16, 1234]).unwrap();
    let p2 = dir.path().join("raw.png");
    raw.save(&p2).unwrap();
    assert_eq!(read_depth_png_mm(&p2).unwrap().data, vec![0.0, 1.234]);
}

#[test]
fn depth_png_rejects_8bit() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("eight.png");
    image::GrayImage::new(3, 3).save(&p).unwrap();
    let e = read_depth_png_mm(&p).unwrap_err();
    assert_names(&e, &p);
    assert!(e.to_string().contains("16-bit"), "{e}");
}

#[test]
fn npy_f32_round_trip_keeps_bits() {
    let dir = tempfile::tempdir().unwrap();
    let mut img = test_frame(8, 6, 2).depth_m;
    img.data[7] = f32::NAN;
    img.data[8] = -3.25;
    let p = dir.path().join("x.npy");
    write_npy_f32(&p, &img).unwrap();
    let back = read_npy_f32(&p).unwrap();
    assert_eq!(back.size(), (8, 6));
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&back.data), bits(&img.data));
    let bytes = std::fs::read(&p).unwrap();
    assert!(String::from_utf8_lossy(&bytes[10..80]).contains("'shape': (6, 8)"));
}

#[test]
fn npy_other_dtypes_shapes_and_orders() {
    let dir = tempfile::tempdir().unwrap();
    let vals = [1.5f64, -2.0, 3.25, 4.0, 5.5, 6.0];
    // float64 (2, 3)
    let p = dir.path().join("f8.npy");
    let data: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(&p, npy_bytes("<f8", false, "(2, 3)", &data)).unwrap();
    let img = read_npy_f32(&p).unwrap();
    assert_eq!((img.width, img.height), (3, 2));
    assert_eq!(img.data, vec![1.5, -2.0, 3.25, 4.0, 5.5, 6.0]);
    // float16 (2, 3, 1)
    let p = dir.path().join("f2.npy");
    let data: Vec<u8> = vals.iter().flat_map(|v| half::f16::from_f64(*v).to_le_bytes()).collect();
    std::fs::write(&p, npy_bytes("<f2", false, "(2, 3, 1)", &data)).unwrap();
    assert_eq!(read_npy_f32(&p).unwrap().data, vec![1.5, -2.0, 3.25, 4.0, 5.5, 6.0]);
    // big-endian float32, Fortran order: stored column by column
    let p = dir.path().join("fortran.npy");
    let col_major = [1.5f32, 4.0, -2.0, 5.5, 3.25, 6.0];
    let data: Vec<u8> = col_major.iter().flat_map(|v| v.to_be_bytes()).collect();
    std::fs::write(&p, npy_bytes(">f4", true, "(2, 3)", &data)).unwrap();
    let img = read_npy_f32(&p).unwrap();
    assert_eq!((img.width, img.height), (3, 2));
    assert_eq!(img.data, vec![1.5, -2.0, 3.25, 4.0, 5.5, 6.0]);
    // matrices of any shape
    let (v, shape) = read_npy_matrix(&dir.path().join("f8.npy")).unwrap();
    assert_eq!(shape, vec![2, 3]);
    assert_eq!(v, vals.to_vec());
    let p = dir.path().join("t.npy");
    write_npy_f64(&p, &[1.0, 2.0, 3.0], &[3]).unwrap();
    assert_eq!(read_npy_matrix(&p).unwrap(), (vec![1.0, 2.0, 3.0], vec![3]));
    // unsupported dtype and dimensionality
    let p = dir.path().join("int.npy");
    std::fs::write(&p, npy_bytes("<i4", false, "(1, 1)", &[0, 0, 0, 0])).unwrap();
    let e = read_npy_f32(&p).unwrap_err();
    assert!(e.to_string().contains("int.npy") && e.to_string().contains("dtype"), "{e}");
    let e = read_npy_f32(&dir.path().join("t.npy")).unwrap_err();
    assert!(e.to_string().contains("2-D"), "{e}");
}

#[test]
fn pose_txt_round_trip_and_7scenes_number_format() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("pose.txt");
    let pose = test_pose(4);
    write_pose_txt(&p, &pose).unwrap();
    let back = read_pose_txt(&p).unwrap();
    assert!(pose_diff(&back, &pose) < 1e-6);
    // 7-Scenes writes three-digit exponents and tabs
    std::fs::write(
        &p,
        "  1.0000000e+000\t  0.0000000e+000\t  0.0000000e+000\t -9.1287065e-001\t\n\
         0 1 0 2.5e-001\n0 0 1 7.5\n0 0 0 1\n",
    )
    .unwrap();
    let t = read_pose_txt(&p).unwrap();
    assert_eq!(t.translation, Vec3::new(-0.91287065, 0.25, 7.5));
}

#[test]
fn tum_and_kitti_trajectories() {
    let dir = tempfile::tempdir().unwrap();
    let poses: Vec<Rigid3> = (0..5).map(test_pose).collect();
    let tum = dir.path().join("traj.tum");
    let timed: Vec<(f64, Rigid3)> = poses.iter().enumerate().map(|(i, p)| (i as f64 * 0.1, *p)).collect();
    write_tum_trajectory(&tum, &timed).unwrap();
    let back = read_tum_trajectory_timed(&tum).unwrap();
    assert_eq!(back.len(), 5);
    for ((t, p), (t0, p0)) in back.iter().zip(&timed) {
        assert!((t - t0).abs() < 1e-6);
        assert!(pose_diff(p, p0) < 1e-5);
    }
    // a hand-written TUM file: 90 degrees about z, comments and blank lines
    std::fs::write(&tum, "# comment\n\n1.0 1 2 3 0 0 0.70710678 0.70710678\n").unwrap();
    let t = read_tum_trajectory(&tum).unwrap();
    assert_eq!(t.len(), 1);
    assert!((t[0].transform_vector(Vec3::X) - Vec3::Y).length() < 1e-6);
    assert_eq!(t[0].translation, Vec3::new(1.0, 2.0, 3.0));

    let kitti = dir.path().join("traj.txt");
    write_kitti_trajectory(&kitti, &poses).unwrap();
    let back = read_kitti_trajectory(&kitti).unwrap();
    for (p, p0) in back.iter().zip(&poses) {
        assert!(pose_diff(p, p0) < 1e-6);
    }
    std::fs::write(&kitti, "1 0 0 0 0 1 0 0 0 0 1\n").unwrap();
    let e = read_kitti_trajectory(&kitti).unwrap_err();
    assert!(e.to_string().contains("traj.txt") && e.to_string().contains("line 1"), "{e}");
}

fn test_mesh() -> TriMesh {
    TriMesh {
        positions: vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(0.25, -0.5, 2.0),
        ],
        colours: vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.2, 0.4, 0.6]],
        triangles: vec![[0, 1, 2], [1, 3, 2]],
    }
}

fn colours_to_8bit(c: &[[f32; 3]]) -> Vec<[u8; 3]> {
    c.iter().map(|c| c.map(to_srgb8)).collect()
}

#[test]
fn ply_round_trip_binary() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = test_mesh();
    let p = dir.path().join("m.ply");
    write_ply(&p, &mesh).unwrap();
    let back = read_ply(&p).unwrap();
    assert_eq!(back.positions, mesh.positions);
    assert_eq!(back.triangles, mesh.triangles);
    assert_eq!(colours_to_8bit(&back.colours), colours_to_8bit(&mesh.colours));
    // without colours
    let plain = TriMesh { colours: vec![], ..mesh };
    write_ply(&p, &plain).unwrap();
    assert_eq!(read_ply(&p).unwrap(), plain);
}

#[test]
fn ply_reads_open3d_style_and_ascii_variants() {
    let dir = tempfile::tempdir().unwrap();
    // Open3D style: double xyz, double normals, uchar colours, uint indices, plus an extra element.
    let mut bytes = b"ply\nformat binary_little_endian 1.0\ncomment Created by Open3D\nelement vertex 3\n\
property double x\nproperty double y\nproperty double z\nproperty double nx\nproperty double ny\nproperty double nz\n\
property uchar red\nproperty uchar green\nproperty uchar blue\nelement face 1\nproperty list uchar uint vertex_indices\n\
element edge 1\nproperty int vertex1\nproperty int vertex2\nend_header\n"
        .to_vec();
    for (i, p) in [[0.5f64, 1.0, 2.0], [1.5, 1.0, 2.0], [0.5, 3.0, -2.0]].iter().enumerate() {
        for c in p {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
        for n in [0.0f64, 0.0, 1.0] {
            bytes.extend_from_slice(&n.to_le_bytes());
        }
        bytes.extend_from_slice(&[255, (i * 100) as u8, 0]);
    }
    bytes.push(3);
    for v in [2u32, 1, 0] {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    bytes.extend_from_slice(&0i32.to_le_bytes());
    bytes.extend_from_slice(&1i32.to_le_bytes());
    let p = dir.path().join("o3d.ply");
    std::fs::write(&p, &bytes).unwrap();
    let m = read_ply(&p).unwrap();
    assert_eq!(m.positions[2], Vec3::new(0.5, 3.0, -2.0));
    assert_eq!(m.triangles, vec![[2, 1, 0]]);
    assert_eq!(m.colours[1], [1.0, 100.0 / 255.0, 0.0]);

    // ASCII, float colours, a quad (triangulated as a fan), big-endian variant of the same
    let ascii = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
property float red\nproperty float green\nproperty float blue\nelement face 1\nproperty list uchar int vertex_index\nend_header\n\
0 0 0 1 0 0\n1 0 0 0 1 0\n1 1 0 0 0 1\n0 1 0 0.5 0.5 0.5\n4 0 1 2 3\n";
    let p = dir.path().join("ascii.ply");
    std::fs::write(&p, ascii).unwrap();
    let m = read_ply(&p).unwrap();
    assert_eq!(m.positions.len(), 4);
    assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    assert_eq!(m.colours[3], [0.5, 0.5, 0.5]);
    assert!((m.area() - 1.0).abs() < 1e-9);

    let mut be =
        b"ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
element face 1\nproperty list uchar int vertex_indices\nend_header\n"
            .to_vec();
    for c in [0.0f32, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 2.0, 0.0] {
        be.extend_from_slice(&c.to_be_bytes());
    }
    be.push(3);
    for v in [0i32, 1, 2] {
        be.extend_from_slice(&v.to_be_bytes());
    }
    let p = dir.path().join("be.ply");
    std::fs::write(&p, &be).unwrap();
    let m = read_ply(&p).unwrap();
    assert!((m.area() - 2.0).abs() < 1e-9);
    assert!(m.colours.is_empty());
}

#[test]
fn obj_has_coloured_vertices_and_one_based_faces() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("m.obj");
    write_obj(&p, &test_mesh()).unwrap();
    let text = std::fs::read_to_string(&p).unwrap();
    let v: Vec<&str> = text.lines().filter(|l| l.starts_with("v ")).collect();
    assert_eq!(v.len(), 4);
    assert_eq!(v[3], "v 0.25 -0.5 2 0.2 0.4 0.6");
    let f: Vec<&str> = text.lines().filter(|l| l.starts_with("f ")).collect();
    assert_eq!(f, vec!["f 1 2 3", "f 2 4 3"]);
}

/// Minimal GLB parse for the test: JSON chunk and BIN chunk.
fn parse_glb(bytes: &[u8]) -> (serde_json::Value, Vec<u8>) {
    let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
    assert_eq!(&bytes[0..4], b"glTF");
    assert_eq!(u32_at(4), 2);
    assert_eq!(u32_at(8) as usize, bytes.len());
    let json_len = u32_at(12) as usize;
    assert_eq!(&bytes[16..20], b"JSON");
    assert_eq!(json_len % 4, 0);
    let json: serde_json::Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
    let mut bin = Vec::new();
    let o = 20 + json_len;
    if o < bytes.len() {
        let bin_len = u32_at(o) as usize;
        assert_eq!(&bytes[o + 4..o + 8], b"BIN\0");
        bin = bytes[o + 8..o + 8 + bin_len].to_vec();
    }
    (json, bin)
}

#[test]
fn glb_is_valid_with_y_up_positions_linear_colours_and_indices() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = test_mesh();
    let p = dir.path().join("m.glb");
    write_glb(&p, &mesh).unwrap();
    let (json, bin) = parse_glb(&std::fs::read(&p).unwrap());
    assert_eq!(json["asset"]["version"], "2.0");
    assert_eq!(json["buffers"][0]["byteLength"].as_u64().unwrap() as usize, bin.len());
    let prim = &json["meshes"][0]["primitives"][0];
    let pos_acc = &json["accessors"][prim["attributes"]["POSITION"].as_u64().unwrap() as usize];
    assert_eq!(pos_acc["count"], 4);
    // world (0.25, -0.5, 2.0) -> glTF (0.25, 2.0, 0.5): up is +y
    assert_eq!(pos_acc["max"], serde_json::json!([1.0, 2.0, 0.5]));
    assert_eq!(pos_acc["min"], serde_json::json!([0.0, 0.0, -1.0]));
    let floats = |off: usize, n: usize| -> Vec<f32> {
        (0..n).map(|i| f32::from_le_bytes(bin[off + 4 * i..off + 4 * i + 4].try_into().unwrap())).collect()
    };
    let view = |acc: &serde_json::Value| &json["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
    let pos_off = view(pos_acc)["byteOffset"].as_u64().unwrap() as usize;
    assert_eq!(floats(pos_off + 36, 3), vec![0.25, 2.0, 0.5]);
    let col_acc = &json["accessors"][prim["attributes"]["COLOR_0"].as_u64().unwrap() as usize];
    let col_off = view(col_acc)["byteOffset"].as_u64().unwrap() as usize;
    let c = floats(col_off + 36, 3);
    assert!((c[0] - srgb_to_linear(0.2)).abs() < 1e-7 && (srgb_to_linear(0.2) - 0.0331).abs() < 1e-3);
    let idx_acc = &json["accessors"][prim["indices"].as_u64().unwrap() as usize];
    assert_eq!(idx_acc["componentType"], 5125);
    assert_eq!(idx_acc["count"], 6);
    let idx_off = view(idx_acc)["byteOffset"].as_u64().unwrap() as usize;
    let idx: Vec<u32> =
        (0..6).map(|i| u32::from_le_bytes(bin[idx_off + 4 * i..idx_off + 4 * i + 4].try_into().unwrap())).collect();
    assert_eq!(idx, vec![0, 1, 2, 1, 3, 2]);
    // the axis change is a proper rotation: triangle normals rotate with it
    let n_world = (mesh.positions[1] - mesh.positions[0]).cross(mesh.positions[2] - mesh.positions[0]);
    let g: Vec<Vec3> = mesh.positions.iter().map(|p| world_to_gltf(*p)).collect();
    let n_gltf = (g[1] - g[0]).cross(g[2] - g[0]);
    assert!((n_gltf - world_to_gltf(n_world)).length() < 1e-6);
    // empty mesh: still a valid file
    write_glb(&p, &TriMesh::default()).unwrap();
    let (json, bin) = parse_glb(&std::fs::read(&p).unwrap());
    assert!(bin.is_empty() && json["scenes"][0]["nodes"].as_array().unwrap().is_empty());
}

#[test]
fn mesh_writers_reject_bad_indices() {
    let dir = tempfile::tempdir().unwrap();
    let mut mesh = test_mesh();
    mesh.triangles.push([0, 1, 9]);
    for name in ["bad.ply", "bad.obj", "bad.glb"] {
        let p = dir.path().join(name);
        let e = match name {
            "bad.ply" => write_ply(&p, &mesh),
            "bad.obj" => write_obj(&p, &mesh),
            _ => write_glb(&p, &mesh),
        }
        .unwrap_err();
        assert_names(&e, &p);
        assert!(!p.exists());
    }
}

#[test]
fn intrinsics_far_from_any_real_camera_are_refused_naming_the_file() {
    let p = std::path::Path::new("camera-intrinsics.txt");
    let k = |fx: f64, cx: f64| [fx, 0.0, cx, 0.0, fx, 240.0, 0.0, 0.0, 1.0];
    assert!(sgam_io::intrinsics_from_k(p, &k(585.0, 320.0), 640, 480).is_ok());
    // slightly off the image is a cropped camera: accepted
    assert!(sgam_io::intrinsics_from_k(p, &k(585.0, -100.0), 640, 480).is_ok());
    let e = sgam_io::intrinsics_from_k(p, &k(585.0, 1e6), 640, 480).unwrap_err().to_string();
    assert!(e.contains("camera-intrinsics.txt") && e.contains("cx"), "{e}");
    let e = sgam_io::intrinsics_from_k(p, &k(1e-3, 320.0), 640, 480).unwrap_err().to_string();
    assert!(e.contains("fx"), "{e}");
}
