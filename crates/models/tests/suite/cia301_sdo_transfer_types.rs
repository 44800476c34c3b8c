//! SDO transfer types as a model's switches (CiA 301 §7.2.4): segmented and block transfer are
//! separate features. A model with one and not the other serves the one and refuses the
//! other's initiates with 0x05040001 (`plain`, the firmware with CANopenNode's default
//! services, has segmented transfer but no block transfer). And the expedited answers are the
//! same whether a host's fast path or the general path (a firmware's) gives them.
use crate::common::{hex, Rig};
use canpos_models::th::TH;
use canpos_models::{Features, Model};
use canpos_stack::od::{DefaultValue, Entry};
use canpos_stack::Table;

/// A device name longer than four bytes: its upload needs a segmented or a block transfer.
static NAME: &str = "canpos position sensor";

/// The TH with `segmented` / `block` transfer and a 22-byte device name (0x1008).
fn model(segmented: bool, block: bool) -> &'static Model {
    let entries: Vec<Entry> = TH
        .entries
        .iter()
        .map(|e| match (e.index, e.sub) {
            (0x1008, 0) => Entry {
                default: DefaultValue::Str(&NAME),
                ..*e
            },
            _ => *e,
        })
        .collect();
    Box::leak(Box::new(Model {
        table: Table {
            name: "th-transfer-types",
            entries: Box::leak(entries.into_boxed_slice()),
            features: Features {
                sdo_segmented: segmented,
                sdo_block: block,
                ..TH.features
            },
            ..TH.table
        },
        ..TH
    }))
}

/// 0x05040001 (client/server command specifier not valid) for `mux`.
fn refused(mux: &str) -> Vec<u8> {
    hex(&format!("80 {mux} 01 00 04 05"))
}

#[test]
fn segmented_without_block() {
    let mut r = Rig::booted(model(true, false));
    // Segmented upload of the 22-byte name: size indicated, then 7 + 7 + 7 + 1 bytes.
    assert_eq!(
        r.sdo("40 08 10 00 00 00 00 00"),
        hex("41 08 10 00 16 00 00 00")
    );
    let mut name = Vec::new();
    for (k, last) in [(0u8, false), (1, false), (0, false), (1, true)] {
        let seg = r.sdo(&format!("{:02X} 00 00 00 00 00 00 00", 0x60 | k << 4));
        assert_eq!(seg[0] & 0x10, k << 4, "toggle");
        assert_eq!(seg[0] & 0x01 != 0, last, "c bit");
        let unused = usize::from((seg[0] >> 1) & 0x07);
        name.extend_from_slice(&seg[1..8 - unused]);
    }
    assert_eq!(name, NAME.as_bytes());
    // Segmented download of 0x1017 = 100 ms.
    assert_eq!(
        r.sdo("21 17 10 00 02 00 00 00"),
        hex("60 17 10 00 00 00 00 00")
    );
    assert_eq!(
        r.sdo("0B 64 00 00 00 00 00 00"),
        hex("20 00 00 00 00 00 00 00")
    );
    assert_eq!(
        r.sdo("40 17 10 00 00 00 00 00"),
        hex("4B 17 10 00 64 00 00 00")
    );
    // Block upload (also with a protocol switch) and block download are refused.
    assert_eq!(r.sdo("A0 08 10 00 14 00 00 00"), refused("08 10 00"));
    assert_eq!(r.sdo("A0 08 10 00 14 7F 00 00"), refused("08 10 00"));
    assert_eq!(r.sdo("C2 17 10 00 02 00 00 00"), refused("17 10 00"));
    // Refusals leave no transfer behind: the next upload is served.
    assert!(r.node.sdo_server().transfer().is_none());
    assert_eq!(r.sdo("40 00 10 00 00 00 00 00")[0], 0x43);
}

#[test]
fn block_without_segmented() {
    let mut r = Rig::booted(model(false, true));
    // A plain upload of the 22-byte name needs a segmented transfer: refused.
    assert_eq!(r.sdo("40 08 10 00 00 00 00 00"), refused("08 10 00"));
    assert_eq!(r.sdo("21 17 10 00 02 00 00 00"), refused("17 10 00"));
    // A block upload with a protocol switch at 127 bytes would switch to that plain upload.
    assert_eq!(r.sdo("A0 08 10 00 14 7F 00 00"), refused("08 10 00"));
    // A block upload serves it: initiate (size indicated), start, four segments, end.
    assert_eq!(
        r.sdo("A0 08 10 00 14 00 00 00"),
        hex("C2 08 10 00 16 00 00 00")
    );
    let segs = r.send(0x67F, &hex("A3 00 00 00 00 00 00 00"));
    assert_eq!(segs.len(), 4);
    let mut name = Vec::new();
    for (n, f) in segs.iter().enumerate() {
        let d = f.data();
        assert_eq!(d[0] & 0x7F, n as u8 + 1, "seqno");
        name.extend_from_slice(&d[1..]);
    }
    assert_eq!(segs[3].data()[0] & 0x80, 0x80, "the last segment has c = 1");
    name.truncate(NAME.len());
    assert_eq!(name, NAME.as_bytes());
    // 22 bytes in 4 segments: 6 unused bytes in the last one.
    assert_eq!(
        r.sdo("A2 04 14 00 00 00 00 00"),
        hex("D9 00 00 00 00 00 00 00")
    );
    assert!(r.send(0x67F, &hex("A1 00 00 00 00 00 00 00")).is_empty());
    // A block download of 0x1017 = 100 ms: initiate, one segment, end.
    assert_eq!(r.sdo("C2 17 10 00 02 00 00 00")[0] & 0xE3, 0xA0);
    assert_eq!(
        r.sdo("81 64 00 00 00 00 00 00"),
        hex("A2 01 7F 00 00 00 00 00")
    );
    assert_eq!(
        r.sdo("D5 00 00 00 00 00 00 00"),
        hex("A1 00 00 00 00 00 00 00")
    );
    assert_eq!(
        r.sdo("40 17 10 00 00 00 00 00"),
        hex("4B 17 10 00 64 00 00 00")
    );
}

/// An expedited request while the server is idle (a host's fast path) and the same request
/// while a segmented transfer is open (the general path: a new initiate ends the old transfer
/// and is served as new) get the same answers, refusals included.
#[test]
fn expedited_answers_are_the_same_on_both_paths() {
    let requests = [
        "40 00 10 00 00 00 00 00", // upload 0x1000
        "40 17 10 00 00 00 00 00", // upload 0x1017 (2 bytes)
        "40 08 10 00 00 00 00 00", // upload 0x1008: 22 bytes, segmented initiate
        "40 00 20 00 00 00 00 00", // upload of a missing object
        "40 18 10 09 00 00 00 00", // upload of a missing sub-index
        "2B 17 10 00 C8 00 00 00", // download 0x1017 = 200, size indicated
        "22 17 10 00 2C 01 00 00", // download 0x1017 = 300, size not indicated
        "23 17 10 00 2C 01 00 00", // download of 4 bytes to a 2-byte object
        "2F 17 10 00 2C 00 00 00", // download of 1 byte to a 2-byte object
        "23 00 10 00 00 00 00 00", // download to a read-only object
        "2F 00 20 00 00 00 00 00", // download to a missing object
        "23 14 10 00 00 00 00 00", // download of a restricted COB-ID (0 for EMCY)
    ];
    for req in requests {
        let mut idle = Rig::booted(model(true, true));
        let direct = idle.sdo(req);
        let mut busy = Rig::booted(model(true, true));
        // Open a segmented download of 0x1017 first.
        assert_eq!(busy.sdo("21 17 10 00 02 00 00 00")[0], 0x60);
        assert!(busy.node.sdo_server().transfer().is_some());
        assert_eq!(busy.sdo(req), direct, "answer to {req}");
        // And the same value landed.
        assert_eq!(
            busy.sdo("40 17 10 00 00 00 00 00"),
            idle.sdo("40 17 10 00 00 00 00 00"),
            "0x1017 after {req}"
        );
    }
}
