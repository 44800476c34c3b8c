//! The physical CAN bus every virtual transport shares: bit timing, arbitration, bus load and
//! error confinement (ISO 11898-1), as a sans-IO [`timeline`] plus the [`bits`] of a frame on
//! the wire. The in-process bus ([`crate::mem`]) and every channel of the socketcand hub run
//! their frames through a [`Timeline`]; docs/BUS.md describes the model.

pub mod bits;
pub mod timeline;

use std::time::SystemTime;

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

/// An error frame as listeners see it (e.g. for recording): when, what, and which frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ErrorFrame {
    /// End of the error delimiter on the bus timeline (wall clock).
    pub timestamp: SystemTime,
    /// What destroyed the frame.
    pub kind: BusErrorKind,
    /// Identifier of the frame that was on the wire, if any.
    pub id: Option<u32>,
}

impl ErrorFrame {
    /// The Linux SocketCAN error frame for it (`linux/can/error.h`): CAN ID with
    /// `CAN_ERR_FLAG` and the error class, and the 8 data bytes. Collision: a bit error
    /// (`CAN_ERR_PROT`, `data[2]` = `CAN_ERR_PROT_BIT`); corrupted: a form error
    /// (`CAN_ERR_PROT_FORM`); another node's error flag: a stuff error (`CAN_ERR_PROT_STUFF`);
    /// stuck dominant: `CAN_ERR_PROT_BIT0` ("unable to send recessive
    /// bit") with `CAN_ERR_BUSERROR`.
    pub fn to_socketcan(&self) -> (u32, [u8; 8]) {
        const CAN_ERR_FLAG: u32 = 0x2000_0000;
        const CAN_ERR_PROT: u32 = 0x0000_0008;
        const CAN_ERR_BUSERROR: u32 = 0x0000_0080;
        const PROT_BIT: u8 = 0x01;
        const PROT_FORM: u8 = 0x02;
        const PROT_STUFF: u8 = 0x04;
        const PROT_BIT0: u8 = 0x08;
        let mut data = [0u8; 8];
        let id = match self.kind {
            BusErrorKind::Collision => {
                data[2] = PROT_BIT;
                CAN_ERR_FLAG | CAN_ERR_PROT
            }
            BusErrorKind::Corrupted => {
                data[2] = PROT_FORM;
                CAN_ERR_FLAG | CAN_ERR_PROT
            }
            BusErrorKind::ErrorFlag => {
                data[2] = PROT_STUFF;
                CAN_ERR_FLAG | CAN_ERR_PROT
            }
            BusErrorKind::StuckDominant { .. } => {
                data[2] = PROT_BIT0;
                CAN_ERR_FLAG | CAN_ERR_PROT | CAN_ERR_BUSERROR
            }
        };
        (id, data)
    }
}
