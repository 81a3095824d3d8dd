//! Worker pools and health: an operator's controls of a worker (disable, enable, drain, clearing
//! its unhealthy mark), clearing a job's blocklist entry, and the task history (every attempt at
//! every task) of a job or of a worker.

use super::AppState;
use super::auth::{self, Principal};
use super::errors::{ApiError, ApiResult, bad};
use crate::protocol::{TaskAttemptList, TaskAttemptQuery, WorkerAdmin, WorkerAdminAnswer};
use crate::service::store::AttemptsOf;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::{Extension, Json};

/// Attempts per page of the task history when the query names no limit.
const DEFAULT_ATTEMPTS: u32 = 100;
/// The most attempts one page of the task history holds.
const MAX_ATTEMPTS: u32 = 1000;

/// Sets worker `id`'s admin state; waiting lease requests look again (an enabled worker may
/// now lease, a disabled one stops being offered tasks at its next look).
/// Admins only, as every worker action.
fn set_admin(
    app: &AppState,
    who: &Principal,
    id: &str,
    admin: WorkerAdmin,
) -> ApiResult<Json<WorkerAdminAnswer>> {
    auth::require_admin(who)?;
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
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<Json<WorkerAdminAnswer>> {
    set_admin(&app, &who, &id, WorkerAdmin::Disabled)
}

/// POST /v1/workers/{id}/enable: the worker leases again.
pub(crate) async fn enable_worker(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<Json<WorkerAdminAnswer>> {
    set_admin(&app, &who, &id, WorkerAdmin::Enabled)
}

/// POST /v1/workers/{id}/drain: the worker leases nothing, finishes the tasks in hand and
/// exits (its heartbeat's answer tells it).
pub(crate) async fn drain_worker(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<Json<WorkerAdminAnswer>> {
    set_admin(&app, &who, &id, WorkerAdmin::Draining)
}

/// DELETE /v1/workers/{id}/unhealthy: the worker leases again (if enabled).
pub(crate) async fn clear_unhealthy(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<Json<WorkerAdminAnswer>> {
    auth::require_admin(&who)?;
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
    Extension(who): Extension<Principal>,
    Path((id, worker)): Path<(String, String)>,
) -> ApiResult<Json<crate::protocol::JobStatus>> {
    let job = app.db().job(&id)?;
    let Some(job) = job else {
        return Err(ApiError::not_found("job", &id));
    };
    auth::require_owner(&who, &id, job.owner.as_deref())?;
    let cleared = app.db().clear_blocklist(&id, &worker)?;
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
