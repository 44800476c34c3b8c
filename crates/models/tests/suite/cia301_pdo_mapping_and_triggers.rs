//! CiA 301 §7.2.2 TPDO rules (SPEC §5, D10) as a master sees them on a TH (node-id 0x7F: SDO
//! 0x67F / 0x5FF, TPDO1 on 0x1FF, TPDO2 on 0x2FF once valid; TMI for its R27): what a mapping puts in the frame,
//! which mappings and COB-IDs are refused, transmission types, remote requests, and the
//! timers of several TPDOs at once.

use crate::common::{booted, Rig};
use canpos_encoder::Sample;
use canpos_models::th::TH;
use canpos_stack::{Frame, Instant};

/// Expedited write of `size` bytes: `None` if accepted, else the abort code.
fn write(r: &mut Rig, index: u16, sub: u8, v: u32, size: usize) -> Option<u32> {
    r.download(index, sub, v, size).err()
}

fn w32(r: &mut Rig, index: u16, sub: u8, v: u32) -> Option<u32> {
    write(r, index, sub, v, 4)
}

fn w8(r: &mut Rig, index: u16, sub: u8, v: u8) -> Option<u32> {
    write(r, index, sub, v.into(), 1)
}

fn w16(r: &mut Rig, index: u16, sub: u8, v: u16) -> Option<u32> {
    write(r, index, sub, v.into(), 2)
}

/// Maps `entries` into TPDO `n` (0-based) the manuals' way: count 0, entries, count.
fn map(r: &mut Rig, n: u16, entries: &[u32]) {
    let mi = 0x1A00 + n;
    assert_eq!(w8(r, mi, 0, 0), None);
    for (k, &e) in entries.iter().enumerate() {
        assert_eq!(w32(r, mi, k as u8 + 1, e), None, "entry {k} {e:08X}");
    }
    assert_eq!(w8(r, mi, 0, entries.len() as u8), None);
}

fn start(r: &mut Rig) {
    r.send(0x000, &[0x01, 0x7F]);
}

fn sample(r: &mut Rig, nm: i64) {
    let mut s = Sample {
        temperature_c: 25,
        ..Default::default()
    };
    s.positions_nm[0] = Some(nm);
    r.node.update_sample(&s, r.now);
}

fn on(frames: &[(Instant, Frame)], id: u16) -> Vec<(u64, Vec<u8>)> {
    frames
        .iter()
        .filter(|(_, f)| f.std_id() == Some(id))
        .map(|(t, f)| (t.micros(), f.data().to_vec()))
        .collect()
}

/// §7.2.2.1 / §7.5.2.37: the mapped objects follow each other in the frame in mapping order,
/// each as the low bytes (little-endian) of its value, as many as the entry's length says; the
/// frame is as long as the mapped bytes.
#[test]
fn cia301_7_5_2_37_mapped_values_fill_the_frame_in_order_and_length() {
    let layouts: [&[u32]; 3] = [
        &[0x6020_0108, 0x6020_0110, 0x6020_0120, 0x6020_0108],
        &[0x6020_0118, 0x6020_0120, 0x6020_0108],
        &[0x6020_0110, 0x6300_0108],
    ];
    for layout in layouts {
        let mut r = Rig::booted(&TH);
        // The preset makes the position a value with four distinct non-zero bytes.
        assert_eq!(w32(&mut r, 0x6010, 1, 0x1234_5678), None);
        map(&mut r, 0, layout);
        start(&mut r);
        for _ in 0..5 {
            r.advance_ms(1);
            sample(&mut r, 100_000_000);
            r.take();
        }
        let pos = r.read(0x6020, 1).to_le_bytes();
        let cam = r.read(0x6300, 1).to_le_bytes();
        assert!(pos.iter().all(|&b| b != 0), "{pos:02X?}");
        let mut want = Vec::new();
        for &e in layout {
            let v = if e >> 16 == 0x6020 { pos } else { cam };
            want.extend_from_slice(&v[..(e & 0xFF) as usize / 8]);
        }
        let got = on(&r.advance_ms(1), 0x1FF);
        assert_eq!(got.len(), 1, "{layout:08X?}");
        assert_eq!(got[0].1, want, "{layout:08X?}");
        assert_eq!(r.read(0x6020, 1).to_le_bytes(), pos);
    }
}

/// §7.5.2.37 / SPEC §5: a PDO carries at most 64 bits (0x06040042), sub 0 cannot count more
/// entries than the record has (0x06040042) or an empty one (0x06040041, DECISIONS), entries
/// change only while sub 0 is 0 (0x06010000); the mapping keeps its value after every refusal.
#[test]
fn cia301_7_5_2_37_mapping_count_rules() {
    let mut r = Rig::booted(&TH);
    assert_eq!(w8(&mut r, 0x1A00, 0, 0), None);
    for k in 1..=3 {
        assert_eq!(w32(&mut r, 0x1A00, k, 0x6020_0120), None);
    }
    assert_eq!(w32(&mut r, 0x1A00, 4, 0), None);
    assert_eq!(w8(&mut r, 0x1A00, 0, 3), Some(0x0604_0042), "96 bits");
    assert_eq!(w8(&mut r, 0x1A00, 0, 4), Some(0x0604_0041), "entry 4 empty");
    assert_eq!(w8(&mut r, 0x1A00, 0, 9), Some(0x0604_0042), "8 entries");
    assert_eq!(r.node.read_object(0x1A00, 0), Ok(0));
    assert_eq!(w8(&mut r, 0x1A00, 0, 2), None, "64 bits fit");
    assert_eq!(
        w32(&mut r, 0x1A00, 1, 0x6020_0110),
        Some(0x0601_0000),
        "sub 0 is not 0"
    );
    assert_eq!(r.node.read_object(0x1A00, 1), Ok(0x6020_0120));
    // Eight one-byte entries: the most the record holds, exactly 64 bits.
    assert_eq!(w8(&mut r, 0x1A00, 0, 0), None);
    for k in 1..=8 {
        assert_eq!(w32(&mut r, 0x1A00, k, 0x6020_0108), None);
    }
    assert_eq!(w8(&mut r, 0x1A00, 0, 8), None);
    start(&mut r);
    let f = on(&r.advance_ms(1), 0x1FF);
    assert_eq!(f.len(), 1);
    assert_eq!(f[0].1.len(), 8);
    // The other TPDOs' mapping records follow the same rules.
    assert_eq!(w32(&mut r, 0x1A03, 1, 0x6020_0420), None, "0x1A03 is empty");
    assert_eq!(w32(&mut r, 0x1A01, 1, 0x6020_0220), Some(0x0601_0000));
}

/// §7.5.2.37: only objects the dictionary marks mappable can be mapped (0x06040041), and only
/// objects that exist (0x06020000 / 0x06090011).
#[test]
fn cia301_7_5_2_37_only_existing_mappable_objects_map() {
    let mut r = Rig::booted(&TH);
    assert_eq!(w8(&mut r, 0x1A00, 0, 0), None);
    // Preset (rw, not mappable), device type (const), heartbeat time.
    for e in [0x6010_0120, 0x1000_0020, 0x1017_0010] {
        assert_eq!(w32(&mut r, 0x1A00, 1, e), Some(0x0604_0041), "{e:08X}");
    }
    assert_eq!(w32(&mut r, 0x1A00, 1, 0x6021_0120), Some(0x0602_0000));
    assert_eq!(w32(&mut r, 0x1A00, 1, 0x6020_3F20), Some(0x0609_0011));
    // Speed (INTEGER16) takes 16 bits, not 32; cam state (UNSIGNED8) 8, not 16.
    assert_eq!(w32(&mut r, 0x1A00, 1, 0x6030_0120), Some(0x0604_0041));
    assert_eq!(w32(&mut r, 0x1A00, 1, 0x6300_0110), Some(0x0604_0041));
    assert_eq!(w32(&mut r, 0x1A00, 1, 0x6030_0110), None);
    assert_eq!(w32(&mut r, 0x1A00, 2, 0x6300_0108), None);
    assert_eq!(w32(&mut r, 0x1A00, 3, 0x6020_0120), None);
    assert_eq!(w8(&mut r, 0x1A00, 0, 3), None);
}

/// §7.5.2.35 COB-ID: bit 29 (29-bit CAN-ID) is not supported, bits 11–28 are 0 in an 11-bit
/// COB-ID, and a valid PDO may not use a
/// restricted CAN-ID (Table 72); an invalid one may hold any 11-bit CAN-ID. Every TPDO's record
/// follows the rule.
#[test]
fn cia301_7_5_2_35_extended_and_restricted_can_ids_are_refused() {
    let mut r = Rig::booted(&TH);
    assert_eq!(
        w32(&mut r, 0x1800, 1, 0xA000_01FF),
        Some(0x0609_0030),
        "bit 29"
    );
    assert_eq!(
        w32(&mut r, 0x1800, 1, 0x2000_01FF),
        Some(0x0609_0030),
        "bit 29"
    );
    for stray in [0x8000_09FF, 0x0000_09FF, 0x9000_01FF, 0x4010_01FF] {
        assert_eq!(
            w32(&mut r, 0x1800, 1, stray),
            Some(0x0609_0030),
            "{stray:#x}: bits 11–28 belong to 29-bit ids"
        );
    }
    assert_eq!(r.read(0x1800, 1), 0x1FF, "refused writes changed nothing");
    for n in 0..4u16 {
        let ci = 0x1800 + n;
        assert_eq!(w32(&mut r, ci, 1, 0x8000_0000 | (0x1FF + n as u32)), None);
        for id in [
            0x000, 0x001, 0x07F, 0x101, 0x180, 0x581, 0x5FF, 0x601, 0x67F, 0x6E0, 0x6FF, 0x701,
            0x77F, 0x780, 0x7FF,
        ] {
            assert_eq!(
                w32(&mut r, ci, 1, id),
                Some(0x0609_0030),
                "{ci:04X} {id:03X}"
            );
            assert_eq!(
                w32(&mut r, ci, 1, 0x8000_0000 | id),
                None,
                "{id:03X} invalid"
            );
        }
        for id in [0x080, 0x100, 0x181, 0x580, 0x600, 0x680, 0x6DF, 0x700] {
            assert_eq!(w32(&mut r, ci, 1, 0x8000_0000 | id), None);
            assert_eq!(w32(&mut r, ci, 1, id), None, "{ci:04X} {id:03X}");
            assert_eq!(w32(&mut r, ci, 1, 0x8000_0000 | id), None);
        }
    }
}

/// D10: transmission types 0…240, 254 and 255 are accepted, 241…253 refused (0x06090030) and
/// the type kept.
#[test]
fn d10_reserved_transmission_types_are_refused() {
    let mut r = Rig::booted(&TH);
    for t in [0u8, 1, 240, 254, 255] {
        assert_eq!(w8(&mut r, 0x1800, 2, t), None, "{t}");
        assert_eq!(r.node.read_object(0x1800, 2), Ok(u32::from(t)));
    }
    for t in [241u8, 247, 253] {
        assert_eq!(w8(&mut r, 0x1801, 2, 254), None);
        assert_eq!(w8(&mut r, 0x1801, 2, t), Some(0x0609_0030), "{t}");
        assert_eq!(r.node.read_object(0x1801, 2), Ok(254));
    }
}

fn sync(r: &mut Rig) -> usize {
    r.send(0x080, &[])
        .iter()
        .filter(|f| f.std_id() == Some(0x1FF))
        .count()
}

/// SPEC §5 / D10 type 0 (acyclic synchronous): sent on a SYNC only when a mapped value changed
/// since the last one; 240: every 240th SYNC; none before Operational.
#[test]
fn cia301_7_2_2_acyclic_synchronous_sends_on_sync_after_a_change() {
    let mut r = Rig::booted(&TH);
    assert_eq!(w8(&mut r, 0x1800, 2, 0), None);
    assert_eq!(sync(&mut r), 0, "pre-operational");
    start(&mut r);
    r.take();
    assert_eq!(
        sync(&mut r),
        1,
        "the values are new on entering Operational"
    );
    assert_eq!(sync(&mut r), 0, "nothing changed");
    assert!(on(&r.advance_ms(20), 0x1FF).is_empty(), "no timer");
    sample(&mut r, 50_000_000);
    r.take();
    r.advance_ms(1);
    sample(&mut r, 60_000_000);
    r.take();
    assert_eq!(sync(&mut r), 1, "the position changed");
    assert_eq!(sync(&mut r), 0);

    let mut r = Rig::booted(&TH);
    assert_eq!(w8(&mut r, 0x1800, 2, 240), None);
    start(&mut r);
    r.take();
    let sent: Vec<usize> = (1..=480).filter(|_| sync(&mut r) == 1).collect();
    assert_eq!(sent.len(), 2);
}

/// A second valid TPDO (TH TPDO2: COB-ID 0x2FF, channel 2's values) runs its own timers next
/// to TPDO1's; at a common expiry they leave in TPDO order.
#[test]
fn cia301_7_2_2_two_tpdos_keep_their_own_event_timers() {
    let mut r = Rig::booted(&TH);
    assert_eq!(w16(&mut r, 0x1800, 5, 10), None);
    assert_eq!(w32(&mut r, 0x1801, 1, 0x0000_02FF), None);
    assert_eq!(w16(&mut r, 0x1801, 5, 15), None);
    r.advance_ms(3);
    start(&mut r);
    r.take();
    let f = r.advance_ms(60);
    let seq: Vec<(u64, u16)> = f
        .iter()
        .filter_map(|(t, f)| {
            let id = f.std_id()?;
            (id == 0x1FF || id == 0x2FF).then_some((t.micros() / 1000, id))
        })
        .collect();
    assert_eq!(
        seq,
        [
            (13, 0x1FF),
            (18, 0x2FF),
            (23, 0x1FF),
            (33, 0x1FF),
            (33, 0x2FF),
            (43, 0x1FF),
            (48, 0x2FF),
            (53, 0x1FF),
            (63, 0x1FF),
            (63, 0x2FF),
        ]
    );
    // TPDO2 no longer valid: TPDO1 alone, on its grid.
    assert_eq!(w32(&mut r, 0x1801, 1, 0x8000_02FF), None);
    let f = r.advance_ms(30);
    let t: Vec<u64> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x1FF) || f.std_id() == Some(0x2FF))
        .map(|(t, f)| {
            assert_eq!(f.std_id(), Some(0x1FF));
            t.micros() / 1000
        })
        .collect();
    assert_eq!(t, [73, 83, 93]);
}

/// §7.2.2 / SPEC §5: the event timer starts when the node enters Operational and a changed
/// event timer restarts it from the write; stopping ends production.
#[test]
fn cia301_7_2_2_event_timer_runs_from_operational_and_restarts_when_written() {
    let mut r = Rig::booted(&TH);
    assert_eq!(w16(&mut r, 0x1800, 5, 10), None);
    r.advance_ms(7);
    start(&mut r);
    r.take();
    let t: Vec<u64> = on(&r.advance_ms(30), 0x1FF)
        .iter()
        .map(|(t, _)| t / 1000)
        .collect();
    assert_eq!(t, [17, 27, 37]);
    r.advance_ms(2); // t = 39
    assert_eq!(w16(&mut r, 0x1800, 5, 4), None);
    let t: Vec<u64> = on(&r.advance_ms(10), 0x1FF)
        .iter()
        .map(|(t, _)| t / 1000)
        .collect();
    assert_eq!(t, [43, 47]);
    r.send(0x000, &[0x02, 0x7F]);
    assert!(on(&r.advance_ms(20), 0x1FF).is_empty(), "stopped");
}

fn rtr(r: &mut Rig, id: u16) -> Vec<Frame> {
    let f = Frame::remote(u32::from(id), false, 8).unwrap();
    r.node.handle_frame(&f, r.now);
    r.take()
}

/// §7.5.2.35 bit 30 / TH Table 16: a remote request for a TPDO's CAN-ID is answered with the
/// TPDO at once when RTR is allowed (bit 30 clear) and the node is Operational; not with bit
/// 30 set, not for an invalid TPDO, not for another CAN-ID.
#[test]
fn cia301_7_2_2_remote_requests_are_answered_where_rtr_is_allowed() {
    let mut r = Rig::booted(&TH);
    assert_eq!(w16(&mut r, 0x1800, 5, 0), None, "no event timer");
    assert!(rtr(&mut r, 0x1FF).is_empty(), "pre-operational");
    start(&mut r);
    r.take();
    r.advance_ms(3);
    let a = rtr(&mut r, 0x1FF);
    assert_eq!(a.len(), 1);
    assert_eq!(
        (a[0].std_id(), a[0].dlc(), a[0].is_remote()),
        (Some(0x1FF), 7, false),
        "position, speed, cam state"
    );
    assert!(rtr(&mut r, 0x1FE).is_empty());
    assert!(rtr(&mut r, 0x2FF).is_empty(), "TPDO2 is not valid");
    assert_eq!(w32(&mut r, 0x1800, 1, 0x4000_01FF), None, "bit 30: no RTR");
    assert!(rtr(&mut r, 0x1FF).is_empty());
    assert_eq!(w32(&mut r, 0x1800, 1, 0x8000_01FF), None);
    assert!(rtr(&mut r, 0x1FF).is_empty(), "not valid");
    assert_eq!(w32(&mut r, 0x1800, 1, 0x0000_01FF), None);
    assert_eq!(rtr(&mut r, 0x1FF).len(), 1);
    // TPDO2 made valid with RTR allowed answers on its own CAN-ID.
    assert_eq!(w32(&mut r, 0x1801, 1, 0x0000_02FF), None);
    let a = rtr(&mut r, 0x2FF);
    assert_eq!(a.len(), 1);
    assert_eq!(a[0].std_id(), Some(0x2FF));
}

/// §7.2.2.2 inhibit time: the minimum time between two transmissions of a TPDO, whatever
/// triggered the first: a TPDO answered to a remote request holds the next event-timer
/// transmission back until the inhibit time has passed.
#[test]
fn cia301_7_2_2_an_rtr_answer_starts_the_inhibit_time() {
    let mut r = Rig::booted(&TH);
    assert_eq!(w16(&mut r, 0x1800, 3, 50), None, "5 ms");
    assert_eq!(w16(&mut r, 0x1800, 5, 10), None);
    start(&mut r);
    r.take();
    let t: Vec<u64> = on(&r.advance_ms(8), 0x1FF)
        .iter()
        .map(|(t, _)| *t)
        .collect();
    assert!(t.is_empty(), "{t:?}");
    assert_eq!(rtr(&mut r, 0x1FF).len(), 1, "at 8 ms");
    let t: Vec<u64> = on(&r.advance_ms(14), 0x1FF)
        .iter()
        .map(|(t, _)| *t)
        .collect();
    assert_eq!(
        t,
        [13_000, 20_000],
        "held from 10 ms until 8 + 5 ms; the grid stays"
    );
}

/// Mapping a TPDO's values only changes what it carries, not when: the remapped PDO keeps the
/// event timer, and mapping nothing (sub 0 = 0) stops it until entries are counted in again.
#[test]
fn cia301_7_5_2_37_a_pdo_with_nothing_mapped_is_not_sent() {
    let mut r = Rig::booted(&TH);
    assert_eq!(w16(&mut r, 0x1800, 5, 2), None);
    start(&mut r);
    r.take();
    assert_eq!(on(&r.advance_ms(4), 0x1FF).len(), 2);
    assert_eq!(w8(&mut r, 0x1A00, 0, 0), None);
    assert!(on(&r.advance_ms(10), 0x1FF).is_empty());
    assert!(rtr(&mut r, 0x1FF).is_empty());
    assert_eq!(w8(&mut r, 0x1A00, 0, 1), None);
    let f = on(&r.advance_ms(4), 0x1FF);
    assert_eq!(f.len(), 2);
    assert_eq!(f[0].1.len(), 4, "position only");
}

/// Every synchronous TPDO answers the SYNC it is due on, in TPDO order (TH: all four TPDOs,
/// TPDO3 / TPDO4 given channel 3 / 4's values; types 1, 2, 1 and 0).
#[test]
fn cia301_7_2_2_each_synchronous_tpdo_counts_the_syncs_itself() {
    let mut r = Rig::booted(&TH);
    for (n, ttype) in [(0u16, 1u8), (1, 2), (2, 1), (3, 0)] {
        assert_eq!(
            w32(&mut r, 0x1800 + n, 1, 0x1FF + 0x100 * u32::from(n)),
            None
        );
        assert_eq!(w8(&mut r, 0x1800 + n, 2, ttype), None);
        assert_eq!(w8(&mut r, 0x1A00 + n, 0, 3), None);
    }
    start(&mut r);
    r.take();
    let ids = |r: &mut Rig| -> Vec<u16> {
        r.send(0x080, &[])
            .iter()
            .filter_map(|f| f.std_id().filter(|id| id & 0xFF == 0xFF && *id < 0x500))
            .collect()
    };
    assert_eq!(ids(&mut r), [0x1FF, 0x3FF, 0x4FF], "TPDO4: new values");
    assert_eq!(ids(&mut r), [0x1FF, 0x2FF, 0x3FF]);
    assert_eq!(ids(&mut r), [0x1FF, 0x3FF]);
    assert_eq!(ids(&mut r), [0x1FF, 0x2FF, 0x3FF]);
    assert!(on(&r.advance_ms(10), 0x1FF).is_empty(), "no timers");
}

/// Several asynchronous TPDOs each keep their own period, whichever is shorter and whichever
/// TPDOs they are (here TPDO3 at 10 ms before TPDO1 at 15 ms).
#[test]
fn cia301_7_2_2_a_later_tpdo_with_a_shorter_period_is_not_held_up() {
    for (other, cob) in [(1u16, 0x2FFu32), (2, 0x3FF)] {
        let mut r = Rig::booted(&TH);
        assert_eq!(w16(&mut r, 0x1800, 5, 15), None);
        assert_eq!(w32(&mut r, 0x1800 + other, 1, cob), None);
        assert_eq!(w16(&mut r, 0x1800 + other, 5, 10), None);
        assert_eq!(w8(&mut r, 0x1A00 + other, 0, 3), None);
        start(&mut r);
        r.take();
        let seq: Vec<(u64, u16)> = r
            .advance_ms(30)
            .iter()
            .filter_map(|(t, f)| {
                let id = f.std_id()?;
                (id == 0x1FF || id == cob as u16).then_some((t.micros() / 1000, id))
            })
            .collect();
        let c = cob as u16;
        assert_eq!(
            seq,
            [(10, c), (15, 0x1FF), (20, c), (30, 0x1FF), (30, c)],
            "TPDO{}",
            other + 1
        );
    }
}

/// Node guarding requests answered while Operational leave the TPDO event timer's grid alone
/// (the PDOs are already running; only a lost life guard stops them, D11).
#[test]
fn cia301_7_2_2_guarding_requests_do_not_restart_the_event_timer() {
    let mut r = Rig::booted(&TH);
    assert_eq!(w16(&mut r, 0x1800, 5, 10), None);
    start(&mut r);
    r.take();
    let mut t = Vec::new();
    for _ in 0..4 {
        t.extend(on(&r.advance_ms(5), 0x1FF).iter().map(|(t, _)| t / 1000));
        let g = rtr(&mut r, 0x77F);
        assert_eq!(g.len(), 1, "guarding answer");
        assert_eq!(g[0].std_id(), Some(0x77F));
    }
    assert_eq!(t, [10, 20]);
    t.extend(on(&r.advance_ms(12), 0x1FF).iter().map(|(t, _)| t / 1000));
    assert_eq!(t, [10, 20, 30]);
}

/// TMI R27 (OD.md): "TPDO1 value for Event Timer must always be higher than the value for
/// Inhibit Time (except for value 0)": event timer (ms) × 10 must exceed the inhibit time
/// (100 µs); a write breaking it, to either object, is refused with 0x06090030.
#[test]
fn tmi_r27_event_timer_stays_above_the_inhibit_time() {
    let mut r = booted("tmi");
    assert_eq!(r.node.read_object(0x1800, 5), Ok(1));
    assert_eq!(w16(&mut r, 0x1800, 3, 9), None, "0.9 ms < 1 ms");
    assert_eq!(
        w16(&mut r, 0x1800, 3, 10),
        Some(0x0609_0030),
        "1 ms is not below 1 ms"
    );
    assert_eq!(r.node.read_object(0x1800, 3), Ok(9));
    assert_eq!(w16(&mut r, 0x1800, 5, 2), None);
    assert_eq!(w16(&mut r, 0x1800, 3, 19), None);
    assert_eq!(w16(&mut r, 0x1800, 3, 20), Some(0x0609_0030));
    assert_eq!(
        w16(&mut r, 0x1800, 5, 1),
        Some(0x0609_0030),
        "1 ms ≤ 1.9 ms"
    );
    assert_eq!(r.node.read_object(0x1800, 5), Ok(2));
    assert_eq!(w16(&mut r, 0x1800, 5, 0), None, "0 (off) excepted");
    assert_eq!(w16(&mut r, 0x1800, 3, 1000), None);
    assert_eq!(w16(&mut r, 0x1800, 5, 100), Some(0x0609_0030));
    assert_eq!(w16(&mut r, 0x1800, 5, 101), None);
    // TH has no such rule.
    let mut r = Rig::booted(&TH);
    assert_eq!(w16(&mut r, 0x1800, 3, 50), None);
    assert_eq!(w16(&mut r, 0x1800, 5, 1), None);
}
