//! CiA 301 §7.5.2.35 / §7.2.2.2 TPDO parameters as a host reads them back from the node's PDO
//! service (`Node::device().tpdos()`, what a runtime reports): the transmission type in force
//! after SDO writes, and the next event-timer deadline, which exists only while the PDOs run
//! (TH, node-id 0x7F: SDO 0x67F, TPDO1 on 0x1FF).

use crate::common::Rig;
use canpos_models::th::TH;
use canpos_stack::Instant;

fn booted() -> Rig {
    let mut r = Rig::new(&TH);
    r.take();
    r
}

/// Writes `v` (`size` bytes) by expedited SDO download; the abort code if refused.
fn write(r: &mut Rig, index: u16, sub: u8, v: u32, size: usize) -> Option<u32> {
    let mut req = vec![
        0x23 | ((4 - size as u8) << 2),
        index as u8,
        (index >> 8) as u8,
        sub,
    ];
    req.extend_from_slice(&v.to_le_bytes());
    let (_, a) = r.req(0x67F, &req);
    (a[0] == 0x80).then(|| u32::from_le_bytes(a[4..8].try_into().unwrap()))
}

fn ttype(r: &Rig, n: usize) -> u8 {
    r.node
        .device()
        .tpdos()
        .get(n)
        .expect("TPDO exists")
        .transmission_type()
}

/// §7.5.2.35 sub 2: the transmission type a master writes is the one the TPDO runs with; a
/// refused one (D10: 241…253) leaves it, and each TPDO has its own.
#[test]
fn cia301_7_5_2_35_the_transmission_type_written_is_the_one_in_force() {
    let mut r = booted();
    assert_eq!(ttype(&r, 0), 254, "TH default: event-driven");
    for v in [5u32, 0, 240, 255, 1] {
        assert_eq!(write(&mut r, 0x1800, 2, v, 1), None, "type {v}");
        assert_eq!(u32::from(ttype(&r, 0)), v);
        assert_eq!(ttype(&r, 1), 254, "TPDO2 keeps its own");
    }
    assert_eq!(write(&mut r, 0x1800, 2, 241, 1), Some(0x0609_0030));
    assert_eq!(ttype(&r, 0), 1, "refused: unchanged");
    assert_eq!(write(&mut r, 0x1801, 2, 3, 1), None);
    assert_eq!((ttype(&r, 0), ttype(&r, 1)), (1, 3));
}

/// §7.2.2.2 event timer: the PDO service reports when its next TPDO is due: none before
/// Operational (no timer runs), the event period after entering Operational, the next period
/// once one was sent, none again once stopped.
#[test]
fn cia301_7_2_2_2_the_next_tpdo_deadline_exists_only_while_the_pdos_run() {
    let mut r = booted();
    let due = |r: &Rig| r.node.device().tpdos().poll_timeout();
    assert_eq!(write(&mut r, 0x1800, 5, 10, 2), None);
    assert_eq!(due(&r), None, "pre-operational");
    r.advance_ms(3);
    r.send(0x000, &[0x01, 0x7F]);
    assert_eq!(due(&r), Some(Instant::from_micros(13_000)), "3 ms + 10 ms");
    let sent: Vec<u64> = r
        .advance_ms(10)
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x1FF))
        .map(|(t, _)| t.micros())
        .collect();
    assert_eq!(sent, [13_000]);
    assert_eq!(due(&r), Some(Instant::from_micros(23_000)));
    assert!(r.node.poll_timeout() <= due(&r), "the node wakes for it");
    r.send(0x000, &[0x80, 0x7F]);
    assert_eq!(due(&r), None, "pre-operational again");
}
