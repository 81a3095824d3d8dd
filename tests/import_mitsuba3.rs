//! The Mitsuba 3 importer: parameters, includes, references and aliases as Mitsuba 3 reads them;
//! shapes, materials, emitters and the camera in its conventions; every construct we cannot
//! render refused at once. Images are checked against Mitsuba 3 itself by .ci/mitsuba-oracle.

mod common;

use common::import::{assert_has, load_err_with as load_err, load_with as load};
use omis::geometry::Vec3;
use omis::light::Light;
use omis::material::{Distribution, MaterialKind};
use omis::scene::SceneParams;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::Command;

fn folder(name: &str) -> PathBuf {
    common::folder("mi3", name)
}

fn params(kv: &[(&str, &str)]) -> SceneParams {
    SceneParams::new(
        kv.iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect::<BTreeMap<_, _>>(),
    )
}

/// A scene: a sensor of `w` x `h` pixels at the origin looking down -z, then `body`.
fn scene(body: &str) -> String {
    format!(
        r#"<scene version="3.0.0">
    <sensor type="perspective">
        <float name="fov" value="60"/>
        <transform name="to_world"><lookat origin="0, 0, 0" target="0, 0, -1" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="16"/><rfilter type="box"/></film>
    </sensor>
{body}
</scene>
"#
    )
}

const LIGHT: &str = r#"<shape type="rectangle">
        <transform name="to_world"><translate z="-3"/></transform>
        <emitter type="area"><rgb name="radiance" value="1, 2, 3"/></emitter>
    </shape>"#;

#[test]
fn parameters_defaults_includes_references_and_aliases() {
    let d = folder("params");
    std::fs::write(
        d.join("part.xml"),
        r#"<scene version="3.0.0">
    <bsdf type="diffuse" id="fromPart"><rgb name="reflectance" value="$albedo"/></bsdf>
</scene>"#,
    )
    .expect("part");
    std::fs::write(
        d.join("bsdf.xml"),
        r#"<bsdf version="3.0.0" type="conductor"><string name="material" value="Au"/></bsdf>"#,
    )
    .expect("bsdf");
    let text = scene(&format!(
        r#"    <default name="albedo" value="0.25"/>
    <default name="spp" value="12"/>
    <integrator type="path"><integer name="max_depth" value="$depth"/></integrator>
    <include filename="part.xml"/>
    <alias id="fromPart" as="other"/>
    <shape type="rectangle">
        <transform name="to_world"><translate z="-2"/></transform>
        <ref id="later"/>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><translate x="3" z="-2"/></transform>
        <ref id="other"/>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><translate x="-3" z="-2"/></transform>
        <include filename="bsdf.xml"/>
    </shape>
    <bsdf type="diffuse" id="later"><rgb name="reflectance" value="0.5\$"/></bsdf>
    {LIGHT}"#
    ))
    .replace("0.5\\$", "0.5");
    let path = d.join("scene.xml");
    std::fs::write(&path, &text).expect("scene");
    // `$depth` has no default: it must be given.
    let e = load_err(&path, &params(&[]));
    assert_has(&e, &["scene.xml", "undefined parameter $depth", "--define"]);
    let s = load(&path, &params(&[("depth", "4"), ("albedo", "0.75")]));
    assert_eq!(s.defaults.max_depth, Some(3), "Mitsuba's depth 4 is our 3");
    // The value given wins over the file's default.
    let albedo = s
        .materials
        .iter()
        .find(|m| m.name == "fromPart")
        .expect("the included bsdf");
    match &albedo.kind {
        MaterialKind::Lambert { albedo } => {
            assert_eq!(albedo.average(), Vec3::splat(0.75));
        }
        k => panic!("{k:?}"),
    }
    // The forward reference, the alias (the same material) and the included bsdf.
    assert!(s.materials.iter().any(|m| m.name == "later"));
    assert!(
        s.materials
            .iter()
            .any(|m| matches!(m.kind, MaterialKind::RoughConductor { .. }))
    );
    assert_eq!(
        s.materials.iter().filter(|m| m.name == "fromPart").count(),
        1
    );
    // A value for a parameter the file does not use is an error, as in Mitsuba.
    let e = load_err(&path, &params(&[("depth", "4"), ("nonesuch", "1")]));
    assert_has(&e, &["$nonesuch"]);
    // An include of itself ends at the nesting limit.
    std::fs::write(
        d.join("loop.xml"),
        r#"<scene version="3.0.0"><include filename="loop.xml"/></scene>"#,
    )
    .expect("loop");
    let e = load_err(&d.join("loop.xml"), &params(&[]));
    assert_has(&e, &["loop.xml", "nested deeper than 15"]);
}

#[test]
fn shapes_materials_and_emitters_in_mitsubas_conventions() {
    let d = folder("shapes");
    let text = scene(&format!(
        r#"
    <shape type="rectangle"><transform name="to_world"><translate z="-5"/></transform>
        <bsdf type="dielectric"><string name="int_ior" value="diamond"/><float name="ext_ior" value="1.5"/></bsdf></shape>
    <shape type="cube"><transform name="to_world"><translate y="-5"/></transform>
        <bsdf type="roughconductor" id="au"><string name="material" value="Au"/>
            <string name="distribution" value="ggx"/><float name="alpha_u" value="0.1"/><float name="alpha_v" value="0.3"/></bsdf></shape>
    <shape type="disk"><transform name="to_world"><translate x="5"/></transform>
        <bsdf type="twosided"><bsdf type="roughplastic"><string name="distribution" value="ggx"/>
            <float name="alpha" value="0.2"/></bsdf></bsdf></shape>
    <shape type="cylinder"><point name="p0" value="-5, 0, 0"/><point name="p1" value="-5, 1, 0"/>
        <float name="radius" value="0.5"/></shape>
    <shape type="sphere"><transform name="to_world"><scale value="2"/><translate y="5"/></transform>
        <float name="radius" value="0.5"/><emitter type="area"><spectrum name="radiance" value="2"/></emitter></shape>
    <shape type="shapegroup" id="g"><shape type="rectangle"/></shape>
    <shape type="instance"><ref id="g"/><transform name="to_world"><translate z="-9"/></transform></shape>
    <shape type="instance"><ref id="g"/><transform name="to_world"><translate z="-10"/></transform></shape>
    <emitter type="point"><point name="position" value="1, 2, 3"/><rgb name="intensity" value="4, 5, 6"/></emitter>
    {LIGHT}"#
    ));
    let path = d.join("scene.xml");
    std::fs::write(&path, text).expect("scene");
    let s = load(&path, &params(&[]));
    // rectangle 2 + cube 12 + disk 256 + cylinder 512 + 2 instanced rectangles 4 + light 2.
    assert_eq!(s.triangles.len(), 2 + 12 + 256 + 512 + 4 + 2);
    assert_eq!(s.spheres.len(), 1);
    assert_eq!(s.spheres[0].radius, 1.0);
    assert_eq!(s.spheres[0].center, Vec3::new(0.0, 5.0, 0.0));
    let kind = |pred: fn(&MaterialKind) -> bool| s.materials.iter().find(|m| pred(&m.kind));
    match kind(|k| matches!(k, MaterialKind::Dielectric { .. })).map(|m| &m.kind) {
        Some(MaterialKind::Dielectric { ior, .. }) => assert!((ior - 2.419 / 1.5).abs() < 1e-6),
        k => panic!("{k:?}"),
    }
    match kind(|k| matches!(k, MaterialKind::RoughConductor { .. })).map(|m| &m.kind) {
        Some(MaterialKind::RoughConductor {
            eta,
            alpha_u,
            alpha_v,
            ..
        }) => {
            assert_eq!(eta.to_array(), [0.143036, 0.375307, 1.442045]);
            assert_eq!((*alpha_u, *alpha_v), (0.1, 0.3));
        }
        k => panic!("{k:?}"),
    }
    let plastic = s
        .materials
        .iter()
        .find(|m| matches!(m.kind, MaterialKind::Plastic { .. }))
        .expect("plastic");
    assert!(plastic.two_sided);
    // Mitsuba's emitters: an emitter's flat spectrum of 2, as Mitsuba's RGB of it; its shape
    // black; the point light as given.
    let sphere_light = s
        .lights
        .iter()
        .find_map(|l| match l {
            Light::Sphere { radiance, .. } => Some(*radiance),
            _ => None,
        })
        .expect("sphere light");
    assert_eq!(
        sphere_light.to_array(),
        [2.0 * 1.20479, 2.0 * 0.948291, 2.0 * 0.908916]
    );
    assert!(s.lights.iter().any(|l| matches!(l,
        Light::Point { position, intensity }
            if *position == Vec3::new(1.0, 2.0, 3.0) && *intensity == Vec3::new(4.0, 5.0, 6.0))));
    // The camera looks down -z with +y up, unmirrored: Mitsuba's +x on the image's right.
    assert!(s.camera.forward().abs_diff_eq(Vec3::NEG_Z, 1e-6));
    assert!(s.camera.right().abs_diff_eq(Vec3::X, 1e-6));
    assert!(!s.camera.flip_x());
    // fov 60 along x on a 2:1 film.
    let vfov = 2.0 * ((30.0f32).to_radians().tan() / 2.0).atan().to_degrees();
    assert!(
        (s.camera.vfov_deg - vfov).abs() < 1e-4,
        "{}",
        s.camera.vfov_deg
    );
}

#[test]
fn what_we_cannot_render_is_refused_naming_every_construct() {
    let d = folder("refused");
    let text = scene(&format!(
        r#"
    <integrator type="path"><boolean name="hide_emitters" value="true"/></integrator>
    <emitter type="sunsky"/>
    <shape type="bsplinecurve"/>
    <shape type="rectangle"><bsdf type="null"/></shape>
    <medium type="homogeneous" id="fog"/>
    {LIGHT}"#
    ));
    let path = d.join("scene.xml");
    std::fs::write(&path, text).expect("scene");
    let e = load_err(&path, &params(&[]));
    assert_has(
        &e,
        &[
            "scene.xml",
            "5 reasons",
            "hide_emitters",
            "emitter \"sunsky\"",
            "null bsdf",
            "shape \"bsplinecurve\"",
            "participating media",
        ],
    );
    // Approximations are warnings naming file and line.
    let text = scene(&format!(
        r#"
    <shape type="rectangle"><bsdf type="roughconductor"/></shape>
    {LIGHT}"#
    ));
    std::fs::write(&path, text).expect("scene");
    let s = load(&path, &params(&[]));
    // Beckmann, Mitsuba's default, is Beckmann; no warning.
    assert!(
        matches!(
            s.materials
                .iter()
                .find(|m| matches!(m.kind, MaterialKind::RoughConductor { .. }))
                .map(|m| &m.kind),
            Some(MaterialKind::RoughConductor {
                distribution: Distribution::Beckmann,
                ..
            })
        ),
        "{:?}",
        s.materials
    );
    assert!(
        !s.warnings.iter().any(|w| w.contains("Beckmann")),
        "{:?}",
        s.warnings
    );
}

#[test]
fn a_serialized_mesh_reads_as_its_positions_normals_and_uvs() {
    let d = folder("serialized");
    // Mesh 0 without normals, mesh 1 with normals and uvs (version 4, float32).
    let mesh = |flags: u32, name: &str, normals: bool, uvs: bool| -> Vec<u8> {
        let mut raw = Vec::new();
        raw.extend(flags.to_le_bytes());
        raw.extend(name.as_bytes());
        raw.push(0);
        raw.extend(3u64.to_le_bytes());
        raw.extend(1u64.to_le_bytes());
        for p in [[0.0f32, 0.0, -2.0], [1.0, 0.0, -2.0], [0.0, 1.0, -2.0]] {
            for v in p {
                raw.extend(v.to_le_bytes());
            }
        }
        if normals {
            for _ in 0..3 {
                for v in [0.0f32, 0.0, 1.0] {
                    raw.extend(v.to_le_bytes());
                }
            }
        }
        if uvs {
            for v in [0.0f32, 0.0, 1.0, 0.0, 0.0, 1.0] {
                raw.extend(v.to_le_bytes());
            }
        }
        for i in [0u32, 1, 2] {
            raw.extend(i.to_le_bytes());
        }
        let mut out = vec![0x1C, 0x04, 4, 0];
        out.extend(miniz_oxide::deflate::compress_to_vec_zlib(&raw, 6));
        out
    };
    let m0 = mesh(0x1000, "a", false, false);
    let m1 = mesh(0x1000 | 0x1 | 0x2, "b", true, true);
    let mut file = m0.clone();
    file.extend(&m1);
    file.extend(0u64.to_le_bytes());
    file.extend((m0.len() as u64).to_le_bytes());
    file.extend(2u32.to_le_bytes());
    std::fs::write(d.join("m.serialized"), &file).expect("serialized");
    for index in [0, 1] {
        let text = scene(&format!(
            r#"<shape type="serialized"><string name="filename" value="m.serialized"/>
        <integer name="shape_index" value="{index}"/></shape>
    {LIGHT}"#
        ));
        let path = d.join(format!("scene{index}.xml"));
        std::fs::write(&path, text).expect("scene");
        let s = load(&path, &params(&[]));
        assert_eq!(s.triangles.len(), 1 + 2, "mesh {index}");
    }
    let text = scene(&format!(
        r#"<shape type="serialized"><string name="filename" value="m.serialized"/>
        <integer name="shape_index" value="2"/></shape>
    {LIGHT}"#
    ));
    std::fs::write(d.join("bad.xml"), text).expect("scene");
    assert_has(
        &load_err(&d.join("bad.xml"), &params(&[])),
        &["shape_index 2", "holds 2 meshes"],
    );
}

#[test]
fn define_sets_a_parameter_from_the_command_line() {
    let d = folder("define");
    // The default comes before its first use, in the sensor.
    let text = scene(&format!(
        r#"    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    {LIGHT}"#
    ))
    .replace(
        "<scene version=\"3.0.0\">",
        "<scene version=\"3.0.0\">\n    <default name=\"spp\" value=\"3\"/>",
    )
    .replace(
        "<rfilter type=\"box\"/></film>",
        "<rfilter type=\"box\"/></film><sampler type=\"independent\"><integer name=\"sample_count\" value=\"$spp\"/></sampler>",
    );
    let path = d.join("scene.xml");
    std::fs::write(&path, text).expect("scene");
    let run = |extra: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_omis"))
            .arg("render")
            .arg(&path)
            .args(["--in-process", "--json", "--out"])
            .arg(d.join("out.exr"))
            .args(extra)
            .output()
            .expect("omis");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let line = String::from_utf8_lossy(&out.stdout)
            .lines()
            .last()
            .unwrap_or("")
            .to_string();
        serde_json::from_str::<serde_json::Value>(&line).expect("JSON summary")
    };
    assert_eq!(run(&[])["spp"], 3);
    assert_eq!(run(&["--define", "spp=5"])["spp"], 5);
    let out = Command::new(env!("CARGO_BIN_EXE_omis"))
        .args(["render", "scenes/furnace.json", "--define", "spp=5"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("omis");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("only to Mitsuba 2/3 files"));
}
