//! docs/OD.md §1.2, row by row, against every unit of the order codes it lists: the dictionary,
//! the running unit through its SDO server (defaults, limits probed, mappability, storage over a
//! power cycle) and the unit's EDS. §1's transcription of the manuals is checked against §1.2,
//! and §3.11's EMCY table (TH / E-Series Table 5 with Table 6's register) against the frames
//! the units send. Nothing here lists an object: the rows come from the document.

use std::collections::{BTreeMap, BTreeSet};

use crate::common::{emcys, hex, sample, Rig};
use canpos_encoder::Fault;
use canpos_models::{self as models, DeviceConfig, Model};
use canpos_stack::eds::{write_eds, EdsInfo};
use canpos_stack::od::{DataType, Group, Hook};
use canpos_stack::Frame;

const OD_MD: &str = include_str!("../../../../docs/OD.md");

/// One row of §1.2.
#[derive(Clone, Debug)]
struct Row {
    units: Vec<String>,
    index: u16,
    sub: u8,
    ty: String,
    access: String,
    default: String,
    limits: String,
    pdo: bool,
    storage: String,
    /// Line in docs/OD.md, for the failure messages.
    line: usize,
}

/// The cells of a Markdown table row.
fn cells(line: &str) -> Vec<String> {
    line.trim()
        .trim_matches('|')
        .split('|')
        .map(|c| c.trim().to_string())
        .collect()
}

/// The table under the heading that starts with `heading`: (line number, cells) per body row.
fn table(heading: &str) -> Vec<(usize, Vec<String>)> {
    let lines: Vec<&str> = OD_MD.lines().collect();
    let start = lines
        .iter()
        .position(|l| l.starts_with(heading))
        .unwrap_or_else(|| panic!("docs/OD.md has no `{heading}`"));
    let first = (start..lines.len())
        .find(|&i| lines[i].starts_with('|'))
        .expect("a table");
    (first + 2..lines.len())
        .take_while(|&i| lines[i].starts_with('|'))
        .map(|i| (i + 1, cells(lines[i])))
        .collect()
}

fn rows() -> Vec<Row> {
    let t = table("### 1.2 ");
    assert!(t.len() > 200, "§1.2 has {} rows", t.len());
    t.into_iter()
        .map(|(line, c)| {
            assert_eq!(c.len(), 10, "docs/OD.md:{line}: 10 cells");
            Row {
                units: c[0].split(',').map(|u| u.trim().to_string()).collect(),
                index: u16::from_str_radix(&c[1], 16).unwrap(),
                sub: c[2].parse().unwrap(),
                ty: c[3].clone(),
                access: c[4].clone(),
                default: c[5].clone(),
                limits: c[6].clone(),
                pdo: match c[7].as_str() {
                    "yes" => true,
                    "no" => false,
                    x => panic!("docs/OD.md:{line}: PDO `{x}`"),
                },
                storage: c[8].clone(),
                line,
            }
        })
        .collect()
}

/// A unit of one order code.
struct Unit {
    code: &'static str,
    model: &'static Model,
    cfg: DeviceConfig,
    /// §1.2's unit name.
    name: &'static str,
}

/// The order codes §1.2 names, each configured as `canpos --order-code` configures it (stroke,
/// resolution, magnets / channels, bit rate; the model derives the rest).
fn units() -> Vec<Unit> {
    let th = models::by_name("th").unwrap();
    let e = models::by_name("e-series").unwrap();
    let tmi = models::by_name("tmi").unwrap();
    let unit = |code, model: &'static Model, stroke, step, ch, kbps, name| {
        let cfg = model.configure(
            model
                .default_config
                .with_stroke_mm(stroke)
                .with_step_nm(step)
                .with_channels(ch)
                .with_bitrate(kbps),
        );
        Unit {
            code,
            model,
            cfg,
            name,
        }
    };
    let listed: Vec<Unit> = vec![
        unit(
            "TH S 1000M C01 1 E N N C304 1 1 1",
            th,
            1000,
            5000,
            1,
            1000,
            "TH",
        ),
        unit(
            "TH S 3000M C01 1 E N N C304 2 2 1 Z04",
            th,
            3000,
            2000,
            4,
            500,
            "TH",
        ),
        unit(
            "TH S 7620M C01 1 E N N C304 4 1 1 Z02",
            th,
            7620,
            5000,
            2,
            125,
            "TH",
        ),
        unit("EP0 0600M D34 1 C304 2 4 1", e, 600, 10_000, 1, 500, "E"),
        unit(
            "EH M 2540M D34 1 C404 4 5 1 Z02",
            e,
            2540,
            20_000,
            2,
            125,
            "E",
        ),
        unit("TMI 0500 101 611 105", tmi, 500, 1000, 1, 250, "TMI1"),
        unit("TMI 0750 101 615 252", tmi, 750, 5000, 1, 250, "TMI1"),
        unit("TMI 1000 101 621 106", tmi, 1000, 1000, 2, 250, "TMI2"),
        unit("TMI 4500 101 625 252", tmi, 4500, 5000, 2, 250, "TMI2"),
    ];
    // The list is §1.2's: the document names the same order codes.
    for u in &listed {
        assert!(
            OD_MD.contains(&format!("`{}`", u.code)),
            "docs/OD.md §1.2 does not list `{}`",
            u.code
        );
    }
    listed
}

/// The rows of `unit`.
fn rows_of<'a>(rows: &'a [Row], unit: &Unit) -> Vec<&'a Row> {
    rows.iter()
        .filter(|r| r.units.iter().any(|u| u == unit.name))
        .collect()
}

fn type_of(name: &str) -> DataType {
    match name {
        "BOOLEAN" => DataType::Boolean,
        "INTEGER8" => DataType::Integer8,
        "INTEGER16" => DataType::Integer16,
        "INTEGER32" => DataType::Integer32,
        "UNSIGNED8" => DataType::Unsigned8,
        "UNSIGNED16" => DataType::Unsigned16,
        "UNSIGNED32" => DataType::Unsigned32,
        "VISIBLE_STRING" => DataType::VisibleString,
        x => panic!("type `{x}`"),
    }
}

/// A number or an order-code symbol of §1.2, for `unit`, as an i64 of the row's type.
fn value(unit: &Unit, s: &str) -> i64 {
    let c = &unit.cfg;
    let tmi = unit.name.starts_with("TMI");
    match s {
        "step" => i64::from(c.position_step_nm),
        "maxpos" => i64::from(c.stroke_mm) * 1_000_000 / i64::from(c.position_step_nm),
        "vstep" if tmi => 250,
        "vstep" => {
            // D18 over the manuals' cycle times (TH §8 by stroke; E-Series 1 ms).
            let cycle_us: i64 = match (unit.name, c.stroke_mm) {
                ("TH", 0..=2400) | ("E", _) => 1000,
                ("TH", 0..=4800) => 2000,
                _ => 4000,
            };
            (i64::from(c.position_step_nm) * 100 * 10 / (cycle_us * 10) + 5) / 10
        }
        "product" => {
            let mut p = i64::from(c.stroke_mm);
            if c.channels > 1 {
                p |= 1 << 31;
            }
            if c.position_step_nm == 5000 {
                p |= 1 << 30;
            }
            p
        }
        "devtype" if c.channels > 1 => 0x000A_0196,
        "devtype" => 0x0008_0196,
        "serial" => i64::from(c.serial),
        "kbps" => i64::from(c.bitrate_kbps),
        n => number(n),
    }
}

fn number(s: &str) -> i64 {
    let s = s.trim();
    if let Some(h) = s.strip_prefix("0x") {
        i64::from_str_radix(h, 16).unwrap_or_else(|_| panic!("number `{s}`"))
    } else {
        s.parse().unwrap_or_else(|_| panic!("number `{s}`"))
    }
}

/// A row's limits for `unit`.
#[derive(Debug)]
enum Limits {
    None,
    /// lo, hi, step, abort codes below / above.
    Range(i64, i64, i64, u32, u32),
    /// Members, abort code outside.
    List(Vec<i64>, u32),
}

fn limits(unit: &Unit, r: &Row) -> Limits {
    let cell = r.limits.as_str();
    if cell == "—" {
        return Limits::None;
    }
    let (body, abort) = match cell.split_once('!') {
        Some((b, a)) => (b.trim(), Some(u32::from_str_radix(a.trim(), 16).unwrap())),
        None => (cell, None),
    };
    if let Some(list) = body.strip_prefix('{') {
        let v = list
            .trim_end_matches('}')
            .split(',')
            .map(|x| value(unit, x))
            .collect();
        return Limits::List(v, abort.unwrap_or(0x0609_0030));
    }
    let (range, step) = match body.split_once('/') {
        Some((a, s)) => (a.trim(), number(s)),
        None => (body, 1),
    };
    let (lo, hi) = range.split_once("..").expect("lo..hi");
    Limits::Range(
        value(unit, lo),
        value(unit, hi),
        step,
        abort.unwrap_or(0x0609_0032),
        abort.unwrap_or(0x0609_0031),
    )
}

/// The raw bits of `v` as the row's type holds them.
fn raw(ty: DataType, v: i64) -> u32 {
    v as u32 & size_mask(ty)
}

fn size_mask(ty: DataType) -> u32 {
    match ty.size() {
        Some(1) => 0xFF,
        Some(2) => 0xFFFF,
        _ => u32::MAX,
    }
}

/// An SDO upload from node 0x7F: the value's bytes, or the abort code.
fn upload(r: &mut Rig, index: u16, sub: u8) -> Result<Vec<u8>, u32> {
    let [i0, i1] = index.to_le_bytes();
    let a = r.sdo(&format!("40 {i0:02X} {i1:02X} {sub:02X} 00 00 00 00"));
    match a[0] {
        0x80 => Err(u32::from_le_bytes([a[4], a[5], a[6], a[7]])),
        c if c & 0xF3 == 0x43 => Ok(a[4..8 - usize::from((c >> 2) & 3)].to_vec()),
        0x41 => {
            let mut out = Vec::new();
            let mut toggle = 0u8;
            loop {
                let s = r.sdo(&format!("{:02X} 00 00 00 00 00 00 00", 0x60 | toggle));
                assert_eq!(s[0] & 0xE0, 0x00, "segment {s:02X?}");
                let n = 7 - usize::from((s[0] >> 1) & 7);
                out.extend_from_slice(&s[1..1 + n]);
                if s[0] & 1 == 1 {
                    return Ok(out);
                }
                toggle ^= 0x10;
            }
        }
        _ => panic!("upload {index:04X}:{sub}: {a:02X?}"),
    }
}

fn write(r: &mut Rig, row: &Row, v: u32) -> Result<(), u32> {
    let ty = type_of(&row.ty);
    r.download(row.index, row.sub, v, ty.size().unwrap_or(4))
}

/// The default of a row for `unit`, as the bytes an upload gives (`None`: live).
fn default_bytes(unit: &Unit, row: &Row) -> Option<Vec<u8>> {
    let ty = type_of(&row.ty);
    let d = row.default.as_str();
    if d == "live" {
        return None;
    }
    if let Some(s) = d.strip_prefix('"') {
        return Some(s.trim_end_matches('"').as_bytes().to_vec());
    }
    let v = match d.strip_prefix("$NODEID+") {
        Some(base) => number(base) + i64::from(unit.cfg.node_id),
        None => value(unit, d),
    };
    let n = ty.size().unwrap();
    Some(raw(ty, v).to_le_bytes()[..n].to_vec())
}

fn group(s: &str, at: usize) -> Group {
    match s {
        "—" => Group::Volatile,
        "comm" => Group::Comm,
        "app" => Group::App,
        "auto" => Group::Auto,
        x => panic!("docs/OD.md:{at}: storage `{x}`"),
    }
}

/// Each row of a unit is an entry of the unit's dictionary with the row's type, access,
/// mappability and storage group, and the dictionary has nothing else.
#[test]
fn every_units_dictionary_is_its_rows() {
    let rows = rows();
    for u in units() {
        let r = Rig::with_config(u.model, u.cfg);
        let model = r.node.device().model();
        let mine = rows_of(&rows, &u);
        let keys: BTreeSet<(u16, u8)> = mine.iter().map(|r| (r.index, r.sub)).collect();
        assert_eq!(keys.len(), mine.len(), "{}: a key twice in §1.2", u.code);
        for e in model.entries {
            assert!(
                keys.contains(&(e.index, e.sub)),
                "{}: {:04X}:{} is in the dictionary but has no row in docs/OD.md §1.2",
                u.code,
                e.index,
                e.sub
            );
        }
        for row in mine {
            let at = format!("{} docs/OD.md:{}", u.code, row.line);
            let e = model
                .entries
                .iter()
                .find(|e| (e.index, e.sub) == (row.index, row.sub))
                .unwrap_or_else(|| {
                    panic!("{at}: {:04X}:{} not in the dictionary", row.index, row.sub)
                });
            assert_eq!(e.ty, type_of(&row.ty), "{at}: type");
            assert_eq!(e.access.eds(), row.access, "{at}: access");
            assert_eq!(e.pdo, row.pdo, "{at}: PDO");
            assert_eq!(e.group, group(&row.storage, row.line), "{at}: storage");
        }
    }
}

/// Through the SDO server of a unit just powered on: every readable row reads its default,
/// every limit is accepted and one step past it refused with the row's abort code.
#[test]
fn every_unit_reads_its_defaults_and_keeps_its_limits() {
    let rows = rows();
    for u in units() {
        let mut r = Rig::with_config(u.model, u.cfg);
        r.take();
        let mine = rows_of(&rows, &u);
        for row in &mine {
            let at = format!("{} docs/OD.md:{}", u.code, row.line);
            let got = upload(&mut r, row.index, row.sub);
            match default_bytes(&u, row) {
                Some(want) => assert_eq!(got, Ok(want), "{at}: default"),
                // A live value reads, or has no data yet (an empty error history).
                None => assert!(
                    matches!(got, Ok(_) | Err(0x0800_0024)),
                    "{at}: live value not readable: {got:?}"
                ),
            }
        }
        for row in &mine {
            let at = format!("{} docs/OD.md:{}", u.code, row.line);
            let ty = type_of(&row.ty);
            let (tmin, tmax) = ty.natural_range();
            match limits(&u, row) {
                Limits::None => {}
                Limits::Range(lo, hi, step, below, above) => {
                    assert_eq!(write(&mut r, row, raw(ty, lo)), Ok(()), "{at}: low limit");
                    assert_eq!(write(&mut r, row, raw(ty, hi)), Ok(()), "{at}: high limit");
                    if lo - step >= tmin {
                        let v = raw(ty, lo - step);
                        assert_eq!(write(&mut r, row, v), Err(below), "{at}: below");
                    }
                    if hi + step <= tmax {
                        let v = raw(ty, hi + step);
                        assert_eq!(write(&mut r, row, v), Err(above), "{at}: above");
                    }
                }
                Limits::List(members, outside) => {
                    for &m in &members {
                        assert_eq!(write(&mut r, row, raw(ty, m)), Ok(()), "{at}: {m}");
                    }
                    let lo = *members.iter().min().unwrap();
                    let hi = *members.iter().max().unwrap();
                    let gap = (lo..=hi).find(|v| !members.contains(v));
                    for v in [Some(lo - 1), Some(hi + 1), gap].into_iter().flatten() {
                        if (tmin..=tmax).contains(&v) {
                            let got = write(&mut r, row, raw(ty, v));
                            assert_eq!(got, Err(outside), "{at}: {v} not in the list");
                        }
                    }
                }
            }
        }
    }
}

/// Every row's mappability, as TPDO1's first mapping entry of a unit in pre-operational: a
/// mappable object is accepted, any other refused with 0x06040041 (TMI: 002 §1.2.5).
#[test]
fn every_unit_maps_exactly_its_mappable_rows() {
    let rows = rows();
    for u in units() {
        let mut r = Rig::with_config(u.model, u.cfg);
        r.take();
        let cob = r.read(0x1800, 1);
        r.write(0x1800, 1, cob | 0x8000_0000, 4);
        r.write(0x1A00, 0, 0, 1);
        for row in rows_of(&rows, &u) {
            let at = format!("{} docs/OD.md:{}", u.code, row.line);
            let bits = type_of(&row.ty).bits().max(8);
            let entry = u32::from(row.index) << 16 | u32::from(row.sub) << 8 | u32::from(bits);
            let got = r.download(0x1A00, 1, entry, 4);
            if row.pdo {
                assert_eq!(got, Ok(()), "{at}: mappable");
            } else {
                assert_eq!(got, Err(0x0604_0041), "{at}: not mappable");
            }
        }
    }
}

/// Values written to every writable row, "save" (0x1010/1), a power cycle: rows with a storage
/// group keep the value, the others read their default again.
#[test]
fn every_unit_stores_exactly_its_stored_rows() {
    let rows = rows();
    for u in units() {
        let mut r = Rig::with_config(u.model, u.cfg);
        r.take();
        let model = r.node.device().model();
        let hook = |row: &Row| {
            model
                .entries
                .iter()
                .find(|e| (e.index, e.sub) == (row.index, row.sub))
                .map(|e| e.hook)
        };
        // The PDOs invalid and unmapped, so that their parameters may change.
        for n in 0..u16::from(model.features.tpdos) {
            let cob = r.read(0x1800 + n, 1);
            r.write(0x1800 + n, 1, cob | 0x8000_0000, 4);
            r.write(0x1A00 + n, 0, 0, 1);
        }
        let mut probe: Vec<&Row> = rows_of(&rows, &u)
            .into_iter()
            .filter(|row| row.access == "rw")
            // Signatures, the error history, and the node-id / bit rate that a reset makes
            // active (their storage: lss_* and tmi_storage).
            .filter(|row| {
                !matches!(
                    hook(row),
                    Some(
                        Hook::StoreParameters
                            | Hook::RestoreDefaults
                            | Hook::ErrorHistory
                            | Hook::PendingNodeId
                            | Hook::PendingBitRate
                    )
                )
            })
            .collect();
        // A mapping's count after its entries.
        probe.sort_by_key(|row| {
            let count = (0x1A00..0x1C00).contains(&row.index) && row.sub == 0;
            (row.index, if count { 0xFF } else { row.sub })
        });
        let mut want: BTreeMap<(u16, u8), (Vec<u8>, usize)> = BTreeMap::new();
        let mut left = probe;
        for _pass in 0..2 {
            let mut again = Vec::new();
            for row in left {
                let ty = type_of(&row.ty);
                let d = default_bytes(&u, row).expect("a writable row has a default");
                let d = i64::from(canpos_stack::od::le_u32(&d));
                let mut cands: Vec<i64> = match limits(&u, row) {
                    Limits::Range(lo, hi, ..) => vec![hi, lo],
                    Limits::List(m, _) => m,
                    Limits::None => vec![],
                };
                if (0x1A00..0x1C00).contains(&row.index) {
                    cands.extend(if row.sub == 0 {
                        [1, 2]
                    } else {
                        [0x6020_0120, 0x6030_0110]
                    });
                }
                cands.extend([d ^ 1, d | 0x8000_0000, d + 1]);
                let size = ty.size().unwrap();
                let mask = i64::from(size_mask(ty));
                let ok = cands.into_iter().find(|&v| {
                    v & mask != d & mask && v & !mask == 0 && write(&mut r, row, raw(ty, v)).is_ok()
                });
                match ok {
                    Some(v) => {
                        let b = raw(ty, v).to_le_bytes()[..size].to_vec();
                        want.insert((row.index, row.sub), (b, row.line));
                    }
                    None => again.push(row),
                }
            }
            left = again;
        }
        let left: Vec<_> = left
            .iter()
            .map(|r| format!("{:04X}:{}", r.index, r.sub))
            .collect();
        assert!(left.is_empty(), "{}: no value accepted by {left:?}", u.code);
        // "save", answered after the store time.
        let f = r.store_cmd(0x67F, &hex("23 10 10 01 73 61 76 65"), 200);
        let ans: Vec<_> = f
            .iter()
            .filter(|(_, f)| f.std_id() == Some(0x5FF))
            .collect();
        assert_eq!(ans.len(), 1, "{}: save", u.code);
        assert_eq!(ans[0].1.data()[0], 0x60, "{}: save confirmed", u.code);
        r.power_cycle();
        r.take();
        for row in rows_of(&rows, &u) {
            let Some((written, line)) = want.get(&(row.index, row.sub)) else {
                continue;
            };
            let at = format!("{} docs/OD.md:{line}", u.code);
            let got = upload(&mut r, row.index, row.sub).unwrap();
            if row.storage == "—" {
                let d = default_bytes(&u, row).unwrap();
                assert_eq!(got, d, "{at}: not stored, back to its default");
            } else {
                assert_eq!(&got, written, "{at}: stored");
            }
        }
    }
}

/// The EDS of a unit (what `canpos eds --order-code` writes) parsed: [section] → key → value.
fn eds_of(u: &Unit) -> BTreeMap<String, BTreeMap<String, String>> {
    let mut s = String::new();
    write_eds(&mut s, u.model, &u.cfg, &EdsInfo::default()).unwrap();
    let mut out: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
    let mut cur = String::new();
    for l in s.lines() {
        let l = l.trim();
        if let Some(sec) = l.strip_prefix('[') {
            cur = sec.trim_end_matches(']').to_ascii_uppercase();
            out.entry(cur.clone()).or_default();
        } else if let Some((k, v)) = l.split_once('=') {
            out.entry(cur.clone())
                .or_default()
                .insert(k.trim().to_string(), v.trim().to_string());
        }
    }
    out
}

/// Every row in the unit's EDS: type, access, default, limits, mappability; and every object
/// of the EDS has its rows.
#[test]
fn every_units_eds_is_its_rows() {
    let rows = rows();
    for u in units() {
        let eds = eds_of(&u);
        let mine = rows_of(&rows, &u);
        let subs = |index: u16| mine.iter().filter(|r| r.index == index).count();
        let mut sections = BTreeSet::new();
        for row in &mine {
            let at = format!("{} docs/OD.md:{}", u.code, row.line);
            let sec = if subs(row.index) == 1 && row.sub == 0 {
                format!("{:04X}", row.index)
            } else {
                format!("{:04X}SUB{:X}", row.index, row.sub)
            };
            let s = eds
                .get(&sec)
                .unwrap_or_else(|| panic!("{at}: no [{sec}] in the EDS"));
            sections.insert(sec.clone());
            let ty = type_of(&row.ty);
            assert_eq!(
                s.get("DataType").map(|v| number(v)),
                Some(i64::from(ty.code())),
                "{at}: DataType"
            );
            assert_eq!(
                s.get("AccessType").map(String::as_str),
                Some(row.access.as_str()),
                "{at}: AccessType"
            );
            assert_eq!(
                s.get("PDOMapping").map(String::as_str),
                Some(if row.pdo { "1" } else { "0" }),
                "{at}: PDOMapping"
            );
            let got = s.get("DefaultValue").map(String::as_str);
            match row.default.as_str() {
                "live" => assert_eq!(got, None, "{at}: a live value has no DefaultValue"),
                d if d.starts_with("$NODEID+") => {
                    let got = got.unwrap_or_else(|| panic!("{at}: no DefaultValue"));
                    let (_, base) = got.split_once('+').expect("$NODEID+…");
                    assert!(got.starts_with("$NODEID+"), "{at}: {got}");
                    assert_eq!(number(base), number(&d[8..]), "{at}: DefaultValue");
                }
                d if d.starts_with('"') => {
                    assert_eq!(got, Some(d.trim_matches('"')), "{at}: DefaultValue")
                }
                d => {
                    let got = got.unwrap_or_else(|| panic!("{at}: no DefaultValue"));
                    assert_eq!(
                        raw(ty, number(got)),
                        raw(ty, value(&u, d)),
                        "{at}: DefaultValue {got}"
                    );
                }
            }
            let lim = (
                s.get("LowLimit").map(|v| number(v)),
                s.get("HighLimit").map(|v| number(v)),
            );
            let want = match limits(&u, row) {
                Limits::None => (None, None),
                Limits::Range(lo, hi, ..) => (Some(lo), Some(hi)),
                Limits::List(m, _) => (m.iter().min().copied(), m.iter().max().copied()),
            };
            let norm = |v: Option<i64>| v.map(|v| raw(ty, v));
            assert_eq!(
                (norm(lim.0), norm(lim.1)),
                (norm(want.0), norm(want.1)),
                "{at}: LowLimit / HighLimit"
            );
        }
        for sec in eds.keys() {
            let object = sec.len() == 4 && u16::from_str_radix(sec, 16).is_ok();
            let sub = sec.len() > 7 && sec[4..].starts_with("SUB");
            // A VAR object's section, or any sub-index's.
            if object && subs(u16::from_str_radix(sec, 16).unwrap()) <= 1 || sub {
                assert!(
                    sections.contains(sec),
                    "{}: EDS [{sec}] has no row in docs/OD.md §1.2",
                    u.code
                );
            }
        }
    }
}

/// §1 (the manuals' transcription) against §1.2: where §1 gives a product a plain type,
/// access or PDO cell, that product's rows in §1.2 agree.
#[test]
fn the_manuals_table_agrees_with_the_rows() {
    let rows = rows();
    let t = table("## 1. Object dictionary");
    let mut checked = 0;
    for (line, c) in t {
        let Ok(index) = u16::from_str_radix(&c[0], 16) else {
            continue;
        };
        let Ok(sub) = c[1].parse::<u8>() else {
            continue;
        };
        let ty = match c[3].as_str() {
            "U8" => Some("UNSIGNED8"),
            "U16" => Some("UNSIGNED16"),
            "U32" => Some("UNSIGNED32"),
            "Integer8" => Some("INTEGER8"),
            "Integer16" => Some("INTEGER16"),
            "Integer32" => Some("INTEGER32"),
            "BOOLEAN" => Some("BOOLEAN"),
            "String" => Some("VISIBLE_STRING"),
            _ => None,
        };
        let access = match c[4].as_str() {
            "ro" => Some(["ro", "const"].as_slice()),
            "rw" => Some(["rw"].as_slice()),
            _ => None,
        };
        let pdo = match c[8].as_str() {
            "**yes**" => Some(true),
            "no" => Some(false),
            _ => None,
        };
        // Product columns: TH, E-Series, TMI (the two-channel unit has every TMI object).
        for (cell, unit) in [(&c[5], "TH"), (&c[6], "E"), (&c[7], "TMI2")] {
            if cell.starts_with('—') || cell.starts_with("not listed") {
                continue;
            }
            let at = format!("docs/OD.md:{line} ({unit} {index:04X}:{sub})");
            let row = rows
                .iter()
                .find(|r| (r.index, r.sub) == (index, sub) && r.units.iter().any(|u| u == unit))
                .unwrap_or_else(|| panic!("{at}: §1 lists it, §1.2 has no row"));
            if let Some(ty) = ty {
                assert_eq!(row.ty, ty, "{at}: type");
            }
            if let Some(a) = access {
                assert!(
                    a.contains(&row.access.as_str()),
                    "{at}: access {}",
                    row.access
                );
            }
            if let Some(p) = pdo {
                assert_eq!(row.pdo, p, "{at}: PDO");
            }
            checked += 1;
        }
    }
    assert!(checked > 150, "{checked} cells checked");
}

/// A one-channel TMI has its channel-1 objects only: no sub 2 of any per-channel array, sub 0
/// reads 1, TPDO2 has nothing mapped, and its EDS has neither (002 §1.6, §1.12).
#[test]
fn a_one_channel_tmi_has_channel_1_only() {
    for u in units().into_iter().filter(|u| u.name == "TMI1") {
        let mut r = Rig::with_config(u.model, u.cfg);
        r.take();
        for index in [
            0x6010, 0x6020, 0x6030, 0x6300, 0x6302, 0x6400, 0x6401, 0x6402,
        ] {
            assert_eq!(upload(&mut r, index, 2), Err(0x0609_0011), "{index:04X}:2");
            assert_eq!(upload(&mut r, index, 0), Ok(vec![1]), "{index:04X}:0");
        }
        assert_eq!(upload(&mut r, 0x1A01, 0), Ok(vec![0]));
        let eds = eds_of(&u);
        assert!(!eds.contains_key("6020SUB2") && !eds.contains_key("6400SUB2"));
        assert_eq!(eds["6020SUB0"]["DefaultValue"], "0x01");
    }
}

/// The byte-exact EMCYs of §3.11 (TH Table 5 / E-Series Table 5 with Table 6's register), each
/// raised on a TH and an E-Series unit: the frame, 0x1001 while the condition stands, and the
/// error reset with 0x1001 after it.
#[test]
fn every_table_5_emcy_is_byte_exact_with_its_register() {
    let t = table("### 3.11 ");
    let codes: Vec<(u16, u8)> = t
        .iter()
        .map(|(_, c)| {
            (
                u16::from_str_radix(c[0].trim_start_matches("0x"), 16).unwrap(),
                u8::from_str_radix(c[2].trim_start_matches("0x"), 16).unwrap(),
            )
        })
        .collect();
    assert_eq!(codes.len(), 11, "Table 5 has eleven codes");
    for name in ["th", "e-series"] {
        for &(code, reg) in &codes {
            let at = format!("{name} EMCY {code:04X}");
            let (raised, standing, reset) = raise(name, code);
            let mut want = vec![0u8; 8];
            want[..2].copy_from_slice(&code.to_le_bytes());
            want[2] = reg;
            assert_eq!(raised, want, "{at}: frame");
            assert_eq!(standing, u32::from(reg), "{at}: 0x1001 while it stands");
            // The data-set error stands until the next reset (nothing repairs the medium).
            if !matches!(code, 0x0000 | 0x6300) {
                assert_eq!(reset, Some(vec![0; 8]), "{at}: the error reset");
            }
        }
    }
}

/// Raises `code` on a booted unit of model `name`: its EMCY, 0x1001 right after it, and the
/// EMCY that follows when the condition ends (`None`: none).
fn raise(name: &str, code: u16) -> (Vec<u8>, u32, Option<Vec<u8>>) {
    let model = models::by_name(name).unwrap();
    if code == 0 {
        // The power-on EMCY "without reasonable data" (D14).
        let mut r = Rig::new(model);
        let e = emcys(&r.take());
        return (e[0].clone(), r.read(0x1001, 0), None);
    }
    if code == 0x6300 {
        // Stored data found corrupt at power-on.
        let mut r = Rig::booted(model);
        r.store_cmd(0x67F, &hex("23 10 10 01 73 61 76 65"), 200);
        r.node.storage_mut().corrupt();
        // The error register of the EMCY sent during power-on, read at once.
        let e = emcys(&r.power_cycle());
        let reg = r.read(0x1001, 0);
        return (e.last().unwrap().clone(), reg, None);
    }
    let mut r = Rig::booted(model);
    let fault = match code {
        0x3100 => Fault::SupplyVoltage,
        0x5000 => Fault::Transducer,
        0x8100 => Fault::Communication,
        0x8110 => Fault::CanOverrun,
        0x8120 => Fault::CanErrorPassive,
        0x8140 => Fault::CanBusOff,
        0x8150 => Fault::CobIdCollision,
        0x8210 => Fault::PdoLength,
        0x8130 => {
            // Life guarding: 10 ms × 2, one guard request, then none.
            r.write(0x100C, 0, 10, 2);
            r.write(0x100D, 0, 2, 1);
            r.node
                .handle_frame(&Frame::remote(0x77F, false, 1).unwrap(), r.now);
            r.take();
            let f: Vec<Frame> = r.advance_ms(30).into_iter().map(|(_, f)| f).collect();
            let e = emcys(&f);
            let reg = r.read(0x1001, 0);
            // Guarding resumes: the error clears.
            r.node
                .handle_frame(&Frame::remote(0x77F, false, 1).unwrap(), r.now);
            let after = emcys(&r.take());
            return (e[0].clone(), reg, after.first().cloned());
        }
        c => panic!("EMCY {c:04X}: §3.11 names a code this test cannot raise"),
    };
    r.node.inject_fault(fault, true);
    let mut e = emcys(&r.take());
    let mut reg = r.read(0x1001, 0);
    if fault == Fault::CanBusOff {
        // Nothing leaves during bus-off; 0x1001 shows it; the recovery sends the EMCY.
        assert!(e.is_empty(), "{name}: EMCY during bus-off: {e:02X?}");
        reg = r.read(0x1001, 0);
        r.node.inject_fault(fault, false);
        e = emcys(&r.take());
        assert_eq!(e.len(), 2, "{name}: 0x8140, then 0x0000: {e:02X?}");
        return (e[0].clone(), reg, Some(e[1].clone()));
    }
    assert_eq!(e.len(), 1 + (fault == Fault::CobIdCollision) as usize);
    if fault == Fault::CobIdCollision {
        // Over with its frame: the error reset follows at once.
        reg = u32::from(e[0][2]);
        return (e[0].clone(), reg, Some(e[1].clone()));
    }
    r.node.inject_fault(fault, false);
    let mut after = emcys(&r.take());
    if after.is_empty() {
        // The transducer's error clears with the next good measurement.
        after = emcys(&r.cycle_sample(&sample(&[Some(100_000_000)])));
    }
    assert_eq!(r.read(0x1001, 0), 0, "{name} {code:04X}: 0x1001 after");
    (e.remove(0), reg, after.first().cloned())
}
