//! OpenEXR output and input with the pure-Rust `exr` crate.
//!
//! A render is written as one EXR part whose channels are `R, G, B` (the beauty layer) plus
//! `<layer>.R, <layer>.G, <layer>.B` for every extra named layer: the dotted naming that
//! OpenEXR, Nuke and Blender read as a multi-layer image.
//!
//! Its scan lines are ZIP-compressed in blocks ([`ExrLayout`]): 16 lines a block, or one where
//! the frame's rows of tiles are not a multiple of 16 lines high, so that every row of tiles
//! begins a block. A block is compressed, checked and stored on its own, so the render
//! service's merge tasks compress the rows they merged and the coordinator only checks their
//! blocks (inflating, which costs a fraction of deflating) and writes them into the file.

use super::Image;
use crate::geometry::Rgb;
use exr::block::chunk::{Chunk, CompressedBlock, CompressedScanLineBlock};
use exr::block::writer::ChunksWriter;
use exr::meta::attribute::{AttributeValue, ChannelDescription, IntegerBounds, SampleType, Text};
use exr::meta::header::{Header, LayerAttributes};
use exr::prelude::{Compression, LineOrder, SmallVec};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

mod read;
pub use read::{beauty_size, for_each_beauty_line, read_exr, read_exr_beauty, read_exr_layers};

/// Why an EXR could not be written, read or laid out: what, and where.
#[derive(Debug, thiserror::Error)]
pub enum ExrError {
    /// A file that could not be created or opened.
    #[error("{}: {source}", path.display())]
    File {
        /// The file.
        path: PathBuf,
        /// The system's error.
        #[source]
        source: std::io::Error,
    },
    /// A file the exr crate cannot read.
    #[error("{}: not a readable EXR: {source}", path.display())]
    Unreadable {
        /// The file.
        path: PathBuf,
        /// The exr crate's error.
        #[source]
        source: exr::error::Error,
    },
    /// A file the exr crate could not write.
    #[error("{}: cannot write EXR: {source}", path.display())]
    Unwritable {
        /// The file.
        path: PathBuf,
        /// The exr crate's error.
        #[source]
        source: exr::error::Error,
    },
    /// A file without a complete R, G, B group of channels.
    #[error("{}: EXR has no R, G, B channels", path.display())]
    NoBeauty {
        /// The file.
        path: PathBuf,
    },
    /// A compressed block that does not inflate to its samples.
    #[error("EXR block {block}: {why}")]
    Block {
        /// The block's index in the file.
        block: usize,
        /// What is wrong with its bytes.
        why: String,
    },
    /// A frame, layer, block or line that does not fit the layout; the message names it.
    #[error("{0}")]
    Layout(String),
    /// The caller's own callback refused the file (its message).
    #[error("{0}")]
    Refused(String),
}

/// For callers whose errors are messages.
impl From<ExrError> for String {
    fn from(e: ExrError) -> String {
        e.to_string()
    }
}

/// A named RGB layer; the empty name is the beauty layer.
pub struct NamedLayer<'a> {
    /// The layer name (channels `<name>.R`, ...); empty for the beauty layer.
    pub name: String,
    /// The layer's pixels.
    pub image: &'a Image,
}

/// Scan lines per ZIP block of the EXR of a frame cut into tiles of `tile_size` pixels: 16
/// (OpenEXR's ZIP), or 1 (ZIPS) where rows of tiles would split a 16-line block.
pub fn block_lines(tile_size: u32) -> usize {
    if tile_size.is_multiple_of(16) { 16 } else { 1 }
}

/// How a render's EXR is laid out: its size, its layers (the beauty, then the extra ones), the
/// channels in the file's (sorted) order and its blocks of scan lines.
#[derive(Clone, Debug)]
pub struct ExrLayout {
    width: usize,
    height: usize,
    lines: usize,
    header: Header,
    /// Per channel in file order: (layer, component R G B = 0 1 2).
    order: Vec<(usize, usize)>,
}

/// A decompressed block: the native-endian f32 samples of its lines, channel by channel within
/// each line (OpenEXR's scan-line block layout).
pub struct Block {
    first_line: usize,
    samples: Vec<u8>,
}

impl ExrLayout {
    /// A `width` x `height` frame with the beauty and the `extra` layers (in that order), in
    /// ZIP blocks of `lines` (1 or 16) scan lines.
    pub fn new(
        width: usize,
        height: usize,
        extra: &[String],
        lines: usize,
    ) -> Result<ExrLayout, ExrError> {
        let compression = match lines {
            1 => Compression::ZIP1,
            16 => Compression::ZIP16,
            _ => return Err(ExrError::Layout(format!("ZIP blocks of {lines} lines"))),
        };
        Self::with(width, height, extra, lines, compression)
    }

    /// The same frame stored uncompressed, one scan line per block: what the coordinator
    /// writes between passes (deflating that beauty was 17.5 % of a 1080p BDPT balance job's
    /// coordinator CPU, BENCHMARKS.md, "The render service").
    pub fn uncompressed(
        width: usize,
        height: usize,
        extra: &[String],
    ) -> Result<ExrLayout, ExrError> {
        Self::with(width, height, extra, 1, Compression::Uncompressed)
    }

    fn with(
        width: usize,
        height: usize,
        extra: &[String],
        lines: usize,
        compression: Compression,
    ) -> Result<ExrLayout, ExrError> {
        if width == 0 || height == 0 {
            return Err(ExrError::Layout(format!(
                "an EXR of {width}x{height} pixels"
            )));
        }
        let mut named: Vec<(String, (usize, usize))> = Vec::new();
        for (l, name) in std::iter::once("")
            .chain(extra.iter().map(String::as_str))
            .enumerate()
        {
            if l > 0 && (name.is_empty() || !name.chars().all(|c| c.is_ascii_graphic())) {
                return Err(ExrError::Layout(format!("invalid layer name '{name}'")));
            }
            for (c, comp) in ["R", "G", "B"].iter().enumerate() {
                let full = if name.is_empty() {
                    comp.to_string()
                } else {
                    format!("{name}.{comp}")
                };
                named.push((full, (l, c)));
            }
        }
        // OpenEXR stores channels sorted by name.
        named.sort_by(|a, b| a.0.as_bytes().cmp(b.0.as_bytes()));
        if named.windows(2).any(|w| w[0].0 == w[1].0) {
            return Err(ExrError::Layout("two layers of the same name".into()));
        }
        let channels: SmallVec<[ChannelDescription; 5]> = named
            .iter()
            .map(|(n, _)| ChannelDescription::named(Text::from(n.as_str()), SampleType::F32))
            .collect();
        let header = Header::new(Text::from("omis"), (width, height), channels).with_encoding(
            compression,
            exr::meta::BlockDescription::ScanLines,
            LineOrder::Increasing,
        );
        Ok(ExrLayout {
            width,
            height,
            lines,
            header,
            order: named.into_iter().map(|(_, o)| o).collect(),
        })
    }

    /// Blocks of the frame, top to bottom.
    pub fn blocks(&self) -> usize {
        self.height.div_ceil(self.lines)
    }

    /// The scan lines of block `b`.
    pub fn block_rows(&self, b: usize) -> std::ops::Range<usize> {
        b * self.lines..((b + 1) * self.lines).min(self.height)
    }

    /// The blocks that hold exactly the scan lines `rows`, or why none do.
    pub fn blocks_of(
        &self,
        rows: std::ops::Range<usize>,
    ) -> Result<std::ops::Range<usize>, ExrError> {
        let aligned = |y: usize| y.is_multiple_of(self.lines) || y == self.height;
        if rows.start >= rows.end
            || rows.end > self.height
            || !aligned(rows.start)
            || !aligned(rows.end)
        {
            return Err(ExrError::Layout(format!(
                "lines {rows:?} of a {}-line frame are not whole blocks of {} lines",
                self.height, self.lines
            )));
        }
        Ok(rows.start / self.lines..rows.end.div_ceil(self.lines))
    }

    /// The most bytes a block can take: its samples uncompressed (OpenEXR stores a block whose
    /// compression would not make it shorter as it is).
    pub fn max_block_bytes(&self) -> usize {
        self.lines * self.width * self.order.len() * 4
    }

    /// Block `b` compressed, from `row(layer, y)`: the `width` pixels of line `y` of `layer`
    /// (0: the beauty, then the extra layers in the order given to `new`).
    pub fn compress_block<'a>(
        &self,
        b: usize,
        row: impl Fn(usize, usize) -> &'a [Rgb],
    ) -> Result<Vec<u8>, ExrError> {
        let rows = self.block_rows(b);
        let mut samples = Vec::with_capacity(rows.len() * self.width * self.order.len() * 4);
        for y in rows.clone() {
            for &(l, c) in &self.order {
                let line = row(l, y);
                if line.len() != self.width {
                    return Err(ExrError::Layout(format!(
                        "line {y} of layer {l} has {} pixels",
                        line.len()
                    )));
                }
                for p in line {
                    samples.extend_from_slice(&p[c].to_ne_bytes());
                }
            }
        }
        self.header
            .compression
            .compress_image_section_to_le(&self.header, samples, self.bounds(&rows))
            .map_err(|e| ExrError::Layout(format!("cannot compress EXR block {b}: {e}")))
    }

    /// Decompresses block `b` from `bytes`, checking that they are one: a ZIP stream (or the
    /// samples stored as they are) that inflates to exactly the block's samples.
    pub fn decompress_block(&self, b: usize, bytes: &[u8]) -> Result<Block, ExrError> {
        if b >= self.blocks() {
            return Err(ExrError::Layout(format!(
                "EXR block {b} of {}",
                self.blocks()
            )));
        }
        if bytes.len() > self.max_block_bytes() {
            return Err(ExrError::Layout(format!(
                "EXR block {b} of {} bytes; at most {} fit",
                bytes.len(),
                self.max_block_bytes()
            )));
        }
        let rows = self.block_rows(b);
        let n = rows.len() * self.width * self.order.len() * 4;
        let zip = matches!(
            self.header.compression,
            Compression::ZIP16 | Compression::ZIP1
        );
        let samples = if zip && bytes.len() != n {
            unzip(bytes, n).map_err(|why| ExrError::Block { block: b, why })?
        } else {
            self.header
                .compression
                .decompress_image_section_from_le(
                    &self.header,
                    bytes.to_vec(),
                    self.bounds(&rows),
                    true,
                )
                .map_err(|e| ExrError::Block {
                    block: b,
                    why: e.to_string(),
                })?
        };
        if samples.len() != n {
            return Err(ExrError::Layout(format!(
                "EXR block {b} holds {} bytes of samples, not {n}",
                samples.len()
            )));
        }
        Ok(Block {
            first_line: rows.start,
            samples,
        })
    }

    /// Line `y` of `layer` of a decompressed block, into `out` (`width` pixels).
    pub fn read_row(&self, block: &Block, layer: usize, y: usize, out: &mut [Rgb]) {
        let w = self.width;
        let line = (y - block.first_line) * self.order.len();
        for (ch, &(l, c)) in self.order.iter().enumerate() {
            if l != layer {
                continue;
            }
            let at = (line + ch) * w * 4;
            for (p, v) in out
                .iter_mut()
                .zip(block.samples[at..at + w * 4].chunks_exact(4))
            {
                p[c] = f32::from_ne_bytes(v.try_into().expect("4 bytes"));
            }
        }
    }

    /// Writes the EXR file from its compressed blocks (every one, in order; they move into the
    /// file's chunks without a copy), with `attributes` as string attributes of its header.
    pub fn write(
        &self,
        path: &Path,
        attributes: &[(&str, String)],
        blocks: Vec<Vec<u8>>,
    ) -> Result<(), ExrError> {
        if blocks.len() != self.blocks() {
            return Err(ExrError::Layout(format!(
                "{} blocks of {}",
                blocks.len(),
                self.blocks()
            )));
        }
        let mut attrs = LayerAttributes::named("omis");
        for (k, v) in attributes {
            attrs
                .other
                .insert(Text::from(*k), AttributeValue::Text(Text::from(v.as_str())));
        }
        let header = self.header.clone().with_attributes(attrs);
        let failed = |source| ExrError::Unwritable {
            path: path.to_path_buf(),
            source,
        };
        let file = std::fs::File::create(path).map_err(|source| ExrError::File {
            path: path.to_path_buf(),
            source,
        })?;
        exr::block::write(
            std::io::BufWriter::with_capacity(1 << 20, file),
            SmallVec::from_elem(header, 1),
            true,
            |_, writer| {
                for (b, bytes) in blocks.into_iter().enumerate() {
                    let chunk = Chunk {
                        layer_index: 0,
                        compressed_block: CompressedBlock::ScanLine(CompressedScanLineBlock {
                            y_coordinate: (b * self.lines) as i32,
                            compressed_pixels_le: bytes,
                        }),
                    };
                    writer.write_chunk(b, chunk)?;
                }
                Ok(())
            },
        )
        .map_err(failed)
    }

    fn bounds(&self, rows: &std::ops::Range<usize>) -> IntegerBounds {
        IntegerBounds::new((0, rows.start as i32), (self.width, rows.len()))
    }
}

/// Writes `beauty` plus `extra` layers (all the same size) as 32-bit float channels in ZIP
/// blocks of 16 scan lines, with `attributes` stored as string header attributes.
pub fn write_exr(
    path: &Path,
    beauty: &Image,
    extra: &[NamedLayer],
    attributes: &[(&str, String)],
) -> Result<(), ExrError> {
    write_exr_in_blocks(path, beauty, extra, attributes, 16)
}

/// `write_exr` in ZIP blocks of `lines` scan lines (`block_lines`), compressed on rayon's
/// threads.
pub fn write_exr_in_blocks(
    path: &Path,
    beauty: &Image,
    extra: &[NamedLayer],
    attributes: &[(&str, String)],
    lines: usize,
) -> Result<(), ExrError> {
    write_layers(path, beauty, extra, attributes, |w, h, names| {
        ExrLayout::new(w, h, names, lines)
    })
}

/// The `n` bytes of samples (little-endian f32, which this machine's are) that an EXR ZIP
/// block `zlib` holds, or why it holds no such thing. OpenEXR's ZIP compression: the bytes are
/// split into their even and odd halves, each byte stored as its difference to the one before
/// plus 128, and the whole deflated in a zlib stream. Inflated by libdeflate (Biggers), which
/// takes the stream whole into a buffer of the size it must fill: the coordinator inflates every
/// block of a job's final EXR to check it.
fn unzip(zlib: &[u8], n: usize) -> Result<Vec<u8>, String> {
    const _: () = assert!(
        cfg!(target_endian = "little"),
        "EXR samples are little-endian"
    );
    thread_local! {
        static INFLATE: std::cell::RefCell<(libdeflater::Decompressor, Vec<u8>)> =
            std::cell::RefCell::new((libdeflater::Decompressor::new(), Vec::new()));
    }
    INFLATE.with_borrow_mut(|(inflater, diffs)| {
        diffs.clear();
        diffs.resize(n, 0);
        match inflater.zlib_decompress(zlib, diffs) {
            Ok(k) if k == n => {}
            Ok(k) => return Err(format!("the zlib stream holds {k} bytes, not {n}")),
            Err(e) => return Err(format!("not a zlib stream of {n} bytes: {e}")),
        }
        undo_predictor(diffs);
        let (even, odd) = diffs.split_at(n.div_ceil(2));
        let mut out = vec![0u8; n];
        for (pair, (e, o)) in out.chunks_exact_mut(2).zip(even.iter().zip(odd)) {
            pair[0] = *e;
            pair[1] = *o;
        }
        if n % 2 == 1 {
            out[n - 1] = even[n / 2];
        }
        Ok(out)
    })
}

/// OpenEXR's ZIP predictor undone in place: every byte after the first is the one before plus
/// itself, less 128 (OpenEXR's `ImfZip.cpp`). A running sum: 16 bytes at a time with SSE2 (it
/// was a third of the time a coordinator spends checking a 1080p job's final EXR blocks).
fn undo_predictor(d: &mut [u8]) {
    let Some((&mut mut prev, rest)) = d.split_first_mut() else {
        return;
    };
    #[cfg(target_arch = "x86_64")]
    let tail = {
        let mut chunks = rest.chunks_exact_mut(16);
        for c in &mut chunks {
            use std::arch::x86_64::*;
            // SAFETY: SSE2 is part of every x86_64; the load and the store are of the 16 bytes of
            // `c` (unaligned).
            unsafe {
                let p = c.as_mut_ptr() as *mut __m128i;
                // The chunk's differences less 128, summed within the chunk (copies shifted by
                // 1, 2, 4 and 8 bytes added in turn), plus the byte before the chunk.
                let mut x = _mm_sub_epi8(_mm_loadu_si128(p), _mm_set1_epi8(i8::MIN));
                x = _mm_add_epi8(x, _mm_slli_si128::<1>(x));
                x = _mm_add_epi8(x, _mm_slli_si128::<2>(x));
                x = _mm_add_epi8(x, _mm_slli_si128::<4>(x));
                x = _mm_add_epi8(x, _mm_slli_si128::<8>(x));
                x = _mm_add_epi8(x, _mm_set1_epi8(prev as i8));
                _mm_storeu_si128(p, x);
                prev = (_mm_extract_epi16::<7>(x) >> 8) as u8;
            }
        }
        chunks.into_remainder()
    };
    #[cfg(not(target_arch = "x86_64"))]
    let tail = rest;
    for b in tail {
        *b = prev.wrapping_add(*b).wrapping_sub(128);
        prev = *b;
    }
}

/// `write_exr` with every sample stored as it is (no compression).
pub fn write_exr_uncompressed(
    path: &Path,
    beauty: &Image,
    extra: &[NamedLayer],
    attributes: &[(&str, String)],
) -> Result<(), ExrError> {
    write_layers(path, beauty, extra, attributes, ExrLayout::uncompressed)
}

/// The beauty and `extra` layers written in the blocks of the layout `layout` makes for them.
fn write_layers(
    path: &Path,
    beauty: &Image,
    extra: &[NamedLayer],
    attributes: &[(&str, String)],
    layout: impl FnOnce(usize, usize, &[String]) -> Result<ExrLayout, ExrError>,
) -> Result<(), ExrError> {
    let (w, h) = (beauty.width, beauty.height);
    let mut images = vec![beauty];
    for l in extra {
        if l.image.width != w || l.image.height != h {
            return Err(ExrError::Layout(format!(
                "layer '{}' is {}x{}, beauty is {w}x{h}",
                l.name, l.image.width, l.image.height
            )));
        }
        images.push(l.image);
    }
    let names: Vec<String> = extra.iter().map(|l| l.name.clone()).collect();
    let layout = layout(w, h, &names)?;
    let blocks = (0..layout.blocks())
        .into_par_iter()
        .map(|b| layout.compress_block(b, |l, y| &images[l].pixels[y * w..(y + 1) * w]))
        .collect::<Result<Vec<_>, _>>()?;
    layout.write(path, attributes, blocks)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame of `w` x `h` whose pixels differ everywhere (layer `l` scaled by l + 1).
    fn ramp(w: usize, h: usize, l: usize) -> Image {
        let mut img = Image::new(w, h);
        for (i, p) in img.pixels.iter_mut().enumerate() {
            let v = (i as f32 * 0.37).sin() * (l + 1) as f32;
            *p = Rgb::new(v, v * 0.5 + i as f32, -v);
        }
        img
    }

    #[test]
    fn blocks_compressed_one_at_a_time_make_the_file_and_read_back() {
        let dir = std::env::temp_dir().join(format!("omis-exr-blocks-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (w, h) = (13, 37);
        let names = ["variance".to_string(), "depth1".to_string()];
        let images: Vec<Image> = (0..3).map(|l| ramp(w, h, l)).collect();
        for lines in [1, 16] {
            let layout = ExrLayout::new(w, h, &names, lines).unwrap();
            assert_eq!(layout.blocks(), h.div_ceil(lines));
            assert_eq!(layout.block_rows(layout.blocks() - 1).end, h);
            // Blocks made out of order, as merge tasks return them; each reads back its lines.
            let mut blocks = vec![Vec::new(); layout.blocks()];
            for b in (0..layout.blocks()).rev() {
                blocks[b] = layout
                    .compress_block(b, |l, y| &images[l].pixels[y * w..(y + 1) * w])
                    .unwrap();
                assert!(blocks[b].len() <= layout.max_block_bytes());
                let samples = layout.decompress_block(b, &blocks[b]).unwrap();
                for y in layout.block_rows(b) {
                    for (l, img) in images.iter().enumerate() {
                        let mut line = vec![Rgb::ZERO; w];
                        layout.read_row(&samples, l, y, &mut line);
                        assert_eq!(line[..], img.pixels[y * w..(y + 1) * w]);
                    }
                }
            }
            let path = dir.join(format!("b{lines}.exr"));
            layout
                .write(&path, &[("omis.spp", "2".into())], blocks.clone())
                .unwrap();
            let read = read_exr_layers(&path).unwrap();
            let find = |n: &str| &read.iter().find(|(m, _)| m == n).unwrap().1;
            assert_eq!(find(""), &images[0]);
            assert_eq!(find("variance"), &images[1]);
            assert_eq!(find("depth1"), &images[2]);
            // The same file as the one compressed here at once.
            let named: Vec<NamedLayer> = names
                .iter()
                .zip(&images[1..])
                .map(|(n, image)| NamedLayer {
                    name: n.clone(),
                    image,
                })
                .collect();
            let whole = dir.join(format!("w{lines}.exr"));
            write_exr_in_blocks(
                &whole,
                &images[0],
                &named,
                &[("omis.spp", "2".into())],
                lines,
            )
            .unwrap();
            assert_eq!(
                std::fs::read(&whole).unwrap(),
                std::fs::read(&path).unwrap()
            );
            // Not every block: refused.
            assert!(layout.write(&path, &[], blocks[1..].to_vec()).is_err());
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    /// The coordinator's interim EXR: every sample stored as it is, read back exactly, as
    /// large as its samples (no compression), its header saying so.
    #[test]
    fn an_uncompressed_exr_reads_back_exactly() {
        let dir = std::env::temp_dir().join(format!("omis-exr-raw-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (w, h) = (13, 37);
        let beauty = ramp(w, h, 0);
        let path = dir.join("raw.exr");
        write_exr_uncompressed(&path, &beauty, &[], &[("omis.spp", "3".into())]).unwrap();
        assert_eq!(read_exr(&path).unwrap(), beauty);
        let len = std::fs::metadata(&path).unwrap().len() as usize;
        assert!(len >= w * h * 12, "{len} bytes");
        let meta = exr::meta::MetaData::read_from_file(&path, false).unwrap();
        assert_eq!(meta.headers[0].compression, Compression::Uncompressed);
        // Compressed, the same samples.
        let zip = dir.join("zip.exr");
        write_exr(&zip, &beauty, &[], &[("omis.spp", "3".into())]).unwrap();
        assert_eq!(read_exr(&zip).unwrap(), beauty);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn zip_blocks_inflate_as_the_exr_crate_reads_them() {
        let (w, h) = (37, 40);
        let img = ramp(w, h, 3);
        let layout = ExrLayout::new(w, h, &["variance".into()], 16).unwrap();
        for b in 0..layout.blocks() {
            let bytes = layout
                .compress_block(b, |_, y| &img.pixels[y * w..(y + 1) * w])
                .unwrap();
            let rows = layout.block_rows(b);
            let theirs = layout
                .header
                .compression
                .decompress_image_section_from_le(
                    &layout.header,
                    bytes.clone(),
                    layout.bounds(&rows),
                    true,
                )
                .unwrap();
            assert!(bytes.len() < theirs.len(), "compressed");
            assert_eq!(layout.decompress_block(b, &bytes).unwrap().samples, theirs);
        }
        // OpenEXR's ZIP of bytes of any length, odd ones too; a stream of the wrong length is
        // refused.
        let mut zip = libdeflater::Compressor::new(libdeflater::CompressionLvl::default());
        for n in [1usize, 2, 3, 16, 17, 18, 33, 1000, 1001, 4099] {
            let raw: Vec<u8> = (0..n).map(|i| (i * i % 253) as u8).collect();
            let mut t: Vec<u8> = raw
                .iter()
                .step_by(2)
                .chain(raw.iter().skip(1).step_by(2))
                .copied()
                .collect();
            for i in (1..n).rev() {
                t[i] = t[i].wrapping_sub(t[i - 1]).wrapping_add(128);
            }
            let mut z = vec![0; zip.zlib_compress_bound(n)];
            let k = zip.zlib_compress(&t, &mut z).unwrap();
            z.truncate(k);
            assert_eq!(unzip(&z, n).unwrap(), raw, "{n} bytes");
            assert!(unzip(&z, n + 1).is_err());
            assert!(unzip(&z, n - 1).is_err());
            if n > 1 {
                assert!(
                    layout.decompress_block(1, &z).is_err(),
                    "{n} bytes in block 1"
                );
            }
        }
    }

    #[test]
    fn damaged_or_misplaced_blocks_are_refused_with_an_error() {
        let (w, h) = (16, 40);
        let img = ramp(w, h, 0);
        let layout = ExrLayout::new(w, h, &[], 16).unwrap();
        let good = layout
            .compress_block(1, |_, y| &img.pixels[y * w..(y + 1) * w])
            .unwrap();
        assert!(good.len() < layout.max_block_bytes(), "compressed");
        assert!(layout.decompress_block(1, &good).is_ok());
        // Another block's lines (the last block has 8), a block past the end, truncated,
        // garbage, too long: each an error, none a panic.
        assert!(layout.decompress_block(2, &good).is_err());
        assert!(layout.decompress_block(3, &good).is_err());
        assert!(layout.decompress_block(1, &good[..good.len() - 1]).is_err());
        assert!(layout.decompress_block(1, &[]).is_err());
        let mut flipped = good.clone();
        let k = flipped.len() / 2;
        flipped[k] ^= 0x40;
        assert!(layout.decompress_block(1, &flipped).is_err());
        assert!(
            layout
                .decompress_block(1, &vec![7; layout.max_block_bytes() + 1])
                .is_err()
        );
        for n in [0, 1, 9, 100, 3000] {
            let junk: Vec<u8> = (0..n).map(|i| (i * 31 % 251) as u8).collect();
            assert!(layout.decompress_block(0, &junk).is_err(), "{n} bytes");
        }
        // Lines that are not whole blocks.
        assert_eq!(layout.blocks_of(16..40).ok(), Some(1..3));
        assert!(layout.blocks_of(8..40).is_err());
        assert!(layout.blocks_of(0..20).is_err());
        assert!(layout.blocks_of(0..41).is_err());
        assert!(ExrLayout::new(w, h, &[], 8).is_err());
        assert!(ExrLayout::new(w, h, &["a b".into()], 16).is_err());
        assert!(ExrLayout::new(w, h, &["x".into(), "x".into()], 16).is_err());
        assert_eq!(block_lines(64), 16);
        assert_eq!(block_lines(24), 1);
    }

    #[test]
    fn round_trip_with_layers() {
        let dir = std::env::temp_dir().join(format!("omis-exr-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.exr");
        let mut a = Image::new(5, 3);
        let mut b = Image::new(5, 3);
        for (i, p) in a.pixels.iter_mut().enumerate() {
            *p = Rgb::new(i as f32 * 0.5, 1e-7 * i as f32, -(i as f32) + 1e6);
        }
        for (i, p) in b.pixels.iter_mut().enumerate() {
            *p = Rgb::splat(i as f32 / 7.0);
        }
        write_exr(
            &path,
            &a,
            &[NamedLayer {
                name: "variance".into(),
                image: &b,
            }],
            &[("omis.spp", "4".into())],
        )
        .unwrap();
        let layers = read_exr_layers(&path).unwrap();
        let beauty = &layers.iter().find(|(n, _)| n.is_empty()).unwrap().1;
        let var = &layers.iter().find(|(n, _)| n == "variance").unwrap().1;
        assert_eq!(beauty, &a);
        assert_eq!(var, &b);
        std::fs::remove_dir_all(&dir).ok();
    }

    /// The beauty read block by block equals the one `read_exr` reads, with several layers, and
    /// from a tiled file; its size comes from the headers alone.
    #[test]
    fn the_beauty_read_block_by_block_is_read_exrs() {
        let dir = std::env::temp_dir().join(format!("omis-exr-beauty-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (w, h) = (37, 21);
        let images: Vec<Image> = (0..3).map(|l| ramp(w, h, l)).collect();
        let named: Vec<NamedLayer> = ["depth1", "variance"]
            .iter()
            .zip(&images[1..])
            .map(|(n, image)| NamedLayer {
                name: n.to_string(),
                image,
            })
            .collect();
        let path = dir.join("layers.exr");
        write_exr(&path, &images[0], &named, &[]).unwrap();
        assert_eq!(read_exr_beauty(&path).unwrap(), read_exr(&path).unwrap());
        assert_eq!(beauty_size(&path).unwrap(), (w, h));
        // Tiled, 16 x 16 tiles.
        use exr::prelude::{Blocks, Encoding, Layer, SpecificChannels, Vec2, WritableImage};
        let img = &images[0];
        let layer = Layer::new(
            (w, h),
            LayerAttributes::default(),
            Encoding {
                compression: Compression::ZIP1,
                blocks: Blocks::Tiles(Vec2(16, 16)),
                line_order: LineOrder::Increasing,
            },
            SpecificChannels::rgb(|p: Vec2<usize>| {
                let c = img.pixels[p.y() * w + p.x()];
                (c[0], c[1], c[2])
            }),
        );
        let tiled = dir.join("tiled.exr");
        exr::image::Image::from_layer(layer)
            .write()
            .to_file(&tiled)
            .unwrap();
        assert_eq!(read_exr_beauty(&tiled).unwrap(), *img);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
