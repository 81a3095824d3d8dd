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
use super::bdpt::{self, SampleSink, Workspace};
use super::bpm;
pub use super::photon_map::{
    DEFAULT_ALPHA, DEFAULT_RADIUS_FACTOR, MAX_MERGE_CANDIDATES, Photon, PhotonMap, radius,
};
use crate::film::RayStats;
use crate::geometry::Rgb;
use crate::material::Mode;
use crate::mis;
use crate::sampler::Sampler;
use crate::scene::Scene;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex, OnceLock};

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
    use crate::geometry::Vec3;
    use crate::integrator::photon_map::luminance;
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
