//! Binary encoding of a tile task's result (what a worker uploads and a coordinator merges).
//!
//! Little-endian, versioned, self-describing enough to be validated before anything is merged:
//!
//! ```text
//! magic "OMISTILE", version u32
//! tile x0 y0 x1 y1 u32, samples s0 s1 u32
//! stats closest shadow samples non_finite u64
//! per tile pixel: count u32, sum 3 x f64, sum_sq 3 x f64 (a record of 52 bytes; in byte planes)
//! splats: n u32, then in planes: n splat steps; [n x layer u8]; [n x depth u8] (layer and
//! depth only when the job keeps strategy / depth layers); the high bytes of the narrow values,
//! then their low bytes (3 x k each: a value is 3 x bfloat16 when every channel is one, as the
//! integrators round light-tracing values: `bf16`); the wide values, 3 x w f32 (k + w = n, in
//! splat order within each plane)
//! layers: n u32 (0 or pixels x 14), then n x 3 x f64 (records of 24 bytes, in byte planes)
//! depths: n u32 (0 or pixels x depth layers), then n x 3 x f64 (the same)
//! optimal: d_opt u32 (0 = none), then pixels x stride f64 (A, b), pixels x d_opt u32 (hits),
//! each list in byte planes
//! records: n u32, pixels n x pixel step, depths n x u8 (none when d_opt is 1: all are 1),
//! value width u8, m u32, values m x width: width 2 (bfloat16, the m high bytes then the m low
//! bytes) when the integrators' rounding made every value one, without each record's
//! light-tracing weight (the others imply it: `LtRecords::implied_weight`), else width 4, all
//! values as f32
//! pixel step: the difference to the previous pixel of the list (0 before the first), zigzag
//! LEB128 (one or two bytes for the sorted lists `TaskFilm::compact` makes)
//! byte planes: a list of n records of s bytes as s planes of n bytes, byte 0 of every record
//! first (`pack::to_planes`); version 6 wrote the records one after another, and is still read
//! splat step: (difference to the previous pixel) x 2 + (1 if the value is f32), LEB128: splat
//! lists are sorted by pixel
//! ```
//! All sums stay f64: the merged frame must equal a single-process render to 1e-6, and solving
//! the optimal systems amplifies rounding. Splats and records lie in planes (v6) so that a
//! banded section is packed plane by plane (`pack::pack_pieces`): the bfloat16 high bytes

use super::codec::{Reader, Writer};
use super::error::FormatError;
use super::lists::{SplatKeys, check_rgb_count, read_rgb_list};
use super::pixel;
use crate::film::{FilmLayout, PixelSums, RayStats, STRATEGY_LAYERS, TaskFilm, Tile};
use crate::mis::OptimalAccum;

const MAGIC: &[u8; 8] = b"OMISTILE";
/// 6: splats and record values in planes; 7: the fixed-size records (pixel sums, layers,
/// optimal systems) in byte planes too.
const VERSION: u32 = 7;
/// The version before, whose results (in a coordinator's logs when it is upgraded) still read.
const VERSION_ROWS: u32 = 6;

impl TaskFilm {
    /// Serialises the result for upload.
    pub fn encode(&self, samples: std::ops::Range<u32>) -> Vec<u8> {
        self.encode_as(samples, VERSION).out
    }

    /// Serialises the result for upload, with the offsets where its planes end: the cuts at
    /// which `pack::pack_pieces` packs it.
    pub fn encode_in_planes(&self, samples: std::ops::Range<u32>) -> (Vec<u8>, Vec<usize>) {
        let w = self.encode_as(samples, VERSION);
        (w.out, w.cuts)
    }

    /// Serialises the result in format `version` (`VERSION`, or `VERSION_ROWS` for tests).
    fn encode_as(&self, samples: std::ops::Range<u32>, version: u32) -> Writer {
        let px = self.tile.pixels();
        let mut w = Writer::new(Vec::with_capacity(128 + px * pixel::LEN));
        w.planes = version == VERSION;
        w.bytes(MAGIC);
        w.u32(version);
        for v in [self.tile.x0, self.tile.y0, self.tile.x1, self.tile.y1] {
            w.u32(v);
        }
        w.u32(samples.start);
        w.u32(samples.end);
        w.stats(&self.stats);
        w.rows((0..px).map(|i| {
            let mut row = [0u8; pixel::LEN];
            row.copy_from_slice(&pixel::encode(&self.sums, i, None)[..pixel::LEN]);
            row
        }));
        w.splats(&self.splats, SplatKeys::of_film(self));
        w.rgb_list(&self.layers);
        w.rgb_list(&self.depths);
        w.optimal(self.optimal.as_ref());
        w.records(&self.records, self.optimal.as_ref().map(|o| o.layout.d_opt));
        w
    }

    /// Parses and validates an uploaded result for a frame of `width` x `height` pixels whose
    /// films have `layout`. Returns the film and its sample range.
    pub fn decode(
        bytes: &[u8],
        width: u32,
        height: u32,
        layout: &FilmLayout,
    ) -> Result<(TaskFilm, std::ops::Range<u32>), FormatError> {
        let (checked, film) = Self::walk(bytes, width, height, layout, true)?;
        Ok((film.expect("kept"), checked.samples))
    }

    /// Checks an encoded result as `decode` would read it (it refuses what `decode` refuses),
    /// without keeping its values (they are skipped, not parsed): its tile, sample range and
    /// work counters, and how many splats and records it holds. What a coordinator does with
    /// the own part of every result it accepts.
    pub fn check(
        bytes: &[u8],
        width: u32,
        height: u32,
        layout: &FilmLayout,
    ) -> Result<Checked, FormatError> {
        Ok(Self::walk(bytes, width, height, layout, false)?.0)
    }

    /// Reads an encoded result, keeping its film when `keep`, or only checking it.
    fn walk(
        bytes: &[u8],
        width: u32,
        height: u32,
        layout: &FilmLayout,
        keep: bool,
    ) -> Result<(Checked, Option<TaskFilm>), FormatError> {
        let d_opt = layout.d_opt();
        let mut r = Reader::new(bytes);
        let planes = r.header_of(MAGIC, &[VERSION, VERSION_ROWS], "tile result")? == VERSION;
        let tile = r.tile()?;
        if !(tile.x0 < tile.x1 && tile.y0 < tile.y1 && tile.x1 <= width && tile.y1 <= height) {
            return Err(FormatError::invalid(format!(
                "tile {tile:?} outside {width}x{height}"
            )));
        }
        let (s0, s1) = (r.u32()?, r.u32()?);
        if s0 > s1 {
            return Err(FormatError::invalid(format!("sample range {s0}..{s1}")));
        }
        let stats = r.stats()?;
        let px = tile.pixels();
        let frame_px = width as u64 * height as u64;
        let keys = SplatKeys::of_layout(layout);
        let strategy_values = if layout.strategy_layers {
            px * STRATEGY_LAYERS
        } else {
            0
        };
        if !keep {
            // Checking only: every length and count, no value.
            r.take(px * pixel::LEN)?;
            let splats = r.count(7, "splats")?;
            keys.allow(splats)?;
            r.check_splats(
                splats,
                keys.layer as usize + keys.depth as usize,
                &(0..frame_px),
            )?;
            check_rgb_count(&mut r, strategy_values, px, "strategy layer")?;
            check_rgb_count(&mut r, px * layout.depth_layers, px, "depth layer")?;
            match (r.u32()?, &layout.optimal) {
                (0, None) => {}
                (d, Some(l)) if d == l.d_opt => {
                    r.take(px * (l.values_per_pixel() * 8 + l.d_opt as usize * 4))?;
                }
                (d, _) => return Err(optimal_mismatch(d, d_opt)),
            }
            let records = r.peek_count()?;
            r.record_list(0..frame_px, d_opt, None)?;
            r.end()?;
            let checked = Checked::of(tile, s0..s1, stats, splats, records);
            return Ok((checked, None));
        }
        let mut sums = PixelSums::new(tile.width(), tile.height());
        let rows = r.rows(px, pixel::LEN, planes)?;
        for (i, rec) in rows.chunks_exact(pixel::LEN).enumerate() {
            pixel::decode(rec, &mut sums, i, None);
        }
        let splats = r.splats(0..frame_px, keys)?;
        let layers = read_rgb_list(&mut r, strategy_values, px, "strategy layer", planes)?;
        let depths = read_rgb_list(&mut r, px * layout.depth_layers, px, "depth layer", planes)?;
        let optimal = match (r.u32()?, &layout.optimal) {
            (0, None) => None,
            (d, Some(l)) if d == l.d_opt => {
                let mut acc = OptimalAccum::new(l.clone(), px);
                r.optimal_into(&mut acc, planes)?;
                Some(acc)
            }
            (d, _) => return Err(optimal_mismatch(d, d_opt)),
        };
        let records = r.records(0..frame_px, d_opt)?;
        r.end()?;
        let checked = Checked::of(tile, s0..s1, stats, splats.len(), records.len());
        let film = TaskFilm {
            tile,
            sums,
            splats,
            layers,
            depths,
            optimal,
            records,
            stats,
        };
        Ok((checked, Some(film)))
    }
}

/// What checking an encoded result (`TaskFilm::check`) found.
#[derive(Clone, Debug, PartialEq)]
pub struct Checked {
    /// Its tile.
    pub tile: Tile,
    /// Its sample range.
    pub samples: std::ops::Range<u32>,
    /// Its work counters.
    pub stats: RayStats,
    /// Light-tracing splats it holds.
    pub splats: usize,
    /// Optimal-MIS records it holds.
    pub records: usize,
}

impl Checked {
    fn of(
        tile: Tile,
        samples: std::ops::Range<u32>,
        stats: RayStats,
        splats: usize,
        records: usize,
    ) -> Checked {
        Checked {
            tile,
            samples,
            stats,
            splats,
            records,
        }
    }
}

fn optimal_mismatch(d: u32, d_opt: Option<u32>) -> FormatError {
    FormatError::invalid(format!(
        "optimal depth {d} does not match the job's {d_opt:?}"
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrator::{IntegratorKind, RenderSettings, render_tile};

    /// A result of version 6 (records one after another) still reads, to the film that the byte
    /// planes of version 7 hold; both have the same length and check alike, and the planes are
    /// where the pieces are cut.
    #[test]
    fn results_in_rows_and_in_byte_planes_read_the_same() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
        let mut scene = crate::scene::Scene::load(&dir.join("cornell-box.json")).expect("scene");
        scene.camera = scene.camera.with_resolution(16, 16).expect("resolution");
        let s = RenderSettings {
            integrator: IntegratorKind::Bdpt,
            mis: crate::mis::MisKind::Optimal,
            sample_block: 2,
            max_depth: 3,
            optimal_max_depth: 2,
            strategies: true,
            depth_layers: true,
            seed: 3,
            ..Default::default()
        };
        let tile = Tile {
            x0: 2,
            y0: 3,
            x1: 13,
            y1: 9,
        };
        let film = render_tile(&scene, &s, tile, 0..2);
        assert!(!film.layers.is_empty() && !film.depths.is_empty() && film.optimal.is_some());
        let layout = s.film_layout();
        let (planes, cuts) = film.encode_in_planes(0..2);
        let rows = film.encode_as(0..2, VERSION_ROWS).out;
        assert_eq!(planes, film.encode(0..2));
        assert_eq!(planes.len(), rows.len());
        assert_ne!(planes, rows);
        let (a, ra) = TaskFilm::decode(&planes, 16, 16, &layout).expect("version 7");
        let (b, rb) = TaskFilm::decode(&rows, 16, 16, &layout).expect("version 6");
        assert_eq!((ra, rb), (0..2, 0..2));
        assert_eq!(a.encode(0..2), planes, "the film read back");
        assert_eq!(b.encode(0..2), planes, "the same film from the rows");
        assert_eq!(
            TaskFilm::check(&planes, 16, 16, &layout).expect("checks"),
            TaskFilm::check(&rows, 16, 16, &layout).expect("checks")
        );
        let mut other = planes.clone();
        other[8..12].copy_from_slice(&5u32.to_le_bytes());
        assert!(TaskFilm::decode(&other, 16, 16, &layout).is_err());
        assert!(TaskFilm::check(&other, 16, 16, &layout).is_err());
        // The sums' 52 planes of a byte per pixel start after the 68-byte header.
        let px = tile.pixels();
        for j in 0..=52 {
            assert!(cuts.contains(&(68 + j * px)), "plane {j}");
        }
    }
}
