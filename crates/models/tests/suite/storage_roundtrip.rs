//! Every stored object of every model survives "save" and a power cycle, with its effect, and
//! the reset scopes reload what D6 says. Generated from the model tables: the objects under
//! test are the table's writable entries in a stored group, so an object added to a table is
//! covered without touching this file, and an object whose group the manual contradicts fails
//! the membership checks below.

use crate::common::{booted, model, Rig};
use canpos_encoder::Sample;
use canpos_models::Model;
use canpos_stack::od::{DataType, Entry, Group, Hook, Range};
use canpos_stack::storage::Scope;
use canpos_stack::{Frame, Instant};

/// The entries "save" (0x1010/1) covers that a master can write.
fn stored_rw(m: &'static Model) -> impl Iterator<Item = &'static Entry> {
    m.entries
        .iter()
        .filter(|e| e.access.writable() && Scope::All.covers(e))
}

/// The node's active id, from its SDO server's view (0x100B where present is not on TMI).
fn node_id(r: &Rig) -> u8 {
    r.node.device().node_id()
}

fn sdo(r: &mut Rig, req: [u8; 8]) -> [u8; 8] {
    let id = node_id(r) as u16;
    let mut answers: Vec<Frame> = r
        .send(0x600 + id, &req)
        .into_iter()
        .filter(|f| f.std_id() == Some(0x580 + id))
        .collect();
    if answers.is_empty() {
        // A store answers after its store time (D7).
        answers = r
            .advance_ms(30)
            .into_iter()
            .map(|(_, f)| f)
            .filter(|f| f.std_id() == Some(0x580 + id))
            .collect();
    }
    assert_eq!(answers.len(), 1, "one answer to {req:02X?}");
    answers[0].data().try_into().unwrap()
}

/// Expedited download of the entry's size: Ok or the abort code.
fn write(r: &mut Rig, index: u16, sub: u8, size: usize, v: u32) -> Result<(), u32> {
    let i = index.to_le_bytes();
    let b = v.to_le_bytes();
    let mut req = [0x23 | ((4 - size as u8) << 2), i[0], i[1], sub, 0, 0, 0, 0];
    req[4..4 + size].copy_from_slice(&b[..size]);
    let a = sdo(r, req);
    match a[0] {
        0x60 => Ok(()),
        _ => Err(u32::from_le_bytes([a[4], a[5], a[6], a[7]])),
    }
}

fn read(r: &mut Rig, index: u16, sub: u8) -> u32 {
    let i = index.to_le_bytes();
    let a = sdo(r, [0x40, i[0], i[1], sub, 0, 0, 0, 0]);
    assert_eq!(a[0] & 0xF3, 0x43, "read {index:04X}:{sub}: {a:02X?}");
    u32::from_le_bytes([a[4], a[5], a[6], a[7]])
}

fn save(r: &mut Rig) {
    assert_eq!(write(r, 0x1010, 1, 4, u32::from_le_bytes(*b"save")), Ok(()));
}

fn size(e: &Entry) -> usize {
    e.ty.size().unwrap()
}

/// Writes a valid value other than the default to `e` the way a master would (PDO mapping
/// entries with their count at 0, as the manuals' procedure says) and returns what the object
/// must read afterwards.
fn write_other(r: &mut Rig, e: &Entry) -> u32 {
    let cur = read(r, e.index, e.sub);
    let v = match (e.hook, e.sub) {
        (Hook::SyncCobId, _) => 0x81,
        (Hook::GuardingCobId, _) => 0x300,
        // A valid EMCY COB-ID's CAN-ID cannot change: invalidate first, then a new one.
        (Hook::EmcyCobId, _) => {
            write(r, e.index, e.sub, 4, cur | 0x8000_0000).unwrap();
            0x85
        }
        (Hook::TpdoComm, 1) => {
            if cur & 0x8000_0000 == 0 {
                write(r, e.index, e.sub, 4, cur | 0x8000_0000).unwrap();
            }
            // A CAN-ID no pre-defined COB-ID uses, valid.
            0x2A0 + (e.index & 0xF) as u32
        }
        (Hook::TpdoComm, 2) => [1, 0xFE, 0]
            .into_iter()
            .find(|&t| t != cur && e.accepts(t))
            .unwrap(),
        // Below the TMI's rule "event timer above the inhibit time" (R27).
        (Hook::TpdoComm, 3) => 5,
        (Hook::TpdoComm, 5) => 100,
        (Hook::TpdoMap, 0) => {
            if cur > 0 {
                cur - 1
            } else {
                // One entry counted: it must name a mappable object (a one-channel TMI's
                // TPDO2 has none by default).
                if read(r, e.index, 1) == 0 {
                    write(r, e.index, 1, 4, 0x6300_0108).unwrap();
                }
                1
            }
        }
        (Hook::TpdoMap, _) => {
            // An 8-bit object every model maps (TMI: 0x6020, 0x6030, 0x6300, 0x6400 only), so
            // the PDO stays within 8 bytes.
            let v = if cur == 0x6300_0108 {
                0x6400_0108
            } else {
                0x6300_0108
            };
            let count = read(r, e.index, 0);
            write(r, e.index, 0, 1, 0).unwrap();
            write(r, e.index, e.sub, 4, v).unwrap();
            write(r, e.index, 0, 1, count).unwrap();
            return v;
        }
        (Hook::PendingNodeId, _) => 9,
        (Hook::PendingBitRate, _) => 250,
        _ => match (e.ty, e.range) {
            (DataType::Boolean, _) => cur ^ 1,
            (_, Range::MinMax(..)) => {
                let (lo, hi) = e.limits().unwrap();
                // Whole µm for a measuring step (R31): the top of the range.
                if e.ty.to_i64(cur) == hi {
                    lo as u32
                } else {
                    hi as u32
                }
            }
            (_, Range::OneOf(list)) => *list.iter().find(|&&v| v != cur).unwrap(),
            (DataType::Unsigned8, Range::Any) if e.index == 0x6301 || e.index == 0x6302 => 0x0F,
            (DataType::Unsigned16, Range::Any) if e.index == 0x6000 => cur ^ 1,
            (DataType::Unsigned16 | DataType::Unsigned8, Range::Any) => cur + 5,
            (_, Range::Any) => cur.wrapping_add(1234),
        },
    };
    assert_eq!(
        write(r, e.index, e.sub, size(e), v),
        Ok(()),
        "{:04X}:{} = {v:#X}",
        e.index,
        e.sub
    );
    v
}

/// The generated round trip: every stored rw object, one at a time on a fresh unit.
fn round_trip(m: &'static Model) -> usize {
    round_trip_with(m, m.default_config)
}

/// [`round_trip`] of a unit configured as `cfg` (its own dictionary: a two-channel TMI's).
fn round_trip_with(m: &'static Model, cfg: canpos_models::DeviceConfig) -> usize {
    let unit = canpos_models::for_unit(m, &cfg);
    let mut n = 0;
    for e in stored_rw(unit) {
        let mut r = Rig::booted_with(m, cfg);
        let v = write_other(&mut r, e);
        save(&mut r);
        r.power_cycle();
        let back = read(&mut r, e.index, e.sub);
        assert_eq!(
            back, v,
            "{} {:04X}:{} after save + power cycle",
            m.name, e.index, e.sub
        );
        n += 1;
    }
    n
}

/// The generated reset scopes (D6): per stored rw object, a saved value, then an unsaved one;
/// reset communication brings the saved value back for communication objects only, reset node
/// for every object. Objects whose second valid value equals the first are counted apart.
fn scope_round_trip(m: &'static Model) -> (usize, usize) {
    let (mut checked, mut same) = (0, 0);
    for e in stored_rw(m) {
        let mut r = Rig::booted(m);
        let v = write_other(&mut r, e);
        save(&mut r);
        let w = write_other(&mut r, e);
        if w == v {
            same += 1;
            continue;
        }
        let what = format!("{} {:04X}:{}", m.name, e.index, e.sub);
        let id = node_id(&r);
        r.send(0x000, &[0x82, id]);
        r.take();
        let want = if e.reset_by_comm() { v } else { w };
        assert_eq!(
            read(&mut r, e.index, e.sub),
            want,
            "{what} after reset communication"
        );
        let id = node_id(&r);
        r.send(0x000, &[0x81, id]);
        r.take();
        assert_eq!(read(&mut r, e.index, e.sub), v, "{what} after reset node");
        checked += 1;
    }
    (checked, same)
}

#[test]
fn every_stored_object_reloads_in_its_reset_scope() {
    for name in ["th", "e-series", "tmi"] {
        let (checked, same) = scope_round_trip(model(name));
        assert!(
            checked > 30,
            "{name}: {checked} checked, {same} without a second value"
        );
    }
}

#[test]
fn th_every_stored_object_survives_a_power_cycle() {
    assert!(round_trip(model("th")) > 40);
}

#[test]
fn e_series_every_stored_object_survives_a_power_cycle() {
    assert!(round_trip(model("e-series")) > 40);
}

#[test]
fn tmi_every_stored_object_survives_a_power_cycle() {
    // One channel (the default unit) and two.
    assert!(round_trip(model("tmi")) > 25);
    let tmi = model("tmi");
    assert!(round_trip_with(tmi, tmi.default_config.with_channels(2)) > 40);
}

/// TH and E-Series: the manuals list every rw parameter as stored; only the commands (0x1010,
/// 0x1011) and the error history (0x1003/0, which a write clears) are not parameters.
#[test]
fn th_and_e_series_store_every_rw_object() {
    for m in [model("th"), model("e-series")] {
        for e in m.entries.iter().filter(|e| e.access.writable()) {
            let command = matches!(
                e.hook,
                Hook::StoreParameters | Hook::RestoreDefaults | Hook::ErrorHistory
            );
            assert_eq!(
                e.group != Group::Volatile,
                !command,
                "{} {:04X}:{} group {:?}",
                m.name,
                e.index,
                e.sub,
                e.group
            );
        }
    }
}

/// TMI 002 §1.16: the storage table's objects, and only those, are stored by "save" (0x1018/2
/// and /4 are the unit's system data there, re-derived at every power-up, see the model).
#[test]
fn tmi_stores_the_manuals_table() {
    let mut listed: Vec<(u16, u8)> = vec![
        (0x1800, 1),
        (0x1800, 2),
        (0x1800, 3),
        (0x1800, 5),
        (0x1801, 1),
        (0x1801, 2),
        (0x1801, 3),
        (0x1017, 0),
        (0x2000, 0),
        (0x2001, 0),
        (0x6005, 1),
        (0x6005, 2),
    ];
    for i in [0x1A00, 0x1A01] {
        listed.extend((0..=5).map(|s| (i, s)));
    }
    for i in [0x6010, 0x6302, 0x6401, 0x6402] {
        listed.extend([(i, 1), (i, 2)]);
    }
    for i in (0x6310..=0x6313)
        .chain(0x6320..=0x6323)
        .chain(0x6330..=0x6333)
    {
        listed.extend([(i, 1), (i, 2)]);
    }
    listed.sort();
    // The two-channel unit (the one-channel unit has channel-1 objects only).
    let mut stored: Vec<(u16, u8)> = canpos_models::tmi::TMI_TWO_CHANNELS
        .entries
        .iter()
        .filter(|e| Scope::All.covers(e))
        .map(|e| (e.index, e.sub))
        .collect();
    stored.sort();
    assert_eq!(stored, listed);
}

/// Effects after the power cycle, not just values: moved COB-IDs move the frames, a stored
/// heartbeat beats, a stored preset moves the position.
#[test]
fn stored_objects_take_effect_after_a_power_cycle() {
    for name in ["th", "e-series", "tmi"] {
        let m = model(name);
        let mut r = Rig::booted(m);
        // EMCY to 0x85 where it is stored (TMI §1.16 does not list 0x1014).
        let emcy_stored = m
            .entries
            .iter()
            .any(|e| e.hook == Hook::EmcyCobId && Scope::All.covers(e));
        if emcy_stored {
            write(&mut r, 0x1014, 0, 4, 0x8000_00FF).unwrap();
            write(&mut r, 0x1014, 0, 4, 0x85).unwrap();
        }
        // TPDO1 to 0x2A0.
        write(&mut r, 0x1800, 1, 4, 0x8000_01FF).unwrap();
        write(&mut r, 0x1800, 1, 4, 0x2A0).unwrap();
        write(&mut r, 0x1017, 0, 2, 50).unwrap();
        write(&mut r, 0x6010, 1, 4, 4242).unwrap();
        save(&mut r);
        let boot = r.power_cycle();
        if emcy_stored {
            assert!(
                boot.iter().any(|f| f.std_id() == Some(0x85)),
                "{name}: power-on EMCY on the stored COB-ID: {boot:?}"
            );
        }
        // Heartbeat every 50 ms.
        let hb: Vec<Instant> = r
            .advance_ms(160)
            .into_iter()
            .filter(|(_, f)| f.std_id() == Some(0x77F))
            .map(|(t, _)| t)
            .collect();
        assert_eq!(hb.len(), 3, "{name}: heartbeats {hb:?}");
        assert_eq!(hb[1].micros() - hb[0].micros(), 50_000);
        // The preset's offset came back: the first measurement reads the preset's frame of
        // reference, not the raw position.
        let mut s = Sample::default();
        s.positions_nm[0] = Some(100_000_000);
        r.node.update_sample(&s, r.now);
        let raw_steps = 100_000_000 / r.node.device().config().position_step_nm as i64;
        let pos = r.node.read_object(0x6020, 1).unwrap() as i32 as i64;
        assert_ne!(pos, raw_steps, "{name}: preset lost its effect");
        // Operational: TPDO1 on 0x2A0.
        r.send(0x000, &[0x01, 0x7F]);
        let f = r.advance_ms(20);
        assert!(
            f.iter().any(|(_, f)| f.std_id() == Some(0x2A0)),
            "{name}: TPDO1 on the stored COB-ID"
        );
        assert!(f.iter().all(|(_, f)| f.std_id() != Some(0x1FF)));
    }
}

/// A stored preset gives the same magnet position the same reading after a power cycle (the
/// offset in 0x650C on TH / E-Series, kept inside the TMI and stored with 0x6010).
#[test]
fn a_stored_preset_keeps_the_position_across_a_power_cycle() {
    for name in ["th", "e-series", "tmi"] {
        let m = model(name);
        let mut r = Rig::booted(m);
        let mut s = Sample::default();
        s.positions_nm[0] = Some(250_000_000);
        r.node.update_sample(&s, r.now);
        let raw = r.node.read_object(0x6020, 1).unwrap() as i32;
        write(&mut r, 0x6010, 1, 4, 1000).unwrap();
        let preset = r.node.read_object(0x6020, 1).unwrap() as i32;
        // CiA 406 on every model: the current position reads the preset (issue 36 item 5).
        assert_ne!(raw, 1000, "{name}");
        let expected = 1000;
        assert_eq!(preset, expected, "{name}");
        save(&mut r);
        r.power_cycle();
        r.node.update_sample(&s, r.now);
        assert_eq!(
            r.node.read_object(0x6020, 1).unwrap() as i32,
            expected,
            "{name}: the same magnet position reads the same after the power cycle"
        );
    }
}

/// D6: reset communication reloads the communication objects from storage (or their
/// defaults), reset node also the application objects; unsaved values go.
#[test]
fn reset_scopes_reload_what_d6_says() {
    for name in ["th", "e-series", "tmi"] {
        let m = model(name);
        let mut r = Rig::booted(m);
        write(&mut r, 0x1017, 0, 2, 100).unwrap();
        write(&mut r, 0x6010, 1, 4, 77).unwrap();
        save(&mut r);
        write(&mut r, 0x1017, 0, 2, 200).unwrap();
        write(&mut r, 0x6010, 1, 4, 88).unwrap();
        // Reset communication: 0x1017 back to the stored 100, 0x6010 untouched.
        r.send(0x000, &[0x82, 0x7F]);
        r.take();
        assert_eq!(read(&mut r, 0x1017, 0), 100, "{name}");
        assert_eq!(read(&mut r, 0x6010, 1), 88, "{name}");
        // Reset node: 0x6010 back to the stored 77.
        r.send(0x000, &[0x81, 0x7F]);
        r.take();
        assert_eq!(read(&mut r, 0x6010, 1), 77, "{name}");
        // Restore defaults, then reset node: defaults again.
        assert_eq!(
            write(&mut r, 0x1011, 1, 4, u32::from_le_bytes(*b"load")),
            Ok(())
        );
        r.send(0x000, &[0x81, 0x7F]);
        r.take();
        assert_eq!(read(&mut r, 0x1017, 0), 0, "{name}");
        assert_eq!(read(&mut r, 0x6010, 1), 0, "{name}");
    }
}

/// LSS store on TMI keeps 0x2000 / 0x2001 in step: a later "save" and power cycle keep the
/// LSS-configured node-id and bit rate (the commissioning is not lost).
#[test]
fn tmi_lss_store_then_save_keeps_the_new_node_id() {
    let mut r = booted("tmi");
    // LSS: node-id 9, bit rate 250 kbit/s (table index 3), store.
    r.lss_configure(&[
        "11 09 00 00 00 00 00 00",
        "13 00 03 00 00 00 00 00",
        "17 00 00 00 00 00 00 00",
    ]);
    // 0x2000 / 0x2001 already say what the next reset activates.
    assert_eq!(read(&mut r, 0x2000, 0), 9);
    assert_eq!(read(&mut r, 0x2001, 0), 250);
    save(&mut r);
    let boot = r.power_cycle();
    assert_eq!(boot[0].std_id(), Some(0x709), "{boot:?}");
    assert_eq!(r.node.device().bitrate(), 250);
    assert_eq!(read(&mut r, 0x2000, 0), 9);
}

/// TMI R17 / R19: a node-id and bit rate written to 0x2000 / 0x2001 and saved after an LSS
/// store are the newer ones: at power-on the saved object copies win over the LSS records.
#[test]
fn tmi_saved_object_copies_win_over_the_lss_records() {
    let mut r = booted("tmi");
    // LSS: node-id 9, bit rate 250 kbit/s (table index 3), store.
    r.lss_configure(&[
        "11 09 00 00 00 00 00 00",
        "13 00 03 00 00 00 00 00",
        "17 00 00 00 00 00 00 00",
    ]);
    write(&mut r, 0x2000, 0, 1, 5).unwrap();
    write(&mut r, 0x2001, 0, 2, 500).unwrap();
    save(&mut r);
    let boot = r.power_cycle();
    assert_eq!(boot[0].std_id(), Some(0x705), "{boot:?}");
    assert_eq!(r.node.device().bitrate(), 500);
    assert_eq!(read(&mut r, 0x2000, 0), 5);
}

/// CiA 301 §7.5.2.13: 0x1010 sub 3 saves the application parameters only. Generated: for each
/// model whose table has subs 2 and 3 (the TMI), one writable communication and one writable
/// application object get new values; after "save" on sub 3 and a power cycle the application
/// value is kept and the communication value is back at its default. Sub 2 is the mirror image.
#[test]
fn cia301_7_5_2_13_save_sub_2_and_3_cover_their_own_group_only() {
    let models = ["th", "e-series", "tmi"].map(model);
    let with_subs = models
        .iter()
        .filter(|m| m.entries.iter().any(|e| e.index == 0x1010 && e.sub == 3));
    let mut tested = 0;
    for m in with_subs {
        let name = m.name;
        tested += 1;
        let simple = |e: &&Entry| {
            !matches!(
                e.hook,
                Hook::PendingNodeId | Hook::PendingBitRate | Hook::TpdoMap | Hook::TpdoComm
            )
        };
        let comm = stored_rw(m)
            .filter(|e| Scope::Comm.covers(e))
            .find(simple)
            .unwrap();
        let app = stored_rw(m)
            .filter(|e| Scope::App.covers(e))
            .find(simple)
            .unwrap();
        for (sub, kept, lost) in [(3u8, app, comm), (2, comm, app)] {
            let mut r = Rig::booted(m);
            let default_lost = read(&mut r, lost.index, lost.sub);
            let v_kept = write_other(&mut r, kept);
            write_other(&mut r, lost);
            assert_eq!(
                write(&mut r, 0x1010, sub, 4, u32::from_le_bytes(*b"save")),
                Ok(()),
                "{name} 0x1010/{sub}"
            );
            r.power_cycle();
            let what = |e: &Entry| format!("{name} 0x1010/{sub}: {:04X}:{}", e.index, e.sub);
            assert_eq!(
                read(&mut r, kept.index, kept.sub),
                v_kept,
                "{} kept",
                what(kept)
            );
            assert_eq!(
                read(&mut r, lost.index, lost.sub),
                default_lost,
                "{} not saved",
                what(lost)
            );
        }
    }
    assert!(tested > 0, "no model has 0x1010/3");
}

/// CiA 301 §7.5.2.14 / CiA 305: restoring the default parameters (0x1011/1 "load") concerns
/// the parameters, not the LSS configuration: a node-id stored through LSS stays after the
/// restore and a power cycle, while the saved parameters are back at their defaults.
#[test]
fn cia301_7_5_2_14_restore_defaults_keeps_the_lss_stored_node_id() {
    let mut r = booted("th");
    // LSS: node-id 9, store.
    r.lss_configure(&["11 09 00 00 00 00 00 00", "17 00 00 00 00 00 00 00"]);
    let boot = r.power_cycle();
    assert_eq!(boot[0].std_id(), Some(0x709), "{boot:?}");
    write(&mut r, 0x1017, 0, 2, 100).unwrap();
    save(&mut r);
    assert_eq!(
        write(&mut r, 0x1011, 1, 4, u32::from_le_bytes(*b"load")),
        Ok(())
    );
    let boot = r.power_cycle();
    assert_eq!(boot[0].std_id(), Some(0x709), "LSS node-id kept: {boot:?}");
    assert_eq!(read(&mut r, 0x1017, 0), 0, "parameters at their defaults");
}
