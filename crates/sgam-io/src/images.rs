//! Colour PNG/JPEG and 16-bit millimetre depth PNG.

use std::path::Path;

use image::codecs::png::PngEncoder;
use image::{DynamicImage, ImageBuffer, ImageReader, Luma, Rgb};
use sgam_core::{is_valid_depth, Image};

use crate::{write_atomic, IoError};

/// Raw value marking invalid depth in a 16-bit millimetre PNG besides `0` (7-Scenes / 3DMatch).
pub const DEPTH_PNG_INVALID_MAX: u16 = u16::MAX;
/// Largest millimetre value [`write_depth_png_mm`] stores (65534: 65535 means invalid).
pub const DEPTH_PNG_MAX_MM: u16 = u16::MAX - 1;

fn decode(path: &Path) -> Result<DynamicImage, IoError> {
    let reader = ImageReader::open(path).map_err(|e| IoError::io(path, e))?;
    let reader = reader.with_guessed_format().map_err(|e| IoError::io(path, e))?;
    reader.decode().map_err(|e| match e {
        image::ImageError::IoError(e) => IoError::io(path, e),
        e => IoError::format(path, format!("cannot decode image: {e}")),
    })
}

/// `(width, height)` of an image file, reading only its header.
pub fn image_size(path: &Path) -> Result<(u32, u32), IoError> {
    let reader = ImageReader::open(path).map_err(|e| IoError::io(path, e))?;
    let reader = reader.with_guessed_format().map_err(|e| IoError::io(path, e))?;
    reader.into_dimensions().map_err(|e| match e {
        image::ImageError::IoError(e) => IoError::io(path, e),
        e => IoError::format(path, format!("cannot read image header: {e}")),
    })
}

/// Reads a colour image (PNG or JPEG; format guessed from the content) as sRGB in `[0, 1]`.
/// 8-bit values `x` become `x / 255`; grey is replicated to three channels; alpha is dropped;
/// 16-bit images are reduced to 8 bits first (so every format reads the same way).
pub fn read_rgb(path: &Path) -> Result<Image<[f32; 3]>, IoError> {
    let rgb = decode(path)?.to_rgb8();
    let (width, height) = rgb.dimensions();
    let data = rgb.pixels().map(|p| p.0.map(|c| c as f32 / 255.0)).collect();
    Ok(Image { width, height, data })
}

/// Converts `[0, 1]` sRGB to 8 bits: clamped, rounded to nearest; non-finite values become 0.
pub fn to_srgb8(c: f32) -> u8 {
    if c.is_finite() {
        (c.clamp(0.0, 1.0) * 255.0).round() as u8
    } else {
        0
    }
}

fn check_len<T>(path: &Path, img: &Image<T>) -> Result<(), IoError> {
    if img.data.len() != img.width as usize * img.height as usize || img.data.is_empty() {
        return Err(IoError::invalid(
            path,
            format!("cannot write a {}x{} image holding {} values", img.width, img.height, img.data.len()),
        ));
    }
    Ok(())
}

/// Writes sRGB `[0, 1]` colour as an 8-bit RGB PNG (values rounded with [`to_srgb8`]), atomically.
pub fn write_rgb_png(path: &Path, colour: &Image<[f32; 3]>) -> Result<(), IoError> {
    check_len(path, colour)?;
    let raw: Vec<u8> = colour.data.iter().flat_map(|p| p.map(to_srgb8)).collect();
    let buf = ImageBuffer::<Rgb<u8>, _>::from_raw(colour.width, colour.height, raw)
        .ok_or_else(|| IoError::invalid(path, "image buffer size mismatch"))?;
    write_atomic(path, |w| buf.write_with_encoder(PngEncoder::new(w)).map_err(std::io::Error::other))
}

/// Reads a 16-bit single-channel PNG of depth in millimetres (7-Scenes / 3DMatch / our
/// exports) as planar depth in metres. Raw `0` and `65535` are invalid and become `0.0`.
/// 8-bit or multi-channel PNGs are rejected (they cannot hold millimetre depth).
pub fn read_depth_png_mm(path: &Path) -> Result<Image<f32>, IoError> {
    read_depth_png_scaled(path, 1e-3)
}

/// Like [`read_depth_png_mm`] with another scale: depth_m = raw * `metres_per_unit`.
pub fn read_depth_png_scaled(path: &Path, metres_per_unit: f64) -> Result<Image<f32>, IoError> {
    let img = match decode(path)? {
        DynamicImage::ImageLuma16(b) => b,
        other => {
            return Err(IoError::format(
                path,
                format!("expected a 16-bit single-channel depth PNG, found {:?}", other.color()),
            ))
        }
    };
    let (width, height) = img.dimensions();
    let data = img
        .pixels()
        .map(|p| match p.0[0] {
            0 | DEPTH_PNG_INVALID_MAX => 0.0,
            raw => (raw as f64 * metres_per_unit) as f32,
        })
        .collect();
    Ok(Image { width, height, data })
}

/// Converts planar depth (metres) to a millimetre PNG value: invalid depth ([`is_valid_depth`])
/// becomes `0`; valid depth is rounded to the nearest millimetre and clamped to
/// `1..=65534` (so valid stays valid and nothing collides with the 65535 marker).
pub fn depth_to_mm(depth_m: f32) -> u16 {
    if is_valid_depth(depth_m) {
        (depth_m as f64 * 1000.0).round().clamp(1.0, DEPTH_PNG_MAX_MM as f64) as u16
    } else {
        0
    }
}

/// Writes planar depth (metres) as a 16-bit millimetre PNG with [`depth_to_mm`], atomically.
pub fn write_depth_png_mm(path: &Path, depth_m: &Image<f32>) -> Result<(), IoError> {
    check_len(path, depth_m)?;
    let raw: Vec<u16> = depth_m.data.iter().map(|d| depth_to_mm(*d)).collect();
    let buf = ImageBuffer::<Luma<u16>, _>::from_raw(depth_m.width, depth_m.height, raw)
        .ok_or_else(|| IoError::invalid(path, "image buffer size mismatch"))?;
    write_atomic(path, |w| buf.write_with_encoder(PngEncoder::new(w)).map_err(std::io::Error::other))
}
