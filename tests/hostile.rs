//! Hostile input and faults against a real coordinator on 127.0.0.1: deep and extreme scene
//! files, slow and idle connections, uploads that claim more than they weigh, tasks that kill or
//! fail on their workers, a damaged database, a full disk, references full of NaN, and bodies
//! and tokens that bend the contract. Each ends with a clear error, the coordinator serving, and
//! nothing it had accepted lost.

mod common;

use common::service::{
    EXE, Proc, get_json, http, peak_rss, post, register, serve, serve_command, try_lease,
};
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn folder(name: &str) -> PathBuf {
    common::folder("hostile", name)
}

/// A tar archive of `files` (path, contents).
fn tar_of(files: &[(&str, &[u8])]) -> Vec<u8> {
    let mut tar = tar::Builder::new(Vec::new());
    for (name, data) in files {
        let mut h = tar::Header::new_gnu();
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        h.set_cksum();
        tar.append_data(&mut h, name, *data).expect("tar entry");
    }
    tar.into_inner().expect("tar")
}

/// POST /v1/scenes with `tar`; the status and the JSON answer.
fn upload_bundle(c: &Client, url: &str, tar: Vec<u8>) -> (u16, Value) {
    let r = c
        .post(format!("{url}/v1/scenes"))
        .header("content-type", "application/x-tar")
        .body(tar)
        .send()
        .expect("POST /v1/scenes");
    let s = r.status().as_u16();
    (s, r.json().unwrap_or(Value::Null))
}

/// `/healthz` answers 200.
fn healthy(c: &Client, url: &str) {
    let r = c.get(format!("{url}/healthz")).send().expect("healthz");
    assert_eq!(r.status().as_u16(), 200);
}

/// A small JSON scene: a furnace-like sphere seen from inside, with `shapes` added.
fn json_scene(extra_shapes: Value) -> Value {
    let mut shapes = vec![json!({
        "type": "sphere", "center": [0, 0, 0], "radius": 1, "inward": true,
        "material": "grey", "emission": 1
    })];
    if let Value::Array(a) = extra_shapes {
        shapes.extend(a);
    }
    json!({
        "camera": {"position": [0, 0, 0], "look_at": [0, 0, 1], "fov": 60, "resolution": [16, 16]},
        "materials": {"grey": {"type": "lambert", "albedo": 0.5}},
        "shapes": shapes
    })
}

/// A Mitsuba 0.5 scene with `inner` inside its one shape.
fn mitsuba(version: &str, inner: &str) -> String {
    format!(
        r#"<?xml version="1.0"?>
<scene version="{version}">
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="toWorld"><lookat origin="0,0,5" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
  </sensor>
  <shape type="sphere">
    <float name="radius" value="1"/>
    <emitter type="area"><spectrum name="radiance" value="1"/></emitter>
    {inner}
  </shape>
</scene>
"#
    )
}

/// A Mitsuba 3 scene lit by a sun-and-sky model, which it cannot be rendered without.
fn mitsuba3_with_environment() -> String {
    r#"<scene version="3.0.0">
    <sensor type="perspective"><float name="fov" value="45"/>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
    <emitter type="sunsky"/>
    <shape type="sphere"/>
</scene>
"#
    .to_string()
}

/// A scene nested `depth` elements deep inside its shape.
fn nested_mitsuba(depth: usize) -> String {
    mitsuba(
        "0.5.0",
        &format!(
            "{}{}",
            "<bsdf type=\"twosided\">".repeat(depth),
            "</bsdf>".repeat(depth)
        ),
    )
}

/// The hostile scene files of the campaign: each is refused with 400 naming its problem.
fn hostile_scenes() -> Vec<(&'static str, String, Vec<u8>)> {
    let extreme = json_scene(json!([{
        "type": "triangles", "positions": [[0, 0, 2], [1e30, 0, 2], [0, 1, 2]],
        "indices": [[0, 1, 2]], "material": "grey"
    }]));
    let json_deep = format!(
        "{{\"camera\": {{\"position\": [0, 0, 0], \"look_at\": [0, 0, 1], \"fov\": 60, \
         \"resolution\": [8, 8]}}, \"materials\": {{\"m\": {}1{}}}}}",
        "{\"a\": ".repeat(100_000),
        "}".repeat(100_000)
    );
    let v4 = "Film \"rgb\" \"integer xresolution\" 16\nCamera \"perspective\"\nWorldBegin\n\
              Material \"interface\"\nShape \"curve\"\n";
    vec![
        (
            "deep.xml",
            nested_mitsuba(7000),
            b"nested more than 128 elements deep".to_vec(),
        ),
        (
            "deep.json",
            json_deep,
            b"materials.m.type: missing \"type\"".to_vec(),
        ),
        (
            "loop.pbrt",
            "Include \"loop.pbrt\"\n".to_string(),
            b"Include nested deeper than".to_vec(),
        ),
        (
            "extreme.json",
            extreme.to_string(),
            b"beyond the largest world coordinate".to_vec(),
        ),
        (
            "mitsuba3.xml",
            mitsuba3_with_environment(),
            b"cannot be rendered as the file means it (1 reason): line 4: emitter \"sunsky\""
                .to_vec(),
        ),
        (
            "v4.pbrt",
            v4.to_string(),
            b"(2 reasons): line 4: material \"interface\": no surface (a medium boundary) is not supported; line 5: Shape \"curve\" is not supported"
                .to_vec(),
        ),
    ]
}

#[test]
fn hostile_scene_files_get_400_naming_the_problem_and_the_coordinator_keeps_serving() {
    let dir = folder("scenes");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    for (name, text, want) in hostile_scenes() {
        let (s, v) = upload_bundle(&c, &url, tar_of(&[(name, text.as_bytes())]));
        let want = String::from_utf8(want).expect("utf-8");
        assert_eq!(s, 400, "{name}: {v}");
        let msg = v["error"].as_str().unwrap_or("");
        assert!(msg.contains(&want), "{name}: '{msg}' should say '{want}'");
        assert!(msg.contains(name), "{name}: '{msg}' should name the file");
        assert!(!msg.contains(&*dir.to_string_lossy()), "{name}: '{msg}'");
        healthy(&c, &url);
    }
    // The JSON ones inline, too.
    let extreme = json_scene(json!([{
        "type": "triangles", "positions": [[0, 0, 2], [0, -3e20, 2], [0, 1, 2]],
        "indices": [[0, 1, 2]], "material": "grey"
    }]));
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({"scene": {"inline": extreme}, "settings": {"spp": 1}}),
    );
    assert_eq!(s, 400, "{v}");
    assert_eq!(v["field"], "scene.inline", "{v}");
    assert!(
        v["error"].as_str().unwrap_or("").contains("shapes[1]"),
        "{v}"
    );
    // Nothing of the refused uploads stays on disk.
    let left = std::fs::read_dir(dir.join("data/scenes"))
        .map(|d| d.count())
        .unwrap_or(0);
    assert_eq!(left, 0, "refused bundles left on disk");
    healthy(&c, &url);
}

#[test]
fn hostile_scene_files_make_omis_render_exit_with_one_line() {
    let dir = folder("render");
    for (name, text, want) in hostile_scenes() {
        let path = dir.join(name);
        std::fs::write(&path, &text).expect("write scene");
        let out = Command::new(EXE)
            .args(["render", "--in-process", "--spp", "1"])
            .arg(&path)
            .arg("--out")
            .arg(dir.join("out.exr"))
            .output()
            .expect("run omis");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{name}: {err}");
        let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
        assert_eq!(lines.len(), 1, "{name}: one line expected, got {err}");
        let want = String::from_utf8(want).expect("utf-8");
        assert!(lines[0].contains(&want), "{name}: {err}");
    }
}

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

/// A ZIP-compressed `w` x `h` EXR of constant `v`, written without holding its pixels.
fn constant_exr(path: &Path, w: usize, h: usize, v: f32) {
    use exr::prelude::*;
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        Encoding {
            compression: Compression::ZIP16,
            ..Encoding::FAST_LOSSLESS
        },
        SpecificChannels::rgb(|_: Vec2<usize>| (v, v, v)),
    );
    Image::from_layer(layer)
        .write()
        .to_file(path)
        .expect("write EXR");
}

/// A JSON scene whose one mesh has `n` x `n` quads, written inline.
fn big_inline_scene(n: usize) -> Value {
    let mut positions = Vec::with_capacity((n + 1) * (n + 1));
    for j in 0..=n {
        for i in 0..=n {
            let (x, y) = (i as f64 / n as f64 - 0.5, j as f64 / n as f64 - 0.5);
            positions.push(json!([x * 0.7, y * 0.7, 0.9 + 0.01 * (x * 7.0).sin()]));
        }
    }
    let mut indices = Vec::with_capacity(2 * n * n);
    for j in 0..n {
        for i in 0..n {
            let a = j * (n + 1) + i;
            indices.push(json!([a, a + 1, a + n + 1]));
            indices.push(json!([a + 1, a + n + 2, a + n + 1]));
        }
    }
    json_scene(json!([{
        "type": "triangles", "positions": positions, "indices": indices, "material": "grey"
    }]))
}

/// The peak memory a request may add to the coordinator, as README.md states it: a bundle or a
/// reference, whatever its size, at most `STREAMED_BYTES` (they go to disk as they arrive and
/// are checked a block at a time); a JSON body (an inline scene) at most `JSON_MULTIPLE` times
/// its size besides; and the scene a request describes `TRIANGLE_BYTES` per triangle (its
/// triangles and their BVH while it is built).
const STREAMED_BYTES: u64 = 48 << 20;
const JSON_MULTIPLE: u64 = 3;
const TRIANGLE_BYTES: u64 = 300;

#[test]
fn uploads_take_memory_in_proportion_to_what_they_check() {
    let dir = folder("memory");
    let (server, url) = serve(
        &dir.join("data"),
        &["--max-upload-mb", "96", "--max-json-mb", "24"],
    );
    let c = http();
    healthy(&c, &url);
    let base = peak_rss(server.pid());
    let grew = |what: &str, limit: u64| {
        let now = peak_rss(server.pid());
        eprintln!(
            "{what}: peak RSS {:.1} MB, {:.1} MB over the start (bound {:.1} MB)",
            now as f64 / 1e6,
            now.saturating_sub(base) as f64 / 1e6,
            limit as f64 / 1e6
        );
        assert!(
            now.saturating_sub(base) <= limit,
            "{what}: the coordinator grew by {} bytes, more than {limit}",
            now - base
        );
    };
    // An 8192 x 8192 reference that compresses to a few hundred kilobytes: checked from its
    // headers, then block by block (it was decoded whole: gigabytes).
    let exr = dir.join("big.exr");
    constant_exr(&exr, 8192, 8192, 0.25);
    let bytes = std::fs::read(&exr).expect("read EXR");
    eprintln!("reference: {} bytes", bytes.len());
    let r = c
        .post(format!("{url}/v1/references"))
        .header("content-type", "image/x-exr")
        .body(bytes)
        .send()
        .expect("POST reference");
    assert_eq!(r.status().as_u16(), 201, "{:?}", r.text());
    grew("an 8192x8192 ZIP reference", STREAMED_BYTES);
    // A bundle at the upload limit: a small scene and 90 MB of other files.
    let filler: Vec<u8> = (0..90u32 << 20)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    let scene = json_scene(json!([])).to_string();
    let tar = tar_of(&[("scene.json", scene.as_bytes()), ("filler.bin", &filler)]);
    drop(filler);
    let (s, v) = upload_bundle(&c, &url, tar);
    assert_eq!(s, 201, "{v}");
    grew("a 90 MB bundle", STREAMED_BYTES);
    // An inline scene near the JSON limit (a mesh of 180k triangles, written as text).
    let body = json!({"scene": {"inline": big_inline_scene(300)}, "settings": {"spp": 1}});
    let text = serde_json::to_vec(&body).expect("json");
    eprintln!("inline scene: {} bytes", text.len());
    assert!(text.len() > 8 << 20 && text.len() < 24 << 20);
    let r = c
        .post(format!("{url}/v1/jobs"))
        .header("content-type", "application/json")
        .body(text.clone())
        .send()
        .expect("POST job");
    assert_eq!(r.status().as_u16(), 201, "{:?}", r.text());
    grew(
        "an inline JSON scene of 180,000 triangles",
        STREAMED_BYTES + JSON_MULTIPLE * text.len() as u64 + TRIANGLE_BYTES * 180_000,
    );
}

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

/// Submits a job of the Cornell box of `tiles` tiles of 16 pixels (one pass, one sample).
fn small_job(c: &Client, url: &str, tiles: u32) -> String {
    let (s, v) = post(
        c,
        &format!("{url}/v1/jobs"),
        &json!({"scene": {"library": "cornell-box"}, "settings": {
            "resolution": [16 * tiles, 16], "tile_size": 16, "spp": 1, "pass_size": 1,
            "max_pass_size": 1, "integrator": "pt"
        }}),
    );
    assert_eq!(s, 201, "{v}");
    v["id"].as_str().expect("id").to_string()
}

fn fail(c: &Client, url: &str, worker: &str, lease: &Value, error: &str) {
    let (s, v) = post(
        c,
        &format!("{url}/v1/worker/tasks/{}/fail", lease["task"]["id"]),
        &json!({"worker_id": worker, "attempt": lease["task"]["attempt"], "error": error}),
    );
    assert_eq!(s, 200, "{v}");
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
fn a_merge_radius_beyond_the_scene_is_refused() {
    let dir = folder("radius");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({"scene": {"library": "cornell-box"},
                "settings": {"integrator": "vcm", "radius": 1e9, "spp": 1}}),
    );
    assert_eq!(s, 422, "{v}");
    assert_eq!(v["field"], "settings.radius");
    assert!(
        v["error"]
            .as_str()
            .unwrap_or("")
            .contains("bounding-sphere radius"),
        "{v}"
    );
}

/// Runs `omis serve` on `data` expecting it to refuse to start; its standard error.
fn refused_start(data: &Path, extra: &[&str]) -> String {
    let mut child = Command::new(EXE)
        .args(["serve", "--bind", "127.0.0.1:0", "--data"])
        .arg(data)
        .args(extra)
        .env("OMIS_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start omis serve");
    let start = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if start.elapsed() > Duration::from_secs(30) {
            let _ = child.kill();
            panic!("omis serve started on a damaged data folder");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = child.wait_with_output().expect("output");
    assert!(!out.status.success());
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn a_missing_or_damaged_database_stops_the_coordinator_at_start() {
    let dir = folder("db");
    let data = dir.join("data");
    let c = http();
    let job = {
        let (mut server, url) = serve(&data, &[]);
        let job = small_job(&c, &url, 1);
        server.kill9();
        job
    };
    let db = data.join("omis.sqlite");
    let copy = dir.join("copy.sqlite");
    // Checkpointed into the main file, so that a copy of it alone is the whole database.
    {
        let (mut server, _url) = serve(&data, &[]);
        server.kill9();
    }
    let conn = rusqlite::Connection::open(&db).expect("open");
    conn.execute_batch("PRAGMA wal_checkpoint(TRUNCATE);")
        .expect("checkpoint");
    drop(conn);
    let _ = std::fs::remove_file(data.join("omis.sqlite-wal"));
    let _ = std::fs::remove_file(data.join("omis.sqlite-shm"));
    std::fs::copy(&db, &copy).expect("copy");

    // Deleted, then truncated: refused, naming --init.
    std::fs::remove_file(&db).expect("delete");
    let err = refused_start(&data, &[]);
    assert!(
        err.contains("missing or empty") && err.contains("--init"),
        "{err}"
    );
    std::fs::write(&db, b"").expect("truncate");
    let err = refused_start(&data, &[]);
    assert!(err.contains("missing or empty"), "{err}");
    // A damaged page: refused with SQLite's words.
    let mut bytes = std::fs::read(&copy).expect("read");
    let page = 4096;
    assert!(bytes.len() >= 3 * page, "{} bytes", bytes.len());
    for b in &mut bytes[page + 8..2 * page] {
        *b = 0xA5;
    }
    std::fs::write(&db, &bytes).expect("damage");
    let err = refused_start(&data, &[]);
    assert!(
        err.contains("damaged") || err.contains("malformed"),
        "{err}"
    );
    // The intact copy back: the job is there.
    std::fs::copy(&copy, &db).expect("restore");
    let (_server, url) = serve(&data, &[]);
    let st = get_json(&c, &format!("{url}/v1/jobs/{job}"));
    assert_eq!(st["id"], job.as_str());
    drop(_server);
    // --init begins anew beside the old folders.
    std::fs::remove_file(&db).expect("delete");
    let (_server, url) = serve(&data, &["--init"]);
    let list = get_json(&c, &format!("{url}/v1/jobs"));
    assert_eq!(list["jobs"], json!([]));
}

/// `omis serve` with every file it writes limited to `bytes` (RLIMIT_FSIZE): a write past it
/// fails as a full disk would, with EFBIG instead of ENOSPC.
fn serve_with_file_limit(data: &Path, bytes: u64, log: &Path) -> (Proc, String) {
    use std::os::unix::process::CommandExt;
    let mut cmd = Command::new(EXE);
    // SAFETY: between fork and exec the closure only calls async-signal-safe functions
    // (setrlimit, signal) on the child's own state.
    unsafe {
        cmd.pre_exec(move || {
            let lim = libc::rlimit {
                rlim_cur: bytes,
                rlim_max: bytes,
            };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // Past the limit a write fails with EFBIG rather than killing the process.
            libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
            Ok(())
        });
    }
    let log = std::fs::File::create(log).expect("log");
    serve_command(cmd, data, &["--workers", "1"], Stdio::from(log))
}

#[test]
fn a_full_disk_is_a_5xx_logged_with_its_cause_and_nothing_accepted_is_lost() {
    let dir = folder("disk");
    let log = dir.join("serve.log");
    let (_server, url) = serve_with_file_limit(&dir.join("data"), 4 << 20, &log);
    let c = http();
    // A job done before the disk fills.
    let job = small_job(&c, &url, 1);
    let start = Instant::now();
    while get_json(&c, &format!("{url}/v1/jobs/{job}"))["state"] != "done" {
        assert!(start.elapsed() < Duration::from_secs(120));
        std::thread::sleep(Duration::from_millis(100));
    }
    let exr = |c: &Client| {
        c.get(format!("{url}/v1/jobs/{job}/image.exr"))
            .send()
            .expect("GET")
            .bytes()
            .expect("bytes")
    };
    let before = exr(&c);
    // Uploads that do not fit.
    let big = vec![7u8; 6 << 20];
    let scene = json_scene(json!([])).to_string();
    let (s, v) = upload_bundle(
        &c,
        &url,
        tar_of(&[("scene.json", scene.as_bytes()), ("big.bin", &big)]),
    );
    assert_eq!(s, 507, "{v}");
    assert!(
        v["error"]
            .as_str()
            .unwrap_or("")
            .contains("storage is full"),
        "{v}"
    );
    let r = c
        .post(format!("{url}/v1/references"))
        .header("content-type", "image/x-exr")
        .body(big.clone())
        .send()
        .expect("POST reference");
    assert_eq!(r.status().as_u16(), 507);
    // Logged with the cause; nothing accepted is lost.
    let text = std::fs::read_to_string(&log).expect("log");
    assert!(
        text.contains("POST /v1/scenes: 507") && text.contains("storage is full"),
        "{text}"
    );
    assert_eq!(exr(&c), before);
    healthy(&c, &url);
}

#[test]
fn a_reference_full_of_nan_is_refused_naming_the_count() {
    let dir = folder("nan");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let mut img = omis::film::Image::new(8, 4);
    for p in img.pixels.iter_mut().take(5) {
        *p = omis::geometry::Rgb::new(f32::NAN, 0.5, f32::INFINITY);
    }
    let path = dir.join("nan.exr");
    omis::film::image::exr_io::write_exr(&path, &img, &[], &[]).expect("write");
    let r = c
        .post(format!("{url}/v1/references"))
        .header("content-type", "image/x-exr")
        .body(std::fs::read(&path).expect("read"))
        .send()
        .expect("POST");
    assert_eq!(r.status().as_u16(), 422);
    let v: Value = r.json().expect("json");
    assert!(
        v["error"]
            .as_str()
            .unwrap_or("")
            .contains("has 10 values that are NaN or infinite"),
        "{v}"
    );
}

#[test]
fn a_refused_job_leaves_no_bundle_behind() {
    let dir = folder("leak");
    let data = dir.join("data");
    let (_server, url) = serve(&data, &[]);
    let c = http();
    let count = || {
        std::fs::read_dir(data.join("scenes"))
            .map(|d| d.count())
            .unwrap_or(0)
    };
    for k in 0..10 {
        let scene = if k % 2 == 0 {
            json!({"library": "cornell-box"})
        } else {
            json!({"inline": json_scene(json!([]))})
        };
        let (s, v) = post(
            &c,
            &format!("{url}/v1/jobs"),
            &json!({"scene": scene, "settings": {"integrator": "vcm", "radius": 1e9}}),
        );
        assert_eq!(s, 422, "{v}");
    }
    assert_eq!(count(), 0, "refused jobs left their bundles");
    let (s, _) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({"scene": {"library": "cornell-box"}, "settings": {"spp": 1}}),
    );
    assert_eq!(s, 201);
    assert_eq!(count(), 1);
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
        &["--token", "s3cret", "--worker-token", "w0rker"],
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
fn upload_warnings_name_files_inside_the_bundle() {
    let dir = folder("warnings");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let scene = mitsuba("0.5.0", "<float name=\"unknownProperty\" value=\"1\"/>");
    let (s, v) = upload_bundle(&c, &url, tar_of(&[("scene.xml", scene.as_bytes())]));
    assert_eq!(s, 201, "{v}");
    let warnings = v["warnings"].as_array().expect("warnings");
    assert!(!warnings.is_empty(), "{v}");
    for w in warnings {
        let w = w.as_str().unwrap_or("");
        assert!(w.starts_with("scene.xml:"), "{w}");
        assert!(!w.contains(&*dir.to_string_lossy()), "{w}");
    }
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
