//! The web view's server side and `omis healthcheck`, against real `omis serve` processes on
//! 127.0.0.1: the page and its assets are served without a token while the API keeps wanting
//! one, a loopback server without tokens answers the API without one (so the page never asks),
//! workers list the tasks they hold, and the health check's exit status. (The page itself runs
//! in a browser in `.ci/browser-test`.)

mod common;

use common::service::{EXE, http, serve};
use serde_json::{Value, json};
use std::path::PathBuf;
use std::process::Command;

fn folder(name: &str) -> PathBuf {
    common::folder("web", name)
}

fn header(r: &reqwest::blocking::Response, name: &str) -> String {
    r.headers()
        .get(name)
        .and_then(|v| v.to_str().ok())
        .unwrap_or_default()
        .to_string()
}

#[test]
fn the_page_and_its_assets_need_no_token_and_the_api_still_does() {
    let dir = folder("page");
    let (_server, url) = serve(
        &dir.join("data"),
        &[
            "--client-token",
            "client-secret",
            "--worker-token",
            "worker-secret",
        ],
    );
    let c = http();

    let r = c.get(format!("{url}/")).send().expect("GET /");
    assert_eq!(r.status(), 200);
    assert!(header(&r, "content-type").starts_with("text/html"));
    let csp = header(&r, "content-security-policy");
    assert!(
        csp.contains("script-src 'self'") && csp.contains("img-src 'self' blob:"),
        "{csp}"
    );
    let html = r.text().expect("body");
    assert!(html.contains("/assets/app.js") && html.contains("/assets/app.css"));
    assert!(!html.contains("client-secret"));

    for (name, mime) in [
        ("app.js", "text/javascript"),
        ("app.css", "text/css"),
        ("favicon.svg", "image/svg+xml"),
    ] {
        let r = c
            .get(format!("{url}/assets/{name}"))
            .send()
            .expect("GET asset");
        assert_eq!(r.status(), 200, "{name}");
        assert!(header(&r, "content-type").starts_with(mime), "{name}");
        assert!(!r.bytes().expect("body").is_empty());
    }
    // Only the embedded files, and no way out of them.
    for bad in ["nope.js", "..%2FCargo.toml", "%2E%2E%2Fapi.rs"] {
        let r = c
            .get(format!("{url}/assets/{bad}"))
            .send()
            .expect("GET asset");
        assert_eq!(r.status(), 404, "{bad}");
        let v: Value = r.json().expect("JSON error");
        assert!(v["error"].is_string(), "{v}");
    }

    // The API: 401 without the token (the page asks for it then), 200 with it.
    let r = c.get(format!("{url}/v1/jobs")).send().expect("GET jobs");
    assert_eq!(r.status(), 401);
    let v: Value = r.json().expect("JSON");
    assert_eq!(v["field"], "Authorization");
    let r = c
        .get(format!("{url}/v1/jobs"))
        .bearer_auth("client-secret")
        .send()
        .expect("GET jobs");
    assert_eq!(r.status(), 200);
    // The page's event stream: fetch() with the header, not a token in the URL.
    let r = c
        .get(format!("{url}/v1/jobs/x/events?token=client-secret"))
        .send()
        .expect("GET events");
    assert_eq!(r.status(), 401);
}

#[test]
fn a_loopback_server_without_tokens_answers_the_api_without_one() {
    let dir = folder("open");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    for path in ["/v1/jobs", "/v1/workers", "/v1/scenes", "/"] {
        let r = c.get(format!("{url}{path}")).send().expect("GET");
        assert_eq!(r.status(), 200, "{path}");
    }
}

#[test]
fn workers_list_the_tasks_they_hold() {
    let dir = folder("held");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let v: Value = c
        .post(format!("{url}/v1/worker/register"))
        .json(&json!({ "name": "hand", "threads": 1 }))
        .send()
        .expect("register")
        .json()
        .expect("JSON");
    let worker = v["worker_id"].as_str().expect("id").to_string();
    let job: Value = c
        .post(format!("{url}/v1/jobs"))
        .json(&json!({
            "scene": { "library": "cornell-box" },
            "settings": { "resolution": [16, 16], "spp": 4, "pass_size": 4, "tile_size": 8 },
        }))
        .send()
        .expect("submit")
        .json()
        .expect("JSON");
    let lease: Value = c
        .post(format!("{url}/v1/worker/lease"))
        .json(&json!({ "worker_id": worker, "wait_s": 5 }))
        .send()
        .expect("lease")
        .json()
        .expect("JSON");
    let workers: Value = c
        .get(format!("{url}/v1/workers"))
        .send()
        .expect("workers")
        .json()
        .expect("JSON");
    let me = workers["workers"]
        .as_array()
        .expect("list")
        .iter()
        .find(|w| w["id"] == worker.as_str())
        .expect("the worker is listed");
    assert_eq!(me["state"], "busy");
    assert_eq!(
        me["tasks"],
        json!([{
            "id": lease["task"]["id"],
            "kind": "render",
            "job_id": job["id"],
            "pass": 0,
            "tile": lease["task"]["tile"],
            "attempt": lease["task"]["attempt"],
        }])
    );
    // Given back, the task is no longer the worker's.
    let r = c
        .post(format!("{url}/v1/worker/deregister"))
        .json(&json!({ "worker_id": worker }))
        .send()
        .expect("deregister");
    assert_eq!(r.status(), 200);
    let workers: Value = c
        .get(format!("{url}/v1/workers"))
        .send()
        .expect("workers")
        .json()
        .expect("JSON");
    assert_eq!(workers["workers"][0]["tasks"], json!([]));
}

#[test]
fn healthcheck_exits_0_for_a_live_coordinator_and_1_otherwise() {
    let dir = folder("health");
    let (server, url) = serve(
        &dir.join("data"),
        &[
            "--client-token",
            "client-secret",
            "--worker-token",
            "worker-secret",
        ],
    );
    // /healthz needs no token, so neither does the check.
    let out = Command::new(EXE)
        .args(["healthcheck", "--server", &url])
        .output()
        .expect("run healthcheck");
    assert!(out.status.success(), "{out:?}");
    assert!(String::from_utf8_lossy(&out.stdout).contains(": ok (omis "));
    let out = Command::new(EXE)
        .args(["healthcheck", "--quiet", "--server", &url])
        .output()
        .expect("run healthcheck");
    assert!(out.status.success() && out.stdout.is_empty(), "{out:?}");

    drop(server);
    let out = Command::new(EXE)
        .args(["healthcheck", "--timeout", "2", "--server", &url])
        .output()
        .expect("run healthcheck");
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    assert!(String::from_utf8_lossy(&out.stderr).contains("/healthz: no answer"));

    let out = Command::new(EXE)
        .args(["healthcheck", "--server", "https://127.0.0.1:1"])
        .output()
        .expect("run healthcheck");
    assert_eq!(out.status.code(), Some(1), "{out:?}");
}
