//! Property tests: random traffic into a TH node (node-id 0x7F).
//!
//! - nothing panics;
//! - every SDO request (0x67F, DLC 8, SDO allowed by NMT) gets exactly one answer on 0x5FF,
//!   except the documented no-reply cases: client aborts (ccs 4) and frames of a block
//!   transfer (sub-block segments are answered only at the end of a block; a block-upload
//!   start / ack is answered by a whole block);
//! - the node only ever sends on its own COB-IDs.
//!
//! LSS frames (0x7E5) are left out: LSS configure node-id plus a reset legitimately moves every
//! COB-ID. Random SDO writes could in principle do that too (0x1800:01, 0x1014), so the
//! multiplexors are drawn from a list without those, plus uniformly random ones (a hit on
//! exactly those objects with a valid value is ~1e-8 per frame).
use crate::common::Rig;
use canpos_models::th::TH;
use canpos_stack::sdo::TransferKind;
use canpos_stack::{Frame, Instant};
use proptest::prelude::*;
use proptest::sample::select;

const OWN_IDS: [u16; 8] = [0x5FF, 0x77F, 0x0FF, 0x1FF, 0x2FF, 0x3FF, 0x4FF, 0x7E4];

#[derive(Clone, Debug)]
enum Op {
    Frame { id: u16, data: Vec<u8>, rtr: bool },
    Advance(u64),
}

fn sdo_frame() -> impl Strategy<Value = Vec<u8>> {
    let b0 = prop_oneof![
        any::<u8>(),
        select(vec![
            0x20u8, 0x21, 0x22, 0x23, 0x27, 0x2B, 0x2F, 0x40, 0x60, 0x70, 0x00, 0x10, 0x01, 0x0B,
            0x1B, 0x07, 0x80, 0xA0, 0xA4, 0xA3, 0xA2, 0xA1, 0xC2, 0xC6, 0xC1, 0xD5, 0x81, 0x82,
            0x83, 0xE0,
        ]),
    ];
    let mux = prop_oneof![
        any::<(u16, u8)>(),
        select(vec![
            (0x1000u16, 0u8),
            (0x1000, 1),
            (0x1001, 0),
            (0x1003, 0),
            (0x1005, 0),
            (0x1008, 0),
            (0x100C, 0),
            (0x1010, 1),
            (0x1011, 1),
            (0x1017, 0),
            (0x1800, 2),
            (0x1A00, 0),
            (0x1A00, 1),
            (0x1234, 0),
        ]),
    ];
    let len = prop_oneof![8 => Just(8usize), 1 => 0usize..=8];
    (b0, mux, any::<[u8; 4]>(), len).prop_map(|(b0, (i, s), tail, len)| {
        let ib = i.to_le_bytes();
        let mut f = vec![b0, ib[0], ib[1], s, tail[0], tail[1], tail[2], tail[3]];
        // Block sizes / ack sequence numbers: keep them mostly in range.
        if matches!(b0, 0xA0 | 0xA4) {
            f[4] = tail[0] % 130;
        }
        f.truncate(len);
        f
    })
}

fn op() -> impl Strategy<Value = Op> {
    let nmt = select(vec![
        vec![0x01u8, 0x7F],
        vec![0x02, 0x7F],
        vec![0x80, 0x00],
        vec![0x81, 0x7F],
        vec![0x82, 0x00],
        vec![0x01, 0x00],
    ]);
    let other_id = (0u16..0x800).prop_filter("no LSS", |id| *id != 0x7E5);
    prop_oneof![
        10 => sdo_frame().prop_map(|data| Op::Frame { id: 0x67F, data, rtr: false }),
        2 => nmt.prop_map(|data| Op::Frame { id: 0x000, data, rtr: false }),
        2 => (other_id, proptest::collection::vec(any::<u8>(), 0..=8), any::<bool>())
            .prop_map(|(id, data, rtr)| Op::Frame { id, data, rtr }),
        3 => prop_oneof![0u64..50, 900u64..1100, 0u64..3000].prop_map(Op::Advance),
    ]
}

/// What NMT allows, mirrored from the commands sent (SDO is served in pre-op and operational).
fn nmt_effect(data: &[u8], sdo_on: &mut bool) {
    if data.len() != 2 || (data[1] != 0 && data[1] != 0x7F) {
        return;
    }
    match data[0] {
        0x01 | 0x80 | 0x81 | 0x82 => *sdo_on = true,
        0x02 => *sdo_on = false,
        _ => {}
    }
}

fn check_ids(frames: &[Frame]) -> Result<(), TestCaseError> {
    for f in frames {
        let id = f.std_id();
        prop_assert!(
            id.is_some_and(|id| OWN_IDS.contains(&id)),
            "sent on a foreign COB-ID: {f:?}"
        );
    }
    Ok(())
}

fn sdo_count(frames: &[Frame]) -> usize {
    frames.iter().filter(|f| f.std_id() == Some(0x5FF)).count()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn random_traffic_is_answered_and_stays_on_own_ids(ops in proptest::collection::vec(op(), 1..80)) {
        let mut r = Rig::new(&TH);
        let boot = r.take();
        check_ids(&boot)?;
        let mut sdo_on = true;
        for op in ops {
            match op {
                Op::Advance(ms) => {
                    let out: Vec<Frame> = r.advance_ms(ms).into_iter().map(|(_, f)| f).collect();
                    check_ids(&out)?;
                    if !sdo_on {
                        prop_assert_eq!(sdo_count(&out), 0, "SDO frame while stopped");
                    }
                }
                Op::Frame { id, data, rtr } => {
                    let f = if rtr {
                        Frame::remote(id as u32, false, data.len() as u8).unwrap()
                    } else {
                        Frame::new(id, &data).unwrap()
                    };
                    let before = r.node.sdo_server().transfer().map(|(k, _)| k);
                    let bad_dlc = r.node.sdo_server().bad_dlc;
                    r.node.handle_frame(&f, r.now);
                    let out = r.take();
                    check_ids(&out)?;
                    if id == 0x000 && !rtr {
                        nmt_effect(&data, &mut sdo_on);
                    }
                    if id != 0x67F || rtr {
                        continue;
                    }
                    let n = sdo_count(&out);
                    if !sdo_on {
                        prop_assert_eq!(n, 0, "SDO answered while stopped");
                        continue;
                    }
                    if data.len() != 8 {
                        prop_assert_eq!(n, 0);
                        prop_assert_eq!(r.node.sdo_server().bad_dlc, bad_dlc.wrapping_add(1));
                        continue;
                    }
                    match before {
                        Some(TransferKind::BlockDownload) => {
                            // Segments: nothing, or one ack / end response / abort.
                            prop_assert!(n <= 1, "{} answers in a block download", n);
                            continue;
                        }
                        Some(TransferKind::BlockUpload) => {
                            // At most one block of segments, or one end / abort / answer.
                            prop_assert!(n <= 127, "{} answers in a block upload", n);
                            continue;
                        }
                        _ => {}
                    }
                    if data[0] >> 5 == 4 {
                        prop_assert_eq!(n, 0, "client abort answered: {:02X?}", data);
                        continue;
                    }
                    if n == 0 {
                        // D7: the answer to "save" / "load" comes once the store completed.
                        let late: Vec<Frame> =
                            r.advance_ms(20).into_iter().map(|(_, f)| f).collect();
                        check_ids(&late)?;
                        prop_assert_eq!(sdo_count(&late), 1, "no answer to {:02X?}", data);
                    } else {
                        prop_assert_eq!(n, 1, "{} answers to {:02X?}: {:?}", n, data, out);
                    }
                }
            }
        }
        // Whatever was left unfinished times out with exactly one abort.
        if sdo_on && r.node.sdo_server().busy() {
            let end = Instant::from_micros(r.now.micros() + 1_000_000);
            let out: Vec<Frame> = r.run_until(end).into_iter().map(|(_, f)| f).collect();
            check_ids(&out)?;
            let aborts: Vec<_> = out
                .iter()
                .filter(|f| f.std_id() == Some(0x5FF))
                .collect();
            prop_assert_eq!(aborts.len(), 1);
            prop_assert_eq!(&aborts[0].data()[4..8], &[0u8, 0, 4, 5][..]);
            prop_assert!(!r.node.sdo_server().busy());
        }
    }
}
