//! Helpers of the importer tests: loading a scene file that must load (or must not), and
//! finding what its messages say.

use omis::scene::{Scene, SceneParams};
use std::path::Path;

/// The scene of `path`, which must load.
pub fn load(path: &Path) -> Scene {
    load_with(path, &SceneParams::default())
}

/// The scene of `path` with the parameter values `params`, which must load.
pub fn load_with(path: &Path, params: &SceneParams) -> Scene {
    Scene::load_with(path, params).unwrap_or_else(|e| panic!("{} should load: {e}", path.display()))
}

/// The error of loading `path`, which must not load.
pub fn load_err(path: &Path) -> String {
    load_err_with(path, &SceneParams::default())
}

/// The error of loading `path` with the parameter values `params`, which must not load.
pub fn load_err_with(path: &Path, params: &SceneParams) -> String {
    match Scene::load_with(path, params) {
        Ok(_) => panic!("{} loaded but should not", path.display()),
        Err(e) => e.to_string(),
    }
}

/// Asserts that `msg` mentions every one of `parts`.
pub fn assert_has(msg: &str, parts: &[&str]) {
    for p in parts {
        assert!(msg.contains(p), "'{msg}' should mention '{p}'");
    }
}

/// The first of the scene's warnings that mentions `part` (there must be one).
pub fn warning<'a>(scene: &'a Scene, part: &str) -> &'a str {
    scene
        .warnings
        .iter()
        .find(|w| w.contains(part))
        .unwrap_or_else(|| {
            panic!(
                "no warning mentions '{part}'; warnings: {:#?}",
                scene.warnings
            )
        })
}
