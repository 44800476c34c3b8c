/// Most position channels a sample carries (TH multi-position: 4 magnets).
pub const MAX_CHANNELS: usize = 4;

/// What the sensing element delivers once per measurement cycle: the input of the CiA 406
/// encoder application. On a host it comes from `canpos-sim`; on a microcontroller from the
/// time-of-flight hardware.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    /// Measured position of channel n (the n-th magnet counted from the sensor head), in
    /// nanometres from the sensor's zero point (start of the measuring range). `None` when the
    /// channel has no usable return pulse (missing magnet, magnet in a dead zone, magnets too
    /// close together).
    pub positions_nm: [Option<i64>; MAX_CHANNELS],
    /// Internal (electronics) temperature in degrees Celsius.
    pub temperature_c: i8,
}

impl Default for Sample {
    fn default() -> Self {
        Sample {
            positions_nm: [None; MAX_CHANNELS],
            temperature_c: 25,
        }
    }
}

// One stored preset offset per channel (a TMI keeps them beside the dictionary).
const _: () = assert!(MAX_CHANNELS <= canpos_stack::config::APP_RECORDS);
