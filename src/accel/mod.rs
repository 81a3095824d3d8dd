//! Ray queries over triangles and spheres with an obvhs compressed wide BVH (CWBVH).
//!
//! Triangles are stored in BVH order in the precomputed form obvhs intersects fastest; spheres
//! follow them. A primitive is named by its index in the scene's own lists ([`Prim`]).
//!
//! In the flow scene -> accel -> integrator: [`SceneBuilder::build`](crate::scene::SceneBuilder::build)
//! builds one BVH over every primitive and one over the emitters; integrators query them only
//! through [`Scene`](crate::scene::Scene) (`intersect`, `occluded`, `light_pdf_dir`), and
//! `omis bench` measures the bare ray rates.

mod flat;
mod hull;

use crate::geometry::{Ray, Vec2, Vec3, Vec3A};
use obvhs::{
    Boundable, BvhBuildParams,
    aabb::Aabb,
    bvh2::{Bvh2, node::Bvh2Node, reinsertion::ReinsertionOptimizer},
    cwbvh::{CwBvh, builder::build_cwbvh, bvh2_to_cwbvh::bvh2_to_cwbvh},
    ploc::PlocBuilder,
    ray::{Ray as BvhRay, RayHit},
    rt_triangle::RtTriangle,
};
use std::time::{Duration, Instant};

/// A primitive of the scene: triangle `i` or sphere `i`, indices into the scene's lists.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Prim {
    /// Index into the scene's triangles.
    Triangle(u32),
    /// Index into the scene's spheres.
    Sphere(u32),
}

/// Analytic sphere as the BVH sees it.
#[derive(Clone, Copy, Debug)]
pub struct SphereGeom {
    /// Centre in world space.
    pub center: Vec3,
    /// Radius.
    pub radius: f32,
}

impl SphereGeom {
    /// Both roots of |o + t d - c| = r (d unit), ordered; `None` when the line misses.
    /// Uses the numerically stable form of Hearn & Baker / Ray Tracing Gems ch. 7.
    #[inline]
    pub fn roots(&self, o: Vec3, d: Vec3) -> Option<(f32, f32)> {
        let f = o - self.center;
        let b = -f.dot(d);
        let c = f.length_squared() - self.radius * self.radius;
        let l = f + b * d;
        let disc = self.radius * self.radius - l.length_squared();
        if disc < 0.0 {
            return None;
        }
        let q = b + b.signum() * disc.sqrt();
        if q == 0.0 {
            return Some((0.0, 0.0));
        }
        let t0 = c / q;
        let t1 = q;
        Some(if t0 < t1 { (t0, t1) } else { (t1, t0) })
    }

    /// Nearest root inside [tmin, tmax], or infinity.
    #[inline]
    pub fn intersect(&self, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> f32 {
        match self.roots(o, d) {
            Some((t0, t1)) => {
                if t0 >= tmin && t0 <= tmax {
                    t0
                } else if t1 >= tmin && t1 <= tmax {
                    t1
                } else {
                    f32::INFINITY
                }
            }
            None => f32::INFINITY,
        }
    }

    fn aabb(&self) -> Aabb {
        let r = Vec3::splat(self.radius);
        Aabb::new((self.center - r).into(), (self.center + r).into())
    }
}

/// What a closest-hit query returns.
#[derive(Clone, Copy, Debug)]
pub struct AccelHit {
    /// The primitive hit.
    pub prim: Prim,
    /// Distance along the ray.
    pub t: f32,
    /// Barycentrics (b1, b2) of vertices 1 and 2 for triangles; zero for spheres.
    pub bary: Vec2,
}

struct BoundsOnly(Aabb);

impl Boundable for BoundsOnly {
    fn aabb(&self) -> Aabb {
        self.0
    }
}

/// Build statistics, for benchmarks and the render summary.
#[derive(Clone, Copy, Debug, Default)]
pub struct BuildStats {
    /// Primitives in the BVH.
    pub primitives: usize,
    /// Build time in seconds.
    pub seconds: f64,
    /// Levels of the wide BVH (root = 1; 0 when empty).
    pub depth: usize,
    /// Primitives built into balanced subtrees of coincident groups (see [`COINCIDENT_MIN`]).
    pub coincident: usize,
}

/// Groups of at least this many primitives whose bounds have one centroid are kept out of PLOC
/// and built into balanced subtrees of their own. PLOC (Meister & Bittner 2018) merges two nodes
/// only when each is the other's nearest neighbour in Morton order. Equal centroids share a Morton
/// code, and equal (or nested) bounds make every neighbour equally near (or the smaller one
/// nearer): ties go one way, so only one pair of such a run agrees per iteration, the run of k
/// needs k iterations over all nodes (O(n k) time: 30,000 copies of a triangle took 22 s) and
/// its parents, as large as their children, form a chain k deep, which overflows the recursive
/// BVH2 -> CWBVH conversion and the 32-entry traversal stack. Shorter runs cost little, and
/// leaving them alone keeps the BVH (and so the images) of ordinary scenes exactly as PLOC builds
/// them.
pub const COINCIDENT_MIN: usize = 16;

/// Primitives sorted by their bounds' centroid, split into the runs of equal centroid with at
/// least [`COINCIDENT_MIN`] members (each run in index order). Primitives with non-finite bounds
/// are returned apart: they cannot be hit, and PLOC needs finite bounds.
fn coincident_groups(bounds: &[BoundsOnly]) -> (Vec<Vec<u32>>, Vec<u32>) {
    let key = |i: u32| {
        let b = &bounds[i as usize].0;
        let c = b.min + b.max;
        (c.x.to_bits(), c.y.to_bits(), c.z.to_bits())
    };
    let finite = |i: u32| {
        let b = &bounds[i as usize].0;
        b.min.is_finite() && b.max.is_finite()
    };
    let (mut order, bad): (Vec<u32>, Vec<u32>) = (0..bounds.len() as u32).partition(|&i| finite(i));
    order.sort_unstable_by_key(|&i| (key(i), i));
    let mut groups = Vec::new();
    let mut start = 0;
    while start < order.len() {
        let k = key(order[start]);
        let mut end = start + 1;
        while end < order.len() && key(order[end]) == k {
            end += 1;
        }
        if end - start >= COINCIDENT_MIN {
            groups.push(order[start..end].to_vec());
        }
        start = end;
    }
    (groups, bad)
}

/// PLOC + reinsertion + CWBVH conversion as `build_cwbvh` does them, over `bounds` in which each
/// coincident group of `groups` stands as one proxy; each proxy leaf then becomes a balanced
/// subtree of its group (median split of the members ordered by surface area, so nested bounds
/// stay together), O(k log k) for k members and log2(k) levels deep.
fn build_grouped(
    bounds: &[BoundsOnly],
    groups: &[Vec<u32>],
    excluded: &[u32],
    params: BvhBuildParams,
) -> CwBvh {
    let mut grouped = vec![false; bounds.len()];
    for &i in groups.iter().flatten().chain(excluded) {
        grouped[i as usize] = true;
    }
    // Proxy p stands for members[p]: a single primitive, or a whole group.
    let mut members: Vec<Vec<u32>> = (0..bounds.len() as u32)
        .filter(|&i| !grouped[i as usize])
        .map(|i| vec![i])
        .collect();
    for g in groups {
        let mut g = g.clone();
        g.sort_by(|&a, &b| {
            let (ha, hb) = (
                bounds[a as usize].0.half_area(),
                bounds[b as usize].0.half_area(),
            );
            ha.total_cmp(&hb).then(a.cmp(&b))
        });
        members.push(g);
    }
    if members.is_empty() {
        return CwBvh::default();
    }
    let union = |m: &[u32]| {
        m.iter()
            .fold(Aabb::empty(), |acc, &i| acc.union(&bounds[i as usize].0))
    };
    let proxies: Vec<BoundsOnly> = members.iter().map(|m| BoundsOnly(union(m))).collect();
    let mut bvh2 = PlocBuilder::with_capacity(proxies.len()).build(
        params.ploc_search_distance,
        &proxies,
        (0..proxies.len() as u32).collect(),
        params.sort_precision,
        params.search_depth_threshold,
    );
    ReinsertionOptimizer::default().run(&mut bvh2, params.reinsertion_batch_ratio, None);
    // Expand the proxy leaves; leaves index `prims`, which names the scene's primitives.
    let mut prims: Vec<u32> = Vec::with_capacity(bounds.len());
    let mut work: Vec<(usize, usize, usize, usize)> = Vec::new(); // (node, proxy, lo, hi)
    for node in 0..bvh2.nodes.len() {
        let n = bvh2.nodes[node];
        if !n.is_leaf() {
            continue;
        }
        let proxy = bvh2.primitive_indices[n.first_index as usize] as usize;
        work.push((node, proxy, 0, members[proxy].len()));
        while let Some((node, proxy, lo, hi)) = work.pop() {
            let m = &members[proxy][lo..hi];
            if m.len() == 1 {
                bvh2.nodes[node] = Bvh2Node::new(bounds[m[0] as usize].0, 1, prims.len() as u32);
                prims.push(m[0]);
                continue;
            }
            let first = bvh2.nodes.len();
            bvh2.nodes[node] = Bvh2Node::new(union(m), 0, first as u32);
            let mid = lo + m.len() / 2;
            let placeholder = Bvh2Node::new(Aabb::empty(), 1, 0);
            bvh2.nodes.push(placeholder);
            bvh2.nodes.push(placeholder);
            work.push((first + 1, proxy, mid, hi));
            work.push((first, proxy, lo, mid));
        }
    }
    bvh2.primitive_indices = prims;
    bvh2.parents.clear();
    bvh2.primitives_to_nodes.clear();
    bvh2.max_depth = bvh2.max_depth.max(bvh2_depth(&bvh2));
    bvh2_to_cwbvh(&bvh2, params.max_prims_per_leaf.clamp(1, 3), true, false)
}

/// Levels of a BVH2 (iteratively: the tree may be degenerate).
fn bvh2_depth(bvh: &Bvh2) -> usize {
    if bvh.nodes.is_empty() {
        return 0;
    }
    let mut deepest = 0;
    let mut stack = vec![(0usize, 1usize)];
    while let Some((i, d)) = stack.pop() {
        deepest = deepest.max(d);
        let n = &bvh.nodes[i];
        if !n.is_leaf() {
            stack.push((n.first_index as usize, d + 1));
            stack.push((n.first_index as usize + 1, d + 1));
        }
    }
    deepest
}

/// Levels of a CWBVH: the `imask` internal children of a node are stored consecutively from
/// `child_base_idx` (the node format of Ylitie et al. 2017).
fn cwbvh_depth(bvh: &CwBvh) -> usize {
    if bvh.nodes.is_empty() {
        return 0;
    }
    let mut deepest = 0;
    let mut stack = vec![(0usize, 1usize)];
    while let Some((i, d)) = stack.pop() {
        deepest = deepest.max(d);
        let n = &bvh.nodes[i];
        for k in 0..n.imask.count_ones() as usize {
            stack.push((n.child_base_idx as usize + k, d + 1));
        }
    }
    deepest
}

/// Scenes of at most this many primitives answer closest-hit and occlusion queries by testing
/// every primitive, eight triangles at a time, instead of traversing the BVH: on 10-36 triangles
/// 1.1-1.5x the closest-hit rate and 1.3-2.1x the occlusion rate; at 52 triangles and 4 spheres
/// the BVH is faster (BENCHMARKS.md, "Rendering speed").
pub const FLAT_MAX: usize = 40;

/// The BVH over a scene's triangles and spheres, answering closest-hit and occlusion queries.
pub struct Accel {
    bvh: CwBvh,
    /// Small scenes: every primitive in a flat list, which answers `intersect` and `occluded`.
    flat: Option<flat::Flat>,
    /// Triangles in BVH leaf order (obvhs' `primitive_indices` resolved once).
    tris: Vec<RtTriangle>,
    /// Per BVH slot: the scene primitive it stands for.
    slots: Vec<Prim>,
    spheres: Vec<SphereGeom>,
    /// Per BVH slot holding a sphere: its index in `spheres`.
    sphere_slot: Vec<u32>,
    /// How the build went.
    pub stats: BuildStats,
}

impl Accel {
    /// `triangles[i]` are the world-space vertices of scene triangle `tri_ids[i]`; likewise
    /// spheres. Scenes of at most [`FLAT_MAX`] primitives are queried flat.
    pub fn build(
        triangles: &[[Vec3; 3]],
        tri_ids: &[u32],
        spheres: &[SphereGeom],
        sphere_ids: &[u32],
    ) -> Accel {
        let flat = triangles.len() + spheres.len() <= FLAT_MAX;
        Accel::build_with(triangles, tri_ids, spheres, sphere_ids, flat)
    }

    /// As [`Accel::build`], with the choice between flat queries and BVH traversal made by the
    /// caller (`omis bench` measures both; tests compare them).
    pub fn build_with(
        triangles: &[[Vec3; 3]],
        tri_ids: &[u32],
        spheres: &[SphereGeom],
        sphere_ids: &[u32],
        flat: bool,
    ) -> Accel {
        let start = Instant::now();
        let mut bounds: Vec<BoundsOnly> = Vec::with_capacity(triangles.len() + spheres.len());
        for t in triangles {
            bounds.push(BoundsOnly(Aabb::from_points(&[
                t[0].into(),
                t[1].into(),
                t[2].into(),
            ])));
        }
        for s in spheres {
            bounds.push(BoundsOnly(s.aabb()));
        }
        let n = bounds.len();
        let params = BvhBuildParams::medium_build();
        let (groups, excluded) = coincident_groups(&bounds);
        let bvh = if n == 0 {
            CwBvh::default()
        } else if groups.is_empty() && excluded.is_empty() {
            build_cwbvh(&bounds, params, &mut Duration::default())
        } else {
            build_grouped(&bounds, &groups, &excluded, params)
        };
        let mut tris = Vec::with_capacity(bvh.primitive_indices.len());
        let mut slots = Vec::with_capacity(bvh.primitive_indices.len());
        let mut sphere_geoms = Vec::new();
        for &pi in &bvh.primitive_indices {
            let pi = pi as usize;
            if pi < triangles.len() {
                let t = triangles[pi];
                tris.push(RtTriangle::new(t[0].into(), t[1].into(), t[2].into()));
                slots.push(Prim::Triangle(tri_ids[pi]));
            } else {
                let k = pi - triangles.len();
                tris.push(RtTriangle::default());
                sphere_geoms.push(spheres[k]);
                slots.push(Prim::Sphere(sphere_ids[k]));
            }
        }
        let mut sphere_slot = vec![u32::MAX; slots.len()];
        let mut k = 0u32;
        for (slot, p) in slots.iter().enumerate() {
            if let Prim::Sphere(_) = p {
                sphere_slot[slot] = k;
                k += 1;
            }
        }
        let depth = cwbvh_depth(&bvh);
        let flat = flat.then(|| flat::Flat::new(triangles, tri_ids, spheres, sphere_ids));
        Accel {
            bvh,
            flat,
            tris,
            slots,
            spheres: sphere_geoms,
            sphere_slot,
            stats: BuildStats {
                primitives: n,
                seconds: start.elapsed().as_secs_f64(),
                depth,
                coincident: groups.iter().map(Vec::len).sum(),
            },
        }
    }

    /// True when the BVH holds no primitive.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    #[inline]
    fn to_bvh_ray(ray: &Ray) -> BvhRay {
        BvhRay::new(ray.o.into(), ray.d.into(), ray.tmin, ray.tmax)
    }

    #[inline]
    fn intersect_slot(&self, r: &BvhRay, slot: usize) -> f32 {
        match self.slots[slot] {
            Prim::Triangle(_) => self.tris[slot].intersect(r),
            Prim::Sphere(_) => {
                let s = &self.spheres[self.sphere_slot[slot] as usize];
                s.intersect(r.origin.into(), r.direction.into(), r.tmin, r.tmax)
            }
        }
    }

    /// Whether queries test every primitive (a scene of at most [`FLAT_MAX`] primitives) rather
    /// than traverse the BVH.
    pub fn is_flat(&self) -> bool {
        self.flat.is_some()
    }

    /// Closest hit in [tmin, tmax).
    pub fn intersect(&self, ray: &Ray) -> Option<AccelHit> {
        if let Some(f) = &self.flat {
            return f
                .intersect(ray)
                .map(|(prim, t, bary)| AccelHit { prim, t, bary });
        }
        if self.slots.is_empty() {
            return None;
        }
        let r = Self::to_bvh_ray(ray);
        let mut hit = RayHit::none();
        if !self
            .bvh
            .ray_traverse(r, &mut hit, |r, slot| self.intersect_slot(r, slot))
        {
            return None;
        }
        let slot = hit.primitive_id as usize;
        let bary = match self.slots[slot] {
            Prim::Triangle(_) => {
                // The flat queries' barycentrics, so that both report the same hit.
                let t = &self.tris[slot];
                let v = |a: Vec3A| Vec3::from(a);
                flat::barycentrics(v(t.v0), v(t.e1), v(t.e2), v(t.ng), ray.o, ray.d)
            }
            Prim::Sphere(_) => Vec2::ZERO,
        };
        Some(AccelHit {
            prim: self.slots[slot],
            t: hit.t,
            bary,
        })
    }

    /// True when something lies on the ray within [tmin, tmax) (early exit).
    pub fn occluded(&self, ray: &Ray) -> bool {
        if let Some(f) = &self.flat {
            return f.occluded(ray);
        }
        if self.slots.is_empty() {
            return false;
        }
        let r = Self::to_bvh_ray(ray);
        !self
            .bvh
            .ray_traverse_miss(r, |r, slot| self.intersect_slot(r, slot))
    }

    /// Calls `f(prim)` once for every primitive whose bounds the ray crosses (candidates: the
    /// callback does its own exact test). Primitives appear once: no spatial splits are used.
    pub fn for_each_candidate(&self, ray: &Ray, mut f: impl FnMut(Prim)) {
        if self.slots.is_empty() {
            return;
        }
        let r = Self::to_bvh_ray(ray);
        self.bvh
            .ray_traverse_anyhit(r, |_, slot| f(self.slots[slot]));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::Pcg32;

    /// A test scene of small scattered triangles, a quad split along its diagonal (rays through
    /// the diagonal hit two triangles at once) and three spheres, with ids, and 40 000 rays:
    /// every tenth aims at the quad's diagonal, every second is a segment ending at its target.
    pub(super) struct TestScene {
        pub tris: Vec<[Vec3; 3]>,
        pub ids: Vec<u32>,
        pub spheres: Vec<SphereGeom>,
        pub sphere_ids: [u32; 3],
        pub rays: Vec<Ray>,
    }

    pub(super) fn test_scene() -> TestScene {
        let mut rng = Pcg32::new(7, 1);
        let mut p = |s: f32| Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * s;
        let mut tris: Vec<[Vec3; 3]> = (0..45)
            .map(|_| {
                let c = p(4.0);
                [c, c + p(1.0), c + p(1.0)]
            })
            .collect();
        let q = [
            Vec3::ZERO,
            Vec3::X * 4.0,
            Vec3::new(4.0, 4.0, 0.0),
            Vec3::Y * 4.0,
        ];
        tris.push([q[0], q[1], q[2]]);
        tris.push([q[0], q[2], q[3]]);
        let ids: Vec<u32> = (0..tris.len() as u32).map(|i| 100 + i).collect();
        let spheres: Vec<SphereGeom> = (0..3)
            .map(|_| SphereGeom {
                center: p(4.0),
                radius: 0.5,
            })
            .collect();
        let rays = (0..40_000)
            .map(|i| {
                let o = p(6.0) - Vec3::splat(1.0);
                let target = if i % 10 == 0 {
                    let u = p(1.0).x;
                    Vec3::new(4.0 * u, 4.0 * u, 0.0)
                } else {
                    p(4.0)
                };
                let tmax = if i % 2 == 0 {
                    f32::INFINITY
                } else {
                    (target - o).length()
                };
                Ray {
                    o,
                    d: (target - o).normalize(),
                    tmin: 1e-3,
                    tmax,
                }
            })
            .collect();
        TestScene {
            tris,
            ids,
            spheres,
            sphere_ids: [7, 8, 9],
            rays,
        }
    }

    /// Flat queries and BVH traversal find the same distance, bit for bit, and the same
    /// primitive unless two primitives lie at that distance (a shared edge); occlusion agrees.
    #[test]
    fn flat_queries_equal_bvh_traversal() {
        let sc = test_scene();
        let build = |flat| Accel::build_with(&sc.tris, &sc.ids, &sc.spheres, &sc.sphere_ids, flat);
        let (flat, bvh) = (build(true), build(false));
        assert!(flat.is_flat() && !bvh.is_flat());
        let (mut hits, mut ties, mut blocked) = (0, 0, 0);
        for (i, ray) in sc.rays.iter().enumerate() {
            let (a, b) = (flat.intersect(ray), bvh.intersect(ray));
            assert_eq!(a.is_some(), b.is_some(), "ray {i}");
            assert_eq!(flat.occluded(ray), bvh.occluded(ray), "ray {i}");
            blocked += flat.occluded(ray) as u32;
            let (Some(a), Some(b)) = (a, b) else { continue };
            hits += 1;
            assert_eq!(a.t.to_bits(), b.t.to_bits(), "ray {i}");
            if a.prim != b.prim {
                ties += 1;
            } else {
                assert_eq!(a.bary, b.bary, "ray {i}");
            }
        }
        assert!(
            hits > 10_000 && blocked > 10_000,
            "{hits} hits, {blocked} blocked"
        );
        assert!(ties < hits / 100, "{ties} ties of {hits} hits");
    }
}
