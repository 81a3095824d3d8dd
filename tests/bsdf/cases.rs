//! The materials and geometry under test.

use super::chi2::POWER_TESTS;
use super::grid::*;
use super::stats::*;

use omis::geometry::{Frame, Rgb, Vec2, Vec3};
use omis::material::{Bsdf, Distribution, Material, MaterialKind, Mode, Texture};
use omis::sampler::Pcg32;

// ================================================================================================
// Materials and geometry under test
// ================================================================================================

pub type Kinds = Vec<(String, MaterialKind)>;

#[derive(Clone, Copy, Debug)]
pub struct Geo {
    pub name: &'static str,
    pub ng: Vec3,
    pub ns: Vec3,
    pub two_sided: bool,
}

/// A geometric normal in no special position, so frames are exercised in general position.
pub fn ng_generic() -> Vec3 {
    Vec3::new(0.3, -0.2, 0.9).normalize()
}

/// Shading normal tilted by atan(0.3) = 16.7 deg towards the tangent of ng's frame.
pub fn tilted(ng: Vec3) -> Vec3 {
    (ng + 0.3 * Frame::from_normal(ng).s).normalize()
}

pub fn geo_flat() -> Geo {
    Geo {
        name: "ns=ng",
        ng: ng_generic(),
        ns: ng_generic(),
        two_sided: true,
    }
}

pub fn geo_tilted() -> Geo {
    Geo {
        name: "tilted ns",
        ng: ng_generic(),
        ns: tilted(ng_generic()),
        two_sided: true,
    }
}

pub fn geo_one_sided() -> Geo {
    Geo {
        name: "ns=ng one-sided",
        two_sided: false,
        ..geo_flat()
    }
}

pub fn geo_tilted_one_sided() -> Geo {
    Geo {
        name: "tilted ns one-sided",
        two_sided: false,
        ..geo_tilted()
    }
}

/// Direction at polar angle `theta_deg` from `n` and azimuth `phi` in n's frame.
pub fn about(n: Vec3, theta_deg: f32, phi: f32) -> Vec3 {
    let t = theta_deg.to_radians();
    Frame::from_normal(n).to_world(Vec3::new(t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos()))
}

/// Outgoing directions: along the normal, 45 deg, grazing 80 deg, and 45 deg on the back side
/// (flipped by two-sided materials, black for one-sided ones); with a tilted shading normal also
/// 60 deg on the side the shading normal leans away from.
pub fn wos(geo: &Geo) -> Vec<(&'static str, Vec3)> {
    let mut v = vec![
        ("wo 0deg", about(geo.ng, 0.0, 0.4)),
        ("wo 45deg", about(geo.ng, 45.0, 0.4)),
        ("wo 80deg", about(geo.ng, 80.0, 0.4)),
        ("wo back 45deg", about(geo.ng, 135.0, 0.4)),
    ];
    if geo.ns != geo.ng {
        v.push((
            "wo 60deg away from ns",
            about(geo.ng, 60.0, 0.4 + std::f32::consts::PI),
        ));
    }
    v
}

pub fn c(v: f32) -> Texture {
    Texture::Constant(Rgb::splat(v))
}

pub fn lambert_kinds() -> Kinds {
    vec![(
        "lambert".into(),
        MaterialKind::Lambert {
            albedo: Texture::Constant(Rgb::new(0.8, 0.5, 0.2)),
        },
    )]
}

pub fn phong_kinds() -> Kinds {
    let p = |kd: f32, ks: f32, n: f32| {
        (
            format!("phong n={n} kd={kd} ks={ks}"),
            MaterialKind::Phong {
                kd: Rgb::splat(kd),
                ks: Rgb::new(ks, 0.8 * ks, 0.6 * ks),
                exponent: n,
            },
        )
    };
    vec![
        p(0.5, 0.4, 1.0),
        p(0.2, 0.7, 20.0),
        p(0.0, 0.9, 200.0),
        p(0.6, 0.3, 200.0),
    ]
}

/// Gold at roughly 650 / 550 / 450 nm.
pub fn gold(ax: f32, ay: f32) -> MaterialKind {
    gold_with(Distribution::Ggx, ax, ay)
}

pub fn gold_with(distribution: Distribution, ax: f32, ay: f32) -> MaterialKind {
    MaterialKind::RoughConductor {
        distribution,
        eta: Rgb::new(0.143, 0.374, 1.442),
        k: Rgb::new(3.983, 2.386, 1.603),
        alpha_u: ax,
        alpha_v: ay,
        scale: Rgb::ONE,
    }
}

pub fn conductor_kinds() -> Kinds {
    vec![
        ("gold ggx 0.05".into(), gold(0.05, 0.05)),
        ("gold ggx 0.3".into(), gold(0.3, 0.3)),
        ("gold ggx 0.8".into(), gold(0.8, 0.8)),
        ("gold ggx 0.1x0.5".into(), gold(0.1, 0.5)),
        (
            "gold beckmann 0.05".into(),
            gold_with(Distribution::Beckmann, 0.05, 0.05),
        ),
        (
            "gold beckmann 0.5".into(),
            gold_with(Distribution::Beckmann, 0.5, 0.5),
        ),
        (
            "gold beckmann 0.1x0.5".into(),
            gold_with(Distribution::Beckmann, 0.1, 0.5),
        ),
    ]
}

pub fn plastic(alpha: f32, layered: bool, nonlinear: bool) -> (String, MaterialKind) {
    plastic_with(Distribution::Ggx, alpha, layered, nonlinear)
}

pub fn plastic_with(
    distribution: Distribution,
    alpha: f32,
    layered: bool,
    nonlinear: bool,
) -> (String, MaterialKind) {
    (
        format!("plastic {distribution:?} alpha={alpha} layered={layered} nonlinear={nonlinear}"),
        MaterialKind::Plastic {
            distribution,
            diffuse: Texture::Constant(Rgb::new(0.6, 0.3, 0.1)),
            specular: Rgb::ONE,
            ior: 1.5,
            alpha,
            layered,
            nonlinear,
        },
    )
}

pub fn plastic_kinds() -> Kinds {
    vec![
        plastic(0.05, true, false),
        plastic(0.3, true, true),
        plastic(0.05, false, false),
        plastic(0.3, false, false),
        plastic_with(Distribution::Beckmann, 0.2, true, true),
    ]
}

pub fn rough_dielectric(ior: f32, ax: f32, ay: f32) -> (String, MaterialKind) {
    rough_dielectric_with(Distribution::Ggx, ior, ax, ay)
}

pub fn rough_dielectric_with(
    distribution: Distribution,
    ior: f32,
    ax: f32,
    ay: f32,
) -> (String, MaterialKind) {
    (
        format!("rough dielectric {ior} {distribution:?} {ax}x{ay}"),
        MaterialKind::RoughDielectric {
            distribution,
            ior,
            alpha_u: ax,
            alpha_v: ay,
            reflectance: Rgb::ONE,
            transmittance: Rgb::new(1.0, 0.9, 0.8),
        },
    )
}

pub fn rough_dielectric_kinds() -> Kinds {
    vec![
        rough_dielectric(1.5, 0.1, 0.1),
        rough_dielectric(1.33, 0.5, 0.5),
        rough_dielectric(1.0 / 1.5, 0.3, 0.3),
        rough_dielectric(1.5, 0.05, 0.4),
        rough_dielectric_with(Distribution::Beckmann, 1.5, 0.2, 0.2),
        rough_dielectric_with(Distribution::Beckmann, 1.0 / 1.33, 0.1, 0.4),
    ]
}

pub fn delta_kinds() -> Kinds {
    vec![
        (
            "mirror".into(),
            MaterialKind::Mirror {
                reflectance: Rgb::new(0.9, 0.8, 0.7),
            },
        ),
        (
            "dielectric 1.5".into(),
            MaterialKind::Dielectric {
                ior: 1.5,
                reflectance: Rgb::ONE,
                transmittance: Rgb::new(1.0, 0.9, 0.8),
            },
        ),
        (
            "thin dielectric 1.5".into(),
            MaterialKind::ThinDielectric {
                ior: 1.5,
                reflectance: Rgb::ONE,
                transmittance: Rgb::new(1.0, 0.9, 0.8),
            },
        ),
    ]
}

pub fn smooth_kinds() -> Kinds {
    [
        lambert_kinds(),
        phong_kinds(),
        conductor_kinds(),
        plastic_kinds(),
        rough_dielectric_kinds(),
    ]
    .concat()
}

#[derive(Clone)]
pub struct Case {
    pub name: String,
    pub bsdf: Bsdf,
    pub wo: Vec3,
    pub geo: Geo,
}

pub fn bsdf_for(kind: &MaterialKind, geo: &Geo) -> Bsdf {
    let m = Material::new("test", kind.clone(), geo.two_sided);
    Bsdf::new(&m, geo.ng, geo.ns, Vec2::new(0.25, 0.75))
}

pub fn cases(kinds: &Kinds, geos: &[Geo]) -> Vec<Case> {
    let mut out = Vec::new();
    for (name, kind) in kinds {
        for geo in geos {
            let bsdf = bsdf_for(kind, geo);
            for (wname, wo) in wos(geo) {
                out.push(Case {
                    name: format!("{name} [{}] {wname}", geo.name),
                    bsdf,
                    wo,
                    geo: *geo,
                });
            }
        }
    }
    out
}

/// Cases whose wo is a direction sampled from wo = 45 deg: their chi2 tests that pdf(wi, .) is
/// the density with which sample(wi, ..) produces directions, i.e. that the reverse pdf BDPT uses
/// for a sampled pair (wo, wi) is right.
pub fn reverse_cases(kinds: &Kinds, geos: &[Geo]) -> Vec<Case> {
    let mut out = Vec::new();
    for (k, (name, kind)) in kinds.iter().enumerate() {
        for (g, geo) in geos.iter().enumerate() {
            let bsdf = bsdf_for(kind, geo);
            let wo = about(geo.ng, 45.0, 0.4);
            let mut rng = Pcg32::new(0xbad_5eed, (k * 16 + g) as u64);
            let mut found = 0;
            for _ in 0..10_000 {
                let (ul, u) = random_u(&mut rng);
                if let Some(s) = bsdf.sample(wo, ul, u, Mode::Radiance) {
                    out.push(Case {
                        name: format!(
                            "{name} [{}] reverse: wo = sample #{found} from 45deg",
                            geo.name
                        ),
                        bsdf,
                        wo: s.wi,
                        geo: *geo,
                    });
                    found += 1;
                    if found == 2 {
                        break;
                    }
                }
            }
            assert_eq!(found, 2, "{name}: sample() from 45 deg never succeeds");
        }
    }
    out
}

pub fn chi2_cases_for(kinds: &Kinds) -> Vec<Case> {
    let geos = [geo_flat(), geo_tilted()];
    let mut v = cases(kinds, &geos);
    v.extend(reverse_cases(kinds, &geos));
    v
}

/// Every chi2 test in this file counts towards one Sidak family.
pub fn chi2_family_size() -> usize {
    [
        [lambert_kinds(), phong_kinds()].concat(),
        conductor_kinds(),
        plastic_kinds(),
        rough_dielectric_kinds(),
    ]
    .iter()
    .map(|k| chi2_cases_for(k).len())
    .sum::<usize>()
        + POWER_TESTS
}

/// Family-wise significance of all chi2 tests together.
pub const CHI2_ALPHA: f64 = 1e-4;
pub const CHI2_SAMPLES: usize = 300_000;

pub fn run_chi2_suite(kinds: Kinds, seed: u64) {
    let alpha = sidak(CHI2_ALPHA, chi2_family_size());
    let mut failures = Vec::new();
    let cases = chi2_cases_for(&kinds);
    for (i, case) in cases.iter().enumerate() {
        let mut rng = Pcg32::new(seed, i as u64);
        match chi2_bsdf(&case.bsdf, case.wo, CHI2_SAMPLES, &mut rng) {
            Ok(r) => {
                println!(
                    "{:<75} chi2 = {:>9.2} dof = {:>3} p = {:.3e}",
                    case.name, r.stat, r.dof, r.p
                );
                if r.p < alpha {
                    failures.push(format!(
                        "{}: chi2 = {:.2}, dof = {}, p = {:.3e} < {alpha:.3e}",
                        case.name, r.stat, r.dof, r.p
                    ));
                }
            }
            Err(e) => failures.push(format!("{}: {e}", case.name)),
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} chi2 tests rejected sample() against pdf() at significance {alpha:.3e}:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}
