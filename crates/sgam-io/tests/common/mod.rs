//! Fixture builders shared by the integration tests (every fixture is generated in a tempdir).
#![allow(dead_code)]

use std::io::Write;
use std::path::Path;

use sgam_core::{Image, Intrinsics, RgbdFrame, Rigid3, Vec3};

/// A deterministic frame whose colours are exact 8-bit values and whose depths are whole
/// millimetres between 0.5 and ~2 m, with pixel (0, 0) invalid.
pub fn test_frame(width: u32, height: u32, seed: u32) -> RgbdFrame {
    let mut colour = Image::filled(width, height, [0.0f32; 3]);
    let mut depth = Image::filled(width, height, 0.0f32);
    for v in 0..height {
        for u in 0..width {
            let k = (u * 7 + v * 13 + seed * 31) % 256;
            *colour.at_mut(u, v) = [k as f32 / 255.0, ((k * 3) % 256) as f32 / 255.0, ((255 - k) % 256) as f32 / 255.0];
            *depth.at_mut(u, v) = (500 + (u * 37 + v * 101 + seed * 7) % 1500) as f32 / 1000.0;
        }
    }
    *depth.at_mut(0, 0) = 0.0;
    RgbdFrame::try_new(colour, depth).unwrap()
}

pub fn test_pose(i: u32) -> Rigid3 {
    let eye = Vec3::new(0.3 * i as f32, -1.0 + 0.1 * i as f32, 1.5);
    Rigid3::look_at(eye, Vec3::new(0.5, 2.0, 0.0), Vec3::Z).unwrap()
}

pub fn test_intrinsics(width: u32, height: u32) -> Intrinsics {
    Intrinsics::try_new(width, height, 9.5, 9.0, 3.7, 2.4).unwrap()
}

/// Writes a 7-Scenes folder: `dir/camera-intrinsics.txt`, `dir/<sub>/frame-NNNNNN.*` for the
/// given frame numbers.
pub fn write_seven_scenes(dir: &Path, sub: &str, numbers: &[u32], width: u32, height: u32) {
    let k = test_intrinsics(width, height);
    let frames_dir = dir.join(sub);
    std::fs::create_dir_all(&frames_dir).unwrap();
    let mut f = std::fs::File::create(dir.join("camera-intrinsics.txt")).unwrap();
    writeln!(f, "{:e}\t0\t{:e}\n0\t{:e}\t{:e}\n0\t0\t1", k.fx, k.cx, k.fy, k.cy).unwrap();
    for &n in numbers {
        let frame = test_frame(width, height, n);
        let stem = frames_dir.join(format!("frame-{n:06}"));
        sgam_io::write_rgb_png(&stem.with_extension("color.png"), &frame.colour).unwrap();
        sgam_io::write_depth_png_mm(&stem.with_extension("depth.png"), &frame.depth_m).unwrap();
        sgam_io::write_pose_txt(&stem.with_extension("pose.txt"), &test_pose(n)).unwrap();
    }
}

/// Raw `.npy` bytes (v1.0 header) for `descr` and `shape` with the given little/big endian data.
pub fn npy_bytes(descr: &str, fortran: bool, shape: &str, data: &[u8]) -> Vec<u8> {
    let mut dict = format!(
        "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}",
        if fortran { "True" } else { "False" }
    );
    while (10 + dict.len() + 1) % 64 != 0 {
        dict.push(' ');
    }
    dict.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out.extend_from_slice(data);
    out
}

/// Asserts that `err`'s message names `file` (its file name).
pub fn assert_names(err: &sgam_io::IoError, file: &Path) {
    let msg = err.to_string();
    let name = file.file_name().unwrap().to_string_lossy();
    assert!(msg.contains(name.as_ref()), "error '{msg}' does not name {name}");
}

pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// Largest absolute difference between the 4x4 matrices of two transforms (`distance_to`'s
/// acos is too coarse near identity in f32).
pub fn pose_diff(a: &Rigid3, b: &Rigid3) -> f64 {
    let (ra, rb) = (a.to_rows(), b.to_rows());
    ra.iter().flatten().zip(rb.iter().flatten()).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}
