//! D15 (docs/DECISIONS.md, "Stored COB-IDs and the node-id"): a stored COB-ID whose default is
//! "base + node-id" follows the active node-id only when its CAN-ID was the pre-defined one; a
//! user's own CAN-ID stays; flag bits stay. Images written before the saved node-id was
//! recorded keep the earlier rule: a CAN-ID in the pre-defined range of any node-id
//! (base + 1 … base + 0x7F) follows.

use crate::common::hex;
use canpos_models::th::TH;
use canpos_models::DeviceConfig;
use canpos_models::SensorNode;
use canpos_stack::storage::{self, RamStorage, KEY_SAVED_NODE_ID};
use canpos_stack::{Instant, Node};

fn sdo(n: &mut SensorNode<RamStorage>, now: Instant, id: u8, req: &str) -> Vec<u8> {
    let f = canpos_stack::Frame::new(0x600 + id as u16, &hex(req)).unwrap();
    n.handle_frame(&f, now);
    let mut out = Vec::new();
    while let Some(f) = n.poll_transmit() {
        out.push(f);
    }
    assert_eq!(out.len(), 1, "{req}: {out:?}");
    out[0].data().to_vec()
}

/// Sets TPDO `n`'s COB-ID (0x1800 + n, sub 1) to `v` the CiA 301 way: invalid first.
fn set_cob(node: &mut SensorNode<RamStorage>, n: u16, v: u32) {
    let cur = node.read_object(0x1800 + n, 1).unwrap();
    for w in [cur | 0x8000_0000, v] {
        let b = w.to_le_bytes();
        let req = format!(
            "23 {:02X} 18 01 {:02X} {:02X} {:02X} {:02X}",
            n, b[0], b[1], b[2], b[3]
        );
        assert_eq!(sdo(node, Instant::ZERO, 0x7F, &req)[0], 0x60, "{req}");
    }
}

/// Node 0x7F with TPDO COB-IDs 1…4 as given, saved; returns its storage.
fn saved_th(cobs: [Option<u32>; 4]) -> RamStorage {
    let mut n = Node::new(&TH, TH.default_config, RamStorage::default());
    n.power_on(Instant::ZERO);
    while n.poll_transmit().is_some() {}
    for (i, c) in cobs.iter().enumerate() {
        if let Some(v) = c {
            set_cob(&mut n, i as u16, *v);
        }
    }
    let f = canpos_stack::Frame::new(0x67F, &hex("23 10 10 01 73 61 76 65")).unwrap();
    n.handle_frame(&f, Instant::ZERO);
    n.handle_timeout(Instant::from_millis(30));
    while n.poll_transmit().is_some() {}
    assert_eq!(n.storage_mut().saves, 1);
    n.storage_mut().clone()
}

fn cobs_as(node_id: u8, st: RamStorage) -> Vec<u32> {
    let cfg = DeviceConfig {
        node_id,
        ..TH.default_config
    };
    let mut n = canpos_models::SensorNode::new(&TH, cfg, st);
    n.power_on(Instant::ZERO);
    (0..4)
        .map(|k| n.read_object(0x1800 + k, 1).unwrap())
        .collect()
}

/// The image as written before the saved node-id was recorded: `st` without that record.
fn older_image(mut st: RamStorage) -> RamStorage {
    storage::update_image(
        &mut st,
        TH.features.tag,
        &|k| k == KEY_SAVED_NODE_ID,
        &mut core::iter::empty(),
    )
    .unwrap();
    st
}

const COBS: [Option<u32>; 4] = [
    None,              // TPDO1: its default, 0x180 + 0x7F (with its flags)
    Some(0x8000_02C0), // TPDO2: node 0x40's pre-defined CAN-ID
    Some(0x8000_0410), // TPDO3: outside 0x381…0x3FF
    Some(0x8000_0480), // TPDO4: the base itself (no node-id's)
];

/// With the saved node-id: only the CAN-ID that was this unit's own pre-defined one follows.
#[test]
fn d15_with_the_saved_node_id_only_the_own_pre_defined_can_id_follows() {
    let st = saved_th(COBS);
    let c = cobs_as(5, st);
    assert_eq!(c[0] & 0x7FF, 0x185);
    assert_eq!(
        c[1], 0x8000_02C0,
        "another node's CAN-ID is the user's choice here"
    );
    assert_eq!(c[2], 0x8000_0410);
    assert_eq!(c[3], 0x8000_0480);
}

/// Without it (an older image): every CAN-ID in a pre-defined range (base + 1 … base + 0x7F)
/// follows, keeping the flags; the base itself and CAN-IDs outside the range stay.
#[test]
fn d15_an_image_without_the_saved_node_id_keeps_the_earlier_rule() {
    let st = older_image(saved_th(COBS));
    let c = cobs_as(5, st.clone());
    let default1 = cobs_as(0x7F, RamStorage::default())[0];
    assert_eq!(c[0], (default1 & !0x7FF) | 0x185, "flags kept");
    assert_eq!(c[1], 0x8000_0285, "0x2C0 is in 0x281…0x2FF: follows");
    assert_eq!(c[2], 0x8000_0410, "outside the range: stays");
    assert_eq!(c[3], 0x8000_0480, "the base is no node-id's: stays");
    // Under the node-id it was saved with, nothing moves but the range's own rule.
    let same = cobs_as(0x7F, st);
    assert_eq!(same[0], default1);
    assert_eq!(same[1], 0x8000_02FF);
}

/// The CAN-ID that follows keeps every other bit of the stored COB-ID, "valid" among them: a
/// valid TPDO2 on 0x2C0 in an older image comes back valid on 0x285 under node-id 5, not as the
/// TPDO's default (disabled).
#[test]
fn d15_a_following_can_id_keeps_the_stored_flags() {
    let st = older_image(saved_th([None, Some(0x0000_02C0), None, None]));
    let c = cobs_as(5, st);
    assert_eq!(c[1], 0x0000_0285);
    assert_ne!(
        c[1],
        cobs_as(5, RamStorage::default())[1],
        "not the default"
    );
}

/// The device's own automatic store (the TH's operating-life temperature record, D19) stores no
/// COB-ID, so it keeps the node-id the COB-IDs were saved under: the rule with the saved node-id
/// still applies after it (it once dropped that record, and the older-image rule took over).
#[test]
fn d15_an_automatic_store_keeps_the_saved_node_id() {
    let mut r = crate::common::Rig {
        node: Node::new(&TH, TH.default_config, saved_th(COBS)),
        now: Instant::ZERO,
    };
    r.node.power_on(r.now);
    r.take();
    let saves = r.node.storage_mut().saves;
    r.cycle_temp(Some(1_000_000), 25);
    r.cycle_temp(Some(1_000_000), 26);
    assert!(r.node.storage_mut().saves > saves, "an automatic store");
    let c = cobs_as(5, r.node.storage_mut().clone());
    assert_eq!(c[1], 0x8000_02C0, "still the user's own CAN-ID");
}
