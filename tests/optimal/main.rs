//! Optimal MIS: the accumulators are a mergeable value (tiling and sample-range invariance, also
//! through the wire encoding), the estimate is unbiased in practice, and it beats balance.

mod auto_depth;
mod band_merge;
#[path = "../common/mod.rs"]
mod common;
mod estimators;
mod support;
mod tile_merge;
mod wire;
