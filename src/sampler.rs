//! Samplers. Every random number of pixel sample `i` of pixel (x, y) derives from
//! hash(seed, x, y, i) and a dimension counter, so a render is a deterministic function of
//! (scene, settings, seed) whatever the thread count, tiling or order of work.
//!
//! The integrators make one [`Sampler`] per pixel sample and [`Stream`]; the job settings
//! choose its [`SamplerKind`].

use crate::geometry::Vec2;
use serde::{Deserialize, Serialize};

/// 64-bit finaliser of MurmurHash3 / SplitMix64 (Steele et al. 2014).
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Hash of a sequence of words; order matters.
#[inline]
pub fn hash_words(words: &[u64]) -> u64 {
    let mut h = 0x9e37_79b9_7f4a_7c15u64;
    for &w in words {
        h = mix64(h ^ w.wrapping_add(0x9e37_79b9_7f4a_7c15).wrapping_add(h << 6));
    }
    h
}

/// PCG32 (O'Neill 2014, XSH-RR variant).
#[derive(Clone, Debug)]
pub struct Pcg32 {
    state: u64,
    inc: u64,
}

impl Pcg32 {
    const MULT: u64 = 6_364_136_223_846_793_005;

    /// A generator seeded with `seed` on sequence `stream` (distinct streams are independent).
    pub fn new(seed: u64, stream: u64) -> Self {
        let mut r = Pcg32 {
            state: 0,
            inc: (stream << 1) | 1,
        };
        r.next_u32();
        r.state = r.state.wrapping_add(seed);
        r.next_u32();
        r
    }

    /// The next 32 random bits.
    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(Self::MULT).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn next_f32(&mut self) -> f32 {
        u32_to_unit(self.next_u32())
    }

    /// Uniform in [0, 1), with 53 random bits.
    pub fn next_f64(&mut self) -> f64 {
        let hi = (self.next_u32() as u64) << 21;
        let lo = (self.next_u32() >> 11) as u64;
        ((hi | lo) as f64) * (1.0 / (1u64 << 53) as f64)
    }
}

/// Top 24 bits of `x` as a float in [0, 1).
#[inline]
fn u32_to_unit(x: u32) -> f32 {
    (x >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
}

/// Which sample generator a render uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum SamplerKind {
    /// Independent uniform numbers from PCG32.
    Independent,
    /// Stratified: jittered strata in 1D and correlated multi-jittered (Kensler 2013) in 2D, over
    /// blocks of `spp` samples.
    Stratified,
    /// Owen-scrambled Sobol' (0,2)-sequence, padded per dimension pair (Burley 2020).
    #[default]
    Sobol,
}

/// Which family of dimensions a sampler serves: camera subpaths and light subpaths of the same
/// pixel sample draw from independent streams.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stream {
    /// Dimensions of the camera subpath (and the pixel position).
    Camera = 0,
    /// Dimensions of the light subpath.
    Light = 1,
}

/// Sobol' dimensions are made this many at a time, one per SIMD lane: the lane loops of
/// [`SobolBlock::fill`] compile to AVX2 in the x86-64-v3 build, about a tenth of the
/// instructions of making each dimension on its own. A dimension's numbers depend on its index
/// alone, never on which block or call made it.
const BLOCK: usize = 8;

/// The random numbers of one pixel sample.
#[derive(Clone, Debug)]
pub struct Sampler {
    kind: SamplerKind,
    /// hash(seed, x, y, stream): scrambles per pixel.
    pixel_hash: u64,
    index: u32,
    /// Stratification block (the requested spp, or the pass size in time-budget renders).
    block: u32,
    dim: u32,
    rng: Pcg32,
    /// Sobol': the dimensions made so far.
    sobol: SobolBlock,
}

/// Sobol': the numbers of dimensions `start .. start + BLOCK` of one pixel sample.
#[derive(Clone, Debug)]
struct SobolBlock {
    /// Per-pixel keys of the three scrambles of a dimension: the index's, x's and y's.
    keys: [u32; 3],
    /// The sample index, bit-reversed (the first step of every index scramble).
    index_reversed: u32,
    /// First dimension of the block; [`SobolBlock::NONE`] before the first is made.
    start: u32,
    x: [f32; BLOCK],
    y: [f32; BLOCK],
}

impl SobolBlock {
    /// `start` before any block is made: no dimension `d` below 2^31 (a pixel sample draws a
    /// few hundred at most) has `d - NONE`, wrapping, below `BLOCK`.
    const NONE: u32 = 1 << 31;

    fn new(pixel_hash: u64, index: u32) -> Self {
        SobolBlock {
            keys: [
                pixel_hash as u32,
                (pixel_hash >> 32) as u32,
                mix64(pixel_hash) as u32,
            ],
            index_reversed: index.reverse_bits(),
            start: Self::NONE,
            x: [0.0; BLOCK],
            y: [0.0; BLOCK],
        }
    }

    /// The numbers of dimension `d`, making its block first when it is not the one held.
    #[inline]
    fn get(&mut self, d: u32) -> (f32, f32) {
        let k = d.wrapping_sub(self.start) as usize;
        if k < BLOCK {
            return (self.x[k], self.y[k]);
        }
        self.fill(d - d % BLOCK as u32);
        let k = (d % BLOCK as u32) as usize;
        (self.x[k], self.y[k])
    }

    /// Makes dimensions `start .. start + BLOCK`, lane by lane with no dependence between lanes.
    #[inline(never)]
    fn fill(&mut self, start: u32) {
        let mut x = [0u32; BLOCK];
        let mut y = [0u32; BLOCK];
        for k in 0..BLOCK {
            let (sx, sy) = sobol_dimension(self.keys, self.index_reversed, start + k as u32);
            x[k] = sx;
            y[k] = sy;
        }
        self.x = x.map(u32_to_unit);
        self.y = y.map(u32_to_unit);
        self.start = start;
    }
}

/// Dimension `d` of the pixel sample whose index bit-reversed is `index_reversed`, as 32-bit
/// fractions: the first two dimensions of the Sobol' (0,2)-sequence at an index shuffled per
/// dimension, each Owen-scrambled (Burley 2020, "Practical Hash-based Owen Scrambling", JCGT
/// 9(4): padding by shuffling the index). The three scrambles' seeds hash the pixel's keys with
/// the dimension.
#[inline(always)]
fn sobol_dimension(keys: [u32; 3], index_reversed: u32, d: u32) -> (u32, u32) {
    let salt = d.wrapping_add(1).wrapping_mul(0x9e37_79b9);
    let [seed_index, seed_x, seed_y] = keys.map(|k| hash32(k ^ salt));
    // The index, Owen-scrambled: nested_uniform_scramble(index, seed_index).
    let i = laine_karras_permutation(index_reversed, seed_index).reverse_bits();
    let x = scrambled_dim0(i, seed_x);
    // nested_uniform_scramble(sobol_dim1(i), seed_y) with the reversal inside it cancelled.
    let y = laine_karras_permutation(sobol_dim1_reversed(i), seed_y).reverse_bits();
    (x, y)
}

/// A 32-bit integer hash with low bias (C. Wellons, "Prospecting for hash functions", 2018:
/// "lowbias32").
#[inline(always)]
fn hash32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

impl Sampler {
    /// The sampler of sample `index` of pixel (`x`, `y`) on `stream`, stratified over blocks of
    /// `block` samples; its numbers depend only on these arguments and `seed`.
    pub fn new(
        kind: SamplerKind,
        seed: u64,
        x: u32,
        y: u32,
        index: u32,
        block: u32,
        stream: Stream,
    ) -> Self {
        let pixel_hash = hash_words(&[seed, x as u64, y as u64, stream as u64]);
        let sample_hash = hash_words(&[pixel_hash, index as u64]);
        Sampler {
            kind,
            pixel_hash,
            index,
            block: block.max(1),
            dim: 0,
            rng: Pcg32::new(sample_hash, stream as u64),
            sobol: SobolBlock::new(pixel_hash, index),
        }
    }

    /// Which generator this is.
    pub fn kind(&self) -> SamplerKind {
        self.kind
    }

    /// The next dimension's number, in [0, 1).
    #[inline]
    pub fn next_1d(&mut self) -> f32 {
        let d = self.dim;
        self.dim += 1;
        match self.kind {
            SamplerKind::Independent => self.rng.next_f32(),
            SamplerKind::Stratified => {
                let round = self.index / self.block;
                let j = self.index % self.block;
                let h = hash_words(&[self.pixel_hash, d as u64, round as u64]) as u32;
                let stratum = permute(j, self.block, h);
                let jitter = self.rng.next_f32();
                ((stratum as f32 + jitter) / self.block as f32).min(ONE_MINUS_EPS)
            }
            SamplerKind::Sobol => self.sobol.get(d).0,
        }
    }

    /// The next dimension's pair of numbers, in [0, 1)^2 (one 2D dimension).
    #[inline]
    pub fn next_2d(&mut self) -> Vec2 {
        let d = self.dim;
        self.dim += 1;
        match self.kind {
            SamplerKind::Independent => Vec2::new(self.rng.next_f32(), self.rng.next_f32()),
            SamplerKind::Stratified => {
                let round = self.index / self.block;
                let j = self.index % self.block;
                let h = hash_words(&[self.pixel_hash, d as u64, round as u64]) as u32;
                cmj(j, self.block, h, &mut self.rng)
            }
            SamplerKind::Sobol => {
                let (x, y) = self.sobol.get(d);
                Vec2::new(x, y)
            }
        }
    }
}

const ONE_MINUS_EPS: f32 = 1.0 - f32::EPSILON / 2.0;

/// First Sobol' dimension (the van der Corput sequence, i.e. bit reversal of i), Owen-scrambled:
/// nested_uniform_scramble(reverse(i), seed) = reverse(laine_karras(i, seed)).
#[inline]
fn scrambled_dim0(i: u32, seed: u32) -> u32 {
    laine_karras_permutation(i, seed).reverse_bits()
}

/// Second Sobol' dimension (primitive polynomial x + 1): direction numbers v_k = v_{k-1} ^ (v_{k-1} >> 1).
/// Returned bit-reversed: bit j of the result is bit 31 - j of the sample, so that
/// `sobol_dim1_reversed(i) == sobol_dim1_reference(i).reverse_bits()`.
///
/// Bit 31 - j of v_k is C(k, j) mod 2, which by Lucas' theorem is 1 exactly when the bits of j are
/// a subset of those of k. Bit j of the result is therefore the parity of the set bits k of `i`
/// with j ⊆ k: a superset-sum transform over the 5-bit positions, five shift-and-xor steps
/// (branch-free, unlike the loop over the bits of a scrambled, i.e. random, index).
#[inline]
fn sobol_dim1_reversed(i: u32) -> u32 {
    let mut s = i;
    s ^= (s >> 1) & 0x5555_5555;
    s ^= (s >> 2) & 0x3333_3333;
    s ^= (s >> 4) & 0x0f0f_0f0f;
    s ^= (s >> 8) & 0x00ff_00ff;
    s ^= (s >> 16) & 0x0000_ffff;
    s
}

/// The definition of [`sobol_dim1_reversed`] (unreversed), kept to test it against.
#[cfg(test)]
fn sobol_dim1_reference(mut i: u32) -> u32 {
    let mut v = 1u32 << 31;
    let mut r = 0u32;
    while i != 0 {
        if i & 1 != 0 {
            r ^= v;
        }
        i >>= 1;
        v ^= v >> 1;
    }
    r
}

/// Laine–Karras style hash permutation, as improved by Burley 2020 ("Practical Hash-based Owen
/// Scrambling", JCGT 9(4)): an Owen scramble of the bit-reversed word.
#[inline]
fn laine_karras_permutation(mut x: u32, seed: u32) -> u32 {
    x = x.wrapping_add(seed);
    x ^= x.wrapping_mul(0x6c50_b47c);
    x ^= x.wrapping_mul(0xb82f_1e52);
    x ^= x.wrapping_mul(0xc7af_e638);
    x ^= x.wrapping_mul(0x8d22_f6e6);
    x
}

#[cfg(test)]
fn nested_uniform_scramble(x: u32, seed: u32) -> u32 {
    laine_karras_permutation(x.reverse_bits(), seed).reverse_bits()
}

/// Hash permutation of [0, l) by cycle walking (Kensler 2013, "Correlated Multi-Jittered Sampling").
fn permute(mut i: u32, l: u32, p: u32) -> u32 {
    if l <= 1 {
        return 0;
    }
    let mut w = l - 1;
    w |= w >> 1;
    w |= w >> 2;
    w |= w >> 4;
    w |= w >> 8;
    w |= w >> 16;
    loop {
        i ^= p;
        i = i.wrapping_mul(0xe170_893d);
        i ^= p >> 16;
        i ^= (i & w) >> 4;
        i ^= p >> 8;
        i = i.wrapping_mul(0x0929_eb3f);
        i ^= p >> 23;
        i ^= (i & w) >> 1;
        i = i.wrapping_mul(1 | p >> 27);
        i = i.wrapping_mul(0x6935_fa69);
        i ^= (i & w) >> 11;
        i = i.wrapping_mul(0x74dc_b303);
        i ^= (i & w) >> 2;
        i = i.wrapping_mul(0x9e50_1cc3);
        i ^= (i & w) >> 2;
        i = i.wrapping_mul(0xc860_a3df);
        i &= w;
        i ^= i >> 5;
        if i < l {
            break;
        }
    }
    (i.wrapping_add(p)) % l
}

/// Correlated multi-jittered 2D sample `s` of `n` (Kensler 2013): stratified in an m x k grid and in
/// both 1D projections, for any n.
fn cmj(s: u32, n: u32, p: u32, rng: &mut Pcg32) -> Vec2 {
    let m = (n as f32).sqrt().ceil().max(1.0) as u32;
    let k = n.div_ceil(m);
    let s = permute(s, n, p.wrapping_mul(0x51633e2d));
    let sx = permute(s % m, m, p.wrapping_mul(0x68bc21eb));
    let sy = permute(s / m, k, p.wrapping_mul(0x02e5be93));
    let jx = rng.next_f32();
    let jy = rng.next_f32();
    let x = ((s % m) as f32 + (sy as f32 + jx) / k as f32) / m as f32;
    let y = ((s / m) as f32 + (sx as f32 + jy) / m as f32) / k as f32;
    Vec2::new(x.min(ONE_MINUS_EPS), y.min(ONE_MINUS_EPS))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sobol_dim1_fast_matches_definition() {
        let mut x = 0x1234_5678u32;
        let check = |i: u32| {
            assert_eq!(
                sobol_dim1_reversed(i).reverse_bits(),
                sobol_dim1_reference(i),
                "{i:#x}"
            )
        };
        for i in 0..(1u32 << 16) {
            check(i);
            check(!i);
            check(i << 16);
        }
        for _ in 0..1_000_000 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            check(x);
        }
    }

    /// The Sobol' sampler as first written, one dimension at a time (the index scrambled, then
    /// the dimension-1 value by the loop over its bits); the blocks must reproduce it bit for bit
    /// whatever the order of 1D and 2D draws.
    #[test]
    fn sobol_matches_reference_formulas() {
        for (x, y, index) in [
            (0u32, 0u32, 0u32),
            (3, 4, 1),
            (17, 250, 15),
            (1023, 7, 4095),
            (5, 9, u32::MAX),
        ] {
            let mut s = Sampler::new(SamplerKind::Sobol, 42, x, y, index, 16, Stream::Camera);
            let keys = s.sobol.keys;
            for d in 0..40u32 {
                let salt = (d + 1).wrapping_mul(0x9e37_79b9);
                let [h_index, h_x, h_y] = keys.map(|k| hash32(k ^ salt));
                let i = nested_uniform_scramble(index, h_index);
                let want_x = u32_to_unit(scrambled_dim0(i, h_x));
                if d % 3 == 0 {
                    assert_eq!(s.next_1d().to_bits(), want_x.to_bits());
                } else {
                    let want_y = u32_to_unit(nested_uniform_scramble(sobol_dim1_reference(i), h_y));
                    let v = s.next_2d();
                    assert_eq!(
                        (v.x.to_bits(), v.y.to_bits()),
                        (want_x.to_bits(), want_y.to_bits())
                    );
                }
            }
        }
    }

    /// Every dimension pair of a pixel's first 16 samples is a (0,4)-net: each 1/16 column and
    /// row holds one point, also for pairs of dimensions in different blocks. Sixteen Sobol'
    /// points at one shuffled index set are; a shuffle or scramble that failed would not be.
    #[test]
    fn sobol_dimensions_are_stratified_in_every_block() {
        for (px, py) in [(0u32, 0u32), (5, 9), (200, 3)] {
            let pts: Vec<Vec<Vec2>> = (0..16)
                .map(|i| {
                    let mut s = Sampler::new(SamplerKind::Sobol, 9, px, py, i, 16, Stream::Light);
                    (0..20).map(|_| s.next_2d()).collect()
                })
                .collect();
            for d in 0..20 {
                let mut cols = [0; 16];
                let mut rows = [0; 16];
                for p in &pts {
                    cols[(p[d].x * 16.0) as usize] += 1;
                    rows[(p[d].y * 16.0) as usize] += 1;
                }
                assert!(cols.iter().all(|&c| c == 1), "dim {d} cols {cols:?}");
                assert!(rows.iter().all(|&c| c == 1), "dim {d} rows {rows:?}");
            }
        }
    }

    #[test]
    fn permute_is_a_permutation() {
        for l in [1u32, 2, 3, 7, 16, 100, 257] {
            let mut seen = vec![false; l as usize];
            for i in 0..l {
                let j = permute(i, l, 0xdead_beef);
                assert!(j < l);
                assert!(!seen[j as usize]);
                seen[j as usize] = true;
            }
        }
    }

    fn samples(kind: SamplerKind, n: u32) -> Vec<Vec2> {
        (0..n)
            .map(|i| Sampler::new(kind, 7, 3, 4, i, n, Stream::Camera).next_2d())
            .collect()
    }

    #[test]
    fn all_kinds_in_unit_square_and_deterministic() {
        for kind in [
            SamplerKind::Independent,
            SamplerKind::Stratified,
            SamplerKind::Sobol,
        ] {
            let a = samples(kind, 64);
            let b = samples(kind, 64);
            assert_eq!(a, b);
            for s in &a {
                assert!((0.0..1.0).contains(&s.x) && (0.0..1.0).contains(&s.y));
            }
        }
    }

    #[test]
    fn stratified_and_sobol_cover_every_stratum() {
        // 16 samples: one per 1/16 column for both; Sobol is a (0,4)-net in base 2 for 16 points.
        for kind in [SamplerKind::Stratified, SamplerKind::Sobol] {
            let s = samples(kind, 16);
            let mut cols = [0; 16];
            let mut rows = [0; 16];
            for p in &s {
                cols[(p.x * 16.0) as usize] += 1;
                rows[(p.y * 16.0) as usize] += 1;
            }
            assert!(cols.iter().all(|&c| c == 1), "{kind:?} cols {cols:?}");
            assert!(rows.iter().all(|&c| c == 1), "{kind:?} rows {rows:?}");
        }
    }

    #[test]
    fn one_d_means_are_unbiased() {
        for kind in [
            SamplerKind::Independent,
            SamplerKind::Stratified,
            SamplerKind::Sobol,
        ] {
            let mut sum = 0.0f64;
            let n = 4096;
            for px in 0..64u32 {
                for i in 0..64u32 {
                    let mut s = Sampler::new(kind, 1, px, 0, i, 64, Stream::Light);
                    s.next_2d();
                    sum += s.next_1d() as f64;
                }
            }
            let mean = sum / n as f64;
            assert!((mean - 0.5).abs() < 0.02, "{kind:?} {mean}");
        }
    }
}
