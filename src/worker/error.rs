//! `WorkerError`: why a worker could not run a task. Its message is the failure text the worker
//! reports to the coordinator (POST /v1/worker/tasks/{id}/fail). No variant names its cause as a
//! `source`: the message already holds it, and error chains print it once.

use reqwest::StatusCode;

/// Why a task (its scene, or a merge) failed on the worker.
#[derive(Debug, thiserror::Error)]
pub(crate) enum WorkerError {
    /// The merge input could not be fetched or was cut off.
    #[error("merge input: {0}")]
    MergeInput(reqwest::Error),
    /// The coordinator refused the merge input (status and its body).
    #[error("merge input: HTTP {status} {body}")]
    MergeInputStatus {
        /// The answer's status.
        status: StatusCode,
        /// The answer's body.
        body: String,
    },
    /// The merge input is malformed.
    #[error(transparent)]
    Merge(#[from] crate::film::format::FormatError),
    /// The merge's blocking thread panicked.
    #[error("merge panicked: {0}")]
    MergePanicked(tokio::task::JoinError),
    /// The scene's bundle could not be downloaded.
    #[error("downloading scene {scene}: {error}")]
    Download {
        /// The bundle's id.
        scene: String,
        /// The HTTP client's error.
        error: reqwest::Error,
    },
    /// The coordinator refused the scene's bundle.
    #[error("downloading scene {scene}: HTTP {status}")]
    DownloadStatus {
        /// The bundle's id.
        scene: String,
        /// The answer's status.
        status: StatusCode,
    },
    /// The downloaded bundle could not be unpacked.
    #[error(transparent)]
    Unpack(#[from] crate::bundle::BundleError),
    /// The unpacked bundle could not be marked complete in the cache.
    #[error(transparent)]
    Cache(#[from] std::io::Error),
    /// The scene did not load.
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    /// The scene's camera cannot take the job's resolution.
    #[error(transparent)]
    Camera(#[from] crate::camera::CameraError),
    /// A blocking thread (unpacking or loading the scene) panicked.
    #[error(transparent)]
    Panicked(#[from] tokio::task::JoinError),
}
