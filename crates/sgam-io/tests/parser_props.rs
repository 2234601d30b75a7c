//! Property tests over every file reader: arbitrary bytes, and valid files with bytes
//! flipped, cut short or spliced, never make a reader panic; whatever a reader accepts obeys its
//! contract (finite rigid poses, finite mesh positions with indices in range, images whose pixel
//! count matches their size, depth finite and non-negative).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};

use proptest::prelude::*;
use sgam_core::{Image, Intrinsics, Rigid3, TriMesh, Vec3};
use sgam_io::*;

/// One valid file per format, written by the crate's own writers: (name, bytes), made once.
fn valid_files() -> &'static [(&'static str, Vec<u8>)] {
    static FILES: std::sync::OnceLock<Vec<(&'static str, Vec<u8>)>> = std::sync::OnceLock::new();
    FILES.get_or_init(make_valid_files)
}

fn make_valid_files() -> Vec<(&'static str, Vec<u8>)> {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pose = Rigid3::new(glam::Mat3::from_rotation_z(0.3), Vec3::new(1.0, -2.0, 0.5));
    let mesh = TriMesh {
        positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::ONE],
        colours: vec![[0.1, 0.2, 0.3]; 4],
        triangles: vec![[0, 1, 2], [1, 3, 2]],
    };
    write_ply(&d.join("m.ply"), &mesh).unwrap();
    write_npy_f32(&d.join("d.npy"), &Image::filled(5, 4, 2.5f32)).unwrap();
    write_pose_txt(&d.join("pose.txt"), &pose).unwrap();
    write_tum_trajectory(&d.join("tum.txt"), &[(0.0, pose), (1.0, Rigid3::IDENTITY)]).unwrap();
    write_kitti_trajectory(&d.join("kitti.txt"), &[pose, Rigid3::IDENTITY]).unwrap();
    let frames = (0..2)
        .map(|i| NerfFrame {
            file_path: format!("rgb/{i:05}.png"),
            depth_file_path: Some(format!("depth/{i:05}.npy")),
            world_from_camera: pose,
            intrinsics: None,
        })
        .collect();
    let k = Intrinsics::from_fov_x(8, 6, 1.0);
    write_nerf_transforms(
        &d.join("nerf.json"),
        &NerfTransforms { intrinsics: k, frames, depth_png_metres_per_unit: 0.001 },
    )
    .unwrap();
    let metas = [ClevrFrameMeta { index: 3, grid_i: -20.0, grid_j: 4.0, world_from_camera: pose }];
    write_clevr_transforms(d, 1.2, &metas, DepthType::RayLength).unwrap();
    write_rgb_png(&d.join("c.png"), &Image::filled(6, 4, [0.2f32, 0.5, 0.9])).unwrap();
    write_depth_png_mm(&d.join("dm.png"), &Image::filled(6, 4, 1.25f32)).unwrap();
    let mut out = Vec::new();
    for name in
        ["m.ply", "d.npy", "pose.txt", "tum.txt", "kitti.txt", "nerf.json", "transforms.json", "c.png", "dm.png"]
    {
        out.push((name, std::fs::read(d.join(name)).unwrap()));
    }
    out
}

fn rigid(p: &Rigid3) -> bool {
    p.is_finite() && Rigid3::try_from_rows(p.to_rows()).is_ok()
}

/// Feeds `bytes` to the reader of `name`'s format; panics (a failed property) only when a
/// reader panics or accepts content that breaks its contract.
fn read_as(dir: &Path, name: &str, bytes: &[u8]) {
    let path: PathBuf = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    match name {
        "m.ply" => {
            if let Ok(m) = read_ply(&path) {
                assert!(m.positions.iter().all(|p| p.is_finite()));
                assert!(m.triangles.iter().flatten().all(|&i| (i as usize) < m.positions.len()));
                assert!(m.colours.is_empty() || m.colours.len() == m.positions.len());
            }
        }
        "d.npy" => {
            if let Ok(img) = read_npy_f32(&path) {
                assert_eq!(img.data.len(), (img.width * img.height) as usize);
            }
            let _ = read_npy_matrix(&path);
            if let Ok(d) = read_depth_any(&path) {
                assert!(d.data.iter().all(|v| v.is_finite() && *v >= 0.0), "depth out of contract");
            }
        }
        "pose.txt" => {
            if let Ok(p) = read_pose_txt(&path) {
                assert!(rigid(&p));
            }
            let _ = read_intrinsics_txt(&path, 64, 48);
        }
        "tum.txt" => {
            if let Ok(ps) = read_tum_trajectory(&path) {
                assert!(ps.iter().all(rigid));
            }
            let _ = read_tum_trajectory_timed(&path);
        }
        "kitti.txt" => {
            if let Ok(ps) = read_kitti_trajectory(&path) {
                assert!(ps.iter().all(rigid));
            }
        }
        "nerf.json" => {
            if let Ok(t) = read_nerf_transforms(&path) {
                assert!(t.frames.iter().all(|f| rigid(&f.world_from_camera)));
            }
        }
        "transforms.json" => {
            if let Ok(t) = read_clevr_transforms(&path) {
                assert!(t.frames.iter().all(|f| rigid(&f.world_from_camera)));
                assert!(t.camera_angle_x.is_finite() && t.camera_angle_x > 0.0);
            }
        }
        "c.png" => {
            if let Ok(img) = read_rgb(&path) {
                assert_eq!(img.data.len(), (img.width * img.height) as usize);
                assert!(img.data.iter().flatten().all(|c| (0.0..=1.0).contains(c)));
            }
            let _ = image_size(&path);
        }
        "dm.png" => {
            if let Ok(d) = read_depth_png_mm(&path) {
                assert!(d.data.iter().all(|v| v.is_finite() && *v >= 0.0));
            }
        }
        other => panic!("no reader for {other}"),
    }
}

/// A valid file changed: `flips` bytes xor-ed, then cut at `cut` (a fraction), then `junk`
/// spliced in at `at` (a fraction).
fn mutate(bytes: &[u8], flips: &[(f64, u8)], cut: f64, junk: &[u8], at: f64) -> Vec<u8> {
    let mut b = bytes.to_vec();
    for (pos, x) in flips {
        if !b.is_empty() {
            let i = ((b.len() - 1) as f64 * pos) as usize;
            b[i] ^= x;
        }
    }
    b.truncate(((b.len() as f64) * cut).ceil() as usize);
    let i = ((b.len() as f64) * at) as usize;
    b.splice(i..i, junk.iter().copied());
    b
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    #[test]
    fn readers_never_panic_on_arbitrary_bytes(bytes in prop::collection::vec(any::<u8>(), 0..512), which in 0usize..9) {
        let dir = tempfile::tempdir().unwrap();
        let files = valid_files();
        read_as(dir.path(), files[which].0, &bytes);
    }

    #[test]
    fn readers_never_panic_on_damaged_valid_files(
        which in 0usize..9,
        flips in prop::collection::vec((0.0f64..1.0, 1u8..=255), 0..4),
        cut in prop_oneof![Just(1.0f64), 0.0f64..1.0],
        junk in prop::collection::vec(any::<u8>(), 0..16),
        at in 0.0f64..1.0,
    ) {
        let dir = tempfile::tempdir().unwrap();
        let files = valid_files();
        let (name, bytes) = &files[which];
        read_as(dir.path(), name, &mutate(bytes, &flips, cut, &junk, at));
    }
}

#[test]
fn the_valid_files_read_back() {
    // the properties above start from files that do parse
    let dir = tempfile::tempdir().unwrap();
    for (name, bytes) in valid_files() {
        std::fs::write(dir.path().join(name), bytes).unwrap();
    }
    let d = dir.path();
    assert_eq!(read_ply(&d.join("m.ply")).unwrap().triangles.len(), 2);
    assert_eq!(read_npy_f32(&d.join("d.npy")).unwrap().data.len(), 20);
    assert_eq!(read_kitti_trajectory(&d.join("kitti.txt")).unwrap().len(), 2);
    assert_eq!(read_tum_trajectory(&d.join("tum.txt")).unwrap().len(), 2);
    assert_eq!(read_nerf_transforms(&d.join("nerf.json")).unwrap().frames.len(), 2);
    assert_eq!(read_clevr_transforms(&d.join("transforms.json")).unwrap().frames.len(), 1);
    assert_eq!(read_rgb(&d.join("c.png")).unwrap().width, 6);
    assert!((read_depth_png_mm(&d.join("dm.png")).unwrap().data[0] - 1.25).abs() < 1e-3);
    read_pose_txt(&d.join("pose.txt")).unwrap();
}

#[test]
fn a_non_finite_ply_vertex_is_an_error_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("nan.ply");
    let text = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
                element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\nnan 1 0\n3 0 1 2\n";
    std::fs::write(&p, text).unwrap();
    let e = read_ply(&p).unwrap_err().to_string();
    assert!(e.contains("nan.ply") && e.contains("vertex 2"), "{e}");
    // an f64 vertex beyond the f32 range becomes infinite: refused too
    std::fs::write(&p, text.replace("property float x", "property double x").replace("nan 1 0", "1e300 1 0")).unwrap();
    assert!(read_ply(&p).is_err());
}
