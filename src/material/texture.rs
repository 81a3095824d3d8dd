//! Reflectance textures: a constant or a bitmap looked up by surface uv.

pub use crate::geometry::colour::{linear_to_srgb, srgb_to_linear};
use crate::geometry::{Rgb, Vec2};
use std::sync::Arc;

/// The most texels of a floating-point image a scene may use (12 bytes each in memory): an
/// 8K x 8K environment map. Other formats go through the `image` crate's own allocation limit.
pub const MAX_TEXELS: usize = 1 << 26;

/// An RGB image in linear space, rows top to bottom.
#[derive(Debug)]
pub struct Bitmap {
    /// Width in texels.
    pub width: usize,
    /// Height in texels.
    pub height: usize,
    texels: Texels,
}

/// 8-bit images keep their bytes and a 256-entry decoding table (a third of the memory of f32
/// texels, and the same values); deeper images keep f32.
#[derive(Debug)]
enum Texels {
    U8 {
        data: Vec<[u8; 3]>,
        table: Box<[f32; 256]>,
    },
    F32(Vec<Rgb>),
}

/// Why an image file cannot be read as a texture: the file and the reason.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{}: {reason}", path.display())]
pub struct TextureError {
    /// The image file.
    pub path: std::path::PathBuf,
    /// What is wrong with it (the decoder's message, or a limit).
    pub reason: String,
}

impl TextureError {
    fn new(path: &std::path::Path, reason: impl std::fmt::Display) -> TextureError {
        TextureError {
            path: path.to_path_buf(),
            reason: reason.to_string(),
        }
    }
}

impl Bitmap {
    /// Decodes an image file (PNG, JPEG, TGA, BMP) whose values are sRGB-encoded, to linear.
    pub fn load(path: &std::path::Path) -> Result<Bitmap, TextureError> {
        Bitmap::load_with(path, true)
    }

    /// Decodes an image file; `srgb` says whether its values are sRGB-encoded (converted to
    /// linear) or already linear (taken as stored, e.g. roughness or bump data).
    pub fn load_with(path: &std::path::Path, srgb: bool) -> Result<Bitmap, TextureError> {
        use image::ColorType;
        let exr = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("exr"));
        if exr {
            return Self::load_exr(path);
        }
        let img = image::open(path).map_err(|e| TextureError::new(path, e))?;
        let (w, h) = (img.width() as usize, img.height() as usize);
        if w == 0 || h == 0 {
            return Err(TextureError::new(path, "empty image"));
        }
        let decode = |v: f32| if srgb { srgb_to_linear(v) } else { v };
        let texels = match img.color() {
            ColorType::L8 | ColorType::La8 | ColorType::Rgb8 | ColorType::Rgba8 => {
                let mut table = Box::new([0.0f32; 256]);
                for (k, t) in table.iter_mut().enumerate() {
                    *t = decode(k as f32 / 255.0);
                }
                let data = img.to_rgb8().pixels().map(|p| p.0).collect();
                Texels::U8 { data, table }
            }
            _ => Texels::F32(
                img.to_rgb32f()
                    .pixels()
                    .map(|p| Rgb::new(decode(p[0]), decode(p[1]), decode(p[2])))
                    .collect(),
            ),
        };
        Ok(Bitmap {
            width: w,
            height: h,
            texels,
        })
    }

    /// An OpenEXR image's first RGB(A) layer, linear, its data window checked against the
    /// image limits first (a small file may claim a huge frame).
    fn load_exr(path: &std::path::Path) -> Result<Bitmap, TextureError> {
        use exr::prelude::*;
        let bad = |e: exr::error::Error| TextureError::new(path, e);
        let meta = exr::meta::MetaData::read_from_file(path, false).map_err(bad)?;
        let too_large = meta
            .headers
            .iter()
            .any(|h| h.layer_size.width().saturating_mul(h.layer_size.height()) > MAX_TEXELS);
        if too_large {
            return Err(TextureError::new(
                path,
                format!("more than {MAX_TEXELS} texels"),
            ));
        }
        let img = read_first_rgba_layer_from_file(
            path,
            |size, _| (size.width(), vec![Rgb::ZERO; size.width() * size.height()]),
            |(w, px): &mut (usize, Vec<Rgb>), pos, (r, g, b, _a): (f32, f32, f32, f32)| {
                px[pos.y() * *w + pos.x()] = Rgb::new(r, g, b);
            },
        )
        .map_err(bad)?;
        let size = img.layer_data.size;
        let (w, h) = (size.width(), size.height());
        if w == 0 || h == 0 {
            return Err(TextureError::new(path, "empty image"));
        }
        Ok(Bitmap {
            width: w,
            height: h,
            texels: Texels::F32(img.layer_data.channel_data.pixels.1),
        })
    }

    /// Every texel, linear, rows top to bottom.
    pub fn to_rgb(&self) -> Vec<Rgb> {
        self.texels().collect()
    }

    #[inline]
    fn texel(&self, i: usize) -> Rgb {
        match &self.texels {
            Texels::U8 { data, table } => {
                let [r, g, b] = data[i];
                Rgb::new(table[r as usize], table[g as usize], table[b as usize])
            }
            Texels::F32(t) => t[i],
        }
    }

    fn texels(&self) -> impl Iterator<Item = Rgb> + '_ {
        (0..self.width * self.height).map(|i| self.texel(i))
    }

    /// Largest value per channel.
    pub fn max(&self) -> Rgb {
        self.texels().fold(Rgb::ZERO, |m, t| m.max(t))
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
            return self.texel(0);
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
        let t = |i| self.texel(i);
        let a = t(ra + xa) * (1.0 - fx) + t(ra + xb) * fx;
        let b = t(rb + xa) * (1.0 - fx) + t(rb + xb) * fx;
        a * (1.0 - fy) + b * fy
    }

    /// Mean of all texels.
    pub fn average(&self) -> Rgb {
        let s: Rgb = self.texels().sum();
        s / (self.width * self.height) as f32
    }
}

/// A reflectance: constant, a bitmap looked up by uv, a checkerboard, or another texture seen
/// through a transform of its coordinates.
#[derive(Clone, Debug)]
pub enum Texture {
    /// The same value everywhere.
    Constant(Rgb),
    /// A bitmap, bilinearly filtered and wrapped, times `scale`.
    Bitmap {
        /// The texels.
        image: Arc<Bitmap>,
        /// A factor applied to every texel.
        scale: Rgb,
    },
    /// Mitsuba 3's `checkerboard`: two values in cells of half a unit of uv, `c0` in the cells
    /// where u and v (Mitsuba's, v running down the image) fall on the same side of 1/2.
    Checker {
        /// The value of the cells [0, 1/2)^2 and [1/2, 1)^2.
        c0: Rgb,
        /// The value of the others.
        c1: Rgb,
    },
    /// `inner` looked up at an affine transform of the coordinates, given as Mitsuba writes it
    /// (its `to_uv`: rows (a, b, c) and (d, e, f) acting on Mitsuba's uv, whose v is 1 - ours).
    Mapped {
        /// The texture looked up.
        inner: Box<Texture>,
        /// The transform's two rows.
        rows: [[f32; 3]; 2],
    },
}

impl Texture {
    /// The value at surface coordinates `uv`.
    #[inline]
    pub fn eval(&self, uv: Vec2) -> Rgb {
        match self {
            Texture::Constant(c) => *c,
            Texture::Bitmap { image, scale } => image.lookup(uv) * *scale,
            Texture::Checker { c0, c1 } => {
                let (u, v) = (uv.x, 1.0 - uv.y);
                let mx = u - u.floor() > 0.5;
                let my = v - v.floor() > 0.5;
                if mx == my { *c0 } else { *c1 }
            }
            Texture::Mapped { inner, rows } => {
                let (u, v) = (uv.x, 1.0 - uv.y);
                let [a, b] = rows;
                let u2 = a[0] * u + a[1] * v + a[2];
                let v2 = b[0] * u + b[1] * v + b[2];
                inner.eval(Vec2::new(u2, 1.0 - v2))
            }
        }
    }

    /// The texture times `s` everywhere.
    pub fn scaled(self, s: Rgb) -> Texture {
        match self {
            Texture::Constant(c) => Texture::Constant(c * s),
            Texture::Bitmap { image, scale } => Texture::Bitmap {
                image,
                scale: scale * s,
            },
            Texture::Checker { c0, c1 } => Texture::Checker {
                c0: c0 * s,
                c1: c1 * s,
            },
            Texture::Mapped { inner, rows } => Texture::Mapped {
                inner: Box::new(inner.scaled(s)),
                rows,
            },
        }
    }

    /// Mean value, used for light power and lobe-selection estimates.
    pub fn average(&self) -> Rgb {
        match self {
            Texture::Constant(c) => *c,
            Texture::Bitmap { image, scale } => image.average() * *scale,
            Texture::Checker { c0, c1 } => 0.5 * (*c0 + *c1),
            Texture::Mapped { inner, .. } => inner.average(),
        }
    }

    /// Largest value any lookup can return, per channel.
    pub fn max_value(&self) -> Rgb {
        match self {
            Texture::Constant(c) => *c,
            Texture::Bitmap { image, scale } => image.max() * *scale,
            Texture::Checker { c0, c1 } => c0.max(*c1),
            Texture::Mapped { inner, .. } => inner.max_value(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(path: &std::path::Path, img: image::DynamicImage) {
        img.save(path).expect("write test image");
    }

    #[test]
    fn eight_bit_and_sixteen_bit_images_decode_to_the_same_linear_values() {
        let dir = std::env::temp_dir().join(format!("omis-tex-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let p8 = dir.join("a8.png");
        let p16 = dir.join("a16.png");
        let mut a = image::RgbImage::new(2, 1);
        a.put_pixel(0, 0, image::Rgb([0, 128, 255]));
        a.put_pixel(1, 0, image::Rgb([10, 20, 30]));
        write(&p8, image::DynamicImage::ImageRgb8(a));
        let mut b = image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::new(2, 1);
        // 257 * v is v / 255 exactly in 16 bits.
        b.put_pixel(0, 0, image::Rgb([0, 128 * 257, 65535]));
        b.put_pixel(1, 0, image::Rgb([10 * 257, 20 * 257, 30 * 257]));
        write(&p16, image::DynamicImage::ImageRgb16(b));
        for srgb in [true, false] {
            let m8 = Bitmap::load_with(&p8, srgb).expect("8-bit");
            let m16 = Bitmap::load_with(&p16, srgb).expect("16-bit");
            assert!(matches!(m8.texels, Texels::U8 { .. }));
            assert!(matches!(m16.texels, Texels::F32(_)));
            for i in 0..2 {
                let (x, y) = (m8.texel(i), m16.texel(i));
                assert!((x - y).abs().max_element() < 1e-6, "{x:?} vs {y:?}");
            }
            let mid = m8.texel(0).y;
            let stored = 128.0 / 255.0;
            if srgb {
                assert_eq!(mid, srgb_to_linear(stored));
            } else {
                assert_eq!(mid, stored);
            }
        }
        assert_eq!(Bitmap::load(&p8).expect("load").max().z, 1.0);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
