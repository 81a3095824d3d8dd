//! Error metrics against a reference image.

use super::Image;

/// An image compared with a reference of another size.
#[derive(Debug, thiserror::Error)]
#[error(
    "size mismatch: image is {}x{}, reference is {}x{}",
    image.0,
    image.1,
    reference.0,
    reference.1
)]
pub struct SizeMismatch {
    /// The image's width and height.
    pub image: (usize, usize),
    /// The reference's.
    pub reference: (usize, usize),
}

impl SizeMismatch {
    /// Ok when `img` and `reference` have the same size.
    pub(crate) fn check(img: &Image, reference: &Image) -> Result<(), SizeMismatch> {
        if img.width != reference.width || img.height != reference.height {
            return Err(SizeMismatch {
                image: (img.width, img.height),
                reference: (reference.width, reference.height),
            });
        }
        Ok(())
    }
}

/// For callers whose errors are messages.
impl From<SizeMismatch> for String {
    fn from(e: SizeMismatch) -> String {
        e.to_string()
    }
}

/// relMSE (the MRSE of Cailleau et al.) = mean over pixels and channels of (I - R)^2 / (R^2 +
/// eps), and MSE; also relMSE without the `TRIM` fraction of pixels with the largest error, where
/// fireflies show as the difference between the two.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct ErrorStats {
    /// Mean relative squared error.
    pub relmse: f64,
    /// relMSE over all but the 0.1% of pixels with the largest relative squared error.
    pub relmse_trimmed: f64,
    /// Mean squared error.
    pub mse: f64,
    /// The eps of relMSE.
    pub eps: f64,
    /// Largest absolute difference of a channel.
    pub max_abs: f64,
    /// Every pixel has the same bits in both images.
    pub identical: bool,
    /// Pixels where either image was not finite (excluded from the means).
    pub non_finite: usize,
}

/// Fraction of pixels `relmse_trimmed` leaves out.
pub const TRIM: f64 = 0.001;

/// Compares `img` against `reference` (same size).
pub fn compare(img: &Image, reference: &Image, eps: f64) -> Result<ErrorStats, SizeMismatch> {
    SizeMismatch::check(img, reference)?;
    let mut per_pixel = Vec::with_capacity(img.pixels.len());
    let mut mse = 0.0f64;
    let mut max_abs = 0.0f64;
    let mut bad = 0usize;
    let mut identical = true;
    for (a, r) in img.pixels.iter().zip(&reference.pixels) {
        for c in 0..3 {
            identical &= a[c].to_bits() == r[c].to_bits();
        }
        if !a.is_finite() || !r.is_finite() {
            bad += 1;
            continue;
        }
        let mut rel = 0.0f64;
        for c in 0..3 {
            let d = a[c] as f64 - r[c] as f64;
            let rr = r[c] as f64;
            // A value equal to its reference has no error, also where the reference is 0 and
            // eps is 0 (0 / 0).
            if d != 0.0 {
                rel += d * d / (rr * rr + eps);
            }
            mse += d * d;
            max_abs = max_abs.max(d.abs());
        }
        per_pixel.push(rel);
    }
    let n = per_pixel.len();
    let total: f64 = per_pixel.iter().sum();
    let drop = ((n as f64 * TRIM).ceil() as usize).min(n.saturating_sub(1));
    let trimmed = if drop > 0 {
        // The `drop` largest values, found in O(n).
        let k = n - drop;
        per_pixel.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
        per_pixel[..k].iter().sum::<f64>()
    } else {
        total
    };
    let channels = (3 * n).max(1) as f64;
    Ok(ErrorStats {
        relmse: total / channels,
        relmse_trimmed: trimmed / (3 * (n - drop)).max(1) as f64,
        mse: mse / channels,
        eps,
        max_abs,
        identical,
        non_finite: bad,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Rgb;

    #[test]
    fn relmse_of_known_images() {
        let mut r = Image::new(2, 1);
        r.pixels = vec![Rgb::splat(1.0), Rgb::splat(2.0)];
        let mut i = r.clone();
        assert_eq!(compare(&i, &r, 0.01).unwrap().relmse, 0.0);
        i.pixels[0] = Rgb::splat(2.0);
        let s = compare(&i, &r, 0.0).unwrap();
        // One pixel off by 1 relative to 1 in all three channels: 3 / 6.
        assert!((s.relmse - 0.5).abs() < 1e-12);
        assert!((s.mse - 0.5).abs() < 1e-12);
    }
}
