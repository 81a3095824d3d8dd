//! Bearer tokens: one for the client routes, one for the worker routes (`/v1/worker/*`).

use super::AppState;
use super::errors::ApiError;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// Checks `Authorization: Bearer <token>` against `want` (None: nothing to check).
fn check_token(headers: &HeaderMap, want: &Option<String>) -> Result<(), ApiError> {
    let Some(want) = want else {
        return Ok(());
    };
    let got = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| {
            // The scheme is case-insensitive (RFC 9110, section 11.1); the token is compared as
            // sent, after exactly one space: nothing is trimmed from it.
            let (scheme, token) = v.split_once(' ')?;
            scheme.eq_ignore_ascii_case("bearer").then_some(token)
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

/// Middleware of the client routes.
pub(crate) async fn client_auth(State(app): State<AppState>, req: Request, next: Next) -> Response {
    match check_token(req.headers(), &app.cfg.client_token) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}

/// Middleware of the worker routes.
pub(crate) async fn worker_auth(State(app): State<AppState>, req: Request, next: Next) -> Response {
    match check_token(req.headers(), &app.cfg.worker_token) {
        Ok(()) => next.run(req).await,
        Err(e) => e.into_response(),
    }
}
