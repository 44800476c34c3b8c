//! The EDS / DCF device: the files canpos exports for its sensors and a hand-written one build
//! the model they describe; every malformed file is an error with its line; the built node
//! serves values, limits, PDOs and storage.

use super::*;
use canpos_models as models;
use canpos_stack::od::{resolve_default, ParamSource};
use canpos_stack::storage::RamStorage;
use canpos_stack::{Frame, Instant, Node};
use canpos_stack::{SIG_LOAD, SIG_SAVE};

const IO: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../examples/io-device.eds"
));

const NONE: Overrides = Overrides {
    node_id: None,
    bitrate_kbps: None,
    serial: None,
};

fn eds(text: &str) -> Result<EdsDevice, EdsError> {
    build(text, "x.eds", FileKind::Eds, &NONE)
}

fn find(m: &Model, index: u16, sub: u8) -> &Entry {
    m.entries
        .iter()
        .find(|e| e.index == index && e.sub == sub)
        .unwrap_or_else(|| panic!("no {index:04X}/{sub}"))
}

struct Unit<C: 'static, X: 'static>(&'static canpos_stack::model::Model<C, X>, C);
impl<C, X> ParamSource for Unit<C, X> {
    fn param(&self, p: Param) -> u32 {
        (self.0.param)(&self.1, p)
    }
}

#[test]
fn the_exported_eds_of_every_model_rebuilds_its_table() {
    for m in models::all() {
        let mut text = String::new();
        canpos_stack::eds::write_eds(
            &mut text,
            m,
            &m.default_config,
            &canpos_stack::eds::EdsInfo::default(),
        )
        .unwrap();
        let d = eds(&text).unwrap_or_else(|e| panic!("{}: {e}", m.name));
        assert!(d.warnings.is_empty(), "{}: {:?}", m.name, d.warnings);
        let b = d.model;
        assert_eq!(b.entries.len(), m.entries.len(), "{}", m.name);
        assert_eq!(b.features.tpdos, m.features.tpdos);
        let mut rates = m.features.bitrates.to_vec();
        rates.sort_unstable();
        assert_eq!(b.features.bitrates, rates);
        assert_eq!(b.vendor, m.vendor);
        let (orig, built) = (Unit(m, m.default_config), Unit(b, b.default_config));
        for (o, e) in m.entries.iter().zip(b.entries) {
            let at = format!("{} {:04X}/{}", m.name, o.index, o.sub);
            assert_eq!(o.key(), e.key(), "{at}");
            assert_eq!(o.ty, e.ty, "{at}");
            assert_eq!(o.pdo, e.pdo, "{at}");
            assert_eq!(o.name, e.name, "{at}");
            // Mappable objects are exported ro (EDS rule), all else as the table says.
            if !(o.pdo && o.access == Access::Rw) {
                assert_eq!(o.access, e.access, "{at}");
            }
            if o.hook.app_number().is_none()
                && !matches!(o.hook, Hook::PendingNodeId | Hook::PendingBitRate)
            {
                assert_eq!(o.hook, e.hook, "{at}");
            }
            if let DefaultValue::Str(s) = o.default {
                assert_eq!(e.default, DefaultValue::Str(s), "{at}");
            } else if o.default != DefaultValue::Live {
                assert_eq!(
                    resolve_default(o, &orig, 127),
                    resolve_default(e, &built, 127),
                    "{at}"
                );
            }
            if let Range::MinMax(..) = o.range {
                assert_eq!(o.limits(), e.limits(), "{at}");
            }
        }
        assert_ne!(b.features.tag, m.features.tag);
        assert_eq!(b.features.tag & 0xC0, TAG_BASE);
    }
}

#[test]
fn the_hand_written_io_device() {
    let d = eds(IO).unwrap();
    let m = d.model;
    // Nothing left out: its RPDO is served, with the RPDO service's rules.
    assert_eq!(d.warnings, Vec::<String>::new());
    assert_eq!(m.features.tpdos, 2);
    assert_eq!(m.features.rpdos, 1);
    assert_eq!(find(m, 0x1400, 1).hook, Hook::RpdoComm);
    assert_eq!(find(m, 0x1400, 5).hook, Hook::RpdoComm);
    assert_eq!(find(m, 0x1600, 1).hook, Hook::RpdoMap);
    assert_eq!(find(m, 0x1400, 1).default, DefaultValue::NodeId(0x200));
    assert_eq!(find(m, 0x1600, 1).group, Group::Comm);
    assert_eq!(m.features.bitrates, &[125, 250, 500, 1000]);
    assert_eq!(m.features.lss_bit_timing, &[4, 3, 2, 0]);
    assert!(m.features.lss_fastscan && m.features.node_guarding);
    assert_eq!((d.vendor_id, d.product_code), (0xCA7, 0x1234));
    assert_eq!(
        (d.cfg.node_id, d.cfg.bitrate_kbps, d.cfg.serial),
        (127, 125, 0x42)
    );
    assert!(m.entries.windows(2).all(|w| w[0].key() < w[1].key()));
    // Hooks by standard index, groups by access and index.
    assert_eq!(find(m, 0x1017, 0).hook, Hook::Heartbeat);
    assert_eq!(find(m, 0x1017, 0).group, Group::Comm);
    assert_eq!(find(m, 0x1010, 2).hook, Hook::StoreParameters);
    assert_eq!(find(m, 0x1010, 2).group, Group::Volatile);
    assert_eq!(find(m, 0x1011, 3).hook, Hook::RestoreDefaults);
    assert_eq!(find(m, 0x100C, 0).hook, Hook::Guarding);
    assert_eq!(find(m, 0x1003, 0).hook, Hook::ErrorHistory);
    assert_eq!(*find(m, 0x1003, 0).range, Range::MinMax(0, 0));
    assert_eq!(find(m, 0x1800, 1).hook, Hook::TpdoComm);
    assert_eq!(find(m, 0x1800, 0).hook, Hook::None);
    assert_eq!(find(m, 0x1A01, 0).hook, Hook::TpdoMap);
    assert_eq!(find(m, 0x1014, 0).default, DefaultValue::NodeId(0x80));
    assert_eq!(
        find(m, 0x1801, 1).default,
        DefaultValue::NodeId(0x8000_0280)
    );
    assert_eq!(find(m, 0x2101, 0).group, Group::App);
    assert_eq!(find(m, 0x2200, 0).group, Group::Volatile);
    assert_eq!(find(m, 0x2000, 0).group, Group::Volatile);
    // Values and limits in the type's terms.
    assert_eq!(
        find(m, 0x2001, 1).default,
        DefaultValue::Const(-1234i16 as u16 as u32)
    );
    assert_eq!(
        find(m, 0x2102, 0).default,
        DefaultValue::Const(-500i32 as u32)
    );
    assert_eq!(find(m, 0x2102, 0).limits(), Some((-100_000, 100_000)));
    assert_eq!(find(m, 0x2103, 0).limits(), Some((-10, 10)));
    assert_eq!(find(m, 0x2101, 0).limits(), Some((1, 1000)));
    assert_eq!(find(m, 0x2300, 0).default, DefaultValue::Str(&"v1.2-io"));
    assert_eq!(find(m, 0x1008, 0).access, Access::Const);
    assert_eq!(find(m, 0x2200, 0).access, Access::Wo);
    assert!(find(m, 0x2000, 0).pdo && !find(m, 0x2100, 0).pdo);
}

/// examples/io-401.eds, the CiA 401 I/O module: it passes every check of the builder, with
/// nothing left out.
#[test]
fn the_cia401_io_module() {
    let text = include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../examples/io-401.eds"
    ));
    let d = eds(text).unwrap();
    assert!(d.warnings.is_empty(), "{:?}", d.warnings);
    let m = d.model;
    assert_eq!((m.features.tpdos, m.features.rpdos), (4, 4));
    // CiA 401's default RPDOs: digital outputs, then analogue outputs 1-4, 5-8, 9-12.
    for (n, first, count) in [
        (0u16, 0x6200_0108u32, 2u8),
        (1, 0x6411_0110, 4),
        (2, 0x6411_0510, 4),
        (3, 0x6411_0910, 4),
    ] {
        assert_eq!(
            find(m, 0x1600 + n, 0).default,
            DefaultValue::Const(count.into())
        );
        for k in 0..count {
            let want = first + (u32::from(k) << 8);
            assert_eq!(
                find(m, 0x1600 + n, k + 1).default,
                DefaultValue::Const(want)
            );
        }
        assert_eq!(
            find(m, 0x1400 + n, 1).default,
            DefaultValue::NodeId(0x200 + 0x100 * u32::from(n))
        );
    }
    assert_eq!((d.vendor_id, d.product_code), (0xCA7, 0x401));
    assert_eq!(find(m, 0x1000, 0).default, DefaultValue::Const(0x000F_0191));
    // CiA 401's default TPDOs: digital inputs, then analogue inputs 1-4, 5-8, 9-12.
    for (n, first, count) in [
        (0u16, 0x6000_0108u32, 2u8),
        (1, 0x6401_0110, 4),
        (2, 0x6401_0510, 4),
        (3, 0x6401_0910, 4),
    ] {
        assert_eq!(
            find(m, 0x1A00 + n, 0).default,
            DefaultValue::Const(count.into())
        );
        for k in 0..count {
            let want = first + (u32::from(k) << 8);
            assert_eq!(
                find(m, 0x1A00 + n, k + 1).default,
                DefaultValue::Const(want)
            );
        }
        assert_eq!(
            find(m, 0x1800 + n, 1).default,
            DefaultValue::NodeId(0x180 + 0x100 * u32::from(n))
        );
        assert_eq!(find(m, 0x1800 + n, 2).default, DefaultValue::Const(255));
    }
    for (i, s, ty, access) in [
        (0x6000, 2, DataType::Unsigned8, Access::Ro),
        (0x6200, 2, DataType::Unsigned8, Access::Rw),
        (0x6401, 12, DataType::Integer16, Access::Ro),
        (0x6411, 12, DataType::Integer16, Access::Rw),
        (0x1016, 4, DataType::Unsigned32, Access::Rw),
        (0x1029, 3, DataType::Unsigned8, Access::Rw),
    ] {
        let e = find(m, i, s);
        assert_eq!((e.ty, e.access), (ty, access), "{i:04X}/{s}");
    }
    assert!(find(m, 0x6401, 1).pdo && find(m, 0x6411, 1).pdo);
}

#[test]
fn overrides_and_state_file() {
    let o = Overrides {
        node_id: Some(5),
        bitrate_kbps: Some(500),
        serial: Some(77),
    };
    let d = build(IO, "x.eds", FileKind::Eds, &o).unwrap();
    assert_eq!(
        (d.cfg.node_id, d.cfg.bitrate_kbps, d.cfg.serial),
        (5, 500, 77)
    );
    assert_eq!(find(d.model, 0x1018, 4).default, DefaultValue::Const(77));
    assert_eq!(
        d.state_file(Path::new("/s")),
        Path::new("/s/eds-00000ca7-00001234-77.bin")
    );
    // Without ObjectType an object is a VAR, or a RECORD when it has a SubNumber.
    let implicit = IO.replace(
        "ObjectType=0x8\nSubNumber=3\n\n[2001sub0]",
        "SubNumber=3\n\n[2001sub0]",
    );
    let implicit2 = implicit.replace(
        "[2000]\nParameterName=Digital inputs\nObjectType=0x7\n",
        "[2000]\nParameterName=Digital inputs\n",
    );
    assert!(implicit != IO && implicit2 != implicit);
    let d2 = eds(&implicit2).unwrap();
    assert_eq!(find(d2.model, 0x2001, 2).default, DefaultValue::Const(2000));
    assert_eq!(find(d2.model, 0x2000, 0).default, DefaultValue::Const(0x5A));
    // Another identity, another tag.
    let other = eds(&IO.replace("0x00001234", "0x00001235")).unwrap();
    assert_ne!(other.model.features.tag, d.model.features.tag);
}

#[test]
fn a_dcf_brings_its_values_and_commissioning() {
    let dcf = IO
        .replace(
            "DefaultValue=10\nLowLimit=1",
            "DefaultValue=10\nParameterValue=250\nLowLimit=1",
        )
        .replace(
            "[DummyUsage]",
            "[DeviceComissioning]\nNodeID=0x21\nBaudrate=500\n\n[DummyUsage]",
        );
    let d = build(&dcf, "x.dcf", FileKind::Dcf, &NONE).unwrap();
    assert_eq!(find(d.model, 0x2101, 0).default, DefaultValue::Const(250));
    assert_eq!((d.cfg.node_id, d.cfg.bitrate_kbps), (0x21, 500));
    // The command line wins.
    let o = Overrides {
        node_id: Some(9),
        bitrate_kbps: Some(250),
        serial: None,
    };
    let d = build(&dcf, "x.dcf", FileKind::Dcf, &o).unwrap();
    assert_eq!((d.cfg.node_id, d.cfg.bitrate_kbps), (9, 250));
    // An EDS ignores both, and says so.
    let e = eds(&dcf).unwrap();
    assert_eq!(find(e.model, 0x2101, 0).default, DefaultValue::Const(10));
    assert_eq!((e.cfg.node_id, e.cfg.bitrate_kbps), (127, 125));
    assert!(e.warnings.iter().any(|w| w.contains("ParameterValue")));
    assert!(e.warnings.iter().any(|w| w.contains("DeviceComissioning")));
    // A ParameterValue outside the limits is an error too.
    let bad = dcf.replace("ParameterValue=250", "ParameterValue=1001");
    let err = build(&bad, "x.dcf", FileKind::Dcf, &NONE).unwrap_err();
    assert!(err.msg.contains("outside LowLimit"), "{err}");
    let bad = dcf.replace("NodeID=0x21", "NodeID=128");
    let err = build(&bad, "x.dcf", FileKind::Dcf, &NONE).unwrap_err();
    assert!(err.msg.contains("NodeID"), "{err}");
}

fn line_of(text: &str, needle: &str) -> usize {
    text.lines()
        .position(|l| l == needle)
        .unwrap_or_else(|| panic!("no line {needle}"))
        + 1
}

/// Replaces the line `from` (within the section `[sec]`) by `to`.
fn edit(sec: &str, from: &str, to: &str) -> String {
    let start = IO.find(&format!("\n[{sec}]\n")).expect(sec);
    let at = start + IO[start..].find(&format!("\n{from}\n")).expect(from);
    format!("{}\n{to}\n{}", &IO[..at], &IO[at + from.len() + 2..])
}

#[test]
fn malformed_files_name_the_line() {
    let sec_line = |name: &str| line_of(IO, &format!("[{name}]"));
    // (file text, expected line (0 = whole file), words in the message)
    let cases: Vec<(String, usize, &str)> = vec![
        (IO.replace("[DeviceInfo]", "[DevInfo]"), 0, "no [DeviceInfo]"),
        (
            IO.replace("[MandatoryObjects]", "[Mandatory]"),
            0,
            "no [MandatoryObjects]",
        ),
        (
            edit("2101", "DefaultValue=10", "DefaultValue=ten"),
            sec_line("2101") + 5,
            "not a number",
        ),
        (
            edit("2101", "DataType=0x0006", "DataType=0x0099"),
            sec_line("2101") + 3,
            "unknown DataType 0x0099",
        ),
        (
            edit("2101", "DataType=0x0006", "DataType=0x000F"),
            sec_line("2101") + 3,
            "DOMAIN",
        ),
        (
            edit("2101", "DataType=0x0006", "DataType=0x0008"),
            sec_line("2101") + 3,
            "not supported",
        ),
        (
            edit("2101", "AccessType=rw", "AccessType=readwrite"),
            sec_line("2101") + 4,
            "AccessType",
        ),
        (
            edit("2300", "AccessType=ro", "AccessType=rw"),
            sec_line("2300") + 4,
            "writable VISIBLE_STRING",
        ),
        (
            edit("2101", "DefaultValue=10", "DefaultValue=1001"),
            sec_line("2101") + 5,
            "outside LowLimit",
        ),
        (
            edit("2101", "HighLimit=1000", "HighLimit=0"),
            sec_line("2101") + 7,
            "below LowLimit",
        ),
        (
            edit("2000", "DefaultValue=0x5A", "DefaultValue=256"),
            sec_line("2000") + 5,
            "outside the range of Unsigned8",
        ),
        (
            edit("2103", "LowLimit=0xF6", "LowLimit=-129"),
            sec_line("2103") + 6,
            "outside the range",
        ),
        (
            edit("2001", "SubNumber=3", "SubNumber=4"),
            sec_line("2001") + 3,
            "SubNumber=4 but 0x2001 has 3",
        ),
        (
            IO.replace("[2001sub1]", "[2001sub01]\n[2001sub1]")
                .replace("[2001sub01]\n", "[2001sub01]\nParameterName=x\n"),
            sec_line("2001sub1") + 2,
            "again",
        ),
        (IO.replace("[2300]", "[2000]"), sec_line("2300"), "given twice"),
        (
            IO.replace("[1018sub4]", "[1019sub4]"),
            sec_line("1018sub4"),
            "no [1019] section",
        ),
        (
            edit("1017", "DataType=0x0006", "DataType=0x0007"),
            sec_line("1017") + 3,
            "must be Unsigned16",
        ),
        (
            edit("MandatoryObjects", "SupportedObjects=3", "SupportedObjects=4"),
            sec_line("MandatoryObjects") + 1,
            "SupportedObjects=4 but",
        ),
        (
            edit("ManufacturerObjects", "8=0x2300", "8=0x2400"),
            sec_line("ManufacturerObjects") + 9,
            "no [2400] section",
        ),
        (
            edit("1A00sub3", "DefaultValue=0x21020020", "DefaultValue=0x21000008"),
            sec_line("1A00sub3") + 5,
            "no PDOMapping=1",
        ),
        (
            edit("1A00sub3", "DefaultValue=0x21020020", "DefaultValue=0x21020010"),
            sec_line("1A00sub3") + 5,
            "with 16 bits",
        ),
        (
            edit("1A00sub3", "DefaultValue=0x21020020", "DefaultValue=0x29990020"),
            sec_line("1A00sub3") + 5,
            "does not exist",
        ),
        (
            edit("1A00sub0", "DefaultValue=3", "DefaultValue=5"),
            sec_line("1A00sub0") + 5,
            "no sub 5",
        ),
        (
            edit("1A00sub4", "DefaultValue=0", "DefaultValue=0x21020020")
                .replace("[1A00sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\nDataType=0x0005\nAccessType=rw\nDefaultValue=3", "[1A00sub0]\nParameterName=Number of mapped objects\nObjectType=0x7\nDataType=0x0005\nAccessType=rw\nDefaultValue=4"),
            sec_line("1A00sub0") + 5,
            "88 bits",
        ),
        (
            edit("1600sub1", "DefaultValue=0x21010010", "DefaultValue=0x20000008"),
            sec_line("1600sub1") + 5,
            "into an RPDO, which is not writable",
        ),
        (
            edit("1600sub1", "DefaultValue=0x21010010", "DefaultValue=0x00050010"),
            sec_line("1600sub1") + 5,
            "a dummy of 0x0005 has 8 bits, not 16",
        ),
        (
            IO.replace("[1600]", "[1602]")
                .replace("[1600sub", "[1602sub")
                .replace("11=0x1600", "11=0x1602"),
            sec_line("1400"),
            "RPDO 1 has no [1600] section",
        ),
        (
            IO.replace("[1801]", "[1804]")
                .replace("[1801sub", "[1804sub")
                .replace("13=0x1801", "13=0x1804"),
            sec_line("1801"),
            "at most 4 TPDOs",
        ),
        (
            edit("2100", "ObjectType=0x7", "ObjectType=0x2"),
            sec_line("2100") + 2,
            "ObjectType 0x2",
        ),
        (
            edit("2001", "SubNumber=3", "SubNumber=3\nCompactSubObj=2"),
            sec_line("2001") + 4,
            "CompactSubObj",
        ),
        (
            IO.replace("\nDataType=0x0007\nAccessType=ro\nDefaultValue=0x000F0191", "\nAccessType=ro\nDefaultValue=0x000F0191"),
            sec_line("1000"),
            "has no DataType",
        ),
        (
            IO.replace("[1001]", "[1002]").replace("2=0x1001", "2=0x1002"),
            sec_line("MandatoryObjects"),
            "0x1001 sub 0 is missing",
        ),
        (
            edit("2100", "PDOMapping=0", "PDOMapping=2"),
            sec_line("2100") + 6,
            "PDOMapping",
        ),
        (
            format!("x=1\n{IO}"),
            1,
            "before the first",
        ),
    ];
    for (text, line, words) in &cases {
        let e = eds(text).expect_err(words);
        assert!(e.msg.contains(words), "expected `{words}`, got: {e}");
        assert_eq!(e.line, *line, "{words}: {e}");
        assert!(e.to_string().starts_with("x.eds"), "{e}");
    }
}

#[test]
fn too_many_entries() {
    // 0x3000 with 254 sub-indices on top of the device's 52 entries.
    let mut text = IO.replace("8=0x2300", "8=0x2300\n9=0x3000").replace(
        "[ManufacturerObjects]\nSupportedObjects=8",
        "[ManufacturerObjects]\nSupportedObjects=9",
    );
    text.push_str("\n[3000]\nParameterName=Big\nObjectType=0x8\nSubNumber=255\n");
    for s in 0..255 {
        text.push_str(&format!(
            "[3000sub{s:X}]\nParameterName=b{s}\nDataType=0x0005\nAccessType=ro\n"
        ));
    }
    let e = eds(&text).unwrap_err();
    assert!(e.msg.contains("at most 256"), "{e}");
}

/// Every file one edit away from the valid one (a line dropped, or a value garbled) builds or
/// fails with an error naming a line of the file; none panics.
#[test]
fn no_edit_of_the_file_panics() {
    let lines: Vec<&str> = IO.lines().collect();
    let n = lines.len();
    let check = |text: String| match eds(&text) {
        Ok(_) => {}
        Err(e) => assert!(e.line <= text.lines().count(), "{e}"),
    };
    for i in 0..n {
        let mut v = lines.clone();
        v.remove(i);
        check(v.join("\n"));
        if let Some((k, _)) = lines[i].split_once('=') {
            for bad in ["", "0x", "-", "$NODEID+", "99999999999999999999"] {
                let mut v: Vec<String> = lines.iter().map(|s| s.to_string()).collect();
                v[i] = format!("{k}={bad}");
                check(v.join("\n"));
            }
        }
    }
    for cut in (0..IO.len()).step_by(97) {
        check(IO[..cut].to_string());
    }
}

// --- the built device on the bus -------------------------------------------------------------

const ID: u8 = 5;

fn node() -> Node<Plain, RamStorage> {
    let o = Overrides {
        node_id: Some(ID),
        ..NONE
    };
    let d = build(IO, "x.eds", FileKind::Eds, &o).unwrap();
    let mut n = Node::with_app(d.model, d.cfg, Plain, RamStorage::default());
    n.power_on(Instant::from_micros(0));
    while n.poll(Instant::from_micros(0)).is_some() {}
    n
}

/// One SDO request at `t`; the answer (the node holds a store's answer for 20 ms).
fn sdo(n: &mut Node<Plain, RamStorage>, t: &mut u64, req: [u8; 8]) -> [u8; 8] {
    n.handle_frame(
        &Frame::std8(0x600 + u16::from(ID), req),
        Instant::from_micros(*t),
    );
    for _ in 0..100 {
        while let Some(f) = n.poll(Instant::from_micros(*t)) {
            if f.std_id() == Some(0x580 + u16::from(ID)) {
                return *f.raw();
            }
        }
        *t += 1000;
    }
    panic!("no SDO answer");
}

fn download(n: &mut Node<Plain, RamStorage>, t: &mut u64, i: u16, s: u8, v: &[u8]) -> Option<u32> {
    let mut r = [0u8; 8];
    r[0] = 0x23 | ((4 - v.len() as u8) << 2);
    r[1..3].copy_from_slice(&i.to_le_bytes());
    r[3] = s;
    r[4..4 + v.len()].copy_from_slice(v);
    let a = sdo(n, t, r);
    (a[0] == 0x80).then(|| u32::from_le_bytes([a[4], a[5], a[6], a[7]]))
}

fn upload(n: &mut Node<Plain, RamStorage>, t: &mut u64, i: u16, s: u8) -> u32 {
    let i = i.to_le_bytes();
    let a = sdo(n, t, [0x40, i[0], i[1], s, 0, 0, 0, 0]);
    assert_eq!(a[0] & 0xF3, 0x43, "{a:02X?}");
    u32::from_le_bytes([a[4], a[5], a[6], a[7]])
}

#[test]
fn the_node_serves_values_limits_pdos_and_storage() {
    let mut n = node();
    let mut t = 1000;
    assert_eq!(upload(&mut n, &mut t, 0x1014, 0), 0x80 + u32::from(ID));
    assert_eq!(upload(&mut n, &mut t, 0x2001, 1) as u16 as i16, -1234);
    // Limits: too high, too low, and the type's own bounds.
    assert_eq!(
        download(&mut n, &mut t, 0x2101, 0, &1001u16.to_le_bytes()),
        Some(0x0609_0031)
    );
    assert_eq!(
        download(&mut n, &mut t, 0x2101, 0, &0u16.to_le_bytes()),
        Some(0x0609_0032)
    );
    assert_eq!(
        download(&mut n, &mut t, 0x2103, 0, &[(-11i8) as u8]),
        Some(0x0609_0032)
    );
    assert_eq!(download(&mut n, &mut t, 0x2103, 0, &[(-10i8) as u8]), None);
    assert_eq!(download(&mut n, &mut t, 0x2000, 0, &[1]), Some(0x0601_0002));
    assert_eq!(download(&mut n, &mut t, 0x2100, 0, &[2]), Some(0x0609_0030));
    assert_eq!(download(&mut n, &mut t, 0x2101, 0, &[1]), Some(0x0607_0013));
    // Write-only: no reads.
    let a = sdo(&mut n, &mut t, [0x40, 0x00, 0x22, 0, 0, 0, 0, 0]);
    assert_eq!(u32::from_le_bytes([a[4], a[5], a[6], a[7]]), 0x0601_0001);
    assert_eq!(
        download(&mut n, &mut t, 0x2200, 0, &7u16.to_le_bytes()),
        None
    );

    // TPDO1 at a 10 ms event timer carries 0x2000, 0x2001/1, 0x2102 once operational.
    assert_eq!(
        download(&mut n, &mut t, 0x2102, 0, &(-7i32).to_le_bytes()),
        None
    );
    assert_eq!(
        download(&mut n, &mut t, 0x1800, 5, &10u16.to_le_bytes()),
        None
    );
    n.handle_frame(
        &Frame::std_len(0, [1, ID, 0, 0, 0, 0, 0, 0], 2),
        Instant::from_micros(t),
    );
    let mut pdos = Vec::new();
    for _ in 0..30 {
        t += 1000;
        while let Some(f) = n.poll(Instant::from_micros(t)) {
            if f.std_id() == Some(0x180 + u16::from(ID)) {
                pdos.push(f.data().to_vec());
            }
        }
    }
    assert!((2..=4).contains(&pdos.len()), "{pdos:?}");
    let mut want = vec![0x5A];
    want.extend_from_slice(&(-1234i16).to_le_bytes());
    want.extend_from_slice(&(-7i32).to_le_bytes());
    assert_eq!(pdos[0], want);
    // Remapped (disabled first, as CiA 301 wants): a string is not mappable, 0x2101 is.
    let cob = 0x180 + u32::from(ID);
    assert_eq!(
        download(
            &mut n,
            &mut t,
            0x1800,
            1,
            &(cob | 0x8000_0000).to_le_bytes()
        ),
        None
    );
    assert_eq!(download(&mut n, &mut t, 0x1A00, 0, &[0]), None);
    let string = 0x2300_0008u32.to_le_bytes();
    assert_eq!(
        download(&mut n, &mut t, 0x1A00, 1, &string),
        Some(0x0604_0041)
    );
    assert_eq!(
        download(&mut n, &mut t, 0x1A00, 1, &0x2101_0010u32.to_le_bytes()),
        None
    );
    assert_eq!(download(&mut n, &mut t, 0x1A00, 0, &[1]), None);
    assert_eq!(
        download(&mut n, &mut t, 0x1800, 1, &cob.to_le_bytes()),
        None
    );
    let mut last = None;
    for _ in 0..15 {
        t += 1000;
        while let Some(f) = n.poll(Instant::from_micros(t)) {
            if f.std_id() == Some(0x180 + u16::from(ID)) {
                last = Some(f.data().to_vec());
            }
        }
    }
    assert_eq!(last, Some(10u16.to_le_bytes().to_vec()));

    // Store, power cycle, restore.
    assert_eq!(
        download(&mut n, &mut t, 0x1017, 0, &250u16.to_le_bytes()),
        None
    );
    assert_eq!(
        download(&mut n, &mut t, 0x1010, 1, &SIG_SAVE.to_le_bytes()),
        None
    );
    n.power_off();
    n.power_on(Instant::from_micros(t));
    assert_eq!(upload(&mut n, &mut t, 0x1017, 0), 250);
    assert_eq!(upload(&mut n, &mut t, 0x2102, 0) as i32, -7);
    assert_eq!(upload(&mut n, &mut t, 0x2103, 0) as u8 as i8, -10);
    assert_eq!(
        download(&mut n, &mut t, 0x1011, 1, &SIG_LOAD.to_le_bytes()),
        None
    );
    n.power_off();
    n.power_on(Instant::from_micros(t));
    assert_eq!(upload(&mut n, &mut t, 0x1017, 0), 0);
    assert_eq!(upload(&mut n, &mut t, 0x2102, 0) as i32, -500);
}

#[test]
fn a_table_whose_cia301_object_lacks_its_hook_is_refused() {
    // What the loader builds carries every hook (the stack attaches them)…
    let d = eds(IO).unwrap();
    let b = Builder {
        file: "x.eds",
        kind: FileKind::Eds,
        warnings: Vec::new(),
    };
    let lines = BTreeMap::from([(canpos_stack::od::key(0x1014, 0), 42usize)]);
    b.check_hooks(d.model.entries, &lines).unwrap();
    // …and a table where one of them is missing or wrong is an error naming the object.
    for (index, sub) in [(0x1005, 0), (0x1010, 1), (0x1014, 0), (0x1017, 0)] {
        let mut t = d.model.entries.to_vec();
        let at = t.iter().position(|e| (e.index, e.sub) == (index, sub));
        let at = at.unwrap_or_else(|| panic!("io-device has 0x{index:04X}/{sub}"));
        for wrong in [Hook::None, Hook::TpdoMap] {
            t[at].hook = wrong;
            let err = b.check_hooks(&t, &lines).unwrap_err();
            assert!(
                err.msg
                    .starts_with(&format!("0x{index:04X} sub {sub} lacks")),
                "{err}"
            );
            if index == 0x1014 {
                assert_eq!(err.line, 42);
            }
        }
    }
}

const HBC: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../tests/interop/hbc-device.eds"
));

/// An EDS that declares 0x1016 and 0x1029 gets their rules (live objects, not plain values):
/// a duplicate node-id is refused with 0x06040043, a 0x1029 value above 2 with 0x06090030, and
/// a missed heartbeat raises EMCY 0x8130 and stops the node as 0x1029 sub 1 = 2 says.
#[test]
fn heartbeat_consumer_and_error_behaviour_are_live() {
    let o = Overrides {
        node_id: Some(ID),
        ..NONE
    };
    let d = build(HBC, "hbc.eds", FileKind::Eds, &o).unwrap();
    assert!(d.warnings.is_empty(), "{:?}", d.warnings);
    assert_eq!(find(d.model, 0x1016, 4).hook, Hook::HbConsumer);
    assert_eq!(find(d.model, 0x1029, 1).hook, Hook::ErrorBehaviour);
    assert_eq!(find(d.model, 0x1029, 2).hook, Hook::ErrorBehaviour);
    let mut n = Node::with_app(d.model, d.cfg, Plain, RamStorage::default());
    n.power_on(Instant::from_micros(0));
    while n.poll(Instant::from_micros(0)).is_some() {}
    let mut t = 0;
    let watch = (0x20u32 << 16 | 100).to_le_bytes();
    assert_eq!(download(&mut n, &mut t, 0x1016, 1, &watch), None);
    assert_eq!(
        download(&mut n, &mut t, 0x1016, 3, &watch),
        Some(0x0604_0043)
    );
    assert_eq!(upload(&mut n, &mut t, 0x1016, 3), 0);
    assert_eq!(download(&mut n, &mut t, 0x1029, 1, &[3]), Some(0x0609_0030));
    assert_eq!(download(&mut n, &mut t, 0x1029, 1, &[2]), None);
    n.handle_frame(
        &Frame::new(0x000, &[0x01, ID]).unwrap(),
        Instant::from_micros(t),
    );
    n.handle_frame(
        &Frame::new(0x720, &[0x05]).unwrap(),
        Instant::from_micros(t),
    );
    let mut emcy = None;
    for _ in 0..200 {
        t += 1000;
        while let Some(f) = n.poll(Instant::from_micros(t)) {
            if f.std_id() == Some(0x80 + u16::from(ID)) {
                emcy = Some(f);
            }
        }
    }
    assert_eq!(n.device().nmt_state(), canpos_stack::nmt::NmtState::Stopped);
    assert!(emcy.is_none(), "a stopped node keeps its EMCY");
    n.handle_frame(
        &Frame::new(0x000, &[0x80, ID]).unwrap(),
        Instant::from_micros(t),
    );
    let f = n
        .poll(Instant::from_micros(t))
        .expect("EMCY once pre-operational");
    assert_eq!(f.data()[..4], [0x30, 0x81, 0x11, 0x20]);
}

/// What the stack cannot serve or would refuse at run time is refused with the file's line: a
/// 0x1016 entry beyond the stack's count, a node-id watched twice, reserved bits, a 0x1029
/// start value that is no reaction.
#[test]
fn error_control_start_values_the_rules_refuse_name_the_line() {
    let beyond = canpos_stack::config::MAX_HB_CONSUMERS + 1;
    let extra = format!(
        "[1016sub{beyond:X}]\nParameterName=x\nObjectType=0x7\nDataType=0x0007\nAccessType=rw\n\
         DefaultValue=0\nPDOMapping=0\n\n[1017]\n"
    );
    let text = HBC.replacen("[1017]\n", &extra, 1).replacen(
        "heartbeat time\nObjectType=0x8\nSubNumber=5",
        "heartbeat time\nObjectType=0x8\nSubNumber=6",
        1,
    );
    let err = eds(&text).unwrap_err();
    assert_eq!(
        err.line,
        line_of(&text, &format!("[1016sub{beyond:X}]")),
        "{err}"
    );
    assert!(err.msg.contains("at most"), "{err}");
    let set = |sec: &str, v: &str| {
        let start = HBC.find(&format!("\n[{sec}]\n")).expect(sec);
        let at = start + HBC[start..].find("\nDefaultValue=").unwrap();
        let end = at + 1 + HBC[at + 1..].find('\n').unwrap();
        format!("{}\nDefaultValue={v}{}", &HBC[..at], &HBC[end..])
    };
    let two = set("1016sub2", "0x00200064");
    let two = {
        let start = two.find("\n[1016sub4]\n").unwrap();
        let at = start + two[start..].find("\nDefaultValue=").unwrap();
        let end = at + 1 + two[at + 1..].find('\n').unwrap();
        format!("{}\nDefaultValue=0x00200010{}", &two[..at], &two[end..])
    };
    let err = eds(&two).unwrap_err();
    assert!(err.msg.contains("as sub 2 does"), "{err}");
    let sec4 = line_of(&two, "[1016sub4]");
    assert!(err.line > sec4 && err.line < sec4 + 8, "{err}");
    // A zero time or another node-id is no clash.
    assert!(eds(&set("1016sub2", "0x00200000")).is_ok());
    let err = eds(&set("1016sub1", "0x01200064")).unwrap_err();
    assert!(err.msg.contains("reserved"), "{err}");
    let err = eds(&set("1029sub2", "3")).unwrap_err();
    assert!(err.msg.contains("no reaction"), "{err}");
    assert!(eds(&set("1029sub2", "2")).is_ok());
}

/// The file's RPDO is served: a value it carries lands after the SDO write's checks, its
/// event timer is a deadline (EMCY 0x8250), and an RPDO beyond those the stack has is left
/// out with a warning naming its line.
#[test]
fn the_node_serves_its_rpdo() {
    let mut n = node();
    let mut t = 1000;
    let at = |t: u64| Instant::from_micros(t);
    let rpdo = |n: &mut Node<Plain, RamStorage>, t: u64, data: &[u8]| {
        n.handle_frame(&Frame::new(0x200 + u16::from(ID), data).unwrap(), at(t));
    };
    // Pre-operational: not processed.
    rpdo(&mut n, t, &500u16.to_le_bytes());
    assert_eq!(upload(&mut n, &mut t, 0x2101, 0), 10);
    n.handle_frame(&Frame::std_len(0, [1, ID, 0, 0, 0, 0, 0, 0], 2), at(t));
    rpdo(&mut n, t, &500u16.to_le_bytes());
    assert_eq!(upload(&mut n, &mut t, 0x2101, 0), 500);
    // Beyond HighLimit: refused as an SDO write would be, the PDO not processed.
    rpdo(&mut n, t, &1001u16.to_le_bytes());
    assert_eq!(upload(&mut n, &mut t, 0x2101, 0), 500);
    // A 50 ms deadline from the next reception.
    assert_eq!(
        download(&mut n, &mut t, 0x1400, 5, &50u16.to_le_bytes()),
        None
    );
    rpdo(&mut n, t, &20u16.to_le_bytes());
    let mut emcy = Vec::new();
    for _ in 0..60 {
        t += 1000;
        while let Some(f) = n.poll(at(t)) {
            if f.std_id() == Some(0x80 + u16::from(ID)) {
                emcy.push(u16::from_le_bytes([f.data()[0], f.data()[1]]));
            }
        }
    }
    assert_eq!(emcy, [0x8250]);
    assert_eq!(upload(&mut n, &mut t, 0x2101, 0), 20);

    let five = IO
        .replace("[1400]", "[1404]")
        .replace("[1400sub", "[1404sub")
        .replace("10=0x1400", "10=0x1404")
        .replace("[1600]", "[1604]")
        .replace("[1600sub", "[1604sub")
        .replace("11=0x1600", "11=0x1604");
    let d = eds(&five).unwrap();
    let line = line_of(&five, "[1404]");
    assert!(
        d.warnings.iter().any(|w| w
            == &format!(
                "[1404] (line {line}): RPDO 5 left out: canpos-stack serves at most 4 RPDOs"
            )),
        "{:?}",
        d.warnings
    );
    assert_eq!(d.model.features.rpdos, 0);
    assert!(!d.model.entries.iter().any(|e| e.index == 0x1404));
}

/// The EDS export of a device with RPDOs lists them as it lists TPDOs (RECORDs, `NrOfRXPDO`)
/// and its RPDO-mappable objects as `rww`; the file builds the same table again.
#[test]
fn the_exported_eds_of_a_device_with_rpdos_rebuilds_it() {
    let m = eds(IO).unwrap().model;
    let mut text = String::new();
    canpos_stack::eds::write_eds(
        &mut text,
        m,
        &m.default_config,
        &canpos_stack::eds::EdsInfo::default(),
    )
    .unwrap();
    assert!(text.contains("NrOfRXPDO=1\n"), "{text}");
    assert!(text.contains("[1400]\nParameterName="), "{text}");
    let at = text.find("[1600]\n").unwrap();
    assert!(text[at..].contains("ObjectType=0x9\n"));
    let at = text.find("[2101]\n").unwrap();
    assert!(
        text[at..].starts_with(
            "[2101]\nParameterName=Filter time\nObjectType=0x7\nDataType=0x0006\nAccessType=rww\n"
        ),
        "{}",
        &text[at..at + 120]
    );
    let d = eds(&text).unwrap();
    assert!(d.warnings.is_empty(), "{:?}", d.warnings);
    let b = d.model;
    assert_eq!(b.features.rpdos, 1);
    let keys = |m: &Model| {
        m.entries
            .iter()
            .map(|e| (e.key(), e.hook, e.access))
            .collect::<Vec<_>>()
    };
    assert_eq!(keys(b), keys(m));
}

/// Sub 0 of 0x1016, 0x1029 and the PDO communication records is their highest sub-index, and
/// the PDOs' start values pass the rules an SDO write of them must: otherwise the file is
/// refused with the value's line (before, a lying sub 0 was served, and an RPDO of the reserved
/// type 241 took frames at once, one on the NMT CAN-ID 0 listened there).
#[test]
fn record_counts_and_pdo_start_values_the_rules_refuse_name_the_line() {
    let io401 = include_str!(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../examples/io-401.eds"
    ));
    let set = |sec: &str, v: &str| {
        let start = io401.find(&format!("\n[{sec}]\n")).expect(sec);
        let at = start + io401[start..].find("\nDefaultValue=").unwrap();
        let end = at + 1 + io401[at + 1..].find('\n').unwrap();
        format!("{}\nDefaultValue={v}{}", &io401[..at], &io401[end..])
    };
    for (sec, v, words) in [
        ("1016sub0", "9", "highest sub-index of 0x1016 is 4"),
        ("1016sub0", "2", "highest sub-index of 0x1016 is 4"),
        ("1029sub0", "1", "highest sub-index of 0x1029 is 3"),
        ("1400sub0", "2", "highest sub-index of 0x1400 is 5"),
        ("1803sub0", "6", "highest sub-index of 0x1803 is 5"),
        ("1400sub2", "241", "transmission type 241 is reserved"),
        ("1802sub2", "253", "transmission type 253 is reserved"),
        ("1400sub1", "0x0", "COB-ID 0x00000000 is refused"),
        (
            "1401sub1",
            "$NODEID+0x580",
            "COB-ID 0x00000581 ($NODEID+0x580 on node-id 1)",
        ),
        (
            "1401sub1",
            "$NODEID+0x560",
            "COB-ID 0x00000581 ($NODEID+0x560 on node-id 33)",
        ),
        ("1800sub1", "0x701", "COB-ID 0x00000701 is refused"),
        ("1400sub1", "0x20000205", "29-bit"),
    ] {
        let text = set(sec, v);
        let err = match build(
            &text,
            "x.eds",
            FileKind::Eds,
            &Overrides {
                node_id: Some(5),
                ..NONE
            },
        ) {
            Err(e) => e,
            Ok(_) => panic!("[{sec}] DefaultValue={v} was taken"),
        };
        let at = line_of(&text, &format!("[{sec}]"));
        assert!(err.line > at && err.line < at + 8, "[{sec}] {v}: {err}");
        assert!(err.msg.contains(words), "[{sec}] {v}: {err}");
    }
    // What a write could set is taken: a restricted CAN-ID on an invalid PDO, type 240; the
    // pre-defined COB-IDs on the highest node-id and on none yet (LSS unconfigured, 255).
    assert!(eds(&set("1400sub1", "0x80000000")).is_ok());
    assert!(eds(&set("1400sub2", "240")).is_ok());
    for node_id in [127, 255] {
        let o = Overrides {
            node_id: Some(node_id),
            ..NONE
        };
        assert!(
            build(io401, "x.eds", FileKind::Eds, &o).is_ok(),
            "{node_id}"
        );
    }
}
