//! Checks an OpenEXR file's headers before its pixels are decoded: a file of a few kilobytes
//! can claim (and, compressed, hold) gigabytes of pixels, and the decoder allocates what the
//! header says. References uploaded to the coordinator and the EXRs `omis diff` and
//! `omis compare` read pass through here first.

use std::path::Path;

/// Channels beyond any image omis makes or reads (its own EXRs have at most a few hundred:
/// beauty, variance, per-depth and per-strategy layers).
pub(crate) const MAX_CHANNELS: usize = 1024;

/// What the headers of an EXR claim.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct ExrSize {
    /// The largest part's data window.
    pub width: usize,
    pub height: usize,
    /// Channels of every part.
    pub channels: usize,
    /// Samples of every channel of every part (the full-resolution level).
    pub samples: u64,
}

/// Why an EXR's headers were refused. Messages do not name the file.
#[derive(Debug, thiserror::Error)]
pub(crate) enum ExrHeaderError {
    /// The headers could not be read: not an EXR, or a damaged one.
    #[error("not a readable EXR: {0}")]
    Unreadable(exr::error::Error),
    /// A part's data window is larger than `max` on a side.
    #[error(
        "its data window is {width}x{height}, larger than the limit of {max}x{max} \
         (--max-resolution)"
    )]
    TooLarge {
        width: usize,
        height: usize,
        max: usize,
    },
    /// A part holds deep data.
    #[error("it holds deep data, which omis does not read")]
    Deep,
    /// More than `MAX_CHANNELS` channels in all (counted up to the part that passed it).
    #[error("it has {0} channels or more, more than the limit of {MAX_CHANNELS}")]
    TooManyChannels(usize),
    /// More than `max` samples in all.
    #[error(
        "it holds {} samples ({}x{}, {} channels), more than the limit of {max}; \
         keep only the layers needed",
        .size.samples, .size.width, .size.height, .size.channels
    )]
    TooManySamples { size: ExrSize, max: u64 },
}

/// An `ExrHeaderError` of a file the command line reads, naming it.
#[derive(Debug, thiserror::Error)]
#[error("{}: {error}", .path.display())]
pub(crate) struct ExrFileError {
    /// The file.
    pub path: std::path::PathBuf,
    /// Why its headers were refused.
    pub error: ExrHeaderError,
}

/// Reads only the headers of the EXR at `path` and refuses one whose parts are larger than
/// `max_resolution` on a side, have more than `MAX_CHANNELS` channels in all, more than
/// `max_samples` samples in all, or deep data. Messages do not name the path.
pub(crate) fn check(
    path: &Path,
    max_resolution: usize,
    max_samples: u64,
) -> Result<ExrSize, ExrHeaderError> {
    let meta =
        exr::meta::MetaData::read_from_file(path, false).map_err(ExrHeaderError::Unreadable)?;
    let mut size = ExrSize {
        width: 0,
        height: 0,
        channels: 0,
        samples: 0,
    };
    for h in meta.headers.iter() {
        let (w, ht) = (h.layer_size.width(), h.layer_size.height());
        if w > max_resolution || ht > max_resolution {
            return Err(ExrHeaderError::TooLarge {
                width: w,
                height: ht,
                max: max_resolution,
            });
        }
        if h.deep {
            return Err(ExrHeaderError::Deep);
        }
        let n = h.channels.list.len();
        size.channels += n;
        if size.channels > MAX_CHANNELS {
            return Err(ExrHeaderError::TooManyChannels(size.channels));
        }
        size.samples = size
            .samples
            .saturating_add((w as u64) * (ht as u64) * n as u64);
        size.width = size.width.max(w);
        size.height = size.height.max(ht);
    }
    if size.samples > max_samples {
        return Err(ExrHeaderError::TooManySamples {
            size,
            max: max_samples,
        });
    }
    Ok(size)
}

/// `check` with the command line's limits (`Limits::default()`), for `omis diff` and
/// `omis compare`: errors name the file.
pub(crate) fn check_cli(path: &Path) -> Result<ExrSize, ExrFileError> {
    let r = crate::job::Limits::default().max_resolution as usize;
    check(path, r, u64::MAX).map_err(|error| ExrFileError {
        path: path.to_path_buf(),
        error,
    })
}
