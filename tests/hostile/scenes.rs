//! Hostile scene files (deep nesting, extreme coordinates, every importer) and out-of-range
//! scene settings: a clear error from the coordinator and from `omis render`.

use crate::common::service::{EXE, http, post, serve};
use crate::support::{folder, healthy, json_scene, mitsuba, tar_of, upload_bundle};
use serde_json::json;
use std::process::Command;

/// A Mitsuba 3 scene lit by a sun-and-sky model, which it cannot be rendered without.
fn mitsuba3_with_environment() -> String {
    r#"<scene version="3.0.0">
    <sensor type="perspective"><float name="fov" value="45"/>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
    <emitter type="sunsky"/>
    <shape type="sphere"/>
</scene>
"#
    .to_string()
}

/// A scene nested `depth` elements deep inside its shape.
fn nested_mitsuba(depth: usize) -> String {
    mitsuba(
        "0.5.0",
        &format!(
            "{}{}",
            "<bsdf type=\"twosided\">".repeat(depth),
            "</bsdf>".repeat(depth)
        ),
    )
}

/// The hostile scene files of the campaign: each is refused with 400 naming its problem.
fn hostile_scenes() -> Vec<(&'static str, String, Vec<u8>)> {
    let extreme = json_scene(json!([{
        "type": "triangles", "positions": [[0, 0, 2], [1e30, 0, 2], [0, 1, 2]],
        "indices": [[0, 1, 2]], "material": "grey"
    }]));
    let json_deep = format!(
        "{{\"camera\": {{\"position\": [0, 0, 0], \"look_at\": [0, 0, 1], \"fov\": 60, \
         \"resolution\": [8, 8]}}, \"materials\": {{\"m\": {}1{}}}}}",
        "{\"a\": ".repeat(100_000),
        "}".repeat(100_000)
    );
    let v4 = "Film \"rgb\" \"integer xresolution\" 16\nCamera \"perspective\"\nWorldBegin\n\
              Material \"interface\"\nShape \"curve\"\n";
    vec![
        (
            "deep.xml",
            nested_mitsuba(7000),
            b"nested more than 128 elements deep".to_vec(),
        ),
        (
            "deep.json",
            json_deep,
            b"materials.m.type: missing \"type\"".to_vec(),
        ),
        (
            "loop.pbrt",
            "Include \"loop.pbrt\"\n".to_string(),
            b"Include nested deeper than".to_vec(),
        ),
        (
            "extreme.json",
            extreme.to_string(),
            b"beyond the largest world coordinate".to_vec(),
        ),
        (
            "mitsuba3.xml",
            mitsuba3_with_environment(),
            b"cannot be rendered as the file means it (1 reason): line 4: emitter \"sunsky\""
                .to_vec(),
        ),
        (
            "v4.pbrt",
            v4.to_string(),
            b"(2 reasons): line 4: material \"interface\": no surface (a medium boundary) is not supported; line 5: Shape \"curve\" is not supported"
                .to_vec(),
        ),
    ]
}

#[test]
fn hostile_scene_files_get_400_naming_the_problem_and_the_coordinator_keeps_serving() {
    let dir = folder("scenes");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    for (name, text, want) in hostile_scenes() {
        let (s, v) = upload_bundle(&c, &url, tar_of(&[(name, text.as_bytes())]));
        let want = String::from_utf8(want).expect("utf-8");
        assert_eq!(s, 400, "{name}: {v}");
        let msg = v["error"].as_str().unwrap_or("");
        assert!(msg.contains(&want), "{name}: '{msg}' should say '{want}'");
        assert!(msg.contains(name), "{name}: '{msg}' should name the file");
        assert!(!msg.contains(&*dir.to_string_lossy()), "{name}: '{msg}'");
        healthy(&c, &url);
    }
    // The JSON ones inline, too.
    let extreme = json_scene(json!([{
        "type": "triangles", "positions": [[0, 0, 2], [0, -3e20, 2], [0, 1, 2]],
        "indices": [[0, 1, 2]], "material": "grey"
    }]));
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({"scene": {"inline": extreme}, "settings": {"spp": 1}}),
    );
    assert_eq!(s, 400, "{v}");
    assert_eq!(v["field"], "scene.inline", "{v}");
    assert!(
        v["error"].as_str().unwrap_or("").contains("shapes[1]"),
        "{v}"
    );
    // Nothing of the refused uploads stays on disk.
    let left = std::fs::read_dir(dir.join("data/scenes"))
        .map(|d| d.count())
        .unwrap_or(0);
    assert_eq!(left, 0, "refused bundles left on disk");
    healthy(&c, &url);
}

#[test]
fn hostile_scene_files_make_omis_render_exit_with_one_line() {
    let dir = folder("render");
    for (name, text, want) in hostile_scenes() {
        let path = dir.join(name);
        std::fs::write(&path, &text).expect("write scene");
        let out = Command::new(EXE)
            .args(["render", "--in-process", "--spp", "1"])
            .arg(&path)
            .arg("--out")
            .arg(dir.join("out.exr"))
            .output()
            .expect("run omis");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{name}: {err}");
        let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
        assert_eq!(lines.len(), 1, "{name}: one line expected, got {err}");
        let want = String::from_utf8(want).expect("utf-8");
        assert!(lines[0].contains(&want), "{name}: {err}");
    }
}

#[test]
fn a_merge_radius_beyond_the_scene_is_refused() {
    let dir = folder("radius");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({"scene": {"library": "cornell-box"},
                "settings": {"integrator": "vcm", "radius": 1e9, "spp": 1}}),
    );
    assert_eq!(s, 422, "{v}");
    assert_eq!(v["field"], "settings.radius");
    assert!(
        v["error"]
            .as_str()
            .unwrap_or("")
            .contains("bounding-sphere radius"),
        "{v}"
    );
}
