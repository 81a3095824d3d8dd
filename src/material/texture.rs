//! Reflectance textures: a constant or a bitmap looked up by surface uv.

use crate::geometry::{Rgb, Vec2};
use std::sync::Arc;

/// An RGB image in linear space, rows top to bottom.
#[derive(Debug)]
pub struct Bitmap {
    pub width: usize,
    pub height: usize,
    pub texels: Vec<Rgb>,
}

impl Bitmap {
    /// Decodes an 8-bit image file (PNG, JPEG, TGA, BMP), converting sRGB to linear.
    pub fn load(path: &std::path::Path) -> Result<Bitmap, String> {
        let img = image::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
        let rgb = img.to_rgb32f();
        let (w, h) = (rgb.width() as usize, rgb.height() as usize);
        if w == 0 || h == 0 {
            return Err(format!("{}: empty image", path.display()));
        }
        let texels = rgb
            .pixels()
            .map(|p| {
                Rgb::new(
                    srgb_to_linear(p[0]),
                    srgb_to_linear(p[1]),
                    srgb_to_linear(p[2]),
                )
            })
            .collect();
        Ok(Bitmap {
            width: w,
            height: h,
            texels,
        })
    }

    /// `i` wrapped into [0, n) (repeat), as `i.rem_euclid(n)`; the division only when needed.
    #[inline]
    fn wrap(i: i64, n: usize) -> usize {
        if (0..n as i64).contains(&i) {
            i as usize
        } else {
            i.rem_euclid(n as i64) as usize
        }
    }

    /// Bilinear lookup with repeat wrapping; uv (0,0) is the bottom-left corner (OBJ convention).
    pub fn lookup(&self, uv: Vec2) -> Rgb {
        let x = uv.x * self.width as f32 - 0.5;
        let y = (1.0 - uv.y) * self.height as f32 - 0.5;
        if !x.is_finite() || !y.is_finite() {
            return self.texels[0];
        }
        let x0 = x.floor();
        let y0 = y.floor();
        let fx = x - x0;
        let fy = y - y0;
        let (x0, y0) = (x0 as i64, y0 as i64);
        // Wrapped columns and rows; x0 + 1 wraps to 0 exactly when x0 wraps to width - 1.
        let (w, h) = (self.width, self.height);
        let xa = Self::wrap(x0, w);
        let xb = if xa + 1 == w { 0 } else { xa + 1 };
        let ya = Self::wrap(y0, h);
        let yb = if ya + 1 == h { 0 } else { ya + 1 };
        let (ra, rb) = (ya * w, yb * w);
        let t = &self.texels;
        let a = t[ra + xa] * (1.0 - fx) + t[ra + xb] * fx;
        let b = t[rb + xa] * (1.0 - fx) + t[rb + xb] * fx;
        a * (1.0 - fy) + b * fy
    }

    pub fn average(&self) -> Rgb {
        let s: Rgb = self.texels.iter().copied().sum();
        s / self.texels.len() as f32
    }
}

/// IEC 61966-2-1 sRGB transfer function, inverted.
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

pub fn linear_to_srgb(c: f32) -> f32 {
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

#[derive(Clone, Debug)]
pub enum Texture {
    Constant(Rgb),
    Bitmap { image: Arc<Bitmap>, scale: Rgb },
}

impl Texture {
    #[inline]
    pub fn eval(&self, uv: Vec2) -> Rgb {
        match self {
            Texture::Constant(c) => *c,
            Texture::Bitmap { image, scale } => image.lookup(uv) * *scale,
        }
    }

    /// Mean value, used for light power and lobe-selection estimates.
    pub fn average(&self) -> Rgb {
        match self {
            Texture::Constant(c) => *c,
            Texture::Bitmap { image, scale } => image.average() * *scale,
        }
    }

    /// Largest value any lookup can return, per channel.
    pub fn max_value(&self) -> Rgb {
        match self {
            Texture::Constant(c) => *c,
            Texture::Bitmap { image, scale } => {
                image.texels.iter().fold(Rgb::ZERO, |m, t| m.max(*t)) * *scale
            }
        }
    }
}
