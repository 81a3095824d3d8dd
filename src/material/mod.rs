//! Materials and the BSDF at a surface point: eval, sample and pdf in both directions.
//!
//! Scenes hold [`Material`]s (built by the importers); at each hit an integrator makes a
//! [`Bsdf`] from the material, the normals and the uv, and samples or evaluates it.

pub mod fresnel;
pub mod lobe;
pub mod microfacet;
pub mod texture;

use crate::geometry::{Frame, Rgb, Vec2, Vec3, luminance};
pub use lobe::{Lobe, LocalSample};
pub use microfacet::Distribution;
use microfacet::Microfacet;
pub use texture::{Bitmap, Texture};

/// Which quantity a path carries: radiance (camera subpaths) or importance (light subpaths).
/// Refraction and shading normals make the BSDF non-symmetric (Veach 1997 ch. 5).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// The path carries radiance: it started at the camera.
    Radiance,
    /// The path carries importance: it started at a light.
    Importance,
}

/// A material as the scene describes it; textures are resolved per hit by [`Bsdf::new`].
#[derive(Clone, Debug)]
pub enum MaterialKind {
    /// Diffuse reflection.
    Lambert {
        /// Reflectance.
        albedo: Texture,
    },
    /// Modified Phong: a diffuse term plus a normalised cos^n specular lobe (see [`Lobe::Phong`]).
    Phong {
        /// Diffuse reflectance.
        kd: Rgb,
        /// Specular reflectance.
        ks: Rgb,
        /// The specular exponent n.
        exponent: f32,
    },
    /// Ideal specular reflection.
    Mirror {
        /// Reflectance.
        reflectance: Rgb,
    },
    /// Smooth glass: specular reflection and refraction weighted by Fresnel.
    Dielectric {
        /// Interior / exterior index of refraction.
        ior: f32,
        /// Scale of the reflected part.
        reflectance: Rgb,
        /// Scale of the transmitted part.
        transmittance: Rgb,
    },
    /// Frosted glass: GGX microfacet reflection and refraction (Walter et al. 2007,
    /// "Microfacet Models for Refraction through Rough Surfaces", EGSR).
    RoughDielectric {
        /// Interior / exterior index of refraction.
        ior: f32,
        /// The microfacet distribution's shape.
        distribution: Distribution,
        /// GGX roughness along the tangent.
        alpha_u: f32,
        /// GGX roughness along the bitangent.
        alpha_v: f32,
        /// Scale of the reflected part.
        reflectance: Rgb,
        /// Scale of the transmitted part.
        transmittance: Rgb,
    },
    /// A thin sheet of glass (a window): reflection with the sheet's total reflectance,
    /// transmission straight through (Mitsuba's `thindielectric`, pbrt-v4's `thindielectric`).
    ThinDielectric {
        /// The sheet's index of refraction over its surroundings'.
        ior: f32,
        /// Scale of the reflected part.
        reflectance: Rgb,
        /// Scale of the transmitted part.
        transmittance: Rgb,
    },
    /// Metal: a GGX microfacet conductor (Walter et al. 2007, "Microfacet models for refraction
    /// through rough surfaces", EGSR) with the complex Fresnel term.
    RoughConductor {
        /// Real part of the index of refraction, per channel.
        eta: Rgb,
        /// Absorption coefficient (imaginary part of the index), per channel.
        k: Rgb,
        /// Roughness along the tangent.
        alpha_u: f32,
        /// Roughness along the bitangent.
        alpha_v: f32,
        /// The microfacet distribution's shape.
        distribution: Distribution,
        /// Scale of the reflectance.
        scale: Rgb,
    },
    /// A diffuse base under a smooth-to-rough dielectric coat (GGX or Beckmann).
    Plastic {
        /// Albedo of the diffuse base.
        diffuse: Texture,
        /// Scale of the coat's specular reflection.
        specular: Rgb,
        /// Index of refraction of the coat.
        ior: f32,
        /// Roughness of the coat.
        alpha: f32,
        /// The coat's microfacet distribution's shape.
        distribution: Distribution,
        /// Layered (energy-coupled) diffuse term; `false` gives the additive pbrt-v3 model.
        layered: bool,
        /// Mitsuba's "nonlinear" internal-scattering term (only with `layered`).
        nonlinear: bool,
    },
}

/// A named material: its scattering model and sidedness.
#[derive(Clone, Debug)]
pub struct Material {
    /// The name in the scene file (for messages).
    pub name: String,
    /// The scattering model.
    pub kind: MaterialKind,
    /// Reflection-only models reflect on both sides when true; on the back side they are black
    /// otherwise (Mitsuba's default). Transmissive models always see both sides.
    pub two_sided: bool,
    /// Internal diffuse Fresnel reflectance of the plastic coat, precomputed.
    fdr: f32,
}

impl Material {
    /// A material from its model; `two_sided` as for [`Material::two_sided`].
    pub fn new(name: impl Into<String>, kind: MaterialKind, two_sided: bool) -> Self {
        let fdr = match &kind {
            MaterialKind::Plastic { ior, .. } => fresnel::internal_diffuse_reflectance(*ior),
            _ => 0.0,
        };
        Material {
            name: name.into(),
            kind,
            two_sided,
            fdr,
        }
    }

    /// Whether the lobe depends on the surface coordinates (any texture but a constant: a
    /// bitmap, a checkerboard, a mapped texture): hits on other materials need no uv.
    pub fn uses_uv(&self) -> bool {
        match &self.kind {
            MaterialKind::Lambert { albedo: t } | MaterialKind::Plastic { diffuse: t, .. } => {
                !matches!(t, Texture::Constant(_))
            }
            _ => false,
        }
    }

    /// The lobe at surface coordinates `uv`.
    pub fn lobe(&self, uv: Vec2) -> Lobe {
        match &self.kind {
            MaterialKind::Lambert { albedo } => {
                let r = albedo.eval(uv);
                if r == Rgb::ZERO {
                    Lobe::Black
                } else {
                    Lobe::Lambert { r }
                }
            }
            MaterialKind::Phong { kd, ks, exponent } => {
                let sd = kd.x + kd.y + kd.z;
                let ss = ks.x + ks.y + ks.z;
                if sd + ss <= 0.0 {
                    return Lobe::Black;
                }
                Lobe::Phong {
                    kd: *kd,
                    ks: *ks,
                    n: *exponent,
                    q: ss / (sd + ss),
                }
            }
            MaterialKind::Mirror { reflectance } => Lobe::Mirror { r: *reflectance },
            MaterialKind::Dielectric {
                ior,
                reflectance,
                transmittance,
            } => Lobe::Dielectric {
                eta: *ior,
                r: *reflectance,
                t: *transmittance,
            },
            // Index 1 refracts every microfacet's ray straight on: no interface at all.
            MaterialKind::RoughDielectric {
                ior,
                reflectance,
                transmittance,
                ..
            } if *ior == 1.0 => Lobe::ThinDielectric {
                eta: 1.0,
                r: *reflectance,
                t: *transmittance,
            },
            MaterialKind::RoughDielectric {
                ior,
                alpha_u,
                alpha_v,
                distribution,
                reflectance,
                transmittance,
            } => Lobe::RoughDielectric {
                mf: Microfacet::new(*distribution, *alpha_u, *alpha_v),
                eta: *ior,
                r: *reflectance,
                t: *transmittance,
            },
            MaterialKind::ThinDielectric {
                ior,
                reflectance,
                transmittance,
            } => Lobe::ThinDielectric {
                eta: *ior,
                r: *reflectance,
                t: *transmittance,
            },
            MaterialKind::RoughConductor {
                eta,
                k,
                alpha_u,
                alpha_v,
                distribution,
                scale,
            } => Lobe::Conductor {
                mf: Microfacet::new(*distribution, *alpha_u, *alpha_v),
                eta: *eta,
                k: *k,
                scale: *scale,
            },
            MaterialKind::Plastic {
                diffuse,
                specular,
                ior,
                alpha,
                distribution,
                layered,
                nonlinear,
            } => {
                let mut kd = diffuse.eval(uv);
                let diffuse_norm = if *layered {
                    // Mitsuba 0.5 roughplastic: kd / (1 - kd Fdr) (nonlinear) or kd / (1 - Fdr),
                    // times (1 - F(wi)) (1 - F(wo)) / (pi eta^2).
                    kd = if *nonlinear {
                        kd / (Rgb::ONE - kd * self.fdr)
                    } else {
                        kd / (1.0 - self.fdr)
                    };
                    1.0 / (crate::geometry::PI * ior * ior)
                } else {
                    crate::geometry::INV_PI
                };
                Lobe::Plastic {
                    mf: Microfacet::new(*distribution, *alpha, *alpha),
                    kd,
                    ks: *specular,
                    eta: *ior,
                    layered: *layered,
                    diffuse_norm,
                }
            }
        }
    }

    /// Rough average albedo, for statistics and heuristics.
    pub fn approx_albedo(&self) -> f32 {
        match &self.kind {
            MaterialKind::Lambert { albedo } => luminance(albedo.average()),
            MaterialKind::Phong { kd, ks, .. } => luminance(*kd + *ks),
            MaterialKind::Mirror { reflectance } => luminance(*reflectance),
            MaterialKind::Dielectric { .. }
            | MaterialKind::RoughDielectric { .. }
            | MaterialKind::ThinDielectric { .. } => 1.0,
            MaterialKind::RoughConductor { scale, .. } => luminance(*scale),
            MaterialKind::Plastic { diffuse, .. } => luminance(diffuse.average()),
        }
    }
}

/// A density as the BSDF reports it: zero where the lobe's is negative, NaN or infinite.
#[inline]
fn clean_pdf(p: f32) -> f32 {
    if p.is_finite() && p > 0.0 { p } else { 0.0 }
}

/// A BSDF query's directions in the shading frame ([`Bsdf::eval_local`]), kept for its
/// densities ([`Bsdf::pdfs`]).
#[derive(Clone, Copy, Debug)]
pub struct LocalPair {
    lo: Vec3,
    li: Vec3,
    /// `localize(wi, wo)` would succeed (see `swapped_ok`).
    rev_ok: bool,
}

/// An outgoing direction made ready for many queries at one BSDF ([`Bsdf::outgoing`]): the world
/// direction with its shading-frame coordinates and its cosine to the geometric normal, computed
/// once instead of per query (a path vertex is evaluated toward every connection).
#[derive(Clone, Copy, Debug, Default)]
pub struct Outgoing {
    /// The direction (unit, world space).
    pub w: Vec3,
    local: Vec3,
    cos_g: f32,
}

/// A BSDF sample in world space.
#[derive(Clone, Copy, Debug)]
pub struct BsdfSample {
    /// The sampled incident direction (unit, world space).
    pub wi: Vec3,
    /// The BSDF value f(wo, wi), without the cosine (shading-normal correction included).
    pub f: Rgb,
    /// Solid-angle density of `wi`, or the discrete probability of a delta lobe.
    pub pdf: f32,
    /// True when a delta lobe was chosen (no MIS with light sampling).
    pub delta: bool,
    /// The density of sampling wo from wi, `pdf(wi, wo)` (0 for a delta sample, as `pdf`).
    pub pdf_rev: f32,
    /// 1 / the radiance scaling of a refraction in `f` (Veach's thesis, section 5.2): eta^2
    /// for a transmission into the side the lobe's index belongs to, 1 / eta^2 out of it, 1
    /// otherwise. A path tracer's Russian roulette multiplies it into the throughput it judges
    /// by, so that paths inside glass are not ended for the scaling alone (pbrt-v3's
    /// `etaScale`).
    pub eta_scale: f32,
}

/// The BSDF at one surface point: a resolved lobe in the shading frame, plus the geometric normal
/// that decides which side of the surface a direction is on.
#[derive(Clone, Copy, Debug)]
pub struct Bsdf {
    /// The resolved scattering model.
    pub lobe: Lobe,
    /// The shading frame (its `n` is the shading normal).
    pub frame: Frame,
    /// The geometric normal (unit).
    pub ng: Vec3,
    two_sided: bool,
}

impl Bsdf {
    /// `ng` is the geometric normal, `ns` the shading normal on the same side.
    pub fn new(material: &Material, ng: Vec3, ns: Vec3, uv: Vec2) -> Bsdf {
        Bsdf {
            lobe: material.lobe(uv),
            frame: Frame::from_normal(ns),
            ng,
            two_sided: material.two_sided,
        }
    }

    /// A BSDF that absorbs everything (for path endpoints that are not surfaces).
    pub fn new_black() -> Bsdf {
        Bsdf {
            lobe: Lobe::Black,
            frame: Frame::from_normal(Vec3::Z),
            ng: Vec3::Z,
            two_sided: false,
        }
    }

    /// True when the lobe is a delta distribution (mirror, smooth dielectric).
    pub fn is_delta(&self) -> bool {
        self.lobe.is_delta()
    }

    /// True when light passes through the surface (dielectrics), which then has two sides.
    pub fn transmits(&self) -> bool {
        self.lobe.transmits()
    }

    /// Continuation probability for Russian roulette: the lobe's albedo estimate, in [0, 1].
    pub fn continuation(&self) -> f32 {
        let a = self.lobe.albedo_estimate();
        if a.is_finite() {
            a.clamp(0.0, 1.0)
        } else {
            1.0
        }
    }

    /// True when the BSDF absorbs everything.
    pub fn is_black(&self) -> bool {
        self.lobe.is_black()
    }

    /// `wo` in this BSDF's frames, for [`Bsdf::eval_local`], [`Bsdf::eval_pdfs`] and
    /// [`Bsdf::sample_from`].
    #[inline]
    pub fn outgoing(&self, wo: Vec3) -> Outgoing {
        Outgoing {
            w: wo,
            local: self.frame.to_local(wo),
            cos_g: wo.dot(self.ng),
        }
    }

    /// Local directions for a query, with reflection-only lobes flipped to wo's side of a
    /// two-sided surface; `None` when the query has no value (back of a one-sided surface, or
    /// geometric and shading normals disagree about the side of a direction).
    #[inline]
    fn localize(&self, wo: &Outgoing, wi: Vec3) -> Option<(Vec3, Vec3)> {
        let go = wo.cos_g;
        let gi = wi.dot(self.ng);
        if go == 0.0 || gi == 0.0 {
            return None;
        }
        let mut lo = wo.local;
        let mut li = self.frame.to_local(wi);
        if self.lobe.transmits() {
            // Geometric and shading classification of reflection vs transmission must agree
            // (signs compared, not multiplied: products of tiny cosines underflow to zero).
            let up = |c: f32| c > 0.0;
            if lo.z == 0.0
                || li.z == 0.0
                || (up(go) == up(gi)) != (up(lo.z) == up(li.z))
                || up(lo.z) != up(go)
            {
                return None;
            }
            return Some((lo, li));
        }
        if go * gi <= 0.0 {
            return None;
        }
        if go < 0.0 {
            if !self.two_sided {
                return None;
            }
            lo.z = -lo.z;
            li.z = -li.z;
        }
        Some((lo, li))
    }

    /// Veach's adjoint correction for shading normals on importance-carrying paths
    /// (Veach 1997 eq. 5.19): |wo.ns| |wi.ng| / (|wo.ng| |wi.ns|).
    #[inline]
    fn shading_correction(&self, wo: &Outgoing, wi: Vec3, mode: Mode) -> f32 {
        if mode == Mode::Radiance {
            return 1.0;
        }
        // wo.n and wo.ng, as `outgoing` computed them.
        let num = wo.local.z.abs() * wi.dot(self.ng).abs();
        let den = wo.cos_g.abs() * wi.dot(self.frame.n).abs();
        if den == 0.0 { 0.0 } else { num / den }
    }

    /// f(wo, wi) without the cosine. Zero for delta lobes; never negative, NaN or infinite.
    pub fn eval(&self, wo: Vec3, wi: Vec3, mode: Mode) -> Rgb {
        self.eval_local(&self.outgoing(wo), wi, mode).0
    }

    /// `eval(wo, wi, mode)`, and the pair of directions in the shading frame from which
    /// [`Bsdf::pdfs`] gives `pdf(wo, wi)` and `pdf(wi, wo)` later without a second change of
    /// frame: for a BDPT connection, whose densities are needed only once its shadow ray finds
    /// it unoccluded (computing them for occluded ones too cost 0.8 % more instructions on
    /// Veach's scene, BENCHMARKS.md, "BDPT against pbrt-v3").
    #[inline]
    pub fn eval_local(&self, wo: &Outgoing, wi: Vec3, mode: Mode) -> (Rgb, Option<LocalPair>) {
        let Some((lo, li)) = self.localize(wo, wi) else {
            return (Rgb::ZERO, None);
        };
        // Cosines at the edge of f32 overflow the shading correction (|wo.ng| |wi.ns| below
        // ~1e-38 gives inf, and 0 * inf = NaN) or underflow a microfacet denominator (4 wo.z wi.z
        // = 0 with G2 = 0 gives 0 / 0). `sample` drops such values and `pdf` maps them to zero;
        // eval must agree.
        let f = self.lobe.eval(lo, li, mode) * self.shading_correction(wo, wi, mode);
        let pair = LocalPair {
            lo,
            li,
            rev_ok: self.swapped_ok(li, wi),
        };
        (if f.is_finite() { f } else { Rgb::ZERO }, Some(pair))
    }

    /// `(pdf(wo, wi), pdf(wi, wo))` of the directions `eval_local` returned (zeros without them).
    #[inline]
    pub fn pdfs(&self, pair: Option<&LocalPair>) -> (f32, f32) {
        let Some(p) = pair else {
            return (0.0, 0.0);
        };
        let (fwd, rev) = self.lobe.pdfs(p.lo, p.li);
        (clean_pdf(fwd), if p.rev_ok { clean_pdf(rev) } else { 0.0 })
    }

    /// `pdf(wo, wi)` alone of the directions `eval_local` returned (zero without them).
    #[inline]
    pub fn pdf_fwd(&self, pair: Option<&LocalPair>) -> f32 {
        pair.map_or(0.0, |p| clean_pdf(self.lobe.pdf(p.lo, p.li)))
    }

    /// `pdf(wi, wo)` alone of the directions `eval_local` returned (zero without them).
    #[inline]
    pub fn pdf_back(&self, pair: Option<&LocalPair>) -> f32 {
        match pair {
            Some(p) if p.rev_ok => clean_pdf(self.lobe.pdf(p.li, p.lo)),
            _ => 0.0,
        }
    }

    /// `(eval(wo, wi, mode), pdf(wo, wi), pdf(wi, wo))` bit for bit, in one change of frame
    /// (Phong's cos^n once): what a merge needs of a camera vertex.
    #[inline]
    pub fn eval_pdfs(&self, wo: &Outgoing, wi: Vec3, mode: Mode) -> (Rgb, f32, f32) {
        let Some((lo, li)) = self.localize(wo, wi) else {
            return (Rgb::ZERO, 0.0, 0.0);
        };
        let (f, fwd, rev) = self.lobe.eval_pdfs(lo, li, mode);
        let f = f * self.shading_correction(wo, wi, mode);
        (
            if f.is_finite() { f } else { Rgb::ZERO },
            clean_pdf(fwd),
            self.swapped_pdf(rev, li, wi),
        )
    }

    /// `pdf(wi, wo)` from `rev`, the lobe's density of the pair `localize(wo, wi)` returned,
    /// swapped.
    #[inline]
    fn swapped_pdf(&self, rev: f32, li: Vec3, wi: Vec3) -> f32 {
        if self.swapped_ok(li, wi) {
            clean_pdf(rev)
        } else {
            0.0
        }
    }

    /// Whether `localize(wi, wo)` succeeds given that `localize(wo, wi)` gave `(_, li)`: it is
    /// that pair swapped, but for transmitting lobes, which also ask wi to lie on the side of the
    /// shading normal its geometric side says.
    #[inline]
    fn swapped_ok(&self, li: Vec3, wi: Vec3) -> bool {
        !self.lobe.transmits() || {
            let gi = wi.dot(self.ng);
            li.z != 0.0 && gi != 0.0 && (li.z > 0.0) == (gi > 0.0)
        }
    }

    /// Solid-angle density of sampling wi from wo. Zero for delta lobes; never negative or NaN.
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        match self.localize(&self.outgoing(wo), wi) {
            Some((lo, li)) => clean_pdf(self.lobe.pdf(lo, li)),
            None => 0.0,
        }
    }

    /// Discrete probability of the delta event taking wo to wi (1 for mirrors, F or 1 - F for
    /// smooth dielectrics); zero for non-delta lobes.
    pub fn delta_pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        match self.localize(&self.outgoing(wo), wi) {
            Some((lo, li)) => self.lobe.delta_pdf(lo, li),
            None => 0.0,
        }
    }

    /// Samples an incident direction for outgoing `wo` (world space) from the numbers `u_lobe`
    /// (lobe choice) and `u`; None when the sample is absorbed or invalid.
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: Vec2, mode: Mode) -> Option<BsdfSample> {
        self.sample_from(&self.outgoing(wo), u_lobe, u, mode)
    }

    /// [`Bsdf::sample`] for an outgoing direction already in this BSDF's frames.
    pub fn sample_from(
        &self,
        out: &Outgoing,
        u_lobe: f32,
        u: Vec2,
        mode: Mode,
    ) -> Option<BsdfSample> {
        let go = out.cos_g;
        if go == 0.0 {
            return None;
        }
        let mut lo = out.local;
        let flip = !self.lobe.transmits() && go < 0.0;
        if flip {
            if !self.two_sided {
                return None;
            }
            lo.z = -lo.z;
        }
        let s = self.lobe.sample(lo, u_lobe, u, mode)?;
        let mut li = s.wi;
        if flip {
            li.z = -li.z;
        }
        let wi = self.frame.to_world(li);
        // Reject samples whose geometric side contradicts the local one (keeps pdf consistent).
        let (lo, li) = self.localize(out, wi)?;
        let f = s.f * self.shading_correction(out, wi, mode);
        if !(s.pdf > 0.0) || !s.pdf.is_finite() || !f.is_finite() {
            return None;
        }
        let pdf_rev = if s.delta {
            0.0
        } else {
            self.swapped_pdf(self.lobe.pdf(li, lo), li, wi)
        };
        let eta_scale = match self.lobe {
            Lobe::Dielectric { eta, .. } | Lobe::RoughDielectric { eta, .. }
                if lo.z * li.z < 0.0 && mode == Mode::Radiance =>
            {
                if lo.z > 0.0 {
                    eta * eta
                } else {
                    1.0 / (eta * eta)
                }
            }
            _ => 1.0,
        };
        Some(BsdfSample {
            wi,
            f,
            pdf: s.pdf,
            delta: s.delta,
            pdf_rev,
            eta_scale,
        })
    }
}
