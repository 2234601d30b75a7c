//! Pose and intrinsics text files: 4x4 pose matrices (7-Scenes / 3DMatch), TUM and KITTI
//! trajectories, 3x3 `camera-intrinsics.txt`.

use std::io::Write;
use std::path::Path;

use glam::{Mat3, Quat};
use sgam_core::{Intrinsics, Rigid3};

use crate::{write_atomic, IoError};

fn read_text(path: &Path) -> Result<String, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, e))?;
    String::from_utf8(bytes).map_err(|_| IoError::format(path, "not a UTF-8 text file"))
}

fn parse_numbers(path: &Path, text: &str, what: &str) -> Result<Vec<f64>, IoError> {
    text.split_whitespace()
        .map(|t| t.parse::<f64>().map_err(|_| IoError::format(path, format!("{what}: '{t}' is not a number"))))
        .collect()
}

/// Checks rigidity ([`Rigid3::try_from_rows`]: finite, orthonormal within 1e-3, det +1, last row
/// `0 0 0 1`) and re-orthonormalises the rotation: real pose files carry ~1e-4 of rounding, and
/// downstream code may rely on `inverse()` being exact.
pub(crate) fn rigid_from_rows(path: &Path, rows: [[f64; 4]; 4], what: &str) -> Result<Rigid3, IoError> {
    Rigid3::try_from_rows(rows).map(|r| r.orthonormalized()).map_err(|e| IoError::invalid(path, format!("{what}: {e}")))
}

/// Reads a 4x4 camera-to-world pose (`world_from_camera`, OpenCV axes), as 16 whitespace
/// separated numbers in row-major order (7-Scenes / 3DMatch `frame-NNNNNN.pose.txt`); 12 numbers
/// (a 3x4 matrix) are also accepted. Non-finite or non-rigid matrices are errors.
pub fn read_pose_txt(path: &Path) -> Result<Rigid3, IoError> {
    let text = read_text(path)?;
    let v = parse_numbers(path, &text, "pose")?;
    let rows = match v.len() {
        16 | 12 => {
            let mut rows = Rigid3::IDENTITY.to_rows();
            for (i, x) in v.iter().enumerate() {
                rows[i / 4][i % 4] = *x;
            }
            rows
        }
        n => return Err(IoError::format(path, format!("expected 16 numbers (a 4x4 pose matrix), found {n}"))),
    };
    rigid_from_rows(path, rows, "pose")
}

/// Writes a 4x4 camera-to-world pose as text (inverse of [`read_pose_txt`]), atomically.
pub fn write_pose_txt(path: &Path, world_from_camera: &Rigid3) -> Result<(), IoError> {
    let rows = world_from_camera.to_rows();
    write_atomic(path, |w| {
        for row in rows {
            writeln!(w, "{:.9e} {:.9e} {:.9e} {:.9e}", row[0], row[1], row[2], row[3])?;
        }
        Ok(())
    })
}

/// Non-comment, non-empty lines with their 1-based line numbers.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

/// Reads a TUM RGB-D trajectory (`timestamp tx ty tz qx qy qz qw` per line, `#` comments) as
/// `(timestamp_s, world_from_camera)`. Quaternions must have unit norm within 1e-2 (they are
/// renormalised); non-finite values are errors naming the line.
pub fn read_tum_trajectory_timed(path: &Path) -> Result<Vec<(f64, Rigid3)>, IoError> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (line_no, line) in data_lines(&text) {
        let what = format!("line {line_no}");
        let v = parse_numbers(path, line, &what)?;
        if v.len() != 8 {
            return Err(IoError::format(
                path,
                format!("{what}: expected 8 numbers (timestamp tx ty tz qx qy qz qw), found {}", v.len()),
            ));
        }
        if v.iter().any(|x| !x.is_finite()) {
            return Err(IoError::invalid(path, format!("{what}: non-finite value in pose")));
        }
        let q = [v[4], v[5], v[6], v[7]];
        let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        if (norm - 1.0).abs() > 1e-2 {
            return Err(IoError::invalid(path, format!("{what}: quaternion norm {norm:.4} is not 1")));
        }
        let quat =
            Quat::from_xyzw((q[0] / norm) as f32, (q[1] / norm) as f32, (q[2] / norm) as f32, (q[3] / norm) as f32);
        let translation = glam::Vec3::new(v[1] as f32, v[2] as f32, v[3] as f32);
        out.push((v[0], Rigid3::new(Mat3::from_quat(quat), translation)));
    }
    Ok(out)
}

/// Reads a TUM trajectory as `world_from_camera` poses (see [`read_tum_trajectory_timed`]).
pub fn read_tum_trajectory(path: &Path) -> Result<Vec<Rigid3>, IoError> {
    Ok(read_tum_trajectory_timed(path)?.into_iter().map(|(_, p)| p).collect())
}

/// Writes `(timestamp_s, world_from_camera)` as a TUM trajectory, atomically.
pub fn write_tum_trajectory(path: &Path, poses: &[(f64, Rigid3)]) -> Result<(), IoError> {
    write_atomic(path, |w| {
        writeln!(w, "# timestamp tx ty tz qx qy qz qw")?;
        for (t, p) in poses {
            let q = Quat::from_mat3(&p.rotation).normalize();
            let c = p.translation;
            writeln!(w, "{t:.6} {} {} {} {} {} {} {}", c.x, c.y, c.z, q.x, q.y, q.z, q.w)?;
        }
        Ok(())
    })
}

/// Reads a KITTI odometry trajectory: 12 numbers per line, the row-major 3x4
/// `world_from_camera` matrix. Every pose must be rigid and finite (errors name the line).
pub fn read_kitti_trajectory(path: &Path) -> Result<Vec<Rigid3>, IoError> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (line_no, line) in data_lines(&text) {
        let what = format!("line {line_no}");
        let v = parse_numbers(path, line, &what)?;
        if v.len() != 12 {
            return Err(IoError::format(
                path,
                format!("{what}: expected 12 numbers (a 3x4 matrix), found {}", v.len()),
            ));
        }
        let mut rows = Rigid3::IDENTITY.to_rows();
        for (i, x) in v.iter().enumerate() {
            rows[i / 4][i % 4] = *x;
        }
        out.push(rigid_from_rows(path, rows, &what)?);
    }
    Ok(out)
}

/// Writes `world_from_camera` poses as a KITTI trajectory (12 numbers per line), atomically.
pub fn write_kitti_trajectory(path: &Path, poses: &[Rigid3]) -> Result<(), IoError> {
    write_atomic(path, |w| {
        for p in poses {
            let r = p.to_rows();
            let v: Vec<String> = r[..3].iter().flatten().map(|x| format!("{x:.9e}")).collect();
            writeln!(w, "{}", v.join(" "))?;
        }
        Ok(())
    })
}

/// Reads a 3x3 pinhole matrix `K` as text (`camera-intrinsics.txt` of 7-Scenes / 3DMatch) and
/// pairs it with an image size. `K` must be `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]` (skew is
/// rejected).
pub fn read_intrinsics_txt(path: &Path, width: u32, height: u32) -> Result<Intrinsics, IoError> {
    let text = read_text(path)?;
    let k = parse_numbers(path, &text, "intrinsics")?;
    if k.len() != 9 {
        return Err(IoError::format(path, format!("expected 9 numbers (a 3x3 matrix K), found {}", k.len())));
    }
    intrinsics_from_k(path, &k, width, height)
}

/// Builds [`Intrinsics`] from a row-major 3x3 `K` (as read from a text or `.npy` file).
pub fn intrinsics_from_k(path: &Path, k: &[f64], width: u32, height: u32) -> Result<Intrinsics, IoError> {
    if k.len() != 9 {
        return Err(IoError::format(path, format!("expected a 3x3 matrix K, found {} values", k.len())));
    }
    if k[1].abs() > 1e-9 || k[3].abs() > 1e-9 || k[6].abs() > 1e-9 || k[7].abs() > 1e-9 || (k[8] - 1.0).abs() > 1e-9 {
        return Err(IoError::invalid(path, format!("K = {k:?} is not of the form [[fx,0,cx],[0,fy,cy],[0,0,1]]")));
    }
    let (w, h) = (f64::from(width), f64::from(height));
    // a camera no real image has: the map's frustum would span thousands of voxels per pixel
    for (name, f, side) in [("fx", k[0], w), ("fy", k[4], h)] {
        let range = Intrinsics::plausible_focal_px(side as f32);
        if !range.contains(&(f as f32)) {
            return Err(IoError::invalid(
                path,
                format!("{name} = {f} px for a {side} px image side (accepted {}..={} px)", range.start(), range.end()),
            ));
        }
    }
    for (name, c, side) in [("cx", k[2], w), ("cy", k[5], h)] {
        if !(c >= -side && c <= 2.0 * side) {
            return Err(IoError::invalid(
                path,
                format!(
                    "{name} = {c} px puts the principal point far off the {side} px image (accepted {}..={} px)",
                    -side,
                    2.0 * side
                ),
            ));
        }
    }
    Intrinsics::try_new(width, height, k[0] as f32, k[4] as f32, k[2] as f32, k[5] as f32)
        .map_err(|e| IoError::invalid(path, e.to_string()))
}
