//! CiA 301 §7.5.2.4 (0x1003 pre-defined error field): writing 0 to sub 0 deletes the history;
//! afterwards no sub-index holds an error (reads abort "no data", as the conformance tool's
//! EMCY-03 expects of an empty history), and the next error is the first entry again.

use crate::common::{booted, hex, model, Rig};
use canpos_models::th::TH;

#[test]
fn cia301_7_5_2_4_writing_0_deletes_the_error_history() {
    let mut r = Rig::new(&TH);
    r.node.set_error(0x3100, 0x04, [0; 5], true);
    r.node.set_error(0x4200, 0x08, [0; 5], true);
    r.take();
    assert_eq!(r.node.read_object(0x1003, 0), Ok(2));
    assert_eq!(
        r.req(0x67F, &hex("2F 03 10 00 00 00 00 00")).1,
        hex("60 03 10 00 00 00 00 00")
    );
    assert_eq!(r.node.read_object(0x1003, 0), Ok(0));
    assert_eq!(
        r.req(0x67F, &hex("40 03 10 01 00 00 00 00")).1,
        hex("80 03 10 01 24 00 00 08"),
        "no data in 1003:01"
    );
    r.node.set_error(0x5000, 0x01, [0; 5], true);
    r.take();
    assert_eq!(r.node.read_object(0x1003, 0), Ok(1), "a new history");
    assert_eq!(
        r.node.read_object(0x1003, 1).map(|v| v & 0xFFFF),
        Ok(0x5000)
    );
}

/// CiA 301 §7.2.8.2.1: a stopped node produces no EMCY; what was raised meanwhile goes out when
/// it leaves Stopped.
#[test]
fn cia301_a_stopped_node_sends_its_emcy_when_it_leaves_stopped() {
    let mut r = Rig::booted(&TH);
    r.send(0x000, &[0x02, 0x7F]);
    r.take();
    r.node.set_error(0x3100, 0x04, [0; 5], true);
    assert!(r.take().is_empty(), "stopped: no EMCY");
    assert!(r.advance_ms(100).is_empty());
    assert_eq!(
        r.node.read_object(0x1001, 0),
        Ok(0x05),
        "the register follows anyway"
    );
    let out = r.send(0x000, &[0x80, 0x7F]);
    assert!(out
        .iter()
        .any(|f| f.std_id() == Some(0x0FF) && f.data()[..2] == [0x00, 0x31]));
}

/// 0x1001 follows the active errors at once, also where no EMCY goes out with the change (the
/// TMI sends 0x0000 only once no error is left, docs/DECISIONS.md).
#[test]
fn tmi_error_register_follows_a_partial_clear() {
    let mut r = booted("tmi");
    r.node.set_error(0x5000, 0x01, [0; 5], true);
    r.node.set_error(0x8110, 0x10, [0; 5], true);
    r.take();
    assert_eq!(r.node.read_object(0x1001, 0), Ok(0x11));
    r.node.set_error(0x8110, 0x10, [0; 5], false);
    assert!(r.take().is_empty(), "no EMCY while an error stays");
    assert_eq!(r.node.read_object(0x1001, 0), Ok(0x01));
}

/// Every sub-index of 0x1003 mirrors the history, the last one (the oldest error kept) too:
/// for each model, as many errors as the table has subs, then each sub read back, newest first.
#[test]
fn cia301_7_5_2_4_every_history_sub_index_holds_its_error() {
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        // The subs 1… the table has, in a row.
        let has = |s: u8| {
            model(name)
                .entries
                .iter()
                .any(|e| e.index == 0x1003 && e.sub == s)
        };
        let subs = (1u8..=8).take_while(|&s| has(s)).count() as u8;
        assert!(subs > 1, "{name}: a history of several entries");
        for k in 0..subs as u16 {
            r.node.set_error(0x5000 + k, 0x01, [0; 5], true);
            r.node.set_error(0x5000 + k, 0x01, [0; 5], false);
        }
        r.take();
        for s in 1..=subs {
            let newest_first = 0x5000 + (subs - s) as u32;
            assert_eq!(
                r.node.read_object(0x1003, s).map(|v| v & 0xFFFF),
                Ok(newest_first),
                "{name}: 1003:{s}"
            );
        }
    }
}
