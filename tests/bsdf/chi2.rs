//! Chi-square goodness of fit of `sample()` against `pdf()`, and the power of the test itself.

use crate::cases::*;
use crate::grid::*;
use crate::stats::*;
use omis::geometry::Rgb;
use omis::material::{MaterialKind, Mode};
use omis::sampler::Pcg32;

#[test]
fn chi2_lambert_and_phong() {
    run_chi2_suite([lambert_kinds(), phong_kinds()].concat(), 101);
}

#[test]
fn chi2_rough_conductor() {
    run_chi2_suite(conductor_kinds(), 202);
}

#[test]
fn chi2_rough_dielectric() {
    run_chi2_suite(rough_dielectric_kinds(), 404);
}

#[test]
fn chi2_plastic() {
    run_chi2_suite(plastic_kinds(), 303);
}

/// Number of chi2 tests in `chi2_has_power_against_wrong_pdfs` (part of the Sidak family).
pub const POWER_TESTS: usize = 4;

/// The chi2 machinery must reject slightly wrong densities at the same significance level the
/// real tests use; otherwise passing them would prove nothing.
#[test]
fn chi2_has_power_against_wrong_pdfs() {
    let alpha = sidak(CHI2_ALPHA, chi2_family_size());
    let geo = geo_flat();
    let wo = about(geo.ng, 45.0, 0.4);
    let phong = |n: f32| MaterialKind::Phong {
        kd: Rgb::ZERO,
        ks: Rgb::splat(0.9),
        exponent: n,
    };
    // (sampled, claimed density, description)
    let pairs: Vec<(MaterialKind, MaterialKind, &str)> = vec![
        (phong(20.0), phong(22.0), "phong n=20 sampled, n=22 pdf"),
        (
            gold(0.3, 0.3),
            gold(0.33, 0.33),
            "ggx 0.3 sampled, 0.33 pdf",
        ),
        (
            gold(0.1, 0.5),
            gold(0.5, 0.1),
            "anisotropic ggx axes swapped",
        ),
    ];
    assert_eq!(pairs.len() + 1, POWER_TESTS);
    for (i, (sampled, claimed, what)) in pairs.iter().enumerate() {
        let bs = bsdf_for(sampled, &geo);
        let bp = bsdf_for(claimed, &geo);
        let grid = Grid::for_bsdf(&bs, wo);
        let mut rng = Pcg32::new(404, i as u64);
        let r = chi2_test(
            &grid,
            CHI2_SAMPLES,
            &mut rng,
            |rng| {
                let (ul, u) = random_u(rng);
                bs.sample(wo, ul, u, Mode::Radiance).map(|s| s.wi)
            },
            |wi| bp.pdf(wo, wi) as f64,
        );
        println!("{what}: {r:?}");
        assert!(
            matches!(r, Ok(r) if r.p < alpha) || r.is_err(),
            "{what}: not rejected: {r:?}"
        );
    }
    // A pdf 5% too large within 14 deg of the peak (about 40% of the samples). A smaller error
    // spread this thinly is below what 3e5 samples resolve at this significance level.
    let bs = bsdf_for(&phong(20.0), &geo);
    let grid = Grid::for_bsdf(&bs, wo);
    let r_dir = 2.0 * wo.dot(geo.ns) * geo.ns - wo;
    let mut rng = Pcg32::new(404, 99);
    let r = chi2_test(
        &grid,
        CHI2_SAMPLES,
        &mut rng,
        |rng| {
            let (ul, u) = random_u(rng);
            bs.sample(wo, ul, u, Mode::Radiance).map(|s| s.wi)
        },
        |wi| {
            let scale = if wi.dot(r_dir) > 0.97 { 1.05 } else { 1.0 };
            scale * bs.pdf(wo, wi) as f64
        },
    );
    println!("phong pdf 5% high near the peak: {r:?}");
    assert!(
        matches!(r, Ok(r) if r.p < alpha) || r.is_err(),
        "5% error not rejected: {r:?}"
    );
}
