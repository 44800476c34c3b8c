//! The services' configuration from the dictionary, EMCY sending and mirroring, PDO activity.

use super::*;

impl<A: Application, S: Storage> Device<A, S> {
    /// The CAN-ID of the SYNC COB-ID (0x1005), whatever its bit 31.
    pub(super) fn sync_can_id(&self) -> u32 {
        self.od.hot(self.hot.sync).unwrap_or(0x80) & 0x7FF
    }

    /// The application and the context it runs in (disjoint borrows of the device).
    pub(super) fn app_ctx(&mut self, now: Instant) -> (&mut A, AppCtx<'_, A>) {
        let cx = AppCtx {
            od: &mut self.od,
            emcy: &mut self.emcy,
            pdo: &mut self.pdo,
            model: self.model,
            cfg: &self.cfg,
            nmt: self.nmt,
            bitrate_kbps: self.bitrate,
            now,
        };
        (&mut self.app, cx)
    }

    /// Hands guard time, life time factor and the guarding COB-ID (0x100E where the model has
    /// it, else the pre-defined 0x700 + node-id) to the error-control service.
    /// Without the feature (a constant where the build fixes the features) life guarding is
    /// never armed, and its code is not linked.
    pub(super) fn apply_guarding(&mut self, now: Instant) {
        if self.features().node_guarding {
            let gt = self.od.value(0x100C, 0).unwrap_or(0) as u16;
            let lf = self.od.value(0x100D, 0).unwrap_or(0) as u8;
            self.errctl.set_guarding(gt, lf, now);
        }
        let id = self
            .od
            .value(0x100E, 0)
            .map_or(cob::ERRCTL + self.node_id as u16, |v| (v & 0x7FF) as u16);
        self.errctl.set_guarding_id(id);
    }

    /// Pushes the cached service configuration from the dictionary after a reload.
    pub(super) fn apply_comm_config(&mut self, now: Instant) {
        self.pdo
            .configure_all(self.features().tpdos as usize, &self.od);
        self.rpdo
            .configure_all(self.features().rpdos as usize, &self.od);
        let hb = self.od.value(0x1017, 0).unwrap_or(0) as u16;
        self.errctl.set_heartbeat(hb, now);
        self.apply_guarding(now);
        if crate::config::MAX_HB_CONSUMERS > 0 {
            self.hbc.load(&self.od);
        }
        self.emcy
            .set_inhibit(self.od.value(0x1015, 0).unwrap_or(0) as u16);
        self.sync_error_register();
    }

    pub(super) fn sync_error_register(&mut self) {
        let h = self.hot;
        let r = self.emcy.register();
        self.od.set_hot(h.err_reg, r as u32);
        let n = self.emcy.history_len();
        self.od.set_hot(h.hist, n as u32);
        // Half-open: an inclusive range's iterator compiles to more code.
        for i in 1..usize::from(h.hist_subs) + 1 {
            let v = self.emcy.history_or_zero(i);
            self.od.set(usize::from(h.hist) + i, v);
        }
        self.emcy_synced = self.emcy.generation();
    }

    /// Moves EMCYs whose inhibit time allows into the transmit queue and mirrors the error
    /// register and history into the dictionary.
    #[inline]
    pub(super) fn flush_emcy(&mut self) {
        // Runs after every frame and timer: on a host the usual "nothing to do" stays inline; a
        // firmware calls straight through (`flush_emcy_slow` checks the same), a test fewer at
        // every call site.
        if crate::config::INLINE_HOT_PATHS
            && self.emcy.generation() == self.emcy_synced
            && !self.emcy.has_pending()
        {
            return;
        }
        self.flush_emcy_slow();
    }

    /// Whether EMCYs go out now: in pre-operational and operational only. A stopped node keeps
    /// them until it leaves Stopped, one without a node-id (initialising) until it has one.
    /// The one rule for both sending and the EMCY deadline.
    #[inline]
    pub(super) fn emcy_served(&self) -> bool {
        self.nmt.sdo_allowed()
    }

    // Out of line: `flush_emcy` is inlined at every entry point's end.
    #[inline(never)]
    fn flush_emcy_slow(&mut self) {
        // Nothing else writes 0x1001 / 0x1003 between resets, so an unchanged EMCY state needs
        // no mirroring (this runs after every frame).
        if self.emcy.generation() != self.emcy_synced {
            self.sync_error_register();
        }
        // No separate "nothing waits" test: `poll` makes it (reading the COB-ID first is cheap).
        if !self.emcy_served() {
            return;
        }
        let cobid = self
            .od
            .hot(self.hot.emcy_cob)
            .unwrap_or(0x80 + self.node_id as u32);
        while let Some(p) = self.emcy.poll(self.now) {
            if cobid & 0x8000_0000 == 0 {
                self.tx.push_std((cobid & 0x7FF) as u16, p, 8);
            }
        }
    }

    pub(super) fn run_pdos(&mut self, now: Instant) {
        let Device { pdo, od, tx, .. } = self;
        pdo.handle_timeout(od, now, &mut |f| {
            tx.push(f);
        });
    }

    /// RPDO `n` received `data` (a data frame on its CAN-ID, in Operational): the RPDO
    /// service's checks, and its values applied when they are due now.
    pub(super) fn receive_rpdo(&mut self, n: usize, data: &[u8], now: Instant) {
        let Device { rpdo, emcy, .. } = self;
        if let Some(d) = rpdo.receive(n, data, now, emcy) {
            self.apply_rpdo(n, d);
        }
    }

    /// A SYNC: the data synchronous RPDOs received since the last one is applied.
    // Inlined, over the device's RPDOs only: a node without any (the sensors) pays one
    // comparison per SYNC, not a call and a walk over the stack's `MAX_RPDOS`.
    #[inline(always)]
    pub(super) fn rpdo_sync(&mut self) {
        for n in 0..self.rpdo.count() {
            if let Some(d) = self.rpdo.take_held(n) {
                self.apply_rpdo(n, d);
            }
        }
    }

    /// PDOs run in Operational unless life guarding was lost (D11).
    pub(super) fn update_pdo_activity(&mut self, now: Instant) {
        let guarding = self.features().node_guarding;
        let lost = guarding && self.errctl.life_guard_lost;
        let on = self.nmt == NmtState::Operational && !lost;
        self.pdo.set_active(on, now);
        self.rpdo.set_active(on);
        if crate::config::MAX_HB_CONSUMERS > 0 && !self.nmt.sdo_allowed() {
            // Heartbeats are consumed in pre-operational and operational only (D27).
            self.hbc.pause();
        }
        // Also a 0x8130 raised from outside (`Node::set_error`), on every model. One code for
        // life guarding and the heartbeat consumer: it stands while either has an error.
        let hb_lost = crate::config::MAX_HB_CONSUMERS > 0 && self.hbc.any_lost();
        if !lost && !hb_lost && self.emcy.is_active(emcy::code::LIFE_GUARD) {
            self.emcy.clear(emcy::code::LIFE_GUARD);
            self.flush_emcy();
        }
    }
}

impl<A: Application, S: Storage> Node<A, S> {
    /// The CAN controller went bus-off (`active`) or recovered, for a device whose application
    /// has no bus-off reaction of its own (a plain device; the sensors report it through their
    /// application's fault). Going bus-off is a communication error: the communication bit of
    /// 0x1001 while it lasts and the 0x1029 sub 1 reaction; the recovery sends EMCY 0x8140
    /// ("recovered from bus-off") and clears it, as CANopenNode reports it (D25).
    pub fn set_bus_off(&mut self, active: bool) {
        if !self.dev.powered {
            return;
        }
        let now = self.dev.now;
        let code = emcy::code::BUS_OFF_RECOVERED;
        let e = &mut self.dev.emcy;
        if active && !e.is_active(code) {
            e.hold(code, emcy::reg::COMMUNICATION);
            self.communication_error(now);
        } else if !active && e.is_active(code) {
            e.event(code, [0; 5]);
            e.clear(code);
        }
        self.epilogue();
    }

    /// A communication error occurred (a heartbeat consumer or life guarding event, bus-off):
    /// the node changes state as 0x1029 sub 1 says, if the table has it
    /// ([`errbehav::reaction`]).
    pub(super) fn communication_error(&mut self, now: Instant) {
        if !crate::config::ERROR_BEHAVIOUR {
            return;
        }
        let d = &mut self.dev;
        let v = d.od.hot(d.hot.comm_error);
        let Some(to) = errbehav::reaction(v, d.nmt) else {
            return;
        };
        d.nmt = to;
        if to == NmtState::Stopped {
            // As the NMT stop command: an unfinished SDO transfer ends silently.
            self.sdo.reset();
        }
        d.update_pdo_activity(now);
    }

    /// The heartbeat consumer's missed heartbeats at `now`: EMCY 0x8130 with the node-id in
    /// its first manufacturer byte (an event of its own for each further node while the error
    /// stands, the register unchanged), and the 0x1029 reaction.
    pub(super) fn heartbeats_missed(&mut self, now: Instant) {
        while let Some(node) = self.dev.hbc.handle_timeout(now) {
            let e = &mut self.dev.emcy;
            let mfr = [node, 0, 0, 0, 0];
            if e.is_active(emcy::code::LIFE_GUARD) {
                e.event(emcy::code::LIFE_GUARD, mfr);
            } else {
                e.raise(emcy::code::LIFE_GUARD, emcy::reg::COMMUNICATION, mfr);
            }
            self.communication_error(now);
        }
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// A frame on a watched node's heartbeat CAN-ID `id` (pre-operational or operational): a
    /// heartbeat or boot-up (one data byte or more; a zero-length frame is a guard request to
    /// that node, D11). An error it ends clears as the others do.
    pub(super) fn heartbeat_received(&mut self, id: u16, f: &Frame, now: Instant) {
        if f.is_remote() || f.dlc() == 0 {
            return;
        }
        if self
            .hbc
            .received((id - cob::ERRCTL) as u8, f.data()[0], now)
        {
            self.update_pdo_activity(now);
        }
    }
}
