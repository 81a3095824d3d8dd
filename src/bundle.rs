//! Scene bundles: a tar archive of a scene file and every file it reads (meshes, textures,
//! includes), with paths relative to the scene's folder. Clients upload them, the coordinator
//! keeps them, workers download and cache them.

use crate::scene::{Scene, SceneParams};
use std::io::Read;
use std::path::{Component, Path, PathBuf};

/// Why a scene was not packed into a bundle. No variant names its cause as a `source`: the
/// message already holds it, and error chains print it once.
#[derive(Debug, thiserror::Error)]
pub enum PackError {
    /// The scene did not load (so the files it reads are unknown).
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    /// The scene's path does not end in a file name.
    #[error("{}: not a file name", .0.display())]
    NotAFileName(PathBuf),
    /// A file (the scene, or one it reads) or the scene's folder could not be read.
    #[error("{}: {error}", .path.display())]
    Read {
        /// The file or folder.
        path: PathBuf,
        /// The file system's error.
        error: std::io::Error,
    },
    /// A file the scene reads lies outside its folder (a bundle holds paths relative to it).
    #[error("{} is outside the scene's folder", .0.display())]
    OutsideFolder(PathBuf),
    /// The archive could not be finished.
    #[error("cannot finish the bundle: {0}")]
    Finish(std::io::Error),
}

/// Packs `scene` (loaded with `params` to learn the files it reads) into a tar archive. Returns
/// the archive and the scene file's name inside it.
pub fn pack(scene_path: &Path, params: &SceneParams) -> Result<(Vec<u8>, String), PackError> {
    let scene = Scene::load_with(scene_path, params)?;
    pack_files(scene_path, &scene.files)
}

/// Packs the scene file and `files` (paths inside the scene's folder).
pub fn pack_files(scene_path: &Path, files: &[PathBuf]) -> Result<(Vec<u8>, String), PackError> {
    let read = |path: &Path| {
        let path = path.to_path_buf();
        move |error: std::io::Error| PackError::Read { path, error }
    };
    let main = scene_path
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| PackError::NotAFileName(scene_path.to_path_buf()))?
        .to_string();
    let base = crate::scene::json::scene_folder(scene_path).map_err(read(scene_path))?;
    let mut tar = tar::Builder::new(Vec::new());
    // The coordinator accepts plain files only; a file with holes on disk (a copied texture,
    // say) must still go as a plain entry, not a GNU sparse one.
    tar.sparse(false);
    tar.append_path_with_name(scene_path, &main)
        .map_err(read(scene_path))?;
    for f in files {
        let rel = f
            .strip_prefix(&base)
            .map_err(|_| PackError::OutsideFolder(f.clone()))?;
        if rel == Path::new(&main) {
            continue;
        }
        tar.append_path_with_name(f, rel).map_err(read(f))?;
    }
    let bytes = tar.into_inner().map_err(PackError::Finish)?;
    Ok((bytes, main))
}

/// Packs the scene files of a sequence's frames (`scenes`, in one folder; each loaded with
/// `params` to learn the files it reads) into one tar archive: every frame's file under its own
/// name and the union of the files they read (shared meshes and textures once).
pub fn pack_frames(scenes: &[PathBuf], params: &SceneParams) -> Result<Vec<u8>, PackError> {
    let read = |path: &Path| {
        let path = path.to_path_buf();
        move |error: std::io::Error| PackError::Read { path, error }
    };
    let Some(first) = scenes.first() else {
        return Err(PackError::NotAFileName(PathBuf::new()));
    };
    let base = crate::scene::json::scene_folder(first).map_err(read(first))?;
    let mut names = std::collections::BTreeSet::new();
    let mut tar = tar::Builder::new(Vec::new());
    tar.sparse(false);
    for scene_path in scenes {
        let name = scene_path
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or_else(|| PackError::NotAFileName(scene_path.to_path_buf()))?
            .to_string();
        if crate::scene::json::scene_folder(scene_path).map_err(read(scene_path))? != base {
            return Err(PackError::OutsideFolder(scene_path.clone()));
        }
        let scene = Scene::load_with(scene_path, params)?;
        if names.insert(PathBuf::from(&name)) {
            tar.append_path_with_name(scene_path, &name)
                .map_err(read(scene_path))?;
        }
        for f in &scene.files {
            let rel = f
                .strip_prefix(&base)
                .map_err(|_| PackError::OutsideFolder(f.clone()))?;
            if names.insert(rel.to_path_buf()) {
                tar.append_path_with_name(f, rel).map_err(read(f))?;
            }
        }
    }
    tar.into_inner().map_err(PackError::Finish)
}

/// Most entries (files and folders) of a bundle: a scene with its meshes and textures needs far
/// fewer, and every entry costs a file on the server.
pub(crate) const MAX_ENTRIES: usize = 10_000;

/// What a tar entry that is not a plain file or folder is, in words.
fn entry_kind(kind: tar::EntryType) -> String {
    use tar::EntryType as T;
    match kind {
        T::Symlink | T::Link => "a link (links are refused)".into(),
        T::GNUSparse => {
            "a GNU sparse file (sparse files are refused; archive it without --sparse)".into()
        }
        T::Char | T::Block => "a device file (refused)".into(),
        T::Fifo => "a FIFO (refused)".into(),
        T::Continuous => "a contiguous file (refused; archive it as a plain file)".into(),
        T::XGlobalHeader | T::XHeader => "a pax header the archive reader could not apply".into(),
        T::GNULongName | T::GNULongLink => "a GNU long-name record without its entry".into(),
        other => format!(
            "an entry of tar type '{}' (only plain files and folders are accepted)",
            (other.as_byte() as char).escape_default()
        ),
    }
}

/// Why a bundle was not unpacked.
#[derive(Debug, thiserror::Error)]
pub enum BundleError {
    /// The archive is malformed, or holds what a bundle may not (the message says what).
    #[error("{0}")]
    Invalid(String),
    /// Writing a file failed (on `path`).
    #[error("{path}: {source}")]
    Disk {
        /// The file or folder inside the bundle.
        path: String,
        /// The error of the file system.
        source: std::io::Error,
    },
}

/// Unpacks a bundle read from `bytes` into `dest` (which must not exist yet), refusing absolute
/// paths, `..`, links, sparse and special files (anything but plain files and folders), more
/// than `MAX_ENTRIES` entries and more than `max_bytes` of content. Files are copied as they are
/// read, a buffer at a time. Returns the relative paths of the files.
pub fn unpack(bytes: impl Read, dest: &Path, max_bytes: u64) -> Result<Vec<String>, BundleError> {
    let invalid = BundleError::Invalid;
    let disk = |path: &str, source| BundleError::Disk {
        path: path.to_string(),
        source,
    };
    let mut archive = tar::Archive::new(bytes);
    let entries = archive
        .entries()
        .map_err(|e| invalid(format!("not a tar archive: {e}")))?;
    std::fs::create_dir_all(dest).map_err(|e| disk(".", e))?;
    let mut total = 0u64;
    let mut files = Vec::new();
    for (n, entry) in entries.enumerate() {
        if n >= MAX_ENTRIES {
            return Err(invalid(format!(
                "the bundle has more than {MAX_ENTRIES} entries (files and folders)"
            )));
        }
        let mut entry = entry.map_err(|e| invalid(format!("not a tar archive: {e}")))?;
        let path = entry
            .path()
            .map_err(|e| invalid(format!("bad path in bundle: {e}")))?
            .into_owned();
        let shown = path.display().to_string();
        if path
            .components()
            .any(|c| !matches!(c, Component::Normal(_) | Component::CurDir))
        {
            return Err(invalid(format!(
                "'{shown}' in the bundle is not a relative path inside it"
            )));
        }
        let kind = entry.header().entry_type();
        if kind.is_dir() {
            continue;
        }
        if !kind.is_file() {
            return Err(invalid(format!(
                "'{shown}' in the bundle is {}, not a plain file",
                entry_kind(kind)
            )));
        }
        total = total.saturating_add(entry.size());
        if total > max_bytes {
            return Err(invalid(format!(
                "the bundle's files exceed {max_bytes} bytes"
            )));
        }
        let target = dest.join(&path);
        if let Some(parent) = target.parent() {
            std::fs::create_dir_all(parent).map_err(|e| disk(&shown, e))?;
        }
        let mut out = std::fs::File::create(&target).map_err(|e| disk(&shown, e))?;
        // A short or damaged archive fails the read; the file system fails the write.
        let mut buf = vec![0u8; 64 << 10];
        loop {
            let k = entry
                .read(&mut buf)
                .map_err(|e| invalid(format!("'{shown}' in the bundle cannot be read: {e}")))?;
            if k == 0 {
                break;
            }
            std::io::Write::write_all(&mut out, &buf[..k]).map_err(|e| disk(&shown, e))?;
        }
        files.push(
            path.components()
                .filter_map(|c| match c {
                    Component::Normal(s) => s.to_str(),
                    _ => None,
                })
                .collect::<Vec<_>>()
                .join("/"),
        );
    }
    if files.is_empty() {
        return Err(invalid("the bundle holds no files".into()));
    }
    Ok(files)
}

/// Why no scene file of an unpacked bundle was chosen.
#[derive(Debug, thiserror::Error)]
pub enum MainFileError {
    /// The scene file named is not one of the bundle's files.
    #[error("main file '{0}' is not in the bundle")]
    NotInBundle(String),
    /// No top-level file has a scene file's extension.
    #[error("the bundle has no top-level .json, .pbrt or .xml scene file")]
    None,
    /// Several top-level files have one (their names, in the bundle's order).
    #[error("the bundle has several scene files ({}); name one with ?main=", .0.join(", "))]
    Several(Vec<String>),
}

/// The scene file of an unpacked bundle: `main` when given (it must be one of the files), else
/// the only top-level .json / .pbrt / .xml file.
pub fn choose_main(files: &[String], main: Option<&str>) -> Result<String, MainFileError> {
    if let Some(m) = main {
        return files
            .iter()
            .find(|f| f.as_str() == m)
            .cloned()
            .ok_or_else(|| MainFileError::NotInBundle(m.to_string()));
    }
    let candidates: Vec<&String> = files
        .iter()
        .filter(|f| {
            !f.contains('/')
                && [".json", ".pbrt", ".xml"]
                    .iter()
                    .any(|e| f.to_ascii_lowercase().ends_with(e))
        })
        .collect();
    match candidates.as_slice() {
        [one] => Ok((*one).clone()),
        [] => Err(MainFileError::None),
        _ => Err(MainFileError::Several(
            candidates.into_iter().cloned().collect(),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Seek, SeekFrom, Write};

    #[test]
    fn a_file_with_holes_is_packed_as_a_plain_file() {
        let dir = std::env::temp_dir().join(format!("omis-bundle-sparse-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let scene = dir.join("scene.json");
        std::fs::write(&scene, "{}").expect("scene");
        // 1 MiB of hole, then a byte: sparse on file systems that keep holes.
        let holes = dir.join("texture.bin");
        let mut f = std::fs::File::create(&holes).expect("file");
        f.seek(SeekFrom::Start(1 << 20)).expect("seek");
        f.write_all(b"x").expect("write");
        drop(f);
        let (tar, main) = pack_files(&scene, std::slice::from_ref(&holes)).expect("packed");
        assert_eq!(main, "scene.json");
        let mut archive = tar::Archive::new(tar.as_slice());
        for entry in archive.entries().expect("a tar") {
            let entry = entry.expect("entry");
            assert_eq!(entry.header().entry_type(), tar::EntryType::Regular);
            if entry.path().expect("path").as_ref() == Path::new("texture.bin") {
                assert_eq!(entry.size(), (1 << 20) + 1);
            }
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
