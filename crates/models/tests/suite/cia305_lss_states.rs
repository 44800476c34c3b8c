//! CiA 305 LSS slave states: "identify non-configured remote slave" is answered only by a node
//! with neither an active nor a pending node-id, and switch state selective is a service of
//! the waiting state (a slave already in configuration ignores it).

use crate::common::{booted, hex, Rig};
use canpos_models as models;

fn lss(r: &mut Rig, req: &str) -> Vec<Vec<u8>> {
    r.send(0x7E5, &hex(req))
        .into_iter()
        .filter(|f| f.std_id() == Some(0x7E4))
        .map(|f| f.data().to_vec())
        .collect()
}

fn le(v: u32) -> String {
    v.to_le_bytes().map(|b| format!("{b:02X}")).join(" ")
}

#[test]
fn a_pending_node_id_makes_the_node_configured() {
    // No active node-id, but one configured for the next reset: not "non-configured".
    let th = models::by_name("th").unwrap();
    let mut r = Rig::with_config(th, th.default_config.with_node_id(0xFF));
    r.take();
    assert_eq!(
        lss(&mut r, "4C 00 00 00 00 00 00 00"),
        vec![hex("50 00 00 00 00 00 00 00")]
    );
    lss(&mut r, "04 01 00 00 00 00 00 00");
    assert_eq!(
        lss(&mut r, "11 05 00 00 00 00 00 00"),
        vec![hex("11 00 00 00 00 00 00 00")]
    );
    assert!(
        lss(&mut r, "4C 00 00 00 00 00 00 00").is_empty(),
        "pending id 5"
    );
}

#[test]
fn an_active_node_id_makes_the_node_configured() {
    // Node 127 told to drop its id at the next reset: still configured until then.
    let mut r = booted("th");
    lss(&mut r, "04 01 00 00 00 00 00 00");
    assert_eq!(
        lss(&mut r, "11 FF 00 00 00 00 00 00"),
        vec![hex("11 00 00 00 00 00 00 00")]
    );
    assert!(
        lss(&mut r, "4C 00 00 00 00 00 00 00").is_empty(),
        "active id 127"
    );
}

#[test]
fn switch_selective_is_ignored_in_configuration() {
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        let addr = r.node.device().lss_address();
        lss(&mut r, "04 01 00 00 00 00 00 00");
        let mut out = Vec::new();
        for (cs, v) in [0x40u8, 0x41, 0x42, 0x43].into_iter().zip(addr) {
            out.extend(lss(&mut r, &format!("{cs:02X} {} 00 00 00", le(v))));
        }
        assert!(out.is_empty(), "{name}: {out:02X?}");
        // Still in configuration.
        assert_eq!(lss(&mut r, "5E 00 00 00 00 00 00 00").len(), 1, "{name}");
    }
}
