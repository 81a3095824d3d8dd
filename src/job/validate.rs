//! The checks of a job's settings that do not depend on its scene: one place, so that the
//! command line and the service refuse the same inputs with the same words.

use super::sizes::check_tiles;
use super::{FieldError, JobSettings, Limits, MAX_KAPPA, MIN_TIME_BUDGET_S};
use crate::integrator::{self, IntegratorKind, Techniques};

impl JobSettings {
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
}
