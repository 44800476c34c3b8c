//! One TCP client of the hub ([`Conn`]): its socket, its state in the socketcand handshake, its
//! queue and its output, written at its own pace (fast clients per frame, slow ones in batches),
//! with the socket helpers that measure what it has not read.

use std::io::{self, Write};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use crossbeam_channel::{Receiver, TryRecvError};
use mio::net::TcpStream;

use crate::can::RxFrame;
use crate::mem::BusCore;
use crate::socketcand::codec::{self, Decoder, ErrorFrame};
use crate::socketcand::session::Session;
use crate::wake::Wake;

use super::*;

/// Turns on TCP_QUICKACK: Linux clears it after use, so it is re-armed after every read, and
/// the hub's ACKs never wait the ~40 ms of delayed ACK.
pub(super) fn quickack(stream: &TcpStream) {
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
pub(super) fn unread(stream: &TcpStream, peak: &mut u32) -> usize {
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
pub(super) fn send_urgent(stream: &TcpStream) -> io::Result<()> {
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

/// The plain raw-mode text of recent frames: every raw client of a channel gets the same frame
/// with the same timestamp, so it is formatted once, not once per client. Direct-mapped by the
/// frame's time; a miss formats it again.
pub(super) struct TextCache {
    pub(super) slots: Vec<Option<Cached>>,
}

/// A frame and its text (`None`: not writable in the plain form).
pub(super) type Cached = (RxFrame, Option<Box<[u8]>>);

impl TextCache {
    const SLOTS: usize = 1024;

    pub(super) fn new() -> TextCache {
        TextCache {
            slots: vec![None; Self::SLOTS],
        }
    }

    /// The text of `rx` for a plain raw client (`None`: it cannot be written in that form).
    pub(super) fn text(&mut self, rx: &RxFrame) -> Option<&[u8]> {
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

pub(super) enum State {
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
pub(super) struct Conn {
    pub(super) stream: TcpStream,
    pub(super) peer: SocketAddr,
    pub(super) state: State,
    pub(super) session: Session,
    pub(super) decoder: Decoder,
    /// Bytes not yet written, from `out_pos` on.
    pub(super) out: Vec<u8>,
    pub(super) out_pos: usize,
    /// Frames of this read not yet on the bus: they enter it together ([`Conn::submit`]).
    pub(super) sends: Vec<canpos_stack::Frame>,
    /// An urgent byte is sent once `out` is written up to here: right after a rawmode
    /// `< ok >` ([`send_urgent`]).
    pub(super) urgent_at: Option<usize>,
    /// Whether WRITABLE interest is registered (only while bytes wait).
    pub(super) writable: bool,
    /// The socket refused bytes (WouldBlock): no write is tried until it reports WRITABLE.
    pub(super) sock_full: bool,
    /// It had much not read at the last look ([`SLOW_QUEUE`]): written in batches.
    pub(super) slow: bool,
    /// Bytes written since the last look at what it has not read.
    pub(super) written: usize,
    /// Its token is in the event loop's list of slow clients.
    pub(super) listed: bool,
    /// The largest receive window the client advertised.
    pub(super) peak_window: u32,
    /// Input read but not yet handled: the client's output was full ([`HubConfig::out_limit`]); handled,
    /// and reading resumed, once the client has read its answers.
    pub(super) rest: Vec<u8>,
    pub(super) handshake_end: Instant,
    pub(super) last_rx: Instant,
    pub(super) closed: bool,
    /// A timed client's horizon on its channel bus's clock (`< clock on >`, docs/CLOCK.md):
    /// set by its `< at … >`, its frames stamped with it; dropped when it leaves.
    pub(super) horizon: Option<crate::clock::Horizon>,
}

impl Conn {
    pub(super) fn pending(&self) -> usize {
        self.out.len() - self.out_pos + usize::from(self.urgent_at.is_some())
    }

    /// Puts the frames the client sent since the last call on the bus together, at one time:
    /// frames that arrived together (one read of its socket) go out back to back, as a burst
    /// a host writes to its controller does, without gaps from the hub's own scheduling.
    pub(super) fn submit(&mut self, now: Instant, shared: &Shared, cache: &mut TextCache) {
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
    pub(super) fn tx_overflow(
        &mut self,
        lost: usize,
        now: Instant,
        shared: &Shared,
        cache: &mut TextCache,
    ) {
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
    pub(super) fn flush(&mut self) {
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
    pub(super) fn check_pace(&mut self) -> bool {
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
    pub(super) fn fill(&mut self, now: Instant, shared: &Shared, cache: &mut TextCache) {
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

    pub(super) fn leave(&mut self) {
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
