//! Leases and task failures: late results of expired leases, a leased task holding back a
//! pass, a task that keeps failing.

use crate::common::service::{get_json, http, post, register, serve, worker};
use crate::support::{
    WAIT, assert_equal, download_exr, folder, in_process, lease, merge_task, submit, tile_result,
    upload, wait_state,
};
use serde_json::json;
use std::time::{Duration, Instant};

#[test]
fn a_late_result_of_an_expired_lease_is_refused_and_changes_nothing() {
    let dir = folder("late");
    let (_server, url) = serve(&dir.join("data"), &["--lease-seconds", "1"]);
    let c = http();
    let id = submit(&c, &url, 64);
    let a = register(&c, &url, "slow");
    let first = lease(&c, &url, &a);
    // The results to upload, rendered now: a late one with a wrong seed (it would show), and
    // one for another tile.
    let wrong = tile_result(&first["task"], 99);
    let mut other = first["task"].clone();
    other["rect"] = json!({ "x0": 16, "y0": 0, "x1": 32, "y1": 16 });
    let other = tile_result(&other, 7);
    // Silent past its lease: the task goes back to the queue and to the next worker.
    let expire = Instant::now();
    while expire.elapsed() < Duration::from_millis(2500) {
        std::thread::sleep(Duration::from_millis(100));
    }
    let b = register(&c, &url, "fast");
    let second = lease(&c, &url, &b);
    assert_eq!(first["task"]["id"], second["task"]["id"]);
    assert_eq!(second["task"]["attempt"], 2);
    // B's lease is current (renewed at once) for the uploads below.
    let (s, v) = post(
        &c,
        &format!("{url}/v1/worker/heartbeat"),
        &json!({ "worker_id": b, "tasks": [{ "id": second["task"]["id"], "attempt": 2 }] }),
    );
    assert_eq!((s, v["lost"].clone()), (200, json!([])), "{v}");
    // The late result (wrong seed, so it would show) is refused, and so is a non-owner's.
    assert_eq!(upload(&c, &url, &first, &a, wrong.clone()), 409);
    assert_eq!(upload(&c, &url, &second, &a, wrong), 409);
    // A result for another tile is refused as invalid.
    assert_eq!(upload(&c, &url, &second, &b, other), 400);
    // After the invalid upload the task is back in the queue; the workers finish the job.
    let _w = worker(&url, "w", &[]);
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 64);
    assert_equal(&download_exr(&c, &url, &id, &dir), &in_process(64));
}

#[test]
fn a_running_jobs_exr_waits_for_the_interval_and_a_cancel_writes_the_merged_passes() {
    let dir = folder("exr-interval");
    let (_server, url) = serve(&dir.join("data"), &["--exr-interval", "3600"]);
    let c = http();
    // 16 passes of 4 spp, 6 tiles each; this test is the only worker.
    let id = submit(&c, &url, 64);
    let w = register(&c, &url, "manual");
    let start = Instant::now();
    while get_json(&c, &format!("{url}/v1/jobs/{id}"))["spp_done"] != 4 {
        assert!(start.elapsed() < WAIT, "the first pass was not merged");
        let t = lease(&c, &url, &w);
        match (t["task"]["kind"].as_str(), t["task"]["pass"].as_u64()) {
            (Some("merge"), _) => assert_eq!(merge_task(&c, &url, &t, &w), 200),
            (Some("render"), Some(0)) => {
                assert_eq!(upload(&c, &url, &t, &w, tile_result(&t["task"], 7)), 200)
            }
            // A task of the second pass stays leased: the job does not get past its first.
            _ => {}
        }
    }
    let file = |name: &str| {
        c.get(format!("{url}/v1/jobs/{id}/{name}"))
            .send()
            .expect("GET")
    };
    // The pass rewrote the preview, but not the EXR: the interval has not passed.
    assert_eq!(file("preview.png").status().as_u16(), 200);
    let r = file("image.exr");
    assert_eq!(r.status().as_u16(), 404);
    assert!(r.text().unwrap_or_default().contains("\"field\""));
    // Cancelled, the job writes the passes it merged.
    let (s, v) = post(&c, &format!("{url}/v1/jobs/{id}/cancel"), &json!({}));
    assert_eq!(s, 200, "{v}");
    let img = download_exr(&c, &url, &id, &dir);
    assert_eq!((img.width, img.height), (40, 32));
    let mean = img.pixels.iter().map(|p| p.x + p.y + p.z).sum::<f32>() / img.pixels.len() as f32;
    assert!(mean.is_finite() && mean > 0.0, "mean {mean}");
}

#[test]
fn a_task_that_fails_three_times_fails_the_job_with_the_workers_error() {
    let dir = folder("fail");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let id = submit(&c, &url, 8);
    for k in 0..3 {
        let w = register(&c, &url, &format!("bad{k}"));
        let t = lease(&c, &url, &w);
        let (s, v) = post(
            &c,
            &format!("{url}/v1/worker/tasks/{}/fail", t["task"]["id"]),
            &json!({ "worker_id": w, "attempt": t["task"]["attempt"], "error": "out of memory" }),
        );
        assert_eq!(s, 200, "{v}");
    }
    let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    assert_eq!(st["state"], "failed");
    assert!(
        st["error"].as_str().unwrap_or("").contains("out of memory"),
        "{st}"
    );
}
