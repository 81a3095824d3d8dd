//! Jobs with a time budget instead of a sample count.

use crate::common::repo;
use crate::common::service::{EXE, http, post, serve, worker};
use crate::support::{download_exr, folder, submit_settings, wait_state};
use serde_json::{Value, json};
use std::process::Command;
use std::time::{Duration, Instant};

#[test]
fn a_time_budget_job_renders_passes_until_its_time_is_up() {
    let dir = folder("budget");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let _w = worker(&url, "w", &[]);
    let c = http();
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({
            "scene": { "library": "cornell-box" },
            "settings": { "resolution": [40, 32], "time_budget_s": 1.0, "pass_size": 4, "max_pass_size": 4 },
        }),
    );
    assert_eq!(s, 201, "{v}");
    assert_eq!(v["spp_target"], Value::Null);
    let id = v["id"].as_str().expect("id").to_string();
    let start = Instant::now();
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    let spp = st["spp_done"].as_u64().expect("spp");
    assert!(spp >= 8 && spp.is_multiple_of(4), "{st}");
    // The last pass is fitted to the time left at the rate so far: the job ends near its
    // budget, before it or after.
    assert!(
        start.elapsed() >= Duration::from_millis(700),
        "ended early: {st}"
    );
    assert_eq!(
        st["series"].as_array().map(|a| a.len() as u64),
        Some(spp / 4)
    );
    // Growing passes (1, 2, 4, ... 64 samples), the last fitted to the time left (where the
    // time left allows a fit: when the job ends can only be measured, BENCHMARKS.md, "The render service").
    let id = submit_settings(
        &c,
        &url,
        json!({ "resolution": [40, 32], "time_budget_s": 1.0, "pass_size": 1, "max_pass_size": 64 }),
    );
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    let spp = st["spp_done"].as_u64().expect("spp");
    // A fitted last pass is the job's sample target once planned (a fit withdrawn or never
    // made leaves none), and its merge writes the final EXR.
    assert!(
        st["spp_target"].is_null() || st["spp_target"].as_u64() == Some(spp),
        "{st}"
    );
    let image = download_exr(&c, &url, &id, &dir);
    assert_eq!((image.width, image.height), (40, 32));
    // The in-process render honours a time budget too.
    let exr = dir.join("budget.exr");
    let out = Command::new(EXE)
        .args(["render", "scenes/cornell-box.json", "--in-process"])
        .args([
            "--resolution",
            "40x32",
            "--time-budget",
            "0.3",
            "--pass-size",
            "2",
        ])
        .arg("--out")
        .arg(&exr)
        .arg("--json")
        .current_dir(repo())
        .output()
        .expect("run");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let line = String::from_utf8_lossy(&out.stdout)
        .lines()
        .last()
        .expect("summary")
        .to_string();
    let v: Value = serde_json::from_str(&line).expect("JSON");
    let spp = v["spp"].as_u64().expect("spp");
    assert!(spp >= 2 && spp.is_multiple_of(2), "{v}");
}
