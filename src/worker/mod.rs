//! `omis worker`: registers with a coordinator, long-polls for tile tasks, renders them (one
//! task per thread), uploads each result, and heartbeats its leases meanwhile. Scenes are
//! downloaded once per bundle and kept loaded (with their BVH) for the tasks that follow.
//! SIGTERM drains: no new task is taken, the ones in hand are finished and uploaded.
//!
//! In the flow film -> worker -> service: the worker takes its tasks and sends its results
//! in the types of [`crate::protocol`], renders with [`crate::integrator`] into a
//! [`TaskFilm`](crate::film::TaskFilm), and ships it laid out by band
//! ([`crate::film::format::encode_banded`]); merge tasks run [`crate::film::merge_task`].

mod error;

pub(crate) use error::WorkerError;

use crate::bundle;
use crate::film;
use crate::integrator;
use crate::integrator::vcm::PhotonCache;
use crate::protocol::{
    DeregisterRequest, FailRequest, HeartbeatAnswer, HeartbeatRequest, HeldTask, Lease,
    LeaseRequest, LeasedJob, LeasedTask, RegisterRequest, Registration, ResultQuery, TaskKind,
};
use crate::scene::Scene;
use anyhow::{Context, Result};
use reqwest::StatusCode;
use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{OnceCell, watch};

/// A `Read` over the chunks of a streamed download, as they arrive from the async side (for a
/// blocking thread).
struct ChannelReader {
    rx: tokio::sync::mpsc::Receiver<Result<bytes::Bytes, WorkerError>>,
    chunk: bytes::Bytes,
}

impl ChannelReader {
    fn new(rx: tokio::sync::mpsc::Receiver<Result<bytes::Bytes, WorkerError>>) -> ChannelReader {
        ChannelReader {
            rx,
            chunk: bytes::Bytes::new(),
        }
    }
}

impl std::io::Read for ChannelReader {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        while self.chunk.is_empty() {
            match self.rx.blocking_recv() {
                Some(Ok(c)) => self.chunk = c,
                Some(Err(e)) => return Err(std::io::Error::other(e)),
                // The download ended.
                None => return Ok(0),
            }
        }
        let n = buf.len().min(self.chunk.len());
        buf[..n].copy_from_slice(&self.chunk[..n]);
        let _ = self.chunk.split_to(n);
        Ok(n)
    }
}

/// Runs a merge task (`film::merge_task`) of a job resolved as `resolved`: its input, fetched with
/// `input` (GET /v1/worker/tasks/{id}/input), is merged as it streams in; returns the output to
/// upload.
pub(crate) async fn run_merge(
    input: reqwest::RequestBuilder,
    resolved: &crate::job::Resolved,
) -> Result<Vec<u8>, WorkerError> {
    let mut r = input
        .timeout(Duration::from_secs(3600))
        .send()
        .await
        .map_err(WorkerError::MergeInput)?;
    if !r.status().is_success() {
        return Err(WorkerError::MergeInputStatus {
            status: r.status(),
            body: r.text().await.unwrap_or_default(),
        });
    }
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let (grid, layout) = (resolved.grid(), resolved.film_layout());
    let merging = tokio::task::spawn_blocking(move || {
        film::merge_task::run(ChannelReader::new(rx), &grid, &layout).map_err(WorkerError::from)
    });
    loop {
        let next = match r.chunk().await {
            Ok(Some(c)) => Ok(c),
            Ok(None) => break,
            Err(e) => Err(WorkerError::MergeInput(e)),
        };
        let failed = next.is_err();
        // A merge that stopped (bad input) has dropped the receiver.
        if tx.send(next).await.is_err() || failed {
            break;
        }
    }
    drop(tx);
    merging.await.map_err(WorkerError::MergePanicked)?
}

/// How a worker runs.
#[derive(Clone, Debug)]
pub(crate) struct WorkerConfig {
    /// The coordinator's URL (`http://host:port`).
    pub coordinator: String,
    /// Tasks rendered at once.
    pub threads: usize,
    /// The worker token.
    pub token: Option<String>,
    /// Shown in GET /v1/workers.
    pub name: String,
    /// Exit when the parent process goes away (local pools).
    pub exit_with_parent: bool,
    /// Where downloaded scene bundles are unpacked.
    pub cache: PathBuf,
    /// Its tags (validated): jobs that require tags go only to workers with all of them.
    pub tags: Vec<String>,
}

/// A scene loaded once for every task of its key, or why it failed (shared by those tasks).
type SceneCell = Arc<OnceCell<Result<Arc<Scene>, Arc<WorkerError>>>>;

/// Loaded scenes a worker keeps (a sequence's frames are a scene each; tasks in hand keep
/// theirs alive past a clear).
const SCENES_KEPT: usize = 8;

struct Worker {
    cfg: WorkerConfig,
    http: reqwest::Client,
    id: Mutex<String>,
    heartbeat_s: Mutex<f64>,
    /// Tasks in hand: id -> attempt.
    held: Mutex<HashMap<i64, u32>>,
    /// Tasks the coordinator says are no longer ours.
    lost: Mutex<HashSet<i64>>,
    scenes: Mutex<HashMap<(String, u32, u32), SceneCell>>,
    /// VCM: the photon maps of the latest jobs' iterations, per job id (each worker traces
    /// the light paths of the iterations it renders itself; see `integrator::vcm`).
    photons: Mutex<HashMap<String, Arc<PhotonCache>>>,
    drain: watch::Sender<bool>,
    /// Results uploaded since the drain began.
    drained_uploads: AtomicUsize,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Worker {
    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.cfg.coordinator.trim_end_matches('/'))
    }

    fn req(&self, method: reqwest::Method, path: &str) -> reqwest::RequestBuilder {
        let r = self.http.request(method, self.url(path));
        match &self.cfg.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }

    fn id(&self) -> String {
        lock(&self.id).clone()
    }

    /// Registers (keeping a previous id), retrying until the coordinator answers.
    async fn register(&self) -> Result<()> {
        let mut backoff = Duration::from_millis(200);
        loop {
            let prev = self.id();
            let body = RegisterRequest {
                name: self.cfg.name.clone(),
                threads: self.cfg.threads.min(u32::MAX as usize) as u32,
                version: env!("CARGO_PKG_VERSION").to_string(),
                id: (!prev.is_empty()).then_some(prev),
                tags: self.cfg.tags.clone(),
            };
            match self
                .req(reqwest::Method::POST, "/v1/worker/register")
                .json(&body)
                .timeout(Duration::from_secs(10))
                .send()
                .await
            {
                Ok(r) if r.status().is_success() => {
                    let v: Registration = r.json().await?;
                    *lock(&self.heartbeat_s) = v.heartbeat_seconds;
                    tracing::info!("registered as {}", v.worker_id);
                    *lock(&self.id) = v.worker_id;
                    return Ok(());
                }
                Ok(r) if r.status() == StatusCode::UNAUTHORIZED => {
                    anyhow::bail!(
                        "the coordinator refused the worker token: {}",
                        r.text().await.unwrap_or_default()
                    );
                }
                Ok(r) if r.status() == StatusCode::BAD_REQUEST => {
                    anyhow::bail!(
                        "the coordinator refused the registration: {}",
                        r.text().await.unwrap_or_default()
                    );
                }
                Ok(r) => tracing::warn!("register: HTTP {}", r.status()),
                Err(e) => tracing::warn!("register: {e}"),
            }
            if *self.drain.borrow() {
                anyhow::bail!("stopped before registering");
            }
            tokio::time::sleep(backoff).await;
            backoff = (backoff * 2).min(Duration::from_secs(5));
        }
    }

    /// The scene of a bundle at the job's resolution, loaded once.
    async fn scene(&self, job: &LeasedJob) -> Result<Arc<Scene>, Arc<WorkerError>> {
        // The same bundle with other parameter values is another scene.
        let defines = serde_json::to_string(&job.resolved.defines).unwrap_or_default();
        // The frames of a sequence share a bundle, each its own scene file.
        let key = (
            format!("{}/{}{defines}", job.scene_id, job.scene_main),
            job.resolved.width,
            job.resolved.height,
        );
        let cell = {
            let mut scenes = lock(&self.scenes);
            // A sequence's frames would otherwise keep every frame's scene loaded.
            if !scenes.contains_key(&key) && scenes.len() >= SCENES_KEPT {
                scenes.clear();
            }
            scenes.entry(key).or_default().clone()
        };
        cell.get_or_init(|| async { self.load_scene(job).await.map_err(Arc::new) })
            .await
            .clone()
    }

    /// Downloads and unpacks the bundle of `job` (unless cached) and loads its scene at the
    /// job's resolution.
    async fn load_scene(&self, job: &LeasedJob) -> Result<Arc<Scene>, WorkerError> {
        let dir = self.cfg.cache.join(&job.scene_id);
        if !dir.join(".complete").exists() {
            let r = self
                .req(
                    reqwest::Method::GET,
                    &format!("/v1/worker/scenes/{}", job.scene_id),
                )
                .send()
                .await
                .map_err(|error| WorkerError::Download {
                    scene: job.scene_id.clone(),
                    error,
                })?;
            if !r.status().is_success() {
                return Err(WorkerError::DownloadStatus {
                    scene: job.scene_id.clone(),
                    status: r.status(),
                });
            }
            let bytes = r.bytes().await.map_err(|error| WorkerError::Download {
                scene: job.scene_id.clone(),
                error,
            })?;
            let d = dir.clone();
            tokio::task::spawn_blocking(move || -> Result<(), WorkerError> {
                let _ = std::fs::remove_dir_all(&d);
                bundle::unpack(&bytes[..], &d, u64::MAX)?;
                std::fs::write(d.join(".complete"), b"")?;
                Ok(())
            })
            .await??;
        }
        let main = dir.join(&job.scene_main);
        let (w, h) = (job.resolved.width, job.resolved.height);
        let params = job.resolved.defines.clone();
        tokio::task::spawn_blocking(move || -> Result<Arc<Scene>, WorkerError> {
            let mut scene = Scene::load_with(&main, &params)?;
            if (scene.camera.width, scene.camera.height) != (w, h) {
                scene.camera = scene.camera.with_resolution(w, h)?;
            }
            Ok(Arc::new(scene))
        })
        .await?
    }

    async fn lease(&self) -> Result<Option<Lease>, reqwest::Error> {
        let r = self
            .req(reqwest::Method::POST, "/v1/worker/lease")
            .json(&LeaseRequest {
                worker_id: self.id(),
                wait_s: Some(10.0),
            })
            .timeout(Duration::from_secs(40))
            .send()
            .await?;
        match r.status() {
            StatusCode::OK => Ok(Some(r.json().await?)),
            StatusCode::NOT_FOUND => {
                tracing::warn!("the coordinator does not know this worker; registering again");
                if let Err(e) = self.register().await {
                    tracing::error!("{e:#}");
                }
                Ok(None)
            }
            s => {
                if !s.is_success() {
                    tracing::warn!("lease: HTTP {s}");
                    tokio::time::sleep(Duration::from_secs(1)).await;
                }
                Ok(None)
            }
        }
    }

    /// Uploads a result, retrying while the coordinator is unreachable (up to about a minute).
    async fn upload(&self, t: &LeasedTask, bytes: Vec<u8>) {
        let path = format!("/v1/worker/tasks/{}/result", t.id);
        let mut backoff = Duration::from_millis(200);
        for _ in 0..30 {
            if lock(&self.lost).contains(&t.id) {
                tracing::warn!("task {} was taken back; result dropped", t.id);
                return;
            }
            let r = self
                .req(reqwest::Method::PUT, &path)
                .query(&ResultQuery {
                    worker_id: self.id(),
                    attempt: t.attempt,
                })
                .header("content-type", "application/octet-stream")
                .body(bytes.clone())
                .timeout(Duration::from_secs(120))
                .send()
                .await;
            match r {
                Ok(r) if r.status().is_success() => {
                    if *self.drain.borrow() {
                        self.drained_uploads.fetch_add(1, Ordering::Relaxed);
                    }
                    return;
                }
                Ok(r) if r.status().is_client_error() => {
                    tracing::warn!(
                        "task {} (job {} pass {} tile {}) refused: HTTP {} {}",
                        t.id,
                        t.job_id,
                        t.pass,
                        t.tile,
                        r.status(),
                        r.text().await.unwrap_or_default()
                    );
                    return;
                }
                Ok(r) => tracing::warn!("upload of task {}: HTTP {}", t.id, r.status()),
                Err(e) => tracing::warn!("upload of task {}: {e}", t.id),
            }
            tokio::time::sleep(backoff).await;
            backoff = (backoff * 2).min(Duration::from_secs(3));
        }
        tracing::error!("task {}: could not upload its result; giving up", t.id);
    }

    async fn fail(&self, t: &LeasedTask, error: &str) {
        let r = self
            .req(
                reqwest::Method::POST,
                &format!("/v1/worker/tasks/{}/fail", t.id),
            )
            .json(&FailRequest {
                worker_id: self.id(),
                attempt: t.attempt,
                error: error.to_string(),
            })
            .timeout(Duration::from_secs(10))
            .send()
            .await;
        if let Err(e) = r {
            tracing::warn!("reporting the failure of task {}: {e}", t.id);
        }
    }

    /// The photon-map cache of job `job` (kept for the two latest jobs; a pass's maps at most).
    fn photon_cache(&self, job: &str, pass_len: u32) -> Arc<PhotonCache> {
        let mut caches = lock(&self.photons);
        if !caches.contains_key(job) && caches.len() >= 2 {
            caches.clear();
        }
        caches
            .entry(job.to_string())
            .or_insert_with(|| Arc::new(PhotonCache::new(pass_len as usize)))
            .clone()
    }

    /// Runs merge task `lease` (`run_merge`) with this worker's credentials.
    async fn merge(&self, lease: &Lease) -> Result<Vec<u8>, WorkerError> {
        let t = &lease.task;
        let input = self
            .req(
                reqwest::Method::GET,
                &format!("/v1/worker/tasks/{}/input", t.id),
            )
            .query(&ResultQuery {
                worker_id: self.id(),
                attempt: t.attempt,
            });
        run_merge(input, &lease.job.resolved).await
    }

    async fn run_task(&self, lease: Lease) {
        let t = &lease.task;
        lock(&self.held).insert(t.id, t.attempt);
        if t.kind == TaskKind::Merge {
            match self.merge(&lease).await {
                Ok(bytes) => self.upload(t, bytes).await,
                Err(e) => {
                    tracing::error!("merge task {}: {e}", t.id);
                    self.fail(t, &e.to_string()).await;
                }
            }
            lock(&self.held).remove(&t.id);
            lock(&self.lost).remove(&t.id);
            return;
        }
        match self.scene(&lease.job).await {
            Err(e) => {
                tracing::error!("task {}: {e}", t.id);
                self.fail(t, &e.to_string()).await;
            }
            Ok(scene) => {
                let settings = lease.job.resolved.render.clone();
                let (rect, range) = (t.rect, t.samples[0]..t.samples[1]);
                let cache = self.photon_cache(&t.job_id, lease.job.resolved.pass_len(u32::MAX));
                let grid = lease.job.resolved.grid();
                let rendered = tokio::task::spawn_blocking(move || {
                    let film = integrator::render_tile_cached(
                        &scene,
                        &settings,
                        rect,
                        range.clone(),
                        &cache,
                    );
                    film::format::encode_banded(film, range, &grid)
                })
                .await;
                match rendered {
                    Ok(bytes) => self.upload(t, bytes).await,
                    Err(e) => {
                        let msg = format!("render panicked: {e}");
                        tracing::error!("task {}: {msg}", t.id);
                        self.fail(t, &msg).await;
                    }
                }
            }
        }
        lock(&self.held).remove(&t.id);
        lock(&self.lost).remove(&t.id);
    }

    async fn slot(self: Arc<Self>) {
        let mut drain = self.drain.subscribe();
        let mut backoff = Duration::from_millis(200);
        while !*drain.borrow() {
            let lease = tokio::select! {
                l = self.lease() => l,
                _ = drain.changed() => break,
            };
            match lease {
                Ok(Some(l)) => {
                    backoff = Duration::from_millis(200);
                    self.run_task(l).await;
                }
                Ok(None) => {}
                Err(e) => {
                    tracing::warn!("lease: {e}");
                    tokio::time::sleep(backoff).await;
                    backoff = (backoff * 2).min(Duration::from_secs(5));
                }
            }
        }
    }

    async fn heartbeat(self: Arc<Self>) {
        loop {
            let every = *lock(&self.heartbeat_s);
            tokio::time::sleep(Duration::from_secs_f64(every.max(0.2))).await;
            let tasks: Vec<_> = lock(&self.held)
                .iter()
                .map(|(&id, &attempt)| HeldTask { id, attempt })
                .collect();
            let r = self
                .req(reqwest::Method::POST, "/v1/worker/heartbeat")
                .json(&HeartbeatRequest {
                    worker_id: self.id(),
                    tasks,
                })
                .timeout(Duration::from_secs(10))
                .send()
                .await;
            match r {
                Ok(r) if r.status().is_success() => {
                    if let Ok(v) = r.json::<HeartbeatAnswer>().await {
                        lock(&self.lost).extend(v.lost);
                        if v.drain && !*self.drain.borrow() {
                            let n = lock(&self.held).len();
                            tracing::info!(
                                "the coordinator asks this worker to drain: finishing the {n} \
                                 task(s) in hand, then exiting"
                            );
                            let _ = self.drain.send(true);
                        }
                    }
                }
                Ok(r) if r.status() == StatusCode::NOT_FOUND => {
                    let _ = self.register().await;
                }
                Ok(r) => tracing::warn!("heartbeat: HTTP {}", r.status()),
                Err(e) => tracing::warn!("heartbeat: {e}"),
            }
        }
    }
}

/// Runs a worker until SIGTERM / Ctrl-C (drained) or, with `exit_with_parent`, its parent's end.
pub(crate) async fn run(cfg: WorkerConfig) -> Result<()> {
    std::fs::create_dir_all(&cfg.cache)
        .with_context(|| format!("cannot create the cache folder {}", cfg.cache.display()))?;
    // A connection cut mid-request (a network partition, a coordinator host lost) is noticed
    // within seconds, not after the whole-request timeouts: idle connections are probed every
    // 2 s after 5 s of silence, and unacknowledged data closes the connection after 10 s. A
    // slow link that still acknowledges is not cut off.
    // Pooled connections are given up before the coordinator closes them as idle (its
    // --header-timeout, 10 s by default), so that no request is sent on one it is closing.
    let http = reqwest::Client::builder()
        .connect_timeout(Duration::from_secs(5))
        .pool_idle_timeout(Duration::from_secs(4))
        .tcp_keepalive(Duration::from_secs(5))
        .tcp_keepalive_interval(Duration::from_secs(2))
        .tcp_keepalive_retries(3);
    #[cfg(target_os = "linux")]
    let http = http.tcp_user_timeout(Duration::from_secs(10));
    let http = http.build().context("cannot create the HTTP client")?;
    let (drain, _) = watch::channel(false);
    let w = Arc::new(Worker {
        cfg: cfg.clone(),
        http,
        id: Mutex::new(String::new()),
        heartbeat_s: Mutex::new(5.0),
        held: Mutex::new(HashMap::new()),
        lost: Mutex::new(HashSet::new()),
        scenes: Mutex::new(HashMap::new()),
        photons: Mutex::new(HashMap::new()),
        drain,
        drained_uploads: AtomicUsize::new(0),
    });
    if cfg.exit_with_parent {
        let parent = std::os::unix::process::parent_id();
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(Duration::from_millis(300)).await;
                if std::os::unix::process::parent_id() != parent {
                    tracing::warn!("the coordinator that started this worker is gone; exiting");
                    std::process::exit(0);
                }
            }
        });
    }
    {
        let w = w.clone();
        // Installed before registering, so a SIGTERM from then on always drains.
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            .context("cannot install the SIGTERM handler")?;
        tokio::spawn(async move {
            tokio::select! {
                _ = term.recv() => {}
                _ = tokio::signal::ctrl_c() => {}
            }
            let n = lock(&w.held).len();
            tracing::info!("draining: finishing the {n} task(s) in hand");
            let _ = w.drain.send(true);
            tokio::select! {
                _ = term.recv() => {}
                _ = tokio::signal::ctrl_c() => {}
            }
            tracing::warn!("second signal: exiting now");
            std::process::exit(1);
        });
    }
    w.register().await?;
    let hb = tokio::spawn(w.clone().heartbeat());
    let slots: Vec<_> = (0..cfg.threads.max(1))
        .map(|_| tokio::spawn(w.clone().slot()))
        .collect();
    for s in slots {
        let _ = s.await;
    }
    hb.abort();
    let _ = w
        .req(reqwest::Method::POST, "/v1/worker/deregister")
        .json(&DeregisterRequest { worker_id: w.id() })
        .timeout(Duration::from_secs(5))
        .send()
        .await;
    let _ = std::fs::remove_dir_all(&cfg.cache);
    if *w.drain.borrow() {
        let n = w.drained_uploads.load(Ordering::Relaxed);
        tracing::info!("drained: {n} task result(s) finished and uploaded since the signal; bye");
    } else {
        tracing::info!("drained; bye");
    }
    Ok(())
}
