//! CiA 301 §7.2.4.3 SDO size rules (TH, node-id 0x7F: requests on 0x67F, answers on 0x5FF).
//! 0x1017 (producer heartbeat time) is an UNSIGNED16: two bytes exactly.

use crate::common::{hex, Rig};
use canpos_models::th::TH;

fn abort(index: u16, sub: u8, code: u32) -> Vec<u8> {
    let mut v = vec![0x80, index as u8, (index >> 8) as u8, sub];
    v.extend_from_slice(&code.to_le_bytes());
    v
}

/// §7.2.4.3.3 (initiate SDO download, segmented): an indicated size that differs from the
/// object's fixed size is refused at initiate, before any segment: too low 0x06070013, too high
/// 0x06070012.
#[test]
fn cia301_7_2_4_3_3_segmented_initiate_with_a_wrong_size_is_refused_at_once() {
    let mut r = Rig::booted(&TH);
    let too_low = r.req(0x67F, &hex("21 17 10 00 01 00 00 00"));
    assert_eq!(too_low, (0x5FF, abort(0x1017, 0, 0x0607_0013)));
    let too_high = r.req(0x67F, &hex("21 17 10 00 03 00 00 00"));
    assert_eq!(too_high, (0x5FF, abort(0x1017, 0, 0x0607_0012)));
    // The right size is accepted, and the object keeps its value throughout.
    assert_eq!(r.req(0x67F, &hex("21 17 10 00 02 00 00 00")).1[0], 0x60);
    r.send(0x67F, &hex("80 17 10 00 00 00 00 00")); // the client aborts
    assert_eq!(
        r.req(0x67F, &hex("40 17 10 00 00 00 00 00")).1,
        hex("4B 17 10 00 00 00 00 00")
    );
}

/// §7.2.4.3.9 (initiate SDO block download): the same size rule as a segmented download.
#[test]
fn cia301_7_2_4_3_9_block_initiate_with_a_wrong_size_is_refused_at_once() {
    let mut r = Rig::booted(&TH);
    let too_low = r.req(0x67F, &hex("C2 17 10 00 01 00 00 00"));
    assert_eq!(too_low, (0x5FF, abort(0x1017, 0, 0x0607_0013)));
    let too_high = r.req(0x67F, &hex("C2 17 10 00 05 00 00 00"));
    assert_eq!(too_high, (0x5FF, abort(0x1017, 0, 0x0607_0012)));
}

/// §7.2.4.3.10 / 0x05040005: a block download of unindicated size whose data, once the last
/// segment is known, exceeds what the server can hold is refused with "out of memory" at the
/// end; nothing (not even an empty value) is written.
#[test]
fn cia301_7_2_4_3_10_block_download_larger_than_the_buffer_is_out_of_memory() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 17 10 00 64 00 00 00")); // 0x1017 = 100
    let ack = r.req(0x67F, &hex("C0 17 10 00 00 00 00 00")); // no size, no CRC
    assert_eq!(ack.1[0], 0xA0);
    // 10 segments of 7 bytes = 70 bytes; the 10th is the last (c = 1).
    let mut answers = Vec::new();
    for seq in 1..=10u8 {
        let c = if seq == 10 { 0x80 } else { 0 };
        answers.extend(r.send(0x67F, &[c | seq, 1, 2, 3, 4, 5, 6, 7]));
    }
    assert_eq!(
        answers.len(),
        1,
        "one acknowledgement, after the last segment"
    );
    assert_eq!(answers[0].data()[..2], [0xA2, 10]);
    // End: n = 0 unused bytes in the last segment, so 70 bytes.
    let end = r.req(0x67F, &hex("C1 00 00 00 00 00 00 00"));
    assert_eq!(end, (0x5FF, abort(0x1017, 0, 0x0504_0005)));
    assert_eq!(
        r.req(0x67F, &hex("40 17 10 00 00 00 00 00")).1,
        hex("4B 17 10 00 64 00 00 00")
    );
}
