//! Output files are checked before the work that fills them: a render must not run for an hour
//! to fail on a path it could never write.

use anyhow::{Context, Result, bail};
use std::fs::OpenOptions;
use std::path::Path;

/// Fails (naming `flag` and the path) unless `path` can be written: its folder exists and takes
/// a new file, and the path is not a folder or a read-only file. Leaves no file behind.
pub(crate) fn check_writable(path: &Path, flag: &str) -> Result<()> {
    if path.is_dir() {
        bail!("{flag} {} is a folder, not a file", path.display());
    }
    if path.exists() {
        OpenOptions::new()
            .append(true)
            .open(path)
            .with_context(|| format!("{flag} {} cannot be written", path.display()))?;
        return Ok(());
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        bail!(
            "{flag} {}: the folder {} does not exist",
            path.display(),
            dir.display()
        );
    }
    let probe = dir.join(format!(".omis-write-check-{}", std::process::id()));
    OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
        .with_context(|| {
            format!(
                "{flag} {}: cannot write in {}",
                path.display(),
                dir.display()
            )
        })?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_folders_folders_and_read_only_files_are_refused() {
        let dir = std::env::temp_dir().join(format!("omis-out-check-{}", uuid::Uuid::new_v4()));
        std::fs::create_dir_all(&dir).unwrap();
        assert!(check_writable(&dir.join("a.exr"), "--out").is_ok());
        assert!(!dir.join("a.exr").exists(), "the check leaves no file");
        let e = check_writable(&dir.join("no/such/a.exr"), "--out").unwrap_err();
        assert!(e.to_string().contains("does not exist"), "{e}");
        let e = check_writable(&dir, "--out").unwrap_err();
        assert!(e.to_string().contains("is a folder"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
