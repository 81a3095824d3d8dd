//! Byte buffers the coordinator reuses for request bodies (results, merge outputs) and for the
//! chunks of merge inputs, instead of allocating a fresh megabyte buffer per request.
//!
//! Buffers of a megabyte or more come from mmap (see `service::start`), so each fresh one was
//! faulted in page by page and zeroed by the kernel, then unmapped when freed: on a 1080p
//! optimal-MIS job that was about a quarter of the coordinator's CPU (BENCHMARKS.md, "The render service"). A
//! buffer given back keeps its pages; the pool holds at most `keep` bytes of them, so the
//! memory it adds to the coordinator is bounded.

use bytes::Bytes;
use std::sync::{Arc, Mutex};

/// Buffers larger than this are freed rather than kept (a rare huge result).
const LARGEST_KEPT: usize = 64 << 20;

/// A bounded pool of empty byte buffers with their capacity.
pub(crate) struct Buffers {
    free: Mutex<Vec<Vec<u8>>>,
    /// Most bytes of capacity the pool holds.
    keep: usize,
}

impl Buffers {
    /// A pool that holds at most `keep` bytes of free buffers.
    pub fn new(keep: usize) -> Buffers {
        Buffers {
            free: Mutex::new(Vec::new()),
            keep,
        }
    }

    /// An empty buffer with room for `want` bytes: the smallest free one that holds it without
    /// wasting more than `want` + 1 MB, else the largest smaller one (grown), else a new one. A
    /// buffer in use keeps all its pages resident, so a small request never takes a large one.
    pub fn take(&self, want: usize) -> Vec<u8> {
        let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        let fits = |c: usize| c >= want && c <= 2 * want + (1 << 20);
        let pick = free
            .iter()
            .enumerate()
            .filter(|(_, b)| fits(b.capacity()))
            .min_by_key(|(_, b)| b.capacity())
            .or_else(|| {
                free.iter()
                    .enumerate()
                    .filter(|(_, b)| b.capacity() < want)
                    .max_by_key(|(_, b)| b.capacity())
            })
            .map(|(k, _)| k);
        let mut v = match pick {
            Some(k) => free.swap_remove(k),
            None => Vec::new(),
        };
        drop(free);
        v.reserve(want);
        v
    }

    /// Gives `v` back (emptied) if the pool has room for its capacity; else it is freed.
    pub fn give(&self, mut v: Vec<u8>) {
        let cap = v.capacity();
        if cap == 0 || cap > LARGEST_KEPT {
            return;
        }
        v.clear();
        let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        let held: usize = free.iter().map(Vec::capacity).sum();
        if held + cap <= self.keep {
            free.push(v);
        }
    }

    /// Bytes of capacity the pool holds now.
    #[cfg(test)]
    fn held(&self) -> usize {
        let free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        free.iter().map(Vec::capacity).sum()
    }
}

/// A buffer that goes back to its pool when dropped.
pub(crate) struct Pooled {
    v: Vec<u8>,
    pool: Arc<Buffers>,
}

impl Pooled {
    /// `v`, to be given back to `pool` when dropped.
    pub fn new(v: Vec<u8>, pool: Arc<Buffers>) -> Pooled {
        Pooled { v, pool }
    }

    /// As `Bytes` (for a response body): the buffer goes back when the last clone is dropped.
    pub fn into_bytes(self) -> Bytes {
        Bytes::from_owner(self)
    }
}

impl std::ops::Deref for Pooled {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        &self.v
    }
}

impl AsRef<[u8]> for Pooled {
    fn as_ref(&self) -> &[u8] {
        &self.v
    }
}

impl Drop for Pooled {
    fn drop(&mut self) {
        self.pool.give(std::mem::take(&mut self.v));
    }
}

/// Why a request body was not read.
#[derive(Debug)]
pub(crate) enum BodyError {
    /// Longer than the limit (the message names it).
    TooLarge(String),
    /// The connection failed or the body was malformed.
    Read(String),
}

/// A request body read whole into a pooled buffer, refused as soon as it passes `limit` bytes.
pub(crate) async fn read_body(
    body: axum::body::Body,
    limit: u64,
    pool: &Arc<Buffers>,
) -> Result<Pooled, BodyError> {
    use axum::body::HttpBody;
    use futures_util::StreamExt;
    let too_large = || BodyError::TooLarge(format!("larger than the limit of {limit} bytes"));
    let hint = HttpBody::size_hint(&body).upper();
    if hint.is_some_and(|n| n > limit) {
        return Err(too_large());
    }
    let want = hint.unwrap_or(0).min(LARGEST_KEPT as u64) as usize;
    let mut out = Pooled::new(pool.take(want), pool.clone());
    let mut stream = body.into_data_stream();
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| BodyError::Read(format!("cannot be read: {e}")))?;
        if (out.v.len() + chunk.len()) as u64 > limit {
            return Err(too_large());
        }
        out.v.extend_from_slice(&chunk);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buffers_are_reused_and_the_pool_stays_bounded() {
        let pool = Arc::new(Buffers::new(3 << 20));
        let a = pool.take(1 << 20);
        let ptr = a.as_ptr();
        pool.give(a);
        // The same allocation comes back, empty, for a request that fits it.
        let b = pool.take(1000);
        assert_eq!(b.as_ptr(), ptr);
        assert!(b.is_empty() && b.capacity() >= 1 << 20);
        // Given back through `Pooled` (as a response body would be).
        let bytes = Pooled::new(b, pool.clone()).into_bytes();
        assert_eq!(pool.held(), 0);
        drop(bytes);
        assert!(pool.held() >= 1 << 20);
        // A small request does not take a much larger buffer (it would hold its pages).
        let small = pool.take(1000);
        assert!(small.capacity() < 2 << 20, "{}", small.capacity());
        drop(small);
        // Beyond `keep`, buffers are freed rather than kept.
        let bufs: Vec<Vec<u8>> = (0..5).map(|_| pool.take(1 << 20)).collect();
        for v in bufs {
            pool.give(v);
        }
        assert!(pool.held() <= 3 << 20, "held {}", pool.held());
        // Larger than the largest kept: freed.
        pool.give(Vec::with_capacity(LARGEST_KEPT + 1));
        assert!(pool.held() <= 3 << 20);
    }

    #[test]
    fn read_body_refuses_a_body_over_the_limit() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        let pool = Arc::new(Buffers::new(1 << 20));
        let ok = rt
            .block_on(read_body(
                axum::body::Body::from(vec![7u8; 100]),
                100,
                &pool,
            ))
            .expect("within the limit");
        assert_eq!(&ok[..], &[7u8; 100][..]);
        // Over the limit: announced by its size (a whole body) or found while streaming.
        let e = rt
            .block_on(read_body(
                axum::body::Body::from(vec![7u8; 101]),
                100,
                &pool,
            ))
            .err()
            .expect("over the limit");
        assert!(
            matches!(&e, BodyError::TooLarge(m) if m.contains("limit of 100")),
            "{e:?}"
        );
        let chunks = futures_util::stream::iter(
            (0..3).map(|_| Ok::<_, std::io::Error>(Bytes::from(vec![1u8; 40]))),
        );
        let e = rt
            .block_on(read_body(axum::body::Body::from_stream(chunks), 100, &pool))
            .err()
            .expect("streamed over the limit");
        assert!(matches!(e, BodyError::TooLarge(_)), "{e:?}");
    }
}
