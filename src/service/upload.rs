//! Large request bodies (scene bundles, reference images) written to disk as they arrive, and
//! files sent back the same way: the coordinator holds a chunk of them at a time, never the whole
//! upload, however large the limit.

use axum::body::{Body, Bytes};
use futures_util::StreamExt;
use std::path::{Path, PathBuf};
use tokio::io::AsyncWriteExt;

/// Why an upload was not stored.
#[derive(Debug)]
pub(crate) enum UploadError {
    /// Longer than the limit (the message names it).
    TooLarge(String),
    /// The client's connection failed, or sent the body too slowly (`server`).
    Read(String),
    /// The coordinator could not write it.
    Disk(std::io::Error),
}

/// The size of the chunks a file is sent in.
const CHUNK: usize = 256 << 10;

/// Writes `body` to `path` (created; removed again on any error), refusing it as soon as it
/// passes `limit` bytes. Returns its length. The file is not made durable: its caller decides.
pub(crate) async fn body_to_file(body: Body, path: &Path, limit: u64) -> Result<u64, UploadError> {
    use axum::body::HttpBody;
    let too_large = || UploadError::TooLarge(format!("larger than the limit of {limit} bytes"));
    if HttpBody::size_hint(&body).lower() > limit {
        return Err(too_large());
    }
    let file = tokio::fs::File::create(path)
        .await
        .map_err(UploadError::Disk)?;
    let mut out = tokio::io::BufWriter::with_capacity(CHUNK, file);
    let mut stream = body.into_data_stream();
    let mut n = 0u64;
    let result = async {
        while let Some(chunk) = stream.next().await {
            let chunk = chunk.map_err(|e| UploadError::Read(format!("cannot be read: {e}")))?;
            n += chunk.len() as u64;
            if n > limit {
                return Err(too_large());
            }
            out.write_all(&chunk).await.map_err(UploadError::Disk)?;
        }
        out.flush().await.map_err(UploadError::Disk)?;
        Ok(n)
    }
    .await;
    if result.is_err() {
        let _ = std::fs::remove_file(path);
    }
    result
}

/// A response body that reads the file at `path` chunk by chunk as it is sent.
pub(crate) async fn file_body(path: PathBuf) -> std::io::Result<(Body, u64)> {
    use tokio::io::AsyncReadExt;
    let file = tokio::fs::File::open(&path).await?;
    let len = file.metadata().await?.len();
    let stream = futures_util::stream::unfold(Some(file), |file| async move {
        let mut file = file?;
        let mut buf = vec![0u8; CHUNK];
        match file.read(&mut buf).await {
            Ok(0) => None,
            Ok(k) => {
                buf.truncate(k);
                Some((Ok::<_, std::io::Error>(Bytes::from(buf)), Some(file)))
            }
            Err(e) => Some((Err(e), None)),
        }
    });
    Ok((Body::from_stream(stream), len))
}
