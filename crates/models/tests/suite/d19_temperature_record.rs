//! D19 / DECISIONS "TH temperature record": the operating-life extremes of 0x2901 are stored by
//! the device itself; only a stored 0 / 0 pair means "never recorded".

use crate::common::{booted, Rig};

fn life(r: &mut Rig) -> (i8, i8) {
    let v = |r: &mut Rig, s| r.read(0x2901, s) as u8 as i8;
    (v(r, 5), v(r, 4))
}

#[test]
fn a_life_extreme_of_0_degrees_is_a_record() {
    // Life minimum 0 °C, maximum 40 °C: one of the pair is 0, the record is real.
    for (lo, hi) in [(0i8, 40i8), (-20, 0)] {
        let mut r = booted("th");
        r.cycle_temp(Some(1_000_000), lo);
        r.cycle_temp(Some(1_000_000), hi);
        assert_eq!(life(&mut r), (lo, hi));
        r.power_cycle();
        r.cycle_temp(Some(1_000_000), 25.clamp(lo, hi));
        assert_eq!(life(&mut r), (lo, hi), "kept over the power cycle");
    }
}

#[test]
fn the_life_record_is_stored_only_when_it_changes() {
    // The device stores its extremes itself (automatic group): once per new extreme, not per
    // measurement cycle (the medium wears).
    let mut r = booted("th");
    r.cycle_temp(Some(1_000_000), 25);
    let saves = r.node.storage_mut().saves;
    for _ in 0..10 {
        r.cycle_temp(Some(1_000_000), 25);
    }
    assert_eq!(r.node.storage_mut().saves, saves, "nothing new");
    r.cycle_temp(Some(1_000_000), 26);
    assert_eq!(r.node.storage_mut().saves, saves + 1, "new maximum");
}
