//! What becomes of an upload from a worker: a render task's result or a merge task's output,
//! checked, stored, recorded, and followed up (the job advanced, or the attempt counted as
//! failed). The HTTP handler (`api::workers::upload_result`) only reads the body and says what
//! became of it.

use super::error::{ServiceError, ServiceResult};
use super::runtime::{PassImages, resolved, runtime};
use super::store::{JobRow, Outcome, TaskRow};
use super::{App, Metrics, buffers::Pooled, jobs, merge};
use crate::film::format;
use crate::film::format::merge_stream::MergeOutput;
use crate::protocol::{JobEvent, TaskKind, TileDoneEvent};
use std::ops::Range;
use std::sync::Arc;

/// What became of an upload.
pub(crate) enum Accepted {
    /// Checked, recorded and stored.
    Yes,
    /// The attempt is no longer current (nothing recorded).
    Stale,
    /// The upload does not match its task (why); the attempt counts as failed.
    Invalid(String),
}

/// Judges the upload `body` of `worker` for `task` of `job` (its current attempt when the upload
/// was read): a render task's result or a merge task's output. At most `App::result_slots`
/// uploads are judged at once, so their working memory stays bounded.
pub(crate) async fn upload(
    app: &Arc<App>,
    task: TaskRow,
    job: JobRow,
    worker: String,
    body: Pooled,
) -> ServiceResult<Accepted> {
    let _slot = app
        .result_slots
        .acquire()
        .await
        .map_err(ServiceError::internal)?;
    match task.kind {
        TaskKind::Merge => merge_output(app, task, job, worker, body).await,
        TaskKind::Render => render_result(app, task, job, worker, body).await,
    }
}

/// A merge task's output: checked, recorded, its checkpoints written (`check_merge_output`);
/// then the job advances (the pass may be complete), or an invalid output counts as a failed
/// attempt.
async fn merge_output(
    app: &Arc<App>,
    task: TaskRow,
    job: JobRow,
    worker: String,
    body: Pooled,
) -> ServiceResult<Accepted> {
    let a = app.clone();
    let (t, w) = (task.clone(), worker.clone());
    let outcome = tokio::task::spawn_blocking(move || check_merge_output(&a, &job, &t, &w, &body))
        .await
        .map_err(ServiceError::internal)??;
    match &outcome {
        Accepted::Yes => {
            Metrics::add(&app.metrics.merges_accepted, 1);
            advance(app, &task.job_id);
        }
        Accepted::Stale => {}
        Accepted::Invalid(problem) => {
            let _ = jobs::task_failed(
                app,
                &task,
                &worker,
                &format!("invalid merge: {problem}"),
                Outcome::Refused,
            );
        }
    }
    Ok(outcome)
}

/// Checks merge task `task`'s output `body` from `worker`, records the task done, writes the
/// group's checkpoints into their slots (none on the job's last pass) and puts its images with
/// the pass's.
fn check_merge_output(
    app: &App,
    job: &JobRow,
    task: &TaskRow,
    worker: &str,
    body: &[u8],
) -> ServiceResult<Accepted> {
    let rt = runtime(app, job)?;
    let r = rt
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .resolved
        .clone();
    let grid = r.grid();
    let layout = r.film_layout();
    let passes = task.pass + 1;
    let out = match MergeOutput::decode(
        body,
        &grid,
        &layout,
        task.bands(),
        passes,
        merge::output_of(&r, task.pass),
    ) {
        Ok(o) => o,
        Err(e) => return Ok(Accepted::Invalid(e.to_string())),
    };
    // The runtime is held from the record to the images, so that the end of the pass (which
    // holds it too) sees the group either not done or done with its checkpoints written.
    let mut rt = rt.lock().unwrap_or_else(|e| e.into_inner());
    if !app.db().complete_merge(task.id, task.attempt, worker)? {
        return Ok(Accepted::Stale);
    }
    let tiles = grid.tiles_of_bands(task.bands().start as usize..task.bands().end as usize);
    for (t, ck) in tiles.zip(&out.checkpoints) {
        if let Err(e) = merge::write_slot(app, &job.id, &r, t, ck, passes) {
            // Recorded done without its checkpoints: the end of the pass finds the group's slots
            // without the pass and merges it again.
            tracing::error!("job {} tile {t}: {e}", job.id);
            return Ok(Accepted::Yes);
        }
    }
    let images = rt.images.get_or_insert_with(|| PassImages::new(task.pass));
    if images.pass == task.pass {
        images.blit(&r, std::slice::from_ref(&out.beauty));
        images.keep_blocks(out.first_block, &out.blocks);
        images.merged.insert(task.tile);
    }
    Ok(Accepted::Yes)
}

/// What the check of a render result found.
enum Checked {
    /// Valid, and stored at this byte range of its pass's result log.
    Stored(Range<u64>),
    /// Not the task's result (why).
    Invalid(String),
}

/// A render task's result: checked against its task and stored in its pass's result log as it
/// came (`check_and_store`); then the task, its `tile_done` event and whether it closed its
/// pass are recorded in one transaction, and the job advances when it did. An invalid result
/// counts as a failed attempt.
async fn render_result(
    app: &Arc<App>,
    task: TaskRow,
    job: JobRow,
    worker: String,
    body: Pooled,
) -> ServiceResult<Accepted> {
    let n = body.len();
    let (a, t) = (app.clone(), task.clone());
    let checked = tokio::task::spawn_blocking(move || check_and_store(&a, &job, &t, &body))
        .await
        .map_err(ServiceError::internal)??;
    let stored = match checked {
        Checked::Stored(stored) => stored,
        Checked::Invalid(problem) => {
            let _ = jobs::task_failed(
                app,
                &task,
                &worker,
                &format!("invalid result: {problem}"),
                Outcome::Refused,
            );
            return Ok(Accepted::Invalid(problem));
        }
    };
    let event = JobEvent::TileDone(TileDoneEvent {
        pass: task.pass,
        tile: task.tile,
        worker: worker.clone(),
        bytes: n as u64,
    });
    let completed = {
        let db = app.db();
        let c = db.complete(&task, &worker, n, stored, (event.kind(), &event.data()))?;
        if let Some(c) = &c {
            app.publish(&db, c.event.clone());
        }
        c
    };
    let Some(completed) = completed else {
        // Its record stays in the log, which nothing points to; the log goes with its pass.
        return Ok(Accepted::Stale);
    };
    Metrics::add(&app.metrics.results_accepted, 1);
    Metrics::add(&app.metrics.result_bytes, n as u64);
    // Only the result that closes its pass can start a merge: whoever completes a pass's last
    // task sees it closed (its own completion is committed before it looks), so the others
    // need not advance the job.
    if !completed.pass_open {
        advance(app, &task.job_id);
    }
    Ok(Accepted::Yes)
}

/// Checks render task `task`'s result `body` (laid out by band, `format::encode_banded`, as the
/// result log keeps it, so that a merge task reads each band's part alone) against its task,
/// and stores it in its pass's result log as it came.
fn check_and_store(app: &App, job: &JobRow, task: &TaskRow, body: &[u8]) -> ServiceResult<Checked> {
    let r = resolved(app, job)?;
    let layout = r.film_layout();
    let tile = jobs::tile_rect(&r, task.tile);
    let index = match format::check_banded(body, &r.grid(), &layout, app.cfg.max_upload_bytes) {
        Err(e) => return Ok(Checked::Invalid(e.to_string())),
        Ok(x) => x,
    };
    if Some(index.tile) != tile || index.samples != (task.s0..task.s1) {
        return Ok(Checked::Invalid(format!(
            "result is for tile {:?} samples {:?}, the task is tile {tile:?} samples {}..{}",
            index.tile, index.samples, task.s0, task.s1
        )));
    }
    let stored = app
        .result_logs
        .write(
            &app.paths,
            &task.job_id,
            task.pass,
            merge::held(&r, job.passes_done),
            body,
        )
        .map_err(|source| ServiceError::Disk {
            what: "cannot store the result",
            source,
        })?;
    Ok(Checked::Stored(stored))
}

/// Advances job `id` on a blocking thread (`jobs::advance`), not waited for.
fn advance(app: &Arc<App>, id: &str) {
    let (a, id) = (app.clone(), id.to_string());
    tokio::task::spawn_blocking(move || jobs::advance(&a, &id));
}
