//! The merge of a finished pass, by merge tasks. When every render task of a pass is done the
//! coordinator cuts the frame into band groups (rows of tiles) and queues one merge task per
//! group. A worker leases it, downloads its input (the group's tile checkpoints and, pass by
//! pass in task order, the parts of the results since them that land in the group, streamed
//! from the result logs), merges with `film::merge_task::run` and uploads the group's new
//! checkpoints and beauty (on the job's last pass: the final EXR's compressed blocks of its scan
//! lines; on a pass after which a path-traced job writes no checkpoints, `output_of`: the beauty
//! alone); the coordinator checks them and writes the checkpoints into the tiles' slots. Once
//! every group is in, the checkpoints are made durable, the pass is recorded and its outputs
//! are written (the final EXR from the blocks as they came: the coordinator compresses
//! nothing).
//!
//! So the coordinator's work per pass is moving bytes: decoding results, adding light-tracing
//! records into optimal systems and solving pixels (what grows with the samples) run on the
//! workers and scale with them. Tiles get exactly `Film::add_task`'s additions in task order
//! whoever merges them, so the image keeps the in-process bits.
//!
//! Durability: a tile's checkpoint has two slots; merging pass p reads the one holding p passes
//! and writes the other, so a merge task run twice (its lease expired, the coordinator
//! restarted) gives the same bits, and a slot torn by a crash is passed over. A merge task is
//! recorded done before its checkpoints are written; groups this process did not see written
//! (after a restart) are read back from their slots before the pass is recorded, and a group
//! whose slots do not hold the pass is merged again. The results of a pass merged without
//! checkpoints, and their task rows, are kept until a pass's checkpoints hold them (`held`):
//! the next merge reads them again, after a restart too.

use super::App;
use super::error::{ServiceError, ServiceResult};
use super::outputs::{Exr, write_outputs};
use super::runtime::{PassImages, PassInputs, PassResult, Runtime};
use super::store::log_file::LogFile;
use super::store::{self, JobRow, TaskRow};
use crate::film::format::merge_stream::{self, MergeHead, MergeOut};
use crate::film::format::{BandedIndex, TileCheckpoint};
use crate::film::image::metrics;
use crate::film::merge_task::{self, LayerImages};
use crate::film::{Image, RayStats, TileAccum, band_bytes, band_groups};
use crate::job::Resolved;
use crate::protocol::{JobEvent, PassDoneEvent, PreviewEvent, SeriesPoint};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Why a merge cannot go on: a stored result that cannot be read (its render task is rendered
/// again) or a problem with the job's own files (the job fails).
#[derive(Debug, thiserror::Error)]
pub(crate) enum MergeError {
    /// The render task (id) whose stored result is damaged or missing, and why.
    #[error("{1}")]
    Result(i64, String),
    /// The job's files cannot serve the merge.
    #[error("{0}")]
    Job(String),
    /// Tile `tile`'s checkpoint file could not be read.
    #[error("tile checkpoint {tile}: {error}")]
    CheckpointRead { tile: usize, error: std::io::Error },
    /// Tile `tile`'s checkpoint holds the passes asked for but does not decode.
    #[error("tile checkpoint {tile}: {error}")]
    CheckpointDecode {
        tile: usize,
        error: crate::film::format::FormatError,
    },
    /// No slot of tile `tile` holds a valid checkpoint of `passes` passes.
    #[error("tile checkpoint {tile}: no valid checkpoint holding {passes} passes")]
    CheckpointAbsent { tile: usize, passes: u32 },
    /// Some tile's slots hold no valid checkpoint of `0` passes.
    #[error("a tile checkpoint holding {0} passes is missing")]
    CheckpointMissing(u32),
}

impl From<std::io::Error> for MergeError {
    fn from(e: std::io::Error) -> Self {
        MergeError::Job(e.to_string())
    }
}

/// Appends byte range `range` of an open file to `buf`; returns where it begins in `buf`.
fn read_into(
    f: &mut std::fs::File,
    range: &std::ops::Range<u64>,
    buf: &mut Vec<u8>,
) -> std::io::Result<usize> {
    use std::io::{Read, Seek, SeekFrom};
    f.seek(SeekFrom::Start(range.start))?;
    let at = buf.len();
    let len = range.end - range.start;
    // Into the spare capacity, not zeroed first (`read_to_end` reads into it as it is).
    buf.reserve(len as usize);
    let got = f.by_ref().take(len).read_to_end(buf)?;
    if got as u64 != len {
        return Err(std::io::Error::new(
            std::io::ErrorKind::UnexpectedEof,
            format!("{got} of {len} bytes at {}", range.start),
        ));
    }
    Ok(at)
}

/// The index of the result stored at `stored` of an open result log (of `log_len` bytes).
fn read_index(
    log: &mut LogFile,
    log_len: u64,
    stored: Option<std::ops::Range<u64>>,
) -> Result<BandedIndex, String> {
    let stored = stored.ok_or("no stored result recorded")?;
    if stored.end > log_len || stored.start > stored.end {
        return Err(format!(
            "stored result at bytes {stored:?} of a log of {log_len}"
        ));
    }
    let len = stored.end - stored.start;
    Ok(BandedIndex::read(&mut log.reader(stored.clone()), len)
        .map_err(|e| e.to_string())?
        .at(stored.start))
}

/// Every accepted result that the merge of pass `pass` of job `id` reads (those of the passes
/// since the checkpoints, `held`), read from its index in its pass's result log.
fn load_inputs(app: &App, id: &str, r: &Resolved, pass: u32) -> Result<PassInputs, MergeError> {
    let mut results = Vec::new();
    let mut stats = RayStats::default();
    for p in held(r, pass)..=pass {
        let tasks = app
            .db()
            .pass_tasks(id, p)
            .map_err(|e| MergeError::Job(e.to_string()))?;
        let log = app.paths.result_log(id, p);
        let mut f = LogFile::open_read(&log).ok();
        let log_len = f.as_ref().and_then(|f| f.len().ok()).unwrap_or(0);
        results.reserve(tasks.len());
        for t in tasks {
            let index = match f.as_mut() {
                Some(f) => read_index(f, log_len, t.result.clone()),
                None => Err("the pass has no result log".to_string()),
            }
            .map_err(|e| MergeError::Result(t.id, e))?;
            if p == pass {
                stats.add(&index.stats);
            }
            results.push(PassResult {
                pass: p,
                tile: t.tile as usize,
                task: t.id,
                index,
            });
        }
    }
    Ok(PassInputs {
        pass,
        results,
        stats,
    })
}

/// The inputs of pass `pass`, read once per pass (and again after a restart).
fn pass_inputs(
    app: &App,
    id: &str,
    rt: &mut Runtime,
    pass: u32,
) -> Result<Arc<PassInputs>, MergeError> {
    if let Some(i) = rt.inputs.as_ref().filter(|i| i.pass == pass) {
        return Ok(i.clone());
    }
    let inputs = Arc::new(load_inputs(app, id, &rt.resolved, pass)?);
    rt.inputs = Some(inputs.clone());
    Ok(inputs)
}

/// A stored result read by the merge of pass `pass` (of that pass or of one since the
/// checkpoints) that cannot be read: its task is rendered again, and the pass's merge waits
/// for it (its merge tasks are dropped; a merge task already done wrote
/// checkpoints holding the pass into slots nothing reads until the merge begins again, which
/// writes them anew).
fn reject_result(app: &App, job: &str, rt: &mut Runtime, pass: u32, task: i64, e: &str) {
    tracing::error!("job {job} pass {pass}: result of task {task}: {e}; rendered again");
    {
        let db = app.db();
        let _ = db.delete_merge_tasks(job, pass);
        let _ = db.requeue(task);
    }
    rt.inputs = None;
    rt.images = None;
    app.work.notify_waiters();
}

/// The band groups of a job's merge tasks: at most 1/16 of the frame's accumulators each (so
/// that a pass is merged by up to 16 workers at once), at least one band, at most the
/// coordinator's merge memory.
fn merge_groups(app: &App, r: &Resolved) -> Vec<std::ops::Range<u32>> {
    let grid = r.grid();
    let layout = r.film_layout();
    let band = band_bytes(&grid, &layout);
    let cap = app
        .cfg
        .merge_memory_bytes
        .min(app.cfg.max_upload_bytes / 2)
        .max(band);
    let budget = (band.saturating_mul(grid.rows() as u64) / 16).clamp(band, cap);
    band_groups(&grid, &layout, budget)
        .into_iter()
        .map(|g| g.start as u32..g.end as u32)
        .collect()
}

/// Samples per pixel once pass `pass` is merged.
fn spp_after(r: &Resolved, pass: u32) -> u32 {
    r.pass_range(pass).map_or(0, |s| s.end)
}

/// Light paths traced for the frame after `spp` samples per pixel (N_L of the optimal-MIS
/// systems): one per pixel sample, as `Film::light_paths` counts them.
fn light_paths(r: &Resolved, spp: u32) -> u64 {
    r.width as u64 * r.height as u64 * spp as u64
}

/// Whether pass `pass` is the job's last (a job with a sample count, or a time-budget job once its
/// last pass is fitted, `Resolved::fit_to_budget`): its merge returns every layer and no
/// checkpoints (the job ends with it and its tile files are removed), and its outputs are the
/// final EXR.
fn is_last(r: &Resolved, pass: u32) -> bool {
    r.spp_limit().is_some() && r.pass_range(pass + 1).is_none()
}

/// What the merge of pass `pass` returns. A job with a sample count whose results hold only
/// their own pixels (no light-tracing splats, no optimal-MIS systems: the path tracer) writes
/// tile checkpoints after every second pass only: a pass's results, packed, take a third of a
/// checkpoint's bytes, so merging pass p + 1 from the checkpoints before pass p and the results
/// of both moves fewer bytes through the coordinator than writing the checkpoints of pass p,
/// storing them and serving them back (1080p: a quarter less coordinator CPU; BENCHMARKS.md,
/// "The render service"). BDPT's results carry splats routed across the frame, more bytes per pass than
/// a checkpoint: reading them twice cost more than it saved. The in-process bits stay: the
/// tiles get the same additions in the same order.
pub(crate) fn output_of(r: &Resolved, pass: u32) -> MergeOut {
    let layout = r.film_layout();
    if is_last(r, pass) {
        MergeOut::Exr
    } else if r.spp.is_some()
        && !layout.splats
        && layout.optimal.is_none()
        && pass.is_multiple_of(2)
    {
        MergeOut::Beauty
    } else {
        MergeOut::Checkpoints
    }
}

/// Passes the tile checkpoints hold once `merged` passes are merged: the merge of pass
/// `merged` starts from them and reads the results of the passes since.
pub(crate) fn held(r: &Resolved, merged: u32) -> u32 {
    (1..=merged)
        .rev()
        .find(|&n| output_of(r, n - 1) == MergeOut::Checkpoints)
        .unwrap_or(0)
}

/// Whether a job of `passes_done` merged passes has merged its last pass: its final EXR was
/// written before that pass was recorded, and no checkpoint holds that pass, so the EXR is not
/// to be assembled from checkpoints again.
pub(crate) fn final_in_exr(r: &Resolved, passes_done: u32) -> bool {
    passes_done > 0 && is_last(r, passes_done - 1)
}

/// Queues the merge tasks of pass `pass`, whose render tasks are all done (called by
/// `jobs::advance`). A result that cannot be read is rendered again first.
pub(crate) fn begin(app: &App, job: &JobRow, rt: &mut Runtime, pass: u32) -> ServiceResult<()> {
    let inputs = match load_inputs(app, &job.id, &rt.resolved, pass) {
        Ok(i) => i,
        Err(MergeError::Result(t, e)) => {
            reject_result(app, &job.id, rt, pass, t, &e);
            return Ok(());
        }
        Err(e) => return Err(ServiceError::job(e)),
    };
    let groups = merge_groups(app, &rt.resolved);
    app.db().create_merge_tasks(&job.id, pass, &groups)?;
    rt.inputs = Some(Arc::new(inputs));
    rt.images = Some(PassImages::reusing(pass, rt.frame.take()));
    app.work.notify_waiters();
    Ok(())
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

/// The bytes of tile `t`'s checkpoint holding exactly `n` passes, or None when its slot holds
/// another pass, was never written, or fails its checksum (torn by a crash).
fn read_slot(
    app: &App,
    job: &str,
    r: &Resolved,
    t: usize,
    n: u32,
) -> Result<Option<Vec<u8>>, MergeError> {
    let mut bytes = Vec::new();
    let slot = checkpoint_slot(app, job, r, t, n);
    Ok(read_slot_into(&slot, r, t, n, &mut bytes)?.map(|_| bytes))
}

/// `read_slot` of the slot `checkpoint_slot` gave (path, offset, length), appended to `buf`
/// (into its spare capacity, not zeroed first): where the checkpoint lies in `buf`, or None
/// with `buf` as it was.
fn read_slot_into(
    (path, at, len): &(std::path::PathBuf, u64, u64),
    r: &Resolved,
    t: usize,
    n: u32,
    buf: &mut Vec<u8>,
) -> Result<Option<std::ops::Range<usize>>, MergeError> {
    let (at, len) = (*at, *len);
    let mut f = match std::fs::File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(error) => return Err(MergeError::CheckpointRead { tile: t, error }),
    };
    no_readahead(&f);
    let start = buf.len();
    let holds = match read_into(&mut f, &(at..at + len), buf) {
        Ok(_) => TileCheckpoint::peek(&buf[start..], r.grid().tile(t)).ok(),
        // Shorter than the slot: never written whole.
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => None,
        Err(error) => {
            buf.truncate(start);
            return Err(MergeError::CheckpointRead { tile: t, error });
        }
    };
    if holds != Some(n) {
        buf.truncate(start);
        return Ok(None);
    }
    Ok(Some(start..buf.len()))
}

/// Tells the kernel that `f` is read at random: a slot is read whole, and the pages after it
/// are the next tile's other slot, which this pass does not read (and which, in a job's first
/// passes, is a hole the read-ahead zeroed page by page: 5 % of an optimal-MIS job's
/// coordinator CPU, BENCHMARKS.md, "The render service").
fn no_readahead(f: &std::fs::File) {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        // Advice only: a failure changes nothing but speed.
        // SAFETY: a valid open descriptor, and the call reads no memory of ours.
        unsafe { libc::posix_fadvise(f.as_raw_fd(), 0, 0, libc::POSIX_FADV_RANDOM) };
    }
    #[cfg(not(target_os = "linux"))]
    let _ = f;
}

/// Writes the encoded checkpoint of tile `t` holding `n` passes into its slot.
pub(crate) fn write_slot(
    app: &App,
    job: &str,
    r: &Resolved,
    t: usize,
    bytes: &[u8],
    n: u32,
) -> std::io::Result<()> {
    let (path, at, len) = checkpoint_slot(app, job, r, t, n);
    if bytes.len() as u64 != len {
        // A checkpoint longer than its slot would overwrite the neighbouring tile's.
        return Err(std::io::Error::other(format!(
            "tile checkpoint {t}: {} bytes for a slot of {len}",
            bytes.len()
        )));
    }
    // Made durable all at once before the pass is recorded (`sync_tiles`) on Linux.
    store::write_at(&path, at, bytes, !cfg!(target_os = "linux"))
}

/// The accumulators of tile `t` holding exactly `n` passes (an empty tile for 0), or None when
/// no valid slot holds them.
fn load_tile(
    app: &App,
    job: &str,
    r: &Resolved,
    t: usize,
    n: u32,
) -> Result<Option<TileAccum>, MergeError> {
    let tile = r.grid().tile(t);
    let layout = r.film_layout();
    if n == 0 {
        return Ok(Some(TileAccum::new(tile, &layout)));
    }
    match read_slot(app, job, r, t, n)? {
        None => Ok(None),
        Some(bytes) => TileCheckpoint::decode(&bytes, tile, &layout)
            .map(|ck| Some(ck.tile))
            .map_err(|error| MergeError::CheckpointDecode { tile: t, error }),
    }
}

/// Streams the input of merge task `task` (of pass `inputs.pass`) to `send`, in pieces of about
/// a megabyte; `send` returns false when the worker has gone (the stream ends early). Every
/// stored part is checked against its checksum as it is read.
pub(crate) fn stream_input(
    app: &App,
    job: &str,
    r: &Resolved,
    task: &TaskRow,
    inputs: &PassInputs,
    send: &mut dyn FnMut(Vec<u8>) -> bool,
) -> Result<(), MergeError> {
    const CHUNK: usize = 1 << 20;
    let pass = inputs.pass;
    let grid = r.grid();
    let bands = task.bands().start as usize..task.bands().end as usize;
    let tiles = grid.tiles_of_bands(bands.clone());
    let touches = |p: &PassResult| tiles.contains(&p.tile) || p.index.span(bands.clone()).is_some();
    let held = held(r, pass);
    let head = MergeHead {
        bands: task.bands(),
        pass: held,
        merged: pass + 1 - held,
        light_paths: light_paths(r, spp_after(r, pass)),
        out: output_of(r, pass),
        results: inputs.results.iter().filter(|p| touches(p)).count() as u32,
    };
    let mut buf = head.encode();
    // Chunks come from the coordinator's reused buffers (`send` gives them back once sent).
    let flush = |buf: &mut Vec<u8>, send: &mut dyn FnMut(Vec<u8>) -> bool, at_least: usize| {
        buf.len() < at_least || send(std::mem::replace(buf, app.buffers.take(2 * CHUNK)))
    };
    for t in tiles.clone() {
        if held == 0 {
            buf.extend(merge_stream::tile_entry(None));
            continue;
        }
        // The entry's head, then the checkpoint read in after it; the length is known
        // beforehand (the slot's), so the head is written first and checked after.
        let slot = checkpoint_slot(app, job, r, t, held);
        buf.extend(merge_stream::tile_entry(Some(slot.2)));
        read_slot_into(&slot, r, t, held, &mut buf)?.ok_or(MergeError::CheckpointAbsent {
            tile: t,
            passes: held,
        })?;
        if !flush(&mut buf, send, CHUNK) {
            return Ok(());
        }
    }
    // The log of the pass being read (results come pass by pass).
    let mut log: Option<(u32, LogFile)> = None;
    for p in inputs.results.iter().filter(|p| touches(p)) {
        let bad = |e: String| MergeError::Result(p.task, e);
        let f = match &mut log {
            Some((at, f)) if *at == p.pass => f,
            _ => {
                let f = LogFile::open_read(&app.paths.result_log(job, p.pass))?;
                &mut log.insert((p.pass, f)).1
            }
        };
        let own = if tiles.contains(&p.tile) {
            p.index.own.clone()
        } else {
            0..0
        };
        let sections: Vec<(usize, &(u32, std::ops::Range<u64>))> = p
            .index
            .sections
            .iter()
            .enumerate()
            .filter(|(_, (b, _))| bands.contains(&(*b as usize)))
            .collect();
        let heads: Vec<(u32, u64)> = sections
            .iter()
            .map(|(_, (b, r))| (*b, r.end - r.start))
            .collect();
        buf.extend(merge_stream::result_entry(
            p.tile as u32,
            own.end - own.start,
            &heads,
        ));
        // Straight from the log into the stream, each part checked where it landed.
        if !own.is_empty() {
            let at = f
                .read_into(&own, &mut buf)
                .map_err(|e| bad(e.to_string()))?;
            p.index
                .check_own(&buf[at..])
                .map_err(|e| bad(e.to_string()))?;
        }
        if let Some(span) = p.index.span(bands.clone()) {
            let at = f
                .read_into(&span, &mut buf)
                .map_err(|e| bad(e.to_string()))?;
            for (k, (_, r)) in &sections {
                let part =
                    &buf[at + (r.start - span.start) as usize..at + (r.end - span.start) as usize];
                p.index
                    .check_section(*k, part)
                    .map_err(|e| bad(e.to_string()))?;
            }
        }
        if !flush(&mut buf, send, CHUNK) {
            return Ok(());
        }
    }
    flush(&mut buf, send, 1);
    Ok(())
}

/// Streams the input of a leased merge task of job `job` (whose runtime is `rt`) through `send`
/// (see `stream_input`), reading the pass's inputs first if this process has not yet. A damaged
/// stored result is rendered again (the merge tasks of its pass are dropped:
/// `ServiceError::RenderedAgain`); a job whose checkpoints cannot be read is
/// `ServiceError::Job`, for the caller to fail. The error ends the stream.
pub(crate) fn serve_input(
    app: &App,
    job: &JobRow,
    rt: &Mutex<Runtime>,
    task: &TaskRow,
    send: &mut dyn FnMut(Vec<u8>) -> bool,
) -> ServiceResult<()> {
    let (r, inputs) = {
        let mut rt = rt.lock().unwrap_or_else(|e| e.into_inner());
        let r = rt.resolved.clone();
        match pass_inputs(app, &job.id, &mut rt, task.pass) {
            Ok(i) => (r, i),
            Err(e) => return Err(merge_failed(app, &job.id, &mut rt, task.pass, e)),
        }
    };
    stream_input(app, &job.id, &r, task, &inputs, send).map_err(|e| {
        let mut rt = rt.lock().unwrap_or_else(|e| e.into_inner());
        merge_failed(app, &job.id, &mut rt, task.pass, e)
    })
}

/// Acts on a merge that cannot go on: a damaged result is rendered again
/// (`ServiceError::RenderedAgain`); a problem with the job's files is returned as
/// `ServiceError::Job`, for the caller to fail the job.
fn merge_failed(app: &App, job: &str, rt: &mut Runtime, pass: u32, e: MergeError) -> ServiceError {
    match e {
        MergeError::Result(t, e) => {
            reject_result(app, job, rt, pass, t, &e);
            ServiceError::RenderedAgain(format!(
                "a result of pass {pass} is damaged ({e}); it is rendered again"
            ))
        }
        e => ServiceError::job(e),
    }
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

/// Threads that read band groups of checkpoints back at once.
fn read_threads() -> usize {
    std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(4)
}

/// Runs `f` on every band group of `groups`, a few at a time (each thread holds one group's
/// tiles, and the coordinator's merge memory bounds them together), and puts the images each
/// returns into `images`. Stops at the first error.
fn for_groups<F>(
    app: &App,
    r: &Resolved,
    groups: &[std::ops::Range<usize>],
    images: &mut PassImages,
    f: F,
) -> Result<(), MergeError>
where
    F: Fn(std::ops::Range<usize>) -> Result<LayerImages, MergeError> + Sync,
{
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let layout = r.film_layout();
    let threads = read_threads()
        .min((app.cfg.merge_memory_bytes / band_bytes(&r.grid(), &layout)).max(1) as usize);
    let next = AtomicUsize::new(0);
    let out = Mutex::new((images, None::<MergeError>));
    std::thread::scope(|s| {
        for _ in 0..threads.min(groups.len()) {
            s.spawn(|| {
                loop {
                    let g = next.fetch_add(1, Ordering::Relaxed);
                    if g >= groups.len() || out.lock().is_ok_and(|o| o.1.is_some()) {
                        return;
                    }
                    let got = f(groups[g].clone());
                    let mut o = out.lock().unwrap_or_else(|e| e.into_inner());
                    match got {
                        Ok(layers) => o.0.blit(r, &layers),
                        Err(e) => {
                            o.1.get_or_insert(e);
                            return;
                        }
                    }
                }
            });
        }
    });
    match out.into_inner().unwrap_or_else(|e| e.into_inner()).1 {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// The images of the tiles of `bands` from their checkpoints holding `n` passes, or None when
/// a tile's slots do not hold them.
fn images_of(
    app: &App,
    job: &str,
    r: &Resolved,
    bands: std::ops::Range<usize>,
    n: u32,
    all_layers: bool,
) -> Result<Option<LayerImages>, MergeError> {
    let mut held = Vec::new();
    for t in r.grid().tiles_of_bands(bands) {
        match load_tile(app, job, r, t, n)? {
            Some(tile) => held.push(tile),
            None => return Ok(None),
        }
    }
    let n_l = light_paths(r, spp_after(r, n.saturating_sub(1)));
    Ok(Some(merge_task::tile_images(
        &held,
        &r.film_layout(),
        n_l,
        all_layers,
    )))
}

/// Records pass `pass` once every merge task (`merges`) is done, in these steps:
/// 1. `read_back_groups`: the images of groups merged before a restart are read back from their
///    checkpoints (a group whose slots do not hold the pass is queued again, and false returned;
///    on a pass whose merges write no checkpoints, every such group is);
/// 2. `pass_stats`: the pass's work counters, from its results' indexes;
/// 3. `make_durable`: the checkpoints synced, or on the last pass the final EXR written (before
///    the pass is recorded, so a job recorded with its last pass has it);
/// 4. `record_pass`: the pass and its counters recorded, the result logs the checkpoints now
///    hold given up;
/// 5. `write_pass_outputs`: the preview (and the interim EXR when due);
/// 6. `report_pass`: the relMSE point and the pass's events.
///
/// False when the pass is not finished after all (groups or a result to do again).
pub(crate) fn finish_pass(
    app: &App,
    job: &JobRow,
    rt: &mut Runtime,
    pass: u32,
    merges: &[TaskRow],
) -> ServiceResult<bool> {
    let t0 = Instant::now();
    let r = rt.resolved.clone();
    let mut images = rt
        .images
        .take()
        .filter(|i| i.pass == pass)
        .unwrap_or_else(|| PassImages::reusing(pass, rt.frame.take()));
    if !read_back_groups(app, job, &r, pass, merges, &mut images)? {
        // The groups queued again are merged with the images of the others kept.
        rt.images = Some(images);
        app.work.notify_waiters();
        return Ok(false);
    }
    let Some(stats) = pass_stats(app, job, rt, pass)? else {
        return Ok(false);
    };
    let spp = spp_after(&r, pass);
    let blocks = images.take_blocks();
    let (image, _) = images.into_named(&r);
    make_durable(app, job, rt, pass, spp, &image, blocks)?;
    record_pass(app, job, &r, pass, spp, &stats)?;
    rt.inputs = None;
    super::Metrics::add(&app.metrics.passes_merged, 1);
    super::Metrics::add(&app.metrics.merge_micros, t0.elapsed().as_micros() as u64);
    let job = app
        .db()
        .job(&job.id)?
        .ok_or_else(|| ServiceError::job("job vanished"))?;
    write_pass_outputs(app, &job, rt, pass, &image)?;
    report_pass(app, &job, rt, pass, spp, &image)?;
    if !is_last(&r, pass) {
        rt.frame = Some(image);
    }
    Ok(true)
}

/// Step 1 of `finish_pass`: puts into `images` the groups of `merges` this process did not
/// accept (merged before a restart), read back from their checkpoints. False when some must be
/// merged again (they are queued): on a pass whose merges write no checkpoints, every such
/// group (its images were in the memory of a coordinator that stopped; its inputs are kept
/// until the pass is recorded); else a group whose slots do not hold the pass.
fn read_back_groups(
    app: &App,
    job: &JobRow,
    r: &Resolved,
    pass: u32,
    merges: &[TaskRow],
    images: &mut PassImages,
) -> ServiceResult<bool> {
    let last = is_last(r, pass);
    let checkpoints = output_of(r, pass) == MergeOut::Checkpoints;
    let unseen: Vec<&TaskRow> = merges
        .iter()
        .filter(|m| !images.merged.contains(&m.tile))
        .collect();
    if !checkpoints && !unseen.is_empty() {
        tracing::warn!(
            "job {} pass {pass} (no checkpoints): {} merge tasks done before a restart; merged again",
            job.id,
            unseen.len()
        );
        for m in unseen {
            app.db().requeue(m.id)?;
        }
        return Ok(false);
    }
    for m in unseen {
        let bands = m.bands().start as usize..m.bands().end as usize;
        let missing = std::sync::atomic::AtomicBool::new(false);
        for_groups(app, r, &[bands], images, |bands| {
            match images_of(app, &job.id, r, bands, pass + 1, last)? {
                Some(layers) => Ok(layers),
                None => {
                    missing.store(true, std::sync::atomic::Ordering::Relaxed);
                    Ok(Vec::new())
                }
            }
        })
        .map_err(ServiceError::job)?;
        if missing.into_inner() {
            tracing::warn!(
                "job {} pass {pass}: merge of bands {:?} is not in its checkpoints; merged again",
                job.id,
                m.bands()
            );
            app.db().requeue(m.id)?;
            return Ok(false);
        }
        images.merged.insert(m.tile);
    }
    Ok(true)
}

/// Step 2 of `finish_pass`: the work counters of the pass's own results; None when a result
/// turned out unreadable (it is rendered again, and the pass waits for it).
fn pass_stats(
    app: &App,
    job: &JobRow,
    rt: &mut Runtime,
    pass: u32,
) -> ServiceResult<Option<RayStats>> {
    match pass_inputs(app, &job.id, rt, pass) {
        Ok(i) => Ok(Some(i.stats)),
        Err(e) => match merge_failed(app, &job.id, rt, pass, e) {
            ServiceError::RenderedAgain(_) => Ok(None),
            e => Err(e),
        },
    }
}

/// Step 3 of `finish_pass`: on the job's last pass, the final EXR from the blocks its merges
/// returned (it stands in for the checkpoints this pass does not write: written and fsync'd
/// before the pass is recorded, `final_in_exr`); on a pass with checkpoints, one sync of them.
fn make_durable(
    app: &App,
    job: &JobRow,
    rt: &mut Runtime,
    pass: u32,
    spp: u32,
    image: &Image,
    blocks: Option<Vec<Vec<u8>>>,
) -> ServiceResult<()> {
    if is_last(&rt.resolved, pass) {
        let at_end = JobRow {
            spp_done: spp,
            ..job.clone()
        };
        let blocks = blocks
            .ok_or_else(|| ServiceError::job("the last pass's merges left an EXR block missing"))?;
        write_outputs(app, &at_end, rt, image, Exr::Blocks(blocks))?;
        rt.exr_written = Instant::now();
    } else if output_of(&rt.resolved, pass) == MergeOut::Checkpoints {
        sync_tiles(app, &job.id)
            .map_err(|e| ServiceError::job(format!("cannot sync the tile checkpoints: {e}")))?;
    }
    Ok(())
}

/// Step 4 of `finish_pass`: records the pass with its work counters `stats`, and gives up the
/// result logs of the passes the checkpoints (or the final EXR) now hold; a later pass of the
/// job rewrites a log in place (`store::ResultLogs`), and a time-budget job's passes have no
/// end. The results of a pass merged without checkpoints are kept for the next merge to read.
fn record_pass(
    app: &App,
    job: &JobRow,
    r: &Resolved,
    pass: u32,
    spp: u32,
    stats: &RayStats,
) -> ServiceResult<()> {
    let read_from = held(r, pass);
    let kept_from = if output_of(r, pass) == MergeOut::Checkpoints || is_last(r, pass) {
        pass + 1
    } else {
        read_from
    };
    app.db()
        .pass_merged(&job.id, pass + 1, spp, kept_from, stats)?;
    for p in read_from..kept_from {
        let reused = r.pass_range(p + 2).is_some();
        app.result_logs.release(&app.paths, &job.id, p, reused);
    }
    Ok(())
}

/// Step 5 of `finish_pass`: a pass before the last writes the preview, and the beauty-only EXR
/// when one is due (`Runtime::exr_due`); the last pass's outputs were written with its EXR.
fn write_pass_outputs(
    app: &App,
    job: &JobRow,
    rt: &mut Runtime,
    pass: u32,
    image: &Image,
) -> ServiceResult<()> {
    let last = is_last(&rt.resolved, pass);
    if !last {
        let exr = rt.exr_due(app.cfg.exr_interval_s);
        let what = if exr { Exr::Interim } else { Exr::No };
        write_outputs(app, job, rt, image, what)?;
        if exr {
            rt.exr_written = Instant::now();
        }
    }
    rt.final_written = last;
    Ok(())
}

/// Step 6 of `finish_pass`: the pass's relMSE against the job's reference (if any) recorded in
/// its series, and its `pass_done` and `preview` events.
fn report_pass(
    app: &App,
    job: &JobRow,
    rt: &Runtime,
    pass: u32,
    spp: u32,
    image: &Image,
) -> ServiceResult<()> {
    let relmse = match &rt.reference {
        Some(reference) => Some(
            metrics::compare(image, reference, rt.resolved.eps)
                .map_err(ServiceError::job)?
                .relmse,
        ),
        None => None,
    };
    // Rendering time: a pause is not counted (a time budget's fit reads these seconds).
    let seconds = job.render_seconds(store::now());
    app.db().add_series(
        &job.id,
        &SeriesPoint {
            pass,
            spp,
            seconds,
            relmse,
        },
    )?;
    app.event(
        &job.id,
        JobEvent::PassDone(PassDoneEvent {
            pass,
            spp,
            seconds,
            relmse,
        }),
    );
    app.event(
        &job.id,
        JobEvent::Preview(PreviewEvent {
            pass,
            spp,
            url: format!("/v1/jobs/{}/preview.png", job.id),
        }),
    );
    Ok(())
}

/// A cancelled job's EXR: every layer of the passes merged, from the checkpoints; when the last
/// pass merged wrote none (a path-traced job's even pass) and its beauty is still in memory, that
/// beauty (every pass merged, as the interim EXR is); else every layer of the passes the
/// checkpoints hold.
pub(crate) fn write_cancelled(app: &App, job: &JobRow, rt: &Runtime) -> ServiceResult<()> {
    match &rt.frame {
        Some(frame) if held(&rt.resolved, job.passes_done) < job.passes_done => {
            write_outputs(app, job, rt, frame, Exr::Interim)
        }
        _ => write_final(app, job, rt),
    }
}

/// The final EXR with every layer the job keeps, assembled band group by band group from the
/// tile checkpoints (a job whose last pass did not write it: a time-budget job).
pub(crate) fn write_final(app: &App, job: &JobRow, rt: &Runtime) -> ServiceResult<()> {
    let r = &rt.resolved;
    // The passes the checkpoints hold: those merged, unless the last merged wrote none (a
    // cancelled job: its EXR then holds the passes checkpointed, none if none is).
    let passes = held(r, job.passes_done);
    if passes == 0 && job.passes_done > 0 {
        return Err(ServiceError::Job(format!(
            "no tile checkpoint holds any of its {} passes merged",
            job.passes_done
        )));
    }
    let fewer;
    let job = if passes < job.passes_done {
        fewer = JobRow {
            passes_done: passes,
            spp_done: spp_after(r, passes - 1),
            ..job.clone()
        };
        &fewer
    } else {
        job
    };
    let groups = band_groups(
        &r.grid(),
        &r.film_layout(),
        app.cfg.merge_memory_bytes / read_threads() as u64,
    );
    let mut images = PassImages::new(passes);
    for_groups(app, r, &groups, &mut images, |bands| {
        images_of(app, &job.id, r, bands, passes, true)?
            .ok_or(MergeError::CheckpointMissing(passes))
    })
    .map_err(ServiceError::job)?;
    let (image, layers) = images.into_named(r);
    write_outputs(app, job, rt, &image, Exr::Images(&layers))
}
