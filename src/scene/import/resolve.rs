//! The one way a loader reaches the files a scene names: a [`Resolver`] turns a path written in
//! the scene into a [`SceneFile`] inside the scene's folder and records it, so that the list of
//! files a scene consists of (for bundles) is complete by construction.

use crate::scene::SceneError;
use std::path::{Path, PathBuf};

/// The canonical folder of a scene file (the current folder for a bare file name).
pub(crate) fn scene_folder(scene_file: &Path) -> std::io::Result<PathBuf> {
    match scene_file.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.canonicalize(),
        _ => Path::new(".").canonicalize(),
    }
}

/// A file inside a scene's folder, handed out (and recorded) by [`Resolver::resolve`]: the only
/// way for a loader to name a file it reads besides the scene file itself. It has no public
/// constructor.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub(crate) struct SceneFile {
    path: PathBuf,
}

impl SceneFile {
    /// The canonical path, inside the scene's folder.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The file's text.
    pub fn read_to_string(&self) -> std::io::Result<String> {
        std::fs::read_to_string(&self.path)
    }

    /// The file, opened for buffered reading.
    pub fn open(&self) -> std::io::Result<std::io::BufReader<std::fs::File>> {
        std::fs::File::open(&self.path).map(std::io::BufReader::new)
    }
}

/// Resolves the relative paths a scene file names against the scene's folder and records every
/// file it hands out: the scene file together with [`Resolver::files`] is a complete bundle.
#[derive(Debug)]
pub(crate) struct Resolver {
    scene_file: PathBuf,
    files: Vec<PathBuf>,
}

impl Resolver {
    /// A resolver for the files `scene_file` names (nothing is read yet).
    pub fn new(scene_file: &Path) -> Resolver {
        Resolver {
            scene_file: scene_file.to_path_buf(),
            files: Vec::new(),
        }
    }

    /// The scene file the paths are relative to.
    pub fn scene_file(&self) -> &Path {
        &self.scene_file
    }

    /// Reads the scene file itself (not recorded: a bundle holds it under its own name).
    pub fn read_scene(&self) -> Result<String, SceneError> {
        std::fs::read_to_string(&self.scene_file)
            .map_err(|e| SceneError::new(&self.scene_file, "file", format!("cannot read: {e}")))
    }

    /// Resolves `rel`, a path relative to the scene's folder; `location` names the place that
    /// wrote it in errors. Refuses absolute paths, any path that leaves the folder (after
    /// following links), and missing files.
    pub fn resolve(&mut self, rel: &str, location: &str) -> Result<SceneFile, SceneError> {
        let err = |m: String| SceneError::new(&self.scene_file, location, m);
        let relp = Path::new(rel);
        if relp.is_absolute() {
            return Err(err(format!(
                "'{rel}' is an absolute path; paths must be relative to the scene's folder"
            )));
        }
        let base = scene_folder(&self.scene_file)
            .map_err(|e| err(format!("cannot resolve the scene's folder: {e}")))?;
        let canon = base
            .join(relp)
            .canonicalize()
            .map_err(|e| err(format!("'{rel}' not found ({e})")))?;
        if !canon.starts_with(&base) {
            return Err(err(format!("'{rel}' leaves the scene's folder; refused")));
        }
        self.files.push(canon.clone());
        Ok(SceneFile { path: canon })
    }

    /// The files resolved so far, sorted and without repeats.
    pub fn files(&self) -> Vec<PathBuf> {
        let mut v = self.files.clone();
        v.sort();
        v.dedup();
        v
    }
}
