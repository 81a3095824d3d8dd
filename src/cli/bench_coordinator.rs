//! `omis bench-coordinator`: a load generator for the coordinator alone. It renders a few real
//! task results once (per tile shape and pass length of the job's schedule), then replays them,
//! relabelled to every task of the job, from N concurrent simulated workers that upload as fast
//! as the coordinator accepts. The coordinator runs as a process of its own, so its CPU time,
//! peak memory and bytes written to storage are its own (from /proc). Worker CPU is the measured
//! render time of the recorded results, so the table also gives the coordinator's CPU as a share
//! of what real workers would have spent on the same job. The simulated workers run the passes'
//! merge tasks for real (`worker::run_merge`); their process's CPU time ("merge CPU", which also
//! holds their HTTP clients) is given as a share of the same render time.

use super::child_coordinator::ChildCoordinator;
use super::client::Client;
use super::job_args::JobArgs;
use super::service_cmds::{runtime, submit_job};
use crate::bundle;
use crate::film::Tile;
use crate::job::{Limits, Resolved};
use crate::protocol::{
    HeartbeatRequest, HeldTask, JobEvent, JobState, Lease, LeaseRequest, RegisterRequest,
    Registration, ResultQuery, SceneSource, TaskKind,
};
use crate::scene::Scene;
use anyhow::{Context, Result, bail};
use clap::Args;
use serde_json::json;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

#[derive(Args)]
pub struct BenchCoordinatorArgs {
    /// Scene file.
    pub scene: PathBuf,
    #[command(flatten)]
    pub job: JobArgs,
    /// Simulated worker counts to measure, e.g. 1,4,16,64.
    #[arg(long, value_delimiter = ',', default_value = "1,4,16,64")]
    pub simulated_workers: Vec<usize>,
    /// Real results recorded per tile shape and pass length (replayed round robin; their mean
    /// CPU time stands for the worker CPU of the job).
    #[arg(long, default_value_t = 4)]
    pub record: usize,
    /// Jobs run one after another on each coordinator (a row each): a coordinator's first job
    /// also pays for what it does once, such as the first use of its files' pages. A row's peak
    /// RSS is the coordinator's peak up to the end of that job.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100))]
    pub jobs: u32,
    /// Print one JSON object per line instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// Recorded results, by (tile width, tile height, pass length): encoded bytes (laid out by band,
/// as a worker uploads them) and the CPU seconds their render took.
type Recorded = HashMap<(u32, u32, u32), Vec<(Vec<u8>, f64)>>;

/// `per` of `tiles` (the tiles of one shape, row-major) spread over the frame in both
/// directions: rows evenly, columns by the golden ratio, so that the samples do not all fall in
/// one column (a frame's edges are often background, much cheaper to render than its middle).
fn spread(tiles: &[Tile], per: usize) -> Vec<Tile> {
    let mut rows: Vec<u32> = tiles.iter().map(|t| t.y0).collect();
    let mut cols: Vec<u32> = tiles.iter().map(|t| t.x0).collect();
    rows.sort_unstable();
    rows.dedup();
    cols.sort_unstable();
    cols.dedup();
    let phi = 0.5 * (5f64.sqrt() - 1.0);
    let mut out: Vec<Tile> = Vec::new();
    for k in 0..per.min(tiles.len()) {
        let y = rows[((k as f64 + 0.5) / per as f64 * rows.len() as f64) as usize % rows.len()];
        let x = cols[((0.5 + k as f64 * phi).fract() * cols.len() as f64) as usize];
        if let Some(t) = tiles.iter().find(|t| (t.x0, t.y0) == (x, y))
            && !out.contains(t)
        {
            out.push(*t);
        }
    }
    if out.is_empty() {
        out.extend(tiles.first());
    }
    out
}

/// Renders `per` results for every tile shape and pass length of the job, from tiles spread
/// over the frame (`spread`).
fn record(scene: &Scene, r: &Resolved, per: usize) -> Recorded {
    let grid = r.grid();
    let mut lengths: Vec<u32> = (0..r.total_passes().unwrap_or(1))
        .filter_map(|p| r.pass_range(p).map(|s| s.end - s.start))
        .collect();
    lengths.sort_unstable();
    lengths.dedup();
    let mut by_shape: HashMap<(u32, u32), Vec<Tile>> = HashMap::new();
    for t in grid.tiles() {
        by_shape
            .entry((t.width() as u32, t.height() as u32))
            .or_default()
            .push(t);
    }
    let mut out = Recorded::new();
    for ((w, h), tiles) in by_shape {
        let picked = spread(&tiles, per.max(1));
        for &len in &lengths {
            for t in &picked {
                let c0 = super::procstat::cpu_seconds(None);
                let film = crate::integrator::render_tile(scene, &r.render, *t, 0..len);
                let bytes = crate::film::format::encode_banded(film, 0..len, &grid);
                let cpu = super::procstat::cpu_seconds(None) - c0;
                out.entry((w, h, len)).or_default().push((bytes, cpu));
            }
        }
    }
    out
}

/// What the simulated workers did.
#[derive(Default)]
struct Counters {
    results: AtomicU64,
    bytes: AtomicU64,
    /// Render CPU micro-seconds the recorded results stood for.
    worker_cpu_us: AtomicU64,
    refused: AtomicU64,
    /// Merge tasks run (their work is real: see `worker::run_merge`).
    merges: AtomicU64,
    /// Bytes of merge output uploaded.
    merge_out_bytes: AtomicU64,
}

/// One simulated worker: lease, upload a recorded result at once, until `done`.
async fn simulated_worker(
    url: String,
    recorded: Arc<Recorded>,
    counters: Arc<Counters>,
    done: Arc<AtomicBool>,
    k: usize,
) -> Result<()> {
    let http = reqwest::Client::new();
    let reg: Registration = http
        .post(format!("{url}/v1/worker/register"))
        .json(&RegisterRequest {
            name: format!("simulated-{k}"),
            threads: 1,
            version: env!("CARGO_PKG_VERSION").to_string(),
            id: None,
            tags: Vec::new(),
        })
        .send()
        .await?
        .error_for_status()?
        .json()
        .await?;
    let mut turn = k;
    while !done.load(Ordering::Relaxed) {
        let r = http
            .post(format!("{url}/v1/worker/lease"))
            .json(&LeaseRequest {
                worker_id: reg.worker_id.clone(),
                wait_s: Some(0.5),
            })
            .timeout(Duration::from_secs(10))
            .send()
            .await?;
        if r.status() != reqwest::StatusCode::OK {
            continue;
        }
        let lease: Lease = r.json().await?;
        let t = &lease.task;
        // A merge task is run for real; a render task replays a recorded result.
        let (body, cpu) = if t.kind == TaskKind::Merge {
            let input = http
                .get(format!("{url}/v1/worker/tasks/{}/input", t.id))
                .query(&ResultQuery {
                    worker_id: reg.worker_id.clone(),
                    attempt: t.attempt,
                });
            // A merge takes a while: its lease is kept alive as a worker's heartbeat would.
            let beat = {
                let (http, url, worker) = (http.clone(), url.clone(), reg.worker_id.clone());
                let held = vec![HeldTask {
                    id: t.id,
                    attempt: t.attempt,
                }];
                let every = Duration::from_secs_f64(reg.heartbeat_seconds.max(0.2));
                tokio::spawn(async move {
                    loop {
                        tokio::time::sleep(every).await;
                        let _ = http
                            .post(format!("{url}/v1/worker/heartbeat"))
                            .json(&HeartbeatRequest {
                                worker_id: worker.clone(),
                                tasks: held.clone(),
                            })
                            .send()
                            .await;
                    }
                })
            };
            let out = crate::worker::run_merge(input, &lease.job.resolved).await;
            beat.abort();
            (out?, None)
        } else {
            let key = (
                t.rect.width() as u32,
                t.rect.height() as u32,
                t.samples[1] - t.samples[0],
            );
            let list = recorded
                .get(&key)
                .with_context(|| format!("no recorded result for tile shape / pass {key:?}"))?;
            turn += 1;
            let (bytes, cpu) = &list[turn % list.len()];
            let body =
                crate::film::format::relabel_banded(bytes, t.rect, t.samples[0]..t.samples[1])
                    .map_err(anyhow::Error::msg)?;
            (body, Some(*cpu))
        };
        let n = body.len() as u64;
        let r = http
            .put(format!("{url}/v1/worker/tasks/{}/result", t.id))
            .query(&ResultQuery {
                worker_id: reg.worker_id.clone(),
                attempt: t.attempt,
            })
            .header("content-type", "application/octet-stream")
            .body(body)
            .timeout(Duration::from_secs(300))
            .send()
            .await?;
        match cpu {
            _ if !r.status().is_success() => {
                counters.refused.fetch_add(1, Ordering::Relaxed);
            }
            None => {
                counters.merges.fetch_add(1, Ordering::Relaxed);
                counters.merge_out_bytes.fetch_add(n, Ordering::Relaxed);
            }
            Some(cpu) => {
                counters.results.fetch_add(1, Ordering::Relaxed);
                counters.bytes.fetch_add(n, Ordering::Relaxed);
                counters
                    .worker_cpu_us
                    .fetch_add((cpu * 1e6) as u64, Ordering::Relaxed);
            }
        }
    }
    Ok(())
}

pub fn run(a: BenchCoordinatorArgs) -> Result<()> {
    if a.simulated_workers.is_empty() || a.simulated_workers.contains(&0) {
        bail!("--simulated-workers needs counts >= 1");
    }
    let settings = a.job.settings()?;
    if settings.time_budget_s.is_some() {
        bail!("--time-budget: the replay needs a fixed number of passes (give --spp)");
    }
    let mut scene = Scene::load(&a.scene).map_err(anyhow::Error::msg)?;
    let r = settings
        .resolve(&mut scene, &Limits::default())
        .map_err(super::job_args::flag_error)?;
    let (tar, main) = bundle::pack_files(&a.scene, &scene.files)?;
    let t0 = Instant::now();
    let recorded = Arc::new(record(&scene, &r, a.record));
    let recorded_n: usize = recorded.values().map(Vec::len).sum();
    eprintln!(
        "recorded {recorded_n} results in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    let tmp = std::env::temp_dir().join(format!("omis-bench-coordinator-{}", std::process::id()));
    std::fs::create_dir_all(&tmp)?;
    let mut rows = Vec::new();
    for &n in &a.simulated_workers {
        let data = tmp.join(format!("data-{n}"));
        let server = ChildCoordinator::start(&data, 0)?;
        let (pid, url) = (server.pid, server.url.clone());
        let result = runtime()?.block_on(async {
            let c = Client::new(&url, None)?;
            let scene = SceneSource::Bundle(c.upload_bundle(tar.clone(), main.clone()).await?);
            let (rss0, _) = super::procstat::memory(Some(pid));
            let mut jobs = Vec::new();
            // Job after job on the one coordinator (`--jobs`): the first one also measures
            // what a coordinator pays once, e.g. the first use of its files' pages.
            for _ in 0..a.jobs {
                let cpu0 = super::procstat::usage(pid);
                let own0 = super::procstat::cpu_seconds(None);
                let io0 = super::procstat::write_bytes(pid);
                let counters = Arc::new(Counters::default());
                let done = Arc::new(AtomicBool::new(false));
                let t0 = Instant::now();
                let st = submit_job(&c, scene.clone(), &a.job, None, None, 0).await?;
                let workers: Vec<_> = (0..n)
                    .map(|k| {
                        tokio::spawn(simulated_worker(
                            url.clone(),
                            recorded.clone(),
                            counters.clone(),
                            done.clone(),
                            k,
                        ))
                    })
                    .collect();
                let mut last_tile = Instant::now();
                let mut latencies = Vec::new();
                let state = c
                    .follow(&st.id, |e| match e {
                        JobEvent::TileDone(_) => last_tile = Instant::now(),
                        JobEvent::PassDone(_) => latencies.push(last_tile.elapsed().as_secs_f64()),
                        _ => {}
                    })
                    .await?;
                let seconds = t0.elapsed().as_secs_f64();
                done.store(true, Ordering::Relaxed);
                for w in workers {
                    w.await??;
                }
                if state != JobState::Done {
                    bail!("the job {state}");
                }
                let used = super::procstat::usage_since(pid, cpu0);
                let own = super::procstat::cpu_seconds(None) - own0;
                let written = super::procstat::write_bytes(pid).saturating_sub(io0);
                let (_, hwm) = super::procstat::memory(Some(pid));
                jobs.push((seconds, used, own, written, hwm, latencies, counters));
            }
            Ok::<_, anyhow::Error>((rss0, jobs))
        });
        server.stop();
        let _ = std::fs::remove_dir_all(&data);
        let (rss0, jobs) = result?;
        for (j, (seconds, used, own_cpu, written, hwm, latencies, counters)) in
            jobs.into_iter().enumerate()
        {
            let cpu = used.map_or(f64::NAN, |u| u.cpu_s());
            let results = counters.results.load(Ordering::Relaxed);
            let bytes = counters.bytes.load(Ordering::Relaxed) as f64;
            let worker_cpu = counters.worker_cpu_us.load(Ordering::Relaxed) as f64 * 1e-6;
            let samples = r.width as f64 * r.height as f64 * r.spp.unwrap_or(0) as f64;
            rows.push(json!({
                "simulated_workers": n,
                "job": j + 1,
                "results": results,
                "refused": counters.refused.load(Ordering::Relaxed),
                "seconds": seconds,
                "results_per_second": results as f64 / seconds,
                "mb_per_second": bytes / 1e6 / seconds,
                "bytes_per_pixel_sample": bytes / samples.max(1.0),
                "coordinator_cpu_s": cpu,
                "coordinator_sys_s": used.map(|u| u.sys_s),
                "coordinator_minor_faults": used.map(|u| u.minor_faults),
                "coordinator_cpu_ms_per_result": cpu * 1e3 / results.max(1) as f64,
                "worker_cpu_s": worker_cpu,
                "coordinator_cpu_share": cpu / worker_cpu.max(1e-9),
                "merges": counters.merges.load(Ordering::Relaxed),
                "merge_output_bytes": counters.merge_out_bytes.load(Ordering::Relaxed),
                "simulated_workers_cpu_s": own_cpu,
                "simulated_workers_cpu_share": own_cpu / worker_cpu.max(1e-9),
                "coordinator_idle_bytes": rss0,
                "coordinator_peak_bytes": hwm,
                "disk_written_bytes": written,
                "disk_written_per_result_bytes": written as f64 / results.max(1) as f64,
                "result_bytes": bytes,
                "pass_latency_mean_s": latencies.iter().sum::<f64>()
                    / latencies.len().max(1) as f64,
                "pass_latency_max_s": latencies.iter().cloned().fold(0.0, f64::max),
                "passes": latencies.len(),
            }));
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
    if a.json {
        for r in &rows {
            println!("{r}");
        }
        return Ok(());
    }
    // The MIS heuristic only where the integrator weighs techniques by it (BDPT).
    let method = match r.render.integrator {
        crate::integrator::IntegratorKind::Bdpt => format!("BDPT, {} MIS", r.render.mis.name()),
        other => format!("{other:?}").to_lowercase(),
    };
    println!(
        "{}: {}x{}, {} spp, {method}, tiles {} ({} per pass), passes {} (first {} spp, up to {})",
        a.scene.display(),
        r.width,
        r.height,
        r.spp.unwrap_or(0),
        r.tile_size,
        r.grid().len(),
        r.total_passes().unwrap_or(0),
        r.pass_size,
        r.pass_len(u32::MAX),
    );
    println!(
        "{:>7} {:>4} {:>8} {:>7} {:>8} {:>9} {:>7} {:>9} {:>9} {:>9} {:>8} {:>9} {:>10} {:>10} {:>9} {:>9}",
        "workers",
        "job",
        "results",
        "merges",
        "seconds",
        "results/s",
        "MB/s",
        "B/sample",
        "coord CPU",
        "of it sys",
        "ms/res",
        "CPU share",
        "merge CPU",
        "peak RSS",
        "disk MB",
        "pass lat"
    );
    for row in &rows {
        let f = |k: &str| row[k].as_f64().unwrap_or(f64::NAN);
        println!(
            "{:>7} {:>4} {:>8} {:>7} {:>8.2} {:>9.1} {:>7.1} {:>9.1} {:>8.2}s {:>8.2}s {:>8.2} {:>8.2}% {:>9.2}% {:>7.0}MB {:>9.1} {:>8.3}s",
            row["simulated_workers"],
            row["job"],
            row["results"],
            row["merges"],
            f("seconds"),
            f("results_per_second"),
            f("mb_per_second"),
            f("bytes_per_pixel_sample"),
            f("coordinator_cpu_s"),
            f("coordinator_sys_s"),
            f("coordinator_cpu_ms_per_result"),
            100.0 * f("coordinator_cpu_share"),
            100.0 * f("simulated_workers_cpu_share"),
            f("coordinator_peak_bytes") / 1e6,
            f("disk_written_bytes") / 1e6,
            f("pass_latency_mean_s"),
        );
    }
    Ok(())
}
