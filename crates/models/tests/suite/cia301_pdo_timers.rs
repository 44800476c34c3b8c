//! CiA 301 §7.2.2 TPDO event timer (TH, node-id 0x7F, TPDO1 on 0x1FF), served by a late host.

use crate::common::{hex, Rig};
use canpos_models::th::TH;
use canpos_stack::Instant;

fn late_tpdo1(r: &mut Rig, at_ms: u64) -> usize {
    r.now = Instant::from_millis(at_ms);
    r.node.handle_timeout(r.now);
    r.take()
        .iter()
        .filter(|f| f.std_id() == Some(0x1FF))
        .count()
}

/// §7.2.2.2.1 (event timer): the period is kept on its absolute grid. A host several periods
/// late gets one TPDO, not a burst; the next is due at the next grid point; and the periods that
/// passed unsent are counted.
#[test]
fn cia301_7_2_2_event_timer_catch_up_sends_one_counts_the_missed_keeps_the_grid() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 00 18 05 0A 00 00 00")); // TPDO1 event timer 10 ms
    r.send(0x000, &[0x01, 0x7F]); // start at t = 0: due 10, 20, 30, ...
    r.take();
    let missed0 = r.node.device().tpdos().get(0).unwrap().missed;
    assert_eq!(late_tpdo1(&mut r, 35), 1, "one TPDO, not three");
    assert_eq!(
        r.node.device().tpdos().get(0).unwrap().missed - missed0,
        2,
        "the periods due at 20 and 30 ms were missed"
    );
    assert_eq!(r.node.poll_timeout().map(|t| t.micros()), Some(40_000));
    assert_eq!(late_tpdo1(&mut r, 39), 0);
    assert_eq!(late_tpdo1(&mut r, 40), 1);
    assert_eq!(r.node.device().tpdos().get(0).unwrap().missed - missed0, 2);
    // Late by exactly whole periods: the grid point reached is the one sent, the next follows.
    assert_eq!(late_tpdo1(&mut r, 70), 1);
    assert_eq!(r.node.device().tpdos().get(0).unwrap().missed - missed0, 4);
    assert_eq!(r.node.poll_timeout().map(|t| t.micros()), Some(80_000));
}
