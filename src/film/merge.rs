//! A pass merged by a worker instead of the coordinator: a merge task takes one band group (a few
//! rows of tiles), reads the group's tile checkpoints and, pass by pass in task order, every
//! part of the results since them that lands in the group, adds them with [`BandGroup`] (so the
//! tiles get exactly the additions `Film::merge_task` makes: the in-process bits), and returns
//! what the task asks for ([`MergeOut`]): the tiles' new checkpoints and their beauty, or their
//! beauty alone (the next merge takes this pass's results again), or, on a job's last pass,
//! from which nothing continues, the group's scan lines of the final EXR, every layer, in
//! compressed blocks (`exr_io::ExrLayout`). The coordinator only moves bytes: it streams the
//! input from its result logs and checkpoint slots, checks the output (inflating the EXR
//! blocks) and writes the checkpoints in place, or the EXR from the blocks; the work that grows
//! with the records (decoding, applying light-tracing records to the optimal systems, solving)
//! and the EXR's compression run on the workers and scale with them.
//!
//! ```text
//! input (coordinator -> worker), streamed:
//!   magic "OMISMRGI", version u32, bands b0 b1 u32, pass u32 (passes the tiles hold),
//!   merged u32 (passes whose results follow), light paths after them u64, output u8
//!   (`MergeOut`: 0 checkpoints, 1 beauty, 2 the final EXR's blocks), results n u32
//!   per tile of the bands, in tile order: present u8 (0: no checkpoint yet, pass 0),
//!     [length u64, the tile checkpoint (wire::TileCheckpoint) holding `pass` passes]
//!   per result, pass by pass, in task order: tile u32, own length u64, sections m u32,
//!     m x (band u32, length u64), then the own part (the result without its splats and records; empty
//!     unless its tile is in the group), then the m sections (wire::decode_section) back to
//!     back, each part packed (film::pack), as the result log keeps them: the coordinator
//!     copies both straight from it
//! output (worker -> coordinator):
//!   magic "OMISMRGO", version u32, bands b0 b1 u32, passes u32 (pass + merged), then
//!   checkpoints: tiles t u32, per tile: length u64, its checkpoint holding pass + merged
//!     passes; then per tile: its beauty, pixels x 3 f32
//!   beauty: tiles t u32, then per tile: its beauty, pixels x 3 f32
//!   the final EXR's blocks: blocks k u32 (those of the group's scan lines, `exr_layout`),
//!     per block: length u32, the block as the EXR stores it (ZIP-compressed, or stored)
//! ```

use super::bands::BandGroup;
use super::exr_io::ExrLayout;
use super::film_tile::TileGrid;
use super::layers::FilmLayout;
use super::wire::{TileCheckpoint, WireError, unpack_own, unpack_section};
use super::{FilmTile, Image, Tile};
use crate::geometry::Rgb;
use std::io::Read;

const IN_MAGIC: &[u8; 8] = b"OMISMRGI";
const OUT_MAGIC: &[u8; 8] = b"OMISMRGO";
/// 3: the last pass's output holds no checkpoints. 4: the results' parts are packed. 5: the
/// last pass's output is the EXR's compressed blocks; before it, the beauty only. 6: a task
/// merges the results of one pass or more and says what it returns (`MergeOut`).
const VERSION: u32 = 6;
/// No part of a merge input (a checkpoint, a result's part) is longer.
const MAX_PART: u64 = 1 << 31;

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

/// Reads a merge input from a stream, naming what was truncated or malformed.
struct Input<R> {
    r: R,
}

impl<R: Read> Input<R> {
    fn bytes<const N: usize>(&mut self, what: &str) -> Result<[u8; N], WireError> {
        let mut b = [0u8; N];
        self.r
            .read_exact(&mut b)
            .map_err(|e| WireError(format!("merge input: {what}: {e}")))?;
        Ok(b)
    }
    fn u8(&mut self, what: &str) -> Result<u8, WireError> {
        Ok(self.bytes::<1>(what)?[0])
    }
    fn u32(&mut self, what: &str) -> Result<u32, WireError> {
        Ok(u32::from_le_bytes(self.bytes(what)?))
    }
    fn u64(&mut self, what: &str) -> Result<u64, WireError> {
        Ok(u64::from_le_bytes(self.bytes(what)?))
    }
    /// A part of `len` bytes (at most `MAX_PART`).
    fn part(&mut self, len: u64, what: &str) -> Result<Vec<u8>, WireError> {
        if len > MAX_PART {
            return Err(WireError(format!("merge input: {what} of {len} bytes")));
        }
        let mut b = Vec::new();
        (&mut self.r)
            .take(len)
            .read_to_end(&mut b)
            .map_err(|e| WireError(format!("merge input: {what}: {e}")))?;
        if b.len() as u64 != len {
            return Err(WireError(format!(
                "merge input: {what} truncated ({} of {len} bytes)",
                b.len()
            )));
        }
        Ok(b)
    }
    fn head(&mut self, grid: &TileGrid) -> Result<MergeHead, WireError> {
        if &self.bytes::<8>("magic")? != IN_MAGIC {
            return Err(WireError("not a merge input (bad magic)".into()));
        }
        let v = self.u32("version")?;
        if v != VERSION {
            return Err(WireError(format!(
                "merge input version {v}, expected {VERSION}"
            )));
        }
        let bands = self.u32("bands")?..self.u32("bands")?;
        if bands.start >= bands.end || bands.end > grid.rows() {
            return Err(WireError(format!(
                "merge input: bands {bands:?} of a frame of {} bands",
                grid.rows()
            )));
        }
        let pass = self.u32("pass")?;
        let merged = self.u32("merged passes")?;
        if merged == 0 || pass.checked_add(merged).is_none() {
            return Err(WireError(format!(
                "merge input: {merged} passes merged after {pass}"
            )));
        }
        let light_paths = self.u64("light paths")?;
        let out = match self.u8("output")? {
            0 => MergeOut::Checkpoints,
            1 => MergeOut::Beauty,
            2 => MergeOut::Exr,
            k => return Err(WireError(format!("merge input: output kind {k}"))),
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

/// Images per layer (beauty first), each a list of (tile, image).
pub type LayerImages = Vec<Vec<(Tile, Image)>>;

/// The beauty of each tile and, with `all_layers`, every other layer the job keeps (in
/// `FilmLayout::extra_layer_names` order): one list of (tile, image) per layer.
pub fn tile_images(
    tiles: &[FilmTile],
    layout: &FilmLayout,
    light_paths: u64,
    all_layers: bool,
) -> LayerImages {
    let mut layers: LayerImages = Vec::new();
    for tile in tiles {
        let mut images = vec![tile.image(light_paths, layout.kappa)];
        if all_layers {
            images.extend(tile.extra_images(layout, light_paths));
        }
        layers.resize_with(images.len(), Vec::new);
        for (l, img) in layers.iter_mut().zip(images) {
            l.push((tile.tile, img));
        }
    }
    layers
}

/// Runs a merge task: reads its input from `input` (for a frame tiled by `grid` whose films have
/// `layout`), merges, and returns the output to upload.
pub fn run(input: impl Read, grid: &TileGrid, layout: &FilmLayout) -> Result<Vec<u8>, WireError> {
    let mut r = Input {
        r: std::io::BufReader::with_capacity(1 << 20, input),
    };
    let head = r.head(grid)?;
    if head.merged > 1 && layout.progressive_layout().is_some() {
        return Err(WireError(format!(
            "merge input: {} passes at once for the progressive estimator, which ends each",
            head.merged
        )));
    }
    let bands = head.bands.start as usize..head.bands.end as usize;
    let tiles = grid.tiles_of_bands(bands.clone());
    let mut held = Vec::with_capacity(tiles.len());
    for t in tiles.clone() {
        let tile = grid.tile(t);
        held.push(match r.u8("tile entry")? {
            0 if head.pass == 0 => FilmTile::new(tile, layout),
            0 => {
                return Err(WireError(format!(
                    "merge input: tile {t} has no checkpoint after {} passes",
                    head.pass
                )));
            }
            _ => {
                let len = r.u64("checkpoint length")?;
                let bytes = r.part(len, "tile checkpoint")?;
                let ck = TileCheckpoint::decode(&bytes, tile, layout)?;
                if ck.passes != head.pass {
                    return Err(WireError(format!(
                        "merge input: checkpoint of tile {t} holds {} passes, not {}",
                        ck.passes, head.pass
                    )));
                }
                ck.tile
            }
        });
    }
    let open = vec![true; held.len()];
    let mut group = BandGroup::new(grid, bands.clone(), held, open);
    for _ in 0..head.results {
        let t = r.u32("result tile")? as usize;
        if t >= grid.len() {
            return Err(WireError(format!("merge input: result of tile {t}")));
        }
        let own_len = r.u64("own length")?;
        let m = r.u32("section count")? as usize;
        if m > bands.len() {
            return Err(WireError(format!(
                "merge input: {m} sections for {} bands",
                bands.len()
            )));
        }
        let mut heads: Vec<(usize, u64)> = Vec::with_capacity(m);
        for _ in 0..m {
            let b = r.u32("section band")? as usize;
            if !bands.contains(&b) || heads.last().is_some_and(|(l, _)| *l >= b) {
                return Err(WireError(format!(
                    "merge input: section of band {b} (bands {bands:?})"
                )));
            }
            heads.push((b, r.u64("section length")?));
        }
        let own = if own_len > 0 {
            if !group.holds(t) {
                return Err(WireError(format!(
                    "merge input: own part of tile {t}, outside bands {bands:?}"
                )));
            }
            let bytes = r.part(own_len, "own part")?;
            let (film, _) = unpack_own(&bytes, MAX_PART as usize, grid.width, grid.height, layout)?;
            if film.tile != grid.tile(t) {
                return Err(WireError(format!(
                    "merge input: own part of tile {:?} for tile {t}",
                    film.tile
                )));
            }
            Some(film)
        } else {
            None
        };
        let mut sections = Vec::with_capacity(m);
        for (b, len) in heads {
            let bytes = r.part(len, "section")?;
            let routed = unpack_section(&bytes, MAX_PART as usize, b, grid, layout)?;
            sections.push((b, routed));
        }
        group.add_task(grid, t, own.as_ref(), &sections);
    }
    group.end_pass(head.light_paths, layout.kappa);
    let passes = head.pass + head.merged;
    let mut out = Vec::new();
    out.extend_from_slice(OUT_MAGIC);
    for v in [VERSION, head.bands.start, head.bands.end, passes] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    if head.out == MergeOut::Exr {
        exr_blocks(
            &mut out,
            grid,
            layout,
            bands,
            &group.tiles,
            head.light_paths,
        )?;
        return Ok(out);
    }
    out.extend_from_slice(&(group.tiles.len() as u32).to_le_bytes());
    if head.out == MergeOut::Checkpoints {
        for tile in &group.tiles {
            let ck = TileCheckpoint::encode_parts(tile, passes);
            out.extend_from_slice(&(ck.len() as u64).to_le_bytes());
            out.extend_from_slice(&ck);
        }
    }
    for (_, img) in tile_images(&group.tiles, layout, head.light_paths, false)
        .iter()
        .flatten()
    {
        for p in &img.pixels {
            for v in p.to_array() {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    Ok(out)
}

/// The EXR layout of a frame tiled by `grid` whose films have `layout`: the beauty and every
/// extra layer, in blocks that rows of tiles never split (`exr_io::block_lines`).
pub fn exr_layout(grid: &TileGrid, layout: &FilmLayout) -> Result<ExrLayout, WireError> {
    ExrLayout::new(
        grid.width as usize,
        grid.height as usize,
        &layout.extra_layer_names(),
        super::exr_io::block_lines(grid.size),
    )
    .map_err(WireError)
}

/// Appends the EXR blocks of the scan lines of `bands` (block count, then each block's length
/// and bytes), made from the images of `tiles` (the bands' tiles, merged).
fn exr_blocks(
    out: &mut Vec<u8>,
    grid: &TileGrid,
    layout: &FilmLayout,
    bands: std::ops::Range<usize>,
    tiles: &[FilmTile],
    light_paths: u64,
) -> Result<(), WireError> {
    let exr = exr_layout(grid, layout)?;
    let rows = grid.band_rows(bands);
    let blocks = exr.blocks_of(rows.clone()).map_err(WireError)?;
    let w = grid.width as usize;
    let mut frames: Vec<Image> = Vec::new();
    for (l, list) in tile_images(tiles, layout, light_paths, true)
        .iter()
        .enumerate()
    {
        frames.push(Image::new(w, rows.len()));
        for (t, img) in list {
            frames[l].blit(img, t.x0 as usize, t.y0 as usize - rows.start);
        }
    }
    out.extend_from_slice(&(blocks.len() as u32).to_le_bytes());
    for b in blocks {
        let line = |l: usize, y: usize| &frames[l].pixels[(y - rows.start) * w..][..w];
        let bytes = exr.compress_block(b, line).map_err(WireError)?;
        out.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
        out.extend_from_slice(&bytes);
    }
    Ok(())
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
    ) -> Result<MergeOutput<'a>, WireError> {
        let mut at = 0usize;
        let mut take = |n: usize| -> Result<&'a [u8], WireError> {
            if bytes.len() - at < n {
                return Err(WireError(format!(
                    "merge output truncated at byte {at} (wanted {n} more)"
                )));
            }
            at += n;
            Ok(&bytes[at - n..at])
        };
        let u32_at = |take: &mut dyn FnMut(usize) -> Result<&'a [u8], WireError>| {
            take(4).map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")))
        };
        if take(8)? != OUT_MAGIC {
            return Err(WireError("not a merge output (bad magic)".into()));
        }
        let mut u32s = [0u32; 5];
        for v in &mut u32s {
            *v = u32_at(&mut take)?;
        }
        let [version, b0, b1, got_passes, n] = u32s;
        if version != VERSION {
            return Err(WireError(format!(
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
            Some(exr) => (
                "EXR blocks",
                exr.blocks_of(rows.clone()).map_err(WireError)?.len(),
            ),
            None => ("tiles", tiles.len()),
        };
        if (b0..b1) != bands || got_passes != passes || n as usize != want {
            return Err(WireError(format!(
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
            let blocks = exr.blocks_of(rows.clone()).map_err(WireError)?;
            let w = grid.width as usize;
            let mut beauty = Image::new(w, rows.len());
            out.first_block = blocks.start;
            for b in blocks {
                let len = u32_at(&mut take)? as usize;
                if len > exr.max_block_bytes() {
                    return Err(WireError(format!(
                        "merge output: EXR block {b} of {len} bytes (at most {})",
                        exr.max_block_bytes()
                    )));
                }
                let block = take(len)?;
                let samples = exr
                    .decompress_block(b, block)
                    .map_err(|e| WireError(format!("merge output: {e}")))?;
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
                    return Err(WireError(format!(
                        "merge output: checkpoint of tile {t} has {len} bytes, expected {want}"
                    )));
                }
                let ck = take(len as usize)?;
                let held = TileCheckpoint::check(ck, grid.tile(t), layout)?;
                if held != passes {
                    return Err(WireError(format!(
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
            return Err(WireError(format!(
                "merge output: {} trailing bytes",
                bytes.len() - at
            )));
        }
        Ok(out)
    }
}
