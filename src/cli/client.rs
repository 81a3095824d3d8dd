//! HTTP client of the coordinator's API, for `submit`, `status`, `download`, `cancel`, the job
//! controls (`jobs`, `pause`, `resume`, ...) and the embedded service behind `omis render`.

use crate::bundle;
use crate::job::frames::{self as job_frames, FrameRange};
use crate::protocol::{
    ErrorBody, EventKind, JobEvent, JobList, JobPatch, JobRequest, JobState, JobStatus,
    ReferenceInfo, SceneMeta, SceneSource, WorkerList,
};
use crate::scene::SceneParams;
use anyhow::{Context, Result, bail};
use std::path::Path;
use std::time::Duration;

/// A client of one coordinator (client token).
pub(crate) struct Client {
    base: String,
    token: Option<String>,
    http: reqwest::Client,
}

impl Client {
    /// A client of the coordinator at `base` (an http:// URL).
    pub(crate) fn new(base: &str, token: Option<String>) -> Result<Client> {
        let base = base.trim_end_matches('/').to_string();
        check_url(&base, "--server")?;
        // Pooled connections are given up before the coordinator closes them as idle.
        let http = reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(5))
            .pool_idle_timeout(Duration::from_secs(4))
            .build()
            .context("cannot create the HTTP client")?;
        Ok(Client { base, token, http })
    }

    fn req(&self, method: reqwest::Method, path: &str) -> reqwest::RequestBuilder {
        let r = self.http.request(method, format!("{}{path}", self.base));
        match &self.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }

    /// Sends and turns a non-2xx answer into the server's error message.
    async fn send(&self, r: reqwest::RequestBuilder, what: &str) -> Result<reqwest::Response> {
        let r = r
            .send()
            .await
            .with_context(|| format!("{what}: cannot reach {}", self.base))?;
        if r.status().is_success() {
            return Ok(r);
        }
        let status = r.status();
        let text = r.text().await.unwrap_or_default();
        let msg = match serde_json::from_str::<ErrorBody>(&text) {
            Ok(ErrorBody {
                error,
                field: Some(f),
            }) => format!("{error} ({f})"),
            Ok(ErrorBody { error, field: None }) => error,
            Err(_) => text,
        };
        bail!("{what}: HTTP {}: {msg}", status.as_u16())
    }

    async fn json<T: serde::de::DeserializeOwned>(
        &self,
        r: reqwest::RequestBuilder,
        what: &str,
    ) -> Result<T> {
        self.send(r, what)
            .await?
            .json()
            .await
            .with_context(|| format!("{what}: bad JSON answer"))
    }

    /// Uploads a scene file and everything it reads (with the parameter values `params`) as a
    /// bundle; returns the bundle id.
    pub(crate) async fn upload_scene(&self, scene: &Path, params: &SceneParams) -> Result<String> {
        let s = scene.to_path_buf();
        let params = params.clone();
        let (tar, main) = tokio::task::spawn_blocking(move || bundle::pack(&s, &params)).await??;
        self.upload_bundle(tar, main).await
    }

    /// Uploads the scene files of `frames` of frame pattern `pattern` (`frame_####.xml`) and
    /// everything they read as one bundle whose main file is the pattern; returns the bundle id.
    pub(crate) async fn upload_frames(
        &self,
        pattern: &Path,
        frames: FrameRange,
        params: &SceneParams,
    ) -> Result<String> {
        let pattern = pattern.to_path_buf();
        let params = params.clone();
        let (tar, main) =
            tokio::task::spawn_blocking(move || super::bundle::sequence(&pattern, frames, &params))
                .await??;
        self.upload_bundle(tar, main).await
    }

    /// Uploads a bundle made by `bundle::pack`; returns its id.
    pub(crate) async fn upload_bundle(&self, tar: Vec<u8>, main: String) -> Result<String> {
        let meta: SceneMeta = self
            .json(
                self.req(reqwest::Method::POST, "/v1/scenes")
                    .query(&[("main", main)])
                    .header("content-type", "application/x-tar")
                    .body(tar),
                "uploading the scene",
            )
            .await?;
        Ok(meta.id)
    }

    /// Uploads a reference EXR; returns its id.
    pub(crate) async fn upload_reference(&self, exr: &Path) -> Result<String> {
        let bytes = tokio::fs::read(exr)
            .await
            .with_context(|| format!("{}", exr.display()))?;
        let info: ReferenceInfo = self
            .json(
                self.req(reqwest::Method::POST, "/v1/references")
                    .header("content-type", "image/x-exr")
                    .body(bytes),
                "uploading the reference",
            )
            .await?;
        Ok(info.id)
    }

    /// GET `path` of the API; its JSON answer (`what` names it in errors).
    pub(crate) async fn get_json<T: serde::de::DeserializeOwned>(
        &self,
        path: &str,
        query: &[(&str, String)],
        what: &str,
    ) -> Result<T> {
        self.json(self.req(reqwest::Method::GET, path).query(query), what)
            .await
    }

    /// `method` (POST, DELETE) on `path` of the API without a body; its JSON answer.
    pub(crate) async fn act<T: serde::de::DeserializeOwned>(
        &self,
        method: reqwest::Method,
        path: &str,
        what: &str,
    ) -> Result<T> {
        self.json(self.req(method, path), what).await
    }

    /// Submits a job; returns its status document.
    pub(crate) async fn submit(&self, request: &JobRequest) -> Result<JobStatus> {
        self.json(
            self.req(reqwest::Method::POST, "/v1/jobs").json(request),
            "submitting the job",
        )
        .await
    }

    /// A job's status document.
    pub(crate) async fn status(&self, id: &str) -> Result<JobStatus> {
        self.json(
            self.req(reqwest::Method::GET, &format!("/v1/jobs/{id}")),
            "job status",
        )
        .await
    }

    /// Cancels a job; returns its status document.
    pub(crate) async fn cancel(&self, id: &str) -> Result<JobStatus> {
        self.json(
            self.req(reqwest::Method::POST, &format!("/v1/jobs/{id}/cancel")),
            "cancelling",
        )
        .await
    }

    /// POST /v1/jobs/{id}/{action} (pause, resume, requeue, retry); the job's status after it
    /// (a retry's: the new job's).
    pub(crate) async fn job_action(&self, id: &str, action: &str) -> Result<JobStatus> {
        self.json(
            self.req(reqwest::Method::POST, &format!("/v1/jobs/{id}/{action}")),
            action,
        )
        .await
    }

    /// Sets a job's priority; returns its status document.
    pub(crate) async fn set_priority(&self, id: &str, priority: i32) -> Result<JobStatus> {
        self.json(
            self.req(reqwest::Method::PATCH, &format!("/v1/jobs/{id}"))
                .json(&JobPatch { priority }),
            "setting the priority",
        )
        .await
    }

    /// Deletes a job that has ended, with its files.
    pub(crate) async fn delete(&self, id: &str) -> Result<()> {
        self.send(
            self.req(reqwest::Method::DELETE, &format!("/v1/jobs/{id}")),
            "deleting",
        )
        .await?;
        Ok(())
    }

    /// Every job `query` selects (GET /v1/jobs, its pages followed), oldest first.
    pub(crate) async fn jobs(&self, query: &[(&str, String)]) -> Result<Vec<JobStatus>> {
        let mut all = Vec::new();
        let mut after: Option<String> = None;
        loop {
            let mut q: Vec<(&str, String)> = query.to_vec();
            if let Some(a) = &after {
                q.push(("after", a.clone()));
            }
            let page: JobList = self
                .json(
                    self.req(reqwest::Method::GET, "/v1/jobs").query(&q),
                    "listing jobs",
                )
                .await?;
            all.extend(page.jobs);
            match page.next {
                Some(n) if after.as_ref() != Some(&n) => after = Some(n),
                _ => return Ok(all),
            }
        }
    }

    /// Every worker the coordinator knows.
    pub(crate) async fn workers(&self) -> Result<WorkerList> {
        self.json(
            self.req(reqwest::Method::GET, "/v1/workers"),
            "listing workers",
        )
        .await
    }

    /// Downloads a job's file (image.exr, preview.png, ...) to `out`.
    pub(crate) async fn download(&self, id: &str, file: &str, out: &Path) -> Result<usize> {
        self.download_frame(id, file, None, out).await
    }

    /// Downloads a job's file (image.exr, preview.png, ...), of frame `frame` of a sequence
    /// when given, to `out`.
    pub(crate) async fn download_frame(
        &self,
        id: &str,
        file: &str,
        frame: Option<u32>,
        out: &Path,
    ) -> Result<usize> {
        let mut req = self.req(reqwest::Method::GET, &format!("/v1/jobs/{id}/{file}"));
        if let Some(f) = frame {
            req = req.query(&[("frame", f)]);
        }
        let r = self.send(req, "downloading").await?;
        let bytes = r.bytes().await.context("downloading")?;
        tokio::fs::write(out, &bytes)
            .await
            .with_context(|| format!("{}", out.display()))?;
        Ok(bytes.len())
    }

    /// Downloads file `file` of every frame of sequence `st` to `out`: a pattern
    /// (`out_####.exr`), or a folder (made if needed) that gets `frame_####.<ext>`. Returns the
    /// files written.
    pub(crate) async fn download_frames(
        &self,
        st: &JobStatus,
        file: &str,
        out: &Path,
    ) -> Result<Vec<std::path::PathBuf>> {
        let frames = st.frames.as_deref().unwrap_or_default();
        let pattern = frame_pattern(out, file)?;
        let mut written = Vec::with_capacity(frames.len());
        for f in frames {
            let path: std::path::PathBuf = job_frames::frame_file(&pattern, f.frame)
                .with_context(|| format!("{pattern}: not a frame pattern"))?
                .into();
            self.download_frame(&st.id, file, Some(f.frame), &path)
                .await?;
            written.push(path);
        }
        Ok(written)
    }

    /// Follows a job's events until it ends; calls `on_event` for each (events of kinds this
    /// build does not know are skipped). Reconnects (with Last-Event-ID) when the stream
    /// breaks. Returns the job's final state.
    pub(crate) async fn follow(
        &self,
        id: &str,
        mut on_event: impl FnMut(&JobEvent),
    ) -> Result<JobState> {
        let mut last_id: Option<String> = None;
        let mut failures = 0;
        loop {
            let mut r = self.req(reqwest::Method::GET, &format!("/v1/jobs/{id}/events"));
            if let Some(l) = &last_id {
                r = r.header("last-event-id", l);
            }
            let resp = match self.send(r, "following the job").await {
                Ok(resp) => resp,
                Err(e) if failures < 30 => {
                    failures += 1;
                    tracing::warn!("{e:#}; retrying");
                    tokio::time::sleep(Duration::from_secs(1)).await;
                    continue;
                }
                Err(e) => return Err(e),
            };
            let mut resp = resp;
            let mut buf = String::new();
            let mut kind = String::new();
            let mut data = String::new();
            loop {
                let chunk = match resp.chunk().await {
                    Ok(Some(c)) => c,
                    Ok(None) | Err(_) => break,
                };
                failures = 0;
                buf.push_str(&String::from_utf8_lossy(&chunk));
                while let Some(nl) = buf.find('\n') {
                    let line = buf[..nl].trim_end_matches('\r').to_string();
                    buf.drain(..=nl);
                    if line.is_empty() {
                        if let Ok(k) = kind.parse::<EventKind>() {
                            let event = serde_json::from_str(&data)
                                .ok()
                                .and_then(|d| JobEvent::parse(k, d).ok());
                            if let Some(e) = &event {
                                on_event(e);
                            }
                            if let Some(state) = final_state(k) {
                                return Ok(state);
                            }
                        }
                        kind.clear();
                        data.clear();
                    } else if let Some(v) = line.strip_prefix("event:") {
                        kind = v.trim().to_string();
                    } else if let Some(v) = line.strip_prefix("data:") {
                        data.push_str(v.trim_start());
                    } else if let Some(v) = line.strip_prefix("id:") {
                        last_id = Some(v.trim().to_string());
                    }
                }
            }
            // The stream ended without a final event: ask for the state, then reconnect.
            let st = self.status(id).await?;
            if !st.state.is_active() {
                return Ok(st.state);
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }
}

/// Where the frames of a sequence's `file` go for `--out out`: `out` itself when it is a
/// pattern with a run of `#`, else `frame_####.<ext of file>` in folder `out` (made here).
pub(crate) fn frame_pattern(out: &Path, file: &str) -> Result<String> {
    let text = out.to_string_lossy().into_owned();
    if job_frames::is_pattern(&text) {
        job_frames::validate_pattern(&text, "--out").map_err(|e| anyhow::anyhow!("{e}"))?;
        return Ok(text);
    }
    std::fs::create_dir_all(out).with_context(|| {
        format!(
            "{text}: a sequence is written as one file per frame: give a pattern \
             (out_####.exr) or a folder"
        )
    })?;
    let ext = Path::new(file)
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("exr");
    Ok(out
        .join(format!("frame_####.{ext}"))
        .to_string_lossy()
        .into_owned())
}

/// Refuses what this build cannot reach: only plain http:// (no TLS is built in; put a TLS
/// proxy in front of a coordinator that must be reached over an untrusted network).
pub(crate) fn check_url(url: &str, flag: &str) -> Result<()> {
    if url.starts_with("https://") {
        bail!(
            "{flag} '{url}': https is not built into omis; use http:// on a private network or a TLS-terminating proxy"
        );
    }
    if !url.starts_with("http://") {
        bail!("{flag} '{url}' is not an http:// URL");
    }
    Ok(())
}

/// The job state a terminal event kind stands for.
fn final_state(kind: EventKind) -> Option<JobState> {
    match kind {
        EventKind::Done => Some(JobState::Done),
        EventKind::Failed => Some(JobState::Failed),
        EventKind::Cancelled => Some(JobState::Cancelled),
        _ => None,
    }
}

/// The job request for a scene argument: an existing file is uploaded as a bundle, anything
/// else names a scene of the server's library.
pub(crate) async fn scene_source(
    client: &Client,
    scene: &str,
    params: &SceneParams,
) -> Result<SceneSource> {
    let p = Path::new(scene);
    if p.is_file() {
        Ok(SceneSource::Bundle(client.upload_scene(p, params).await?))
    } else if p.components().count() == 1 && !scene.contains('.') || scene.starts_with("library:") {
        Ok(SceneSource::Library(
            scene.trim_start_matches("library:").to_string(),
        ))
    } else {
        bail!("{scene}: no such scene file (a bare name is looked up in the server's library)")
    }
}
