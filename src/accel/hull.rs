//! The boundary of a closed room: planes behind which the whole scene lies, each holding some of
//! the scene's triangles (walls, floor, ceiling). A segment that starts and ends in front of
//! every plane stays in front of them all (the region in front of them is convex), so it cannot
//! meet a boundary triangle: a shadow ray between two points of the room need not test the
//! walls. The flat queries use it for shadow rays (`flat::Flat`); the answers are the same as
//! testing every triangle.

use super::SphereGeom;
use crate::geometry::Vec3;
use glam::DVec3;

/// The most planes kept: one register of f32 lanes. A room has six at most; further planes'
/// triangles are treated as inside the room.
pub(super) const PLANES: usize = 8;

/// How far, relative to the scene's largest coordinate, a triangle may stand from a plane and
/// still be taken as lying on it.
const COPLANAR: f64 = 1e-5;
/// The margin, relative to the scene's largest coordinate, by which each plane's band is widened
/// towards the room: many times the rounding error of a dot product of f32 points, and well
/// under the lift that moves a ray's origin off a wall (256 ulps, `geometry::offset_origin`).
const MARGIN: f64 = 2e-6;

/// Boundary planes, one per lane; lanes past `count` never report a crossing.
#[derive(Clone, Copy, Debug)]
pub(super) struct Hull {
    /// Outward unit normals (unused lanes: zero).
    n: [[f32; PLANES]; 3],
    /// The inner face of each plane's band: every point of its triangles has n . x above it,
    /// every point of the scene has n . x at most the band's outer face (unused lanes: 1).
    lower: [f32; PLANES],
    count: usize,
}

impl Hull {
    /// No planes: nothing is skipped.
    pub(super) const NONE: Hull = Hull {
        n: [[0.0; PLANES]; 3],
        lower: [1.0; PLANES],
        count: 0,
    };

    /// The boundary planes of a scene of `triangles` and `spheres`, and for each triangle
    /// whether it lies on one of them.
    pub(super) fn find(triangles: &[[Vec3; 3]], spheres: &[SphereGeom]) -> (Hull, Vec<bool>) {
        let mut on_hull = vec![false; triangles.len()];
        let mut hull = Hull::NONE;
        let v = |p: Vec3| DVec3::new(p.x as f64, p.y as f64, p.z as f64);
        let scale = triangles
            .iter()
            .flatten()
            .map(|&p| v(p).abs().max_element())
            .chain(
                spheres
                    .iter()
                    .map(|s| v(s.center).abs().max_element() + s.radius as f64),
            )
            .fold(0.0f64, f64::max);
        if !(scale > 0.0 && scale.is_finite()) {
            return (hull, on_hull);
        }
        // The farthest any primitive reaches along `n`.
        let reach = |n: DVec3| {
            triangles
                .iter()
                .flatten()
                .map(|&p| n.dot(v(p)))
                .chain(spheres.iter().map(|s| n.dot(v(s.center)) + s.radius as f64))
                .fold(f64::NEG_INFINITY, f64::max)
        };
        let lowest =
            |n: DVec3, t: &[Vec3; 3]| t.iter().map(|&p| n.dot(v(p))).fold(f64::MAX, f64::min);
        for i in 0..triangles.len() {
            if on_hull[i] || hull.count == PLANES {
                continue;
            }
            let t = &triangles[i];
            let normal = (v(t[1]) - v(t[0]))
                .cross(v(t[2]) - v(t[0]))
                .normalize_or_zero();
            if normal == DVec3::ZERO {
                continue;
            }
            for n in [normal, -normal] {
                let outer = reach(n);
                let near = |t: &[Vec3; 3]| lowest(n, t) >= outer - COPLANAR * scale;
                if !near(t) {
                    continue;
                }
                let mut lower = f64::MAX;
                for (j, tj) in triangles.iter().enumerate() {
                    if !on_hull[j] && near(tj) {
                        on_hull[j] = true;
                        lower = lower.min(lowest(n, tj));
                    }
                }
                let k = hull.count;
                for a in 0..3 {
                    hull.n[a][k] = n[a] as f32;
                }
                hull.lower[k] = (lower - MARGIN * scale) as f32;
                hull.count += 1;
                break;
            }
        }
        (hull, on_hull)
    }

    /// Whether the segment from `o` to `o + t d` lies in front of every plane's band, so that no
    /// boundary triangle meets it (false for an infinite `t`).
    #[inline(always)]
    pub(super) fn clear(&self, o: Vec3, d: Vec3, t: f32) -> bool {
        let e = o + d * t;
        let mut clear = true;
        for j in 0..PLANES {
            let (nx, ny, nz) = (self.n[0][j], self.n[1][j], self.n[2][j]);
            let a = nx * o.x + ny * o.y + nz * o.z;
            let b = nx * e.x + ny * e.y + nz * e.z;
            clear &= a < self.lower[j] && b < self.lower[j];
        }
        clear
    }

    /// `clear` for the eight planes at once (the same arithmetic).
    #[cfg(target_arch = "x86_64")]
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) fn clear_avx2(&self, o: Vec3, d: Vec3, t: f32) -> bool {
        use std::arch::x86_64::*;
        let e = o + d * t;
        // SAFETY: each row is eight f32.
        let row = |r: &[f32; PLANES]| unsafe { _mm256_loadu_ps(r.as_ptr()) };
        let (nx, ny, nz) = (row(&self.n[0]), row(&self.n[1]), row(&self.n[2]));
        let dot = |p: Vec3| {
            let x = _mm256_mul_ps(nx, _mm256_set1_ps(p.x));
            let y = _mm256_mul_ps(ny, _mm256_set1_ps(p.y));
            let z = _mm256_mul_ps(nz, _mm256_set1_ps(p.z));
            _mm256_add_ps(_mm256_add_ps(x, y), z)
        };
        let lower = row(&self.lower);
        let inside = _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_LT_OQ>(dot(o), lower),
            _mm256_cmp_ps::<_CMP_LT_OQ>(dot(e), lower),
        );
        _mm256_movemask_ps(inside) == 0xff
    }

    /// Planes found.
    #[cfg(test)]
    pub(super) fn count(&self) -> usize {
        self.count
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// A room open at the front: floor (tilted by 1e-7, as exported meshes are), ceiling, back
    /// and side walls (triangles 0-9); a block standing on the floor, its bottom on the floor's
    /// plane (10, 11), its top and a side (12-15); a sphere.
    pub(in crate::accel) fn room() -> (Vec<[Vec3; 3]>, Vec<SphereGeom>) {
        #[rustfmt::skip]
        let quads: [[[f32; 3]; 4]; 8] = [
            [[-1.0, 1e-7, -1.0], [1.0, -1e-7, -1.0], [1.0, -1e-7, 1.0], [-1.0, 1e-7, 1.0]],
            [[-1.0, 2.0, -1.0], [-1.0, 2.0, 1.0], [1.0, 2.0, 1.0], [1.0, 2.0, -1.0]],
            [[-1.0, 0.0, -1.0], [-1.0, 2.0, -1.0], [1.0, 2.0, -1.0], [1.0, 0.0, -1.0]],
            [[-1.0, 0.0, -1.0], [-1.0, 0.0, 1.0], [-1.0, 2.0, 1.0], [-1.0, 2.0, -1.0]],
            [[1.0, 0.0, -1.0], [1.0, 2.0, -1.0], [1.0, 2.0, 1.0], [1.0, 0.0, 1.0]],
            [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.5, 0.0, 0.5], [0.0, 0.0, 0.5]],
            [[0.0, 0.6, 0.0], [0.0, 0.6, 0.5], [0.5, 0.6, 0.5], [0.5, 0.6, 0.0]],
            [[0.0, 0.0, 0.5], [0.5, 0.0, 0.5], [0.5, 0.6, 0.5], [0.0, 0.6, 0.5]],
        ];
        let tris = quads
            .iter()
            .flat_map(|q| {
                let [a, b, c, d] = q.map(Vec3::from_array);
                [[a, b, c], [a, c, d]]
            })
            .collect();
        let p = Vec3::new;
        let sphere = SphereGeom {
            center: p(-0.5, 0.5, 0.0),
            radius: 0.4,
        };
        (tris, vec![sphere])
    }

    /// The room's walls are on the hull with the block's bottom (on the floor's plane); its
    /// other faces and the sphere are inside. Segments inside the room are clear of the hull;
    /// those that leave it, or reach a wall, are not.
    #[test]
    fn a_room_has_its_walls_on_the_hull_and_nothing_else() {
        let (tris, spheres) = room();
        let p = Vec3::new;
        let (hull, on) = Hull::find(&tris, &spheres);
        assert_eq!(hull.count(), 5);
        assert_eq!(on, [[true; 12].as_slice(), &[false; 4]].concat());
        // A shadow ray across the room, lifted off the floor, does not reach a band; one through
        // the ceiling, or from the camera's side of the open front to the back wall, does.
        let o = p(0.2, 3e-5, 0.2);
        let to = |q: Vec3| ((q - o).normalize(), (q - o).length());
        let (d, t) = to(p(0.9, 1.5, -0.9));
        assert!(hull.clear(o, d, t));
        let (d, t) = to(p(0.9, 2.5, -0.9));
        assert!(!hull.clear(o, d, t));
        assert!(!hull.clear(o, d, f32::INFINITY));
        assert!(hull.clear(p(0.0, 1.0, 5.0), Vec3::NEG_Z, 5.9));
        assert!(!hull.clear(p(0.0, 1.0, 5.0), Vec3::NEG_Z, 6.0));
        // From above the ceiling, outside the room.
        assert!(!hull.clear(p(0.0, 3.0, 0.0), Vec3::NEG_Y, 0.5));
        // A sphere that pokes through the floor keeps the floor (and the block's bottom) off
        // the hull.
        let low = SphereGeom {
            center: p(0.5, 0.1, 0.5),
            radius: 0.2,
        };
        let (hull, on) = Hull::find(&tris, &[low]);
        assert_eq!(hull.count(), 4);
        assert!(!on[0] && !on[1] && on[2] && !on[10]);
    }
}
