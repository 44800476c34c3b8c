//! CiA 406 parameter writes and what follows from them at once (SPEC §10, D2, D5, D12, R31):
//! positions follow a new code sequence or measuring step without waiting for the next cycle,
//! 0x6200 is TPDO1's event timer, and a cam enable / polarity names only four cams.

use crate::common::booted;

#[test]
fn code_sequence_applies_to_the_position_at_once() {
    // D2: 0x6000 bit 0; the position 0x6020 reads the new direction before the next cycle.
    let mut r = booted("th");
    r.cycle(Some(100_000_000)); // 20000 steps of 5 µm
    assert_eq!(r.read(0x6020, 1), 20_000);
    r.download(0x6000, 0, 1, 2).unwrap();
    assert_eq!(r.read(0x6020, 1), 200_000 - 20_000);
    assert_eq!(
        r.node.device().od().value(0x6500, 0),
        Some(1),
        "0x6500 follows"
    );
    r.download(0x6000, 0, 0, 2).unwrap();
    assert_eq!(r.read(0x6020, 1), 20_000);
}

#[test]
fn tmi_measuring_step_applies_to_the_position_at_once() {
    // R31: 0x6005/1 writable on the TMI in whole µm; the position follows the new step.
    let mut r = booted("tmi");
    r.cycle(Some(12_000_000));
    assert_eq!(r.read(0x6020, 1), 12_000);
    r.download(0x6005, 1, 5000, 4).unwrap();
    assert_eq!(r.read(0x6020, 1), 2400);
}

#[test]
fn cyclic_timer_is_tpdo1s_event_timer() {
    // D12: writing 0x6200 sets 0x1800/5, and TPDO1 sends at that period.
    let mut r = booted("th");
    r.download(0x6200, 0, 5, 2).unwrap();
    assert_eq!(r.read(0x1800, 5), 5);
    r.send(0x000, &[0x01, 0x7F]);
    r.take();
    let sent = r
        .advance_ms(50)
        .into_iter()
        .filter(|(_, f)| f.std_id() == Some(0x1FF))
        .count();
    assert!(
        (9..=11).contains(&sent),
        "{sent} TPDO1 frames in 50 ms at 5 ms"
    );
}

#[test]
fn only_tpdo1s_event_timer_is_the_cyclic_timer() {
    // D12 ties 0x6200 to 0x1800/5 only: TPDO1's inhibit time and TPDO2's event timer do not
    // change it.
    let mut r = booted("th");
    let before = r.read(0x6200, 0);
    r.download(0x1800, 3, 40, 2).unwrap();
    r.download(0x1801, 5, 70, 2).unwrap();
    assert_eq!(r.read(0x6200, 0), before);
    r.download(0x1800, 5, 30, 2).unwrap();
    assert_eq!(r.read(0x6200, 0), 30);
}

#[test]
fn cam_enable_and_polarity_name_four_cams() {
    // Four cams per channel: bits 4…7 of 0x6301 / 0x6302 name no cam (0x06090030); a refused
    // write changes nothing.
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        for index in [0x6301u16, 0x6302] {
            r.download(index, 1, 0x0F, 1).unwrap();
            assert_eq!(r.download(index, 1, 0x10, 1), Err(0x0609_0030), "{name}");
            assert_eq!(r.download(index, 1, 0x8F, 1), Err(0x0609_0030), "{name}");
            assert_eq!(r.read(index, 1), 0x0F, "{name}: unchanged");
        }
    }
}

#[test]
fn operating_status_reads_the_stored_code_sequence_before_any_measurement() {
    // D2: 0x6500 mirrors 0x6000, also when 0x6000 came from storage at power-on.
    let mut r = booted("th");
    r.download(0x6000, 0, 1, 2).unwrap();
    r.send(0x67F, &[0x23, 0x10, 0x10, 0x01, b's', b'a', b'v', b'e']);
    r.advance_ms(30);
    r.power_cycle();
    assert_eq!(r.read(0x6000, 0), 1);
    assert_eq!(r.read(0x6500, 0), 1);
}
