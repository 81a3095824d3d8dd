//! Who may do what: per-user tokens (`omis serve --users`), jobs owned by their submitter, an
//! admin role that may act on every job, the single client token as the admin.

use crate::common::service::{EXE, http, serve};
use crate::support::{folder, settings};
use reqwest::blocking::Client;
use serde_json::{Value, json};
use sha2::{Digest, Sha256};
use std::process::Command;

/// Sends `req` with `token`; the status and the JSON answer (null if none).
fn call(req: reqwest::blocking::RequestBuilder, token: &str) -> (u16, Value) {
    let r = req.bearer_auth(token).send().expect("request");
    let s = r.status().as_u16();
    (s, r.json().unwrap_or(Value::Null))
}

/// Submits a job that stays queued (no worker runs) as the user of `token`; its id.
fn submit_as(c: &Client, url: &str, token: &str) -> String {
    let (s, v) = call(
        c.post(format!("{url}/v1/jobs")).json(&json!({
            "scene": { "library": "cornell-box" },
            "settings": settings(64),
        })),
        token,
    );
    assert_eq!(s, 201, "{v}");
    v["id"].as_str().expect("id").to_string()
}

fn cancel_as(c: &Client, url: &str, id: &str, token: &str) -> (u16, Value) {
    call(c.post(format!("{url}/v1/jobs/{id}/cancel")), token)
}

fn state_of(c: &Client, url: &str, id: &str, token: &str) -> Value {
    let (s, v) = call(c.get(format!("{url}/v1/jobs/{id}")), token);
    assert_eq!(s, 200, "{v}");
    v
}

#[test]
fn a_user_acts_on_its_own_jobs_only_and_an_admin_on_every_job() {
    let dir = folder("access-users");
    std::fs::create_dir_all(&dir).expect("folder");
    let cyd_hash: String = Sha256::digest(b"cyd-token-1")
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    let users = dir.join("users.json");
    std::fs::write(
        &users,
        json!([
            { "name": "ana", "role": "admin", "token": "ana-token-1" },
            { "name": "bob", "role": "user", "token": "bob-token-1" },
            { "name": "cyd", "role": "user", "token_sha256": cyd_hash },
        ])
        .to_string(),
    )
    .expect("users file");
    let users = users.to_str().expect("path").to_string();
    let (_server, url) = serve(
        &dir.join("data"),
        &["--users", &users, "--client-token", "root-token-1"],
    );
    let c = http();

    for (token, name, role) in [
        ("bob-token-1", "bob", "user"),
        ("cyd-token-1", "cyd", "user"),
        ("ana-token-1", "ana", "admin"),
        ("root-token-1", "admin", "admin"),
    ] {
        let (s, v) = call(c.get(format!("{url}/v1/whoami")), token);
        assert_eq!((s, &v), (200, &json!({ "name": name, "role": role })));
    }
    let (s, v) = call(c.get(format!("{url}/v1/whoami")), "nobody-token");
    assert_eq!(
        (s, v["field"].as_str()),
        (401, Some("Authorization")),
        "{v}"
    );

    let bobs = submit_as(&c, &url, "bob-token-1");
    let bobs_other = submit_as(&c, &url, "bob-token-1");
    let cyds = submit_as(&c, &url, "cyd-token-1");
    assert_eq!(state_of(&c, &url, &bobs, "cyd-token-1")["owner"], "bob");
    assert_eq!(state_of(&c, &url, &cyds, "bob-token-1")["owner"], "cyd");
    // Every user reads every job.
    let (s, list) = call(c.get(format!("{url}/v1/jobs")), "cyd-token-1");
    assert_eq!(s, 200);
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(3), "{list}");

    // Another user's job: 403 naming the job and its owner; the job is untouched.
    let (s, v) = cancel_as(&c, &url, &bobs, "cyd-token-1");
    assert_eq!(s, 403, "{v}");
    assert_eq!(v["field"], "id", "{v}");
    let msg = v["error"].as_str().expect("error");
    assert!(msg.contains(&bobs) && msg.contains("'bob'"), "{msg}");
    assert_eq!(state_of(&c, &url, &bobs, "bob-token-1")["state"], "queued");

    // Its own job: cancelled.
    let (s, v) = cancel_as(&c, &url, &bobs, "bob-token-1");
    assert_eq!((s, v["state"].as_str()), (200, Some("cancelled")), "{v}");
    // The admins may cancel anyone's: a user of role admin, and the single client token.
    let (s, v) = cancel_as(&c, &url, &cyds, "ana-token-1");
    assert_eq!((s, v["state"].as_str()), (200, Some("cancelled")), "{v}");
    let (s, v) = cancel_as(&c, &url, &bobs_other, "root-token-1");
    assert_eq!((s, v["state"].as_str()), (200, Some("cancelled")), "{v}");

    // A job the single token submitted is the admin's: a user may not touch it.
    let roots = submit_as(&c, &url, "root-token-1");
    assert_eq!(state_of(&c, &url, &roots, "bob-token-1")["owner"], "admin");
    let (s, _) = cancel_as(&c, &url, &roots, "bob-token-1");
    assert_eq!(s, 403);
    let (s, _) = cancel_as(&c, &url, &roots, "ana-token-1");
    assert_eq!(s, 200);

    // Every job control is the owner's or an admin's; every worker action an admin's.
    let cyds = submit_as(&c, &url, "cyd-token-1");
    let controls = [
        c.post(format!("{url}/v1/jobs/{cyds}/pause")),
        c.post(format!("{url}/v1/jobs/{cyds}/resume")),
        c.post(format!("{url}/v1/jobs/{cyds}/requeue")),
        c.post(format!("{url}/v1/jobs/{cyds}/retry")),
        c.patch(format!("{url}/v1/jobs/{cyds}"))
            .json(&json!({ "priority": 5 })),
        c.delete(format!("{url}/v1/jobs/{cyds}")),
        c.delete(format!("{url}/v1/jobs/{cyds}/blocklist/w1")),
    ];
    for req in controls {
        let (s, v) = call(req, "bob-token-1");
        assert_eq!((s, v["field"].as_str()), (403, Some("id")), "{v}");
    }
    assert_eq!(state_of(&c, &url, &cyds, "cyd-token-1")["priority"], 0);
    let (s, v) = call(
        c.patch(format!("{url}/v1/jobs/{cyds}"))
            .json(&json!({ "priority": 5 })),
        "cyd-token-1",
    );
    assert_eq!((s, v["priority"].as_i64()), (200, Some(5)), "{v}");
    let (s, v) = call(c.post(format!("{url}/v1/jobs/{cyds}/pause")), "ana-token-1");
    assert_eq!((s, v["state"].as_str()), (200, Some("paused")), "{v}");
    for action in ["disable", "enable", "drain"] {
        let (s, v) = call(
            c.post(format!("{url}/v1/workers/no-such-worker/{action}")),
            "bob-token-1",
        );
        assert_eq!(s, 403, "{action}: {v}");
        let (s, v) = call(
            c.post(format!("{url}/v1/workers/no-such-worker/{action}")),
            "ana-token-1",
        );
        assert_eq!(s, 404, "{action}: an admin gets as far as the worker: {v}");
    }
    let (s, _) = call(
        c.delete(format!("{url}/v1/workers/no-such-worker/unhealthy")),
        "bob-token-1",
    );
    assert_eq!(s, 403);
}

#[test]
fn a_bad_users_file_stops_serve_with_one_line_naming_entry_and_field() {
    let dir = folder("access-bad-users");
    std::fs::create_dir_all(&dir).expect("folder");
    for (text, want) in [
        (
            r#"[{"name": "ana", "role": "admin", "token": "ana-token-1"},
                {"name": "bob", "role": "user"}]"#,
            "entry 1 (\"bob\"): token",
        ),
        (
            r#"[{"name": "ana", "role": "owner", "token": "ana-token-1"}]"#,
            "[0].role",
        ),
        ("not json", "--users"),
    ] {
        let users = dir.join("users.json");
        std::fs::write(&users, text).expect("users file");
        let out = Command::new(EXE)
            .args(["serve", "--bind", "127.0.0.1:0", "--data"])
            .arg(dir.join("data"))
            .arg("--users")
            .arg(&users)
            .env_remove("OMIS_TOKEN")
            .env_remove("OMIS_CLIENT_TOKEN")
            .env_remove("OMIS_WORKER_TOKEN")
            .output()
            .expect("run omis serve");
        assert!(!out.status.success(), "{text}: serve started");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(err.trim().lines().count(), 1, "{text}: {err}");
        assert!(
            err.contains(want) && err.contains("--users"),
            "{text}: {err}"
        );
    }
}

#[test]
fn the_worker_refuses_the_old_ambiguous_token_flag_with_the_new_name() {
    let out = Command::new(EXE)
        .args([
            "worker",
            "--coordinator",
            "http://127.0.0.1:9",
            "--token",
            "secret",
        ])
        .output()
        .expect("run omis worker");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(err.contains("--worker-token"), "{err}");
}

#[test]
fn client_commands_take_the_client_token_by_its_new_name_and_the_old_one_with_a_warning() {
    let dir = folder("access-client-flags");
    let (_server, url) = serve(&dir.join("data"), &["--client-token", "client-token-1"]);
    let omis = |args: &[&str]| {
        Command::new(EXE)
            .args(args)
            .args(["--server", &url])
            .env("OMIS_LOG", "warn")
            .env_remove("OMIS_TOKEN")
            .env_remove("OMIS_CLIENT_TOKEN")
            .output()
            .expect("run omis")
    };
    let hook = "http://127.0.0.1:9/hook";
    let out = omis(&[
        "submit",
        "cornell-box",
        "--spp",
        "64",
        "--client-token",
        "client-token-1",
        "--webhook",
        hook,
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let st = state_of(&http(), &url, &id, "client-token-1");
    assert_eq!(
        (&st["owner"], &st["webhooks"]),
        (&json!("admin"), &json!([hook]))
    );

    let out = omis(&["status", &id, "--token", "client-token-1"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("deprecated") && err.contains("--client-token"),
        "{err}"
    );

    let out = omis(&["status", &id, "--client-token", "wrong-token"]);
    assert!(!out.status.success());
}
