//! `omis diff`: relMSE and MSE of an image against a reference, and the signed error map.

use crate::film::{exr_io, metrics, png};
use anyhow::Result;
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
    /// Relative error shown at full intensity in the error map.
    #[arg(long, default_value_t = 1.0)]
    pub error_scale: f64,
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: DiffArgs) -> Result<()> {
    let img = exr_io::read_exr(&a.image).map_err(anyhow::Error::msg)?;
    let reference = exr_io::read_exr(&a.reference).map_err(anyhow::Error::msg)?;
    let s = metrics::compare(&img, &reference, a.eps).map_err(anyhow::Error::msg)?;
    if let Some(p) = &a.error_map {
        let map = metrics::error_map(&img, &reference, a.eps, a.error_scale)
            .map_err(anyhow::Error::msg)?;
        png::write_rgb8(p, img.width, img.height, &map).map_err(anyhow::Error::msg)?;
    }
    if a.json {
        println!("{}", serde_json::to_string(&s)?);
    } else {
        println!(
            "relMSE {:.6e}  MSE {:.6e}  (eps {})",
            s.relmse, s.mse, s.eps
        );
        if s.non_finite > 0 {
            println!("{} pixels were not finite and were left out", s.non_finite);
        }
    }
    Ok(())
}
