//! The codec every byte format of the film shares: a little-endian writer and a bounds-checked
//! reader that names what was truncated and where, the LEB128 and zigzag steps of delta-coded
//! lists, byte planes, and CRC-32 (IEEE) checksums.

use super::error::FormatError;
use super::pack;
use crate::film::{RayStats, Tile};

/// A little-endian writer into a byte vector.
pub(super) struct Writer {
    pub(super) out: Vec<u8>,
    /// Where the planes of lists end (`pack::pack_pieces` cuts there).
    pub(super) cuts: Vec<usize>,
    /// Whether lists of fixed-size records go in byte planes (`rows`): tile results, not
    /// checkpoints (rewritten in place, never packed).
    pub(super) planes: bool,
}

impl Writer {
    pub(super) fn new(out: Vec<u8>) -> Self {
        Writer {
            out,
            cuts: Vec::new(),
            planes: false,
        }
    }
    /// Fixed-size records of `S` bytes: in byte planes, each ending at a cut, where the writer
    /// lays them so; else one after another.
    pub(super) fn rows<const S: usize>(&mut self, rows: impl Iterator<Item = [u8; S]>) {
        if !self.planes {
            return self.out.extend(rows.flatten());
        }
        let rows: Vec<u8> = rows.flatten().collect();
        self.cut();
        let start = self.out.len();
        pack::to_planes(&rows, S, &mut self.out);
        let n = rows.len() / S;
        self.cuts.extend((1..=S).map(|j| start + j * n));
    }
    /// Marks the end of a plane.
    pub(super) fn cut(&mut self) {
        self.cuts.push(self.out.len());
    }
    pub(super) fn bytes(&mut self, b: &[u8]) {
        self.out.extend_from_slice(b);
    }
    pub(super) fn u8(&mut self, v: u8) {
        self.bytes(&[v]);
    }
    pub(super) fn u32(&mut self, v: u32) {
        self.bytes(&v.to_le_bytes());
    }
    pub(super) fn u64(&mut self, v: u64) {
        self.bytes(&v.to_le_bytes());
    }
    pub(super) fn f32(&mut self, v: f32) {
        self.bytes(&v.to_le_bytes());
    }
    pub(super) fn f64(&mut self, v: f64) {
        self.bytes(&v.to_le_bytes());
    }
    /// A signed difference, zigzag-mapped, as unsigned LEB128 (1 to 5 bytes for 32-bit steps).
    pub(super) fn step(&mut self, from: u32, to: u32) {
        let d = to as i64 - from as i64;
        self.leb128(((d << 1) ^ (d >> 63)) as u64);
    }
    /// Unsigned LEB128: seven bits a byte, low bits first.
    pub(super) fn leb128(&mut self, mut z: u64) {
        loop {
            let byte = (z & 0x7f) as u8;
            z >>= 7;
            if z == 0 {
                self.u8(byte);
                return;
            }
            self.u8(byte | 0x80);
        }
    }
    pub(super) fn stats(&mut self, s: &RayStats) {
        for v in [s.closest, s.shadow, s.samples, s.non_finite] {
            self.u64(v);
        }
    }
}

/// A little-endian reader over a byte slice that names what was truncated.
pub(super) struct Reader<'a> {
    pub(super) b: &'a [u8],
    pub(super) at: usize,
}

impl<'a> Reader<'a> {
    /// A reader at the start of `b`.
    pub(super) fn new(b: &'a [u8]) -> Self {
        Reader { b, at: 0 }
    }
    pub(super) fn take(&mut self, n: usize) -> Result<&[u8], FormatError> {
        if self.b.len() - self.at < n {
            return Err(FormatError::Truncated {
                at: self.at,
                wanted: n,
            });
        }
        let s = &self.b[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }
    pub(super) fn u8(&mut self) -> Result<u8, FormatError> {
        Ok(self.take(1)?[0])
    }
    pub(super) fn u32(&mut self) -> Result<u32, FormatError> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }
    pub(super) fn u64(&mut self) -> Result<u64, FormatError> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
    pub(super) fn f64(&mut self) -> Result<f64, FormatError> {
        Ok(f64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
    /// Unsigned LEB128 of at most 5 bytes (a 32-bit step and one flag bit); `what` names it in
    /// the error.
    pub(super) fn leb128(&mut self, what: &str) -> Result<u64, FormatError> {
        let mut z = 0u64;
        for k in 0..5 {
            // Indexed directly: the hot loop of checking and decoding splats and records.
            let Some(&byte) = self.b.get(self.at) else {
                return Err(FormatError::invalid(format!(
                    "truncated at byte {}",
                    self.at
                )));
            };
            self.at += 1;
            z |= ((byte & 0x7f) as u64) << (7 * k);
            if byte & 0x80 == 0 {
                return Ok(z);
            }
        }
        Err(FormatError::invalid(format!("{what} longer than 5 bytes")))
    }
    /// The pixel `step` (see the format) after pixel `from`: a pixel index of the u32 range.
    pub(super) fn step(&mut self, from: u32) -> Result<u32, FormatError> {
        let z = self.leb128("pixel step")?;
        let d = (z >> 1) as i64 ^ -((z & 1) as i64);
        u32::try_from(from as i64 + d).map_err(|_| {
            FormatError::invalid(format!("pixel step {d} from {from} leaves the u32 range"))
        })
    }
    /// A format's magic and one of its `versions` (which it returns), or an error naming `what`
    /// was expected.
    pub(super) fn header_of(
        &mut self,
        magic: &[u8; 8],
        versions: &'static [u32],
        what: &'static str,
    ) -> Result<u32, FormatError> {
        if self.take(8)? != magic {
            return Err(FormatError::Magic { format: what });
        }
        let got = self.u32()?;
        if !versions.contains(&got) {
            return Err(FormatError::Version {
                format: what,
                got,
                expected: versions,
            });
        }
        Ok(got)
    }
    /// `n` records of `stride` bytes, row-major: gathered from byte planes when `planes`
    /// (`Writer::rows`), else as they lie.
    pub(super) fn rows(
        &mut self,
        n: usize,
        stride: usize,
        planes: bool,
    ) -> Result<std::borrow::Cow<'a, [u8]>, FormatError> {
        let b: &'a [u8] = self.b;
        let len = n.saturating_mul(stride);
        if b.len() - self.at < len {
            return Err(FormatError::Truncated {
                at: self.at,
                wanted: len,
            });
        }
        let bytes = &b[self.at..self.at + len];
        self.at += len;
        if !planes {
            return Ok(bytes.into());
        }
        let mut rows = Vec::with_capacity(len);
        pack::from_planes(bytes, stride, &mut rows);
        Ok(rows.into())
    }
    /// A tile rectangle (x0 y0 x1 y1).
    pub(super) fn tile(&mut self) -> Result<Tile, FormatError> {
        Ok(Tile {
            x0: self.u32()?,
            y0: self.u32()?,
            x1: self.u32()?,
            y1: self.u32()?,
        })
    }
    pub(super) fn stats(&mut self) -> Result<RayStats, FormatError> {
        Ok(RayStats {
            closest: self.u64()?,
            shadow: self.u64()?,
            samples: self.u64()?,
            non_finite: self.u64()?,
        })
    }
    /// Nothing is left to read.
    pub(super) fn end(&self) -> Result<(), FormatError> {
        match self.b.len() - self.at {
            0 => Ok(()),
            n => Err(FormatError::invalid(format!("{n} trailing bytes"))),
        }
    }
    /// The u32 at the reading position, not consumed.
    pub(super) fn peek_count(&self) -> Result<usize, FormatError> {
        let b = self
            .b
            .get(self.at..self.at + 4)
            .ok_or_else(|| FormatError::invalid(format!("truncated at byte {}", self.at)))?;
        Ok(u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize)
    }
    /// A count that must fit in the remaining bytes at `unit` bytes per item.
    pub(super) fn count(&mut self, unit: usize, what: &str) -> Result<usize, FormatError> {
        let n = self.u32()? as usize;
        if n.saturating_mul(unit) > self.b.len() - self.at {
            return Err(FormatError::invalid(format!(
                "{what}: count {n} exceeds the payload"
            )));
        }
        Ok(n)
    }
}
