//! What to render besides the scene: the settings of a render job, shared by `omis render`, the
//! coordinator's REST API and the worker. One place validates them, so the command line and the
//! service refuse the same inputs with the same words, and resolve them to the same
//! `RenderSettings` (the in-process and distributed renders of a job must be equal).

pub mod frames;
pub mod optimal_depth;
mod resolve;
mod schedule;
mod sizes;
#[cfg(test)]
mod tests;
mod validate;

pub use resolve::Resolved;
pub use schedule::{RenderOutput, make_tiles};
pub use sizes::{
    DEFAULT_MAX_PASS_SIZE, DEFAULT_PASS_SIZE, DEFAULT_TILE_SIZE, HUGE_TILE_MIN_TASKS,
    HUGE_TILE_SIZE, LARGE_TILE_MIN_TASKS, LARGE_TILE_SIZE, PHOTON_MAP_BYTES_PER_PIXEL,
    PHOTON_PASS_BYTES, auto_tile_size, photon_passes,
};

use crate::integrator::path::DirectStrategy;
use crate::integrator::{self, IntegratorKind, Techniques};
use crate::mis::MisKind;
use crate::sampler::SamplerKind;
use crate::scene::SceneParams;
use serde::{Deserialize, Serialize};

/// A setting that is out of range: which one (its JSON name) and why.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct FieldError {
    /// The setting's JSON name.
    pub field: String,
    /// Why it was refused.
    pub message: String,
}

impl FieldError {
    /// The error of setting `field`.
    pub fn new(field: impl Into<String>, message: impl Into<String>) -> FieldError {
        FieldError {
            field: field.into(),
            message: message.into(),
        }
    }
}

/// The settings of a render job. Every field has a default; unknown fields are refused.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct JobSettings {
    /// Values of the scene file's parameters (Mitsuba's `$name`; only Mitsuba 2/3 files have
    /// them), winning over the file's `<default>`s.
    #[serde(skip_serializing_if = "SceneParams::is_empty")]
    pub defines: SceneParams,
    /// [width, height]; default: the scene's.
    pub resolution: Option<[u32; 2]>,
    /// Samples per pixel; default: the scene's, else 16 (unless a time budget is given).
    pub spp: Option<u32>,
    /// Render passes until this many seconds have passed (at least one pass; the last one
    /// fitted to the time left, `Resolved::fit_to_budget`; the D_opt pilot's time counted). With
    /// `spp` too, whichever comes first ends the job.
    pub time_budget_s: Option<f64>,
    /// Which integrator renders the job.
    pub integrator: IntegratorKind,
    /// How BDPT's techniques are weighted.
    pub mis: MisKind,
    /// BDPT: which techniques contribute (all, or light tracing / NEE alone for validation).
    pub techniques: Techniques,
    /// Optimal MIS: depths 1 ..= D weighted optimally, balance above; None (the default): chosen
    /// by a pilot render (`optimal_depth::choose`).
    pub optimal_max_depth: Option<u32>,
    /// Optimal MIS: regularisation toward the balance solution (0 = the plain direct estimator).
    pub kappa: f64,
    /// Maximum path depth in bounces; default: the scene's, else 5.
    pub max_depth: Option<u32>,
    /// Seed of the sampler's random numbers (equal seeds give equal images).
    pub seed: u64,
    /// How sample points are generated.
    pub sampler: SamplerKind,
    /// Path tracer: how emitters are reached.
    pub direct: DirectStrategy,
    /// BDPT: weighted contribution of each (s, t) up to depth 3 as EXR layers.
    pub strategies: bool,
    /// The image of each path depth as EXR layers `depth<d>`.
    pub depth_layers: bool,
    /// Tile edge in pixels; None (the default): `auto_tile_size` of the frame.
    pub tile_size: Option<u32>,
    /// Samples per pixel of the first pass (a task renders one tile for one pass). Each pass
    /// after it is twice as long as the one before, up to `max_pass_size`.
    pub pass_size: u32,
    /// The longest pass, in samples per pixel (at least `pass_size`; equal: constant passes).
    pub max_pass_size: u32,
    /// eps of relMSE = mean (I - R)^2 / (R^2 + eps).
    pub eps: f64,
    /// VCM: initial merge radius in scene units, at most the scene's bounding-sphere radius;
    /// default: 0.003 times it.
    pub radius: Option<f64>,
    /// VCM: radius reduction exponent alpha in (0, 1]: r_i = r_0 (i + 1)^((alpha - 1) / 2).
    pub radius_alpha: f64,
    /// BPM: backward diffuse depth M, 1 ..= 64.
    pub bdd: u32,
    /// BPM: fixed BDD or BDD / BDD + 1 mixed by the optimal weights.
    pub bpm_weights: integrator::bpm::BpmWeights,
    /// VCM: Georgiev et al.'s weights, or with the merges at x_1 and x_2 split by Ershov et
    /// al.'s optimal weight.
    pub vcm_weights: integrator::vcm::VcmWeights,
    /// BDPT, VCM, BPM: subpaths also end by Russian roulette. None (the default): on for VCM,
    /// where it pays at equal time (BENCHMARKS.md, "BDPT and VCM against SmallVCM"), and for BDPT from its
    /// `bdpt::ROULETTE_FROM`-th vertex (BENCHMARKS.md, "BDPT against pbrt-v3"); off for BPM; on when `roulette_from` is
    /// set.
    pub roulette: Option<bool>,
    /// BDPT, VCM, BPM: the first subpath vertex (1 = the first surface hit) roulette may end a
    /// subpath at. None: `bdpt::ROULETTE_FROM` for BDPT, 1 (every vertex, SmallVCM's) for VCM and
    /// BPM, which take no other.
    pub roulette_from: Option<u32>,
}

impl Default for JobSettings {
    fn default() -> Self {
        JobSettings {
            defines: SceneParams::default(),
            resolution: None,
            spp: None,
            time_budget_s: None,
            integrator: IntegratorKind::Pt,
            mis: MisKind::Balance,
            techniques: Techniques::All,
            optimal_max_depth: None,
            kappa: crate::mis::DEFAULT_KAPPA,
            max_depth: None,
            seed: 0,
            sampler: SamplerKind::Sobol,
            direct: DirectStrategy::Mis,
            strategies: false,
            depth_layers: false,
            tile_size: None,
            pass_size: DEFAULT_PASS_SIZE,
            max_pass_size: DEFAULT_MAX_PASS_SIZE,
            eps: 0.01,
            radius: None,
            radius_alpha: integrator::vcm::DEFAULT_ALPHA as f64,
            bdd: 1,
            bpm_weights: integrator::bpm::BpmWeights::Optimal,
            vcm_weights: integrator::vcm::VcmWeights::Georgiev,
            roulette: None,
            roulette_from: None,
        }
    }
}

/// Limits a coordinator puts on jobs (the command line uses `Limits::default()`).
#[derive(Clone, Debug)]
pub struct Limits {
    /// Largest image width or height.
    pub max_resolution: u32,
    /// Largest total samples per pixel.
    pub max_spp: u32,
    /// Most triangles a scene may have.
    pub max_triangles: usize,
    /// Longest time budget in seconds.
    pub max_time_budget_s: f64,
    /// Tiles of a frame, i.e. tasks of one pass: the coordinator keeps a row per task.
    pub max_tasks_per_pass: u32,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_resolution: 16384,
            max_spp: 1 << 20,
            max_triangles: 50_000_000,
            max_time_budget_s: 7.0 * 24.0 * 3600.0,
            // A frame at the largest resolution in tiles of the default size.
            max_tasks_per_pass: 1 << 18,
        }
    }
}

/// Largest optimal-MIS regularisation (pseudo-samples toward balance).
pub const MAX_KAPPA: f64 = 1e6;
/// Shortest time budget in seconds.
pub const MIN_TIME_BUDGET_S: f64 = 1e-3;

impl JobSettings {
    /// Whether the job's pixels hold no optimal-MIS systems: the path tracer, and BDPT with a
    /// heuristic (VCM and BPM are left at the tiles they were measured with).
    pub fn light_pixels(&self) -> bool {
        match self.integrator {
            IntegratorKind::Pt => true,
            IntegratorKind::Bdpt => !self.mis.is_optimal(),
            _ => false,
        }
    }

    /// `auto_tile_size` of a `width` x `height` frame for this job.
    pub fn auto_tile_size(&self, width: u32, height: u32) -> u32 {
        auto_tile_size(width, height, self.light_pixels())
    }
}
