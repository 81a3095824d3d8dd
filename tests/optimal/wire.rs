//! Results on the wire: bfloat16 light-tracing values, decoding and checking damaged results,
//! banded uploads and sections.

use crate::common::load;
use crate::support::optimal;
use omis::film::{LtRecords, TaskFilm, Tile};
use omis::integrator::{self, RenderSettings};
use omis::mis::MisKind;

/// Light-tracing values leave a task as bfloat16: every splat that one sample made and every
/// record value but the light-tracing weight is one (the integrator rounds them, `film::bf16`),
/// so the wire ships 6 bytes of splat value where it shipped 12 and leaves that weight out;
/// sums of several splats and values that are not bfloat16 travel as f32. Either way the result decodes to the same bits.
#[test]
fn light_tracing_values_travel_as_bfloat16_and_decode_to_the_same_bits() {
    use omis::film::bf16;
    let scene = load("cornell-box.json", 16, 16);
    for (s, d_opt) in [(optimal(4, 3, 1), 1), (optimal(4, 3, 2), 2), {
        let mut b = optimal(4, 3, 1);
        b.mis = MisKind::Balance;
        (b, 0)
    }] {
        let tile = Tile {
            x0: 0,
            y0: 0,
            x1: 8,
            y1: 8,
        };
        let layout = s.film_layout();
        let mut film = integrator::render_tile(&scene, &s, tile, 0..4);
        assert!(film.splats.len() > 20, "{} splats", film.splats.len());
        let singles = film
            .splats
            .iter()
            .filter(|p| p.value.iter().all(|v| bf16::exact(*v)))
            .count();
        assert!(singles > 10, "{singles} of {}", film.splats.len());
        // A record's values are bfloat16, all but its light-tracing weight, which the others
        // imply (balance weights sum to 1) and the wire leaves out.
        let mut at = 0;
        for &d in &film.records.depths {
            let n = d as usize + 2;
            let rec = &film.records.values[at..at + n + 3];
            at += n + 3;
            assert!(
                rec[..n - 1]
                    .iter()
                    .chain(&rec[n..])
                    .all(|v| bf16::exact(*v))
            );
            assert_eq!(rec[n - 1], LtRecords::implied_weight(&rec[..n - 1]));
            let sum: f64 = rec[..n].iter().map(|w| *w as f64).sum();
            assert!((sum - 1.0).abs() < 1e-6, "weights sum to {sum}");
        }
        assert_eq!(at, film.records.values.len());
        assert_eq!(film.records.is_empty(), d_opt == 0);
        let check = |film: &TaskFilm| {
            let bytes = film.encode(0..4);
            let (back, _) = TaskFilm::decode(&bytes, 16, 16, &layout).expect("decodes");
            assert_eq!(back.splats, film.splats);
            assert_eq!(back.records, film.records);
            bytes.len()
        };
        let narrow = check(&film);
        // Values that are not bfloat16 take 6 bytes more a splat; records then travel as f32,
        // light-tracing weights included: 2 bytes more a value, 4 more a record.
        for p in &mut film.splats {
            p.value[0] = f32::from_bits(p.value[0].to_bits() | 1);
        }
        if let Some(v) = film.records.values.first_mut() {
            *v = f32::from_bits(v.to_bits() | 1);
        }
        let wide = check(&film);
        assert_eq!(
            wide - narrow,
            6 * singles + 2 * film.records.values.len() + 2 * film.records.len(),
            "d_opt {d_opt}"
        );
    }
}

#[test]
fn wire_decoding_rejects_damaged_results() {
    let scene = load("cornell-box.json", 16, 16);
    let s = optimal(2, 3, 3);
    let tile = Tile {
        x0: 0,
        y0: 0,
        x1: 8,
        y1: 8,
    };
    let film = integrator::render_tile(&scene, &s, tile, 0..2);
    let bytes = film.encode(0..2);
    let layout = s.film_layout();
    let shallower = optimal(2, 3, 2).film_layout();
    assert!(TaskFilm::decode(&bytes, 16, 16, &layout).is_ok());
    assert!(TaskFilm::decode(&bytes[..bytes.len() - 1], 16, 16, &layout).is_err());
    assert!(
        TaskFilm::decode(&bytes, 16, 16, &shallower).is_err(),
        "depth mismatch"
    );
    assert!(
        TaskFilm::decode(&bytes, 4, 4, &layout).is_err(),
        "tile outside the frame"
    );
    let mut bad = bytes.clone();
    bad[0] = b'X';
    assert!(TaskFilm::decode(&bad, 16, 16, &layout).is_err());
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(TaskFilm::decode(&longer, 16, 16, &layout).is_err());
    let with_depths = RenderSettings {
        depth_layers: true,
        ..s.clone()
    };
    assert!(
        TaskFilm::decode(&bytes, 16, 16, &with_depths.film_layout()).is_err(),
        "depth layers missing"
    );
    // The records close the result: value width u8, count u32, then the bfloat16 values, which
    // leave out each record's light-tracing weight.
    let r = &film.records;
    assert!(!r.is_empty());
    let m = r.values.len() - r.len();
    let width_at = bytes.len() - 2 * m - 5;
    assert_eq!(bytes[width_at], 2);
    let err = |b: &[u8]| match TaskFilm::decode(b, 16, 16, &layout) {
        Ok(_) => panic!("a damaged record list was accepted"),
        Err(e) => e.to_string(),
    };
    let mut bad = bytes.clone();
    bad[width_at] = 3;
    assert!(err(&bad).contains("record value width 3"), "{}", err(&bad));
    // f32 values take twice the bytes, and every record has one value more.
    bad[width_at] = 4;
    assert!(err(&bad).contains("record values"), "{}", err(&bad));
    let mut bad = bytes.clone();
    bad[width_at + 1..width_at + 5].copy_from_slice(&(m as u32 - 1).to_le_bytes());
    assert!(err(&bad).contains("expected"), "{}", err(&bad));
}

/// The coordinator's check of a result (`TaskFilm::check`, which skips the values) refuses
/// exactly what decoding refuses, and reports what decoding reads: for results with every kind
/// of content (splats, records, strategy and depth layers, optimal systems, and none of them),
/// whole, cut anywhere, with a byte changed anywhere, checked against another layout.
#[test]
fn checking_a_result_refuses_exactly_what_decoding_refuses() {
    let scene = load("cornell-box.json", 16, 16);
    let tile = Tile {
        x0: 8,
        y0: 0,
        x1: 16,
        y1: 8,
    };
    let full = RenderSettings {
        strategies: true,
        depth_layers: true,
        ..optimal(2, 3, 2)
    };
    let plain = RenderSettings {
        mis: MisKind::Balance,
        ..optimal(2, 3, 2)
    };
    let layouts = [full.film_layout(), plain.film_layout()];
    for s in [&full, &plain] {
        let mut film = integrator::render_tile(&scene, s, tile, 0..2);
        let whole = film.encode(0..2);
        film.splats.clear();
        film.records = Default::default();
        let own = film.encode(0..2);
        for bytes in [whole, own] {
            let mut variants = vec![bytes.clone()];
            for cut in (0..bytes.len()).step_by(bytes.len() / 97 + 1) {
                variants.push(bytes[..cut].to_vec());
            }
            for at in (0..bytes.len()).step_by(bytes.len() / 389 + 1) {
                for flip in [0x01u8, 0x80, 0xff] {
                    let mut v = bytes.clone();
                    v[at] ^= flip;
                    variants.push(v);
                }
            }
            let mut refused = 0;
            for v in &variants {
                for layout in &layouts {
                    let checked = TaskFilm::check(v, 16, 16, layout);
                    match TaskFilm::decode(v, 16, 16, layout) {
                        Ok((f, samples)) => {
                            let c = checked.expect("decoded, so it checks");
                            assert_eq!(c.tile, f.tile);
                            assert_eq!(c.samples, samples);
                            assert_eq!(c.stats, f.stats);
                            assert_eq!(c.splats, f.splats.len());
                            assert_eq!(c.records, f.records.pixels.len());
                        }
                        Err(e) => {
                            refused += 1;
                            assert!(checked.is_err(), "decode refused ({e}), check accepted");
                        }
                    }
                }
            }
            assert!(
                refused > variants.len() / 2,
                "{refused} of {}",
                2 * variants.len()
            );
        }
    }
}

/// The upload of tile 0 (samples 0..2, optimal MIS D_opt 3) of a 16x16 Cornell box in tiles of
/// 8, laid out by band as a worker sends it: (grid, layout, bytes).
fn banded_result() -> (omis::film::TileGrid, omis::film::FilmLayout, Vec<u8>) {
    banded_result_of(&optimal(2, 3, 3))
}

/// The upload of tile 0 (samples 0..2) of a 16x16 Cornell box in tiles of 8 rendered with `s`.
fn banded_result_of(s: &RenderSettings) -> (omis::film::TileGrid, omis::film::FilmLayout, Vec<u8>) {
    let scene = load("cornell-box.json", 16, 16);
    let grid = omis::film::TileGrid::new(16, 16, 8);
    let film = integrator::render_tile(&scene, s, grid.tile(0), 0..2);
    let bytes = omis::film::format::encode_banded(film, 0..2, &grid);
    (grid, s.film_layout(), bytes)
}

/// A result uploaded laid out by band is checked part by part before the coordinator stores it
/// as it came: a flipped byte in any part, a section out of its band or of the frame, an own
/// part that disagrees with the header are refused; a relabelled one (what the load generator
/// replays) passes as the other task's.
#[test]
fn banded_uploads_are_checked_before_they_are_stored() {
    use omis::film::TileGrid;
    use omis::film::format::{BandedIndex, check_banded, relabel_banded};
    let (grid, layout, bytes) = banded_result();
    let tile = grid.tile(0);
    let index = check_banded(&bytes, &grid, &layout, ANY).expect("a worker's upload passes");
    assert_eq!((index.tile, index.samples.clone()), (tile, 0..2));
    assert!(index.sections.len() == 2, "light paths reach both bands");
    // Any flipped byte of any part is found (header and table, own part, each section).
    let parts = std::iter::once(0..index.own.start as usize)
        .chain(std::iter::once(
            index.own.start as usize..index.own.end as usize,
        ))
        .chain(
            index
                .sections
                .iter()
                .map(|(_, r)| r.start as usize..r.end as usize),
        );
    for r in parts {
        let mut bad = bytes.clone();
        bad[(r.start + r.end) / 2] ^= 0x08;
        assert!(
            check_banded(&bad, &grid, &layout, ANY).is_err(),
            "part {r:?}"
        );
    }
    // Another frame: the sections' pixels leave their bands (or the bands the frame).
    assert!(check_banded(&bytes, &TileGrid::new(16, 8, 8), &layout, ANY).is_err());
    assert!(check_banded(&bytes, &TileGrid::new(16, 16, 16), &layout, ANY).is_err());
    assert!(check_banded(&bytes[..bytes.len() - 1], &grid, &layout, ANY).is_err());
    // Relabelled as tile 3, samples 4..6: checked as that task's result, parts unchanged.
    let moved = relabel_banded(&bytes, grid.tile(3), 4..6).expect("relabel");
    let again = check_banded(&moved, &grid, &layout, ANY).expect("the relabelled upload passes");
    assert_eq!((again.tile, again.samples.clone()), (grid.tile(3), 4..6));
    let bands = |i: &BandedIndex, b: &[u8]| -> Vec<(u32, Vec<u8>)> {
        i.sections
            .iter()
            .map(|(k, r)| (*k, b[r.start as usize..r.end as usize].to_vec()))
            .collect()
    };
    assert_eq!(bands(&again, &moved), bands(&index, &bytes));
    let read = BandedIndex::read(&mut &moved[..], moved.len() as u64).expect("index");
    assert_eq!(read, again);
    // Parts travel packed: what they inflate to is bounded by the caller, before anything is
    // inflated (a small upload must not become a large allocation).
    let raw: usize = std::iter::once(&index.own)
        .chain(index.sections.iter().map(|(_, r)| r))
        .map(|r| {
            omis::film::format::pack::raw_len(&bytes[r.start as usize..r.end as usize])
                .expect("head")
        })
        .sum();
    assert!(
        raw > bytes.len(),
        "the parts are compressed ({raw} raw, {} packed)",
        bytes.len()
    );
    assert!(check_banded(&bytes, &grid, &layout, raw as u64).is_ok());
    let err = check_banded(&bytes, &grid, &layout, raw as u64 - 1).expect_err("over the bound");
    assert!(err.to_string().contains("inflates"), "{err}");
}

/// No bound on what a test's upload inflates to.
const ANY: u64 = u64::MAX;

/// The coordinator checks sections without decoding them (`check_section`'s short path over
/// the pixel steps); whatever it accepts or refuses, decoding accepts or refuses alike, for
/// (unpacked) sections damaged anywhere (a splat's or record's pixel step, a count, a value, a
/// plane), with records of several depths, and with splats keyed by strategy and depth layer.
#[test]
fn checking_a_section_agrees_with_decoding_it() {
    let keyed = RenderSettings {
        mis: MisKind::Balance,
        strategies: true,
        depth_layers: true,
        ..optimal(2, 3, 3)
    };
    for s in [optimal(2, 3, 3), keyed] {
        check_and_decode_agree(banded_result_of(&s));
    }
}

fn check_and_decode_agree(
    (grid, layout, bytes): (omis::film::TileGrid, omis::film::FilmLayout, Vec<u8>),
) {
    use omis::film::format::{BandedIndex, check_section, decode_section};
    let index = BandedIndex::read(&mut &bytes[..], bytes.len() as u64).expect("index");
    let mut rng = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    let (mut refused, mut tried) = (0, 0);
    for (band, r) in &index.sections {
        let packed = &bytes[r.start as usize..r.end as usize];
        let section =
            &omis::film::format::pack::unpack_vec(packed, usize::MAX).expect("unpacks")[..];
        assert!(check_section(section, *band as usize, &grid, &layout).is_ok());
        for _ in 0..1500 {
            let mut bad = section.to_vec();
            for _ in 0..1 + next() % 3 {
                let at = (next() % bad.len() as u64) as usize;
                bad[at] ^= 1 << (next() % 8);
            }
            let checked = check_section(&bad, *band as usize, &grid, &layout);
            let decoded = decode_section(&bad, *band as usize, &grid, &layout);
            assert_eq!(
                checked.is_ok(),
                decoded.is_ok(),
                "band {band}: check {checked:?}, decode {:?}",
                decoded.err()
            );
            tried += 1;
            refused += checked.is_err() as u32;
        }
    }
    // Both outcomes were exercised.
    assert!(
        refused > 0 && refused < tried,
        "{refused} of {tried} refused"
    );
}
