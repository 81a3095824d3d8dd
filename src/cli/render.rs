//! `omis render`: load a scene, render it, write EXR / PNG, print a summary.

use crate::film::{exr_io, metrics, png};
use crate::integrator::path::DirectStrategy;
use crate::integrator::{self, IntegratorKind, MisKind, RenderSettings};
use crate::sampler::SamplerKind;
use crate::scene::Scene;
use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

#[derive(Args)]
pub struct RenderArgs {
    /// Scene file (.json).
    pub scene: PathBuf,
    /// Samples per pixel (default: the scene's, else 16).
    #[arg(long)]
    pub spp: Option<u32>,
    /// Maximum path depth in bounces: 0 = emitters seen directly, 1 = direct light (default: the
    /// scene's, else 5).
    #[arg(long)]
    pub max_depth: Option<u32>,
    #[arg(long, value_enum, default_value_t = IntegratorKind::Pt)]
    pub integrator: IntegratorKind,
    /// BDPT technique weights.
    #[arg(long, value_enum, default_value_t = MisKind::Balance)]
    pub mis: MisKind,
    /// BDPT: write the weighted contribution of every (s, t) up to depth 3 as EXR layers
    /// `s<S>_t<T>`.
    #[arg(long)]
    pub strategies: bool,
    /// Optimal MIS: weight depths 1..=D optimally, balance above.
    #[arg(long, default_value_t = 5)]
    pub optimal_max_depth: u32,
    /// Optimal MIS: regularisation toward the balance solution (0 = the seed's direct estimator).
    #[arg(long, default_value_t = integrator::DEFAULT_KAPPA)]
    pub kappa: f64,
    #[arg(long, value_enum, default_value_t = SamplerKind::Sobol)]
    pub sampler: SamplerKind,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Path tracer: how emitters are reached. `light` / `bsdf` use one strategy alone (for
    /// validation; both are unbiased, BSDF sampling cannot see point lights).
    #[arg(long, value_enum, default_value_t = DirectStrategy::Mis)]
    pub direct: DirectStrategy,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Override the scene's resolution, e.g. 256x256 (the vertical field of view is kept).
    #[arg(long)]
    pub resolution: Option<String>,
    /// Output EXR (default: <scene name>.exr in the current folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Also write an sRGB PNG preview.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Reference EXR: report relMSE against it.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// eps of relMSE = mean (I - R)^2 / (R^2 + eps).
    #[arg(long, default_value_t = 0.01)]
    pub eps: f64,
    /// Tile edge in pixels.
    #[arg(long, default_value_t = 16)]
    pub tile_size: u32,
    /// Print a JSON summary as the last line of stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: RenderArgs) -> Result<()> {
    let mut scene = Scene::load(&a.scene).map_err(anyhow::Error::msg)?;
    for w in &scene.warnings {
        eprintln!("omis: warning: {w}");
    }
    if let Some(r) = &a.resolution {
        let (w, h) = super::parse_resolution(r).map_err(anyhow::Error::msg)?;
        scene.camera = scene
            .camera
            .with_resolution(w, h)
            .map_err(anyhow::Error::msg)?;
    }
    let spp = a.spp.or(scene.defaults.spp).unwrap_or(16);
    if spp == 0 {
        bail!("--spp must be >= 1");
    }
    if a.tile_size == 0 {
        bail!("--tile-size must be >= 1");
    }
    let reference = match &a.reference {
        Some(p) => {
            let r = exr_io::read_exr(p).map_err(anyhow::Error::msg)?;
            if r.width != scene.camera.width as usize || r.height != scene.camera.height as usize {
                bail!(
                    "reference {} is {}x{}, the render is {}x{}",
                    p.display(),
                    r.width,
                    r.height,
                    scene.camera.width,
                    scene.camera.height
                );
            }
            Some(r)
        }
        None => None,
    };
    let settings = RenderSettings {
        integrator: a.integrator,
        spp,
        max_depth: a.max_depth.or(scene.defaults.max_depth).unwrap_or(5),
        seed: a.seed,
        sampler: a.sampler,
        direct: a.direct,
        mis: a.mis,
        strategies: a.strategies,
        optimal_max_depth: a.optimal_max_depth,
        optimal_kappa: a.kappa,
        ..Default::default()
    };
    if a.mis == MisKind::Optimal && settings.integrator != IntegratorKind::Bdpt {
        bail!("--mis optimal needs --integrator bdpt");
    }
    if a.optimal_max_depth > crate::mis::optimal::MAX_OPTIMAL_DEPTH {
        bail!(
            "--optimal-max-depth {} exceeds {}",
            a.optimal_max_depth,
            crate::mis::optimal::MAX_OPTIMAL_DEPTH
        );
    }
    if !(a.kappa >= 0.0 && a.kappa.is_finite()) {
        bail!("--kappa must be a finite number >= 0");
    }
    if settings.max_depth > integrator::bdpt::MAX_DEPTH
        && settings.integrator == IntegratorKind::Bdpt
    {
        bail!(
            "--max-depth {} exceeds the BDPT limit of {}",
            settings.max_depth,
            integrator::bdpt::MAX_DEPTH
        );
    }
    let out = a.out.clone().unwrap_or_else(|| {
        let stem = a
            .scene
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "render".into());
        PathBuf::from(format!("{stem}.exr"))
    });

    let pool = super::thread_pool(a.threads)?;
    let tasks = integrator::task_count(
        scene.camera.width,
        scene.camera.height,
        a.tile_size,
        settings.spp,
    );
    let bar = ProgressBar::new(tasks as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} tiles {eta}",
        )
        .expect("valid template"),
    );
    let output =
        pool.install(|| integrator::render(&scene, &settings, a.tile_size, &|n| bar.inc(n as u64)));
    bar.finish_and_clear();

    let image = output.image();
    let mut layers: Vec<(String, crate::film::Image)> = Vec::new();
    if settings.integrator == IntegratorKind::Pt {
        // Per-pixel variance of the mean (BDPT's light-tracing splats have no per-pixel samples).
        layers.push(("variance".into(), output.sums().variance_of_mean()));
    }
    layers.extend(output.frame.strategy_images());
    let attrs = [
        ("omis.scene", a.scene.display().to_string()),
        (
            "omis.integrator",
            format!("{:?}", settings.integrator).to_lowercase(),
        ),
        ("omis.spp", settings.spp.to_string()),
        ("omis.max_depth", settings.max_depth.to_string()),
        ("omis.seed", settings.seed.to_string()),
    ];
    let named: Vec<exr_io::NamedLayer> = layers
        .iter()
        .map(|(name, image)| exr_io::NamedLayer {
            name: name.clone(),
            image,
        })
        .collect();
    exr_io::write_exr(&out, &image, &named, &attrs).map_err(anyhow::Error::msg)?;
    if let Some(p) = &a.png {
        png::write_png(p, &image, 0.0).map_err(anyhow::Error::msg)?;
    }

    let secs = output.seconds.max(1e-9);
    let st = &output.stats;
    let mean = image.mean();
    let err = match &reference {
        Some(r) => Some(metrics::compare(&image, r, a.eps).map_err(anyhow::Error::msg)?),
        None => None,
    };
    let threads = pool.current_num_threads();
    eprintln!(
        "{}: {}x{} {} spp, max depth {}, {} threads: {:.3} s, {:.0} pixel samples/s, {:.2} Mrays/s ({} closest, {} shadow){}",
        out.display(),
        scene.camera.width,
        scene.camera.height,
        settings.spp,
        settings.max_depth,
        threads,
        secs,
        st.samples as f64 / secs,
        st.rays() as f64 / secs / 1e6,
        st.closest,
        st.shadow,
        match &err {
            Some(e) => format!(", relMSE {:.6e} (eps {})", e.relmse, e.eps),
            None => String::new(),
        }
    );
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
            "width": scene.camera.width,
            "height": scene.camera.height,
            "integrator": settings.integrator,
            "mis": settings.mis,
            "sampler": settings.sampler,
            "spp": settings.spp,
            "max_depth": settings.max_depth,
            "seed": settings.seed,
            "threads": threads,
            "seconds": secs,
            "pixel_samples_per_second": st.samples as f64 / secs,
            "rays_per_second": st.rays() as f64 / secs,
            "closest_rays": st.closest,
            "shadow_rays": st.shadow,
            "mean_rgb": mean,
            "non_finite_samples": st.non_finite,
        });
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
