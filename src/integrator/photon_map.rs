//! The photon map of one VCM / BPM iteration: its light subpaths' vertices after the first
//! bounce that are not specular ([`Photon`]) in a hash grid ([`PhotonMap`]), the subpaths kept
//! so each is traced once per iteration, and the merge radius of the iteration.

use super::RenderSettings;
use super::bdpt::{self, StoredVertex, Workspace};
use crate::film::RayStats;
use crate::geometry::{Rgb, Vec3};
use crate::mis::{self, MisKind};
use crate::sampler::{Sampler, Stream};
use crate::scene::Scene;

/// Default initial radius, as a fraction of the scene's bounding-sphere radius (SmallVCM's
/// default, Davidovič and Georgiev).
pub const DEFAULT_RADIUS_FACTOR: f32 = 0.003;
/// Default radius reduction exponent alpha (Knaus and Zwicker 2011 §4.3 recommend 2/3 .. 0.75).
pub const DEFAULT_ALPHA: f32 = 0.75;

/// The merge radius of iteration `iteration`: r_0 (i + 1)^((alpha - 1) / 2), r_0 the setting or
/// by default `DEFAULT_RADIUS_FACTOR` times the scene's bounding-sphere radius.
pub fn radius(scene: &Scene, settings: &RenderSettings, iteration: u32) -> f32 {
    let r0 = if settings.radius > 0.0 {
        settings.radius
    } else {
        let (lo, hi) = scene.bounds();
        let r = 0.5 * (hi - lo).length();
        DEFAULT_RADIUS_FACTOR * if r.is_finite() && r > 0.0 { r } else { 1.0 }
    };
    let alpha = settings.radius_alpha as f64;
    (r0 as f64 * (iteration as f64 + 1.0).powf(0.5 * (alpha - 1.0))) as f32
}

/// A light vertex y_i (i >= 1, not specular) as merges use it: one 64-byte cache line, so that
/// a query's scan of a grid bucket reads everything an accepted photon needs.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Photon {
    /// The light side of a merge's weight is `light_a + light_b m(pE)`, pE the density with
    /// which the camera vertex's BSDF samples the direction toward y_{i-1}: the light subpath's
    /// partial sum S_i (see `Workspace::prepare`) over m(eta pL_i), completed with
    /// pE_{i-1} = pE |cos at y_{i-1}| / distance^2 (Georgiev et al. 2012, the dVCM / dVM terms).
    pub(super) light_a: f64,
    pub(super) light_b: f64,
    /// Position.
    pub p: Vec3,
    /// Unit direction toward y_{i-1} (the direction the light arrived from).
    pub wi: Vec3,
    /// Throughput of the light subpath up to y_i (f / p).
    pub beta: Rgb,
    /// Index of y_i in the map's kept subpaths (y_{i-1} precedes it).
    vertex: u32,
    /// i: the vertex's index in its light subpath (edges from the light).
    pub index: u32,
    /// Whether y_1 .. y_{i-1} are all specular: a direct or caustic photon.
    pub caustic: bool,
}

/// The photons of one iteration in a hash grid (cells of 2 r, so that a query visits at most 8),
/// and the iteration's light subpaths.
pub struct PhotonMap {
    /// Photons, sorted by bucket (stable: in light-path order within a bucket).
    pub(super) photons: Vec<Photon>,
    /// Bucket b holds photons[start[b] .. start[b + 1]].
    start: Vec<u32>,
    /// Every light subpath's vertices; subpath k (pixel k in row-major order) is
    /// vertices[path_start[k] .. path_start[k + 1]].
    vertices: Vec<StoredVertex>,
    path_start: Vec<u32>,
    /// Frame width (pixels per row of subpaths).
    width: u32,
    lo: Vec3,
    inv_cell: f32,
    /// Merge radius of the iteration.
    pub radius: f32,
    /// eta = N_L pi r^2.
    pub eta: f64,
    /// Light subpaths traced (N_L).
    pub light_paths: u64,
    /// Mean over the light subpaths of the throughput reaching the first surface (luminance):
    /// an estimate of the flux the lights put into the scene.
    pub flux: f64,
    /// Rays traced to build the map.
    pub stats: RayStats,
}

impl PhotonMap {
    /// Traces the N_L light subpaths of iteration `iteration` (one per pixel, in row-major order),
    /// keeps them and stores their photons.
    pub fn build(scene: &Scene, settings: &RenderSettings, iteration: u32) -> PhotonMap {
        let (w, h) = (scene.camera.width, scene.camera.height);
        let max_depth = settings.max_depth.min(bdpt::MAX_DEPTH);
        let radius = radius(scene, settings, iteration);
        let light_paths = w as u64 * h as u64;
        let eta = light_paths as f64 * std::f64::consts::PI * (radius as f64).powi(2);
        let heuristic = heuristic(settings);
        let b = heuristic.beta();
        let eta_b = mis::ratio_term(eta, b);
        let mut ws = Workspace::default();
        ws.set_merging(eta);
        ws.set_roulette(settings.roulette_start());
        let mut stats = RayStats::default();
        let mut photons = Vec::new();
        let mut vertices = Vec::new();
        let mut path_start = Vec::with_capacity(light_paths as usize + 1);
        let mut flux = 0.0f64;
        for y in 0..h {
            for x in 0..w {
                let mut sampler = Sampler::new(
                    settings.sampler,
                    settings.seed,
                    x,
                    y,
                    iteration,
                    settings.sample_block,
                    Stream::Light,
                );
                bdpt::light_subpath(scene, &mut sampler, max_depth, &mut ws, &mut stats);
                ws.clear_camera();
                ws.prepare(scene, heuristic);
                let base = vertices.len() as u32;
                path_start.push(base);
                vertices.extend(ws.light_vertices().iter().map(|v| v.stored()));
                ws.photons(eta_b, b, base, &mut photons);
                if let Some(y1) = ws.light_vertices().get(1) {
                    flux += luminance(y1.throughput());
                }
            }
        }
        path_start.push(vertices.len() as u32);
        let mut map = PhotonMap {
            photons: Vec::new(),
            start: Vec::new(),
            vertices,
            path_start,
            width: w,
            lo: Vec3::ZERO,
            inv_cell: 1.0 / (2.0 * radius.max(f32::MIN_POSITIVE)),
            radius,
            eta,
            light_paths,
            flux: flux / light_paths.max(1) as f64,
            stats,
        };
        map.index(photons);
        map
    }

    /// Sorts `photons` into the hash grid (a counting sort, stable).
    fn index(&mut self, photons: Vec<Photon>) {
        let n = photons.len();
        let buckets = n.next_power_of_two().max(1);
        let lo = photons
            .iter()
            .fold(Vec3::splat(f32::INFINITY), |a, p| a.min(p.p));
        self.lo = if lo.is_finite() { lo } else { Vec3::ZERO };
        let keys: Vec<usize> = photons
            .iter()
            .map(|p| self.bucket(self.cell(p.p), buckets))
            .collect();
        let mut start = vec![0u32; buckets + 1];
        for &k in &keys {
            start[k + 1] += 1;
        }
        for b in 0..buckets {
            start[b + 1] += start[b];
        }
        // Where each photon goes, then the photons moved once (no second full copy to overwrite).
        let mut next = start.clone();
        let mut order = vec![0u32; n];
        for (i, &k) in keys.iter().enumerate() {
            order[next[k] as usize] = i as u32;
            next[k] += 1;
        }
        self.photons = order.iter().map(|&i| photons[i as usize]).collect();
        self.start = start;
    }

    fn cell(&self, p: Vec3) -> [i64; 3] {
        let c = ((p - self.lo) * self.inv_cell).floor();
        [c.x as i64, c.y as i64, c.z as i64]
    }

    fn bucket(&self, c: [i64; 3], buckets: usize) -> usize {
        // Teschner et al., "Optimized Spatial Hashing for Collision Detection of Deformable
        // Objects", VMV 2003: the primes of their hash.
        let h = (c[0].wrapping_mul(73_856_093))
            ^ (c[1].wrapping_mul(19_349_663))
            ^ (c[2].wrapping_mul(83_492_791));
        (h as u64 as usize) & (buckets - 1)
    }

    /// Number of photons.
    pub fn len(&self) -> usize {
        self.photons.len()
    }

    /// Whether the map holds no photon.
    pub fn is_empty(&self) -> bool {
        self.photons.is_empty()
    }

    /// Bytes the map occupies: photons, grid and light subpaths (what shipping it would cost,
    /// before compression).
    pub fn bytes(&self) -> usize {
        use std::mem::size_of;
        self.photons.len() * size_of::<Photon>()
            + self.vertices.len() * size_of::<StoredVertex>()
            + (self.start.len() + self.path_start.len()) * 4
    }

    /// The light subpath of pixel `pixel` (the one BDPT traces for that pixel sample).
    pub(crate) fn light_path(&self, pixel: (u32, u32)) -> &[StoredVertex] {
        let k = pixel.1 as usize * self.width as usize + pixel.0 as usize;
        &self.vertices[self.path_start[k] as usize..self.path_start[k + 1] as usize]
    }

    /// The density ratio pE_{i-1} / pL_i between merging photon `ph`'s path at y_{i-1} (one
    /// vertex nearer the light) and merging it at y_i, as a merge at y_i sees it: `pdf_dir` is
    /// the camera's solid-angle density there toward y_{i-1} (Georgiev et al. 2012: the two
    /// merges differ only in which subpath made the vertex between them). 0 where no merge can
    /// be made at y_{i-1}: it is the light, or specular.
    pub(crate) fn merge_nearer_light(&self, scene: &Scene, ph: &Photon, pdf_dir: f32) -> f64 {
        if ph.index < 2 {
            return 0.0;
        }
        let y = &self.vertices[ph.vertex as usize];
        let yp = self.vertices[ph.vertex as usize - 1].load(scene, false);
        let (wi, d2) = bdpt::dir_to(y.position(), yp.position());
        if yp.is_delta() || !(d2 > 0.0) || !(y.pdf_fwd() > 0.0) {
            return 0.0;
        }
        (pdf_dir * yp.abs_cos_ng(wi) / d2) as f64 / y.pdf_fwd() as f64
    }

    /// Calls `f(photon, scale)` for every photon within the radius of `p`, in a fixed order,
    /// with `scale` 1. Where the cells around `p` hold more than `MAX_MERGE_CANDIDATES` photons
    /// (a radius as large as the scene, or a scene whose bounding sphere dwarfs what the camera
    /// sees), only an evenly spaced `MAX_MERGE_CANDIDATES` of them are tested, from an offset
    /// hashed from `p`, each with `scale` = candidates / tested: every candidate is tested with
    /// probability 1 / scale, so the scaled sum keeps its expectation (systematic sampling), and
    /// a query's work stays bounded.
    pub(crate) fn query(&self, p: Vec3, mut f: impl FnMut(&Photon, f32)) {
        if self.photons.is_empty() {
            return;
        }
        let buckets = self.start.len() - 1;
        let c = (p - self.lo) * self.inv_cell;
        let base = c.floor();
        let frac = c - base;
        let mut cells = [0usize; 8];
        for (k, cell) in cells.iter_mut().enumerate() {
            let mut q = [base.x as i64, base.y as i64, base.z as i64];
            for (axis, qa) in q.iter_mut().enumerate() {
                if k >> axis & 1 == 1 {
                    *qa += if frac[axis] < 0.5 { -1 } else { 1 };
                }
            }
            *cell = self.bucket(q, buckets);
        }
        // Two cells may share a bucket: visit each bucket once.
        cells.sort_unstable();
        // The buckets' ranges first, then their photons' first cache lines asked for, before any
        // is used: eight independent loads whose cache misses overlap, where reading each bucket
        // as it comes would wait for them one after another.
        let ranges = cells.map(|b| (self.start[b] as usize, self.start[b + 1] as usize));
        for &(lo, hi) in &ranges {
            if lo < hi {
                prefetch(&self.photons[lo]);
            }
        }
        let r2 = self.radius * self.radius;
        let first = |k: usize| k == 0 || cells[k - 1] != cells[k];
        let candidates: usize = (0..8)
            .filter(|&k| first(k))
            .map(|k| ranges[k].1 - ranges[k].0)
            .sum();
        if candidates <= MAX_MERGE_CANDIDATES {
            for (k, &(lo, hi)) in ranges.iter().enumerate() {
                if !first(k) {
                    continue;
                }
                for ph in &self.photons[lo..hi] {
                    if ph.p.distance_squared(p) <= r2 {
                        f(ph, 1.0);
                    }
                }
            }
            return;
        }
        // Candidate c is tested when some point offset + j stride falls in [c, c + 1).
        let stride = candidates as f64 / MAX_MERGE_CANDIDATES as f64;
        let offset = hash_unit(p, self.radius) * stride;
        let scale = stride as f32;
        let mut base = 0usize;
        let mut next = offset;
        for (k, &(lo, hi)) in ranges.iter().enumerate() {
            if !first(k) {
                continue;
            }
            let n = hi - lo;
            while next < (base + n) as f64 {
                let ph = &self.photons[lo + (next as usize - base)];
                if ph.p.distance_squared(p) <= r2 {
                    f(ph, scale);
                }
                next += stride;
            }
            base += n;
        }
    }
}

/// Most photons one merge query tests (`PhotonMap::query`): with a sensible radius a query
/// finds tens of photons; past this one it tests a systematic sample of them.
pub const MAX_MERGE_CANDIDATES: usize = 4096;

/// A number in [0, 1) hashed from a query point and the radius (SplitMix64's finaliser over
/// their bits): the offset of a query's systematic sample, the same wherever the query runs.
fn hash_unit(p: Vec3, radius: f32) -> f64 {
    let mut h = (p.x.to_bits() as u64) << 32 ^ p.y.to_bits() as u64;
    h ^= (p.z.to_bits() as u64) << 17 ^ (radius.to_bits() as u64) << 41;
    h = (h ^ (h >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    h ^= h >> 31;
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Asks for the cache line holding `x` (a hint; nothing on processors without the instruction).
#[inline(always)]
fn prefetch<T>(x: &T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: prefetching is a hint that never faults, whatever the address.
    unsafe {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        _mm_prefetch::<_MM_HINT_T0>((x as *const T).cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = x;
}

/// Mean of the three channels.
pub(crate) fn luminance(c: Rgb) -> f64 {
    (c.x as f64 + c.y as f64 + c.z as f64) / 3.0
}

/// The heuristic of the weights (optimal MIS is not defined for merging: balance).
fn heuristic(settings: &RenderSettings) -> MisKind {
    if settings.mis == MisKind::Power {
        MisKind::Power
    } else {
        MisKind::Balance
    }
}

impl Workspace {
    /// Appends the photons of the prepared light subpath (`prepare` with merging on), whose
    /// vertices are kept from index `base` on.
    fn photons(&self, eta_b: f64, b: i32, base: u32, out: &mut Vec<Photon>) {
        let light = self.light_vertices();
        let m = |x: f64| mis::ratio_term(x, b);
        let mut caustic = true;
        for i in 1..light.len() {
            if i >= 2 {
                caustic &= light[i - 1].is_delta();
            }
            let (y, yp) = (&light[i], &light[i - 1]);
            if y.is_delta() || y.is_black() {
                continue;
            }
            let (wi, d2) = bdpt::dir_to(y.position(), yp.position());
            // pE_{i-1} = pE g: the camera's solid-angle density at y_i to area density at y_{i-1}.
            let g = if yp.is_point() || !(d2 > 0.0) {
                0.0
            } else {
                yp.abs_cos_ng(wi) / d2
            } as f64;
            // S_i = alpha + beta m(pE_{i-1}) (see `Workspace::prepare`).
            let pl_prev = m(yp.pdf_fwd() as f64);
            let (alpha, beta) = if i == 1 {
                let v0 = !yp.is_point() as u8 as f64;
                (m(self.q1() as f64) / pl_prev, v0 / pl_prev)
            } else {
                let v = !yp.is_delta() as u8 as f64;
                let merge_prev = if yp.is_delta() { 0.0 } else { eta_b };
                (v, self.light_sum(i - 1) / pl_prev + merge_prev)
            };
            let over = eta_b * m(y.pdf_fwd() as f64);
            out.push(Photon {
                light_a: alpha / over,
                light_b: beta * m(g) / over,
                p: y.position(),
                wi,
                beta: y.throughput(),
                vertex: base + i as u32,
                index: i as u32,
                caustic,
            });
        }
    }
}
