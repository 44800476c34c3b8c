//! EDS export (CiA 306 electronic data sheet), generated from the same model tables the device
//! runs on, so the file cannot drift from the dictionary.
//!
//! Written to any [`core::fmt::Write`] without allocation. Rules (SPEC §12, CONFORMANCE §1 and
//! §13):
//!
//! * TPDO-mappable objects are `ro` (never plain `rw`), and live values carry no
//!   `DefaultValue` (a conformance tool compares defaults with what it reads). On a device
//!   with RPDOs a writable mappable object is `rww` (CiA 306: written by the process output,
//!   an RPDO), never plain `rw` either.
//! * Defaults that follow the node-id are written `$NODEID+0x180` style; other unit-dependent
//!   defaults (product code, serial, measuring steps, limits) are resolved for the given unit.
//! * Objects with sub-indices are ARRAY (0x8) when all subs after sub 0 share one type,
//!   RECORD (0x9) otherwise and for the identity and PDO parameter records.
//! * `LowLimit` / `HighLimit` only where the table declares a range.
//! * No keys outside CiA 306 (the conformance checker warns about them).
//! * Unsigned values in hex as wide as their type (`0x00000000` for an unused mapping entry,
//!   `0x05` for an UNSIGNED8), signed values in decimal.
//!
//! [`write_dcf`] writes the same file with each object's current value (`ParameterValue`) and
//! `[DeviceComissioning]` (CiA 306 §4.6; the section name is spelt so in the standard).

use core::fmt::{self, Write};

use crate::model::{Model, UnitConfig};
use crate::od::{resolve_default, DataType, DefaultValue, Entry, Param, ParamSource, Range};

/// File information for [`write_eds`] (the core has no clock or file system).
#[derive(Clone, Copy, Debug)]
pub struct EdsInfo<'a> {
    /// `FileName` (e.g. `canpos-th.eds`).
    pub file_name: &'a str,
    /// `CreationDate` / `ModificationDate`, `MM-DD-YYYY`.
    pub date: &'a str,
    /// `CreationTime` / `ModificationTime`, `hh:mm(AM|PM)`.
    pub time: &'a str,
    /// `CreatedBy` / `ModifiedBy`.
    pub created_by: &'a str,
    /// `OrderCode`: the unit's order code where one is known, else empty.
    pub order_code: &'a str,
}

/// A value read from a configured unit, for [`write_dcf`].
#[derive(Clone, Copy, Debug)]
pub enum DcfValue<'a> {
    /// A numeric object's raw value (as the dictionary stores it: sign-extended for signed).
    Number(u32),
    /// A string or domain object's bytes.
    Bytes(&'a [u8]),
}

/// `[DeviceComissioning]` of a DCF.
#[derive(Clone, Copy, Debug)]
pub struct Commissioning<'a> {
    /// `NodeID` (1…127).
    pub node_id: u8,
    /// `NodeName`.
    pub node_name: &'a str,
    /// `Baudrate` in kbit/s.
    pub bitrate_kbps: u16,
    /// `NetNumber`.
    pub net_number: u32,
    /// `NetworkName`.
    pub network_name: &'a str,
    /// `LSS_SerialNumber` (0x1018/4).
    pub lss_serial: u32,
    /// `LastEDS` in `[FileInfo]`: the EDS the DCF was made from.
    pub last_eds: &'a str,
}

impl core::default::Default for EdsInfo<'_> {
    fn default() -> Self {
        EdsInfo {
            file_name: "canpos.eds",
            date: "01-01-2025",
            time: "12:00PM",
            created_by: "canpos",
            order_code: "",
        }
    }
}

struct Unit<'a, C: 'static, X: 'static> {
    model: &'static Model<C, X>,
    cfg: &'a C,
}

impl<C, X> ParamSource for Unit<'_, C, X> {
    fn param(&self, p: Param) -> u32 {
        (self.model.param)(self.cfg, p)
    }
}

/// Writes the EDS of `model` for the unit `cfg` to `w`.
pub fn write_eds<C: UnitConfig, X>(
    w: &mut dyn Write,
    model: &'static Model<C, X>,
    cfg: &C,
    info: &EdsInfo<'_>,
) -> fmt::Result {
    write_file(w, model, cfg, info, None)
}

/// The current values of a unit for [`write_dcf`]: `None` for an object that could not be read
/// (write-only, or refused), which then gets no `ParameterValue`.
pub type ValueSource<'a> = &'a dyn Fn(u16, u8) -> Option<DcfValue<'a>>;

/// Writes the DCF of a configured unit: the EDS of `model` for `cfg`, with `[DeviceComissioning]`
/// and each object's current value from `values` as `ParameterValue`.
pub fn write_dcf<C: UnitConfig, X>(
    w: &mut dyn Write,
    model: &'static Model<C, X>,
    cfg: &C,
    info: &EdsInfo<'_>,
    commissioning: &Commissioning<'_>,
    values: ValueSource<'_>,
) -> fmt::Result {
    write_file(w, model, cfg, info, Some((commissioning, values)))
}

fn write_file<C: UnitConfig, X>(
    w: &mut dyn Write,
    model: &'static Model<C, X>,
    cfg: &C,
    info: &EdsInfo<'_>,
    dcf: Option<(&Commissioning<'_>, ValueSource<'_>)>,
) -> fmt::Result {
    // The unit's own dictionary: one EDS per configuration (TMI 002 §1.6).
    let model = model.for_unit(cfg);
    let unit = Unit { model, cfg };
    let value = |index: u16, sub: u8| -> u32 {
        model
            .entries
            .iter()
            .find(|e| e.index == index && e.sub == sub)
            .map_or(0, |e| resolve_default(e, &unit, cfg.node_id()))
    };

    writeln!(w, "[FileInfo]")?;
    writeln!(w, "FileName={}", info.file_name)?;
    writeln!(w, "FileVersion=1")?;
    writeln!(w, "FileRevision=0")?;
    writeln!(w, "EDSVersion=4.0")?;
    writeln!(w, "Description={} (canpos software twin)", model.product)?;
    writeln!(w, "CreationTime={}", info.time)?;
    writeln!(w, "CreationDate={}", info.date)?;
    writeln!(w, "CreatedBy={}", info.created_by)?;
    writeln!(w, "ModificationTime={}", info.time)?;
    writeln!(w, "ModificationDate={}", info.date)?;
    writeln!(w, "ModifiedBy={}", info.created_by)?;
    if let Some((c, _)) = dcf {
        writeln!(w, "LastEDS={}", c.last_eds)?;
    }
    writeln!(w)?;

    let f = &model.features;
    writeln!(w, "[DeviceInfo]")?;
    writeln!(w, "VendorName={}", model.vendor)?;
    writeln!(w, "VendorNumber=0x{:08X}", value(0x1018, 1))?;
    writeln!(w, "ProductName={}", model.product)?;
    writeln!(w, "ProductNumber=0x{:08X}", value(0x1018, 2))?;
    writeln!(w, "RevisionNumber=0x{:08X}", value(0x1018, 3))?;
    writeln!(w, "OrderCode={}", info.order_code)?;
    for rate in [10u16, 20, 50, 125, 250, 500, 800, 1000] {
        writeln!(w, "BaudRate_{}={}", rate, f.bitrates.contains(&rate) as u8)?;
    }
    writeln!(w, "SimpleBootUpMaster=0")?;
    writeln!(w, "SimpleBootUpSlave=1")?;
    writeln!(w, "Granularity=8")?;
    writeln!(w, "DynamicChannelsSupported=0")?;
    writeln!(w, "GroupMessaging=0")?;
    writeln!(w, "NrOfRXPDO={}", f.rpdos)?;
    writeln!(w, "NrOfTXPDO={}", f.tpdos)?;
    writeln!(w, "LSS_Supported=1")?;
    writeln!(w)?;

    if let Some((c, _)) = dcf {
        writeln!(w, "[DeviceComissioning]")?;
        writeln!(w, "NodeID=0x{:02X}", c.node_id)?;
        writeln!(w, "NodeName={}", c.node_name)?;
        writeln!(w, "Baudrate={}", c.bitrate_kbps)?;
        writeln!(w, "NetNumber={}", c.net_number)?;
        writeln!(w, "NetworkName={}", c.network_name)?;
        writeln!(w, "CANopenManager=0")?;
        writeln!(w, "LSS_SerialNumber=0x{:08X}", c.lss_serial)?;
        writeln!(w)?;
    }

    // The mapping checks accept only objects in the table: no dummy entries.
    writeln!(w, "[DummyUsage]")?;
    for d in 1..=7 {
        writeln!(w, "Dummy{:04X}=0", d)?;
    }
    writeln!(w)?;

    let mandatory = |i: u16| matches!(i, 0x1000 | 0x1001 | 0x1018);
    let manufacturer = |i: u16| (0x2000..0x6000).contains(&i);
    write_list(w, "MandatoryObjects", model.entries, &|i| mandatory(i))?;
    write_list(w, "OptionalObjects", model.entries, &|i| {
        !mandatory(i) && !manufacturer(i)
    })?;
    write_list(w, "ManufacturerObjects", model.entries, &|i| {
        manufacturer(i)
    })?;

    let values = dcf.map(|(_, v)| v);
    for obj in objects(model.entries) {
        write_object(w, obj, &unit, cfg, values)?;
    }
    Ok(())
}

/// The entries of each object, in table order.
fn objects(entries: &'static [Entry]) -> impl Iterator<Item = &'static [Entry]> {
    let mut rest = entries;
    core::iter::from_fn(move || {
        let first = rest.first()?;
        let n = rest.iter().take_while(|e| e.index == first.index).count();
        let (obj, tail) = rest.split_at(n);
        rest = tail;
        Some(obj)
    })
}

fn write_list(
    w: &mut dyn Write,
    section: &str,
    entries: &'static [Entry],
    pick: &dyn Fn(u16) -> bool,
) -> fmt::Result {
    let count = objects(entries).filter(|o| pick(o[0].index)).count();
    writeln!(w, "[{section}]")?;
    writeln!(w, "SupportedObjects={count}")?;
    for (i, o) in objects(entries).filter(|o| pick(o[0].index)).enumerate() {
        writeln!(w, "{}=0x{:04X}", i + 1, o[0].index)?;
    }
    writeln!(w)
}

/// A plain VAR when the object is sub 0 alone, else ARRAY / RECORD with one section per sub.
fn write_object<C: UnitConfig, X>(
    w: &mut dyn Write,
    obj: &'static [Entry],
    unit: &Unit<'_, C, X>,
    cfg: &C,
    values: Option<ValueSource<'_>>,
) -> fmt::Result {
    let first = &obj[0];
    if obj.len() == 1 && first.sub == 0 {
        writeln!(w, "[{:04X}]", first.index)?;
        return write_var(w, first, first.name, unit, cfg, values);
    }
    let index = first.index;
    let record = matches!(index, 0x1018 | 0x1400..=0x17FF | 0x1800..=0x1BFF)
        || obj
            .iter()
            .filter(|e| e.sub > 0)
            .any(|e| e.ty != obj[obj.len() - 1].ty);
    writeln!(w, "[{index:04X}]")?;
    writeln!(w, "ParameterName={}", object_name(first.name))?;
    writeln!(w, "ObjectType=0x{}", if record { 9 } else { 8 })?;
    writeln!(w, "SubNumber={}", obj.len())?;
    writeln!(w)?;
    for e in obj {
        writeln!(w, "[{:04X}sub{:X}]", e.index, e.sub)?;
        write_var(w, e, e.name, unit, cfg, values)?;
    }
    Ok(())
}

/// The object's name: the sub-0 name up to its ':' ("Identity object: number of entries").
fn object_name(sub0: &str) -> &str {
    sub0.split(':').next().unwrap_or(sub0).trim()
}

fn write_var<C: UnitConfig, X>(
    w: &mut dyn Write,
    e: &Entry,
    name: &str,
    unit: &Unit<'_, C, X>,
    cfg: &C,
    values: Option<ValueSource<'_>>,
) -> fmt::Result {
    writeln!(w, "ParameterName={name}")?;
    writeln!(w, "ObjectType=0x7")?;
    writeln!(w, "DataType=0x{:04X}", e.ty.code())?;
    // Mappable values are produced by the device: ro, never rw (CONFORMANCE EDS-01); on a
    // device with RPDOs a writable one is what they write: rww.
    let access = if e.pdo && e.access.writable() {
        if unit.model.features.rpdos > 0 {
            "rww"
        } else {
            "ro"
        }
    } else {
        e.access.eds()
    };
    writeln!(w, "AccessType={access}")?;
    if let Some((lo, hi)) = limits(e, cfg) {
        write!(w, "LowLimit=")?;
        write_number(w, e.ty, lo)?;
        write!(w, "\nHighLimit=")?;
        write_number(w, e.ty, hi)?;
        writeln!(w)?;
    }
    match e.default {
        DefaultValue::Live => {}
        DefaultValue::Str(s) => writeln!(w, "DefaultValue={s}")?,
        DefaultValue::NodeId(base) => {
            write!(w, "DefaultValue=$NODEID+")?;
            write_number(w, e.ty, base as i64)?;
            writeln!(w)?;
        }
        DefaultValue::Const(v) => {
            write!(w, "DefaultValue=")?;
            write_number(w, e.ty, e.ty.to_i64(v))?;
            writeln!(w)?;
        }
        DefaultValue::Param(p) => {
            // A value that moves with the node-id is written relative to it.
            let at = |id: u8| {
                let mut c = *cfg;
                c.set_node_id(id);
                (unit.model.param)(&c, p)
            };
            let (v0, v1) = (at(0), at(1));
            if v1.wrapping_sub(v0) == 1 && p != Param::BitRateKbps {
                // "$NODEID+0x0" rather than a bare "$NODEID": python-canopen only resolves
                // the "+" form.
                write!(w, "DefaultValue=$NODEID+")?;
                write_number(w, e.ty, v0 as i64)?;
                writeln!(w)?;
            } else {
                write!(w, "DefaultValue=")?;
                write_number(w, e.ty, e.ty.to_i64(unit.param(p)))?;
                writeln!(w)?;
            }
        }
    }
    match values.and_then(|v| v(e.index, e.sub)) {
        None => {}
        Some(DcfValue::Number(raw)) => {
            write!(w, "ParameterValue=")?;
            write_number(w, e.ty, e.ty.to_i64(raw))?;
            writeln!(w)?;
        }
        Some(DcfValue::Bytes(b)) => {
            write!(w, "ParameterValue=")?;
            match e.ty {
                // A string is written as its text; bytes outside printable ASCII cannot be.
                DataType::VisibleString if b.iter().all(|c| (0x20..0x7F).contains(c)) => {
                    for &c in b {
                        w.write_char(c as char)?;
                    }
                }
                _ => {
                    for c in b {
                        write!(w, "{c:02X}")?;
                    }
                }
            }
            writeln!(w)?;
        }
    }
    writeln!(w, "PDOMapping={}", e.pdo as u8)?;
    writeln!(w)
}

/// The values the unit `cfg` accepts as EDS limits: the table's range narrowed by the rule of
/// the application hook of the entry for this unit ([`UnitConfig::app_limits`]). Lists of
/// allowed values are not expressible; they get the smallest and largest member.
fn limits<C: UnitConfig>(e: &Entry, cfg: &C) -> Option<(i64, i64)> {
    let table = match *e.range {
        Range::Any => None,
        Range::MinMax(..) => e.limits(),
        Range::OneOf(list) => {
            let lo = list.iter().map(|&v| e.ty.to_i64(v)).min()?;
            let hi = list.iter().map(|&v| e.ty.to_i64(v)).max()?;
            Some((lo, hi))
        }
    };
    // A rule limits what a write may bring: none on a read-only entry (TH 0x6005/1).
    let rule = e
        .hook
        .app_number()
        .filter(|_| e.access.writable())
        .and_then(|h| cfg.app_limits(h))
        .map(|(lo, hi)| (e.ty.to_i64(lo), e.ty.to_i64(hi)));
    match (table, rule) {
        (Some((a, b)), Some((c, d))) => Some((a.max(c), b.min(d))),
        (t, r) => t.or(r),
    }
}

/// Unsigned values in hex as wide as the type (what tools show for COB-IDs and codes; eds-utils
/// wants mapping entries as `0x00000000`), signed in decimal.
fn write_number(w: &mut dyn Write, ty: DataType, v: i64) -> fmt::Result {
    if ty.is_signed() {
        write!(w, "{v}")
    } else {
        let digits = 2 * ty.size().unwrap_or(4);
        write!(w, "0x{:0digits$X}", v as u64 & 0xFFFF_FFFF)
    }
}
