//! Every multiple-importance-sampling weighting rule: the heuristics (balance, power) and the
//! optimal weights (Kondapaneni et al., "Optimal Multiple Importance Sampling", ACM TOG 38(4),
//! 2019) with their per-pixel accumulators and the small linear solver they need.

pub mod heuristic;
pub mod optimal;
pub mod progressive;
pub mod solve;

pub use heuristic::{MisKind, power_heuristic, ratio_term, weight};
pub use optimal::{DEFAULT_KAPPA, DEFAULT_OPTIMAL_MAX_DEPTH, Layout, OptimalAccum, SolveScratch};
pub use progressive::Progressive;
