//! [`Resolved`]: a job's settings resolved against its scene, with the `RenderSettings` every
//! process renders it with.

use super::sizes::{check_tiles, photon_passes};
use super::{FieldError, JobSettings, Limits, optimal_depth};
use crate::film::FilmLayout;
use crate::integrator::{self, IntegratorKind, RenderSettings, Techniques};
use crate::scene::{Scene, SceneParams};
use serde::{Deserialize, Serialize};

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
    /// `render.sample_block` is the stratification block of the sampler: the total spp of a
    /// fixed-spp job, the pass size of a time-budget job.
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
    /// Applies the resolution to the scene's camera and resolves the settings against the
    /// scene's defaults, and checks the result against `limits` whichever of the two each
    /// value came from.
    pub fn resolve(&self, scene: &mut Scene, limits: &Limits) -> Result<Resolved, FieldError> {
        self.validate(limits)?;
        if let Some([w, h]) = self.resolution {
            scene.camera = scene
                .camera
                .with_resolution(w, h)
                .map_err(|e| FieldError::new("resolution", e.to_string()))?;
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
            sample_block: spp.unwrap_or(pass_size),
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
