//! Interpretation of stored depth maps: which values mean "no measurement", ray length to
//! planar depth, and the "at least one valid pixel" check every frame reader applies.

use std::path::Path;

use serde::{Deserialize, Serialize};
use sgam_core::{is_valid_depth, Image, Intrinsics, Vec2};

use crate::IoError;

/// Values at or above this in a float depth file are "no measurement" markers: 65504 is the
/// largest float16 and marks sky in the Google Earth seeds; Blender writes 1e10 for background.
pub const NPY_DEPTH_INVALID_MIN: f32 = 65504.0;

/// What a stored float depth value measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DepthType {
    /// Euclidean distance from the camera centre along the pixel's ray (Blender Cycles Z pass;
    /// the SGAM authors' `dm_*.npy`).
    RayLength,
    /// Planar depth z along the optical axis (what the library uses everywhere).
    Planar,
}

impl DepthType {
    /// The string stored in `transforms.json` (`"ray_length"` / `"planar"`).
    pub fn as_str(self) -> &'static str {
        match self {
            DepthType::RayLength => "ray_length",
            DepthType::Planar => "planar",
        }
    }
}

/// Cleans a float depth map read from `path` (NPY): NaN, +-inf, `0` and values
/// `>= NPY_DEPTH_INVALID_MIN` are legitimate "no measurement" encodings and become `0.0`
/// (invalid); a negative finite value has no legitimate meaning and is an error naming the pixel.
pub fn sanitize_float_depth(path: &Path, depth: &mut Image<f32>) -> Result<(), IoError> {
    let width = depth.width.max(1) as usize;
    for (i, d) in depth.data.iter_mut().enumerate() {
        if !d.is_finite() || *d >= NPY_DEPTH_INVALID_MIN {
            *d = 0.0;
        } else if *d < 0.0 {
            return Err(IoError::invalid(
                path,
                format!("negative depth {} at pixel (u={}, v={})", *d, i % width, i / width),
            ));
        }
    }
    Ok(())
}

/// Converts valid ray lengths to planar depth in place with
/// `z = r / |ray_z1(u, v)|` at each pixel centre `(u, v)` of `intrinsics` (OpenCV convention);
/// invalid values stay as they are.
pub fn ray_length_to_planar_image(depth: &mut Image<f32>, intrinsics: &Intrinsics) {
    let w = depth.width as usize;
    for (i, d) in depth.data.iter_mut().enumerate() {
        if is_valid_depth(*d) {
            let uv = Vec2::new((i % w) as f32, (i / w) as f32);
            *d = intrinsics.ray_length_to_planar(uv, *d);
        }
    }
}

/// Inverse of [`ray_length_to_planar_image`]: `r = z * |ray_z1(u, v)|`; invalid stays invalid.
pub fn planar_to_ray_length_image(depth: &mut Image<f32>, intrinsics: &Intrinsics) {
    let w = depth.width as usize;
    for (i, d) in depth.data.iter_mut().enumerate() {
        if is_valid_depth(*d) {
            let uv = Vec2::new((i % w) as f32, (i / w) as f32);
            *d *= intrinsics.ray_z1(uv).length();
        }
    }
}

/// Errors unless at least one pixel of `depth` (read from `path`) is valid.
pub fn require_some_valid(path: &Path, depth: &Image<f32>) -> Result<(), IoError> {
    if depth.data.iter().any(|d| is_valid_depth(*d)) {
        Ok(())
    } else {
        Err(IoError::invalid(path, "no valid depth pixel in the frame (all zero, non-finite or marked invalid)"))
    }
}

/// Reads a depth file by extension: `.png` is 16-bit millimetres (0 and 65535 invalid),
/// `.npy` is float metres sanitised with [`sanitize_float_depth`]. Returns planar/ray values as
/// stored (no conversion).
pub fn read_depth_any(path: &Path) -> Result<Image<f32>, IoError> {
    match extension(path).as_deref() {
        Some("png") => crate::read_depth_png_mm(path),
        Some("npy") => {
            let mut d = crate::read_npy_f32(path)?;
            sanitize_float_depth(path, &mut d)?;
            Ok(d)
        }
        _ => Err(IoError::format(path, "unsupported depth file type (expected .png in millimetres or .npy in metres)")),
    }
}

pub(crate) fn extension(path: &Path) -> Option<String> {
    path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase())
}
