//! Optimal MIS: the accumulators are a mergeable value (tiling and sample-range invariance, also
//! through the wire encoding), the estimate is unbiased in practice, and it beats balance.

use omis::film::Image;
use omis::integrator::{self, Frame, IntegratorKind, MisKind, RenderSettings, TileFilm};
use omis::sampler::SamplerKind;
use omis::scene::Scene;
use std::path::Path;

fn load(name: &str, w: u32, h: u32) -> Scene {
    let mut s = Scene::load(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scenes")
            .join(name),
    )
    .expect(name);
    s.camera = s.camera.with_resolution(w, h).expect("resolution");
    s
}

fn optimal(spp: u32, max_depth: u32, d_opt: u32) -> RenderSettings {
    RenderSettings {
        integrator: IntegratorKind::Bdpt,
        mis: MisKind::Optimal,
        spp,
        max_depth,
        optimal_max_depth: d_opt,
        sampler: SamplerKind::Independent,
        seed: 5,
        ..Default::default()
    }
}

/// Renders the given (tile, samples) tasks and merges them in the given order.
fn tasks_image(
    scene: &Scene,
    s: &RenderSettings,
    tasks: &[(integrator::Tile, std::ops::Range<u32>)],
    through_wire: bool,
) -> Image {
    let (w, h) = (scene.camera.width, scene.camera.height);
    let mut frame = Frame::new(w, h, s);
    let d_opt = s.optimal_layout().map(|l| l.d_opt);
    for (tile, range) in tasks {
        let mut film = integrator::render_tile(scene, s, *tile, range.clone());
        if through_wire {
            let bytes = film.encode(range.clone());
            let (back, r) = TileFilm::decode(&bytes, w, h, d_opt).expect("decodes");
            assert_eq!(&r, range);
            assert_eq!(back.encode(range.clone()), bytes, "encoding is canonical");
            film = back;
        }
        frame.merge(&film);
        frame.apply_records(&film.records);
    }
    frame.image()
}

fn max_rel_diff(a: &Image, b: &Image) -> f64 {
    a.pixels
        .iter()
        .zip(&b.pixels)
        .flat_map(|(x, y)| (0..3).map(move |c| (x[c] as f64, y[c] as f64)))
        .map(|(x, y)| (x - y).abs() / x.abs().max(y.abs()).max(1e-3))
        .fold(0.0, f64::max)
}

#[test]
fn tiles_and_sample_ranges_merge_to_the_single_pass_image() {
    let scene = load("cornell-box-small-light.json", 32, 32);
    for settings in [optimal(4, 5, 5), optimal(4, 5, 2), {
        let mut s = optimal(4, 5, 5);
        s.mis = MisKind::Power;
        s.strategies = true;
        s
    }] {
        let whole = integrator::Tile {
            x0: 0,
            y0: 0,
            x1: 32,
            y1: 32,
        };
        let one = tasks_image(&scene, &settings, &[(whole, 0..4)], false);
        // 16 tiles, merged in reverse order.
        let mut t16: Vec<_> = integrator::make_tiles(32, 32, 8)
            .into_iter()
            .map(|t| (t, 0..4))
            .collect();
        t16.reverse();
        let sixteen = tasks_image(&scene, &settings, &t16, false);
        // 64 tiles, each as two sample ranges, interleaved, through the wire encoding.
        let mut t64 = Vec::new();
        for t in integrator::make_tiles(32, 32, 4) {
            t64.push((t, 2..4));
        }
        for t in integrator::make_tiles(32, 32, 4).into_iter().rev() {
            t64.push((t, 0..2));
        }
        let sixty_four = tasks_image(&scene, &settings, &t64, true);
        let d16 = max_rel_diff(&one, &sixteen);
        let d64 = max_rel_diff(&one, &sixty_four);
        eprintln!(
            "{:?}: max relative difference 16 tiles {d16:.2e}, 64 tiles x 2 ranges {d64:.2e}",
            settings.mis
        );
        assert!(d16 <= 1e-6 && d64 <= 1e-6, "{d16} {d64}");
        // And the frame's own render loop agrees as well.
        let full = integrator::render(&scene, &settings, 16, &|_| {}).image();
        assert!(max_rel_diff(&one, &full) <= 1e-6);
    }
}

#[test]
fn wire_decoding_rejects_damaged_results() {
    let scene = load("cornell-box.json", 16, 16);
    let s = optimal(2, 3, 3);
    let tile = integrator::Tile {
        x0: 0,
        y0: 0,
        x1: 8,
        y1: 8,
    };
    let film = integrator::render_tile(&scene, &s, tile, 0..2);
    let bytes = film.encode(0..2);
    assert!(TileFilm::decode(&bytes, 16, 16, Some(3)).is_ok());
    assert!(TileFilm::decode(&bytes[..bytes.len() - 1], 16, 16, Some(3)).is_err());
    assert!(
        TileFilm::decode(&bytes, 16, 16, Some(2)).is_err(),
        "depth mismatch"
    );
    assert!(
        TileFilm::decode(&bytes, 4, 4, Some(3)).is_err(),
        "tile outside the frame"
    );
    let mut bad = bytes.clone();
    bad[0] = b'X';
    assert!(TileFilm::decode(&bad, 16, 16, Some(3)).is_err());
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(TileFilm::decode(&longer, 16, 16, Some(3)).is_err());
}
