//! Anisotropic microfacet distributions: GGX (Trowbridge–Reitz) with visible-normal sampling
//! (Heitz 2018, "Sampling the GGX Distribution of Visible Normals", JCGT 7(4)), and Beckmann
//! (Walter, Marschner, Li and Torrance, "Microfacet Models for Refraction through Rough
//! Surfaces", EGSR 2007, eqs. 25-27) with visible-normal sampling (Jakob, "An Improved
//! Visible Normal Sampling Routine for the Beckmann Distribution", 2014, as pbrt-v3 has it).
//! All directions are in the local shading frame (+z = normal).

use crate::geometry::{PI, Vec2, Vec3};
use serde::{Deserialize, Serialize};

/// The shape of a microfacet normal distribution.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Distribution {
    /// GGX (Trowbridge–Reitz): long tails; pbrt's and omis's default.
    #[default]
    Ggx,
    /// Beckmann: a Gaussian of slopes; Mitsuba's default.
    Beckmann,
}

/// Smallest roughness we trace as a microfacet surface; below it the lobe is numerically a mirror
/// and f32 densities overflow.
pub const MIN_ALPHA: f32 = 1e-3;

/// An anisotropic microfacet distribution with roughness `ax` along the tangent, `ay` along
/// the bitangent.
#[derive(Clone, Copy, Debug)]
pub struct Microfacet {
    /// Roughness along the local x axis.
    pub ax: f32,
    /// Roughness along the local y axis.
    pub ay: f32,
    /// GGX or Beckmann.
    pub model: Distribution,
}

impl Microfacet {
    /// A distribution of roughness (`ax`, `ay`), each at least [`MIN_ALPHA`].
    pub fn new(model: Distribution, ax: f32, ay: f32) -> Self {
        Microfacet {
            ax: ax.max(MIN_ALPHA),
            ay: ay.max(MIN_ALPHA),
            model,
        }
    }

    /// A GGX distribution of roughness (`ax`, `ay`).
    pub fn ggx(ax: f32, ay: f32) -> Self {
        Self::new(Distribution::Ggx, ax, ay)
    }

    /// Normal distribution D(h), h in the upper hemisphere.
    #[inline]
    pub fn d(&self, h: Vec3) -> f32 {
        if h.z <= 0.0 {
            return 0.0;
        }
        let x = h.x / self.ax;
        let y = h.y / self.ay;
        match self.model {
            Distribution::Ggx => {
                let t = x * x + y * y + h.z * h.z;
                1.0 / (PI * self.ax * self.ay * t * t)
            }
            Distribution::Beckmann => {
                // exp(-tan^2 theta (cos^2 phi / ax^2 + sin^2 phi / ay^2)) / (pi ax ay cos^4).
                let z2 = h.z * h.z;
                let d = (-(x * x + y * y) / z2).exp() / (PI * self.ax * self.ay * z2 * z2);
                if d.is_finite() { d } else { 0.0 }
            }
        }
    }

    /// Smith Lambda for direction w.
    #[inline]
    pub fn lambda(&self, w: Vec3) -> f32 {
        let z2 = w.z * w.z;
        if z2 == 0.0 {
            return f32::INFINITY;
        }
        let a2 = (self.ax * w.x).powi(2) + (self.ay * w.y).powi(2);
        match self.model {
            Distribution::Ggx => 0.5 * ((1.0 + a2 / z2).sqrt() - 1.0),
            Distribution::Beckmann => {
                // (erf(a) - 1) / 2 + exp(-a^2) / (2 a sqrt(pi)), a = 1 / (alpha tan theta)
                // (Walter et al. 2007 eq. 27 before its approximation: visible-normal
                // sampling draws exactly this masking).
                if a2 == 0.0 {
                    return 0.0;
                }
                let a = (z2 / a2).sqrt();
                if a > 6.0 {
                    return 0.0;
                }
                let l = 0.5 * (erf(a) - 1.0) + (-a * a).exp() / (2.0 * a * PI.sqrt());
                l.max(0.0)
            }
        }
    }

    /// Smith masking G1(w) = 1 / (1 + Lambda(w)).
    #[inline]
    pub fn g1(&self, w: Vec3) -> f32 {
        1.0 / (1.0 + self.lambda(w))
    }

    /// Height-correlated masking-shadowing G2(wo, wi).
    #[inline]
    pub fn g2(&self, wo: Vec3, wi: Vec3) -> f32 {
        1.0 / (1.0 + self.lambda(wo) + self.lambda(wi))
    }

    /// Samples a visible microfacet normal for `wo` (wo.z > 0).
    #[inline]
    pub fn sample_normal(&self, wo: Vec3, u: Vec2) -> Vec3 {
        match self.model {
            Distribution::Ggx => self.sample_visible_normal(wo, u),
            Distribution::Beckmann => {
                // Stretch to unit roughness, sample the slopes, rotate and unstretch
                // (Heitz and d'Eon 2014, "Importance Sampling Microfacet-Based BSDFs using the
                // Distribution of Visible Normals", EGSR, §4).
                let v = Vec3::new(self.ax * wo.x, self.ay * wo.y, wo.z).normalize();
                let (sx, sy) = beckmann_slopes(v.z, u);
                let r = (v.x * v.x + v.y * v.y).sqrt();
                let (c, s) = if r > 0.0 {
                    (v.x / r, v.y / r)
                } else {
                    (1.0, 0.0)
                };
                let (sx, sy) = (c * sx - s * sy, s * sx + c * sy);
                Vec3::new(-sx * self.ax, -sy * self.ay, 1.0).normalize()
            }
        }
    }

    /// The density of `sample_normal`'s h given wo: G1(wo) max(0, wo.h) D(h) / wo.z.
    #[inline]
    pub fn normal_pdf(&self, wo: Vec3, h: Vec3) -> f32 {
        self.visible_normal_pdf(wo, h)
    }

    /// Samples a visible GGX microfacet normal for `wo` (wo.z > 0).
    pub fn sample_visible_normal(&self, wo: Vec3, u: Vec2) -> Vec3 {
        debug_assert!(self.model == Distribution::Ggx);
        let vh = Vec3::new(self.ax * wo.x, self.ay * wo.y, wo.z).normalize();
        let lensq = vh.x * vh.x + vh.y * vh.y;
        let t1 = if lensq > 0.0 {
            Vec3::new(-vh.y, vh.x, 0.0) / lensq.sqrt()
        } else {
            Vec3::X
        };
        let t2 = vh.cross(t1);
        let r = u.x.sqrt();
        let phi = 2.0 * PI * u.y;
        let p1 = r * phi.cos();
        let mut p2 = r * phi.sin();
        let s = 0.5 * (1.0 + vh.z);
        p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * p2;
        let nh = p1 * t1 + p2 * t2 + (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt() * vh;
        Vec3::new(self.ax * nh.x, self.ay * nh.y, nh.z.max(1e-6)).normalize()
    }

    /// Density of the visible normal h given wo: G1(wo) max(0, wo.h) D(h) / wo.z.
    #[inline]
    pub fn visible_normal_pdf(&self, wo: Vec3, h: Vec3) -> f32 {
        let woh = wo.dot(h);
        if wo.z <= 0.0 || woh <= 0.0 || h.z <= 0.0 {
            return 0.0;
        }
        self.g1(wo) * woh * self.d(h) / wo.z
    }

    /// Density of the reflected direction wi = reflect(wo, h) when h is drawn by
    /// `sample_normal`: p(h) / (4 |wo.h|). Zero for any configuration reflection sampling cannot produce, never
    /// negative (the guard Cailleau et al. §V-D ask for).
    #[inline]
    pub fn reflection_pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        let h = (wo + wi).normalize();
        let woh = wo.dot(h);
        if woh <= 0.0 || !h.is_finite() {
            return 0.0;
        }
        let p = self.normal_pdf(wo, h) / (4.0 * woh);
        if p.is_finite() { p.max(0.0) } else { 0.0 }
    }
}

/// Slopes of a visible Beckmann normal of unit roughness for a direction of cosine `cos_o`
/// (Jakob 2014: the marginal slope CDF inverted by a safeguarded Newton iteration from a fitted
/// first guess; the other slope is Gaussian).
fn beckmann_slopes(cos_o: f32, u: Vec2) -> (f32, f32) {
    let inv_sqrt_pi = 1.0 / PI.sqrt();
    if cos_o > 0.9999 {
        let r = (-(1.0 - u.x).max(f32::MIN_POSITIVE).ln()).sqrt();
        let phi = 2.0 * PI * u.y;
        return (r * phi.cos(), r * phi.sin());
    }
    let sin_o = (1.0 - cos_o * cos_o).max(0.0).sqrt();
    let tan_o = sin_o / cos_o;
    let cot_o = 1.0 / tan_o;
    let (mut lo, mut hi) = (-1.0f32, erf(cot_o));
    let x = u.x.max(1e-6);
    let theta = cos_o.clamp(-1.0, 1.0).acos();
    let fit = 1.0 + theta * (-0.876 + theta * (0.4265 - 0.0594 * theta));
    let mut b = hi - (1.0 + hi) * (1.0 - x).powf(fit);
    let norm = 1.0 / (1.0 + hi + inv_sqrt_pi * tan_o * (-cot_o * cot_o).exp());
    for _ in 0..10 {
        if !(b >= lo && b <= hi) {
            b = 0.5 * (lo + hi);
        }
        let inv = erf_inv(b);
        let value = norm * (1.0 + b + inv_sqrt_pi * tan_o * (-inv * inv).exp()) - x;
        let derivative = norm * (1.0 - inv * tan_o);
        if value.abs() < 1e-5 {
            break;
        }
        if value > 0.0 {
            hi = b;
        } else {
            lo = b;
        }
        b -= value / derivative;
    }
    (erf_inv(b), erf_inv(2.0 * u.y.max(1e-6) - 1.0))
}

/// The error function (Abramowitz and Stegun, Handbook of Mathematical Functions, 7.1.26;
/// absolute error below 1.5e-7). Hand-written: std has none, and no maintained crate offers an
/// f32 erf with its inverse beside it.
fn erf(x: f32) -> f32 {
    let (a1, a2, a3, a4, a5, p) = (
        0.254_829_6,
        -0.284_496_74,
        1.421_413_8,
        -1.453_152_1,
        1.061_405_4,
        0.327_591_1,
    );
    let s = x.signum();
    let x = x.abs();
    let t = 1.0 / (1.0 + p * x);
    let y = 1.0 - (((((a5 * t + a4) * t) + a3) * t + a2) * t + a1) * t * (-x * x).exp();
    s * y
}

/// The inverse error function (Giles, "Approximating the erfinv function", GPU Computing Gems
/// Jade Edition, 2011: the single-precision polynomials).
fn erf_inv(x: f32) -> f32 {
    let x = x.clamp(-0.99999, 0.99999);
    let mut w = -((1.0 - x) * (1.0 + x)).ln();
    let p = if w < 5.0 {
        w -= 2.5;
        let mut p = 2.810_226_4e-8;
        for c in [
            3.432_739_4e-7,
            -3.523_387_7e-6,
            -4.391_506_5e-6,
            0.000_218_580_87,
            -0.001_253_725,
            -0.004_177_681_6,
            0.246_640_73,
            1.501_409_4,
        ] {
            p = c + p * w;
        }
        p
    } else {
        w = w.sqrt() - 3.0;
        let mut p = -0.000_200_214_26;
        for c in [
            0.000_100_950_56,
            0.001_349_343_2,
            -0.003_673_428_4,
            0.005_739_507_7,
            -0.007_622_461,
            0.009_438_870_5,
            1.001_674,
            2.832_976_8,
        ] {
            p = c + p * w;
        }
        p
    };
    p * x
}
