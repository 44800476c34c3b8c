//! CiA 406 encoder profile: channels, preset / offset, measuring steps, velocity, cams, work
//! areas, alarms.

mod sample;

pub use sample::{Sample, MAX_CHANNELS};

use crate::emcy::{self, Emcy};
use crate::models::{DeviceConfig, Model};
use crate::od::{Abort, Dictionary};
use crate::pdo::Tpdos;
use crate::wire::Instant;

/// What the application may touch while it runs a cycle or reacts to a write.
pub struct AppCtx<'a> {
    /// The dictionary (live values are written here).
    pub od: &'a mut Dictionary,
    /// EMCY producer.
    pub emcy: &'a mut Emcy,
    /// TPDOs (told about changed mapped values).
    pub pdo: &'a mut Tpdos,
    /// The product model.
    pub model: &'static Model,
    /// Current time.
    pub now: Instant,
}

/// Read-only view for write validation.
pub struct AppView<'a> {
    /// The dictionary.
    pub od: &'a Dictionary,
    /// The product model.
    pub model: &'static Model,
    /// The unit configuration.
    pub cfg: &'a DeviceConfig,
}

/// The CiA 406 application state (per-channel history the dictionary does not hold).
#[derive(Clone, Debug, Default)]
pub struct Encoder {
    last_nm: [Option<i64>; MAX_CHANNELS],
    missing: [bool; MAX_CHANNELS],
    alarm: bool,
}

impl Encoder {
    /// Forgets runtime state (reset node).
    pub fn reset(&mut self) {
        *self = Encoder::default();
    }

    /// Runs one measurement cycle. Returns true when the model's reaction forces the node back
    /// to pre-operational.
    pub fn cycle(&mut self, s: &Sample, cx: &mut AppCtx<'_>) -> bool {
        let step = cx.od.value(0x6005, 1).unwrap_or(1000).max(1) as i64;
        let channels = cx.od.value(0x6020, 0).unwrap_or(1) as usize;
        let mut any_missing = false;
        for ch in 0..channels.min(MAX_CHANNELS) {
            let sub = ch as u8 + 1;
            match s.positions_nm[ch] {
                Some(nm) => {
                    let pos = (nm / step) as i32;
                    cx.od.set_value(0x6020, sub, pos as u32);
                    if let Some(prev) = self.last_nm[ch] {
                        let vstep = cx.od.value(0x6005, 2).unwrap_or(100).max(1) as i64;
                        // nm per cycle → 0.01 mm/s per cycle time (1 ms default).
                        let v = (nm - prev) * 100 / vstep / 1000;
                        cx.od.set_value(0x6030, sub, v as i16 as u16 as u32);
                    }
                    self.last_nm[ch] = Some(nm);
                    self.missing[ch] = false;
                }
                None => {
                    self.missing[ch] = true;
                    any_missing = true;
                }
            }
        }
        if any_missing != self.alarm {
            self.alarm = any_missing;
            cx.od.set_value(0x6503, 0, any_missing as u32);
            if any_missing {
                cx.emcy
                    .raise(emcy::code::HARDWARE, emcy::reg::MANUFACTURER, [0; 5]);
            } else {
                cx.emcy.clear(emcy::code::HARDWARE);
            }
        }
        false
    }

    /// TMI lock-out active (Operational refused until a power cycle).
    pub fn lockout(&self) -> bool {
        false
    }

    /// Repeats the lock-out EMCY on a refused start.
    pub fn repeat_lockout_emcy(&self, _emcy: &mut Emcy) {}

    /// The stored data failed to load.
    pub fn storage_corrupt(&mut self, _emcy: &mut Emcy, _model: &Model) {}

    /// Whether the model reports corrupt storage itself (TMI 0x1002 bit 14) instead of the
    /// generic EMCY 0x6300.
    pub fn handles_storage_corrupt(&self, _model: &Model) -> bool {
        false
    }

    /// Application rules for a write to 0x2000–0x9FFF.
    pub fn validate(
        &self,
        _index: u16,
        _sub: u8,
        _raw: u32,
        _cx: &AppView<'_>,
    ) -> Result<(), Abort> {
        Ok(())
    }

    /// Side effects of a write to 0x2000–0x9FFF.
    pub fn written(&mut self, _index: u16, _sub: u8, _raw: u32, _cx: &mut AppCtx<'_>) {}
}
