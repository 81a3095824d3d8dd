//! Binary encoding of a tile task's result (what a worker uploads and a coordinator merges).
//!
//! Little-endian, versioned, self-describing enough to be validated before anything is merged:
//!
//! ```text
//! magic "OMISTILE", version u32
//! tile x0 y0 x1 y1 u32, samples s0 s1 u32
//! stats closest shadow samples non_finite u64
//! per tile pixel: count u32, sum 3 x f64, sum_sq 3 x f64 (a record of 52 bytes; in byte planes)
//! splats: n u32, then in planes: n splat steps; [n x layer u8]; [n x depth u8] (layer and
//! depth only when the job keeps strategy / depth layers); the high bytes of the narrow values,
//! then their low bytes (3 x k each: a value is 3 x bfloat16 when every channel is one, as the
//! integrators round light-tracing values: `bf16`); the wide values, 3 x w f32 (k + w = n, in
//! splat order within each plane)
//! layers: n u32 (0 or pixels x 14), then n x 3 x f64 (records of 24 bytes, in byte planes)
//! depths: n u32 (0 or pixels x depth layers), then n x 3 x f64 (the same)
//! optimal: d_opt u32 (0 = none), then pixels x stride f64 (A, b), pixels x d_opt u32 (hits),
//! each list in byte planes
//! records: n u32, pixels n x pixel step, depths n x u8 (none when d_opt is 1: all are 1),
//! value width u8, m u32, values m x width: width 2 (bfloat16, the m high bytes then the m low
//! bytes) when the integrators' rounding made every value one, without each record's
//! light-tracing weight (the others imply it: `LtRecords::implied_weight`), else width 4, all
//! values as f32
//! pixel step: the difference to the previous pixel of the list (0 before the first), zigzag
//! LEB128 (one or two bytes for the sorted lists `TileFilm::compact` makes)
//! byte planes: a list of n records of s bytes as s planes of n bytes, byte 0 of every record
//! first (`pack::to_planes`); version 6 wrote the records one after another, and is still read
//! splat step: (difference to the previous pixel) x 2 + (1 if the value is f32), LEB128: splat
//! lists are sorted by pixel
//! ```
//! All sums stay f64: the merged frame must equal a single-process render to 1e-6, and solving
//! the optimal systems amplifies rounding. Splats and records lie in planes (v6) so that a
//! banded section is packed plane by plane (`pack::pack_pieces`): the bfloat16 high bytes
//! (sign, exponent) compress well, the low bytes (mantissa noise) not at all.

use super::{
    FilmLayout, FilmTile, LtRecords, PixelSums, RayStats, STRATEGY_LAYERS, Splat, Tile, TileFilm,
};
use super::{bf16, pack};
use crate::mis::{OptimalAccum, Progressive};

const MAGIC: &[u8; 8] = b"OMISTILE";
/// 6: splats and record values in planes; 7: the fixed-size records (pixel sums, layers,
/// optimal systems) in byte planes too.
const VERSION: u32 = 7;
/// The version before, whose results (in a coordinator's logs when it is upgraded) still read.
const VERSION_ROWS: u32 = 6;

/// Which of a splat's keys the wire carries: its strategy layer and its depth only when the
/// film keeps strategy / depth layers (otherwise both are u8::MAX after `TileFilm::compact`,
/// and nothing reads them).
#[derive(Clone, Copy, Debug)]
struct SplatKeys {
    layer: bool,
    depth: bool,
    /// Whether the film may hold splats at all (not the path tracer's: `FilmLayout::splats`).
    kept: bool,
}

impl SplatKeys {
    fn of_layout(l: &FilmLayout) -> SplatKeys {
        SplatKeys {
            layer: l.strategy_layers,
            depth: l.depth_layers > 0,
            kept: l.splats,
        }
    }
    /// Refuses `n` splats for a film that keeps none.
    fn allow(self, n: usize) -> Result<(), WireError> {
        if n > 0 && !self.kept {
            return Err(WireError(format!(
                "{n} light-tracing splats for a film that keeps none (the path tracer)"
            )));
        }
        Ok(())
    }
    /// The keys of a film made with some layout (its layer lists are empty when not kept).
    fn of_film(f: &TileFilm) -> SplatKeys {
        SplatKeys {
            layer: !f.layers.is_empty(),
            depth: !f.depths.is_empty(),
            kept: true,
        }
    }
}

/// A result that failed validation.
#[derive(Debug, thiserror::Error)]
#[error("invalid tile result: {0}")]
pub struct WireError(pub String);

/// Records of a film whose systems stop at depth 1 are all of depth 1: the wire leaves their
/// depths out.
fn depths_implied(d_opt: Option<u32>) -> bool {
    d_opt == Some(1)
}

/// A little-endian writer into a byte vector.
struct Writer {
    out: Vec<u8>,
    /// Where the planes of lists end (`pack::pack_pieces` cuts there).
    cuts: Vec<usize>,
    /// Whether lists of fixed-size records go in byte planes (`rows`): tile results, not
    /// checkpoints (rewritten in place, never packed).
    planes: bool,
}

impl Writer {
    fn new(out: Vec<u8>) -> Self {
        Writer {
            out,
            cuts: Vec::new(),
            planes: false,
        }
    }
    /// Fixed-size records of `S` bytes: in byte planes, each ending at a cut, where the writer
    /// lays them so; else one after another.
    fn rows<const S: usize>(&mut self, rows: impl Iterator<Item = [u8; S]>) {
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
    fn cut(&mut self) {
        self.cuts.push(self.out.len());
    }
    fn bytes(&mut self, b: &[u8]) {
        self.out.extend_from_slice(b);
    }
    fn u8(&mut self, v: u8) {
        self.bytes(&[v]);
    }
    fn u32(&mut self, v: u32) {
        self.bytes(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.bytes(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.bytes(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.bytes(&v.to_le_bytes());
    }
    /// A signed difference, zigzag-mapped, as unsigned LEB128 (1 to 5 bytes for 32-bit steps).
    fn step(&mut self, from: u32, to: u32) {
        let d = to as i64 - from as i64;
        self.leb128(((d << 1) ^ (d >> 63)) as u64);
    }
    /// Unsigned LEB128: seven bits a byte, low bits first.
    fn leb128(&mut self, mut z: u64) {
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
}

impl Writer {
    fn stats(&mut self, s: &RayStats) {
        for v in [s.closest, s.shadow, s.samples, s.non_finite] {
            self.u64(v);
        }
    }
    /// A counted list of RGB f64 triples (strategy or depth layers).
    fn rgb_list(&mut self, list: &[[f64; 3]]) {
        self.u32(list.len() as u32);
        self.rows(list.iter().map(|[r, g, b]| {
            let mut row = [0u8; 24];
            for (at, v) in row.chunks_exact_mut(8).zip([r, g, b]) {
                at.copy_from_slice(&v.to_le_bytes());
            }
            row
        }));
    }
    /// A counted list of splats, sorted by pixel (`TileFilm::compact`; routing keeps the
    /// order), in planes: delta-coded pixels, their layers and depths only where the film keeps
    /// them (`keys`), then the values, bfloat16 (high bytes, then low bytes) where they are
    /// one, and the others as f32.
    fn splats(&mut self, splats: &[Splat], keys: SplatKeys) {
        self.u32(splats.len() as u32);
        let wide: Vec<bool> = splats
            .iter()
            .map(|s| !s.value.iter().all(|v| bf16::exact(*v)))
            .collect();
        let mut prev = 0;
        for (s, &w) in splats.iter().zip(&wide) {
            assert!(s.pixel >= prev, "splats out of pixel order");
            self.leb128(((s.pixel - prev) as u64) << 1 | w as u64);
            prev = s.pixel;
        }
        self.cut();
        if keys.layer {
            self.out.extend(splats.iter().map(|s| s.layer));
        }
        if keys.depth {
            self.out.extend(splats.iter().map(|s| s.depth));
        }
        self.cut();
        let of = |want: bool| {
            splats
                .iter()
                .zip(&wide)
                .filter(move |(_, w)| **w == want)
                .flat_map(|(s, _)| s.value)
        };
        let narrow = || of(false);
        self.out
            .extend(narrow().map(|v| (bf16::bits(v) >> 8) as u8));
        self.cut();
        self.out.extend(narrow().map(|v| bf16::bits(v) as u8));
        self.cut();
        for v in of(true) {
            self.f32(v);
        }
        self.cut();
    }
    /// Optimal-MIS records of a film with systems of depths 1 ..= `d_opt`: count, delta-coded
    /// pixels, depths (implied where `d_opt` is 1), then the values: as bfloat16 without each
    /// record's light-tracing weight where the integrators' rounding made them so, else all as
    /// f32.
    fn records(&mut self, r: &LtRecords, d_opt: Option<u32>) {
        self.u32(r.pixels.len() as u32);
        let mut prev = 0;
        for &p in &r.pixels {
            self.step(prev, p);
            prev = p;
        }
        if !depths_implied(d_opt) {
            self.bytes(&r.depths);
        }
        let short = r.depths.iter().scan(0usize, |at, &d| {
            let n = d as usize + 2;
            let rec = &r.values[*at..*at + n + 3];
            *at += n + 3;
            Some(rec)
        });
        let compact = short.clone().all(|rec| {
            let n = rec.len() - 3;
            rec[n - 1].to_bits() == LtRecords::implied_weight(&rec[..n - 1]).to_bits()
                && rec[..n - 1]
                    .iter()
                    .chain(&rec[n..])
                    .all(|v| bf16::exact(*v))
        });
        self.cut();
        if compact {
            self.u8(2);
            self.u32((r.values.len() - r.len()) as u32);
            let kept = || {
                short.clone().flat_map(|rec| {
                    let n = rec.len() - 3;
                    rec[..n - 1].iter().chain(&rec[n..])
                })
            };
            self.out.extend(kept().map(|v| (bf16::bits(*v) >> 8) as u8));
            self.cut();
            self.out.extend(kept().map(|v| bf16::bits(*v) as u8));
        } else {
            self.u8(4);
            self.u32(r.values.len() as u32);
            for v in &r.values {
                self.f32(*v);
            }
        }
    }
    /// The optimal-MIS systems: d_opt (0 = none), the f64 values, the u32 hit counts.
    fn optimal(&mut self, o: Option<&OptimalAccum>) {
        match o {
            None => self.u32(0),
            Some(o) => {
                self.u32(o.layout.d_opt);
                self.rows(o.data.iter().map(|v| v.to_le_bytes()));
                self.rows(o.hits.iter().map(|v| v.to_le_bytes()));
            }
        }
    }
}

/// A little-endian reader over a byte slice that names what was truncated.
struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&[u8], WireError> {
        if self.b.len() - self.at < n {
            return Err(WireError(format!(
                "truncated at byte {} (wanted {n} more)",
                self.at
            )));
        }
        let s = &self.b[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, WireError> {
        Ok(self.take(1)?[0])
    }
    fn u32(&mut self) -> Result<u32, WireError> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }
    fn u64(&mut self) -> Result<u64, WireError> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
    fn f64(&mut self) -> Result<f64, WireError> {
        Ok(f64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
    /// Unsigned LEB128 of at most 5 bytes (a 32-bit step and one flag bit); `what` names it in
    /// the error.
    fn leb128(&mut self, what: &str) -> Result<u64, WireError> {
        let mut z = 0u64;
        for k in 0..5 {
            // Indexed directly: the hot loop of checking and decoding splats and records.
            let Some(&byte) = self.b.get(self.at) else {
                return Err(WireError(format!("truncated at byte {}", self.at)));
            };
            self.at += 1;
            z |= ((byte & 0x7f) as u64) << (7 * k);
            if byte & 0x80 == 0 {
                return Ok(z);
            }
        }
        Err(WireError(format!("{what} longer than 5 bytes")))
    }
    /// The pixel `step` (see the format) after pixel `from`: a pixel index of the u32 range.
    fn step(&mut self, from: u32) -> Result<u32, WireError> {
        let z = self.leb128("pixel step")?;
        let d = (z >> 1) as i64 ^ -((z & 1) as i64);
        u32::try_from(from as i64 + d)
            .map_err(|_| WireError(format!("pixel step {d} from {from} leaves the u32 range")))
    }
    /// The next pixel of a delta-coded list after `prev` (which becomes it); it must lie in
    /// `pixels` (`what` names the list's items in the error).
    fn pixel(
        &mut self,
        prev: &mut u32,
        pixels: &std::ops::Range<u64>,
        what: &str,
    ) -> Result<u32, WireError> {
        let p = self.step(*prev)?;
        *prev = p;
        if !pixels.contains(&(p as u64)) {
            return Err(WireError(format!(
                "{what} pixel {p} outside pixels {pixels:?}"
            )));
        }
        Ok(p)
    }
    /// Checks `n` list entries of a pixel step and `stride` bytes (skipped) without decoding
    /// them: every pixel in `pixels`, the list within the payload. What the coordinator does
    /// for every record it accepts (`check_splats` for splats), so one-byte steps (most of a
    /// sorted list) take a short path; the others go through `step`.
    fn check_pixels(
        &mut self,
        n: usize,
        stride: usize,
        pixels: &std::ops::Range<u64>,
        what: &str,
    ) -> Result<(), WireError> {
        let (lo, hi) = (pixels.start as i64, pixels.end as i64);
        let mut prev = 0i64;
        for _ in 0..n {
            let p = match self.b.get(self.at) {
                Some(&byte) if byte < 0x80 => {
                    self.at += 1;
                    let z = byte as i64;
                    prev + ((z >> 1) ^ -(z & 1))
                }
                _ => self.step(u32::try_from(prev).unwrap_or(0))? as i64,
            };
            if p < lo || p >= hi {
                return Err(WireError(format!(
                    "{what} pixel {p} outside pixels {pixels:?}"
                )));
            }
            prev = p;
            self.at += stride;
        }
        if self.at > self.b.len() {
            return Err(WireError(format!(
                "{what}s: truncated at byte {} (wanted {} more)",
                self.b.len(),
                self.at - self.b.len()
            )));
        }
        Ok(())
    }
    /// A splat step (see the format) after pixel `from`: the pixel and whether its value is f32.
    fn splat_step(&mut self, from: u32) -> Result<(u32, bool), WireError> {
        let z = self.leb128("splat step")?;
        let pixel = u32::try_from(from as u64 + (z >> 1)).map_err(|_| {
            WireError(format!(
                "splat step {} from {from} leaves the u32 range",
                z >> 1
            ))
        })?;
        Ok((pixel, z & 1 == 1))
    }
    /// Checks `n` splats without decoding their values: every pixel in `pixels`, the planes
    /// within the payload. What the coordinator does for every splat it accepts, so one-byte
    /// steps (most of a sorted list) take a short path.
    fn check_splats(
        &mut self,
        n: usize,
        keys_len: usize,
        pixels: &std::ops::Range<u64>,
    ) -> Result<(), WireError> {
        let hi = pixels.end;
        let mut prev = 0u64;
        let mut wide = 0usize;
        for _ in 0..n {
            let (p, w) = match self.b.get(self.at) {
                Some(&byte) if byte < 0x80 => {
                    self.at += 1;
                    (prev + (byte >> 1) as u64, byte & 1 == 1)
                }
                _ => {
                    let (p, w) = self.splat_step(u32::try_from(prev).unwrap_or(u32::MAX))?;
                    (p as u64, w)
                }
            };
            if p < pixels.start || p >= hi {
                return Err(WireError(format!(
                    "splat pixel {p} outside pixels {pixels:?}"
                )));
            }
            prev = p;
            wide += w as usize;
        }
        self.take(n * keys_len + (n - wide) * 6 + wide * 12)
            .map_err(|e| WireError(format!("splats: {}", e.0)))?;
        Ok(())
    }
    /// A format's magic and version, or an error naming `what` was expected.
    fn header(&mut self, magic: &[u8; 8], version: u32, what: &str) -> Result<(), WireError> {
        self.header_of(magic, &[version], what).map(|_| ())
    }
    /// A format's magic and one of its `versions` (which it returns), or an error naming `what`
    /// was expected.
    fn header_of(
        &mut self,
        magic: &[u8; 8],
        versions: &[u32],
        what: &str,
    ) -> Result<u32, WireError> {
        if self.take(8)? != magic {
            return Err(WireError(format!("not a {what} (bad magic)")));
        }
        let v = self.u32()?;
        if !versions.contains(&v) {
            return Err(WireError(format!(
                "{what} version {v}, expected {versions:?}"
            )));
        }
        Ok(v)
    }
    /// `n` records of `stride` bytes, row-major: gathered from byte planes when `planes`
    /// (`Writer::rows`), else as they lie.
    fn rows(
        &mut self,
        n: usize,
        stride: usize,
        planes: bool,
    ) -> Result<std::borrow::Cow<'a, [u8]>, WireError> {
        let b: &'a [u8] = self.b;
        let len = n.saturating_mul(stride);
        if b.len() - self.at < len {
            return Err(WireError(format!(
                "truncated at byte {} (wanted {len} more)",
                self.at
            )));
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
    fn tile(&mut self) -> Result<Tile, WireError> {
        Ok(Tile {
            x0: self.u32()?,
            y0: self.u32()?,
            x1: self.u32()?,
            y1: self.u32()?,
        })
    }
    /// A counted splat list whose pixels must lie in `pixels`; layer and depth where `keys` has
    /// them (u8::MAX, "not kept", otherwise).
    fn splats(
        &mut self,
        pixels: std::ops::Range<u64>,
        keys: SplatKeys,
    ) -> Result<Vec<Splat>, WireError> {
        let mut splats = Vec::new();
        self.splat_list(pixels, keys, Some(&mut splats))?;
        Ok(splats)
    }
    /// Reads a counted splat list into `out`, or only checks it when `out` is None (its values
    /// are then skipped, not parsed).
    fn splat_list(
        &mut self,
        pixels: std::ops::Range<u64>,
        keys: SplatKeys,
        out: Option<&mut Vec<Splat>>,
    ) -> Result<(), WireError> {
        let n = self.count(1, "splats")?;
        keys.allow(n)?;
        let keys_len = keys.layer as usize + keys.depth as usize;
        let Some(o) = out else {
            return self.check_splats(n, keys_len, &pixels);
        };
        let first = o.len();
        o.reserve(n);
        let mut wide = Vec::with_capacity(n);
        let mut prev = 0;
        for _ in 0..n {
            let (pixel, w) = self.splat_step(prev)?;
            if !pixels.contains(&(pixel as u64)) {
                return Err(WireError(format!(
                    "splat pixel {pixel} outside pixels {pixels:?}"
                )));
            }
            prev = pixel;
            wide.push(w);
            o.push(Splat {
                pixel,
                layer: u8::MAX,
                depth: u8::MAX,
                value: [0.0; 3],
            });
        }
        let splats = &mut o[first..];
        if keys.layer {
            for (s, &l) in splats.iter_mut().zip(self.take(n)?) {
                s.layer = l;
            }
        }
        if keys.depth {
            for (s, &d) in splats.iter_mut().zip(self.take(n)?) {
                s.depth = d;
            }
        }
        let k = wide.iter().filter(|w| !**w).count();
        let planes = self.take(6 * k + 12 * (n - k))?;
        let (high, rest) = planes.split_at(3 * k);
        let (low, full) = rest.split_at(3 * k);
        let mut narrow = high
            .iter()
            .zip(low)
            .map(|(&h, &l)| bf16::value(u16::from_le_bytes([l, h])));
        let mut f32s = full
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")));
        for (s, w) in splats.iter_mut().zip(wide) {
            let values = if w {
                &mut f32s as &mut dyn Iterator<Item = f32>
            } else {
                &mut narrow
            };
            for v in &mut s.value {
                *v = values.next().expect("counted");
            }
        }
        Ok(())
    }
    /// Optimal-MIS records whose pixels must lie in `pixels` and depths in 1..=d_opt, each with
    /// as many values as its depth asks.
    fn records(
        &mut self,
        pixels: std::ops::Range<u64>,
        d_opt: Option<u32>,
    ) -> Result<LtRecords, WireError> {
        let mut records = LtRecords::default();
        self.record_list(pixels, d_opt, Some(&mut records))?;
        Ok(records)
    }
    /// Reads records into `out`, or only checks them when `out` is None (values skipped).
    fn record_list(
        &mut self,
        pixels: std::ops::Range<u64>,
        d_opt: Option<u32>,
        mut out: Option<&mut LtRecords>,
    ) -> Result<(), WireError> {
        let n = self.count(2, "records")?;
        match out.as_deref_mut() {
            None => self.check_pixels(n, 0, &pixels, "record")?,
            Some(o) => {
                let mut prev = 0;
                for _ in 0..n {
                    o.pixels.push(self.pixel(&mut prev, &pixels, "record")?);
                }
            }
        }
        if depths_implied(d_opt) {
            if let Some(o) = out.as_deref_mut() {
                o.depths.resize(o.depths.len() + n, 1);
            }
        } else {
            for &dd in self.take(n)? {
                if dd == 0 || Some(dd as u32) > d_opt {
                    return Err(WireError(format!(
                        "record depth {dd} outside 1..={d_opt:?}"
                    )));
                }
            }
            if let Some(o) = out.as_deref_mut() {
                o.depths.extend_from_slice(&self.b[self.at - n..self.at]);
            }
        }
        let depths = &self.b[self.at - if depths_implied(d_opt) { 0 } else { n }..self.at];
        let weights: usize = if depths_implied(d_opt) {
            n * 3
        } else {
            depths.iter().map(|&d| d as usize + 2).sum()
        };
        let width = self.u8()? as usize;
        // bfloat16 values leave out each record's light-tracing weight.
        let need = match width {
            2 => weights - n + 3 * n,
            4 => weights + 3 * n,
            _ => return Err(WireError(format!("record value width {width}, not 2 or 4"))),
        };
        let m = self.count(width, "record values")?;
        if m != need {
            return Err(WireError(format!("{m} record values, expected {need}")));
        }
        let values = self.take(width * m)?;
        let Some(o) = out else { return Ok(()) };
        if width == 4 {
            o.values.extend(
                values
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))),
            );
            return Ok(());
        }
        let (high, low) = values.split_at(m);
        let mut vals = high
            .iter()
            .zip(low)
            .map(|(&h, &l)| bf16::value(u16::from_le_bytes([l, h])));
        o.values.reserve(weights + 3 * n);
        let first = o.depths.len() - n;
        for k in first..o.depths.len() {
            let others = o.depths[k] as usize + 1;
            let start = o.values.len();
            o.values.extend(vals.by_ref().take(others));
            o.values.push(LtRecords::implied_weight(&o.values[start..]));
            o.values.extend(vals.by_ref().take(3));
        }
        Ok(())
    }
    fn stats(&mut self) -> Result<RayStats, WireError> {
        Ok(RayStats {
            closest: self.u64()?,
            shadow: self.u64()?,
            samples: self.u64()?,
            non_finite: self.u64()?,
        })
    }
    /// Fills `acc` (whose layout says how much) with the optimal-MIS values and hit counts.
    /// Each list in byte planes when `planes`.
    fn optimal_into(&mut self, acc: &mut OptimalAccum, planes: bool) -> Result<(), WireError> {
        if acc.data.len() * 8 + acc.hits.len() * 4 > self.b.len() - self.at {
            return Err(WireError("optimal systems truncated".into()));
        }
        let data = self.rows(acc.data.len(), 8, planes)?;
        for (v, b) in acc.data.iter_mut().zip(data.chunks_exact(8)) {
            *v = f64::from_le_bytes(b.try_into().expect("8 bytes"));
        }
        let hits = self.rows(acc.hits.len(), 4, planes)?;
        for (v, b) in acc.hits.iter_mut().zip(hits.chunks_exact(4)) {
            *v = u32::from_le_bytes(b.try_into().expect("4 bytes"));
        }
        Ok(())
    }
    /// Nothing is left to read.
    fn end(&self) -> Result<(), WireError> {
        match self.b.len() - self.at {
            0 => Ok(()),
            n => Err(WireError(format!("{n} trailing bytes"))),
        }
    }
    /// The u32 at the reading position, not consumed.
    fn peek_count(&self) -> Result<usize, WireError> {
        let b = self
            .b
            .get(self.at..self.at + 4)
            .ok_or_else(|| WireError(format!("truncated at byte {}", self.at)))?;
        Ok(u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize)
    }
    /// A count that must fit in the remaining bytes at `unit` bytes per item.
    fn count(&mut self, unit: usize, what: &str) -> Result<usize, WireError> {
        let n = self.u32()? as usize;
        if n.saturating_mul(unit) > self.b.len() - self.at {
            return Err(WireError(format!("{what}: count {n} exceeds the payload")));
        }
        Ok(n)
    }
}

impl TileFilm {
    /// Serialises the result for upload.
    pub fn encode(&self, samples: std::ops::Range<u32>) -> Vec<u8> {
        self.encode_as(samples, VERSION).out
    }

    /// Serialises the result for upload, with the offsets where its planes end: the cuts at
    /// which `pack::pack_pieces` packs it.
    pub fn encode_in_planes(&self, samples: std::ops::Range<u32>) -> (Vec<u8>, Vec<usize>) {
        let w = self.encode_as(samples, VERSION);
        (w.out, w.cuts)
    }

    /// Serialises the result in format `version` (`VERSION`, or `VERSION_ROWS` for tests).
    fn encode_as(&self, samples: std::ops::Range<u32>, version: u32) -> Writer {
        let px = self.tile.pixels();
        let mut w = Writer::new(Vec::with_capacity(128 + px * 52));
        w.planes = version == VERSION;
        w.bytes(MAGIC);
        w.u32(version);
        for v in [self.tile.x0, self.tile.y0, self.tile.x1, self.tile.y1] {
            w.u32(v);
        }
        w.u32(samples.start);
        w.u32(samples.end);
        w.stats(&self.stats);
        w.rows((0..px).map(|i| {
            let mut row = [0u8; 52];
            row[..4].copy_from_slice(&self.sums.count[i].to_le_bytes());
            let values = self.sums.sum[i].iter().chain(&self.sums.sum_sq[i]);
            for (at, v) in row[4..].chunks_exact_mut(8).zip(values) {
                at.copy_from_slice(&v.to_le_bytes());
            }
            row
        }));
        w.splats(&self.splats, SplatKeys::of_film(self));
        w.rgb_list(&self.layers);
        w.rgb_list(&self.depths);
        w.optimal(self.optimal.as_ref());
        w.records(&self.records, self.optimal.as_ref().map(|o| o.layout.d_opt));
        w
    }

    /// Parses and validates an uploaded result for a frame of `width` x `height` pixels whose
    /// films have `layout`. Returns the film and its sample range.
    pub fn decode(
        bytes: &[u8],
        width: u32,
        height: u32,
        layout: &FilmLayout,
    ) -> Result<(TileFilm, std::ops::Range<u32>), WireError> {
        let (checked, film) = Self::walk(bytes, width, height, layout, true)?;
        Ok((film.expect("kept"), checked.samples))
    }

    /// Checks an encoded result as `decode` would read it (it refuses what `decode` refuses),
    /// without keeping its values (they are skipped, not parsed): its tile, sample range and
    /// work counters, and how many splats and records it holds. What a coordinator does with
    /// the own part of every result it accepts.
    pub fn check(
        bytes: &[u8],
        width: u32,
        height: u32,
        layout: &FilmLayout,
    ) -> Result<Checked, WireError> {
        Ok(Self::walk(bytes, width, height, layout, false)?.0)
    }

    /// Reads an encoded result, keeping its film when `keep`, or only checking it.
    fn walk(
        bytes: &[u8],
        width: u32,
        height: u32,
        layout: &FilmLayout,
        keep: bool,
    ) -> Result<(Checked, Option<TileFilm>), WireError> {
        let d_opt = layout.d_opt();
        let mut r = Reader { b: bytes, at: 0 };
        let planes = r.header_of(MAGIC, &[VERSION, VERSION_ROWS], "tile result")? == VERSION;
        let tile = r.tile()?;
        if !(tile.x0 < tile.x1 && tile.y0 < tile.y1 && tile.x1 <= width && tile.y1 <= height) {
            return Err(WireError(format!("tile {tile:?} outside {width}x{height}")));
        }
        let (s0, s1) = (r.u32()?, r.u32()?);
        if s0 > s1 {
            return Err(WireError(format!("sample range {s0}..{s1}")));
        }
        let stats = r.stats()?;
        let px = tile.pixels();
        let frame_px = width as u64 * height as u64;
        let keys = SplatKeys::of_layout(layout);
        let strategy_values = if layout.strategy_layers {
            px * STRATEGY_LAYERS
        } else {
            0
        };
        if !keep {
            // Checking only: every length and count, no value.
            r.take(px * 52)?;
            let splats = r.count(7, "splats")?;
            keys.allow(splats)?;
            r.check_splats(
                splats,
                keys.layer as usize + keys.depth as usize,
                &(0..frame_px),
            )?;
            check_rgb_count(&mut r, strategy_values, px, "strategy layer")?;
            check_rgb_count(&mut r, px * layout.depth_layers, px, "depth layer")?;
            match (r.u32()?, &layout.optimal) {
                (0, None) => {}
                (d, Some(l)) if d == l.d_opt => {
                    r.take(px * (l.values_per_pixel() * 8 + l.d_opt as usize * 4))?;
                }
                (d, _) => return Err(optimal_mismatch(d, d_opt)),
            }
            let records = r.peek_count()?;
            r.record_list(0..frame_px, d_opt, None)?;
            r.end()?;
            let checked = Checked::of(tile, s0..s1, stats, splats, records);
            return Ok((checked, None));
        }
        let mut sums = PixelSums::new(tile.width(), tile.height());
        let rows = r.rows(px, 52, planes)?;
        let mut p = Reader { b: &rows, at: 0 };
        for i in 0..px {
            sums.count[i] = p.u32()?;
            for c in 0..3 {
                sums.sum[i][c] = p.f64()?;
            }
            for c in 0..3 {
                sums.sum_sq[i][c] = p.f64()?;
            }
        }
        let splats = r.splats(0..frame_px, keys)?;
        let layers = read_rgb_list(&mut r, strategy_values, px, "strategy layer", planes)?;
        let depths = read_rgb_list(&mut r, px * layout.depth_layers, px, "depth layer", planes)?;
        let optimal = match (r.u32()?, &layout.optimal) {
            (0, None) => None,
            (d, Some(l)) if d == l.d_opt => {
                let mut acc = OptimalAccum::new(l.clone(), px);
                r.optimal_into(&mut acc, planes)?;
                Some(acc)
            }
            (d, _) => return Err(optimal_mismatch(d, d_opt)),
        };
        let records = r.records(0..frame_px, d_opt)?;
        r.end()?;
        let checked = Checked::of(tile, s0..s1, stats, splats.len(), records.len());
        let film = TileFilm {
            tile,
            sums,
            splats,
            layers,
            depths,
            optimal,
            records,
            stats,
        };
        Ok((checked, Some(film)))
    }
}

/// What checking an encoded result (`TileFilm::check`) found.
#[derive(Clone, Debug, PartialEq)]
pub struct Checked {
    /// Its tile.
    pub tile: Tile,
    /// Its sample range.
    pub samples: std::ops::Range<u32>,
    /// Its work counters.
    pub stats: RayStats,
    /// Light-tracing splats it holds.
    pub splats: usize,
    /// Optimal-MIS records it holds.
    pub records: usize,
}

impl Checked {
    fn of(
        tile: Tile,
        samples: std::ops::Range<u32>,
        stats: RayStats,
        splats: usize,
        records: usize,
    ) -> Checked {
        Checked {
            tile,
            samples,
            stats,
            splats,
            records,
        }
    }
}

fn optimal_mismatch(d: u32, d_opt: Option<u32>) -> WireError {
    WireError(format!(
        "optimal depth {d} does not match the job's {d_opt:?}"
    ))
}

/// Checks the count of a list of RGB f64 triples (`want` of them for `px` pixels) and skips it.
fn check_rgb_count(r: &mut Reader, want: usize, px: usize, what: &str) -> Result<(), WireError> {
    let n = r.count(24, what)?;
    if n != want {
        return Err(WireError(format!("{n} {what} values for {px} pixels")));
    }
    r.take(n * 24)?;
    Ok(())
}

/// Reads a list of RGB f64 triples (`want` of them for `px` pixels; in byte planes when
/// `planes`).
fn read_rgb_list(
    r: &mut Reader,
    want: usize,
    px: usize,
    what: &str,
    planes: bool,
) -> Result<Vec<[f64; 3]>, WireError> {
    let n = r.count(24, what)?;
    if n != want {
        return Err(WireError(format!("{n} {what} values for {px} pixels")));
    }
    let rows = r.rows(n, 24, planes)?;
    let f = |b: &[u8]| f64::from_le_bytes(b.try_into().expect("8 bytes"));
    Ok(rows
        .chunks_exact(24)
        .map(|v| [f(&v[..8]), f(&v[8..16]), f(&v[16..])])
        .collect())
}

/// The accumulators of a `FilmTile`, after a tile checkpoint's header:
///
/// ```text
/// per pixel: count u32, sum 3 x f64, sum_sq 3 x f64, splat 3 x f64 (where kept: `FilmLayout::splats`)
/// layers: n u32, n x 3 x f64; depths: n u32, n x 3 x f64
/// optimal: d_opt u32 (0 = none), then pixels x stride f64, pixels x d_opt u32
/// progressive (only when the job's layout keeps it): solved_at u32, pixels x values f64
/// (`mis::Progressive`)
/// ```
fn write_tile_body(w: &mut Writer, t: &FilmTile) {
    for i in 0..t.tile.pixels() {
        w.u32(t.sums.count[i]);
        // The splat sums only where the film keeps them (`FilmLayout::splats`).
        let splat = t.splat.get(i).map_or(&[][..], |s| &s[..]);
        for v in t.sums.sum[i].iter().chain(&t.sums.sum_sq[i]).chain(splat) {
            w.f64(*v);
        }
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
/// `FilmTile::new` allocates (a checkpoint is read into a tile made so).
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
    mut out: Option<&mut FilmTile>,
) -> Result<(), WireError> {
    let n = lens.pixels;
    let per_pixel = if lens.splats { 76 } else { 52 };
    if n.saturating_mul(per_pixel) > r.b.len() - r.at {
        return Err(WireError("checkpoint pixels truncated".into()));
    }
    match out.as_deref_mut() {
        None => {
            r.take(n * per_pixel)?;
        }
        Some(t) => {
            for i in 0..n {
                t.sums.count[i] = r.u32()?;
                for c in 0..3 {
                    t.sums.sum[i][c] = r.f64()?;
                }
                for c in 0..3 {
                    t.sums.sum_sq[i][c] = r.f64()?;
                }
                if let Some(splat) = t.splat.get_mut(i) {
                    for v in splat.iter_mut() {
                        *v = r.f64()?;
                    }
                }
            }
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
            return Err(WireError(format!("{what}: {m} values, the job has {len}")));
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
                        return Err(WireError("optimal systems truncated".into()));
                    }
                    r.take(values * 8 + hits * 4)?;
                }
            }
        }
        _ => {
            return Err(WireError(format!(
                "optimal depth {d} does not match the job's settings"
            )));
        }
    }
    if let Some(values) = lens.progressive {
        let solved_at = r.u32()?;
        if values.saturating_mul(8) > r.b.len() - r.at {
            return Err(WireError("progressive estimator state truncated".into()));
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
fn checked<'a>(bytes: &'a [u8], what: &str) -> Result<&'a [u8], WireError> {
    let Some(split) = bytes.len().checked_sub(4) else {
        return Err(WireError(format!("{what} truncated")));
    };
    let (body, crc) = bytes.split_at(split);
    let want = u32::from_le_bytes(crc.try_into().expect("4 bytes"));
    if crc32fast::hash(body) != want {
        return Err(WireError(format!(
            "{what}: checksum mismatch (damaged or torn)"
        )));
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
    pub tile: FilmTile,
    /// Passes merged into them.
    pub passes: u32,
}

impl TileCheckpoint {
    /// The encoding.
    pub fn encode(&self) -> Vec<u8> {
        TileCheckpoint::encode_parts(&self.tile, self.passes)
    }

    /// The encoding of the checkpoint of `tile` holding `passes` passes (without making one).
    pub fn encode_parts(tile: &FilmTile, passes: u32) -> Vec<u8> {
        let mut w = Writer::new(Vec::with_capacity(36 + tile.tile.pixels() * 76));
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
    pub fn peek(bytes: &[u8], tile: Tile) -> Result<u32, WireError> {
        let bytes = checked(bytes, "tile checkpoint")?;
        let mut r = Reader { b: bytes, at: 0 };
        r.header(TILE_MAGIC, TILE_VERSION, "tile checkpoint")?;
        let got = r.tile()?;
        if got != tile {
            return Err(WireError(format!(
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
    ) -> Result<TileCheckpoint, WireError> {
        let mut t = FilmTile::new(tile, layout);
        let passes = Self::walk(bytes, tile, layout, Some(&mut t))?;
        Ok(TileCheckpoint { tile: t, passes })
    }

    /// Checks the checkpoint of `tile` as `decode` reads it (it refuses what `decode` refuses),
    /// skipping the values; returns the passes it holds. What a coordinator does with the
    /// checkpoints a merge task returns.
    pub fn check(bytes: &[u8], tile: Tile, layout: &FilmLayout) -> Result<u32, WireError> {
        Self::walk(bytes, tile, layout, None)
    }

    fn walk(
        bytes: &[u8],
        tile: Tile,
        layout: &FilmLayout,
        out: Option<&mut FilmTile>,
    ) -> Result<u32, WireError> {
        let bytes = checked(bytes, "tile checkpoint")?;
        let mut r = Reader { b: bytes, at: 0 };
        r.header(TILE_MAGIC, TILE_VERSION, "tile checkpoint")?;
        let got = r.tile()?;
        if got != tile {
            return Err(WireError(format!(
                "checkpoint of tile {got:?}, expected {tile:?}"
            )));
        }
        let passes = r.u32()?;
        walk_tile_body(&mut r, &BodyLens::of(tile, layout), out)?;
        Ok(passes)
    }
}

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
    pub fn read(r: &mut impl std::io::Read, len: u64) -> Result<BandedIndex, WireError> {
        let io = |e: std::io::Error| WireError(format!("banded result header: {e}"));
        let mut head = [0u8; BAND_HEAD];
        r.read_exact(&mut head).map_err(io)?;
        let mut h = Reader { b: &head, at: 0 };
        h.header(BAND_MAGIC, BAND_VERSION, "banded result")?;
        let tile = h.tile()?;
        let samples = h.u32()?..h.u32()?;
        let stats = h.stats()?;
        let own_len = h.u64()?;
        let own_crc = h.u32()?;
        let n = h.u32()? as u64;
        if n.saturating_mul(BAND_ENTRY as u64) > len {
            return Err(WireError(format!("{n} sections exceed the record")));
        }
        let mut table = vec![0u8; n as usize * BAND_ENTRY + 4];
        r.read_exact(&mut table).map_err(io)?;
        let mut crc = crc32fast::Hasher::new();
        crc.update(&head);
        crc.update(&table[..table.len() - 4]);
        let mut t = Reader { b: &table, at: 0 };
        let mut at = BAND_HEAD as u64 + table.len() as u64;
        let own = at..at.saturating_add(own_len);
        at = own.end;
        let mut sections = Vec::with_capacity(n as usize);
        let mut section_crcs = Vec::with_capacity(n as usize);
        let mut last = None;
        for _ in 0..n {
            let band = t.u32()?;
            if last.is_some_and(|l| l >= band) {
                return Err(WireError(format!("section of band {band} out of order")));
            }
            last = Some(band);
            let len = t.u64()?;
            section_crcs.push(t.u32()?);
            sections.push((band, at..at.saturating_add(len)));
            at = at.saturating_add(len);
        }
        if t.u32()? != crc.finalize() {
            return Err(WireError(
                "banded result header: checksum mismatch (damaged)".into(),
            ));
        }
        if at != len {
            return Err(WireError(format!(
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
    pub fn check_own(&self, bytes: &[u8]) -> Result<(), WireError> {
        check_crc(bytes, self.own_crc, "own part")
    }

    /// Checks the bytes of section `k` (of `sections`) against its checksum.
    pub fn check_section(&self, k: usize, bytes: &[u8]) -> Result<(), WireError> {
        let want = self.section_crcs.get(k).copied().unwrap_or(0);
        check_crc(bytes, want, "section")
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

fn check_crc(bytes: &[u8], want: u32, what: &str) -> Result<(), WireError> {
    if crc32fast::hash(bytes) != want {
        return Err(WireError(format!(
            "banded result {what}: checksum mismatch (damaged)"
        )));
    }
    Ok(())
}

/// Lays a decoded, validated task result out for band-wise merging (see `BandedIndex`), each
/// part packed (`pack`).
pub fn encode_banded(
    mut film: TileFilm,
    samples: std::ops::Range<u32>,
    grid: &super::TileGrid,
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
    grid: &super::TileGrid,
    layout: &FilmLayout,
    max_raw: u64,
) -> Result<BandedIndex, WireError> {
    let index = BandedIndex::read(&mut &bytes[..], bytes.len() as u64)?;
    let part = |r: &std::ops::Range<u64>| &bytes[r.start as usize..r.end as usize];
    let mut budget = usize::try_from(max_raw).unwrap_or(usize::MAX);
    let mut spend = |p: &[u8]| -> Result<usize, WireError> {
        let n = pack::raw_len(p)?;
        budget = budget.checked_sub(n).ok_or_else(|| {
            WireError(format!(
                "banded result inflates to more than the {max_raw} bytes allowed"
            ))
        })?;
        Ok(n)
    };
    let own = part(&index.own);
    index.check_own(own)?;
    let n = spend(own)?;
    let film = pack::unpack(own, n, |raw| {
        TileFilm::check(raw, grid.width, grid.height, layout)
    })?;
    if film.tile != index.tile || film.samples != index.samples || film.stats != index.stats {
        return Err(WireError(format!(
            "own part of tile {:?} samples {:?} under a header of tile {:?} samples {:?}",
            film.tile, film.samples, index.tile, index.samples
        )));
    }
    if film.splats > 0 || film.records > 0 {
        return Err(WireError(
            "own part with splats or records (they belong in the sections)".into(),
        ));
    }
    for (k, (b, r)) in index.sections.iter().enumerate() {
        if *b >= grid.rows() {
            return Err(WireError(format!(
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
) -> Result<Vec<u8>, WireError> {
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
        return Err(WireError(format!("own part of {} bytes", own.len())));
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
    grid: &super::TileGrid,
    layout: &FilmLayout,
) -> Result<(), WireError> {
    section(bytes, band, grid, layout, None)
}

/// Parses the section of `band` (its raw bytes, unpacked) of a banded result for `grid`,
/// whose films have `layout`: everything must land in the band.
pub fn decode_section(
    bytes: &[u8],
    band: usize,
    grid: &super::TileGrid,
    layout: &FilmLayout,
) -> Result<super::Routed, WireError> {
    let mut routed = super::Routed::default();
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
) -> Result<(TileFilm, std::ops::Range<u32>), WireError> {
    pack::unpack(part, max_raw, |raw| {
        TileFilm::decode(raw, width, height, layout)
    })
}

/// The section of `band` of a banded result as stored (packed, at most `max_raw` bytes
/// inflated), decoded (`decode_section`).
pub fn unpack_section(
    part: &[u8],
    max_raw: usize,
    band: usize,
    grid: &super::TileGrid,
    layout: &FilmLayout,
) -> Result<super::Routed, WireError> {
    pack::unpack(part, max_raw, |raw| decode_section(raw, band, grid, layout))
}

/// Reads a section into `out`, or only checks it when `out` is None.
fn section(
    bytes: &[u8],
    band: usize,
    grid: &super::TileGrid,
    layout: &FilmLayout,
    mut out: Option<&mut super::Routed>,
) -> Result<(), WireError> {
    let mut r = Reader { b: bytes, at: 0 };
    let pixels = grid.band_pixels(band);
    let keys = SplatKeys::of_layout(layout);
    r.splat_list(
        pixels.clone(),
        keys,
        out.as_deref_mut().map(|o| &mut o.splats),
    )?;
    r.record_list(pixels, layout.d_opt(), out.map(|o| &mut o.records))?;
    if r.at != bytes.len() {
        return Err(WireError(format!(
            "section of band {band}: {} trailing bytes",
            bytes.len() - r.at
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrator::{IntegratorKind, RenderSettings, render_tile};

    /// A result of version 6 (records one after another) still reads, to the film that the byte
    /// planes of version 7 hold; both have the same length and check alike, and the planes are
    /// where the pieces are cut.
    #[test]
    fn results_in_rows_and_in_byte_planes_read_the_same() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
        let mut scene = crate::scene::Scene::load(&dir.join("cornell-box.json")).expect("scene");
        scene.camera = scene.camera.with_resolution(16, 16).expect("resolution");
        let s = RenderSettings {
            integrator: IntegratorKind::Bdpt,
            mis: crate::mis::MisKind::Optimal,
            sample_block: 2,
            max_depth: 3,
            optimal_max_depth: 2,
            strategies: true,
            depth_layers: true,
            seed: 3,
            ..Default::default()
        };
        let tile = Tile {
            x0: 2,
            y0: 3,
            x1: 13,
            y1: 9,
        };
        let film = render_tile(&scene, &s, tile, 0..2);
        assert!(!film.layers.is_empty() && !film.depths.is_empty() && film.optimal.is_some());
        let layout = s.film_layout();
        let (planes, cuts) = film.encode_in_planes(0..2);
        let rows = film.encode_as(0..2, VERSION_ROWS).out;
        assert_eq!(planes, film.encode(0..2));
        assert_eq!(planes.len(), rows.len());
        assert_ne!(planes, rows);
        let (a, ra) = TileFilm::decode(&planes, 16, 16, &layout).expect("version 7");
        let (b, rb) = TileFilm::decode(&rows, 16, 16, &layout).expect("version 6");
        assert_eq!((ra, rb), (0..2, 0..2));
        assert_eq!(a.encode(0..2), planes, "the film read back");
        assert_eq!(b.encode(0..2), planes, "the same film from the rows");
        assert_eq!(
            TileFilm::check(&planes, 16, 16, &layout).expect("checks"),
            TileFilm::check(&rows, 16, 16, &layout).expect("checks")
        );
        let mut other = planes.clone();
        other[8..12].copy_from_slice(&5u32.to_le_bytes());
        assert!(TileFilm::decode(&other, 16, 16, &layout).is_err());
        assert!(TileFilm::check(&other, 16, 16, &layout).is_err());
        // The sums' 52 planes of a byte per pixel start after the 68-byte header.
        let px = tile.pixels();
        for j in 0..=52 {
            assert!(cuts.contains(&(68 + j * px)), "plane {j}");
        }
    }
}
