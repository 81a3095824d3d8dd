//! What to render besides the scene: the settings of a render job, shared by `omis render`, the
//! coordinator's REST API and the worker. One place validates them, so the command line and the
//! service refuse the same inputs with the same words, and resolve them to the same
//! `RenderSettings` (the in-process and distributed renders of a job must be equal).

pub mod optimal_depth;
mod schedule;

pub use schedule::{RenderOutput, make_tiles};

use crate::film::FilmLayout;
use crate::integrator::path::DirectStrategy;
use crate::integrator::{self, IntegratorKind, RenderSettings, Techniques};
use crate::mis::MisKind;
use crate::sampler::SamplerKind;
use crate::scene::{Scene, SceneParams};
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
    /// where it pays at equal time (BENCHMARKS.md #15, stop 28), and for BDPT from its
    /// `bdpt::ROULETTE_FROM`-th vertex (#13, stop 46); off for BPM; on when `roulette_from` is
    /// set.
    pub roulette: Option<bool>,
    /// BDPT, VCM, BPM: the first subpath vertex (1 = the first surface hit) roulette may end a
    /// subpath at. None: `bdpt::ROULETTE_FROM` for BDPT, 1 (every vertex, SmallVCM's) for VCM and
    /// BPM, which take no other.
    pub roulette_from: Option<u32>,
}

/// Default samples of the first pass: the first preview after 16 spp.
pub const DEFAULT_PASS_SIZE: u32 = 16;
/// Default longest pass: passes double from `DEFAULT_PASS_SIZE` up to this, so that a job's
/// merges grow as O(log spp) rather than O(spp), and light-tracing records per task stay bounded.
pub const DEFAULT_MAX_PASS_SIZE: u32 = 256;
/// VCM and BPM: every process that renders a pass holds the photon map of each of its
/// iterations at once (a map keeps the iteration's light subpaths and photons: 591 bytes per
/// pixel on SmallVCM's scene 2 at depth 9, BENCHMARKS.md #15), so their passes are kept short
/// enough that a pass's maps fit in this many bytes, at `PHOTON_MAP_BYTES_PER_PIXEL` a map.
pub const PHOTON_PASS_BYTES: u64 = 4 << 30;
/// What a photon map is assumed to take per pixel when passes are limited (about twice what
/// SmallVCM's scene 2 takes).
pub const PHOTON_MAP_BYTES_PER_PIXEL: u64 = 1024;

/// VCM's and BPM's (first pass, longest pass): the settings', each at most the largest power of
/// two of iterations whose photon maps fit in `PHOTON_PASS_BYTES` (at least 1).
pub fn photon_passes(width: u32, height: u32, pass_size: u32, max_pass_size: u32) -> (u32, u32) {
    let per_map = (width as u64 * height as u64 * PHOTON_MAP_BYTES_PER_PIXEL).max(1);
    let fit = (PHOTON_PASS_BYTES / per_map).clamp(1, 1 << 16) as u32;
    let limit = 1 << fit.ilog2();
    let first = pass_size.min(limit);
    (first, max_pass_size.max(first).min(limit))
}

/// Tile edge of frames with fewer than `LARGE_TILE_MIN_TASKS` tiles of `LARGE_TILE_SIZE`.
pub const DEFAULT_TILE_SIZE: u32 = 32;
/// Tile edge of large frames: a task of 4x the pixels costs the coordinator about what a small
/// one does (1080p path tracing: 26 % less coordinator CPU, BDPT: 10-18 % fewer bytes per
/// sample; BENCHMARKS.md #12, stops 28 and 29).
pub const LARGE_TILE_SIZE: u32 = 64;
/// Tasks per pass a frame must have in tiles of `LARGE_TILE_SIZE` to get them (1024x1024 and
/// up), so that a pass still keeps dozens of workers busy.
pub const LARGE_TILE_MIN_TASKS: u64 = 256;
/// Tile edge of large frames for jobs whose pixels hold no optimal-MIS systems (the path
/// tracer, BDPT with the balance or power heuristic): their tasks are short and light, so a task
/// of 4x the pixels cuts what the coordinator spends per pixel sample by a quarter to a third
/// (1080p: PT 2.8 -> 1.8 %, BDPT balance 1.8 -> 1.4 % of the workers' CPU; BDPT's light-tracing
/// splats aggregate per pixel, 10.7 -> 8.6 bytes per pixel sample; BENCHMARKS.md #12, stop 33). Optimal-MIS
/// tasks keep `LARGE_TILE_SIZE`: their systems (up to 1.3 kB a pixel) and records make a task
/// of this size heavy for the workers, and the coordinator gains less.
pub const HUGE_TILE_SIZE: u32 = 128;
/// Tasks per pass a frame must have in tiles of `HUGE_TILE_SIZE` to get them (1920x1080 and
/// up): a job queues two passes at once, so a pass of 128 tasks keeps a farm of 100 busy.
pub const HUGE_TILE_MIN_TASKS: u64 = 128;

/// The tile edge of a job that does not set one: `HUGE_TILE_SIZE` for a `light` job (no
/// optimal-MIS systems: `JobSettings::light_pixels`) whose frame has at least
/// `HUGE_TILE_MIN_TASKS` such tiles, else `LARGE_TILE_SIZE` where the frame has at least
/// `LARGE_TILE_MIN_TASKS` such tiles, else `DEFAULT_TILE_SIZE`.
pub fn auto_tile_size(width: u32, height: u32, light: bool) -> u32 {
    let tiles = |size: u32| {
        let size = size as u64;
        (width as u64).div_ceil(size) * (height as u64).div_ceil(size)
    };
    if light && tiles(HUGE_TILE_SIZE) >= HUGE_TILE_MIN_TASKS {
        HUGE_TILE_SIZE
    } else if tiles(LARGE_TILE_SIZE) >= LARGE_TILE_MIN_TASKS {
        LARGE_TILE_SIZE
    } else {
        DEFAULT_TILE_SIZE
    }
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

/// Refuses a frame of more than `limits.max_tasks_per_pass` tiles (field `tile_size`).
fn check_tiles(width: u32, height: u32, tile: u32, limits: &Limits) -> Result<(), FieldError> {
    let tiles = |t: u64| (width as u64).div_ceil(t) * (height as u64).div_ceil(t);
    let max = limits.max_tasks_per_pass as u64;
    if tiles(tile.max(1) as u64) <= max {
        return Ok(());
    }
    let smallest = (1..=width.max(height) as u64)
        .find(|&t| tiles(t) <= max)
        .unwrap_or(width.max(height) as u64);
    Err(FieldError::new(
        "tile_size",
        format!(
            "{width}x{height} in tiles of {tile} is {} tasks per pass, more than the limit of \
             {max} (max_tasks_per_pass); use a tile_size of at least {smallest}",
            tiles(tile.max(1) as u64)
        ),
    ))
}

/// A job's settings resolved against its scene: everything a worker needs to render a task.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Resolved {
    /// Values of the scene file's parameters, with which every process loads the scene.
    #[serde(default, skip_serializing_if = "SceneParams::is_empty")]
    pub defines: SceneParams,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// `render.spp` is the stratification block of the sampler: the total spp of a fixed-spp
    /// job, the pass size of a time-budget job.
    pub render: RenderSettings,
    /// Total samples per pixel, or None for a time budget without spp.
    pub spp: Option<u32>,
    /// Wall-clock budget in seconds, if any.
    pub time_budget_s: Option<f64>,
    /// A time-budget job's last sample per pixel, set when its last pass is fitted to the time
    /// left (`fit_to_budget`); None until then, and for jobs without a budget.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub budget_spp: Option<u32>,
    /// Wall seconds the D_opt pilot took, where it ran (`optimal_depth`): a time budget counts
    /// them, so that a job with the pilot takes no more time than one without.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pilot_s: Option<f64>,
    /// Tile edge in pixels.
    pub tile_size: u32,
    /// Samples of the first pass.
    pub pass_size: u32,
    /// Passes double up to this many samples; None: every pass has `pass_size` samples.
    #[serde(default)]
    pub max_pass_size: Option<u32>,
    /// eps of relMSE = mean (I - R)^2 / (R^2 + eps).
    pub eps: f64,
    /// Optimal MIS with D_opt left to the pilot: what it measured and chose
    /// (`render.optimal_max_depth` holds the choice).
    #[serde(default)]
    pub optimal_depth: Option<optimal_depth::DepthChoice>,
}

impl Resolved {
    /// Header attributes of the job's EXR (the same in-process and from the service).
    pub fn exr_attributes(&self, scene: &str, spp_done: u32) -> Vec<(&'static str, String)> {
        let r = &self.render;
        let mut attributes = vec![
            ("omis.scene", scene.to_string()),
            (
                "omis.integrator",
                format!("{:?}", r.integrator).to_lowercase(),
            ),
            ("omis.mis", r.mis.name().to_string()),
            ("omis.spp", spp_done.to_string()),
            ("omis.max_depth", r.max_depth.to_string()),
            ("omis.seed", r.seed.to_string()),
        ];
        if r.techniques != Techniques::All {
            attributes.push((
                "omis.techniques",
                format!("{:?}", r.techniques).to_lowercase(),
            ));
        }
        if r.integrator != IntegratorKind::Pt {
            let on = if r.roulette { "on" } else { "off" };
            attributes.push(("omis.roulette", on.to_string()));
            if r.roulette {
                attributes.push(("omis.roulette_from", r.roulette_from.to_string()));
            }
        }
        if let Some(d_opt) = self.optimal_max_depth() {
            attributes.push(("omis.optimal_max_depth", d_opt.to_string()));
            attributes.push(("omis.kappa", r.optimal_kappa.to_string()));
            if let Some(c) = &self.optimal_depth {
                attributes.push(("omis.optimal_max_depth_auto", c.summary()));
            }
        }
        attributes
    }

    /// Optimal MIS: the largest depth weighted optimally (0: balance at every depth); None for
    /// other weights.
    pub fn optimal_max_depth(&self) -> Option<u32> {
        self.render
            .mis
            .is_optimal()
            .then(|| self.film_layout().d_opt().unwrap_or(0))
    }

    /// The accumulators the job's films keep.
    pub fn film_layout(&self) -> FilmLayout {
        self.render.film_layout()
    }
}

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

    /// Checks the settings that do not depend on the scene.
    pub fn validate(&self, limits: &Limits) -> Result<(), FieldError> {
        if let Some([w, h]) = self.resolution
            && (w == 0 || h == 0 || w > limits.max_resolution || h > limits.max_resolution)
        {
            return Err(FieldError::new(
                "resolution",
                format!(
                    "{w}x{h} is outside 1x1 .. {m}x{m}",
                    m = limits.max_resolution
                ),
            ));
        }
        if let Some(spp) = self.spp
            && (spp == 0 || spp > limits.max_spp)
        {
            return Err(FieldError::new(
                "spp",
                format!("{spp} is outside 1 ..= {}", limits.max_spp),
            ));
        }
        if let Some(t) = self.time_budget_s
            && !(t >= MIN_TIME_BUDGET_S && t <= limits.max_time_budget_s)
        {
            return Err(FieldError::new(
                "time_budget_s",
                format!(
                    "{t} is outside [{MIN_TIME_BUDGET_S}, {}] seconds",
                    limits.max_time_budget_s
                ),
            ));
        }
        if self.mis.is_optimal() && self.integrator != IntegratorKind::Bdpt {
            return Err(FieldError::new(
                "mis",
                "optimal MIS needs the bdpt integrator",
            ));
        }
        if self.techniques != Techniques::All && self.integrator != IntegratorKind::Bdpt {
            return Err(FieldError::new(
                "techniques",
                "selecting techniques needs the bdpt integrator",
            ));
        }
        if self.techniques != Techniques::All && self.mis.is_optimal() {
            return Err(FieldError::new(
                "techniques",
                "light tracing or NEE alone has one technique per depth: nothing for optimal MIS to weight",
            ));
        }
        if let Some(d) = self.optimal_max_depth
            && d > crate::mis::optimal::MAX_OPTIMAL_DEPTH
        {
            return Err(FieldError::new(
                "optimal_max_depth",
                format!("{d} exceeds {}", crate::mis::optimal::MAX_OPTIMAL_DEPTH),
            ));
        }
        if !(self.kappa >= 0.0 && self.kappa <= MAX_KAPPA) {
            return Err(FieldError::new(
                "kappa",
                format!("must be a number within 0 ..= {MAX_KAPPA:e}"),
            ));
        }
        if let Some(d) = self.max_depth
            && d > integrator::bdpt::MAX_DEPTH
        {
            return Err(FieldError::new(
                "max_depth",
                format!("{d} exceeds the limit of {}", integrator::bdpt::MAX_DEPTH),
            ));
        }
        if let Some(r) = self.radius
            && !(r > 0.0 && r <= 1e9)
        {
            return Err(FieldError::new(
                "radius",
                format!("{r} is outside (0, 1e9] scene units"),
            ));
        }
        if self.bdd == 0 || self.bdd > integrator::bdpt::MAX_DEPTH {
            return Err(FieldError::new(
                "bdd",
                format!(
                    "{} is outside 1 ..= {}",
                    self.bdd,
                    integrator::bdpt::MAX_DEPTH
                ),
            ));
        }
        if let Some(n) = self.roulette_from {
            if n == 0 || n > integrator::bdpt::MAX_DEPTH {
                return Err(FieldError::new(
                    "roulette_from",
                    format!(
                        "{n} is outside 1 ..= {} (1: the first surface vertex)",
                        integrator::bdpt::MAX_DEPTH
                    ),
                ));
            }
            if self.roulette == Some(false) {
                return Err(FieldError::new(
                    "roulette_from",
                    "is set while roulette is false",
                ));
            }
            // VCM's and BPM's merge weights take every vertex's q as the same from both sides,
            // which holds for a start at the first vertex only.
            if n > 1 && matches!(self.integrator, IntegratorKind::Vcm | IntegratorKind::Bpm) {
                return Err(FieldError::new(
                    "roulette_from",
                    format!("{n}: vcm and bpm take 1 only (roulette at every vertex)"),
                ));
            }
        }
        if !(self.radius_alpha > 0.0 && self.radius_alpha <= 1.0) {
            return Err(FieldError::new(
                "radius_alpha",
                format!("{} is outside (0, 1]", self.radius_alpha),
            ));
        }
        if let Some(t) = self.tile_size
            && (t == 0 || t > 4096)
        {
            return Err(FieldError::new("tile_size", "must be within 1 ..= 4096"));
        }
        if self.pass_size == 0 || self.pass_size > 1 << 16 {
            return Err(FieldError::new("pass_size", "must be within 1 ..= 65536"));
        }
        if self.max_pass_size == 0 || self.max_pass_size > 1 << 16 {
            return Err(FieldError::new(
                "max_pass_size",
                "must be within 1 ..= 65536",
            ));
        }
        if !(self.eps > 0.0 && self.eps.is_finite()) {
            return Err(FieldError::new("eps", "must be a finite number > 0"));
        }
        if let Some([w, h]) = self.resolution {
            let tile = self.tile_size.unwrap_or_else(|| self.auto_tile_size(w, h));
            check_tiles(w, h, tile, limits)?;
        }
        Ok(())
    }

    /// Applies the resolution to the scene's camera and resolves the settings against the
    /// scene's defaults, and checks the result against `limits` whichever of the two each
    /// value came from.
    pub fn resolve(&self, scene: &mut Scene, limits: &Limits) -> Result<Resolved, FieldError> {
        self.validate(limits)?;
        if let Some([w, h]) = self.resolution {
            scene.camera = scene
                .camera
                .with_resolution(w, h)
                .map_err(|e| FieldError::new("resolution", e))?;
        }
        let (width, height) = (scene.camera.width, scene.camera.height);
        if width == 0
            || height == 0
            || width > limits.max_resolution
            || height > limits.max_resolution
        {
            return Err(FieldError::new(
                "resolution",
                format!(
                    "the scene's {width}x{height} is outside 1x1 .. {m}x{m}",
                    m = limits.max_resolution
                ),
            ));
        }
        let tile_size = self
            .tile_size
            .unwrap_or_else(|| self.auto_tile_size(width, height));
        check_tiles(width, height, tile_size, limits)?;
        if let Some(r) = self.radius {
            let (lo, hi) = scene.bounds();
            let bound = 0.5 * (hi - lo).length() as f64;
            if bound.is_finite() && r > bound {
                return Err(FieldError::new(
                    "radius",
                    format!(
                        "{r} exceeds the scene's bounding-sphere radius {bound}: every photon \
                         would merge with every camera vertex"
                    ),
                ));
            }
        }
        if scene.stats.triangles > limits.max_triangles {
            return Err(FieldError::new(
                "scene",
                format!(
                    "{} triangles exceed the limit of {}",
                    scene.stats.triangles, limits.max_triangles
                ),
            ));
        }
        let spp = match (self.spp, self.time_budget_s) {
            (Some(s), _) => Some(s),
            (None, Some(_)) => None,
            (None, None) => {
                let s = scene.defaults.spp.unwrap_or(16);
                if s == 0 || s > limits.max_spp {
                    return Err(FieldError::new(
                        "spp",
                        format!(
                            "the scene's default of {s} is outside 1 ..= {}; give spp",
                            limits.max_spp
                        ),
                    ));
                }
                Some(s)
            }
        };
        let max_depth = self.max_depth.or(scene.defaults.max_depth).unwrap_or(5);
        if max_depth > integrator::bdpt::MAX_DEPTH {
            return Err(FieldError::new(
                "max_depth",
                format!(
                    "{max_depth} (the scene's default) exceeds the limit of {}",
                    integrator::bdpt::MAX_DEPTH
                ),
            ));
        }
        let (pass_size, max_pass_size) =
            if matches!(self.integrator, IntegratorKind::Vcm | IntegratorKind::Bpm) {
                photon_passes(width, height, self.pass_size, self.max_pass_size)
            } else {
                (self.pass_size, self.max_pass_size.max(self.pass_size))
            };
        let mut render = RenderSettings {
            integrator: self.integrator,
            spp: spp.unwrap_or(pass_size),
            max_depth,
            seed: self.seed,
            sampler: self.sampler,
            direct: self.direct,
            mis: self.mis,
            techniques: self.techniques,
            strategies: self.strategies,
            optimal_max_depth: self
                .optimal_max_depth
                .unwrap_or(crate::mis::DEFAULT_OPTIMAL_MAX_DEPTH),
            optimal_kappa: self.kappa,
            depth_layers: self.depth_layers,
            radius: self.radius.unwrap_or(0.0) as f32,
            radius_alpha: self.radius_alpha as f32,
            bdd: self.bdd,
            bpm_weights: self.bpm_weights,
            vcm_weights: self.vcm_weights,
            roulette: self.roulette.unwrap_or(
                self.roulette_from.is_some()
                    || matches!(self.integrator, IntegratorKind::Vcm | IntegratorKind::Bdpt),
            ),
            roulette_from: self.roulette_from.unwrap_or(match self.integrator {
                IntegratorKind::Bdpt => integrator::bdpt::ROULETTE_FROM,
                _ => 1,
            }),
        };
        let pilot_start = std::time::Instant::now();
        let clock = || pilot_start.elapsed().as_secs_f64();
        let optimal_depth =
            (self.optimal_max_depth.is_none() && render.optimal_applies()).then(|| {
                let pixels = width as u64 * height as u64;
                let size = optimal_depth::JobSize {
                    samples: spp.map(|s| pixels.saturating_mul(s as u64)),
                    budget: self.time_budget_s.map(|seconds| optimal_depth::Budget {
                        seconds,
                        clock: &clock,
                    }),
                };
                optimal_depth::choose(scene, &render, self.eps, size)
            });
        let pilot_s = optimal_depth
            .is_some()
            .then(|| pilot_start.elapsed().as_secs_f64());
        if let Some(c) = &optimal_depth {
            render.optimal_max_depth = c.chosen;
        }
        Ok(Resolved {
            defines: self.defines.clone(),
            width,
            height,
            render,
            spp,
            time_budget_s: self.time_budget_s,
            budget_spp: None,
            pilot_s,
            tile_size,
            pass_size,
            max_pass_size: Some(max_pass_size),
            eps: self.eps,
            optimal_depth,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A VCM or BPM pass holds one photon map per iteration in every process that renders it:
    /// passes are cut to what fits in `PHOTON_PASS_BYTES`; other integrators keep theirs.
    #[test]
    fn photon_passes_fit_the_memory_budget() {
        assert_eq!(photon_passes(512, 512, 16, 256), (16, 16));
        assert_eq!(photon_passes(512, 512, 1, 4), (1, 4));
        assert_eq!(photon_passes(1920, 1080, 16, 256), (2, 2));
        assert_eq!(photon_passes(3840, 2160, 16, 256), (1, 1));
        assert_eq!(photon_passes(64, 64, 16, 256), (16, 256));
        for (w, h) in [(1, 1), (512, 512), (1920, 1080), (65536, 65536)] {
            let (first, max) = photon_passes(w, h, 16, 256);
            assert!(first >= 1 && max >= first && max.is_power_of_two());
            let maps = max as u64 * w as u64 * h as u64 * PHOTON_MAP_BYTES_PER_PIXEL;
            assert!(max == 1 || maps <= PHOTON_PASS_BYTES, "{w}x{h}: {max}");
        }
        let mut scene = crate::scene::Scene::load(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/scenes/cornell-box.json"
        )))
        .expect("the Cornell box");
        for (integrator, pass) in [
            (IntegratorKind::Vcm, Some(16)),
            (IntegratorKind::Bpm, Some(16)),
            (IntegratorKind::Bdpt, Some(256)),
        ] {
            let job = JobSettings {
                resolution: Some([512, 512]),
                spp: Some(64),
                integrator,
                ..Default::default()
            };
            let r = job
                .resolve(&mut scene, &Limits::default())
                .expect("resolves");
            assert_eq!(r.max_pass_size, pass, "{integrator:?}");
        }
    }

    #[test]
    fn roulette_defaults_per_integrator_and_is_recorded_in_the_exr() {
        let mut scene = crate::scene::Scene::load(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/scenes/cornell-box.json"
        )))
        .expect("the Cornell box");
        let bdpt_from = integrator::bdpt::ROULETTE_FROM;
        // (integrator, roulette, roulette_from) -> the start vertex, None without roulette.
        let cases = [
            (IntegratorKind::Vcm, None, None, Some(1)),
            (IntegratorKind::Vcm, Some(false), None, None),
            (IntegratorKind::Bdpt, None, None, Some(bdpt_from)),
            (IntegratorKind::Bdpt, Some(false), None, None),
            (IntegratorKind::Bdpt, Some(true), Some(1), Some(1)),
            (IntegratorKind::Bdpt, None, Some(7), Some(7)),
            (IntegratorKind::Bpm, None, None, None),
            (IntegratorKind::Bpm, None, Some(1), Some(1)),
            (IntegratorKind::Pt, None, None, None),
        ];
        for (integrator, roulette, roulette_from, want) in cases {
            let job = JobSettings {
                resolution: Some([64, 64]),
                spp: Some(4),
                integrator,
                roulette,
                roulette_from,
                ..Default::default()
            };
            let r = job
                .resolve(&mut scene, &Limits::default())
                .expect("resolves");
            let case = format!("{integrator:?} {roulette:?} {roulette_from:?}");
            if integrator != IntegratorKind::Pt {
                assert_eq!(r.render.roulette_start(), want, "{case}");
            }
            let attributes = r.exr_attributes("cornell-box", 4);
            let attribute = |name: &str| {
                attributes
                    .iter()
                    .find(|(k, _)| *k == name)
                    .map(|(_, v)| v.clone())
            };
            let expected = (integrator != IntegratorKind::Pt)
                .then(|| (if want.is_some() { "on" } else { "off" }).to_string());
            assert_eq!(attribute("omis.roulette"), expected, "{case}");
            assert_eq!(
                attribute("omis.roulette_from"),
                want.map(|n| n.to_string()),
                "{case}"
            );
        }
        // A job stored before the field was optional reads back as what it said.
        let old: JobSettings =
            serde_json::from_str(r#"{"integrator": "vcm", "roulette": false}"#).expect("parses");
        assert_eq!(old.roulette, Some(false));
        // Render settings from before `roulette_from` meant roulette at every vertex.
        let new = serde_json::to_string(&RenderSettings {
            roulette: true,
            roulette_from: 5,
            ..Default::default()
        })
        .expect("serialises");
        let field = ",\"roulette_from\":5";
        assert!(new.contains(field), "{new}");
        let old: RenderSettings = serde_json::from_str(&new.replace(field, "")).expect("parses");
        assert_eq!(old.roulette_start(), Some(1));
        // Starts outside 1 ..= 64, or with roulette off, are refused by name.
        for (integrator, roulette, from) in [
            (IntegratorKind::Bdpt, None, 0),
            (IntegratorKind::Bdpt, None, 65),
            (IntegratorKind::Bdpt, Some(false), 3),
            (IntegratorKind::Vcm, None, 2),
            (IntegratorKind::Bpm, Some(true), 4),
        ] {
            let job = JobSettings {
                integrator,
                roulette,
                roulette_from: Some(from),
                ..Default::default()
            };
            let e = job.validate(&Limits::default()).expect_err("refused");
            assert_eq!(
                e.field, "roulette_from",
                "{integrator:?} {roulette:?} {from}"
            );
        }
    }

    #[test]
    fn tiles_grow_with_the_frame_unless_set() {
        for light in [false, true] {
            assert_eq!(auto_tile_size(512, 512, light), DEFAULT_TILE_SIZE);
            assert_eq!(auto_tile_size(1280, 720, light), DEFAULT_TILE_SIZE); // 240 large tiles
            assert_eq!(auto_tile_size(1024, 1024, light), LARGE_TILE_SIZE); // 256, 64 huge
            assert_eq!(auto_tile_size(0, 0, light), DEFAULT_TILE_SIZE);
        }
        // 1080p: 510 large tiles, 135 huge ones; huge only where no systems are kept.
        assert_eq!(auto_tile_size(1920, 1080, false), LARGE_TILE_SIZE);
        assert_eq!(auto_tile_size(1920, 1080, true), HUGE_TILE_SIZE);
        let job = |integrator, mis| JobSettings {
            integrator,
            mis,
            ..JobSettings::default()
        };
        let (pt, bdpt) = (IntegratorKind::Pt, IntegratorKind::Bdpt);
        assert_eq!(job(pt, MisKind::Balance).auto_tile_size(1920, 1080), 128);
        assert_eq!(job(bdpt, MisKind::Power).auto_tile_size(1920, 1080), 128);
        assert_eq!(job(bdpt, MisKind::Optimal).auto_tile_size(1920, 1080), 64);
        assert_eq!(
            job(bdpt, MisKind::OptimalProgressive).auto_tile_size(1920, 1080),
            64
        );
        assert_eq!(
            job(IntegratorKind::Vcm, MisKind::Balance).auto_tile_size(1920, 1080),
            64
        );
        // Resolved against the scene's frame; an explicit size wins, also where it is smaller.
        let mut scene = crate::scene::Scene::load(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/scenes/cornell-box.json"
        )))
        .expect("scene");
        let l = Limits::default();
        let at = |res: [u32; 2], tile: Option<u32>, scene: &mut crate::scene::Scene| {
            JobSettings {
                resolution: Some(res),
                tile_size: tile,
                integrator: IntegratorKind::Pt,
                spp: Some(1),
                ..Default::default()
            }
            .resolve(scene, &l)
            .expect("resolves")
            .tile_size
        };
        assert_eq!(at([1920, 1080], None, &mut scene), 128); // the path tracer: light
        assert_eq!(at([640, 480], None, &mut scene), 32);
        assert_eq!(at([1920, 1080], Some(16), &mut scene), 16);
        // Stored settings from before the field was optional read back as what they said.
        let old: JobSettings = serde_json::from_str(r#"{"tile_size": 32}"#).expect("parses");
        assert_eq!(old.tile_size, Some(32));
    }

    #[test]
    fn pass_ranges_cover_the_samples_once() {
        let mut r = Resolved {
            defines: SceneParams::default(),
            width: 4,
            height: 4,
            render: RenderSettings::default(),
            spp: Some(40),
            time_budget_s: None,
            budget_spp: None,
            pilot_s: None,
            tile_size: 2,
            pass_size: 16,
            max_pass_size: None,
            eps: 0.01,
            optimal_depth: None,
        };
        assert_eq!(r.total_passes(), Some(3));
        assert_eq!(r.pass_range(0), Some(0..16));
        assert_eq!(r.pass_range(2), Some(32..40));
        assert_eq!(r.pass_range(3), None);
        r.spp = None;
        assert_eq!(r.pass_range(7), Some(112..128));
        assert_eq!(r.total_passes(), None);
        // Growing passes: 16, 32, 64, 64, ... (a cap of 100 rounds down to 16 x 4).
        r.max_pass_size = Some(100);
        assert_eq!(
            (0..5).map(|p| r.pass_range(p)).collect::<Vec<_>>(),
            [
                Some(0..16),
                Some(16..48),
                Some(48..112),
                Some(112..176),
                Some(176..240)
            ]
        );
        // Every fixed spp is covered exactly once, by total_passes passes.
        for max in [None, Some(16), Some(17), Some(256), Some(65536)] {
            r.max_pass_size = max;
            for spp in [1, 15, 16, 17, 47, 48, 49, 1000, 4096, 1 << 20] {
                r.spp = Some(spp);
                let n = r.total_passes().expect("fixed spp");
                let mut next = 0;
                for p in 0..n {
                    let range = r.pass_range(p).expect("a pass below total_passes");
                    assert_eq!(range.start, next, "{max:?} {spp} pass {p}");
                    assert!(range.end > range.start);
                    next = range.end;
                }
                assert_eq!(next, spp, "{max:?} {spp}");
                assert_eq!(r.pass_range(n), None, "{max:?} {spp}");
            }
        }
        // Ranges past u32::MAX samples do not exist.
        r.spp = None;
        r.max_pass_size = Some(65536);
        assert_eq!(r.pass_range(u32::MAX), None);
    }

    /// A time-budget job rendered at a steady `seconds_per_spp`, pass after pass as the runners
    /// do: its samples per pixel and the seconds it took.
    fn budget_run(r: &Resolved, seconds_per_spp: f64) -> (u32, f64) {
        let mut job = r.clone();
        let (mut spp, mut t, mut p) = (0, 0.0, 0);
        while let Some(range) = job.fit_to_budget(p, t, spp as f64, seconds_per_spp) {
            assert_eq!(range.start, spp, "passes follow one another");
            t += seconds_per_spp * (range.end - range.start) as f64;
            spp = range.end;
            p += 1;
        }
        (spp, t)
    }

    #[test]
    fn the_last_pass_is_fitted_to_the_time_budget() {
        let mut r = Resolved {
            defines: SceneParams::default(),
            width: 4,
            height: 4,
            render: RenderSettings::default(),
            spp: None,
            time_budget_s: Some(1.0),
            budget_spp: None,
            pilot_s: None,
            tile_size: 2,
            pass_size: 1,
            max_pass_size: Some(256),
            eps: 0.01,
            optimal_depth: None,
        };
        for (pass_size, max) in [(1, 256), (1, 4), (4, 64), (3, 48), (16, 16)] {
            r.pass_size = pass_size;
            r.max_pass_size = Some(max);
            for spp_in_budget in [0.3, 1.0, 1.6, 7.0, 100.0, 300.0, 511.0, 1000.5, 1e5] {
                let (spp, t) = budget_run(&r, 1.0 / spp_in_budget);
                let block = pass_size as f64 / spp_in_budget;
                if spp_in_budget <= pass_size as f64 {
                    // The first pass is rendered whatever the budget.
                    assert_eq!(spp, pass_size, "{pass_size} {max} {spp_in_budget}");
                } else {
                    // The end nearest the budget that whole blocks allow.
                    assert!(
                        (t - 1.0).abs() <= block / 2.0 + 1e-9,
                        "{pass_size} {max} {spp_in_budget}: {spp} spp, {t} s"
                    );
                }
                // With a sample count as well, whichever comes first ends the job.
                let capped = Resolved {
                    spp: Some(50),
                    ..r.clone()
                };
                let (spp_c, _) = budget_run(&capped, 1.0 / spp_in_budget);
                assert_eq!(spp_c, spp.min(50).max(pass_size.min(50)));
            }
        }
        r.pass_size = 1;
        r.max_pass_size = Some(256);
        // The pilot's seconds count against the budget: a quarter of it leaves three quarters
        // for the passes.
        let piloted = Resolved {
            pilot_s: Some(0.25),
            ..r.clone()
        };
        let (spp, t) = budget_run(&piloted, 1.0 / 1000.0);
        assert!((t - 0.75).abs() <= 0.5 / 1000.0 + 1e-9, "{spp} spp, {t} s");
        // A budget that the passes so far have used up begins no further pass.
        assert_eq!(r.clone().fit_to_budget(3, 1.0, 7.0, 1.0 / 7.0), None);
        assert_eq!(r.clone().fit_to_budget(0, 5.0, 0.0, 0.0), Some(0..1));
        // Without a budget, or before any sample, the pass is the planned one.
        assert_eq!(r.clone().fit_to_budget(3, 0.0, 0.0, 0.0), Some(7..15));
        let fixed = Resolved {
            time_budget_s: None,
            spp: Some(100),
            ..r.clone()
        };
        assert_eq!(
            fixed.clone().fit_to_budget(3, 10.0, 7.0, 10.0 / 7.0),
            Some(7..15)
        );
        // The fitted count is stored only where it is set.
        let json = serde_json::to_string(&r).expect("serialises");
        assert!(!json.contains("budget_spp"), "{json}");
        let mut fitted = r.clone();
        assert_eq!(fitted.fit_to_budget(3, 0.5, 7.0, 0.5 / 7.0), Some(7..14));
        assert_eq!(fitted.budget_spp, Some(14));
        assert_eq!(fitted.total_passes(), Some(4));
        let back: Resolved =
            serde_json::from_str(&serde_json::to_string(&fitted).expect("serialises"))
                .expect("parses");
        assert_eq!(back, fitted);
        // A fit whose pass was never begun (its tasks never made) is withdrawn when the pass is
        // not begun after all: the job's target is where it ends.
        assert_eq!(fitted.fit_to_budget(3, 1.5, 7.0, 0.5 / 7.0), None);
        assert_eq!(fitted.budget_spp, None);
        assert_eq!(fitted.total_passes(), None);
    }

    #[test]
    fn the_in_process_runner_fits_its_last_pass_to_the_budget() {
        let mut scene = crate::scene::Scene::load(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/scenes/cornell-box.json"
        )))
        .expect("the Cornell box");
        scene.camera = scene.camera.with_resolution(8, 8).expect("8x8");
        let settings = RenderSettings {
            max_depth: 2,
            ..RenderSettings::default()
        };
        // Passes of 1, 2, 4, ..., 64 samples; a clock that counts one second per sample per
        // pixel rendered (from the tasks done: the runner reads it between passes).
        let job = Resolved {
            max_pass_size: Some(64),
            ..Resolved::timed(&scene, &settings, 4, 1, 100.0)
        };
        let tiles = job.tiles().len();
        let tasks = std::sync::atomic::AtomicUsize::new(0);
        let clock = || {
            let passes = tasks.load(std::sync::atomic::Ordering::Relaxed) / tiles;
            passes
                .checked_sub(1)
                .and_then(|p| job.pass_range(p as u32))
                .map_or(0.0, |r| r.end as f64)
        };
        let out = job.render_in_process_clocked(
            &scene,
            &|n| {
                tasks.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
            },
            &clock,
        );
        // Not 127 (the pass of 64 begun at 63 s run to its end).
        assert_eq!(out.spp, 100);
    }

    #[test]
    fn bad_settings_name_their_field() {
        let l = Limits::default();
        let cases = [
            (
                JobSettings {
                    resolution: Some([0, 4]),
                    ..Default::default()
                },
                "resolution",
            ),
            (
                JobSettings {
                    resolution: Some([100000, 4]),
                    ..Default::default()
                },
                "resolution",
            ),
            (
                JobSettings {
                    spp: Some(0),
                    ..Default::default()
                },
                "spp",
            ),
            (
                JobSettings {
                    mis: MisKind::Optimal,
                    ..Default::default()
                },
                "mis",
            ),
            (
                JobSettings {
                    kappa: f64::NAN,
                    ..Default::default()
                },
                "kappa",
            ),
            (
                JobSettings {
                    tile_size: Some(0),
                    ..Default::default()
                },
                "tile_size",
            ),
        ];
        for (s, field) in cases {
            assert_eq!(s.validate(&l).map_err(|e| e.field), Err(field.to_string()));
        }
        assert!(JobSettings::default().validate(&l).is_ok());
    }

    #[test]
    fn unknown_fields_are_refused() {
        let e = serde_json::from_str::<JobSettings>(r#"{"spp": 4, "spq": 1}"#).unwrap_err();
        assert!(e.to_string().contains("spq"), "{e}");
        let s: JobSettings = serde_json::from_str(r#"{"spp": 4, "resolution": [8, 6]}"#).unwrap();
        assert_eq!(s.spp, Some(4));
        assert_eq!(s.resolution, Some([8, 6]));
    }
}
