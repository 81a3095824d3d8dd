//! Workers: the worker protocol under /v1/worker/* (register, lease, heartbeat, deregister,
//! scene download, result upload, failure report) and the worker list (GET /v1/workers).

use super::errors::{ApiError, ApiResult, JsonBody, bad};
use super::{AppState, is_safe_id, scenes};
use crate::film::Tile;
use crate::protocol::{
    DeregisterAnswer, DeregisterRequest, FailRequest, HeartbeatAnswer, HeartbeatRequest, JobState,
    Lease, LeaseRequest, LeasedJob, LeasedTask, OkAnswer, RegisterRequest, Registration,
    ResultAnswer, ResultQuery, TaskKind, TaskState, WorkerAdmin, WorkerList, WorkerState,
    validate_tags,
};
use crate::service::accept::{self, Accepted};
use crate::service::buffers::{self, Pooled};
use crate::service::store::{JobRow, Outcome, TaskRow};
use crate::service::{Metrics, jobs, runtime, upload};
use axum::Json;
use axum::body::{Body, Bytes};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use std::time::Duration;

/// GET /v1/workers (client token).
pub(crate) async fn list_workers(State(app): State<AppState>) -> ApiResult<Json<WorkerList>> {
    let workers = app.db().workers()?;
    Ok(Json(WorkerList { workers }))
}

fn unknown_worker() -> ApiError {
    ApiError::field(
        StatusCode::NOT_FOUND,
        "worker_id",
        "unknown worker; register again",
    )
}

/// POST /v1/worker/register.
pub(crate) async fn register(
    State(app): State<AppState>,
    JsonBody(r): JsonBody<RegisterRequest>,
) -> ApiResult<Json<Registration>> {
    let id = match r.id {
        Some(id) if is_safe_id(&id) => id,
        Some(_) => return Err(bad("id", "not a worker id")),
        None => uuid::Uuid::new_v4().to_string(),
    };
    let name: String = r
        .name
        .chars()
        .filter(|c| !c.is_control())
        .take(200)
        .collect();
    let tags = validate_tags(&r.tags).map_err(|e| bad("tags", e))?;
    app.db()
        .register_worker(&id, &name, r.threads.clamp(1, 4096), &r.version, &tags)?;
    tracing::info!("worker {name} ({id}) registered with {} threads", r.threads);
    Ok(Json(Registration {
        worker_id: id,
        lease_seconds: app.cfg.lease_s,
        heartbeat_seconds: (app.cfg.lease_s / 4.0).max(0.5),
    }))
}

/// POST /v1/worker/lease: a task, or 204 after `wait_s` without one.
pub(crate) async fn lease(
    State(app): State<AppState>,
    JsonBody(r): JsonBody<LeaseRequest>,
) -> ApiResult<Response> {
    if !app.db().touch_worker(&r.worker_id, None)? {
        return Err(unknown_worker());
    }
    let wait = r
        .wait_s
        .unwrap_or(20.0)
        .clamp(0.0, app.cfg.max_lease_wait_s.clamp(0.0, 30.0));
    let deadline = tokio::time::Instant::now() + Duration::from_secs_f64(wait);
    loop {
        let notified = app.work.notified();
        tokio::pin!(notified);
        notified.as_mut().enable();
        let leased = {
            let db = app.db();
            match db.lease(&r.worker_id, app.cfg.lease_s)? {
                Some(t) => {
                    let job = db.job(&t.job_id)?;
                    Some((t, job))
                }
                None => None,
            }
        };
        if let Some((task, Some(job))) = leased {
            let res = runtime::resolved(&app, &job)?;
            let (rect, samples, bands) = match task.kind {
                TaskKind::Render => (
                    jobs::tile_rect(&res, task.tile)
                        .ok_or_else(|| ApiError::internal("tile index out of range"))?,
                    [task.s0, task.s1],
                    None,
                ),
                TaskKind::Merge => {
                    let grid = res.grid();
                    let b = task.bands();
                    let rect = Tile {
                        x0: 0,
                        y0: (b.start * grid.size).min(res.height),
                        x1: res.width,
                        y1: (b.end * grid.size).min(res.height),
                    };
                    let s = res.pass_range(task.pass).unwrap_or(0..0);
                    (rect, [s.start, s.end], Some([b.start, b.end]))
                }
            };
            let lease = Lease {
                task: LeasedTask {
                    id: task.id,
                    attempt: task.attempt,
                    kind: task.kind,
                    job_id: task.job_id,
                    pass: task.pass,
                    tile: task.tile,
                    rect,
                    samples,
                    bands,
                },
                job: LeasedJob {
                    scene_id: job.scene_id,
                    scene_main: job.scene_main,
                    resolved: res,
                },
                lease_seconds: app.cfg.lease_s,
            };
            return Ok(Json(lease).into_response());
        }
        tokio::select! {
            _ = &mut notified => {}
            _ = tokio::time::sleep_until(deadline) => return Ok(StatusCode::NO_CONTENT.into_response()),
            _ = tokio::time::sleep(Duration::from_secs(1)) => {}
        }
    }
}

/// POST /v1/worker/heartbeat.
pub(crate) async fn heartbeat(
    State(app): State<AppState>,
    JsonBody(r): JsonBody<HeartbeatRequest>,
) -> ApiResult<Json<HeartbeatAnswer>> {
    let db = app.db();
    let state = if r.tasks.is_empty() {
        WorkerState::Idle
    } else {
        WorkerState::Busy
    };
    if !db.touch_worker(&r.worker_id, Some(state))? {
        return Err(unknown_worker());
    }
    let mut lost = Vec::new();
    for t in &r.tasks {
        if !db.extend(t.id, t.attempt, &r.worker_id, app.cfg.lease_s)? {
            lost.push(t.id);
        }
    }
    let drain = db.worker_admin(&r.worker_id)? == Some(WorkerAdmin::Draining);
    Ok(Json(HeartbeatAnswer { lost, drain }))
}

/// POST /v1/worker/deregister: the worker is `left`, its leases go back to the queue.
pub(crate) async fn deregister(
    State(app): State<AppState>,
    JsonBody(r): JsonBody<DeregisterRequest>,
) -> ApiResult<Json<DeregisterAnswer>> {
    let released = {
        let db = app.db();
        if !db.touch_worker(&r.worker_id, Some(WorkerState::Left))? {
            return Err(ApiError::field(
                StatusCode::NOT_FOUND,
                "worker_id",
                "unknown worker",
            ));
        }
        db.release_worker(&r.worker_id)?
    };
    if released > 0 {
        app.work.notify_waiters();
    }
    Ok(Json(DeregisterAnswer { ok: true, released }))
}

/// GET /v1/worker/scenes/{id}: a bundle's tar.
pub(crate) async fn worker_scene(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    if scenes::scene_meta(&app, &id).is_none() {
        return Err(ApiError::not_found("scene", &id));
    }
    // Sent as it is read: workers download bundles together, and one may be as large as an
    // upload may be.
    let (body, len) = upload::file_body(scenes::bundle_path(&app, &id))
        .await
        .map_err(|e| ApiError::disk("cannot read the bundle", e))?;
    Ok((
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static("application/x-tar"),
            ),
            (header::CONTENT_LENGTH, HeaderValue::from(len)),
        ],
        body,
    )
        .into_response())
}

/// Whether `task` is still `worker`'s current attempt (else the 409 to answer).
fn check_owner(task: &TaskRow, worker: &str, attempt: u32) -> ApiResult<()> {
    if task.state != TaskState::Leased
        || task.attempt != attempt
        || task.worker_id.as_deref() != Some(worker)
    {
        return Err(ApiError::field(
            StatusCode::CONFLICT,
            "attempt",
            format!(
                "task {} attempt {attempt} of worker {worker} is not current (task is {}, attempt {}, owner {})",
                task.id,
                task.state,
                task.attempt,
                task.worker_id.as_deref().unwrap_or("none")
            ),
        ));
    }
    Ok(())
}

/// The task `task_id` and its job, when `q` names the current attempt of the worker holding it
/// and the job is running or paused (404 for a task never issued, 409 for one no longer current).
fn current_task(app: &AppState, task_id: i64, q: &ResultQuery) -> ApiResult<(TaskRow, JobRow)> {
    let (task, job) = {
        let db = app.db();
        let Some(task) = db.task(task_id)? else {
            return Err(if db.task_existed(task_id)? {
                ApiError::field(
                    StatusCode::CONFLICT,
                    "id",
                    format!("task {task_id} is no longer current (its pass was merged)"),
                )
            } else {
                ApiError::not_found("task", &task_id.to_string())
            });
        };
        let job = db
            .job(&task.job_id)?
            .ok_or_else(|| ApiError::internal("task without job"))?;
        (task, job)
    };
    check_owner(&task, &q.worker_id, q.attempt)?;
    // A paused job's tasks in hand finish: their results are kept.
    if !matches!(job.state, JobState::Running | JobState::Paused) {
        return Err(ApiError::field(
            StatusCode::CONFLICT,
            "id",
            format!("job '{}' is {}", job.id, job.state),
        ));
    }
    Ok((task, job))
}

/// An upload's body, read into a reused buffer: 413 over `--max-upload-mb`, 400 if unreadable.
async fn read_upload(app: &AppState, body: Body) -> ApiResult<Pooled> {
    Ok(buffers::read_body(body, app.cfg.max_upload_bytes, &app.buffers).await?)
}

/// GET /v1/worker/tasks/{id}/input: a merge task's input (`film::merge_task`), streamed.
pub(crate) async fn merge_input(
    State(app): State<AppState>,
    Path(task_id): Path<i64>,
    Query(q): Query<ResultQuery>,
) -> ApiResult<Response> {
    let (task, job) = current_task(&app, task_id, &q)?;
    if task.kind != TaskKind::Merge {
        return Err(ApiError::field(
            StatusCode::CONFLICT,
            "id",
            format!("task {task_id} is a {} task: it has no input", task.kind),
        ));
    }
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(2);
    let a = app.clone();
    tokio::task::spawn_blocking(move || {
        let pool = a.buffers.clone();
        let mut send = |chunk: Vec<u8>| {
            let chunk = Pooled::new(chunk, pool.clone()).into_bytes();
            tx.blocking_send(Ok(chunk)).is_ok()
        };
        if let Err(e) = jobs::serve_merge_input(&a, &job, &task, &mut send) {
            tracing::warn!("merge task {}: input ended: {e}", task.id);
            let _ = tx.blocking_send(Err(std::io::Error::other(e)));
        }
    });
    let stream = futures_util::stream::unfold(rx, |mut rx| async move {
        rx.recv().await.map(|chunk| (chunk, rx))
    });
    Ok((
        [(header::CONTENT_TYPE, "application/octet-stream")],
        axum::body::Body::from_stream(stream),
    )
        .into_response())
}

/// PUT /v1/worker/tasks/{id}/result: a render task's encoded accumulators, or a merge task's
/// output, judged by `accept::upload`. Refused (`Metrics::results_refused`): a body too large or
/// unreadable, an attempt not current, an upload that does not match its task.
pub(crate) async fn upload_result(
    State(app): State<AppState>,
    Path(task_id): Path<i64>,
    Query(q): Query<ResultQuery>,
    body: Body,
) -> ApiResult<Json<ResultAnswer>> {
    let refused = |e: ApiError| {
        Metrics::add(&app.metrics.results_refused, 1);
        e
    };
    // A merge output is large: read only a few at once (`App::merge_bodies`). Only the task's
    // kind is looked at here; everything else is judged once the body is read.
    let merge = matches!(app.db().task(task_id), Ok(Some(t)) if t.kind == TaskKind::Merge);
    let _permit = if merge {
        Some(
            app.merge_bodies
                .acquire()
                .await
                .map_err(ApiError::internal)?,
        )
    } else {
        None
    };
    // Read whole before it is judged (as an extractor would): a client refused while it is
    // still sending would see its connection cut rather than the answer.
    let body = read_upload(&app, body).await.map_err(refused)?;
    let (task, job) = current_task(&app, task_id, &q).map_err(refused)?;
    let (id, attempt) = (task.id, task.attempt);
    match accept::upload(&app, task, job, q.worker_id, body).await? {
        Accepted::Yes => Ok(Json(ResultAnswer { accepted: true })),
        Accepted::Stale => Err(refused(ApiError::field(
            StatusCode::CONFLICT,
            "attempt",
            format!("task {id} attempt {attempt} is no longer current"),
        ))),
        Accepted::Invalid(problem) => Err(refused(ApiError::field(
            StatusCode::BAD_REQUEST,
            "body",
            problem,
        ))),
    }
}

/// POST /v1/worker/tasks/{id}/fail.
pub(crate) async fn fail_task(
    State(app): State<AppState>,
    Path(task_id): Path<i64>,
    JsonBody(r): JsonBody<FailRequest>,
) -> ApiResult<Json<OkAnswer>> {
    let task = app
        .db()
        .task(task_id)?
        .ok_or_else(|| ApiError::not_found("task", &task_id.to_string()))?;
    check_owner(&task, &r.worker_id, r.attempt)?;
    let error: String = r.error.chars().take(2000).collect();
    let a = app.clone();
    let w = r.worker_id.clone();
    tokio::task::spawn_blocking(move || jobs::task_failed(&a, &task, &w, &error, Outcome::Failed))
        .await
        .map_err(ApiError::internal)??;
    Ok(Json(OkAnswer { ok: true }))
}
