//! Object access: the SDO server's view of the dictionary and the node's write rules.

use super::lss_glue::kbps_of_object;
use super::*;
use crate::config::{ERROR_BEHAVIOUR, MAX_HB_CONSUMERS};

impl<A: Application, S: Storage> Device<A, S> {
    /// The rule of an entry's hook for a value of its own, on this node-id, whatever the object
    /// holds now: an SDO write must pass it, and a value from the state file that fails it is
    /// not loaded. For COB-IDs of services this node produces or answers on it keeps them off
    /// 29-bit and CiA 301 restricted CAN-IDs (else a write or a state file could make the node
    /// talk on the NMT or SYNC identifier). Out of line in firmware: writes and loads share it.
    /// On a host always in line: with the arms of the heartbeat consumer, 0x1029 and RPDOs
    /// rustc's hint no longer inlined it, and an SDO download paid 25 instructions.
    #[cfg_attr(feature = "inline-hot-paths", inline(always))]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub(super) fn value_allowed(&self, e: &Entry, raw: u32) -> Result<(), Abort> {
        // Each service's own rule says whether its COB-ID may name a restricted CAN-ID.
        let may_be_restricted = match e.hook {
            Hook::SyncCobId => false,
            Hook::EmcyCobId => emcy::cob_id_may_be_restricted(raw),
            Hook::GuardingCobId => errctl::guarding_cob_id_may_be_restricted(raw, self.node_id),
            Hook::TpdoComm | Hook::TpdoMap => {
                return Tpdos::check_value(&self.od, e.index, e.sub, raw)
            }
            // (Guards that are constants where a build compiles the services out.)
            Hook::HbConsumer if MAX_HB_CONSUMERS > 0 => return hbcons::value_allowed(raw),
            Hook::ErrorBehaviour if ERROR_BEHAVIOUR => return errbehav::value_allowed(raw),
            // (A build without RPDOs has no such object: no code for it.)
            Hook::RpdoComm | Hook::RpdoMap if crate::config::MAX_RPDOS > 0 => {
                return Rpdos::check_value(&self.od, e.index, e.sub, raw)
            }
            // The others check nothing beyond the table.
            _ => return Ok(()),
        };
        if cob::service_cob_id_refused(raw, may_be_restricted) {
            return Err(Abort::InvalidValue);
        }
        Ok(())
    }

    /// The rule of an entry's hook for an SDO write of `raw` over `cur` that passed the
    /// table's checks: [`Device::value_allowed`] and what relates the new value to the current
    /// one (a state file's values are loaded without the latter).
    // One caller (`check_write`); out of line it cost an SDO download a call and its register
    // saves (the services' arms live in `validate_service`, out of line).
    #[inline(always)]
    fn validate(&mut self, e: &Entry, cur: u32, raw: u32) -> Result<(), Abort> {
        if e.hook.checked_by_service() {
            return self.validate_service(e, raw);
        }
        // One call for every other hook (`value_allowed` is a match of its own).
        self.value_allowed(e, raw)?;
        let clash = match e.hook {
            Hook::EmcyCobId => emcy::cob_id_change_refused(cur, raw),
            // D22: SYNC and guarding on different CAN-IDs.
            Hook::SyncCobId => errctl::sync_guarding_clash(raw, self.errctl.guarding_id().into()),
            Hook::GuardingCobId => errctl::sync_guarding_clash(raw, self.sync_can_id()),
            // The others (`Hook::None` among them) check nothing beyond their own value (or
            // act instead of storing).
            _ => false,
        };
        if clash {
            return Err(Abort::InvalidValue);
        }
        Ok(())
    }

    /// [`Device::validate`] for the PDO parameters and the application's objects.
    #[inline(never)]
    fn validate_service(&mut self, e: &Entry, raw: u32) -> Result<(), Abort> {
        match e.hook {
            Hook::TpdoComm | Hook::TpdoMap => {
                let strict = self.features().event_timer_above_inhibit;
                self.pdo.validate(&self.od, e.index, e.sub, raw, strict)
            }
            Hook::RpdoComm | Hook::RpdoMap if crate::config::MAX_RPDOS > 0 => {
                self.rpdo.validate(&self.od, e.index, e.sub, raw)
            }
            // The value on its own, then CiA 301's one entry per node-id (its own abort code).
            Hook::HbConsumer if MAX_HB_CONSUMERS > 0 => {
                hbcons::value_allowed(raw)?;
                hbcons::check(&self.od, e.sub, raw)
            }
            hook => match hook.app_number() {
                Some(h) => {
                    let cx = AppView {
                        od: &self.od,
                        model: self.model,
                        cfg: &self.cfg,
                    };
                    self.app.validate(h, e.sub, raw, &cx)
                }
                None => Ok(()),
            },
        }
    }

    /// The side effects of an entry's hook once a write has landed.
    #[inline]
    fn written(&mut self, e: &Entry, raw: u32) {
        // Most objects have none: no call for them.
        if e.hook.acts_when_written() {
            self.written_slow(e, raw);
        }
    }

    #[inline(never)]
    fn written_slow(&mut self, e: &Entry, raw: u32) {
        let now = self.now;
        match e.hook {
            Hook::ErrorHistory => {
                self.emcy.clear_history();
                self.sync_error_register();
            }
            Hook::Guarding | Hook::GuardingCobId => self.apply_guarding(now),
            Hook::EmcyInhibit => self.emcy.set_inhibit(raw as u16),
            Hook::Heartbeat => self.errctl.set_heartbeat(raw as u16, now),
            Hook::HbConsumer if MAX_HB_CONSUMERS > 0 => {
                if self.hbc.set(e.sub, raw) {
                    // Its error ended: cleared as the others are.
                    self.update_pdo_activity(now);
                }
            }
            Hook::TpdoComm | Hook::TpdoMap => {
                let n = (e.index & 0x1FF) as usize;
                self.pdo.reconfigure(n, &self.od, now);
                if e.hook == Hook::TpdoComm {
                    let (app, mut cx) = self.app_ctx(now);
                    app.tpdo_comm_written(n, e.sub, raw, &mut cx);
                }
            }
            Hook::RpdoComm | Hook::RpdoMap if crate::config::MAX_RPDOS > 0 => {
                let n = (e.index & 0x1FF) as usize;
                self.rpdo.configure(n, &self.od, &mut self.emcy)
            }
            Hook::PendingNodeId => self.pending_node_id = raw as u8,
            Hook::PendingBitRate => self.pending_bitrate = kbps_of_object(raw),
            hook => {
                if let Some(h) = hook.app_number() {
                    let (app, mut cx) = self.app_ctx(now);
                    app.written(h, e.sub, raw, &mut cx);
                }
            }
        }
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// [`Dictionary::find`] with a one-entry memo (the table never changes, so a found slot
    /// stays right).
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn find(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let key = od::key(index, sub);
        if self.memo.0 == key {
            return Ok(self.memo.1);
        }
        let slot = self.od.find(index, sub)?;
        self.memo = (key, slot);
        Ok(slot)
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// The slot of `index`/`sub` if it may be read now (the two steps of every upload; one
    /// shared copy in firmware).
    #[cfg_attr(feature = "inline-hot-paths", inline(always))] // a host: on the SDO fast paths
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn find_readable(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let slot = self.find(index, sub)?;
        self.readable(slot)?;
        Ok(slot)
    }

    /// The slot of `index`/`sub` if it may be written (every download's first step).
    #[cfg_attr(feature = "inline-hot-paths", inline(always))] // a host: on the SDO fast paths
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    fn find_writable(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let slot = self.find(index, sub)?;
        if !self.od.entry(slot).access.writable() {
            return Err(Abort::ReadOnly);
        }
        Ok(slot)
    }

    /// Whether `slot` may be read now: readable, and (0x1003) within the recorded errors
    /// ([`Emcy::history_readable`]).
    #[inline]
    fn readable(&self, slot: usize) -> Result<(), Abort> {
        let e = self.od.entry(slot);
        if !e.access.readable() {
            return Err(Abort::WriteOnly);
        }
        if e.hook == Hook::ErrorHistory {
            return self.emcy.history_readable(e.sub);
        }
        Ok(())
    }
}

impl<A: Application, S: Storage> ObjectAccess for Device<A, S> {
    fn upload_size(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        let slot = self.find_readable(index, sub)?;
        Ok(self.od.size_of(slot))
    }

    fn read(&mut self, index: u16, sub: u8, offset: usize, buf: &mut [u8]) -> Result<usize, Abort> {
        let slot = self.find_readable(index, sub)?;
        // Values the application derives from others are current when read.
        if let Some(h) = self.od.entry(slot).hook.app_number() {
            self.app.refresh(h, &mut self.od, self.nmt);
        }
        Ok(self.od.read_at(slot, offset, buf))
    }

    fn download_size(&mut self, index: u16, sub: u8) -> Result<Option<usize>, Abort> {
        let slot = self.find_writable(index, sub)?;
        Ok(self.od.entry(slot).ty.size())
    }

    fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), Abort> {
        let slot = self.find_writable(index, sub)?;
        self.write_slot(slot, data.len(), le_u32(data))
    }

    #[inline]
    fn write_expedited(
        &mut self,
        index: u16,
        sub: u8,
        size: Option<u32>,
        data: &[u8; 4],
    ) -> Result<(), Abort> {
        // `download_size` and `write` with one lookup: the same checks in the same order.
        let slot = self.find_writable(index, sub)?;
        let e = self.od.entry(slot);
        let len = match size {
            Some(n) => n as usize,
            None => e.ty.size().unwrap_or(4),
        }
        .min(4);
        // `le_u32` of the first `len` bytes.
        let raw = u32::from_le_bytes(*data) & (u64::from(u32::MAX) >> (32 - 8 * len as u32)) as u32;
        self.write_slot(slot, len, raw)
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// The checks and side effects of a write of `len` bytes (`raw`, little-endian) to a
    /// writable object.
    #[inline]
    fn write_slot(&mut self, slot: usize, len: usize, raw: u32) -> Result<(), Abort> {
        let e = self.od.entry(slot);
        let Some(size) = e.ty.size() else {
            return Err(Abort::UnsupportedAccess);
        };
        if len > size {
            return Err(Abort::LengthTooHigh);
        }
        if len < size {
            return Err(Abort::LengthTooLow);
        }
        if matches!(e.hook, Hook::StoreParameters | Hook::RestoreDefaults) {
            return self.storage_command(e, raw);
        }
        self.check_write(slot, e, raw)?;
        self.land_write(slot, e, raw);
        Ok(())
    }

    /// The checks of a value written to `slot` (an SDO download's, an RPDO's): the table's
    /// and the hook's rules.
    // Inlined, with the entry its caller found: an SDO download runs it on every write; the
    // RPDO path is the other caller (out of line, with a second lookup, they cost a download
    // about 40 instructions, docs/BENCHMARKS.md).
    #[inline(always)]
    fn check_write(&mut self, slot: usize, e: &'static Entry, raw: u32) -> Result<(), Abort> {
        if e.ty == DataType::Boolean && raw > 1 {
            return Err(Abort::InvalidValue);
        }
        e.check(raw)?;
        self.validate(e, self.od.get(slot), raw)
    }

    /// A checked value lands in `slot`, with its hook's side effects.
    // Inlined as `check_write` is.
    #[inline(always)]
    fn land_write(&mut self, slot: usize, e: &'static Entry, raw: u32) {
        self.od.set(slot, raw);
        self.written(e, raw);
    }

    /// RPDO `n`'s data: each value is checked as an SDO download's would be and, only when all
    /// pass (D24: a value that fails leaves the whole PDO unprocessed),
    /// written with the same side effects; an object a TPDO maps then sets off its
    /// asynchronous TPDOs as an application event does.
    pub(super) fn apply_rpdo(&mut self, n: usize, data: [u8; 8]) {
        let values = self.rpdo.values(n, data);
        if values
            .iter()
            .any(|(slot, raw)| self.check_write(slot, self.od.entry(slot), raw).is_err())
        {
            return;
        }
        for (slot, raw) in values.iter() {
            self.land_write(slot, self.od.entry(slot), raw);
            self.pdo.value_changed(slot, true);
        }
    }
}
