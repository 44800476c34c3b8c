//! TMI: node-id / bit rate through 0x2000 / 0x2001 + "save" (R17, R19, D16), store only in
//! pre-operational, and the "kill" signature in both byte orders (D23).

use crate::common::{booted, hex, Rig};

fn store(r: &mut Rig, bytes: &str) -> Vec<u8> {
    r.store_cmd(0x67F, &hex(bytes), 25)
        .into_iter()
        .find(|(_, f)| f.std_id() == Some(0x5FF))
        .map(|(_, f)| f.data().to_vec())
        .unwrap()
}

#[test]
fn node_id_via_0x2000_and_save_applies_after_power_cycle() {
    let mut r = booted("tmi");
    assert_eq!(
        r.req(0x67F, &hex("2F 00 20 00 09 00 00 00")).1,
        hex("60 00 20 00 00 00 00 00")
    );
    assert_eq!(
        store(&mut r, "23 10 10 01 73 61 76 65"),
        hex("60 10 10 01 00 00 00 00")
    );
    r.node.power_off();
    r.node.power_on(r.now);
    let f = r.take();
    assert_eq!(
        f[0].std_id(),
        Some(0x709),
        "boot-up from the stored node-id"
    );
    assert_eq!(
        r.req(0x609, &hex("40 00 20 00 00 00 00 00")).1,
        hex("4F 00 20 00 09 00 00 00")
    );
}

#[test]
fn node_id_via_0x2000_applies_after_reset_communication() {
    let mut r = booted("tmi");
    r.req(0x67F, &hex("2F 00 20 00 0A 00 00 00"));
    let f = r.send(0x000, &[0x82, 0x7F]);
    assert_eq!(f[0].std_id(), Some(0x70A));
}

#[test]
fn store_only_in_pre_operational() {
    let mut r = booted("tmi");
    r.send(0x000, &[0x01, 0x7F]);
    r.take();
    assert_eq!(
        r.req(0x67F, &hex("23 10 10 01 73 61 76 65")).1,
        hex("80 10 10 01 22 00 00 08")
    );
}

#[test]
fn kill_in_both_byte_orders_deletes_the_stored_set() {
    for kill in ["23 10 10 01 6B 69 6C 6C", "23 10 10 01 6C 6C 69 6B"] {
        let mut r = booted("tmi");
        r.req(0x67F, &hex("2B 17 10 00 64 00 00 00"));
        store(&mut r, "23 10 10 01 73 61 76 65");
        assert_eq!(store(&mut r, kill), hex("60 10 10 01 00 00 00 00"));
        r.power_cycle();
        assert_eq!(
            r.req(0x67F, &hex("40 17 10 00 00 00 00 00")).1,
            hex("4B 17 10 00 00 00 00 00")
        );
    }
}
