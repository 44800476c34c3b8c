//! `Node::poll(now)` is documented as `handle_timeout(now)` when a deadline has passed, then
//! `poll_transmit()`. Its fast path hands a due TPDO out without the transmit queue; this
//! property test drives two nodes with the same stimuli, one through each API, and requires
//! the same frames in the same order after every stimulus, and the same deadlines.
//!
//! The stimuli aim at what the fast path depends on: TPDO timers (event timer, inhibit time,
//! transmission type, validity, several TPDOs due together), NMT state, SYNC, heartbeat,
//! EMCY from samples without a magnet, bit-rate mismatch (frames lost), power cycles, and time
//! stepped through every deadline or in jumps.

use canpos_core::encoder::Sample;
use canpos_core::models;
use canpos_core::storage::RamStorage;
use canpos_core::{Frame, Instant, Node};
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
    /// The bit rate of the bus (None: matches the node); frames are lost on a mismatch.
    Bus(Option<u16>),
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
        prop::option::weighted(0.2, Just(50u16)).prop_map(Stim::Bus),
        Just(Stim::PowerCycle),
    ]
}

/// Node A: the separate calls. Node B: `poll`.
struct Pair {
    a: Node<RamStorage>,
    b: Node<RamStorage>,
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
        prop_assert_eq!(&fa, &fb, "{} at {} µs", what, now.0);
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
                let end = Instant(self.now.0 + u64::from(dt));
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
            Stim::Bus(kbps) => {
                self.a.set_bus_bitrate(kbps);
                self.b.set_bus_bitrate(kbps);
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
