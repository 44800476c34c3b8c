//! CiA 301 §7.5.2.13 / §7.5.2.14 (0x1010 store, 0x1011 restore, subs 1 all, 2 communication,
//! 3 application) and CiA 305 store configuration, as the node carries them out: a command of
//! one scope changes what is stored for that scope only, keeps what was stored for the other
//! and the LSS configuration; LSS "store configuration" keeps every stored copy of the node-id
//! and bit rate equal (TMI 0x2000 / 0x2001, docs/DECISIONS.md).

use crate::common::{booted, hex, Rig};
use canpos_models::th::TH;
use canpos_stack::Frame;

/// A 0x1010 / 0x1011 command on `sub`; the answer comes after the store time (D7).
fn command(r: &mut Rig, index: u16, sub: u8, sig: &[u8; 4]) {
    let [i0, i1] = index.to_le_bytes();
    let f = Frame::new(0x67F, &[0x23, i0, i1, sub, sig[0], sig[1], sig[2], sig[3]]).unwrap();
    r.node.handle_frame(&f, r.now);
    let a = r.advance_ms(25);
    assert!(
        a.iter()
            .any(|(_, f)| f.std_id() == Some(0x5FF) && f.data()[0] == 0x60),
        "{index:04X}:{sub}: {a:?}"
    );
}

/// TMI objects of each group: 0x1017 heartbeat (communication), 0x6010/1 preset (application).
fn set_both(r: &mut Rig) {
    r.req(0x67F, &hex("2B 17 10 00 64 00 00 00"));
    r.req(0x67F, &hex("23 10 60 01 D2 04 00 00"));
}

fn both(r: &mut Rig) -> (u32, u32) {
    (r.read(0x1017, 0), r.read(0x6010, 1))
}

/// §7.5.2.13: after "save all", a "save" of one group replaces that group's stored values and
/// keeps the other's.
#[test]
fn cia301_7_5_2_13_a_save_of_one_group_keeps_the_other_groups_stored_values() {
    for (sub, after) in [(2u8, (50, 1234)), (3, (100, 99))] {
        let mut r = booted("tmi");
        set_both(&mut r);
        command(&mut r, 0x1010, 1, b"save");
        r.req(0x67F, &hex("2B 17 10 00 32 00 00 00")); // 50 ms
        r.req(0x67F, &hex("23 10 60 01 63 00 00 00")); // 99
        command(&mut r, 0x1010, sub, b"save");
        r.power_cycle();
        assert_eq!(both(&mut r), after, "save sub {sub}");
    }
}

/// §7.5.2.14: a restore of one group forgets that group's stored values only; the defaults
/// apply after the next reset.
#[test]
fn cia301_7_5_2_14_restore_of_one_group_forgets_that_group_only() {
    for (sub, after) in [(2u8, (0, 1234)), (3, (100, 0)), (1, (0, 0))] {
        let mut r = booted("tmi");
        set_both(&mut r);
        command(&mut r, 0x1010, 1, b"save");
        command(&mut r, 0x1011, sub, b"load");
        assert_eq!(
            both(&mut r),
            (100, 1234),
            "restore sub {sub}: nothing before the reset"
        );
        r.power_cycle();
        assert_eq!(both(&mut r), after, "restore sub {sub}");
    }
}

/// CiA 305 / §7.5.2.13: "save" stores the parameters and leaves the LSS-stored node-id and bit
/// rate alone (TH: no object holds a copy of them).
#[test]
fn cia301_save_keeps_the_lss_stored_configuration() {
    let mut r = Rig::booted(&TH);
    // LSS: node-id 9, bit rate 500 kbit/s (table index 2), store.
    r.lss_configure(&[
        "11 09 00 00 00 00 00 00",
        "13 00 02 00 00 00 00 00",
        "17 00 00 00 00 00 00 00",
    ]);
    r.req(0x67F, &hex("2B 17 10 00 64 00 00 00"));
    command(&mut r, 0x1010, 1, b"save");
    let boot = r.power_cycle();
    assert_eq!(boot[0].std_id(), Some(0x709), "{boot:?}");
    assert_eq!(r.node.device().bitrate(), 500);
    assert_eq!(r.node.read_object(0x1017, 0), Ok(100));
}

/// TMI (docs/DECISIONS.md): LSS "store configuration" after a "save" replaces the saved copies in
/// 0x2000 / 0x2001 too, so the next power-on uses what LSS stored, not the older saved copy; the
/// other saved parameters stay.
#[test]
fn tmi_lss_store_after_a_save_replaces_the_saved_copies() {
    let mut r = booted("tmi");
    r.req(0x67F, &hex("2B 17 10 00 64 00 00 00"));
    command(&mut r, 0x1010, 1, b"save"); // 0x2000 = 0x7F, 0x2001 = its bit rate, 0x1017
    let before = r.node.device().bitrate();
    assert_ne!(before, 500);
    // LSS: node-id 9, bit rate 500 kbit/s (table index 2), store.
    r.lss_configure(&[
        "11 09 00 00 00 00 00 00",
        "13 00 02 00 00 00 00 00",
        "17 00 00 00 00 00 00 00",
    ]);
    let boot = r.power_cycle();
    assert_eq!(boot[0].std_id(), Some(0x709), "{boot:?}");
    assert_eq!(r.node.device().bitrate(), 500);
    assert_eq!(r.node.read_object(0x2000, 0), Ok(9));
    assert_eq!(r.node.read_object(0x2001, 0), Ok(500));
    assert_eq!(
        r.node.read_object(0x1017, 0),
        Ok(100),
        "the other saved values stay"
    );
}
