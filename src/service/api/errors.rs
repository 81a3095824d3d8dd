//! Errors of the API: `ApiError` and its JSON body `{"error": "...", "field": "..."}`; the one
//! place where the coordinator's errors (`ServiceError`, `StoreError`, upload and body errors)
//! become a status and a body; the parsing of JSON bodies that names the field of the first
//! problem; and the middleware that turns the framework's own plain-text rejections into the
//! same JSON shape.

use super::AppState;
use crate::job::FieldError;
use crate::protocol::ErrorBody;
use crate::service::Metrics;
use crate::service::buffers::{BodyError, read_body};
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

    /// A failure of the coordinator's disk while doing `what`: 507 when its storage is full,
    /// else 500; both are the server's fault, logged with their cause (`json_errors`).
    pub fn disk(what: &str, e: std::io::Error) -> ApiError {
        if is_disk_full(&e) {
            ApiError {
                status: StatusCode::INSUFFICIENT_STORAGE,
                error: format!("{what}: the coordinator's storage is full ({e})"),
                field: None,
            }
        } else {
            ApiError::internal(format!("{what}: {e}"))
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

impl From<crate::service::store::StoreError> for ApiError {
    fn from(e: crate::service::store::StoreError) -> Self {
        if e.disk_full {
            ApiError {
                status: StatusCode::INSUFFICIENT_STORAGE,
                error: format!("database: the coordinator's storage is full ({e})"),
                field: None,
            }
        } else {
            ApiError::internal(format!("database: {e}"))
        }
    }
}

impl From<crate::service::error::ServiceError> for ApiError {
    /// The store's errors as the store's (507 when its storage is full), the disk's as the
    /// disk's (507 or 500); everything else is the server's fault: 500 with its message.
    fn from(e: crate::service::error::ServiceError) -> Self {
        use crate::service::error::ServiceError as S;
        match e {
            S::Store(e) => e.into(),
            S::Disk { what, source } => ApiError::disk(what, source),
            e @ (S::Io(_) | S::Job(_) | S::RenderedAgain(_) | S::Internal(_)) => {
                ApiError::internal(e)
            }
        }
    }
}

/// Whether `e` says the storage is full: no space left, the quota reached, or the largest file
/// the process may write (RLIMIT_FSIZE) reached.
pub(crate) fn is_disk_full(e: &std::io::Error) -> bool {
    use std::io::ErrorKind as K;
    matches!(
        e.kind(),
        K::StorageFull | K::QuotaExceeded | K::FileTooLarge
    ) || matches!(
        e.raw_os_error(),
        Some(libc::ENOSPC | libc::EDQUOT | libc::EFBIG)
    )
}

impl From<crate::service::upload::UploadError> for ApiError {
    fn from(e: crate::service::upload::UploadError) -> Self {
        use crate::service::upload::UploadError as U;
        match e {
            U::TooLarge(m) => ApiError::field(StatusCode::PAYLOAD_TOO_LARGE, "body", m),
            U::Read(m) => ApiError::field(StatusCode::BAD_REQUEST, "body", m),
            U::Disk(e) => ApiError::disk("cannot store the upload", e),
        }
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

/// Parses a JSON body, naming the field of the first problem (unknown fields included); anything
/// but whitespace after the value is refused.
pub(crate) fn parse_json<T: serde::de::DeserializeOwned>(body: &[u8]) -> ApiResult<T> {
    let de = &mut serde_json::Deserializer::from_slice(body);
    let value = serde_path_to_error::deserialize(&mut *de).map_err(|e| {
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
    })?;
    de.end().map_err(|e| {
        bad(
            "body",
            format!("invalid JSON: bytes after the JSON value ({e})"),
        )
    })?;
    Ok(value)
}

/// A JSON request body: `Content-Type: application/json` (415 otherwise), at most
/// `Config::max_json_bytes` long (413), parsed whole by [`parse_json`].
pub(crate) struct JsonBody<T>(pub T);

impl<T: serde::de::DeserializeOwned> axum::extract::FromRequest<AppState> for JsonBody<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, app: &AppState) -> Result<Self, ApiError> {
        require_json(req.headers())?;
        // Not from the pool of reused buffers: a JSON body is parsed once and its memory given
        // back at once, rather than kept resident for a next upload.
        let once = std::sync::Arc::new(crate::service::buffers::Buffers::new(0));
        let body = read_body(req.into_body(), app.cfg.max_json_bytes, &once).await?;
        parse_json(&body).map(JsonBody)
    }
}

/// 415 unless the request says its body is JSON (`application/json` or a `+json` type, with any
/// parameters).
pub(crate) fn require_json(headers: &axum::http::HeaderMap) -> ApiResult<()> {
    let ct = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let mime = ct
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    if mime == "application/json" || (mime.starts_with("application/") && mime.ends_with("+json")) {
        return Ok(());
    }
    Err(ApiError::field(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "Content-Type",
        if ct.is_empty() {
            "missing Content-Type; the body must be JSON (Content-Type: application/json)"
                .to_string()
        } else {
            format!("Content-Type '{ct}'; the body must be JSON (Content-Type: application/json)")
        },
    ))
}

impl From<BodyError> for ApiError {
    /// 413 over the limit, 400 for a body the connection cut or sent too slowly
    /// (`service::server`).
    fn from(e: BodyError) -> Self {
        match e {
            BodyError::TooLarge(m) => ApiError::field(StatusCode::PAYLOAD_TOO_LARGE, "body", m),
            BodyError::Read(m) => ApiError::field(StatusCode::BAD_REQUEST, "body", m),
        }
    }
}

/// Counts errors, and turns the plain-text rejections of axum's extractors and router (bad path
/// or query parameters, wrong method, body too large) into our JSON error shape.
pub(crate) async fn json_errors(State(app): State<AppState>, req: Request, next: Next) -> Response {
    let route = format!("{} {}", req.method(), req.uri().path());
    let has_body = req.headers().contains_key(header::TRANSFER_ENCODING)
        || req
            .headers()
            .get(header::CONTENT_LENGTH)
            .is_some_and(|v| v.as_bytes() != b"0");
    let mut r = next.run(req).await;
    let status = r.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return r;
    }
    // A body refused before it was read whole leaves the connection in the middle of it: the
    // client must not send its next request there.
    if has_body {
        r.headers_mut().insert(
            header::CONNECTION,
            header::HeaderValue::from_static("close"),
        );
    }
    Metrics::add(&app.metrics.http_errors, 1);
    let is_json = r
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if is_json && status.is_server_error() && status != StatusCode::SERVICE_UNAVAILABLE {
        // The server's own faults are logged with their cause (the body says it).
        let (parts, body) = r.into_parts();
        let bytes = axum::body::to_bytes(body, 64 << 10)
            .await
            .unwrap_or_default();
        tracing::error!("{route}: {status}: {}", String::from_utf8_lossy(&bytes));
        return Response::from_parts(parts, axum::body::Body::from(bytes));
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A full disk, a quota or the file-size limit is 507; any other failure of the disk 500.
    #[test]
    fn a_full_disk_is_507_and_other_disk_errors_500() {
        for code in [libc::ENOSPC, libc::EDQUOT, libc::EFBIG] {
            let e = ApiError::disk("x", std::io::Error::from_raw_os_error(code));
            assert_eq!(e.status, StatusCode::INSUFFICIENT_STORAGE, "{code}");
            assert!(e.error.contains("storage is full"), "{}", e.error);
        }
        let e = ApiError::disk("x", std::io::Error::from_raw_os_error(libc::EIO));
        assert_eq!(e.status, StatusCode::INTERNAL_SERVER_ERROR);
    }

    /// A service error becomes the status its cause calls for, with its message in the body: a
    /// full store or disk 507, anything else 500.
    #[test]
    fn service_errors_map_to_their_status_and_message() {
        use crate::service::error::ServiceError;
        use crate::service::store::StoreError;
        let full = StoreError {
            message: "database or disk is full".into(),
            disk_full: true,
        };
        let e = ApiError::from(ServiceError::from(full));
        assert_eq!(e.status, StatusCode::INSUFFICIENT_STORAGE);
        assert!(e.error.starts_with("database: "), "{}", e.error);
        let e = ApiError::from(ServiceError::from(StoreError::new("locked")));
        assert_eq!(
            (e.status, e.error.as_str()),
            (StatusCode::INTERNAL_SERVER_ERROR, "database: locked")
        );
        let e = ApiError::from(ServiceError::Disk {
            what: "cannot store the result",
            source: std::io::Error::from_raw_os_error(libc::ENOSPC),
        });
        assert_eq!(e.status, StatusCode::INSUFFICIENT_STORAGE);
        assert!(
            e.error.starts_with("cannot store the result: "),
            "{}",
            e.error
        );
        let e = ApiError::from(ServiceError::job("job j: bad settings: x"));
        assert_eq!(
            (e.status, e.error.as_str(), e.field),
            (
                StatusCode::INTERNAL_SERVER_ERROR,
                "job j: bad settings: x",
                None
            )
        );
    }
}
