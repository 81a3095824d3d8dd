//! The local worker pool: a dead worker restarted, workers draining on SIGTERM.

use crate::common::service::{get_json, http, serve, worker};
use crate::support::{WAIT, assert_equal, download_exr, folder, in_process, submit, wait_state};
use std::time::{Duration, Instant};

/// Pids of the children of `pid` (of any of its threads).
fn children(pid: u32) -> Vec<u32> {
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return Vec::new();
    };
    tasks
        .filter_map(|t| t.ok())
        .flat_map(|t| {
            std::fs::read_to_string(t.path().join("children"))
                .unwrap_or_default()
                .split_whitespace()
                .filter_map(|s| s.parse().ok())
                .collect::<Vec<u32>>()
        })
        .collect()
}

#[test]
fn a_local_pool_restarts_a_worker_that_dies_and_workers_drain_on_sigterm() {
    let dir = folder("pool");
    let (server, url) = serve(
        &dir.join("data"),
        &["--workers", "1", "--lease-seconds", "1"],
    );
    let c = http();
    // Wait for the pool's worker, kill it, and see it replaced.
    let start = Instant::now();
    let first = loop {
        if let Some(&p) = children(server.0.id()).first() {
            break p;
        }
        assert!(start.elapsed() < WAIT, "no local worker started");
        std::thread::sleep(Duration::from_millis(50));
    };
    // SAFETY: kill(2) on a pid we just read as our child's child.
    unsafe {
        libc::kill(first as libc::pid_t, libc::SIGKILL);
    }
    let start = Instant::now();
    loop {
        let m = c
            .get(format!("{url}/metrics"))
            .send()
            .expect("metrics")
            .text()
            .expect("text");
        if m.contains("omis_worker_restarts_total 1") && !children(server.0.id()).is_empty() {
            break;
        }
        assert!(start.elapsed() < WAIT, "the worker was not restarted: {m}");
        std::thread::sleep(Duration::from_millis(100));
    }
    // A job still completes with the restarted worker and an extra one that is told to drain.
    let mut extra = worker(&url, "drainer", &[]);
    // Registered means its signal handlers are installed (they come first).
    let start = Instant::now();
    while !get_json(&c, &format!("{url}/v1/workers"))["workers"]
        .as_array()
        .is_some_and(|w| w.iter().any(|w| w["name"] == "drainer"))
    {
        assert!(start.elapsed() < WAIT, "the drainer never registered");
        std::thread::sleep(Duration::from_millis(20));
    }
    let id = submit(&c, &url, 16);
    wait_state(&c, &url, &id, |s| {
        s["tiles_done"].as_u64().unwrap_or(0) >= 1
    });
    // SAFETY: kill(2) on our own child.
    unsafe {
        libc::kill(extra.0.id() as libc::pid_t, libc::SIGTERM);
    }
    let start = Instant::now();
    let status = loop {
        if let Some(s) = extra.0.try_wait().expect("wait") {
            break s;
        }
        assert!(start.elapsed() < WAIT, "the worker did not drain");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "a drained worker exits 0: {status}");
    let workers = get_json(&c, &format!("{url}/v1/workers"));
    let drainer = workers["workers"]
        .as_array()
        .and_then(|w| w.iter().find(|w| w["name"] == "drainer").cloned())
        .expect("drainer listed");
    assert_eq!(drainer["state"], "left");
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 16);
    assert_equal(&download_exr(&c, &url, &id, &dir), &in_process(16));
}
