//! Tasks that fail or kill their workers: lost leases, failing workers kept away, restarts.

use crate::common::service::{get_json, http, post, register, serve, try_lease};
use crate::support::{fail, folder, small_job};
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::time::{Duration, Instant};

/// Lets `worker` poll for a lease until `job` has ended (the poll keeps it live); the job's
/// status.
fn poll_until_ended(c: &Client, url: &str, worker: &str, job: &str) -> Value {
    let start = Instant::now();
    loop {
        let st = get_json(c, &format!("{url}/v1/jobs/{job}"));
        if !matches!(st["state"].as_str(), Some("queued" | "running")) {
            return st;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "{st}");
        let (s, v) = try_lease(c, url, worker, 0.5);
        assert_eq!(s, 204, "{worker} must get no task: {v}");
    }
}

fn worker_info(c: &Client, url: &str, id: &str) -> Value {
    let list = get_json(c, &format!("{url}/v1/workers"));
    list["workers"]
        .as_array()
        .expect("workers")
        .iter()
        .find(|w| w["id"] == id)
        .cloned()
        .expect("the worker is listed")
}

#[test]
fn lost_leases_count_and_failing_workers_are_kept_from_the_tasks_they_failed() {
    let dir = folder("failing");
    let (_server, url) = serve(&dir.join("data"), &["--lease-seconds", "1"]);
    let c = http();
    // A task whose worker dies every time: three silent workers in turn, then the job fails.
    let job = small_job(&c, &url, 1);
    let silent: Vec<String> = (0..3)
        .map(|k| register(&c, &url, &format!("s{k}")))
        .collect();
    for w in &silent {
        let (s, lease) = try_lease(&c, &url, w, 10.0);
        assert_eq!(s, 200, "{w} gets the task again: {lease}");
        assert_eq!(lease["task"]["tile"], 0);
        // ... and dies: no heartbeat, no result. The next worker gets it once the lease expires.
    }
    let start = Instant::now();
    let st = loop {
        let st = get_json(&c, &format!("{url}/v1/jobs/{job}"));
        if st["state"] == "failed" {
            break st;
        }
        assert!(start.elapsed() < Duration::from_secs(30), "{st}");
        std::thread::sleep(Duration::from_millis(100));
    };
    let err = st["error"].as_str().unwrap_or("");
    assert!(
        err.contains("failed 3 times (worker lost 3 times)"),
        "{err}"
    );
    assert!(err.contains("its lease expired"), "{err}");

    // A worker that fails a task is not given it again; after three tasks of a job, none of its
    // tasks; and a job whose last task no live worker may take fails with that reason.
    let job = small_job(&c, &url, 3);
    let f = register(&c, &url, "faulty");
    let mut tiles = Vec::new();
    for _ in 0..3 {
        let (s, lease) = try_lease(&c, &url, &f, 10.0);
        assert_eq!(s, 200, "{lease}");
        tiles.push(lease["task"]["tile"].as_u64().expect("tile"));
        fail(&c, &url, &f, &lease, "disk full on the worker");
    }
    tiles.sort_unstable();
    assert_eq!(tiles, [0, 1, 2], "each failed task went to the worker once");
    assert_eq!(
        worker_info(&c, &url, &f)["blocklisted_jobs"],
        json!([job.clone()])
    );
    let st = poll_until_ended(&c, &url, &f, &job);
    assert_eq!(st["state"], "failed", "{st}");
    let err = st["error"].as_str().unwrap_or("");
    assert!(err.contains("failed on every live worker"), "{err}");
    assert!(err.contains("disk full on the worker"), "{err}");

    // Failures in three jobs in a row mark the worker unhealthy: it leases nothing, and another
    // worker takes the work.
    for _ in 0..2 {
        let j = small_job(&c, &url, 1);
        let (s, lease) = try_lease(&c, &url, &f, 10.0);
        assert_eq!(s, 200, "{lease}");
        assert_eq!(lease["task"]["job_id"], j.as_str());
        fail(&c, &url, &f, &lease, "disk full on the worker");
    }
    let info = worker_info(&c, &url, &f);
    let why = info["unhealthy"].as_str().unwrap_or("");
    assert!(why.contains("3 jobs"), "{info}");
    let j = small_job(&c, &url, 1);
    let (s, v) = try_lease(&c, &url, &f, 1.0);
    assert_eq!(s, 204, "an unhealthy worker leased {v}");
    let good = register(&c, &url, "good");
    // The good worker may first get the earlier jobs' tasks: any task is proof enough that it
    // leases, and the new job's task is among them.
    let mut got = Vec::new();
    for _ in 0..4 {
        let (s, lease) = try_lease(&c, &url, &good, 2.0);
        if s != 200 {
            break;
        }
        got.push(lease["task"]["job_id"].as_str().unwrap_or("").to_string());
    }
    assert!(got.contains(&j), "the healthy worker got {got:?}, not {j}");
}

#[test]
fn a_local_worker_killed_by_its_task_is_restarted_and_the_job_fails_after_three_losses() {
    // A worker process that dies with its task (kill -9 of the pool's worker, three times):
    // the coordinator counts each loss, the pool restarts the worker, and the job fails.
    let dir = folder("pool");
    let (_server, url) = serve(
        &dir.join("data"),
        &["--lease-seconds", "1", "--workers", "1"],
    );
    let c = http();
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({"scene": {"library": "cornell-box"}, "settings": {
            "resolution": [64, 64], "spp": 65536, "integrator": "bdpt", "tile_size": 64,
            "pass_size": 65536, "max_pass_size": 65536
        }}),
    );
    assert_eq!(s, 201, "{v}");
    let job = v["id"].as_str().expect("id").to_string();
    let start = Instant::now();
    let mut killed = 0;
    let st = loop {
        let st = get_json(&c, &format!("{url}/v1/jobs/{job}"));
        if st["state"] == "failed" {
            break st;
        }
        assert!(start.elapsed() < Duration::from_secs(90), "{st}");
        let workers = get_json(&c, &format!("{url}/v1/workers"));
        for w in workers["workers"].as_array().expect("workers") {
            let busy = w["tasks"].as_array().is_some_and(|t| !t.is_empty());
            if busy && w["state"] != "gone" {
                // The worker's name is local-0; its pid is not in the API: kill the one child
                // of the coordinator that runs `omis worker`.
                if kill_local_worker() {
                    killed += 1;
                }
            }
        }
        std::thread::sleep(Duration::from_millis(300));
    };
    assert!(killed >= 3, "killed {killed} workers");
    let err = st["error"].as_str().unwrap_or("");
    assert!(err.contains("worker lost 3 times"), "{err}");
}

/// Kills (SIGKILL) the `omis worker` processes of this test's coordinator; whether one was.
fn kill_local_worker() -> bool {
    let me = std::process::id();
    let mut any = false;
    for entry in std::fs::read_dir("/proc").expect("proc").flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
        let args: Vec<&[u8]> = cmd.split(|b| *b == 0).collect();
        let is_worker = args.get(1) == Some(&&b"worker"[..]);
        // Only workers whose coordinator is a child of this test process.
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
        let parent = stat
            .rsplit(')')
            .next()
            .and_then(|s| s.split_whitespace().nth(1))
            .and_then(|p| p.parse::<u32>().ok());
        let grandparent = parent.and_then(|p| {
            std::fs::read_to_string(format!("/proc/{p}/stat"))
                .ok()?
                .rsplit(')')
                .next()?
                .split_whitespace()
                .nth(1)?
                .parse::<u32>()
                .ok()
        });
        if is_worker && grandparent == Some(me) {
            // SAFETY: kill(2) of a process this test started (through its coordinator).
            unsafe {
                libc::kill(pid as libc::pid_t, libc::SIGKILL);
            }
            any = true;
        }
    }
    any
}
