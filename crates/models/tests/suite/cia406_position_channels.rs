//! CiA 406 position channels (SPEC §10, D13): velocity is the position change over the time
//! since the channel's last measurement, and the host can ask which channel lost its magnet.

use crate::common::{booted, Rig};
use canpos_models as models;

fn velocity(r: &mut Rig, ch: u8) -> i16 {
    r.read(0x6030, ch) as u16 as i16
}

#[test]
fn velocity_after_a_gap_spans_the_whole_gap() {
    // TH: 1 ms cycle, velocity step 0.5 mm/s (0x6005/2 = 50). The magnet is lost for one
    // cycle, then found 2 mm further on: 2 mm in 2 ms = 1 m/s = 2000 steps, not 2 mm in 1 ms.
    let mut r = booted("th");
    r.cycle(Some(100_000_000));
    r.cycle(None);
    assert_eq!(velocity(&mut r, 1), 0, "D13: no velocity while it is lost");
    r.cycle(Some(102_000_000));
    assert_eq!(velocity(&mut r, 1), 2000);
    // Three missing cycles: 3 mm over 4 ms = 0.75 m/s.
    for _ in 0..3 {
        r.cycle(None);
    }
    r.cycle(Some(105_000_000));
    assert_eq!(velocity(&mut r, 1), 1500);
}

#[test]
fn the_host_sees_which_channel_misses_its_magnet() {
    let th = models::by_name("th").unwrap();
    let mut r = Rig::with_config(th, th.configure(th.default_config.with_channels(2)));
    r.take();
    let app = |r: &Rig, ch| r.node.device().app().missing(ch);
    r.cycle_channels(&[Some(100_000_000), Some(200_000_000)]);
    assert!(!app(&r, 0) && !app(&r, 1));
    r.cycle_channels(&[Some(100_000_000), None]);
    assert!(!app(&r, 0) && app(&r, 1), "second magnet lost");
    r.cycle_channels(&[None, Some(200_000_000)]);
    assert!(app(&r, 0) && !app(&r, 1), "first magnet lost, second back");
    assert!(!app(&r, 7), "no such channel");
}

#[test]
fn velocity_rounds_half_away_from_zero() {
    // D18: the position change over the cycle in 0x6005/2 units, rounded to nearest, halves
    // away from zero. TH: 1 ms, 0.5 mm/s per step = 500 nm per cycle per step.
    let mut r = booted("th");
    let mut nm = 100_000_000;
    r.cycle(Some(nm));
    for (d, v) in [
        (750, 2),
        (749, 1),
        (250, 1),
        (249, 0),
        (-750, -2),
        (-749, -1),
        (-250, -1),
    ] {
        nm += d;
        r.cycle(Some(nm));
        assert_eq!(velocity(&mut r, 1), v, "{d} nm per cycle");
    }
}
