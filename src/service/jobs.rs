//! Job life cycle in the coordinator: tasks pass by pass, the advance from a finished pass to
//! its merge (by merge tasks, `merge`) and to the next pass, failures and cancellation,
//! recovery after a restart, and expiry of silent leases. It drives `merge`; `merge` never calls
//! back: a step that cannot go on returns its error, and `advance` fails the job with it.

use super::error::{ServiceError, ServiceResult};
use super::runtime::{Runtime, drop_runtime, resolved_of, runtime};
use super::store::{self, JobRow, TaskRow};
use super::{App, merge};
use crate::film::Tile;
use crate::film::image::plot;
use crate::job::Resolved;
use crate::protocol::{
    CancelledEvent, DoneEvent, FailedEvent, JobEvent, JobState, SeriesPoint, TaskFailedEvent,
    TaskKind, TaskState,
};
use std::ops::Range;
use std::sync::Arc;
use std::sync::atomic::Ordering;

/// A task that failed on this many attempts fails its job.
pub(crate) const MAX_FAILURES: u32 = 3;

/// Tasks created per SQLite transaction: the store's lock is never held long, whatever the size
/// of the frame.
const TASK_CHUNK: u32 = 2048;

/// Tiles of a frame (the length of `r.tiles()`, without making the list).
pub(crate) fn tile_count(r: &Resolved) -> u32 {
    r.grid().len().min(u32::MAX as usize) as u32
}

/// Tile `i` of `r.tiles()` (row-major), computed directly.
pub(crate) fn tile_rect(r: &Resolved, i: u32) -> Option<Tile> {
    let g = r.grid();
    ((i as usize) < g.len()).then(|| g.tile(i as usize))
}

/// Samples per pixel a job has rendered: its merged passes, and the finished tiles of the
/// passes since pro rata, at the length of the next pass to merge (`tiles_done`: the done render
/// tasks of its unmerged passes).
pub(crate) fn progress_spp(job: &JobRow, r: &Resolved, tiles_done: u32) -> f64 {
    job.spp_done as f64
        + tiles_done as f64 / tile_count(r).max(1) as f64 * r.pass_len(job.passes_done) as f64
}

/// The samples of pass `p`, none of whose tasks exist yet: a time-budget job's pass is fitted to
/// the time left at the job's rate so far (`Resolved::fit_to_budget`), and the settings it
/// fitted are stored before any task of the pass exists (so a restart reads them back). None:
/// no such pass.
fn plan_pass(
    app: &App,
    job: &JobRow,
    r: &mut Resolved,
    p: u32,
) -> store::StoreResult<Option<Range<u32>>> {
    let (Some(_), Some(_)) = (r.time_budget_s, job.started_at) else {
        return Ok(r.pass_range(p));
    };
    let done = progress_spp(job, r, app.db().tasks_done(&job.id)?);
    // The budget is of rendering time: the time the job spent paused is left out.
    let elapsed = job.render_seconds(store::now());
    // The rate between the last two merges where two passes are merged: the passes overlap
    // (two are queued at a time), so the merges come as fast as the workers render and merge,
    // and the last pass is the longest, its fixed costs the least per sample. Before that, the
    // rate since the start, which counts the start-up and the tiles in hand as time without
    // samples: slower than the workers are (the job ends early, not late).
    let series = app.db().series(&job.id)?;
    let last_two = series
        .len()
        .checked_sub(2)
        .map(|i| (&series[i], &series[i + 1]));
    let seconds_per_spp = match last_two {
        Some((a, b)) if b.spp > a.spp && b.seconds > a.seconds => {
            (b.seconds - a.seconds) / (b.spp - a.spp) as f64
        }
        _ => elapsed / done,
    };
    let mut fitted = r.clone();
    let range = fitted.fit_to_budget(p, elapsed, done, seconds_per_spp);
    if fitted != *r {
        let json =
            serde_json::to_string(&fitted).map_err(|e| store::StoreError::new(e.to_string()))?;
        if !app.db().set_job_resolved(&job.id, &json)? {
            return Ok(None);
        }
        *r = fitted;
    }
    Ok(range)
}

/// Makes sure the job's next two passes (`passes_done` and the one after) have their tasks, so
/// workers never wait on a merge; a time-budget job's next pass is fitted to the time it has
/// left, or not begun (`plan_pass`). Tasks are created in chunks of `TASK_CHUNK`, each its own
/// transaction, the store unlocked in between and workers woken after each; it stops early when
/// the job ends or the coordinator stops. Idempotent: called at creation, after every merge and
/// after a restart.
pub(crate) fn ensure_passes(app: &App, job: &JobRow, r: &mut Resolved) -> store::StoreResult<()> {
    let tiles = tile_count(r);
    for p in job.passes_done..job.passes_done + 2 {
        // The store's guard must be gone before `plan_pass` locks it again.
        let last = app.db().last_tile(&job.id, p)?;
        let (mut next, range) = match last {
            Some(last) => (last + 1, r.pass_range(p)),
            // No fit is stored for a pass that a stopping coordinator would not begin.
            None if app.stopping.load(Ordering::Relaxed) => return Ok(()),
            None => (0, plan_pass(app, job, r, p)?),
        };
        let Some(range) = range else {
            continue;
        };
        while next < tiles {
            if app.stopping.load(Ordering::Relaxed) {
                return Ok(());
            }
            let end = next.saturating_add(TASK_CHUNK).min(tiles);
            {
                let db = app.db();
                if !db.job(&job.id)?.is_some_and(|j| j.state.is_active()) {
                    return Ok(());
                }
                db.create_tasks(&job.id, p, next..end, range.clone())?;
            }
            app.work.notify_waiters();
            next = end;
        }
    }
    Ok(())
}

/// Fails job `id` with `error` (when it is still active) and forgets its runtime.
pub(crate) fn fail_job(app: &App, id: &str, error: &str) {
    tracing::error!("job {id}: {error}");
    // The store's guard must be gone before `event` locks it again.
    let failed = app.db().set_job_state(id, JobState::Failed, Some(error));
    if let Ok(true) = failed {
        app.event(
            id,
            JobEvent::Failed(FailedEvent {
                error: error.to_string(),
            }),
        );
        // Its result logs stay: a requeue goes on from them (deleting the job removes them).
        app.result_logs.forget(id);
        frame_ended(app, id);
    }
    drop_runtime(app, id);
}

/// Merges every finished pass of a job, in order (by merge tasks: `merge`), and finishes the
/// job after its last one.
/// Runs on a blocking thread; one advance per job at a time: a call while one runs only asks it
/// to look again, so a burst of results never parks a thread per result. A job that recovery
/// has not reconciled yet is left to recovery.
pub(crate) fn advance(app: &App, id: &str) {
    if app.is_recovering(id) {
        return;
    }
    {
        let mut running = app.advancing.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(again) = running.get_mut(id) {
            *again = true;
            return;
        }
        running.insert(id.to_string(), false);
    }
    loop {
        if let Err(e) = advance_inner(app, id) {
            fail_job(app, id, &e.to_string());
        }
        let mut running = app.advancing.lock().unwrap_or_else(|e| e.into_inner());
        match running.get_mut(id) {
            Some(again) if *again => *again = false,
            _ => {
                running.remove(id);
                return;
            }
        }
    }
}

/// Gives the memory a merge freed back to the system (glibc keeps freed blocks of every
/// thread's arena otherwise, and the merge threads are new each pass).
fn trim_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free memory to the system.
    unsafe {
        libc::malloc_trim(0);
    }
}

fn advance_inner(app: &App, id: &str) -> ServiceResult<()> {
    let Some(job) = app.db().job(id)? else {
        return Ok(());
    };
    if !job.state.is_active() {
        return Ok(());
    }
    if job.is_sequence() {
        // Its frames do the work; it ends with them (after a restart too).
        settle_sequence(app, &job)?;
        return Ok(());
    }
    let rt = runtime(app, &job)?;
    let mut rt = rt.lock().unwrap_or_else(|e| e.into_inner());
    loop {
        let Some(job) = app.db().job(id)? else {
            return Ok(());
        };
        if !job.state.is_active() {
            drop_runtime(app, id);
            return Ok(());
        }
        ensure_passes(app, &job, &mut rt.resolved)?;
        app.work.notify_waiters();
        let pass = job.passes_done;
        let (last, open) = {
            let db = app.db();
            let last = db.last_tile(id, pass)?;
            (last, db.pass_open(id, pass)?)
        };
        let complete = last.is_some_and(|l| l + 1 >= tile_count(&rt.resolved));
        if !complete || open {
            if last.is_none() && finished_all(app, &job)? {
                finish(app, &job, &mut rt)?;
                drop_runtime(app, id);
            }
            return Ok(());
        }
        // Every render task of the pass is done: its merge tasks are queued, or in hand, or
        // done.
        let merges = app.db().merge_tasks(id, pass)?;
        if merges.is_empty() {
            return merge::begin(app, &job, &mut rt, pass);
        }
        if merges.iter().any(|m| m.state != TaskState::Done) {
            return Ok(());
        }
        if !merge::finish_pass(app, &job, &mut rt, pass, &merges)? {
            return Ok(());
        }
        trim_memory();
    }
}

/// True when no task of the job is left after its merged passes.
fn finished_all(app: &App, job: &JobRow) -> ServiceResult<bool> {
    let last = app.db().last_pass(&job.id)?;
    Ok(last.is_none_or(|l| l < job.passes_done))
}

fn finish(app: &App, job: &JobRow, rt: &mut Runtime) -> ServiceResult<()> {
    if !rt.final_written && !merge::final_in_exr(&rt.resolved, job.passes_done) {
        merge::write_final(app, job, rt)?;
        trim_memory();
    }
    let ended = app.db().set_job_state(&job.id, JobState::Done, None)?;
    if ended {
        let _ = std::fs::remove_dir_all(app.paths.tiles_dir(&job.id));
        app.result_logs.remove(&app.paths, &job.id);
        app.event(&job.id, JobEvent::Done(DoneEvent { spp: job.spp_done }));
        frame_ended(app, &job.id);
    }
    Ok(())
}

/// After job `id` ended: when it is a frame of a sequence, the sequence ends once its last
/// frame has.
fn frame_ended(app: &App, id: &str) {
    // Each guard of the store is gone before the next call locks it again.
    let job = app.db().job(id);
    let Ok(Some(JobRow {
        parent_id: Some(parent),
        ..
    })) = job
    else {
        return;
    };
    let sequence = app.db().job(&parent);
    let settled = match sequence {
        Ok(Some(p)) => settle_sequence(app, &p),
        Ok(None) => Ok(()),
        Err(e) => Err(e.into()),
    };
    if let Err(e) = settled {
        tracing::error!("sequence {parent}: {e}");
    }
}

/// The state a sequence takes from its frames: active while any frame is, else failed if one
/// failed, else cancelled if one was, else done.
pub(crate) fn sequence_state(frames: &[JobRow]) -> JobState {
    if frames.iter().any(|f| f.state.is_active()) {
        if frames.iter().any(|f| f.started_at.is_some()) {
            JobState::Running
        } else {
            JobState::Queued
        }
    } else if frames.iter().any(|f| f.state == JobState::Failed) {
        JobState::Failed
    } else if frames.iter().any(|f| f.state == JobState::Cancelled) {
        JobState::Cancelled
    } else {
        JobState::Done
    }
}

/// Ends active sequence `job` once none of its frames is active, in the state its frames give
/// it (`sequence_state`), with its event.
fn settle_sequence(app: &App, job: &JobRow) -> ServiceResult<()> {
    let frames = app.db().frames(&job.id)?;
    let state = sequence_state(&frames);
    if state.is_active() {
        return Ok(());
    }
    let failed: Vec<String> = frames
        .iter()
        .filter(|f| f.state == JobState::Failed)
        .map(|f| {
            format!(
                "frame {}: {}",
                f.frame.unwrap_or_default(),
                f.error.as_deref().unwrap_or("failed")
            )
        })
        .collect();
    let error = (!failed.is_empty()).then(|| failed.join("; "));
    let ended = app.db().set_job_state(&job.id, state, error.as_deref())?;
    if ended {
        let spp = frames.iter().map(|f| f.spp_done).min().unwrap_or(0);
        app.event(
            &job.id,
            match state {
                JobState::Failed => JobEvent::Failed(FailedEvent {
                    error: error.unwrap_or_default(),
                }),
                JobState::Cancelled => JobEvent::Cancelled(CancelledEvent {}),
                _ => JobEvent::Done(DoneEvent { spp }),
            },
        );
    }
    Ok(())
}

/// Records a failed attempt (`outcome`: failed, or its result refused); after `MAX_FAILURES` failed or lost attempts the job fails with
/// the worker's error. False when the attempt was not current.
pub(crate) fn task_failed(
    app: &App,
    task: &TaskRow,
    worker: &str,
    error: &str,
    outcome: store::Outcome,
) -> ServiceResult<bool> {
    let failure = app
        .db()
        .fail(task.id, task.attempt, worker, error, outcome)?;
    match failure {
        Some(f) => {
            after_failure(app, &f);
            Ok(true)
        }
        None => Ok(false),
    }
}

/// What follows a failed or lost attempt (recorded by the store): its event, and the job's
/// failure once the task has failed `MAX_FAILURES` times.
fn after_failure(app: &App, f: &store::Failure) {
    let task = &f.task;
    let lost = f.outcome == store::Outcome::Lost;
    app.event(
        &task.job_id,
        JobEvent::TaskFailed(TaskFailedEvent {
            pass: task.pass,
            tile: task.tile,
            worker: f.worker.clone(),
            error: f.error.clone(),
            failures: f.failures,
            lost,
        }),
    );
    if f.failures >= MAX_FAILURES {
        let lost = match f.lost {
            0 => String::new(),
            n => format!(" (worker lost {n} times)"),
        };
        let msg = format!(
            "{} of pass {} failed {} times{lost}; last error (worker {}): {}",
            task_name(task),
            task.pass,
            f.failures,
            f.worker,
            f.error
        );
        fail_job(app, &task.job_id, &msg);
    } else {
        app.work.notify_waiters();
    }
}

/// A task in words: its tile, or a merge's bands.
fn task_name(task: &TaskRow) -> String {
    match task.kind {
        TaskKind::Render => format!("tile {}", task.tile),
        TaskKind::Merge => format!("the merge of bands {:?}", task.bands()),
    }
}

/// Cancels a job that has not ended (a sequence: with every frame not ended); false when it
/// had.
pub(crate) fn cancel(app: &App, id: &str) -> ServiceResult<bool> {
    let Some(job) = app.db().job(id)? else {
        return Ok(false);
    };
    if !job.state.is_active() {
        return Ok(false);
    }
    if job.is_sequence() {
        // The sequence first: its frames' ends then leave it cancelled.
        let ended = app.db().set_job_state(id, JobState::Cancelled, None)?;
        if ended {
            app.event(id, JobEvent::Cancelled(CancelledEvent {}));
        }
        let frames = app.db().frames(id)?;
        for f in frames.iter().filter(|f| f.state.is_active()) {
            cancel(app, &f.id)?;
        }
        return Ok(ended);
    }
    // Taken before the job ends: a merge that sees it ended drops the job's runtime, and a new
    // one would not have the last pass's beauty (`Runtime::frame`) that the EXR below may need.
    // One that cannot be made (its reference unreadable) does not keep the job from ending.
    let early = runtime(app, &job);
    let ended = app.db().set_job_state(id, JobState::Cancelled, None)?;
    if ended {
        app.event(id, JobEvent::Cancelled(CancelledEvent {}));
        frame_ended(app, id);
        app.work.notify_waiters();
        let rt = early.or_else(|_| runtime(app, &job))?;
        // The passes merged so far as image.exr (`merge::write_cancelled`): a pass rewrites it
        // at most every `exr_interval_s`, so the last one may not have. The row is read again under the
        // runtime's lock, which a pass holds while it is recorded: its count then matches the
        // checkpoints.
        let rt = rt.lock().unwrap_or_else(|e| e.into_inner());
        let now = app.db().job(id)?;
        if let Some(job) = now.filter(|j| {
            j.passes_done > 0
                && !rt.final_written
                && !merge::final_in_exr(&rt.resolved, j.passes_done)
        }) && let Err(e) = merge::write_cancelled(app, &job, &rt)
        {
            tracing::warn!(
                "job {id}: cancelled; its EXR of {} passes: {e}",
                job.passes_done
            );
        }
        app.result_logs.remove(&app.paths, id);
    }
    drop_runtime(app, id);
    Ok(ended)
}

/// Pauses a queued or running job: it leases nothing more; the tasks in hand finish and their
/// results are kept. False when it was not queued or running.
/// A sequence's frames go with it.
pub(crate) fn pause(app: &App, id: &str) -> ServiceResult<bool> {
    let paused = app.db().pause(id)?;
    if paused {
        tracing::info!("job {id}: paused");
        for f in frames_of(app, id)? {
            pause(app, &f.id)?;
        }
    }
    Ok(paused)
}

/// The frames of job `id` when it is a sequence (its controls act on them too); else none.
fn frames_of(app: &App, id: &str) -> ServiceResult<Vec<JobRow>> {
    let job = app.db().job(id)?;
    match job {
        Some(j) if j.is_sequence() => Ok(app.db().frames(id)?),
        _ => Ok(Vec::new()),
    }
}

/// Resumes a paused job (a sequence with its paused frames); false when it was not paused.
pub(crate) fn resume(app: &App, id: &str) -> ServiceResult<bool> {
    let resumed = app.db().resume(id)?;
    if resumed {
        for f in frames_of(app, id)? {
            if f.state == JobState::Paused {
                resume(app, &f.id)?;
            }
        }
        tracing::info!("job {id}: resumed");
        app.work.notify_waiters();
        // A pass whose results all came in while paused is merged now.
        advance(app, id);
    }
    Ok(resumed)
}

/// Makes a failed job active again: its failed tasks are queued afresh (every worker may take
/// them again), its error is cleared, and it goes on from its checkpoints and the results it
/// kept, as after a restart; a sequence with its failed frames. False when it had not failed.
pub(crate) fn requeue(app: &App, id: &str) -> ServiceResult<bool> {
    let requeued = app.db().requeue_failed(id)?;
    if requeued {
        for f in frames_of(app, id)? {
            if f.state == JobState::Failed {
                requeue(app, &f.id)?;
            }
        }
        tracing::info!("job {id}: requeued");
        drop_runtime(app, id);
        app.work.notify_waiters();
        advance(app, id);
    }
    Ok(requeued)
}

/// Sets the priority of a job that has not ended (a sequence's frames' too); false when it had.
pub(crate) fn set_priority(app: &App, id: &str, priority: i32) -> ServiceResult<bool> {
    let set = app.db().set_priority(id, priority)?;
    if set {
        for f in frames_of(app, id)? {
            app.db().set_priority(&f.id, priority)?;
        }
        app.work.notify_waiters();
    }
    Ok(set)
}

/// Deletes a job that has ended: its rows (`JobStore::delete_job`), then its files
/// (`delete_files`); not one that is active, nor one whose image another job uses as its
/// reference (the answer says which).
/// A sequence is deleted with its frames, each as a job of its own first.
pub(crate) fn delete(app: &App, id: &str) -> ServiceResult<store::Deleted> {
    let job = app.db().job(id)?;
    if let Some(j) = &job
        && j.is_sequence()
        && !j.state.is_active()
    {
        // The store's guard must be gone before each frame's delete locks it again.
        let frames = app.db().frames(id)?;
        for f in frames {
            let d = delete(app, &f.id)?;
            if !matches!(d, store::Deleted::Removed(_) | store::Deleted::Missing) {
                return Ok(d);
            }
        }
    }
    let image = app.paths.output(id, "image.exr").display().to_string();
    let deleted = app.db().delete_job(id, &image)?;
    if let store::Deleted::Removed(row) = &deleted {
        delete_files(app, row);
        tracing::info!("job {id}: deleted ({})", row.state);
    }
    Ok(deleted)
}

/// Removes every file a deleted job stored: its folder (result logs, tile checkpoints,
/// outputs), its uploaded reference and its scene bundle when no other job uses them. Its rows
/// are gone already, so a crash in between leaves files that no row names, never a row without
/// its files.
fn delete_files(app: &App, job: &JobRow) {
    drop_runtime(app, &job.id);
    app.result_logs.forget(&job.id);
    let dir = app.paths.job(&job.id);
    if let Err(e) = std::fs::remove_dir_all(&dir)
        && e.kind() != std::io::ErrorKind::NotFound
    {
        tracing::warn!("job {}: cannot remove {}: {e}", job.id, dir.display());
    }
    if let Some(reference) = &job.reference {
        let uploaded = std::path::Path::new(reference).starts_with(app.paths.reference_dir());
        if uploaded && !app.db().reference_in_use(reference).unwrap_or(true) {
            let _ = std::fs::remove_file(reference);
        }
    }
    if !app.db().scene_in_use(&job.scene_id).unwrap_or(true) {
        let _ = std::fs::remove_dir_all(app.paths.scene(&job.scene_id));
    }
}

/// Streams the input of leased merge task `task` of `job` through `send` (`merge::serve_input`);
/// a job whose files cannot serve it fails. The error ends the stream.
pub(crate) fn serve_merge_input(
    app: &App,
    job: &JobRow,
    task: &TaskRow,
    send: &mut dyn FnMut(Vec<u8>) -> bool,
) -> ServiceResult<()> {
    let rt = runtime(app, job)?;
    let served = merge::serve_input(app, job, &rt, task, send);
    if let Err(ServiceError::Job(e)) = &served {
        fail_job(app, &job.id, e);
    }
    served
}

/// After a restart: reconcile each unfinished job with its checkpoint, fail the ones this
/// server's limits no longer allow, and merge passes whose results all arrived before the stop.
/// Runs in the background while the server already answers; `App::recovering` holds the jobs
/// not reconciled yet (no merge touches them meanwhile).
pub(crate) async fn recover(app: Arc<App>) {
    let jobs: Vec<String> = app
        .recovering
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .iter()
        .cloned()
        .collect();
    for id in jobs {
        let a = app.clone();
        let i = id.clone();
        let r = tokio::task::spawn_blocking(move || reconcile(&a, &i)).await;
        match r {
            Ok(Ok(())) => {}
            Ok(Err(e)) => tracing::error!("recovering job {id}: {e}"),
            Err(e) => tracing::error!("recovering job {id}: {e}"),
        }
        app.recovering
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&id);
        let a = app.clone();
        let _ = tokio::task::spawn_blocking(move || advance(&a, &id)).await;
    }
    app.work.notify_waiters();
}

/// Recovery of one job (blocking).
fn reconcile(app: &App, id: &str) -> anyhow::Result<()> {
    let Some(job) = app.db().job(id)? else {
        return Ok(());
    };
    if job.is_sequence() {
        // No tasks of its own: its frames are reconciled as jobs of their own.
        return Ok(());
    }
    let r = resolved_of(&job)?;
    let tiles = tile_count(&r) as u64;
    if tiles > app.cfg.limits.max_tasks_per_pass as u64 {
        let msg = format!(
            "the job has {tiles} tasks per pass, more than this server's limit of {} \
             (--max-tasks-per-pass)",
            app.cfg.limits.max_tasks_per_pass
        );
        tracing::error!("job {id}: {msg}");
        if app.db().set_job_state(id, JobState::Failed, Some(&msg))? {
            app.event(id, JobEvent::Failed(FailedEvent { error: msg }));
        }
        return Ok(());
    }
    tracing::info!("recovering job {} ({})", job.id, job.state);
    Ok(())
}

/// How often the reaper looks for tasks no worker may take any more.
const STRANDED_CHECK: std::time::Duration = std::time::Duration::from_secs(5);

/// Twice a second: requeue expired leases (each a lost attempt of its worker), mark silent
/// workers gone; every `STRANDED_CHECK`, fail the jobs of tasks that no live worker may take
/// any more (each failed them or is blocklisted) for longer than a lease.
pub(crate) async fn reaper(app: Arc<App>) {
    let mut tick = tokio::time::interval(std::time::Duration::from_millis(500));
    let mut stranded_since: std::collections::HashMap<i64, std::time::Instant> =
        std::collections::HashMap::new();
    let mut last_check = std::time::Instant::now();
    loop {
        tick.tick().await;
        let a = app.clone();
        let lost = tokio::task::spawn_blocking(move || {
            let lost = {
                let db = a.db();
                let lost = db.expire_leases();
                let _ = db.mark_gone(a.cfg.lease_s * 2.0);
                lost
            };
            match lost {
                Ok(lost) => {
                    for f in &lost {
                        after_failure(&a, f);
                    }
                    lost.len()
                }
                Err(e) => {
                    tracing::error!("cannot expire leases: {e}");
                    0
                }
            }
        })
        .await
        .unwrap_or(0);
        if lost > 0 {
            tracing::warn!("{lost} lease(s) expired; tasks requeued, each a lost attempt");
            super::Metrics::add(&app.metrics.leases_expired, lost as u64);
            app.work.notify_waiters();
        }
        if last_check.elapsed() < STRANDED_CHECK {
            continue;
        }
        last_check = std::time::Instant::now();
        let stranded = app.db().stranded_tasks(app.cfg.lease_s * 2.0);
        let stranded = match stranded {
            Ok(s) => s,
            Err(e) => {
                tracing::error!("cannot look for stranded tasks: {e}");
                continue;
            }
        };
        let now = std::time::Instant::now();
        stranded_since.retain(|id, _| stranded.iter().any(|t| t.id == *id));
        for task in stranded {
            let since = *stranded_since.entry(task.id).or_insert(now);
            if now.duration_since(since).as_secs_f64() < app.cfg.lease_s {
                continue;
            }
            let msg = format!(
                "{} of pass {} failed on every live worker, and each is kept from it (a task \
                 is not given again to a worker that failed it); last error: {}",
                task_name(&task),
                task.pass,
                app.db()
                    .last_error(task.id)
                    .ok()
                    .flatten()
                    .unwrap_or_else(|| "unknown".into())
            );
            let a = app.clone();
            let job = task.job_id.clone();
            let _ = tokio::task::spawn_blocking(move || fail_job(&a, &job, &msg)).await;
            stranded_since.remove(&task.id);
        }
    }
}

/// The convergence plot of a job: relMSE against spp (log-log).
pub(crate) fn convergence_svg(job: &JobRow, series: &[SeriesPoint]) -> String {
    let pts: Vec<(f64, f64)> = series
        .iter()
        .filter_map(|p| p.relmse.map(|r| (p.spp as f64, r)))
        .collect();
    plot::line_chart(
        &format!("job {}: relMSE vs samples per pixel", job.id),
        "samples per pixel",
        "relMSE",
        &[("relMSE".to_string(), pts)],
        true,
        true,
    )
}
