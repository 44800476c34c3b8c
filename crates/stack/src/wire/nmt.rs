//! NMT node-control frames (CiA 301 §7.2.8.3.1): COB-ID 0x000, exactly 2 bytes, the command
//! specifier and the node-id addressed (0 = all nodes). [`NmtFrame`] parses and emits them for
//! the master and the slave alike.

/// NMT node-control commands, with their command specifiers as discriminants.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum NmtCommand {
    /// 0x01 start remote node.
    Start = 0x01,
    /// 0x02 stop remote node.
    Stop = 0x02,
    /// 0x80 enter pre-operational.
    EnterPreOperational = 0x80,
    /// 0x81 reset node (application).
    ResetNode = 0x81,
    /// 0x82 reset communication.
    ResetCommunication = 0x82,
}

impl NmtCommand {
    /// The five commands.
    pub const ALL: [NmtCommand; 5] = [
        NmtCommand::Start,
        NmtCommand::Stop,
        NmtCommand::EnterPreOperational,
        NmtCommand::ResetNode,
        NmtCommand::ResetCommunication,
    ];

    /// The command specifier byte.
    pub const fn code(self) -> u8 {
        self as u8
    }

    /// The command of specifier `b`, `None` for an unknown one.
    pub const fn from_code(b: u8) -> Option<NmtCommand> {
        Some(match b {
            0x01 => NmtCommand::Start,
            0x02 => NmtCommand::Stop,
            0x80 => NmtCommand::EnterPreOperational,
            0x81 => NmtCommand::ResetNode,
            0x82 => NmtCommand::ResetCommunication,
            _ => return None,
        })
    }

    /// Decodes an NMT frame's data for the node `node_id`. Returns `None` for frames that are
    /// not for this node, have the wrong length (CiA 301: exactly 2 bytes) or an unknown
    /// command.
    pub fn parse(data: &[u8], node_id: u8) -> Option<NmtCommand> {
        if data.len() != 2 || (data[1] != 0 && data[1] != node_id) {
            return None;
        }
        // Its own match rather than `from_code`'s: the smaller firmware (docs/BENCHMARKS.md "One
        // wire vocabulary"); `from_code_answers_as_parse` keeps the two alike.
        Some(match data[0] {
            0x01 => NmtCommand::Start,
            0x02 => NmtCommand::Stop,
            0x80 => NmtCommand::EnterPreOperational,
            0x81 => NmtCommand::ResetNode,
            0x82 => NmtCommand::ResetCommunication,
            _ => return None,
        })
    }
}

/// The node-id of an NMT frame addressed to every node.
pub const ALL_NODES: u8 = 0;

/// One NMT node-control frame: a command and the node it addresses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NmtFrame {
    /// The command.
    pub command: NmtCommand,
    /// The node-id addressed, [`ALL_NODES`] for all.
    pub node: u8,
}

impl NmtFrame {
    /// Reads an NMT frame's data: `None` unless it is exactly 2 bytes with a known command.
    pub const fn parse(data: &[u8]) -> Option<NmtFrame> {
        let [c, node] = *data else { return None };
        match NmtCommand::from_code(c) {
            Some(command) => Some(NmtFrame { command, node }),
            None => None,
        }
    }

    /// The frame's 2 bytes.
    pub const fn emit(&self) -> [u8; 2] {
        [self.command.code(), self.node]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Emit then parse gives the frame back, for every command and node-id.
        #[test]
        fn round_trip(i in 0usize..5, node in any::<u8>()) {
            let f = NmtFrame { command: NmtCommand::ALL[i], node };
            prop_assert_eq!(NmtFrame::parse(&f.emit()), Some(f));
        }

        /// A 2-byte frame parses exactly when its specifier is a command, and emits its bytes.
        #[test]
        fn bytes_survive(d in any::<[u8; 2]>()) {
            match NmtFrame::parse(&d) {
                Some(f) => prop_assert_eq!(f.emit(), d),
                None => prop_assert_eq!(NmtCommand::from_code(d[0]), None),
            }
        }
    }

    /// The slave's `parse` reads every specifier byte as `from_code` does.
    #[test]
    fn from_code_answers_as_parse() {
        for b in 0..=255u8 {
            assert_eq!(
                NmtCommand::parse(&[b, 0], 5),
                NmtCommand::from_code(b),
                "{b:#04x}"
            );
        }
    }

    /// The manual's NMT table (TH Table 3 / E Table 2): command byte, then 0 = all or the
    /// node-id; any other length is no NMT frame.
    #[test]
    fn manual_table_byte_exact() {
        let start = NmtFrame {
            command: NmtCommand::Start,
            node: 0x7F,
        };
        assert_eq!(start.emit(), [0x01, 0x7F]);
        let reset = NmtFrame {
            command: NmtCommand::ResetCommunication,
            node: ALL_NODES,
        };
        assert_eq!(reset.emit(), [0x82, 0x00]);
        assert_eq!(NmtFrame::parse(&[0x01]), None);
        assert_eq!(NmtFrame::parse(&[0x01, 0x7F, 0]), None);
        assert_eq!(NmtFrame::parse(&[0x03, 0x7F]), None);
    }
}
