//! Emitters: one-sided triangle area lights, sphere lights, point and spot lights, and the dome
//! that carries light from infinitely far away (an environment, a distant sun: `environment`),
//! with light selection proportional to power.
//!
//! [`SceneBuilder::build`](crate::scene::SceneBuilder::build) turns emissive primitives and
//! point lights into [`Light`]s and the selection [`Distribution1D`]; integrators sample them
//! through [`Scene`](crate::scene::Scene) (next-event estimation, BDPT light subpaths).

mod distribution;
pub mod environment;

pub use distribution::Distribution1D;
pub use environment::{Environment, Sky, Sun};

use crate::geometry::warp::uniform_sphere;
use crate::geometry::{Frame, PI, Rgb, Vec2, Vec3, luminance};

/// An emitter, in world space.
#[derive(Clone, Debug)]
pub enum Light {
    /// One-sided area light on a triangle; emits on the side of `n`.
    Triangle {
        /// First vertex.
        p0: Vec3,
        /// Edge from `p0` to the second vertex.
        e1: Vec3,
        /// Edge from `p0` to the third vertex.
        e2: Vec3,
        /// Unit normal of the emitting side.
        n: Vec3,
        /// Area of the triangle.
        area: f32,
        /// Emitted radiance (uniform over the surface, cosine-weighted in direction).
        radiance: Rgb,
    },
    /// Sphere emitting outward (or inward when `inward`, e.g. an enclosing furnace).
    Sphere {
        /// Centre in world space.
        center: Vec3,
        /// Radius.
        radius: f32,
        /// Emits into the sphere rather than out of it.
        inward: bool,
        /// Emitted radiance.
        radiance: Rgb,
    },
    /// Isotropic point light of radiant intensity `intensity`.
    Point {
        /// Position in world space.
        position: Vec3,
        /// Radiant intensity (power per unit solid angle).
        intensity: Rgb,
    },
    /// A point light emitting within a cone (Mitsuba 3's `spot`): full intensity within
    /// `beam` of the axis, falling off linearly in angle to zero at `cutoff`.
    Spot {
        /// Position in world space.
        position: Vec3,
        /// The frame whose `n` is the cone's axis.
        frame: Frame,
        /// Radiant intensity on the axis.
        intensity: Rgb,
        /// Half-angle of full intensity, radians.
        beam: f32,
        /// Half-angle of the cone, radians.
        cutoff: f32,
        /// cos(cutoff).
        cos_cutoff: f32,
    },
    /// The inside of a sphere around the scene, emitting toward its centre the radiance the sky
    /// sends from each direction (`environment`): the scene's light from infinitely far away.
    Dome {
        /// Centre of the sphere.
        center: Vec3,
        /// Radius (everything the scene holds, the camera included, lies inside).
        radius: f32,
        /// Radiance by direction.
        sky: std::sync::Arc<Sky>,
    },
}

/// A point sampled on a light, as seen from a reference point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Point on the light.
    pub p: Vec3,
    /// Oriented normal of the light surface at `p`, on its emitting side (zero for points).
    pub n: Vec3,
    /// Unit direction from the reference point toward `p`.
    pub wi: Vec3,
    /// Distance from the reference point to `p`.
    pub dist: f32,
    /// Radiance arriving from `p` along -wi (intensity / dist^2 for point lights).
    pub le: Rgb,
    /// Solid-angle density of `wi` under this light's sampling (1 for point lights).
    pub pdf: f32,
    /// True for a point light (a delta distribution: no MIS with BSDF sampling).
    pub delta: bool,
}

impl Light {
    /// A triangle area light emitting `radiance` on the side of `n`; None when degenerate.
    pub fn triangle(p0: Vec3, p1: Vec3, p2: Vec3, n: Vec3, radiance: Rgb) -> Option<Light> {
        let e1 = p1 - p0;
        let e2 = p2 - p0;
        let area = 0.5 * e1.cross(e2).length();
        if !(area > 0.0) || !area.is_finite() {
            return None;
        }
        Some(Light::Triangle {
            p0,
            e1,
            e2,
            n,
            area,
            radiance,
        })
    }

    /// True for lights that BSDF sampling cannot hit (point and spot lights).
    pub fn is_delta(&self) -> bool {
        matches!(self, Light::Point { .. } | Light::Spot { .. })
    }

    /// Emitted power (luminance), used for light selection. The dome's is the sky's flux onto
    /// a disc as large as the scene (pbrt-v3's power of infinite lights), not its own.
    pub fn power(&self) -> f32 {
        match self {
            Light::Triangle { area, radiance, .. } => PI * area * luminance(*radiance),
            Light::Sphere {
                radius, radiance, ..
            } => PI * 4.0 * PI * radius * radius * luminance(*radiance),
            Light::Point { intensity, .. } => 4.0 * PI * luminance(*intensity),
            Light::Spot {
                intensity,
                beam,
                cutoff,
                ..
            } => {
                // The cone's solid angle at the mean of the two half-angles (pbrt-v3's).
                let cos_mid = (0.5 * (beam + cutoff)).cos();
                2.0 * PI * (1.0 - cos_mid) * luminance(*intensity)
            }
            Light::Dome { radius, sky, .. } => sky.power(*radius / DOME_MARGIN),
        }
    }

    /// The intensity of a spot light toward `w` (unit, from the light): Mitsuba 3's falloff,
    /// linear in angle from the beam to the cutoff.
    fn spot_intensity(frame: &Frame, intensity: Rgb, beam: f32, cutoff: f32, w: Vec3) -> Rgb {
        let cos = w.dot(frame.n);
        if cos <= cutoff.cos() {
            return Rgb::ZERO;
        }
        let theta = cos.clamp(-1.0, 1.0).acos();
        if theta <= beam {
            intensity
        } else {
            intensity * ((cutoff - theta) / (cutoff - beam))
        }
    }

    /// Radiance leaving a point of the light with oriented normal `n` (the emitting side, as in
    /// [`LightSample::n`] and `SurfaceHit::ng`) toward direction `w`: one-sided emission. Zero for
    /// point lights, which emit no radiance (a delta): they light surfaces through `sample_li` /
    /// `sample_le` and are never seen directly.
    #[inline]
    pub fn le(&self, n: Vec3, w: Vec3) -> Rgb {
        match self {
            Light::Triangle { radiance, .. } | Light::Sphere { radiance, .. } => {
                if n.dot(w) > 0.0 {
                    *radiance
                } else {
                    Rgb::ZERO
                }
            }
            Light::Point { .. } | Light::Spot { .. } => Rgb::ZERO,
            // Toward the centre the dome sends what the sky sends from the opposite direction.
            Light::Dome { sky, .. } => {
                if n.dot(w) > 0.0 {
                    sky.radiance(-w)
                } else {
                    Rgb::ZERO
                }
            }
        }
    }

    /// Samples a direction toward the light from `p_ref` (Lambers, "Path Tracing": sphere lights by uniform cone
    /// sampling from outside, uniform area sampling from inside; triangles by uniform area).
    pub fn sample_li(&self, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        match *self {
            Light::Triangle {
                p0,
                e1,
                e2,
                n,
                area,
                ..
            } => {
                let (b1, b2) = crate::geometry::warp::uniform_triangle(u);
                let p = p0 + e1 * b1 + e2 * b2;
                let d = p - p_ref;
                let dist2 = d.length_squared();
                let dist = dist2.sqrt();
                if !(dist > 0.0) {
                    return None;
                }
                let wi = d / dist;
                let cos_l = n.dot(-wi).abs();
                if cos_l <= 0.0 {
                    return None;
                }
                let pdf = dist2 / (cos_l * area);
                let le = self.le(n, -wi);
                finite_sample(LightSample {
                    p,
                    n,
                    wi,
                    dist,
                    le,
                    pdf,
                    delta: false,
                })
            }
            Light::Sphere {
                center,
                radius,
                inward,
                ..
            } => {
                let to_c = center - p_ref;
                let dc2 = to_c.length_squared();
                let r2 = radius * radius;
                if dc2 > r2 * 1.000_01 {
                    let dc = dc2.sqrt();
                    let sin2_max = r2 / dc2;
                    let cos_max = (1.0 - sin2_max).max(0.0).sqrt();
                    let one_minus_cos_max = sin2_max / (1.0 + cos_max);
                    // Cone sampling written with 1 - cos to keep precision for distant lights.
                    let omc = u.x * one_minus_cos_max;
                    let cos_t = 1.0 - omc;
                    let sin_t = (omc * (2.0 - omc)).max(0.0).sqrt();
                    let phi = 2.0 * PI * u.y;
                    let axis = to_c / dc;
                    let wi = Frame::from_normal(axis)
                        .to_world(Vec3::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t))
                        .normalize();
                    // Near intersection of the sampled direction with the sphere.
                    let disc = (r2 - dc2 * sin_t * sin_t).max(0.0);
                    let dist = (dc * cos_t - disc.sqrt()).max(0.0);
                    let p = p_ref + wi * dist;
                    let n_out = (p - center).normalize();
                    let n = if inward { -n_out } else { n_out };
                    let pdf = 1.0 / (2.0 * PI * one_minus_cos_max);
                    let le = self.le(n, -wi);
                    finite_sample(LightSample {
                        p,
                        n,
                        wi,
                        dist,
                        le,
                        pdf,
                        delta: false,
                    })
                } else {
                    let n_out = uniform_sphere(u);
                    let p = center + n_out * radius;
                    let n = if inward { -n_out } else { n_out };
                    let d = p - p_ref;
                    let dist2 = d.length_squared();
                    let dist = dist2.sqrt();
                    if !(dist > 0.0) {
                        return None;
                    }
                    let wi = d / dist;
                    let cos_l = n.dot(wi).abs();
                    if cos_l <= 0.0 {
                        return None;
                    }
                    let pdf = dist2 / (cos_l * 4.0 * PI * r2);
                    let le = self.le(n, -wi);
                    finite_sample(LightSample {
                        p,
                        n,
                        wi,
                        dist,
                        le,
                        pdf,
                        delta: false,
                    })
                }
            }
            Light::Point {
                position,
                intensity,
            } => {
                let d = position - p_ref;
                let dist2 = d.length_squared();
                let dist = dist2.sqrt();
                if !(dist > 0.0) {
                    return None;
                }
                finite_sample(LightSample {
                    p: position,
                    n: Vec3::ZERO,
                    wi: d / dist,
                    dist,
                    le: intensity / dist2,
                    pdf: 1.0,
                    delta: true,
                })
            }
            Light::Spot {
                position,
                frame,
                intensity,
                beam,
                cutoff,
                ..
            } => {
                let d = position - p_ref;
                let dist2 = d.length_squared();
                let dist = dist2.sqrt();
                if !(dist > 0.0) {
                    return None;
                }
                let wi = d / dist;
                let i = Self::spot_intensity(&frame, intensity, beam, cutoff, -wi);
                if i == Rgb::ZERO {
                    return None;
                }
                finite_sample(LightSample {
                    p: position,
                    n: Vec3::ZERO,
                    wi,
                    dist,
                    le: i / dist2,
                    pdf: 1.0,
                    delta: true,
                })
            }
            Light::Dome {
                center,
                radius,
                ref sky,
            } => {
                let (wi, pdf) = sky.sample(u)?;
                let dist = dome_exit(center, radius, p_ref, wi)?;
                let p = p_ref + wi * dist;
                let n = (center - p).normalize();
                finite_sample(LightSample {
                    p,
                    n,
                    wi,
                    dist,
                    le: sky.radiance(wi),
                    pdf,
                    delta: false,
                })
            }
        }
    }

    /// Solid-angle density with which `sample_li(p_ref, ..)` produces direction `wi`, whether or
    /// not the light is the first thing the ray meets ("Demystifying multiple importance sampling": the light-sampling pdf of a
    /// direction sums over every light the ray reaches). Zero for point lights.
    pub fn pdf_li(&self, p_ref: Vec3, wi: Vec3) -> f32 {
        match *self {
            Light::Triangle {
                p0, e1, e2, area, ..
            } => {
                // Moeller–Trumbore.
                let pv = wi.cross(e2);
                let det = e1.dot(pv);
                if det.abs() < 1e-12 {
                    return 0.0;
                }
                let inv = 1.0 / det;
                let tv = p_ref - p0;
                let b1 = tv.dot(pv) * inv;
                if !(0.0..=1.0).contains(&b1) {
                    return 0.0;
                }
                let qv = tv.cross(e1);
                let b2 = wi.dot(qv) * inv;
                if b2 < 0.0 || b1 + b2 > 1.0 {
                    return 0.0;
                }
                let t = e2.dot(qv) * inv;
                if !(t > 0.0) {
                    return 0.0;
                }
                let ng = e1.cross(e2) / (2.0 * area);
                let cos_l = ng.dot(wi).abs();
                if cos_l <= 0.0 {
                    return 0.0;
                }
                let p = t * t / (cos_l * area);
                if p.is_finite() { p } else { 0.0 }
            }
            Light::Sphere { center, radius, .. } => {
                let to_c = center - p_ref;
                let dc2 = to_c.length_squared();
                let r2 = radius * radius;
                let geom = crate::accel::SphereGeom { center, radius };
                let Some((t0, t1)) = geom.roots(p_ref, wi) else {
                    return 0.0;
                };
                if dc2 > r2 * 1.000_01 {
                    if t1 <= 0.0 {
                        return 0.0;
                    }
                    let sin2_max = r2 / dc2;
                    let cos_max = (1.0 - sin2_max).max(0.0).sqrt();
                    1.0 / (2.0 * PI * (sin2_max / (1.0 + cos_max)))
                } else {
                    // From inside (or on) the sphere the ray leaves through one point; skip the
                    // root at the reference point itself when it lies on the surface.
                    let t = if t0 > 1e-4 * radius { t0 } else { t1 };
                    if !(t > 0.0) {
                        return 0.0;
                    }
                    let p = p_ref + wi * t;
                    let n = (p - center) / radius;
                    let cos_l = n.dot(wi).abs();
                    if cos_l <= 0.0 {
                        return 0.0;
                    }
                    let pdf = t * t / (cos_l * 4.0 * PI * r2);
                    if pdf.is_finite() { pdf } else { 0.0 }
                }
            }
            Light::Point { .. } | Light::Spot { .. } => 0.0,
            // Every ray from inside leaves through the dome once.
            Light::Dome { ref sky, .. } => sky.pdf(wi),
        }
    }
}

/// The dome's radius over the radius of everything it encloses.
pub const DOME_MARGIN: f32 = 1.5;

/// Distance from `p` (inside) along unit `d` to where it leaves the sphere (`center`, `radius`).
pub fn dome_exit(center: Vec3, radius: f32, p: Vec3, d: Vec3) -> Option<f32> {
    let (_, t1) = crate::accel::SphereGeom { center, radius }.roots(p, d)?;
    (t1 > 0.0 && t1.is_finite()).then_some(t1)
}

/// A ray leaving a light (BDPT light subpaths), with the densities that produced it.
#[derive(Clone, Copy, Debug)]
pub struct EmissionSample {
    /// Point on the light.
    pub p: Vec3,
    /// Oriented normal on the emitting side (zero for point lights).
    pub n: Vec3,
    /// Unit direction of the ray.
    pub dir: Vec3,
    /// Radiance (area lights) or intensity (point lights) along `dir`.
    pub le: Rgb,
    /// Area density of `p` (1 for point lights: a delta in position).
    pub pdf_pos: f32,
    /// Solid-angle density of `dir` given `p`.
    pub pdf_dir: f32,
}

impl Light {
    /// Samples an emitted ray: a point uniformly by area, a direction cosine-weighted about the
    /// emitting normal (area lights) or uniformly (point lights) (Veach 1997 §10.2; PBR 3rd ed.
    /// §14.2 / §16.3).
    pub fn sample_le(&self, u_pos: Vec2, u_dir: Vec2) -> Option<EmissionSample> {
        let (p, n, pdf_pos) = match *self {
            Light::Triangle {
                p0,
                e1,
                e2,
                n,
                area,
                ..
            } => {
                let (b1, b2) = crate::geometry::warp::uniform_triangle(u_pos);
                (p0 + e1 * b1 + e2 * b2, n, 1.0 / area)
            }
            Light::Sphere {
                center,
                radius,
                inward,
                ..
            } => {
                let n_out = uniform_sphere(u_pos);
                let n = if inward { -n_out } else { n_out };
                (
                    center + n_out * radius,
                    n,
                    1.0 / (4.0 * PI * radius * radius),
                )
            }
            Light::Point {
                position,
                intensity,
            } => {
                let dir = uniform_sphere(u_dir);
                return Some(EmissionSample {
                    p: position,
                    n: Vec3::ZERO,
                    dir,
                    le: intensity,
                    pdf_pos: 1.0,
                    pdf_dir: crate::geometry::warp::UNIFORM_SPHERE_PDF,
                });
            }
            Light::Spot {
                position,
                frame,
                intensity,
                beam,
                cutoff,
                cos_cutoff,
            } => {
                let dir = frame
                    .to_world(crate::geometry::warp::uniform_cone(u_dir, cos_cutoff))
                    .normalize();
                let le = Self::spot_intensity(&frame, intensity, beam, cutoff, dir);
                return (le != Rgb::ZERO).then_some(EmissionSample {
                    p: position,
                    n: Vec3::ZERO,
                    dir,
                    le,
                    pdf_pos: 1.0,
                    pdf_dir: crate::geometry::warp::uniform_cone_pdf(cos_cutoff),
                });
            }
            Light::Dome {
                center,
                radius,
                ref sky,
            } => {
                // A point uniformly on the dome and a direction by the sky's density, turned
                // inward when it points out: every point gets a direction (techniques that use
                // the point alone, like light tracing's connection to the camera, count on its
                // density), and a direction's density is the sky's for it and for its opposite.
                let n_out = uniform_sphere(u_pos);
                let p = center + n_out * radius;
                let n = -n_out;
                let (to_sky, _) = sky.sample(u_dir)?;
                let dir = if n.dot(to_sky) < 0.0 { -to_sky } else { to_sky };
                let pdf_dir = sky.pdf(-dir) + sky.pdf(dir);
                if !(pdf_dir > 0.0) || n.dot(dir) == 0.0 {
                    return None;
                }
                return Some(EmissionSample {
                    p,
                    n,
                    dir,
                    le: sky.radiance(-dir),
                    pdf_pos: 1.0 / (4.0 * PI * radius * radius),
                    pdf_dir,
                });
            }
        };
        let local = crate::geometry::warp::cosine_hemisphere(u_dir);
        let dir = Frame::from_normal(n).to_world(local);
        let pdf_dir = crate::geometry::warp::cosine_hemisphere_pdf(local.z);
        if !(pdf_dir > 0.0) || !(pdf_pos > 0.0) || !pdf_pos.is_finite() {
            return None;
        }
        Some(EmissionSample {
            p,
            n,
            dir,
            le: self.le(n, dir),
            pdf_pos,
            pdf_dir,
        })
    }

    /// Densities with which `sample_le` produces point `p` (oriented normal `n`) and direction
    /// `dir` from it: (area density, solid-angle density).
    pub fn pdf_le(&self, n: Vec3, dir: Vec3) -> (f32, f32) {
        match *self {
            Light::Triangle { area, .. } => (
                1.0 / area,
                crate::geometry::warp::cosine_hemisphere_pdf(n.dot(dir)),
            ),
            Light::Sphere { radius, .. } => (
                1.0 / (4.0 * PI * radius * radius),
                crate::geometry::warp::cosine_hemisphere_pdf(n.dot(dir)),
            ),
            Light::Point { .. } => (1.0, crate::geometry::warp::UNIFORM_SPHERE_PDF),
            Light::Spot {
                frame, cos_cutoff, ..
            } => (
                1.0,
                if frame.n.dot(dir) > cos_cutoff {
                    crate::geometry::warp::uniform_cone_pdf(cos_cutoff)
                } else {
                    0.0
                },
            ),
            Light::Dome {
                radius, ref sky, ..
            } => (
                1.0 / (4.0 * PI * radius * radius),
                if n.dot(dir) > 0.0 {
                    sky.pdf(-dir) + sky.pdf(dir)
                } else {
                    0.0
                },
            ),
        }
    }
}

fn finite_sample(s: LightSample) -> Option<LightSample> {
    if s.pdf > 0.0 && s.pdf.is_finite() && s.wi.is_finite() && s.le.is_finite() {
        Some(s)
    } else {
        None
    }
}
