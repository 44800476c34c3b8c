//! Wire-level types: the CAN frame, time, and COB-ID helpers shared by every service.
//!
//! Codecs for individual message kinds live next to the service that owns them; this module only
//! holds what all of them need.

mod frame;
mod time;

pub use frame::{Frame, FrameError};
pub use time::{Duration, Instant};

/// Function codes of the CiA 301 pre-defined connection set (the high four bits of an 11-bit id).
pub mod cob {
    /// NMT node control (master → all).
    pub const NMT: u16 = 0x000;
    /// Default SYNC COB-ID.
    pub const SYNC: u16 = 0x080;
    /// EMCY base; + node-id.
    pub const EMCY: u16 = 0x080;
    /// TPDO1 base; TPDO n uses `TPDO1 + 0x100 * (n - 1)` + node-id.
    pub const TPDO1: u16 = 0x180;
    /// SDO server → client base; + node-id.
    pub const SDO_TX: u16 = 0x580;
    /// SDO client → server base; + node-id.
    pub const SDO_RX: u16 = 0x600;
    /// Error control (boot-up, heartbeat, node guarding) base; + node-id.
    pub const ERRCTL: u16 = 0x700;
    /// LSS master → slave.
    pub const LSS_RX: u16 = 0x7E5;
    /// LSS slave → master.
    pub const LSS_TX: u16 = 0x7E4;
}
