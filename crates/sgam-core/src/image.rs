use serde::{Deserialize, Serialize};

use crate::CoreError;

/// True for a usable planar depth: finite and strictly positive.
#[inline]
pub fn is_valid_depth(depth_m: f32) -> bool {
    depth_m.is_finite() && depth_m > 0.0
}

/// The pixels of `depth` marked in `marked` (row-major, as long as the image; a short mask marks
/// nothing past its end) that hold a valid depth, in row-major order: `(u, v, index, depth)`.
/// The loop of every pass over a frame's invented pixels (flying pixels, free space, ground
/// prior).
pub(crate) fn marked_depths<'a>(
    depth: &'a Image<f32>,
    marked: &'a [bool],
) -> impl Iterator<Item = (u32, u32, usize, f32)> + 'a {
    let w = depth.width;
    depth
        .data
        .iter()
        .zip(marked)
        .enumerate()
        .filter(|&(_, (&d, &m))| m && is_valid_depth(d))
        .map(move |(i, (&d, _))| ((i as u32) % w, (i as u32) / w, i, d))
}

/// A row-major image `[H, W]` of `T`; pixel `(u, v)` is at index `v * width + u`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Image<T> {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height` values, row-major.
    pub data: Vec<T>,
}

impl<T: Clone> Image<T> {
    /// An image filled with `value`.
    pub fn filled(width: u32, height: u32, value: T) -> Self {
        Self { width, height, data: vec![value; width as usize * height as usize] }
    }
}

impl<T> Image<T> {
    /// Wraps row-major data, checking its length.
    pub fn try_from_vec(width: u32, height: u32, data: Vec<T>) -> Result<Self, CoreError> {
        if data.len() != width as usize * height as usize {
            return Err(CoreError::SizeMismatch(format!("{} values for a {width}x{height} image", data.len())));
        }
        Ok(Self { width, height, data })
    }

    /// The value at pixel `(u, v)`; panics out of range (use in loops over the image).
    #[inline]
    pub fn at(&self, u: u32, v: u32) -> &T {
        &self.data[v as usize * self.width as usize + u as usize]
    }

    /// Mutable value at pixel `(u, v)`.
    #[inline]
    pub fn at_mut(&mut self, u: u32, v: u32) -> &mut T {
        let w = self.width as usize;
        &mut self.data[v as usize * w + u as usize]
    }

    /// `(width, height)`.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// True for a 0-pixel image.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
}

/// One RGB-D frame: sRGB colour in `[0, 1]` and planar depth in metres, same size.
/// Invalid depth (see [`is_valid_depth`]) marks pixels without geometry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RgbdFrame {
    /// Colour, sRGB in `[0, 1]`.
    pub colour: Image<[f32; 3]>,
    /// Planar depth, metres; `0` / non-finite = invalid.
    pub depth_m: Image<f32>,
}

impl RgbdFrame {
    /// Pairs colour and depth, checking sizes.
    pub fn try_new(colour: Image<[f32; 3]>, depth_m: Image<f32>) -> Result<Self, CoreError> {
        if colour.size() != depth_m.size() {
            return Err(CoreError::SizeMismatch(format!(
                "colour is {}x{} but depth is {}x{}",
                colour.width, colour.height, depth_m.width, depth_m.height
            )));
        }
        Ok(Self { colour, depth_m })
    }

    /// A black frame with all depth invalid.
    pub fn empty(width: u32, height: u32) -> Self {
        Self { colour: Image::filled(width, height, [0.0; 3]), depth_m: Image::filled(width, height, 0.0) }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.colour.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.colour.height
    }

    /// Fraction of pixels with valid depth.
    pub fn valid_fraction(&self) -> f32 {
        let n = self.depth_m.data.iter().filter(|d| is_valid_depth(**d)).count();
        n as f32 / self.depth_m.len().max(1) as f32
    }
}
