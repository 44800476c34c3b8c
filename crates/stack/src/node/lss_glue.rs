//! LSS glue: what the LSS slave asks of the device, and the object copies of node-id and bit rate.

use super::*;

/// The bit rate in kbit/s (0 = autobaud) that an object copy of it holds (TMI 0x2001: kbit/s,
/// 0xFFFF = autobaud, D16).
pub(super) fn kbps_of_object(raw: u32) -> u16 {
    if raw == 0xFFFF {
        0
    } else {
        raw as u16
    }
}

/// [`kbps_of_object`] the other way round.
pub(super) fn object_of_kbps(kbps: u16) -> u32 {
    if kbps == 0 {
        0xFFFF
    } else {
        kbps as u32
    }
}

impl<A: Application, S: Storage> Node<A, S> {
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))] // one copy for both callers
    pub(super) fn after_lss(&mut self, now: Instant) {
        // A node that was unconfigured enters NMT once it has a node-id and LSS is waiting.
        let d = &self.dev;
        if d.node_id == UNCONFIGURED
            && d.pending_node_id != UNCONFIGURED
            && !self.lss.in_configuration()
        {
            self.reset(false, now);
        }
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// Carries out what an LSS request asks; returns whether it succeeded. Configure node-id /
    /// bit timing set the pending value and the objects that copy it (TMI 0x2000 / 0x2001), so
    /// that every copy says the same.
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))] // rare: out of the frame path
    pub(super) fn lss_request(&mut self, r: lss::Request) -> bool {
        let (hook, raw) = match r {
            lss::Request::ConfigureNodeId(id) => {
                self.pending_node_id = id;
                if id == UNCONFIGURED {
                    return true;
                }
                (Hook::PendingNodeId, id as u32)
            }
            lss::Request::ConfigureBitRate(kbps) => {
                self.pending_bitrate = kbps;
                (Hook::PendingBitRate, object_of_kbps(kbps))
            }
            lss::Request::ActivateBitRate { silent_until } => {
                // Deaf and mute for both switch delays; checked on every frame.
                self.silent_until = Some(silent_until);
                return true;
            }
            lss::Request::StoreConfiguration => return self.store_lss().is_ok(),
        };
        self.set_hooked(hook, raw);
        true
    }

    /// Sets every entry with `hook` (rare paths only: it scans the table).
    fn set_hooked(&mut self, hook: Hook, raw: u32) {
        // The table is 'static: walked directly, not looked up slot by slot.
        for (slot, e) in self.od.entries().iter().enumerate() {
            if e.hook == hook {
                self.od.set(slot, raw);
            }
        }
    }

    /// Makes `kbps` the active bit rate now (LSS activate bit timing).
    pub(crate) fn activate_bitrate(&mut self, kbps: u16) {
        self.bitrate = kbps;
        self.cfg.set_bitrate_kbps(kbps);
    }
}

impl<A: Application, S: Storage> lss::LssNode for Device<A, S> {
    fn address(&self) -> [u32; 4] {
        self.lss_address()
    }
    fn address_part(&self, i: u8) -> u32 {
        // One dictionary search rather than the four of `lss_address`.
        self.od.value(0x1018, i + 1).unwrap_or(0)
    }
    fn node_id(&self) -> u8 {
        self.node_id
    }
    fn pending(&self) -> (u8, u16) {
        (self.pending_node_id, self.pending_bitrate)
    }
    fn fastscan(&self) -> bool {
        self.features().lss_fastscan
    }
    fn bit_timing(&self) -> &'static [u8] {
        self.features().lss_bit_timing
    }
}
