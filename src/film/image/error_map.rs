//! The signed relative error picture of an image against a reference, scaled to the image's own
//! error and with a legend under it that says what full colour means, so that a map of a
//! realistic render (relative errors of a few percent) is not black and can be read alone.

use super::Image;
use super::metrics::SizeMismatch;

/// Signed relative error picture (as in Cailleau et al.'s figures): red where the image is brighter than the
/// reference, green where it is darker; intensity |I - R| / (R + sqrt(eps)) on luminance,
/// saturating at `scale`.
pub fn relative_error_map(
    img: &Image,
    reference: &Image,
    eps: f64,
    scale: f64,
) -> Result<Vec<u8>, SizeMismatch> {
    SizeMismatch::check(img, reference)?;
    let mut out = Vec::with_capacity(img.pixels.len() * 3);
    for (a, r) in img.pixels.iter().zip(&reference.pixels) {
        let la = crate::geometry::luminance(*a) as f64;
        let lr = crate::geometry::luminance(*r) as f64;
        let e = if la == lr {
            0.0
        } else {
            (la - lr) / (lr.abs() + eps.sqrt())
        };
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

/// The share of pixels whose error the automatic scale shows without saturating.
const AUTO_SCALE_QUANTILE: f64 = 0.95;

/// A scale for [`relative_error_map`] fitted to the image: the 95th percentile of the pixels'
/// relative error, rounded up to 1, 2 or 5 times a power of ten so that the legend reads well.
/// 1 when the images agree everywhere.
pub fn auto_scale(img: &Image, reference: &Image, eps: f64) -> Result<f64, SizeMismatch> {
    SizeMismatch::check(img, reference)?;
    let mut errors: Vec<f64> = img
        .pixels
        .iter()
        .zip(&reference.pixels)
        .map(|(a, r)| {
            let la = crate::geometry::luminance(*a) as f64;
            let lr = crate::geometry::luminance(*r) as f64;
            ((la - lr) / (lr.abs() + eps.sqrt())).abs()
        })
        .filter(|e| e.is_finite())
        .collect();
    if errors.is_empty() {
        return Ok(1.0);
    }
    let k = ((errors.len() - 1) as f64 * AUTO_SCALE_QUANTILE).round() as usize;
    let (_, q, _) = errors.select_nth_unstable_by(k, f64::total_cmp);
    let q = *q;
    if q <= 0.0 {
        return Ok(1.0);
    }
    let decade = 10f64.powf(q.log10().floor());
    let nice = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * decade)
        .find(|&s| s >= q * (1.0 - 1e-9))
        .unwrap_or(10.0 * decade);
    Ok(nice.max(1e-4))
}

/// An RGB8 picture: the error map with its legend below.
pub struct ErrorPicture {
    /// Width in pixels (the image's).
    pub width: usize,
    /// Height in pixels: the image's plus the legend's.
    pub height: usize,
    /// Row-major RGB8 samples.
    pub rgb: Vec<u8>,
    /// The relative error shown at full colour.
    pub scale: f64,
}

/// Rows of the legend: a colour bar and a line of labels.
const BAR_ROWS: usize = 6;
const GAP_ROWS: usize = 2;
const GLYPH_W: usize = 3;
const GLYPH_H: usize = 5;
const LEGEND_ROWS: usize = BAR_ROWS + GAP_ROWS + GLYPH_H + 2;

/// The error map of `img` against `reference`, at `scale` (None: [`auto_scale`]), with a legend
/// under it: a bar from full green (darker than the reference by `scale`) through black to full
/// red (brighter by `scale`), labelled "-X%", "0" and "+X%" where the image is wide enough.
pub fn error_picture(
    img: &Image,
    reference: &Image,
    eps: f64,
    scale: Option<f64>,
) -> Result<ErrorPicture, SizeMismatch> {
    let scale = match scale {
        Some(s) => s,
        None => auto_scale(img, reference, eps)?,
    };
    let mut rgb = relative_error_map(img, reference, eps, scale)?;
    let w = img.width;
    let mut legend = vec![32u8; w * LEGEND_ROWS * 3];
    for x in 0..w {
        // -1 at the left edge, +1 at the right.
        let t = if w > 1 {
            2.0 * x as f64 / (w - 1) as f64 - 1.0
        } else {
            0.0
        };
        let v = (t.abs() * 255.0 + 0.5) as u8;
        let px = if t >= 0.0 { [v, 0, 0] } else { [0, v, 0] };
        for y in 1..=BAR_ROWS {
            legend[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&px);
        }
    }
    let pct = format_percent(scale);
    let labels = [
        (format!("-{pct}"), 0usize),
        ("0".to_string(), w / 2),
        (format!("+{pct}"), w),
    ];
    let top = BAR_ROWS + GAP_ROWS;
    let widths: Vec<usize> = labels.iter().map(|(s, _)| text_width(s)).collect();
    // Labels only where all three fit side by side without overlapping.
    if widths.iter().sum::<usize>() + 4 <= w {
        for ((text, anchor), tw) in labels.iter().zip(&widths) {
            let x0 = anchor.saturating_sub(tw / 2).min(w - tw);
            let x0 = if *anchor == 0 { 0 } else { x0 };
            draw_text(&mut legend, w, x0, top, text);
        }
    }
    rgb.extend_from_slice(&legend);
    Ok(ErrorPicture {
        width: w,
        height: img.height + LEGEND_ROWS,
        rgb,
        scale,
    })
}

/// `scale` as a percentage with at most two significant digits: 0.05 -> "5%", 0.002 -> "0.2%".
fn format_percent(scale: f64) -> String {
    let p = scale * 100.0;
    let digits = if p >= 10.0 {
        0
    } else {
        (1.0 - p.log10().floor()).max(0.0) as usize
    };
    let s = format!("{p:.digits$}");
    let s = if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    };
    format!("{s}%")
}

/// 3x5 glyphs of the legend's characters, one row per byte (bit 2 = left column).
fn glyph(c: char) -> [u8; GLYPH_H] {
    match c {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        '%' => [5, 1, 2, 4, 5],
        '+' => [0, 2, 7, 2, 0],
        '-' => [0, 0, 7, 0, 0],
        _ => [0; GLYPH_H],
    }
}

fn text_width(text: &str) -> usize {
    text.chars().count() * (GLYPH_W + 1)
}

/// Draws `text` in white into the RGB8 rows `rgb` of width `w`, top-left at (x0, y0).
fn draw_text(rgb: &mut [u8], w: usize, x0: usize, y0: usize, text: &str) {
    for (i, c) in text.chars().enumerate() {
        for (dy, bits) in glyph(c).iter().enumerate() {
            for dx in 0..GLYPH_W {
                let x = x0 + i * (GLYPH_W + 1) + dx;
                if bits & (4 >> dx) != 0 && x < w {
                    let at = ((y0 + dy) * w + x) * 3;
                    if let Some(px) = rgb.get_mut(at..at + 3) {
                        px.copy_from_slice(&[255, 255, 255]);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Rgb;

    #[test]
    fn brighter_is_red_darker_is_green() {
        let mut r = Image::new(2, 1);
        r.pixels = vec![Rgb::splat(1.0), Rgb::splat(2.0)];
        let mut i = r.clone();
        i.pixels[0] = Rgb::splat(2.0);
        i.pixels[1] = Rgb::splat(1.0);
        let map = relative_error_map(&i, &r, 0.0, 1.0).unwrap();
        assert_eq!(&map[..3], &[255, 0, 0]);
        assert!(map[3] == 0 && map[4] > 100 && map[5] == 0);
    }

    #[test]
    fn the_automatic_scale_shows_a_few_percent_error_in_colour() {
        // A render 3% off its reference everywhere but one firefly: at a fixed scale of 1 the map
        // is almost black; the automatic scale (5%) shows it at 60% intensity.
        let r = Image {
            width: 100,
            height: 10,
            pixels: vec![Rgb::splat(0.5); 1000],
        };
        let mut i = r.clone();
        for (k, p) in i.pixels.iter_mut().enumerate() {
            *p = Rgb::splat(if k % 2 == 0 { 0.515 } else { 0.485 });
        }
        i.pixels[7] = Rgb::splat(500.0);
        let fixed = relative_error_map(&i, &r, 0.0, 1.0).unwrap();
        assert!(fixed[0] < 10, "{}", fixed[0]);
        let s = auto_scale(&i, &r, 0.0).unwrap();
        assert!((s - 0.05).abs() < 1e-12, "{s}");
        let pic = error_picture(&i, &r, 0.0, None).unwrap();
        assert_eq!((pic.width, pic.height), (100, 10 + LEGEND_ROWS));
        assert_eq!(pic.rgb.len(), pic.width * pic.height * 3);
        assert!((140..170).contains(&pic.rgb[0]), "{}", pic.rgb[0]);
        // The legend bar: full green at the left edge, full red at the right.
        let row = 10 + 1;
        assert_eq!(&pic.rgb[row * 100 * 3..row * 100 * 3 + 3], &[0, 255, 0]);
        assert_eq!(
            &pic.rgb[(row * 100 + 99) * 3..(row * 100 + 100) * 3],
            &[255, 0, 0]
        );
        // Labels drawn in white below it.
        let text = &pic.rgb[(10 + BAR_ROWS + GAP_ROWS) * 100 * 3..];
        assert!(text.chunks(3).any(|p| p == [255, 255, 255]));
    }

    #[test]
    fn percentages_read_well() {
        assert_eq!(format_percent(0.05), "5%");
        assert_eq!(format_percent(0.002), "0.2%");
        assert_eq!(format_percent(0.0001), "0.01%");
        assert_eq!(format_percent(2.0), "200%");
        assert_eq!(format_percent(0.2), "20%");
    }
}
