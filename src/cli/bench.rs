//! `omis bench`: the samplers' cost per number, BVH build time, closest-hit and occlusion ray
//! rates with random rays, and the path tracer's throughput compared with the bare BVH rate for
//! the same mix of queries; peak memory (VmHWM) after loading and at the end; optionally the
//! path tracer's relMSE against a reference (box-downsampled to the bench resolution when it is
//! an integer multiple of it).

use crate::accel::{Accel, SphereGeom};
use crate::film::image::{Image, error_map, exr_io, metrics, png};
use crate::geometry::warp::uniform_sphere;
use crate::geometry::{Ray, Vec2, Vec3};
use crate::integrator::{IntegratorKind, RenderSettings};
use crate::job::Resolved;
use crate::sampler::{Pcg32, Sampler, SamplerKind, Stream};
use crate::scene::{Scene, mesh};
use anyhow::{Context, Result, bail};
use clap::Args;
use rayon::prelude::*;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
pub struct BenchArgs {
    /// Scene files to measure (BVH and path tracer).
    #[arg(long = "scene")]
    pub scenes: Vec<PathBuf>,
    /// A folder of OBJ files loaded in place as one mesh (BVH only), e.g.
    /// ../shared/scenes/staircase/mitsuba/models.
    #[arg(long)]
    pub obj_dir: Vec<PathBuf>,
    /// Random rays per measurement.
    #[arg(long, default_value_t = 2_000_000)]
    pub rays: usize,
    /// Threads (0 = all cores); ray rates are measured on 1 thread and on this many.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Path tracer spp and resolution for the throughput run.
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
    #[arg(long, default_value = "256x256")]
    pub resolution: String,
    #[arg(long, default_value_t = 5)]
    pub max_depth: u32,
    /// Reference EXR for the path tracer's image (first --scene only): relMSE is reported. A
    /// reference k times the bench resolution in both axes is box-downsampled to it first.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// With --reference: write the signed relative error map (as `omis diff --error-map`).
    #[arg(long)]
    pub error_map: Option<PathBuf>,
    /// With --reference: also write the reference as used (downsampled) to this EXR.
    #[arg(long)]
    pub reference_out: Option<PathBuf>,
    /// Write the path tracer's image (first --scene only) to this EXR.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print one JSON object per target.
    #[arg(long)]
    pub json: bool,
    /// Ray queries: `auto` (flat for scenes of at most 64 primitives, else the BVH), `bvh` or
    /// `flat`, to compare the two on one scene.
    #[arg(long, value_enum, default_value_t = AccelChoice::Auto)]
    pub accel: AccelChoice,
}

/// How `omis bench` answers ray queries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum AccelChoice {
    /// As renders do: flat for small scenes, else the BVH.
    Auto,
    /// Always the BVH.
    Bvh,
    /// Every primitive tested against every ray.
    Flat,
}

/// Box-downsamples `img` to `w` x `h` (its size must be an integer multiple of it).
fn downsample(img: &Image, w: usize, h: usize) -> Result<Image> {
    if img.width == w && img.height == h {
        return Ok(img.clone());
    }
    let (kx, ky) = (img.width / w, img.height / h);
    if kx == 0 || kx != ky || kx * w != img.width || ky * h != img.height {
        bail!(
            "reference is {}x{}, not an integer multiple of the bench resolution {w}x{h}",
            img.width,
            img.height
        );
    }
    let mut out = Image::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let mut s = [0.0f64; 3];
            for dy in 0..ky {
                for dx in 0..kx {
                    let p = img.get(x * kx + dx, y * ky + dy);
                    for (c, v) in s.iter_mut().enumerate() {
                        *v += p[c] as f64;
                    }
                }
            }
            let n = (kx * ky) as f64;
            out.set(
                x,
                y,
                crate::geometry::Rgb::new((s[0] / n) as f32, (s[1] / n) as f32, (s[2] / n) as f32),
            );
        }
    }
    Ok(out)
}

/// Nanoseconds per 2D and 1D number pair of each sampler kind (by its name on the command line),
/// on one thread: `n` pixel samples of eight pairs each, the samplers' construction included.
fn measure_samplers(n: u32) -> Vec<(String, f64)> {
    [
        SamplerKind::Sobol,
        SamplerKind::Stratified,
        SamplerKind::Independent,
    ]
    .into_iter()
    .map(|kind| {
        let start = Instant::now();
        let mut acc = 0.0f32;
        for i in 0..n {
            let mut s = Sampler::new(kind, 1, i % 256, i / 256, i % 16, 16, Stream::Camera);
            for _ in 0..8 {
                let v = s.next_2d();
                acc += v.x + v.y + s.next_1d();
            }
        }
        std::hint::black_box(acc);
        let ns = start.elapsed().as_secs_f64() * 1e9 / (n as f64 * 8.0);
        (format!("{kind:?}").to_lowercase(), ns)
    })
    .collect()
}

struct RayRates {
    /// The queries tested every primitive (no BVH).
    flat: bool,
    closest_1t: f64,
    occlusion_1t: f64,
    closest_nt: f64,
    occlusion_nt: f64,
}

/// Random rays inside the bounds: closest-hit rays from a random interior point in a uniform
/// direction; occlusion rays as segments between two random interior points.
fn measure_rays(accel: &Accel, lo: Vec3, hi: Vec3, n: usize, pool: &rayon::ThreadPool) -> RayRates {
    let ext = hi - lo;
    let point = |r: &mut Pcg32| lo + ext * Vec3::new(r.next_f32(), r.next_f32(), r.next_f32());
    let closest = |chunk: usize, count: usize| -> usize {
        let mut rng = Pcg32::new(chunk as u64, 1);
        let mut hits = 0;
        for _ in 0..count {
            let o = point(&mut rng);
            let d = uniform_sphere(Vec2::new(rng.next_f32(), rng.next_f32()));
            hits += accel.intersect(&Ray::new(o, d)).is_some() as usize;
        }
        hits
    };
    let occl = |chunk: usize, count: usize| -> usize {
        let mut rng = Pcg32::new(chunk as u64, 2);
        let mut blocked = 0;
        for _ in 0..count {
            let a = point(&mut rng);
            let b = point(&mut rng);
            let d = b - a;
            let len = d.length();
            if len > 0.0 {
                blocked += accel.occluded(&Ray::segment(a, d / len, len)) as usize;
            }
        }
        blocked
    };
    let time = |f: &(dyn Fn(usize, usize) -> usize + Sync), parallel: bool| -> f64 {
        let start = Instant::now();
        if parallel {
            let chunks = 256;
            let per = n.div_ceil(chunks);
            let _: usize = pool.install(|| (0..chunks).into_par_iter().map(|c| f(c, per)).sum());
            (per * chunks) as f64 / start.elapsed().as_secs_f64()
        } else {
            let _ = f(0, n / 4);
            (n / 4) as f64 / start.elapsed().as_secs_f64()
        }
    };
    RayRates {
        flat: accel.is_flat(),
        closest_1t: time(&closest, false),
        occlusion_1t: time(&occl, false),
        closest_nt: time(&closest, true),
        occlusion_nt: time(&occl, true),
    }
}

pub fn run(a: BenchArgs) -> Result<()> {
    let pool = super::thread_pool(a.threads)?;
    let threads = pool.current_num_threads();
    let (w, h) = super::parse_resolution(&a.resolution).map_err(anyhow::Error::msg)?;
    let samplers = measure_samplers((a.rays / 8).clamp(1000, 1 << 24) as u32);
    if a.json {
        let per: serde_json::Map<String, serde_json::Value> = samplers
            .iter()
            .map(|(name, ns)| (name.clone(), serde_json::json!(ns)))
            .collect();
        println!(
            "{}",
            serde_json::json!({"target": "samplers", "ns_per_2d_1d_draw": per})
        );
    } else {
        let per: Vec<String> = samplers
            .iter()
            .map(|(name, ns)| format!("{name} {ns:.1}"))
            .collect();
        println!(
            "samplers, 1 thread, ns per 2D + 1D draw (8 per pixel sample, its construction included): {}",
            per.join(", ")
        );
    }
    let mut scenes = a.scenes.clone();
    if scenes.is_empty() && a.obj_dir.is_empty() {
        scenes.push(PathBuf::from("scenes/cornell-box.json"));
    }
    for (k, path) in scenes.iter().enumerate() {
        let t0 = Instant::now();
        let mut scene = Scene::load(path).map_err(anyhow::Error::msg)?;
        let load = t0.elapsed().as_secs_f64();
        let rss_loaded = super::procstat::peak_rss_mib();
        match a.accel {
            AccelChoice::Auto => {}
            AccelChoice::Bvh => scene.rebuild_accel(false),
            AccelChoice::Flat => scene.rebuild_accel(true),
        }
        scene.camera = scene
            .camera
            .with_resolution(w, h)
            .map_err(anyhow::Error::msg)?;
        let (lo, hi) = scene.bounds();
        let rates = measure_rays(scene.accel(), lo, hi, a.rays, &pool);
        let settings = RenderSettings {
            integrator: IntegratorKind::Pt,
            sample_block: a.spp,
            max_depth: a.max_depth,
            seed: 1,
            sampler: SamplerKind::Sobol,
            ..Default::default()
        };
        let job = Resolved::fixed(&scene, &settings, 16, 64);
        let out = pool.install(|| job.render_in_process(&scene, &|_| {}));
        let st = out.stats;
        let secs = out.seconds;
        let reference = if k == 0 {
            compare_reference(&a, &out.image())?
        } else {
            None
        };
        // Time the bare BVH would need for the same numbers of closest and occlusion queries.
        let bare = st.closest as f64 / rates.closest_nt + st.shadow as f64 / rates.occlusion_nt;
        report(
            &a,
            &path.display().to_string(),
            scene.stats.triangles,
            load,
            scene.stats.bvh_build_seconds,
            &rates,
            threads,
            Some(PtRun {
                samples_per_second: st.samples as f64 / secs,
                rays_per_second: st.rays() as f64 / secs,
                fraction_of_bare: bare / secs,
                seconds: secs,
                reference,
            }),
            (rss_loaded, super::procstat::peak_rss_mib()),
        );
    }
    for dir in &a.obj_dir {
        let t0 = Instant::now();
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .with_context(|| format!("reading {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("obj")))
            .collect();
        files.sort();
        let mut tris: Vec<[Vec3; 3]> = Vec::new();
        for f in &files {
            let m = mesh::load_obj(f).map_err(|e| anyhow::anyhow!("{}: {e}", f.display()))?;
            tris.extend(m.indices.iter().map(|t| t.map(|k| m.positions[k as usize])));
        }
        let ids: Vec<u32> = (0..tris.len() as u32).collect();
        let accel = match a.accel {
            AccelChoice::Auto => Accel::build(&tris, &ids, &[] as &[SphereGeom], &[]),
            choice => Accel::build_with(&tris, &ids, &[], &[], choice == AccelChoice::Flat),
        };
        // As for scenes: the load time includes the BVH build.
        let load = t0.elapsed().as_secs_f64();
        let rss_loaded = super::procstat::peak_rss_mib();
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for t in &tris {
            for v in t {
                lo = lo.min(*v);
                hi = hi.max(*v);
            }
        }
        let rates = measure_rays(&accel, lo, hi, a.rays, &pool);
        report(
            &a,
            &format!("{} ({} OBJ files)", dir.display(), files.len()),
            tris.len(),
            load,
            accel.stats.seconds,
            &rates,
            threads,
            None,
            (rss_loaded, super::procstat::peak_rss_mib()),
        );
    }
    Ok(())
}

/// The path tracer's run on a scene.
struct PtRun {
    samples_per_second: f64,
    rays_per_second: f64,
    fraction_of_bare: f64,
    seconds: f64,
    /// Comparison with the reference, when one was given.
    reference: Option<RefStats>,
}

/// The path tracer's image against the reference.
struct RefStats {
    relmse: f64,
    mean_rgb: [f64; 3],
    reference_mean_rgb: [f64; 3],
}

/// With --reference: relMSE (eps 0.01) of `img` against the (downsampled) reference and both
/// images' mean RGB; writes the error map and the optional EXR outputs.
fn compare_reference(a: &BenchArgs, img: &Image) -> Result<Option<RefStats>> {
    if let Some(p) = &a.out {
        exr_io::write_exr(p, img, &[], &[]).map_err(anyhow::Error::msg)?;
    }
    let Some(rp) = &a.reference else {
        return Ok(None);
    };
    let full = exr_io::read_exr(rp).map_err(anyhow::Error::msg)?;
    let reference = downsample(&full, img.width, img.height)?;
    if let Some(p) = &a.reference_out {
        exr_io::write_exr(p, &reference, &[], &[]).map_err(anyhow::Error::msg)?;
    }
    let e = metrics::compare(img, &reference, 0.01).map_err(anyhow::Error::msg)?;
    if let Some(p) = &a.error_map {
        let pic =
            error_map::error_picture(img, &reference, 0.01, None).map_err(anyhow::Error::msg)?;
        png::write_rgb8(p, pic.width, pic.height, &pic.rgb).map_err(anyhow::Error::msg)?;
    }
    Ok(Some(RefStats {
        relmse: e.relmse,
        mean_rgb: img.mean(),
        reference_mean_rgb: reference.mean(),
    }))
}

#[allow(clippy::too_many_arguments)]
fn report(
    a: &BenchArgs,
    name: &str,
    triangles: usize,
    load: f64,
    build: f64,
    r: &RayRates,
    threads: usize,
    pt: Option<PtRun>,
    (rss_loaded, rss_end): (f64, f64),
) {
    if a.json {
        let mut j = serde_json::json!({
            "target": name, "triangles": triangles, "load_seconds": load,
            "bvh_build_seconds": build, "threads": threads, "flat": r.flat,
            "closest_mrays_1t": r.closest_1t / 1e6, "occlusion_mrays_1t": r.occlusion_1t / 1e6,
            "closest_mrays": r.closest_nt / 1e6, "occlusion_mrays": r.occlusion_nt / 1e6,
            "peak_rss_mib_after_load": rss_loaded, "peak_rss_mib": rss_end,
        });
        if let Some(p) = pt {
            j["pt_pixel_samples_per_second"] = serde_json::json!(p.samples_per_second);
            j["pt_mrays"] = serde_json::json!(p.rays_per_second / 1e6);
            j["pt_fraction_of_bare_bvh"] = serde_json::json!(p.fraction_of_bare);
            j["pt_seconds"] = serde_json::json!(p.seconds);
            if let Some(r) = &p.reference {
                j["pt_relmse"] = serde_json::json!(r.relmse);
                j["pt_mean_rgb"] = serde_json::json!(r.mean_rgb);
                j["reference_mean_rgb"] = serde_json::json!(r.reference_mean_rgb);
            }
        }
        println!("{j}");
        return;
    }
    println!(
        "{name}: {triangles} triangles, load {load:.3} s (BVH build {build:.3} s of it); peak memory (VmHWM) {rss_loaded:.0} MiB after load"
    );
    let queries = if r.flat { "flat" } else { "BVH" };
    println!(
        "  random rays ({queries}), 1 thread : closest {:.2} Mrays/s, occlusion {:.2} Mrays/s",
        r.closest_1t / 1e6,
        r.occlusion_1t / 1e6
    );
    println!(
        "  random rays ({queries}), {threads} thread(s): closest {:.2} Mrays/s, occlusion {:.2} Mrays/s",
        r.closest_nt / 1e6,
        r.occlusion_nt / 1e6
    );
    if let Some(p) = pt {
        println!(
            "  path tracer ({} spp, {}, depth {}): {:.2} s, {:.0} pixel samples/s, {:.2} Mrays/s = {:.0}% of the bare BVH rate for the same query mix",
            a.spp,
            a.resolution,
            a.max_depth,
            p.seconds,
            p.samples_per_second,
            p.rays_per_second / 1e6,
            p.fraction_of_bare * 100.0
        );
        if let Some(r) = &p.reference {
            println!(
                "  relMSE against the reference (eps 0.01): {:.6}; mean RGB {:.4?}, reference {:.4?}",
                r.relmse, r.mean_rgb, r.reference_mean_rgb
            );
        }
    }
    println!("  peak memory (VmHWM) so far: {rss_end:.0} MiB");
}
