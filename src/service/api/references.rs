//! Reference images: EXRs uploaded with POST /v1/references, and the reference of a new job
//! (an upload, or the image of an earlier job that is done).

use super::errors::{ApiError, ApiResult, bad};
use super::{AppState, is_safe_id};
use crate::film::image::exr_io;
use crate::protocol::{JobState, ReferenceInfo, ReferenceSource};
use crate::service::{App, exr_header, upload};
use axum::Json;
use axum::body::Body;
use axum::extract::State;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use std::path::Path;

/// POST /v1/references: an OpenEXR image, written to disk as it arrives, checked from its
/// headers and then block by block: its beauty must be finite.
pub(crate) async fn upload_reference(
    State(app): State<AppState>,
    body: Body,
) -> ApiResult<Response> {
    let id = uuid::Uuid::new_v4().to_string();
    let path = app.paths.reference(&id);
    if let Some(dir) = path.parent() {
        tokio::fs::create_dir_all(dir)
            .await
            .map_err(|e| ApiError::disk("cannot store the reference", e))?;
    }
    upload::body_to_file(body, &path, app.cfg.max_upload_bytes).await?;
    let _permit = app.validation().await?;
    let max = app.cfg.limits.max_resolution as usize;
    let p = path.clone();
    let checked = tokio::task::spawn_blocking(move || check_reference(&p, max))
        .await
        .map_err(ApiError::internal)?;
    let (width, height) = match checked {
        Ok(size) => size,
        Err(e) => {
            let _ = std::fs::remove_file(&path);
            return Err(e);
        }
    };
    let info = ReferenceInfo { id, width, height };
    Ok((StatusCode::CREATED, Json(info)).into_response())
}

/// Checks an uploaded reference: its headers first (a small file can claim, and hold
/// compressed, a huge frame: at most an RGBA image at the largest resolution a job may have),
/// then its beauty block by block, every value finite. Returns the beauty's size.
fn check_reference(path: &Path, max_resolution: usize) -> ApiResult<(usize, usize)> {
    let max_samples = 4 * (max_resolution as u64) * (max_resolution as u64);
    if let Err(e) = exr_header::check(path, max_resolution, max_samples) {
        let status = if matches!(e, exr_header::ExrHeaderError::Unreadable(_)) {
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
    let hide = |e: String| e.replace(&format!("{}: ", path.display()), "");
    let mut size = (0, 0);
    let mut non_finite = 0u64;
    exr_io::for_each_beauty_line(
        path,
        |w, h| {
            size = (w, h);
            Ok(())
        },
        |_, _, _, values| non_finite += values.iter().filter(|v| !v.is_finite()).count() as u64,
    )
    .map_err(|e| {
        bad(
            "body",
            format!(
                "the reference must be an OpenEXR image: {}",
                hide(e.to_string())
            ),
        )
    })?;
    if non_finite > 0 {
        return Err(ApiError::field(
            StatusCode::UNPROCESSABLE_ENTITY,
            "body",
            format!(
                "the reference's beauty ({}x{}) has {non_finite} values that are NaN or \
                 infinite: an error measured against it would mean nothing",
                size.0, size.1
            ),
        ));
    }
    Ok(size)
}

/// The path of a new job's reference image, checked (from its headers) to be `width` x
/// `height`. Runs on a blocking thread.
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
    let (w, h) = exr_io::beauty_size(&path)
        .map_err(|_| bad(field, "no such reference image".to_string()))?;
    if (w, h) != (width as usize, height as usize) {
        return Err(bad(
            field,
            format!("the reference is {w}x{h}, the job renders {width}x{height}"),
        ));
    }
    Ok(path.display().to_string())
}
