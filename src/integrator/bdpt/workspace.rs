//! The per-thread buffers of BDPT: both subpaths, the weights' scratch, the partial sums and
//! the settings (merging, roulette) they are prepared for.

use super::MAX_DEPTH;
use super::vertex::{StoredVertex, Vertex, dir_to};
use crate::scene::Scene;

/// Per-thread buffers, reused from sample to sample.
pub struct Workspace {
    pub(super) cam: Vec<Vertex>,
    pub(super) light: Vec<Vertex>,
    pub(super) pl: Vec<f64>,
    pub(super) pe: Vec<f64>,
    pub(super) weights: Vec<f64>,
    /// Per light vertex j: the partial sum S_j of the recursive weights (see `prepare`).
    pub(super) light_sums: Vec<f64>,
    /// Per camera vertex j: the partial sum T_j of the recursive weights.
    pub(super) cam_sums: Vec<f64>,
    /// Density with which next-event estimation from y_1 picks y_0 (0 without y_1).
    pub(super) q1: f32,
    /// Exponent of the heuristic the partial sums are for: 1 balance, 2 power.
    pub(super) exponent: i32,
    /// Vertex merging's eta = N_L pi r^2 (0: no merging, plain BDPT): see `set_merging`.
    pub(super) eta: f64,
    /// Subpaths end by Russian roulette from their vertex of this index on (`set_roulette`);
    /// `usize::MAX`: never.
    pub(super) roulette_from: usize,
    /// The light vertex of the latest next-event sample (for tests of the weights).
    pub(super) last_nee: Option<Vertex>,
}

impl Default for Workspace {
    fn default() -> Self {
        let n = MAX_DEPTH as usize + 3;
        Workspace {
            cam: Vec::with_capacity(n),
            light: Vec::with_capacity(n),
            pl: vec![0.0; 2 * n],
            pe: vec![0.0; 2 * n],
            weights: vec![0.0; 2 * n],
            light_sums: Vec::with_capacity(n),
            cam_sums: Vec::with_capacity(n),
            q1: 0.0,
            exponent: 1,
            eta: 0.0,
            roulette_from: usize::MAX,
            last_nee: None,
        }
    }
}

impl Workspace {
    /// Turns vertex merging on for the next `prepare` and weights: `eta` = N_L pi r^2, the
    /// number of light subpaths a camera vertex merges with times the merge disc's area
    /// (Georgiev et al. 2012, eq. 11). 0, the default, is plain BDPT.
    pub fn set_merging(&mut self, eta: f64) {
        self.eta = eta;
    }

    /// Whether subpaths traced from now on end by Russian roulette besides the max depth:
    /// `Some(n)`, each vertex from the n-th surface vertex on (n >= 1; the endpoints are vertex
    /// 0) continues with its BSDF's albedo estimate; the vertices before it always continue.
    pub fn set_roulette(&mut self, from: Option<u32>) {
        self.roulette_from = from.map_or(usize::MAX, |n| n.max(1) as usize);
    }

    /// Forgets the camera subpath (a light subpath prepared alone).
    pub(crate) fn clear_camera(&mut self) {
        self.cam.clear();
    }

    /// The light subpath y_0 ...
    pub(crate) fn light_vertices(&self) -> &[Vertex] {
        &self.light
    }

    /// The camera subpath z_0 (the pinhole) ...
    pub(crate) fn camera_vertices(&self) -> &[Vertex] {
        &self.cam
    }

    /// Takes `path` (a light subpath kept by [`Vertex::stored`]) as the light subpath, in place
    /// of tracing one: the same vertices as `light_subpath` made.
    pub(crate) fn load_light(&mut self, scene: &Scene, path: &[StoredVertex]) {
        self.light.clear();
        self.light
            .extend(path.iter().enumerate().map(|(i, v)| v.load(scene, i == 0)));
        for i in 1..self.light.len() {
            let (y, yp) = (&self.light[i], &self.light[i - 1]);
            self.light[i].wo = y.bsdf.outgoing(dir_to(y.p, yp.p).0);
        }
    }

    /// The prepared partial sum S_j of light vertex j.
    pub(crate) fn light_sum(&self, j: usize) -> f64 {
        self.light_sums[j]
    }

    /// The prepared partial sum T_j of camera vertex j.
    pub(crate) fn camera_sum(&self, j: usize) -> f64 {
        self.cam_sums[j]
    }

    /// Next-event density of y_0 from y_1 (0 without y_1), once prepared.
    pub(crate) fn q1(&self) -> f32 {
        self.q1
    }

    /// Exponent of the prepared heuristic (1 balance, 2 power).
    pub(crate) fn exponent(&self) -> i32 {
        self.exponent
    }
}
