//! Bad jobs, tokens, routes and binds: 4xx JSON errors naming the problem, the server serving.

use crate::common::service::{EXE, http, serve, worker};
use crate::support::{WAIT, folder, settings};
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::process::Command;
use std::time::{Duration, Instant};

/// The coordinator of `bad_inputs_get_4xx_naming_the_problem_and_the_server_keeps_serving`, with
/// tokens for clients and workers, and its HTTP client.
struct Guarded {
    c: Client,
    url: String,
}

impl Guarded {
    /// `r` with the client token.
    fn auth(&self, r: reqwest::blocking::RequestBuilder) -> reqwest::blocking::RequestBuilder {
        r.bearer_auth("client-secret")
    }

    /// POSTs `body` as a job: the status and the JSON answer.
    fn send(&self, body: &str) -> (u16, Value) {
        let r = self
            .auth(self.c.post(format!("{}/v1/jobs", self.url)))
            .header("content-type", "application/json")
            .body(body.to_string())
            .send()
            .expect("POST");
        (r.status().as_u16(), r.json().unwrap_or(Value::Null))
    }
}

/// A good job, which must survive every bad input: its id.
fn submit_the_good_job(g: &Guarded) -> String {
    let good = g
        .auth(g.c.post(format!("{}/v1/jobs", g.url)))
        .json(&json!({ "scene": { "library": "cornell-box" }, "settings": settings(8) }))
        .send()
        .expect("POST");
    assert_eq!(good.status().as_u16(), 201);
    let good: Value = good.json().expect("JSON");
    good["id"].as_str().expect("id").to_string()
}

/// Malformed jobs, settings out of range, scenes and references that do not exist: 400 or
/// 422 naming the field and the problem.
fn bad_jobs_name_their_field(g: &Guarded) {
    let job = |settings: Value| {
        json!({ "scene": { "library": "cornell-box" }, "settings": settings }).to_string()
    };
    let cases: Vec<(String, u16, &str, &str)> = vec![
        ("{\"scene\": ".to_string(), 400, "body", "JSON"),
        (
            job(json!({ "spq": 4 })),
            422,
            "settings.spq",
            "unknown field",
        ),
        (
            job(json!({ "resolution": [0, 4] })),
            422,
            "settings.resolution",
            "0x4",
        ),
        (
            job(json!({ "resolution": [100000, 4] })),
            422,
            "settings.resolution",
            "100000",
        ),
        (job(json!({ "spp": -1 })), 422, "settings.spp", "-1"),
        (
            json!({ "scene": { "library": "../../etc/passwd" } }).to_string(),
            400,
            "scene.library",
            "not a scene name",
        ),
        (
            json!({ "scene": { "library": "no-such-scene" } }).to_string(),
            400,
            "scene.library",
            "no scene",
        ),
        (
            json!({ "scene": { "library": "cornell-box" }, "reference": { "upload": "nope" } })
                .to_string(),
            400,
            "reference.upload",
            "reference",
        ),
    ];
    for (body, status, field, needle) in &cases {
        let (s, v) = g.send(body);
        assert_eq!(s, *status, "{body} -> {v}");
        assert_eq!(v["field"].as_str(), Some(*field), "{body} -> {v}");
        assert!(
            v["error"].as_str().unwrap_or("").contains(needle),
            "{body} -> {v} should mention {needle}"
        );
    }
}

/// A reference that is not an EXR.
fn a_reference_that_is_not_an_exr_is_refused(g: &Guarded) {
    let r = g
        .auth(g.c.post(format!("{}/v1/references", g.url)))
        .body("P6 not an exr")
        .send()
        .expect("POST");
    assert_eq!(r.status().as_u16(), 400);
    let v: Value = r.json().expect("JSON");
    assert!(v["error"].as_str().unwrap_or("").contains("OpenEXR"), "{v}");
}

/// Missing and wrong tokens, for clients and for workers.
fn missing_and_wrong_tokens_are_refused(g: &Guarded) {
    let (c, url) = (&g.c, &g.url);
    let r = c.get(format!("{url}/v1/jobs")).send().expect("GET");
    assert_eq!(r.status().as_u16(), 401);
    let v: Value = r.json().expect("JSON");
    assert_eq!(v["field"], "Authorization");
    let r = c
        .post(format!("{url}/v1/worker/register"))
        .bearer_auth("client-secret")
        .json(&json!({ "name": "x", "threads": 1 }))
        .send()
        .expect("POST");
    assert_eq!(r.status().as_u16(), 401);
}

/// An unknown job, a wrong method, a result upload without its query: JSON errors too.
fn unknown_routes_methods_and_queries_get_json_errors(g: &Guarded) {
    let (c, url) = (&g.c, &g.url);
    let r = g
        .auth(c.get(format!("{url}/v1/jobs/nope")))
        .send()
        .expect("GET");
    assert_eq!(r.status().as_u16(), 404);
    let r = g
        .auth(c.delete(format!("{url}/v1/jobs")))
        .send()
        .expect("DELETE");
    assert_eq!(r.status().as_u16(), 405);
    let allow = r
        .headers()
        .get("allow")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    assert!(
        allow.contains("GET") && allow.contains("POST"),
        "Allow: {allow}"
    );
    let v: Value = r.json().expect("JSON");
    assert_eq!(v["field"], "method");
    let r = c
        .put(format!("{url}/v1/worker/tasks/1/result"))
        .bearer_auth("worker-secret")
        .body("x")
        .send()
        .expect("PUT");
    assert_eq!(r.status().as_u16(), 400);
    let v: Value = r.json().expect("JSON");
    assert_eq!(v["field"], "query", "{v}");
}

/// The server still serves, and the good job `id` is intact and finishes on a worker.
fn the_good_job_still_finishes(g: &Guarded, id: &str) {
    let (c, url) = (&g.c, &g.url);
    let ok = c.get(format!("{url}/healthz")).send().expect("healthz");
    assert!(ok.status().is_success());
    let _w = worker(url, "w", &["--worker-token", "worker-secret"]);
    let start = Instant::now();
    loop {
        let st: Value = g
            .auth(c.get(format!("{url}/v1/jobs/{id}")))
            .send()
            .expect("GET")
            .json()
            .expect("JSON");
        if st["state"] == "done" {
            break;
        }
        assert!(start.elapsed() < WAIT, "{st}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// One coordinator takes every kind of bad input in turn (each step a function above); its
/// process is killed when the test ends, also when a step fails.
#[test]
fn bad_inputs_get_4xx_naming_the_problem_and_the_server_keeps_serving() {
    let dir = folder("bad");
    let (_server, url) = serve(
        &dir.join("data"),
        &[
            "--client-token",
            "client-secret",
            "--worker-token",
            "worker-secret",
        ],
    );
    let g = Guarded { c: http(), url };
    let id = submit_the_good_job(&g);
    bad_jobs_name_their_field(&g);
    a_reference_that_is_not_an_exr_is_refused(&g);
    missing_and_wrong_tokens_are_refused(&g);
    unknown_routes_methods_and_queries_get_json_errors(&g);
    the_good_job_still_finishes(&g, &id);
}

#[test]
fn a_non_loopback_bind_without_tokens_is_refused() {
    let dir = folder("bind");
    let out = Command::new(EXE)
        .args(["serve", "--bind", "0.0.0.0:0", "--data"])
        .arg(dir.join("data"))
        .env_remove("OMIS_TOKEN")
        .env_remove("OMIS_CLIENT_TOKEN")
        .env_remove("OMIS_WORKER_TOKEN")
        .output()
        .expect("run");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("refusing to serve"), "{err}");
}
