//! The optimal-MIS direct estimator per pixel and per path depth (Cailleau, Kerbiriou, Pipelin,
//! Salaün et al., "Optimal Multiple Importance Sampling for Bidirectional Path Tracing", §V-A,
//! Algorithm 1 and Appendix A; Kondapaneni et al., "Optimal Multiple Importance Sampling", ACM
//! TOG 38(4), 2019).
//!
//! For pixel p and depth d (N = d + 2 techniques, (s, t = d + 2 - s) for s = 0 ..= d + 1, the last
//! one light tracing) we accumulate, over every full-path sample X with balance-weight vector W:
//!
//!   A += W W^T,      b += (C(X) W_s(X)) W,
//!
//! where C = f / p_s is the sample's unweighted contribution in film units (the quantity BDPT
//! splats). Zero-contribution samples update A too; a technique that produced no path adds a null
//! sample only it could make (A_ss += 1); light-tracing samples that landed in p are counted (h),
//! and the N_L - h that did not are added to A_lt,lt before solving.
//!
//! Sample counts: with S samples per pixel, each camera technique (t >= 2) has n = S
//! samples for p, and light tracing n = N_L = W H S light paths (one per pixel sample of the
//! frame). With film-wide camera densities, the balance weights BDPT computes are exactly
//! n_i p_i / sum_k n_k p_k for these counts, and f / sum_k n_k p_k = C W_s / S for every
//! technique (the pixel's importance W H We and the light-tracing density 1 / N_L cancel).
//! Hence with b as accumulated (no 1/S), the solution x of A x = b gives
//!
//!   F = sum_i (n_i / S) x_i = sum_{camera techniques} x_i + W H x_lt      (Appendix A, eq. 20).
//!
//! One technique reduces to plain Monte Carlo: A = S, b = sum C, F = sum C / S.
//!
//! Beyond the paper: at low sample counts A is estimated from few samples and its solution is
//! noisy ("salt and pepper", Cailleau et al. Fig. 7): a technique that never dominated has a tiny A_ii
//! and a wild x_i. We regularise toward the balance-heuristic solution x_bal (x_bal,i = b_i /
//! n_i, which gives exactly the balance estimate sum_i b_i / S) with kappa pseudo-samples:
//! solve (A + kappa M) x = b + kappa M x_bal, M = diag(n_i / S). `E[A_ii] <= n_i`, so the prior
//! weighs like kappa of the S samples for a dominant technique and far more for a technique the
//! samples barely saw; its pull vanishes as O(1/S), like the estimator's own bias.

use super::solve::solve_psd;

/// Default regularisation strength kappa (pseudo-samples pulling toward the balance solution).
pub const DEFAULT_KAPPA: f64 = 1.0;

/// Largest depth weighted optimally where no pilot chooses it (`RenderSettings` built directly;
/// jobs default to the pilot, `job::optimal_depth`). Measured on four scenes (BENCHMARKS.md,
/// "Optimal against balance MIS"): the equal-spp gain is at depth 1, and depths 2-5 stay within 2 % of balance at equal
/// spp while their systems cost 10-30 % of the samples at equal time.
pub const DEFAULT_OPTIMAL_MAX_DEPTH: u32 = 1;

/// Largest depth the optimal estimator supports (N = d + 2 <= 64 techniques).
pub const MAX_OPTIMAL_DEPTH: u32 = 62;

/// Where each depth's system lives inside a pixel's block of f64 values.
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    /// Depths 1 ..= `d_opt` are weighted optimally.
    pub d_opt: u32,
    /// offsets[d - 1] = start of depth d's block; the block holds the packed upper triangle of A
    /// (N (N + 1) / 2 values, row-major) followed by b (N x 3, row-major).
    offsets: Vec<usize>,
    stride: usize,
}

/// Values (A and b) of depth d's system.
pub const fn block_len(d: u32) -> usize {
    let n = d as usize + 2;
    n * (n + 1) / 2 + 3 * n
}

/// Index of A_ij (i <= j) in the packed upper triangle of an n x n matrix.
#[inline]
fn packed(n: usize, i: usize, j: usize) -> usize {
    i * (2 * n - i + 1) / 2 + (j - i)
}

/// A += W W^T, b += c W on one system of `n` techniques: the packed upper triangle of A, then b.
/// Inlined into `add_sample`'s cases with a constant `n`, where the compiler unrolls it. A
/// technique of weight 0 adds +0 to its row, which leaves every value as it was (A's entries are
/// sums of products of non-negative weights, so none is -0).
#[inline(always)]
fn add_outer(blk: &mut [f64], n: usize, w: &[f64], c: [f64; 3]) {
    let (a, b) = blk[..block_len(n as u32 - 2)].split_at_mut(n * (n + 1) / 2);
    let w = &w[..n];
    let mut idx = 0;
    for i in 0..n {
        let wi = w[i];
        for wj in &w[i..] {
            a[idx] += wi * wj;
            idx += 1;
        }
        for ch in 0..3 {
            b[i * 3 + ch] += c[ch] * wi;
        }
    }
}

impl Layout {
    /// The layout of depths 1 ..= `d_opt` (clamped to [`MAX_OPTIMAL_DEPTH`]).
    pub fn new(d_opt: u32) -> Layout {
        let d_opt = d_opt.min(MAX_OPTIMAL_DEPTH);
        let mut offsets = Vec::with_capacity(d_opt as usize);
        let mut off = 0;
        for d in 1..=d_opt {
            offsets.push(off);
            off += block_len(d);
        }
        Layout {
            d_opt,
            offsets,
            stride: off,
        }
    }

    /// f64 values per pixel.
    pub fn values_per_pixel(&self) -> usize {
        self.stride
    }

    /// Bytes per pixel of the accumulators: the f64 systems and one u32 light-tracing count per
    /// depth.
    pub fn bytes_per_pixel(&self) -> usize {
        self.stride * 8 + self.d_opt as usize * 4
    }

    /// Start of depth d's block within a pixel's values.
    #[inline]
    pub(crate) fn offset(&self, d: u32) -> usize {
        self.offsets[d as usize - 1]
    }
}

/// The accumulators of a set of pixels (a tile, or the frame).
#[derive(Clone, Debug)]
pub struct OptimalAccum {
    /// Where each depth's system lives in a pixel's block.
    pub layout: Layout,
    /// Number of pixels.
    pub pixels: usize,
    /// `pixels` blocks of `layout.values_per_pixel()` values.
    pub data: Vec<f64>,
    /// Light-tracing samples of depth d that landed in the pixel: pixels x d_opt.
    pub hits: Vec<u32>,
}

impl OptimalAccum {
    /// Zeroed accumulators for `pixels` pixels.
    pub fn new(layout: Layout, pixels: usize) -> OptimalAccum {
        let data = vec![0.0; pixels * layout.values_per_pixel()];
        let hits = vec![0; pixels * layout.d_opt as usize];
        OptimalAccum {
            layout,
            pixels,
            data,
            hits,
        }
    }

    #[inline]
    fn block(&mut self, pixel: usize, d: u32) -> &mut [f64] {
        let start = pixel * self.layout.stride + self.layout.offset(d);
        &mut self.data[start..start + block_len(d)]
    }

    /// A += W W^T, b += c W (Algorithm 1, lines 6-7, for one sample).
    #[inline]
    pub fn add_sample(&mut self, pixel: usize, d: u32, w: &[f64], c: [f64; 3]) {
        let n = d as usize + 2;
        debug_assert_eq!(w.len(), n);
        let blk = self.block(pixel, d);
        // The depths a job weights optimally (D_opt <= 5 in practice) get a loop the compiler
        // unrolls without bounds checks; every value receives the same one addition either way.
        match n {
            3 => add_outer(blk, 3, w, c),
            4 => add_outer(blk, 4, w, c),
            5 => add_outer(blk, 5, w, c),
            6 => add_outer(blk, 6, w, c),
            7 => add_outer(blk, 7, w, c),
            _ => add_outer(blk, n, w, c),
        }
    }

    /// A null sample only technique `s` could make: A_ss += 1.
    #[inline]
    pub fn add_unsampled(&mut self, pixel: usize, d: u32, s: u32) {
        let n = d as usize + 2;
        let idx = packed(n, s as usize, s as usize);
        self.block(pixel, d)[idx] += 1.0;
    }

    /// A light-tracing sample of depth d landed in the pixel.
    #[inline]
    pub fn add_hit(&mut self, pixel: usize, d: u32) {
        self.hits[pixel * self.layout.d_opt as usize + d as usize - 1] += 1;
    }

    /// Adds pixel `src` of `other` into pixel `dst` of `self` (same layout).
    pub fn add_pixel(&mut self, dst: usize, other: &OptimalAccum, src: usize) {
        let st = self.layout.stride;
        let a = &mut self.data[dst * st..(dst + 1) * st];
        let b = &other.data[src * st..(src + 1) * st];
        for (x, y) in a.iter_mut().zip(b) {
            *x += y;
        }
        let dd = self.layout.d_opt as usize;
        for k in 0..dd {
            self.hits[dst * dd + k] += other.hits[src * dd + k];
        }
    }

    /// Solves depth d's system of `pixel`. `spp` samples of this pixel have been taken, and
    /// `light_paths` light paths for the whole frame (N_L: one per pixel sample of the frame, so
    /// W H spp when every pixel has `spp`, which the balance weights of the samples assume).
    /// `kappa` is the regularisation strength toward the balance solution (0 = the plain direct
    /// estimator).
    pub fn solve(
        &self,
        pixel: usize,
        d: u32,
        spp: u32,
        light_paths: u64,
        kappa: f64,
        scratch: &mut SolveScratch,
    ) -> [f64; 3] {
        let n = d as usize + 2;
        let m = technique_counts(n, spp, light_paths);
        if let Some(x) = self.solution(pixel, d, spp, light_paths, kappa, scratch) {
            let mut f = [0.0f64; 3];
            for i in 0..n {
                for ch in 0..3 {
                    f[ch] += m(i) * x[i * 3 + ch];
                }
            }
            if f.iter().all(|v| v.is_finite()) {
                return f;
            }
        }
        // Cannot happen for a PSD system; fall back to the balance estimate all the same.
        self.balance(pixel, d, spp)
    }

    /// The solution x (N x 3, row-major) of depth d's regularised system at `pixel` (arguments
    /// as for `solve`, whose estimate is sum_i m_i x_i), or None when it is not finite.
    pub fn solution<'s>(
        &self,
        pixel: usize,
        d: u32,
        spp: u32,
        light_paths: u64,
        kappa: f64,
        scratch: &'s mut SolveScratch,
    ) -> Option<&'s [f64]> {
        let n = d as usize + 2;
        let start = pixel * self.layout.stride + self.layout.offset(d);
        let blk = &self.data[start..start + block_len(d)];
        let (ap, bp) = blk.split_at(n * (n + 1) / 2);
        let s = spp.max(1) as f64;
        let lt = n - 1;
        let n_l = light_paths as f64;
        let m = technique_counts(n, spp, light_paths);
        scratch.a.clear();
        scratch.a.resize(n * n, 0.0);
        let a = &mut scratch.a;
        for i in 0..n {
            for j in i..n {
                let v = ap[packed(n, i, j)];
                a[i * n + j] = v;
                a[j * n + i] = v;
            }
        }
        let hits = self.hits[pixel * self.layout.d_opt as usize + d as usize - 1] as f64;
        a[lt * n + lt] += (n_l - hits).max(0.0);
        scratch.b.clear();
        scratch.b.extend_from_slice(bp);
        let b = &mut scratch.b;
        if kappa > 0.0 {
            // kappa pseudo-samples of a prior centred on the balance solution:
            // (A + kappa M) x = b + kappa M x_bal, M = diag(n) / S, x_bal,i = b_i / n_i.
            for i in 0..n {
                let pull = kappa * m(i);
                a[i * n + i] += pull;
                for ch in 0..3 {
                    b[i * 3 + ch] += kappa * bp[i * 3 + ch] / s;
                }
            }
        }
        solve_psd(a, n, b, 3, 1e-12, &mut scratch.factor);
        b.iter().all(|v| v.is_finite()).then_some(&b[..])
    }

    /// Samples added to depth d's system at `pixel` (null samples included): every sample adds
    /// W W^T with sum_i W_i = 1, so the entries of A sum to the sample count.
    pub fn samples_taken(&self, pixel: usize, d: u32) -> f64 {
        let n = d as usize + 2;
        let start = pixel * self.layout.stride + self.layout.offset(d);
        let a = &self.data[start..start + n * (n + 1) / 2];
        let mut total = 0.0;
        for i in 0..n {
            for j in i..n {
                total += if i == j { 1.0 } else { 2.0 } * a[packed(n, i, j)];
            }
        }
        total
    }

    /// The balance-heuristic estimate of depth d at `pixel` from the same accumulators:
    /// sum_i b_i / S (since the W_i of a sample sum to one).
    pub fn balance(&self, pixel: usize, d: u32, spp: u32) -> [f64; 3] {
        let n = d as usize + 2;
        let start = pixel * self.layout.stride + self.layout.offset(d);
        let b = &self.data[start + n * (n + 1) / 2..start + block_len(d)];
        let mut g = [0.0; 3];
        for i in 0..n {
            for ch in 0..3 {
                g[ch] += b[i * 3 + ch] / spp.max(1) as f64;
            }
        }
        g
    }
}

/// Technique counts relative to S, m_i = n_i / S: 1 for camera techniques, N_L / S (= W H) for
/// light tracing (the last of the n).
fn technique_counts(n: usize, spp: u32, light_paths: u64) -> impl Fn(usize) -> f64 {
    let s = spp.max(1) as f64;
    let n_l = light_paths as f64;
    move |i: usize| if i == n - 1 { n_l / s } else { 1.0 }
}

/// Reusable buffers for `solve`.
#[derive(Default)]
pub struct SolveScratch {
    a: Vec<f64>,
    b: Vec<f64>,
    factor: Vec<f64>,
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// One pixel's depth-1 systems of the hand-built case below (also used by `progressive`).
    pub(crate) fn hand_built_depth1() -> OptimalAccum {
        let mut acc = OptimalAccum::new(Layout::new(1), 1);
        acc.add_sample(0, 1, &[0.5, 0.5, 0.0], [1.0; 3]);
        acc.add_unsampled(0, 1, 1);
        acc.add_sample(0, 1, &[0.0, 1.0, 0.0], [0.0; 3]);
        acc.add_sample(0, 1, &[0.0, 0.5, 0.5], [4.0; 3]);
        acc.add_hit(0, 1);
        acc
    }

    #[test]
    fn unrolled_updates_equal_the_definition_at_every_system_size() {
        // Depths 1 ..= 8: the unrolled systems (N = 3 ..= 7) and the general loop (N >= 8) add
        // exactly W_i W_j to A_ij (i <= j, packed) and C_c W_i to b, zeros included, bit for bit.
        let dmax = 8;
        let mut acc = OptimalAccum::new(Layout::new(dmax), 2);
        let mut want = acc.data.clone();
        let mut rng = crate::sampler::Pcg32::new(7, 1);
        for k in 0..200 {
            let pixel = k % 2;
            let d = 1 + (k as u32 % dmax);
            let n = d as usize + 2;
            let mut w: Vec<f64> = (0..n).map(|_| rng.next_f64()).collect();
            w[k % n] = 0.0;
            let sum: f64 = w.iter().sum();
            w.iter_mut().for_each(|x| *x /= sum);
            let c = [rng.next_f64(), 2.0 * rng.next_f64(), 0.0];
            acc.add_sample(pixel, d, &w, c);
            let start = pixel * acc.layout.values_per_pixel() + acc.layout.offset(d);
            for i in 0..n {
                for j in i..n {
                    want[start + packed(n, i, j)] += w[i] * w[j];
                }
                for (ch, cc) in c.iter().enumerate() {
                    want[start + n * (n + 1) / 2 + i * 3 + ch] += cc * w[i];
                }
            }
        }
        assert!(
            acc.data
                .iter()
                .zip(&want)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
    }

    #[test]
    fn layout_matches_the_design_memory_formula() {
        // 155 values per pixel at D_opt = 5.
        let l = Layout::new(5);
        assert_eq!(l.values_per_pixel(), 155);
        assert_eq!(l.bytes_per_pixel(), 155 * 8 + 5 * 4);
        assert_eq!(Layout::new(1).values_per_pixel(), 6 + 9);
    }

    #[test]
    fn one_camera_technique_reduces_to_plain_monte_carlo() {
        // Depth 1 with every sample made by technique 0 alone (W = e_0), light tracing never
        // landing: A = diag(S, 0, N_L), b_0 = sum C.
        let mut acc = OptimalAccum::new(Layout::new(1), 1);
        let spp = 8;
        let values = [0.5, 0.0, 2.0, 1.0, 0.0, 0.0, 3.0, 0.25];
        for v in values {
            acc.add_sample(0, 1, &[1.0, 0.0, 0.0], [v, 2.0 * v, 0.0]);
        }
        let mut sc = SolveScratch::default();
        let f = acc.solve(0, 1, spp, 16 * spp as u64, 0.0, &mut sc);
        let mean = values.iter().sum::<f64>() / spp as f64;
        assert!(
            (f[0] - mean).abs() < 1e-12 && (f[1] - 2.0 * mean).abs() < 1e-12,
            "{f:?}"
        );
        assert_eq!(f[2], 0.0);
        // Regularisation toward balance cannot move a one-technique estimate.
        let g = acc.solve(0, 1, spp, 16 * spp as u64, 4.0, &mut sc);
        assert!((g[0] - mean).abs() < 1e-12);
    }

    #[test]
    fn closed_form_with_light_tracing_count_and_unsampled_rule() {
        // Hand-built depth-1 case (N = 3: techniques (0,3), (1,2), (2,1)), frame of 4 pixels,
        // S = 2 samples per pixel, so N_L = 8 light paths.
        //  sample 1: camera, W = (0.5, 0.5, 0), C W_s = 1 (from technique 0)
        //  sample 2: technique 1 unsampled (subpath too short): A_11 += 1
        //  sample 3: technique 0 zero contribution with W = (0, 1, 0)... (a path only 1 makes)
        //  light tracing: 1 hit in this pixel with W = (0, 0.5, 0.5), C W_s = 4.
        let acc = hand_built_depth1();
        // A = [[.25, .25, 0], [.25, .25+1+1+.25, .25], [0, .25, .25 + (8 - 1)]]
        //   = [[.25, .25, 0], [.25, 2.5, .25], [0, .25, 7.25]]
        // b = 1 * (.5, .5, 0) + 4 * (0, .5, .5) = (.5, 2.5, 2)
        let a = [[0.25, 0.25, 0.0], [0.25, 2.5, 0.25], [0.0, 0.25, 7.25]];
        let b = [0.5, 2.5, 2.0];
        // Solve by Cramer's rule.
        let det = |m: [[f64; 3]; 3]| {
            m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
                - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
        };
        let d = det(a);
        let mut x = [0.0; 3];
        for (k, xk) in x.iter_mut().enumerate() {
            let mut m = a;
            for r in 0..3 {
                m[r][k] = b[r];
            }
            *xk = det(m) / d;
        }
        let expected = x[0] + x[1] + 4.0 * x[2]; // W H = 4 for light tracing
        let mut sc = SolveScratch::default();
        let f = acc.solve(0, 1, 2, 8, 0.0, &mut sc);
        assert!((f[0] - expected).abs() < 1e-12, "{f:?} vs {expected}");
        // The balance estimate from the same accumulators: sum b / S = 5 / 2.
        assert!((acc.balance(0, 1, 2)[0] - 2.5).abs() < 1e-12);
        // Infinite regularisation gives the balance estimate back.
        let g = acc.solve(0, 1, 2, 8, 1e12, &mut sc);
        assert!((g[0] - 2.5).abs() < 1e-6, "{g:?}");
    }
}
