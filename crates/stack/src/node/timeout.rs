//! Deadlines: the services whose timers passed, and the TPDO-only fast path.

use super::*;

impl<A: Application, S: Storage> Node<A, S> {
    #[inline(never)]
    pub(super) fn handle_timeout_slow(&mut self, now: Instant) {
        self.handle_timeout_full(now);
        self.epilogue();
    }

    fn handle_timeout_full(&mut self, now: Instant) {
        // The table says which services have a deadline that passed (the epilogue of the
        // entry point before wrote it); the others have nothing to do.
        let due = |t| self.timers.due(t, now.0);
        let (transfer, switch, silence) = (
            due(Timer::SdoTransfer),
            due(Timer::LssSwitch),
            due(Timer::Silence),
        );
        if transfer {
            if let Some(r) = self.sdo.handle_timeout(now) {
                let id = cob::SDO_TX + self.dev.node_id as u16;
                self.dev.tx.push_std(id, r, 8);
            }
        }
        if switch {
            if let Some(kbps) = self.lss.handle_timeout(now) {
                self.dev.activate_bitrate(kbps);
            }
        }
        if silence {
            // The bit-rate switch is over: the node talks again.
            self.dev.silent_until = None;
        }
        self.after_lss(now);
        let d = &mut self.dev;
        // (A node without a node-id is initialising: one test says both.)
        if d.nmt == NmtState::Initialising {
            return;
        }
        // (Never due in a build without RPDOs: the test goes with them.)
        if crate::config::MAX_RPDOS > 0 && self.timers.due(Timer::Rpdo, now.0) {
            d.rpdo.handle_timeout(now, &mut d.emcy);
        }
        let guarding = d.features().node_guarding;
        while let Some(ev) = d.errctl.handle_timeout(now, d.nmt, guarding) {
            match ev {
                ErrCtlEvent::Heartbeat(b) => {
                    let id = cob::ERRCTL + d.node_id as u16;
                    d.tx.push_std(id, [b, 0, 0, 0, 0, 0, 0, 0], 1);
                }
                ErrCtlEvent::LifeGuardingLost => {
                    d.emcy
                        .raise(emcy::code::LIFE_GUARD, emcy::reg::COMMUNICATION, [0; 5]);
                    d.update_pdo_activity(now);
                }
            }
        }
        d.run_pdos(now);
    }

    /// The rest of the timer fast path once the TPDOs ran: the node's clock and deadline
    /// (TPDOs change neither the other deadlines nor the EMCY state).
    #[inline(always)]
    pub(super) fn after_tpdo_timers(&mut self, now: Instant) {
        let d = &mut self.dev;
        d.now = now;
        // Nothing for the EMCY service to do (see `fast_due`).
        debug_assert!(d.emcy.generation() == d.emcy_synced, "EMCY not mirrored");
        // (A stopped node keeps its EMCYs until it leaves Stopped.)
        debug_assert!(
            !d.emcy.has_pending()
                || !d.emcy_served()
                || d.emcy.poll_timeout().is_some_and(|t| now < t),
            "EMCY due: {:?} at {now:?}, nmt {:?}",
            d.emcy.poll_timeout(),
            d.nmt
        );
        // The epilogue for the one schedule that can have changed.
        self.deadline = self.other_due.min(d.pdo.due_us());
    }
}
