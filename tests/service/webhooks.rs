//! Webhooks through the real service: a receiver on loopback (a thread here) gets each final
//! event once, signed; a receiver that answers 500 gets the delivery again; a delivery pending
//! when the coordinator is killed is made after its restart.

use crate::common::service::{get_json, http, post, serve, worker};
use crate::support::{WAIT, folder, settings, wait_state};
use hmac::{Hmac, Mac};
use serde_json::{Value, json};
use sha2::Sha256;
use std::collections::HashMap;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// One request a receiver got, and what it answered.
#[derive(Clone, Debug)]
struct Hit {
    headers: HashMap<String, String>,
    body: Vec<u8>,
    status: u16,
}

impl Hit {
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body).expect("a JSON body")
    }

    fn header(&self, name: &str) -> &str {
        self.headers.get(name).map_or("", String::as_str)
    }
}

/// How a receiver answers.
#[derive(Clone)]
enum Answer {
    /// 200 to everything.
    Ok,
    /// 500 to the first request of each delivery id, 200 to the next ones.
    FailFirst,
    /// 500 while the flag is false.
    FailUntil(Arc<AtomicBool>),
}

/// A webhook receiver: an HTTP/1.1 server on a loopback port, in a thread, that records every
/// request.
struct Receiver {
    url: String,
    hits: Arc<Mutex<Vec<Hit>>>,
}

impl Receiver {
    fn start(answer: Answer) -> Receiver {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind a loopback port");
        let url = format!("http://{}/hook", listener.local_addr().expect("address"));
        let hits: Arc<Mutex<Vec<Hit>>> = Arc::default();
        let recorded = hits.clone();
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(mut stream) = stream else { continue };
                let _ = stream.set_read_timeout(Some(Duration::from_secs(5)));
                let Some((headers, body)) = read_request(&mut stream) else {
                    continue;
                };
                let mut hits = recorded.lock().unwrap_or_else(|e| e.into_inner());
                let delivery = headers.get("x-omis-delivery").cloned().unwrap_or_default();
                let status = match &answer {
                    Answer::Ok => 200,
                    Answer::FailFirst => {
                        let seen = hits.iter().any(|h| h.header("x-omis-delivery") == delivery);
                        if seen { 200 } else { 500 }
                    }
                    Answer::FailUntil(ok) => {
                        if ok.load(Ordering::SeqCst) {
                            200
                        } else {
                            500
                        }
                    }
                };
                hits.push(Hit {
                    headers,
                    body,
                    status,
                });
                drop(hits);
                let _ = write!(
                    stream,
                    "HTTP/1.1 {status} X\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
                );
            }
        });
        Receiver { url, hits }
    }

    fn hits(&self) -> Vec<Hit> {
        self.hits.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Waits until `pred` holds of the requests so far.
    fn wait_for(&self, what: &str, pred: impl Fn(&[Hit]) -> bool) -> Vec<Hit> {
        let start = Instant::now();
        loop {
            let hits = self.hits();
            if pred(&hits) {
                return hits;
            }
            assert!(
                start.elapsed() < WAIT,
                "timed out waiting for {what}: {hits:?}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// Reads one request: its headers (names in lower case) and its body.
fn read_request(stream: &mut std::net::TcpStream) -> Option<(HashMap<String, String>, Vec<u8>)> {
    let mut reader = BufReader::new(stream);
    let mut line = String::new();
    reader.read_line(&mut line).ok()?;
    let mut headers = HashMap::new();
    loop {
        line.clear();
        reader.read_line(&mut line).ok()?;
        let l = line.trim_end();
        if l.is_empty() {
            break;
        }
        let (k, v) = l.split_once(':')?;
        headers.insert(k.trim().to_ascii_lowercase(), v.trim().to_string());
    }
    let len: usize = headers.get("content-length")?.parse().ok()?;
    let mut body = vec![0u8; len];
    reader.read_exact(&mut body).ok()?;
    Some((headers, body))
}

/// Whether `hit` carries `sha256=<hex HMAC-SHA256(secret, body)>`.
fn signed_with(hit: &Hit, secret: &str) -> bool {
    let mut mac = <Hmac<Sha256> as Mac>::new_from_slice(secret.as_bytes()).expect("key");
    mac.update(&hit.body);
    let hex: String = mac
        .finalize()
        .into_bytes()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    hit.header("x-omis-signature") == format!("sha256={hex}")
}

fn submit_with_hooks(c: &reqwest::blocking::Client, url: &str, spp: u32, hooks: Value) -> String {
    let (s, v) = post(
        c,
        &format!("{url}/v1/jobs"),
        &json!({
            "scene": { "library": "cornell-box" },
            "settings": settings(spp),
            "webhooks": hooks,
        }),
    );
    assert_eq!(s, 201, "{v}");
    v["id"].as_str().expect("id").to_string()
}

/// The job's deliveries once none is pending.
fn settled_deliveries(c: &reqwest::blocking::Client, url: &str, id: &str) -> Vec<Value> {
    let start = Instant::now();
    loop {
        let v = get_json(c, &format!("{url}/v1/jobs/{id}/webhooks"));
        let d = v["deliveries"].as_array().cloned().unwrap_or_default();
        if !d.is_empty() && d.iter().all(|d| d["state"] != "pending") {
            return d;
        }
        assert!(start.elapsed() < WAIT, "deliveries still pending: {v}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn each_final_event_reaches_each_receiver_once_signed_and_a_500_is_retried() {
    let dir = folder("webhooks");
    std::fs::create_dir_all(&dir).expect("folder");
    let global = Receiver::start(Answer::FailFirst);
    let own = Receiver::start(Answer::Ok);
    let secret_file = dir.join("webhook-secret");
    std::fs::write(&secret_file, "global-secret\n").expect("secret file");
    let (_server, url) = serve(
        &dir.join("data"),
        &[
            "--webhook",
            &global.url,
            "--webhook-secret-file",
            secret_file.to_str().expect("path"),
        ],
    );
    let c = http();

    // Bad receivers are refused, naming the field.
    for (hooks, field) in [
        (json!([{ "url": "ftp://127.0.0.1/x" }]), "webhooks[0].url"),
        (
            json!([{ "url": own.url, "secret": "" }]),
            "webhooks[0].secret",
        ),
        (json!([{ "url": own.url, "sekret": "x" }]), "webhooks[0]"),
    ] {
        let (s, v) = post(
            &c,
            &format!("{url}/v1/jobs"),
            &json!({ "scene": { "library": "cornell-box" }, "settings": settings(4),
                     "webhooks": hooks }),
        );
        assert!((400..500).contains(&s), "{hooks}: {s} {v}");
        assert!(
            v["field"].as_str().is_some_and(|f| f.starts_with(field)),
            "{hooks}: {v}"
        );
    }

    // A job that is cancelled while queued (no worker yet), and one that renders to its end.
    let cancelled = submit_with_hooks(&c, &url, 64, json!([]));
    let (s, v) = post(&c, &format!("{url}/v1/jobs/{cancelled}/cancel"), &json!({}));
    assert_eq!(s, 200, "{v}");
    let done = submit_with_hooks(
        &c,
        &url,
        4,
        json!([{ "url": own.url, "secret": "job-secret" }]),
    );
    let st = get_json(&c, &format!("{url}/v1/jobs/{done}"));
    assert_eq!(st["webhooks"], json!([own.url]), "{st}");
    assert!(
        !st.to_string().contains("job-secret"),
        "the secret is shown: {st}"
    );
    let _w = worker(&url, "w1", &[]);
    wait_state(&c, &url, &done, |s| s["state"] == "done");

    let d = settled_deliveries(&c, &url, &done);
    assert_eq!(d.len(), 2, "{d:?}");
    assert!(d.iter().all(|d| d["state"] == "delivered"), "{d:?}");
    let by_url = |u: &str| {
        d.iter()
            .find(|d| d["url"] == u)
            .expect("a delivery")
            .clone()
    };
    assert_eq!(by_url(&global.url)["attempts"], 2, "{d:?}");
    assert_eq!(by_url(&global.url)["last_status"], 200, "{d:?}");
    assert_eq!(by_url(&own.url)["attempts"], 1, "{d:?}");
    let d = settled_deliveries(&c, &url, &cancelled);
    assert_eq!(d.len(), 1, "{d:?}");
    assert_eq!(
        (&d[0]["event"], &d[0]["state"]),
        (&json!("cancelled"), &json!("delivered"))
    );

    // Nothing more arrives later: each event once (a retry repeats the same delivery).
    std::thread::sleep(Duration::from_secs(3));
    let own_hits = own.hits();
    assert_eq!(own_hits.len(), 1, "{own_hits:?}");
    let hit = &own_hits[0];
    assert!(signed_with(hit, "job-secret"), "{hit:?}");
    assert_eq!(hit.header("x-omis-event"), "done");
    assert_eq!(hit.header("content-type"), "application/json");
    let body = hit.json();
    assert_eq!(body["event"], "done");
    assert_eq!(body["delivery_id"], hit.header("x-omis-delivery"));
    assert_eq!(body["job"]["id"], done.as_str());
    assert_eq!(body["job"]["state"], "done");
    assert_eq!(body["job"]["spp_done"], 4);
    assert_eq!(body["job"]["owner"], "admin");
    assert_eq!(
        body["job"]["links"]["image"],
        format!("/v1/jobs/{done}/image.exr")
    );
    assert!(body["at"].as_f64().is_some_and(|t| t > 0.0), "{body}");

    let global_hits = global.hits();
    assert_eq!(
        global_hits.len(),
        4,
        "two deliveries, two attempts each: {global_hits:?}"
    );
    for job in [&done, &cancelled] {
        let of_job: Vec<&Hit> = global_hits
            .iter()
            .filter(|h| h.json()["job"]["id"] == job.as_str())
            .collect();
        assert_eq!(
            of_job.iter().map(|h| h.status).collect::<Vec<_>>(),
            [500, 200],
            "{of_job:?}"
        );
        // The retry is the same delivery: same id, same body, same signature.
        assert_eq!(
            of_job[0].header("x-omis-delivery"),
            of_job[1].header("x-omis-delivery")
        );
        assert_eq!(of_job[0].body, of_job[1].body);
        assert!(
            of_job.iter().all(|h| signed_with(h, "global-secret")),
            "{of_job:?}"
        );
    }
    let metrics = c
        .get(format!("{url}/metrics"))
        .send()
        .expect("metrics")
        .text()
        .expect("text");
    assert!(
        metrics.contains("omis_webhook_deliveries{state=\"delivered\"} 3"),
        "{metrics}"
    );
    let cancelled_hit = global_hits
        .iter()
        .find(|h| h.json()["job"]["id"] == cancelled.as_str())
        .expect("the cancelled job's delivery");
    assert_eq!(cancelled_hit.json()["event"], "cancelled");
    assert_eq!(cancelled_hit.header("x-omis-event"), "cancelled");
}

#[test]
fn a_delivery_pending_when_the_coordinator_is_killed_is_made_after_its_restart() {
    let dir = folder("webhooks-restart");
    let data = dir.join("data");
    let ok = Arc::new(AtomicBool::new(false));
    let receiver = Receiver::start(Answer::FailUntil(ok.clone()));
    let (mut server, url) = serve(&data, &[]);
    let c = http();
    let id = submit_with_hooks(&c, &url, 64, json!([{ "url": receiver.url }]));
    let (s, v) = post(&c, &format!("{url}/v1/jobs/{id}/cancel"), &json!({}));
    assert_eq!(s, 200, "{v}");
    let first = receiver.wait_for("a first attempt", |h| !h.is_empty());
    let delivery = first[0].header("x-omis-delivery").to_string();
    assert_eq!(first[0].status, 500);
    assert!(
        first[0].header("x-omis-signature").is_empty(),
        "no secret, no signature"
    );
    server.kill9();

    ok.store(true, Ordering::SeqCst);
    let (_server, url) = serve(&data, &[]);
    let hits = receiver.wait_for("a delivery after the restart", |h| {
        h.iter().any(|h| h.status == 200)
    });
    let delivered: Vec<&Hit> = hits.iter().filter(|h| h.status == 200).collect();
    assert_eq!(delivered.len(), 1, "{hits:?}");
    assert_eq!(delivered[0].header("x-omis-delivery"), delivery);
    assert_eq!(delivered[0].json()["job"]["state"], "cancelled");
    let d = settled_deliveries(&c, &url, &id);
    assert_eq!(d.len(), 1, "{d:?}");
    assert_eq!(d[0]["state"], "delivered", "{d:?}");
    assert_eq!(d[0]["id"], delivery.as_str());
}
