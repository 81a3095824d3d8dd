//! Bidirectional path tracing with every strategy (Veach 1997 ch. 10; Cailleau et al., "Optimal Multiple Importance Sampling for
//! Bidirectional Path Tracing", §IV-D).
//!
//! For each pixel sample a camera subpath z_0 (the pinhole) .. z_{nC-1} and a light subpath
//! y_0 (on a light) .. y_{nL-1} are traced; every pair (s, t) with s light and t camera vertices
//! and depth d = s + t - 2 <= max depth is a sample of technique (s, t):
//! - s = 0: the camera subpath hits an emitter;
//! - s = 1, t >= 2: next-event estimation (a fresh light sample connected to z_{t-1});
//! - t = 1: light tracing, y_{s-1} connected to the camera and splatted where it lands;
//! - otherwise y_{s-1} is connected to z_{t-1}.
//!
//! Each sample is handed to a [`SampleSink`] with its unweighted contribution f / p_s and its
//! MIS weight. Where the sink asks for it (optimal MIS, depths <= D_opt) it also gets the vector
//! of *balance* weights over all d + 2 techniques of its depth (zero for those that cannot make
//! it), an O(d) loop over the path per connection. Elsewhere the balance or power weight of the
//! sample's own technique comes in O(1) per connection from partial sums kept per subpath vertex
//! (the recursive MIS of Georgiev, Křivánek, Davidovič and Slusallek, "Light Transport
//! Simulation with Vertex Connection and Merging", SIGGRAPH Asia 2012, and Georgiev's technical report
//! "Implementing Vertex Connection and Merging": their dVC quantities; see
//! [`Workspace::prepare`]). Balance- and power-weighted BDPT and the optimal-MIS accumulators are
//! sinks.
//!
//! Densities are stored per vertex in area measure, in both directions (pbrt-v3 convention:
//! `pdf_fwd` from the vertex's predecessor in its own subpath, `pdf_rev` from its successor).
//! A specular event's solid-angle density is taken as 1 in both directions and converted to
//! area like any other: |cos| / d^2 at the vertex it reaches. That is the limit of a glossy lobe
//! whose width goes to 0 and the cosine Georgiev et al.'s dVC keeps at specular vertices.
//! pbrt-v3 uses 1 for the area density itself; its weights still sum to 1 (unbiased), but they
//! are not balance's, and they gave 1.07-1.14x the variance behind SmallVCM's mirror and glass
//! spheres (BENCHMARKS.md, "BDPT and VCM against SmallVCM").
//!
//! Subpaths end where a BSDF is black or fails to sample, at an escape, at the max depth, and
//! with [`Workspace::set_roulette`] by Russian roulette: from its start vertex R on, a walk
//! continues from each vertex with probability q, its BSDF's albedo estimate, as in SmallVCM
//! (R = 1) and Georgiev et al. 2012's implementation; the vertices before R always continue.
//! Roulette multiplies a surviving subpath's throughput by 1/q, and on paths that only one
//! technique can make (caustics seen through glass or in a mirror) MIS cannot take that back:
//! from the first vertex it made the glass-and-mirror Cornell box 1.3x noisier per sample, most
//! of it in fireflies, while it saves 20-50 % of the time on long paths (BENCHMARKS.md,
//! "BDPT against pbrt-v3"). BDPT's default start ([`ROULETTE_FROM`]) leaves those short paths alone.
//!
//! q is a factor of every density sampled from a vertex, in both directions, so the weights
//! stay exact; with R > 1 it depends on the technique: x_j of a path of k vertices is light
//! vertex j but camera vertex k - 1 - j, and continues with q where that index is >= R. Forward
//! densities (`pdf_fwd`) carry the q of the subpath that made them; reverse densities
//! (`pdf_rev`) are stored without it and get it where they are used
//! (`continuation_at` and `Workspace::sum_for`).

mod connect;
mod subpath;
#[cfg(test)]
mod tests;
mod vertex;
mod weights;
mod workspace;

pub(crate) use connect::connect_all;
pub(crate) use subpath::pixel_camera_subpath;
pub use subpath::{camera_subpath, light_subpath};
pub use vertex::Vertex;
pub(crate) use vertex::{StoredVertex, dir_to};
pub use workspace::Workspace;

use crate::film::RayStats;
use crate::geometry::Rgb;
use crate::mis::MisKind;
use crate::sampler::Sampler;
use crate::scene::Scene;

/// Longest supported max depth (subpaths have at most max_depth + 2 vertices).
pub const MAX_DEPTH: u32 = 64;

/// BDPT's default first roulette vertex: subpaths always continue through their first two
/// surface vertices, where paths that one technique alone makes (caustics seen directly or in
/// a mirror) get their fireflies from 1/q, and end by roulette from the third on (as the path
/// tracer's from its third bounce), where most of a long path's time goes: pbrt-v3's per-sample
/// error on the glass-and-mirror box, 1.5x SmallVCM per CPU second on its scene 1 (BENCHMARKS.md,
/// "BDPT against pbrt-v3").
pub const ROULETTE_FROM: u32 = 3;

/// One BDPT sample as the sinks see it.
#[derive(Debug)]
pub struct PathSample<'a> {
    /// Path depth in bounces (edges - 1): s + t - 2.
    pub depth: u32,
    /// Vertices of the light subpath.
    pub s: u32,
    /// Vertices of the camera subpath (t = 1: light tracing, a connection to the camera).
    pub t: u32,
    /// The pixel: the camera pixel for t >= 2, the pixel the light path lands in for t = 1.
    pub pixel: (u32, u32),
    /// Unweighted contribution f / p_s(x) (zero for occluded or zero-BSDF connections).
    /// Camera and light-tracing samples share one normalisation: divide pixel sums by spp.
    pub contribution: Rgb,
    /// The weight of technique (s, t) by the sink's heuristic ([`SampleSink::heuristic`]).
    pub weight: f64,
    /// Only where the sink asked for it ([`SampleSink::wants_vector`]), else empty: balance
    /// weights over techniques s' = 0 ..= depth + 1 (t' = depth + 2 - s'); zero where a technique
    /// cannot produce the path. Sums to 1.
    pub balance: &'a [f64],
}

/// Receives the samples of one pixel sample.
pub trait SampleSink {
    /// Whether samples of depth `depth` with zero contribution, and techniques that produced no
    /// path, must be reported (optimal MIS needs them; the heuristics do not).
    fn wants_zero_samples(&self, depth: u32) -> bool;
    /// Whether samples of depth `depth` must carry the whole vector of balance weights (O(depth)
    /// per sample; optimal MIS needs it), not only their own weight (O(1)).
    fn wants_vector(&self, depth: u32) -> bool;
    /// The heuristic of [`PathSample::weight`]: balance or power (optimal counts as balance).
    fn heuristic(&self) -> MisKind;
    /// Receives one sample (any technique, any depth).
    fn sample(&mut self, s: &PathSample);
    /// Technique (s, t >= 2) of depth `depth` produced no path for the camera pixel this time
    /// (its subpath ended early, or the connection vertex is specular).
    fn unsampled(&mut self, pixel: (u32, u32), depth: u32, s: u32);
}

/// Everything a pixel sample needs besides the scene.
pub struct PixelSample<'a> {
    /// The camera pixel, (x, y).
    pub pixel: (u32, u32),
    /// Maximum path depth in bounces.
    pub max_depth: u32,
    /// Numbers for the camera subpath.
    pub cam_sampler: &'a mut Sampler,
    /// Numbers for the light subpath.
    pub light_sampler: &'a mut Sampler,
}

/// Renders one pixel sample: both subpaths, then every technique, reported to `sink`.
pub fn pixel_sample<S: SampleSink + ?Sized>(
    scene: &Scene,
    ps: PixelSample,
    ws: &mut Workspace,
    sink: &mut S,
    stats: &mut RayStats,
) {
    pixel_camera_subpath(scene, ps.pixel, ps.cam_sampler, ps.max_depth, ws, stats);
    light_subpath(scene, ps.light_sampler, ps.max_depth, ws, stats);
    connect_all(
        scene,
        ps.pixel,
        ps.max_depth,
        ps.cam_sampler,
        ws,
        sink,
        stats,
    );
}
