//! The one tile x pass schedule of a job, and the in-process runner that follows it.
//!
//! A job renders in passes: pass p covers samples `pass_range(p)` of every tile of `tiles()`,
//! and each (pass, tile) is a task. Results are merged pass by pass, tile by tile in `tiles()`
//! order, so every way of running the tasks (this process's threads, the render service's
//! workers, retries) gives the same bits. `omis render --in-process`, `omis compare`,
//! `omis bench`, the tests and the coordinator all take their tasks from here.

use super::Resolved;
use crate::film::{Film, Image, PixelSums, RayStats, TaskFilm, Tile, TileGrid};
use crate::integrator::vcm::PhotonCache;
use crate::integrator::{self, IntegratorKind, RenderSettings};
use crate::scene::Scene;
use rayon::prelude::*;
use std::ops::Range;
use std::time::Instant;

/// Row-major tiles of at most `size` x `size` pixels covering the frame.
pub fn make_tiles(width: u32, height: u32, size: u32) -> Vec<Tile> {
    TileGrid::new(width, height, size).tiles()
}

/// The result of rendering a job in this process.
pub struct RenderOutput {
    /// The merged accumulators.
    pub film: Film,
    /// Work counters of every task.
    pub stats: RayStats,
    /// Wall time.
    pub seconds: f64,
    /// Samples per pixel rendered (a time-budget job's last pass may be shortened to fit its
    /// budget, `Resolved::fit_to_budget`).
    pub spp: u32,
}

impl RenderOutput {
    /// Camera-side sums (the whole estimate for the path tracer).
    pub fn sums(&self) -> &PixelSums {
        self.film.sums()
    }

    /// The beauty image.
    pub fn image(&self) -> Image {
        self.film.image()
    }
}

impl Resolved {
    /// A fixed-spp job of `settings.sample_block` samples at the scene camera's resolution, in tiles of
    /// `tile_size` and passes of `pass_size` samples (no limits checked: for callers that build
    /// their settings themselves, as benchmarks and tests do).
    pub fn fixed(
        scene: &Scene,
        settings: &RenderSettings,
        tile_size: u32,
        pass_size: u32,
    ) -> Resolved {
        Resolved {
            defines: Default::default(),
            width: scene.camera.width,
            height: scene.camera.height,
            render: settings.clone(),
            spp: Some(settings.sample_block),
            time_budget_s: None,
            budget_spp: None,
            pilot_s: None,
            tile_size,
            pass_size,
            max_pass_size: None,
            eps: 0.01,
            optimal_depth: None,
        }
    }

    /// A job that renders passes of `pass_size` samples until `seconds` have passed (at least
    /// one pass); the sampler stratifies over blocks of `pass_size` samples.
    pub fn timed(
        scene: &Scene,
        settings: &RenderSettings,
        tile_size: u32,
        pass_size: u32,
        seconds: f64,
    ) -> Resolved {
        let pass_size = pass_size.max(1);
        Resolved {
            render: RenderSettings {
                sample_block: pass_size,
                ..settings.clone()
            },
            spp: None,
            time_budget_s: Some(seconds),
            ..Resolved::fixed(scene, settings, tile_size, pass_size)
        }
    }

    /// The tiles of the frame, in the order tasks are created and merged.
    pub fn tiles(&self) -> Vec<Tile> {
        self.grid().tiles()
    }

    /// The tiling of the frame.
    pub fn grid(&self) -> TileGrid {
        TileGrid::new(self.width, self.height, self.tile_size)
    }

    /// Samples of pass `p`: `pass_size` doubled once per pass, up to the largest
    /// `pass_size` x 2^k that is at most `max_pass_size` (so every pass is a whole number of
    /// first passes).
    pub fn pass_len(&self, p: u32) -> u32 {
        let base = self.pass_size.max(1);
        let max = self.max_pass_size.unwrap_or(base).max(base);
        let steps = (max / base).ilog2();
        base << p.min(steps)
    }

    /// Sample range of pass `p`, or None when a fixed-spp job has no such pass (or the range
    /// would pass u32::MAX samples).
    pub fn pass_range(&self, p: u32) -> Option<Range<u32>> {
        let base = self.pass_size.max(1) as u64;
        let steps = (self.pass_len(u32::MAX) as u64 / base).ilog2();
        // Samples before pass p: base (2^min(p, steps) - 1) for the doubling passes, then the
        // full-length passes.
        let doubling = p.min(steps);
        let s0 = base * ((1u64 << doubling) - 1) + (p - doubling) as u64 * (base << steps);
        let s1 = s0 + self.pass_len(p) as u64;
        let (s0, s1) = (u32::try_from(s0).ok()?, u32::try_from(s1).ok()?);
        match self.spp_limit() {
            Some(spp) if s0 >= spp => None,
            Some(spp) => Some(s0..s1.min(spp)),
            None => Some(s0..s1),
        }
    }

    /// The sample per pixel that ends the job: its spp, or the one its time budget was fitted to
    /// (`budget_spp`), whichever is less; None while a time budget alone ends it.
    pub fn spp_limit(&self) -> Option<u32> {
        match (self.spp, self.budget_spp) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// The samples of pass `p`, not yet begun, of a job `elapsed` seconds into its rendering with
    /// `spp_done` samples per pixel rendered (counting the passes in flight pro rata) at
    /// `seconds_per_spp` (the rate so far); its time budget also counts the pilot's `pilot_s`:
    /// - the pass as planned where the budget allows it at that rate, or where the rate is not
    ///   known yet (nothing rendered) or the job has no budget;
    /// - the pass shortened to whole first passes (`pass_size` samples, the blocks a
    ///   time-budget job's sampler stratifies over) so that the job ends as near the budget as
    ///   such a block allows, recorded in `budget_spp` (which ends the job with that pass);
    /// - None where the time is up, or where stopping now is nearer the budget than one more
    ///   block (`not_begun`).
    ///
    /// Without it a pass begun at the end of the budget ran to completion, and passes double up
    /// to `max_pass_size`: the budget was overrun by up to its own length.
    pub fn fit_to_budget(
        &mut self,
        p: u32,
        elapsed: f64,
        spp_done: f64,
        seconds_per_spp: f64,
    ) -> Option<Range<u32>> {
        let range = self.pass_range(p)?;
        let Some(budget) = self.time_budget_s else {
            return Some(range);
        };
        // The pilot's time was spent on the job too.
        let elapsed = elapsed + self.pilot_s.unwrap_or(0.0);
        // The first pass is always rendered.
        if p > 0 && elapsed >= budget {
            return self.not_begun(&range);
        }
        if !(spp_done > 0.0 && seconds_per_spp > 0.0) {
            return Some(range);
        }
        // Samples per pixel the budget holds at that rate.
        let fits = spp_done + (budget - elapsed) / seconds_per_spp;
        if fits >= range.end as f64 {
            return Some(range);
        }
        let base = self.pass_size.max(1);
        let blocks = ((fits - range.start as f64) / base as f64).round();
        if blocks < 1.0 {
            return self.not_begun(&range);
        }
        // `fits` < range.end, but rounding to whole blocks may give the whole pass back.
        let end = range.start + (blocks as u32).saturating_mul(base);
        if end >= range.end {
            return Some(range);
        }
        self.budget_spp = Some(end);
        self.pass_range(p)
    }

    /// `fit_to_budget`'s answer for a pass it does not begin: a fit recorded for that pass
    /// whose tasks were never made (the coordinator stopped between the two) is withdrawn, so
    /// that the job's sample target is where it ends.
    fn not_begun(&mut self, range: &Range<u32>) -> Option<Range<u32>> {
        if self.budget_spp.is_some_and(|b| b > range.start) {
            self.budget_spp = None;
        }
        None
    }

    /// Number of passes of a job with a sample count (fixed, or fitted to its time budget).
    pub fn total_passes(&self) -> Option<u32> {
        let spp = self.spp_limit()?;
        let full = self.pass_len(u32::MAX);
        let mut p = 0;
        // The doubling passes (at most 16 of them), then whole full-length passes.
        while self.pass_len(p) < full {
            match self.pass_range(p) {
                Some(r) if r.end < spp => p += 1,
                Some(_) => return Some(p + 1),
                None => return Some(p),
            }
        }
        let start = self.pass_range(p).map_or(spp, |r| r.start);
        Some(p + (spp.saturating_sub(start)).div_ceil(full))
    }

    /// Number of tasks of a fixed-spp job (for progress bars).
    pub fn task_count(&self) -> Option<usize> {
        Some(self.tiles().len() * self.total_passes()? as usize)
    }

    /// Renders the job in this process on the current rayon pool: the same tasks, merged in the
    /// same order, as the render service (so the same image). `progress` hears of every
    /// finished task.
    pub fn render_in_process(
        &self,
        scene: &Scene,
        progress: &(dyn Fn(usize) + Sync),
    ) -> RenderOutput {
        let start = Instant::now();
        self.render_in_process_clocked(scene, progress, &|| start.elapsed().as_secs_f64())
    }

    /// `render_in_process` with the time budget counted by `clock` (seconds since the render
    /// began, e.g. CPU seconds; `render_in_process` counts wall seconds).
    pub fn render_in_process_clocked(
        &self,
        scene: &Scene,
        progress: &(dyn Fn(usize) + Sync),
        clock: &dyn Fn() -> f64,
    ) -> RenderOutput {
        let start = Instant::now();
        let tiles = self.tiles();
        let mut film = Film::new(self.width, self.height, &self.render.film_layout());
        let mut stats = RayStats::default();
        let mut spp = 0;
        let mut p = 0;
        // The last pass is fitted to the time left (`fit_to_budget`).
        let mut job = self.clone();
        // VCM: the photon maps of a pass's iterations, built once (in parallel) and shared by
        // its tasks.
        let vcm = matches!(
            self.render.integrator,
            IntegratorKind::Vcm | IntegratorKind::Bpm
        );
        let cache = PhotonCache::new(if vcm {
            self.pass_len(u32::MAX) as usize
        } else {
            1
        });
        // When the last pass began, and at which sample: its rate, the longest pass's, is the
        // budget's measure (the first passes' fixed costs weigh more per sample).
        let mut last_pass = (0.0, 0);
        loop {
            let elapsed = clock();
            let rate = (elapsed - last_pass.0) / (spp - last_pass.1) as f64;
            let Some(range) = job.fit_to_budget(p, elapsed, spp as f64, rate) else {
                break;
            };
            last_pass = (elapsed, spp);
            if vcm {
                range.clone().into_par_iter().for_each(|i| {
                    cache.get(scene, &self.render, i);
                });
            }
            let tasks: Vec<_> = tiles.iter().map(|&t| (t, range.clone())).collect();
            run_tasks(
                scene,
                &self.render,
                &tasks,
                &cache,
                &mut film,
                &mut stats,
                progress,
            );
            film.end_pass();
            spp = range.end;
            p += 1;
        }
        RenderOutput {
            film,
            stats,
            seconds: start.elapsed().as_secs_f64(),
            spp,
        }
    }
}

/// Renders tasks on the current rayon pool, merging results in task order, a wave at a time.
fn run_tasks(
    scene: &Scene,
    settings: &RenderSettings,
    tasks: &[(Tile, Range<u32>)],
    cache: &PhotonCache,
    film: &mut Film,
    stats: &mut RayStats,
    progress: &(dyn Fn(usize) + Sync),
) {
    let wave = (rayon::current_num_threads() * 4).max(1);
    for chunk in tasks.chunks(wave) {
        let results: Vec<TaskFilm> = chunk
            .par_iter()
            .map(|(tile, range)| {
                let f =
                    integrator::render_tile_cached(scene, settings, *tile, range.clone(), cache);
                progress(1);
                f
            })
            .collect();
        for r in &results {
            stats.add(&r.stats);
            film.add_task(r);
        }
    }
}
