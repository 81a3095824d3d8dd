//! Helpers of the tests that run the service as real processes on 127.0.0.1: a coordinator
//! (`omis serve`), workers, and HTTP calls. Every process a test starts is killed (SIGKILL) and
//! reaped when its handle is dropped, also when the test fails.

use reqwest::blocking::Client;
use serde_json::{Value, json};
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// The `omis` binary under test.
pub const EXE: &str = env!("CARGO_BIN_EXE_omis");

/// A child process killed (SIGKILL) and reaped on drop.
pub struct Proc(pub Child);

impl Proc {
    /// Kills and reaps the process now.
    pub fn kill9(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.0.id()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill9();
    }
}

/// `omis serve` on a free loopback port with the repository's scene library; returns the
/// process and its URL.
pub fn serve(data: &Path, extra: &[&str]) -> (Proc, String) {
    serve_command(Command::new(EXE), data, extra, Stdio::inherit())
}

/// `serve` from the command `cmd` (the binary with settings of its own, e.g. limits), its
/// standard error to `stderr`.
pub fn serve_command(
    mut cmd: Command,
    data: &Path,
    extra: &[&str],
    stderr: Stdio,
) -> (Proc, String) {
    let scenes = super::repo().join("scenes");
    let mut child = cmd
        .args(["serve", "--bind", "127.0.0.1:0", "--data"])
        .arg(data)
        .arg("--scenes")
        .arg(&scenes)
        .args(extra)
        .env("OMIS_LOG", "warn")
        .env_remove("OMIS_TOKEN")
        .env_remove("OMIS_CLIENT_TOKEN")
        .env_remove("OMIS_WORKER_TOKEN")
        .stdout(Stdio::piped())
        .stderr(stderr)
        .spawn()
        .expect("start omis serve");
    let stdout = child.stdout.take().expect("stdout");
    let proc = Proc(child);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut lines = BufReader::new(stdout).lines();
        if let Some(Ok(l)) = lines.next() {
            let _ = tx.send(l);
        }
        for _ in lines {}
    });
    let line = rx
        .recv_timeout(Duration::from_secs(60))
        .expect("omis serve printed its address");
    let url = line
        .strip_prefix("listening on ")
        .unwrap_or_else(|| panic!("unexpected first line: {line}"))
        .to_string();
    (proc, url)
}

/// An `omis worker` process of one thread.
pub fn worker(url: &str, name: &str, extra: &[&str]) -> Proc {
    Proc(
        Command::new(EXE)
            .args([
                "worker",
                "--coordinator",
                url,
                "--threads",
                "1",
                "--name",
                name,
            ])
            .args(extra)
            .env("OMIS_LOG", "warn")
            .stdin(Stdio::null())
            .spawn()
            .expect("start omis worker"),
    )
}

/// An HTTP client with a minute's timeout.
pub fn http() -> Client {
    Client::builder()
        .timeout(Duration::from_secs(60))
        .build()
        .expect("client")
}

/// POSTs JSON; the status and the JSON answer (null if none).
pub fn post(c: &Client, url: &str, body: &Value) -> (u16, Value) {
    let r = c.post(url).json(body).send().expect("POST");
    let s = r.status().as_u16();
    (s, r.json().unwrap_or(Value::Null))
}

/// GETs JSON, which must succeed.
pub fn get_json(c: &Client, url: &str) -> Value {
    let r = c.get(url).send().expect("GET");
    assert!(r.status().is_success(), "GET {url}: {}", r.status());
    r.json().expect("JSON")
}

/// Registers a worker through the worker protocol; its id.
pub fn register(c: &Client, url: &str, name: &str) -> String {
    let (s, v) = post(
        c,
        &format!("{url}/v1/worker/register"),
        &json!({ "name": name, "threads": 1 }),
    );
    assert_eq!(s, 200, "{v}");
    v["worker_id"].as_str().expect("id").to_string()
}

/// Asks for a lease, waiting up to `wait_s`; the status and the lease (null on 204).
pub fn try_lease(c: &Client, url: &str, worker: &str, wait_s: f64) -> (u16, Value) {
    post(
        c,
        &format!("{url}/v1/worker/lease"),
        &json!({ "worker_id": worker, "wait_s": wait_s }),
    )
}

/// The peak resident memory of process `pid` so far (VmHWM), in bytes.
pub fn peak_rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("proc status");
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map(|kb| kb * 1024)
        .expect("VmHWM")
}
