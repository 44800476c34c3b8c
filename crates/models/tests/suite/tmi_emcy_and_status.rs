//! TMI 002 §1.14 (emergency messages, tables 2 and 3) and §1.15 (0x1002 manufacturer status):
//! the EMCY bytes, status bits and NMT reaction of each condition, as a master sees them.

use crate::common::{booted, emcys, hex, Rig};
use canpos_encoder::{Fault, SystemDataError};
use canpos_stack::Frame;

fn status(r: &mut Rig) -> u32 {
    r.read(0x1002, 0)
}

fn start(r: &mut Rig) -> Vec<Frame> {
    r.send(0x000, &[0x01, 0x7F])
}

/// Bits 8…14 of 0x1002: the system-data errors (and bit 14 the EEPROM check).
const SYSDATA_BITS: u32 = 0x7F00;

#[test]
fn each_system_data_error_sets_its_own_status_bit_and_emcy_bytes() {
    // (error, 0x1002 bit, EMCY bytes 3…5 per table 2; the third byte of 1/3/x is canpos's).
    for (e, bit, mfr) in [
        (SystemDataError::WrongMapping, 13, [1, 2, 0]),
        (SystemDataError::WrongVendorId, 12, [1, 3, 1]),
        (SystemDataError::WrongScale, 11, [1, 3, 2]),
        (SystemDataError::WrongResolution, 10, [1, 4, 0]),
        (SystemDataError::Unexpected, 9, [1, 5, 0]),
        (SystemDataError::NoSystemData, 8, [1, 6, 0]),
        (SystemDataError::InvalidSerial, 14, [2, 1, 0]),
    ] {
        let mut r = booted("tmi");
        r.cycle(Some(1_000_000));
        assert_ne!(status(&mut r) & (1 << 16), 0, "{e:?}: receiving before");
        r.node.inject_fault(Fault::SystemData(e), true);
        let f = r.take();
        let want = [0x00, 0x50, 0x81, mfr[0], mfr[1], mfr[2], 0, 0];
        assert_eq!(emcys(&f), vec![want.to_vec()], "{e:?}");
        let st = status(&mut r);
        assert_eq!(st & SYSDATA_BITS, 1 << bit, "{e:?}: 0x1002 = {st:#X}");
        assert_eq!(st & (1 << 16), 0, "{e:?}: no process data while it lasts");
        r.node.inject_fault(Fault::SystemData(e), false);
        assert_eq!(status(&mut r) & SYSDATA_BITS, 0, "{e:?}: removed");
    }
}

#[test]
fn unexpected_system_data_forces_pre_operational_once_without_lock_out() {
    // Table 2, 5000 1/5/0: pre-operational, then "normal operation can continue afterwards".
    let mut r = booted("tmi");
    start(&mut r);
    r.cycle(Some(1_000_000));
    assert_eq!(status(&mut r) & 0b11, 0b10, "operational");
    r.node
        .inject_fault(Fault::SystemData(SystemDataError::Unexpected), true);
    r.take();
    assert_eq!(status(&mut r) & 0b11, 0b01, "forced pre-operational");
    assert!(!r.node.device().app().lockout());
    let f = start(&mut r);
    assert!(
        emcys(&f).is_empty(),
        "the start is not refused: {:02X?}",
        emcys(&f)
    );
    assert_eq!(status(&mut r) & 0b11, 0b10, "operational again");
}

#[test]
fn a_locking_system_data_error_refuses_every_start_until_power_cycle() {
    let mut r = booted("tmi");
    r.node
        .inject_fault(Fault::SystemData(SystemDataError::NoSystemData), true);
    assert_eq!(emcys(&r.take()), vec![hex("00 50 81 01 06 00 00 00")]);
    assert!(r.node.device().app().lockout());
    for _ in 0..2 {
        // "Attempted setting into OPERATIONAL will result in repeated EMCY message sending."
        assert_eq!(emcys(&start(&mut r)), vec![hex("00 50 81 01 06 00 00 00")]);
        assert_eq!(status(&mut r) & 0b11, 0b01);
    }
}

#[test]
fn can_overflows_have_their_own_bytes_and_status_bits() {
    // Table 2: 8110 1/0/0 controller overflow (0x1002 bit 7), 8110 2/0/0 buffer overflow (bit 6).
    for (fault, bit, byte3) in [(Fault::CanOverrun, 7, 1), (Fault::CanBufferOverflow, 6, 2)] {
        let mut r = booted("tmi");
        r.node.inject_fault(fault, true);
        let want = vec![0x10, 0x81, 0x11, byte3, 0, 0, 0, 0];
        assert_eq!(emcys(&r.take()), vec![want], "{fault:?}");
        assert_eq!(status(&mut r) & 0xC0, 1 << bit, "{fault:?}");
        // A lasting condition: it stays over measurement cycles, no second EMCY.
        assert!(emcys(&r.cycle(Some(1_000_000))).is_empty(), "{fault:?}");
        assert_eq!(status(&mut r) & 0xC0, 1 << bit, "{fault:?}");
        r.node.inject_fault(fault, false);
        assert_eq!(emcys(&r.take()), vec![hex("00 00 00 00 00 00 00 00")]);
        assert_eq!(status(&mut r) & 0xC0, 0, "{fault:?} removed");
    }
}

#[test]
fn both_overflows_share_8110_until_the_last_clears() {
    let mut r = booted("tmi");
    r.node.inject_fault(Fault::CanOverrun, true);
    r.node.inject_fault(Fault::CanBufferOverflow, true);
    // The second reason is announced with its own bytes.
    assert_eq!(
        emcys(&r.take()),
        vec![
            hex("10 81 11 01 00 00 00 00"),
            hex("10 81 11 02 00 00 00 00")
        ]
    );
    r.node.inject_fault(Fault::CanOverrun, false);
    assert!(emcys(&r.take()).is_empty(), "0x8110 still active");
    assert_eq!(status(&mut r) & 0xC0, 1 << 6);
    r.node.inject_fault(Fault::CanBufferOverflow, false);
    assert_eq!(emcys(&r.take()), vec![hex("00 00 00 00 00 00 00 00")]);
}

#[test]
fn transmit_overflow_is_the_insufficient_event_timer_while_it_lasts() {
    // DECISIONS "The physical bus": "TPDO1 sending will occur partially" — 0x6000 1/0/0 and
    // 0x1002 bit 15, held over measurement cycles until the overflow ends.
    let mut r = booted("tmi");
    r.node.inject_fault(Fault::TransmitOverflow, true);
    assert_eq!(emcys(&r.take()), vec![hex("00 60 01 01 00 00 00 00")]);
    for _ in 0..3 {
        assert!(emcys(&r.cycle(Some(1_000_000))).is_empty());
        assert_ne!(status(&mut r) & (1 << 15), 0, "bit 15 while it lasts");
    }
    r.node.inject_fault(Fault::TransmitOverflow, false);
    assert_eq!(emcys(&r.take()), vec![hex("00 00 00 00 00 00 00 00")]);
    r.cycle(Some(1_000_000));
    assert_eq!(status(&mut r) & (1 << 15), 0);
}

#[test]
fn error_passive_and_bus_off_status_bits() {
    // §1.15: bit 5 CAN error passive; bit 4 CAN bus-off with bit 3 its bus-off timer.
    let mut r = booted("tmi");
    r.node.inject_fault(Fault::CanErrorPassive, true);
    assert_eq!(emcys(&r.take()), vec![hex("20 81 11 00 00 00 00 00")]);
    assert_eq!(status(&mut r) & 0xF8, 1 << 5);
    r.node.inject_fault(Fault::CanErrorPassive, false);
    assert_eq!(status(&mut r) & 0xF8, 0);
    r.node.inject_fault(Fault::CanBusOff, true);
    assert_eq!(status(&mut r) & 0xF8, (1 << 4) | (1 << 3));
    r.node.inject_fault(Fault::CanBusOff, false);
    assert_eq!(status(&mut r) & 0xF8, 0);
}

#[test]
fn status_bits_1_0_carry_the_nmt_state() {
    // §1.15: %11 stopped, %10 operational, %01 pre-operational.
    let mut r = booted("tmi");
    assert_eq!(status(&mut r) & 0b11, 0b01);
    start(&mut r);
    assert_eq!(status(&mut r) & 0b11, 0b10);
    r.send(0x000, &[0x02, 0x7F]);
    assert_eq!(status(&mut r) & 0b11, 0b11);
    r.send(0x000, &[0x80, 0x7F]);
    assert_eq!(status(&mut r) & 0b11, 0b01);
}
