//! Math for the renderer: rays, orthonormal frames, transforms and sampling warps.
//!
//! Geometry and radiance are f32 (glam); sums that accumulate live elsewhere in f64.
//!
//! The bottom of the dependency graph: every other module uses these types, and this one
//! uses none of the crate's.

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
    const ORIGIN: f32 = 1.0 / 32.0;
    const FLOAT_SCALE: f32 = 1.0 / 65536.0;
    const INT_SCALE: f32 = 256.0;
    let n = if ng.dot(dir) < 0.0 { -ng } else { ng };
    let of_i = [
        (INT_SCALE * n.x) as i32,
        (INT_SCALE * n.y) as i32,
        (INT_SCALE * n.z) as i32,
    ];
    let pa = p.to_array();
    let na = n.to_array();
    let mut out = [0.0f32; 3];
    for k in 0..3 {
        let bits = pa[k].to_bits() as i32;
        let moved = bits.wrapping_add(if pa[k] < 0.0 { -of_i[k] } else { of_i[k] });
        let p_i = f32::from_bits(moved as u32);
        out[k] = if pa[k].abs() < ORIGIN {
            pa[k] + FLOAT_SCALE * na[k]
        } else {
            p_i
        };
    }
    Vec3::from_array(out)
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
}
