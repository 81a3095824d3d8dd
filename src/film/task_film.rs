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
    /// The contribution (RGB radiance), already weighted.
    pub value: [f32; 3],
}

/// What a tile task produces: camera-side sums of its own pixels, splats anywhere.
#[derive(Clone)]
pub struct TaskFilm {
    /// The tile's pixel rectangle in the frame.
    pub tile: Tile,
    /// Per pixel of the tile, the sum over its samples of the camera-side estimate (for the path
    /// tracer: the whole estimate).
    pub sums: PixelSums,
    /// Light-tracing contributions, to any pixel of the frame.
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
    /// Work done by the task.
    pub stats: RayStats,
}

impl TaskFilm {
    /// Empty accumulators of `tile` with the layers `layout` asks for.
    pub fn new(tile: Tile, layout: &FilmLayout) -> TaskFilm {
        TaskFilm {
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

impl TaskFilm {
    /// Puts a finished task's splats and records in canonical form: splats summed per
    /// destination (pixel, and the strategy / depth layer when `layout` keeps it) in their order,
    /// sorted by pixel; records sorted by pixel, each pixel's records in their order. What a pixel
    /// receives, and in which order, is unchanged, so the merged image does not depend on whether
    /// this ran; it makes results smaller (a pixel hit by several light paths ships one splat) and
    /// lets the wire format delta-code pixel indices.
    pub fn compact(&mut self, layout: &FilmLayout) {
        for s in &mut self.splats {
            if !layout.strategy_layers {
                s.layer = u8::MAX;
            }
            if (s.depth as usize) >= layout.depth_layers {
                s.depth = u8::MAX;
            }
        }
        // Stable: equal keys keep their order; each key's values are summed in f64, in render
        // order, and rounded to f32 once. A radix sort (O(n), and only over the bytes in which
        // the keys differ): a tile's splats are tens of thousands of light-tracing hits.
        radsort::sort_by_key(&mut self.splats, |s| (s.pixel, s.layer, s.depth));
        let key = |s: &Splat| (s.pixel, s.layer, s.depth);
        let mut out: Vec<Splat> = Vec::with_capacity(self.splats.len());
        let mut i = 0;
        while i < self.splats.len() {
            let first = self.splats[i];
            let mut sum = first.value.map(|v| v as f64);
            let mut j = i + 1;
            while j < self.splats.len() && key(&self.splats[j]) == key(&first) {
                for (c, v) in sum.iter_mut().enumerate() {
                    *v += self.splats[j].value[c] as f64;
                }
                j += 1;
            }
            out.push(Splat {
                value: sum.map(|v| v as f32),
                ..first
            });
            i = j;
        }
        self.splats = out;
        self.records.sort_by_pixel();
    }
}

/// Light-tracing samples for optimal MIS, for pixels of other tiles: pixel (frame index), depth,
/// and d + 2 weights followed by C W_s (3 values), as f32.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LtRecords {
    /// Frame pixel index of each record.
    pub pixels: Vec<u32>,
    /// Path depth of each record (it sets how many weights the record has).
    pub depths: Vec<u8>,
    /// Each record's depth + 2 weights then C W_s (3 values), back to back.
    pub values: Vec<f32>,
}

impl LtRecords {
    /// Number of records.
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    /// True when there are no records.
    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    /// The light-tracing weight (the last of a record's d + 2) that the other `d + 1` weights
    /// imply: balance weights sum to 1. The integrators set it so, after rounding the others to
    /// bfloat16, and the wire leaves it out; being 1 minus unbiased estimates of the others, it
    /// is an unbiased estimate of its own weight, and sum_i b_i = C W_s holds for every record.
    #[inline]
    pub fn implied_weight(others: &[f32]) -> f32 {
        1.0 - others.iter().sum::<f32>()
    }

    /// Adds a record: its depth + 2 weights `w` and C W_s `c`.
    pub(crate) fn push(&mut self, pixel: u32, depth: u32, w: &[f32], c: [f32; 3]) {
        self.pixels.push(pixel);
        self.depths.push(depth as u8);
        self.values.extend_from_slice(w);
        self.values.extend_from_slice(&c);
    }

    /// Sorts the records by pixel, keeping the order of each pixel's records.
    pub fn sort_by_pixel(&mut self) {
        if self.pixels.windows(2).all(|w| w[0] <= w[1]) {
            return;
        }
        let mut offsets = Vec::with_capacity(self.len());
        let mut off = 0;
        for &d in &self.depths {
            offsets.push(off);
            off += d as usize + 2 + 3;
        }
        let mut order: Vec<u32> = (0..self.len() as u32).collect();
        radsort::sort_by_key(&mut order, |&k| self.pixels[k as usize]);
        let mut sorted = LtRecords {
            pixels: Vec::with_capacity(self.len()),
            depths: Vec::with_capacity(self.len()),
            values: Vec::with_capacity(self.values.len()),
        };
        for k in order {
            let k = k as usize;
            let n = self.depths[k] as usize + 2 + 3;
            sorted.pixels.push(self.pixels[k]);
            sorted.depths.push(self.depths[k]);
            sorted
                .values
                .extend_from_slice(&self.values[offsets[k]..offsets[k] + n]);
        }
        *self = sorted;
    }

    /// Adds every record into `acc`, whose pixel i is frame pixel `map(i)`.
    pub fn apply(&self, acc: &mut OptimalAccum, map: impl Fn(u32) -> Option<usize>) {
        self.for_each(map, |i, d, w, c| {
            acc.add_sample(i, d, w, c);
            acc.add_hit(i, d);
        });
    }

    /// Calls `f(i, depth, weights, C W_s)` for every record, in order, whose frame pixel maps to
    /// some i by `map` (values widened to f64).
    pub fn for_each(
        &self,
        map: impl Fn(u32) -> Option<usize>,
        mut f: impl FnMut(usize, u32, &[f64], [f64; 3]),
    ) {
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
                f(i, d, &w[..n], c);
            }
        }
    }
}
