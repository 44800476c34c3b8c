//! SPEC §11 (faults to inject): each injected condition is active exactly while it is injected,
//! independently of the others, and the host can ask for it (`Encoder::fault_active`); events
//! (CAN-ID collision) are never "active". TMI system-data errors (002 §1.14) are
//! conditions of their own on the TMI and a transducer error on TH / E-Series.

use crate::common::{booted, emcys, hex, Rig};
use canpos_encoder::{Fault, Sample, SystemDataError};

/// The lasting conditions every model accepts (system-data errors aside).
const LASTING: [Fault; 11] = [
    Fault::Transducer,
    Fault::PdoLength,
    Fault::SupplyVoltage,
    Fault::OverTemperature,
    Fault::CanErrorPassive,
    Fault::Communication,
    Fault::CanBusOff,
    Fault::CanOverrun,
    Fault::CanBufferOverflow,
    Fault::TransmitOverflow,
    Fault::Warning(0xFFFF),
];

const SYSDATA: [SystemDataError; 7] = [
    SystemDataError::WrongMapping,
    SystemDataError::WrongVendorId,
    SystemDataError::WrongScale,
    SystemDataError::WrongResolution,
    SystemDataError::Unexpected,
    SystemDataError::NoSystemData,
    SystemDataError::InvalidSerial,
];

/// Which of `LASTING` and of the system-data errors are active.
fn active(r: &Rig) -> (Vec<bool>, Vec<bool>) {
    let app = r.node.device().app();
    (
        LASTING.iter().map(|&f| app.fault_active(f)).collect(),
        SYSDATA
            .iter()
            .map(|&e| app.fault_active(Fault::SystemData(e)))
            .collect(),
    )
}

fn only(k: usize, n: usize) -> Vec<bool> {
    (0..n).map(|i| i == k).collect()
}

#[test]
fn each_condition_is_active_exactly_while_injected() {
    // The TMI supports no warning (0x6506 = 0): its warning injection stays inactive.
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        assert_eq!(
            active(&r),
            (vec![false; LASTING.len()], vec![false; SYSDATA.len()]),
            "{name}: nothing injected"
        );
        for (k, &f) in LASTING.iter().enumerate() {
            r.node.inject_fault(f, true);
            let mut want = only(k, LASTING.len());
            // Nor has it a PDO-length code: no condition (002 §1.14).
            if name == "tmi" && matches!(f, Fault::Warning(_) | Fault::PdoLength) {
                want[k] = false;
            }
            assert_eq!(active(&r).0, want, "{name}: {f:?} injected");
            r.node.inject_fault(f, false);
            assert_eq!(
                active(&r),
                (vec![false; LASTING.len()], vec![false; SYSDATA.len()]),
                "{name}: {f:?} removed"
            );
        }
    }
}

#[test]
fn events_are_never_active() {
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        let f = Fault::CobIdCollision;
        r.node.inject_fault(f, true);
        assert!(!r.node.device().app().fault_active(f), "{name}: {f:?}");
        assert_eq!(active(&r).0, vec![false; LASTING.len()], "{name}: {f:?}");
    }
}

#[test]
fn warnings_are_active_only_for_supported_bits() {
    // D3: TH supports warning 0x0004 (0x6506); an injection of other bits sets nothing.
    let mut r = booted("th");
    r.node.inject_fault(Fault::Warning(0x0002), true);
    assert!(!r.node.device().app().fault_active(Fault::Warning(0xFFFF)));
    r.node.inject_fault(Fault::Warning(0x0006), true);
    let app = r.node.device().app();
    assert!(app.fault_active(Fault::Warning(0x0004)));
    assert!(!app.fault_active(Fault::Warning(0x0002)));
}

#[test]
fn tmi_system_data_errors_are_conditions_of_their_own() {
    for (k, &e) in SYSDATA.iter().enumerate() {
        // A fresh unit per error: all but one lock the sensor out until a power cycle.
        let mut r = booted("tmi");
        r.node.inject_fault(Fault::SystemData(e), true);
        assert_eq!(
            active(&r),
            (vec![false; LASTING.len()], only(k, SYSDATA.len())),
            "{e:?} injected"
        );
        r.node.inject_fault(Fault::SystemData(e), false);
        assert_eq!(active(&r).1, vec![false; SYSDATA.len()], "{e:?} removed");
    }
}

#[test]
fn system_data_errors_are_transducer_errors_on_th_and_e_series() {
    for name in ["th", "e-series"] {
        for e in SYSDATA {
            let mut r = booted(name);
            r.node.inject_fault(Fault::SystemData(e), true);
            assert_eq!(
                active(&r),
                (only(0, LASTING.len()), vec![false; SYSDATA.len()]),
                "{name}: {e:?}"
            );
            r.node.inject_fault(Fault::SystemData(e), false);
            assert_eq!(active(&r).0, vec![false; LASTING.len()], "{name}: {e:?}");
        }
    }
}

#[test]
fn lasting_conditions_are_reported_again_after_reset_communication() {
    // Reset communication forgets the active EMCY errors (CiA 301); a condition that is still
    // there is reported again by the next cycle, and the error register shows it.
    for (name, fault, emcy, reg) in [
        ("th", Fault::SupplyVoltage, "00 31 05 00 00 00 00 00", 0x05),
        ("th", Fault::CanOverrun, "10 81 11 00 00 00 00 00", 0x11),
        (
            "e-series",
            Fault::OverTemperature,
            "00 42 09 00 00 00 00 00",
            0x09,
        ),
        (
            "tmi",
            Fault::CanBufferOverflow,
            "10 81 11 02 00 00 00 00",
            0x11,
        ),
    ] {
        let mut r = booted(name);
        r.node.inject_fault(fault, true);
        assert_eq!(emcys(&r.take()), vec![hex(emcy)], "{name}: {fault:?}");
        r.send(0x000, &[0x82, 0x7F]);
        let f = r.cycle(Some(100_000_000));
        assert!(
            emcys(&f).contains(&hex(emcy)),
            "{name}: {fault:?} again: {:02X?}",
            emcys(&f)
        );
        assert_eq!(r.read(0x1001, 0), reg, "{name}: {fault:?}");
    }
}

#[test]
fn an_error_that_clears_does_not_re_announce_one_that_stays() {
    // SPEC §6: one EMCY per event. 0x8110 stays active while a sensor error comes and goes.
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        r.cycle(Some(100_000_000));
        r.node.inject_fault(Fault::CanOverrun, true);
        r.take();
        r.node.inject_fault(Fault::Transducer, true);
        let mut f = r.take();
        f.extend(r.cycle(Some(100_000_000)));
        r.node.inject_fault(Fault::Transducer, false);
        f.extend(r.take());
        for _ in 0..3 {
            f.extend(r.cycle(Some(100_000_000)));
        }
        let again: Vec<_> = emcys(&f)
            .into_iter()
            .filter(|e| e[..2] == [0x10, 0x81])
            .collect();
        assert!(again.is_empty(), "{name}: 0x8110 sent again: {again:02X?}");
    }
}

#[test]
fn removing_a_condition_that_is_not_there_sends_nothing() {
    // A removal is no event: no "recovered from bus-off" without a bus-off, no CAN-ID
    // collision, no system-data reaction (the TMI stays operational, no lock-out).
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        r.send(0x000, &[0x01, 0x7F]);
        r.cycle(Some(100_000_000));
        r.take();
        let mut all = [Fault::CanBusOff, Fault::CobIdCollision, Fault::PdoLength].to_vec();
        all.extend(SYSDATA.map(Fault::SystemData));
        for f in all {
            r.node.inject_fault(f, false);
            assert!(emcys(&r.take()).is_empty(), "{name}: {f:?} removed");
        }
        assert!(!r.node.device().app().lockout(), "{name}");
        assert_eq!(
            r.node.device().nmt_state(),
            canpos_stack::nmt::NmtState::Operational,
            "{name}"
        );
    }
}

#[test]
fn a_repeated_injection_is_not_a_new_event() {
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        r.node.inject_fault(Fault::CanBusOff, true);
        r.node.inject_fault(Fault::CanBusOff, true);
        assert!(emcys(&r.take()).is_empty(), "{name}: bus-off twice");
    }
    // TMI: Unexpected system data forces pre-operational once, not again while it lasts.
    let mut r = booted("tmi");
    let e = Fault::SystemData(SystemDataError::Unexpected);
    r.node.inject_fault(e, true);
    r.send(0x000, &[0x01, 0x7F]);
    r.node.inject_fault(e, true);
    assert_eq!(
        r.node.device().nmt_state(),
        canpos_stack::nmt::NmtState::Operational
    );
}

#[test]
fn cob_id_collision_is_a_th_and_e_series_event() {
    // TH Table 5 / E-Series: one-shot 0x8150 "CAN ID collision" with the communication error
    // of Table 6, over with its frame (the error reset follows); not in the TMI's table.
    let reset = hex("00 00 00 00 00 00 00 00");
    for (name, want) in [
        ("th", vec![hex("50 81 11 00 00 00 00 00"), reset.clone()]),
        (
            "e-series",
            vec![hex("50 81 11 00 00 00 00 00"), reset.clone()],
        ),
        ("tmi", vec![]),
    ] {
        let mut r = booted(name);
        r.node.inject_fault(Fault::CobIdCollision, true);
        assert_eq!(emcys(&r.take()), want, "{name}");
    }
}

#[test]
fn a_removed_warning_clears_only_its_bits() {
    // D3: 0x6505 holds the injected, supported warning bits (TH supports 0x0004).
    let mut r = booted("th");
    let warnings = |r: &mut Rig| r.read(0x6505, 0);
    r.node.inject_fault(Fault::Warning(0x0004), true);
    assert_eq!(warnings(&mut r), 0x0004);
    r.node.inject_fault(Fault::Warning(0x0002), false);
    assert_eq!(warnings(&mut r), 0x0004, "another bit removed");
    r.node.inject_fault(Fault::Warning(0x0004), false);
    assert_eq!(warnings(&mut r), 0);
}

#[test]
fn th_transducer_error_leaves_no_usable_position() {
    // TH / E-Series: while the transducer error lasts the position keeps its last value, the
    // velocity reads 0 (D13) and the position alarm is set.
    for name in ["th", "e-series"] {
        let mut r = booted(name);
        r.cycle(Some(100_000_000));
        let pos = r.read(0x6020, 1);
        r.node.inject_fault(Fault::Transducer, true);
        for k in 1..4i64 {
            r.advance_ms(1);
            let mut s = Sample::default();
            s.positions_nm[0] = Some(100_000_000 + k * 1_000_000);
            r.node.update_sample(&s, r.now);
            assert_eq!(r.read(0x6020, 1), pos, "{name}");
            assert_eq!(r.read(0x6030, 1), 0, "{name}");
            assert_eq!(r.read(0x6503, 0), 1, "{name}");
        }
    }
}
