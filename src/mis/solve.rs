//! Small dense symmetric positive semi-definite systems: pivoted Cholesky (LDL^T with symmetric
//! diagonal pivoting), which reveals rank and leaves directions it cannot resolve at zero.

/// Solves `a x = b` for a symmetric positive semi-definite `a` (n x n, row-major, only read) and
/// `m` right-hand sides (`b` is n x m, row-major; overwritten with x). The system is first
/// scaled to unit diagonal, A' = D^-1/2 A D^-1/2, b' = D^-1/2 b, x = D^-1/2 x' (Jacobi scaling),
/// so that the rank decision does not depend on the unknowns' units: pivots of the scaled
/// system below `rel_tol` are treated as zero and their unknowns set to 0 (the basic solution on
/// the well-determined subspace), as are the unknowns of zero (or non-finite) diagonal entries,
/// whose rows are zero in a PSD matrix. Returns the numerical rank.
///
/// Algorithm: outer-product LDL^T with complete (diagonal) pivoting, Golub & Van Loan §4.2.9,
/// after Jacobi scaling, which is within a factor n of the best diagonal scaling (van der Sluis
/// 1969; Higham 2002, Thm. 7.5).
pub fn solve_psd(
    a: &[f64],
    n: usize,
    b: &mut [f64],
    m: usize,
    rel_tol: f64,
    scratch: &mut Vec<f64>,
) -> usize {
    // The work arrays live on the stack; the systems of D_opt <= 6 get small ones, so that a
    // 3 x 3 solve does not zero kilobytes of arrays it never reads.
    if n <= 8 {
        solve_with::<8>(a, n, b, m, rel_tol, scratch)
    } else {
        solve_with::<64>(a, n, b, m, rel_tol, scratch)
    }
}

/// `solve_psd` for systems of at most `CAP` unknowns.
fn solve_with<const CAP: usize>(
    a: &[f64],
    n: usize,
    b: &mut [f64],
    m: usize,
    rel_tol: f64,
    scratch: &mut Vec<f64>,
) -> usize {
    debug_assert_eq!(a.len(), n * n);
    debug_assert_eq!(b.len(), n * m);
    let mut perm: [usize; CAP] = [0; CAP];
    assert!(
        n <= perm.len(),
        "system of {n} techniques is larger than supported"
    );
    for (i, p) in perm.iter_mut().enumerate().take(n) {
        *p = i;
    }
    // D^-1/2, with 0 for unknowns whose diagonal is not positive and finite.
    let mut scale = [0.0f64; CAP];
    for (i, sc) in scale.iter_mut().enumerate().take(n) {
        let d = a[i * n + i];
        if d > 0.0 && d.is_finite() {
            *sc = 1.0 / d.sqrt();
        }
    }
    if scale[..n].iter().all(|&sc| sc == 0.0) {
        b.fill(0.0);
        return 0;
    }
    scratch.clear();
    scratch.resize(n * n, 0.0);
    let l = &mut scratch[..];
    for i in 0..n {
        for j in 0..n {
            l[i * n + j] = if i == j {
                if scale[i] > 0.0 { 1.0 } else { 0.0 }
            } else {
                a[i * n + j] * scale[i] * scale[j]
            };
        }
        for c in 0..m {
            b[i * m + c] *= scale[i];
        }
    }
    // The scaled diagonal is 1 (or 0): the tolerance is relative to 1.
    let tol = rel_tol;
    let mut rank = 0;
    // Column k below the pivot (entries k + 1 .. n are written before they are read).
    let mut col = [0.0f64; CAP];
    // Factor in place: after step k, rows/cols perm[..k] hold L (unit lower) and D on the diagonal.
    for k in 0..n {
        // Pivot: largest remaining diagonal.
        let (mut best, mut bv) = (k, l[perm[k] * n + perm[k]]);
        for (i, &pi) in perm.iter().enumerate().take(n).skip(k + 1) {
            let v = l[pi * n + pi];
            if v > bv {
                best = i;
                bv = v;
            }
        }
        if !(bv > tol) {
            break;
        }
        perm.swap(k, best);
        let pk = perm[k];
        let d = l[pk * n + pk];
        for i in k + 1..n {
            col[i] = l[perm[i] * n + pk];
        }
        for i in k + 1..n {
            let pi = perm[i];
            let lik = col[i] / d;
            for j in k + 1..=i {
                let pj = perm[j];
                let v = l[pi * n + pj] - lik * col[j];
                l[pi * n + pj] = v;
                l[pj * n + pi] = v;
            }
        }
        for i in k + 1..n {
            let pi = perm[i];
            let lik = col[i] / d;
            l[pi * n + pk] = lik;
            l[pk * n + pi] = lik;
        }
        rank = k + 1;
    }
    // Solve for each right-hand side: L y = P b, D z = y, L^T w = z, x = P^T w (unknowns past
    // the rank are 0).
    let mut y = [0.0f64; CAP];
    for c in 0..m {
        for k in 0..rank {
            let pk = perm[k];
            let mut v = b[pk * m + c];
            for (j, yj) in y.iter().enumerate().take(k) {
                v -= l[pk * n + perm[j]] * yj;
            }
            y[k] = v;
        }
        for k in 0..rank {
            let pk = perm[k];
            y[k] /= l[pk * n + pk];
        }
        for k in (0..rank).rev() {
            let pk = perm[k];
            let mut v = y[k];
            for j in k + 1..rank {
                v -= l[perm[j] * n + pk] * y[j];
            }
            y[k] = v;
        }
        for k in 0..n {
            let pk = perm[k];
            b[pk * m + c] = if k < rank { y[k] * scale[pk] } else { 0.0 };
        }
    }
    rank
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mul(a: &[f64], n: usize, x: &[f64]) -> Vec<f64> {
        (0..n)
            .map(|i| (0..n).map(|j| a[i * n + j] * x[j]).sum())
            .collect()
    }

    #[test]
    fn solves_definite_systems() {
        // Sizes on both sides of the small work arrays (8 unknowns).
        for n in [1, 5, 8, 9, 20] {
            solves_definite_system(n);
        }
    }

    fn solves_definite_system(n: usize) {
        // A = M M^T + I for a fixed M.
        let m: Vec<f64> = (0..n * n)
            .map(|k| ((k * 7 + 3) % 11) as f64 / 5.0 - 1.0)
            .collect();
        let mut a = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..n {
                a[i * n + j] = (0..n).map(|k| m[i * n + k] * m[j * n + k]).sum::<f64>()
                    + if i == j { 1.0 } else { 0.0 };
            }
        }
        let x_true: Vec<f64> = [1.0, -2.0, 0.5, 3.0, 0.0]
            .into_iter()
            .cycle()
            .take(n)
            .collect();
        let rhs = mul(&a, n, &x_true);
        let mut b = rhs.clone();
        let mut s = Vec::new();
        assert_eq!(solve_psd(&a, n, &mut b, 1, 1e-12, &mut s), n);
        for (x, t) in b.iter().zip(&x_true) {
            assert!((x - t).abs() < 1e-9, "n = {n}: {b:?}");
        }
    }

    #[test]
    fn badly_scaled_unknowns_keep_their_pivots() {
        // One unknown on a scale 1e13 times the others' (the light-tracing count of a 4K frame
        // at high spp next to camera techniques): relative to the largest diagonal the camera
        // block's pivots are below any sensible tolerance, yet it is perfectly conditioned.
        let big = 1e13;
        let a = [2.0, 1.0, 0.0, 1.0, 2.0, 0.0, 0.0, 0.0, big];
        let x_true = [1.0, -1.0, 3.0];
        let mut b = mul(&a, 3, &x_true);
        let mut s = Vec::new();
        assert_eq!(solve_psd(&a, 3, &mut b, 1, 1e-12, &mut s), 3);
        for (x, t) in b.iter().zip(&x_true) {
            assert!((x - t).abs() < 1e-12 * t.abs().max(1.0), "{b:?}");
        }
    }

    #[test]
    fn rank_deficient_and_zero_rows() {
        // Technique 1 never sampled (zero row/column); techniques 0 and 2 identical.
        let a = [4.0, 0.0, 4.0, 0.0, 0.0, 0.0, 4.0, 0.0, 4.0];
        let mut b = [8.0, 10.0, 0.0, 0.0, 8.0, 10.0];
        let mut s = Vec::new();
        let r = solve_psd(&a, 3, &mut b, 2, 1e-10, &mut s);
        assert_eq!(r, 1);
        // The basic solution puts everything on one of the two equal techniques.
        let x0 = [b[0], b[2], b[4]];
        assert!((x0[0] + x0[2] - 2.0).abs() < 1e-12 && x0[1] == 0.0);
        assert!(b.iter().all(|v| v.is_finite()));
        let zero = [0.0; 4];
        let mut bz = [1.0, 2.0];
        assert_eq!(solve_psd(&zero, 2, &mut bz, 1, 1e-10, &mut s), 0);
        assert_eq!(bz, [0.0, 0.0]);
    }
}
