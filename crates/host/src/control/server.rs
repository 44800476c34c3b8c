//! The control interface's server (a loopback TCP listener answering JSON lines, one thread per
//! connection, bounded in count, line length and idle time) and its one-shot client [`call`].
//! Above the runtime: each request goes to a [`ControlHandle`].

use std::io::{self, BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use serde_json::{json, Value};

use super::request::{parse_request, Request};
use crate::runtime::ControlHandle;

/// Longest request line accepted (a request is a few dozen bytes). A longer line is answered
/// with one error and skipped up to its newline: no part of it is ever run as a request.
pub const MAX_LINE: usize = 64 * 1024;

/// Most control connections served at once; one more is answered with an error and closed.
/// Clients are test harnesses (a handful); the cap keeps a runaway client from using up
/// threads.
pub const MAX_CONNECTIONS: usize = 32;

/// A running control server.
pub struct ControlServer {
    addr: SocketAddr,
    _thread: JoinHandle<()>,
}

impl ControlServer {
    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }
}

/// How long a control connection may stay without a complete request before it is closed
/// (and how long an answer may wait for its client to take it). Clients keep a connection
/// only while they use it, or reconnect: the dashboard and `canpos ctl` connect per request,
/// the Python client reconnects when it finds its connection closed.
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(30);

/// Longest answer line [`call`] reads (a `state` answer is a few KiB): a server that sends
/// an endless line gets an error, not all of the client's memory.
pub const MAX_ANSWER: usize = 1024 * 1024;

/// Limits of a control server ([`serve_with`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ServeOptions {
    /// A connection is closed, without a word, when no complete request line arrives within
    /// this time after it opened or after its last answer; it is also closed when an answer
    /// cannot be handed to the socket within this time (its client does not read). Default
    /// [`IDLE_TIMEOUT`]; at least 1 ms is used.
    pub idle_timeout: Duration,
    /// Connections served at once; one more gets one error line and is closed. Default
    /// [`MAX_CONNECTIONS`].
    pub max_connections: usize,
}

impl Default for ServeOptions {
    fn default() -> Self {
        ServeOptions {
            idle_timeout: IDLE_TIMEOUT,
            max_connections: MAX_CONNECTIONS,
        }
    }
}

/// Serves the control interface on `addr`, answering through `handle`, with the default
/// [`ServeOptions`]. Each connection gets a thread (clients are test harnesses: few). Warns
/// when `addr` is not loopback: the interface has no authentication.
pub fn serve(addr: impl ToSocketAddrs, handle: ControlHandle) -> io::Result<ControlServer> {
    serve_on(TcpListener::bind(addr)?, handle)
}

/// [`serve`] on a listener bound earlier: a host binds before its sensors boot, so that a
/// client that saw the boot-up can connect at once (connections wait in the backlog until
/// the runtime is up).
pub fn serve_on(listener: TcpListener, handle: ControlHandle) -> io::Result<ControlServer> {
    serve_with(listener, handle, ServeOptions::default())
}

/// [`serve_on`] with other limits (a short idle timeout in a test, say).
///
/// What a connection can hold: one request line (at most [`MAX_LINE`] bytes) and one answer
/// at a time. Answers are written straight to the socket, never queued here: a client that
/// sends requests and never reads fills the kernel's socket buffers, then the server stops
/// reading its requests (TCP holds the client back), and after `idle_timeout` without
/// progress the connection is closed. So every connection costs at most a line, an answer and
/// its thread, for at most `idle_timeout` past its last request.
pub fn serve_with(
    listener: TcpListener,
    handle: ControlHandle,
    options: ServeOptions,
) -> io::Result<ControlServer> {
    let addr = listener.local_addr()?;
    crate::sys::warn_if_exposed(addr, "the control interface");
    let open = Arc::new(AtomicUsize::new(0));
    let thread = std::thread::Builder::new()
        .name("canpos-control".into())
        .spawn(move || {
            for conn in listener.incoming() {
                let stream = match conn {
                    Ok(s) => s,
                    Err(e) => {
                        // Out of descriptors, say: retrying at once would spin; the connection
                        // waits in the backlog meanwhile.
                        tracing::warn!(error = %e, "control interface: accept failed");
                        std::thread::sleep(Duration::from_millis(100));
                        continue;
                    }
                };
                if open.fetch_add(1, Ordering::SeqCst) >= options.max_connections {
                    open.fetch_sub(1, Ordering::SeqCst);
                    refuse(stream, options.max_connections);
                    continue;
                }
                let h = handle.clone();
                let count = Arc::clone(&open);
                let spawned = std::thread::Builder::new()
                    .name("canpos-control-conn".into())
                    .spawn(move || {
                        match serve_conn(stream, h, options.idle_timeout) {
                            Ok(End::Closed) => {}
                            Ok(End::Idle) => tracing::debug!(
                                timeout_s = options.idle_timeout.as_secs_f64(),
                                "control connection closed: idle"
                            ),
                            Ok(End::NotReading) => tracing::warn!(
                                timeout_s = options.idle_timeout.as_secs_f64(),
                                "control connection closed: its client takes no answers"
                            ),
                            Err(e) => tracing::debug!(error = %e, "control connection ended"),
                        }
                        count.fetch_sub(1, Ordering::SeqCst);
                    });
                if spawned.is_err() {
                    open.fetch_sub(1, Ordering::SeqCst);
                }
            }
        })?;
    Ok(ControlServer {
        addr,
        _thread: thread,
    })
}

/// Answers a connection beyond the limit with one error line and closes it, at once: the
/// accept loop never waits on that client (a fresh socket's buffer takes the line whole).
fn refuse(stream: TcpStream, max: usize) {
    let line = format!(
        "{}\n",
        json!({"ok": false, "error": format!("too many control connections (at most {max}); idle ones are closed after their timeout, try again")})
    );
    let _ = stream.set_nonblocking(true);
    let _ = (&stream).write_all(line.as_bytes());
    let _ = stream.shutdown(std::net::Shutdown::Write);
}

/// One line read by [`read_line_limited`].
#[derive(Debug, PartialEq, Eq)]
pub enum Line {
    /// A complete line (without its newline; the last line may lack one).
    Text(Vec<u8>),
    /// A line longer than the limit; it was read up to and including its newline and dropped.
    TooLong,
    /// End of the stream.
    Eof,
}

/// Reads one line of at most `limit` bytes. A longer line is consumed up to its newline (or
/// the end of the stream) without keeping more than `limit` bytes, and reported as
/// [`Line::TooLong`]: the caller answers it once and no tail of it becomes a request.
pub fn read_line_limited(r: &mut impl BufRead, limit: usize) -> io::Result<Line> {
    let mut line = Vec::new();
    let mut too_long = false;
    loop {
        let buf = match r.fill_buf() {
            Ok(b) => b,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        if buf.is_empty() {
            return Ok(match (too_long, line.is_empty()) {
                (true, _) => Line::TooLong,
                (false, true) => Line::Eof,
                (false, false) => Line::Text(line),
            });
        }
        let (chunk, done) = match buf.iter().position(|&b| b == b'\n') {
            Some(i) => (&buf[..i], Some(i + 1)),
            None => (buf, None),
        };
        if !too_long {
            if line.len() + chunk.len() > limit {
                too_long = true;
                line = Vec::new();
            } else {
                line.extend_from_slice(chunk);
            }
        }
        let used = done.unwrap_or(buf.len());
        r.consume(used);
        if done.is_some() {
            return Ok(if too_long {
                Line::TooLong
            } else {
                Line::Text(line)
            });
        }
    }
}

/// Answers one request line: parsed here, checked and applied by the runtime.
pub fn answer_line(line: &str, handle: &ControlHandle) -> Value {
    match parse_request(line) {
        Ok(req) => handle.request(req),
        Err(e) => e,
    }
}

/// How a connection ended without an error.
enum End {
    /// The client closed it.
    Closed,
    /// No request within the idle timeout.
    Idle,
    /// An answer not taken within the idle timeout: the client does not read.
    NotReading,
}

/// A connection's reading side with a deadline for the whole of the next request line: a
/// client that sends nothing, or a byte now and then, is closed all the same.
struct Deadline {
    stream: TcpStream,
    at: std::time::Instant,
}

impl io::Read for Deadline {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let left = self.at.saturating_duration_since(std::time::Instant::now());
        if left.is_zero() {
            return Err(io::ErrorKind::TimedOut.into());
        }
        self.stream.set_read_timeout(Some(left))?;
        self.stream.read(buf)
    }
}

/// Now plus `d`, or a year from now when `d` is beyond what the clock can add.
fn deadline_after(d: Duration) -> std::time::Instant {
    let now = std::time::Instant::now();
    now.checked_add(d)
        .unwrap_or_else(|| now + Duration::from_secs(365 * 24 * 3600))
}

fn serve_conn(stream: TcpStream, handle: ControlHandle, idle: Duration) -> io::Result<End> {
    // A socket timeout of zero is refused by the OS (and would mean none).
    let idle = idle.max(Duration::from_millis(1));
    stream.set_nodelay(true)?;
    // An answer the client does not take within the idle time ends the connection.
    stream.set_write_timeout(Some(idle))?;
    let mut out = stream.try_clone()?;
    let mut reader = BufReader::new(Deadline {
        stream,
        at: deadline_after(idle),
    });
    loop {
        let line = match read_line_limited(&mut reader, MAX_LINE) {
            Ok(l) => l,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
                ) =>
            {
                return Ok(End::Idle)
            }
            Err(e) => return Err(e),
        };
        let answer = match line {
            Line::Eof => return Ok(End::Closed),
            Line::TooLong => json!({
                "ok": false,
                "error": format!("request line longer than {MAX_LINE} bytes; discarded up to its newline")
            }),
            Line::Text(bytes) => match std::str::from_utf8(&bytes) {
                Err(_) => json!({"ok": false, "error": "request line is not UTF-8"}),
                Ok(text) => {
                    let text = text.trim();
                    if text.is_empty() {
                        continue;
                    }
                    answer_line(text, &handle)
                }
            },
        };
        let mut s = answer.to_string();
        s.push('\n');
        match out.write_all(s.as_bytes()) {
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
                ) =>
            {
                return Ok(End::NotReading)
            }
            r => r?,
        }
        reader.get_mut().at = deadline_after(idle);
    }
}

/// Client side: sends one request and returns the answer (used by `canpos ctl`).
pub fn call(addr: impl ToSocketAddrs, req: &Request, timeout: Duration) -> io::Result<Value> {
    let mut last = None;
    for a in addr.to_socket_addrs()? {
        match TcpStream::connect_timeout(&a, timeout) {
            Ok(mut s) => {
                s.set_write_timeout(Some(timeout))?;
                let mut line = serde_json::to_string(req).map_err(io::Error::other)?;
                line.push('\n');
                s.write_all(line.as_bytes())?;
                // The whole answer within `timeout`, not each read: a server that trickles
                // bytes cannot hold the caller longer.
                let mut r = BufReader::new(Deadline {
                    stream: s,
                    at: deadline_after(timeout),
                });
                let reply = match read_line_limited(&mut r, MAX_ANSWER)? {
                    Line::Text(t) => t,
                    Line::TooLong => {
                        return Err(io::Error::new(
                            io::ErrorKind::InvalidData,
                            format!("answer longer than {MAX_ANSWER} bytes"),
                        ))
                    }
                    Line::Eof => {
                        return Err(io::Error::new(
                            io::ErrorKind::UnexpectedEof,
                            "the control interface closed the connection without an answer",
                        ))
                    }
                };
                return serde_json::from_slice(&reply).map_err(|e| {
                    io::Error::new(io::ErrorKind::InvalidData, format!("bad answer: {e}"))
                });
            }
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no address")))
}
