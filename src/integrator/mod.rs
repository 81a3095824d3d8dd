//! Integrators and the tile loop that drives them.
//!
//! Work is cut into tiles; each tile renders its pixels' samples [s0, s1) into tile-local f64
//! accumulators. Every random number comes from (seed, pixel, sample index), so the image does
//! not depend on the number of threads or the order in which tiles finish.

pub mod path;

use crate::film::PixelSums;
use crate::geometry::{Rgb, Vec2};
use crate::sampler::{SamplerKind, Stream};
use crate::scene::Scene;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::time::Instant;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum, Default)]
#[serde(rename_all = "lowercase")]
pub enum IntegratorKind {
    /// Unidirectional path tracing with NEE and MIS (power heuristic).
    #[default]
    Pt,
}

/// Everything besides the scene that determines the image.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct RenderSettings {
    pub integrator: IntegratorKind,
    pub spp: u32,
    pub max_depth: u32,
    pub seed: u64,
    pub sampler: SamplerKind,
    /// Path tracer only: how emitters are reached (MIS, or one strategy alone for validation).
    #[serde(default)]
    pub direct: path::DirectStrategy,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            integrator: IntegratorKind::Pt,
            spp: 16,
            max_depth: 5,
            seed: 0,
            sampler: SamplerKind::Sobol,
            direct: path::DirectStrategy::Mis,
        }
    }
}

/// Counters of work done.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct RayStats {
    /// Closest-hit queries.
    pub closest: u64,
    /// Occlusion (shadow) queries.
    pub shadow: u64,
    /// Pixel samples.
    pub samples: u64,
    /// Samples whose estimate was NaN or infinite (dropped to zero; should stay 0).
    pub non_finite: u64,
}

impl RayStats {
    pub fn add(&mut self, o: &RayStats) {
        self.closest += o.closest;
        self.shadow += o.shadow;
        self.samples += o.samples;
        self.non_finite += o.non_finite;
    }

    pub fn rays(&self) -> u64 {
        self.closest + self.shadow
    }
}

/// A rectangle of pixels [x0, x1) x [y0, y1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Hash)]
pub struct Tile {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl Tile {
    pub fn width(&self) -> usize {
        (self.x1 - self.x0) as usize
    }
    pub fn height(&self) -> usize {
        (self.y1 - self.y0) as usize
    }
    pub fn pixels(&self) -> usize {
        self.width() * self.height()
    }
}

/// Row-major tiles of at most `size` x `size` pixels covering the frame.
pub fn make_tiles(width: u32, height: u32, size: u32) -> Vec<Tile> {
    let size = size.max(1);
    let mut tiles = Vec::new();
    let mut y = 0;
    while y < height {
        let mut x = 0;
        while x < width {
            tiles.push(Tile {
                x0: x,
                y0: y,
                x1: (x + size).min(width),
                y1: (y + size).min(height),
            });
            x += size;
        }
        y += size;
    }
    tiles
}

/// Renders samples `samples` of every pixel of `tile` into `sums` (tile-sized, row-major).
pub fn render_tile(
    scene: &Scene,
    settings: &RenderSettings,
    tile: Tile,
    samples: Range<u32>,
    sums: &mut PixelSums,
    stats: &mut RayStats,
) {
    let cam = &scene.camera;
    for y in tile.y0..tile.y1 {
        for x in tile.x0..tile.x1 {
            let idx = (y - tile.y0) as usize * tile.width() + (x - tile.x0) as usize;
            for i in samples.clone() {
                let mut sampler = crate::sampler::Sampler::new(
                    settings.sampler,
                    settings.seed,
                    x,
                    y,
                    i,
                    settings.spp,
                    Stream::Camera,
                );
                let film = sampler.next_2d();
                let ray = cam.ray(Vec2::new(x as f32 + film.x, y as f32 + film.y));
                let mut l = match settings.integrator {
                    IntegratorKind::Pt => path::li(
                        scene,
                        ray,
                        &mut sampler,
                        settings.max_depth,
                        settings.direct,
                        stats,
                    ),
                };
                if !l.is_finite() {
                    stats.non_finite += 1;
                    l = Rgb::ZERO;
                }
                stats.samples += 1;
                sums.add(idx, l);
            }
        }
    }
}

/// The result of a whole-frame render.
pub struct RenderOutput {
    pub sums: PixelSums,
    pub stats: RayStats,
    pub seconds: f64,
}

/// Renders the whole frame on the current rayon pool, reporting each finished tile.
pub fn render(
    scene: &Scene,
    settings: &RenderSettings,
    tile_size: u32,
    progress: &(dyn Fn(usize) + Sync),
) -> RenderOutput {
    let start = Instant::now();
    let (w, h) = (scene.camera.width, scene.camera.height);
    let tiles = make_tiles(w, h, tile_size);
    let results: Vec<(Tile, PixelSums, RayStats)> = tiles
        .par_iter()
        .map(|&tile| {
            let mut sums = PixelSums::new(tile.width(), tile.height());
            let mut stats = RayStats::default();
            render_tile(
                scene,
                settings,
                tile,
                0..settings.spp,
                &mut sums,
                &mut stats,
            );
            progress(1);
            (tile, sums, stats)
        })
        .collect();
    let mut frame = PixelSums::new(w as usize, h as usize);
    let mut stats = RayStats::default();
    for (tile, sums, s) in results {
        stats.add(&s);
        for ty in 0..tile.height() {
            for tx in 0..tile.width() {
                let src = ty * tile.width() + tx;
                let dst = (tile.y0 as usize + ty) * w as usize + tile.x0 as usize + tx;
                frame.sum[dst] = sums.sum[src];
                frame.sum_sq[dst] = sums.sum_sq[src];
                frame.count[dst] = sums.count[src];
            }
        }
    }
    RenderOutput {
        sums: frame,
        stats,
        seconds: start.elapsed().as_secs_f64(),
    }
}
