//! bfloat16: the upper 16 bits of an f32 (sign, 8 exponent bits, 7 mantissa bits). The wire
//! format ships a light-tracing value in this width when it is exactly representable, which the
//! integrators arrange by rounding each contribution stochastically (`round`): the rounded value
//! equals the input in expectation, so estimates stay unbiased, and its relative error is at most
//! 2^-7 (standard deviation at most 2^-8 of the value, Connolly, Higham and Mary, "Stochastic
//! rounding and its probabilistic backward error analysis", SIAM J. Sci. Comput. 43(1), 2021).

/// True when `v` has a bfloat16 representation (its low 16 bits are zero).
#[inline]
pub fn exact(v: f32) -> bool {
    v.to_bits() & 0xffff == 0
}

/// The bfloat16 bits of `v`, which must be `exact`.
#[inline]
pub fn bits(v: f32) -> u16 {
    debug_assert!(exact(v), "{v} is not a bfloat16 value");
    (v.to_bits() >> 16) as u16
}

/// The f32 of bfloat16 `bits` (exact).
#[inline]
pub fn value(bits: u16) -> f32 {
    f32::from_bits((bits as u32) << 16)
}

/// `v` rounded to one of the two bfloat16 values around it, up with probability equal to the
/// fraction of the way `v` lies between them, decided by `r` (16 uniform random bits): E[round(v,
/// r)] = v over uniform r. The bits of a finite f32 grow with its magnitude and are linear in it
/// between two bfloat16 neighbours, so the fraction is the low 16 bits / 2^16. Non-finite values
/// pass as they are (their upper bits); a finite value never rounds to infinity.
#[inline]
pub fn round(v: f32, r: u16) -> f32 {
    let b = v.to_bits();
    let low = b & 0xffff;
    let mut high = b >> 16;
    if !v.is_finite() {
        return v;
    }
    if (r as u32) < low {
        high += 1;
        if (high & 0x7f80) == 0x7f80 {
            // Up from the largest finite binade: stay at the largest finite value.
            high -= 1;
        }
    }
    f32::from_bits(high << 16)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_is_exact_unbiased_and_within_one_step() {
        let mut rng = crate::sampler::Pcg32::new(7, 0);
        for _ in 0..2000 {
            // Values of every magnitude and sign, subnormals included.
            let v = f32::from_bits(rng.next_u32());
            if !v.is_finite() {
                continue;
            }
            let lo = f32::from_bits(v.to_bits() & 0xffff_0000);
            let hi = round(v, 0);
            assert!(exact(lo) && exact(hi));
            assert_eq!(round(v, u16::MAX), lo, "{v}");
            if exact(v) {
                assert_eq!(hi, v);
                continue;
            }
            // Over every r the mean is v itself (up to f64 summation): unbiased.
            let mut sum = 0.0f64;
            for r in 0..=u16::MAX {
                let q = round(v, r);
                assert!(q == lo || q == hi, "{v}: {q} not a neighbour");
                sum += q as f64;
            }
            if (hi.to_bits() >> 16) & 0x7f80 != 0x7f80 && hi.abs() > lo.abs() {
                // Exactly v: the mean of the two neighbours weighted by the low bits.
                assert_eq!(sum / 65536.0, v as f64, "{v}");
                if v.is_normal() {
                    // One bfloat16 step, at most 2^-7 of the value.
                    let step = (hi as f64 - lo as f64).abs();
                    assert!(step <= (v as f64).abs() * 2f64.powi(-7), "{v}");
                }
            }
            assert_eq!(value(bits(lo)), lo);
        }
        assert_eq!(round(f32::MAX, 0), f32::from_bits(0x7f7f_0000));
        assert!(round(f32::INFINITY, 0).is_infinite());
        assert!(round(f32::NAN, 0).is_nan());
        assert_eq!(round(0.0, 0), 0.0);
    }
}
