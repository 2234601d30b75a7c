//! Input packing: RGB-D frames + missing mask <-> network tensors.
//!
//! Input tensor `[B, 5, H, W]`: channels 0..3 = sRGB mapped to `[-1, 1]` (`2 c - 1`), channel 3 =
//! normalised disparity `2 s - 1` with `s = (1/(z+offset) - 1/far) / (1/near - 1/far)` (not
//! clipped on input), channel 4 = mask (1 = missing). At a missing pixel, or where depth is
//! invalid, the disparity channel is `-2`; at a missing pixel the colour channels are `0`
//! (mid-grey), so a missing pixel carries no information but the mask.
//!
//! Output tensor `[B, 4, H, W]`: the same first four channels; [`unpack`] inverts the mapping and
//! clips colour to `[0, 1]` and `s` to `[0, 1]`, so depth lies in `[near, far] - offset`.

use burn::tensor::{Device, Tensor, TensorData};
use sgam_core::{is_valid_depth, Image, Intrinsics, RgbdFrame};

use crate::config::{DepthCoding, ModelConfig};
use crate::ModelError;

/// Disparity channel value at missing / invalid pixels.
pub const MISSING_DISPARITY: f32 = -2.0;

impl DepthCoding {
    /// Planar depth (metres) -> channel value `2 s - 1`; `-2` for invalid depth.
    pub fn encode(&self, depth_m: f32) -> f32 {
        let z = depth_m + self.offset_m;
        if !is_valid_depth(depth_m) || z <= 0.0 {
            return MISSING_DISPARITY;
        }
        let s = (1.0 / z - 1.0 / self.far_m) / (1.0 / self.near_m - 1.0 / self.far_m);
        2.0 * s - 1.0
    }

    /// Channel value -> planar depth (metres), with `s` clipped to `[0, 1]`.
    pub fn decode(&self, c: f32) -> f32 {
        let s = ((c + 1.0) * 0.5).clamp(0.0, 1.0);
        let inv = s * (1.0 / self.near_m - 1.0 / self.far_m) + 1.0 / self.far_m;
        1.0 / inv - self.offset_m
    }
}

/// Packs frames and their missing masks (row-major, `true` = missing; `None` = nothing missing)
/// into row-major `[B, 5, H, W]` values. All frames must share one size.
pub fn pack_values(
    frames: &[&RgbdFrame],
    missing: &[Option<&[bool]>],
    coding: &DepthCoding,
) -> Result<(Vec<f32>, [usize; 4]), ModelError> {
    let Some(first) = frames.first() else {
        return Err(ModelError::EmptyBatch("packing frames"));
    };
    let (w, h) = (first.width() as usize, first.height() as usize);
    let hw = w * h;
    let mut out = vec![0.0f32; frames.len() * 5 * hw];
    for (b, frame) in frames.iter().enumerate() {
        if frame.width() as usize != w || frame.height() as usize != h || frame.depth_m.len() != hw {
            return Err(ModelError::shape(
                "a frame of the batch",
                format!("{w}x{h} (the first frame's size)"),
                format!("{}x{} (frame {b})", frame.width(), frame.height()),
            ));
        }
        let mask = missing.get(b).copied().flatten();
        if let Some(m) = mask {
            if m.len() != hw {
                return Err(ModelError::shape(
                    "a missing mask",
                    format!("{hw} values for {w}x{h}"),
                    format!("{} (mask {b})", m.len()),
                ));
            }
        }
        let base = b * 5 * hw;
        for i in 0..hw {
            let miss = mask.is_some_and(|m| m[i]);
            let rgb = frame.colour.data[i];
            for c in 0..3 {
                out[base + c * hw + i] = if miss { 0.0 } else { 2.0 * rgb[c] - 1.0 };
            }
            out[base + 3 * hw + i] = if miss { MISSING_DISPARITY } else { coding.encode(frame.depth_m.data[i]) };
            out[base + 4 * hw + i] = if miss { 1.0 } else { 0.0 };
        }
    }
    Ok((out, [frames.len(), 5, h, w]))
}

/// Packs frames + masks into a `[B, 5, H, W]` tensor on `device` (see [`pack_values`]).
pub fn pack(
    frames: &[&RgbdFrame],
    missing: &[Option<&[bool]>],
    coding: &DepthCoding,
    device: &Device,
) -> Result<Tensor<4>, ModelError> {
    let (values, shape) = pack_values(frames, missing, coding)?;
    Ok(Tensor::from_data(TensorData::new(values, shape), device))
}

/// Packs frames + masks into the network input of `config`: the 5 channels of [`pack`], and
/// when [`ModelConfig::ray_channels`] is set two more, each pixel's viewing ray
/// `2 (u - cx) / fx`, `2 (v - cy) / fy` from `intrinsics` (one per frame; a crop's intrinsics
/// carry its shifted principal point). Result `[B, 5 or 7, H, W]`.
pub fn pack_input(
    frames: &[&RgbdFrame],
    missing: &[Option<&[bool]>],
    intrinsics: &[Intrinsics],
    config: &ModelConfig,
    device: &Device,
) -> Result<Tensor<4>, ModelError> {
    let (values, shape) = pack_input_values(frames, missing, intrinsics, config)?;
    Ok(Tensor::from_data(TensorData::new(values, shape), device))
}

/// [`pack_input`]'s values on the host (row-major) and their shape.
pub fn pack_input_values(
    frames: &[&RgbdFrame],
    missing: &[Option<&[bool]>],
    intrinsics: &[Intrinsics],
    config: &ModelConfig,
) -> Result<(Vec<f32>, [usize; 4]), ModelError> {
    let (values, shape) = pack_values(frames, missing, &config.depth)?;
    if !config.ray_channels {
        return Ok((values, shape));
    }
    let [b, _, h, w] = shape;
    if intrinsics.len() != b {
        return Err(ModelError::shape("the intrinsics", format!("one per frame, {b}"), intrinsics.len()));
    }
    let hw = h * w;
    let mut out = Vec::with_capacity(b * 7 * hw);
    for (i, k) in intrinsics.iter().enumerate() {
        out.extend_from_slice(&values[i * 5 * hw..(i + 1) * 5 * hw]);
        out.extend((0..hw).map(|p| 2.0 * ((p % w) as f32 - k.cx) / k.fx));
        out.extend((0..hw).map(|p| 2.0 * ((p / w) as f32 - k.cy) / k.fy));
    }
    Ok((out, [b, 7, h, w]))
}

/// Packs target frames into the 4-channel `[B, 4, H, W]` training target (no mask channel;
/// invalid depth becomes `-2`).
pub fn pack_target(frames: &[&RgbdFrame], coding: &DepthCoding, device: &Device) -> Result<Tensor<4>, ModelError> {
    let (values, [b, _, h, w]) = pack_values(frames, &[], coding)?;
    let hw = h * w;
    let mut out = Vec::with_capacity(b * 4 * hw);
    for i in 0..b {
        out.extend_from_slice(&values[i * 5 * hw..i * 5 * hw + 4 * hw]);
    }
    Ok(Tensor::from_data(TensorData::new(out, [b, 4, h, w]), device))
}

/// Inverts row-major `[B, 4, H, W]` values into frames, clipping to valid ranges.
pub fn unpack_values(values: &[f32], shape: [usize; 4], coding: &DepthCoding) -> Result<Vec<RgbdFrame>, ModelError> {
    let [b, c, h, w] = shape;
    let hw = h * w;
    if c != 4 || values.len() != b * 4 * hw {
        return Err(ModelError::shape(
            "an output to unpack",
            format!("{} values for [B, 4, H, W] = {shape:?}", b * 4 * hw),
            values.len(),
        ));
    }
    let mut frames = Vec::with_capacity(b);
    for i in 0..b {
        let base = i * 4 * hw;
        let colour: Vec<[f32; 3]> = (0..hw)
            .map(|p| std::array::from_fn(|ch| ((values[base + ch * hw + p] + 1.0) * 0.5).clamp(0.0, 1.0)))
            .collect();
        let depth: Vec<f32> = (0..hw).map(|p| coding.decode(values[base + 3 * hw + p])).collect();
        let colour = Image::try_from_vec(w as u32, h as u32, colour)
            .map_err(|e| ModelError::shape("an unpacked colour image", format!("{w}x{h}"), e))?;
        let depth = Image::try_from_vec(w as u32, h as u32, depth)
            .map_err(|e| ModelError::shape("an unpacked depth image", format!("{w}x{h}"), e))?;
        frames.push(RgbdFrame { colour, depth_m: depth });
    }
    Ok(frames)
}

/// Inverts a `[B, 4, H, W]` output tensor into frames (see [`unpack_values`]).
pub fn unpack(output: Tensor<4>, coding: &DepthCoding) -> Result<Vec<RgbdFrame>, ModelError> {
    let dims = output.dims();
    let values = output.into_data().try_to_vec_as::<f32>().map_err(|e| ModelError::TensorRead(format!("{e:?}")))?;
    unpack_values(&values, dims, coding)
}

/// Marks latent cells as missing: the `factor x factor` pixel cell is missing when more than
/// `threshold` (a fraction, e.g. 0.5 = "most") of its pixels are missing. Row-major `[h, w]`
/// with `h = H / factor`, `w = W / factor`.
pub fn missing_cells(missing: &[bool], width: usize, height: usize, factor: usize, threshold: f32) -> Vec<bool> {
    let (cw, ch) = (width / factor.max(1), height / factor.max(1));
    let mut out = vec![false; cw * ch];
    for cy in 0..ch {
        for cx in 0..cw {
            let mut n = 0usize;
            for y in cy * factor..(cy + 1) * factor {
                for x in cx * factor..(cx + 1) * factor {
                    n += missing.get(y * width + x).copied().unwrap_or(false) as usize;
                }
            }
            out[cy * cw + cx] = n as f32 > threshold * (factor * factor) as f32;
        }
    }
    out
}
