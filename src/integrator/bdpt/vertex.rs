//! The subpath vertex: where a walk hit, its BSDF, its densities in both directions and its
//! continuation probability, and the compact form in which light subpaths are kept.

use crate::geometry::{Rgb, Vec2, Vec3};
use crate::material::{Bsdf, Outgoing};
use crate::scene::{NO_LIGHT, Scene};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Kind {
    Camera,
    Light,
    Surface,
}

/// A subpath vertex.
#[derive(Clone, Copy, Debug)]
pub struct Vertex {
    pub(super) kind: Kind,
    pub(super) p: Vec3,
    /// Geometric normal (oriented emitting side for light vertices; zero for points).
    pub(super) ng: Vec3,
    /// Shading normal.
    pub(super) ns: Vec3,
    pub(super) bsdf: Bsdf,
    /// The direction toward the predecessor in the subpath, made ready for the BSDF's queries
    /// (zero at the endpoints): every connection from here evaluates the BSDF with it.
    pub(super) wo: Outgoing,
    /// Light index (light vertices and emissive surfaces), else NO_LIGHT.
    pub(super) light: u32,
    /// Throughput up to and including this vertex's generation (f / p of the subpath so far).
    /// For a light vertex: 1 / (pmf * pdf_pos).
    pub(super) beta: Rgb,
    /// Area density of this vertex from its predecessor in its subpath (with the predecessor's
    /// continuation probability `q`).
    pub(super) pdf_fwd: f32,
    /// Area density of this vertex from its successor, without the successor's continuation
    /// probability: which one applies depends on the technique (`continuation_at`).
    pub(super) pdf_rev: f32,
    /// Probability that this subpath continued from this vertex (Russian roulette; 1 without it,
    /// before the roulette's start and at the endpoints): a factor of every density its walk
    /// samples from here.
    pub(super) q: f32,
    /// The vertex's continuation probability at any index past the roulette's start: its BSDF's
    /// albedo estimate with roulette on, else 1. The q of this vertex when a technique's other
    /// subpath would have sampled from it there.
    pub(super) rr: f32,
    /// Specular (delta) BSDF: no connection can be made here.
    pub(super) delta: bool,
    /// Point light: a delta in position, never hit.
    pub(super) delta_pos: bool,
    /// The surface's material ([`NO_MATERIAL`] for the camera and light endpoints) and uv: what
    /// the BSDF was made from, so that a stored vertex can make it again.
    pub(super) material: u32,
    pub(super) uv: Vec2,
}

/// The material of a path endpoint (camera or light vertex): its BSDF is black.
const NO_MATERIAL: u32 = u32::MAX;

impl Vertex {
    pub(super) fn endpoint(kind: Kind, p: Vec3, n: Vec3, beta: Rgb, pdf_fwd: f32) -> Vertex {
        Vertex {
            kind,
            p,
            ng: n,
            ns: n,
            bsdf: Bsdf::new_black(),
            wo: Outgoing::default(),
            light: NO_LIGHT,
            beta,
            pdf_fwd,
            pdf_rev: 0.0,
            q: 1.0,
            rr: 1.0,
            delta: false,
            delta_pos: false,
            material: NO_MATERIAL,
            uv: Vec2::ZERO,
        }
    }

    /// The vertex without its BSDF and outgoing direction (80 bytes instead of 208), for keeping
    /// many light subpaths.
    pub(crate) fn stored(&self) -> StoredVertex {
        debug_assert_eq!(
            self.q, self.rr,
            "kept subpaths have roulette from vertex 1 or none"
        );
        StoredVertex {
            p: self.p,
            ng: self.ng,
            ns: self.ns,
            beta: self.beta,
            uv: self.uv,
            pdf_fwd: self.pdf_fwd,
            pdf_rev: self.pdf_rev,
            q: self.q,
            material: self.material,
            light: self.light,
            delta_pos: self.delta_pos,
        }
    }

    /// |cos| between `w` and the geometric normal, 1 for points (camera, point lights).
    #[inline]
    pub(crate) fn abs_cos_ng(&self, w: Vec3) -> f32 {
        if self.ng == Vec3::ZERO {
            1.0
        } else {
            self.ng.dot(w).abs()
        }
    }

    /// Position.
    pub(crate) fn position(&self) -> Vec3 {
        self.p
    }

    /// Throughput up to and including this vertex's generation.
    pub(crate) fn throughput(&self) -> Rgb {
        self.beta
    }

    /// The vertex's BSDF.
    pub(crate) fn bsdf(&self) -> &Bsdf {
        &self.bsdf
    }

    /// The direction toward the predecessor, made ready for the BSDF (zero at the endpoints).
    pub(crate) fn outgoing(&self) -> &Outgoing {
        &self.wo
    }

    /// Area density of this vertex from its predecessor in its subpath.
    pub(crate) fn pdf_fwd(&self) -> f32 {
        self.pdf_fwd
    }

    /// Specular BSDF.
    pub(crate) fn is_delta(&self) -> bool {
        self.delta
    }

    /// Probability that a subpath continues from here (1 without roulette).
    pub(crate) fn continuation(&self) -> f32 {
        self.q
    }

    /// Black BSDF (nothing scatters here).
    pub(crate) fn is_black(&self) -> bool {
        self.bsdf.is_black()
    }

    /// Geometric normal.
    pub(crate) fn normal(&self) -> Vec3 {
        self.ng
    }

    /// Shading normal.
    pub(crate) fn shading_normal(&self) -> Vec3 {
        self.ns
    }

    /// The light this vertex lies on, or NO_LIGHT.
    pub(crate) fn light_index(&self) -> u32 {
        self.light
    }

    /// A point light (a delta in position).
    pub(crate) fn is_point(&self) -> bool {
        self.delta_pos
    }

    /// Converts the solid-angle density with which a subpath continuing from `self` samples the
    /// direction toward `next` into an area density at `next`, times `self.q` (the walk must
    /// survive roulette here to sample it at all).
    #[inline]
    pub(crate) fn area_density(self, pdf_dir: f32, next: &Vertex) -> f32 {
        self.q * self.to_area(pdf_dir, next)
    }

    /// Converts a solid-angle density at `self` toward `next` into an area density at `next`,
    /// without `self.q`: for a light point that next-event estimation from `self` picks.
    #[inline]
    pub(crate) fn to_area(self, pdf_dir: f32, next: &Vertex) -> f32 {
        let d = next.p - self.p;
        let dist2 = d.length_squared();
        if !(dist2 > 0.0) {
            return 0.0;
        }
        if next.delta_pos {
            return 0.0; // a point cannot be hit
        }
        let w = d / dist2.sqrt();
        pdf_dir * next.abs_cos_ng(w) / dist2
    }
}

/// A light subpath vertex as [`Vertex::stored`] keeps it: the BSDF is made again from the
/// material and uv ([`StoredVertex::load`]), the same bits as the one the random walk made.
#[derive(Clone, Copy, Debug)]
pub(crate) struct StoredVertex {
    p: Vec3,
    ng: Vec3,
    ns: Vec3,
    beta: Rgb,
    uv: Vec2,
    pdf_fwd: f32,
    pdf_rev: f32,
    q: f32,
    material: u32,
    light: u32,
    delta_pos: bool,
}

const _: () = assert!(std::mem::size_of::<StoredVertex>() == 80);

impl StoredVertex {
    /// Position.
    pub(crate) fn position(&self) -> Vec3 {
        self.p
    }

    /// Area density of this vertex from its predecessor in its subpath.
    pub(crate) fn pdf_fwd(&self) -> f32 {
        self.pdf_fwd
    }

    /// The vertex again; `first` for y_0 (on the light), else a surface vertex.
    pub(crate) fn load(&self, scene: &Scene, first: bool) -> Vertex {
        let bsdf = if self.material == NO_MATERIAL {
            Bsdf::new_black()
        } else {
            Bsdf::new(
                &scene.materials[self.material as usize],
                self.ng,
                self.ns,
                self.uv,
            )
        };
        Vertex {
            kind: if first { Kind::Light } else { Kind::Surface },
            p: self.p,
            ng: self.ng,
            ns: self.ns,
            bsdf,
            wo: Outgoing::default(),
            light: self.light,
            beta: self.beta,
            pdf_fwd: self.pdf_fwd,
            pdf_rev: self.pdf_rev,
            q: self.q,
            // VCM and BPM keep subpaths, and their roulette starts at vertex 1 (or is off), where
            // a vertex's q is its rr (`stored` checks it).
            rr: self.q,
            delta: !first && bsdf.is_delta(),
            delta_pos: self.delta_pos,
            material: self.material,
            uv: self.uv,
        }
    }
}

/// The continuation probability of `v` as vertex `index` of a subpath whose roulette starts at
/// vertex `from` (1 before it). A technique's density at a vertex carries the q of the vertex
/// that sampled it in that technique's subpaths, and x_j of a path of k vertices is light vertex
/// j but camera vertex k - 1 - j: with a start past vertex 1 the two differ near the ends.
#[inline]
pub(super) fn continuation_at(v: &Vertex, index: usize, from: usize) -> f32 {
    if index >= from { v.rr } else { 1.0 }
}

/// Unit direction and squared distance from `a` to `b`.
#[inline]
pub(crate) fn dir_to(a: Vec3, b: Vec3) -> (Vec3, f32) {
    let d = b - a;
    let d2 = d.length_squared();
    (d / d2.sqrt(), d2)
}
