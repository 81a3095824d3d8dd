//! Images and what leaves a renderer as one: `Image` (linear RGB f32), EXR files written and
//! read (`exr_io`), 8-bit sRGB PNG previews (`png`), error metrics against a reference
//! (`metrics`), the error picture with its legend (`error_map`) and SVG charts (`plot`). It
//! knows nothing of how an image was accumulated.

pub mod error_map;
pub mod exr_io;
pub mod metrics;
pub mod plot;
pub mod png;

use crate::geometry::Rgb;

/// An RGB f32 image, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Row-major pixels, `width * height` of them.
    pub pixels: Vec<Rgb>,
}

impl Image {
    /// A black image of `width` x `height` pixels.
    pub fn new(width: usize, height: usize) -> Self {
        Image {
            width,
            height,
            pixels: vec![Rgb::ZERO; width * height],
        }
    }

    /// The pixel at column `x`, row `y`.
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> Rgb {
        self.pixels[y * self.width + x]
    }

    /// Sets the pixel at column `x`, row `y`.
    #[inline]
    pub fn set(&mut self, x: usize, y: usize, v: Rgb) {
        self.pixels[y * self.width + x] = v;
    }

    /// Mean over all pixels, in f64.
    pub fn mean(&self) -> [f64; 3] {
        let mut s = [0.0f64; 3];
        for p in &self.pixels {
            s[0] += p.x as f64;
            s[1] += p.y as f64;
            s[2] += p.z as f64;
        }
        let n = self.pixels.len().max(1) as f64;
        [s[0] / n, s[1] / n, s[2] / n]
    }

    /// Copies `src` into this image with its top-left corner at (x0, y0).
    pub fn blit(&mut self, src: &Image, x0: usize, y0: usize) {
        for y in 0..src.height {
            let row = &src.pixels[y * src.width..(y + 1) * src.width];
            let at = (y0 + y) * self.width + x0;
            self.pixels[at..at + src.width].copy_from_slice(row);
        }
    }
}
