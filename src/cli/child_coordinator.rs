//! A coordinator started as a child process (`omis serve` on a free loopback port), so that a
//! benchmark measures its CPU, memory and I/O alone, from /proc.

use anyhow::{Context, Result};
use std::path::Path;

/// A running `omis serve` child.
pub struct ChildCoordinator {
    child: std::process::Child,
    /// Its process id (for /proc).
    pub pid: u32,
    /// `http://` and the address it printed.
    pub url: String,
}

impl ChildCoordinator {
    /// Starts this binary's `serve` on 127.0.0.1:0 with `data` and `workers` local workers, and
    /// waits for the address it prints.
    pub fn start(data: &Path, workers: usize) -> Result<ChildCoordinator> {
        use std::io::BufRead;
        let mut child = std::process::Command::new(std::env::current_exe()?)
            .args(["serve", "--bind", "127.0.0.1:0", "--data"])
            .arg(data)
            .args(["--workers", &workers.to_string()])
            .env("OMIS_LOG", "warn")
            .stdout(std::process::Stdio::piped())
            .spawn()?;
        let pid = child.id();
        let stdout = child.stdout.take().context("coordinator stdout")?;
        let mut line = String::new();
        std::io::BufReader::new(stdout).read_line(&mut line)?;
        let url = line
            .trim()
            .strip_prefix("listening on ")
            .context("the coordinator did not print its address")?
            .to_string();
        Ok(ChildCoordinator { child, pid, url })
    }

    /// Stops it with SIGTERM (its workers drain) and waits for it.
    pub fn stop(mut self) {
        // SAFETY: kill(2) on our own child.
        unsafe {
            libc::kill(self.pid as libc::pid_t, libc::SIGTERM);
        }
        let _ = self.child.wait();
    }
}
