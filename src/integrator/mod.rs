//! Integrators and the tile loop that drives them.
//!
//! Work is cut into tiles; each tile renders its pixels' samples [s0, s1) into tile-local f64
//! accumulators, plus light-tracing splat records for any pixel. Every random number comes from
//! (seed, pixel, sample index), and results are merged in a fixed order (pass, tile, record), so
//! the image does not depend on the number of threads or the order in which tiles finish.

pub mod bdpt;
pub mod path;
pub mod wire;

use crate::film::{Image, PixelSums};
use crate::geometry::{Rgb, Vec2};
use crate::mis::{OptimalAccum, SolveScratch};
use crate::sampler::{Sampler, SamplerKind, Stream};
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
    /// Bidirectional path tracing with every strategy.
    Bdpt,
}

/// How BDPT weights its techniques.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum, Default)]
#[serde(rename_all = "lowercase")]
pub enum MisKind {
    /// Balance heuristic (Veach 1997 eq. 9.6).
    #[default]
    Balance,
    /// Power heuristic, beta = 2 (Veach 1997 eq. 9.13).
    Power,
    /// Validation: light tracing alone (every t = 1 technique, unweighted).
    Lt,
    /// Validation: next-event estimation alone (every (1, t >= 2), unweighted; depth 0 by (0, 2)).
    Nee,
    /// Optimal weights per pixel and depth for depths 1 ..= optimal_max_depth (seed 000), balance
    /// for depth 0 and above.
    Optimal,
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
    /// BDPT only: technique weights.
    #[serde(default)]
    pub mis: MisKind,
    /// BDPT only: keep the weighted contribution of every (s, t) up to depth 3 as extra layers.
    #[serde(default)]
    pub strategies: bool,
    /// Optimal MIS: the largest depth weighted optimally (D_opt).
    #[serde(default = "default_optimal_max_depth")]
    pub optimal_max_depth: u32,
    /// Optimal MIS: strength of the regularisation toward the balance solution (kappa; 0 = the
    /// seed's plain direct estimator).
    #[serde(default = "default_kappa")]
    pub optimal_kappa: f64,
    /// Keep the image of every path depth 0 ..= max_depth as extra layers.
    #[serde(default)]
    pub depth_layers: bool,
}

fn default_optimal_max_depth() -> u32 {
    5
}

/// Default regularisation strength of the optimal estimator (see mis::optimal).
pub const DEFAULT_KAPPA: f64 = 1.0;

fn default_kappa() -> f64 {
    DEFAULT_KAPPA
}

impl RenderSettings {
    /// Number of per-depth layers kept (0 when not requested).
    pub fn depth_count(&self) -> usize {
        if self.depth_layers {
            self.max_depth.min(bdpt::MAX_DEPTH) as usize + 1
        } else {
            0
        }
    }

    /// The optimal-MIS layout when this render accumulates optimal systems.
    pub fn optimal_layout(&self) -> Option<crate::mis::Layout> {
        (self.integrator == IntegratorKind::Bdpt
            && self.mis == MisKind::Optimal
            && self.optimal_max_depth >= 1)
            .then(|| crate::mis::Layout::new(self.optimal_max_depth.min(self.max_depth)))
    }
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
            mis: MisKind::Balance,
            strategies: false,
            optimal_max_depth: default_optimal_max_depth(),
            optimal_kappa: DEFAULT_KAPPA,
            depth_layers: false,
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

/// (s, t) techniques kept as strategy layers: every technique of depth 0 ..= STRATEGY_DEPTH.
pub const STRATEGY_DEPTH: u32 = 3;

/// Number of strategy layers: sum over d <= 3 of (d + 2) = 14.
pub const STRATEGY_LAYERS: usize = 14;

/// Layer index of technique (s, depth) for depth <= STRATEGY_DEPTH.
#[inline]
pub fn strategy_layer(depth: u32, s: u32) -> Option<usize> {
    (depth <= STRATEGY_DEPTH).then(|| (depth * (depth + 3) / 2 + s) as usize)
}

/// Name of strategy layer `i`, e.g. "s1_t2" (depth s + t - 2).
pub fn strategy_layer_name(i: usize) -> String {
    let mut d = 0u32;
    let mut base = 0usize;
    while base + (d as usize + 2) <= i {
        base += d as usize + 2;
        d += 1;
    }
    let s = (i - base) as u32;
    format!("s{}_t{}", s, d + 2 - s)
}

/// A light-tracing contribution to any pixel of the frame.
#[derive(Clone, Copy, Debug)]
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

    fn push(&mut self, pixel: u32, depth: u32, w: &[f32], c: [f32; 3]) {
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

/// The weight of technique (s, t) for a path whose balance weights over all techniques of its
/// depth are `balance` (n_i p_i / sum_k n_k p_k). Power heuristic, beta = 2 (Veach 1997 eq.
/// 9.13): (n_s p_s)^2 / sum_k (n_k p_k)^2 = b_s^2 / sum_k b_k^2. Optimal MIS weights its depths
/// through its own systems; here (depth 0 and deeper than D_opt) it is balance.
#[inline]
pub fn mis_weight(mis: MisKind, balance: &[f64], s: u32, t: u32) -> f64 {
    match mis {
        MisKind::Balance | MisKind::Optimal => balance[s as usize],
        MisKind::Power => {
            let b = balance[s as usize];
            let sq: f64 = balance.iter().map(|x| x * x).sum();
            if sq > 0.0 { b * b / sq } else { 0.0 }
        }
        MisKind::Lt => (t == 1) as u8 as f64,
        // Depth 0 (an emitter seen directly) has only (0, 2) on the camera side.
        MisKind::Nee => (s == 1 && t >= 2 || s == 0 && t == 2 && balance.len() == 2) as u8 as f64,
    }
}

/// Turns BDPT samples into film: heuristic-weighted contributions (camera ones into the current
/// pixel sample, light-tracing ones into splat records), and for optimal MIS the per-pixel,
/// per-depth systems of depths 1 ..= D_opt.
struct FilmSink<'a> {
    mis: MisKind,
    frame_width: u32,
    tile: Tile,
    value: Rgb,
    splats: &'a mut Vec<Splat>,
    /// The current pixel's strategy layers, when kept.
    layers: Option<&'a mut [[f64; 3]]>,
    /// The current pixel's per-depth sums, when kept.
    depths: Option<&'a mut [[f64; 3]]>,
    optimal: Option<&'a mut OptimalAccum>,
    records: &'a mut LtRecords,
    /// Index of the current camera pixel in the tile.
    pixel: usize,
}

impl FilmSink<'_> {
    fn d_opt(&self) -> u32 {
        self.optimal.as_ref().map_or(0, |a| a.layout.d_opt)
    }

    fn tile_index(&self, x: u32, y: u32) -> Option<usize> {
        let t = &self.tile;
        (x >= t.x0 && x < t.x1 && y >= t.y0 && y < t.y1)
            .then(|| (y - t.y0) as usize * t.width() + (x - t.x0) as usize)
    }
}

impl bdpt::SampleSink for FilmSink<'_> {
    fn wants_zero_samples(&self, depth: u32) -> bool {
        depth >= 1 && depth <= self.d_opt()
    }

    fn sample(&mut self, s: &bdpt::PathSample) {
        if s.depth >= 1 && s.depth <= self.d_opt() {
            let ws = s.balance[s.s as usize];
            let c = s.contribution;
            if s.t == 1 {
                // Light tracing: the same f32 values whichever tile the pixel belongs to, so that
                // the image does not depend on the tiling.
                let mut w32 = [0.0f32; 64];
                for (d, w) in w32.iter_mut().zip(s.balance) {
                    *d = *w as f32;
                }
                let n = s.balance.len();
                let cw = [
                    (c.x as f64 * ws) as f32,
                    (c.y as f64 * ws) as f32,
                    (c.z as f64 * ws) as f32,
                ];
                let frame_pixel = s.pixel.1 * self.frame_width + s.pixel.0;
                match self.tile_index(s.pixel.0, s.pixel.1) {
                    Some(i) => {
                        let acc = self.optimal.as_deref_mut().expect("optimal");
                        let mut w = [0.0f64; 64];
                        for (d, v) in w.iter_mut().zip(&w32[..n]) {
                            *d = *v as f64;
                        }
                        acc.add_sample(i, s.depth, &w[..n], cw.map(|v| v as f64));
                        acc.add_hit(i, s.depth);
                    }
                    None => self.records.push(frame_pixel, s.depth, &w32[..n], cw),
                }
            } else {
                let pixel = self.pixel;
                let cw = [c.x as f64 * ws, c.y as f64 * ws, c.z as f64 * ws];
                self.optimal
                    .as_deref_mut()
                    .expect("optimal")
                    .add_sample(pixel, s.depth, s.balance, cw);
            }
            return;
        }
        if s.contribution == Rgb::ZERO {
            return;
        }
        let w = mis_weight(self.mis, s.balance, s.s, s.t);
        if w == 0.0 {
            return;
        }
        let v = s.contribution * w as f32;
        let layer = strategy_layer(s.depth, s.s);
        if s.t == 1 {
            self.splats.push(Splat {
                pixel: s.pixel.1 * self.frame_width + s.pixel.0,
                layer: layer.map_or(u8::MAX, |l| l as u8),
                depth: s.depth as u8,
                value: v.to_array(),
            });
        } else {
            self.value += v;
            if let Some(d) = self.depths.as_deref_mut() {
                for c in 0..3 {
                    d[s.depth as usize][c] += v[c] as f64;
                }
            }
            if let (Some(layers), Some(l)) = (self.layers.as_deref_mut(), layer) {
                for c in 0..3 {
                    layers[l][c] += v[c] as f64;
                }
            }
        }
    }

    fn unsampled(&mut self, _pixel: (u32, u32), depth: u32, s: u32) {
        if depth >= 1 && depth <= self.d_opt() {
            let pixel = self.pixel;
            self.optimal
                .as_deref_mut()
                .expect("optimal")
                .add_unsampled(pixel, depth, s);
        }
    }
}

/// Renders samples `samples` of every pixel of `tile`.
pub fn render_tile(
    scene: &Scene,
    settings: &RenderSettings,
    tile: Tile,
    samples: Range<u32>,
) -> TileFilm {
    let mut film = TileFilm {
        tile,
        sums: PixelSums::new(tile.width(), tile.height()),
        splats: Vec::new(),
        layers: if settings.strategies && settings.integrator == IntegratorKind::Bdpt {
            vec![[0.0; 3]; tile.pixels() * STRATEGY_LAYERS]
        } else {
            Vec::new()
        },
        depths: vec![[0.0; 3]; tile.pixels() * settings.depth_count()],
        optimal: settings
            .optimal_layout()
            .map(|l| OptimalAccum::new(l, tile.pixels())),
        records: LtRecords::default(),
        stats: RayStats::default(),
    };
    let mut ws = bdpt::Workspace::default();
    let max_depth = settings.max_depth.min(bdpt::MAX_DEPTH);
    let nd = settings.depth_count();
    let mut per_depth = vec![Rgb::ZERO; nd];
    let cam = &scene.camera;
    let stats = &mut film.stats;
    for y in tile.y0..tile.y1 {
        for x in tile.x0..tile.x1 {
            let idx = (y - tile.y0) as usize * tile.width() + (x - tile.x0) as usize;
            for i in samples.clone() {
                let mut sampler = Sampler::new(
                    settings.sampler,
                    settings.seed,
                    x,
                    y,
                    i,
                    settings.spp,
                    Stream::Camera,
                );
                let mut l = match settings.integrator {
                    IntegratorKind::Pt => {
                        let f = sampler.next_2d();
                        let ray = cam.ray(Vec2::new(x as f32 + f.x, y as f32 + f.y));
                        per_depth.fill(Rgb::ZERO);
                        let pd = (nd > 0).then_some(&mut per_depth[..]);
                        let l = path::li(
                            scene,
                            ray,
                            &mut sampler,
                            max_depth,
                            settings.direct,
                            pd,
                            stats,
                        );
                        if l.is_finite() {
                            for (k, v) in per_depth.iter().enumerate() {
                                for c in 0..3 {
                                    film.depths[idx * nd + k][c] += v[c] as f64;
                                }
                            }
                        }
                        l
                    }
                    IntegratorKind::Bdpt => {
                        let mut light_sampler = Sampler::new(
                            settings.sampler,
                            settings.seed,
                            x,
                            y,
                            i,
                            settings.spp,
                            Stream::Light,
                        );
                        let layers = if film.layers.is_empty() {
                            None
                        } else {
                            Some(
                                &mut film.layers
                                    [idx * STRATEGY_LAYERS..(idx + 1) * STRATEGY_LAYERS],
                            )
                        };
                        let depths = (nd > 0).then(|| &mut film.depths[idx * nd..(idx + 1) * nd]);
                        let mut sink = FilmSink {
                            mis: settings.mis,
                            frame_width: cam.width,
                            tile,
                            value: Rgb::ZERO,
                            splats: &mut film.splats,
                            layers,
                            depths,
                            optimal: film.optimal.as_mut(),
                            records: &mut film.records,
                            pixel: idx,
                        };
                        bdpt::pixel_sample(
                            scene,
                            bdpt::PixelSample {
                                pixel: (x, y),
                                max_depth,
                                cam_sampler: &mut sampler,
                                light_sampler: &mut light_sampler,
                            },
                            &mut ws,
                            &mut sink,
                            stats,
                        );
                        sink.value
                    }
                };
                if !l.is_finite() {
                    stats.non_finite += 1;
                    l = Rgb::ZERO;
                }
                stats.samples += 1;
                film.sums.add(idx, l);
            }
        }
    }
    film.splats.retain(|s| {
        let ok = s.value.iter().all(|v| v.is_finite());
        if !ok {
            stats.non_finite += 1;
        }
        ok
    });
    film
}

/// Whole-frame accumulators: camera-side sums, light-tracing splats, strategy layers.
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub sums: PixelSums,
    pub splat: Vec<[f64; 3]>,
    /// STRATEGY_LAYERS per pixel when kept (camera and light-tracing parts together).
    pub layers: Vec<[f64; 3]>,
    /// Per-depth sums (camera side and splats together), depth_count per pixel, when kept.
    pub depths: Vec<[f64; 3]>,
    pub depth_count: usize,
    /// Optimal MIS systems of every pixel.
    pub optimal: Option<OptimalAccum>,
    /// Optimal MIS regularisation strength.
    pub kappa: f64,
}

impl Frame {
    pub fn new(width: u32, height: u32, settings: &RenderSettings) -> Frame {
        let n = (width * height) as usize;
        let strategies = settings.strategies && settings.integrator == IntegratorKind::Bdpt;
        Frame {
            width,
            height,
            sums: PixelSums::new(width as usize, height as usize),
            splat: vec![[0.0; 3]; n],
            layers: if strategies {
                vec![[0.0; 3]; n * STRATEGY_LAYERS]
            } else {
                Vec::new()
            },
            depths: vec![[0.0; 3]; n * settings.depth_count()],
            depth_count: settings.depth_count(),
            optimal: settings.optimal_layout().map(|l| OptimalAccum::new(l, n)),
            kappa: settings.optimal_kappa,
        }
    }

    /// Light paths traced for the frame so far: one per pixel sample (N_L of the optimal-MIS
    /// systems; W H spp once every pass has covered the whole frame).
    pub fn light_paths(&self) -> u64 {
        self.sums.count.iter().map(|&c| c as u64).sum()
    }

    /// Bytes of accumulator memory per pixel (camera sums, splats, optimal systems).
    pub fn bytes_per_pixel(&self) -> usize {
        let base = 2 * 24 + 4 + 24;
        base + self
            .optimal
            .as_ref()
            .map_or(0, |o| o.layout.bytes_per_pixel())
            + if self.layers.is_empty() {
                0
            } else {
                STRATEGY_LAYERS * 24
            }
            + self.depth_count * 24
    }

    /// The image of each path depth 0 ..= max_depth (when depth layers are kept).
    pub fn depth_images(&self) -> Vec<Image> {
        let nd = self.depth_count;
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
                            let f = o.solve(i, d as u32, spp, light_paths, self.kappa, scratch);
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
                let nd = self.depth_count;
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
            if (s.depth as usize) < self.depth_count {
                let nd = self.depth_count;
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
    pub fn extra_layers(&self, integrator: IntegratorKind) -> Vec<(String, Image)> {
        let mut layers = Vec::new();
        if integrator == IntegratorKind::Pt {
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
        integrator: IntegratorKind,
        attributes: &[(&str, String)],
    ) -> Result<Image, String> {
        let image = self.image();
        let layers = self.extra_layers(integrator);
        let named: Vec<crate::film::exr_io::NamedLayer> = layers
            .iter()
            .map(|(name, image)| crate::film::exr_io::NamedLayer {
                name: name.clone(),
                image,
            })
            .collect();
        crate::film::exr_io::write_exr(path, &image, &named, attributes)?;
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
                        let f = o.solve(i, d, spp, light_paths, self.kappa, scratch);
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

/// The result of a whole-frame render.
pub struct RenderOutput {
    pub frame: Frame,
    pub stats: RayStats,
    pub seconds: f64,
}

impl RenderOutput {
    /// Camera-side sums (the whole estimate for the path tracer).
    pub fn sums(&self) -> &PixelSums {
        &self.frame.sums
    }

    pub fn image(&self) -> Image {
        self.frame.image()
    }
}

/// Samples per tile task of `render`: bounds the memory of splat records between merges.
pub const PASS_SIZE: u32 = 64;

/// Renders the whole frame on the current rayon pool, reporting each finished tile task.
/// Tasks are (pass, tile) pairs of `PASS_SIZE` samples; see `render_passes`.
pub fn render(
    scene: &Scene,
    settings: &RenderSettings,
    tile_size: u32,
    progress: &(dyn Fn(usize) + Sync),
) -> RenderOutput {
    render_passes(scene, settings, tile_size, PASS_SIZE, progress)
}

/// The tasks of a frame: pass by pass (`pass_size` samples each), tile by tile in `make_tiles`
/// order. Merging results in this order makes every way of running them give the same bits.
pub fn pass_tasks(tiles: &[Tile], spp: u32, pass_size: u32) -> Vec<(Tile, Range<u32>)> {
    let pass_size = pass_size.max(1);
    let mut tasks = Vec::new();
    let mut s0 = 0;
    while s0 < spp {
        let s1 = s0.saturating_add(pass_size).min(spp);
        tasks.extend(tiles.iter().map(|&t| (t, s0..s1)));
        s0 = s1;
    }
    tasks
}

/// Renders the whole frame on the current rayon pool, reporting each finished tile task.
/// Tasks are `pass_tasks`; results are merged in task order, a wave at a time (the render
/// service merges in the same order, so its image has the same bits).
pub fn render_passes(
    scene: &Scene,
    settings: &RenderSettings,
    tile_size: u32,
    pass_size: u32,
    progress: &(dyn Fn(usize) + Sync),
) -> RenderOutput {
    let start = Instant::now();
    let (w, h) = (scene.camera.width, scene.camera.height);
    let tiles = make_tiles(w, h, tile_size);
    let mut frame = Frame::new(w, h, settings);
    let mut stats = RayStats::default();
    let tasks = pass_tasks(&tiles, settings.spp, pass_size);
    run_tasks(scene, settings, &tasks, &mut frame, &mut stats, progress);
    RenderOutput {
        frame,
        stats,
        seconds: start.elapsed().as_secs_f64(),
    }
}

/// Renders tasks on the current rayon pool, merging results in task order, a wave at a time.
pub fn run_tasks(
    scene: &Scene,
    settings: &RenderSettings,
    tasks: &[(Tile, Range<u32>)],
    frame: &mut Frame,
    stats: &mut RayStats,
    progress: &(dyn Fn(usize) + Sync),
) {
    let wave = (rayon::current_num_threads() * 4).max(1);
    for chunk in tasks.chunks(wave) {
        let results: Vec<TileFilm> = chunk
            .par_iter()
            .map(|(tile, range)| {
                let f = render_tile(scene, settings, *tile, range.clone());
                progress(1);
                f
            })
            .collect();
        for r in &results {
            stats.add(&r.stats);
            frame.merge_task(r);
        }
    }
}

/// Renders passes of `pass_spp` samples per pixel over the whole frame until `budget` has
/// elapsed (at least one pass), as for equal-time comparisons. The samplers stratify over blocks
/// of `pass_spp` samples. Returns the output and the samples per pixel reached.
pub fn render_for(
    scene: &Scene,
    settings: &RenderSettings,
    tile_size: u32,
    pass_spp: u32,
    budget: std::time::Duration,
) -> (RenderOutput, u32) {
    let start = Instant::now();
    let pass_spp = pass_spp.max(1);
    let s = RenderSettings {
        spp: pass_spp,
        ..settings.clone()
    };
    let (w, h) = (scene.camera.width, scene.camera.height);
    let tiles = make_tiles(w, h, tile_size);
    let mut frame = Frame::new(w, h, &s);
    let mut stats = RayStats::default();
    let mut done = 0u32;
    loop {
        let tasks: Vec<_> = tiles.iter().map(|&t| (t, done..done + pass_spp)).collect();
        run_tasks(scene, &s, &tasks, &mut frame, &mut stats, &|_| {});
        done += pass_spp;
        if start.elapsed() >= budget {
            break;
        }
    }
    (
        RenderOutput {
            frame,
            stats,
            seconds: start.elapsed().as_secs_f64(),
        },
        done,
    )
}

/// Number of tile tasks `render_passes` runs (for progress bars).
pub fn task_count(width: u32, height: u32, tile_size: u32, spp: u32, pass_size: u32) -> usize {
    make_tiles(width, height, tile_size).len() * spp.div_ceil(pass_size.max(1)) as usize
}
