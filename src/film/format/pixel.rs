//! The pixel record, the one fixed-size record every pixel of a task result and of a tile
//! checkpoint holds:
//!
//! ```text
//! count u32, sum 3 x f64, sum_sq 3 x f64, [splat 3 x f64: a checkpoint's, where the film keeps
//! light-tracing splat sums (`FilmLayout::splats`)]
//! ```
//!
//! A task result lays its records out in byte planes, a checkpoint one after another (`Writer::rows`).

use crate::film::PixelSums;

/// Bytes of a record without splat sums (a task result's, the path tracer's checkpoints).
pub(super) const LEN: usize = 4 + 6 * 8;
/// Bytes of a record with splat sums.
pub(super) const LEN_WITH_SPLAT: usize = LEN + 3 * 8;

/// Bytes of a record, with or without splat sums.
pub(super) fn len(splat: bool) -> usize {
    if splat { LEN_WITH_SPLAT } else { LEN }
}

/// The record of pixel `i` of `sums`, with `splat` where it is kept: the first
/// `len(splat.is_some())` bytes of the array.
pub(super) fn encode(sums: &PixelSums, i: usize, splat: Option<&[f64; 3]>) -> [u8; LEN_WITH_SPLAT] {
    let mut rec = [0u8; LEN_WITH_SPLAT];
    rec[..4].copy_from_slice(&sums.count[i].to_le_bytes());
    let values = sums.sum[i]
        .iter()
        .chain(&sums.sum_sq[i])
        .chain(splat.into_iter().flatten());
    for (at, v) in rec[4..].chunks_exact_mut(8).zip(values) {
        at.copy_from_slice(&v.to_le_bytes());
    }
    rec
}

/// Sets pixel `i` of `sums` (and `splat`, where it is kept) from `rec`, a record of
/// `len(splat.is_some())` bytes.
pub(super) fn decode(rec: &[u8], sums: &mut PixelSums, i: usize, splat: Option<&mut [f64; 3]>) {
    let f = |k: usize| f64::from_le_bytes(rec[4 + 8 * k..12 + 8 * k].try_into().expect("8 bytes"));
    sums.count[i] = u32::from_le_bytes(rec[..4].try_into().expect("4 bytes"));
    for c in 0..3 {
        sums.sum[i][c] = f(c);
        sums.sum_sq[i][c] = f(3 + c);
    }
    if let Some(s) = splat {
        for (c, v) in s.iter_mut().enumerate() {
            *v = f(6 + c);
        }
    }
}
