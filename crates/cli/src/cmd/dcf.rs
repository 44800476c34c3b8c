//! DCF (CiA 306 device configuration file) of a configured canpos sensor: `canpos dcf` writes
//! one from a running node over SDO, `canpos run --dcf FILE` starts a unit from one
//! (docs/FILES.md "DCF").
//!
//! A DCF is a canpos model's when its `[DeviceInfo]` `ProductName` is a model's product and its
//! `VendorNumber` that model's vendor-id; any other DCF is served as a plain CiA 301 device
//! (docs/EDS_DEVICE.md).

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use anyhow::{anyhow, bail, Context, Result};
use canpos_host::ini::Ini;
use canpos_host::FileStorage;
use canpos_models::SensorNode;
use canpos_models::{self as models, DeviceConfig, Model};
use canpos_stack::eds::{Commissioning, DcfValue, EdsInfo};
use canpos_stack::od::{DataType, DefaultValue, Entry};
use canpos_stack::sdo::wire::{Mux, Request, Response};
use canpos_stack::storage::{Storage, StorageError, IMAGE_MAX};
use canpos_stack::{cob, Frame, Instant, Node};
use clap::Args;

use crate::client::{SdoClient, SdoError};
use crate::common::{open_bus, BusArg, Usage};

/// `canpos dcf`: write the DCF of a configured unit, read from the running node over SDO or
/// from its state file.
#[derive(Args, Debug, Clone)]
pub struct DcfArgs {
    /// Node-id of the running unit (1…127), read over SDO on --bus. With --state: the node-id
    /// the unit is started with (`run --node-id`; a stored LSS node-id wins).
    #[arg(long, required_unless_present = "state")]
    pub node: Option<u8>,
    /// The unit's state file (`MODEL-SERIAL.bin` in its --state-dir): the unit as it starts
    /// from it (stored values, stored LSS node-id and bit rate).
    #[arg(long, value_name = "FILE")]
    pub state: Option<PathBuf>,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
    /// Model (th, e-series, tmi); default: from the state file's name, or recognised over SDO
    /// from 0x1008 and 0x1018/1.
    #[arg(long, conflicts_with = "order_code")]
    pub model: Option<String>,
    /// The unit's order code: its model, the defaults of its variant, `OrderCode`.
    #[arg(long, value_name = "CODE")]
    pub order_code: Option<String>,
    /// The bit rate in kbit/s for `[DeviceComissioning]` when read over SDO (no object holds
    /// it; default: the order code's, else the model's). A state file gives its own.
    #[arg(long, value_name = "KBPS")]
    pub bitrate: Option<u16>,
    /// Output file (default: standard output).
    #[arg(long, short = 'o')]
    pub output: Option<PathBuf>,
    /// Time to wait for each SDO answer, in ms.
    #[arg(long, default_value_t = 1000, value_name = "MS")]
    pub timeout: u64,
}

/// Values read from a unit: index, sub, bytes.
type Values = Vec<(u16, u8, Vec<u8>)>;

/// The model and serial a state file's name (`MODEL-SERIAL.bin`) gives.
fn parse_state_name(p: &Path) -> Option<(&'static Model, u32)> {
    let stem = p.file_stem()?.to_str()?;
    let (model, serial) = stem.rsplit_once('-')?;
    Some((models::by_name(model)?, serial.parse().ok()?))
}

/// The configuration of the unit whose state file `path` is, when only its model is known:
/// the model's default unit, or its widest when the file holds a record that only the widest
/// has (the TMI's one- and two-channel units share `tmi-SERIAL.bin`; a two-channel unit's
/// "save" stores its channel-2 objects), so that a DCF leaves none of its configuration out.
fn state_unit(path: &Path, model: &'static Model) -> DeviceConfig {
    let cfg = model.default_config;
    let (narrow, widest) = (models::for_unit(model, &cfg), models::widest(model));
    if core::ptr::eq(narrow, widest) {
        return cfg;
    }
    let mut image = [0u8; IMAGE_MAX];
    let Ok(n) = FileStorage::new(path).for_model(model).load(&mut image) else {
        // read_state reports the file.
        return cfg;
    };
    let Ok(mut recs) = canpos_stack::storage::parse_image(&image[..n], model.features.tag) else {
        return cfg;
    };
    let wider = recs.any(|(k, _)| {
        canpos_stack::storage::is_object_key(k)
            && widest.search(k).is_ok()
            && narrow.search(k).is_err()
    });
    if wider {
        widest.default_config
    } else {
        cfg
    }
}

/// Reads the unit from its state file: the node runs in-process on it (nothing is written).
fn read_state(
    path: &Path,
    model: &'static Model,
    mut cfg: DeviceConfig,
) -> Result<(DeviceConfig, Values)> {
    // The file is loaded once before the node does it, so that one that cannot be used (a
    // link, a FIFO, a failed check) is an error here, not a DCF of the defaults.
    let mut probe = FileStorage::new(path).for_model(model);
    let mut image = [0u8; IMAGE_MAX];
    match probe.load(&mut image) {
        Ok(_) => {}
        Err(StorageError::Empty) => bail!("{}: no such state file", path.display()),
        Err(_) => bail!(
            "{}: not a usable state file: {}",
            path.display(),
            probe.problem().unwrap_or("it cannot be read")
        ),
    }
    // Unlocked: the unit may be running on it; this node only reads (it stores nothing unless
    // told by 0x1010, which nobody sends it).
    let mut node = SensorNode::new(model, cfg, FileStorage::new(path).for_model(model));
    node.power_on(Instant::ZERO);
    cfg.node_id = node.device().node_id();
    cfg.bitrate_kbps = node.device().bitrate();
    let mut values = Vec::new();
    // Measurements (positions, speeds, states) have no value without a magnet: left out.
    for e in node
        .device()
        .model()
        .entries
        .iter()
        .filter(|e| e.access.readable() && e.default != DefaultValue::Live)
    {
        let bytes = match (e.ty.size(), e.default) {
            (Some(n), _) => match node.read_object(e.index, e.sub) {
                Ok(raw) => raw.to_le_bytes()[..n].to_vec(),
                Err(_) => continue,
            },
            (None, DefaultValue::Str(s)) => s.as_bytes().to_vec(),
            (None, _) => continue,
        };
        values.push((e.index, e.sub, bytes));
    }
    Ok((cfg, values))
}

/// Writes the DCF of a unit read over SDO or from its state file.
pub fn dcf(a: DcfArgs) -> Result<i32> {
    let (model, mut cfg, order_code, values) = if let Some(state) = &a.state {
        let (model, mut cfg, code) = match (&a.model, &a.order_code, parse_state_name(state)) {
            (None, None, Some((m, _))) => (m, state_unit(state, m), String::new()),
            (None, None, None) => {
                return Err(anyhow::Error::new(Usage(format!(
                    "{}: not named MODEL-SERIAL.bin; give --model or --order-code",
                    state.display()
                ))))
            }
            (m, code, _) => crate::sensor::export_unit(m.as_deref(), code.as_deref())?,
        };
        if let Some((_, serial)) = parse_state_name(state) {
            cfg.serial = serial;
        }
        if let Some(n) = a.node {
            cfg.node_id = n;
        }
        let (cfg, values) = read_state(state, model, cfg)?;
        (model, cfg, code, values)
    } else {
        let node = a.node.unwrap_or(0);
        if !(1..=127).contains(&node) {
            return Err(anyhow::Error::new(Usage(format!(
                "node-id {node} out of range 1..=127"
            ))));
        }
        let mut bus = open_bus(&a.bus.bus)?;
        let mut c = SdoClient::new(&mut *bus, node, Duration::from_millis(a.timeout));
        let (model, mut cfg, code) = match (&a.model, &a.order_code) {
            (None, None) => {
                let m = recognise(&mut c)?;
                (m, m.default_config, String::new())
            }
            (m, code) => crate::sensor::export_unit(m.as_deref(), code.as_deref())?,
        };
        cfg.node_id = node;
        if let Some(b) = a.bitrate {
            cfg.bitrate_kbps = b;
        }
        let mut values: Vec<(u16, u8, Vec<u8>)> = Vec::new();
        // Every object the model's units may have (a one-channel TMI refuses channel 2).
        for e in models::widest(model)
            .entries
            .iter()
            .filter(|e| e.access.readable())
        {
            match c.upload(e.index, e.sub) {
                Ok(d) => values.push((e.index, e.sub, d)),
                // Refused (e.g. an object this unit's variant lacks): no ParameterValue.
                Err(SdoError::Abort(_)) => {}
                Err(err) => bail!("reading 0x{:04X}/{}: {err}", e.index, e.sub),
            }
        }
        (model, unit_of_reads(model, cfg, &values), code, values)
    };
    if let Some(serial) = values
        .iter()
        .find(|(i, s, _)| *i == 0x1018 && *s == 4)
        .and_then(|(_, _, d)| d.get(..4)?.try_into().ok())
        .map(u32::from_le_bytes)
    {
        cfg.serial = serial;
    }
    let text = render(model, &cfg, &order_code, a.output.as_deref(), &values)?;
    match &a.output {
        Some(p) => std::fs::write(p, text).with_context(|| format!("writing {}", p.display()))?,
        None => {
            use std::io::Write as _;
            std::io::stdout().write_all(text.as_bytes())?;
        }
    }
    Ok(0)
}

/// The model whose device name (0x1008) and vendor-id (0x1018/1) the unit reports.
fn recognise(c: &mut SdoClient<'_>) -> Result<&'static Model> {
    let name = c
        .upload(0x1008, 0)
        .map_err(|e| anyhow!("reading 0x1008: {e}"))?;
    let vendor = c
        .upload(0x1018, 1)
        .map_err(|e| anyhow!("reading 0x1018/1: {e}"))?;
    let vendor = u32::from_le_bytes(
        vendor
            .get(..4)
            .and_then(|b| b.try_into().ok())
            .unwrap_or([0; 4]),
    );
    models::all()
        .iter()
        .find(|m| {
            let named = m.entries.iter().any(|e| {
                e.index == 0x1008 && matches!(e.default, DefaultValue::Str(s) if s.as_bytes() == name)
            });
            named && model_vendor(m) == vendor
        })
        .copied()
        .ok_or_else(|| {
            anyhow!(
                "node reports 0x1008 `{}` and vendor-id 0x{vendor:08X}: not a canpos model (give --model)",
                String::from_utf8_lossy(&name)
            )
        })
}

/// The unit `cfg` of `model` as its objects read over SDO (`values`) show it: a unit whose
/// configuration has a dictionary of its own (TMI, 002 §1.6) has the channels it answered
/// for. (`canpos dcf --node` and the dashboard's DCF export.)
pub(crate) fn unit_of_reads(
    model: &'static Model,
    mut cfg: DeviceConfig,
    values: &[(u16, u8, Vec<u8>)],
) -> DeviceConfig {
    if !std::ptr::eq(models::for_unit(model, &cfg), models::widest(model)) {
        let channels = values.iter().filter(|v| v.0 == 0x6020 && v.1 > 0).count();
        if channels > 0 {
            cfg.channels = channels as u8;
        }
    }
    if let Some(serial) = values
        .iter()
        .find(|(i, s, _)| *i == 0x1018 && *s == 4)
        .and_then(|(_, _, d)| d.get(..4)?.try_into().ok())
        .map(u32::from_le_bytes)
    {
        cfg.serial = serial;
    }
    cfg
}

fn model_vendor(m: &Model) -> u32 {
    m.entries
        .iter()
        .find(|e| e.index == 0x1018 && e.sub == 1)
        .and_then(|e| match e.default {
            DefaultValue::Const(v) => Some(v),
            _ => None,
        })
        .unwrap_or(0)
}

fn numeric(ty: DataType) -> bool {
    ty.size().is_some()
}

/// The DCF text of `model` for unit `cfg` with the read `values`.
pub(crate) fn render(
    model: &'static Model,
    cfg: &DeviceConfig,
    order_code: &str,
    output: Option<&Path>,
    values: &[(u16, u8, Vec<u8>)],
) -> Result<String> {
    let file_name = output
        .and_then(|p| p.file_name())
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| format!("canpos-{}-{}.dcf", model.name, cfg.node_id));
    let last_eds = if order_code.is_empty() {
        format!("canpos-{}.eds", model.name)
    } else {
        format!("{order_code}.eds")
    };
    let (date, time) = crate::capture::eds_date_time(SystemTime::now());
    let info = EdsInfo {
        file_name: &file_name,
        date: &date,
        time: &time,
        order_code,
        ..Default::default()
    };
    let node_name = format!("{} {}", model.name, cfg.serial);
    let comm = Commissioning {
        node_id: cfg.node_id,
        node_name: &node_name,
        bitrate_kbps: cfg.bitrate_kbps,
        net_number: 0,
        network_name: "canpos",
        lss_serial: cfg.serial,
        last_eds: &last_eds,
    };
    // The unit's own dictionary (a two-channel TMI's has its channel-2 objects).
    let unit = models::for_unit(model, cfg);
    let lookup = |index: u16, sub: u8| -> Option<DcfValue<'_>> {
        let e = unit
            .entries
            .iter()
            .find(|e| e.index == index && e.sub == sub)?;
        let (_, _, d) = values.iter().find(|(i, s, _)| *i == index && *s == sub)?;
        if numeric(e.ty) {
            let mut b = [0u8; 4];
            let n = d.len().min(4);
            b[..n].copy_from_slice(&d[..n]);
            Some(DcfValue::Number(u32::from_le_bytes(b)))
        } else {
            Some(DcfValue::Bytes(d))
        }
    };
    let mut text = String::new();
    canpos_stack::eds::write_dcf(&mut text, model, cfg, &info, &comm, &lookup)
        .map_err(|_| anyhow!("formatting the DCF failed"))?;
    Ok(text)
}

/// A canpos model's DCF, as `canpos run --dcf` reads it.
#[derive(Debug)]
pub struct ModelDcf {
    /// The model.
    pub model: &'static Model,
    /// `OrderCode` (empty: the model's default unit).
    pub order_code: String,
    /// `[DeviceComissioning]` NodeID.
    pub node_id: Option<u8>,
    /// `[DeviceComissioning]` Baudrate (kbit/s).
    pub bitrate_kbps: Option<u16>,
    /// `LSS_SerialNumber`, else the `ParameterValue` of 0x1018/4.
    pub serial: Option<u32>,
    /// Each `ParameterValue` of a writable object: index, sub, raw value, line.
    pub values: Vec<(u16, u8, u32, usize)>,
    /// Without an `OrderCode`: the position channels of the unit the file's objects name, when
    /// it names an object the model's default unit does not have (a two-channel TMI's
    /// channel-2 objects); `None`: the default unit's.
    pub channels: Option<u8>,
}

fn parse_num(s: &str) -> Option<i64> {
    let s = s.trim();
    let (neg, s) = match s.strip_prefix('-') {
        Some(r) => (true, r),
        None => (false, s),
    };
    let v = match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => i64::from_str_radix(h, 16).ok()?,
        None => s.parse().ok()?,
    };
    Some(if neg { -v } else { v })
}

/// Reads `path` as a canpos model's DCF; `Ok(None)` when it is not one (another device's DCF,
/// served as a plain device). Errors name the file and line.
pub fn read_model_dcf(path: &Path) -> Result<Option<ModelDcf>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let ini = Ini::parse(&text).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    let product = ini.get("DeviceInfo", "ProductName").unwrap_or("");
    let vendor = ini.get("DeviceInfo", "VendorNumber").and_then(parse_num);
    let Some(model) = models::all()
        .iter()
        .find(|m| m.product == product && vendor == Some(model_vendor(m) as i64))
        .copied()
    else {
        return Ok(None);
    };
    // Every object the model's units may have: the file says which of them this one has.
    let (base, model) = (model, models::widest(model));
    let at = |sec: &str, key: &str| {
        ini.section(sec)
            .and_then(|s| s.key(key))
            .map(|k| k.line)
            .unwrap_or(0)
    };
    let bad = |sec: &str, key: &str, why: &str| {
        anyhow!("{}:{}: [{sec}] {key}: {why}", path.display(), at(sec, key))
    };
    let order_code = ini
        .get("DeviceInfo", "OrderCode")
        .unwrap_or("")
        .trim()
        .to_string();
    let node_id = match ini.get("DeviceComissioning", "NodeID") {
        None => None,
        Some(v) => Some(
            parse_num(v)
                .filter(|n| (1..=127).contains(n))
                .ok_or_else(|| bad("DeviceComissioning", "NodeID", "not a node-id 1…127"))?
                as u8,
        ),
    };
    let bitrate_kbps = match ini.get("DeviceComissioning", "Baudrate") {
        None => None,
        Some(v) => Some(
            parse_num(v)
                .filter(|n| model.features.bitrates.contains(&(*n as u16)) && *n > 0 && *n <= 1000)
                .ok_or_else(|| {
                    bad(
                        "DeviceComissioning",
                        "Baudrate",
                        "not a bit rate of this model",
                    )
                })? as u16,
        ),
    };
    let mut values = Vec::new();
    // A serial number is an UNSIGNED32 (0x1018/4): anything else is an error at its line, as a
    // bad NodeID is (it names the state file: a wrong one would start another unit's state).
    let serial_of = |v: &str, sec: &str, key: &str| {
        parse_num(v)
            .filter(|n| (0..=i64::from(u32::MAX)).contains(n))
            .map(|n| n as u32)
            .ok_or_else(|| bad(sec, key, "not a serial number (0…0xFFFFFFFF)"))
    };
    let mut serial = match ini.get("DeviceComissioning", "LSS_SerialNumber") {
        None => None,
        Some(v) => Some(serial_of(v, "DeviceComissioning", "LSS_SerialNumber")?),
    };
    for e in model.entries {
        let sec = section_name(e, model);
        let Some(v) = ini.get(&sec, "ParameterValue") else {
            continue;
        };
        if e.index == 0x1018 && e.sub == 4 {
            let v = serial_of(v, &sec, "ParameterValue")?;
            serial.get_or_insert(v);
        }
        if !writable_config(e) {
            continue;
        }
        let n = parse_num(v)
            .filter(|&n| fits(e.ty, n))
            .ok_or_else(|| bad(&sec, "ParameterValue", "not a value of the object's type"))?;
        values.push((e.index, e.sub, n as u32, at(&sec, "ParameterValue")));
    }
    // The unit: the default one, unless the file configures an object only a wider unit has.
    let narrow = models::for_unit(base, &base.default_config);
    let wider = !core::ptr::eq(narrow, model)
        && values
            .iter()
            .any(|&(i, s, _, _)| narrow.search(u32::from(i) << 8 | u32::from(s)).is_err());
    let channels = (order_code.is_empty() && wider).then_some(model.default_config.channels);
    Ok(Some(ModelDcf {
        model,
        order_code,
        node_id,
        bitrate_kbps,
        serial,
        values,
        channels,
    }))
}

/// `[1800sub1]`, or `[1000]` for an object that is sub 0 alone.
fn section_name(e: &Entry, model: &Model) -> String {
    let alone = model.entries.iter().filter(|x| x.index == e.index).count() == 1 && e.sub == 0;
    if alone {
        format!("{:04X}", e.index)
    } else {
        format!("{:04X}sub{:X}", e.index, e.sub)
    }
}

/// Objects a DCF configures: writable, numeric, not device-produced (mappable), not the
/// store / restore commands.
fn writable_config(e: &Entry) -> bool {
    e.access.writable() && !e.pdo && numeric(e.ty) && !matches!(e.index, 0x1010 | 0x1011)
}

fn fits(ty: DataType, n: i64) -> bool {
    let bits = 8 * ty.size().unwrap_or(4) as u32;
    if ty.is_signed() {
        let half = 1i64 << (bits - 1);
        (-half..half).contains(&n)
    } else {
        (0..(1i64 << bits)).contains(&n)
    }
}

/// Downloads the DCF's values into the unit's state file and stores them (0x1010/1 "save"),
/// as a master's DCF download and store does: the node is run in-process on the state file,
/// the values go in by SDO in an order the PDO rules accept (a PDO's mapping is written with
/// the PDO disabled and sub 0 at 0, then enabled). Returns the objects the unit refused
/// (`index, sub, line, abort`), which keep their previous values.
pub fn apply_to_state(
    dcf: &ModelDcf,
    cfg: DeviceConfig,
    state: &Path,
) -> Result<Vec<(u16, u8, usize, String)>> {
    let storage = FileStorage::open(state)
        .with_context(|| format!("cannot open {}", state.display()))?
        .for_model(dcf.model);
    let mut node = SensorNode::new(dcf.model, cfg, storage);
    let mut now = Instant::ZERO;
    node.power_on(now);
    while node.poll(now).is_some() {}
    let id = node.device().node_id();
    if !(1..=127).contains(&id) {
        bail!("the unit has no node-id (255): give the DCF a [DeviceComissioning] NodeID");
    }
    let mut refused = Vec::new();
    let mut write = |node: &mut Node<_, _>, index: u16, sub: u8, raw: u32, size: usize| {
        let req = Request::DownloadInitiate {
            mux: Mux { index, sub },
            expedited: true,
            size: Some(size.clamp(1, 4) as u32),
            data: raw.to_le_bytes(),
        }
        .emit();
        now += canpos_stack::Duration::from_millis(1);
        node.handle_frame(&Frame::std8(cob::SDO_RX + id as u16, req), now);
        let mut answer = None;
        // A store may answer later (a held SDO): let the node's time run until it does.
        for _ in 0..1000 {
            while let Some(f) = node.poll(now) {
                if f.std_id() == Some(cob::SDO_TX + id as u16) {
                    answer = Some(*f.raw());
                }
            }
            if answer.is_some() {
                break;
            }
            now += canpos_stack::Duration::from_millis(10);
        }
        match answer.map(|a| Response::parse(&a)) {
            Some(Response::DownloadInitiate { .. }) => Ok(()),
            Some(Response::Abort { code, .. }) => Err(format!("SDO abort 0x{code:08X}")),
            _ => Err("no SDO answer".to_string()),
        }
    };
    let size_of = |i: u16, s: u8| {
        dcf.model
            .entries
            .iter()
            .find(|e| e.index == i && e.sub == s)
            .and_then(|e| e.ty.size())
            .unwrap_or(4)
    };
    let value = |i: u16, s: u8| dcf.values.iter().find(|v| v.0 == i && v.1 == s);
    // PDO parameters: disable each PDO, clear its mapping, write it, then the rest.
    let pdos: Vec<u16> = dcf
        .values
        .iter()
        .filter(|v| (0x1A00..0x1C00).contains(&v.0) || (0x1600..0x1800).contains(&v.0))
        .map(|v| v.0)
        .fold(Vec::new(), |mut acc, i| {
            if !acc.contains(&i) {
                acc.push(i);
            }
            acc
        });
    for &map in &pdos {
        let comm = map - 0x200;
        let cob = read(&mut node, comm, 1).unwrap_or(0);
        let _ = write(&mut node, comm, 1, cob | 0x8000_0000, 4);
        let _ = write(&mut node, map, 0, 0, 1);
    }
    let mut done = Vec::new();
    for &(i, s, raw, line) in &dcf.values {
        let is_map = pdos.contains(&i);
        let is_comm_cob = s == 1 && pdos.contains(&(i + 0x200));
        if (is_map && s == 0) || is_comm_cob {
            continue; // written below, after the entries
        }
        if let Err(why) = write(&mut node, i, s, raw, size_of(i, s)) {
            refused.push((i, s, line, why));
        }
        done.push((i, s));
    }
    for &map in &pdos {
        if let Some(&(i, s, raw, line)) = value(map, 0) {
            if let Err(why) = write(&mut node, i, s, raw, 1) {
                refused.push((i, s, line, why));
            }
        }
        let comm = map - 0x200;
        if let Some(&(i, s, raw, line)) = value(comm, 1) {
            if let Err(why) = write(&mut node, i, s, raw, 4) {
                refused.push((i, s, line, why));
            }
        }
    }
    // 0x1010/1 "save": the values survive the start that follows.
    write(&mut node, 0x1010, 1, u32::from_le_bytes(*b"save"), 4)
        .map_err(|why| anyhow!("storing the DCF's values: {why}"))?;
    Ok(refused)
}

fn read<A: canpos_stack::Application, S: canpos_stack::Storage>(
    node: &mut Node<A, S>,
    index: u16,
    sub: u8,
) -> Option<u32> {
    node.read_object(index, sub).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `canpos dcf --state tmi-SERIAL.bin` of a two-channel TMI (no order code given) has its
    /// channel-2 configuration; a one-channel unit's file gives the one-channel unit.
    #[test]
    fn a_two_channel_tmi_state_file_gives_a_dcf_with_channel_2() {
        let tmi = models::by_name("tmi").unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tmi-9050001.bin");
        let write = |recs: &[(u32, u32)]| {
            let mut buf = [0u8; IMAGE_MAX];
            let mut w = canpos_stack::storage::ImageWriter::new(&mut buf, tmi.features.tag);
            for &(k, v) in recs {
                assert!(w.push(k, v));
            }
            let n = w.finish();
            std::fs::write(&path, &buf[..n]).unwrap();
        };
        // Cam 1 low limit, channel 1 and 2 (0x6310:1 / :2), as a two-channel unit saves them.
        write(&[(0x0063_1001, 111), (0x0063_1002, 1234)]);
        let cfg = state_unit(&path, tmi);
        assert_eq!(cfg.channels, 2);
        let (_, values) = read_state(&path, tmi, cfg).unwrap();
        let val = |i: u16, s: u8| {
            values
                .iter()
                .find(|x| x.0 == i && x.1 == s)
                .map(|x| x.2.clone())
        };
        assert_eq!(val(0x6310, 2), Some(1234i32.to_le_bytes().to_vec()));
        assert_eq!(val(0x6310, 1), Some(111i32.to_le_bytes().to_vec()));
        // Its DCF (no OrderCode: none is known) starts a two-channel unit with `run --dcf`,
        // which takes the channel-2 value.
        let text = render(tmi, &cfg, "", None, &values).unwrap();
        let dcf = dir.path().join("unit.dcf");
        std::fs::write(&dcf, &text).unwrap();
        let d = read_model_dcf(&dcf).unwrap().unwrap();
        assert_eq!(d.channels, Some(2));
        let opts = crate::sensor::SensorOpts {
            model: Some("tmi".into()),
            unit_channels: d.channels,
            ..Default::default()
        };
        let built = crate::sensor::build_setup(&opts, dir.path()).unwrap();
        assert_eq!(built.setup.cfg.channels, 2);
        let fresh = dir.path().join("fresh.bin");
        let refused = apply_to_state(&d, built.setup.cfg, &fresh).unwrap();
        assert!(refused.is_empty(), "{refused:?}");
        let (_, got) = read_state(&fresh, tmi, built.setup.cfg).unwrap();
        let got = |i: u16, s: u8| {
            got.iter()
                .find(|x| x.0 == i && x.1 == s)
                .map(|x| x.2.clone())
        };
        assert_eq!(got(0x6310, 2), Some(1234i32.to_le_bytes().to_vec()));
        write(&[(0x0063_1001, 111)]);
        assert_eq!(state_unit(&path, tmi).channels, 1);
        let one = state_unit(&path, tmi);
        let (_, values) = read_state(&path, tmi, one).unwrap();
        let text = render(tmi, &one, "", None, &values).unwrap();
        std::fs::write(&dcf, &text).unwrap();
        assert_eq!(read_model_dcf(&dcf).unwrap().unwrap().channels, None);
    }

    fn tempdir() -> PathBuf {
        static N: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let d = std::env::temp_dir().join(format!("canpos-dcf-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// A TH DCF with a heartbeat and TPDO1 remapped to one object: read back, downloaded into
    /// a state file, and the unit started from that file has the values.
    #[test]
    fn a_model_dcf_goes_into_the_state_file() {
        let th = models::by_name("th").unwrap();
        let dir = tempdir();
        // The unit's values (node-id 20): the defaults, with the configuration changed.
        let src = dir.join("src.bin");
        let (cfg, mut values) = read_state_or_defaults(th, &src);
        for (i, s, v) in [
            (0x1017u16, 0u8, 250u32),
            (0x1A00, 0, 1),
            (0x1A00, 1, 0x6020_0120),
            (0x1800, 5, 20),
            // 0x6200 (cyclic timer) is the same value as 0x1800/5 on a TH.
            (0x6200, 0, 20),
        ] {
            let n = th
                .entries
                .iter()
                .find(|e| e.index == i && e.sub == s)
                .unwrap()
                .ty
                .size()
                .unwrap();
            let slot = values.iter_mut().find(|x| x.0 == i && x.1 == s).unwrap();
            slot.2 = v.to_le_bytes()[..n].to_vec();
        }
        let text = render(th, &cfg.with_node_id(20), "", None, &values).unwrap();
        let path = dir.join("unit.dcf");
        std::fs::write(&path, &text).unwrap();
        let d = read_model_dcf(&path)
            .unwrap()
            .expect("a canpos model's DCF");
        assert_eq!((d.model.name, d.node_id), ("th", Some(20)));
        let state = dir.join("th-1.bin");
        let refused = apply_to_state(&d, th.default_config.with_node_id(20), &state).unwrap();
        assert!(refused.is_empty(), "{refused:?}");
        let (got_cfg, got) = read_state(&state, th, th.default_config.with_node_id(20)).unwrap();
        assert_eq!(got_cfg.node_id, 20);
        let val = |i: u16, s: u8| got.iter().find(|x| x.0 == i && x.1 == s).unwrap().2.clone();
        assert_eq!(val(0x1017, 0), 250u16.to_le_bytes());
        assert_eq!(val(0x1A00, 0), [1]);
        assert_eq!(val(0x1A00, 1), 0x6020_0120u32.to_le_bytes());
        assert_eq!(val(0x1800, 5), 20u16.to_le_bytes());
        // A malformed value is reported with its line.
        let bad = text.replacen("NodeID=0x14", "NodeID=0x99", 1);
        std::fs::write(&path, bad).unwrap();
        let e = read_model_dcf(&path).unwrap_err().to_string();
        assert!(e.contains("unit.dcf:") && e.contains("NodeID"), "{e}");
        // So is a serial number that is none (issue 35 item 10: it used to be ignored), with
        // the line of its key.
        let line_of = |t: &str, key: &str| 1 + t.lines().position(|l| l.starts_with(key)).unwrap();
        for (from, to) in [
            ("LSS_SerialNumber=0x", "LSS_SerialNumber=zz"),
            ("LSS_SerialNumber=0x", "LSS_SerialNumber=0x1"),
            ("LSS_SerialNumber=0x", "LSS_SerialNumber=-0x"),
        ] {
            let bad = text.replacen(from, to, 1);
            assert_ne!(bad, text);
            std::fs::write(&path, &bad).unwrap();
            let e = read_model_dcf(&path).unwrap_err().to_string();
            let want = format!(
                "unit.dcf:{}: [DeviceComissioning] LSS_SerialNumber: not a serial number",
                line_of(&bad, "LSS_SerialNumber=")
            );
            assert!(e.contains(&want), "{to}: {e}");
        }
        // Without LSS_SerialNumber, 0x1018/4's ParameterValue is the serial: checked alike.
        let no_lss: String = text
            .lines()
            .filter(|l| !l.starts_with("LSS_SerialNumber="))
            .map(|l| format!("{l}\n"))
            .collect();
        std::fs::write(&path, &no_lss).unwrap();
        assert_eq!(
            read_model_dcf(&path).unwrap().unwrap().serial,
            Some(th.default_config.serial)
        );
        let sec = no_lss.find("[1018sub4]").unwrap();
        let at = sec + no_lss[sec..].find("ParameterValue=").unwrap();
        let end = at + no_lss[at..].find('\n').unwrap();
        let bad = format!("{}ParameterValue=serial{}", &no_lss[..at], &no_lss[end..]);
        std::fs::write(&path, &bad).unwrap();
        let e = read_model_dcf(&path).unwrap_err().to_string();
        assert!(
            e.contains("[1018sub4] ParameterValue: not a serial number"),
            "{e}"
        );
        // Another device's DCF is none of canpos's.
        let foreign = text.replace("ProductName=", "ProductName=Other ");
        std::fs::write(&path, foreign).unwrap();
        assert!(read_model_dcf(&path).unwrap().is_none());
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn read_state_or_defaults(m: &'static Model, p: &Path) -> (DeviceConfig, Values) {
        std::fs::write(p, b"").ok();
        let _ = std::fs::remove_file(p);
        // A missing file: the unit on its defaults.
        let storage = FileStorage::new(p);
        let cfg = m.default_config.with_node_id(20);
        let mut node = SensorNode::new(m, cfg, storage);
        node.power_on(Instant::ZERO);
        let values = m
            .entries
            .iter()
            .filter(|e| e.access.readable() && e.ty.size().is_some())
            .filter_map(|e| {
                let raw = node.read_object(e.index, e.sub).ok()?;
                Some((e.index, e.sub, raw.to_le_bytes()[..e.ty.size()?].to_vec()))
            })
            .collect();
        (cfg, values)
    }
}
