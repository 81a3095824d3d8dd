//! Delta lobes: mirror and smooth dielectric.

use crate::cases::*;
use crate::grid::*;
use crate::support::{reflect, rel_close, rgb_close};
use omis::geometry::{Rgb, Vec2};
use omis::material::{MaterialKind, Mode};
use omis::sampler::Pcg32;

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
