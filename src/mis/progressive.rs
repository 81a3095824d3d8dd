//! The progressive optimal-MIS estimator: pass k's samples weighted with the optimal weights of
//! an alpha solved from passes 1 .. k - 1 (Kondapaneni et al., "Optimal Multiple Importance
//! Sampling", ACM TOG 38(4), 2019, the progressive estimator; weights as in Cailleau et al.,
//! "Optimal Multiple Importance Sampling for Bidirectional Path Tracing", eq. 6).
//!
//! **The estimator as a control variate.** For one pixel and depth, N techniques with n_i samples
//! each, P(X) = sum_k n_k p_k(X) and the balance vector W_i = n_i p_i / P (it sums to 1), the
//! optimal weights of eq. 6,
//!
//!   w_i(X) = alpha_i p_i / f + (n_i p_i / P) (1 - sum_k alpha_k p_k / f),
//!
//! give the multi-sample estimator sum_i (1 / n_i) sum_j w_i f / p_i (Veach 1997, §9.2)
//!
//!   F_alpha = sum_i alpha_i + sum_X (f - sum_k alpha_k p_k) / P
//!           = F_bal + sum_k alpha_k D_k,   D_k = 1 - (1 / n_k) sum_X W_k(X) = 1 - (A 1)_k / n_k,
//!
//! where F_bal = sum_X f / P is the balance estimate and A = sum_X W W^T is the system `optimal`
//! accumulates (A 1 = sum_X W since each W sums to 1). The product w_i f is defined for
//! f(X) = 0 too, so zero-contribution samples need no special case. D is zero-mean:
//! E[sum_X W_k] = sum_i n_i E_i[n_k p_k / P] = n_k, counting, as `optimal` does (and as the
//! direct estimator's A needs), a sample that technique k failed to make (and the
//! zero-contribution samples `integrator::bdpt` reports alone) as one with W = e_k, a point only
//! k can produce, and the N_L - h light paths that did not reach the pixel as light-tracing
//! samples with W = e_lt. Hence **for any alpha independent of the pass's samples, F_alpha is
//! unbiased**; the optimal alpha (A alpha = b, Cailleau et al. eq. 7) minimises its variance.
//! Pass k uses an alpha solved from the systems of passes < k (regularised with the job's kappa,
//! `OptimalAccum::solution`); the first pass uses alpha = 0, balance. `tests/bias.rs` measures
//! the result unbiased to 0.05 % at 1-8 spp.
//!
//! **What this needs.** With x the solution of `optimal`'s system (alpha_i = m_i x_i, m = 1 for
//! camera techniques and W H for light tracing, n_i = m_i S_k for a pass of S_k samples), the
//! pass's estimate times S_k is
//!
//!   S_k F_k = sum_X C W_s + S_k sum_{i != lt} x_i - sum_X sum_i x_i W_i(X) + x_lt h_k,
//!
//! (the light-tracing null samples' -x_lt (N_L - h_k) and S_k alpha_lt = x_lt N_L cancel but for
//! x_lt h_k), sums over the samples recorded in the pixel, which are exactly what a pass merges
//! into it: a task's own pixels (its A, whose row sums are sum_X W, its sample count S_k and its
//! hit counts h) and the light-tracing records other tasks route there (each its W). The first
//! term is the pass's part of b, already accumulated. So x is applied where a pass is merged
//! into the film (`Progressive::add_own`, `add_record`), solved again from the totals once a
//! pass is complete and the samples have doubled since the last solve (`end_pass`: O(log spp)
//! solves, each as costly as the direct estimator's one), and workers never see it: 0 bytes
//! are shipped.
//!
//! **Combining passes.** Pass k has weight S_k / S, fixed in advance by its sample count, so the
//! sum stays unbiased and is one accumulator per pixel and depth: F = (sum b + q) / S, with q the
//! sum of the control-variate terms above. (Weights from measured per-pass variances would
//! correlate the weights with the estimates and bias the sum.)

use super::optimal::{OptimalAccum, SolveScratch, block_len};

/// The progressive state of a set of pixels (a tile, or the frame): per pixel and optimal depth,
/// the solution x (N x 3) the next pass is weighted with, and q (3), the control-variate sums of
/// the passes merged so far.
#[derive(Clone, Debug, PartialEq)]
pub struct Progressive {
    /// Optimal depths 1 ..= d_opt.
    pub d_opt: u32,
    /// Number of pixels.
    pub pixels: usize,
    /// Per pixel: for each depth d, (d + 2) x 3 values of x (row-major), then d_opt x 3 of q.
    pub data: Vec<f64>,
    /// Samples per pixel when x was last solved (0: never, x = 0).
    pub solved_at: u32,
}

/// Offset of depth d's x within a pixel's block: 3 sum_{d' < d} (d' + 2).
#[inline]
fn x_offset(d: u32) -> usize {
    let d = d as usize;
    3 * ((d - 1) * (d + 4) / 2)
}

impl Progressive {
    /// Zeroed state (x = 0: the first pass is balance) for `pixels` pixels of `d_opt` depths.
    pub fn new(d_opt: u32, pixels: usize) -> Progressive {
        Progressive {
            d_opt,
            pixels,
            data: vec![0.0; pixels * Progressive::values_per_pixel(d_opt)],
            solved_at: 0,
        }
    }

    /// f64 values per pixel.
    pub fn values_per_pixel(d_opt: u32) -> usize {
        x_offset(d_opt + 1) + 3 * d_opt as usize
    }

    /// Bytes per pixel.
    pub fn bytes_per_pixel(d_opt: u32) -> usize {
        8 * Progressive::values_per_pixel(d_opt)
    }

    #[inline]
    fn stride(&self) -> usize {
        Progressive::values_per_pixel(self.d_opt)
    }

    /// x of depth d at `pixel` and q of depth d at `pixel` (q is written through the second).
    #[inline]
    fn parts(&mut self, pixel: usize, d: u32) -> (&[f64], &mut [f64; 3]) {
        let st = self.stride();
        let blk = &mut self.data[pixel * st..(pixel + 1) * st];
        let (xs, qs) = blk.split_at_mut(x_offset(self.d_opt + 1));
        let n = d as usize + 2;
        let x = &xs[x_offset(d)..x_offset(d) + 3 * n];
        let q: &mut [f64; 3] = (&mut qs[3 * (d as usize - 1)..3 * d as usize])
            .try_into()
            .expect("3 values");
        (x, q)
    }

    /// q of depth d at `pixel`.
    #[inline]
    pub fn q(&self, pixel: usize, d: u32) -> [f64; 3] {
        let at = pixel * self.stride() + x_offset(self.d_opt + 1) + 3 * (d as usize - 1);
        [self.data[at], self.data[at + 1], self.data[at + 2]]
    }

    /// Adds one task's own samples of a pixel: pixel `src` of the task's systems `task` (one
    /// pass, `count` samples of the pixel) into pixel `dst`:
    /// q += count sum_{i != lt} x_i - x^T A 1 + x_lt h.
    pub fn add_own(&mut self, dst: usize, task: &OptimalAccum, src: usize, count: u32) {
        let st = task.layout.values_per_pixel();
        let sys = &task.data[src * st..(src + 1) * st];
        let dd = task.layout.d_opt as usize;
        for d in 1..=self.d_opt.min(task.layout.d_opt) {
            let n = d as usize + 2;
            let hits = task.hits[src * dd + d as usize - 1] as f64;
            let a = &sys[task.layout.offset(d)..task.layout.offset(d) + block_len(d)];
            let (x, q) = self.parts(dst, d);
            let lt = n - 1;
            for ch in 0..3 {
                let xi = |i: usize| x[i * 3 + ch];
                // x^T A 1 over the packed upper triangle: A_ij (x_i + x_j) for i < j, A_ii x_i.
                let mut xa1 = 0.0;
                let mut p = 0;
                for i in 0..n {
                    xa1 += a[p] * xi(i);
                    p += 1;
                    for j in i + 1..n {
                        xa1 += a[p] * (xi(i) + xi(j));
                        p += 1;
                    }
                }
                let cam: f64 = (0..lt).map(xi).sum();
                q[ch] += count as f64 * cam - xa1 + xi(lt) * hits;
            }
        }
    }

    /// Adds one light-tracing sample recorded in `pixel` (depth d, balance vector w):
    /// q += x_lt - x^T w.
    pub fn add_record(&mut self, pixel: usize, d: u32, w: &[f64]) {
        if d > self.d_opt {
            return;
        }
        let (x, q) = self.parts(pixel, d);
        let lt = w.len() - 1;
        for ch in 0..3 {
            let mut xw = 0.0;
            for (i, wi) in w.iter().enumerate() {
                xw += x[i * 3 + ch] * wi;
            }
            q[ch] += x[lt * 3 + ch] - xw;
        }
    }

    /// After a whole pass is merged: the next passes' x from the totals `acc` (pixel i has
    /// `counts[i]` samples, `light_paths` light paths for the frame), regularised with `kappa`,
    /// once the samples have doubled since the last solve (so O(log spp) solves; x from any
    /// earlier passes keeps the estimate unbiased). Every pass covers every pixel, so the rule
    /// sees the same counts in every tile and the frame.
    pub fn end_pass(&mut self, acc: &OptimalAccum, counts: &[u32], light_paths: u64, kappa: f64) {
        use rayon::prelude::*;
        let spp = counts.iter().copied().max().unwrap_or(0);
        if spp == 0 || (self.solved_at > 0 && spp < self.solved_at.saturating_mul(2)) {
            return;
        }
        self.solved_at = spp;
        let st = self.stride();
        let d_opt = self.d_opt.min(acc.layout.d_opt);
        let xs_len = x_offset(self.d_opt + 1);
        self.data.par_chunks_mut(st).enumerate().for_each_init(
            SolveScratch::default,
            |scratch, (i, blk)| {
                for d in 1..=d_opt {
                    let n = d as usize + 2;
                    let x = &mut blk[..xs_len][x_offset(d)..x_offset(d) + 3 * n];
                    match acc.solution(i, d, counts[i], light_paths, kappa, scratch) {
                        Some(sol) => x.copy_from_slice(sol),
                        None => x.fill(0.0),
                    }
                }
            },
        );
    }

    /// The estimate of depth d at `pixel` after `spp` samples: (sum_i b_i + q) / S.
    pub fn estimate(&self, acc: &OptimalAccum, pixel: usize, d: u32, spp: u32) -> [f64; 3] {
        let bal = acc.balance(pixel, d, spp);
        let q = self.q(pixel, d);
        let s = spp.max(1) as f64;
        [bal[0] + q[0] / s, bal[1] + q[1] / s, bal[2] + q[2] / s]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mis::Layout;

    #[test]
    fn offsets_pack_every_depth() {
        assert_eq!(x_offset(1), 0);
        assert_eq!(x_offset(2), 9);
        assert_eq!(x_offset(3), 21);
        // D_opt 5: x of 3 + 4 + 5 + 6 + 7 = 25 techniques x 3, then 5 x 3 of q.
        assert_eq!(Progressive::values_per_pixel(5), 75 + 15);
    }

    #[test]
    fn zero_x_is_balance_and_q_is_the_control_variate() {
        // Depth 1, one pixel of a 4-pixel frame, S = 2 (N_L = 8): the systems of the hand-built
        // case in `optimal`'s tests.
        let acc = crate::mis::optimal::tests::hand_built_depth1();
        let mut p = Progressive::new(1, 1);
        p.add_own(0, &acc, 0, 2);
        assert_eq!(p.q(0, 1), [0.0; 3]);
        assert_eq!(p.estimate(&acc, 0, 1, 2), acc.balance(0, 1, 2));
        // With x set by hand: q = S sum_{i != lt} x_i - x^T (A 1) + x_lt h, where A 1 = sum W
        // = (0.5, 3.0, 0.5) here (the null sample included).
        let x = [0.3, -0.2, 0.05];
        for (i, v) in x.iter().enumerate() {
            for ch in 0..3 {
                p.data[i * 3 + ch] = *v;
            }
        }
        let mut q = Progressive::new(1, 1);
        q.data[..9].copy_from_slice(&p.data[..9]);
        q.add_own(0, &acc, 0, 2);
        let expected = 2.0 * (0.3 - 0.2) - (0.3 * 0.5 - 0.2 * 3.0 + 0.05 * 0.5) + 0.05;
        assert!((q.q(0, 1)[0] - expected).abs() < 1e-12, "{:?}", q.q(0, 1));
        // The same sample as an out-of-tile record instead: its part of q is x_lt - x^T w.
        let mut r = Progressive::new(1, 1);
        r.data[..9].copy_from_slice(&p.data[..9]);
        r.add_record(0, 1, &[0.0, 0.5, 0.5]);
        assert!((r.q(0, 1)[1] - (0.05 - (-0.1 + 0.025))).abs() < 1e-12);
    }

    #[test]
    fn weights_are_solved_again_once_the_samples_double() {
        let mut acc = OptimalAccum::new(Layout::new(1), 1);
        acc.add_sample(0, 1, &[0.5, 0.5, 0.0], [1.0; 3]);
        let mut p = Progressive::new(1, 1);
        let mut solved = Vec::new();
        for spp in [1, 3, 5, 6, 11, 12] {
            p.end_pass(&acc, &[spp], 4 * spp as u64, 1.0);
            solved.push(p.solved_at);
        }
        assert_eq!(solved, [1, 3, 3, 6, 6, 12]);
        assert!(p.data[..9].iter().any(|&v| v != 0.0), "x was solved");
    }

    #[test]
    fn control_variate_has_zero_mean_on_a_toy_integral() {
        // Two techniques on [0, 1]: p_0 = 1, p_1 = 2u, one sample each per pass; f = u^2, whose
        // integral is 1/3. Any fixed x leaves the mean of the pass estimate at 1/3, and a good
        // one lowers its variance.
        let mut rng = crate::sampler::Pcg32::new(7, 3);
        let f = |u: f64| u * u;
        let pdf = |u: f64| [1.0, 2.0 * u];
        let run = |x: [f64; 2], rng: &mut crate::sampler::Pcg32| -> f64 {
            let samples = [rng.next_f64(), (rng.next_f64()).sqrt()];
            let mut est = 0.0;
            let mut a1 = [0.0; 2];
            for u in samples {
                let p = pdf(u);
                let big_p = p[0] + p[1];
                let w = [p[0] / big_p, p[1] / big_p];
                est += f(u) / big_p;
                a1[0] += w[0];
                a1[1] += w[1];
            }
            // F_alpha = F_bal + sum_k alpha_k (1 - (A 1)_k / n_k), n_k = 1.
            est + x[0] * (1.0 - a1[0]) + x[1] * (1.0 - a1[1])
        };
        let n = 200_000;
        for x in [[0.0, 0.0], [0.5, -0.3], [0.1, 0.25]] {
            let (mut m, mut m2) = (0.0, 0.0);
            for _ in 0..n {
                let v = run(x, &mut rng);
                m += v;
                m2 += v * v;
            }
            m /= n as f64;
            let var = m2 / n as f64 - m * m;
            let se = (var / n as f64).sqrt();
            assert!((m - 1.0 / 3.0).abs() < 4.0 * se, "x {x:?}: {m} +- {se}");
        }
    }
}
