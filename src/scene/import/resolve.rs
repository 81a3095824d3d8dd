//! The one way a loader reaches the files a scene names: a [`Resolver`] turns a path written in
//! the scene into a [`SceneFile`] inside the scene's folder and records it, so that the list of
//! files a scene consists of (for bundles) is complete by construction.

use crate::scene::SceneError;
use std::path::{Component, Path, PathBuf};

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
///
/// Paths that are absolute or leave the folder are refused before the file system is asked
/// anything about them, and a path that leaves the folder only through a link gets the same
/// answer, whether or not its target exists: the answers say nothing about files outside.
#[derive(Debug)]
pub(crate) struct Resolver {
    scene_file: PathBuf,
    /// The canonical scene folder, once something was resolved.
    folder: Option<PathBuf>,
    files: Vec<PathBuf>,
}

impl Resolver {
    /// A resolver for the files `scene_file` names (nothing is read yet).
    pub fn new(scene_file: &Path) -> Resolver {
        Resolver {
            scene_file: scene_file.to_path_buf(),
            folder: None,
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
    /// wrote it in errors. Refuses absolute paths, paths that leave the folder (lexically or
    /// through links: the same message either way) and missing files.
    pub fn resolve(&mut self, rel: &str, location: &str) -> Result<SceneFile, SceneError> {
        let err = |m: String| SceneError::new(&self.scene_file, location, m);
        let relp = Path::new(rel);
        // Lexical checks first: nothing outside the folder is looked at.
        if relp.is_absolute() || relp.has_root() {
            return Err(err(format!(
                "'{rel}' is an absolute path; paths must be relative to the scene's folder"
            )));
        }
        if leaves_lexically(relp) {
            return Err(err(leaves_message(rel)));
        }
        let base = match &self.folder {
            Some(f) => f.clone(),
            None => {
                let f = scene_folder(&self.scene_file)
                    .map_err(|e| err(format!("cannot resolve the scene's folder: {e}")))?;
                self.folder = Some(f.clone());
                f
            }
        };
        let canon = match walk(&base, relp) {
            Ok(c) => c,
            Err(Walk::Leaves) => return Err(err(leaves_message(rel))),
            Err(Walk::Missing(e)) => return Err(err(format!("'{rel}' not found ({e})"))),
        };
        if !canon.is_file() {
            return Err(err(format!("'{rel}' is not a file")));
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

fn leaves_message(rel: &str) -> String {
    format!("'{rel}' leaves the scene's folder; refused")
}

/// Why [`walk`] gave up.
enum Walk {
    /// The path, or a link on it, leads outside the folder.
    Leaves,
    /// A component inside the folder does not exist (or cannot be read).
    Missing(std::io::Error),
}

/// Links followed in one resolution before giving up (a loop), as Linux does.
const MAX_LINKS: usize = 40;

/// Resolves `rel` under the canonical folder `base` one component at a time, following links
/// itself, so that nothing outside `base` is ever looked at: a link whose target leaves `base`
/// (lexically) ends the walk before its target is consulted. The result has no links.
fn walk(base: &Path, rel: &Path) -> Result<PathBuf, Walk> {
    // Components still to resolve, the next one last.
    let mut pending: Vec<PathBuf> = rel
        .components()
        .rev()
        .map(|c| PathBuf::from(c.as_os_str()))
        .collect();
    let mut cur = base.to_path_buf();
    let mut links = 0;
    while let Some(c) = pending.pop() {
        match c.components().next() {
            None | Some(Component::CurDir) => {}
            Some(Component::ParentDir) => {
                if cur == base {
                    return Err(Walk::Leaves);
                }
                cur.pop();
            }
            Some(Component::Normal(name)) => {
                let next = cur.join(name);
                let meta = std::fs::symlink_metadata(&next).map_err(Walk::Missing)?;
                if meta.file_type().is_symlink() {
                    links += 1;
                    if links > MAX_LINKS {
                        return Err(Walk::Missing(std::io::Error::other("too many links")));
                    }
                    let target = std::fs::read_link(&next).map_err(Walk::Missing)?;
                    let rest = if target.is_absolute() || target.has_root() {
                        // Only an absolute target inside the folder is followed, from the folder.
                        let t = normalize(&target);
                        match t.strip_prefix(base) {
                            Ok(r) => {
                                cur = base.to_path_buf();
                                r.to_path_buf()
                            }
                            Err(_) => return Err(Walk::Leaves),
                        }
                    } else {
                        target
                    };
                    pending.extend(
                        rest.components()
                            .rev()
                            .map(|c| PathBuf::from(c.as_os_str())),
                    );
                } else {
                    if !meta.is_dir() && pending.iter().any(|p| p.as_os_str() != ".") {
                        let e = std::io::Error::from(std::io::ErrorKind::NotADirectory);
                        return Err(Walk::Missing(e));
                    }
                    cur = next;
                }
            }
            Some(Component::RootDir | Component::Prefix(_)) => return Err(Walk::Leaves),
        }
    }
    Ok(cur)
}

/// `p` with `.` and `..` applied lexically (for absolute link targets).
fn normalize(p: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in p.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                out.pop();
            }
            other => out.push(other.as_os_str()),
        }
    }
    out
}

/// True when the `..` components of `rel` climb above its start (without looking at links).
fn leaves_lexically(rel: &Path) -> bool {
    let mut depth = 0usize;
    for c in rel.components() {
        match c {
            Component::Normal(_) => depth += 1,
            Component::CurDir => {}
            Component::ParentDir => match depth.checked_sub(1) {
                Some(d) => depth = d,
                None => return true,
            },
            Component::RootDir | Component::Prefix(_) => return true,
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lexical_escapes_are_found_without_the_file_system() {
        for p in ["..", "../a", "a/../../b", "./../a", "a/./../.."] {
            assert!(leaves_lexically(Path::new(p)), "{p}");
        }
        for p in ["a", "a/..", "a/b/../c", "./a", "a/../b/../c"] {
            assert!(!leaves_lexically(Path::new(p)), "{p}");
        }
        // A folder that does not exist is never consulted for these.
        let mut r = Resolver::new(Path::new("/nonexistent-omis-folder/scene.json"));
        let e = r.resolve("../x.obj", "here").unwrap_err();
        assert_eq!(e.message, "'../x.obj' leaves the scene's folder; refused");
        let e = r.resolve("/etc/passwd", "here").unwrap_err();
        assert!(e.message.contains("absolute"), "{e}");
        assert!(r.files().is_empty());
    }

    #[cfg(unix)]
    #[test]
    fn links_are_followed_inside_the_folder_only() {
        use std::os::unix::fs::symlink;
        let root = std::env::temp_dir().join(format!("omis-resolve-links-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let inner = root.join("inner");
        std::fs::create_dir_all(inner.join("sub")).unwrap();
        std::fs::write(root.join("secret.obj"), "x").unwrap();
        std::fs::write(inner.join("sub/mesh.obj"), "x").unwrap();
        symlink("..", inner.join("up")).unwrap();
        symlink(&root, inner.join("abs")).unwrap();
        symlink("../gone", inner.join("dangling")).unwrap();
        symlink("sub", inner.join("here")).unwrap();
        symlink(inner.join("sub"), inner.join("here_abs")).unwrap();
        symlink("loop", inner.join("loop")).unwrap();
        let mut r = Resolver::new(&inner.join("scene.json"));
        let canon = inner.canonicalize().unwrap().join("sub/mesh.obj");
        for rel in ["here/mesh.obj", "here_abs/mesh.obj", "sub/../here/mesh.obj"] {
            assert_eq!(r.resolve(rel, "x").unwrap().path(), canon, "{rel}");
        }
        let leaves = |r: &mut Resolver, rel: &str| r.resolve(rel, "x").unwrap_err().message;
        for rel in [
            "up/secret.obj",
            "abs/secret.obj",
            "dangling",
            "dangling/x.obj",
        ] {
            assert_eq!(leaves(&mut r, rel), leaves_message(rel), "{rel}");
        }
        // The same answers when the target outside does not exist.
        std::fs::remove_file(root.join("secret.obj")).unwrap();
        for rel in ["up/secret.obj", "abs/secret.obj"] {
            assert_eq!(leaves(&mut r, rel), leaves_message(rel), "{rel}");
        }
        assert!(leaves(&mut r, "loop").contains("not found"));
        assert!(leaves(&mut r, "sub/mesh.obj/x").contains("not found"));
        assert!(leaves(&mut r, "sub").contains("not a file"));
        assert_eq!(r.files(), vec![canon]);
        let _ = std::fs::remove_dir_all(&root);
    }
}
