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

/// The scene's material called `name` (there must be one).
pub fn material<'a>(scene: &'a Scene, name: &str) -> &'a omis::material::Material {
    scene
        .materials
        .iter()
        .find(|m| m.name == name)
        .unwrap_or_else(|| panic!("no material '{name}'"))
}

/// Whether `a` and `b` agree to a relative tolerance `tol` (absolute near zero).
pub fn close(a: f32, b: f32, tol: f32) -> bool {
    (a - b).abs() <= tol * (1.0 + a.abs().max(b.abs()))
}

/// An ASCII and a binary PLY with the same two triangles.
pub fn write_plys(d: &Path) {
    let verts = [
        [0.0f32, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ];
    let mut ascii = String::from(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n",
    );
    for v in verts {
        ascii += &format!("{} {} {}\n", v[0], v[1], v[2]);
    }
    ascii += "4 0 1 2 3\n";
    std::fs::write(d.join("quad.ply"), ascii).expect("ply");
    let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
    for v in verts {
        for c in v {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for f in [[0i32, 1, 2], [0, 2, 3]] {
        bin.push(3);
        for i in f {
            bin.extend_from_slice(&i.to_le_bytes());
        }
    }
    std::fs::create_dir_all(d.join("models")).expect("models dir");
    std::fs::write(d.join("models/quad-bin.ply"), bin).expect("ply");
}

/// A unit quad `quad.obj` in `d`.
pub fn write_obj(d: &Path) {
    // A unit quad in the xy plane facing +z, with uvs (v = 0 at the bottom) and normals that
    // lean towards +y along its right edge.
    super::write(
        d,
        "quad.obj",
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\nvn 0 0.6 0.8\nf 1/1/1 2/2/2 3/3/2 4/4/1\n",
    );
}

/// A 2x2 PNG: top row red, bottom row green.
pub fn write_png(d: &Path) {
    let data = [255u8, 0, 0, 255, 0, 0, 0, 255, 0, 0, 255, 0];
    omis::film::image::png::write_rgb8(&d.join("tex.png"), 2, 2, &data).expect("png");
}
