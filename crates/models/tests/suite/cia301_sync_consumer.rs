//! CiA 301 §7.2.5 SYNC consumer: which frames on the SYNC COB-ID (0x1005) are SYNC objects, and
//! the "unexpected SYNC data length" EMCY (0x8240, §7.2.7.1) where the manual lists it.

use crate::common::{hex, Rig};
use canpos_models::{by_name, Model};
use canpos_stack::Frame;

/// Operational, TPDO1 synchronous on every SYNC (transmission type 1).
fn sync_type_1(model: &'static Model) -> Rig {
    let mut r = Rig::booted(model);
    r.req(0x67F, &hex("2F 00 18 02 01 00 00 00"));
    r.send(0x000, &[0x01, 0x7F]);
    r.take();
    r
}

fn count(frames: &[Frame], id: u16) -> usize {
    frames.iter().filter(|f| f.std_id() == Some(id)).count()
}

/// §7.2.5.2: the SYNC carries no data, or one byte (the counter, which a consumer without 0x1019
/// ignores): both trigger the synchronous TPDO.
#[test]
fn cia301_7_2_5_sync_without_data_or_with_a_counter_triggers() {
    for name in ["th", "e-series", "tmi"] {
        let mut r = sync_type_1(by_name(name).unwrap());
        assert_eq!(count(&r.send(0x080, &[]), 0x1FF), 1, "{name}: DLC 0");
        assert_eq!(count(&r.send(0x080, &[7]), 0x1FF), 1, "{name}: DLC 1");
    }
}

/// §7.2.5 / §7.2.7.1: a SYNC longer than the counter is not a SYNC object: no TPDO. TH and
/// E-Series report it with EMCY 0x8240 "unexpected SYNC data length" (a one-shot event); the
/// TMI's EMCY table has no such code, so it ignores the frame.
#[test]
fn cia301_7_2_7_sync_with_a_wrong_length_is_no_sync() {
    for name in ["th", "e-series"] {
        let mut r = sync_type_1(by_name(name).unwrap());
        let out = r.send(0x080, &[1, 2]);
        assert_eq!(count(&out, 0x1FF), 0, "{name}: no TPDO");
        let emcy: Vec<_> = out.iter().filter(|f| f.std_id() == Some(0x0FF)).collect();
        assert_eq!(emcy.len(), 1, "{name}: {out:?}");
        assert_eq!(emcy[0].data()[..2], [0x40, 0x82], "{name}");
    }
    let mut r = sync_type_1(by_name("tmi").unwrap());
    assert!(r.send(0x080, &[1, 2]).is_empty(), "TMI: nothing");
}

/// §7.2.5: the SYNC object is a data frame; a remote request on the SYNC COB-ID asks for no PDO
/// and triggers none.
#[test]
fn cia301_7_2_5_a_remote_frame_on_the_sync_cob_id_is_no_sync() {
    for name in ["th", "e-series", "tmi"] {
        let mut r = sync_type_1(by_name(name).unwrap());
        let f = Frame::remote(0x080, false, 0).unwrap();
        r.node.handle_frame(&f, r.now);
        assert!(r.take().is_empty(), "{name}");
        // And the next real SYNC is the first one the node counts.
        assert_eq!(count(&r.send(0x080, &[]), 0x1FF), 1, "{name}");
    }
}

/// §7.2.5: SYNC is served in pre-operational and operational only; a stopped node neither sends
/// the synchronous TPDO nor the length EMCY.
#[test]
fn cia301_7_2_5_a_stopped_node_ignores_sync() {
    let mut r = sync_type_1(by_name("th").unwrap());
    r.send(0x000, &[0x02, 0x7F]);
    r.take();
    assert!(r.send(0x080, &[]).is_empty());
    assert!(r.send(0x080, &[1, 2]).is_empty());
}
