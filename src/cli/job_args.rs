//! The render settings flags shared by `omis render` and `omis submit`.

use super::choices::{
    BpmWeightsArg, DirectArg, IntegratorArg, MisArg, OptimalDepthArg, SamplerArg, TechniquesArg,
    VcmWeightsArg,
};
use crate::job::{self, FieldError, JobSettings};
use clap::Args;

#[derive(Args, Clone, Debug)]
pub struct JobArgs {
    /// A worker tag the job needs (repeatable, or a comma-separated list): only workers with
    /// every such tag render it.
    #[arg(long = "require-tag", value_name = "TAG", value_delimiter = ',')]
    pub require_tags: Vec<String>,
    /// A value for a parameter of the scene file (Mitsuba's `$name`), winning over its
    /// `<default>`: `--define spp=64` (repeatable).
    #[arg(long = "define", value_name = "NAME=VALUE")]
    pub defines: Vec<String>,
    /// Samples per pixel (default: the scene's, else 16).
    #[arg(long)]
    pub spp: Option<u32>,
    /// Render passes for this many seconds instead (with --spp: whichever ends first); the last
    /// pass is fitted to the time left at the rate so far, so the render ends near the budget.
    /// The automatic D_opt pilot's time counts against it.
    #[arg(long)]
    pub time_budget: Option<f64>,
    /// Maximum path depth in bounces: 0 = emitters seen directly, 1 = direct light (default: the
    /// scene's, else 5).
    #[arg(long)]
    pub max_depth: Option<u32>,
    #[arg(long, value_enum, default_value_t = IntegratorArg::Pt)]
    pub integrator: IntegratorArg,
    /// BDPT technique weights.
    #[arg(long, value_enum, default_value_t = MisArg::Balance)]
    pub mis: MisArg,
    /// BDPT: every technique, or light tracing / NEE alone (validation: each is unbiased alone).
    #[arg(long, value_enum, default_value_t = TechniquesArg::All)]
    pub techniques: TechniquesArg,
    /// BDPT: write the weighted contribution of every (s, t) up to depth 3 as EXR layers
    /// `s<S>_t<T>`.
    #[arg(long)]
    pub strategies: bool,
    /// Write the image of every path depth as EXR layers `depth<d>`.
    #[arg(long)]
    pub depth_layers: bool,
    /// Optimal MIS: weight depths 1..=D optimally, balance above; `auto`: a pilot render of
    /// about 37k pixel samples (at most 1/64 of the job's, at least 4k or the whole frame when
    /// smaller) measures which depths pay at equal time.
    #[arg(long, default_value_t = OptimalDepthArg(None))]
    pub optimal_max_depth: OptimalDepthArg,
    /// Optimal MIS: regularisation toward the balance solution, in pseudo-samples (0 = the
    /// plain direct estimator).
    #[arg(long, default_value_t = crate::mis::DEFAULT_KAPPA)]
    pub kappa: f64,
    #[arg(long, value_enum, default_value_t = SamplerArg::Sobol)]
    pub sampler: SamplerArg,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Path tracer: how emitters are reached. `light` / `bsdf` use one strategy alone (for
    /// validation; both are unbiased, BSDF sampling cannot see point lights).
    #[arg(long, value_enum, default_value_t = DirectArg::Mis)]
    pub direct: DirectArg,
    /// Override the scene's resolution, e.g. 256x256 (the vertical field of view is kept).
    #[arg(long)]
    pub resolution: Option<String>,
    /// Tile edge in pixels [default: 128 for PT and BDPT balance / power where the frame has at
    /// least 128 such tiles (1920x1080 and up), else 64 where it has at least 256 such tiles
    /// (1024x1024 and up), else 32].
    #[arg(long)]
    pub tile_size: Option<u32>,
    /// Samples per pixel of the first pass (one task = one tile for one pass); each pass after
    /// it is twice as long, up to --max-pass-size.
    #[arg(long, default_value_t = job::DEFAULT_PASS_SIZE)]
    pub pass_size: u32,
    /// The longest pass in samples per pixel (= --pass-size for passes of constant length).
    #[arg(long, default_value_t = job::DEFAULT_MAX_PASS_SIZE)]
    pub max_pass_size: u32,
    /// eps of relMSE = mean (I - R)^2 / (R^2 + eps).
    #[arg(long, default_value_t = 0.01)]
    pub eps: f64,
    /// VCM: initial merge radius in scene units (default: 0.003 times the scene's
    /// bounding-sphere radius).
    #[arg(long)]
    pub radius: Option<f64>,
    /// VCM: radius reduction exponent alpha in (0, 1]; the radius of sample index i is
    /// r (i + 1)^((alpha - 1) / 2) (1: constant radius).
    #[arg(long, default_value_t = crate::integrator::vcm::DEFAULT_ALPHA as f64)]
    pub radius_alpha: f64,
    /// BPM: backward diffuse depth, the camera's non-specular vertex where photons merge.
    #[arg(long, default_value_t = 1)]
    pub bdd: u32,
    /// BPM: fixed --bdd, or --bdd and --bdd + 1 mixed by optimal weights.
    #[arg(long, value_enum, default_value_t = BpmWeightsArg::Optimal)]
    pub bpm_weights: BpmWeightsArg,
    /// VCM: Georgiev et al.'s weights, or the merges at the first two camera-side vertices
    /// split by Ershov et al.'s optimal weight.
    #[arg(long, value_enum, default_value_t = VcmWeightsArg::Georgiev)]
    pub vcm_weights: VcmWeightsArg,
    /// BDPT, VCM and BPM: subpaths also end by Russian roulette, each vertex from
    /// --roulette-from on continuing with its BSDF's albedo estimate (as SmallVCM's do): shorter
    /// subpaths, more variance on paths only one technique makes. Default: on for bdpt (from its
    /// 3rd vertex) and vcm (from the 1st), where it pays at equal time; off for bpm.
    #[arg(long, conflicts_with = "no_roulette")]
    pub roulette: bool,
    /// BDPT, VCM and BPM: the first subpath vertex (1 = the first surface hit) roulette may end a
    /// subpath at; implies --roulette. Default: 3 for bdpt; vcm and bpm take 1 only.
    #[arg(long, conflicts_with = "no_roulette", value_name = "N")]
    pub roulette_from: Option<u32>,
    /// BDPT, VCM and BPM: no Russian roulette (subpaths run to the max depth).
    #[arg(long)]
    pub no_roulette: bool,
}

impl JobArgs {
    /// The job settings these flags describe (validated).
    pub fn settings(&self) -> anyhow::Result<JobSettings> {
        let resolution = match &self.resolution {
            Some(r) => {
                let (w, h) = super::parse_resolution(r).map_err(anyhow::Error::msg)?;
                Some([w, h])
            }
            None => None,
        };
        let s = JobSettings {
            defines: parse_defines(&self.defines)?,
            resolution,
            spp: self.spp,
            time_budget_s: self.time_budget,
            integrator: self.integrator.into(),
            mis: self.mis.into(),
            techniques: self.techniques.into(),
            optimal_max_depth: self.optimal_max_depth.0,
            kappa: self.kappa,
            max_depth: self.max_depth,
            seed: self.seed,
            sampler: self.sampler.into(),
            direct: self.direct.into(),
            strategies: self.strategies,
            depth_layers: self.depth_layers,
            tile_size: self.tile_size,
            pass_size: self.pass_size,
            max_pass_size: self.max_pass_size,
            eps: self.eps,
            radius: self.radius,
            radius_alpha: self.radius_alpha,
            bdd: self.bdd,
            bpm_weights: self.bpm_weights.into(),
            vcm_weights: self.vcm_weights.into(),
            // The two flags conflict, so at most one is set.
            roulette: (self.roulette || self.no_roulette).then_some(self.roulette),
            roulette_from: self.roulette_from,
        };
        s.validate(&job::Limits::default()).map_err(flag_error)?;
        Ok(s)
    }
}

/// A job-settings error in the words of the command line: the flag that set the field.
pub fn flag_error(e: FieldError) -> anyhow::Error {
    let flag = match e.field.as_str() {
        "time_budget_s" => "time-budget".to_string(),
        "scene" => return anyhow::anyhow!("{}", e.message),
        f => f.replace('_', "-"),
    };
    anyhow::anyhow!("--{flag}: {}", e.message)
}

/// The scene parameters of repeated `--define NAME=VALUE` flags.
pub fn parse_defines(flags: &[String]) -> anyhow::Result<crate::scene::SceneParams> {
    let mut defines = std::collections::BTreeMap::new();
    for d in flags {
        let (k, v) = d
            .split_once('=')
            .filter(|(k, _)| !k.is_empty())
            .ok_or_else(|| anyhow::anyhow!("--define: expected NAME=VALUE, got '{d}'"))?;
        defines.insert(k.to_string(), v.to_string());
    }
    Ok(crate::scene::SceneParams::new(defines))
}
