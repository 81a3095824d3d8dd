//! `omis diff`: relMSE (all pixels, and without the 0.1% worst) and MSE of an image against a
//! reference, the signed error map, and with `--layers` every EXR layer the two files share.

use crate::film::image::{error_map, exr_io, metrics, png};
use crate::service::exr_header;
use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub struct DiffArgs {
    pub image: PathBuf,
    pub reference: PathBuf,
    /// eps of relMSE = mean (I - R)^2 / (R^2 + eps).
    #[arg(long, default_value_t = 0.01)]
    pub eps: f64,
    /// Write the red (brighter) / green (darker) relative error picture.
    #[arg(long)]
    pub error_map: Option<PathBuf>,
    /// Relative error shown at full intensity in the error map (default: fitted to the image's
    /// error, the 95th percentile rounded up; the legend under the map gives it).
    #[arg(long)]
    pub error_scale: Option<f64>,
    /// Compare every layer the two files share (beauty, variance, strategies, depths), and
    /// fail unless each is bit-identical when `--eps 0`.
    #[arg(long)]
    pub layers: bool,
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: DiffArgs) -> Result<()> {
    if !(a.eps >= 0.0 && a.eps.is_finite()) {
        bail!("--eps must be a finite number >= 0");
    }
    if a.layers {
        return run_layers(&a);
    }
    check_headers(&a)?;
    let img = exr_io::read_exr(&a.image).map_err(anyhow::Error::msg)?;
    let reference = exr_io::read_exr(&a.reference).map_err(anyhow::Error::msg)?;
    let s = metrics::compare(&img, &reference, a.eps).map_err(anyhow::Error::msg)?;
    if let Some(p) = &a.error_map {
        if let Some(s) = a.error_scale
            && !(s > 0.0 && s.is_finite())
        {
            bail!("--error-scale must be a finite number > 0");
        }
        let pic = error_map::error_picture(&img, &reference, a.eps, a.error_scale)
            .map_err(anyhow::Error::msg)?;
        png::write_rgb8(p, pic.width, pic.height, &pic.rgb).map_err(anyhow::Error::msg)?;
    }
    if a.json {
        println!("{}", serde_json::to_string(&s)?);
    } else {
        println!(
            "relMSE {:.6e}  without the 0.1% worst pixels {:.6e}  MSE {:.6e}  (eps {}){}",
            s.relmse,
            s.relmse_trimmed,
            s.mse,
            s.eps,
            if s.identical { "  identical" } else { "" }
        );
        if s.non_finite > 0 {
            println!("{} pixels were not finite and were left out", s.non_finite);
        }
    }
    Ok(())
}

/// Every shared layer, by name; with `--eps 0` an error unless every one is bit-identical.
/// Both files' headers, before decoding: a small file can claim a frame too large to decode.
fn check_headers(a: &DiffArgs) -> Result<()> {
    for p in [&a.image, &a.reference] {
        exr_header::check_cli(p)?;
    }
    Ok(())
}

fn run_layers(a: &DiffArgs) -> Result<()> {
    check_headers(a)?;
    let img = exr_io::read_exr_layers(&a.image).map_err(anyhow::Error::msg)?;
    let reference = exr_io::read_exr_layers(&a.reference).map_err(anyhow::Error::msg)?;
    let mut rows = Vec::new();
    let names =
        |l: &[(String, crate::film::Image)]| l.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
    if names(&img) != names(&reference) {
        bail!(
            "the files have different layers: {:?} vs {:?}",
            names(&img),
            names(&reference)
        );
    }
    for ((name, i), (_, r)) in img.iter().zip(&reference) {
        let s = metrics::compare(i, r, a.eps.max(f64::MIN_POSITIVE))
            .map_err(|e| anyhow::anyhow!("layer '{name}': {e}"))?;
        if !a.json {
            println!(
                "{:<12} relMSE {:.6e}  max |diff| {:.3e}{}",
                if name.is_empty() { "beauty" } else { name },
                s.relmse,
                s.max_abs,
                if s.identical { "  identical" } else { "" }
            );
        }
        rows.push((name.clone(), s));
    }
    if a.json {
        let v: serde_json::Map<String, serde_json::Value> = rows
            .iter()
            .map(|(n, s)| (n.clone(), serde_json::json!(s)))
            .collect();
        println!("{}", serde_json::Value::Object(v));
    }
    let differ: Vec<&str> = rows
        .iter()
        .filter(|(_, s)| !s.identical)
        .map(|(n, _)| if n.is_empty() { "beauty" } else { n.as_str() })
        .collect();
    if a.eps == 0.0 && !differ.is_empty() {
        bail!("layers differ: {}", differ.join(", "));
    }
    Ok(())
}
