//! The parts of a banded task result (`wire::encode_banded`) travel and rest compressed.
//!
//! A part is `method u8 (0 stored, 1 zstd), raw length u64, payload`: the payload is the raw
//! bytes (method 0, where compression would not make them shorter) or one zstd frame of them
//! (method 1, level 1: Collet and Kucherawy, "Zstandard Compression and the 'application/zstd'
//! Media Type", RFC 8878). The raw length comes first so that a reader bounds what it allocates
//! before it inflates anything, and refuses a part that inflates to anything else. Compression
//! is lossless, so the merged image does not change by a bit.
//!
//! Measured on a 1080p Cornell box (BENCHMARKS.md #12, stop 31): the camera-side f64 sums
//! shrink the most (sums of a few f32 values leave the low mantissa bits zero), the
//! light-tracing splats and records least (their bfloat16 mantissas are noise).

use super::wire::WireError;
use std::cell::RefCell;

/// zstd's level: on a pass's result log (`zstd -b1 -e3`, 2-core machine) level 1 compresses
/// to 64 % at ~460 MB/s and inflates at ~1.1 GB/s; level 3 to 58 % at ~200 MB/s.
const LEVEL: i32 = 1;
const STORED: u8 = 0;
const ZSTD: u8 = 1;
/// Bytes before the payload.
pub const HEAD: usize = 9;
/// A scratch buffer larger than this is freed after use rather than kept by its thread.
const KEPT_SCRATCH: usize = 16 << 20;

thread_local! {
    static COMPRESSOR: RefCell<Option<zstd::bulk::Compressor<'static>>> = const { RefCell::new(None) };
    static DECOMPRESSOR: RefCell<Option<zstd::bulk::Decompressor<'static>>> = const { RefCell::new(None) };
    static SCRATCH: RefCell<Vec<u8>> = const { RefCell::new(Vec::new()) };
}

/// `raw` as a part: zstd-compressed where that makes it shorter, else stored.
pub fn pack(raw: &[u8]) -> Vec<u8> {
    let mut frame = Vec::with_capacity(zstd::compress_bound(raw.len()));
    let compressed = COMPRESSOR.with_borrow_mut(|c| {
        if c.is_none() {
            *c = zstd::bulk::Compressor::new(LEVEL).ok();
        }
        c.as_mut()
            .is_some_and(|c| c.compress_to_buffer(raw, &mut frame).is_ok())
    }) && frame.len() < raw.len();
    let (method, payload) = if compressed {
        (ZSTD, &frame[..])
    } else {
        (STORED, raw)
    };
    let mut out = Vec::with_capacity(HEAD + payload.len());
    out.push(method);
    out.extend_from_slice(&(raw.len() as u64).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// The raw length a part says it holds (checked when it is unpacked).
pub fn raw_len(part: &[u8]) -> Result<usize, WireError> {
    let head: [u8; HEAD] = part
        .get(..HEAD)
        .and_then(|h| h.try_into().ok())
        .ok_or_else(|| WireError(format!("packed part of {} bytes", part.len())))?;
    let mut n = [0u8; 8];
    n.copy_from_slice(&head[1..]);
    usize::try_from(u64::from_le_bytes(n))
        .map_err(|_| WireError("packed part longer than this machine's memory".into()))
}

/// Calls `f` with the raw bytes of `part`, which may say it holds at most `max_raw` bytes.
/// Inflates into this thread's scratch buffer (kept between calls, so a coordinator's checks do
/// not fault in fresh pages per part); `f` must not unpack another part.
pub fn unpack<R>(
    part: &[u8],
    max_raw: usize,
    f: impl FnOnce(&[u8]) -> Result<R, WireError>,
) -> Result<R, WireError> {
    let n = raw_len(part)?;
    if n > max_raw {
        return Err(WireError(format!(
            "packed part of {n} bytes, more than the {max_raw} allowed"
        )));
    }
    let payload = &part[HEAD..];
    match part[0] {
        STORED if payload.len() == n => f(payload),
        STORED => Err(WireError(format!(
            "stored part of {} bytes says it holds {n}",
            payload.len()
        ))),
        ZSTD => {
            let mut raw = SCRATCH.with_borrow_mut(std::mem::take);
            raw.clear();
            raw.reserve(n);
            let got = DECOMPRESSOR.with_borrow_mut(|d| {
                if d.is_none() {
                    *d = zstd::bulk::Decompressor::new().ok();
                }
                match d.as_mut() {
                    Some(d) => d
                        .decompress_to_buffer(payload, &mut raw)
                        .map_err(|e| e.to_string()),
                    None => Err("no zstd context".into()),
                }
            });
            let out = match got {
                Ok(k) if k == n && raw.len() == n => f(&raw),
                Ok(k) => Err(WireError(format!(
                    "packed part inflates to {k} bytes, says {n}"
                ))),
                Err(e) => Err(WireError(format!("packed part does not inflate: {e}"))),
            };
            if raw.capacity() <= KEPT_SCRATCH {
                SCRATCH.with_borrow_mut(|s| *s = raw);
            }
            out
        }
        m => Err(WireError(format!("packed part of method {m}"))),
    }
}

/// The raw bytes of `part` as a vector (tests, tools).
pub fn unpack_vec(part: &[u8], max_raw: usize) -> Result<Vec<u8>, WireError> {
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
}
