//! TH / E-Series manual SDO tables (000/001 Tables 8–12), byte-exact on node 0x7F
//! (request 0x67F, response 0x5FF). D8: command bytes and little-endian abort codes.
use crate::common::{hex, Rig};
use canpos_models::th::TH;

/// Table 8 / 9: download with each command byte, answered `60 index sub 00 00 00 00`.
#[test]
fn table_8_9_download_forms() {
    let mut r = Rig::booted(&TH);
    // 0x2B: write 2 bytes (heartbeat 100 ms, the brief's example).
    assert_eq!(
        r.sdo("2B 17 10 00 64 00 00 00"),
        hex("60 17 10 00 00 00 00 00")
    );
    assert_eq!(
        r.sdo("40 17 10 00 00 00 00 00"),
        hex("4B 17 10 00 64 00 00 00")
    );
    // 0x22: size not indicated: the object's own size (2 bytes) is taken, bytes 6–7 ignored.
    assert_eq!(
        r.sdo("22 17 10 00 E8 03 AA BB"),
        hex("60 17 10 00 00 00 00 00")
    );
    assert_eq!(
        r.sdo("40 17 10 00 00 00 00 00"),
        hex("4B 17 10 00 E8 03 00 00")
    );
    // 0x23: write 4 bytes (manual §5.7.4 example: 1800/1 = 0x400001FF, no RTR, valid).
    assert_eq!(
        r.sdo("23 00 18 01 FF 01 00 40"),
        hex("60 00 18 01 00 00 00 00")
    );
    assert_eq!(
        r.sdo("40 00 18 01 00 00 00 00"),
        hex("43 00 18 01 FF 01 00 40")
    );
    // 0x2F: write 1 byte (transmission type 0xFE).
    assert_eq!(
        r.sdo("2F 00 18 02 FE 00 00 00"),
        hex("60 00 18 02 00 00 00 00")
    );
    assert_eq!(
        r.sdo("40 00 18 02 00 00 00 00"),
        hex("4F 00 18 02 FE 00 00 00")
    );
    // 0x2B on the event timer (manual: "1 ms").
    assert_eq!(
        r.sdo("2B 00 18 05 01 00 00 00"),
        hex("60 00 18 05 00 00 00 00")
    );
    assert_eq!(
        r.sdo("40 00 18 05 00 00 00 00"),
        hex("4B 00 18 05 01 00 00 00")
    );
    // 0x27 (3 bytes, not in the manual's table, D8) to a U32 is too short.
    assert_eq!(
        r.sdo("27 05 10 00 80 00 00 00"),
        hex("80 05 10 00 13 00 07 06")
    );
}

/// Table 10 / 11: upload answers 0x43 / 0x4B / 0x4F with the exact size.
#[test]
fn table_10_11_upload_forms() {
    let mut r = Rig::booted(&TH);
    // D1: device type 0x00080196 (one magnet).
    assert_eq!(
        r.sdo("40 00 10 00 00 00 00 00"),
        hex("43 00 10 00 96 01 08 00")
    );
    // 2 bytes: heartbeat time (default 0).
    assert_eq!(r.sdo("40 17 10 00 00 00 00 00")[0], 0x4B);
    // 1 byte: error register.
    assert_eq!(r.sdo("40 01 10 00 00 00 00 00")[0], 0x4F);
    // Any upload-initiate byte 0x40…0x5F is an upload (bits 0–4 reserved).
    assert_eq!(
        r.sdo("41 00 10 00 11 22 33 44"),
        hex("43 00 10 00 96 01 08 00")
    );
    // 4-char strings fit an expedited answer: device name "C304".
    assert_eq!(
        r.sdo("40 08 10 00 00 00 00 00"),
        hex("43 08 10 00 43 33 30 34")
    );
}

/// Table 12: `80 index sub code` with the code little-endian (D8; the manual prints it MSB
/// first), one row per code the manual lists that the TH can produce.
#[test]
fn table_12_abort_layout() {
    let mut r = Rig::booted(&TH);
    let rows = [
        // object does not exist
        ("40 34 12 00 00 00 00 00", "80 34 12 00 00 00 02 06"),
        // sub-index does not exist
        ("40 00 10 01 00 00 00 00", "80 00 10 01 11 00 09 06"),
        // value exceeded (D10: transmission type 241)
        ("2F 00 18 02 F1 00 00 00", "80 00 18 02 30 00 09 06"),
        // attempt to write a read-only object
        ("23 00 10 00 96 01 08 00", "80 00 10 00 02 00 01 06"),
        // data transport error: wrong "save" signature (D7)
        ("23 10 10 01 73 61 76 00", "80 10 10 01 20 00 00 08"),
        // unsupported access: mapping entry while sub 0 ≠ 0
        ("23 00 1A 01 20 01 20 60", "80 00 1A 01 00 00 01 06"),
    ];
    for (req, resp) in rows {
        assert_eq!(r.sdo(req), hex(resp), "request {req}");
    }
}
