//! EDS export (CiA 306): every model's file parses as INI and lists every table object with
//! the table's type, access, default and mapping (CONFORMANCE §1 EDS-01, §13).

use std::collections::BTreeMap;

use canpos_core::eds::{write_eds, EdsInfo};
use canpos_core::models::{self, Model};
use canpos_core::od::{Default, Entry};

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
                    Default::Live => {
                        assert!(
                            !sec.contains_key("DefaultValue"),
                            "{what}: live, no default"
                        )
                    }
                    Default::NodeId(base) => {
                        assert_eq!(sec["DefaultValue"], format!("$NODEID+0x{base:X}"), "{what}")
                    }
                    Default::Str(s) => assert_eq!(sec["DefaultValue"], s, "{what}"),
                    Default::Const(v) => {
                        assert_eq!(num(&sec["DefaultValue"]), e.ty.to_i64(v), "{what}")
                    }
                    Default::Param(_) => assert!(sec.contains_key("DefaultValue"), "{what}"),
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
                    Default::Const(v) => v as i64,
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
    assert_eq!(ini["1800sub1"]["DefaultValue"], "$NODEID+0x180");
    assert_eq!(ini["1801sub1"]["DefaultValue"], "$NODEID+0x80000280");
    assert_eq!(ini["1014"]["DefaultValue"], "$NODEID+0x80");
    assert_eq!(ini["100B"]["DefaultValue"], "$NODEID+0x0");
    let e = parse_ini(&eds_of(models::by_name("e-series").unwrap()));
    assert_eq!(e["1800sub1"]["DefaultValue"], "$NODEID+0x40000180");
    assert_eq!(e["1803sub1"]["DefaultValue"], "$NODEID+0xC0000480");
    assert_eq!(num(&e["DeviceInfo"]["ProductNumber"]), 0x0E);
    assert_eq!(num(&e["DeviceInfo"]["RevisionNumber"]), 0x0309_0001);
    let t = parse_ini(&eds_of(models::by_name("tmi").unwrap()));
    // One-channel TMI: TPDO2 disabled (D21), still node-id relative.
    assert_eq!(t["1801sub1"]["DefaultValue"], "$NODEID+0xC0000280");
    assert_eq!(t["2000"]["DefaultValue"], "$NODEID+0x0");
    assert_eq!(num(&t["2001"]["DefaultValue"]), 250);
    assert_eq!(t["6005sub2"]["LowLimit"], "0x14");
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
