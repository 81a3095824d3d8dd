//! Reference images: EXRs uploaded with POST /v1/references, and the reference of a new job
//! (an upload, or the image of an earlier job that is done).

use super::errors::{ApiError, ApiResult, bad};
use super::{AppState, is_safe_id};
use crate::film::exr_io;
use crate::service::protocol::{JobState, ReferenceInfo, ReferenceSource};
use crate::service::{App, exr_header, store};
use axum::Json;
use axum::body::Bytes;
use axum::extract::State;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

/// POST /v1/references: an OpenEXR image.
pub(crate) async fn upload_reference(
    State(app): State<AppState>,
    body: Bytes,
) -> ApiResult<Response> {
    let id = uuid::Uuid::new_v4().to_string();
    let path = app.paths.reference(&id);
    let max = app.cfg.limits.max_resolution as usize;
    let img = tokio::task::spawn_blocking(move || {
        store::write_atomic(&path, &body).map_err(ApiError::internal)?;
        // The header first: a small file can claim (and hold, compressed) a huge frame. At
        // most an RGBA image at the largest resolution a job may have.
        let max_samples = 4 * (max as u64) * (max as u64);
        if let Err(e) = exr_header::check(&path, max, max_samples) {
            let _ = std::fs::remove_file(&path);
            let status = if e.starts_with("not a readable EXR") {
                StatusCode::BAD_REQUEST
            } else {
                StatusCode::UNPROCESSABLE_ENTITY
            };
            return Err(ApiError::field(
                status,
                "body",
                format!("the reference must be an OpenEXR image within the limits: {e}"),
            ));
        }
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
    let info = ReferenceInfo {
        id,
        width: img.width,
        height: img.height,
    };
    Ok((StatusCode::CREATED, Json(info)).into_response())
}

/// The path of a new job's reference image, checked to be `width` x `height`. Runs on a
/// blocking thread.
pub(crate) fn job_reference(
    app: &App,
    src: &ReferenceSource,
    width: u32,
    height: u32,
) -> ApiResult<String> {
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
            if j.state != JobState::Done {
                return Err(bad(
                    "reference.job",
                    format!("job '{id}' is {}, not done", j.state),
                ));
            }
            (app.paths.output(id, "image.exr"), "reference.job")
        }
    };
    let img =
        exr_io::read_exr(&path).map_err(|_| bad(field, "no such reference image".to_string()))?;
    if (img.width, img.height) != (width as usize, height as usize) {
        return Err(bad(
            field,
            format!(
                "the reference is {}x{}, the job renders {width}x{height}",
                img.width, img.height
            ),
        ));
    }
    Ok(path.display().to_string())
}
