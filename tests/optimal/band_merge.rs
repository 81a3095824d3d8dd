//! Band-group merges of banded results and merge tasks chained over passes, bit for bit.

use crate::common::load;
use crate::support::optimal;
use omis::film::{Film, Image, TaskFilm};
use omis::integrator;
use omis::mis::MisKind;

/// The coordinator's merge: results stored laid out by band, every pass added band group by band
/// group (each group reading only its bands' sections), with a restart in the middle of a pass
/// (some groups already hold it), has the bits of the frame merged task by task. Damaged stored
/// results are refused.
#[test]
fn band_group_merge_of_banded_results_has_the_bits_of_the_task_order_merge() {
    band_group_merge_case(MisKind::OptimalProgressive);
    band_group_merge_case(MisKind::Optimal);
}

fn band_group_merge_case(mis: MisKind) {
    use omis::film::format::{self, BandedIndex};
    use omis::film::{BandGroup, TileAccum, TileGrid, band_groups};
    let (w, h) = (24, 20);
    let scene = load("cornell-box-small-light.json", w, h);
    let mut s = optimal(6, 5, 3);
    s.mis = mis;
    s.strategies = true;
    s.depth_layers = true;
    let layout = s.film_layout();
    let grid = TileGrid::new(w, h, 8);
    let tiles = grid.tiles();
    let passes = [0..2u32, 2..4, 4..6];
    let mut film = Film::new(w, h, &layout);
    let mut stored: Vec<Vec<Vec<u8>>> = Vec::new();
    for range in &passes {
        let mut pass = Vec::new();
        for t in &tiles {
            let r = integrator::render_tile(&scene, &s, *t, range.clone());
            film.add_task(&r);
            // What the coordinator stores: the upload, decoded, laid out by band.
            let (back, got) =
                TaskFilm::decode(&r.encode(range.clone()), w, h, &layout).expect("decodes");
            pass.push(format::encode_banded(back, got, &grid));
        }
        film.end_pass();
        stored.push(pass);
    }
    // Groups of one band, and a budget that puts two bands in a group.
    let band_bytes = (w as u64) * 8 * layout.bytes_per_pixel() as u64;
    for budget in [1, 2 * band_bytes] {
        let groups = band_groups(&grid, &layout, budget);
        assert_eq!(groups.first().map(|g| g.start), Some(0));
        assert_eq!(groups.last().map(|g| g.end), Some(grid.rows() as usize));
        let mut acc: Vec<TileAccum> = tiles.iter().map(|t| TileAccum::new(*t, &layout)).collect();
        let mut done = vec![0u32; tiles.len()];
        for (p, pass) in stored.iter().enumerate() {
            // Pass 1 restarted after its first group: that group's tiles hold it already.
            let restarts = p == 1;
            for (g, bands) in groups.iter().enumerate() {
                let rounds = if restarts && g == 0 { 2 } else { 1 };
                for _ in 0..rounds {
                    let range = grid.tiles_of_bands(bands.clone());
                    let open: Vec<bool> = range.clone().map(|t| done[t] == p as u32).collect();
                    let mut group =
                        BandGroup::new(&grid, bands.clone(), acc[range.clone()].to_vec(), open);
                    for (u, bytes) in pass.iter().enumerate() {
                        let index =
                            BandedIndex::read(&mut &bytes[..], bytes.len() as u64).expect("index");
                        assert_eq!(index.tile, tiles[u]);
                        let own = group.holds(u).then(|| {
                            let part = &bytes[index.own.start as usize..index.own.end as usize];
                            format::unpack_own(part, usize::MAX, w, h, &layout)
                                .expect("own")
                                .0
                        });
                        let sections: Vec<_> = index
                            .sections
                            .iter()
                            .filter(|(b, _)| bands.contains(&(*b as usize)))
                            .map(|(b, r)| {
                                let part = &bytes[r.start as usize..r.end as usize];
                                let b = *b as usize;
                                (
                                    b,
                                    format::unpack_section(part, usize::MAX, b, &grid, &layout)
                                        .expect("section"),
                                )
                            })
                            .collect();
                        group.add_task(&grid, u, own.as_ref(), &sections);
                    }
                    group.end_pass(w as u64 * h as u64 * passes[p].end as u64, layout.kappa);
                    for (k, t) in range.clone().enumerate() {
                        if group.open[k] {
                            done[t] += 1;
                        }
                        acc[t] = group.tiles[k].clone();
                    }
                }
            }
        }
        assert!(
            done.iter().all(|&d| d == 3),
            "each tile merged each pass once"
        );
        let light_paths = film.light_paths();
        let mut beauty = Image::new(w as usize, h as usize);
        let mut depth2 = Image::new(w as usize, h as usize);
        for t in &acc {
            let (x, y) = (t.tile.x0 as usize, t.tile.y0 as usize);
            beauty.blit(&t.image(light_paths, layout.kappa), x, y);
            depth2.blit(&t.depth_image(2, light_paths, layout.kappa), x, y);
        }
        assert!(film.image() == beauty, "{mis:?}: beauty, budget {budget}");
        assert!(
            film.depth_images()[2] == depth2,
            "{mis:?}: depth 2, budget {budget}"
        );
    }
    if mis == MisKind::Optimal {
        damaged_results_are_refused(&stored, &grid, &layout);
    }
}

fn damaged_results_are_refused(
    stored: &[Vec<Vec<u8>>],
    grid: &omis::film::TileGrid,
    layout: &omis::film::FilmLayout,
) {
    use omis::film::format::{self, BandedIndex};
    // Damage is refused: truncation, a wrong length, a section read as another band's.
    let bytes = &stored[0][3];
    let len = bytes.len() as u64;
    assert!(BandedIndex::read(&mut &bytes[..], len - 1).is_err());
    assert!(BandedIndex::read(&mut &bytes[..20], 20).is_err());
    assert!(BandedIndex::read(&mut &bytes[..], len + 1).is_err());
    let mut bad = bytes.clone();
    bad[0] ^= 1;
    assert!(BandedIndex::read(&mut &bad[..], len).is_err());
    let index = BandedIndex::read(&mut &bytes[..], len).expect("index");
    let (b, r) = index
        .sections
        .first()
        .expect("light tracing reaches some band")
        .clone();
    let part = &bytes[r.start as usize..r.end as usize];
    let other = (b as usize + 1) % grid.rows() as usize;
    assert!(format::decode_section(part, other, grid, layout).is_err());
    assert!(format::decode_section(&part[..part.len() - 1], b as usize, grid, layout).is_err());
    // Every part has its checksum; the header and table have theirs.
    assert!(index.check_section(0, part).is_ok());
    let mut flipped = part.to_vec();
    flipped[part.len() / 2] ^= 4;
    assert!(index.check_section(0, &flipped).is_err());
    let own = &bytes[index.own.start as usize..index.own.end as usize];
    assert!(index.check_own(own).is_ok());
    let mut flipped = own.to_vec();
    flipped[own.len() / 2] ^= 4;
    assert!(index.check_own(&flipped).is_err());
    let mut bad = bytes.clone();
    bad[84 + 12] ^= 1; // the first section's checksum: only the header's own catches it
    assert!(BandedIndex::read(&mut &bad[..], len).is_err());
    // Moved to where the record lies in a log, the ranges follow.
    let moved = index.clone().at(1000);
    assert_eq!(moved.own, index.own.start + 1000..index.own.end + 1000);
}

/// A merge task as a worker runs it (`film::merge_task::run`): fed the pass's banded results and the
/// previous pass's checkpoints, pass after pass and group by group, its outputs have the bits of
/// the in-process merge (beauties and checkpoints that the next pass continues from; on the
/// last pass the final EXR's blocks, every layer, in ZIP blocks of 16 lines or of one where
/// rows of tiles split them); an input cut anywhere is refused with an error, never a panic or
/// a partial output, and so is an output with a damaged block.
#[test]
fn merge_tasks_chained_over_passes_have_the_in_process_bits_and_refuse_cut_input() {
    use omis::film::format::merge_stream::{self, MergeHead, MergeOut, MergeOutput};
    use omis::film::format::{self, BandedIndex};
    use omis::film::merge_task;
    use omis::film::{TileGrid, band_groups};
    let (w, h) = (24, 20);
    let scene = load("cornell-box-small-light.json", w, h);
    let mut s = optimal(4, 5, 2);
    s.mis = MisKind::OptimalProgressive;
    s.depth_layers = true;
    let layout = s.film_layout();
    for tile_size in [8, 16] {
        let grid = TileGrid::new(w, h, tile_size);
        let exr = merge_stream::exr_layout(&grid, &layout).expect("layout");
        let tiles = grid.tiles();
        let groups = band_groups(&grid, &layout, 1);
        let mut film = Film::new(w, h, &layout);
        // Per tile: its latest checkpoint (None before the first pass).
        let mut checkpoints: Vec<Option<Vec<u8>>> = vec![None; tiles.len()];
        for (p, range) in [0..2u32, 2..4].into_iter().enumerate() {
            let stored: Vec<Vec<u8>> = tiles
                .iter()
                .map(|t| {
                    let r = integrator::render_tile(&scene, &s, *t, range.clone());
                    film.add_task(&r);
                    format::encode_banded(r, range.clone(), &grid)
                })
                .collect();
            film.end_pass();
            // Every layer the EXR holds, beauty first.
            let want: Vec<Image> = std::iter::once(film.image())
                .chain(film.extra_layers().into_iter().map(|(_, i)| i))
                .collect();
            assert!(want.len() > 2, "beauty, variance and depth layers");
            let last = p == 1;
            for bands in &groups {
                let b = bands.start as u32..bands.end as u32;
                let group_tiles = grid.tiles_of_bands(bands.clone());
                let kind = if last {
                    MergeOut::Exr
                } else {
                    MergeOut::Checkpoints
                };
                let mut input = MergeHead {
                    bands: b.clone(),
                    pass: p as u32,
                    merged: 1,
                    light_paths: (w * h * range.end) as u64,
                    out: kind,
                    results: stored.len() as u32,
                }
                .encode();
                for t in group_tiles.clone() {
                    let ck = checkpoints[t].as_ref();
                    input.extend(merge_stream::tile_entry(ck.map(|c| c.len() as u64)));
                    input.extend(ck.into_iter().flatten());
                }
                for (u, bytes) in stored.iter().enumerate() {
                    let index =
                        BandedIndex::read(&mut &bytes[..], bytes.len() as u64).expect("index");
                    let own = if group_tiles.contains(&u) {
                        &bytes[index.own.start as usize..index.own.end as usize]
                    } else {
                        &[][..]
                    };
                    let inside: Vec<_> = index
                        .sections
                        .iter()
                        .filter(|(band, _)| bands.contains(&(*band as usize)))
                        .collect();
                    let heads: Vec<(u32, u64)> =
                        inside.iter().map(|(b, r)| (*b, r.end - r.start)).collect();
                    input.extend(merge_stream::result_entry(
                        u as u32,
                        own.len() as u64,
                        &heads,
                    ));
                    input.extend_from_slice(own);
                    for (_, r) in inside {
                        input.extend_from_slice(&bytes[r.start as usize..r.end as usize]);
                    }
                }
                let out = merge_task::run(&input[..], &grid, &layout).expect("merge");
                let decode = |bytes: &[u8], b: std::ops::Range<u32>, passes: u32, k: MergeOut| {
                    MergeOutput::decode(bytes, &grid, &layout, b, passes, k).is_ok()
                };
                let got = MergeOutput::decode(&out, &grid, &layout, b.clone(), p as u32 + 1, kind)
                    .expect("the output checks");
                for other in [MergeOut::Checkpoints, MergeOut::Beauty, MergeOut::Exr] {
                    assert_eq!(decode(&out, b.clone(), p as u32 + 1, other), other == kind);
                }
                // The beauty: per tile, or the group's rows (read from its EXR blocks).
                for (tile, img) in &got.beauty {
                    for y in 0..tile.height() {
                        for x in 0..tile.width() {
                            let px = want[0].get(tile.x0 as usize + x, tile.y0 as usize + y);
                            assert_eq!(img.get(x, y), px, "pass {p} {tile:?} pixel ({x}, {y})");
                        }
                    }
                }
                if last {
                    // No checkpoint (nothing continues from it); the EXR's blocks of the
                    // group's rows, every layer with the in-process bits.
                    assert!(got.checkpoints.is_empty());
                    let rows = grid.band_rows(bands.clone());
                    assert_eq!(got.beauty.len(), 1);
                    assert_eq!(
                        got.first_block..got.first_block + got.blocks.len(),
                        exr.blocks_of(rows).expect("aligned")
                    );
                    for (k, bytes) in got.blocks.iter().enumerate() {
                        let blk = got.first_block + k;
                        let samples = exr.decompress_block(blk, bytes).expect("a block");
                        for (l, img) in want.iter().enumerate() {
                            for y in exr.block_rows(blk) {
                                let mut line = vec![Default::default(); w as usize];
                                exr.read_row(&samples, l, y, &mut line);
                                assert_eq!(line[..], img.pixels[y * w as usize..][..w as usize]);
                            }
                        }
                    }
                    // A damaged block is refused when the output is checked.
                    let first_len = 8 + 5 * 4 + 4;
                    for at in [first_len + 2, out.len() - 3] {
                        let mut bad = out.clone();
                        bad[at] ^= 0x5a;
                        assert!(!decode(&bad, b.clone(), p as u32 + 1, kind), "byte {at}");
                    }
                } else {
                    assert_eq!(got.checkpoints.len(), group_tiles.len());
                    assert_eq!(got.beauty.len(), group_tiles.len());
                    for (k, t) in group_tiles.clone().enumerate() {
                        checkpoints[t] = Some(got.checkpoints[k].to_vec());
                    }
                }
                // Another task's bands or passes: refused.
                let other = b.start + 1..b.end + 1;
                assert!(!decode(&out, other, p as u32 + 1, kind));
                assert!(!decode(&out, b.clone(), p as u32, kind));
                for cut in (0..input.len()).step_by(input.len() / 40 + 1) {
                    assert!(
                        merge_task::run(&input[..cut], &grid, &layout).is_err(),
                        "cut at {cut}"
                    );
                }
            }
        }
    }
}
