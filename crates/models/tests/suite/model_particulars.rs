//! The model particulars the manuals state (issue 18 item 10): each model reports through its
//! own EMCY table, with its own reactions.

use crate::common::{booted, emcys, hex, sample, Rig};
use canpos_encoder::Fault;
use canpos_stack::Frame;

/// A measurement with the magnet at `nm`, at the current time (no time passes).
fn measure(r: &mut Rig, nm: i64) -> Vec<Frame> {
    r.node.update_sample(&sample(&[Some(nm)]), r.now);
    r.take()
}

/// TH / E-Series: "Emergency objects go along with changes of the internal error status
/// register": an error that clears while another stays sends 0x0000 with the register left.
/// TMI: 0x0000 is its "Sensor Error resetted", sent once no error is left.
#[test]
fn a_partial_clear_sends_the_error_reset_where_the_manual_says() {
    for (name, expect) in [("th", true), ("e-series", true), ("tmi", false)] {
        let mut r = booted(name);
        r.node.inject_fault(Fault::CanErrorPassive, true);
        r.node.inject_fault(Fault::Transducer, true);
        r.take();
        r.node.inject_fault(Fault::CanErrorPassive, false);
        let e = emcys(&r.take());
        if expect {
            // The register keeps the transducer error: generic + manufacturer.
            assert_eq!(e, vec![hex("00 00 81 00 00 00 00 00")], "{name}");
        } else {
            assert!(e.is_empty(), "{name}: {e:02X?}");
        }
        // The last one clears: 0x0000 with register 0 on every model.
        r.node.inject_fault(Fault::Transducer, false);
        let mut f = r.take();
        f.extend(measure(&mut r, 100_000_000));
        assert_eq!(emcys(&f), vec![hex("00 00 00 00 00 00 00 00")], "{name}");
    }
}

/// Recovery from bus-off: 0x8140, then on TH / E-Series the error reset (the control
/// documentation's promise); the TMI's table has 0x8140 0/0/0 alone.
#[test]
fn bus_off_recovery_then_error_reset() {
    for (name, reset) in [("th", true), ("e-series", true), ("tmi", false)] {
        let mut r = booted(name);
        r.node.inject_fault(Fault::CanBusOff, true);
        r.take();
        r.node.inject_fault(Fault::CanBusOff, false);
        let e = emcys(&r.take());
        assert_eq!(e[0][..2], [0x40, 0x81], "{name}");
        assert_eq!(e.len(), 1 + reset as usize, "{name}: {e:02X?}");
        if reset {
            assert_eq!(e[1], hex("00 00 00 00 00 00 00 00"));
        }
    }
}

/// TH Table 5 / E-Series: 0x8100 communication (generic) and 0x8210 PDO length can be raised;
/// the TMI has neither code and sends nothing.
#[test]
fn communication_and_pdo_length_codes() {
    for name in ["th", "e-series", "tmi"] {
        let tmi = name == "tmi";
        let mut r = booted(name);
        r.node.inject_fault(Fault::Communication, true);
        let e = emcys(&r.take());
        if tmi {
            assert!(e.is_empty(), "{name}");
        } else {
            assert_eq!(e, vec![hex("00 81 11 00 00 00 00 00")], "{name}");
        }
        r.node.inject_fault(Fault::Communication, false);
        r.take();
        r.node.inject_fault(Fault::PdoLength, true);
        let e = emcys(&r.take());
        if tmi {
            assert!(e.is_empty(), "{name}");
        } else {
            // Table 6: a communication error, in the EMCY and in 0x1001 while it stands.
            assert_eq!(e, vec![hex("10 82 11 00 00 00 00 00")], "{name}");
            assert_eq!(r.read(0x1001, 0), 0x11, "{name}");
        }
        r.node.inject_fault(Fault::PdoLength, false);
        let e = emcys(&r.take());
        if !tmi {
            assert_eq!(e, vec![hex("00 00 00 00 00 00 00 00")], "{name}");
        }
        assert_eq!(r.read(0x1001, 0), 0, "{name}");
    }
}

/// TMI 002 §1.14 has no supply-voltage or temperature code: the TMI reports both as its sensor
/// error (0x5000 1/1/0) with that error's reaction (process values frozen), and 0x0000 when
/// it clears. TH / E-Series keep 0x3100 / 0x4200.
#[test]
fn tmi_reports_supply_and_temperature_as_its_sensor_error() {
    for fault in [Fault::SupplyVoltage, Fault::OverTemperature] {
        let mut r = booted("tmi");
        measure(&mut r, 100_000_000);
        let before = r.read(0x6020, 1);
        r.node.inject_fault(fault, true);
        assert_eq!(
            emcys(&r.take()),
            vec![hex("00 50 81 01 01 00 00 00")],
            "{fault:?}"
        );
        measure(&mut r, 200_000_000);
        assert_eq!(r.read(0x6020, 1), before, "frozen");
        r.node.inject_fault(fault, false);
        assert_eq!(emcys(&r.take()), vec![hex("00 00 00 00 00 00 00 00")]);
    }
    let mut r = booted("th");
    r.node.inject_fault(Fault::SupplyVoltage, true);
    assert_eq!(emcys(&r.take()), vec![hex("00 31 05 00 00 00 00 00")]);
}

/// TMI 002 §1.11.2: work-area bit 0 is set at "Position <= Preset Value" or "Position >= Sensor
/// length" (both in the preset's coordinates; tmi_preset_cia406.rs has the full set).
#[test]
fn tmi_work_area_bit_0_at_the_preset_and_the_length() {
    let mut r = booted("tmi");
    let step = r.node.device().config().position_step_nm as i64;
    let stroke_nm = r.node.device().config().stroke_mm as i64 * 1_000_000;
    // A preset of 500 steps before any measurement: the start of the range reads 500.
    r.send(0x67F, &[0x23, 0x10, 0x60, 0x01, 0xF4, 0x01, 0, 0]);
    measure(&mut r, 10 * step);
    assert_eq!(r.read(0x6020, 1), 510);
    assert_eq!(r.read(0x6400, 1) & 1, 0, "inside");
    measure(&mut r, 0);
    assert_eq!(r.read(0x6020, 1), 500);
    assert_eq!(r.read(0x6400, 1) & 1, 1, "position <= preset");
    // Position >= sensor length: the end of the range, where the position reads length + 500.
    measure(&mut r, stroke_nm - step);
    assert_eq!(r.read(0x6400, 1) & 1, 0, "one step before the length");
    measure(&mut r, stroke_nm);
    assert_eq!(r.read(0x6020, 1) as i64, stroke_nm / step + 500);
    assert_eq!(r.read(0x6400, 1) & 1, 1, "position >= length");
    measure(&mut r, stroke_nm / 2);
    assert_eq!(r.read(0x6400, 1) & 1, 0);
}

/// TH Table 15: 0x100E (COB-ID guarding) is rw, and guarding requests on the configured COB-ID
/// are answered there (and no longer on 0x77F).
#[test]
fn th_guarding_answers_on_the_configured_cob_id() {
    let mut r = booted("th");
    let rtr = |r: &mut Rig, id: u16| {
        let f = Frame::remote(u32::from(id), false, 1).unwrap();
        r.node.handle_frame(&f, r.now);
        r.take()
    };
    assert_eq!(rtr(&mut r, 0x77F)[0].std_id(), Some(0x77F));
    assert_eq!(
        r.req(0x67F, &[0x23, 0x0E, 0x10, 0, 0x00, 0x03, 0, 0]).1[0],
        0x60
    );
    let a = rtr(&mut r, 0x300);
    assert_eq!(a.len(), 1);
    assert_eq!(a[0].std_id(), Some(0x300));
    assert_eq!(a[0].data()[0] & 0x7F, 0x7F, "pre-operational");
    assert!(rtr(&mut r, 0x77F).is_empty());
    // A restricted CAN-ID is refused.
    assert_eq!(
        r.req(0x67F, &[0x23, 0x0E, 0x10, 0, 0x81, 0x05, 0, 0]).1,
        hex("80 0E 10 00 30 00 09 06")
    );
}
