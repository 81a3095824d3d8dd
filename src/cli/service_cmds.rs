//! `omis serve`, `omis worker`, and the clients `submit`, `download`, `cancel` (the job
//! controls and `status` are in `job_cmds.rs`).

use super::client::{self, Client};
use super::job_args::JobArgs;
use super::progress::RenderProgress;
use crate::job::Limits;
use crate::job::frames::FrameRange;
use crate::protocol::{
    JobEvent, JobRequest, JobState, JobStatus, ReferenceSource, SceneSource, WebhookSpec,
    validate_tags,
};
use crate::service;
use crate::worker;
use anyhow::{Context, Result, bail};
use clap::Args;
use std::net::SocketAddr;
use std::path::PathBuf;

/// A token given directly, or read from a file (first line).
fn token(direct: &Option<String>, file: &Option<PathBuf>, what: &str) -> Result<Option<String>> {
    if let Some(t) = direct.as_ref().filter(|t| !t.is_empty()) {
        return Ok(Some(t.clone()));
    }
    match file {
        Some(f) => {
            let text = std::fs::read_to_string(f)
                .with_context(|| format!("{what} file {}", f.display()))?;
            let t = text.lines().next().unwrap_or("").trim().to_string();
            if t.is_empty() {
                bail!("{what} file {} is empty", f.display());
            }
            Ok(Some(t))
        }
        None => Ok(None),
    }
}

/// The client token of `serve` and the client commands: `--client-token`,
/// `--client-token-file` or OMIS_CLIENT_TOKEN, else the deprecated `--token`, `--token-file` or
/// OMIS_TOKEN (each with a warning on stderr).
fn client_token(a: &ClientTokenArgs) -> Result<Option<String>> {
    if let Some(t) = token(&a.client_token, &a.client_token_file, "--client-token-file")? {
        return Ok(Some(t));
    }
    if a.token.is_some() || a.token_file.is_some() {
        eprintln!(
            "warning: --token and --token-file are deprecated: use --client-token and \
             --client-token-file"
        );
        return token(&a.token, &a.token_file, "--token-file");
    }
    match std::env::var("OMIS_TOKEN") {
        Ok(t) if !t.is_empty() => {
            eprintln!("warning: OMIS_TOKEN is deprecated: use OMIS_CLIENT_TOKEN");
            Ok(Some(t))
        }
        _ => Ok(None),
    }
}

/// The client token's flags, shared by `serve` (the token clients must send) and the client
/// commands (the token they send).
#[derive(Args, Clone)]
pub(crate) struct ClientTokenArgs {
    /// The client bearer token (a user named "admin" of role admin).
    #[arg(long, env = "OMIS_CLIENT_TOKEN", hide_env_values = true)]
    pub client_token: Option<String>,
    /// The client token, as the first line of this file.
    #[arg(long)]
    pub client_token_file: Option<PathBuf>,
    /// Deprecated: --client-token.
    #[arg(long, hide = true, conflicts_with = "client_token")]
    pub token: Option<String>,
    /// Deprecated: --client-token-file.
    #[arg(long, hide = true, conflicts_with = "client_token_file")]
    pub token_file: Option<PathBuf>,
}

/// The users of `omis serve --users FILE`.
fn read_users(path: &std::path::Path) -> Result<Vec<service::api::auth::User>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("--users {}", path.display()))?;
    service::api::auth::parse_users(&text)
        .map_err(|e| anyhow::anyhow!("--users {}: {e}", path.display()))
}

/// The receivers of `--webhook` (of `serve`: every job's; of `submit`: the job's), all signed
/// with the secret of `--webhook-secret-file` (if given).
fn global_webhooks(
    urls: &[String],
    secret_file: &Option<PathBuf>,
) -> Result<Vec<service::store::WebhookTarget>> {
    let secret = token(&None, secret_file, "--webhook-secret-file")?;
    if let Some(s) = &secret {
        service::webhooks::check_secret(s)
            .map_err(|e| anyhow::anyhow!("--webhook-secret-file: {e}"))?;
    }
    if secret.is_some() && urls.is_empty() {
        bail!("--webhook-secret-file signs the --webhook receivers: give at least one --webhook");
    }
    urls.iter()
        .map(|u| {
            service::webhooks::check_url(u).map_err(|e| anyhow::anyhow!("--webhook {u}: {e}"))?;
            Ok(service::store::WebhookTarget {
                url: u.clone(),
                secret: secret.clone(),
            })
        })
        .collect()
}

pub(crate) fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")
}

pub(crate) fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_env("OMIS_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        // Colour codes only where a terminal shows them, not in redirected logs.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
}

#[derive(Args)]
pub(crate) struct ServeArgs {
    /// Address to listen on (port 0 = any free port; the address is printed).
    #[arg(long, default_value = "127.0.0.1:8570")]
    pub bind: SocketAddr,
    /// Folder for the database, task results and outputs (created if missing).
    #[arg(long)]
    pub data: PathBuf,
    /// Begin a new, empty database although the data folder holds the jobs and scenes of an
    /// earlier one (whose database is missing or empty); they are not recovered. Without it
    /// the coordinator refuses to start there.
    #[arg(long)]
    pub init: bool,
    /// Local worker processes to start and keep alive.
    #[arg(long, default_value_t = 0)]
    pub workers: usize,
    /// Threads (concurrent tasks) of each local worker.
    #[arg(long, default_value_t = 1)]
    pub worker_threads: usize,
    /// Tags of the local workers (repeatable, or a comma-separated list).
    #[arg(long = "tag", value_name = "TAG", value_delimiter = ',')]
    pub tags: Vec<String>,
    /// Scene library: jobs may name a scene file of this folder.
    #[arg(long, default_value = "scenes")]
    pub scenes: PathBuf,
    // The token clients must send.
    #[command(flatten)]
    pub client: ClientTokenArgs,
    /// Bearer token workers must send.
    #[arg(long, env = "OMIS_WORKER_TOKEN", hide_env_values = true)]
    pub worker_token: Option<String>,
    /// The worker token, as the first line of this file.
    #[arg(long)]
    pub worker_token_file: Option<PathBuf>,
    /// Users of the client routes, each with its own token: a JSON file
    /// `[{"name": "ana", "role": "admin"|"user", "token": "..."}]` ("token_sha256", the hex
    /// SHA-256 of the token, instead of "token" keeps secrets out of the file). A user may act
    /// on its own jobs, an admin on every job.
    #[arg(long)]
    pub users: Option<PathBuf>,
    /// A receiver of every job's final event (done, failed, cancelled), POSTed as JSON; may be
    /// given several times. http:// only.
    #[arg(long = "webhook")]
    pub webhooks: Vec<String>,
    /// Signs the bodies POSTed to the --webhook receivers with this file's first line
    /// (X-Omis-Signature: sha256=<hex HMAC-SHA256>).
    #[arg(long)]
    pub webhook_secret_file: Option<PathBuf>,
    /// Seconds a worker may stay silent before its task is given to another.
    #[arg(long, default_value_t = 30.0)]
    pub lease_seconds: f64,
    /// Longest wait of a worker's lease request for a task, in seconds (at most 30).
    #[arg(long, default_value_t = 30.0)]
    pub max_lease_wait: f64,
    /// Largest width or height of a job.
    #[arg(long, default_value_t = 8192)]
    pub max_resolution: u32,
    #[arg(long, default_value_t = 65536)]
    pub max_spp: u32,
    #[arg(long, default_value_t = 20_000_000)]
    pub max_triangles: usize,
    /// Most tiles of a frame, i.e. tasks of one pass (the database holds a row per task).
    #[arg(long, default_value_t = 65536)]
    pub max_tasks_per_pass: u32,
    /// Largest upload (scene bundle, reference, task result) in MiB.
    #[arg(long, default_value_t = 1024)]
    pub max_upload_mb: u64,
    /// Largest JSON body (a job with its scene inline, the worker protocol's messages) in MiB.
    #[arg(long, default_value_t = service::DEFAULT_MAX_JSON_BYTES >> 20)]
    pub max_json_mb: u64,
    /// Most open connections; at the cap the oldest idle one is closed for a new one, or the
    /// new one is answered 503 when none is idle. Lowered to fit the limit on open files.
    #[arg(long, default_value_t = 2048)]
    pub max_connections: usize,
    /// Client requests in flight at once (an event stream counts while open); more get 503.
    #[arg(long, default_value_t = 512)]
    pub max_client_requests: usize,
    /// Worker requests in flight at once (a lease's long poll counts); more get 503.
    #[arg(long, default_value_t = 1024)]
    pub max_worker_requests: usize,
    /// Seconds a client has to send a request's headers, and to send its next request on a
    /// kept-alive connection, before the connection is closed.
    #[arg(long, default_value_t = 10.0)]
    pub header_timeout: f64,
    /// Slowest request body, in bytes per second on average, once --body-grace has passed;
    /// a slower one is cut off with 400.
    #[arg(long, default_value_t = 4096)]
    pub body_min_rate: u64,
    /// Seconds a request body may take before --body-min-rate applies.
    #[arg(long, default_value_t = 10.0)]
    pub body_grace: f64,
    /// Tile accumulators one merge task holds in memory, in MiB, whatever the size of the frame
    /// (workers merge a pass band group by band group; the coordinator reads groups back with
    /// at most this much in all after a restart and for a time-budget job's final EXR).
    #[arg(long, default_value_t = 256)]
    pub merge_memory_mb: u64,
    /// Shortest time between two rewrites of a running job's image.exr (its beauty,
    /// uncompressed) after a pass, in seconds (the preview is rewritten after every pass, the
    /// final EXR always written; 0: the EXR after every pass too).
    #[arg(long, default_value_t = service::DEFAULT_EXR_INTERVAL_S)]
    pub exr_interval: f64,
    /// Delete finished (done, failed, cancelled) jobs, with their files, this many days after
    /// they ended (fractions allowed).
    #[arg(long, value_name = "DAYS")]
    pub keep_finished: Option<f64>,
    /// While the data folder holds more than this (e.g. 20G, 512M), delete the finished jobs
    /// that ended first, with their files.
    #[arg(long, value_name = "SIZE")]
    pub store_budget: Option<String>,
    /// Seconds between two sweeps of --keep-finished and --store-budget.
    #[arg(long, default_value_t = 60.0, hide = true)]
    pub sweep_interval: f64,
}

pub(crate) fn serve(a: ServeArgs) -> Result<()> {
    init_logging();
    if !(a.lease_seconds >= 1.0 && a.lease_seconds.is_finite()) {
        bail!("--lease-seconds must be >= 1");
    }
    let mut cfg = service::Config::new(a.bind, a.data.clone());
    cfg.init = a.init;
    cfg.library = a.scenes.is_dir().then(|| a.scenes.clone());
    cfg.client_token = client_token(&a.client)?;
    cfg.worker_token = token(&a.worker_token, &a.worker_token_file, "--worker-token-file")?;
    if let Some(path) = &a.users {
        cfg.users = read_users(path)?;
    }
    cfg.webhooks = global_webhooks(&a.webhooks, &a.webhook_secret_file)?;
    cfg.workers = a.workers;
    cfg.worker_threads = a.worker_threads.max(1);
    cfg.worker_tags = validate_tags(&a.tags).map_err(|e| anyhow::anyhow!("--tag: {e}"))?;
    cfg.lease_s = a.lease_seconds;
    if !(0.0..=30.0).contains(&a.max_lease_wait) {
        bail!("--max-lease-wait must be within 0 ..= 30 seconds");
    }
    cfg.max_lease_wait_s = a.max_lease_wait;
    cfg.limits = Limits {
        max_resolution: a.max_resolution,
        max_spp: a.max_spp,
        max_triangles: a.max_triangles,
        max_tasks_per_pass: a.max_tasks_per_pass.max(1),
        ..Limits::default()
    };
    cfg.max_upload_bytes = a.max_upload_mb.saturating_mul(1 << 20);
    cfg.max_json_bytes = a.max_json_mb.max(1).saturating_mul(1 << 20);
    let seconds = |v: f64, flag: &str| -> Result<std::time::Duration> {
        if !(v > 0.0 && v <= 3600.0) {
            bail!("{flag} must be a number of seconds within (0, 3600]");
        }
        Ok(std::time::Duration::from_secs_f64(v))
    };
    cfg.server = service::server::ServerConfig {
        max_connections: a.max_connections.max(1),
        header_timeout: seconds(a.header_timeout, "--header-timeout")?,
        body_min_rate: a.body_min_rate.max(1),
        body_grace: seconds(a.body_grace, "--body-grace")?,
    };
    if a.max_client_requests == 0 || a.max_worker_requests == 0 {
        bail!("--max-client-requests and --max-worker-requests must be >= 1");
    }
    cfg.max_client_requests = a.max_client_requests;
    cfg.max_worker_requests = a.max_worker_requests;
    if a.merge_memory_mb == 0 {
        bail!("--merge-memory-mb must be >= 1");
    }
    cfg.merge_memory_bytes = a.merge_memory_mb.saturating_mul(1 << 20);
    if !(a.exr_interval >= 0.0 && a.exr_interval.is_finite()) {
        bail!("--exr-interval must be a finite number of seconds >= 0");
    }
    cfg.exr_interval_s = a.exr_interval;
    if let Some(days) = a.keep_finished {
        if !(days >= 0.0 && days.is_finite()) {
            bail!("--keep-finished must be a number of days >= 0");
        }
        cfg.keep_finished_s = Some(days * 86400.0);
    }
    if let Some(size) = &a.store_budget {
        cfg.store_budget_bytes = Some(
            service::retention::parse_size(size)
                .map_err(|e| anyhow::anyhow!("--store-budget: {e}"))?,
        );
    }
    if !(a.sweep_interval > 0.0 && a.sweep_interval.is_finite()) {
        bail!("--sweep-interval must be a number of seconds > 0");
    }
    cfg.sweep_interval_s = a.sweep_interval;
    let rt = runtime()?;
    let result = rt.block_on(async move {
        let running = service::start(cfg).await?;
        // The first line of stdout is the address (scripts and tests read it).
        println!("listening on {}", running.url);
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        tokio::select! {
            _ = term.recv() => {}
            _ = tokio::signal::ctrl_c() => {}
        }
        tracing::info!("stopping: draining local workers");
        running.stop().await;
        Ok(())
    });
    // Background work (task creation, merges) stops at its next chunk; never wait forever.
    rt.shutdown_timeout(std::time::Duration::from_secs(10));
    result
}

#[derive(Args)]
pub(crate) struct WorkerArgs {
    /// The coordinator's URL, e.g. http://render-host:8570.
    #[arg(long, env = "OMIS_COORDINATOR")]
    pub coordinator: String,
    /// Tasks rendered at once (0 = number of cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// The worker token (the coordinator's --worker-token).
    #[arg(long, env = "OMIS_WORKER_TOKEN", hide_env_values = true)]
    pub worker_token: Option<String>,
    /// The worker token, as the first line of this file.
    #[arg(long)]
    pub worker_token_file: Option<PathBuf>,
    /// Gone (it read as the client token): refused with the new name.
    #[arg(long, hide = true)]
    pub token: Option<String>,
    /// Gone: refused with the new name.
    #[arg(long, hide = true)]
    pub token_file: Option<PathBuf>,
    /// Name shown in GET /v1/workers (default: host name and pid).
    #[arg(long)]
    pub name: Option<String>,
    /// Folder for downloaded scenes (default: a temporary folder, removed on exit).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Exit when the parent process ends (used by local pools).
    #[arg(long, hide = true)]
    pub exit_with_parent: bool,
    /// Tags of this worker (repeatable, or a comma-separated list; a-z, 0-9, '_', '-'): a job
    /// that requires tags goes only to workers with every one of them.
    #[arg(long = "tag", value_name = "TAG", value_delimiter = ',')]
    pub tags: Vec<String>,
}

pub(crate) fn worker(a: WorkerArgs) -> Result<()> {
    if a.token.is_some() || a.token_file.is_some() {
        bail!(
            "omis worker: --token and --token-file are gone (they meant the worker token, \
             unlike everywhere else): use --worker-token or --worker-token-file"
        );
    }
    init_logging();
    let threads = if a.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        a.threads
    };
    let host = std::fs::read_to_string("/etc/hostname")
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|_| "worker".into());
    let cfg = worker::WorkerConfig {
        coordinator: a.coordinator.trim_end_matches('/').to_string(),
        threads,
        token: token(&a.worker_token, &a.worker_token_file, "--worker-token-file")?,
        name: a
            .name
            .unwrap_or_else(|| format!("{host}-{}", std::process::id())),
        exit_with_parent: a.exit_with_parent,
        tags: validate_tags(&a.tags).map_err(|e| anyhow::anyhow!("--tag: {e}"))?,
        cache: a.cache.unwrap_or_else(|| {
            std::env::temp_dir().join(format!("omis-worker-{}", std::process::id()))
        }),
    };
    client::check_url(&cfg.coordinator, "--coordinator")?;
    runtime()?.block_on(worker::run(cfg))
}

#[derive(Args, Clone)]
pub(crate) struct ServerArgs {
    /// The coordinator's URL.
    #[arg(long, env = "OMIS_SERVER", default_value = "http://127.0.0.1:8570")]
    pub server: String,
    // The client bearer token (the coordinator's --client-token, or a --users token).
    #[command(flatten)]
    pub token: ClientTokenArgs,
}

impl ServerArgs {
    pub(crate) fn client(&self) -> Result<Client> {
        Client::new(&self.server, client_token(&self.token)?)
    }
}

#[derive(Args)]
pub(crate) struct SubmitArgs {
    /// A scene file (uploaded with the files it reads) or the name of a library scene; with
    /// --frames, a frame pattern (frame_####.xml: a run of '#' where the zero-padded frame
    /// number goes).
    pub scene: String,
    /// Render a sequence: these frames of the pattern SCENE (FIRST-LAST or FIRST-LAST:STEP),
    /// every frame file and what it reads packed into one bundle.
    #[arg(long, value_name = "FIRST-LAST")]
    pub frames: Option<FrameRange>,
    #[command(flatten)]
    pub job: JobArgs,
    /// Reference EXR: the job reports relMSE per pass and an error map.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// A name for the job.
    #[arg(long)]
    pub name: Option<String>,
    /// The job's priority: workers take the tasks of higher ones first (default 0).
    #[arg(long, default_value_t = 0, allow_hyphen_values = true)]
    pub priority: i32,
    /// Wait until the job ends, with a progress bar.
    #[arg(long)]
    pub wait: bool,
    /// With --wait: download the EXR here (a sequence: a pattern out_####.exr, or a folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// A receiver of the job's final event (done, failed, cancelled), POSTed as JSON; may be
    /// given several times. http:// only.
    #[arg(long = "webhook")]
    pub webhooks: Vec<String>,
    /// Signs the bodies POSTed to this job's --webhook receivers with this file's first line.
    #[arg(long)]
    pub webhook_secret_file: Option<PathBuf>,
    #[command(flatten)]
    pub server: ServerArgs,
}

/// Builds a job request and submits it; returns the job's status document.
pub(crate) async fn submit_job(
    c: &Client,
    scene: SceneSource,
    job: &JobArgs,
    reference: Option<&std::path::Path>,
    name: Option<&str>,
    priority: i32,
) -> Result<JobStatus> {
    let extras = JobExtras {
        priority,
        ..JobExtras::default()
    };
    submit_request(c, scene, job, reference, name, extras).await
}

/// What a job request may carry beyond its scene, settings, reference and name.
#[derive(Default)]
pub(crate) struct JobExtras {
    /// Higher first in the lease order.
    pub priority: i32,
    /// The job's own receivers of its final event.
    pub webhooks: Vec<WebhookSpec>,
    /// A sequence: its frames.
    pub frames: Option<FrameRange>,
}

/// Builds a job request (a sequence when `extras` has frames) and submits it; returns the
/// job's status document.
pub(crate) async fn submit_request(
    c: &Client,
    scene: SceneSource,
    job: &JobArgs,
    reference: Option<&std::path::Path>,
    name: Option<&str>,
    extras: JobExtras,
) -> Result<JobStatus> {
    let settings = job.settings()?;
    let reference = match reference {
        Some(r) => Some(ReferenceSource::Upload(c.upload_reference(r).await?)),
        None => None,
    };
    let req = JobRequest {
        scene,
        settings,
        reference,
        name: name.map(str::to_string),
        priority: extras.priority,
        require_tags: validate_tags(&job.require_tags)
            .map_err(|e| anyhow::anyhow!("--require-tag: {e}"))?,
        webhooks: extras.webhooks,
        frames: extras.frames,
    };
    c.submit(&req).await
}

/// Follows a job with a progress bar over its tiles; returns its final state.
pub(crate) async fn wait_job(c: &Client, status: &JobStatus, quiet: bool) -> Result<JobState> {
    if let Some(frames) = &status.frames {
        return wait_sequence(c, status, frames.len() as u64, quiet).await;
    }
    let id = &status.id;
    let tiles = status.tiles_per_pass as u64;
    let bar = RenderProgress::new(
        status.passes_total.map(|p| p as u64 * tiles),
        status.time_budget_s,
        status.elapsed_s,
        quiet,
    );
    let state = c
        .follow(id, |e| match e {
            JobEvent::TileDone(_) => bar.tiles_done(1),
            JobEvent::PassDone(p) => bar.pass_done(p.spp, p.relmse),
            _ => {}
        })
        .await?;
    bar.finish();
    Ok(state)
}

/// Follows a sequence with a progress bar over its frames (its status, twice a second); returns
/// its final state.
async fn wait_sequence(
    c: &Client,
    status: &JobStatus,
    frames: u64,
    quiet: bool,
) -> Result<JobState> {
    let bar = RenderProgress::frames(frames, quiet);
    loop {
        let st = c.status(&status.id).await?;
        let ended = st
            .frames
            .as_deref()
            .unwrap_or_default()
            .iter()
            .filter(|f| !f.state.is_active())
            .count();
        bar.frames_ended(ended as u64);
        if !st.state.is_active() {
            bar.finish();
            return Ok(st.state);
        }
        tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    }
}

pub(crate) fn submit(a: SubmitArgs) -> Result<()> {
    runtime()?.block_on(async move {
        // A sequence's --out is a folder or a frame pattern, written frame by frame.
        if let Some(out) = &a.out
            && a.frames.is_none()
        {
            super::out_path::check_writable(out, "--out")?;
        }
        let c = a.server.client()?;
        let webhooks = global_webhooks(&a.webhooks, &a.webhook_secret_file)?
            .into_iter()
            .map(|t| WebhookSpec {
                url: t.url,
                secret: t.secret,
            })
            .collect();
        let defines = a.job.settings()?.defines;
        let scene = match a.frames {
            Some(frames) => SceneSource::Bundle(
                c.upload_frames(std::path::Path::new(&a.scene), frames, &defines)
                    .await?,
            ),
            None => client::scene_source(&c, &a.scene, &defines).await?,
        };
        let extras = JobExtras {
            priority: a.priority,
            webhooks,
            frames: a.frames,
        };
        let st = submit_request(
            &c,
            scene,
            &a.job,
            a.reference.as_deref(),
            a.name.as_deref(),
            extras,
        )
        .await?;
        let id = st.id.clone();
        if !a.wait {
            println!("{id}");
            return Ok(());
        }
        eprintln!("job {id}");
        let state = wait_job(&c, &st, false).await?;
        let st = c.status(&id).await?;
        if state != JobState::Done {
            bail!(
                "job {id} {state}: {}",
                st.error.as_deref().unwrap_or("no error given")
            );
        }
        if let Some(out) = &a.out {
            if st.frames.is_some() {
                for f in c.download_frames(&st, "image.exr", out).await? {
                    eprintln!("{}", f.display());
                }
            } else {
                c.download(&id, "image.exr", out).await?;
                eprintln!("{}", out.display());
            }
        }
        println!("{}", serde_json::to_string(&st)?);
        Ok(())
    })
}

#[derive(Args)]
pub(crate) struct IdArgs {
    /// The job id.
    pub id: String,
    #[command(flatten)]
    pub server: ServerArgs,
}

pub(crate) fn cancel(a: IdArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let st = a.server.client()?.cancel(&a.id).await?;
        println!("{}", st.state);
        Ok(())
    })
}

#[derive(Args)]
pub(crate) struct DownloadArgs {
    /// The job id.
    pub id: String,
    /// Where to write the file (a sequence's EXRs or previews: a pattern out_####.exr, or a
    /// folder, one file per frame).
    #[arg(long)]
    pub out: PathBuf,
    /// Which file: image.exr, preview.png, error.png or convergence.svg.
    #[arg(long, default_value = "image.exr")]
    pub file: String,
    #[command(flatten)]
    pub server: ServerArgs,
}

pub(crate) fn download(a: DownloadArgs) -> Result<()> {
    if !matches!(
        a.file.as_str(),
        "image.exr" | "preview.png" | "error.png" | "convergence.svg"
    ) {
        bail!(
            "--file '{}' is not one of image.exr, preview.png, error.png, convergence.svg",
            a.file
        );
    }
    runtime()?.block_on(async move {
        let c = a.server.client()?;
        let st = c.status(&a.id).await?;
        if st.frames.is_some() && matches!(a.file.as_str(), "image.exr" | "preview.png") {
            for f in c.download_frames(&st, &a.file, &a.out).await? {
                eprintln!("{}", f.display());
            }
            return Ok(());
        }
        super::out_path::check_writable(&a.out, "--out")?;
        let n = c.download(&a.id, &a.file, &a.out).await?;
        eprintln!("{}: {n} bytes", a.out.display());
        Ok(())
    })
}
