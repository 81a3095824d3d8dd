//! Helpers shared by the service tests: the test jobs and their in-process renders, waiting on
//! and downloading jobs, SSE, and what a worker does (lease, render a tile, upload, merge).

use crate::common;
use crate::common::repo;
use crate::common::service::{get_json, post};
use omis::film::Image;
use omis::film::image::exr_io;
use omis::job::{JobSettings, Limits};
use omis::scene::Scene;
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

pub const WAIT: Duration = Duration::from_secs(180);

pub fn folder(name: &str) -> PathBuf {
    common::folder("svc", name)
}

/// The settings of the test jobs: a small Cornell box, BDPT with optimal MIS, several passes.
pub fn settings(spp: u32) -> Value {
    json!({
        "resolution": [40, 32],
        "spp": spp,
        "pass_size": 4,
        "max_pass_size": 4,
        "tile_size": 16,
        "integrator": "bdpt",
        "mis": "optimal",
        "max_depth": 4,
        "seed": 7,
    })
}

pub fn submit(c: &Client, url: &str, spp: u32) -> String {
    submit_settings(c, url, settings(spp))
}

pub fn submit_settings(c: &Client, url: &str, settings: Value) -> String {
    let (s, v) = post(
        c,
        &format!("{url}/v1/jobs"),
        &json!({ "scene": { "library": "cornell-box" }, "settings": settings }),
    );
    assert_eq!(s, 201, "{v}");
    v["id"].as_str().expect("id").to_string()
}

pub fn wait_state(c: &Client, url: &str, id: &str, pred: impl Fn(&Value) -> bool) -> Value {
    let start = Instant::now();
    loop {
        let st = get_json(c, &format!("{url}/v1/jobs/{id}"));
        if pred(&st) {
            return st;
        }
        assert!(
            !matches!(st["state"].as_str(), Some("failed" | "cancelled")),
            "job ended: {st}"
        );
        assert!(start.elapsed() < WAIT, "timed out; last status {st}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

pub fn download_exr(c: &Client, url: &str, id: &str, dir: &Path) -> Image {
    let r = c
        .get(format!("{url}/v1/jobs/{id}/image.exr"))
        .send()
        .expect("GET image.exr");
    assert!(r.status().is_success(), "{}", r.status());
    let p = dir.join(format!("{id}.exr"));
    std::fs::write(&p, r.bytes().expect("bytes")).expect("write");
    exr_io::read_exr(&p).expect("the EXR opens")
}

/// The same job rendered in this process.
pub fn in_process(spp: u32) -> Image {
    in_process_settings(settings(spp))
}

/// A job of `settings` rendered in this process.
pub fn in_process_settings(settings: Value) -> Image {
    let s: JobSettings = serde_json::from_value(settings).expect("settings");
    let mut scene = Scene::load(&repo().join("scenes/cornell-box.json")).expect("scene");
    let r = s.resolve(&mut scene, &Limits::default()).expect("resolve");
    r.render_in_process(&scene, &|_| {}).image()
}

pub fn assert_equal(a: &Image, b: &Image) {
    assert_eq!((a.width, a.height), (b.width, b.height));
    let mut worst = 0.0f64;
    for (p, q) in a.pixels.iter().zip(&b.pixels) {
        for c in 0..3 {
            let (x, y) = (p[c] as f64, q[c] as f64);
            let rel = (x - y).abs() / x.abs().max(y.abs()).max(1e-30);
            if x != y {
                worst = worst.max(rel);
            }
        }
    }
    assert!(worst <= 1e-6, "max relative difference {worst:e}");
    let mean = a.mean();
    assert!(mean[0] > 0.01, "the image is not black: {mean:?}");
}

/// Reads SSE events (kind, data) from a job's stream until a final one.
pub fn follow_sse(c: &Client, url: &str, id: &str) -> Vec<(String, Value)> {
    let mut r = c
        .get(format!("{url}/v1/jobs/{id}/events"))
        .timeout(WAIT)
        .send()
        .expect("GET events");
    assert_eq!(
        r.headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok()),
        Some("text/event-stream")
    );
    let mut text = String::new();
    let mut events = Vec::new();
    let mut buf = [0u8; 8192];
    let start = Instant::now();
    loop {
        let n = r.read(&mut buf).expect("read SSE");
        if n == 0 {
            break;
        }
        text.push_str(&String::from_utf8_lossy(&buf[..n]));
        while let Some(end) = text.find("\n\n") {
            let block: String = text.drain(..end + 2).collect();
            let mut kind = String::new();
            let mut data = Value::Null;
            for line in block.lines() {
                if let Some(k) = line.strip_prefix("event:") {
                    kind = k.trim().to_string();
                } else if let Some(d) = line.strip_prefix("data:") {
                    data = serde_json::from_str(d.trim()).unwrap_or(Value::Null);
                }
            }
            if !kind.is_empty() {
                events.push((kind, data));
            }
        }
        if events
            .last()
            .is_some_and(|(k, _)| matches!(k.as_str(), "done" | "failed" | "cancelled"))
        {
            break;
        }
        assert!(start.elapsed() < WAIT, "SSE stream did not end");
    }
    events
}

/// A tile result as a worker would upload it, rendered with `seed`.
pub fn tile_result(task: &Value, seed: u64) -> Vec<u8> {
    tile_result_of(&settings(64), task, seed)
}

/// `tile_result` of a job of `settings`.
pub fn tile_result_of(settings: &Value, task: &Value, seed: u64) -> Vec<u8> {
    let mut s: JobSettings = serde_json::from_value(settings.clone()).expect("settings");
    s.seed = seed;
    let mut scene = Scene::load(&repo().join("scenes/cornell-box.json")).expect("scene");
    let r = s.resolve(&mut scene, &Limits::default()).expect("resolve");
    let rect: omis::film::Tile = serde_json::from_value(task["rect"].clone()).expect("rect");
    let range = task["samples"][0].as_u64().expect("s0") as u32
        ..task["samples"][1].as_u64().expect("s1") as u32;
    let film = omis::integrator::render_tile(&scene, &r.render, rect, range.clone());
    omis::film::format::encode_banded(film, range, &r.grid())
}

pub fn lease(c: &Client, url: &str, worker: &str) -> Value {
    let (s, v) = post(
        c,
        &format!("{url}/v1/worker/lease"),
        &json!({ "worker_id": worker, "wait_s": 5 }),
    );
    assert_eq!(s, 200, "{v}");
    v
}

pub fn upload(c: &Client, url: &str, task: &Value, worker: &str, body: Vec<u8>) -> u16 {
    c.put(format!(
        "{url}/v1/worker/tasks/{}/result",
        task["task"]["id"]
    ))
    .query(&[
        ("worker_id", worker.to_string()),
        ("attempt", task["task"]["attempt"].to_string()),
    ])
    .body(body)
    .send()
    .expect("PUT result")
    .status()
    .as_u16()
}

/// Runs the merge task of `lease` as a worker does: its input streamed from the coordinator
/// into `film::merge_task::run` in this process, its output uploaded; the upload's status.
pub fn merge_task(c: &Client, url: &str, lease: &Value, worker: &str) -> u16 {
    let t = &lease["task"];
    assert_eq!(t["kind"], "merge", "{lease}");
    let r: omis::job::Resolved =
        serde_json::from_value(lease["job"]["resolved"].clone()).expect("resolved");
    let input = c
        .get(format!("{url}/v1/worker/tasks/{}/input", t["id"]))
        .query(&[
            ("worker_id", worker.to_string()),
            ("attempt", t["attempt"].to_string()),
        ])
        .send()
        .expect("GET input");
    assert_eq!(input.status().as_u16(), 200);
    let out = omis::film::merge_task::run(input, &r.grid(), &r.film_layout()).expect("merge");
    upload(c, url, lease, worker, out)
}

/// The film layout of a synthetic-stream job.
pub fn synthetic_layout(settings: &Value) -> omis::film::FilmLayout {
    let s: JobSettings = serde_json::from_value(settings.clone()).expect("settings");
    let mut scene = Scene::load(&repo().join("scenes/cornell-box.json")).expect("scene");
    let limits = Limits {
        max_resolution: 8192,
        ..Limits::default()
    };
    s.resolve(&mut scene, &limits)
        .expect("resolve")
        .film_layout()
}
