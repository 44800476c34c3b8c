//! CiA 406 encoder profile: channels, preset / offset, measuring steps, velocity, cams, work
//! areas, alarms.

mod sample;

pub use sample::{Sample, MAX_CHANNELS};
