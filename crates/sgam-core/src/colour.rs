//! The sRGB transfer function, both ways (IEC 61966-2-1), on values in `[0, 1]`.

/// sRGB-encoded value in `[0, 1]` to linear (inputs are clamped to `[0, 1]` first).
pub fn srgb_to_linear(c: f32) -> f32 {
    let c = c.clamp(0.0, 1.0);
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear value in `[0, 1]` to sRGB encoding (inputs are clamped to `[0, 1]` first).
pub fn linear_to_srgb(c: f32) -> f32 {
    let c = c.clamp(0.0, 1.0);
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}
