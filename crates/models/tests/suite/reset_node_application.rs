//! NMT reset node (CiA 301 "reset application") and the CiA 406 application: the measurement
//! starts over (no velocity from a value before the reset), while what only a power cycle
//! clears stays: injected hardware conditions, TMI system-data errors and the EEPROM check,
//! warnings, and the TH temperature record (D19).

use crate::common::{booted, Rig};
use canpos_encoder::{Fault, SystemDataError};

fn reset_node(r: &mut Rig) {
    r.send(0x000, &[0x81, 0x7F]);
}

#[test]
fn the_first_measurement_after_reset_has_no_velocity() {
    let mut r = booted("th");
    r.cycle(Some(100_000_000));
    r.cycle(Some(100_100_000));
    assert_ne!(r.read(0x6030, 1), 0);
    reset_node(&mut r);
    r.cycle(Some(110_000_000));
    assert_eq!(r.read(0x6030, 1), 0, "no velocity across the reset");
    assert_eq!(r.read(0x6020, 1), 22_000);
}

#[test]
fn tmi_system_data_error_and_eeprom_bit_stay_over_reset() {
    let mut r = booted("tmi");
    r.node
        .inject_fault(Fault::SystemData(SystemDataError::WrongVendorId), true);
    reset_node(&mut r);
    r.cycle(Some(1_000_000));
    assert_ne!(r.read(0x1002, 0) & (1 << 12), 0, "wrong vendor-ID");
    assert!(r
        .node
        .device()
        .app()
        .fault_active(Fault::SystemData(SystemDataError::WrongVendorId)));

    // Corrupt stored data found at power-on (0x1002 bit 14) is still reported after a reset.
    let mut r = booted("tmi");
    r.send(0x67F, &[0x23, 0x10, 0x10, 0x01, b's', b'a', b'v', b'e']);
    r.advance_ms(30);
    r.node.storage_mut().corrupt();
    r.power_cycle();
    assert_ne!(r.read(0x1002, 0) & (1 << 14), 0);
    reset_node(&mut r);
    assert_ne!(r.read(0x1002, 0) & (1 << 14), 0, "after reset node");
}

#[test]
fn warnings_stay_over_reset() {
    let mut r = booted("th");
    r.node.inject_fault(Fault::Warning(0x0004), true);
    reset_node(&mut r);
    r.cycle(Some(100_000_000));
    assert_eq!(r.read(0x6505, 0), 0x0004);
}

#[test]
fn th_temperature_record_stays_over_reset() {
    // 0x2901/2, /3: max / min since start-up (a reset is no start-up); /4, /5 over the
    // operating life, kept in the device even when the medium could not store them.
    let mut r = booted("th");
    r.node.storage_mut().fail = true;
    for t in [20i8, 40, 30] {
        r.cycle_temp(Some(100_000_000), t);
    }
    reset_node(&mut r);
    r.cycle_temp(Some(100_000_000), 25);
    let t = |r: &mut Rig, s| r.read(0x2901, s) as u8 as i8;
    let got = [
        t(&mut r, 1),
        t(&mut r, 2),
        t(&mut r, 3),
        t(&mut r, 4),
        t(&mut r, 5),
    ];
    assert_eq!(got, [25, 40, 20, 40, 20]);
}
