//! LSS slave (CiA 305): commissioning node-id and bit rate on 0x7E5 / 0x7E4.

use crate::node::Device;
use crate::storage::Storage;
use crate::wire::Instant;

/// LSS slave state (waiting / configuration) beside the NMT state machine.
#[derive(Clone, Debug, Default)]
pub struct LssSlave {
    configuration: bool,
}

impl LssSlave {
    /// Whether the slave is in LSS configuration state.
    pub fn in_configuration(&self) -> bool {
        self.configuration
    }

    /// Enters configuration state (a node without a valid node-id lives there).
    pub fn force_configuration(&mut self) {
        self.configuration = true;
    }

    /// Handles one frame on 0x7E5; returns the response payload for 0x7E4, if any.
    pub fn handle<S: Storage>(
        &mut self,
        data: &[u8],
        _now: Instant,
        _dev: &mut Device<S>,
    ) -> Option<[u8; 8]> {
        if data.len() != 8 {
            return None;
        }
        if data[0] == 0x04 {
            self.configuration = data[1] == 1;
        }
        None
    }

    /// Deadline of a pending bit-rate switch.
    pub fn poll_timeout(&self) -> Option<Instant> {
        None
    }

    /// Advances a pending bit-rate switch.
    pub fn handle_timeout<S: Storage>(&mut self, _now: Instant, _dev: &mut Device<S>) {}
}
