//! Routing of received frames: which service a frame is for, and the NMT commands.

use super::*;

impl<A: Application, S: Storage> Node<A, S> {
    /// Returns whether the frame concerned the node (only then can a deadline have changed).
    pub(super) fn handle_frame_inner(&mut self, f: &Frame, now: Instant) -> bool {
        self.dev.now = now;
        if !self.dev.hears(now) {
            return true;
        }
        let Some(id) = f.std_id() else { return false };
        // Most traffic on a busy bus is other nodes' PDOs: recognise it before anything else.
        if self.dev.ignores(id, f.is_remote()) {
            return false;
        }
        let d = &mut self.dev;
        if id == cob::LSS_RX {
            let reply = match self.lss.handle(f.data(), now, &*d) {
                lss::Output::Silent => None,
                lss::Output::Answer(a) => Some(a),
                lss::Output::Do(r) => {
                    let ok = d.lss_request(r);
                    if let Some(kbps) = self.lss.handle_timeout(now) {
                        // A switch delay of 0: the new bit rate is active at once.
                        d.activate_bitrate(kbps);
                    }
                    lss::confirm(r, ok)
                }
            };
            if let Some(r) = reply {
                d.tx.push(Frame::std8(cob::LSS_TX, r));
            }
            self.after_lss(now);
            return true;
        }
        if d.node_id == UNCONFIGURED {
            return true;
        }
        let node = d.node_id as u16;
        if id == cob::NMT {
            if f.is_remote() {
                return true;
            }
            if let Some(c) = NmtCommand::parse(f.data(), d.node_id) {
                self.nmt_command(c, now);
            }
            return true;
        }
        if id == cob::SDO_RX + node && !f.is_remote() {
            if d.nmt.sdo_allowed() {
                // Read only where a request needs them (the expedited fast path does not).
                let model = d.model;
                let t = move || A::features(model).sdo_transfers();
                if let Some(r) = self.sdo.handle_as(f.data(), now, d, t) {
                    // After a store, the first frame this one queues (`Stats::stores`).
                    d.tx.push_std(cob::SDO_TX + node, r, 8);
                }
                // Block-upload segments (a whole block answers one request).
                while let Some(s) = self.sdo.poll_transmit_as(t) {
                    d.tx.push_std(cob::SDO_TX + node, s, 8);
                }
            }
            return true;
        }
        let sync_id = d.od.hot(d.hot.sync).unwrap_or(0x80);
        let sync = sync_id & 0x8000_0000 == 0 && id as u32 == sync_id & 0x7FF && !f.is_remote();
        // A SYNC is never taken for a guard request (the write rules keep the two CAN-IDs
        // apart; this keeps it so whatever else changes).
        if id == d.errctl.guarding_id() && !sync {
            // Node guarding: an RTR, or on socketcand (no RTR) a zero-length data frame (D11, D22).
            if d.features().node_guarding && (f.is_remote() || f.dlc() == 0) {
                let b = d.errctl.guard_request(d.nmt, now);
                d.tx.push_std(id, [b, 0, 0, 0, 0, 0, 0, 0], 1);
                d.update_pdo_activity(now);
            }
            return true;
        }
        if !d.nmt.sdo_allowed() {
            return true;
        }
        if sync {
            if f.dlc() <= 1 {
                // RPDO data is applied before the TPDOs sample theirs.
                d.rpdo_sync();
                let counter = f.data().first().copied();
                let Device { pdo, od, tx, .. } = d;
                pdo.on_sync(od, now, counter, tx);
            } else if d.features().sync_length_emcy {
                // CiA 301 "unexpected SYNC data length" (conformance EMCY-04 without an RPDO).
                // DLC 1 stays accepted: without 0x1019 the counter byte is simply ignored.
                // Without `Features::sync_length_emcy` (a device whose EMCY table has no such
                // code) the frame is ignored.
                d.emcy.event(emcy::code::SYNC_LENGTH, [0; 5]);
            }
            return true;
        }
        if !f.is_remote() {
            if let Some(n) = d.rpdo.find(id) {
                d.receive_rpdo(n, f.data(), now);
                return true;
            }
        }
        // What is left `ignores` let through as a remote request on a model with RTR-triggered
        // TPDOs.
        let Device { pdo, od, tx, .. } = d;
        pdo.on_rtr(id, od, now, &mut |fr| {
            tx.push(fr);
        });
        true
    }

    fn nmt_command(&mut self, c: NmtCommand, now: Instant) {
        let d = &mut self.dev;
        match c {
            NmtCommand::Start => {
                if d.app.refuses_start(&mut d.emcy) {
                    // E.g. the TMI lock-out: stays pre-operational, the EMCY repeats (§1.14).
                    return;
                }
                d.nmt = NmtState::Operational;
            }
            NmtCommand::Stop => {
                d.nmt = NmtState::Stopped;
                // No SDO in Stopped: an unfinished transfer ends silently (no timeout abort).
                self.sdo.reset();
            }
            NmtCommand::EnterPreOperational => d.nmt = NmtState::PreOperational,
            NmtCommand::ResetNode => return self.reset(true, now),
            NmtCommand::ResetCommunication => return self.reset(false, now),
        }
        d.update_pdo_activity(now);
    }
}

impl<A: Application, S: Storage> Device<A, S> {
    /// Whether a standard frame `id` is none of the node's business: not LSS, NMT, its SDO or
    /// error control, SYNC, one of its RPDOs, nor (where the model allows) a remote request. Mirrors the checks of
    /// `Node::handle_frame_inner` that would end in doing nothing.
    #[inline]
    fn ignores(&self, id: u16, remote: bool) -> bool {
        if id == cob::LSS_RX {
            return false;
        }
        if self.node_id == UNCONFIGURED {
            return true;
        }
        let node = self.node_id as u16;
        if id == cob::NMT || id == cob::SDO_RX + node || id == self.errctl.guarding_id() {
            return false;
        }
        if !self.nmt.sdo_allowed() {
            return true;
        }
        let sync_id = self.od.hot(self.hot.sync).unwrap_or(0x80);
        let is_sync = sync_id & 0x8000_0000 == 0 && id as u32 == sync_id & 0x7FF && !remote;
        !(is_sync || remote && self.features().tpdo_rtr || !remote && self.rpdo.find(id).is_some())
    }
}
