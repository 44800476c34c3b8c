//! E-Series 0x6509 "Offset value": the offset channel 1's preset produced (mirrors 0x650C/1),
//! in the dictionary itself as soon as the preset is written; a preset of another channel
//! leaves it alone.

use crate::common::Rig;
use canpos_encoder::Sample;
use canpos_models as models;

#[test]
fn the_dictionary_holds_channel_1s_offset() {
    let e = models::by_name("e-series").unwrap();
    let mut r = Rig::with_config(e, e.configure(e.default_config.with_channels(2)));
    r.take();
    r.advance_ms(1);
    let mut s = Sample::default();
    s.positions_nm[0] = Some(100_000_000); // 10000 steps of 10 µm
    s.positions_nm[1] = Some(200_000_000); // 20000
    r.node.update_sample(&s, r.now);
    let raw = |r: &Rig| r.node.device().od().value(0x6509, 0).unwrap() as i32;
    r.write(0x6010, 1, 250, 4);
    assert_eq!(raw(&r), 250 - 10_000, "written with the preset");
    r.write(0x6010, 2, 100, 4);
    assert_eq!(raw(&r), 250 - 10_000, "channel 2's preset is not 0x6509");
    assert_eq!(r.read(0x650C, 2) as i32, 100 - 20_000);
}

#[test]
fn a_stored_offset_reads_back_before_any_measurement() {
    // 0x6509 reads the offset of channel 1 (0x650C/1) even when no cycle ran since it was
    // loaded: after a power cycle with a saved preset, and after "restore defaults" + reset.
    let e = models::by_name("e-series").unwrap();
    let mut r = Rig::booted(e);
    r.advance_ms(1);
    let mut s = Sample::default();
    s.positions_nm[0] = Some(100_000_000);
    r.node.update_sample(&s, r.now);
    r.write(0x6010, 1, 250, 4);
    r.send(0x67F, &[0x23, 0x10, 0x10, 0x01, b's', b'a', b'v', b'e']);
    r.advance_ms(30);
    r.power_cycle();
    assert_eq!(r.read(0x6509, 0) as i32, 250 - 10_000);
}
