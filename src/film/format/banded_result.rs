//! A task result as the coordinator stores it and merge tasks read it: laid out by band.

use super::codec::{Reader, Writer};
use super::error::FormatError;
use super::lists::SplatKeys;
use super::pack;
use crate::film::{FilmLayout, LtRecords, RayStats, Routed, TaskFilm, Tile, TileGrid};

const BAND_MAGIC: &[u8; 8] = b"OMISBAND";
/// 5: parts packed (`pack`). 6: sections in planes, packed in pieces.
const BAND_VERSION: u32 = 6;
/// Bytes before a banded result's section table.
const BAND_HEAD: usize = 8 + 4 + 16 + 8 + 32 + 8 + 4 + 4;
/// Bytes of one entry of the section table.
const BAND_ENTRY: usize = 4 + 8 + 4;

/// A task result as a coordinator stores it: laid out so that a merge holding only some bands
/// (rows of tiles) of the frame reads only what lands there, each part with its checksum, so a
/// record damaged on disk is found when it is read (and its task rendered again).
///
/// ```text
/// magic "OMISBAND", version u32, tile x0 y0 x1 y1 u32, samples s0 s1 u32, stats 4 x u64
/// own length u64, own CRC-32 u32, sections n u32, then n x (band u32, length u64, CRC-32 u32),
/// in band order, then the CRC-32 of the header and table, u32
/// own part: the tile result (OMISTILE) without its splats and records, packed (`pack`)
/// per section: splats, then records (the tile result's lists) that land in its band, packed
/// lengths and checksums are of the packed parts, as stored
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct BandedIndex {
    /// The task's tile.
    pub tile: Tile,
    /// Its sample range.
    pub samples: std::ops::Range<u32>,
    /// Its work counters.
    pub stats: RayStats,
    /// Byte range of the own part in the file.
    pub own: std::ops::Range<u64>,
    /// Checksum (CRC-32) of the own part.
    pub own_crc: u32,
    /// Band and byte range of each section, in band order.
    pub sections: Vec<(u32, std::ops::Range<u64>)>,
    /// Checksum (CRC-32) of each section, in the order of `sections`.
    pub section_crcs: Vec<u32>,
}

impl BandedIndex {
    /// Reads the header and section table from `r` (positioned at the start of a record of
    /// `len` bytes), checking its checksum and that the parts fill the record exactly.
    pub fn read(r: &mut impl std::io::Read, len: u64) -> Result<BandedIndex, FormatError> {
        let io = |source| FormatError::Read {
            part: "banded result header".into(),
            source,
        };
        let mut head = [0u8; BAND_HEAD];
        r.read_exact(&mut head).map_err(io)?;
        let mut h = Reader::new(&head);
        h.header_of(BAND_MAGIC, &[BAND_VERSION], "banded result")?;
        let tile = h.tile()?;
        let samples = h.u32()?..h.u32()?;
        let stats = h.stats()?;
        let own_len = h.u64()?;
        let own_crc = h.u32()?;
        let n = h.u32()? as u64;
        if n.saturating_mul(BAND_ENTRY as u64) > len {
            return Err(FormatError::invalid(format!(
                "{n} sections exceed the record"
            )));
        }
        let mut table = vec![0u8; n as usize * BAND_ENTRY + 4];
        r.read_exact(&mut table).map_err(io)?;
        let mut crc = crc32fast::Hasher::new();
        crc.update(&head);
        crc.update(&table[..table.len() - 4]);
        let mut t = Reader::new(&table);
        let mut at = BAND_HEAD as u64 + table.len() as u64;
        let own = at..at.saturating_add(own_len);
        at = own.end;
        let mut sections = Vec::with_capacity(n as usize);
        let mut section_crcs = Vec::with_capacity(n as usize);
        let mut last = None;
        for _ in 0..n {
            let band = t.u32()?;
            if last.is_some_and(|l| l >= band) {
                return Err(FormatError::invalid(format!(
                    "section of band {band} out of order"
                )));
            }
            last = Some(band);
            let len = t.u64()?;
            section_crcs.push(t.u32()?);
            sections.push((band, at..at.saturating_add(len)));
            at = at.saturating_add(len);
        }
        if t.u32()? != crc.finalize() {
            return Err(FormatError::Checksum {
                part: "banded result header",
                cause: "damaged",
            });
        }
        if at != len {
            return Err(FormatError::invalid(format!(
                "banded result parts end at byte {at}, the record has {len}"
            )));
        }
        Ok(BandedIndex {
            tile,
            samples,
            stats,
            own,
            own_crc,
            sections,
            section_crcs,
        })
    }

    /// The same index for the record stored at byte `base` of a file (every range moved).
    pub fn at(mut self, base: u64) -> BandedIndex {
        let shift = |r: &mut std::ops::Range<u64>| {
            *r = r.start.saturating_add(base)..r.end.saturating_add(base)
        };
        shift(&mut self.own);
        for (_, r) in &mut self.sections {
            shift(r);
        }
        self
    }

    /// Checks the bytes of the own part against its checksum.
    pub fn check_own(&self, bytes: &[u8]) -> Result<(), FormatError> {
        check_crc(bytes, self.own_crc, "banded result own part")
    }

    /// Checks the bytes of section `k` (of `sections`) against its checksum.
    pub fn check_section(&self, k: usize, bytes: &[u8]) -> Result<(), FormatError> {
        let want = self.section_crcs.get(k).copied().unwrap_or(0);
        check_crc(bytes, want, "banded result section")
    }

    /// The byte range holding the sections of `bands` (contiguous: sections are in band order),
    /// or None when none of them received anything.
    pub fn span(&self, bands: std::ops::Range<usize>) -> Option<std::ops::Range<u64>> {
        let mut inside = self
            .sections
            .iter()
            .filter(|(b, _)| bands.contains(&(*b as usize)));
        let first = inside.next()?;
        let end = inside.next_back().unwrap_or(first).1.end;
        Some(first.1.start..end)
    }
}

/// Checks `bytes`, the part `what`, against its checksum `want`.
fn check_crc(bytes: &[u8], want: u32, what: &'static str) -> Result<(), FormatError> {
    if crc32fast::hash(bytes) != want {
        return Err(FormatError::Checksum {
            part: what,
            cause: "damaged",
        });
    }
    Ok(())
}

/// Lays a decoded, validated task result out for band-wise merging (see `BandedIndex`), each
/// part packed (`pack`).
pub fn encode_banded(
    mut film: TaskFilm,
    samples: std::ops::Range<u32>,
    grid: &TileGrid,
) -> Vec<u8> {
    let bands = film.route_bands(grid);
    let keys = SplatKeys::of_film(&film);
    let d_opt = film.optimal.as_ref().map(|o| o.layout.d_opt);
    film.splats = Vec::new();
    film.records = LtRecords::default();
    let (own, cuts) = film.encode_in_planes(samples.clone());
    let own = pack::pack_pieces(&own, &cuts);
    let sections: Vec<(u32, Vec<u8>)> = bands
        .into_iter()
        .map(|(b, routed)| {
            let mut w = Writer::new(Vec::new());
            w.splats(&routed.splats, keys);
            w.records(&routed.records, d_opt);
            (b as u32, pack::pack_pieces(&w.out, &w.cuts))
        })
        .collect();
    let sections: Vec<(u32, &[u8])> = sections.iter().map(|(b, s)| (*b, &s[..])).collect();
    assemble(film.tile, samples, &film.stats, &own, &sections)
}

/// A banded result of `tile`, `samples` and `stats` from its packed parts (`BandedIndex`).
fn assemble(
    t: Tile,
    samples: std::ops::Range<u32>,
    stats: &RayStats,
    own: &[u8],
    sections: &[(u32, &[u8])],
) -> Vec<u8> {
    let body: usize = own.len() + sections.iter().map(|(_, s)| s.len()).sum::<usize>();
    let table = sections.len() * BAND_ENTRY + 4;
    let mut w = Writer::new(Vec::with_capacity(BAND_HEAD + table + body));
    w.bytes(BAND_MAGIC);
    w.u32(BAND_VERSION);
    for v in [t.x0, t.y0, t.x1, t.y1, samples.start, samples.end] {
        w.u32(v);
    }
    w.stats(stats);
    w.u64(own.len() as u64);
    w.u32(crc32fast::hash(own));
    w.u32(sections.len() as u32);
    for (b, s) in sections {
        w.u32(*b);
        w.u64(s.len() as u64);
        w.u32(crc32fast::hash(s));
    }
    let head_crc = crc32fast::hash(&w.out);
    w.u32(head_crc);
    w.bytes(own);
    for (_, s) in sections {
        w.bytes(s);
    }
    w.out
}

/// Checks a banded result as a worker uploads it (`encode_banded`), for a frame tiled by `grid`
/// whose films have `layout`: its header and section table, every part's checksum, the own part
/// (a tile result without splats or records, with the header's tile, samples and counters) and
/// every section (its band one of the frame's, everything in it landing there). Its parts may
/// inflate to at most `max_raw` bytes together. Returns the index, its ranges relative to the
/// start of `bytes`.
pub fn check_banded(
    bytes: &[u8],
    grid: &TileGrid,
    layout: &FilmLayout,
    max_raw: u64,
) -> Result<BandedIndex, FormatError> {
    let index = BandedIndex::read(&mut &bytes[..], bytes.len() as u64)?;
    let part = |r: &std::ops::Range<u64>| &bytes[r.start as usize..r.end as usize];
    let mut budget = usize::try_from(max_raw).unwrap_or(usize::MAX);
    let mut spend = |p: &[u8]| -> Result<usize, FormatError> {
        let n = pack::raw_len(p)?;
        budget = budget.checked_sub(n).ok_or_else(|| {
            FormatError::invalid(format!(
                "banded result inflates to more than the {max_raw} bytes allowed"
            ))
        })?;
        Ok(n)
    };
    let own = part(&index.own);
    index.check_own(own)?;
    let n = spend(own)?;
    let film = pack::unpack(own, n, |raw| {
        TaskFilm::check(raw, grid.width, grid.height, layout)
    })?;
    if film.tile != index.tile || film.samples != index.samples || film.stats != index.stats {
        return Err(FormatError::invalid(format!(
            "own part of tile {:?} samples {:?} under a header of tile {:?} samples {:?}",
            film.tile, film.samples, index.tile, index.samples
        )));
    }
    if film.splats > 0 || film.records > 0 {
        return Err(FormatError::invalid(
            "own part with splats or records (they belong in the sections)",
        ));
    }
    for (k, (b, r)) in index.sections.iter().enumerate() {
        if *b >= grid.rows() {
            return Err(FormatError::invalid(format!(
                "section of band {b}; the frame has {}",
                grid.rows()
            )));
        }
        let s = part(r);
        index.check_section(k, s)?;
        let n = spend(s)?;
        pack::unpack(s, n, |raw| check_section(raw, *b as usize, grid, layout))?;
    }
    Ok(index)
}

/// A banded result with its tile and sample range changed to `tile` and `samples` (in the
/// header and the own part, which is packed again; the sections are kept as they are): what a
/// load generator replays as another task's result. `bytes` must be a banded result
/// (`encode_banded`).
pub fn relabel_banded(
    bytes: &[u8],
    tile: Tile,
    samples: std::ops::Range<u32>,
) -> Result<Vec<u8>, FormatError> {
    let index = BandedIndex::read(&mut &bytes[..], bytes.len() as u64)?;
    let part = |r: &std::ops::Range<u64>| &bytes[r.start as usize..r.end as usize];
    let mut own = pack::unpack_vec(part(&index.own), usize::MAX)?;
    let cuts = pack::piece_cuts(part(&index.own))?;
    let fields = [
        tile.x0,
        tile.y0,
        tile.x1,
        tile.y1,
        samples.start,
        samples.end,
    ];
    // The own part holds the tile and the samples at bytes 12 .. 36 (after magic and version).
    if own.len() < 36 {
        return Err(FormatError::invalid(format!(
            "own part of {} bytes",
            own.len()
        )));
    }
    for (k, v) in fields.iter().enumerate() {
        own[12 + 4 * k..16 + 4 * k].copy_from_slice(&v.to_le_bytes());
    }
    let sections: Vec<(u32, &[u8])> = index.sections.iter().map(|(b, r)| (*b, part(r))).collect();
    Ok(assemble(
        tile,
        samples,
        &index.stats,
        &pack::pack_pieces(&own, &cuts),
        &sections,
    ))
}

/// Checks the section of `band` of a banded result (its raw bytes, unpacked) as
/// `decode_section` would parse it, without keeping anything (its values are skipped).
pub fn check_section(
    bytes: &[u8],
    band: usize,
    grid: &TileGrid,
    layout: &FilmLayout,
) -> Result<(), FormatError> {
    section(bytes, band, grid, layout, None)
}

/// Parses the section of `band` (its raw bytes, unpacked) of a banded result for `grid`,
/// whose films have `layout`: everything must land in the band.
pub fn decode_section(
    bytes: &[u8],
    band: usize,
    grid: &TileGrid,
    layout: &FilmLayout,
) -> Result<Routed, FormatError> {
    let mut routed = Routed::default();
    section(bytes, band, grid, layout, Some(&mut routed))?;
    Ok(routed)
}

/// The own part of a banded result as stored (packed, at most `max_raw` bytes inflated),
/// decoded for a frame of `width` x `height` pixels whose films have `layout`.
pub fn unpack_own(
    part: &[u8],
    max_raw: usize,
    width: u32,
    height: u32,
    layout: &FilmLayout,
) -> Result<(TaskFilm, std::ops::Range<u32>), FormatError> {
    pack::unpack(part, max_raw, |raw| {
        TaskFilm::decode(raw, width, height, layout)
    })
}

/// The section of `band` of a banded result as stored (packed, at most `max_raw` bytes
/// inflated), decoded (`decode_section`).
pub fn unpack_section(
    part: &[u8],
    max_raw: usize,
    band: usize,
    grid: &TileGrid,
    layout: &FilmLayout,
) -> Result<Routed, FormatError> {
    pack::unpack(part, max_raw, |raw| decode_section(raw, band, grid, layout))
}

/// Reads a section into `out`, or only checks it when `out` is None.
fn section(
    bytes: &[u8],
    band: usize,
    grid: &TileGrid,
    layout: &FilmLayout,
    mut out: Option<&mut Routed>,
) -> Result<(), FormatError> {
    let mut r = Reader::new(bytes);
    let pixels = grid.band_pixels(band);
    let keys = SplatKeys::of_layout(layout);
    r.splat_list(
        pixels.clone(),
        keys,
        out.as_deref_mut().map(|o| &mut o.splats),
    )?;
    r.record_list(pixels, layout.d_opt(), out.map(|o| &mut o.records))?;
    if r.at != bytes.len() {
        return Err(FormatError::invalid(format!(
            "section of band {band}: {} trailing bytes",
            bytes.len() - r.at
        )));
    }
    Ok(())
}
