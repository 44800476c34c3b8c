//! Error behaviour (CiA 301 §7.5.2.32, object 0x1029): the NMT state a device changes to on an
//! error of a class, sub 1 the communication error class.
//!
//! Communication errors (CiA 301; vendors' manuals list the same three): bus-off, a life
//! guarding event and a heartbeat consumer event, each on its occurrence (not on its end;
//! bus-off through `Node::set_bus_off`). The
//! further sub-indices an EDS may declare (device-profile or manufacturer-specific classes) are
//! values of the same range with no error feeding them in this stack (D25 in
//! docs/DECISIONS.md). A device without 0x1029 keeps what it did before (the sensors: life
//! guarding stops their PDOs, D11, and nothing more).

use crate::nmt::NmtState;
use crate::od::Abort;

/// The error behaviour object.
pub const INDEX: u16 = 0x1029;

/// "Change to pre-operational (only if currently in operational)".
pub const PRE_OPERATIONAL: u32 = 0;
/// "No change of the NMT state".
pub const NO_CHANGE: u32 = 1;
/// "Change to stopped".
pub const STOPPED: u32 = 2;

/// The rule of a value of any sub-index 1…: 0, 1 or 2. CiA 301 reserves 0x03–0x7F and leaves
/// 0x80–0xFF to the manufacturer; this stack defines none of the latter, so both are refused
/// with 0x06090030 (value range exceeded) rather than stored and ignored.
pub fn value_allowed(raw: u32) -> Result<(), Abort> {
    if raw > STOPPED {
        return Err(Abort::InvalidValue);
    }
    Ok(())
}

/// The state a node in `state` changes to on an error of a class whose 0x1029 value is `v`
/// (`None`: the device has no such sub-index), `None` for no change.
pub fn reaction(v: Option<u32>, state: NmtState) -> Option<NmtState> {
    match (v?, state) {
        (PRE_OPERATIONAL, NmtState::Operational) => Some(NmtState::PreOperational),
        (STOPPED, NmtState::PreOperational | NmtState::Operational) => Some(NmtState::Stopped),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const STATES: [NmtState; 4] = [
        NmtState::Initialising,
        NmtState::PreOperational,
        NmtState::Operational,
        NmtState::Stopped,
    ];

    /// CiA 301 §7.5.2.32, every value over every state: 0 leaves Operational only, 1 never
    /// changes, 2 stops a running node; without the object nothing changes.
    #[test]
    fn cia301_7_5_2_32_each_value_in_each_state() {
        for s in STATES {
            let runs = matches!(s, NmtState::PreOperational | NmtState::Operational);
            let pre = (s == NmtState::Operational).then_some(NmtState::PreOperational);
            assert_eq!(reaction(Some(0), s), pre, "0 from {s:?}");
            assert_eq!(reaction(Some(1), s), None, "1 from {s:?}");
            let stop = runs.then_some(NmtState::Stopped);
            assert_eq!(reaction(Some(2), s), stop, "2 from {s:?}");
            assert_eq!(reaction(None, s), None, "no object");
        }
    }

    #[test]
    fn cia301_values_0_1_2_only() {
        for v in 0..=2 {
            assert_eq!(value_allowed(v), Ok(()));
        }
        for v in [3, 0x7F, 0x80, 0xFF] {
            assert_eq!(value_allowed(v), Err(Abort::InvalidValue), "{v}");
        }
    }
}
