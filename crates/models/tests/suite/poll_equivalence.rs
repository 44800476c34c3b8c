//! The TPDO timer path that a producing node spends its time in, tested three ways:
//!
//! - `Node::poll(now)` is documented as `handle_timeout(now)` when a deadline has passed, then
//!   `poll_transmit()`. Its fast path hands a due TPDO out without the transmit queue; one
//!   property drives two nodes with the same stimuli, one through each API, and requires the
//!   same frames in the same order after every stimulus, and the same deadlines. The stimuli
//!   aim at what the fast path depends on: TPDO timers (event timer, inhibit time,
//!   transmission type, validity, several TPDOs due together), NMT state, SYNC, heartbeat,
//!   EMCY from samples without a magnet, bit-rate mismatch (frames lost), power cycles, and
//!   time stepped through every deadline or in jumps.
//! - Both APIs share the timer walk, so two more properties check it against oracles written
//!   here from CiA 301's rules, not from the implementation: every event timer keeps its
//!   absolute schedule, TPDOs due together come in TPDO order (also for a late host), and the
//!   inhibit time holds a TPDO back and then sends it.

use canpos_encoder::Sample;
use canpos_models as models;
use canpos_models::SensorNode;
use canpos_stack::storage::RamStorage;
use canpos_stack::{Frame, Instant, Node};
use proptest::prelude::*;

#[derive(Clone, Debug)]
enum Stim {
    /// SDO expedited download (index, sub, value, size in bytes).
    Write(u16, u8, u32, u8),
    /// NMT command to all nodes.
    Nmt(u8),
    Sync,
    /// A sample: position in µm, or no magnet.
    Sample(Option<i32>),
    /// Time: through every deadline up to +dt µs, or one jump.
    Advance(u32, bool),
    /// LSS "activate bit timing" with a switch delay of this many ms: the node can neither
    /// hear nor talk for twice that (its frames meanwhile are lost).
    Switch(u16),
    PowerCycle,
}

fn stim() -> impl Strategy<Value = Stim> {
    let tpdo = 0u16..4;
    prop_oneof![
        // Event timer (ms), inhibit time (100 µs), transmission type, COB-ID valid bit.
        (tpdo.clone(), 0u32..6).prop_map(|(n, ms)| Stim::Write(0x1800 + n, 5, ms, 2)),
        (tpdo.clone(), 0u32..40).prop_map(|(n, i)| Stim::Write(0x1800 + n, 3, i, 2)),
        (
            tpdo.clone(),
            prop::sample::select(vec![0u32, 1, 2, 254, 255])
        )
            .prop_map(|(n, t)| Stim::Write(0x1800 + n, 2, t, 1)),
        (tpdo, any::<bool>()).prop_map(|(n, off)| {
            let cob = 0x180 + 0x100 * u32::from(n) + 0x7F;
            Stim::Write(0x1800 + n, 1, cob | if off { 0x8000_0000 } else { 0 }, 4)
        }),
        (0u32..4).prop_map(|ms| Stim::Write(0x1017, 0, ms, 2)),
        prop::sample::select(vec![0x01u8, 0x02, 0x80, 0x81, 0x82]).prop_map(Stim::Nmt),
        Just(Stim::Sync),
        prop::option::weighted(0.8, -100i32..600_000).prop_map(Stim::Sample),
        (0u32..25_000, any::<bool>()).prop_map(|(dt, jump)| Stim::Advance(dt, jump)),
        (0u16..8).prop_map(Stim::Switch),
        Just(Stim::PowerCycle),
    ]
}

/// Node A: the separate calls. Node B: `poll`.
struct Pair {
    a: SensorNode<RamStorage>,
    b: SensorNode<RamStorage>,
    now: Instant,
    id: u16,
}

impl Pair {
    fn new(model: &'static models::Model) -> Pair {
        let mut a = Node::new(model, model.default_config, RamStorage::default());
        let mut b = Node::new(model, model.default_config, RamStorage::default());
        a.power_on(Instant::ZERO);
        b.power_on(Instant::ZERO);
        let id = u16::from(model.default_config.node_id);
        Pair {
            a,
            b,
            now: Instant::ZERO,
            id,
        }
    }

    /// Both nodes' output at `now`; they must agree.
    fn settle(&mut self, what: &str) -> Result<(), TestCaseError> {
        let now = self.now;
        let mut fa: Vec<Frame> = Vec::new();
        if self.a.poll_timeout().is_some_and(|t| t <= now) {
            self.a.handle_timeout(now);
        }
        while let Some(f) = self.a.poll_transmit() {
            fa.push(f);
        }
        let mut fb: Vec<Frame> = Vec::new();
        while let Some(f) = self.b.poll(now) {
            fb.push(f);
            prop_assert!(fb.len() < 10_000, "poll does not end");
        }
        prop_assert_eq!(&fa, &fb, "{} at {} µs", what, now.micros());
        prop_assert_eq!(
            self.a.poll_timeout(),
            self.b.poll_timeout(),
            "deadline after {}",
            what
        );
        Ok(())
    }

    fn apply(&mut self, s: &Stim) -> Result<(), TestCaseError> {
        let what = format!("{s:?}");
        match *s {
            Stim::Write(index, sub, v, size) => {
                let cs = match size {
                    1 => 0x2F,
                    2 => 0x2B,
                    _ => 0x23,
                };
                let [i0, i1] = index.to_le_bytes();
                let [v0, v1, v2, v3] = v.to_le_bytes();
                let f = Frame::std8(0x600 + self.id, [cs, i0, i1, sub, v0, v1, v2, v3]);
                self.a.handle_frame(&f, self.now);
                self.b.handle_frame(&f, self.now);
            }
            Stim::Nmt(cmd) => {
                let f = Frame::new(0x000, &[cmd, 0]).expect("NMT frame");
                self.a.handle_frame(&f, self.now);
                self.b.handle_frame(&f, self.now);
            }
            Stim::Sync => {
                let f = Frame::new(0x080, &[]).expect("SYNC frame");
                self.a.handle_frame(&f, self.now);
                self.b.handle_frame(&f, self.now);
            }
            Stim::Sample(p) => {
                let mut smp = Sample::default();
                smp.positions_nm[0] = p.map(|um| i64::from(um) * 1000);
                self.a.update_sample(&smp, self.now);
                self.b.update_sample(&smp, self.now);
            }
            Stim::Advance(dt, jump) => {
                let end = Instant::from_micros(self.now.micros() + u64::from(dt));
                if !jump {
                    // As a runtime does: wake at every deadline (A's; B must have the same).
                    let mut guard = 0;
                    while let Some(t) = self.a.poll_timeout() {
                        if t > end || guard > 5_000 {
                            break;
                        }
                        guard += 1;
                        self.now = t.max(self.now);
                        self.settle(&what)?;
                    }
                }
                self.now = end;
            }
            Stim::Switch(ms) => {
                let [d0, d1] = ms.to_le_bytes();
                for req in [
                    [0x04, 1, 0, 0, 0, 0, 0, 0],
                    [0x15, d0, d1, 0, 0, 0, 0, 0],
                    [0x04, 0, 0, 0, 0, 0, 0, 0],
                ] {
                    let f = Frame::new(0x7E5, &req).expect("LSS frame");
                    self.a.handle_frame(&f, self.now);
                    self.b.handle_frame(&f, self.now);
                }
            }
            Stim::PowerCycle => {
                self.a.power_off();
                self.b.power_off();
                self.a.power_on(self.now);
                self.b.power_on(self.now);
            }
        }
        self.settle(&what)
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn poll_equals_handle_timeout_then_poll_transmit(
        model in 0usize..3,
        start in any::<bool>(),
        stims in proptest::collection::vec(stim(), 1..60),
    ) {
        let model = models::all()[model];
        let mut p = Pair::new(model);
        p.settle("power-on")?;
        if start {
            p.apply(&Stim::Nmt(0x01))?;
        }
        for s in &stims {
            p.apply(s)?;
        }
    }
}

/// SDO expedited download; whether the node accepted it.
fn sdo_write(
    n: &mut SensorNode<RamStorage>,
    id: u16,
    index: u16,
    sub: u8,
    v: u32,
    now: Instant,
) -> bool {
    let [i0, i1] = index.to_le_bytes();
    let [v0, v1, v2, v3] = v.to_le_bytes();
    // The objects' sizes: mapping counts and transmission type 1 byte, times 2, the rest 4.
    let cs = match (index & 0xFF00, sub) {
        (0x1A00, 0) | (0x1800, 2) => 0x2F,
        (0x1800, 3 | 5) => 0x2B,
        _ => 0x23,
    };
    n.handle_frame(
        &Frame::std8(0x600 + id, [cs, i0, i1, sub, v0, v1, v2, v3]),
        now,
    );
    let mut answers = Vec::new();
    while let Some(f) = n.poll(now) {
        answers.push(f);
    }
    answers.first().map(|f| f.raw()[0]) == Some(0x60)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// An independent oracle for the timer walk (`poll` and `handle_timeout` share it): every
    /// TPDO of the model made asynchronous with its own event timer produces exactly one frame
    /// at `start + k × period`, and TPDOs due at the same instant come in TPDO order, whether
    /// the host wakes at every deadline or late.
    #[test]
    fn every_event_timer_keeps_its_absolute_schedule(
        model in 0usize..3,
        periods in proptest::collection::vec(1u32..6, 4),
        late in proptest::collection::vec(0u64..2500, 0..40),
    ) {
        let model = models::all()[model];
        let mut n = Node::new(model, model.default_config, RamStorage::default());
        n.power_on(Instant::ZERO);
        while n.poll(Instant::ZERO).is_some() {}
        let id = u16::from(model.default_config.node_id);
        let count = usize::from(model.features.tpdos);
        let map1 = n.read_object(0x1A00, 1).expect("TPDO1 maps something");
        let now = Instant::from_micros(1_000);
        // (TPDO index, CAN-ID) of the TPDOs the model lets us configure so.
        let mut cobs: Vec<(usize, u16)> = Vec::new();
        for (k, &period) in periods.iter().enumerate().take(count) {
            let (comm, map) = (0x1800 + k as u16, 0x1A00 + k as u16);
            let cob = 0x180 + 0x100 * k as u32 + u32::from(id);
            // Valid, asynchronous, no inhibit time, its own period; one mapped value. A model
            // that fixes one of these for a TPDO (read-only or limited) leaves it out.
            let mut ok = sdo_write(&mut n, id, comm, 1, cob | 0x8000_0000, now);
            ok &= sdo_write(&mut n, id, map, 0, 0, now);
            ok &= sdo_write(&mut n, id, map, 1, map1, now);
            ok &= sdo_write(&mut n, id, map, 0, 1, now);
            let _ = sdo_write(&mut n, id, comm, 2, 254, now);
            ok &= n.read_object(comm, 2).is_ok_and(|t| t >= 254);
            let _ = sdo_write(&mut n, id, comm, 3, 0, now);
            ok &= n.read_object(comm, 3).map_or(true, |i| i == 0);
            ok &= sdo_write(&mut n, id, comm, 5, period, now);
            let valid = sdo_write(&mut n, id, comm, 1, if ok { cob } else { cob | 0x8000_0000 }, now);
            if ok && valid {
                cobs.push((k, cob as u16));
            }
        }
        prop_assert!(!cobs.is_empty(), "no TPDO could be configured");
        n.handle_frame(&Frame::new(0x000, &[0x01, 0]).expect("NMT"), now);
        while n.poll(now).is_some() {}

        // The host: wakes at every deadline, sometimes late (but never later than the
        // shortest period, so no period is skipped).
        let end = now.micros() + 30_000;
        let mut got: Vec<(u64, u16)> = Vec::new();
        let mut t = now;
        let mut k = 0;
        while let Some(d) = n.poll_timeout() {
            if d.micros() > end {
                break;
            }
            let delay = late.get(k).copied().unwrap_or(0) % 900;
            k += 1;
            t = Instant::from_micros(d.micros().max(t.micros()) + delay);
            while let Some(f) = n.poll(t) {
                got.push((t.micros(), f.std_id().expect("standard id")));
            }
        }
        // The oracle: frame k of TPDO j is due at now + k × period_j; a late host sends it
        // at its wake-up, TPDOs in index order among those due together.
        let due: Vec<(u64, usize)> = {
            let mut v: Vec<(u64, usize)> = cobs
                .iter()
                .enumerate()
                .flat_map(|(j, &(k, _))| {
                    let p = u64::from(periods[k]) * 1000;
                    (1..).map(move |i| (now.micros() + i * p, j)).take_while(|&(t, _)| t <= end)
                })
                .collect();
            v.sort();
            v
        };
        let sent: Vec<u16> = got.iter().map(|&(_, c)| c).collect();
        let mut want: Vec<u16> = Vec::new();
        // Group the oracle's frames by the wake-up that serves them.
        let wakes: Vec<u64> = {
            let mut w: Vec<u64> = got.iter().map(|&(t, _)| t).collect();
            w.dedup();
            w
        };
        let mut i = 0;
        for &w in &wakes {
            let mut batch: Vec<usize> = Vec::new();
            while i < due.len() && due[i].0 <= w {
                batch.push(due[i].1);
                i += 1;
            }
            batch.sort();
            want.extend(batch.iter().map(|&j| cobs[j].1));
        }
        prop_assert!(
            i + cobs.len() >= due.len(),
            "frames missing: {} of {}",
            i,
            due.len()
        );
        prop_assert_eq!(sent, want);
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// An independent oracle for the inhibit time of an event-timer TPDO: each expiry makes the
    /// TPDO pending; it goes out at the expiry or when the inhibit time since the previous
    /// frame ends, whichever is later; expiries while it waits merge into that one frame.
    #[test]
    fn inhibit_time_holds_and_then_sends_the_tpdo(
        model in 0usize..3,
        period_ms in 1u32..6,
        inhibit_100us in 0u32..60,
    ) {
        let model = models::all()[model];
        let mut n = Node::new(model, model.default_config, RamStorage::default());
        n.power_on(Instant::ZERO);
        while n.poll(Instant::ZERO).is_some() {}
        let id = u16::from(model.default_config.node_id);
        let now = Instant::from_micros(1_000);
        // TMI refuses an inhibit time not below the event timer: the values that landed count.
        let _ = sdo_write(&mut n, id, 0x1800, 5, period_ms, now);
        let _ = sdo_write(&mut n, id, 0x1800, 3, inhibit_100us, now);
        let p = u64::from(n.read_object(0x1800, 5).expect("event timer")) * 1000;
        let inh = u64::from(n.read_object(0x1800, 3).expect("inhibit time")) * 100;
        prop_assume!(p > 0 && n.read_object(0x1800, 2).is_ok_and(|t| t >= 254));
        n.handle_frame(&Frame::new(0x000, &[0x01, 0]).expect("NMT"), now);
        while n.poll(now).is_some() {}

        let end = now.micros() + 40_000;
        let mut got = Vec::new();
        while let Some(d) = n.poll_timeout() {
            if d.micros() > end {
                break;
            }
            while let Some(f) = n.poll(d) {
                if f.std_id() == Some(0x180 + id) {
                    got.push(d.micros());
                }
            }
        }
        let mut want = Vec::new();
        let (mut fire, mut free_at) = (now.micros() + p, 0u64);
        loop {
            let send = fire.max(free_at);
            if send > end {
                break;
            }
            want.push(send);
            free_at = send + inh;
            // Expiries up to the send merged into it; the next one after it starts anew.
            fire = now.micros() + ((send - now.micros()) / p + 1) * p;
        }
        prop_assert_eq!(got, want, "period {} µs, inhibit {} µs", p, inh);
    }
}
