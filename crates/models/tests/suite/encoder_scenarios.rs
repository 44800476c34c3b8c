//! CiA 406 application scenarios on a virtual clock (SPEC §10, §11): exact positions and
//! velocities with ideal samples, cam and work-area switch points with the TPDOs / EMCYs each
//! model sends, missing magnet (D13), presets, injected faults, TMI status and lock-out.

use crate::common::{booted, emcys, expedited_download, hex, model, Rig};
use canpos_encoder::{Fault, SystemDataError};
use canpos_stack::storage::RamStorage;
use canpos_stack::{Frame, Instant};

fn sdo_write(r: &mut Rig, index: u16, sub: u8, v: u32, n: usize) -> Vec<Frame> {
    let out = r.send(0x67F, &expedited_download(index, sub, v, n));
    assert!(
        out.iter()
            .any(|f| f.std_id() == Some(0x5FF) && f.data()[0] == 0x60),
        "write {index:04X}:{sub} = {v:#X}: {out:?}"
    );
    out
}

fn tpdos(frames: &[Frame], id: u16) -> Vec<Vec<u8>> {
    frames
        .iter()
        .filter(|f| f.std_id() == Some(id))
        .map(|f| f.data().to_vec())
        .collect()
}

#[test]
fn constant_speed_gives_exact_positions_and_velocities() {
    // (model, position step nm, velocity step 0.01 mm/s): 100 mm/s = 100 µm per 1 ms cycle.
    for (name, step, vstep) in [
        ("th", 5000i64, 50i64),
        ("e-series", 10_000, 100),
        ("tmi", 1000, 250),
    ] {
        let mut r = booted(name);
        let v_expected = 100_000 * 100 / (1000 * vstep);
        for k in 0..50i64 {
            let nm = 100_000_000 + k * 100_000;
            r.cycle(Some(nm));
            assert_eq!(r.read(0x6020, 1) as i32 as i64, nm / step, "{name} k={k}");
            let v = r.read(0x6030, 1) as u16 as i16 as i64;
            assert_eq!(v, if k == 0 { 0 } else { v_expected }, "{name} k={k}");
        }
        // Moving toward the head: negative velocity (D18).
        r.cycle(Some(100_000_000 + 48 * 100_000));
        assert_eq!(
            r.read(0x6030, 1) as u16 as i16 as i64,
            -v_expected,
            "{name}"
        );
    }
}

#[test]
fn code_sequence_bit_counts_down_from_the_end() {
    // D2 / SPEC §10: 0x6000 bit 0 = counts decrease away from the head (velocity too).
    let mut r = booted("th");
    sdo_write(&mut r, 0x6000, 0, 1, 2);
    r.cycle(Some(100_000_000));
    r.cycle(Some(100_100_000));
    // 1000 mm / 5 µm = 200000 steps.
    assert_eq!(r.read(0x6020, 1), 200_000 - 20_020);
    assert_eq!(r.read(0x6030, 1) as u16 as i16, -200);
    assert_eq!(r.read(0x6500, 0), 1, "0x6500 mirrors 0x6000");
}

#[test]
fn th_threshold_cam_switches_at_threshold_and_sends_tpdo() {
    // D5: TH cams are thresholds: active when position >= 0x631k, polarity inverts.
    let mut r = booted("th");
    sdo_write(&mut r, 0x6310, 1, 20_100, 4);
    sdo_write(&mut r, 0x6301, 1, 0x01, 1);
    // Event timer 0: TPDO1 (maps 0x6300/1) goes out only on cam events.
    sdo_write(&mut r, 0x1800, 5, 0, 2);
    assert_eq!(r.read(0x6200, 0), 0, "D12");
    r.send(0x000, &[0x01, 0x7F]);
    let mut switched = None;
    for k in 0..10i64 {
        let nm = 100_000_000 + k * 100_000; // 20000 + 20k steps
        let f = r.cycle(Some(nm));
        let pos = 20_000 + 20 * k;
        let state = r.read(0x6300, 1);
        assert_eq!(state, (pos >= 20_100) as u32, "k={k}");
        let pdo = tpdos(&f, 0x1FF);
        if pos == 20_100 {
            assert_eq!(pdo.len(), 1, "TPDO on the cam change");
            assert_eq!(pdo[0][6], 0x01);
            switched = Some(k);
        } else {
            assert!(pdo.is_empty(), "k={k}: no TPDO without an event");
        }
        assert!(emcys(&f).is_empty(), "TH sends no cam EMCY");
    }
    assert_eq!(switched, Some(5));
    // Polarity inverts at once (the write re-evaluates the state) and sends the TPDO.
    sdo_write(&mut r, 0x6302, 1, 0x01, 1);
    assert_eq!(r.read(0x6300, 1), 0);
    // The event TPDO goes out at the node's next deadline, which is now.
    assert!(r.node.poll_timeout() <= Some(r.now));
    let f: Vec<Frame> = r.advance_ms(0).into_iter().map(|(_, f)| f).collect();
    // Position 20180 (0x4ED4), velocity 200, cam state 0.
    assert_eq!(tpdos(&f, 0x1FF), vec![hex("D4 4E 00 00 C8 00 00")]);
    // Back below the threshold: active again (inverted).
    r.cycle(Some(100_000_000));
    assert_eq!(r.read(0x6300, 1), 1);
    // A disabled cam reads 0.
    sdo_write(&mut r, 0x6301, 1, 0, 1);
    assert_eq!(r.read(0x6300, 1), 0);
}

#[test]
fn tmi_window_cam_with_hysteresis_both_directions() {
    // D5 / TMI §1.10: window [low, high], hysteresis added in the direction of motion;
    // each change sends EMCY 0x9080 (channel, state) and the event-driven TPDO1.
    let mut r = booted("tmi");
    sdo_write(&mut r, 0x6310, 1, 1000, 4);
    sdo_write(&mut r, 0x6320, 1, 2000, 4);
    sdo_write(&mut r, 0x6330, 1, 10, 2);
    sdo_write(&mut r, 0x6301, 1, 0x01, 1);
    sdo_write(&mut r, 0x1800, 5, 0, 2);
    r.send(0x000, &[0x01, 0x7F]);
    let mut changes = Vec::new();
    // Up from 900 µm to 2100 µm in 5 µm steps, then back down to 900.
    let up = (0..=240).map(|k| 900 + 5 * k);
    let down = (0..=240).map(|k| 2100 - 5 * k);
    for pos in up.chain(down) {
        let f = r.cycle(Some(pos as i64 * 1000));
        for e in emcys(&f) {
            assert_eq!(&e[..2], &[0x80, 0x90]);
            assert_eq!(e[3], 1, "channel");
            changes.push((pos, e[4]));
            assert_eq!(tpdos(&f, 0x1FF).len(), 1, "TPDO with the EMCY");
            assert_eq!(tpdos(&f, 0x1FF)[0][6], e[4], "cam state byte");
        }
    }
    assert_eq!(changes, vec![(1010, 1), (2015, 0), (1990, 1), (985, 0)]);
}

#[test]
fn tmi_work_area_change_sends_emcy_9090() {
    let mut r = booted("tmi");
    r.cycle(Some(900_000));
    assert_eq!(r.read(0x6400, 1), 0);
    let f = sdo_write(&mut r, 0x6401, 1, 1500, 4);
    assert_eq!(r.read(0x6400, 1), 0b100, "below the low limit");
    assert_eq!(emcys(&f), vec![hex("90 90 00 01 00 04 00 00")]);
    let f = r.cycle(Some(1_600_000));
    assert_eq!(emcys(&f), vec![hex("90 90 00 01 00 00 00 00")]);
}

#[test]
fn e_series_work_area_crossing_sends_default_tpdo() {
    // E maps the work-area state in TPDO1 (Table 16): crossing the high limit is an event.
    let mut r = booted("e-series");
    sdo_write(&mut r, 0x6402, 1, 10_020, 4);
    sdo_write(&mut r, 0x1800, 5, 0, 2);
    r.send(0x000, &[0x01, 0x7F]);
    let mut seen = Vec::new();
    for k in 0..5i64 {
        let f = r.cycle(Some(100_000_000 + k * 100_000));
        for d in tpdos(&f, 0x1FF) {
            seen.push((k, d[6]));
        }
    }
    // Position 10000 + 10k; > 10020 first at k = 3 → bit 1.
    assert_eq!(seen, vec![(3, 0b010)]);
}

#[test]
fn missing_magnet_alarm_emcy_and_last_position() {
    // D13 on TH / E: EMCY 0x5000 register 0x81, 0x6503 bit 0, last position kept, 0x0000 on return.
    for name in ["th", "e-series"] {
        let mut r = booted(name);
        r.cycle(Some(100_000_000));
        r.cycle(Some(100_100_000));
        let pos = r.read(0x6020, 1);
        let f = r.cycle(None);
        assert_eq!(emcys(&f), vec![hex("00 50 81 00 00 00 00 00")], "{name}");
        assert_eq!(r.read(0x6503, 0), 1);
        assert_eq!(r.read(0x1001, 0), 0x81);
        for _ in 0..3 {
            assert!(emcys(&r.cycle(None)).is_empty(), "once per event");
            assert_eq!(r.read(0x6020, 1), pos, "last position kept");
            assert_eq!(r.read(0x6030, 1), 0);
        }
        let f = r.cycle(Some(100_200_000));
        assert_eq!(emcys(&f), vec![hex("00 00 00 00 00 00 00 00")], "{name}");
        assert_eq!(r.read(0x6503, 0), 0);
        assert_eq!(r.read(0x1003, 1) & 0xFFFF, 0x5000, "history");
    }
    // TMI: 0x5000 with bytes 3–5 = 1, 1, 0.
    let mut r = booted("tmi");
    r.cycle(Some(1_000_000));
    let f = r.cycle(None);
    assert_eq!(emcys(&f), vec![hex("00 50 81 01 01 00 00 00")]);
    assert_eq!(r.read(0x6503, 0), 1);
    let f = r.cycle(Some(1_000_000));
    assert_eq!(emcys(&f), vec![hex("00 00 00 00 00 00 00 00")]);
}

#[test]
fn preset_makes_current_position_read_the_preset() {
    let mut r = booted("th");
    r.cycle(Some(100_000_000));
    assert_eq!(r.read(0x6020, 1), 20_000);
    sdo_write(&mut r, 0x6010, 1, 5000, 4);
    assert_eq!(r.read(0x6020, 1), 5000, "at once");
    assert_eq!(r.read(0x650C, 1) as i32, 5000 - 20_000);
    r.cycle(Some(100_100_000));
    assert_eq!(r.read(0x6020, 1), 5020);
    // Negative presets work too.
    sdo_write(&mut r, 0x6010, 1, (-7i32) as u32, 4);
    assert_eq!(r.read(0x6020, 1) as i32, -7);
    // Stored with "save", the offset survives a power cycle.
    let i = [0x22, 0x10, 0x10, 0x01, b's', b'a', b'v', b'e'];
    r.send(0x67F, &i);
    r.advance_ms(30);
    r.power_cycle();
    r.cycle(Some(100_100_000));
    assert_eq!(r.read(0x6020, 1) as i32, -7);
}

#[test]
fn e_series_preset_offset_readout_and_clear() {
    let mut r = booted("e-series");
    r.cycle(Some(100_000_000));
    assert_eq!(r.read(0x6020, 1), 10_000);
    sdo_write(&mut r, 0x6010, 1, 250, 4);
    assert_eq!(r.read(0x6020, 1), 250);
    assert_eq!(r.read(0x6509, 0) as i32, 250 - 10_000, "offset read out");
    // R30: 0xFFFFFFFF clears the preset.
    sdo_write(&mut r, 0x6010, 1, 0xFFFF_FFFF, 4);
    assert_eq!(r.read(0x6020, 1), 10_000);
    assert_eq!(r.read(0x6509, 0), 0);
    assert_eq!(r.read(0x6010, 1), 0);
    // On the TH 0xFFFFFFFF is an ordinary preset of -1.
    let mut r = booted("th");
    r.cycle(Some(100_000_000));
    sdo_write(&mut r, 0x6010, 1, 0xFFFF_FFFF, 4);
    assert_eq!(r.read(0x6020, 1) as i32, -1);
}

#[test]
fn supply_voltage_fault_matches_manual_example_3() {
    let mut r = booted("th");
    r.node.inject_fault(Fault::SupplyVoltage, true);
    assert_eq!(emcys(&r.take()), vec![hex("00 31 05 00 00 00 00 00")]);
    r.node.inject_fault(Fault::SupplyVoltage, false);
    assert_eq!(emcys(&r.take()), vec![hex("00 00 00 00 00 00 00 00")]);
    // CAN faults: error passive (register 0x11), bus-off recovery, overrun.
    r.node.inject_fault(Fault::CanErrorPassive, true);
    assert_eq!(emcys(&r.take()), vec![hex("20 81 11 00 00 00 00 00")]);
    r.node.inject_fault(Fault::CanErrorPassive, false);
    r.take();
    r.node.inject_fault(Fault::CanBusOff, true);
    assert!(r.take().is_empty());
    r.node.inject_fault(Fault::CanBusOff, false);
    // Recovered, with the communication error that stood during bus-off (Table 6), then the
    // error reset the TH's EMCYs go along with.
    assert_eq!(
        emcys(&r.take()),
        vec![
            hex("40 81 11 00 00 00 00 00"),
            hex("00 00 00 00 00 00 00 00")
        ]
    );
    r.node.inject_fault(Fault::CanOverrun, true);
    assert_eq!(emcys(&r.take()), vec![hex("10 81 11 00 00 00 00 00")]);
    r.node.inject_fault(Fault::OverTemperature, true);
    assert_eq!(emcys(&r.take()), vec![hex("00 42 19 00 00 00 00 00")]);
    // Transducer error: position error alarm, 0x5000 / 0x81 (the register keeps the others).
    r.node.inject_fault(Fault::Transducer, true);
    assert_eq!(emcys(&r.take()), vec![hex("00 50 99 00 00 00 00 00")]);
    assert_eq!(r.read(0x6503, 0), 1);
    // D3: warnings only as injected and supported (TH 0x0004).
    r.node.inject_fault(Fault::Warning(0x0006), true);
    assert_eq!(r.read(0x6505, 0), 0x0004);
}

#[test]
fn tmi_lockout_status_and_repeated_emcy() {
    let mut r = booted("tmi");
    r.cycle(Some(1_000_000));
    r.send(0x000, &[0x01, 0x7F]);
    assert_eq!(r.read(0x1002, 0) & 0x3, 0b10, "operational");
    assert_ne!(r.read(0x1002, 0) & (1 << 16), 0, "receiving process data");
    r.node
        .inject_fault(Fault::SystemData(SystemDataError::WrongMapping), true);
    assert_eq!(emcys(&r.take()), vec![hex("00 50 81 01 02 00 00 00")]);
    let st = r.read(0x1002, 0);
    assert_eq!(st & 0x3, 0b01, "forced pre-operational");
    assert_ne!(st & (1 << 13), 0);
    // Start refused, EMCY repeated; reset node does not lift it.
    let f = r.send(0x000, &[0x01, 0x7F]);
    assert_eq!(emcys(&f), vec![hex("00 50 81 01 02 00 00 00")]);
    assert_eq!(r.read(0x1002, 0) & 0x3, 0b01);
    r.send(0x000, &[0x81, 0x7F]);
    r.send(0x000, &[0x01, 0x7F]);
    assert_eq!(r.read(0x1002, 0) & 0x3, 0b01, "until a power cycle");
    r.power_cycle();
    r.send(0x000, &[0x01, 0x7F]);
    assert_eq!(r.read(0x1002, 0) & 0x3, 0b10);
}

#[test]
fn tmi_insufficient_event_timer_r27() {
    // 10 kbit/s: an 8-byte TPDO takes ~13.5 ms, the 1 ms event timer is too short.
    let t = model("tmi");
    let mut r = Rig::with_config(t, t.default_config.with_bitrate(10));
    r.take();
    let f = r.cycle(Some(1_000_000));
    assert_eq!(emcys(&f), vec![hex("00 60 01 01 00 00 00 00")]);
    assert_ne!(r.read(0x1002, 0) & (1 << 15), 0);
    // 20 ms is enough.
    sdo_write(&mut r, 0x1800, 5, 20, 2);
    let f = r.cycle(Some(1_000_000));
    assert_eq!(emcys(&f), vec![hex("00 00 00 00 00 00 00 00")]);
    assert_eq!(r.read(0x1002, 0) & (1 << 15), 0);
}

#[test]
fn corrupt_storage_reports_per_model() {
    for (name, emcy_expected) in [("th", true), ("tmi", false)] {
        let m = model(name);
        let mut node = canpos_models::SensorNode::new(m, m.default_config, RamStorage::default());
        node.power_on(Instant::ZERO);
        while node.poll_transmit().is_some() {}
        node.handle_frame(
            &Frame::new(0x67F, &hex("22 10 10 01 73 61 76 65")).unwrap(),
            Instant::ZERO,
        );
        node.handle_timeout(Instant::from_millis(30));
        while node.poll_transmit().is_some() {}
        node.storage_mut().corrupt();
        node.power_off();
        node.power_on(Instant::from_millis(40));
        let mut frames = Vec::new();
        while let Some(f) = node.poll_transmit() {
            frames.push(f);
        }
        let has_6300 = emcys(&frames).iter().any(|e| e[..2] == [0x00, 0x63]);
        assert_eq!(has_6300, emcy_expected, "{name}: EMCY 0x6300");
        if name == "tmi" {
            assert_ne!(
                node.read_object(0x1002, 0).unwrap() & (1 << 14),
                0,
                "EEPROM CRC bit"
            );
        }
    }
}

#[test]
fn th_temperature_record_and_life_extremes_persist() {
    // D19: 0x2901 in °C; life min / max stored by the device itself.
    let mut r = booted("th");
    for t in [20i8, 30, 25] {
        r.cycle_temp(Some(1_000_000), t);
    }
    // 0x2901 subs 1…5 as °C.
    let record = |r: &mut Rig| [1, 2, 3, 4, 5].map(|s| r.read(0x2901, s) as u8 as i8);
    assert_eq!(record(&mut r), [25, 30, 20, 30, 20]);
    r.power_cycle();
    r.cycle_temp(Some(1_000_000), 22);
    assert_eq!(record(&mut r), [22, 22, 22, 30, 20]);
}

/// An EMCY goes out once per event: an injected sensor (transducer) error sends 0x5000 once,
/// however many cycles it lasts (its lost pulses are that error, not a new one), and once
/// more 0x0000 when it clears.
#[test]
fn injected_sensor_error_sends_its_emcy_once() {
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        r.cycle(Some(100_000_000));
        r.node.inject_fault(Fault::Transducer, true);
        let mut f = r.take();
        for _ in 0..5 {
            f.extend(r.cycle(Some(100_000_000)));
        }
        let e = emcys(&f);
        assert_eq!(e.len(), 1, "{name}: {e:02X?}");
        assert_eq!(&e[0][..2], &[0x00, 0x50], "{name}");
        r.node.inject_fault(Fault::Transducer, false);
        let mut f = r.take();
        f.extend(r.cycle(Some(100_000_000)));
        let e = emcys(&f);
        assert_eq!(e.len(), 1, "{name}: {e:02X?}");
        assert_eq!(&e[0][..3], &[0, 0, 0], "{name}: cleared");
    }
}
