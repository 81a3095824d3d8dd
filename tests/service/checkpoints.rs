//! Stored results and tile checkpoints: damage on disk, passes merged without checkpoints,
//! torn and unreadable checkpoints.

use crate::common::service::{get_json, http, post, register, serve, worker};
use crate::support::{
    WAIT, assert_equal, download_exr, folder, in_process, in_process_settings, lease, merge_task,
    settings, submit, submit_settings, synthetic_layout, tile_result, tile_result_of, upload,
    wait_state,
};
use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A metric's value from GET /metrics.
fn metric(c: &Client, url: &str, name: &str) -> f64 {
    let text = c
        .get(format!("{url}/metrics"))
        .send()
        .expect("GET /metrics")
        .text()
        .expect("text");
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
        .unwrap_or_else(|| panic!("no metric {name} in {text}"))
}

#[test]
fn a_recorded_result_damaged_on_disk_is_rendered_again() {
    let dir = folder("damaged");
    let data = dir.join("data");
    let (_server, url) = serve(&data, &[]);
    let c = http();
    let id = submit(&c, &url, 4);
    let w = register(&c, &url, "manual");
    let t = lease(&c, &url, &w);
    assert_eq!(upload(&c, &url, &t, &w, tile_result(&t["task"], 7)), 200);
    // Damage the stored record before its pass is merged: one byte in the middle of the first
    // pixel's radiance sum (it would still decode, and the image would show it).
    let log = data.join(format!("jobs/{id}/results-0.log"));
    let mut bytes = std::fs::read(&log).expect("the pass's result log");
    let sections = u32::from_le_bytes(bytes[80..84].try_into().expect("4 bytes")) as usize;
    let own = 84 + sections * 16 + 4;
    let first_sum = own + 68 + 4;
    bytes[first_sum + 5] ^= 0x10;
    std::fs::write(&log, &bytes).expect("write the log");
    // The workers finish the pass; its merge finds the damage and the tile is rendered again.
    let _w = worker(&url, "w", &[]);
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 4);
    let tasks = 6.0; // 40x32 in tiles of 16
    assert_eq!(metric(&c, &url, "omis_results_accepted_total"), tasks + 1.0);
    assert_equal(&download_exr(&c, &url, &id, &dir), &in_process(4));
    // The ended job's result log is kept as a spare for the next job's, not left in its folder.
    assert!(!data.join(format!("jobs/{id}/results-0.log")).exists());
    let spares = std::fs::read_dir(data.join("spare-logs")).map_or(0, |d| d.count());
    assert_eq!(spares, 1, "the job's one log, kept as a spare");
}

/// A job of two passes of 4 spp (6 tiles of at most 16x16 on `data`) whose first pass is
/// merged, with the path of its first band's tile checkpoints and their bytes, and the length of
/// one slot.
fn first_pass_merged(c: &Client, url: &str, data: &Path) -> (String, PathBuf, Vec<u8>, usize) {
    let id = merge_first_pass(c, url, &settings(8));
    let layout = synthetic_layout(&settings(8));
    let len = omis::film::format::TileCheckpoint::encoded_len(16 * 16, &layout) as usize;
    let band = data.join(format!("jobs/{id}/tiles/band-000000.acc"));
    let bytes = std::fs::read(&band).expect("the band's checkpoints");
    (id, band, bytes, len)
}

/// Submits a job of `settings` (6 tiles on 40x32) and, as its only worker, renders and merges
/// its first pass; returns the job's id.
fn merge_first_pass(c: &Client, url: &str, settings: &Value) -> String {
    let id = submit_settings(c, url, settings.clone());
    let w = register(c, url, "manual");
    for _ in 0..6 {
        let t = lease(c, url, &w);
        assert_eq!(t["task"]["pass"], 0, "{t}");
        let body = tile_result_of(settings, &t["task"], 7);
        assert_eq!(upload(c, url, &t, &w, body), 200);
    }
    // The pass's merge tasks (leased before the next pass's render tasks once they exist).
    let start = Instant::now();
    while get_json(c, &format!("{url}/v1/jobs/{id}"))["passes_done"] != 1 {
        assert!(start.elapsed() < WAIT, "the first pass was not merged");
        let t = lease(c, url, &w);
        if t["task"]["kind"] == "merge" {
            assert_eq!(merge_task(c, url, &t, &w), 200);
        } else {
            let body = tile_result_of(settings, &t["task"], 7);
            assert_eq!(upload(c, url, &t, &w, body), 200);
        }
    }
    id
}

/// A path-traced job of `spp` in passes of 4 (its results hold only their own pixels: its
/// checkpoints are written after every second pass).
fn path_traced(spp: u32) -> Value {
    let mut s = settings(spp);
    s["integrator"] = json!("pt");
    s.as_object_mut().expect("object").remove("mis");
    s
}

/// A path-traced job's first pass is merged without checkpoints (the next merge reads its results
/// again), so its results and their tasks must outlive its record: across a coordinator
/// restart right after it, and with one of its records damaged on disk after it was merged
/// (its tile is rendered again), the job ends with the in-process bits.
#[test]
fn a_pass_merged_without_checkpoints_survives_a_restart_and_a_damaged_record() {
    let dir = folder("deferred");
    let data = dir.join("data");
    let (mut server, url) = serve(&data, &[]);
    let c = http();
    let job = path_traced(12);
    let id = merge_first_pass(&c, &url, &job);
    let tiles = data.join(format!("jobs/{id}/tiles"));
    let holds_checkpoints = || std::fs::read_dir(&tiles).is_ok_and(|mut d| d.next().is_some());
    assert!(!holds_checkpoints(), "the first pass wrote checkpoints");
    server.kill9();
    let (mut server, url) = serve(&data, &["--workers", "2", "--lease-seconds", "1"]);
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 12);
    assert_equal(
        &download_exr(&c, &url, &id, &dir),
        &in_process_settings(job),
    );
    server.kill9();

    let (_server, url) = serve(&data, &[]);
    let job = path_traced(8);
    let id = merge_first_pass(&c, &url, &job);
    // One byte of the first record's own part, which the first merge read whole.
    let log = data.join(format!("jobs/{id}/results-0.log"));
    let mut bytes = std::fs::read(&log).expect("the first pass's result log, still kept");
    let sections = u32::from_le_bytes(bytes[80..84].try_into().expect("4 bytes")) as usize;
    bytes[84 + sections * 16 + 4 + 40] ^= 0x10;
    std::fs::write(&log, &bytes).expect("write the log");
    let _w = worker(&url, "w", &[]);
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 8);
    let tasks = 6.0 * 2.0; // 40x32 in tiles of 16, two passes
    assert_eq!(metric(&c, &url, "omis_results_accepted_total"), tasks + 1.0);
    assert_equal(
        &download_exr(&c, &url, &id, &dir),
        &in_process_settings(job),
    );
}

/// Cancelled after a pass merged without checkpoints, a path-traced job's EXR still holds every
/// pass merged: the beauty of its first pass, with the bits of a one-pass render.
#[test]
fn a_path_traced_job_cancelled_after_a_pass_without_checkpoints_keeps_that_pass() {
    let dir = folder("cancel-light");
    let (_server, url) = serve(&dir.join("data"), &["--exr-interval", "3600"]);
    let c = http();
    let id = merge_first_pass(&c, &url, &path_traced(8));
    let (s, v) = post(&c, &format!("{url}/v1/jobs/{id}/cancel"), &json!({}));
    assert_eq!(s, 200, "{v}");
    assert_equal(
        &download_exr(&c, &url, &id, &dir),
        &in_process_settings(path_traced(4)),
    );
}

/// The third pass of a path-traced job writes the log its first pass wrote, while the merge of the
/// second still reads the first pass's results from it: they go after them, and nothing is
/// rendered twice.
#[test]
fn a_pass_that_shares_a_log_with_results_still_read_leaves_them_whole() {
    let dir = folder("shared-log");
    let (_server, url) = serve(&dir.join("data"), &[]);
    let c = http();
    let job = path_traced(12);
    let id = merge_first_pass(&c, &url, &job);
    let w = register(&c, &url, "manual2");
    let render = |t: &Value| upload(&c, &url, t, &w, tile_result_of(&job, &t["task"], 7));
    // One task of the second pass held back until every task of the third is in (the first
    // worker may have rendered some of the second pass's already).
    let held = lease(&c, &url, &w);
    assert_eq!(held["task"]["pass"], 1, "{held}");
    let mut third = 0;
    while third < 6 {
        let t = lease(&c, &url, &w);
        assert_eq!(t["task"]["kind"], "render", "{t}");
        third += (t["task"]["pass"] == 2) as usize;
        assert_eq!(render(&t), 200);
    }
    assert_eq!(render(&held), 200);
    let start = Instant::now();
    while get_json(&c, &format!("{url}/v1/jobs/{id}"))["state"] != "done" {
        assert!(start.elapsed() < WAIT, "the job did not end");
        // 204 once nothing is left to lease.
        let (_, t) = post(
            &c,
            &format!("{url}/v1/worker/lease"),
            &json!({ "worker_id": w, "wait_s": 1 }),
        );
        match t["task"]["kind"].as_str() {
            Some("merge") => assert_eq!(merge_task(&c, &url, &t, &w), 200),
            Some(_) => assert_eq!(render(&t), 200),
            None => {}
        }
    }
    assert_eq!(metric(&c, &url, "omis_results_accepted_total"), 18.0);
    assert_equal(
        &download_exr(&c, &url, &id, &dir),
        &in_process_settings(job),
    );
}

#[test]
fn a_tile_checkpoint_torn_mid_write_falls_back_to_the_previous_pass() {
    let dir = folder("torn");
    let data = dir.join("data");
    let (_server, url) = serve(&data, &[]);
    let c = http();
    let (id, band, mut bytes, len) = first_pass_merged(&c, &url, &data);
    // Tile 0 holds pass 1 in its slot 1. What a crash in the middle of writing pass 2 into its
    // slot 0 leaves: a checkpoint that claims 2 passes, torn (one byte of its sums differs).
    let mut torn = bytes[len..2 * len].to_vec();
    torn[28..32].copy_from_slice(&2u32.to_le_bytes()); // passes
    torn[len / 2] ^= 0x10;
    bytes[..len].copy_from_slice(&torn);
    std::fs::write(&band, &bytes).expect("write the checkpoints");
    // The merge of pass 2 passes over the torn slot and merges tile 0 from pass 1.
    let _w = worker(&url, "w", &[]);
    let st = wait_state(&c, &url, &id, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 8);
    assert_equal(&download_exr(&c, &url, &id, &dir), &in_process(8));
}

#[test]
fn a_merge_that_cannot_read_its_checkpoints_fails_the_job_and_the_coordinator_keeps_serving() {
    let dir = folder("unreadable");
    let data = dir.join("data");
    let (_server, url) = serve(&data, &[]);
    let c = http();
    let (id, band, mut bytes, len) = first_pass_merged(&c, &url, &data);
    // Both slots of tile 0 damaged (as a data folder of another version would read): the merge
    // of pass 2 cannot continue the tile.
    bytes[len / 2] ^= 0x10;
    bytes[len + len / 2] ^= 0x10;
    std::fs::write(&band, &bytes).expect("write the checkpoints");
    let _w = worker(&url, "w", &[]);
    let st = wait_state(&c, &url, &id, |s| s["state"] == "failed");
    assert!(
        st["error"]
            .as_str()
            .unwrap_or("")
            .contains("tile checkpoint 0"),
        "{st}"
    );
    // The failure released the store: the coordinator answers and finishes the next job.
    let next = submit(&c, &url, 4);
    let st = wait_state(&c, &url, &next, |s| s["state"] == "done");
    assert_eq!(st["spp_done"], 4);
}
