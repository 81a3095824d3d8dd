//! A missing or damaged database and a full disk.

use crate::common::service::{EXE, Proc, get_json, http, serve, serve_command};
use crate::support::{folder, healthy, json_scene, small_job, tar_of, upload_bundle};
use reqwest::blocking::Client;
use serde_json::json;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

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
