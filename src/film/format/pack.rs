//! The parts of a banded task result (`format::encode_banded`) travel and rest compressed.
//!
//! A part is `method u8, raw length u64, payload`. Method 0: the payload is the raw bytes (where
//! compression would not make them shorter); 1: one zstd frame of them (level 1: Collet and
//! Kucherawy, "Zstandard Compression and the 'application/zstd' Media Type", RFC 8878); 2: the
//! raw bytes in pieces, `pieces u32`, then per piece `method u8 (0 or 1), raw length u32,
//! payload length u32, payload`, each piece stored or compressed on its own. The raw length
//! comes first so that a reader bounds what it allocates before it inflates anything, and
//! refuses a part that inflates to anything else. Compression is lossless, so the merged image
//! does not change by a bit.
//!
//! Measured on a 1080p Cornell box (BENCHMARKS.md, "The render service"): the camera-side
//! f64 sums shrink the most (sums of a few f32 values leave the low mantissa bits zero). A
//! section of light-tracing splats and records is cut into pieces along its planes (`lists`):
//! pixel steps, the high bytes of the bfloat16 values (sign and exponent: 0.11-0.31 of their
//! size), their low bytes (mantissa noise: stored, never inflated) and the f32 values: an
//! optimal-MIS job ships 14.6 bytes per pixel sample in pieces against 17.1 as one frame per
//! section (`omis bench-coordinator`, BENCHMARKS.md, "The render service"). A result's own part is cut
//! into the byte planes of its fixed-size records (`to_planes`): path-tracing results shrink
//! from 0.41 to 0.34 of their raw size and are checked 3.1 times as fast (`cargo bench --bench
//! check_uploads`).

use super::error::FormatError;
use std::cell::RefCell;

/// zstd's level: on a pass's result log (`zstd -b1 -e3`, 2-core machine) level 1 compresses
/// to 64 % at ~460 MB/s and inflates at ~1.1 GB/s; level 3 to 58 % at ~200 MB/s.
const LEVEL: i32 = 1;
const STORED: u8 = 0;
const ZSTD: u8 = 1;
const PIECES: u8 = 2;
/// Bytes before a piece's payload.
const PIECE_HEAD: usize = 9;
/// A part shorter than this is packed whole: its pieces' heads would cost more than they save.
const MIN_PIECES: usize = 4096;
/// Bytes before the payload.
pub const HEAD: usize = 9;
/// A scratch buffer larger than this is freed after use rather than kept by its thread.
const KEPT_SCRATCH: usize = 16 << 20;

thread_local! {
    static COMPRESSOR: RefCell<Option<zstd::bulk::Compressor<'static>>> = const { RefCell::new(None) };
    static DECOMPRESSOR: RefCell<Option<zstd::bulk::Decompressor<'static>>> = const { RefCell::new(None) };
    static SCRATCH: RefCell<Vec<u8>> = const { RefCell::new(Vec::new()) };
}

/// `raw` zstd-compressed (method ZSTD) where that makes it shorter, else as it is (STORED).
fn compress(raw: &[u8]) -> (u8, std::borrow::Cow<'_, [u8]>) {
    let mut frame = Vec::with_capacity(zstd::compress_bound(raw.len()));
    let compressed = COMPRESSOR.with_borrow_mut(|c| {
        if c.is_none() {
            *c = zstd::bulk::Compressor::new(LEVEL).ok();
        }
        c.as_mut()
            .is_some_and(|c| c.compress_to_buffer(raw, &mut frame).is_ok())
    }) && frame.len() < raw.len();
    if compressed {
        (ZSTD, frame.into())
    } else {
        (STORED, raw.into())
    }
}

/// `raw` as a part: zstd-compressed where that makes it shorter, else stored.
pub fn pack(raw: &[u8]) -> Vec<u8> {
    let (method, payload) = compress(raw);
    let mut out = Vec::with_capacity(HEAD + payload.len());
    out.push(method);
    out.extend_from_slice(&(raw.len() as u64).to_le_bytes());
    out.extend_from_slice(&payload);
    out
}

/// `raw` as a part in pieces cut at `cuts` (increasing offsets into `raw`), each compressed on
/// its own where that makes it shorter, else stored; a short `raw` is packed whole (`pack`).
pub fn pack_pieces(raw: &[u8], cuts: &[usize]) -> Vec<u8> {
    if raw.len() < MIN_PIECES || raw.len() > u32::MAX as usize {
        return pack(raw);
    }
    let mut bounds: Vec<usize> = std::iter::once(0)
        .chain(cuts.iter().copied().filter(|&c| c > 0 && c < raw.len()))
        .chain(std::iter::once(raw.len()))
        .collect();
    bounds.dedup();
    let pieces: Vec<(u8, std::borrow::Cow<[u8]>, usize)> = bounds
        .windows(2)
        .map(|w| {
            let (method, payload) = compress(&raw[w[0]..w[1]]);
            (method, payload, w[1] - w[0])
        })
        .collect();
    let len: usize = pieces.iter().map(|p| PIECE_HEAD + p.1.len()).sum();
    let mut out = Vec::with_capacity(HEAD + 4 + len);
    out.push(PIECES);
    out.extend_from_slice(&(raw.len() as u64).to_le_bytes());
    out.extend_from_slice(&(pieces.len() as u32).to_le_bytes());
    for (method, payload, raw_len) in &pieces {
        out.push(*method);
        out.extend_from_slice(&(*raw_len as u32).to_le_bytes());
        out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        out.extend_from_slice(payload);
    }
    out
}

/// Rows of records at a time when laying bytes out in planes: a block of rows stays in the
/// first-level cache while each of its planes is written.
const PLANE_BLOCK: usize = 64;

/// Appends the records of `rows` (row-major, `stride` bytes each) to `out` in byte planes:
/// byte 0 of every record, then byte 1, and so on. The bytes of a float that vary alike (sign
/// and exponent, the high mantissa, the low mantissa that a sum of few f32 values leaves zero)
/// then lie together, and each plane is compressed or stored on its own (`pack_pieces`).
pub fn to_planes(rows: &[u8], stride: usize, out: &mut Vec<u8>) {
    transpose(rows, stride, out, true);
}

/// Appends the records held in byte planes by `planes` (`to_planes` of `stride`-byte records)
/// to `out`, row-major again.
pub fn from_planes(planes: &[u8], stride: usize, out: &mut Vec<u8>) {
    transpose(planes, stride, out, false);
}

/// Appends `src`, records of `stride` bytes, to `out` with byte j of record i moved from
/// i * stride + j to j * records + i (`into_planes`) or back, a block of records at a time.
fn transpose(src: &[u8], stride: usize, out: &mut Vec<u8>, into_planes: bool) {
    assert!(
        stride > 0 && src.len().is_multiple_of(stride),
        "whole records"
    );
    let n = src.len() / stride;
    let start = out.len();
    out.resize(start + src.len(), 0);
    let dst = &mut out[start..];
    for first in (0..n).step_by(PLANE_BLOCK) {
        let rows = first..(first + PLANE_BLOCK).min(n);
        for j in 0..stride {
            for i in rows.clone() {
                let (row, plane) = (i * stride + j, j * n + i);
                if into_planes {
                    dst[plane] = src[row];
                } else {
                    dst[row] = src[plane];
                }
            }
        }
    }
}

/// The offsets into its raw bytes where the pieces of `part` end but the last (none for a part
/// packed whole): the cuts that `pack_pieces` would make again.
pub fn piece_cuts(part: &[u8]) -> Result<Vec<usize>, FormatError> {
    if part.first() != Some(&PIECES) {
        return Ok(Vec::new());
    }
    let payload = part
        .get(HEAD..)
        .ok_or_else(|| piece_error("no piece count".into()))?;
    let mut ends = Vec::new();
    for_pieces(payload, |_, _, len, _| {
        ends.push(ends.last().copied().unwrap_or(0) + len);
        Ok(())
    })?;
    ends.pop();
    Ok(ends)
}

/// The raw length a part says it holds (checked when it is unpacked).
pub fn raw_len(part: &[u8]) -> Result<usize, FormatError> {
    let head: [u8; HEAD] = part
        .get(..HEAD)
        .and_then(|h| h.try_into().ok())
        .ok_or_else(|| FormatError::invalid(format!("packed part of {} bytes", part.len())))?;
    let mut n = [0u8; 8];
    n.copy_from_slice(&head[1..]);
    usize::try_from(u64::from_le_bytes(n))
        .map_err(|_| FormatError::invalid("packed part longer than this machine's memory"))
}

/// Calls `f` with the raw bytes of `part`, which may say it holds at most `max_raw` bytes.
/// Inflates into this thread's scratch buffer (kept between calls, so a coordinator's checks do
/// not fault in fresh pages per part); `f` must not unpack another part.
pub fn unpack<R>(
    part: &[u8],
    max_raw: usize,
    f: impl FnOnce(&[u8]) -> Result<R, FormatError>,
) -> Result<R, FormatError> {
    let n = raw_len(part)?;
    if n > max_raw {
        return Err(FormatError::invalid(format!(
            "packed part of {n} bytes, more than the {max_raw} allowed"
        )));
    }
    let payload = &part[HEAD..];
    match part[0] {
        STORED if payload.len() == n => f(payload),
        STORED => Err(FormatError::invalid(format!(
            "stored part of {} bytes says it holds {n}",
            payload.len()
        ))),
        ZSTD | PIECES => {
            let mut raw = SCRATCH.with_borrow_mut(std::mem::take);
            raw.clear();
            raw.reserve(n);
            let filled = if part[0] == ZSTD {
                inflate(payload, n, &mut raw)
            } else {
                unpieces(payload, n, &mut raw)
            };
            let out = match filled {
                Ok(()) if raw.len() == n => f(&raw),
                Ok(()) => Err(FormatError::invalid(format!(
                    "packed part inflates to {} bytes, says {n}",
                    raw.len()
                ))),
                Err(e) => Err(e),
            };
            if raw.capacity() <= KEPT_SCRATCH {
                SCRATCH.with_borrow_mut(|s| *s = raw);
            }
            out
        }
        m => Err(FormatError::invalid(format!("packed part of method {m}"))),
    }
}

/// Appends the zstd frame `frame`, which must hold exactly `n` bytes, to `raw` (whose spare
/// capacity is at least `n`).
fn inflate(frame: &[u8], n: usize, raw: &mut Vec<u8>) -> Result<(), FormatError> {
    let start = raw.len();
    if raw.capacity() - start < n {
        return Err(FormatError::invalid(format!(
            "packed piece of {n} bytes overflows its part"
        )));
    }
    let got = DECOMPRESSOR.with_borrow_mut(|d| {
        if d.is_none() {
            *d = zstd::bulk::Decompressor::new().ok();
        }
        let mut at = std::io::Cursor::new(&mut *raw);
        at.set_position(start as u64);
        match d.as_mut() {
            Some(d) => d
                .decompress_to_buffer(frame, &mut at)
                .map_err(|e| e.to_string()),
            None => Err("no zstd context".into()),
        }
    });
    match got {
        Ok(k) if k == n && raw.len() == start + n => Ok(()),
        Ok(k) => Err(FormatError::invalid(format!(
            "packed part inflates to {k} bytes, says {n}"
        ))),
        Err(e) => Err(FormatError::invalid(format!(
            "packed part does not inflate: {e}"
        ))),
    }
}

/// Appends the pieces of `payload` (a PIECES part that says it holds `n` bytes) to `raw`,
/// checking every piece's head against the part and against what it inflates to.
fn unpieces(payload: &[u8], n: usize, raw: &mut Vec<u8>) -> Result<(), FormatError> {
    for_pieces(payload, |k, method, len, body| {
        if len > n - raw.len() {
            return Err(piece_error(format!(
                "piece {k} of {len} bytes overflows the part's {n}"
            )));
        }
        match method {
            STORED if body.len() == len => raw.extend_from_slice(body),
            ZSTD => inflate(body, len, raw)?,
            m => {
                return Err(piece_error(format!(
                    "piece {k} of method {m} ({} bytes for {len})",
                    body.len()
                )));
            }
        }
        Ok(())
    })
}

/// Calls `f(k, method, raw length, payload)` for each piece of `payload` (a PIECES part's),
/// in order, checking that the heads and payloads lie within it and fill it.
fn for_pieces<'a>(
    payload: &'a [u8],
    mut f: impl FnMut(usize, u8, usize, &'a [u8]) -> Result<(), FormatError>,
) -> Result<(), FormatError> {
    let Some(count) = payload.get(..4) else {
        return Err(piece_error("no piece count".into()));
    };
    let count = u32::from_le_bytes(count.try_into().expect("4 bytes")) as usize;
    let mut at = 4;
    for k in 0..count {
        let Some(head) = payload.get(at..at + PIECE_HEAD) else {
            return Err(piece_error(format!("piece {k} of {count} truncated")));
        };
        let word = |i: usize| u32::from_le_bytes(head[i..i + 4].try_into().expect("4")) as usize;
        let (method, len, stored) = (head[0], word(1), word(5));
        at += PIECE_HEAD;
        let Some(body) = payload.get(at..at.saturating_add(stored)) else {
            return Err(piece_error(format!(
                "piece {k} of {stored} bytes truncated"
            )));
        };
        at += stored;
        f(k, method, len, body)?;
    }
    if at != payload.len() {
        return Err(piece_error(format!(
            "{} bytes after its {count} pieces",
            payload.len() - at
        )));
    }
    Ok(())
}

fn piece_error(what: String) -> FormatError {
    FormatError::invalid(format!("packed part in pieces: {what}"))
}

/// The raw bytes of `part` as a vector (tests, tools).
pub fn unpack_vec(part: &[u8], max_raw: usize) -> Result<Vec<u8>, FormatError> {
    unpack(part, max_raw, |raw| Ok(raw.to_vec()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_round_trip_and_refuse_what_they_do_not_hold() {
        let zeros = vec![0u8; 100_000];
        let noise: Vec<u8> = (0..1000u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
            .collect();
        for raw in [&zeros[..], &noise[..], &[][..], &[7u8][..]] {
            let part = pack(raw);
            assert!(part.len() <= raw.len() + HEAD, "never longer than stored");
            assert_eq!(unpack_vec(&part, raw.len()).expect("unpacks"), raw);
            // More than allowed, or a damaged head or payload: refused, not inflated.
            if !raw.is_empty() {
                assert!(unpack_vec(&part, raw.len() - 1).is_err());
            }
            let mut longer = part.clone();
            longer[1] = longer[1].wrapping_add(1);
            assert!(unpack_vec(&longer, usize::MAX).is_err());
            assert!(unpack_vec(&part[..part.len() - 1], usize::MAX).is_err() || raw.is_empty());
        }
        assert_eq!(pack(&zeros)[0], ZSTD);
        assert!(pack(&zeros).len() < 1000);
        assert!(unpack_vec(&[9, 0, 0, 0, 0, 0, 0, 0, 0], 10).is_err());
        assert!(unpack_vec(&[1, 0], 10).is_err());
    }

    #[test]
    fn parts_in_pieces_round_trip_and_refuse_damage() {
        // A plane that compresses, one of noise, one that compresses again.
        let mut raw: Vec<u8> = (0..6000u32).map(|i| (i / 300) as u8).collect();
        let mut x = 1u64;
        let noise: Vec<u8> = (0..5000)
            .map(|_| {
                x = x
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                (x >> 56) as u8
            })
            .collect();
        raw.extend_from_slice(&noise);
        raw.extend(std::iter::repeat_n(3u8, 4000));
        let cuts = [6000, 6000, 11000, 0, 15000, 99999];
        let part = pack_pieces(&raw, &cuts);
        assert_eq!(part[0], PIECES);
        assert!(part.len() > noise.len(), "the noise is stored");
        assert_eq!(unpack_vec(&part, raw.len()).expect("unpacks"), raw);
        assert!(unpack_vec(&part, raw.len() - 1).is_err());
        // Short: whole.
        assert_eq!(pack_pieces(&raw[..100], &[50])[0], ZSTD);
        // Every byte of the part damaged in turn: an error or, where a stored piece's byte
        // changed, the same length; never a panic, never more than the part says.
        for at in 0..part.len() {
            for flip in [0x01u8, 0x80] {
                let mut bad = part.clone();
                bad[at] ^= flip;
                if let Ok(got) = unpack_vec(&bad, raw.len()) {
                    assert_eq!(got.len(), raw.len(), "byte {at}");
                }
            }
        }
        for cut in 0..part.len() {
            assert!(
                unpack_vec(&part[..cut], usize::MAX).is_err(),
                "cut at {cut}"
            );
        }
    }

    #[test]
    fn byte_planes_round_trip_and_pieces_give_back_their_cuts() {
        for stride in [1, 4, 8, 24, 52] {
            for n in [0, 1, 63, 64, 65, 1000] {
                let rows: Vec<u8> = (0..n * stride).map(|i| (i * 7 + i / 3) as u8).collect();
                let mut planes = vec![9];
                to_planes(&rows, stride, &mut planes);
                assert_eq!(planes.len(), 1 + rows.len());
                for i in 0..n {
                    for j in 0..stride {
                        assert_eq!(planes[1 + j * n + i], rows[i * stride + j], "{stride} {n}");
                    }
                }
                let mut back = vec![5];
                from_planes(&planes[1..], stride, &mut back);
                assert_eq!(back[0], 5);
                assert_eq!(&back[1..], &rows[..], "stride {stride}, {n} records");
            }
        }
        let raw: Vec<u8> = (0..20_000u32).map(|i| (i / 700) as u8).collect();
        let part = pack_pieces(&raw, &[6000, 11000, 15000]);
        let cuts = piece_cuts(&part).expect("cuts");
        assert_eq!(cuts, [6000, 11000, 15000]);
        assert_eq!(pack_pieces(&raw, &cuts), part, "packed again the same");
        assert!(piece_cuts(&pack(&raw)).expect("whole").is_empty());
        for cut in [1, HEAD, HEAD + 4, HEAD + 10] {
            assert!(piece_cuts(&part[..cut]).is_err(), "cut at {cut}");
        }
    }
}
