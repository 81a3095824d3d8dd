//! 8-bit sRGB PNG previews.

use super::Image;
use crate::material::texture::linear_to_srgb;
use std::path::Path;

/// Tone maps linear radiance to 8-bit sRGB: scale by 2^exposure, clamp to [0, 1], sRGB encode.
pub fn to_srgb8(img: &Image, exposure: f32) -> Vec<u8> {
    let k = exposure.exp2();
    let mut out = Vec::with_capacity(img.pixels.len() * 3);
    for p in &img.pixels {
        for c in 0..3 {
            let v = p[c] * k;
            let v = if v.is_finite() {
                v.clamp(0.0, 1.0)
            } else {
                0.0
            };
            out.push((linear_to_srgb(v) * 255.0 + 0.5) as u8);
        }
    }
    out
}

/// Writes already-encoded 8-bit RGB data.
pub fn write_rgb8(path: &Path, width: usize, height: usize, data: &[u8]) -> Result<(), String> {
    image::save_buffer(
        path,
        data,
        width as u32,
        height as u32,
        image::ExtendedColorType::Rgb8,
    )
    .map_err(|e| format!("{}: cannot write PNG: {e}", path.display()))
}

/// PNG bytes in memory (for previews served over HTTP).
pub fn encode_rgb8(width: usize, height: usize, data: &[u8]) -> Result<Vec<u8>, String> {
    let mut buf = std::io::Cursor::new(Vec::new());
    image::write_buffer_with_format(
        &mut buf,
        data,
        width as u32,
        height as u32,
        image::ExtendedColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .map_err(|e| format!("cannot encode PNG: {e}"))?;
    Ok(buf.into_inner())
}

/// Tone maps `img` with `exposure` (see [`to_srgb8`]) and writes it as a PNG.
pub fn write_png(path: &Path, img: &Image, exposure: f32) -> Result<(), String> {
    write_rgb8(path, img.width, img.height, &to_srgb8(img, exposure))
}
