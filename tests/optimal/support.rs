//! The render settings of the optimal-MIS tests.

use omis::integrator::{IntegratorKind, RenderSettings};
use omis::mis::MisKind;
use omis::sampler::SamplerKind;

pub fn optimal(spp: u32, max_depth: u32, d_opt: u32) -> RenderSettings {
    RenderSettings {
        integrator: IntegratorKind::Bdpt,
        mis: MisKind::Optimal,
        sample_block: spp,
        max_depth,
        optimal_max_depth: d_opt,
        sampler: SamplerKind::Independent,
        seed: 5,
        ..Default::default()
    }
}
