//! Statistical verification of every BSDF in `omis::material`.
//!
//! * `chi2_*`: chi-square goodness of fit of `sample()` against `pdf()` (Mitsuba / pbrt style:
//!   bin the sampled directions on the sphere, integrate the pdf over each bin numerically, pool
//!   bins with fewer than 5 expected samples, Sidak-corrected significance over all chi2 tests).
//!   Also run from directions produced by `sample()` itself ("reverse" cases), which tests that
//!   `pdf(wi, wo)` is the density of sampling wo from wi.
//! * `pdf_integrates_to_sampling_probability`: integral of pdf(wo, .) = P(sample() is Some).
//! * `samples_agree_with_eval_and_pdf`: every sample's f / pdf equal eval / pdf at its direction;
//!   reciprocity (and Veach's adjoint relation with shading normals).
//! * `delta_lobes_mirror_and_dielectric`: discrete probabilities, geometry, Mode scaling, energy.
//! * `robustness_*`: no NaN / inf / negative values anywhere, including grazing, exactly normal,
//!   denormal cosines and GGX visible normals nearly perpendicular to wo.
//! * `white_furnace`: energy conservation.
//! * `chi2_has_power_against_wrong_pdfs` / `statistics_helpers_are_correct`: the machinery itself.

mod cases;
mod grid;
mod stats;

use cases::*;
use grid::*;
use stats::*;
use std::f64::consts::PI as PI64;

use omis::geometry::{Frame, Rgb, Vec2, Vec3};
use omis::material::fresnel;
use omis::material::microfacet::Microfacet;
use omis::material::{Bsdf, BsdfSample, Distribution, MaterialKind, Mode};
use omis::sampler::Pcg32;

// ================================================================================================
// 1. Chi-square goodness of fit
// ================================================================================================

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

// ================================================================================================
// 2. The pdf integrates to the probability that sample() succeeds
// ================================================================================================

/// Absolute error allowed for the grid integration of a pdf over the sphere.
/// `statistics_helpers_are_correct` measures the grid on a cosine lobe and on a uniform
/// hemisphere whose horizon cuts the bins diagonally (a jump, the worst case here) at a few 1e-7;
/// 1e-4 leaves a wide margin and is still small next to the sampling tolerance (5 standard
/// errors, 1e-3 to 8e-3 at 1e5 samples).
const INTEGRATION_TOL: f64 = 1e-4;

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

// ================================================================================================
// 3. Each sample agrees with eval() and pdf(); reciprocity
// ================================================================================================

fn rel_close(a: f32, b: f32, rel: f32) -> bool {
    (a - b).abs() <= rel * a.abs().max(b.abs()) + 1e-30
}

fn rgb_close(a: Rgb, b: Rgb, rel: f32) -> bool {
    rel_close(a.x, b.x, rel) && rel_close(a.y, b.y, rel) && rel_close(a.z, b.z, rel)
}

fn valid_rgb(c: Rgb) -> bool {
    c.is_finite() && c.min_element() >= 0.0
}

/// Checks one sample against the BSDF's own eval / pdf / delta_pdf; returns a description of the
/// first inconsistency.
fn check_sample(bsdf: &Bsdf, wo: Vec3, s: &BsdfSample, mode: Mode) -> Result<(), String> {
    if !(s.wi.is_finite() && (s.wi.length() - 1.0).abs() < 1e-4) {
        return Err(format!("wi {} is not a unit vector", s.wi));
    }
    if !(s.pdf > 0.0 && s.pdf.is_finite()) {
        return Err(format!("pdf {}", s.pdf));
    }
    if !valid_rgb(s.f) {
        return Err(format!("f {}", s.f));
    }
    if s.delta != bsdf.is_delta() {
        return Err(format!(
            "delta flag {} on a lobe with is_delta {}",
            s.delta,
            bsdf.is_delta()
        ));
    }
    if s.delta {
        let dp = bsdf.delta_pdf(wo, s.wi);
        if !rel_close(dp, s.pdf, 1e-5) {
            return Err(format!("delta_pdf {dp} != sampled probability {}", s.pdf));
        }
        let (f, p) = (bsdf.eval(wo, s.wi, mode), bsdf.pdf(wo, s.wi));
        if f != Rgb::ZERO || p != 0.0 {
            return Err(format!("delta lobe has eval {f} / pdf {p} != 0"));
        }
    } else {
        let p = bsdf.pdf(wo, s.wi);
        if !rel_close(p, s.pdf, 1e-3) {
            return Err(format!("sampled pdf {} != pdf(wo, wi) {p}", s.pdf));
        }
        let f = bsdf.eval(wo, s.wi, mode);
        if !rgb_close(f, s.f, 1e-3) {
            return Err(format!("sampled f {} != eval(wo, wi) {f}", s.f));
        }
        if bsdf.delta_pdf(wo, s.wi) != 0.0 {
            return Err("delta_pdf != 0 on a non-delta lobe".into());
        }
    }
    Ok(())
}

/// Adjoint relation of a reflection-only BSDF with shading normals (Veach 1997 eq. 5.19 applied to
/// a symmetric f_s): f_imp(wo, wi) |wo.ng| |wi.ns| = f_rad(wi, wo) |wo.ns| |wi.ng|. With ns = ng it
/// is plain reciprocity, f(wo, wi) = f(wi, wo) in both modes.
fn check_adjoint(bsdf: &Bsdf, wo: Vec3, wi: Vec3) -> Result<(), String> {
    let (ng, ns) = (bsdf.ng, bsdf.frame.n);
    let lhs = bsdf.eval(wo, wi, Mode::Importance) * (wo.dot(ng).abs() * wi.dot(ns).abs());
    let rhs = bsdf.eval(wi, wo, Mode::Radiance) * (wo.dot(ns).abs() * wi.dot(ng).abs());
    if !rgb_close(lhs, rhs, 1e-3) {
        return Err(format!(
            "adjoint: f_imp(wo, wi) term {lhs} != f_rad(wi, wo) term {rhs}"
        ));
    }
    // A refraction is reciprocal only up to the indices (Veach 1997 eq. 5.39): the adjoint
    // relation above is what holds.
    let refracts = wo.dot(ng) * wi.dot(ng) < 0.0;
    if ng == ns && !refracts {
        let a = bsdf.eval(wo, wi, Mode::Radiance);
        let b = bsdf.eval(wi, wo, Mode::Radiance);
        if !rgb_close(a, b, 1e-3) {
            return Err(format!("reciprocity: f(wo, wi) {a} != f(wi, wo) {b}"));
        }
        if !rgb_close(a, bsdf.eval(wo, wi, Mode::Importance), 1e-6) {
            return Err("Radiance and Importance differ without shading normals".into());
        }
        // The pair can be sampled in reverse: the reverse density is positive and finite.
        let rp = bsdf.pdf(wi, wo);
        if !(rp > 0.0 && rp.is_finite()) {
            return Err(format!("reverse pdf(wi, wo) = {rp} for a sampled pair"));
        }
        // A two-sided surface seen from the back is its front mirrored through the surface (a
        // dielectric's back has the inverse index).
        if wo.dot(ng) < 0.0 && !bsdf.transmits() {
            let m = |w: Vec3| w - 2.0 * w.dot(ng) * ng;
            let (fb, ff) = (a, bsdf.eval(m(wo), m(wi), Mode::Radiance));
            let (pb, pf) = (bsdf.pdf(wo, wi), bsdf.pdf(m(wo), m(wi)));
            if !rgb_close(fb, ff, 1e-3) || !rel_close(pb, pf, 1e-3) {
                return Err(format!(
                    "back side f {fb} / pdf {pb} != mirrored front side f {ff} / pdf {pf}"
                ));
            }
        }
    }
    Ok(())
}

#[test]
fn samples_agree_with_eval_and_pdf() {
    const N: usize = 10_000;
    let geos = [
        geo_flat(),
        geo_tilted(),
        geo_one_sided(),
        geo_tilted_one_sided(),
    ];
    let kinds = [smooth_kinds(), delta_kinds()].concat();
    let mut failures = Vec::new();
    let mut checked = 0usize;
    for (i, case) in cases(&kinds, &geos).iter().enumerate() {
        let (bsdf, wo) = (&case.bsdf, case.wo);
        let mut rng = Pcg32::new(606, i as u64);
        'samples: for _ in 0..N {
            let (ul, u) = random_u(&mut rng);
            for mode in [Mode::Radiance, Mode::Importance] {
                let Some(s) = bsdf.sample(wo, ul, u, mode) else {
                    continue;
                };
                checked += 1;
                let mut r = check_sample(bsdf, wo, &s, mode);
                if r.is_ok() && !s.delta {
                    r = check_adjoint(bsdf, wo, s.wi);
                }
                if let Err(e) = r {
                    failures.push(format!(
                        "{} {mode:?}: wo {wo} u ({ul}, {u}) wi {}: {e}",
                        case.name, s.wi
                    ));
                    break 'samples;
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert!(checked > 1_000_000, "only {checked} samples checked");
}

// ================================================================================================
// 3b. Delta lobes: mirror and smooth dielectric
// ================================================================================================

/// Independent unpolarised Fresnel reflectance (f64) for light going from index eta_i to eta_t.
fn fresnel_ref(cos_i: f64, eta_i: f64, eta_t: f64) -> f64 {
    let sin_t = eta_i / eta_t * (1.0 - cos_i * cos_i).max(0.0).sqrt();
    if sin_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin_t * sin_t).sqrt();
    let rs = (eta_i * cos_i - eta_t * cos_t) / (eta_i * cos_i + eta_t * cos_t);
    let rp = (eta_t * cos_i - eta_i * cos_t) / (eta_t * cos_i + eta_i * cos_t);
    0.5 * (rs * rs + rp * rp)
}

fn reflect(w: Vec3, n: Vec3) -> Vec3 {
    2.0 * w.dot(n) * n - w
}

#[test]
fn delta_lobes_mirror_and_dielectric() {
    let mut failures: Vec<String> = Vec::new();
    let mut check = |ok: bool, msg: String| {
        if !ok {
            failures.push(msg);
        }
    };
    let u = Vec2::new(0.3, 0.7);

    // --- Mirror: reflects about ns with probability 1 and f cos / pdf = reflectance.
    let r = Rgb::new(0.9, 0.8, 0.7);
    for geo in [geo_flat(), geo_tilted(), geo_one_sided()] {
        let bsdf = bsdf_for(&MaterialKind::Mirror { reflectance: r }, &geo);
        for (wname, wo) in wos(&geo) {
            let name = format!("mirror [{}] {wname}", geo.name);
            let s = bsdf.sample(wo, 0.5, u, Mode::Radiance);
            let back = wo.dot(geo.ng) < 0.0;
            let expect_some = (geo.two_sided || !back) && wo.dot(geo.ns) * wo.dot(geo.ng) > 0.0;
            let Some(s) = s else {
                check(
                    !expect_some || reflect(wo, geo.ns).dot(geo.ng) * wo.dot(geo.ng) <= 0.0,
                    format!("{name}: no sample"),
                );
                continue;
            };
            check(expect_some, format!("{name}: sample on a black side"));
            let cos = s.wi.dot(geo.ns).abs();
            check(
                (s.wi - reflect(wo, geo.ns)).length() < 1e-5,
                format!("{name}: wi {} is not the mirror direction", s.wi),
            );
            check(s.delta && s.pdf == 1.0, format!("{name}: {s:?}"));
            check(
                rgb_close(s.f * cos / s.pdf, r, 1e-5),
                format!("{name}: f cos / pdf = {} != {r}", s.f * cos / s.pdf),
            );
            check(
                bsdf.delta_pdf(wo, s.wi) == 1.0,
                format!("{name}: delta_pdf != 1"),
            );
        }
    }

    // --- Smooth dielectric, ior 1.5, entered from outside and left from inside.
    let eta = 1.5f32;
    let kind = MaterialKind::Dielectric {
        ior: eta,
        reflectance: Rgb::ONE,
        transmittance: Rgb::ONE,
    };
    let mut n_tir = 0;
    for geo in [geo_flat(), geo_tilted()] {
        let bsdf = bsdf_for(&kind, &geo);
        for theta in [
            0.0f32, 30.0, 60.0, 85.0, 180.0, 150.0, 140.0, 135.0, 120.0, 95.0,
        ] {
            let wo = about(geo.ng, theta, 0.4);
            let name = format!("dielectric [{}] theta {theta}", geo.name);
            let ns = geo.ns;
            let outside = wo.dot(geo.ng) > 0.0;
            // eta_rel = index on wi's side of a transmission over index on wo's side.
            let eta_rel = if outside { eta } else { 1.0 / eta };
            let cos_o = wo.dot(ns).abs() as f64;
            let f_ref = if outside {
                fresnel_ref(cos_o, 1.0, eta as f64)
            } else {
                fresnel_ref(cos_o, eta as f64, 1.0)
            };
            // u_lobe = 0 always picks reflection (F > 0), u_lobe -> 1 transmission unless TIR.
            let refl = [Mode::Radiance, Mode::Importance].map(|m| bsdf.sample(wo, 0.0, u, m));
            let tran = [Mode::Radiance, Mode::Importance]
                .map(|m| bsdf.sample(wo, 1.0 - f32::EPSILON / 2.0, u, m));
            let (Some(rr), Some(ri)) = (refl[0], refl[1]) else {
                check(geo.ns != geo.ng, format!("{name}: no reflection sample"));
                continue;
            };
            check(
                (rr.wi - reflect(wo, ns)).length() < 1e-5 && rr.delta,
                format!("{name}: reflection {rr:?}"),
            );
            check(
                (rr.pdf as f64 - f_ref).abs() < 1e-5,
                format!("{name}: P(reflect) {} != Fresnel {f_ref}", rr.pdf),
            );
            check(
                rel_close(bsdf.delta_pdf(wo, rr.wi), rr.pdf, 1e-6),
                format!("{name}: delta_pdf(reflection) != sampled probability"),
            );
            check(
                rgb_close(rr.f, ri.f, 1e-6) || geo.ns != geo.ng,
                format!("{name}: reflection differs between modes"),
            );
            let e_refl = rr.f * rr.wi.dot(ns).abs();
            if f_ref >= 1.0 {
                // Total internal reflection: the "transmission" draw is the same reflection.
                n_tir += 1;
                let t = tran[0].map(|t| (t.wi - rr.wi).length() < 1e-6 && t.pdf == 1.0);
                check(t == Some(true), format!("{name}: TIR {:?}", tran[0]));
                check(
                    rgb_close(e_refl, Rgb::ONE, 1e-5),
                    format!("{name}: TIR energy {e_refl}"),
                );
                continue;
            }
            let (Some(tr), Some(ti)) = (tran[0], tran[1]) else {
                check(geo.ns != geo.ng, format!("{name}: no transmission sample"));
                continue;
            };
            // Geometry: opposite side, Snell's law, plane of incidence.
            let cos_t = tr.wi.dot(ns);
            let sin_o = (1.0 - cos_o * cos_o).max(0.0).sqrt();
            let sin_t = (1.0 - (cos_t as f64).powi(2)).max(0.0).sqrt();
            check(
                tr.delta && cos_t * wo.dot(ns) < 0.0,
                format!("{name}: transmission {tr:?}"),
            );
            check(
                (sin_o - eta_rel as f64 * sin_t).abs() < 1e-5,
                format!("{name}: Snell: sin_o {sin_o} != {eta_rel} sin_t {sin_t}"),
            );
            check(
                wo.cross(ns).dot(tr.wi).abs() < 1e-5,
                format!("{name}: transmission leaves the plane of incidence"),
            );
            check(
                rel_close(bsdf.delta_pdf(wo, tr.wi), tr.pdf, 1e-6),
                format!("{name}: delta_pdf(transmission) != sampled probability"),
            );
            check(
                ((rr.pdf + tr.pdf) as f64 - 1.0).abs() < 1e-6,
                format!("{name}: P(reflect) + P(transmit) = {}", rr.pdf + tr.pdf),
            );
            // Radiance is scaled by (eta_wo / eta_wi)^2 = 1 / eta_rel^2 when it crosses the
            // interface; importance is not (Veach 1997 §5.2). With a shading normal the importance
            // value also carries the adjoint correction, divided out here.
            let corr = wo.dot(ns).abs() * tr.wi.dot(geo.ng).abs()
                / (wo.dot(geo.ng).abs() * tr.wi.dot(ns).abs());
            let ratio = ti.f / (tr.f * corr);
            check(
                rgb_close(ratio, Rgb::splat(eta_rel * eta_rel), 1e-5),
                format!(
                    "{name}: f_imp / f_rad = {ratio}, expected eta_rel^2 = {}",
                    eta_rel * eta_rel
                ),
            );
            // Energy: sum over events of P(event) * f cos / P(event). With r = t = 1 it is
            // exactly 1 for importance; radiance gains / loses the eta_rel^2 factor physically.
            let e_tran_imp = ti.f * ti.wi.dot(ns).abs() / corr;
            let e_tran_rad = tr.f * tr.wi.dot(ns).abs();
            let e_imp = e_refl + e_tran_imp;
            check(
                rgb_close(e_imp, Rgb::ONE, 1e-5),
                format!("{name}: importance energy {e_imp} != 1"),
            );
            let expect_rad = f_ref as f32 + (1.0 - f_ref as f32) / (eta_rel * eta_rel);
            check(
                rgb_close(e_refl + e_tran_rad, Rgb::splat(expect_rad), 1e-5),
                format!(
                    "{name}: radiance energy {} != {expect_rad}",
                    e_refl + e_tran_rad
                ),
            );
            if outside {
                check(
                    (e_refl + e_tran_rad).max_element() <= 1.0 + 1e-5,
                    format!("{name}: radiance entering glass gains energy"),
                );
            }
            // The choice between the events follows the Fresnel probabilities.
            let n = 200_000;
            let mut rng = Pcg32::new(707, theta.to_bits() as u64);
            let mut n_refl = 0usize;
            for _ in 0..n {
                let (ul, u) = random_u(&mut rng);
                if let Some(s) = bsdf.sample(wo, ul, u, Mode::Radiance)
                    && s.wi.dot(ns) * wo.dot(ns) > 0.0
                {
                    n_refl += 1;
                }
            }
            let frac = n_refl as f64 / n as f64;
            let se = (f_ref * (1.0 - f_ref) / n as f64).sqrt();
            check(
                (frac - f_ref).abs() < 5.0 * se + 1e-6,
                format!("{name}: reflected fraction {frac} vs F {f_ref} (se {se:.1e})"),
            );
        }
    }
    assert!(n_tir >= 3, "no total internal reflection case tested");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

// ================================================================================================
// 4. Robustness
// ================================================================================================

/// Random queries concentrated where things break: exact normals, exact and denormal-grazing
/// cosines (in the geometric and the shading frame), axis directions, pairs related by
/// reflection, and the extreme random numbers 0 and 1 - 2^-24.
struct Fuzz {
    rng: Pcg32,
    frames: [Frame; 2],
}

impl Fuzz {
    fn unit(&mut self) -> f32 {
        match self.rng.next_u32() % 10 {
            0 => 0.0,
            1 => 1.0 - f32::EPSILON / 2.0,
            2 => f32::EPSILON / 2.0,
            3 => 0.5,
            4 => 1.0 - self.rng.next_f32() * 1e-3,
            _ => self.rng.next_f32(),
        }
    }

    fn sign(&mut self) -> f32 {
        if self.rng.next_u32() & 1 == 0 {
            1.0
        } else {
            -1.0
        }
    }

    fn dir(&mut self, other: Vec3) -> Vec3 {
        let frame = self.frames[(self.rng.next_u32() & 1) as usize];
        let phi = 2.0 * std::f32::consts::PI * self.rng.next_f32();
        let around = |z: f32| {
            let r = (1.0 - z * z).max(0.0).sqrt();
            frame.to_world(Vec3::new(r * phi.cos(), r * phi.sin(), z))
        };
        match self.rng.next_u32() % 12 {
            0..=3 => {
                let z = 1.0 - 2.0 * self.rng.next_f32();
                around(z)
            }
            4 => self.sign() * frame.n,
            5 => around(0.0),
            6 | 7 => {
                // |cos| = 10^-e, e in [0.5, 45]: down to the smallest denormal.
                let e = 0.5 + 44.5 * self.rng.next_f32();
                around(self.sign() * 10f32.powf(-e))
            }
            8 => {
                let axes = [Vec3::X, Vec3::Y, Vec3::Z];
                self.sign() * axes[(self.rng.next_u32() % 3) as usize]
            }
            9 => match self.rng.next_u32() % 4 {
                0 => reflect(other, frame.n),
                1 => -other,
                2 => other,
                _ => Vec3::new(-other.x, -other.y, other.z),
            },
            10 => around(self.sign() * (1.0 - self.rng.next_f32() * 1e-6)),
            _ => {
                // Near grazing, cos^4 distributed.
                let z = self.rng.next_f32().powi(4);
                around(self.sign() * z)
            }
        }
    }
}

/// Geometries for the fuzz test. The axis-aligned ones make tiny cosines exact in the local
/// frame (Frame::from_normal(Z) is the identity), so denormal cosines reach the lobes unchanged.
fn fuzz_geos() -> Vec<Geo> {
    let ng_tilt = Vec3::new(-0.3, 0.0, 1.0).normalize();
    vec![
        Geo {
            name: "ns=ng=Z",
            ng: Vec3::Z,
            ns: Vec3::Z,
            two_sided: true,
        },
        Geo {
            name: "ns=ng=Z one-sided",
            ng: Vec3::Z,
            ns: Vec3::Z,
            two_sided: false,
        },
        geo_tilted(),
        Geo {
            name: "ns=Z, ng tilted",
            ng: ng_tilt,
            ns: Vec3::Z,
            two_sided: true,
        },
    ]
}

fn fuzz_one(bsdf: &Bsdf, fz: &mut Fuzz) -> Result<(), String> {
    let wo = fz.dir(Vec3::Z);
    let wi = fz.dir(wo);
    let (ul, u) = (fz.unit(), Vec2::new(fz.unit(), fz.unit()));
    let ctx = || format!("wo {wo:?} wi {wi:?} u ({ul:?}, {u:?})");
    for mode in [Mode::Radiance, Mode::Importance] {
        let f = bsdf.eval(wo, wi, mode);
        if !valid_rgb(f) {
            return Err(format!("eval {mode:?} = {f} at {}", ctx()));
        }
        // The fused query is the three separate ones, bit for bit.
        let fused = bsdf.eval_pdfs(&bsdf.outgoing(wo), wi, mode);
        let apart = (f, bsdf.pdf(wo, wi), bsdf.pdf(wi, wo));
        let bits =
            |(f, a, b): (Rgb, f32, f32)| (f.to_array().map(f32::to_bits), a.to_bits(), b.to_bits());
        if bits(fused) != bits(apart) {
            return Err(format!(
                "eval_pdfs {mode:?} = {fused:?}, apart {apart:?} at {}",
                ctx()
            ));
        }
        // The deferred query (value now, densities after the shadow ray) is the same bits.
        let (fl, pair) = bsdf.eval_local(&bsdf.outgoing(wo), wi, mode);
        let (fwd, rev) = bsdf.pdfs(pair.as_ref());
        let back = bsdf.pdf_back(pair.as_ref());
        let ahead = bsdf.pdf_fwd(pair.as_ref());
        if bits((fl, fwd, rev)) != bits(apart)
            || back.to_bits() != apart.2.to_bits()
            || ahead.to_bits() != apart.1.to_bits()
        {
            return Err(format!(
                "eval_local {mode:?} = {:?}, pdfs ({fwd}, {rev}), pdf_back {back}, pdf_fwd {ahead}; apart {apart:?} at {}",
                fl,
                ctx()
            ));
        }
    }
    let p = bsdf.pdf(wo, wi);
    if !(p.is_finite() && p >= 0.0) {
        return Err(format!("pdf = {p} at {}", ctx()));
    }
    let dp = bsdf.delta_pdf(wo, wi);
    if !(0.0..=1.0).contains(&dp) {
        return Err(format!("delta_pdf = {dp} at {}", ctx()));
    }
    let mode = if fz.rng.next_u32() & 1 == 0 {
        Mode::Radiance
    } else {
        Mode::Importance
    };
    if let Some(s) = bsdf.sample(wo, ul, u, mode) {
        let rev = if s.delta { 0.0 } else { bsdf.pdf(s.wi, wo) };
        if s.pdf_rev.to_bits() != rev.to_bits() {
            return Err(format!(
                "sample {mode:?} = {s:?}, pdf(wi, wo) = {rev} at {}",
                ctx()
            ));
        }
    }
    if let Some(s) = bsdf.sample(wo, ul, u, mode)
        && !(valid_rgb(s.f)
            && s.pdf > 0.0
            && s.pdf.is_finite()
            && s.wi.is_finite()
            && (s.wi.length() - 1.0).abs() < 1e-3)
    {
        return Err(format!("sample {mode:?} = {s:?} at {}", ctx()));
    }
    Ok(())
}

const FUZZ_QUERIES: usize = 1_000_000;

fn run_fuzz(kinds: Kinds, seed: u64) {
    let geos = fuzz_geos();
    let mut failures = Vec::new();
    for (k, (name, kind)) in kinds.iter().enumerate() {
        for (g, geo) in geos.iter().enumerate() {
            let bsdf = bsdf_for(kind, geo);
            let mut fz = Fuzz {
                rng: Pcg32::new(seed, (k * 16 + g) as u64),
                frames: [Frame::from_normal(geo.ng), Frame::from_normal(geo.ns)],
            };
            let mut bad = 0usize;
            let mut first = None;
            for _ in 0..FUZZ_QUERIES / geos.len() {
                if let Err(e) = fuzz_one(&bsdf, &mut fz) {
                    bad += 1;
                    first.get_or_insert(e);
                }
            }
            if let Some(e) = first {
                failures.push(format!(
                    "{name} [{}]: {bad} bad queries, first: {e}",
                    geo.name
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn robustness_lambert_phong_delta() {
    run_fuzz(
        [
            lambert_kinds(),
            phong_kinds(),
            delta_kinds(),
            vec![(
                "black lambert".into(),
                MaterialKind::Lambert { albedo: c(0.0) },
            )],
        ]
        .concat(),
        808,
    );
}

#[test]
fn robustness_microfacet() {
    let mut kinds = [conductor_kinds(), plastic_kinds(), rough_dielectric_kinds()].concat();
    kinds.push(rough_dielectric(1.5, 1e-5, 1e-5));
    kinds.push(rough_dielectric(1.0, 0.3, 0.3));
    kinds.push(rough_dielectric_with(
        Distribution::Beckmann,
        1.5,
        1e-5,
        1e-5,
    ));
    kinds.push((
        "gold beckmann 1e-5".into(),
        gold_with(Distribution::Beckmann, 1e-5, 1e-5),
    ));
    // Roughness below the clamp and a conductor whose Fresnel term is numerically 1.
    kinds.push(("gold ggx 1e-5".into(), gold(1e-5, 1e-5)));
    kinds.push((
        "conductor k=1e3".into(),
        MaterialKind::RoughConductor {
            distribution: Distribution::Beckmann,
            eta: Rgb::ONE,
            k: Rgb::splat(1e3),
            alpha_u: 0.2,
            alpha_v: 0.2,
            scale: Rgb::ONE,
        },
    ));
    run_fuzz(kinds, 909);
}

/// The case Cailleau et al. §V-D warn of: a grazing wo and a visible normal sampled at the rim of the projected disk
/// (u.x -> 1) are nearly perpendicular, so wo.h comes out as a tiny number of either sign. The
/// distribution functions and every BSDF built on them must stay finite and non-negative there,
/// and a sample must still agree with pdf() and eval().
#[test]
fn robustness_grazing_visible_normals() {
    let mut rng = Pcg32::new(1010, 0);
    let mut negative = 0usize;
    let mut failures = Vec::new();
    let geo = Geo {
        name: "ns=ng=Z",
        ng: Vec3::Z,
        ns: Vec3::Z,
        two_sided: true,
    };
    let kinds = [conductor_kinds(), plastic_kinds()].concat();
    let bsdfs: Vec<Bsdf> = kinds.iter().map(|(_, k)| bsdf_for(k, &geo)).collect();
    let ggxs = [
        Microfacet::ggx(0.05, 0.05),
        Microfacet::ggx(0.3, 0.3),
        Microfacet::ggx(0.8, 0.8),
        Microfacet::ggx(0.1, 0.5),
        Microfacet::ggx(0.0, 0.0),
    ];
    for i in 0..400_000 {
        let z = match i % 4 {
            0 => 10f32.powf(-1.0 - 6.0 * rng.next_f32()),
            1 => 10f32.powf(-7.0 - 38.0 * rng.next_f32()),
            2 => 0.2 * rng.next_f32(),
            _ => rng.next_f32(),
        };
        let phi = 2.0 * std::f32::consts::PI * rng.next_f32();
        let r = (1.0 - z * z).max(0.0).sqrt();
        let wo = Vec3::new(r * phi.cos(), r * phi.sin(), z);
        let ux = match i % 3 {
            0 => 1.0 - f32::EPSILON / 2.0,
            1 => 1.0 - 1e-3 * rng.next_f32(),
            _ => 1.0 - 1e-6 * rng.next_f32(),
        };
        let u = Vec2::new(ux, rng.next_f32());
        let ggx = ggxs[i % ggxs.len()];
        let h = ggx.sample_visible_normal(wo, u);
        if !(h.is_finite() && (h.length() - 1.0).abs() < 1e-4 && h.z > 0.0) {
            failures.push(format!("{ggx:?}: h = {h} for wo {wo:?}, u {u:?}"));
            continue;
        }
        let woh = wo.dot(h);
        if woh < 0.0 {
            negative += 1;
        }
        let wi = 2.0 * woh * h - wo;
        let vals = [
            ggx.d(h),
            ggx.visible_normal_pdf(wo, h),
            ggx.reflection_pdf(wo, wi),
            ggx.g1(wo),
            ggx.g2(wo, wi),
        ];
        if vals.iter().any(|v| !(v.is_finite() && *v >= 0.0)) || vals[3] > 1.0 || vals[4] > 1.0 {
            failures.push(format!(
                "{ggx:?}: [D, vis pdf, refl pdf, G1, G2] = {vals:?} for wo {wo:?}, h {h:?}, wo.h {woh:e}"
            ));
        }
        let bsdf = &bsdfs[i % bsdfs.len()];
        let ul = if i % 2 == 0 { 0.0 } else { rng.next_f32() };
        if let Some(s) = bsdf.sample(wo, ul, u, Mode::Radiance)
            && let Err(e) = check_sample(bsdf, wo, &s, Mode::Radiance)
        {
            failures.push(format!(
                "{}: wo {wo:?} u ({ul}, {u:?}) wi {:?}: {e}",
                kinds[i % bsdfs.len()].0,
                s.wi
            ));
        }
        if failures.len() > 20 {
            break;
        }
    }
    println!("visible normals with wo.h < 0: {negative}");
    // The test must actually reach the tiny-negative-cosine regime it is about.
    assert!(negative > 0, "no visible normal with wo.h < 0 was sampled");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

// ================================================================================================
// 5. White furnace
// ================================================================================================

/// Mean and standard error of f cos / pdf per channel over n samples (failures count as 0).
fn albedo(bsdf: &Bsdf, wo: Vec3, n: usize, rng: &mut Pcg32) -> ([f64; 3], [f64; 3]) {
    let mut sum = [0.0f64; 3];
    let mut sum2 = [0.0f64; 3];
    let ns = bsdf.frame.n;
    for _ in 0..n {
        let (ul, u) = random_u(rng);
        if let Some(s) = bsdf.sample(wo, ul, u, Mode::Radiance) {
            let w = s.f * s.wi.dot(ns).abs() / s.pdf;
            for (c, v) in w.to_array().iter().enumerate() {
                sum[c] += *v as f64;
                sum2[c] += (*v as f64).powi(2);
            }
        }
    }
    let nf = n as f64;
    let mean = sum.map(|s| s / nf);
    let se = std::array::from_fn(|ch| ((sum2[ch] / nf - mean[ch] * mean[ch]).max(0.0) / nf).sqrt());
    (mean, se)
}

#[test]
fn white_furnace() {
    const N: usize = 200_000;
    let geo = geo_flat();
    let mut failures = Vec::new();
    // A conductor whose Fresnel term is ~1 at every angle.
    let perfect = |distribution, ax: f32, ay: f32| MaterialKind::RoughConductor {
        distribution,
        eta: Rgb::ONE,
        k: Rgb::splat(1e3),
        alpha_u: ax,
        alpha_v: ay,
        scale: Rgb::ONE,
    };
    for cos in [0.0f32, 0.1, 0.5, 1.0] {
        let f = fresnel::conductor(cos, Rgb::ONE, Rgb::splat(1e3));
        assert!(f.min_element() > 0.999, "F({cos}) = {f}");
    }
    // (material, must equal 1 exactly (within 3 SE), lower bound as a sanity check)
    let mut subjects: Vec<(String, MaterialKind, bool, f64)> = vec![
        (
            "lambert 1".into(),
            MaterialKind::Lambert { albedo: c(1.0) },
            true,
            1.0,
        ),
        (
            "mirror 1".into(),
            MaterialKind::Mirror {
                reflectance: Rgb::ONE,
            },
            true,
            1.0,
        ),
    ];
    for distribution in [Distribution::Ggx, Distribution::Beckmann] {
        for (a, b, lo) in [
            (0.05, 0.05, 0.9),
            (0.3, 0.3, 0.7),
            (0.8, 0.8, 0.4),
            (0.1, 0.5, 0.5),
        ] {
            subjects.push((
                format!("perfect conductor {distribution:?} {a}x{b}"),
                perfect(distribution, a, b),
                false,
                lo,
            ));
        }
    }
    // Energy-normalised modified Phong with kd + ks = 1.
    for n in [1.0, 20.0, 200.0] {
        subjects.push((
            format!("phong kd+ks=1 n={n}"),
            MaterialKind::Phong {
                kd: Rgb::splat(0.4),
                ks: Rgb::splat(0.6),
                exponent: n,
            },
            false,
            0.3,
        ));
    }
    for (i, (name, kind, exact, lower)) in subjects.iter().enumerate() {
        let bsdf = bsdf_for(kind, &geo);
        for (j, (wname, wo)) in wos(&geo).iter().enumerate() {
            let mut rng = Pcg32::new(1111, (i * 16 + j) as u64);
            let (mean, se) = albedo(&bsdf, *wo, N, &mut rng);
            println!(
                "{name:<32} {wname:<16} albedo {mean:.5?} se {:.1e} {:.1e} {:.1e}",
                se[0], se[1], se[2]
            );
            for (ch, (m, s)) in mean.iter().zip(se).enumerate() {
                // 1e-5 absorbs f32 rounding when the estimator has zero variance.
                let tol = 3.0 * s + 1e-5;
                let bad = *m > 1.0 + tol
                    || (*exact && (m - 1.0).abs() > tol)
                    || (wo.dot(geo.ng) > 0.5 && m < lower);
                if bad {
                    failures.push(format!("{name} {wname}: albedo {m} +- {s} (channel {ch})"));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A rough dielectric loses energy only to the single-scattering model's missing interreflection
/// (importance is not compressed by refraction, so its albedo is at most 1); nearly smooth, it
/// is the smooth dielectric, whose albedo is exactly 1 (the same estimator against the analytic
/// value).
#[test]
fn rough_dielectric_energy() {
    const N: usize = 200_000;
    let geo = geo_flat();
    let mut failures = Vec::new();
    let white = |ior: f32, a: f32| MaterialKind::RoughDielectric {
        ior,
        distribution: Distribution::Ggx,
        alpha_u: a,
        alpha_v: a,
        reflectance: Rgb::ONE,
        transmittance: Rgb::ONE,
    };
    // (ior, alpha, lower bound of the albedo at wo within 60 deg of the normal)
    let subjects = [
        (1.5, 0.002, 0.995),
        (1.0 / 1.5, 0.002, 0.995),
        (1.5, 0.2, 0.9),
        (1.5, 0.8, 0.5),
    ];
    for (i, (ior, a, lower)) in subjects.into_iter().enumerate() {
        let bsdf = bsdf_for(&white(ior, a), &geo);
        for (j, (wname, wo)) in wos(&geo).iter().enumerate() {
            let mut rng = Pcg32::new(1212, (i * 16 + j) as u64);
            let mut sum = 0.0f64;
            let mut sum2 = 0.0f64;
            for _ in 0..N {
                let (ul, u) = random_u(&mut rng);
                if let Some(s) = bsdf.sample(*wo, ul, u, Mode::Importance) {
                    let w = (s.f.x * s.wi.dot(bsdf.frame.n).abs() / s.pdf) as f64;
                    sum += w;
                    sum2 += w * w;
                }
            }
            let m = sum / N as f64;
            let se = ((sum2 / N as f64 - m * m).max(0.0) / N as f64).sqrt();
            println!("rough dielectric {ior} ggx {a} {wname:<16} albedo {m:.5} se {se:.1e}");
            let near_normal = wo.dot(geo.ng).abs() > 0.5;
            if m > 1.0 + 3.0 * se + 1e-5 || (near_normal && m < lower) {
                failures.push(format!("ior {ior} alpha {a} {wname}: albedo {m} +- {se}"));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

// ================================================================================================
// The machinery itself
// ================================================================================================

#[test]
fn statistics_helpers_are_correct() {
    // Reference chi-square tail probabilities: Q(dof / 2, x / 2) from mpmath.gammainc at 30 digits.
    let refs = [
        (3.841_458_820_694_124, 1, 0.05),
        (18.307_038_053_275_146, 10, 0.05),
        (100.0, 100, 0.481_191_684_527_956_7),
        (150.0, 100, 0.000_903_932_042_354_009),
        (30.0, 2, 3.059_023_205_018_258e-7),
        (600.0, 480, 0.000_152_204_284_508_461_6),
    ];
    for (x, dof, p) in refs {
        let got = chi2_sf(x, dof);
        assert!(
            (got - p).abs() < 1e-9 * p,
            "chi2_sf({x}, {dof}) = {got}, expected {p}"
        );
    }
    assert!((sidak(0.05, 1) - 0.05).abs() < 1e-15);
    assert!((1.0 - (1.0 - sidak(1e-4, 100)).powi(100) - 1e-4).abs() < 1e-12);
    // Pooling: small cells merge; an impossible observation is an error.
    // Sorted: 1.0, 1.5, 3.5 pool to 6 (>= 5), then 10 stands alone: two cells, one dof.
    let r = chi2_pooled(&[10.0, 1.0, 2.0, 1.0], &[10.0, 1.5, 3.5, 1.0], 5.0).unwrap();
    assert_eq!(r.dof, 1);
    let stat = 0.0 + (4.0f64 - 6.0).powi(2) / 6.0;
    assert!((r.stat - stat).abs() < 1e-12, "{r:?}");
    // Pooling goes on past a small cell until the pool holds 5 expected samples.
    let r = chi2_pooled(&[10.0, 1.0, 2.0, 1.0], &[10.0, 1.5, 1.5, 1.0], 5.0).unwrap();
    assert_eq!(r.dof, 0);
    assert!(chi2_pooled(&[1.0, 9.0], &[0.0, 10.0], 5.0).is_err());

    // The grid integrates densities exactly where they are smooth and accurately across a
    // horizon that cuts bins diagonally.
    let pole = Vec3::new(0.2, 0.5, -0.6).normalize();
    let h = Vec3::new(0.1, -0.3, 0.9).normalize();
    let grid = Grid::new(pole, &[h]);
    let uniform: f64 = grid.integrate(&|_| 0.25 / PI64).iter().sum();
    assert!((uniform - 1.0).abs() < 1e-9, "{uniform}");
    let lambert: f64 = grid
        .integrate(&|w| (w.dot(h) as f64).max(0.0) / PI64)
        .iter()
        .sum();
    assert!((lambert - 1.0).abs() < 1e-5, "{lambert}");
    // A density with a jump at the horizon (uniform hemisphere): the worst case for the cut.
    let hemi: f64 = grid
        .integrate(&|w| if w.dot(h) > 0.0 { 0.5 / PI64 } else { 0.0 })
        .iter()
        .sum();
    println!(
        "integration errors: cosine {:.2e}, hemisphere {:.2e}",
        lambert - 1.0,
        hemi - 1.0
    );
    assert!((hemi - 1.0).abs() < INTEGRATION_TOL / 4.0, "{hemi}");
    // Binning agrees with the integration domains: a direction generated inside a bin lands in it.
    let mut rng = Pcg32::new(1212, 0);
    for _ in 0..10_000 {
        let cell = (rng.next_u32() as usize) % grid.cells();
        let (i, j) = (cell / N_PHI, cell % N_PHI);
        let z = Grid::cos_edge(i + 1)
            + (0.05 + 0.9 * rng.next_f64()) * (Grid::cos_edge(i) - Grid::cos_edge(i + 1));
        let p = Grid::phi_edge(j) + (0.05 + 0.9 * rng.next_f64()) * (2.0 * PI64 / N_PHI as f64);
        assert_eq!(grid.cell_of(grid.dir(z, p)), cell);
    }
}
