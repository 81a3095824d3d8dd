//! `omis bundle`: the bundle `omis submit` uploads for a scene file (the scene and every file its
//! importer read), written to a file, so other clients (the Python package) pack exactly the same.

use super::job_args::parse_defines;
use crate::bundle;
use crate::job::frames::{self as job_frames, FrameRange};
use anyhow::Context;
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct BundleArgs {
    /// The scene file (any format omis reads); with --frames, a frame pattern
    /// (frame_####.xml).
    pub scene: PathBuf,
    /// Pack a sequence: these frames of the pattern SCENE (FIRST-LAST or FIRST-LAST:STEP), every
    /// frame file and what it reads in one bundle whose main file is the pattern.
    #[arg(long, value_name = "FIRST-LAST")]
    pub frames: Option<FrameRange>,
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
    let (tar, main) = match a.frames {
        Some(frames) => sequence(&a.scene, frames, &params)?,
        None => bundle::pack(&a.scene, &params)?,
    };
    std::fs::write(&a.out, &tar).with_context(|| format!("{}", a.out.display()))?;
    println!(
        "{}",
        serde_json::json!({ "main": main, "bytes": tar.len() })
    );
    Ok(())
}

/// The bundle of `frames` of frame pattern `pattern`, and the pattern's file name (its main).
pub(crate) fn sequence(
    pattern: &std::path::Path,
    frames: FrameRange,
    params: &crate::scene::SceneParams,
) -> anyhow::Result<(Vec<u8>, String)> {
    frames.validate().map_err(|e| anyhow::anyhow!("--{e}"))?;
    let text = pattern.to_string_lossy().into_owned();
    job_frames::validate_pattern(&text, "scene").map_err(|e| anyhow::anyhow!(e.message))?;
    let main = pattern
        .file_name()
        .and_then(|n| n.to_str())
        .with_context(|| format!("{text}: not a file name"))?
        .to_string();
    let files: Vec<PathBuf> = frames
        .frames()
        .filter_map(|f| job_frames::frame_file(&text, f).map(Into::into))
        .collect();
    if let Some(missing) = files.iter().find(|f| !f.is_file()) {
        anyhow::bail!("{}: no such frame file", missing.display());
    }
    Ok((bundle::pack_frames(&files, params)?, main))
}
