//! The one tile x pass schedule of a job, and the in-process runner that follows it.
//!
//! A job renders in passes: pass p covers samples `pass_range(p)` of every tile of `tiles()`,
//! and each (pass, tile) is a task. Results are merged pass by pass, tile by tile in `tiles()`
//! order, so every way of running the tasks (this process's threads, the render service's
//! workers, retries) gives the same bits. `omis render --in-process`, `omis compare`,
//! `omis bench`, the tests and the coordinator all take their tasks from here.

use super::Resolved;
use crate::film::{Film, Image, PixelSums, RayStats, Tile, TileFilm, TileGrid};
use crate::integrator::{self, RenderSettings};
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
    /// Samples per pixel rendered (a time-budget job stops after a whole pass).
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
    /// A fixed-spp job of `settings.spp` samples at the scene camera's resolution, in tiles of
    /// `tile_size` and passes of `pass_size` samples (no limits checked: for callers that build
    /// their settings themselves, as benchmarks and tests do).
    pub fn fixed(
        scene: &Scene,
        settings: &RenderSettings,
        tile_size: u32,
        pass_size: u32,
    ) -> Resolved {
        Resolved {
            width: scene.camera.width,
            height: scene.camera.height,
            render: settings.clone(),
            spp: Some(settings.spp),
            time_budget_s: None,
            tile_size,
            pass_size,
            eps: 0.01,
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
                spp: pass_size,
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

    /// Sample range of pass `p`, or None when a fixed-spp job has no such pass.
    pub fn pass_range(&self, p: u32) -> Option<Range<u32>> {
        let s0 = p.checked_mul(self.pass_size)?;
        match self.spp {
            Some(spp) if s0 >= spp => None,
            Some(spp) => Some(s0..(s0 + self.pass_size).min(spp)),
            None => Some(s0..s0.checked_add(self.pass_size)?),
        }
    }

    /// Number of passes of a fixed-spp job.
    pub fn total_passes(&self) -> Option<u32> {
        self.spp.map(|s| s.div_ceil(self.pass_size))
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
        let tiles = self.tiles();
        let mut film = Film::new(self.width, self.height, &self.render.film_layout());
        let mut stats = RayStats::default();
        let mut spp = 0;
        let mut p = 0;
        while let Some(range) = self.pass_range(p) {
            let tasks: Vec<_> = tiles.iter().map(|&t| (t, range.clone())).collect();
            run_tasks(scene, &self.render, &tasks, &mut film, &mut stats, progress);
            spp = range.end;
            p += 1;
            if self
                .time_budget_s
                .is_some_and(|b| start.elapsed().as_secs_f64() >= b)
            {
                break;
            }
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
    film: &mut Film,
    stats: &mut RayStats,
    progress: &(dyn Fn(usize) + Sync),
) {
    let wave = (rayon::current_num_threads() * 4).max(1);
    for chunk in tasks.chunks(wave) {
        let results: Vec<TileFilm> = chunk
            .par_iter()
            .map(|(tile, range)| {
                let f = integrator::render_tile(scene, settings, *tile, range.clone());
                progress(1);
                f
            })
            .collect();
        for r in &results {
            stats.add(&r.stats);
            film.merge_task(r);
        }
    }
}
