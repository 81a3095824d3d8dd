//! The accumulators of one task: camera-side sums of a tile's own pixels, light-tracing splats
//! that may land anywhere in the frame, optional strategy / depth layers and optimal-MIS systems,
//! and the work counters. Integrators add samples to it; the wire format ships it; a `Film`
//! merges it.

use super::layers::{FilmLayout, STRATEGY_LAYERS};
use super::{PixelSums, Tile};
use crate::mis::OptimalAccum;
use serde::{Deserialize, Serialize};

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
    /// Adds another task's counters.
    pub fn add(&mut self, o: &RayStats) {
        self.closest += o.closest;
        self.shadow += o.shadow;
        self.samples += o.samples;
        self.non_finite += o.non_finite;
    }

    /// Rays traced (closest-hit and occlusion queries).
    pub fn rays(&self) -> u64 {
        self.closest + self.shadow
    }
}

/// A light-tracing contribution to any pixel of the frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Splat {
    /// Pixel index y * width + x in the frame.
    pub pixel: u32,
    /// Strategy layer, or u8::MAX when the technique's depth is not kept as a layer.
    pub layer: u8,
    /// Path depth.
    pub depth: u8,
    pub value: [f32; 3],
}

/// What a tile task produces: camera-side sums of its own pixels, splats anywhere.
pub struct TileFilm {
    pub tile: Tile,
    /// Per pixel of the tile, the sum over its samples of the camera-side estimate (for the path
    /// tracer: the whole estimate).
    pub sums: PixelSums,
    pub splats: Vec<Splat>,
    /// Strategy layers of the tile's pixels (pixel-major, STRATEGY_LAYERS each), when requested.
    pub layers: Vec<[f64; 3]>,
    /// Per-depth camera-side sums of the tile's pixels (pixel-major, depth_count each), when
    /// requested.
    pub depths: Vec<[f64; 3]>,
    /// Optimal MIS: the systems of the tile's pixels.
    pub optimal: Option<OptimalAccum>,
    /// Optimal MIS: light-tracing samples that landed outside the tile.
    pub records: LtRecords,
    pub stats: RayStats,
}

impl TileFilm {
    /// Empty accumulators of `tile` with the layers `layout` asks for.
    pub fn new(tile: Tile, layout: &FilmLayout) -> TileFilm {
        TileFilm {
            tile,
            sums: PixelSums::new(tile.width(), tile.height()),
            splats: Vec::new(),
            layers: if layout.strategy_layers {
                vec![[0.0; 3]; tile.pixels() * STRATEGY_LAYERS]
            } else {
                Vec::new()
            },
            depths: vec![[0.0; 3]; tile.pixels() * layout.depth_layers],
            optimal: layout
                .optimal
                .clone()
                .map(|l| OptimalAccum::new(l, tile.pixels())),
            records: LtRecords::default(),
            stats: RayStats::default(),
        }
    }
}

/// Light-tracing samples for optimal MIS, for pixels of other tiles: pixel (frame index), depth,
/// and d + 2 weights followed by C W_s (3 values), as f32.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LtRecords {
    pub pixels: Vec<u32>,
    pub depths: Vec<u8>,
    pub values: Vec<f32>,
}

impl LtRecords {
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    pub(crate) fn push(&mut self, pixel: u32, depth: u32, w: &[f32], c: [f32; 3]) {
        self.pixels.push(pixel);
        self.depths.push(depth as u8);
        self.values.extend_from_slice(w);
        self.values.extend_from_slice(&c);
    }

    /// Adds every record into `acc`, whose pixel i is frame pixel `map(i)`.
    pub fn apply(&self, acc: &mut OptimalAccum, map: impl Fn(u32) -> Option<usize>) {
        let mut w = [0.0f64; 64];
        let mut off = 0;
        for (k, &p) in self.pixels.iter().enumerate() {
            let d = self.depths[k] as u32;
            let n = d as usize + 2;
            let vals = &self.values[off..off + n + 3];
            off += n + 3;
            if let Some(i) = map(p) {
                for (dst, src) in w.iter_mut().zip(&vals[..n]) {
                    *dst = *src as f64;
                }
                let c = [vals[n] as f64, vals[n + 1] as f64, vals[n + 2] as f64];
                acc.add_sample(i, d, &w[..n], c);
                acc.add_hit(i, d);
            }
        }
    }
}
