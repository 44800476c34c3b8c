//! The CAN vocabulary of the host, at the bottom of it: frames as the host carries them
//! ([`RxFrame`]), a controller's error state ([`BusState`]) and counters ([`MemberStats`],
//! [`BusStats`]), what can go wrong on a bus ([`BusErrorKind`], [`Disturbance`]), the one
//! [`ErrorFrame`] type, and the [`Transport`] trait every bus connection implements. It names
//! no transport: the transports sit above it and the URL factory ([`crate::transport`]) above
//! them.
//!
//! # Design: every transport is a channel
//!
//! Every transport in this crate delivers received frames into a bounded
//! [`crossbeam_channel`] queue, filled either by the bus itself (in-process [`mem`](crate::mem)
//! bus, in-process hub participants) or by one reader thread per connection (socketcand client,
//! SocketCAN). [`Transport::receiver`] exposes that queue, so:
//!
//! - a thread driving **one** node calls [`Transport::recv_deadline`] with the node's next timer
//!   deadline and wakes exactly at the frame or at the deadline, whichever comes first;
//! - a thread driving **many** nodes builds one [`crossbeam_channel::Select`] over all their
//!   receivers and waits with [`Select::ready_deadline`](crossbeam_channel::Select::ready_deadline)
//!   on the earliest deadline, then drains the ready transports with [`Transport::try_recv`].
//!   No per-node thread and no polling are needed; sending never blocks on the network peer.
//!
//! A receiver that reports *disconnected* means the transport died (peer closed, interface
//! gone); the next `recv_*` call returns the reason as an error.

use std::io;
use std::time::{Duration, Instant, SystemTime};

use canpos_stack::Frame;
pub use crossbeam_channel::Receiver;

/// A received frame with the time it was seen on the bus.
///
/// On socketcand the timestamp is the one the server put in the `< frame ... >` element; on a
/// paced in-process bus or hub channel it is the frame's end-of-frame time on the bus timeline
/// (monotonic per bus); on an instant bus, the time of the `send`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RxFrame {
    /// The frame.
    pub frame: Frame,
    /// When the frame was on the bus (wall clock).
    pub timestamp: SystemTime,
}

impl RxFrame {
    /// A frame stamped with the current wall-clock time.
    pub fn now(frame: Frame) -> Self {
        RxFrame {
            frame,
            timestamp: SystemTime::now(),
        }
    }
}

/// Error state of the CAN controller (ISO 11898-1 fault confinement).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum BusState {
    /// Normal operation.
    #[default]
    ErrorActive,
    /// An error counter passed 127: the controller may only send passive error flags.
    ErrorPassive,
    /// The transmit error counter passed 255: the controller is off the bus.
    BusOff,
}

/// Load and counters of a paced virtual bus, and of one port's controller on it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BusStats {
    /// The bus's bit rate (its pacing), kbit/s.
    pub bitrate_kbps: u32,
    /// Share of the last second the bus was busy (0…1), error frames included.
    pub load: f64,
    /// Frames per second over the last second.
    pub frames_per_s: f64,
    /// Frames sent successfully since the bus started.
    pub frames: u64,
    /// Error frames since the bus started.
    pub error_frames: u64,
    /// Frames lost in transmit queues (full, or their controller bus-off), all members.
    pub tx_lost: u64,
    /// Deliveries lost because a receiver's queue was full, all members.
    pub rx_dropped: u64,
    /// This port's controller (counters, error state, transmit queue and its wait).
    pub controller: Option<MemberStats>,
}

/// A disturbance of a paced virtual bus (see docs/BUS.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Disturbance {
    /// Corrupt this many of every million frames (0 … 1 000 000; 0 stops).
    CorruptedFrames {
        /// Frames per million.
        per_million: u32,
    },
    /// Hold the bus dominant from now on for this long (one bit time … 60 s).
    StuckDominant {
        /// How long.
        duration: Duration,
    },
    /// This port's transceiver fails (its frames never reach the bus) or works again.
    TransceiverFailed(bool),
}

/// Counters of one member.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MemberStats {
    /// Frames that went on the bus successfully.
    pub sent: u64,
    /// Frames lost because the transmit queue was full.
    pub lost_overflow: u64,
    /// Frames lost because the member was (or went) bus-off.
    pub lost_bus_off: u64,
    /// Transmissions that ended in an error frame (retransmitted automatically).
    pub tx_errors: u64,
    /// Of those, collisions with another member sending the same identifier.
    pub collisions: u64,
    /// Time the last sent frame waited from submission to its start of frame.
    pub last_wait: u64,
    /// Longest such wait.
    pub max_wait: u64,
    /// Frames waiting in the transmit queue.
    pub queued: usize,
    /// Transmit error counter.
    pub tec: u16,
    /// Receive error counter.
    pub rec: u16,
    /// Error state.
    pub state: BusState,
}

/// What kind of error destroyed a frame (or held the bus).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BusErrorKind {
    /// Two or more members sent the same identifier with different control or data bits in one
    /// arbitration: each saw a bit error (a duplicate node-id shows up as this).
    Collision,
    /// A frame corrupted on the wire (injected disturbance): the receivers flag a CRC or form
    /// error.
    Corrupted,
    /// The bus was held dominant for `bits` bit times (injected disturbance).
    StuckDominant {
        /// Length of the dominant interval in bit times.
        bits: u64,
    },
    /// A member sent an active error flag ([`Timeline::error_flag`](crate::bus::Timeline::error_flag)): the other controllers
    /// see six dominant bits, a stuff error.
    ErrorFlag,
}
/// Linux CAN error classes (`linux/can/error.h`), as socketcand reports them.
pub mod err_class {
    /// Controller problems; data byte 1 says which.
    pub const CRTL: u32 = 0x0004;
    /// Bus off.
    pub const BUSOFF: u32 = 0x0040;
    /// Controller restarted (back to error active after bus-off).
    pub const RESTARTED: u32 = 0x0100;
    /// Protocol violation (an error frame on the wire; data bytes 2 and 3 say which).
    pub const PROT: u32 = 0x0008;
    /// No acknowledgement on transmission (the transmitter's ACK error).
    pub const ACK: u32 = 0x0020;
    /// Bus error (may flood: the controller reports every error frame).
    pub const BUSERROR: u32 = 0x0080;
    /// The classes that stand for an error frame on the bus; the others report one
    /// controller's own condition (its state, its transceiver, a lost arbitration, a timeout).
    pub const ON_THE_WIRE: u32 = PROT | ACK | BUSERROR;
    /// Data byte 1 of [`CRTL`]: receive error counter reached the passive level.
    pub const CRTL_RX_PASSIVE: u8 = 0x10;
    /// Data byte 1 of [`CRTL`]: transmit error counter reached the passive level.
    pub const CRTL_TX_PASSIVE: u8 = 0x20;
    /// Data byte 1 of [`CRTL`]: back to error active.
    pub const CRTL_ACTIVE: u8 = 0x40;
    /// Data byte 1 of [`CRTL`]: a frame was lost in the full transmit queue
    /// (`CAN_ERR_CRTL_TX_OVERFLOW`).
    pub const CRTL_TX_OVERFLOW: u8 = 0x02;
}

/// A CAN error frame as socketcand carries it: the error class (the identifier of a Linux error
/// frame) and, where the server gives them, the 8 data bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ErrorFrame {
    /// Error class bits ([`err_class`]).
    pub class: u32,
    /// The error frame's data (`None`: the server sent the class only, as socketcand's raw
    /// mode does).
    pub data: Option<[u8; 8]>,
    /// When the error was seen.
    pub timestamp: SystemTime,
    /// Identifier of the frame the error destroyed, where the bus model knows it (an error of
    /// the virtual bus); neither socketcand nor SocketCAN carries it, so `None` from them.
    pub id: Option<u32>,
}

impl ErrorFrame {
    /// The error frame of a bus error of the virtual bus model, as a Linux SocketCAN controller
    /// reports it (`linux/can/error.h`): collision, a bit error (`CAN_ERR_PROT`, `data[2]` =
    /// `CAN_ERR_PROT_BIT`); corrupted, a form error (`CAN_ERR_PROT_FORM`); another node's error
    /// flag, a stuff error (`CAN_ERR_PROT_STUFF`); stuck dominant, `CAN_ERR_PROT_BIT0` ("unable
    /// to send recessive bit") with `CAN_ERR_BUSERROR`.
    pub fn bus_error(kind: BusErrorKind, id: Option<u32>, timestamp: SystemTime) -> ErrorFrame {
        const PROT_BIT: u8 = 0x01;
        const PROT_FORM: u8 = 0x02;
        const PROT_STUFF: u8 = 0x04;
        const PROT_BIT0: u8 = 0x08;
        use err_class::{BUSERROR, PROT};
        let mut data = [0u8; 8];
        let class = match kind {
            BusErrorKind::Collision => {
                data[2] = PROT_BIT;
                PROT
            }
            BusErrorKind::Corrupted => {
                data[2] = PROT_FORM;
                PROT
            }
            BusErrorKind::ErrorFlag => {
                data[2] = PROT_STUFF;
                PROT
            }
            BusErrorKind::StuckDominant { .. } => {
                data[2] = PROT_BIT0;
                PROT | BUSERROR
            }
        };
        ErrorFrame {
            class,
            data: Some(data),
            timestamp,
            id,
        }
    }

    /// The error frame a controller reports on entering `state`.
    pub fn for_state(state: BusState, timestamp: SystemTime) -> ErrorFrame {
        use err_class::*;
        let (class, ctrl) = match state {
            BusState::BusOff => (BUSOFF, 0),
            BusState::ErrorPassive => (CRTL, CRTL_RX_PASSIVE | CRTL_TX_PASSIVE),
            BusState::ErrorActive => (CRTL | RESTARTED, CRTL_ACTIVE),
        };
        let mut data = [0u8; 8];
        data[1] = ctrl;
        ErrorFrame {
            class,
            data: Some(data),
            timestamp,
            id: None,
        }
    }

    /// The controller-problem frame of a transmit queue that overflowed (frames lost in it),
    /// as a canpos hub reports it to the client whose queue it is.
    pub fn tx_overflow(timestamp: SystemTime) -> ErrorFrame {
        let mut data = [0u8; 8];
        data[1] = err_class::CRTL_TX_OVERFLOW;
        ErrorFrame {
            class: err_class::CRTL,
            data: Some(data),
            timestamp,
            id: None,
        }
    }

    /// Whether it reports frames lost in the controller's full transmit queue.
    pub fn is_tx_overflow(&self) -> bool {
        self.class & err_class::CRTL != 0
            && self
                .data
                .is_some_and(|d| d[1] & err_class::CRTL_TX_OVERFLOW != 0)
    }

    /// The controller state the frame announces, if any: bus-off, restart / back to active, or
    /// a passive controller. A controller-problem class without data (socketcand's raw mode
    /// sends no data) is taken as error passive: that is the state a master must react to, and
    /// warnings and overflows alone do not reach a client without data.
    pub fn bus_state(&self) -> Option<BusState> {
        use err_class::*;
        if self.class & BUSOFF != 0 {
            return Some(BusState::BusOff);
        }
        if self.class & CRTL != 0 {
            return match self.data.map(|d| d[1]) {
                None => Some(BusState::ErrorPassive),
                Some(c) if c & (CRTL_RX_PASSIVE | CRTL_TX_PASSIVE) != 0 => {
                    Some(BusState::ErrorPassive)
                }
                Some(c) if c & CRTL_ACTIVE != 0 => Some(BusState::ErrorActive),
                Some(_) if self.class & RESTARTED != 0 => Some(BusState::ErrorActive),
                Some(_) => None,
            };
        }
        (self.class & RESTARTED != 0).then_some(BusState::ErrorActive)
    }
}
/// A connection to a CAN bus, as seen by one node (or one tool).
///
/// Frames sent through a transport are not received back by the same transport.
pub trait Transport: Send {
    /// Puts a frame on the bus. Never waits for other participants to read.
    fn send(&mut self, frame: &Frame) -> io::Result<()>;

    /// Waits up to `timeout` (`None`: forever, `Some(ZERO)`: just poll) for a frame.
    ///
    /// `Ok(None)` means the timeout passed; an error means the transport is dead.
    fn recv_timeout(&mut self, timeout: Option<Duration>) -> io::Result<Option<RxFrame>> {
        let rx = self.receiver();
        let r = match timeout {
            None => rx
                .recv()
                .map_err(|_| crossbeam_channel::RecvTimeoutError::Disconnected),
            Some(t) if t.is_zero() => rx.try_recv().map_err(|e| match e {
                crossbeam_channel::TryRecvError::Empty => {
                    crossbeam_channel::RecvTimeoutError::Timeout
                }
                crossbeam_channel::TryRecvError::Disconnected => {
                    crossbeam_channel::RecvTimeoutError::Disconnected
                }
            }),
            Some(t) => rx.recv_timeout(t),
        };
        match r {
            Ok(f) => Ok(Some(f)),
            Err(crossbeam_channel::RecvTimeoutError::Timeout) => Ok(None),
            Err(crossbeam_channel::RecvTimeoutError::Disconnected) => Err(self.dead_error()),
        }
    }

    /// Waits for a frame until the absolute `deadline` (monotonic clock).
    ///
    /// Waking is as precise as the OS allows: the underlying channel wait is deadline-based, so
    /// there is no drift from re-computing relative timeouts.
    fn recv_deadline(&mut self, deadline: Instant) -> io::Result<Option<RxFrame>> {
        match self.receiver().recv_deadline(deadline) {
            Ok(f) => Ok(Some(f)),
            Err(crossbeam_channel::RecvTimeoutError::Timeout) => Ok(None),
            Err(crossbeam_channel::RecvTimeoutError::Disconnected) => Err(self.dead_error()),
        }
    }

    /// Returns a frame if one is queued, without waiting.
    fn try_recv(&mut self) -> io::Result<Option<RxFrame>> {
        self.recv_timeout(Some(Duration::ZERO))
    }

    /// The queue received frames arrive in; use it to wait on many transports at once
    /// (see the [module docs](self)). Taking frames from it directly is allowed.
    fn receiver(&self) -> &Receiver<RxFrame>;

    /// Why the transport stopped, once its receiver reports disconnected.
    fn dead_error(&self) -> io::Error {
        io::Error::new(io::ErrorKind::ConnectionAborted, "CAN transport closed")
    }

    /// The bus bit rate in kbit/s, when the bus models one (the in-process bus can); a node
    /// configured for another bit rate must neither send nor receive.
    fn bus_bitrate(&self) -> Option<u32> {
        None
    }

    /// Frames this transport lost because its receive queue was full; the runtime raises the
    /// CAN overrun EMCY on them. SocketCAN: the frames its controller reported lost and those
    /// given up after a full transmit queue, not those the host lost by running late (the
    /// kernel's socket buffer, canpos's own queue: `socketcan::Stats`).
    fn dropped(&self) -> u64 {
        0
    }

    /// The CAN controller's error state, where the transport can know it (SocketCAN error
    /// frames); otherwise always error-active.
    fn bus_state(&self) -> BusState {
        BusState::ErrorActive
    }

    /// Times the server reported frames lost in this transport's own full transmit queue on the
    /// bus (a canpos hub's TX-overflow error frames: the bus could not take what this process
    /// sends); the runtime reacts as a sensor's controller does. 0 where the transport cannot
    /// know ([`Transport::bus_stats`] gives in-process ports their controller's counters).
    fn tx_overflows(&self) -> u64 {
        0
    }

    /// Puts a bus error on the bus for its other listeners, where the transport can (a canpos
    /// hub that accepted `< errors on >`: docs/SOCKETCAND.md); `Ok(false)` where it cannot.
    fn send_error_frame(&mut self, e: &ErrorFrame) -> io::Result<bool> {
        let _ = e;
        Ok(false)
    }

    /// The bus's error frames as this transport receives them (a canpos hub's `< error … >`
    /// after `< errors on >`, SocketCAN's `CAN_ERR_FLAG` frames), in arrival order, for a
    /// recorder: `None` where the transport delivers none. Every call returns the same queue
    /// (bounded: a listener that falls behind loses the excess).
    fn error_frames(&self) -> Option<Receiver<ErrorFrame>> {
        None
    }

    /// How many times the transport lost its bus and got it back (a socketcand server that went
    /// away and returned); the runtime boots its nodes again after each, as after a power
    /// cycle. Always 0 for transports that do not reconnect.
    fn reconnections(&self) -> u64 {
        0
    }

    /// Load and counters of the bus and of this port's controller, where the transport models
    /// the bus (paced in-process buses and hub channels).
    fn bus_stats(&self) -> Option<BusStats> {
        None
    }

    /// Another CAN controller on the same bus for one more node of this process: it only
    /// transmits (what it sends does not come back through this transport), with its own
    /// transmit queue and error counters. `None` where the transport is one controller only
    /// (a TCP connection, a SocketCAN socket).
    fn controller(&self) -> Option<Box<dyn Transport>> {
        None
    }

    /// Disturbs the bus (or, for [`Disturbance::TransceiverFailed`], this port's
    /// transceiver). Parameters out of range are refused and change nothing.
    fn disturb(&self, d: Disturbance) -> Result<(), String> {
        let _ = d;
        Err(format!(
            "{} has no physical bus model to disturb",
            self.describe()
        ))
    }

    /// Asks the transport to deliver only frames with these standard COB-IDs (plus remote
    /// frames); `Ok(true)` when it did (SocketCAN kernel filters), `Ok(false)` when it does not
    /// filter. Other frames may still arrive.
    fn set_rx_filter(&mut self, std_ids: &[u16]) -> io::Result<bool> {
        let _ = std_ids;
        Ok(false)
    }

    /// Joins the bus's simulation clock as a timed participant (docs/CLOCK.md): the bus runs
    /// no further than the returned horizon, stamps this transport's frames (and those of its
    /// [`controller`](Transport::controller)s) with it, and waits at each frame it delivered
    /// here until [`Horizon::taken`](crate::clock::Horizon::taken). A sensor's connection to a
    /// canpos hub that accepted `< clock on >` forwards the horizon to the hub as `< at … >`
    /// instead (docs/CLOCK.md, "Behind the hub"). `None` where the bus has no simulation clock
    /// (a SocketCAN interface, another socketcand server: their time is the wall clock's).
    fn join_clock(&mut self) -> Option<crate::clock::Horizon> {
        None
    }

    /// Runs an in-process bus to its clock's time on the caller's thread, delivering what is
    /// due (a timed participant does this before it takes its frames); nothing elsewhere.
    fn sync_bus(&self) {}

    /// A short description for logs, e.g. the URL.
    fn describe(&self) -> String;
}

impl<T: Transport + ?Sized> Transport for Box<T> {
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        (**self).send(frame)
    }
    fn recv_timeout(&mut self, timeout: Option<Duration>) -> io::Result<Option<RxFrame>> {
        (**self).recv_timeout(timeout)
    }
    fn recv_deadline(&mut self, deadline: Instant) -> io::Result<Option<RxFrame>> {
        (**self).recv_deadline(deadline)
    }
    fn try_recv(&mut self) -> io::Result<Option<RxFrame>> {
        (**self).try_recv()
    }
    fn receiver(&self) -> &Receiver<RxFrame> {
        (**self).receiver()
    }
    fn dead_error(&self) -> io::Error {
        (**self).dead_error()
    }
    fn bus_bitrate(&self) -> Option<u32> {
        (**self).bus_bitrate()
    }
    fn dropped(&self) -> u64 {
        (**self).dropped()
    }
    fn bus_state(&self) -> BusState {
        (**self).bus_state()
    }
    fn tx_overflows(&self) -> u64 {
        (**self).tx_overflows()
    }
    fn set_rx_filter(&mut self, std_ids: &[u16]) -> io::Result<bool> {
        (**self).set_rx_filter(std_ids)
    }
    fn reconnections(&self) -> u64 {
        (**self).reconnections()
    }
    fn error_frames(&self) -> Option<Receiver<ErrorFrame>> {
        (**self).error_frames()
    }
    fn send_error_frame(&mut self, e: &ErrorFrame) -> io::Result<bool> {
        (**self).send_error_frame(e)
    }
    fn bus_stats(&self) -> Option<BusStats> {
        (**self).bus_stats()
    }
    fn controller(&self) -> Option<Box<dyn Transport>> {
        (**self).controller()
    }
    fn disturb(&self, d: Disturbance) -> Result<(), String> {
        (**self).disturb(d)
    }
    fn join_clock(&mut self) -> Option<crate::clock::Horizon> {
        (**self).join_clock()
    }
    fn sync_bus(&self) {
        (**self).sync_bus()
    }
    fn describe(&self) -> String {
        (**self).describe()
    }
}
