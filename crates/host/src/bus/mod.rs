//! The physical CAN bus every virtual transport shares: bit timing, arbitration, bus load and
//! error confinement (ISO 11898-1), as a sans-IO [`timeline`] plus the [`bits`] of a frame on
//! the wire. The in-process bus ([`crate::mem`]) and every channel of the socketcand hub run
//! their frames through a [`Timeline`]; docs/BUS.md describes the model.

pub mod bits;
pub mod controllers;
pub mod ports;
pub mod timeline;

pub use timeline::{
    check_bitrate, BusError, BusErrorKind, BusEvent, MemberId, MemberStats, Nanos, Timeline,
    TxOrder, CIA301_BITRATES, DEFAULT_TX_DEPTH,
};

/// The bit rate of a virtual bus whose rate nobody set, kbit/s: the fastest CiA 301 rate, so
/// that pacing never makes a workflow slower than a real bus could carry it (docs/BUS.md).
pub const DEFAULT_BITRATE_KBPS: u32 = 1000;

/// How a virtual bus delivers frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pacing {
    /// Frames take their time on the wire at this bit rate (kbit/s), one at a time.
    Paced(u32),
    /// Every frame is delivered at once, without limit (benchmarks only; never the default).
    Instant,
}

impl Default for Pacing {
    fn default() -> Self {
        Pacing::Paced(DEFAULT_BITRATE_KBPS)
    }
}
