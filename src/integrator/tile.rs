//! The tile loop: every pixel sample of a task, through the path tracer, BDPT or VCM, into the
//! task's `TaskFilm` (BDPT samples weighted by the MIS rule, or into optimal-MIS systems).

use super::bpm::{self, BpmWeights};
use super::vcm::{self, PhotonCache};
use super::{IntegratorKind, RenderSettings, Techniques, bdpt, path};
use crate::film::bf16;
use crate::film::{
    FilmLayout, LtRecords, PixelSums, RayStats, STRATEGY_LAYERS, Splat, TaskFilm, Tile,
    strategy_layer,
};
use crate::geometry::{Rgb, Vec2};
use crate::mis::{MisKind, OptimalAccum};
use crate::sampler::{Sampler, Stream, hash_words, mix64};
use crate::scene::Scene;
use std::ops::Range;

/// Turns BDPT samples into film: heuristic-weighted contributions (camera ones into the current
/// pixel sample, light-tracing ones into splat records), and for optimal MIS the per-pixel,
/// per-depth systems of depths 1 ..= D_opt.
struct FilmSink<'a> {
    mis: MisKind,
    techniques: Techniques,
    frame_width: u32,
    tile: Tile,
    value: Rgb,
    splats: &'a mut Vec<Splat>,
    /// The current pixel's strategy layers, when kept.
    layers: Option<&'a mut [[f64; 3]]>,
    /// The current pixel's per-depth sums, when kept.
    depths: Option<&'a mut [[f64; 3]]>,
    optimal: Option<&'a mut OptimalAccum>,
    /// Depths 1 ..= d_opt are weighted optimally (0 without systems).
    d_opt: u32,
    records: &'a mut LtRecords,
    /// Index of the current camera pixel in the tile.
    pixel: usize,
    /// Samples whose contribution or weights were NaN or infinite.
    non_finite: u64,
    /// The rounding of the current pixel sample's light-tracing values.
    rounding: LtRounding,
}

/// Light-tracing values leave a task as bfloat16 (`film::bf16`: 6 bytes a splat instead of 12):
/// each is rounded stochastically, unbiased, with random bits from hash(seed, x, y, i) of the
/// pixel sample that made it and its technique's s (a pixel sample makes one light-tracing
/// sample per s), so a value's rounding depends on that sample alone: not on the tile, the
/// thread, whether the value lands in its own tile, or which other samples were kept (optimal
/// MIS keeps zero-contribution ones). The rounding adds at most 2^-16 of a value's square to its
/// variance, against the O(1) relative variance of a light-tracing sample (BENCHMARKS.md,
/// "The render service").
struct LtRounding {
    key: u64,
}

impl LtRounding {
    /// Tells these random bits from the sampler's streams (`Stream`: 0 and 1).
    const STREAM: u64 = 2;

    fn new(seed: u64, x: u32, y: u32, i: u32) -> LtRounding {
        LtRounding {
            key: hash_words(&[seed, x as u64, y as u64, Self::STREAM, i as u64]),
        }
    }

    /// The random bits of the light-tracing sample of technique (s, 1).
    fn technique(&self, s: u32) -> RoundingBits {
        RoundingBits {
            key: mix64(self.key ^ (s as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15)),
            counter: 0,
            bits: 0,
            left: 0,
        }
    }
}

/// 16 random bits at a time for `bf16::round`: four from each hash of (key, counter).
struct RoundingBits {
    key: u64,
    counter: u64,
    bits: u64,
    left: u32,
}

impl RoundingBits {
    /// `v` rounded to bfloat16 with the next 16 random bits.
    #[inline]
    fn round(&mut self, v: f32) -> f32 {
        if self.left == 0 {
            self.counter += 1;
            self.bits = mix64(self.key.wrapping_add(self.counter));
            self.left = 4;
        }
        let r = self.bits as u16;
        self.bits >>= 16;
        self.left -= 1;
        bf16::round(v, r)
    }
}

/// Techniques of the systems whose light-tracing weights are rounded on the stack (D_opt <= 6).
const INLINE_TECHNIQUES: usize = 8;

impl FilmSink<'_> {
    fn d_opt(&self) -> u32 {
        self.d_opt
    }
}

impl bdpt::SampleSink for FilmSink<'_> {
    fn wants_zero_samples(&self, depth: u32) -> bool {
        depth >= 1 && depth <= self.d_opt()
    }

    fn wants_vector(&self, depth: u32) -> bool {
        depth >= 1 && depth <= self.d_opt()
    }

    fn heuristic(&self) -> MisKind {
        // The validation modes weight nothing; optimal MIS is balance outside its systems.
        if self.techniques == Techniques::All && self.mis == MisKind::Power {
            MisKind::Power
        } else {
            MisKind::Balance
        }
    }

    fn sample(&mut self, s: &bdpt::PathSample) {
        // A non-finite sample is counted and dropped the same way in every mode: its
        // contribution becomes zero; if its weights are not finite either, nothing of it is kept
        // (one NaN in an optimal system would spoil its pixel for the rest of the job).
        let mut c = s.contribution;
        let weights_finite = s.weight.is_finite() && s.balance.iter().all(|w| w.is_finite());
        if !c.is_finite() || !weights_finite {
            self.non_finite += 1;
            if !weights_finite {
                return;
            }
            c = Rgb::ZERO;
        }
        if s.depth >= 1 && s.depth <= self.d_opt() {
            let ws = s.balance[s.s as usize];
            if s.t == 1 {
                // Light tracing: the same rounded values whichever tile the pixel belongs to,
                // so that the image does not depend on the tiling.
                // The weighted contribution as the balance heuristic's splat computes it, rounded
                // with the same random bits, then the weights but the light-tracing one, which
                // the others imply (`LtRecords::implied_weight`: the wire leaves it out).
                let mut bits = self.rounding.technique(s.s);
                let v = c * ws as f32;
                let cw = v.to_array().map(|v| bits.round(v));
                let n = s.balance.len();
                let mut small = [0.0f32; INLINE_TECHNIQUES];
                let mut large = Vec::new();
                let w: &mut [f32] = if n <= INLINE_TECHNIQUES {
                    &mut small[..n]
                } else {
                    large.resize(n, 0.0);
                    &mut large
                };
                for (d, v) in w[..n - 1].iter_mut().zip(s.balance) {
                    *d = bits.round(*v as f32);
                }
                w[n - 1] = LtRecords::implied_weight(&w[..n - 1]);
                match self.tile.index_of(s.pixel.0, s.pixel.1) {
                    Some(i) => {
                        let acc = self.optimal.as_deref_mut().expect("optimal");
                        let c64 = cw.map(|v| v as f64);
                        if n <= INLINE_TECHNIQUES {
                            let mut w64 = [0.0f64; INLINE_TECHNIQUES];
                            for (d, v) in w64.iter_mut().zip(w.iter()) {
                                *d = *v as f64;
                            }
                            acc.add_sample(i, s.depth, &w64[..n], c64);
                        } else {
                            let w64: Vec<f64> = w.iter().map(|v| *v as f64).collect();
                            acc.add_sample(i, s.depth, &w64, c64);
                        }
                        acc.add_hit(i, s.depth);
                    }
                    None => {
                        let frame_pixel = s.pixel.1 * self.frame_width + s.pixel.0;
                        self.records.push(frame_pixel, s.depth, w, cw);
                    }
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
        if c == Rgb::ZERO {
            return;
        }
        let w = if self.techniques == Techniques::All {
            s.weight
        } else {
            self.techniques.selects(s.s, s.t, s.depth as usize + 2) as u8 as f64
        };
        if w == 0.0 {
            return;
        }
        let v = c * w as f32;
        let layer = strategy_layer(s.depth, s.s);
        if s.t == 1 {
            let mut bits = self.rounding.technique(s.s);
            self.splats.push(Splat {
                pixel: s.pixel.1 * self.frame_width + s.pixel.0,
                layer: layer.map_or(u8::MAX, |l| l as u8),
                depth: s.depth as u8,
                value: v.to_array().map(|v| bits.round(v)),
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

/// Renders samples `samples` of every pixel of `tile`. VCM builds the photon maps it needs
/// here; `render_tile_cached` shares them between tasks.
pub fn render_tile(
    scene: &Scene,
    settings: &RenderSettings,
    tile: Tile,
    samples: Range<u32>,
) -> TaskFilm {
    render_tile_cached(scene, settings, tile, samples, &PhotonCache::new(1))
}

/// `render_tile` with VCM's photon maps taken from (and built into) `cache`, which must serve
/// this scene and these settings only. The same bits as `render_tile`.
pub fn render_tile_cached(
    scene: &Scene,
    settings: &RenderSettings,
    tile: Tile,
    samples: Range<u32>,
    cache: &PhotonCache,
) -> TaskFilm {
    if matches!(
        settings.integrator,
        IntegratorKind::Vcm | IntegratorKind::Bpm
    ) {
        return render_tile_vcm(scene, settings, tile, samples, cache);
    }
    let mut film = TaskFilm::new(tile, &settings.film_layout());
    let mut ws = bdpt::Workspace::default();
    ws.set_roulette(settings.roulette_start());
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
                    settings.sample_block,
                    Stream::Camera,
                );
                let l = match settings.integrator {
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
                            add_depths(&mut film.depths[idx * nd..(idx + 1) * nd], &per_depth);
                        }
                        l
                    }
                    IntegratorKind::Vcm | IntegratorKind::Bpm => unreachable!("render_tile_vcm"),
                    IntegratorKind::Bdpt => {
                        let mut light_sampler = Sampler::new(
                            settings.sampler,
                            settings.seed,
                            x,
                            y,
                            i,
                            settings.sample_block,
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
                        let d_opt = film.optimal.as_ref().map_or(0, |a| a.layout.d_opt);
                        let mut sink = FilmSink {
                            mis: settings.mis,
                            techniques: settings.techniques,
                            frame_width: cam.width,
                            tile,
                            value: Rgb::ZERO,
                            splats: &mut film.splats,
                            layers,
                            depths,
                            optimal: film.optimal.as_mut(),
                            d_opt,
                            records: &mut film.records,
                            pixel: idx,
                            non_finite: 0,
                            rounding: LtRounding::new(settings.seed, x, y, i),
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
                        stats.non_finite += sink.non_finite;
                        sink.value
                    }
                };
                add_sample(stats, &mut film.sums, idx, l);
            }
        }
    }
    finish(film, &settings.film_layout())
}

/// Adds one pixel sample's parts by depth to a pixel's depth sums.
fn add_depths(sums: &mut [[f64; 3]], per_depth: &[Rgb]) {
    for (s, v) in sums.iter_mut().zip(per_depth) {
        for c in 0..3 {
            s[c] += v[c] as f64;
        }
    }
}

/// Adds one pixel sample's estimate `l` to pixel `idx` (a non-finite one is counted and added
/// as zero).
fn add_sample(stats: &mut RayStats, sums: &mut PixelSums, idx: usize, l: Rgb) {
    let l = if l.is_finite() {
        l
    } else {
        stats.non_finite += 1;
        Rgb::ZERO
    };
    stats.samples += 1;
    sums.add(idx, l);
}

/// The end of every tile loop: non-finite splats are dropped (and counted), the film compacted.
fn finish(mut film: TaskFilm, layout: &FilmLayout) -> TaskFilm {
    let stats = &mut film.stats;
    film.splats.retain(|s| {
        let ok = s.value.iter().all(|v| v.is_finite());
        if !ok {
            stats.non_finite += 1;
        }
        ok
    });
    film.compact(layout);
    film
}

/// VCM's and BPM's tile loop: iteration by iteration (one photon map at a time), every pixel of
/// the tile.
fn render_tile_vcm(
    scene: &Scene,
    settings: &RenderSettings,
    tile: Tile,
    samples: Range<u32>,
    cache: &PhotonCache,
) -> TaskFilm {
    let layout = settings.film_layout();
    let mut film = TaskFilm::new(tile, &layout);
    let mut ws = bdpt::Workspace::default();
    ws.set_roulette(settings.roulette_start());
    let max_depth = settings.max_depth.min(bdpt::MAX_DEPTH);
    let nd = settings.depth_count();
    let mut per_depth = vec![Rgb::ZERO; nd];
    let cam = &scene.camera;
    let bpm = settings.integrator == IntegratorKind::Bpm;
    let frozen = if bpm {
        settings.bpm_weights == BpmWeights::Optimal
    } else {
        settings.vcm_weights == vcm::VcmWeights::Ershov
    }
    .then(|| cache.get(scene, settings, 0));
    for i in samples {
        let map = cache.get(scene, settings, i);
        for y in tile.y0..tile.y1 {
            for x in tile.x0..tile.x1 {
                let idx = (y - tile.y0) as usize * tile.width() + (x - tile.x0) as usize;
                let mut sampler = Sampler::new(
                    settings.sampler,
                    settings.seed,
                    x,
                    y,
                    i,
                    settings.sample_block,
                    Stream::Camera,
                );
                if bpm {
                    per_depth.fill(Rgb::ZERO);
                    let l = bpm::pixel_sample(
                        scene,
                        (x, y),
                        &mut sampler,
                        max_depth,
                        settings.bdd,
                        &map,
                        frozen.as_deref(),
                        &mut ws,
                        (nd > 0).then_some(&mut per_depth[..]),
                        &mut film.stats,
                    );
                    if l.is_finite() {
                        add_depths(&mut film.depths[idx * nd..(idx + 1) * nd], &per_depth);
                    }
                    add_sample(&mut film.stats, &mut film.sums, idx, l);
                    continue;
                }
                let depths = (nd > 0).then(|| &mut film.depths[idx * nd..(idx + 1) * nd]);
                let mut sink = FilmSink {
                    mis: settings.mis,
                    techniques: Techniques::All,
                    frame_width: cam.width,
                    tile,
                    value: Rgb::ZERO,
                    splats: &mut film.splats,
                    layers: None,
                    depths,
                    optimal: None,
                    d_opt: 0,
                    records: &mut film.records,
                    pixel: idx,
                    non_finite: 0,
                    rounding: LtRounding::new(settings.seed, x, y, i),
                };
                vcm::pixel_sample(
                    scene,
                    (x, y),
                    max_depth,
                    &mut sampler,
                    &map,
                    frozen.as_deref(),
                    &mut ws,
                    &mut sink,
                    &mut film.stats,
                );
                film.stats.non_finite += sink.non_finite;
                add_sample(&mut film.stats, &mut film.sums, idx, sink.value);
            }
        }
    }
    finish(film, &layout)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mis::Layout;
    use bdpt::{PathSample, SampleSink};

    fn sample(depth: u32, s: u32, pixel: (u32, u32), c: Rgb, balance: &[f64]) -> PathSample<'_> {
        PathSample {
            depth,
            s,
            t: depth + 2 - s,
            pixel,
            contribution: c,
            weight: balance[s as usize],
            balance,
        }
    }

    /// Feeds a finite sample, then one with contribution `bad` and otherwise finite, one with NaN
    /// weights, and a light-tracing splat of contribution `bad` outside the tile, through a sink
    /// of `mis`.
    fn feed(mis: MisKind, bad: Rgb) -> (Option<OptimalAccum>, LtRecords, Vec<Splat>, Rgb, u64) {
        let tile = Tile {
            x0: 0,
            y0: 0,
            x1: 2,
            y1: 2,
        };
        let mut optimal = (mis == MisKind::Optimal).then(|| OptimalAccum::new(Layout::new(2), 4));
        let mut splats = Vec::new();
        let mut records = LtRecords::default();
        let mut sink = FilmSink {
            mis,
            techniques: Techniques::All,
            frame_width: 8,
            tile,
            value: Rgb::ZERO,
            splats: &mut splats,
            layers: None,
            depths: None,
            d_opt: optimal.as_ref().map_or(0, |a| a.layout.d_opt),
            optimal: optimal.as_mut(),
            records: &mut records,
            pixel: 0,
            non_finite: 0,
            rounding: LtRounding::new(1, 0, 0, 0),
        };
        let w = [0.2, 0.5, 0.3];
        let nan_w = [0.2, f64::NAN, 0.3];
        sink.sample(&sample(1, 1, (0, 0), Rgb::splat(1.0), &w));
        sink.sample(&sample(1, 0, (0, 0), bad, &w));
        sink.sample(&sample(1, 1, (0, 0), Rgb::splat(1.0), &nan_w));
        sink.sample(&sample(1, 2, (5, 5), bad, &w));
        let (value, n) = (sink.value, sink.non_finite);
        (optimal, records, splats, value, n)
    }

    #[test]
    fn non_finite_samples_are_counted_and_dropped_in_every_mode() {
        for mis in [MisKind::Balance, MisKind::Power, MisKind::Optimal] {
            for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
                let (optimal, records, splats, value, n) = feed(mis, Rgb::new(bad, 0.0, 1.0));
                assert_eq!(n, 3, "{mis:?} {bad}: every non-finite sample is counted");
                assert!(value.is_finite(), "{mis:?}: {value:?}");
                assert!(splats.iter().all(|s| s.value.iter().all(|v| v.is_finite())));
                assert!(records.values.iter().all(|v| v.is_finite()), "{mis:?}");
                // A non-finite contribution counts as a zero-contribution sample of its weights:
                // the same accumulators as if it had been zero.
                let (zero, zero_records, ..) = feed(mis, Rgb::ZERO);
                assert_eq!(records, zero_records, "{mis:?} {bad}");
                if let (Some(o), Some(z)) = (optimal, zero) {
                    assert!(
                        o.data.iter().all(|v| v.is_finite()),
                        "{mis:?}: system poisoned"
                    );
                    assert_eq!(o.data, z.data, "{bad}");
                    assert_eq!(o.hits, z.hits, "{bad}");
                }
            }
        }
    }
}
