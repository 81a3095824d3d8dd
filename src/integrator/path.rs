//! Unidirectional path tracer: next-event estimation and BSDF sampling combined by MIS with the
//! power heuristic, Russian roulette, maximum depth.
//!
//! Depth counts bounces: a path of k vertices (camera and light vertex included) has depth
//! k - 2. Depth 0 is an emitter seen directly, depth 1 direct lighting. `max_depth` D keeps
//! every path of depth <= D.
//!
//! Light sampling is treated in the direction domain (as "Demystifying multiple importance sampling" explains): its density for a direction is
//! the sum, over every light the ray meets, of (selection probability x that light's density),
//! and the value of a light-sampled direction is the radiance of the first surface along it.

use crate::film::RayStats;
use crate::geometry::{Ray, Rgb, Vec3, max_component};
use crate::material::{Bsdf, Mode, Outgoing};
use crate::mis::power_heuristic;
use crate::sampler::Sampler;
use crate::scene::{NO_LIGHT, Scene, SurfaceHit};

/// Paths of this many bounces or more are subject to Russian roulette, with survival
/// probability q = min(max channel of throughput x eta^2, 0.95) (Mitsuba 3's rule). Mitsuba 3
/// starts at 5 bounces: there omis's samples are as noisy as Mitsuba's or less (staircase 0.89x,
/// from 3: 1.29x; bench/vs-mitsuba/run, BENCHMARKS.md "Path tracer noise against Mitsuba 3"),
/// but the longer paths cost 1.25-1.5x the rays per sample, and noise x rays is 5-10 % worse on
/// the staircase and a mixed Cornell box (14 % better on a diffuse one): the start stays at 3
/// until timings on an idle machine say which pays.
pub const RR_START_DEPTH: u32 = 3;

/// How emitters are reached at each vertex. `Mis` is the renderer; the single strategies are
/// unbiased on their own (except that BSDF sampling cannot see point lights) and exist to
/// validate each other.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DirectStrategy {
    /// Light sampling and BSDF sampling combined with the power heuristic.
    #[default]
    Mis,
    /// Next-event estimation only (emitters hit by BSDF-sampled rays count only after the camera
    /// or a delta bounce).
    Light,
    /// BSDF sampling only (no next-event estimation).
    Bsdf,
}

/// Radiance along `ray` (one pixel sample). When `per_depth` is given (max_depth + 1 entries),
/// each contribution is also added to the entry of its path depth.
pub fn li(
    scene: &Scene,
    ray: Ray,
    sampler: &mut Sampler,
    max_depth: u32,
    strategy: DirectStrategy,
    mut per_depth: Option<&mut [Rgb]>,
    stats: &mut RayStats,
) -> Rgb {
    let mut add = |l: &mut Rgb, d: u32, v: Rgb| {
        *l += v;
        if let Some(pd) = per_depth.as_deref_mut() {
            pd[d as usize] += v;
        }
    };
    let mut l = Rgb::ZERO;
    let mut beta = Rgb::ONE;
    // The product of the samples' `eta_scale`: 1 / the radiance scaling of the refractions so far.
    let mut eta_scale = 1.0f32;
    let mut ray = ray;
    // Previous scattering vertex: position and BSDF pdf of the sampled direction; None after the
    // camera or a delta bounce (emission is then counted with weight 1).
    let mut prev: Option<(Vec3, f32)> = None;
    let mut depth = 0u32;
    loop {
        stats.closest += 1;
        let Some(hit) = scene.intersect(&ray) else {
            break;
        };
        let wo = -ray.d;
        if hit.light != NO_LIGHT {
            let le = scene.lights[hit.light as usize].le(hit.ng, wo);
            if le != Rgb::ZERO {
                let w = match (prev, strategy) {
                    (None, _) | (_, DirectStrategy::Bsdf) => 1.0,
                    (Some(_), DirectStrategy::Light) => 0.0,
                    (Some((p, pdf_bsdf)), DirectStrategy::Mis) => {
                        power_heuristic(pdf_bsdf, scene.light_pdf_hit(p, ray.d, hit.light))
                    }
                };
                add(&mut l, depth, beta * le * w);
            }
        }
        if depth >= max_depth {
            break;
        }
        let bsdf = Bsdf::new(
            &scene.materials[hit.material as usize],
            hit.ng,
            hit.ns,
            hit.uv,
        );
        if bsdf.is_black() {
            break;
        }
        // wo in the BSDF's frames, once for the light sample and the BSDF sample.
        let out = bsdf.outgoing(wo);
        if !bsdf.is_delta() && strategy != DirectStrategy::Bsdf {
            let v = beta * direct(scene, &hit, &bsdf, &out, sampler, strategy, stats);
            add(&mut l, depth + 1, v);
        }
        let u_lobe = sampler.next_1d();
        let u = sampler.next_2d();
        let Some(s) = bsdf.sample_from(&out, u_lobe, u, Mode::Radiance) else {
            break;
        };
        beta *= s.f * (s.wi.dot(hit.ns).abs() / s.pdf);
        eta_scale *= s.eta_scale;
        prev = if s.delta { None } else { Some((hit.p, s.pdf)) };
        ray = Scene::spawn_ray(hit.p, hit.ng, s.wi);
        depth += 1;
        if depth >= RR_START_DEPTH {
            // Judged without refraction's radiance scaling (pbrt-v3's `etaScale`; Mitsuba 3
            // does the same): inside glass the throughput is scaled by 1 / eta^2 until the path
            // leaves it, which alone would end paths the scaling will give back.
            let q = (max_component(beta) * eta_scale).min(0.95);
            if !(sampler.next_1d() < q) {
                break;
            }
            beta /= q;
        }
    }
    l
}

/// Next-event estimate at `hit`: one light sample, MIS-weighted against BSDF sampling.
fn direct(
    scene: &Scene,
    hit: &SurfaceHit,
    bsdf: &Bsdf,
    wo: &Outgoing,
    sampler: &mut Sampler,
    strategy: DirectStrategy,
    stats: &mut RayStats,
) -> Rgb {
    let u_light = sampler.next_1d();
    let u = sampler.next_2d();
    let Some((li, pmf)) = scene.sample_light(u_light) else {
        return Rgb::ZERO;
    };
    let light = &scene.lights[li as usize];
    let Some(ls) = light.sample_li(hit.p, u) else {
        return Rgb::ZERO;
    };
    let (f, pair) = bsdf.eval_local(wo, ls.wi, Mode::Radiance);
    if f == Rgb::ZERO {
        return Rgb::ZERO;
    }
    let cos = ls.wi.dot(hit.ns).abs();
    if ls.delta {
        stats.shadow += 1;
        if ls.le == Rgb::ZERO || scene.occluded(hit.p, hit.ng, ls.p, Vec3::ZERO) {
            return Rgb::ZERO;
        }
        return f * ls.le * (cos / pmf);
    }
    stats.shadow += 1;
    let le = if !scene.occluded(hit.p, hit.ng, ls.p, ls.n) {
        ls.le
    } else if scene.emitters_may_occlude_each_other() {
        // Direction domain: the value is the radiance of whatever emitter is hit first.
        stats.closest += 1;
        match scene.intersect(&Scene::spawn_ray(hit.p, hit.ng, ls.wi)) {
            Some(h) if h.light != NO_LIGHT => scene.lights[h.light as usize].le(h.ng, -ls.wi),
            _ => Rgb::ZERO,
        }
    } else {
        Rgb::ZERO
    };
    if le == Rgb::ZERO {
        return Rgb::ZERO;
    }
    let pdf_light = scene.light_pdf_sampled(hit.p, ls.wi, pmf, ls.pdf);
    if !(pdf_light > 0.0) {
        return Rgb::ZERO;
    }
    let w = match strategy {
        DirectStrategy::Mis => power_heuristic(pdf_light, bsdf.pdf_fwd(pair.as_ref())),
        _ => 1.0,
    };
    f * le * (cos * w / pdf_light)
}
