//! The film: what samples accumulate into and how results leave a renderer. Four concerns, each
//! in its own place:
//! - accumulators: a task's result (`TaskFilm`), a tile's merged accumulators (`TileAccum`,
//!   tiled by `TileGrid`), the whole frame's (`Film`), the merge rule of a band group
//!   (`BandGroup`), and what they hold (`FilmLayout`, `PixelSums`, `bf16`);
//! - `format`: the byte formats (a task result, a tile checkpoint, a result laid out by band,
//!   the banded merge stream) over one codec, with one error (`FormatError`);
//! - `merge_task`: a merge task as a worker runs it;
//! - `image`: images, EXR and PNG files, metrics and plots.
//!
//! Data flows one way: accumulators -> formats -> merge task, and accumulators -> images.
//! Integrators add samples to films; the render service moves, merges and stores films and
//! knows nothing of how the samples were made.

mod bands;
pub mod bf16;
pub mod format;
mod frame;
pub mod image;
pub mod layers;
pub mod merge_task;
mod pixel_sums;
mod task_film;
mod tile;
mod tile_accum;

pub use self::image::Image;
pub use bands::{BandGroup, band_bytes, band_groups};
pub use frame::Film;
pub use layers::{
    FilmLayout, STRATEGY_DEPTH, STRATEGY_LAYERS, strategy_layer, strategy_layer_name,
};
pub use pixel_sums::PixelSums;
pub use task_film::{LtRecords, RayStats, Splat, TaskFilm};
pub use tile::Tile;
pub use tile_accum::{Routed, TileAccum, TileGrid};
