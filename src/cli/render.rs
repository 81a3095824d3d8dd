//! `omis render`: render a scene to an EXR (and a PNG) and print a summary. By default through
//! the render service: an embedded coordinator on a free loopback port with a temporary store
//! and local worker processes; `--in-process` renders in this process with the same tasks and
//! merge order (the same image).

use super::client::Client;
use super::job_args::JobArgs;
use super::progress::RenderProgress;
use super::service_cmds::{JobExtras, init_logging, runtime, submit_job, submit_request, wait_job};
use crate::film::RayStats;
use crate::film::image::{Image, exr_io, metrics, png};
use crate::job::optimal_depth::DepthChoice;
use crate::job::{JobSettings, Limits, Resolved};
use crate::protocol::{JobState, SceneSource};
use crate::scene::Scene;
use crate::service;
use crate::service::exr_header;
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};

#[derive(Args)]
pub struct RenderArgs {
    /// Scene file (.json, .pbrt or .xml); with --frames, a frame pattern (frame_####.xml: a
    /// run of '#' where the zero-padded frame number goes).
    pub scene: PathBuf,
    /// Render a sequence through the service: these frames of the pattern SCENE (FIRST-LAST
    /// or FIRST-LAST:STEP), one EXR per frame (--out: a pattern out_####.exr or a folder;
    /// default <pattern's name>.exr with its run of '#').
    #[arg(long, value_name = "FIRST-LAST", conflicts_with_all = ["in_process", "reference", "png"])]
    pub frames: Option<crate::job::frames::FrameRange>,
    #[command(flatten)]
    pub job: JobArgs,
    /// Threads (0 = all cores): rayon threads in-process, else the number of local worker
    /// processes unless --workers is given.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Local worker processes of the embedded service (default: --threads, else the cores).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Render in this process instead of through the embedded service.
    #[arg(long)]
    pub in_process: bool,
    /// Output EXR (default: <scene name>.exr in the current folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Also write an sRGB PNG preview.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Reference EXR: report relMSE against it.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Print a JSON summary as the last line of stdout.
    #[arg(long)]
    pub json: bool,
}

/// What a render did, for the summary.
struct Done {
    image: Image,
    stats: RayStats,
    seconds: f64,
    spp: u32,
    threads: usize,
    mode: String,
    bytes_per_pixel: usize,
    /// Optimal MIS: the D_opt rendered with, and the pilot's choice when it chose.
    optimal: Option<(u32, Option<DepthChoice>)>,
}

fn read_reference(p: &Path, r: &Resolved) -> Result<Image> {
    exr_header::check_cli(p)?;
    let img = exr_io::read_exr(p).map_err(anyhow::Error::msg)?;
    if img.width != r.width as usize || img.height != r.height as usize {
        bail!(
            "reference {} is {}x{}, the render is {}x{}",
            p.display(),
            img.width,
            img.height,
            r.width,
            r.height
        );
    }
    Ok(img)
}

fn cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

pub fn run(a: RenderArgs) -> Result<()> {
    if let Some(frames) = a.frames {
        return sequence(&a, frames);
    }
    let settings = a.job.settings()?;
    let mut scene = Scene::load_with(&a.scene, &settings.defines).map_err(anyhow::Error::msg)?;
    for w in &scene.warnings {
        eprintln!("omis: warning: {w}");
    }
    // Through the service the coordinator resolves the job (and runs the D_opt pilot); this
    // copy only checks the settings against the scene and sizes the reference.
    let local = if a.in_process {
        settings.clone()
    } else {
        JobSettings {
            optimal_max_depth: Some(settings.optimal_max_depth.unwrap_or(0)),
            ..settings.clone()
        }
    };
    let resolved = local
        .resolve(&mut scene, &Limits::default())
        .map_err(super::job_args::flag_error)?;
    let reference = match &a.reference {
        Some(p) => Some(read_reference(p, &resolved)?),
        None => None,
    };
    let out = a.out.clone().unwrap_or_else(|| {
        let stem = a
            .scene
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "render".into());
        PathBuf::from(format!("{stem}.exr"))
    });
    super::out_path::check_writable(&out, "--out")?;
    if let Some(p) = &a.png {
        super::out_path::check_writable(p, "--png")?;
    }
    let done = if a.in_process {
        in_process(&a, &scene, &resolved, &out)?
    } else {
        let (tar, main) = crate::bundle::pack_files(&a.scene, &scene.files)?;
        drop(scene);
        through_service(&a, (tar, main), &out)?
    };
    summary(&a, &resolved, &out, &done, reference.as_ref())
}

fn in_process(a: &RenderArgs, scene: &Scene, r: &Resolved, out: &Path) -> Result<Done> {
    let pool = super::thread_pool(a.threads)?;
    let tiles = r.tiles().len() as u64;
    let bar = RenderProgress::new(
        r.total_passes().map(|p| p as u64 * tiles),
        r.time_budget_s,
        0.0,
        false,
    );
    let output = pool.install(|| r.render_in_process(scene, &|n| bar.tiles_done(n as u64)));
    let spp = output.spp;
    bar.finish();
    let scene_name = a
        .scene
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let image = output
        .film
        .write_exr(
            out,
            &r.exr_attributes(&scene_name, spp),
            exr_io::block_lines(r.tile_size),
        )
        .map_err(anyhow::Error::msg)?;
    if let Some(p) = &a.png {
        png::write_png(p, &image, 0.0).map_err(anyhow::Error::msg)?;
    }
    Ok(Done {
        image,
        stats: output.stats,
        seconds: output.seconds,
        spp,
        threads: pool.current_num_threads(),
        mode: "in-process".into(),
        bytes_per_pixel: r.film_layout().bytes_per_pixel(),
        optimal: r.optimal_max_depth().map(|d| (d, r.optimal_depth.clone())),
    })
}

fn through_service(a: &RenderArgs, (tar, main): (Vec<u8>, String), out: &Path) -> Result<Done> {
    let ((st, seconds), workers) = with_embedded_service(a, async |c| {
        let start = std::time::Instant::now();
        let scene = SceneSource::Bundle(c.upload_bundle(tar, main).await?);
        let st = submit_job(c, scene, &a.job, a.reference.as_deref(), None, 0).await?;
        let st = finish(c, &st).await?;
        c.download(&st.id, "image.exr", out).await?;
        if let Some(p) = &a.png {
            c.download(&st.id, "preview.png", p).await?;
        }
        Ok((st, start.elapsed().as_secs_f64()))
    })?;
    let image = exr_io::read_exr(out).map_err(anyhow::Error::msg)?;
    Ok(Done {
        image,
        stats: RayStats {
            closest: st.rays.max(0) as u64,
            shadow: 0,
            samples: st.samples.max(0) as u64,
            non_finite: st.non_finite_samples.max(0) as u64,
        },
        seconds,
        spp: st.spp_done,
        threads: workers,
        mode: format!("{workers} worker processes"),
        bytes_per_pixel: st.accum_bytes_per_pixel.max(0) as usize,
        optimal: st.optimal_max_depth.map(|d| (d, st.optimal_depth.clone())),
    })
}

/// `omis render --frames`: the sequence through the embedded service, one EXR per frame.
fn sequence(a: &RenderArgs, frames: crate::job::frames::FrameRange) -> Result<()> {
    let settings = a.job.settings()?;
    let (tar, main) = super::bundle::sequence(&a.scene, frames, &settings.defines)?;
    let out = match &a.out {
        Some(o) => o.clone(),
        None => PathBuf::from(
            Path::new(&main)
                .with_extension("exr")
                .to_string_lossy()
                .into_owned(),
        ),
    };
    let ((st, written), _) = with_embedded_service(a, async |c| {
        let scene = SceneSource::Bundle(c.upload_bundle(tar, main).await?);
        let extras = JobExtras {
            frames: Some(frames),
            ..JobExtras::default()
        };
        let st = submit_request(c, scene, &a.job, None, None, extras).await?;
        let st = finish(c, &st).await?;
        let written = c.download_frames(&st, "image.exr", &out).await?;
        Ok((st, written))
    })?;
    for w in &written {
        eprintln!("{}", w.display());
    }
    if a.json {
        println!("{}", serde_json::to_string(&st)?);
    }
    Ok(())
}

/// Runs `body` against an embedded coordinator with local worker processes (`--workers`, by
/// default one per thread; they carry the job's required tags) in a temporary data folder,
/// stopped and removed after; returns its answer and the number of workers.
fn with_embedded_service<T>(
    a: &RenderArgs,
    body: impl AsyncFnOnce(&Client) -> Result<T>,
) -> Result<(T, usize)> {
    let workers = a
        .workers
        .unwrap_or(if a.threads > 0 { a.threads } else { cores() })
        .max(1);
    if std::env::var_os("OMIS_LOG").is_some() {
        init_logging();
    }
    let data = std::env::temp_dir().join(format!("omis-render-{}", uuid::Uuid::new_v4()));
    let result = runtime()?.block_on(async {
        let mut cfg =
            service::Config::new("127.0.0.1:0".parse().expect("valid address"), data.clone());
        cfg.workers = workers;
        cfg.worker_threads = 1;
        // The local workers serve the job, whatever tags it requires.
        cfg.worker_tags = crate::protocol::validate_tags(&a.job.require_tags)
            .map_err(|e| anyhow::anyhow!("--require-tag: {e}"))?;
        cfg.lease_s = 30.0;
        if std::env::var_os("OMIS_LOG").is_none() {
            cfg.worker_log = Some("warn".into());
        }
        let running = service::start(cfg).await?;
        let result = match Client::new(&running.url, None) {
            Ok(c) => body(&c).await,
            Err(e) => Err(e),
        };
        running.stop().await;
        result
    });
    let _ = std::fs::remove_dir_all(&data);
    Ok((result?, workers))
}

/// Follows job `st` to its end; its final status, or an error unless it is done.
async fn finish(c: &Client, st: &crate::protocol::JobStatus) -> Result<crate::protocol::JobStatus> {
    let state = wait_job(c, st, false).await?;
    let st = c.status(&st.id).await?;
    if state != JobState::Done {
        bail!(
            "the render {state}: {}",
            st.error.as_deref().unwrap_or("no error given")
        );
    }
    Ok(st)
}

fn summary(
    a: &RenderArgs,
    r: &Resolved,
    out: &Path,
    d: &Done,
    reference: Option<&Image>,
) -> Result<()> {
    let secs = d.seconds.max(1e-9);
    let st = &d.stats;
    let mean = d.image.mean();
    let err = match reference {
        Some(img) => Some(metrics::compare(&d.image, img, r.eps).map_err(anyhow::Error::msg)?),
        None => None,
    };
    eprintln!(
        "{}: {}x{} {} spp, max depth {}, {}: {:.3} s, {:.0} pixel samples/s, {:.2} Mrays/s, \
         accumulators {} bytes/pixel{}",
        out.display(),
        r.width,
        r.height,
        d.spp,
        r.render.max_depth,
        d.mode,
        secs,
        st.samples as f64 / secs,
        st.rays() as f64 / secs / 1e6,
        d.bytes_per_pixel,
        match &err {
            Some(e) => format!(", relMSE {:.6e} (eps {})", e.relmse, e.eps),
            None => String::new(),
        }
    );
    if let Some((d_opt, choice)) = &d.optimal {
        match choice {
            Some(c) => eprintln!("optimal MIS: {}", c.summary()),
            None => eprintln!("optimal MIS: D_opt {d_opt} (--optimal-max-depth)"),
        }
    }
    if st.non_finite > 0 {
        eprintln!(
            "omis: warning: {} samples were NaN or infinite and were dropped",
            st.non_finite
        );
    }
    if a.json {
        let mut j = serde_json::json!({
            "scene": a.scene.display().to_string(),
            "out": out.display().to_string(),
            "width": r.width,
            "height": r.height,
            "integrator": r.render.integrator,
            "mis": r.render.mis,
            "sampler": r.render.sampler,
            "spp": d.spp,
            "max_depth": r.render.max_depth,
            "seed": r.render.seed,
            "threads": d.threads,
            "mode": d.mode,
            "seconds": secs,
            "pixel_samples_per_second": st.samples as f64 / secs,
            "rays_per_second": st.rays() as f64 / secs,
            "rays": st.rays(),
            "accumulator_bytes_per_pixel": d.bytes_per_pixel,
            "mean_rgb": mean,
            "non_finite_samples": st.non_finite,
        });
        if let Some((d_opt, choice)) = &d.optimal {
            j["optimal_max_depth"] = serde_json::json!(d_opt);
            j["optimal_depth"] = serde_json::json!(choice);
        }
        if a.in_process {
            j["closest_rays"] = serde_json::json!(st.closest);
            j["shadow_rays"] = serde_json::json!(st.shadow);
        }
        if let Some(e) = err {
            j["relmse"] = serde_json::json!(e.relmse);
            j["mse"] = serde_json::json!(e.mse);
            j["eps"] = serde_json::json!(e.eps);
        }
        println!(
            "{}",
            serde_json::to_string(&j).context("serialising summary")?
        );
    }
    Ok(())
}
