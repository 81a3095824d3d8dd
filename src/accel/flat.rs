//! Every primitive tested against every ray, eight triangles at a time: for scenes of a few dozen
//! primitives (the Cornell boxes, SmallVCM's scenes) this beats any hierarchy, whose node tests,
//! stack and per-primitive callbacks cost more than the triangles they skip. SmallVCM has no BVH
//! for the same reason.
//!
//! The triangle test is obvhs's `RtTriangle::intersect` (Möller and Trumbore, "Fast, Minimum
//! Storage Ray/Triangle Intersection", JGT 1997, in the edge layout of
//! madmann91's "An introduction to BVHs", 2021) with the same operations in the same order, lane
//! by lane, so a triangle reports the same distance bit for bit whichever index finds it.

use super::{Prim, SphereGeom};
use crate::geometry::{Ray, Vec2, Vec3};

/// Triangles per block: one AVX register of f32, two SSE registers.
const LANES: usize = 8;

/// Eight triangles, structure of arrays. Unused lanes are all zero: their determinant is 0, so
/// their distance is 0 * inf = NaN, which fails every range test.
#[derive(Clone, Copy, Default)]
#[repr(C, align(32))]
struct Block {
    v0: [[f32; LANES]; 3],
    /// v0 - v1.
    e1: [[f32; LANES]; 3],
    /// v2 - v0.
    e2: [[f32; LANES]; 3],
    /// e1 x e2.
    ng: [[f32; LANES]; 3],
}

/// The distances of a ray to the eight triangles of a block: inside [tmin, tmax], else infinity.
#[inline(always)]
#[allow(clippy::needless_range_loop)] // lane loops index several arrays: the form that vectorises
fn block_distances(b: &Block, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> [f32; LANES] {
    let mut out = [f32::INFINITY; LANES];
    for i in 0..LANES {
        let (cx, cy, cz) = (b.v0[0][i] - o.x, b.v0[1][i] - o.y, b.v0[2][i] - o.z);
        // r = d x c
        let rx = d.y * cz - d.z * cy;
        let ry = d.z * cx - d.x * cz;
        let rz = d.x * cy - d.y * cx;
        let inv_det = 1.0 / (b.ng[0][i] * d.x + b.ng[1][i] * d.y + b.ng[2][i] * d.z);
        let u = (rx * b.e2[0][i] + ry * b.e2[1][i] + rz * b.e2[2][i]) * inv_det;
        let v = (rx * b.e1[0][i] + ry * b.e1[1][i] + rz * b.e1[2][i]) * inv_det;
        let w = 1.0 - u - v;
        let t = (b.ng[0][i] * cx + b.ng[1][i] * cy + b.ng[2][i] * cz) * inv_det;
        // As obvhs: a sign bit on any barycentric (-0.0 included) is a miss.
        let inside = (u.to_bits() | v.to_bits() | w.to_bits()) & 0x8000_0000 == 0;
        if inv_det != 0.0 && inside && t >= tmin && t <= tmax {
            out[i] = t;
        }
    }
    out
}

/// A flat list of a small scene's primitives.
pub(super) struct Flat {
    blocks: Vec<Block>,
    /// The primitive of each triangle lane (block * LANES + lane).
    tri_prims: Vec<Prim>,
    spheres: Vec<(SphereGeom, Prim)>,
    /// The processor has AVX2: the same arithmetic runs eight lanes per instruction.
    avx2: bool,
}

/// What a closest-hit query found: the primitive, its distance and, for triangles, the
/// barycentrics (b1, b2) of vertices 1 and 2.
pub(super) type FlatHit = (Prim, f32, Vec2);

impl Flat {
    /// `triangles[i]` is scene triangle `tri_ids[i]`; likewise the spheres.
    pub(super) fn new(
        triangles: &[[Vec3; 3]],
        tri_ids: &[u32],
        spheres: &[SphereGeom],
        sphere_ids: &[u32],
    ) -> Flat {
        let mut blocks = vec![Block::default(); triangles.len().div_ceil(LANES)];
        for (k, t) in triangles.iter().enumerate() {
            let b = &mut blocks[k / LANES];
            let lane = k % LANES;
            let (e1, e2) = (t[0] - t[1], t[2] - t[0]);
            let ng = e1.cross(e2);
            for a in 0..3 {
                b.v0[a][lane] = t[0][a];
                b.e1[a][lane] = e1[a];
                b.e2[a][lane] = e2[a];
                b.ng[a][lane] = ng[a];
            }
        }
        Flat {
            blocks,
            tri_prims: tri_ids.iter().map(|&i| Prim::Triangle(i)).collect(),
            spheres: spheres
                .iter()
                .zip(sphere_ids)
                .map(|(s, &i)| (*s, Prim::Sphere(i)))
                .collect(),
            avx2: has_avx2(),
        }
    }

    /// Closest hit with t in [tmin, tmax) (a hit exactly at tmax is a miss, as in obvhs); of
    /// triangles at the same distance, the first in the scene's order.
    #[inline]
    pub(super) fn intersect(&self, ray: &Ray) -> Option<FlatHit> {
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is true only where the processor reports AVX2.
            return unsafe { self.intersect_avx2(ray) };
        }
        self.intersect_any(ray)
    }

    /// True when some primitive lies on the ray with t in [tmin, tmax) (as obvhs).
    #[inline]
    pub(super) fn occluded(&self, ray: &Ray) -> bool {
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is true only where the processor reports AVX2.
            return unsafe { self.occluded_avx2(ray) };
        }
        self.occluded_any(ray)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn intersect_avx2(&self, ray: &Ray) -> Option<FlatHit> {
        self.intersect_any(ray)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn occluded_avx2(&self, ray: &Ray) -> bool {
        self.occluded_any(ray)
    }

    /// `intersect` for whatever instruction set it is compiled for.
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // lane loops, as in `block_distances`
    fn intersect_any(&self, ray: &Ray) -> Option<FlatHit> {
        let (o, d) = (ray.o, ray.d);
        // Per lane, the nearest distance and its block: a select per lane, no branch.
        let mut lane_t = [ray.tmax; LANES];
        let mut lane_block = [0u32; LANES];
        for (k, b) in self.blocks.iter().enumerate() {
            let ts = block_distances(b, o, d, ray.tmin, ray.tmax);
            for i in 0..LANES {
                let nearer = ts[i] < lane_t[i];
                lane_t[i] = if nearer { ts[i] } else { lane_t[i] };
                lane_block[i] = if nearer { k as u32 } else { lane_block[i] };
            }
        }
        let mut best = ray.tmax;
        let mut found = usize::MAX;
        for i in 0..LANES {
            let index = lane_block[i] as usize * LANES + i;
            if lane_t[i] < best || lane_t[i] == best && lane_t[i] < ray.tmax && index < found {
                best = lane_t[i];
                found = index;
            }
        }
        let mut sphere = None;
        for (s, prim) in &self.spheres {
            let t = s.intersect(o, d, ray.tmin, best);
            if t < best {
                best = t;
                sphere = Some(*prim);
            }
        }
        if let Some(prim) = sphere {
            return Some((prim, best, Vec2::ZERO));
        }
        if found == usize::MAX {
            return None;
        }
        let b = &self.blocks[found / LANES];
        let lane = found % LANES;
        let get = |m: &[[f32; LANES]; 3]| Vec3::new(m[0][lane], m[1][lane], m[2][lane]);
        // obvhs's `compute_barycentric`, operation for operation.
        let r = d.cross(get(&b.v0) - o);
        let bary = Vec2::new(r.dot(get(&b.e2)), r.dot(get(&b.e1))) / get(&b.ng).dot(d);
        Some((self.tri_prims[found], best, bary))
    }

    /// `occluded` for whatever instruction set it is compiled for.
    #[inline(always)]
    fn occluded_any(&self, ray: &Ray) -> bool {
        let (o, d) = (ray.o, ray.d);
        for b in &self.blocks {
            let ts = block_distances(b, o, d, ray.tmin, ray.tmax);
            if ts.iter().any(|&t| t < ray.tmax) {
                return true;
            }
        }
        self.spheres
            .iter()
            .any(|(s, _)| s.intersect(o, d, ray.tmin, ray.tmax) < ray.tmax)
    }
}

/// Whether the processor has AVX2 (never on other architectures).
fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}
