//! Helpers shared by the integration tests: where scenes are, temporary folders, renders on a
//! pool of a given size, and the rule for tests that need `../shared/scenes`.
#![allow(dead_code)] // Each test crate uses a subset.

use omis::film::Film;
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
