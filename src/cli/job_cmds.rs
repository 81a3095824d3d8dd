//! The job controls of the command line: `omis jobs` (a table), `omis status` (a readable
//! summary of the farm or of one job; `--json` for the raw document), `pause`, `resume`,
//! `requeue`, `retry`, `delete` and `priority`. A job is named by its id or a unique prefix of
//! it.

use super::client::Client;
use super::service_cmds::{ServerArgs, runtime};
use crate::protocol::{JobState, JobStatus, WorkerInfo, WorkerState};
use anyhow::{Result, bail};
use clap::Args;
use std::collections::BTreeMap;

/// The id of the job `prefix` names: itself when it is a job's id, else the one job whose id
/// starts with it (none or several: an error naming them).
async fn resolve(c: &Client, prefix: &str) -> Result<String> {
    let prefix = prefix.trim();
    if prefix.is_empty() {
        bail!("the job id is empty");
    }
    let jobs = c.jobs(&[]).await?;
    if jobs.iter().any(|j| j.id == prefix) {
        return Ok(prefix.to_string());
    }
    let matching: Vec<&JobStatus> = jobs.iter().filter(|j| j.id.starts_with(prefix)).collect();
    match matching.as_slice() {
        [one] => Ok(one.id.clone()),
        [] => bail!("no job's id starts with '{prefix}'"),
        many => bail!(
            "'{prefix}' is ambiguous: {} jobs' ids start with it ({}); give more of the id",
            many.len(),
            many.iter()
                .take(5)
                .map(|j| j.id.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// A number of seconds as `1h02m`, `3m05s` or `12s`.
fn duration(s: f64) -> String {
    let s = s.max(0.0).round() as u64;
    match s {
        0..60 => format!("{s}s"),
        60..3600 => format!("{}m{:02}s", s / 60, s % 60),
        3600..86400 => format!("{}h{:02}m", s / 3600, s % 3600 / 60),
        _ => format!("{}d{:02}h", s / 86400, s % 86400 / 3600),
    }
}

/// A job's progress in words: samples per pixel merged of the target (or of the time budget).
fn progress(j: &JobStatus) -> String {
    match (j.spp_target, j.time_budget_s) {
        (Some(t), _) => format!(
            "{}/{t} spp ({:.0}%)",
            j.spp_done,
            100.0 * j.spp_done as f64 / t.max(1) as f64
        ),
        (None, Some(b)) => format!(
            "{} spp, {}/{}",
            j.spp_done,
            duration(j.elapsed_s),
            duration(b)
        ),
        (None, None) => format!("{} spp", j.spp_done),
    }
}

/// The first 8 characters of an id.
fn short(id: &str) -> &str {
    id.get(..8).unwrap_or(id)
}

/// Cuts `s` to `n` characters (an ellipsis marks a cut).
fn clip(s: &str, n: usize) -> String {
    if s.chars().count() <= n {
        s.to_string()
    } else {
        let mut t: String = s.chars().take(n.saturating_sub(1)).collect();
        t.push('…');
        t
    }
}

#[derive(Args)]
pub(crate) struct JobsArgs {
    /// Only jobs in these states (comma-separated: queued, running, paused, done, failed,
    /// cancelled).
    #[arg(long)]
    pub state: Option<String>,
    /// Only jobs whose name contains this (case-insensitive).
    #[arg(long)]
    pub name: Option<String>,
    /// The jobs' status documents as one JSON array.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub server: ServerArgs,
}

/// `omis jobs`: a table of the jobs, oldest first.
pub(crate) fn jobs(a: JobsArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let c = a.server.client()?;
        let mut q = Vec::new();
        if let Some(s) = &a.state {
            q.push(("state", s.clone()));
        }
        if let Some(n) = &a.name {
            q.push(("name", n.clone()));
        }
        let jobs = c.jobs(&q).await?;
        if a.json {
            println!("{}", serde_json::to_string_pretty(&jobs)?);
            return Ok(());
        }
        let now = crate::service::store::now();
        println!(
            "{:<8}  {:<24}  {:<9}  {:>4}  {:<24}  {:>9}  {:>7}",
            "ID", "NAME", "STATE", "PRI", "PROGRESS", "RELMSE", "AGE"
        );
        for j in &jobs {
            println!(
                "{:<8}  {:<24}  {:<9}  {:>4}  {:<24}  {:>9}  {:>7}",
                short(&j.id),
                clip(j.name.as_deref().unwrap_or("-"), 24),
                j.state.as_str(),
                j.priority,
                clip(&progress(j), 24),
                j.relmse.map_or("-".to_string(), |r| format!("{r:.3e}")),
                duration(now - j.created_at)
            );
        }
        if jobs.is_empty() {
            eprintln!("no jobs");
        }
        Ok(())
    })
}

#[derive(Args)]
pub(crate) struct StatusArgs {
    /// A job (its id or a unique prefix); without it, a summary of the farm.
    pub job: Option<String>,
    /// The raw JSON: the job's status document, or the farm summary as an object.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub server: ServerArgs,
}

/// `omis status [JOB]`.
pub(crate) fn status(a: StatusArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let c = a.server.client()?;
        match &a.job {
            Some(prefix) => {
                let id = resolve(&c, prefix).await?;
                let st = c.status(&id).await?;
                if a.json {
                    println!("{}", serde_json::to_string_pretty(&st)?);
                } else {
                    print!("{}", job_summary(&st));
                }
            }
            None => {
                let jobs = c.jobs(&[]).await?;
                let workers = c.workers().await?.workers;
                let summary = farm_summary(&jobs, &workers);
                if a.json {
                    println!("{}", serde_json::to_string_pretty(&summary.json)?);
                } else {
                    print!("{}", summary.text);
                }
            }
        }
        Ok(())
    })
}

/// One job in readable lines.
fn job_summary(j: &JobStatus) -> String {
    let mut out = String::new();
    let mut line = |k: &str, v: String| out.push_str(&format!("{k:<10} {v}\n"));
    line("job", j.id.clone());
    if let Some(n) = &j.name {
        line("name", n.clone());
    }
    line("state", j.state.to_string());
    if let Some(e) = &j.error {
        line("error", e.clone());
    }
    if let Some(r) = &j.retry_of {
        line("retry of", r.clone());
    }
    line("priority", j.priority.to_string());
    line("image", format!("{}x{}", j.width, j.height));
    line("progress", progress(j));
    line(
        "passes",
        match j.passes_total {
            Some(t) => format!("{}/{t} merged", j.passes_done),
            None => format!("{} merged", j.passes_done),
        },
    );
    if j.state.is_active() {
        line(
            "tiles",
            format!("{} of {} done in the pass", j.tiles_done, j.tiles_per_pass),
        );
    }
    let mut time = duration(j.elapsed_s);
    if j.paused_s > 0.0 {
        time.push_str(&format!(" (paused {})", duration(j.paused_s)));
    }
    line("rendering", time);
    line(
        "eta",
        match (j.state, j.eta_s) {
            (JobState::Paused, _) => "paused".to_string(),
            (s, _) if s.is_final() => "-".to_string(),
            (_, Some(e)) => duration(e),
            (_, None) => "unknown".to_string(),
        },
    );
    if let Some(r) = j.relmse {
        line("relMSE", format!("{r:.4e}"));
    }
    out
}

/// The farm at a glance, in words and as JSON.
struct FarmSummary {
    text: String,
    json: serde_json::Value,
}

fn farm_summary(jobs: &[JobStatus], workers: &[WorkerInfo]) -> FarmSummary {
    let mut by_state: BTreeMap<&str, usize> = BTreeMap::new();
    for j in jobs {
        *by_state.entry(j.state.as_str()).or_default() += 1;
    }
    let mut workers_by_state: BTreeMap<&str, usize> = BTreeMap::new();
    for w in workers {
        *workers_by_state.entry(w.state.as_str()).or_default() += 1;
    }
    let unhealthy = workers.iter().filter(|w| w.unhealthy.is_some()).count();
    let threads: u32 = workers
        .iter()
        .filter(|w| matches!(w.state, WorkerState::Idle | WorkerState::Busy))
        .map(|w| w.threads)
        .sum();
    // The queue as the lease query orders it: priority, then age; paused jobs after.
    let mut queue: Vec<&JobStatus> = jobs.iter().filter(|j| j.state.is_active()).collect();
    queue.sort_by(|a, b| {
        (a.state == JobState::Paused)
            .cmp(&(b.state == JobState::Paused))
            .then(b.priority.cmp(&a.priority))
            .then(a.created_at.total_cmp(&b.created_at))
    });
    let counts = |m: &BTreeMap<&str, usize>| {
        if m.is_empty() {
            "none".to_string()
        } else {
            m.iter()
                .map(|(k, v)| format!("{v} {k}"))
                .collect::<Vec<_>>()
                .join(", ")
        }
    };
    let mut text = format!("jobs      {} ({})\n", jobs.len(), counts(&by_state));
    text.push_str(&format!(
        "workers   {} ({}), {threads} threads live{}\n",
        workers.len(),
        counts(&workers_by_state),
        if unhealthy > 0 {
            format!(", {unhealthy} unhealthy")
        } else {
            String::new()
        }
    ));
    if queue.is_empty() {
        text.push_str("queue     empty\n");
    } else {
        text.push_str("queue     (priority, then age)\n");
        for j in queue.iter().take(10) {
            text.push_str(&format!(
                "  {:<8}  {:<24}  {:<8}  pri {:>3}  {}\n",
                short(&j.id),
                clip(j.name.as_deref().unwrap_or("-"), 24),
                j.state.as_str(),
                j.priority,
                progress(j)
            ));
        }
        if queue.len() > 10 {
            text.push_str(&format!("  ... and {} more\n", queue.len() - 10));
        }
    }
    let json = serde_json::json!({
        "jobs": by_state,
        "workers": workers_by_state,
        "workers_unhealthy": unhealthy,
        "threads": threads,
        "queue": queue.iter().map(|j| serde_json::json!({
            "id": j.id,
            "name": j.name,
            "state": j.state,
            "priority": j.priority,
            "spp_done": j.spp_done,
            "spp_target": j.spp_target,
        })).collect::<Vec<_>>(),
    });
    FarmSummary { text, json }
}

#[derive(Args)]
pub(crate) struct JobArgs {
    /// The job: its id or a unique prefix of it.
    pub job: String,
    #[command(flatten)]
    pub server: ServerArgs,
}

/// `omis pause|resume|requeue|retry JOB`: prints the job's state after it (a retry: the new
/// job's id).
pub(crate) fn action(a: JobArgs, action: &'static str) -> Result<()> {
    runtime()?.block_on(async move {
        let c = a.server.client()?;
        let id = resolve(&c, &a.job).await?;
        let st = c.job_action(&id, action).await?;
        if action == "retry" {
            println!("{}", st.id);
        } else {
            println!("{}", st.state);
        }
        Ok(())
    })
}

/// `omis delete JOB`.
pub(crate) fn delete(a: JobArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let c = a.server.client()?;
        let id = resolve(&c, &a.job).await?;
        c.delete(&id).await?;
        println!("deleted {id}");
        Ok(())
    })
}

#[derive(Args)]
pub(crate) struct PriorityArgs {
    /// The job: its id or a unique prefix of it.
    pub job: String,
    /// Its new priority (higher first).
    #[arg(allow_hyphen_values = true)]
    pub priority: i32,
    #[command(flatten)]
    pub server: ServerArgs,
}

/// `omis priority JOB N`.
pub(crate) fn priority(a: PriorityArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let c = a.server.client()?;
        let id = resolve(&c, &a.job).await?;
        let st = c.set_priority(&id, a.priority).await?;
        println!("{}", st.priority);
        Ok(())
    })
}
