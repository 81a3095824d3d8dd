//! The command line's names for the renderer's choices. The renderer's enums know nothing of
//! clap; each gets a mirror here with its help text, converted at the edge.

use crate::integrator::bpm::BpmWeights;
use crate::integrator::path::DirectStrategy;
use crate::integrator::vcm::VcmWeights;
use crate::integrator::{IntegratorKind, Techniques};
use crate::mis::MisKind;
use crate::sampler::SamplerKind;

/// A clap value enum mirroring a renderer enum variant for variant, with `From` both ways.
macro_rules! mirror {
    ($(#[$m:meta])* $name:ident => $core:ident { $($(#[$vm:meta])* $v:ident),+ $(,)? }) => {
        $(#[$m])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
        pub enum $name {
            $($(#[$vm])* $v),+
        }
        impl From<$name> for $core {
            fn from(v: $name) -> $core {
                match v {
                    $($name::$v => $core::$v),+
                }
            }
        }
        impl From<$core> for $name {
            fn from(v: $core) -> $name {
                match v {
                    $($core::$v => $name::$v),+
                }
            }
        }
    };
}

mirror! {
    /// `--integrator`.
    IntegratorArg => IntegratorKind {
        /// Unidirectional path tracing with NEE and MIS (power heuristic).
        Pt,
        /// Bidirectional path tracing with every strategy.
        Bdpt,
        /// Vertex connection and merging: BDPT plus photon merging within --radius, one MIS
        /// (Georgiev et al. 2012).
        Vcm,
        /// Bidirectional photon mapping: merging only, at --bdd (--bpm-weights).
        Bpm,
    }
}

mirror! {
    /// `--bpm-weights`.
    BpmWeightsArg => BpmWeights {
        /// Merge at the camera's --bdd-th non-specular vertex only.
        Fixed,
        /// Mix --bdd and --bdd + 1 with the optimal weights of Ershov et al. (CPT 2020, CEUR-WS vol. 2763)
        /// from a photon map frozen at the first iteration.
        Optimal,
    }
}

mirror! {
    /// `--vcm-weights`.
    VcmWeightsArg => VcmWeights {
        /// Every connection and merge by --mis balance or power (Georgiev et al., SIGGRAPH Asia 2012).
        Georgiev,
        /// As georgiev, but the joint share of the merges at the camera's first non-specular
        /// vertex and at the path's next vertex is split by Ershov et al.'s optimal weight (CPT
        /// 2020, CEUR-WS vol. 2763), from a photon map frozen at the first iteration.
        Ershov,
    }
}

mirror! {
    /// `--mis`.
    MisArg => MisKind {
        /// Balance heuristic (Veach 1997 eq. 9.6).
        Balance,
        /// Power heuristic, beta = 2 (Veach 1997 eq. 9.13).
        Power,
        /// Optimal weights per pixel and depth for depths 1 ..= --optimal-max-depth
        /// (Kondapaneni et al., ACM TOG 2019), balance for depth 0 and above: the direct
        /// estimator (biased at low spp).
        Optimal,
        /// The same optimal weights applied progressively: each pass uses the weights solved
        /// from the passes before it (the first pass is balance); unbiased at any spp.
        OptimalProgressive,
    }
}

mirror! {
    /// `--techniques`.
    TechniquesArg => Techniques {
        /// Every (s, t), weighted by --mis.
        All,
        /// Validation: light tracing alone (every t = 1 technique, unweighted).
        Lt,
        /// Validation: next-event estimation alone (every (1, t >= 2), unweighted; depth 0 by (0, 2)).
        Nee,
    }
}

mirror! {
    /// `--sampler`.
    SamplerArg => SamplerKind {
        /// Independent uniform numbers from PCG32.
        Independent,
        /// Jittered strata in 1D, correlated multi-jittered (Kensler 2013) in 2D.
        Stratified,
        /// Owen-scrambled Sobol' (0,2)-sequence, padded per dimension pair (Burley 2020).
        Sobol,
    }
}

mirror! {
    /// `--direct`.
    DirectArg => DirectStrategy {
        /// Light sampling and BSDF sampling combined with the power heuristic.
        Mis,
        /// Next-event estimation only.
        Light,
        /// BSDF sampling only (cannot see point lights).
        Bsdf,
    }
}

/// `--optimal-max-depth`: `auto` (a pilot render chooses, `job::optimal_depth`) or a depth.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OptimalDepthArg(pub Option<u32>);

impl std::str::FromStr for OptimalDepthArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "auto" {
            return Ok(OptimalDepthArg(None));
        }
        s.parse::<u32>()
            .map(|d| OptimalDepthArg(Some(d)))
            .map_err(|_| format!("`{s}` is neither `auto` nor a depth (0, 1, 2, ...)"))
    }
}

impl std::fmt::Display for OptimalDepthArg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            None => f.write_str("auto"),
            Some(d) => write!(f, "{d}"),
        }
    }
}
