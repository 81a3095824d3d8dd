//! Statistical proofs of BDPT: single strategies are unbiased on their own, balance- and
//! power-weighted BDPT equal the path tracer (and the analytic furnace), the caustic scene, and
//! determinism with light-tracing splats. Standard errors come from the spread of 32
//! independent seeds (so that the 4-standard-error bound is a t-test with 31 degrees of freedom).

mod common;

use common::{assert_agree, load, region};
use omis::film::Image;
use omis::integrator::bdpt::ROULETTE_FROM;
use omis::integrator::{IntegratorKind, RenderSettings, Techniques};
use omis::mis::MisKind;
use omis::sampler::SamplerKind;
use omis::scene::Scene;
use std::path::Path;

fn render(scene: &Scene, settings: &RenderSettings, threads: usize) -> Image {
    common::render_on(scene, settings, 8, threads).image()
}

const SEEDS: u64 = 32;

/// Renders with SEEDS independent seeds.
fn renders(scene: &Scene, base: &RenderSettings) -> Vec<Image> {
    renders_n(scene, base, SEEDS)
}

/// Renders with `n` independent seeds.
fn renders_n(scene: &Scene, base: &RenderSettings, n: u64) -> Vec<Image> {
    (0..n)
        .map(|k| {
            render(
                scene,
                &RenderSettings {
                    seed: 1000 + k,
                    ..base.clone()
                },
                2,
            )
        })
        .collect()
}

fn bdpt(mis: MisKind, spp: u32, max_depth: u32) -> RenderSettings {
    RenderSettings {
        integrator: IntegratorKind::Bdpt,
        mis,
        sample_block: spp,
        max_depth,
        sampler: SamplerKind::Independent,
        ..Default::default()
    }
}

/// BDPT with one technique per depth alone (light tracing or NEE), unweighted.
fn alone(techniques: Techniques, spp: u32, max_depth: u32) -> RenderSettings {
    RenderSettings {
        techniques,
        ..bdpt(MisKind::Balance, spp, max_depth)
    }
}

fn pt(spp: u32, max_depth: u32) -> RenderSettings {
    RenderSettings {
        integrator: IntegratorKind::Pt,
        sample_block: spp,
        max_depth,
        sampler: SamplerKind::Independent,
        ..Default::default()
    }
}

#[test]
fn light_tracing_alone_and_nee_alone_equal_the_path_tracer() {
    // The sharpest test of importance and pdf conventions: each strategy unweighted, on its own.
    let scene = load("cornell-box.json", 24, 24);
    let reference = renders(&scene, &pt(16, 5));
    let lt = renders(&scene, &alone(Techniques::Lt, 8, 5));
    let nee = renders(&scene, &alone(Techniques::Nee, 4, 5));
    assert_agree("light tracing vs PT", &lt, &reference, 4);
    assert_agree("NEE vs PT", &nee, &reference, 4);
}

#[test]
fn bdpt_equals_the_analytic_furnace() {
    let scene = load("furnace.json", 8, 8);
    for mis in [MisKind::Balance, MisKind::Power] {
        for max_depth in [1u32, 2, 5] {
            let expected: f64 = (0..=max_depth).map(|d| 0.5f64.powi(d as i32)).sum();
            let imgs = renders(&scene, &bdpt(mis, 8, max_depth));
            let (m, se) = region(&imgs, (0, 0, 8, 8), 1);
            assert!(
                (m - expected).abs() <= 4.0 * se + 1e-5 * expected,
                "{mis:?} depth {max_depth}: {m} vs {expected} (se {se})"
            );
        }
    }
}

#[test]
fn roulette_keeps_bdpt_unbiased() {
    // With --roulette every density sampled from a vertex carries its continuation probability
    // q, in both directions and at specular events too. Balance and power weights stay unbiased
    // with any densities that every technique computes alike (q left out everywhere passes);
    // optimal MIS needs the true densities: without q it gave 1.825 against 1.75 (26 standard
    // errors) at depth 2. The furnace (q = 0.5 at every vertex) is analytic; on the Cornell box
    // q is the walls' albedo; the glass caustic's mirror has q = 0.9 at specular vertices. Both
    // starts: roulette at every vertex, and from BDPT's default vertex on.
    let furnace = load("furnace.json", 8, 8);
    for from in [1, ROULETTE_FROM] {
        for mis in [MisKind::Balance, MisKind::Power, MisKind::Optimal] {
            for max_depth in [2u32, 6] {
                let expected: f64 = (0..=max_depth).map(|d| 0.5f64.powi(d as i32)).sum();
                let s = RenderSettings {
                    roulette: true,
                    roulette_from: from,
                    ..bdpt(mis, 8, max_depth)
                };
                let imgs = renders(&furnace, &s);
                let (m, se) = region(&imgs, (0, 0, 8, 8), 1);
                assert!(
                    (m - expected).abs() <= 4.0 * se + 1e-5 * expected,
                    "{mis:?} depth {max_depth}, roulette from {from}: {m} vs {expected} (se {se})"
                );
            }
        }
    }
    let with_roulette = |scene: &Scene, s: &RenderSettings, from: u32| -> Vec<Image> {
        (0..SEEDS)
            .map(|k| {
                let s = RenderSettings {
                    seed: 5000 + k,
                    roulette: true,
                    roulette_from: from,
                    ..s.clone()
                };
                render(scene, &s, 2)
            })
            .collect()
    };
    let cornell = load("cornell-box.json", 24, 24);
    let reference = renders(&cornell, &pt(16, 5));
    let rr = with_roulette(&cornell, &bdpt(MisKind::Balance, 4, 5), 1);
    assert_agree("Cornell box, BDPT with roulette vs PT", &rr, &reference, 3);
    let glass = load("glass-caustic.json", 32, 32);
    let plain = renders(&glass, &bdpt(MisKind::Balance, 8, 8));
    for from in [1, ROULETTE_FROM] {
        let rr = with_roulette(&glass, &bdpt(MisKind::Balance, 8, 8), from);
        assert_agree(
            &format!("glass caustic, BDPT with roulette from {from} vs without"),
            &rr,
            &plain,
            2,
        );
    }
}

#[test]
fn bdpt_equals_the_path_tracer_on_cornell_and_veach() {
    let cases = [
        ("cornell-box.json", 24, 24, 4, 16),
        ("veach-mis.json", 48, 27, 3, 64),
    ];
    for (name, w, h, bdpt_spp, pt_spp) in cases {
        let scene = load(name, w, h);
        for max_depth in [1u32, 2, 5] {
            let reference = renders(&scene, &pt(pt_spp, max_depth));
            for mis in [MisKind::Balance, MisKind::Power] {
                let b = renders(&scene, &bdpt(mis, bdpt_spp, max_depth));
                assert_agree(
                    &format!("{name} {mis:?} depth {max_depth}"),
                    &b,
                    &reference,
                    3,
                );
            }
        }
    }
}

#[test]
fn bdpt_finds_the_caustic_and_agrees_with_a_long_path_traced_reference() {
    let scene = load("glass-caustic.json", 32, 32);
    // The caustic under the glass sphere, at this framing.
    let caustic = (20, 29, 24, 31);
    let reference = renders(&scene, &pt(256, 8));
    let b = renders(&scene, &bdpt(MisKind::Balance, 8, 8));
    let p = renders(&scene, &pt(8, 8));
    assert_agree("glass caustic, BDPT vs long PT", &b, &reference, 2);
    let (m_b, se_b) = region(&b, caustic, 1);
    let (m_r, se_r) = region(&reference, caustic, 1);
    let (m_p, se_p) = region(&p, caustic, 1);
    eprintln!(
        "caustic: BDPT {m_b:.4} +- {se_b:.4}, PT {m_p:.4} +- {se_p:.4} (8 spp); PT reference {m_r:.4} +- {se_r:.4} (256 spp)"
    );
    // The caustic is there (brighter than the floor around it) and BDPT's estimate of it is less
    // noisy than the path tracer's at the same sample count: measured 0.055 vs 0.104, i.e. a
    // variance 3.6x lower (only light tracing and (0, t) can make these paths; the rest of the
    // region's noise is shared). Asserted with margin: at least 2x.
    let (floor, _) = region(&reference, (8, 29, 14, 31), 1);
    assert!(m_b > 2.0 * floor, "caustic {m_b} vs floor {floor}");
    assert!((m_b - m_r).abs() <= 4.0 * (se_b * se_b + se_r * se_r).sqrt());
    assert!(
        se_b < 0.71 * se_p,
        "BDPT se {se_b} vs PT se {se_p} at equal spp"
    );
}

#[test]
fn bdpt_with_splats_is_bit_identical_for_any_thread_count() {
    let scene = load("glass-caustic.json", 24, 20);
    for mis in [MisKind::Balance, MisKind::Power] {
        let mut s = bdpt(mis, 4, 6);
        s.sampler = SamplerKind::Sobol;
        s.strategies = true;
        let one = render(&scene, &s, 1);
        let two = render(&scene, &s, 2);
        let three = render(&scene, &s, 3);
        assert_eq!(one, two, "{mis:?}: 1 vs 2 threads");
        assert_eq!(one, three, "{mis:?}: 1 vs 3 threads");
    }
}

#[test]
fn strategy_layers_sum_to_the_image() {
    // At max depth 3 every technique is kept as a layer: the layers add up to the image.
    let scene = load("cornell-box.json", 16, 16);
    let mut s = bdpt(MisKind::Balance, 4, 3);
    s.strategies = true;
    let out = omis::job::Resolved::fixed(&scene, &s, 8, 64).render_in_process(&scene, &|_| {});
    let img = out.image();
    let layers = out.film.strategy_images();
    assert_eq!(layers.len(), omis::film::STRATEGY_LAYERS);
    assert!(layers.iter().any(|(n, _)| n == "s1_t1") && layers.iter().any(|(n, _)| n == "s0_t5"));
    for i in 0..img.pixels.len() {
        let sum: omis::geometry::Vec3 = layers.iter().map(|(_, l)| l.pixels[i]).sum();
        let d = (sum - img.pixels[i]).abs().max_element();
        assert!(
            d <= 1e-4 * (1.0 + img.pixels[i].max_element()),
            "pixel {i}: {sum} vs {}",
            img.pixels[i]
        );
    }
}

/// A box of one-sided Lambert walls (floor, ceiling, back, left, right; normals inward), open
/// toward the camera outside it, with `shapes` (JSON, after a comma) added and `lights` (the JSON
/// "lights" list) as its point lights.
fn lit_box(shapes: &str, lights: &str, w: u32, h: u32) -> Scene {
    let text = format!(
        r#"{{
          "camera": {{"position": [0, 1, 3.6], "look_at": [0, 1, 0], "fov": 42, "resolution": [{w}, {h}]}},
          "materials": {{"white": {{"type": "lambert", "albedo": 0.7, "two_sided": false}},
                        "red": {{"type": "lambert", "albedo": [0.6, 0.1, 0.1], "two_sided": false}},
                        "black": {{"type": "lambert", "albedo": 0}}}},
          "shapes": [
            {{"type": "quad", "material": "white", "corner": [-1, 0, -1], "edge1": [0, 0, 2], "edge2": [2, 0, 0]}},
            {{"type": "quad", "material": "white", "corner": [-1, 2, -1], "edge1": [2, 0, 0], "edge2": [0, 0, 2]}},
            {{"type": "quad", "material": "white", "corner": [-1, 0, -1], "edge1": [2, 0, 0], "edge2": [0, 2, 0]}},
            {{"type": "quad", "material": "white", "corner": [1, 0, -1], "edge1": [0, 0, 2], "edge2": [0, 2, 0]}},
            {{"type": "quad", "material": "red", "corner": [-1, 0, -1], "edge1": [0, 2, 0], "edge2": [0, 0, 2]}}
            {shapes}
          ],
          "lights": [{lights}]
        }}"#
    );
    omis::scene::json::parse(&text, Path::new("lit-box.json"))
        .expect("parse")
        .build()
        .expect("build")
}

/// Light tracing alone, NEE alone and balance-weighted BDPT agree with the path tracer in the
/// box for every kind of light: point lights (whose subpaths start at a delta in position),
/// sphere lights (cone sampling from outside, area sampling from inside), one-sided quads, an
/// enclosing inward sphere, and all of them at once (light selection mixing delta and area
/// lights). Point lights and spheres in the middle of the box, high near the front, 10 cm from a
/// wall and 1 cm from it. A point light 1 cm from a wall is checked on direct light only: deeper
/// paths draw most of their light from the tiny hot spot beside it, which camera-side strategies
/// find a few times in the whole test, so that their sample spread is no standard error there
/// (the same holds for seeing a sphere much smaller than a pixel; the spheres here are not).
#[test]
fn every_light_type_agrees_across_strategies_in_a_one_sided_box() {
    // Point lights: (position, max depth).
    let points = [
        ([0.0, 1.0, 0.0], 3),
        ([-0.5, 1.6, 0.4], 3),
        ([0.9, 0.5, -0.5], 3),
        ([0.99, 0.5, -0.5], 1),
    ];
    // Spheres: (centre, radius); the last two end 10 cm and 1 cm from the right wall.
    let spheres = [
        ([0.0, 1.0, 0.0], 0.12),
        ([-0.5, 1.6, 0.4], 0.12),
        ([0.85, 0.5, -0.5], 0.05),
        ([0.87, 0.5, -0.5], 0.12),
    ];
    let mut cases: Vec<(String, String, String, u32)> = Vec::new();
    for ([x, y, z], depth) in points {
        cases.push((
            format!("point light at {:?}", [x, y, z]),
            String::new(),
            format!(r#"{{"type": "point", "position": [{x}, {y}, {z}], "intensity": 0.6}}"#),
            depth,
        ));
    }
    for ([x, y, z], r) in spheres {
        // The power of the point lights: pi^2 r^2 L = 4 pi I.
        let radiance = 4.0 * 0.6 / (std::f64::consts::PI * r * r);
        cases.push((
            format!("sphere light r={r} at {:?}", [x, y, z]),
            format!(
                r#", {{"type": "sphere", "center": [{x}, {y}, {z}], "radius": {r}, "material": "black", "emission": {radiance}}}"#
            ),
            String::new(),
            3,
        ));
    }
    let quad = r#", {"type": "quad", "material": "black", "corner": [-0.25, 1.98, -0.25], "edge1": [0.5, 0, 0], "edge2": [0, 0, 0.5], "emission": 6}"#;
    cases.push(("ceiling quad light".into(), quad.into(), String::new(), 3));
    let enclosing = r#", {"type": "sphere", "center": [0, 1, 0], "radius": 8, "inward": true, "material": "black", "emission": 0.5}"#;
    cases.push((
        "enclosing inward sphere".into(),
        enclosing.into(),
        String::new(),
        3,
    ));
    cases.push((
        "all at once".into(),
        format!(
            r#"{quad}, {{"type": "sphere", "center": [0.5, 0.4, -0.4], "radius": 0.1, "material": "black", "emission": 15}}"#
        ),
        r#"{"type": "point", "position": [-0.6, 1.2, -0.3], "intensity": 0.4}"#.into(),
        3,
    ));
    // 33 comparisons of 2 x 2 regions in 3 channels: 64 seeds keep the 4-standard-error bound
    // a t-test with 63 degrees of freedom.
    let seeds = 64;
    for (what, shapes, lights, max_depth) in &cases {
        let scene = lit_box(shapes, lights, 18, 18);
        let reference = renders_n(&scene, &pt(8, *max_depth), seeds);
        let lt = renders_n(&scene, &alone(Techniques::Lt, 4, *max_depth), seeds);
        let nee = renders_n(&scene, &alone(Techniques::Nee, 4, *max_depth), seeds);
        let bal = renders_n(&scene, &bdpt(MisKind::Balance, 4, *max_depth), seeds);
        let what = format!("{what}, max depth {max_depth}");
        assert_agree(&format!("{what}: light tracing vs PT"), &lt, &reference, 2);
        assert_agree(&format!("{what}: NEE vs PT"), &nee, &reference, 2);
        assert_agree(&format!("{what}: balance vs PT"), &bal, &reference, 2);
    }
}

/// Collects the unweighted contribution of every camera-side technique (t >= 2) relative to the
/// furnace's closed form.
struct FurnaceSink {
    /// (s, t, contribution / 0.5^depth) per sample with a contribution.
    ratios: Vec<(u32, u32, f64)>,
}

impl omis::integrator::bdpt::SampleSink for FurnaceSink {
    fn wants_zero_samples(&self, _depth: u32) -> bool {
        false
    }
    fn wants_vector(&self, _depth: u32) -> bool {
        false
    }
    fn heuristic(&self) -> MisKind {
        MisKind::Balance
    }
    fn sample(&mut self, s: &omis::integrator::bdpt::PathSample) {
        if s.t >= 2 && s.contribution.y != 0.0 {
            let expected = 0.5f64.powi(s.depth as i32);
            self.ratios
                .push((s.s, s.t, s.contribution.y as f64 / expected));
        }
    }
    fn unsampled(&mut self, _: (u32, u32), _: u32, _: u32) {}
}

/// The furnace's (s, t, contribution / a^d) of every camera-side technique's sample with a
/// contribution, 1024 pixel samples of max depth 6, with subpaths ending by roulette from
/// vertex `roulette` on (None: no roulette).
fn furnace_ratios(roulette: Option<u32>) -> Vec<(u32, u32, f64)> {
    use omis::film::RayStats;
    use omis::integrator::bdpt::{PixelSample, Workspace, pixel_sample};
    use omis::sampler::{Sampler, Stream};
    let scene = load("furnace.json", 16, 16);
    let mut ws = Workspace::default();
    ws.set_roulette(roulette);
    let mut stats = RayStats::default();
    let mut sink = FurnaceSink { ratios: Vec::new() };
    for y in 0..16 {
        for x in 0..16 {
            for i in 0..4 {
                let kind = SamplerKind::Independent;
                let mut cs = Sampler::new(kind, 7, x, y, i, 4, Stream::Camera);
                let mut ls = Sampler::new(kind, 7, x, y, i, 4, Stream::Light);
                let ps = PixelSample {
                    pixel: (x, y),
                    max_depth: FURNACE_DEPTH,
                    cam_sampler: &mut cs,
                    light_sampler: &mut ls,
                };
                pixel_sample(&scene, ps, &mut ws, &mut sink, &mut stats);
            }
        }
    }
    sink.ratios
}

const FURNACE_DEPTH: u32 = 6;

/// Catches Russian roulette (or any other random throughput factor) in the BDPT subpaths, the
/// cause of fireflies on glass and mirrors. Inside the furnace (a sphere of albedo a = 0.5 and
/// emission 1, seen from inside) every camera-side technique (s, t >= 2) has an unweighted
/// contribution f / p_s of exactly a^d for a path of depth d, whatever its vertices: cosine
/// sampling gives f cos / p = a at each bounce, and between two points of a sphere
/// cos cos / r^2 = 1 / (4 R^2), so that uniform area sampling (of the light point, and of the
/// emitted ray's origin) cancels the connection's geometry (Veach 1997 eq. 8.3; the sphere
/// identity is Lambert's). The closed-form variance of each technique is therefore 0: a roulette
/// survivor would carry 1/q = 2 per surviving vertex past the roulette's start.
#[test]
fn bdpt_subpath_throughputs_have_zero_variance_in_the_furnace() {
    let max_depth = FURNACE_DEPTH;
    let r = &furnace_ratios(None);

    let n = r.len() as f64;
    let mean = r.iter().map(|x| x.2).sum::<f64>() / n;
    let var = r.iter().map(|x| (x.2 - mean).powi(2)).sum::<f64>() / (n - 1.0);
    let worst = r
        .iter()
        .max_by(|a, b| (a.2 - 1.0).abs().total_cmp(&(b.2 - 1.0).abs()))
        .copied();
    // f32 rounding of the throughputs and of the sphere geometry only.
    assert!(
        (mean - 1.0).abs() < 1e-4 && var < 1e-7,
        "contribution / a^d: mean {mean}, variance {var}, worst (s, t, ratio) {worst:?}"
    );
    // Every technique of every depth is there, the deepest ones included (the subpaths run to
    // the max depth: 1024 pixel samples, each with its techniques of depths 0 ..= 6).
    for s in 0..=max_depth {
        let n = r.iter().filter(|x| x.0 == s).count();
        assert!(n >= 1024, "technique s = {s}: only {n} samples");
    }
    let deep = r.iter().filter(|x| x.0 + x.1 == max_depth + 2).count();
    assert!(deep >= 1024 * 6, "only {deep} samples of depth {max_depth}");
}

/// BDPT's default roulette starts at vertex `bdpt::ROULETTE_FROM`, no earlier: in the furnace
/// (see above) a technique's contribution / a^d is 2^n exactly, n the number of subpath vertices
/// at or past the start that the sample continued from (light vertices y_1 .. y_{s-2}, camera
/// vertices z_1 .. z_{t-2}). A start one vertex earlier (fireflies on short
/// caustic paths) or later (the time of long paths) fails it, and so does roulette that never
/// happens.
#[test]
fn bdpt_roulette_starts_at_its_default_vertex_in_the_furnace() {
    let from = ROULETTE_FROM;
    let r = furnace_ratios(Some(from));
    let past = |len: u32| (len as i32 - 1 - from as i32).max(0);
    let mut survivors = 0;
    for &(s, t, ratio) in &r {
        let n = past(s) + past(t);
        let expected = 2f64.powi(n);
        assert!(
            (ratio / expected - 1.0).abs() < 1e-3,
            "(s, t) = ({s}, {t}): contribution / a^d {ratio}, expected 2^{n}"
        );
        survivors += (n > 0) as usize;
    }
    // Subpaths do survive roulette (the deepest techniques have samples) and short ones are
    // all there.
    assert!(
        survivors >= 200,
        "only {survivors} samples past the roulette"
    );
    let short = r.iter().filter(|x| x.0 + x.1 <= from + 1).count();
    assert!(short >= 1024 * from as usize, "only {short} short samples");
}
