//! CiA 301 §7.3.3 pre-defined connection set: a device whose dictionary lacks the COB-ID object
//! of a service (0x1005 SYNC, 0x1014 EMCY, 0x100E guarding: all optional, e.g. on a device built
//! from an EDS that leaves them out) uses the pre-defined COB-ID: SYNC 0x080, EMCY 0x080 +
//! node-id, node guarding 0x700 + node-id.

use crate::common::{hex, Rig};
use canpos_models::th::TH;
use canpos_models::Model;
use canpos_stack::Frame;
use canpos_stack::Table;

/// The TH without the objects `drop`.
fn th_without(drop: &[u16]) -> &'static Model {
    let entries: Vec<_> = TH
        .entries
        .iter()
        .filter(|e| !drop.contains(&e.index))
        .copied()
        .collect();
    let keys: Vec<u32> = entries.iter().map(|e| e.key()).collect();
    Box::leak(Box::new(Model {
        table: Table {
            name: "th-predefined",
            entries: Box::leak(entries.into_boxed_slice()),
            keys: Box::leak(keys.into_boxed_slice()),
            ..TH.table
        },
        ..TH
    }))
}

#[test]
fn cia301_7_3_3_without_the_cob_id_objects_the_predefined_ones_apply() {
    let m = th_without(&[0x1005, 0x1014, 0x100E]);
    let mut r = Rig::new(m);
    let boot = r.take();
    assert_eq!(boot[0].std_id(), Some(0x77F));
    assert!(
        r.node.read_object(0x1014, 0).is_err(),
        "no 0x1014 in this dictionary"
    );
    // EMCY on 0x080 + node-id.
    r.node.set_error(0x3100, 0x04, [0; 5], true);
    let e = r.take();
    assert_eq!(e.len(), 1);
    assert_eq!(
        (e[0].std_id(), &e[0].data()[..2]),
        (Some(0x0FF), &[0x00, 0x31][..])
    );
    // Node guarding on 0x700 + node-id.
    let f = Frame::remote(0x77F, false, 1).unwrap();
    r.node.handle_frame(&f, r.now);
    let g = r.take();
    assert_eq!(g.len(), 1);
    assert_eq!((g[0].std_id(), g[0].data()), (Some(0x77F), &[0x7F][..]));
    // SYNC on 0x080.
    r.req(0x67F, &hex("2F 00 18 02 01 00 00 00"));
    r.send(0x000, &[0x01, 0x7F]);
    r.take();
    let s = r.send(0x080, &[]);
    assert_eq!(s.len(), 1);
    assert_eq!(s[0].std_id(), Some(0x1FF));
}
