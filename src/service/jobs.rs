//! Job life cycle in the coordinator: tasks pass by pass, the merge of a finished pass (in tile
//! order, so the image has the bits of an in-process render), checkpoints, outputs, recovery
//! after a restart, and expiry of silent leases.

use super::App;
use super::protocol::{
    CancelledEvent, DoneEvent, FailedEvent, JobEvent, JobState, PassDoneEvent, PreviewEvent,
    SeriesPoint, TaskFailedEvent,
};
use super::store::{self, JobRow, TaskRow, write_atomic};
use crate::film::wire::Checkpoint;
use crate::film::{Film, RayStats, Tile, TileFilm};
use crate::film::{Image, exr_io, metrics, plot, png};
use crate::job::Resolved;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// A task that failed on this many attempts fails its job.
pub(crate) const MAX_FAILURES: u32 = 3;

/// What merging needs of a running job, kept between passes.
pub(crate) struct Runtime {
    pub resolved: Resolved,
    /// The merged accumulators (loaded from the checkpoint on first use).
    pub checkpoint: Option<Checkpoint>,
    pub reference: Option<Image>,
}

/// The resolved settings a job was created with.
pub(crate) fn resolved_of(job: &JobRow) -> Result<Resolved, String> {
    serde_json::from_str(&job.resolved).map_err(|e| format!("job {}: bad settings: {e}", job.id))
}

/// The runtime of an active job, created on first use.
fn runtime(app: &App, job: &JobRow) -> Result<Arc<Mutex<Runtime>>, String> {
    let mut map = app.runtimes.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(r) = map.get(&job.id) {
        return Ok(r.clone());
    }
    let resolved = resolved_of(job)?;
    let reference = match &job.reference {
        Some(r) => Some(exr_io::read_exr(std::path::Path::new(r))?),
        None => None,
    };
    let rt = Arc::new(Mutex::new(Runtime {
        resolved,
        checkpoint: None,
        reference,
    }));
    map.insert(job.id.clone(), rt.clone());
    Ok(rt)
}

fn drop_runtime(app: &App, id: &str) {
    app.runtimes
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .remove(id);
}

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

/// Makes sure the job's next two passes (`passes_done` and the one after) have their tasks, so
/// workers never wait on a merge; a time-budget job starts no new pass once its time is up (a
/// pass begun is completed). Tasks are created in chunks of `TASK_CHUNK`, each its own
/// transaction, the store unlocked in between and workers woken after each; it stops early when
/// the job ends or the coordinator stops. Idempotent: called at creation, after every merge and
/// after a restart.
pub(crate) fn ensure_passes(app: &App, job: &JobRow, r: &Resolved) -> rusqlite::Result<()> {
    let within_time = r
        .time_budget_s
        .is_none_or(|b| job.started_at.is_none_or(|s| store::now() - s < b));
    let tiles = tile_count(r);
    for p in job.passes_done..job.passes_done + 2 {
        let Some(range) = r.pass_range(p) else {
            continue;
        };
        let mut next = match app.db().last_tile(&job.id, p)? {
            Some(last) => last + 1,
            None if within_time => 0,
            None => continue,
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

/// Merges every finished pass of a job, in order, and finishes the job after its last one.
/// Runs on a blocking thread; one merge per job at a time. A job that recovery has not
/// reconciled yet is left to recovery.
pub(crate) fn advance(app: &App, id: &str) {
    if app.is_recovering(id) {
        return;
    }
    if let Err(e) = advance_inner(app, id) {
        tracing::error!("job {id}: {e}");
        if let Ok(true) = app.db().set_job_state(id, JobState::Failed, Some(&e)) {
            app.event(id, JobEvent::Failed(FailedEvent { error: e }));
        }
        drop_runtime(app, id);
    }
}

fn advance_inner(app: &App, id: &str) -> Result<(), String> {
    let Some(job) = app.db().job(id).map_err(|e| e.to_string())? else {
        return Ok(());
    };
    if !job.state.is_active() {
        return Ok(());
    }
    let rt = runtime(app, &job)?;
    let mut rt = rt.lock().unwrap_or_else(|e| e.into_inner());
    loop {
        let Some(job) = app.db().job(id).map_err(|e| e.to_string())? else {
            return Ok(());
        };
        if !job.state.is_active() {
            drop_runtime(app, id);
            return Ok(());
        }
        ensure_passes(app, &job, &rt.resolved).map_err(|e| e.to_string())?;
        app.work.notify_waiters();
        let pass = job.passes_done;
        let (last, open) = {
            let db = app.db();
            let last = db.last_tile(id, pass).map_err(|e| e.to_string())?;
            (last, db.pass_open(id, pass).map_err(|e| e.to_string())?)
        };
        let complete = last.is_some_and(|l| l + 1 >= tile_count(&rt.resolved));
        if !complete || open {
            if last.is_none() && finished_all(app, &job)? {
                finish(app, &job, &mut rt)?;
                drop_runtime(app, id);
            }
            return Ok(());
        }
        let tasks = app.db().pass_tasks(id, pass).map_err(|e| e.to_string())?;
        merge_pass(app, &job, &mut rt, pass, &tasks)?;
    }
}

/// True when no task of the job is left after its merged passes.
fn finished_all(app: &App, job: &JobRow) -> Result<bool, String> {
    let last = app.db().last_pass(&job.id).map_err(|e| e.to_string())?;
    Ok(last.is_none_or(|l| l < job.passes_done))
}

fn load_checkpoint<'a>(
    app: &App,
    job: &JobRow,
    rt: &'a mut Runtime,
) -> Result<&'a mut Checkpoint, String> {
    if rt.checkpoint.is_none() {
        let r = &rt.resolved;
        let path = app.paths.checkpoint(&job.id);
        let ck = match std::fs::read(&path) {
            Ok(bytes) => Checkpoint::decode(&bytes, r.width, r.height, &r.film_layout())
                .map_err(|e| format!("{}: {e}", path.display()))?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Checkpoint {
                frame: Film::new(r.width, r.height, &r.film_layout()),
                passes: 0,
                stats: RayStats::default(),
            },
            Err(e) => return Err(format!("{}: {e}", path.display())),
        };
        if ck.passes != job.passes_done {
            return Err(format!(
                "checkpoint holds {} passes, the database {}",
                ck.passes, job.passes_done
            ));
        }
        rt.checkpoint = Some(ck);
    }
    Ok(rt.checkpoint.as_mut().expect("loaded above"))
}

fn merge_pass(
    app: &App,
    job: &JobRow,
    rt: &mut Runtime,
    pass: u32,
    tasks: &[TaskRow],
) -> Result<(), String> {
    let t0 = Instant::now();
    let (w, h) = (rt.resolved.width, rt.resolved.height);
    let layout = rt.resolved.film_layout();
    // One result at a time (peak memory: the frame and one tile). A result that cannot be read
    // drops the half-merged accumulators (the checkpoint on disk is intact) and is rendered again.
    load_checkpoint(app, job, rt)?;
    for t in tasks {
        let path = app.paths.result(&job.id, pass, t.tile, t.attempt);
        let film = std::fs::read(&path)
            .map_err(|e| e.to_string())
            .and_then(|b| TileFilm::decode(&b, w, h, &layout).map_err(|e| e.to_string()));
        match film {
            Ok((f, _)) => {
                let ck = rt.checkpoint.as_mut().expect("loaded above");
                ck.frame.merge_task(&f);
                ck.stats.add(&f.stats);
            }
            Err(e) => {
                tracing::error!("job {} pass {pass} tile {}: {e}; requeued", job.id, t.tile);
                rt.checkpoint = None;
                app.db().requeue(t.id).map_err(|e| e.to_string())?;
                app.work.notify_waiters();
                return Ok(());
            }
        }
    }
    let ck = rt.checkpoint.as_mut().expect("loaded above");
    ck.passes = pass + 1;
    store::write_atomic_with(&app.paths.checkpoint(&job.id), |f| {
        ck.write_to(f).map(|_| ())
    })
    .map_err(|e| format!("cannot write the checkpoint: {e}"))?;
    let spp_done = tasks.first().map_or(0, |t| t.s1);
    app.db()
        .pass_merged(&job.id, pass + 1, spp_done, &ck.stats)
        .map_err(|e| e.to_string())?;
    let _ = std::fs::remove_dir_all(app.paths.pass_dir(&job.id, pass));
    super::Metrics::add(&app.metrics.passes_merged, 1);
    super::Metrics::add(&app.metrics.merge_micros, t0.elapsed().as_micros() as u64);

    // Outputs of the pass: preview, EXR, error map, relMSE.
    let job = app
        .db()
        .job(&job.id)
        .map_err(|e| e.to_string())?
        .ok_or("job vanished")?;
    let image = write_outputs(app, &job, rt)?;
    let relmse = match &rt.reference {
        Some(r) => Some(
            metrics::compare(&image, r, rt.resolved.eps)
                .map_err(|e| e.to_string())?
                .relmse,
        ),
        None => None,
    };
    let seconds = job.started_at.map_or(0.0, |s| store::now() - s);
    app.db()
        .add_series(
            &job.id,
            &SeriesPoint {
                pass,
                spp: spp_done,
                seconds,
                relmse,
            },
        )
        .map_err(|e| e.to_string())?;
    app.event(
        &job.id,
        JobEvent::PassDone(PassDoneEvent {
            pass,
            spp: spp_done,
            seconds,
            relmse,
        }),
    );
    app.event(
        &job.id,
        JobEvent::Preview(PreviewEvent {
            pass,
            spp: spp_done,
            url: format!("/v1/jobs/{}/preview.png", job.id),
        }),
    );

    Ok(())
}

/// The image of the merged passes; writes preview.png, image.exr and (with a reference)
/// error.png.
fn write_outputs(app: &App, job: &JobRow, rt: &mut Runtime) -> Result<Image, String> {
    let mut attrs = rt.resolved.exr_attributes(&job.scene_main, job.spp_done);
    attrs.push(("omis.job", job.id.clone()));
    let ck = load_checkpoint(app, job, rt)?;
    let tmp = app.paths.output(&job.id, "image.exr.tmp");
    let image = ck.frame.write_exr(&tmp, &attrs)?;
    let preview = png::encode_rgb8(image.width, image.height, &png::to_srgb8(&image, 0.0))?;
    write_atomic(&app.paths.output(&job.id, "preview.png"), &preview).map_err(|e| e.to_string())?;
    std::fs::rename(&tmp, app.paths.output(&job.id, "image.exr")).map_err(|e| e.to_string())?;
    if let Some(r) = &rt.reference {
        let map = metrics::error_map(&image, r, rt.resolved.eps, 1.0)?;
        let bytes = png::encode_rgb8(image.width, image.height, &map)?;
        write_atomic(&app.paths.output(&job.id, "error.png"), &bytes).map_err(|e| e.to_string())?;
    }
    Ok(image)
}

fn finish(app: &App, job: &JobRow, rt: &mut Runtime) -> Result<(), String> {
    if job.passes_done == 0 {
        write_outputs(app, job, rt)?;
    }
    let ended = app
        .db()
        .set_job_state(&job.id, JobState::Done, None)
        .map_err(|e| e.to_string())?;
    if ended {
        let _ = std::fs::remove_file(app.paths.checkpoint(&job.id));
        app.event(&job.id, JobEvent::Done(DoneEvent { spp: job.spp_done }));
    }
    Ok(())
}

/// Records a failed attempt; after `MAX_FAILURES` the job fails with the worker's error.
pub(crate) fn task_failed(
    app: &App,
    task: &TaskRow,
    worker: &str,
    error: &str,
) -> Result<bool, String> {
    let failures = app
        .db()
        .fail(task.id, task.attempt, worker, error)
        .map_err(|e| e.to_string())?;
    let Some(failures) = failures else {
        return Ok(false);
    };
    app.event(
        &task.job_id,
        JobEvent::TaskFailed(TaskFailedEvent {
            pass: task.pass,
            tile: task.tile,
            worker: worker.to_string(),
            error: error.to_string(),
            failures,
        }),
    );
    if failures >= MAX_FAILURES {
        let msg = format!(
            "tile {} of pass {} failed {failures} times; last error (worker {worker}): {error}",
            task.tile, task.pass
        );
        let ended = app
            .db()
            .set_job_state(&task.job_id, JobState::Failed, Some(&msg))
            .map_err(|e| e.to_string())?;
        if ended {
            app.event(&task.job_id, JobEvent::Failed(FailedEvent { error: msg }));
        }
        drop_runtime(app, &task.job_id);
    } else {
        app.work.notify_waiters();
    }
    Ok(true)
}

/// Cancels a job that has not ended; false when it had.
pub(crate) fn cancel(app: &App, id: &str) -> Result<bool, String> {
    let Some(job) = app.db().job(id).map_err(|e| e.to_string())? else {
        return Ok(false);
    };
    if !job.state.is_active() {
        return Ok(false);
    }
    let ended = app
        .db()
        .set_job_state(id, JobState::Cancelled, None)
        .map_err(|e| e.to_string())?;
    if ended {
        app.event(id, JobEvent::Cancelled(CancelledEvent {}));
        app.work.notify_waiters();
    }
    drop_runtime(app, id);
    Ok(ended)
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
    let r = resolved_of(&job).map_err(anyhow::Error::msg)?;
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
    let path = app.paths.checkpoint(&job.id);
    if let Ok(bytes) = std::fs::read(&path) {
        match Checkpoint::decode(&bytes, r.width, r.height, &r.film_layout()) {
            Ok(ck) if ck.passes > job.passes_done => {
                // Stopped between writing the checkpoint and recording it.
                let spp = r
                    .pass_range(ck.passes - 1)
                    .map_or(job.spp_done, |range| range.end);
                app.db().pass_merged(&job.id, ck.passes, spp, &ck.stats)?;
            }
            Ok(_) => {}
            Err(e) => tracing::error!("job {}: {e}", job.id),
        }
    }
    // Results of passes merged before the stop are no longer needed.
    if let Some(job) = app.db().job(&job.id)? {
        for p in 0..job.passes_done {
            let _ = std::fs::remove_dir_all(app.paths.pass_dir(&job.id, p));
        }
    }
    tracing::info!("recovering job {} ({})", job.id, job.state);
    Ok(())
}

/// Every second: requeue expired leases, mark silent workers gone.
pub(crate) async fn reaper(app: Arc<App>) {
    let mut tick = tokio::time::interval(std::time::Duration::from_millis(500));
    loop {
        tick.tick().await;
        let (expired, _) = {
            let db = app.db();
            (
                db.expire_leases().unwrap_or(0),
                db.mark_gone(app.cfg.lease_s * 2.0).unwrap_or(0),
            )
        };
        if expired > 0 {
            tracing::warn!("{expired} lease(s) expired; tasks requeued");
            super::Metrics::add(&app.metrics.leases_expired, expired as u64);
            app.work.notify_waiters();
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
