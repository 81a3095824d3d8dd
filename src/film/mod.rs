//! The film: what samples accumulate into and how results leave a renderer. Per-task
//! accumulators (`TileFilm`), the whole frame's (`Film`) with merge and solve, their binary wire
//! format and checkpoints, images, EXR / PNG output, error metrics and plots.
//!
//! Integrators add samples to films; the render service moves, merges and stores films and
//! knows nothing of how the samples were made.

mod bands;
pub mod bf16;
pub mod exr_io;
mod film_tile;
mod frame;
pub mod layers;
pub mod merge;
pub mod metrics;
pub mod pack;
pub mod plot;
pub mod png;
mod tile;
mod tile_film;
pub mod wire;

pub use bands::{BandGroup, band_bytes, band_groups};
pub use film_tile::{FilmTile, Routed, TileGrid};
pub use frame::Film;
pub use layers::{
    FilmLayout, STRATEGY_DEPTH, STRATEGY_LAYERS, strategy_layer, strategy_layer_name,
};
pub use tile::Tile;
pub use tile_film::{LtRecords, RayStats, Splat, TileFilm};

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
}

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
