//! pbrt-v3 errors name file and line; unsupported features are reported once by name.

use crate::common;
use crate::common::import::{assert_has, load, load_err, material, warning};
use crate::support::folder;
use omis::geometry::Vec3;
use omis::material::MaterialKind;

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
