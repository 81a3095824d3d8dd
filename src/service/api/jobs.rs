//! Jobs: submit (POST /v1/jobs), list, status, cancel, the event stream (Server-Sent Events)
//! and the job's files (EXR, preview, error map, convergence plot).

use super::errors::{ApiError, ApiResult, JsonBody, bad, settings_error};
use super::{AppState, references, scenes, sequences};
use crate::protocol::{
    ImageQuery, JobEvent, JobLinks, JobList, JobListQuery, JobRequest, JobStatus, QueuedEvent,
    SceneMeta, SceneRef, SceneSource, SseData,
};
use crate::service::store::{self, EventRow, JobRow};
use crate::service::{App, jobs, runtime};
use axum::Json;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use futures_util::stream::{self, Stream, StreamExt};
use std::convert::Infallible;
use std::time::Duration;

/// POST /v1/jobs.
pub(crate) async fn create_job(
    State(app): State<AppState>,
    JsonBody(req): JsonBody<JobRequest>,
) -> ApiResult<Response> {
    req.settings
        .validate(&app.cfg.limits)
        .map_err(settings_error)?;
    if let Some(n) = &req.name
        && (n.chars().count() > 200 || n.chars().any(|c| c.is_control()))
    {
        return Err(bad("name", "at most 200 characters, no control characters"));
    }
    // Loading the scene, resolving the settings (the automatic D_opt's pilot renders) and
    // reading the reference take memory and time in proportion to the job: a few at once.
    let _permit = app.validation().await?;
    let a = app.clone();
    let (job, to_start) = tokio::task::spawn_blocking(move || {
        if sequences::is_sequence_request(&a, &req) {
            sequences::create_sequence(&a, &req)
        } else {
            create_job_blocking(&a, req).map(|j| {
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

fn create_job_blocking(app: &App, req: JobRequest) -> ApiResult<JobRow> {
    let (meta, scene) = match &req.scene {
        SceneSource::Library(name) => scenes::store_library(app, name)?,
        SceneSource::Bundle(id) => scenes::load_bundle(app, id)?,
        SceneSource::Inline(v) => scenes::store_inline(app, v)?,
    };
    let made_here = !matches!(req.scene, SceneSource::Bundle(_));
    let created = create_job_with(app, &req, &meta, scene);
    // A bundle this request made for a job it did not create is of no use to anyone.
    if created.is_err() && made_here {
        scenes::remove_bundle(app, &meta.id);
    }
    created
}

/// The job of `req` on its stored scene bundle `meta`, loaded as `scene`.
fn create_job_with(
    app: &App,
    req: &JobRequest,
    meta: &SceneMeta,
    mut scene: crate::scene::Scene,
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
    let reference = match &req.reference {
        None => None,
        Some(src) => Some(references::job_reference(
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
    let elapsed = job
        .started_at
        .map(|s| job.finished_at.unwrap_or(now) - s)
        .unwrap_or(0.0);
    let progress_spp = jobs::progress_spp(job, &r, tiles_done);
    // The budget left: the pilot's seconds count against it (`Resolved::fit_to_budget`).
    let budget_left = r
        .time_budget_s
        .map(|b| (b - r.pilot_s.unwrap_or(0.0) - elapsed).max(0.0));
    let eta = if !active {
        Some(0.0)
    } else if let Some(spp) = r.spp_limit() {
        (progress_spp > 0.0)
            .then(|| elapsed / progress_spp * (spp as f64 - progress_spp).max(0.0))
            .map(|e| budget_left.map_or(e, |left| e.min(left)))
    } else {
        budget_left
    };
    let mut st = JobStatus {
        id: job.id.clone(),
        name: job.name.clone(),
        state: job.state,
        error: job.error.clone(),
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
        frames: None,
        parent: job.parent_id.clone(),
        frame: job.frame,
    };
    if job.is_sequence() {
        sequences::fill_status(app, job, &mut st, |f| job_status(app, f))?;
    }
    Ok(st)
}

fn find_job(app: &App, id: &str) -> ApiResult<JobRow> {
    app.db()
        .job(id)?
        .ok_or_else(|| ApiError::not_found("job", id))
}

/// GET /v1/jobs.
pub(crate) async fn list_jobs(
    State(app): State<AppState>,
    Query(q): Query<JobListQuery>,
) -> ApiResult<Json<JobList>> {
    let rows = app.db().jobs()?;
    let jobs = rows
        .iter()
        // A sequence's frames are listed in its status.
        .filter(|j| q.include_frames || j.parent_id.is_none())
        .map(|j| job_status(&app, j))
        .collect::<ApiResult<_>>()?;
    Ok(Json(JobList { jobs }))
}

/// GET /v1/jobs/{id}.
pub(crate) async fn get_job(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Json<JobStatus>> {
    let job = find_job(&app, &id)?;
    Ok(Json(job_status(&app, &job)?))
}

/// POST /v1/jobs/{id}/cancel.
pub(crate) async fn cancel_job(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Json<JobStatus>> {
    let job = find_job(&app, &id)?;
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
