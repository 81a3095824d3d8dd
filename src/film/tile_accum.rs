//! The merged accumulators of one tile of the frame, and how a task's results reach them.
//!
//! A task's `TaskFilm` holds its tile's own camera-side sums, and light-tracing splats and
//! optimal-MIS records that may land in any pixel. `TaskFilm::route` splits the latter by the
//! tile they land in. A tile's accumulators receive, pass by pass, the contributions of every
//! task of the pass in task order (tile order within the pass): for source tile U, first U's own
//! sums when U is this tile, then what U routed here, in U's order. That is the order in which
//! `Film::add_task` adds a whole frame, so a frame merged tile by tile, on another machine, in
//! any interleaving of tiles, has the same bits.

use super::layers::{FilmLayout, STRATEGY_LAYERS, strategy_layer_name};
use super::{Image, LtRecords, PixelSums, Splat, TaskFilm, Tile};
use crate::geometry::Rgb;
use crate::mis::{OptimalAccum, Progressive, SolveScratch};

/// The tiles of a frame: `size` x `size` pixels, row-major (the order tasks are merged in).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileGrid {
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Tile edge in pixels.
    pub size: u32,
}

impl TileGrid {
    /// The grid of a `width` x `height` frame in tiles of `size` (at least 1) pixels.
    pub fn new(width: u32, height: u32, size: u32) -> TileGrid {
        TileGrid {
            width,
            height,
            size: size.max(1),
        }
    }

    /// Tiles per row.
    pub fn columns(&self) -> u32 {
        self.width.div_ceil(self.size)
    }

    /// Tiles per column.
    pub fn rows(&self) -> u32 {
        self.height.div_ceil(self.size)
    }

    /// Number of tiles.
    pub fn len(&self) -> usize {
        self.columns() as usize * self.rows() as usize
    }

    /// Whether the frame has no pixels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Tile `i` (row-major).
    pub fn tile(&self, i: usize) -> Tile {
        let c = self.columns() as usize;
        let (tx, ty) = ((i % c) as u32, (i / c) as u32);
        let (x0, y0) = (tx * self.size, ty * self.size);
        Tile {
            x0,
            y0,
            x1: x0.saturating_add(self.size).min(self.width),
            y1: y0.saturating_add(self.size).min(self.height),
        }
    }

    /// Every tile, row-major.
    pub fn tiles(&self) -> Vec<Tile> {
        (0..self.len()).map(|i| self.tile(i)).collect()
    }

    /// Index of the tile holding frame pixel `p` (y * width + x).
    #[inline]
    pub fn tile_of(&self, p: u32) -> usize {
        let (x, y) = (p % self.width, p / self.width);
        (y / self.size) as usize * self.columns() as usize + (x / self.size) as usize
    }

    /// The tiles of the bands `bands`, as indices (consecutive: the grid is row-major).
    pub fn tiles_of_bands(&self, bands: std::ops::Range<usize>) -> std::ops::Range<usize> {
        if bands.is_empty() {
            return 0..0;
        }
        self.band_tiles(bands.start).start..self.band_tiles(bands.end - 1).end
    }

    /// The band (row of tiles) holding frame pixel `p`.
    #[inline]
    pub fn band_of(&self, p: u32) -> usize {
        (p / self.width / self.size) as usize
    }

    /// The tiles of band `b`, as indices.
    pub fn band_tiles(&self, b: usize) -> std::ops::Range<usize> {
        let c = self.columns() as usize;
        (b * c).min(self.len())..((b + 1) * c).min(self.len())
    }

    /// The scan lines of the bands `bands`.
    pub fn band_rows(&self, bands: std::ops::Range<usize>) -> std::ops::Range<usize> {
        let y = |b: usize| (b as u64 * self.size as u64).min(self.height as u64) as usize;
        y(bands.start)..y(bands.end)
    }

    /// The frame pixels (y * width + x) of band `b`.
    pub fn band_pixels(&self, b: usize) -> std::ops::Range<u64> {
        let w = self.width as u64;
        let y0 = (b as u64 * self.size as u64).min(self.height as u64);
        let y1 = (y0 + self.size as u64).min(self.height as u64);
        y0 * w..y1 * w
    }

    /// Index of `tile` in the grid, when it is one of its tiles.
    pub fn index_of(&self, tile: &Tile) -> Option<usize> {
        let i = self.tile_of(tile.y0.checked_mul(self.width)?.checked_add(tile.x0)?);
        (tile.x0 < self.width && tile.y0 < self.height && self.tile(i) == *tile).then_some(i)
    }
}

/// What one task routed to one tile: its splats and optimal-MIS records that land there, in the
/// task's order (frame pixel indices).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Routed {
    /// Light-tracing splats.
    pub splats: Vec<Splat>,
    /// Optimal-MIS light-tracing samples.
    pub records: LtRecords,
}

impl Routed {
    /// Whether nothing was routed.
    pub fn is_empty(&self) -> bool {
        self.splats.is_empty() && self.records.is_empty()
    }
}

impl Routed {
    /// Splits `splats` and `records` by `key(pixel)`, keeping their order within each key; keys
    /// that receive nothing are left out. Sorted by key.
    pub fn split_by(
        splats: &[Splat],
        records: &LtRecords,
        key: impl Fn(u32) -> usize,
    ) -> Vec<(usize, Routed)> {
        let mut out: Vec<(usize, Routed)> = Vec::new();
        let mut slot = std::collections::HashMap::new();
        // Lists sorted by pixel (`TaskFilm::compact`) come in runs of one key: look up once a run.
        let mut last = (usize::MAX, 0);
        let mut at = |dest: usize, out: &mut Vec<(usize, Routed)>| -> usize {
            if last.0 == dest {
                return last.1;
            }
            let k = *slot.entry(dest).or_insert_with(|| {
                out.push((dest, Routed::default()));
                out.len() - 1
            });
            last = (dest, k);
            k
        };
        for s in splats {
            let k = at(key(s.pixel), &mut out);
            out[k].1.splats.push(*s);
        }
        let mut off = 0;
        for (i, &p) in records.pixels.iter().enumerate() {
            let n = records.depths[i] as usize + 2 + 3;
            let k = at(key(p), &mut out);
            let dst = &mut out[k].1.records;
            dst.pixels.push(p);
            dst.depths.push(records.depths[i]);
            dst.values.extend_from_slice(&records.values[off..off + n]);
            off += n;
        }
        out.sort_by_key(|(d, _)| *d);
        out
    }

    /// Splits what was routed to a band (or any set of tiles) by the tile of `grid` it lands in.
    pub fn by_tile(&self, grid: &TileGrid) -> Vec<(usize, Routed)> {
        Routed::split_by(&self.splats, &self.records, |p| grid.tile_of(p))
    }
}

impl TaskFilm {
    /// Splits the task's splats and records by the tile of `grid` they land in, keeping their
    /// order; tiles that receive nothing are left out. Sorted by destination tile.
    pub fn route(&self, grid: &TileGrid) -> Vec<(usize, Routed)> {
        Routed::split_by(&self.splats, &self.records, |p| grid.tile_of(p))
    }

    /// The same split by band (tile row) of `grid`.
    pub fn route_bands(&self, grid: &TileGrid) -> Vec<(usize, Routed)> {
        Routed::split_by(&self.splats, &self.records, |p| grid.band_of(p))
    }
}

/// The merged accumulators of one tile's pixels: camera-side sums, light-tracing splat sums,
/// strategy and depth layers, optimal-MIS systems.
#[derive(Clone, Debug)]
pub struct TileAccum {
    /// Which pixels.
    pub tile: Tile,
    /// Camera-side sums (the whole estimate for the path tracer).
    pub sums: PixelSums,
    /// Light-tracing splat sums (empty where the layout keeps none: the path tracer).
    pub splat: Vec<[f64; 3]>,
    /// STRATEGY_LAYERS per pixel when kept (camera and light-tracing parts together).
    pub layers: Vec<[f64; 3]>,
    /// Per-depth sums, `depth_layers` per pixel.
    pub depths: Vec<[f64; 3]>,
    /// Optimal-MIS systems of the tile's pixels.
    pub optimal: Option<OptimalAccum>,
    /// The progressive estimator's state (with `optimal`, when the layout asks for it).
    pub progressive: Option<Progressive>,
}

impl TileAccum {
    /// Empty accumulators of `tile` with the layers `layout` asks for.
    pub fn new(tile: Tile, layout: &FilmLayout) -> TileAccum {
        let n = tile.pixels();
        TileAccum {
            tile,
            sums: PixelSums::new(tile.width(), tile.height()),
            splat: if layout.splats {
                vec![[0.0; 3]; n]
            } else {
                Vec::new()
            },
            layers: if layout.strategy_layers {
                vec![[0.0; 3]; n * STRATEGY_LAYERS]
            } else {
                Vec::new()
            },
            depths: vec![[0.0; 3]; n * layout.depth_layers],
            optimal: layout.optimal.clone().map(|l| OptimalAccum::new(l, n)),
            progressive: layout
                .progressive_layout()
                .map(|d_opt| Progressive::new(d_opt, n)),
        }
    }

    /// Depth layers kept per pixel.
    fn depth_layers(&self) -> usize {
        self.depths.len() / self.tile.pixels().max(1)
    }

    /// Index in this tile of frame pixel `p` of a frame `frame_width` wide.
    #[inline]
    fn local(&self, p: u32, frame_width: u32) -> Option<usize> {
        self.tile.index_of(p % frame_width, p / frame_width)
    }

    /// Adds the camera-side part of a task's result: the sums, layers and optimal systems of its
    /// own pixels that lie in this tile (not its splats or records).
    pub fn add_own(&mut self, t: &TaskFilm) {
        let nd = self.depth_layers();
        let y0 = t.tile.y0.max(self.tile.y0);
        let y1 = t.tile.y1.min(self.tile.y1);
        let x0 = t.tile.x0.max(self.tile.x0);
        let x1 = t.tile.x1.min(self.tile.x1);
        for y in y0..y1 {
            for x in x0..x1 {
                let (Some(src), Some(dst)) = (t.tile.index_of(x, y), self.tile.index_of(x, y))
                else {
                    continue;
                };
                for c in 0..3 {
                    self.sums.sum[dst][c] += t.sums.sum[src][c];
                    self.sums.sum_sq[dst][c] += t.sums.sum_sq[src][c];
                }
                self.sums.count[dst] += t.sums.count[src];
                if let (Some(o), Some(to)) = (self.optimal.as_mut(), t.optimal.as_ref()) {
                    o.add_pixel(dst, to, src);
                    if let Some(p) = self.progressive.as_mut() {
                        p.add_own(dst, to, src, t.sums.count[src]);
                    }
                }
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
    }

    /// Adds the light-tracing splats that land in this tile, in their order.
    pub fn add_splats(&mut self, splats: &[Splat], frame_width: u32) {
        let nd = self.depth_layers();
        for s in splats {
            let Some(p) = self.local(s.pixel, frame_width) else {
                continue;
            };
            // A film without splat sums receives none (the wire refuses them).
            if let Some(sum) = self.splat.get_mut(p) {
                for (a, v) in sum.iter_mut().zip(s.value) {
                    *a += v as f64;
                }
            }
            if (s.depth as usize) < nd {
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

    /// Adds the optimal-MIS light-tracing records that land in this tile, in their order.
    pub fn add_records(&mut self, r: &LtRecords, frame_width: u32) {
        let tile = self.tile;
        let local = |p: u32| tile.index_of(p % frame_width, p / frame_width);
        match (self.optimal.as_mut(), self.progressive.as_mut()) {
            (Some(o), Some(prog)) => r.for_each(local, |i, d, w, c| {
                o.add_sample(i, d, w, c);
                o.add_hit(i, d);
                prog.add_record(i, d, w);
            }),
            (Some(o), None) => r.apply(o, local),
            _ => {}
        }
    }

    /// Closes a pass once every task of it is merged: the progressive estimator solves the
    /// weights of the next pass from the totals, with `light_paths` light paths traced for the
    /// whole frame so far and regularisation `kappa` (nothing to do for other layouts).
    pub fn end_pass(&mut self, light_paths: u64, kappa: f64) {
        if let (Some(o), Some(p)) = (self.optimal.as_ref(), self.progressive.as_mut()) {
            p.end_pass(o, &self.sums.count, light_paths, kappa);
        }
    }

    /// Adds what one task routed to this tile.
    pub fn add_routed(&mut self, r: &Routed, frame_width: u32) {
        self.add_splats(&r.splats, frame_width);
        self.add_records(&r.records, frame_width);
    }

    /// Pixel samples taken in this tile (its part of the light-path count N_L).
    pub fn samples(&self) -> u64 {
        self.sums.count.iter().map(|&c| c as u64).sum()
    }

    /// The tile's beauty: (camera sums + splats) / samples per pixel, plus the solved optimal
    /// depths, with `light_paths` light paths traced for the whole frame.
    pub fn image(&self, light_paths: u64, kappa: f64) -> Image {
        self.solved(light_paths, kappa, None)
    }

    /// The image of path depth `d` of the tile.
    pub fn depth_image(&self, d: usize, light_paths: u64, kappa: f64) -> Image {
        self.solved(light_paths, kappa, Some(d))
    }

    /// Beauty (`depth` None) or one depth layer. Pixels are independent: solved in parallel, the
    /// same bits as in sequence.
    fn solved(&self, light_paths: u64, kappa: f64, depth: Option<usize>) -> Image {
        use rayon::prelude::*;
        let nd = self.depth_layers();
        let mut img = Image::new(self.tile.width(), self.tile.height());
        img.pixels.par_iter_mut().enumerate().for_each_init(
            SolveScratch::default,
            |scratch, (i, p)| {
                let spp = self.sums.count[i];
                let n = spp.max(1) as f64;
                let s = match depth {
                    None => {
                        let s = self.sums.sum[i];
                        let l = self.splat.get(i).copied().unwrap_or_default();
                        [s[0] + l[0], s[1] + l[1], s[2] + l[2]]
                    }
                    Some(d) => self.depths[i * nd + d],
                };
                let mut v = [s[0] / n, s[1] / n, s[2] / n];
                if let Some(o) = &self.optimal {
                    // The optimal depths this image holds: all of them for the beauty.
                    let (lo, hi) = match depth {
                        None => (1, o.layout.d_opt),
                        Some(d) => (d.max(1) as u32, (d as u32).min(o.layout.d_opt)),
                    };
                    for d in lo..hi + 1 {
                        let f = match &self.progressive {
                            Some(prog) => prog.estimate(o, i, d, spp),
                            None => o.solve(i, d, spp, light_paths, kappa, scratch),
                        };
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

    /// The EXR layers besides the beauty, for the tile's pixels, with `light_paths` light paths
    /// traced for the whole frame, named as `FilmLayout::extra_layer_names` says.
    pub fn extra_layers(&self, layout: &FilmLayout, light_paths: u64) -> Vec<(String, Image)> {
        layout
            .extra_layer_names()
            .into_iter()
            .zip(self.extra_images(layout, light_paths))
            .collect()
    }

    /// The images of `extra_layers`, in the same order, without their names.
    pub fn extra_images(&self, layout: &FilmLayout, light_paths: u64) -> Vec<Image> {
        let mut images = Vec::new();
        if layout.variance_layer {
            images.push(self.sums.variance_of_mean());
        }
        if layout.strategy_layers {
            images.extend((0..STRATEGY_LAYERS).map(|l| self.strategy_image(l)));
        }
        images.extend(
            (0..layout.depth_layers).map(|d| self.depth_image(d, light_paths, layout.kappa)),
        );
        images
    }

    /// The strategy layers as (name, image) pairs, when `layout` keeps them.
    pub fn strategy_images(&self, layout: &FilmLayout) -> Vec<(String, Image)> {
        if !layout.strategy_layers {
            return Vec::new();
        }
        (0..STRATEGY_LAYERS)
            .map(|l| (strategy_layer_name(l), self.strategy_image(l)))
            .collect()
    }

    /// Strategy layer `l` of the tile.
    pub fn strategy_image(&self, l: usize) -> Image {
        let mut img = Image::new(self.tile.width(), self.tile.height());
        if self.layers.is_empty() {
            return img;
        }
        for (i, p) in img.pixels.iter_mut().enumerate() {
            let n = self.sums.count[i].max(1) as f64;
            let v = self.layers[i * STRATEGY_LAYERS + l];
            *p = Rgb::new((v[0] / n) as f32, (v[1] / n) as f32, (v[2] / n) as f32);
        }
        img
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_tiles_pixels_and_indices_agree() {
        for (w, h, t) in [(40, 32, 16), (7, 5, 2), (1, 1, 4), (33, 64, 32), (5, 9, 1)] {
            let g = TileGrid::new(w, h, t);
            let tiles = g.tiles();
            assert_eq!(tiles.len(), g.len());
            let mut covered = vec![0u32; (w * h) as usize];
            for (i, tile) in tiles.iter().enumerate() {
                assert_eq!(g.index_of(tile), Some(i));
                assert!(tile.x0 < tile.x1 && tile.y0 < tile.y1 && tile.x1 <= w && tile.y1 <= h);
                for y in tile.y0..tile.y1 {
                    for x in tile.x0..tile.x1 {
                        let p = y * w + x;
                        assert_eq!(g.tile_of(p), i, "{w}x{h}/{t}: pixel ({x}, {y})");
                        covered[p as usize] += 1;
                    }
                }
            }
            assert!(
                covered.iter().all(|&c| c == 1),
                "{w}x{h}/{t}: tiles cover once"
            );
            let odd = Tile {
                x0: 1,
                y0: 0,
                x1: 2,
                y1: 1,
            };
            assert_eq!(g.index_of(&odd).is_some(), t == 1);
        }
    }
}
