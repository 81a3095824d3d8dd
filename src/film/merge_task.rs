//! A pass merged by a worker instead of the coordinator: a merge task takes one band group (a few
//! rows of tiles), reads the group's tile checkpoints and, pass by pass in task order, every
//! part of the results since them that lands in the group, adds them with [`BandGroup`] (so the
//! tiles get exactly the additions `Film::add_task` makes: the in-process bits), and returns
//! what the task asks for ([`MergeOut`]): the tiles' new checkpoints and their beauty, or their
//! beauty alone (the next merge takes this pass's results again), or, on a job's last pass,
//! from which nothing continues, the group's scan lines of the final EXR, every layer, in
//! compressed blocks (`exr_io::ExrLayout`). The coordinator only moves bytes: it streams the
//! input from its result logs and checkpoint slots, checks the output (inflating the EXR
//! blocks) and writes the checkpoints in place, or the EXR from the blocks; the work that grows
//! with the records (decoding, applying light-tracing records to the optimal systems, solving)
//! and the EXR's compression run on the workers and scale with them.
//!
//! The bytes it reads and writes are the banded merge stream (`format::merge_stream`).

use super::bands::BandGroup;
use super::format::TileCheckpoint;
use super::format::merge_stream::{self, MAX_PART, MergeInput, MergeOut};
use super::format::{FormatError, unpack_own, unpack_section};
use super::{FilmLayout, Image, Tile, TileAccum, TileGrid};
use std::io::Read;

/// Images per layer (beauty first), each a list of (tile, image).
pub type LayerImages = Vec<Vec<(Tile, Image)>>;

/// The beauty of each tile and, with `all_layers`, every other layer the job keeps (in
/// `FilmLayout::extra_layer_names` order): one list of (tile, image) per layer.
pub fn tile_images(
    tiles: &[TileAccum],
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
pub fn run(input: impl Read, grid: &TileGrid, layout: &FilmLayout) -> Result<Vec<u8>, FormatError> {
    let mut r = MergeInput::new(input);
    let head = r.head(grid)?;
    if head.merged > 1 && layout.progressive_layout().is_some() {
        return Err(FormatError::invalid(format!(
            "merge input: {} passes at once for the progressive estimator, which ends each",
            head.merged
        )));
    }
    let bands = head.bands.start as usize..head.bands.end as usize;
    let tiles = grid.tiles_of_bands(bands.clone());
    let mut held = Vec::with_capacity(tiles.len());
    for t in tiles.clone() {
        let tile = grid.tile(t);
        held.push(match r.tile_checkpoint()? {
            None if head.pass == 0 => TileAccum::new(tile, layout),
            None => {
                return Err(FormatError::invalid(format!(
                    "merge input: tile {t} has no checkpoint after {} passes",
                    head.pass
                )));
            }
            Some(bytes) => {
                let ck = TileCheckpoint::decode(&bytes, tile, layout)?;
                if ck.passes != head.pass {
                    return Err(FormatError::invalid(format!(
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
        let result = r.result_head(grid, &bands)?;
        let t = result.tile;
        let own = if result.own_len > 0 {
            if !group.holds(t) {
                return Err(FormatError::invalid(format!(
                    "merge input: own part of tile {t}, outside bands {bands:?}"
                )));
            }
            let bytes = r.part(result.own_len, "own part")?;
            let (film, _) = unpack_own(&bytes, MAX_PART as usize, grid.width, grid.height, layout)?;
            if film.tile != grid.tile(t) {
                return Err(FormatError::invalid(format!(
                    "merge input: own part of tile {:?} for tile {t}",
                    film.tile
                )));
            }
            Some(film)
        } else {
            None
        };
        let mut sections = Vec::with_capacity(result.sections.len());
        for (b, len) in result.sections {
            let bytes = r.part(len, "section")?;
            let routed = unpack_section(&bytes, MAX_PART as usize, b, grid, layout)?;
            sections.push((b, routed));
        }
        group.add_task(grid, t, own.as_ref(), &sections);
    }
    group.end_pass(head.light_paths, layout.kappa);
    let passes = head.pass + head.merged;
    let mut out = merge_stream::output_head(&head.bands, passes);
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
    merge_stream::push_count(&mut out, group.tiles.len());
    if head.out == MergeOut::Checkpoints {
        for tile in &group.tiles {
            merge_stream::push_checkpoint(&mut out, &TileCheckpoint::encode_parts(tile, passes));
        }
    }
    for (_, img) in tile_images(&group.tiles, layout, head.light_paths, false)
        .iter()
        .flatten()
    {
        merge_stream::push_beauty(&mut out, img);
    }
    Ok(out)
}

/// Appends the EXR blocks of the scan lines of `bands` (block count, then each block's length
/// and bytes), made from the images of `tiles` (the bands' tiles, merged).
fn exr_blocks(
    out: &mut Vec<u8>,
    grid: &TileGrid,
    layout: &FilmLayout,
    bands: std::ops::Range<usize>,
    tiles: &[TileAccum],
    light_paths: u64,
) -> Result<(), FormatError> {
    let exr = merge_stream::exr_layout(grid, layout)?;
    let rows = grid.band_rows(bands);
    let blocks = exr.blocks_of(rows.clone())?;
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
    merge_stream::push_count(out, blocks.len());
    for b in blocks {
        let line = |l: usize, y: usize| &frames[l].pixels[(y - rows.start) * w..][..w];
        merge_stream::push_block(out, &exr.compress_block(b, line)?);
    }
    Ok(())
}
