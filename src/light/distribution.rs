//! Discrete distribution proportional to non-negative weights, sampled by CDF inversion.

/// A discrete distribution over indices 0 .. n, proportional to weights (light selection by
/// power).
#[derive(Clone, Debug, Default)]
pub struct Distribution1D {
    /// `cdf[i] = sum of pmf[0..i]`; `cdf.len() = n + 1`, `cdf[n] = 1`.
    cdf: Vec<f64>,
    pmf: Vec<f32>,
}

impl Distribution1D {
    /// `None` when no weight is positive (or any is negative / not finite).
    pub fn new(weights: &[f32]) -> Option<Self> {
        if weights.iter().any(|w| !(w.is_finite() && *w >= 0.0)) {
            return None;
        }
        let total: f64 = weights.iter().map(|&w| w as f64).sum();
        if !(total > 0.0) {
            return None;
        }
        let mut cdf = Vec::with_capacity(weights.len() + 1);
        let mut acc = 0.0f64;
        cdf.push(0.0);
        for &w in weights {
            acc += w as f64;
            cdf.push(acc / total);
        }
        *cdf.last_mut().expect("non-empty") = 1.0;
        let pmf = weights.iter().map(|&w| (w as f64 / total) as f32).collect();
        Some(Distribution1D { cdf, pmf })
    }

    /// Number of outcomes n.
    pub fn len(&self) -> usize {
        self.pmf.len()
    }

    /// True when there are no outcomes.
    pub fn is_empty(&self) -> bool {
        self.pmf.is_empty()
    }

    /// Probability of index `i`.
    #[inline]
    pub fn pmf(&self, i: usize) -> f32 {
        self.pmf[i]
    }

    /// Index with probability pmf(index), for u in [0, 1).
    #[inline]
    pub fn sample(&self, u: f32) -> (usize, f32) {
        let u = u as f64;
        // First i with cdf[i + 1] > u, skipping zero-weight entries.
        let mut lo = 0usize;
        let mut hi = self.pmf.len();
        while lo < hi {
            let mid = (lo + hi) / 2;
            if self.cdf[mid + 1] <= u {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        let mut i = lo.min(self.pmf.len() - 1);
        while self.pmf[i] == 0.0 && i > 0 {
            i -= 1;
        }
        (i, self.pmf[i])
    }
}

impl Distribution1D {
    /// [`Distribution1D::sample`] and where in its bin `u` fell, in [0, 1): the same u reused to
    /// place a continuous sample inside the bin.
    #[inline]
    pub fn sample_remapped(&self, u: f32) -> (usize, f32, f32) {
        let (i, p) = self.sample(u);
        let lo = self.cdf[i];
        let width = self.cdf[i + 1] - lo;
        let r = if width > 0.0 {
            ((u as f64 - lo) / width).clamp(0.0, 1.0 - f64::EPSILON) as f32
        } else {
            0.5
        };
        (i, p, r.min(1.0 - f32::EPSILON))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frequencies_follow_weights() {
        let d = Distribution1D::new(&[1.0, 0.0, 3.0, 4.0]).unwrap();
        let mut counts = [0usize; 4];
        let n = 80_000;
        for k in 0..n {
            let u = (k as f32 + 0.5) / n as f32;
            let (i, p) = d.sample(u);
            assert_eq!(p, d.pmf(i));
            counts[i] += 1;
        }
        assert_eq!(counts[1], 0);
        assert!((counts[0] as f32 / n as f32 - 0.125).abs() < 1e-3);
        assert!((counts[3] as f32 / n as f32 - 0.5).abs() < 1e-3);
        assert!(Distribution1D::new(&[0.0, 0.0]).is_none());
        assert!(Distribution1D::new(&[1.0, f32::NAN]).is_none());
    }
}
