//! EDS export (CiA 306): every model's file parses as INI and lists every table object with
//! the table's type, access, default and mapping (CONFORMANCE §1 EDS-01, §13).

use std::collections::BTreeMap;

use canpos_models::{self as models, Model};
use canpos_stack::eds::{write_dcf, write_eds, Commissioning, DcfValue, EdsInfo};
use canpos_stack::od::{
    resolve_default, Access, DataType, DefaultValue, Entry, Group, Param, ParamSource, Range,
};
use canpos_stack::Table;

type Ini = BTreeMap<String, BTreeMap<String, String>>;

/// A small INI reader that refuses what an EDS must not contain: keys outside a section,
/// duplicate sections or keys, lines without '='.
fn parse_ini(text: &str) -> Ini {
    let mut ini = Ini::new();
    let mut current: Option<String> = None;
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with(';') {
            continue;
        }
        if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            assert!(
                ini.insert(name.to_string(), BTreeMap::new()).is_none(),
                "duplicate section [{name}]"
            );
            current = Some(name.to_string());
            continue;
        }
        let (k, v) = line
            .split_once('=')
            .unwrap_or_else(|| panic!("line {}: not key=value: {line}", n + 1));
        let sec = current
            .as_ref()
            .unwrap_or_else(|| panic!("line {}: key outside a section", n + 1));
        let prev = ini
            .get_mut(sec)
            .unwrap()
            .insert(k.trim().to_string(), v.trim().to_string());
        assert!(prev.is_none(), "duplicate key {k} in [{sec}]");
    }
    ini
}

fn eds_of(model: &'static Model) -> String {
    let mut s = String::new();
    let info = EdsInfo {
        file_name: "test.eds",
        ..EdsInfo::default()
    };
    write_eds(&mut s, model, &model.default_config, &info).unwrap();
    s
}

fn objects(model: &Model) -> BTreeMap<u16, Vec<&'static Entry>> {
    let mut m: BTreeMap<u16, Vec<&'static Entry>> = BTreeMap::new();
    for e in model.entries {
        m.entry(e.index).or_default().push(e);
    }
    m
}

fn num(v: &str) -> i64 {
    match v.strip_prefix("0x") {
        Some(h) => i64::from_str_radix(h, 16).unwrap(),
        None => v.parse().unwrap(),
    }
}

#[test]
fn every_model_eds_parses_and_lists_every_object() {
    for model in models::all() {
        let text = eds_of(model);
        let ini = parse_ini(&text);
        let objs = objects(model);

        // Object lists: each listed object has a section, and every object is listed once.
        let mut listed = Vec::new();
        for list in ["MandatoryObjects", "OptionalObjects", "ManufacturerObjects"] {
            let sec = &ini[list];
            let n: usize = sec["SupportedObjects"].parse().unwrap();
            assert_eq!(sec.len(), n + 1, "{} [{list}] count", model.name);
            for i in 1..=n {
                listed.push(num(&sec[&i.to_string()]) as u16);
            }
        }
        listed.sort();
        assert_eq!(
            listed,
            objs.keys().copied().collect::<Vec<_>>(),
            "{}: object lists",
            model.name
        );
        for idx in [0x1000u16, 0x1001, 0x1018] {
            assert!(ini["MandatoryObjects"]
                .values()
                .any(|v| num(v) == idx as i64));
        }

        for (idx, subs) in &objs {
            let head = &ini[&format!("{idx:04X}")];
            let single = subs.len() == 1 && subs[0].sub == 0;
            if !single {
                assert_eq!(head["SubNumber"], subs.len().to_string(), "{idx:04X}");
                let ot = &head["ObjectType"];
                assert!(ot == "0x8" || ot == "0x9", "{idx:04X} ObjectType {ot}");
            }
            for e in subs {
                let sec = if single {
                    head
                } else {
                    &ini[&format!("{idx:04X}sub{:X}", e.sub)]
                };
                let what = format!("{} {:04X}sub{}", model.name, e.index, e.sub);
                assert_eq!(sec["ObjectType"], "0x7", "{what}");
                assert_eq!(num(&sec["DataType"]), e.ty.code() as i64, "{what}");
                assert_eq!(sec["PDOMapping"], (e.pdo as u8).to_string(), "{what}");
                let acc = sec["AccessType"].as_str();
                if e.pdo {
                    assert_eq!(acc, "ro", "{what}: mappable objects are ro (EDS-01)");
                } else {
                    assert_eq!(acc, e.access.eds(), "{what}");
                }
                match e.default {
                    DefaultValue::Live => {
                        assert!(
                            !sec.contains_key("DefaultValue"),
                            "{what}: live, no default"
                        )
                    }
                    DefaultValue::NodeId(base) => {
                        let w = 2 * e.ty.size().unwrap();
                        assert_eq!(
                            sec["DefaultValue"],
                            format!("$NODEID+0x{base:0w$X}"),
                            "{what}"
                        )
                    }
                    DefaultValue::Str(s) => assert_eq!(sec["DefaultValue"], *s, "{what}"),
                    DefaultValue::Const(v) => {
                        assert_eq!(num(&sec["DefaultValue"]), e.ty.to_i64(v), "{what}")
                    }
                    DefaultValue::Param(_) => assert!(sec.contains_key("DefaultValue"), "{what}"),
                }
            }
        }

        let di = &ini["DeviceInfo"];
        assert_eq!(di["NrOfTXPDO"], model.features.tpdos.to_string());
        assert_eq!(di["NrOfRXPDO"], "0");
        assert_eq!(di["LSS_Supported"], "1");
        assert_eq!(
            num(&di["VendorNumber"]),
            model.entries[0..]
                .iter()
                .find(|e| e.index == 0x1018 && e.sub == 1)
                .map(|e| match e.default {
                    DefaultValue::Const(v) => v as i64,
                    _ => -1,
                })
                .unwrap()
        );
        for rate in model.features.bitrates {
            assert_eq!(
                di[&format!("BaudRate_{rate}")],
                "1",
                "{} {rate}",
                model.name
            );
        }
        assert!(
            !ini["FileInfo"].contains_key("LastEDS"),
            "no custom keys (EDS-01)"
        );
        assert!(ini.contains_key("DummyUsage"));
    }
}

#[test]
fn node_id_dependent_defaults_use_nodeid() {
    let th = eds_of(models::by_name("th").unwrap());
    let ini = parse_ini(&th);
    assert_eq!(ini["1800sub1"]["DefaultValue"], "$NODEID+0x00000180");
    assert_eq!(ini["1801sub1"]["DefaultValue"], "$NODEID+0x80000280");
    assert_eq!(ini["1014"]["DefaultValue"], "$NODEID+0x00000080");
    assert_eq!(ini["100B"]["DefaultValue"], "$NODEID+0x00000000");
    let e = parse_ini(&eds_of(models::by_name("e-series").unwrap()));
    assert_eq!(e["1800sub1"]["DefaultValue"], "$NODEID+0x40000180");
    assert_eq!(e["1803sub1"]["DefaultValue"], "$NODEID+0xC0000480");
    assert_eq!(num(&e["DeviceInfo"]["ProductNumber"]), 0x0E);
    assert_eq!(num(&e["DeviceInfo"]["RevisionNumber"]), 0x0309_0001);
    let t = parse_ini(&eds_of(models::by_name("tmi").unwrap()));
    // One-channel TMI: TPDO2 disabled (D21), still node-id relative.
    assert_eq!(t["1801sub1"]["DefaultValue"], "$NODEID+0xC0000280");
    assert_eq!(t["2000"]["DefaultValue"], "$NODEID+0x00");
    assert_eq!(num(&t["2001"]["DefaultValue"]), 250);
    assert_eq!(t["6005sub2"]["LowLimit"], "0x00000014");
    assert_eq!(t["DeviceInfo"]["BaudRate_10"], "1");
    assert_eq!(t["DeviceInfo"]["NrOfTXPDO"], "2");
}

/// With `CANPOS_EDS_DIR` set, writes each model's EDS there (for checks with other tools, e.g.
/// python-canopen's `import_od`).
#[test]
fn dump_eds_files_when_asked() {
    let Ok(dir) = std::env::var("CANPOS_EDS_DIR") else {
        return;
    };
    for model in models::all() {
        let path = std::path::Path::new(&dir).join(format!("canpos-{}.eds", model.name));
        std::fs::write(path, eds_of(model)).unwrap();
    }
}

/// Unsigned values are hex as wide as their type (`0x00000000` for an unused mapping entry),
/// signed ones decimal: every `DefaultValue`, `LowLimit` and `HighLimit` of every model.
#[test]
fn hex_values_are_as_wide_as_their_type() {
    for model in models::all() {
        let ini = parse_ini(&eds_of(model));
        for (name, sec) in &ini {
            let Some(ty) = sec.get("DataType") else {
                continue;
            };
            let bytes = match num(ty) {
                0x1 | 0x5 => 1,
                0x6 => 2,
                0x7 => 4,
                _ => continue,
            };
            for key in ["DefaultValue", "LowLimit", "HighLimit"] {
                let Some(v) = sec.get(key) else { continue };
                let v = v.strip_prefix("$NODEID+").unwrap_or(v);
                let hex = v
                    .strip_prefix("0x")
                    .unwrap_or_else(|| panic!("{name} {key}={v}"));
                assert_eq!(hex.len(), 2 * bytes, "{} [{name}] {key}={v}", model.name);
            }
        }
        // Unused mapping entries, as eds-utils wants them.
        assert!(
            ini.iter().any(|(n, sec)| n.starts_with("1A")
                && sec.get("DefaultValue").map(String::as_str) == Some("0x00000000")),
            "{}",
            model.name
        );
    }
}

/// CiA 306 §4.6.3: an object with sub-indices is an ARRAY (ObjectType 0x8) when every
/// sub-index from 1 up has one type, a RECORD (0x9) otherwise; the identity object and the
/// PDO parameter objects are RECORDs by CiA 301's definition whatever their types. The object's
/// `ParameterName` is the object's own name (sub 0's name before its ':').
#[test]
fn arrays_records_and_object_names() {
    for model in models::all() {
        let ini = parse_ini(&eds_of(model));
        for (idx, subs) in &objects(model) {
            if subs.len() == 1 && subs[0].sub == 0 {
                assert!(!ini[&format!("{idx:04X}")].contains_key("SubNumber"));
                continue;
            }
            let last = subs[subs.len() - 1].ty;
            let mixed = subs.iter().any(|e| e.sub > 0 && e.ty != last);
            let cia301_record = matches!(idx, 0x1018 | 0x1800..=0x1BFF);
            let want = if mixed || cia301_record { "0x9" } else { "0x8" };
            let head = &ini[&format!("{idx:04X}")];
            assert_eq!(head["ObjectType"], want, "{} {idx:04X}", model.name);
            let name = subs[0].name.split(':').next().unwrap().trim();
            assert!(!name.is_empty());
            assert_eq!(head["ParameterName"], name, "{} {idx:04X}", model.name);
        }
    }
    let th = models::by_name("th").unwrap();
    let ini = parse_ini(&eds_of(th));
    assert_eq!(ini["1018"]["ParameterName"], "Identity object");
    assert_eq!(ini["1018"]["ObjectType"], "0x9");
    // "save" / "restore": sub 0 is UNSIGNED8, every other sub UNSIGNED32: an ARRAY.
    assert_eq!(ini["1010"]["ObjectType"], "0x8");
    assert_eq!(ini["1011"]["ObjectType"], "0x8");
    // A manufacturer object with mixed sub types (a device described by its own EDS) is a
    // RECORD; the same object with one type is an ARRAY.
    let with = |tys: [DataType; 2]| {
        let mut entries = th.entries.to_vec();
        let sub = |s: u8, ty| {
            Entry::build(
                0x2F00,
                s,
                "Test object: sub",
                ty,
                Access::Rw,
                false,
                DefaultValue::Const(0),
                &Range::Any,
                Group::App,
            )
        };
        entries.push(sub(0, DataType::Unsigned8));
        entries.push(sub(1, tys[0]));
        entries.push(sub(2, tys[1]));
        entries.sort_by_key(Entry::key);
        let entries: &'static [Entry] = Box::leak(entries.into_boxed_slice());
        #[cfg(feature = "inline-hot-paths")]
        let keys: &'static [u32] = Box::leak(entries.iter().map(Entry::key).collect());
        let m: &'static Model = Box::leak(Box::new(Model {
            table: Table {
                entries,
                #[cfg(feature = "inline-hot-paths")]
                keys,
                ..th.table
            },
            ..*th
        }));
        parse_ini(&eds_of(m))["2F00"]["ObjectType"].clone()
    };
    assert_eq!(with([DataType::Unsigned16, DataType::Unsigned32]), "0x9");
    assert_eq!(with([DataType::Unsigned32, DataType::Unsigned32]), "0x8");
}

struct Unit(&'static Model);

impl ParamSource for Unit {
    fn param(&self, p: Param) -> u32 {
        (self.0.param)(&self.0.default_config, p)
    }
}

/// `[DeviceInfo]` carries the identity object's vendor, product and revision (CiA 306 §4.4).
#[test]
fn device_info_is_the_identity_object() {
    for model in models::all() {
        let ini = parse_ini(&eds_of(model));
        let di = &ini["DeviceInfo"];
        let unit = Unit(model);
        let id = |sub: u8| {
            let e = model
                .entries
                .iter()
                .find(|e| e.index == 0x1018 && e.sub == sub);
            resolve_default(e.unwrap(), &unit, model.default_config.node_id) as i64
        };
        assert_eq!(num(&di["VendorNumber"]), id(1), "{}", model.name);
        assert_eq!(num(&di["ProductNumber"]), id(2), "{}", model.name);
        assert_eq!(num(&di["RevisionNumber"]), id(3), "{}", model.name);
    }
}

/// A unit-dependent default is the unit's value (its stroke, resolution, serial number), written
/// as `$NODEID+…` only when it moves with the node-id one for one.
#[test]
fn unit_dependent_defaults_are_the_units_values() {
    for model in models::all() {
        let cfg = model.default_config;
        let ini = parse_ini(&eds_of(model));
        for (idx, subs) in &objects(model) {
            for e in subs {
                let DefaultValue::Param(p) = e.default else {
                    continue;
                };
                let single = subs.len() == 1 && e.sub == 0;
                let key = if single {
                    format!("{idx:04X}")
                } else {
                    format!("{idx:04X}sub{:X}", e.sub)
                };
                let v = &ini[&key]["DefaultValue"];
                let at =
                    |id: u8| (model.param)(&canpos_models::DeviceConfig { node_id: id, ..cfg }, p);
                let relative = at(1).wrapping_sub(at(0)) == 1 && p != Param::BitRateKbps;
                let what = format!("{} [{key}] {v}", model.name);
                if relative {
                    let base = v
                        .strip_prefix("$NODEID+")
                        .unwrap_or_else(|| panic!("{what}"));
                    assert_eq!(num(base) as u32, at(0), "{what}");
                } else {
                    assert!(!v.starts_with("$NODEID"), "{what}");
                    assert_eq!(num(v), e.ty.to_i64((model.param)(&cfg, p)), "{what}");
                }
            }
        }
    }
    // Spot checks on TH: the measuring step and the serial number are plain numbers.
    let th = models::by_name("th").unwrap();
    let ini = parse_ini(&eds_of(th));
    let step = (th.param)(&th.default_config, canpos_encoder::param::POSITION_STEP_NM);
    assert!(step > 1);
    assert_eq!(num(&ini["6005sub1"]["DefaultValue"]), step as i64);
    assert_eq!(ini["100B"]["DefaultValue"], "$NODEID+0x00000000");
}

/// A DCF's `ParameterValue` (CiA 306 §4.6.4): numbers as in the EDS; a VISIBLE_STRING as its
/// text when it is printable ASCII, otherwise (and any other byte string) as hex digits.
#[test]
fn dcf_parameter_values() {
    let th = models::by_name("th").unwrap();
    let c = Commissioning {
        node_id: 5,
        node_name: "cyl",
        bitrate_kbps: 500,
        net_number: 1,
        network_name: "net",
        lss_serial: 0x1234,
        last_eds: "th.eds",
    };
    let dcf = |name: &'static [u8]| {
        let mut s = String::new();
        let values = move |i: u16, sub: u8| match (i, sub) {
            (0x1008, 0) => Some(DcfValue::Bytes(name)),
            (0x1017, 0) => Some(DcfValue::Number(250)),
            _ => None,
        };
        write_dcf(
            &mut s,
            th,
            &th.default_config,
            &EdsInfo::default(),
            &c,
            &values,
        )
        .unwrap();
        parse_ini(&s)
    };
    let ini = dcf(b"Cyl 7");
    assert_eq!(ini["1008"]["ParameterValue"], "Cyl 7");
    assert_eq!(ini["1017"]["ParameterValue"], "0x00FA");
    assert!(!ini["1000"].contains_key("ParameterValue"));
    assert_eq!(ini["DeviceComissioning"]["NodeID"], "0x05");
    assert_eq!(ini["FileInfo"]["LastEDS"], "th.eds");
    let ini = dcf(&[0x01, 0x7F, b'A']);
    assert_eq!(ini["1008"]["ParameterValue"], "017F41");
    assert_eq!(
        th.entries.iter().find(|e| e.index == 0x1008).unwrap().ty,
        DataType::VisibleString
    );
}
