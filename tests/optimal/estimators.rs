//! The optimal estimator against balance-weighted BDPT and a long path-traced reference.

use crate::common::load;
use crate::support::optimal;
use omis::film::Image;
use omis::integrator::RenderSettings;
use omis::job::Resolved;
use omis::mis::MisKind;
use omis::sampler::SamplerKind;
use omis::scene::Scene;

#[test]
fn balance_from_the_optimal_accumulators_equals_balance_weighted_bdpt() {
    // Same seed, same random numbers: sum_i b_i / S of every optimal system plus the balance
    // part of the other depths must reproduce balance-weighted BDPT. This checks the b
    // bookkeeping (C W_s W, light-tracing routing, normalisation) end to end.
    let scene = load("cornell-box-small-light.json", 24, 24);
    let mut s = optimal(8, 5, 3);
    let out = Resolved::fixed(&scene, &s, 8, 64).render_in_process(&scene, &|_| {});
    s.mis = MisKind::Balance;
    let bal = Resolved::fixed(&scene, &s, 8, 64)
        .render_in_process(&scene, &|_| {})
        .image();
    let f = &out.film;
    let o = f.acc.optimal.as_ref().expect("optimal systems");
    let mut worst: f64 = 0.0;
    for i in 0..bal.pixels.len() {
        let n = f.acc.sums.count[i] as f64;
        for c in 0..3 {
            let mut v = (f.acc.sums.sum[i][c] + f.acc.splat[i][c]) / n;
            for d in 1..=3 {
                v += o.balance(i, d, f.acc.sums.count[i])[c];
            }
            let b = bal.pixels[i][c] as f64;
            worst = worst.max((v - b).abs() / b.abs().max(1e-3));
        }
    }
    assert!(worst < 1e-4, "worst relative difference {worst}");
}

/// Mean and standard error over seeds of the mean of region `r` in channel `c`.
fn region_stats(imgs: &[Image], r: (usize, usize, usize, usize), c: usize) -> (f64, f64) {
    let v: Vec<f64> = imgs
        .iter()
        .map(|img| {
            let mut s = 0.0;
            for y in r.1..r.3 {
                for x in r.0..r.2 {
                    s += img.get(x, y)[c] as f64;
                }
            }
            s / ((r.2 - r.0) * (r.3 - r.1)) as f64
        })
        .collect();
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0);
    (m, (var / n).sqrt())
}

fn seeds(scene: &Scene, s: &RenderSettings, n: u64) -> Vec<Image> {
    (0..n)
        .map(|k| {
            Resolved::fixed(
                scene,
                &RenderSettings {
                    seed: 100 + k,
                    ..s.clone()
                },
                8,
                64,
            )
            .render_in_process(scene, &|_| {})
            .image()
        })
        .collect()
}

#[test]
fn optimal_at_64_spp_is_unbiased_against_a_long_path_traced_reference() {
    for (name, w, h) in [("cornell-box.json", 16, 16), ("veach-mis.json", 32, 18)] {
        let scene = load(name, w, h);
        let opt = seeds(&scene, &optimal(64, 5, 5), 24);
        let pt = seeds(
            &scene,
            &RenderSettings {
                sample_block: 256,
                max_depth: 5,
                sampler: SamplerKind::Independent,
                ..Default::default()
            },
            24,
        );
        let g = 3;
        let mut worst: f64 = 0.0;
        for ry in 0..g {
            for rx in 0..g {
                let r = (
                    rx * w as usize / g,
                    ry * h as usize / g,
                    (rx + 1) * w as usize / g,
                    (ry + 1) * h as usize / g,
                );
                for c in 0..3 {
                    let (mo, so) = region_stats(&opt, r, c);
                    let (mp, sp) = region_stats(&pt, r, c);
                    let se = (so * so + sp * sp).sqrt();
                    assert!(
                        (mo - mp).abs() <= 4.0 * se + 1e-7,
                        "{name} region {r:?} channel {c}: optimal {mo} vs PT {mp} (se {se})"
                    );
                    if se > 0.0 {
                        worst = worst.max((mo - mp).abs() / se);
                    }
                }
            }
        }
        eprintln!("{name}: optimal vs PT, worst region deviation {worst:.2} standard errors");
    }
}

#[test]
fn optimal_beats_balance_at_equal_spp_and_is_never_worse_at_low_spp() {
    for (name, w, h) in [
        ("cornell-box-small-light.json", 24, 24),
        ("veach-mis.json", 32, 18),
    ] {
        let scene = load(name, w, h);
        // An unbiased long reference: balance-weighted BDPT at 4096 spp.
        let mut rs = optimal(4096, 5, 5);
        rs.mis = MisKind::Balance;
        rs.seed = 999;
        let reference = Resolved::fixed(&scene, &rs, 8, 64)
            .render_in_process(&scene, &|_| {})
            .image();
        for spp in [1u32, 2, 4, 16, 64] {
            let mut rel = [0.0f64; 2];
            for (k, mis) in [MisKind::Balance, MisKind::Optimal].into_iter().enumerate() {
                let mut s = optimal(spp, 5, 5);
                s.mis = mis;
                for img in seeds(&scene, &s, 5) {
                    rel[k] += omis::film::image::metrics::compare(&img, &reference, 0.01)
                        .expect("same size")
                        .relmse
                        / 5.0;
                }
            }
            eprintln!(
                "{name} {spp:>3} spp: balance {:.4e}, optimal {:.4e} ({:.3}x)",
                rel[0],
                rel[1],
                rel[1] / rel[0]
            );
            assert!(
                rel[1] < rel[0],
                "{name} at {spp} spp: optimal {} vs balance {}",
                rel[1],
                rel[0]
            );
        }
    }
}

#[test]
fn camera_techniques_survive_a_light_tracing_count_1e13_times_larger() {
    // One pixel's depth-1 system (techniques (0, 3), (1, 2), (2, 1)) with kappa = 0, after 4
    // camera samples, in a frame that traced N_L = 1e13 light paths of which none landed here
    // (4K at ~1.2M spp): A_lt,lt = 1e13 while the camera block is O(1). The light-tracing row is
    // decoupled, so the estimate is the camera block's own solution, x_0 + x_1.
    use omis::mis::{Layout, OptimalAccum, SolveScratch};
    let samples: [([f64; 3], f64); 4] = [
        ([0.5, 0.5, 0.0], 2.0),
        ([0.8, 0.2, 0.0], 1.0),
        ([0.1, 0.9, 0.0], 0.5),
        ([1.0, 0.0, 0.0], 0.0),
    ];
    let mut acc = OptimalAccum::new(Layout::new(1), 1);
    let (mut a, mut b) = ([[0.0f64; 2]; 2], [0.0f64; 2]);
    for (w, c) in samples {
        acc.add_sample(0, 1, &w, [c, 2.0 * c, 0.0]);
        for i in 0..2 {
            for j in 0..2 {
                a[i][j] += w[i] * w[j];
            }
            b[i] += c * w[i];
        }
    }
    let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    let x0 = (b[0] * a[1][1] - a[0][1] * b[1]) / det;
    let x1 = (a[0][0] * b[1] - a[1][0] * b[0]) / det;
    let expected = x0 + x1;
    let mut sc = SolveScratch::default();
    let light_paths = 10_000_000_000_000u64;
    let f = acc.solve(0, 1, 4, light_paths, 0.0, &mut sc);
    assert!(
        (f[0] - expected).abs() <= 1e-9 * expected.abs(),
        "{f:?} vs {expected}"
    );
    assert!((f[1] - 2.0 * expected).abs() <= 1e-9 * expected.abs());
    assert_eq!(f[2], 0.0);
}
