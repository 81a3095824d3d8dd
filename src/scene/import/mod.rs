//! Scene importers: our JSON format, OBJ and PLY meshes, pbrt-v3, Mitsuba 0.5 and Mitsuba 3
//! files.
//!
//! Every loader receives a `Resolver` (inside the [`SceneBuilder`] it fills) and reaches the
//! files a scene names only through it: a `SceneFile` cannot be made any other way, and the
//! resolver records each one, so the list of files a scene reads ([`Scene::files`], what bundles
//! pack) is complete whatever the format.

mod common;
pub mod json;
pub(crate) mod mesh;
pub(crate) mod mitsuba;
mod mitsuba3;
pub mod pbrt;
mod resolve;
pub(crate) mod xml;

pub(crate) use resolve::Resolver;

use super::{Scene, SceneError, SceneParams};
use std::path::Path;

/// Loads a scene file, choosing the importer by extension (and, for `.pbrt`, the dialect by the
/// contents; for `.xml`, Mitsuba's version by the root element) with values for its parameters;
/// the scene's `files` are those its resolver handed out.
pub(crate) fn load(path: &Path, params: &SceneParams) -> Result<Scene, SceneError> {
    let resolver = Resolver::new(path);
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let no_params = |path: &Path| {
        if params.is_empty() {
            Ok(())
        } else {
            Err(SceneError::new(
                path,
                "parameters",
                "parameters (--define, a job's defines) apply only to Mitsuba 2/3 files",
            ))
        }
    };
    let text = match ext.as_str() {
        "json" | "pbrt" | "xml" => resolver.read_scene()?,
        other => {
            return Err(SceneError::new(
                path,
                "file",
                format!("unknown scene format '.{other}' (expected .json, .pbrt or .xml)"),
            ));
        }
    };
    let builder = match ext.as_str() {
        "json" => {
            no_params(path)?;
            json::parse_with(&text, resolver)?
        }
        "pbrt" => {
            no_params(path)?;
            pbrt::parse_with(&text, resolver)?
        }
        _ => mitsuba::parse_with(&text, resolver, params)?,
    };
    builder.build()
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    /// Calls that open or look up files by path.
    const OPENERS: [&str; 8] = [
        "std::fs",
        "fs::",
        "File::open",
        "Bitmap::load",
        "canonicalize",
        "image::open",
        "load_obj(",
        "symlink_metadata",
    ];

    /// The lines outside `resolve.rs` allowed to open a file: the standalone OBJ reader (for
    /// files of no scene) and the bitmap cache, which takes a resolved file.
    const ALLOWED: [(&str, &str); 3] = [
        ("mesh.rs", "pub fn load_obj(path: &Path)"),
        ("mesh.rs", "let file = std::fs::File::open(path)"),
        ("common.rs", "Bitmap::load_with(file.path(), srgb)"),
    ];

    fn sources(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
        for e in std::fs::read_dir(dir).expect("import sources") {
            let p = e.expect("entry").path();
            if p.is_dir() {
                sources(&p, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }

    /// Only the resolver opens a scene's files: no importer source (outside its tests) opens or
    /// looks up a file by path, which would bypass the recorded file list and the folder checks.
    #[test]
    fn only_the_resolver_opens_files() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/scene/import");
        let mut files = Vec::new();
        sources(&dir, &mut files);
        assert!(files.len() > 10, "{files:?}");
        let mut bad = Vec::new();
        for f in files {
            let name = f.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if name == "resolve.rs" {
                continue;
            }
            let text = std::fs::read_to_string(&f).expect("source");
            // Test code (after `#[cfg(test)]`) may set up files.
            for (i, line) in text.lines().enumerate() {
                let code = line.trim();
                if code == "#[cfg(test)]" {
                    break;
                }
                if code.starts_with("//") || !OPENERS.iter().any(|o| code.contains(o)) {
                    continue;
                }
                if !ALLOWED.iter().any(|(n, a)| *n == name && code.contains(a)) {
                    bad.push(format!("{}:{}: {code}", f.display(), i + 1));
                }
            }
        }
        assert!(
            bad.is_empty(),
            "files opened outside the resolver:\n{}",
            bad.join("\n")
        );
    }
}
