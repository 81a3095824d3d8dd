//! Math for the renderer: rays, orthonormal frames, transforms and sampling warps.
//!
//! Geometry and radiance are f32 (glam); sums that accumulate live elsewhere in f64.
//!
//! The bottom of the dependency graph: every other module uses these types, and this one
//! uses none of the crate's.

pub mod colour;
pub mod warp;

pub use glam::{Mat4, Vec2, Vec3, Vec3A};

/// Linear RGB radiance / reflectance triple.
pub type Rgb = Vec3;

/// pi.
pub const PI: f32 = std::f32::consts::PI;
/// 1 / pi.
pub const INV_PI: f32 = 1.0 / PI;
/// 1 / (2 pi).
pub const INV_2PI: f32 = 0.5 / PI;
/// 1 / (4 pi).
pub const INV_4PI: f32 = 0.25 / PI;

/// A ray with a parametric interval `[tmin, tmax]`.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    /// Origin.
    pub o: Vec3,
    /// Direction (not necessarily unit; `t` is in units of its length).
    pub d: Vec3,
    /// Start of the interval.
    pub tmin: f32,
    /// End of the interval.
    pub tmax: f32,
}

impl Ray {
    /// An unbounded ray from `o` along `d`.
    pub fn new(o: Vec3, d: Vec3) -> Self {
        Ray {
            o,
            d,
            tmin: 0.0,
            tmax: f32::INFINITY,
        }
    }

    /// A ray from `o` along `d` that ends at `tmax`.
    pub fn segment(o: Vec3, d: Vec3, tmax: f32) -> Self {
        Ray {
            o,
            d,
            tmin: 0.0,
            tmax,
        }
    }

    /// The point at parameter `t`.
    pub fn at(&self, t: f32) -> Vec3 {
        self.o + self.d * t
    }

    /// The shadow ray of the open segment from `from` to `to` (world points): its origin lifted
    /// off the surface of normal `n_from`, its end pulled back from `to`'s surface (normal
    /// `n_to`, zero for a point with no surface) and shortened by 1e-4 of its length. `None`
    /// when the two points coincide.
    #[inline]
    pub fn between(from: Vec3, n_from: Vec3, to: Vec3, n_to: Vec3) -> Option<Self> {
        let d = to - from;
        let o = offset_origin(from, n_from, d);
        let target = if n_to == Vec3::ZERO {
            to
        } else {
            offset_origin(to, n_to, -d)
        };
        let seg = target - o;
        let len = seg.length();
        if !(len > 0.0) {
            return None;
        }
        Some(Ray::segment(o, seg / len, len * (1.0 - 1e-4)))
    }
}

/// Orthonormal frame; `n` is the local +z axis.
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    /// First tangent (local +x).
    pub s: Vec3,
    /// Second tangent (local +y).
    pub t: Vec3,
    /// The normal (local +z).
    pub n: Vec3,
}

impl Frame {
    /// Branchless ONB from a unit normal (Duff et al. 2017, "Building an Orthonormal Basis, Revisited").
    pub fn from_normal(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let s = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let t = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Frame { s, t, n }
    }

    /// World vector `v` in this frame's coordinates.
    #[inline]
    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }

    /// Local vector `v` back in world coordinates.
    #[inline]
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }
}

/// Moves a ray origin off a surface along its geometric normal, in the direction of `dir`, by a few
/// floating-point ulps (Wächter & Binder, "A Fast and Robust Method for Avoiding Self-Intersection",
/// Ray Tracing Gems ch. 6): robust at any scene scale.
#[inline]
pub fn offset_origin(p: Vec3, ng: Vec3, dir: Vec3) -> Vec3 {
    let n = if ng.dot(dir) < 0.0 { -ng } else { ng };
    #[cfg(target_arch = "x86_64")]
    {
        offset_sse2(p, n)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        offset_lanes(p, n)
    }
}

const OFFSET_ORIGIN: f32 = 1.0 / 32.0;
const OFFSET_FLOAT_SCALE: f32 = 1.0 / 65536.0;
const OFFSET_INT_SCALE: f32 = 256.0;

/// [`offset_origin`]'s move along `n` (already facing the ray), one coordinate at a time.
#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
#[inline]
fn offset_lanes(p: Vec3, n: Vec3) -> Vec3 {
    let pa = p.to_array();
    let na = n.to_array();
    let mut out = [0.0f32; 3];
    for k in 0..3 {
        let of_i = (OFFSET_INT_SCALE * na[k]) as i32;
        let bits = pa[k].to_bits() as i32;
        let moved = bits.wrapping_add(if pa[k] < 0.0 { -of_i } else { of_i });
        out[k] = if pa[k].abs() < OFFSET_ORIGIN {
            pa[k] + OFFSET_FLOAT_SCALE * na[k]
        } else {
            f32::from_bits(moved as u32)
        };
    }
    Vec3::from_array(out)
}

/// [`offset_lanes`] on the three coordinates at once (SSE2, every x86-64): the same operations,
/// branch-free. They agree bit for bit for every finite normal of length <= 1 (the conversion
/// of 256 n to an integer differs only out of range: SSE2 gives i32::MIN, `as` saturates).
#[cfg(target_arch = "x86_64")]
#[inline]
fn offset_sse2(p: Vec3, n: Vec3) -> Vec3 {
    use std::arch::x86_64::*;
    // SAFETY: SSE2 is part of x86-64; the loads and the store are of local arrays of four f32.
    unsafe {
        let pv = _mm_loadu_ps([p.x, p.y, p.z, 0.0].as_ptr());
        let nv = _mm_loadu_ps([n.x, n.y, n.z, 0.0].as_ptr());
        let of_i = _mm_cvttps_epi32(_mm_mul_ps(_mm_set1_ps(OFFSET_INT_SCALE), nv));
        // -of_i where p < 0: (of_i ^ m) - m with m all ones.
        let neg = _mm_castps_si128(_mm_cmplt_ps(pv, _mm_setzero_ps()));
        let step = _mm_sub_epi32(_mm_xor_si128(of_i, neg), neg);
        let p_i = _mm_castsi128_ps(_mm_add_epi32(_mm_castps_si128(pv), step));
        let abs = _mm_andnot_ps(_mm_set1_ps(-0.0), pv);
        let near = _mm_cmplt_ps(abs, _mm_set1_ps(OFFSET_ORIGIN));
        let p_f = _mm_add_ps(pv, _mm_mul_ps(_mm_set1_ps(OFFSET_FLOAT_SCALE), nv));
        let out = _mm_or_ps(_mm_and_ps(near, p_f), _mm_andnot_ps(near, p_i));
        let mut o = [0.0f32; 4];
        _mm_storeu_ps(o.as_mut_ptr(), out);
        Vec3::new(o[0], o[1], o[2])
    }
}

/// Mirror `v` about `n` (both unit, `v` pointing away from the surface).
#[inline]
pub fn reflect(v: Vec3, n: Vec3) -> Vec3 {
    2.0 * v.dot(n) * n - v
}

/// Rec. 709 luminance.
#[inline]
pub fn luminance(c: Rgb) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// The largest of the three channels.
#[inline]
pub fn max_component(c: Rgb) -> f32 {
    c.x.max(c.y).max(c.z)
}

/// True when every channel is exactly zero.
#[inline]
pub fn is_black(c: Rgb) -> bool {
    c.x == 0.0 && c.y == 0.0 && c.z == 0.0
}

/// Affine transform with its inverse, applied at load time (scenes are flattened to world space).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transform {
    /// Object to world.
    pub m: Mat4,
    /// World to object.
    pub inv: Mat4,
}

impl Default for Transform {
    fn default() -> Self {
        Transform::IDENTITY
    }
}

impl Transform {
    /// The identity.
    pub const IDENTITY: Transform = Transform {
        m: Mat4::IDENTITY,
        inv: Mat4::IDENTITY,
    };

    /// `None` when the matrix is singular or not finite.
    pub fn new(m: Mat4) -> Option<Self> {
        let det = m.determinant();
        if !det.is_finite() || det.abs() < 1e-20 || !m.is_finite() {
            return None;
        }
        Some(Transform {
            m,
            inv: m.inverse(),
        })
    }

    /// This transform followed by `outer`.
    pub fn then(&self, outer: &Transform) -> Transform {
        Transform {
            m: outer.m * self.m,
            inv: self.inv * outer.inv,
        }
    }

    /// Transforms a point.
    pub fn point(&self, p: Vec3) -> Vec3 {
        self.m.transform_point3(p)
    }

    /// Transforms a direction (no translation).
    pub fn vector(&self, v: Vec3) -> Vec3 {
        self.m.transform_vector3(v)
    }

    /// Normals transform with the inverse transpose.
    pub fn normal(&self, n: Vec3) -> Vec3 {
        self.inv.transpose().transform_vector3(n)
    }

    /// True when the transform flips handedness (negative determinant).
    pub fn swaps_handedness(&self) -> bool {
        self.m.determinant() < 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_is_orthonormal() {
        for n in [
            Vec3::Z,
            -Vec3::Z,
            Vec3::X,
            Vec3::new(0.3, -0.5, 0.81).normalize(),
            Vec3::new(0.0, 0.0, -0.99999).normalize(),
        ] {
            let f = Frame::from_normal(n);
            assert!((f.s.length() - 1.0).abs() < 1e-5);
            assert!((f.t.length() - 1.0).abs() < 1e-5);
            assert!(f.s.dot(f.t).abs() < 1e-5);
            assert!(f.s.dot(n).abs() < 1e-5);
            assert!((f.s.cross(f.t) - n).length() < 1e-4);
            let v = Vec3::new(0.2, 0.7, -0.4);
            assert!((f.to_world(f.to_local(v)) - v).length() < 1e-5);
        }
    }

    #[test]
    fn offset_moves_to_the_right_side() {
        for p in [Vec3::ZERO, Vec3::splat(1000.0), Vec3::new(-3.0, 0.01, 5.0)] {
            let n = Vec3::Y;
            assert!((offset_origin(p, n, Vec3::Y) - p).dot(n) > 0.0);
            assert!((offset_origin(p, n, -Vec3::Y) - p).dot(n) < 0.0);
        }
    }

    /// The SSE2 offset equals the per-coordinate one bit for bit: coordinates of every sign and
    /// scale (zeros, subnormals, either side of the 1/32 threshold, up to 1e30), unit normals.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn sse2_offset_equals_the_per_coordinate_one() {
        let mut rng = crate::sampler::Pcg32::new(7, 1);
        let specials = [
            0.0,
            -0.0,
            1e-40,
            -1e-40,
            1.0 / 32.0,
            -1.0 / 32.0,
            0.031,
            -0.032,
        ];
        for i in 0..200_000u32 {
            let mut c = [0.0f32; 3];
            for x in &mut c {
                *x = if rng.next_f32() < 0.1 {
                    specials[(rng.next_u32() % specials.len() as u32) as usize]
                } else {
                    let mag = 10f32.powf(rng.next_f32() * 36.0 - 6.0);
                    if rng.next_u32() & 1 == 0 { mag } else { -mag }
                };
            }
            let p = Vec3::from_array(c);
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            let mut n = crate::geometry::warp::uniform_sphere(u);
            if i % 7 == 0 {
                n = [Vec3::X, -Vec3::Y, Vec3::Z][(i / 7 % 3) as usize];
            }
            let (a, b) = (offset_sse2(p, n), offset_lanes(p, n));
            assert_eq!(
                a.to_array().map(f32::to_bits),
                b.to_array().map(f32::to_bits),
                "p {p:?} n {n:?}"
            );
        }
    }
}
