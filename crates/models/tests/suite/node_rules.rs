//! Node-level rules that span services (TH, node-id 0x7F).

use crate::common::{booted, hex, Rig};
use canpos_encoder::Fault;
use canpos_models::th::TH;
use canpos_stack::Frame;
use canpos_stack::Table;

fn emcy_codes(frames: &[Frame]) -> Vec<u16> {
    frames
        .iter()
        .filter(|f| f.std_id() == Some(0x0FF))
        .map(|f| u16::from_le_bytes([f.data()[0], f.data()[1]]))
        .collect()
}

/// A hardware fault is a condition of the unit, not of the protocol: NMT reset node clears the
/// EMCY state, and the fault, still present, is reported again.
#[test]
fn hardware_faults_persist_across_reset_node() {
    let mut r = Rig::booted(&TH);
    r.node.inject_fault(Fault::SupplyVoltage, true);
    assert_eq!(emcy_codes(&r.take()), [0x3100]);
    r.send(0x000, &[0x81, 0x7F]);
    r.take();
    let mut after = Vec::new();
    for _ in 0..5 {
        after.extend(r.cycle(Some(100_000_000)));
    }
    assert!(
        emcy_codes(&after).contains(&0x3100),
        "reported again: {after:?}"
    );
    assert_ne!(r.read(0x1001, 0) & 0x04, 0, "voltage bit set");
    r.node.inject_fault(Fault::SupplyVoltage, false);
    assert_eq!(r.read(0x1001, 0), 0);
}

/// CiA 301 §7.2.7: an error that goes away and comes back is a second error event.
#[test]
fn cia301_7_2_7_an_error_that_returns_sends_a_second_emcy() {
    let mut r = Rig::booted(&TH);
    r.node.inject_fault(Fault::SupplyVoltage, true);
    r.node.inject_fault(Fault::SupplyVoltage, false);
    r.node.inject_fault(Fault::SupplyVoltage, true);
    assert_eq!(emcy_codes(&r.take()), [0x3100, 0x0000, 0x3100]);
}

/// An error the MCU's own monitors raise with `set_error` stays until they clear it, also when
/// its code is one the sensor application raises for reasons of its own (0x5000): measuring
/// cycles that find no sensor error of theirs leave it active (no EMCY 0000, 0x1001 keeps it).
/// The application's own 0x5000 still clears when its reason goes.
#[test]
fn an_error_raised_with_set_error_is_cleared_only_by_set_error() {
    let mut r = Rig::booted(&TH);
    r.node.set_error(0x5000, 0x81, [0; 5], true);
    assert_eq!(emcy_codes(&r.take()), [0x5000]);
    let mut out = Vec::new();
    for _ in 0..5 {
        out.extend(r.cycle_temp(Some(100_000_000), 25));
    }
    assert!(emcy_codes(&out).is_empty(), "{out:?}");
    assert!(r.node.device().emcy().is_active(0x5000));
    assert_eq!(r.node.read_object(0x1001, 0), Ok(0x81));
    r.node.set_error(0x5000, 0x81, [0; 5], false);
    assert_eq!(emcy_codes(&r.take()), [0x0000]);
    assert_eq!(r.node.read_object(0x1001, 0), Ok(0));

    // The application's own: raised by a transducer error, cleared when it goes.
    r.node.inject_fault(Fault::Transducer, true);
    assert_eq!(emcy_codes(&r.take()), [0x5000]);
    r.node.inject_fault(Fault::Transducer, false);
    assert_eq!(emcy_codes(&r.take()), [0x0000]);
    assert!(!r.node.device().emcy().is_active(0x5000));
}

/// CiA 301 Table 86 (services per NMT state): EMCY is served in pre-operational and
/// operational, not in stopped, and not by a node without a node-id. What a master sees: in a
/// serving state the EMCY at once, or the inhibited one when 0x1015 allows; in a state that does
/// not serve none, and no due deadline (a host loop would spin on one); once the node serves
/// again, what waited goes out.
#[test]
fn cia301_emcy_is_served_in_pre_operational_and_operational_only() {
    use canpos_stack::nmt::NmtState;
    let no_due = |r: &Rig| {
        assert!(
            r.node.poll_timeout().is_none_or(|t| t > r.now),
            "a due deadline at {:?} in {:?}",
            r.node.poll_timeout(),
            r.node.device().nmt_state()
        )
    };
    let emcy_at = |f: &[(canpos_stack::Instant, Frame)]| -> Vec<(u64, u16)> {
        f.iter()
            .filter(|(_, f)| f.std_id() == Some(0x0FF))
            .map(|(t, f)| (t.micros(), u16::from_le_bytes([f.data()[0], f.data()[1]])))
            .collect()
    };
    for (cmd, state) in [
        (0x80, NmtState::PreOperational),
        (0x01, NmtState::Operational),
        (0x02, NmtState::Stopped),
    ] {
        let mut r = Rig::booted(&TH);
        r.req(0x67F, &hex("2B 15 10 00 64 00 00 00")); // 10 ms inhibit
        r.send(0x000, &[cmd, 0x7F]);
        r.take();
        assert_eq!(r.node.device().nmt_state(), state);
        let t0 = r.now.micros();
        r.node.set_error(0x3100, 0x04, [0; 5], true);
        r.node.set_error(0x4200, 0x08, [0; 5], true);
        let now = emcy_codes(&r.take());
        let later = emcy_at(&r.advance_ms(50));
        no_due(&r);
        if state == NmtState::Stopped {
            assert!(
                now.is_empty() && later.is_empty(),
                "{state:?}: {now:X?} {later:X?}"
            );
            // Pre-operational again: both go out, the second after the inhibit time.
            let now = emcy_codes(&r.send(0x000, &[0x80, 0x7F]));
            assert_eq!(now, [0x3100], "{state:?}");
            let t1 = r.now.micros();
            assert_eq!(emcy_at(&r.advance_ms(50)), [(t1 + 10_000, 0x4200)]);
        } else {
            assert_eq!(now, [0x3100], "{state:?}");
            assert_eq!(later, [(t0 + 10_000, 0x4200)], "{state:?}");
        }
        no_due(&r);
    }
    // Without a node-id (initialising, LSS): nothing, and nothing due.
    let mut r = Rig::with_config(&TH, TH.default_config.with_node_id(0xFF));
    r.take();
    assert_eq!(r.node.device().nmt_state(), NmtState::Initialising);
    r.node.set_error(0x3100, 0x04, [0; 5], true);
    assert!(r.take().is_empty());
    assert!(r.advance_ms(50).is_empty());
    no_due(&r);
}

/// CiA 301 §7.5.2.18 (0x1015 inhibit time EMCY, 100 µs units): an EMCY held back by the
/// inhibit time goes out when it ends, at the node's own deadline (the host need not poll).
#[test]
fn cia301_7_5_2_18_an_inhibited_emcy_leaves_when_the_inhibit_time_ends() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 15 10 00 64 00 00 00")); // 100 × 100 µs = 10 ms
    r.node.inject_fault(Fault::SupplyVoltage, true);
    r.node.inject_fault(Fault::OverTemperature, true);
    assert_eq!(emcy_codes(&r.take()), [0x3100], "the second waits");
    assert_eq!(r.node.poll_timeout().map(|t| t.micros()), Some(10_000));
    let f = r.advance_ms(50);
    let emcy: Vec<_> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x0FF))
        .collect();
    assert_eq!(emcy.len(), 1);
    assert_eq!(emcy[0].0.micros(), 10_000);
}

/// A node takes part only in the traffic addressed to it: frames of other nodes (their PDOs,
/// EMCYs, heartbeats, SDO requests) change nothing and produce nothing, not even an output that
/// was due anyway (an EMCY held back by 0x1015 leaves at the node's own deadline). A node that
/// sees them runs exactly as one that does not.
#[test]
fn frames_for_other_nodes_change_nothing() {
    let mut seen = Rig::booted(&TH);
    let mut quiet = Rig::booted(&TH);
    for r in [&mut seen, &mut quiet] {
        r.req(0x67F, &hex("2B 15 10 00 64 00 00 00")); // EMCY inhibit 10 ms
        r.node.inject_fault(Fault::SupplyVoltage, true);
        r.node.inject_fault(Fault::OverTemperature, true);
        assert_eq!(emcy_codes(&r.take()), [0x3100], "the second waits");
        r.now = canpos_stack::Instant::from_millis(15);
    }
    for (id, data) in [
        (0x181u16, &[1u8, 2, 3][..]),
        (0x0FE, &[0x00, 0x31, 0x05, 0, 0, 0, 0, 0]),
        (0x701, &[0x05]),
        (0x601, &hex("40 00 10 00 00 00 00 00")),
        (0x581, &hex("43 00 10 00 96 01 08 00")),
    ] {
        let f = Frame::new(id, data).unwrap();
        seen.node.handle_frame(&f, seen.now);
        assert!(seen.take().is_empty(), "{id:03X} produced output");
    }
    assert_eq!(seen.node.poll_timeout(), quiet.node.poll_timeout());
    assert_eq!(seen.advance_ms(50), quiet.advance_ms(50));
}

/// CiA 301 §7.2.2.3: a remote request for a TPDO whose COB-ID allows RTR (bit 30 = 0) is
/// answered with the PDO, in operational only.
#[test]
fn cia301_7_2_2_3_rtr_requests_a_tpdo_in_operational() {
    let mut r = Rig::booted(&TH);
    let rtr = |r: &mut Rig| {
        let f = Frame::remote(0x1FF, false, 7).unwrap();
        r.node.handle_frame(&f, r.now);
        r.take()
    };
    assert!(rtr(&mut r).is_empty(), "pre-operational: no PDO");
    r.send(0x000, &[0x01, 0x7F]);
    r.take();
    let a = rtr(&mut r);
    assert_eq!(a.len(), 1, "{a:?}");
    assert_eq!((a[0].std_id(), a[0].is_remote()), (Some(0x1FF), false));
}

/// A model whose features say "no RTR-triggered TPDOs" answers no remote request for a TPDO,
/// whatever the COB-ID's bit 30 says.
#[test]
fn a_model_without_tpdo_rtr_answers_no_remote_request() {
    use canpos_models::{Features, Model};
    let model: &'static Model = Box::leak(Box::new(Model {
        table: Table {
            name: "th-no-rtr",
            features: Features {
                tpdo_rtr: false,
                ..TH.features
            },
            ..TH.table
        },
        ..TH
    }));
    let mut r = Rig::booted(model);
    r.send(0x000, &[0x01, 0x7F]);
    r.take();
    let f = Frame::remote(0x1FF, false, 7).unwrap();
    r.node.handle_frame(&f, r.now);
    assert!(r.take().is_empty());
}

/// A node that loses power sends nothing more: what it had queued is gone, and after the next
/// power-on its first frame is the boot-up.
#[test]
fn power_off_drops_what_was_waiting() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 17 10 00 0A 00 00 00")); // heartbeat 10 ms
    r.now = canpos_stack::Instant::from_millis(35);
    r.node.handle_timeout(r.now); // a heartbeat queued, not yet taken
    r.node.power_off();
    assert!(r.node.poll_transmit().is_none());
    r.node.power_on(r.now);
    let f = r.take();
    assert_eq!((f[0].std_id(), f[0].data()), (Some(0x77F), &[0u8][..]));
}

/// CiA 305: a node without a node-id takes part in LSS only. An error raised meanwhile (here a
/// supply fault) sends no EMCY, and it leaves the node no deadline that is already due: a host
/// that waits for `poll_timeout` does not spin.
#[test]
fn cia305_an_unconfigured_node_keeps_errors_to_itself_and_has_no_due_deadline() {
    let cfg = canpos_models::DeviceConfig {
        node_id: 0xFF,
        ..TH.default_config
    };
    let mut r = Rig::with_config(&TH, cfg);
    assert!(r.take().is_empty());
    r.node.inject_fault(Fault::SupplyVoltage, true);
    assert!(r.take().is_empty(), "no EMCY without a node-id");
    assert!(
        r.node.poll_timeout().is_none_or(|t| t > r.now),
        "a due deadline at {:?} that nothing serves",
        r.node.poll_timeout()
    );
    assert!(r.advance_ms(100).is_empty());
}

/// TMI (docs/DECISIONS.md): a bit rate written to 0x2001 is the one the next reset
/// communication activates.
#[test]
fn tmi_0x2001_applies_at_reset_communication() {
    let mut r = booted("tmi");
    assert_eq!(r.node.device().bitrate(), 250);
    r.req(0x67F, &hex("2B 01 20 00 F4 01 00 00")); // 500
    assert_eq!(r.node.device().bitrate(), 250, "not before the reset");
    assert_eq!(r.node.device().pending().1, 500);
    r.send(0x000, &[0x82, 0x7F]);
    assert_eq!(r.node.device().bitrate(), 500);
}

/// A checksummed state file can still hold values no write would have been let in (found by
/// fuzzing): a valid EMCY COB-ID on the NMT identifier 0x000, a SYNC COB-ID on 0x000 with
/// 29 bits. Such an object keeps its default, and the node talks only on its own COB-IDs.
#[test]
fn cia301_restricted_cob_ids_in_a_state_file_are_not_loaded() {
    use canpos_stack::storage::{ImageWriter, RamStorage, Storage, IMAGE_MAX};
    use canpos_stack::Instant;
    let mut image = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut image, TH.features.tag);
    let key = |index: u32| index << 8;
    assert!(w.push(key(0x1014), 0x0060_0000)); // valid, CAN-ID 0x000
    assert!(w.push(key(0x1005), 0x2000_0000)); // 29-bit SYNC
    assert!(w.push(key(0x1017), 250)); // a plain value: loaded
    let n = w.finish();
    let mut ram = RamStorage::default();
    ram.save(&image[..n]).unwrap();
    let mut node = canpos_models::SensorNode::new(&TH, TH.default_config, ram);
    node.power_on(Instant::ZERO);
    let id = node.device().node_id() as u32;
    assert_eq!(node.read_object(0x1014, 0), Ok(0x80 + id));
    assert_eq!(node.read_object(0x1005, 0), Ok(0x80));
    assert_eq!(node.read_object(0x1017, 0), Ok(250));
    assert_eq!(node.read_object(0x100E, 0), Ok(0x700 + id));
    // Raise an error: its EMCY goes out on 0x080 + node-id.
    node.set_error(0x5000, 0x81, [0; 5], true);
    while let Some(f) = node.poll_transmit() {
        let cob = f.std_id().unwrap() as u32;
        assert!(cob == 0x700 + id || cob == 0x080 + id, "{cob:03X}");
    }
}

/// The guarding COB-ID from a state file: its own pre-defined 0x700 + node-id loads (it is
/// restricted, but the node's own), another node's 0x700 + x does not.
#[test]
fn cia301_stored_guarding_cob_id_only_the_nodes_own() {
    use canpos_stack::storage::{ImageWriter, RamStorage, Storage, IMAGE_MAX};
    use canpos_stack::Instant;
    let boot = |v: u32| {
        let mut image = [0u8; IMAGE_MAX];
        let mut w = ImageWriter::new(&mut image, TH.features.tag);
        assert!(w.push(0x100E << 8, v));
        let n = w.finish();
        let mut ram = RamStorage::default();
        ram.save(&image[..n]).unwrap();
        let mut node = canpos_models::SensorNode::new(&TH, TH.default_config.with_node_id(5), ram);
        node.power_on(Instant::ZERO);
        node.read_object(0x100E, 0).unwrap()
    };
    assert_eq!(boot(0x705), 0x705); // own id: loaded
    assert_eq!(boot(0x4000_0705), 0x705); // bit 30 set: refused by a write, so the default
    assert_eq!(boot(0x706), 0x705); // another node's: the default
    assert_eq!(boot(0x3A5), 0x3A5); // not restricted: loaded
    assert_eq!(boot(0x123), 0x705); // restricted (0x101…0x180): the default
}

/// A node whose state file holds `records` (TH, node-id 5), powered on.
fn boot_with(
    records: &[(u32, u32)],
) -> canpos_models::SensorNode<canpos_stack::storage::RamStorage> {
    use canpos_stack::storage::{ImageWriter, RamStorage, Storage, IMAGE_MAX};
    use canpos_stack::Instant;
    let mut image = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut image, TH.features.tag);
    for &(key, v) in records {
        assert!(w.push(key, v));
    }
    let n = w.finish();
    let mut ram = RamStorage::default();
    ram.save(&image[..n]).unwrap();
    let mut node = canpos_models::SensorNode::new(&TH, TH.default_config.with_node_id(5), ram);
    node.power_on(Instant::ZERO);
    node
}

/// One rule per COB-ID and TPDO parameter: a state file's value loads exactly when an SDO
/// write of it to a node holding the defaults is accepted (the rules that relate a write to
/// the value it replaces, e.g. a valid EMCY's CAN-ID, apply to writes only). Each refused
/// value leaves its object at the default.
#[test]
fn cia301_state_file_values_load_only_as_an_sdo_write_would_be_accepted() {
    let key = |index: u32, sub: u32| index << 8 | sub;
    // (index, sub, value, loads)
    let cases: &[(u32, u32, u32, bool)] = &[
        (0x100E, 0, 0x8000_0123, false), // guarding has no "not valid" bit: restricted 0x123
        (0x100E, 0, 0x2000_03A5, false), // 29-bit
        (0x100E, 0, 0x3A5, true),        // unrestricted
        (0x1005, 0, 0x8000_0000, false), // restricted 0x000, bit 31 or not
        (0x1005, 0, 0x4000_0090, false), // bit 30: this node does not generate SYNC
        (0x1005, 0, 0x0000_0090, true),
        (0x1014, 0, 0xA000_0085, false), // 29-bit, not valid
        (0x1014, 0, 0x8000_0300, true),  // not valid, another CAN-ID
        (0x1014, 0, 0x4000_0085, false), // reserved bit 30
        (0x1014, 0, 0x8000_0885, false), // bit 11: 29-bit ids only
        (0x1005, 0, 0x0001_0090, false), // bit 16: 29-bit ids only
        (0x100E, 0, 0x0000_0BA5, false), // bit 11
        (0x1800, 1, 0x8010_0285, false), // bit 20
        (0x1014, 0, 0x0000_0300, true),  // valid, another CAN-ID: a write needs bit 31 first
        (0x1800, 1, 0xA000_0185, false), // 29-bit, not valid
        (0x1800, 1, 0x0000_0123, false), // restricted
        (0x1800, 1, 0x8000_0285, true),
        (0x1800, 2, 245, false), // reserved transmission type (D10)
        (0x1800, 2, 1, true),
        (0x1A00, 1, 0x1000_0020, false), // 0x1000 is not mappable
        (0x1A00, 1, 0x6020_0220, true),
        (0x1A00, 0, 9, false), // more entries than the record has
    ];
    let mut fresh = boot_with(&[]);
    for &(index, sub, v, loads) in cases {
        let default = fresh.read_object(index as u16, sub as u8).unwrap();
        assert_ne!(default, v);
        // What an SDO write of `v` to the defaults gets (mapping entries with sub 0 at 0 first).
        let mut r = Rig::with_config(&TH, TH.default_config.with_node_id(5));
        r.take();
        if index == 0x1A00 && sub > 0 {
            r.req(0x605, &hex("2F 00 1A 00 00 00 00 00"));
        }
        let cs = if index == 0x1800 && sub == 2 || index == 0x1A00 && sub == 0 {
            0x2F
        } else {
            0x23
        };
        let mut req = vec![cs, index as u8, (index >> 8) as u8, sub as u8];
        req.extend_from_slice(&v.to_le_bytes());
        let accepted = r.req(0x605, &req).1[0] == 0x60;
        let transition_only = index == 0x1014 && v == 0x300;
        assert_eq!(
            accepted,
            loads && !transition_only,
            "{index:04X}/{sub} = {v:08X}"
        );
        let mut node = boot_with(&[(key(index, sub), v)]);
        let loaded = node.read_object(index as u16, sub as u8).unwrap();
        let expect = if loads { v } else { default };
        assert_eq!(
            loaded, expect,
            "{index:04X}/{sub} = {v:08X} from the state file"
        );
    }
}
