//! The catalogue of `docs/CONFORMANCE_CATALOGUE.md` as code: one function per case ID. Each runs
//! against a [`Harness`] and either passes (assertions), or returns [`Outcome::Na`] with the
//! catalogue's reason for this model.
//!
//! Where the catalogue's stimulus names objects the device does not have, the case uses the
//! device's equivalent and says so in [`Case::note`]; where a product manual contradicts the
//! catalogue, the manual wins and the note says what the device does instead.

use canpos_encoder::Fault;
use canpos_stack::od::Group;

use crate::eds::{export, Eds, EdsEntry};
use crate::harness::{abort, nmt, BlockUpload, Harness};

/// The verdict of a case that did not fail.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// Every check passed.
    Pass,
    /// Not applicable to this model, with the catalogue's reason.
    Na(&'static str),
}

use Outcome::{Na, Pass};

/// One catalogue case.
pub struct Case {
    /// Catalogue ID, e.g. `SDO-07`.
    pub id: &'static str,
    /// Short title.
    pub title: &'static str,
    /// How the case runs on this device where that differs from the catalogue's wording.
    pub note: &'static str,
    /// The case.
    pub run: fn(&mut Harness) -> Outcome,
}

const NODE: u16 = 0x7F;
const EMCY: u16 = 0x80 + NODE;
const HB: u16 = 0x700 + NODE;
const SAVE: u32 = 0x6576_6173;
const LOAD: u32 = 0x6461_6F6C;
const WRONG: u32 = 0x7772_6F6E;

const NO_GUARDING: &str = "TMI has no node guarding (manual; SPEC §7)";
const NO_RPDO: &str = "no RPDO (TPDO-only sensor)";
const NO_1019: &str = "0x1006 / 0x1019 not implemented (SYNC consumer without counter)";
const NO_PRODUCER: &str = "no SYNC producer";
const NO_CONSUMER: &str = "no heartbeat consumer";

// ---- helpers ------------------------------------------------------------------------------

fn guarding(h: &Harness) -> bool {
    h.model().features.node_guarding
}
fn segmented(h: &Harness) -> bool {
    h.model().features.sdo_segmented
}
fn block(h: &Harness) -> bool {
    h.model().features.sdo_block
}

/// The SDO result is one of the accepted abort codes.
#[track_caller]
fn aborts<T: std::fmt::Debug>(r: Result<T, u32>, ok: &[u32]) {
    match r {
        Err(c) if ok.contains(&c) => {}
        other => panic!("expected abort {ok:08X?}, got {other:08X?}"),
    }
}

#[track_caller]
fn ok<T: std::fmt::Debug>(r: Result<T, u32>) -> T {
    match r {
        Ok(v) => v,
        Err(c) => panic!("unexpected abort {c:08X}"),
    }
}

fn eds(h: &Harness) -> Eds {
    Eds::parse(&export(h.model())).expect("EDS parses")
}

/// TPDOs (0-based) whose COB-ID is valid by default and whose mapping is not empty: the only
/// ones the CTT exercises; of those, the ones that may be event-driven (asynchronous by
/// default: the two-channel TMI's TPDO2 is "synchronous; no RTR's", 002 §1.2.5, and refuses
/// the asynchronous types the cases set up).
fn default_tpdos(h: &mut Harness) -> Vec<u16> {
    let mut v = Vec::new();
    for n in 0..u16::from(h.model().features.tpdos) {
        let cob = ok(h.read(0x1800 + n, 1));
        let cnt = ok(h.read(0x1A00 + n, 0));
        let ttype = ok(h.read(0x1800 + n, 2));
        if cob & 0x8000_0000 == 0 && cnt > 0 && ttype >= 254 {
            v.push(n);
        }
    }
    assert!(!v.is_empty(), "no valid default TPDO");
    v
}

fn tpdo_id(h: &mut Harness, n: u16) -> u16 {
    (ok(h.read(0x1800 + n, 1)) & 0x7FF) as u16
}

/// The CTT's configuration sequence (pre-op): invalid + no RTR, type, event timer, valid.
fn setup_tpdo(h: &mut Harness, n: u16, ttype: u8, event_ms: Option<u16>) {
    let cob = ok(h.read(0x1800 + n, 1)) & 0x7FF;
    ok(h.write(0x1800 + n, 1, 0xC000_0000 | cob, 4));
    ok(h.write(0x1800 + n, 2, u32::from(ttype), 1));
    if let Some(ms) = event_ms {
        ok(h.write(0x1800 + n, 5, u32::from(ms), 2));
    }
    ok(h.write(0x1800 + n, 1, 0x4000_0000 | cob, 4));
}

/// `n` within ±10 % of `expected` (at least ±1 frame for the window edges).
#[track_caller]
fn within(n: usize, expected: usize, what: &str) {
    let tol = (expected / 10).max(1);
    assert!(
        n + tol >= expected && n <= expected + tol,
        "{what}: {n} frames, expected {expected} ±{tol}"
    );
}

/// Observation window: long on the virtual clock (as the CTT), short in real time.
fn window_ms(h: &Harness, virtual_ms: u64, real_ms: u64) -> u64 {
    if h.is_virtual() {
        virtual_ms
    } else {
        real_ms
    }
}

/// The state byte of the next heartbeat (1017 must be set).
fn hb_state(h: &mut Harness) -> u8 {
    let (_, f) = h
        .wait_for(1100, |f| f.std_id() == Some(HB))
        .expect("heartbeat");
    assert_eq!(f.dlc(), 1);
    f.data()[0]
}

/// Heartbeat 500 ms then read the state from it and, where the model has guarding, from a
/// guarding reply too (the STATE / TRANS sub-steps CANopenNode skipped).
#[track_caller]
fn expect_state(h: &mut Harness, state: u8) {
    h.clear();
    assert_eq!(hb_state(h), state, "heartbeat state");
    if guarding(h) {
        let g = h.guard().expect("guarding reply");
        assert_eq!(g & 0x7F, state, "guarding state");
    }
}

/// Reads a value as the EDS describes it and compares with the EDS default.
fn check_default(h: &mut Harness, e: &EdsEntry) {
    let Some(d) = e.default.as_deref() else {
        return;
    };
    if e.is_string() {
        let got = ok(h.upload(e.index, e.sub));
        assert_eq!(
            got,
            d.as_bytes(),
            "{:04X}:{:02X} string default",
            e.index,
            e.sub
        );
        return;
    }
    let size = e.size().expect("numeric type");
    let want = e.default_raw(127).expect("numeric default") as u64;
    let mask = if size >= 4 {
        0xFFFF_FFFF
    } else {
        (1u64 << (8 * size)) - 1
    };
    let got = h
        .upload(e.index, e.sub)
        .unwrap_or_else(|c| panic!("{:04X}:{:02X} upload aborted {c:08X}", e.index, e.sub));
    assert_eq!(got.len(), size, "{:04X}:{:02X} size", e.index, e.sub);
    let mut b = [0u8; 8];
    b[..size].copy_from_slice(&got);
    let got = u64::from_le_bytes(b);
    assert_eq!(
        got,
        want & mask,
        "{:04X}:{:02X} ({}) differs from the EDS default",
        e.index,
        e.sub,
        e.name
    );
}

/// Storage group of an object in the model's table (what "save" covers, per manual).
fn group(h: &Harness, index: u16, sub: u8) -> Option<Group> {
    h.model()
        .entries
        .iter()
        .find(|e| e.index == index && e.sub == sub)
        .map(|e| e.group)
}

/// Mapping entries are written only through the procedure (PDO-22…26); the OD walk skips
/// them because a write-back with `map:00 ≠ 0` is refused by design (PDO-23/24).
fn is_mapping_entry(e: &EdsEntry) -> bool {
    (0x1A00..=0x1BFF).contains(&e.index) && e.sub > 0
}

// ---- 1. EDS -------------------------------------------------------------------------------

fn eds_01(h: &mut Harness) -> Outcome {
    let text = export(h.model());
    let eds = Eds::parse(&text).expect("EDS parses as INI");
    const FILEINFO: &[&str] = &[
        "FileName",
        "FileVersion",
        "FileRevision",
        "EDSVersion",
        "Description",
        "CreationTime",
        "CreationDate",
        "CreatedBy",
        "ModificationTime",
        "ModificationDate",
        "ModifiedBy",
    ];
    for k in &eds.ini.section("FileInfo").expect("[FileInfo]").keys {
        let k = &k.name;
        assert!(FILEINFO.contains(&k.as_str()), "unknown [FileInfo] key {k}");
    }
    for k in [
        "VendorName",
        "VendorNumber",
        "ProductName",
        "NrOfRXPDO",
        "NrOfTXPDO",
    ] {
        assert!(
            eds.ini.get("DeviceInfo", k).is_some(),
            "[DeviceInfo] lacks {k}"
        );
    }
    assert_eq!(eds.ini.get("DeviceInfo", "NrOfRXPDO"), Some("0"));
    let ntx: usize = eds
        .ini
        .get("DeviceInfo", "NrOfTXPDO")
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(ntx, usize::from(h.model().features.tpdos));
    // Object lists and sections agree in both directions, counts included.
    let mut listed = Vec::new();
    for sec in ["MandatoryObjects", "OptionalObjects", "ManufacturerObjects"] {
        let keys = &eds.ini.section(sec).expect(sec).keys;
        let n: usize = eds
            .ini
            .get(sec, "SupportedObjects")
            .unwrap()
            .parse()
            .unwrap();
        assert_eq!(keys.len(), n + 1, "[{sec}] SupportedObjects");
        for k in keys.iter().filter(|k| k.name != "SupportedObjects") {
            let _: usize = k.name.parse().expect("list key is a number");
            listed.push(crate::eds::parse_number(&k.value, 0).unwrap() as u16);
        }
    }
    for i in [0x1000u16, 0x1001, 0x1018] {
        assert!(listed.contains(&i), "mandatory {i:04X} not listed");
    }
    let mut objects: Vec<u16> = eds.sub_numbers.keys().copied().collect();
    objects.sort();
    listed.sort();
    assert_eq!(listed, objects, "object lists vs object sections");
    for (&index, &n) in &eds.sub_numbers {
        let subs = eds.entries.iter().filter(|e| e.index == index).count();
        if n == 0 {
            assert_eq!(subs, 1, "{index:04X} VAR");
        } else {
            assert_eq!(subs, n, "{index:04X} SubNumber");
        }
        assert!(
            !(0x1400..=0x17FF).contains(&index),
            "RPDO section {index:04X}"
        );
    }
    for e in &eds.entries {
        let at = format!("{:04X}sub{:X}", e.index, e.sub);
        assert!(
            ["ro", "wo", "rw", "rwr", "rww", "const"].contains(&e.access.as_str()),
            "{at} AccessType {}",
            e.access
        );
        // (a) of the catalogue: no plain rw objects that are PDO-mappable.
        assert!(
            !(e.pdo_mapping && e.access == "rw"),
            "{at}: rw and PDOMapping=1"
        );
        assert!(
            e.is_string() || e.size().is_some(),
            "{at}: DataType {:04X}",
            e.data_type
        );
        if let Some(d) = &e.default {
            if !e.is_string() {
                let v = crate::eds::parse_number(d, 127)
                    .unwrap_or_else(|| panic!("{at}: DefaultValue {d} is not a number"));
                let lo = e
                    .limits
                    .0
                    .as_deref()
                    .and_then(|l| crate::eds::parse_number(l, 127));
                let hi = e
                    .limits
                    .1
                    .as_deref()
                    .and_then(|l| crate::eds::parse_number(l, 127));
                let sv = if e.signed() { v } else { v & 0xFFFF_FFFF };
                assert!(lo.is_none_or(|lo| sv >= lo), "{at}: default below LowLimit");
                assert!(
                    hi.is_none_or(|hi| sv <= hi),
                    "{at}: default above HighLimit"
                );
            }
        }
    }
    Pass
}

// ---- 2. SDO -------------------------------------------------------------------------------

fn sdo_01(h: &mut Harness) -> Outcome {
    let r = h
        .sdo_raw(&[0x40, 0x00, 0x10, 0, 0, 0, 0, 0])
        .expect("answer");
    assert_eq!(&r[..4], &[0x43, 0x00, 0x10, 0x00]);
    let want = eds(h).entry(0x1000, 0).unwrap().default_raw(127).unwrap();
    assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), want);
    Pass
}

fn sdo_02(h: &mut Harness) -> Outcome {
    let v = ok(h.upload(0x1017, 0));
    assert_eq!(v.len(), 2);
    ok(h.download(0x1017, 0, &v));
    Pass
}

fn sdo_03(h: &mut Harness) -> Outcome {
    let v = ok(h.read(0x1000, 0));
    aborts(
        h.write(0x1000, 0, v, 4),
        &[abort::READ_ONLY, abort::UNSUPPORTED, abort::GENERAL],
    );
    Pass
}

fn sdo_04(h: &mut Harness) -> Outcome {
    if eds(h).entries.iter().any(|e| e.access == "wo") {
        panic!("the EDS has wo objects: SDO-04 must be implemented");
    }
    Na("no write-only object in the EDS")
}

fn sdo_05(h: &mut Harness) -> Outcome {
    aborts(h.upload(0x1000, 1), &[abort::NO_SUB, abort::GENERAL]);
    Pass
}

fn sdo_06(h: &mut Harness) -> Outcome {
    aborts(h.upload(0x1004, 0), &[abort::NO_OBJECT, abort::GENERAL]);
    Pass
}

fn sdo_07(h: &mut Harness) -> Outcome {
    let r = h
        .sdo_raw(&[0xE0, 0x00, 0x10, 0x00, 0, 0, 0, 0])
        .expect("answer");
    assert_eq!(r[0], 0x80);
    let code = u32::from_le_bytes([r[4], r[5], r[6], r[7]]);
    assert!(
        [abort::BAD_COMMAND, abort::GENERAL].contains(&code),
        "{code:08X}"
    );
    // Cleaner than CANopenNode: the abort names the object of the bad frame.
    assert_eq!(&r[1..4], &[0x00, 0x10, 0x00]);
    Pass
}

fn sdo_08(h: &mut Harness) -> Outcome {
    ok(h.read(0x1003, 0));
    aborts(
        h.write(0x1003, 0, 0, 4),
        &[abort::LENGTH_HIGH, abort::LENGTH, abort::GENERAL],
    );
    Pass
}

fn sdo_09(h: &mut Harness) -> Outcome {
    aborts(
        h.write(0x1005, 0, 0x80, 1),
        &[abort::LENGTH_LOW, abort::LENGTH, abort::GENERAL],
    );
    Pass
}

fn sdo_10(h: &mut Harness) -> Outcome {
    aborts(
        h.write(0x1003, 0, 0xFF, 1),
        &[abort::RANGE, abort::TOO_HIGH, abort::GENERAL],
    );
    Pass
}

fn sdo_11(h: &mut Harness) -> Outcome {
    // Every rw object with a LowLimit above its type's minimum gets LowLimit − 1.
    let eds = eds(h);
    let mut n = 0;
    for e in eds.entries.iter().filter(|e| e.writable()) {
        let Some(lo) = e
            .limits
            .0
            .as_deref()
            .and_then(|l| crate::eds::parse_number(l, 127))
        else {
            continue;
        };
        let size = e.size().unwrap();
        let type_min = if e.signed() {
            -(1i64 << (8 * size - 1))
        } else {
            0
        };
        if lo <= type_min {
            continue;
        }
        n += 1;
        aborts(
            h.write(e.index, e.sub, (lo - 1) as u32, size),
            &[abort::TOO_LOW, abort::RANGE, abort::GENERAL],
        );
    }
    if n == 0 {
        return Na("no LowLimit above the type minimum in the EDS");
    }
    Pass
}

fn sdo_12(h: &mut Harness) -> Outcome {
    assert_eq!(ok(h.read(0x1200, 1)), 0x600 + u32::from(NODE));
    assert_eq!(ok(h.read(0x1200, 2)), 0x580 + u32::from(NODE));
    Pass
}

fn sdo_13(h: &mut Harness) -> Outcome {
    let want = ok(h.read(0x1000, 0));
    assert_eq!(
        want,
        eds(h).entry(0x1000, 0).unwrap().default_raw(127).unwrap()
    );
    Pass
}

/// Segmented download of a 2-byte object (SDO-14 / SDO-15 pattern); TMI checks the refusal.
fn seg_write(h: &mut Harness, index: u16) -> Outcome {
    let i = index.to_le_bytes();
    let r = h
        .sdo_raw(&[0x21, i[0], i[1], 0, 2, 0, 0, 0])
        .expect("answer");
    if !segmented(h) {
        assert_eq!(r[0], 0x80);
        assert_eq!(
            u32::from_le_bytes([r[4], r[5], r[6], r[7]]),
            abort::BAD_COMMAND
        );
        return Pass;
    }
    assert_eq!(&r[..4], &[0x60, i[0], i[1], 0]);
    let r = h
        .sdo_raw(&[0x0B, 0x00, 0x00, 0, 0, 0, 0, 0])
        .expect("segment ack");
    assert_eq!(r[0], 0x20);
    assert_eq!(ok(h.read(index, 0)), 0);
    Pass
}

fn sdo_14(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    seg_write(h, 0x100C)
}

fn sdo_15(h: &mut Harness) -> Outcome {
    seg_write(h, 0x1017)
}

/// The longest readable object: SDO-16…18/22/23 use 1008 (device name). Its text is the
/// manual's ("C304", "MTS", "TMI"), so it fits an expedited answer.
fn sdo_16(h: &mut Harness) -> Outcome {
    let name = ok(h.upload(0x1008, 0));
    let want = eds(h).entry(0x1008, 0).unwrap().default.clone().unwrap();
    assert_eq!(name, want.as_bytes());
    if segmented(h) {
        // The segmented path with toggles, end bit and n field: a 6-byte string download
        // is refused at the initiate (const object), so the upload side is checked on the
        // server's answer form and the toggle logic through SDO-15/17.
        aborts(
            h.download_segmented(0x1008, 0, b"ABCDEF", false),
            &[abort::READ_ONLY, abort::UNSUPPORTED, abort::GENERAL],
        );
    }
    Pass
}

fn sdo_17(h: &mut Harness) -> Outcome {
    if !segmented(h) {
        let r = h
            .sdo_raw(&[0x21, 0x17, 0x10, 0, 2, 0, 0, 0])
            .expect("answer");
        assert_eq!(
            u32::from_le_bytes([r[4], r[5], r[6], r[7]]),
            abort::BAD_COMMAND
        );
        return Pass;
    }
    // Upload side: a segment request without a transfer in progress is refused.
    let r = h.sdo_raw(&[0x70, 0, 0, 0, 0, 0, 0, 0]).expect("answer");
    assert_eq!(r[0], 0x80);
    // Download side: first segment with toggle 1.
    aborts(
        h.download_segmented(0x1017, 0, &[0, 0], true),
        &[abort::TOGGLE],
    );
    Pass
}

fn sdo_18(h: &mut Harness) -> Outcome {
    sdo_16(h)
}

/// Block initiate on a model without block transfer: refused with 0x05040001.
fn block_refused(h: &mut Harness, upload: bool) -> Outcome {
    let req = if upload {
        [0xA4, 0x00, 0x10, 0, 20, 0, 0, 0]
    } else {
        [0xC6, 0x17, 0x10, 0, 2, 0, 0, 0]
    };
    let r = h.sdo_raw(&req).expect("answer");
    assert_eq!(r[0], 0x80);
    assert_eq!(
        u32::from_le_bytes([r[4], r[5], r[6], r[7]]),
        abort::BAD_COMMAND
    );
    Pass
}

fn sdo_19(h: &mut Harness) -> Outcome {
    if !block(h) {
        return block_refused(h, true);
    }
    let d = ok(h.block_upload(0x1000, 0, BlockUpload::default()));
    assert_eq!(d, ok(h.upload(0x1000, 0)));
    Pass
}

fn block_write(h: &mut Harness, index: u16, crc: bool) -> Outcome {
    if !block(h) {
        return block_refused(h, false);
    }
    let blk = ok(h.block_download(index, 0, &[0x2C, 0x01], crc));
    assert_eq!(blk, 127);
    assert_eq!(ok(h.read(index, 0)), 300);
    Pass
}

fn sdo_20(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    block_write(h, 0x100C, false)
}

fn sdo_21(h: &mut Harness) -> Outcome {
    block_write(h, 0x1017, false)
}

fn sdo_22(h: &mut Harness) -> Outcome {
    if !block(h) {
        return block_refused(h, true);
    }
    let d = ok(h.block_upload(0x1008, 0, BlockUpload::default()));
    assert_eq!(d, ok(h.upload(0x1008, 0)));
    // Several segments in one block as in the log: blksize 1 forces one block per segment.
    let d = ok(h.block_upload(
        0x1008,
        0,
        BlockUpload {
            blksize: 1,
            ..Default::default()
        },
    ));
    assert_eq!(d, ok(h.upload(0x1008, 0)));
    Pass
}

fn sdo_23(h: &mut Harness) -> Outcome {
    if !block(h) {
        return block_refused(h, true);
    }
    // The catalogue's CRC check value first (the harness's CRC is what the server must match).
    assert_eq!(canpos_stack::sdo::wire::crc16(b"CANopenDemoPIC32"), 0x43F3);
    let o = BlockUpload {
        crc: true,
        ..Default::default()
    };
    let d = ok(h.block_upload(0x1008, 0, o));
    assert_eq!(d, ok(h.upload(0x1008, 0)));
    Pass
}

fn sdo_24(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    block_write(h, 0x100C, true)
}

fn sdo_25(h: &mut Harness) -> Outcome {
    block_write(h, 0x1017, true)
}

fn sdo_26(h: &mut Harness) -> Outcome {
    let r = h
        .sdo_raw(&[0xA0, 0x00, 0x10, 0, 0x80, 0, 0, 0])
        .expect("answer");
    assert_eq!(r[0], 0x80);
    let code = u32::from_le_bytes([r[4], r[5], r[6], r[7]]);
    if block(h) {
        assert!(
            [abort::BAD_BLOCK_SIZE, abort::BAD_COMMAND, abort::GENERAL].contains(&code),
            "{code:08X}"
        );
    } else {
        assert_eq!(code, abort::BAD_COMMAND);
    }
    Pass
}

fn sdo_27(h: &mut Harness) -> Outcome {
    if !block(h) {
        return block_refused(h, true);
    }
    let o = BlockUpload {
        forged_ackseq: Some(128),
        ..Default::default()
    };
    // Exactly 0x05040003: 0x05040001 would make the CTT skip (catalogue §13).
    aborts(h.block_upload(0x1000, 0, o), &[abort::BAD_SEQUENCE]);
    Pass
}

fn sdo_28(h: &mut Harness) -> Outcome {
    for i in 0x1201..=0x127F {
        aborts(h.upload(i, 1), &[abort::NO_OBJECT, abort::GENERAL]);
    }
    Pass
}

fn sdo_29(_: &mut Harness) -> Outcome {
    Na("only the default SDO server")
}

fn sdo_30(_: &mut Harness) -> Outcome {
    Na("no SDO client")
}

// ---- 3. PDO -------------------------------------------------------------------------------

fn pdo_01(h: &mut Harness) -> Outcome {
    for i in 0x1400..=0x1403 {
        aborts(h.upload(i, 1), &[abort::NO_OBJECT]);
    }
    Pass
}

fn pdo_02(h: &mut Harness) -> Outcome {
    let f = h.model().features;
    for n in 0..4u16 {
        let r = h.read(0x1800 + n, 1);
        if n >= u16::from(f.tpdos) {
            aborts(r, &[abort::NO_OBJECT]);
            continue;
        }
        let cob = ok(r);
        assert_eq!(
            cob & 0x7FF,
            0x180 + 0x100 * u32::from(n) + u32::from(NODE),
            "TPDO{}",
            n + 1
        );
        if !f.tpdo_rtr {
            assert_ne!(cob & 0x4000_0000, 0, "bit 30 without RTR support");
        }
        assert_eq!(cob & 0x2000_0000, 0);
    }
    Pass
}

/// Whether TPDO `n` answers RTRs by default (COB-ID bit 30 clear and the model supports it).
fn rtr_tpdo(h: &mut Harness) -> Option<(u16, u16)> {
    if !h.model().features.tpdo_rtr {
        return None;
    }
    for n in default_tpdos(h) {
        let cob = ok(h.read(0x1800 + n, 1));
        if cob & 0x4000_0000 == 0 {
            return Some((n, (cob & 0x7FF) as u16));
        }
    }
    None
}

const NO_RTR: &str = "TPDO RTR not supported (COB-ID bit 30 set)";

fn rtr_case(h: &mut Harness, cs: Option<u8>, answer: bool) -> Outcome {
    let Some((_, id)) = rtr_tpdo(h) else {
        return Na(NO_RTR);
    };
    if let Some(cs) = cs {
        h.nmt(cs);
    }
    h.clear();
    h.rtr(id, 8);
    let got = h.wait_for(50, |f| f.std_id() == Some(id) && !f.is_remote());
    assert_eq!(got.is_some(), answer, "TPDO answer to RTR");
    Pass
}

fn pdo_03(h: &mut Harness) -> Outcome {
    // Event timer off so only the RTR can produce the frame.
    let Some((n, _)) = rtr_tpdo(h) else {
        return Na(NO_RTR);
    };
    let cob = ok(h.read(0x1800 + n, 1));
    ok(h.write(0x1800 + n, 1, cob | 0x8000_0000, 4));
    ok(h.write(0x1800 + n, 5, 0, 2));
    ok(h.write(0x1800 + n, 1, cob, 4));
    rtr_case(h, Some(nmt::START), true)
}

/// PDO-04 / 05 / 10 / 11 / 16 / 17: type 254, 100 ms event timer, in state `cs`.
fn event_case(h: &mut Harness, cs: Option<u8>, produce: bool) -> Outcome {
    for n in default_tpdos(h) {
        setup_tpdo(h, n, 254, Some(100));
        let id = tpdo_id(h, n);
        if let Some(cs) = cs {
            h.nmt(cs);
        }
        let win = window_ms(h, 2000, 1000);
        let frames = h.wait_ms(win);
        let c = Harness::count(&frames, id);
        if produce {
            within(c, (win / 100) as usize, "TPDO with 100 ms event timer");
            // "At least one more frame when the CTT waits again."
            let more = h.wait_ms(150);
            assert!(Harness::count(&more, id) >= 1);
        } else {
            assert_eq!(c, 0, "TPDO outside operational");
        }
        h.nmt(nmt::PRE_OP);
    }
    Pass
}

fn pdo_04(h: &mut Harness) -> Outcome {
    event_case(h, Some(nmt::START), true)
}
fn pdo_05(h: &mut Harness) -> Outcome {
    event_case(h, Some(nmt::START), true)
}

fn pdo_06(h: &mut Harness) -> Outcome {
    for n in default_tpdos(h) {
        setup_tpdo(h, n, 1, None);
        let id = tpdo_id(h, n);
        h.nmt(nmt::START);
        assert_eq!(Harness::count(&h.wait_ms(500), id), 0, "TPDO before SYNC");
        h.sync();
        assert_eq!(
            Harness::count(&h.wait_ms(200), id),
            1,
            "TPDO after one SYNC"
        );
        h.nmt(nmt::PRE_OP);
    }
    Pass
}

fn pdo_07(h: &mut Harness) -> Outcome {
    for n in default_tpdos(h) {
        setup_tpdo(h, n, 0, None);
        let id = tpdo_id(h, n);
        h.nmt(nmt::START);
        h.clear();
        // §13: the mapped value changes between SYNCs (the magnet moves: sensor hook in
        // place of the CTT's RPDO-driven data), so every SYNC has a TPDO.
        for k in 0..3 {
            h.move_magnet(100.0 + 10.0 * f64::from(k));
            h.sync();
            assert_eq!(
                Harness::count(&h.wait_ms(100), id),
                1,
                "TPDO after SYNC {k}"
            );
        }
        // CiA 301 acyclic: no change, no TPDO.
        h.sync();
        assert_eq!(
            Harness::count(&h.wait_ms(100), id),
            0,
            "TPDO without change"
        );
        h.nmt(nmt::PRE_OP);
    }
    Pass
}

const NO_START_VALUE: &str = "1800:06 SYNC start value and 0x1019 not implemented";

fn pdo_08(h: &mut Harness) -> Outcome {
    aborts(h.upload(0x1800, 6), &[abort::NO_SUB]);
    aborts(h.upload(0x1019, 0), &[abort::NO_OBJECT]);
    Na(NO_START_VALUE)
}

fn pdo_09(h: &mut Harness) -> Outcome {
    rtr_case(h, Some(nmt::STOP), false)
}

fn pdo_10(h: &mut Harness) -> Outcome {
    event_case(h, Some(nmt::STOP), false)
}
fn pdo_11(h: &mut Harness) -> Outcome {
    event_case(h, Some(nmt::STOP), false)
}

fn sync_case(h: &mut Harness, ttype: u8, cs: Option<u8>) -> Outcome {
    for n in default_tpdos(h) {
        setup_tpdo(h, n, ttype, None);
        let id = tpdo_id(h, n);
        if let Some(cs) = cs {
            h.nmt(cs);
        }
        h.clear();
        for _ in 0..2 {
            h.move_magnet(200.0);
            h.sync();
            h.move_magnet(300.0);
        }
        assert_eq!(Harness::count(&h.wait_ms(200), id), 0);
        h.nmt(nmt::PRE_OP);
    }
    Pass
}

fn pdo_12(h: &mut Harness) -> Outcome {
    sync_case(h, 1, Some(nmt::STOP))
}
fn pdo_13(h: &mut Harness) -> Outcome {
    sync_case(h, 0, Some(nmt::STOP))
}
fn pdo_14(h: &mut Harness) -> Outcome {
    pdo_08(h)
}
fn pdo_15(h: &mut Harness) -> Outcome {
    rtr_case(h, None, false)
}
fn pdo_16(h: &mut Harness) -> Outcome {
    event_case(h, None, false)
}
fn pdo_17(h: &mut Harness) -> Outcome {
    event_case(h, None, false)
}
fn pdo_18(h: &mut Harness) -> Outcome {
    sync_case(h, 1, None)
}
fn pdo_19(h: &mut Harness) -> Outcome {
    sync_case(h, 0, None)
}
fn pdo_20(h: &mut Harness) -> Outcome {
    pdo_08(h)
}

fn pdo_21(h: &mut Harness) -> Outcome {
    let eds = eds(h);
    for i in 0x1600..=0x1603 {
        aborts(h.upload(i, 0), &[abort::NO_OBJECT]);
    }
    for n in 0..u16::from(h.model().features.tpdos) {
        let cnt = ok(h.read(0x1A00 + n, 0));
        let e = eds.entry(0x1A00 + n, 0).unwrap();
        assert_eq!(Some(cnt), e.default_raw(127), "1A{n:02X}:00");
        for k in 1..=cnt as u8 {
            let m = ok(h.read(0x1A00 + n, k));
            assert_eq!(Some(m), eds.entry(0x1A00 + n, k).unwrap().default_raw(127));
            let (i, s) = ((m >> 16) as u16, (m >> 8) as u8);
            let obj = eds
                .entry(i, s)
                .unwrap_or_else(|| panic!("mapped {i:04X}:{s:02X} missing"));
            assert!(obj.pdo_mapping, "{i:04X}:{s:02X} not mappable in the EDS");
            ok(h.upload(i, s));
        }
    }
    Pass
}

/// The mapping procedure on TPDO `n` with `entries`; returns the result of each step.
fn procedure(h: &mut Harness, n: u16, entries: &[u32], count: u8) -> Vec<Result<(), u32>> {
    let cob = ok(h.read(0x1800 + n, 1));
    let mut r = vec![
        h.write(0x1800 + n, 1, cob | 0x8000_0000, 4),
        h.write(0x1A00 + n, 0, 0, 1),
    ];
    for (k, &e) in entries.iter().enumerate() {
        r.push(h.write(0x1A00 + n, k as u8 + 1, e, 4));
    }
    r.push(h.write(0x1A00 + n, 0, u32::from(count), 1));
    r.push(h.write(0x1800 + n, 1, cob & !0x8000_0000, 4));
    r
}

fn pdo_22(h: &mut Harness) -> Outcome {
    for n in default_tpdos(h) {
        let cnt = ok(h.read(0x1A00 + n, 0)) as u8;
        let entries: Vec<u32> = (1..=cnt).map(|k| ok(h.read(0x1A00 + n, k))).collect();
        for (k, r) in procedure(h, n, &entries, cnt).into_iter().enumerate() {
            assert_eq!(r, Ok(()), "procedure step {k}");
        }
        // The PDO really runs with that mapping.
        let id = tpdo_id(h, n);
        let len: u32 = entries.iter().map(|e| (e & 0xFF) / 8).sum();
        h.nmt(nmt::START);
        let (_, f) = h.wait_for(500, |f| f.std_id() == Some(id)).expect("TPDO");
        assert_eq!(u32::from(f.dlc()), len);
        h.nmt(nmt::PRE_OP);
    }
    Pass
}

fn pdo_23(h: &mut Harness) -> Outcome {
    for n in default_tpdos(h) {
        let cob = ok(h.read(0x1800 + n, 1));
        ok(h.write(0x1800 + n, 1, cob | 0x8000_0000, 4));
        let e = ok(h.read(0x1A00 + n, 1));
        aborts(
            h.write(0x1A00 + n, 1, e, 4),
            &[abort::UNSUPPORTED, abort::NOT_MAPPABLE, abort::GENERAL],
        );
    }
    Pass
}

fn pdo_24(h: &mut Harness) -> Outcome {
    // "Restore defaults first": a fresh device per case has them.
    for n in default_tpdos(h) {
        let cob = ok(h.read(0x1800 + n, 1));
        assert_eq!(cob & 0x8000_0000, 0);
        let cnt = ok(h.read(0x1A00 + n, 0));
        let e = ok(h.read(0x1A00 + n, 1));
        aborts(
            h.write(0x1A00 + n, 1, e, 4),
            &[abort::UNSUPPORTED, abort::NOT_MAPPABLE, abort::GENERAL],
        );
        // Manual wins (TH / E-Series Example 5): sub 0 = 0 on a valid PDO is accepted and
        // the mapping is changed without touching COB-ID bit 31.
        ok(h.write(0x1A00 + n, 0, 0, 1));
        ok(h.write(0x1A00 + n, 1, e, 4));
        ok(h.write(0x1A00 + n, 0, cnt, 1));
        assert_eq!(ok(h.read(0x1800 + n, 1)), cob);
    }
    Pass
}

/// The number of mapping entries TPDO `n` has (8 on TH / E, 5 on TMI).
fn map_subs(h: &Harness, n: u16) -> u8 {
    h.model()
        .entries
        .iter()
        .filter(|e| e.index == 0x1A00 + n && e.sub > 0)
        .count() as u8
}

/// The 8-bit input the CTT maps (1001:00), or, where the manual names the mappable objects and
/// 1001 is not among them (TMI 002 §1.2.5), the cam state of channel 1 (DECISIONS.md).
fn input8(h: &Harness) -> u32 {
    let mappable = h
        .model()
        .entries
        .iter()
        .any(|e| (e.index, e.sub) == (0x1001, 0) && e.pdo);
    if mappable {
        0x1001_0008
    } else {
        0x6300_0108
    }
}

fn pdo_25(h: &mut Harness) -> Outcome {
    for n in default_tpdos(h) {
        let subs = map_subs(h, n);
        let entries = vec![input8(h); usize::from(subs)];
        let r = procedure(h, n, &entries, subs + 1);
        for (k, x) in r[..r.len() - 2].iter().enumerate() {
            assert_eq!(*x, Ok(()), "step {k}");
        }
        aborts(
            r[r.len() - 2],
            &[abort::MAPPING_LENGTH, abort::NO_OBJECT, abort::NOT_MAPPABLE],
        );
        if subs == 8 {
            ok(h.write(0x1A00 + n, 0, 8, 1));
        }
    }
    Pass
}

fn pdo_26(h: &mut Harness) -> Outcome {
    for n in default_tpdos(h) {
        let subs = map_subs(h, n);
        let entries = vec![0x6020_0120; usize::from(subs)];
        let r = procedure(h, n, &entries, subs);
        for (k, x) in r[..r.len() - 2].iter().enumerate() {
            assert_eq!(*x, Ok(()), "step {k}");
        }
        aborts(
            r[r.len() - 2],
            &[abort::MAPPING_LENGTH, abort::NO_OBJECT, abort::NOT_MAPPABLE],
        );
    }
    Pass
}

fn pdo_27(_: &mut Harness) -> Outcome {
    Na(NO_RPDO)
}
fn pdo_28(_: &mut Harness) -> Outcome {
    Na(NO_RPDO)
}
fn pdo_29(_: &mut Harness) -> Outcome {
    Na(NO_RPDO)
}

fn pdo_30(h: &mut Harness) -> Outcome {
    if input8(h) != 0x1001_0008 {
        // The manual wins: 1001 is no mappable object of this product.
        let r = procedure(h, 0, &[0x1001_0008], 1);
        assert_eq!(r[2], Err(abort::NOT_MAPPABLE), "1001:00 into TPDO1");
    }
    for n in 0..u16::from(h.model().features.tpdos) {
        for (k, r) in procedure(h, n, &[input8(h)], 1).into_iter().enumerate() {
            // The last step validates the PDO; TMI's TPDO2 is only valid on two-channel units
            // but its COB-ID may still be set valid.
            assert_eq!(r, Ok(()), "TPDO{} step {k}", n + 1);
        }
    }
    Pass
}

fn pdo_31(h: &mut Harness) -> Outcome {
    let eds = eds(h);
    assert!(!eds
        .entries
        .iter()
        .any(|e| matches!(e.access.as_str(), "rww" | "wo")));
    Na("no output (rww / wo) objects: a pure sensor")
}

fn pdo_32(h: &mut Harness) -> Outcome {
    for n in 0..u16::from(h.model().features.tpdos) {
        let cob = ok(h.read(0x1800 + n, 1));
        ok(h.write(0x1800 + n, 1, cob | 0x8000_0000, 4));
        ok(h.write(0x1A00 + n, 0, 0, 1));
        aborts(
            h.write(0x1A00 + n, 1, 0x1000_0020, 4),
            &[abort::NOT_MAPPABLE, abort::NO_OBJECT],
        );
    }
    Pass
}

fn pdo_33(_: &mut Harness) -> Outcome {
    Na("dummy mapping is for RPDOs only; no RPDO")
}

// ---- 4. OD --------------------------------------------------------------------------------

/// OD-01 / 07: upload everything, write back rw values (1010 / 1011 only read).
fn od_walk(h: &mut Harness, lo: u16, hi: u16, write_back: bool) -> Outcome {
    let eds = eds(h);
    for e in eds.entries.iter().filter(|e| (lo..=hi).contains(&e.index)) {
        if !e.readable() {
            continue;
        }
        let v = match h.upload(e.index, e.sub) {
            Ok(v) => v,
            // 1003:n beyond the number of errors holds no data (EMCY-03).
            Err(abort::NO_DATA) if e.index == 0x1003 => continue,
            Err(c) => panic!("upload {:04X}:{:02X} aborted {c:08X}", e.index, e.sub),
        };
        if write_back && e.writable() && !matches!(e.index, 0x1010 | 0x1011) && !is_mapping_entry(e)
        {
            let r = h.download(e.index, e.sub, &v);
            assert_eq!(
                r,
                Ok(()),
                "write-back {:04X}:{:02X} ({})",
                e.index,
                e.sub,
                e.name
            );
        }
    }
    Pass
}

fn od_01(h: &mut Harness) -> Outcome {
    od_walk(h, 0x1000, 0xFFFF, true)
}

fn od_02(h: &mut Harness) -> Outcome {
    defaults(h, 0x1000, 0xFFFF)
}

fn defaults(h: &mut Harness, lo: u16, hi: u16) -> Outcome {
    let eds = eds(h);
    let table = h.model().entries;
    for e in eds.entries.iter().filter(|e| (lo..=hi).contains(&e.index)) {
        check_default(h, e);
        // Live values carry no default (§13 item 4).
        let t = table
            .iter()
            .find(|t| t.index == e.index && t.sub == e.sub)
            .unwrap();
        if matches!(t.default, canpos_stack::od::DefaultValue::Live) {
            assert!(
                e.default.is_none(),
                "{:04X}:{:02X} live with DefaultValue",
                e.index,
                e.sub
            );
        }
    }
    Pass
}

fn od_03(h: &mut Harness) -> Outcome {
    let eds = eds(h);
    for e in eds
        .entries
        .iter()
        .filter(|e| matches!(e.access.as_str(), "ro" | "const"))
    {
        let v = match h.upload(e.index, e.sub) {
            Ok(v) => v,
            Err(abort::NO_DATA) if e.index == 0x1003 => vec![0; 4],
            Err(c) => panic!("upload {:04X}:{:02X}: {c:08X}", e.index, e.sub),
        };
        let ok_codes = [abort::READ_ONLY, abort::UNSUPPORTED, abort::GENERAL];
        if v.len() <= 4 {
            aborts(h.download(e.index, e.sub, &v), &ok_codes);
        }
        if segmented(h) {
            // Segmented initiate with a size that does not match: refused at the initiate.
            let mut long = v.clone();
            long.extend_from_slice(b"xyz");
            aborts(
                h.download_segmented(e.index, e.sub, &long, false),
                &ok_codes,
            );
        }
    }
    Pass
}

fn od_04(h: &mut Harness) -> Outcome {
    sdo_04(h)
}

fn od_05(h: &mut Harness) -> Outcome {
    // Optional: sub FFh is not supported, so the answer is an abort (the CTT then skips).
    aborts(h.upload(0x1000, 0xFF), &[abort::NO_SUB]);
    Pass
}

fn od_06(h: &mut Harness) -> Outcome {
    let eds = eds(h);
    let mut n = 0;
    for e in eds
        .entries
        .iter()
        .filter(|e| e.writable() && e.size().is_some())
    {
        let (Some(lo), Some(hi)) = (
            e.limits
                .0
                .as_deref()
                .and_then(|l| crate::eds::parse_number(l, 127)),
            e.limits
                .1
                .as_deref()
                .and_then(|l| crate::eds::parse_number(l, 127)),
        ) else {
            continue;
        };
        let size = e.size().unwrap();
        let (tmin, tmax) = if e.signed() {
            (-(1i64 << (8 * size - 1)), (1i64 << (8 * size - 1)) - 1)
        } else {
            (0, (1i64 << (8 * size.min(4))) - 1)
        };
        let codes = [
            abort::RANGE,
            abort::TOO_HIGH,
            abort::TOO_LOW,
            abort::GENERAL,
        ];
        if hi < tmax {
            n += 1;
            aborts(h.write(e.index, e.sub, (hi + 1) as u32, size), &codes);
        }
        if lo > tmin {
            n += 1;
            aborts(h.write(e.index, e.sub, (lo - 1) as u32, size), &codes);
        }
    }
    assert!(n > 0);
    Pass
}

fn od_07(h: &mut Harness) -> Outcome {
    od_walk(h, 0x2000, 0x9FFF, true)
}
fn od_08(h: &mut Harness) -> Outcome {
    defaults(h, 0x2000, 0x9FFF)
}
fn od_09(h: &mut Harness) -> Outcome {
    od_walk(h, 0x2000, 0x9FFF, true)
}

// ---- 5. EMCY ------------------------------------------------------------------------------

fn emcy_01(h: &mut Harness) -> Outcome {
    assert_eq!(ok(h.read(0x1014, 0)), 0x80 + u32::from(NODE));
    Pass
}

fn emcy_02(h: &mut Harness) -> Outcome {
    assert_eq!(ok(h.read(0x1001, 0)), 0);
    Pass
}

fn emcy_03(h: &mut Harness) -> Outcome {
    assert_eq!(ok(h.read(0x1003, 0)), 0);
    aborts(
        h.upload(0x1003, 1),
        &[abort::NO_DATA, abort::NO_SUB, abort::GENERAL],
    );
    Pass
}

/// Forces an EMCY without an RPDO; returns the frame. TH / E-Series: a SYNC with a wrong
/// length (0x8240, CiA 301); TMI, whose manual's EMCY table has no 0x8240: the transducer
/// fault hook (0x5000).
fn force_emcy(h: &mut Harness) -> [u8; 8] {
    h.clear();
    if h.model().profile.tmi_error_reactions {
        h.fault(Fault::Transducer, true);
    } else {
        h.raw(0x080, &[0, 0]);
    }
    let (_, f) = h.wait_for(100, |f| f.std_id() == Some(EMCY)).expect("EMCY");
    let mut b = [0u8; 8];
    b.copy_from_slice(f.data());
    b
}

fn emcy_04(h: &mut Harness) -> Outcome {
    ok(h.upload(0x1000, 0));
    h.nmt(nmt::START);
    let e = force_emcy(h);
    let code = u16::from_le_bytes([e[0], e[1]]);
    if h.model().profile.tmi_error_reactions {
        assert_eq!(code, 0x5000);
    } else {
        assert_eq!(code, 0x8240);
    }
    // Byte 2 is the error register at the time of the EMCY.
    h.nmt(nmt::PRE_OP);
    assert_eq!(u32::from(e[2]), ok(h.read(0x1001, 0)));
    Pass
}

fn emcy_05(h: &mut Harness) -> Outcome {
    force_emcy(h);
    ok(h.read(0x1001, 0));
    Pass
}

fn emcy_06(h: &mut Harness) -> Outcome {
    for _ in 0..2 {
        let e = force_emcy(h);
        let hist = ok(h.read(0x1003, 1));
        assert_eq!(hist & 0xFFFF, u32::from(u16::from_le_bytes([e[0], e[1]])));
        assert_eq!(hist >> 16, u32::from(u16::from_le_bytes([e[3], e[4]])));
        if h.model().profile.tmi_error_reactions {
            break;
        }
    }
    // A second trigger with other manufacturer bytes (the fault hook on every model).
    if !h.model().profile.tmi_error_reactions {
        let _ = h.take();
        h.fault(Fault::SupplyVoltage, true);
        let (_, f) = h.wait_for(100, |f| f.std_id() == Some(EMCY)).expect("EMCY");
        let e = f.data();
        let hist = ok(h.read(0x1003, 1));
        assert_eq!(hist & 0xFFFF, u32::from(u16::from_le_bytes([e[0], e[1]])));
        assert_eq!(hist >> 16, u32::from(u16::from_le_bytes([e[3], e[4]])));
    }
    Pass
}

// ---- 6. SYNC ------------------------------------------------------------------------------

fn sync_01(h: &mut Harness) -> Outcome {
    assert_eq!(ok(h.read(0x1005, 0)), 0x80);
    Pass
}

fn sync_02(h: &mut Harness) -> Outcome {
    // Not a producer: bit 30 is refused as the catalogue asks.
    aborts(h.write(0x1005, 0, 0x4000_0080, 4), &[abort::RANGE]);
    Na(NO_PRODUCER)
}

fn sync_03(h: &mut Harness) -> Outcome {
    for n in default_tpdos(h) {
        setup_tpdo(h, n, 10, None);
        let id = tpdo_id(h, n);
        h.nmt(nmt::START);
        h.clear();
        // 10 s at 100 ms on the virtual clock; 0.5 s at 5 ms in real time.
        let (count, period) = if h.is_virtual() { (100, 100) } else { (100, 5) };
        let mut tpdos = 0;
        for _ in 0..count {
            h.sync();
            tpdos += Harness::count(&h.wait_ms(period), id);
        }
        // A TPDO the last SYNCs caused may still be on its way when the loop ends (in real
        // time on a loaded machine): it counts, a further one could not have been caused.
        tpdos += Harness::count(&h.wait_ms(50), id);
        assert_eq!(tpdos, count / 10, "TPDOs per 10 SYNCs");
        h.nmt(nmt::PRE_OP);
    }
    Pass
}

fn sync_04(h: &mut Harness) -> Outcome {
    ok(h.write(0x1005, 0, 0x80, 4));
    aborts(h.write(0x1006, 0, 0, 4), &[abort::NO_OBJECT]);
    Pass
}

fn sync_05(h: &mut Harness) -> Outcome {
    aborts(h.write(0x1019, 0, 1, 1), &[abort::NO_OBJECT]);
    Na(NO_1019)
}
fn sync_06(_: &mut Harness) -> Outcome {
    Na(NO_PRODUCER)
}
fn sync_07(_: &mut Harness) -> Outcome {
    Na(NO_PRODUCER)
}
fn sync_08(_: &mut Harness) -> Outcome {
    Na(NO_PRODUCER)
}
fn sync_09(h: &mut Harness) -> Outcome {
    sync_05(h)
}
fn sync_10(h: &mut Harness) -> Outcome {
    sync_05(h)
}

// ---- 7. Node guarding ---------------------------------------------------------------------

fn grd_01(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        aborts(h.upload(0x100C, 0), &[abort::NO_OBJECT]);
        return Na(NO_GUARDING);
    }
    let eds = eds(h);
    for i in [0x100C, 0x100D] {
        check_default(h, eds.entry(i, 0).unwrap());
    }
    Pass
}

fn grd_02(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        assert_eq!(h.guard(), None, "TMI answered a guarding request");
        return Na(NO_GUARDING);
    }
    h.clear();
    h.rtr(HB, 1);
    let frames = h.wait_ms(50);
    assert_eq!(Harness::count(&frames, HB), 1);
    let f = frames
        .iter()
        .find(|(_, f)| f.std_id() == Some(HB))
        .unwrap()
        .1;
    assert_eq!(f.data(), [0x7F]);
    // socketcand has no RTR: a zero-length frame is the same request (D22).
    assert_eq!(h.guard_zero_length(), Some(0xFF));
    Pass
}

fn grd_03(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    for cs in [nmt::RESET_NODE, nmt::RESET_COMM] {
        let mut t = 0;
        for _ in 0..5 {
            assert_eq!(h.guard(), Some(0x7F | t));
            t ^= 0x80;
        }
        h.reset(cs);
    }
    assert_eq!(h.guard(), Some(0x7F));
    Pass
}

fn grd_04(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    h.clear();
    for n in (1..=0x7Fu16).filter(|&n| n != NODE) {
        h.rtr(0x700 + n, 1);
    }
    let frames = h.wait_ms(50);
    assert!(frames.is_empty(), "answers on foreign IDs: {frames:?}");
    assert_eq!(h.guard(), Some(0x7F));
    Pass
}

fn grd_05(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    ok(h.write(0x100C, 0, 500, 2));
    ok(h.write(0x100D, 0, 3, 1));
    assert_eq!(ok(h.read(0x100C, 0)), 500);
    assert_eq!(ok(h.read(0x100D, 0)), 3);
    Pass
}

/// Life guarding: EMCY 0x8130 after guard time × factor without a request, PDOs stop, and
/// resume (EMCY 0x0000) with the next request. 1029 is not implemented: the reaction is the
/// products' (SPEC D11), not a state change.
fn life_guarding(h: &mut Harness) {
    ok(h.write(0x100C, 0, 100, 2));
    ok(h.write(0x100D, 0, 3, 1));
    for _ in 0..5 {
        assert!(h.guard().is_some());
        h.wait_ms(80);
    }
    h.clear();
    let frames = h.wait_ms(400);
    let emcy: Vec<_> = frames
        .iter()
        .filter(|(_, f)| f.std_id() == Some(EMCY))
        .collect();
    assert_eq!(emcy.len(), 1, "one life-guard EMCY");
    assert_eq!(&emcy[0].1.data()[..2], &[0x30, 0x81]);
    assert!(h.guard().is_some());
    let (_, f) = h
        .wait_for(100, |f| f.std_id() == Some(EMCY))
        .expect("EMCY 0000");
    assert_eq!(&f.data()[..2], &[0, 0]);
}

fn grd_06(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    life_guarding(h);
    Pass
}

// ---- 8. Heartbeat -------------------------------------------------------------------------

fn hb_01(h: &mut Harness) -> Outcome {
    ok(h.write(0x1017, 0, 0, 2));
    Pass
}

fn hb_02(h: &mut Harness) -> Outcome {
    ok(h.write(0x1017, 0, 100, 2));
    h.clear();
    let win = window_ms(h, 10_000, 1000);
    let frames = h.wait_ms(win);
    within(
        Harness::count(&frames, HB),
        (win / 100) as usize,
        "heartbeats at 100 ms",
    );
    assert!(frames
        .iter()
        .filter(|(_, f)| f.std_id() == Some(HB))
        .all(|(_, f)| f.data() == [0x7F]));
    Pass
}

fn hb_03(h: &mut Harness) -> Outcome {
    ok(h.write(0x1017, 0, 100, 2));
    h.wait_ms(300);
    ok(h.write(0x1017, 0, 0, 2));
    h.clear();
    assert_eq!(Harness::count(&h.wait_ms(2000), HB), 0);
    Pass
}

fn hb_04(h: &mut Harness) -> Outcome {
    aborts(h.upload(0x1016, 1), &[abort::NO_OBJECT]);
    Na(NO_CONSUMER)
}
fn hb_05(h: &mut Harness) -> Outcome {
    hb_04(h)
}
fn hb_06(h: &mut Harness) -> Outcome {
    hb_04(h)
}
fn hb_07(h: &mut Harness) -> Outcome {
    hb_04(h)
}

// ---- 9. Heartbeat vs guarding ---------------------------------------------------------------

fn hbg_01(h: &mut Harness) -> Outcome {
    ok(h.read(0x1017, 0));
    if guarding(h) {
        ok(h.read(0x100C, 0));
        ok(h.read(0x100D, 0));
    }
    Pass
}

fn hbg_02(h: &mut Harness) -> Outcome {
    hb_03(h)
}

fn hbg_03(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    ok(h.write(0x1017, 0, 0, 2));
    assert_eq!(h.guard(), Some(0x7F));
    assert_eq!(h.guard(), Some(0xFF));
    assert_eq!(h.guard(), Some(0x7F));
    Pass
}

fn hbg_04(h: &mut Harness) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    ok(h.write(0x100C, 0, 0, 2));
    ok(h.write(0x100D, 0, 0, 1));
    ok(h.write(0x1017, 0, 200, 2));
    h.clear();
    within(
        Harness::count(&h.wait_ms(4000), HB),
        20,
        "heartbeats at 200 ms",
    );
    Pass
}

/// Heartbeat at 200 ms, guarding `gt` × 3, RTRs every 50 ms when `rtrs`: the heartbeat keeps
/// its period and no life-guard EMCY comes.
fn hbg_mixed(h: &mut Harness, gt: u16, rtrs: bool) -> Outcome {
    if !guarding(h) {
        return Na(NO_GUARDING);
    }
    ok(h.write(0x100C, 0, u32::from(gt), 2));
    ok(h.write(0x100D, 0, if gt == 0 { 0 } else { 3 }, 1));
    ok(h.write(0x1017, 0, 200, 2));
    h.clear();
    let mut hb = Vec::new();
    for _ in 0..80 {
        if rtrs {
            h.rtr(HB, 1);
        }
        hb.extend(h.wait_ms(50));
    }
    let beats: Vec<u64> = hb
        .iter()
        .filter(|(_, f)| f.std_id() == Some(HB) && f.dlc() == 1 && f.data()[0] & 0x80 == 0)
        .map(|(t, _)| *t)
        .collect();
    // Guarding replies (state | toggle) and heartbeats share the COB-ID; heartbeats are the
    // ones on the 200 ms grid.
    let on_grid = beats
        .windows(2)
        .filter(|w| (w[1] - w[0]) % 200_000 == 0)
        .count();
    assert!(on_grid >= 18, "heartbeat disturbed: {on_grid} periods");
    assert_eq!(
        Harness::count(&hb, EMCY),
        0,
        "life-guard event under heartbeat"
    );
    Pass
}

fn hbg_05(h: &mut Harness) -> Outcome {
    hbg_mixed(h, 0, true)
}
fn hbg_06(h: &mut Harness) -> Outcome {
    hbg_mixed(h, 100, false)
}
fn hbg_07(h: &mut Harness) -> Outcome {
    hbg_mixed(h, 100, true)
}

// ---- 10. Other: store / restore, restricted IDs ---------------------------------------------

/// The catalogue's changed objects that exist on this device (1006 does not): (index, value,
/// size).
const CHANGED: &[(u16, u32, usize)] = &[(0x1005, 0x200, 4), (0x1015, 1000, 2), (0x1017, 20000, 2)];

fn change_objects(h: &mut Harness) {
    aborts(h.write(0x1006, 0, 5000, 4), &[abort::NO_OBJECT]);
    for &(i, v, s) in CHANGED {
        ok(h.write(i, 0, v, s));
    }
}

/// After a reset: stored objects keep the changed value, the others are back to default
/// (the TMI stores only what its manual's storage table lists).
fn check_changed(h: &mut Harness, stored: bool) {
    let defaults = [(0x1005u16, 0x80u32), (0x1015, 0), (0x1017, 0)];
    for (&(i, v, _), &(_, d)) in CHANGED.iter().zip(&defaults) {
        let keeps = stored && group(h, i, 0) != Some(Group::Volatile);
        let want = if keeps { v } else { d };
        assert_eq!(ok(h.read(i, 0)), want, "{i:04X} after reset");
    }
}

fn has_sub(h: &Harness, index: u16, sub: u8) -> bool {
    h.model()
        .entries
        .iter()
        .any(|e| e.index == index && e.sub == sub)
}

const SUB1_ONLY: &str = "1010 / 1011 have sub 1 only (TH / E-Series manuals)";

fn wrong_signature(h: &mut Harness, index: u16, sub: u8) -> Outcome {
    if !has_sub(h, index, sub) {
        return Na(SUB1_ONLY);
    }
    assert_eq!(ok(h.read(index, sub)), 1, "saves on command only");
    change_objects(h);
    aborts(h.write(index, sub, WRONG, 4), &[abort::CANNOT_STORE]);
    Pass
}

fn store_and_reset(h: &mut Harness, sub: u8) -> Outcome {
    if !has_sub(h, 0x1010, sub) {
        return Na(SUB1_ONLY);
    }
    change_objects(h);
    ok(h.write(0x1010, sub, SAVE, 4));
    h.wait_ms(500);
    h.reset(nmt::RESET_NODE);
    check_changed(h, true);
    // And across a power cycle.
    h.power_cycle();
    check_changed(h, true);
    Pass
}

fn restore_and_reset(h: &mut Harness, sub: u8) -> Outcome {
    if !has_sub(h, 0x1011, sub) {
        return Na(SUB1_ONLY);
    }
    change_objects(h);
    ok(h.write(0x1010, sub, SAVE, 4));
    ok(h.write(0x1011, sub, LOAD, 4));
    h.wait_ms(500);
    h.reset(nmt::RESET_NODE);
    check_changed(h, false);
    Pass
}

fn oth_01(h: &mut Harness) -> Outcome {
    wrong_signature(h, 0x1010, 1)
}
fn oth_02(h: &mut Harness) -> Outcome {
    store_and_reset(h, 1)
}
fn oth_03(h: &mut Harness) -> Outcome {
    wrong_signature(h, 0x1011, 1)
}
fn oth_04(h: &mut Harness) -> Outcome {
    restore_and_reset(h, 1)
}
fn oth_05(h: &mut Harness) -> Outcome {
    wrong_signature(h, 0x1010, 2)
}
fn oth_06(h: &mut Harness) -> Outcome {
    store_and_reset(h, 2)
}
fn oth_07(h: &mut Harness) -> Outcome {
    wrong_signature(h, 0x1011, 2)
}
fn oth_08(h: &mut Harness) -> Outcome {
    restore_and_reset(h, 2)
}
fn oth_09(h: &mut Harness) -> Outcome {
    aborts(h.upload(0x1020, 1), &[abort::NO_OBJECT]);
    Na("0x1020 verify configuration not implemented")
}

/// The restricted CAN-IDs of CiA 301 (797 values).
pub fn restricted_ids() -> Vec<u32> {
    [
        (0x000, 0x07F),
        (0x101, 0x180),
        (0x581, 0x5FF),
        (0x601, 0x67F),
        (0x6E0, 0x6FF),
        (0x701, 0x7FF),
    ]
    .iter()
    .flat_map(|&(a, b)| a..=b)
    .collect()
}

fn oth_10(h: &mut Harness) -> Outcome {
    let ids = restricted_ids();
    assert_eq!(ids.len(), 797);
    // As the CTT writes them (objects valid), then with the object first made invalid, so the
    // restricted-ID rule itself is what refuses (not "no CAN-ID change while valid").
    for invalid_first in [false, true] {
        for (i, s) in [(0x1005u16, 0u8), (0x1014, 0), (0x1800, 1)] {
            let cur = ok(h.read(i, s));
            if invalid_first && i != 0x1005 {
                ok(h.write(i, s, cur | 0x8000_0000, 4));
            }
            for &id in &ids {
                let r = h.write(i, s, id, 4);
                assert_eq!(r, Err(abort::RANGE), "{i:04X}:{s:02X} = {id:03X}");
            }
            ok(h.write(i, s, cur, 4));
        }
    }
    assert_eq!(ok(h.read(0x1005, 0)), 0x80);
    Pass
}

// ---- 11. NMT states -----------------------------------------------------------------------

/// A small deterministic generator for STATE-01's random downloads.
struct XorShift(u64);
impl XorShift {
    fn next(&mut self) -> u32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 16) as u32
    }
}

fn state_01(h: &mut Harness) -> Outcome {
    h.reset(nmt::RESET_NODE);
    ok(h.write(0x1017, 0, 500, 2));
    expect_state(h, 0x7F);
    let eds = eds(h);
    let mut rng = XorShift(0x2545_F491_4F6C_DD1D);
    for e in eds
        .entries
        .iter()
        .filter(|e| e.writable() && e.index < 0x2000)
    {
        if matches!(e.index, 0x1010 | 0x1011) {
            continue;
        }
        let Some(size) = e.size() else { continue };
        // Aborts are tolerated: only what lands matters for the check after the reset.
        let _ = h.write(e.index, e.sub, rng.next(), size);
    }
    h.reset(nmt::RESET_NODE);
    defaults(h, 0x1000, 0xFFFF)
}

fn state_02(h: &mut Harness) -> Outcome {
    h.reset(nmt::RESET_NODE);
    ok(h.write(0x1017, 0, 500, 2));
    expect_state(h, 0x7F);
    // The SYNC-producer step is n.a.: bit 30 refused, 1006 absent.
    aborts(h.write(0x1005, 0, 0x4000_0080, 4), &[abort::RANGE]);
    aborts(h.write(0x1006, 0, 6000, 4), &[abort::NO_OBJECT]);
    for n in default_tpdos(h) {
        aborts(h.write(0x1800 + n, 2, 253, 1), &[abort::RANGE]);
        setup_tpdo(h, n, 254, Some(1000));
        let id = tpdo_id(h, n);
        h.clear();
        assert_eq!(Harness::count(&h.wait_ms(2500), id), 0, "TPDO in pre-op");
    }
    Pass
}

fn state_03(h: &mut Harness) -> Outcome {
    h.reset(nmt::RESET_NODE);
    ok(h.write(0x1017, 0, 500, 2));
    h.nmt(nmt::START);
    expect_state(h, 0x05);
    ok(h.read(0x1000, 0));
    for n in default_tpdos(h) {
        h.nmt(nmt::PRE_OP);
        setup_tpdo(h, n, 254, Some(1000));
        let id = tpdo_id(h, n);
        h.nmt(nmt::START);
        assert!(
            h.wait_for(1100, |f| f.std_id() == Some(id)).is_some(),
            "TPDO in op"
        );
    }
    if guarding(h) {
        life_guarding(h);
    }
    Pass
}

fn state_04(h: &mut Harness) -> Outcome {
    h.reset(nmt::RESET_NODE);
    ok(h.write(0x1017, 0, 500, 2));
    for n in default_tpdos(h) {
        setup_tpdo(h, n, 254, Some(1000));
    }
    h.nmt(nmt::STOP);
    // No SDO in stopped: the client times out and aborts.
    aborts(h.upload(0x1000, 0), &[abort::TIMEOUT]);
    expect_state(h, 0x04);
    h.clear();
    let frames = h.wait_ms(2500);
    assert!(
        frames.iter().all(|(_, f)| f.std_id() == Some(HB)),
        "only error control in stopped: {frames:?}"
    );
    Pass
}

// ---- 12. NMT transitions ------------------------------------------------------------------

fn trans_01(h: &mut Harness) -> Outcome {
    h.reset(nmt::RESET_NODE);
    ok(h.write(0x1017, 0, 500, 2));
    expect_state(h, 0x7F);
    h.nmt(nmt::START);
    expect_state(h, 0x05);
    h.reset(nmt::RESET_COMM);
    // Heartbeat is off again after the reset (1017 default 0): re-enable, as the CTT does.
    assert_eq!(ok(h.read(0x1017, 0)), 0);
    ok(h.write(0x1017, 0, 500, 2));
    expect_state(h, 0x7F);
    Pass
}

fn transitions(h: &mut Harness, seq: &[(u8, u8)]) -> Outcome {
    h.reset(nmt::RESET_NODE);
    ok(h.write(0x1017, 0, 500, 2));
    expect_state(h, 0x7F);
    for &(cs, state) in seq {
        h.nmt(cs);
        expect_state(h, state);
    }
    Pass
}

fn trans_02(h: &mut Harness) -> Outcome {
    transitions(
        h,
        &[
            (nmt::PRE_OP, 0x7F),
            (nmt::START, 0x05),
            (nmt::PRE_OP, 0x7F),
            (nmt::STOP, 0x04),
            (nmt::PRE_OP, 0x7F),
        ],
    )
}
fn trans_03(h: &mut Harness) -> Outcome {
    transitions(
        h,
        &[
            (nmt::PRE_OP, 0x7F),
            (nmt::START, 0x05),
            (nmt::STOP, 0x04),
            (nmt::START, 0x05),
        ],
    )
}
fn trans_04(h: &mut Harness) -> Outcome {
    transitions(
        h,
        &[
            (nmt::PRE_OP, 0x7F),
            (nmt::STOP, 0x04),
            (nmt::START, 0x05),
            (nmt::STOP, 0x04),
        ],
    )
}

// ---- the catalogue ------------------------------------------------------------------------

macro_rules! cases {
    ($( $id:literal $f:ident $title:literal $note:literal ;)*) => {
        /// Every case of the catalogue, in catalogue order.
        pub const CASES: &[Case] = &[ $( Case { id: $id, title: $title, note: $note, run: $f }, )* ];
    };
}

cases! {
    "EDS-01" eds_01 "EDS static check" "CANchkEDS-equivalent checks in the harness";
    "SDO-01" sdo_01 "expedited read of device type" "";
    "SDO-02" sdo_02 "read / write-back of 1017" "";
    "SDO-03" sdo_03 "write to read-only" "";
    "SDO-04" sdo_04 "read write-only" "";
    "SDO-05" sdo_05 "non-existent sub-index" "";
    "SDO-06" sdo_06 "non-existent object" "";
    "SDO-07" sdo_07 "invalid command specifier" "the abort echoes 1000:00";
    "SDO-08" sdo_08 "too many data bytes" "";
    "SDO-09" sdo_09 "too few data bytes" "";
    "SDO-10" sdo_10 "value above maximum" "";
    "SDO-11" sdo_11 "value below minimum" "";
    "SDO-12" sdo_12 "SDO COB-IDs 1200:01/02" "";
    "SDO-13" sdo_13 "upload of a 4-byte object" "";
    "SDO-14" sdo_14 "segmented write of guard time" "";
    "SDO-15" sdo_15 "segmented write of heartbeat time" "TMI: refusal 05040001";
    "SDO-16" sdo_16 "segmented read > 4 bytes" "1008 is the manual's name (≤ 4 chars), so the server answers expedited";
    "SDO-17" sdo_17 "wrong toggle" "toggle checked on a segmented download (1008 ≤ 4 chars); TMI: refusal 05040001";
    "SDO-18" sdo_18 "segmented read again" "as SDO-16";
    "SDO-19" sdo_19 "block upload, no CRC" "TMI: refusal 05040001";
    "SDO-20" sdo_20 "block write of guard time, no CRC" "";
    "SDO-21" sdo_21 "block download, no CRC" "TMI: refusal 05040001";
    "SDO-22" sdo_22 "block upload of 1008" "1008 ≤ 4 chars; TMI: refusal 05040001";
    "SDO-23" sdo_23 "block upload with CRC" "TMI: refusal 05040001";
    "SDO-24" sdo_24 "block write of guard time with CRC" "";
    "SDO-25" sdo_25 "block download with CRC" "TMI: refusal 05040001";
    "SDO-26" sdo_26 "illegal block size" "";
    "SDO-27" sdo_27 "illegal ack sequence" "answers 05040003; TMI: refusal 05040001";
    "SDO-28" sdo_28 "scan for extra SDO servers" "";
    "SDO-29" sdo_29 "extra SDO servers across reset comm" "";
    "SDO-30" sdo_30 "SDO client objects" "";
    "PDO-01" pdo_01 "RPDO scan" "";
    "PDO-02" pdo_02 "TPDO scan" "";
    "PDO-03" pdo_03 "TPDO by RTR, operational" "";
    "PDO-04" pdo_04 "event-driven TPDO, operational" "";
    "PDO-05" pdo_05 "event timer, operational" "";
    "PDO-06" pdo_06 "synchronous cyclic, type 1" "";
    "PDO-07" pdo_07 "synchronous acyclic, type 0" "the magnet moves between SYNCs (sensor hook)";
    "PDO-08" pdo_08 "cyclic with SYNC start value" "";
    "PDO-09" pdo_09 "RTR in stopped" "";
    "PDO-10" pdo_10 "event-driven, stopped" "";
    "PDO-11" pdo_11 "event timer, stopped" "";
    "PDO-12" pdo_12 "type 1, stopped" "";
    "PDO-13" pdo_13 "type 0, stopped" "";
    "PDO-14" pdo_14 "start value, stopped" "";
    "PDO-15" pdo_15 "RTR, pre-operational" "";
    "PDO-16" pdo_16 "event-driven, pre-operational" "";
    "PDO-17" pdo_17 "event timer, pre-operational" "";
    "PDO-18" pdo_18 "type 1, pre-operational" "";
    "PDO-19" pdo_19 "type 0, pre-operational" "";
    "PDO-20" pdo_20 "start value, pre-operational" "";
    "PDO-21" pdo_21 "default mapping vs EDS" "";
    "PDO-22" pdo_22 "legal re-mapping by procedure" "";
    "PDO-23" pdo_23 "mapping write without the procedure" "";
    "PDO-24" pdo_24 "mapping write on a valid PDO" "manual wins: sub 0 = 0 on a valid PDO is accepted (TH/E Example 5); entry writes with sub 0 ≠ 0 abort 06010000";
    "PDO-25" pdo_25 "too many entries" "TMI: 5 entries, sub 0 = 6; 6300:01 for 1001:00 (not mappable, 002 §1.2.5)";
    "PDO-26" pdo_26 "entries too long" "6020:01 (32 bit); TMI: 5 entries";
    "PDO-27" pdo_27 "map an output into an RPDO" "";
    "PDO-28" pdo_28 "map an input into an RPDO" "";
    "PDO-29" pdo_29 "map a non-mappable object into an RPDO" "";
    "PDO-30" pdo_30 "map an input into a TPDO" "manual wins: TMI maps 6300:01, 1001:00 aborts 06040041 (002 §1.2.5)";
    "PDO-31" pdo_31 "map an output into a TPDO" "";
    "PDO-32" pdo_32 "map a non-mappable object into a TPDO" "";
    "PDO-33" pdo_33 "dummy mapping" "";
    "OD-01" od_01 "access by access type, whole OD" "mapping entries are covered by PDO-22…26";
    "OD-02" od_02 "value vs EDS default" "live values carry no DefaultValue";
    "OD-03" od_03 "writes to ro objects" "";
    "OD-04" od_04 "reads of wo objects" "";
    "OD-05" od_05 "sub-index FFh" "optional: answered 06090011";
    "OD-06" od_06 "limit check" "";
    "OD-07" od_07 "access by type, 2000h–9FFFh" "";
    "OD-08" od_08 "default check, 2000h–9FFFh" "";
    "OD-09" od_09 "read + write-back, 2000h–9FFFh" "";
    "EMCY-01" emcy_01 "EMCY COB-ID" "";
    "EMCY-02" emcy_02 "error register" "";
    "EMCY-03" emcy_03 "empty error history" "";
    "EMCY-04" emcy_04 "forced EMCY" "no RPDO: SYNC with DLC 2 gives 8240h (TH/E); TMI: transducer fault hook (5000h)";
    "EMCY-05" emcy_05 "error register after EMCY" "";
    "EMCY-06" emcy_06 "history matches EMCY" "";
    "SYNC-01" sync_01 "default SYNC COB-ID" "";
    "SYNC-02" sync_02 "DUT as SYNC producer" "bit 30 refused with 06090030";
    "SYNC-03" sync_03 "TPDO every 10th SYNC" "";
    "SYNC-04" sync_04 "consumer set-up" "1006 absent (06020000)";
    "SYNC-05" sync_05 "illegal counter overflow" "";
    "SYNC-06" sync_06 "producer without counter" "";
    "SYNC-07" sync_07 "producer with counter" "";
    "SYNC-08" sync_08 "producer config survives save and reset" "";
    "SYNC-09" sync_09 "counter locked while period ≠ 0" "";
    "SYNC-10" sync_10 "store SYNC settings" "";
    "GRD-01" grd_01 "guard objects present" "";
    "GRD-02" grd_02 "guarding reply" "";
    "GRD-03" grd_03 "toggle bit" "";
    "GRD-04" grd_04 "ID range" "";
    "GRD-05" grd_05 "write guard parameters" "";
    "GRD-06" grd_06 "life guarding" "1029 not implemented: EMCY 8130h and TPDOs stop (SPEC D11)";
    "HB-01" hb_01 "heartbeat time writable" "";
    "HB-02" hb_02 "heartbeat period" "";
    "HB-03" hb_03 "heartbeat off" "";
    "HB-04" hb_04 "duplicate consumer entry" "";
    "HB-05" hb_05 "consumer, producer faster" "";
    "HB-06" hb_06 "consumer, producer slower" "";
    "HB-07" hb_07 "consumer timeout in operational" "";
    "HBG-01" hbg_01 "objects present" "";
    "HBG-02" hbg_02 "heartbeat off" "";
    "HBG-03" hbg_03 "guarding with heartbeat off" "";
    "HBG-04" hbg_04 "guarding off, heartbeat on" "";
    "HBG-05" hbg_05 "heartbeat on plus RTRs" "guarding replies continue (D11); heartbeat undisturbed";
    "HBG-06" hbg_06 "both configured" "";
    "HBG-07" hbg_07 "both configured plus RTRs" "guarding replies continue (D11); heartbeat undisturbed";
    "OTH-01" oth_01 "wrong signature on 1010:01" "";
    "OTH-02" oth_02 "save all" "1006 absent; TMI keeps only what its storage table lists (1017)";
    "OTH-03" oth_03 "wrong signature on 1011:01" "";
    "OTH-04" oth_04 "restore all" "";
    "OTH-05" oth_05 "wrong signature on 1010:02" "";
    "OTH-06" oth_06 "save comm params" "";
    "OTH-07" oth_07 "wrong signature on 1011:02" "";
    "OTH-08" oth_08 "restore comm params" "";
    "OTH-09" oth_09 "verify configuration" "";
    "OTH-10" oth_10 "restricted CAN-IDs" "1005, 1014, 1800:01 (1012 and 1400 absent)";
    "STATE-01" state_01 "boot-up and defaults" "";
    "STATE-02" state_02 "pre-operational" "SYNC-producer step n.a. (refused)";
    "STATE-03" state_03 "operational" "life guarding without 1029 (D11); TMI: no guarding";
    "STATE-04" state_04 "stopped" "";
    "TRANS-01" trans_01 "reset node / reset comm" "";
    "TRANS-02" trans_02 "enter pre-operational" "";
    "TRANS-03" trans_03 "start remote node" "";
    "TRANS-04" trans_04 "stop remote node" "";
}
