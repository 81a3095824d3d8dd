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
    AttemptOutcome, BlocklistEntry, EventKind, JobState, SeriesPoint, TaskAttempt, TaskKind,
    TaskState, WorkerAdmin, WorkerInfo, WorkerState,
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
    /// Its place in submission order (the job list's cursor).
    pub seq: i64,
    /// Higher first in the lease order.
    pub priority: i32,
    /// When it was paused (or failed: a requeue counts that time as paused), if it is.
    pub paused_at: Option<f64>,
    /// Seconds spent paused before `paused_at`.
    pub paused_s: f64,
    /// The job this one retries.
    pub retry_of: Option<String>,
    /// Worker tags the job needs (sorted).
    pub require_tags: Vec<String>,
    /// The user who submitted it (None: no user, i.e. the single client token or none).
    pub owner: Option<String>,
    /// The job's own webhook receivers: `protocol::WebhookSpec`s as JSON (None: none).
    pub webhooks: Option<String>,
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

    /// Seconds the job has spent paused up to time `at`.
    pub fn paused_until(&self, at: f64) -> f64 {
        self.paused_s + self.paused_at.map_or(0.0, |p| (at - p).max(0.0))
    }

    /// Seconds of rendering from the first lease to `at` (or to the end, if earlier), the time
    /// paused left out: what a time budget counts.
    pub fn render_seconds(&self, at: f64) -> f64 {
        let end = self.finished_at.map_or(at, |f| f.min(at));
        self.started_at
            .map_or(0.0, |s| (end - s - self.paused_until(end)).max(0.0))
    }
}

/// What [`JobStore::jobs_page`] selects.
#[derive(Clone, Debug, Default)]
pub(crate) struct JobQuery {
    /// Jobs in one of these states (empty: any).
    pub states: Vec<JobState>,
    /// Jobs whose name contains this (case-insensitively, ASCII).
    pub name: Option<String>,
    /// Jobs created at or after this time (seconds since the Unix epoch).
    pub since: Option<f64>,
    /// Jobs after this one in submission order (its `seq`).
    pub after: Option<i64>,
    /// At most this many.
    pub limit: u32,
    /// The frames of sequences too (else only single jobs and sequences).
    pub include_frames: bool,
}

/// What [`JobStore::delete_job`] did.
#[derive(Clone, Debug)]
pub(crate) enum Deleted {
    /// The job's rows are gone; the row it had (its files are the caller's to remove).
    Removed(Box<JobRow>),
    /// The job has not ended: nothing was deleted.
    NotFinal(JobState),
    /// Another job (this one) uses the job's image as its reference: nothing was deleted.
    Referenced(String),
    /// No such job.
    Missing,
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
    pub priority: i32,
    pub retry_of: Option<&'a str>,
    /// Worker tags the job needs (validated, sorted).
    pub require_tags: &'a [String],
    /// The submitter's user name.
    pub owner: Option<&'a str>,
    /// The job's own webhook receivers (JSON of `protocol::WebhookSpec`s).
    pub webhooks: Option<&'a str>,
}

/// A webhook receiver: where a job's final event is POSTed, and the secret that signs it.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub(crate) struct WebhookTarget {
    pub url: String,
    pub secret: Option<String>,
}

/// One delivery of a job's final event to one receiver (the webhook outbox).
#[derive(Clone, Debug)]
pub(crate) struct DeliveryRow {
    /// The delivery id (`X-Omis-Delivery`), the same on every attempt.
    pub id: String,
    pub job_id: String,
    /// `done`, `failed` or `cancelled`.
    pub event: String,
    pub url: String,
    pub secret: Option<String>,
    /// When the event happened.
    pub at: f64,
    /// `pending`, `delivered` or `failed`.
    pub state: String,
    pub attempts: u32,
    pub next_at: f64,
    pub last_status: Option<u16>,
    pub last_error: Option<String>,
    pub delivered_at: Option<f64>,
}

/// What one attempt of a delivery came to.
#[derive(Clone, Debug)]
pub(crate) struct DeliveryAttempt {
    /// The receiver's status, if it answered.
    pub status: Option<u16>,
    /// Why it did not count as delivered (None: a 2xx answer).
    pub error: Option<String>,
    /// When to try again (None: no more attempts; with an error, the delivery has failed).
    pub retry_at: Option<f64>,
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

/// Whose task attempts [`JobStore::task_attempts`] lists.
#[derive(Clone, Copy, Debug)]
pub(crate) enum AttemptsOf<'a> {
    /// A job's.
    Job(&'a str),
    /// A worker's.
    Worker(&'a str),
}

/// How an attempt ended without a result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Outcome {
    /// The worker reported an error (or its result was refused).
    Failed,
    /// The worker went silent: its lease expired.
    Lost,
    /// The worker's result was refused as invalid.
    Refused,
}

impl Outcome {
    /// The outcome's name, as stored.
    pub(crate) fn as_str(self) -> &'static str {
        match self {
            Outcome::Failed => "failed",
            Outcome::Lost => "lost",
            Outcome::Refused => "refused",
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
    /// One page of the jobs `q` selects, in submission order.
    fn jobs_page(&self, q: &JobQuery) -> StoreResult<Vec<JobRow>>;
    /// Jobs in a final state, those that ended first first.
    fn finished_jobs(&self) -> StoreResult<Vec<JobRow>>;
    /// Whether a job uses scene bundle `scene`.
    fn scene_in_use(&self, scene: &str) -> StoreResult<bool>;
    /// Whether a job uses the reference image at `path`.
    fn reference_in_use(&self, path: &str) -> StoreResult<bool>;
    /// Jobs still to be worked on (queued, running or paused).
    fn active_jobs(&self) -> StoreResult<Vec<JobRow>>;
    /// Sets the priority of a job that has not ended; false when it had.
    fn set_priority(&self, id: &str, priority: i32) -> StoreResult<bool>;
    /// Pauses a queued or running job (it leases nothing until resumed); false otherwise.
    fn pause(&self, id: &str) -> StoreResult<bool>;
    /// Resumes a paused job: running again, or queued when no task of it was ever leased;
    /// its time paused is added up. False when it was not paused.
    fn resume(&self, id: &str) -> StoreResult<bool>;
    /// Makes a failed job active again, in one transaction: its queued and leased tasks are
    /// queued with their failure counts cleared, its failed attempts and blocklist forgotten
    /// (every worker may take its tasks again), its error cleared, the time it spent failed
    /// counted as paused. False when it had not failed.
    fn requeue_failed(&self, id: &str) -> StoreResult<bool>;
    /// Deletes a job that has ended and every row of it (tasks, events, series, failed
    /// attempts, blocklist), in one transaction; not while another job's reference is its
    /// image (at `image`).
    fn delete_job(&self, id: &str, image: &str) -> StoreResult<Deleted>;
    /// Moves an active (queued, running or paused) job to `state`; false when the job had
    /// already ended (a cancelled job stays cancelled). A final state queues, in the same transaction,
    /// a webhook delivery of its event to each receiver: the store's global ones
    /// (`SqliteStore::with_webhooks`) and the job's own.
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
    /// Leases the first queued task of the queued or running job of highest priority (the
    /// oldest of those) to `worker`: its merge tasks first, then its render tasks, passes in
    /// order; the worker is marked busy in the same
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
        outcome: Outcome,
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
    /// Registers a worker with its `tags` (validated, sorted), or refreshes one that registers
    /// again with its id; it is `idle`, and keeps what an operator allowed it.
    fn register_worker(
        &self,
        id: &str,
        name: &str,
        threads: u32,
        version: &str,
        tags: &[String],
    ) -> StoreResult<()>;
    /// What an operator allows a worker; None when it is unknown.
    fn worker_admin(&self, id: &str) -> StoreResult<Option<WorkerAdmin>>;
    /// Sets what an operator allows a worker; the worker's admin state and health after it,
    /// None when it is unknown.
    fn set_worker_admin(
        &self,
        id: &str,
        admin: WorkerAdmin,
    ) -> StoreResult<Option<(WorkerAdmin, Option<String>)>>;
    /// Clears a worker's unhealthy mark (the failures before now no longer count towards
    /// another); its admin state, None when it is unknown.
    fn clear_unhealthy(&self, id: &str) -> StoreResult<Option<WorkerAdmin>>;
    /// Takes a worker off a job's blocklist and forgets its failed attempts of the job's tasks
    /// (so it may take them again); false when it was not on it and had failed none.
    fn clear_blocklist(&self, job: &str, worker: &str) -> StoreResult<bool>;
    /// The workers blocklisted for a job, oldest first.
    fn blocklist(&self, job: &str) -> StoreResult<Vec<BlocklistEntry>>;
    /// A page of task attempts of a job or of a worker (`of`), failed first, then by lease
    /// time: `limit` of them after skipping `offset`, only those ending with `outcome` if given.
    fn task_attempts(
        &self,
        of: AttemptsOf<'_>,
        outcome: Option<AttemptOutcome>,
        limit: u32,
        offset: u32,
    ) -> StoreResult<Vec<TaskAttempt>>;
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
    /// Counts of (state, n) in a table (jobs, tasks, workers or webhook_deliveries).
    fn state_counts(&self, table: &str) -> StoreResult<Vec<(String, i64)>>;
    /// Pending webhook deliveries due at `now`, at most `limit`, earliest first.
    fn due_deliveries(&self, now: f64, limit: u32) -> StoreResult<Vec<DeliveryRow>>;
    /// The earliest `next_at` of a pending delivery, if any.
    fn next_delivery_at(&self) -> StoreResult<Option<f64>>;
    /// Records an attempt of pending delivery `id`: delivered, due again at `retry_at`, or failed.
    fn record_delivery(&self, id: &str, attempt: &DeliveryAttempt) -> StoreResult<()>;
    /// A job's webhook deliveries, oldest first.
    fn deliveries(&self, job: &str) -> StoreResult<Vec<DeliveryRow>>;
}
