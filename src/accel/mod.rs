//! Ray queries over triangles and spheres with an obvhs compressed wide BVH (CWBVH).
//!
//! Triangles are stored in BVH order in the precomputed form obvhs intersects fastest; spheres
//! follow them. A primitive is named by its index in the scene's own lists ([`Prim`]).

use crate::geometry::{Ray, Vec2, Vec3};
use obvhs::{
    Boundable, BvhBuildParams,
    aabb::Aabb,
    cwbvh::{CwBvh, builder::build_cwbvh},
    ray::{Ray as BvhRay, RayHit},
    rt_triangle::RtTriangle,
};
use std::time::{Duration, Instant};

/// A primitive of the scene: triangle `i` or sphere `i`, indices into the scene's lists.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Prim {
    Triangle(u32),
    Sphere(u32),
}

/// Analytic sphere as the BVH sees it.
#[derive(Clone, Copy, Debug)]
pub struct SphereGeom {
    pub center: Vec3,
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
    pub prim: Prim,
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
    pub primitives: usize,
    pub seconds: f64,
}

pub struct Accel {
    bvh: CwBvh,
    /// Triangles in BVH leaf order (obvhs' `primitive_indices` resolved once).
    tris: Vec<RtTriangle>,
    /// Per BVH slot: the scene primitive it stands for.
    slots: Vec<Prim>,
    spheres: Vec<SphereGeom>,
    /// Per BVH slot holding a sphere: its index in `spheres`.
    sphere_slot: Vec<u32>,
    pub stats: BuildStats,
}

impl Accel {
    /// `triangles[i]` are the world-space vertices of scene triangle `tri_ids[i]`; likewise spheres.
    pub fn build(
        triangles: &[[Vec3; 3]],
        tri_ids: &[u32],
        spheres: &[SphereGeom],
        sphere_ids: &[u32],
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
        let bvh = if n == 0 {
            CwBvh::default()
        } else {
            build_cwbvh(
                &bounds,
                BvhBuildParams::medium_build(),
                &mut Duration::default(),
            )
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
        Accel {
            bvh,
            tris,
            slots,
            spheres: sphere_geoms,
            sphere_slot,
            stats: BuildStats {
                primitives: n,
                seconds: start.elapsed().as_secs_f64(),
            },
        }
    }

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

    /// Closest hit in [tmin, tmax].
    pub fn intersect(&self, ray: &Ray) -> Option<AccelHit> {
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
                let hr = BvhRay::new(r.origin, r.direction, r.tmin, r.tmax);
                let b = self.tris[slot].compute_barycentric(&hr);
                Vec2::new(b.x, b.y)
            }
            Prim::Sphere(_) => Vec2::ZERO,
        };
        Some(AccelHit {
            prim: self.slots[slot],
            t: hit.t,
            bary,
        })
    }

    /// True when something lies on the ray within [tmin, tmax] (early exit).
    pub fn occluded(&self, ray: &Ray) -> bool {
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
