//! The farm controls through the real service: priorities (the lease order, changed while a job
//! runs), pause and resume, requeue and retry, delete (the disk it frees, measured), retention
//! under a tiny store budget, and the paged, filtered job list.

use crate::common::service::{get_json, http, post, register, serve, worker};
use crate::support::{
    WAIT, assert_equal, download_exr, folder, in_process, lease, settings, submit, wait_state,
};
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::path::Path;
use std::time::{Duration, Instant};

/// Submits a library job with `extra` fields besides scene and settings; its status.
fn submit_with(c: &Client, url: &str, settings: Value, extra: Value) -> Value {
    let mut body = json!({ "scene": { "library": "cornell-box" }, "settings": settings });
    if let (Some(b), Some(e)) = (body.as_object_mut(), extra.as_object()) {
        b.extend(e.clone());
    }
    let (s, v) = post(c, &format!("{url}/v1/jobs"), &body);
    assert_eq!(s, 201, "{v}");
    v
}

/// The job of a lease.
fn job_of(lease: &Value) -> String {
    lease["task"]["job_id"]
        .as_str()
        .expect("job_id")
        .to_string()
}

/// POST /v1/jobs/{id}/{action}: status and answer.
fn control(c: &Client, url: &str, id: &str, action: &str) -> (u16, Value) {
    let r = c
        .post(format!("{url}/v1/jobs/{id}/{action}"))
        .send()
        .expect("POST");
    let s = r.status().as_u16();
    (s, r.json().unwrap_or(Value::Null))
}

/// Bytes of the files under `dir` that jobs store: the database (which keeps its pages) and the
/// spare result logs (a bounded pool kept for reuse by the next job) left out.
fn job_bytes(dir: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| {
            let name = e.file_name().to_string_lossy().to_string();
            if name.starts_with("omis.sqlite") || name == "spare-logs" {
                0
            } else if e.path().is_dir() {
                job_bytes(&e.path())
            } else {
                e.metadata().map_or(0, |m| m.len())
            }
        })
        .sum()
}

/// Whether any worker holds a task of job `id`.
fn held_by_workers(c: &Client, url: &str, id: &str) -> bool {
    let w = get_json(c, &format!("{url}/v1/workers"));
    w["workers"]
        .as_array()
        .into_iter()
        .flatten()
        .flat_map(|w| w["tasks"].as_array().into_iter().flatten())
        .any(|t| t["job_id"] == id)
}

#[test]
fn a_priority_job_overtakes_a_long_one_and_a_priority_changes_while_queued() {
    let dir = folder("priority");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    // The long job: 6 tiles a pass, 16 passes. Two workers take its first tiles.
    let long = submit(&c, &url, 64);
    let (a, b) = (register(&c, &url, "a"), register(&c, &url, "b"));
    assert_eq!(job_of(&lease(&c, &url, &a)), long);
    assert_eq!(job_of(&lease(&c, &url, &b)), long);
    // A job submitted later with a higher priority gets the next free workers (once its tasks
    // exist: both jobs' first two passes, 6 tiles each, two of them leased).
    let urgent = submit_with(
        &c,
        &url,
        settings(8),
        json!({ "priority": 5, "name": "urgent" }),
    );
    assert_eq!(urgent["priority"], 5);
    let urgent = urgent["id"].as_str().expect("id").to_string();
    let start = Instant::now();
    loop {
        let m = c
            .get(format!("{url}/metrics"))
            .send()
            .and_then(|r| r.text())
            .expect("metrics");
        if m.contains("omis_tasks{state=\"queued\"} 22") {
            break;
        }
        assert!(start.elapsed() < WAIT, "the tasks were never made: {m}");
        std::thread::sleep(Duration::from_millis(50));
    }
    for w in [&a, &b, &a] {
        assert_eq!(
            job_of(&lease(&c, &url, w)),
            urgent,
            "the priority job first"
        );
    }
    // Raised above it while running, the long job comes first again.
    let r = c
        .patch(format!("{url}/v1/jobs/{long}"))
        .json(&json!({ "priority": 9 }))
        .send()
        .expect("PATCH");
    assert_eq!(r.status().as_u16(), 200);
    let st: Value = r.json().expect("status");
    assert_eq!(st["priority"], 9);
    assert_eq!(job_of(&lease(&c, &url, &b)), long);
    // A bad patch names its field; an ended job's priority cannot change.
    let r = c
        .patch(format!("{url}/v1/jobs/{long}"))
        .json(&json!({ "priority": "high" }))
        .send()
        .expect("PATCH");
    assert_eq!(r.status().as_u16(), 422);
    let v: Value = r.json().expect("error");
    assert_eq!(v["field"], "priority", "{v}");
    assert_eq!(control(&c, &url, &long, "cancel").0, 200);
    let r = c
        .patch(format!("{url}/v1/jobs/{long}"))
        .json(&json!({ "priority": 1 }))
        .send()
        .expect("PATCH");
    assert_eq!(r.status().as_u16(), 409);
}

#[test]
fn a_paused_job_leases_nothing_and_resumes_to_the_same_bits() {
    let dir = folder("pause");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let _w1 = worker(&url, "w1", &[]);
    let _w2 = worker(&url, "w2", &[]);
    let c = http();
    let id = submit(&c, &url, 32);
    let (s, st) = control(&c, &url, &id, "pause");
    assert_eq!(s, 200, "{st}");
    assert_eq!(st["state"], "paused");
    assert!(st["eta_s"].is_null(), "{st}");
    assert_eq!(control(&c, &url, &id, "pause").0, 409, "already paused");
    // The tasks in hand finish; then nothing is leased, and nothing changes, for a while.
    let start = Instant::now();
    while held_by_workers(&c, &url, &id) {
        assert!(start.elapsed() < WAIT, "tasks in hand never finished");
        std::thread::sleep(Duration::from_millis(50));
    }
    let frozen = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    let progress = |s: &Value| (s["passes_done"].clone(), s["tiles_done"].clone());
    let watch = Instant::now();
    while watch.elapsed() < Duration::from_secs(3) {
        assert!(
            !held_by_workers(&c, &url, &id),
            "a paused job's task was leased"
        );
        let now = get_json(&c, &format!("{url}/v1/jobs/{id}"));
        assert_eq!(now["state"], "paused");
        assert_eq!(progress(&now), progress(&frozen), "a paused job progressed");
        std::thread::sleep(Duration::from_millis(100));
    }
    let (s, st) = control(&c, &url, &id, "resume");
    assert_eq!(s, 200, "{st}");
    assert!(
        matches!(st["state"].as_str(), Some("queued" | "running")),
        "{st}"
    );
    assert!(st["paused_s"].as_f64().unwrap_or(0.0) >= 3.0, "{st}");
    assert_eq!(control(&c, &url, &id, "resume").0, 409, "not paused");
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 32);
    // Bit for bit the uninterrupted render.
    let img = download_exr(&c, &url, &id, &dir);
    let want = in_process(32);
    assert_equal(&img, &want);
    assert!(img.pixels == want.pixels, "not bit-identical");
}

#[test]
fn a_failed_job_requeued_finishes_and_a_cancelled_one_retries_as_a_new_job() {
    let dir = folder("requeue");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let id = submit_with(
        &c,
        &url,
        settings(8),
        json!({ "name": "flaky", "priority": 2 }),
    )["id"]
        .as_str()
        .expect("id")
        .to_string();
    assert_eq!(control(&c, &url, &id, "requeue").0, 409, "not failed");
    assert_eq!(control(&c, &url, &id, "retry").0, 409, "not ended");
    // Three workers fail the same task (a full disk, say): the job fails.
    let mut bad = Vec::new();
    for k in 0..3 {
        let w = register(&c, &url, &format!("bad{k}"));
        let t = lease(&c, &url, &w);
        let (s, v) = post(
            &c,
            &format!("{url}/v1/worker/tasks/{}/fail", t["task"]["id"]),
            &json!({ "worker_id": w, "attempt": t["task"]["attempt"], "error": "disk full" }),
        );
        assert_eq!(s, 200, "{v}");
        bad.push(w);
    }
    let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    assert_eq!(st["state"], "failed", "{st}");
    // After the fix: requeued, its error cleared, and a worker that failed it may take it again.
    let (s, st) = control(&c, &url, &id, "requeue");
    assert_eq!(s, 200, "{st}");
    assert!(st["error"].is_null(), "{st}");
    assert!(
        matches!(st["state"].as_str(), Some("queued" | "running")),
        "{st}"
    );
    let again = lease(&c, &url, &bad[0]);
    assert_eq!(job_of(&again), id);
    for w in &bad {
        let (s, _) = post(
            &c,
            &format!("{url}/v1/worker/deregister"),
            &json!({ "worker_id": w }),
        );
        assert_eq!(s, 200);
    }
    let _w = worker(&url, "good", &[]);
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 8);
    assert_equal(&download_exr(&c, &url, &id, &dir), &in_process(8));
    assert_eq!(control(&c, &url, &id, "retry").0, 409, "done: not retried");
    // A cancelled job retried: a new job with the same request, naming the old one.
    let old = submit_with(
        &c,
        &url,
        settings(8),
        json!({ "name": "again", "priority": 3 }),
    );
    let old = old["id"].as_str().expect("id").to_string();
    assert_eq!(control(&c, &url, &old, "cancel").0, 200);
    let (s, new) = control(&c, &url, &old, "retry");
    assert_eq!(s, 201, "{new}");
    assert_ne!(new["id"], old.as_str());
    assert_eq!(new["retry_of"], old.as_str());
    assert_eq!(
        (new["name"].clone(), new["priority"].clone()),
        (json!("again"), json!(3))
    );
    let new_id = new["id"].as_str().expect("id");
    let st = wait_state(&c, &url, new_id, |s| s["state"] == "done");
    assert_equal(&download_exr(&c, &url, new_id, &dir), &in_process(8));
    assert_eq!(
        st["settings"],
        get_json(&c, &format!("{url}/v1/jobs/{old}"))["settings"]
    );
}

#[test]
fn deleting_a_job_frees_the_disk_it_used_and_only_an_ended_job_is_deleted() {
    let dir = folder("delete");
    let data = dir.join("data");
    let (_server, url) = serve(&data, &[]);
    let c = http();
    let before = job_bytes(&data);
    let id = submit(&c, &url, 16);
    let r = c
        .delete(format!("{url}/v1/jobs/{id}"))
        .send()
        .expect("DELETE");
    assert_eq!(r.status().as_u16(), 409, "an active job is not deleted");
    let v: Value = r.json().expect("error");
    assert_eq!(v["field"], "id");
    let _w = worker(&url, "w", &[]);
    wait_state(&c, &url, &id, |s| s["state"] == "done");
    let done = job_bytes(&data);
    assert!(done > before, "the job stored nothing? {before} -> {done}");
    // A job whose reference is its image keeps it until that job is deleted.
    let user = submit_with(&c, &url, settings(4), json!({ "reference": { "job": id } }));
    let user = user["id"].as_str().expect("id").to_string();
    wait_state(&c, &url, &user, |s| s["state"] == "done");
    let delete = |job: &str| {
        c.delete(format!("{url}/v1/jobs/{job}"))
            .send()
            .expect("DELETE")
    };
    let r = delete(&id);
    assert_eq!(r.status().as_u16(), 409);
    let v: Value = r.json().expect("error");
    assert!(v["error"].as_str().unwrap_or("").contains(&user), "{v}");
    assert_eq!(delete(&user).status().as_u16(), 204);
    assert_eq!(delete(&id).status().as_u16(), 204);
    let after = job_bytes(&data);
    assert_eq!(
        after, before,
        "bytes before {before}, done {done}, after delete {after}"
    );
    let r = c.get(format!("{url}/v1/jobs/{id}")).send().expect("GET");
    assert_eq!(r.status().as_u16(), 404);
    let r = c
        .delete(format!("{url}/v1/jobs/{id}"))
        .send()
        .expect("DELETE");
    assert_eq!(r.status().as_u16(), 404);
}

#[test]
fn retention_deletes_finished_jobs_over_the_store_budget_and_keeps_active_ones() {
    let dir = folder("retention");
    let (_server, url) = serve(
        &dir.join("data"),
        &["--store-budget", "1", "--sweep-interval", "0.5"],
    );
    let c = http();
    let kept = submit(&c, &url, 16);
    assert_eq!(control(&c, &url, &kept, "pause").0, 200);
    let _w = worker(&url, "w", &[]);
    let done = submit(&c, &url, 8);
    let start = Instant::now();
    loop {
        let r = c.get(format!("{url}/v1/jobs/{done}")).send().expect("GET");
        if r.status().as_u16() == 404 {
            break;
        }
        let st: Value = r.json().expect("status");
        assert!(
            matches!(st["state"].as_str(), Some("queued" | "running" | "done")),
            "{st}"
        );
        assert!(
            start.elapsed() < WAIT,
            "the finished job was never swept: {st}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    // The paused job (active) stays, whatever the budget.
    let st = get_json(&c, &format!("{url}/v1/jobs/{kept}"));
    assert_eq!(st["state"], "paused");
}

#[test]
fn the_job_list_pages_and_filters_and_names_a_bad_query_field() {
    let dir = folder("list");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let mut ids = Vec::new();
    for k in 0..5 {
        let v = submit_with(
            &c,
            &url,
            settings(64),
            json!({ "name": format!("shot-{k}") }),
        );
        ids.push(v["id"].as_str().expect("id").to_string());
    }
    assert_eq!(control(&c, &url, &ids[1], "cancel").0, 200);
    assert_eq!(control(&c, &url, &ids[3], "pause").0, 200);
    // Pages of two, oldest first, following `next`.
    let mut seen = Vec::new();
    let mut after: Option<String> = None;
    loop {
        let mut u = format!("{url}/v1/jobs?limit=2");
        if let Some(a) = &after {
            u.push_str(&format!("&after={a}"));
        }
        let page = get_json(&c, &u);
        let jobs = page["jobs"].as_array().expect("jobs");
        assert!(jobs.len() <= 2);
        seen.extend(
            jobs.iter()
                .map(|j| j["id"].as_str().expect("id").to_string()),
        );
        match page["next"].as_str() {
            Some(n) => after = Some(n.to_string()),
            None => break,
        }
    }
    assert_eq!(seen, ids);
    let ids_of = |q: &str| -> Vec<String> {
        get_json(&c, &format!("{url}/v1/jobs?{q}"))["jobs"]
            .as_array()
            .expect("jobs")
            .iter()
            .map(|j| j["id"].as_str().expect("id").to_string())
            .collect()
    };
    assert_eq!(
        ids_of("state=cancelled,paused"),
        [ids[1].clone(), ids[3].clone()]
    );
    assert_eq!(ids_of("name=SHOT-4"), [ids[4].clone()]);
    assert_eq!(ids_of("since=4000000000"), Vec::<String>::new());
    assert_eq!(
        ids_of("since=0&limit=100000").len(),
        5,
        "limit capped, not refused"
    );
    assert_eq!(
        get_json(&c, &format!("{url}/v1/jobs"))["jobs"]
            .as_array()
            .map(Vec::len),
        Some(5)
    );
    for (q, field) in [
        ("state=finished", "state"),
        ("since=yesterday", "since"),
        ("limit=0", "limit"),
        ("after=x", "after"),
    ] {
        let r = c.get(format!("{url}/v1/jobs?{q}")).send().expect("GET");
        assert_eq!(r.status().as_u16(), 400, "{q}");
        let v: Value = r.json().expect("error");
        assert_eq!(v["field"], field, "{q}: {v}");
    }
}

#[test]
fn time_paused_does_not_count_against_a_time_budget() {
    let dir = folder("pause-budget");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let _w = worker(&url, "w", &[]);
    let c = http();
    let v = submit_with(
        &c,
        &url,
        json!({ "resolution": [40, 32], "time_budget_s": 2.0, "pass_size": 4, "max_pass_size": 4 }),
        json!({}),
    );
    let id = v["id"].as_str().expect("id").to_string();
    wait_state(&c, &url, &id, |s| s["state"] == "running");
    assert_eq!(control(&c, &url, &id, "pause").0, 200);
    // Paused for longer than the whole budget.
    std::thread::sleep(Duration::from_millis(3000));
    let (s, st) = control(&c, &url, &id, "resume");
    assert_eq!(s, 200, "{st}");
    let resumed = st["spp_done"].as_u64().expect("spp");
    let resumed_at = Instant::now();
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    // Had the pause counted, the budget would be spent and the job would end at once; it
    // renders on for the rest of its budget instead.
    assert!(
        resumed_at.elapsed() >= Duration::from_millis(1000),
        "ended {:?} after the resume: {st}",
        resumed_at.elapsed()
    );
    assert!(st["spp_done"].as_u64().expect("spp") > resumed, "{st}");
    let (elapsed, paused) = (
        st["elapsed_s"].as_f64().expect("elapsed"),
        st["paused_s"].as_f64().expect("paused"),
    );
    assert!(paused >= 2.9, "{st}");
    assert!(elapsed < 3.5, "the time paused counted as rendering: {st}");
}

#[test]
fn the_cli_lists_summarises_and_controls_jobs_by_id_prefix() {
    let dir = folder("cli-controls");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let omis = |args: &[&str]| {
        let out = std::process::Command::new(crate::common::service::EXE)
            .args(args)
            .args(["--server", &url])
            .env("OMIS_LOG", "warn")
            .output()
            .expect("run omis");
        let text = |b: &[u8]| String::from_utf8_lossy(b).trim().to_string();
        (out.status.success(), text(&out.stdout), text(&out.stderr))
    };
    // Jobs until two ids share their first character (an ambiguous prefix).
    let mut ids: Vec<String> = Vec::new();
    let shared = loop {
        let v = submit_with(
            &c,
            &url,
            settings(64),
            json!({ "name": format!("shot-{}", ids.len()) }),
        );
        let id = v["id"].as_str().expect("id").to_string();
        let first = &id[..1];
        if ids.iter().any(|o| o.starts_with(first)) {
            ids.push(id.clone());
            break first.to_string();
        }
        ids.push(id);
    };
    let unique = |id: &str| -> String {
        (1..=id.len())
            .map(|k| id[..k].to_string())
            .find(|p| ids.iter().filter(|o| o.starts_with(p.as_str())).count() == 1)
            .expect("a unique prefix")
    };
    let a = ids[0].clone();
    let (ok, out, err) = omis(&["pause", &unique(&a)]);
    assert!(ok, "{err}");
    assert_eq!(out, "paused");
    let (ok, out, err) = omis(&["priority", &unique(&a), "-3"]);
    assert!(ok, "{err}");
    assert_eq!(out, "-3");
    assert_eq!(get_json(&c, &format!("{url}/v1/jobs/{a}"))["priority"], -3);
    // An ambiguous or unknown prefix is a one-line error naming the problem.
    let (ok, _, err) = omis(&["resume", &shared]);
    assert!(!ok);
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(err.contains("ambiguous"), "{err}");
    let (ok, _, err) = omis(&["resume", "zzzz"]);
    assert!(!ok && err.contains("no job"), "{err}");
    // The table, filtered; the farm summary; one job, readable and raw.
    let (ok, out, err) = omis(&["jobs", "--state", "paused"]);
    assert!(ok, "{err}");
    assert!(out.starts_with("ID"), "{out}");
    assert_eq!(out.lines().count(), 2, "{out}");
    assert!(
        out.contains(&a[..8]) && out.contains("shot-0") && out.contains("paused"),
        "{out}"
    );
    let (ok, out, err) = omis(&["status"]);
    assert!(ok, "{err}");
    assert!(out.contains(&format!("jobs      {}", ids.len())), "{out}");
    assert!(out.contains("1 paused") && out.contains("queue"), "{out}");
    let (ok, out, err) = omis(&["status", &unique(&a)]);
    assert!(ok, "{err}");
    assert!(
        out.contains("paused") && out.contains("priority   -3"),
        "{out}"
    );
    let (ok, out, err) = omis(&["status", &unique(&a), "--json"]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(&out).expect("JSON");
    assert_eq!(v["id"], a.as_str());
    let (ok, out, err) = omis(&["status", "--json"]);
    assert!(ok, "{err}");
    let v: Value = serde_json::from_str(&out).expect("JSON");
    assert_eq!(v["jobs"]["paused"], 1, "{v}");
    // Resume, cancel, retry as a new job, delete.
    let (ok, out, err) = omis(&["resume", &unique(&a)]);
    assert!(ok && out == "queued", "{out} {err}");
    assert_eq!(control(&c, &url, &a, "cancel").0, 200);
    let (ok, out, err) = omis(&["retry", &unique(&a)]);
    assert!(ok, "{err}");
    let again = get_json(&c, &format!("{url}/v1/jobs/{out}"));
    assert_eq!(again["retry_of"], a.as_str());
    let (ok, out, err) = omis(&["delete", &a]);
    assert!(ok, "{err}");
    assert_eq!(out, format!("deleted {a}"));
    let (ok, _, err) = omis(&["delete", &a]);
    assert!(
        !ok && err.lines().count() == 1 && err.contains("no job"),
        "{err}"
    );
}
