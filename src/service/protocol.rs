//! The wire protocol of the render service, in one place: every JSON message between the
//! coordinator and its workers (register, lease, heartbeat, result, failure, deregister), the
//! client-facing documents (job status, lists, uploads, Server-Sent Events), and the states and
//! event kinds stored in the coordinator's database. The coordinator (src/service/api), the
//! worker (src/worker) and the HTTP client (src/cli/client.rs) all use these types; the
//! contract they implement is proto/openapi.yaml, and a test checks the enums against it.
//!
//! Requests are strict (`deny_unknown_fields`, as the server has always refused unknown
//! fields); answers are lenient when read, so that a client survives a newer server's extra
//! fields.

use crate::film::Tile;
use crate::job::{JobSettings, Resolved};
use serde::{Deserialize, Serialize};

/// A closed set of lowercase names: serde (lowercase / snake_case), `as_str()` for SQL and
/// logs, parsing back, and the SQLite conversions of the store.
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

        impl rusqlite::types::ToSql for $name {
            fn to_sql(&self) -> rusqlite::Result<rusqlite::types::ToSqlOutput<'_>> {
                Ok(rusqlite::types::ToSqlOutput::from(self.as_str()))
            }
        }

        impl rusqlite::types::FromSql for $name {
            fn column_result(
                value: rusqlite::types::ValueRef<'_>,
            ) -> rusqlite::types::FromSqlResult<Self> {
                value
                    .as_str()?
                    .parse()
                    .map_err(|e: String| rusqlite::types::FromSqlError::Other(e.into()))
            }
        }
    };
}

string_enum! {
    /// A job's state: `queued` until a task is first leased, `running`, then one of the three
    /// final states.
    JobState {
        Queued = "queued",
        Running = "running",
        Done = "done",
        Failed = "failed",
        Cancelled = "cancelled",
    }
}

impl JobState {
    /// Queued or running: the job still has work to hand out.
    pub fn is_active(self) -> bool {
        matches!(self, JobState::Queued | JobState::Running)
    }
}

string_enum! {
    /// A task's state (tasks of merged passes are deleted).
    TaskState {
        Queued = "queued",
        Leased = "leased",
        Done = "done",
    }
}

string_enum! {
    /// A worker's state: `gone` after two lease times without news, `left` after deregistering.
    WorkerState {
        Idle = "idle",
        Busy = "busy",
        Left = "left",
        Gone = "gone",
    }
}

string_enum! {
    /// The kind of a job event (the SSE `event:` line).
    EventKind {
        Queued = "queued",
        TileDone = "tile_done",
        PassDone = "pass_done",
        Preview = "preview",
        TaskFailed = "task_failed",
        Done = "done",
        Failed = "failed",
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
    pub width: u32,
    pub height: u32,
    /// Total samples per pixel; None for a time budget without spp.
    pub spp: Option<u32>,
}

/// `tile_done`: a task's result was accepted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileDoneEvent {
    pub pass: u32,
    pub tile: u32,
    /// The worker id.
    pub worker: String,
    /// Size of the result.
    pub bytes: u64,
}

/// `pass_done`: a pass was merged.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PassDoneEvent {
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
    pub pass: u32,
    pub spp: u32,
    /// The preview's path, /v1/jobs/{id}/preview.png.
    pub url: String,
}

/// `task_failed`: an attempt failed (reported by its worker, or its result was invalid).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TaskFailedEvent {
    pub pass: u32,
    pub tile: u32,
    pub worker: String,
    pub error: String,
    /// Failed attempts of the task so far.
    pub failures: u32,
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
    pub error: String,
}

/// `cancelled` (terminal): the job was cancelled.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CancelledEvent {}

/// One job event: its kind and its data.
#[derive(Clone, Debug, PartialEq)]
pub enum JobEvent {
    Queued(QueuedEvent),
    TileDone(TileDoneEvent),
    PassDone(PassDoneEvent),
    Preview(PreviewEvent),
    TaskFailed(TaskFailedEvent),
    Done(DoneEvent),
    Failed(FailedEvent),
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
    /// A scene in omis's JSON format, inline (meshes inline too).
    Inline(serde_json::Value),
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
    pub scene: SceneSource,
    #[serde(default)]
    pub settings: JobSettings,
    #[serde(default)]
    pub reference: Option<ReferenceSource>,
    #[serde(default)]
    pub name: Option<String>,
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
    pub relmse: Option<f64>,
}

/// A job's scene bundle and the scene file inside it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneRef {
    pub id: String,
    pub main: String,
}

/// Paths of a job's resources.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobLinks {
    #[serde(rename = "self")]
    pub self_: String,
    pub events: String,
    pub image: String,
    pub preview: String,
    pub error: String,
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
    pub id: String,
    pub name: Option<String>,
    pub state: JobState,
    /// Why the job failed.
    pub error: Option<String>,
    pub scene: SceneRef,
    /// The request's settings with every field filled in.
    pub settings: JobSettings,
    pub width: u32,
    pub height: u32,
    /// Total samples per pixel; None for a time budget without spp.
    pub spp_target: Option<u32>,
    pub time_budget_s: Option<f64>,
    /// Samples per pixel of the merged passes.
    pub spp_done: u32,
    pub passes_done: u32,
    pub passes_total: Option<u32>,
    pub tiles_per_pass: u32,
    /// Finished tiles of passes not merged yet; 0 once the job has ended.
    pub tiles_done: u32,
    pub created_at: f64,
    pub started_at: Option<f64>,
    pub finished_at: Option<f64>,
    pub elapsed_s: f64,
    pub eta_s: Option<f64>,
    /// relMSE of the last merged pass against the reference.
    pub relmse: Option<f64>,
    pub series: Vec<SeriesPoint>,
    pub accum_bytes: i64,
    pub accum_bytes_per_pixel: i64,
    pub result_bytes: i64,
    pub samples: i64,
    pub rays: i64,
    pub non_finite_samples: i64,
    pub has_reference: bool,
    pub links: JobLinks,
}

/// GET /v1/jobs.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobList {
    pub jobs: Vec<JobStatus>,
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
    pub triangles: usize,
    /// The scene camera's resolution.
    pub width: u32,
    pub height: u32,
    /// What the importer could not represent exactly.
    pub warnings: Vec<String>,
}

/// The query of POST /v1/scenes.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneUploadQuery {
    /// The scene file inside the archive.
    pub main: Option<String>,
}

/// GET /v1/scenes: the library's scene names.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneLibrary {
    pub library: Vec<String>,
}

/// The answer of POST /v1/references.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ReferenceInfo {
    /// The reference id, for `{"reference": {"upload": id}}`.
    pub id: String,
    pub width: usize,
    pub height: usize,
}

/// A registered worker (GET /v1/workers).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WorkerInfo {
    pub id: String,
    pub name: String,
    pub threads: u32,
    pub version: String,
    pub registered_at: f64,
    pub last_seen: f64,
    pub state: WorkerState,
    pub tasks_done: i64,
    /// The tasks it holds a lease on now.
    #[serde(default)]
    pub tasks: Vec<WorkerTask>,
}

/// A task a worker holds a lease on (GET /v1/workers).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WorkerTask {
    pub id: i64,
    pub job_id: String,
    pub pass: u32,
    pub tile: u32,
    pub attempt: u32,
}

/// GET /v1/workers.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WorkerList {
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
    pub error: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
}

// ---- the worker protocol (/v1/worker/*) ----

/// POST /v1/worker/register.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterRequest {
    pub name: String,
    pub threads: u32,
    #[serde(default)]
    pub version: String,
    /// A previous id, to keep it across reconnects.
    #[serde(default)]
    pub id: Option<String>,
}

/// The answer of POST /v1/worker/register.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Registration {
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
    pub worker_id: String,
    /// Long-poll up to this many seconds (at most 30).
    #[serde(default)]
    pub wait_s: Option<f64>,
}

/// The task of a lease.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LeasedTask {
    pub id: i64,
    /// Send it back with the result, a failure or a heartbeat.
    pub attempt: u32,
    pub job_id: String,
    pub pass: u32,
    /// Index of the tile in the job's row-major tile order.
    pub tile: u32,
    pub rect: Tile,
    /// The sample range [s0, s1) of the pass.
    pub samples: [u32; 2],
}

/// What a worker needs of the task's job.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LeasedJob {
    /// GET /v1/worker/scenes/{scene_id} for the bundle.
    pub scene_id: String,
    /// The scene file inside the bundle.
    pub scene_main: String,
    pub resolved: Resolved,
}

/// The answer of POST /v1/worker/lease (200).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Lease {
    pub task: LeasedTask,
    pub job: LeasedJob,
    pub lease_seconds: f64,
}

/// A task a worker holds.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeldTask {
    pub id: i64,
    pub attempt: u32,
}

/// POST /v1/worker/heartbeat.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeartbeatRequest {
    pub worker_id: String,
    #[serde(default)]
    pub tasks: Vec<HeldTask>,
}

/// The answer of POST /v1/worker/heartbeat: held tasks that are no longer this worker's.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct HeartbeatAnswer {
    pub lost: Vec<i64>,
}

/// POST /v1/worker/deregister.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeregisterRequest {
    pub worker_id: String,
}

/// The answer of POST /v1/worker/deregister.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DeregisterAnswer {
    pub ok: bool,
    /// Leases the worker still held, given back to the queue.
    pub released: usize,
}

/// The query of PUT /v1/worker/tasks/{id}/result.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResultQuery {
    pub worker_id: String,
    pub attempt: u32,
}

/// The answer of PUT /v1/worker/tasks/{id}/result.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ResultAnswer {
    pub accepted: bool,
}

/// POST /v1/worker/tasks/{id}/fail.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FailRequest {
    pub worker_id: String,
    pub attempt: u32,
    pub error: String,
}

/// `{"ok": true}`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct OkAnswer {
    pub ok: bool,
}
