//! Warps from the unit square to directions and points, each with its density.

use super::{INV_2PI, INV_4PI, INV_PI, PI, Vec2, Vec3};

/// Shirley–Chiu concentric map of the unit square to the unit disk (area preserving; Shirley and
/// Chiu, "A Low Distortion Map Between Disk and Square", JGT 1997). Without a branch on which
/// of |a|, |b| is larger (a coin flip per sample, which no branch predictor learns, on the
/// critical path of every diffuse bounce): the angle within the octant is taken once, and the
/// other octants' sine and cosine are the same two numbers swapped.
#[inline]
pub fn concentric_disk(u: Vec2) -> Vec2 {
    let a = 2.0 * u.x - 1.0;
    let b = 2.0 * u.y - 1.0;
    // |a| > |b|: r = a, phi = (pi / 4) (b / a); else r = b, phi = pi / 2 - (pi / 4) (a / b),
    // whose cosine and sine are the sine and cosine of (pi / 4) (a / b).
    let steep = a * a <= b * b;
    let (r, other) = if steep { (b, a) } else { (a, b) };
    let x = if r == 0.0 {
        0.0
    } else {
        (PI / 4.0) * (other / r)
    };
    let (sin, cos) = sincos_octant(x);
    let (cx, cy) = if steep { (sin, cos) } else { (cos, sin) };
    Vec2::new(r * cx, r * cy)
}

/// sin x and cos x for |x| <= pi / 4, within an ulp or two of f32: the minimax polynomials of
/// Moshier's Cephes library (sinf.c, "Cephes Mathematical Library", 1984-1995), without the
/// range reduction and its branches that `f32::sin` and `f32::cos` need for other arguments.
#[inline]
pub fn sincos_octant(x: f32) -> (f32, f32) {
    let z = x * x;
    let sin = ((-1.951_529_6e-4 * z + 8.332_161e-3) * z - 1.666_665_5e-1) * z * x + x;
    let cos = ((2.443_315_7e-5 * z - 1.388_731_6e-3) * z + 4.166_664_6e-2) * z * z - 0.5 * z + 1.0;
    (sin, cos)
}

/// Cosine-weighted hemisphere around +z (Malley's method); density cos(theta)/pi.
pub fn cosine_hemisphere(u: Vec2) -> Vec3 {
    let d = concentric_disk(u);
    let z = (1.0 - d.x * d.x - d.y * d.y).max(0.0).sqrt();
    Vec3::new(d.x, d.y, z)
}

/// Density of [`cosine_hemisphere`] for a direction of cosine `cos_theta` (0 below the horizon).
#[inline]
pub fn cosine_hemisphere_pdf(cos_theta: f32) -> f32 {
    if cos_theta > 0.0 {
        cos_theta * INV_PI
    } else {
        0.0
    }
}

/// Uniform direction on the unit sphere; density 1/(4 pi).
pub fn uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Density of [`uniform_sphere`]: 1 / (4 pi).
pub const UNIFORM_SPHERE_PDF: f32 = INV_4PI;

/// Uniform direction in the cone of half-angle acos(cos_max) around +z (Lambers, "Path Tracing", sphere lights):
/// cos(theta) = (1 - u0) + u0 cos_max, density 1 / (2 pi (1 - cos_max)).
pub fn uniform_cone(u: Vec2, cos_max: f32) -> Vec3 {
    let cos_t = (1.0 - u.x) + u.x * cos_max;
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    Vec3::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t)
}

/// Density of [`uniform_cone`]: 1 / (2 pi (1 - cos_max)).
#[inline]
pub fn uniform_cone_pdf(cos_max: f32) -> f32 {
    INV_2PI / (1.0 - cos_max)
}

/// Uniform barycentrics (b0, b1) on a triangle (Heitz 2019 low-distortion square-to-triangle map).
pub fn uniform_triangle(u: Vec2) -> (f32, f32) {
    let (b0, b1);
    if u.x < u.y {
        b0 = u.x / 2.0;
        b1 = u.y - b0;
    } else {
        b1 = u.y / 2.0;
        b0 = u.x - b1;
    }
    (b0, b1)
}

/// Direction around +z with density (s + 1)/(2 pi) cos^s (theta): the modified-Phong lobe
/// (Lambers, "Path Tracing", "Material Importance Sampling for Phong": cos theta = (1 - u0)^(1/(s+1))).
pub fn power_cosine(u: Vec2, s: f32) -> Vec3 {
    let cos_t = (1.0 - u.x).powf(1.0 / (s + 1.0));
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    Vec3::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t)
}

/// Density of [`power_cosine`]: (s + 1) / (2 pi) cos^s(theta) (0 below the horizon).
#[inline]
pub fn power_cosine_pdf(cos_t: f32, s: f32) -> f32 {
    if cos_t > 0.0 {
        (s + 1.0) * INV_2PI * cos_t.powf(s)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warps_land_where_they_should() {
        let mut u = 0.1f32;
        for _ in 0..1000 {
            u = (u * 7.31 + 0.377).fract();
            let v = ((u * 13.7) + 0.19).fract();
            let q = Vec2::new(u, v);
            let d = cosine_hemisphere(q);
            assert!((d.length() - 1.0).abs() < 1e-4 && d.z >= 0.0);
            assert!((uniform_sphere(q).length() - 1.0).abs() < 1e-4);
            let c = uniform_cone(q, 0.9);
            assert!(c.z >= 0.9 - 1e-5);
            let (b0, b1) = uniform_triangle(q);
            assert!(b0 >= 0.0 && b1 >= 0.0 && b0 + b1 <= 1.0 + 1e-6);
            let p = power_cosine(q, 20.0);
            assert!((p.length() - 1.0).abs() < 1e-4 && p.z >= 0.0);
        }
    }

    /// The octant's sine and cosine are within 2 ulps (of 1) of f64's over the whole octant.
    #[test]
    fn octant_sine_and_cosine_match_f64() {
        let n = 200_000;
        let mut worst = 0.0f64;
        for i in 0..=n {
            let x = (i as f64 / n as f64 * 2.0 - 1.0) * std::f64::consts::FRAC_PI_4;
            let (s, c) = sincos_octant(x as f32);
            let x = x as f32 as f64;
            worst = worst
                .max((s as f64 - x.sin()).abs())
                .max((c as f64 - x.cos()).abs());
        }
        assert!(worst < 2.0 * f32::EPSILON as f64, "worst error {worst:e}");
    }

    /// The branch-free concentric map is Shirley and Chiu's, computed in f64 with both of its
    /// branches and the library's sine and cosine, to within 4e-7 on a grid that includes the
    /// diagonals, the axes and the centre.
    #[test]
    fn concentric_map_matches_the_two_branch_form() {
        use std::f64::consts::{FRAC_PI_2, FRAC_PI_4};
        let n = 400;
        for i in 0..=n {
            for j in 0..=n {
                let u = Vec2::new(i as f32 / n as f32, j as f32 / n as f32)
                    .min(Vec2::splat(0.999_999_94));
                let (a, b) = (2.0 * u.x as f64 - 1.0, 2.0 * u.y as f64 - 1.0);
                let (r, phi) = if a == 0.0 && b == 0.0 {
                    (0.0, 0.0)
                } else if a * a > b * b {
                    (a, FRAC_PI_4 * (b / a))
                } else {
                    (b, FRAC_PI_2 - FRAC_PI_4 * (a / b))
                };
                let d = concentric_disk(u);
                let (ex, ey) = (r * phi.cos(), r * phi.sin());
                let err = (d.x as f64 - ex).abs().max((d.y as f64 - ey).abs());
                assert!(err < 4e-7, "u {u}: {d} against ({ex}, {ey})");
            }
        }
    }
}
