//! Wire-level types: the CAN frame, time, and COB-ID helpers shared by every service, and the
//! frames of the LSS ([`lss`]) and NMT ([`nmt`]) services, parsed and emitted for both ends
//! (the SDO frames are `sdo::wire`'s).

pub mod cob;
mod frame;
pub mod lss;
pub mod nmt;
mod time;

pub use frame::{Frame, FrameError};
pub use time::{Duration, Instant};
