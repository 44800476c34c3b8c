//! The timeline's wire: arbitration among the members ready to send, the frame on the wire to
//! its end (received, corrupted, collided), and fault confinement (error counters and states,
//! failed attempts, a stuck-dominant bus), as a further `impl` block of [`Timeline`].

use super::*;

impl Timeline {
    pub(super) fn arbitrate(&mut self, t: Nanos, out: &mut Vec<BusEvent>) {
        // Everyone with a frame ready at `t` takes part; the lowest arbitration value wins.
        let mut best: Option<u32> = None;
        let mut offers: Vec<Offer> = Vec::new();
        for &i in &self.active {
            let m = &self.members[i as usize];
            if !m.can_arbitrate() || m.suspend_until > t {
                continue;
            }
            if let Some(q) = m.offer(t) {
                let key = m.queue[q].key;
                offers.push((i, q, key));
                best = Some(best.map_or(key, |b| b.min(key)));
            }
        }
        let Some(best) = best else {
            return;
        };
        if offers.len() > 1 {
            // Each offer is another member's: a loser leaving its queue moves no winner's index.
            self.arbitration_losses(&offers, best, t, out);
        }
        offers.retain(|&(_, _, k)| k == best);
        self.note_bus_activity(t);
        // The same identifier with other bits: at the first difference, whoever sends recessive
        // and reads dominant has a bit error. An error-active one destroys the frame with its
        // active error flag (so every sender sees the error); an error-passive one's flag is
        // recessive: it drops out alone and the others' frame goes on.
        let stuffed_of =
            |m: &[Member], o: &(u32, usize, u32)| stuffed(&m[o.0 as usize].queue[o.1].frame);
        let mut passive_losers = Vec::new();
        let mut diff = None;
        loop {
            let lead = self.members[offers[0].0 as usize].queue[offers[0].1].frame;
            let p = offers
                .iter()
                .skip(1)
                .filter_map(|o| {
                    first_difference(&lead, &self.members[o.0 as usize].queue[o.1].frame)
                })
                .min();
            let Some(p) = p else { break };
            let (losers, winners): (Vec<Offer>, Vec<Offer>) = offers
                .iter()
                .partition(|o| stuffed_of(&self.members, o).get(p));
            if losers
                .iter()
                .any(|o| self.members[o.0 as usize].state == BusState::ErrorActive)
            {
                diff = Some(p);
                break;
            }
            passive_losers.extend(losers.iter().map(|o| (MemberId(o.0), p)));
            offers = winners;
        }
        let (first, fq, _) = offers[0];
        let frame = self.members[first as usize].queue[fq].frame;
        let senders: Vec<(MemberId, u64)> = offers
            .iter()
            .map(|&(i, q, _)| {
                let m = &mut self.members[i as usize];
                m.queue[q].on_wire = true;
                (MemberId(i), m.queue[q].seq)
            })
            .collect();
        let bit = self.bit_ns;
        let (error, bits) = if let Some(p) = diff {
            (
                Some(BusErrorKind::Collision),
                u64::from(p + 1 + ERROR_FRAME_BITS),
            )
        } else if self.corrupt_ppm > 0
            && self.next_random() % 1_000_000 < u64::from(self.corrupt_ppm)
        {
            let len = u64::from(stuffed(&frame).len());
            let p = 1 + self.next_random() % (len - 1);
            (
                Some(BusErrorKind::Corrupted),
                p + 1 + u64::from(ERROR_FRAME_BITS),
            )
        } else {
            let total = u64::from(frame_length(&frame).total);
            (None, total - u64::from(INTERMISSION_BITS))
        };
        let end = t + bits * bit;
        self.current = Some(OnWire {
            senders,
            frame,
            start: t,
            end,
            free: end + u64::from(INTERMISSION_BITS) * bit,
            error,
            bits: bits + u64::from(INTERMISSION_BITS),
            passive_losers,
        });
    }

    /// Members whose offer lost to `best`: reported, and taken out of the queue of a member
    /// that discards its losers.
    fn arbitration_losses(
        &mut self,
        offers: &[Offer],
        best: u32,
        t: Nanos,
        out: &mut Vec<BusEvent>,
    ) {
        for &(i, q, key) in offers {
            if key == best {
                continue;
            }
            let m = &mut self.members[i as usize];
            let frame = m.queue[q].frame;
            let discarded = m.discard_on_loss;
            if !discarded && !self.report_losses {
                continue;
            }
            if discarded {
                m.queue.remove(q);
                if m.queue.is_empty() {
                    self.active.retain(|&a| a != i);
                }
            }
            if !self.report_losses {
                continue;
            }
            out.push(BusEvent::ArbitrationLost {
                member: MemberId(i),
                frame,
                at: t,
                discarded,
            });
        }
    }

    pub(super) fn finish(&mut self, cur: OnWire, out: &mut Vec<BusEvent>) {
        self.free_at = cur.free;
        for &(id, p) in &cur.passive_losers {
            let m = &mut self.members[id.0 as usize];
            m.stats.tx_errors += 1;
            m.stats.collisions += 1;
            m.suspend_until = cur.free + u64::from(SUSPEND_BITS) * self.bit_ns;
            let at = cur.start + u64::from(p + 1 + ERROR_FRAME_BITS) * self.bit_ns;
            self.bump_tec(id, 8, at.min(cur.end), out);
        }
        self.record(cur.end, cur.bits, cur.error.is_none());
        let senders: Vec<MemberId> = cur.senders.iter().map(|s| s.0).collect();
        match cur.error {
            None => {
                self.frames += 1;
                for &(id, seq) in &cur.senders {
                    let m = &mut self.members[id.0 as usize];
                    if !m.live {
                        continue;
                    }
                    if let Some(i) = m.queue.iter().position(|q| q.seq == seq) {
                        let q = m.queue.swap_remove(i);
                        let wait = cur.start - q.ready_at;
                        m.stats.last_wait = wait;
                        m.stats.max_wait = m.stats.max_wait.max(wait);
                    }
                    m.stats.sent += 1;
                    m.tec = m.tec.saturating_sub(1);
                    if m.queue.is_empty() {
                        self.active.retain(|&i| i != id.0);
                    }
                }
                for &(id, _) in &cur.senders {
                    let m = &self.members[id.0 as usize];
                    if m.leaving && m.queue.is_empty() {
                        self.remove(id);
                    }
                }
                self.receivers_ok(&senders, cur.end, out);
                out.push(BusEvent::Frame {
                    // Its senders all left while it was on the wire: from nobody.
                    from: senders.first().copied().unwrap_or(MemberId(u32::MAX)),
                    co_senders: senders.get(1..).unwrap_or_default().to_vec(),
                    frame: cur.frame,
                    start: cur.start,
                    end: cur.end,
                });
            }
            Some(kind) => {
                self.error_frames += 1;
                for &(id, seq) in &cur.senders {
                    let m = &mut self.members[id.0 as usize];
                    if let Some(q) = m.queue.iter_mut().find(|q| q.seq == seq) {
                        q.on_wire = false;
                    }
                    m.stats.tx_errors += 1;
                    if kind == BusErrorKind::Collision {
                        m.stats.collisions += 1;
                    }
                }
                out.push(BusEvent::Error(BusError {
                    at: cur.end,
                    kind,
                    id: Some(cur.frame.id()),
                    transmitters: senders.clone(),
                }));
                for &s in &senders {
                    self.bump_tec(s, 8, cur.end, out);
                }
                self.receivers_error(&senders, 1, cur.end, out);
            }
        }
        // An error-passive transmitter waits 8 more bits before its next frame.
        for &s in &senders {
            let m = &mut self.members[s.0 as usize];
            if m.state == BusState::ErrorPassive {
                m.suspend_until = cur.free + u64::from(SUSPEND_BITS) * self.bit_ns;
            }
            self.update_state(s, cur.end, out);
        }
        self.note_bus_idle(cur.end);
    }

    /// Successful reception: REC − 1 (above 127: back to 119; ISO 11898-1 allows 119…127).
    pub(super) fn receivers_ok(
        &mut self,
        senders: &[MemberId],
        at: Nanos,
        out: &mut Vec<BusEvent>,
    ) {
        // Most buses never see an error: no pass over every member per frame then.
        if !self.rec_raised {
            return;
        }
        let mut any = false;
        for i in 0..self.members.len() as u32 {
            let m = &mut self.members[i as usize];
            if m.rec == 0
                || !m.live
                || m.state == BusState::BusOff
                || senders.contains(&MemberId(i))
            {
                any |= m.rec > 0;
                continue;
            }
            m.rec = if m.rec > 127 { 119 } else { m.rec - 1 };
            any |= m.rec > 0;
            self.update_state(MemberId(i), at, out);
        }
        self.rec_raised = any;
    }

    pub(super) fn receivers_error(
        &mut self,
        senders: &[MemberId],
        by: u16,
        at: Nanos,
        out: &mut Vec<BusEvent>,
    ) {
        for i in 0..self.members.len() as u32 {
            let m = &mut self.members[i as usize];
            if !m.live || m.state == BusState::BusOff || senders.contains(&MemberId(i)) {
                continue;
            }
            m.rec = (m.rec + by).min(255);
            self.rec_raised = true;
            self.update_state(MemberId(i), at, out);
        }
    }

    pub(super) fn bump_tec(&mut self, id: MemberId, by: u16, at: Nanos, out: &mut Vec<BusEvent>) {
        let m = &mut self.members[id.0 as usize];
        if !m.live || m.state == BusState::BusOff {
            return;
        }
        m.tec = (m.tec + by).min(256);
        self.update_state(id, at, out);
    }

    /// Applies the thresholds: error passive at 128, bus-off at 256 (ISO 11898-1).
    pub(super) fn update_state(&mut self, id: MemberId, at: Nanos, out: &mut Vec<BusEvent>) {
        let m = &mut self.members[id.0 as usize];
        if !m.live || m.state == BusState::BusOff {
            return;
        }
        let state = if m.tec >= 256 {
            BusState::BusOff
        } else if m.tec >= 128 || m.rec >= 128 {
            BusState::ErrorPassive
        } else {
            BusState::ErrorActive
        };
        if state == m.state {
            return;
        }
        m.state = state;
        if state == BusState::BusOff {
            // The controller leaves the bus: what it had queued is lost.
            let on_wire = m.queue.iter().filter(|q| q.on_wire).count();
            m.stats.lost_bus_off += (m.queue.len() - on_wire) as u64;
            m.queue.retain(|q| q.on_wire);
            m.off_sequences = 0;
            m.off_run_start = at;
            self.off.push(id.0);
            self.active.retain(|&i| i != id.0);
        }
        out.push(BusEvent::State {
            member: id,
            at,
            state,
            tec: m.tec,
            rec: m.rec,
        });
    }

    /// Attempts of members whose transceiver failed: a bit error at SOF each, seen by nobody
    /// else (the bus stays recessive).
    pub(super) fn failed_attempts(&mut self, now: Nanos, out: &mut Vec<BusEvent>) {
        let bit = self.bit_ns;
        for k in 0..self.failed.len() {
            let id = self.failed[k];
            loop {
                let m = &mut self.members[id as usize];
                if m.state == BusState::BusOff {
                    break;
                }
                let Some(ready) = m.earliest_ready() else {
                    break;
                };
                let t = m.next_attempt.max(ready);
                if t > now {
                    break;
                }
                let end = t + u64::from(1 + ERROR_FRAME_BITS) * bit;
                let mut next = end + u64::from(INTERMISSION_BITS) * bit;
                if m.state == BusState::ErrorPassive {
                    next += u64::from(SUSPEND_BITS) * bit;
                }
                m.next_attempt = next;
                m.stats.tx_errors += 1;
                self.bump_tec(MemberId(id), 8, end, out);
                let m = &mut self.members[id as usize];
                if m.state == BusState::BusOff {
                    // It counts recessive bits from here (the bus itself is fine).
                    m.off_run_start = end;
                }
            }
        }
    }

    /// The bus was held dominant for [a, b): the frame on the wire is destroyed; every 8
    /// dominant bits after the first 14 raise the transmitter's TEC and the receivers' REC by 8
    /// (ISO 11898-1 fault confinement rule 6), after the error each saw first.
    pub(super) fn apply_stuck(&mut self, out: &mut Vec<BusEvent>) {
        let Some((a, b)) = self.stuck.take() else {
            return;
        };
        let flagger = self.flag.take();
        let flag = flagger.is_some();
        let bits = (b - a) / self.bit_ns;
        let steps = if bits >= 14 { 1 + (bits - 14) / 8 } else { 0 };
        let cur = self.current.take();
        let senders: Vec<MemberId> = cur
            .as_ref()
            .map(|c| c.senders.iter().map(|s| s.0).collect())
            .unwrap_or_default();
        if let Some(c) = &cur {
            for &(id, seq) in &c.senders {
                let m = &mut self.members[id.0 as usize];
                if let Some(q) = m.queue.iter_mut().find(|q| q.seq == seq) {
                    q.on_wire = false;
                }
                m.stats.tx_errors += 1;
            }
        }
        self.note_bus_activity(a);
        self.error_frames += 1;
        // An error flag is followed by its 8-bit delimiter on the wire.
        self.record(b, if flag { bits + 8 } else { bits }, false);
        out.push(BusEvent::Error(BusError {
            at: b,
            kind: if flag {
                BusErrorKind::ErrorFlag
            } else {
                BusErrorKind::StuckDominant { bits }
            },
            id: cur.as_ref().map(|c| c.frame.id()),
            transmitters: senders.clone(),
        }));
        for &s in &senders {
            for _ in 0..=steps {
                self.bump_tec(s, 8, b, out);
            }
        }
        // Receivers: the error they detect (+1), then +8 per step.
        self.receivers_error(&senders, (1 + 8 * steps).min(255) as u16, b, out);
        // The flagger (not a transmitter) sees the others' flags right after its own: + 8
        // (rule 2). A transmitter that flagged was counted as one above.
        if let Some(f) = flagger.filter(|f| !senders.contains(f)) {
            let m = &mut self.members[f.0 as usize];
            if m.live && m.state != BusState::BusOff {
                m.rec = (m.rec + 8).min(255);
                self.update_state(f, b, out);
            }
        }
        // Bus integration: 11 recessive bits before anyone may start.
        self.free_at = b + u64::from(RECESSIVE_SEQUENCE_BITS) * self.bit_ns;
        self.note_bus_idle(b + 8 * self.bit_ns);
    }
}
