//! The lists a task result, its banded sections and a tile checkpoint hold: light-tracing
//! splats, optimal-MIS records, RGB layers and the optimal systems, each written and read (or
//! only checked, its values skipped) in one place.

use super::codec::{Reader, Writer};
use super::error::FormatError;
use crate::film::{FilmLayout, LtRecords, Splat, TaskFilm, bf16};
use crate::mis::OptimalAccum;

/// Which of a splat's keys the wire carries: its strategy layer and its depth only when the
/// film keeps strategy / depth layers (otherwise both are u8::MAX after `TaskFilm::compact`,
/// and nothing reads them).
#[derive(Clone, Copy, Debug)]
pub(super) struct SplatKeys {
    pub(super) layer: bool,
    pub(super) depth: bool,
    /// Whether the film may hold splats at all (not the path tracer's: `FilmLayout::splats`).
    pub(super) kept: bool,
}

impl SplatKeys {
    pub(super) fn of_layout(l: &FilmLayout) -> SplatKeys {
        SplatKeys {
            layer: l.strategy_layers,
            depth: l.depth_layers > 0,
            kept: l.splats,
        }
    }
    /// Refuses `n` splats for a film that keeps none.
    pub(super) fn allow(self, n: usize) -> Result<(), FormatError> {
        if n > 0 && !self.kept {
            return Err(FormatError::invalid(format!(
                "{n} light-tracing splats for a film that keeps none (the path tracer)"
            )));
        }
        Ok(())
    }
    /// The keys of a film made with some layout (its layer lists are empty when not kept).
    pub(super) fn of_film(f: &TaskFilm) -> SplatKeys {
        SplatKeys {
            layer: !f.layers.is_empty(),
            depth: !f.depths.is_empty(),
            kept: true,
        }
    }
}

/// depths out.
pub(super) fn depths_implied(d_opt: Option<u32>) -> bool {
    d_opt == Some(1)
}

impl Writer {
    /// A counted list of RGB f64 triples (strategy or depth layers).
    pub(super) fn rgb_list(&mut self, list: &[[f64; 3]]) {
        self.u32(list.len() as u32);
        self.rows(list.iter().map(|[r, g, b]| {
            let mut row = [0u8; 24];
            for (at, v) in row.chunks_exact_mut(8).zip([r, g, b]) {
                at.copy_from_slice(&v.to_le_bytes());
            }
            row
        }));
    }
    /// A counted list of splats, sorted by pixel (`TaskFilm::compact`; routing keeps the
    /// order), in planes: delta-coded pixels, their layers and depths only where the film keeps
    /// them (`keys`), then the values, bfloat16 (high bytes, then low bytes) where they are
    /// one, and the others as f32.
    pub(super) fn splats(&mut self, splats: &[Splat], keys: SplatKeys) {
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
    pub(super) fn records(&mut self, r: &LtRecords, d_opt: Option<u32>) {
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
    pub(super) fn optimal(&mut self, o: Option<&OptimalAccum>) {
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

impl Reader<'_> {
    /// The next pixel of a delta-coded list after `prev` (which becomes it); it must lie in
    /// `pixels` (`what` names the list's items in the error).
    pub(super) fn pixel(
        &mut self,
        prev: &mut u32,
        pixels: &std::ops::Range<u64>,
        what: &str,
    ) -> Result<u32, FormatError> {
        let p = self.step(*prev)?;
        *prev = p;
        if !pixels.contains(&(p as u64)) {
            return Err(FormatError::invalid(format!(
                "{what} pixel {p} outside pixels {pixels:?}"
            )));
        }
        Ok(p)
    }
    /// Checks `n` list entries of a pixel step and `stride` bytes (skipped) without decoding
    /// them: every pixel in `pixels`, the list within the payload. What the coordinator does
    /// for every record it accepts (`check_splats` for splats), so one-byte steps (most of a
    /// sorted list) take a short path; the others go through `step`.
    pub(super) fn check_pixels(
        &mut self,
        n: usize,
        stride: usize,
        pixels: &std::ops::Range<u64>,
        what: &str,
    ) -> Result<(), FormatError> {
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
                return Err(FormatError::invalid(format!(
                    "{what} pixel {p} outside pixels {pixels:?}"
                )));
            }
            prev = p;
            self.at += stride;
        }
        if self.at > self.b.len() {
            return Err(FormatError::invalid(format!(
                "{what}s: truncated at byte {} (wanted {} more)",
                self.b.len(),
                self.at - self.b.len()
            )));
        }
        Ok(())
    }
    /// A splat step (see the format) after pixel `from`: the pixel and whether its value is f32.
    pub(super) fn splat_step(&mut self, from: u32) -> Result<(u32, bool), FormatError> {
        let z = self.leb128("splat step")?;
        let pixel = u32::try_from(from as u64 + (z >> 1)).map_err(|_| {
            FormatError::invalid(format!(
                "splat step {} from {from} leaves the u32 range",
                z >> 1
            ))
        })?;
        Ok((pixel, z & 1 == 1))
    }
    /// Checks `n` splats without decoding their values: every pixel in `pixels`, the planes
    /// within the payload. What the coordinator does for every splat it accepts, so one-byte
    /// steps (most of a sorted list) take a short path.
    pub(super) fn check_splats(
        &mut self,
        n: usize,
        keys_len: usize,
        pixels: &std::ops::Range<u64>,
    ) -> Result<(), FormatError> {
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
                return Err(FormatError::invalid(format!(
                    "splat pixel {p} outside pixels {pixels:?}"
                )));
            }
            prev = p;
            wide += w as usize;
        }
        self.take(n * keys_len + (n - wide) * 6 + wide * 12)
            .map_err(|e| match e {
                FormatError::Truncated { at, wanted } => FormatError::invalid(format!(
                    "splats: truncated at byte {at} (wanted {wanted} more)"
                )),
                e => e,
            })?;
        Ok(())
    }
    /// A counted splat list whose pixels must lie in `pixels`; layer and depth where `keys` has
    /// them (u8::MAX, "not kept", otherwise).
    pub(super) fn splats(
        &mut self,
        pixels: std::ops::Range<u64>,
        keys: SplatKeys,
    ) -> Result<Vec<Splat>, FormatError> {
        let mut splats = Vec::new();
        self.splat_list(pixels, keys, Some(&mut splats))?;
        Ok(splats)
    }
    /// Reads a counted splat list into `out`, or only checks it when `out` is None (its values
    /// are then skipped, not parsed).
    pub(super) fn splat_list(
        &mut self,
        pixels: std::ops::Range<u64>,
        keys: SplatKeys,
        out: Option<&mut Vec<Splat>>,
    ) -> Result<(), FormatError> {
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
                return Err(FormatError::invalid(format!(
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
    pub(super) fn records(
        &mut self,
        pixels: std::ops::Range<u64>,
        d_opt: Option<u32>,
    ) -> Result<LtRecords, FormatError> {
        let mut records = LtRecords::default();
        self.record_list(pixels, d_opt, Some(&mut records))?;
        Ok(records)
    }
    /// Reads records into `out`, or only checks them when `out` is None (values skipped).
    pub(super) fn record_list(
        &mut self,
        pixels: std::ops::Range<u64>,
        d_opt: Option<u32>,
        mut out: Option<&mut LtRecords>,
    ) -> Result<(), FormatError> {
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
                    return Err(FormatError::invalid(format!(
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
            _ => {
                return Err(FormatError::invalid(format!(
                    "record value width {width}, not 2 or 4"
                )));
            }
        };
        let m = self.count(width, "record values")?;
        if m != need {
            return Err(FormatError::invalid(format!(
                "{m} record values, expected {need}"
            )));
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
    /// Fills `acc` (whose layout says how much) with the optimal-MIS values and hit counts.
    /// Each list in byte planes when `planes`.
    pub(super) fn optimal_into(
        &mut self,
        acc: &mut OptimalAccum,
        planes: bool,
    ) -> Result<(), FormatError> {
        if acc.data.len() * 8 + acc.hits.len() * 4 > self.b.len() - self.at {
            return Err(FormatError::invalid("optimal systems truncated"));
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
}

/// Checks the count of a list of RGB f64 triples (`want` of them for `px` pixels) and skips it.
pub(super) fn check_rgb_count(
    r: &mut Reader,
    want: usize,
    px: usize,
    what: &str,
) -> Result<(), FormatError> {
    let n = r.count(24, what)?;
    if n != want {
        return Err(FormatError::invalid(format!(
            "{n} {what} values for {px} pixels"
        )));
    }
    r.take(n * 24)?;
    Ok(())
}

/// Reads a list of RGB f64 triples (`want` of them for `px` pixels; in byte planes when
/// `planes`).
pub(super) fn read_rgb_list(
    r: &mut Reader,
    want: usize,
    px: usize,
    what: &str,
    planes: bool,
) -> Result<Vec<[f64; 3]>, FormatError> {
    let n = r.count(24, what)?;
    if n != want {
        return Err(FormatError::invalid(format!(
            "{n} {what} values for {px} pixels"
        )));
    }
    let rows = r.rows(n, 24, planes)?;
    let f = |b: &[u8]| f64::from_le_bytes(b.try_into().expect("8 bytes"));
    Ok(rows
        .chunks_exact(24)
        .map(|v| [f(&v[..8]), f(&v[8..16]), f(&v[16..])])
        .collect())
}
