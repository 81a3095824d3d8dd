//! The command-line clients of the service: submit, wait, download, status, cancel.

use crate::common::repo;
use crate::common::service::{EXE, http, serve, worker};
use crate::support::{folder, wait_state};
use omis::film::image::exr_io;
use serde_json::Value;
use std::path::Path;
use std::process::Command;

#[test]
fn cli_clients_submit_wait_download_status_and_cancel() {
    let dir = folder("clients");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let _w = worker(&url, "w", &[]);
    let omis = |args: &[&str]| {
        Command::new(EXE)
            .args(args)
            .args(["--server", &url])
            .env("OMIS_LOG", "warn")
            .output()
            .expect("run omis")
    };
    let exr = dir.join("first.exr");
    let s = |p: &Path| p.to_str().expect("utf-8").to_string();
    // The same small job settings for both submissions.
    let submit = |scene: &str, extra: &[&str]| {
        let args = [
            "submit",
            scene,
            "--resolution",
            "40x32",
            "--spp",
            "8",
            "--pass-size",
            "4",
            "--integrator",
            "bdpt",
        ];
        let out = omis(&[&args[..], extra].concat());
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        out
    };
    // The first job, from the library, becomes the reference of the second.
    let out = submit("cornell-box", &["--wait", "--out", &s(&exr)]);
    let st: Value = serde_json::from_str(
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .last()
            .expect("a line"),
    )
    .expect("JSON status");
    assert_eq!(st["state"], "done");
    exr_io::read_exr(&exr).expect("the downloaded EXR opens");
    // The second job, a scene file uploaded as a bundle, with the first as reference.
    let scene = repo().join("scenes/cornell-box.json");
    let out = submit(&s(&scene), &["--seed", "3", "--reference", &s(&exr)]);
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let c = http();
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    let series = st["series"].as_array().expect("series");
    assert_eq!(series.len(), 2);
    let relmse = series[1]["relmse"].as_f64().expect("relMSE per pass");
    assert!(relmse > 0.0 && relmse < 1.0, "{relmse}");
    // The last pass's relMSE is the final image's, to the bit: the frame it was measured on
    // (which reuses the previous pass's memory) holds every pixel of the last pass.
    let second = dir.join("second.exr");
    let out = omis(&["download", &id, "--out", &s(&second)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let image = exr_io::read_exr(&second).expect("the second EXR opens");
    let reference = exr_io::read_exr(&exr).expect("the reference opens");
    let eps = st["settings"]["eps"].as_f64().expect("eps");
    let measured = omis::film::image::metrics::compare(&image, &reference, eps)
        .expect("same size")
        .relmse;
    assert_eq!(
        measured, relmse,
        "relMSE of the final EXR against the pass's"
    );
    let out = omis(&["status", &id, "--json"]);
    assert!(out.status.success());
    let v: Value = serde_json::from_slice(&out.stdout).expect("status JSON");
    assert_eq!(v["id"], id.as_str());
    let png = dir.join("error.png");
    let out = omis(&["download", &id, "--file", "error.png", "--out", &s(&png)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The error map is scaled to this render's error (a few percent per pixel at 2 passes, which
    // a fixed scale of 100% showed as black) and carries its legend below the image.
    let map = image::open(&png).expect("the error map decodes").to_rgb8();
    assert_eq!(map.width() as usize, image.width);
    assert!(
        map.height() as usize > image.height,
        "a legend under the map"
    );
    let mean_of = |px: &mut dyn Iterator<Item = u8>| {
        let v: Vec<f64> = px.map(f64::from).collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    let shown = mean_of(&mut (0..image.height as u32).flat_map(|y| {
        let map = &map;
        (0..map.width()).map(move |x| *map.get_pixel(x, y).0.iter().max().unwrap_or(&0))
    }));
    let fixed = omis::film::image::error_map::relative_error_map(&image, &reference, eps, 1.0)
        .expect("same size");
    let at_full_scale = mean_of(&mut fixed.chunks(3).map(|p| p[0].max(p[1])));
    assert!(
        shown > 40.0 && shown > 3.0 * at_full_scale,
        "mean intensity {shown:.1} scaled, {at_full_scale:.1} at a scale of 100%"
    );
    // Cancelling an ended job is a one-line error naming the state.
    let out = omis(&["cancel", &id]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(
        err.contains("409") && err.contains("already ended"),
        "{err}"
    );
    // A queued job can be cancelled.
    let out = omis(&["submit", "cornell-box", "--spp", "60000"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let out = omis(&["cancel", &id]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "cancelled");
}
