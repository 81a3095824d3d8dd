//! Robustness: no NaN, inf or negative values anywhere, grazing and degenerate directions included.

use crate::cases::*;
use crate::support::{check_sample, reflect, valid_rgb};
use omis::geometry::{Frame, Rgb, Vec2, Vec3};
use omis::material::microfacet::Microfacet;
use omis::material::{Bsdf, Distribution, MaterialKind, Mode};
use omis::sampler::Pcg32;

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
