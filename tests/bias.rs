//! Bias of the optimal-MIS estimators at 1-4 spp: the mean of many independent renders of a tiny
//! frame against a reference from balance-weighted renders (unbiased), within 4 standard errors.
//! The direct estimator's bias is O(1/spp) (Cailleau et al., §V-A); the progressive one is
//! unbiased at any spp (`omis::mis::progressive`).

mod common;

use common::load;
use omis::integrator::{IntegratorKind, RenderSettings};
use omis::job::Resolved;
use omis::mis::MisKind;
use omis::sampler::SamplerKind;
use omis::scene::Scene;
use rayon::prelude::*;

const W: u32 = 8;
const H: u32 = 8;
const MAX_DEPTH: u32 = 3;

fn settings(mis: MisKind, kappa: f64, spp: u32, seed: u64) -> RenderSettings {
    RenderSettings {
        integrator: IntegratorKind::Bdpt,
        mis,
        sample_block: spp,
        max_depth: MAX_DEPTH,
        optimal_max_depth: MAX_DEPTH,
        optimal_kappa: kappa,
        sampler: SamplerKind::Independent,
        seed,
        ..Default::default()
    }
}

/// Mean and standard error over independent renders (seeds `seeds`) of the frame's mean, per
/// channel, in passes of one sample.
fn frame_means(
    scene: &Scene,
    mis: MisKind,
    kappa: f64,
    spp: u32,
    seeds: std::ops::Range<u64>,
) -> ([f64; 3], [f64; 3]) {
    let means: Vec<[f64; 3]> = seeds
        .into_par_iter()
        .map(|seed| {
            let s = settings(mis, kappa, spp, seed);
            Resolved::fixed(scene, &s, W, 1)
                .render_in_process(scene, &|_| {})
                .image()
                .mean()
        })
        .collect();
    let n = means.len() as f64;
    let mut m = [0.0; 3];
    let mut se = [0.0; 3];
    for c in 0..3 {
        m[c] = means.iter().map(|v| v[c]).sum::<f64>() / n;
        let var = means.iter().map(|v| (v[c] - m[c]).powi(2)).sum::<f64>() / (n - 1.0);
        se[c] = (var / n).sqrt();
    }
    (m, se)
}

/// The largest |difference| / combined standard error over the channels, and the relative
/// difference of the channel sum.
fn z_and_bias(a: ([f64; 3], [f64; 3]), r: ([f64; 3], [f64; 3])) -> (f64, f64) {
    let z = (0..3)
        .map(|c| (a.0[c] - r.0[c]).abs() / (a.1[c].powi(2) + r.1[c].powi(2)).sqrt())
        .fold(0.0, f64::max);
    let sum = |v: [f64; 3]| v[0] + v[1] + v[2];
    (z, sum(a.0) / sum(r.0) - 1.0)
}

/// The reference: balance-weighted renders of other seeds, 256 spp each.
fn reference(scene: &Scene, renders: u64) -> ([f64; 3], [f64; 3]) {
    frame_means(
        scene,
        MisKind::Balance,
        0.0,
        256,
        1_000_000..1_000_000 + renders,
    )
}

/// Progressive: unbiased (within 4 standard errors, about 0.3% of the frame mean). The direct
/// estimator is biased, and the test asserts what was measured (BENCHMARKS.md, "Optimal against balance MIS"), with margin:
/// with kappa 0 the bias is detectable and shrinks with spp (+67%, +4.9%, +1.2% at 1, 2, 4 spp);
/// the default kappa keeps it under 2% (-0.7% at 1 spp, undetectable at 2 and 4).
#[test]
fn progressive_optimal_is_unbiased_at_1_to_4_spp_and_the_direct_bias_is_bounded() {
    let scene = load("cornell-box.json", W, H);
    let r = reference(&scene, 48);
    let mut kappa0 = Vec::new();
    for spp in [1, 2, 4] {
        let renders = 1024 / spp as u64;
        let prog = frame_means(&scene, MisKind::OptimalProgressive, 1.0, spp, 0..renders);
        let (z, bias) = z_and_bias(prog, r);
        eprintln!("progressive {spp} spp: z {z:.2}, relative bias {bias:+.4}");
        assert!(
            z < 4.0,
            "progressive at {spp} spp: {z:.2} standard errors off"
        );
        let direct = frame_means(&scene, MisKind::Optimal, 0.0, spp, 0..renders);
        let (z, bias) = z_and_bias(direct, r);
        eprintln!("direct kappa 0 {spp} spp: z {z:.2}, relative bias {bias:+.4}");
        kappa0.push((z, bias.abs()));
        let direct = frame_means(&scene, MisKind::Optimal, 1.0, spp, 0..renders);
        let (z, bias) = z_and_bias(direct, r);
        eprintln!("direct kappa 1 {spp} spp: z {z:.2}, relative bias {bias:+.4}");
        assert!(
            bias.abs() < 0.02,
            "direct, kappa 1, {spp} spp: relative bias {bias:+.4} (z {z:.2})"
        );
    }
    assert!(
        kappa0[0].0 > 4.0 && kappa0[0].1 < 1.0,
        "direct, kappa 0, 1 spp: {:?}",
        kappa0[0]
    );
    assert!(
        kappa0[1].1 < 0.1 && kappa0[2].1 < 0.03 && kappa0[2].1 < kappa0[0].1,
        "direct, kappa 0, 2 and 4 spp: {kappa0:?}"
    );
}

/// The measurement of BENCHMARKS.md, "Optimal against balance MIS" (1-8 spp, 2048 spp of renders per point): progressive
/// within 4 standard errors; the direct estimator's relative bias printed
/// (`cargo test --profile ci --test bias -- --ignored --nocapture`).
#[test]
#[ignore]
fn bias_at_1_to_8_spp_for_the_benchmarks() {
    let scene = load("cornell-box.json", W, H);
    let r = reference(&scene, 96);
    for spp in [1, 2, 4, 8] {
        let renders = 2048 / spp as u64;
        for (mis, kappa) in [
            (MisKind::OptimalProgressive, 1.0),
            (MisKind::Optimal, 0.0),
            (MisKind::Optimal, 1.0),
        ] {
            let (z, bias) = z_and_bias(frame_means(&scene, mis, kappa, spp, 0..renders), r);
            eprintln!(
                "{} kappa {kappa} {spp} spp: relative bias {bias:+.4}, z {z:.2}",
                mis.name()
            );
            if mis == MisKind::OptimalProgressive {
                assert!(
                    z < 4.0,
                    "progressive at {spp} spp: {z:.2} standard errors off"
                );
            }
        }
    }
}
