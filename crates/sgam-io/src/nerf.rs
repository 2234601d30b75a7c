//! NeRF / nerfstudio / instant-ngp `transforms.json`: our export format for generated worlds.
//!
//! Written keys: `camera_model: "OPENCV"`, `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, zero
//! distortion `k1 k2 p1 p2`, `camera_angle_x` / `camera_angle_y` (instant-ngp),
//! `integer_depth_scale` (metres per unit of 16-bit depth PNGs, instant-ngp), and per frame
//! `file_path` (colour), `depth_file_path` (nerfstudio) and `depth_path` (instant-ngp) relative to
//! the json's folder, `transform_matrix` (OpenGL camera-to-world: camera looks down -z, +y up),
//! and optional per-frame intrinsics.
//!
//! Principal point: nerfstudio and instant-ngp cast pixel `(u, v)`'s ray through
//! `(u + 0.5, v + 0.5)` (pixel-edge convention), we through `(u, v)` (OpenCV), so the json stores
//! `cx + 0.5`, `cy + 0.5` and the reader subtracts it back. Depth PNGs are planar millimetres;
//! depth `.npy` files are planar metres.

use std::path::Path;

use serde::{Deserialize, Serialize};
use sgam_core::{Intrinsics, Rigid3};

use crate::clevr::matrix_rows;
use crate::{write_atomic, IoError};

/// Half a pixel: the json's principal point minus ours.
const PIXEL_EDGE_OFFSET: f32 = 0.5;

/// One frame of a NeRF-style `transforms.json`.
#[derive(Debug, Clone, PartialEq)]
pub struct NerfFrame {
    /// Colour image, relative to the json's folder (e.g. `rgb/00000.png`).
    pub file_path: String,
    /// Depth image relative to the json's folder: `.png` (16-bit planar millimetres) or `.npy`
    /// (float planar metres).
    pub depth_file_path: Option<String>,
    /// Camera-to-world, OpenCV axes (stored as OpenGL in the file).
    pub world_from_camera: Rigid3,
    /// Per-frame intrinsics overriding the global ones.
    pub intrinsics: Option<Intrinsics>,
}

/// The content of a NeRF-style `transforms.json`.
#[derive(Debug, Clone, PartialEq)]
pub struct NerfTransforms {
    /// Global intrinsics (OpenCV principal point convention).
    pub intrinsics: Intrinsics,
    /// Frames in file order.
    pub frames: Vec<NerfFrame>,
    /// Metres per unit of 16-bit depth PNGs (`integer_depth_scale`); `0.001` for millimetres.
    pub depth_png_metres_per_unit: f64,
}

impl NerfTransforms {
    /// The intrinsics of frame `i` (per-frame if given, else global).
    pub fn frame_intrinsics(&self, i: usize) -> Intrinsics {
        self.frames.get(i).and_then(|f| f.intrinsics).unwrap_or(self.intrinsics)
    }
}

#[derive(Debug, Default, Deserialize, Serialize)]
struct CameraJson {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    fl_x: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    fl_y: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    cx: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    cy: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    w: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    h: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    camera_angle_x: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    camera_angle_y: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    k1: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    k2: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    k3: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    k4: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    p1: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    p2: Option<f64>,
}

#[derive(Debug, Deserialize, Serialize)]
struct FrameJson {
    file_path: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    depth_file_path: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    depth_path: Option<String>,
    transform_matrix: Vec<Vec<f64>>,
    #[serde(flatten)]
    camera: CameraJson,
}

#[derive(Debug, Deserialize, Serialize)]
struct TransformsJson {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    camera_model: Option<String>,
    #[serde(flatten)]
    camera: CameraJson,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    integer_depth_scale: Option<f64>,
    frames: Vec<FrameJson>,
}

fn camera_json(k: &Intrinsics) -> CameraJson {
    let fov_y = 2.0 * (0.5 * k.height as f64 / k.fy as f64).atan();
    CameraJson {
        fl_x: Some(k.fx as f64),
        fl_y: Some(k.fy as f64),
        cx: Some(k.cx as f64 + PIXEL_EDGE_OFFSET as f64),
        cy: Some(k.cy as f64 + PIXEL_EDGE_OFFSET as f64),
        w: Some(k.width as f64),
        h: Some(k.height as f64),
        camera_angle_x: Some(k.fov_x_rad() as f64),
        camera_angle_y: Some(fov_y),
        k1: Some(0.0),
        k2: Some(0.0),
        p1: Some(0.0),
        p2: Some(0.0),
        k3: None,
        k4: None,
    }
}

/// Writes a NeRF-style `transforms.json` (see the module docs for the keys), atomically.
pub fn write_nerf_transforms(path: &Path, transforms: &NerfTransforms) -> Result<(), IoError> {
    let global = &transforms.intrinsics;
    let json = TransformsJson {
        camera_model: Some("OPENCV".into()),
        camera: camera_json(global),
        integer_depth_scale: Some(transforms.depth_png_metres_per_unit),
        frames: transforms
            .frames
            .iter()
            .map(|f| FrameJson {
                file_path: f.file_path.clone(),
                depth_file_path: f.depth_file_path.clone(),
                depth_path: f.depth_file_path.clone(),
                transform_matrix: f.world_from_camera.to_opengl_camera().to_rows().iter().map(|r| r.to_vec()).collect(),
                camera: match &f.intrinsics {
                    Some(k) if k != global => camera_json(k),
                    _ => CameraJson::default(),
                },
            })
            .collect(),
    };
    write_atomic(path, |w| serde_json::to_writer_pretty(w, &json).map_err(std::io::Error::other))
}

/// Intrinsics from whatever subset of keys is present; `image_size` supplies `w`/`h` when the
/// json lacks them (read from the first image by the caller).
fn intrinsics_from_json(
    path: &Path,
    c: &CameraJson,
    fallback: Option<&Intrinsics>,
    image_size: &dyn Fn() -> Result<(u32, u32), IoError>,
    what: &str,
) -> Result<Option<Intrinsics>, IoError> {
    let distortion = [c.k1, c.k2, c.k3, c.k4, c.p1, c.p2];
    if distortion.iter().flatten().any(|d| *d != 0.0) {
        return Err(IoError::invalid(path, format!("{what}: lens distortion (k1..k4, p1, p2) is not supported")));
    }
    let has_any = c.fl_x.is_some() || c.fl_y.is_some() || c.camera_angle_x.is_some() || c.w.is_some();
    if !has_any {
        return Ok(None);
    }
    let (width, height) = match (c.w, c.h, fallback) {
        (Some(w), Some(h), _) => (w.round() as u32, h.round() as u32),
        (_, _, Some(k)) => (k.width, k.height),
        _ => image_size()?,
    };
    let fx = match (c.fl_x, c.camera_angle_x, fallback) {
        (Some(f), _, _) => f,
        (None, Some(a), _) => 0.5 * width as f64 / (0.5 * a).tan(),
        (None, None, Some(k)) => k.fx as f64,
        _ => return Err(IoError::format(path, format!("{what}: neither fl_x nor camera_angle_x"))),
    };
    let fy = match (c.fl_y, c.camera_angle_y, fallback) {
        (Some(f), _, _) => f,
        (None, Some(a), _) => 0.5 * height as f64 / (0.5 * a).tan(),
        (None, None, Some(k)) if c.fl_x.is_none() && c.camera_angle_x.is_none() => k.fy as f64,
        _ => fx,
    };
    let edge = PIXEL_EDGE_OFFSET as f64;
    let cx = c.cx.map(|v| v - edge).unwrap_or(width as f64 * 0.5 - edge);
    let cy = c.cy.map(|v| v - edge).unwrap_or(height as f64 * 0.5 - edge);
    Intrinsics::try_new(width, height, fx as f32, fy as f32, cx as f32, cy as f32)
        .map(Some)
        .map_err(|e| IoError::invalid(path, format!("{what}: {e}")))
}

/// Reads a NeRF-style `transforms.json` (ours, nerfstudio's or instant-ngp's). Intrinsics come
/// from `fl_x/fl_y/cx/cy/w/h`, else from `camera_angle_x` and the size of the first image (the
/// original NeRF Blender datasets); poses are converted from OpenGL to OpenCV and checked for
/// rigidity. Depth paths come from `depth_file_path` (nerfstudio) or `depth_path` (instant-ngp).
pub fn read_nerf_transforms(path: &Path) -> Result<NerfTransforms, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, e))?;
    let json: TransformsJson = serde_json::from_slice(&bytes)
        .map_err(|e| IoError::format(path, format!("not a NeRF transforms.json: {e}")))?;
    if let Some(model) = &json.camera_model {
        if !matches!(model.as_str(), "OPENCV" | "PINHOLE" | "SIMPLE_PINHOLE") {
            return Err(IoError::invalid(path, format!("camera_model {model} is not supported (use OPENCV/PINHOLE)")));
        }
    }
    let dir = path.parent().unwrap_or(Path::new("."));
    let first_image_size = || -> Result<(u32, u32), IoError> {
        let f = json.frames.first().ok_or_else(|| IoError::invalid(path, "no frames"))?;
        crate::images::image_size(&resolve_colour_path(dir, &f.file_path))
    };
    let global = intrinsics_from_json(path, &json.camera, None, &first_image_size, "global camera")?;
    let mut frames = Vec::with_capacity(json.frames.len());
    for (i, f) in json.frames.iter().enumerate() {
        let what = format!("frames[{i}] ({})", f.file_path);
        let own = intrinsics_from_json(path, &f.camera, global.as_ref(), &first_image_size, &what)?;
        let rows = matrix_rows(path, &f.transform_matrix, &what)?;
        let world_from_gl = crate::poses::rigid_from_rows(path, rows, &what)?;
        frames.push(NerfFrame {
            file_path: f.file_path.clone(),
            depth_file_path: f.depth_file_path.clone().or_else(|| f.depth_path.clone()),
            world_from_camera: Rigid3::from_opengl_camera(world_from_gl),
            intrinsics: own,
        });
    }
    let intrinsics = match global.or_else(|| frames.first().and_then(|f| f.intrinsics)) {
        Some(k) => k,
        None => return Err(IoError::format(path, "no intrinsics (fl_x/fl_y/cx/cy/w/h or camera_angle_x)")),
    };
    let depth_png_metres_per_unit = json.integer_depth_scale.unwrap_or(1e-3);
    if !(depth_png_metres_per_unit.is_finite() && depth_png_metres_per_unit > 0.0) {
        return Err(IoError::invalid(
            path,
            format!("integer_depth_scale {depth_png_metres_per_unit} must be positive"),
        ));
    }
    Ok(NerfTransforms { intrinsics, frames, depth_png_metres_per_unit })
}

/// The colour file of a frame: `file_path` relative to the json's folder; the original NeRF
/// datasets omit the extension (`./train/r_0`), then `.png` is appended.
pub(crate) fn resolve_colour_path(dir: &Path, file_path: &str) -> std::path::PathBuf {
    let p = dir.join(file_path);
    if p.extension().is_none() && !p.exists() {
        p.with_extension("png")
    } else {
        p
    }
}
