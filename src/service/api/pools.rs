//! Worker pools and health: an operator's controls of a worker (disable, enable, drain, clearing
//! its unhealthy mark), clearing a job's blocklist entry, and the task history (every attempt at
//! every task) of a job or of a worker.

use super::AppState;
use super::errors::{ApiError, ApiResult, bad};
use crate::protocol::{
    TaskAttemptList, TaskAttemptQuery, WorkerAdmin, WorkerAdminAnswer, WorkerInfo,
};
use crate::service::store::AttemptsOf;
use axum::Json;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;

/// Attempts per page of the task history when the query names no limit.
const DEFAULT_ATTEMPTS: u32 = 100;
/// The most attempts one page of the task history holds.
const MAX_ATTEMPTS: u32 = 1000;

/// Sets worker `id`'s admin state; waiting lease requests look again (an enabled worker may
/// now lease, a disabled one stops being offered tasks at its next look).
fn set_admin(app: &AppState, id: &str, admin: WorkerAdmin) -> ApiResult<Json<WorkerAdminAnswer>> {
    let (admin, unhealthy) = app
        .db()
        .set_worker_admin(id, admin)?
        .ok_or_else(|| ApiError::not_found("worker", id))?;
    tracing::info!("worker {id}: {admin}");
    app.work.notify_waiters();
    Ok(Json(WorkerAdminAnswer {
        worker_id: id.to_string(),
        admin,
        unhealthy,
    }))
}

/// POST /v1/workers/{id}/disable: the worker leases nothing; the tasks in hand finish.
pub(crate) async fn disable_worker(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Json<WorkerAdminAnswer>> {
    set_admin(&app, &id, WorkerAdmin::Disabled)
}

/// POST /v1/workers/{id}/enable: the worker leases again.
pub(crate) async fn enable_worker(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Json<WorkerAdminAnswer>> {
    set_admin(&app, &id, WorkerAdmin::Enabled)
}

/// POST /v1/workers/{id}/drain: the worker leases nothing, finishes the tasks in hand and
/// exits (its heartbeat's answer tells it).
pub(crate) async fn drain_worker(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Json<WorkerAdminAnswer>> {
    set_admin(&app, &id, WorkerAdmin::Draining)
}

/// DELETE /v1/workers/{id}/unhealthy: the worker leases again (if enabled).
pub(crate) async fn clear_unhealthy(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Json<WorkerAdminAnswer>> {
    let admin = app
        .db()
        .clear_unhealthy(&id)?
        .ok_or_else(|| ApiError::not_found("worker", &id))?;
    tracing::info!("worker {id}: unhealthy mark cleared");
    app.work.notify_waiters();
    Ok(Json(WorkerAdminAnswer {
        worker_id: id,
        admin,
        unhealthy: None,
    }))
}

/// DELETE /v1/jobs/{id}/blocklist/{worker}: the worker may take the job's tasks again,
/// those it failed included.
pub(crate) async fn clear_blocklist(
    State(app): State<AppState>,
    Path((id, worker)): Path<(String, String)>,
) -> ApiResult<Json<crate::protocol::JobStatus>> {
    let cleared = {
        let db = app.db();
        if db.job(&id)?.is_none() {
            return Err(ApiError::not_found("job", &id));
        }
        db.clear_blocklist(&id, &worker)?
    };
    if !cleared {
        return Err(ApiError::field(
            StatusCode::NOT_FOUND,
            "worker",
            format!(
                "worker '{worker}' is not blocklisted for job '{id}' and failed none of its tasks"
            ),
        ));
    }
    tracing::info!("job {id}: worker {worker} taken off its blocklist");
    app.work.notify_waiters();
    super::jobs::status_of(&app, &id).map(Json)
}

/// The page of `q` of the attempts of `of`.
fn attempts(
    app: &AppState,
    of: AttemptsOf<'_>,
    q: &TaskAttemptQuery,
) -> ApiResult<Json<TaskAttemptList>> {
    let limit = q.limit.unwrap_or(DEFAULT_ATTEMPTS);
    if limit == 0 || limit > MAX_ATTEMPTS {
        return Err(bad("limit", format!("1 to {MAX_ATTEMPTS}")));
    }
    let after = q.after.unwrap_or(0);
    // One more than the page, to tell whether another follows.
    let mut attempts = app.db().task_attempts(of, q.outcome, limit + 1, after)?;
    let next = (attempts.len() > limit as usize).then(|| after.saturating_add(limit));
    attempts.truncate(limit as usize);
    Ok(Json(TaskAttemptList { attempts, next }))
}

/// GET /v1/jobs/{id}/tasks: the job's task attempts, failed ones first, then by lease time.
pub(crate) async fn job_tasks(
    State(app): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<TaskAttemptQuery>,
) -> ApiResult<Json<TaskAttemptList>> {
    if app.db().job(&id)?.is_none() {
        return Err(ApiError::not_found("job", &id));
    }
    attempts(&app, AttemptsOf::Job(&id), &q)
}

/// GET /v1/workers/{id}/tasks: the worker's task attempts, failed ones first, then by lease
/// time.
pub(crate) async fn worker_tasks(
    State(app): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<TaskAttemptQuery>,
) -> ApiResult<Json<TaskAttemptList>> {
    if app.db().worker_admin(&id)?.is_none() {
        return Err(ApiError::not_found("worker", &id));
    }
    attempts(&app, AttemptsOf::Worker(&id), &q)
}

/// Why no worker serves an active job that requires `tags`, if none does: no live, enabled,
/// healthy worker that is not blocklisted for it has them all.
pub(crate) fn waiting_for(
    job: &str,
    tags: &[String],
    workers: &[WorkerInfo],
    now: f64,
    silent_s: f64,
) -> Option<String> {
    use crate::protocol::WorkerState;
    if tags.is_empty() {
        return None;
    }
    let live = |w: &&WorkerInfo| {
        !matches!(w.state, WorkerState::Gone | WorkerState::Left) && w.last_seen >= now - silent_s
    };
    let tagged: Vec<&WorkerInfo> = workers
        .iter()
        .filter(live)
        .filter(|w| tags.iter().all(|t| w.tags.contains(t)))
        .collect();
    let list = tags.join(", ");
    if tagged.is_empty() {
        return Some(format!("no live worker has tags [{list}]"));
    }
    let serving = tagged.iter().any(|w| {
        w.admin == WorkerAdmin::Enabled
            && w.unhealthy.is_none()
            && !w.blocklisted_jobs.iter().any(|j| j == job)
    });
    (!serving).then(|| {
        format!(
            "every live worker with tags [{list}] is disabled, draining, unhealthy or \
             blocklisted for this job"
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::WorkerState;

    fn worker(id: &str, tags: &[&str]) -> WorkerInfo {
        WorkerInfo {
            id: id.to_string(),
            name: id.to_string(),
            threads: 1,
            version: String::new(),
            registered_at: 0.0,
            last_seen: 100.0,
            state: WorkerState::Idle,
            tasks_done: 0,
            unhealthy: None,
            blocklisted_jobs: Vec::new(),
            tasks: Vec::new(),
            tags: tags.iter().map(|t| t.to_string()).collect(),
            admin: WorkerAdmin::Enabled,
        }
    }

    #[test]
    fn a_tagged_job_waits_for_a_live_enabled_healthy_worker_with_every_tag() {
        let tags = vec!["fast".to_string(), "gpu".to_string()];
        let why = |ws: &[WorkerInfo]| waiting_for("j", &tags, ws, 100.0, 60.0);
        assert_eq!(
            why(&[]).as_deref(),
            Some("no live worker has tags [fast, gpu]")
        );
        assert!(why(&[worker("a", &["gpu"])]).is_some());
        let mut w = worker("a", &["gpu", "fast", "big"]);
        assert_eq!(why(std::slice::from_ref(&w)), None);
        // Not heard from: not live.
        w.last_seen = 10.0;
        assert!(
            why(std::slice::from_ref(&w))
                .unwrap_or_default()
                .contains("no live")
        );
        w.last_seen = 100.0;
        for admin in [WorkerAdmin::Disabled, WorkerAdmin::Draining] {
            w.admin = admin;
            assert!(
                why(std::slice::from_ref(&w))
                    .unwrap_or_default()
                    .contains("disabled")
            );
        }
        w.admin = WorkerAdmin::Enabled;
        w.blocklisted_jobs = vec!["j".to_string()];
        assert!(why(std::slice::from_ref(&w)).is_some());
        // An untagged job never waits for tags.
        assert_eq!(waiting_for("j", &[], &[], 100.0, 60.0), None);
    }
}
