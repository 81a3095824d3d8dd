//! Uploads: memory in proportion to what is checked, NaN references, refused bundles, warnings.

use crate::common::service::{http, peak_rss, post, serve};
use crate::support::{folder, healthy, json_scene, mitsuba, tar_of, upload_bundle};
use serde_json::{Value, json};
use std::path::Path;

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
