//! A plain CiA 301 device described by a user's EDS or DCF file (CiA 306): the file becomes a
//! [`Model`] at run time, served by [`canpos_stack::Node`] with the [`Plain`] application.
//!
//! The core takes its dictionary as a `&'static [Entry]`; the table built here is leaked
//! (`Box::leak`) once per process, like the strings it names. What the file says:
//!
//! - objects, sub-indices, `ParameterName`, `DataType`, `AccessType`, `PDOMapping`;
//! - `DefaultValue` (`$NODEID+…` becomes a node-id relative default), `LowLimit` / `HighLimit`;
//! - with a DCF, `ParameterValue` is the value the device starts with, and
//!   `[DeviceComissioning]` `NodeID` / `Baudrate` its node-id and bit rate;
//! - `[DeviceInfo]`: `VendorName`, `ProductName`, `NrOfTXPDO` / `NrOfRXPDO` (checked against
//!   the objects), `BaudRate_*`, `LSS_Supported`.
//!
//! What the standard says, not the file (`STANDARD`, one table): which service owns the CiA
//! 301 objects (their [`Hook`]) and which data type each must have. Storage groups follow
//! from access and index: rw objects of 0x1000–0x1FFF are communication parameters, rw objects
//! from 0x2000 on application parameters, everything else is volatile.
//!
//! What the core cannot serve is an error naming the file and line, as is anything malformed:
//! DOMAIN and 64-bit / REAL / OCTET_STRING types, writable strings, more than
//! [`MAX_ENTRIES`] entries, [`pdo::MAX_TPDOS`] TPDOs or [`MAX_HB_CONSUMERS`] heartbeat
//! consumer entries (0x1016), and start values the services' rules refuse (a node-id watched
//! twice in 0x1016, a 0x1029 reaction other than 0, 1, 2, a reserved PDO transmission type, a
//! sub 0 that is not its record's highest sub-index). RPDOs beyond [`rpdo::MAX_RPDOS`]
//! are left out with a warning naming their line (the ones served stay usable: a master that
//! configures only the first ones works).

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

use canpos_stack::config::MAX_HB_CONSUMERS;
use canpos_stack::model::{CommConfig, Features, Model, Table};
use canpos_stack::od::{
    cia301, Access, DataType, DefaultValue, Entry, Group, Hook, Param, Range, MAX_ENTRIES,
};
use canpos_stack::storage::{crc32, IMAGE_MAX};
use canpos_stack::Plain;
use canpos_stack::{pdo, rpdo};

use crate::ini::{Ini, Key, Section};

mod checks;
mod values;

use values::{access, data_type, raw_of};
pub use values::{parse_int, parse_number, parse_value, section_object};

/// What is wrong with an EDS / DCF file, and where.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EdsError {
    /// The file as given.
    pub file: String,
    /// 1-based line; 0 when the problem is the file as a whole (a missing section).
    pub line: usize,
    /// What is wrong.
    pub msg: String,
}

impl fmt::Display for EdsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.line == 0 {
            write!(f, "{}: {}", self.file, self.msg)
        } else {
            write!(f, "{}:{}: {}", self.file, self.line, self.msg)
        }
    }
}

impl std::error::Error for EdsError {}

/// An EDS (device description) or a DCF (one configured device).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileKind {
    /// `ParameterValue` and `[DeviceComissioning]` are ignored (with a warning).
    Eds,
    /// `ParameterValue` is the start value, `[DeviceComissioning]` gives node-id and bit rate.
    Dcf,
}

/// Command-line values that win over the file's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Overrides {
    /// Node-id (1…127, 255 = unconfigured).
    pub node_id: Option<u8>,
    /// The node's bit rate in kbit/s.
    pub bitrate_kbps: Option<u16>,
    /// Serial number (0x1018/4).
    pub serial: Option<u32>,
}

/// Node-id when neither the command line nor a DCF gives one (that of the sensors).
pub const DEFAULT_NODE_ID: u8 = 127;
/// Bit rate in kbit/s when neither the command line nor a DCF gives one and the file allows it.
pub const DEFAULT_BITRATE: u16 = 125;

/// A device built from a file: the model and the unit configuration to run it with.
#[derive(Debug)]
pub struct EdsDevice {
    /// The model (table and features leaked for the life of the process).
    pub model: &'static Model,
    /// Node-id and bit rate (command line, else DCF, else the defaults) and serial number.
    pub cfg: CommConfig,
    /// Things left out or not used (RPDOs, unlisted objects, …), for the log.
    pub warnings: Vec<String>,
    /// 0x1018/1 vendor-id.
    pub vendor_id: u32,
    /// 0x1018/2 product code (0 when the file has none).
    pub product_code: u32,
}

impl EdsDevice {
    /// The state file of this device in `state_dir`:
    /// `eds-VVVVVVVV-PPPPPPPP-SERIAL.bin` (vendor-id, product code in hex, serial number), so
    /// two devices of different identity never share an image.
    pub fn state_file(&self, state_dir: &Path) -> PathBuf {
        let name = format!("eds-{:08x}-{:08x}", self.vendor_id, self.product_code);
        crate::runtime::state_file(state_dir, &name, self.cfg.serial)
    }
}

/// Reads and builds the device of file `path`.
pub fn load(path: &Path, kind: FileKind, o: &Overrides) -> Result<EdsDevice, EdsError> {
    let file = path.display().to_string();
    let text = std::fs::read(path).map_err(|e| EdsError {
        file: file.clone(),
        line: 0,
        msg: format!("cannot read: {e}"),
    })?;
    let text = String::from_utf8_lossy(&text);
    build(&text, &file, kind, o)
}

/// Builds the device of EDS / DCF text (`file` names it in errors).
pub fn build(text: &str, file: &str, kind: FileKind, o: &Overrides) -> Result<EdsDevice, EdsError> {
    let ini = Ini::parse(text).map_err(|e| EdsError {
        file: file.to_string(),
        line: e.line,
        msg: e.msg,
    })?;
    Builder {
        file,
        kind,
        warnings: Vec::new(),
    }
    .build(&ini, o)
}

/// One CiA 301 object the standard defines, with the data type it must have. Its hook (the
/// service rule that owns it) is the stack's: [`cia301::hook_of`].
struct Std {
    index: std::ops::RangeInclusive<u16>,
    subs: std::ops::RangeInclusive<u8>,
    ty: DataType,
}

const fn row(lo: u16, hi: u16, s0: u8, s1: u8, ty: DataType) -> Std {
    Std {
        index: lo..=hi,
        subs: s0..=s1,
        ty,
    }
}

/// The CiA 301 objects whose meaning the core's services implement, by their standard
/// indices, with their data types.
const STANDARD: &[Std] = {
    use DataType::{Unsigned16 as U16, Unsigned32 as U32, Unsigned8 as U8};
    let t = pdo::MAX_TPDOS as u16 - 1;
    let r = rpdo::MAX_RPDOS as u16 - 1;
    &[
        row(0x1000, 0x1000, 0, 0, U32),
        row(0x1001, 0x1001, 0, 0, U8),
        row(0x1003, 0x1003, 0, 0, U8),
        row(0x1003, 0x1003, 1, 0xFE, U32),
        row(0x1005, 0x1005, 0, 0, U32),
        row(0x100C, 0x100C, 0, 0, U16),
        row(0x100D, 0x100D, 0, 0, U8),
        row(0x100E, 0x100E, 0, 0, U32),
        row(0x1010, 0x1010, 0, 0, U8),
        row(0x1010, 0x1010, 1, 0x7F, U32),
        row(0x1011, 0x1011, 0, 0, U8),
        row(0x1011, 0x1011, 1, 0x7F, U32),
        row(0x1014, 0x1014, 0, 0, U32),
        row(0x1015, 0x1015, 0, 0, U16),
        row(0x1016, 0x1016, 0, 0, U8),
        row(0x1016, 0x1016, 1, MAX_HB_CONSUMERS as u8, U32),
        row(0x1017, 0x1017, 0, 0, U16),
        row(0x1018, 0x1018, 0, 0, U8),
        row(0x1018, 0x1018, 1, 4, U32),
        row(0x1029, 0x1029, 0, 0, U8),
        row(0x1029, 0x1029, 1, 0xFE, U8),
        row(0x1400, 0x1400 + r, 0, 0, U8),
        row(0x1400, 0x1400 + r, 1, 1, U32),
        row(0x1400, 0x1400 + r, 2, 2, U8),
        row(0x1400, 0x1400 + r, 3, 3, U16),
        row(0x1400, 0x1400 + r, 5, 5, U16),
        row(0x1600, 0x1600 + r, 0, 0, U8),
        row(0x1600, 0x1600 + r, 1, pdo::MAX_MAP as u8, U32),
        row(0x1800, 0x1800 + t, 0, 0, U8),
        row(0x1800, 0x1800 + t, 1, 1, U32),
        row(0x1800, 0x1800 + t, 2, 2, U8),
        row(0x1800, 0x1800 + t, 3, 3, U16),
        row(0x1800, 0x1800 + t, 5, 5, U16),
        row(0x1800, 0x1800 + t, 6, 6, U8),
        row(0x1A00, 0x1A00 + t, 0, 0, U8),
        row(0x1A00, 0x1A00 + t, 1, pdo::MAX_MAP as u8, U32),
    ]
};

fn standard(index: u16, sub: u8) -> Option<&'static Std> {
    STANDARD
        .iter()
        .find(|s| s.index.contains(&index) && s.subs.contains(&sub))
}

fn leak(s: &str) -> &'static str {
    Box::leak(s.to_owned().into_boxed_str())
}

struct Builder<'a> {
    file: &'a str,
    kind: FileKind,
    warnings: Vec<String>,
}

impl Builder<'_> {
    fn err(&self, line: usize, msg: impl Into<String>) -> EdsError {
        EdsError {
            file: self.file.to_string(),
            line,
            msg: msg.into(),
        }
    }

    fn num(&self, k: &Key) -> Result<i64, EdsError> {
        parse_int(&k.value)
            .ok_or_else(|| self.err(k.line, format!("{}: `{}` is not a number", k.name, k.value)))
    }

    fn build(mut self, ini: &Ini, o: &Overrides) -> Result<EdsDevice, EdsError> {
        let info = ini
            .section("DeviceInfo")
            .ok_or_else(|| self.err(0, "no [DeviceInfo] section"))?;
        if ini.section("MandatoryObjects").is_none() {
            return Err(self.err(0, "no [MandatoryObjects] section"));
        }

        // Objects and their sub-index sections, by index.
        let mut objects: BTreeMap<u16, &Section> = BTreeMap::new();
        let mut subs: BTreeMap<u16, BTreeMap<u8, &Section>> = BTreeMap::new();
        for s in &ini.sections {
            match section_object(&s.name) {
                Some((index, None)) => {
                    objects.insert(index, s);
                }
                Some((index, Some(sub))) => {
                    if let Some(first) = subs.entry(index).or_default().insert(sub, s) {
                        return Err(self.err(
                            s.line,
                            format!(
                                "[{}] is sub-index {sub} of 0x{index:04X} again (first [{}] on \
                                 line {})",
                                s.name, first.name, first.line
                            ),
                        ));
                    }
                }
                None => {}
            }
        }
        for (index, m) in &subs {
            if !objects.contains_key(index) {
                let s = m.values().next().expect("non-empty");
                return Err(self.err(
                    s.line,
                    format!(
                        "[{}]: object 0x{index:04X} has no [{index:04X}] section",
                        s.name
                    ),
                ));
            }
        }
        self.check_lists(ini, &objects)?;

        let dcf = self.kind == FileKind::Dcf;
        let mut entries: Vec<Entry> = Vec::new();
        let mut value_lines: BTreeMap<u32, usize> = BTreeMap::new();
        let mut tpdo_objects = 0usize;
        let mut rpdo_objects = 0usize;
        for (&index, sec) in &objects {
            if index < 0x1000 {
                self.warnings.push(format!(
                    "[{}] (line {}): data type definitions are not objects of the device; \
                     left out",
                    sec.name, sec.line
                ));
                continue;
            }
            if (0x1400..=0x17FF).contains(&index) {
                let n = usize::from(index & 0x1FF);
                if n >= rpdo::MAX_RPDOS {
                    self.warnings.push(format!(
                        "[{}] (line {}): RPDO {} left out: canpos-stack serves at most {} RPDOs",
                        sec.name,
                        sec.line,
                        n + 1,
                        rpdo::MAX_RPDOS
                    ));
                    continue;
                }
                self.check_pdo_pair(&objects, sec, index, "RPDO")?;
                rpdo_objects = rpdo_objects.max(n + 1);
            }
            if (0x1800..=0x19FF).contains(&index) || (0x1A00..=0x1BFF).contains(&index) {
                let n = usize::from(index & 0x1FF);
                if n >= pdo::MAX_TPDOS {
                    return Err(self.err(
                        sec.line,
                        format!(
                            "[{}]: TPDO {} — canpos-stack serves at most {} TPDOs",
                            sec.name,
                            n + 1,
                            pdo::MAX_TPDOS
                        ),
                    ));
                }
                self.check_pdo_pair(&objects, sec, index, "TPDO")?;
                tpdo_objects = tpdo_objects.max(n + 1);
            }
            if let Some(k) = sec.key("CompactSubObj") {
                if self.num(k)? != 0 {
                    return Err(self.err(
                        k.line,
                        "CompactSubObj is not supported; write each sub-index as its own \
                         [xxxxsubN] section",
                    ));
                }
            }
            // ObjectType is optional (CiA 306: VAR); a SubNumber says it has sub-indices.
            let ot = match sec.key("ObjectType") {
                Some(k) => self.num(k)?,
                None if sec.key("SubNumber").is_some() => 9,
                None => 7,
            };
            let mine = subs.get(&index);
            match ot {
                7 => {
                    if let Some(m) = mine {
                        let s = m.values().next().expect("non-empty");
                        return Err(self.err(
                            s.line,
                            format!(
                                "[{}]: 0x{index:04X} is a VAR, it has no sub-indices",
                                s.name
                            ),
                        ));
                    }
                    entries.push(self.var(sec, index, 0, dcf, &mut value_lines)?);
                }
                8 | 9 => {
                    let k = sec.key("SubNumber").ok_or_else(|| {
                        self.err(
                            sec.line,
                            format!("[{}]: ARRAY / RECORD without SubNumber", sec.name),
                        )
                    })?;
                    let n = self.num(k)?;
                    let have = mine.map_or(0, |m| m.len());
                    if n < 1 || n as usize != have {
                        return Err(self.err(
                            k.line,
                            format!(
                                "SubNumber={} but 0x{index:04X} has {have} sub-index section(s)",
                                k.value
                            ),
                        ));
                    }
                    let m = mine.expect("have > 0");
                    if !m.contains_key(&0) {
                        return Err(self.err(
                            sec.line,
                            format!("[{}]: no [{index:04X}sub0] (highest sub-index)", sec.name),
                        ));
                    }
                    for (&sub, s) in m {
                        if let Some(k) = s.key("ObjectType") {
                            if self.num(k)? != 7 {
                                return Err(self.err(k.line, "a sub-index must be a VAR (0x7)"));
                            }
                        }
                        entries.push(self.var(s, index, sub, dcf, &mut value_lines)?);
                    }
                }
                _ => {
                    let line = sec.key("ObjectType").map_or(sec.line, |k| k.line);
                    return Err(self.err(
                        line,
                        format!(
                            "ObjectType 0x{ot:X} is not supported (VAR 0x7, ARRAY 0x8 and RECORD \
                             0x9 are)"
                        ),
                    ));
                }
            }
        }

        let mandatory_line = ini.section("MandatoryObjects").map_or(0, |s| s.line);
        for (i, s) in [(0x1000u16, 0u8), (0x1001, 0), (0x1018, 1)] {
            if !entries.iter().any(|e| e.index == i && e.sub == s) {
                return Err(self.err(
                    mandatory_line,
                    format!("the mandatory object 0x{i:04X} sub {s} is missing (CiA 301)"),
                ));
            }
        }
        self.check_hooks(&entries, &value_lines)?;
        if entries.len() > MAX_ENTRIES {
            return Err(self.err(
                0,
                format!(
                    "{} entries (objects and sub-indices); canpos-stack serves at most {MAX_ENTRIES}",
                    entries.len()
                ),
            ));
        }
        // The image also holds the LSS node-id, bit rate and the saved node-id.
        let stored = entries
            .iter()
            .filter(|e| e.group != Group::Volatile)
            .count();
        let max_stored = (IMAGE_MAX - 12) / 8 - 3;
        if stored > max_stored {
            return Err(self.err(
                0,
                format!(
                    "{stored} stored (rw) entries; canpos-stack's storage image holds {max_stored}"
                ),
            ));
        }
        self.check_mappings(&entries, &value_lines)?;
        self.check_error_control(&entries, &value_lines)?;
        self.check_highest_sub(&entries, &value_lines)?;

        for (key, have, what) in [
            ("NrOfTXPDO", tpdo_objects, "TPDO"),
            ("NrOfRXPDO", rpdo_objects, "RPDO"),
        ] {
            if let Some(k) = info.key(key) {
                if self.num(k)? != have as i64 {
                    self.warnings.push(format!(
                        "line {}: {key}={} but the file has {have} {what}(s); the objects \
                         are served",
                        k.line, k.value
                    ));
                }
            }
        }
        // Dummy entries of the integer types (0x0002–0x0007) map into RPDOs; a BOOLEAN one is
        // a single bit, and PDOs are mapped in whole bytes.
        if ini.get("DummyUsage", "Dummy0001").and_then(parse_int) == Some(1) {
            self.warnings.push(
                "Dummy0001=1: a 1-bit dummy is not supported (PDOs map whole bytes); not mappable"
                    .into(),
            );
        }

        let bitrates: Vec<u16> = [10u16, 20, 50, 125, 250, 500, 800, 1000]
            .into_iter()
            .filter(|r| info.get(&format!("BaudRate_{r}")).and_then(parse_int) == Some(1))
            .collect();
        let lss = info.get("LSS_Supported").and_then(parse_int).unwrap_or(0) == 1;
        // CiA 305 bit timing table 0 index of each rate.
        let lss_bit_timing: Vec<u8> = bitrates
            .iter()
            .map(|r| match r {
                1000 => 0,
                800 => 1,
                500 => 2,
                250 => 3,
                125 => 4,
                50 => 6,
                20 => 7,
                _ => 8,
            })
            .collect();

        let (mut node_id, mut bitrate) = (None, None);
        if let Some(c) = ini.section("DeviceComissioning") {
            if dcf {
                if let Some(k) = c.key("NodeID") {
                    let v = self.num(k)?;
                    if !(1..=127).contains(&v) {
                        return Err(self.err(k.line, format!("NodeID {v} is not 1…127")));
                    }
                    node_id = Some(v as u8);
                }
                if let Some(k) = c.key("Baudrate") {
                    let v = self.num(k)?;
                    if ![10, 20, 50, 100, 125, 250, 500, 800, 1000].contains(&v) {
                        return Err(self.err(
                            k.line,
                            format!("Baudrate {v} is not a CAN bit rate in kbit/s"),
                        ));
                    }
                    bitrate = Some(v as u16);
                }
            } else {
                self.warnings.push(format!(
                    "[DeviceComissioning] (line {}) ignored in an EDS (use --dcf)",
                    c.line
                ));
            }
        }
        let node_id = o.node_id.or(node_id).unwrap_or(DEFAULT_NODE_ID);
        let bitrate = o.bitrate_kbps.or(bitrate).unwrap_or(
            if bitrates.is_empty() || bitrates.contains(&DEFAULT_BITRATE) {
                DEFAULT_BITRATE
            } else {
                bitrates[0]
            },
        );

        let value = |i: u16, s: u8| {
            entries
                .iter()
                .find(|e| e.index == i && e.sub == s)
                .and_then(|e| match e.default {
                    DefaultValue::Const(v) => Some(v),
                    _ => None,
                })
        };
        let vendor_id = value(0x1018, 1).unwrap_or(0);
        let product_code = value(0x1018, 2).unwrap_or(0);
        let mut serial = value(0x1018, 4).unwrap_or(0);
        if let Some(s) = o.serial {
            match entries.iter_mut().find(|e| e.index == 0x1018 && e.sub == 4) {
                Some(e) => e.default = DefaultValue::Const(s),
                None => self.warnings.push(
                    "--serial: the file has no 0x1018 sub 4; only names the state file".into(),
                ),
            }
            serial = s;
        }

        // Tag: fixed high bits apart from the three sensor models (1…3), low bits from the
        // identity and the layout, so an image of another EDS device is not loaded.
        let mut layout = Vec::with_capacity(8 + entries.len() * 6);
        layout.extend_from_slice(&vendor_id.to_le_bytes());
        layout.extend_from_slice(&product_code.to_le_bytes());
        for e in &entries {
            layout.extend_from_slice(&e.key().to_le_bytes());
            layout.push(e.ty.code() as u8);
            layout.push(e.access as u8);
        }
        let tag = TAG_BASE | (crc32(&layout) & 0x3F) as u8;

        let features = Features {
            tag,
            tpdos: tpdo_objects as u8,
            rpdos: rpdo_objects as u8,
            sdo_segmented: true,
            sdo_block: true,
            node_guarding: objects.contains_key(&0x100C) && objects.contains_key(&0x100D),
            tpdo_rtr: true,
            lss_fastscan: lss,
            lss_bit_timing: Box::leak(lss_bit_timing.into_boxed_slice()),
            bitrates: Box::leak(bitrates.into_boxed_slice()),
            store_preop_only: false,
            kill_signature: false,
            power_on_emcy: false,
            sync_length_emcy: true,
            event_timer_above_inhibit: false,
            lss_unconfigured_configures: false,
            // CiA 301: the error reset once no error is left.
            emcy_on_register_change: false,
        };
        let vendor = leak(info.get("VendorName").unwrap_or(""));
        let product = leak(info.get("ProductName").unwrap_or(""));
        let table: &'static [Entry] = Box::leak(entries.into_boxed_slice());
        let keys: &'static [u32] = Box::leak(table.iter().map(Entry::key).collect());
        let model: &'static Model = Box::leak(Box::new(Model {
            table: Table {
                name: "eds",
                product,
                vendor,
                entries: table,
                keys,
                features,
            },
            profile: (),
            param,
            derive: |c| c,
            variant: None,
            default_config: CommConfig {
                node_id,
                bitrate_kbps: bitrate,
                serial,
            },
        }));
        // On the table as served (a leak of a refused file's table is a few KiB, once).
        self.check_pdo_comm(model, &value_lines)?;
        Ok(EdsDevice {
            model,
            cfg: model.default_config,
            warnings: self.warnings,
            vendor_id,
            product_code,
        })
    }

    /// One VAR (an object or a sub-index) as an [`Entry`].
    fn var(
        &mut self,
        sec: &Section,
        index: u16,
        sub: u8,
        dcf: bool,
        value_lines: &mut BTreeMap<u32, usize>,
    ) -> Result<Entry, EdsError> {
        let need = |k: &str| {
            sec.key(k)
                .ok_or_else(|| self.err(sec.line, format!("[{}] has no {k}", sec.name)))
        };
        let name = need("ParameterName")?;
        let dt = need("DataType")?;
        let ty = data_type(self.num(dt)?).map_err(|m| self.err(dt.line, m))?;
        let acc = need("AccessType")?;
        let access = access(&acc.value).ok_or_else(|| {
            self.err(
                acc.line,
                format!(
                    "AccessType `{}` is not ro, wo, rw, rwr, rww or const",
                    acc.value
                ),
            )
        })?;
        let pdo = match sec.key("PDOMapping") {
            Some(k) => match self.num(k)? {
                0 => false,
                1 => true,
                _ => return Err(self.err(k.line, "PDOMapping is 0 or 1")),
            },
            None => false,
        };
        let std = standard(index, sub);
        if let Some(s) = std {
            if s.ty != ty {
                return Err(self.err(
                    dt.line,
                    format!(
                        "0x{index:04X} sub {sub} must be {:?} (CiA 301), not {:?}",
                        s.ty, ty
                    ),
                ));
            }
        }
        for (maps, what) in [(0x1A00..=0x1BFF, "TPDO"), (0x1600..=0x17FF, "RPDO")] {
            if maps.contains(&index) && std.is_none() {
                return Err(self.err(
                    sec.line,
                    format!(
                        "[{}]: canpos-stack maps at most {} objects per {what}",
                        sec.name,
                        pdo::MAX_MAP
                    ),
                ));
            }
        }
        if index == 0x1016 && std.is_none() {
            return Err(self.err(
                sec.line,
                format!(
                    "[{}]: canpos-stack consumes at most {MAX_HB_CONSUMERS} heartbeats \
                     (0x1016 sub 1…{MAX_HB_CONSUMERS})",
                    sec.name
                ),
            ));
        }
        let hook = cia301::hook_of(index, sub);

        let pv = sec.key("ParameterValue");
        if pv.is_some() && !dcf {
            self.warnings.push(format!(
                "[{}]: ParameterValue ignored in an EDS (use --dcf)",
                sec.name
            ));
        }
        let val = if dcf { pv } else { None }.or_else(|| sec.key("DefaultValue"));
        let val = val.filter(|k| !k.value.is_empty());

        if ty == DataType::VisibleString {
            if access.writable() {
                return Err(self.err(
                    acc.line,
                    format!(
                        "[{}]: a writable VISIBLE_STRING is not supported by canpos-stack \
                         (ro / const only)",
                        sec.name
                    ),
                ));
            }
            if pdo {
                return Err(self.err(
                    sec.line,
                    format!("[{}]: a string cannot be mapped", sec.name),
                ));
            }
            let s = val.map_or("", |k| k.value.as_str());
            if s.len() > 64 {
                return Err(self.err(
                    val.map_or(sec.line, |k| k.line),
                    "a string of more than 64 bytes is not supported by canpos-stack",
                ));
            }
            return Ok(Entry {
                index,
                sub,
                name: leak(&name.value),
                ty,
                access,
                pdo: false,
                default: DefaultValue::Str(Box::leak(Box::new(leak(s)))),
                range: &Range::Any,
                group: Group::Volatile,
                hook,
            });
        }

        let limit = |key: &str| -> Result<Option<i64>, EdsError> {
            let Some(k) = sec.key(key).filter(|k| !k.value.is_empty()) else {
                return Ok(None);
            };
            let v = self.num(k)?;
            let raw = raw_of(ty, v, &k.value).ok_or_else(|| {
                self.err(
                    k.line,
                    format!("{key} {} is outside the range of {ty:?}", k.value),
                )
            })?;
            Ok(Some(ty.to_i64(raw)))
        };
        let (lo, hi) = (limit("LowLimit")?, limit("HighLimit")?);
        let range = match (lo, hi) {
            (None, None) if index == 0x1003 && sub == 0 => Range::MinMax(0, 0),
            (None, None) => Range::Any,
            (lo, hi) => {
                let (nlo, nhi) = ty.natural_range();
                let (lo, hi) = (lo.unwrap_or(nlo), hi.unwrap_or(nhi));
                if lo > hi {
                    return Err(self.err(
                        sec.key("HighLimit").map_or(sec.line, |k| k.line),
                        format!("HighLimit {hi} is below LowLimit {lo}"),
                    ));
                }
                Range::between(lo, hi)
            }
        };

        let default = match val {
            None => DefaultValue::Const(0),
            Some(k) => {
                let (v, rel) = parse_value(&k.value).ok_or_else(|| {
                    self.err(k.line, format!("{}: `{}` is not a number", k.name, k.value))
                })?;
                if rel {
                    let base = u32::try_from(v).map_err(|_| {
                        self.err(k.line, format!("{}: offset {v} out of range", k.name))
                    })?;
                    DefaultValue::NodeId(base)
                } else {
                    let raw = raw_of(ty, v, &k.value).ok_or_else(|| {
                        self.err(
                            k.line,
                            format!("{} {} is outside the range of {ty:?}", k.name, k.value),
                        )
                    })?;
                    if let Range::MinMax(lo, hi) = range {
                        let (x, lo, hi) = (ty.to_i64(raw), ty.to_i64(lo), ty.to_i64(hi));
                        if (x < lo || x > hi) && !(index == 0x1003 && sub == 0) {
                            return Err(self.err(
                                k.line,
                                format!(
                                    "{} {} is outside LowLimit…HighLimit {lo}…{hi}",
                                    k.name, k.value
                                ),
                            ));
                        }
                    }
                    DefaultValue::Const(raw)
                }
            }
        };

        value_lines.insert(
            (index as u32) << 8 | sub as u32,
            val.map_or(sec.line, |k| k.line),
        );
        let group = match (access, hook) {
            (_, Hook::StoreParameters | Hook::RestoreDefaults | Hook::ErrorHistory) => {
                Group::Volatile
            }
            (Access::Rw, _) if (0x1000..=0x1FFF).contains(&index) => Group::Comm,
            (Access::Rw, _) if index >= 0x2000 => Group::App,
            _ => Group::Volatile,
        };
        Ok(Entry {
            index,
            sub,
            name: leak(&name.value),
            ty,
            access,
            pdo: pdo && access.readable(),
            default,
            // Leaked like the names: a device's dictionary lives as long as the process.
            range: match range {
                Range::Any => &Range::Any,
                r => Box::leak(Box::new(r)),
            },
            group,
            hook,
        })
    }
}

/// The storage image tag of every EDS device has these bits (the sensors' tags are 1…3).
pub const TAG_BASE: u8 = 0x40;

/// A plain device has no configuration-dependent defaults beyond the unit's identity.
fn param(cfg: &CommConfig, p: Param) -> u32 {
    match p {
        Param::NodeId => u32::from(cfg.node_id),
        Param::BitRateKbps => u32::from(cfg.bitrate_kbps),
        Param::SerialNumber => cfg.serial,
        _ => 0,
    }
}

/// The node of an EDS device.
pub type PlainNode<S> = canpos_stack::Node<Plain, S>;

#[cfg(test)]
mod tests;
