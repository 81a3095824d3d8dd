//! omis: a bidirectional path tracer with optimal multiple importance sampling, and the render
//! service around it. See ARCHITECTURE.md (layout) and README.md (use).
//!
//! Data flows one way: scene -> accel -> integrator (material, light, sampler) -> film -> job ->
//! worker -> service -> cli.

// `!(x > 0.0)` is deliberate throughout: it rejects NaN along with non-positive values.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
#![warn(missing_docs)]

pub mod accel;
pub(crate) mod bundle;
pub mod camera;
pub mod cli;
pub mod film;
pub mod geometry;
pub mod integrator;
pub mod job;
pub mod light;
pub mod material;
pub mod mis;
pub mod protocol;
pub mod sampler;
pub mod scene;
pub mod service;
pub mod worker;
