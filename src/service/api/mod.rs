//! The REST API under /v1 (contract: proto/openapi.yaml), Server-Sent Events, /healthz and
//! /metrics: the router and what its handlers share; one module per resource. Errors are JSON
//! `{"error": "...", "field": "..."}` with a 4xx status (errors.rs).

pub(crate) mod auth;
mod errors;
mod jobs;
mod metrics;
mod pools;
mod references;
mod scenes;
mod sequences;
mod workers;

use super::App;
use crate::service::server::Held;
use axum::Router;
use axum::body::Body;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post, put};
pub(crate) use errors::ApiError;
use std::sync::Arc;
use tokio::sync::Semaphore;

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
    ("patch", "/v1/jobs/{id}"),
    ("delete", "/v1/jobs/{id}"),
    ("post", "/v1/jobs/{id}/pause"),
    ("post", "/v1/jobs/{id}/resume"),
    ("post", "/v1/jobs/{id}/requeue"),
    ("post", "/v1/jobs/{id}/retry"),
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
    ("post", "/v1/workers/{id}/disable"),
    ("post", "/v1/workers/{id}/enable"),
    ("post", "/v1/workers/{id}/drain"),
    ("delete", "/v1/workers/{id}/unhealthy"),
    ("get", "/v1/workers/{id}/tasks"),
    ("delete", "/v1/jobs/{id}/blocklist/{worker}"),
    ("get", "/v1/jobs/{id}/tasks"),
    ("get", "/v1/jobs/{id}/webhooks"),
    ("get", "/v1/whoami"),
];

/// The coordinator's router: client routes (client token), worker routes (worker token),
/// health and metrics (no token), and a JSON 404 for anything else.
pub(crate) fn router(app: AppState) -> Router {
    let limit = DefaultBodyLimit::max(app.cfg.max_upload_bytes as usize);
    let client = Router::new()
        .route("/v1/jobs", post(jobs::create_job).get(jobs::list_jobs))
        .route(
            "/v1/jobs/{id}",
            get(jobs::get_job)
                .patch(jobs::patch_job)
                .delete(jobs::delete_job),
        )
        .route("/v1/jobs/{id}/cancel", post(jobs::cancel_job))
        .route("/v1/jobs/{id}/pause", post(jobs::pause_job))
        .route("/v1/jobs/{id}/resume", post(jobs::resume_job))
        .route("/v1/jobs/{id}/requeue", post(jobs::requeue_job))
        .route("/v1/jobs/{id}/retry", post(jobs::retry_job))
        .route("/v1/jobs/{id}/events", get(jobs::job_events))
        .route("/v1/jobs/{id}/image.exr", get(jobs::job_exr))
        .route("/v1/jobs/{id}/preview.png", get(jobs::job_preview))
        .route("/v1/jobs/{id}/error.png", get(jobs::job_error_map))
        .route("/v1/jobs/{id}/convergence.svg", get(jobs::job_convergence))
        .route("/v1/jobs/{id}/webhooks", get(jobs::job_webhooks))
        .route("/v1/whoami", get(jobs::whoami))
        .route(
            "/v1/scenes",
            post(scenes::upload_scene).get(scenes::list_scenes),
        )
        .route("/v1/references", post(references::upload_reference))
        .route("/v1/workers", get(workers::list_workers))
        .route("/v1/workers/{id}/disable", post(pools::disable_worker))
        .route("/v1/workers/{id}/enable", post(pools::enable_worker))
        .route("/v1/workers/{id}/drain", post(pools::drain_worker))
        .route("/v1/workers/{id}/unhealthy", delete(pools::clear_unhealthy))
        .route("/v1/workers/{id}/tasks", get(pools::worker_tasks))
        .route(
            "/v1/jobs/{id}/blocklist/{worker}",
            delete(pools::clear_blocklist),
        )
        .route("/v1/jobs/{id}/tasks", get(pools::job_tasks))
        .route_layer(middleware::from_fn_with_state(app.clone(), admit_client))
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
        .route_layer(middleware::from_fn_with_state(app.clone(), admit_worker))
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

/// Runs `req` if its class of routes has a request slot free (`sem`), else answers 503 at once.
/// The slot is held until the response's body has been sent: an event stream holds one while
/// it is open. With the classes' caps below the connection cap (`service::server`), requests in
/// flight never fill every connection, so there is room for `/healthz` and a newcomer.
async fn admit(sem: &Arc<Semaphore>, class: &str, req: Request, next: Next) -> Response {
    let Ok(permit) = sem.clone().try_acquire_owned() else {
        let mut r = ApiError {
            status: StatusCode::SERVICE_UNAVAILABLE,
            error: format!("too many {class} requests in flight; retry shortly"),
            field: None,
        }
        .into_response();
        r.headers_mut()
            .insert(header::RETRY_AFTER, HeaderValue::from_static("1"));
        return r;
    };
    next.run(req).await.map(|inner| {
        Body::new(Held {
            inner,
            _guard: permit,
        })
    })
}

/// The request cap of the client routes (`Config::max_client_requests`).
async fn admit_client(State(app): State<AppState>, req: Request, next: Next) -> Response {
    admit(&app.client_requests, "client", req, next).await
}

/// The request cap of the worker routes (`Config::max_worker_requests`).
async fn admit_worker(State(app): State<AppState>, req: Request, next: Next) -> Response {
    admit(&app.worker_requests, "worker", req, next).await
}

/// An id the server made or accepts: letters, digits, `-`, `_`, `.` (not first), at most 128.
pub(crate) fn is_safe_id(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= 128
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        && !s.starts_with('.')
}
