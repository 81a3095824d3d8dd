//! Helpers shared by the integration tests: where scenes are, temporary folders, renders on a
//! pool of a given size, and the rule for tests that need `../shared/scenes`.
#![allow(dead_code)] // Each test crate uses a subset.

pub mod import;
pub mod service;

use omis::film::{Film, Image};
use omis::integrator::RenderSettings;
use omis::job::{RenderOutput, Resolved};
use omis::scene::Scene;
use std::path::{Path, PathBuf};

/// The repository's root.
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// A scene of the repository's `scenes/` at `w` x `h` pixels.
pub fn load(name: &str, w: u32, h: u32) -> Scene {
    let mut s = load_as_is(name);
    s.camera = s.camera.with_resolution(w, h).expect("resolution");
    s
}

/// A scene of the repository's `scenes/` at its own resolution.
pub fn load_as_is(name: &str) -> Scene {
    Scene::load(&repo().join("scenes").join(name)).expect(name)
}

/// A fresh, empty folder for one test's files (unique per test name and process).
pub fn folder(prefix: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("omis-{prefix}-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// Writes `text` to `dir/name`.
pub fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).expect("write file");
    p
}

/// Renders a fixed-spp job of `settings` in tiles of `tile` pixels (passes of 64 samples) on a
/// pool of `threads` threads.
pub fn render_on(
    scene: &Scene,
    settings: &RenderSettings,
    tile: u32,
    threads: usize,
) -> RenderOutput {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("pool");
    pool.install(|| Resolved::fixed(scene, settings, tile, 64).render_in_process(scene, &|_| {}))
}

/// The same on the current pool.
pub fn render(scene: &Scene, settings: &RenderSettings, tile: u32) -> RenderOutput {
    Resolved::fixed(scene, settings, tile, 64).render_in_process(scene, &|_| {})
}

/// The merged film of a render.
pub fn film(scene: &Scene, settings: &RenderSettings, tile: u32) -> Film {
    render(scene, settings, tile).film
}

/// `../shared/scenes`, the public test scenes read in place. When this checkout has none, a test
/// that needs them fails under `CI=true` (CI must never pass by skipping) and otherwise says that
/// it skipped.
pub fn shared_scenes(test: &str) -> Option<PathBuf> {
    let d = repo().join("../shared/scenes");
    if d.is_dir() {
        return Some(d);
    }
    let why = format!(
        "{test}: {} is absent (public test scenes are not part of the repository)",
        d.display()
    );
    if std::env::var("CI").is_ok_and(|v| !v.is_empty() && v != "0" && v != "false") {
        panic!("{why}; CI=true, so this test must not skip");
    }
    eprintln!("SKIPPED {why}");
    None
}

/// Mean and standard error of the mean of independent values.
pub fn mean_se(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0).max(1.0);
    (m, (var / n).sqrt())
}

/// Mean over the seeds of a region's mean, and its standard error (from the seed spread).
pub fn region(images: &[Image], r: (usize, usize, usize, usize), c: usize) -> (f64, f64) {
    let (x0, y0, x1, y1) = r;
    let means: Vec<f64> = images
        .iter()
        .map(|img| {
            let mut s = 0.0;
            for y in y0..y1 {
                for x in x0..x1 {
                    s += img.get(x, y)[c] as f64;
                }
            }
            s / ((x1 - x0) * (y1 - y0)) as f64
        })
        .collect();
    let n = means.len() as f64;
    let m = means.iter().sum::<f64>() / n;
    let var = means.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (n - 1.0);
    (m, (var / n).sqrt())
}

/// Every region of a `g` x `g` grid and every channel agree within 4 combined standard errors.
/// Returns the largest deviation in standard errors.
pub fn assert_agree(what: &str, a: &[Image], b: &[Image], g: usize) -> f64 {
    let (w, h) = (a[0].width, a[0].height);
    let mut worst: f64 = 0.0;
    for ry in 0..g {
        for rx in 0..g {
            let r = (rx * w / g, ry * h / g, (rx + 1) * w / g, (ry + 1) * h / g);
            for c in 0..3 {
                let (ma, sa) = region(a, r, c);
                let (mb, sb) = region(b, r, c);
                let se = (sa * sa + sb * sb).sqrt();
                let tol = 4.0 * se + 1e-6 * ma.abs().max(mb.abs());
                assert!(
                    (ma - mb).abs() <= tol,
                    "{what}: region {r:?} channel {c}: {ma} vs {mb} (se {se})"
                );
                if se > 0.0 {
                    worst = worst.max((ma - mb).abs() / se);
                }
            }
        }
    }
    eprintln!("{what}: worst deviation {worst:.2} standard errors");
    worst
}

/// Mean and standard error of the mean over the pixels [x0, x1) x [y0, y1) of accumulated sums
/// (pixels are independent estimates).
pub fn sums_region(
    sums: &omis::film::PixelSums,
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
    c: usize,
) -> (f64, f64) {
    let mut m = 0.0;
    let mut v = 0.0;
    let mut n = 0.0;
    for y in y0..y1 {
        for x in x0..x1 {
            let i = y * sums.width + x;
            let k = sums.count[i] as f64;
            let mean = sums.sum[i][c] / k;
            let var = ((sums.sum_sq[i][c] / k - mean * mean) * k / (k - 1.0)).max(0.0) / k;
            m += mean;
            v += var;
            n += 1.0;
        }
    }
    (m / n, (v / (n * n)).sqrt())
}
