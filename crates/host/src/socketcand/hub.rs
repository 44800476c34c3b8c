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
use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, TryRecvError};
use mio::net::{TcpListener as MioListener, TcpStream};
use mio::{Events, Interest, Poll, Token, Waker};

use super::codec::{self, Decoder, Element, ErrorFrame, Piece};
use super::session::{Effect, Session};
use crate::can::RxFrame;
use crate::mem::{BusCore, MemBus, MemPort, Sink};
use crate::wake::Wake;

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

/// Turns on TCP_QUICKACK: Linux clears it after use, so it is re-armed after every read, and
/// the hub's ACKs never wait the ~40 ms of delayed ACK.
fn quickack(stream: &TcpStream) {
    use std::os::fd::AsRawFd;
    let on: libc::c_int = 1;
    // SAFETY: setsockopt reads one c_int from a pointer we own, on a socket we own.
    unsafe {
        libc::setsockopt(
            stream.as_raw_fd(),
            libc::IPPROTO_TCP,
            libc::TCP_QUICKACK,
            (&on as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        );
    }
}

/// About how many bytes written to a peer it has not read yet: what our send queue holds for it
/// (`SIOCOUTQ`) and how far its advertised receive window shrank below the largest it
/// advertised (`tcpi_snd_wnd`, Linux 5.19 and later; without it only the send queue, which
/// grows once the window is closed). A peer that reads keeps its window open.
fn unread(stream: &TcpStream, peak: &mut u32) -> usize {
    use std::os::fd::AsRawFd;
    let fd = stream.as_raw_fd();
    let mut queued: libc::c_int = 0;
    // SAFETY: the ioctl writes one c_int we own, on a socket we own.
    if unsafe { libc::ioctl(fd, libc::TIOCOUTQ, &mut queued) } != 0 {
        queued = 0;
    }
    // struct tcp_info up to tcpi_snd_wnd (offset 228, `linux/tcp.h`); libc's copy of the
    // struct ends before it.
    const SND_WND: usize = 228;
    let mut info = [0u8; 256];
    let mut len = info.len() as libc::socklen_t;
    // SAFETY: getsockopt writes at most `len` bytes into the buffer we own, and sets `len`.
    let r = unsafe {
        libc::getsockopt(
            fd,
            libc::IPPROTO_TCP,
            libc::TCP_INFO,
            info.as_mut_ptr().cast(),
            &mut len,
        )
    };
    let mut shrunk = 0;
    if r == 0 && len as usize >= SND_WND + 4 {
        let mut w = [0u8; 4];
        w.copy_from_slice(&info[SND_WND..SND_WND + 4]);
        let window = u32::from_ne_bytes(w);
        *peak = (*peak).max(window);
        shrunk = (*peak - window) as usize;
    }
    usize::try_from(queued).unwrap_or(0) + shrunk
}

/// Sends one TCP urgent byte (a space, `MSG_OOB`) to end the client's first read in raw mode at
/// the `< ok >` before it.
///
/// python-can reads the rawmode `< ok >` with one `recv(256)` and compares it exactly, so a frame
/// that arrives before that `recv` runs (the client descheduled, frames flowing) failed its
/// handshake. A receive stops at the urgent mark (BSD sockets, Linux `tcp_recvmsg`), so that
/// read returns `< ok >` alone whenever it runs; the next read skips the byte (it is out of
/// band) and returns the frames. A client with `SO_OOBINLINE` reads a space between two
/// elements, which every socketcand parser skips. Before, the hub held frames back for up to
/// 500 ms after the `< ok >`, until the client spoke: a listen-only client got its first frames
/// late (issue 36 item 4).
fn send_urgent(stream: &TcpStream) -> io::Result<()> {
    use std::os::fd::AsRawFd;
    // SAFETY: sends one byte from a static buffer on a socket we own.
    let n = unsafe {
        libc::send(
            stream.as_raw_fd(),
            b" ".as_ptr().cast(),
            1,
            libc::MSG_OOB | libc::MSG_NOSIGNAL,
        )
    };
    match n {
        1 => Ok(()),
        0 => Err(io::Error::from(io::ErrorKind::WouldBlock)),
        _ => Err(io::Error::last_os_error()),
    }
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

    /// Serves clients on the calling thread until shut down.
    pub fn run(self) -> io::Result<()> {
        EventLoop::new(self)?.run()
    }

    /// Serves clients on a background thread.
    pub fn spawn(self) -> io::Result<HubHandle> {
        let shutdown = self.shutdown_handle();
        let ev = EventLoop::new(self)?;
        let join = thread::Builder::new()
            .name("socketcand-hub".into())
            .spawn(move || ev.run())?;
        Ok(HubHandle {
            shutdown,
            join: Some(join),
        })
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

/// The plain raw-mode text of recent frames: every raw client of a channel gets the same frame
/// with the same timestamp, so it is formatted once, not once per client. Direct-mapped by the
/// frame's time; a miss formats it again.
struct TextCache {
    slots: Vec<Option<Cached>>,
}

/// A frame and its text (`None`: not writable in the plain form).
type Cached = (RxFrame, Option<Box<[u8]>>);

impl TextCache {
    const SLOTS: usize = 1024;

    fn new() -> TextCache {
        TextCache {
            slots: vec![None; Self::SLOTS],
        }
    }

    /// The text of `rx` for a plain raw client (`None`: it cannot be written in that form).
    fn text(&mut self, rx: &RxFrame) -> Option<&[u8]> {
        let t = rx
            .timestamp
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        let h = (t.subsec_nanos() as usize ^ t.as_secs() as usize ^ rx.frame.id() as usize)
            % Self::SLOTS;
        let slot = &mut self.slots[h];
        if !matches!(slot, Some((f, _)) if f == rx) {
            let mut out = Vec::with_capacity(48);
            let text = codec::write_frame(&mut out, &rx.frame, rx.timestamp)
                .then(|| out.into_boxed_slice());
            *slot = Some((*rx, text));
        }
        slot.as_ref().and_then(|(_, t)| t.as_deref())
    }
}

enum State {
    /// Greeted, no channel yet.
    Opening,
    /// On a channel (BCM, raw or control mode: see the connection's [`Session`]).
    Raw {
        channel: String,
        bus: Arc<BusCore>,
        id: u64,
        rx: Receiver<RxFrame>,
        wake: Arc<Wake>,
        dropped: Arc<AtomicU64>,
    },
}

/// One TCP client.
struct Conn {
    stream: TcpStream,
    peer: SocketAddr,
    state: State,
    session: Session,
    decoder: Decoder,
    /// Bytes not yet written, from `out_pos` on.
    out: Vec<u8>,
    out_pos: usize,
    /// Frames of this read not yet on the bus: they enter it together ([`Conn::submit`]).
    sends: Vec<canpos_core::Frame>,
    /// An urgent byte is sent once `out` is written up to here: right after a rawmode
    /// `< ok >` ([`send_urgent`]).
    urgent_at: Option<usize>,
    /// Whether WRITABLE interest is registered (only while bytes wait).
    writable: bool,
    /// The socket refused bytes (WouldBlock): no write is tried until it reports WRITABLE.
    sock_full: bool,
    /// It had much not read at the last look ([`SLOW_QUEUE`]): written in batches.
    slow: bool,
    /// Bytes written since the last look at what it has not read.
    written: usize,
    /// Its token is in the event loop's list of slow clients.
    listed: bool,
    /// The largest receive window the client advertised.
    peak_window: u32,
    /// Input read but not yet handled: the client's output was full ([`HubConfig::out_limit`]); handled,
    /// and reading resumed, once the client has read its answers.
    rest: Vec<u8>,
    handshake_end: Instant,
    last_rx: Instant,
    closed: bool,
    /// A timed client's horizon on its channel bus's clock (`< clock on >`, docs/CLOCK.md):
    /// set by its `< at … >`, its frames stamped with it; dropped when it leaves.
    horizon: Option<crate::clock::Horizon>,
}

impl Conn {
    fn pending(&self) -> usize {
        self.out.len() - self.out_pos + usize::from(self.urgent_at.is_some())
    }

    /// Puts the frames the client sent since the last call on the bus together, at one time:
    /// frames that arrived together (one read of its socket) go out back to back, as a burst
    /// a host writes to its controller does, without gaps from the hub's own scheduling.
    fn submit(&mut self, now: Instant, shared: &Shared, cache: &mut TextCache) {
        if self.sends.is_empty() {
            return;
        }
        let lost = match &self.state {
            State::Raw { bus, id, .. } => bus.transmit_all(*id, &self.sends),
            State::Opening => 0,
        };
        self.sends.clear();
        self.tx_overflow(lost, now, shared, cache);
    }

    /// Its transmit queue on the bus lost `lost` frames (full, the bus busier than it can
    /// take): a client that takes bus errors is told with a controller-problem error frame
    /// with the TX-overflow bit, as SocketCAN reports an overflow to a host, so that a sensor
    /// behind the hub reacts as on the wire (issue 36 item 7). One report per submission.
    fn tx_overflow(&mut self, lost: usize, now: Instant, shared: &Shared, cache: &mut TextCache) {
        let all = shared.config.error_frames;
        if lost == 0 || !self.session.takes_errors(all) {
            return;
        }
        // The frames the bus delivered before go out before it.
        self.fill(now, shared, cache);
        if self.pending() >= shared.config.out_limit {
            return;
        }
        let e = codec::ErrorFrame::tx_overflow(std::time::SystemTime::now());
        self.session.error_frame(&e, all, &mut self.out);
    }

    /// Writes what waits, without blocking.
    fn flush(&mut self) {
        while self.out_pos < self.out.len() || self.urgent_at == Some(self.out_pos) {
            if self.urgent_at == Some(self.out_pos) {
                match send_urgent(&self.stream) {
                    Ok(()) => self.urgent_at = None,
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                        self.sock_full = true;
                        break;
                    }
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(_) => {
                        self.closed = true;
                        return;
                    }
                }
                continue;
            }
            let end = match self.urgent_at {
                Some(u) if u > self.out_pos => u,
                _ => self.out.len(),
            };
            match self.stream.write(&self.out[self.out_pos..end]) {
                Ok(0) => {
                    self.closed = true;
                    return;
                }
                Ok(n) => {
                    self.out_pos += n;
                    self.written += n;
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    self.sock_full = true;
                    break;
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(_) => {
                    self.closed = true;
                    return;
                }
            }
        }
        if self.out_pos == self.out.len() && self.urgent_at.is_none() {
            self.out.clear();
            self.out_pos = 0;
        } else if self.out_pos > OUT_LIMIT {
            self.out.drain(..self.out_pos);
            self.urgent_at = self.urgent_at.map(|u| u - self.out_pos);
            self.out_pos = 0;
        }
    }

    /// Looks at how much the client has not read every [`CHECK_EVERY`] bytes written (and at
    /// every write while slow): true when it changed between keeping up and not.
    fn check_pace(&mut self) -> bool {
        if self.written < CHECK_EVERY && !self.slow {
            return false;
        }
        self.written = 0;
        let queued = unread(&self.stream, &mut self.peak_window);
        let slow = if self.slow {
            queued >= FAST_QUEUE
        } else {
            queued >= SLOW_QUEUE
        };
        let changed = slow != self.slow;
        self.slow = slow;
        if let State::Raw { wake, .. } = &self.state {
            wake.quiet.store(slow, Ordering::Relaxed);
            // Before the queue is looked at again (`service`'s backlog): see `Wake::queued`.
            std::sync::atomic::fence(Ordering::SeqCst);
        }
        changed
    }

    /// Moves queued frames into the output, as long as the output has room.
    fn fill(&mut self, now: Instant, shared: &Shared, cache: &mut TextCache) {
        let State::Raw { rx, wake, .. } = &mut self.state else {
            return;
        };
        // Cleared before draining: a frame sent meanwhile wakes the loop again.
        wake.pending.store(false, Ordering::Release);
        let limit = shared.config.out_limit;
        let plain = self.session.takes_plain_raw();
        while self.out.len() - self.out_pos < limit {
            match rx.try_recv() {
                Ok(f) if plain => {
                    self.session.count_rx(&f.frame);
                    match cache.text(&f) {
                        Some(text) => self.out.extend_from_slice(text),
                        None => {
                            shared.unencodable.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                }
                Ok(f) => {
                    if !self
                        .session
                        .deliver(&f.frame, f.timestamp, now, &mut self.out)
                    {
                        shared.unencodable.fetch_add(1, Ordering::Relaxed);
                    }
                }
                Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
            }
        }
        // Its own controller's state, as a SocketCAN interface reports it (only to a client
        // that takes errors), after the frames that were on the bus before it was taken; it
        // waits while the output is full.
        if self.out.len() - self.out_pos < limit {
            if let Some(s) = wake.take_state() {
                let e = ErrorFrame::for_state(s, std::time::SystemTime::now());
                self.session
                    .error_frame(&e, shared.config.error_frames, &mut self.out);
            }
        }
        // Losses of its frames that joined its queue at their time (one report per wake-up,
        // as one per batch at submission).
        if self.out.len() - self.out_pos < limit && wake.tx_overflowed.swap(false, Ordering::AcqRel)
        {
            let e = ErrorFrame::tx_overflow(std::time::SystemTime::now());
            self.session
                .error_frame(&e, shared.config.error_frames, &mut self.out);
        }
    }

    fn leave(&mut self) {
        self.horizon = None;
        if let State::Raw {
            bus, id, dropped, ..
        } = &self.state
        {
            bus.leave(*id);
            tracing::debug!(peer = %self.peer, dropped = dropped.load(Ordering::Relaxed), "client disconnected");
        }
        self.state = State::Opening;
    }
}

struct EventLoop {
    listener: MioListener,
    poll: Poll,
    shared: Arc<Shared>,
    conns: HashMap<usize, Conn>,
    next_token: usize,
    /// No client deadline comes before this (it may be early: idle deadlines move on).
    earliest: Option<Instant>,
    /// Accepting failed (e.g. out of descriptors) with connections left in the backlog: the
    /// listener is edge-triggered and will not report them again, so retry on a timer.
    accept_retry: bool,
    /// Accepts that failed since the last one that worked, and when that was last logged: a
    /// process out of descriptors retries every 10 ms, and must not log 100 lines a second.
    accept_failures: u64,
    accept_warned: Option<Instant>,
    /// An accept slice ended before the backlog did.
    accept_more: bool,
    /// Connections whose session has timed work (BCM send jobs, statistics): when it is due.
    timed: HashMap<usize, Instant>,
    /// Clients to serve again next turn without waiting for an event: their socket had more to
    /// read than one turn takes, or their queue more than the output took while the socket
    /// still had room. Readiness is edge-triggered: no new event would come for either.
    again: Vec<usize>,
    /// Frames formatted once for all plain raw clients.
    cache: TextCache,
    /// Slow clients (may hold tokens of clients no longer slow or gone: dropped when met), and
    /// where the next slice of them starts.
    slow: Vec<usize>,
    slow_pos: usize,
    /// When the next slice of slow clients is written.
    slow_next: Instant,
}

impl EventLoop {
    fn new(hub: Hub) -> io::Result<EventLoop> {
        let mut listener = MioListener::from_std(hub.listener);
        hub.poll
            .registry()
            .register(&mut listener, LISTENER, Interest::READABLE)?;
        Ok(EventLoop {
            listener,
            poll: hub.poll,
            shared: hub.shared,
            conns: HashMap::new(),
            next_token: 0,
            earliest: None,
            accept_retry: false,
            accept_failures: 0,
            accept_warned: None,
            accept_more: false,
            again: Vec::new(),
            timed: HashMap::new(),
            cache: TextCache::new(),
            slow: Vec::new(),
            slow_pos: 0,
            slow_next: Instant::now(),
        })
    }

    fn run(mut self) -> io::Result<()> {
        tracing::info!(addr = %self.shared.local_addr, "socketcand hub listening");
        let mut events = Events::with_capacity(1024);
        // The deadlines (handshake, idle) are scanned over all clients only when the
        // earliest is due, and at most every SCAN_EVERY: a turn costs the clients that had
        // events, not all of them.
        const SCAN_EVERY: Duration = Duration::from_millis(2);
        let mut next_scan = Instant::now();
        loop {
            if self.shared.shutdown.load(Ordering::SeqCst) {
                break;
            }
            let mut timeout = self
                .earliest
                .map(|d| d.max(next_scan).saturating_duration_since(Instant::now()));
            if self.accept_retry || self.accept_more || !self.again.is_empty() {
                let retry = if self.accept_more || !self.again.is_empty() {
                    Duration::ZERO
                } else {
                    Duration::from_millis(10)
                };
                timeout = Some(timeout.map_or(retry, |t| t.min(retry)));
            }
            if !self.slow.is_empty() {
                let left = self.slow_next.saturating_duration_since(Instant::now());
                timeout = Some(timeout.map_or(left, |t| t.min(left)));
            }
            if let Some(d) = self.timed.values().min() {
                let left = d.saturating_duration_since(Instant::now());
                timeout = Some(timeout.map_or(left, |t| t.min(left)));
            }
            if let Err(e) = self.poll.poll(&mut events, timeout) {
                if e.kind() == io::ErrorKind::Interrupted {
                    continue;
                }
                return Err(e);
            }
            let now = Instant::now();
            let mut touched = Vec::new();
            let again = std::mem::take(&mut self.accept_more);
            if std::mem::take(&mut self.accept_retry) || again {
                self.accept(now);
            }
            for t in std::mem::take(&mut self.again) {
                self.read(t, now);
                touched.push(t);
            }
            for ev in events.iter() {
                match ev.token() {
                    LISTENER => self.accept(now),
                    WAKER => {
                        let ready = std::mem::take(
                            &mut *self.shared.ready.lock().unwrap_or_else(|e| e.into_inner()),
                        );
                        touched.extend(ready);
                        self.post_errors(&mut touched);
                    }
                    Token(t) => {
                        if ev.is_writable() {
                            if let Some(c) = self.conns.get_mut(&t) {
                                c.sock_full = false;
                            }
                        }
                        if ev.is_readable() || ev.is_read_closed() || ev.is_error() {
                            self.read(t, now);
                        }
                        touched.push(t);
                    }
                }
            }
            let now = Instant::now();
            if now >= next_scan && self.earliest.is_some_and(|d| now >= d) {
                self.timers(now, &mut touched);
                self.earliest = self.next_deadline();
                next_scan = now + SCAN_EVERY;
            }
            self.run_timed(now, &mut touched);
            if !self.slow.is_empty() && now >= self.slow_next {
                self.slow_slice(&mut touched);
                self.slow_next = now + SLOW_PERIOD / SLOW_SLICES;
            }
            touched.sort_unstable();
            touched.dedup();
            for t in touched {
                self.service(t, now);
            }
        }
        // Dropping the connections closes them; members leave their channels.
        for (_, mut c) in self.conns.drain() {
            c.leave();
        }
        self.shared.clients.store(0, Ordering::Relaxed);
        Ok(())
    }

    /// The earliest handshake or idle deadline.
    fn next_deadline(&self) -> Option<Instant> {
        let idle = self.shared.config.idle_timeout;
        self.conns
            .values()
            .filter_map(|c| match &c.state {
                State::Raw { .. } => idle.map(|d| c.last_rx + d),
                _ => Some(c.handshake_end),
            })
            .min()
    }

    /// Closes timed-out clients.
    fn timers(&mut self, now: Instant, touched: &mut Vec<usize>) {
        let idle = self.shared.config.idle_timeout;
        for (t, c) in &mut self.conns {
            match &c.state {
                State::Raw { .. } if idle.is_some_and(|d| now >= c.last_rx + d) => {
                    tracing::debug!(peer = %c.peer, "idle client closed");
                    c.closed = true;
                }
                State::Raw { .. } => {}
                _ if now >= c.handshake_end => {
                    tracing::debug!(peer = %c.peer, "handshake timeout");
                    c.closed = true;
                    touched.push(*t);
                }
                _ => {}
            }
            if c.closed {
                touched.push(*t);
            }
        }
    }

    fn accept(&mut self, now: Instant) {
        // A burst of connections is taken in slices, between which the clients that have
        // traffic are served: a flood of connects must not stall the bus.
        for _ in 0..ACCEPT_SLICE {
            let (mut stream, peer) = match self.listener.accept() {
                Ok(x) => x,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    // E.g. out of file descriptors: leave the rest in the backlog for now.
                    self.accept_failures += 1;
                    if self
                        .accept_warned
                        .is_none_or(|t| now.saturating_duration_since(t) >= ACCEPT_WARN_EVERY)
                    {
                        tracing::warn!(failures = self.accept_failures,
                            "accept failed: {e}; retrying every 10 ms (logged at most once a minute)");
                        self.accept_warned = Some(now);
                    }
                    self.accept_retry = true;
                    return;
                }
            };
            if self.accept_failures > 0 {
                tracing::info!(
                    failures = self.accept_failures,
                    "accepting connections again"
                );
                self.accept_failures = 0;
                self.accept_warned = None;
            }
            self.shared.accepted.fetch_add(1, Ordering::Relaxed);
            if self.conns.len() >= self.shared.config.max_clients {
                let refused = self.shared.refused.fetch_add(1, Ordering::Relaxed);
                let _ = stream.write(b"< error too many clients >");
                // The 1st, 2nd, 4th, 8th … refusal: a flood must not flood the log too.
                if (refused + 1).is_power_of_two() {
                    tracing::warn!(%peer, max = self.shared.config.max_clients, refused = refused + 1,
                        "socketcand client refused: too many clients");
                }
                continue;
            }
            let _ = stream.set_nodelay(true);
            quickack(&stream);
            if let Some(n) = self.shared.config.send_buffer {
                let _ = socket2::SockRef::from(&stream).set_send_buffer_size(n);
            }
            let token = self.next_token;
            self.next_token = (self.next_token + 1) % (usize::MAX - 16);
            if let Err(e) =
                self.poll
                    .registry()
                    .register(&mut stream, Token(token), Interest::READABLE)
            {
                tracing::warn!(%peer, "cannot watch client socket: {e}");
                continue;
            }
            tracing::debug!(%peer, "client connected");
            let mut c = Conn {
                stream,
                peer,
                state: State::Opening,
                session: Session::new(),
                decoder: Decoder::new(),
                out: codec::HI.to_vec(),
                out_pos: 0,
                sends: Vec::new(),
                urgent_at: None,
                writable: false,
                sock_full: false,
                slow: false,
                written: 0,
                listed: false,
                peak_window: 0,
                rest: Vec::new(),
                handshake_end: now + self.shared.config.handshake_timeout,
                last_rx: now,
                closed: false,
                horizon: None,
            };
            c.flush();
            self.note_deadline(c.handshake_end);
            self.conns.insert(token, c);
            self.shared
                .clients
                .store(self.conns.len(), Ordering::Relaxed);
            // Serviced on the next turn (interest, closing).
            self.shared
                .ready
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(token);
            let _ = self.shared.waker.wake();
        }
        // The slice ended with connections maybe left: come back at once.
        self.accept_more = true;
    }

    fn read(&mut self, t: usize, now: Instant) {
        let Some(c) = self.conns.get_mut(&t) else {
            return;
        };
        let was_joined = matches!(c.state, State::Raw { .. });
        // Input left over from a full output first; while the output stays full, nothing more
        // is read (the kernel's buffers fill, then the client's sends block).
        let mut stalled = false;
        if !c.rest.is_empty() {
            let rest = std::mem::take(&mut c.rest);
            let used = consume(c, &rest, &self.shared, &mut self.cache, t, now);
            if used < rest.len() && !c.closed {
                c.rest = rest[used..].to_vec();
                stalled = true;
            }
        }
        let mut buf = [0u8; 4096];
        // At most 64 KiB per turn, so one fast sender cannot starve the others; the rest next
        // turn.
        let mut drained = stalled || c.closed;
        if !drained {
            for _ in 0..16 {
                match c.stream.read(&mut buf) {
                    Ok(0) => {
                        c.closed = true;
                        drained = true;
                        break;
                    }
                    Ok(n) => {
                        quickack(&c.stream);
                        c.last_rx = now;
                        let used = consume(c, &buf[..n], &self.shared, &mut self.cache, t, now);
                        if c.closed {
                            drained = true;
                            break;
                        }
                        if used < n {
                            c.rest = buf[used..n].to_vec();
                            drained = true;
                            break;
                        }
                    }
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                        drained = true;
                        break;
                    }
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(_) => {
                        c.closed = true;
                        drained = true;
                        break;
                    }
                }
            }
        }
        // What this turn read enters the bus together.
        c.submit(now, &self.shared, &mut self.cache);
        if !drained {
            self.again.push(t);
        }
        let mut due = None;
        if let State::Raw { .. } = &c.state {
            // A channel was opened: the idle deadline.
            if let (false, Some(d)) = (was_joined, self.shared.config.idle_timeout) {
                due = Some(now + d);
            }
        }
        let timed = c.session.next_deadline();
        if let Some(d) = due {
            self.note_deadline(d);
        }
        self.set_timed(t, timed);
    }

    /// Records when a connection's session (BCM jobs, statistics) next needs [`Session::poll`].
    fn set_timed(&mut self, t: usize, due: Option<Instant>) {
        match due {
            Some(d) => {
                self.timed.insert(t, d);
            }
            None => {
                self.timed.remove(&t);
            }
        }
    }

    /// Runs the due BCM send jobs and statistics.
    fn run_timed(&mut self, now: Instant, touched: &mut Vec<usize>) {
        let due: Vec<usize> = self
            .timed
            .iter()
            .filter(|(_, d)| **d <= now)
            .map(|(t, _)| *t)
            .collect();
        let mut frames = Vec::new();
        for t in due {
            let Some(c) = self.conns.get_mut(&t) else {
                self.timed.remove(&t);
                continue;
            };
            frames.clear();
            // A statistics line only while the output has room: a client that does not read
            // them loses them (the next one has the current counters); its send jobs go on.
            let mut stat = Vec::new();
            c.session.poll(now, &mut stat, &mut frames);
            if c.pending() < self.shared.config.out_limit {
                c.out.extend_from_slice(&stat);
            }
            let lost = match &c.state {
                State::Raw { bus, id, .. } => bus.transmit_all(*id, &frames),
                State::Opening => 0,
            };
            c.tx_overflow(lost, now, &self.shared, &mut self.cache);
            let next = c.session.next_deadline();
            self.set_timed(t, next);
            touched.push(t);
        }
    }

    /// Gives bus errors posted by [`HubHandle::post_error`] to the clients of their channel.
    fn post_errors(&mut self, touched: &mut Vec<usize>) {
        let errors =
            std::mem::take(&mut *self.shared.errors.lock().unwrap_or_else(|e| e.into_inner()));
        let now = Instant::now();
        for (channel, e, from) in errors {
            for (t, c) in &mut self.conns {
                if Some(*t) == from {
                    continue;
                }
                // The frames the bus delivered before this error go out before it: they wait
                // in the client's queue, the error would otherwise pass them in its output.
                if c.session.takes_errors(self.shared.config.error_frames) {
                    c.fill(now, &self.shared, &mut self.cache);
                }
                // A client whose output is full loses bus errors as it loses frames.
                if c.pending() >= self.shared.config.out_limit {
                    continue;
                }
                if matches!(&c.state, State::Raw { channel: ch, .. } if *ch == channel) {
                    let before = c.out.len();
                    c.session
                        .error_frame(&e, self.shared.config.error_frames, &mut c.out);
                    if c.out.len() != before {
                        touched.push(*t);
                    }
                }
            }
        }
    }

    /// The next share of the slow clients, to be written this turn.
    fn slow_slice(&mut self, touched: &mut Vec<usize>) {
        let n = self.slow.len().div_ceil(SLOW_SLICES as usize);
        let mut taken = 0;
        while taken < n && !self.slow.is_empty() {
            if self.slow_pos >= self.slow.len() {
                self.slow_pos = 0;
            }
            let t = self.slow[self.slow_pos];
            match self.conns.get_mut(&t) {
                Some(c) if c.slow => {
                    touched.push(t);
                    self.slow_pos += 1;
                }
                other => {
                    if let Some(c) = other {
                        c.listed = false;
                    }
                    self.slow.swap_remove(self.slow_pos);
                }
            }
            taken += 1;
        }
    }

    fn note_deadline(&mut self, d: Instant) {
        self.earliest = Some(self.earliest.map_or(d, |e| e.min(d)));
    }

    /// Output, interest and closing of one client.
    fn service(&mut self, t: usize, now: Instant) {
        let Some(c) = self.conns.get_mut(&t) else {
            return;
        };
        if !c.closed {
            c.fill(now, &self.shared, &mut self.cache);
            // What reading, the timers and the queue added is all there is before the flush.
            self.shared
                .out_peak
                .fetch_max(c.pending(), Ordering::Relaxed);
            // A socket that refused bytes is not tried again before it reports WRITABLE.
            if !c.sock_full {
                c.flush();
                if c.check_pace() && c.slow && !c.listed {
                    c.listed = true;
                    self.slow.push(t);
                }
            }
            if let State::Raw {
                wake, rx, dropped, ..
            } = &c.state
            {
                let blocked = c.sock_full && c.pending() >= self.shared.config.out_limit;
                if wake.is_blocked() != blocked {
                    wake.blocked.store(blocked, Ordering::Relaxed);
                    if blocked {
                        // What waits in its queue is behind more than its socket and output
                        // hold already: lost now (counted), not kept for a client that may
                        // never read.
                        let mut n = 0;
                        while rx.try_recv().is_ok() {
                            n += 1;
                        }
                        dropped.fetch_add(n, Ordering::Relaxed);
                        self.shared.dropped.fetch_add(n, Ordering::Relaxed);
                    }
                }
            }
        }
        if c.closed {
            let mut c = self.conns.remove(&t).expect("present");
            self.timed.remove(&t);
            c.leave();
            let _ = self.poll.registry().deregister(&mut c.stream);
            self.shared
                .clients
                .store(self.conns.len(), Ordering::Relaxed);
            return;
        }
        // Input waits for room for its replies: the room is there, handle it next turn.
        if !c.rest.is_empty() && c.pending() < 2 * self.shared.config.out_limit {
            self.again.push(t);
        }
        // Queue not drained (output full): come back when the socket takes more.
        let backlog = matches!(&c.state, State::Raw { rx, .. } if !rx.is_empty());
        if backlog && c.pending() == 0 {
            // The socket took all there was and has room: no WRITABLE edge will come.
            self.again.push(t);
        }
        let want = c.pending() > 0 || backlog;
        if want != c.writable {
            let interest = if want {
                Interest::READABLE | Interest::WRITABLE
            } else {
                Interest::READABLE
            };
            if self
                .poll
                .registry()
                .reregister(&mut c.stream, Token(t), interest)
                .is_ok()
            {
                c.writable = want;
            }
        }
    }
}

/// Decodes and handles the elements of `input` while the client's output has room for replies
/// ([`HubConfig::out_limit`]); returns how many bytes it took (all, unless the output filled up or the
/// connection is to be closed).
fn consume(
    c: &mut Conn,
    input: &[u8],
    shared: &Arc<Shared>,
    cache: &mut TextCache,
    token: usize,
    now: Instant,
) -> usize {
    let mut used = 0;
    while used < input.len() {
        if c.pending() >= 2 * shared.config.out_limit {
            break;
        }
        let (n, piece) = c.decoder.next(&input[used..]);
        used += n;
        let el = match piece {
            Some(Piece::Body(body)) => Element::parse(body),
            Some(Piece::TooLong) => Element::TooLong,
            None => continue,
        };
        if !handle_element(el, c, shared, cache, token, now) {
            c.closed = true;
            break;
        }
    }
    used
}

/// Returns false when the connection should be closed.
fn handle_element(
    el: Element,
    c: &mut Conn,
    shared: &Arc<Shared>,
    cache: &mut TextCache,
    token: usize,
    now: Instant,
) -> bool {
    // Frames queued before an echo or a mode switch go out (or, outside raw mode, are passed
    // over) before its answer; the client's own frames before it enter the bus first, so that
    // an echo is a barrier: their overflow (reported at once) comes before its answer.
    if matches!(el, Element::Echo | Element::Mode(_)) {
        c.submit(now, shared, cache);
        c.fill(now, shared, cache);
    }
    if let Element::Other(text) = &el {
        tracing::trace!(peer = %c.peer, "unknown command {text:?}");
    }
    for effect in c.session.handle(el, now, &mut c.out, valid_channel) {
        // The frames before anything else that touches the bus (or the channel) go first.
        if !matches!(effect, Effect::Send(_)) {
            c.submit(now, shared, cache);
        }
        match effect {
            Effect::Join(ch) => {
                let bus = shared.channel(&ch);
                let (tx, rx) = crossbeam_channel::unbounded();
                let wake = Arc::new(Wake {
                    cap: shared.config.queue_len,
                    token,
                    pending: AtomicBool::new(false),
                    blocked: AtomicBool::new(false),
                    quiet: AtomicBool::new(false),
                    ctl_state: AtomicU8::new(0),
                    tx_overflowed: AtomicBool::new(false),
                    ready: shared.ready.clone(),
                    waker: shared.waker.clone(),
                });
                let (id, dropped) = bus.join(Sink::Remote(tx, wake.clone()));
                tracing::debug!(peer = %c.peer, channel = %ch, "client opened a channel");
                c.state = State::Raw {
                    channel: ch,
                    bus,
                    id,
                    rx,
                    wake,
                    dropped,
                };
            }
            Effect::Send(frame) => {
                if let State::Raw { .. } = &c.state {
                    shared.frames_in.fetch_add(1, Ordering::Relaxed);
                    c.sends.push(frame);
                }
            }
            Effect::TxOrder(order) => {
                if let State::Raw { bus, id, .. } = &c.state {
                    bus.set_tx_order(*id, order);
                }
            }
            Effect::Clock(on) => clock_option(c, on),
            Effect::At(t) => at(c, t),
            Effect::RawStarted => {
                // The `< ok >` (the last thing in the output) is followed by an urgent byte:
                // the client's first read ends with the `< ok >`, however many frames follow.
                c.urgent_at = Some(c.out.len());
                tracing::debug!(peer = %c.peer, "client in raw mode");
            }
            Effect::ErrorFlag(e) => {
                if let State::Raw {
                    channel, bus, id, ..
                } = &c.state
                {
                    // On a paced channel an error frame on the bus timeline (which reports it
                    // to the clients that take errors, the client too, as a controller
                    // reports the error frames on its bus); an instant channel has no bus
                    // timeline: the report goes to the others as it came.
                    if bus.error_flag(*id).is_none() {
                        shared.post_error_from(channel, e, Some(token));
                    }
                }
            }
            Effect::Close => {
                tracing::debug!(peer = %c.peer, "refused channel name");
                c.flush();
                return false;
            }
        }
    }
    true
}

/// `< clock on >` / `< clock off >`: joins (leaves) the channel bus's clock as a timed
/// participant. It holds nothing until its first `< at … >`: a client that asked and never
/// says where it is must not stop the bus for the others even for the stall bound.
fn clock_option(c: &mut Conn, on: bool) {
    let State::Raw { bus, id, .. } = &c.state else {
        return;
    };
    if !on {
        c.horizon = None;
        c.out.extend_from_slice(codec::OK);
        return;
    }
    if c.horizon.is_none() {
        match bus.join_clock_as(*id, &format!("socketcand client {}", c.peer)) {
            Some(h) => {
                h.set(u64::MAX);
                c.horizon = Some(h);
            }
            None => {
                codec::write_error_text(&mut c.out, "this channel has no clock (instant bus)");
                return;
            }
        }
    }
    tracing::debug!(peer = %c.peer, "timed client");
    c.out.extend_from_slice(codec::OK);
}

/// `< at SEC.USEC >`: a timed client's horizon. A time further before the time its bus
/// reached than the clock's stall bound is refused (nothing changes): the bus cannot go back,
/// and such a client would not hold it anyway. A time in the future holds nothing until the
/// bus gets there; frames are never stamped after the wall clock.
fn at(c: &mut Conn, t: std::time::SystemTime) {
    let (State::Raw { bus, .. }, Some(h)) = (&c.state, &c.horizon) else {
        codec::write_error_text(&mut c.out, "at needs clock on");
        return;
    };
    let (Some(clock), Some(reached)) = (bus.sim_clock(), bus.reached()) else {
        return;
    };
    match clock.nanos_of(t) {
        Some(ns) if ns.saturating_add(clock.stall_bound()) >= reached => h.set(ns),
        _ => codec::write_error_text(
            &mut c.out,
            "at is before the bus's time by more than the stall bound",
        ),
    }
}

fn valid_channel(ch: &str) -> bool {
    !ch.is_empty() && ch.len() <= 64 && ch.bytes().all(|b| b.is_ascii_graphic())
}
