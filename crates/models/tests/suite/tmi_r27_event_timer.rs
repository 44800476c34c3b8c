//! TMI R27 (002 §1.2.5, §1.14 "Insufficient Event Timer Value"): TPDO1's event timer is too
//! short when it ends before one worst-case frame of TPDO1's length at the active bit rate:
//! 47 + 8n bits plus the stuff bits of the 34 + 8n stuffable bits ((34 + 8n − 1) / 4), i.e.
//! 55 + 10n bits for n data bytes. Only a valid, event-driven (254 / 255) TPDO1 with an event
//! timer is checked.

use crate::common::Rig;
use canpos_models as models;

/// A TMI at `kbps`, booted.
fn tmi_at(kbps: u16) -> Rig {
    let t = models::by_name("tmi").unwrap();
    let mut r = Rig::with_config(t, t.default_config.with_bitrate(kbps));
    r.take();
    r
}

/// Maps objects to TPDO1 that make `n` data bytes (CiA 301 procedure: invalidate, count 0,
/// entries, count, valid again).
fn map_bytes(r: &mut Rig, n: u32) {
    let objects: &[u32] = match n {
        0 => &[],
        1 => &[0x6300_0108],
        2 => &[0x6030_0110],
        3 => &[0x6030_0110, 0x6300_0108],
        4 => &[0x6020_0120],
        5 => &[0x6020_0120, 0x6300_0108],
        6 => &[0x6020_0120, 0x6030_0110],
        7 => &[0x6020_0120, 0x6030_0110, 0x6300_0108],
        _ => &[0x6020_0120, 0x6030_0110, 0x6300_0108, 0x6400_0108],
    };
    let cob = r.read(0x1800, 1);
    r.write(0x1800, 1, cob | 0x8000_0000, 4);
    r.write(0x1A00, 0, 0, 1);
    for (k, &o) in objects.iter().enumerate() {
        r.write(0x1A00, k as u8 + 1, o, 4);
    }
    r.write(0x1A00, 0, objects.len() as u32, 1);
    r.write(0x1800, 1, cob & !0x8000_0000, 4);
}

/// Whether a measurement cycle finds the event timer insufficient (0x1002 bit 15).
fn insufficient(r: &mut Rig) -> bool {
    r.cycle(Some(1_000_000));
    r.read(0x1002, 0) & (1 << 15) != 0
}

#[test]
fn the_worst_case_frame_is_55_plus_10_bits_per_byte() {
    // At 10 kbit/s a bit is 100 µs: n bytes take 5.5 + n ms, so an event timer of 5 + n ms is
    // too short and 6 + n ms is enough.
    let mut r = tmi_at(10);
    for n in 0..=8u32 {
        map_bytes(&mut r, n);
        r.write(0x1800, 5, 5 + n, 2);
        assert!(insufficient(&mut r), "{n} bytes, {} ms", 5 + n);
        r.write(0x1800, 5, 6 + n, 2);
        assert!(!insufficient(&mut r), "{n} bytes, {} ms", 6 + n);
    }
}

#[test]
fn a_timer_as_long_as_the_frame_is_enough() {
    // 125 kbit/s, 7 bytes: 125 bits = exactly 1 ms, the 1 ms timer is not shorter.
    let mut r = tmi_at(125);
    map_bytes(&mut r, 7);
    r.write(0x1800, 5, 1, 2);
    assert!(!insufficient(&mut r));
    map_bytes(&mut r, 8);
    assert!(insufficient(&mut r), "135 bits = 1.08 ms");
}

#[test]
fn only_a_valid_event_driven_tpdo1_with_a_timer_is_checked() {
    let mut r = tmi_at(10);
    map_bytes(&mut r, 8);
    r.write(0x1800, 5, 1, 2);
    for ttype in [254, 255] {
        r.write(0x1800, 2, ttype, 1);
        assert!(insufficient(&mut r), "transmission type {ttype}");
    }
    // Synchronous: the event timer does not drive it.
    r.write(0x1800, 2, 1, 1);
    assert!(!insufficient(&mut r), "synchronous");
    r.write(0x1800, 2, 254, 1);
    // Not valid: nothing is sent at all.
    let cob = r.read(0x1800, 1);
    r.write(0x1800, 1, cob | 0x8000_0000, 4);
    assert!(!insufficient(&mut r), "TPDO1 not valid");
    r.write(0x1800, 1, cob, 4);
    assert!(insufficient(&mut r));
    // Event timer 0: no timer to be too short.
    r.write(0x1800, 5, 0, 2);
    assert!(!insufficient(&mut r), "no event timer");
}
