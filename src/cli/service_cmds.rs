//! `omis serve`, `omis worker`, and the clients `submit`, `status`, `download`, `cancel`.

use super::client::{self, Client};
use super::job_args::JobArgs;
use crate::job::Limits;
use crate::job::frames::FrameRange;
use crate::protocol::{JobEvent, JobRequest, JobState, JobStatus, ReferenceSource, SceneSource};
use crate::service;
use crate::worker;
use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
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
    /// Scene library: jobs may name a scene file of this folder.
    #[arg(long, default_value = "scenes")]
    pub scenes: PathBuf,
    /// Bearer token clients must send.
    #[arg(long, env = "OMIS_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    #[arg(long)]
    pub token_file: Option<PathBuf>,
    /// Bearer token workers must send.
    #[arg(long, env = "OMIS_WORKER_TOKEN", hide_env_values = true)]
    pub worker_token: Option<String>,
    #[arg(long)]
    pub worker_token_file: Option<PathBuf>,
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
}

pub(crate) fn serve(a: ServeArgs) -> Result<()> {
    init_logging();
    if !(a.lease_seconds >= 1.0 && a.lease_seconds.is_finite()) {
        bail!("--lease-seconds must be >= 1");
    }
    let mut cfg = service::Config::new(a.bind, a.data.clone());
    cfg.init = a.init;
    cfg.library = a.scenes.is_dir().then(|| a.scenes.clone());
    cfg.client_token = token(&a.token, &a.token_file, "--token-file")?;
    cfg.worker_token = token(&a.worker_token, &a.worker_token_file, "--worker-token-file")?;
    cfg.workers = a.workers;
    cfg.worker_threads = a.worker_threads.max(1);
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
    #[arg(long, env = "OMIS_WORKER_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    #[arg(long)]
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
}

pub(crate) fn worker(a: WorkerArgs) -> Result<()> {
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
        token: token(&a.token, &a.token_file, "--token-file")?,
        name: a
            .name
            .unwrap_or_else(|| format!("{host}-{}", std::process::id())),
        exit_with_parent: a.exit_with_parent,
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
    /// Client bearer token.
    #[arg(long, env = "OMIS_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    #[arg(long)]
    pub token_file: Option<PathBuf>,
}

impl ServerArgs {
    fn client(&self) -> Result<Client> {
        Client::new(
            &self.server,
            token(&self.token, &self.token_file, "--token-file")?,
        )
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
    /// Wait until the job ends, with a progress bar.
    #[arg(long)]
    pub wait: bool,
    /// With --wait: download the EXR here (a sequence: a pattern out_####.exr, or a folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
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
) -> Result<JobStatus> {
    submit_frames(c, scene, job, reference, name, None).await
}

/// Builds a job request, a sequence of `frames` when given, and submits it; returns the job's
/// status document.
pub(crate) async fn submit_frames(
    c: &Client,
    scene: SceneSource,
    job: &JobArgs,
    reference: Option<&std::path::Path>,
    name: Option<&str>,
    frames: Option<FrameRange>,
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
        frames,
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
    let total = status.passes_total.map(|p| p as u64 * tiles);
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(total.unwrap_or(0))
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} tiles {msg} {eta}",
        )
        .expect("valid template"),
    );
    let state = c
        .follow(id, |e| match e {
            JobEvent::TileDone(_) => bar.inc(1),
            JobEvent::PassDone(p) => {
                let spp = p.spp;
                match p.relmse {
                    Some(r) => bar.set_message(format!("{spp} spp, relMSE {r:.3e}")),
                    None => bar.set_message(format!("{spp} spp")),
                }
                if total.is_none() {
                    bar.set_length(bar.position());
                }
            }
            _ => {}
        })
        .await?;
    bar.finish_and_clear();
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
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(frames)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} frames {eta}",
        )
        .expect("valid template"),
    );
    loop {
        let st = c.status(&status.id).await?;
        let ended = st
            .frames
            .as_deref()
            .unwrap_or_default()
            .iter()
            .filter(|f| !f.state.is_active())
            .count();
        bar.set_position(ended as u64);
        if !st.state.is_active() {
            bar.finish_and_clear();
            return Ok(st.state);
        }
        tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    }
}

pub(crate) fn submit(a: SubmitArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let c = a.server.client()?;
        let defines = a.job.settings()?.defines;
        let scene = match a.frames {
            Some(frames) => SceneSource::Bundle(
                c.upload_frames(std::path::Path::new(&a.scene), frames, &defines)
                    .await?,
            ),
            None => client::scene_source(&c, &a.scene, &defines).await?,
        };
        let st = submit_frames(
            &c,
            scene,
            &a.job,
            a.reference.as_deref(),
            a.name.as_deref(),
            a.frames,
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

pub(crate) fn status(a: IdArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let st = a.server.client()?.status(&a.id).await?;
        println!("{}", serde_json::to_string_pretty(&st)?);
        Ok(())
    })
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
        let n = c.download(&a.id, &a.file, &a.out).await?;
        eprintln!("{}: {n} bytes", a.out.display());
        Ok(())
    })
}
