//! The state of a running job in this process, and of the pass being merged: the one owner of
//! both. `Runtime` holds what the job's merges and outputs need between passes (its resolved
//! settings, its reference image, the last pass's beauty) and the pass in hand (`PassInputs`:
//! the results its merge tasks read; `PassImages`: the images of the band groups merged so
//! far). `App::runtimes` keeps one per job, behind a lock that a merge step holds while it
//! changes the pass's state.

use super::App;
use super::error::{ServiceError, ServiceResult};
use super::store::JobRow;
use crate::film::format::BandedIndex;
use crate::film::image::exr_io;
use crate::film::{Image, RayStats, Tile};
use crate::job::Resolved;
use std::collections::HashSet;
use std::sync::{Arc, Mutex};

/// What merging needs of a running job, kept between passes.
pub(crate) struct Runtime {
    pub resolved: Resolved,
    pub reference: Option<Image>,
    /// The final EXR (every layer) was written by the merge of the last pass.
    pub final_written: bool,
    /// The pass being merged: its results, read once (`PassInputs`).
    pub inputs: Option<Arc<PassInputs>>,
    /// The images of its band groups merged so far.
    pub images: Option<PassImages>,
    /// The last finished pass's beauty, kept for the next pass's frame to reuse.
    pub frame: Option<Image>,
    /// When a pass last wrote image.exr, or (before one did) when this coordinator took the
    /// job up.
    pub exr_written: std::time::Instant,
}

impl Runtime {
    /// Whether a pass before the last rewrites image.exr: when the last rewrite (or the job's
    /// start here) is `interval_s` old. The last pass always writes it (`merge::finish_pass`).
    pub fn exr_due(&self, interval_s: f64) -> bool {
        self.exr_written.elapsed().as_secs_f64() >= interval_s
    }
}

/// The resolved settings a job was created with.
pub(crate) fn resolved_of(job: &JobRow) -> ServiceResult<Resolved> {
    serde_json::from_str(&job.resolved)
        .map_err(|e| ServiceError::job(format!("job {}: bad settings: {e}", job.id)))
}

/// The resolved settings of job `job`, from its runtime (parsed once per job, not per request).
pub(crate) fn resolved(app: &App, job: &JobRow) -> ServiceResult<Resolved> {
    let rt = runtime(app, job)?;
    let r = rt
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .resolved
        .clone();
    Ok(r)
}

/// The runtime of an active job, created on first use.
pub(crate) fn runtime(app: &App, job: &JobRow) -> ServiceResult<Arc<Mutex<Runtime>>> {
    let mut map = app.runtimes.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(r) = map.get(&job.id) {
        return Ok(r.clone());
    }
    let resolved = resolved_of(job)?;
    let reference = match &job.reference {
        // Its beauty alone, block by block: the job's frame, not every layer of the file.
        Some(r) => {
            Some(exr_io::read_exr_beauty(std::path::Path::new(r)).map_err(ServiceError::job)?)
        }
        None => None,
    };
    let rt = Arc::new(Mutex::new(Runtime {
        resolved,
        reference,
        final_written: false,
        inputs: None,
        images: None,
        frame: None,
        exr_written: std::time::Instant::now(),
    }));
    map.insert(job.id.clone(), rt.clone());
    Ok(rt)
}

/// Forgets job `id`'s runtime (the job ended, or its pass state is to be read afresh).
pub(crate) fn drop_runtime(app: &App, id: &str) {
    app.runtimes
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .remove(id);
}

/// One accepted result of a pass being merged.
pub(crate) struct PassResult {
    /// Its pass (its result log).
    pub pass: u32,
    /// Its tile (its place in the merge order within its pass).
    pub tile: usize,
    /// Its render task.
    pub task: i64,
    /// Its index, with byte ranges in the pass's result log.
    pub index: BandedIndex,
}

/// What the merge tasks of a pass read: the accepted results of every pass since the tiles'
/// checkpoints (`held`), pass by pass in task order.
pub(crate) struct PassInputs {
    /// The pass.
    pub pass: u32,
    /// The results, pass by pass in task order.
    pub results: Vec<PassResult>,
    /// The work counters of the pass's own results.
    pub stats: RayStats,
}

/// The images of the band groups of a pass that this process accepted (beauty first), and on
/// the job's last pass the final EXR's blocks they returned.
pub(crate) struct PassImages {
    /// The pass.
    pub pass: u32,
    /// The frame of each layer, beauty first.
    pub layers: Vec<Image>,
    /// Last pass's beauty, whose memory the next frame reuses (its pixels are all overwritten:
    /// every group is put here before a pass is finished).
    spare: Option<Image>,
    /// The final EXR's blocks (compressed, as the merge tasks returned them), by block index.
    blocks: Vec<Option<Vec<u8>>>,
    /// Merge tasks (their group index) whose checkpoints were written and images put here.
    pub merged: HashSet<u32>,
}

impl PassImages {
    pub(crate) fn new(pass: u32) -> PassImages {
        PassImages::reusing(pass, None)
    }

    /// Images of pass `pass` whose beauty reuses `spare` (a frame's image) when it has the
    /// frame's size: no fresh frame-sized allocation, faulted in page by page, per pass.
    pub(crate) fn reusing(pass: u32, spare: Option<Image>) -> PassImages {
        PassImages {
            pass,
            layers: Vec::new(),
            spare,
            blocks: Vec::new(),
            merged: HashSet::new(),
        }
    }

    /// Keeps the EXR blocks `blocks`, the first being block `first`.
    pub(crate) fn keep_blocks(&mut self, first: usize, blocks: &[&[u8]]) {
        if self.blocks.len() < first + blocks.len() {
            self.blocks.resize_with(first + blocks.len(), || None);
        }
        for (slot, b) in self.blocks[first..].iter_mut().zip(blocks) {
            *slot = Some(b.to_vec());
        }
    }

    /// The blocks kept, or None while one before the last kept is missing (the file's writer
    /// refuses fewer blocks than the frame has).
    pub(crate) fn take_blocks(&mut self) -> Option<Vec<Vec<u8>>> {
        std::mem::take(&mut self.blocks).into_iter().collect()
    }

    pub(crate) fn blit(&mut self, r: &Resolved, layers: &[Vec<(Tile, Image)>]) {
        let (w, h) = (r.width as usize, r.height as usize);
        while self.layers.len() < layers.len() {
            let frame = match self.spare.take() {
                Some(f) if f.width == w && f.height == h => f,
                _ => Image::new(w, h),
            };
            self.layers.push(frame);
        }
        for (frame, tiles) in self.layers.iter_mut().zip(layers) {
            for (t, img) in tiles {
                frame.blit(img, t.x0 as usize, t.y0 as usize);
            }
        }
    }

    /// The beauty and the other layers the images hold (none before the last pass), named.
    pub(crate) fn into_named(self, r: &Resolved) -> (Image, Vec<(String, Image)>) {
        let mut frames = self.layers.into_iter();
        let image = frames
            .next()
            .unwrap_or_else(|| Image::new(r.width as usize, r.height as usize));
        let layers = r
            .film_layout()
            .extra_layer_names()
            .into_iter()
            .zip(frames)
            .collect();
        (image, layers)
    }
}
