//! The one error of every byte format: what was refused, and where.

/// Bytes that a format refuses: truncated, of another format or version, damaged (checksums),
/// or holding a value outside what the job allows. Nothing of them is merged.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// A field runs past the end of the bytes: where it starts and how many more bytes it needs.
    #[error("invalid tile result: truncated at byte {at} (wanted {wanted} more)")]
    Truncated {
        /// The offset at which the field starts.
        at: usize,
        /// The bytes it needs beyond those left.
        wanted: usize,
    },
    /// The bytes do not start with the format's magic.
    #[error("invalid tile result: not a {format} (bad magic)")]
    Magic {
        /// The format expected.
        format: &'static str,
    },
    /// The format in a version this build does not read.
    #[error("invalid tile result: {format} version {got}, expected {expected:?}")]
    Version {
        /// The format.
        format: &'static str,
        /// The version the bytes carry.
        got: u32,
        /// The versions read.
        expected: &'static [u32],
    },
    /// A part whose checksum does not match its bytes: damaged on disk or in transit, or a
    /// write torn by a crash.
    #[error("invalid tile result: {part}: checksum mismatch ({cause})")]
    Checksum {
        /// The part checked.
        part: &'static str,
        /// What may have damaged it.
        cause: &'static str,
    },
    /// Reading a stream failed.
    #[error("invalid tile result: {part}: {source}")]
    Read {
        /// The field being read.
        part: String,
        /// The stream's error.
        #[source]
        source: std::io::Error,
    },
    /// EXR blocks that do not fit the frame's layout, or do not inflate to it.
    #[error("invalid tile result: {0}")]
    Exr(#[from] crate::film::image::exr_io::ExrError),
    /// A value the format or the job does not allow; the message names the field, its value
    /// and where it lies.
    #[error("invalid tile result: {0}")]
    Invalid(String),
}

impl FormatError {
    /// A refused value, described by `what` (the field, its value, where).
    pub(crate) fn invalid(what: impl Into<String>) -> FormatError {
        FormatError::Invalid(what.into())
    }
}
