//! A socketcand server acting as a hub: each channel name is an isolated virtual bus shared by
//! all clients that opened it (TCP clients and in-process [`MemPort`]s).
//!
//! Threads: one accept loop, and per TCP client one reader thread (parse, forward) and one
//! writer thread fed by a bounded queue. Forwarding only ever `try_send`s into queues, so a
//! client that reads slowly or not at all loses frames (counted) and never stalls the others.
//!
//! Limits: at most [`HubConfig::max_clients`] connections at once (so at most twice that many
//! client threads, whatever connects); one more is told `< error too many clients >` and closed
//! by the accept loop itself. A client must finish the handshake (`open`, `rawmode`) within
//! [`HubConfig::handshake_timeout`], and a raw-mode client that sends nothing for
//! [`HubConfig::idle_timeout`] (off by default: listen-only clients are normal) is closed.

use std::collections::HashMap;
use std::io::{self, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::os::linux::net::TcpStreamExt;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use crossbeam_channel::Receiver;

use super::codec::{self, Decoder, Element};
use crate::mem::{BusCore, MemBus, MemPort, Sink};
use crate::transport::RxFrame;

/// The default listen address: loopback only.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:29536";

/// What a TCP client's writer thread sends.
pub(crate) enum Out {
    Frame(RxFrame),
    Echo,
}

/// Hub tuning.
#[derive(Clone, Debug)]
pub struct HubConfig {
    /// Frames queued per TCP client before further frames to it are dropped.
    pub queue_len: usize,
    /// How long frames are held back after the rawmode `< ok >` (python-can reads that reply
    /// with one `recv` and fails if a frame shares its TCP segment).
    pub hold_back: Duration,
    /// `SO_SNDBUF` for client sockets (`None`: kernel autotuning). A fixed, modest buffer makes a
    /// stuck client start losing frames after a bounded backlog instead of megabytes.
    pub send_buffer: Option<usize>,
    /// Most TCP clients connected at once; further connections are refused.
    pub max_clients: usize,
    /// Time from accept to raw mode; a client slower than that is closed.
    pub handshake_timeout: Duration,
    /// Longest silence of a raw-mode client before it is closed (`None`: no limit).
    pub idle_timeout: Option<Duration>,
}

impl Default for HubConfig {
    fn default() -> Self {
        HubConfig {
            queue_len: 4096,
            hold_back: Duration::from_millis(20),
            send_buffer: Some(256 * 1024),
            max_clients: 1024,
            handshake_timeout: Duration::from_secs(10),
            idle_timeout: None,
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
}

struct Shared {
    config: HubConfig,
    local_addr: SocketAddr,
    channels: Mutex<HashMap<String, Weak<BusCore>>>,
    /// Clones of every client socket, to cut them at shutdown.
    clients: Mutex<HashMap<u64, TcpStream>>,
    next_client: AtomicU64,
    shutdown: AtomicBool,
    accepted: AtomicU64,
    frames_in: AtomicU64,
    /// Drops of all channels, past and present.
    dropped: Arc<AtomicU64>,
    unencodable: AtomicU64,
    /// Connections being served (accepted, thread not yet ended).
    active: std::sync::atomic::AtomicUsize,
    refused: AtomicU64,
}

impl Shared {
    fn channel(&self, name: &str) -> Arc<BusCore> {
        let mut map = self.channels.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(core) = map.get(name).and_then(Weak::upgrade) {
            return core;
        }
        // Forget channels nobody uses any more, so many channel names do not accumulate.
        map.retain(|_, w| w.strong_count() > 0);
        let core = Arc::new(BusCore::with_drop_counter(self.dropped.clone()));
        map.insert(name.to_string(), Arc::downgrade(&core));
        core
    }

    fn stats(&self) -> HubStats {
        let map = self.channels.lock().unwrap_or_else(|e| e.into_inner());
        let live: Vec<Arc<BusCore>> = map.values().filter_map(Weak::upgrade).collect();
        drop(map);
        HubStats {
            clients: self.clients.lock().unwrap_or_else(|e| e.into_inner()).len(),
            accepted: self.accepted.load(Ordering::Relaxed),
            channels: live.iter().filter(|c| c.member_count() > 0).count(),
            frames_in: self.frames_in.load(Ordering::Relaxed),
            dropped: self.dropped.load(Ordering::Relaxed),
            unencodable: self.unencodable.load(Ordering::Relaxed),
            refused: self.refused.load(Ordering::Relaxed),
        }
    }

    fn attach(&self, channel: &str) -> MemPort {
        MemBus::from_core(self.channel(channel), self.config.queue_len).attach()
    }

    fn shutdown(&self, listener: &TcpListener) {
        if self.shutdown.swap(true, Ordering::SeqCst) {
            return;
        }
        // shutdown(2) on a listening socket wakes a blocked accept on Linux; the self-connect
        // is a fallback in case it does not.
        let _ = socket2::SockRef::from(listener).shutdown(Shutdown::Both);
        let mut wake = self.local_addr;
        if wake.ip().is_unspecified() {
            wake.set_ip(if wake.is_ipv4() {
                std::net::Ipv4Addr::LOCALHOST.into()
            } else {
                std::net::Ipv6Addr::LOCALHOST.into()
            });
        }
        let _ = TcpStream::connect_timeout(&wake, Duration::from_millis(100));
        for s in self
            .clients
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .values()
        {
            let _ = s.shutdown(Shutdown::Both);
        }
    }
}

/// A bound, not yet running hub.
pub struct Hub {
    listener: Arc<TcpListener>,
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
        config.max_clients = config.max_clients.max(1);
        let listener = TcpListener::bind(addr)?;
        let local_addr = listener.local_addr()?;
        Ok(Hub {
            listener: Arc::new(listener),
            shared: Arc::new(Shared {
                config,
                local_addr,
                channels: Mutex::new(HashMap::new()),
                clients: Mutex::new(HashMap::new()),
                next_client: AtomicU64::new(1),
                shutdown: AtomicBool::new(false),
                accepted: AtomicU64::new(0),
                frames_in: AtomicU64::new(0),
                dropped: Arc::new(AtomicU64::new(0)),
                unencodable: AtomicU64::new(0),
                active: std::sync::atomic::AtomicUsize::new(0),
                refused: AtomicU64::new(0),
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
            listener: self.listener.clone(),
            shared: self.shared.clone(),
        }
    }

    /// Serves clients on the calling thread until shut down.
    pub fn run(self) -> io::Result<()> {
        accept_loop(&self.listener, &self.shared)
    }

    /// Serves clients on a background thread.
    pub fn spawn(self) -> io::Result<HubHandle> {
        let shutdown = self.shutdown_handle();
        let (listener, shared) = (self.listener, self.shared);
        let join = thread::Builder::new()
            .name("socketcand-hub".into())
            .spawn(move || accept_loop(&listener, &shared))?;
        Ok(HubHandle {
            shutdown,
            join: Some(join),
        })
    }
}

/// Stops a hub: closes the listener and every client connection. Cheap to clone.
#[derive(Clone)]
pub struct ShutdownHandle {
    listener: Arc<TcpListener>,
    shared: Arc<Shared>,
}

impl ShutdownHandle {
    /// Stops the hub; idempotent. In-process ports stay usable among themselves.
    pub fn shutdown(&self) {
        self.shared.shutdown(&self.listener);
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

    /// A handle to stop the hub from elsewhere.
    pub fn shutdown_handle(&self) -> ShutdownHandle {
        self.shutdown.clone()
    }

    /// Whether the accept loop is still running.
    pub fn is_running(&self) -> bool {
        self.join.as_ref().is_some_and(|j| !j.is_finished())
    }

    /// Stops the hub and waits for the accept loop to end.
    pub fn shutdown(mut self) -> io::Result<()> {
        self.stop()
    }

    fn stop(&mut self) -> io::Result<()> {
        self.shutdown.shutdown();
        match self.join.take() {
            Some(j) => j
                .join()
                .unwrap_or_else(|_| Err(io::Error::other("hub accept thread panicked"))),
            None => Ok(()),
        }
    }
}

impl Drop for HubHandle {
    fn drop(&mut self) {
        let _ = self.stop();
    }
}

fn accept_loop(listener: &TcpListener, shared: &Arc<Shared>) -> io::Result<()> {
    tracing::info!(addr = %shared.local_addr, "socketcand hub listening");
    loop {
        let accepted = listener.accept();
        if shared.shutdown.load(Ordering::SeqCst) {
            return Ok(());
        }
        match accepted {
            Ok((mut stream, peer)) => {
                shared.accepted.fetch_add(1, Ordering::Relaxed);
                if shared.active.fetch_add(1, Ordering::SeqCst) >= shared.config.max_clients {
                    shared.active.fetch_sub(1, Ordering::SeqCst);
                    let refused = shared.refused.fetch_add(1, Ordering::Relaxed);
                    // Without a thread: the refusal must not cost what the limit protects.
                    let _ = stream.set_nonblocking(true);
                    let _ = stream.write_all(b"< error too many clients >");
                    // The 1st, 2nd, 4th, 8th … refusal: a flood must not flood the log too.
                    if (refused + 1).is_power_of_two() {
                        tracing::warn!(%peer, max = shared.config.max_clients, refused = refused + 1,
                            "socketcand client refused: too many clients");
                    }
                    continue;
                }
                let active = Active(shared.clone());
                let shared = shared.clone();
                let spawned = thread::Builder::new()
                    .name(format!("socketcand {peer}"))
                    .spawn(move || {
                        let _active = active;
                        serve_client(stream, peer, shared)
                    });
                if let Err(e) = spawned {
                    tracing::warn!(%peer, "cannot start client thread: {e}");
                }
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => {
                // E.g. out of file descriptors: back off instead of spinning or dying.
                tracing::warn!("accept failed: {e}");
                thread::sleep(Duration::from_millis(10));
            }
        }
    }
}

fn tune(stream: &TcpStream, config: &HubConfig) {
    let _ = stream.set_nodelay(true);
    let _ = stream.set_quickack(true);
    if let Some(n) = config.send_buffer {
        let _ = socket2::SockRef::from(stream).set_send_buffer_size(n);
    }
}

/// Counts a connection as served until its thread ends (or was never started).
struct Active(Arc<Shared>);

impl Drop for Active {
    fn drop(&mut self) {
        self.0.active.fetch_sub(1, Ordering::SeqCst);
    }
}

/// Removes the client from the hub's registry (and its bus) when its reader ends, however it
/// ends.
struct ClientGuard {
    shared: Arc<Shared>,
    client: u64,
    member: Option<(Arc<BusCore>, u64, Arc<AtomicU64>)>,
}

impl Drop for ClientGuard {
    fn drop(&mut self) {
        if let Some((bus, id, _)) = self.member.take() {
            bus.leave(id);
        }
        let removed = self
            .shared
            .clients
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&self.client);
        if let Some(s) = removed {
            let _ = s.shutdown(Shutdown::Both);
        }
    }
}

enum State {
    Opening,
    Opened(String),
    Raw {
        bus: Arc<BusCore>,
        id: u64,
        queue: crossbeam_channel::Sender<Out>,
    },
}

fn serve_client(mut stream: TcpStream, peer: SocketAddr, shared: Arc<Shared>) {
    tune(&stream, &shared.config);
    let client = shared.next_client.fetch_add(1, Ordering::Relaxed);
    match stream.try_clone() {
        Ok(s) => {
            shared
                .clients
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .insert(client, s);
        }
        Err(e) => {
            tracing::warn!(%peer, "cannot clone client socket: {e}");
            return;
        }
    }
    let mut guard = ClientGuard {
        shared: shared.clone(),
        client,
        member: None,
    };
    // A shutdown between accept and registration would miss this socket.
    if shared.shutdown.load(Ordering::SeqCst) {
        return;
    }
    tracing::debug!(%peer, "client connected");
    if stream.write_all(codec::HI).is_err() {
        return;
    }
    let mut decoder = Decoder::new();
    let mut state = State::Opening;
    let mut buf = [0u8; 4096];
    let mut elements = Vec::new();
    // The whole handshake has one deadline (not one per read: a byte every few seconds must
    // not keep a connection half-open for ever).
    let handshake_end = Instant::now() + shared.config.handshake_timeout;
    loop {
        if !matches!(state, State::Raw { .. }) {
            let left = handshake_end.saturating_duration_since(Instant::now());
            if left.is_zero() || stream.set_read_timeout(Some(left)).is_err() {
                tracing::debug!(%peer, "handshake timeout");
                break;
            }
        }
        let n = match stream.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                tracing::debug!(%peer, "client timed out");
                break;
            }
            Err(_) => break,
        };
        // Linux clears QUICKACK after use; re-arm so our ACKs never wait ~40 ms.
        let _ = stream.set_quickack(true);
        elements.clear();
        decoder.feed(&buf[..n], |body| elements.push(Element::parse(body)));
        for el in elements.drain(..) {
            if !handle_element(el, &mut stream, &mut state, &shared, &mut guard, peer) {
                return;
            }
        }
    }
    tracing::debug!(%peer, dropped = guard.member.as_ref().map(|m| m.2.load(Ordering::Relaxed)), "client disconnected");
}

/// Returns false when the connection should be closed.
fn handle_element(
    el: Element,
    stream: &mut TcpStream,
    state: &mut State,
    shared: &Arc<Shared>,
    guard: &mut ClientGuard,
    peer: SocketAddr,
) -> bool {
    match (el, &*state) {
        (Element::Send(frame), State::Raw { bus, id, .. }) => {
            shared.frames_in.fetch_add(1, Ordering::Relaxed);
            bus.broadcast(*id, RxFrame::now(frame));
            true
        }
        (Element::Echo, State::Raw { queue, .. }) => {
            // Through the queue so the reply is never interleaved with a frame being written.
            let _ = queue.try_send(Out::Echo);
            true
        }
        (Element::Echo, _) => stream.write_all(codec::ECHO).is_ok(),
        (Element::Open(ch), State::Opening) => {
            if !valid_channel(&ch) {
                tracing::debug!(%peer, "refusing channel name {ch:?}");
                return false;
            }
            *state = State::Opened(ch);
            stream.write_all(codec::OK).is_ok()
        }
        (Element::RawMode, State::Opened(ch)) => {
            let bus = shared.channel(ch);
            let (tx, rx) = crossbeam_channel::bounded(shared.config.queue_len);
            let Ok(writer_stream) = stream.try_clone() else {
                return false;
            };
            // The `< ok >` goes out before the member joins, so no frame can precede it.
            if stream.write_all(codec::OK).is_err() {
                return false;
            }
            let hold_until = Instant::now() + shared.config.hold_back;
            let (id, dropped) = bus.join(Sink::Remote(tx.clone()));
            guard.member = Some((bus.clone(), id, dropped));
            let sh = shared.clone();
            let spawned = thread::Builder::new()
                .name(format!("socketcand {peer} tx"))
                .spawn(move || writer(writer_stream, rx, hold_until, &sh));
            if spawned.is_err() {
                return false;
            }
            tracing::debug!(%peer, channel = %ch, "client in raw mode");
            *state = State::Raw { bus, id, queue: tx };
            // From now on only the idle limit applies (none by default).
            stream.set_read_timeout(shared.config.idle_timeout).is_ok()
        }
        (el, _) => {
            // Unknown or out-of-order commands are ignored: python-can raises on `< error >`
            // in raw mode, and a misbehaving client must not take the hub down.
            tracing::trace!(%peer, "ignored element {el:?}");
            true
        }
    }
}

fn valid_channel(ch: &str) -> bool {
    !ch.is_empty() && ch.len() <= 64 && ch.bytes().all(|b| b.is_ascii_graphic())
}

fn writer(mut stream: TcpStream, rx: Receiver<Out>, hold_until: Instant, shared: &Shared) {
    let mut buf = Vec::with_capacity(4096);
    let mut first = true;
    while let Ok(item) = rx.recv() {
        if first {
            first = false;
            let now = Instant::now();
            if now < hold_until {
                thread::sleep(hold_until - now);
            }
        }
        buf.clear();
        push(&mut buf, item, shared);
        // Batch whatever else is queued into one write: fewer syscalls under load, and no
        // added latency because we never wait for more.
        while buf.len() < 32 * 1024 {
            match rx.try_recv() {
                Ok(item) => push(&mut buf, item, shared),
                Err(_) => break,
            }
        }
        if !buf.is_empty() && stream.write_all(&buf).is_err() {
            break;
        }
    }
    // Make the reader notice too, if it is the writer that failed.
    let _ = stream.shutdown(Shutdown::Both);
}

fn push(buf: &mut Vec<u8>, item: Out, shared: &Shared) {
    match item {
        Out::Frame(rx) => {
            if !codec::write_frame(buf, &rx.frame, rx.timestamp) {
                shared.unencodable.fetch_add(1, Ordering::Relaxed);
            }
        }
        Out::Echo => buf.extend_from_slice(codec::ECHO),
    }
}
