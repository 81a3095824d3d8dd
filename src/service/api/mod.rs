//! The REST API under /v1 (contract: proto/openapi.yaml), Server-Sent Events, /healthz and
//! /metrics: the router and what its handlers share; one module per resource. Errors are JSON
//! `{"error": "...", "field": "..."}` with a 4xx status (errors.rs).

mod auth;
mod errors;
mod jobs;
mod metrics;
mod references;
mod scenes;
mod workers;

use super::App;
use axum::Router;
use axum::extract::DefaultBodyLimit;
use axum::http::StatusCode;
use axum::middleware;
use axum::routing::{get, post, put};
use errors::ApiError;
use std::sync::Arc;

/// The state every handler gets.
pub(crate) type AppState = Arc<App>;

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
    ("get", "/v1/worker/tasks/{id}/input"),
    ("put", "/v1/worker/tasks/{id}/result"),
    ("post", "/v1/worker/tasks/{id}/fail"),
];

/// The coordinator's router: client routes (client token), worker routes (worker token),
/// health and metrics (no token), and a JSON 404 for anything else.
pub(crate) fn router(app: AppState) -> Router {
    let limit = DefaultBodyLimit::max(app.cfg.max_upload_bytes as usize);
    let client = Router::new()
        .route("/v1/jobs", post(jobs::create_job).get(jobs::list_jobs))
        .route("/v1/jobs/{id}", get(jobs::get_job))
        .route("/v1/jobs/{id}/cancel", post(jobs::cancel_job))
        .route("/v1/jobs/{id}/events", get(jobs::job_events))
        .route("/v1/jobs/{id}/image.exr", get(jobs::job_exr))
        .route("/v1/jobs/{id}/preview.png", get(jobs::job_preview))
        .route("/v1/jobs/{id}/error.png", get(jobs::job_error_map))
        .route("/v1/jobs/{id}/convergence.svg", get(jobs::job_convergence))
        .route(
            "/v1/scenes",
            post(scenes::upload_scene).get(scenes::list_scenes),
        )
        .route("/v1/references", post(references::upload_reference))
        .route("/v1/workers", get(workers::list_workers))
        .route_layer(middleware::from_fn_with_state(
            app.clone(),
            auth::client_auth,
        ));
    let worker = Router::new()
        .route("/v1/worker/register", post(workers::register))
        .route("/v1/worker/lease", post(workers::lease))
        .route("/v1/worker/heartbeat", post(workers::heartbeat))
        .route("/v1/worker/deregister", post(workers::deregister))
        .route("/v1/worker/scenes/{id}", get(workers::worker_scene))
        .route("/v1/worker/tasks/{id}/input", get(workers::merge_input))
        .route("/v1/worker/tasks/{id}/result", put(workers::upload_result))
        .route("/v1/worker/tasks/{id}/fail", post(workers::fail_task))
        .route_layer(middleware::from_fn_with_state(
            app.clone(),
            auth::worker_auth,
        ));
    Router::new()
        .route("/healthz", get(metrics::healthz))
        .route("/metrics", get(metrics::metrics))
        .merge(client)
        .merge(worker)
        .merge(super::web::routes())
        .fallback(|| async { ApiError::field(StatusCode::NOT_FOUND, "path", "no such route") })
        .layer(limit)
        .layer(middleware::from_fn_with_state(
            app.clone(),
            errors::json_errors,
        ))
        .with_state(app)
}

/// An id the server made or accepts: letters, digits, `-`, `_`, `.` (not first), at most 128.
pub(crate) fn is_safe_id(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= 128
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        && !s.starts_with('.')
}
