//! Tiles, sample ranges and tile checkpoints merge to the single-pass image, bit for bit.

use crate::common::load;
use crate::support::optimal;
use omis::film::{Film, Image, TaskFilm, Tile};
use omis::integrator::{self, IntegratorKind, RenderSettings};
use omis::job::{Resolved, make_tiles};
use omis::mis::MisKind;
use omis::scene::Scene;

/// Renders the given (tile, samples) tasks and merges them in the given order.
fn tasks_image(
    scene: &Scene,
    s: &RenderSettings,
    tasks: &[(Tile, std::ops::Range<u32>)],
    through_wire: bool,
) -> Image {
    let (w, h) = (scene.camera.width, scene.camera.height);
    let mut frame = Film::new(w, h, &s.film_layout());
    for (tile, range) in tasks {
        let mut film = integrator::render_tile(scene, s, *tile, range.clone());
        if through_wire {
            let bytes = film.encode(range.clone());
            let (back, r) = TaskFilm::decode(&bytes, w, h, &s.film_layout()).expect("decodes");
            assert_eq!(&r, range);
            assert_eq!(back.encode(range.clone()), bytes, "encoding is canonical");
            film = back;
        }
        frame.add_own_and_splats(&film);
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
        let whole = Tile {
            x0: 0,
            y0: 0,
            x1: 32,
            y1: 32,
        };
        let one = tasks_image(&scene, &settings, &[(whole, 0..4)], false);
        // 16 tiles, merged in reverse order.
        let mut t16: Vec<_> = make_tiles(32, 32, 8)
            .into_iter()
            .map(|t| (t, 0..4))
            .collect();
        t16.reverse();
        let sixteen = tasks_image(&scene, &settings, &t16, false);
        // 64 tiles, each as two sample ranges, interleaved, through the wire encoding.
        let mut t64 = Vec::new();
        for t in make_tiles(32, 32, 4) {
            t64.push((t, 2..4));
        }
        for t in make_tiles(32, 32, 4).into_iter().rev() {
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
        let full = Resolved::fixed(&scene, &settings, 16, 64)
            .render_in_process(&scene, &|_| {})
            .image();
        assert!(max_rel_diff(&one, &full) <= 1e-6);
    }
}

/// The path tracer makes no light-tracing splats: its films and tile checkpoints keep no splat
/// sums (52 bytes a pixel instead of 76), its image is the same, and a result or a banded
/// upload that carries splats is refused for it rather than merged into sums it does not keep.
#[test]
fn path_tracer_checkpoints_keep_no_splat_sums_and_its_results_no_splats() {
    use omis::film::format::{self, TileCheckpoint};
    use omis::film::{TileAccum, TileGrid};
    let scene = load("cornell-box.json", 16, 16);
    let pt = RenderSettings {
        integrator: IntegratorKind::Pt,
        ..optimal(4, 3, 1)
    };
    let bdpt = RenderSettings {
        mis: MisKind::Balance,
        ..optimal(4, 3, 1)
    };
    let (pt_layout, bdpt_layout) = (pt.film_layout(), bdpt.film_layout());
    assert!(!pt_layout.splats && bdpt_layout.splats);
    let grid = TileGrid::new(16, 16, 8);
    let tile = grid.tile(3);
    let px = tile.pixels();
    assert_eq!(
        TileCheckpoint::encoded_len(px, &bdpt_layout) - TileCheckpoint::encoded_len(px, &pt_layout),
        24 * px as u64
    );
    // A path-traced tile through its checkpoint: exact, and the image of the frame's pixels.
    let film = integrator::render_tile(&scene, &pt, tile, 0..4);
    let mut acc = TileAccum::new(tile, &pt_layout);
    assert!(acc.splat.is_empty());
    acc.add_own(&film);
    acc.end_pass(16 * 16 * 4, pt_layout.kappa);
    let bytes = TileCheckpoint {
        tile: acc.clone(),
        passes: 1,
    }
    .encode();
    assert_eq!(
        bytes.len() as u64,
        TileCheckpoint::encoded_len(px, &pt_layout)
    );
    let back = TileCheckpoint::decode(&bytes, tile, &pt_layout).expect("decodes");
    assert_eq!(back.tile.sums.sum, acc.sums.sum);
    assert_eq!(back.tile.sums.sum_sq, acc.sums.sum_sq);
    assert_eq!(back.tile.sums.count, acc.sums.count);
    assert_eq!(
        TileCheckpoint::check(&bytes, tile, &pt_layout).ok(),
        Some(1)
    );
    // Each layout refuses the other's checkpoints (their lengths differ), never misreads them.
    assert!(TileCheckpoint::check(&bytes, tile, &bdpt_layout).is_err());
    let b = TileCheckpoint {
        tile: TileAccum::new(tile, &bdpt_layout),
        passes: 1,
    }
    .encode();
    assert!(TileCheckpoint::check(&b, tile, &pt_layout).is_err());
    assert!(TileCheckpoint::decode(&b, tile, &pt_layout).is_err());
    // The image is the camera sums' mean.
    let img = acc.image(16 * 16 * 4, pt_layout.kappa);
    for (i, p) in img.pixels.iter().enumerate() {
        let n = acc.sums.count[i].max(1) as f64;
        assert_eq!(p.x, (acc.sums.sum[i][0] / n) as f32);
    }
    // A BDPT result has splats: the path tracer's layout refuses it, whole or banded, with an
    // error that says so; BDPT's own layout accepts the same bytes.
    let with_splats = integrator::render_tile(&scene, &bdpt, tile, 0..4);
    assert!(!with_splats.splats.is_empty());
    let whole = with_splats.encode(0..4);
    let e = TaskFilm::check(&whole, 16, 16, &pt_layout).expect_err("refused");
    assert!(e.to_string().contains("splats"), "{e}");
    assert!(TaskFilm::decode(&whole, 16, 16, &pt_layout).is_err());
    assert!(TaskFilm::check(&whole, 16, 16, &bdpt_layout).is_ok());
    let banded = format::encode_banded(with_splats, 0..4, &grid);
    let e = format::check_banded(&banded, &grid, &pt_layout, 1 << 30).expect_err("refused");
    assert!(e.to_string().contains("splats"), "{e}");
    assert!(format::check_banded(&banded, &grid, &bdpt_layout, 1 << 30).is_ok());
    // The path tracer's own result passes.
    let banded = format::encode_banded(film, 0..4, &grid);
    assert!(format::check_banded(&banded, &grid, &pt_layout, 1 << 30).is_ok());
}

/// A frame merged tile by tile — each tile's accumulators receiving, pass by pass, its own
/// task's sums and what every task of the pass routed to it, in task order — has the bits of the
/// frame merged task by task, whatever order the tiles are merged in.
#[test]
fn tile_by_tile_merge_has_the_bits_of_the_task_order_merge() {
    for mis in [MisKind::Optimal, MisKind::OptimalProgressive] {
        tile_by_tile_merge_case(mis);
    }
}

fn tile_by_tile_merge_case(mis: MisKind) {
    use omis::film::format::TileCheckpoint;
    use omis::film::{TileAccum, TileGrid};
    let scene = load("cornell-box-small-light.json", 24, 20);
    let mut s = optimal(6, 5, 3);
    s.mis = mis;
    s.strategies = true;
    s.depth_layers = true;
    let layout = s.film_layout();
    let grid = TileGrid::new(24, 20, 8);
    let tiles = grid.tiles();
    assert_eq!(
        tiles,
        make_tiles(24, 20, 8),
        "the grid is the schedule's tiling"
    );
    // Three passes: the progressive estimator weights the last two with solved weights.
    let passes = [0..2, 2..4, 4..6];
    let results: Vec<Vec<TaskFilm>> = passes
        .iter()
        .map(|r| {
            tiles
                .iter()
                .map(|t| integrator::render_tile(&scene, &s, *t, r.clone()))
                .collect()
        })
        .collect();
    // Task order, into one frame.
    let mut film = Film::new(24, 20, &layout);
    for pass in &results {
        for r in pass {
            film.add_task(r);
        }
        film.end_pass();
    }
    // Tile by tile, tiles in a scrambled order.
    let mut acc: Vec<TileAccum> = tiles.iter().map(|t| TileAccum::new(*t, &layout)).collect();
    for (p, pass) in results.iter().enumerate() {
        let routed: Vec<_> = pass.iter().map(|r| r.route(&grid)).collect();
        for k in 0..tiles.len() {
            let dest = (k * 7 + 3) % tiles.len();
            for (u, r) in pass.iter().enumerate() {
                if u == dest {
                    acc[dest].add_own(r);
                }
                if let Some((_, part)) = routed[u].iter().find(|(d, _)| *d == dest) {
                    acc[dest].add_routed(part, 24);
                }
            }
            acc[dest].end_pass(24 * 20 * passes[p].end as u64, layout.kappa);
        }
    }
    // Through the per-tile checkpoint encoding, which must be exact and validated.
    let acc: Vec<TileAccum> = acc
        .into_iter()
        .map(|t| {
            let bytes = TileCheckpoint {
                tile: t.clone(),
                passes: 3,
            }
            .encode();
            let len = TileCheckpoint::encoded_len(t.tile.pixels(), &layout);
            assert_eq!(bytes.len() as u64, len, "checkpoints have a fixed length");
            // Whether a checkpoint decodes; checking it without decoding (what the coordinator
            // does with a merge's output) must say the same, with the same passes.
            let decodes = |b: &[u8], tile: Tile, layout: &omis::film::FilmLayout| {
                let d = TileCheckpoint::decode(b, tile, layout);
                let c = TileCheckpoint::check(b, tile, layout);
                assert_eq!(d.as_ref().map(|d| d.passes).ok(), c.as_ref().ok().copied());
                d.is_ok()
            };
            let back = TileCheckpoint::decode(&bytes, t.tile, &layout).expect("decodes");
            assert_eq!(back.passes, 3);
            assert_eq!(back.tile.progressive, t.progressive);
            assert!(decodes(&bytes, t.tile, &layout));
            assert!(!decodes(&bytes[..bytes.len() - 1], t.tile, &layout));
            // A torn or damaged checkpoint fails its checksum.
            let mut torn = bytes.clone();
            torn[bytes.len() / 2] ^= 1;
            assert!(!decodes(&torn, t.tile, &layout));
            // Damage under a checksum made again: the structure's checks alone.
            let body = bytes.len() - 4;
            let mut refused = 0;
            // The header (magic, version, tile, passes), the counts of the layer lists and the
            // optimal depth after the pixels, the tail, and bytes all over.
            let layers_at = 32 + t.tile.pixels() * 76;
            let depths_at = layers_at + 4 + t.layers.len() * 24;
            let d_at = depths_at + 4 + t.depths.len() * 24;
            let counts = [layers_at, depths_at, d_at]
                .into_iter()
                .flat_map(|a| a..a + 4);
            for at in (0..40)
                .chain(counts)
                .chain((0..body).step_by(body / 211 + 1))
                .chain(body - 40..body)
            {
                let mut bad = bytes.clone();
                bad[at] ^= 0x81;
                let crc = crc32fast::hash(&bad[..body]);
                bad[body..].copy_from_slice(&crc.to_le_bytes());
                refused += !decodes(&bad, t.tile, &layout) as usize;
            }
            assert!(refused >= 40, "{refused}");
            assert!(decodes(&bytes, tiles[0], &layout) == (t.tile == tiles[0]));
            let mut shallower = optimal(4, 5, 2);
            shallower.mis = mis;
            assert!(!decodes(&bytes, t.tile, &shallower.film_layout()));
            // A checkpoint of the other optimal estimator is refused, not misread.
            let mut other = s.clone();
            other.mis = if mis == MisKind::Optimal {
                MisKind::OptimalProgressive
            } else {
                MisKind::Optimal
            };
            assert!(!decodes(&bytes, t.tile, &other.film_layout()));
            back.tile
        })
        .collect();
    let light_paths: u64 = acc.iter().map(|t| t.samples()).sum();
    assert_eq!(light_paths, film.light_paths());
    let mut beauty = Image::new(24, 20);
    let mut depth2 = Image::new(24, 20);
    let mut layer5 = Image::new(24, 20);
    for t in &acc {
        let (x, y) = (t.tile.x0 as usize, t.tile.y0 as usize);
        beauty.blit(&t.image(light_paths, layout.kappa), x, y);
        depth2.blit(&t.depth_image(2, light_paths, layout.kappa), x, y);
        layer5.blit(&t.strategy_image(5), x, y);
    }
    let q_set = film
        .acc
        .progressive
        .as_ref()
        .map(|p| p.data.iter().any(|&v| v != 0.0));
    let expect = (mis == MisKind::OptimalProgressive).then_some(true);
    assert_eq!(q_set, expect, "{mis:?}: progressive state kept and used");
    assert!(film.image() == beauty, "{mis:?}: beauty");
    assert!(film.depth_images()[2] == depth2, "{mis:?}: depth 2");
    assert!(
        film.strategy_images()[5].1 == layer5,
        "{mis:?}: strategy layer 5"
    );
    // Routing keeps everything and sends each record to the tile that holds its pixel.
    for r in &results[1] {
        let routed = r.route(&grid);
        let splats: usize = routed.iter().map(|(_, p)| p.splats.len()).sum();
        let records: usize = routed.iter().map(|(_, p)| p.records.len()).sum();
        assert_eq!((splats, records), (r.splats.len(), r.records.len()));
        for (d, part) in &routed {
            assert!(part.splats.iter().all(|x| grid.tile_of(x.pixel) == *d));
            assert!(part.records.pixels.iter().all(|&p| grid.tile_of(p) == *d));
        }
    }
}
