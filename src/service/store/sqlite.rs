//! The SQLite engine of the store: `SqliteStore`, one embedded database (WAL) under the data
//! folder, every query a statement prepared once per connection; the conversions of the
//! protocol's states and kinds to and from SQLite's text values; and SQLite's errors as
//! `StoreError`s. The schema and its migrations are in `migrations.rs`.

use super::migrations;
use super::{
    AttemptsOf, BLOCKLIST_AFTER, Completed, Deleted, DeliveryAttempt, DeliveryRow, EventRow,
    Failure, JobQuery, JobRow, JobStore, NewJob, Outcome, StoreError, StoreResult, TaskRow,
    UNHEALTHY_AFTER_JOBS, WebhookTarget, now,
};
use crate::protocol::{
    AttemptOutcome, BlocklistEntry, EventKind, JobState, SeriesPoint, TaskAttempt, TaskKind,
    TaskState, WorkerAdmin, WorkerInfo, WorkerState, WorkerTask,
};
use rusqlite::types::{FromSql, FromSqlError, FromSqlResult, ToSql, ToSqlOutput, ValueRef};
use rusqlite::{Connection, OptionalExtension, params};
use std::collections::HashMap;
use std::path::Path;

impl From<rusqlite::Error> for StoreError {
    fn from(e: rusqlite::Error) -> Self {
        StoreError {
            disk_full: e.sqlite_error_code() == Some(rusqlite::ErrorCode::DiskFull),
            message: e.to_string(),
        }
    }
}

/// Stores each of the protocol's closed sets of names as its name (`as_str`), read back with
/// `FromStr`: a name this omis does not know is an error of the row, not a panic.
macro_rules! stored_as_name {
    ($($name:ty),+ $(,)?) => {$(
        impl ToSql for $name {
            fn to_sql(&self) -> rusqlite::Result<ToSqlOutput<'_>> {
                Ok(ToSqlOutput::from(self.as_str()))
            }
        }

        impl FromSql for $name {
            fn column_result(value: ValueRef<'_>) -> FromSqlResult<Self> {
                value
                    .as_str()?
                    .parse()
                    .map_err(|e: String| FromSqlError::Other(e.into()))
            }
        }
    )+};
}

stored_as_name!(
    JobState,
    TaskState,
    TaskKind,
    WorkerState,
    EventKind,
    WorkerAdmin,
    AttemptOutcome
);

/// A list of tags as stored: sorted, comma-separated ('' for none).
fn tags_text(tags: &[String]) -> String {
    tags.join(",")
}

/// The tags of their stored text.
fn tags_of(text: &str) -> Vec<String> {
    text.split(',')
        .filter(|t| !t.is_empty())
        .map(str::to_string)
        .collect()
}

/// The database of a coordinator.
pub(crate) struct SqliteStore {
    conn: Connection,
    /// Receivers of every job's final event (`omis serve --webhook`).
    webhooks: Vec<WebhookTarget>,
}

const JOB_COLS: &str = "id, name, state, error, settings, resolved, scene_id, scene_main, \
    reference, created_at, started_at, finished_at, passes_done, spp_done, samples, rays, \
    non_finite, accum_bytes, result_bytes, seq, priority, paused_at, paused_s, retry_of, \
    require_tags, owner, webhooks, parent_id, frame, frames";

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
        seq: r.get(19)?,
        priority: r.get(20)?,
        paused_at: r.get(21)?,
        paused_s: r.get(22)?,
        retry_of: r.get(23)?,
        require_tags: tags_of(&r.get::<_, String>(24)?),
        owner: r.get(25)?,
        webhooks: r.get(26)?,
        parent_id: r.get(27)?,
        frame: r.get(28)?,
        frames: r.get(29)?,
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

/// Every row `sql` selects with `p`, each made by `f`.
fn query_all<T>(
    conn: &Connection,
    sql: &str,
    p: impl rusqlite::Params,
    f: impl FnMut(&rusqlite::Row) -> rusqlite::Result<T>,
) -> StoreResult<Vec<T>> {
    let mut st = conn.prepare_cached(sql)?;
    st.query_map(p, f)?
        .collect::<rusqlite::Result<Vec<_>>>()
        .map_err(StoreError::from)
}

/// Runs `sql` (a statement prepared once per connection and cached); rows changed.
fn cached_exec(conn: &Connection, sql: &str, p: impl rusqlite::Params) -> rusqlite::Result<usize> {
    conn.prepare_cached(sql)?.execute(p)
}

/// Inserts a queued job at place `seq` of the queue; `frame_of`: the sequence and frame number
/// of a sequence's frame.
fn insert_job_row(
    conn: &Connection,
    j: &NewJob,
    seq: i64,
    frame_of: Option<(&str, u32)>,
) -> rusqlite::Result<usize> {
    cached_exec(
        conn,
        "INSERT INTO jobs (id, seq, name, state, settings, resolved, scene_id, scene_main, \
         reference, created_at, accum_bytes, priority, retry_of, require_tags, owner, \
         webhooks, parent_id, frame) \
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17, ?18)",
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
            j.accum_bytes,
            j.priority,
            j.retry_of,
            tags_text(j.require_tags),
            j.owner,
            j.webhooks,
            frame_of.map(|f| f.0),
            frame_of.map(|f| f.1)
        ],
    )
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

// The states bound as parameters wherever a statement names one.
const J_QUEUED: JobState = JobState::Queued;
const J_RUNNING: JobState = JobState::Running;
const J_PAUSED: JobState = JobState::Paused;
const J_FAILED: JobState = JobState::Failed;
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
    let ended = match outcome {
        Outcome::Failed => AttemptOutcome::Failed,
        Outcome::Lost => AttemptOutcome::Expired,
        Outcome::Refused => AttemptOutcome::Refused,
    };
    end_attempt(conn, task.id, task.attempt, ended, Some(error), t)?;
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

/// A task attempt of its row (`task_attempts`' columns in order, as `task_attempts` reads them).
fn attempt_row(r: &rusqlite::Row) -> rusqlite::Result<TaskAttempt> {
    let leased_at: f64 = r.get(7)?;
    let ended_at: Option<f64> = r.get(8)?;
    Ok(TaskAttempt {
        task_id: r.get(0)?,
        job_id: r.get(1)?,
        kind: r.get(2)?,
        pass: r.get(3)?,
        tile: r.get(4)?,
        attempt: r.get(5)?,
        worker_id: r.get(6)?,
        leased_at,
        ended_at,
        outcome: r.get(9)?,
        error: r.get(10)?,
        seconds: ended_at.map(|e| (e - leased_at).max(0.0)),
    })
}

/// Records how attempt `attempt` of task `task_id` ended (inside the caller's transaction).
fn end_attempt(
    conn: &Connection,
    task_id: i64,
    attempt: u32,
    outcome: AttemptOutcome,
    error: Option<&str>,
    at: f64,
) -> rusqlite::Result<usize> {
    cached_exec(
        conn,
        "UPDATE task_attempts SET outcome = ?3, error = ?4, ended_at = ?5 \
         WHERE task_id = ?1 AND attempt = ?2 AND outcome = ?6",
        params![
            task_id,
            attempt,
            outcome,
            error,
            at,
            AttemptOutcome::Running
        ],
    )
}

/// Records every running attempt of the tasks chosen by `which` (an SQL condition on
/// `task_attempts` with ?1 its one parameter) as cancelled with `error` (inside the caller's
/// transaction).
fn cancel_attempts(
    conn: &Connection,
    which: &str,
    key: &dyn ToSql,
    error: &str,
) -> rusqlite::Result<usize> {
    cached_exec(
        conn,
        &format!(
            "UPDATE task_attempts SET outcome = ?2, error = ?3, ended_at = ?4 \
             WHERE {which} AND outcome = ?5"
        ),
        params![
            key,
            AttemptOutcome::Cancelled,
            error,
            now(),
            AttemptOutcome::Running
        ],
    )
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
        conn.set_prepared_statement_cache_capacity(96);
        // And kept: without the query planner stability guarantee, SQLite (built with STAT4)
        // re-prepares a statement whenever a value bound to it could change its plan, which
        // the lease query's did on every lease (BENCHMARKS.md, "The render service"). Every query here
        // is written for its index.
        conn.set_db_config(
            rusqlite::config::DbConfig::SQLITE_DBCONFIG_ENABLE_QPSG,
            true,
        )?;
        // Per connection (the journal mode is kept by the file too).
        conn.execute_batch(
            "PRAGMA journal_mode = WAL; PRAGMA synchronous = NORMAL; PRAGMA foreign_keys = ON;",
        )?;
        migrations::migrate(&conn)?;
        Ok(SqliteStore {
            conn,
            webhooks: Vec::new(),
        })
    }

    /// The store with `webhooks` as the receivers of every job's final event.
    pub fn with_webhooks(mut self, webhooks: Vec<WebhookTarget>) -> SqliteStore {
        self.webhooks = webhooks;
        self
    }

    /// Queues a delivery of job `id`'s final event `event` to every receiver (the global ones,
    /// then the job's own), within the caller's transaction.
    fn queue_deliveries(&self, tx: &Connection, id: &str, event: &str) -> StoreResult<()> {
        let own: Option<String> =
            cached_row(tx, "SELECT webhooks FROM jobs WHERE id = ?1", [id], |r| {
                r.get(0)
            })
            .optional()?
            .flatten();
        // Unreadable receivers must not keep the job from ending: they are left out, logged.
        let own: Vec<WebhookTarget> = match own.map(|j| serde_json::from_str(&j)) {
            Some(Ok(targets)) => targets,
            Some(Err(e)) => {
                tracing::error!("job {id}: its webhooks are unreadable ({e}); none is notified");
                Vec::new()
            }
            None => Vec::new(),
        };
        let at = now();
        for hook in self.webhooks.iter().chain(&own) {
            cached_exec(
                tx,
                "INSERT INTO webhook_deliveries (id, job_id, event, url, secret, at, state, \
                 next_at) VALUES (?1, ?2, ?3, ?4, ?5, ?6, 'pending', ?6)",
                params![
                    uuid::Uuid::new_v4().to_string(),
                    id,
                    event,
                    hook.url,
                    hook.secret,
                    at
                ],
            )?;
        }
        Ok(())
    }
}

const DELIVERY_COLS: &str = "id, job_id, event, url, secret, at, state, attempts, next_at, \
    last_status, last_error, delivered_at";

fn delivery_row(r: &rusqlite::Row) -> rusqlite::Result<DeliveryRow> {
    Ok(DeliveryRow {
        id: r.get(0)?,
        job_id: r.get(1)?,
        event: r.get(2)?,
        url: r.get(3)?,
        secret: r.get(4)?,
        at: r.get(5)?,
        state: r.get(6)?,
        attempts: r.get(7)?,
        next_at: r.get(8)?,
        last_status: r.get(9)?,
        last_error: r.get(10)?,
        delivered_at: r.get(11)?,
    })
}

impl JobStore for SqliteStore {
    fn insert_job(&self, j: &NewJob) -> StoreResult<()> {
        let seq: i64 =
            self.conn
                .query_row("SELECT COALESCE(MAX(seq), 0) + 1 FROM jobs", [], |r| {
                    r.get(0)
                })?;
        insert_job_row(&self.conn, j, seq, None)?;
        Ok(())
    }
    fn insert_sequence(
        &self,
        parent: &NewJob,
        frames: &str,
        children: &[(u32, NewJob)],
    ) -> StoreResult<()> {
        let tx = self.conn.unchecked_transaction()?;
        let seq: i64 = tx.query_row("SELECT COALESCE(MAX(seq), 0) + 1 FROM jobs", [], |r| {
            r.get(0)
        })?;
        insert_job_row(&tx, parent, seq, None)?;
        cached_exec(
            &tx,
            "UPDATE jobs SET frames = ?2 WHERE id = ?1",
            params![parent.id, frames],
        )?;
        // Consecutive after the parent: the lease order (by seq) takes the frames in order.
        for (k, (frame, child)) in children.iter().enumerate() {
            insert_job_row(&tx, child, seq + 1 + k as i64, Some((parent.id, *frame)))?;
        }
        tx.commit()?;
        Ok(())
    }
    fn frames(&self, parent: &str) -> StoreResult<Vec<JobRow>> {
        query_all(
            &self.conn,
            &format!("SELECT {JOB_COLS} FROM jobs WHERE parent_id = ?1 ORDER BY frame"),
            [parent],
            job_row,
        )
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
    fn jobs_page(&self, q: &JobQuery) -> StoreResult<Vec<JobRow>> {
        // One statement for every query: an absent filter binds NULL, which passes every row.
        let states: Option<String> = (!q.states.is_empty()).then(|| {
            q.states
                .iter()
                .map(|s| s.as_str())
                .collect::<Vec<_>>()
                .join(",")
        });
        query_all(
            &self.conn,
            &format!(
                "SELECT {JOB_COLS} FROM jobs WHERE seq > ?1 \
             AND (?2 IS NULL OR instr(',' || ?2 || ',', ',' || state || ',') > 0) \
             AND (?3 IS NULL OR instr(lower(COALESCE(name, '')), lower(?3)) > 0) \
             AND (?4 IS NULL OR created_at >= ?4) \
             AND (?6 OR parent_id IS NULL) \
             ORDER BY seq LIMIT ?5"
            ),
            params![
                q.after.unwrap_or(i64::MIN),
                states,
                q.name,
                q.since,
                q.limit,
                q.include_frames
            ],
            job_row,
        )
    }
    fn finished_jobs(&self) -> StoreResult<Vec<JobRow>> {
        query_all(
            &self.conn,
            &format!(
                "SELECT {JOB_COLS} FROM jobs WHERE state NOT IN (?1, ?2, ?3) AND parent_id IS NULL \
             ORDER BY COALESCE(finished_at, created_at), seq"
            ),
            params![J_QUEUED, J_RUNNING, J_PAUSED],
            job_row,
        )
    }
    fn scene_in_use(&self, scene: &str) -> StoreResult<bool> {
        Ok(cached_row(
            &self.conn,
            "SELECT EXISTS (SELECT 1 FROM jobs WHERE scene_id = ?1)",
            [scene],
            |r| r.get(0),
        )?)
    }
    fn reference_in_use(&self, path: &str) -> StoreResult<bool> {
        Ok(cached_row(
            &self.conn,
            "SELECT EXISTS (SELECT 1 FROM jobs WHERE reference = ?1)",
            [path],
            |r| r.get(0),
        )?)
    }
    fn set_priority(&self, id: &str, priority: i32) -> StoreResult<bool> {
        let n = cached_exec(
            &self.conn,
            "UPDATE jobs SET priority = ?2 WHERE id = ?1 AND state IN (?3, ?4, ?5)",
            params![id, priority, J_QUEUED, J_RUNNING, J_PAUSED],
        )?;
        Ok(n == 1)
    }
    fn pause(&self, id: &str) -> StoreResult<bool> {
        let n = cached_exec(
            &self.conn,
            "UPDATE jobs SET state = ?2, paused_at = ?3 WHERE id = ?1 AND state IN (?4, ?5)",
            params![id, J_PAUSED, now(), J_QUEUED, J_RUNNING],
        )?;
        Ok(n == 1)
    }
    fn resume(&self, id: &str) -> StoreResult<bool> {
        let n = cached_exec(
            &self.conn,
            "UPDATE jobs SET state = CASE WHEN started_at IS NULL THEN ?2 ELSE ?3 END, \
             paused_s = paused_s + MAX(0, ?4 - COALESCE(paused_at, ?4)), paused_at = NULL \
             WHERE id = ?1 AND state = ?5",
            params![id, J_QUEUED, J_RUNNING, now(), J_PAUSED],
        )?;
        Ok(n == 1)
    }
    fn requeue_failed(&self, id: &str) -> StoreResult<bool> {
        let tx = self.conn.unchecked_transaction()?;
        let n = cached_exec(
            &tx,
            "UPDATE jobs SET state = CASE WHEN started_at IS NULL THEN ?2 ELSE ?3 END, \
             error = NULL, \
             paused_s = paused_s + MAX(0, ?4 - COALESCE(paused_at, finished_at, ?4)), \
             paused_at = NULL, finished_at = NULL WHERE id = ?1 AND state = ?5",
            params![id, J_QUEUED, J_RUNNING, now(), J_FAILED],
        )?;
        if n != 1 {
            return Ok(false);
        }
        cached_exec(
            &tx,
            "UPDATE tasks SET state = ?2, worker_id = NULL, lease_expires = NULL, failures = 0, \
             last_error = NULL WHERE job_id = ?1 AND state IN (?2, ?3)",
            params![id, T_QUEUED, T_LEASED],
        )?;
        cached_exec(&tx, "DELETE FROM failures WHERE job_id = ?1", [id])?;
        cached_exec(&tx, "DELETE FROM blocklist WHERE job_id = ?1", [id])?;
        tx.commit()?;
        Ok(true)
    }
    fn delete_job(&self, id: &str, image: &str) -> StoreResult<Deleted> {
        let tx = self.conn.unchecked_transaction()?;
        let row = cached_row(
            &tx,
            &format!("SELECT {JOB_COLS} FROM jobs WHERE id = ?1"),
            [id],
            job_row,
        )
        .optional()?;
        let Some(row) = row else {
            return Ok(Deleted::Missing);
        };
        if row.state.is_active() {
            return Ok(Deleted::NotFinal(row.state));
        }
        let user: Option<String> = cached_row(
            &tx,
            "SELECT id FROM jobs WHERE reference = ?1 AND id != ?2 ORDER BY seq LIMIT 1",
            params![image, id],
            |r| r.get(0),
        )
        .optional()?;
        if let Some(user) = user {
            return Ok(Deleted::Referenced(user));
        }
        for table in ["tasks", "events", "series", "failures", "blocklist"] {
            cached_exec(&tx, &format!("DELETE FROM {table} WHERE job_id = ?1"), [id])?;
        }
        cached_exec(&tx, "DELETE FROM jobs WHERE id = ?1", [id])?;
        tx.commit()?;
        Ok(Deleted::Removed(Box::new(row)))
    }
    fn active_jobs(&self) -> StoreResult<Vec<JobRow>> {
        query_all(
            &self.conn,
            &format!("SELECT {JOB_COLS} FROM jobs WHERE state IN (?1, ?2, ?3) ORDER BY seq"),
            params![J_QUEUED, J_RUNNING, J_PAUSED],
            job_row,
        )
    }
    fn set_job_state(&self, id: &str, state: JobState, error: Option<&str>) -> StoreResult<bool> {
        let finished = (!state.is_active()).then(now);
        let tx = self.conn.unchecked_transaction()?;
        let n = cached_exec(
            &tx,
            "UPDATE jobs SET state = ?2, error = COALESCE(?3, error), \
             finished_at = COALESCE(?4, finished_at) WHERE id = ?1 \
             AND state IN (?5, ?6, ?7)",
            params![id, state, error, finished, J_QUEUED, J_RUNNING, J_PAUSED],
        )?;
        if n == 1 && finished.is_some() {
            cancel_attempts(&tx, "job_id = ?1", &id, &format!("the job is {state}"))?;
        }
        if n == 1
            && matches!(
                state,
                JobState::Done | JobState::Failed | JobState::Cancelled
            )
        {
            self.queue_deliveries(&tx, id, state.as_str())?;
        }
        tx.commit()?;
        Ok(n == 1)
    }
    fn set_job_resolved(&self, id: &str, resolved: &str) -> StoreResult<bool> {
        let n = cached_exec(
            &self.conn,
            "UPDATE jobs SET resolved = ?2 WHERE id = ?1 AND state IN (?3, ?4, ?5)",
            params![id, resolved, J_QUEUED, J_RUNNING, J_PAUSED],
        )?;
        Ok(n == 1)
    }
    fn release_worker(&self, worker: &str) -> StoreResult<usize> {
        let tx = self.conn.unchecked_transaction()?;
        cancel_attempts(
            &tx,
            "worker_id = ?1",
            &worker,
            "the worker left and gave its lease back",
        )?;
        let n = tx.execute(
            "UPDATE tasks SET state = ?2, worker_id = NULL, lease_expires = NULL \
             WHERE worker_id = ?1 AND state = ?3",
            params![worker, T_QUEUED, T_LEASED],
        )?;
        tx.commit()?;
        Ok(n)
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
        query_all(
            &self.conn,
            "SELECT pass, spp, seconds, relmse FROM series WHERE job_id = ?1 ORDER BY pass",
            [id],
            |r| {
                Ok(SeriesPoint {
                    pass: r.get(0)?,
                    spp: r.get(1)?,
                    seconds: r.get(2)?,
                    relmse: r.get(3)?,
                })
            },
        )
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
        query_all(
            &self.conn,
            &format!(
                "SELECT {TASK_COLS} FROM tasks WHERE job_id = ?1 AND pass = ?2 AND kind = ?3 \
             ORDER BY tile"
            ),
            params![id, pass, K_MERGE],
            task_row,
        )
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
        let tx = self.conn.unchecked_transaction()?;
        let n = cached_exec(
            &tx,
            "UPDATE tasks SET state = ?4, lease_expires = NULL \
             WHERE id = ?1 AND attempt = ?2 AND worker_id = ?3 AND state = ?5 AND kind = ?6",
            params![task_id, attempt, worker, T_DONE, T_LEASED, K_MERGE],
        )?;
        if n == 1 {
            let t = now();
            cached_exec(
                &tx,
                "UPDATE workers SET last_done_at = ?2 WHERE id = ?1",
                params![worker, t],
            )?;
            end_attempt(&tx, task_id, attempt, AttemptOutcome::Done, None, t)?;
        }
        tx.commit()?;
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
        query_all(
            &self.conn,
            &format!(
                "SELECT {TASK_COLS} FROM tasks WHERE job_id = ?1 AND kind = ?3 AND pass = ?2 \
             ORDER BY tile"
            ),
            params![id, pass, K_RENDER],
            task_row,
        )
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
        let tx = self.conn.unchecked_transaction()?;
        cancel_attempts(
            &tx,
            "task_id = ?1",
            &task_id,
            "requeued: its result could not be merged",
        )?;
        cached_exec(
            &tx,
            "UPDATE tasks SET state = ?2, worker_id = NULL WHERE id = ?1",
            params![task_id, T_QUEUED],
        )?;
        tx.commit()?;
        Ok(())
    }
    fn lease(&self, worker: &str, lease_s: f64) -> StoreResult<Option<TaskRow>> {
        let tx = self.conn.unchecked_transaction()?;
        let me: Option<(Option<String>, WorkerAdmin, String)> = cached_row(
            &tx,
            "SELECT unhealthy, admin, tags FROM workers WHERE id = ?1",
            [worker],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
        )
        .optional()?;
        let tags = match me {
            Some((None, WorkerAdmin::Enabled, tags)) => tags_of(&tags),
            // Unhealthy, disabled or draining: nothing.
            Some(_) => return Ok(None),
            None => Vec::new(),
        };
        // Job by job (few), each an index lookup of (state, job, pass, tile): no sort of the
        // queue, however many tasks it holds. A job that requires tags the worker lacks is
        // passed over.
        let jobs: Vec<String> = {
            let mut st = tx.prepare_cached(
                "SELECT id, require_tags FROM jobs WHERE state IN (?1, ?2) AND NOT EXISTS \
                 (SELECT 1 FROM blocklist b WHERE b.job_id = jobs.id AND b.worker_id = ?3) \
                 ORDER BY priority DESC, seq",
            )?;
            let rows = st.query_map(params![J_QUEUED, J_RUNNING, worker], |r| {
                Ok((r.get::<_, String>(0)?, r.get::<_, String>(1)?))
            })?;
            let mut jobs = Vec::new();
            for row in rows {
                let (job, required) = row?;
                if tags_of(&required).iter().all(|t| tags.contains(t)) {
                    jobs.push(job);
                }
            }
            jobs
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
        // A sequence runs from its first frame's first lease.
        cached_exec(
            &tx,
            "UPDATE jobs SET state = ?3, started_at = COALESCE(started_at, ?2) \
             WHERE id = (SELECT parent_id FROM jobs WHERE id = \
             (SELECT job_id FROM tasks WHERE id = ?1)) AND state = ?4",
            params![id, t, J_RUNNING, J_QUEUED],
        )?;
        cached_exec(
            &tx,
            "UPDATE workers SET last_seen = ?2, state = ?3 WHERE id = ?1",
            params![worker, t, WorkerState::Busy],
        )?;
        cached_exec(
            &tx,
            "INSERT OR REPLACE INTO task_attempts (task_id, attempt, job_id, kind, pass, tile, \
             worker_id, leased_at, outcome) \
             SELECT id, attempt, job_id, kind, pass, tile, worker_id, ?2, ?3 FROM tasks \
             WHERE id = ?1",
            params![id, t, AttemptOutcome::Running],
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
             AND state = ?5 AND job_id IN (SELECT id FROM jobs WHERE state IN (?6, ?7))",
            params![
                task_id,
                attempt,
                worker,
                now() + lease_s,
                T_LEASED,
                J_RUNNING,
                J_PAUSED
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
            let t = now();
            cached_exec(
                &tx,
                "UPDATE workers SET tasks_done = tasks_done + 1, last_done_at = ?2 WHERE id = ?1",
                params![worker, t],
            )?;
            end_attempt(&tx, task_id, attempt, AttemptOutcome::Done, None, t)?;
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
        outcome: Outcome,
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
        let f = record_failure(&tx, &task, worker, outcome, error)?;
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
        tags: &[String],
    ) -> StoreResult<()> {
        let t = now();
        cached_exec(
            &self.conn,
            "INSERT INTO workers (id, name, threads, version, registered_at, last_seen, state, \
             tags) VALUES (?1, ?2, ?3, ?4, ?5, ?5, ?6, ?7) ON CONFLICT (id) DO UPDATE SET \
             name = ?2, threads = ?3, version = ?4, last_seen = ?5, state = ?6, tags = ?7",
            params![
                id,
                name,
                threads,
                version,
                t,
                WorkerState::Idle,
                tags_text(tags)
            ],
        )?;
        Ok(())
    }
    fn worker_admin(&self, id: &str) -> StoreResult<Option<WorkerAdmin>> {
        Ok(cached_row(
            &self.conn,
            "SELECT admin FROM workers WHERE id = ?1",
            [id],
            |r| r.get(0),
        )
        .optional()?)
    }
    fn set_worker_admin(
        &self,
        id: &str,
        admin: WorkerAdmin,
    ) -> StoreResult<Option<(WorkerAdmin, Option<String>)>> {
        Ok(cached_row(
            &self.conn,
            "UPDATE workers SET admin = ?2 WHERE id = ?1 RETURNING admin, unhealthy",
            params![id, admin],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .optional()?)
    }
    fn clear_unhealthy(&self, id: &str) -> StoreResult<Option<WorkerAdmin>> {
        // The mark counts failures since the worker's last result: from now on, as if it had
        // just delivered one.
        Ok(cached_row(
            &self.conn,
            "UPDATE workers SET unhealthy = NULL, last_done_at = ?2 WHERE id = ?1 RETURNING admin",
            params![id, now()],
            |r| r.get(0),
        )
        .optional()?)
    }
    fn clear_blocklist(&self, job: &str, worker: &str) -> StoreResult<bool> {
        let tx = self.conn.unchecked_transaction()?;
        let listed = tx.execute(
            "DELETE FROM blocklist WHERE job_id = ?1 AND worker_id = ?2",
            params![job, worker],
        )?;
        // Its failed attempts would keep those tasks from it, and count towards the next entry.
        let failed = tx.execute(
            "DELETE FROM failures WHERE job_id = ?1 AND worker_id = ?2",
            params![job, worker],
        )?;
        tx.commit()?;
        Ok(listed + failed > 0)
    }
    fn blocklist(&self, job: &str) -> StoreResult<Vec<BlocklistEntry>> {
        query_all(
            &self.conn,
            "SELECT worker_id, since, reason FROM blocklist WHERE job_id = ?1 ORDER BY since",
            [job],
            |r| {
                Ok(BlocklistEntry {
                    worker_id: r.get(0)?,
                    since: r.get(1)?,
                    reason: r.get(2)?,
                })
            },
        )
    }
    fn task_attempts(
        &self,
        of: AttemptsOf<'_>,
        outcome: Option<AttemptOutcome>,
        limit: u32,
        offset: u32,
    ) -> StoreResult<Vec<TaskAttempt>> {
        let (column, key) = match of {
            AttemptsOf::Job(j) => ("job_id", j),
            AttemptsOf::Worker(w) => ("worker_id", w),
        };
        let cols = "task_id, job_id, kind, pass, tile, attempt, worker_id, leased_at, ended_at, \
             outcome, error";
        // Each page is read from an index in order (no sort of a large job's attempts while
        // the store is held): the failed attempts, then the others.
        let page = |sql: &str, p: &[&dyn ToSql]| -> rusqlite::Result<Vec<TaskAttempt>> {
            let mut st = self.conn.prepare_cached(sql)?;
            st.query_map(p, attempt_row)?.collect()
        };
        let of_outcome = format!(
            "SELECT {cols} FROM task_attempts WHERE {column} = ?1 AND outcome = ?2 \
             ORDER BY leased_at, rowid LIMIT ?3 OFFSET ?4"
        );
        if let Some(o) = outcome {
            return Ok(page(&of_outcome, params![key, o, limit, offset])?);
        }
        let failed: u32 = cached_row(
            &self.conn,
            &format!("SELECT COUNT(*) FROM task_attempts WHERE {column} = ?1 AND outcome = ?2"),
            params![key, AttemptOutcome::Failed],
            |r| r.get(0),
        )?;
        let mut rows = if offset < failed {
            page(
                &of_outcome,
                params![key, AttemptOutcome::Failed, limit, offset],
            )?
        } else {
            Vec::new()
        };
        let left = limit.saturating_sub(rows.len() as u32);
        if left > 0 {
            rows.extend(page(
                &format!(
                    "SELECT {cols} FROM task_attempts WHERE {column} = ?1 AND outcome != ?2 \
                     ORDER BY leased_at, rowid LIMIT ?3 OFFSET ?4"
                ),
                params![
                    key,
                    AttemptOutcome::Failed,
                    left,
                    offset.saturating_sub(failed)
                ],
            )?);
        }
        Ok(rows)
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
        query_all(
            &self.conn,
            "SELECT id, name, threads, version, registered_at, last_seen, state, tasks_done, \
             unhealthy, tags, admin FROM workers ORDER BY registered_at",
            [],
            |r| {
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
                    tags: tags_of(&r.get::<_, String>(9)?),
                    admin: r.get(10)?,
                })
            },
        )
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
        query_all(
            &self.conn,
            "SELECT id, job_id, kind, data, at FROM events WHERE job_id = ?1 AND id > ?2 ORDER BY id",
            params![job, after],
            |r| {
                let data: String = r.get(3)?;
                Ok(EventRow {
                    id: r.get(0)?,
                    job_id: r.get(1)?,
                    kind: r.get(2)?,
                    data: serde_json::from_str(&data).unwrap_or(serde_json::Value::Null),
                    at: r.get(4)?,
                })
            },
        )
    }
    fn state_counts(&self, table: &str) -> StoreResult<Vec<(String, i64)>> {
        let table = match table {
            "jobs" | "tasks" | "workers" | "webhook_deliveries" => table,
            _ => return Ok(Vec::new()),
        };
        query_all(
            &self.conn,
            &format!("SELECT state, COUNT(*) FROM {table} GROUP BY state"),
            [],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
    }
    fn due_deliveries(&self, now: f64, limit: u32) -> StoreResult<Vec<DeliveryRow>> {
        query_all(
            &self.conn,
            &format!(
                "SELECT {DELIVERY_COLS} FROM webhook_deliveries WHERE state = 'pending' \
             AND next_at <= ?1 ORDER BY next_at, seq LIMIT ?2"
            ),
            params![now, limit],
            delivery_row,
        )
    }
    fn next_delivery_at(&self) -> StoreResult<Option<f64>> {
        Ok(cached_row(
            &self.conn,
            "SELECT MIN(next_at) FROM webhook_deliveries WHERE state = 'pending'",
            [],
            |r| r.get(0),
        )?)
    }
    fn record_delivery(&self, id: &str, a: &DeliveryAttempt) -> StoreResult<()> {
        let state = match (&a.error, a.retry_at) {
            (None, _) => "delivered",
            (Some(_), Some(_)) => "pending",
            (Some(_), None) => "failed",
        };
        let delivered_at = a.error.is_none().then(now);
        cached_exec(
            &self.conn,
            "UPDATE webhook_deliveries SET state = ?2, attempts = attempts + 1, \
             next_at = COALESCE(?3, next_at), last_status = ?4, last_error = ?5, \
             delivered_at = ?6 WHERE id = ?1 AND state = 'pending'",
            params![id, state, a.retry_at, a.status, a.error, delivered_at],
        )?;
        Ok(())
    }
    fn deliveries(&self, job: &str) -> StoreResult<Vec<DeliveryRow>> {
        query_all(
            &self.conn,
            &format!(
                "SELECT {DELIVERY_COLS} FROM webhook_deliveries WHERE job_id = ?1 ORDER BY seq"
            ),
            [job],
            delivery_row,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
                priority: 0,
                retry_of: None,
                require_tags: &[],
                owner: None,
                webhooks: None,
            })
            .expect("job");
            db.create_tasks(job, 0, 0..tiles, 0..16).expect("tasks");
        }
        db.register_worker("w", "w", 1, "test", &[])
            .expect("worker");
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

    /// The lease order: priority first (higher first), then submission order; a paused job
    /// leases nothing and, resumed, leases again; a priority changed later counts at the next
    /// lease. A job deleted in a final state takes its rows with it; an active one is kept.
    #[test]
    fn leases_follow_priority_and_skip_paused_jobs() {
        let dir = std::env::temp_dir().join(format!("omis-store-{}", uuid::Uuid::new_v4()));
        std::fs::create_dir_all(&dir).expect("temporary folder");
        let db = SqliteStore::open(&dir.join("db.sqlite")).expect("store");
        for (job, priority) in [("old", 0), ("urgent", 5), ("later", 0)] {
            db.insert_job(&NewJob {
                id: job,
                name: Some(job),
                settings: "{}",
                resolved: "{}",
                scene_id: "s",
                scene_main: "scene.json",
                reference: None,
                accum_bytes: 0,
                priority,
                retry_of: None,
                require_tags: &[],
                owner: None,
                webhooks: None,
            })
            .expect("job");
            db.create_tasks(job, 0, 0..2, 0..16).expect("tasks");
        }
        db.register_worker("w", "w", 1, "test", &[])
            .expect("worker");
        let lease = || db.lease("w", 60.0).expect("lease").map(|t| t.job_id);
        assert_eq!(lease().as_deref(), Some("urgent"));
        assert!(db.pause("urgent").expect("pause"));
        assert!(!db.pause("urgent").expect("pause twice"), "already paused");
        assert_eq!(
            lease().as_deref(),
            Some("old"),
            "a paused job leases nothing"
        );
        assert!(db.set_priority("later", 9).expect("priority"));
        assert_eq!(lease().as_deref(), Some("later"));
        assert!(db.resume("urgent").expect("resume"));
        let urgent = db.job("urgent").expect("job").expect("there");
        assert_eq!(urgent.state, JobState::Running);
        assert!(urgent.paused_at.is_none() && urgent.paused_s >= 0.0);
        assert_eq!(lease().as_deref(), Some("later"));
        assert_eq!(lease().as_deref(), Some("urgent"));
        assert_eq!(lease().as_deref(), Some("old"));
        assert_eq!(lease(), None);
        let page = db
            .jobs_page(&JobQuery {
                name: Some("RG".into()),
                limit: 10,
                ..JobQuery::default()
            })
            .expect("page");
        assert_eq!(
            page.iter().map(|j| j.id.as_str()).collect::<Vec<_>>(),
            ["urgent"]
        );
        assert!(matches!(
            db.delete_job("old", "old.exr").expect("delete"),
            Deleted::NotFinal(JobState::Running)
        ));
        assert!(
            db.set_job_state("old", JobState::Failed, Some("x"))
                .expect("fail")
        );
        assert!(db.requeue_failed("old").expect("requeue"));
        let old = db.job("old").expect("job").expect("there");
        assert_eq!((old.state, old.error), (JobState::Running, None));
        assert!(
            db.set_job_state("old", JobState::Cancelled, None)
                .expect("cancel")
        );
        assert!(matches!(
            db.delete_job("old", "old.exr").expect("delete"),
            Deleted::Removed(_)
        ));
        assert!(db.job("old").expect("job").is_none());
        assert!(matches!(
            db.delete_job("old", "old.exr").expect("delete"),
            Deleted::Missing
        ));
        drop(db);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A job's final state queues one delivery per receiver (global ones first) in the same
    /// transaction; a change that does not end the job, or comes after its end, queues none.
    /// A 500 keeps a delivery pending with its next attempt due later; a 2xx delivers it.
    #[test]
    fn a_final_state_queues_its_webhook_deliveries() {
        let dir = std::env::temp_dir().join(format!("omis-store-{}", uuid::Uuid::new_v4()));
        std::fs::create_dir_all(&dir).expect("temporary folder");
        let global = WebhookTarget {
            url: "http://127.0.0.1:9/all".into(),
            secret: Some("s".into()),
        };
        let db = SqliteStore::open(&dir.join("db.sqlite"))
            .expect("store")
            .with_webhooks(vec![global]);
        let own = r#"[{"url": "http://127.0.0.1:9/own", "secret": null}]"#;
        db.insert_job(&NewJob {
            id: "j",
            name: None,
            settings: "{}",
            resolved: "{}",
            scene_id: "s",
            scene_main: "scene.json",
            reference: None,
            accum_bytes: 0,
            priority: 0,
            retry_of: None,
            require_tags: &[],
            owner: Some("ana"),
            webhooks: Some(own),
        })
        .expect("job");
        assert_eq!(
            db.job("j").expect("job").expect("row").owner.as_deref(),
            Some("ana")
        );
        assert!(
            db.set_job_state("j", JobState::Running, None)
                .expect("running")
        );
        assert!(db.deliveries("j").expect("deliveries").is_empty());
        assert!(db.set_job_state("j", JobState::Done, None).expect("done"));
        assert!(
            !db.set_job_state("j", JobState::Cancelled, None)
                .expect("ended")
        );
        let d = db.deliveries("j").expect("deliveries");
        let urls: Vec<(&str, &str)> = d
            .iter()
            .map(|d| (d.url.as_str(), d.event.as_str()))
            .collect();
        assert_eq!(
            urls,
            [
                ("http://127.0.0.1:9/all", "done"),
                ("http://127.0.0.1:9/own", "done")
            ]
        );
        assert_eq!(db.due_deliveries(now() + 1.0, 10).expect("due").len(), 2);
        let later = now() + 100.0;
        db.record_delivery(
            &d[0].id,
            &DeliveryAttempt {
                status: Some(500),
                error: Some("HTTP 500".into()),
                retry_at: Some(later),
            },
        )
        .expect("attempt");
        db.record_delivery(
            &d[1].id,
            &DeliveryAttempt {
                status: Some(204),
                error: None,
                retry_at: None,
            },
        )
        .expect("attempt");
        assert!(db.due_deliveries(now() + 1.0, 10).expect("due").is_empty());
        assert_eq!(db.next_delivery_at().expect("next"), Some(later));
        let d = db.deliveries("j").expect("deliveries");
        assert_eq!(
            (d[0].state.as_str(), d[0].attempts, d[0].last_status),
            ("pending", 1, Some(500))
        );
        assert_eq!((d[1].state.as_str(), d[1].attempts), ("delivered", 1));
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A sequence is recorded at once, its frames in frame order right after it in the queue:
    /// a job submitted earlier leases first, then the frames one after the other, and the first
    /// frame's lease starts the sequence.
    #[test]
    fn a_sequence_queues_its_frames_in_order() {
        let dir = std::env::temp_dir().join(format!("omis-store-{}", uuid::Uuid::new_v4()));
        std::fs::create_dir_all(&dir).expect("temporary folder");
        let db = SqliteStore::open(&dir.join("db.sqlite")).expect("store");
        let job = |id: &'static str, main: &'static str| NewJob {
            id,
            name: None,
            settings: "{}",
            resolved: "{}",
            scene_id: "s",
            scene_main: main,
            reference: None,
            accum_bytes: 0,
            priority: 0,
            retry_of: None,
            require_tags: &[],
            owner: None,
            webhooks: None,
        };
        db.insert_job(&job("single", "scene.json")).expect("job");
        db.insert_sequence(
            &job("seq", "f_#.json"),
            "1-3",
            &[
                (1, job("f1", "f_1.json")),
                (2, job("f2", "f_2.json")),
                (3, job("f3", "f_3.json")),
            ],
        )
        .expect("sequence");
        for id in ["f3", "f1", "f2", "single"] {
            db.create_tasks(id, 0, 0..2, 0..16).expect("tasks");
        }
        let frames = db.frames("seq").expect("frames");
        let listed: Vec<(&str, Option<u32>, Option<&str>)> = frames
            .iter()
            .map(|j| (j.id.as_str(), j.frame, j.parent_id.as_deref()))
            .collect();
        assert_eq!(
            listed,
            vec![
                ("f1", Some(1), Some("seq")),
                ("f2", Some(2), Some("seq")),
                ("f3", Some(3), Some("seq"))
            ]
        );
        let parent = db.job("seq").expect("job").expect("the parent");
        assert_eq!(parent.frames.as_deref(), Some("1-3"));
        assert_eq!(parent.state, JobState::Queued);
        db.register_worker("w", "w", 1, "test", &[])
            .expect("worker");
        let mut leased = Vec::new();
        while let Some(t) = db.lease("w", 60.0).expect("lease") {
            leased.push(t.job_id);
        }
        assert_eq!(
            leased,
            ["single", "single", "f1", "f1", "f2", "f2", "f3", "f3"]
        );
        let parent = db.job("seq").expect("job").expect("the parent");
        assert_eq!(parent.state, JobState::Running);
        assert!(parent.started_at.is_some());
        drop(db);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
