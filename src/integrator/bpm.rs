//! Bidirectional photon mapping (Vorba, "Bidirectional Photon Mapping", CESCG 2011) with the
//! camera path merging at a fixed backward diffuse depth M (`--bdd`), or mixing depths M and
//! M + 1 with the optimal weights of Ershov, Voloboy, Zhdanov and Zhdanov, "Calculation of MIS
//! weights for bidirectional path tracing with photon maps" (CPT 2020, CEUR Workshop Proceedings
//! vol. 2763), eq. 10 with a, A and B from photon sums (eqs. 11-12).
//!
//! Fixed BDD = M: the camera subpath merges at its M-th non-specular vertex with every photon,
//! and at its earlier non-specular vertices with direct and caustic photons only (light
//! subpaths with no non-specular vertex before the photon); a camera subpath that reaches an
//! emitter through specular vertices only sees its emission. Each path is made once.
//!
//! Mixed M / M + 1: paths with at least M + 1 non-specular vertices are also merged at the
//! (M + 1)-th, weighted w1(v, u, x_M) there and 1 - w1 at x_M, where x_M is the camera's M-th
//! non-specular vertex, u the direction from it toward the camera and v the direction toward
//! the path's next vertex (at x_M, the direction the merged photon arrived from, the one its
//! BSDF is evaluated in; at x_{M+1}, the camera's own). The weights must be deterministic functions of the path, so a, A
//! and B are sums over a photon map frozen once (iteration 0's, at radius r_0); the estimate
//! uses the current iteration's photons. The closed form: w1 = W1 + A / ((1 - n_F B) a), with
//! W1 = f~ / (n_F a), a = (f~ + b / L) / n_F + L, n_F = S N_F (S = pi r_0^2, N_F light
//! paths), f~ the backward-normalised BSDF at x_M (its sampling density over |cos|, exact for
//! Lambert), L and b the radiance and the squared-BSDF sum of the frozen photons at the next
//! vertex y (the first hit from x_M along v), per unit flux. Eq. 10 as printed reads
//! w1 = W1 + A / a; solving eq. 9 for its integral gives the (1 - n_F B) factor, where B
//! enters. w1 is clamped to [0, 1] (any deterministic weight is unbiased).

use super::bdpt::{self, Workspace};
use super::photon_map::{Photon, PhotonMap, luminance};
use crate::film::RayStats;
use crate::geometry::{Rgb, Vec2, Vec3};
use crate::material::{Bsdf, Mode};
use crate::sampler::Sampler;
use crate::scene::{NO_LIGHT, Scene};
use serde::{Deserialize, Serialize};

/// How BPM weights its merges.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum BpmWeights {
    /// Merge at the camera's BDD-th non-specular vertex only (direct and caustic photons before).
    Fixed,
    /// Mix BDD and BDD + 1 with Ershov et al.'s optimal weights from the frozen photon map.
    #[default]
    Optimal,
}

/// The optimal weights' sums at x_M (eqs. 11-12 over the frozen map).
pub(crate) struct Mixing<'a> {
    scene: &'a Scene,
    frozen: &'a PhotonMap,
    /// x_M and its BSDF.
    pub(crate) p: Vec3,
    ng: Vec3,
    ns: Vec3,
    bsdf: Bsdf,
    /// u: toward the camera.
    wo: Vec3,
    /// n_F = S N_F, and 1 / (S N_F Phi) (photon sums to radiance per unit flux).
    n_f: f64,
    per_flux: f64,
    /// A / (1 - n_F B).
    gamma: f64,
}

impl<'a> Mixing<'a> {
    /// The sums at x_M = `x`, `wo` (u) toward the camera.
    pub(crate) fn new(scene: &'a Scene, frozen: &'a PhotonMap, x: &bdpt::Vertex, wo: Vec3) -> Self {
        let s = std::f64::consts::PI * (frozen.radius as f64).powi(2);
        let n_f = s * frozen.light_paths as f64;
        let per_flux = if frozen.flux > 0.0 {
            1.0 / (n_f * frozen.flux)
        } else {
            0.0
        };
        let mut m = Mixing {
            scene,
            frozen,
            p: x.position(),
            ng: x.normal(),
            ns: x.shading_normal(),
            bsdf: *x.bsdf(),
            wo,
            n_f,
            per_flux,
            gamma: 0.0,
        };
        // A and B: sums over the frozen photons at x_M of W1 at their directions.
        let (mut a_sum, mut nb) = (0.0, 0.0);
        let mut qs: Vec<(Photon, f32)> = Vec::new();
        frozen.query(m.p, |q, scale| qs.push((*q, scale)));
        for (q, scale) in &qs {
            let (w1_0, _, f_t) = m.w1_parts(q.wi);
            let e = luminance(q.beta) * *scale as f64 / frozen.flux.max(f64::MIN_POSITIVE);
            a_sum += w1_0 * f_t * e / n_f;
            nb += w1_0 * e;
        }
        m.gamma = a_sum / (1.0 - nb).max(1e-3);
        m
    }

    /// (W1, a, f~) for direction `v` from x_M (W1 = 0, a = infinity where the next vertex
    /// sends no light).
    fn w1_parts(&self, v: Vec3) -> (f64, f64, f64) {
        let cos = v.dot(self.ns).abs() as f64;
        let f_t = if cos > 0.0 {
            self.bsdf.pdf(self.wo, v) as f64 / cos
        } else {
            0.0
        };
        let Some(hit) = self.scene.intersect(&Scene::spawn_ray(self.p, self.ng, v)) else {
            return (0.0, f64::INFINITY, f_t);
        };
        let bsdf = Bsdf::new(
            &self.scene.materials[hit.material as usize],
            hit.ng,
            hit.ns,
            hit.uv,
        );
        let (mut l, mut b) = (0.0, 0.0);
        self.frozen.query(hit.p, |q, scale| {
            let f = luminance(bsdf.eval(-v, q.wi, Mode::Radiance));
            let e = luminance(q.beta) * scale as f64;
            l += f * e;
            b += f * f * e;
        });
        l *= self.per_flux;
        b *= self.per_flux;
        if !(l > 0.0) {
            return (0.0, f64::INFINITY, f_t);
        }
        let a = (f_t + b / l) / self.n_f + l;
        (f_t / self.n_f / a, a, f_t)
    }

    /// w1 for direction `v` from x_M, in [0, 1].
    pub(crate) fn w1(&self, v: Vec3) -> f64 {
        let (w, a, _) = self.w1_parts(v);
        let w1 = w + self.gamma / a;
        if w1.is_finite() {
            w1.clamp(0.0, 1.0)
        } else {
            0.0
        }
    }
}

/// Renders one pixel sample of BPM: the camera subpath, its emission seen through specular
/// vertices, and its merges with `map`; `frozen` (iteration 0's map) for the optimal weights,
/// None for fixed BDD. Returns the pixel sample's estimate; with `per_depth` (max_depth + 1
/// entries) its parts by path depth go there too.
#[allow(clippy::too_many_arguments)]
pub fn pixel_sample(
    scene: &Scene,
    pixel: (u32, u32),
    sampler: &mut Sampler,
    max_depth: u32,
    bdd: u32,
    map: &PhotonMap,
    frozen: Option<&PhotonMap>,
    ws: &mut Workspace,
    mut per_depth: Option<&mut [Rgb]>,
    stats: &mut RayStats,
) -> Rgb {
    let film = sampler.next_2d();
    let raster = Vec2::new(pixel.0 as f32 + film.x, pixel.1 as f32 + film.y);
    bdpt::camera_subpath(scene, raster, sampler, max_depth, ws, stats);
    let cam = ws.camera_vertices();
    let m = bdd.max(1);
    let last = m + frozen.is_some() as u32;
    let norm = (1.0 / map.eta) as f32;
    let mut value = Rgb::ZERO;
    let mut c = 0u32;
    let mut mixing: Option<Mixing> = None;
    // w1 of the camera's own continuation past x_M (the weight of every merge at x_{M+1}).
    let mut w_next = 0.0f64;
    for j in 1..cam.len() {
        let z = &cam[j];
        let wo = z.outgoing();
        if c == 0 && z.light_index() != NO_LIGHT {
            let e = z.throughput() * scene.lights[z.light_index() as usize].le(z.normal(), wo.w);
            value += e;
            if let Some(pd) = per_depth.as_deref_mut() {
                pd[j - 1] += e;
            }
        }
        if z.is_delta() {
            continue;
        }
        c += 1;
        if c > last || z.is_black() {
            break;
        }
        if c == m
            && let Some(f) = frozen
        {
            let mx = Mixing::new(scene, f, z, wo.w);
            if let Some(next) = cam.get(j + 1) {
                w_next = mx.w1((next.position() - z.position()).normalize_or_zero());
            }
            mixing = Some(mx);
        }
        let mut sum = Rgb::ZERO;
        let beta = z.throughput();
        map.query(z.position(), |ph, scale| {
            let depth = ph.index + j as u32 - 1;
            if depth > max_depth || c < m && !ph.caustic {
                return;
            }
            let w = if c == m + 1 {
                w_next
            } else if c == m && !ph.caustic {
                mixing.as_ref().map_or(1.0, |mx| 1.0 - mx.w1(ph.wi))
            } else {
                1.0
            };
            if w == 0.0 {
                return;
            }
            let f = z.bsdf().eval_local(wo, ph.wi, Mode::Radiance).0;
            // `scale` is 1 but where the query tested a sample of its photons.
            let v = f * ph.beta * (w as f32 * scale);
            sum += v;
            if let Some(pd) = per_depth.as_deref_mut() {
                pd[depth as usize] += beta * v * norm;
            }
        });
        value += beta * sum * norm;
    }
    value
}
