//! The statistics helpers themselves.

use crate::grid::*;
use crate::stats::*;
use crate::support::INTEGRATION_TOL;
use omis::geometry::Vec3;
use omis::sampler::Pcg32;
use std::f64::consts::PI as PI64;

#[test]
fn statistics_helpers_are_correct() {
    // Reference chi-square tail probabilities: Q(dof / 2, x / 2) from mpmath.gammainc at 30 digits.
    let refs = [
        (3.841_458_820_694_124, 1, 0.05),
        (18.307_038_053_275_146, 10, 0.05),
        (100.0, 100, 0.481_191_684_527_956_7),
        (150.0, 100, 0.000_903_932_042_354_009),
        (30.0, 2, 3.059_023_205_018_258e-7),
        (600.0, 480, 0.000_152_204_284_508_461_6),
    ];
    for (x, dof, p) in refs {
        let got = chi2_sf(x, dof);
        assert!(
            (got - p).abs() < 1e-9 * p,
            "chi2_sf({x}, {dof}) = {got}, expected {p}"
        );
    }
    assert!((sidak(0.05, 1) - 0.05).abs() < 1e-15);
    assert!((1.0 - (1.0 - sidak(1e-4, 100)).powi(100) - 1e-4).abs() < 1e-12);
    // Pooling: small cells merge; an impossible observation is an error.
    // Sorted: 1.0, 1.5, 3.5 pool to 6 (>= 5), then 10 stands alone: two cells, one dof.
    let r = chi2_pooled(&[10.0, 1.0, 2.0, 1.0], &[10.0, 1.5, 3.5, 1.0], 5.0).unwrap();
    assert_eq!(r.dof, 1);
    let stat = 0.0 + (4.0f64 - 6.0).powi(2) / 6.0;
    assert!((r.stat - stat).abs() < 1e-12, "{r:?}");
    // Pooling goes on past a small cell until the pool holds 5 expected samples.
    let r = chi2_pooled(&[10.0, 1.0, 2.0, 1.0], &[10.0, 1.5, 1.5, 1.0], 5.0).unwrap();
    assert_eq!(r.dof, 0);
    assert!(chi2_pooled(&[1.0, 9.0], &[0.0, 10.0], 5.0).is_err());

    // The grid integrates densities exactly where they are smooth and accurately across a
    // horizon that cuts bins diagonally.
    let pole = Vec3::new(0.2, 0.5, -0.6).normalize();
    let h = Vec3::new(0.1, -0.3, 0.9).normalize();
    let grid = Grid::new(pole, &[h]);
    let uniform: f64 = grid.integrate(&|_| 0.25 / PI64).iter().sum();
    assert!((uniform - 1.0).abs() < 1e-9, "{uniform}");
    let lambert: f64 = grid
        .integrate(&|w| (w.dot(h) as f64).max(0.0) / PI64)
        .iter()
        .sum();
    assert!((lambert - 1.0).abs() < 1e-5, "{lambert}");
    // A density with a jump at the horizon (uniform hemisphere): the worst case for the cut.
    let hemi: f64 = grid
        .integrate(&|w| if w.dot(h) > 0.0 { 0.5 / PI64 } else { 0.0 })
        .iter()
        .sum();
    println!(
        "integration errors: cosine {:.2e}, hemisphere {:.2e}",
        lambert - 1.0,
        hemi - 1.0
    );
    assert!((hemi - 1.0).abs() < INTEGRATION_TOL / 4.0, "{hemi}");
    // Binning agrees with the integration domains: a direction generated inside a bin lands in it.
    let mut rng = Pcg32::new(1212, 0);
    for _ in 0..10_000 {
        let cell = (rng.next_u32() as usize) % grid.cells();
        let (i, j) = (cell / N_PHI, cell % N_PHI);
        let z = Grid::cos_edge(i + 1)
            + (0.05 + 0.9 * rng.next_f64()) * (Grid::cos_edge(i) - Grid::cos_edge(i + 1));
        let p = Grid::phi_edge(j) + (0.05 + 0.9 * rng.next_f64()) * (2.0 * PI64 / N_PHI as f64);
        assert_eq!(grid.cell_of(grid.dir(z, p)), cell);
    }
}
