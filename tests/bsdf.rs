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

use std::f64::consts::PI as PI64;

use omis::geometry::{Frame, Rgb, Vec2, Vec3};
use omis::material::fresnel;
use omis::material::microfacet::Ggx;
use omis::material::{Bsdf, BsdfSample, Material, MaterialKind, Mode, Texture};
use omis::sampler::Pcg32;

// ================================================================================================
// Statistics
// ================================================================================================

/// ln Gamma(x) for x > 0 (Lanczos, g = 7, n = 9; ~1e-15 relative).
fn ln_gamma(x: f64) -> f64 {
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
fn gamma_q(a: f64, x: f64) -> f64 {
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
fn chi2_sf(stat: f64, dof: usize) -> f64 {
    gamma_q(0.5 * dof as f64, 0.5 * stat)
}

/// Per-test significance level so that m independent tests together reject a correct
/// implementation with probability `alpha` (Sidak): 1 - (1 - alpha)^(1/m).
fn sidak(alpha: f64, m: usize) -> f64 {
    -((-alpha).ln_1p() / m as f64).exp_m1()
}

#[derive(Debug, Clone, Copy)]
struct Chi2 {
    stat: f64,
    dof: usize,
    p: f64,
}

/// Pearson's chi-square with Mitsuba's pooling: cells sorted by expected count; those with fewer
/// than `min_exp` expected samples are pooled (and pooling continues until the pool reaches
/// `min_exp`). An observation in a cell of zero probability is an error.
fn chi2_pooled(obs: &[f64], exp: &[f64], min_exp: f64) -> Result<Chi2, String> {
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

// ================================================================================================
// Spherical grid: binning of directions and numerical integration over the bins
// ================================================================================================

const N_THETA: usize = 20;
const N_PHI: usize = 24;
/// Sub-cells per bin and per dimension, each integrated by 2 x 2 Gauss-Legendre. (The midpoint
/// rule is not enough: it under-integrates the Phong n = 200 peak by 3e-4 of its mass, which the
/// chi2 test, with its "sample failed" cell, detects at 3e5 samples.)
const SUB: usize = 8;
/// Sub-cells that a horizon (a discontinuity of the pdf) crosses are split REFINE x REFINE times,
/// DEPTH times over, so the quadrature stays accurate across the cut.
const REFINE: usize = 8;
const DEPTH: u32 = 2;

/// Bins over the whole sphere in a frame whose pole is (usually) the mirror direction, where the
/// glossy lobes peak: theta edges at pi (i / N_THETA)^2 give fine rings around the peak and coarse
/// ones far from it; uniform in phi. Bins are integrated in (cos theta, phi), whose Jacobian is 1.
struct Grid {
    frame: Frame,
    /// Normals of the great circles where the pdf may jump (geometric and shading horizons).
    horizons: Vec<Vec3>,
}

impl Grid {
    fn new(pole: Vec3, horizons: &[Vec3]) -> Grid {
        Grid {
            frame: Frame::from_normal(pole.normalize()),
            horizons: horizons.to_vec(),
        }
    }

    /// Pole at the mirror direction of wo about the shading normal.
    fn for_bsdf(bsdf: &Bsdf, wo: Vec3) -> Grid {
        let ns = bsdf.frame.n;
        let r = 2.0 * wo.dot(ns) * ns - wo;
        Grid::new(r, &[bsdf.ng, ns])
    }

    fn cells(&self) -> usize {
        N_THETA * N_PHI
    }

    fn cos_edge(i: usize) -> f64 {
        let t = i as f64 / N_THETA as f64;
        (PI64 * t * t).cos()
    }

    fn phi_edge(j: usize) -> f64 {
        -PI64 + 2.0 * PI64 * j as f64 / N_PHI as f64
    }

    fn cell_of(&self, w: Vec3) -> usize {
        let l = self.frame.to_local(w);
        let (x, y, z) = (l.x as f64, l.y as f64, l.z as f64);
        let theta = (x * x + y * y).sqrt().atan2(z);
        let t = (theta / PI64).max(0.0).sqrt();
        let i = ((t * N_THETA as f64) as usize).min(N_THETA - 1);
        let phi = y.atan2(x);
        let j = (((phi + PI64) / (2.0 * PI64) * N_PHI as f64) as usize).min(N_PHI - 1);
        i * N_PHI + j
    }

    fn dir(&self, z: f64, phi: f64) -> Vec3 {
        let r = (1.0 - z * z).max(0.0).sqrt();
        let l = Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32);
        self.frame.to_world(l)
    }

    /// Direction at polar coordinates given as (z, sqrt(1 - z^2)) and (cos phi, sin phi).
    fn dir_at(&self, (z, r): (f64, f64), (c, s): (f64, f64)) -> Vec3 {
        self.frame
            .to_world(Vec3::new((r * c) as f32, (r * s) as f32, z as f32))
    }

    /// Integral of g over z in [z0, z1], phi in [p0, p1], split into n x n sub-cells with 2 x 2
    /// Gauss-Legendre each; sub-cells whose corners lie on different sides of a horizon are
    /// split again (`depth` more times).
    #[allow(clippy::too_many_arguments)]
    fn integrate_rect(
        &self,
        g: &impl Fn(Vec3) -> f64,
        z0: f64,
        z1: f64,
        p0: f64,
        p1: f64,
        n: usize,
        depth: u32,
    ) -> f64 {
        // 2-point Gauss-Legendre nodes at the centre +- h / (2 sqrt 3), weights h / 2.
        const D: f64 = 0.5 / 1.732_050_807_568_877_2;
        let dz = (z1 - z0) / n as f64;
        let dp = (p1 - p0) / n as f64;
        let zr = |z: f64| (z, (1.0 - z * z).max(0.0).sqrt());
        let cs = |p: f64| (p.cos(), p.sin());
        // Horizon sides of the sub-cell corners (bit k: above horizon k).
        let corner_side: Vec<u32> = if depth > 0 {
            let zs: Vec<_> = (0..=n).map(|a| zr(z0 + a as f64 * dz)).collect();
            let ps: Vec<_> = (0..=n).map(|b| cs(p0 + b as f64 * dp)).collect();
            zs.iter()
                .flat_map(|&z| ps.iter().map(move |&p| (z, p)))
                .map(|(z, p)| {
                    let d = self.dir_at(z, p);
                    self.horizons
                        .iter()
                        .enumerate()
                        .fold(0, |m, (k, h)| m | (u32::from(d.dot(*h) > 0.0) << k))
                })
                .collect()
        } else {
            Vec::new()
        };
        let zq: Vec<_> = (0..2 * n)
            .map(|k| zr(z0 + (k / 2) as f64 * dz + (0.5 + if k % 2 == 0 { -D } else { D }) * dz))
            .collect();
        let pq: Vec<_> = (0..2 * n)
            .map(|k| cs(p0 + (k / 2) as f64 * dp + (0.5 + if k % 2 == 0 { -D } else { D }) * dp))
            .collect();
        let mut sum = 0.0;
        for a in 0..n {
            for b in 0..n {
                if depth > 0 {
                    let i = a * (n + 1) + b;
                    let c = corner_side[i];
                    let straddles = corner_side[i + 1] != c
                        || corner_side[i + n + 1] != c
                        || corner_side[i + n + 2] != c;
                    if straddles {
                        let (za, pa) = (z0 + a as f64 * dz, p0 + b as f64 * dp);
                        sum += self.integrate_rect(g, za, za + dz, pa, pa + dp, REFINE, depth - 1);
                        continue;
                    }
                }
                let mut cell = 0.0;
                for &z in &zq[2 * a..2 * a + 2] {
                    for &p in &pq[2 * b..2 * b + 2] {
                        cell += g(self.dir_at(z, p));
                    }
                }
                sum += 0.25 * cell * dz * dp;
            }
        }
        sum
    }

    /// Integral of g (a density in solid angle) over every bin.
    fn integrate(&self, g: &impl Fn(Vec3) -> f64) -> Vec<f64> {
        let mut out = Vec::with_capacity(self.cells());
        for i in 0..N_THETA {
            // Bin i spans theta in [theta_i, theta_i+1], i.e. cos theta in [cos_edge(i+1), cos_edge(i)].
            let (z0, z1) = (Grid::cos_edge(i + 1), Grid::cos_edge(i));
            for j in 0..N_PHI {
                let (p0, p1) = (Grid::phi_edge(j), Grid::phi_edge(j + 1));
                out.push(self.integrate_rect(g, z0, z1, p0, p1, SUB, DEPTH));
            }
        }
        out
    }
}

/// Chi-square test of `sample` (a direction or None) against the density `pdf`. The outcome
/// "None" is one more cell, with probability 1 - integral of pdf.
fn chi2_test(
    grid: &Grid,
    n: usize,
    rng: &mut Pcg32,
    mut sample: impl FnMut(&mut Pcg32) -> Option<Vec3>,
    pdf: impl Fn(Vec3) -> f64,
) -> Result<Chi2, String> {
    let cells = grid.cells();
    let mut obs = vec![0.0f64; cells + 1];
    for _ in 0..n {
        match sample(rng) {
            Some(wi) => {
                if !wi.is_finite() {
                    return Err(format!("sampled a non-finite direction {wi}"));
                }
                obs[grid.cell_of(wi)] += 1.0
            }
            None => obs[cells] += 1.0,
        }
    }
    let integral = grid.integrate(&pdf);
    let total: f64 = integral.iter().sum();
    let mut exp: Vec<f64> = integral.iter().map(|p| p * n as f64).collect();
    // The integration error can push a (near-)zero failure probability below zero; a floor of
    // 1e-3 expected samples keeps that cell in the pooled remainder instead of calling a single
    // failed sample impossible. A real surplus of failures still shows up in the statistic.
    exp.push((n as f64 * (1.0 - total)).max(1e-3));
    chi2_pooled(&obs, &exp, 5.0)
}

fn random_u(rng: &mut Pcg32) -> (f32, Vec2) {
    let ul = rng.next_f32();
    let u = Vec2::new(rng.next_f32(), rng.next_f32());
    (ul, u)
}

fn chi2_bsdf(bsdf: &Bsdf, wo: Vec3, n: usize, rng: &mut Pcg32) -> Result<Chi2, String> {
    let grid = Grid::for_bsdf(bsdf, wo);
    chi2_test(
        &grid,
        n,
        rng,
        |rng| {
            let (ul, u) = random_u(rng);
            bsdf.sample(wo, ul, u, Mode::Radiance).map(|s| s.wi)
        },
        |wi| bsdf.pdf(wo, wi) as f64,
    )
}

// ================================================================================================
// Materials and geometry under test
// ================================================================================================

type Kinds = Vec<(String, MaterialKind)>;

#[derive(Clone, Copy, Debug)]
struct Geo {
    name: &'static str,
    ng: Vec3,
    ns: Vec3,
    two_sided: bool,
}

/// A geometric normal in no special position, so frames are exercised in general position.
fn ng_generic() -> Vec3 {
    Vec3::new(0.3, -0.2, 0.9).normalize()
}

/// Shading normal tilted by atan(0.3) = 16.7 deg towards the tangent of ng's frame.
fn tilted(ng: Vec3) -> Vec3 {
    (ng + 0.3 * Frame::from_normal(ng).s).normalize()
}

fn geo_flat() -> Geo {
    Geo {
        name: "ns=ng",
        ng: ng_generic(),
        ns: ng_generic(),
        two_sided: true,
    }
}

fn geo_tilted() -> Geo {
    Geo {
        name: "tilted ns",
        ng: ng_generic(),
        ns: tilted(ng_generic()),
        two_sided: true,
    }
}

fn geo_one_sided() -> Geo {
    Geo {
        name: "ns=ng one-sided",
        two_sided: false,
        ..geo_flat()
    }
}

fn geo_tilted_one_sided() -> Geo {
    Geo {
        name: "tilted ns one-sided",
        two_sided: false,
        ..geo_tilted()
    }
}

/// Direction at polar angle `theta_deg` from `n` and azimuth `phi` in n's frame.
fn about(n: Vec3, theta_deg: f32, phi: f32) -> Vec3 {
    let t = theta_deg.to_radians();
    Frame::from_normal(n).to_world(Vec3::new(t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos()))
}

/// Outgoing directions: along the normal, 45 deg, grazing 80 deg, and 45 deg on the back side
/// (flipped by two-sided materials, black for one-sided ones); with a tilted shading normal also
/// 60 deg on the side the shading normal leans away from.
fn wos(geo: &Geo) -> Vec<(&'static str, Vec3)> {
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

fn c(v: f32) -> Texture {
    Texture::Constant(Rgb::splat(v))
}

fn lambert_kinds() -> Kinds {
    vec![(
        "lambert".into(),
        MaterialKind::Lambert {
            albedo: Texture::Constant(Rgb::new(0.8, 0.5, 0.2)),
        },
    )]
}

fn phong_kinds() -> Kinds {
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
fn gold(ax: f32, ay: f32) -> MaterialKind {
    MaterialKind::RoughConductor {
        eta: Rgb::new(0.143, 0.374, 1.442),
        k: Rgb::new(3.983, 2.386, 1.603),
        alpha_u: ax,
        alpha_v: ay,
        scale: Rgb::ONE,
    }
}

fn conductor_kinds() -> Kinds {
    vec![
        ("gold ggx 0.05".into(), gold(0.05, 0.05)),
        ("gold ggx 0.3".into(), gold(0.3, 0.3)),
        ("gold ggx 0.8".into(), gold(0.8, 0.8)),
        ("gold ggx 0.1x0.5".into(), gold(0.1, 0.5)),
    ]
}

fn plastic(alpha: f32, layered: bool, nonlinear: bool) -> (String, MaterialKind) {
    (
        format!("plastic alpha={alpha} layered={layered} nonlinear={nonlinear}"),
        MaterialKind::Plastic {
            diffuse: Texture::Constant(Rgb::new(0.6, 0.3, 0.1)),
            specular: Rgb::ONE,
            ior: 1.5,
            alpha,
            layered,
            nonlinear,
        },
    )
}

fn plastic_kinds() -> Kinds {
    vec![
        plastic(0.05, true, false),
        plastic(0.3, true, true),
        plastic(0.05, false, false),
        plastic(0.3, false, false),
    ]
}

fn delta_kinds() -> Kinds {
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
    ]
}

fn smooth_kinds() -> Kinds {
    [
        lambert_kinds(),
        phong_kinds(),
        conductor_kinds(),
        plastic_kinds(),
    ]
    .concat()
}

#[derive(Clone)]
struct Case {
    name: String,
    bsdf: Bsdf,
    wo: Vec3,
    geo: Geo,
}

fn bsdf_for(kind: &MaterialKind, geo: &Geo) -> Bsdf {
    let m = Material::new("test", kind.clone(), geo.two_sided);
    Bsdf::new(&m, geo.ng, geo.ns, Vec2::new(0.25, 0.75))
}

fn cases(kinds: &Kinds, geos: &[Geo]) -> Vec<Case> {
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
fn reverse_cases(kinds: &Kinds, geos: &[Geo]) -> Vec<Case> {
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

fn chi2_cases_for(kinds: &Kinds) -> Vec<Case> {
    let geos = [geo_flat(), geo_tilted()];
    let mut v = cases(kinds, &geos);
    v.extend(reverse_cases(kinds, &geos));
    v
}

/// Every chi2 test in this file counts towards one Sidak family.
fn chi2_family_size() -> usize {
    [
        [lambert_kinds(), phong_kinds()].concat(),
        conductor_kinds(),
        plastic_kinds(),
    ]
    .iter()
    .map(|k| chi2_cases_for(k).len())
    .sum::<usize>()
        + POWER_TESTS
}

/// Family-wise significance of all chi2 tests together.
const CHI2_ALPHA: f64 = 1e-4;
const CHI2_SAMPLES: usize = 300_000;

fn run_chi2_suite(kinds: Kinds, seed: u64) {
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
fn chi2_plastic() {
    run_chi2_suite(plastic_kinds(), 303);
}

/// Number of chi2 tests in `chi2_has_power_against_wrong_pdfs` (part of the Sidak family).
const POWER_TESTS: usize = 4;

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
        if !case.geo.two_sided && wo.dot(case.geo.ng) < 0.0 {
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
    if ng == ns {
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
        // A two-sided surface seen from the back is its front mirrored through the surface.
        if wo.dot(ng) < 0.0 {
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
    let mut kinds = [conductor_kinds(), plastic_kinds()].concat();
    // Roughness below the clamp and a conductor whose Fresnel term is numerically 1.
    kinds.push(("gold ggx 1e-5".into(), gold(1e-5, 1e-5)));
    kinds.push((
        "conductor k=1e3".into(),
        MaterialKind::RoughConductor {
            eta: Rgb::ONE,
            k: Rgb::splat(1e3),
            alpha_u: 0.2,
            alpha_v: 0.2,
            scale: Rgb::ONE,
        },
    ));
    run_fuzz(kinds, 909);
}

/// Seed report case: a grazing wo and a visible normal sampled at the rim of the projected disk
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
        Ggx::new(0.05, 0.05),
        Ggx::new(0.3, 0.3),
        Ggx::new(0.8, 0.8),
        Ggx::new(0.1, 0.5),
        Ggx::new(0.0, 0.0),
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
    let perfect = |ax: f32, ay: f32| MaterialKind::RoughConductor {
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
    for (a, b, lo) in [
        (0.05, 0.05, 0.9),
        (0.3, 0.3, 0.7),
        (0.8, 0.8, 0.4),
        (0.1, 0.5, 0.5),
    ] {
        subjects.push((
            format!("perfect conductor ggx {a}x{b}"),
            perfect(a, b),
            false,
            lo,
        ));
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
