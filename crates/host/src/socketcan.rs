//! Linux SocketCAN transport (`socketcan://IFACE`), built on the `socketcan` crate.
//!
//! A reader thread blocks on the raw CAN socket (with a short timeout so it notices when the
//! transport is dropped) and feeds the receive queue; `send` writes from the caller's thread.
//! Kernels without `AF_CAN` make [`SocketCanTransport::open`] fail with an explanatory error.
//!
//! What real adapters need, and this transport does:
//!
//! - **Kernel receive filters**: [`Transport::set_rx_filter`] installs `CAN_RAW_FILTER`s for the
//!   COB-IDs the node listens to (the runtime passes NMT, SYNC, LSS, SDO and error control), plus
//!   every remote frame (RTR-triggered TPDOs, node guarding), so a busy bus does not wake the
//!   simulator for other nodes' traffic.
//! - **Receive timestamps**: `SO_TIMESTAMP`, the time the kernel received the frame; the wall
//!   clock at read time when the kernel gives none.
//! - **Lost frames**: frames the controller reported lost (`CAN_ERR_CRTL_RX_OVERFLOW` error
//!   frames) and frames given up after a full transmit queue make [`Transport::dropped`], on
//!   which the runtime raises the CAN overrun EMCY (0x8110): a real controller loses those. Frames
//!   lost on the host are counted and logged (at most once a second) but not in `dropped`: the
//!   kernel's (`SO_RXQ_OVFL`, `rx_kernel_dropped`: the socket's receive buffer was full because
//!   the reader thread was not scheduled in time) and canpos's own (`rx_queue_dropped`: the
//!   runtime thread did not take its frames in time). Both come from the host's scheduling, and
//!   the twin reports no fault of its own for that (docs/CLOCK.md); [`SocketCanTransport::stats`]
//!   and [`StatsHandle`] show them.
//! - **Full transmit queue** (`ENOBUFS` from the qdisc, `EAGAIN` after the send timeout): the
//!   frame is retried with exponential back-off ([`TX_RETRIES`] times, [`TX_BACKOFF_MAX`] total at
//!   most), then dropped and counted; never an error that stops the node.
//! - **Error frames** (`CAN_ERR_FLAG`): all error classes are received, counted and logged;
//!   error-passive and bus-off (and the return to error-active) update [`Transport::bus_state`],
//!   from which the runtime sends EMCY 0x8120 and, after a bus-off, 0x8140.

use std::io;
use std::mem::{size_of, MaybeUninit};
use std::os::fd::{AsRawFd, RawFd};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use canpos_stack::Frame;
use crossbeam_channel::{Receiver, Sender, TrySendError};
use socketcan::{CanFilter, CanFrame, CanSocket, Socket, SocketOptions};

use crate::can::{BusState, ErrorFrame, RxFrame, Transport};

/// Receive queue length, in frames.
pub const QUEUE_LEN: usize = 4096;
/// How often the reader thread checks whether the transport was dropped.
const POLL: Duration = Duration::from_millis(100);
/// How long one `write` may block on a full socket send buffer.
const SEND_TIMEOUT: Duration = Duration::from_millis(5);
/// Retries of a frame the transmit queue had no room for.
pub const TX_RETRIES: u32 = 8;
/// First back-off delay; doubled after every retry.
pub const TX_BACKOFF_FIRST: Duration = Duration::from_micros(100);
/// Upper bound of the total back-off of one frame.
pub const TX_BACKOFF_MAX: Duration = Duration::from_millis(20);

// linux/can.h, linux/can/error.h.
const CAN_EFF_FLAG: u32 = 0x8000_0000;
const CAN_RTR_FLAG: u32 = 0x4000_0000;
const CAN_ERR_FLAG: u32 = 0x2000_0000;
const CAN_SFF_MASK: u32 = 0x0000_07FF;
const CAN_EFF_MASK: u32 = 0x1FFF_FFFF;
const CAN_ERR_MASK: u32 = 0x1FFF_FFFF;
/// Error classes (`can_id` bits of an error frame).
pub mod err {
    /// TX timeout (by netdevice driver).
    pub const TX_TIMEOUT: u32 = 0x0001;
    /// Lost arbitration.
    pub const LOSTARB: u32 = 0x0002;
    /// Controller problems (details in data\[1\]).
    pub const CRTL: u32 = 0x0004;
    /// Protocol violations.
    pub const PROT: u32 = 0x0008;
    /// Transceiver status.
    pub const TRX: u32 = 0x0010;
    /// No ACK on transmission.
    pub const ACK: u32 = 0x0020;
    /// Bus off.
    pub const BUSOFF: u32 = 0x0040;
    /// Bus error.
    pub const BUSERROR: u32 = 0x0080;
    /// Controller restarted.
    pub const RESTARTED: u32 = 0x0100;
    /// data\[1\]: RX buffer overflow.
    pub const CRTL_RX_OVERFLOW: u8 = 0x01;
    /// data\[1\]: TX buffer overflow.
    pub const CRTL_TX_OVERFLOW: u8 = 0x02;
    /// data\[1\]: reached error-passive status RX.
    pub const CRTL_RX_PASSIVE: u8 = 0x10;
    /// data\[1\]: reached error-passive status TX.
    pub const CRTL_TX_PASSIVE: u8 = 0x20;
    /// data\[1\]: recovered to error-active state.
    pub const CRTL_ACTIVE: u8 = 0x40;
}

/// Converts a canpos frame to a SocketCAN frame.
pub fn to_socketcan(frame: &Frame) -> Option<CanFrame> {
    frame.to_embedded::<CanFrame>()
}

/// Converts a SocketCAN frame to a canpos frame; `None` for error frames, which are not
/// CAN traffic.
pub fn from_socketcan(frame: &CanFrame) -> Option<Frame> {
    match frame {
        CanFrame::Error(_) => None,
        f => Frame::from_embedded(f),
    }
}

/// Converts a kernel `struct can_frame` to a canpos frame; `None` for error frames.
fn from_raw(f: &libc::can_frame) -> Option<Frame> {
    if f.can_id & CAN_ERR_FLAG != 0 {
        return None;
    }
    let ext = f.can_id & CAN_EFF_FLAG != 0;
    let id = f.can_id & if ext { CAN_EFF_MASK } else { CAN_SFF_MASK };
    let dlc = f.can_dlc.min(8);
    if f.can_id & CAN_RTR_FLAG != 0 {
        Frame::remote(id, ext, dlc).ok()
    } else {
        Frame::with_id(id, ext, &f.data[..dlc as usize]).ok()
    }
}

/// Counters of one SocketCAN transport (all since it was opened).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// CAN frames received (error frames not included).
    pub rx_frames: u64,
    /// Frames received while canpos's receive queue was full, dropped.
    pub rx_queue_dropped: u64,
    /// Frames the kernel dropped because the socket's receive buffer was full (`SO_RXQ_OVFL`):
    /// the reader thread was not scheduled in time. Not in [`Stats::bus_losses`].
    pub rx_kernel_dropped: u64,
    /// Controller receive overflows reported by error frames.
    pub rx_controller_overflows: u64,
    /// Frames sent.
    pub tx_frames: u64,
    /// Retries after a full transmit queue.
    pub tx_retries: u64,
    /// Frames dropped after [`TX_RETRIES`] retries.
    pub tx_dropped: u64,
    /// Error frames received.
    pub error_frames: u64,
    /// Bus-off events.
    pub bus_off: u64,
}

impl Stats {
    /// Frames lost as a real controller loses them: its receive overflows and frames given up
    /// after a full transmit queue ([`Transport::dropped`], the runtime's EMCY 0x8110). Frames the
    /// host lost because a thread of canpos ran late (`rx_kernel_dropped`, `rx_queue_dropped`)
    /// are not in it: a busy host is no fault of the sensor.
    pub fn bus_losses(&self) -> u64 {
        self.rx_controller_overflows + self.tx_dropped
    }
}

/// A handle on a [`SocketCanTransport`]'s counters that outlives handing the transport over
/// (to a [`crate::Runtime`]).
#[derive(Clone)]
pub struct StatsHandle(Arc<Counters>);

impl StatsHandle {
    /// The counters now.
    pub fn get(&self) -> Stats {
        self.0.snapshot()
    }
}

#[derive(Default)]
struct Counters {
    rx_frames: AtomicU64,
    rx_queue_dropped: AtomicU64,
    rx_kernel_dropped: AtomicU64,
    rx_controller_overflows: AtomicU64,
    tx_frames: AtomicU64,
    tx_retries: AtomicU64,
    tx_dropped: AtomicU64,
    error_frames: AtomicU64,
    bus_off: AtomicU64,
    /// [`BusState`] as u8.
    state: AtomicU8,
}

impl Counters {
    fn snapshot(&self) -> Stats {
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        Stats {
            rx_frames: l(&self.rx_frames),
            rx_queue_dropped: l(&self.rx_queue_dropped),
            rx_kernel_dropped: l(&self.rx_kernel_dropped),
            rx_controller_overflows: l(&self.rx_controller_overflows),
            tx_frames: l(&self.tx_frames),
            tx_retries: l(&self.tx_retries),
            tx_dropped: l(&self.tx_dropped),
            error_frames: l(&self.error_frames),
            bus_off: l(&self.bus_off),
        }
    }

    fn state(&self) -> BusState {
        match self.state.load(Ordering::Relaxed) {
            1 => BusState::ErrorPassive,
            2 => BusState::BusOff,
            _ => BusState::ErrorActive,
        }
    }

    fn set_state(&self, s: BusState, iface: &str) {
        let v = match s {
            BusState::ErrorActive => 0,
            BusState::ErrorPassive => 1,
            BusState::BusOff => 2,
        };
        let old = self.state.swap(v, Ordering::Relaxed);
        if old != v {
            if s == BusState::BusOff {
                self.bus_off.fetch_add(1, Ordering::Relaxed);
            }
            tracing::warn!(iface, state = ?s, "CAN controller state changed");
        }
    }
}

/// Options of [`SocketCanTransport::open_with`].
#[derive(Clone, Debug, Default)]
pub struct Options {
    /// `SO_RCVBUF` in bytes (the kernel doubles it and enforces a minimum); `None`: the
    /// system default. Tests use a tiny one to provoke receive overflows.
    pub rcvbuf: Option<usize>,
}

/// A raw CAN socket bound to one interface.
pub struct SocketCanTransport {
    socket: Arc<CanSocket>,
    rx: Receiver<RxFrame>,
    stop: Arc<AtomicBool>,
    error: Arc<Mutex<Option<io::Error>>>,
    iface: String,
    counters: Arc<Counters>,
    /// The bus's error frames ([`Transport::error_frames`]).
    error_rx: Receiver<ErrorFrame>,
    /// Last time a transmit drop was logged (rate limit).
    last_tx_warn: Option<std::time::Instant>,
}

/// Adds a hint for the errors a missing CAN stack or interface produce.
fn explain(iface: &str, e: io::Error) -> io::Error {
    let hint = match e.raw_os_error() {
        Some(97) => " (this kernel has no SocketCAN support: AF_CAN is not available; use socketcand:// or mem:// instead)",
        Some(19) => " (no such network interface; for a virtual bus: ip link add dev vcan0 type vcan && ip link set up vcan0)",
        _ => "",
    };
    io::Error::new(e.kind(), format!("{iface}: {e}{hint}"))
}

fn setsockopt_int(
    fd: RawFd,
    level: libc::c_int,
    name: libc::c_int,
    v: libc::c_int,
) -> io::Result<()> {
    // SAFETY: the option value is one c_int we own, its size passed along.
    let r = unsafe {
        libc::setsockopt(
            fd,
            level,
            name,
            (&v as *const libc::c_int).cast(),
            size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    if r == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

impl SocketCanTransport {
    /// Opens interface `iface` (e.g. `can0`, `vcan0`).
    pub fn open(iface: &str) -> io::Result<Self> {
        Self::open_with(iface, &Options::default())
    }

    /// Opens interface `iface` with `opts`.
    pub fn open_with(iface: &str, opts: &Options) -> io::Result<Self> {
        let socket = CanSocket::open(iface).map_err(|e| explain(iface, e))?;
        socket.set_read_timeout(POLL)?;
        socket.set_write_timeout(SEND_TIMEOUT)?;
        // Every error class: the reader counts and logs them, the runtime reacts to states.
        socket.set_error_filter_accept_all()?;
        let fd = socket.as_raw_fd();
        if let Some(n) = opts.rcvbuf {
            setsockopt_int(
                fd,
                libc::SOL_SOCKET,
                libc::SO_RCVBUF,
                n.min(i32::MAX as usize) as i32,
            )?;
        }
        // Where the kernel lacks them, the transport still works (timestamps at read time, no
        // kernel drop count).
        if let Err(e) = setsockopt_int(fd, libc::SOL_SOCKET, libc::SO_RXQ_OVFL, 1) {
            tracing::debug!(iface, error = %e, "SO_RXQ_OVFL not available");
        }
        if let Err(e) = setsockopt_int(fd, libc::SOL_SOCKET, libc::SO_TIMESTAMP, 1) {
            tracing::debug!(iface, error = %e, "SO_TIMESTAMP not available");
        }
        let socket = Arc::new(socket);
        let (tx, rx) = crossbeam_channel::bounded(QUEUE_LEN);
        let stop = Arc::new(AtomicBool::new(false));
        let error = Arc::new(Mutex::new(None));
        let counters = Arc::new(Counters::default());
        let (error_tx, error_rx) = crossbeam_channel::bounded(1024);
        let (s, st, er, c) = (
            socket.clone(),
            stop.clone(),
            error.clone(),
            counters.clone(),
        );
        let name = iface.to_string();
        thread::Builder::new()
            .name(format!("socketcan {iface}"))
            .spawn(move || {
                let e = reader(&s, &st, &tx, &error_tx, &c, &name);
                if let Some(e) = &e {
                    tracing::error!(iface = %name, error = %e, "SocketCAN reader stopped");
                }
                *er.lock().unwrap_or_else(|p| p.into_inner()) = e;
            })?;
        Ok(SocketCanTransport {
            socket,
            rx,
            stop,
            error,
            iface: iface.to_string(),
            counters,
            error_rx,
            last_tx_warn: None,
        })
    }

    /// The transport's counters.
    pub fn stats(&self) -> Stats {
        self.counters.snapshot()
    }

    /// A handle on the transport's counters, readable after the transport was handed over.
    pub fn stats_handle(&self) -> StatsHandle {
        StatsHandle(self.counters.clone())
    }
}

/// One `recvmsg` result.
struct RawRx {
    frame: libc::can_frame,
    /// `SO_TIMESTAMP`.
    timestamp: Option<SystemTime>,
    /// `SO_RXQ_OVFL`: frames dropped by the kernel on this socket so far.
    overflow: Option<u32>,
}

/// Reads one frame with its control messages.
fn recv_raw(fd: RawFd) -> io::Result<RawRx> {
    let mut frame = MaybeUninit::<libc::can_frame>::zeroed();
    let mut iov = libc::iovec {
        iov_base: frame.as_mut_ptr().cast(),
        iov_len: size_of::<libc::can_frame>(),
    };
    // Aligned room for a timeval and a u32 control message (and then some).
    let mut cbuf = [0u64; 16];
    // SAFETY: msghdr is plain data; all pointers set below point to live locals.
    let mut msg: libc::msghdr = unsafe { std::mem::zeroed() };
    msg.msg_iov = &mut iov;
    msg.msg_iovlen = 1;
    msg.msg_control = cbuf.as_mut_ptr().cast();
    msg.msg_controllen = size_of::<[u64; 16]>() as _;
    // SAFETY: fd is a socket; msg describes valid buffers.
    let n = unsafe { libc::recvmsg(fd, &mut msg, 0) };
    if n < 0 {
        return Err(io::Error::last_os_error());
    }
    if (n as usize) < size_of::<libc::can_frame>() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("short CAN read: {n} bytes"),
        ));
    }
    let mut out = RawRx {
        // SAFETY: the kernel filled the whole struct (checked above); it was zeroed before.
        frame: unsafe { frame.assume_init() },
        timestamp: None,
        overflow: None,
    };
    // SAFETY: standard control-message walk over the buffer the kernel filled.
    unsafe {
        let mut c = libc::CMSG_FIRSTHDR(&msg);
        while !c.is_null() {
            let h = &*c;
            if h.cmsg_level == libc::SOL_SOCKET {
                let data = libc::CMSG_DATA(c);
                if h.cmsg_type == libc::SCM_TIMESTAMP {
                    let tv: libc::timeval = std::ptr::read_unaligned(data.cast());
                    out.timestamp = Some(
                        UNIX_EPOCH
                            + Duration::new(
                                tv.tv_sec.max(0) as u64,
                                (tv.tv_usec.max(0) as u32) * 1000,
                            ),
                    );
                } else if h.cmsg_type == libc::SO_RXQ_OVFL {
                    out.overflow = Some(std::ptr::read_unaligned(data.cast::<u32>()));
                }
            }
            c = libc::CMSG_NXTHDR(&msg, c);
        }
    }
    Ok(out)
}

/// Counts, logs and interprets one error frame.
fn on_error_frame(f: &libc::can_frame, c: &Counters, iface: &str) {
    c.error_frames.fetch_add(1, Ordering::Relaxed);
    let class = f.can_id & CAN_ERR_MASK;
    let ctrl = f.data[1];
    tracing::debug!(iface, class = format_args!("{class:#05x}"), data = ?f.data, "CAN error frame");
    if class & err::CRTL != 0 && ctrl & err::CRTL_RX_OVERFLOW != 0 {
        c.rx_controller_overflows.fetch_add(1, Ordering::Relaxed);
    }
    if class & err::BUSOFF != 0 {
        c.set_state(BusState::BusOff, iface);
    } else if class & err::RESTARTED != 0 {
        c.set_state(BusState::ErrorActive, iface);
    } else if class & err::CRTL != 0 {
        if ctrl & (err::CRTL_RX_PASSIVE | err::CRTL_TX_PASSIVE) != 0 {
            c.set_state(BusState::ErrorPassive, iface);
        } else if ctrl & err::CRTL_ACTIVE != 0 {
            c.set_state(BusState::ErrorActive, iface);
        }
    }
}

/// The kernel's `SO_RXQ_OVFL` count as the reader sees it.
#[derive(Default)]
struct KernelOverflow {
    /// The last count the kernel reported (cumulative, wraps at 2^32).
    last: Option<u32>,
    /// Last time a kernel drop was logged (rate limit).
    last_warn: Option<std::time::Instant>,
}

impl KernelOverflow {
    /// Takes the kernel's cumulative drop count `n` delivered with a frame: counts the frames
    /// lost since the last one in `rx_kernel_dropped` (not in [`Transport::dropped`]: the reader
    /// thread ran late, the bus lost nothing) and logs at most once a second.
    fn update(&mut self, n: u32, c: &Counters, iface: &str, now: std::time::Instant) {
        let lost = n.wrapping_sub(self.last.unwrap_or(0));
        self.last = Some(n);
        if lost == 0 {
            return;
        }
        let total = c
            .rx_kernel_dropped
            .fetch_add(u64::from(lost), Ordering::Relaxed)
            + u64::from(lost);
        if self
            .last_warn
            .is_none_or(|t| now.duration_since(t) >= Duration::from_secs(1))
        {
            self.last_warn = Some(now);
            tracing::warn!(
                iface,
                lost,
                lost_total = total,
                "the kernel dropped received frames (socket receive buffer full: canpos's reader \
                 thread ran late, host busy): not reported as a CAN overrun"
            );
        }
    }
}

fn reader(
    socket: &CanSocket,
    stop: &AtomicBool,
    tx: &Sender<RxFrame>,
    error_tx: &Sender<ErrorFrame>,
    c: &Counters,
    iface: &str,
) -> Option<io::Error> {
    let fd = socket.as_raw_fd();
    let mut kernel_ovfl = KernelOverflow::default();
    while !stop.load(Ordering::Relaxed) {
        match recv_raw(fd) {
            Ok(r) => {
                if let Some(n) = r.overflow {
                    kernel_ovfl.update(n, c, iface, std::time::Instant::now());
                }
                if r.frame.can_id & CAN_ERR_FLAG != 0 {
                    on_error_frame(&r.frame, c, iface);
                    // For a recorder; nobody reading it must not stall the frames.
                    let _ = error_tx.try_send(ErrorFrame {
                        class: r.frame.can_id & CAN_ERR_MASK,
                        data: Some(r.frame.data),
                        timestamp: r.timestamp.unwrap_or_else(SystemTime::now),
                        id: None,
                    });
                    continue;
                }
                let Some(frame) = from_raw(&r.frame) else {
                    continue;
                };
                c.rx_frames.fetch_add(1, Ordering::Relaxed);
                let rx = RxFrame {
                    frame,
                    timestamp: r.timestamp.unwrap_or_else(SystemTime::now),
                };
                match tx.try_send(rx) {
                    Ok(()) => {}
                    // A real bus cannot be paused: losing frames beats blocking the socket.
                    Err(TrySendError::Full(_)) => {
                        let n = c.rx_queue_dropped.fetch_add(1, Ordering::Relaxed) + 1;
                        if n.is_power_of_two() {
                            tracing::warn!(%iface, lost_total = n,
                                "the runtime did not take its received frames in time (host busy): frames lost, not reported as a CAN overrun");
                        }
                    }
                    Err(TrySendError::Disconnected(_)) => return None,
                }
            }
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock
                        | io::ErrorKind::TimedOut
                        | io::ErrorKind::Interrupted
                ) => {}
            // The interface went down (ip link set down) or its driver restarts: keep the
            // transport alive, it comes back with the interface.
            Err(e) if matches!(e.raw_os_error(), Some(libc::ENETDOWN) | Some(libc::ENOBUFS)) => {
                tracing::warn!(iface, error = %e, "CAN receive error; retrying");
                thread::sleep(POLL);
            }
            Err(e) => return Some(e),
        }
    }
    None
}

/// What [`send_with_backoff`] did with a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SendOutcome {
    /// Written after this many retries.
    Sent {
        /// Retries needed.
        retries: u32,
    },
    /// Dropped after [`TX_RETRIES`] retries.
    Dropped,
}

/// Whether a write error means "transmit queue full, try again later".
pub fn is_queue_full(e: &io::Error) -> bool {
    e.raw_os_error() == Some(libc::ENOBUFS)
        || matches!(
            e.kind(),
            io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
        )
}

/// Calls `write` until it succeeds, retrying a full transmit queue with exponential back-off
/// (from [`TX_BACKOFF_FIRST`], at most [`TX_RETRIES`] retries and [`TX_BACKOFF_MAX`] in total);
/// other errors are returned at once.
pub fn send_with_backoff(
    mut write: impl FnMut() -> io::Result<()>,
    mut sleep: impl FnMut(Duration),
) -> io::Result<SendOutcome> {
    let mut delay = TX_BACKOFF_FIRST;
    let mut slept = Duration::ZERO;
    let mut retries = 0;
    loop {
        match write() {
            Ok(()) => return Ok(SendOutcome::Sent { retries }),
            Err(e) if is_queue_full(&e) => {
                if retries >= TX_RETRIES || slept >= TX_BACKOFF_MAX {
                    return Ok(SendOutcome::Dropped);
                }
                let d = delay.min(TX_BACKOFF_MAX - slept);
                sleep(d);
                slept += d;
                delay *= 2;
                retries += 1;
            }
            Err(e) => return Err(e),
        }
    }
}

impl Drop for SocketCanTransport {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// The kernel filters for a node listening to `std_ids`: those IDs (data and remote), and every
/// standard remote frame.
pub fn filters_for(std_ids: &[u16]) -> Vec<CanFilter> {
    let mut v: Vec<CanFilter> = std_ids
        .iter()
        .map(|&id| CanFilter::new(u32::from(id) & CAN_SFF_MASK, CAN_EFF_FLAG | CAN_SFF_MASK))
        .collect();
    v.push(CanFilter::new(CAN_RTR_FLAG, CAN_EFF_FLAG | CAN_RTR_FLAG));
    v
}

impl Transport for SocketCanTransport {
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        let f = to_socketcan(frame).ok_or_else(|| {
            io::Error::new(io::ErrorKind::InvalidInput, "frame not representable")
        })?;
        let socket = &self.socket;
        let c = &self.counters;
        let out = send_with_backoff(
            || socket.write_frame(&f),
            |d| {
                c.tx_retries.fetch_add(1, Ordering::Relaxed);
                thread::sleep(d);
            },
        );
        match out {
            Ok(SendOutcome::Sent { .. }) => {
                c.tx_frames.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
            Ok(SendOutcome::Dropped) => {
                let n = c.tx_dropped.fetch_add(1, Ordering::Relaxed) + 1;
                let now = std::time::Instant::now();
                if self
                    .last_tx_warn
                    .is_none_or(|t| now.duration_since(t) >= Duration::from_secs(1))
                {
                    self.last_tx_warn = Some(now);
                    tracing::warn!(iface = %self.iface, dropped_total = n,
                        "CAN transmit queue full: frame dropped after back-off");
                }
                Ok(())
            }
            Err(e) => Err(e),
        }
    }

    fn receiver(&self) -> &Receiver<RxFrame> {
        &self.rx
    }

    fn dead_error(&self) -> io::Error {
        match &*self.error.lock().unwrap_or_else(|p| p.into_inner()) {
            Some(e) => io::Error::new(e.kind(), format!("socketcan {}: {e}", self.iface)),
            None => io::Error::new(io::ErrorKind::ConnectionAborted, "socketcan reader stopped"),
        }
    }

    fn dropped(&self) -> u64 {
        self.counters.snapshot().bus_losses()
    }

    fn bus_state(&self) -> BusState {
        self.counters.state()
    }

    fn error_frames(&self) -> Option<Receiver<ErrorFrame>> {
        Some(self.error_rx.clone())
    }

    fn set_rx_filter(&mut self, std_ids: &[u16]) -> io::Result<bool> {
        self.socket.set_filters(&filters_for(std_ids))?;
        Ok(true)
    }

    fn describe(&self) -> String {
        format!("socketcan://{}", self.iface)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use socketcan::EmbeddedFrame;

    #[test]
    fn converts_frames_both_ways() {
        let cases = [
            Frame::new(0x123, &[1, 2, 3]).unwrap(),
            Frame::new(0x000, &[]).unwrap(),
            Frame::with_id(0x1ABC_DEF0, true, &[0xFF; 8]).unwrap(),
            Frame::remote(0x705, false, 1).unwrap(),
            Frame::remote(0x1234, true, 0).unwrap(),
        ];
        for f in cases {
            let s = to_socketcan(&f).unwrap();
            assert_eq!(s.is_extended(), f.is_extended());
            assert_eq!(s.is_remote_frame(), f.is_remote());
            assert_eq!(EmbeddedFrame::dlc(&s), f.dlc() as usize);
            assert_eq!(from_socketcan(&s), Some(f));
        }
    }

    fn raw(can_id: u32, data: &[u8]) -> libc::can_frame {
        // SAFETY: can_frame is plain data.
        let mut f: libc::can_frame = unsafe { std::mem::zeroed() };
        f.can_id = can_id;
        f.can_dlc = data.len() as u8;
        f.data[..data.len()].copy_from_slice(data);
        f
    }

    #[test]
    fn converts_kernel_frames() {
        assert_eq!(
            from_raw(&raw(0x181, &[1, 2])),
            Some(Frame::new(0x181, &[1, 2]).unwrap())
        );
        assert_eq!(
            from_raw(&raw(0x77F | CAN_RTR_FLAG, &[0])),
            Some(Frame::remote(0x77F, false, 1).unwrap())
        );
        assert_eq!(
            from_raw(&raw(0x1234_5678 | CAN_EFF_FLAG, &[9; 8])),
            Some(Frame::with_id(0x1234_5678, true, &[9; 8]).unwrap())
        );
        assert_eq!(from_raw(&raw(CAN_ERR_FLAG | err::BUSOFF, &[0; 8])), None);
    }

    #[test]
    fn error_frames_are_not_traffic() {
        let e = socketcan::CanErrorFrame::new_error(0x004, &[0; 8]).unwrap();
        assert_eq!(from_socketcan(&CanFrame::Error(e)), None);
    }

    #[test]
    fn error_frames_drive_the_bus_state() {
        let c = Counters::default();
        let passive = raw(
            CAN_ERR_FLAG | err::CRTL,
            &[0, err::CRTL_TX_PASSIVE, 0, 0, 0, 0, 0, 0],
        );
        on_error_frame(&passive, &c, "t");
        assert_eq!(c.state(), BusState::ErrorPassive);
        on_error_frame(&raw(CAN_ERR_FLAG | err::BUSOFF, &[0; 8]), &c, "t");
        assert_eq!(c.state(), BusState::BusOff);
        on_error_frame(&raw(CAN_ERR_FLAG | err::RESTARTED, &[0; 8]), &c, "t");
        assert_eq!(c.state(), BusState::ErrorActive);
        let ovf = raw(
            CAN_ERR_FLAG | err::CRTL,
            &[0, err::CRTL_RX_OVERFLOW, 0, 0, 0, 0, 0, 0],
        );
        on_error_frame(&ovf, &c, "t");
        let s = c.snapshot();
        assert_eq!(
            (s.error_frames, s.bus_off, s.rx_controller_overflows),
            (4, 1, 1)
        );
        assert_eq!(c.state(), BusState::ErrorActive);
    }

    #[test]
    fn only_what_the_bus_lost_is_dropped() {
        let c = Counters::default();
        let mut k = KernelOverflow::default();
        let t0 = std::time::Instant::now();
        // The kernel's cumulative count, as delivered with frames: 5 lost, none more, 7 more.
        for (i, n) in [5u32, 5, 12].into_iter().enumerate() {
            k.update(n, &c, "t", t0 + Duration::from_millis(i as u64));
        }
        assert_eq!(c.snapshot().rx_kernel_dropped, 12);
        // The count wraps at 2^32.
        k.last = Some(u32::MAX - 1);
        k.update(2, &c, "t", t0);
        assert_eq!(c.snapshot().rx_kernel_dropped, 16);
        // The host's losses (kernel buffer, canpos's queue) raise no CAN overrun.
        c.rx_queue_dropped.fetch_add(3, Ordering::Relaxed);
        assert_eq!(c.snapshot().bus_losses(), 0);
        // The controller's own losses and frames given up after a full transmit queue do.
        let ovf = raw(
            CAN_ERR_FLAG | err::CRTL,
            &[0, err::CRTL_RX_OVERFLOW, 0, 0, 0, 0, 0, 0],
        );
        on_error_frame(&ovf, &c, "t");
        assert_eq!(c.snapshot().bus_losses(), 1);
        c.tx_dropped.fetch_add(1, Ordering::Relaxed);
        assert_eq!(c.snapshot().bus_losses(), 2);
        let s = c.snapshot();
        assert_eq!((s.rx_kernel_dropped, s.rx_queue_dropped), (16, 3));
    }

    #[test]
    fn full_tx_queue_backs_off_then_drops() {
        let enobufs = || io::Error::from_raw_os_error(libc::ENOBUFS);
        // Two refusals, then room: sent after two retries, sleeping 100 then 200 µs.
        let mut left = 2;
        let mut slept = Vec::new();
        let r = send_with_backoff(
            || {
                if left > 0 {
                    left -= 1;
                    Err(enobufs())
                } else {
                    Ok(())
                }
            },
            |d| slept.push(d),
        )
        .unwrap();
        assert_eq!(r, SendOutcome::Sent { retries: 2 });
        assert_eq!(
            slept,
            [Duration::from_micros(100), Duration::from_micros(200)]
        );
        // Never room: dropped, bounded in retries and in total time.
        let mut slept = Vec::new();
        let r = send_with_backoff(|| Err(enobufs()), |d| slept.push(d)).unwrap();
        assert_eq!(r, SendOutcome::Dropped);
        assert!(slept.len() as u32 <= TX_RETRIES);
        assert!(slept.iter().sum::<Duration>() <= TX_BACKOFF_MAX);
        // EAGAIN from the send timeout counts as a full queue too; other errors do not retry.
        let r = send_with_backoff(|| Err(io::Error::from(io::ErrorKind::WouldBlock)), |_| {});
        assert_eq!(r.unwrap(), SendOutcome::Dropped);
        let r = send_with_backoff(
            || Err(io::Error::from_raw_os_error(libc::ENETDOWN)),
            |_| panic!("must not retry"),
        );
        assert!(r.is_err());
    }

    #[test]
    fn filters_cover_ids_and_remote_frames() {
        let f = filters_for(&[0x000, 0x605]);
        assert_eq!(f.len(), 3);
    }

    #[test]
    fn open_fails_cleanly_without_can() {
        // Whatever this kernel has, a nonexistent interface must be an error, not a panic.
        let e = match SocketCanTransport::open("canposnone0") {
            Err(e) => e,
            Ok(_) => panic!("opened a nonexistent interface"),
        };
        assert!(e.to_string().contains("canposnone0"), "{e}");
        let e = match crate::transport::open("socketcan://canposnone0") {
            Err(e) => e.to_string(),
            Ok(_) => panic!("opened a nonexistent interface"),
        };
        assert!(
            e.contains("cannot open SocketCAN interface `canposnone0`"),
            "{e}"
        );
    }
}
