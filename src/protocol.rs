//! The wire protocol of the render service, in one place: every JSON message between the
//! coordinator and its workers (register, lease, heartbeat, result, failure, deregister), the
//! client-facing documents (job status, lists, uploads, Server-Sent Events), and the states and
//! event kinds the coordinator also stores (as their names: `as_str`; the store's engine
//! converts them, the types here know no SQL). The coordinator (src/service/api), the
//! worker (src/worker) and the HTTP client (src/cli/client.rs) all use these types; the
//! contract they implement is proto/openapi.yaml, and a test checks the enums against it.
//!
//! Requests are strict (`deny_unknown_fields`, as the server has always refused unknown
//! fields); answers are lenient when read, so that a client survives a newer server's extra
//! fields.

use crate::film::Tile;
use crate::job::{JobSettings, Resolved};
use serde::{Deserialize, Serialize};

/// A closed set of lowercase names: serde (lowercase / snake_case), `as_str()` for the
/// database and logs, and parsing back (`FromStr`).
macro_rules! string_enum {
    ($(#[$meta:meta])* $name:ident { $($(#[$vmeta:meta])* $variant:ident = $text:literal,)+ }) => {
        $(#[$meta])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
        #[serde(rename_all = "snake_case")]
        pub enum $name {
            $($(#[$vmeta])* $variant,)+
        }

        impl $name {
            /// Every variant, in declaration order.
            pub const ALL: &'static [$name] = &[$($name::$variant,)+];

            /// The name on the wire and in the database.
            pub const fn as_str(self) -> &'static str {
                match self {
                    $($name::$variant => $text,)+
                }
            }
        }

        impl std::fmt::Display for $name {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.as_str())
            }
        }

        impl std::str::FromStr for $name {
            type Err = String;
            fn from_str(s: &str) -> Result<Self, String> {
                match s {
                    $($text => Ok($name::$variant),)+
                    _ => Err(format!("'{s}' is not a {}", stringify!($name))),
                }
            }
        }
    };
}

string_enum! {
    /// A job's state: `queued` until a task is first leased, `running` (or `paused` by a client
    /// from either), then one of the three final states.
    JobState {
        /// Created; no task leased yet.
        Queued = "queued",
        /// At least one task was leased.
        Running = "running",
        /// Every pass merged: the image is final.
        Done = "done",
        /// Stopped by an error (see the status's `error`).
        Failed = "failed",
        /// Cancelled by a client.
        Cancelled = "cancelled",
        /// Paused by a client: no new leases; tasks in hand finish and are kept. Resuming
        /// returns it to `queued` (no task leased yet) or `running`.
        Paused = "paused",
    }
}

impl JobState {
    /// Not ended (queued, running or paused): the job still has work to do, though a paused
    /// one hands none out.
    pub fn is_active(self) -> bool {
        matches!(
            self,
            JobState::Queued | JobState::Running | JobState::Paused
        )
    }

    /// Done, failed or cancelled: nothing more will happen to the job.
    pub fn is_final(self) -> bool {
        !self.is_active()
    }
}

string_enum! {
    /// A task's state (tasks of merged passes are deleted).
    TaskState {
        /// Waiting for a worker.
        Queued = "queued",
        /// Held by a worker until its lease expires.
        Leased = "leased",
        /// Its result was accepted; waiting for the rest of the pass.
        Done = "done",
    }
}

string_enum! {
    /// What a task does: render a tile's samples of a pass, or merge a finished pass into one
    /// band group of tiles (the coordinator only moves the bytes; see `film::merge_task`).
    TaskKind {
        /// Render samples [s0, s1) of every pixel of a tile; upload a tile result.
        Render = "render",
        /// Merge the pass's results into a band group's tiles; download the input, upload the
        /// group's checkpoints and images.
        Merge = "merge",
    }
}

string_enum! {
    /// A worker's state: `gone` after two lease times without news, `left` after deregistering.
    WorkerState {
        /// Registered, holding no lease.
        Idle = "idle",
        /// Holding at least one lease.
        Busy = "busy",
        /// Deregistered itself.
        Left = "left",
        /// Not heard from within two lease times.
        Gone = "gone",
    }
}

string_enum! {
    /// What an operator allows a worker: lease tasks (`enabled`), lease none while keeping the
    /// tasks in hand (`disabled`), or finish the tasks in hand and exit (`draining`). Kept
    /// across restarts of the coordinator and of the worker.
    WorkerAdmin {
        /// Leases tasks.
        Enabled = "enabled",
        /// Leases nothing; the tasks in hand finish.
        Disabled = "disabled",
        /// Leases nothing; the worker exits once the tasks in hand are finished.
        Draining = "draining",
    }
}

string_enum! {
    /// How an attempt at a task ended (`running` while its lease is held).
    AttemptOutcome {
        /// The lease is held.
        Running = "running",
        /// Its result was accepted.
        Done = "done",
        /// The worker reported an error.
        Failed = "failed",
        /// The worker went silent: the lease expired.
        Expired = "expired",
        /// Taken back without a verdict on the worker: its job ended, it left, or the task was
        /// requeued.
        Cancelled = "cancelled",
        /// Its result was refused as invalid.
        Refused = "refused",
    }
}

/// The most tags a worker or a job may name.
pub const MAX_TAGS: usize = 16;
/// The longest tag, in bytes.
pub const MAX_TAG_LEN: usize = 32;

/// Checks a list of worker tags (`[a-z0-9_-]`, 1 to `MAX_TAG_LEN` long, at most `MAX_TAGS`);
/// the tags sorted, without duplicates, or what is wrong with them.
pub fn validate_tags(tags: &[String]) -> Result<Vec<String>, String> {
    if tags.len() > MAX_TAGS {
        return Err(format!("at most {MAX_TAGS} tags"));
    }
    for t in tags {
        let ok = !t.is_empty()
            && t.len() <= MAX_TAG_LEN
            && t.bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_' || b == b'-');
        if !ok {
            let shown: String = t.chars().take(40).collect();
            return Err(format!(
                "tag '{shown}': 1 to {MAX_TAG_LEN} of a-z, 0-9, '_' and '-'"
            ));
        }
    }
    let mut v = tags.to_vec();
    v.sort();
    v.dedup();
    Ok(v)
}

string_enum! {
    /// The kind of a job event (the SSE `event:` line).
    EventKind {
        /// The job was created.
        Queued = "queued",
        /// A task's result was accepted.
        TileDone = "tile_done",
        /// A pass was merged into the job's image.
        PassDone = "pass_done",
        /// The preview image was rewritten.
        Preview = "preview",
        /// An attempt at a task failed.
        TaskFailed = "task_failed",
        /// The job finished (terminal).
        Done = "done",
        /// The job failed (terminal).
        Failed = "failed",
        /// The job was cancelled (terminal).
        Cancelled = "cancelled",
    }
}

impl EventKind {
    /// The job's last event: `done`, `failed` or `cancelled`.
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            EventKind::Done | EventKind::Failed | EventKind::Cancelled
        )
    }
}

// ---- job events (the `data:` of each SSE event, without `job` and `at`) ----

/// `queued`: the job was created.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QueuedEvent {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Total samples per pixel; None for a time budget without spp.
    pub spp: Option<u32>,
}

/// `tile_done`: a task's result was accepted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileDoneEvent {
    /// The pass index (from 0).
    pub pass: u32,
    /// The tile index in the job's row-major tile order.
    pub tile: u32,
    /// The worker id.
    pub worker: String,
    /// Size of the result.
    pub bytes: u64,
}

/// `pass_done`: a pass was merged.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PassDoneEvent {
    /// The pass index (from 0).
    pub pass: u32,
    /// Samples per pixel merged so far.
    pub spp: u32,
    /// Seconds since the job started.
    pub seconds: f64,
    /// Against the reference; None without one.
    pub relmse: Option<f64>,
}

/// `preview`: preview.png was rewritten after a pass.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PreviewEvent {
    /// The pass index (from 0).
    pub pass: u32,
    /// Samples per pixel merged so far.
    pub spp: u32,
    /// The preview's path, /v1/jobs/{id}/preview.png.
    pub url: String,
}

/// `task_failed`: an attempt failed (reported by its worker, or its result was invalid).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TaskFailedEvent {
    /// The pass index (from 0).
    pub pass: u32,
    /// The tile index in the job's row-major tile order.
    pub tile: u32,
    /// The worker id.
    pub worker: String,
    /// What went wrong.
    pub error: String,
    /// Failed and lost attempts of the task so far.
    pub failures: u32,
    /// Whether this attempt was lost (its worker went silent and the lease expired) rather
    /// than reported failed.
    #[serde(default)]
    pub lost: bool,
}

/// `done` (terminal): the job finished.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DoneEvent {
    /// Samples per pixel of the final image.
    pub spp: u32,
}

/// `failed` (terminal): the job failed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FailedEvent {
    /// Why the job failed.
    pub error: String,
}

/// `cancelled` (terminal): the job was cancelled.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CancelledEvent {}

/// One job event: its kind and its data.
#[derive(Clone, Debug, PartialEq)]
pub enum JobEvent {
    /// See [`QueuedEvent`].
    Queued(QueuedEvent),
    /// See [`TileDoneEvent`].
    TileDone(TileDoneEvent),
    /// See [`PassDoneEvent`].
    PassDone(PassDoneEvent),
    /// See [`PreviewEvent`].
    Preview(PreviewEvent),
    /// See [`TaskFailedEvent`].
    TaskFailed(TaskFailedEvent),
    /// See [`DoneEvent`].
    Done(DoneEvent),
    /// See [`FailedEvent`].
    Failed(FailedEvent),
    /// See [`CancelledEvent`].
    Cancelled(CancelledEvent),
}

impl JobEvent {
    /// The event's kind.
    pub fn kind(&self) -> EventKind {
        match self {
            JobEvent::Queued(_) => EventKind::Queued,
            JobEvent::TileDone(_) => EventKind::TileDone,
            JobEvent::PassDone(_) => EventKind::PassDone,
            JobEvent::Preview(_) => EventKind::Preview,
            JobEvent::TaskFailed(_) => EventKind::TaskFailed,
            JobEvent::Done(_) => EventKind::Done,
            JobEvent::Failed(_) => EventKind::Failed,
            JobEvent::Cancelled(_) => EventKind::Cancelled,
        }
    }

    /// The event's data as a JSON object.
    pub fn data(&self) -> serde_json::Value {
        let v = match self {
            JobEvent::Queued(e) => serde_json::to_value(e),
            JobEvent::TileDone(e) => serde_json::to_value(e),
            JobEvent::PassDone(e) => serde_json::to_value(e),
            JobEvent::Preview(e) => serde_json::to_value(e),
            JobEvent::TaskFailed(e) => serde_json::to_value(e),
            JobEvent::Done(e) => serde_json::to_value(e),
            JobEvent::Failed(e) => serde_json::to_value(e),
            JobEvent::Cancelled(e) => serde_json::to_value(e),
        };
        // Plain structs of numbers and strings always serialise.
        v.unwrap_or(serde_json::Value::Null)
    }

    /// An event from its kind and data (extra fields such as `job` and `at` are ignored).
    pub fn parse(kind: EventKind, data: serde_json::Value) -> Result<JobEvent, serde_json::Error> {
        use serde_json::from_value as de;
        Ok(match kind {
            EventKind::Queued => JobEvent::Queued(de(data)?),
            EventKind::TileDone => JobEvent::TileDone(de(data)?),
            EventKind::PassDone => JobEvent::PassDone(de(data)?),
            EventKind::Preview => JobEvent::Preview(de(data)?),
            EventKind::TaskFailed => JobEvent::TaskFailed(de(data)?),
            EventKind::Done => JobEvent::Done(de(data)?),
            EventKind::Failed => JobEvent::Failed(de(data)?),
            EventKind::Cancelled => JobEvent::Cancelled(de(data)?),
        })
    }
}

/// The `data:` of an SSE event: the event's fields plus the job and when it was recorded.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SseData {
    /// The event's own fields (those of its [`JobEvent`] variant).
    #[serde(flatten)]
    pub fields: serde_json::Map<String, serde_json::Value>,
    /// The job id.
    pub job: String,
    /// When the event was recorded (seconds since the Unix epoch).
    pub at: f64,
}

// ---- client requests and documents ----

/// Where a job's scene comes from: exactly one of `library`, `bundle` or `inline`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "lowercase")]
pub enum SceneSource {
    /// A scene file of the server's library, by name (with or without extension).
    Library(String),
    /// A bundle uploaded with POST /v1/scenes.
    Bundle(String),
    /// A scene in omis's JSON format, inline (meshes inline too): kept as the text sent, not a
    /// tree of values (which takes tens of times the text's memory).
    Inline(Box<serde_json::value::RawValue>),
}

/// A job's reference image: exactly one of `upload` or `job`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "lowercase")]
pub enum ReferenceSource {
    /// An EXR uploaded with POST /v1/references.
    Upload(String),
    /// The image of an earlier job that is done.
    Job(String),
}

/// POST /v1/jobs.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobRequest {
    /// Where the scene comes from.
    pub scene: SceneSource,
    /// Render settings; every omitted field takes its default (see [`JobSettings`]).
    #[serde(default)]
    pub settings: JobSettings,
    /// An image to measure relMSE against, per pass.
    #[serde(default)]
    pub reference: Option<ReferenceSource>,
    /// A label for lists and logs.
    #[serde(default)]
    pub name: Option<String>,
    /// Higher first: workers take the tasks of the job of highest priority, then of the
    /// oldest job within a priority.
    #[serde(default)]
    pub priority: i32,
    /// Worker tags the job needs: only a worker with every one of them gets its tasks.
    #[serde(default)]
    pub require_tags: Vec<String>,
    /// Receivers of this job's final event (`done`, `failed` or `cancelled`), besides the
    /// coordinator's own (`omis serve --webhook`).
    #[serde(default)]
    pub webhooks: Vec<WebhookSpec>,
    /// A sequence: these frames of a bundle whose main file is a frame pattern
    /// (`frame_####.xml`); each frame is a job of its own (a child of this one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames: Option<crate::job::frames::FrameRange>,
}

/// The query of GET /v1/jobs (every field optional; as sent, checked by the coordinator).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct JobListQuery {
    /// Comma-separated job states (any of them).
    pub state: Option<String>,
    /// A substring of the job's name (case-insensitive).
    pub name: Option<String>,
    /// Jobs created at or after this time (seconds since the Unix epoch).
    pub since: Option<String>,
    /// Jobs per page (at most `JobListQuery::MAX_LIMIT`, the default).
    pub limit: Option<String>,
    /// The `next` of the page before.
    pub after: Option<String>,
    /// `true`: list the frames of sequences too (each a job of its own); hidden by default.
    pub include_frames: Option<String>,
}

impl JobListQuery {
    /// The most jobs in one page, and the default.
    pub const MAX_LIMIT: u32 = 500;
}

/// PATCH /v1/jobs/{id}: what to change of a job that has not ended.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobPatch {
    /// The job's new priority (higher first).
    pub priority: i32,
}

/// A webhook receiver of a job (`JobRequest::webhooks`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebhookSpec {
    /// Where the event is POSTed (`http://`).
    pub url: String,
    /// Signs each body: `X-Omis-Signature: sha256=<hex HMAC-SHA256(secret, body)>`. Never shown
    /// back.
    #[serde(default)]
    pub secret: Option<String>,
}

/// The job of a webhook's body: what a receiver needs to act on the event.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WebhookJob {
    /// The job id.
    pub id: String,
    /// The client's label, if it gave one.
    pub name: Option<String>,
    /// The job's state after the event.
    pub state: JobState,
    /// Why the job failed.
    pub error: Option<String>,
    /// The user who submitted it (None: submitted without a user).
    pub owner: Option<String>,
    /// Samples per pixel of the merged passes.
    pub spp_done: u32,
    /// relMSE of the last merged pass against the reference.
    pub relmse: Option<f64>,
    /// Paths of the job's resources (relative to the coordinator's URL).
    pub links: JobLinks,
}

/// The body POSTed to a webhook receiver.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WebhookBody {
    /// `done`, `failed` or `cancelled`.
    pub event: String,
    /// The delivery's id, the same on every attempt (also `X-Omis-Delivery`): a receiver
    /// dedupes on it, since a delivery is made at least once.
    pub delivery_id: String,
    /// The job.
    pub job: WebhookJob,
    /// When the event happened (seconds since the Unix epoch).
    pub at: f64,
}

/// One delivery of a job's event to one receiver (GET /v1/jobs/{id}/webhooks).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WebhookDelivery {
    /// The delivery id (`X-Omis-Delivery`).
    pub id: String,
    /// The event delivered.
    pub event: String,
    /// The receiver.
    pub url: String,
    /// `pending` (being tried), `delivered` (a 2xx answer) or `failed` (every attempt failed).
    pub state: String,
    /// Attempts made so far.
    pub attempts: u32,
    /// When the event happened.
    pub at: f64,
    /// When the next attempt is due (pending deliveries).
    pub next_at: Option<f64>,
    /// The last attempt's HTTP status, if it got an answer.
    pub last_status: Option<u16>,
    /// The last attempt's error (no answer, or not 2xx).
    pub last_error: Option<String>,
    /// When a 2xx answer came.
    pub delivered_at: Option<f64>,
}

/// GET /v1/jobs/{id}/webhooks.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WebhookDeliveryList {
    /// The job's deliveries, oldest first.
    pub deliveries: Vec<WebhookDelivery>,
}

/// A user's role: an admin may act on every job and on workers; a user on its own jobs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// May act on every job and worker.
    Admin,
    /// May read everything, act on its own jobs.
    User,
}

/// GET /v1/whoami: whom the client token stands for.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Whoami {
    /// The user's name (`admin` for the single client token, or without one).
    pub name: String,
    /// The user's role.
    pub role: Role,
}

/// One point of a job's relMSE series (one per merged pass).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SeriesPoint {
    /// The pass index (from 0).
    pub pass: u32,
    /// Samples per pixel merged after this pass.
    pub spp: u32,
    /// Seconds since the job started when the pass was merged.
    pub seconds: f64,
    /// Against the reference; None without one.
    pub relmse: Option<f64>,
}

/// A job's scene bundle and the scene file inside it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneRef {
    /// The bundle id.
    pub id: String,
    /// The scene file inside the bundle.
    pub main: String,
}

/// Paths of a job's resources.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobLinks {
    #[serde(rename = "self")]
    /// This job's status document.
    pub self_: String,
    /// Its Server-Sent Events stream.
    pub events: String,
    /// The image so far (OpenEXR).
    pub image: String,
    /// The tone-mapped preview (PNG).
    pub preview: String,
    /// The error image against the reference (PNG).
    pub error: String,
    /// The relMSE-over-time plot (SVG).
    pub convergence: String,
}

impl JobLinks {
    /// The links of job `id`.
    pub fn of(id: &str) -> JobLinks {
        JobLinks {
            self_: format!("/v1/jobs/{id}"),
            events: format!("/v1/jobs/{id}/events"),
            image: format!("/v1/jobs/{id}/image.exr"),
            preview: format!("/v1/jobs/{id}/preview.png"),
            error: format!("/v1/jobs/{id}/error.png"),
            convergence: format!("/v1/jobs/{id}/convergence.svg"),
        }
    }
}

/// The status document of a job (GET /v1/jobs/{id}, and the answer of create and cancel).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobStatus {
    /// The job id (a UUID).
    pub id: String,
    /// The client's label, if it gave one.
    pub name: Option<String>,
    /// Where the job is in its life.
    pub state: JobState,
    /// Why the job failed.
    pub error: Option<String>,
    /// The user who submitted it (None: submitted without a user, anyone's to act on is an
    /// admin's).
    #[serde(default)]
    pub owner: Option<String>,
    /// The job's own webhook receivers (their secrets are not shown).
    #[serde(default)]
    pub webhooks: Vec<String>,
    /// The scene bundle rendered.
    pub scene: SceneRef,
    /// The request's settings with every field filled in.
    pub settings: JobSettings,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Total samples per pixel: the job's, or the one its time budget's last pass was fitted to
    /// once it is planned; None while a time budget alone ends the job.
    pub spp_target: Option<u32>,
    /// Wall-clock budget in seconds, if the job has one.
    pub time_budget_s: Option<f64>,
    /// Samples per pixel of the merged passes.
    pub spp_done: u32,
    /// Passes merged.
    pub passes_done: u32,
    /// Passes in the job; None for a time budget without spp.
    pub passes_total: Option<u32>,
    /// Tasks (tiles) in each pass.
    pub tiles_per_pass: u32,
    /// Finished tiles of passes not merged yet; 0 once the job has ended.
    pub tiles_done: u32,
    /// When the job was created (seconds since the Unix epoch).
    pub created_at: f64,
    /// When its first task was leased.
    pub started_at: Option<f64>,
    /// When it reached a final state.
    pub finished_at: Option<f64>,
    /// Seconds of rendering from the first lease to the end (or to now), time paused left
    /// out; 0 before the first lease.
    pub elapsed_s: f64,
    /// Estimated seconds left; 0 once the job has ended; None while paused or unknown.
    pub eta_s: Option<f64>,
    /// relMSE of the last merged pass against the reference.
    pub relmse: Option<f64>,
    /// One point per merged pass.
    pub series: Vec<SeriesPoint>,
    /// Size of the job's accumulators (the merged film), in bytes.
    pub accum_bytes: i64,
    /// [`accum_bytes`](Self::accum_bytes) per image pixel.
    pub accum_bytes_per_pixel: i64,
    /// Bytes of task results received.
    pub result_bytes: i64,
    /// Camera samples merged.
    pub samples: i64,
    /// Rays traced for the merged samples.
    pub rays: i64,
    /// Samples discarded because they were NaN or infinite.
    pub non_finite_samples: i64,
    /// Whether the job has a reference image.
    pub has_reference: bool,
    /// Optimal MIS: the largest depth weighted optimally (D_opt; 0: balance at every depth).
    pub optimal_max_depth: Option<u32>,
    /// Optimal MIS with `optimal_max_depth` left unset: what the pilot measured and chose.
    pub optimal_depth: Option<crate::job::optimal_depth::DepthChoice>,
    /// Paths of the job's resources.
    pub links: JobLinks,
    /// Higher first (see [`JobRequest::priority`]).
    #[serde(default)]
    pub priority: i32,
    /// Seconds the job has spent paused (or failed before a requeue): not counted in
    /// `elapsed_s` nor against a time budget.
    #[serde(default)]
    pub paused_s: f64,
    /// The job this one retries (POST /v1/jobs/{id}/retry).
    #[serde(default)]
    pub retry_of: Option<String>,
    /// Worker tags the job needs.
    #[serde(default)]
    pub require_tags: Vec<String>,
    /// Workers that get none of its tasks any more (they failed several).
    #[serde(default)]
    pub blocklisted_workers: Vec<BlocklistEntry>,
    /// Why an active job gets no worker (e.g. no live worker has its tags), or null.
    #[serde(default)]
    pub waiting_for: Option<String>,
    /// A sequence: its frames in order, each a job of its own. The counts above (spp, passes,
    /// tiles, samples, bytes) are then sums over the frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames: Option<Vec<FrameStatus>>,
    /// A frame of a sequence: the sequence's job id.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parent: Option<String>,
    /// A frame of a sequence: its frame number.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<u32>,
}

/// One frame of a sequence job, as its status lists it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FrameStatus {
    /// The frame number.
    pub frame: u32,
    /// The frame's own job.
    pub job_id: String,
    /// The frame's state.
    pub state: JobState,
    /// Samples per pixel merged.
    pub spp_done: u32,
    /// Passes merged.
    pub passes_done: u32,
    /// Why the frame failed.
    pub error: Option<String>,
    /// Seconds from its first lease to its end (or to now).
    pub elapsed_s: f64,
}

/// A worker blocklisted for a job.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BlocklistEntry {
    /// The worker id.
    pub worker_id: String,
    /// Since when (seconds since the Unix epoch).
    pub since: f64,
    /// Why: the tasks it failed and the last error.
    pub reason: String,
}

/// GET /v1/jobs: one page of the jobs that match the query, oldest first.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobList {
    /// The page's jobs, oldest first.
    pub jobs: Vec<JobStatus>,
    /// The `after` of the next page; None on the last.
    #[serde(default)]
    pub next: Option<String>,
}

/// Metadata of a stored scene bundle (the answer of POST /v1/scenes).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneMeta {
    /// The bundle id, for `{"scene": {"bundle": id}}`.
    pub id: String,
    /// The scene file inside the bundle.
    pub main: String,
    /// Relative paths of the bundle's files.
    pub files: Vec<String>,
    /// Size of the archive.
    pub bytes: u64,
    /// Triangles of the scene.
    pub triangles: usize,
    /// The scene camera's resolution.
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// What the importer could not represent exactly.
    pub warnings: Vec<String>,
}

/// The query of POST /v1/scenes.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneUploadQuery {
    /// The scene file inside the archive, or a frame pattern (`frame_####.xml`) for a
    /// sequence's bundle.
    pub main: Option<String>,
}

/// The query of a job's images (GET /v1/jobs/{id}/image.exr, preview.png).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ImageQuery {
    /// The frame of a sequence (required for one; refused for a single-frame job).
    pub frame: Option<u32>,
}

/// GET /v1/scenes: the library's scene names.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneLibrary {
    /// Scene files of the library, by name.
    pub library: Vec<String>,
}

/// The answer of POST /v1/references.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ReferenceInfo {
    /// The reference id, for `{"reference": {"upload": id}}`.
    pub id: String,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
}

/// A registered worker (GET /v1/workers).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WorkerInfo {
    /// The worker id.
    pub id: String,
    /// The name it registered with (by default its host name and pid).
    pub name: String,
    /// Render threads it runs.
    pub threads: u32,
    /// Its crate version.
    pub version: String,
    /// When it registered (seconds since the Unix epoch).
    pub registered_at: f64,
    /// When it was last heard from.
    pub last_seen: f64,
    /// Its state.
    pub state: WorkerState,
    /// Tasks whose result it delivered.
    pub tasks_done: i64,
    /// Why it leases no task (it failed tasks of several jobs since its last result), or null
    /// when it is healthy.
    #[serde(default)]
    pub unhealthy: Option<String>,
    /// Jobs that give it no task any more: it failed several of their tasks.
    #[serde(default)]
    pub blocklisted_jobs: Vec<String>,
    /// The tasks it holds a lease on now.
    #[serde(default)]
    pub tasks: Vec<WorkerTask>,
    /// The tags it registered with.
    #[serde(default)]
    pub tags: Vec<String>,
    /// What an operator allows it.
    #[serde(default = "enabled")]
    pub admin: WorkerAdmin,
}

fn enabled() -> WorkerAdmin {
    WorkerAdmin::Enabled
}

/// One attempt at a task (GET /v1/jobs/{id}/tasks, GET /v1/workers/{id}/tasks).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TaskAttempt {
    /// The task id.
    pub task_id: i64,
    /// The job the task belongs to.
    pub job_id: String,
    /// Render or merge.
    pub kind: TaskKind,
    /// The pass index (from 0).
    pub pass: u32,
    /// The tile index (a merge task: its band group).
    pub tile: u32,
    /// The attempt number (from 1).
    pub attempt: u32,
    /// The worker that held it.
    pub worker_id: String,
    /// When it was leased.
    pub leased_at: f64,
    /// When it ended; null while running.
    pub ended_at: Option<f64>,
    /// How it ended.
    pub outcome: AttemptOutcome,
    /// What went wrong (failed, expired, refused, cancelled).
    pub error: Option<String>,
    /// Seconds from lease to end.
    pub seconds: Option<f64>,
}

/// A page of task attempts: failed ones first, then by lease time.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TaskAttemptList {
    /// The attempts of this page.
    pub attempts: Vec<TaskAttempt>,
    /// The `after` of the next page; null on the last one.
    pub next: Option<u32>,
}

/// The query of the task-history routes.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskAttemptQuery {
    /// Only attempts that ended so.
    #[serde(default)]
    pub outcome: Option<AttemptOutcome>,
    /// Attempts per page (default 100, at most 1000).
    #[serde(default)]
    pub limit: Option<u32>,
    /// Attempts of earlier pages to skip (the previous page's `next`).
    #[serde(default)]
    pub after: Option<u32>,
}

/// The answer of the worker admin routes (disable, enable, drain, clearing the unhealthy mark).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WorkerAdminAnswer {
    /// The worker id.
    pub worker_id: String,
    /// What an operator allows it now.
    pub admin: WorkerAdmin,
    /// Why it leases nothing, or null when it is healthy.
    pub unhealthy: Option<String>,
}

/// A task a worker holds a lease on (GET /v1/workers).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WorkerTask {
    /// The task id.
    pub id: i64,
    /// Render or merge.
    pub kind: TaskKind,
    /// The job the task belongs to.
    pub job_id: String,
    /// The pass index (from 0).
    pub pass: u32,
    /// The tile index in the job's row-major tile order (a merge task: its band group).
    pub tile: u32,
    /// The attempt number (from 1).
    pub attempt: u32,
}

/// GET /v1/workers.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WorkerList {
    /// Every worker the coordinator knows.
    pub workers: Vec<WorkerInfo>,
}

/// GET /healthz.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Health {
    /// Always `ok`.
    pub status: String,
    /// The server's crate version.
    pub version: String,
}

/// Every error of the API: what went wrong, and the field, parameter or header it is about.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ErrorBody {
    /// What went wrong.
    pub error: String,
    /// The request field, query parameter or header at fault, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
}

// ---- the worker protocol (/v1/worker/*) ----

/// POST /v1/worker/register.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterRequest {
    /// The worker's name (by default its host name and pid).
    pub name: String,
    /// Render threads it will run.
    pub threads: u32,
    /// Its crate version.
    #[serde(default)]
    pub version: String,
    /// A previous id, to keep it across reconnects.
    #[serde(default)]
    pub id: Option<String>,
    /// Its tags (`[a-z0-9_-]`, at most 16): jobs that require tags go only to workers with them.
    #[serde(default)]
    pub tags: Vec<String>,
}

/// The answer of POST /v1/worker/register.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Registration {
    /// The id to send with every later request.
    pub worker_id: String,
    /// How long a lease lasts without a heartbeat.
    pub lease_seconds: f64,
    /// How often to send heartbeats.
    pub heartbeat_seconds: f64,
}

/// POST /v1/worker/lease.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LeaseRequest {
    /// The id from [`Registration`].
    pub worker_id: String,
    /// Long-poll up to this many seconds (at most 30).
    #[serde(default)]
    pub wait_s: Option<f64>,
}

/// The task of a lease.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LeasedTask {
    /// The task id.
    pub id: i64,
    /// Send it back with the result, a failure or a heartbeat.
    pub attempt: u32,
    /// Render or merge (a worker of an older version only renders; absent means render).
    #[serde(default = "render_kind")]
    pub kind: TaskKind,
    /// The job the task belongs to.
    pub job_id: String,
    /// The pass index (from 0).
    pub pass: u32,
    /// Render: index of the tile in the job's row-major tile order. Merge: index of the band
    /// group in the pass's merge.
    pub tile: u32,
    /// Render: the tile's pixel rectangle. Merge: the band group's rectangle.
    pub rect: Tile,
    /// The sample range [s0, s1) of the pass.
    pub samples: [u32; 2],
    /// Merge: the band group (rows of tiles) [b0, b1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bands: Option<[u32; 2]>,
}

fn render_kind() -> TaskKind {
    TaskKind::Render
}

/// What a worker needs of the task's job.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LeasedJob {
    /// GET /v1/worker/scenes/{scene_id} for the bundle.
    pub scene_id: String,
    /// The scene file inside the bundle.
    pub scene_main: String,
    /// The job's settings resolved against the scene (image size, spp, integrator, seed, ...).
    pub resolved: Resolved,
}

/// The answer of POST /v1/worker/lease (200).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Lease {
    /// What to render.
    pub task: LeasedTask,
    /// The job it belongs to.
    pub job: LeasedJob,
    /// How long the lease lasts without a heartbeat, in seconds.
    pub lease_seconds: f64,
}

/// A task a worker holds.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeldTask {
    /// The task id.
    pub id: i64,
    /// The attempt number from its [`LeasedTask`].
    pub attempt: u32,
}

/// POST /v1/worker/heartbeat.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeartbeatRequest {
    /// The id from [`Registration`].
    pub worker_id: String,
    /// The tasks it is rendering; their leases are extended.
    #[serde(default)]
    pub tasks: Vec<HeldTask>,
}

/// The answer of POST /v1/worker/heartbeat: held tasks that are no longer this worker's.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct HeartbeatAnswer {
    /// Ids of held tasks the worker should stop rendering.
    pub lost: Vec<i64>,
    /// An operator asked the worker to drain: take no new task, finish those in hand, exit.
    #[serde(default)]
    pub drain: bool,
}

/// POST /v1/worker/deregister.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeregisterRequest {
    /// The id from [`Registration`].
    pub worker_id: String,
}

/// The answer of POST /v1/worker/deregister.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DeregisterAnswer {
    /// Always true.
    pub ok: bool,
    /// Leases the worker still held, given back to the queue.
    pub released: usize,
}

/// The query of PUT /v1/worker/tasks/{id}/result.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResultQuery {
    /// The id from [`Registration`].
    pub worker_id: String,
    /// The attempt number from the [`LeasedTask`].
    pub attempt: u32,
}

/// The answer of PUT /v1/worker/tasks/{id}/result.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ResultAnswer {
    /// False when the attempt is no longer this worker's (the task was leased again).
    pub accepted: bool,
}

/// POST /v1/worker/tasks/{id}/fail.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FailRequest {
    /// The id from [`Registration`].
    pub worker_id: String,
    /// The attempt number from the [`LeasedTask`].
    pub attempt: u32,
    /// What went wrong.
    pub error: String,
}

/// `{"ok": true}`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct OkAnswer {
    /// Always true.
    pub ok: bool,
}
