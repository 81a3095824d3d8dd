//! The Mitsuba 0.5 importer: every element from small files written to a temporary folder,
//! errors that name file and line, and the fallbacks it warns about.

mod common;

use common::import::{
    assert_has, close, load, load_err, material, warning, write_obj, write_plys, write_png,
};
use omis::geometry::{Vec2, Vec3};
use omis::light::Light;
use omis::material::MaterialKind;
use std::path::PathBuf;

fn folder(name: &str) -> PathBuf {
    common::folder("import", name)
}

#[test]
fn mitsuba_elements_build_the_expected_scene() {
    let d = folder("mitsuba-elements");
    write_obj(&d);
    write_plys(&d);
    write_png(&d);
    let text = r##"<?xml version="1.0" encoding="utf-8"?>
<scene version="0.5.0">
  <integrator type="path">
    <integer name="maxDepth" value="3"/>
    <boolean name="strictNormals" value="true"/>
  </integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <string name="fovAxis" value="y"/>
    <transform name="toWorld">
      <lookat origin="0, 1, 10" target="0, 1, 0" up="0, 1, 0"/>
    </transform>
    <sampler type="independent"><integer name="sampleCount" value="12"/></sampler>
    <film type="hdrfilm">
      <integer name="width" value="48"/>
      <integer name="height" value="24"/>
      <rfilter type="box"/>
    </film>
  </sensor>
  <texture type="bitmap" id="checker"><string name="filename" value="tex.png"/></texture>
  <bsdf type="diffuse" id="plain"><rgb name="reflectance" value="0.2, 0.4, 0.6"/></bsdf>
  <bsdf type="twosided" id="textured">
    <bsdf type="diffuse"><ref name="reflectance" id="checker"/></bsdf>
  </bsdf>
  <bsdf type="roughplastic" id="rp">
    <float name="alpha" value="0.2"/>
    <string name="distribution" value="ggx"/>
    <float name="intIOR" value="1.5"/>
    <boolean name="nonlinear" value="true"/>
    <srgb name="diffuseReflectance" value="#808080"/>
  </bsdf>
  <bsdf type="plastic" id="smoothplastic"><float name="intIOR" value="1.5"/></bsdf>
  <bsdf type="roughconductor" id="rc">
    <float name="alpha" value="0.05"/>
    <string name="material" value="Au"/>
    <float name="extEta" value="2"/>
    <rgb name="specularReflectance" value="0.3"/>
  </bsdf>
  <bsdf type="roughconductor" id="rc2"><float name="alphaU" value="0.1"/><float name="alphaV" value="0.2"/></bsdf>
  <bsdf type="conductor" id="mirrorish"><spectrum name="eta" value="1.5"/><spectrum name="k" value="2"/></bsdf>
  <bsdf type="dielectric" id="water"><string name="intIOR" value="water"/><float name="extIOR" value="1"/></bsdf>
  <bsdf type="bumpmap">
    <texture type="bitmap" name="map"><string name="filename" value="tex.png"/></texture>
    <bsdf type="twosided" id="bumped"><bsdf type="diffuse"/></bsdf>
  </bsdf>
  <shape type="obj">
    <string name="filename" value="quad.obj"/>
    <boolean name="faceNormals" value="true"/>
    <transform name="toWorld">
      <scale value="2"/>
      <rotate y="1" angle="90"/>
      <translate x="1" y="2" z="3"/>
    </transform>
    <ref id="textured"/>
  </shape>
  <shape type="obj">
    <string name="filename" value="quad.obj"/>
    <boolean name="flipTexCoords" value="false"/>
    <ref id="plain"/>
  </shape>
  <shape type="rectangle">
    <transform name="toWorld"><matrix value="1 0 0 0  0 0 1 5  0 -1 0 0  0 0 0 1"/></transform>
    <boolean name="flipNormals" value="true"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
    <emitter type="area"><rgb name="radiance" value="1, 2, 3"/></emitter>
  </shape>
  <shape type="cube"><ref id="rp"/></shape>
  <shape type="sphere">
    <point name="center" x="1" y="2" z="3"/>
    <float name="radius" value="0.5"/>
    <transform name="toWorld"><scale value="2"/></transform>
    <ref id="rc"/>
    <emitter type="area"><spectrum name="radiance" value="4"/></emitter>
  </shape>
  <shape type="sphere"><boolean name="flipNormals" value="true"/><ref id="water"/></shape>
  <shape type="cube"><ref id="bumped"/></shape>
  <shape type="cube"><ref id="smoothplastic"/></shape>
  <shape type="cube"><ref id="rc2"/></shape>
  <shape type="cube"><ref id="mirrorish"/></shape>
  <shape type="ply"><string name="filename" value="models/quad-bin.ply"/><ref id="plain"/></shape>
  <shape type="disk"><ref id="plain"/></shape>
  <emitter type="point"><point name="position" x="0" y="3" z="0"/><rgb name="intensity" value="7"/></emitter>
</scene>
"##;
    let p = common::write(&d, "scene.xml", text);
    let line_of = |what: &str| 1 + text.lines().position(|l| l.contains(what)).expect("line");
    let s = load(&p);
    for w in &s.warnings {
        eprintln!("warning: {w}");
    }
    // Integrator: Mitsuba's maxDepth 3 is our 2. Sampler, film, camera.
    assert_eq!(s.defaults.max_depth, Some(2));
    assert_eq!(s.defaults.spp, Some(12));
    assert_eq!((s.camera.width, s.camera.height), (48, 24));
    assert!(close(s.camera.vfov_deg, 40.0, 1e-5));
    assert!(
        !s.camera.flip_x(),
        "a Mitsuba lookat camera is not mirrored"
    );
    assert!((s.camera.position - Vec3::new(0.0, 1.0, 10.0)).length() < 1e-5);
    // Looking down -z with +y up, +x is on the right (in Mitsuba and here).
    assert!(s.camera.ray(Vec2::new(46.0, 12.0)).d.x > 0.0);

    // Materials.
    assert!(
        !material(&s, "plain").two_sided,
        "Mitsuba BSDFs are one-sided"
    );
    assert!(material(&s, "textured").two_sided);
    assert!(matches!(
        material(&s, "textured").kind,
        MaterialKind::Lambert {
            albedo: omis::material::Texture::Bitmap { .. }
        }
    ));
    match &material(&s, "rp").kind {
        MaterialKind::Plastic {
            alpha,
            ior,
            layered,
            nonlinear,
            diffuse,
            ..
        } => {
            assert_eq!((*alpha, *layered, *nonlinear), (0.2, true, true));
            assert!(close(*ior, 1.5 / 1.00028, 1e-6));
            // srgb #808080 decoded to linear.
            assert!(
                close(diffuse.average().x, 0.2158605, 1e-4),
                "{:?}",
                diffuse.average()
            );
        }
        k => panic!("{k:?}"),
    }
    match &material(&s, "rc").kind {
        MaterialKind::RoughConductor {
            eta,
            k,
            alpha_u,
            scale,
            ..
        } => {
            assert_eq!(*alpha_u, 0.05);
            // Au relative to extEta 2; specularReflectance is our scale.
            assert!(close(eta.x, 0.143119 / 2.0, 1e-5) && close(k.x, 3.98316 / 2.0, 1e-5));
            assert_eq!(*scale, Vec3::splat(0.3));
        }
        k => panic!("{k:?}"),
    }
    assert!(
        matches!(material(&s, "rc2").kind, MaterialKind::RoughConductor { alpha_u, alpha_v, .. } if alpha_u == 0.1 && alpha_v == 0.2)
    );
    assert!(
        matches!(material(&s, "mirrorish").kind, MaterialKind::RoughConductor { alpha_u, .. } if alpha_u <= 1e-3)
    );
    assert!(
        matches!(material(&s, "smoothplastic").kind, MaterialKind::Plastic { alpha, .. } if alpha <= 1e-3)
    );
    assert!(
        matches!(material(&s, "water").kind, MaterialKind::Dielectric { ior, .. } if close(ior, 1.333, 1e-6))
    );
    assert!(material(&s, "bumped").two_sided);

    // Warnings: Beckmann (the default distribution of rc2) once, bump map, smooth models.
    assert_has(warning(&s, "beckmann approximated by ggx"), &["scene.xml:"]);
    assert_has(
        warning(&s, "bump"),
        &[&format!("scene.xml:{}", line_of("type=\"bumpmap\""))],
    );
    warning(&s, "smooth plastic");
    warning(&s, "smooth conductor");

    // Geometry: OBJ 2 + 2 triangles, rectangle 2, five cubes 12 each, binary PLY 2, the disk
    // as a fan of 256; two spheres.
    assert_eq!(s.stats.triangles, 2 + 2 + 2 + 12 * 5 + 2 + 256);
    warning(&s, "disk tessellated");
    assert_eq!(s.spheres.len(), 2);
    assert!((s.spheres[0].center - Vec3::new(2.0, 4.0, 6.0)).length() < 1e-5);
    assert_eq!(s.spheres[0].radius, 1.0);
    assert!(!s.spheres[0].inward && s.spheres[1].inward);
    // The first OBJ: scale 2, then rotate 90 degrees about y, then translate: (1,0,0) -> (1,2,1).
    assert!(
        s.positions
            .iter()
            .any(|p| (*p - Vec3::new(1.0, 2.0, 1.0)).length() < 1e-5)
    );
    // faceNormals dropped the first OBJ's normals; the second keeps them (they are not the
    // geometric normal, which flat normals would be taken as).
    assert!(!s.triangles[0].has_normals);
    assert!(s.triangles[2].has_normals);
    // OBJ uvs: Mitsuba's default flipTexCoords is the usual OBJ convention, ours (kept);
    // flipTexCoords false flips them.
    let uv_of = |tri: usize, corner: usize| s.uvs[s.triangles[tri].v[corner] as usize];
    assert_eq!(uv_of(0, 0), Vec2::new(0.0, 0.0));
    assert_eq!(uv_of(2, 0), Vec2::new(0.0, 1.0));
    // Lights: the rectangle (the matrix turns its +z face to +y; flipNormals turns it down), the
    // sphere and the point light.
    let tri_normals: Vec<Vec3> = s
        .lights
        .iter()
        .filter_map(|l| match l {
            Light::Triangle { n, radiance, .. } => {
                assert_eq!(*radiance, Vec3::new(1.0, 2.0, 3.0));
                Some(*n)
            }
            _ => None,
        })
        .collect();
    assert_eq!(tri_normals.len(), 2);
    assert!(tri_normals.iter().all(|n| n.y < -0.99), "{tri_normals:?}");
    assert!(
        s.lights
            .iter()
            .any(|l| matches!(l, Light::Sphere { radiance, .. } if *radiance == Vec3::splat(4.0)))
    );
    assert!(s.lights.iter().any(|l| matches!(l, Light::Point { position, intensity } if *position == Vec3::new(0.0, 3.0, 0.0) && *intensity == Vec3::splat(7.0))));
}

#[test]
fn mitsuba_fov_axes_and_depths() {
    let d = folder("mitsuba-fov");
    let scene = |w: u32, h: u32, fov_axis: &str, depth: i32| {
        common::write(
            &d,
            "f.xml",
            &format!(
                r#"<scene version="0.5.0"><integrator type="path"><integer name="maxDepth" value="{depth}"/></integrator>
<sensor type="perspective"><float name="fov" value="50"/><string name="fovAxis" value="{fov_axis}"/>
<film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/><rfilter type="box"/></film></sensor></scene>"#
            ),
        )
    };
    let t = (25.0f32).to_radians().tan();
    let vfov = |tan_half: f32| 2.0 * tan_half.atan().to_degrees();
    for (w, h, axis, expect) in [
        (40, 20, "x", vfov(t * 0.5)),
        (40, 20, "y", 50.0),
        (40, 20, "smaller", 50.0),
        (40, 20, "larger", vfov(t * 0.5)),
        (20, 40, "smaller", vfov(t * 2.0)),
        (20, 40, "larger", 50.0),
        (30, 40, "diagonal", vfov(t * 40.0 / 50.0)),
    ] {
        let s = load(&scene(w, h, axis, 2));
        assert!(
            close(s.camera.vfov_deg, expect, 1e-5),
            "{w}x{h} {axis}: {} vs {expect}",
            s.camera.vfov_deg
        );
    }
    // maxDepth: 1 is directly visible emitters only (our 0); -1 unlimited becomes 64.
    let s = load(&scene(8, 8, "x", 1));
    assert_eq!(s.defaults.max_depth, Some(0));
    warning(&s, "maxDepth 1");
    let s = load(&scene(8, 8, "x", -1));
    assert_eq!(s.defaults.max_depth, Some(64));
    warning(&s, "unlimited");
    assert_has(
        &load_err(&scene(8, 8, "x", 0)),
        &["f.xml", "line 1", "maxDepth 0"],
    );
}

#[test]
fn mitsuba_errors_name_file_and_line() {
    let d = folder("mitsuba-errors");
    write_obj(&d);
    let case = |name: &str, body: &str| -> String {
        let p = common::write(
            &d,
            name,
            &format!(
                "<scene version=\"0.5.0\">\n<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/></sensor>\n{body}\n</scene>\n"
            ),
        );
        load_err(&p)
    };
    let e = case("xml.xml", "<shape type=\"cube\">\n</scene>");
    assert_has(&e, &["xml.xml", "line 4", "malformed XML"]);
    let e = case("attr.xml", "<shape type=\"cube\" type=\"sphere\"/>");
    assert_has(&e, &["attr.xml", "line 3"]);
    let e = case("element.xml", "\n<teapot/>");
    assert_has(&e, &["element.xml", "line 4", "unknown element <teapot>"]);
    let e = case(
        "serialized.xml",
        "<shape type=\"serialized\"><string name=\"filename\" value=\"x.serialized\"/></shape>",
    );
    assert_has(
        &e,
        &["serialized.xml", "line 3", "serialized", "not supported"],
    );
    let e = case(
        "ref.xml",
        "<shape type=\"cube\">\n  <ref id=\"nothing\"/>\n</shape>",
    );
    assert_has(&e, &["ref.xml", "line 4", "unknown id \"nothing\""]);
    for (i, ty) in ["envmap", "sunsky", "directional", "constant", "spot"]
        .iter()
        .enumerate()
    {
        let e = case(&format!("em{i}.xml"), &format!("<emitter type=\"{ty}\"/>"));
        assert_has(&e, &[&format!("em{i}.xml"), "line 3", ty, "not supported"]);
    }
    let e = case(
        "missing.xml",
        "<shape type=\"obj\"><string name=\"filename\" value=\"gone.obj\"/></shape>",
    );
    assert_has(&e, &["missing.xml", "line 3", "gone.obj", "not found"]);
    let e = case(
        "number.xml",
        "<shape type=\"sphere\">\n<float name=\"radius\" value=\"big\"/></shape>",
    );
    assert_has(&e, &["number.xml", "line 4", "malformed number 'big'"]);
    let e = case(
        "matrix.xml",
        "<shape type=\"cube\"><transform name=\"toWorld\">\n<matrix value=\"1 2 3\"/></transform></shape>",
    );
    assert_has(&e, &["matrix.xml", "line 4", "16 values"]);
    let e = case(
        "dup.xml",
        "<bsdf type=\"diffuse\" id=\"a\"/>\n<bsdf type=\"diffuse\" id=\"a\"/>",
    );
    assert_has(&e, &["dup.xml", "line 4", "duplicate id"]);
    let e = case(
        "spectrum.xml",
        "<shape type=\"cube\"><emitter type=\"area\">\n<spectrum name=\"radiance\" value=\"400:1, 700:2\"/></emitter></shape>",
    );
    assert_has(&e, &["spectrum.xml", "line 4", "sampled spectra"]);
    let e = case(
        "escape.xml",
        "<shape type=\"obj\"><string name=\"filename\" value=\"../x.obj\"/></shape>",
    );
    assert_has(&e, &["escape.xml", "line 3"]);
}

#[test]
fn mitsuba_unknown_bsdf_falls_back_with_a_warning() {
    let d = folder("mitsuba-fallback");
    let p = common::write(
        &d,
        "f.xml",
        r#"<scene version="0.5.0">
<sensor type="perspective"><float name="fov" value="40"/><film type="hdrfilm"><rfilter type="gaussian"/></film></sensor>
<bsdf type="irawan" id="cloth"><float name="repeatU" value="4"/></bsdf>
<shape type="cube"><ref id="cloth"/><integer name="mystery" value="1"/></shape>
</scene>
"#,
    );
    let s = load(&p);
    assert_has(warning(&s, "irawan"), &["f.xml:3", "became diffuse"]);
    assert_has(warning(&s, "gaussian"), &["f.xml:2", "box"]);
    assert_has(warning(&s, "mystery"), &["f.xml:4"]);
    assert!(matches!(
        material(&s, "cloth").kind,
        MaterialKind::Lambert { .. }
    ));
}
