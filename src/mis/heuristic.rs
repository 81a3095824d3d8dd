//! The MIS heuristics (Veach 1997, ch. 9): how a sample's technique is weighted from the
//! densities of every technique that could have made it. The optimal weights, which need a
//! per-pixel linear system, live in `optimal`.

use serde::{Deserialize, Serialize};

/// How BDPT weights its techniques.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum MisKind {
    /// Balance heuristic (Veach 1997 eq. 9.6).
    #[default]
    Balance,
    /// Power heuristic, beta = 2 (Veach 1997 eq. 9.13).
    Power,
    /// Optimal weights per pixel and depth for depths 1 ..= D_opt (Kondapaneni et al. 2019, in
    /// the BDPT formulation of Cailleau et al.), balance for depth 0 and above D_opt: the direct
    /// estimator (the solved systems' sum of alpha; biased, O(1/n)).
    Optimal,
    /// The same systems, used progressively: pass k's samples are weighted with the optimal
    /// weights of the alpha solved from passes before k, an unbiased estimate at any spp
    /// (`mis::progressive`).
    #[serde(rename = "optimal-progressive")]
    OptimalProgressive,
}

impl MisKind {
    /// Whether the render accumulates optimal-MIS systems (either estimator).
    pub fn is_optimal(self) -> bool {
        matches!(self, MisKind::Optimal | MisKind::OptimalProgressive)
    }

    /// The name the API, the command line and the EXR attributes use.
    pub fn name(self) -> &'static str {
        match self {
            MisKind::Balance => "balance",
            MisKind::Power => "power",
            MisKind::Optimal => "optimal",
            MisKind::OptimalProgressive => "optimal-progressive",
        }
    }

    /// The heuristic's exponent beta (Veach 1997 eq. 9.13): 2 for power, 1 for balance (and for
    /// optimal MIS outside its systems).
    pub fn beta(self) -> i32 {
        if self == MisKind::Power { 2 } else { 1 }
    }
}

/// What a heuristic of exponent `beta` makes of a density ratio x: x^beta (Veach 1997 eq. 9.13;
/// the recursive weights sum these terms).
#[inline]
pub fn ratio_term(x: f64, beta: i32) -> f64 {
    if beta == 2 { x * x } else { x }
}

/// The weight of technique `s` for a path whose balance weights over all techniques of its depth
/// are `balance` (n_i p_i / sum_k n_k p_k). Power heuristic, beta = 2 (Veach 1997 eq. 9.13):
/// (n_s p_s)^2 / sum_k (n_k p_k)^2 = b_s^2 / sum_k b_k^2. Optimal MIS weights its depths through
/// its own systems; where it is asked here (depth 0 and deeper than D_opt) it is balance.
#[inline]
pub fn weight(mis: MisKind, balance: &[f64], s: u32) -> f64 {
    match mis {
        MisKind::Balance | MisKind::Optimal | MisKind::OptimalProgressive => balance[s as usize],
        MisKind::Power => {
            let b = balance[s as usize];
            let sq: f64 = balance.iter().map(|x| x * x).sum();
            if sq > 0.0 { b * b / sq } else { 0.0 }
        }
    }
}

/// Power heuristic with beta = 2 (Veach 1997, eq. 9.13), written for n_f = n_g = 1.
#[inline]
pub fn power_heuristic(pdf_f: f32, pdf_g: f32) -> f32 {
    let f = pdf_f * pdf_f;
    let g = pdf_g * pdf_g;
    if f == 0.0 {
        return 0.0;
    }
    if g.is_infinite() {
        return 0.0;
    }
    if f.is_infinite() {
        return 1.0;
    }
    f / (f + g)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn power_heuristic_limits() {
        assert_eq!(power_heuristic(0.0, 1.0), 0.0);
        assert_eq!(power_heuristic(1.0, 0.0), 1.0);
        assert!((power_heuristic(1.0, 1.0) - 0.5).abs() < 1e-6);
        assert_eq!(power_heuristic(f32::INFINITY, 3.0), 1.0);
    }

    #[test]
    fn weights_of_one_path_sum_to_one() {
        let b = [0.5, 0.3, 0.2, 0.0];
        for mis in [
            MisKind::Balance,
            MisKind::Power,
            MisKind::Optimal,
            MisKind::OptimalProgressive,
        ] {
            let sum: f64 = (0..4).map(|s| weight(mis, &b, s)).sum();
            assert!((sum - 1.0).abs() < 1e-12, "{mis:?}: {sum}");
        }
        assert_eq!(weight(MisKind::Power, &b, 3), 0.0);
        assert!((weight(MisKind::Power, &b, 0) - 0.25 / 0.38).abs() < 1e-12);
    }

    #[test]
    fn names_are_the_serde_names() {
        for mis in [
            MisKind::Balance,
            MisKind::Power,
            MisKind::Optimal,
            MisKind::OptimalProgressive,
        ] {
            let json = serde_json::to_string(&mis).expect("serialises");
            assert_eq!(json, format!("\"{}\"", mis.name()));
            assert_eq!(serde_json::from_str::<MisKind>(&json).ok(), Some(mis));
        }
    }
}
