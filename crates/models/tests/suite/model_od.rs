//! Every model's object dictionary as a master sees it over SDO after boot: sizes, access and
//! defaults equal the table; rw objects take a valid value and give it back; ro / const
//! objects refuse writes with 0x06010002; the default TPDO is byte-exact (TH / E Tables 21/22).

use crate::common::{booted, sample, Rig};
use canpos_encoder::Channels;
use canpos_models::{self as models, DeviceConfig, Model};
use canpos_stack::od::{resolve_default, DefaultValue, Entry, Group, Param, ParamSource, Range};

struct Unit<'a>(&'static Model, &'a DeviceConfig);
impl ParamSource for Unit<'_> {
    fn param(&self, p: Param) -> u32 {
        (self.0.param)(self.1, p)
    }
}

const SDO_RX: u16 = 0x67F;
const SDO_TX: u16 = 0x5FF;

/// Upload: Ok(bytes) or Err(abort code).
fn upload(r: &mut Rig, index: u16, sub: u8) -> Result<Vec<u8>, u32> {
    let i = index.to_le_bytes();
    let (id, d) = r.req(SDO_RX, &[0x40, i[0], i[1], sub, 0, 0, 0, 0]);
    assert_eq!(id, SDO_TX);
    assert_eq!(&d[1..4], &[i[0], i[1], sub], "multiplexer echoed");
    match d[0] {
        0x80 => Err(u32::from_le_bytes([d[4], d[5], d[6], d[7]])),
        c if c & 0xF3 == 0x43 => {
            let n = 4 - ((c >> 2) & 3) as usize;
            Ok(d[4..4 + n].to_vec())
        }
        c => panic!("{index:04X}:{sub}: unexpected command byte {c:02X} (segmented?)"),
    }
}

/// Expedited download of `bytes`; waits for a held answer (store takes ≥ 20 ms, D7).
fn download(r: &mut Rig, index: u16, sub: u8, bytes: &[u8]) -> Result<(), u32> {
    let i = index.to_le_bytes();
    let n = bytes.len();
    assert!((1..=4).contains(&n));
    let mut req = [0x23 | ((4 - n as u8) << 2), i[0], i[1], sub, 0, 0, 0, 0];
    req[4..4 + n].copy_from_slice(bytes);
    let mut answers: Vec<Vec<u8>> = r
        .send(SDO_RX, &req)
        .into_iter()
        .filter(|f| f.std_id() == Some(SDO_TX))
        .map(|f| f.data().to_vec())
        .collect();
    if answers.is_empty() {
        answers = r
            .advance_ms(30)
            .into_iter()
            .filter(|(_, f)| f.std_id() == Some(SDO_TX))
            .map(|(_, f)| f.data().to_vec())
            .collect();
    }
    assert_eq!(answers.len(), 1, "{index:04X}:{sub}: one answer");
    let d = &answers[0];
    assert_eq!(&d[1..4], &[i[0], i[1], sub]);
    match d[0] {
        0x60 => Ok(()),
        0x80 => Err(u32::from_le_bytes([d[4], d[5], d[6], d[7]])),
        c => panic!("unexpected {c:02X}"),
    }
}

fn le(v: u32, n: usize) -> Vec<u8> {
    v.to_le_bytes()[..n].to_vec()
}

fn expected(model: &'static Model, cfg: &DeviceConfig, e: &Entry) -> Option<Vec<u8>> {
    match e.default {
        DefaultValue::Live => None,
        DefaultValue::Str(s) => Some(s.as_bytes().to_vec()),
        _ => {
            let v = resolve_default(e, &Unit(model, cfg), cfg.node_id);
            Some(le(v, e.ty.size().unwrap()))
        }
    }
}

/// A valid value different from `cur` where the object allows one (else `cur`).
fn other_value(e: &Entry, cur: u32) -> u32 {
    match (e.index, e.sub) {
        (0x1003, 0) => 0,
        (0x1005, _) => 0x81,
        // Guarding moves to a CAN-ID no service reserves.
        (0x100E, _) => 0x300,
        // Toggle "not valid" (allowed while valid, SPEC §5) keeping the CAN-ID.
        (0x1014, _) | (0x1800..=0x1803, 1) => cur ^ 0x8000_0000,
        (0x6000, _) => cur ^ 1,
        (0x6301 | 0x6302, _) => 0x0F,
        (0x1A00..=0x1A03, 0) => cur,
        // Cam state of channel 1: every model maps it (the TMI no communication object, 002
        // §1.2.5), and no default entry is it (TH's TPDO1 maps it third).
        (0x1A00..=0x1A03, _) if cur != 0x6400_0108 => 0x6400_0108,
        (0x1A00..=0x1A03, _) => 0x6300_0108,
        _ => match e.range {
            Range::MinMax(..) => {
                let (lo, hi) = e.limits().unwrap();
                if e.ty.to_i64(cur) == lo {
                    hi as u32
                } else {
                    lo as u32
                }
            }
            Range::OneOf(list) => *list.iter().find(|&&v| v != cur).unwrap_or(&cur),
            Range::Any => cur ^ 1,
        },
    }
}

fn check_model(model: &'static Model) {
    let cfg = model.default_config;
    let mut r = Rig::booted(model);
    for e in model.entries {
        let what = format!("{} {:04X}:{}", model.name, e.index, e.sub);
        if e.index == 0x1003 && e.sub > 0 {
            // Empty error history: its entries hold no data (conformance EMCY-03).
            assert_eq!(upload(&mut r, e.index, e.sub), Err(0x0800_0024), "{what}");
            continue;
        }
        let got =
            upload(&mut r, e.index, e.sub).unwrap_or_else(|a| panic!("{what}: abort {a:08X}"));
        let size = e.ty.size().unwrap_or(match e.default {
            DefaultValue::Str(s) => s.len(),
            _ => 0,
        });
        assert_eq!(got.len(), size, "{what}: size");
        // 0x1010 / 0x1011 read 1 (D7); their table default says so.
        if let Some(exp) = expected(model, &cfg, e) {
            assert_eq!(got, exp, "{what}: default");
        }
    }
    // Writes.
    for e in model.entries {
        let what = format!("{} {:04X}:{}", model.name, e.index, e.sub);
        let n = e.ty.size().unwrap_or(4).min(4);
        let cur = u32::from_le_bytes({
            let mut b = [0u8; 4];
            // 1003:n has no data while the history is empty: its write check uses 0.
            let g = upload(&mut r, e.index, e.sub).unwrap_or_default();
            b[..g.len()].copy_from_slice(&g);
            b
        });
        if !e.access.writable() {
            assert_eq!(
                download(&mut r, e.index, e.sub, &le(cur, n)),
                Err(0x0601_0002),
                "{what}: read-only"
            );
            continue;
        }
        if matches!(e.index, 0x1010 | 0x1011) {
            let sig: &[u8] = if e.index == 0x1010 { b"save" } else { b"load" };
            assert_eq!(
                download(&mut r, e.index, e.sub, sig),
                Ok(()),
                "{what}: signature"
            );
            assert_eq!(
                upload(&mut r, e.index, e.sub),
                Ok(le(1, 4)),
                "{what}: reads 1"
            );
            continue;
        }
        let mapping_entry = (0x1A00..=0x1A03).contains(&e.index) && e.sub > 0;
        let count = if mapping_entry {
            let c = upload(&mut r, e.index, 0).unwrap()[0];
            assert_eq!(download(&mut r, e.index, 0, &[0]), Ok(()));
            c
        } else {
            0
        };
        // Write-back of the current value, then a different valid value, then restore.
        assert_eq!(
            download(&mut r, e.index, e.sub, &le(cur, n)),
            Ok(()),
            "{what}: write-back"
        );
        let v = other_value(e, cur);
        assert_eq!(
            download(&mut r, e.index, e.sub, &le(v, n)),
            Ok(()),
            "{what}: write {v:#X}"
        );
        assert_eq!(
            upload(&mut r, e.index, e.sub),
            Ok(le(v, n)),
            "{what}: read back"
        );
        assert_eq!(
            download(&mut r, e.index, e.sub, &le(cur, n)),
            Ok(()),
            "{what}: restore"
        );
        if mapping_entry {
            assert_eq!(download(&mut r, e.index, 0, &[count]), Ok(()));
        }
    }
}

#[test]
fn th_objects_sizes_access_defaults() {
    check_model(models::by_name("th").unwrap());
}

#[test]
fn e_series_objects_sizes_access_defaults() {
    check_model(models::by_name("e-series").unwrap());
}

#[test]
fn tmi_objects_sizes_access_defaults() {
    check_model(models::by_name("tmi").unwrap());
}

#[test]
fn identity_spot_checks_against_od_md() {
    let mut r = booted("th");
    assert_eq!(upload(&mut r, 0x1018, 1), Ok(le(0x40, 4)));
    assert_eq!(upload(&mut r, 0x1018, 2), Ok(le(0x4333_3034, 4)));
    assert_eq!(upload(&mut r, 0x1018, 3), Ok(le(0x0001_0005, 4)));
    assert_eq!(upload(&mut r, 0x1018, 4), Ok(le(17_143_876, 4)));
    assert_eq!(upload(&mut r, 0x1008, 0), Ok(b"C304".to_vec()));
    assert_eq!(upload(&mut r, 0x100E, 0), Ok(le(0x77F, 4)));
    assert_eq!(upload(&mut r, 0x6507, 0), Ok(le(0x0301_0401, 4)), "D4");
    assert_eq!(upload(&mut r, 0x6005, 2), Ok(le(50, 4)), "D18: 5 µm, 1 ms");
    assert_eq!(upload(&mut r, 0x1A00, 3), Ok(le(0x6300_0108, 4)));
    assert_eq!(upload(&mut r, 0x1A00, 8), Ok(le(0, 4)), "8 mapping entries");
    assert_eq!(
        upload(&mut r, 0x6320, 1),
        Err(0x0602_0000),
        "D5: no high limits on TH"
    );

    let e = models::by_name("e-series").unwrap();
    let mut r = Rig::booted(e);
    assert_eq!(upload(&mut r, 0x1018, 2), Ok(le(0x0E, 4)), "D17");
    assert_eq!(upload(&mut r, 0x1018, 3), Ok(le(0x0309_0001, 4)), "D17");
    assert_eq!(upload(&mut r, 0x1008, 0), Ok(b"MTS".to_vec()));
    assert_eq!(upload(&mut r, 0x1800, 1), Ok(le(0x4000_01FF, 4)));
    assert_eq!(upload(&mut r, 0x1801, 1), Ok(le(0xC000_02FF, 4)));
    assert_eq!(upload(&mut r, 0x1A00, 3), Ok(le(0x6400_0108, 4)));
    assert_eq!(upload(&mut r, 0x6506, 0), Ok(le(0x7000, 2)));
    assert_eq!(upload(&mut r, 0x6508, 0), Ok(le(0xFFFF_FFFF, 4)));
    assert_eq!(upload(&mut r, 0x6005, 2), Ok(le(100, 4)), "D18: 10 µm");
    assert_eq!(
        upload(&mut r, 0x650A, 3),
        Ok(le(100_000, 4)),
        "D20: 1000 mm / 10 µm"
    );
    assert_eq!(upload(&mut r, 0x100B, 0), Err(0x0602_0000));

    let t = models::by_name("tmi").unwrap();
    let mut r = Rig::booted(t);
    assert_eq!(upload(&mut r, 0x1018, 1), Ok(le(0x182, 4)));
    assert_eq!(upload(&mut r, 0x1018, 3), Ok(le(0x0002_0003, 4)));
    // 500 mm, 1 µm minimum step, one channel.
    assert_eq!(upload(&mut r, 0x1018, 2), Ok(le(500, 4)));
    assert_eq!(upload(&mut r, 0x2000, 0), Ok(vec![0x7F]), "D16");
    assert_eq!(upload(&mut r, 0x2001, 0), Ok(le(250, 2)), "D16");
    assert_eq!(upload(&mut r, 0x1010, 0), Ok(vec![3]), "D7");
    assert_eq!(upload(&mut r, 0x1A00, 0), Ok(vec![4]), "D21");
    assert_eq!(
        upload(&mut r, 0x1A00, 6),
        Err(0x0609_0011),
        "5 entries at most"
    );
    assert_eq!(
        upload(&mut r, 0x1801, 1),
        Ok(le(0xC000_02FF, 4)),
        "D21: one channel"
    );
    assert_eq!(upload(&mut r, 0x6005, 2), Ok(le(250, 4)), "D18");
    assert_eq!(
        upload(&mut r, 0x100C, 0),
        Err(0x0602_0000),
        "no node guarding"
    );
    // 0x1002 bits 1–0: pre-operational.
    assert_eq!(upload(&mut r, 0x1002, 0), Ok(le(0b01, 4)));
    // R31: position step in whole µm, from the minimum up to 100 µm.
    assert_eq!(download(&mut r, 0x6005, 1, &le(2500, 4)), Err(0x0609_0030));
    assert_eq!(
        download(&mut r, 0x6005, 1, &le(101_000, 4)),
        Err(0x0609_0031)
    );
    assert_eq!(download(&mut r, 0x6005, 1, &le(7000, 4)), Ok(()));
    assert_eq!(download(&mut r, 0x6005, 2, &le(30, 4)), Err(0x0609_0030));
    assert_eq!(
        download(&mut r, 0x2001, 0, &le(0xFFFF, 2)),
        Ok(()),
        "autobaud"
    );
    assert_eq!(download(&mut r, 0x2001, 0, &le(300, 2)), Err(0x0609_0030));
    assert_eq!(download(&mut r, 0x2000, 0, &[0]), Err(0x0609_0032));

    // Two-channel TMI with 5 µm minimum: product code bits 31 / 30, TPDO2 valid (D21).
    let cfg = t.configure(t.default_config.with_channels(2).with_step_nm(5000));
    let mut r = Rig::with_config(t, cfg);
    r.take();
    assert_eq!(upload(&mut r, 0x1018, 2), Ok(le(0xC000_01F4, 4)));
    assert_eq!(upload(&mut r, 0x1000, 0), Ok(le(0x000A_0196, 4)), "D1");
    assert_eq!(upload(&mut r, 0x1801, 1), Ok(le(0x4000_02FF, 4)));
    assert_eq!(upload(&mut r, 0x1801, 2), Ok(vec![1]));
    assert_eq!(
        download(&mut r, 0x6005, 1, &le(4000, 4)),
        Err(0x0609_0032),
        "below minimum"
    );
}

#[test]
fn d2_operating_parameters_only_bit_0() {
    for m in ["th", "e-series", "tmi"] {
        let mut r = booted(m);
        assert_eq!(
            download(&mut r, 0x6000, 0, &le(2, 2)),
            Err(0x0609_0030),
            "{m}"
        );
        assert_eq!(download(&mut r, 0x6000, 0, &le(1, 2)), Ok(()), "{m}");
        assert_eq!(
            upload(&mut r, 0x6500, 0),
            Ok(le(1, 2)),
            "{m}: 0x6500 mirrors"
        );
    }
}

#[test]
fn storage_groups_follow_the_manuals() {
    let th = models::by_name("th").unwrap();
    let g = |m: &Model, i: u16, s: u8| {
        m.entries
            .iter()
            .find(|e| e.index == i && e.sub == s)
            .unwrap()
            .group
    };
    assert_eq!(g(th, 0x2101, 0), Group::App, "D19");
    assert_eq!(g(th, 0x2901, 4), Group::Auto, "D19");
    let tmi = &models::tmi::TMI_TWO_CHANNELS;
    assert_eq!(g(tmi, 0x6301, 1), Group::Volatile, "not in the §1.16 list");
    assert_eq!(g(tmi, 0x6330, 2), Group::App);
    assert_eq!(g(tmi, 0x1017, 0), Group::Comm);
}

/// The magnet at 123.455 mm, 1 ms later at 123.555 mm, then NMT start: the one TPDO1 of the
/// next millisecond.
fn tpdo1_after_0_1_mm_in_1_ms(r: &mut Rig) -> Vec<u8> {
    r.node.update_sample(&sample(&[Some(123_455_000)]), r.now);
    r.advance_ms(1);
    r.node.update_sample(&sample(&[Some(123_555_000)]), r.now);
    r.take();
    r.send(0x000, &[0x01, 0x7F]);
    let f: Vec<_> = r
        .advance_ms(1)
        .into_iter()
        .filter(|(_, f)| f.std_id() == Some(0x1FF))
        .collect();
    assert_eq!(f.len(), 1);
    f[0].1.data().to_vec()
}

/// TH Table 22 / E Table 21: position LE u32, velocity LE i16, state byte; DLC 7.
#[test]
fn default_tpdo_is_byte_exact() {
    // TH: 123.455 mm then +0.1 mm in 1 ms (100 mm/s): 24711 steps of 5 µm, 200 × 0.5 mm/s.
    let th = models::by_name("th").unwrap();
    let mut r = Rig::booted(th);
    assert_eq!(
        tpdo1_after_0_1_mm_in_1_ms(&mut r),
        [0x87, 0x60, 0x00, 0x00, 0xC8, 0x00, 0x00]
    );

    // E-Series: 123.555 mm = 12355.5 steps of 10 µm → 12356 (to nearest, halves up), 100 × 1
    // mm/s; work-area high limit 1000 → bit 1.
    let e = models::by_name("e-series").unwrap();
    let mut r = Rig::booted(e);
    assert_eq!(download(&mut r, 0x6402, 1, &le(1000, 4)), Ok(()));
    assert_eq!(
        tpdo1_after_0_1_mm_in_1_ms(&mut r),
        [0x44, 0x30, 0x00, 0x00, 0x64, 0x00, 0x02]
    );
}

#[test]
fn per_node_state_fits_4_kib() {
    use canpos_encoder::Encoder;
    use canpos_stack::storage::NoStorage;
    let node = std::mem::size_of::<canpos_models::SensorNode<NoStorage>>();
    assert!(node <= 4096, "Node is {node} bytes");
    assert!(std::mem::size_of::<Encoder>() <= 512);
    for m in models::all() {
        assert!(
            m.entries.len() <= canpos_stack::od::MAX_ENTRIES,
            "{}",
            m.name
        );
    }
}

/// OD.md 0x6020: TH and E-Series carry up to four position channels (magnets), TMI one or two,
/// each in its own dictionary (002 §1.6).
#[test]
fn most_position_channels_per_model() {
    assert_eq!(models::by_name("th").unwrap().max_channels(), 4);
    assert_eq!(models::by_name("e-series").unwrap().max_channels(), 4);
    let tmi = models::by_name("tmi").unwrap();
    assert_eq!(tmi.max_channels(), 1);
    let two = models::for_unit(tmi, &tmi.default_config.with_channels(2));
    assert_eq!(two.max_channels(), 2);
}

/// OD.md 0x6010…0x6300 sub 0: the CiA 406 per-channel arrays carry their highest sub-index in
/// sub 0 (in the communication area sub 0 can count something else: errors, mapped objects).
#[test]
fn constant_sub_0_is_the_highest_sub_index() {
    for m in models::all() {
        let mut checked = 0;
        for e in m.entries.iter().filter(|e| e.sub == 0 && e.index >= 0x6000) {
            let subs: Vec<_> = m
                .entries
                .iter()
                .filter(|x| x.index == e.index && x.sub > 0)
                .collect();
            let (DefaultValue::Const(n), Some(last)) = (e.default, subs.last()) else {
                continue;
            };
            assert_eq!(n, last.sub as u32, "{} {:04X}", m.name, e.index);
            checked += 1;
        }
        assert!(checked >= 5, "{}: {checked}", m.name);
    }
}

/// Models are found by their command-line names, case-insensitively, E-Series also as `e` and
/// `eseries`; a model prints as its name.
#[test]
fn models_by_name() {
    for (n, want) in [
        ("th", "th"),
        ("TH", "th"),
        ("e", "e-series"),
        ("E", "e-series"),
        ("eseries", "e-series"),
        ("ESeries", "e-series"),
        ("e-series", "e-series"),
        ("tmi", "tmi"),
    ] {
        let m = models::by_name(n).unwrap_or_else(|| panic!("{n}"));
        assert_eq!(m.name, want);
        assert_eq!(format!("{m:?}"), want);
    }
    assert!(models::by_name("x").is_none());
    assert!(models::by_name("").is_none());
}
