//! The banded merge stream: what a coordinator streams to a merge task (its input) and what the
//! task uploads (its output), written and read here alone. The coordinator builds the input
//! (`MergeHead::encode`, `tile_entry`, `result_entry`, copying checkpoints and result parts
//! straight from its files) and checks the output (`MergeOutput::decode`); the merge task
//! (`film::merge_task`) reads the input (`MergeInput`) and writes the output (`output_head`,
//! `push_*`).
//!
//! ```text
//! input (coordinator -> worker), streamed:
//!   magic "OMISMRGI", version u32, bands b0 b1 u32, pass u32 (passes the tiles hold),
//!   merged u32 (passes whose results follow), light paths after them u64, output u8
//!   (`MergeOut`: 0 checkpoints, 1 beauty, 2 the final EXR's blocks), results n u32
//!   per tile of the bands, in tile order: present u8 (0: no checkpoint yet, pass 0),
//!     [length u64, the tile checkpoint (`TileCheckpoint`) holding `pass` passes]
//!   per result, pass by pass, in task order: tile u32, own length u64, sections m u32,
//!     m x (band u32, length u64), then the own part (the result without its splats and records; empty
//!     unless its tile is in the group), then the m sections (`decode_section`) back to
//!     back, each part packed (`pack`), as the result log keeps them: the coordinator
//!     copies both straight from it
//! output (worker -> coordinator):
//!   magic "OMISMRGO", version u32, bands b0 b1 u32, passes u32 (pass + merged), then
//!   checkpoints: tiles t u32, per tile: length u64, its checkpoint holding pass + merged
//!     passes; then per tile: its beauty, pixels x 3 f32
//!   beauty: tiles t u32, then per tile: its beauty, pixels x 3 f32
//!   the final EXR's blocks: blocks k u32 (those of the group's scan lines, `exr_layout`),
//!     per block: length u32, the block as the EXR stores it (ZIP-compressed, or stored)
//! ```

use super::checkpoint::TileCheckpoint;
use super::error::FormatError;
use crate::film::image::exr_io::{self, ExrLayout};
use crate::film::{FilmLayout, Image, Tile, TileGrid};
use crate::geometry::Rgb;
use std::io::Read;

const IN_MAGIC: &[u8; 8] = b"OMISMRGI";
const OUT_MAGIC: &[u8; 8] = b"OMISMRGO";
/// 3: the last pass's output holds no checkpoints. 4: the results' parts are packed. 5: the
/// last pass's output is the EXR's compressed blocks; before it, the beauty only. 6: a task
/// merges the results of one pass or more and says what it returns (`MergeOut`).
const VERSION: u32 = 6;
/// No part of a merge input (a checkpoint, a result's part) is longer.
pub const MAX_PART: u64 = 1 << 31;

/// What a merge task merges: the header of its input.
#[derive(Clone, Debug, PartialEq)]
pub struct MergeHead {
    /// The band group.
    pub bands: std::ops::Range<u32>,
    /// Passes the tiles hold before the merge (the index of the first pass merged).
    pub pass: u32,
    /// Passes whose results follow the tiles, one after another (at least one); a job whose
    /// pixels keep the progressive estimator's state merges one at a time (it ends each pass).
    pub merged: u32,
    /// Light paths traced for the frame once the passes are merged (N_L of the optimal systems).
    pub light_paths: u64,
    /// What the task returns.
    pub out: MergeOut,
    /// Results that follow the tiles.
    pub results: u32,
}

/// What a merge task returns.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MergeOut {
    /// The tiles' new checkpoints and their beauty.
    Checkpoints,
    /// The tiles' beauty alone: nothing continues from this merge, the next one takes its
    /// passes' results again (a pass's results can cost fewer bytes than a checkpoint).
    Beauty,
    /// The job's last pass: the final EXR's blocks of the group's scan lines (every layer the
    /// job keeps); the job ends with it.
    Exr,
}

impl MergeOut {
    fn code(self) -> u8 {
        match self {
            MergeOut::Checkpoints => 0,
            MergeOut::Beauty => 1,
            MergeOut::Exr => 2,
        }
    }
}

impl MergeHead {
    /// The first bytes of the input.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(37);
        out.extend_from_slice(IN_MAGIC);
        for v in [
            VERSION,
            self.bands.start,
            self.bands.end,
            self.pass,
            self.merged,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&self.light_paths.to_le_bytes());
        out.push(self.out.code());
        out.extend_from_slice(&self.results.to_le_bytes());
        out
    }
}

/// The bytes before a tile's checkpoint in the input (`None`: the tile has none yet).
pub fn tile_entry(checkpoint_len: Option<u64>) -> Vec<u8> {
    match checkpoint_len {
        None => vec![0],
        Some(n) => {
            let mut out = vec![1];
            out.extend_from_slice(&n.to_le_bytes());
            out
        }
    }
}

/// The bytes before a result's own part in the input: its tile, the own part's length (0 when
/// its tile is not in the group) and the band and length of each section that follows it.
pub fn result_entry(tile: u32, own_len: u64, sections: &[(u32, u64)]) -> Vec<u8> {
    let mut out = Vec::with_capacity(16 + 12 * sections.len());
    out.extend_from_slice(&tile.to_le_bytes());
    out.extend_from_slice(&own_len.to_le_bytes());
    out.extend_from_slice(&(sections.len() as u32).to_le_bytes());
    for (band, len) in sections {
        out.extend_from_slice(&band.to_le_bytes());
        out.extend_from_slice(&len.to_le_bytes());
    }
    out
}

/// A merge input read from a stream, naming what was truncated or malformed.
pub struct MergeInput<R> {
    r: std::io::BufReader<R>,
}

/// The head of one result in a merge input: its tile, the length of its own part (0 when its
/// tile is not in the group) and the band and length of each section that follows.
pub struct ResultHead {
    /// The result's tile (its index in the grid).
    pub tile: usize,
    /// Bytes of its own part.
    pub own_len: u64,
    /// Band and byte length of each section, in band order.
    pub sections: Vec<(usize, u64)>,
}

impl<R: Read> MergeInput<R> {
    /// A reader of the merge input `input`, buffered.
    pub fn new(input: R) -> Self {
        MergeInput {
            r: std::io::BufReader::with_capacity(1 << 20, input),
        }
    }
    fn bytes<const N: usize>(&mut self, what: &str) -> Result<[u8; N], FormatError> {
        let mut b = [0u8; N];
        self.r
            .read_exact(&mut b)
            .map_err(|source| FormatError::Read {
                part: format!("merge input: {what}"),
                source,
            })?;
        Ok(b)
    }
    fn u8(&mut self, what: &str) -> Result<u8, FormatError> {
        Ok(self.bytes::<1>(what)?[0])
    }
    fn u32(&mut self, what: &str) -> Result<u32, FormatError> {
        Ok(u32::from_le_bytes(self.bytes(what)?))
    }
    fn u64(&mut self, what: &str) -> Result<u64, FormatError> {
        Ok(u64::from_le_bytes(self.bytes(what)?))
    }
    /// A part of `len` bytes (at most `MAX_PART`), `what` naming it.
    pub fn part(&mut self, len: u64, what: &str) -> Result<Vec<u8>, FormatError> {
        if len > MAX_PART {
            return Err(FormatError::invalid(format!(
                "merge input: {what} of {len} bytes"
            )));
        }
        let mut b = Vec::new();
        (&mut self.r)
            .take(len)
            .read_to_end(&mut b)
            .map_err(|source| FormatError::Read {
                part: format!("merge input: {what}"),
                source,
            })?;
        if b.len() as u64 != len {
            return Err(FormatError::invalid(format!(
                "merge input: {what} truncated ({} of {len} bytes)",
                b.len()
            )));
        }
        Ok(b)
    }
    /// The input's head, for a frame tiled by `grid`.
    pub fn head(&mut self, grid: &TileGrid) -> Result<MergeHead, FormatError> {
        if &self.bytes::<8>("magic")? != IN_MAGIC {
            return Err(FormatError::Magic {
                format: "merge input",
            });
        }
        let got = self.u32("version")?;
        if got != VERSION {
            return Err(FormatError::Version {
                format: "merge input",
                got,
                expected: &[VERSION],
            });
        }
        let bands = self.u32("bands")?..self.u32("bands")?;
        if bands.start >= bands.end || bands.end > grid.rows() {
            return Err(FormatError::invalid(format!(
                "merge input: bands {bands:?} of a frame of {} bands",
                grid.rows()
            )));
        }
        let pass = self.u32("pass")?;
        let merged = self.u32("merged passes")?;
        if merged == 0 || pass.checked_add(merged).is_none() {
            return Err(FormatError::invalid(format!(
                "merge input: {merged} passes merged after {pass}"
            )));
        }
        let light_paths = self.u64("light paths")?;
        let out = match self.u8("output")? {
            0 => MergeOut::Checkpoints,
            1 => MergeOut::Beauty,
            2 => MergeOut::Exr,
            k => {
                return Err(FormatError::invalid(format!(
                    "merge input: output kind {k}"
                )));
            }
        };
        Ok(MergeHead {
            bands,
            pass,
            merged,
            light_paths,
            out,
            results: self.u32("result count")?,
        })
    }
}

impl<R: Read> MergeInput<R> {
    /// The next tile's checkpoint (None: the tile has none yet).
    pub fn tile_checkpoint(&mut self) -> Result<Option<Vec<u8>>, FormatError> {
        if self.u8("tile entry")? == 0 {
            return Ok(None);
        }
        let len = self.u64("checkpoint length")?;
        self.part(len, "tile checkpoint").map(Some)
    }

    /// The next result's head, for a frame tiled by `grid` of which the task merges `bands`.
    pub fn result_head(
        &mut self,
        grid: &TileGrid,
        bands: &std::ops::Range<usize>,
    ) -> Result<ResultHead, FormatError> {
        let t = self.u32("result tile")? as usize;
        if t >= grid.len() {
            return Err(FormatError::invalid(format!(
                "merge input: result of tile {t}"
            )));
        }
        let own_len = self.u64("own length")?;
        let m = self.u32("section count")? as usize;
        if m > bands.len() {
            return Err(FormatError::invalid(format!(
                "merge input: {m} sections for {} bands",
                bands.len()
            )));
        }
        let mut sections: Vec<(usize, u64)> = Vec::with_capacity(m);
        for _ in 0..m {
            let b = self.u32("section band")? as usize;
            if !bands.contains(&b) || sections.last().is_some_and(|(l, _)| *l >= b) {
                return Err(FormatError::invalid(format!(
                    "merge input: section of band {b} (bands {bands:?})"
                )));
            }
            sections.push((b, self.u64("section length")?));
        }
        Ok(ResultHead {
            tile: t,
            own_len,
            sections,
        })
    }
}

/// The first bytes of a merge output: the merge of `bands` into tiles holding `passes` passes.
pub fn output_head(bands: &std::ops::Range<u32>, passes: u32) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(OUT_MAGIC);
    for v in [VERSION, bands.start, bands.end, passes] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Appends the count of what follows (tiles, or EXR blocks).
pub fn push_count(out: &mut Vec<u8>, n: usize) {
    out.extend_from_slice(&(n as u32).to_le_bytes());
}

/// Appends a tile's encoded checkpoint.
pub fn push_checkpoint(out: &mut Vec<u8>, checkpoint: &[u8]) {
    out.extend_from_slice(&(checkpoint.len() as u64).to_le_bytes());
    out.extend_from_slice(checkpoint);
}

/// Appends a tile's beauty.
pub fn push_beauty(out: &mut Vec<u8>, img: &Image) {
    for p in &img.pixels {
        for v in p.to_array() {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
}

/// Appends an EXR block as the EXR stores it.
pub fn push_block(out: &mut Vec<u8>, block: &[u8]) {
    out.extend_from_slice(&(block.len() as u32).to_le_bytes());
    out.extend_from_slice(block);
}

/// The EXR layout of a frame tiled by `grid` whose films have `layout`: the beauty and every
/// extra layer, in blocks that rows of tiles never split (`exr_io::block_lines`).
pub fn exr_layout(grid: &TileGrid, layout: &FilmLayout) -> Result<ExrLayout, FormatError> {
    ExrLayout::new(
        grid.width as usize,
        grid.height as usize,
        &layout.extra_layer_names(),
        exr_io::block_lines(grid.size),
    )
    .map_err(FormatError::from)
}

/// A merge task's output, checked against what the task asked for.
pub struct MergeOutput<'a> {
    /// Per tile of the group, in tile order: its encoded checkpoint (holding `passes`), where
    /// it lies in the output; none unless the task returns checkpoints.
    pub checkpoints: Vec<&'a [u8]>,
    /// The group's beauty: per tile before the job's last pass; after it, one image of the
    /// group's scan lines, read from its EXR blocks.
    pub beauty: Vec<(Tile, Image)>,
    /// After the job's last pass: the final EXR's blocks of the group's scan lines, as the EXR
    /// stores them (`exr_layout`), the first being block `first_block`; each one was inflated
    /// to check it (and read for the beauty).
    pub blocks: Vec<&'a [u8]>,
    /// The frame's block index of `blocks[0]`.
    pub first_block: usize,
}

impl<'a> MergeOutput<'a> {
    /// Parses the output of the merge of `bands` into tiles that hold `passes` passes now, for a
    /// frame tiled by `grid` whose films have `layout`, which the task asked to return as
    /// `kind`. Every checkpoint is checked (its structure and checksum, as decoding would) and
    /// every EXR block inflated before it is accepted.
    pub fn decode(
        bytes: &'a [u8],
        grid: &TileGrid,
        layout: &FilmLayout,
        bands: std::ops::Range<u32>,
        passes: u32,
        kind: MergeOut,
    ) -> Result<MergeOutput<'a>, FormatError> {
        let mut at = 0usize;
        let mut take = |n: usize| -> Result<&'a [u8], FormatError> {
            if bytes.len() - at < n {
                return Err(FormatError::invalid(format!(
                    "merge output truncated at byte {at} (wanted {n} more)"
                )));
            }
            at += n;
            Ok(&bytes[at - n..at])
        };
        let u32_at = |take: &mut dyn FnMut(usize) -> Result<&'a [u8], FormatError>| {
            take(4).map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")))
        };
        if take(8)? != OUT_MAGIC {
            return Err(FormatError::invalid("not a merge output (bad magic)"));
        }
        let mut u32s = [0u32; 5];
        for v in &mut u32s {
            *v = u32_at(&mut take)?;
        }
        let [version, b0, b1, got_passes, n] = u32s;
        if version != VERSION {
            return Err(FormatError::invalid(format!(
                "merge output version {version}, expected {VERSION}"
            )));
        }
        let band_range = bands.start as usize..bands.end as usize;
        let tiles = grid.tiles_of_bands(band_range.clone());
        let rows = grid.band_rows(band_range);
        let exr = match kind {
            MergeOut::Exr => Some(exr_layout(grid, layout)?),
            _ => None,
        };
        let (what, want) = match &exr {
            Some(exr) => ("EXR blocks", exr.blocks_of(rows.clone())?.len()),
            None => ("tiles", tiles.len()),
        };
        if (b0..b1) != bands || got_passes != passes || n as usize != want {
            return Err(FormatError::invalid(format!(
                "merge output of bands {b0}..{b1} holding {got_passes} passes with {n} {what}; \
                 the task is bands {bands:?}, {passes} passes, {want} {what}"
            )));
        }
        let mut out = MergeOutput {
            checkpoints: Vec::new(),
            beauty: Vec::new(),
            blocks: Vec::new(),
            first_block: 0,
        };
        if let Some(exr) = exr {
            let blocks = exr.blocks_of(rows.clone())?;
            let w = grid.width as usize;
            let mut beauty = Image::new(w, rows.len());
            out.first_block = blocks.start;
            for b in blocks {
                let len = u32_at(&mut take)? as usize;
                if len > exr.max_block_bytes() {
                    return Err(FormatError::invalid(format!(
                        "merge output: EXR block {b} of {len} bytes (at most {})",
                        exr.max_block_bytes()
                    )));
                }
                let block = take(len)?;
                let samples = exr
                    .decompress_block(b, block)
                    .map_err(|e| FormatError::invalid(format!("merge output: {e}")))?;
                for y in exr.block_rows(b) {
                    let line = &mut beauty.pixels[(y - rows.start) * w..][..w];
                    exr.read_row(&samples, 0, y, line);
                }
                out.blocks.push(block);
            }
            let tile = Tile {
                x0: 0,
                y0: rows.start as u32,
                x1: grid.width,
                y1: rows.end as u32,
            };
            out.beauty.push((tile, beauty));
        } else {
            let checkpoints = if kind == MergeOut::Checkpoints {
                tiles.clone()
            } else {
                0..0
            };
            for t in checkpoints {
                let len = u64::from_le_bytes(take(8)?.try_into().expect("8 bytes"));
                let want = TileCheckpoint::encoded_len(grid.tile(t).pixels(), layout);
                if len != want {
                    return Err(FormatError::invalid(format!(
                        "merge output: checkpoint of tile {t} has {len} bytes, expected {want}"
                    )));
                }
                let ck = take(len as usize)?;
                let held = TileCheckpoint::check(ck, grid.tile(t), layout)?;
                if held != passes {
                    return Err(FormatError::invalid(format!(
                        "merge output: checkpoint of tile {t} holds {held} passes"
                    )));
                }
                out.checkpoints.push(ck);
            }
            for t in tiles {
                let tile = grid.tile(t);
                let raw = take(tile.pixels() * 12)?;
                let mut img = Image::new(tile.width(), tile.height());
                for (p, c) in img.pixels.iter_mut().zip(raw.chunks_exact(12)) {
                    let f = |k: usize| f32::from_le_bytes(c[k..k + 4].try_into().expect("4"));
                    *p = Rgb::new(f(0), f(4), f(8));
                }
                out.beauty.push((tile, img));
            }
        }
        if at != bytes.len() {
            return Err(FormatError::invalid(format!(
                "merge output: {} trailing bytes",
                bytes.len() - at
            )));
        }
        Ok(out)
    }
}
