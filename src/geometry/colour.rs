//! Colour encodings: the sRGB transfer function (IEC 61966-2-1), the one home of the conversion
//! that textures decode with and previews encode with.

/// IEC 61966-2-1 sRGB transfer function, inverted.
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// IEC 61966-2-1 sRGB transfer function (linear to encoded).
pub fn linear_to_srgb(c: f32) -> f32 {
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}
