//! Limits on uploads, scenes, tiles, references, settings and bundles.

use crate::common::repo;
use crate::common::service::{http, post, serve};
use crate::support::{WAIT, folder};
use omis::film::Image;
use omis::film::image::exr_io;
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::path::Path;
use std::time::{Duration, Instant};

#[test]
fn upload_and_scene_limits_are_enforced_with_json_errors() {
    let dir = folder("limits");
    let (_server, url) = serve(
        &dir.join("data"),
        &[
            "--max-upload-mb",
            "1",
            "--max-triangles",
            "8",
            "--max-spp",
            "64",
        ],
    );
    let c = http();
    // A body over the upload limit: 413, as JSON, answered from the declared length before
    // any of the body is read. (Raw: a client still writing the body the server will not read
    // can see its connection closed under it instead of the answer.)
    {
        use std::io::{Read, Write};
        let addr = url.trim_start_matches("http://").to_string();
        let mut tcp = std::net::TcpStream::connect(&addr).expect("connect");
        tcp.set_read_timeout(Some(std::time::Duration::from_secs(10)))
            .expect("timeout");
        let head = format!(
            "POST /v1/references HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/octet-stream\r\nContent-Length: {}\r\n\r\n",
            2 << 20
        );
        tcp.write_all(head.as_bytes()).expect("headers");
        let mut answer = Vec::new();
        let mut buf = [0u8; 4096];
        while let Ok(n) = tcp.read(&mut buf) {
            if n == 0 {
                break;
            }
            answer.extend_from_slice(&buf[..n]);
            let text = String::from_utf8_lossy(&answer);
            if let Some(end) = text.find("\r\n\r\n")
                && text[end + 4..].trim_end().ends_with('}')
            {
                break;
            }
        }
        let text = String::from_utf8_lossy(&answer).to_string();
        assert!(text.starts_with("HTTP/1.1 413"), "{text}");
        let body = &text[text.find("\r\n\r\n").expect("headers end") + 4..];
        let v: Value = serde_json::from_str(body.trim()).expect("JSON");
        assert_eq!(v["field"], "body", "{v}");
    }
    // A scene over the triangle limit, and spp over the server's limit.
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({ "scene": { "library": "cornell-box" } }),
    );
    assert_eq!(s, 400, "{v}");
    assert_eq!(v["field"], "scene.library");
    assert!(
        v["error"].as_str().unwrap_or("").contains("triangles"),
        "{v}"
    );
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({ "scene": { "library": "furnace" }, "settings": { "spp": 65 } }),
    );
    assert_eq!(s, 422, "{v}");
    assert_eq!(v["field"], "settings.spp");
    // Within the limits the same server accepts a job.
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({ "scene": { "library": "furnace" }, "settings": { "spp": 4, "resolution": [8, 8] } }),
    );
    assert_eq!(s, 201, "{v}");
}

/// The furnace scene as an inline JSON scene, with its `render` defaults replaced.
fn inline_furnace(render: Value) -> Value {
    let text = std::fs::read_to_string(repo().join("scenes/furnace.json")).expect("furnace");
    let mut scene: Value = serde_json::from_str(&text).expect("JSON");
    scene["render"] = render;
    scene
}

/// Queued tasks of every job, from /metrics.
fn queued_tasks(c: &Client, url: &str) -> u64 {
    let m = c
        .get(format!("{url}/metrics"))
        .send()
        .expect("metrics")
        .text()
        .expect("text");
    m.lines()
        .find_map(|l| l.strip_prefix("omis_tasks{state=\"queued\"} "))
        .map_or(0, |n| n.trim().parse().expect("a count"))
}

/// The slowest of GET /healthz and GET /v1/jobs (which reads the store) while `until` is false,
/// polled for at most `limit`.
fn slowest_answer(c: &Client, url: &str, limit: Duration, until: impl Fn() -> bool) -> Duration {
    let start = Instant::now();
    let mut worst = Duration::ZERO;
    while !until() {
        assert!(start.elapsed() < limit, "not done after {limit:?}");
        for path in ["/healthz", "/v1/jobs"] {
            let t = Instant::now();
            let r = c
                .get(format!("{url}{path}"))
                .timeout(Duration::from_secs(30))
                .send()
                .unwrap_or_else(|e| panic!("GET {path}: {e}"));
            assert!(r.status().is_success(), "GET {path}: {}", r.status());
            worst = worst.max(t.elapsed());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    worst
}

#[test]
fn too_many_tiles_are_refused_and_a_large_job_keeps_the_api_responsive_across_a_restart() {
    let dir = folder("tiles");
    let data = dir.join("data");
    let args = ["--max-tasks-per-pass", "200000"];
    let (mut server, url) = serve(&data, &args);
    let c = http();
    // 8192x8192 in tiles of 1 is 67M tasks a pass: refused at once, naming the bound.
    let t = Instant::now();
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({ "scene": { "library": "furnace" },
                 "settings": { "resolution": [8192, 8192], "tile_size": 1 } }),
    );
    assert_eq!(
        (s, v["field"].as_str()),
        (422, Some("settings.tile_size")),
        "{v}"
    );
    let msg = v["error"].as_str().unwrap_or("");
    assert!(msg.contains("67108864") && msg.contains("200000"), "{v}");
    assert!(t.elapsed() < Duration::from_secs(10));
    // So is a scene whose own resolution makes too many tiles.
    let mut big = inline_furnace(json!({ "spp": 4 }));
    big["camera"]["resolution"] = json!([1000, 1000]);
    let (s, v) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({ "scene": { "inline": big }, "settings": { "tile_size": 2 } }),
    );
    assert_eq!(
        (s, v["field"].as_str()),
        (422, Some("settings.tile_size")),
        "{v}"
    );
    // A large job within the bound: 400x400 tiles of 1, 160000 tasks a pass, two passes open.
    let job = json!({ "scene": { "library": "furnace" },
                      "settings": { "resolution": [400, 400], "tile_size": 1, "spp": 8, "pass_size": 1 } });
    let posted = {
        let (u, j) = (url.clone(), job.clone());
        std::thread::spawn(move || {
            let (s, v) = post(&http(), &format!("{u}/v1/jobs"), &j);
            assert_eq!(s, 201, "{v}");
        })
    };
    let worst = slowest_answer(&c, &url, WAIT, || {
        posted.is_finished() && queued_tasks(&http(), &url) >= 320_000
    });
    assert!(worst < Duration::from_secs(3), "an answer took {worst:?}");
    posted.join().expect("the job was created");
    // A second one, and the coordinator killed while its tasks are being made: the restarted
    // coordinator answers at once and finishes making them in the background.
    let (s, v) = post(&c, &format!("{url}/v1/jobs"), &job);
    assert_eq!(s, 201, "{v}");
    server.kill9();
    let t = Instant::now();
    let (mut server, url) = serve(&data, &args);
    assert!(
        t.elapsed() < Duration::from_secs(15),
        "the restart took {:?}",
        t.elapsed()
    );
    let worst = slowest_answer(&c, &url, WAIT, || queued_tasks(&c, &url) >= 640_000);
    assert!(worst < Duration::from_secs(3), "an answer took {worst:?}");
    // SIGTERM while a third job's tasks are being made: the coordinator stops promptly.
    let (s, v) = post(&c, &format!("{url}/v1/jobs"), &job);
    assert_eq!(s, 201, "{v}");
    // SAFETY: kill(2) on our own child.
    unsafe {
        libc::kill(server.0.id() as libc::pid_t, libc::SIGTERM);
    }
    let t = Instant::now();
    while server.0.try_wait().expect("wait").is_none() {
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "SIGTERM did not stop the coordinator"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A real little EXR (8x8, ZIP) whose header then claims a `w` x `h` data window.
fn exr_claiming(dir: &Path, w: i32, h: i32) -> Vec<u8> {
    let path = dir.join("small.exr");
    let img = Image::new(8, 8);
    exr_io::write_exr(&path, &img, &[], &[]).expect("write EXR");
    let mut bytes = std::fs::read(&path).expect("read EXR");
    let key = b"dataWindow\0box2i\0";
    let at = bytes
        .windows(key.len())
        .position(|w| w == key)
        .expect("a dataWindow attribute")
        + key.len()
        + 4;
    for (k, v) in [0i32, 0, w - 1, h - 1].iter().enumerate() {
        bytes[at + 4 * k..at + 4 * k + 4].copy_from_slice(&v.to_le_bytes());
    }
    bytes
}

/// A 1x1 EXR with `n` channels.
fn exr_with_channels(dir: &Path, n: usize) -> Vec<u8> {
    use exr::prelude::*;
    let path = dir.join("channels.exr");
    let channels: Vec<AnyChannel<FlatSamples>> = (0..n)
        .map(|i| AnyChannel::new(format!("c{i:05}").as_str(), FlatSamples::F32(vec![0.0])))
        .collect();
    let layer = Layer::new(
        (1, 1),
        LayerAttributes::named("many"),
        Encoding::UNCOMPRESSED,
        AnyChannels::sort(channels.into()),
    );
    exr::image::Image::from_layer(layer)
        .write()
        .to_file(&path)
        .expect("write EXR");
    std::fs::read(&path).expect("read EXR")
}

/// Peak resident memory of a process in KiB.
fn peak_rss_kib(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_default()
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

#[test]
fn a_reference_whose_header_claims_too_much_is_refused_before_decoding() {
    let dir = folder("bomb");
    let (server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let rss0 = peak_rss_kib(server.0.id());
    for (body, needle) in [
        (exr_claiming(&dir, 16384, 16384), "16384x16384"),
        (exr_with_channels(&dir, 1100), "channels"),
    ] {
        let t = Instant::now();
        let r = c
            .post(format!("{url}/v1/references"))
            .body(body)
            .send()
            .expect("POST");
        let status = r.status().as_u16();
        let v: Value = r.json().expect("JSON");
        assert_eq!((status, v["field"].as_str()), (422, Some("body")), "{v}");
        assert!(
            v["error"].as_str().unwrap_or("").contains(needle),
            "{v} should mention {needle}"
        );
        assert!(
            t.elapsed() < Duration::from_secs(5),
            "took {:?}",
            t.elapsed()
        );
    }
    let grew = peak_rss_kib(server.0.id()).saturating_sub(rss0);
    assert!(
        grew < 200 << 10,
        "the server's peak memory grew by {grew} KiB"
    );
    // A reference within the limits is still taken.
    let path = dir.join("ok.exr");
    exr_io::write_exr(&path, &Image::new(8, 6), &[], &[]).expect("write");
    let r = c
        .post(format!("{url}/v1/references"))
        .body(std::fs::read(&path).expect("read"))
        .send()
        .expect("POST");
    assert_eq!(r.status().as_u16(), 201);
    let v: Value = r.json().expect("JSON");
    assert_eq!(
        (v["width"].as_u64(), v["height"].as_u64()),
        (Some(8), Some(6))
    );
}

#[test]
fn settings_are_validated_wherever_they_come_from() {
    let dir = folder("resolved");
    let (_server, url) = serve(&dir.join("data"), &["--max-spp", "64"]);
    let c = http();
    let jobs = format!("{url}/v1/jobs");
    // The depth limit holds for a depth the scene file sets, with the path tracer too.
    let scene = inline_furnace(json!({ "spp": 4, "max_depth": 4294967295u64 }));
    let (s, v) = post(
        &c,
        &jobs,
        &json!({ "scene": { "inline": scene }, "settings": { "integrator": "pt" } }),
    );
    assert_eq!(
        (s, v["field"].as_str()),
        (422, Some("settings.max_depth")),
        "{v}"
    );
    assert!(
        v["error"].as_str().unwrap_or("").contains("4294967295"),
        "{v}"
    );
    // And the spp limit for the scene's default spp.
    let scene = inline_furnace(json!({ "spp": 1000 }));
    let (s, v) = post(&c, &jobs, &json!({ "scene": { "inline": scene } }));
    assert_eq!((s, v["field"].as_str()), (422, Some("settings.spp")), "{v}");
    assert!(v["error"].as_str().unwrap_or("").contains("64"), "{v}");
    // Settings that override the scene's defaults make it acceptable.
    let scene = inline_furnace(json!({ "spp": 1000, "max_depth": 4294967295u64 }));
    let (s, v) = post(
        &c,
        &jobs,
        &json!({ "scene": { "inline": scene }, "settings": { "spp": 4, "max_depth": 3 } }),
    );
    assert_eq!(s, 201, "{v}");
    assert_eq!(v["spp_target"], 4);
    // Absurd numbers in the settings themselves.
    for (settings, field) in [
        (json!({ "kappa": 1e308 }), "settings.kappa"),
        (json!({ "time_budget_s": 1e-320 }), "settings.time_budget_s"),
    ] {
        let (s, v) = post(
            &c,
            &jobs,
            &json!({ "scene": { "library": "furnace" }, "settings": settings }),
        );
        assert_eq!((s, v["field"].as_str()), (422, Some(field)), "{v}");
    }
}

/// A tar archive of `files` (path, contents).
fn tar_of(files: &[(String, Vec<u8>)]) -> Vec<u8> {
    let mut b = tar::Builder::new(Vec::new());
    for (path, data) in files {
        let mut h = tar::Header::new_gnu();
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        h.set_cksum();
        b.append_data(&mut h, path, data.as_slice())
            .expect("append");
    }
    b.into_inner().expect("tar")
}

#[test]
fn bundles_and_library_names_cannot_abuse_the_server() {
    let dir = folder("bundles");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let scene = serde_json::to_vec(&inline_furnace(json!({ "spp": 4 }))).expect("JSON");
    let upload = |tar: Vec<u8>| -> (u16, Value) {
        let r = c
            .post(format!("{url}/v1/scenes"))
            .body(tar)
            .send()
            .expect("POST");
        (r.status().as_u16(), r.json().unwrap_or(Value::Null))
    };
    // A scene with 10,000 other files: more entries than a bundle may have.
    let mut files = vec![("scene.json".to_string(), scene.clone())];
    files.extend((0..10_000).map(|i| (format!("junk/{i}"), Vec::new())));
    let (s, v) = upload(tar_of(&files));
    assert_eq!((s, v["field"].as_str()), (400, Some("body")), "{v}");
    assert!(v["error"].as_str().unwrap_or("").contains("10000"), "{v}");
    // A GNU sparse entry is called what it is.
    // (512 bytes of data at offset 0 of a 1 MiB file, as `tar --sparse` writes it.)
    let mut sparse = tar::Header::new_gnu();
    sparse.set_path("holes.bin").expect("path");
    sparse.set_entry_type(tar::EntryType::GNUSparse);
    sparse.set_size(512);
    let gnu = sparse.as_gnu_mut().expect("a GNU header");
    gnu.set_real_size(1 << 20);
    gnu.sparse[0].set_offset(0);
    gnu.sparse[0].set_length(512);
    sparse.set_cksum();
    let mut tar = tar_of(&[("scene.json".into(), scene.clone())]);
    tar.truncate(tar.len() - 1024); // the end-of-archive blocks
    tar.extend_from_slice(sparse.as_bytes());
    tar.extend_from_slice(&[7u8; 512]);
    tar.extend_from_slice(&[0u8; 1024]);
    let (s, v) = upload(tar);
    assert_eq!(s, 400, "{v}");
    let e = v["error"].as_str().unwrap_or("");
    assert!(e.contains("sparse") && !e.contains("link"), "{v}");
    // The scene alone is fine.
    let (s, v) = upload(tar_of(&[("scene.json".into(), scene)]));
    assert_eq!(s, 201, "{v}");
    // A library file that is not a scene: refused, and without the server's folders.
    let library = repo().join("scenes");
    for name in ["README.md", "README"] {
        let (s, v) = post(
            &c,
            &format!("{url}/v1/jobs"),
            &json!({ "scene": { "library": name } }),
        );
        assert_eq!(
            (s, v["field"].as_str()),
            (400, Some("scene.library")),
            "{v}"
        );
        let text = v.to_string();
        assert!(
            !text.contains(library.to_str().expect("utf-8"))
                && !text.contains(&*dir.to_string_lossy()),
            "{v} shows a server path"
        );
    }
}
