//! Each sample agrees with `eval()` and `pdf()`; reciprocity and the adjoint relation.

use crate::cases::*;
use crate::grid::*;
use crate::support::{check_sample, rel_close, rgb_close};
use omis::geometry::Vec3;
use omis::material::{Bsdf, Mode};
use omis::sampler::Pcg32;

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
