//! The pbrt-v3 importer: every directive from small files written to a temporary folder,
//! errors that name file and line; the pbrt dialects and the files a scene reads; and the public
//! scenes in `../shared/scenes` loaded, rendered and compared with our own scenes and between
//! formats. The Mitsuba 0.5 importer's elements are in `import_mitsuba.rs`.

mod common;

use common::import::{
    assert_has, close, load, load_err, material, warning, write_obj, write_plys, write_png,
};
use omis::film::PixelSums;
use omis::geometry::{Vec2, Vec3};
use omis::integrator::RenderSettings;
use omis::light::Light;
use omis::material::MaterialKind;
use omis::sampler::SamplerKind;
use omis::scene::Scene;
use std::path::{Path, PathBuf};
use std::time::Instant;

// ------------------------------------------------------------------------------------------
// Helpers.

fn folder(name: &str) -> PathBuf {
    common::folder("import", name)
}

fn render(scene: &Scene, spp: u32, max_depth: u32, seed: u64) -> PixelSums {
    let settings = RenderSettings {
        sample_block: spp,
        max_depth,
        seed,
        sampler: SamplerKind::Independent,
        ..Default::default()
    };
    omis::job::Resolved::fixed(scene, &settings, 16, 64)
        .render_in_process(scene, &|_| {})
        .sums()
        .clone()
}

/// Mean and standard error of the mean over a pixel region (pixels are independent estimates).
fn region(sums: &PixelSums, x0: usize, y0: usize, x1: usize, y1: usize, c: usize) -> (f64, f64) {
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

/// Compares two renders region by region, every channel, within 4 combined standard errors.
/// Returns the number of regions with signal.
fn compare_regions(
    what: &str,
    a: &PixelSums,
    b: &PixelSums,
    regions: &[(usize, usize, usize, usize)],
) -> usize {
    let mut lit = 0;
    let mut worst: f64 = 0.0;
    for &(x0, y0, x1, y1) in regions {
        for c in 0..3 {
            let (ma, sa) = region(a, x0, y0, x1, y1, c);
            let (mb, sb) = region(b, x0, y0, x1, y1, c);
            let se = (sa * sa + sb * sb).sqrt();
            // A tiny relative allowance covers f32 rounding where both are exact.
            let tol = 4.0 * se + 1e-6 * ma.abs().max(mb.abs());
            assert!(
                (ma - mb).abs() <= tol,
                "{what}: region ({x0},{y0})-({x1},{y1}) channel {c}: {ma} vs {mb} (tol {tol})"
            );
            worst = worst.max((ma - mb).abs() / se.max(1e-12));
            if ma > 1e-3 {
                lit += 1;
            }
        }
    }
    eprintln!(
        "{what}: worst difference {worst:.2} standard errors over {} regions",
        regions.len()
    );
    lit
}

fn grid(w: usize, h: usize, n: usize) -> Vec<(usize, usize, usize, usize)> {
    let mut r = Vec::new();
    for ry in 0..n {
        for rx in 0..n {
            r.push((rx * w / n, ry * h / n, (rx + 1) * w / n, (ry + 1) * h / n));
        }
    }
    r
}

fn mean_rgb(sums: &PixelSums) -> [f64; 3] {
    sums.mean().mean()
}

/// Peak resident memory of this process (VmHWM), in MiB.
fn peak_memory_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

// ------------------------------------------------------------------------------------------
// pbrt-v3: directives.

const PBRT_HEADER: &str = r#"# a comment line
Integrator "path" "integer maxdepth" [ 7 ]
Sampler "halton" "integer pixelsamples" 9
PixelFilter "box"
Film "image" "integer xresolution" [ 40 ] "integer yresolution" [ 20 ] "string filename" "out.exr"
LookAt 0 1 10  0 1 0  0 1 0
Camera "perspective" "float fov" [ 30 ]
"#;

#[test]
fn pbrt_options_camera_and_world_directives() {
    let d = folder("pbrt-directives");
    let p = common::write(
        &d,
        "scene.pbrt",
        &format!(
            r#"{PBRT_HEADER}
WorldBegin
  MakeNamedMaterial "white" "string type" "matte" "rgb Kd" [ 0.5 0.6 0.7 ]
  MakeNamedMaterial "shiny" "string type" [ "metal" ] "float roughness" 0.1
  MakeNamedMaterial "raw" "string type" [ "metal" ] "float roughness" 0.1 "bool remaproughness" "false"
      "rgb eta" [ 1 2 3 ] "rgb k" [ 4 5 6 ]
  MakeNamedMaterial "aniso" "string type" "metal" "float uroughness" 0.2 "float vroughness" 0.3
      "bool remaproughness" false
  MakeNamedMaterial "paint" "string type" "plastic" "rgb Kd" [ 0.3 0.2 0.1 ] "rgb Ks" [ 0.4 0.4 0.4 ]
      "float roughness" 0.05 "bool remaproughness" "false"
  MakeNamedMaterial "coat" "string type" "substrate" "rgb Kd" [ 0.3 0.3 0.3 ] "rgb Ks" [ 0.1 0.1 0.1 ]
  MakeNamedMaterial "mirror" "string type" "mirror" "rgb Kr" [ 0.8 0.8 0.8 ]
  MakeNamedMaterial "glass" "string type" "glass" "float index" 1.33
  MakeNamedMaterial "uberplastic" "string type" "uber" "rgb Kd" [ 0.2 0.2 0.2 ] "float eta" 1.4
  MakeNamedMaterial "uberglass" "string type" "uber" "rgb Kd" [ 0 0 0 ] "rgb Ks" [ 0 0 0 ] "rgb Kt" [ 1 1 1 ] "rgb Kr" [ 1 1 1 ]

  NamedMaterial "white"
  Shape "trianglemesh" "integer indices" [ 0 1 2 0 2 3 ]
      "point P" [ -5 0 -5  5 0 -5  5 0 5  -5 0 5 ]
      "normal N" [ 0 1 0 0 1 0 0 1 0 0 1 0 ]
      "float uv" [ 0 0 1 0 1 1 0 1 ]
  AttributeBegin
    Material "plastic" "rgb Kd" [ 0.1 0.2 0.3 ]
    Translate 1 0 0
    Scale 2 2 2
    Shape "sphere" "float radius" 0.5
    TransformBegin
      Rotate 90 0 0 1
      Translate 1 0 0
      NamedMaterial "mirror"
      Shape "sphere" "float radius" 0.25
    TransformEnd
    ConcatTransform [ 1 0 0 0  0 1 0 0  0 0 1 0  0 0 3 1 ]
    Shape "sphere"
  AttributeEnd
  # After AttributeEnd: identity again and the "white" material.
  Shape "sphere" "float radius" 0.125
  AttributeBegin
    Transform [ 1 0 0 0  0 1 0 0  0 0 1 0  4 5 6 1 ]
    Identity
    Translate 0 2 0
    AreaLightSource "diffuse" "rgb L" [ 10 20 30 ] "rgb scale" [ 2 2 2 ]
    Shape "sphere" "float radius" 0.3
  AttributeEnd
  LightSource "point" "rgb I" [ 5 5 5 ] "point from" [ 0 4 0 ]
WorldEnd
"#
        ),
    );
    let s = load(&p);
    // Everything here is supported; only the substrate approximation is worth a warning.
    assert_eq!(s.warnings.len(), 1, "{:#?}", s.warnings);
    assert_has(
        warning(&s, "substrate"),
        &["scene.pbrt:18", "layered plastic"],
    );
    // Integrator, Sampler, Film.
    assert_eq!(s.defaults.max_depth, Some(7));
    assert_eq!(s.defaults.spp, Some(9));
    assert_eq!((s.camera.width, s.camera.height), (40, 20));
    // Landscape: pbrt's fov is on the shorter (vertical) axis.
    assert!(
        close(s.camera.vfov_deg, 30.0, 1e-5),
        "{}",
        s.camera.vfov_deg
    );
    assert!((s.camera.position - Vec3::new(0.0, 1.0, 10.0)).length() < 1e-5);
    // A LookAt camera is a proper rotation in pbrt's left-handed camera space: mirrored for us.
    assert!(s.camera.flip_x());

    // Shapes: spheres in creation order with their CTMs.
    let sph: Vec<(Vec3, f32)> = s.spheres.iter().map(|x| (x.center, x.radius)).collect();
    let expect = [
        (Vec3::new(1.0, 0.0, 0.0), 1.0), // Translate 1 0 0, Scale 2: radius 0.5 * 2
        (Vec3::new(1.0, 2.0, 0.0), 0.5), // then Rotate 90 about z of (1, 0, 0): (0, 1, 0) * 2
        (Vec3::new(1.0, 0.0, 6.0), 2.0), // ConcatTransform translate z 3 (scaled by 2)
        (Vec3::new(0.0, 0.0, 0.0), 0.125), // AttributeEnd restored the identity
        (Vec3::new(0.0, 2.0, 0.0), 0.3), // Identity dropped the Transform
    ];
    assert_eq!(sph.len(), expect.len());
    for (i, ((c, r), (ec, er))) in sph.iter().zip(expect).enumerate() {
        assert!(
            (*c - ec).length() < 1e-4 && close(*r, er, 1e-5),
            "sphere {i}: {c:?} r {r}, expected {ec:?} r {er}"
        );
    }
    // Materials: AttributeEnd restored "white"; the TransformBegin block's NamedMaterial stays
    // until AttributeEnd.
    let mat = |i: usize| &s.materials[s.spheres[i].material as usize];
    assert!(matches!(
        mat(0).kind,
        MaterialKind::Plastic { layered: false, .. }
    ));
    assert_eq!(mat(1).name, "mirror");
    assert_eq!(mat(2).name, "mirror");
    assert_eq!(mat(3).name, "white");
    assert!(
        s.materials.iter().all(|m| m.two_sided),
        "pbrt materials are two-sided"
    );
    // The area light: L * scale, only on the sphere inside its AttributeBegin.
    assert_eq!(s.lights.len(), 2);
    assert!(s.lights.iter().any(
        |l| matches!(l, Light::Sphere { radiance, .. } if *radiance == Vec3::new(20.0, 40.0, 60.0))
    ));
    assert!(s.lights.iter().any(|l| matches!(l, Light::Point { position, intensity } if (*position - Vec3::new(0.0, 4.0, 0.0)).length() < 1e-6 && *intensity == Vec3::splat(5.0))));
    assert_eq!(s.stats.triangles, 2);
    assert!(s.uvs.iter().any(|uv| *uv == Vec2::new(1.0, 1.0)));

    // Material mappings.
    match &material(&s, "white").kind {
        MaterialKind::Lambert { albedo } => assert_eq!(albedo.average(), Vec3::new(0.5, 0.6, 0.7)),
        k => panic!("matte became {k:?}"),
    }
    match &material(&s, "shiny").kind {
        MaterialKind::RoughConductor {
            alpha_u,
            alpha_v,
            eta,
            ..
        } => {
            // pbrt-v3 RoughnessToAlpha(0.1), and the default copper.
            let a = omis::scene::pbrt::roughness_to_alpha(0.1);
            assert!(close(*alpha_u, a, 1e-6) && close(*alpha_v, a, 1e-6));
            assert!((a - 0.46176).abs() < 1e-4, "{a}");
            assert!(close(eta.x, 0.200438, 1e-5));
        }
        k => panic!("metal became {k:?}"),
    }
    match &material(&s, "raw").kind {
        MaterialKind::RoughConductor {
            alpha_u,
            eta,
            k,
            scale,
            ..
        } => {
            assert_eq!(*alpha_u, 0.1);
            assert_eq!(*eta, Vec3::new(1.0, 2.0, 3.0));
            assert_eq!(*k, Vec3::new(4.0, 5.0, 6.0));
            assert_eq!(*scale, Vec3::ONE);
        }
        k => panic!("metal became {k:?}"),
    }
    match &material(&s, "aniso").kind {
        MaterialKind::RoughConductor {
            alpha_u, alpha_v, ..
        } => assert_eq!((*alpha_u, *alpha_v), (0.2, 0.3)),
        k => panic!("metal became {k:?}"),
    }
    match &material(&s, "paint").kind {
        MaterialKind::Plastic {
            specular,
            ior,
            alpha,
            layered,
            ..
        } => {
            assert_eq!(
                (*specular, *ior, *alpha, *layered),
                (Vec3::splat(0.4), 1.5, 0.05, false)
            );
        }
        k => panic!("plastic became {k:?}"),
    }
    assert!(matches!(
        material(&s, "coat").kind,
        MaterialKind::Plastic { layered: true, .. }
    ));
    assert!(
        matches!(material(&s, "mirror").kind, MaterialKind::Mirror { reflectance } if reflectance == Vec3::splat(0.8))
    );
    assert!(
        matches!(material(&s, "glass").kind, MaterialKind::Dielectric { ior, .. } if ior == 1.33)
    );
    assert!(
        matches!(material(&s, "uberplastic").kind, MaterialKind::Plastic { ior, layered: false, .. } if ior == 1.4)
    );
    assert!(matches!(
        material(&s, "uberglass").kind,
        MaterialKind::Dielectric { .. }
    ));
}

#[test]
fn pbrt_fov_is_on_the_shorter_axis() {
    let d = folder("pbrt-fov");
    for (w, h, expect) in [
        (40u32, 20u32, 30.0f32),
        (
            20,
            40,
            2.0 * ((15.0f32).to_radians().tan() * 2.0).atan().to_degrees(),
        ),
        (30, 30, 30.0),
    ] {
        let p = common::write(
            &d,
            "fov.pbrt",
            &format!(
                "Film \"image\" \"integer xresolution\" {w} \"integer yresolution\" {h}\nCamera \"perspective\" \"float fov\" 30\nWorldBegin\nWorldEnd\n"
            ),
        );
        let s = load(&p);
        assert!(
            close(s.camera.vfov_deg, expect, 1e-5),
            "{w}x{h}: {} vs {expect}",
            s.camera.vfov_deg
        );
    }
}

#[test]
fn pbrt_camera_handedness_decides_mirroring() {
    let d = folder("pbrt-hand");
    // A camera at the origin looking down +z with +y up. In pbrt-v3, camera +x = up x dir = +x
    // is on the image's right; our right-handed camera would show -x there.
    let right_of = |prefix: &str| {
        let p = common::write(
            &d,
            "h.pbrt",
            &format!(
                "Film \"image\" \"integer xresolution\" 32 \"integer yresolution\" 32\n{prefix}\nLookAt 0 0 0  0 0 1  0 1 0\nCamera \"perspective\" \"float fov\" 40\nWorldBegin\nWorldEnd\n"
            ),
        );
        let s = load(&p);
        (s.camera.ray(Vec2::new(30.0, 16.0)).d.x, s.camera.flip_x())
    };
    let (x, flip) = right_of("");
    assert!(
        x > 0.0 && flip,
        "pbrt LookAt: +x must be on the right ({x}, flip {flip})"
    );
    // The usual trick to make a pbrt camera right-handed: the image shows -x on the right.
    let (x, flip) = right_of("Scale -1 1 1");
    assert!(
        x < 0.0 && !flip,
        "Scale -1 1 1: -x on the right ({x}, flip {flip})"
    );
}

#[test]
fn pbrt_plymesh_ascii_and_binary_include_and_instances() {
    let d = folder("pbrt-ply");
    write_plys(&d);
    common::write(
        &d,
        "geometry.pbrt",
        "# included\nShape \"plymesh\" \"string filename\" \"quad.ply\"\n",
    );
    let p = common::write(
        &d,
        "scene.pbrt",
        r#"Film "image" "integer xresolution" 8 "integer yresolution" 8
Camera "perspective"
WorldBegin
Include "geometry.pbrt"
Shape "plymesh" "string filename" [ "models/quad-bin.ply" ]
ObjectBegin "pair"
  Translate 0 0 5
  Shape "plymesh" "string filename" "quad.ply"
ObjectEnd
AttributeBegin
  Translate 10 0 0
  ObjectInstance "pair"
AttributeEnd
ObjectInstance "pair"
WorldEnd
"#,
    );
    let s = load(&p);
    assert_eq!(
        s.stats.triangles, 8,
        "2 (ASCII) + 2 (binary) + 2 instances x 2"
    );
    let (lo, hi) = s.bounds();
    assert!((lo - Vec3::ZERO).length() < 1e-6, "{lo:?}");
    assert!((hi - Vec3::new(11.0, 1.0, 5.0)).length() < 1e-6, "{hi:?}");
}

#[test]
fn pbrt_errors_name_file_and_line() {
    let d = folder("pbrt-errors");
    let case = |name: &str, body: &str| -> String {
        let p = common::write(&d, name, body);
        load_err(&p)
    };
    let world = |body: &str| format!("Camera \"perspective\"\nWorldBegin\n{body}\nWorldEnd\n");

    // Malformed token.
    let e = case(
        "malformed.pbrt",
        &world("Shape \"sphere\" \"float radius\" [ 1.2.3 ]"),
    );
    assert_has(
        &e,
        &["malformed.pbrt", "line 3", "malformed number '1.2.3'"],
    );
    let e = case("string.pbrt", &world("Shape \"sphere"));
    assert_has(&e, &["string.pbrt", "line 3", "string"]);
    // Unknown directive.
    let e = case("unknown.pbrt", &world("\n\nFrobnicate \"x\""));
    assert_has(
        &e,
        &["unknown.pbrt", "line 5", "unknown directive 'Frobnicate'"],
    );
    // Missing file.
    let e = case(
        "missing.pbrt",
        &world("Shape \"plymesh\" \"string filename\" \"nope.ply\""),
    );
    assert_has(&e, &["missing.pbrt", "line 3", "nope.ply", "not found"]);
    // Paths may not leave the scene's folder.
    let e = case(
        "escape.pbrt",
        &world("Shape \"plymesh\" \"string filename\" \"../../etc/passwd.ply\""),
    );
    assert_has(&e, &["escape.pbrt", "line 3"]);
    // Unsupported lights are errors, never a silently different image.
    for (i, ty) in ["infinite", "distant", "spot", "goniometric", "projection"]
        .iter()
        .enumerate()
    {
        let e = case(
            &format!("light{i}.pbrt"),
            &world(&format!("LightSource \"{ty}\"")),
        );
        assert_has(
            &e,
            &[&format!("light{i}.pbrt"), "line 3", ty, "not supported"],
        );
    }
    let e = case(
        "blackbody.pbrt",
        &world("AreaLightSource \"diffuse\" \"blackbody L\" [ 6500 1 ]"),
    );
    assert_has(&e, &["line 3", "blackbody"]);
    let e = case("shape.pbrt", &world("Shape \"cylinder\""));
    assert_has(&e, &["line 3", "cylinder", "not supported"]);
    let e = case(
        "partial.pbrt",
        &world("Shape \"sphere\" \"float zmax\" 0.5"),
    );
    assert_has(&e, &["line 3", "partial spheres"]);
    let e = case(
        "camera.pbrt",
        "Camera \"orthographic\"\nWorldBegin\nWorldEnd\n",
    );
    assert_has(&e, &["camera.pbrt", "line 1", "orthographic"]);
    // Parameter-list errors.
    let e = case("decl.pbrt", &world("Shape \"sphere\" \"radius\" 1"));
    assert_has(&e, &["line 3", "malformed parameter declaration"]);
    let e = case("type.pbrt", &world("Shape \"sphere\" \"real radius\" 1"));
    assert_has(&e, &["line 3", "unknown parameter type 'real'"]);
    let e = case(
        "novalue.pbrt",
        &world("Shape \"sphere\" \"float radius\"\nWorldEnd"),
    );
    assert_has(&e, &["line 3", "no value"]);
    let e = case(
        "kind.pbrt",
        &world("Shape \"sphere\" \"float radius\" \"big\""),
    );
    assert_has(&e, &["line 3", "expects numbers"]);
    let e = case("named.pbrt", &world("NamedMaterial \"nothing\""));
    assert_has(&e, &["line 3", "unknown material \"nothing\""]);
    let e = case("nesting.pbrt", &world("AttributeEnd"));
    assert_has(&e, &["line 3", "AttributeEnd without AttributeBegin"]);
    let e = case("nums.pbrt", &world("Translate 1 2"));
    assert_has(&e, &["line 3", "Translate expects 3 numbers"]);
    let e = case("noworld.pbrt", "Camera \"perspective\"\n");
    assert_has(&e, &["noworld.pbrt", "WorldBegin"]);
    let e = case(
        "mesh.pbrt",
        &world(
            "Shape \"trianglemesh\" \"point P\" [ 0 0 0 1 0 0 0 1 0 ] \"integer indices\" [ 0 1 5 ]",
        ),
    );
    assert_has(&e, &["line 3", "out of range"]);
    // Errors in an included file name that file.
    common::write(
        &d,
        "inc.pbrt",
        "\nShape \"sphere\" \"float radius\" [ x ]\n",
    );
    let e = case("includer.pbrt", &world("Include \"inc.pbrt\""));
    assert_has(&e, &["inc.pbrt", "line 2"]);
}

#[test]
fn pbrt_unsupported_features_are_reported_once_by_name_and_line() {
    let d = folder("pbrt-warn");
    let p = common::write(
        &d,
        "warn.pbrt",
        r#"Integrator "bdpt" "integer maxdepth" 3
PixelFilter "gaussian" "float xwidth" 2
Camera "perspective" "float lensradius" 0.1
WorldBegin
MakeNamedMaterial "d" "string type" "disney" "rgb Kd" [ 0.3 0.3 0.3 ]
NamedMaterial "d"
Shape "sphere" "float radius" 1 "float frobs" 2
Shape "sphere" "float radius" 2 "float frobs" 2
AttributeBegin
  AreaLightSource "diffuse" "rgb L" [ 1 1 1 ] "bool twosided" "true"
  Shape "trianglemesh" "point P" [ 0 0 0 1 0 0 0 1 0 ]
AttributeEnd
WorldEnd
"#,
    );
    let s = load(&p);
    for w in &s.warnings {
        eprintln!("warning: {w}");
    }
    assert_has(
        warning(&s, "PixelFilter"),
        &["warn.pbrt:2", "\"gaussian\"", "box"],
    );
    assert_has(warning(&s, "bdpt"), &["warn.pbrt:1", "path tracer"]);
    assert_has(warning(&s, "lensradius"), &["warn.pbrt:3"]);
    assert_has(warning(&s, "disney"), &["warn.pbrt:5", "became matte"]);
    assert_has(warning(&s, "twosided"), &["warn.pbrt:10", "front side"]);
    // The same unsupported parameter twice: one warning, at its first line, with a count.
    assert_has(warning(&s, "frobs"), &["warn.pbrt:7", "2 occurrences"]);
    assert_eq!(s.warnings.iter().filter(|w| w.contains("frobs")).count(), 1);
    match &material(&s, "d").kind {
        MaterialKind::Lambert { albedo } => assert_eq!(albedo.average(), Vec3::splat(0.3)),
        k => panic!("{k:?}"),
    }
    assert_eq!(s.defaults.max_depth, Some(3));
}

#[test]
fn pbrt_emission_side_follows_winding_normals_and_reverse_orientation() {
    let d = folder("pbrt-orient");
    // A triangle in the plane y = 1, counter-clockwise seen from below: it faces down.
    let tri =
        r#"Shape "trianglemesh" "point P" [ 0 1 0  1 1 0  0 1 1 ] "integer indices" [ 0 1 2 ]"#;
    let normal_of = |prefix: &str, extra: &str| {
        let p = common::write(
            &d,
            "o.pbrt",
            &format!(
                "Camera \"perspective\"\nWorldBegin\nAttributeBegin\n{prefix}\nAreaLightSource \"diffuse\"\n{tri} {extra}\nAttributeEnd\nWorldEnd\n"
            ),
        );
        let s = load(&p);
        match &s.lights[0] {
            Light::Triangle { n, .. } => n.y,
            l => panic!("{l:?}"),
        }
    };
    assert!(normal_of("", "") < 0.0);
    assert!(normal_of("ReverseOrientation", "") > 0.0);
    // A reflection flips the handedness, which pbrt-v3 compensates for.
    assert!(normal_of("Scale 1 1 -1", "") < 0.0);
    // Vertex normals decide, and ReverseOrientation does not change them (pbrt-v3).
    assert!(normal_of("ReverseOrientation", r#""normal N" [ 0 1 0 0 1 0 0 1 0 ]"#) > 0.0);
}

// ------------------------------------------------------------------------------------------
// The pbrt dialect, and the files a scene reads.

#[test]
fn pbrt_v4_files_are_read_as_pbrt_v4_from_the_first_pbrt_v4_construct() {
    let d = folder("pbrt-v4");
    let head = "LookAt 0 0 5  0 0 0  0 1 0\nCamera \"perspective\" \"float fov\" 40\n";
    // Each body has one pbrt-v4 construct: the file loads as pbrt-v4 (the pbrt-v3 path would
    // have refused, tests/import_pbrt4.rs checks the pbrt-v4 meanings).
    let bodies = [
        "ColorSpace \"srgb\"\nWorldBegin",
        "Option \"bool disablepixeljitter\" true\nWorldBegin",
        "Film \"rgb\" \"integer xresolution\" 8\nWorldBegin",
        "Sampler \"zsobol\"\nWorldBegin",
        "WorldBegin\nMaterial \"diffuse\" \"rgb reflectance\" [ 0.5 0.5 0.5 ]\nShape \"sphere\"",
        "WorldBegin\nMakeNamedMaterial \"c\"\n  \"string type\" \"coateddiffuse\"\nNamedMaterial \"c\"",
        "WorldBegin\nShape \"bilinearmesh\" \"point3 P\" [ 0 0 0 1 0 0 0 1 0 1 1 0 ]",
        "WorldBegin\nAreaLightSource \"diffuse\" \"rgb L\" [ 1 1 1 ]\n  \"float scale\" 4\nShape \"sphere\"",
        "WorldBegin\nLightSource \"point\" \"float power\" 100",
    ];
    for (i, body) in bodies.iter().enumerate() {
        let name = format!("v4-{i}.pbrt");
        load(&common::write(&d, &name, &format!("{head}{body}\n")));
    }
    // `Attribute "shape"` sets a default every later shape of the block reads.
    let s = load(&common::write(
        &d,
        "v4-attribute.pbrt",
        &format!("{head}WorldBegin\nAttribute \"shape\" \"float radius\" 2\nShape \"sphere\"\n"),
    ));
    assert_eq!(s.spheres[0].radius, 2.0);
    // A pbrt-v4 file included from a pbrt-v3 one: read as pbrt-v4 from there on; its errors
    // name it.
    common::write(&d, "v4-part.pbrt", "# pbrt-v4\n\nShape \"bilinearmesh\"\n");
    let e = load_err(&common::write(
        &d,
        "v3-main.pbrt",
        &format!("{head}WorldBegin\nInclude \"v4-part.pbrt\"\nWorldEnd\n"),
    ));
    assert_has(
        &e,
        &["v4-part.pbrt", "line 3", "bilinearmesh has no \"point3 P\""],
    );
    // A whole pbrt-v4 scene (as pbrt-v4 writes them: no WorldEnd) is read as such: the missing
    // mesh is what fails.
    let e = load_err(&common::write(
        &d,
        "v4-scene.pbrt",
        "LookAt 0 1 5  0 1 0  0 1 0\nCamera \"perspective\" \"float fov\" 40\n\
         Sampler \"halton\" \"integer pixelsamples\" 16\n\
         Film \"rgb\" \"string filename\" \"out.exr\"\n\
         WorldBegin\nMaterial \"diffuse\"\nShape \"plymesh\" \"string filename\" \"missing.ply\"\n",
    ));
    assert_has(&e, &["v4-scene.pbrt", "line 7", "missing.ply"]);
    // pbrt-v3 declarations that pbrt-v4 shares are not taken for pbrt-v4.
    let s = load(&common::write(
        &d,
        "v3.pbrt",
        &format!(
            "{head}WorldBegin\nAttributeBegin\nAreaLightSource \"diffuse\" \"rgb L\" [ 1 1 1 ]\n\
             Shape \"sphere\"\nAttributeEnd\nLightSource \"point\" \"rgb I\" [ 1 1 1 ]\n\
             \"rgb scale\" [ 2 2 2 ]\nWorldEnd\n"
        ),
    ));
    assert_eq!(s.lights.len(), 2);
}

#[test]
fn every_file_a_scene_reads_is_in_its_file_list() {
    let d = folder("files");
    write_plys(&d);
    write_obj(&d);
    write_png(&d);
    common::write(
        &d,
        "part.pbrt",
        "Shape \"plymesh\" \"string filename\" \"models/quad-bin.ply\"\n",
    );
    let p = common::write(
        &d,
        "scene.pbrt",
        r#"Camera "perspective"
WorldBegin
Texture "t" "spectrum" "imagemap" "string filename" "tex.png"
Material "matte" "texture Kd" "t"
Include "part.pbrt"
Shape "plymesh" "string filename" "quad.ply"
Shape "plymesh" "string filename" "./quad.ply"
WorldEnd
"#,
    );
    let canon = |n: &str| d.join(n).canonicalize().expect("canonical");
    let s = load(&p);
    assert_eq!(
        s.files,
        ["models/quad-bin.ply", "part.pbrt", "quad.ply", "tex.png"].map(canon)
    );
    let p = common::write(
        &d,
        "scene.xml",
        r#"<scene version="0.5.0">
  <sensor type="perspective"/>
  <bsdf type="diffuse" id="m">
    <texture type="bitmap" name="reflectance"><string name="filename" value="tex.png"/></texture>
  </bsdf>
  <shape type="obj"><string name="filename" value="quad.obj"/><ref id="m"/></shape>
  <shape type="ply"><string name="filename" value="models/quad-bin.ply"/></shape>
</scene>
"#,
    );
    let s = load(&p);
    assert_eq!(
        s.files,
        ["models/quad-bin.ply", "quad.obj", "tex.png"].map(canon)
    );
}

// ------------------------------------------------------------------------------------------
// The public scenes.

#[test]
fn shared_scenes_load_and_render() {
    let Some(dir) = common::shared_scenes("shared_scenes_load_and_render") else {
        return;
    };
    for (rel, w, h) in [
        ("cornell-box/pbrt-v3/scene.pbrt", 24, 24),
        ("veach-mis/pbrt-v3/scene.pbrt", 32, 18),
        ("veach-mis/mitsuba/scene.xml", 32, 18),
        ("veach-bidir/pbrt-v3/scene.pbrt", 24, 24),
        ("staircase/mitsuba/scene.xml", 18, 32),
    ] {
        let t0 = Instant::now();
        let mut s = load(&dir.join(rel));
        let load_s = t0.elapsed().as_secs_f64();
        eprintln!(
            "{rel}: {} triangles, {} spheres, {} lights, {} materials, loaded in {load_s:.2} s (BVH {:.2} s)",
            s.stats.triangles,
            s.spheres.len(),
            s.lights.len(),
            s.materials.len(),
            s.stats.bvh_build_seconds
        );
        for w in &s.warnings {
            eprintln!("  warning: {w}");
        }
        assert!(s.stats.lights > 0);
        s.camera = s.camera.with_resolution(w, h).expect("resolution");
        let t0 = Instant::now();
        let sums = render(&s, 4, 3, 1);
        let m = mean_rgb(&sums);
        eprintln!(
            "  rendered {w}x{h} at 4 spp in {:.2} s: mean {m:?}",
            t0.elapsed().as_secs_f64()
        );
        assert!(
            m.iter().all(|c| c.is_finite() && *c > 0.0),
            "{rel}: mean {m:?}"
        );
    }
}

#[test]
fn cornell_box_pbrt_matches_our_json_scene() {
    let Some(dir) = common::shared_scenes("cornell_box_pbrt_matches_our_json_scene") else {
        return;
    };
    let mut pbrt = load(&dir.join("cornell-box/pbrt-v3/scene.pbrt"));
    let mut json = load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell-box.json"));
    // Same camera: Bitterli's world-to-camera matrix is a reflection, so no mirroring.
    assert!(!pbrt.camera.flip_x());
    assert!((pbrt.camera.position - json.camera.position).length() < 1e-5);
    assert!((pbrt.camera.forward() - json.camera.forward()).length() < 1e-5);
    assert!(close(pbrt.camera.vfov_deg, json.camera.vfov_deg, 1e-6));
    assert_eq!(pbrt.defaults.max_depth, Some(5));
    assert_eq!(pbrt.defaults.spp, Some(64));
    assert_has(warning(&pbrt, "PixelFilter"), &["\"triangle\""]);
    pbrt.camera = pbrt.camera.with_resolution(64, 64).expect("resolution");
    json.camera = json.camera.with_resolution(64, 64).expect("resolution");
    let a = render(&pbrt, 96, 5, 1);
    let b = render(&json, 96, 5, 2);
    let lit = compare_regions("cornell pbrt vs json", &a, &b, &grid(64, 64, 4));
    assert!(
        lit >= 40,
        "the image is mostly dark ({lit} lit region-channels)"
    );
    // The red wall is on the left, the green on the right (as in Tungsten's reference).
    let (red_left, _) = region(&a, 2, 24, 8, 40, 0);
    let (green_left, _) = region(&a, 2, 24, 8, 40, 1);
    let (red_right, _) = region(&a, 56, 24, 62, 40, 0);
    let (green_right, _) = region(&a, 56, 24, 62, 40, 1);
    assert!(red_left > 2.0 * green_left && green_right > 2.0 * red_right);
}

#[test]
fn veach_mis_pbrt_matches_mitsuba_where_the_models_agree() {
    let Some(dir) = common::shared_scenes("veach_mis_pbrt_matches_mitsuba_where_the_models_agree")
    else {
        return;
    };
    let mut pbrt = load(&dir.join("veach-mis/pbrt-v3/scene.pbrt"));
    let mut mts = load(&dir.join("veach-mis/mitsuba/scene.xml"));
    for w in &mts.warnings {
        eprintln!("mitsuba warning: {w}");
    }
    // Same camera: pbrt's 20.11 degrees on the short (vertical) axis is Mitsuba's 35 on x.
    assert!((pbrt.camera.position - mts.camera.position).length() < 1e-4);
    assert!((pbrt.camera.forward() - mts.camera.forward()).length() < 1e-5);
    assert!(!pbrt.camera.flip_x() && !mts.camera.flip_x());
    let (w, h) = (64usize, 36usize);
    pbrt.camera = pbrt
        .camera
        .with_resolution(w as u32, h as u32)
        .expect("resolution");
    mts.camera = mts
        .camera
        .with_resolution(w as u32, h as u32)
        .expect("resolution");
    assert!(
        close(pbrt.camera.vfov_deg, mts.camera.vfov_deg, 1e-4),
        "{} vs {}",
        pbrt.camera.vfov_deg,
        mts.camera.vfov_deg
    );
    // Direct lighting (max depth 1): the diffuse floor and back wall see the three sphere lights
    // through the same geometry in both files (the plates only cast shadows). The plates
    // themselves differ: pbrt-v3's `metal` is GGX with the full Fresnel reflectance, Mitsuba's
    // (Tungsten's) roughconductor is Beckmann (here approximated by GGX of the same alpha) with
    // specularReflectance 0.3, so plate pixels are ~0.3x as bright. At depth >= 2 the floor
    // also receives light reflected by the plates and would differ too.
    let a = render(&pbrt, 64, 1, 1);
    let b = render(&mts, 64, 1, 2);
    // Regions away from the plates (picked from a 320x180 render, in 64x36 pixels): the back
    // wall above them (with the lights), the wall and floor left and right of them, and the
    // floor below the lowest plate.
    let mut regions = Vec::new();
    for rx in 0..8 {
        let (x0, x1) = (rx * w / 8, (rx + 1) * w / 8);
        regions.push((x0, 0, x1, 8));
        regions.push((x0, 34, x1, 36));
    }
    for ry in 0..3 {
        let (y0, y1) = (8 + ry * 26 / 3, 8 + (ry + 1) * 26 / 3);
        regions.push((0, y0, 6, y1));
        regions.push((58, y0, 64, y1));
    }
    let lit = compare_regions("veach-mis pbrt vs mitsuba (diffuse)", &a, &b, &regions);
    assert!(lit >= 50, "too few lit regions ({lit})");
    // And the plates do differ: Mitsuba's are darker (specularReflectance 0.3).
    let plates = |s: &PixelSums| region(s, 0, 12, w, 24, 1).0;
    eprintln!("plate band: pbrt {} mitsuba {}", plates(&a), plates(&b));
    assert!(plates(&b) < plates(&a));
}

/// Averages `b` x `b` blocks: what is left of the difference between two images is bias, not
/// noise.
fn blocks(img: &omis::film::Image, b: usize) -> omis::film::Image {
    let (w, h) = (img.width / b, img.height / b);
    let mut out = omis::film::Image::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let mut s = Vec3::ZERO;
            for dy in 0..b {
                for dx in 0..b {
                    s += img.get(x * b + dx, y * b + dy);
                }
            }
            out.set(x, y, s / (b * b) as f32);
        }
    }
    out
}

/// Nearest-neighbour upscaling of an RGB8 buffer, for viewing block maps.
fn upscale(data: &[u8], w: usize, h: usize, f: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(data.len() * f * f);
    for y in 0..h * f {
        for x in 0..w * f {
            let i = 3 * ((y / f) * w + x / f);
            out.extend_from_slice(&data[i..i + 3]);
        }
    }
    out
}

/// Path-traced staircase against Tungsten's converged reference, at the reference resolution.
/// Run with `cargo test --release --test import -- --ignored staircase --nocapture`
/// (OMIS_STAIRCASE_SPP sets the samples per pixel, default 64). Prints load time, BVH build
/// time, peak memory (VmHWM), pixel samples per second and relMSE, and writes the render, the
/// reference and error maps to the temporary folder.
#[test]
#[ignore]
fn staircase_relmse_against_tungsten() {
    let Some(dir) = common::shared_scenes("staircase_relmse_against_tungsten") else {
        return;
    };
    let scene_path = dir.join("staircase/mitsuba/scene.xml");
    let t0 = Instant::now();
    let scene = load(&scene_path);
    let load_s = t0.elapsed().as_secs_f64();
    let peak_after_load = peak_memory_mib().unwrap_or(f64::NAN);
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    eprintln!(
        "staircase: {} triangles, {} materials; load {load_s:.2} s (BVH build {:.3} s of it); peak memory (VmHWM) after load {peak_after_load:.0} MiB",
        scene.stats.triangles,
        scene.materials.len(),
        scene.stats.bvh_build_seconds,
    );
    let reference =
        omis::film::image::exr_io::read_exr(&dir.join("staircase/mitsuba/TungstenRender.exr"))
            .expect("reference EXR");
    assert_eq!(
        (scene.camera.width as usize, scene.camera.height as usize),
        (reference.width, reference.height),
        "the scene's film is the reference's resolution"
    );
    let spp: u32 = std::env::var("OMIS_STAIRCASE_SPP")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(64);
    let max_depth = scene.defaults.max_depth.unwrap_or(64);
    let settings = RenderSettings {
        sample_block: spp,
        max_depth,
        seed: 1,
        sampler: SamplerKind::Sobol,
        ..Default::default()
    };
    let out =
        omis::job::Resolved::fixed(&scene, &settings, 16, 64).render_in_process(&scene, &|_| {});
    let img = out.image();
    let rate = out.stats.samples as f64 / out.seconds;
    let stats = omis::film::image::metrics::compare(&img, &reference, 0.01).expect("same size");
    // 8x8 block means: the noise of the render mostly averages out, model differences stay.
    let (bi, br) = (blocks(&img, 8), blocks(&reference, 8));
    let bias = omis::film::image::metrics::compare(&bi, &br, 0.01).expect("same size");
    eprintln!(
        "staircase {}x{} at {spp} spp, max depth {max_depth}: relMSE {:.5} (eps 0.01), MSE {:.5}; relMSE of 8x8 block means {:.5}; {:.1} s, {:.0} pixel samples/s ({} threads); peak memory (VmHWM) {:.0} MiB",
        img.width,
        img.height,
        stats.relmse,
        stats.mse,
        bias.relmse,
        out.seconds,
        rate,
        rayon::current_num_threads(),
        peak_memory_mib().unwrap_or(f64::NAN)
    );
    let mr = img.mean();
    let rr = reference.mean();
    eprintln!("mean RGB: ours {mr:?}, Tungsten {rr:?}");
    // Attribute the differences to materials: the material seen through each pixel's centre.
    let mut per: std::collections::BTreeMap<String, (usize, f64, f64, f64)> = Default::default();
    for y in 0..img.height {
        for x in 0..img.width {
            let ray = scene.camera.ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            let name = match scene.intersect(&ray) {
                Some(h) => scene.materials[h.material as usize].name.clone(),
                None => "(nothing)".into(),
            };
            let (a, r) = (img.get(x, y), reference.get(x, y));
            let e = per.entry(name).or_default();
            e.0 += 1;
            e.1 += omis::geometry::luminance(a) as f64;
            e.2 += omis::geometry::luminance(r) as f64;
            for c in 0..3 {
                let d = (a[c] - r[c]) as f64;
                e.3 += d * d / ((r[c] as f64).powi(2) + 0.01);
            }
        }
    }
    let mut rows: Vec<_> = per.into_iter().collect();
    rows.sort_by_key(|r| std::cmp::Reverse(r.1.0));
    let total = (3 * img.width * img.height) as f64;
    eprintln!("material            pixels   ours/Tungsten (luminance)   share of relMSE");
    for (name, (n, a, r, e)) in rows {
        eprintln!(
            "{name:<20}{n:>7}   {:>8.4}                    {:>6.4}",
            a / r.max(1e-12),
            e / total
        );
    }
    let tmp = std::env::temp_dir();
    let paths = [
        "omis-staircase.png",
        "omis-staircase-tungsten.png",
        "omis-staircase-error-map.png",
        "omis-staircase-error-map-8x8.png",
    ]
    .map(|n| tmp.join(n));
    omis::film::image::png::write_png(&paths[0], &img, 1.0).expect("write render");
    omis::film::image::png::write_png(&paths[1], &reference, 1.0).expect("write reference");
    let map =
        omis::film::image::metrics::error_map(&img, &reference, 0.01, 1.0).expect("error map");
    omis::film::image::png::write_rgb8(&paths[2], img.width, img.height, &map).expect("write map");
    // Block map at a finer scale (saturating at 25 %), shown at full size.
    let bmap = omis::film::image::metrics::error_map(&bi, &br, 0.01, 0.25).expect("error map");
    let up = upscale(&bmap, bi.width, bi.height, 8);
    omis::film::image::png::write_rgb8(&paths[3], bi.width * 8, bi.height * 8, &up)
        .expect("write map");
    eprintln!(
        "render: {}\nreference (same tone mapping): {}\nerror map (red: brighter than Tungsten, green: darker; saturates at 100 %): {}\nerror map of 8x8 block means (saturates at 25 %): {}",
        paths[0].display(),
        paths[1].display(),
        paths[2].display(),
        paths[3].display()
    );
    assert!(stats.relmse.is_finite());
}
