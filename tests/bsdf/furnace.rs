//! Energy conservation: the white furnace and the rough dielectric's energy.

use crate::cases::*;
use crate::grid::*;
use crate::support::albedo;
use omis::geometry::Rgb;
use omis::material::{Distribution, MaterialKind, Mode, fresnel};
use omis::sampler::Pcg32;

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
