//! Errors of the API: `ApiError` and its JSON body `{"error": "...", "field": "..."}`, the
//! parsing of JSON bodies that names the field of the first problem, and the middleware that
//! turns the framework's own plain-text rejections into the same JSON shape.

use super::AppState;
use crate::job::FieldError;
use crate::service::Metrics;
use crate::service::protocol::ErrorBody;
use axum::Json;
use axum::extract::{Request, State};
use axum::http::{StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// An API error: status, message, and the field or parameter it is about.
#[derive(Debug)]
pub(crate) struct ApiError {
    pub status: StatusCode,
    pub error: String,
    pub field: Option<String>,
}

impl ApiError {
    /// An error about the field, parameter or header `field`.
    pub fn field(status: StatusCode, field: impl Into<String>, error: impl Into<String>) -> Self {
        ApiError {
            status,
            error: error.into(),
            field: Some(field.into()),
        }
    }

    /// A server-side failure (500).
    pub fn internal(e: impl std::fmt::Display) -> ApiError {
        ApiError {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            error: e.to_string(),
            field: None,
        }
    }

    /// 404 for an unknown id of a `what`.
    pub fn not_found(what: &str, id: &str) -> ApiError {
        ApiError::field(StatusCode::NOT_FOUND, "id", format!("no {what} '{id}'"))
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = ErrorBody {
            error: self.error,
            field: self.field,
        };
        (self.status, Json(body)).into_response()
    }
}

impl From<rusqlite::Error> for ApiError {
    fn from(e: rusqlite::Error) -> Self {
        ApiError::internal(format!("database: {e}"))
    }
}

impl From<crate::service::store::StoreError> for ApiError {
    fn from(e: crate::service::store::StoreError) -> Self {
        ApiError::internal(format!("database: {e}"))
    }
}

/// The result of a handler.
pub(crate) type ApiResult<T> = Result<T, ApiError>;

/// 400 about `field`.
pub(crate) fn bad(field: &str, msg: impl Into<String>) -> ApiError {
    ApiError::field(StatusCode::BAD_REQUEST, field, msg)
}

/// 422 for job settings out of range: `settings.<name>` (or `scene` for scene limits).
pub(crate) fn settings_error(e: FieldError) -> ApiError {
    let field = if e.field == "scene" {
        e.field
    } else {
        format!("settings.{}", e.field)
    };
    ApiError::field(StatusCode::UNPROCESSABLE_ENTITY, field, e.message)
}

/// Parses a JSON body, naming the field of the first problem (unknown fields included).
pub(crate) fn parse_json<T: serde::de::DeserializeOwned>(body: &[u8]) -> ApiResult<T> {
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

/// Counts errors, and turns the plain-text rejections of axum's extractors and router (bad path
/// or query parameters, wrong method, body too large) into our JSON error shape.
pub(crate) async fn json_errors(State(app): State<AppState>, req: Request, next: Next) -> Response {
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
    // Keep what the framework said besides the body (the `Allow` of a 405).
    let mut headers = r.headers().clone();
    headers.remove(header::CONTENT_TYPE);
    headers.remove(header::CONTENT_LENGTH);
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
    let mut out = ApiError::field(status, field, msg).into_response();
    out.headers_mut().extend(headers);
    out
}
