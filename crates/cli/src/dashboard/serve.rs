//! The dashboard's accept loop (issue 35 item 5). axum::serve sets no header timeout, caps no
//! connections and logs an accept error a second; a sensor's `--web` shares its descriptors
//! with storage, the bus and the control interface, so this loop
//! * serves at most [`connection_cap`] connections at once, below the process's descriptor
//!   budget; one more is answered 503 and closed at once, and the refusals are logged 1st,
//!   2nd, 4th, 8th… (a flood does not flood the log);
//! * closes a connection whose request head is not complete within [`HEADER_TIMEOUT`] (the
//!   time between requests of a kept-alive connection counts too), whose body is not within
//!   [`super::guard::BODY_TIMEOUT`], and one whose client takes no response byte for
//!   [`WRITE_STALL`] (an event stream nobody reads);
//! * backs off when accept fails (out of descriptors: 10 ms doubling to 1 s), logging the
//!   first failure and then at most one summary a minute.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::extract::Request;
use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tower::ServiceExt;

use super::guard::Served;

/// Time for a request head to arrive, from the connection's start or the previous response.
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// A client that takes no byte of a response for this long is disconnected.
pub const WRITE_STALL: Duration = Duration::from_secs(30);
/// Web connections at most, however many descriptors there are: a browser tab holds its event
/// stream and up to six requests.
pub const MAX_CONNECTIONS: usize = 128;
/// Descriptors left to the rest of the process beyond those open when the dashboard starts:
/// storage (state, lock and temporary files, the directory), bus connections, the control
/// interface's 32 connections, the runtime's own.
pub const RESERVE: usize = 64;
/// Longest request head, bytes (431 beyond).
const MAX_HEAD: usize = 64 * 1024;

/// Connections the dashboard serves at once: half of the descriptors left after those open
/// now and [`RESERVE`], at most [`MAX_CONNECTIONS`], at least 1.
pub fn connection_cap() -> usize {
    cap_for(open_file_limit(), open_descriptors())
}

fn cap_for(limit: Option<usize>, open: usize) -> usize {
    match limit {
        Some(l) => (l.saturating_sub(open + RESERVE) / 2).clamp(1, MAX_CONNECTIONS),
        None => MAX_CONNECTIONS,
    }
}

/// The soft limit of open files (None: unlimited or unknown).
fn open_file_limit() -> Option<usize> {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes the struct we own.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) } != 0
        || lim.rlim_cur == libc::RLIM_INFINITY
    {
        return None;
    }
    usize::try_from(lim.rlim_cur).ok()
}

/// Descriptors open in this process now (0 where /proc is not there).
fn open_descriptors() -> usize {
    std::fs::read_dir("/proc/self/fd").map_or(0, |d| d.count())
}

/// Open web connections, counted down when a connection's task ends.
struct Slot(Arc<AtomicUsize>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

/// Serves `router` on `listener` until `stop` fires; `open` counts the connections.
pub async fn run(
    listener: TcpListener,
    router: Router,
    cap: usize,
    open: Arc<AtomicUsize>,
    stop: tokio::sync::oneshot::Receiver<()>,
) {
    let mut stop = std::pin::pin!(stop);
    let mut failures = AcceptFailures::default();
    let mut refused: u64 = 0;
    loop {
        let accepted = tokio::select! {
            _ = &mut stop => return,
            r = listener.accept() => r,
        };
        let (stream, peer) = match accepted {
            Ok(x) => {
                failures.ok();
                x
            }
            // The peer gave up before the accept: nothing to do.
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::ConnectionAborted
                        | io::ErrorKind::ConnectionReset
                        | io::ErrorKind::Interrupted
                ) =>
            {
                continue
            }
            Err(e) => {
                let wait = failures.failed(&e, Instant::now());
                tokio::select! {
                    _ = &mut stop => return,
                    _ = tokio::time::sleep(wait) => continue,
                }
            }
        };
        if open.load(Ordering::SeqCst) >= cap {
            refused += 1;
            refuse(&stream, cap);
            drop(stream);
            if refused.is_power_of_two() {
                tracing::warn!(%peer, max = cap, refused,
                    "dashboard: web connection refused: too many connections");
            }
            continue;
        }
        let Ok(local) = stream.local_addr() else {
            continue;
        };
        open.fetch_add(1, Ordering::SeqCst);
        let slot = Slot(open.clone());
        let svc = router.clone().map_request(move |mut r: Request<Incoming>| {
            r.extensions_mut().insert(Served(local));
            r
        });
        tokio::spawn(async move {
            let _slot = slot;
            let _ = stream.set_nodelay(true);
            let io = TokioIo::new(Stalled::new(stream, WRITE_STALL));
            let conn = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(HEADER_TIMEOUT)
                .max_header_size(MAX_HEAD)
                .max_buf_size(MAX_HEAD)
                .serve_connection(io, TowerToHyperService::new(svc));
            if let Err(e) = conn.await {
                tracing::debug!(%peer, "dashboard connection: {e}");
            }
        });
    }
}

/// Tells a connection beyond the cap why it is closed, if its socket takes the answer now.
fn refuse(stream: &TcpStream, cap: usize) {
    let body = format!(
        r#"{{"ok":false,"error":"the dashboard serves at most {cap} connections at once; try again later"}}"#
    );
    let answer = format!(
        "HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\nConnection: close\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    );
    let _ = stream.try_write(answer.as_bytes());
}

/// Accept failures (e.g. EMFILE: the connection stays in the backlog, and accept fails again
/// at once): how long to wait, and what to log.
#[derive(Default)]
struct AcceptFailures {
    /// Failures in a row.
    row: u32,
    /// Failures not yet logged, and when the log last spoke.
    unlogged: u64,
    logged_at: Option<Instant>,
}

/// The log speaks of accept failures at most this often.
const FAILURE_LOG_PERIOD: Duration = Duration::from_secs(60);

impl AcceptFailures {
    fn ok(&mut self) {
        self.row = 0;
    }

    /// Counts a failure; the wait before the next accept.
    fn failed(&mut self, e: &io::Error, now: Instant) -> Duration {
        self.row = self.row.saturating_add(1);
        self.unlogged += 1;
        let due = self
            .logged_at
            .is_none_or(|t| now.duration_since(t) >= FAILURE_LOG_PERIOD);
        if due {
            tracing::warn!(
                failures = self.unlogged,
                "dashboard: accept failed: {e}; retrying with a back-off (logged at most once a minute)"
            );
            self.unlogged = 0;
            self.logged_at = Some(now);
        }
        backoff(self.row)
    }
}

/// 10 ms, doubling with each failure in a row, at most 1 s.
fn backoff(row: u32) -> Duration {
    Duration::from_millis(10u64 << row.saturating_sub(1).min(7)).min(Duration::from_secs(1))
}

/// A connection whose writes fail once no byte has gone out for `limit`: a client that stops
/// reading cannot hold its connection (and its descriptor) for ever.
struct Stalled<T> {
    io: T,
    limit: Duration,
    since: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl<T> Stalled<T> {
    fn new(io: T, limit: Duration) -> Self {
        Stalled {
            io,
            limit,
            since: None,
        }
    }

    /// A write-side result: progress restarts the clock, waiting runs it.
    fn watch<R>(&mut self, cx: &mut Context<'_>, r: Poll<io::Result<R>>) -> Poll<io::Result<R>> {
        match r {
            Poll::Ready(r) => {
                self.since = None;
                Poll::Ready(r)
            }
            Poll::Pending => {
                let limit = self.limit;
                let t = self
                    .since
                    .get_or_insert_with(|| Box::pin(tokio::time::sleep(limit)));
                match t.as_mut().poll(cx) {
                    Poll::Ready(()) => Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        format!("the client took nothing for {} s", limit.as_secs()),
                    ))),
                    Poll::Pending => Poll::Pending,
                }
            }
        }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for Stalled<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Stalled<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let r = Pin::new(&mut self.io).poll_write(cx, buf);
        self.watch(cx, r)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let r = Pin::new(&mut self.io).poll_write_vectored(cx, bufs);
        self.watch(cx, r)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let r = Pin::new(&mut self.io).poll_flush(cx);
        self.watch(cx, r)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_keeps_below_the_descriptor_budget() {
        // The usual 1,024 with a sensor's few dozen open: the fixed maximum.
        assert_eq!(cap_for(Some(1024), 40), MAX_CONNECTIONS);
        // A tight limit: half of what is left beyond the reserve.
        assert_eq!(cap_for(Some(256), 30), (256 - 30 - RESERVE) / 2);
        assert!(cap_for(Some(256), 30) + 30 + RESERVE < 256);
        // Nothing left: the page can still be served, one connection at a time.
        assert_eq!(cap_for(Some(64), 60), 1);
        assert_eq!(cap_for(None, 10), MAX_CONNECTIONS);
    }

    /// A client that stops reading: its writes fail once nothing went out for the limit, on
    /// tokio's paused clock; a client that reads keeps its connection however slow it is.
    #[tokio::test(start_paused = true)]
    async fn a_client_that_takes_nothing_is_cut_off() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let limit = Duration::from_secs(30);
        let (near, mut far) = tokio::io::duplex(1024);
        let mut w = Stalled::new(near, limit);
        let t0 = tokio::time::Instant::now();
        // Reads 1 KiB every 20 s: slower than the writes, never stalled for 30 s.
        let reader = tokio::spawn(async move {
            let mut buf = [0u8; 1024];
            for _ in 0..5 {
                tokio::time::sleep(Duration::from_secs(20)).await;
                let _ = far.read(&mut buf).await;
            }
            far
        });
        let mut sent = 0;
        let err = loop {
            match w.write(&[0u8; 256]).await {
                Ok(n) => sent += n,
                Err(e) => break e,
            }
        };
        assert_eq!(err.kind(), io::ErrorKind::TimedOut);
        // The buffer and the five reads went out; then 30 s without a byte.
        assert_eq!(sent, 6 * 1024);
        assert_eq!(t0.elapsed(), Duration::from_secs(5 * 20 + 30));
        drop(reader.await.unwrap());
    }

    #[test]
    fn accept_failures_back_off_and_log_once_a_minute() {
        assert_eq!(backoff(1), Duration::from_millis(10));
        assert_eq!(backoff(2), Duration::from_millis(20));
        assert_eq!(backoff(8), Duration::from_secs(1));
        assert_eq!(backoff(u32::MAX), Duration::from_secs(1));
        let e = io::Error::from_raw_os_error(libc::EMFILE);
        let mut f = AcceptFailures::default();
        let t0 = Instant::now();
        let mut slept = Duration::ZERO;
        // A minute of failures in a row, on the clock the waits make.
        while slept < Duration::from_secs(59) {
            slept += f.failed(&e, t0 + slept);
        }
        // Logged at the first; the rest wait for the next minute.
        assert_eq!(f.logged_at, Some(t0));
        assert!(f.unlogged > 50, "{}", f.unlogged);
        f.failed(&e, t0 + Duration::from_secs(60));
        assert_eq!(f.unlogged, 0);
        // At most one accept a second meanwhile, not a hundred.
        assert!(f.row < 70, "{}", f.row);
        f.ok();
        assert_eq!(
            f.failed(&e, t0 + Duration::from_secs(61)),
            Duration::from_millis(10)
        );
    }
}
