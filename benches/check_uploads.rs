//! What the coordinator does to every byte it accepts: `format::check_banded` on real results of
//! a 1080p optimal-MIS job (Cornell box, BDPT, D_opt 1, first pass of 16 spp), rendered here
//! from 24 tiles spread over the frame; and what a worker does to make them
//! (`format::encode_banded`, which packs every part). `cargo bench --bench check_uploads` prints
//! both throughputs, in bytes uploaded (BENCHMARKS.md #12); then the check of a 1080p
//! path-tracing job's results in pixels a second (formats of different sizes compare), and
//! their size against their raw bytes.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use omis::job::{JobSettings, Limits};
use omis::scene::Scene;

type Results = (
    Vec<omis::film::TaskFilm>,
    Vec<Vec<u8>>,
    omis::film::TileGrid,
    omis::film::FilmLayout,
);

fn render_results(job: serde_json::Value) -> Results {
    let settings: JobSettings = serde_json::from_value(job).expect("settings");
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell-box.json");
    let mut scene = Scene::load(&path).expect("scene");
    let r = settings
        .resolve(&mut scene, &Limits::default())
        .expect("resolve");
    let grid = r.grid();
    let tiles = grid.tiles();
    let films: Vec<_> = (0..24)
        .map(|k| {
            let t = tiles[k * tiles.len() / 24];
            omis::integrator::render_tile(&scene, &r.render, t, 0..16)
        })
        .collect();
    let bytes = films
        .iter()
        .map(|f| omis::film::format::encode_banded(f.clone(), 0..16, &grid))
        .collect();
    (films, bytes, grid, r.film_layout())
}

/// Every result of `r` checked as the coordinator checks an upload.
fn check_all(r: &Results) {
    for bytes in &r.1 {
        omis::film::format::check_banded(bytes, &r.2, &r.3, u64::MAX).expect("valid");
    }
}

fn check_uploads(c: &mut Criterion) {
    let optimal = render_results(serde_json::json!({
        "resolution": [1920, 1080], "spp": 48, "integrator": "bdpt", "mis": "optimal",
        "optimal_max_depth": 1, "seed": 1
    }));
    let (films, results, grid, _) = &optimal;
    let total: usize = results.iter().map(Vec::len).sum();
    let mut g = c.benchmark_group("coordinator");
    g.throughput(Throughput::Bytes(total as u64));
    g.sample_size(20);
    g.bench_function("check_banded, 24 results of a 1080p optimal job", |b| {
        b.iter(|| check_all(&optimal))
    });
    g.bench_function("encode_banded (a worker), the same 24 results", |b| {
        b.iter(|| {
            for f in films {
                std::hint::black_box(omis::film::format::encode_banded(f.clone(), 0..16, grid));
            }
        })
    });
    g.finish();
    let pt = render_results(serde_json::json!({
        "resolution": [1920, 1080], "spp": 48, "integrator": "pt", "seed": 1
    }));
    let (films, results, _, _) = &pt;
    let pixels: usize = films.iter().map(|f| f.tile.pixels()).sum();
    let packed: usize = results.iter().map(Vec::len).sum();
    let raw: usize = films.iter().map(|f| f.encode(0..16).len()).sum();
    println!(
        "24 results of a 1080p PT job: {packed} bytes uploaded, {:.3} of their {raw} raw bytes",
        packed as f64 / raw as f64
    );
    let mut g = c.benchmark_group("coordinator");
    g.throughput(Throughput::Elements(pixels as u64));
    g.sample_size(20);
    g.bench_function("check_banded, 24 results of a 1080p PT job (pixels)", |b| {
        b.iter(|| check_all(&pt))
    });
    g.finish();
}

criterion_group!(benches, check_uploads);
criterion_main!(benches);
