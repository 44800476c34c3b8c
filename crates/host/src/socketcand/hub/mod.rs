//! A socketcand server acting as a hub: each channel name is an isolated virtual bus shared by
//! all clients that opened it (TCP clients and in-process [`MemPort`]s).
//!
//! One thread serves every TCP client, event-driven (`mio`: epoll): it accepts, reads and parses,
//! forwards, and writes. Each raw-mode client has a bounded queue that the channel's senders
//! (other clients, in-process [`MemPort`]s on any thread) only ever `try_send` into, waking the
//! I/O thread; a client that reads slowly or not at all loses frames (counted) and never stalls
//! the others. Its socket is written without blocking, with at most [`HubConfig::out_limit`]
//! bytes of frames waiting; replies may add as much again, then the hub stops reading from the
//! client until it reads them (backpressure). A client whose socket and output are full costs
//! nothing per frame: its frames are dropped (counted) by their sender, and its socket is not
//! tried again before it is writable.
//!
//! Limits: at most [`HubConfig::max_clients`] connections at once; one more is told
//! `< error too many clients >` and closed. Threads do not grow with clients at all. A client
//! must open a channel (`open`: then in BCM mode, as with socketcand) within [`HubConfig::handshake_timeout`], and a
//! client on a channel that sends nothing for [`HubConfig::idle_timeout`] (off by default:
//! listen-only clients are normal) is closed.

use std::collections::HashMap;
use std::io;
use std::net::{SocketAddr, TcpListener, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::thread::JoinHandle;
use std::time::Duration;

use mio::{Poll, Token, Waker};

use super::codec::ErrorFrame;
use crate::mem::{BusCore, MemBus, MemPort};

/// The default listen address: loopback only.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:29536";

/// Default of [`HubConfig::out_limit`].
pub const OUT_LIMIT: usize = 64 * 1024;

const LISTENER: Token = Token(usize::MAX - 1);
/// Least time between two warnings of failing accepts.
const ACCEPT_WARN_EVERY: Duration = Duration::from_secs(60);
/// Connections accepted per turn of the event loop.
const ACCEPT_SLICE: usize = 64;
const WAKER: Token = Token(usize::MAX - 2);

/// Bytes written to a client between two looks at how much of it the client has not read.
const CHECK_EVERY: usize = 4 * 1024;
/// A client that has this much not read (its receive window shrunk by it, or our send queue
/// waiting for it) does not read as fast as frames come: it is written in batches, at most
/// every [`SLOW_PERIOD`], instead of once per frame.
const SLOW_QUEUE: usize = 16 * 1024;
/// Below this it keeps up again.
const FAST_QUEUE: usize = 4 * 1024;
/// How often a slow client is written (its frames wait in its queue meanwhile).
const SLOW_PERIOD: Duration = Duration::from_millis(100);
/// Slow clients are written a share at a time, every [`SLOW_PERIOD`] / this.
const SLOW_SLICES: u32 = 50;

/// Hub tuning.
#[derive(Clone, Debug)]
pub struct HubConfig {
    /// Frames queued per TCP client before further frames to it are dropped.
    pub queue_len: usize,
    /// `SO_SNDBUF` for client sockets (`None`: kernel autotuning). A fixed, modest buffer makes a
    /// stuck client start losing frames after a bounded backlog instead of megabytes.
    pub send_buffer: Option<usize>,
    /// Most TCP clients connected at once; further connections are refused. Also kept below the
    /// process's limit of open files (less 64 for everything else), so that the hub refuses
    /// cleanly instead of failing to accept.
    pub max_clients: usize,
    /// Time from accept to `open` (the client is then in BCM mode); a client slower than that
    /// is closed.
    pub handshake_timeout: Duration,
    /// Longest silence of a client on a channel (any mode) before it is closed (`None`: no limit).
    pub idle_timeout: Option<Duration>,
    /// Give bus errors ([`HubHandle::post_error`]) to every raw and BCM client, as socketcand
    /// does when started with an error mask (`-e`); off by default: otherwise only clients
    /// that sent the extension `< errors on >` get them.
    pub error_frames: bool,
    /// How each channel delivers frames: paced at a bit rate (default
    /// [`DEFAULT_BITRATE_KBPS`](crate::bus::DEFAULT_BITRATE_KBPS)) or instant.
    pub pacing: crate::bus::Pacing,
    /// Bytes that may wait in the hub for a client's socket (default [`OUT_LIMIT`]). Frames,
    /// bus errors and statistics lines are added only below it (beyond, the client loses them,
    /// counted for frames). Replies to its commands (`< ok >`, `< echo >`, `< error … >`) may
    /// take as much again; with twice this waiting the hub reads nothing more from the client
    /// until it has read its answers (backpressure through TCP, as a socketcand process
    /// blocked in `send` does). A client thus never holds more than twice this (and one reply)
    /// in the hub, plus the input read but not yet handled (< 4 KiB).
    pub out_limit: usize,
    /// How long a timed client (`< clock on >`) that is behind may hold its channel's bus
    /// (the clock's stall bound, default [`crate::clock::STALL_BOUND`]; docs/CLOCK.md).
    pub stall_bound: Duration,
}

impl Default for HubConfig {
    fn default() -> Self {
        HubConfig {
            queue_len: 4096,
            send_buffer: Some(256 * 1024),
            max_clients: 10_000,
            handshake_timeout: Duration::from_secs(10),
            idle_timeout: None,
            error_frames: false,
            pacing: crate::bus::Pacing::default(),
            out_limit: OUT_LIMIT,
            stall_bound: crate::clock::STALL_BOUND,
        }
    }
}

/// Counters of a running hub.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HubStats {
    /// TCP clients currently connected (in any state).
    pub clients: usize,
    /// TCP connections accepted since start.
    pub accepted: u64,
    /// Channels with at least one participant.
    pub channels: usize,
    /// Frames received from TCP clients.
    pub frames_in: u64,
    /// Frame deliveries dropped because a participant's queue was full, since start.
    pub dropped: u64,
    /// Frames that a TCP client could not be given (remote frames with DLC > 0).
    pub unencodable: u64,
    /// Connections refused because [`HubConfig::max_clients`] were connected.
    pub refused: u64,
    /// Most bytes that ever waited in the hub for one client (bounded by twice
    /// [`HubConfig::out_limit`] and one reply).
    pub out_peak: usize,
}

struct Shared {
    config: HubConfig,
    local_addr: SocketAddr,
    channels: Mutex<HashMap<String, Weak<BusCore>>>,
    shutdown: AtomicBool,
    waker: Arc<Waker>,
    ready: Arc<Mutex<Vec<usize>>>,
    clients: AtomicUsize,
    accepted: AtomicU64,
    frames_in: AtomicU64,
    /// Drops of all channels, past and present.
    dropped: Arc<AtomicU64>,
    unencodable: AtomicU64,
    refused: AtomicU64,
    out_peak: AtomicUsize,
    /// Bus errors waiting for the I/O thread, by channel.
    errors: Arc<ErrorQueue>,
}

impl Shared {
    fn channel(&self, name: &str) -> Arc<BusCore> {
        let mut map = self.channels.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(core) = map.get(name).and_then(Weak::upgrade) {
            return core;
        }
        // Forget channels nobody uses any more, so many channel names do not accumulate.
        map.retain(|_, w| w.strong_count() > 0);
        let core = BusCore::create_with_clock(
            self.config.pacing,
            self.dropped.clone(),
            crate::clock::SimClock::wall_with_stall_bound(self.config.stall_bound),
        );
        // The timeline's error frames go to the channel's TCP clients that take errors.
        let (errors, waker, channel) = (self.errors.clone(), self.waker.clone(), name.to_string());
        core.set_error_hook(Box::new(move |ef| {
            if push_error(&errors, (channel.clone(), *ef, None)) {
                let _ = waker.wake();
            }
        }));
        map.insert(name.to_string(), Arc::downgrade(&core));
        core
    }

    fn stats(&self) -> HubStats {
        let map = self.channels.lock().unwrap_or_else(|e| e.into_inner());
        let live: Vec<Arc<BusCore>> = map.values().filter_map(Weak::upgrade).collect();
        drop(map);
        HubStats {
            clients: self.clients.load(Ordering::Relaxed),
            accepted: self.accepted.load(Ordering::Relaxed),
            channels: live.iter().filter(|c| c.member_count() > 0).count(),
            frames_in: self.frames_in.load(Ordering::Relaxed),
            dropped: self.dropped.load(Ordering::Relaxed),
            unencodable: self.unencodable.load(Ordering::Relaxed),
            refused: self.refused.load(Ordering::Relaxed),
            out_peak: self.out_peak.load(Ordering::Relaxed),
        }
    }

    fn attach(&self, channel: &str) -> MemPort {
        MemBus::from_core(self.channel(channel), self.config.queue_len).attach()
    }

    fn post_error(&self, channel: &str, e: ErrorFrame) {
        self.post_error_from(channel, e, None);
    }

    /// Queues a bus error for the clients of `channel`, except the connection `from`.
    fn post_error_from(&self, channel: &str, e: ErrorFrame, from: Option<usize>) {
        if push_error(&self.errors, (channel.to_string(), e, from)) {
            let _ = self.waker.wake();
        }
    }

    fn channel_stats(&self) -> Vec<(String, crate::can::BusStats)> {
        let map = self.channels.lock().unwrap_or_else(|e| e.into_inner());
        let mut v: Vec<(String, crate::can::BusStats)> = map
            .iter()
            .filter_map(|(name, w)| {
                let core = w.upgrade()?;
                (core.member_count() > 0)
                    .then(|| core.stats(None).map(|s| (name.clone(), s)))
                    .flatten()
            })
            .collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    }

    fn shutdown(&self) {
        if !self.shutdown.swap(true, Ordering::SeqCst) {
            let _ = self.waker.wake();
        }
    }
}

/// Bus errors waiting for the I/O thread: channel, error, and the connection that posted it.
type ErrorQueue = Mutex<Vec<(String, ErrorFrame, Option<usize>)>>;

/// Queues a bus error; false when the queue is full (a flood of errors with a stuck I/O thread
/// must not grow without limit: the excess is lost).
fn push_error(q: &ErrorQueue, e: (String, ErrorFrame, Option<usize>)) -> bool {
    let mut q = q.lock().unwrap_or_else(|e| e.into_inner());
    if q.len() >= 1024 {
        return false;
    }
    q.push(e);
    true
}

/// Descriptors the hub may use for clients: the soft limit of open files less 64.
fn open_file_budget() -> usize {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes the struct we own.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) } != 0 {
        return usize::MAX;
    }
    usize::try_from(lim.rlim_cur)
        .unwrap_or(usize::MAX)
        .saturating_sub(64)
}

/// A bound, not yet running hub.
pub struct Hub {
    listener: TcpListener,
    poll: Poll,
    shared: Arc<Shared>,
}

impl Hub {
    /// Binds to `addr` (e.g. [`DEFAULT_LISTEN`]; port 0 picks a free port) with default tuning.
    pub fn bind(addr: impl ToSocketAddrs) -> io::Result<Hub> {
        Self::bind_with(addr, HubConfig::default())
    }

    /// Binds with explicit tuning.
    pub fn bind_with(addr: impl ToSocketAddrs, mut config: HubConfig) -> io::Result<Hub> {
        config.queue_len = config.queue_len.max(1);
        config.out_limit = config.out_limit.max(64);
        config.max_clients = config.max_clients.min(open_file_budget()).max(1);
        let listener = TcpListener::bind(addr)?;
        listener.set_nonblocking(true)?;
        let local_addr = listener.local_addr()?;
        let poll = Poll::new()?;
        let waker = Arc::new(Waker::new(poll.registry(), WAKER)?);
        Ok(Hub {
            listener,
            poll,
            shared: Arc::new(Shared {
                config,
                local_addr,
                channels: Mutex::new(HashMap::new()),
                shutdown: AtomicBool::new(false),
                waker,
                ready: Arc::new(Mutex::new(Vec::new())),
                clients: AtomicUsize::new(0),
                accepted: AtomicU64::new(0),
                frames_in: AtomicU64::new(0),
                dropped: Arc::new(AtomicU64::new(0)),
                unencodable: AtomicU64::new(0),
                refused: AtomicU64::new(0),
                out_peak: AtomicUsize::new(0),
                errors: Arc::new(Mutex::new(Vec::new())),
            }),
        })
    }

    /// The address actually bound.
    pub fn local_addr(&self) -> SocketAddr {
        self.shared.local_addr
    }

    /// Joins `channel` as an in-process participant (no TCP): it sees every frame of the
    /// channel's TCP clients and other ports, and they see its frames.
    pub fn attach(&self, channel: &str) -> MemPort {
        self.shared.attach(channel)
    }

    /// Current counters.
    pub fn stats(&self) -> HubStats {
        self.shared.stats()
    }

    /// A handle that stops [`Hub::run`] from another thread.
    pub fn shutdown_handle(&self) -> ShutdownHandle {
        ShutdownHandle {
            shared: self.shared.clone(),
        }
    }
}

/// Stops a hub: closes the listener and every client connection. Cheap to clone.
#[derive(Clone)]
pub struct ShutdownHandle {
    shared: Arc<Shared>,
}

impl ShutdownHandle {
    /// Stops the hub; idempotent. In-process ports stay usable among themselves.
    pub fn shutdown(&self) {
        self.shared.shutdown();
    }
}

/// A hub running on a background thread; dropping it shuts the hub down.
pub struct HubHandle {
    shutdown: ShutdownHandle,
    join: Option<JoinHandle<io::Result<()>>>,
}

impl HubHandle {
    /// The address the hub listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.shutdown.shared.local_addr
    }

    /// See [`Hub::attach`].
    pub fn attach(&self, channel: &str) -> MemPort {
        self.shutdown.shared.attach(channel)
    }

    /// Current counters.
    pub fn stats(&self) -> HubStats {
        self.shutdown.shared.stats()
    }

    /// Load and counters of every channel in use (paced channels), by name.
    pub fn channel_stats(&self) -> Vec<(String, crate::can::BusStats)> {
        self.shutdown.shared.channel_stats()
    }

    /// A handle to stop the hub from elsewhere.
    pub fn shutdown_handle(&self) -> ShutdownHandle {
        self.shutdown.clone()
    }

    /// Reports a bus error on `channel` to its TCP clients that take error frames (see
    /// [`HubConfig::error_frames`]) as `< error CLASS SEC.USEC D0 .. D7 >`.
    pub fn post_error(&self, channel: &str, e: ErrorFrame) {
        self.shutdown.shared.post_error(channel, e);
    }

    /// Whether the I/O thread is still running.
    pub fn is_running(&self) -> bool {
        self.join.as_ref().is_some_and(|j| !j.is_finished())
    }

    /// Stops the hub and waits for the I/O thread to end.
    pub fn shutdown(mut self) -> io::Result<()> {
        self.stop()
    }

    fn stop(&mut self) -> io::Result<()> {
        self.shutdown.shutdown();
        match self.join.take() {
            Some(j) => j
                .join()
                .unwrap_or_else(|_| Err(io::Error::other("hub I/O thread panicked"))),
            None => Ok(()),
        }
    }
}

impl Drop for HubHandle {
    fn drop(&mut self) {
        let _ = self.stop();
    }
}

mod conn;
mod event_loop;
