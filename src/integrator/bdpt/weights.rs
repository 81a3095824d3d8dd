//! MIS weights of a technique: the O(k) vector of balance weights from the densities along the
//! whole path, and the O(1) recursive weights from the partial sums prepared per subpath vertex;
//! the reports that hand a sample with its weights to the sink.

use super::vertex::{Kind, Vertex, continuation_at, dir_to};
use super::workspace::Workspace;
use super::{PathSample, SampleSink};
use crate::geometry::Rgb;
use crate::mis::{self, MisKind};
use crate::scene::{NO_LIGHT, Scene};

/// The densities of a full path v_0 (light) .. v_{k-1} (camera) that a connection changes: the
/// pdf_rev of the light-side connection vertex and its predecessor, the pdf_fwd (from the light
/// side) of the camera-side connection vertex and its predecessor, and q1: the density with
/// which next-event estimation from v_1 picks v_0 (technique s' = 1 when k >= 3).
#[derive(Clone, Copy, Default)]
pub(super) struct Connection {
    pub(super) pe_y1: f32,
    pub(super) pe_y2: f32,
    pub(super) pl_z1: f32,
    pub(super) pl_z2: f32,
    pub(super) q1: f32,
}

/// Computes into `ws.weights[0..k]` the balance weights of every technique s' = 0 .. k-1 for the
/// full path made of `light[0..s]` (or `nee` as v_0 when s = 1 and t >= 2), and `cam[0..t]`.
/// Returns false if the densities are degenerate (the caller then weights the sample 1 alone).
///
/// Ratio recurrence (Veach 1997 §10.2): p_{s'+1} / p_{s'} = pL(v_{s'}) / pE(v_{s'}), where pL is
/// the density of a vertex generated from the light side and pE from the camera side.
pub(super) fn balance_weights(
    ws: &mut Workspace,
    nee: Option<&Vertex>,
    s: usize,
    t: usize,
    c: &Connection,
) -> bool {
    let k = s + t;
    let from = ws.roulette_from;
    let Workspace {
        cam,
        light,
        pl,
        pe,
        weights,
        ..
    } = ws;
    let vert = |i: usize| -> &Vertex {
        if i < s {
            if i == 0 && s == 1 && t >= 2 {
                nee.expect("NEE vertex")
            } else {
                &light[i]
            }
        } else {
            &cam[k - 1 - i]
        }
    };
    for i in 0..k {
        let v = vert(i);
        // The density from the far side carries the q of the vertex that sampled v there, at
        // its index in that side's subpath (`continuation_at`); the connection's own
        // densities below replace the ones whose sampling vertex is not stored.
        let (mut l, mut e) = if i + 2 < s {
            let q = continuation_at(&light[i + 1], k - 2 - i, from);
            (v.pdf_fwd as f64, (v.pdf_rev * q) as f64)
        } else if i < s {
            (v.pdf_fwd as f64, 0.0)
        } else if i >= s + 2 {
            let q = continuation_at(&cam[k - i], i - 1, from);
            ((v.pdf_rev * q) as f64, v.pdf_fwd as f64)
        } else {
            (0.0, v.pdf_fwd as f64)
        };
        // Densities the connection changes.
        if i + 1 == s {
            e = c.pe_y1 as f64;
        } else if i + 2 == s {
            e = c.pe_y2 as f64;
        } else if i == s {
            l = c.pl_z1 as f64;
        } else if i == s + 1 {
            l = c.pl_z2 as f64;
        }
        pl[i] = l;
        pe[i] = e;
    }
    pe[k - 1] = 1.0;
    let r = &mut weights[..k];
    r[s] = 1.0;
    for sp in s..k - 1 {
        r[sp + 1] = r[sp] * pl[sp] / pe[sp];
    }
    for sp in (1..=s).rev() {
        r[sp - 1] = r[sp] * pe[sp - 1] / pl[sp - 1];
    }
    // Next-event estimation picks v_0 with its own density q1 rather than by emission.
    if k >= 3 && pl[0] > 0.0 {
        r[1] *= c.q1 as f64 / pl[0];
    }
    // Techniques that cannot make this path: connections at a specular vertex, or hitting a
    // point light.
    let v0 = vert(0);
    if v0.delta_pos || v0.kind != Kind::Light && v0.light == NO_LIGHT {
        r[0] = 0.0;
    }
    for (sp, x) in r.iter_mut().enumerate().skip(1) {
        if vert(sp - 1).delta || vert(sp).delta {
            *x = 0.0;
        }
    }
    let sum: f64 = r.iter().sum();
    if !(sum > 0.0) || !sum.is_finite() || r.iter().any(|x| !x.is_finite()) {
        r.fill(0.0);
        r[s] = 1.0;
        return false;
    }
    for x in r.iter_mut() {
        *x /= sum;
    }
    true
}

/// Weights of a path only technique `s` could have made (an occluded connection: every other
/// technique would have traced that segment and stopped at the occluder), over `k` techniques.
pub(super) fn weights_alone(ws: &mut Workspace, s: usize, k: usize) {
    let w = &mut ws.weights[..k];
    w.fill(0.0);
    w[s] = 1.0;
}

impl Workspace {
    /// Partial sums of the recursive weights, once both subpaths are traced, for `heuristic`
    /// (balance: exponent b = 1; power: b = 2). Notation of `balance_weights`: p_{s'} is the
    /// density of technique s' for a full path v_0 .. v_{k-1}, pL_i / pE_i the densities of v_i
    /// from the light / camera side, q1 the next-event density of v_0, and v(s') = 1 when
    /// technique s' can make the path (no delta vertex at its connection), else 0. For light
    /// vertices (v_i = y_i):
    ///
    ///   S_0 = v(0),  S_1 = (v(0) pE_0^b + v(1) q1^b) / pL_0^b,  S_j = v(j) + (pE_{j-1}/pL_{j-1})^b S_{j-1},
    ///
    /// so that sum_{s' < s} (p_{s'}/p_s)^b = (pE_{s-1}/pL_{s-1})^b S_{s-1} for s >= 2; for camera
    /// vertices z_j, with v'(t') = v(k - t') (technique with t' camera vertices):
    ///
    ///   T_1 = v'(1),  T_j = v'(j) + (pL(z_{j-1})/pE(z_{j-1}))^b T_{j-1},
    ///
    /// so that sum_{t' < t} (p_{k-t'}/p_{k-t})^b = (pL(z_{t-1})/pE(z_{t-1}))^b T_{t-1}. This is
    /// Veach's ratio recurrence (Veach 1997 §10.2) summed from the ends, the dVC quantity of
    /// Georgiev, "Implementing Vertex Connection and Merging" (tech. report, 2012) as a ratio.
    /// A connection changes only the last two densities on each side (the `Connection`), so it
    /// completes S_{s-1} from S_{s-2} and T_{t-1} from T_{t-2} in O(1): `heuristic_weight`.
    /// S_j needs pE_{j-1}, known once y_j has sampled its successor; the last vertex's sum is
    /// never used.
    ///
    /// With vertex merging (`set_merging`, eta = N_L pi r^2) the sums also hold the merging
    /// techniques: merging at x_i (1 <= i <= k - 2, x_i not specular) has density
    /// p_VM(i) = eta pE_i p_{i+1} = eta pL_i p_i (Georgiev et al. 2012, eq. 11 and §4.3), which adds
    /// m(eta pE_{j-1}) to S_j for j >= 2 and m(eta pL(z_{j-1})) to T_j for j >= 2 (the
    /// technique merging at the sum's previous vertex, relative to p_j); older merges ride the
    /// ratio recurrence like the connections. This is the dVM part of Georgiev's dVCM / dVC / dVM
    /// (tech. report, 2012) in ratio form.
    pub fn prepare(&mut self, scene: &Scene, heuristic: MisKind) {
        self.exponent = heuristic.beta();
        self.q1 = if self.light.len() >= 2 {
            nee_density(scene, &self.light[0], &self.light[1])
        } else {
            0.0
        };
        self.light_sums.clear();
        let mut prev = 0.0;
        for j in 0..self.light.len() {
            prev = self.light_sum_next(j, prev, self.light[j].rr);
            self.light_sums.push(prev);
        }
        self.cam_sums.clear();
        let mut prev = 0.0;
        for j in 0..self.cam.len() {
            prev = self.cam_sum_next(j, prev, self.cam[j].rr);
            self.cam_sums.push(prev);
        }
    }

    /// [`continuation_at`] with this workspace's roulette start.
    #[inline]
    pub(super) fn q_as(&self, v: &Vertex, index: usize) -> f32 {
        continuation_at(v, index, self.roulette_from)
    }

    /// S_j from S_{j-1} = `prev` (see `prepare`), with y_j's continuation probability `q_rev` in
    /// pE_{j-1}, the density of y_{j-1} from the camera side.
    fn light_sum_next(&self, j: usize, prev: f64, q_rev: f32) -> f64 {
        let b = self.exponent;
        let m = |x: f64| mis::ratio_term(x, b);
        let light = &self.light;
        let y = &light[j];
        match j {
            0 => !y.delta_pos as u8 as f64,
            1 => {
                let y0 = &light[0];
                let v0 = !y0.delta_pos as u8 as f64;
                let v1 = !y.delta as u8 as f64;
                (v0 * m((y0.pdf_rev * q_rev) as f64) + v1 * m(self.q1 as f64))
                    / m(y0.pdf_fwd as f64)
            }
            _ => {
                let yp = &light[j - 1];
                let v = !(yp.delta || y.delta) as u8 as f64;
                let pe = (yp.pdf_rev * q_rev) as f64;
                v + m(pe / yp.pdf_fwd as f64) * prev + merge_term(m(self.eta), yp, pe, b)
            }
        }
    }

    /// T_j from T_{j-1} = `prev`, with z_j's continuation probability `q_rev` in pL(z_{j-1}).
    fn cam_sum_next(&self, j: usize, prev: f64, q_rev: f32) -> f64 {
        let b = self.exponent;
        let m = |x: f64| mis::ratio_term(x, b);
        match j {
            0 => 0.0,
            _ => {
                let (z, zp) = (&self.cam[j], &self.cam[j - 1]);
                let v = !(z.delta || zp.delta) as u8 as f64;
                let older = if j == 1 {
                    0.0
                } else {
                    let pl = (zp.pdf_rev * q_rev) as f64;
                    m(pl / zp.pdf_fwd as f64) * prev + merge_term(m(self.eta), zp, pl, b)
                };
                v + older
            }
        }
    }

    /// S_j (`camera` false) or T_j (true) for a full path of k vertices. The prepared sum takes
    /// every vertex i <= j of its subpath to sample vertex i - 1 past the roulette's start,
    /// which holds when vertex j has index k - 1 - j >= R in the other subpath of the techniques
    /// it sums; closer to the connection the last few terms are made again with q = 1 where that
    /// index is below R: at most R - 1 steps.
    fn sum_for(&self, camera: bool, j: usize, k: usize) -> f64 {
        let (sums, path) = if camera {
            (&self.cam_sums, &self.cam)
        } else {
            (&self.light_sums, &self.light)
        };
        let r = self.roulette_from;
        if r == usize::MAX || j + r < k {
            return sums[j];
        }
        let mut i = (k - 1).saturating_sub(r);
        let mut sum = sums[i];
        while i < j {
            i += 1;
            let q = self.q_as(&path[i], k - 1 - i);
            sum = if camera {
                self.cam_sum_next(i, sum, q)
            } else {
                self.light_sum_next(i, sum, q)
            };
        }
        sum
    }
}

/// The merging term m(eta p) of a vertex (0 at a specular vertex or without merging); `eta_b`
/// is m(eta).
#[inline]
fn merge_term(eta_b: f64, v: &Vertex, p: f64, b: i32) -> f64 {
    if eta_b == 0.0 || v.delta {
        0.0
    } else {
        eta_b * mis::ratio_term(p, b)
    }
}

/// The weight of technique (s, t) by the heuristic of `Workspace::prepare`, in O(1): the same
/// number as `mis::weight` of the `balance_weights` vector (up to rounding), p_s^b / sum p_{s'}^b
/// = 1 / (1 + sum over s' != s of (p_{s'}/p_s)^b), both sides' sums completed from the partial
/// sums with the densities the connection changes. `nee` is v_0 of a next-event sample, `emitter`
/// the camera vertex on an emitter for s = 0. Degenerate densities weight the sample 1, as
/// `balance_weights` does.
pub(super) fn heuristic_weight(
    ws: &Workspace,
    nee: Option<&Vertex>,
    s: usize,
    t: usize,
    c: &Connection,
) -> f64 {
    let b = ws.exponent;
    let m = |x: f64| mis::ratio_term(x, b);
    let eta_b = m(ws.eta);
    let (pe_y1, pe_y2) = (c.pe_y1 as f64, c.pe_y2 as f64);
    let (pl_z1, pl_z2, q1) = (c.pl_z1 as f64, c.pl_z2 as f64, c.q1 as f64);
    // Techniques s' < s, relative to p_s.
    let light_side = match s {
        0 => 0.0,
        1 => {
            let v0 = nee.unwrap_or_else(|| &ws.light[0]);
            if v0.delta_pos {
                0.0
            } else if t >= 2 {
                // p_1 picks v_0 by next-event estimation.
                m(pe_y1 / q1)
            } else {
                m(pe_y1 / v0.pdf_fwd as f64)
            }
        }
        _ => {
            let y = &ws.light[s - 1];
            let yp = &ws.light[s - 2];
            let inner = if s == 2 {
                let v0 = !yp.delta_pos as u8 as f64;
                (v0 * m(pe_y2) + m(ws.q1 as f64)) / m(yp.pdf_fwd as f64)
            } else {
                let v = !yp.delta as u8 as f64;
                v + m(pe_y2 / yp.pdf_fwd as f64) * ws.sum_for(false, s - 2, s + t)
                    + merge_term(eta_b, yp, pe_y2, b)
            };
            // Merging at y_{s-1} (s - 1 >= 1), then the older techniques.
            m(pe_y1 / y.pdf_fwd as f64) * inner + merge_term(eta_b, y, pe_y1, b)
        }
    };
    // Techniques s' > s (t' < t), relative to p_s.
    let cam_side = if t == 1 {
        0.0
    } else {
        let z = &ws.cam[t - 1];
        let zp = &ws.cam[t - 2];
        let v = !(z.delta || zp.delta) as u8 as f64;
        let pe_z1 = z.pdf_fwd as f64;
        // sum_{t' < t - 1} relative to p_{s+1}; T_0 = 0.
        let rest = if t >= 3 {
            m(pl_z2 / zp.pdf_fwd as f64) * ws.sum_for(true, t - 2, s + t)
                + merge_term(eta_b, zp, pl_z2, b)
        } else {
            0.0
        };
        // Merging at z_{t-1}: not for s = 0, where z_{t-1} is the light vertex x_0.
        let merge_z = merge_term(eta_b, z, pl_z1, b);
        match s {
            // p_1 picks v_0 = z_{t-1} by next-event estimation, p_{s' >= 2} by emission (k >= 3).
            0 if t >= 3 => v * m(q1 / pe_z1) + m(pl_z1 / pe_z1) * rest,
            0 => m(pl_z1 / pe_z1) * (v + rest),
            // p_1 itself picked v_0 by next-event estimation: every p_{s' >= 2} (and every merge)
            // has the emission density pL_0 where p_1 has q1.
            1 => {
                let pl0 = nee.map_or(0.0, |v| v.pdf_fwd as f64);
                let vc = m(pl0 / q1) * m(pl_z1 / pe_z1) * (v + rest);
                if merge_z == 0.0 {
                    vc
                } else {
                    vc + m(pl0 / q1) * merge_z
                }
            }
            _ => m(pl_z1 / pe_z1) * (v + rest) + merge_z,
        }
    };
    let total = 1.0 + light_side + cam_side;
    if total.is_finite() { 1.0 / total } else { 1.0 }
}

/// Reports a sample with a contribution: its weight, and the balance vector where the sink wants
/// it.
#[allow(clippy::too_many_arguments)]
pub(super) fn report<S: SampleSink + ?Sized>(
    ws: &mut Workspace,
    sink: &mut S,
    nee: Option<&Vertex>,
    s: usize,
    t: usize,
    c: &Connection,
    depth: u32,
    pixel: (u32, u32),
    contribution: Rgb,
) {
    let k = s + t;
    let (weight, n) = if sink.wants_vector(depth) {
        balance_weights(ws, nee, s, t, c);
        (mis::weight(sink.heuristic(), &ws.weights[..k], s as u32), k)
    } else {
        (heuristic_weight(ws, nee, s, t, c), 0)
    };
    sink.sample(&PathSample {
        depth,
        s: s as u32,
        t: t as u32,
        pixel,
        contribution,
        weight,
        balance: &ws.weights[..n],
    });
}

/// Reports a sample only technique `s` of the `k` of its depth could make (see `weights_alone`).
pub(super) fn report_alone<S: SampleSink + ?Sized>(
    ws: &mut Workspace,
    sink: &mut S,
    s: usize,
    t: usize,
    depth: u32,
    pixel: (u32, u32),
) {
    weights_alone(ws, s, s + t);
    let n = if sink.wants_vector(depth) { s + t } else { 0 };
    sink.sample(&PathSample {
        depth,
        s: s as u32,
        t: t as u32,
        pixel,
        contribution: Rgb::ZERO,
        weight: 1.0,
        balance: &ws.weights[..n],
    });
}

/// Area density with which next-event estimation from `v1` would pick the light point `v0`.
pub(super) fn nee_density(scene: &Scene, v0: &Vertex, v1: &Vertex) -> f32 {
    let pmf = scene.light_pmf(v0.light);
    if v0.delta_pos {
        return pmf;
    }
    let (wi, _) = dir_to(v1.p, v0.p);
    v1.to_area(pmf * scene.lights[v0.light as usize].pdf_li(v1.p, wi), v0)
}
