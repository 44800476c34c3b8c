//! The hub's event loop: one thread, `mio` over the listener, every client socket and the
//! waker; accepts, reads and parses, forwards to the channel's bus, writes. [`Hub::run`] and
//! [`Hub::spawn`] start it.

use std::collections::HashMap;
use std::io::{self, Read, Write};
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::sync::Arc;
use std::thread::{self};
use std::time::{Duration, Instant};

use mio::net::TcpListener as MioListener;
use mio::{Events, Interest, Poll, Token};

use crate::mem::Sink;
use crate::socketcand::codec::{self, Decoder, Element, Piece};
use crate::socketcand::session::{Effect, Session};
use crate::wake::Wake;

use super::conn::*;
use super::*;

impl Hub {
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

pub(super) struct EventLoop {
    pub(super) listener: MioListener,
    pub(super) poll: Poll,
    pub(super) shared: Arc<Shared>,
    pub(super) conns: HashMap<usize, Conn>,
    pub(super) next_token: usize,
    /// No client deadline comes before this (it may be early: idle deadlines move on).
    pub(super) earliest: Option<Instant>,
    /// Accepting failed (e.g. out of descriptors) with connections left in the backlog: the
    /// listener is edge-triggered and will not report them again, so retry on a timer.
    pub(super) accept_retry: bool,
    /// Accepts that failed since the last one that worked, and when that was last logged: a
    /// process out of descriptors retries every 10 ms, and must not log 100 lines a second.
    pub(super) accept_failures: u64,
    pub(super) accept_warned: Option<Instant>,
    /// An accept slice ended before the backlog did.
    pub(super) accept_more: bool,
    /// Connections whose session has timed work (BCM send jobs, statistics): when it is due.
    pub(super) timed: HashMap<usize, Instant>,
    /// Clients to serve again next turn without waiting for an event: their socket had more to
    /// read than one turn takes, or their queue more than the output took while the socket
    /// still had room. Readiness is edge-triggered: no new event would come for either.
    pub(super) again: Vec<usize>,
    /// Frames formatted once for all plain raw clients.
    pub(super) cache: TextCache,
    /// Slow clients (may hold tokens of clients no longer slow or gone: dropped when met), and
    /// where the next slice of them starts.
    pub(super) slow: Vec<usize>,
    pub(super) slow_pos: usize,
    /// When the next slice of slow clients is written.
    pub(super) slow_next: Instant,
}

impl EventLoop {
    pub(super) fn new(hub: Hub) -> io::Result<EventLoop> {
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

    pub(super) fn run(mut self) -> io::Result<()> {
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
    pub(super) fn next_deadline(&self) -> Option<Instant> {
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
    pub(super) fn timers(&mut self, now: Instant, touched: &mut Vec<usize>) {
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

    pub(super) fn accept(&mut self, now: Instant) {
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

    pub(super) fn read(&mut self, t: usize, now: Instant) {
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
    pub(super) fn set_timed(&mut self, t: usize, due: Option<Instant>) {
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
    pub(super) fn run_timed(&mut self, now: Instant, touched: &mut Vec<usize>) {
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
    pub(super) fn post_errors(&mut self, touched: &mut Vec<usize>) {
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
    pub(super) fn slow_slice(&mut self, touched: &mut Vec<usize>) {
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

    pub(super) fn note_deadline(&mut self, d: Instant) {
        self.earliest = Some(self.earliest.map_or(d, |e| e.min(d)));
    }

    /// Output, interest and closing of one client.
    pub(super) fn service(&mut self, t: usize, now: Instant) {
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
pub(super) fn consume(
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
pub(super) fn handle_element(
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
pub(super) fn clock_option(c: &mut Conn, on: bool) {
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
pub(super) fn at(c: &mut Conn, t: std::time::SystemTime) {
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

pub(super) fn valid_channel(ch: &str) -> bool {
    !ch.is_empty() && ch.len() <= 64 && ch.bytes().all(|b| b.is_ascii_graphic())
}
