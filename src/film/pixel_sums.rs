//! Per-pixel sums of a box-filtered estimate, the camera-side accumulators of every film.

use super::Image;
use crate::geometry::Rgb;

/// Per-pixel f64 accumulators of a box-filtered estimate: sum, sum of squares, sample count.
/// Sums merge by addition, so tiles and sample ranges can be rendered apart and combined.
#[derive(Clone, Debug)]
pub struct PixelSums {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Per pixel (row-major), the sum of the sample values.
    pub sum: Vec<[f64; 3]>,
    /// Per pixel, the sum of the squared sample values (for variance).
    pub sum_sq: Vec<[f64; 3]>,
    /// Per pixel, the number of samples added.
    pub count: Vec<u32>,
}

impl PixelSums {
    /// Empty accumulators for `width` x `height` pixels.
    pub fn new(width: usize, height: usize) -> Self {
        PixelSums {
            width,
            height,
            sum: vec![[0.0; 3]; width * height],
            sum_sq: vec![[0.0; 3]; width * height],
            count: vec![0; width * height],
        }
    }

    /// Adds one sample `v` to pixel `idx` (row-major index).
    #[inline]
    pub fn add(&mut self, idx: usize, v: Rgb) {
        let s = &mut self.sum[idx];
        let q = &mut self.sum_sq[idx];
        let v = [v.x as f64, v.y as f64, v.z as f64];
        for c in 0..3 {
            s[c] += v[c];
            q[c] += v[c] * v[c];
        }
        self.count[idx] += 1;
    }

    /// The mean image.
    pub fn mean(&self) -> Image {
        let mut img = Image::new(self.width, self.height);
        for (i, p) in img.pixels.iter_mut().enumerate() {
            let n = self.count[i].max(1) as f64;
            let s = self.sum[i];
            *p = Rgb::new((s[0] / n) as f32, (s[1] / n) as f32, (s[2] / n) as f32);
        }
        img
    }

    /// Per-pixel variance of the mean estimate (sample variance / n), per channel.
    pub fn variance_of_mean(&self) -> Image {
        let mut img = Image::new(self.width, self.height);
        for (i, p) in img.pixels.iter_mut().enumerate() {
            let n = self.count[i] as f64;
            if n < 2.0 {
                continue;
            }
            let mut v = [0.0f32; 3];
            for (c, out) in v.iter_mut().enumerate() {
                let m = self.sum[i][c] / n;
                let var = ((self.sum_sq[i][c] / n - m * m) * n / (n - 1.0)).max(0.0);
                *out = (var / n) as f32;
            }
            *p = Rgb::from_array(v);
        }
        img
    }
}
