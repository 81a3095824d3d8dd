//! Jobs on real workers equal the in-process render, also when a worker or the coordinator
//! dies mid-job.

use crate::common::repo;
use crate::common::service::{get_json, http, post, serve, worker};
use crate::support::{
    assert_equal, download_exr, folder, follow_sse, in_process, in_process_settings, settings,
    submit, submit_settings, wait_state,
};
use omis::job::{JobSettings, Limits};
use omis::scene::Scene;
use serde_json::json;
use std::time::Duration;

#[test]
fn http_job_with_two_workers_follows_sse_and_equals_the_in_process_render() {
    let dir = folder("basic");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let _w1 = worker(&url, "w1", &[]);
    let _w2 = worker(&url, "w2", &[]);
    let c = http();
    let id = submit(&c, &url, 16);
    let events = follow_sse(&c, &url, &id);
    let kinds: Vec<&str> = events.iter().map(|(k, _)| k.as_str()).collect();
    assert_eq!(kinds.first(), Some(&"queued"), "{kinds:?}");
    assert_eq!(kinds.last(), Some(&"done"), "{kinds:?}");
    let passes: Vec<u64> = events
        .iter()
        .filter(|(k, _)| k == "pass_done")
        .map(|(_, d)| d["spp"].as_u64().expect("spp"))
        .collect();
    assert_eq!(passes, vec![4, 8, 12, 16]);
    assert_eq!(kinds.iter().filter(|k| **k == "tile_done").count(), 4 * 6);
    assert!(kinds.contains(&"preview"));
    let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    assert_eq!(st["state"], "done");
    assert_eq!(st["spp_done"], 16);
    assert!(st["accum_bytes"].as_i64().unwrap_or(0) > 0);
    let workers = get_json(&c, &format!("{url}/v1/workers"));
    assert_eq!(workers["workers"].as_array().map(|w| w.len()), Some(2));
    let img = download_exr(&c, &url, &id, &dir);
    assert_equal(&img, &in_process(16));
    // The preview is a PNG; the convergence plot an SVG; no reference, so no error map.
    let png = c
        .get(format!("{url}/v1/jobs/{id}/preview.png"))
        .send()
        .expect("preview");
    assert_eq!(&png.bytes().expect("bytes")[..4], b"\x89PNG");
    let svg = c
        .get(format!("{url}/v1/jobs/{id}/convergence.svg"))
        .send()
        .expect("svg");
    assert!(svg.text().expect("text").contains("<svg"));
    let e = c
        .get(format!("{url}/v1/jobs/{id}/error.png"))
        .send()
        .expect("error map");
    assert_eq!(e.status().as_u16(), 404);
    let metrics = c
        .get(format!("{url}/metrics"))
        .send()
        .expect("metrics")
        .text()
        .expect("text");
    assert!(metrics.contains("omis_jobs{state=\"done\"} 1"), "{metrics}");
    assert!(metrics.contains("omis_passes_merged_total 4"), "{metrics}");
}

#[test]
fn a_vcm_job_on_two_workers_equals_the_in_process_render() {
    // Each worker traces the light paths of the iterations it renders: the tiles of a pass merge
    // with every photon of the pass whichever worker renders them.
    let dir = folder("vcm");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let _w1 = worker(&url, "w1", &[]);
    let _w2 = worker(&url, "w2", &[]);
    let c = http();
    let settings = json!({
        "resolution": [40, 32],
        "spp": 8,
        "pass_size": 2,
        "max_pass_size": 2,
        "tile_size": 16,
        "integrator": "vcm",
        "radius": 0.03,
        "max_depth": 4,
        "seed": 7,
    });
    let (st, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({ "scene": { "library": "cornell-box" }, "settings": settings }),
    );
    assert_eq!(st, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 8);
    let s: JobSettings = serde_json::from_value(settings).expect("settings");
    let mut scene = Scene::load(&repo().join("scenes/cornell-box.json")).expect("scene");
    let r = s.resolve(&mut scene, &Limits::default()).expect("resolve");
    let local = r.render_in_process(&scene, &|_| {}).image();
    assert_equal(&download_exr(&c, &url, &id, &dir), &local);
}

#[test]
fn killing_a_worker_mid_job_loses_nothing() {
    let dir = folder("killworker");
    let (_server, url) = serve(&dir.join("data"), &["--lease-seconds", "1"]);
    let mut w1 = worker(&url, "w1", &[]);
    let _w2 = worker(&url, "w2", &[]);
    let c = http();
    let id = submit(&c, &url, 64);
    let st = wait_state(&c, &url, &id, |s| {
        s["tiles_done"].as_u64().unwrap_or(0) >= 2
    });
    w1.kill9();
    assert_ne!(st["state"], "done", "the job ended before the kill");
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 64);
    assert_equal(&download_exr(&c, &url, &id, &dir), &in_process(64));
}

#[test]
fn killing_the_coordinator_mid_job_resumes_without_losing_a_pass() {
    let dir = folder("killserver");
    let data = dir.join("data");
    let (mut server, url) = serve(&data, &["--workers", "2", "--lease-seconds", "1"]);
    let c = http();
    let id = submit(&c, &url, 64);
    let before = wait_state(&c, &url, &id, |s| {
        s["passes_done"].as_u64().unwrap_or(0) >= 2
    });
    server.kill9();
    let passes_before = before["passes_done"].as_u64().expect("passes");
    assert!(passes_before < 16, "the job ended before the kill");
    // The local workers follow their coordinator.
    std::thread::sleep(Duration::from_millis(1500));
    let (_server2, url2) = serve(&data, &["--workers", "2", "--lease-seconds", "1"]);
    let after = get_json(&c, &format!("{url2}/v1/jobs/{id}"));
    assert!(
        after["passes_done"].as_u64().expect("passes") >= passes_before,
        "a finished pass was lost: {after}"
    );
    let st = wait_state(&c, &url2, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 64);
    assert_equal(&download_exr(&c, &url2, &id, &dir), &in_process(64));
}

/// The progressive optimal estimator's weights are solved where the coordinator merges a pass
/// and kept in its tile checkpoints: across a coordinator restart, the image has the bits of the
/// in-process render (whose weights are solved the same way), and it differs from the direct
/// estimator's.
#[test]
fn progressive_optimal_survives_a_coordinator_restart_with_the_in_process_bits() {
    let dir = folder("progressive");
    let data = dir.join("data");
    let mut job = settings(32);
    job["mis"] = json!("optimal-progressive");
    let (mut server, url) = serve(&data, &["--workers", "2", "--lease-seconds", "1"]);
    let c = http();
    let id = submit_settings(&c, &url, job.clone());
    let before = wait_state(&c, &url, &id, |s| {
        s["passes_done"].as_u64().unwrap_or(0) >= 2
    });
    server.kill9();
    assert!(
        before["passes_done"].as_u64().expect("passes") < 8,
        "the job ended before the kill"
    );
    std::thread::sleep(Duration::from_millis(1500));
    let (_server2, url2) = serve(&data, &["--workers", "2", "--lease-seconds", "1"]);
    let st = wait_state(&c, &url2, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 32);
    let img = download_exr(&c, &url2, &id, &dir);
    assert_equal(&img, &in_process_settings(job));
    assert!(
        img != in_process(32),
        "the progressive image is the direct one"
    );
}
