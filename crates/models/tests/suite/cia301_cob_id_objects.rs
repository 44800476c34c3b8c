//! CiA 301 §7.5.2.5 (0x1005 COB-ID SYNC), §7.5.2.17 (0x1014 COB-ID EMCY) and the TH's 0x100E
//! (COB-ID guarding, TH Table 15; docs/DECISIONS.md): which values a write may set, with the
//! restricted CAN-IDs of §7.3.5 (conformance OTH-10). A refused write answers 0x06090030 and
//! changes nothing; an accepted one moves the service.

use crate::common::{hex, Rig};
use canpos_models::th::TH;
use canpos_stack::Frame;

const INVALID_VALUE: u32 = 0x0609_0030;

/// Expedited 4-byte write: `None` if accepted, else the abort code.
fn write(r: &mut Rig, index: u16, v: u32) -> Option<u32> {
    r.download(index, 0, v, 4).err()
}

/// 0x1005: the node is a SYNC consumer only, so bit 30 ("generates SYNC") cannot be set; bit 29
/// (29-bit CAN-ID) is not supported; a restricted CAN-ID is refused. An 11-bit CAN-ID that is
/// free moves the consumer.
#[test]
fn cia301_7_5_2_5_cob_id_sync_values() {
    let mut r = Rig::booted(&TH);
    for bad in [
        0x4000_0080,
        0x2000_0080,
        0x6000_0081,
        0x0000_0701,
        0x0000_0001,
        // Bits 11–28 belong to 29-bit ids only.
        0x0000_0880,
        0x1000_0080,
    ] {
        assert_eq!(write(&mut r, 0x1005, bad), Some(INVALID_VALUE), "{bad:#x}");
        assert_eq!(r.read(0x1005, 0), 0x80, "{bad:#x} changed nothing");
    }
    assert_eq!(write(&mut r, 0x1005, 0x0000_0090), None);
    r.req(0x67F, &hex("2F 00 18 02 01 00 00 00"));
    r.send(0x000, &[0x01, 0x7F]);
    r.take();
    assert!(r.send(0x080, &[]).is_empty());
    assert_eq!(r.send(0x090, &[]).len(), 1, "SYNC now on 0x090");
}

fn emcy_on(r: &mut Rig) -> Vec<u16> {
    r.node.set_error(0x5000, 0x01, [0; 5], true);
    r.node.set_error(0x5000, 0x01, [0; 5], false);
    r.take().iter().filter_map(|f| f.std_id()).collect()
}

/// 0x1014: bits 29 and 30 (reserved) are refused, and so are bits 11–28 (29-bit ids only),
/// whatever bit 31 says; a valid COB-ID (bit 31 = 0) may not carry a restricted CAN-ID,
/// an invalid one may; and while the EMCY is valid its CAN-ID cannot change ("bits 0–29 shall
/// not be changed while the object exists"): invalidate first, change, validate.
#[test]
fn cia301_7_5_2_17_cob_id_emcy_values() {
    let mut r = Rig::booted(&TH);
    assert_eq!(r.read(0x1014, 0), 0xFF);
    for bad in [
        0x2000_00FF,
        0x0000_0701,
        0x0000_0001,
        0x0000_00A0,
        0x4000_00FF,
        0x0000_08FF,
        0x1000_00FF,
        0x8000_08FF,
        0xC000_00FF,
    ] {
        assert_eq!(write(&mut r, 0x1014, bad), Some(INVALID_VALUE), "{bad:#x}");
        assert_eq!(r.read(0x1014, 0), 0xFF, "{bad:#x} changed nothing");
    }
    assert_eq!(
        write(&mut r, 0x1014, 0x0000_00FF),
        None,
        "same CAN-ID: no change"
    );
    assert_eq!(write(&mut r, 0x1014, 0x8000_00FF), None, "invalidate");
    assert!(emcy_on(&mut r).is_empty(), "no EMCY while invalid");
    assert_eq!(
        write(&mut r, 0x1014, 0x8000_0701),
        None,
        "restricted, but invalid"
    );
    assert_eq!(write(&mut r, 0x1014, 0x0000_0701), Some(INVALID_VALUE));
    assert_eq!(write(&mut r, 0x1014, 0x8000_00A0), None);
    assert_eq!(
        write(&mut r, 0x1014, 0x0000_00A0),
        None,
        "validate on the new CAN-ID"
    );
    assert_eq!(emcy_on(&mut r), [0x0A0, 0x0A0]);
}

fn guard_answer(r: &mut Rig, id: u16) -> Vec<Frame> {
    let f = Frame::remote(u32::from(id), false, 1).unwrap();
    r.node.handle_frame(&f, r.now);
    r.take()
}

/// 0x100E (TH): bits 30 and 29 are refused, and so are bits 11–28 (29-bit ids only) and a
/// restricted CAN-ID other than the pre-defined 0x700 + node-id, which stays allowed.
#[test]
fn th_cob_id_guarding_values() {
    let mut r = Rig::booted(&TH);
    for bad in [
        0x4000_0300,
        0x2000_0300,
        0x0000_077E,
        0x0000_0701,
        0x0000_0001,
        0x0000_0B00,
        0x1000_0300,
    ] {
        assert_eq!(write(&mut r, 0x100E, bad), Some(INVALID_VALUE), "{bad:#x}");
        assert_eq!(r.read(0x100E, 0), 0x77F, "{bad:#x} changed nothing");
    }
    assert_eq!(write(&mut r, 0x100E, 0x0000_0300), None);
    assert_eq!(guard_answer(&mut r, 0x300).len(), 1);
    assert_eq!(
        write(&mut r, 0x100E, 0x0000_077F),
        None,
        "back to the pre-defined one"
    );
    assert_eq!(guard_answer(&mut r, 0x77F).len(), 1);
    assert!(guard_answer(&mut r, 0x300).is_empty());
}

/// Guarding and SYNC on one CAN-ID: zero-length data frames count as guard requests (D22), so
/// every SYNC would be answered as one. Neither COB-ID may take the other's CAN-ID (0x100E has
/// no "not valid" bit, so its bit 31 does not help), neither by a write nor from the state file
/// (there guarding keeps its default). A SYNC on 0x080 then still triggers the synchronous
/// TPDO and draws no guarding answer.
#[test]
fn th_guarding_and_sync_never_share_a_can_id() {
    let mut r = Rig::booted(&TH);
    for bad in [0x0000_0080, 0x8000_0080] {
        assert_eq!(write(&mut r, 0x100E, bad), Some(INVALID_VALUE), "{bad:#x}");
        assert_eq!(r.read(0x100E, 0), 0x77F, "{bad:#x} changed nothing");
    }
    assert_eq!(write(&mut r, 0x1005, 0x300), None);
    assert_eq!(write(&mut r, 0x100E, 0x300), Some(INVALID_VALUE));
    assert_eq!(write(&mut r, 0x100E, 0x310), None);
    assert_eq!(write(&mut r, 0x1005, 0x310), Some(INVALID_VALUE));
    assert_eq!(r.read(0x1005, 0), 0x300);
    assert_eq!(write(&mut r, 0x1005, 0x080), None);
    // TPDO1 synchronous, operational: a SYNC (DLC 0) on 0x080 sends it, and nothing on 0x080.
    r.req(0x67F, &hex("2F 00 18 02 01 00 00 00"));
    r.send(0x000, &[0x01, 0x7F]);
    r.take();
    let out = r.send(0x080, &[]);
    let ids: Vec<u16> = out.iter().filter_map(|f| f.std_id()).collect();
    assert_eq!(ids, [0x1FF], "the TPDO only: {out:?}");

    // From the state file: guarding on SYNC's CAN-ID keeps its default.
    use canpos_stack::storage::{ImageWriter, RamStorage, Storage, IMAGE_MAX};
    use canpos_stack::{Instant, Node};
    let boot = |records: &[(u16, u32)]| {
        let mut image = [0u8; IMAGE_MAX];
        let mut w = ImageWriter::new(&mut image, TH.features.tag);
        for &(index, v) in records {
            assert!(w.push(u32::from(index) << 8, v));
        }
        let n = w.finish();
        let mut ram = RamStorage::default();
        ram.save(&image[..n]).unwrap();
        let mut node = Node::new(&TH, TH.default_config, ram);
        node.power_on(Instant::ZERO);
        let get = |node: &mut canpos_models::SensorNode<RamStorage>, i| node.read_object(i, 0);
        (
            get(&mut node, 0x1005).unwrap(),
            get(&mut node, 0x100E).unwrap(),
        )
    };
    assert_eq!(boot(&[(0x100E, 0x080)]), (0x080, 0x77F));
    assert_eq!(boot(&[(0x1005, 0x300), (0x100E, 0x300)]), (0x300, 0x77F));
    assert_eq!(boot(&[(0x100E, 0x300), (0x1005, 0x300)]), (0x300, 0x77F));
    assert_eq!(boot(&[(0x1005, 0x300), (0x100E, 0x310)]), (0x300, 0x310));
}
