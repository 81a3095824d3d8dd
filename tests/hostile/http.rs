//! HTTP against the contract: slow and idle connections, class caps, JSON bodies, bearer tokens.

use crate::common::service::{http, register, serve};
use crate::support::{folder, healthy, small_job};
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

/// Whether the server closed `s` (or cut it) by now; false while it is open and silent.
fn closed(s: &mut TcpStream) -> bool {
    let mut buf = [0u8; 4096];
    s.set_read_timeout(Some(Duration::from_millis(5)))
        .expect("timeout");
    loop {
        match s.read(&mut buf) {
            Ok(0) => return true,
            Ok(_) => continue, // an answer (400 for a slow body): read on to the close
            Err(e) => {
                return !matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                );
            }
        }
    }
}

#[test]
fn slow_and_idle_connections_are_closed_while_healthz_keeps_answering() {
    let dir = folder("slow");
    let (_server, url) = serve(
        &dir.join("data"),
        &[
            "--header-timeout",
            "1",
            "--body-grace",
            "1",
            "--body-min-rate",
            "1000",
            "--max-connections",
            "200",
            "--max-client-requests",
            "40",
            "--max-worker-requests",
            "40",
        ],
    );
    let addr = url.trim_start_matches("http://").to_string();
    let connect = || TcpStream::connect(&addr).expect("connect");
    let start = Instant::now();
    // Idle connections, more than the cap; slow headers; slow bodies (50 bytes/s).
    let mut idle: Vec<TcpStream> = (0..600).map(|_| connect()).collect();
    let mut slow_headers: Vec<TcpStream> = (0..20).map(|_| connect()).collect();
    let mut slow_bodies: Vec<TcpStream> = (0..20)
        .map(|_| {
            let mut s = connect();
            s.write_all(
                b"POST /v1/scenes HTTP/1.1\r\nhost: x\r\ncontent-type: application/x-tar\r\n\
                  content-length: 1000000\r\n\r\n",
            )
            .expect("head");
            s
        })
        .collect();
    let c = http();
    let mut worst = Duration::ZERO;
    let mut answered = 0;
    while start.elapsed() < Duration::from_secs(4) {
        for s in slow_headers.iter_mut() {
            let _ = s.write_all(b"X");
        }
        for s in slow_bodies.iter_mut() {
            let _ = s.write_all(&[0u8; 5]);
        }
        let t = Instant::now();
        let r = Client::builder()
            .timeout(Duration::from_secs(5))
            .pool_max_idle_per_host(0)
            .build()
            .expect("client")
            .get(format!("{url}/healthz"))
            .send()
            .expect("healthz under attack");
        assert_eq!(r.status().as_u16(), 200);
        worst = worst.max(t.elapsed());
        answered += 1;
        std::thread::sleep(Duration::from_millis(100));
    }
    eprintln!("/healthz: {answered} answers, the slowest in {worst:?}");
    assert!(worst < Duration::from_secs(1), "/healthz took {worst:?}");
    // By now (4 s, timeouts of 1 s) the server has closed every one of them.
    let open = |v: &mut Vec<TcpStream>| v.iter_mut().map(closed).filter(|c| !c).count();
    assert_eq!(open(&mut idle), 0, "idle connections still open");
    assert_eq!(
        open(&mut slow_headers),
        0,
        "slow-header connections still open"
    );
    assert_eq!(
        open(&mut slow_bodies),
        0,
        "slow-body connections still open"
    );
    let m = c
        .get(format!("{url}/metrics"))
        .send()
        .expect("metrics")
        .text()
        .expect("text");
    assert!(m.contains("omis_connections_max 200"), "{m}");
    healthy(&c, &url);
}

#[test]
fn json_bodies_are_json_whole_and_said_so() {
    let dir = folder("json");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let w = register(&c, &url, "w");
    let job = json!({"scene": {"library": "cornell-box"}, "settings": {"spp": 1}});
    let routes = [
        ("/v1/jobs", job.clone()),
        ("/v1/worker/register", json!({"name": "x", "threads": 1})),
        ("/v1/worker/lease", json!({"worker_id": w, "wait_s": 0})),
        ("/v1/worker/heartbeat", json!({"worker_id": w, "tasks": []})),
        (
            "/v1/worker/tasks/1/fail",
            json!({"worker_id": w, "attempt": 1, "error": "x"}),
        ),
        ("/v1/worker/deregister", json!({"worker_id": w})),
    ];
    for (route, body) in &routes {
        let send = |text: String, ct: Option<&str>| {
            let mut r = c.post(format!("{url}{route}")).body(text);
            if let Some(ct) = ct {
                r = r.header("content-type", ct);
            }
            let r = r.send().expect("POST");
            let s = r.status().as_u16();
            (s, r.json::<Value>().unwrap_or(Value::Null))
        };
        let (s, v) = send(format!("{body} xx"), Some("application/json"));
        assert_eq!(s, 400, "{route} with trailing bytes: {v}");
        assert_eq!(v["field"], "body", "{route}: {v}");
        let (s, v) = send(body.to_string(), Some("text/plain"));
        assert_eq!(s, 415, "{route} as text/plain: {v}");
        assert_eq!(v["field"], "Content-Type", "{route}: {v}");
        let (s, v) = send(body.to_string(), None);
        assert_eq!(s, 415, "{route} without Content-Type: {v}");
        // Whitespace after the value is JSON.
        let (s, v) = send(
            format!("{body} \n"),
            Some("application/json; charset=utf-8"),
        );
        assert!(
            s < 300 || s == 404,
            "{route} with trailing whitespace: {s} {v}"
        );
    }
}

#[test]
fn bearer_tokens_follow_the_contract() {
    let dir = folder("tokens");
    let (_server, url) = serve(
        &dir.join("data"),
        &["--client-token", "s3cret", "--worker-token", "w0rker"],
    );
    let c = http();
    let with = |auth: &str| {
        c.get(format!("{url}/v1/jobs"))
            .header("authorization", auth)
            .send()
            .expect("GET")
            .status()
            .as_u16()
    };
    // The scheme is case-insensitive (RFC 9110); the token is exact.
    assert_eq!(with("Bearer s3cret"), 200);
    assert_eq!(with("bearer s3cret"), 200);
    assert_eq!(with("BEARER s3cret"), 200);
    // (HTTP drops the whitespace around a header's value before anyone sees it.)
    assert_eq!(with("Bearer  s3cret"), 401);
    assert_eq!(with("Bearer s3cret s3cret"), 401);
    assert_eq!(with("Bearer w0rker"), 401);
    assert_eq!(with("Basic s3cret"), 401);
}

#[test]
fn requests_past_a_class_cap_get_503_while_health_and_workers_still_answer() {
    let dir = folder("admission");
    let (_server, url) = serve(&dir.join("data"), &["--max-client-requests", "2"]);
    let c = http();
    let job = small_job(&c, &url, 1);
    // Two event streams hold the client routes' two slots while they are open.
    let streams: Vec<_> = (0..2)
        .map(|_| {
            c.get(format!("{url}/v1/jobs/{job}/events"))
                .send()
                .expect("GET events")
        })
        .collect();
    assert!(streams.iter().all(|r| r.status().as_u16() == 200));
    let r = c.get(format!("{url}/v1/jobs")).send().expect("GET jobs");
    assert_eq!(r.status().as_u16(), 503);
    assert_eq!(
        r.headers().get("retry-after").and_then(|v| v.to_str().ok()),
        Some("1")
    );
    let v: Value = r.json().expect("json");
    assert!(
        v["error"]
            .as_str()
            .unwrap_or("")
            .contains("too many client requests"),
        "{v}"
    );
    healthy(&c, &url);
    register(&c, &url, "still-served");
    // A stream closed gives its slot back.
    drop(streams);
    let start = Instant::now();
    loop {
        let s = c.get(format!("{url}/v1/jobs")).send().expect("GET jobs");
        if s.status().as_u16() == 200 {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "no slot came back"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}
