//! The REST API under /v1 (contract: proto/openapi.yaml), Server-Sent Events, /healthz and
//! /metrics. Errors are JSON `{"error": "...", "field": "..."}` with a 4xx status.

use super::store::{self, JobRow};
use super::{App, Metrics, bundle, jobs};
use crate::film::TileFilm;
use crate::film::exr_io;
use crate::job::{FieldError, JobSettings};
use crate::scene::Scene;
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, Path, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use axum::{Json, Router};
use futures_util::stream::{self, Stream, StreamExt};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use std::convert::Infallible;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

type AppState = Arc<App>;

/// An API error: status, message, and the field or parameter it is about.
#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub error: String,
    pub field: Option<String>,
}

impl ApiError {
    pub fn new(status: StatusCode, error: impl Into<String>) -> ApiError {
        ApiError {
            status,
            error: error.into(),
            field: None,
        }
    }
    pub fn field(status: StatusCode, field: impl Into<String>, error: impl Into<String>) -> Self {
        ApiError {
            status,
            error: error.into(),
            field: Some(field.into()),
        }
    }
    fn internal(e: impl std::fmt::Display) -> ApiError {
        ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string())
    }
    fn not_found(what: &str, id: &str) -> ApiError {
        ApiError::field(StatusCode::NOT_FOUND, "id", format!("no {what} '{id}'"))
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut body = json!({ "error": self.error });
        if let Some(f) = self.field {
            body["field"] = json!(f);
        }
        (self.status, Json(body)).into_response()
    }
}

impl From<rusqlite::Error> for ApiError {
    fn from(e: rusqlite::Error) -> Self {
        ApiError::internal(format!("database: {e}"))
    }
}

type ApiResult<T> = Result<T, ApiError>;

/// Parses a JSON body, naming the field of the first problem (unknown fields included).
fn parse_json<T: serde::de::DeserializeOwned>(body: &[u8]) -> ApiResult<T> {
    let de = &mut serde_json::Deserializer::from_slice(body);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let syntax = inner.is_syntax() || inner.is_eof();
        let field = if path == "." || syntax {
            "body".to_string()
        } else {
            path
        };
        let status = if syntax {
            StatusCode::BAD_REQUEST
        } else {
            StatusCode::UNPROCESSABLE_ENTITY
        };
        ApiError::field(status, field, format!("invalid JSON: {inner}"))
    })
}

/// Every route the router serves, as (method, path) — the set proto/openapi.yaml must describe.
pub const ROUTES: &[(&str, &str)] = &[
    ("get", "/healthz"),
    ("get", "/metrics"),
    ("post", "/v1/jobs"),
    ("get", "/v1/jobs"),
    ("get", "/v1/jobs/{id}"),
    ("post", "/v1/jobs/{id}/cancel"),
    ("get", "/v1/jobs/{id}/events"),
    ("get", "/v1/jobs/{id}/image.exr"),
    ("get", "/v1/jobs/{id}/preview.png"),
    ("get", "/v1/jobs/{id}/error.png"),
    ("get", "/v1/jobs/{id}/convergence.svg"),
    ("post", "/v1/scenes"),
    ("get", "/v1/scenes"),
    ("post", "/v1/references"),
    ("get", "/v1/workers"),
    ("post", "/v1/worker/register"),
    ("post", "/v1/worker/lease"),
    ("post", "/v1/worker/heartbeat"),
    ("post", "/v1/worker/deregister"),
    ("get", "/v1/worker/scenes/{id}"),
    ("put", "/v1/worker/tasks/{id}/result"),
    ("post", "/v1/worker/tasks/{id}/fail"),
];

pub fn router(app: AppState) -> Router {
    let limit = DefaultBodyLimit::max(app.cfg.max_upload_bytes as usize);
    let client = Router::new()
        .route("/v1/jobs", post(create_job).get(list_jobs))
        .route("/v1/jobs/{id}", get(get_job))
        .route("/v1/jobs/{id}/cancel", post(cancel_job))
        .route("/v1/jobs/{id}/events", get(job_events))
        .route("/v1/jobs/{id}/image.exr", get(job_exr))
        .route("/v1/jobs/{id}/preview.png", get(job_preview))
        .route("/v1/jobs/{id}/error.png", get(job_error_map))
        .route("/v1/jobs/{id}/convergence.svg", get(job_convergence))
        .route("/v1/scenes", post(upload_scene).get(list_scenes))
        .route("/v1/references", post(upload_reference))
        .route("/v1/workers", get(list_workers))
        .route_layer(middleware::from_fn_with_state(app.clone(), client_auth));
    let worker = Router::new()
        .route("/v1/worker/register", post(register))
        .route("/v1/worker/lease", post(lease))
        .route("/v1/worker/heartbeat", post(heartbeat))
        .route("/v1/worker/deregister", post(deregister))
        .route("/v1/worker/scenes/{id}", get(worker_scene))
        .route("/v1/worker/tasks/{id}/result", put(upload_result))
        .route("/v1/worker/tasks/{id}/fail", post(fail_task))
        .route_layer(middleware::from_fn_with_state(app.clone(), worker_auth));
    Router::new()
        .route("/healthz", get(healthz))
        .route("/metrics", get(metrics))
        .merge(client)
        .merge(worker)
        .merge(super::web::routes())
        .fallback(|| async { ApiError::field(StatusCode::NOT_FOUND, "path", "no such route") })
        .layer(limit)
        .layer(middleware::from_fn_with_state(app.clone(), count_errors))
        .with_state(app)
}

/// Counts errors, and turns the plain-text rejections of axum's extractors and router (bad path
/// or query parameters, wrong method, body too large) into our JSON error shape.
async fn count_errors(State(app): State<AppState>, req: Request, next: Next) -> Response {
    let r = next.run(req).await;
    let status = r.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return r;
    }
    Metrics::add(&app.metrics.http_errors, 1);
    let is_json = r
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if is_json {
        return r;
    }
    let text = match axum::body::to_bytes(r.into_body(), 64 << 10).await {
        Ok(b) => String::from_utf8_lossy(&b).into_owned(),
        Err(_) => String::new(),
    };
    let field = match status {
        StatusCode::METHOD_NOT_ALLOWED => "method",
        StatusCode::PAYLOAD_TOO_LARGE => "body",
        _ if text.contains("query") => "query",
        _ if text.contains("path") => "path",
        _ => "body",
    };
    let msg = if text.is_empty() {
        status
            .canonical_reason()
            .unwrap_or("request refused")
            .to_string()
    } else {
        text
    };
    ApiError::field(status, field, msg).into_response()
}

fn check_token(headers: &HeaderMap, want: &Option<String>) -> Result<(), ApiError> {
    let Some(want) = want else {
        return Ok(());
    };
    let got = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| {
            let (scheme, token) = v.split_once(' ')?;
            scheme.eq_ignore_ascii_case("bearer").then(|| token.trim())
        });
    match got {
        Some(t) if constant_time_eq(t.as_bytes(), want.as_bytes()) => Ok(()),
        Some(_) => Err(ApiError::field(
            StatusCode::UNAUTHORIZED,
            "Authorization",
            "invalid bearer token",
        )),
        None => Err(ApiError::field(
            StatusCode::UNAUTHORIZED,
            "Authorization",
            "missing bearer token (Authorization: Bearer <token>)",
        )),
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

async fn client_auth(State(app): State<AppState>, req: Request, next: Next) -> Response {
    match check_token(req.headers(), &app.cfg.client_token) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

async fn worker_auth(State(app): State<AppState>, req: Request, next: Next) -> Response {
    match check_token(req.headers(), &app.cfg.worker_token) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

async fn healthz() -> Json<Value> {
    Json(json!({ "status": "ok", "version": env!("CARGO_PKG_VERSION") }))
}

async fn metrics(State(app): State<AppState>) -> ApiResult<Response> {
    use std::fmt::Write;
    let mut out = String::new();
    {
        let db = app.db();
        for (table, help) in [
            ("jobs", "Jobs by state."),
            ("tasks", "Tasks of unmerged passes by state."),
            ("workers", "Registered workers by state."),
        ] {
            let _ = writeln!(out, "# HELP omis_{table} {help}\n# TYPE omis_{table} gauge");
            for (state, n) in db.state_counts(table)? {
                let _ = writeln!(out, "omis_{table}{{state=\"{state}\"}} {n}");
            }
        }
    }
    let m = &app.metrics;
    for (name, help, v) in [
        (
            "omis_results_accepted_total",
            "Task results merged or awaiting their pass.",
            &m.results_accepted,
        ),
        (
            "omis_results_refused_total",
            "Task results refused (stale attempt, non-owner, invalid).",
            &m.results_refused,
        ),
        (
            "omis_result_bytes_total",
            "Bytes of accepted task results.",
            &m.result_bytes,
        ),
        (
            "omis_passes_merged_total",
            "Passes merged.",
            &m.passes_merged,
        ),
        (
            "omis_merge_microseconds_total",
            "Time spent merging passes.",
            &m.merge_micros,
        ),
        (
            "omis_leases_expired_total",
            "Leases given back after a silent worker.",
            &m.leases_expired,
        ),
        (
            "omis_worker_restarts_total",
            "Local worker processes restarted.",
            &m.worker_restarts,
        ),
        (
            "omis_http_errors_total",
            "HTTP responses with a 4xx or 5xx status.",
            &m.http_errors,
        ),
    ] {
        let _ = writeln!(
            out,
            "# HELP {name} {help}\n# TYPE {name} counter\n{name} {}",
            v.load(Ordering::Relaxed)
        );
    }
    Ok((
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/plain; version=0.0.4"),
        )],
        out,
    )
        .into_response())
}

// ---- jobs ----

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "lowercase")]
enum SceneSource {
    /// A scene file of the server's library, by name (with or without extension).
    Library(String),
    /// A bundle uploaded with POST /v1/scenes.
    Bundle(String),
    /// A scene in omis's JSON format, inline (meshes inline too).
    Inline(Value),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "lowercase")]
enum ReferenceSource {
    /// An EXR uploaded with POST /v1/references.
    Upload(String),
    /// The image of an earlier job that is done.
    Job(String),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JobRequest {
    scene: SceneSource,
    #[serde(default)]
    settings: JobSettings,
    #[serde(default)]
    reference: Option<ReferenceSource>,
    #[serde(default)]
    name: Option<String>,
}

fn is_safe_id(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= 128
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        && !s.starts_with('.')
}

fn bad(field: &str, msg: impl Into<String>) -> ApiError {
    ApiError::field(StatusCode::BAD_REQUEST, field, msg)
}

fn settings_error(e: FieldError) -> ApiError {
    let field = if e.field == "scene" {
        e.field
    } else {
        format!("settings.{}", e.field)
    };
    ApiError::field(StatusCode::UNPROCESSABLE_ENTITY, field, e.message)
}

/// Metadata of a stored scene bundle.
#[derive(Serialize, Deserialize, Clone)]
struct SceneMeta {
    id: String,
    main: String,
    files: Vec<String>,
    bytes: u64,
    triangles: usize,
    width: u32,
    height: u32,
    warnings: Vec<String>,
}

/// Stores a bundle: unpacks it under scenes/<id>/files, loads it to check it, keeps the tar for
/// workers. Runs on a blocking thread.
fn store_bundle(
    app: &App,
    tar: &[u8],
    main: Option<&str>,
    field: &str,
) -> ApiResult<(SceneMeta, Scene)> {
    let id = uuid::Uuid::new_v4().to_string();
    let dir = app.paths.scene(&id);
    let files_dir = dir.join("files");
    let result = (|| {
        let files =
            bundle::unpack(tar, &files_dir, app.cfg.max_upload_bytes).map_err(|e| bad(field, e))?;
        let main = bundle::choose_main(&files, main).map_err(|e| bad(field, e))?;
        let scene = Scene::load(&files_dir.join(&main)).map_err(|e| {
            // Name the file inside the bundle, not the server's path.
            let msg = e
                .to_string()
                .replace(&format!("{}/", files_dir.display()), "");
            bad(field, msg)
        })?;
        if scene.stats.triangles > app.cfg.limits.max_triangles {
            return Err(bad(
                field,
                format!(
                    "{} triangles exceed the limit of {}",
                    scene.stats.triangles, app.cfg.limits.max_triangles
                ),
            ));
        }
        let meta = SceneMeta {
            id: id.clone(),
            main,
            files,
            bytes: tar.len() as u64,
            triangles: scene.stats.triangles,
            width: scene.camera.width,
            height: scene.camera.height,
            warnings: scene.warnings.clone(),
        };
        std::fs::write(dir.join("bundle.tar"), tar).map_err(ApiError::internal)?;
        let json = serde_json::to_vec_pretty(&meta).map_err(ApiError::internal)?;
        store::write_atomic(&dir.join("meta.json"), &json).map_err(ApiError::internal)?;
        Ok((meta, scene))
    })();
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&dir);
    }
    result
}

fn scene_meta(app: &App, id: &str) -> Option<SceneMeta> {
    if !is_safe_id(id) {
        return None;
    }
    let bytes = std::fs::read(app.paths.scene(id).join("meta.json")).ok()?;
    serde_json::from_slice(&bytes).ok()
}

/// A library scene file by name: `name` or `name.json|.pbrt|.xml`, directly in the library.
fn library_file(app: &App, name: &str) -> ApiResult<std::path::PathBuf> {
    let lib = app
        .cfg
        .library
        .as_ref()
        .ok_or_else(|| bad("scene.library", "this server has no scene library"))?;
    if !is_safe_id(name) {
        return Err(bad(
            "scene.library",
            format!("'{name}' is not a scene name (letters, digits, - _ . only; no paths)"),
        ));
    }
    let candidates = [
        name.to_string(),
        format!("{name}.json"),
        format!("{name}.pbrt"),
        format!("{name}.xml"),
    ];
    candidates
        .iter()
        .map(|c| lib.join(c))
        .find(|p| p.is_file())
        .ok_or_else(|| bad("scene.library", format!("no scene '{name}' in the library")))
}

fn library_names(app: &App) -> Vec<String> {
    let Some(lib) = &app.cfg.library else {
        return Vec::new();
    };
    let mut v: Vec<String> = std::fs::read_dir(lib)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| e.file_name().to_str().map(str::to_string))
                .filter_map(|n| {
                    [".json", ".pbrt", ".xml"]
                        .iter()
                        .find_map(|ext| n.strip_suffix(ext).map(str::to_string))
                })
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

async fn create_job(State(app): State<AppState>, body: Bytes) -> ApiResult<Response> {
    let req: JobRequest = parse_json(&body)?;
    req.settings
        .validate(&app.cfg.limits)
        .map_err(settings_error)?;
    if let Some(n) = &req.name
        && (n.len() > 200 || n.chars().any(|c| c.is_control()))
    {
        return Err(bad("name", "at most 200 characters, no control characters"));
    }
    let a = app.clone();
    let job = tokio::task::spawn_blocking(move || create_job_blocking(&a, req))
        .await
        .map_err(ApiError::internal)??;
    app.work.notify_waiters();
    let status = job_status(&app, &job)?;
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, format!("/v1/jobs/{}", job.id))],
        Json(status),
    )
        .into_response())
}

fn create_job_blocking(app: &App, req: JobRequest) -> ApiResult<JobRow> {
    let (meta, mut scene) = match &req.scene {
        SceneSource::Library(name) => {
            let path = library_file(app, name)?;
            let (tar, main) = bundle::pack(&path).map_err(|e| bad("scene.library", e))?;
            store_bundle(app, &tar, Some(&main), "scene.library")?
        }
        SceneSource::Bundle(id) => {
            let meta = scene_meta(app, id)
                .ok_or_else(|| bad("scene.bundle", format!("no scene bundle '{id}'")))?;
            let path = app.paths.scene(id).join("files").join(&meta.main);
            let scene = Scene::load(&path).map_err(|e| bad("scene.bundle", e.to_string()))?;
            (meta, scene)
        }
        SceneSource::Inline(v) => {
            if !v.is_object() {
                return Err(bad("scene.inline", "must be a scene object"));
            }
            let text = serde_json::to_vec_pretty(v).map_err(ApiError::internal)?;
            let mut tar = tar::Builder::new(Vec::new());
            let mut h = tar::Header::new_gnu();
            h.set_size(text.len() as u64);
            h.set_mode(0o644);
            h.set_cksum();
            tar.append_data(&mut h, "scene.json", text.as_slice())
                .map_err(ApiError::internal)?;
            let bytes = tar.into_inner().map_err(ApiError::internal)?;
            store_bundle(app, &bytes, Some("scene.json"), "scene.inline")?
        }
    };
    let resolved = req
        .settings
        .resolve(&mut scene, &app.cfg.limits)
        .map_err(settings_error)?;
    let reference = match &req.reference {
        None => None,
        Some(src) => {
            let (path, field) = match src {
                ReferenceSource::Upload(id) => {
                    if !is_safe_id(id) {
                        return Err(bad("reference.upload", format!("no reference '{id}'")));
                    }
                    (app.paths.reference(id), "reference.upload")
                }
                ReferenceSource::Job(id) => {
                    let j = app
                        .db()
                        .job(id)?
                        .ok_or_else(|| bad("reference.job", format!("no job '{id}'")))?;
                    if j.state != store::DONE {
                        return Err(bad(
                            "reference.job",
                            format!("job '{id}' is {}, not done", j.state),
                        ));
                    }
                    (app.paths.output(id, "image.exr"), "reference.job")
                }
            };
            let img = exr_io::read_exr(&path)
                .map_err(|_| bad(field, "no such reference image".to_string()))?;
            if (img.width, img.height) != (resolved.width as usize, resolved.height as usize) {
                return Err(bad(
                    field,
                    format!(
                        "the reference is {}x{}, the job renders {}x{}",
                        img.width, img.height, resolved.width, resolved.height
                    ),
                ));
            }
            Some(path.display().to_string())
        }
    };
    let id = uuid::Uuid::new_v4().to_string();
    let accum = resolved.film_layout().bytes_per_pixel() as i64
        * resolved.width as i64
        * resolved.height as i64;
    let settings = serde_json::to_string(&req.settings).map_err(ApiError::internal)?;
    let res = serde_json::to_string(&resolved).map_err(ApiError::internal)?;
    std::fs::create_dir_all(app.paths.job(&id)).map_err(ApiError::internal)?;
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
    let row = app
        .db()
        .job(&id)?
        .ok_or_else(|| ApiError::internal("job vanished"))?;
    jobs::ensure_passes(app, &row, &resolved)?;
    app.event(
        &id,
        "queued",
        json!({ "width": resolved.width, "height": resolved.height, "spp": resolved.spp }),
    );
    app.db()
        .job(&id)?
        .ok_or_else(|| ApiError::internal("job vanished"))
}

/// The status document of a job (GET /v1/jobs/{id}).
fn job_status(app: &App, job: &JobRow) -> ApiResult<Value> {
    let r = jobs::resolved_of(job).map_err(ApiError::internal)?;
    let settings: Value = serde_json::from_str(&job.settings).unwrap_or(Value::Null);
    let series = app.db().series(&job.id)?;
    let tiles = r.tiles().len() as u32;
    let active = matches!(job.state.as_str(), store::QUEUED | store::RUNNING);
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
    // Samples per pixel done, counting finished tiles of unmerged passes pro rata.
    let progress_spp =
        job.spp_done as f64 + tiles_done as f64 / tiles.max(1) as f64 * r.pass_size as f64;
    let eta = if !active {
        Some(0.0)
    } else if let Some(spp) = r.spp {
        (progress_spp > 0.0)
            .then(|| elapsed / progress_spp * (spp as f64 - progress_spp).max(0.0))
            .map(|e| match r.time_budget_s {
                Some(b) => e.min((b - elapsed).max(0.0)),
                None => e,
            })
    } else {
        r.time_budget_s.map(|b| (b - elapsed).max(0.0))
    };
    let id = &job.id;
    Ok(json!({
        "id": id,
        "name": job.name,
        "state": job.state,
        "error": job.error,
        "scene": { "id": job.scene_id, "main": job.scene_main },
        "settings": settings,
        "width": r.width,
        "height": r.height,
        "spp_target": r.spp,
        "time_budget_s": r.time_budget_s,
        "spp_done": job.spp_done,
        "passes_done": job.passes_done,
        "passes_total": r.total_passes(),
        "tiles_per_pass": tiles,
        "tiles_done": tiles_done,
        "created_at": job.created_at,
        "started_at": job.started_at,
        "finished_at": job.finished_at,
        "elapsed_s": elapsed,
        "eta_s": eta,
        "relmse": series.last().and_then(|p| p.relmse),
        "series": series,
        "accum_bytes": job.accum_bytes,
        "accum_bytes_per_pixel": job.accum_bytes / (r.width as i64 * r.height as i64).max(1),
        "result_bytes": job.result_bytes,
        "samples": job.samples,
        "rays": job.rays,
        "non_finite_samples": job.non_finite,
        "has_reference": job.reference.is_some(),
        "links": {
            "self": format!("/v1/jobs/{id}"),
            "events": format!("/v1/jobs/{id}/events"),
            "image": format!("/v1/jobs/{id}/image.exr"),
            "preview": format!("/v1/jobs/{id}/preview.png"),
            "error": format!("/v1/jobs/{id}/error.png"),
            "convergence": format!("/v1/jobs/{id}/convergence.svg"),
        }
    }))
}

fn find_job(app: &App, id: &str) -> ApiResult<JobRow> {
    app.db()
        .job(id)?
        .ok_or_else(|| ApiError::not_found("job", id))
}

async fn list_jobs(State(app): State<AppState>) -> ApiResult<Json<Value>> {
    let jobs = app.db().jobs()?;
    let list: Vec<Value> = jobs
        .iter()
        .map(|j| job_status(&app, j))
        .collect::<ApiResult<_>>()?;
    Ok(Json(json!({ "jobs": list })))
}

async fn get_job(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult<Json<Value>> {
    let job = find_job(&app, &id)?;
    Ok(Json(job_status(&app, &job)?))
}

async fn cancel_job(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult<Json<Value>> {
    let job = find_job(&app, &id)?;
    let a = app.clone();
    let i = id.clone();
    let cancelled = tokio::task::spawn_blocking(move || jobs::cancel(&a, &i))
        .await
        .map_err(ApiError::internal)?
        .map_err(ApiError::internal)?;
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

fn sse_event(row: &store::EventRow) -> Event {
    let mut data = row.data.clone();
    if let Value::Object(m) = &mut data {
        m.insert("job".into(), json!(row.job_id));
        m.insert("at".into(), json!(row.at));
    }
    Event::default()
        .id(row.id.to_string())
        .event(row.kind.clone())
        .data(data.to_string())
}

fn is_terminal(kind: &str) -> bool {
    matches!(kind, "done" | "failed" | "cancelled")
}

async fn job_events(
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
    let ended = backlog.iter().any(|e| is_terminal(&e.kind))
        || !matches!(job.state.as_str(), store::QUEUED | store::RUNNING);
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
                        let end = is_terminal(&e.kind);
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
    let job = find_job(app, id)?;
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

async fn job_exr(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    job_file(&app, &id, "image.exr", "image/x-exr").await
}

async fn job_preview(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    job_file(&app, &id, "preview.png", "image/png").await
}

async fn job_error_map(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
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

async fn job_convergence(
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

// ---- scenes and references ----

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneQuery {
    main: Option<String>,
}

async fn upload_scene(
    State(app): State<AppState>,
    Query(q): Query<SceneQuery>,
    body: Bytes,
) -> ApiResult<Response> {
    if body.is_empty() {
        return Err(bad("body", "empty body; send a tar archive of the scene"));
    }
    let a = app.clone();
    let (meta, _) =
        tokio::task::spawn_blocking(move || store_bundle(&a, &body, q.main.as_deref(), "body"))
            .await
            .map_err(ApiError::internal)??;
    Ok((StatusCode::CREATED, Json(meta)).into_response())
}

async fn list_scenes(State(app): State<AppState>) -> Json<Value> {
    Json(json!({ "library": library_names(&app) }))
}

async fn upload_reference(State(app): State<AppState>, body: Bytes) -> ApiResult<Response> {
    let id = uuid::Uuid::new_v4().to_string();
    let path = app.paths.reference(&id);
    let img = tokio::task::spawn_blocking(move || {
        store::write_atomic(&path, &body).map_err(ApiError::internal)?;
        exr_io::read_exr(&path).map_err(|e| {
            let _ = std::fs::remove_file(&path);
            let msg = e.replace(&format!("{}: ", path.display()), "");
            bad(
                "body",
                format!("the reference must be an OpenEXR image: {msg}"),
            )
        })
    })
    .await
    .map_err(ApiError::internal)??;
    Ok((
        StatusCode::CREATED,
        Json(json!({ "id": id, "width": img.width, "height": img.height })),
    )
        .into_response())
}

async fn list_workers(State(app): State<AppState>) -> ApiResult<Json<Value>> {
    let workers = app.db().workers()?;
    Ok(Json(json!({ "workers": workers })))
}

// ---- workers ----

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RegisterRequest {
    name: String,
    threads: u32,
    #[serde(default)]
    version: String,
    /// A previous id, to keep it across reconnects.
    #[serde(default)]
    id: Option<String>,
}

async fn register(State(app): State<AppState>, body: Bytes) -> ApiResult<Json<Value>> {
    let r: RegisterRequest = parse_json(&body)?;
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
    app.db()
        .register_worker(&id, &name, r.threads.clamp(1, 4096), &r.version)?;
    tracing::info!("worker {name} ({id}) registered with {} threads", r.threads);
    Ok(Json(json!({
        "worker_id": id,
        "lease_seconds": app.cfg.lease_s,
        "heartbeat_seconds": (app.cfg.lease_s / 4.0).max(0.5),
    })))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct LeaseRequest {
    worker_id: String,
    /// Long-poll up to this many seconds (at most 30).
    #[serde(default)]
    wait_s: Option<f64>,
}

async fn lease(State(app): State<AppState>, body: Bytes) -> ApiResult<Response> {
    let r: LeaseRequest = parse_json(&body)?;
    if !app.db().touch_worker(&r.worker_id, None)? {
        return Err(ApiError::field(
            StatusCode::NOT_FOUND,
            "worker_id",
            "unknown worker; register again",
        ));
    }
    let wait = r.wait_s.unwrap_or(20.0).clamp(0.0, 30.0);
    let deadline = tokio::time::Instant::now() + Duration::from_secs_f64(wait);
    loop {
        let notified = app.work.notified();
        tokio::pin!(notified);
        notified.as_mut().enable();
        let leased = {
            let db = app.db();
            match db.lease(&r.worker_id, app.cfg.lease_s)? {
                Some(t) => {
                    db.touch_worker(&r.worker_id, Some("busy"))?;
                    let job = db.job(&t.job_id)?;
                    Some((t, job))
                }
                None => None,
            }
        };
        if let Some((task, Some(job))) = leased {
            let res = jobs::resolved_of(&job).map_err(ApiError::internal)?;
            let tile = res
                .tiles()
                .get(task.tile as usize)
                .copied()
                .ok_or_else(|| ApiError::internal("tile index out of range"))?;
            return Ok(Json(json!({
                "task": {
                    "id": task.id,
                    "attempt": task.attempt,
                    "job_id": task.job_id,
                    "pass": task.pass,
                    "tile": task.tile,
                    "rect": tile,
                    "samples": [task.s0, task.s1],
                },
                "job": {
                    "scene_id": job.scene_id,
                    "scene_main": job.scene_main,
                    "resolved": res,
                },
                "lease_seconds": app.cfg.lease_s,
            }))
            .into_response());
        }
        tokio::select! {
            _ = &mut notified => {}
            _ = tokio::time::sleep_until(deadline) => return Ok(StatusCode::NO_CONTENT.into_response()),
            _ = tokio::time::sleep(Duration::from_secs(1)) => {}
        }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct HeldTask {
    id: i64,
    attempt: u32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct HeartbeatRequest {
    worker_id: String,
    #[serde(default)]
    tasks: Vec<HeldTask>,
}

async fn heartbeat(State(app): State<AppState>, body: Bytes) -> ApiResult<Json<Value>> {
    let r: HeartbeatRequest = parse_json(&body)?;
    let db = app.db();
    let state = if r.tasks.is_empty() { "idle" } else { "busy" };
    if !db.touch_worker(&r.worker_id, Some(state))? {
        return Err(ApiError::field(
            StatusCode::NOT_FOUND,
            "worker_id",
            "unknown worker; register again",
        ));
    }
    let mut lost = Vec::new();
    for t in &r.tasks {
        if !db.extend(t.id, t.attempt, &r.worker_id, app.cfg.lease_s)? {
            lost.push(t.id);
        }
    }
    Ok(Json(json!({ "lost": lost })))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct DeregisterRequest {
    worker_id: String,
}

async fn deregister(State(app): State<AppState>, body: Bytes) -> ApiResult<Json<Value>> {
    let r: DeregisterRequest = parse_json(&body)?;
    let released = {
        let db = app.db();
        if !db.touch_worker(&r.worker_id, Some("left"))? {
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
    Ok(Json(json!({ "ok": true, "released": released })))
}

async fn worker_scene(State(app): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    if scene_meta(&app, &id).is_none() {
        return Err(ApiError::not_found("scene", &id));
    }
    let bytes = tokio::fs::read(app.paths.scene(&id).join("bundle.tar"))
        .await
        .map_err(ApiError::internal)?;
    Ok((
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/x-tar"),
        )],
        bytes,
    )
        .into_response())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ResultQuery {
    worker_id: String,
    attempt: u32,
}

/// Whether `task` is still `worker`'s current attempt (else the 409 to answer).
fn check_owner(task: &store::TaskRow, worker: &str, attempt: u32) -> ApiResult<()> {
    if task.state != store::T_LEASED
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

async fn upload_result(
    State(app): State<AppState>,
    Path(task_id): Path<i64>,
    Query(q): Query<ResultQuery>,
    body: Bytes,
) -> ApiResult<Json<Value>> {
    let refused = |e: ApiError| {
        Metrics::add(&app.metrics.results_refused, 1);
        e
    };
    let (task, job) = {
        let db = app.db();
        let Some(task) = db.task(task_id)? else {
            return Err(refused(if db.task_existed(task_id)? {
                ApiError::field(
                    StatusCode::CONFLICT,
                    "id",
                    format!("task {task_id} is no longer current (its pass was merged)"),
                )
            } else {
                ApiError::not_found("task", &task_id.to_string())
            }));
        };
        let job = db
            .job(&task.job_id)?
            .ok_or_else(|| ApiError::internal("task without job"))?;
        (task, job)
    };
    check_owner(&task, &q.worker_id, q.attempt).map_err(refused)?;
    if job.state != store::RUNNING {
        return Err(refused(ApiError::field(
            StatusCode::CONFLICT,
            "id",
            format!("job '{}' is {}", job.id, job.state),
        )));
    }
    let a = app.clone();
    let t = task.clone();
    let worker = q.worker_id.clone();
    let n = body.len();
    let checked = tokio::task::spawn_blocking(move || -> ApiResult<Option<String>> {
        let r = jobs::resolved_of(&job).map_err(ApiError::internal)?;
        let layout = r.film_layout();
        let tile = r.tiles().get(t.tile as usize).copied();
        let problem = match TileFilm::decode(&body, r.width, r.height, &layout) {
            Err(e) => Some(e.to_string()),
            Ok((f, range)) if Some(f.tile) != tile || range != (t.s0..t.s1) => Some(format!(
                "result is for tile {:?} samples {range:?}, the task is tile {tile:?} samples {}..{}",
                f.tile, t.s0, t.s1
            )),
            Ok(_) => None,
        };
        if let Some(p) = problem {
            return Ok(Some(p));
        }
        let path = a.paths.result(&t.job_id, t.pass, t.tile, t.attempt);
        store::write_atomic(&path, &body).map_err(ApiError::internal)?;
        Ok(None)
    })
    .await
    .map_err(ApiError::internal)??;
    if let Some(problem) = checked {
        let _ = jobs::task_failed(&app, &task, &worker, &format!("invalid result: {problem}"));
        return Err(refused(ApiError::field(
            StatusCode::BAD_REQUEST,
            "body",
            problem,
        )));
    }
    let accepted = app.db().complete(task.id, task.attempt, &worker, n)?;
    if !accepted {
        let _ = std::fs::remove_file(app.paths.result(
            &task.job_id,
            task.pass,
            task.tile,
            task.attempt,
        ));
        return Err(refused(ApiError::field(
            StatusCode::CONFLICT,
            "attempt",
            format!(
                "task {} attempt {} is no longer current",
                task.id, task.attempt
            ),
        )));
    }
    Metrics::add(&app.metrics.results_accepted, 1);
    Metrics::add(&app.metrics.result_bytes, n as u64);
    app.event(
        &task.job_id,
        "tile_done",
        json!({ "pass": task.pass, "tile": task.tile, "worker": worker, "bytes": n }),
    );
    let a = app.clone();
    let id = task.job_id.clone();
    tokio::task::spawn_blocking(move || jobs::advance(&a, &id));
    Ok(Json(json!({ "accepted": true })))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FailRequest {
    worker_id: String,
    attempt: u32,
    error: String,
}

async fn fail_task(
    State(app): State<AppState>,
    Path(task_id): Path<i64>,
    body: Bytes,
) -> ApiResult<Json<Value>> {
    let r: FailRequest = parse_json(&body)?;
    let task = app
        .db()
        .task(task_id)?
        .ok_or_else(|| ApiError::not_found("task", &task_id.to_string()))?;
    check_owner(&task, &r.worker_id, r.attempt)?;
    let error: String = r.error.chars().take(2000).collect();
    let a = app.clone();
    let w = r.worker_id.clone();
    tokio::task::spawn_blocking(move || jobs::task_failed(&a, &task, &w, &error))
        .await
        .map_err(ApiError::internal)?
        .map_err(ApiError::internal)?;
    Ok(Json(json!({ "ok": true })))
}
