//! `omis bench-service`: the render service measured against the in-process render of the same
//! job: wall time, CPU time (coordinator and its workers together, and the coordinator alone,
//! with its kernel time and minor page faults) and throughput with 1, 2, ... local worker
//! processes, bytes shipped per pixel sample, coordinator memory per megapixel, pass latency
//! (last tile of a pass in, pass merged and solved), and whether the images are equal.

use super::child_coordinator::ChildCoordinator;
use super::client::Client;
use super::job_args::JobArgs;
use super::service_cmds::{runtime, submit_job};
use crate::bundle;
use crate::film::image::exr_io;
use crate::job::Limits;
use crate::protocol::{JobEvent, JobState, SceneSource, WorkerList};
use crate::scene::Scene;
use anyhow::{Result, bail};
use clap::Args;
use serde_json::json;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
pub struct BenchServiceArgs {
    /// Scene file.
    pub scene: PathBuf,
    #[command(flatten)]
    pub job: JobArgs,
    /// Worker process counts to measure, e.g. 1,2,4.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    pub workers: Vec<usize>,
    /// Print one JSON object per line instead of the table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: BenchServiceArgs) -> Result<()> {
    if a.workers.is_empty() || a.workers.contains(&0) {
        bail!("--workers needs counts >= 1");
    }
    let settings = a.job.settings()?;
    let mut scene = Scene::load(&a.scene).map_err(anyhow::Error::msg)?;
    let r = settings
        .resolve(&mut scene, &Limits::default())
        .map_err(super::job_args::flag_error)?;
    let (tar, main) = bundle::pack_files(&a.scene, &scene.files)?;
    let megapixels = (r.width as f64 * r.height as f64) / 1e6;
    let tmp = std::env::temp_dir().join(format!("omis-bench-service-{}", std::process::id()));
    std::fs::create_dir_all(&tmp)?;
    let mut rows = Vec::new();
    let mut images = Vec::new();
    for &n in &a.workers {
        let data = tmp.join(format!("data-{n}"));
        let out = tmp.join(format!("svc-{n}.exr"));
        // The coordinator is a process of its own, so its memory is measured alone.
        let server = ChildCoordinator::start(&data, n)?;
        let (pid, url) = (server.pid, server.url.clone());
        let (rss0, _) = super::procstat::memory(Some(pid));
        let result = runtime()?.block_on(async {
            // Let the workers start and register before the clock starts.
            let c = Client::new(&url, None)?;
            for _ in 0..200 {
                let v: WorkerList = reqwest::get(format!("{url}/v1/workers"))
                    .await?
                    .json()
                    .await?;
                if v.workers.len() >= n {
                    break;
                }
                tokio::time::sleep(std::time::Duration::from_millis(50)).await;
            }
            let t0 = Instant::now();
            let (cpu0, coord0) = (
                super::procstat::cpu_seconds_with_children(pid),
                super::procstat::usage(pid),
            );
            let scene = SceneSource::Bundle(c.upload_bundle(tar.clone(), main.clone()).await?);
            let st = submit_job(&c, scene, &a.job, None, None, 0).await?;
            let id = st.id.clone();
            let mut last_tile = Instant::now();
            let mut latencies = Vec::new();
            let state = c
                .follow(&id, |e| match e {
                    JobEvent::TileDone(_) => last_tile = Instant::now(),
                    JobEvent::PassDone(_) => latencies.push(last_tile.elapsed().as_secs_f64()),
                    _ => {}
                })
                .await?;
            let seconds = t0.elapsed().as_secs_f64();
            let cpu = super::procstat::cpu_seconds_with_children(pid) - cpu0;
            let coordinator = super::procstat::usage_since(pid, coord0);
            if state != JobState::Done {
                bail!("the job {state}");
            }
            let st = c.status(&id).await?;
            c.download(&id, "image.exr", &out).await?;
            Ok::<_, anyhow::Error>(((st, seconds, cpu, coordinator), latencies))
        });
        let (_, hwm) = super::procstat::memory(Some(pid));
        server.stop();
        let (row, passes) = result?;
        let (st, seconds, cpu, coordinator) = row;
        let samples = st.samples as f64;
        let bytes = st.result_bytes as f64;
        let mean_latency = passes.iter().sum::<f64>() / passes.len().max(1) as f64;
        images.push(exr_io::read_exr(&out).map_err(anyhow::Error::msg)?);
        rows.push(json!({
            "mode": format!("{n} workers"),
            "workers": n,
            "seconds": seconds,
            "cpu_s": cpu,
            "coordinator_cpu_s": coordinator.map(|u| u.cpu_s()),
            "coordinator_sys_s": coordinator.map(|u| u.sys_s),
            "coordinator_minor_faults": coordinator.map(|u| u.minor_faults),
            "pixel_samples_per_second": samples / seconds,
            "bytes_per_pixel_sample": bytes / samples.max(1.0),
            "result_bytes": bytes,
            "coordinator_idle_bytes": rss0,
            "coordinator_peak_bytes": hwm,
            "coordinator_peak_bytes_per_megapixel": hwm.saturating_sub(rss0) as f64 / megapixels,
            "pass_latency_s": mean_latency,
            "passes": passes.len(),
        }));
        let _ = std::fs::remove_dir_all(&data);
    }
    // The in-process render of the same job, on as many threads as the largest pool.
    let threads = *a.workers.iter().max().unwrap_or(&1);
    let pool = super::thread_pool(threads)?;
    let t0 = Instant::now();
    let cpu0 = super::procstat::cpu_seconds(None);
    let output = pool.install(|| r.render_in_process(&scene, &|_| {}));
    let seconds = t0.elapsed().as_secs_f64();
    let cpu = super::procstat::cpu_seconds(None) - cpu0;
    let reference = output.image();
    rows.push(json!({
        "mode": format!("in-process, {threads} threads"),
        "workers": 0,
        "seconds": seconds,
        "cpu_s": cpu,
        "pixel_samples_per_second": output.stats.samples as f64 / seconds,
    }));
    for (k, img) in images.iter().enumerate() {
        let equal = img.pixels == reference.pixels;
        rows[k]["equal_to_in_process"] = json!(equal);
    }
    let _ = std::fs::remove_dir_all(&tmp);
    if a.json {
        for r in &rows {
            println!("{r}");
        }
        return Ok(());
    }
    println!(
        "{}: {}x{}, {} spp, tiles {}, pass {} spp",
        a.scene.display(),
        r.width,
        r.height,
        r.spp.unwrap_or(0),
        r.tile_size,
        r.pass_size
    );
    println!(
        "{:<22} {:>9} {:>9} {:>10} {:>10} {:>14} {:>12} {:>14} {:>10} {:>6}",
        "mode",
        "seconds",
        "CPU s",
        "coord CPU",
        "of it sys",
        "samples/s",
        "B/sample",
        "coord MB/Mpx",
        "pass lat",
        "equal"
    );
    for row in &rows {
        let f = |k: &str| row[k].as_f64();
        println!(
            "{:<22} {:>9.3} {:>9.2} {:>10} {:>10} {:>14.0} {:>12} {:>14} {:>10} {:>6}",
            row["mode"].as_str().unwrap_or(""),
            f("seconds").unwrap_or(0.0),
            f("cpu_s").unwrap_or(f64::NAN),
            f("coordinator_cpu_s").map_or("-".into(), |v| format!("{v:.2}")),
            f("coordinator_sys_s").map_or("-".into(), |v| format!("{v:.2}")),
            f("pixel_samples_per_second").unwrap_or(0.0),
            f("bytes_per_pixel_sample").map_or("-".into(), |v| format!("{v:.1}")),
            f("coordinator_peak_bytes_per_megapixel")
                .map_or("-".into(), |v| format!("{:.1}", v / 1e6)),
            f("pass_latency_s").map_or("-".into(), |v| format!("{:.3} s", v)),
            row["equal_to_in_process"]
                .as_bool()
                .map_or("-".into(), |b| b.to_string()),
        );
    }
    Ok(())
}
