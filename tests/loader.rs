//! Scene loading: every bad input is a clear error naming the file and the place, never a panic;
//! meshes load from OBJ and PLY (ASCII and binary).

mod common;

use omis::scene::Scene;
use std::path::{Path, PathBuf};

fn folder(name: &str) -> PathBuf {
    common::folder("loader", name)
}

const CAMERA: &str =
    r#""camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "fov": 40, "resolution": [8, 8]}"#;
const MATERIALS: &str = r#""materials": {"m": {"type": "lambert", "albedo": 0.5}}"#;

fn scene_with_shapes(dir: &Path, shapes: &str) -> PathBuf {
    let p = dir.join("scene.json");
    std::fs::write(
        &p,
        format!("{{\n{CAMERA},\n{MATERIALS},\n\"shapes\": [{shapes}]\n}}\n"),
    )
    .expect("write scene");
    p
}

fn load_err(path: &Path) -> String {
    match Scene::load(path) {
        Ok(_) => panic!("{} loaded but should not", path.display()),
        Err(e) => e.to_string(),
    }
}

fn assert_has(msg: &str, parts: &[&str]) {
    for p in parts {
        assert!(msg.contains(p), "error '{msg}' should mention '{p}'");
    }
}

#[test]
fn malformed_json_names_file_and_line() {
    let d = folder("malformed");
    let p = d.join("scene.json");
    std::fs::write(&p, "{\n  \"camera\": {\"position\": [0, 0, 5],\n  oops\n}").unwrap();
    let e = load_err(&p);
    assert_has(&e, &["scene.json", "line 3"]);
}

#[test]
fn unknown_field_and_wrong_type_name_the_json_path() {
    let d = folder("unknown");
    let p = d.join("scene.json");
    std::fs::write(
        &p,
        r#"{"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "fovv": 40, "resolution": [8, 8]}}"#,
    )
    .unwrap();
    assert_has(&load_err(&p), &["camera", "fovv"]);
    let p = scene_with_shapes(
        &d,
        r#"{"type": "sphere", "center": [0, 0, "x"], "radius": 1, "material": "m"}"#,
    );
    assert_has(&load_err(&p), &["shapes[0].center"]);
    let p = scene_with_shapes(&d, r#"{"type": "torus", "material": "m"}"#);
    assert_has(&load_err(&p), &["shapes[0]", "torus"]);
}

#[test]
fn missing_mesh_is_reported_with_its_field() {
    let d = folder("missing");
    let p = scene_with_shapes(
        &d,
        r#"{"type": "mesh", "file": "nowhere.obj", "material": "m"}"#,
    );
    assert_has(
        &load_err(&p),
        &["scene.json", "shapes[0].file", "nowhere.obj", "not found"],
    );
}

#[test]
fn negative_radius_is_refused() {
    let d = folder("radius");
    let p = scene_with_shapes(
        &d,
        r#"{"type": "sphere", "center": [0, 0, 0], "radius": -1, "material": "m"}"#,
    );
    assert_has(&load_err(&p), &["shapes[0].radius", "-1"]);
}

#[test]
fn nan_vertex_in_a_mesh_file_is_refused() {
    let d = folder("nan");
    std::fs::write(d.join("bad.obj"), "v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n").unwrap();
    let p = scene_with_shapes(
        &d,
        r#"{"type": "mesh", "file": "bad.obj", "material": "m"}"#,
    );
    assert_has(
        &load_err(&p),
        &["shapes[0]", "bad.obj", "vertex 2 is not finite"],
    );
    // Out-of-range JSON numbers cannot smuggle infinities in either.
    let p = scene_with_shapes(
        &d,
        r#"{"type": "triangles", "positions": [[0,0,0],[1,0,0],[0,1e999,0]], "indices": [[0,1,2]], "material": "m"}"#,
    );
    assert_has(&load_err(&p), &["shapes[0].positions"]);
}

#[test]
fn paths_outside_the_scene_folder_are_refused() {
    let root = folder("outside");
    let inner = root.join("inner");
    std::fs::create_dir_all(&inner).unwrap();
    std::fs::write(
        root.join("secret.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    let p = scene_with_shapes(
        &inner,
        r#"{"type": "mesh", "file": "../secret.obj", "material": "m"}"#,
    );
    assert_has(
        &load_err(&p),
        &["shapes[0].file", "leaves the scene's folder"],
    );
    let abs = root.join("secret.obj");
    let p = scene_with_shapes(
        &inner,
        &format!(
            r#"{{"type": "mesh", "file": "{}", "material": "m"}}"#,
            abs.display()
        ),
    );
    assert_has(&load_err(&p), &["shapes[0].file", "absolute"]);
}

#[test]
fn unknown_material_and_bad_values_are_named() {
    let d = folder("values");
    let p = scene_with_shapes(
        &d,
        r#"{"type": "sphere", "center": [0, 0, 0], "radius": 1, "material": "gold"}"#,
    );
    assert_has(&load_err(&p), &["shapes[0].material", "gold"]);
    let p = scene_with_shapes(
        &d,
        r#"{"type": "sphere", "center": [0, 0, 0], "radius": 1, "material": "m", "emission": [1, -2, 0]}"#,
    );
    assert_has(&load_err(&p), &["shapes[0].emission"]);
    let p = d.join("cam.json");
    std::fs::write(
        &p,
        r#"{"camera": {"position": [0, 0, 5], "look_at": [0, 0, 5], "fov": 40, "resolution": [8, 8]}}"#,
    )
    .unwrap();
    assert_has(&load_err(&p), &["camera", "look_at"]);
}

#[test]
fn obj_and_ply_meshes_load() {
    let d = folder("meshes");
    // A unit quad as an OBJ polygon (triangulated), with normals and uvs.
    std::fs::write(
        d.join("quad.obj"),
        "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nvn 0 0 1\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1/1 2/2/1 3/3/1 4/4/1\n",
    )
    .unwrap();
    // The same quad as ASCII PLY.
    std::fs::write(
        d.join("quad.ply"),
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n-1 -1 1\n1 -1 1\n1 1 1\n-1 1 1\n4 0 1 2 3\n",
    )
    .unwrap();
    // And as binary little-endian PLY with normals.
    let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
    for v in [[0.0f32, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]] {
        for c in v.iter().chain([0.0f32, 0.0, 1.0].iter()) {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    bin.push(3);
    for i in [0i32, 1, 2] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    std::fs::write(d.join("tri.ply"), bin).unwrap();
    let p = scene_with_shapes(
        &d,
        r#"{"type": "mesh", "file": "quad.obj", "material": "m"},
           {"type": "mesh", "file": "quad.ply", "material": "m", "transform": [{"translate": [0, 0, 0.5]}]},
           {"type": "mesh", "file": "tri.ply", "material": "m", "emission": 2}"#,
    );
    let scene = Scene::load(&p).expect("meshes load");
    assert_eq!(scene.triangles.len(), 2 + 2 + 1);
    assert_eq!(scene.lights.len(), 1);
    // The translated PLY quad sits at z = 1.5, in front of the OBJ quad at z = 0.
    let hit = scene
        .intersect(&omis::geometry::Ray::new(
            omis::geometry::Vec3::new(0.2, -0.3, 5.0),
            omis::geometry::Vec3::NEG_Z,
        ))
        .expect("hit");
    assert!(
        (hit.p.z - 2.0).abs() < 1e-5 || (hit.p.z - 1.5).abs() < 1e-5,
        "{:?}",
        hit.p
    );
    // A malformed PLY is an error naming the file.
    std::fs::write(
        d.join("broken.ply"),
        "ply\nformat ascii 1.0\nelement vertex 2\nend_header\n1 2\n",
    )
    .unwrap();
    let p = scene_with_shapes(
        &d,
        r#"{"type": "mesh", "file": "broken.ply", "material": "m"}"#,
    );
    assert_has(&load_err(&p), &["shapes[0].file", "broken.ply"]);
}

/// Vertex normals that are the geometric normal (a flat mesh exported with normals) shade as
/// the geometric normal does, without interpolation; curved ones are interpolated. Uvs are kept
/// only where the material reads them.
#[test]
fn flat_vertex_normals_are_the_geometric_normal() {
    use omis::geometry::{Ray, Vec3};
    let d = folder("flat-normals");
    // The same quad at z = 0 twice: normals along +z (flat) and tilted apart (curved).
    std::fs::write(
        d.join("flat.obj"),
        "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nvn 0 0 1\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1/1 2/2/1 3/3/1 4/4/1\n",
    )
    .unwrap();
    std::fs::write(
        d.join("curved.obj"),
        "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nvn -0.6 0 0.8\nvn 0.6 0 0.8\nf 1//1 2//2 3//2 4//1\n",
    )
    .unwrap();
    let p = scene_with_shapes(
        &d,
        r#"{"type": "mesh", "file": "flat.obj", "material": "m"},
           {"type": "mesh", "file": "curved.obj", "material": "m", "transform": [{"translate": [0, 0, -1]}]}"#,
    );
    let scene = Scene::load(&p).expect("meshes load");
    let flags: Vec<(bool, bool)> = scene
        .triangles
        .iter()
        .map(|t| (t.has_normals, t.has_uvs))
        .collect();
    assert_eq!(
        flags,
        [(false, false); 2]
            .iter()
            .chain(&[(true, false); 2])
            .copied()
            .collect::<Vec<_>>()
    );
    let down = |x: f32, z: f32| {
        scene
            .intersect(&Ray::new(Vec3::new(x, 0.3, z), Vec3::NEG_Z))
            .expect("hit")
    };
    let flat = down(0.5, 5.0);
    assert_eq!(flat.ns, flat.ng);
    assert_eq!(flat.ns, Vec3::Z);
    // Behind the flat quad: a ray starting between the two.
    let curved = down(0.5, -0.5);
    assert!((curved.p.z + 1.0).abs() < 1e-6);
    assert!(
        (curved.ns - Vec3::new(0.3, 0.0, 0.8).normalize()).length() < 1e-5,
        "{:?}",
        curved.ns
    );
}

/// Light-sampling densities skip the sum over lights only where no ray meets two emitters; there
/// they equal the sum.
#[test]
fn the_light_pdf_skips_the_sum_only_where_no_ray_meets_two_emitters() {
    use omis::geometry::{Vec2, Vec3};
    use omis::sampler::Pcg32;
    use omis::scene::NO_LIGHT;
    let d = folder("one-emitter-per-ray");
    let quad = |corner: [f32; 3], e1: [f32; 3], e2: [f32; 3]| {
        format!(
            r#"{{"type": "quad", "material": "m", "corner": {corner:?}, "edge1": {e1:?}, "edge2": {e2:?}, "emission": 2}}"#
        )
    };
    let down = ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
    let cases = [
        // Two quads side by side in the plane y = 2, sharing an edge: four triangles, no overlap.
        (quad([-1.0, 2.0, -0.5], down.0, down.1) + ", " + &quad([0.0, 2.0, -0.5], down.0, down.1), true),
        // The same plane, overlapping by a quarter of a quad.
        (quad([-1.0, 2.0, -0.5], down.0, down.1) + ", " + &quad([-0.25, 2.0, -0.5], down.0, down.1), false),
        // Parallel planes: a ray can cross both.
        (quad([-1.0, 2.0, -0.5], down.0, down.1) + ", " + &quad([-1.0, 2.5, -0.5], down.0, down.1), false),
        // One quad is two triangles in one plane.
        (quad([-1.0, 2.0, -0.5], down.0, down.1), true),
        // A sphere light alone.
        (r#"{"type": "sphere", "center": [0, 2, 0], "radius": 0.3, "material": "m", "emission": 2}"#.to_string(), true),
    ];
    for (k, (shapes, want)) in cases.iter().enumerate() {
        let floor = r#"{"type": "quad", "material": "m", "corner": [-3, 0, -3], "edge1": [6, 0, 0], "edge2": [0, 0, 6]}"#;
        let p = scene_with_shapes(&d, &format!("{floor}, {shapes}"));
        let scene = Scene::load(&p).expect("scene loads");
        assert_eq!(scene.one_emitter_per_ray(), *want, "case {k}");
        // From points on the floor: each light sample's density and a hit light's density
        // against the sum over every light the ray meets.
        let mut checked = 0;
        // Samples where the sampled light's own density is not the sum: where the shortcut is
        // refused, there must be some, or the case tests nothing.
        let mut two_lights = 0;
        let mut rng = Pcg32::new(17, k as u64);
        for _ in 0..400 {
            let mut f = || rng.next_f32();
            let p = Vec3::new(4.0 * f() - 2.0, 1e-3, 4.0 * f() - 2.0);
            let Some((l, pmf)) = scene.sample_light(f()) else {
                continue;
            };
            let Some(ls) = scene.lights[l as usize].sample_li(p, Vec2::new(f(), f())) else {
                continue;
            };
            let sum = scene.light_pdf_dir(p, ls.wi);
            let close = |a: f32| (a - sum).abs() <= 1e-4 * sum;
            if *want {
                assert!(
                    close(scene.light_pdf_sampled(p, ls.wi, pmf, ls.pdf)),
                    "case {k}"
                );
                let hit = scene
                    .intersect(&omis::geometry::Ray::new(p, ls.wi))
                    .expect("hit");
                assert_ne!(hit.light, NO_LIGHT, "case {k}");
                assert!(close(scene.light_pdf_hit(p, ls.wi, hit.light)), "case {k}");
            } else {
                assert_eq!(scene.light_pdf_sampled(p, ls.wi, pmf, ls.pdf), sum);
                if (pmf * ls.pdf - sum).abs() > 1e-3 * sum {
                    two_lights += 1;
                }
            }
            checked += 1;
        }
        assert!(checked > 300, "case {k}: {checked}");
        assert!(*want || two_lights > 20, "case {k}: {two_lights}");
    }
}

#[test]
fn shipped_scenes_load() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).expect("scenes/") {
        let p = e.expect("entry").path();
        if p.extension().is_some_and(|x| x == "json") {
            let s = Scene::load(&p).unwrap_or_else(|e| panic!("{e}"));
            assert!(!s.lights.is_empty(), "{} has no light", p.display());
            n += 1;
        }
    }
    assert!(n >= 4, "expected the four shipped scenes, found {n}");
}

#[test]
fn the_documented_example_scene_loads() {
    // The complete example of scenes/README.md, with the files it names made up here.
    let doc =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/README.md"))
            .expect("scenes/README.md");
    let start = doc.find("```json\n").expect("a json block") + "```json\n".len();
    let end = start + doc[start..].find("```").expect("end of block");
    let d = folder("doc-example");
    std::fs::create_dir_all(d.join("models")).unwrap();
    std::fs::create_dir_all(d.join("textures")).unwrap();
    std::fs::write(
        d.join("models/bunny.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    std::fs::write(
        d.join("models/table.ply"),
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 0 1\n3 0 1 2\n",
    )
    .unwrap();
    image::RgbImage::from_pixel(2, 2, image::Rgb([200, 150, 100]))
        .save(d.join("textures/wood.jpg"))
        .unwrap();
    let p = d.join("example.json");
    std::fs::write(&p, &doc[start..end]).unwrap();
    let scene = Scene::load(&p).unwrap_or_else(|e| panic!("documented example: {e}"));
    assert_eq!(scene.materials.len(), 9);
    assert_eq!(scene.spheres.len(), 1);
    // Two emitting triangles of the quad light and the point light.
    assert_eq!(scene.lights.len(), 3);
}

#[test]
fn a_path_outside_the_folder_gets_one_answer_whether_or_not_it_exists() {
    // The answer must not tell whether a file outside the scene's folder exists.
    let root = folder("oracle");
    let inner = root.join("inner");
    std::fs::create_dir_all(&inner).unwrap();
    let secret = root.join("secret.obj");
    let abs = secret.display().to_string();
    let mut paths = vec![
        "../secret.obj".to_string(),
        abs,
        "a/../../secret.obj".into(),
    ];
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(&root, inner.join("up")).unwrap();
        paths.push("up/secret.obj".into());
    }
    for rel in &paths {
        let p = scene_with_shapes(
            &inner,
            &format!(r#"{{"type": "mesh", "file": "{rel}", "material": "m"}}"#),
        );
        std::fs::write(&secret, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
        let exists = load_err(&p);
        std::fs::remove_file(&secret).unwrap();
        let missing = load_err(&p);
        assert_eq!(exists, missing, "'{rel}'");
        assert_has(&exists, &["shapes[0].file", rel]);
        assert!(!exists.contains("not found"), "{exists}");
    }
    // Inside the folder a missing file is simply not found.
    let p = scene_with_shapes(
        &inner,
        r#"{"type": "mesh", "file": "sub/../gone.obj", "material": "m"}"#,
    );
    assert_has(&load_err(&p), &["shapes[0].file", "gone.obj", "not found"]);
}

#[test]
fn the_file_list_holds_every_file_the_scene_reads() {
    let d = folder("file-list");
    std::fs::create_dir_all(d.join("models")).unwrap();
    std::fs::write(
        d.join("models/tri.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    image::RgbImage::from_pixel(2, 2, image::Rgb([200, 150, 100]))
        .save(d.join("wood.png"))
        .unwrap();
    let p = d.join("scene.json");
    std::fs::write(
        &p,
        format!(
            "{{\n{CAMERA},\n\"materials\": {{\"w\": {{\"type\": \"lambert\", \"albedo\": {{\"texture\": \"wood.png\"}}}}}},\n\
             \"shapes\": [{{\"type\": \"mesh\", \"file\": \"models/tri.obj\", \"material\": \"w\"}},\n\
             {{\"type\": \"mesh\", \"file\": \"./models/../models/tri.obj\", \"material\": \"w\"}}]\n}}\n"
        ),
    )
    .unwrap();
    let scene = Scene::load(&p).unwrap_or_else(|e| panic!("{e}"));
    let canon = |n: &str| d.join(n).canonicalize().unwrap();
    assert_eq!(
        scene.files,
        vec![canon("models/tri.obj"), canon("wood.png")]
    );
}

/// Loads `path` on a thread with a 256 KiB stack, so that recursion as deep as the input is long
/// (a degenerate BVH: the BVH2 -> CWBVH conversion recurses per level) fails the test.
fn load_on_small_stack(path: PathBuf) -> Scene {
    std::thread::Builder::new()
        .stack_size(256 * 1024)
        .spawn(move || Scene::load(&path).unwrap_or_else(|e| panic!("{e}")))
        .expect("spawn")
        .join()
        .expect("loading panicked")
}

/// `n` faces over the vertices `v` (OBJ text): face k uses vertices f(k).
fn obj(v: &[[f32; 3]], n: usize, f: impl Fn(usize) -> [usize; 3]) -> String {
    let mut s = String::new();
    for p in v {
        s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    for k in 0..n {
        let [a, b, c] = f(k);
        s += &format!("f {} {} {}\n", a + 1, b + 1, c + 1);
    }
    s
}

#[test]
fn coincident_and_degenerate_triangles_load_with_a_shallow_bvh() {
    // Each case: 30,000 triangles that PLOC cannot pair (one centroid for all), and how many
    // survive loading. Before the coincident groups, 30,000 copies took ~50 s to load and
    // built a chain of that depth.
    const N: usize = 30_000;
    let d = folder("coincident");
    let copies = obj(
        &[[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]],
        N,
        |_| [0, 1, 2],
    );
    // Zero area (collinear): dropped by the loader.
    let flat = obj(
        &[[-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
        N,
        |_| [0, 1, 2],
    );
    // Slivers of area ~1e-20 (kept: the cross product does not underflow), all alike.
    let slivers = obj(
        &[[-1.0, -1e-20, 0.0], [1.0, -1e-20, 0.0], [0.0, 1e-20, 0.0]],
        N,
        |_| [0, 1, 2],
    );
    // Nested triangles symmetric about the origin: different bounds, one centroid.
    let nested: Vec<[f32; 3]> = (0..N)
        .flat_map(|k| {
            let s = 1.0 + k as f32 * 1e-3;
            [[-s, -s, 0.0], [s, -s, 0.0], [0.0, s, 0.0]]
        })
        .collect();
    let nested = obj(&nested, N, |k| [3 * k, 3 * k + 1, 3 * k + 2]);
    for (name, text, kept) in [
        ("copies", copies, N),
        ("flat", flat, 0),
        ("slivers", slivers, N),
        ("nested", nested, N),
    ] {
        std::fs::write(d.join(format!("{name}.obj")), text).unwrap();
        // One ordinary triangle besides, behind the others.
        let p = scene_with_shapes(
            &d,
            &format!(
                r#"{{"type": "mesh", "file": "{name}.obj", "material": "m"}},
                   {{"type": "triangles", "positions": [[-2, -2, -1], [2, -2, -1], [0, 2, -1]], "indices": [[0, 1, 2]], "material": "m"}}"#
            ),
        );
        let scene = load_on_small_stack(p);
        assert_eq!(scene.triangles.len(), kept + 1, "{name}");
        let stats = scene.accel().stats;
        // A balanced wide BVH over 30,001 primitives has ~5 levels; CWBVH traversal keeps a
        // 32-entry stack.
        assert!(stats.depth <= 12, "{name}: BVH depth {}", stats.depth);
        assert_eq!(stats.coincident, kept, "{name}");
        // Rays find the nearest surface: the group at z = 0 where it has area, else the
        // triangle behind.
        let hit = scene
            .intersect(&omis::geometry::Ray::new(
                omis::geometry::Vec3::new(0.0, -0.5, 5.0),
                omis::geometry::Vec3::NEG_Z,
            ))
            .expect("hit");
        let z = if name == "copies" || name == "nested" {
            0.0
        } else {
            -1.0
        };
        assert!((hit.p.z - z).abs() < 1e-5, "{name}: hit at {:?}", hit.p);
    }
}

#[test]
fn non_finite_vertices_are_refused_naming_the_mesh_in_every_format() {
    let d = folder("nonfinite");
    std::fs::write(d.join("bad.obj"), "v 0 0 0\nv 1 0 0\nv 0 inf 0\nf 1 2 3\n").unwrap();
    // Binary PLY carries a NaN as it is (the ASCII parser refuses the word).
    let mut ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
    for c in [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, f32::NAN, 1.0, 0.0] {
        ply.extend_from_slice(&c.to_le_bytes());
    }
    ply.push(3);
    for i in [0i32, 1, 2] {
        ply.extend_from_slice(&i.to_le_bytes());
    }
    std::fs::write(d.join("bad.ply"), ply).unwrap();
    for mesh in ["bad.obj", "bad.ply"] {
        let p = scene_with_shapes(
            &d,
            &format!(r#"{{"type": "mesh", "file": "{mesh}", "material": "m"}}"#),
        );
        assert_has(
            &load_err(&p),
            &["shapes[0]", mesh, "vertex 2 is not finite"],
        );
        let ty = &mesh[4..];
        let xml = d.join(format!("scene-{ty}.xml"));
        std::fs::write(
            &xml,
            format!(
                r#"<scene version="0.5.0">
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="toWorld"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
  </sensor>
  <shape type="{ty}"><string name="filename" value="{mesh}"/></shape>
</scene>
"#
            ),
        )
        .unwrap();
        assert_has(&load_err(&xml), &["line 6", mesh, "vertex 2 is not finite"]);
    }
    let pbrt = d.join("scene.pbrt");
    std::fs::write(
        &pbrt,
        "LookAt 0 0 5  0 0 0  0 1 0\nCamera \"perspective\" \"float fov\" [40]\nFilm \"image\" \"integer xresolution\" [8] \"integer yresolution\" [8]\nWorldBegin\nShape \"plymesh\" \"string filename\" \"bad.ply\"\nWorldEnd\n",
    )
    .unwrap();
    assert_has(
        &load_err(&pbrt),
        &["line 5", "bad.ply", "vertex 2 is not finite"],
    );
}
