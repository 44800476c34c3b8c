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
    pub(super) fn rpdo_sync(&mut self) {
        for n in 0..crate::config::MAX_RPDOS {
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
        // Also a 0x8130 raised from outside (`Node::set_error`), on every model.
        if !lost && self.emcy.is_active(emcy::code::LIFE_GUARD) {
            self.emcy.clear(emcy::code::LIFE_GUARD);
            self.flush_emcy();
        }
    }
}
