//! The accept loop and the connections: HTTP/1.1, HTTP/2 and gRPC on one port (hyper's
//! protocol-sniffing server), with the limits that keep slow or idle clients from holding the
//! server: a header-read timeout, an idle timeout (no byte in either direction), a body-read
//! timeout (between body chunks), and a cap on open connections. At the cap the connection idle
//! the longest is closed to make room; when none is idle the new connection is closed at once.
//! Accept errors (out of file descriptors) back off instead of spinning. On drain every
//! connection is told to finish (HTTP/1: after the request in hand; HTTP/2: GOAWAY), and after
//! the drain deadline whatever is left is cut.

use std::collections::HashMap;
use std::os::fd::AsRawFd;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Notify;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;

use super::peer::Peer;

/// Connection limits (flags of `posefuse serve`).
#[derive(Debug, Clone)]
pub struct ConnLimits {
    /// A client must send a request's whole header within this time (HTTP/1).
    pub header_read_timeout: Duration,
    /// Longest pause between two chunks of a request body.
    pub body_read_timeout: Duration,
    /// A connection with no byte read or written for this long is closed.
    pub idle_timeout: Duration,
    /// Open connections at most (0: from the file-descriptor limit, see [`default_max_connections`]).
    pub max_connections: usize,
}

impl ConnLimits {
    /// The defaults (those of `posefuse serve`).
    pub const DEFAULT: ConnLimits = ConnLimits {
        header_read_timeout: Duration::from_secs(10),
        body_read_timeout: Duration::from_secs(30),
        idle_timeout: Duration::from_secs(60),
        max_connections: 0,
    };
}

impl Default for ConnLimits {
    fn default() -> Self {
        ConnLimits::DEFAULT
    }
}

/// What the drain left behind.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct DrainReport {
    /// Connections still open at the deadline (closed without finishing).
    pub connections_cut: usize,
}

fn epoch() -> Instant {
    static E: OnceLock<Instant> = OnceLock::new();
    *E.get_or_init(Instant::now)
}

fn now_ms() -> u64 {
    epoch().elapsed().as_millis() as u64
}

/// One open connection, as the registry sees it.
struct ConnHandle {
    last_io_ms: AtomicU64,
    /// Requests whose response future is still running on this connection.
    busy: AtomicUsize,
    evict: Notify,
}

impl ConnHandle {
    fn touch(&self) {
        self.last_io_ms.store(now_ms(), Ordering::Relaxed);
    }

    fn idle_ms(&self) -> u64 {
        now_ms().saturating_sub(self.last_io_ms.load(Ordering::Relaxed))
    }
}

/// The open connections (for the cap, eviction and the drain count).
#[derive(Default)]
pub struct Registry {
    next: AtomicU64,
    conns: Mutex<HashMap<u64, Arc<ConnHandle>>>,
}

impl Registry {
    /// Connections open now.
    pub fn open(&self) -> usize {
        self.conns.lock().map_or(0, |c| c.len())
    }

    fn add(&self) -> (u64, Arc<ConnHandle>) {
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let h = Arc::new(ConnHandle {
            last_io_ms: AtomicU64::new(now_ms()),
            busy: AtomicUsize::new(0),
            evict: Notify::new(),
        });
        if let Ok(mut c) = self.conns.lock() {
            c.insert(id, h.clone());
            metrics::gauge!("posefuse_connections_open").set(c.len() as f64);
        }
        (id, h)
    }

    fn remove(&self, id: u64) {
        if let Ok(mut c) = self.conns.lock() {
            c.remove(&id);
            metrics::gauge!("posefuse_connections_open").set(c.len() as f64);
        }
    }

    /// Asks the connection idle the longest (no request running, quiet for at least
    /// `min_idle_ms`) to close; false when there is none.
    fn evict_idlest(&self, min_idle_ms: u64) -> bool {
        let Ok(c) = self.conns.lock() else { return false };
        let victim = c
            .values()
            .filter(|h| h.busy.load(Ordering::Relaxed) == 0)
            .map(|h| (h.idle_ms(), h))
            .filter(|(idle, _)| *idle >= min_idle_ms)
            .max_by_key(|(idle, _)| *idle);
        match victim {
            Some((_, h)) => {
                h.evict.notify_one();
                true
            }
            None => false,
        }
    }
}

/// A socket that records when bytes last moved.
struct Tracked {
    inner: TcpStream,
    handle: Arc<ConnHandle>,
}

impl AsyncRead for Tracked {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let r = Pin::new(&mut self.inner).poll_read(cx, buf);
        if matches!(r, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            self.handle.touch();
        }
        r
    }
}

impl AsyncWrite for Tracked {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, data: &[u8]) -> Poll<std::io::Result<usize>> {
        let r = Pin::new(&mut self.inner).poll_write(cx, data);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            self.handle.touch();
        }
        r
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let r = Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            self.handle.touch();
        }
        r
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// Raises the soft limit on open files to the hard limit (where allowed) and returns the soft
/// limit in force.
pub fn raise_fd_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut lim = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
        // SAFETY: getrlimit/setrlimit only read and write the struct passed.
        unsafe {
            if libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) != 0 {
                return None;
            }
            if lim.rlim_cur < lim.rlim_max {
                // Up to the hard limit, bounded (an "unlimited" hard limit is huge).
                let want = libc::rlimit { rlim_cur: lim.rlim_max.min(1 << 20), rlim_max: lim.rlim_max };
                if want.rlim_cur > lim.rlim_cur && libc::setrlimit(libc::RLIMIT_NOFILE, &want) == 0 {
                    lim.rlim_cur = want.rlim_cur;
                }
            }
        }
        #[allow(clippy::unnecessary_cast)] // rlim_t is not u64 on every platform
        Some(lim.rlim_cur as u64)
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// File descriptors kept back for the bundle, logs and the runtime's own files.
const FD_RESERVE: u64 = 256;

/// The connection cap for a file-descriptor limit: what the limit leaves after a reserve, at
/// most 100,000, at least 64.
pub fn default_max_connections(fd_limit: Option<u64>) -> usize {
    let fds = fd_limit.unwrap_or(1024);
    fds.saturating_sub(FD_RESERVE).clamp(64, 100_000) as usize
}

/// Serves connections from `listener` until `stop` is cancelled, then lets every connection
/// finish gracefully for at most `drain_timeout` and cuts the rest.
pub async fn serve(
    listener: TcpListener,
    app: axum::Router,
    limits: ConnLimits,
    registry: Arc<Registry>,
    stop: CancellationToken,
    drain_timeout: Duration,
) -> DrainReport {
    let max = if limits.max_connections == 0 { default_max_connections(None) } else { limits.max_connections };
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder.http1().timer(TokioTimer::new()).header_read_timeout(limits.header_read_timeout);
    builder.http2().timer(TokioTimer::new());
    let builder = Arc::new(builder);
    let svc = tower::ServiceBuilder::new()
        .layer(tower_http::timeout::RequestBodyTimeoutLayer::new(limits.body_read_timeout))
        .service(app);
    let mut tasks = JoinSet::new();
    let mut last_refusal_log: Option<Instant> = None;
    loop {
        let accepted = tokio::select! {
            biased;
            _ = stop.cancelled() => break,
            Some(_) = tasks.join_next(), if !tasks.is_empty() => continue,
            a = listener.accept() => a,
        };
        let stream = match accepted {
            Ok((s, _)) => s,
            Err(e) => {
                // Out of file descriptors (or another per-connection error): wait for some to be
                // freed instead of retrying in a busy loop.
                metrics::counter!("posefuse_accept_errors_total").increment(1);
                if last_refusal_log.is_none_or(|t| t.elapsed() > Duration::from_secs(5)) {
                    tracing::warn!("accept failed: {e}; backing off");
                    last_refusal_log = Some(Instant::now());
                }
                tokio::select! {
                    _ = stop.cancelled() => break,
                    _ = tokio::time::sleep(Duration::from_millis(50)) => {}
                }
                continue;
            }
        };
        if registry.open() >= max && !registry.evict_idlest(100) {
            metrics::counter!("posefuse_connections_refused_total").increment(1);
            if last_refusal_log.is_none_or(|t| t.elapsed() > Duration::from_secs(5)) {
                tracing::warn!(max_connections = max, "connection cap reached and none idle: closing new connections");
                last_refusal_log = Some(Instant::now());
            }
            drop(stream);
            continue;
        }
        // Responses go out as several small writes (headers, body, gRPC trailers); Nagle's
        // algorithm would hold them back for the peer's delayed ACK (~40 ms).
        let _ = stream.set_nodelay(true);
        let (id, handle) = registry.add();
        let (builder, svc, stop, registry) = (builder.clone(), svc.clone(), stop.clone(), registry.clone());
        let idle = limits.idle_timeout;
        tasks.spawn(async move {
            serve_one(stream, handle, &builder, svc, stop, idle).await;
            registry.remove(id);
        });
    }
    drop(listener);
    let open = tasks.len();
    if open > 0 {
        tracing::info!(connections = open, "listener closed; waiting for open connections to finish");
    }
    let finished = tokio::time::timeout(drain_timeout, async { while tasks.join_next().await.is_some() {} }).await;
    let mut report = DrainReport::default();
    if finished.is_err() {
        report.connections_cut = tasks.len();
        tasks.abort_all();
        while tasks.join_next().await.is_some() {}
    }
    report
}

/// Marks a connection's [`Peer`] closed when the connection ends.
struct Closing(Arc<Peer>);

impl Drop for Closing {
    fn drop(&mut self) {
        self.0.closed();
    }
}

async fn serve_one<S>(
    stream: TcpStream,
    handle: Arc<ConnHandle>,
    builder: &auto::Builder<TokioExecutor>,
    svc: S,
    stop: CancellationToken,
    idle: Duration,
) where
    S: tower::Service<axum::http::Request<hyper::body::Incoming>, Response = axum::response::Response>
        + Clone
        + Send
        + 'static,
    S::Future: Send + 'static,
    S::Error: Into<Box<dyn std::error::Error + Send + Sync>> + Send + Sync + 'static,
{
    let busy = handle.clone();
    let peer = Peer::new(stream.as_raw_fd());
    let on_request = peer.clone();
    let counted = tower::service_fn(move |mut req: axum::http::Request<hyper::body::Incoming>| {
        let mut svc = svc.clone();
        let busy = busy.clone();
        req.extensions_mut().insert(on_request.clone());
        busy.busy.fetch_add(1, Ordering::Relaxed);
        async move {
            let r = tower::ServiceExt::ready(&mut svc).await;
            let r = match r {
                Ok(s) => s.call(req).await,
                Err(e) => Err(e),
            };
            busy.busy.fetch_sub(1, Ordering::Relaxed);
            busy.touch();
            r
        }
    });
    let io = TokioIo::new(Tracked { inner: stream, handle: handle.clone() });
    let conn = builder.serve_connection_with_upgrades(io, TowerToHyperService::new(counted));
    tokio::pin!(conn);
    // Dropped before `conn` (and its socket): a request still holding `peer` never asks about a
    // closed descriptor.
    let _closing = Closing(peer);
    let mut draining = false;
    loop {
        let quiet_for = Duration::from_millis(handle.idle_ms());
        let check_in = idle.saturating_sub(quiet_for).max(Duration::from_millis(10));
        tokio::select! {
            r = conn.as_mut() => {
                if let Err(e) = r {
                    tracing::debug!("connection ended: {e}");
                }
                return;
            }
            _ = stop.cancelled(), if !draining => {
                draining = true;
                conn.as_mut().graceful_shutdown();
            }
            _ = handle.evict.notified() => {
                metrics::counter!("posefuse_connections_evicted_total").increment(1);
                return;
            }
            _ = tokio::time::sleep(check_in) => {
                if handle.busy.load(Ordering::Relaxed) == 0 && handle.idle_ms() >= idle.as_millis() as u64 {
                    metrics::counter!("posefuse_connections_idle_closed_total").increment(1);
                    return;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_follows_the_descriptor_limit() {
        assert_eq!(default_max_connections(Some(1024)), 768);
        assert_eq!(default_max_connections(Some(100)), 64);
        assert_eq!(default_max_connections(Some(1 << 20)), 100_000);
    }

    #[tokio::test]
    async fn eviction_picks_the_quietest_idle_connection() {
        let r = Registry::default();
        let (_, a) = r.add();
        let (_, b) = r.add();
        assert!(!r.evict_idlest(100), "nothing has been quiet for 100 ms");
        a.last_io_ms.store(0, Ordering::Relaxed);
        b.last_io_ms.store(0, Ordering::Relaxed);
        std::thread::sleep(Duration::from_millis(120));
        b.busy.store(1, Ordering::Relaxed);
        assert!(r.evict_idlest(100));
        // `a` was asked to close (busy `b` is never evicted).
        let woke = tokio::time::timeout(Duration::from_millis(50), a.evict.notified()).await.is_ok();
        assert!(woke);
    }
}
