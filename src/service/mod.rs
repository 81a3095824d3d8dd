//! The render service's coordinator: jobs, tile tasks leased to workers, the
//! merge of their results pass by pass, and the REST API over it. It knows scenes only as
//! bundles and results only as accumulators: it never touches a BSDF.

pub(crate) mod accept;
pub mod api;
pub(crate) mod buffers;
pub(crate) mod error;
pub(crate) mod exr_header;
pub(crate) mod jobs;
pub(crate) mod merge;
pub(crate) mod outputs;
pub(crate) mod pool;
pub(crate) mod retention;
pub(crate) mod runtime;
pub(crate) mod server;
pub(crate) mod store;
pub(crate) mod upload;
pub(crate) mod web;
pub(crate) mod webhooks;

use crate::job::Limits;
use crate::protocol::JobEvent;
use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use store::{EventRow, JobStore, Paths, SqliteStore};
use tokio::sync::{Notify, broadcast};

/// How a coordinator runs.
#[derive(Clone, Debug)]
pub(crate) struct Config {
    /// Address to listen on (port 0: any free port).
    pub bind: SocketAddr,
    /// Begin a new database although the data folder holds jobs or scenes of an earlier one.
    pub init: bool,
    /// Folder of the database, task results and outputs.
    pub data: PathBuf,
    /// The scene library: jobs may name a scene file in this folder.
    pub library: Option<PathBuf>,
    /// Bearer token of the client routes (None: not checked; loopback only).
    pub client_token: Option<String>,
    /// Bearer token of the worker routes (None: not checked; loopback only).
    pub worker_token: Option<String>,
    /// Users of the client routes, each with its own token (`omis serve --users`); the client
    /// token, if any, stays the admin's.
    pub users: Vec<api::auth::User>,
    /// Receivers of every job's final event (`omis serve --webhook`).
    pub webhooks: Vec<store::WebhookTarget>,
    /// Local worker processes to spawn and keep alive.
    pub workers: usize,
    /// Threads (concurrent tasks) of each local worker.
    pub worker_threads: usize,
    /// Seconds a worker may stay silent before its lease is given to another.
    pub lease_s: f64,
    /// Longest long poll of a lease request, in seconds (a worker asks for at most 30).
    pub max_lease_wait_s: f64,
    /// Limits on jobs.
    pub limits: Limits,
    /// Largest request body (bundle, reference, task result).
    pub max_upload_bytes: u64,
    /// Largest JSON request body (a job with an inline scene, the worker protocol's messages).
    pub max_json_bytes: u64,
    /// Connections: the cap, timeouts, the slowest body (`server`).
    pub server: server::ServerConfig,
    /// Requests of the client routes in flight at once (an event stream counts while open).
    pub max_client_requests: usize,
    /// Requests of the worker routes in flight at once (a lease's long poll counts).
    pub max_worker_requests: usize,
    /// OMIS_LOG of local workers (None: inherit).
    pub worker_log: Option<String>,
    /// Tags of the local workers.
    pub worker_tags: Vec<String>,
    /// Tile accumulators one merge task holds at most, and the coordinator when it reads
    /// checkpoints back, in bytes.
    pub merge_memory_bytes: u64,
    /// Shortest time between two rewrites of a running job's image.exr after a pass, in
    /// seconds (the last pass's is always written; 0: after every pass). A 1080p beauty EXR
    /// costs its ZIP compression, ~0.4 CPU-seconds: a third of what a path-traced job's
    /// coordinator spent when it was written after every pass (BENCHMARKS.md, "The render service").
    pub exr_interval_s: f64,
    /// Finished jobs older than this many seconds are deleted (`retention`).
    pub keep_finished_s: Option<f64>,
    /// While the data folder holds more bytes than this, the finished jobs that ended first
    /// are deleted (`retention`).
    pub store_budget_bytes: Option<u64>,
    /// Seconds between two retention sweeps.
    pub sweep_interval_s: f64,
}

/// Bytes of free upload and merge-input buffers the coordinator keeps for reuse.
const KEPT_BUFFER_BYTES: usize = 128 << 20;
/// Uploads checked at once (`App::validations`).
pub(crate) const VALIDATIONS: usize = 2;
/// Merge outputs read and accepted at once (`App::merge_bodies`).
const MERGE_BODIES: usize = 2;

/// Default of `Config::max_json_bytes`: an inline scene of a few hundred thousand triangles.
pub const DEFAULT_MAX_JSON_BYTES: u64 = 32 << 20;

/// Default of `Config::exr_interval_s`.
pub const DEFAULT_EXR_INTERVAL_S: f64 = 30.0;

impl Config {
    /// A coordinator on `bind` keeping its state in `data`, with default limits, no tokens, no
    /// library and no local workers.
    pub fn new(bind: SocketAddr, data: PathBuf) -> Config {
        Config {
            bind,
            init: false,
            data,
            library: None,
            client_token: None,
            worker_token: None,
            users: Vec::new(),
            webhooks: Vec::new(),
            workers: 0,
            worker_threads: 1,
            lease_s: 30.0,
            max_lease_wait_s: 30.0,
            limits: Limits::default(),
            max_upload_bytes: 1 << 30,
            max_json_bytes: DEFAULT_MAX_JSON_BYTES,
            server: server::ServerConfig::default(),
            max_client_requests: 512,
            max_worker_requests: 1024,
            worker_log: None,
            worker_tags: Vec::new(),
            merge_memory_bytes: 256 << 20,
            exr_interval_s: DEFAULT_EXR_INTERVAL_S,
            keep_finished_s: None,
            store_budget_bytes: None,
            sweep_interval_s: 60.0,
        }
    }
}

/// Counters for /metrics.
#[derive(Default)]
pub(crate) struct Metrics {
    pub results_accepted: AtomicU64,
    pub results_refused: AtomicU64,
    pub result_bytes: AtomicU64,
    pub passes_merged: AtomicU64,
    pub merges_accepted: AtomicU64,
    pub merge_micros: AtomicU64,
    pub leases_expired: AtomicU64,
    pub worker_restarts: AtomicU64,
    pub http_errors: AtomicU64,
}

impl Metrics {
    pub fn add(c: &AtomicU64, v: u64) {
        c.fetch_add(v, Ordering::Relaxed);
    }
}

/// The coordinator's shared state.
pub(crate) struct App {
    pub cfg: Config,
    pub paths: Paths,
    pub store: Mutex<Box<dyn JobStore>>,
    pub events: broadcast::Sender<EventRow>,
    /// Woken when tasks may have become available.
    pub work: Notify,
    /// Per running job: the merged accumulators and what a merge needs (one merge at a time).
    pub runtimes: Mutex<HashMap<String, Arc<Mutex<runtime::Runtime>>>>,
    pub metrics: Metrics,
    /// Set when the coordinator stops: background work ends at its next chunk.
    pub stopping: AtomicBool,
    /// Jobs that recovery has not reconciled yet (after a restart).
    pub recovering: Mutex<HashSet<String>>,
    /// Jobs being advanced (`jobs::advance`), each with whether another call asked to look again.
    pub advancing: Mutex<HashMap<String, bool>>,
    /// Uploaded results decoded and stored at once: their working memory stays bounded
    /// however many workers upload together.
    pub result_slots: tokio::sync::Semaphore,
    /// Merge outputs read and accepted at once: each holds up to 1/16 of a frame's accumulators
    /// (`merge::merge_groups`), so a pass's outputs arriving together would otherwise hold the
    /// whole frame in this process; two at a time also lets their buffers be reused
    /// (`buffers`) instead of faulted in afresh.
    pub merge_bodies: tokio::sync::Semaphore,
    /// The result logs' write positions (one write at a time).
    pub result_logs: store::ResultLogs,
    /// Reused buffers for uploads and merge inputs (`buffers`).
    pub buffers: Arc<buffers::Buffers>,
    /// Client requests in flight (`Config::max_client_requests`).
    pub client_requests: Arc<tokio::sync::Semaphore>,
    /// Worker requests in flight (`Config::max_worker_requests`).
    pub worker_requests: Arc<tokio::sync::Semaphore>,
    /// The HTTP server's connection counters.
    pub server: Arc<server::ServerStats>,
    /// Uploads checked at once (a scene loaded, a reference read): each takes memory in
    /// proportion to what it checks, so their number bounds the coordinator's peak.
    pub validations: Arc<tokio::sync::Semaphore>,
    /// Woken when a webhook delivery may have been queued (`webhooks::dispatch`).
    pub deliveries: Notify,
}

impl App {
    /// Locks the store (a panic while holding it cannot leave SQLite inconsistent).
    pub fn db(&self) -> std::sync::MutexGuard<'_, Box<dyn JobStore>> {
        self.store.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A turn to check an upload (`validations`), waited for.
    pub async fn validation(&self) -> Result<tokio::sync::OwnedSemaphorePermit, api::ApiError> {
        self.validations
            .clone()
            .acquire_owned()
            .await
            .map_err(api::ApiError::internal)
    }

    /// Whether recovery has yet to reconcile job `id`.
    pub fn is_recovering(&self, id: &str) -> bool {
        self.recovering
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .contains(id)
    }

    /// Records an event and publishes it to SSE subscribers.
    pub fn event(&self, job: &str, event: JobEvent) {
        let kind = event.kind();
        let db = self.db();
        match db.add_event(job, kind, &event.data()) {
            Ok(row) => self.publish(&db, row),
            Err(e) => tracing::error!("cannot record event {kind} of job {job}: {e}"),
        }
        if kind.is_terminal() {
            // Its webhook deliveries were queued with the job's final state.
            self.deliveries.notify_one();
        }
    }

    /// Publishes a recorded event to SSE subscribers. It takes the store's lock, held since
    /// the event was recorded: events then reach subscribers in the order of their ids, which
    /// a stream relies on when it skips those it has sent (`e.id > last`).
    pub fn publish(
        &self,
        _recorded_under: &std::sync::MutexGuard<'_, Box<dyn JobStore>>,
        row: EventRow,
    ) {
        let _ = self.events.send(row);
    }
}

/// A started coordinator.
pub(crate) struct Running {
    /// `http://` and the address.
    pub url: String,
    app: Arc<App>,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    server: tokio::task::JoinHandle<()>,
    pool: Option<pool::Pool>,
}

impl Running {
    /// Stops the HTTP server and the local workers.
    pub async fn stop(mut self) {
        self.app.stopping.store(true, Ordering::Relaxed);
        if let Some(p) = self.pool.take() {
            p.stop().await;
        }
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        let _ = tokio::time::timeout(std::time::Duration::from_secs(5), &mut self.server).await;
        self.server.abort();
    }
}

fn is_loopback(addr: &SocketAddr) -> bool {
    addr.ip().is_loopback()
}

/// Opens the data folder, recovers unfinished jobs, binds and serves; spawns the local pool.
pub(crate) async fn start(cfg: Config) -> anyhow::Result<Running> {
    use anyhow::Context;
    // Results and tile accumulators are megabyte buffers freed by many threads: glibc's
    // threshold for serving them from mmap (returned to the system on free) would otherwise grow
    // with them and leave the coordinator's peak memory to arena fragmentation. Setting it fixes
    // the trim threshold at 128 KB, so every free at the top of a heap gave its pages back and
    // the next request faulted them in again; a 64 MB one keeps them (a 1080p PT job: a third
    // fewer page faults, 9 % less coordinator CPU; BENCHMARKS.md, "The render service").
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets an allocator parameter.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 64 << 20);
    }
    let client_checked = cfg.client_token.is_some() || !cfg.users.is_empty();
    if (!client_checked || cfg.worker_token.is_none()) && !is_loopback(&cfg.bind) {
        anyhow::bail!(
            "refusing to serve {} without both client tokens (--client-token or --users) and a \
             worker token (--worker-token); without tokens bind a loopback address such as \
             127.0.0.1",
            cfg.bind
        );
    }
    std::fs::create_dir_all(&cfg.data)
        .with_context(|| format!("cannot create the data folder {}", cfg.data.display()))?;
    let paths = Paths {
        root: cfg
            .data
            .canonicalize()
            .with_context(|| format!("{}", cfg.data.display()))?,
    };
    let db = paths.db();
    let db_empty = std::fs::metadata(&db).map_or(true, |m| m.len() == 0);
    if db_empty && !cfg.init && paths.holds_jobs_or_scenes() {
        anyhow::bail!(
            "the database {} is missing or empty, but {} holds the jobs and scenes of an earlier \
             one: restore the database, or start with --init to begin a new one (the jobs and \
             scenes beside it are then not recovered)",
            db.display(),
            paths.root.display()
        );
    }
    let store = SqliteStore::open(&db)
        .with_context(|| {
            format!(
                "cannot open the database {}: restore it from a backup, or move it away and \
                 start with --init",
                db.display()
            )
        })?
        .with_webhooks(cfg.webhooks.clone());
    // Leases are the workers' to renew: after a stop, they get a lease's time to report back
    // before their tasks count as lost.
    store.extend_all_leases(cfg.lease_s)?;
    let listener = tokio::net::TcpListener::bind(cfg.bind)
        .await
        .with_context(|| format!("cannot bind {}", cfg.bind))?;
    let addr = listener.local_addr()?;
    let url = format!("http://{addr}");
    let (events, _) = broadcast::channel(4096);
    let app = Arc::new(App {
        cfg: cfg.clone(),
        paths,
        store: Mutex::new(Box::new(store)),
        events,
        work: Notify::new(),
        runtimes: Mutex::new(HashMap::new()),
        metrics: Metrics::default(),
        stopping: AtomicBool::new(false),
        recovering: Mutex::new(HashSet::new()),
        advancing: Mutex::new(HashMap::new()),
        result_slots: tokio::sync::Semaphore::new(
            std::thread::available_parallelism().map_or(2, |n| n.get().max(2)),
        ),
        merge_bodies: tokio::sync::Semaphore::new(MERGE_BODIES),
        result_logs: store::ResultLogs::default(),
        buffers: Arc::new(buffers::Buffers::new(KEPT_BUFFER_BYTES)),
        client_requests: Arc::new(tokio::sync::Semaphore::new(cfg.max_client_requests.max(1))),
        worker_requests: Arc::new(tokio::sync::Semaphore::new(cfg.max_worker_requests.max(1))),
        server: Arc::new(server::ServerStats::default()),
        validations: Arc::new(tokio::sync::Semaphore::new(VALIDATIONS)),
        deliveries: Notify::new(),
    });
    if !client_checked && cfg.worker_token.is_none() {
        tracing::warn!("no tokens given: serving {addr} (loopback only) without authentication");
    }
    // Recovery runs in the background: the API answers at once, also with a large backlog.
    {
        let active = app.db().active_jobs()?;
        let mut r = app.recovering.lock().unwrap_or_else(|e| e.into_inner());
        r.extend(active.into_iter().map(|j| j.id));
    }
    tokio::spawn(jobs::recover(app.clone()));
    let router = api::router(app.clone());
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let (server_cfg, stats) = (cfg.server.clone(), app.server.clone());
    let server = tokio::spawn(async move {
        server::serve(listener, router, server_cfg, stats, async move {
            let _ = rx.await;
        })
        .await;
    });
    tokio::spawn(jobs::reaper(app.clone()));
    tokio::spawn(retention::sweeper(app.clone()));
    tokio::spawn(webhooks::dispatch(app.clone()));
    let pool = (cfg.workers > 0).then(|| pool::Pool::spawn(app.clone(), &url));
    Ok(Running {
        app,
        url,
        shutdown: Some(tx),
        server,
        pool,
    })
}
