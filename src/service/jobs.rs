//! Job life cycle in the coordinator: tasks pass by pass, the merge of a finished pass (in tile
//! order, so the image has the bits of an in-process render), checkpoints, outputs, recovery
//! after a restart, and expiry of silent leases.

use super::App;
use super::protocol::{
    CancelledEvent, DoneEvent, FailedEvent, JobEvent, JobState, PassDoneEvent, PreviewEvent,
    SeriesPoint, TaskFailedEvent,
};
use super::store::{self, JobRow, TaskRow, write_atomic};
use crate::film::wire::{self, BandedIndex, TileCheckpoint};
use crate::film::{BandGroup, FilmTile, RayStats, Routed, Tile, TileFilm, band_bytes, band_groups};
use crate::film::{Image, exr_io, metrics, plot, png};
use crate::job::Resolved;
use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// A task that failed on this many attempts fails its job.
pub(crate) const MAX_FAILURES: u32 = 3;

/// What merging needs of a running job, kept between passes.
pub(crate) struct Runtime {
    pub resolved: Resolved,
    pub reference: Option<Image>,
    /// The final EXR (every layer) was written by the merge of the last pass.
    pub final_written: bool,
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
        reference,
        final_written: false,
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
pub(crate) fn ensure_passes(app: &App, job: &JobRow, r: &Resolved) -> store::StoreResult<()> {
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
            tracing::error!("job {id}: {e}");
            // The store's guard must be gone before `event` locks it again.
            let failed = app.db().set_job_state(id, JobState::Failed, Some(&e));
            if let Ok(true) = failed {
                app.event(id, JobEvent::Failed(FailedEvent { error: e }));
            }
            drop_runtime(app, id);
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

/// Threads that merge band groups of one pass at once.
fn merge_threads() -> usize {
    std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(4)
}

/// Why a merge stopped: a task result that cannot be read (the task is rendered again) or a
/// problem with the job's own files (the job fails).
enum MergeError {
    Result(usize, String),
    Job(String),
}

impl From<std::io::Error> for MergeError {
    fn from(e: std::io::Error) -> Self {
        MergeError::Job(e.to_string())
    }
}

/// One accepted result of the pass being merged.
struct PassResult {
    /// Its tile (its place in the merge order).
    tile: usize,
    /// Its index, with byte ranges in the pass's result log.
    index: BandedIndex,
}

/// Reads byte range `range` of an open result file.
fn read_range(f: &mut std::fs::File, range: &std::ops::Range<u64>) -> std::io::Result<Vec<u8>> {
    use std::io::{Read, Seek, SeekFrom};
    f.seek(SeekFrom::Start(range.start))?;
    let mut buf = vec![0u8; (range.end - range.start) as usize];
    f.read_exact(&mut buf)?;
    Ok(buf)
}

/// The index of the result stored at `stored` of an open result log (of `log_len` bytes).
fn read_index(
    log: &mut std::fs::File,
    log_len: u64,
    stored: Option<std::ops::Range<u64>>,
) -> Result<BandedIndex, String> {
    use std::io::{Read, Seek, SeekFrom};
    let stored = stored.ok_or("no stored result recorded")?;
    if stored.end > log_len || stored.start > stored.end {
        return Err(format!(
            "stored result at bytes {stored:?} of a log of {log_len}"
        ));
    }
    log.seek(SeekFrom::Start(stored.start))
        .map_err(|e| e.to_string())?;
    let len = stored.end - stored.start;
    let mut r = std::io::BufReader::new(log.take(len));
    Ok(BandedIndex::read(&mut r, len)
        .map_err(|e| e.to_string())?
        .at(stored.start))
}

/// Where the checkpoint of tile `t` holding `n` passes lies: its band's file, the byte offset
/// and the length. Each tile has two slots of the length of a full tile's checkpoint, side by
/// side in the band's file, written in turn (`n % 2`): a write torn by a crash leaves the
/// previous pass in the other slot. The files are made once per job and rewritten in place.
fn checkpoint_slot(
    app: &App,
    job: &str,
    r: &Resolved,
    t: usize,
    n: u32,
) -> (std::path::PathBuf, u64, u64) {
    let grid = r.grid();
    let layout = r.film_layout();
    let columns = grid.columns() as usize;
    let full = TileCheckpoint::encoded_len(grid.size as usize * grid.size as usize, &layout);
    let len = TileCheckpoint::encoded_len(grid.tile(t).pixels(), &layout);
    let slot = 2 * (t % columns) as u64 + (n % 2) as u64;
    (
        app.paths.band_checkpoints(job, (t / columns) as u32),
        slot * full,
        len,
    )
}

/// Writes the checkpoint of `tile` (tile `t` of the frame) holding `n` passes into its slot.
fn write_tile(
    app: &App,
    job: &str,
    r: &Resolved,
    t: usize,
    tile: &FilmTile,
    n: u32,
) -> std::io::Result<()> {
    let (path, at, len) = checkpoint_slot(app, job, r, t, n);
    let bytes = TileCheckpoint::encode_parts(tile, n);
    if bytes.len() as u64 != len {
        // A checkpoint longer than its slot would overwrite the neighbouring tile's.
        return Err(std::io::Error::other(format!(
            "tile checkpoint {t}: {} bytes for a slot of {len}",
            bytes.len()
        )));
    }
    // Made durable all at once before the pass is recorded (`sync_tiles`) on Linux.
    store::write_at(&path, at, &bytes, !cfg!(target_os = "linux"))
}

/// The accumulators of tile `t` of a job that has merged `passes` passes: the tile's checkpoint
/// holding `passes + 1` passes when a merge interrupted by a restart wrote it already, else the
/// one holding `passes`. A slot whose checksum fails (a write torn by a crash) or that was never
/// written is passed over.
fn load_tile(
    app: &App,
    job: &str,
    r: &Resolved,
    t: usize,
    passes: u32,
) -> Result<TileCheckpoint, String> {
    use std::io::{Read, Seek, SeekFrom};
    let grid = r.grid();
    let layout = r.film_layout();
    let read = |n: u32| -> Result<Option<TileCheckpoint>, String> {
        let (path, at, len) = checkpoint_slot(app, job, r, t, n);
        let mut f = match std::fs::File::open(&path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(format!("tile checkpoint {t}: {e}")),
        };
        let mut bytes = vec![0u8; len as usize];
        f.seek(SeekFrom::Start(at))
            .map_err(|e| format!("tile checkpoint {t}: {e}"))?;
        match f.read_exact(&mut bytes) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
            Err(e) => return Err(format!("tile checkpoint {t}: {e}")),
        }
        Ok(TileCheckpoint::decode(&bytes, grid.tile(t), &layout)
            .ok()
            .filter(|ck| ck.passes == n))
    };
    if let Some(ck) = read(passes + 1)? {
        return Ok(ck);
    }
    if let Some(ck) = read(passes)? {
        return Ok(ck);
    }
    if passes == 0 {
        return Ok(TileCheckpoint {
            tile: FilmTile::new(grid.tile(t), &layout),
            passes: 0,
        });
    }
    Err(format!(
        "tile checkpoint {t}: no valid checkpoint holding {passes} passes"
    ))
}

/// Light paths traced for the frame after `spp` samples per pixel (N_L of the optimal-MIS
/// systems): one per pixel sample, as `Film::light_paths` counts them.
fn light_paths(r: &Resolved, spp: u32) -> u64 {
    r.width as u64 * r.height as u64 * spp as u64
}

/// What the merge of one pass works from.
#[derive(Clone, Copy)]
struct PassMerge<'a> {
    app: &'a App,
    job: &'a str,
    r: &'a Resolved,
    pass: u32,
    /// The pass's result log and the accepted results in it.
    log: &'a Path,
    results: &'a [PassResult],
    /// Samples per pixel once the pass is merged.
    spp: u32,
    /// Return every layer (the last pass), not only the beauty.
    all_layers: bool,
}

/// Adds pass `pass` to the tiles of `bands`, writes their checkpoints, and returns the tiles'
/// beauty images. Tiles that already hold the pass (merged before a restart) are read, not
/// merged again.
fn merge_group(
    m: &PassMerge,
    bands: std::ops::Range<usize>,
) -> Result<Vec<Vec<(Tile, Image)>>, MergeError> {
    let PassMerge {
        app,
        job,
        r,
        pass,
        log,
        results,
        spp,
        all_layers,
    } = *m;
    let grid = r.grid();
    let tiles = grid.tiles_of_bands(bands.clone());
    let first = tiles.start;
    let mut held = Vec::with_capacity(tiles.len());
    let mut open = Vec::with_capacity(tiles.len());
    for t in tiles {
        let ck = load_tile(app, job, r, t, pass).map_err(MergeError::Job)?;
        if ck.passes != pass && ck.passes != pass + 1 {
            return Err(MergeError::Job(format!(
                "tile checkpoint {t} holds {} passes, the job {pass}",
                ck.passes
            )));
        }
        open.push(ck.passes == pass);
        held.push(ck.tile);
    }
    let mut group = BandGroup::new(&grid, bands.clone(), held, open);
    if group.open.iter().any(|&o| o) {
        for res in results {
            let own_needed = group.holds(res.tile) && group.open[res.tile - first];
            let span = res.index.span(bands.clone());
            if !own_needed && span.is_none() {
                continue;
            }
            let parts = read_parts(r, log, res, own_needed, span, &bands)
                .map_err(|e| MergeError::Result(res.tile, e))?;
            group.add_task(&grid, res.tile, parts.own.as_ref(), &parts.sections);
        }
        group.end_pass(light_paths(r, spp), r.render.optimal_kappa);
        for (k, tile) in group.tiles.iter().enumerate() {
            if group.open[k] {
                // Into the slot that does not hold the previous pass.
                write_tile(app, job, r, first + k, tile, pass + 1)?;
            }
        }
    }
    Ok(tile_layers(&group.tiles, r, spp, all_layers))
}

/// The parts of one result a band group adds.
struct ResultParts {
    own: Option<TileFilm>,
    sections: Vec<(usize, Routed)>,
}

/// What a band group needs of one stored result in `log`: its own pixels (when `own_needed`)
/// and its sections of `bands` (the byte range `span` holds them), each checked against its
/// checksum.
fn read_parts(
    r: &Resolved,
    log: &Path,
    res: &PassResult,
    own_needed: bool,
    span: Option<std::ops::Range<u64>>,
    bands: &std::ops::Range<usize>,
) -> Result<ResultParts, String> {
    let layout = r.film_layout();
    let grid = r.grid();
    let mut f = std::fs::File::open(log).map_err(|e| e.to_string())?;
    let own = if own_needed {
        let bytes = read_range(&mut f, &res.index.own).map_err(|e| e.to_string())?;
        res.index.check_own(&bytes).map_err(|e| e.to_string())?;
        let (film, _) =
            TileFilm::decode(&bytes, r.width, r.height, &layout).map_err(|e| e.to_string())?;
        if film.tile != grid.tile(res.tile) {
            return Err(format!("result of tile {:?}", film.tile));
        }
        Some(film)
    } else {
        None
    };
    let mut sections = Vec::new();
    if let Some(span) = span {
        let bytes = read_range(&mut f, &span).map_err(|e| e.to_string())?;
        for (k, (b, range)) in res.index.sections.iter().enumerate() {
            let b = *b as usize;
            if bands.contains(&b) {
                let part =
                    &bytes[(range.start - span.start) as usize..(range.end - span.start) as usize];
                res.index
                    .check_section(k, part)
                    .map_err(|e| e.to_string())?;
                let routed =
                    wire::decode_section(part, b, &grid, &layout).map_err(|e| e.to_string())?;
                sections.push((b, routed));
            }
        }
    }
    Ok(ResultParts { own, sections })
}

/// The beauty of each tile (and, with `all_layers`, every other layer the job keeps), as one
/// list of (tile, image) per layer.
fn tile_layers(
    tiles: &[FilmTile],
    r: &Resolved,
    spp: u32,
    all_layers: bool,
) -> Vec<Vec<(Tile, Image)>> {
    let layout = r.film_layout();
    let n_l = light_paths(r, spp);
    let mut layers: Vec<Vec<(Tile, Image)>> = Vec::new();
    for tile in tiles {
        let mut images = vec![tile.image(n_l, layout.kappa)];
        if all_layers {
            images.extend(tile.extra_images(&layout, n_l));
        }
        layers.resize_with(images.len(), Vec::new);
        for (l, img) in layers.iter_mut().zip(images) {
            l.push((tile.tile, img));
        }
    }
    layers
}

/// Makes the tile checkpoints written without fsync durable (Linux: one syncfs of the data
/// folder's file system; elsewhere each file was fsync'd as it was written).
fn sync_tiles(app: &App, job: &str) -> std::io::Result<()> {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        let dir = std::fs::File::open(app.paths.tiles_dir(job))?;
        // SAFETY: syncfs on a file descriptor we own and keep open for the call.
        if unsafe { libc::syncfs(dir.as_raw_fd()) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (app, job);
    Ok(())
}

/// Runs `f` on every band group of the job's frame, `merge_threads()` at a time, and puts the
/// images each returns (tile by tile) into one frame image per layer.
fn for_groups<F>(app: &App, r: &Resolved, f: F) -> Result<Vec<Image>, MergeError>
where
    F: Fn(std::ops::Range<usize>) -> Result<Vec<Vec<(Tile, Image)>>, MergeError> + Sync,
{
    use std::sync::atomic::AtomicUsize;
    // Each thread holds one group (at least one band): the threads together at most the
    // configured memory, so fewer threads when a band alone is large.
    let layout = r.film_layout();
    let total = app.cfg.merge_memory_bytes;
    let threads = merge_threads().min((total / band_bytes(&r.grid(), &layout)).max(1) as usize);
    let budget = total / threads as u64;
    let groups = band_groups(&r.grid(), &layout, budget);
    let next = AtomicUsize::new(0);
    let frames: Mutex<Vec<Image>> = Mutex::new(Vec::new());
    let failed: Mutex<Option<MergeError>> = Mutex::new(None);
    let (w, h) = (r.width as usize, r.height as usize);
    std::thread::scope(|s| {
        for _ in 0..threads.min(groups.len()) {
            s.spawn(|| {
                loop {
                    let g = next.fetch_add(1, Ordering::Relaxed);
                    if g >= groups.len() || failed.lock().is_ok_and(|e| e.is_some()) {
                        return;
                    }
                    match f(groups[g].clone()) {
                        Ok(layers) => {
                            let mut frames = frames.lock().unwrap_or_else(|e| e.into_inner());
                            if frames.len() < layers.len() {
                                frames.resize_with(layers.len(), || Image::new(w, h));
                            }
                            for (frame, tiles) in frames.iter_mut().zip(layers) {
                                for (t, img) in tiles {
                                    frame.blit(&img, t.x0 as usize, t.y0 as usize);
                                }
                            }
                        }
                        Err(e) => {
                            let mut slot = failed.lock().unwrap_or_else(|e| e.into_inner());
                            slot.get_or_insert(e);
                            return;
                        }
                    }
                }
            });
        }
    });
    if let Some(e) = failed.into_inner().unwrap_or_else(|e| e.into_inner()) {
        return Err(e);
    }
    let mut frames = frames.into_inner().unwrap_or_else(|e| e.into_inner());
    if frames.is_empty() {
        frames.push(Image::new(w, h));
    }
    Ok(frames)
}

fn merge_pass(
    app: &App,
    job: &JobRow,
    rt: &mut Runtime,
    pass: u32,
    tasks: &[TaskRow],
) -> Result<(), String> {
    let t0 = Instant::now();
    let r = &rt.resolved;
    // Every result's index first: a result that cannot be read is rendered again before any
    // tile is touched.
    let mut results = Vec::with_capacity(tasks.len());
    let mut stats = RayStats::default();
    let log = app.paths.result_log(&job.id, pass);
    let mut f = std::fs::File::open(&log).ok();
    let log_len = f
        .as_ref()
        .and_then(|f| f.metadata().ok())
        .map_or(0, |m| m.len());
    for t in tasks {
        let index = match f.as_mut() {
            Some(f) => read_index(f, log_len, t.result.clone()),
            None => Err("the pass has no result log".to_string()),
        };
        match index {
            Ok(index) => {
                stats.add(&index.stats);
                results.push(PassResult {
                    tile: t.tile as usize,
                    index,
                });
            }
            Err(e) => return requeue(app, job, pass, t, &e),
        }
    }
    drop(f);
    let spp_done = tasks.first().map_or(0, |t| t.s1);
    // The last pass of a job with a sample count writes the final EXR at once.
    let last = r.spp.is_some() && r.pass_range(pass + 1).is_none();
    let m = PassMerge {
        app,
        job: &job.id,
        r,
        pass,
        log: &log,
        results: &results,
        spp: spp_done,
        all_layers: last,
    };
    let merged = for_groups(app, r, |bands| merge_group(&m, bands));
    trim_memory();
    let (image, layers) = match merged {
        Ok(frames) => {
            let mut frames = frames.into_iter();
            let image = frames.next().ok_or("no image")?;
            let layers: Vec<(String, Image)> = if last {
                r.film_layout()
                    .extra_layer_names()
                    .into_iter()
                    .zip(frames)
                    .collect()
            } else {
                Vec::new()
            };
            (image, layers)
        }
        Err(MergeError::Result(u, e)) => {
            let t = tasks
                .iter()
                .find(|t| t.tile as usize == u)
                .ok_or("merged a result of no task")?;
            return requeue(app, job, pass, t, &e);
        }
        Err(MergeError::Job(e)) => return Err(e),
    };
    sync_tiles(app, &job.id).map_err(|e| format!("cannot sync the tile checkpoints: {e}"))?;
    app.db()
        .pass_merged(&job.id, pass + 1, spp_done, &stats)
        .map_err(|e| e.to_string())?;
    let _ = std::fs::remove_dir_all(app.paths.pass_dir(&job.id, pass));
    super::Metrics::add(&app.metrics.passes_merged, 1);
    super::Metrics::add(&app.metrics.merge_micros, t0.elapsed().as_micros() as u64);

    // Outputs of the pass: preview, beauty EXR, error map, relMSE.
    let job = app
        .db()
        .job(&job.id)
        .map_err(|e| e.to_string())?
        .ok_or("job vanished")?;
    write_outputs(app, &job, rt, &image, &layers)?;
    rt.final_written = last;
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

/// A result of pass `pass` that cannot be read: its task is rendered again (tiles that merged
/// the pass already keep it; a re-render has the same bits).
fn requeue(app: &App, job: &JobRow, pass: u32, t: &TaskRow, e: &str) -> Result<(), String> {
    tracing::error!("job {} pass {pass} tile {}: {e}; requeued", job.id, t.tile);
    app.db().requeue(t.id).map_err(|e| e.to_string())?;
    app.work.notify_waiters();
    Ok(())
}

/// Writes image.exr (the beauty and `layers`), preview.png and (with a reference) error.png.
fn write_outputs(
    app: &App,
    job: &JobRow,
    rt: &Runtime,
    image: &Image,
    layers: &[(String, Image)],
) -> Result<(), String> {
    let mut attrs = rt.resolved.exr_attributes(&job.scene_main, job.spp_done);
    attrs.push(("omis.job", job.id.clone()));
    let tmp = app.paths.output(&job.id, "image.exr.tmp");
    let named: Vec<exr_io::NamedLayer> = layers
        .iter()
        .map(|(name, image)| exr_io::NamedLayer {
            name: name.clone(),
            image,
        })
        .collect();
    exr_io::write_exr(&tmp, image, &named, &attrs)?;
    let preview = png::encode_rgb8(image.width, image.height, &png::to_srgb8(image, 0.0))?;
    write_atomic(&app.paths.output(&job.id, "preview.png"), &preview).map_err(|e| e.to_string())?;
    std::fs::rename(&tmp, app.paths.output(&job.id, "image.exr")).map_err(|e| e.to_string())?;
    if let Some(r) = &rt.reference {
        let map = metrics::error_map(image, r, rt.resolved.eps, 1.0)?;
        let bytes = png::encode_rgb8(image.width, image.height, &map)?;
        write_atomic(&app.paths.output(&job.id, "error.png"), &bytes).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// The final EXR with every layer the job keeps, assembled band group by band group from the
/// tile checkpoints.
fn write_final(app: &App, job: &JobRow, rt: &Runtime) -> Result<(), String> {
    let r = &rt.resolved;
    let grid = r.grid();
    let frames = for_groups(app, r, |bands| {
        let tiles = grid.tiles_of_bands(bands);
        let mut held = Vec::with_capacity(tiles.len());
        for t in tiles {
            let ck = load_tile(app, &job.id, r, t, job.passes_done).map_err(MergeError::Job)?;
            if ck.passes != job.passes_done {
                return Err(MergeError::Job(format!(
                    "tile checkpoint {t} holds {} passes, the job {}",
                    ck.passes, job.passes_done
                )));
            }
            held.push(ck.tile);
        }
        Ok(tile_layers(&held, r, job.spp_done, true))
    })
    .map_err(|e| match e {
        MergeError::Job(e) | MergeError::Result(_, e) => e,
    })?;
    trim_memory();
    let mut frames = frames.into_iter();
    let image = frames.next().ok_or("no image")?;
    let layers: Vec<(String, Image)> = r
        .film_layout()
        .extra_layer_names()
        .into_iter()
        .zip(frames)
        .collect();
    write_outputs(app, job, rt, &image, &layers)
}

fn finish(app: &App, job: &JobRow, rt: &mut Runtime) -> Result<(), String> {
    if !rt.final_written {
        write_final(app, job, rt)?;
    }
    let ended = app
        .db()
        .set_job_state(&job.id, JobState::Done, None)
        .map_err(|e| e.to_string())?;
    if ended {
        let _ = std::fs::remove_dir_all(app.paths.tiles_dir(&job.id));
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
