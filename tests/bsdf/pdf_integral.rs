//! The pdf integrates to the probability that `sample()` succeeds.

use crate::cases::*;
use crate::grid::*;
use crate::support::INTEGRATION_TOL;
use omis::geometry::Rgb;
use omis::material::Mode;
use omis::sampler::Pcg32;

#[test]
fn pdf_integrates_to_sampling_probability() {
    const N: usize = 100_000;
    let geos = [
        geo_flat(),
        geo_tilted(),
        geo_one_sided(),
        geo_tilted_one_sided(),
    ];
    let mut failures = Vec::new();
    // On its front a one-sided surface is the two-sided one; test it at 45 deg and on the back.
    let all = cases(&smooth_kinds(), &geos);
    let selected = all.iter().filter(|c| {
        c.geo.two_sided || c.name.ends_with("wo 45deg") || c.name.ends_with("wo back 45deg")
    });
    for (i, case) in selected.enumerate() {
        let (bsdf, wo) = (&case.bsdf, case.wo);
        let grid = Grid::for_bsdf(bsdf, wo);
        let total: f64 = grid.integrate(&|wi| bsdf.pdf(wo, wi) as f64).iter().sum();
        let mut rng = Pcg32::new(505, i as u64);
        let mut some = 0usize;
        for _ in 0..N {
            let (ul, u) = random_u(&mut rng);
            if bsdf.sample(wo, ul, u, Mode::Radiance).is_some() {
                some += 1;
            }
        }
        let frac = some as f64 / N as f64;
        // Binomial standard error; the larger of the two estimates of p guards against a zero SE
        // when the sampler happens to always succeed.
        let p = frac.max(total).min(1.0);
        let se = (p * (1.0 - p) / N as f64).sqrt();
        let tol = 5.0 * se + INTEGRATION_TOL;
        println!(
            "{:<75} integral {total:.6} P(Some) {frac:.6} tol {tol:.1e}",
            case.name
        );
        if (total - frac).abs() > tol || total > 1.0 + INTEGRATION_TOL {
            failures.push(format!(
                "{}: integral of pdf = {total:.6}, fraction of successful samples = {frac:.6} (tol {tol:.1e})",
                case.name
            ));
        }
        // The back of a one-sided surface is black: nothing to sample, zero density and value.
        if !case.geo.two_sided && wo.dot(case.geo.ng) < 0.0 && !bsdf.transmits() {
            let mut black = total == 0.0 && some == 0;
            for _ in 0..10_000 {
                let z = 1.0 - 2.0 * rng.next_f32();
                let wi = about(case.geo.ng, z.acos().to_degrees(), 6.3 * rng.next_f32());
                black &= bsdf.eval(wo, wi, Mode::Radiance) == Rgb::ZERO
                    && bsdf.eval(wo, wi, Mode::Importance) == Rgb::ZERO
                    && bsdf.pdf(wo, wi) == 0.0;
            }
            if !black {
                failures.push(format!(
                    "{}: back of a one-sided surface not black",
                    case.name
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
