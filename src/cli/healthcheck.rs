//! `omis healthcheck`: asks a coordinator's /healthz, for container health checks (the image
//! needs no curl). Exit status 0 when it answers `{"status": "ok"}`, 1 otherwise.

use super::client;
use anyhow::{Context, Result, bail};
use clap::Args;
use std::time::Duration;

#[derive(Args)]
pub struct HealthcheckArgs {
    /// The coordinator's URL.
    #[arg(long, default_value = "http://127.0.0.1:8570")]
    pub server: String,
    /// Seconds to wait for the answer.
    #[arg(long, default_value_t = 3.0)]
    pub timeout: f64,
    /// Print nothing when healthy.
    #[arg(long, short)]
    pub quiet: bool,
}

pub fn run(a: HealthcheckArgs) -> Result<()> {
    let base = a.server.trim_end_matches('/');
    client::check_url(base, "--server")?;
    if !(a.timeout > 0.0 && a.timeout <= 3600.0) {
        bail!("--timeout must be within (0, 3600] seconds");
    }
    let url = format!("{base}/healthz");
    let http = reqwest::blocking::Client::builder()
        .timeout(Duration::from_secs_f64(a.timeout))
        .build()
        .context("cannot create the HTTP client")?;
    let r = http
        .get(&url)
        .send()
        .with_context(|| format!("{url}: no answer"))?;
    let status = r.status();
    let text = r.text().unwrap_or_default();
    if !status.is_success() {
        bail!("{url}: HTTP {}: {}", status.as_u16(), text.trim());
    }
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{url}: not JSON: {text}"))?;
    if v["status"].as_str() != Some("ok") {
        bail!("{url}: unhealthy: {text}");
    }
    if !a.quiet {
        println!(
            "{url}: ok (omis {})",
            v["version"].as_str().unwrap_or("unknown")
        );
    }
    Ok(())
}
