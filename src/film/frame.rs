//! The whole frame's accumulators (pbrt-v4's `Film`): the frame as one `TileAccum`, with the merge
//! of task results in task order, the solve of the optimal-MIS systems, the images and the EXR.

use super::image::exr_io;
use super::layers::FilmLayout;
use super::task_film::{LtRecords, TaskFilm};
use super::tile_accum::TileAccum;
use super::{Image, PixelSums, Tile};

/// Whole-frame accumulators: camera-side sums, light-tracing splats, strategy and depth layers,
/// optimal-MIS systems. Tasks' `TaskFilm`s merge into it by addition; it solves and writes images.
pub struct Film {
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// The accumulators of every pixel.
    pub acc: TileAccum,
    /// What is accumulated (and the kappa the optimal systems are solved with).
    pub layout: FilmLayout,
}

impl Film {
    /// Empty accumulators of a `width` x `height` frame with the layers `layout` asks for.
    pub fn new(width: u32, height: u32, layout: &FilmLayout) -> Film {
        let tile = Tile {
            x0: 0,
            y0: 0,
            x1: width,
            y1: height,
        };
        Film {
            width,
            height,
            acc: TileAccum::new(tile, layout),
            layout: layout.clone(),
        }
    }

    /// Camera-side sums of every pixel (the whole estimate for the path tracer).
    pub fn sums(&self) -> &PixelSums {
        &self.acc.sums
    }

    /// Light paths traced for the frame so far: one per pixel sample (N_L of the optimal-MIS
    /// systems; W H spp once every pass has covered the whole frame).
    pub fn light_paths(&self) -> u64 {
        self.acc.samples()
    }

    /// The image of each path depth 0 ..= max_depth (when depth layers are kept).
    pub fn depth_images(&self) -> Vec<Image> {
        let light_paths = self.light_paths();
        (0..self.layout.depth_layers)
            .map(|d| self.acc.depth_image(d, light_paths, self.layout.kappa))
            .collect()
    }

    /// Adds a tile's results: its own pixels and its light-tracing splats (order matters only
    /// for the last bits of the f64 sums).
    pub fn add_own_and_splats(&mut self, t: &TaskFilm) {
        self.acc.add_own(t);
        self.acc.add_splats(&t.splats, self.width);
    }

    /// Adds a task's whole result: its tile, its splats and its out-of-tile light-tracing records.
    pub fn add_task(&mut self, t: &TaskFilm) {
        self.add_own_and_splats(t);
        self.apply_records(&t.records);
    }

    /// Closes a pass once all its tasks are merged (see `TileAccum::end_pass`): the progressive
    /// estimator's next weights.
    pub fn end_pass(&mut self) {
        let light_paths = self.light_paths();
        self.acc.end_pass(light_paths, self.layout.kappa);
    }

    /// Adds out-of-tile light-tracing records (frame pixel indices).
    pub fn apply_records(&mut self, r: &LtRecords) {
        self.acc.add_records(r, self.width);
    }

    /// The EXR layers besides the beauty (see `TileAccum::extra_layers`).
    pub fn extra_layers(&self) -> Vec<(String, Image)> {
        self.acc.extra_layers(&self.layout, self.light_paths())
    }

    /// Writes the EXR of the frame (beauty and `extra_layers`) with `attributes` in its header,
    /// in ZIP blocks of `lines` scan lines (`exr_io::block_lines`); returns the beauty image.
    pub fn write_exr(
        &self,
        path: &std::path::Path,
        attributes: &[(&str, String)],
        lines: usize,
    ) -> Result<Image, exr_io::ExrError> {
        let image = self.image();
        let layers = self.extra_layers();
        let named: Vec<exr_io::NamedLayer> = layers
            .iter()
            .map(|(name, image)| exr_io::NamedLayer {
                name: name.clone(),
                image,
            })
            .collect();
        exr_io::write_exr_in_blocks(path, &image, &named, attributes, lines)?;
        Ok(image)
    }

    /// The image: (camera sums + splats) / samples per pixel, plus the solved optimal depths.
    pub fn image(&self) -> Image {
        self.acc.image(self.light_paths(), self.layout.kappa)
    }

    /// The strategy layers as (name, image) pairs.
    pub fn strategy_images(&self) -> Vec<(String, Image)> {
        self.acc.strategy_images(&self.layout)
    }
}
