//! One tile's checkpoint: its merged accumulators and the passes merged into them, as the
//! coordinator keeps them on disk and merge tasks read and return them.

use super::codec::{Reader, Writer};
use super::error::FormatError;
use super::pixel;
use crate::film::{FilmLayout, STRATEGY_LAYERS, Tile, TileAccum};
use crate::mis::Progressive;

/// The accumulators of a `TileAccum`, after a tile checkpoint's header:
///
/// ```text
/// per pixel: count u32, sum 3 x f64, sum_sq 3 x f64, splat 3 x f64 (where kept: `FilmLayout::splats`)
/// layers: n u32, n x 3 x f64; depths: n u32, n x 3 x f64
/// optimal: d_opt u32 (0 = none), then pixels x stride f64, pixels x d_opt u32
/// progressive (only when the job's layout keeps it): solved_at u32, pixels x values f64
/// (`mis::Progressive`)
/// ```
fn write_tile_body(w: &mut Writer, t: &TileAccum) {
    for i in 0..t.tile.pixels() {
        // The splat sums only where the film keeps them (`FilmLayout::splats`).
        let splat = t.splat.get(i);
        w.bytes(&pixel::encode(&t.sums, i, splat)[..pixel::len(splat.is_some())]);
    }
    w.rgb_list(&t.layers);
    w.rgb_list(&t.depths);
    w.optimal(t.optimal.as_ref());
    if let Some(p) = &t.progressive {
        w.u32(p.solved_at);
        for v in &p.data {
            w.f64(*v);
        }
    }
}

/// How many values each list of a tile's accumulators holds for a layout: what
/// `TileAccum::new` allocates (a checkpoint is read into a tile made so).
struct BodyLens {
    pixels: usize,
    /// Whether each pixel holds its splat sums.
    splats: bool,
    layers: usize,
    depths: usize,
    /// d_opt, f64 values and u32 hits of the optimal systems.
    optimal: Option<(u32, usize, usize)>,
    /// f64 values of the progressive estimator's state.
    progressive: Option<usize>,
}

impl BodyLens {
    fn of(tile: Tile, layout: &FilmLayout) -> BodyLens {
        let n = tile.pixels();
        BodyLens {
            pixels: n,
            splats: layout.splats,
            layers: if layout.strategy_layers {
                n * STRATEGY_LAYERS
            } else {
                0
            },
            depths: n * layout.depth_layers,
            optimal: layout
                .optimal
                .as_ref()
                .map(|l| (l.d_opt, n * l.values_per_pixel(), n * l.d_opt as usize)),
            progressive: layout
                .progressive_layout()
                .map(|d| n * Progressive::values_per_pixel(d)),
        }
    }
}

/// Reads a tile's accumulators of the lengths `lens` from `r` into `out`, or only checks them
/// (lengths, counts, depth) when `out` is None, skipping the values.
fn walk_tile_body(
    r: &mut Reader,
    lens: &BodyLens,
    mut out: Option<&mut TileAccum>,
) -> Result<(), FormatError> {
    let n = lens.pixels;
    let per_pixel = pixel::len(lens.splats);
    if n.saturating_mul(per_pixel) > r.b.len() - r.at {
        return Err(FormatError::invalid("checkpoint pixels truncated"));
    }
    let records = r.take(n * per_pixel)?;
    if let Some(t) = out.as_deref_mut() {
        for (i, rec) in records.chunks_exact(per_pixel).enumerate() {
            let splat = t.splat.get_mut(i).filter(|_| lens.splats);
            pixel::decode(rec, &mut t.sums, i, splat);
        }
    }
    for (k, (len, what)) in [
        (lens.layers, "strategy layers"),
        (lens.depths, "depth layers"),
    ]
    .into_iter()
    .enumerate()
    {
        let m = r.count(24, what)?;
        if m != len {
            return Err(FormatError::invalid(format!(
                "{what}: {m} values, the job has {len}"
            )));
        }
        match out.as_deref_mut() {
            None => {
                r.take(m * 24)?;
            }
            Some(t) => {
                let list = if k == 0 { &mut t.layers } else { &mut t.depths };
                for v in list.iter_mut() {
                    *v = [r.f64()?, r.f64()?, r.f64()?];
                }
            }
        }
    }
    let d = r.u32()?;
    match (lens.optimal, out.as_deref_mut()) {
        (None, _) if d == 0 => {}
        (Some((d_opt, values, hits)), t) if d_opt == d => {
            match t.and_then(|t| t.optimal.as_mut()) {
                Some(o) => r.optimal_into(o, false)?,
                None => {
                    if values * 8 + hits * 4 > r.b.len() - r.at {
                        return Err(FormatError::invalid("optimal systems truncated"));
                    }
                    r.take(values * 8 + hits * 4)?;
                }
            }
        }
        _ => {
            return Err(FormatError::invalid(format!(
                "optimal depth {d} does not match the job's settings"
            )));
        }
    }
    if let Some(values) = lens.progressive {
        let solved_at = r.u32()?;
        if values.saturating_mul(8) > r.b.len() - r.at {
            return Err(FormatError::invalid(
                "progressive estimator state truncated",
            ));
        }
        match out.and_then(|t| t.progressive.as_mut()) {
            Some(p) => {
                p.solved_at = solved_at;
                for v in p.data.iter_mut() {
                    *v = r.f64()?;
                }
            }
            None => {
                r.take(values * 8)?;
            }
        }
    }
    r.end()?;
    Ok(())
}

const TILE_MAGIC: &[u8; 8] = b"OMISTACC";
/// 3: the path tracer's checkpoints without splat sums.
const TILE_VERSION: u32 = 3;

/// `bytes` without its trailing CRC-32 (IEEE, u32), when the checksum matches.
fn checked<'a>(bytes: &'a [u8], what: &'static str) -> Result<&'a [u8], FormatError> {
    let Some(split) = bytes.len().checked_sub(4) else {
        return Err(FormatError::invalid(format!("{what} truncated")));
    };
    let (body, crc) = bytes.split_at(split);
    let want = u32::from_le_bytes(crc.try_into().expect("4 bytes"));
    if crc32fast::hash(body) != want {
        return Err(FormatError::Checksum {
            part: what,
            cause: "damaged or torn",
        });
    }
    Ok(body)
}

/// One tile's merged accumulators with the number of passes merged into it: the checkpoint a
/// coordinator keeps per tile, rewritten only when the tile merges a pass, so a restart loses no
/// merged pass and no write is larger than one tile. The checksum finds a checkpoint torn by a
/// crash in the middle of its write (the coordinator then reads the previous one).
///
/// ```text
/// magic "OMISTACC", version u32, tile x0 y0 x1 y1 u32, passes u32, then the tile's accumulators,
/// then the CRC-32 (IEEE) of everything before it, u32
/// ```
pub struct TileCheckpoint {
    /// The accumulators.
    pub tile: TileAccum,
    /// Passes merged into them.
    pub passes: u32,
}

impl TileCheckpoint {
    /// The encoding.
    pub fn encode(&self) -> Vec<u8> {
        TileCheckpoint::encode_parts(&self.tile, self.passes)
    }

    /// The encoding of the checkpoint of `tile` holding `passes` passes (without making one).
    pub fn encode_parts(tile: &TileAccum, passes: u32) -> Vec<u8> {
        let mut w = Writer::new(Vec::with_capacity(
            36 + tile.tile.pixels() * pixel::LEN_WITH_SPLAT,
        ));
        debug_assert!(tile.splat.is_empty() || tile.splat.len() == tile.tile.pixels());
        w.bytes(TILE_MAGIC);
        w.u32(TILE_VERSION);
        let t = &tile.tile;
        for v in [t.x0, t.y0, t.x1, t.y1, passes] {
            w.u32(v);
        }
        write_tile_body(&mut w, tile);
        let crc = crc32fast::hash(&w.out);
        w.u32(crc);
        w.out
    }

    /// The length of the checkpoint of a tile of `pixels` pixels whose films have `layout`
    /// (fixed: a coordinator rewrites checkpoints in place).
    pub fn encoded_len(pixels: usize, layout: &FilmLayout) -> u64 {
        // Header (magic, version, tile, passes), the three list lengths, the checksum, and the
        // progressive estimator's `solved_at` when the job keeps it.
        let progressive = if layout.progressive_layout().is_some() {
            4
        } else {
            0
        };
        (8 + 4 + 16 + 4 + 12 + 4 + progressive) as u64
            + (pixels as u64) * layout.bytes_per_pixel() as u64
    }

    /// The passes a stored checkpoint of `tile` holds, after checking its checksum, format and
    /// tile (without decoding the accumulators).
    pub fn peek(bytes: &[u8], tile: Tile) -> Result<u32, FormatError> {
        let bytes = checked(bytes, "tile checkpoint")?;
        let mut r = Reader::new(bytes);
        r.header_of(TILE_MAGIC, &[TILE_VERSION], "tile checkpoint")?;
        let got = r.tile()?;
        if got != tile {
            return Err(FormatError::invalid(format!(
                "checkpoint of tile {got:?}, expected {tile:?}"
            )));
        }
        r.u32()
    }

    /// Parses the checkpoint of `tile` of a job whose films have `layout`.
    pub fn decode(
        bytes: &[u8],
        tile: Tile,
        layout: &FilmLayout,
    ) -> Result<TileCheckpoint, FormatError> {
        let mut t = TileAccum::new(tile, layout);
        let passes = Self::walk(bytes, tile, layout, Some(&mut t))?;
        Ok(TileCheckpoint { tile: t, passes })
    }

    /// Checks the checkpoint of `tile` as `decode` reads it (it refuses what `decode` refuses),
    /// skipping the values; returns the passes it holds. What a coordinator does with the
    /// checkpoints a merge task returns.
    pub fn check(bytes: &[u8], tile: Tile, layout: &FilmLayout) -> Result<u32, FormatError> {
        Self::walk(bytes, tile, layout, None)
    }

    fn walk(
        bytes: &[u8],
        tile: Tile,
        layout: &FilmLayout,
        out: Option<&mut TileAccum>,
    ) -> Result<u32, FormatError> {
        let bytes = checked(bytes, "tile checkpoint")?;
        let mut r = Reader::new(bytes);
        r.header_of(TILE_MAGIC, &[TILE_VERSION], "tile checkpoint")?;
        let got = r.tile()?;
        if got != tile {
            return Err(FormatError::invalid(format!(
                "checkpoint of tile {got:?}, expected {tile:?}"
            )));
        }
        let passes = r.u32()?;
        walk_tile_body(&mut r, &BodyLens::of(tile, layout), out)?;
        Ok(passes)
    }
}
