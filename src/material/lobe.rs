//! The scattering models in their local shading frame (+z = shading normal, wo.z > 0 for the
//! reflection-only models, which the caller guarantees by flipping two-sided surfaces).
//!
//! Conventions: `eval` returns the BSDF value f(wo, wi) without the cosine; `pdf(wo, wi)` is the
//! solid-angle density with which `sample(wo, ..)` produces wi; delta lobes return f = 0 and
//! pdf = 0 from `eval`/`pdf` and a discrete probability from `sample`.

use super::Mode;
use super::fresnel;
use super::microfacet::Microfacet;
use crate::geometry::warp::{
    cosine_hemisphere, cosine_hemisphere_pdf, power_cosine, power_cosine_pdf,
};
use crate::geometry::{Frame, INV_2PI, INV_PI, Rgb, Vec2, Vec3, luminance, max_component};

/// A scattering model with its parameters resolved for one shading point.
#[derive(Clone, Copy, Debug)]
pub enum Lobe {
    /// Absorbs everything (e.g. the geometry of an emitter with no reflectance).
    Black,
    /// Diffuse reflection, r / pi.
    Lambert {
        /// Reflectance.
        r: Rgb,
    },
    /// Modified Phong (Lafortune & Willems 1994), energy-normalised: kd/pi + ks (n+2)/(2 pi) cos^n a.
    /// The specular lobe is chosen with probability `q` from the albedos (Lambers, "Path Tracing" lecture notes).
    Phong {
        /// Diffuse reflectance.
        kd: Rgb,
        /// Specular reflectance.
        ks: Rgb,
        /// The specular exponent n.
        n: f32,
        /// Probability of sampling the specular lobe.
        q: f32,
    },
    /// Ideal specular reflection.
    Mirror {
        /// Reflectance.
        r: Rgb,
    },
    /// Smooth dielectric; `eta` = interior / exterior index.
    Dielectric {
        /// Interior / exterior index of refraction.
        eta: f32,
        /// Scale of the reflected part.
        r: Rgb,
        /// Scale of the transmitted part.
        t: Rgb,
    },
    /// Rough dielectric: GGX microfacet reflection and refraction (Walter et al. 2007,
    /// "Microfacet Models for Refraction through Rough Surfaces", EGSR, eqs. 20 and 21).
    RoughDielectric {
        /// The microfacet distribution (the same seen from either side).
        mf: Microfacet,
        /// Interior / exterior index of refraction.
        eta: f32,
        /// Scale of the reflected part.
        r: Rgb,
        /// Scale of the transmitted part.
        t: Rgb,
    },
    /// A thin sheet of dielectric (a window pane): mirror reflection with the sheet's total
    /// reflectance, else straight through, unbent.
    ThinDielectric {
        /// Index of refraction of the sheet over its surroundings'.
        eta: f32,
        /// Scale of the reflected part.
        r: Rgb,
        /// Scale of the transmitted part.
        t: Rgb,
    },
    /// GGX rough conductor with complex Fresnel, reflectance scaled by `scale`.
    Conductor {
        /// The microfacet distribution.
        mf: Microfacet,
        /// Real part of the index of refraction, per channel.
        eta: Rgb,
        /// Absorption coefficient, per channel.
        k: Rgb,
        /// Scale of the reflectance.
        scale: Rgb,
    },
    /// Diffuse base under a GGX dielectric coat. `diffuse` is the effective diffuse albedo factor
    /// (already divided by the internal-reflection term when the layered model is used).
    Plastic {
        /// The coat's microfacet distribution.
        mf: Microfacet,
        /// Effective diffuse albedo factor.
        kd: Rgb,
        /// Scale of the coat's specular reflection.
        ks: Rgb,
        /// Index of refraction of the coat.
        eta: f32,
        /// Energy-coupled diffuse term (see [`MaterialKind::Plastic`](super::MaterialKind::Plastic)).
        layered: bool,
        /// 1 / (pi eta^2) for the layered model, 1 / pi otherwise.
        diffuse_norm: f32,
    },
}

/// A sample of a lobe in the local shading frame.
#[derive(Clone, Copy, Debug)]
pub struct LocalSample {
    /// The sampled incident direction (local frame).
    pub wi: Vec3,
    /// The BSDF value f(wo, wi), without the cosine.
    pub f: Rgb,
    /// Solid-angle density of `wi`, or the discrete probability of a delta lobe.
    pub pdf: f32,
    /// True when a delta component was sampled.
    pub delta: bool,
}

#[inline]
fn reflect_z(w: Vec3) -> Vec3 {
    Vec3::new(-w.x, -w.y, w.z)
}

impl Lobe {
    /// True for mirror and smooth dielectric lobes.
    pub fn is_delta(&self) -> bool {
        matches!(
            self,
            Lobe::Mirror { .. } | Lobe::Dielectric { .. } | Lobe::ThinDielectric { .. }
        )
    }

    /// True for the black lobe.
    pub fn is_black(&self) -> bool {
        matches!(self, Lobe::Black)
    }

    /// Rough upper estimate of the directional albedo (largest channel), for Russian roulette.
    pub fn albedo_estimate(&self) -> f32 {
        match *self {
            Lobe::Black => 0.0,
            Lobe::Lambert { r } | Lobe::Mirror { r } => max_component(r),
            Lobe::Phong { kd, ks, .. } => max_component(kd + ks),
            Lobe::Dielectric { r, t, .. }
            | Lobe::RoughDielectric { r, t, .. }
            | Lobe::ThinDielectric { r, t, .. } => max_component(r.max(t)),
            Lobe::Conductor { scale, .. } => max_component(scale),
            Lobe::Plastic { kd, ks, .. } => max_component(kd + ks * 0.1).min(1.0),
        }
    }

    /// Transmissive lobes see both sides of the surface; the others are reflection-only.
    pub fn transmits(&self) -> bool {
        matches!(
            self,
            Lobe::Dielectric { .. } | Lobe::RoughDielectric { .. } | Lobe::ThinDielectric { .. }
        )
    }

    /// The microfacet normal of a rough dielectric that takes wo to wi (local frame, the
    /// interior below), oriented up, and whether the pair refracts; None where no microfacet
    /// facing both directions does (Walter et al. 2007 eq. 13 for reflection, eq. 16 for
    /// refraction; back-facing microfacets discarded). The pair and its swap give the same
    /// normal bit for bit: refraction weighs the direction below by the interior index.
    #[inline]
    fn rough_dielectric_normal(wo: Vec3, wi: Vec3, eta: f32) -> Option<(Vec3, bool)> {
        if wo.z == 0.0 || wi.z == 0.0 {
            return None;
        }
        let refracts = (wo.z > 0.0) != (wi.z > 0.0);
        if refracts && eta == 1.0 {
            return None;
        }
        let h = if !refracts {
            wo + wi
        } else if wo.z > 0.0 {
            wo + wi * eta
        } else {
            wi + wo * eta
        };
        let h = h.normalize();
        let h = if h.z < 0.0 { -h } else { h };
        let faces = |w: Vec3| {
            let c = w.dot(h);
            c != 0.0 && (c > 0.0) == (w.z > 0.0)
        };
        if !h.is_finite() || h.z == 0.0 || !faces(wo) || !faces(wi) {
            return None;
        }
        Some((h, refracts))
    }

    /// The Fresnel reflectance at microfacet `h` for light arriving along `w`.
    #[inline]
    fn rough_dielectric_fresnel(w: Vec3, h: Vec3, eta: f32) -> f32 {
        let eta_rel = if w.z > 0.0 { eta } else { 1.0 / eta };
        fresnel::dielectric(w.dot(h).abs(), eta_rel)
    }

    /// f(wo, wi) of a rough dielectric (Walter et al. 2007 eqs. 20, 21), written in the pair's
    /// direction above (a) and below (b) so that f_rad(wi, wo) = f_imp(wo, wi) holds in f32 as
    /// it does exactly: (1 - F) D G |a.h| |b.h| / (|a.z| |b.z| (a.h + eta b.h)^2), times eta^2
    /// for radiance arriving from inside or importance from outside (Veach 1997 §5.2).
    fn rough_dielectric_eval(
        mf: &Microfacet,
        eta: f32,
        r: Rgb,
        t: Rgb,
        wo: Vec3,
        wi: Vec3,
        mode: Mode,
    ) -> Rgb {
        let Some((h, refracts)) = Self::rough_dielectric_normal(wo, wi, eta) else {
            return Rgb::ZERO;
        };
        let dg = mf.d(h) * mf.g2(wo, wi);
        if !refracts {
            // wo.h = wi.h but for rounding, to which F is sensitive near the critical angle:
            // their mean keeps f(wo, wi) = f(wi, wo) exact.
            let cos = 0.5 * (wo.dot(h).abs() + wi.dot(h).abs());
            let eta_rel = if wo.z > 0.0 { eta } else { 1.0 / eta };
            let f = fresnel::dielectric(cos, eta_rel);
            return r * (f * dg / (4.0 * wo.z * wi.z).abs());
        }
        let (a, b) = if wo.z > 0.0 { (wo, wi) } else { (wi, wo) };
        let (a_h, b_h) = (a.dot(h), b.dot(h));
        let f = Self::rough_dielectric_fresnel(a, h, eta);
        let denom = a_h + eta * b_h;
        let mut ft = (1.0 - f) * dg * (a_h * b_h / (a.z * b.z * denom * denom)).abs();
        if (wo.z > 0.0) == (mode == Mode::Importance) {
            ft *= eta * eta;
        }
        t * ft
    }

    /// The density of wi from `sample` of a rough dielectric: the density of wo's visible
    /// normal (seen from wo's side) times the Jacobian of reflection (Walter et al. 2007 eq. 14)
    /// or refraction (eq. 17), times the probability F or 1 - F of the choice.
    fn rough_dielectric_pdf(mf: &Microfacet, eta: f32, wo: Vec3, wi: Vec3) -> f32 {
        let Some((h, refracts)) = Self::rough_dielectric_normal(wo, wi, eta) else {
            return 0.0;
        };
        let f = Self::rough_dielectric_fresnel(wo, h, eta);
        // From inside, `sample` mirrors the surface: wo's z and the normal's tangent part flip.
        let p_h = if wo.z > 0.0 {
            mf.normal_pdf(wo, h)
        } else {
            mf.normal_pdf(Vec3::new(wo.x, wo.y, -wo.z), Vec3::new(-h.x, -h.y, h.z))
        };
        let wo_h = wo.dot(h).abs();
        if !refracts {
            return f * p_h / (4.0 * wo_h);
        }
        // |wi.h| / (wi.h + wo.h / eta_rel)^2 with eta_rel = wi's index over wo's.
        let (a, b) = if wo.z > 0.0 { (wo, wi) } else { (wi, wo) };
        let denom = a.dot(h) + eta * b.dot(h);
        let jacobian = wi.dot(h).abs() * if wo.z > 0.0 { eta * eta } else { 1.0 } / (denom * denom);
        (1.0 - f) * p_h * jacobian
    }

    /// The reflectance of a thin sheet: Fresnel's R at the first interface, and every
    /// reflection between its two faces, R + T^2 R / (1 - R^2) = 2 R / (1 + R) (Mitsuba's
    /// `thindielectric`).
    fn thin_reflectance(cos: f32, eta: f32) -> f32 {
        let r = fresnel::dielectric(cos, eta);
        2.0 * r / (1.0 + r)
    }

    fn plastic_spec_prob(ks: Rgb, kd: Rgb, f_o: f32) -> f32 {
        let s = luminance(ks) * f_o;
        let d = luminance(kd) * (1.0 - f_o);
        if s + d <= 0.0 { 0.0 } else { s / (s + d) }
    }

    /// f(wo, wi) without the cosine (0 for delta lobes); `mode` is the quantity transported.
    pub fn eval(&self, wo: Vec3, wi: Vec3, mode: Mode) -> Rgb {
        let _ = mode;
        match *self {
            Lobe::Black
            | Lobe::Mirror { .. }
            | Lobe::Dielectric { .. }
            | Lobe::ThinDielectric { .. } => Rgb::ZERO,
            Lobe::Lambert { r } => {
                if wo.z > 0.0 && wi.z > 0.0 {
                    r * INV_PI
                } else {
                    Rgb::ZERO
                }
            }
            Lobe::RoughDielectric { mf, eta, r, t } => {
                Self::rough_dielectric_eval(&mf, eta, r, t, wo, wi, mode)
            }
            Lobe::Phong { kd, ks, n, .. } => {
                if wo.z <= 0.0 || wi.z <= 0.0 {
                    return Rgb::ZERO;
                }
                let c = reflect_z(wo).dot(wi).max(0.0);
                kd * INV_PI + ks * ((n + 2.0) * INV_2PI * c.powf(n))
            }
            Lobe::Conductor { mf, eta, k, scale } => {
                if wo.z <= 0.0 || wi.z <= 0.0 {
                    return Rgb::ZERO;
                }
                let h = (wo + wi).normalize();
                let f = fresnel::conductor(wo.dot(h), eta, k);
                scale * f * (mf.d(h) * mf.g2(wo, wi) / (4.0 * wo.z * wi.z))
            }
            Lobe::Plastic {
                mf,
                kd,
                ks,
                eta,
                diffuse_norm,
                layered,
            } => {
                if wo.z <= 0.0 || wi.z <= 0.0 {
                    return Rgb::ZERO;
                }
                let h = (wo + wi).normalize();
                let spec = ks
                    * (fresnel::dielectric(wo.dot(h), eta) * mf.d(h) * mf.g2(wo, wi)
                        / (4.0 * wo.z * wi.z));
                let coupling = if layered {
                    (1.0 - fresnel::dielectric(wo.z, eta)) * (1.0 - fresnel::dielectric(wi.z, eta))
                } else {
                    1.0
                };
                spec + kd * (diffuse_norm * coupling)
            }
        }
    }

    /// `(eval(wo, wi, mode), pdf(wo, wi), pdf(wi, wo))`, bit for bit, sharing what the three
    /// have in common (Phong's cos^n).
    #[inline]
    pub fn eval_pdfs(&self, wo: Vec3, wi: Vec3, mode: Mode) -> (Rgb, f32, f32) {
        self.eval_pdfs_if(wo, wi, mode, true)
    }

    /// `(pdf(wo, wi), pdf(wi, wo))`, bit for bit, sharing what the two have in common (Phong's
    /// cos^n).
    #[inline]
    pub fn pdfs(&self, wo: Vec3, wi: Vec3) -> (f32, f32) {
        match *self {
            Lobe::Phong { .. } => {
                let (_, fwd, rev) = self.eval_pdfs_if(wo, wi, Mode::Radiance, true);
                (fwd, rev)
            }
            _ => (self.pdf(wo, wi), self.pdf(wi, wo)),
        }
    }

    /// `eval_pdfs`, with pdf(wi, wo) computed only when `rev` (else 0, unless it came free).
    #[inline]
    fn eval_pdfs_if(&self, wo: Vec3, wi: Vec3, mode: Mode, rev: bool) -> (Rgb, f32, f32) {
        match *self {
            Lobe::Phong { kd, ks, n, q } => {
                if wo.z <= 0.0 || wi.z <= 0.0 {
                    return (Rgb::ZERO, 0.0, 0.0);
                }
                // reflect_z(wo) . wi = reflect_z(wi) . wo, operation for operation.
                let c = reflect_z(wo).dot(wi);
                let cn = c.max(0.0).powf(n);
                let f = kd * INV_PI + ks * ((n + 2.0) * INV_2PI * cn);
                // power_cosine_pdf(c, n) with the power above.
                let spec = if c > 0.0 {
                    (n + 1.0) * INV_2PI * cn
                } else {
                    0.0
                };
                let pdf = |cos_i: f32| (1.0 - q) * cosine_hemisphere_pdf(cos_i) + q * spec;
                (f, pdf(wi.z), pdf(wo.z))
            }
            _ => (
                self.eval(wo, wi, mode),
                self.pdf(wo, wi),
                if rev { self.pdf(wi, wo) } else { 0.0 },
            ),
        }
    }

    /// Solid-angle density with which [`sample`](Self::sample) produces `wi` (0 for delta lobes).
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        match *self {
            Lobe::Black
            | Lobe::Mirror { .. }
            | Lobe::Dielectric { .. }
            | Lobe::ThinDielectric { .. } => 0.0,
            Lobe::Lambert { .. } => {
                if wo.z > 0.0 {
                    cosine_hemisphere_pdf(wi.z)
                } else {
                    0.0
                }
            }
            Lobe::Phong { n, q, .. } => {
                if wo.z <= 0.0 || wi.z <= 0.0 {
                    return 0.0;
                }
                let c = reflect_z(wo).dot(wi);
                (1.0 - q) * cosine_hemisphere_pdf(wi.z) + q * power_cosine_pdf(c, n)
            }
            Lobe::Conductor { mf, .. } => mf.reflection_pdf(wo, wi),
            Lobe::RoughDielectric { mf, eta, .. } => Self::rough_dielectric_pdf(&mf, eta, wo, wi),
            Lobe::Plastic {
                mf, kd, ks, eta, ..
            } => {
                if wo.z <= 0.0 || wi.z <= 0.0 {
                    return 0.0;
                }
                let q = Self::plastic_spec_prob(ks, kd, fresnel::dielectric(wo.z, eta));
                q * mf.reflection_pdf(wo, wi) + (1.0 - q) * cosine_hemisphere_pdf(wi.z)
            }
        }
    }

    /// Samples wi given wo; `u_lobe` picks a lobe, `u` the direction within it.
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: Vec2, mode: Mode) -> Option<LocalSample> {
        let continuous = |wi: Vec3| -> Option<LocalSample> {
            let (f, pdf, _) = self.eval_pdfs_if(wo, wi, mode, false);
            if !(pdf > 0.0) || !pdf.is_finite() {
                return None;
            }
            Some(LocalSample {
                wi,
                f,
                pdf,
                delta: false,
            })
        };
        match *self {
            Lobe::Black => None,
            Lobe::Lambert { .. } => {
                if wo.z <= 0.0 {
                    return None;
                }
                continuous(cosine_hemisphere(u))
            }
            Lobe::Phong { n, q, .. } => {
                if wo.z <= 0.0 {
                    return None;
                }
                let wi = if u_lobe < q {
                    let r = reflect_z(wo);
                    Frame::from_normal(r).to_world(power_cosine(u, n))
                } else {
                    cosine_hemisphere(u)
                };
                if wi.z <= 0.0 {
                    return None;
                }
                continuous(wi)
            }
            Lobe::Mirror { r } => {
                if wo.z <= 0.0 {
                    return None;
                }
                let wi = reflect_z(wo);
                Some(LocalSample {
                    wi,
                    f: r / wi.z,
                    pdf: 1.0,
                    delta: true,
                })
            }
            Lobe::Dielectric { eta, r, t } => {
                if wo.z == 0.0 {
                    return None;
                }
                let entering = wo.z > 0.0;
                let eta_rel = if entering { eta } else { 1.0 / eta };
                let cos_o = wo.z.abs();
                let f = fresnel::dielectric(cos_o, eta_rel);
                if u_lobe < f {
                    let wi = reflect_z(wo);
                    Some(LocalSample {
                        wi,
                        f: r * (f / cos_o),
                        pdf: f,
                        delta: true,
                    })
                } else {
                    let cos_t = fresnel::refracted_cos(cos_o, eta_rel)?;
                    let nz = if entering { 1.0 } else { -1.0 };
                    let wi = -wo / eta_rel + Vec3::new(0.0, 0.0, nz * (cos_o / eta_rel - cos_t));
                    let wi = wi.normalize();
                    let mut ft = t * ((1.0 - f) / wi.z.abs());
                    if mode == Mode::Radiance {
                        // Radiance is compressed into the denser medium: (eta_o / eta_i)^2 with
                        // eta_o on wo's side (Veach 1997 §5.2).
                        ft /= eta_rel * eta_rel;
                    }
                    Some(LocalSample {
                        wi,
                        f: ft,
                        pdf: 1.0 - f,
                        delta: true,
                    })
                }
            }
            Lobe::ThinDielectric { eta, r, t } => {
                if wo.z == 0.0 {
                    return None;
                }
                let cos_o = wo.z.abs();
                let f = Self::thin_reflectance(cos_o, eta);
                // Out on the other side along the same line: nothing to compress, either way.
                let (wi, w, p) = if u_lobe < f {
                    (reflect_z(wo), r, f)
                } else {
                    (-wo, t, 1.0 - f)
                };
                Some(LocalSample {
                    wi,
                    f: w * (p / cos_o),
                    pdf: p,
                    delta: true,
                })
            }
            Lobe::RoughDielectric { mf, eta, .. } => {
                if wo.z == 0.0 {
                    return None;
                }
                // Sampled from above: the surface mirrored when wo is inside.
                let (up, eta_up) = if wo.z > 0.0 {
                    (wo, eta)
                } else {
                    (Vec3::new(wo.x, wo.y, -wo.z), 1.0 / eta)
                };
                let h = mf.sample_normal(up, u);
                let cos_o = up.dot(h);
                // A normal rounded to face away from wo: no event the density counts.
                if cos_o <= 0.0 {
                    return None;
                }
                let f = fresnel::dielectric(cos_o, eta_up);
                let reflect = u_lobe < f;
                let wi_up = if reflect {
                    2.0 * cos_o * h - up
                } else {
                    let cos_t = fresnel::refracted_cos(cos_o, eta_up)?;
                    (-up / eta_up + h * (cos_o / eta_up - cos_t)).normalize()
                };
                // A microfacet can send the ray to the other side than its choice meant; the
                // density counts only the rays on the side chosen.
                if (wi_up.z > 0.0) != reflect {
                    return None;
                }
                let wi = if wo.z > 0.0 {
                    wi_up
                } else {
                    Vec3::new(wi_up.x, wi_up.y, -wi_up.z)
                };
                continuous(wi)
            }
            Lobe::Conductor { mf, .. } => {
                if wo.z <= 0.0 {
                    return None;
                }
                let h = mf.sample_normal(wo, u);
                let wi = 2.0 * wo.dot(h) * h - wo;
                if wi.z <= 0.0 {
                    return None;
                }
                continuous(wi)
            }
            Lobe::Plastic {
                mf, kd, ks, eta, ..
            } => {
                if wo.z <= 0.0 {
                    return None;
                }
                let q = Self::plastic_spec_prob(ks, kd, fresnel::dielectric(wo.z, eta));
                let wi = if u_lobe < q {
                    let h = mf.sample_normal(wo, u);
                    2.0 * wo.dot(h) * h - wo
                } else {
                    cosine_hemisphere(u)
                };
                if wi.z <= 0.0 {
                    return None;
                }
                continuous(wi)
            }
        }
    }

    /// Discrete probability of the delta event that maps wo to wi (for BDPT's reverse pdfs);
    /// zero for non-delta lobes.
    pub fn delta_pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        match *self {
            Lobe::Mirror { .. } => 1.0,
            Lobe::Dielectric { eta, .. } => {
                let eta_rel = if wo.z > 0.0 { eta } else { 1.0 / eta };
                let f = fresnel::dielectric(wo.z.abs(), eta_rel);
                if wo.z * wi.z > 0.0 { f } else { 1.0 - f }
            }
            Lobe::ThinDielectric { eta, .. } => {
                let f = Self::thin_reflectance(wo.z.abs(), eta);
                if wo.z * wi.z > 0.0 { f } else { 1.0 - f }
            }
            _ => 0.0,
        }
    }
}
