//! Whether a ray can meet two emitters: where none can, the light-sampling density of a
//! direction needs no sum over the lights its ray meets.

use crate::geometry::Vec3;
use crate::light::Light;
use glam::{DVec2, DVec3};

/// The most coplanar triangle lights whose interiors are checked pair by pair for
/// [`one_emitter_per_ray`]; past it the light-sampling density sums over the lights a ray meets.
const ONE_EMITTER_CHECK_MAX: usize = 64;

/// True when no ray meets two emitters (except on a set of measure zero): at most one area light,
/// or triangles in one plane (`coplanar`, from [`coplanar_triangle_lights`]) no two of which
/// overlap. A ray crosses the plane once, so it meets at most one of them.
pub(super) fn one_emitter_per_ray(lights: &[Light], area: &[u32], coplanar: bool) -> bool {
    if area.len() <= 1 {
        return true;
    }
    if !coplanar || area.len() > ONE_EMITTER_CHECK_MAX {
        return false;
    }
    let corners: Vec<[DVec3; 3]> = area
        .iter()
        .filter_map(|&l| match &lights[l as usize] {
            Light::Triangle { p0, e1, e2, .. } => {
                let p0 = p0.as_dvec3();
                Some([p0, p0 + e1.as_dvec3(), p0 + e2.as_dvec3()])
            }
            _ => None,
        })
        .collect();
    if corners.len() != area.len() {
        return false;
    }
    // The plane's axes, from the first triangle (the rest lie in its plane).
    let [a, b, c] = corners[0];
    let (s, t) = (b - a).cross(c - a).normalize().any_orthonormal_pair();
    let flat: Vec<[DVec2; 3]> = corners
        .iter()
        .map(|tri| tri.map(|p| DVec2::new(p.dot(s), p.dot(t))))
        .collect();
    let scale = flat
        .iter()
        .flatten()
        .fold(0.0f64, |m, p| m.max(p.abs().max_element()));
    for (i, a) in flat.iter().enumerate() {
        if flat[i + 1..].iter().any(|b| interiors_overlap(a, b, scale)) {
            return false;
        }
    }
    true
}

/// Separating-axis test of two triangles in a plane: true unless an edge normal of either
/// separates them (touching along an edge or at a corner, to within rounding, is separate).
/// `scale` is the largest coordinate.
fn interiors_overlap(a: &[DVec2; 3], b: &[DVec2; 3], scale: f64) -> bool {
    let range = |tri: &[DVec2; 3], axis: DVec2| {
        let d = tri.map(|p| p.dot(axis));
        (d[0].min(d[1]).min(d[2]), d[0].max(d[1]).max(d[2]))
    };
    for tri in [a, b] {
        for k in 0..3 {
            let e = tri[(k + 1) % 3] - tri[k];
            let axis = e.perp();
            let tol = 1e-10 * axis.length() * scale;
            let (a_lo, a_hi) = range(a, axis);
            let (b_lo, b_hi) = range(b, axis);
            if a_hi <= b_lo + tol || b_hi <= a_lo + tol {
                return false;
            }
        }
    }
    true
}

/// True when there is at most one area light, or all are triangles in one plane.
pub(super) fn coplanar_triangle_lights(lights: &[Light], area: &[u32]) -> bool {
    let mut plane: Option<(Vec3, Vec3)> = None;
    for &l in area {
        let Light::Triangle { p0, e1, e2, .. } = &lights[l as usize] else {
            return area.len() <= 1;
        };
        let n = e1.cross(*e2).normalize();
        match plane {
            None => plane = Some((*p0, n)),
            Some((q, m)) => {
                let scale = 1e-5 * (1.0 + q.abs().max_element() + p0.abs().max_element());
                let pts = [*p0, *p0 + *e1, *p0 + *e2];
                if n.dot(m).abs() < 1.0 - 1e-6 || pts.iter().any(|p| (*p - q).dot(m).abs() > scale)
                {
                    return false;
                }
            }
        }
    }
    true
}
