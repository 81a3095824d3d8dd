//! Error metrics against a reference image.

use super::Image;

/// relMSE (the seed's MRSE) = mean over pixels and channels of (I - R)^2 / (R^2 + eps), and MSE.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct ErrorStats {
    pub relmse: f64,
    pub mse: f64,
    pub eps: f64,
    /// Pixels where either image was not finite (excluded from the means).
    pub non_finite: usize,
}

pub fn compare(img: &Image, reference: &Image, eps: f64) -> Result<ErrorStats, String> {
    if img.width != reference.width || img.height != reference.height {
        return Err(format!(
            "size mismatch: image is {}x{}, reference is {}x{}",
            img.width, img.height, reference.width, reference.height
        ));
    }
    let mut rel = 0.0f64;
    let mut mse = 0.0f64;
    let mut n = 0usize;
    let mut bad = 0usize;
    for (a, r) in img.pixels.iter().zip(&reference.pixels) {
        if !a.is_finite() || !r.is_finite() {
            bad += 1;
            continue;
        }
        for c in 0..3 {
            let d = a[c] as f64 - r[c] as f64;
            let rr = r[c] as f64;
            rel += d * d / (rr * rr + eps);
            mse += d * d;
        }
        n += 3;
    }
    let n = n.max(1) as f64;
    Ok(ErrorStats {
        relmse: rel / n,
        mse: mse / n,
        eps,
        non_finite: bad,
    })
}

/// Signed relative error picture (seed 000, Fig. 5): red where the image is brighter than the
/// reference, green where it is darker; intensity |I - R| / (R + sqrt(eps)) on luminance,
/// saturating at `scale`.
pub fn error_map(img: &Image, reference: &Image, eps: f64, scale: f64) -> Result<Vec<u8>, String> {
    if img.width != reference.width || img.height != reference.height {
        return Err("size mismatch".into());
    }
    let mut out = Vec::with_capacity(img.pixels.len() * 3);
    for (a, r) in img.pixels.iter().zip(&reference.pixels) {
        let la = crate::geometry::luminance(*a) as f64;
        let lr = crate::geometry::luminance(*r) as f64;
        let e = (la - lr) / (lr.abs() + eps.sqrt());
        let m = if e.is_finite() {
            (e.abs() / scale).min(1.0)
        } else {
            1.0
        };
        let v = (m * 255.0 + 0.5) as u8;
        if e >= 0.0 {
            out.extend_from_slice(&[v, 0, 0]);
        } else {
            out.extend_from_slice(&[0, v, 0]);
        }
    }
    Ok(out)
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
        let map = error_map(&i, &r, 0.01, 1.0).unwrap();
        assert!(map[0] > 0 && map[1] == 0);
    }
}
