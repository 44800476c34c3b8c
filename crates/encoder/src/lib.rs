//! canpos-encoder: the CiA 406 encoder application on canpos-stack. Its profile: channels, preset / offset, measuring steps, velocity, cams, work
//! areas, alarms, and the device-side error reactions of each model (SPEC §10, §11).
//!
//! The application keeps in [`Encoder`] only what the dictionary cannot hold: the last measured
//! position of each channel (for velocity and for re-evaluating states after a write), the cam
//! hysteresis memory, and the fault conditions. Everything a master can see lives in the
//! dictionary, so one cycle reads its parameters there and writes its results there.
//!
//! Per channel n (sub-index n):
//!
//! ```text
//! steps    = round(measured_nm / 0x6005/1)            (to nearest, halves up; from the range start)
//! steps'   = max_steps − steps   if 0x6000 bit 0 (counts decrease away from the head)
//! position = steps' + offset_n                       (offset from the last preset: 0x650C/n,
//!                                                     or kept inside the device on a TMI)
//! velocity = Δnm / Δt in 0x6005/2 units (0.01 mm/s), rounded, sign flipped with bit 0
//! ```
#![no_std]
#![forbid(unsafe_code)]
#![deny(missing_docs)]

mod config;
pub mod hook;
mod sample;

pub use config::{
    common_param, limits, param, Channels, DeviceConfig, Fixed, Model, Switches, Unfixed,
};
pub use sample::{Sample, MAX_CHANNELS};

/// A position sensor: the CiA 301 / 305 stack running the CiA 406 application (`P`: the
/// description the build fixes, if any).
pub type SensorNode<S, P = Unfixed> = canpos_stack::Node<Encoder<P>, S>;

use canpos_stack::div;
use canpos_stack::emcy::{self, Emcy};
use canpos_stack::nmt::NmtState;
use canpos_stack::od::{Abort, Dictionary};
use canpos_stack::{AppCtx, AppView, Application};

/// The EMCY codes of the products' CiA 406 reactions that CiA 301 has no name for.
pub mod code {
    /// TMI: cam state changed.
    pub const TMI_CAM: u16 = 0x9080;
    /// TMI: work area state changed.
    pub const TMI_WORK_AREA: u16 = 0x9090;
}

/// TMI system-data errors (§1.14, 0x5000 with sub-codes). All but
/// [`SystemDataError::Unexpected`] lock the sensor out of Operational until a power cycle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SystemDataError {
    /// 0x5000 1/2/0, 0x1002 bit 13.
    WrongMapping,
    /// 0x5000 1/3/1, 0x1002 bit 12 (third byte lost in the manual's OCR: canpos uses 1).
    WrongVendorId,
    /// 0x5000 1/3/2, 0x1002 bit 11 (third byte lost in the manual's OCR: canpos uses 2).
    WrongScale,
    /// 0x5000 1/4/0, 0x1002 bit 10.
    WrongResolution,
    /// 0x5000 1/5/0, 0x1002 bit 9: forces pre-operational once, no lock-out.
    Unexpected,
    /// 0x5000 1/6/0, 0x1002 bit 8.
    NoSystemData,
    /// 0x5000 2/1/0, 0x1002 bit 14 (invalid serial number / product code in EEPROM).
    InvalidSerial,
}

impl SystemDataError {
    const ALL: [SystemDataError; 7] = [
        SystemDataError::WrongMapping,
        SystemDataError::WrongVendorId,
        SystemDataError::WrongScale,
        SystemDataError::WrongResolution,
        SystemDataError::Unexpected,
        SystemDataError::NoSystemData,
        SystemDataError::InvalidSerial,
    ];

    fn bit(self) -> u16 {
        1 << self as u16
    }

    /// EMCY bytes 3–5 (D13 layout: one byte per field of the manual's table).
    fn mfr(self) -> [u8; 5] {
        match self {
            SystemDataError::WrongMapping => [1, 2, 0, 0, 0],
            SystemDataError::WrongVendorId => [1, 3, 1, 0, 0],
            SystemDataError::WrongScale => [1, 3, 2, 0, 0],
            SystemDataError::WrongResolution => [1, 4, 0, 0, 0],
            SystemDataError::Unexpected => [1, 5, 0, 0, 0],
            SystemDataError::NoSystemData => [1, 6, 0, 0, 0],
            SystemDataError::InvalidSerial => [2, 1, 0, 0, 0],
        }
    }

    fn status_bit(self) -> u32 {
        match self {
            SystemDataError::WrongMapping => 1 << 13,
            SystemDataError::WrongVendorId => 1 << 12,
            SystemDataError::WrongScale => 1 << 11,
            SystemDataError::WrongResolution => 1 << 10,
            SystemDataError::Unexpected => 1 << 9,
            SystemDataError::NoSystemData => 1 << 8,
            SystemDataError::InvalidSerial => 1 << 14,
        }
    }

    fn locks_out(self) -> bool {
        self != SystemDataError::Unexpected
    }
}

/// A fault that surfaces in the CANopen core (SPEC §11). Magnet faults (missing, extra, too
/// close) arrive through the [`Sample`] instead; storage corruption through the storage check
/// at power-on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// Sensor (transducer) error: EMCY 0x5000, register 0x81 (TMI: 0x5000 1/1/0, process
    /// values, cam and work-area states frozen); 0x6503 bit 0.
    Transducer,
    /// Supply voltage out of range: EMCY 0x3100, register 0x05 (TH/E Example 3).
    SupplyVoltage,
    /// Over-temperature: EMCY 0x4200, register 0x09 (no manual lists a code; CiA 301's
    /// "device temperature").
    OverTemperature,
    /// CAN controller error passive: EMCY 0x8120, register 0x11 (TMI 0x1002 bit 5).
    CanErrorPassive,
    /// A communication error of no more specific kind: EMCY 0x8100 "Communication (generic)",
    /// register 0x11 (TH Table 5, E-Series EMCY table). The TMI's table has no such code: it
    /// reports nothing.
    Communication,
    /// PDOs not processed because of their length: EMCY 0x8210 with register 0x11 (TH /
    /// E-Series Table 5 and Table 6: a communication error), which 0x1001 shows until the
    /// condition is removed (then 0x0000; "Emergency objects go along with changes of the
    /// internal error status register", §5.6.1). The sensors have no RPDO, so only the
    /// injection raises it. Not in the TMI's table: nothing.
    PdoLength,
    /// CAN bus-off: while active the host keeps the node off the bus (TMI 0x1002 bits 4, 3;
    /// TH / E-Series: 0x1001 shows the communication error, 0x11); clearing it is the
    /// recovery, EMCY 0x8140 (TH / E-Series with register 0x11, then 0x0000).
    CanBusOff,
    /// CAN controller overrun: EMCY 0x8110 (TMI 0x8110 1/0/0, 0x1002 bit 7).
    CanOverrun,
    /// CAN software buffer overflow: EMCY 0x8110 (TMI 0x8110 2/0/0, 0x1002 bit 6).
    CanBufferOverflow,
    /// The bus cannot take the frames the node produces: its transmit queue overflows and
    /// frames are lost. TH / E-Series: CAN overrun, EMCY 0x8110 (their EMCY tables). TMI:
    /// "Insufficient Event Timer Value", EMCY 0x6000 1/0/0 and 0x1002 bit 15, "TPDO1 sending
    /// will occur partially" (002 §1.14).
    TransmitOverflow,
    /// The controller saw a bit error while sending its own identifier (another node sends
    /// the same COB-ID): TH / E-Series one-shot EMCY 0x8150 "CAN ID collision"; not in the
    /// TMI's table: nothing. `active == false` does nothing.
    CobIdCollision,
    /// Warning bits of 0x6505 (only bits the model supports in 0x6506 are set, D3).
    Warning(u16),
    /// TMI system-data error (lock-out, §1.14). On TH / E-Series it reports as a transducer
    /// error.
    SystemData(SystemDataError),
}

// Condition bits of `Encoder::faults`.
const F_TRANSDUCER: u16 = 1 << 0;
const F_VOLTAGE: u16 = 1 << 1;
const F_TEMPERATURE: u16 = 1 << 2;
const F_PASSIVE: u16 = 1 << 3;
const F_BUS_OFF: u16 = 1 << 4;
const F_OVERRUN: u16 = 1 << 5;
const F_BUFFER: u16 = 1 << 6;
const F_EVENT_TIMER: u16 = 1 << 7;
const F_MISSING: u16 = 1 << 8;
const F_COMMUNICATION: u16 = 1 << 9;
const F_TX_OVERFLOW: u16 = 1 << 10;
const F_PDO_LENGTH: u16 = 1 << 11;

/// Per-channel memory.
#[derive(Clone, Copy, Debug, Default)]
struct Channel {
    /// Last usable measured position (nm from the start of the measuring range).
    nm: Option<i64>,
    /// Cycles since `nm` was measured (velocity over a gap).
    age: u32,
    /// No usable pulse in the last cycle.
    missing: bool,
    /// Cam window state before polarity, for hysteresis (TMI); `None` before the first
    /// evaluation.
    inside: [Option<bool>; 4],
}

/// The CiA 406 application state (per-channel history the dictionary does not hold).
#[derive(Clone, Debug, Default)]
pub struct Encoder<P: Fixed = Unfixed> {
    /// The description the build fixes, if any ([`Fixed`]).
    _fixed: core::marker::PhantomData<P>,
    ch: [Channel; MAX_CHANNELS],
    /// Active fault conditions (F_* bits).
    faults: u16,
    /// EMCY codes this application raised for a condition and has not cleared (F_* bits by
    /// code).
    raised: u16,
    /// This application raised 0x5000 for reasons of its own (`hw_seen`) and has not cleared
    /// it. An MCU's monitors may raise the code too (`Node::set_error`): theirs is theirs to
    /// clear.
    hw_raised: bool,
    /// Active TMI system-data errors.
    sysdata: u16,
    /// 0x5000 reasons already announced (a new one while 0x5000 is active sends another EMCY):
    /// fault bits in the low half, system-data errors in the high half.
    hw_seen: u32,
    /// TMI lock-out: the EMCY that repeats on every refused start.
    lockout: Option<[u8; 5]>,
    /// The model reacts by going pre-operational at the end of this call.
    force_preop: bool,
    /// Stored data failed to load at the last power-on (TMI 0x1002 bit 14).
    storage_corrupt: bool,
    /// Warning bits injected (0x6505).
    warnings: u16,
    /// A sample arrived since the last reset (TMI 0x1002 bit 16).
    receiving: bool,
    /// TH 0x2901: min / max since start-up.
    temp_run: Option<(i8, i8)>,
    /// TH 0x2901: min / max over the operating life (loaded from the dictionary once).
    temp_life: Option<(i8, i8)>,
    temp_life_loaded: bool,
    /// Auto-stored values changed: the node should persist them.
    auto_dirty: bool,
    /// The offset each channel's last preset produced, on a model that keeps it inside the
    /// device ([`Switches::preset_offset_internal`], TMI): stored with 0x6010
    /// (the application parameters) and given back at reset node. `None`: no preset since the
    /// defaults, the position is the measured one.
    offsets: [Option<i32>; MAX_CHANNELS],
}

impl<P: Fixed> Encoder<P> {
    /// Whether a fault condition is active (hosts, tests).
    pub fn fault_active(&self, f: Fault) -> bool {
        match f {
            Fault::Transducer => self.faults & F_TRANSDUCER != 0,
            Fault::SupplyVoltage => self.faults & F_VOLTAGE != 0,
            Fault::OverTemperature => self.faults & F_TEMPERATURE != 0,
            Fault::CanErrorPassive => self.faults & F_PASSIVE != 0,
            Fault::Communication => self.faults & F_COMMUNICATION != 0,
            Fault::PdoLength => self.faults & F_PDO_LENGTH != 0,
            Fault::CanBusOff => self.faults & F_BUS_OFF != 0,
            Fault::CanOverrun => self.faults & F_OVERRUN != 0,
            Fault::CanBufferOverflow => self.faults & F_BUFFER != 0,
            Fault::TransmitOverflow => self.faults & F_TX_OVERFLOW != 0,
            Fault::CobIdCollision => false,
            Fault::Warning(bits) => self.warnings & bits != 0,
            Fault::SystemData(e) => self.sysdata & e.bit() != 0,
        }
    }

    /// TMI lock-out active (Operational refused until a power cycle).
    pub fn lockout(&self) -> bool {
        self.lockout.is_some()
    }

    /// Whether channel `ch` (0-based) had no usable position in the last cycle.
    pub fn missing(&self, ch: usize) -> bool {
        self.ch.get(ch).is_some_and(|c| c.missing)
    }

    /// TMI 0x1002 (§1.15): bits 16…3 from the conditions, bits 1–0 the NMT state.
    pub fn status(&self, nmt: NmtState) -> u32 {
        let mut v = match nmt {
            NmtState::Stopped => 0b11,
            NmtState::Operational => 0b10,
            NmtState::PreOperational => 0b01,
            _ => 0b00,
        };
        if self.receiving && self.sysdata == 0 {
            v |= 1 << 16;
        }
        if self.faults & F_EVENT_TIMER != 0 {
            v |= 1 << 15;
        }
        if self.storage_corrupt {
            v |= 1 << 14;
        }
        for e in SystemDataError::ALL {
            if self.sysdata & e.bit() != 0 {
                v |= e.status_bit();
            }
        }
        if self.faults & F_OVERRUN != 0 {
            v |= 1 << 7;
        }
        if self.faults & F_BUFFER != 0 {
            v |= 1 << 6;
        }
        if self.faults & F_PASSIVE != 0 {
            v |= 1 << 5;
        }
        if self.faults & F_BUS_OFF != 0 {
            v |= (1 << 4) | (1 << 3);
        }
        v
    }

    /// One channel's measurement: position, velocity, then the states derived from them.
    fn measure(&mut self, ch: usize, nm: Option<i64>, cx: &mut AppCtx<'_, Self>) {
        let sub = ch as u8 + 1;
        let tmi = Self::profile(cx.model).tmi_error_reactions;
        let c = &mut self.ch[ch];
        match nm {
            Some(nm) => {
                let v = match c.nm {
                    // `age` ≥ 1 whenever `nm` holds a measurement: the velocity spans the gap.
                    Some(prev) => {
                        let dt_us = c.age as i64 * cx.cfg.cycle_us.max(1) as i64;
                        velocity(nm - prev, dt_us, cx.od)
                    }
                    // First value after boot or reset: no velocity.
                    None => 0,
                };
                c.nm = Some(nm);
                c.age = 1;
                c.missing = false;
                set_live(cx, 0x6030, sub, v as i16 as u16 as u32, false);
                self.publish(ch, cx);
            }
            None => {
                c.missing = true;
                c.age = c.age.saturating_add(1);
                // D13: the position keeps its last value. Velocity (the position difference)
                // is then 0; TMI keeps its process values unchanged (§1.14).
                if !tmi {
                    set_live(cx, 0x6030, sub, 0, false);
                }
            }
        }
    }

    /// Position of channel `ch` from its last measurement, and its cam / work-area states.
    fn publish(&mut self, ch: usize, cx: &mut AppCtx<'_, Self>) {
        let Some(nm) = self.ch[ch].nm else {
            return;
        };
        let sub = ch as u8 + 1;
        let pos = self.base_steps(nm, cx) + self.offset(ch, cx);
        let pos = pos.clamp(i32::MIN as i64, i32::MAX as i64);
        set_live(cx, 0x6020, sub, pos as i32 as u32, false);
        self.cams(ch, pos, cx);
        self.work_area(ch, pos, nm, cx);
    }

    /// Position steps before the preset offset: quantised, direction applied.
    fn base_steps(&self, nm: i64, cx: &AppCtx<'_, Self>) -> i64 {
        let step = cx
            .od
            .value(0x6005, 1)
            .unwrap_or(cx.cfg.position_step_nm)
            .max(1) as i64;
        // Round to nearest: truncating would bias every reading by −step / 2 (issue 15).
        let steps = div::div_floor(nm + step / 2, step as u64);
        if cx.od.value(0x6000, 0).unwrap_or(0) & 1 != 0 {
            // Code sequence: counts decrease away from the head, from the end of the range.
            let max = div::div(u64::from(cx.cfg.stroke_mm) * 1_000_000, step as u64) as i64;
            max - steps
        } else {
            steps
        }
    }

    /// The offset added to channel `ch`'s steps: the one the last preset produced, in 0x650C/n
    /// or kept inside the device (TMI, see [`Switches::preset_offset_internal`]).
    fn offset(&self, ch: usize, cx: &AppCtx<'_, Self>) -> i64 {
        if Self::profile(cx.model).preset_offset_internal {
            return self.offsets[ch].unwrap_or(0) as i64;
        }
        cx.od.value(0x650C, ch as u8 + 1).unwrap_or(0) as i32 as i64
    }

    /// Writing a preset makes the current position read it (SPEC §10, CiA 406): the device
    /// keeps the offset between the two; E-Series clears the preset with 0xFFFFFFFF.
    fn preset(&mut self, ch: usize, raw: u32, cx: &mut AppCtx<'_, Self>) {
        let sub = ch as u8 + 1;
        let offset = if Self::profile(cx.model).preset_clear && raw == 0xFFFF_FFFF {
            cx.od.set_value(0x6010, sub, 0);
            0
        } else {
            // Without any measurement yet, the preset refers to the start of the range.
            let base = self.ch[ch].nm.map_or(0, |nm| self.base_steps(nm, cx));
            (raw as i32 as i64 - base).clamp(i32::MIN as i64, i32::MAX as i64)
        };
        if Self::profile(cx.model).preset_offset_internal {
            self.offsets[ch] = Some(offset as i32);
            return;
        }
        cx.od.set_value(0x650C, sub, offset as i32 as u32);
        if ch == 0 {
            cx.od.set_value(0x6509, 0, offset as i32 as u32);
        }
    }

    /// Cam states of one channel (D5).
    fn cams(&mut self, ch: usize, pos: i64, cx: &mut AppCtx<'_, Self>) {
        let sub = ch as u8 + 1;
        let enable = cx.od.value(0x6301, sub).unwrap_or(0);
        let polarity = cx.od.value(0x6302, sub).unwrap_or(0);
        let window = Self::profile(cx.model).window_cams;
        let mut state = 0u32;
        for k in 0..4u16 {
            let low = cx.od.value(0x6310 + k, sub).unwrap_or(0) as i32 as i64;
            let raw_on = if window {
                let high = cx.od.value(0x6320 + k, sub).unwrap_or(0) as i32 as i64;
                let h = cx.od.value(0x6330 + k, sub).unwrap_or(0) as u16 as i64;
                // Hysteresis moves each switch point by h in the direction of motion: a cam
                // that is off switches on h inside the window, one that is on switches off h
                // outside it.
                let inside = match self.ch[ch].inside[k as usize] {
                    Some(true) => pos >= low - h && pos <= high + h,
                    Some(false) => pos >= low + h && pos <= high - h,
                    None => pos >= low && pos <= high,
                };
                self.ch[ch].inside[k as usize] = Some(inside);
                inside
            } else {
                // TH / E-Series threshold cam: active at and beyond the threshold.
                pos >= low
            };
            let bit = 1u32 << k;
            if enable & bit != 0 && (raw_on ^ (polarity & bit != 0)) {
                state |= bit;
            }
        }
        if set_live(cx, 0x6300, sub, state, true) && Self::profile(cx.model).tmi_error_reactions {
            cx.emcy.event(code::TMI_CAM, [sub, state as u8, 0, 0, 0]);
        }
    }

    /// Work-area state of one channel: bit 2 below the low limit, bit 1 above the high limit,
    /// bit 0 outside the measuring range (TH / E-Series) or at or below the preset or at or
    /// past the sensor length (TMI §1.11.2 with its inclusive bounds).
    fn work_area(&mut self, ch: usize, pos: i64, nm: i64, cx: &mut AppCtx<'_, Self>) {
        let sub = ch as u8 + 1;
        let low = cx.od.value(0x6401, sub).unwrap_or(0) as i32 as i64;
        let high = cx.od.value(0x6402, sub).unwrap_or(0) as i32 as i64;
        let end = cx.cfg.stroke_mm as i64 * 1_000_000;
        let out = if Self::profile(cx.model).preset_offset_internal {
            // TMI 002 §1.11.2: "Position <= Preset Value or Position >= Sensor length", both in
            // the preset's coordinates as the limits are ("regard the preset"): the length in
            // position steps, shifted by the preset's offset.
            let step = cx
                .od
                .value(0x6005, 1)
                .unwrap_or(cx.cfg.position_step_nm)
                .max(1) as i64;
            let preset = cx.od.value(0x6010, sub).unwrap_or(0) as i32 as i64;
            let length = div::div(end as u64, step as u64) as i64 + self.offset(ch, cx);
            pos <= preset || pos >= length
        } else {
            nm < 0 || nm > end
        };
        let state = ((pos < low) as u32) << 2 | ((pos > high) as u32) << 1 | out as u32;
        if set_live(cx, 0x6400, sub, state, true) && Self::profile(cx.model).tmi_error_reactions {
            cx.emcy
                .event(code::TMI_WORK_AREA, [sub, 0, state as u8, 0, 0]);
        }
    }

    /// TH 0x2901: actual, since start-up and operating-life extremes.
    fn temperature(&mut self, t: i8, cx: &mut AppCtx<'_, Self>) {
        if cx.od.find(0x2901, 1).is_err() {
            return;
        }
        if !self.temp_life_loaded {
            self.temp_life_loaded = true;
            let max = cx.od.value(0x2901, 4).unwrap_or(0) as u8 as i8;
            let min = cx.od.value(0x2901, 5).unwrap_or(0) as u8 as i8;
            // Both 0 is what an empty store gives: nothing recorded yet.
            self.temp_life = (max != 0 || min != 0).then_some((min, max));
        }
        let run = self
            .temp_run
            .map_or((t, t), |(lo, hi)| (lo.min(t), hi.max(t)));
        self.temp_run = Some(run);
        let life = self
            .temp_life
            .map_or((t, t), |(lo, hi)| (lo.min(t), hi.max(t)));
        if self.temp_life != Some(life) {
            self.temp_life = Some(life);
            self.auto_dirty = true;
        }
        let b = |v: i8| v as u8 as u32;
        cx.od.set_value(0x2901, 1, b(t));
        cx.od.set_value(0x2901, 2, b(run.1));
        cx.od.set_value(0x2901, 3, b(run.0));
        cx.od.set_value(0x2901, 4, b(life.1));
        cx.od.set_value(0x2901, 5, b(life.0));
    }

    /// Brings alarms, warnings and EMCYs in line with the conditions.
    fn sync(&mut self, cx: &mut AppCtx<'_, Self>) {
        let tmi = Self::profile(cx.model).tmi_error_reactions;
        let position_error = self.faults & (F_MISSING | F_TRANSDUCER) != 0;
        cx.od.set_value(0x6503, 0, position_error as u32);
        cx.od.set_value(0x6505, 0, self.warnings as u32);
        let mirror = cx.od.value(0x6000, 0).unwrap_or(0);
        cx.od.set_value(0x6500, 0, mirror);
        if tmi {
            cx.od.set_value(0x1002, 0, self.status(cx.nmt));
        }

        // 0x5000: missing magnet, transducer error and (TMI) system-data errors share the
        // code; each new reason is announced, the code clears when none is left (D13).
        let mfr_sensor = if tmi { [1, 1, 0, 0, 0] } else { [0; 5] };
        let mut reasons = (self.faults & (F_MISSING | sensor_error_faults(tmi))) as u32;
        if tmi {
            reasons |= (self.sysdata as u32) << 16;
        }
        let fresh = reasons & !self.hw_seen;
        let active = cx.emcy.is_active(emcy::code::HARDWARE);
        if reasons != 0 {
            let mfr = first_mfr(fresh, mfr_sensor);
            if !active {
                // First reason, or still present after a reset communication forgot it.
                cx.emcy
                    .raise(emcy::code::HARDWARE, emcy::reg::MANUFACTURER, mfr);
                self.hw_raised = true;
            } else if fresh != 0 {
                cx.emcy.event(emcy::code::HARDWARE, mfr);
            }
        } else if core::mem::take(&mut self.hw_raised) && active {
            cx.emcy.clear(emcy::code::HARDWARE);
        }
        self.hw_seen = reasons;

        let comm = emcy::reg::COMMUNICATION;
        // TH / E-Series: bus-off is a communication error in 0x1001 while it lasts (Table 6;
        // its EMCY 0x8140 leaves at the recovery, see `inject`). Held again after a reset
        // forgot it.
        if !tmi && self.faults & F_BUS_OFF != 0 && !cx.emcy.is_active(emcy::code::BUS_OFF_RECOVERED)
        {
            cx.emcy.hold(emcy::code::BUS_OFF_RECOVERED, comm);
        }
        let conditions: [(u16, u16, u8, [u8; 5]); 9] = [
            (
                F_VOLTAGE,
                emcy::code::MAIN_VOLTAGE,
                emcy::reg::VOLTAGE,
                [0; 5],
            ),
            (
                F_TEMPERATURE,
                emcy::code::TEMPERATURE,
                emcy::reg::TEMPERATURE,
                [0; 5],
            ),
            (F_PASSIVE, emcy::code::ERROR_PASSIVE, comm, [0; 5]),
            (F_COMMUNICATION, emcy::code::COMMUNICATION, comm, [0; 5]),
            (F_OVERRUN, emcy::code::CAN_OVERRUN, comm, [1, 0, 0, 0, 0]),
            (F_BUFFER, emcy::code::CAN_OVERRUN, comm, [2, 0, 0, 0, 0]),
            (
                F_TX_OVERFLOW,
                emcy::code::CAN_OVERRUN,
                comm,
                [1, 0, 0, 0, 0],
            ),
            (F_EVENT_TIMER, emcy::code::SOFTWARE, 0, [1, 0, 0, 0, 0]),
            (F_PDO_LENGTH, emcy::code::PDO_LENGTH, comm, [0; 5]),
        ];
        for (flag, code, reg, mfr) in conditions {
            if tmi && flag & TMI_NO_CODE != 0 {
                // Not in the TMI's EMCY table (see `sensor_error_faults`).
                continue;
            }
            let mfr = if tmi { mfr } else { [0; 5] };
            let want = self.faults & flag != 0;
            let have = self.raised & flag != 0;
            if want && (!have || !cx.emcy.is_active(code)) {
                if cx.emcy.is_active(code) && !have {
                    // Same code already active for another reason (overrun and buffer
                    // overflow share 0x8110): announce without a second raise.
                    cx.emcy.event(code, mfr);
                } else {
                    cx.emcy.raise(code, reg, mfr);
                }
                self.raised |= flag;
            } else if !want && have {
                self.raised &= !flag;
                let shared = conditions
                    .iter()
                    .any(|&(f, c, _, _)| f != flag && c == code && self.raised & f != 0);
                if !shared {
                    cx.emcy.clear(code);
                }
            }
        }
    }
}

impl<P: Fixed> Application for Encoder<P> {
    type Sample = Sample;
    type Fault = Fault;
    type Config = DeviceConfig;
    type Profile = Switches;
    const FIXED: Option<&'static Model> = P::MODEL;

    fn power_on(&mut self) {
        *self = Encoder::default();
    }

    /// Forgets runtime state (reset node). What only a power cycle clears stays: the TMI
    /// lock-out, the storage-corruption flag, the temperature extremes since start-up, and the
    /// injected fault conditions (the hardware is still faulty after a reset).
    fn reset(&mut self) {
        let keep = Encoder {
            faults: self.faults & !F_MISSING & !F_EVENT_TIMER,
            sysdata: self.sysdata,
            lockout: self.lockout,
            storage_corrupt: self.storage_corrupt,
            warnings: self.warnings,
            temp_run: self.temp_run,
            temp_life: self.temp_life,
            temp_life_loaded: self.temp_life_loaded,
            ..Encoder::default()
        };
        *self = keep;
    }

    /// Runs one measurement cycle. Returns true when the model's reaction forces the node back
    /// to pre-operational. Out of line, so that its frame is gone before the node stores what
    /// the cycle changed (0x2901): on an MCU that store is the deepest stack.
    #[inline(never)]
    fn cycle(&mut self, s: &Sample, cx: &mut AppCtx<'_, Self>) -> bool {
        let tmi = Self::profile(cx.model).tmi_error_reactions;
        let n = (cx.cfg.channels as usize).clamp(1, MAX_CHANNELS);
        self.receiving = true;
        // TMI sensor error: "the current process values stay in the object directory; the cam
        // and work area states stay unchanged" (§1.14).
        let frozen = tmi && self.faults & sensor_error_faults(tmi) != 0;
        // TH / E-Series: a transducer error leaves no usable position on any channel.
        let blind = !tmi && self.faults & F_TRANSDUCER != 0;
        let mut missing = false;
        if !frozen {
            for ch in 0..n {
                let nm = if blind { None } else { s.positions_nm[ch] };
                self.measure(ch, nm, cx);
                missing |= self.ch[ch].missing;
            }
            // A blind transducer's lost pulses are that error, not a second event: its EMCY
            // goes out once (0x5000 is announced per event).
            set_flag(&mut self.faults, F_MISSING, missing && !blind);
        }
        self.temperature(s.temperature_c, cx);
        if tmi {
            let short = event_timer_insufficient(cx);
            let overflow = self.faults & F_TX_OVERFLOW != 0;
            set_flag(&mut self.faults, F_EVENT_TIMER, short || overflow);
        }
        self.sync(cx);
        core::mem::take(&mut self.force_preop)
    }

    /// Injects (`active`) or removes a fault condition. Returns true when the model's
    /// reaction forces the node back to pre-operational.
    fn inject(&mut self, f: Fault, active: bool, cx: &mut AppCtx<'_, Self>) -> bool {
        let tmi = Self::profile(cx.model).tmi_error_reactions;
        match f {
            Fault::Transducer => set_flag(&mut self.faults, F_TRANSDUCER, active),
            Fault::SupplyVoltage => set_flag(&mut self.faults, F_VOLTAGE, active),
            Fault::OverTemperature => set_flag(&mut self.faults, F_TEMPERATURE, active),
            Fault::CanErrorPassive => set_flag(&mut self.faults, F_PASSIVE, active),
            Fault::Communication => set_flag(&mut self.faults, F_COMMUNICATION, active),
            // Not in the TMI's table: no condition there.
            Fault::PdoLength => set_flag(&mut self.faults, F_PDO_LENGTH, active && !tmi),
            Fault::CanBusOff => {
                let was = self.faults & F_BUS_OFF != 0;
                set_flag(&mut self.faults, F_BUS_OFF, active);
                if was && !active {
                    // Recovered (TH/E Table 5, TMI 0x8140 0/0/0). TH / E-Series: the EMCY
                    // carries the communication error that stood during bus-off (Table 6:
                    // 0x11, held by `sync`), then its clearing sends the error reset. TMI: a
                    // one-shot event (its table has 0x0000 only for the sensor error).
                    cx.emcy.event(emcy::code::BUS_OFF_RECOVERED, [0; 5]);
                    if cx.emcy.is_active(emcy::code::BUS_OFF_RECOVERED) {
                        cx.emcy.clear(emcy::code::BUS_OFF_RECOVERED);
                    } else if Self::features(cx.model).emcy_on_register_change {
                        cx.emcy.reset_message();
                    }
                }
            }
            Fault::CanOverrun => set_flag(&mut self.faults, F_OVERRUN, active),
            Fault::CanBufferOverflow => set_flag(&mut self.faults, F_BUFFER, active),
            Fault::TransmitOverflow => {
                set_flag(&mut self.faults, F_TX_OVERFLOW, active);
                if tmi {
                    let short = event_timer_insufficient(cx);
                    set_flag(&mut self.faults, F_EVENT_TIMER, short || active);
                }
            }
            Fault::CobIdCollision => {
                if active && !tmi {
                    // A communication error for the moment of the collision (Table 6: 0x11 in
                    // the EMCY and in 0x1001), over with the frame: the error reset follows.
                    cx.emcy
                        .raise(emcy::code::COB_COLLISION, emcy::reg::COMMUNICATION, [0; 5]);
                    cx.emcy.clear(emcy::code::COB_COLLISION);
                }
            }
            Fault::Warning(bits) => {
                let supported = cx.od.value(0x6506, 0).unwrap_or(0) as u16;
                if active {
                    self.warnings |= bits & supported;
                } else {
                    self.warnings &= !bits;
                }
            }
            Fault::SystemData(e) if tmi => {
                let was = self.sysdata & e.bit() != 0;
                set_flag(&mut self.sysdata, e.bit(), active);
                if active && !was {
                    if e.locks_out() {
                        // Lock-out L: pre-operational until a power cycle; the EMCY repeats
                        // on every refused start.
                        self.lockout = Some(e.mfr());
                    }
                    self.force_preop = true;
                }
            }
            Fault::SystemData(_) => set_flag(&mut self.faults, F_TRANSDUCER, active),
        }
        self.sync(cx);
        core::mem::take(&mut self.force_preop)
    }

    /// The rule of application hook `h` for a write of `raw` to `sub`.
    fn validate(&self, h: u8, sub: u8, raw: u32, cx: &AppView<'_, Self>) -> Result<(), Abort> {
        match h {
            // D2: only the code-sequence bit.
            hook::CODE_SEQUENCE if raw & !1 != 0 => Err(Abort::InvalidValue),
            // R31: whole µm, not below the variant's minimum step.
            hook::MEASURING_STEP if !raw.is_multiple_of(1000) => Err(Abort::InvalidValue),
            // The unit's bounds (`limits`, what its EDS says), looked up only for the hooks
            // that have them.
            hook::MEASURING_STEP | hook::CAM_SWITCH => match limits(h, cx.cfg) {
                Some((lo, _)) if h == hook::MEASURING_STEP && raw < lo => Err(Abort::ValueTooLow),
                // Four cams per channel: bits 4…7 name no cam.
                Some((_, hi)) if h == hook::CAM_SWITCH && sub >= 1 && raw > hi => {
                    Err(Abort::InvalidValue)
                }
                _ => Ok(()),
            },
            _ => Ok(()),
        }
    }

    /// The side effects of application hook `h` once `raw` was written to `sub`.
    fn written(&mut self, h: u8, sub: u8, raw: u32, cx: &mut AppCtx<'_, Self>) {
        let n = (cx.cfg.channels as usize).clamp(1, MAX_CHANNELS);
        match h {
            hook::PRESET => {
                let ch = (sub as usize).wrapping_sub(1);
                if ch < MAX_CHANNELS {
                    self.preset(ch, raw, cx);
                    self.publish(ch, cx);
                }
            }
            hook::CODE_SEQUENCE => {
                cx.od.set_value(0x6500, 0, raw);
                for ch in 0..n {
                    self.publish(ch, cx);
                }
            }
            hook::MEASURING_STEP => {
                // Offsets stay in position units (the manual says nothing about rescaling a
                // preset when the step changes): write the preset again after changing it.
                for ch in 0..n {
                    self.publish(ch, cx);
                }
            }
            hook::CYCLIC_TIMER => {
                // D12: one value with TPDO1's event timer.
                cx.od.set_value(0x1800, 5, raw);
                cx.pdo.reconfigure(0, cx.od, cx.now);
            }
            hook::CAM_SWITCH | hook::CAM_LIMIT | hook::WORK_AREA_LIMIT => {
                let ch = (sub as usize).wrapping_sub(1);
                if ch < n {
                    self.publish(ch, cx);
                }
            }
            _ => {}
        }
        self.sync(cx);
    }

    /// A communication parameter `sub` of TPDO `n` changed: 0x6200 is one value with TPDO1's
    /// event timer (D12).
    fn tpdo_comm_written(&mut self, n: usize, sub: u8, raw: u32, cx: &mut AppCtx<'_, Self>) {
        if n == 0 && sub == 5 {
            cx.od.set_value(0x6200, 0, raw);
        }
    }

    /// Values derived from other objects, brought up to date just before an SDO read of an
    /// object with application hook `h` (they must be right even when no measurement cycle ran
    /// since the change): 0x6500 mirrors 0x6000 (D2), 0x6509 mirrors 0x650C/1, TMI 0x1002
    /// carries the NMT state.
    fn refresh(&self, h: u8, od: &mut Dictionary, nmt: NmtState) {
        match h {
            hook::OPERATING_STATUS => {
                let v = od.value(0x6000, 0).unwrap_or(0);
                od.set_value(0x6500, 0, v);
            }
            hook::OFFSET => {
                let v = od.value(0x650C, 1).unwrap_or(0);
                od.set_value(0x6509, 0, v);
            }
            hook::MANUFACTURER_STATUS => {
                od.set_value(0x1002, 0, self.status(nmt));
            }
            _ => {}
        }
    }

    /// The preset offsets a model without an offset object keeps (TMI): stored with 0x6010.
    fn stored_value(&self, k: usize) -> Option<u32> {
        self.offsets.get(k).copied().flatten().map(|o| o as u32)
    }

    /// A stored preset offset back at reset node.
    fn load_stored(&mut self, k: usize, v: u32) {
        if let Some(o) = self.offsets.get_mut(k) {
            *o = Some(v as i32);
        }
    }

    /// Whether values of the automatically stored group changed since the last call (the node
    /// then persists them; TH 0x2901 operating-life extremes, D19).
    fn take_auto_dirty(&mut self) -> bool {
        core::mem::take(&mut self.auto_dirty)
    }

    /// The TMI lock-out (§1.14): the start is refused and the lock-out EMCY repeats.
    fn refuses_start(&self, emcy: &mut Emcy) -> bool {
        if let Some(mfr) = self.lockout {
            emcy.event(emcy::code::HARDWARE, mfr);
            return true;
        }
        false
    }

    /// The TMI reports corrupt storage itself (0x1002 bit 14); the others leave it to the
    /// generic EMCY 0x6300.
    fn storage_corrupt(&mut self, cx: &mut AppCtx<'_, Self>) -> bool {
        self.storage_corrupt = true;
        Self::profile(cx.model).tmi_error_reactions
    }
}

/// Conditions the TMI's EMCY table (002 §1.14) has no code for. Supply voltage and temperature
/// reach its electronics as an internal error of the sensing element: the TMI reports them as
/// its "Sensor Error" (0x5000 1/1/0, with that error's reaction); a generic communication fault
/// it does not report at all (DECISIONS.md). A transmit overflow it reports as its 0x6000 (`F_EVENT_TIMER`), not as 0x8110.
const TMI_NO_CODE: u16 = F_VOLTAGE | F_TEMPERATURE | F_COMMUNICATION | F_TX_OVERFLOW | F_PDO_LENGTH;

/// The conditions that make the model's sensor error (0x5000).
const fn sensor_error_faults(tmi: bool) -> u16 {
    if tmi {
        F_TRANSDUCER | F_VOLTAGE | F_TEMPERATURE
    } else {
        F_TRANSDUCER
    }
}

fn set_flag(bits: &mut u16, flag: u16, on: bool) {
    if on {
        *bits |= flag;
    } else {
        *bits &= !flag;
    }
}

/// The manufacturer bytes announcing the first of the `fresh` 0x5000 reasons.
fn first_mfr(fresh: u32, sensor: [u8; 5]) -> [u8; 5] {
    for e in SystemDataError::ALL {
        if (fresh >> 16) as u16 & e.bit() != 0 {
            return e.mfr();
        }
    }
    sensor
}

/// Writes a live value; tells the TPDOs when it changed (`event` for cam / work-area states,
/// which trigger event-driven TPDOs). Returns whether it changed.
fn set_live<A: Application + ?Sized>(
    cx: &mut AppCtx<'_, A>,
    index: u16,
    sub: u8,
    raw: u32,
    event: bool,
) -> bool {
    let Ok(slot) = cx.od.find(index, sub) else {
        return false;
    };
    if cx.od.get(slot) == raw {
        return false;
    }
    cx.od.set(slot, raw);
    cx.pdo.value_changed(slot, event);
    true
}

/// Velocity in 0x6005/2 units (of 0.01 mm/s), rounded half away from zero, positive away
/// from the head before the code sequence (D18), saturated to INTEGER16.
fn velocity(dnm: i64, dt_us: i64, od: &Dictionary) -> i64 {
    let vstep = od.value(0x6005, 2).unwrap_or(100).max(1) as i64;
    let reversed = od.value(0x6000, 0).unwrap_or(0) & 1 != 0;
    velocity_units(dnm, dt_us, vstep, reversed)
}

/// `dnm` nm in `dt_us` µs in units of `vstep` × 0.01 mm/s, rounded half away from zero,
/// negated when `reversed`, saturated to INTEGER16.
///
/// 1 nm/µs = 1 mm/s = 100 × 0.01 mm/s. In 64 bits, not 128 (a 128-bit division would link
/// compiler-builtins' general one into a firmware; its size in docs/FIRMWARE.md): a product past i64 saturates, and only a move of some 10^17 nm in one interval
/// could make that change a result the clamp lets through.
fn velocity_units(dnm: i64, dt_us: i64, vstep: i64, reversed: bool) -> i64 {
    let num = dnm.saturating_mul(100);
    let den = dt_us.saturating_mul(vstep).max(1) as u64;
    let (q, r) = div::div_rem(num.unsigned_abs(), den);
    // Half away from zero: one more when the remainder is at least half the divisor.
    let mag = (q + (r >= den - r) as u64).min(1 << 15) as i64;
    let v = mag * num.signum();
    let v = if reversed { -v } else { v };
    v.clamp(i16::MIN as i64, i16::MAX as i64)
}

/// TMI R27: TPDO1's event timer is shorter than one worst-case frame at the active bit rate.
fn event_timer_insufficient<A: Application + ?Sized>(cx: &AppCtx<'_, A>) -> bool {
    if cx.bitrate_kbps == 0 {
        return false;
    }
    let od = &*cx.od;
    let cob = od.value(0x1800, 1).unwrap_or(0x8000_0000);
    let ttype = od.value(0x1800, 2).unwrap_or(0);
    let et_ms = od.value(0x1800, 5).unwrap_or(0);
    if cob & 0x8000_0000 != 0 || ttype < 254 || et_ms == 0 {
        return false;
    }
    let count = od.value(0x1A00, 0).unwrap_or(0);
    let bytes: u32 = (1..=count.min(8))
        .map(|k| (od.value(0x1A00, k as u8).unwrap_or(0) & 0xFF) / 8)
        .sum::<u32>()
        .min(8);
    // 11-bit data frame: 47 bits of frame plus data, plus worst-case stuff bits on the 34 + 8n
    // stuffable bits (the manuals' "103…126 bits" for 7 bytes).
    let bits = 47 + 8 * bytes + (34 + 8 * bytes - 1) / 4;
    // Small numbers: 32 bits (µs of one frame at ≥ 1 kbit/s).
    let frame_us = bits * 1000 / u32::from(cx.bitrate_kbps);
    u64::from(et_ms) * 1000 < u64::from(frame_us)
}

#[cfg(test)]
mod tests {
    use super::velocity_units;
    use proptest::prelude::*;

    /// The exact quotient, rounded half away from zero, in 128 bits.
    fn reference(dnm: i64, dt_us: i64, vstep: i64, reversed: bool) -> i64 {
        let (num, den) = (dnm as i128 * 100, dt_us as i128 * vstep as i128);
        let v = (2 * num + num.signum() * den) / (2 * den);
        let v = if reversed { -v } else { v };
        v.clamp(i16::MIN as i128, i16::MAX as i128) as i64
    }

    #[test]
    fn halves_round_away_from_zero_and_the_range_saturates() {
        let v = |dnm, dt_us, vstep| velocity_units(dnm, dt_us, vstep, false);
        // 1 nm/µs = 100 units of 0.01 mm/s; 0.5 unit rounds away from zero.
        assert_eq!(v(1, 1, 1), 100);
        assert_eq!(v(1, 200, 1), 1);
        assert_eq!(v(-1, 200, 1), -1);
        assert_eq!(v(1, 201, 1), 0);
        assert_eq!(v(3, 200, 1), 2);
        assert_eq!(v(-3, 200, 1), -2);
        assert_eq!(v(0, 1, 1), 0);
        assert_eq!(v(i64::MAX, 1, 1), 32767);
        assert_eq!(v(i64::MIN, 1, 1), -32768);
        assert_eq!(v(1, i64::MAX, i64::MAX), 0);
        // Reversed (code sequence): the sign flips before the clamp, so the most negative
        // move saturates at +32767 rather than wrapping.
        assert_eq!(velocity_units(i64::MIN, 1, 1, true), 32767);
        assert_eq!(velocity_units(i64::MAX, 1, 1, true), -32768);
        assert_eq!(velocity_units(3, 200, 1, true), -2);
    }

    proptest! {
        /// Equal to the 128-bit quotient for every move, interval and step a sensor can see.
        #[test]
        fn equals_the_128_bit_quotient(
            dnm in -1_000_000_000_000_000i64..1_000_000_000_000_000,
            dt_us in 1i64..1_000_000_000_000,
            vstep in 1i64..=u32::MAX as i64,
            reversed: bool,
        ) {
            prop_assert_eq!(
                velocity_units(dnm, dt_us, vstep, reversed),
                reference(dnm, dt_us, vstep, reversed)
            );
        }

        /// Small moves over short intervals, where the rounding decides.
        #[test]
        fn equals_the_128_bit_quotient_near_halves(
            dnm in -100_000i64..100_000,
            dt_us in 1i64..10_000,
            vstep in 1i64..1_000,
            reversed: bool,
        ) {
            prop_assert_eq!(
                velocity_units(dnm, dt_us, vstep, reversed),
                reference(dnm, dt_us, vstep, reversed)
            );
        }
    }
}
