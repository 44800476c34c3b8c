//! D13 / SPEC §6: missing magnet, transducer error and (TMI) system-data errors share EMCY
//! 0x5000; each new reason is announced while the code is active, and an error still present
//! after a reset communication is reported again.

use crate::common::{booted, emcys, hex};
use canpos_encoder::{Fault, SystemDataError};

#[test]
fn tmi_a_second_reason_is_announced_while_5000_is_active() {
    let mut r = booted("tmi");
    r.cycle(Some(1_000_000));
    let f = r.cycle(None);
    assert_eq!(
        emcys(&f),
        vec![hex("00 50 81 01 01 00 00 00")],
        "magnet lost"
    );
    r.node
        .inject_fault(Fault::SystemData(SystemDataError::WrongScale), true);
    assert_eq!(
        emcys(&r.take()),
        vec![hex("00 50 81 01 03 02 00 00")],
        "the new reason, with its bytes"
    );
    // Nothing new: nothing sent.
    assert!(emcys(&r.cycle(None)).is_empty());
}

#[test]
fn th_transducer_error_after_a_lost_magnet_is_announced() {
    let mut r = booted("th");
    r.cycle(Some(100_000_000));
    assert_eq!(emcys(&r.cycle(None)), vec![hex("00 50 81 00 00 00 00 00")]);
    r.node.inject_fault(Fault::Transducer, true);
    assert_eq!(emcys(&r.take()), vec![hex("00 50 81 00 00 00 00 00")]);
}

#[test]
fn a_lasting_sensor_error_is_reported_again_after_reset_communication() {
    // Reset communication forgets the active EMCY errors (CiA 301); the transducer is still
    // faulty, so the next cycle reports it again and the error register shows it.
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        r.cycle(Some(100_000_000));
        r.node.inject_fault(Fault::Transducer, true);
        let first = emcys(&r.take());
        assert_eq!(first.len(), 1, "{name}");
        r.send(0x000, &[0x82, 0x7F]);
        let f = r.cycle(Some(100_000_000));
        assert!(emcys(&f).contains(&first[0]), "{name}: {:02X?}", emcys(&f));
        assert_eq!(r.read(0x1001, 0) & 0x80, 0x80, "{name}");
    }
}
