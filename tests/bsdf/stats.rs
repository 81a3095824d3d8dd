//! Chi-square statistics: tail probabilities, Sidak correction, pooled goodness of fit.

use std::f64::consts::PI as PI64;

// ================================================================================================
// Statistics
// ================================================================================================

/// ln Gamma(x) for x > 0 (Lanczos, g = 7, n = 9; ~1e-15 relative).
pub fn ln_gamma(x: f64) -> f64 {
    const G: f64 = 7.0;
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection formula.
        return (PI64 / (PI64 * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let t = x + G + 0.5;
    let mut a = C[0];
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * PI64).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularized upper incomplete gamma function Q(a, x) (Numerical Recipes 6.2: series below
/// x = a + 1, Lentz continued fraction above, so the upper tail is accurate).
pub fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let ln_pre = -x + a * x.ln() - ln_gamma(a);
    if x < a + 1.0 {
        let mut ap = a;
        let mut del = 1.0 / a;
        let mut sum = del;
        for _ in 0..100_000 {
            ap += 1.0;
            del *= x / ap;
            sum += del;
            if del.abs() < sum.abs() * 1e-16 {
                break;
            }
        }
        (1.0 - sum * ln_pre.exp()).clamp(0.0, 1.0)
    } else {
        const TINY: f64 = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / TINY;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..100_000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < TINY {
                d = TINY;
            }
            c = b + an / c;
            if c.abs() < TINY {
                c = TINY;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-16 {
                break;
            }
        }
        (ln_pre.exp() * h).clamp(0.0, 1.0)
    }
}

/// P(X >= stat) for X ~ chi2(dof).
pub fn chi2_sf(stat: f64, dof: usize) -> f64 {
    gamma_q(0.5 * dof as f64, 0.5 * stat)
}

/// Per-test significance level so that m independent tests together reject a correct
/// implementation with probability `alpha` (Sidak): 1 - (1 - alpha)^(1/m).
pub fn sidak(alpha: f64, m: usize) -> f64 {
    -((-alpha).ln_1p() / m as f64).exp_m1()
}

#[derive(Debug, Clone, Copy)]
pub struct Chi2 {
    pub stat: f64,
    pub dof: usize,
    pub p: f64,
}

/// Pearson's chi-square with Mitsuba's pooling: cells sorted by expected count; those with fewer
/// than `min_exp` expected samples are pooled (and pooling continues until the pool reaches
/// `min_exp`). An observation in a cell of zero probability is an error.
pub fn chi2_pooled(obs: &[f64], exp: &[f64], min_exp: f64) -> Result<Chi2, String> {
    assert_eq!(obs.len(), exp.len());
    let mut idx: Vec<usize> = (0..obs.len()).collect();
    idx.sort_by(|&a, &b| exp[a].total_cmp(&exp[b]));
    let (mut pool_o, mut pool_e) = (0.0f64, 0.0f64);
    let mut stat = 0.0f64;
    let mut cells = 0usize;
    for &i in &idx {
        if exp[i] <= 0.0 {
            if obs[i] > 0.0 {
                return Err(format!(
                    "{} samples in cell {i}, whose integrated pdf is zero",
                    obs[i]
                ));
            }
        } else if exp[i] < min_exp || (pool_e > 0.0 && pool_e < min_exp) {
            pool_o += obs[i];
            pool_e += exp[i];
        } else {
            stat += (obs[i] - exp[i]).powi(2) / exp[i];
            cells += 1;
        }
    }
    if pool_e > 0.0 {
        stat += (pool_o - pool_e).powi(2) / pool_e;
        cells += 1;
    }
    let dof = cells.saturating_sub(1);
    let p = if dof == 0 { 1.0 } else { chi2_sf(stat, dof) };
    Ok(Chi2 { stat, dof, p })
}
