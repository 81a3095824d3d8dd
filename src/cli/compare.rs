//! `omis compare`: MIS strategies at equal sample counts (and optionally equal time) against a
//! reference: relMSE table, relMSE-vs-spp plot, gain per path depth, time and memory overhead
//! (the experiments of Cailleau et al., "Optimal Multiple Importance Sampling for
//! Bidirectional Path Tracing", Figs. 5, 7, 8, 9, 10).

use super::choices::{MisArg, OptimalDepthArg, SamplerArg};
use crate::film::image::{Image, exr_io, metrics, plot};
use crate::integrator::{IntegratorKind, RenderSettings};
use crate::job::optimal_depth::{self, DepthChoice};
use crate::job::{RenderOutput, Resolved};
use crate::mis::MisKind;
use crate::scene::Scene;
use crate::service::exr_header;
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};

#[derive(Args)]
pub struct CompareArgs {
    pub scene: PathBuf,
    /// Sample counts, comma separated.
    #[arg(long, default_value = "1,2,4,8,16,64,256", value_delimiter = ',')]
    pub spp: Vec<u32>,
    /// MIS strategies, comma separated (balance, power, optimal, optimal-progressive).
    #[arg(long, default_value = "balance,power,optimal", value_delimiter = ',')]
    pub mis: Vec<MisArg>,
    /// Converged reference EXR (its resolution is the render's). Layers named depth0, depth1,
    /// ... (from `omis render --depth-layers`) enable per-depth relMSE.
    #[arg(long)]
    pub reference: PathBuf,
    /// Also run each strategy for this many seconds (per seed) and compare relMSE at equal time.
    #[arg(long)]
    pub equal_time: Option<f64>,
    /// With --equal-time: count the budget in CPU seconds of this process (every thread of the
    /// pool) instead of wall seconds, for a loaded machine where wall time measures the load.
    #[arg(long)]
    pub cpu_time: bool,
    /// Output folder for plots and results.json.
    #[arg(long, default_value = "compare-out")]
    pub out: PathBuf,
    /// Independent seeds averaged per point.
    #[arg(long, default_value_t = 3)]
    pub seeds: u64,
    #[arg(long, default_value_t = 5)]
    pub max_depth: u32,
    /// Optimal MIS: weight depths 1..=D optimally; `auto`: every optimal render chooses with
    /// its own pilot, as `omis render` does (sized by the render's spp or time budget), and
    /// pays for it: the pilot's time is in the render's times and in its equal-time budget.
    #[arg(long, default_value_t = OptimalDepthArg(None))]
    pub optimal_max_depth: OptimalDepthArg,
    #[arg(long, default_value_t = crate::mis::DEFAULT_KAPPA)]
    pub kappa: f64,
    /// Sample generator (`omis render` defaults to sobol; this to independent samples).
    #[arg(long, value_enum, default_value_t = SamplerArg::Independent)]
    pub sampler: SamplerArg,
    #[arg(long, default_value_t = 0.01)]
    pub eps: f64,
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Also run the path tracer (power-heuristic NEE) as a baseline.
    #[arg(long)]
    pub pt: bool,
    /// BDPT: subpaths end by Russian roulette from their N-th vertex on (1 = the first surface
    /// hit). Default: `omis render`'s (3).
    #[arg(long, value_name = "N", conflicts_with = "no_roulette")]
    pub roulette_from: Option<u32>,
    /// BDPT: no Russian roulette (subpaths run to the max depth).
    #[arg(long)]
    pub no_roulette: bool,
    /// Print the results as one JSON object (last line of stdout).
    #[arg(long)]
    pub json: bool,
}

/// A rendering method: BDPT with a weighting, or the path tracer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
enum Method {
    Bdpt(MisKind),
    Pt,
}

impl Method {
    fn name(&self) -> String {
        match self {
            Method::Bdpt(m) => m.name().into(),
            Method::Pt => "pt".into(),
        }
    }
}

/// Tiles of the comparison renders.
const TILE_SIZE: u32 = 16;
/// Passes start at one sample and double up to this many at equal spp (the progressive
/// estimator weights each pass with what the passes before it solved).
const MAX_PASS_SIZE: u32 = 64;
/// The same at equal time, where a pass past the budget is wasted.
const MAX_TIMED_PASS_SIZE: u32 = 4;

const BALANCE: Method = Method::Bdpt(MisKind::Balance);
const OPTIMAL: Method = Method::Bdpt(MisKind::Optimal);

#[derive(serde::Serialize, Clone)]
struct Point {
    #[serde(serialize_with = "ser_method")]
    method: Method,
    spp: u32,
    /// relMSE averaged over seeds, and its standard deviation across seeds.
    relmse: f64,
    relmse_sd: f64,
    /// relMSE without the 0.1% worst pixels, averaged over seeds.
    relmse_trimmed: f64,
    /// Wall seconds per render.
    seconds: f64,
    /// CPU seconds per render (every thread of the pool).
    cpu_seconds: f64,
    bytes_per_pixel: usize,
    /// relMSE of each depth 0 ..= max_depth (against reference depth layers, or the relative
    /// variance across seeds when the reference has none).
    relmse_per_depth: Vec<f64>,
    /// Per seed, what the render's pilot chose (`--optimal-max-depth auto`; empty otherwise).
    optimal_depth: Vec<DepthChoice>,
    /// CPU seconds per render of its pilot (part of `cpu_seconds`).
    pilot_cpu_seconds: f64,
}

fn ser_method<S: serde::Serializer>(m: &Method, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&m.name())
}

/// One render of a comparison, reduced to its errors and costs.
struct Rendered {
    relmse: f64,
    relmse_trimmed: f64,
    seconds: f64,
    cpu: f64,
    spp: u32,
    bytes_per_pixel: usize,
    /// Per depth: its relMSE against the reference's depth layer, or its image when the
    /// reference has none (the point then takes the relative variance across seeds).
    depths: Vec<DepthError>,
    /// The render's pilot, where it ran one (its times are in `seconds` and `cpu`).
    pilot: Option<Pilot>,
}

/// A pilot render that chose a render's D_opt, and what it cost.
struct Pilot {
    choice: DepthChoice,
    /// Wall and CPU seconds.
    seconds: f64,
    cpu: f64,
    /// Seconds on the clock of the render's time budget.
    on_clock: f64,
}

/// One render of a comparison, as it ran.
struct Run {
    out: RenderOutput,
    cpu: f64,
    pilot: Option<Pilot>,
}

enum DepthError {
    Against(f64),
    Image(Image),
}

fn mean_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = if v.len() > 1 {
        v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    (m, var.sqrt())
}

/// Relative variance across renders of the same settings: mean over pixels and channels of
/// var_k(I_k) / (mean_k(I_k)^2 + eps), the relMSE of an unbiased estimator when no reference
/// exists.
fn relative_variance(imgs: &[&Image], eps: f64) -> f64 {
    let n = imgs.len() as f64;
    if imgs.len() < 2 {
        return f64::NAN;
    }
    let mut acc = 0.0;
    let count = imgs[0].pixels.len() * 3;
    for i in 0..imgs[0].pixels.len() {
        for c in 0..3 {
            let vals: Vec<f64> = imgs.iter().map(|im| im.pixels[i][c] as f64).collect();
            let m = vals.iter().sum::<f64>() / n;
            let var = vals.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0);
            acc += var / (m * m + eps);
        }
    }
    acc / count as f64
}

/// Runs `omis compare`: the renders, the table, the plots and `results.json`.
pub fn run(a: CompareArgs) -> Result<()> {
    let roulette_from = check_args(&a)?;
    let reference = Reference::load(&a.reference, a.max_depth)?;
    let scene = load_scene(&a.scene, &reference.beauty)?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let mut methods: Vec<Method> = a.mis.iter().map(|&m| Method::Bdpt(m.into())).collect();
    if a.pt {
        methods.push(Method::Pt);
    }
    let comparison = Comparison {
        a: &a,
        reference: &reference,
        // A pilot moves the camera for its replicas (and gives it back) before its render
        // borrows the scene.
        scene: std::cell::RefCell::new(scene),
        pool: super::thread_pool(a.threads)?,
        methods,
        roulette_from,
    };
    let points = comparison.equal_spp()?;
    let timed = match a.equal_time {
        Some(t) => comparison.equal_time(t)?,
        None => Vec::new(),
    };
    print_table(&points, &timed, &a);
    write_plots(&points, &a)?;
    write_results(&a, &reference.beauty, roulette_from, &points, &timed)
}

/// Refuses arguments that cannot make a comparison; the first vertex of BDPT's roulette.
fn check_args(a: &CompareArgs) -> Result<u32> {
    if a.seeds == 0 || a.spp.is_empty() || a.mis.is_empty() {
        bail!("need at least one seed, one spp and one strategy");
    }
    if a.spp.contains(&0) {
        bail!("--spp values must be >= 1");
    }
    let roulette_from = a
        .roulette_from
        .unwrap_or(crate::integrator::bdpt::ROULETTE_FROM);
    if !(1..=crate::integrator::bdpt::MAX_DEPTH).contains(&roulette_from) {
        bail!(
            "--roulette-from {roulette_from} is outside 1 ..= {} (1: the first surface vertex)",
            crate::integrator::bdpt::MAX_DEPTH
        );
    }
    if a.cpu_time && a.equal_time.is_none() {
        bail!("--cpu-time sets the clock of --equal-time, which is missing");
    }
    if a.cpu_time && super::procstat::cpu_seconds(None).is_nan() {
        bail!("--cpu-time: this system does not report the process's CPU time");
    }
    Ok(roulette_from)
}

/// The reference EXR: its beauty, and its depth layers where it has them.
struct Reference {
    beauty: Image,
    /// Layer `depth{d}` for d = 0 ..= max depth, where the file has it.
    depths: Vec<Option<Image>>,
}

impl Reference {
    /// Reads the reference EXR, its beauty and its layers of depths 0 ..= `max_depth`.
    fn load(path: &Path, max_depth: u32) -> Result<Reference> {
        // The header first: a small file can claim a frame too large to decode.
        exr_header::check_cli(path)?;
        let layers = exr_io::read_exr_layers(path).map_err(anyhow::Error::msg)?;
        let beauty = layers
            .iter()
            .find(|(n, _)| n.is_empty())
            .map(|(_, i)| i.clone())
            .unwrap_or_else(|| layers[0].1.clone());
        let depths = (0..=max_depth)
            .map(|d| {
                layers
                    .iter()
                    .find(|(n, _)| *n == format!("depth{d}"))
                    .map(|(_, i)| i.clone())
            })
            .collect();
        Ok(Reference { beauty, depths })
    }
}

/// The scene at the reference's resolution.
fn load_scene(path: &Path, reference: &Image) -> Result<Scene> {
    let mut scene = Scene::load(path).map_err(anyhow::Error::msg)?;
    scene.camera = scene
        .camera
        .with_resolution(reference.width as u32, reference.height as u32)
        .map_err(anyhow::Error::msg)?;
    Ok(scene)
}

/// What every render of a comparison shares: the arguments, the reference, the scene, the pool
/// and the methods compared.
struct Comparison<'a> {
    a: &'a CompareArgs,
    reference: &'a Reference,
    scene: std::cell::RefCell<Scene>,
    pool: rayon::ThreadPool,
    methods: Vec<Method>,
    roulette_from: u32,
}

impl Comparison<'_> {
    /// The settings of a render of `method` at `spp` with `seed` and D_opt `d_opt`.
    fn base(&self, method: Method, spp: u32, seed: u64, d_opt: u32) -> RenderSettings {
        let a = self.a;
        RenderSettings {
            integrator: match method {
                Method::Pt => IntegratorKind::Pt,
                Method::Bdpt(_) => IntegratorKind::Bdpt,
            },
            mis: match method {
                Method::Pt => MisKind::Balance,
                Method::Bdpt(m) => m,
            },
            sample_block: spp,
            max_depth: a.max_depth,
            seed,
            sampler: a.sampler.into(),
            optimal_max_depth: d_opt,
            optimal_kappa: a.kappa,
            depth_layers: true,
            // BDPT's roulette as `omis render` resolves it (the path tracer has its own).
            roulette: !a.no_roulette,
            roulette_from: self.roulette_from,
            ..Default::default()
        }
    }

    /// `--optimal-max-depth auto`: an optimal render's pilot, as `omis render` runs it for a job
    /// of `spp` samples per pixel or a budget of `budget_s` seconds (on the budget's clock).
    fn pilot(
        &self,
        method: Method,
        seed: u64,
        spp: Option<u32>,
        budget_s: Option<f64>,
    ) -> Option<Pilot> {
        let a = self.a;
        if a.optimal_max_depth.0.is_some() || !matches!(method, Method::Bdpt(k) if k.is_optimal()) {
            return None;
        }
        let pixels = self.reference.beauty.width as u64 * self.reference.beauty.height as u64;
        let wall0 = std::time::Instant::now();
        let cpu0 = super::procstat::cpu_seconds(None);
        let clock = || {
            if a.cpu_time {
                super::procstat::cpu_seconds(None) - cpu0
            } else {
                wall0.elapsed().as_secs_f64()
            }
        };
        let size = optimal_depth::JobSize {
            samples: spp.map(|n| pixels.saturating_mul(n as u64)),
            budget: budget_s.map(|seconds| optimal_depth::Budget {
                seconds,
                clock: &clock,
            }),
        };
        let s = self.base(method, 1, seed, 0);
        let mut scene = self.scene.borrow_mut();
        let scene: &mut Scene = &mut scene;
        let choice = self
            .pool
            .install(|| optimal_depth::choose(scene, &s, a.eps, size));
        let point = spp.map_or_else(|| "equal time".to_string(), |n| format!("{n} spp"));
        eprintln!(
            "{} seed {seed}, {point}: {}",
            method.name(),
            choice.summary()
        );
        Some(Pilot {
            choice,
            seconds: wall0.elapsed().as_secs_f64(),
            cpu: super::procstat::cpu_seconds(None) - cpu0,
            on_clock: clock(),
        })
    }

    /// The settings of a render, with the D_opt its pilot chose, or the argument's.
    fn settings(
        &self,
        method: Method,
        spp: u32,
        seed: u64,
        pilot: &Option<Pilot>,
    ) -> RenderSettings {
        let d_opt = match (pilot, self.a.optimal_max_depth.0) {
            (Some(p), _) => p.choice.chosen,
            (None, Some(d)) => d,
            (None, None) => crate::mis::DEFAULT_OPTIMAL_MAX_DEPTH,
        };
        self.base(method, spp, seed, d_opt)
    }

    /// One render reduced to what its point needs; the film is dropped here, so a comparison
    /// holds images, not every render's accumulators.
    fn summarize(&self, Run { out, cpu, pilot }: Run) -> Result<Rendered> {
        let eps = self.a.eps;
        let img = out.image();
        let e = metrics::compare(&img, &self.reference.beauty, eps).map_err(anyhow::Error::msg)?;
        let mut depths = Vec::new();
        for (d, im) in out.film.depth_images().into_iter().enumerate() {
            depths.push(match self.reference.depths.get(d) {
                Some(Some(r)) => DepthError::Against(
                    metrics::compare(&im, r, eps)
                        .map_err(anyhow::Error::msg)?
                        .relmse,
                ),
                _ => DepthError::Image(im),
            });
        }
        Ok(Rendered {
            relmse: e.relmse,
            relmse_trimmed: e.relmse_trimmed,
            seconds: out.seconds + pilot.as_ref().map_or(0.0, |p| p.seconds),
            cpu: cpu + pilot.as_ref().map_or(0.0, |p| p.cpu),
            spp: out.spp,
            bytes_per_pixel: out.film.layout.bytes_per_pixel(),
            depths,
            pilot,
        })
    }

    /// Every method's renders of a seed run back to back, the first method rotating with the
    /// seed: a machine whose speed drifts during the comparison (other load, thermal limits)
    /// then slows every method alike, which matters most for the equal-time budgets.
    fn interleaved(&self, render: &dyn Fn(Method, u64) -> Run) -> Result<Vec<Vec<Rendered>>> {
        let methods = &self.methods;
        let mut runs: Vec<Vec<Rendered>> = methods.iter().map(|_| Vec::new()).collect();
        for seed in 0..self.a.seeds {
            for k in 0..methods.len() {
                let m = (k + seed as usize) % methods.len();
                runs[m].push(self.summarize(render(methods[m], seed))?);
            }
        }
        Ok(runs)
    }

    /// The points at each of the arguments' sample counts.
    fn equal_spp(&self) -> Result<Vec<Point>> {
        let mut points = Vec::new();
        for &spp in &self.a.spp {
            let runs = self.interleaved(&|mis, seed| {
                let pilot = self.pilot(mis, seed, Some(spp), None);
                let s = self.settings(mis, spp, seed, &pilot);
                let job = Resolved {
                    max_pass_size: Some(MAX_PASS_SIZE),
                    ..Resolved::fixed(&self.scene.borrow(), &s, TILE_SIZE, 1)
                };
                let (out, cpu) = timed_render(&self.pool, &job, &self.scene.borrow(), false);
                Run { out, cpu, pilot }
            })?;
            for (&mis, runs) in self.methods.iter().zip(runs) {
                let p = point(mis, spp, runs, self.a);
                eprintln!(
                    "{:>8} {:>5} spp: relMSE {:.4e} +- {:.1e}  {:.2} s",
                    p.method.name(),
                    spp,
                    p.relmse,
                    p.relmse_sd,
                    p.seconds
                );
                points.push(p);
            }
        }
        Ok(points)
    }

    /// The points at an equal time of `t` seconds per render.
    fn equal_time(&self, t: f64) -> Result<Vec<Point>> {
        if !(t > 0.0 && t.is_finite()) {
            bail!("--equal-time must be a positive number of seconds");
        }
        let a = self.a;
        let runs = self.interleaved(&|mis, seed| {
            // The pilot's time counts against the budget, as in `omis render --time-budget`.
            let pilot = self.pilot(mis, seed, None, Some(t));
            let s = self.settings(mis, 1, seed, &pilot);
            let job = Resolved {
                max_pass_size: Some(MAX_TIMED_PASS_SIZE),
                pilot_s: pilot.as_ref().map(|p| p.on_clock),
                ..Resolved::timed(&self.scene.borrow(), &s, TILE_SIZE, 1, t)
            };
            let (out, cpu) = timed_render(&self.pool, &job, &self.scene.borrow(), a.cpu_time);
            Run { out, cpu, pilot }
        })?;
        let mut timed = Vec::new();
        for (&mis, runs) in self.methods.iter().zip(runs) {
            let spp = runs.iter().map(|r| r.spp).min().unwrap_or(0);
            let p = point(mis, spp, runs, a);
            eprintln!(
                "{:>8} equal {} time {t} s: {} spp, relMSE {:.4e}",
                p.method.name(),
                clock_name(a.cpu_time),
                p.spp,
                p.relmse
            );
            timed.push(p);
        }
        Ok(timed)
    }
}

/// The point of `method` at `spp` from its renders: relMSE over seeds, per depth against the
/// reference's layers or, without them, the relative variance across seeds; times and costs.
fn point(method: Method, spp: u32, runs: Vec<Rendered>, a: &CompareArgs) -> Point {
    let n = runs.len() as f64;
    let rel: Vec<f64> = runs.iter().map(|r| r.relmse).collect();
    let trimmed: Vec<f64> = runs.iter().map(|r| r.relmse_trimmed).collect();
    let (m, sd) = mean_sd(&rel);
    let per_depth = (0..=a.max_depth as usize)
        .map(|d| {
            let of_depth = runs.iter().filter_map(|r| r.depths.get(d));
            let against: Vec<f64> = of_depth
                .clone()
                .filter_map(|e| match e {
                    DepthError::Against(v) => Some(*v),
                    DepthError::Image(_) => None,
                })
                .collect();
            if against.is_empty() {
                let imgs: Vec<&Image> = of_depth
                    .filter_map(|e| match e {
                        DepthError::Image(im) => Some(im),
                        DepthError::Against(_) => None,
                    })
                    .collect();
                relative_variance(&imgs, a.eps)
            } else {
                mean_sd(&against).0
            }
        })
        .collect();
    Point {
        method,
        spp,
        relmse: m,
        relmse_sd: sd,
        relmse_trimmed: mean_sd(&trimmed).0,
        seconds: runs.iter().map(|r| r.seconds).sum::<f64>() / n,
        cpu_seconds: runs.iter().map(|r| r.cpu).sum::<f64>() / n,
        bytes_per_pixel: runs.first().map_or(0, |r| r.bytes_per_pixel),
        relmse_per_depth: per_depth,
        optimal_depth: runs
            .iter()
            .filter_map(|r| r.pilot.as_ref().map(|p| p.choice.clone()))
            .collect(),
        pilot_cpu_seconds: runs
            .iter()
            .map(|r| r.pilot.as_ref().map_or(0.0, |p| p.cpu))
            .sum::<f64>()
            / n,
    }
}

/// Writes `results.json` into the output folder, and prints it with `--json`.
fn write_results(
    a: &CompareArgs,
    reference: &Image,
    roulette_from: u32,
    points: &[Point],
    timed: &[Point],
) -> Result<()> {
    let result = serde_json::json!({
        "scene": a.scene.display().to_string(),
        "reference": a.reference.display().to_string(),
        "width": reference.width, "height": reference.height,
        "max_depth": a.max_depth, "optimal_max_depth": a.optimal_max_depth.to_string(),
        "kappa": a.kappa,
        "roulette_from": (!a.no_roulette).then_some(roulette_from),
        "seeds": a.seeds, "eps": a.eps, "equal_time_clock": clock_name(a.cpu_time),
        "equal_spp": points, "equal_time": timed,
    });
    std::fs::write(
        a.out.join("results.json"),
        serde_json::to_string_pretty(&result)?,
    )
    .context("writing results.json")?;
    if a.json {
        println!("{result}");
    }
    Ok(())
}

/// What the equal-time budget counts.
fn clock_name(cpu_time: bool) -> &'static str {
    if cpu_time { "CPU" } else { "wall" }
}

/// Renders `job` on `pool` (a time budget counted in CPU seconds with `cpu_time`); returns the
/// output and the CPU seconds it took.
fn timed_render(
    pool: &rayon::ThreadPool,
    job: &Resolved,
    scene: &Scene,
    cpu_time: bool,
) -> (RenderOutput, f64) {
    let cpu0 = super::procstat::cpu_seconds(None);
    let out = pool.install(|| {
        if cpu_time {
            let clock = || super::procstat::cpu_seconds(None) - cpu0;
            job.render_in_process_clocked(scene, &|_| {}, &clock)
        } else {
            job.render_in_process(scene, &|_| {})
        }
    });
    (out, super::procstat::cpu_seconds(None) - cpu0)
}

fn print_table(points: &[Point], timed: &[Point], a: &CompareArgs) {
    let out = &mut String::new();
    use std::fmt::Write;
    let _ = writeln!(
        out,
        "{:>9} {:>6} {:>12} {:>10} {:>9} {:>10} {:>8} {:>12} {:>10}",
        "mis",
        "spp",
        "relMSE",
        "vs balance",
        "seconds",
        "vs balance",
        "B/pixel",
        "relMSE x s",
        "vs balance"
    );
    for p in points {
        let bal = points
            .iter()
            .find(|q| q.spp == p.spp && q.method == BALANCE);
        // relMSE x seconds: the inverse of the efficiency (lower is better).
        let work = p.relmse * p.seconds;
        let (rr, tr, wr) = match bal {
            Some(b) => (
                format!("{:.3}x", p.relmse / b.relmse),
                format!("{:.3}x", p.seconds / b.seconds),
                format!("{:.3}x", work / (b.relmse * b.seconds)),
            ),
            None => ("-".into(), "-".into(), "-".into()),
        };
        let _ = writeln!(
            out,
            "{:>9} {:>6} {:>12.4e} {:>10} {:>9.3} {:>10} {:>8} {:>12.4e} {:>10}",
            p.method.name(),
            p.spp,
            p.relmse,
            rr,
            p.seconds,
            tr,
            p.bytes_per_pixel,
            work,
            wr
        );
    }
    if !timed.is_empty() {
        let _ = writeln!(
            out,
            "equal time ({} {} s per render):",
            a.equal_time.unwrap_or(0.0),
            clock_name(a.cpu_time)
        );
        let bal = timed.iter().find(|q| q.method == BALANCE);
        for p in timed {
            let _ = writeln!(
                out,
                "{:>9} {:>6} spp {:>12.4e} {:>10} trimmed {:>11.4e} {:>10} {:>8.2} s wall {:>8.2} s CPU",
                p.method.name(),
                p.spp,
                p.relmse,
                bal.map_or("-".into(), |b| format!("{:.3}x", p.relmse / b.relmse)),
                p.relmse_trimmed,
                bal.map_or("-".into(), |b| format!(
                    "{:.3}x",
                    p.relmse_trimmed / b.relmse_trimmed
                )),
                p.seconds,
                p.cpu_seconds
            );
        }
    }
    if a.json {
        eprint!("{out}");
    } else {
        print!("{out}");
    }
}

fn write_plots(points: &[Point], a: &CompareArgs) -> Result<()> {
    let mut kinds: Vec<Method> = Vec::new();
    for p in points {
        if !kinds.contains(&p.method) {
            kinds.push(p.method);
        }
    }
    let series: Vec<(String, Vec<(f64, f64)>)> = kinds
        .iter()
        .map(|&k| {
            (
                k.name(),
                points
                    .iter()
                    .filter(|p| p.method == k)
                    .map(|p| (p.spp as f64, p.relmse))
                    .collect(),
            )
        })
        .collect();
    let svg = plot::line_chart(
        "relMSE vs samples per pixel",
        "spp",
        "relMSE",
        &series,
        true,
        true,
    );
    std::fs::write(a.out.join("relmse_vs_spp.svg"), svg)?;
    // Gain per depth: balance relMSE / optimal relMSE for depths 1..=D_opt, one bar per spp.
    if kinds.contains(&OPTIMAL) && kinds.contains(&BALANCE) {
        let depths: Vec<String> = (0..=a.max_depth).map(|d| format!("d={d}")).collect();
        let mut gain = Vec::new();
        for &spp in &a.spp {
            let b = points.iter().find(|p| p.spp == spp && p.method == BALANCE);
            let o = points.iter().find(|p| p.spp == spp && p.method == OPTIMAL);
            if let (Some(b), Some(o)) = (b, o) {
                gain.push((
                    format!("{spp} spp"),
                    b.relmse_per_depth
                        .iter()
                        .zip(&o.relmse_per_depth)
                        .map(|(x, y)| x / y)
                        .collect(),
                ));
            }
        }
        let svg = plot::bar_chart(
            "Gain per depth: balance relMSE / optimal relMSE",
            "gain",
            &depths,
            &gain,
            Some(1.0),
        );
        std::fs::write(a.out.join("gain_per_depth.svg"), svg)?;
    }
    // Overhead: time and memory relative to balance, per strategy, at each spp.
    let cats: Vec<String> = a.spp.iter().map(|s| format!("{s} spp")).collect();
    let time: Vec<(String, Vec<f64>)> = kinds
        .iter()
        .map(|&k| {
            (
                k.name(),
                a.spp
                    .iter()
                    .map(|&spp| {
                        let p = points.iter().find(|p| p.spp == spp && p.method == k);
                        let b = points.iter().find(|p| p.spp == spp && p.method == BALANCE);
                        match (p, b) {
                            (Some(p), Some(b)) => p.seconds / b.seconds,
                            _ => f64::NAN,
                        }
                    })
                    .collect(),
            )
        })
        .collect();
    std::fs::write(
        a.out.join("time_overhead.svg"),
        plot::bar_chart(
            "Render time relative to balance",
            "time / balance time",
            &cats,
            &time,
            Some(1.0),
        ),
    )?;
    let mem: Vec<(String, Vec<f64>)> = kinds
        .iter()
        .map(|&k| {
            let p = points.iter().find(|p| p.method == k);
            (
                k.name(),
                vec![p.map_or(f64::NAN, |p| p.bytes_per_pixel as f64)],
            )
        })
        .collect();
    std::fs::write(
        a.out.join("memory.svg"),
        plot::bar_chart(
            "Accumulator memory",
            "bytes per pixel",
            &["".into()],
            &mem,
            None,
        ),
    )?;
    Ok(())
}
