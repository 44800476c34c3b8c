//! Wire-level types: the CAN frame, time, and COB-ID helpers shared by every service.
//!
//! Codecs for individual message kinds live next to the service that owns them; this module only
//! holds what all of them need.

pub mod cob;
mod frame;
mod time;

pub use frame::{Frame, FrameError};
pub use time::{Duration, Instant};
