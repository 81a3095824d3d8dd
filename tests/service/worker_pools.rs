//! Worker pools and health: tags, an operator's disable / enable / drain, the blocklist and the
//! unhealthy mark cleared, and the task history.

use crate::common::service::{EXE, get_json, http, post, register, serve, try_lease, worker};
use crate::support::{WAIT, folder, settings, submit, tile_result};
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::process::Command;
use std::time::{Duration, Instant};

/// Submits the test job of `spp` requiring `tags`; the status code and answer.
fn submit_tagged(c: &Client, url: &str, spp: u32, tags: &[&str]) -> (u16, Value) {
    post(
        c,
        &format!("{url}/v1/jobs"),
        &json!({
            "scene": { "library": "cornell-box" },
            "settings": settings(spp),
            "require_tags": tags,
        }),
    )
}

/// Registers a worker with `tags`; its id.
fn register_tagged(c: &Client, url: &str, name: &str, tags: &[&str]) -> String {
    let (s, v) = post(
        c,
        &format!("{url}/v1/worker/register"),
        &json!({ "name": name, "threads": 1, "tags": tags }),
    );
    assert_eq!(s, 200, "{v}");
    v["worker_id"].as_str().expect("id").to_string()
}

/// The worker `id` as GET /v1/workers lists it.
fn worker_info(c: &Client, url: &str, id: &str) -> Value {
    let list = get_json(c, &format!("{url}/v1/workers"));
    list["workers"]
        .as_array()
        .expect("workers")
        .iter()
        .find(|w| w["id"] == id)
        .cloned()
        .unwrap_or_else(|| panic!("worker {id} is not listed: {list}"))
}

/// Reports attempt `lease` of `worker` failed with `error`.
fn fail(c: &Client, url: &str, lease: &Value, worker: &str, error: &str) {
    let (s, v) = post(
        c,
        &format!("{url}/v1/worker/tasks/{}/fail", lease["task"]["id"]),
        &json!({ "worker_id": worker, "attempt": lease["task"]["attempt"], "error": error }),
    );
    assert_eq!(s, 200, "{v}");
}

/// POSTs or DELETEs `path` without a body; the status and the JSON answer.
fn act(c: &Client, method: reqwest::Method, url: &str) -> (u16, Value) {
    let r = c.request(method, url).send().expect("request");
    let s = r.status().as_u16();
    (s, r.json().unwrap_or(Value::Null))
}

#[test]
fn a_tagged_job_goes_only_to_a_worker_with_every_tag_it_requires() {
    let dir = folder("pool-tags");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    // Tags are checked, on both sides.
    let (s, v) = submit_tagged(&c, &url, 8, &["GPU"]);
    assert_eq!((s, v["field"].as_str()), (400, Some("require_tags")), "{v}");
    let (s, v) = post(
        &c,
        &format!("{url}/v1/worker/register"),
        &json!({ "name": "x", "threads": 1, "tags": ["a b"] }),
    );
    assert_eq!((s, v["field"].as_str()), (400, Some("tags")), "{v}");
    // And by the command line, before anything is sent.
    for args in [
        vec!["worker", "--coordinator", url.as_str(), "--tag", "gpu,Fast"],
        vec![
            "submit",
            "cornell-box",
            "--require-tag",
            "a b",
            "--server",
            url.as_str(),
        ],
    ] {
        let out = Command::new(EXE).args(&args).output().expect("omis");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert!(
            err.contains("tag") && err.trim().lines().count() == 1,
            "{args:?}: {err}"
        );
    }
    let plain = register(&c, &url, "plain");
    let half = register_tagged(&c, &url, "half", &["gpu"]);
    let (s, v) = submit_tagged(&c, &url, 8, &["gpu", "fast"]);
    assert_eq!(s, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    assert_eq!(v["require_tags"], json!(["fast", "gpu"]));
    // No live worker has both tags: the status says so.
    let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    let waiting = st["waiting_for"].as_str().unwrap_or_default().to_string();
    assert!(
        waiting.contains("no live worker has tags [fast, gpu]"),
        "{st}"
    );
    for w in [&plain, &half] {
        let (s, v) = try_lease(&c, &url, w, 1.0);
        assert_eq!(s, 204, "worker without every tag leased {v}");
    }
    let tagged = register_tagged(&c, &url, "tagged", &["fast", "gpu", "big"]);
    assert_eq!(
        worker_info(&c, &url, &tagged)["tags"],
        json!(["big", "fast", "gpu"])
    );
    let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    assert_eq!(st["waiting_for"], Value::Null, "{st}");
    let (s, v) = try_lease(&c, &url, &tagged, 5.0);
    assert_eq!(
        (s, v["task"]["job_id"].as_str()),
        (200, Some(id.as_str())),
        "{v}"
    );
    // An untagged job goes to anyone, the tagged worker included.
    let other = submit(&c, &url, 8);
    let (s, v) = try_lease(&c, &url, &plain, 5.0);
    assert_eq!(
        (s, v["task"]["job_id"].as_str()),
        (200, Some(other.as_str())),
        "{v}"
    );
}

#[test]
fn a_disabled_worker_leases_nothing_across_a_restart_and_enable_restores_it() {
    let dir = folder("pool-disable");
    let data = dir.join("data");
    let (mut server, url) = serve(&data, &[]);
    let c = http();
    let id = submit(&c, &url, 8);
    let w = register(&c, &url, "operated");
    let (s, v) = act(
        &c,
        reqwest::Method::POST,
        &format!("{url}/v1/workers/{w}/disable"),
    );
    assert_eq!((s, v["admin"].as_str()), (200, Some("disabled")), "{v}");
    let (s, v) = act(
        &c,
        reqwest::Method::POST,
        &format!("{url}/v1/workers/nobody/disable"),
    );
    assert_eq!(s, 404, "{v}");
    let (s, _) = try_lease(&c, &url, &w, 1.0);
    assert_eq!(s, 204);
    // Kept by the coordinator's database.
    server.kill9();
    let (_server, url) = serve(&data, &[]);
    assert_eq!(worker_info(&c, &url, &w)["admin"], "disabled");
    let (s, _) = try_lease(&c, &url, &w, 1.0);
    assert_eq!(s, 204);
    // The CLI shows it, and enables it by an id prefix.
    let out = Command::new(EXE)
        .args(["workers", "--server", &url])
        .output()
        .expect("omis workers");
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{table}");
    let row = table
        .lines()
        .find(|l| l.starts_with("operated"))
        .unwrap_or_else(|| panic!("no row of the worker: {table}"));
    assert!(row.contains("disabled") && row.contains(&w[..8]), "{row}");
    let out = Command::new(EXE)
        .args(["workers", "enable", &w[..8], "--server", &url])
        .output()
        .expect("omis workers enable");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(worker_info(&c, &url, &w)["admin"], "enabled");
    let (s, v) = try_lease(&c, &url, &w, 5.0);
    assert_eq!(
        (s, v["task"]["job_id"].as_str()),
        (200, Some(id.as_str())),
        "{v}"
    );
}

#[test]
fn a_drained_worker_finishes_its_task_and_exits() {
    let dir = folder("pool-drain");
    // Short leases: heartbeats every half second carry the drain.
    let (_server, url) = serve(&dir.join("data"), &["--lease-seconds", "2"]);
    let c = http();
    let id = submit(&c, &url, 256);
    let mut proc = worker(&url, "drained", &[]);
    // Once it has delivered a result, drain it.
    let start = Instant::now();
    let w = loop {
        let list = get_json(&c, &format!("{url}/v1/workers"));
        let found = list["workers"]
            .as_array()
            .and_then(|ws| ws.iter().find(|w| w["name"] == "drained"))
            .filter(|w| w["tasks_done"].as_i64().unwrap_or(0) > 0)
            .cloned();
        if let Some(w) = found {
            break w["id"].as_str().expect("id").to_string();
        }
        assert!(start.elapsed() < WAIT, "the worker delivered nothing");
        std::thread::sleep(Duration::from_millis(100));
    };
    let (s, v) = act(
        &c,
        reqwest::Method::POST,
        &format!("{url}/v1/workers/{w}/drain"),
    );
    assert_eq!((s, v["admin"].as_str()), (200, Some("draining")), "{v}");
    let start = Instant::now();
    let status = loop {
        if let Some(s) = proc.0.try_wait().expect("wait") {
            break s;
        }
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "the drained worker did not exit"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(status.success(), "{status:?}");
    let info = worker_info(&c, &url, &w);
    assert_eq!(
        (info["state"].as_str(), info["admin"].as_str()),
        (Some("left"), Some("draining"))
    );
    // Every task it held was finished and delivered, none given back unfinished.
    let h = get_json(&c, &format!("{url}/v1/workers/{w}/tasks?limit=1000"));
    let attempts = h["attempts"].as_array().expect("attempts");
    assert!(!attempts.is_empty(), "{h}");
    for a in attempts {
        assert_eq!(a["outcome"], "done", "{a}");
        assert_eq!(a["job_id"], id.as_str());
    }
}

#[test]
fn a_blocklisted_worker_gets_no_task_of_the_job_until_cleared_and_the_history_shows_why() {
    let dir = folder("pool-blocklist");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let id = submit(&c, &url, 64);
    let bad = register(&c, &url, "bad");
    // Three tasks failed: blocklisted for the job.
    let mut failed = Vec::new();
    for k in 0..3 {
        let (s, t) = try_lease(&c, &url, &bad, 5.0);
        assert_eq!(s, 200, "{t}");
        fail(&c, &url, &t, &bad, &format!("disk full #{k}"));
        failed.push(t["task"]["id"].clone());
    }
    let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    assert_eq!(
        st["blocklisted_workers"][0]["worker_id"],
        bad.as_str(),
        "{st}"
    );
    assert!(worker_info(&c, &url, &bad)["blocklisted_jobs"] == json!([id]));
    for _ in 0..2 {
        let (s, v) = try_lease(&c, &url, &bad, 1.0);
        assert_eq!(s, 204, "a blocklisted worker leased {v}");
    }
    // Another worker takes the first failed task, and delivers something invalid for it.
    let good = register(&c, &url, "good");
    let (s, t) = try_lease(&c, &url, &good, 5.0);
    assert_eq!((s, &t["task"]["id"]), (200, &failed[0]), "{t}");
    let mut wrong = t["task"].clone();
    wrong["rect"] = json!({ "x0": 16, "y0": 0, "x1": 32, "y1": 16 });
    let r = c
        .put(format!("{url}/v1/worker/tasks/{}/result", t["task"]["id"]))
        .query(&[
            ("worker_id", good.clone()),
            ("attempt", t["task"]["attempt"].to_string()),
        ])
        .body(tile_result(&wrong, 7))
        .send()
        .expect("PUT");
    assert_eq!(r.status().as_u16(), 400);
    // Cleared, the worker gets the job's tasks again, those it failed included.
    let (s, v) = act(
        &c,
        reqwest::Method::DELETE,
        &format!("{url}/v1/jobs/{id}/blocklist/{bad}"),
    );
    assert_eq!(s, 200, "{v}");
    assert_eq!(v["blocklisted_workers"], json!([]));
    let (s, _) = act(
        &c,
        reqwest::Method::DELETE,
        &format!("{url}/v1/jobs/{id}/blocklist/{bad}"),
    );
    assert_eq!(s, 404);
    let (s, t) = try_lease(&c, &url, &bad, 5.0);
    assert_eq!(s, 200, "{t}");
    assert!(
        failed.contains(&t["task"]["id"]),
        "{t} is none of {failed:?}"
    );
    // The history: every attempt, the failed ones first with their errors.
    let h = get_json(&c, &format!("{url}/v1/jobs/{id}/tasks"));
    let attempts = h["attempts"].as_array().expect("attempts");
    assert_eq!(attempts.len(), 5, "{h}");
    let outcomes: Vec<&str> = attempts
        .iter()
        .map(|a| a["outcome"].as_str().unwrap_or(""))
        .collect();
    assert_eq!(
        outcomes,
        ["failed", "failed", "failed", "refused", "running"],
        "{h}"
    );
    for (k, a) in attempts[..3].iter().enumerate() {
        assert_eq!(a["worker_id"], bad.as_str());
        assert_eq!(a["error"], format!("disk full #{k}"));
        assert!(a["seconds"].as_f64().is_some_and(|s| s >= 0.0), "{a}");
    }
    assert_eq!(attempts[3]["worker_id"], good.as_str());
    assert!(
        attempts[3]["error"]
            .as_str()
            .is_some_and(|e| e.starts_with("invalid result")),
        "{h}"
    );
    assert_eq!(h["next"], Value::Null);
    // Filtered and paged.
    let f = get_json(
        &c,
        &format!("{url}/v1/jobs/{id}/tasks?outcome=failed&limit=2"),
    );
    assert_eq!(f["attempts"].as_array().map(Vec::len), Some(2));
    assert_eq!(f["next"], 2);
    let f = get_json(
        &c,
        &format!("{url}/v1/jobs/{id}/tasks?outcome=failed&limit=2&after=2"),
    );
    assert_eq!(f["attempts"][0]["error"], "disk full #2");
    assert_eq!(f["next"], Value::Null);
    // A page across the failed attempts' end.
    let f = get_json(&c, &format!("{url}/v1/jobs/{id}/tasks?limit=2&after=2"));
    assert_eq!(f["attempts"][0]["error"], "disk full #2", "{f}");
    assert_eq!(f["attempts"][1]["outcome"], "refused", "{f}");
    assert_eq!(f["next"], 4);
    let r = c
        .get(format!("{url}/v1/jobs/{id}/tasks?limit=0"))
        .send()
        .expect("GET");
    assert_eq!(r.status().as_u16(), 400);
    let w = get_json(&c, &format!("{url}/v1/workers/{good}/tasks"));
    assert_eq!(w["attempts"][0]["outcome"], "refused", "{w}");
    // `omis tasks --failed` prints them.
    let out = Command::new(EXE)
        .args(["tasks", &id, "--failed", "--server", &url])
        .output()
        .expect("omis tasks");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    assert_eq!(text.lines().count(), 4, "{text}");
    assert!(
        text.contains("disk full #0") && !text.contains("invalid result"),
        "{text}"
    );
}

#[test]
fn clearing_the_unhealthy_mark_lets_a_worker_lease_again() {
    let dir = folder("pool-unhealthy");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let w = register(&c, &url, "flaky");
    // A failed task in each of three jobs: unhealthy.
    for _ in 0..3 {
        let id = submit(&c, &url, 8);
        let (s, t) = try_lease(&c, &url, &w, 5.0);
        assert_eq!(
            (s, t["task"]["job_id"].as_str()),
            (200, Some(id.as_str())),
            "{t}"
        );
        fail(&c, &url, &t, &w, "GPU lost");
        let (s, v) = post(&c, &format!("{url}/v1/jobs/{id}/cancel"), &json!({}));
        assert_eq!(s, 200, "{v}");
    }
    let id = submit(&c, &url, 8);
    assert!(worker_info(&c, &url, &w)["unhealthy"].is_string());
    let (s, _) = try_lease(&c, &url, &w, 1.0);
    assert_eq!(s, 204);
    let (s, v) = act(
        &c,
        reqwest::Method::DELETE,
        &format!("{url}/v1/workers/{w}/unhealthy"),
    );
    assert_eq!((s, &v["unhealthy"]), (200, &Value::Null), "{v}");
    let (s, t) = try_lease(&c, &url, &w, 5.0);
    assert_eq!(
        (s, t["task"]["job_id"].as_str()),
        (200, Some(id.as_str())),
        "{t}"
    );
    // The cancelled jobs' attempts ended with them.
    let h = get_json(&c, &format!("{url}/v1/workers/{w}/tasks"));
    let outcomes: Vec<&str> = h["attempts"]
        .as_array()
        .expect("attempts")
        .iter()
        .map(|a| a["outcome"].as_str().unwrap_or(""))
        .collect();
    assert_eq!(outcomes, ["failed", "failed", "failed", "running"], "{h}");
}
