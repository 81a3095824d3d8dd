//! Integrators: they turn a scene into samples, and add them to a tile's film.
//!
//! A task renders samples [s0, s1) of every pixel of a tile (`render_tile`). Every random number
//! comes from (seed, pixel, sample index), so a sample does not depend on the tiling, the thread
//! or the machine that renders it; how tasks are scheduled and merged is `job::schedule`'s.

pub mod bdpt;
pub mod bpm;
pub mod path;
pub mod photon_map;
mod tile;
pub mod vcm;

pub use tile::{render_tile, render_tile_cached};

use crate::film::FilmLayout;
use crate::mis::MisKind;
use crate::sampler::SamplerKind;
use serde::{Deserialize, Serialize};

/// Which integrator renders the image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum IntegratorKind {
    /// Unidirectional path tracing with NEE and MIS (power heuristic).
    #[default]
    Pt,
    /// Bidirectional path tracing with every strategy.
    Bdpt,
    /// Vertex connection and merging: BDPT's connections plus photon merging, one MIS.
    Vcm,
    /// Bidirectional photon mapping: merging only, at a fixed backward diffuse depth or mixing
    /// two with Ershov et al.'s optimal weights.
    Bpm,
}

/// Which BDPT techniques contribute. Not a weighting rule: the validation modes keep one
/// technique per path depth, so each is an unbiased estimator on its own, unweighted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Techniques {
    /// Every (s, t), weighted by the MIS rule.
    #[default]
    All,
    /// Light tracing alone: every t = 1 technique.
    Lt,
    /// Next-event estimation alone: every (1, t >= 2); depth 0 by (0, 2).
    Nee,
}

impl Techniques {
    /// Whether technique (s, t) of a depth with `n` techniques contributes.
    #[inline]
    pub fn selects(self, s: u32, t: u32, n: usize) -> bool {
        match self {
            Techniques::All => true,
            Techniques::Lt => t == 1,
            // Depth 0 (an emitter seen directly) has only (0, 2) on the camera side.
            Techniques::Nee => s == 1 && t >= 2 || s == 0 && t == 2 && n == 2,
        }
    }
}

/// Everything besides the scene that determines the image.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct RenderSettings {
    /// Path tracing or BDPT.
    pub integrator: IntegratorKind,
    /// Samples per pixel of the sampler's stratification block: a fixed-spp job's total, a
    /// time-budget job's pass size (`Resolved::spp` is the job's total).
    #[serde(rename = "spp")]
    pub sample_block: u32,
    /// Longest path kept, in bounces.
    pub max_depth: u32,
    /// Seed of every random number.
    pub seed: u64,
    /// Sample generator.
    pub sampler: SamplerKind,
    /// Path tracer only: how emitters are reached (MIS, or one strategy alone for validation).
    #[serde(default)]
    pub direct: path::DirectStrategy,
    /// BDPT only: technique weights.
    #[serde(default)]
    pub mis: MisKind,
    /// BDPT only: which techniques contribute (all, or one alone for validation).
    #[serde(default)]
    pub techniques: Techniques,
    /// BDPT only: keep the weighted contribution of every (s, t) up to depth 3 as extra layers.
    #[serde(default)]
    pub strategies: bool,
    /// Optimal MIS: the largest depth weighted optimally (D_opt).
    #[serde(default = "default_optimal_max_depth")]
    pub optimal_max_depth: u32,
    /// Optimal MIS: strength of the regularisation toward the balance solution (kappa; 0 = the
    /// plain direct estimator of Kondapaneni et al. 2019).
    #[serde(default = "default_kappa")]
    pub optimal_kappa: f64,
    /// Keep the image of every path depth 0 ..= max_depth as extra layers.
    #[serde(default)]
    pub depth_layers: bool,
    /// VCM only: initial merge radius in scene units (0: `vcm::DEFAULT_RADIUS_FACTOR` times the
    /// scene's bounding-sphere radius).
    #[serde(default)]
    pub radius: f32,
    /// VCM only: radius reduction exponent alpha, r_i = r_0 (i + 1)^((alpha - 1) / 2).
    #[serde(default = "default_alpha")]
    pub radius_alpha: f32,
    /// BPM only: the backward diffuse depth M (the camera's M-th non-specular vertex merges).
    #[serde(default = "default_bdd")]
    pub bdd: u32,
    /// BPM only: fixed BDD, or BDD and BDD + 1 mixed by the optimal weights.
    #[serde(default)]
    pub bpm_weights: bpm::BpmWeights,
    /// VCM only: Georgiev et al.'s weights, or Ershov et al.'s split of the merges at x_1 / x_2.
    #[serde(default)]
    pub vcm_weights: vcm::VcmWeights,
    /// BDPT, VCM and BPM: subpaths also end by Russian roulette (q = the BSDF's albedo
    /// estimate at each vertex); the path tracer always uses its own.
    #[serde(default)]
    pub roulette: bool,
    /// The first subpath vertex (1 = the first surface hit) that roulette may end a subpath at;
    /// the vertices before it always continue.
    #[serde(default = "default_roulette_from")]
    pub roulette_from: u32,
}

/// Roulette from the first surface vertex: what `roulette` meant before `roulette_from`.
fn default_roulette_from() -> u32 {
    1
}

fn default_bdd() -> u32 {
    1
}

fn default_alpha() -> f32 {
    vcm::DEFAULT_ALPHA
}

fn default_optimal_max_depth() -> u32 {
    crate::mis::DEFAULT_OPTIMAL_MAX_DEPTH
}

fn default_kappa() -> f64 {
    crate::mis::DEFAULT_KAPPA
}

impl RenderSettings {
    /// The vertex BDPT-family subpaths' Russian roulette starts at, or None without roulette.
    pub fn roulette_start(&self) -> Option<u32> {
        self.roulette.then_some(self.roulette_from)
    }

    /// Number of per-depth layers kept (0 when not requested).
    pub fn depth_count(&self) -> usize {
        if self.depth_layers {
            self.max_depth.min(bdpt::MAX_DEPTH) as usize + 1
        } else {
            0
        }
    }

    /// Whether optimal weights apply to this render at all (BDPT, optimal MIS, every technique),
    /// whatever its D_opt.
    pub fn optimal_applies(&self) -> bool {
        self.integrator == IntegratorKind::Bdpt
            && self.mis.is_optimal()
            && self.techniques == Techniques::All
    }

    /// The optimal-MIS layout when this render accumulates optimal systems.
    pub fn optimal_layout(&self) -> Option<crate::mis::Layout> {
        (self.optimal_applies() && self.optimal_max_depth >= 1)
            .then(|| crate::mis::Layout::new(self.optimal_max_depth.min(self.max_depth)))
    }

    /// The accumulators a film of this render keeps.
    pub fn film_layout(&self) -> FilmLayout {
        FilmLayout {
            strategy_layers: self.strategies && self.integrator == IntegratorKind::Bdpt,
            depth_layers: self.depth_count(),
            optimal: self.optimal_layout(),
            progressive: self.mis == MisKind::OptimalProgressive && self.optimal_layout().is_some(),
            kappa: self.optimal_kappa,
            variance_layer: self.integrator == IntegratorKind::Pt,
            splats: self.integrator != IntegratorKind::Pt,
        }
    }
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            integrator: IntegratorKind::Pt,
            sample_block: 16,
            max_depth: 5,
            seed: 0,
            sampler: SamplerKind::Sobol,
            direct: path::DirectStrategy::Mis,
            mis: MisKind::Balance,
            techniques: Techniques::All,
            strategies: false,
            optimal_max_depth: default_optimal_max_depth(),
            optimal_kappa: crate::mis::DEFAULT_KAPPA,
            depth_layers: false,
            radius: 0.0,
            radius_alpha: vcm::DEFAULT_ALPHA,
            bdd: 1,
            bpm_weights: bpm::BpmWeights::Optimal,
            vcm_weights: vcm::VcmWeights::Georgiev,
            roulette: false,
            roulette_from: default_roulette_from(),
        }
    }
}
