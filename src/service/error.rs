//! `ServiceError`: why the coordinator could not do what was asked of it, typed by who is at
//! fault. The API turns it into a status and a JSON body in one place
//! (`api::errors`, `From<ServiceError> for ApiError`); the job life cycle fails a job with its
//! message.

use super::store::StoreError;

/// Why the coordinator could not do something.
#[derive(Debug, thiserror::Error)]
pub(crate) enum ServiceError {
    /// The job store failed (its message; `disk_full` when its storage is full).
    #[error(transparent)]
    Store(#[from] StoreError),
    /// A file of the coordinator's could not be read or written.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The coordinator's disk failed while doing `what` (507 when its storage is full).
    #[error("{what}: {source}")]
    Disk {
        /// What it was doing.
        what: &'static str,
        /// The disk's error.
        source: std::io::Error,
    },
    /// A job's own settings, reference, checkpoints or outputs cannot serve it: the job fails
    /// with this message.
    #[error("{0}")]
    Job(String),
    /// A stored result could not be read: its task is rendered again and the pass's merge
    /// waits for it (the job goes on).
    #[error("{0}")]
    RenderedAgain(String),
    /// The coordinator's own failure (a blocking task that panicked, a closed semaphore).
    #[error("{0}")]
    Internal(String),
}

impl ServiceError {
    /// A job's own problem, in words (a message, or an error of the film's formats and images).
    pub fn job(message: impl std::fmt::Display) -> ServiceError {
        ServiceError::Job(message.to_string())
    }

    /// The coordinator's own failure.
    pub fn internal(e: impl std::fmt::Display) -> ServiceError {
        ServiceError::Internal(e.to_string())
    }
}

/// The result of a coordinator operation.
pub(crate) type ServiceResult<T> = Result<T, ServiceError>;
