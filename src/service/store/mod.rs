//! The coordinator's durable state: jobs, tasks (leases), workers, the relMSE series and the
//! event log, behind the `JobStore` trait (its one engine: SQLite, `sqlite.rs`, with its
//! numbered schema migrations in `migrations.rs`), and the files beside the database
//! (`files.rs`: where each lies, atomic and in-place writes; `result_logs.rs`: the per-pass
//! result logs, written through `log_file.rs`).

mod files;
pub(crate) mod log_file;
mod migrations;
mod result_logs;
mod sqlite;

pub(crate) use files::{Paths, write_at, write_atomic};
pub(crate) use result_logs::ResultLogs;
pub(crate) use sqlite::SqliteStore;

use crate::protocol::{
    EventKind, JobState, SeriesPoint, TaskKind, TaskState, WorkerInfo, WorkerState,
};
use std::time::{SystemTime, UNIX_EPOCH};

/// Seconds since the Unix epoch.
pub(crate) fn now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
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
    /// A frame of a sequence: the sequence's job.
    pub parent_id: Option<String>,
    /// A frame of a sequence: its frame number.
    pub frame: Option<u32>,
    /// A sequence (a parent job, with no tasks of its own): its frame range
    /// (`FrameRange`'s text).
    pub frames: Option<String>,
}

impl JobRow {
    /// Whether the job is a sequence: its frames are its child jobs, it has no tasks itself.
    pub fn is_sequence(&self) -> bool {
        self.frames.is_some()
    }
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
    /// The outcome's name, as stored.
    pub(crate) fn as_str(self) -> &'static str {
        match self {
            Outcome::Failed => "failed",
            Outcome::Lost => "lost",
        }
    }
}

/// The queries the coordinator makes of its job store: jobs, their tasks pass by pass,
/// leases, workers, the relMSE series and the event log. Every method is one short
/// transaction.
///
/// This trait is the seam for another engine. SQLite (`SqliteStore`, `sqlite.rs`) is the
/// embedded one; a shared engine (PostgreSQL, so that several coordinators serve one queue)
/// would implement, in a module beside it:
/// - every method below, with the same atomicity (`lease`, `complete`, `fail` and
///   `expire_leases` each change a task, its worker and their events in one transaction; a
///   lease must go to one worker only, e.g. `SELECT ... FOR UPDATE SKIP LOCKED`);
/// - its own schema and numbered migrations (as `migrations.rs` does for SQLite), refusing a
///   database newer than it knows;
/// - the conversions of the protocol's states and kinds to and from their names
///   (`JobState::as_str` and `FromStr`, as `sqlite.rs` does for SQLite's types);
/// - `From<its error> for StoreError`, setting `disk_full` when its storage is full (the API
///   answers 507).
///
/// Nothing else in the coordinator names an engine: `App::store` is a `Box<dyn JobStore>`.
pub(crate) trait JobStore: Send {
    /// Adds a job, `queued`, after every earlier one.
    fn insert_job(&self, j: &NewJob) -> StoreResult<()>;
    /// Adds a sequence job (`frames`: its range as text) and its frames' jobs (each with its
    /// frame number), `queued`, in one transaction; the frames follow the parent in the queue
    /// in the order given.
    fn insert_sequence(
        &self,
        parent: &NewJob,
        frames: &str,
        children: &[(u32, NewJob)],
    ) -> StoreResult<()>;
    /// The frames' jobs of sequence `parent`, in frame order (empty for any other job).
    fn frames(&self, parent: &str) -> StoreResult<Vec<JobRow>>;
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
