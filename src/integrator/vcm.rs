//! Vertex connection and merging (Georgiev, Křivánek, Davidovič and Slusallek, "Light Transport
//! Simulation with Vertex Connection and Merging", SIGGRAPH Asia 2012; Hachisuka, Pantaleoni and
//! Jensen, "A Path Space Extension for Robust Light Transport Simulation", SIGGRAPH Asia 2012).
//!
//! An iteration is one sample index i: its N_L = width x height light subpaths are those BDPT
//! traces for the pixel samples (x, y, i), so they are deterministic functions of (seed, i,
//! pixel). Their vertices after the first bounce that are not specular are the iteration's
//! photons ([`PhotonMap`], a hash grid). The map keeps the subpaths too, so each is traced once
//! per iteration: a pixel sample of iteration i is BDPT's (every connection, with its own light
//! subpath, taken from the map) plus merging: every camera vertex z_j (j >= 1, not
//! specular) gathers the photons within r_i, each a path of depth i_photon + j - 1. One MIS covers
//! connections and merges, the recursive weights of [`bdpt::Workspace::prepare`] with eta =
//! N_L pi r_i^2.
//!
//! The radius shrinks as r_i = r_0 (i + 1)^((alpha - 1) / 2) (Knaus and Zwicker, "Progressive
//! Photon Mapping: A Probabilistic Approach", ACM TOG 2011, eq. 13 with one photon pass per
//! iteration), so the estimate is consistent.
//!
//! A tile task must merge with every light vertex of its iterations, not only its own pixels'.
//! Each task takes the maps from a [`PhotonCache`] that builds them on first use: the same map
//! whichever process or thread builds it, so the image does not depend on the tiling, the
//! threads, the workers or retries.

use super::RenderSettings;
use super::bdpt::{self, SampleSink, StoredVertex, Workspace};
use super::bpm;
use crate::film::RayStats;
use crate::geometry::{Rgb, Vec3};
use crate::material::Mode;
use crate::mis::{self, MisKind};
use crate::sampler::{Sampler, Stream};
use crate::scene::Scene;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex, OnceLock};

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
    light_a: f64,
    light_b: f64,
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
    photons: Vec<Photon>,
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

/// How VCM weights its merges.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum VcmWeights {
    /// Every connection and merge by the balance or power heuristic (Georgiev et al. 2012).
    #[default]
    Georgiev,
    /// As `Georgiev`, except for the two merges of a path at the camera's first non-specular
    /// vertex x_1 and at the path's next vertex x_2: their joint share is split between them by
    /// the optimal w1 of Ershov et al. (CPT 2020, eq. 10), which accounts for their
    /// correlation (both use the same photons), from the photon map frozen at iteration 0.
    Ershov,
}

/// Ershov et al.'s split at the camera's first non-specular vertex x_1 (camera vertex `at`).
struct Split<'a> {
    at: usize,
    mixing: bpm::Mixing<'a>,
    /// w1 of the camera's own continuation x_1 -> x_2 (the share of the merges at x_2).
    w_next: f64,
}

impl<'a> Split<'a> {
    fn new(scene: &'a Scene, frozen: &'a PhotonMap, cam: &[bdpt::Vertex]) -> Option<Split<'a>> {
        let at = (1..cam.len()).find(|&j| !cam[j].is_delta())?;
        let x = &cam[at];
        if x.is_black() {
            return None;
        }
        let mixing = bpm::Mixing::new(scene, frozen, x, x.outgoing().w);
        let w_next = cam.get(at + 1).map_or(0.0, |next| {
            mixing.w1((next.position() - x.position()).normalize_or_zero())
        });
        Some(Split { at, mixing, w_next })
    }
}

/// Merges every camera vertex of the prepared workspace (`bdpt::pixel_sample` with merging on)
/// with the photons of `map`, and reports each merge to `sink` as a camera-side sample. With
/// `frozen`, the merges at x_1 and x_2 are weighted by [`VcmWeights::Ershov`].
#[allow(clippy::too_many_arguments)]
fn merge(
    scene: &Scene,
    ws: &Workspace,
    map: &PhotonMap,
    frozen: Option<&PhotonMap>,
    max_depth: u32,
    pixel: (u32, u32),
    sink: &mut dyn SampleSink,
) {
    let b = ws.exponent();
    let m = |x: f64| mis::ratio_term(x, b);
    let eta = map.eta;
    let eta_b = m(eta);
    let norm = (1.0 / (eta)) as f32;
    let cam = ws.camera_vertices();
    let split = frozen.and_then(|f| Split::new(scene, f, cam));
    for j in 1..cam.len() {
        let t = j + 1;
        let (z, zp) = (&cam[j], &cam[j - 1]);
        if z.is_delta() || z.is_black() {
            continue;
        }
        let wo = z.outgoing();
        let pe_z = z.pdf_fwd() as f64;
        map.query(z.position(), |ph, scale| {
            let depth = ph.index + t as u32 - 2;
            if depth > max_depth {
                return;
            }
            let (f, pdf_fwd, pdf_rev) = z.bsdf().eval_pdfs(wo, ph.wi, Mode::Radiance);
            if f == Rgb::ZERO {
                return;
            }
            // The camera's density toward y_{i-1}, as its walk would sample it (roulette at z).
            let pdf_fwd = pdf_fwd * z.continuation();
            // `scale` is 1 but where the query tested a sample of its photons: norm * 1 is norm.
            let contribution = z.throughput() * f * ph.beta * (norm * scale);
            // Light side: m(1 / (eta pL_i)) S_i, S_i completed with pE_{i-1} from the camera's
            // direction.
            let light = ph.light_a + ph.light_b * m(pdf_fwd as f64);
            // Camera side: m(1 / (eta pE(z))) T_{t-1}, T_{t-1} completed with pL(z_{t-2}) from
            // the photon's direction.
            let sum = if t == 2 {
                1.0
            } else {
                let pl_zp = z.area_density(pdf_rev, zp) as f64;
                let v = !zp.is_delta() as u8 as f64;
                let merge_zp = if zp.is_delta() { 0.0 } else { eta_b * m(pl_zp) };
                v + m(pl_zp / zp.pdf_fwd() as f64) * ws.camera_sum(j - 1) + merge_zp
            };
            let camera = sum / (eta_b * m(pe_z));
            let total = 1.0 + light + camera;
            let mut weight = if total.is_finite() { 1.0 / total } else { 0.0 };
            // Ershov et al.: the pair's joint share W = w (1 + rho), rho the other merge's weight
            // over this one's, split as (1 - w1) W at x_1 and w1 W at x_2. At x_1, w1 is taken
            // in the photon's own direction, the one its BSDF is evaluated in: (1 - w1) then
            // meets the same directions as w1 does where the camera samples them toward x_2.
            if let Some(sp) = &split {
                if j == sp.at {
                    let rho = m(map.merge_nearer_light(scene, ph, pdf_fwd));
                    if rho > 0.0 {
                        weight *= (1.0 + rho) * (1.0 - sp.mixing.w1(ph.wi));
                    }
                } else if j == sp.at + 1 {
                    let pl_zp = z.area_density(pdf_rev, zp) as f64;
                    weight *= (1.0 + m(pl_zp / pe_z)) * sp.w_next;
                }
            }
            sink.sample(&bdpt::PathSample {
                depth,
                s: ph.index + 1,
                t: t as u32,
                pixel,
                contribution,
                weight,
                balance: &[],
            });
        });
    }
}

/// Renders one pixel sample of VCM: BDPT's techniques weighted with merging, then the merges
/// against `map` (the photons of this sample's iteration); `frozen` (iteration 0's map) for
/// [`VcmWeights::Ershov`], else None. `sampler` is the pixel sample's
/// camera stream; its light subpath is the one `map` kept for `pixel` (the one BDPT would trace
/// from the light stream, the same bits).
#[allow(clippy::too_many_arguments)]
pub fn pixel_sample(
    scene: &Scene,
    pixel: (u32, u32),
    max_depth: u32,
    sampler: &mut Sampler,
    map: &PhotonMap,
    frozen: Option<&PhotonMap>,
    ws: &mut Workspace,
    sink: &mut dyn SampleSink,
    stats: &mut RayStats,
) {
    ws.set_merging(map.eta);
    bdpt::pixel_camera_subpath(scene, pixel, sampler, max_depth, ws, stats);
    ws.load_light(scene, map.light_path(pixel));
    bdpt::connect_all(scene, pixel, max_depth, sampler, ws, sink, stats);
    merge(scene, ws, map, frozen, max_depth, pixel, sink);
}

/// A map built once by whichever task asks first.
type MapCell = Arc<OnceLock<Arc<PhotonMap>>>;

/// The photon maps of one render's iterations, built on first use and shared by its tasks; at
/// most `capacity` are kept (the oldest is dropped; a dropped map asked for again is rebuilt,
/// the same bits). A cache serves one scene and one `RenderSettings`.
pub struct PhotonCache {
    capacity: usize,
    /// Iteration 0's map, kept apart (BPM's frozen map of Ershov et al.'s weights).
    first: OnceLock<Arc<PhotonMap>>,
    entries: Mutex<Vec<(u32, MapCell)>>,
}

impl PhotonCache {
    /// A cache of at most `capacity` maps (at least 1).
    pub fn new(capacity: usize) -> PhotonCache {
        PhotonCache {
            capacity: capacity.max(1),
            first: OnceLock::new(),
            entries: Mutex::new(Vec::new()),
        }
    }

    /// The map of iteration `iteration`, built here if no one has built it yet (other callers
    /// of the same iteration wait for it).
    pub fn get(&self, scene: &Scene, settings: &RenderSettings, iteration: u32) -> Arc<PhotonMap> {
        if iteration == 0 {
            return self
                .first
                .get_or_init(|| Arc::new(PhotonMap::build(scene, settings, 0)))
                .clone();
        }
        let cell = {
            let mut e = self.entries.lock().unwrap_or_else(|p| p.into_inner());
            match e.iter().find(|(i, _)| *i == iteration) {
                Some((_, c)) => c.clone(),
                None => {
                    if e.len() >= self.capacity {
                        e.remove(0);
                    }
                    let c = Arc::new(OnceLock::new());
                    e.push((iteration, c.clone()));
                    c
                }
            }
        };
        cell.get_or_init(|| Arc::new(PhotonMap::build(scene, settings, iteration)))
            .clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    /// The hash grid finds exactly the photons a brute-force search finds, each once, and a map
    /// built twice is the same.
    #[test]
    fn hash_grid_queries_equal_brute_force() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
        let mut scene = Scene::load(&dir.join("cornell-box.json")).expect("scene");
        scene.camera = scene.camera.with_resolution(32, 32).expect("resolution");
        let settings = RenderSettings {
            radius: 0.1,
            ..Default::default()
        };
        let map = PhotonMap::build(&scene, &settings, 3);
        assert!(map.len() > 1000, "{} photons", map.len());
        let again = PhotonMap::build(&scene, &settings, 3);
        let key = |p: &Photon| (p.p.to_array(), p.index, p.beta.to_array());
        assert!(
            map.photons
                .iter()
                .map(key)
                .eq(again.photons.iter().map(key))
        );
        let r2 = map.radius * map.radius;
        for q in map.photons.iter().step_by(7) {
            for c in [q.p, q.p + Vec3::new(0.03, -0.05, 0.02)] {
                let mut found = Vec::new();
                map.query(c, |p, scale| {
                    assert_eq!(scale, 1.0);
                    found.push(key(p))
                });
                let mut brute: Vec<_> = map
                    .photons
                    .iter()
                    .filter(|p| p.p.distance_squared(c) <= r2)
                    .map(key)
                    .collect();
                found.sort_by(|a, b| a.partial_cmp(b).expect("finite"));
                brute.sort_by(|a, b| a.partial_cmp(b).expect("finite"));
                assert_eq!(found, brute);
            }
        }
    }

    /// A query among more photons than `MAX_MERGE_CANDIDATES` tests at most that many, and its
    /// scaled sum keeps its expectation: averaged over queries (offsets), it equals the sum over
    /// every photon within 4 standard errors.
    #[test]
    fn a_query_among_too_many_photons_is_bounded_and_unbiased() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
        let mut scene = Scene::load(&dir.join("cornell-box.json")).expect("scene");
        scene.camera = scene.camera.with_resolution(96, 96).expect("resolution");
        // A radius beyond the room: every photon is a candidate of every query.
        let settings = RenderSettings {
            radius: 50.0,
            ..Default::default()
        };
        let map = PhotonMap::build(&scene, &settings, 0);
        assert!(
            map.len() > 2 * MAX_MERGE_CANDIDATES,
            "{} photons",
            map.len()
        );
        let exact: f64 = map.photons.iter().map(|p| luminance(p.beta)).sum();
        let center = Vec3::new(0.0, 1.0, 0.0);
        let mut sums = Vec::new();
        for k in 0..400 {
            let q = center + Vec3::new(k as f32 * 1e-4, 0.0, 0.0);
            let (mut tested, mut sum) = (0usize, 0.0f64);
            map.query(q, |p, scale| {
                tested += 1;
                sum += luminance(p.beta) * scale as f64;
            });
            assert!(
                tested <= MAX_MERGE_CANDIDATES + 1,
                "{tested} photons tested"
            );
            sums.push(sum);
        }
        let n = sums.len() as f64;
        let mean = sums.iter().sum::<f64>() / n;
        let var = sums.iter().map(|s| (s - mean) * (s - mean)).sum::<f64>() / (n - 1.0);
        let se = (var / n).sqrt();
        assert!(
            (mean - exact).abs() <= 4.0 * se + 1e-9 * exact,
            "mean {mean} vs exact {exact} (se {se})"
        );
        assert!(se > 0.0, "the offsets differ from query to query");
    }
}
