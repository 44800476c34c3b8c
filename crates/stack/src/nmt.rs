//! NMT slave (CiA 301 §7.2.8): states, commands and what each state lets through.

/// NMT states of the slave, with the byte heartbeat / guarding replies carry (the
/// discriminant, so that [`NmtState::code`] is no lookup).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum NmtState {
    /// Initialising (only seen in the boot-up frame, byte 0x00).
    Initialising = 0x00,
    /// Pre-operational: SDO, EMCY, SYNC and error control active; no PDOs.
    PreOperational = 0x7F,
    /// Operational: everything.
    Operational = 0x05,
    /// Stopped: only NMT and error control.
    Stopped = 0x04,
}

impl NmtState {
    /// The state byte of heartbeat and node-guarding frames.
    pub const fn code(self) -> u8 {
        self as u8
    }
    /// SDO, EMCY and SYNC are served.
    pub const fn sdo_allowed(self) -> bool {
        // Pre-operational (0x7F) and operational (0x05) are the states with odd codes.
        self as u8 & 1 != 0
    }
}

pub use crate::wire::nmt::{NmtCommand, NmtFrame, ALL_NODES};

impl NmtState {
    /// The state of a heartbeat / guarding state byte (bit 7, the guarding toggle, stripped),
    /// `None` for a byte that names no state.
    pub const fn from_code(b: u8) -> Option<NmtState> {
        Some(match b & 0x7F {
            0x00 => NmtState::Initialising,
            0x7F => NmtState::PreOperational,
            0x05 => NmtState::Operational,
            0x04 => NmtState::Stopped,
            _ => return None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The state bytes of CiA 301 §7.2.8.3.2.1 (heartbeat / guarding), and SDO, EMCY and SYNC
    /// served in pre-operational and operational only.
    #[test]
    fn state_codes_and_what_each_state_serves() {
        let all = [
            (NmtState::Initialising, 0x00, false),
            (NmtState::PreOperational, 0x7F, true),
            (NmtState::Operational, 0x05, true),
            (NmtState::Stopped, 0x04, false),
        ];
        for (s, code, sdo) in all {
            assert_eq!((s.code(), s.sdo_allowed()), (code, sdo), "{s:?}");
            assert_eq!(NmtState::from_code(code), Some(s));
            assert_eq!(NmtState::from_code(code | 0x80), Some(s), "guarding toggle");
        }
        assert_eq!(NmtState::from_code(0x06), None);
    }

    /// Each command's specifier byte, and `parse` reads it back.
    #[test]
    fn command_codes_round_trip() {
        let all = [
            (NmtCommand::Start, 0x01),
            (NmtCommand::Stop, 0x02),
            (NmtCommand::EnterPreOperational, 0x80),
            (NmtCommand::ResetNode, 0x81),
            (NmtCommand::ResetCommunication, 0x82),
        ];
        for (c, code) in all {
            assert_eq!(c.code(), code, "{c:?}");
            assert_eq!(NmtCommand::parse(&[code, 0], 5), Some(c));
        }
    }

    #[test]
    fn nmt_table_3_commands() {
        // Manual (TH Table 3 / E Table 2): command byte, then 0 = all or the node-id.
        assert_eq!(
            NmtCommand::parse(&[0x01, 0x7F], 0x7F),
            Some(NmtCommand::Start)
        );
        assert_eq!(
            NmtCommand::parse(&[0x02, 0x00], 0x7F),
            Some(NmtCommand::Stop)
        );
        assert_eq!(
            NmtCommand::parse(&[0x80, 0x7F], 0x7F),
            Some(NmtCommand::EnterPreOperational)
        );
        assert_eq!(
            NmtCommand::parse(&[0x81, 0x00], 0x7F),
            Some(NmtCommand::ResetNode)
        );
        assert_eq!(
            NmtCommand::parse(&[0x82, 0x7F], 0x7F),
            Some(NmtCommand::ResetCommunication)
        );
        assert_eq!(NmtCommand::parse(&[0x01, 0x05], 0x7F), None, "other node");
        assert_eq!(NmtCommand::parse(&[0x01], 0x7F), None, "short");
        assert_eq!(NmtCommand::parse(&[0x01, 0x7F, 0], 0x7F), None, "long");
        assert_eq!(NmtCommand::parse(&[0x03, 0x7F], 0x7F), None, "unknown");
    }
}
