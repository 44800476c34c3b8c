//! socketcand client transport: connects, performs the raw-mode handshake, asks for canpos's
//! protocol extensions (`< rtr on >`, `< errors on >`, and for a device `< txorder priority >`;
//! docs/SOCKETCAND.md), then a reader thread turns `< frame ... >` elements into [`RxFrame`]s
//! and `< error ... >` bus errors into the [`BusState`] and the transmit-queue overflows the
//! runtime reacts to.
//!
//! Against a server without the extensions (the reference socketcand answers them with
//! `< error unknown command >`) the client speaks the plain protocol: remote frames with DLC 0
//! go out as zero-length data frames, as python-can sends them.

use std::io::{self, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpStream, ToSocketAddrs};
use std::os::linux::net::TcpStreamExt;
use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use canpos_stack::Frame;
use crossbeam_channel::{Receiver, Sender};

/// How long [`open`](crate::transport::open) waits for a socketcand server to accept and complete
/// the handshake.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);

use super::codec::{self, Decoder, Element};
use crate::can::{BusState, RxFrame, Transport};
use crate::clock::{Horizon, Nanos, SimClock, Slot};

/// How long the client waits for the answer to an extension request before taking it as
/// unsupported (a server that ignores unknown commands).
pub const EXTENSION_TIMEOUT: Duration = Duration::from_millis(500);

/// Receive queue length of a client, in frames. When full, the reader stops reading and TCP
/// flow control pushes back to the server (which drops frames for us instead of stalling).
pub const CLIENT_QUEUE_LEN: usize = 4096;

/// Depth of the queue of received error frames ([`Transport::error_frames`]).
const ERROR_QUEUE_LEN: usize = 1024;

/// A connection to a socketcand server in raw mode. Dropping it closes the connection.
pub struct Client {
    /// For shutting the connection down; writes go through `writer`.
    stream: TcpStream,
    /// Frames and horizon messages go out through it, in order (the runtime's thread and the
    /// horizon forwarder write).
    writer: Arc<Mutex<Writer>>,
    /// The server made this client a timed participant of its bus's clock (`< clock on >`
    /// answered `< ok >`).
    clock: bool,
    rx: Receiver<RxFrame>,
    error: Arc<Mutex<Option<io::Error>>>,
    peer: SocketAddr,
    channel: String,
    /// The server carries remote frames (`< rtr on >` answered `< ok >`).
    rtr: bool,
    /// The server takes and gives bus errors (`< errors on >` answered `< ok >`).
    errors: bool,
    /// [`BusState`] as u8, from the server's error frames.
    state: Arc<AtomicU8>,
    /// The server's error frames ([`Transport::error_frames`]).
    error_rx: Receiver<codec::ErrorFrame>,
    /// Transmit-queue overflows the server reported ([`Transport::tx_overflows`]).
    tx_overflows: Arc<AtomicU64>,
}

fn state_to_u8(s: BusState) -> u8 {
    match s {
        BusState::ErrorActive => 0,
        BusState::ErrorPassive => 1,
        BusState::BusOff => 2,
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// The writing half of a connection.
struct Writer {
    stream: TcpStream,
    buf: Vec<u8>,
    /// A runtime's horizon forwarded as `< at … >` (a timed client).
    timed: Option<TimedLink>,
    /// Frames and `< at … >` messages written (the rate of the horizon messages).
    frames: u64,
    ats: u64,
}

/// A runtime's horizon on a local wall clock (the client's [`Transport::join_clock`]): its
/// value goes to the hub as `< at … >`, in wall-clock time, before the frames stamped with it.
struct TimedLink {
    clock: SimClock,
    slot: std::sync::Weak<Slot>,
    /// What the hub was told last.
    told: Option<Nanos>,
}

impl Writer {
    /// Appends `< at … >` when the horizon differs from what the hub was told (coalesced: one
    /// message for any number of moves since); `< clock off >` once the runtime is gone.
    fn horizon(&mut self) {
        let Some(link) = &mut self.timed else { return };
        match link.slot.upgrade() {
            Some(slot) => {
                let h = slot.at();
                if link.told != Some(h) {
                    link.told = Some(h);
                    codec::write_at(&mut self.buf, link.clock.system_time_of(h));
                    self.ats += 1;
                }
            }
            None => {
                self.timed = None;
                self.buf.extend_from_slice(b"< clock off >");
            }
        }
    }

    fn flush(&mut self) -> io::Result<()> {
        let r = self.stream.write_all(&self.buf);
        self.buf.clear();
        r
    }
}

/// The horizon forwarder of a timed client: wakes when the runtime's horizon moves on (its
/// local clock tells it) and tells the hub, so that a runtime waiting for its next deadline
/// does not hold the bus at its last frame. Ends with the client or the runtime's horizon.
fn forward_horizon(writer: std::sync::Weak<Mutex<Writer>>, moved: Receiver<()>) {
    loop {
        // A bound on the wait: the client may be gone.
        let _ = moved.recv_timeout(Duration::from_millis(500));
        let Some(w) = writer.upgrade() else { return };
        let mut w = lock(&w);
        if w.timed.is_none() {
            return;
        }
        w.horizon();
        if w.buf.is_empty() {
            continue;
        }
        if w.flush().is_err() {
            return;
        }
    }
}

fn proto_err(msg: impl Into<String>) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, msg.into())
}

impl Client {
    /// Connects to `addr` and opens `channel`, waiting at most [`super::client::CONNECT_TIMEOUT`].
    pub fn connect(addr: impl ToSocketAddrs, channel: &str) -> io::Result<Client> {
        let mut last = None;
        for a in addr.to_socket_addrs()? {
            match Self::connect_timeout(a, channel, super::client::CONNECT_TIMEOUT) {
                Ok(c) => return Ok(c),
                Err(e) => last = Some(e),
            }
        }
        Err(last.unwrap_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no address")))
    }

    /// Connects and completes the handshake within `timeout`. Its frames go on the bus in the
    /// order sent, as a host's (a master, a replayed log).
    pub fn connect_timeout(
        addr: SocketAddr,
        channel: &str,
        timeout: Duration,
    ) -> io::Result<Client> {
        Self::connect_as(addr, channel, timeout, false)
    }

    /// [`connect_timeout`](Self::connect_timeout) for a device (a sensor's runtime): it also
    /// asks a canpos hub for `< txorder priority >`, so that its transmit queue on the bus goes
    /// out most important frame first, as a device's CAN controller sends (its EMCY overtakes
    /// its queued PDOs).
    pub fn connect_device_timeout(
        addr: SocketAddr,
        channel: &str,
        timeout: Duration,
    ) -> io::Result<Client> {
        Self::connect_as(addr, channel, timeout, true)
    }

    fn connect_as(
        addr: SocketAddr,
        channel: &str,
        timeout: Duration,
        device: bool,
    ) -> io::Result<Client> {
        if channel.is_empty()
            || !channel
                .bytes()
                .all(|b| b.is_ascii_graphic() && b != b'<' && b != b'>')
        {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("bad socketcand channel name {channel:?}"),
            ));
        }
        let deadline = Instant::now() + timeout;
        let mut stream = TcpStream::connect_timeout(&addr, timeout)?;
        stream.set_nodelay(true)?;
        let _ = stream.set_quickack(true);
        let mut decoder = Decoder::new();
        let mut pending = Vec::new();

        expect(
            &mut stream,
            &mut decoder,
            &mut pending,
            deadline,
            "< hi >",
            |e| matches!(e, Element::Hi),
        )?;
        let mut open = Vec::new();
        codec::write_open(&mut open, channel);
        stream.write_all(&open)?;
        expect(
            &mut stream,
            &mut decoder,
            &mut pending,
            deadline,
            "< ok > to open",
            |e| matches!(e, Element::Ok),
        )?;
        stream.write_all(codec::RAWMODE)?;
        expect(
            &mut stream,
            &mut decoder,
            &mut pending,
            deadline,
            "< ok > to rawmode",
            |e| matches!(e, Element::Ok),
        )?;
        stream.write_all(b"< rtr on >< errors on >")?;
        if device {
            stream.write_all(b"< txorder priority >< clock on >")?;
        }
        let ext_deadline = deadline.min(Instant::now() + EXTENSION_TIMEOUT);
        let rtr = extension(&mut stream, &mut decoder, &mut pending, ext_deadline, "rtr")?;
        let errors = extension(
            &mut stream,
            &mut decoder,
            &mut pending,
            ext_deadline,
            "errors",
        )?;
        let by_priority = device
            && extension(
                &mut stream,
                &mut decoder,
                &mut pending,
                ext_deadline,
                "txorder",
            )?;
        let clock = device
            && extension(
                &mut stream,
                &mut decoder,
                &mut pending,
                ext_deadline,
                "clock",
            )?;
        tracing::debug!(%addr, rtr, errors, by_priority, clock, "socketcand extensions");
        stream.set_read_timeout(None)?;

        let (tx, rx) = crossbeam_channel::bounded(CLIENT_QUEUE_LEN);
        let (error_tx, error_rx) = crossbeam_channel::bounded(ERROR_QUEUE_LEN);
        let error = Arc::new(Mutex::new(None));
        let state = Arc::new(AtomicU8::new(0));
        let tx_overflows = Arc::new(AtomicU64::new(0));
        let reader_stream = stream.try_clone()?;
        let err = error.clone();
        let st = state.clone();
        let overflows = tx_overflows.clone();
        thread::Builder::new()
            .name(format!("socketcand client {addr}"))
            .spawn(move || {
                let to = Reported {
                    state: &st,
                    tx_overflows: &overflows,
                };
                let e = reader(reader_stream, decoder, pending, &tx, &error_tx, to);
                *err.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
            })?;
        let writer = Arc::new(Mutex::new(Writer {
            stream: stream.try_clone()?,
            buf: Vec::with_capacity(64),
            timed: None,
            frames: 0,
            ats: 0,
        }));
        Ok(Client {
            stream,
            writer,
            clock,
            rx,
            error,
            peer: addr,
            channel: channel.to_string(),
            rtr,
            errors,
            state,
            error_rx,
            tx_overflows,
        })
    }

    /// Whether the server carries remote frames as such (canpos's `< rtr on >` extension).
    pub fn carries_remote_frames(&self) -> bool {
        self.rtr
    }

    /// The server's address.
    pub fn peer_addr(&self) -> SocketAddr {
        self.peer
    }

    /// Whether the server made this client a timed participant of its bus's clock (a device
    /// on a canpos hub: `< clock on >`, docs/CLOCK.md).
    pub fn is_timed(&self) -> bool {
        self.clock
    }

    /// Frames sent and `< at … >` horizon messages sent so far.
    pub fn sent_counts(&self) -> (u64, u64) {
        let w = lock(&self.writer);
        (w.frames, w.ats)
    }

    /// Forwards the horizon in `slot` (on `clock`, a local wall clock) to the hub as
    /// `< at … >`: before each frame when it changed, and when it moves on while the runtime
    /// waits (a forwarder thread). `false` when the server has no clock for this client.
    pub(crate) fn attach_clock(&self, clock: &SimClock, slot: std::sync::Weak<Slot>) -> bool {
        if !self.clock {
            return false;
        }
        let moved = clock.subscribe();
        // Horizons tell the clock's listeners only while one waits: this one always does.
        clock.waiting(true);
        lock(&self.writer).timed = Some(TimedLink {
            clock: clock.clone(),
            slot,
            told: None,
        });
        let writer = Arc::downgrade(&self.writer);
        match thread::Builder::new()
            .name(format!("socketcand horizon {}", self.peer))
            .spawn(move || forward_horizon(writer, moved))
        {
            Ok(_) => true,
            Err(e) => {
                tracing::warn!("cannot start the horizon forwarder: {e}; the client stays untimed");
                lock(&self.writer).timed = None;
                false
            }
        }
    }
}

/// A timed client's horizon: a participant of a local wall clock (the runtime's clock; its
/// times map to the hub's through wall-clock time, both on one host), forwarded by `client`.
pub(crate) fn timed_horizon(client: &Client) -> Option<Horizon> {
    if !client.clock {
        return None;
    }
    let clock = SimClock::wall();
    let h = clock.participant("socketcand runtime");
    client.attach_clock(&clock, h.slot()).then_some(h)
}

/// Reads until an element satisfying `want` arrives; elements after it stay in `pending`.
fn expect(
    stream: &mut TcpStream,
    decoder: &mut Decoder,
    pending: &mut Vec<Element>,
    deadline: Instant,
    what: &str,
    want: impl Fn(&Element) -> bool,
) -> io::Result<()> {
    let mut buf = [0u8; 512];
    loop {
        if let Some(i) = pending.iter().position(&want) {
            if let Some(Element::Error(e)) =
                pending[..i].iter().find(|e| matches!(e, Element::Error(_)))
            {
                return Err(proto_err(format!(
                    "server answered `< {e} >` while expecting {what}"
                )));
            }
            pending.drain(..=i);
            return Ok(());
        }
        if let Some(Element::Error(e)) = pending.iter().find(|e| matches!(e, Element::Error(_))) {
            return Err(proto_err(format!(
                "server answered `< {e} >` while expecting {what}"
            )));
        }
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(io::Error::new(
                io::ErrorKind::TimedOut,
                format!("no {what} from the socketcand server"),
            ));
        }
        stream.set_read_timeout(Some(left))?;
        let n = match stream.read(&mut buf) {
            Ok(0) => {
                return Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    format!("server closed the connection while we waited for {what}"),
                ))
            }
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                continue
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        let _ = stream.set_quickack(true);
        decoder.feed(&buf[..n], |b| pending.push(Element::parse(b)));
    }
}

/// Waits for the answer to an extension request: `< ok >` (true), `< error … >` (false: the
/// server does not have it), or nothing by `deadline` (false). Frames that arrive meanwhile stay
/// in `pending`, in order.
fn extension(
    stream: &mut TcpStream,
    decoder: &mut Decoder,
    pending: &mut Vec<Element>,
    deadline: Instant,
    what: &str,
) -> io::Result<bool> {
    let mut buf = [0u8; 512];
    loop {
        if let Some(i) = pending
            .iter()
            .position(|e| matches!(e, Element::Ok | Element::Error(_)))
        {
            return Ok(matches!(pending.remove(i), Element::Ok));
        }
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            tracing::debug!("no answer to `< {what} on >`: taken as unsupported");
            return Ok(false);
        }
        stream.set_read_timeout(Some(left))?;
        match stream.read(&mut buf) {
            Ok(0) => {
                return Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    "server closed the connection after the handshake",
                ))
            }
            Ok(n) => decoder.feed(&buf[..n], |b| pending.push(Element::parse(b))),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock
                        | io::ErrorKind::TimedOut
                        | io::ErrorKind::Interrupted
                ) => {}
            Err(e) => return Err(e),
        }
    }
}

/// What the reader keeps up to date from the server's error frames.
struct Reported<'a> {
    /// [`BusState`] as u8.
    state: &'a AtomicU8,
    /// Transmit-queue overflows.
    tx_overflows: &'a AtomicU64,
}

/// Runs until the connection ends or the client is dropped; returns why it ended.
fn reader(
    mut stream: TcpStream,
    mut decoder: Decoder,
    pending: Vec<Element>,
    tx: &Sender<RxFrame>,
    error_tx: &Sender<codec::ErrorFrame>,
    to: Reported<'_>,
) -> io::Error {
    let mut elements = pending;
    let mut buf = [0u8; 4096];
    loop {
        for el in elements.drain(..) {
            match el {
                Element::Frame(f) => {
                    if tx.send(f).is_err() {
                        return io::Error::new(io::ErrorKind::ConnectionAborted, "client closed");
                    }
                }
                Element::Echo | Element::Ok => {}
                Element::ErrorFrame(e) => {
                    tracing::debug!(class = format_args!("{:#05x}", e.class), data = ?e.data, "socketcand bus error");
                    if let Some(s) = e.bus_state() {
                        to.state.store(state_to_u8(s), Ordering::Relaxed);
                    }
                    if e.is_tx_overflow() {
                        to.tx_overflows.fetch_add(1, Ordering::Relaxed);
                    }
                    // For a recorder; nobody reading it must not stall the frames.
                    let _ = error_tx.try_send(e);
                }
                Element::Error(text) => tracing::warn!("socketcand server: `< {text} >`"),
                other => tracing::trace!("socketcand client ignored {other:?}"),
            }
        }
        let n = match stream.read(&mut buf) {
            Ok(0) => {
                return io::Error::new(
                    io::ErrorKind::ConnectionAborted,
                    "socketcand server closed the connection",
                )
            }
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return e,
        };
        let _ = stream.set_quickack(true);
        decoder.feed(&buf[..n], |b| elements.push(Element::parse(b)));
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        let (frames, ats) = self.sent_counts();
        if self.clock {
            tracing::debug!(frames, at_messages = ats, "timed socketcand client closed");
        }
        // Wakes the reader thread, which then ends.
        let _ = self.stream.shutdown(Shutdown::Both);
    }
}

impl Client {
    /// Reports a bus error to the channel's other clients (canpos hub extension, after
    /// `< errors on >`); `Ok(false)` when the server does not take them.
    pub fn send_error_frame(&mut self, e: &codec::ErrorFrame) -> io::Result<bool> {
        if !self.errors {
            return Ok(false);
        }
        let mut w = lock(&self.writer);
        w.horizon();
        codec::write_error_frame(&mut w.buf, e);
        w.flush()?;
        Ok(true)
    }
}

impl Transport for Client {
    /// Sends `< send ... >`. With a server that carries remote frames, a remote frame goes out
    /// as `< send ID DLC R >`; otherwise one with DLC 0 goes out as a zero-length data frame and
    /// one with DLC > 0 is refused (`InvalidInput`).
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        let mut w = lock(&self.writer);
        // A timed client's frame is stamped with the horizon it is sent at: the hub is told
        // first when that changed.
        w.horizon();
        if self.rtr {
            codec::write_send_rtr(&mut w.buf, frame);
        } else if !codec::write_send(&mut w.buf, frame) {
            // The horizon alone is harmless; the frame cannot go.
            w.flush()?;
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "socketcand cannot carry remote frames with DLC > 0",
            ));
        }
        w.frames += 1;
        w.flush()
    }

    /// A device on a canpos hub that accepted `< clock on >`: the runtime's horizon goes to the
    /// hub as `< at … >` (docs/CLOCK.md); `None` elsewhere (the runtime keeps its own clock).
    fn join_clock(&mut self) -> Option<Horizon> {
        timed_horizon(self)
    }

    fn receiver(&self) -> &Receiver<RxFrame> {
        &self.rx
    }

    fn dead_error(&self) -> io::Error {
        match &*self.error.lock().unwrap_or_else(|p| p.into_inner()) {
            Some(e) => io::Error::new(e.kind(), format!("socketcand {}: {e}", self.peer)),
            None => io::Error::new(
                io::ErrorKind::ConnectionAborted,
                "socketcand connection closed",
            ),
        }
    }

    fn send_error_frame(&mut self, e: &codec::ErrorFrame) -> io::Result<bool> {
        Client::send_error_frame(self, e)
    }

    fn error_frames(&self) -> Option<Receiver<codec::ErrorFrame>> {
        Some(self.error_rx.clone())
    }

    /// Overflows of its transmit queue on the bus, as a canpos hub reports them (after
    /// `< errors on >`).
    fn tx_overflows(&self) -> u64 {
        self.tx_overflows.load(Ordering::Relaxed)
    }

    fn bus_state(&self) -> BusState {
        match self.state.load(Ordering::Relaxed) {
            1 => BusState::ErrorPassive,
            2 => BusState::BusOff,
            _ => BusState::ErrorActive,
        }
    }

    fn describe(&self) -> String {
        format!("socketcand://{}/{}", self.peer, self.channel)
    }
}
