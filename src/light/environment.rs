//! Light from infinitely far away: an environment (constant, or an equirectangular image in
//! Mitsuba 3's mapping) and a distant sun, seen through the [`Light::Dome`](super::Light): a
//! sphere around the scene whose radiance toward a direction depends on the direction alone.
//!
//! Radiance that depends on the direction alone is what an environment at infinity gives, so
//! the dome renders it exactly whatever its radius: a ray from a point of the scene in
//! direction w meets the dome once and receives the environment's radiance from w. As an area
//! light on a sphere the dome needs nothing new of the integrators: a camera subpath that leaves
//! the scene hits it, next-event estimation samples it (by the environment's luminance), light
//! subpaths leave it, and every technique's densities are the area light's.

use super::Distribution1D;
use crate::geometry::warp::{uniform_cone, uniform_cone_pdf};
use crate::geometry::{Frame, Mat4, PI, Rgb, Vec2, Vec3, luminance};

/// Radiance by direction, at infinity.
#[derive(Clone, Debug)]
pub struct Environment {
    image: EnvImage,
    /// World to the map's own frame (the inverse of its `to_world`, rotation only).
    to_local: glam::Mat3,
    /// The map's frame to world.
    to_world: glam::Mat3,
    /// A factor of every texel.
    scale: f32,
    /// Sampling by luminance times the solid angle of each texel's cell: rows, then the
    /// columns of each row.
    rows: Option<Distribution1D>,
    cols: Vec<Option<Distribution1D>>,
    /// Mean luminance over the sphere (by solid angle).
    mean: f32,
}

#[derive(Clone, Debug)]
enum EnvImage {
    Constant(Rgb),
    /// An equirectangular image, row 0 at the top (+y, the zenith).
    Image {
        width: usize,
        height: usize,
        texels: Vec<Rgb>,
    },
}

/// The smallest sampling weight of a texel's cell, as a fraction of the mean: every direction
/// keeps a positive density, so that light sampling covers what bilinear filtering spreads into
/// black texels.
const MIN_WEIGHT: f32 = 1e-3;

/// Why an environment map cannot be made.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EnvironmentError {
    /// Texels that do not fill width x height, or fewer than two rows.
    #[error("an environment map of {0}x{1} texels")]
    Size(usize, usize),
    /// A texel below zero or not finite.
    #[error("an environment map with negative or non-finite texels")]
    Texels,
    /// A transform that is not a rotation.
    #[error("an environment map's to_world must be a rotation")]
    NotARotation,
}

impl Environment {
    /// The same radiance from every direction.
    pub fn constant(radiance: Rgb) -> Environment {
        Environment {
            image: EnvImage::Constant(radiance),
            to_local: glam::Mat3::IDENTITY,
            to_world: glam::Mat3::IDENTITY,
            scale: 1.0,
            rows: None,
            cols: Vec::new(),
            mean: luminance(radiance),
        }
    }

    /// An equirectangular image of `width` x `height` texels (row-major from the top row),
    /// times `scale`, oriented by `to_world` (its rotation): Mitsuba 3's `envmap`.
    pub fn image(
        width: usize,
        height: usize,
        texels: Vec<Rgb>,
        scale: f32,
        to_world: &Mat4,
    ) -> Result<Environment, EnvironmentError> {
        if width == 0 || height < 2 || texels.len() != width * height {
            return Err(EnvironmentError::Size(width, height));
        }
        if texels
            .iter()
            .any(|t| !(t.is_finite() && t.min_element() >= 0.0))
        {
            return Err(EnvironmentError::Texels);
        }
        let m = glam::Mat3::from_mat4(*to_world);
        let to_world = glam::Mat3::from_cols(
            m.x_axis.normalize_or_zero(),
            m.y_axis.normalize_or_zero(),
            m.z_axis.normalize_or_zero(),
        );
        if !(to_world.determinant().abs() > 0.5) {
            return Err(EnvironmentError::NotARotation);
        }
        let mut env = Environment {
            image: EnvImage::Image {
                width,
                height,
                texels,
            },
            to_local: to_world.inverse(),
            to_world,
            scale,
            rows: None,
            cols: Vec::new(),
            mean: 0.0,
        };
        env.build_distribution(width, height);
        Ok(env)
    }

    fn build_distribution(&mut self, width: usize, height: usize) {
        // Cell (i, j) covers u in [i, i + 1) / width and v in [j, j + 1) / height; its weight is
        // the mean of the filtered radiance over it times its solid angle (sin theta dtheta
        // dphi). The bilinear filter spreads a bright texel over the neighbouring cells, so a
        // weight from the cell's centre alone would leave half a sun's rim sampled as sky:
        // horizontally the filter's kink sits on the centre (the trapezoid rule on its halves
        // is exact), vertically it falls anywhere (the trapezoid rule on quarters).
        const XS: [(f32, f32); 3] = [(0.0, 0.25), (0.5, 0.5), (1.0, 0.25)];
        const YS: [(f32, f32); 5] = [
            (0.0, 0.125),
            (0.25, 0.25),
            (0.5, 0.25),
            (0.75, 0.25),
            (1.0, 0.125),
        ];
        let mut weights = vec![0f32; width * height];
        let mut total = 0f64;
        let mut area = 0f64;
        for j in 0..height {
            let theta = (j as f32 + 0.5) / height as f32 * PI;
            let sin = theta.sin();
            for i in 0..width {
                let mut l = 0.0;
                for (dy, wy) in YS {
                    let v = (j as f32 + dy) / height as f32;
                    for (dx, wx) in XS {
                        let u = (i as f32 + dx) / width as f32;
                        l += wx * wy * luminance(self.lookup(u, v));
                    }
                }
                weights[j * width + i] = l * sin;
                total += (l * sin) as f64;
                area += sin as f64;
            }
        }
        let mean = if area > 0.0 {
            (total / area) as f32
        } else {
            0.0
        };
        self.mean = mean;
        let floor = MIN_WEIGHT * mean.max(f32::MIN_POSITIVE);
        let mut row_weights = Vec::with_capacity(height);
        let mut cols = Vec::with_capacity(height);
        for j in 0..height {
            let theta = (j as f32 + 0.5) / height as f32 * PI;
            let sin = theta.sin();
            let row: Vec<f32> = weights[j * width..(j + 1) * width]
                .iter()
                .map(|w| w.max(floor * sin))
                .collect();
            row_weights.push(row.iter().sum());
            cols.push(Distribution1D::new(&row));
        }
        self.rows = Distribution1D::new(&row_weights);
        self.cols = cols;
    }

    /// Texel `(i, j)` of the image (wrapped horizontally, clamped vertically).
    fn texel(&self, i: i64, j: i64) -> Rgb {
        match &self.image {
            EnvImage::Constant(c) => *c,
            EnvImage::Image {
                width,
                height,
                texels,
            } => {
                let i = i.rem_euclid(*width as i64) as usize;
                let j = j.clamp(0, *height as i64 - 1) as usize;
                texels[j * width + i]
            }
        }
    }

    /// The image at (u, v) as Mitsuba 3 filters it: bilinear, texel centres at (i + 1/2) / width
    /// horizontally (periodic) and row j at v = j / (height - 1) (rows on the poles).
    fn lookup(&self, u: f32, v: f32) -> Rgb {
        let EnvImage::Image { width, height, .. } = &self.image else {
            return self.texel(0, 0);
        };
        let x = u * *width as f32 - 0.5;
        let y = v.clamp(0.0, 1.0) * (*height as f32 - 1.0);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let a = self.texel(x0, y0) * (1.0 - fx) + self.texel(x0 + 1, y0) * fx;
        let b = self.texel(x0, y0 + 1) * (1.0 - fx) + self.texel(x0 + 1, y0 + 1) * fx;
        a * (1.0 - fy) + b * fy
    }

    /// Mitsuba 3's map coordinates of a direction in the map's frame: u = atan2(x, -z) / 2 pi,
    /// v = acos(y) / pi (+y the zenith, -z at the image's left edge).
    fn uv(d: Vec3) -> Vec2 {
        let u = d.x.atan2(-d.z) * crate::geometry::INV_2PI;
        Vec2::new(
            u - u.floor(),
            d.y.clamp(-1.0, 1.0).acos() * crate::geometry::INV_PI,
        )
    }

    /// The direction of map coordinates (u, v), in the map's frame.
    fn dir(uv: Vec2) -> Vec3 {
        let phi = uv.x * 2.0 * PI;
        let theta = uv.y * PI;
        let s = theta.sin();
        Vec3::new(s * phi.sin(), theta.cos(), -s * phi.cos())
    }

    /// Radiance arriving from world direction `w` (unit; pointing toward the environment).
    pub fn radiance(&self, w: Vec3) -> Rgb {
        match &self.image {
            EnvImage::Constant(c) => *c,
            EnvImage::Image { .. } => {
                let uv = Self::uv(self.to_local * w);
                self.lookup(uv.x, uv.y) * self.scale
            }
        }
    }

    /// Mean luminance of the radiance over the sphere of directions.
    pub fn mean_luminance(&self) -> f32 {
        self.mean * self.scale
    }

    /// A direction toward the environment, by luminance: (world direction, solid-angle density).
    pub fn sample(&self, u: Vec2) -> Option<(Vec3, f32)> {
        let (Some(rows), EnvImage::Image { width, height, .. }) = (&self.rows, &self.image) else {
            let w = crate::geometry::warp::uniform_sphere(u);
            return Some((w, crate::geometry::warp::UNIFORM_SPHERE_PDF));
        };
        let (j, pj, vy) = rows.sample_remapped(u.y);
        let cols = self.cols[j].as_ref()?;
        let (i, pi, vx) = cols.sample_remapped(u.x);
        let uv = Vec2::new(
            (i as f32 + vx) / *width as f32,
            (j as f32 + vy) / *height as f32,
        );
        let local = Self::dir(uv);
        let sin = (uv.y * PI).sin();
        if !(sin > 0.0) {
            return None;
        }
        let pdf = pj * pi * (*width * *height) as f32 / (2.0 * PI * PI * sin);
        let w = (self.to_world * local).normalize();
        (pdf > 0.0 && pdf.is_finite()).then_some((w, pdf))
    }

    /// The solid-angle density with which `sample` produces world direction `w`.
    pub fn pdf(&self, w: Vec3) -> f32 {
        let (Some(rows), EnvImage::Image { width, height, .. }) = (&self.rows, &self.image) else {
            return crate::geometry::warp::UNIFORM_SPHERE_PDF;
        };
        let uv = Self::uv(self.to_local * w);
        let sin = (uv.y * PI).sin();
        if !(sin > 0.0) {
            return 0.0;
        }
        let i = ((uv.x * *width as f32) as usize).min(width - 1);
        let j = ((uv.y * *height as f32) as usize).min(height - 1);
        let Some(cols) = &self.cols[j] else {
            return 0.0;
        };
        rows.pmf(j) * cols.pmf(i) * (*width * *height) as f32 / (2.0 * PI * PI * sin)
    }
}

/// A distant light of small angular size: radiance `radiance` from the directions within
/// `cos_max` of `to_sun` (unit, toward the light).
#[derive(Clone, Copy, Debug)]
pub struct Sun {
    /// Unit direction toward the sun.
    pub to_sun: Vec3,
    /// Cosine of the sun's angular radius.
    pub cos_max: f32,
    /// Radiance from within the disc.
    pub radiance: Rgb,
}

/// The angular radius (degrees) of the sun a directional light is rendered as: a shadow 1 unit
/// behind its occluder is blurred by 1.7e-3 units, and the cone is wide enough to sample in f32.
pub const SUN_ANGULAR_RADIUS_DEG: f32 = 0.1;

impl Sun {
    /// The sun that gives irradiance `irradiance` on a surface facing it, travelling along
    /// `direction` (Mitsuba's `directional`): a disc of `SUN_ANGULAR_RADIUS_DEG`.
    pub fn directional(direction: Vec3, irradiance: Rgb) -> Option<Sun> {
        let to_sun = -direction.normalize_or_zero();
        if to_sun == Vec3::ZERO {
            return None;
        }
        let cos_max = SUN_ANGULAR_RADIUS_DEG.to_radians().cos();
        // The irradiance of a disc of radiance L whose edge is at cos_max, on a surface facing
        // it: L pi (1 - cos_max^2). With the cosine as stored (f32 rounds 1 - cos_max by a few
        // per cent), so that what sampling integrates is exactly the irradiance asked for.
        let sin2 = (1.0 - cos_max) * (1.0 + cos_max);
        let radiance = irradiance / (PI * sin2);
        Some(Sun {
            to_sun,
            cos_max,
            radiance,
        })
    }

    /// Radiance arriving from `w`.
    pub fn radiance(&self, w: Vec3) -> Rgb {
        if w.dot(self.to_sun) >= self.cos_max {
            self.radiance
        } else {
            Rgb::ZERO
        }
    }

    /// A direction toward the sun, uniform over its disc: (direction, solid-angle density).
    pub fn sample(&self, u: Vec2) -> (Vec3, f32) {
        let w = Frame::from_normal(self.to_sun).to_world(uniform_cone(u, self.cos_max));
        (w.normalize(), uniform_cone_pdf(self.cos_max))
    }

    /// The density with which `sample` gives `w`.
    pub fn pdf(&self, w: Vec3) -> f32 {
        if w.dot(self.to_sun) >= self.cos_max {
            uniform_cone_pdf(self.cos_max)
        } else {
            0.0
        }
    }

    /// Irradiance on a surface facing it.
    pub fn irradiance(&self) -> f32 {
        let sin2 = (1.0 - self.cos_max) * (1.0 + self.cos_max);
        luminance(self.radiance) * PI * sin2
    }
}

/// Everything at infinity: an environment, a sun, or both, and how light sampling chooses
/// between them.
#[derive(Clone, Debug)]
pub struct Sky {
    /// The environment, if any.
    pub env: Option<std::sync::Arc<Environment>>,
    /// The sun, if any.
    pub sun: Option<Sun>,
    /// Probability that light sampling picks the sun (when both exist).
    pub sun_prob: f32,
}

impl Sky {
    /// Radiance arriving from `w`.
    pub fn radiance(&self, w: Vec3) -> Rgb {
        let mut l = Rgb::ZERO;
        if let Some(e) = &self.env {
            l += e.radiance(w);
        }
        if let Some(s) = &self.sun {
            l += s.radiance(w);
        }
        l
    }

    /// A direction toward the sky: (direction, solid-angle density of the mixture).
    pub fn sample(&self, u: Vec2) -> Option<(Vec3, f32)> {
        let w = match (&self.env, &self.sun) {
            (Some(e), Some(s)) => {
                if u.x < self.sun_prob {
                    s.sample(Vec2::new(u.x / self.sun_prob, u.y)).0
                } else {
                    let ux = (u.x - self.sun_prob) / (1.0 - self.sun_prob);
                    e.sample(Vec2::new(ux.min(1.0 - f32::EPSILON), u.y))?.0
                }
            }
            (Some(e), None) => e.sample(u)?.0,
            (None, Some(s)) => s.sample(u).0,
            (None, None) => return None,
        };
        let pdf = self.pdf(w);
        (pdf > 0.0).then_some((w, pdf))
    }

    /// The solid-angle density with which `sample` gives `w`.
    pub fn pdf(&self, w: Vec3) -> f32 {
        match (&self.env, &self.sun) {
            (Some(e), Some(s)) => self.sun_prob * s.pdf(w) + (1.0 - self.sun_prob) * e.pdf(w),
            (Some(e), None) => e.pdf(w),
            (None, Some(s)) => s.pdf(w),
            (None, None) => 0.0,
        }
    }

    /// The sky's flux onto a disc of radius `r` facing it: its power for light selection
    /// (pbrt-v3's for infinite lights, pi r^2 times the irradiance).
    pub fn power(&self, r: f32) -> f32 {
        let mut e = 0.0;
        if let Some(env) = &self.env {
            e += PI * env.mean_luminance();
        }
        if let Some(s) = &self.sun {
            e += s.irradiance();
        }
        PI * r * r * e
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Mitsuba's map orientation: u = 0 at -z, 0.25 at +x, 0.5 at +z; v = 0 at +y; and sampling
    /// densities that integrate to 1 and match the sampled directions.
    #[test]
    fn the_map_is_oriented_as_mitsubas_and_its_density_integrates_to_one() {
        for (d, u) in [
            (Vec3::NEG_Z, 0.0),
            (Vec3::X, 0.25),
            (Vec3::Z, 0.5),
            (Vec3::NEG_X, 0.75),
        ] {
            let uv = Environment::uv(d);
            assert!(
                (uv.x - u).abs() < 1e-6 || (uv.x - u - 1.0).abs() < 1e-6,
                "{d}: {uv}"
            );
            assert!((uv.y - 0.5).abs() < 1e-6);
            assert!(Environment::dir(uv).abs_diff_eq(d, 1e-5));
        }
        assert!(Environment::uv(Vec3::Y).y.abs() < 1e-6);
        // A bright texel among dim ones.
        let (w, h) = (16, 8);
        let mut texels = vec![Rgb::splat(0.1); w * h];
        texels[3 * w + 5] = Rgb::splat(50.0);
        let env = Environment::image(w, h, texels, 1.0, &Mat4::IDENTITY).expect("env");
        // The density integrates to 1 over the sphere (midpoint rule in theta, phi).
        let (nt, np) = (400, 800);
        let mut total = 0.0f64;
        for a in 0..nt {
            for b in 0..np {
                let theta = (a as f32 + 0.5) / nt as f32 * PI;
                let phi = (b as f32 + 0.5) / np as f32 * 2.0 * PI;
                let d = Vec3::new(
                    theta.sin() * phi.cos(),
                    theta.cos(),
                    theta.sin() * phi.sin(),
                );
                total += (env.pdf(d) * theta.sin()) as f64
                    * (PI / nt as f32) as f64
                    * (2.0 * PI / np as f32) as f64;
            }
        }
        assert!((total - 1.0).abs() < 2e-3, "{total}");
        // Sampled directions carry the density pdf() gives them.
        let mut rng = crate::sampler::Pcg32::new(3, 5);
        for _ in 0..1000 {
            let mut next = || (rng.next_u32() >> 8) as f32 / (1u32 << 24) as f32;
            let u = Vec2::new(next(), next());
            let (d, p) = env.sample(u).expect("a direction");
            assert!((p - env.pdf(d)).abs() <= 1e-3 * p, "{p} vs {}", env.pdf(d));
        }
    }
}
