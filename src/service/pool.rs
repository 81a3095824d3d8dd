//! A local pool: N `omis worker` processes on this machine, each restarted when it dies.

use super::{App, Metrics};
use std::sync::Arc;
use std::time::Duration;
use tokio::process::Command;
use tokio::sync::watch;

pub struct Pool {
    stop: watch::Sender<bool>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Pool {
    pub fn spawn(app: Arc<App>, url: &str) -> Pool {
        let (stop, rx) = watch::channel(false);
        let exe = std::env::current_exe();
        let tasks = (0..app.cfg.workers)
            .map(|k| {
                let app = app.clone();
                let url = url.to_string();
                let mut rx = rx.clone();
                let exe = exe.as_ref().ok().cloned();
                tokio::spawn(async move {
                    let Some(exe) = exe else {
                        tracing::error!("cannot find the omis executable to start local workers");
                        return;
                    };
                    loop {
                        let mut cmd = Command::new(&exe);
                        cmd.arg("worker")
                            .arg("--coordinator")
                            .arg(&url)
                            .arg("--threads")
                            .arg(app.cfg.worker_threads.to_string())
                            .arg("--name")
                            .arg(format!("local-{k}"))
                            .arg("--exit-with-parent")
                            .args(
                                (!app.cfg.worker_tags.is_empty())
                                    .then(|| ["--tag".to_string(), app.cfg.worker_tags.join(",")])
                                    .into_iter()
                                    .flatten(),
                            )
                            .stdin(std::process::Stdio::null())
                            .kill_on_drop(true);
                        if let Some(l) = &app.cfg.worker_log {
                            cmd.env("OMIS_LOG", l);
                        }
                        if let Some(t) = &app.cfg.worker_token {
                            cmd.env("OMIS_WORKER_TOKEN", t);
                        }
                        let mut child = match cmd.spawn() {
                            Ok(c) => c,
                            Err(e) => {
                                tracing::error!("cannot start local worker {k}: {e}");
                                return;
                            }
                        };
                        tokio::select! {
                            status = child.wait() => {
                                if *rx.borrow() {
                                    return;
                                }
                                // A worker ends cleanly only when drained (by an operator or
                                // a SIGTERM): it was asked to leave, so it stays out.
                                if matches!(&status, Ok(s) if s.success()) {
                                    tracing::info!("local worker {k} drained; not restarted");
                                    return;
                                }
                                tracing::warn!("local worker {k} exited ({status:?}); restarting");
                                Metrics::add(&app.metrics.worker_restarts, 1);
                            }
                            _ = rx.changed() => {
                                // Drain: SIGTERM, then a kill after a grace period.
                                if let Some(pid) = child.id() {
                                    // SAFETY: kill(2) on our own child's pid.
                                    unsafe {
                                        libc::kill(pid as libc::pid_t, libc::SIGTERM);
                                    }
                                }
                                if tokio::time::timeout(Duration::from_secs(10), child.wait())
                                    .await
                                    .is_err()
                                {
                                    let _ = child.kill().await;
                                }
                                return;
                            }
                        }
                        tokio::time::sleep(Duration::from_millis(500)).await;
                    }
                })
            })
            .collect();
        Pool { stop, tasks }
    }

    /// Stops every worker (SIGTERM: they finish and upload their task first).
    pub async fn stop(self) {
        let _ = self.stop.send(true);
        for t in self.tasks {
            let _ = t.await;
        }
    }
}
