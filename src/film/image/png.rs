//! 8-bit sRGB PNG previews.

use super::Image;
use crate::geometry::colour::linear_to_srgb;
use std::path::{Path, PathBuf};

/// Why a PNG could not be encoded or written.
#[derive(Debug, thiserror::Error)]
pub enum PngError {
    /// Writing the file failed.
    #[error("{}: cannot write PNG: {source}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The image crate's error.
        #[source]
        source: image::ImageError,
    },
    /// Encoding in memory failed.
    #[error("cannot encode PNG: {0}")]
    Encode(#[source] image::ImageError),
}

/// For callers whose errors are messages.
impl From<PngError> for String {
    fn from(e: PngError) -> String {
        e.to_string()
    }
}

/// Tone maps linear radiance to 8-bit sRGB: scale by 2^exposure, clamp to [0, 1], sRGB encode.
pub fn to_srgb8(img: &Image, exposure: f32) -> Vec<u8> {
    let k = exposure.exp2();
    let table = Srgb8::get();
    // Into a sized buffer, three codes per pixel, with no capacity check per value.
    let mut out = vec![0u8; img.pixels.len() * 3];
    for (o, p) in out.chunks_exact_mut(3).zip(&img.pixels) {
        for c in 0..3 {
            o[c] = table.code(p[c] * k);
        }
    }
    out
}

/// The 8-bit sRGB code of a linear value (non-finite: 0; clamped to [0, 1]), rounded to nearest:
/// what `linear_to_srgb(v) * 255 + 0.5` truncates to, without a `powf` per value.
pub fn srgb8(v: f32) -> u8 {
    let v = if v.is_finite() {
        v.clamp(0.0, 1.0)
    } else {
        0.0
    };
    (linear_to_srgb(v) * 255.0 + 0.5) as u8
}

/// `srgb8` by table. It is a step function of the value: `first[i]` is the code of i / 4096 and
/// `up[k]` the least value whose code is k or more, so a value's code is its 4096th's first code,
/// stepped up past the thresholds it reaches (at most one: no 4096th holds two of them).
struct Srgb8 {
    first: Vec<u8>,
    up: [f32; 257],
}

impl Srgb8 {
    const STEPS: usize = 4096;

    fn get() -> &'static Srgb8 {
        static TABLE: std::sync::OnceLock<Srgb8> = std::sync::OnceLock::new();
        TABLE.get_or_init(|| {
            let mut up = [f32::INFINITY; 257];
            up[0] = 0.0;
            for (k, t) in up.iter_mut().enumerate().take(256).skip(1) {
                // The least value of [0, 1] (by its bits: they order non-negative floats)
                // whose code is at least k.
                let (mut lo, mut hi) = (0u32, 1f32.to_bits());
                while lo < hi {
                    let mid = lo + (hi - lo) / 2;
                    if srgb8(f32::from_bits(mid)) as usize >= k {
                        hi = mid;
                    } else {
                        lo = mid + 1;
                    }
                }
                *t = f32::from_bits(lo);
            }
            let first = (0..=Self::STEPS)
                .map(|i| srgb8(i as f32 / Self::STEPS as f32))
                .collect();
            Srgb8 { first, up }
        })
    }

    #[inline]
    fn code(&self, v: f32) -> u8 {
        let v = if v.is_finite() {
            v.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let k = self.first[(v * Self::STEPS as f32) as usize];
        k + (v >= self.up[k as usize + 1]) as u8
    }
}

/// Writes already-encoded 8-bit RGB data.
pub fn write_rgb8(path: &Path, width: usize, height: usize, data: &[u8]) -> Result<(), PngError> {
    image::save_buffer(
        path,
        data,
        width as u32,
        height as u32,
        image::ExtendedColorType::Rgb8,
    )
    .map_err(|source| PngError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// PNG bytes in memory (for previews served over HTTP).
pub fn encode_rgb8(width: usize, height: usize, data: &[u8]) -> Result<Vec<u8>, PngError> {
    let mut buf = std::io::Cursor::new(Vec::new());
    image::write_buffer_with_format(
        &mut buf,
        data,
        width as u32,
        height as u32,
        image::ExtendedColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .map_err(PngError::Encode)?;
    Ok(buf.into_inner())
}

/// Tone maps `img` with `exposure` (see [`to_srgb8`]) and writes it as a PNG.
pub fn write_png(path: &Path, img: &Image, exposure: f32) -> Result<(), PngError> {
    write_rgb8(path, img.width, img.height, &to_srgb8(img, exposure))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_gives_the_transfer_functions_codes() {
        let table = Srgb8::get();
        // Every 61st float of [0, 1] (17 million), the thresholds and their neighbours, and
        // what clamps.
        let mut bits = 0u32;
        while bits <= 1f32.to_bits() {
            let v = f32::from_bits(bits);
            assert_eq!(table.code(v), srgb8(v), "{v:e}");
            bits += 61;
        }
        for &t in &table.up[1..256] {
            for v in [
                t,
                f32::from_bits(t.to_bits() - 1),
                f32::from_bits(t.to_bits() + 1),
            ] {
                assert_eq!(table.code(v), srgb8(v), "{v:e}");
            }
        }
        for v in [
            -1.0,
            -0.0,
            1.0,
            2.0,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            1e-45,
        ] {
            assert_eq!(table.code(v), srgb8(v), "{v:e}");
        }
        assert_eq!((table.code(0.0), table.code(1.0)), (0, 255));
        // At most one threshold in a 4096th (above its first value), so one step up suffices.
        for i in 0..Srgb8::STEPS {
            let (lo, hi) = (i as f32 / 4096.0, (i + 1) as f32 / 4096.0);
            let inside = table.up[1..256]
                .iter()
                .filter(|&&t| t > lo && t < hi)
                .count();
            assert!(inside <= 1, "{inside} thresholds in [{lo}, {hi})");
        }
    }
}
