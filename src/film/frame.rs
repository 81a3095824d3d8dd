//! The whole frame's accumulators (pbrt-v4's `Film`): merge of task results, solve of the
//! optimal-MIS systems, the images and the EXR.

use super::layers::{FilmLayout, STRATEGY_LAYERS, strategy_layer_name};
use super::tile_film::{LtRecords, TileFilm};
use super::{Image, PixelSums};
use crate::geometry::Rgb;
use crate::mis::{OptimalAccum, SolveScratch};
use rayon::prelude::*;

/// Whole-frame accumulators: camera-side sums, light-tracing splats, strategy and depth layers,
/// optimal-MIS systems. Tasks' `TileFilm`s merge into it by addition; it solves and writes images.
pub struct Film {
    pub width: u32,
    pub height: u32,
    pub sums: PixelSums,
    pub splat: Vec<[f64; 3]>,
    /// STRATEGY_LAYERS per pixel when kept (camera and light-tracing parts together).
    pub layers: Vec<[f64; 3]>,
    /// Per-depth sums (camera side and splats together), `layout.depth_layers` per pixel.
    pub depths: Vec<[f64; 3]>,
    /// Optimal MIS systems of every pixel.
    pub optimal: Option<OptimalAccum>,
    /// What is accumulated (and the kappa the optimal systems are solved with).
    pub layout: FilmLayout,
}

impl Film {
    /// Empty accumulators of a `width` x `height` frame with the layers `layout` asks for.
    pub fn new(width: u32, height: u32, layout: &FilmLayout) -> Film {
        let n = (width * height) as usize;
        Film {
            width,
            height,
            sums: PixelSums::new(width as usize, height as usize),
            splat: vec![[0.0; 3]; n],
            layers: if layout.strategy_layers {
                vec![[0.0; 3]; n * STRATEGY_LAYERS]
            } else {
                Vec::new()
            },
            depths: vec![[0.0; 3]; n * layout.depth_layers],
            optimal: layout.optimal.clone().map(|l| OptimalAccum::new(l, n)),
            layout: layout.clone(),
        }
    }

    /// Light paths traced for the frame so far: one per pixel sample (N_L of the optimal-MIS
    /// systems; W H spp once every pass has covered the whole frame).
    pub fn light_paths(&self) -> u64 {
        self.sums.count.iter().map(|&c| c as u64).sum()
    }

    /// The image of each path depth 0 ..= max_depth (when depth layers are kept).
    pub fn depth_images(&self) -> Vec<Image> {
        let nd = self.layout.depth_layers;
        let light_paths = self.light_paths();
        (0..nd)
            .map(|d| {
                let mut img = Image::new(self.width as usize, self.height as usize);
                img.pixels.par_iter_mut().enumerate().for_each_init(
                    SolveScratch::default,
                    |scratch, (i, p)| {
                        let spp = self.sums.count[i];
                        let n = spp.max(1) as f64;
                        let s = self.depths[i * nd + d];
                        let mut v = [s[0] / n, s[1] / n, s[2] / n];
                        if let Some(o) = &self.optimal
                            && d >= 1
                            && d as u32 <= o.layout.d_opt
                        {
                            let f =
                                o.solve(i, d as u32, spp, light_paths, self.layout.kappa, scratch);
                            for c in 0..3 {
                                v[c] += f[c];
                            }
                        }
                        *p = Rgb::new(v[0] as f32, v[1] as f32, v[2] as f32);
                    },
                );
                img
            })
            .collect()
    }

    /// Adds a tile's results (order matters only for the last bits of the f64 sums).
    pub fn merge(&mut self, t: &TileFilm) {
        let w = self.width as usize;
        for ty in 0..t.tile.height() {
            for tx in 0..t.tile.width() {
                let src = ty * t.tile.width() + tx;
                let dst = (t.tile.y0 as usize + ty) * w + t.tile.x0 as usize + tx;
                for c in 0..3 {
                    self.sums.sum[dst][c] += t.sums.sum[src][c];
                    self.sums.sum_sq[dst][c] += t.sums.sum_sq[src][c];
                }
                self.sums.count[dst] += t.sums.count[src];
                if let (Some(o), Some(to)) = (self.optimal.as_mut(), t.optimal.as_ref()) {
                    o.add_pixel(dst, to, src);
                }
                let nd = self.layout.depth_layers;
                if nd > 0 && t.depths.len() == t.tile.pixels() * nd {
                    for k in 0..nd {
                        for c in 0..3 {
                            self.depths[dst * nd + k][c] += t.depths[src * nd + k][c];
                        }
                    }
                }
                if !self.layers.is_empty() && !t.layers.is_empty() {
                    for l in 0..STRATEGY_LAYERS {
                        for c in 0..3 {
                            self.layers[dst * STRATEGY_LAYERS + l][c] +=
                                t.layers[src * STRATEGY_LAYERS + l][c];
                        }
                    }
                }
            }
        }
        for s in &t.splats {
            let p = s.pixel as usize;
            for c in 0..3 {
                self.splat[p][c] += s.value[c] as f64;
            }
            if (s.depth as usize) < self.layout.depth_layers {
                let nd = self.layout.depth_layers;
                for c in 0..3 {
                    self.depths[p * nd + s.depth as usize][c] += s.value[c] as f64;
                }
            }
            if !self.layers.is_empty() && (s.layer as usize) < STRATEGY_LAYERS {
                for c in 0..3 {
                    self.layers[p * STRATEGY_LAYERS + s.layer as usize][c] += s.value[c] as f64;
                }
            }
        }
    }

    /// Adds a task's whole result: its tile and its out-of-tile light-tracing records.
    pub fn merge_task(&mut self, t: &TileFilm) {
        self.merge(t);
        self.apply_records(&t.records);
    }

    /// The EXR layers besides the beauty: the per-pixel variance of the mean (path tracer; BDPT's
    /// light-tracing splats have no per-pixel samples), strategy layers `s<S>_t<T>`, and depth
    /// layers `depth<d>`.
    pub fn extra_layers(&self) -> Vec<(String, Image)> {
        let mut layers = Vec::new();
        if self.layout.variance_layer {
            layers.push(("variance".to_string(), self.sums.variance_of_mean()));
        }
        layers.extend(self.strategy_images());
        layers.extend(
            self.depth_images()
                .into_iter()
                .enumerate()
                .map(|(d, img)| (format!("depth{d}"), img)),
        );
        layers
    }

    /// Writes the EXR of the frame (beauty and `extra_layers`) with `attributes` in its header;
    /// returns the beauty image.
    pub fn write_exr(
        &self,
        path: &std::path::Path,
        attributes: &[(&str, String)],
    ) -> Result<Image, String> {
        let image = self.image();
        let layers = self.extra_layers();
        let named: Vec<super::exr_io::NamedLayer> = layers
            .iter()
            .map(|(name, image)| super::exr_io::NamedLayer {
                name: name.clone(),
                image,
            })
            .collect();
        super::exr_io::write_exr(path, &image, &named, attributes)?;
        Ok(image)
    }

    /// Adds out-of-tile light-tracing records (frame pixel indices).
    pub fn apply_records(&mut self, r: &LtRecords) {
        if let Some(o) = self.optimal.as_mut() {
            r.apply(o, |p| Some(p as usize));
        }
    }

    /// The image: (camera sums + splats) / samples per pixel, plus the solved optimal depths.
    pub fn image(&self) -> Image {
        let mut img = Image::new(self.width as usize, self.height as usize);
        let light_paths = self.light_paths();
        // Pixels are independent: solved in parallel, the same bits as in sequence.
        img.pixels.par_iter_mut().enumerate().for_each_init(
            SolveScratch::default,
            |scratch, (i, p)| {
                let spp = self.sums.count[i];
                let n = spp.max(1) as f64;
                let s = self.sums.sum[i];
                let l = self.splat[i];
                let mut v = [(s[0] + l[0]) / n, (s[1] + l[1]) / n, (s[2] + l[2]) / n];
                if let Some(o) = &self.optimal {
                    for d in 1..=o.layout.d_opt {
                        let f = o.solve(i, d, spp, light_paths, self.layout.kappa, scratch);
                        for c in 0..3 {
                            v[c] += f[c];
                        }
                    }
                }
                *p = Rgb::new(v[0] as f32, v[1] as f32, v[2] as f32);
            },
        );
        img
    }

    /// The strategy layers as (name, image) pairs.
    pub fn strategy_images(&self) -> Vec<(String, Image)> {
        if self.layers.is_empty() {
            return Vec::new();
        }
        (0..STRATEGY_LAYERS)
            .map(|l| {
                let mut img = Image::new(self.width as usize, self.height as usize);
                for (i, p) in img.pixels.iter_mut().enumerate() {
                    let n = self.sums.count[i].max(1) as f64;
                    let v = self.layers[i * STRATEGY_LAYERS + l];
                    *p = Rgb::new((v[0] / n) as f32, (v[1] / n) as f32, (v[2] / n) as f32);
                }
                (strategy_layer_name(l), img)
            })
            .collect()
    }
}
