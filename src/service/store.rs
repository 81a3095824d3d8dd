//! The coordinator's durable state: jobs, tasks (leases), workers, the relMSE series and the
//! event log, in one embedded SQLite database (WAL) under the data folder. Outputs and task
//! results are files beside it (see `Paths`).

use super::log_file::{self, LogFile};
use super::protocol::{
    EventKind, JobState, SeriesPoint, TaskKind, TaskState, WorkerInfo, WorkerState, WorkerTask,
};
use rusqlite::{Connection, OptionalExtension, params};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{SystemTime, UNIX_EPOCH};

/// Seconds since the Unix epoch.
pub(crate) fn now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

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
        self.root.join("references").join(format!("{id}.exr"))
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

/// Where the next record of each result log goes (`Paths::result_log`).
///
/// A log is not deleted and written afresh each pass but rewritten in place, from its start,
/// by the pass two after the one it held, once that pass is recorded (no merge reads it any
/// more; `jobs::ensure_passes` creates a pass's tasks only once the pass two before it is
/// recorded). A log no later pass of its job will write is not deleted either but kept as a
/// spare (up to `SPARE_LOGS` of them, in `Paths::spare_logs`), which the next new log takes
/// instead of a new file, as PostgreSQL recycles its WAL segments. A file written afresh takes
/// new page-cache pages, and on a virtual machine that hands freed memory back to its host each
/// new page is faulted in on the host too: writing 850 MB (a 1080p BDPT pass's results) into a
/// new file took 2.6-2.8 s of system CPU on this project's benchmark machine, into the same
/// file again 0.16-0.19 s; a coordinator's second and later balance jobs took a fifth less CPU
/// (BENCHMARKS.md #12, stop 35). Since the logs go around the page cache (`log_file`, stop 36)
/// that gain is gone (jobs 1 / 2 / 3: 2.63 / 2.62 / 2.46 s): recycling pays where a file system
/// refuses direct I/O and the logs fall back to the page cache. Records are not fsync'd: a
/// record damaged by a power cut (or found holding an older pass's bytes) fails its checksums
/// when merged, and its task is rendered again.
#[derive(Default)]
pub(crate) struct ResultLogs {
    /// Per job, per log (pass parity): the pass writing it now and where its records end.
    cursors: Mutex<HashMap<String, [Option<LogCursor>; 2]>>,
}

/// Spare result logs kept at most, and their bytes at most (a log is as long as the longest
/// pass's results it held; a longer one is deleted, as every log was before).
const SPARE_LOGS: usize = 4;
const SPARE_LOG_BYTES: u64 = 4 << 30;

#[derive(Clone, Copy)]
struct LogCursor {
    pass: u32,
    end: u64,
}

impl ResultLogs {
    /// Writes `bytes`, a result of pass `pass` of job `job` (whose tile checkpoints hold
    /// `recorded` passes: no merge reads an earlier pass's results), into its log and returns
    /// where they lie. They go after the pass's last record; at the start of the log when the
    /// pass is the first to write it since the checkpoints hold the pass it held; and at the end
    /// of the file when this process does not know the log (after a restart), when the pass it
    /// holds is still read, or when the result is of an older pass than the log's (a stale
    /// attempt, which the store will refuse, or a result rendered again because its record was
    /// found damaged). One write at a time: every log's cursor is held meanwhile.
    pub fn write(
        &self,
        paths: &Paths,
        job: &str,
        pass: u32,
        recorded: u32,
        bytes: &[u8],
    ) -> std::io::Result<std::ops::Range<u64>> {
        let mut cursors = self.cursors.lock().unwrap_or_else(|e| e.into_inner());
        let slot = &mut cursors.entry(job.to_string()).or_default()[(pass % 2) as usize];
        let path = paths.result_log(job, pass);
        // Records start at multiples of `log_file::ALIGN` (direct I/O).
        let file_end = || match std::fs::metadata(&path) {
            Ok(m) => Ok(log_file::align_up(m.len())),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(0),
            Err(e) => Err(e),
        };
        let (at, moves) = match *slot {
            Some(c) if c.pass == pass => (c.end, true),
            Some(c) if c.pass < pass && recorded > c.pass => (0, true),
            Some(c) if c.pass > pass => (file_end()?, false),
            _ => match file_end()? {
                // A new log: a spare's old bytes are never read (no record points there).
                0 => {
                    take_spare(paths, &path);
                    (0, true)
                }
                end => (end, true),
            },
        };
        LogFile::open_write(&path)?.write_at(at, bytes)?;
        let end = at + bytes.len() as u64;
        if moves {
            *slot = Some(LogCursor {
                pass,
                end: log_file::align_up(end),
            });
        }
        Ok(at..end)
    }

    /// Gives up the log of recorded pass `pass` of job `job` when no later pass of the job will
    /// write it (`reused`: false): kept as a spare for another job's, or deleted (`retire`);
    /// else it waits for pass `pass + 2`.
    pub fn release(&self, paths: &Paths, job: &str, pass: u32, reused: bool) {
        if reused {
            return;
        }
        let mut cursors = self.cursors.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(logs) = cursors.get_mut(job) {
            logs[(pass % 2) as usize] = None;
        }
        retire(paths, &paths.result_log(job, pass));
    }

    /// Forgets job `job`'s logs (it ended) and keeps them as spares.
    pub fn remove(&self, paths: &Paths, job: &str) {
        let mut cursors = self.cursors.lock().unwrap_or_else(|e| e.into_inner());
        cursors.remove(job);
        for parity in 0..2 {
            retire(paths, &paths.result_log(job, parity));
        }
    }
}

/// Moves a spare log (if there is one) to `path`, which does not exist.
fn take_spare(paths: &Paths, path: &Path) {
    let Ok(dir) = std::fs::read_dir(paths.spare_logs()) else {
        return;
    };
    if path
        .parent()
        .is_some_and(|p| std::fs::create_dir_all(p).is_err())
    {
        return;
    }
    for spare in dir.flatten() {
        if std::fs::rename(spare.path(), path).is_ok() {
            return;
        }
    }
}

/// Keeps the log at `path` as a spare, or deletes it when `SPARE_LOGS` are kept already or it
/// would take the spares past `SPARE_LOG_BYTES`.
fn retire(paths: &Paths, path: &Path) {
    let Ok(len) = std::fs::metadata(path).map(|m| m.len()) else {
        return;
    };
    let dir = paths.spare_logs();
    let spares: Vec<u64> = std::fs::read_dir(&dir).map_or(Vec::new(), |d| {
        d.flatten()
            .map(|e| e.metadata().map_or(0, |m| m.len()))
            .collect()
    });
    if spares.len() < SPARE_LOGS
        && spares.iter().sum::<u64>() + len <= SPARE_LOG_BYTES
        && std::fs::create_dir_all(&dir).is_ok()
        && std::fs::rename(path, dir.join(format!("{}.log", uuid::Uuid::new_v4()))).is_ok()
    {
        return;
    }
    let _ = std::fs::remove_file(path);
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

/// A job as stored.
#[derive(Clone, Debug)]
pub(crate) struct JobRow {
    pub id: String,
    pub name: Option<String>,
    pub state: JobState,
    pub error: Option<String>,
    /// The request's settings (JSON) and their resolution against the scene (JSON).
    pub settings: String,
    pub resolved: String,
    pub scene_id: String,
    pub scene_main: String,
    pub reference: Option<String>,
    pub created_at: f64,
    pub started_at: Option<f64>,
    pub finished_at: Option<f64>,
    pub passes_done: u32,
    pub spp_done: u32,
    pub samples: i64,
    pub rays: i64,
    pub non_finite: i64,
    pub accum_bytes: i64,
    pub result_bytes: i64,
}

/// A task (one tile of one pass) as stored.
#[derive(Clone, Debug)]
pub(crate) struct TaskRow {
    pub id: i64,
    pub job_id: String,
    pub pass: u32,
    pub tile: u32,
    pub s0: u32,
    pub s1: u32,
    pub state: TaskState,
    pub attempt: u32,
    pub worker_id: Option<String>,
    /// Where the accepted result lies in its pass's result log (done render tasks).
    pub result: Option<std::ops::Range<u64>>,
    /// Render or merge. A merge task's `tile` is its band group's index and `s0 .. s1` are the
    /// group's bands (`TaskRow::bands`).
    pub kind: TaskKind,
}

impl TaskRow {
    /// The bands of a merge task.
    pub fn bands(&self) -> std::ops::Range<u32> {
        self.s0..self.s1
    }
}

/// A recorded job event.
#[derive(Clone, Debug)]
pub(crate) struct EventRow {
    pub id: i64,
    pub job_id: String,
    pub kind: EventKind,
    pub data: serde_json::Value,
    pub at: f64,
}

/// What [`JobStore::complete`] recorded.
#[derive(Clone, Debug)]
pub(crate) struct Completed {
    /// The event recorded with the task.
    pub event: EventRow,
    /// Whether render tasks of the task's pass are still queued or leased.
    pub pass_open: bool,
}

/// The database of a coordinator.
pub(crate) struct SqliteStore {
    conn: Connection,
}

const SCHEMA: &str = "
PRAGMA journal_mode = WAL;
PRAGMA synchronous = NORMAL;
PRAGMA foreign_keys = ON;
CREATE TABLE IF NOT EXISTS jobs (
  id TEXT PRIMARY KEY,
  seq INTEGER NOT NULL,
  name TEXT,
  state TEXT NOT NULL,
  error TEXT,
  settings TEXT NOT NULL,
  resolved TEXT NOT NULL,
  scene_id TEXT NOT NULL,
  scene_main TEXT NOT NULL,
  reference TEXT,
  created_at REAL NOT NULL,
  started_at REAL,
  finished_at REAL,
  passes_done INTEGER NOT NULL DEFAULT 0,
  spp_done INTEGER NOT NULL DEFAULT 0,
  samples INTEGER NOT NULL DEFAULT 0,
  rays INTEGER NOT NULL DEFAULT 0,
  non_finite INTEGER NOT NULL DEFAULT 0,
  accum_bytes INTEGER NOT NULL DEFAULT 0,
  result_bytes INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS workers (
  id TEXT PRIMARY KEY,
  name TEXT NOT NULL,
  threads INTEGER NOT NULL,
  version TEXT NOT NULL,
  registered_at REAL NOT NULL,
  last_seen REAL NOT NULL,
  state TEXT NOT NULL,
  tasks_done INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS series (
  job_id TEXT NOT NULL REFERENCES jobs(id),
  pass INTEGER NOT NULL,
  spp INTEGER NOT NULL,
  seconds REAL NOT NULL,
  relmse REAL,
  PRIMARY KEY (job_id, pass)
);
CREATE TABLE IF NOT EXISTS events (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  job_id TEXT NOT NULL,
  kind TEXT NOT NULL,
  data TEXT NOT NULL,
  at REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS events_job ON events (job_id, id);
";

/// The tasks table: render tasks (`kind` 'render', one per tile and pass) and merge tasks
/// ('merge', one per band group of a finished pass: `tile` is the group's index, s0 .. s1 its
/// bands). The queue index orders a job's queued tasks merges first ('merge' < 'render'), then
/// by pass and tile.
const TASKS_TABLE: &str = "
CREATE TABLE IF NOT EXISTS tasks (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  job_id TEXT NOT NULL REFERENCES jobs(id),
  kind TEXT NOT NULL DEFAULT 'render',
  pass INTEGER NOT NULL,
  tile INTEGER NOT NULL,
  s0 INTEGER NOT NULL,
  s1 INTEGER NOT NULL,
  state TEXT NOT NULL,
  attempt INTEGER NOT NULL DEFAULT 0,
  worker_id TEXT,
  lease_expires REAL,
  failures INTEGER NOT NULL DEFAULT 0,
  last_error TEXT,
  result_at INTEGER,
  result_len INTEGER,
  UNIQUE (job_id, pass, kind, tile)
);
CREATE INDEX IF NOT EXISTS tasks_queue ON tasks (state, job_id, kind, pass, tile);
";

/// The columns a tasks table of an older data folder (before merge tasks) shares with today's.
const TASKS_V1_COLS: &str = "id, job_id, pass, tile, s0, s1, state, attempt, worker_id, \
    lease_expires, failures, last_error, result_at, result_len";

const JOB_COLS: &str = "id, name, state, error, settings, resolved, scene_id, scene_main, \
    reference, created_at, started_at, finished_at, passes_done, spp_done, samples, rays, \
    non_finite, accum_bytes, result_bytes";

const TASK_COLS: &str =
    "id, job_id, pass, tile, s0, s1, state, attempt, worker_id, result_at, result_len, kind";

fn job_row(r: &rusqlite::Row) -> rusqlite::Result<JobRow> {
    Ok(JobRow {
        id: r.get(0)?,
        name: r.get(1)?,
        state: r.get(2)?,
        error: r.get(3)?,
        settings: r.get(4)?,
        resolved: r.get(5)?,
        scene_id: r.get(6)?,
        scene_main: r.get(7)?,
        reference: r.get(8)?,
        created_at: r.get(9)?,
        started_at: r.get(10)?,
        finished_at: r.get(11)?,
        passes_done: r.get(12)?,
        spp_done: r.get(13)?,
        samples: r.get(14)?,
        rays: r.get(15)?,
        non_finite: r.get(16)?,
        accum_bytes: r.get(17)?,
        result_bytes: r.get(18)?,
    })
}

fn task_row(r: &rusqlite::Row) -> rusqlite::Result<TaskRow> {
    Ok(TaskRow {
        id: r.get(0)?,
        job_id: r.get(1)?,
        pass: r.get(2)?,
        tile: r.get(3)?,
        s0: r.get(4)?,
        s1: r.get(5)?,
        state: r.get(6)?,
        attempt: r.get(7)?,
        worker_id: r.get(8)?,
        result: match (r.get::<_, Option<i64>>(9)?, r.get::<_, Option<i64>>(10)?) {
            (Some(at), Some(len)) if at >= 0 && len >= 0 => Some(at as u64..(at + len) as u64),
            _ => None,
        },
        kind: r.get(11)?,
    })
}

/// One row of `sql` (a statement prepared once per connection and cached).
fn cached_row<T>(
    conn: &Connection,
    sql: &str,
    p: impl rusqlite::Params,
    f: impl FnOnce(&rusqlite::Row<'_>) -> rusqlite::Result<T>,
) -> rusqlite::Result<T> {
    conn.prepare_cached(sql)?.query_row(p, f)
}

/// Runs `sql` (a statement prepared once per connection and cached); rows changed.
fn cached_exec(conn: &Connection, sql: &str, p: impl rusqlite::Params) -> rusqlite::Result<usize> {
    conn.prepare_cached(sql)?.execute(p)
}

/// Inserts an event of `job` (inside the caller's transaction, if any).
fn insert_event(
    conn: &Connection,
    job: &str,
    kind: EventKind,
    data: &serde_json::Value,
) -> rusqlite::Result<EventRow> {
    let at = now();
    cached_exec(
        conn,
        "INSERT INTO events (job_id, kind, data, at) VALUES (?1, ?2, ?3, ?4)",
        params![job, kind, data.to_string(), at],
    )?;
    Ok(EventRow {
        id: conn.last_insert_rowid(),
        job_id: job.to_string(),
        kind,
        data: data.clone(),
        at,
    })
}

/// A store's error, whatever the engine.
#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub(crate) struct StoreError {
    pub message: String,
    /// The disk holding the store is full (the API answers 507).
    pub disk_full: bool,
}

impl StoreError {
    /// An error of the store's own making.
    pub fn new(message: impl Into<String>) -> StoreError {
        StoreError {
            message: message.into(),
            disk_full: false,
        }
    }
}

impl From<rusqlite::Error> for StoreError {
    fn from(e: rusqlite::Error) -> Self {
        StoreError {
            disk_full: e.sqlite_error_code() == Some(rusqlite::ErrorCode::DiskFull),
            message: e.to_string(),
        }
    }
}

/// The result of a store query.
pub(crate) type StoreResult<T> = Result<T, StoreError>;

/// A new job's row.
pub(crate) struct NewJob<'a> {
    pub id: &'a str,
    pub name: Option<&'a str>,
    pub settings: &'a str,
    pub resolved: &'a str,
    pub scene_id: &'a str,
    pub scene_main: &'a str,
    pub reference: Option<&'a str>,
    pub accum_bytes: i64,
}

// The states bound as parameters wherever a statement names one.
const J_QUEUED: JobState = JobState::Queued;
const J_RUNNING: JobState = JobState::Running;
const T_QUEUED: TaskState = TaskState::Queued;
const T_LEASED: TaskState = TaskState::Leased;
const T_DONE: TaskState = TaskState::Done;
const K_RENDER: TaskKind = TaskKind::Render;
const K_MERGE: TaskKind = TaskKind::Merge;

/// The first queued task of a job (`lease`) that worker ?3 has not failed: merges first, then
/// passes and tiles in order.
const NEXT_QUEUED: &str = "SELECT id FROM tasks WHERE state = ?1 AND job_id = ?2 \
     AND NOT EXISTS (SELECT 1 FROM failures f WHERE f.task_id = tasks.id AND f.worker_id = ?3) \
     ORDER BY kind, pass, tile LIMIT 1";

/// Failed tasks of one job (distinct) after which a worker gets none of its tasks any more
/// (Flamenco's blocklist threshold).
pub(crate) const BLOCKLIST_AFTER: i64 = 3;
/// Jobs whose tasks a worker failed since its last delivered result after which it is marked
/// unhealthy and leases nothing until it registers again.
pub(crate) const UNHEALTHY_AFTER_JOBS: i64 = 3;

/// A failed or lost attempt, as [`JobStore::fail`] and [`JobStore::expire_leases`] record it.
#[derive(Clone, Debug)]
pub(crate) struct Failure {
    /// The task, as it was when the attempt ended.
    pub task: TaskRow,
    /// The worker that held it.
    pub worker: String,
    /// Failed and lost attempts of the task so far, this one included.
    pub failures: u32,
    /// Lost attempts of the task so far (leases that expired), this one included if lost.
    pub lost: u32,
    /// What went wrong.
    pub error: String,
    /// How the attempt ended.
    pub outcome: Outcome,
}

/// How an attempt ended without a result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Outcome {
    /// The worker reported an error (or its result was refused).
    Failed,
    /// The worker went silent: its lease expired.
    Lost,
}

impl Outcome {
    fn as_str(self) -> &'static str {
        match self {
            Outcome::Failed => "failed",
            Outcome::Lost => "lost",
        }
    }
}

/// The migrations after the base schema, in order: `PRAGMA user_version` counts those applied.
/// A database from a newer omis (a higher version) is refused.
const MIGRATIONS: &[&str] = &[
    // 1: failed and lost attempts (what keeps a task from a worker that failed it), per-job
    // blocklists, and a worker's health.
    "CREATE TABLE failures (
       task_id INTEGER NOT NULL,
       attempt INTEGER NOT NULL,
       job_id TEXT NOT NULL,
       worker_id TEXT NOT NULL,
       outcome TEXT NOT NULL,
       error TEXT NOT NULL,
       at REAL NOT NULL,
       PRIMARY KEY (task_id, attempt)
     );
     CREATE INDEX failures_worker ON failures (worker_id, task_id);
     CREATE INDEX failures_job ON failures (job_id, worker_id);
     CREATE TABLE blocklist (
       job_id TEXT NOT NULL,
       worker_id TEXT NOT NULL,
       since REAL NOT NULL,
       reason TEXT NOT NULL,
       PRIMARY KEY (job_id, worker_id)
     );
     ALTER TABLE workers ADD COLUMN unhealthy TEXT;
     ALTER TABLE workers ADD COLUMN last_done_at REAL;",
];

/// Records attempt `task.attempt` of `task` as `outcome` on `worker` and requeues the task; then
/// blocklists the worker for the job after `BLOCKLIST_AFTER` failed tasks of it, and marks it
/// unhealthy after failures in `UNHEALTHY_AFTER_JOBS` jobs since its last result. Runs inside
/// the caller's transaction.
fn record_failure(
    conn: &Connection,
    task: &TaskRow,
    worker: &str,
    outcome: Outcome,
    error: &str,
) -> StoreResult<Failure> {
    let t = now();
    cached_exec(
        conn,
        "UPDATE tasks SET state = ?2, worker_id = NULL, lease_expires = NULL, \
         failures = failures + 1, last_error = ?3 WHERE id = ?1",
        params![task.id, T_QUEUED, error],
    )?;
    cached_exec(
        conn,
        "INSERT OR REPLACE INTO failures (task_id, attempt, job_id, worker_id, outcome, error, at) \
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
        params![
            task.id,
            task.attempt,
            task.job_id,
            worker,
            outcome.as_str(),
            error,
            t
        ],
    )?;
    let (failures, lost): (u32, u32) = cached_row(
        conn,
        "SELECT (SELECT failures FROM tasks WHERE id = ?1), \
         (SELECT COUNT(*) FROM failures WHERE task_id = ?1 AND outcome = 'lost')",
        [task.id],
        |r| Ok((r.get(0)?, r.get(1)?)),
    )?;
    let failed_tasks: i64 = cached_row(
        conn,
        "SELECT COUNT(DISTINCT task_id) FROM failures WHERE job_id = ?1 AND worker_id = ?2",
        params![task.job_id, worker],
        |r| r.get(0),
    )?;
    if failed_tasks >= BLOCKLIST_AFTER {
        cached_exec(
            conn,
            "INSERT OR IGNORE INTO blocklist (job_id, worker_id, since, reason) \
             VALUES (?1, ?2, ?3, ?4)",
            params![
                task.job_id,
                worker,
                t,
                format!("failed {failed_tasks} tasks of the job; last: {error}")
            ],
        )?;
    }
    let failed_jobs: i64 = cached_row(
        conn,
        "SELECT COUNT(DISTINCT job_id) FROM failures WHERE worker_id = ?1 \
         AND at > COALESCE((SELECT last_done_at FROM workers WHERE id = ?1), 0)",
        [worker],
        |r| r.get(0),
    )?;
    if failed_jobs >= UNHEALTHY_AFTER_JOBS {
        cached_exec(
            conn,
            "UPDATE workers SET unhealthy = ?2 WHERE id = ?1 AND unhealthy IS NULL",
            params![
                worker,
                format!("failed tasks of {failed_jobs} jobs since its last result; last: {error}")
            ],
        )?;
    }
    Ok(Failure {
        task: task.clone(),
        worker: worker.to_string(),
        failures,
        lost,
        error: error.to_string(),
        outcome,
    })
}

/// Applies the migrations `conn` has not had, each in its own transaction.
fn migrate(conn: &Connection) -> StoreResult<()> {
    let have: i64 = conn.query_row("PRAGMA user_version", [], |r| r.get(0))?;
    let known = MIGRATIONS.len() as i64;
    if have > known {
        return Err(StoreError::new(format!(
            "the database has schema version {have}, newer than this omis knows ({known}); \
             run the omis that wrote it"
        )));
    }
    for (k, m) in MIGRATIONS.iter().enumerate().skip(have.max(0) as usize) {
        conn.execute_batch(&format!(
            "BEGIN; {m}; PRAGMA user_version = {}; COMMIT;",
            k + 1
        ))?;
    }
    Ok(())
}

/// The queries the coordinator makes of its job store: jobs, their tasks pass by pass,
/// leases, workers, the relMSE series and the event log. SQLite (`SqliteStore`) is the embedded
/// store; a shared one (PostgreSQL, so that several coordinators serve one queue) implements
/// the same trait. Every method is one short transaction.
pub(crate) trait JobStore: Send {
    /// Adds a job, `queued`, after every earlier one.
    fn insert_job(&self, j: &NewJob) -> StoreResult<()>;
    /// A job by id.
    fn job(&self, id: &str) -> StoreResult<Option<JobRow>>;
    /// Every job, oldest first.
    fn jobs(&self) -> StoreResult<Vec<JobRow>>;
    /// Jobs still to be worked on (queued or running).
    fn active_jobs(&self) -> StoreResult<Vec<JobRow>>;
    /// Moves an active (queued or running) job to `state`; false when the job had already
    /// ended (a cancelled job stays cancelled).
    fn set_job_state(&self, id: &str, state: JobState, error: Option<&str>) -> StoreResult<bool>;
    /// Replaces an active job's resolved settings (a time-budget job's fitted last pass,
    /// `Resolved::fit_to_budget`); false when the job had ended.
    fn set_job_resolved(&self, id: &str, resolved: &str) -> StoreResult<bool>;
    /// Gives back every task a worker holds (it said it is leaving).
    fn release_worker(&self, worker: &str) -> StoreResult<usize>;
    /// True when `task_id` was ever issued (tasks of merged passes are deleted).
    fn task_existed(&self, task_id: i64) -> StoreResult<bool>;
    /// Records a merged pass and adds its work counters `stats` (once: only when the job had
    /// merged `passes_done - 1` passes); the task rows of the passes before `held` (those the
    /// tile checkpoints hold: no merge reads their results again) are no longer needed.
    fn pass_merged(
        &self,
        id: &str,
        passes_done: u32,
        spp_done: u32,
        held: u32,
        stats: &crate::film::RayStats,
    ) -> StoreResult<()>;
    /// Records the relMSE point of a merged pass.
    fn add_series(&self, id: &str, p: &SeriesPoint) -> StoreResult<()>;
    /// A job's relMSE series, pass by pass.
    fn series(&self, id: &str) -> StoreResult<Vec<SeriesPoint>>;
    /// Creates the tasks of `tiles` of one pass in one transaction (idempotent). Callers create
    /// a pass in bounded chunks, in tile order, so that a pass with tile `t` has every tile
    /// before it.
    fn create_tasks(
        &self,
        id: &str,
        pass: u32,
        tiles: std::ops::Range<u32>,
        samples: std::ops::Range<u32>,
    ) -> StoreResult<()>;
    /// Creates the merge tasks of a finished pass, one per band group (`groups`: each group's
    /// bands), in one transaction (idempotent).
    fn create_merge_tasks(
        &self,
        id: &str,
        pass: u32,
        groups: &[std::ops::Range<u32>],
    ) -> StoreResult<()>;
    /// The merge tasks of a pass, in group order (empty: its merge has not begun).
    fn merge_tasks(&self, id: &str, pass: u32) -> StoreResult<Vec<TaskRow>>;
    /// Deletes the merge tasks of a pass (a result turned out unreadable: the pass is not
    /// complete any more).
    fn delete_merge_tasks(&self, id: &str, pass: u32) -> StoreResult<()>;
    /// Marks a merge task done if it is still this worker's current attempt.
    fn complete_merge(&self, task_id: i64, attempt: u32, worker: &str) -> StoreResult<bool>;
    /// The highest tile of a pass that has its render task (None: the pass has none).
    fn last_tile(&self, id: &str, pass: u32) -> StoreResult<Option<u32>>;
    /// The highest pass with tasks, if any.
    fn last_pass(&self, id: &str) -> StoreResult<Option<u32>>;
    /// Whether a render task of the pass is still queued or leased.
    fn pass_open(&self, id: &str, pass: u32) -> StoreResult<bool>;
    /// Done render tasks of a job's unmerged passes.
    fn tasks_done(&self, id: &str) -> StoreResult<u32>;
    /// The render tasks of a pass in tile order.
    fn pass_tasks(&self, id: &str, pass: u32) -> StoreResult<Vec<TaskRow>>;
    /// A task by id.
    fn task(&self, task_id: i64) -> StoreResult<Option<TaskRow>>;
    /// Puts a task back in the queue (its result could not be merged).
    fn requeue(&self, task_id: i64) -> StoreResult<()>;
    /// Leases the first queued task of the oldest active job to `worker`: its merge tasks
    /// first, then its render tasks, passes in order; the worker is marked busy in the same
    /// transaction.
    fn lease(&self, worker: &str, lease_s: f64) -> StoreResult<Option<TaskRow>>;
    /// Extends a lease; false when the task is no longer this worker's attempt.
    fn extend(&self, task_id: i64, attempt: u32, worker: &str, lease_s: f64) -> StoreResult<bool>;
    /// Marks render task `task` done if it is still this worker's current attempt, its result
    /// (`bytes` uploaded) stored at `stored` of its pass's result log, and records `event`
    /// (kind and data) of its job in the same transaction. None when the attempt was not
    /// current (nothing recorded).
    fn complete(
        &self,
        task: &TaskRow,
        worker: &str,
        bytes: usize,
        stored: std::ops::Range<u64>,
        event: (EventKind, &serde_json::Value),
    ) -> StoreResult<Option<Completed>>;
    /// Records a failed attempt and requeues the task (which `worker` is not given again; after
    /// `BLOCKLIST_AFTER` failed tasks of the job, none of the job's tasks; after failures in
    /// `UNHEALTHY_AFTER_JOBS` jobs since its last result, no task at all: it is marked
    /// unhealthy). None when the attempt was not current.
    fn fail(
        &self,
        task_id: i64,
        attempt: u32,
        worker: &str,
        error: &str,
    ) -> StoreResult<Option<Failure>>;
    /// Requeues every lease that expired, each recorded as a lost attempt of its worker with the
    /// consequences `fail` has.
    fn expire_leases(&self) -> StoreResult<Vec<Failure>>;
    /// Gives every lease `lease_s` from now: a restarted coordinator's workers have that long to
    /// report back before their leases count as lost.
    fn extend_all_leases(&self, lease_s: f64) -> StoreResult<usize>;
    /// Queued tasks that have failed, of active jobs, that no live healthy worker may take (each
    /// failed it or is blocklisted for its job), while a live healthy worker (heard from within
    /// `silent_s`) exists.
    fn stranded_tasks(&self, silent_s: f64) -> StoreResult<Vec<TaskRow>>;
    /// The error of a task's last failed or lost attempt.
    fn last_error(&self, task_id: i64) -> StoreResult<Option<String>>;
    /// Registers a worker, or refreshes one that registers again with its id; it is `idle`.
    fn register_worker(&self, id: &str, name: &str, threads: u32, version: &str)
    -> StoreResult<()>;
    /// Notes that a worker is alive, and its state when given (None keeps it, except that a
    /// worker marked gone is back); false when it is unknown.
    fn touch_worker(&self, id: &str, state: Option<WorkerState>) -> StoreResult<bool>;
    /// Workers not heard from for `silent_s` are marked gone.
    fn mark_gone(&self, silent_s: f64) -> StoreResult<usize>;
    /// Every worker, in order of first registration.
    fn workers(&self) -> StoreResult<Vec<WorkerInfo>>;
    /// Records an event of a job.
    fn add_event(
        &self,
        job: &str,
        kind: EventKind,
        data: &serde_json::Value,
    ) -> StoreResult<EventRow>;
    /// A job's events after event `after`, in order.
    fn events_after(&self, job: &str, after: i64) -> StoreResult<Vec<EventRow>>;
    /// Counts of (state, n) in a table (jobs, tasks or workers).
    fn state_counts(&self, table: &str) -> StoreResult<Vec<(String, i64)>>;
}

impl SqliteStore {
    /// Opens (creating if needed) the database at `path`.
    pub fn open(path: &Path) -> StoreResult<SqliteStore> {
        let conn = Connection::open(path)?;
        conn.busy_timeout(std::time::Duration::from_secs(10))?;
        // A damaged file is refused before anything is written to it: a coordinator that
        // started on it would accept jobs it cannot record.
        let problems: Vec<String> = {
            let mut st = conn.prepare("PRAGMA quick_check")?;
            st.query_map([], |r| r.get(0))?
                .collect::<rusqlite::Result<_>>()?
        };
        if problems != ["ok"] {
            return Err(StoreError::new(format!(
                "the database is damaged (SQLite's quick_check: {})",
                problems
                    .iter()
                    .take(5)
                    .cloned()
                    .collect::<Vec<_>>()
                    .join("; ")
            )));
        }
        // Every query of the store is a cached statement (parsed once, not per result).
        conn.set_prepared_statement_cache_capacity(64);
        // And kept: without the query planner stability guarantee, SQLite (built with STAT4)
        // re-prepares a statement whenever a value bound to it could change its plan, which
        // the lease query's did on every lease (BENCHMARKS.md #12, stop 34). Every query here
        // is written for its index.
        conn.set_db_config(
            rusqlite::config::DbConfig::SQLITE_DBCONFIG_ENABLE_QPSG,
            true,
        )?;
        conn.execute_batch(SCHEMA)?;
        let has = |sql: &str| conn.prepare(sql).is_ok();
        let old = has("SELECT id FROM tasks LIMIT 0") && !has("SELECT kind FROM tasks LIMIT 0");
        if old {
            // A data folder from before the result logs: its tasks gain the columns (a done
            // task without them is rendered again).
            if !has("SELECT result_at, result_len FROM tasks LIMIT 0") {
                conn.execute_batch(
                    "ALTER TABLE tasks ADD COLUMN result_at INTEGER; \
                     ALTER TABLE tasks ADD COLUMN result_len INTEGER;",
                )?;
            }
            // From before merge tasks: the table is made again with their column (and a
            // uniqueness that includes it); every task it held is a render task.
            conn.execute_batch(&format!(
                "BEGIN; ALTER TABLE tasks RENAME TO tasks_v1; {TASKS_TABLE} \
                 INSERT INTO tasks ({TASKS_V1_COLS}) SELECT {TASKS_V1_COLS} FROM tasks_v1; \
                 DROP TABLE tasks_v1; COMMIT;"
            ))?;
        }
        conn.execute_batch(TASKS_TABLE)?;
        migrate(&conn)?;
        Ok(SqliteStore { conn })
    }
}

impl JobStore for SqliteStore {
    fn insert_job(&self, j: &NewJob) -> StoreResult<()> {
        let seq: i64 =
            self.conn
                .query_row("SELECT COALESCE(MAX(seq), 0) + 1 FROM jobs", [], |r| {
                    r.get(0)
                })?;
        cached_exec(
            &self.conn,
            "INSERT INTO jobs (id, seq, name, state, settings, resolved, scene_id, scene_main, \
             reference, created_at, accum_bytes) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11)",
            params![
                j.id,
                seq,
                j.name,
                J_QUEUED,
                j.settings,
                j.resolved,
                j.scene_id,
                j.scene_main,
                j.reference,
                now(),
                j.accum_bytes
            ],
        )?;
        Ok(())
    }
    fn job(&self, id: &str) -> StoreResult<Option<JobRow>> {
        cached_row(
            &self.conn,
            &format!("SELECT {JOB_COLS} FROM jobs WHERE id = ?1"),
            [id],
            job_row,
        )
        .optional()
        .map_err(StoreError::from)
    }
    fn jobs(&self) -> StoreResult<Vec<JobRow>> {
        let mut st = self
            .conn
            .prepare(&format!("SELECT {JOB_COLS} FROM jobs ORDER BY seq"))?;
        st.query_map([], job_row)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .map_err(StoreError::from)
    }
    fn active_jobs(&self) -> StoreResult<Vec<JobRow>> {
        let mut st = self.conn.prepare_cached(&format!(
            "SELECT {JOB_COLS} FROM jobs WHERE state IN (?1, ?2) ORDER BY seq"
        ))?;
        st.query_map(params![J_QUEUED, J_RUNNING], job_row)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .map_err(StoreError::from)
    }
    fn set_job_state(&self, id: &str, state: JobState, error: Option<&str>) -> StoreResult<bool> {
        let finished = (!state.is_active()).then(now);
        let n = cached_exec(
            &self.conn,
            "UPDATE jobs SET state = ?2, error = COALESCE(?3, error), \
             finished_at = COALESCE(?4, finished_at) WHERE id = ?1 \
             AND state IN (?5, ?6)",
            params![id, state, error, finished, J_QUEUED, J_RUNNING],
        )?;
        Ok(n == 1)
    }
    fn set_job_resolved(&self, id: &str, resolved: &str) -> StoreResult<bool> {
        let n = cached_exec(
            &self.conn,
            "UPDATE jobs SET resolved = ?2 WHERE id = ?1 AND state IN (?3, ?4)",
            params![id, resolved, J_QUEUED, J_RUNNING],
        )?;
        Ok(n == 1)
    }
    fn release_worker(&self, worker: &str) -> StoreResult<usize> {
        self.conn
            .execute(
                "UPDATE tasks SET state = ?2, worker_id = NULL, lease_expires = NULL \
             WHERE worker_id = ?1 AND state = ?3",
                params![worker, T_QUEUED, T_LEASED],
            )
            .map_err(StoreError::from)
    }
    fn task_existed(&self, task_id: i64) -> StoreResult<bool> {
        let max: Option<i64> = self
            .conn
            .query_row(
                "SELECT seq FROM sqlite_sequence WHERE name = 'tasks'",
                [],
                |r| r.get(0),
            )
            .optional()?;
        Ok(task_id >= 1 && max.is_some_and(|m| task_id <= m))
    }
    fn pass_merged(
        &self,
        id: &str,
        passes_done: u32,
        spp_done: u32,
        held: u32,
        stats: &crate::film::RayStats,
    ) -> StoreResult<()> {
        cached_exec(
            &self.conn,
            "UPDATE jobs SET passes_done = ?2, spp_done = ?3, samples = samples + ?4, \
             rays = rays + ?5, non_finite = non_finite + ?6 \
             WHERE id = ?1 AND passes_done = ?2 - 1",
            params![
                id,
                passes_done,
                spp_done,
                stats.samples as i64,
                stats.rays() as i64,
                stats.non_finite as i64
            ],
        )?;
        cached_exec(
            &self.conn,
            "DELETE FROM tasks WHERE job_id = ?1 AND pass < ?2",
            params![id, held.min(passes_done)],
        )?;
        Ok(())
    }
    fn add_series(&self, id: &str, p: &SeriesPoint) -> StoreResult<()> {
        cached_exec(
            &self.conn,
            "INSERT OR REPLACE INTO series (job_id, pass, spp, seconds, relmse) VALUES (?1, ?2, ?3, ?4, ?5)",
            params![id, p.pass, p.spp, p.seconds, p.relmse],
        )?;
        Ok(())
    }
    fn series(&self, id: &str) -> StoreResult<Vec<SeriesPoint>> {
        let mut st = self.conn.prepare_cached(
            "SELECT pass, spp, seconds, relmse FROM series WHERE job_id = ?1 ORDER BY pass",
        )?;
        st.query_map([id], |r| {
            Ok(SeriesPoint {
                pass: r.get(0)?,
                spp: r.get(1)?,
                seconds: r.get(2)?,
                relmse: r.get(3)?,
            })
        })?
        .collect::<rusqlite::Result<Vec<_>>>()
        .map_err(StoreError::from)
    }
    fn create_tasks(
        &self,
        id: &str,
        pass: u32,
        tiles: std::ops::Range<u32>,
        samples: std::ops::Range<u32>,
    ) -> StoreResult<()> {
        let tx = self.conn.unchecked_transaction()?;
        {
            let mut st = tx.prepare_cached(
                "INSERT OR IGNORE INTO tasks (job_id, pass, tile, s0, s1, state) VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            )?;
            for t in tiles {
                st.execute(params![id, pass, t, samples.start, samples.end, T_QUEUED])?;
            }
        }
        tx.commit().map_err(StoreError::from)
    }
    fn create_merge_tasks(
        &self,
        id: &str,
        pass: u32,
        groups: &[std::ops::Range<u32>],
    ) -> StoreResult<()> {
        let tx = self.conn.unchecked_transaction()?;
        {
            let mut st = tx.prepare_cached(
                "INSERT OR IGNORE INTO tasks (job_id, kind, pass, tile, s0, s1, state) \
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
            )?;
            for (g, bands) in groups.iter().enumerate() {
                st.execute(params![
                    id,
                    K_MERGE,
                    pass,
                    g as u32,
                    bands.start,
                    bands.end,
                    T_QUEUED
                ])?;
            }
        }
        tx.commit().map_err(StoreError::from)
    }
    fn merge_tasks(&self, id: &str, pass: u32) -> StoreResult<Vec<TaskRow>> {
        let mut st = self.conn.prepare_cached(&format!(
            "SELECT {TASK_COLS} FROM tasks WHERE job_id = ?1 AND pass = ?2 AND kind = ?3 \
             ORDER BY tile"
        ))?;
        st.query_map(params![id, pass, K_MERGE], task_row)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .map_err(StoreError::from)
    }
    fn delete_merge_tasks(&self, id: &str, pass: u32) -> StoreResult<()> {
        cached_exec(
            &self.conn,
            "DELETE FROM tasks WHERE job_id = ?1 AND pass = ?2 AND kind = ?3",
            params![id, pass, K_MERGE],
        )?;
        Ok(())
    }
    fn complete_merge(&self, task_id: i64, attempt: u32, worker: &str) -> StoreResult<bool> {
        let n = cached_exec(
            &self.conn,
            "UPDATE tasks SET state = ?4, lease_expires = NULL \
             WHERE id = ?1 AND attempt = ?2 AND worker_id = ?3 AND state = ?5 AND kind = ?6",
            params![task_id, attempt, worker, T_DONE, T_LEASED, K_MERGE],
        )?;
        if n == 1 {
            cached_exec(
                &self.conn,
                "UPDATE workers SET last_done_at = ?2 WHERE id = ?1",
                params![worker, now()],
            )?;
        }
        Ok(n == 1)
    }
    fn last_tile(&self, id: &str, pass: u32) -> StoreResult<Option<u32>> {
        cached_row(
            &self.conn,
            "SELECT MAX(tile) FROM tasks WHERE job_id = ?1 AND pass = ?2 AND kind = ?3",
            params![id, pass, K_RENDER],
            |r| r.get(0),
        )
        .map_err(StoreError::from)
    }
    fn last_pass(&self, id: &str) -> StoreResult<Option<u32>> {
        cached_row(
            &self.conn,
            "SELECT MAX(pass) FROM tasks WHERE job_id = ?1",
            [id],
            |r| r.get(0),
        )
        .map_err(StoreError::from)
    }
    fn pass_open(&self, id: &str, pass: u32) -> StoreResult<bool> {
        cached_row(
            &self.conn,
            "SELECT EXISTS (SELECT 1 FROM tasks WHERE state IN (?3, ?4) AND job_id = ?1 \
             AND kind = ?5 AND pass = ?2)",
            params![id, pass, T_QUEUED, T_LEASED, K_RENDER],
            |r| r.get(0),
        )
        .map_err(StoreError::from)
    }
    fn tasks_done(&self, id: &str) -> StoreResult<u32> {
        cached_row(
            &self.conn,
            "SELECT COUNT(*) FROM tasks WHERE job_id = ?1 AND state = ?2 AND kind = ?3 \
             AND pass >= (SELECT passes_done FROM jobs WHERE id = ?1)",
            params![id, T_DONE, K_RENDER],
            |r| r.get(0),
        )
        .map_err(StoreError::from)
    }
    fn pass_tasks(&self, id: &str, pass: u32) -> StoreResult<Vec<TaskRow>> {
        let mut st = self.conn.prepare_cached(&format!(
            "SELECT {TASK_COLS} FROM tasks WHERE job_id = ?1 AND kind = ?3 AND pass = ?2 \
             ORDER BY tile"
        ))?;
        st.query_map(params![id, pass, K_RENDER], task_row)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .map_err(StoreError::from)
    }
    fn task(&self, task_id: i64) -> StoreResult<Option<TaskRow>> {
        cached_row(
            &self.conn,
            &format!("SELECT {TASK_COLS} FROM tasks WHERE id = ?1"),
            [task_id],
            task_row,
        )
        .optional()
        .map_err(StoreError::from)
    }
    fn requeue(&self, task_id: i64) -> StoreResult<()> {
        cached_exec(
            &self.conn,
            "UPDATE tasks SET state = ?2, worker_id = NULL WHERE id = ?1",
            params![task_id, T_QUEUED],
        )?;
        Ok(())
    }
    fn lease(&self, worker: &str, lease_s: f64) -> StoreResult<Option<TaskRow>> {
        let tx = self.conn.unchecked_transaction()?;
        let unhealthy: Option<String> = cached_row(
            &tx,
            "SELECT unhealthy FROM workers WHERE id = ?1",
            [worker],
            |r| r.get(0),
        )
        .optional()?
        .flatten();
        if unhealthy.is_some() {
            return Ok(None);
        }
        // Job by job (few), each an index lookup of (state, job, pass, tile): no sort of the
        // queue, however many tasks it holds.
        let jobs: Vec<String> = {
            let mut st = tx.prepare_cached(
                "SELECT id FROM jobs WHERE state IN (?1, ?2) AND NOT EXISTS \
                 (SELECT 1 FROM blocklist b WHERE b.job_id = jobs.id AND b.worker_id = ?3) \
                 ORDER BY seq",
            )?;
            st.query_map(params![J_QUEUED, J_RUNNING, worker], |r| r.get(0))?
                .collect::<rusqlite::Result<_>>()?
        };
        let mut id: Option<i64> = None;
        for job in &jobs {
            id = tx
                .prepare_cached(NEXT_QUEUED)?
                .query_row(params![T_QUEUED, job, worker], |r| r.get(0))
                .optional()?;
            if id.is_some() {
                break;
            }
        }
        let Some(id) = id else {
            return Ok(None);
        };
        let t = now();
        cached_exec(
            &tx,
            "UPDATE tasks SET state = ?4, attempt = attempt + 1, worker_id = ?2, \
             lease_expires = ?3 WHERE id = ?1",
            params![id, worker, t + lease_s, T_LEASED],
        )?;
        cached_exec(
            &tx,
            "UPDATE jobs SET state = ?3, started_at = COALESCE(started_at, ?2) \
             WHERE id = (SELECT job_id FROM tasks WHERE id = ?1) AND state = ?4",
            params![id, t, J_RUNNING, J_QUEUED],
        )?;
        cached_exec(
            &tx,
            "UPDATE workers SET last_seen = ?2, state = ?3 WHERE id = ?1",
            params![worker, t, WorkerState::Busy],
        )?;
        let row = cached_row(
            &tx,
            &format!("SELECT {TASK_COLS} FROM tasks WHERE id = ?1"),
            [id],
            task_row,
        )?;
        tx.commit()?;
        Ok(Some(row))
    }
    fn extend(&self, task_id: i64, attempt: u32, worker: &str, lease_s: f64) -> StoreResult<bool> {
        let n = cached_exec(
            &self.conn,
            "UPDATE tasks SET lease_expires = ?4 WHERE id = ?1 AND attempt = ?2 AND worker_id = ?3 \
             AND state = ?5 AND job_id IN (SELECT id FROM jobs WHERE state = ?6)",
            params![
                task_id,
                attempt,
                worker,
                now() + lease_s,
                T_LEASED,
                J_RUNNING
            ],
        )?;
        Ok(n == 1)
    }
    fn complete(
        &self,
        task: &TaskRow,
        worker: &str,
        bytes: usize,
        stored: std::ops::Range<u64>,
        event: (EventKind, &serde_json::Value),
    ) -> StoreResult<Option<Completed>> {
        let (task_id, attempt) = (task.id, task.attempt);
        let tx = self.conn.unchecked_transaction()?;
        let n = cached_exec(
            &tx,
            "UPDATE tasks SET state = ?4, lease_expires = NULL, result_at = ?6, result_len = ?7 \
             WHERE id = ?1 AND attempt = ?2 AND worker_id = ?3 AND state = ?5",
            params![
                task_id,
                attempt,
                worker,
                T_DONE,
                T_LEASED,
                stored.start as i64,
                (stored.end - stored.start) as i64
            ],
        )?;
        if n == 1 {
            cached_exec(
                &tx,
                "UPDATE jobs SET result_bytes = result_bytes + ?2 WHERE id = (SELECT job_id FROM tasks WHERE id = ?1)",
                params![task_id, bytes as i64],
            )?;
            cached_exec(
                &tx,
                "UPDATE workers SET tasks_done = tasks_done + 1, last_done_at = ?2 WHERE id = ?1",
                params![worker, now()],
            )?;
        }
        if n != 1 {
            return Ok(None);
        }
        let event = insert_event(&tx, &task.job_id, event.0, event.1)?;
        let pass_open = self.pass_open(&task.job_id, task.pass)?;
        tx.commit()?;
        Ok(Some(Completed { event, pass_open }))
    }
    fn fail(
        &self,
        task_id: i64,
        attempt: u32,
        worker: &str,
        error: &str,
    ) -> StoreResult<Option<Failure>> {
        let tx = self.conn.unchecked_transaction()?;
        let task = cached_row(
            &tx,
            &format!(
                "SELECT {TASK_COLS} FROM tasks WHERE id = ?1 AND attempt = ?2 AND worker_id = ?3 \
                 AND state = ?4"
            ),
            params![task_id, attempt, worker, T_LEASED],
            task_row,
        )
        .optional()?;
        let Some(task) = task else {
            return Ok(None);
        };
        let f = record_failure(&tx, &task, worker, Outcome::Failed, error)?;
        tx.commit()?;
        Ok(Some(f))
    }
    fn expire_leases(&self) -> StoreResult<Vec<Failure>> {
        let tx = self.conn.unchecked_transaction()?;
        let expired: Vec<TaskRow> = {
            let mut st = tx.prepare_cached(&format!(
                "SELECT {TASK_COLS} FROM tasks WHERE state = ?2 AND lease_expires < ?1"
            ))?;
            st.query_map(params![now(), T_LEASED], task_row)?
                .collect::<rusqlite::Result<_>>()?
        };
        let mut lost = Vec::with_capacity(expired.len());
        for task in &expired {
            let worker = task.worker_id.clone().unwrap_or_default();
            let error = format!("worker {worker} went silent: its lease expired");
            lost.push(record_failure(&tx, task, &worker, Outcome::Lost, &error)?);
        }
        tx.commit()?;
        Ok(lost)
    }
    fn extend_all_leases(&self, lease_s: f64) -> StoreResult<usize> {
        Ok(self.conn.execute(
            "UPDATE tasks SET lease_expires = ?1 WHERE state = ?2",
            params![now() + lease_s, T_LEASED],
        )?)
    }
    fn last_error(&self, task_id: i64) -> StoreResult<Option<String>> {
        Ok(cached_row(
            &self.conn,
            "SELECT last_error FROM tasks WHERE id = ?1",
            [task_id],
            |r| r.get(0),
        )
        .optional()?
        .flatten())
    }
    fn stranded_tasks(&self, silent_s: f64) -> StoreResult<Vec<TaskRow>> {
        let live = "w.state NOT IN (?2, ?3) AND w.last_seen >= ?4 AND w.unhealthy IS NULL";
        let mut st = self.conn.prepare_cached(&format!(
            "SELECT {TASK_COLS} FROM tasks WHERE state = ?1 \
             AND id IN (SELECT task_id FROM failures) \
             AND job_id IN (SELECT id FROM jobs WHERE state IN (?5, ?6)) \
             AND EXISTS (SELECT 1 FROM workers w WHERE {live}) \
             AND NOT EXISTS (SELECT 1 FROM workers w WHERE {live} \
               AND NOT EXISTS (SELECT 1 FROM failures f \
                 WHERE f.task_id = tasks.id AND f.worker_id = w.id) \
               AND NOT EXISTS (SELECT 1 FROM blocklist b \
                 WHERE b.job_id = tasks.job_id AND b.worker_id = w.id))"
        ))?;
        st.query_map(
            params![
                T_QUEUED,
                WorkerState::Gone,
                WorkerState::Left,
                now() - silent_s,
                J_QUEUED,
                J_RUNNING
            ],
            task_row,
        )?
        .collect::<rusqlite::Result<_>>()
        .map_err(StoreError::from)
    }
    fn register_worker(
        &self,
        id: &str,
        name: &str,
        threads: u32,
        version: &str,
    ) -> StoreResult<()> {
        let t = now();
        cached_exec(
            &self.conn,
            "INSERT INTO workers (id, name, threads, version, registered_at, last_seen, state) \
             VALUES (?1, ?2, ?3, ?4, ?5, ?5, ?6) ON CONFLICT (id) DO UPDATE SET \
             name = ?2, threads = ?3, version = ?4, last_seen = ?5, state = ?6",
            params![id, name, threads, version, t, WorkerState::Idle],
        )?;
        Ok(())
    }
    fn touch_worker(&self, id: &str, state: Option<WorkerState>) -> StoreResult<bool> {
        let n = cached_exec(
            &self.conn,
            "UPDATE workers SET last_seen = ?2, state = COALESCE(?3, \
             CASE state WHEN ?4 THEN ?5 ELSE state END) WHERE id = ?1",
            params![id, now(), state, WorkerState::Gone, WorkerState::Idle],
        )?;
        Ok(n == 1)
    }
    fn mark_gone(&self, silent_s: f64) -> StoreResult<usize> {
        self.conn
            .execute(
                "UPDATE workers SET state = ?2 WHERE state != ?2 AND last_seen < ?1",
                params![now() - silent_s, WorkerState::Gone],
            )
            .map_err(StoreError::from)
    }
    fn workers(&self) -> StoreResult<Vec<WorkerInfo>> {
        let mut held: HashMap<String, Vec<WorkerTask>> = HashMap::new();
        let mut st = self.conn.prepare_cached(
            "SELECT worker_id, id, job_id, pass, tile, attempt, kind FROM tasks \
             WHERE state = ?1 AND worker_id IS NOT NULL ORDER BY id",
        )?;
        let rows = st.query_map(params![TaskState::Leased], |r| {
            Ok((
                r.get::<_, String>(0)?,
                WorkerTask {
                    id: r.get(1)?,
                    job_id: r.get(2)?,
                    pass: r.get(3)?,
                    tile: r.get(4)?,
                    attempt: r.get(5)?,
                    kind: r.get(6)?,
                },
            ))
        })?;
        for row in rows {
            let (worker, task) = row?;
            held.entry(worker).or_default().push(task);
        }
        let mut blocked: HashMap<String, Vec<String>> = HashMap::new();
        let mut st = self
            .conn
            .prepare_cached("SELECT worker_id, job_id FROM blocklist ORDER BY since")?;
        for row in st.query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, String>(1)?)))? {
            let (worker, job) = row?;
            blocked.entry(worker).or_default().push(job);
        }
        let mut st = self.conn.prepare_cached(
            "SELECT id, name, threads, version, registered_at, last_seen, state, tasks_done, \
             unhealthy FROM workers ORDER BY registered_at",
        )?;
        st.query_map([], |r| {
            let id: String = r.get(0)?;
            Ok(WorkerInfo {
                tasks: held.remove(&id).unwrap_or_default(),
                blocklisted_jobs: blocked.remove(&id).unwrap_or_default(),
                unhealthy: r.get(8)?,
                id,
                name: r.get(1)?,
                threads: r.get(2)?,
                version: r.get(3)?,
                registered_at: r.get(4)?,
                last_seen: r.get(5)?,
                state: r.get(6)?,
                tasks_done: r.get(7)?,
            })
        })?
        .collect::<rusqlite::Result<Vec<_>>>()
        .map_err(StoreError::from)
    }
    fn add_event(
        &self,
        job: &str,
        kind: EventKind,
        data: &serde_json::Value,
    ) -> StoreResult<EventRow> {
        Ok(insert_event(&self.conn, job, kind, data)?)
    }
    fn events_after(&self, job: &str, after: i64) -> StoreResult<Vec<EventRow>> {
        let mut st = self.conn.prepare_cached(
            "SELECT id, job_id, kind, data, at FROM events WHERE job_id = ?1 AND id > ?2 ORDER BY id",
        )?;
        st.query_map(params![job, after], |r| {
            let data: String = r.get(3)?;
            Ok(EventRow {
                id: r.get(0)?,
                job_id: r.get(1)?,
                kind: r.get(2)?,
                data: serde_json::from_str(&data).unwrap_or(serde_json::Value::Null),
                at: r.get(4)?,
            })
        })?
        .collect::<rusqlite::Result<Vec<_>>>()
        .map_err(StoreError::from)
    }
    fn state_counts(&self, table: &str) -> StoreResult<Vec<(String, i64)>> {
        let table = match table {
            "jobs" | "tasks" | "workers" => table,
            _ => return Ok(Vec::new()),
        };
        let mut st = self.conn.prepare_cached(&format!(
            "SELECT state, COUNT(*) FROM {table} GROUP BY state"
        ))?;
        st.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?
            .collect::<rusqlite::Result<Vec<_>>>()
            .map_err(StoreError::from)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pass's results follow one another in its log; the pass two later rewrites the log from
    /// its start only once the pass it held is recorded; a stale attempt of an older pass and
    /// a process that does not know the log (a restart) write after everything in the file, so
    /// no record a merge may still read is ever overwritten.
    #[test]
    fn result_logs_are_rewritten_in_place_only_once_their_pass_is_recorded() {
        let dir = std::env::temp_dir().join(format!("omis-logs-{}", uuid::Uuid::new_v4()));
        let paths = Paths { root: dir.clone() };
        let logs = ResultLogs::default();
        let read = |pass: u32, r: &std::ops::Range<u64>| {
            let bytes = std::fs::read(paths.result_log("j", pass)).expect("log");
            bytes[r.start as usize..r.end as usize].to_vec()
        };
        let w = |pass: u32, recorded: u32, b: &[u8]| {
            logs.write(&paths, "j", pass, recorded, b).expect("write")
        };
        // Records start at multiples of ALIGN (direct I/O pads each one up to the next).
        const A: u64 = log_file::ALIGN;
        // Pass 0 and pass 1 (each in its own log) while pass 0 is merged.
        assert_eq!(w(0, 0, b"aaaa"), 0..4);
        assert_eq!(w(0, 0, b"bb"), A..A + 2);
        assert_eq!(w(1, 0, b"cccc"), 0..4);
        // Pass 2 before pass 0 is recorded (ensure_passes never lets it, but if it did): after
        // pass 0's records.
        assert_eq!(w(2, 0, b"dd"), 2 * A..2 * A + 2);
        assert_eq!(read(0, &(0..4)), b"aaaa");
        // Once pass 0 is recorded, pass 2 begins the log again.
        let logs2 = ResultLogs::default();
        let w2 = |pass: u32, recorded: u32, b: &[u8]| {
            logs2.write(&paths, "j", pass, recorded, b).expect("write")
        };
        // (A process that does not know the log writes after its end: three records so far.)
        assert_eq!(w2(0, 0, b"ee"), 3 * A..3 * A + 2);
        assert_eq!(w2(2, 1, b"ffff"), 0..4);
        assert_eq!(w2(2, 1, b"g"), A..A + 1);
        assert_eq!(read(2, &(0..4)), b"ffff");
        assert_eq!(read(2, &(A..A + 1)), b"g");
        // A late attempt of pass 0 goes after the end and leaves pass 2's place alone.
        assert_eq!(w2(0, 1, b"hh"), 4 * A..4 * A + 2);
        assert_eq!(w2(2, 1, b"i"), 2 * A..2 * A + 1);
        assert_eq!(read(2, &(0..4)), b"ffff");
        assert_eq!(read(2, &(A..A + 1)), b"g");
        assert_eq!(read(2, &(2 * A..2 * A + 1)), b"i");
        // A recorded pass no later pass writes gives its log up at once, the others when the
        // job ends: kept as spares, which the next new logs take (and write from their start).
        let spares = || std::fs::read_dir(paths.spare_logs()).map_or(0, |d| d.count());
        logs2.release(&paths, "j", 1, false);
        assert!(!paths.result_log("j", 1).exists());
        logs2.release(&paths, "j", 2, true);
        assert!(paths.result_log("j", 2).exists());
        logs2.remove(&paths, "j");
        assert!(!paths.result_log("j", 0).exists());
        assert_eq!(spares(), 2);
        for job in ["k", "l", "m"] {
            assert_eq!(logs2.write(&paths, job, 0, 0, b"n").expect("write"), 0..1);
        }
        assert_eq!(spares(), 0);
        // (Padded to ALIGN with direct I/O, not where the file system refuses it.)
        let len = |job: &str| {
            log_file::align_up(
                std::fs::metadata(paths.result_log(job, 0))
                    .expect("log")
                    .len(),
            )
        };
        let mut taken = [len("k"), len("l")];
        taken.sort_unstable();
        assert_eq!(
            (taken, len("m")),
            ([A, 5 * A], A),
            "the two spares, then a new log"
        );
        // At most SPARE_LOGS are kept; the rest are deleted.
        for j in 0..SPARE_LOGS + 2 {
            let path = dir.join(format!("extra-{j}.log"));
            std::fs::write(&path, b"p").expect("a log");
            retire(&paths, &path);
            assert!(!path.exists());
        }
        assert_eq!(spares(), SPARE_LOGS);
        // Nor past SPARE_LOG_BYTES (a sparse file: no disk is written).
        let spare = std::fs::read_dir(paths.spare_logs())
            .expect("spares")
            .flatten()
            .next()
            .expect("a spare")
            .path();
        std::fs::remove_file(&spare).expect("one spare fewer");
        let big = dir.join("big.log");
        std::fs::File::create(&big)
            .and_then(|f| f.set_len(SPARE_LOG_BYTES))
            .expect("a sparse log");
        retire(&paths, &big);
        assert!(!big.exists());
        assert_eq!(spares(), SPARE_LOGS - 1);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Leases bind new values to cached statements; none of them may be parsed again for it
    /// (SQLite's STAT4 build re-prepared the lease query on every lease without QPSG).
    #[test]
    fn leasing_reuses_prepared_statements() {
        let dir = std::env::temp_dir().join(format!("omis-store-{}", uuid::Uuid::new_v4()));
        std::fs::create_dir_all(&dir).expect("temporary folder");
        let db = SqliteStore::open(&dir.join("db.sqlite")).expect("store");
        for (job, tiles) in [("a", 3), ("b", 40)] {
            db.insert_job(&NewJob {
                id: job,
                name: None,
                settings: "{}",
                resolved: "{}",
                scene_id: "s",
                scene_main: "scene.json",
                reference: None,
                accum_bytes: 0,
            })
            .expect("job");
            db.create_tasks(job, 0, 0..tiles, 0..16).expect("tasks");
        }
        db.register_worker("w", "w", 1, "test").expect("worker");
        let mut leased = Vec::new();
        for _ in 0..12 {
            let t = db.lease("w", 60.0).expect("lease").expect("a queued task");
            leased.push((t.job_id, t.tile));
        }
        // Job by job in order, tile by tile: the lease query's plan still holds.
        let want: Vec<(String, u32)> = (0..3)
            .map(|t| ("a".to_string(), t))
            .chain((0..9).map(|t| ("b".to_string(), t)))
            .collect();
        assert_eq!(leased, want);
        let st = db.conn.prepare_cached(NEXT_QUEUED).expect("cached");
        assert_eq!(
            st.get_status(rusqlite::StatementStatus::RePrepare),
            0,
            "the lease query was prepared again"
        );
        drop(st);
        drop(db);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A database of every older schema version opens and is migrated to the current one with
    /// its rows; one of a newer version is refused; a damaged one too.
    #[test]
    fn older_schemas_are_migrated_and_newer_or_damaged_ones_refused() {
        let dir = std::env::temp_dir().join(format!("omis-store-{}", uuid::Uuid::new_v4()));
        std::fs::create_dir_all(&dir).expect("temporary folder");
        for from in 0..MIGRATIONS.len() {
            let path = dir.join(format!("v{from}.sqlite"));
            {
                // The schema as version `from` had it, with a worker.
                let conn = Connection::open(&path).expect("open");
                conn.execute_batch(SCHEMA).expect("schema");
                conn.execute_batch(TASKS_TABLE).expect("tasks");
                for m in &MIGRATIONS[..from] {
                    conn.execute_batch(m).expect("migration");
                }
                conn.execute_batch(&format!("PRAGMA user_version = {from};"))
                    .expect("version");
                conn.execute(
                    "INSERT INTO workers (id, name, threads, version, registered_at, \
                     last_seen, state) VALUES ('w', 'w', 1, 'old', 0, 0, 'idle')",
                    [],
                )
                .expect("a worker");
            }
            let db = SqliteStore::open(&path).expect("migrated");
            let version: i64 = db
                .conn
                .query_row("PRAGMA user_version", [], |r| r.get(0))
                .expect("version");
            assert_eq!(version, MIGRATIONS.len() as i64, "from {from}");
            let workers = db.workers().expect("workers");
            assert_eq!(workers.len(), 1, "from {from}");
            assert_eq!(workers[0].unhealthy, None);
            // Opening it again changes nothing.
            drop(db);
            SqliteStore::open(&path).expect("opens again");
        }
        let newer = dir.join("newer.sqlite");
        {
            let conn = Connection::open(&newer).expect("open");
            conn.execute_batch("PRAGMA user_version = 999;")
                .expect("version");
        }
        let e = SqliteStore::open(&newer).err().expect("refused");
        assert!(e.to_string().contains("schema version 999"), "{e}");
        let damaged = dir.join("damaged.sqlite");
        std::fs::write(&damaged, vec![0x5au8; 16384]).expect("garbage");
        assert!(SqliteStore::open(&damaged).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
