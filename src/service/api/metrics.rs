//! `/healthz` and `/metrics` (Prometheus text): no token.

use super::AppState;
use super::errors::ApiResult;
use crate::protocol::Health;
use axum::Json;
use axum::extract::State;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use std::sync::atomic::Ordering;

/// GET /healthz.
pub(crate) async fn healthz() -> Json<Health> {
    Json(Health {
        status: "ok".into(),
        version: env!("CARGO_PKG_VERSION").into(),
    })
}

/// GET /metrics.
pub(crate) async fn metrics(State(app): State<AppState>) -> ApiResult<Response> {
    use std::fmt::Write;
    let mut out = String::new();
    {
        let db = app.db();
        for (table, help) in [
            ("jobs", "Jobs by state."),
            ("tasks", "Tasks of unmerged passes by state."),
            ("workers", "Registered workers by state."),
            (
                "webhook_deliveries",
                "Webhook deliveries by state (pending, delivered, failed).",
            ),
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
            "omis_merges_accepted_total",
            "Merge task outputs (one band group of a pass each) accepted.",
            &m.merges_accepted,
        ),
        (
            "omis_merge_microseconds_total",
            "Time the coordinator spent recording merged passes.",
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
    let c = &app.server;
    for (name, kind, help, v) in [
        (
            "omis_connections_open",
            "gauge",
            "HTTP connections open now.",
            c.open.load(Ordering::Relaxed) as u64,
        ),
        (
            "omis_connections_max",
            "gauge",
            "The cap on open HTTP connections (--max-connections, within the open-files limit).",
            c.max_connections.load(Ordering::Relaxed) as u64,
        ),
        (
            "omis_connections_accepted_total",
            "counter",
            "HTTP connections accepted.",
            c.accepted.load(Ordering::Relaxed),
        ),
        (
            "omis_connections_evicted_total",
            "counter",
            "Idle connections closed at the cap to make room for a new one.",
            c.evicted.load(Ordering::Relaxed),
        ),
        (
            "omis_connections_shed_total",
            "counter",
            "Connections answered 503 at the cap, every open one having a request in flight.",
            c.shed.load(Ordering::Relaxed),
        ),
    ] {
        let _ = writeln!(
            out,
            "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {v}"
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
