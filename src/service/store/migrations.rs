//! The SQLite schema as numbered migrations. The table `schema_version` records the version of
//! a database (one row); migration N upgrades version N - 1 to N, in one transaction with the
//! new version recorded. Version 0 is an empty database, so a new one is made by running every
//! migration in turn, the same way an old one is brought up to date. A database of a version
//! newer than `MIGRATIONS` knows is refused before anything is written to it.
//!
//! The statements of a migration are never edited once released: a database made by it exists
//! somewhere. A change of schema is a new migration at the end of the list.

use super::{StoreError, StoreResult};
use rusqlite::Connection;

/// Every migration, in order: `MIGRATIONS[k]` upgrades version k to k + 1.
pub(super) const MIGRATIONS: &[&str] = &[
    // 1: the base schema: jobs, render tasks (one per tile and pass), workers, the relMSE series
    // and the event log.
    "CREATE TABLE IF NOT EXISTS jobs (
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
     CREATE TABLE IF NOT EXISTS tasks (
       id INTEGER PRIMARY KEY AUTOINCREMENT,
       job_id TEXT NOT NULL REFERENCES jobs(id),
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
       UNIQUE (job_id, pass, tile)
     );
     CREATE INDEX IF NOT EXISTS tasks_state ON tasks (state, job_id, pass, tile);
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
     CREATE INDEX IF NOT EXISTS events_job ON events (job_id, id);",
    // 2: where a done task's accepted result lies in its pass's result log (a done task without
    // it is rendered again).
    "ALTER TABLE tasks ADD COLUMN result_at INTEGER;
     ALTER TABLE tasks ADD COLUMN result_len INTEGER;",
    // 3: merge tasks. The tasks table is made again with their `kind` (and a uniqueness that
    // includes it); every task it held is a render task. A merge task's `tile` is its band
    // group's index and s0 .. s1 its bands; the queue index orders a job's queued tasks merges
    // first ('merge' < 'render'), then by pass and tile.
    "ALTER TABLE tasks RENAME TO tasks_v1;
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
     INSERT INTO tasks (id, job_id, pass, tile, s0, s1, state, attempt, worker_id,
       lease_expires, failures, last_error, result_at, result_len)
     SELECT id, job_id, pass, tile, s0, s1, state, attempt, worker_id,
       lease_expires, failures, last_error, result_at, result_len FROM tasks_v1;
     DROP TABLE tasks_v1;",
    // 4: failed and lost attempts (what keeps a task from a worker that failed it), per-job
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
    // 5: farm controls: a job's priority (the lease order: priority, then seq), when it was
    // paused and the seconds it spent paused before (not rendering time), the job a retry
    // repeats; indexes for the lease order, the filtered job list and retention.
    "ALTER TABLE jobs ADD COLUMN priority INTEGER NOT NULL DEFAULT 0;
     ALTER TABLE jobs ADD COLUMN paused_at REAL;
     ALTER TABLE jobs ADD COLUMN paused_s REAL NOT NULL DEFAULT 0;
     ALTER TABLE jobs ADD COLUMN retry_of TEXT;
     CREATE INDEX jobs_lease_order ON jobs (state, priority DESC, seq);
     CREATE INDEX jobs_seq ON jobs (seq);
     CREATE INDEX jobs_finished ON jobs (finished_at);",
    // 6: worker pools and task history: a worker's tags and what an operator allows it
    // (enabled, disabled, draining), the tags a job requires (both a sorted, comma-separated
    // list; '' for none), and every attempt at every task, kept after its task row is deleted.
    "ALTER TABLE workers ADD COLUMN tags TEXT NOT NULL DEFAULT '';
     ALTER TABLE workers ADD COLUMN admin TEXT NOT NULL DEFAULT 'enabled';
     ALTER TABLE jobs ADD COLUMN require_tags TEXT NOT NULL DEFAULT '';
     CREATE TABLE task_attempts (
       task_id INTEGER NOT NULL,
       attempt INTEGER NOT NULL,
       job_id TEXT NOT NULL,
       kind TEXT NOT NULL,
       pass INTEGER NOT NULL,
       tile INTEGER NOT NULL,
       worker_id TEXT NOT NULL,
       leased_at REAL NOT NULL,
       ended_at REAL,
       outcome TEXT NOT NULL,
       error TEXT,
       PRIMARY KEY (task_id, attempt)
     );
     CREATE INDEX task_attempts_job ON task_attempts (job_id, leased_at);
     CREATE INDEX task_attempts_job_outcome ON task_attempts (job_id, outcome, leased_at);
     CREATE INDEX task_attempts_worker ON task_attempts (worker_id, leased_at);
     CREATE INDEX task_attempts_worker_outcome ON task_attempts (worker_id, outcome, leased_at);",
    // 7: who submitted a job (NULL: no user, as before users existed), the job's own webhook
    // receivers (JSON), and the webhook outbox: a delivery row is written in the transaction
    // that ends its job, so a restart resumes every delivery not yet made.
    "ALTER TABLE jobs ADD COLUMN owner TEXT;
     ALTER TABLE jobs ADD COLUMN webhooks TEXT;
     CREATE TABLE webhook_deliveries (
       seq INTEGER PRIMARY KEY AUTOINCREMENT,
       id TEXT NOT NULL UNIQUE,
       job_id TEXT NOT NULL,
       event TEXT NOT NULL,
       url TEXT NOT NULL,
       secret TEXT,
       at REAL NOT NULL,
       state TEXT NOT NULL,
       attempts INTEGER NOT NULL DEFAULT 0,
       next_at REAL NOT NULL,
       last_status INTEGER,
       last_error TEXT,
       delivered_at REAL
     );
     CREATE INDEX webhook_deliveries_due ON webhook_deliveries (state, next_at);
     CREATE INDEX webhook_deliveries_job ON webhook_deliveries (job_id, seq);",
    // 8: sequences. A sequence is a parent job (`frames`: its frame range, as text) whose frames
    // are ordinary jobs, its children (`parent_id`, `frame`).
    "ALTER TABLE jobs ADD COLUMN parent_id TEXT;
     ALTER TABLE jobs ADD COLUMN frame INTEGER;
     ALTER TABLE jobs ADD COLUMN frames TEXT;
     CREATE INDEX jobs_parent ON jobs (parent_id, frame);",
];

/// The version whose schema `PRAGMA user_version` 0 stood for before `schema_version` existed:
/// that pragma counted the migrations after it.
const USER_VERSION_BASE: i64 = 3;

/// Brings the database of `conn` to the newest version, one migration at a time, or refuses it
/// when it is newer than this omis.
pub(super) fn migrate(conn: &Connection) -> StoreResult<()> {
    let known = MIGRATIONS.len() as i64;
    let have = version(conn)?;
    if have > known {
        return Err(StoreError::new(format!(
            "the database has schema version {have}, newer than this omis knows ({known}); \
             run the omis that wrote it"
        )));
    }
    if !has_table(conn, "schema_version")? {
        let tx = conn.unchecked_transaction()?;
        tx.execute_batch("CREATE TABLE schema_version (version INTEGER NOT NULL)")?;
        tx.execute("INSERT INTO schema_version (version) VALUES (?1)", [have])?;
        tx.commit()?;
    }
    for (k, m) in MIGRATIONS.iter().enumerate().skip(have.max(0) as usize) {
        let v = k as i64 + 1;
        let tx = conn.unchecked_transaction()?;
        tx.execute_batch(m)?;
        tx.execute("UPDATE schema_version SET version = ?1", [v])?;
        // Kept equal to the version: an omis from before `schema_version` reads this pragma
        // and refuses a database newer than it knows.
        tx.pragma_update(None, "user_version", v)?;
        tx.commit()?;
    }
    Ok(())
}

/// The schema version of the database of `conn`.
fn version(conn: &Connection) -> StoreResult<i64> {
    if has_table(conn, "schema_version")? {
        return Ok(conn.query_row("SELECT version FROM schema_version", [], |r| r.get(0))?);
    }
    unrecorded_version(conn)
}

/// The version of a database that has no `schema_version` table: one written before the table
/// existed, or an empty one (0). The omis that wrote it counted the migrations after version
/// `USER_VERSION_BASE` in `PRAGMA user_version`; before that it kept no count, and the tasks
/// table's columns tell versions 1 to 3 apart (the only time a column is looked for).
fn unrecorded_version(conn: &Connection) -> StoreResult<i64> {
    let user: i64 = conn.query_row("PRAGMA user_version", [], |r| r.get(0))?;
    if user > 0 {
        return Ok(USER_VERSION_BASE + user);
    }
    let columns: Vec<String> = {
        let mut st = conn.prepare("SELECT name FROM pragma_table_info('tasks')")?;
        st.query_map([], |r| r.get(0))?
            .collect::<rusqlite::Result<_>>()?
    };
    let has = |c: &str| columns.iter().any(|n| n == c);
    Ok(if columns.is_empty() {
        0
    } else if has("kind") {
        3
    } else if has("result_at") {
        2
    } else {
        1
    })
}

fn has_table(conn: &Connection, name: &str) -> StoreResult<bool> {
    Ok(conn.query_row(
        "SELECT EXISTS (SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?1)",
        [name],
        |r| r.get(0),
    )?)
}

#[cfg(test)]
mod tests {
    use super::super::{JobStore, SqliteStore, TaskRow};
    use super::*;
    use crate::protocol::{JobState, TaskKind, TaskState};

    /// The schema of a database: every table and index as SQLite records it.
    fn schema(conn: &Connection) -> Vec<(String, String)> {
        let mut st = conn
            .prepare(
                "SELECT name, COALESCE(sql, '') FROM sqlite_master \
                 WHERE name NOT LIKE 'sqlite_%' ORDER BY name",
            )
            .expect("schema query");
        st.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
            .expect("schema")
            .collect::<rusqlite::Result<_>>()
            .expect("schema rows")
    }

    /// A database of every older schema version, as the omis of that version left it (its
    /// statements are the migrations up to it; it recorded no `schema_version`, and counted in
    /// `PRAGMA user_version` only past version 3), with a job, a done task and a worker, opens:
    /// it is migrated to the newest version with its rows, and its schema is a new database's.
    /// One of a newer version is refused, with nothing written; a damaged one too.
    #[test]
    fn older_schemas_are_migrated_and_newer_or_damaged_ones_refused() {
        let dir = std::env::temp_dir().join(format!("omis-store-{}", uuid::Uuid::new_v4()));
        std::fs::create_dir_all(&dir).expect("temporary folder");
        let fresh = dir.join("fresh.sqlite");
        drop(SqliteStore::open(&fresh).expect("a new database"));
        let fresh_schema = schema(&Connection::open(&fresh).expect("open"));
        let known = MIGRATIONS.len() as i64;
        for from in 1..=known {
            let path = dir.join(format!("v{from}.sqlite"));
            {
                let conn = Connection::open(&path).expect("open");
                for m in &MIGRATIONS[..from as usize] {
                    conn.execute_batch(m).expect("migration");
                }
                conn.pragma_update(None, "user_version", (from - USER_VERSION_BASE).max(0))
                    .expect("version");
                conn.execute(
                    "INSERT INTO jobs (id, seq, state, settings, resolved, scene_id, \
                     scene_main, created_at, passes_done) \
                     VALUES ('j', 1, 'running', '{}', '{}', 's', 'scene.json', 1.5, 2)",
                    [],
                )
                .expect("a job");
                let (cols, values) = if from >= 2 {
                    (", result_at, result_len", ", 4096, 100")
                } else {
                    ("", "")
                };
                conn.execute(
                    &format!(
                        "INSERT INTO tasks (id, job_id, pass, tile, s0, s1, state, attempt{cols}) \
                         VALUES (7, 'j', 2, 3, 4, 8, 'done', 1{values})"
                    ),
                    [],
                )
                .expect("a task");
                conn.execute(
                    "INSERT INTO workers (id, name, threads, version, registered_at, \
                     last_seen, state) VALUES ('w', 'w', 1, 'old', 0, 0, 'idle')",
                    [],
                )
                .expect("a worker");
            }
            let db = SqliteStore::open(&path).unwrap_or_else(|e| panic!("from {from}: {e}"));
            let job = db.job("j").expect("job").expect("the job is there");
            assert_eq!(
                (job.state, job.passes_done, job.scene_main.as_str()),
                (JobState::Running, 2, "scene.json"),
                "from {from}"
            );
            // Jobs from before priorities: priority 0, never paused, no retry.
            assert_eq!(
                (
                    job.priority,
                    job.paused_at,
                    job.paused_s,
                    job.retry_of.as_deref()
                ),
                (0, None, 0.0, None),
                "from {from}"
            );
            assert_eq!(
                (job.parent_id.as_deref(), job.frame, job.frames.as_deref()),
                (None, None, None),
                "an older job is no sequence, from {from}"
            );
            let task: TaskRow = db.task(7).expect("task").expect("the task is there");
            assert_eq!(
                (
                    task.kind, task.state, task.pass, task.tile, task.s0, task.s1
                ),
                (TaskKind::Render, TaskState::Done, 2, 3, 4, 8),
                "from {from}"
            );
            let result = (from >= 2).then_some(4096..4196);
            assert_eq!(task.result, result, "from {from}");
            // A job from before users has no owner: anyone's (an admin's) to act on.
            assert_eq!(job.owner, None, "from {from}");
            let workers = db.workers().expect("workers");
            assert_eq!(workers.len(), 1, "from {from}");
            assert_eq!(workers[0].unhealthy, None);
            // Pools: an old worker is enabled and untagged; an old job requires no tag.
            assert_eq!(workers[0].admin, crate::protocol::WorkerAdmin::Enabled);
            assert!(workers[0].tags.is_empty());
            assert!(job.require_tags.is_empty());
            assert!(
                db.task_attempts(super::super::AttemptsOf::Job("j"), None, 10, 0)
                    .expect("history")
                    .is_empty()
            );
            drop(db);
            // Opening it again changes nothing.
            drop(SqliteStore::open(&path).expect("opens again"));
            let conn = Connection::open(&path).expect("open");
            assert_eq!(version(&conn).expect("version"), known, "from {from}");
            assert_eq!(schema(&conn), fresh_schema, "from {from}");
        }
        // Newer, recorded either way: refused, and left as it was.
        let newer = dir.join("newer.sqlite");
        {
            let conn = Connection::open(&newer).expect("open");
            conn.execute_batch(
                "CREATE TABLE schema_version (version INTEGER NOT NULL); \
                 INSERT INTO schema_version VALUES (999);",
            )
            .expect("version");
        }
        let e = SqliteStore::open(&newer).err().expect("refused");
        assert!(e.to_string().contains("schema version 999"), "{e}");
        let older_omis = dir.join("older-omis.sqlite");
        {
            let conn = Connection::open(&older_omis).expect("open");
            conn.pragma_update(None, "user_version", 999)
                .expect("version");
        }
        let e = SqliteStore::open(&older_omis).err().expect("refused");
        assert!(e.to_string().contains("newer than this omis"), "{e}");
        let conn = Connection::open(&older_omis).expect("open");
        assert!(!has_table(&conn, "schema_version").expect("tables"));
        let damaged = dir.join("damaged.sqlite");
        std::fs::write(&damaged, vec![0x5au8; 16384]).expect("garbage");
        assert!(SqliteStore::open(&damaged).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
