//! The tile loop: every pixel sample of a task, through the path tracer or BDPT, into the task's
//! `TileFilm` (BDPT samples weighted by the MIS rule, or into optimal-MIS systems).

use super::{IntegratorKind, RenderSettings, Techniques, bdpt, path};
use crate::film::{LtRecords, STRATEGY_LAYERS, Splat, Tile, TileFilm, strategy_layer};
use crate::geometry::{Rgb, Vec2};
use crate::mis::{self, MisKind, OptimalAccum};
use crate::sampler::{Sampler, Stream};
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
    records: &'a mut LtRecords,
    /// Index of the current camera pixel in the tile.
    pixel: usize,
}

impl FilmSink<'_> {
    fn d_opt(&self) -> u32 {
        self.optimal.as_ref().map_or(0, |a| a.layout.d_opt)
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
                match self.tile.index_of(s.pixel.0, s.pixel.1) {
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
        let w = if self.techniques == Techniques::All {
            mis::weight(self.mis, s.balance, s.s)
        } else {
            self.techniques.selects(s.s, s.t, s.balance.len()) as u8 as f64
        };
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
    let mut film = TileFilm::new(tile, &settings.film_layout());
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
                            techniques: settings.techniques,
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
