//! What the coordinator does to every byte it accepts: `wire::check_banded` on real results of
//! a 1080p optimal-MIS job (Cornell box, BDPT, D_opt 1, first pass of 16 spp), rendered here
//! from 24 tiles spread over the frame. `cargo bench --bench check_uploads` prints its
//! throughput (BENCHMARKS.md #12).

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use omis::job::{JobSettings, Limits};
use omis::scene::Scene;

fn results() -> (Vec<Vec<u8>>, omis::film::TileGrid, omis::film::FilmLayout) {
    let settings: JobSettings = serde_json::from_value(serde_json::json!({
        "resolution": [1920, 1080], "spp": 48, "integrator": "bdpt", "mis": "optimal",
        "optimal_max_depth": 1, "seed": 1
    }))
    .expect("settings");
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell-box.json");
    let mut scene = Scene::load(&path).expect("scene");
    let r = settings
        .resolve(&mut scene, &Limits::default())
        .expect("resolve");
    let grid = r.grid();
    let tiles = grid.tiles();
    let bytes = (0..24)
        .map(|k| {
            let t = tiles[k * tiles.len() / 24];
            let film = omis::integrator::render_tile(&scene, &r.render, t, 0..16);
            omis::film::wire::encode_banded(film, 0..16, &grid)
        })
        .collect();
    (bytes, grid, r.film_layout())
}

fn check_uploads(c: &mut Criterion) {
    let (results, grid, layout) = results();
    let total: usize = results.iter().map(Vec::len).sum();
    let mut g = c.benchmark_group("coordinator");
    g.throughput(Throughput::Bytes(total as u64));
    g.sample_size(20);
    g.bench_function("check_banded, 24 results of a 1080p optimal job", |b| {
        b.iter(|| {
            for r in &results {
                omis::film::wire::check_banded(r, &grid, &layout).expect("valid");
            }
        })
    });
    g.finish();
}

criterion_group!(benches, check_uploads);
criterion_main!(benches);
