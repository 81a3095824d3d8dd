//! Scene importers: our JSON format, OBJ and PLY meshes, pbrt-v3 and Mitsuba 0.5 files.
//!
//! Every loader receives a `Resolver` (inside the [`SceneBuilder`] it fills) and reaches the
//! files a scene names only through it: a `SceneFile` cannot be made any other way, and the
//! resolver records each one, so the list of files a scene reads ([`Scene::files`], what bundles
//! pack) is complete whatever the format.

mod common;
pub mod json;
pub(crate) mod mesh;
pub(crate) mod mitsuba;
pub mod pbrt;
mod resolve;

pub(crate) use resolve::Resolver;

use super::{Scene, SceneBuilder, SceneError};
use std::path::Path;

/// Loads a scene file, choosing the importer by extension (and, for `.pbrt`, the dialect by the
/// contents); the scene's `files` are those its resolver handed out.
pub(crate) fn load(path: &Path) -> Result<Scene, SceneError> {
    let resolver = Resolver::new(path);
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let parse: fn(&str, Resolver) -> Result<SceneBuilder, SceneError> = match ext.as_str() {
        "json" => json::parse_with,
        "pbrt" => pbrt::parse_with,
        "xml" => mitsuba::parse_with,
        other => {
            return Err(SceneError::new(
                path,
                "file",
                format!("unknown scene format '.{other}' (expected .json, .pbrt or .xml)"),
            ));
        }
    };
    let text = resolver.read_scene()?;
    parse(&text, resolver)?.build()
}
