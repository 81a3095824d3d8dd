//! Jobs: submit (POST /v1/jobs), list (paged, filtered), status, the controls (cancel, pause,
//! resume, requeue, retry, priority, delete), the event stream (Server-Sent Events) and the
//! job's files (EXR, preview, error map, convergence plot).

use super::auth::{self, Principal};
use super::errors::{ApiError, ApiResult, JsonBody, bad, settings_error};
use super::{AppState, references, scenes, sequences};
use crate::protocol::{
    ImageQuery, JobEvent, JobLinks, JobList, JobListQuery, JobPatch, JobRequest, JobState,
    JobStatus, QueuedEvent, SceneMeta, SceneRef, SceneSource, SseData, WebhookDelivery,
    WebhookDeliveryList, Whoami, WorkerAdmin, WorkerInfo, WorkerState, validate_tags,
};
use crate::service::store::{self, EventRow, JobRow};
use crate::service::{App, jobs, runtime, webhooks};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use futures_util::stream::{self, Stream, StreamExt};
use std::convert::Infallible;
use std::time::Duration;

/// POST /v1/jobs.
pub(crate) async fn create_job(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    JsonBody(req): JsonBody<JobRequest>,
) -> ApiResult<Response> {
    req.settings
        .validate(&app.cfg.limits)
        .map_err(settings_error)?;
    let hooks = webhooks::job_targets(&req.webhooks).map_err(|(field, e)| bad(&field, &e))?;
    if let Some(n) = &req.name
        && (n.chars().count() > 200 || n.chars().any(|c| c.is_control()))
    {
        return Err(bad("name", "at most 200 characters, no control characters"));
    }
    let require_tags = validate_tags(&req.require_tags).map_err(|e| bad("require_tags", e))?;
    let req = JobRequest {
        require_tags,
        ..req
    };
    // Loading the scene, resolving the settings (the automatic D_opt's pilot renders) and
    // reading the reference take memory and time in proportion to the job: a few at once.
    let _permit = app.validation().await?;
    let a = app.clone();
    let (job, to_start) = tokio::task::spawn_blocking(move || {
        if sequences::is_sequence_request(&a, &req) {
            sequences::create_sequence(&a, &req, Some(&who.name), hooks.as_deref())
        } else {
            create_job_blocking(&a, req, &who, hooks).map(|j| {
                let id = j.id.clone();
                (j, vec![id])
            })
        }
    })
    .await
    .map_err(ApiError::internal)??;
    // Its tasks are created in the background, chunk by chunk (the first ones are leased while
    // the rest are made): a large frame does not hold up this answer or the store. A
    // sequence's are its frames'.
    let a = app.clone();
    tokio::task::spawn_blocking(move || {
        for id in &to_start {
            jobs::advance(&a, id);
        }
    });
    let status = job_status(&app, &job)?;
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, format!("/v1/jobs/{}", job.id))],
        Json(status),
    )
        .into_response())
}

fn create_job_blocking(
    app: &App,
    req: JobRequest,
    owner: &Principal,
    hooks: Option<String>,
) -> ApiResult<JobRow> {
    let (meta, scene) = match &req.scene {
        SceneSource::Library(name) => scenes::store_library(app, name)?,
        SceneSource::Bundle(id) => scenes::load_bundle(app, id)?,
        SceneSource::Inline(v) => scenes::store_inline(app, v)?,
    };
    let made_here = !matches!(req.scene, SceneSource::Bundle(_));
    let created = create_job_with(
        app,
        &req,
        &meta,
        scene,
        None,
        Some(&owner.name),
        hooks.as_deref(),
    );
    // A bundle this request made for a job it did not create is of no use to anyone.
    if created.is_err() && made_here {
        scenes::remove_bundle(app, &meta.id);
    }
    created
}

/// What a retry takes over of the job it repeats (beyond its request).
struct RetryOf<'a> {
    /// The job retried.
    id: &'a str,
    /// Its reference image, already checked when it was created.
    reference: Option<&'a str>,
}

/// The job of `req` on its stored scene bundle `meta`, loaded as `scene` (a retry: of the job
/// `retry`, with its reference).
fn create_job_with(
    app: &App,
    req: &JobRequest,
    meta: &SceneMeta,
    mut scene: crate::scene::Scene,
    retry: Option<RetryOf>,
    owner: Option<&str>,
    hooks: Option<&str>,
) -> ApiResult<JobRow> {
    if !req.settings.defines.is_empty() {
        // The bundle was checked with the file's own defaults; the job renders it with its
        // parameter values.
        scene = scenes::load_bundle_with(app, &meta.id, &req.settings.defines)?.1;
    }
    let resolved = req
        .settings
        .resolve(&mut scene, &app.cfg.limits)
        .map_err(settings_error)?;
    let reference = match (&retry, &req.reference) {
        (Some(r), _) => r.reference.map(str::to_string),
        (None, None) => None,
        (None, Some(src)) => Some(references::job_reference(
            app,
            src,
            resolved.width,
            resolved.height,
        )?),
    };
    let id = uuid::Uuid::new_v4().to_string();
    let accum = resolved.film_layout().bytes_per_pixel() as i64
        * resolved.width as i64
        * resolved.height as i64;
    let settings = serde_json::to_string(&req.settings).map_err(ApiError::internal)?;
    let res = serde_json::to_string(&resolved).map_err(ApiError::internal)?;
    std::fs::create_dir_all(app.paths.job(&id))
        .map_err(|e| ApiError::disk("cannot make the job's folder", e))?;
    app.db().insert_job(&store::NewJob {
        id: &id,
        name: req.name.as_deref(),
        settings: &settings,
        resolved: &res,
        scene_id: &meta.id,
        scene_main: &meta.main,
        reference: reference.as_deref(),
        accum_bytes: accum,
        priority: req.priority,
        retry_of: retry.as_ref().map(|r| r.id),
        require_tags: &req.require_tags,
        owner,
        webhooks: hooks,
    })?;
    app.event(
        &id,
        JobEvent::Queued(QueuedEvent {
            width: resolved.width,
            height: resolved.height,
            spp: resolved.spp,
        }),
    );
    app.db()
        .job(&id)?
        .ok_or_else(|| ApiError::internal("job vanished"))
}

/// The status document of a job (GET /v1/jobs/{id}).
fn job_status(app: &App, job: &JobRow) -> ApiResult<JobStatus> {
    let r = runtime::resolved_of(job)?;
    let mut settings: crate::job::JobSettings = serde_json::from_str(&job.settings)
        .map_err(|e| ApiError::internal(format!("job {}: bad settings: {e}", job.id)))?;
    // Filled in from what the job resolved to, like the rest of the settings.
    settings.tile_size = Some(r.tile_size);
    let series = app.db().series(&job.id)?;
    let tiles = jobs::tile_count(&r);
    let active = job.state.is_active();
    let tiles_done = if active {
        app.db().tasks_done(&job.id)?
    } else {
        0
    };
    let now = store::now();
    // Rendering time: a pause does not count (nor against a time budget).
    let elapsed = job.render_seconds(now);
    let progress_spp = jobs::progress_spp(job, &r, tiles_done);
    // The budget left: the pilot's seconds count against it (`Resolved::fit_to_budget`).
    let budget_left = r
        .time_budget_s
        .map(|b| (b - r.pilot_s.unwrap_or(0.0) - elapsed).max(0.0));
    let eta = if !active {
        Some(0.0)
    } else if job.state == JobState::Paused {
        None
    } else if let Some(spp) = r.spp_limit() {
        (progress_spp > 0.0)
            .then(|| elapsed / progress_spp * (spp as f64 - progress_spp).max(0.0))
            .map(|e| budget_left.map_or(e, |left| e.min(left)))
    } else {
        budget_left
    };
    // Each read of the store on its own line: a guard held to the end of the status's
    // expression would lock the store twice.
    let blocklisted_workers = app.db().blocklist(&job.id)?;
    let waiting_for = if active && !job.require_tags.is_empty() {
        let workers = app.db().workers()?;
        waiting_for(
            &job.id,
            &job.require_tags,
            &workers,
            now,
            app.cfg.lease_s * 2.0,
        )
    } else {
        None
    };
    let mut st = JobStatus {
        id: job.id.clone(),
        name: job.name.clone(),
        state: job.state,
        error: job.error.clone(),
        owner: job.owner.clone(),
        webhooks: webhooks::job_urls(job.webhooks.as_deref()),
        scene: SceneRef {
            id: job.scene_id.clone(),
            main: job.scene_main.clone(),
        },
        settings,
        width: r.width,
        height: r.height,
        spp_target: r.spp_limit(),
        time_budget_s: r.time_budget_s,
        spp_done: job.spp_done,
        passes_done: job.passes_done,
        passes_total: r.total_passes(),
        tiles_per_pass: tiles,
        tiles_done,
        created_at: job.created_at,
        started_at: job.started_at,
        finished_at: job.finished_at,
        elapsed_s: elapsed,
        eta_s: eta,
        relmse: series.last().and_then(|p| p.relmse),
        series,
        accum_bytes: job.accum_bytes,
        accum_bytes_per_pixel: job.accum_bytes / (r.width as i64 * r.height as i64).max(1),
        result_bytes: job.result_bytes,
        samples: job.samples,
        rays: job.rays,
        non_finite_samples: job.non_finite,
        has_reference: job.reference.is_some(),
        optimal_max_depth: r.optimal_max_depth(),
        optimal_depth: r.optimal_depth.clone(),
        links: JobLinks::of(&job.id),
        priority: job.priority,
        paused_s: job.paused_until(job.finished_at.unwrap_or(now)),
        retry_of: job.retry_of.clone(),
        require_tags: job.require_tags.clone(),
        blocklisted_workers,
        waiting_for,
        frames: None,
        parent: job.parent_id.clone(),
        frame: job.frame,
    };
    if job.is_sequence() {
        sequences::fill_status(app, job, &mut st, |f| job_status(app, f))?;
    }
    Ok(st)
}

/// The status document of job `id` (404 if there is none).
pub(crate) fn status_of(app: &App, id: &str) -> ApiResult<JobStatus> {
    job_status(app, &find_job(app, id)?)
}

fn find_job(app: &App, id: &str) -> ApiResult<JobRow> {
    app.db()
        .job(id)?
        .ok_or_else(|| ApiError::not_found("job", id))
}

/// A whole number of decimal digits; one past `u64::MAX` is `u64::MAX` (more than any limit or
/// cursor, not an error).
fn whole_number(s: &str) -> Option<u64> {
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(s.parse::<u64>().unwrap_or(u64::MAX))
}

/// The store's query for GET /v1/jobs's `q`: 400 naming the query field that is wrong.
fn job_query(q: &JobListQuery) -> ApiResult<store::JobQuery> {
    let states = match q.state.as_deref() {
        None | Some("") => Vec::new(),
        Some(list) => list
            .split(',')
            .map(|s| s.trim().parse::<JobState>())
            .collect::<Result<_, _>>()
            .map_err(|e| {
                let names: Vec<&str> = JobState::ALL.iter().map(|s| s.as_str()).collect();
                bad("state", format!("{e}; states: {}", names.join(", ")))
            })?,
    };
    let name = match q.name.as_deref() {
        None | Some("") => None,
        Some(n) if n.chars().count() > 200 || n.chars().any(|c| c.is_control()) => {
            return Err(bad("name", "at most 200 characters, no control characters"));
        }
        Some(n) => Some(n.to_string()),
    };
    let since = match q.since.as_deref() {
        None | Some("") => None,
        Some(s) => Some(
            // Past the largest float (infinity) is after every job: not an error.
            s.parse::<f64>()
                .ok()
                .filter(|t| !t.is_nan() && *t >= 0.0)
                .ok_or_else(|| bad("since", "seconds since the Unix epoch, a number >= 0"))?,
        ),
    };
    let limit = match q.limit.as_deref() {
        None | Some("") => JobListQuery::MAX_LIMIT,
        Some(l) => whole_number(l)
            .filter(|n| *n >= 1)
            .ok_or_else(|| bad("limit", "a whole number >= 1"))?
            .min(JobListQuery::MAX_LIMIT as u64) as u32,
    };
    let after = match q.after.as_deref() {
        None | Some("") => None,
        Some(a) => Some(
            whole_number(a)
                .ok_or_else(|| bad("after", "the `next` of an earlier page"))?
                .min(i64::MAX as u64) as i64,
        ),
    };
    let include_frames = match q.include_frames.as_deref() {
        None | Some("") | Some("false") => false,
        Some("true") => true,
        Some(_) => return Err(bad("include_frames", "true or false")),
    };
    Ok(store::JobQuery {
        states,
        name,
        since,
        after,
        limit,
        include_frames,
    })
}

/// GET /v1/jobs: one page of the jobs the query selects, oldest first, and the cursor of the
/// next page. A sequence's frames are listed in its status (or with `include_frames=true`).
pub(crate) async fn list_jobs(
    State(app): State<AppState>,
    Query(q): Query<JobListQuery>,
) -> ApiResult<Json<JobList>> {
    let mut query = job_query(&q)?;
    let limit = query.limit as usize;
    // One more than the page: whether a next page exists.
    query.limit += 1;
    let mut rows = app.db().jobs_page(&query)?;
    let next = (rows.len() > limit).then(|| rows[limit - 1].seq.to_string());
    rows.truncate(limit);
    let jobs = rows
        .iter()
        .map(|j| job_status(&app, j))
        .collect::<ApiResult<_>>()?;
    Ok(Json(JobList { jobs, next }))
}

/// A 409 for a control that the job's state does not allow.
fn wrong_state(id: &str, state: JobState, wants: &str) -> ApiError {
    ApiError::field(
        StatusCode::CONFLICT,
        "id",
        format!("job '{id}' is {state}; {wants}"),
    )
}

/// Runs control `f` on job `id` on a blocking thread, for its owner or an admin (`who`); its
/// `false` answers 409 (`wants`: the states it needs), else the job's status after it.
async fn control(
    app: AppState,
    who: &Principal,
    id: String,
    wants: &'static str,
    f: fn(&App, &str) -> crate::service::error::ServiceResult<bool>,
) -> ApiResult<Json<JobStatus>> {
    let job = find_job(&app, &id)?;
    auth::require_owner(who, &id, job.owner.as_deref())?;
    let a = app.clone();
    let i = id.clone();
    let done = tokio::task::spawn_blocking(move || f(&a, &i))
        .await
        .map_err(ApiError::internal)??;
    let job = find_job(&app, &id)?;
    if !done {
        return Err(wrong_state(&id, job.state, wants));
    }
    Ok(Json(job_status(&app, &job)?))
}

/// POST /v1/jobs/{id}/pause.
pub(crate) async fn pause_job(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<Json<JobStatus>> {
    control(
        app,
        &who,
        id,
        "only a queued or running job can be paused",
        jobs::pause,
    )
    .await
}

/// POST /v1/jobs/{id}/resume.
pub(crate) async fn resume_job(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<Json<JobStatus>> {
    control(
        app,
        &who,
        id,
        "only a paused job can be resumed",
        jobs::resume,
    )
    .await
}

/// POST /v1/jobs/{id}/requeue.
pub(crate) async fn requeue_job(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<Json<JobStatus>> {
    control(
        app,
        &who,
        id,
        "only a failed job can be requeued (retry makes a new job of a cancelled one)",
        jobs::requeue,
    )
    .await
}

/// PATCH /v1/jobs/{id}: its priority.
pub(crate) async fn patch_job(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
    JsonBody(patch): JsonBody<JobPatch>,
) -> ApiResult<Json<JobStatus>> {
    let job = find_job(&app, &id)?;
    auth::require_owner(&who, &id, job.owner.as_deref())?;
    let set = jobs::set_priority(&app, &id, patch.priority)?;
    let job = find_job(&app, &id)?;
    if !set {
        return Err(wrong_state(
            &id,
            job.state,
            "the priority of a job that has ended cannot change",
        ));
    }
    Ok(Json(job_status(&app, &job)?))
}

/// POST /v1/jobs/{id}/retry: a failed or cancelled job again, as a new job (same scene,
/// settings, reference, name and priority); 201 with the new job's status.
pub(crate) async fn retry_job(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let old = find_job(&app, &id)?;
    auth::require_owner(&who, &id, old.owner.as_deref())?;
    if old.is_sequence() {
        return Err(wrong_state(
            &id,
            old.state,
            "a sequence is not retried as a whole: requeue it (its failed frames go on) or submit it again",
        ));
    }
    if !matches!(old.state, JobState::Failed | JobState::Cancelled) {
        return Err(wrong_state(
            &id,
            old.state,
            "only a failed or cancelled job can be retried",
        ));
    }
    let _permit = app.validation().await?;
    let a = app.clone();
    let job = tokio::task::spawn_blocking(move || retry_blocking(&a, &old))
        .await
        .map_err(ApiError::internal)??;
    let a = app.clone();
    let new_id = job.id.clone();
    tokio::task::spawn_blocking(move || jobs::advance(&a, &new_id));
    let status = job_status(&app, &job)?;
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, format!("/v1/jobs/{}", job.id))],
        Json(status),
    )
        .into_response())
}

fn retry_blocking(app: &App, old: &JobRow) -> ApiResult<JobRow> {
    let settings: crate::job::JobSettings = serde_json::from_str(&old.settings)
        .map_err(|e| ApiError::internal(format!("job {}: bad settings: {e}", old.id)))?;
    let gone = |what: &str| {
        ApiError::field(
            StatusCode::CONFLICT,
            "id",
            format!("job '{}' cannot be retried: its {what} is gone", old.id),
        )
    };
    if scenes::scene_meta(app, &old.scene_id).is_none() {
        return Err(gone("scene bundle"));
    }
    if let Some(r) = &old.reference
        && !std::path::Path::new(r).is_file()
    {
        return Err(gone("reference image"));
    }
    let (meta, scene) = scenes::load_bundle(app, &old.scene_id)?;
    let req = JobRequest {
        scene: SceneSource::Bundle(old.scene_id.clone()),
        settings,
        reference: None,
        name: old.name.clone(),
        priority: old.priority,
        require_tags: old.require_tags.clone(),
        // The receivers (with their secrets) are the old job's, carried over as stored.
        webhooks: Vec::new(),
        frames: None,
    };
    create_job_with(
        app,
        &req,
        &meta,
        scene,
        Some(RetryOf {
            id: &old.id,
            reference: old.reference.as_deref(),
        }),
        old.owner.as_deref(),
        old.webhooks.as_deref(),
    )
}

/// DELETE /v1/jobs/{id}: a job that has ended, with every file it stored; 204.
pub(crate) async fn delete_job(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<StatusCode> {
    let job = find_job(&app, &id)?;
    auth::require_owner(&who, &id, job.owner.as_deref())?;
    if let Some(parent) = &job.parent_id {
        return Err(ApiError::field(
            StatusCode::CONFLICT,
            "id",
            format!("job '{id}' is a frame of sequence '{parent}': delete the sequence"),
        ));
    }
    let a = app.clone();
    let i = id.clone();
    let deleted = tokio::task::spawn_blocking(move || jobs::delete(&a, &i))
        .await
        .map_err(ApiError::internal)??;
    match deleted {
        store::Deleted::Removed(_) => Ok(StatusCode::NO_CONTENT),
        store::Deleted::Missing => Err(ApiError::not_found("job", &id)),
        store::Deleted::NotFinal(state) => Err(wrong_state(
            &id,
            state,
            "only a done, failed or cancelled job can be deleted (cancel it first)",
        )),
        store::Deleted::Referenced(user) => Err(ApiError::field(
            StatusCode::CONFLICT,
            "id",
            format!("job '{user}' uses the image of job '{id}' as its reference; delete it first"),
        )),
    }
}

/// GET /v1/jobs/{id}.
pub(crate) async fn get_job(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Json<JobStatus>> {
    let job = find_job(&app, &id)?;
    Ok(Json(job_status(&app, &job)?))
}

/// POST /v1/jobs/{id}/cancel: the job's owner's, or an admin's.
pub(crate) async fn cancel_job(
    State(app): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> ApiResult<Json<JobStatus>> {
    let job = find_job(&app, &id)?;
    auth::require_owner(&who, &id, job.owner.as_deref())?;
    let a = app.clone();
    let i = id.clone();
    let cancelled = tokio::task::spawn_blocking(move || jobs::cancel(&a, &i))
        .await
        .map_err(ApiError::internal)??;
    if !cancelled {
        return Err(ApiError::field(
            StatusCode::CONFLICT,
            "id",
            format!("job '{id}' has already ended ({})", job.state),
        ));
    }
    let job = find_job(&app, &id)?;
    Ok(Json(job_status(&app, &job)?))
}

/// GET /v1/jobs/{id}/webhooks: the deliveries of the job's final event, oldest first.
pub(crate) async fn job_webhooks(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Json<WebhookDeliveryList>> {
    find_job(&app, &id)?;
    let rows = app.db().deliveries(&id)?;
    let deliveries = rows
        .into_iter()
        .map(|d| WebhookDelivery {
            next_at: (d.state == "pending").then_some(d.next_at),
            id: d.id,
            event: d.event,
            url: d.url,
            state: d.state,
            attempts: d.attempts,
            at: d.at,
            last_status: d.last_status,
            last_error: d.last_error,
            delivered_at: d.delivered_at,
        })
        .collect();
    Ok(Json(WebhookDeliveryList { deliveries }))
}

/// GET /v1/whoami: whom the request's client token stands for.
pub(crate) async fn whoami(Extension(who): Extension<Principal>) -> Json<Whoami> {
    Json(Whoami {
        name: who.name,
        role: who.role,
    })
}

fn sse_event(row: &EventRow) -> Event {
    let data = SseData {
        fields: match &row.data {
            serde_json::Value::Object(m) => m.clone(),
            _ => serde_json::Map::new(),
        },
        job: row.job_id.clone(),
        at: row.at,
    };
    Event::default()
        .id(row.id.to_string())
        .event(row.kind.as_str())
        .data(serde_json::to_string(&data).unwrap_or_default())
}

/// GET /v1/jobs/{id}/events: the recorded events after Last-Event-ID, then live ones, until a
/// terminal one.
pub(crate) async fn job_events(
    State(app): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Sse<impl Stream<Item = Result<Event, Infallible>>>> {
    let job = find_job(&app, &id)?;
    let after: i64 = headers
        .get("last-event-id")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    // Subscribe before reading the log so that nothing falls between the two.
    let rx = app.events.subscribe();
    let backlog = app.db().events_after(&id, after)?;
    let last = backlog.last().map_or(after, |e| e.id);
    // A job that has ended (its final event at or before Last-Event-ID) ends the stream.
    let ended = backlog.iter().any(|e| e.kind.is_terminal()) || !job.state.is_active();
    let backlog_stream = stream::iter(
        backlog
            .into_iter()
            .map(|e| Ok::<_, Infallible>(sse_event(&e)))
            .collect::<Vec<_>>(),
    );
    let live = stream::unfold(
        (rx, ended, id.clone(), last),
        |(mut rx, ended, id, last)| async move {
            if ended {
                return None;
            }
            loop {
                match rx.recv().await {
                    Ok(e) if e.job_id == id && e.id > last => {
                        let end = e.kind.is_terminal();
                        return Some((Ok(sse_event(&e)), (rx, end, id, e.id)));
                    }
                    Ok(_) => continue,
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
                    Err(_) => return None,
                }
            }
        },
    );
    Ok(Sse::new(backlog_stream.chain(live))
        .keep_alive(KeepAlive::new().interval(Duration::from_secs(15))))
}

async fn job_file(app: &App, id: &str, name: &str, mime: &'static str) -> ApiResult<Response> {
    job_frame_file(app, id, None, name, mime).await
}

/// File `name` of job `id`, or of its frame `frame` for a sequence.
async fn job_frame_file(
    app: &App,
    id: &str,
    frame: Option<u32>,
    name: &str,
    mime: &'static str,
) -> ApiResult<Response> {
    let job = sequences::image_job(app, find_job(app, id)?, frame)?;
    let path = app.paths.output(&job.id, name);
    match tokio::fs::read(&path).await {
        Ok(bytes) => Ok((
            [(header::CONTENT_TYPE, HeaderValue::from_static(mime))],
            bytes,
        )
            .into_response()),
        Err(_) => Err(ApiError::field(
            StatusCode::NOT_FOUND,
            "id",
            format!(
                "job '{id}' has no {name} yet (state {}, {} passes merged)",
                job.state, job.passes_done
            ),
        )),
    }
}

/// GET /v1/jobs/{id}/image.exr (?frame=N of a sequence).
pub(crate) async fn job_exr(
    State(app): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<ImageQuery>,
) -> ApiResult<Response> {
    job_frame_file(&app, &id, q.frame, "image.exr", "image/x-exr").await
}

/// GET /v1/jobs/{id}/preview.png (?frame=N of a sequence).
pub(crate) async fn job_preview(
    State(app): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<ImageQuery>,
) -> ApiResult<Response> {
    job_frame_file(&app, &id, q.frame, "preview.png", "image/png").await
}

/// GET /v1/jobs/{id}/error.png.
pub(crate) async fn job_error_map(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let job = find_job(&app, &id)?;
    if job.reference.is_none() {
        return Err(ApiError::field(
            StatusCode::NOT_FOUND,
            "id",
            format!("job '{id}' has no reference, so no error map"),
        ));
    }
    job_file(&app, &id, "error.png", "image/png").await
}

/// GET /v1/jobs/{id}/convergence.svg.
pub(crate) async fn job_convergence(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let job = find_job(&app, &id)?;
    let series = app.db().series(&id)?;
    let svg = jobs::convergence_svg(&job, &series);
    Ok((
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("image/svg+xml"),
        )],
        svg,
    )
        .into_response())
}

/// Why no worker serves an active job that requires `tags`, if none does: no live, enabled,
/// healthy worker that is not blocklisted for it has them all.
fn waiting_for(
    job: &str,
    tags: &[String],
    workers: &[WorkerInfo],
    now: f64,
    silent_s: f64,
) -> Option<String> {
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
