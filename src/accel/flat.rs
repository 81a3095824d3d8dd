//! Every primitive tested against every ray, eight triangles at a time (sixteen with AVX-512): for
//! scenes of a few dozen primitives (the Cornell boxes, SmallVCM's scenes) this beats any
//! hierarchy, whose node tests, stack and per-primitive callbacks cost more than the triangles
//! they skip. SmallVCM has no BVH for the same reason.
//!
//! The triangle test is obvhs's `RtTriangle::intersect` (Möller and Trumbore, "Fast, Minimum
//! Storage Ray/Triangle Intersection", JGT 1997, in the edge layout of
//! madmann91's "An introduction to BVHs", 2021) with the same operations in the same order, lane
//! by lane (glam's cross product included, which fuses a product where the build has FMA), so a
//! triangle reports the same distance bit for bit whichever index finds it. The barycentrics of
//! the hit are the lane's own (u and v times 1 / det), kept beside the nearest distance: no
//! second computation after the query, on the walk's path from one hit to the next. The BVH's
//! hits take theirs from the same formula (`barycentrics`), not from obvhs's
//! `compute_barycentric` (which divides), so both still report the same hit.
//!
//! In a closed room the walls, floor and ceiling (`hull::Hull`) cannot block a shadow ray
//! between two points of the room: their triangles are kept in blocks of their own, after the
//! rest, and shadow rays test them only when the segment may reach them.

use super::hull::Hull;
use super::{Prim, SphereGeom};
use crate::geometry::{Ray, Vec2, Vec3, Vec3A};

/// Triangles per block: one AVX register of f32, two SSE registers.
const LANES: usize = 8;
/// Triangles per wide block: one AVX-512 register of f32.
const WIDE: usize = 16;

/// `N` triangles, structure of arrays: eight for the portable and AVX2 queries ([`Block`]),
/// sixteen for the AVX-512 ones ([`WideBlock`]); triangle `k` in block `k / N`, lane `k % N`.
/// Unused lanes are all zero: their determinant is 0, so their distance is 0 * inf = NaN, which
/// fails every range test.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Rows<const N: usize> {
    v0: [[f32; N]; 3],
    /// v0 - v1.
    e1: [[f32; N]; 3],
    /// v2 - v0.
    e2: [[f32; N]; 3],
    /// e1 x e2.
    ng: [[f32; N]; 3],
}

impl<const N: usize> Rows<N> {
    const ZERO: Self = Rows {
        v0: [[0.0; N]; 3],
        e1: [[0.0; N]; 3],
        e2: [[0.0; N]; 3],
        ng: [[0.0; N]; 3],
    };
}

/// Eight triangles: one AVX register of f32 per row.
type Block = Rows<LANES>;
/// Sixteen triangles: one AVX-512 register of f32 per row.
type WideBlock = Rows<WIDE>;

/// a b - c d as glam's `Vec3A::cross` forms each component, which obvhs's triangle test uses:
/// the second product fused into the subtraction where the build has FMA (x86-64-v3).
#[inline(always)]
fn cross_term(a: f32, b: f32, c: f32, d: f32) -> f32 {
    #[cfg(target_feature = "fma")]
    {
        (-c).mul_add(d, a * b)
    }
    #[cfg(not(target_feature = "fma"))]
    {
        a * b - c * d
    }
}

/// One triangle (`v0`, `e1` = v0 - v1, `e2` = v2 - v0, `ng` = e1 x e2) against a ray: 1 / det,
/// the barycentrics u (of v1), v (of v2) and w = 1 - u - v, and the distance t, by obvhs's
/// `RtTriangle::intersect` operation for operation. Every form of the flat queries computes a
/// lane this way, and the BVH's hits take their barycentrics from it (`barycentrics`).
#[inline(always)]
fn triangle_terms(v0: Vec3, e1: Vec3, e2: Vec3, ng: Vec3, o: Vec3, d: Vec3) -> [f32; 5] {
    let (cx, cy, cz) = (v0.x - o.x, v0.y - o.y, v0.z - o.z);
    // r = d x c, as glam's Vec3A forms it
    let rx = cross_term(d.y, cz, cy, d.z);
    let ry = cross_term(d.z, cx, cz, d.x);
    let rz = cross_term(d.x, cy, cx, d.y);
    let inv_det = 1.0 / (ng.x * d.x + ng.y * d.y + ng.z * d.z);
    let u = (rx * e2.x + ry * e2.y + rz * e2.z) * inv_det;
    let v = (rx * e1.x + ry * e1.y + rz * e1.z) * inv_det;
    let w = 1.0 - u - v;
    let t = (ng.x * cx + ng.y * cy + ng.z * cz) * inv_det;
    [inv_det, u, v, w, t]
}

/// The barycentrics (of vertices 1 and 2) at which a ray crosses a triangle's plane, as the flat
/// queries find them (`triangle_terms`): the BVH's hits use them too, so that both report the
/// same hit bit for bit.
#[inline]
pub(super) fn barycentrics(v0: Vec3, e1: Vec3, e2: Vec3, ng: Vec3, o: Vec3, d: Vec3) -> Vec2 {
    let [_, u, v, _, _] = triangle_terms(v0, e1, e2, ng, o, d);
    Vec2::new(u, v)
}

/// What a block of triangles gives a ray, per lane: the distance inside [tmin, tmax] (else
/// infinity) and the barycentrics u and v there.
type LaneHits = [[f32; LANES]; 3];

/// The distances of a ray to the eight triangles of a block, and their barycentrics.
#[inline(always)]
#[allow(clippy::needless_range_loop)] // lane loops index several arrays (the portable form, off x86-64)
fn block_distances(b: &Block, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> LaneHits {
    let mut out = [[f32::INFINITY; LANES], [0.0; LANES], [0.0; LANES]];
    for i in 0..LANES {
        let row = |m: &[[f32; LANES]; 3]| Vec3::new(m[0][i], m[1][i], m[2][i]);
        let [inv_det, u, v, w, t] =
            triangle_terms(row(&b.v0), row(&b.e1), row(&b.e2), row(&b.ng), o, d);
        // As obvhs: a sign bit on any barycentric (-0.0 included) is a miss.
        let inside = (u.to_bits() | v.to_bits() | w.to_bits()) & 0x8000_0000 == 0;
        if inv_det != 0.0 && inside && t >= tmin && t <= tmax {
            out[0][i] = t;
        }
        out[1][i] = u;
        out[2][i] = v;
    }
    out
}

/// A flat list of a small scene's primitives.
pub(super) struct Flat {
    /// The triangles eight to a block: those inside the room first (`inner` blocks), then
    /// those on its boundary (`hull`), each in the scene's order.
    blocks: Vec<Block>,
    /// The same triangles sixteen to a block, where the processor has AVX-512 (else empty):
    /// `inner_wide` blocks inside, then the boundary's.
    wide: Vec<WideBlock>,
    inner: usize,
    inner_wide: usize,
    /// The primitive of each triangle lane (block * LANES + lane; padding: never found).
    tri_prims: Vec<Prim>,
    /// The primitive of each wide lane (block * WIDE + lane).
    wide_prims: Vec<Prim>,
    spheres: Vec<(SphereGeom, Prim)>,
    /// The planes the boundary's triangles lie on.
    hull: Hull,
    /// The widest instructions the processor offers for the same arithmetic.
    isa: Isa,
}

/// Which form of the queries runs: the same arithmetic on 1, 8 or 16 lanes per instruction.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Isa {
    Portable,
    Avx2,
    Avx512,
}

/// What a closest-hit query found: the primitive, its distance and, for triangles, the
/// barycentrics (b1, b2) of vertices 1 and 2.
pub(super) type FlatHit = (Prim, f32, Vec2);

/// `triangles` (indices into `all`, in order) into blocks of `N` lanes; `prims` gets each lane's
/// primitive (padding: a triangle id no scene has, never found since padding never hits).
fn fill<const N: usize>(
    all: &[[Vec3; 3]],
    ids: &[u32],
    triangles: &[usize],
    blocks: &mut Vec<Rows<N>>,
    prims: &mut Vec<Prim>,
) {
    let first = blocks.len();
    blocks.resize(first + triangles.len().div_ceil(N), Rows::ZERO);
    prims.resize(blocks.len() * N, Prim::Triangle(u32::MAX));
    for (k, &i) in triangles.iter().enumerate() {
        let t = &all[i];
        let b = &mut blocks[first + k / N];
        let lane = k % N;
        let (e1, e2) = (t[0] - t[1], t[2] - t[0]);
        let ng = Vec3::from(Vec3A::from(e1).cross(Vec3A::from(e2)));
        for a in 0..3 {
            b.v0[a][lane] = t[0][a];
            b.e1[a][lane] = e1[a];
            b.e2[a][lane] = e2[a];
            b.ng[a][lane] = ng[a];
        }
        prims[first * N + k] = Prim::Triangle(ids[i]);
    }
}

impl Flat {
    /// `triangles[i]` is scene triangle `tri_ids[i]`; likewise the spheres.
    pub(super) fn new(
        triangles: &[[Vec3; 3]],
        tri_ids: &[u32],
        spheres: &[SphereGeom],
        sphere_ids: &[u32],
    ) -> Flat {
        Flat::with_hull(triangles, tri_ids, spheres, sphere_ids, true)
    }

    /// As `new`, with the room's boundary found (`Hull::find`) or not (every shadow ray tests
    /// every triangle).
    fn with_hull(
        triangles: &[[Vec3; 3]],
        tri_ids: &[u32],
        spheres: &[SphereGeom],
        sphere_ids: &[u32],
        find_hull: bool,
    ) -> Flat {
        let isa = detect_isa();
        let (hull, on_hull) = if find_hull {
            Hull::find(triangles, spheres)
        } else {
            (Hull::NONE, vec![false; triangles.len()])
        };
        let (inside, boundary): (Vec<usize>, Vec<usize>) =
            (0..triangles.len()).partition(|&i| !on_hull[i]);
        let (mut blocks, mut tri_prims) = (Vec::new(), Vec::new());
        fill(triangles, tri_ids, &inside, &mut blocks, &mut tri_prims);
        let inner = blocks.len();
        fill(triangles, tri_ids, &boundary, &mut blocks, &mut tri_prims);
        let (mut wide, mut wide_prims) = (Vec::new(), Vec::new());
        if isa == Isa::Avx512 {
            fill(triangles, tri_ids, &inside, &mut wide, &mut wide_prims);
        }
        let inner_wide = wide.len();
        if isa == Isa::Avx512 {
            fill(triangles, tri_ids, &boundary, &mut wide, &mut wide_prims);
        }
        Flat {
            blocks,
            wide,
            inner,
            inner_wide,
            tri_prims,
            wide_prims,
            spheres: spheres
                .iter()
                .zip(sphere_ids)
                .map(|(s, &i)| (*s, Prim::Sphere(i)))
                .collect(),
            hull,
            isa,
        }
    }

    /// Closest hit with t in [tmin, tmax) (a hit exactly at tmax is a miss, as in obvhs); of
    /// triangles at the same distance, the first in the flat's order (the room's inside, then
    /// its boundary, each in the scene's order).
    #[inline]
    pub(super) fn intersect(&self, ray: &Ray) -> Option<FlatHit> {
        #[cfg(target_arch = "x86_64")]
        match self.isa {
            // SAFETY: `isa` names only instruction sets the processor reports.
            Isa::Avx512 => return unsafe { self.intersect_avx512(ray) },
            // SAFETY: as above.
            Isa::Avx2 => return unsafe { self.intersect_avx2(ray) },
            Isa::Portable => {}
        }
        self.intersect_any(ray)
    }

    /// True when some primitive lies on the ray with t in [tmin, tmax) (as obvhs).
    #[inline]
    pub(super) fn occluded(&self, ray: &Ray) -> bool {
        #[cfg(target_arch = "x86_64")]
        match self.isa {
            // SAFETY: `isa` names only instruction sets the processor reports.
            Isa::Avx512 => return unsafe { self.occluded_avx512(ray) },
            // SAFETY: as above.
            Isa::Avx2 => return unsafe { self.occluded_avx2(ray) },
            Isa::Portable => {}
        }
        self.occluded_any(ray)
    }

    /// `intersect_any` in AVX2 registers: the distances stay in registers from the triangle test
    /// to the per-lane minimum (the portable form's array of distances went through the stack
    /// with a masked store, whose reload stalled). Same operations, same order: same bits.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn intersect_avx2(&self, ray: &Ray) -> Option<FlatHit> {
        use std::arch::x86_64::*;
        let r = avx2::ray_lanes(ray);
        let mut lane_t = _mm256_set1_ps(ray.tmax);
        let mut lane_block = _mm256_setzero_ps();
        let (mut lane_u, mut lane_v) = (_mm256_setzero_ps(), _mm256_setzero_ps());
        for (k, b) in self.blocks.iter().enumerate() {
            let (ts, u, v) = avx2::block_distances(b, &r);
            let nearer = _mm256_cmp_ps::<_CMP_LT_OQ>(ts, lane_t);
            lane_t = _mm256_blendv_ps(lane_t, ts, nearer);
            lane_u = _mm256_blendv_ps(lane_u, u, nearer);
            lane_v = _mm256_blendv_ps(lane_v, v, nearer);
            let block = _mm256_castsi256_ps(_mm256_set1_epi32(k as i32));
            lane_block = _mm256_blendv_ps(lane_block, block, nearer);
        }
        let (best, found) = avx2::nearest_lane(lane_t, _mm256_castps_si256(lane_block), ray.tmax);
        let (mut us, mut vs) = ([0.0f32; LANES], [0.0f32; LANES]);
        // SAFETY: eight f32 each; AVX2 is enabled here.
        unsafe {
            _mm256_storeu_ps(us.as_mut_ptr(), lane_u);
            _mm256_storeu_ps(vs.as_mut_ptr(), lane_v);
        }
        let lane = found % LANES;
        self.closest_of(
            ray,
            best,
            found,
            Vec2::new(us[lane], vs[lane]),
            &self.tri_prims,
        )
    }

    /// `occluded_any` in AVX2 registers (see `intersect_avx2`).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn occluded_avx2(&self, ray: &Ray) -> bool {
        use std::arch::x86_64::*;
        // Spheres first: one costs a fraction of a block of triangles, and in a closed room (the
        // Cornell boxes) the walls never block a connection while a sphere often does.
        if self.spheres_occlude(ray) {
            return true;
        }
        let r = avx2::ray_lanes(ray);
        let hits = |b: &Block| {
            let (ts, _, _) = avx2::block_distances(b, &r);
            _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(ts, r.tmax)) != 0
        };
        let clear = || self.hull.clear_avx2(ray.o, ray.d, ray.tmax);
        blocked(&self.blocks, self.inner, hits, clear)
    }

    /// `intersect_any` in AVX-512 registers, sixteen triangles per block (see `intersect_avx2`).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    fn intersect_avx512(&self, ray: &Ray) -> Option<FlatHit> {
        use std::arch::x86_64::*;
        let r = avx512::ray_lanes(ray);
        let mut lane_t = _mm512_set1_ps(ray.tmax);
        let mut lane_block = _mm512_setzero_si512();
        let (mut lane_u, mut lane_v) = (_mm512_setzero_ps(), _mm512_setzero_ps());
        for (k, b) in self.wide.iter().enumerate() {
            let (ts, u, v) = avx512::block_distances(b, &r);
            let nearer = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(ts, lane_t);
            lane_t = _mm512_mask_mov_ps(lane_t, nearer, ts);
            lane_u = _mm512_mask_mov_ps(lane_u, nearer, u);
            lane_v = _mm512_mask_mov_ps(lane_v, nearer, v);
            lane_block = _mm512_mask_mov_epi32(lane_block, nearer, _mm512_set1_epi32(k as i32));
        }
        let (best, found) = avx512::nearest_lane(lane_t, lane_block, ray.tmax);
        let (mut us, mut vs) = ([0.0f32; WIDE], [0.0f32; WIDE]);
        // SAFETY: sixteen f32 each; AVX-512 is enabled here.
        unsafe {
            _mm512_storeu_ps(us.as_mut_ptr(), lane_u);
            _mm512_storeu_ps(vs.as_mut_ptr(), lane_v);
        }
        let lane = found % WIDE;
        self.closest_of(
            ray,
            best,
            found,
            Vec2::new(us[lane], vs[lane]),
            &self.wide_prims,
        )
    }

    /// `occluded_any` in AVX-512 registers (see `occluded_avx2`).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    fn occluded_avx512(&self, ray: &Ray) -> bool {
        use std::arch::x86_64::*;
        if self.spheres_occlude(ray) {
            return true;
        }
        let r = avx512::ray_lanes(ray);
        let hits = |b: &WideBlock| {
            let (ts, _, _) = avx512::block_distances(b, &r);
            _mm512_cmp_ps_mask::<_CMP_LT_OQ>(ts, r.tmax) != 0
        };
        let clear = || self.hull.clear_avx2(ray.o, ray.d, ray.tmax);
        blocked(&self.wide, self.inner_wide, hits, clear)
    }

    /// `intersect` for whatever instruction set it is compiled for.
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // lane loops, as in `block_distances`
    fn intersect_any(&self, ray: &Ray) -> Option<FlatHit> {
        let (o, d) = (ray.o, ray.d);
        // Per lane, the nearest distance and its block: a select per lane, no branch.
        let mut lane_t = [ray.tmax; LANES];
        let mut lane_block = [0u32; LANES];
        let (mut lane_u, mut lane_v) = ([0.0; LANES], [0.0; LANES]);
        for (k, b) in self.blocks.iter().enumerate() {
            let [ts, us, vs] = block_distances(b, o, d, ray.tmin, ray.tmax);
            for i in 0..LANES {
                let nearer = ts[i] < lane_t[i];
                lane_t[i] = if nearer { ts[i] } else { lane_t[i] };
                lane_u[i] = if nearer { us[i] } else { lane_u[i] };
                lane_v[i] = if nearer { vs[i] } else { lane_v[i] };
                lane_block[i] = if nearer { k as u32 } else { lane_block[i] };
            }
        }
        let (best, found) = nearest_lane(&lane_t, &lane_block, ray.tmax);
        let lane = found % LANES;
        self.closest_of(
            ray,
            best,
            found,
            Vec2::new(lane_u[lane], lane_v[lane]),
            &self.tri_prims,
        )
    }

    /// The closest hit given the nearest triangle (`best`, `found` as [`nearest_lane`] gives
    /// them, numbering the lanes of `prims`; `bary` its barycentrics from the lanes, meaningless
    /// where none was found), then the spheres.
    #[inline(always)]
    fn closest_of(
        &self,
        ray: &Ray,
        mut best: f32,
        found: usize,
        bary: Vec2,
        prims: &[Prim],
    ) -> Option<FlatHit> {
        let (o, d) = (ray.o, ray.d);
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
        Some((prims[found], best, bary))
    }

    /// `occluded` for whatever instruction set it is compiled for.
    #[inline(always)]
    fn occluded_any(&self, ray: &Ray) -> bool {
        let (o, d) = (ray.o, ray.d);
        let hits = |b: &Block| {
            let [ts, _, _] = block_distances(b, o, d, ray.tmin, ray.tmax);
            ts.iter().any(|&t| t < ray.tmax)
        };
        let clear = || self.hull.clear(o, d, ray.tmax);
        self.spheres_occlude(ray) || blocked(&self.blocks, self.inner, hits, clear)
    }

    #[inline(always)]
    fn spheres_occlude(&self, ray: &Ray) -> bool {
        self.spheres
            .iter()
            .any(|(s, _)| s.intersect(ray.o, ray.d, ray.tmin, ray.tmax) < ray.tmax)
    }
}

/// Whether some block of `blocks` (the first `inner` inside the room, the rest on its boundary)
/// blocks a shadow ray (`hits`): the boundary's only when the segment may reach it (`clear` is
/// false), which is decided after the inside's tests, beside them rather than before.
#[inline(always)]
fn blocked<B>(
    blocks: &[B],
    inner: usize,
    hits: impl Fn(&B) -> bool,
    clear: impl FnOnce() -> bool,
) -> bool {
    let (inside, boundary) = blocks.split_at(inner);
    inside.iter().any(&hits) || !boundary.is_empty() && !clear() && boundary.iter().any(hits)
}

/// The nearest of the lanes' distances (`tmax` when none is nearer) and its triangle, numbered
/// `block * LANES + lane` (`usize::MAX` for none); of lanes at the same distance, the first
/// triangle in the flat's order.
#[inline(always)]
fn nearest_lane(lane_t: &[f32; LANES], lane_block: &[u32; LANES], tmax: f32) -> (f32, usize) {
    let mut best = tmax;
    let mut found = usize::MAX;
    for i in 0..LANES {
        let index = lane_block[i] as usize * LANES + i;
        if lane_t[i] < best || lane_t[i] == best && lane_t[i] < tmax && index < found {
            best = lane_t[i];
            found = index;
        }
    }
    (best, found)
}

/// The triangle test's arithmetic on a block of rows (`super::block_distances`, operation for
/// operation) with one instruction set's vector operations: `$load` a row, `$splat` a constant,
/// `$add`, `$sub`, `$mul`, `$div`, and `$cross` (`super::cross_term`). Gives (inv_det, u, v, w,
/// t) per lane.
#[cfg(target_arch = "x86_64")]
macro_rules! triangle_lanes {
    ($b:expr, $r:expr, $load:ident, $splat:ident, $add:ident, $sub:ident, $mul:ident, $div:ident,
     $cross:ident) => {{
        let (b, r) = ($b, $r);
        let [ox, oy, oz] = r.o;
        let [dx, dy, dz] = r.d;
        let (cx, cy, cz) = (
            $sub($load(&b.v0[0]), ox),
            $sub($load(&b.v0[1]), oy),
            $sub($load(&b.v0[2]), oz),
        );
        let rx = $cross(dy, cz, cy, dz);
        let ry = $cross(dz, cx, cz, dx);
        let rz = $cross(dx, cy, cx, dy);
        let (ngx, ngy, ngz) = ($load(&b.ng[0]), $load(&b.ng[1]), $load(&b.ng[2]));
        let det = $add($add($mul(ngx, dx), $mul(ngy, dy)), $mul(ngz, dz));
        let inv_det = $div($splat(1.0), det);
        let dot = |x: &[[f32; _]; 3]| {
            $add(
                $add($mul(rx, $load(&x[0])), $mul(ry, $load(&x[1]))),
                $mul(rz, $load(&x[2])),
            )
        };
        let u = $mul(dot(&b.e2), inv_det);
        let v = $mul(dot(&b.e1), inv_det);
        let w = $sub($sub($splat(1.0), u), v);
        let t = $mul(
            $add($add($mul(ngx, cx), $mul(ngy, cy)), $mul(ngz, cz)),
            inv_det,
        );
        (inv_det, u, v, w, t)
    }};
}

/// A ray broadcast to every lane of a vector type `V`.
#[cfg(target_arch = "x86_64")]
struct RayLanes<V> {
    o: [V; 3],
    d: [V; 3],
    tmin: V,
    tmax: V,
}

#[cfg(target_arch = "x86_64")]
impl<V> RayLanes<V> {
    /// Every component of `ray` through `splat`.
    #[inline(always)]
    fn splat(ray: &Ray, splat: impl Fn(f32) -> V) -> RayLanes<V> {
        let (o, d) = (ray.o, ray.d);
        RayLanes {
            o: [splat(o.x), splat(o.y), splat(o.z)],
            d: [splat(d.x), splat(d.y), splat(d.z)],
            tmin: splat(ray.tmin),
            tmax: splat(ray.tmax),
        }
    }
}

/// `block_distances` eight lanes per instruction.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Block, LANES};
    use crate::geometry::Ray;
    use std::arch::x86_64::*;

    /// A ray broadcast to every lane.
    pub(super) type RayLanes = super::RayLanes<__m256>;

    /// `ray` broadcast to every lane.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) fn ray_lanes(ray: &Ray) -> RayLanes {
        RayLanes::splat(ray, |x| _mm256_set1_ps(x))
    }

    /// `super::cross_term` eight lanes at a time.
    #[cfg(target_feature = "fma")]
    #[inline]
    #[target_feature(enable = "avx2")]
    fn cross_term(a: __m256, b: __m256, c: __m256, d: __m256) -> __m256 {
        // SAFETY: this build targets FMA (the cfg above).
        unsafe { _mm256_fnmadd_ps(c, d, _mm256_mul_ps(a, b)) }
    }

    /// `super::cross_term` eight lanes at a time.
    #[cfg(not(target_feature = "fma"))]
    #[inline]
    #[target_feature(enable = "avx2")]
    fn cross_term(a: __m256, b: __m256, c: __m256, d: __m256) -> __m256 {
        _mm256_sub_ps(_mm256_mul_ps(a, b), _mm256_mul_ps(c, d))
    }

    #[inline(always)]
    fn load(row: &[f32; LANES]) -> __m256 {
        // SAFETY: eight f32 in a 32-byte aligned block row; AVX2 is enabled by every caller.
        unsafe { _mm256_load_ps(row.as_ptr()) }
    }

    /// `super::nearest_lane` in registers: the minimum distance, then the smallest triangle
    /// index among the lanes that hold it. No lane holds NaN (a NaN distance becomes infinity in
    /// `block_distances`), so the minimum is exact and its lanes compare equal to it; the same
    /// answer as the lane loop but for the sign of a zero distance (a ray starting exactly on a
    /// triangle's plane with tmin 0), which `min` may take from either zero.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) fn nearest_lane(lane_t: __m256, lane_block: __m256i, tmax: f32) -> (f32, usize) {
        // Horizontal minimum: halves, then pairs, then neighbours.
        let m = _mm256_min_ps(lane_t, _mm256_permute2f128_ps::<1>(lane_t, lane_t));
        let m = _mm256_min_ps(m, _mm256_permute_ps::<0b01_00_11_10>(m));
        let m = _mm256_min_ps(m, _mm256_permute_ps::<0b10_11_00_01>(m));
        let best = _mm256_cvtss_f32(m);
        if !(best < tmax) {
            return (tmax, usize::MAX);
        }
        let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let index = _mm256_add_epi32(_mm256_slli_epi32::<3>(lane_block), lanes);
        let at_best = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_EQ_OQ>(lane_t, m));
        let index = _mm256_blendv_epi8(_mm256_set1_epi32(-1), index, at_best);
        let i = _mm256_min_epu32(index, _mm256_permute2x128_si256::<1>(index, index));
        let i = _mm256_min_epu32(i, _mm256_shuffle_epi32::<0b01_00_11_10>(i));
        let i = _mm256_min_epu32(i, _mm256_shuffle_epi32::<0b10_11_00_01>(i));
        (best, _mm256_cvtsi256_si32(i) as u32 as usize)
    }

    /// `super::block_distances`, operation for operation.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) fn block_distances(b: &Block, r: &RayLanes) -> (__m256, __m256, __m256) {
        let (inv_det, u, v, w, t) = triangle_lanes!(
            b,
            r,
            load,
            _mm256_set1_ps,
            _mm256_add_ps,
            _mm256_sub_ps,
            _mm256_mul_ps,
            _mm256_div_ps,
            cross_term
        );
        // `inv_det != 0.0` is true for NaN: unordered or not equal.
        let valid = _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_NEQ_UQ>(inv_det, _mm256_setzero_ps()),
            _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(t, r.tmin),
                _mm256_cmp_ps::<_CMP_LE_OQ>(t, r.tmax),
            ),
        );
        let inf = _mm256_set1_ps(f32::INFINITY);
        let hit = _mm256_blendv_ps(inf, t, valid);
        // A sign bit on any barycentric (-0.0 included) is a miss: blendv reads the sign bit.
        let t = _mm256_blendv_ps(hit, inf, _mm256_or_ps(_mm256_or_ps(u, v), w));
        (t, u, v)
    }
}

/// `block_distances` sixteen lanes per instruction, as the `avx2` module does eight.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{WIDE, WideBlock};
    use crate::geometry::Ray;
    use std::arch::x86_64::*;

    /// A ray broadcast to every lane.
    pub(super) type RayLanes = super::RayLanes<__m512>;

    /// `ray` broadcast to every lane.
    #[inline]
    #[target_feature(enable = "avx512f")]
    pub(super) fn ray_lanes(ray: &Ray) -> RayLanes {
        RayLanes::splat(ray, |x| _mm512_set1_ps(x))
    }

    /// `super::cross_term` sixteen lanes at a time.
    #[cfg(target_feature = "fma")]
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn cross_term(a: __m512, b: __m512, c: __m512, d: __m512) -> __m512 {
        _mm512_fnmadd_ps(c, d, _mm512_mul_ps(a, b))
    }

    /// `super::cross_term` sixteen lanes at a time.
    #[cfg(not(target_feature = "fma"))]
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn cross_term(a: __m512, b: __m512, c: __m512, d: __m512) -> __m512 {
        _mm512_sub_ps(_mm512_mul_ps(a, b), _mm512_mul_ps(c, d))
    }

    #[inline]
    #[target_feature(enable = "avx512f")]
    fn load(row: &[f32; WIDE]) -> __m512 {
        // SAFETY: sixteen f32 in a 64-byte aligned block row.
        unsafe { _mm512_load_ps(row.as_ptr()) }
    }

    /// `super::nearest_lane` in registers (see `avx2::nearest_lane`), the triangle numbered
    /// `block * WIDE + lane`: the same number as `block * LANES + lane` of the eight-lane blocks.
    #[inline]
    #[target_feature(enable = "avx512f")]
    pub(super) fn nearest_lane(lane_t: __m512, lane_block: __m512i, tmax: f32) -> (f32, usize) {
        let best = _mm512_reduce_min_ps(lane_t);
        if !(best < tmax) {
            return (tmax, usize::MAX);
        }
        let lanes = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        let index = _mm512_add_epi32(_mm512_slli_epi32::<4>(lane_block), lanes);
        let at_best = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(lane_t, _mm512_set1_ps(best));
        let i = _mm512_mask_reduce_min_epu32(at_best, index);
        (best, i as usize)
    }

    /// `super::block_distances`, operation for operation.
    #[inline]
    #[target_feature(enable = "avx512f")]
    pub(super) fn block_distances(b: &WideBlock, r: &RayLanes) -> (__m512, __m512, __m512) {
        let (inv_det, u, v, w, t) = triangle_lanes!(
            b,
            r,
            load,
            _mm512_set1_ps,
            _mm512_add_ps,
            _mm512_sub_ps,
            _mm512_mul_ps,
            _mm512_div_ps,
            cross_term
        );
        // `inv_det != 0.0` is true for NaN: unordered or not equal. A sign bit on any
        // barycentric (-0.0 included) is a miss: the bits as an integer are negative.
        let signs = _mm512_or_si512(
            _mm512_or_si512(_mm512_castps_si512(u), _mm512_castps_si512(v)),
            _mm512_castps_si512(w),
        );
        let valid = _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(inv_det, _mm512_setzero_ps())
            & _mm512_cmp_ps_mask::<_CMP_GE_OQ>(t, r.tmin)
            & _mm512_cmp_ps_mask::<_CMP_LE_OQ>(t, r.tmax)
            & !_mm512_cmplt_epi32_mask(signs, _mm512_setzero_si512());
        let t = _mm512_mask_mov_ps(_mm512_set1_ps(f32::INFINITY), valid, t);
        (t, u, v)
    }
}

/// The widest form of the queries the processor runs (the portable one on other
/// architectures). AVX-512 is taken from Ice Lake and Zen 4 on (VBMI2 marks them): earlier
/// Intel processors (Skylake-SP, Cascade Lake) slow the whole core down while they run 512-bit
/// floating-point instructions.
fn detect_isa() -> Isa {
    #[cfg(target_arch = "x86_64")]
    {
        if avx512_wanted() {
            return Isa::Avx512;
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            return Isa::Avx2;
        }
    }
    Isa::Portable
}

/// AVX-512 (its foundation), on a processor that runs it at full speed (see `detect_isa`).
#[cfg(target_arch = "x86_64")]
fn avx512_wanted() -> bool {
    std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512vbmi2")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::tests::test_scene;

    /// The AVX2 and AVX-512 queries answer every ray as the portable ones do, bit for bit: the
    /// same primitive, distance and barycentrics, and the same occlusion. AVX2 is required (omis
    /// is built for x86-64-v3); the AVX-512 form is checked where the processor has it, which is
    /// the only place `Flat` runs it (`detect_isa`, checked against the processor's flags).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn wide_queries_equal_the_portable_ones() {
        let (avx2, avx512) = (std::arch::is_x86_feature_detected!("avx2"), avx512_wanted());
        assert!(avx2, "this test needs a processor with AVX2");
        let sc = test_scene();
        let flat = Flat::new(&sc.tris, &sc.ids, &sc.spheres, &sc.sphere_ids);
        assert_eq!(
            flat.isa,
            if avx512 { Isa::Avx512 } else { Isa::Avx2 },
            "the queries run the widest form the processor has"
        );
        assert_eq!(flat.inner, flat.blocks.len(), "no boundary in this scene");
        assert_eq!(flat.wide.len(), if avx512 { 3 } else { 0 });
        let bits =
            |h: Option<FlatHit>| h.map(|(p, t, b)| (p, t.to_bits(), b.x.to_bits(), b.y.to_bits()));
        let (mut hits, mut blocked, mut ties) = (0, 0, 0);
        for (i, ray) in sc.rays.iter().enumerate() {
            let portable = flat.intersect_any(ray);
            let occluded = flat.occluded_any(ray);
            // SAFETY: AVX2 is present (asserted above).
            let (a, b) = unsafe { (flat.intersect_avx2(ray), flat.occluded_avx2(ray)) };
            assert_eq!(bits(a), bits(portable), "ray {i}, AVX2");
            assert_eq!(b, occluded, "ray {i}, AVX2");
            if avx512 {
                // SAFETY: AVX-512 is present (checked above).
                let (a, b) = unsafe { (flat.intersect_avx512(ray), flat.occluded_avx512(ray)) };
                assert_eq!(bits(a), bits(portable), "ray {i}, AVX-512");
                assert_eq!(b, occluded, "ray {i}, AVX-512");
            }
            hits += portable.is_some() as u32;
            blocked += occluded as u32;
            // Rays along the quad's shared diagonal, where two triangles tie.
            ties +=
                (i % 10 == 0 && portable.is_some_and(|(p, ..)| p == Prim::Triangle(145))) as u32;
        }
        assert!(
            hits > 10_000 && blocked > 10_000 && ties > 100,
            "{hits} hits, {blocked} blocked, {ties} ties"
        );
    }

    /// In a room, shadow rays that leave out the boundary's triangles (`Hull`) get the answers
    /// of rays that test every triangle, in every form, and so do closest-hit queries (the
    /// triangles are only reordered); most shadow rays between points of the room leave them
    /// out. The rays run between points on every surface, lifted off them as the integrators'
    /// are (`Ray::between`), from outside the room, and to infinity.
    #[test]
    fn leaving_out_the_rooms_boundary_changes_no_answer() {
        use crate::sampler::Pcg32;
        let (tris, spheres) = crate::accel::hull::tests::room();
        let ids: Vec<u32> = (0..tris.len() as u32).collect();
        let sphere_ids = [50];
        let flat = Flat::with_hull(&tris, &ids, &spheres, &sphere_ids, true);
        let every = Flat::with_hull(&tris, &ids, &spheres, &sphere_ids, false);
        assert_eq!((flat.inner, flat.blocks.len()), (1, 3));
        assert_eq!(every.inner, every.blocks.len());
        let mut rng = Pcg32::new(11, 3);
        // A point on a random surface and its normal.
        let surface = |rng: &mut Pcg32| {
            let k = (rng.next_f32() * 17.0) as usize;
            let (u, v) = (rng.next_f32(), rng.next_f32());
            if k >= tris.len() {
                let s = spheres[0];
                let z = 1.0 - 2.0 * u;
                let r = (1.0 - z * z).max(0.0).sqrt();
                let phi = std::f32::consts::TAU * v;
                let n = Vec3::new(r * phi.cos(), r * phi.sin(), z);
                return (s.center + n * s.radius, n);
            }
            let t = tris[k];
            let (u, v) = if u + v > 1.0 {
                (1.0 - u, 1.0 - v)
            } else {
                (u, v)
            };
            let n = (t[1] - t[0]).cross(t[2] - t[0]).normalize();
            (t[0] + (t[1] - t[0]) * u + (t[2] - t[0]) * v, n)
        };
        let bits =
            |h: Option<FlatHit>| h.map(|(p, t, b)| (p, t.to_bits(), b.x.to_bits(), b.y.to_bits()));
        let (mut clear, mut blocked, mut open) = (0, 0, 0);
        for i in 0..20_000 {
            let (from, n_from) = surface(&mut rng);
            let (to, n_to) = match i % 4 {
                // The camera, before the open front; above the ceiling.
                0 => (Vec3::new(0.3 * rng.next_f32(), 1.0, 5.0), Vec3::ZERO),
                1 if i % 8 == 1 => (Vec3::new(0.0, 3.0, 0.2), Vec3::ZERO),
                _ => surface(&mut rng),
            };
            let Some(mut ray) = Ray::between(from, n_from, to, n_to) else {
                continue;
            };
            if i % 16 == 2 {
                ray.tmax = f32::INFINITY;
            }
            clear += flat.hull.clear(ray.o, ray.d, ray.tmax) as u32;
            let occluded = every.occluded_any(&ray);
            let closest = bits(every.intersect_any(&ray));
            blocked += occluded as u32;
            open += !occluded as u32;
            assert_eq!(flat.occluded_any(&ray), occluded, "ray {i}");
            assert_eq!(bits(flat.intersect_any(&ray)), closest, "ray {i}");
            #[cfg(target_arch = "x86_64")]
            {
                assert_eq!(
                    flat.hull.clear(ray.o, ray.d, ray.tmax),
                    // SAFETY: omis requires AVX2 (`wide_queries_equal_the_portable_ones`).
                    unsafe { flat.hull.clear_avx2(ray.o, ray.d, ray.tmax) },
                    "ray {i}"
                );
                // SAFETY: as above.
                unsafe {
                    assert_eq!(flat.occluded_avx2(&ray), occluded, "ray {i}, AVX2");
                    assert_eq!(bits(flat.intersect_avx2(&ray)), closest, "ray {i}, AVX2");
                }
                if flat.isa == Isa::Avx512 {
                    // SAFETY: the processor has AVX-512 (`detect_isa`).
                    unsafe {
                        assert_eq!(flat.occluded_avx512(&ray), occluded, "ray {i}, AVX-512");
                        assert_eq!(bits(flat.intersect_avx512(&ray)), closest, "ray {i}");
                    }
                }
            }
        }
        assert!(
            clear > 10_000 && blocked > 2_000 && open > 10_000,
            "{clear} clear of the boundary, {blocked} blocked, {open} open"
        );
    }
}
