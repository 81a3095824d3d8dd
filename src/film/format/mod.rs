//! The byte formats of the film, little-endian and versioned, each in one module over one codec
//! (`codec`: writer, bounds-checked reader, LEB128 steps, byte planes) and one error
//! (`FormatError`):
//! - `task_result`: a task's result as a worker encodes it (`TaskFilm::encode` / `decode` /
//!   `check`), wire v7 (v6 still reads);
//! - `banded_result`: a task result as the coordinator stores it, laid out by band
//!   (`encode_banded`, `BandedIndex`, `check_banded`, sections), its parts packed (`pack`);
//! - `checkpoint`: one tile's merged accumulators (`TileCheckpoint`);
//! - `merge_stream`: a merge task's input and output (`MergeHead`, `MergeInput`,
//!   `MergeOutput`).
//!
//! The pixel record (`pixel`) and the lists (`lists`: splats, records, layers, optimal systems)
//! are encoded and decoded in one place each. What a coordinator checks it checks without
//! decoding: each walk over the bytes skips the values and refuses exactly what decoding
//! refuses.

mod banded_result;
mod checkpoint;
mod codec;
mod error;
mod lists;
pub mod merge_stream;
pub mod pack;
mod pixel;
mod task_result;

pub use banded_result::{
    BandedIndex, check_banded, check_section, decode_section, encode_banded, relabel_banded,
    unpack_own, unpack_section,
};
pub use checkpoint::TileCheckpoint;
pub use error::FormatError;
pub use task_result::Checked;
