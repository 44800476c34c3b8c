//! A small INI / EDS (CiA 306) reader: enough to walk a device's dictionary the way the
//! conformance tool does (access type, data type, default with `$NODEID`, limits, mapping).

use std::collections::BTreeMap;

pub use canpos_host::eds_device::parse_number;
use canpos_host::eds_device::section_object;
pub use canpos_host::ini::Ini;

/// One sub-index as the EDS declares it.
#[derive(Clone, Debug)]
pub struct EdsEntry {
    /// Index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// `ParameterName`.
    pub name: String,
    /// `DataType` code (0x0007 UNSIGNED32, 0x0009 VISIBLE_STRING, …).
    pub data_type: u16,
    /// `AccessType`, lower-case.
    pub access: String,
    /// `DefaultValue` as written, if any.
    pub default: Option<String>,
    /// `PDOMapping`.
    pub pdo_mapping: bool,
    /// `LowLimit` / `HighLimit` as written.
    pub limits: (Option<String>, Option<String>),
}

impl EdsEntry {
    /// Readable by SDO.
    pub fn readable(&self) -> bool {
        self.access != "wo"
    }
    /// Writable by SDO.
    pub fn writable(&self) -> bool {
        matches!(self.access.as_str(), "rw" | "wo" | "rww" | "rwr")
    }
    /// A string type (compared as text, transferred by size).
    pub fn is_string(&self) -> bool {
        matches!(self.data_type, 0x0009 | 0x000A | 0x000B | 0x000F)
    }
    /// Size in bytes of a numeric type.
    pub fn size(&self) -> Option<usize> {
        Some(match self.data_type {
            0x0001 | 0x0002 | 0x0005 => 1,
            0x0003 | 0x0006 => 2,
            0x0004 | 0x0007 | 0x0008 => 4,
            0x0010 | 0x0016 => 3,
            0x0015 | 0x001B | 0x0011 => 8,
            _ => return None,
        })
    }
    /// Signed integer type.
    pub fn signed(&self) -> bool {
        matches!(self.data_type, 0x0002 | 0x0003 | 0x0004 | 0x0010 | 0x0015)
    }
    /// The default as the raw little-endian bits the device should hold, `$NODEID` resolved.
    pub fn default_raw(&self, node_id: u8) -> Option<u32> {
        let d = self.default.as_deref()?;
        Some(parse_number(d, node_id)? as u32)
    }
}

/// A parsed EDS: the INI plus the dictionary in index / sub-index order.
pub struct Eds {
    /// The raw INI.
    pub ini: Ini,
    /// Every sub-index the EDS declares.
    pub entries: Vec<EdsEntry>,
    /// Sub-index count each object declares (`SubNumber`; 0 for a VAR).
    pub sub_numbers: BTreeMap<u16, usize>,
}

impl Eds {
    /// Parses EDS text and collects the dictionary from the object sections.
    pub fn parse(text: &str) -> Result<Eds, String> {
        let ini = Ini::parse(text).map_err(|e| e.to_string())?;
        let mut entries = Vec::new();
        let mut sub_numbers = BTreeMap::new();
        for sec in &ini.sections {
            let name = sec.name.as_str();
            let Some((index, None)) = section_object(name) else {
                continue;
            };
            if let Some(n) = sec.get("SubNumber") {
                sub_numbers.insert(index, n.parse().map_err(|_| format!("[{name}] SubNumber"))?);
                continue;
            }
            sub_numbers.entry(index).or_insert(0);
            entries.push(var(&ini, name, index, 0)?);
        }
        for sec in &ini.sections {
            if let Some((index, Some(sub))) = section_object(&sec.name) {
                entries.push(var(&ini, &sec.name, index, sub)?);
            }
        }
        entries.sort_by_key(|e| (e.index, e.sub));
        Ok(Eds {
            ini,
            entries,
            sub_numbers,
        })
    }

    /// The entry `index`/`sub`.
    pub fn entry(&self, index: u16, sub: u8) -> Option<&EdsEntry> {
        self.entries
            .iter()
            .find(|e| e.index == index && e.sub == sub)
    }
}

fn var(ini: &Ini, sec: &str, index: u16, sub: u8) -> Result<EdsEntry, String> {
    let need = |k: &str| {
        ini.get(sec, k)
            .map(str::to_string)
            .ok_or_else(|| format!("[{sec}] has no {k}"))
    };
    let dt = need("DataType")?;
    let data_type = parse_number(&dt, 0).ok_or_else(|| format!("[{sec}] DataType {dt}"))? as u16;
    Ok(EdsEntry {
        index,
        sub,
        name: need("ParameterName")?,
        data_type,
        access: need("AccessType")?.to_ascii_lowercase(),
        default: ini.get(sec, "DefaultValue").map(str::to_string),
        pdo_mapping: ini.get(sec, "PDOMapping").is_some_and(|v| v == "1"),
        limits: (
            ini.get(sec, "LowLimit").map(str::to_string),
            ini.get(sec, "HighLimit").map(str::to_string),
        ),
    })
}

/// The EDS `canpos_stack` exports for `model`'s default unit.
pub fn export(model: &'static canpos_models::Model) -> String {
    let mut s = String::new();
    canpos_stack::eds::write_eds(
        &mut s,
        model,
        &model.default_config,
        &canpos_stack::eds::EdsInfo::default(),
    )
    .expect("EDS export");
    s
}
