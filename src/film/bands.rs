//! A pass merged band by band: a coordinator holds the accumulators of a few bands (rows of
//! tiles) at a time, never the whole frame, and adds every task of the pass to them in task
//! order. Each tile sees the additions of `Film::add_task` restricted to its pixels (a task's
//! own pixels, then its splats, then its records), so the merged tiles have the bits of a frame
//! merged in one piece.

use super::layers::FilmLayout;
use super::task_film::TaskFilm;
use super::tile_accum::{Routed, TileAccum, TileGrid};

/// Bytes of accumulators of one full band (row of tiles) of `grid` (at least 1).
pub fn band_bytes(grid: &TileGrid, layout: &FilmLayout) -> u64 {
    (grid.width as u64 * grid.size as u64)
        .saturating_mul(layout.bytes_per_pixel() as u64)
        .max(1)
}

/// Splits the bands of `grid` into consecutive groups whose accumulators take at most `budget`
/// bytes each (at least one band per group).
pub fn band_groups(
    grid: &TileGrid,
    layout: &FilmLayout,
    budget: u64,
) -> Vec<std::ops::Range<usize>> {
    let per = (budget / band_bytes(grid, layout)).max(1) as usize;
    let rows = grid.rows() as usize;
    (0..rows.div_ceil(per))
        .map(|g| g * per..((g + 1) * per).min(rows))
        .collect()
}

/// The tiles of consecutive bands that one merge step holds.
pub struct BandGroup {
    /// The bands.
    pub bands: std::ops::Range<usize>,
    /// Index of the first tile (row-major).
    pub first: usize,
    /// The tiles' accumulators, in tile order.
    pub tiles: Vec<TileAccum>,
    /// Per tile: whether this pass is still to be added (false: it was, before a restart).
    pub open: Vec<bool>,
}

impl BandGroup {
    /// A group of `bands` of `grid` with the tiles' accumulators as loaded and which of them
    /// take this pass.
    pub fn new(
        grid: &TileGrid,
        bands: std::ops::Range<usize>,
        tiles: Vec<TileAccum>,
        open: Vec<bool>,
    ) -> BandGroup {
        let first = grid.tiles_of_bands(bands.clone()).start;
        BandGroup {
            bands,
            first,
            tiles,
            open,
        }
    }

    /// Whether tile `t` (frame index) is in the group.
    pub fn holds(&self, t: usize) -> bool {
        (self.first..self.first + self.tiles.len()).contains(&t)
    }

    /// Closes the pass in the tiles that took it, once every task is added (`TileAccum::end_pass`,
    /// `light_paths` light paths traced for the frame so far).
    pub fn end_pass(&mut self, light_paths: u64, kappa: f64) {
        for (tile, open) in self.tiles.iter_mut().zip(&self.open) {
            if *open {
                tile.end_pass(light_paths, kappa);
            }
        }
    }

    /// Adds task `task`'s parts in merge order: its own pixels (`own`, when its tile is in the
    /// group), then what it routed to each band of the group (`sections`, in band order).
    pub fn add_task(
        &mut self,
        grid: &TileGrid,
        task: usize,
        own: Option<&TaskFilm>,
        sections: &[(usize, Routed)],
    ) {
        if let Some(own) = own
            && self.holds(task)
        {
            let k = task - self.first;
            if self.open[k] {
                self.tiles[k].add_own(own);
            }
        }
        for (_, routed) in sections {
            for (t, part) in routed.by_tile(grid) {
                if !self.holds(t) || !self.open[t - self.first] {
                    continue;
                }
                self.tiles[t - self.first].add_routed(&part, grid.width);
            }
        }
    }
}
