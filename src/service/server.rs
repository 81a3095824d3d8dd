//! The coordinator's HTTP server: connections accepted under a cap, with timeouts, so that no
//! client can hold the coordinator's file descriptors or its attention.
//!
//! - A request's headers must arrive within `header_timeout`, and a kept-alive connection that
//!   sends no next request is closed after the same time (hyper starts the header timer when a
//!   connection becomes idle).
//! - A request body must keep up `body_min_rate` bytes per second once `body_grace` has passed
//!   (the rule of Apache's mod_reqtimeout): a body trickled slower ends with an error (400).
//! - At most `max_connections` are open. When a new one arrives at the cap, the oldest idle one
//!   (no request in flight: waiting for its first request or kept alive between two) is closed
//!   to make room, so idle connections cannot crowd out `/healthz` or a worker; when every open
//!   connection has a request in flight, the new one is answered 503 and closed. Requests in
//!   flight are capped per class of route (`api::admission`) well below the cap, so some
//!   connections are always idle and evictable.
//! - The soft limit on open files is raised to the hard one at start, and the cap kept below it.
//!
//! Routes are axum's (`api::router`); hyper serves HTTP/1.1.

use axum::Router;
use axum::body::{Body, Bytes, HttpBody};
use hyper::body::{Frame, Incoming, SizeHint};
use std::collections::BTreeMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Notify;

/// How the server treats connections.
#[derive(Clone, Debug)]
pub(crate) struct ServerConfig {
    /// Most open connections (lowered to fit the process's limit on open files).
    pub max_connections: usize,
    /// Longest wait for a request's headers, and for the next request on a kept-alive connection.
    pub header_timeout: Duration,
    /// Slowest request body, in bytes per second, once `body_grace` has passed.
    pub body_min_rate: u64,
    /// Time a request body may take before its rate is held to `body_min_rate`.
    pub body_grace: Duration,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            max_connections: 2048,
            header_timeout: Duration::from_secs(10),
            body_min_rate: 4096,
            body_grace: Duration::from_secs(10),
        }
    }
}

/// File descriptors kept for everything but connections (the database, result logs, scene
/// files, local workers' pipes).
const RESERVED_FDS: u64 = 256;
/// Connections at most being answered 503 at once; past it a connection is closed unanswered.
const MAX_SHEDDING: usize = 256;
/// How long a 503 may take to write before the connection is dropped.
const SHED_WRITE_TIMEOUT: Duration = Duration::from_secs(1);
/// How long an evicted or shut-down connection may take to finish before it is dropped.
const CLOSE_GRACE: Duration = Duration::from_secs(1);

/// Counters of the server, for /metrics.
#[derive(Default)]
pub(crate) struct ServerStats {
    /// Connections open now.
    pub open: AtomicUsize,
    /// Connections accepted since start.
    pub accepted: AtomicU64,
    /// Idle connections closed to make room for a new one.
    pub evicted: AtomicU64,
    /// Connections answered 503 (or closed) because every open one was busy.
    pub shed: AtomicU64,
    /// The effective cap on open connections.
    pub max_connections: AtomicUsize,
}

/// One open connection, as the cap sees it.
struct Conn {
    /// Requests being answered on it (a response counts until its body has been sent).
    in_flight: AtomicUsize,
    /// Told to close (evicted, or the server stops).
    close: Notify,
    /// Chosen to be closed: not chosen again.
    closing: std::sync::atomic::AtomicBool,
}

/// The open connections by age (ids grow).
#[derive(Default)]
struct Conns {
    open: Mutex<BTreeMap<u64, Arc<Conn>>>,
}

impl Conns {
    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, Arc<Conn>>> {
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Closes the oldest connection with no request in flight; false when there is none.
    fn evict_oldest_idle(&self) -> bool {
        let open = self.lock();
        let victim = open
            .values()
            .find(|c| {
                c.in_flight.load(Ordering::Acquire) == 0 && !c.closing.swap(true, Ordering::AcqRel)
            })
            .cloned();
        drop(open);
        match victim {
            Some(c) => {
                c.close.notify_one();
                true
            }
            None => false,
        }
    }
}

/// Raises the soft limit on open files to the hard limit; returns the soft limit now in force.
fn raise_open_files_limit() -> u64 {
    #[cfg(unix)]
    {
        let mut lim = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit and setrlimit read and write only the struct passed to them.
        unsafe {
            if libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) != 0 {
                return 1024;
            }
            if lim.rlim_cur < lim.rlim_max {
                let want = libc::rlimit {
                    rlim_cur: lim.rlim_max,
                    rlim_max: lim.rlim_max,
                };
                if libc::setrlimit(libc::RLIMIT_NOFILE, &want) == 0 {
                    lim.rlim_cur = lim.rlim_max;
                }
            }
        }
        lim.rlim_cur
    }
    #[cfg(not(unix))]
    {
        1024
    }
}

/// The cap on connections that fits the limit on open files.
pub(crate) fn effective_max_connections(wanted: usize) -> usize {
    let files = raise_open_files_limit();
    let room = files.saturating_sub(RESERVED_FDS).max(16) as usize;
    if wanted > room {
        tracing::warn!(
            "--max-connections {wanted} lowered to {room}: the process may open {files} files"
        );
    }
    wanted.min(room).max(1)
}

/// Serves `router` on `listener` until `shutdown` resolves, then closes every connection
/// (letting requests in flight finish within `CLOSE_GRACE`).
pub(crate) async fn serve(
    listener: TcpListener,
    router: Router,
    cfg: ServerConfig,
    stats: Arc<ServerStats>,
    shutdown: impl std::future::Future<Output = ()>,
) {
    let max = effective_max_connections(cfg.max_connections);
    stats.max_connections.store(max, Ordering::Relaxed);
    let conns = Arc::new(Conns::default());
    let shedding = Arc::new(AtomicUsize::new(0));
    let mut next_id = 0u64;
    tokio::pin!(shutdown);
    loop {
        let accepted = tokio::select! {
            a = listener.accept() => a,
            _ = &mut shutdown => break,
        };
        let (stream, _) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // Out of file descriptors despite the cap (other files), or a connection reset
                // before it was accepted: wait a little rather than spin.
                tracing::warn!("accept: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        stats.accepted.fetch_add(1, Ordering::Relaxed);
        if stats.open.load(Ordering::Acquire) >= max {
            if conns.evict_oldest_idle() {
                stats.evicted.fetch_add(1, Ordering::Relaxed);
            } else {
                stats.shed.fetch_add(1, Ordering::Relaxed);
                shed(stream, &shedding);
                continue;
            }
        }
        let _ = stream.set_nodelay(true);
        let id = next_id;
        next_id += 1;
        let conn = Arc::new(Conn {
            in_flight: AtomicUsize::new(0),
            close: Notify::new(),
            closing: std::sync::atomic::AtomicBool::new(false),
        });
        conns.lock().insert(id, conn.clone());
        stats.open.fetch_add(1, Ordering::AcqRel);
        let (router, cfg, conns, stats) =
            (router.clone(), cfg.clone(), conns.clone(), stats.clone());
        tokio::spawn(async move {
            serve_connection(stream, router, &cfg, conn).await;
            conns.lock().remove(&id);
            stats.open.fetch_sub(1, Ordering::AcqRel);
        });
    }
    let open: Vec<Arc<Conn>> = conns.lock().values().cloned().collect();
    for c in open {
        c.close.notify_one();
    }
}

/// Answers 503 on a connection the cap has no room for, and closes it.
fn shed(mut stream: TcpStream, shedding: &Arc<AtomicUsize>) {
    if shedding.fetch_add(1, Ordering::AcqRel) >= MAX_SHEDDING {
        shedding.fetch_sub(1, Ordering::AcqRel);
        return; // dropped: closed unanswered
    }
    let shedding = shedding.clone();
    tokio::spawn(async move {
        use tokio::io::AsyncWriteExt;
        let body = r#"{"error":"the coordinator has no room for another connection; retry shortly","field":null}"#;
        let answer = format!(
            "HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\n\
             content-length: {}\r\nretry-after: 1\r\nconnection: close\r\n\r\n{body}",
            body.len()
        );
        let _ = tokio::time::timeout(SHED_WRITE_TIMEOUT, async {
            stream.write_all(answer.as_bytes()).await?;
            stream.shutdown().await
        })
        .await;
        shedding.fetch_sub(1, Ordering::AcqRel);
    });
}

/// Serves one connection until it ends, its peer goes quiet past the timeouts, or it is told
/// to close.
async fn serve_connection(stream: TcpStream, router: Router, cfg: &ServerConfig, conn: Arc<Conn>) {
    let (rate, grace) = (cfg.body_min_rate, cfg.body_grace);
    let tracked = conn.clone();
    let service = hyper::service::service_fn(move |req: hyper::Request<Incoming>| {
        let guard = InFlight::new(tracked.clone());
        let router = router.clone();
        async move {
            let req = req.map(|b| Body::new(MinRate::new(b, rate, grace)));
            let resp = tower::ServiceExt::oneshot(router, req).await?;
            Ok::<_, std::convert::Infallible>(resp.map(|b| {
                Body::new(Held {
                    inner: b,
                    _guard: guard,
                })
            }))
        }
    });
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(hyper_util::rt::TokioTimer::new())
        .header_read_timeout(cfg.header_timeout)
        .keep_alive(true);
    let io = hyper_util::rt::TokioIo::new(stream);
    let served = builder.serve_connection(io, service).with_upgrades();
    tokio::pin!(served);
    tokio::select! {
        r = served.as_mut() => {
            if let Err(e) = r {
                tracing::debug!("connection: {e}");
            }
            return;
        }
        _ = conn.close.notified() => {}
    }
    // Idle (evicted, or the server stops between requests): closed at once. Otherwise the
    // request in flight may finish.
    if conn.in_flight.load(Ordering::Acquire) == 0 {
        return;
    }
    served.as_mut().graceful_shutdown();
    let _ = tokio::time::timeout(CLOSE_GRACE, served).await;
}

/// A request in flight on its connection, until the response's body has been sent or dropped.
struct InFlight(Arc<Conn>);

impl InFlight {
    fn new(conn: Arc<Conn>) -> InFlight {
        conn.in_flight.fetch_add(1, Ordering::AcqRel);
        InFlight(conn)
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.in_flight.fetch_sub(1, Ordering::AcqRel);
    }
}

/// A body that keeps something alive (a guard, a permit) until it has been sent or dropped.
pub(crate) struct Held<G> {
    pub inner: Body,
    /// Kept for its `Drop` only.
    pub _guard: G,
}

impl<G: Unpin> HttpBody for Held<G> {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// A request body held to a minimum rate: after `grace`, at least `rate` bytes per second on
/// average since the request began, else an error that ends the request.
struct MinRate {
    inner: Incoming,
    start: Instant,
    received: u64,
    rate: u64,
    grace: Duration,
    timer: Pin<Box<tokio::time::Sleep>>,
}

impl MinRate {
    fn new(inner: Incoming, rate: u64, grace: Duration) -> MinRate {
        let start = Instant::now();
        MinRate {
            inner,
            start,
            received: 0,
            rate: rate.max(1),
            grace,
            timer: Box::pin(tokio::time::sleep(grace)),
        }
    }

    /// When the body must have sent more than it has.
    fn deadline(&self) -> Instant {
        self.start + self.grace + Duration::from_secs_f64(self.received as f64 / self.rate as f64)
    }
}

/// A request body that arrived slower than the server's minimum rate.
#[derive(Debug)]
pub(crate) struct TooSlow {
    rate: u64,
    received: u64,
    seconds: f64,
}

impl std::fmt::Display for TooSlow {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "the request body arrived slower than {} bytes per second ({} bytes in {:.1} s)",
            self.rate, self.received, self.seconds
        )
    }
}

impl std::error::Error for TooSlow {}

impl HttpBody for MinRate {
    type Data = Bytes;
    type Error = Box<dyn std::error::Error + Send + Sync>;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        match Pin::new(&mut self.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(d) = frame.data_ref() {
                    self.received += d.len() as u64;
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Ready(Some(Err(e))) => Poll::Ready(Some(Err(Box::new(e)))),
            Poll::Ready(None) => Poll::Ready(None),
            Poll::Pending => {
                let deadline = self.deadline();
                self.timer
                    .as_mut()
                    .reset(tokio::time::Instant::from_std(deadline));
                if self.timer.as_mut().poll(cx).is_ready() {
                    let slow = TooSlow {
                        rate: self.rate,
                        received: self.received,
                        seconds: self.start.elapsed().as_secs_f64(),
                    };
                    return Poll::Ready(Some(Err(Box::new(slow))));
                }
                Poll::Pending
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}
