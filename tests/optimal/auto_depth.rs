//! The automatic D_opt: its pilot, its choice, its time budget.

use crate::common;
use crate::common::load;
use crate::support::optimal;
use omis::film::{Film, Image};
use omis::integrator::RenderSettings;
use omis::mis::MisKind;
use omis::sampler::SamplerKind;

/// relMSE-style variance across `imgs` (seeds) per pixel and channel, over (R^2 + eps) with R
/// the mean of `norm`: (mean of the terms, its standard error).
fn variance_terms(imgs: &[Image], norm: &[Image], eps: f64) -> (f64, f64) {
    let k = imgs.len() as f64;
    let mut terms = Vec::new();
    for i in 0..imgs[0].pixels.len() {
        for c in 0..3 {
            let r = norm.iter().map(|m| m.pixels[i][c] as f64).sum::<f64>() / norm.len() as f64;
            let mean = imgs.iter().map(|m| m.pixels[i][c] as f64).sum::<f64>() / k;
            let var = imgs
                .iter()
                .map(|m| (m.pixels[i][c] as f64 - mean).powi(2))
                .sum::<f64>()
                / (k - 1.0);
            terms.push(var / (r * r + eps));
        }
    }
    let n = terms.len() as f64;
    let m = terms.iter().sum::<f64>() / n;
    let v = terms.iter().map(|t| (t - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, (v / n).sqrt())
}

#[test]
fn auto_depth_predicts_the_variance_of_independent_renders_and_keeps_optimal_where_it_pays() {
    use omis::job::optimal_depth::{self, PILOT_SPP};
    // The small-light box: depth 1 (NEE against light tracing and emitter hits of a 2 cm light)
    // is where optimal weights gain most (BENCHMARKS.md, "Optimal against balance MIS").
    let mut scene = load("cornell-box-small-light.json", 96, 80);
    let s = RenderSettings {
        seed: 11,
        ..optimal(16, 5, 1)
    };
    let eps = 0.01;
    let c = optimal_depth::choose(&mut scene, &s, eps, Default::default());
    assert_eq!(
        (scene.camera.width, scene.camera.height),
        (96, 80),
        "the pilot gives the camera back"
    );
    let [w, h] = c.pilot_resolution;
    assert!(
        w * h <= optimal_depth::PILOT_PIXELS && (w as f64 / h as f64 - 1.2).abs() < 0.05,
        "{c:?}"
    );
    assert_eq!(c.relmse.len(), 6, "{c:?}");
    assert!(c.time.windows(2).all(|t| t[1] > t[0]), "{c:?}");
    // Deterministic: the same job gives the same choice.
    assert_eq!(
        optimal_depth::choose(&mut scene, &s, eps, Default::default()),
        c
    );

    // Independent renders at the pilot's resolution and spp, D_opt 1: balance at depth 1, and
    // depth 1 weighted with the optimal weights solved from the next render's systems (the
    // pilot's cross-fitting: weights independent of the samples they weight).
    let pilot = load("cornell-box-small-light.json", w, h);
    let films: Vec<Film> = (0..16)
        .map(|k| {
            let r = RenderSettings {
                seed: 1000 + k,
                ..optimal(PILOT_SPP, 5, 1)
            };
            common::film(&pilot, &r, 16)
        })
        .collect();
    let image = |k: usize, cross: bool| -> Image {
        let acc = &films[k].acc;
        let sys = acc.optimal.as_ref().expect("systems");
        let next = &films[(k + 1) % films.len()];
        let mut weights = omis::mis::progressive::Progressive::new(1, acc.tile.pixels());
        weights.end_pass(
            next.acc.optimal.as_ref().expect("systems"),
            &next.acc.sums.count,
            next.light_paths(),
            omis::mis::DEFAULT_KAPPA,
        );
        let mut img = Image::new(w as usize, h as usize);
        for i in 0..acc.tile.pixels() {
            let n = acc.sums.count[i];
            weights.add_own(i, sys, i, n);
            let d1 = if cross {
                weights.estimate(sys, i, 1, n)
            } else {
                sys.balance(i, 1, n)
            };
            let v: [f64; 3] = std::array::from_fn(|c| {
                (acc.sums.sum[i][c] + acc.splat[i][c]) / n.max(1) as f64 + d1[c]
            });
            img.pixels[i] = omis::geometry::Rgb::new(v[0] as f32, v[1] as f32, v[2] as f32);
        }
        img
    };
    let bal: Vec<Image> = (0..films.len()).map(|k| image(k, false)).collect();
    let opt: Vec<Image> = (0..films.len()).map(|k| image(k, true)).collect();
    // Balance at depth 1 is what a balance render of the same samples gives.
    let balance_render = common::render(
        &pilot,
        &RenderSettings {
            mis: MisKind::Balance,
            seed: 1000,
            ..optimal(PILOT_SPP, 5, 1)
        },
        16,
    )
    .image();
    for (a, b) in bal[0].pixels.iter().zip(&balance_render.pixels) {
        assert!(
            (*a - *b).abs().max_element() <= 1e-5 * (1.0 + b.max_element()),
            "{a} vs {b}"
        );
    }
    let (v0, se0) = variance_terms(&bal, &bal, eps);
    let (v1, se1) = variance_terms(&opt, &bal, eps);
    let measured = v1 / v0;
    let measured_se = measured * ((se0 / v0).powi(2) + (se1 / v1).powi(2)).sqrt();
    let predicted = c.relmse[1] / c.relmse[0];
    let predicted_se = predicted
        * ((c.relmse_se[0] / c.relmse[0]).powi(2) + (c.relmse_se[1] / c.relmse[1]).powi(2)).sqrt();
    eprintln!(
        "pilot {c:?}\nD_opt 1 / balance variance: predicted {predicted:.3} +- {predicted_se:.3}, \
         measured over 16 seeds {measured:.3} +- {measured_se:.3}"
    );
    assert!(
        (predicted - measured).abs() < 4.0 * (predicted_se.powi(2) + measured_se.powi(2)).sqrt(),
        "predicted {predicted} +- {predicted_se}, measured {measured} +- {measured_se}"
    );
    // It pays here, so the pilot keeps optimal weights at depth 1 at least.
    assert!(
        measured + 4.0 * measured_se < 1.0,
        "{measured} +- {measured_se}"
    );
    assert!(c.chosen >= 1, "{c:?}");
    assert!(c.relative_cost(c.chosen as usize) < 1.0, "{c:?}");
}

/// The pilot weights each replica with the optimal weights solved from another one. Solved and
/// applied on the same 4 samples per pixel, the weights fit those samples: on the glass caustic
/// that made optimal weights at depth 3 look 20 % better than at depth 2 (relMSE x time 0.532
/// against 0.678 of balance's here), the job took D_opt 3, and at equal time it measured 1.3x
/// balance's error (BENCHMARKS.md, "Optimal against balance MIS"). Cross-fitted, depth 3 gains nothing over depth 2 (1.09
/// against 0.68).
#[test]
fn auto_depth_is_not_fooled_by_weights_fitted_to_the_pilots_own_samples() {
    use omis::job::optimal_depth;
    let mut scene = load("glass-caustic.json", 64, 64);
    let s = RenderSettings {
        seed: 1,
        sampler: SamplerKind::Sobol,
        ..optimal(16, 5, 1)
    };
    let c = optimal_depth::choose(&mut scene, &s, 0.01, Default::default());
    eprintln!("{}", c.summary());
    assert!(c.relmse[3] >= 0.97 * c.relmse[2], "{c:?}");
    assert!(c.chosen <= 2, "{c:?}");
}

/// A time budget bounds the pilot by time: a probe (replica 0 at the smallest frame), timed on
/// the budget's clock, sets the frame whose replicas take `PILOT_SHARE` of the budget. Here the
/// clock says the probe took `probe_s`; the frame follows from it, and where it is the smallest
/// frame the probe is replica 0: the same choice as a pilot bounded to that frame by samples.
#[test]
fn a_time_budget_bounds_the_pilot_by_the_probes_rate() {
    use omis::job::optimal_depth::{self, Budget, JobSize};
    use std::sync::atomic::{AtomicU32, Ordering};
    let mut scene = load("cornell-box-small-light.json", 96, 80);
    let s = RenderSettings {
        seed: 3,
        ..optimal(16, 5, 1)
    };
    let probe_s = 0.01;
    let choose = |scene: &mut omis::scene::Scene, seconds: f64| {
        // Each reading is `probe_s` later than the one before: the probe took `probe_s`.
        let calls = AtomicU32::new(0);
        let clock = || calls.fetch_add(1, Ordering::Relaxed) as f64 * probe_s;
        let size = JobSize {
            samples: None,
            budget: Some(Budget {
                seconds,
                clock: &clock,
            }),
        };
        let c = optimal_depth::choose(scene, &s, 0.01, size);
        assert_eq!(calls.load(Ordering::Relaxed), 2, "the probe is timed once");
        c
    };
    let smallest = optimal_depth::pilot_resolution(96, 80, optimal_depth::MIN_PILOT_PIXELS);
    let probe_pixels = smallest[0] * smallest[1];
    for seconds in [10.0, 20.0, 40.0] {
        let c = choose(&mut scene, seconds);
        let [w, h] = c.pilot_resolution;
        let allowed = optimal_depth::budget_pixels(seconds, probe_s, probe_pixels);
        // The probe and the replicas at the probe's rate within the share of the budget,
        // unless that is below the smallest frame.
        let pilot_s =
            probe_s * (1.0 + (optimal_depth::PILOT_REPLICAS * w * h) as f64 / probe_pixels as f64);
        assert!(
            [w, h] == smallest || pilot_s <= seconds * optimal_depth::PILOT_SHARE * (1.0 + 1e-9),
            "{seconds} s: {w}x{h}, {pilot_s} s"
        );
        assert_eq!(
            [w, h],
            optimal_depth::pilot_resolution(
                96,
                80,
                allowed.clamp(
                    optimal_depth::MIN_PILOT_PIXELS as f64,
                    optimal_depth::PILOT_PIXELS as f64
                ) as u32
            ),
            "{seconds} s"
        );
    }
    // 1 s: the probe alone is more than the share, so the smallest frame, the probe as replica
    // 0: the same choice, bit for bit, as the pilot a small spp job gets there.
    let c = choose(&mut scene, 1.0);
    assert_eq!(c.pilot_resolution, smallest);
    let by_samples = optimal_depth::choose(
        &mut scene,
        &s,
        0.01,
        JobSize {
            samples: Some(1000),
            budget: None,
        },
    );
    assert_eq!(c, by_samples);
    // A large budget: the full pilot.
    let c = choose(&mut scene, 1e6);
    let [w, h] = c.pilot_resolution;
    assert!(w * h > optimal_depth::PILOT_PIXELS * 9 / 10, "{c:?}");
    assert_eq!(
        (scene.camera.width, scene.camera.height),
        (96, 80),
        "the pilot gives the camera back"
    );
}
