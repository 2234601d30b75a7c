//! The SGAM authors' CLEVR-Infinite scene layout: `transforms.json` (`camera_angle_x`,
//! `frames[]` with `file_path`, `grid_i`, `grid_j`, `transform_matrix` = Blender/OpenGL
//! camera-to-world), `im_NNNNN.png` (sRGB) and `dm_NNNNN.npy` (float32 depth, ray length unless
//! the json says `"depth_type": "planar"`).
//!
//! # Principal point
//! Blender places the principal point at the image centre in the *pixel-edge* convention (pixel
//! `u` spans `[u, u+1]`, its centre is at `u + 0.5`), which is `cx = W/2 - 0.5` in our OpenCV
//! convention. Files without a `depth_type` key are the authors' Blender renders and are read
//! with that exact principal point (the ray-length conversion then equals the data README's
//! `z = r f / sqrt(f^2 + (u + 0.5 - W/2)^2 + (v + 0.5 - H/2)^2)`). Files we write carry
//! `depth_type`; they were made with [`Intrinsics::from_fov_x`] (`cx = W/2` in the OpenCV
//! convention, as sgam-core's cameras render) and are read back with exactly those intrinsics.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sgam_core::{Image, Intrinsics, RgbdFrame, Rigid3};

use crate::depth::{planar_to_ray_length_image, DepthType};
use crate::{write_atomic, write_npy_f32, write_rgb_png, IoError};

/// One camera of a CLEVR-Infinite scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClevrFrameMeta {
    /// Frame number: files are `im_{index:05}.png` and `dm_{index:05}.npy`.
    pub index: u32,
    /// Grid coordinate along the first axis (the authors store the camera's world x/y grid value).
    pub grid_i: f64,
    /// Grid coordinate along the second axis.
    pub grid_j: f64,
    /// Camera-to-world, OpenCV axes (converted from Blender's at the file boundary).
    pub world_from_camera: Rigid3,
}

/// The content of a CLEVR-Infinite `transforms.json`.
#[derive(Debug, Clone, PartialEq)]
pub struct ClevrTransforms {
    /// Horizontal field of view, radians.
    pub camera_angle_x: f64,
    /// What `dm_*.npy` holds; `None` when the key is absent (the authors' files: ray length, and
    /// Blender's pixel-edge principal point, see the module docs).
    pub depth_type: Option<DepthType>,
    /// Cameras in file order.
    pub frames: Vec<ClevrFrameMeta>,
}

impl ClevrTransforms {
    /// What `dm_*.npy` holds (ray length when unspecified).
    pub fn effective_depth_type(&self) -> DepthType {
        self.depth_type.unwrap_or(DepthType::RayLength)
    }

    /// Intrinsics for images of `width x height` (see the module docs on the principal point).
    pub fn intrinsics(&self, width: u32, height: u32) -> Intrinsics {
        let k = Intrinsics::from_fov_x(width, height, self.camera_angle_x as f32);
        if self.depth_type.is_some() {
            k
        } else {
            Intrinsics { cx: k.cx - 0.5, cy: k.cy - 0.5, ..k }
        }
    }
}

#[derive(Debug, Deserialize, Serialize)]
struct FrameJson {
    file_path: String,
    #[serde(default)]
    grid_i: f64,
    #[serde(default)]
    grid_j: f64,
    transform_matrix: Vec<Vec<f64>>,
}

#[derive(Debug, Deserialize, Serialize)]
struct TransformsJson {
    camera_angle_x: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    depth_type: Option<DepthType>,
    frames: Vec<FrameJson>,
}

/// Parses a `transform_matrix` (4x4, or 3x4 with an implicit last row) into rows.
pub(crate) fn matrix_rows(path: &Path, m: &[Vec<f64>], what: &str) -> Result<[[f64; 4]; 4], IoError> {
    let mut rows = Rigid3::IDENTITY.to_rows();
    if !(m.len() == 4 || m.len() == 3) || m.iter().any(|r| r.len() != 4) {
        return Err(IoError::format(path, format!("{what}: transform_matrix must be 4x4")));
    }
    for (r, row) in m.iter().enumerate() {
        rows[r].copy_from_slice(row);
    }
    Ok(rows)
}

/// The first run of decimal digits in the file stem of `file_path` (`.../00012.exr` -> 12,
/// `im_00012.png` -> 12).
fn index_from_file_path(file_path: &str) -> Option<u32> {
    let stem = Path::new(file_path).file_stem()?.to_str()?;
    let digits: String = stem.chars().skip_while(|c| !c.is_ascii_digit()).take_while(|c| c.is_ascii_digit()).collect();
    digits.parse().ok()
}

/// Reads a CLEVR-Infinite `transforms.json`. Poses are converted from Blender (OpenGL) to
/// OpenCV `world_from_camera` and checked for rigidity. A frame's index is the number in its
/// `file_path` (the authors write `.../00012.exr`), else its position in `frames`.
pub fn read_clevr_transforms(path: &Path) -> Result<ClevrTransforms, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, e))?;
    let json: TransformsJson = serde_json::from_slice(&bytes)
        .map_err(|e| IoError::format(path, format!("not a CLEVR-Infinite transforms.json: {e}")))?;
    if !(json.camera_angle_x.is_finite() && json.camera_angle_x > 0.0 && json.camera_angle_x < std::f64::consts::PI) {
        return Err(IoError::invalid(
            path,
            format!("camera_angle_x {} is not a usable field of view", json.camera_angle_x),
        ));
    }
    let mut frames = Vec::with_capacity(json.frames.len());
    for (pos, f) in json.frames.iter().enumerate() {
        let what = format!("frames[{pos}] ({})", f.file_path);
        let rows = matrix_rows(path, &f.transform_matrix, &what)?;
        let world_from_gl = crate::poses::rigid_from_rows(path, rows, &what)?;
        frames.push(ClevrFrameMeta {
            index: index_from_file_path(&f.file_path).unwrap_or(pos as u32),
            grid_i: f.grid_i,
            grid_j: f.grid_j,
            world_from_camera: Rigid3::from_opengl_camera(world_from_gl),
        });
    }
    Ok(ClevrTransforms { camera_angle_x: json.camera_angle_x, depth_type: json.depth_type, frames })
}

/// Colour file of frame `index`: `dir/im_{index:05}.png`.
pub fn clevr_colour_path(dir: &Path, index: u32) -> PathBuf {
    dir.join(format!("im_{index:05}.png"))
}

/// Depth file of frame `index` as we write it: `dir/dm_{index:05}.npy`.
pub fn clevr_depth_path(dir: &Path, index: u32) -> PathBuf {
    dir.join(format!("dm_{index:05}.npy"))
}

/// Writes `transforms.json` of a CLEVR-Infinite scene into `dir`, atomically: `camera_angle_x`
/// (radians), `depth_type`, and per frame `file_path` (`im_{index:05}.png`), `grid_i`, `grid_j`
/// and `transform_matrix` (Blender/OpenGL camera-to-world, converted from the OpenCV
/// `world_from_camera`).
pub fn write_clevr_transforms(
    dir: &Path,
    camera_angle_x: f64,
    frames: &[ClevrFrameMeta],
    depth_type: DepthType,
) -> Result<(), IoError> {
    let path = dir.join("transforms.json");
    let json = TransformsJson {
        camera_angle_x,
        depth_type: Some(depth_type),
        frames: frames
            .iter()
            .map(|f| FrameJson {
                file_path: format!("im_{:05}.png", f.index),
                grid_i: f.grid_i,
                grid_j: f.grid_j,
                transform_matrix: f.world_from_camera.to_opengl_camera().to_rows().iter().map(|r| r.to_vec()).collect(),
            })
            .collect(),
    };
    write_atomic(&path, |w| serde_json::to_writer_pretty(w, &json).map_err(std::io::Error::other))
}

/// Writes frame `index` of a CLEVR-Infinite scene into `dir`: `im_{index:05}.png` (8-bit sRGB)
/// and `dm_{index:05}.npy` (float32; planar depth converted to ray length with `intrinsics` when
/// `depth_type` is [`DepthType::RayLength`]; invalid depth stored as `0`). Both atomic.
/// `intrinsics` must be the scene's ([`Intrinsics::from_fov_x`] of its `camera_angle_x`).
pub fn write_clevr_frame(
    dir: &Path,
    index: u32,
    frame: &RgbdFrame,
    intrinsics: &Intrinsics,
    depth_type: DepthType,
) -> Result<(), IoError> {
    let colour_path = clevr_colour_path(dir, index);
    let depth_path = clevr_depth_path(dir, index);
    if frame.colour.size() != frame.depth_m.size() || frame.colour.size() != (intrinsics.width, intrinsics.height) {
        return Err(IoError::invalid(
            &depth_path,
            format!(
                "colour {:?}, depth {:?} and intrinsics {}x{} sizes differ",
                frame.colour.size(),
                frame.depth_m.size(),
                intrinsics.width,
                intrinsics.height
            ),
        ));
    }
    let mut depth: Image<f32> = frame.depth_m.clone();
    for d in depth.data.iter_mut() {
        if !sgam_core::is_valid_depth(*d) {
            *d = 0.0;
        }
    }
    if depth_type == DepthType::RayLength {
        planar_to_ray_length_image(&mut depth, intrinsics);
    }
    write_rgb_png(&colour_path, &frame.colour)?;
    write_npy_f32(&depth_path, &depth)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_parsing() {
        assert_eq!(index_from_file_path("/data/x/diffuse_scene_1647996146/00012.exr"), Some(12));
        assert_eq!(index_from_file_path("im_00007.png"), Some(7));
        assert_eq!(index_from_file_path("./im_00007_00_01.png"), Some(7));
        assert_eq!(index_from_file_path("rgb.png"), None);
    }
}
