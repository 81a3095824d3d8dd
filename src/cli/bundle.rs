//! `omis bundle`: the bundle `omis submit` uploads for a scene file (the scene and every file its
//! importer read), written to a file, so other clients (the Python package) pack exactly the same.

use super::job_args::parse_defines;
use crate::bundle;
use anyhow::Context;
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct BundleArgs {
    /// The scene file (any format omis reads).
    pub scene: PathBuf,
    /// Where to write the bundle (a tar archive).
    #[arg(long)]
    pub out: PathBuf,
    /// A value for a parameter of the scene file (Mitsuba's `$name`), as for `omis submit`
    /// (repeatable).
    #[arg(long = "define", value_name = "NAME=VALUE")]
    pub defines: Vec<String>,
}

/// Loads the scene (which records every file it reads), packs the bundle, writes it, and prints
/// one JSON line: `{"main": <the scene's name in the bundle>, "bytes": <bundle size>}`; `main` is
/// the `main` query parameter of `POST /v1/scenes`.
pub fn run(a: BundleArgs) -> anyhow::Result<()> {
    let params = parse_defines(&a.defines)?;
    let (tar, main) = bundle::pack(&a.scene, &params)?;
    std::fs::write(&a.out, &tar).with_context(|| format!("{}", a.out.display()))?;
    println!(
        "{}",
        serde_json::json!({ "main": main, "bytes": tar.len() })
    );
    Ok(())
}
