//! LSS slave robustness: any sequence of frames on 0x7E5 (any DLC, any bytes) never panics and
//! makes the node answer only on 0x7E4 with 8 bytes.

use crate::common::Rig;
use canpos_models::th::TH;
use canpos_models::DeviceConfig;
use canpos_stack::Frame;
use proptest::prelude::*;

/// Valid command specifiers, so that random runs reach deep into the state machine.
const KNOWN: &[u8] = &[
    0x04, 0x11, 0x13, 0x15, 0x17, 0x40, 0x41, 0x42, 0x43, 0x46, 0x47, 0x48, 0x49, 0x4A, 0x4B, 0x4C,
    0x51, 0x5A, 0x5B, 0x5C, 0x5D, 0x5E,
];

/// One request: raw bytes (0…8 of them), optionally with a known specifier in byte 0 and a
/// small byte 1 (switch-state modes, table selectors), plus a pause before it in ms.
fn request() -> impl Strategy<Value = (Vec<u8>, u64)> {
    (
        prop::collection::vec(any::<u8>(), 0..=8),
        prop::option::of(prop::sample::select(KNOWN)),
        prop::option::of(0u8..3),
        prop_oneof![3 => Just(0u64), 1 => 0u64..50],
    )
        .prop_map(|(mut data, cs, b1, pause)| {
            if let (Some(cs), Some(b)) = (cs, data.first_mut()) {
                *b = cs;
            }
            if let (Some(v), Some(b)) = (b1, data.get_mut(1)) {
                *b = v;
            }
            (data, pause)
        })
}

/// Sends the requests; returns every frame the node answered directly to an LSS request.
fn run(r: &mut Rig, reqs: &[(Vec<u8>, u64)]) -> Vec<Frame> {
    let mut answers = Vec::new();
    for (data, pause) in reqs {
        // Time runs too, so activate-bit-timing switches complete (their frames are not
        // answers; heartbeats and the like may appear there and are not checked).
        r.advance_ms(*pause);
        let f = Frame::new(0x7E5, data).unwrap();
        r.node.handle_frame(&f, r.now);
        while let Some(f) = r.node.poll_transmit() {
            answers.push(f);
        }
    }
    answers
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// A configured node: LSS never resets it, so every direct answer is an LSS answer.
    #[test]
    fn configured_node_answers_only_on_7e4_with_dlc_8(
        reqs in prop::collection::vec(request(), 1..40)
    ) {
        let mut r = Rig::booted(&TH);
        for f in run(&mut r, &reqs) {
            prop_assert_eq!(f.std_id(), Some(0x7E4), "{:?}", f);
            prop_assert_eq!(f.dlc(), 8);
        }
    }

    /// An unconfigured node: it may enter NMT when it gets a node-id (boot-up, power-on EMCY);
    /// anything else it sends is an 8-byte LSS answer.
    #[test]
    fn unconfigured_node_answers_only_on_7e4_with_dlc_8(
        reqs in prop::collection::vec(request(), 1..40)
    ) {
        let cfg = DeviceConfig { node_id: 0xFF, ..TH.default_config };
        let mut r = Rig::with_config(&TH, cfg);
        prop_assert!(r.take().is_empty());
        let answers = run(&mut r, &reqs);
        let id = r.node.device().node_id();
        for f in answers {
            let sid = f.std_id().unwrap();
            if sid == 0x7E4 {
                prop_assert_eq!(f.dlc(), 8);
            } else {
                prop_assert!(id != 0xFF, "{:?} from a node without a node-id", f);
                prop_assert!(sid == 0x700 + id as u16 || sid == 0x80 + id as u16, "{:?}", f);
            }
        }
    }
}
