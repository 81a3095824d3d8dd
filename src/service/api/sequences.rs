//! Sequences through the API: a job of many frames (a bundle whose main file is a frame
//! pattern, and a frame range) is created as a parent job and one ordinary job per frame, its
//! children; its status sums its frames' and lists them; its images are its frames'.

use super::errors::{ApiError, ApiResult, bad, settings_error};
use super::scenes;
use crate::job::frames::{self, FrameRange};
use crate::protocol::{
    FrameStatus, JobEvent, JobRequest, JobState, JobStatus, QueuedEvent, SceneSource,
};
use crate::scene::Scene;
use crate::service::store::{self, JobRow};
use crate::service::{App, jobs};
use axum::http::StatusCode;

/// Whether `req` asks for a sequence: frames given, or a bundle whose main file is a frame
/// pattern (which then needs them).
pub(super) fn is_sequence_request(app: &App, req: &JobRequest) -> bool {
    req.frames.is_some()
        || matches!(&req.scene, SceneSource::Bundle(id)
            if scenes::scene_meta(app, id).is_some_and(|m| frames::is_pattern(&m.main)))
}

/// Creates sequence `req`: every frame's scene file must be in the bundle; each frame's scene is
/// loaded and the settings resolved against it, as for a single job, before anything is
/// recorded; then the parent and its frames are recorded at once. Returns the parent and the
/// frames' ids. Runs on a blocking thread.
/// `owner` and `hooks` are the sequence's; its frames share its owner, priority and required
/// tags (so that they lease and are controlled as it is), and only the sequence's own end is
/// notified.
pub(super) fn create_sequence(
    app: &App,
    req: &JobRequest,
    owner: Option<&str>,
    hooks: Option<&str>,
) -> ApiResult<(JobRow, Vec<String>)> {
    let SceneSource::Bundle(bundle) = &req.scene else {
        return Err(bad(
            "frames",
            "a sequence's scene is an uploaded bundle (POST /v1/scenes) whose main file is a \
             frame pattern (frame_####.xml)",
        ));
    };
    let meta = scenes::scene_meta(app, bundle)
        .ok_or_else(|| bad("scene.bundle", format!("no scene bundle '{bundle}'")))?;
    let Some(range) = req.frames else {
        return Err(bad(
            "frames",
            format!(
                "the bundle's main file '{}' is a frame pattern: give the frames to render \
                 (\"frames\": \"1-100\")",
                meta.main
            ),
        ));
    };
    range.validate().map_err(|e| bad("frames", e.message))?;
    if !frames::is_pattern(&meta.main) {
        return Err(bad(
            "frames",
            format!(
                "the bundle's main file '{}' is not a frame pattern; upload the bundle with \
                 main=frame_####.xml (a run of '#' where the frame number goes)",
                meta.main
            ),
        ));
    }
    if req.reference.is_some() {
        return Err(bad("reference", "a sequence takes no reference image"));
    }
    let files: Vec<(u32, String)> = range
        .frames()
        .map(|f| {
            let file = frames::frame_file(&meta.main, f)
                .ok_or_else(|| bad("scene.bundle", format!("'{}' is no pattern", meta.main)))?;
            if !meta.files.contains(&file) {
                return Err(bad(
                    "frames",
                    format!("frame {f}: its scene file '{file}' is not in the bundle"),
                ));
            }
            Ok((f, file))
        })
        .collect::<ApiResult<_>>()?;
    let dir = app.paths.scene(bundle).join("files");
    let settings = serde_json::to_string(&req.settings).map_err(ApiError::internal)?;
    let mut children = Vec::with_capacity(files.len());
    for (frame, file) in &files {
        let mut scene = Scene::load_with(&dir.join(file), &req.settings.defines).map_err(|e| {
            bad(
                "frames",
                format!(
                    "frame {frame} ({file}): {}",
                    scenes::hide_folder(&e.to_string(), &dir)
                ),
            )
        })?;
        if scene.stats.triangles > app.cfg.limits.max_triangles {
            return Err(bad(
                "frames",
                format!(
                    "frame {frame} ({file}): {} triangles exceed the limit of {}",
                    scene.stats.triangles, app.cfg.limits.max_triangles
                ),
            ));
        }
        let resolved = req
            .settings
            .resolve(&mut scene, &app.cfg.limits)
            .map_err(settings_error)?;
        let accum = resolved.film_layout().bytes_per_pixel() as i64
            * resolved.width as i64
            * resolved.height as i64;
        children.push(Frame {
            frame: *frame,
            id: uuid::Uuid::new_v4().to_string(),
            file: file.clone(),
            queued: QueuedEvent {
                width: resolved.width,
                height: resolved.height,
                spp: resolved.spp,
            },
            resolved: serde_json::to_string(&resolved).map_err(ApiError::internal)?,
            accum,
        });
    }
    let first = children
        .first()
        .ok_or_else(|| bad("frames", "the range holds no frame"))?;
    let id = uuid::Uuid::new_v4().to_string();
    for job in std::iter::once(&id).chain(children.iter().map(|c| &c.id)) {
        std::fs::create_dir_all(app.paths.job(job))
            .map_err(|e| ApiError::disk("cannot make the job's folder", e))?;
    }
    let names: Vec<Option<String>> = children
        .iter()
        .map(|c| req.name.as_ref().map(|n| format!("{n} frame {}", c.frame)))
        .collect();
    let child_rows: Vec<(u32, store::NewJob)> = children
        .iter()
        .zip(&names)
        .map(|(c, name)| {
            (
                c.frame,
                store::NewJob {
                    id: &c.id,
                    name: name.as_deref(),
                    settings: &settings,
                    resolved: &c.resolved,
                    scene_id: &meta.id,
                    scene_main: &c.file,
                    reference: None,
                    accum_bytes: c.accum,
                    priority: req.priority,
                    retry_of: None,
                    require_tags: &req.require_tags,
                    owner,
                    webhooks: None,
                },
            )
        })
        .collect();
    app.db().insert_sequence(
        &store::NewJob {
            id: &id,
            name: req.name.as_deref(),
            settings: &settings,
            // The first frame's: what the parent's status reads its size and settings from.
            resolved: &first.resolved,
            scene_id: &meta.id,
            scene_main: &meta.main,
            reference: None,
            accum_bytes: children.iter().map(|c| c.accum).sum(),
            priority: req.priority,
            retry_of: None,
            require_tags: &req.require_tags,
            owner,
            webhooks: hooks,
        },
        &range.to_string(),
        &child_rows,
    )?;
    app.event(&id, JobEvent::Queued(first.queued.clone()));
    for c in &children {
        app.event(&c.id, JobEvent::Queued(c.queued.clone()));
    }
    let job = app
        .db()
        .job(&id)?
        .ok_or_else(|| ApiError::internal("job vanished"))?;
    Ok((job, children.into_iter().map(|c| c.id).collect()))
}

/// A frame of a sequence being created.
struct Frame {
    frame: u32,
    id: String,
    file: String,
    queued: QueuedEvent,
    resolved: String,
    accum: i64,
}

/// The frame range of sequence `job`.
fn range_of(job: &JobRow) -> ApiResult<FrameRange> {
    job.frames
        .as_deref()
        .unwrap_or_default()
        .parse()
        .map_err(|e| ApiError::internal(format!("job {}: bad frame range: {e}", job.id)))
}

/// The job whose images `GET /v1/jobs/{id}/image.exr?frame=N` serves: frame `N`'s of a
/// sequence (which needs it: 400 without it), the job itself otherwise (404 with one).
pub(super) fn image_job(app: &App, job: JobRow, frame: Option<u32>) -> ApiResult<JobRow> {
    if !job.is_sequence() {
        return match frame {
            None => Ok(job),
            Some(f) => Err(no_frame(format!(
                "job '{}' is a single frame, not a sequence: it has no frame {f}",
                job.id
            ))),
        };
    }
    let range = range_of(&job)?;
    let Some(frame) = frame else {
        return Err(bad(
            "frame",
            format!(
                "job '{}' is a sequence of frames {range}: ask for one with ?frame=N",
                job.id
            ),
        ));
    };
    if !range.contains(frame) {
        return Err(no_frame(format!(
            "frame {frame} is not one of the sequence's frames ({range})"
        )));
    }
    app.db()
        .frames(&job.id)?
        .into_iter()
        .find(|f| f.frame == Some(frame))
        .ok_or_else(|| no_frame(format!("frame {frame} of job '{}' is gone", job.id)))
}

/// 404 naming `frame`: the job has no such frame (a well-formed request for a resource that
/// does not exist).
fn no_frame(message: String) -> ApiError {
    ApiError::field(StatusCode::NOT_FOUND, "frame", message)
}

/// Fills the status `st` of sequence `job` from its frames' statuses (`frame_status` of each):
/// the counts summed over the frames, the time left from the frames' progress together, and
/// the list of frames.
pub(super) fn fill_status(
    app: &App,
    job: &JobRow,
    st: &mut JobStatus,
    frame_status: impl Fn(&JobRow) -> ApiResult<JobStatus>,
) -> ApiResult<()> {
    let rows = app.db().frames(&job.id)?;
    let frames: Vec<JobStatus> = rows.iter().map(frame_status).collect::<ApiResult<_>>()?;
    let sum = |f: fn(&JobStatus) -> i64| frames.iter().map(f).sum::<i64>();
    let sum32 = |f: fn(&JobStatus) -> u32| frames.iter().map(f).fold(0u32, u32::saturating_add);
    let all = |f: fn(&JobStatus) -> Option<u32>| {
        frames
            .iter()
            .map(f)
            .try_fold(0u32, |a, b| b.map(|b| a.saturating_add(b)))
    };
    st.spp_target = all(|f| f.spp_target);
    st.spp_done = sum32(|f| f.spp_done);
    st.passes_done = sum32(|f| f.passes_done);
    st.passes_total = all(|f| f.passes_total);
    st.tiles_per_pass = sum32(|f| f.tiles_per_pass);
    st.tiles_done = sum32(|f| f.tiles_done);
    st.accum_bytes = sum(|f| f.accum_bytes);
    st.result_bytes = sum(|f| f.result_bytes);
    st.samples = sum(|f| f.samples);
    st.rays = sum(|f| f.rays);
    st.non_finite_samples = sum(|f| f.non_finite_samples);
    st.series = Vec::new();
    st.relmse = None;
    st.eta_s = if job.state.is_active() {
        // Frames render one after the other: the time left is the sum of theirs, a frame not
        // begun taking as long as the mean of those done.
        let done: Vec<f64> = frames
            .iter()
            .filter(|f| !f.state.is_active())
            .map(|f| f.elapsed_s)
            .collect();
        let mean = (!done.is_empty()).then(|| done.iter().sum::<f64>() / done.len() as f64);
        frames
            .iter()
            .filter(|f| f.state.is_active())
            .map(|f| match f.started_at {
                Some(_) => f.eta_s,
                None => mean,
            })
            .sum::<Option<f64>>()
    } else {
        Some(0.0)
    };
    st.frames = Some(
        frames
            .iter()
            .zip(&rows)
            .map(|(f, row)| FrameStatus {
                frame: row.frame.unwrap_or_default(),
                job_id: f.id.clone(),
                state: f.state,
                spp_done: f.spp_done,
                passes_done: f.passes_done,
                error: f.error.clone(),
                elapsed_s: f.elapsed_s,
            })
            .collect(),
    );
    // Stored as it ends or is paused; while it runs, its frames say whether one has begun.
    if job.state.is_active() && job.state != JobState::Paused {
        st.state = jobs::sequence_state(&rows);
    }
    Ok(())
}
