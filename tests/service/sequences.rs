//! Sequences: a job of many frames (a bundle of frame files `frame_####.json` sharing a mesh,
//! and a frame range) renders each frame to the bits of a single-frame job of its file, frames in
//! order; its images are served per frame; a bad frame range is refused naming `frames`; cancel
//! of the sequence cancels its frames.

use crate::common::repo;
use crate::common::service::{EXE, get_json, http, post, serve, worker};
use crate::support::{folder, follow_sse};
use omis::film::Image;
use omis::film::image::exr_io;
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};

/// Writes a 3-frame sequence into `dir`: the Cornell box with a shared OBJ block
/// (`meshes/block.obj`) and a camera that moves sideways frame by frame. Returns the frame
/// files.
fn write_sequence(dir: &Path) -> Vec<PathBuf> {
    std::fs::create_dir_all(dir.join("meshes")).expect("scene folder");
    std::fs::write(
        dir.join("meshes/block.obj"),
        "v -0.3 0.0 0.3\nv 0.3 0.0 0.3\nv 0.3 0.5 0.3\nv -0.3 0.5 0.3\nf 1 2 3\nf 1 3 4\n",
    )
    .expect("mesh");
    let text = std::fs::read_to_string(repo().join("scenes/cornell-box.json")).expect("scene");
    let base: Value = serde_json::from_str(&text).expect("JSON");
    (1..=3)
        .map(|f| {
            let mut scene = base.clone();
            scene["camera"]["position"] = json!([0.25 * (f as f64 - 2.0), 1.0, 6.8]);
            scene["shapes"]
                .as_array_mut()
                .expect("shapes")
                .push(json!({ "type": "mesh", "file": "meshes/block.obj", "material": "white" }));
            let path = dir.join(format!("frame_{f:04}.json"));
            std::fs::write(&path, serde_json::to_vec(&scene).expect("JSON")).expect("frame");
            path
        })
        .collect()
}

/// Small, quick frames of several passes and tiles.
fn settings() -> Value {
    json!({
        "resolution": [40, 32],
        "spp": 8,
        "pass_size": 4,
        "max_pass_size": 4,
        "tile_size": 16,
        "integrator": "pt",
        "max_depth": 4,
        "seed": 11,
    })
}

/// Uploads a bundle with main file `main`; its id.
fn upload(c: &Client, url: &str, tar: Vec<u8>, main: &str) -> String {
    let r = c
        .post(format!("{url}/v1/scenes"))
        .query(&[("main", main)])
        .body(tar)
        .send()
        .expect("POST /v1/scenes");
    let status = r.status().as_u16();
    let v: Value = r.json().unwrap_or(Value::Null);
    assert_eq!(status, 201, "{v}");
    v["id"].as_str().expect("bundle id").to_string()
}

/// A tar archive of `files` (paths relative to `dir`).
fn tar_of(dir: &Path, files: &[&str]) -> Vec<u8> {
    let mut b = tar::Builder::new(Vec::new());
    for f in files {
        b.append_path_with_name(dir.join(f), f).expect("append");
    }
    b.into_inner().expect("tar")
}

/// The sequence's bundle (its frame files and their mesh), uploaded.
fn upload_sequence(c: &Client, url: &str, dir: &Path) -> String {
    let tar = tar_of(
        dir,
        &[
            "frame_0001.json",
            "frame_0002.json",
            "frame_0003.json",
            "meshes/block.obj",
        ],
    );
    upload(c, url, tar, "frame_####.json")
}

/// `omis submit --wait` of `scene` with the flags of `settings()` and `extra`; the status
/// document it prints last.
fn submit_cli(url: &str, scene: &Path, extra: &[&str]) -> Value {
    let out = std::process::Command::new(EXE)
        .arg("submit")
        .arg(scene)
        .args([
            "--server",
            url,
            "--wait",
            "--resolution",
            "40x32",
            "--spp",
            "8",
            "--pass-size",
            "4",
            "--max-pass-size",
            "4",
            "--tile-size",
            "16",
            "--integrator",
            "pt",
            "--max-depth",
            "4",
            "--seed",
            "11",
        ])
        .args(extra)
        .env_remove("OMIS_TOKEN")
        .output()
        .expect("omis submit");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "omis submit: {}\n{stdout}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(stdout.lines().last().unwrap_or("")).expect("the status, as JSON")
}

/// GET `path` of the service: status and body.
fn get(c: &Client, url: &str, path: &str) -> (u16, Vec<u8>) {
    let r = c.get(format!("{url}{path}")).send().expect("GET");
    (r.status().as_u16(), r.bytes().expect("body").to_vec())
}

fn exr(bytes: &[u8], dir: &Path, name: &str) -> Image {
    let p = dir.join(name);
    std::fs::write(&p, bytes).expect("write");
    exr_io::read_exr(&p).expect("the EXR opens")
}

fn bits(img: &Image) -> Vec<[u32; 3]> {
    img.pixels
        .iter()
        .map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
        .collect()
}

/// A 400 JSON error naming `field`.
fn assert_refused(status: u16, body: &[u8], field: &str) -> Value {
    assert_error(status, body, 400, field)
}

/// A JSON error of status `want` naming `field`.
fn assert_error(status: u16, body: &[u8], want: u16, field: &str) -> Value {
    let v: Value = serde_json::from_slice(body).unwrap_or(Value::Null);
    assert_eq!((status, v["field"].as_str()), (want, Some(field)), "{v}");
    v
}

#[test]
fn a_sequence_renders_its_frames_in_order_to_the_bits_of_single_frame_jobs() {
    let dir = folder("sequence");
    let frames = write_sequence(&dir.join("scene"));
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    // One worker: the frames render one after the other, in frame order.
    let _w = worker(&url, "w1", &[]);
    // `omis submit --frames` packs every frame file with the mesh they share, and writes one
    // EXR per frame.
    let out = dir.join("out");
    std::fs::create_dir_all(&out).expect("out folder");
    let st = submit_cli(
        &url,
        &dir.join("scene/frame_####.json"),
        &[
            "--frames",
            "1-3",
            "--name",
            "walk",
            "--out",
            &out.join("seq_##.exr").to_string_lossy(),
        ],
    );
    let id = st["id"].as_str().expect("id").to_string();
    assert_eq!(st["state"], "done", "{st}");
    assert_eq!(st["spp_done"], 3 * 8, "{st}");
    let children: Vec<Value> = st["frames"]
        .as_array()
        .expect("the frames are listed")
        .iter()
        .map(|f| {
            assert_eq!(f["state"], "done", "{f}");
            let child = f["job_id"].as_str().expect("job id");
            get_json(&c, &format!("{url}/v1/jobs/{child}"))
        })
        .collect();
    assert_eq!(children.len(), 3);
    for (k, child) in children.iter().enumerate() {
        assert_eq!(child["parent"].as_str(), Some(id.as_str()));
        assert_eq!(child["frame"].as_u64(), Some(k as u64 + 1));
        assert_eq!(child["scene"]["main"], format!("frame_{:04}.json", k + 1));
    }
    let times = |key: &str| -> Vec<f64> {
        children
            .iter()
            .map(|c| c[key].as_f64().expect("a time"))
            .collect()
    };
    for key in ["started_at", "finished_at"] {
        let t = times(key);
        assert!(
            t.windows(2).all(|w| w[0] <= w[1]),
            "{key} out of frame order: {t:?}"
        );
    }
    // The list shows the sequence, not its frames, unless asked.
    let list = get_json(&c, &format!("{url}/v1/jobs"));
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(1), "{list}");
    let all = get_json(&c, &format!("{url}/v1/jobs?include_frames=true"));
    assert_eq!(all["jobs"].as_array().map(Vec::len), Some(4));
    // Each frame's EXR as the CLI wrote it equals the one served by frame number.
    let images: Vec<Image> = (1..=3)
        .map(|f| {
            let (s, body) = get(&c, &url, &format!("/v1/jobs/{id}/image.exr?frame={f}"));
            assert_eq!(s, 200);
            let served = exr(&body, &dir, &format!("served_{f}.exr"));
            let written = exr_io::read_exr(&out.join(format!("seq_{f:02}.exr")))
                .expect("the CLI wrote the frame's EXR");
            assert!(bits(&served) == bits(&written), "frame {f}");
            served
        })
        .collect();
    assert_ne!(bits(&images[0]), bits(&images[1]), "the camera moves");
    assert_ne!(bits(&images[1]), bits(&images[2]), "the camera moves");
    let (s, body) = get(&c, &url, &format!("/v1/jobs/{id}/preview.png?frame=2"));
    assert_eq!((s, &body[..4]), (200, &b"\x89PNG"[..]));
    // A frame the job does not have (out of range, or of a single frame): 404 naming `frame`;
    // a sequence's image without one: 400.
    let (s, body) = get(&c, &url, &format!("/v1/jobs/{id}/image.exr?frame=4"));
    assert_error(s, &body, 404, "frame");
    let (s, body) = get(&c, &url, &format!("/v1/jobs/{id}/image.exr"));
    assert_refused(s, &body, "frame");
    // Each frame alone, as a single-frame job of its file: the same bits.
    for (k, frame) in frames.iter().enumerate() {
        let single_out = dir.join(format!("single_{k}.exr"));
        let st = submit_cli(&url, frame, &["--out", &single_out.to_string_lossy()]);
        let img = exr_io::read_exr(&single_out).expect("the single frame's EXR");
        assert!(img.mean()[0] > 0.01, "the image is not black");
        assert!(
            bits(&img) == bits(&images[k]),
            "frame {} differs from its single-frame render",
            k + 1
        );
        let single = st["id"].as_str().expect("id");
        let (s, body) = get(&c, &url, &format!("/v1/jobs/{single}/image.exr?frame=1"));
        assert_error(s, &body, 404, "frame");
    }
}

#[test]
fn a_bad_frame_range_is_refused_and_cancelling_a_sequence_cancels_its_frames() {
    let dir = folder("sequence-cancel");
    let frames = write_sequence(&dir.join("scene"));
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    assert_eq!(frames.len(), 3);
    let bundle = upload_sequence(&c, &url, &dir.join("scene"));
    let submit = |req: Value| {
        let (s, v) = post(&c, &format!("{url}/v1/jobs"), &req);
        (s, serde_json::to_vec(&v).expect("JSON"))
    };
    let scene = json!({ "bundle": bundle });
    // A frame whose file is not in the bundle, named.
    let (s, v) = submit(json!({ "scene": scene, "frames": {"first": 1, "last": 4} }));
    let v = assert_refused(s, &v, "frames");
    assert!(
        v["error"]
            .as_str()
            .unwrap_or("")
            .contains("frame_0004.json"),
        "{v}"
    );
    // A pattern bundle without frames; frames of a scene that is no pattern; bad ranges.
    let (s, v) = submit(json!({ "scene": scene }));
    assert_refused(s, &v, "frames");
    let (s, v) = submit(json!({ "scene": { "library": "cornell-box" }, "frames": "1-3" }));
    assert_refused(s, &v, "frames");
    for bad in ["3-1", "1-3:0", "0-20000"] {
        let (s, v) = submit(json!({ "scene": scene, "frames": bad }));
        assert_refused(s, &v, "frames");
    }
    let list = get_json(&c, &format!("{url}/v1/jobs?include_frames=true"));
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(0), "{list}");
    // No worker: the sequence waits; cancelled, every frame is.
    let (s, v) = submit(json!({ "scene": scene, "frames": "1-3:2", "settings": settings() }));
    assert_eq!(s, 201);
    let st: Value = serde_json::from_slice(&v).expect("JSON");
    let id = st["id"].as_str().expect("id").to_string();
    assert_eq!(st["frames"].as_array().map(Vec::len), Some(2), "{st}");
    // Pause, priority and resume act on every frame with the sequence.
    let frame_states = |want: &str, priority: i64| {
        let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
        for f in st["frames"].as_array().expect("frames") {
            let child = get_json(
                &c,
                &format!("{url}/v1/jobs/{}", f["job_id"].as_str().unwrap_or("")),
            );
            assert_eq!(
                (child["state"].as_str(), child["priority"].as_i64()),
                (Some(want), Some(priority)),
                "{child}"
            );
        }
    };
    let (s, v) = post(&c, &format!("{url}/v1/jobs/{id}/pause"), &json!({}));
    assert_eq!((s, v["state"].as_str()), (200, Some("paused")), "{v}");
    frame_states("paused", 0);
    let r = c
        .patch(format!("{url}/v1/jobs/{id}"))
        .json(&json!({ "priority": 7 }))
        .send()
        .expect("patch");
    assert_eq!(r.status().as_u16(), 200);
    frame_states("paused", 7);
    let (s, v) = post(&c, &format!("{url}/v1/jobs/{id}/resume"), &json!({}));
    assert_eq!((s, v["state"].as_str()), (200, Some("queued")), "{v}");
    frame_states("queued", 7);
    // A frame is deleted with its sequence, not alone.
    let frame = st["frames"][0]["job_id"]
        .as_str()
        .expect("frame id")
        .to_string();
    let r = c
        .delete(format!("{url}/v1/jobs/{frame}"))
        .send()
        .expect("delete");
    assert_eq!(r.status().as_u16(), 409);
    let (s, v) = post(&c, &format!("{url}/v1/jobs/{id}/cancel"), &json!({}));
    assert_eq!((s, v["state"].as_str()), (200, Some("cancelled")), "{v}");
    let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    for f in st["frames"].as_array().expect("frames") {
        assert_eq!(f["state"], "cancelled", "{st}");
        let child = get_json(
            &c,
            &format!("{url}/v1/jobs/{}", f["job_id"].as_str().unwrap_or("")),
        );
        assert_eq!(child["state"], "cancelled");
    }
    let events = follow_sse(&c, &url, &id);
    assert_eq!(
        events.last().map(|(k, _)| k.as_str()),
        Some("cancelled"),
        "{events:?}"
    );
    // A worker that comes now finds nothing to do: the frames stay cancelled.
    let _w = worker(&url, "w1", &[]);
    std::thread::sleep(std::time::Duration::from_secs(2));
    let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    assert_eq!(st["state"], "cancelled");
    assert_eq!(st["spp_done"], 0, "{st}");
    // Deleting the sequence deletes its frames.
    let r = c
        .delete(format!("{url}/v1/jobs/{id}"))
        .send()
        .expect("delete");
    assert_eq!(r.status().as_u16(), 204);
    let list = get_json(&c, &format!("{url}/v1/jobs?include_frames=true"));
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(0), "{list}");
}

#[test]
fn omis_render_of_a_sequence_writes_one_exr_per_frame() {
    let dir = folder("sequence-render");
    write_sequence(&dir.join("scene"));
    let out = dir.join("frames");
    let done = std::process::Command::new(EXE)
        .arg("render")
        .arg(dir.join("scene/frame_####.json"))
        .args([
            "--frames",
            "1-3:2",
            "--workers",
            "1",
            "--resolution",
            "40x32",
            "--spp",
            "4",
            "--tile-size",
            "16",
            "--integrator",
            "pt",
            "--max-depth",
            "3",
        ])
        .arg("--out")
        .arg(&out)
        .env_remove("OMIS_LOG")
        .output()
        .expect("omis render");
    assert!(
        done.status.success(),
        "omis render: {}",
        String::from_utf8_lossy(&done.stderr)
    );
    let first = exr_io::read_exr(&out.join("frame_0001.exr")).expect("frame 1");
    let third = exr_io::read_exr(&out.join("frame_0003.exr")).expect("frame 3");
    assert!(first.mean()[0] > 0.01, "the image is not black");
    assert_ne!(bits(&first), bits(&third), "the camera moves");
    assert!(
        !out.join("frame_0002.exr").exists(),
        "frame 2 is not in 1-3:2"
    );
}

#[test]
fn a_sequence_killed_with_its_coordinator_finishes_after_the_restart() {
    let dir = folder("sequence-restart");
    write_sequence(&dir.join("scene"));
    let data = dir.join("data");
    let (mut server, url) = serve(&data, &[]);
    let c = http();
    let bundle = upload_sequence(&c, &url, &dir.join("scene"));
    let (s, st) = post(
        &c,
        &format!("{url}/v1/jobs"),
        &json!({ "scene": { "bundle": bundle }, "frames": "1-3", "settings": settings() }),
    );
    assert_eq!(s, 201, "{st}");
    let id = st["id"].as_str().expect("id").to_string();
    // Accepted, then the coordinator dies before any worker came: nothing is lost.
    server.kill9();
    let (_server, url) = serve(&data, &[]);
    let _w = worker(&url, "w1", &[]);
    let events = follow_sse(&c, &url, &id);
    assert_eq!(
        events.last().map(|(k, _)| k.as_str()),
        Some("done"),
        "{events:?}"
    );
    let st = get_json(&c, &format!("{url}/v1/jobs/{id}"));
    assert_eq!(st["spp_done"], 3 * 8, "{st}");
    for f in 1..=3 {
        let (s, _) = get(&c, &url, &format!("/v1/jobs/{id}/image.exr?frame={f}"));
        assert_eq!(s, 200, "frame {f}");
    }
}
