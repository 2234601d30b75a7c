//! Seed RGB-D images that start a generated world.

use std::path::Path;

use sgam_core::{Camera, Image, Intrinsics, RgbdFrame, Rigid3};

use crate::depth::{read_depth_any, require_some_valid, sanitize_float_depth};
use crate::images::read_rgb;
use crate::sequence::{Layout, Sequence};
use crate::IoError;

/// Focal length of the SGAM Google Earth seeds at 512 px (pixels).
pub const GOOGLE_EARTH_FOCAL_PX_AT_512: f32 = 497.77774;

/// A posed RGB-D seed frame.
#[derive(Debug, Clone, PartialEq)]
pub struct SeedImage {
    /// Intrinsics (matching the frame's size) and `world_from_camera` (OpenCV).
    pub camera: Camera,
    /// Colour in `[0, 1]` and planar depth in metres (scene units).
    pub frame: RgbdFrame,
}

fn check_sizes(
    colour_path: &Path,
    depth_path: &Path,
    colour: &Image<[f32; 3]>,
    depth: &Image<f32>,
) -> Result<(), IoError> {
    if colour.size() != depth.size() {
        return Err(IoError::invalid(
            depth_path,
            format!(
                "depth is {}x{} but colour {} is {}x{}",
                depth.width,
                depth.height,
                colour_path.display(),
                colour.width,
                colour.height
            ),
        ));
    }
    Ok(())
}

/// Reads any RGB image with its depth: `.png` (16-bit millimetres; 0/65535 invalid) or `.npy`
/// (planar metres; NaN/inf/0/>=65504 invalid, negative is an error). The seed's pose is the
/// identity (it defines the world frame). When `intrinsics` are for another resolution with the
/// same aspect ratio (within 1 %), they are rescaled to the image; otherwise a size mismatch is
/// an error.
pub fn read_seed_rgbd(rgb: &Path, depth: &Path, intrinsics: Intrinsics) -> Result<SeedImage, IoError> {
    let colour = read_rgb(rgb)?;
    let depth_m = read_depth_any(depth)?;
    check_sizes(rgb, depth, &colour, &depth_m)?;
    require_some_valid(depth, &depth_m)?;
    let (w, h) = colour.size();
    let k = if (intrinsics.width, intrinsics.height) == (w, h) {
        intrinsics
    } else {
        let aspect_image = w as f64 / h as f64;
        let aspect_k = intrinsics.width as f64 / intrinsics.height.max(1) as f64;
        if (aspect_image / aspect_k - 1.0).abs() > 0.01 {
            return Err(IoError::invalid(
                rgb,
                format!(
                    "image is {w}x{h} but the intrinsics are for {}x{} (a different aspect ratio)",
                    intrinsics.width, intrinsics.height
                ),
            ));
        }
        intrinsics.resized(w, h)
    };
    Ok(SeedImage { camera: Camera::new(k, Rigid3::IDENTITY), frame: RgbdFrame { colour, depth_m } })
}

/// Reads the SGAM authors' CLEVR-Infinite template folder (`sgam-clevr-template`): its first
/// frame with an image (frame 0), ray-length depth converted to planar, pose from
/// `transforms.json` (Blender camera-to-world converted to OpenCV).
pub fn read_clevr_template(dir: &Path) -> Result<SeedImage, IoError> {
    let seq = Sequence::open(dir)?;
    if seq.layout != Layout::ClevrAuthors {
        return Err(IoError::invalid(
            dir,
            format!("expected a CLEVR-Infinite template, found the {:?} layout", seq.layout),
        ));
    }
    let frame = seq.read_frame(0)?;
    Ok(SeedImage { camera: seq.camera(0), frame })
}

/// Reads a SGAM Google Earth seed folder (`seedN/`): `im_00000.png`, `dm_00000.npy` (planar
/// depth in scene units, 65504 = sky/invalid); intrinsics fx = fy = 497.77774, cx = cy = 256 at
/// 512 px, scaled with the image size; identity pose (the seed defines the world frame).
pub fn read_google_earth_seed(dir: &Path) -> Result<SeedImage, IoError> {
    let rgb = dir.join("im_00000.png");
    let depth = dir.join("dm_00000.npy");
    if !rgb.exists() {
        refuse_seed_collection(dir)?;
    }
    let colour = read_rgb(&rgb)?;
    let mut depth_m = crate::read_npy_f32(&depth)?;
    sanitize_float_depth(&depth, &mut depth_m)?;
    check_sizes(&rgb, &depth, &colour, &depth_m)?;
    require_some_valid(&depth, &depth_m)?;
    let (w, h) = colour.size();
    let f = GOOGLE_EARTH_FOCAL_PX_AT_512;
    let k = Intrinsics::try_new(512, 512, f, f, 256.0, 256.0).map_err(|e| IoError::invalid(&rgb, e.to_string()))?;
    let k = k.resized(w, h);
    Ok(SeedImage { camera: Camera::new(k, Rigid3::IDENTITY), frame: RgbdFrame { colour, depth_m } })
}

/// A folder of Google Earth seeds (`seed0/`, `seed1/`, ... each with `im_00000.png` and
/// `dm_00000.npy`) given where
/// one seed's folder was expected: an error naming the seeds to choose from.
fn refuse_seed_collection(dir: &Path) -> Result<(), IoError> {
    let Ok(items) = std::fs::read_dir(dir) else { return Ok(()) };
    let mut seeds: Vec<String> = items
        .flatten()
        .filter(|e| e.path().join("im_00000.png").is_file() && e.path().join("dm_00000.npy").is_file())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    if seeds.is_empty() {
        return Ok(());
    }
    seeds.sort();
    let shown = seeds.iter().take(5).cloned().collect::<Vec<_>>().join(", ");
    let more = if seeds.len() > 5 { ", ..." } else { "" };
    Err(IoError::invalid(
        dir,
        format!(
            "holds {} Google Earth seed{} ({shown}{more}), not a seed itself: pass one of them, e.g. {}",
            seeds.len(),
            if seeds.len() == 1 { "" } else { "s" },
            dir.join(&seeds[0]).display()
        ),
    ))
}
