//! CiA 406 cams and work areas (SPEC §10, D5; TMI 002 §1.10 / §1.11.2): every one of the four
//! cams of a channel follows its own limits, and the work-area state bits follow their
//! inclusive limits and the measuring range.

use crate::common::booted;

#[test]
fn th_each_cam_switches_at_its_own_threshold() {
    // TH: cam k active at and beyond 0x631k (its "upper or lower threshold"); bit k of 0x6300.
    let mut r = booted("th");
    let thresholds = [20_040u32, 20_080, 20_120, 20_160];
    for (k, &t) in thresholds.iter().enumerate() {
        r.write(0x6310 + k as u16, 1, t, 4);
    }
    r.write(0x6301, 1, 0x0F, 1);
    // 5 µm steps: position 20000 + 20 per 100 µm.
    for i in 0..12i64 {
        r.cycle(Some(100_000_000 + i * 100_000));
        let pos = 20_000 + 20 * i as u32;
        let want = thresholds
            .iter()
            .enumerate()
            .filter(|&(_, &t)| pos >= t)
            .fold(0, |s, (k, _)| s | 1 << k);
        assert_eq!(r.read(0x6300, 1), want, "position {pos}");
    }
}

#[test]
fn tmi_each_cam_has_its_own_window_and_hysteresis() {
    // TMI window cams: cam k on inside [0x631k, 0x632k]; its hysteresis 0x633k moves each
    // switch point in the direction of motion (on at low + h, off past high + h going up).
    let mut r = booted("tmi");
    let cams: Vec<(u32, u32, u32)> = (1..=4u32)
        .map(|k| (1000 * k, 1000 * k + 500, 10 * k))
        .collect();
    for (k, &(low, high, h)) in cams.iter().enumerate() {
        let k = k as u16;
        r.write(0x6310 + k, 1, low, 4);
        r.write(0x6320 + k, 1, high, 4);
        r.write(0x6330 + k, 1, h, 2);
    }
    r.write(0x6301, 1, 0x0F, 1);
    let mut changes = Vec::new();
    let mut last = 0;
    // Up from 900 µm in 5 µm steps (TMI: 1 µm per position step).
    for pos in (900..=5000).step_by(5) {
        r.cycle(Some(pos as i64 * 1000));
        let state = r.read(0x6300, 1);
        if state != last {
            changes.push((pos, state));
            last = state;
        }
    }
    let mut want = Vec::new();
    for (k, &(low, high, h)) in cams.iter().enumerate() {
        want.push((low + h, 1 << k));
        want.push((high + h + 5, 0));
    }
    assert_eq!(changes, want);
}

#[test]
fn tmi_cam_first_evaluation_is_the_plain_window() {
    // Before the cam has a state there is no direction of motion to apply hysteresis in: the
    // first measurement inside [low, high] switches it on.
    let mut r = booted("tmi");
    r.write(0x6310, 1, 1000, 4);
    r.write(0x6320, 1, 2000, 4);
    r.write(0x6330, 1, 50, 2);
    r.write(0x6301, 1, 0x01, 1);
    r.cycle(Some(1_010_000));
    assert_eq!(r.read(0x6300, 1), 1);
    let mut r = booted("tmi");
    r.write(0x6310, 1, 1000, 4);
    r.write(0x6320, 1, 2000, 4);
    r.write(0x6301, 1, 0x01, 1);
    r.cycle(Some(2_000_000));
    assert_eq!(r.read(0x6300, 1), 1, "high limit inclusive");
    r.cycle(Some(2_001_000));
    assert_eq!(r.read(0x6300, 1), 0);
}

#[test]
fn work_area_limits_are_inclusive() {
    // Bit 2: position below 0x6401; bit 1: above 0x6402; a position on a limit is inside.
    let mut r = booted("th");
    r.cycle(Some(100_000_000)); // position 20000
    r.write(0x6401, 1, 20_000, 4);
    r.write(0x6402, 1, 20_000, 4);
    assert_eq!(r.read(0x6400, 1), 0, "on both limits");
    r.write(0x6401, 1, 20_001, 4);
    assert_eq!(r.read(0x6400, 1), 0b100);
    r.write(0x6401, 1, 19_000, 4);
    r.write(0x6402, 1, 19_999, 4);
    assert_eq!(r.read(0x6400, 1), 0b010);
    // Both at once (low limit above high limit).
    r.write(0x6401, 1, 20_001, 4);
    assert_eq!(r.read(0x6400, 1), 0b110);
}

#[test]
fn work_area_bit_0_outside_the_measuring_range() {
    // TH / E-Series: bit 0 while the magnet is measured past either end of the range (the
    // soft edge, DECISIONS "soft stroke edge"); the ends themselves are inside. 1000 mm.
    for name in ["th", "e-series"] {
        let mut r = booted(name);
        for (nm, out) in [
            (-5_000i64, true),
            (0, false),
            (500_000_000, false),
            (1_000_000_000, false),
            (1_000_005_000, true),
        ] {
            r.cycle(Some(nm));
            assert_eq!(r.read(0x6400, 1) & 1, out as u32, "{name}: {nm} nm");
        }
    }
}
