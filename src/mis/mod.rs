//! Multiple importance sampling beyond the heuristics: the optimal-MIS accumulators per pixel and
//! depth, and the small linear solver they need.

pub mod optimal;
pub mod solve;

pub use optimal::{Layout, OptimalAccum, SolveScratch};
