//! The coordinator's files beside its database: where each one lies under the data folder
//! (`Paths`), and the ways they are written: whole and atomically (`write_atomic`,
//! `write_replacing`), or in place (`write_at`, the tile checkpoints' slots).

use std::path::{Path, PathBuf};

/// Where a coordinator keeps its files.
#[derive(Clone, Debug)]
pub(crate) struct Paths {
    pub root: PathBuf,
}

impl Paths {
    pub fn db(&self) -> PathBuf {
        self.root.join("omis.sqlite")
    }
    pub fn job(&self, id: &str) -> PathBuf {
        self.root.join("jobs").join(id)
    }
    /// The log of the uploaded results of pass `pass`: one file for a job's even passes and one
    /// for its odd ones, each record written after the one before, and a log rewritten from its
    /// start by the pass two after the one it held (`ResultLogs`); the store records where the
    /// accepted attempt of each task lies.
    pub fn result_log(&self, id: &str, pass: u32) -> PathBuf {
        self.job(id).join(format!("results-{}.log", pass % 2))
    }
    /// Result logs of ended jobs, kept to be written again (`ResultLogs`).
    pub fn spare_logs(&self) -> PathBuf {
        self.root.join("spare-logs")
    }
    /// The folder of a job's tile checkpoints.
    pub fn tiles_dir(&self, id: &str) -> PathBuf {
        self.job(id).join("tiles")
    }
    /// The merged accumulators of the tiles of one band (row of tiles) of a job: two slots per
    /// tile, rewritten in place (`merge::checkpoint_slot` says where).
    pub fn band_checkpoints(&self, id: &str, band: u32) -> PathBuf {
        self.tiles_dir(id).join(format!("band-{band:06}.acc"))
    }
    pub fn output(&self, id: &str, name: &str) -> PathBuf {
        self.job(id).join(name)
    }
    pub fn scene(&self, id: &str) -> PathBuf {
        self.root.join("scenes").join(id)
    }
    pub fn reference(&self, id: &str) -> PathBuf {
        self.reference_dir().join(format!("{id}.exr"))
    }
    /// The folder of uploaded reference images.
    pub fn reference_dir(&self) -> PathBuf {
        self.root.join("references")
    }
    /// Whether the folder holds jobs or scenes (of an earlier database).
    pub fn holds_jobs_or_scenes(&self) -> bool {
        ["jobs", "scenes"].iter().any(|d| {
            std::fs::read_dir(self.root.join(d)).is_ok_and(|mut entries| entries.next().is_some())
        })
    }
}

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename).
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_replacing(path, bytes, true)
}

/// Writes `bytes` to `path` atomically (temporary file, rename), fsync'd when `durable`.
/// Without it a power cut may leave the file empty or damaged (never half-renamed): fine for a
/// task result, which a merge that cannot read it renders again; not for what a merge produced.
pub(crate) fn write_replacing(path: &Path, bytes: &[u8], durable: bool) -> std::io::Result<()> {
    use std::io::Write;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = path.with_extension(format!("tmp{}.{n}", std::process::id()));
    {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        if durable {
            f.sync_all()?;
        }
    }
    std::fs::rename(&tmp, path)
}

/// `open(path)`, making the file's folder first when it is missing.
pub(crate) fn open_creating<F>(
    path: &Path,
    open: impl Fn(&Path) -> std::io::Result<F>,
) -> std::io::Result<F> {
    match open(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if let Some(dir) = path.parent() {
                std::fs::create_dir_all(dir)?;
            }
            open(path)
        }
        f => f,
    }
}

/// Overwrites bytes `at..` of the file at `path` with `bytes` in place (the file is created
/// with its folder when missing; no new file or rename once it exists), fsync'd when `durable`.
/// A crash in the middle leaves them torn: only for what carries a checksum and has a second
/// copy (the tile checkpoints' two slots).
pub(crate) fn write_at(path: &Path, at: u64, bytes: &[u8], durable: bool) -> std::io::Result<()> {
    use std::io::{Seek, SeekFrom, Write};
    let mut f = open_creating(path, |p| {
        std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(false)
            .open(p)
    })?;
    f.seek(SeekFrom::Start(at))?;
    f.write_all(bytes)?;
    if durable {
        f.sync_all()?;
    }
    Ok(())
}
