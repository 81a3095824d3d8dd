//! Anisotropic GGX (Trowbridge–Reitz) microfacet distribution with visible-normal sampling
//! (Heitz 2018, "Sampling the GGX Distribution of Visible Normals", JCGT 7(4)).
//! All directions are in the local shading frame (+z = normal).

use crate::geometry::{PI, Vec2, Vec3};

/// Smallest roughness we trace as a microfacet surface; below it the lobe is numerically a mirror
/// and f32 densities overflow.
pub const MIN_ALPHA: f32 = 1e-3;

/// An anisotropic GGX distribution with roughness `ax` along the tangent, `ay` along the
/// bitangent.
#[derive(Clone, Copy, Debug)]
pub struct Ggx {
    /// Roughness along the local x axis.
    pub ax: f32,
    /// Roughness along the local y axis.
    pub ay: f32,
}

impl Ggx {
    /// A distribution of roughness (`ax`, `ay`), each at least [`MIN_ALPHA`].
    pub fn new(ax: f32, ay: f32) -> Self {
        Ggx {
            ax: ax.max(MIN_ALPHA),
            ay: ay.max(MIN_ALPHA),
        }
    }

    /// Normal distribution D(h), h in the upper hemisphere.
    #[inline]
    pub fn d(&self, h: Vec3) -> f32 {
        if h.z <= 0.0 {
            return 0.0;
        }
        let x = h.x / self.ax;
        let y = h.y / self.ay;
        let t = x * x + y * y + h.z * h.z;
        1.0 / (PI * self.ax * self.ay * t * t)
    }

    /// Smith Lambda for direction w.
    #[inline]
    pub fn lambda(&self, w: Vec3) -> f32 {
        let z2 = w.z * w.z;
        if z2 == 0.0 {
            return f32::INFINITY;
        }
        let a2 = (self.ax * w.x).powi(2) + (self.ay * w.y).powi(2);
        0.5 * ((1.0 + a2 / z2).sqrt() - 1.0)
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
    pub fn sample_visible_normal(&self, wo: Vec3, u: Vec2) -> Vec3 {
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

    /// Density of the reflected direction wi = reflect(wo, h) when h is VNDF-sampled:
    /// p(h) / (4 |wo.h|). Zero for any configuration reflection sampling cannot produce, never
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
        let p = self.visible_normal_pdf(wo, h) / (4.0 * woh);
        if p.is_finite() { p.max(0.0) } else { 0.0 }
    }
}
