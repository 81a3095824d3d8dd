//! `omis workers` (the worker table; disable, enable, drain, clear-unhealthy, unblock) and
//! `omis tasks` (a job's task history).

use super::client::Client;
use super::service_cmds::{ServerArgs, runtime};
use crate::protocol::{
    AttemptOutcome, JobStatus, TaskAttemptList, WorkerAdminAnswer, WorkerInfo, WorkerList,
};
use crate::service::store::now;
use anyhow::{Result, bail};
use clap::{Args, Subcommand};

#[derive(Args)]
#[command(args_conflicts_with_subcommands = true)]
pub(crate) struct WorkersArgs {
    #[command(subcommand)]
    pub action: Option<WorkerAction>,
    /// Print the raw JSON list instead of the table.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub server: ServerArgs,
}

#[derive(Subcommand)]
pub(crate) enum WorkerAction {
    /// Lease the worker nothing more; the tasks in hand finish.
    Disable(WorkerRef),
    /// Let the worker lease again.
    Enable(WorkerRef),
    /// The worker finishes the tasks in hand, leases nothing more, and exits.
    Drain(WorkerRef),
    /// Clear the worker's unhealthy mark (it failed tasks of several jobs).
    ClearUnhealthy(WorkerRef),
    /// Take the worker off a job's blocklist.
    Unblock(UnblockArgs),
}

#[derive(Args)]
pub(crate) struct WorkerRef {
    /// The worker: its id, a unique prefix of it, or its name.
    pub worker: String,
    #[command(flatten)]
    pub server: ServerArgs,
}

#[derive(Args)]
pub(crate) struct UnblockArgs {
    /// The worker: its id, a unique prefix of it, or its name.
    pub worker: String,
    /// The job whose blocklist it is on.
    #[arg(long)]
    pub job: String,
    #[command(flatten)]
    pub server: ServerArgs,
}

#[derive(Args)]
pub(crate) struct TasksArgs {
    /// The job id.
    pub job: String,
    /// Only the failed attempts.
    #[arg(long)]
    pub failed: bool,
    /// At most this many attempts (the newest pages are fetched until then).
    #[arg(long, default_value_t = 200)]
    pub limit: u32,
    /// Print the raw JSON list instead of the table.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub server: ServerArgs,
}

/// The id of the worker `given` names: an id, a unique id prefix, or a unique name.
async fn worker_id(c: &Client, given: &str) -> Result<String> {
    let list: WorkerList = c.get_json("/v1/workers", &[], "listing workers").await?;
    if list.workers.iter().any(|w| w.id == given) {
        return Ok(given.to_string());
    }
    let found: Vec<&WorkerInfo> = list
        .workers
        .iter()
        .filter(|w| w.id.starts_with(given) || w.name == given)
        .collect();
    match found.as_slice() {
        [w] => Ok(w.id.clone()),
        [] => bail!("no worker has the id, id prefix or name '{given}'"),
        _ => bail!(
            "'{given}' names {} workers; give more of the id",
            found.len()
        ),
    }
}

/// How long ago `t` was, in words.
fn ago(t: f64, now: f64) -> String {
    let s = (now - t).max(0.0);
    if s < 120.0 {
        format!("{s:.0}s ago")
    } else if s < 7200.0 {
        format!("{:.0}m ago", s / 60.0)
    } else {
        format!("{:.0}h ago", s / 3600.0)
    }
}

/// The table of `omis workers`.
fn workers_table(workers: &[WorkerInfo], now: f64) -> String {
    let mut rows = vec![
        [
            "NAME",
            "ID",
            "STATE",
            "ADMIN",
            "TAGS",
            "THREADS",
            "DONE",
            "LAST SEEN",
            "HEALTH",
        ]
        .map(str::to_string),
    ];
    for w in workers {
        let health = match (&w.unhealthy, w.blocklisted_jobs.len()) {
            (Some(why), _) => format!("unhealthy: {why}"),
            (None, 0) => "ok".to_string(),
            (None, n) => format!("blocklisted by {n} job(s)"),
        };
        rows.push([
            w.name.clone(),
            w.id.chars().take(8).collect(),
            w.state.to_string(),
            w.admin.to_string(),
            if w.tags.is_empty() {
                "-".to_string()
            } else {
                w.tags.join(",")
            },
            w.threads.to_string(),
            w.tasks_done.to_string(),
            ago(w.last_seen, now),
            health,
        ]);
    }
    table(&rows)
}

/// Rows as columns padded to their widest cell (the last column unpadded).
fn table<const N: usize>(rows: &[[String; N]]) -> String {
    let mut widths = [0usize; N];
    for r in rows {
        for (w, cell) in widths.iter_mut().zip(r) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let mut out = String::new();
    for r in rows {
        let mut line = String::new();
        for (k, cell) in r.iter().enumerate() {
            if k + 1 == N {
                line.push_str(cell);
            } else {
                line.push_str(&format!("{cell:<w$}  ", w = widths[k]));
            }
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
    out
}

pub(crate) fn workers(a: WorkersArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let Some(action) = a.action else {
            let c = a.server.client()?;
            let list: WorkerList = c.get_json("/v1/workers", &[], "listing workers").await?;
            if a.json {
                println!("{}", serde_json::to_string_pretty(&list)?);
            } else {
                print!("{}", workers_table(&list.workers, now()));
            }
            return Ok(());
        };
        let (r, verb) = match &action {
            WorkerAction::Disable(r) => (r, "disable"),
            WorkerAction::Enable(r) => (r, "enable"),
            WorkerAction::Drain(r) => (r, "drain"),
            WorkerAction::ClearUnhealthy(r) => (r, "unhealthy"),
            WorkerAction::Unblock(u) => {
                let c = u.server.client()?;
                let id = worker_id(&c, &u.worker).await?;
                let st: JobStatus = c
                    .act(
                        reqwest::Method::DELETE,
                        &format!("/v1/jobs/{}/blocklist/{id}", u.job),
                        "unblocking",
                    )
                    .await?;
                println!(
                    "worker {id} may take tasks of job {} again ({} worker(s) still blocklisted)",
                    st.id,
                    st.blocklisted_workers.len()
                );
                return Ok(());
            }
        };
        let c = r.server.client()?;
        let id = worker_id(&c, &r.worker).await?;
        let (method, path) = if verb == "unhealthy" {
            (
                reqwest::Method::DELETE,
                format!("/v1/workers/{id}/unhealthy"),
            )
        } else {
            (reqwest::Method::POST, format!("/v1/workers/{id}/{verb}"))
        };
        let ans: WorkerAdminAnswer = c.act(method, &path, verb).await?;
        println!("worker {}: {}", ans.worker_id, ans.admin);
        Ok(())
    })
}

pub(crate) fn tasks(a: TasksArgs) -> Result<()> {
    if a.limit == 0 {
        bail!("--limit must be >= 1");
    }
    runtime()?.block_on(async move {
        let c = a.server.client()?;
        let mut attempts = Vec::new();
        let mut after = 0u32;
        loop {
            let mut query = vec![
                ("limit", a.limit.min(1000).to_string()),
                ("after", after.to_string()),
            ];
            if a.failed {
                query.push(("outcome", AttemptOutcome::Failed.to_string()));
            }
            let page: TaskAttemptList = c
                .get_json(&format!("/v1/jobs/{}/tasks", a.job), &query, "task history")
                .await?;
            attempts.extend(page.attempts);
            match page.next {
                Some(n) if attempts.len() < a.limit as usize => after = n,
                _ => break,
            }
        }
        attempts.truncate(a.limit as usize);
        if a.json {
            println!("{}", serde_json::to_string_pretty(&attempts)?);
            return Ok(());
        }
        let mut rows = vec![
            [
                "TASK", "KIND", "PASS", "TILE", "TRY", "WORKER", "OUTCOME", "SECONDS", "ERROR",
            ]
            .map(str::to_string),
        ];
        for t in &attempts {
            rows.push([
                t.task_id.to_string(),
                t.kind.to_string(),
                t.pass.to_string(),
                t.tile.to_string(),
                t.attempt.to_string(),
                t.worker_id.chars().take(8).collect(),
                t.outcome.to_string(),
                t.seconds.map_or("-".to_string(), |s| format!("{s:.2}")),
                t.error.clone().unwrap_or_default().replace('\n', " "),
            ]);
        }
        print!("{}", table(&rows));
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_pads_every_column_but_the_last() {
        let rows = vec![
            ["A".to_string(), "BB".to_string(), "C".to_string()],
            ["long".to_string(), "x".to_string(), "tail text".to_string()],
        ];
        assert_eq!(table(&rows), "A     BB  C\nlong  x   tail text\n");
    }
}
