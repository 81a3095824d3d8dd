//! Helpers shared by the hostile-input tests: folders, bundles, health checks, small scenes and
//! jobs, failing a leased task.

use crate::common;
use crate::common::service::post;
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::path::PathBuf;

pub fn folder(name: &str) -> PathBuf {
    common::folder("hostile", name)
}

/// A tar archive of `files` (path, contents).
pub fn tar_of(files: &[(&str, &[u8])]) -> Vec<u8> {
    let mut tar = tar::Builder::new(Vec::new());
    for (name, data) in files {
        let mut h = tar::Header::new_gnu();
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        h.set_cksum();
        tar.append_data(&mut h, name, *data).expect("tar entry");
    }
    tar.into_inner().expect("tar")
}

/// POST /v1/scenes with `tar`; the status and the JSON answer.
pub fn upload_bundle(c: &Client, url: &str, tar: Vec<u8>) -> (u16, Value) {
    let r = c
        .post(format!("{url}/v1/scenes"))
        .header("content-type", "application/x-tar")
        .body(tar)
        .send()
        .expect("POST /v1/scenes");
    let s = r.status().as_u16();
    (s, r.json().unwrap_or(Value::Null))
}

/// `/healthz` answers 200.
pub fn healthy(c: &Client, url: &str) {
    let r = c.get(format!("{url}/healthz")).send().expect("healthz");
    assert_eq!(r.status().as_u16(), 200);
}

/// A small JSON scene: a furnace-like sphere seen from inside, with `shapes` added.
pub fn json_scene(extra_shapes: Value) -> Value {
    let mut shapes = vec![json!({
        "type": "sphere", "center": [0, 0, 0], "radius": 1, "inward": true,
        "material": "grey", "emission": 1
    })];
    if let Value::Array(a) = extra_shapes {
        shapes.extend(a);
    }
    json!({
        "camera": {"position": [0, 0, 0], "look_at": [0, 0, 1], "fov": 60, "resolution": [16, 16]},
        "materials": {"grey": {"type": "lambert", "albedo": 0.5}},
        "shapes": shapes
    })
}

/// A Mitsuba 0.5 scene with `inner` inside its one shape.
pub fn mitsuba(version: &str, inner: &str) -> String {
    format!(
        r#"<?xml version="1.0"?>
<scene version="{version}">
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="toWorld"><lookat origin="0,0,5" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
  </sensor>
  <shape type="sphere">
    <float name="radius" value="1"/>
    <emitter type="area"><spectrum name="radiance" value="1"/></emitter>
    {inner}
  </shape>
</scene>
"#
    )
}

/// Submits a job of the Cornell box of `tiles` tiles of 16 pixels (one pass, one sample).
pub fn small_job(c: &Client, url: &str, tiles: u32) -> String {
    let (s, v) = post(
        c,
        &format!("{url}/v1/jobs"),
        &json!({"scene": {"library": "cornell-box"}, "settings": {
            "resolution": [16 * tiles, 16], "tile_size": 16, "spp": 1, "pass_size": 1,
            "max_pass_size": 1, "integrator": "pt"
        }}),
    );
    assert_eq!(s, 201, "{v}");
    v["id"].as_str().expect("id").to_string()
}

pub fn fail(c: &Client, url: &str, worker: &str, lease: &Value, error: &str) {
    let (s, v) = post(
        c,
        &format!("{url}/v1/worker/tasks/{}/fail", lease["task"]["id"]),
        &json!({"worker_id": worker, "attempt": lease["task"]["attempt"], "error": error}),
    );
    assert_eq!(s, 200, "{v}");
}
