//! The commissioning-master side of `canpos`: NMT, SDO, LSS, scan, monitor, EDS export and
//! candump record / replay, against any bus URL.
//!
//! Exit codes of every command (the same for the whole binary, see `main.rs`): 0 success,
//! [`EXIT_REFUSED`] the device refused (SDO abort, LSS error status) or nothing was found,
//! [`EXIT_TIMEOUT`] no answer within the timeout. Errors before anything was sent are returned
//! as `Err` for the caller to report: [`Usage`] for bad arguments, anything else (bus not
//! reachable) as a runtime error.
//!
//! The protocol pieces ([`SdoClient`], [`LssMaster`], [`decode`]) are independent of the
//! command line so that other commands (benchmarks, tests) can reuse them.

pub mod decode;
pub mod lss;
pub mod sdo;

use std::collections::{HashMap, VecDeque};
use std::fs::File;
use std::io::{self, BufRead, BufReader, BufWriter, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime};

use anyhow::{anyhow, bail, Context, Result};
use canpos_core::Frame;
use canpos_host::candump::format_line;
use canpos_host::transport::{self, BusUrl, RxFrame, Transport, DEFAULT_URL};
use clap::{Args, Subcommand, ValueEnum};

pub use lss::{Inquire, LssAddress, LssError, LssMaster, LssStatus};
pub use sdo::{SdoClient, SdoError, ValueType};

/// Exit code: success.
pub const EXIT_OK: i32 = 0;
/// Exit code: a runtime error (bus unreachable, file unreadable, bad scenario, …).
pub const EXIT_ERROR: i32 = 1;
/// Exit code: a bad command line (clap's own code for usage errors).
pub const EXIT_USAGE: i32 = 2;
/// Exit code: the device refused (SDO abort, LSS error status) or nothing was found.
pub const EXIT_REFUSED: i32 = 3;
/// Exit code: no answer in time.
pub const EXIT_TIMEOUT: i32 = 4;

/// A bad argument found after clap parsed the command line (node-id, index, value): reported
/// with [`EXIT_USAGE`], like clap's own errors.
#[derive(Debug)]
pub struct Usage(pub String);

impl std::fmt::Display for Usage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Usage {}

/// `Err(Usage(…))` as an `anyhow::Error`.
macro_rules! usage {
    ($($t:tt)*) => { anyhow::Error::new(Usage(format!($($t)*))) };
}

/// The bus option every master command takes.
#[derive(Args, Debug, Clone)]
pub struct BusArg {
    /// Bus URL: socketcand://HOST:PORT/CHANNEL, socketcan://IFACE or mem://NAME.
    #[arg(long, global = true, default_value = DEFAULT_URL, value_name = "URL")]
    pub bus: String,
}

/// Opens a master command's bus: a malformed URL is a usage error, a refused connection gets
/// the hint to start a hub or sensor.
pub fn open_bus(url: &str) -> Result<Box<dyn Transport>> {
    transport::open(url).map_err(|e| match e {
        // A malformed URL is the user's typo: no hint about hubs.
        transport::Error::BadUrl { .. } => usage!("{e}"),
        transport::Error::Connect { .. } => anyhow::Error::new(e).context(format!(
            "cannot open the bus {url} (is `canpos bus serve`, `canpos run` or a scenario running?)"
        )),
        e => anyhow::Error::new(e).context(format!("cannot open the bus {url}")),
    })
}

fn ms(v: u64) -> Duration {
    Duration::from_millis(v)
}

/// Parses a node-id: decimal or 0x-hex, within `min..=127`.
pub(crate) fn parse_node(s: &str, min: u8) -> Result<u8> {
    let v = sdo::parse_u64(s).ok_or_else(|| usage!("node-id `{s}` is not a number"))?;
    if v < min as u64 || v > 127 {
        return Err(usage!("node-id {v} out of range {min}..=127"));
    }
    Ok(v as u8)
}

/// Parses an object index: hex, with or without `0x` (`0x1018` and `1018` are the same).
pub(crate) fn parse_index(s: &str) -> Result<u16> {
    let h = s
        .strip_prefix("0x")
        .or_else(|| s.strip_prefix("0X"))
        .unwrap_or(s);
    u16::from_str_radix(h, 16)
        .map_err(|_| usage!("index `{s}` is not a 16-bit hex number (e.g. 0x1018 or 1018)"))
}

/// Parses a sub-index: decimal, or hex with `0x`.
pub(crate) fn parse_sub(s: &str) -> Result<u8> {
    sdo::parse_u64(s)
        .and_then(|v| u8::try_from(v).ok())
        .ok_or_else(|| usage!("sub-index `{s}` is not 0..=255 (decimal, or hex with 0x)"))
}

fn parse_u32_arg(s: &str) -> Result<u32, String> {
    sdo::parse_u64(s)
        .and_then(|v| u32::try_from(v).ok())
        .ok_or_else(|| format!("`{s}` is not a 32-bit number (decimal or 0x-hex)"))
}

// ---------------------------------------------------------------------------------------- NMT

/// NMT commands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum NmtCommand {
    /// Start (operational), 0x01.
    Start,
    /// Stop, 0x02.
    Stop,
    /// Enter pre-operational, 0x80.
    Preop,
    /// Reset node (application), 0x81.
    Reset,
    /// Reset communication, 0x82.
    ResetComm,
}

impl NmtCommand {
    /// The command specifier byte.
    pub fn byte(self) -> u8 {
        match self {
            NmtCommand::Start => 0x01,
            NmtCommand::Stop => 0x02,
            NmtCommand::Preop => 0x80,
            NmtCommand::Reset => 0x81,
            NmtCommand::ResetComm => 0x82,
        }
    }
}

/// `canpos nmt`: send an NMT command.
#[derive(Args, Debug, Clone)]
pub struct NmtArgs {
    /// The command.
    pub command: NmtCommand,
    /// Node-id (1…127), or 0 for all nodes.
    #[arg(long, default_value = "0")]
    pub node: String,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
}

/// Sends an NMT command (unconfirmed: NMT has no answer except the boot-up after a reset).
pub fn nmt(a: NmtArgs) -> Result<i32> {
    let node = parse_node(&a.node, 0)?;
    let mut bus = open_bus(&a.bus.bus)?;
    bus.send(&Frame::std_len(
        0x000,
        [a.command.byte(), node, 0, 0, 0, 0, 0, 0],
        2,
    ))
    .context("sending the NMT command")?;
    let target = if node == 0 {
        "all nodes".to_string()
    } else {
        format!("node {node}")
    };
    println!(
        "NMT {} sent to {target}",
        decode::nmt_command_name(a.command.byte())
    );
    Ok(EXIT_OK)
}

/// `canpos guard`: node guarding with remote frames.
#[derive(Args, Debug, Clone)]
pub struct GuardArgs {
    /// Node-id (1…127).
    #[arg(long)]
    pub node: String,
    /// Guarding requests to send.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub count: u32,
    /// Time between requests and the wait for each answer, ms.
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(1..=60_000))]
    pub interval: u32,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
}

/// Guards a node as a master does (CiA 301 node guarding): a remote frame on 0x700 + id with
/// DLC 1 per request, and the answer's NMT state and toggle bit. Over socketcand the remote
/// frame is a true RTR where the server carries them (canpos's hub, docs/SOCKETCAND.md) and a
/// zero-length data frame elsewhere. Exit 4 when a request gets no answer, 1 when the toggle
/// does not alternate.
pub fn guard(a: GuardArgs) -> Result<i32> {
    let node = parse_node(&a.node, 1)?;
    let mut bus = open_bus(&a.bus.bus)?;
    let cob = 0x700 + u16::from(node);
    let wait = Duration::from_millis(a.interval.into());
    let request = Frame::remote(cob.into(), false, 1).expect("a valid remote frame");
    let zero = Frame::remote(cob.into(), false, 0).expect("a valid remote frame");
    let mut last_toggle = None;
    for i in 0..a.count {
        let start = Instant::now();
        // DLC 1 (the answer's length) where the transport carries it; DLC 0 where it cannot.
        if let Err(e) = bus.send(&request) {
            if e.kind() != std::io::ErrorKind::InvalidInput {
                return Err(e).context("sending the guarding request");
            }
            bus.send(&zero).context("sending the guarding request")?;
        }
        let end = start + wait;
        let answer = loop {
            match bus.recv_deadline(end)? {
                Some(rx) if rx.frame.std_id() == Some(cob) && !rx.frame.is_remote() => {
                    if let [b] = rx.frame.data() {
                        break Some(*b);
                    }
                }
                Some(_) => {}
                None => break None,
            }
        };
        let Some(b) = answer else {
            println!("request {}: no answer from node {node}", i + 1);
            return Ok(EXIT_TIMEOUT);
        };
        let toggle = b >> 7;
        println!(
            "request {}: node {node} {} (toggle {toggle})",
            i + 1,
            decode::nmt_state_name(b & 0x7F)
        );
        if last_toggle == Some(toggle) {
            println!("the toggle bit did not alternate");
            return Ok(EXIT_ERROR);
        }
        last_toggle = Some(toggle);
        if i + 1 < a.count {
            std::thread::sleep(wait.saturating_sub(start.elapsed()));
        }
    }
    Ok(EXIT_OK)
}

// ---------------------------------------------------------------------------------------- SDO

/// `canpos sdo`: read or write an object.
#[derive(Args, Debug, Clone)]
pub struct SdoArgs {
    #[command(subcommand)]
    #[allow(missing_docs)]
    pub cmd: SdoCmd,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
    /// Time to wait for each answer, in ms.
    #[arg(long, global = true, default_value_t = 1000, value_name = "MS")]
    pub timeout: u64,
}

/// SDO operations. INDEX is hex (`0x1018` or `1018`); SUB is decimal or `0x`-hex.
#[derive(Subcommand, Debug, Clone)]
pub enum SdoCmd {
    /// Read (upload) an object and print its value.
    Read {
        /// Node-id 1…127.
        node: String,
        /// Object index, hex (0x1018 or 1018).
        index: String,
        /// Sub-index, decimal or 0x-hex (0 when left out: a variable's value, a record's or
        /// array's number of entries).
        #[arg(default_value = "0")]
        sub: String,
        /// How to show the value (default: number for ≤ 4 bytes, else text or hex).
        #[arg(long = "type", short = 't', value_enum)]
        ty: Option<ValueType>,
    },
    /// Write (download) an object.
    Write {
        /// Node-id 1…127.
        node: String,
        /// Object index, hex (0x1018 or 1018).
        index: String,
        /// Sub-index, decimal or 0x-hex.
        sub: String,
        /// The value: decimal or 0x-hex for numbers, text for str, hex bytes for bytes.
        #[arg(allow_hyphen_values = true)]
        value: String,
        /// The object's type (sets the size written).
        #[arg(long = "type", short = 't', value_enum)]
        ty: ValueType,
    },
}

fn sdo_failure(e: SdoError) -> Result<i32> {
    let code = match e {
        SdoError::Abort(_) | SdoError::Protocol(_) => EXIT_REFUSED,
        SdoError::Timeout => EXIT_TIMEOUT,
        SdoError::Io(e) => return Err(anyhow::Error::new(e).context("CAN transport failed")),
    };
    eprintln!("error: {e}");
    Ok(code)
}

/// Reads or writes one object.
pub fn sdo(a: SdoArgs) -> Result<i32> {
    match a.cmd {
        SdoCmd::Read {
            node,
            index,
            sub,
            ty,
        } => {
            let (node, index, sub) = (
                parse_node(&node, 1)?,
                parse_index(&index)?,
                parse_sub(&sub)?,
            );
            let mut bus = open_bus(&a.bus.bus)?;
            let mut c = SdoClient::new(&mut *bus, node, ms(a.timeout));
            match c.upload(index, sub) {
                Ok(d) => match ty {
                    None => {
                        println!("{}", sdo::format_auto(&d));
                        Ok(EXIT_OK)
                    }
                    Some(t) => match t.decode(&d) {
                        Ok(s) => {
                            println!("{s}");
                            Ok(EXIT_OK)
                        }
                        Err(m) => {
                            eprintln!("error: {m}; raw: {}", sdo::hex_string(&d));
                            Ok(EXIT_REFUSED)
                        }
                    },
                },
                Err(e) => sdo_failure(e),
            }
        }
        SdoCmd::Write {
            node,
            index,
            sub,
            value,
            ty,
        } => {
            let (node, index, sub) = (
                parse_node(&node, 1)?,
                parse_index(&index)?,
                parse_sub(&sub)?,
            );
            let data = ty.encode(&value).map_err(|m| usage!("{m}"))?;
            let mut bus = open_bus(&a.bus.bus)?;
            let mut c = SdoClient::new(&mut *bus, node, ms(a.timeout));
            match c.download(index, sub, &data) {
                Ok(()) => {
                    println!("ok");
                    Ok(EXIT_OK)
                }
                Err(e) => sdo_failure(e),
            }
        }
    }
}

// ---------------------------------------------------------------------------------------- LSS

/// `canpos lss`: layer setting services. Most need a node in configuration state first
/// (`switch-global config` with a single node on the bus, or `switch-selective`).
#[derive(Args, Debug, Clone)]
pub struct LssArgs {
    #[command(subcommand)]
    #[allow(missing_docs)]
    pub cmd: LssCmd,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
    /// Time to wait for an answer, in ms (default 1000; for fastscan: per step, default 25).
    #[arg(long, global = true, value_name = "MS")]
    pub timeout: Option<u64>,
}

/// LSS modes for `switch-global`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LssMode {
    /// Configuration state.
    Config,
    /// Waiting state.
    Waiting,
}

/// What `lss inquire` asks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum InquireWhat {
    /// Vendor-id.
    Vendor,
    /// Product code.
    Product,
    /// Revision number.
    Revision,
    /// Serial number.
    Serial,
    /// Node-id.
    NodeId,
    /// All of the above.
    All,
}

/// LSS services.
#[derive(Subcommand, Debug, Clone)]
pub enum LssCmd {
    /// Switch state global: all nodes to configuration or waiting state.
    SwitchGlobal {
        /// Target state.
        mode: LssMode,
    },
    /// Switch state selective: the node with this address enters configuration state.
    SwitchSelective {
        /// Vendor-id (0x1018/1).
        #[arg(long, value_parser = parse_u32_arg)]
        vendor: u32,
        /// Product code (0x1018/2).
        #[arg(long, value_parser = parse_u32_arg)]
        product: u32,
        /// Revision number (0x1018/3).
        #[arg(long, value_parser = parse_u32_arg)]
        revision: u32,
        /// Serial number (0x1018/4).
        #[arg(long, value_parser = parse_u32_arg)]
        serial: u32,
    },
    /// Configure node-id (1…127, or 255 = unconfigured); effective after reset communication.
    SetNodeId {
        /// The new node-id.
        id: String,
    },
    /// Configure the bit rate (kbit/s: 1000, 800, 500, 250, 125, 50, 20, 10).
    SetBitrate {
        /// Bit rate in kbit/s.
        kbps: u32,
    },
    /// Activate bit timing: all nodes switch to the configured bit rate.
    Activate {
        /// Switch delay in ms.
        #[arg(long, default_value_t = 100)]
        delay: u16,
    },
    /// Store configuration (node-id and bit rate) in the node's non-volatile memory.
    Store,
    /// Inquire identity values or the node-id of the node in configuration state.
    Inquire {
        /// What to ask.
        #[arg(value_enum, default_value = "all")]
        what: InquireWhat,
    },
    /// Identify non-configured remote slaves (any node without a node-id?).
    IdentifyUnconfigured,
    /// Fastscan: find one non-configured node's LSS address and put it in configuration state.
    Fastscan,
}

fn lss_failure(e: LssError) -> Result<i32> {
    match e {
        LssError::Timeout => {
            eprintln!("error: {e}");
            Ok(EXIT_TIMEOUT)
        }
        LssError::Io(e) => Err(anyhow::Error::new(e).context("CAN transport failed")),
    }
}

fn lss_status(cs: u8, what: &str, r: Result<LssStatus, LssError>) -> Result<i32> {
    match r {
        Ok(s) if s.ok() => {
            println!("{what}: ok");
            Ok(EXIT_OK)
        }
        Ok(s) => {
            eprintln!(
                "error: {what}: error status {} ({}), manufacturer code {}",
                s.code,
                lss::status_meaning(cs, s.code),
                s.spec
            );
            Ok(EXIT_REFUSED)
        }
        Err(e) => lss_failure(e),
    }
}

/// Runs one LSS service.
pub fn lss(a: LssArgs) -> Result<i32> {
    // Validate before touching the bus.
    let node_id = match &a.cmd {
        LssCmd::SetNodeId { id } => {
            let v = sdo::parse_u64(id).ok_or_else(|| usage!("node-id `{id}` is not a number"))?;
            if !(1..=127).contains(&v) && v != 255 {
                return Err(usage!(
                    "node-id {v} out of range (1..=127, or 255 for unconfigured)"
                ));
            }
            v as u8
        }
        _ => 0,
    };
    let bit_index = match &a.cmd {
        LssCmd::SetBitrate { kbps } => lss::bit_timing_index(*kbps).ok_or_else(|| {
            usage!("{kbps} kbit/s is not in CiA 305 table 0 (1000, 800, 500, 250, 125, 50, 20, 10)")
        })?,
        _ => 0,
    };
    let is_fastscan = matches!(a.cmd, LssCmd::Fastscan);
    let timeout = ms(a.timeout.unwrap_or(if is_fastscan { 25 } else { 1000 }));
    let mut bus = open_bus(&a.bus.bus)?;
    let mut m = LssMaster::new(&mut *bus, timeout);
    match a.cmd {
        LssCmd::SwitchGlobal { mode } => {
            if let Err(e) = m.switch_global(mode == LssMode::Config) {
                return lss_failure(e);
            }
            println!(
                "switch state global: {}",
                match mode {
                    LssMode::Config => "configuration",
                    LssMode::Waiting => "waiting",
                }
            );
            Ok(EXIT_OK)
        }
        LssCmd::SwitchSelective {
            vendor,
            product,
            revision,
            serial,
        } => {
            let addr = LssAddress {
                vendor,
                product,
                revision,
                serial,
            };
            match m.switch_selective(&addr) {
                Ok(()) => {
                    println!("selected ({addr}): configuration state");
                    Ok(EXIT_OK)
                }
                Err(LssError::Timeout) => {
                    eprintln!("error: no node with {addr} answered");
                    Ok(EXIT_TIMEOUT)
                }
                Err(e) => lss_failure(e),
            }
        }
        LssCmd::SetNodeId { .. } => lss_status(
            0x11,
            &format!("configure node-id {node_id}"),
            m.configure_node_id(node_id),
        ),
        LssCmd::SetBitrate { kbps } => lss_status(
            0x13,
            &format!("configure bit timing {kbps} kbit/s (table 0 index {bit_index})"),
            m.configure_bit_timing(bit_index),
        ),
        LssCmd::Activate { delay } => {
            if let Err(e) = m.activate_bit_timing(delay) {
                return lss_failure(e);
            }
            println!("activate bit timing sent (switch delay {delay} ms)");
            Ok(EXIT_OK)
        }
        LssCmd::Store => lss_status(0x17, "store configuration", m.store()),
        LssCmd::Inquire { what } => {
            let list: &[(Inquire, &str)] = match what {
                InquireWhat::Vendor => &[(Inquire::Vendor, "vendor-id")],
                InquireWhat::Product => &[(Inquire::Product, "product code")],
                InquireWhat::Revision => &[(Inquire::Revision, "revision")],
                InquireWhat::Serial => &[(Inquire::Serial, "serial number")],
                InquireWhat::NodeId => &[(Inquire::NodeId, "node-id")],
                InquireWhat::All => &[
                    (Inquire::Vendor, "vendor-id"),
                    (Inquire::Product, "product code"),
                    (Inquire::Revision, "revision"),
                    (Inquire::Serial, "serial number"),
                    (Inquire::NodeId, "node-id"),
                ],
            };
            for (q, name) in list {
                match m.inquire(*q) {
                    Ok(v) if *q == Inquire::NodeId => {
                        let note = if v == 0xFF { " (unconfigured)" } else { "" };
                        println!("{name}: {v}{note}");
                    }
                    Ok(v) => println!("{name}: 0x{v:08X} ({v})"),
                    Err(e) => return lss_failure(e),
                }
            }
            Ok(EXIT_OK)
        }
        LssCmd::IdentifyUnconfigured => match m.identify_non_configured() {
            Ok(true) => {
                println!("a non-configured node is present");
                Ok(EXIT_OK)
            }
            Ok(false) => {
                println!("no non-configured node answered");
                Ok(EXIT_REFUSED)
            }
            Err(e) => lss_failure(e),
        },
        LssCmd::Fastscan => match m.fastscan(timeout) {
            Ok(Some(addr)) => {
                println!("found {addr}");
                println!("the node is now in LSS configuration state");
                Ok(EXIT_OK)
            }
            Ok(None) => {
                println!("no non-configured node answered the fastscan");
                Ok(EXIT_REFUSED)
            }
            Err(LssError::Timeout) => {
                eprintln!(
                    "error: fastscan lost the node during confirmation; try a longer --timeout"
                );
                Ok(EXIT_TIMEOUT)
            }
            Err(e) => lss_failure(e),
        },
    }
}

// --------------------------------------------------------------------------------------- scan

/// `canpos scan`: find the nodes on the bus and show their identity.
#[derive(Args, Debug, Clone)]
pub struct ScanArgs {
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
    /// How long to collect answers after the last request, and the per-read timeout of the
    /// identity reads, in ms.
    #[arg(long, default_value_t = 300, value_name = "MS")]
    pub timeout: u64,
}

/// One node found by [`scan_bus`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ScanResult {
    /// Node-id.
    pub node: u8,
    /// 0x1000, when the node answered SDO.
    pub device_type: Option<u32>,
    /// 0x1018/1…4 (missing sub-indices are `None`).
    pub identity: [Option<u32>; 4],
    /// 0x1008.
    pub name: Option<String>,
    /// Last NMT state seen in a heartbeat / boot-up, if any.
    pub state: Option<u8>,
}

/// Finds nodes: SDO upload of 0x1000 to every node-id, plus heartbeats and boot-ups heard,
/// then reads each node's identity.
pub fn scan_bus(bus: &mut dyn Transport, timeout: Duration) -> io::Result<Vec<ScanResult>> {
    let mut found: HashMap<u8, ScanResult> = HashMap::new();
    let note = |found: &mut HashMap<u8, ScanResult>, rx: RxFrame| {
        let f = rx.frame;
        if f.is_extended() || f.is_remote() {
            return;
        }
        let id = f.id() as u16;
        let node = (id & 0x7F) as u8;
        match (id & 0x780, f.data()) {
            (0x580, [0x43, 0x00, 0x10, 0x00, a, b, c, d]) if node != 0 => {
                let e = found.entry(node).or_default();
                e.node = node;
                e.device_type = Some(u32::from_le_bytes([*a, *b, *c, *d]));
            }
            (0x580, [0x80, 0x00, 0x10, 0x00, ..]) if node != 0 => {
                found.entry(node).or_default().node = node;
            }
            (0x700, [s]) if node != 0 => {
                let e = found.entry(node).or_default();
                e.node = node;
                e.state = Some(*s & 0x7F);
            }
            _ => {}
        }
    };
    // Requests go out in small bursts: a real adapter's transmit queue (and a slow hub client)
    // would drop frames if all 127 were queued at once.
    for node in 1..=127u8 {
        bus.send(&Frame::std8(
            0x600 + node as u16,
            [0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0],
        ))?;
        if node % 16 == 0 {
            let until = Instant::now() + ms(2);
            while let Some(rx) = bus.recv_deadline(until)? {
                note(&mut found, rx);
            }
        }
    }
    let until = Instant::now() + timeout;
    while let Some(rx) = bus.recv_deadline(until)? {
        note(&mut found, rx);
    }
    let mut nodes: Vec<ScanResult> = found.into_values().collect();
    nodes.sort_by_key(|n| n.node);
    for n in &mut nodes {
        let mut c = SdoClient::new(bus, n.node, timeout);
        if n.device_type.is_none() {
            match c.read_u32(0x1000, 0) {
                Ok(v) => n.device_type = Some(v),
                // A node that does not answer SDO (stopped) yields no more information.
                Err(SdoError::Timeout) => continue,
                Err(SdoError::Io(e)) => return Err(e),
                Err(_) => {}
            }
        }
        for sub in 1..=4u8 {
            match c.read_u32(0x1018, sub) {
                Ok(v) => n.identity[sub as usize - 1] = Some(v),
                Err(SdoError::Io(e)) => return Err(e),
                Err(_) => {}
            }
        }
        match c.upload(0x1008, 0) {
            Ok(d) => {
                n.name = Some(
                    String::from_utf8_lossy(&d)
                        .trim_end_matches('\0')
                        .to_string(),
                )
            }
            Err(SdoError::Io(e)) => return Err(e),
            Err(_) => {}
        }
    }
    Ok(nodes)
}

/// Scans the bus and prints one line per node.
pub fn scan(a: ScanArgs) -> Result<i32> {
    let mut bus = open_bus(&a.bus.bus)?;
    let nodes = scan_bus(&mut *bus, ms(a.timeout)).context("scanning the bus")?;
    if nodes.is_empty() {
        println!("no node found");
        return Ok(EXIT_REFUSED);
    }
    let hex = |v: Option<u32>| v.map_or("-".to_string(), |v| format!("0x{v:08X}"));
    println!("node  device-type  vendor      product     revision    serial      name       state");
    for n in &nodes {
        println!(
            "{:>4}  {:<11}  {:<10}  {:<10}  {:<10}  {:<10}  {:<9}  {}",
            n.node,
            hex(n.device_type),
            hex(n.identity[0]),
            hex(n.identity[1]),
            hex(n.identity[2]),
            n.identity[3].map_or("-".to_string(), |v| v.to_string()),
            n.name.as_deref().unwrap_or("-"),
            n.state.map_or("-", decode::nmt_state_name),
        );
    }
    Ok(EXIT_OK)
}

// ------------------------------------------------------------------------------------ monitor

/// How long `monitor --count N` waits for a frame to print before it gives up.
pub const DEFAULT_MONITOR_IDLE_S: f64 = 5.0;

/// `canpos monitor`: print decoded bus traffic.
#[derive(Args, Debug, Clone)]
pub struct MonitorArgs {
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
    /// Only traffic of this node (NMT and SYNC are always shown).
    #[arg(long)]
    pub node: Option<String>,
    /// Stop after this many frames printed (or when none came for the `--idle` time).
    #[arg(long)]
    pub count: Option<u64>,
    /// Stop when no frame to print came for S seconds: with `--count` 5 s unless given, which
    /// then exits 4 (fewer frames than counted); without `--count` only when given (exit 0).
    #[arg(long, value_name = "S", value_parser = crate::limits::parse_positive_seconds)]
    pub idle: Option<f64>,
    /// Stop after this many seconds.
    #[arg(long, value_name = "S", value_parser = crate::limits::parse_seconds)]
    pub duration: Option<f64>,
    /// Also print each frame as a candump -L line.
    #[arg(long)]
    pub raw: bool,
    /// Do not read PDO mapping and measuring steps by SDO (pure listening).
    #[arg(long)]
    pub passive: bool,
    /// SDO timeout for the configuration reads, in ms.
    #[arg(long, default_value_t = 200, value_name = "MS")]
    pub timeout: u64,
    /// Bit rate of the bus in kbit/s, for the bus load in the header (default 1000, the rate
    /// of a virtual bus nobody set).
    #[arg(long, value_name = "KBPS", value_parser = crate::device::parse_bitrate)]
    pub bitrate: Option<u32>,
}

/// Bus load from the frames a listener sees: their bits on the wire (stuff bits included) over
/// the last second of their timestamps.
struct LoadMeter {
    bit_ns: u64,
    window: VecDeque<(SystemTime, u64)>,
    bits: u64,
}

impl LoadMeter {
    fn new(kbps: u32) -> Self {
        LoadMeter {
            bit_ns: 1_000_000 / u64::from(kbps.max(1)),
            window: VecDeque::new(),
            bits: 0,
        }
    }

    /// Adds a frame; returns (load %, frames/s) over the second before it.
    fn add(&mut self, t: SystemTime, f: &Frame) -> (f64, usize) {
        let bits = u64::from(canpos_host::bus::bits::frame_length(f).total);
        self.window.push_back((t, bits));
        self.bits += bits;
        while let Some(&(t0, b)) = self.window.front() {
            if t.duration_since(t0).unwrap_or_default() < Duration::from_secs(1) {
                break;
            }
            self.window.pop_front();
            self.bits -= b;
        }
        let pct = (self.bits * self.bit_ns) as f64 / 1e9 * 100.0;
        (pct.min(100.0), self.window.len())
    }
}

/// The state of a running monitor: what is known about each node.
#[derive(Default)]
pub struct Monitor {
    nodes: HashMap<u8, Option<decode::NodeInfo>>,
    /// COB-ID → (node, mapping) for the TPDOs learned.
    tpdo: HashMap<u16, (u8, u8, Vec<u32>)>,
}

impl Monitor {
    /// A monitor that knows nothing yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The node that produced `f` (boot-up, heartbeat, EMCY, TPDO, SDO answer), if any.
    fn producer(f: &Frame) -> Option<u8> {
        if f.is_extended() {
            return None;
        }
        let id = f.id() as u16;
        let node = (id & 0x7F) as u8;
        let fc = id & 0x780;
        (node != 0 && matches!(fc, 0x080 | 0x180 | 0x280 | 0x380 | 0x480 | 0x580 | 0x700))
            .then_some(node)
    }

    /// Whether the node's configuration still has to be read.
    pub fn needs_query(&self, f: &Frame) -> Option<u8> {
        let n = Self::producer(f)?;
        (!self.nodes.contains_key(&n)).then_some(n)
    }

    /// Records what was read about `node` (`None`: it could not be read).
    pub fn learn(&mut self, node: u8, info: Option<decode::NodeInfo>) {
        if let Some(i) = &info {
            self.tpdo.retain(|_, (n, _, _)| *n != node);
            for (num, cob, map) in &i.tpdos {
                self.tpdo.insert(*cob, (node, *num, map.clone()));
            }
        }
        self.nodes.insert(node, info);
    }

    /// Forgets a node (after a boot-up its mapping may have changed).
    pub fn forget(&mut self, node: u8) {
        self.nodes.remove(&node);
        self.tpdo.retain(|_, (n, _, _)| *n != node);
    }

    /// Reads a node's measuring steps and TPDO configuration by SDO.
    pub fn query(client: &mut SdoClient<'_>) -> Result<decode::NodeInfo, SdoError> {
        let mut info = decode::NodeInfo {
            position_step_nm: match client.read_u32(0x6005, 1) {
                Ok(v) => Some(v),
                // No answer at all: nothing else will answer either.
                Err(e @ (SdoError::Timeout | SdoError::Io(_))) => return Err(e),
                Err(_) => None,
            },
            ..Default::default()
        };
        info.velocity_step = client.read_u32(0x6005, 2).ok();
        for n in 0..4u16 {
            let cob = match client.read_u32(0x1800 + n, 1) {
                Ok(v) => v,
                Err(SdoError::Abort(_)) => break,
                Err(e) => return Err(e),
            };
            if cob & 0x8000_0000 != 0 {
                continue;
            }
            let count = client.read_u32(0x1A00 + n, 0)?.min(64);
            let mut map = Vec::new();
            for s in 1..=count as u8 {
                map.push(client.read_u32(0x1A00 + n, s)?);
            }
            info.tpdos.push((n as u8 + 1, (cob & 0x7FF) as u16, map));
        }
        Ok(info)
    }

    /// Decodes one frame into a line of text (without timestamp).
    pub fn describe(&self, f: &Frame) -> String {
        if !f.is_extended() && !f.is_remote() {
            if let Some((node, num, map)) = self.tpdo.get(&(f.id() as u16)) {
                let info = self
                    .nodes
                    .get(node)
                    .and_then(|i| i.as_ref())
                    .cloned()
                    .unwrap_or_default();
                return format!(
                    "node {node} TPDO{num} {}",
                    decode::decode_pdo(&info, map, f.data())
                );
            }
        }
        decode::describe(f).unwrap_or_else(|| {
            format!(
                "0x{:03X} {}",
                f.id(),
                if f.is_remote() {
                    "RTR".to_string()
                } else {
                    sdo::hex_string(f.data())
                }
            )
        })
    }

    /// Whether `f` concerns `node` (for `--node`).
    pub fn concerns(&self, f: &Frame, node: u8) -> bool {
        if f.is_extended() {
            return false;
        }
        let id = f.id() as u16;
        if let Some((n, _, _)) = self.tpdo.get(&id) {
            return *n == node;
        }
        match id {
            0x000 => f.data().get(1).is_some_and(|n| *n == 0 || *n == node),
            0x080 => true,
            0x7E4 | 0x7E5 => true,
            _ => (id & 0x7F) as u8 == node && id >= 0x080,
        }
    }
}

fn elapsed_since(start: SystemTime, t: SystemTime) -> f64 {
    t.duration_since(start)
        .map(|d| d.as_secs_f64())
        .unwrap_or_else(|e| -e.duration().as_secs_f64())
}

/// Prints decoded traffic until `--count` / `--duration` is reached (or forever).
pub fn monitor(a: MonitorArgs) -> Result<i32> {
    let only = a.node.as_deref().map(|n| parse_node(n, 1)).transpose()?;
    let mut bus = open_bus(&a.bus.bus)?;
    let iface = interface_name(&a.bus.bus);
    let start = SystemTime::now();
    let end = a
        .duration
        .and_then(|d| crate::limits::deadline(Instant::now(), d));
    // A counted monitor of a silent node ends (a script's `--count 1` must not hang).
    let idle = a
        .idle
        .or(a.count.map(|_| DEFAULT_MONITOR_IDLE_S))
        .map(Duration::from_secs_f64);
    let mut last_printed = Instant::now();
    let mut mon = Monitor::new();
    let mut pending: VecDeque<RxFrame> = VecDeque::new();
    let mut printed = 0u64;
    let out = io::stdout();
    let mut out = out.lock();
    let kbps = a.bitrate.unwrap_or(canpos_host::bus::DEFAULT_BITRATE_KBPS);
    let mut load = LoadMeter::new(kbps);
    let mut next_header = Instant::now();
    writeln!(
        out,
        "# {}: bus load at {kbps} kbit/s every second (frames seen, stuff bits included)",
        a.bus.bus
    )?;
    loop {
        if a.count.is_some_and(|c| printed >= c) {
            break;
        }
        let rx = match pending.pop_front() {
            Some(rx) => rx,
            None => {
                let quiet_end = idle.and_then(|i| last_printed.checked_add(i));
                let r = match (end, quiet_end) {
                    (Some(e), Some(q)) => bus.recv_deadline(e.min(q))?,
                    (Some(e), None) | (None, Some(e)) => bus.recv_deadline(e)?,
                    (None, None) => bus.recv_timeout(None)?,
                };
                match r {
                    Some(rx) => rx,
                    None if quiet_end.is_some_and(|q| Instant::now() >= q) => {
                        out.flush()?;
                        let what = only.map_or("the bus".to_string(), |n| format!("node {n}"));
                        let waited = idle.unwrap_or_default().as_secs_f64();
                        return Ok(match a.count {
                            Some(c) => {
                                eprintln!(
                                    "monitor: {what} silent for {waited} s: {printed} of {c} frames"
                                );
                                EXIT_TIMEOUT
                            }
                            None => EXIT_OK,
                        });
                    }
                    None => break,
                }
            }
        };
        let f = rx.frame;
        let (pct, fps) = load.add(rx.timestamp, &f);
        if Instant::now() >= next_header {
            writeln!(out, "# bus load {pct:.1} %, {fps} frames/s")?;
            next_header = Instant::now() + Duration::from_secs(1);
        }
        // A boot-up means the node's configuration may have been reset: read it again.
        if !f.is_extended() && (0x701..=0x77F).contains(&f.id()) && f.data() == [0] {
            mon.forget((f.id() & 0x7F) as u8);
        }
        if let Some(node) = mon.needs_query(&f).filter(|_| !a.passive) {
            if only.is_none_or(|o| o == node) {
                let mut c = SdoClient::new(&mut *bus, node, ms(a.timeout)).keep_other_frames();
                let info = Monitor::query(&mut c);
                pending.extend(c.take_other_frames());
                match info {
                    Ok(i) => mon.learn(node, Some(i)),
                    Err(e) => {
                        writeln!(
                            out,
                            "# node {node}: cannot read its PDO configuration ({e})"
                        )?;
                        mon.learn(node, None);
                    }
                }
            }
        }
        if only.is_some_and(|n| !mon.concerns(&f, n)) {
            continue;
        }
        let t = elapsed_since(start, rx.timestamp);
        if a.raw {
            writeln!(out, "{}", format_line(rx.timestamp, &iface, &f))?;
        }
        writeln!(out, "[{t:10.6}] {}", mon.describe(&f))?;
        printed += 1;
        last_printed = Instant::now();
    }
    out.flush()?;
    Ok(EXIT_OK)
}

// ---------------------------------------------------------------------------------------- EDS

/// `canpos eds`: write a model's EDS (CiA 306) file, or that of the unit an order code names.
#[derive(Args, Debug, Clone)]
pub struct EdsArgs {
    /// Model name: th, e-series, tmi.
    #[arg(
        long,
        required_unless_present = "order_code",
        conflicts_with = "order_code"
    )]
    pub model: Option<String>,
    /// Order code of a unit (e.g. EP00600MD341C304241Z02): its model with the defaults of its
    /// stroke, resolution, channels and bit rate, and the code as `OrderCode`.
    #[arg(long, value_name = "CODE")]
    pub order_code: Option<String>,
    /// Output file (default: standard output).
    #[arg(long, short = 'o')]
    pub output: Option<PathBuf>,
}

/// The file name an export writes into `FileName`: the output's, else `default`.
fn export_file_name(output: Option<&PathBuf>, default: String) -> String {
    output
        .and_then(|p| p.file_name())
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or(default)
}

/// Writes `text` to `output`, or to standard output.
fn write_export(output: Option<&PathBuf>, text: &str) -> Result<()> {
    match output {
        Some(p) => std::fs::write(p, text).with_context(|| format!("writing {}", p.display())),
        None => {
            use std::io::Write as _;
            std::io::stdout().write_all(text.as_bytes())?;
            Ok(())
        }
    }
}

/// The model (and unit configuration, and order code) an export is for.
pub(crate) fn export_unit(
    model: Option<&str>,
    order_code: Option<&str>,
) -> Result<(
    &'static canpos_core::models::Model,
    canpos_core::models::DeviceConfig,
    String,
)> {
    if let Some(code) = order_code {
        let (m, cfg, _, oc) = crate::device::order_code_unit(code).map_err(|e| usage!("{e:#}"))?;
        return Ok((m, cfg, oc.normalized));
    }
    let name = model.unwrap_or("th");
    let names: Vec<&str> = canpos_core::models::all().iter().map(|m| m.name).collect();
    let Some(m) = canpos_core::models::by_name(name) else {
        bail!("unknown model `{name}` (known: {})", names.join(", "));
    };
    Ok((m, m.default_config, String::new()))
}

/// Exports a model's EDS file: creation and modification date and time are the export's (UTC).
pub fn eds(a: EdsArgs) -> Result<i32> {
    let (model, cfg, order_code) = export_unit(a.model.as_deref(), a.order_code.as_deref())?;
    let default_name = if order_code.is_empty() {
        format!("canpos-{}.eds", model.name)
    } else {
        format!("{order_code}.eds")
    };
    let file_name = export_file_name(a.output.as_ref(), default_name);
    let (date, time) = crate::capture::eds_date_time(SystemTime::now());
    let info = canpos_core::eds::EdsInfo {
        file_name: &file_name,
        date: &date,
        time: &time,
        order_code: &order_code,
        ..Default::default()
    };
    let mut text = String::new();
    canpos_core::eds::write_eds(&mut text, model, &cfg, &info)
        .map_err(|_| anyhow::anyhow!("formatting the EDS failed"))?;
    write_export(a.output.as_ref(), &text)?;
    Ok(0)
}

// ------------------------------------------------------------------------- record and replay

/// The interface name written into candump logs: the socketcand channel, the SocketCAN
/// interface or the in-process bus name.
fn interface_name(url: &str) -> String {
    match BusUrl::parse(url) {
        Ok(BusUrl::Socketcand { channel, .. }) => channel,
        Ok(BusUrl::SocketCan { iface }) => iface,
        Ok(BusUrl::Mem { name }) => name,
        Err(_) => "can0".to_string(),
    }
}

/// `canpos record`: write bus traffic to pcapng, pcap, a candump `-L` log or Vector ASC.
#[derive(Args, Debug, Clone)]
pub struct RecordArgs {
    /// Output file (`-` = standard output, with `--format`).
    pub file: PathBuf,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
    /// File format (default: from the extension: .pcapng, .pcap, .log, .asc).
    #[arg(long, value_enum)]
    pub format: Option<crate::capture::Format>,
    /// Stop after this many seconds.
    #[arg(long, value_name = "S", value_parser = crate::limits::parse_seconds)]
    pub duration: Option<f64>,
    /// Stop after this many frames.
    #[arg(long)]
    pub count: Option<u64>,
    /// Interface name written in the file (default: the bus channel / interface name).
    #[arg(long)]
    pub interface: Option<String>,
}

/// The format of `file`: `--format`, else its extension; a candump log for `-` without one
/// (what `canpos record -` always wrote).
fn record_format(
    file: &std::path::Path,
    format: Option<crate::capture::Format>,
) -> Result<crate::capture::Format> {
    use crate::capture::Format;
    if let Some(f) = format {
        return Ok(f);
    }
    if file.as_os_str() == "-" {
        return Ok(Format::Candump);
    }
    Format::from_path(file).ok_or_else(|| {
        usage!(
            "{}: cannot tell the format from the extension (.pcapng, .pcap, .log, .asc); give --format",
            file.display()
        )
    })
}

/// Records frames until `--duration` / `--count` (or until killed; every frame is flushed as
/// it is written, so an interrupted recording keeps what was seen and a pipe is a live view).
///
/// Timestamps are the transport's receive stamps. The file's stamps never go backwards: a frame
/// stamped earlier than the one before it (two sources of stamps, a clock step) is written
/// with the previous stamp, and the number of such frames is reported at the end.
pub fn record(a: RecordArgs) -> Result<i32> {
    use canpos_host::candump::Record;
    let format = record_format(&a.file, a.format)?;
    let iface = a
        .interface
        .clone()
        .unwrap_or_else(|| interface_name(&a.bus.bus));
    // The bus first: an unreachable bus leaves no empty file, and a file that exists is being
    // recorded into (tests wait for it).
    let bus = open_bus(&a.bus.bus)?;
    let out: Box<dyn Write> = if a.file.as_os_str() == "-" {
        Box::new(io::stdout())
    } else {
        Box::new(
            File::create(&a.file).with_context(|| format!("cannot create {}", a.file.display()))?,
        )
    };
    let mut w = crate::capture::CaptureWriter::new(BufWriter::new(out), format, &iface)?;
    let end = a
        .duration
        .and_then(|d| crate::limits::deadline(Instant::now(), d));
    let mut n = 0u64;
    let mut errors = 0u64;
    let mut held = 0u64;
    let mut last = SystemTime::UNIX_EPOCH;
    // Error frames come on a queue of their own where the transport delivers them (a canpos
    // hub, SocketCAN); a transport without them gives a queue that never delivers.
    let error_rx = bus.error_frames().unwrap_or_else(crossbeam_channel::never);
    while a.count.is_none_or(|c| n < c) {
        let (stamp, record) = {
            let frames = bus.receiver();
            let mut sel = crossbeam_channel::Select::new();
            let fi = sel.recv(frames);
            let ei = sel.recv(&error_rx);
            let op = match end {
                Some(e) => match sel.select_deadline(e) {
                    Ok(op) => op,
                    Err(_) => break,
                },
                None => sel.select(),
            };
            if op.index() == fi {
                match op.recv(frames) {
                    Ok(rx) => (rx.timestamp, Record::Frame(rx.frame)),
                    Err(_) => return Err(anyhow::Error::new(bus.dead_error())),
                }
            } else if op.index() == ei {
                match op.recv(&error_rx) {
                    Ok(e) => {
                        errors += 1;
                        let ef = canpos_host::candump::ErrorFrame::new(
                            e.class,
                            e.data.unwrap_or([0; 8]),
                        );
                        (e.timestamp, Record::Error(ef))
                    }
                    // The transport dropped its error queue: frames go on.
                    Err(_) => continue,
                }
            } else {
                unreachable!("two operations were selected on")
            }
        };
        let t = if stamp < last {
            held += 1;
            last
        } else {
            stamp
        };
        last = t;
        w.write(t, &record)?;
        n += 1;
    }
    w.finish()?;
    if held > 0 {
        eprintln!("{held} frames came with a stamp older than the frame before; written with that frame's stamp");
    }
    if a.file.as_os_str() != "-" {
        eprintln!(
            "recorded {n} frames ({errors} of them error frames) to {}",
            a.file.display()
        );
    }
    Ok(EXIT_OK)
}

/// What `canpos replay` does with a malformed line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum OnMalformed {
    /// Report it with its line number and send nothing (the whole log is read first).
    Stop,
    /// Report it with its line number, skip it and play the rest.
    Skip,
}

/// `canpos replay`: send the frames of a candump `-L` log or Vector ASC file with their
/// original timing.
#[derive(Args, Debug, Clone)]
pub struct ReplayArgs {
    /// Log file (`-` = standard input): candump -L (can-utils, python-can), or ASC (.asc).
    pub file: PathBuf,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub bus: BusArg,
    /// Input format (default: ASC for .asc, else candump).
    #[arg(long, value_enum)]
    pub format: Option<crate::capture::Format>,
    /// Time scale: 2 = twice as fast; 0 = as fast as possible (else 0.001 … 1e6).
    #[arg(long, default_value_t = 1.0, value_parser = crate::limits::parse_speed)]
    pub speed: f64,
    /// Start again at the end of the file (until killed).
    #[arg(long = "loop")]
    pub repeat: bool,
    /// A malformed line: stop (nothing is sent) or skip it and play the rest.
    #[arg(long, value_enum, default_value = "stop", value_name = "ACTION")]
    pub on_malformed: OnMalformed,
    /// Shorten every pause between frames longer than this to it (seconds of replay, after
    /// --speed), as python-can's `can.player --skip` does; default: the log's pauses.
    #[arg(long, value_name = "SECONDS", value_parser = crate::limits::parse_seconds)]
    pub max_gap: Option<f64>,
}

fn open_log(path: &PathBuf) -> Result<Box<dyn BufRead>> {
    if path.as_os_str() == "-" {
        return Ok(Box::new(BufReader::new(io::stdin())));
    }
    let f = File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    Ok(Box::new(BufReader::new(f)))
}

/// Most frames `canpos replay` holds from an input it cannot read twice (standard input, a
/// pipe, a device): it checks a whole log before the first frame goes out, so such an input is
/// held, and no more than this of it (about 80 MB). A regular file is read twice instead and
/// holds nothing.
pub const REPLAY_HELD_MAX: usize = 2_000_000;

/// A wait for the next frame longer than this (seconds) is announced on stderr first.
pub const REPLAY_LONG_WAIT: f64 = 10.0;

/// Malformed lines `--on-malformed stop` reports before it stops reading: the first one already
/// means nothing is sent, so an endless input of them (`yes | canpos replay -`) ends here.
pub const REPLAY_MALFORMED_MAX: u64 = 100;

/// What replay does with a record: a frame it sends, or a kind it counts.
#[derive(Clone, Copy)]
enum Play {
    Frame(Frame),
    Error,
    Fd,
}

impl From<canpos_host::candump::Record> for Play {
    fn from(r: canpos_host::candump::Record) -> Play {
        use canpos_host::candump::Record;
        match r {
            Record::Frame(f) => Play::Frame(f),
            Record::Error(_) => Play::Error,
            Record::Fd(_) => Play::Fd,
        }
    }
}

/// Each record's time of replay (seconds from the start): its log time divided by `--speed`,
/// less what `--max-gap` took off the pauses before it.
#[derive(Clone, Copy)]
struct Timeline {
    speed: f64,
    max_gap: Option<f64>,
    /// The latest log time seen (scaled), from the log's start.
    latest: f64,
    cut: f64,
}

impl Timeline {
    fn new(speed: f64, max_gap: Option<f64>) -> Timeline {
        Timeline {
            speed,
            max_gap,
            latest: 0.0,
            cut: 0.0,
        }
    }

    /// What [`offset`](Self::offset) would give for `t`, without taking `t` in.
    fn peek(&self, t: f64) -> f64 {
        let mut probe = *self;
        probe.offset(t)
    }

    fn offset(&mut self, t: f64) -> f64 {
        if self.speed <= 0.0 {
            return 0.0;
        }
        let t = t / self.speed;
        if t > self.latest {
            if let Some(m) = self.max_gap {
                self.cut += (t - self.latest - m).max(0.0);
            }
            self.latest = t;
        }
        t - self.cut
    }
}

/// The `FILE:LINE: why` of an error that ends reading a log.
fn log_error(file: &str, e: canpos_host::candump::LogError) -> anyhow::Error {
    use canpos_host::candump::LogError;
    match e {
        LogError::TooLong { line } => anyhow!(
            "{file}:{line}: longer than {} bytes without a newline: not a candump -L log or ASC file; nothing more is read",
            canpos_host::candump::MAX_LINE
        ),
        LogError::Parse { line, error } => anyhow!("{file}:{line}: {error}"),
        LogError::Io(e) => anyhow::Error::new(e).context(format!("reading {file}")),
    }
}

/// Sends the records of a replay on their times.
struct Player {
    bus: Box<dyn Transport>,
    file: String,
    t0: Instant,
    timeline: Timeline,
    /// The latest replay time sent at, s from the start.
    last: f64,
    sent: u64,
    errors: u64,
    fd: u64,
    refused: u64,
}

impl Player {
    fn play(&mut self, line: usize, t: f64, p: Play) -> Result<()> {
        let f = match p {
            Play::Frame(f) => f,
            Play::Error => {
                self.errors += 1;
                return Ok(());
            }
            Play::Fd => {
                self.fd += 1;
                return Ok(());
            }
        };
        let off = self.timeline.offset(t);
        let pause = off - self.last;
        self.last = self.last.max(off);
        if off > 0.0 {
            if let Some(due) = crate::limits::deadline(self.t0, off) {
                let now = Instant::now();
                if due > now {
                    let wait = due - now;
                    if wait.as_secs_f64() > REPLAY_LONG_WAIT {
                        let hint = if self.timeline.max_gap.is_none() {
                            " (--max-gap shortens such pauses)"
                        } else {
                            ""
                        };
                        eprintln!(
                            "{}:{line}: this frame comes {} after the one before: waiting{hint}",
                            self.file,
                            show_wait(pause.max(wait.as_secs_f64()))
                        );
                    }
                    std::thread::sleep(wait);
                }
            }
        }
        match self.bus.send(&f) {
            Ok(()) => self.sent += 1,
            // The transport cannot carry this frame (socketcand: a remote frame with DLC).
            Err(e) if e.kind() == io::ErrorKind::InvalidInput => self.refused += 1,
            Err(e) => return Err(anyhow::Error::new(e).context("sending a frame")),
        }
        Ok(())
    }
}

/// A pause in words: seconds, and days or years when that long.
fn show_wait(s: f64) -> String {
    let days = s / 86_400.0;
    if days >= 365.25 {
        format!("{s:.1} s ({:.1} years)", days / 365.25)
    } else if days >= 1.0 {
        format!("{s:.1} s ({days:.1} days)")
    } else {
        format!("{s:.1} s")
    }
}

/// Replays a log; the frames keep their relative spacing, divided by `--speed`. Lines that
/// cannot go on this bus (error frames, CAN FD frames, remote frames with a DLC on a
/// transport without them) are skipped and counted; the counts are reported at the end.
///
/// The whole log is read and checked before the first frame goes out; memory stays bounded
/// whatever the input: lines of at most `MAX_LINE` bytes, a regular file read twice (checked,
/// then played) and any other input held up to [`REPLAY_HELD_MAX`] frames.
pub fn replay(a: ReplayArgs) -> Result<i32> {
    use crate::capture::{LogItem, LogItems};
    // Checked again for callers that build the arguments in code.
    crate::limits::parse_speed(&a.speed.to_string()).map_err(|e| anyhow!("--speed {e}"))?;
    if let Some(g) = a.max_gap {
        crate::limits::check_seconds(g, false).map_err(|e| anyhow!("--max-gap {e}"))?;
    }
    if a.repeat && a.file.as_os_str() == "-" {
        bail!("--loop needs a file, not standard input");
    }
    let format = match a.format {
        Some(f) => f,
        None => match crate::capture::Format::from_path(&a.file) {
            Some(crate::capture::Format::Asc) => crate::capture::Format::Asc,
            _ => crate::capture::Format::Candump,
        },
    };
    let name = a.file.display().to_string();
    let items = |input| {
        LogItems::new(input, format)
            .ok_or_else(|| usage!("replay reads candump -L logs and ASC files, not pcap / pcapng"))
    };
    // A regular file is read again to play it; anything else (standard input, a pipe, a
    // device) only once, so its frames are held.
    let again = a.file.as_os_str() != "-" && std::fs::metadata(&a.file).is_ok_and(|m| m.is_file());
    let mut held: Option<Vec<(usize, f64, Play)>> = (!again).then(Vec::new);
    // Read everything first so a malformed log (with --on-malformed stop) fails before
    // anything goes on the bus, and a log too long for this speed sends nothing.
    let (mut malformed, mut records) = (0u64, 0u64);
    let mut timeline = Timeline::new(a.speed, a.max_gap);
    let mut span = 0.0f64;
    // The last line checked: a file that grows after the check (a log still being recorded)
    // is played as far as it was checked, never further.
    let mut checked = 0usize;
    for item in items(open_log(&a.file)?)? {
        match item.map_err(|e| log_error(&name, e))? {
            LogItem::Malformed { line, why } => {
                eprintln!("{name}:{line}: {why}");
                malformed += 1;
                checked = line;
                if a.on_malformed == OnMalformed::Stop && malformed >= REPLAY_MALFORMED_MAX {
                    bail!(
                        "{name}: {malformed} malformed lines, and the rest not read; nothing sent (--on-malformed skip plays the rest)"
                    );
                }
            }
            LogItem::Record { line, t, record } => {
                records += 1;
                checked = line;
                let play = Play::from(record);
                if matches!(play, Play::Frame(_)) {
                    span = span.max(timeline.offset(t));
                }
                if let Some(h) = &mut held {
                    if h.len() >= REPLAY_HELD_MAX {
                        bail!(
                            "{name}:{line}: more than {REPLAY_HELD_MAX} frames from an input that cannot be read twice; replay checks a whole log before sending, so it holds them: write the log to a file and replay that; nothing sent"
                        );
                    }
                    h.push((line, t, play));
                }
            }
        }
    }
    if malformed > 0 && a.on_malformed == OnMalformed::Stop {
        bail!(
            "{name}: {malformed} malformed line(s), nothing sent (--on-malformed skip plays the rest)"
        );
    }
    if records == 0 {
        eprintln!("{name}: no frames");
        return Ok(EXIT_OK);
    }
    crate::limits::check_seconds(span, false)
        .map_err(|e| anyhow!("{name}: at --speed {} the replay would take {e}", a.speed))?;
    let mut p = Player {
        bus: open_bus(&a.bus.bus)?,
        file: name.clone(),
        t0: Instant::now(),
        timeline: Timeline::new(a.speed, a.max_gap),
        last: 0.0,
        sent: 0,
        errors: 0,
        fd: 0,
        refused: 0,
    };
    loop {
        p.t0 = Instant::now();
        p.timeline = Timeline::new(a.speed, a.max_gap);
        p.last = 0.0;
        let sent_before = p.sent;
        match &held {
            Some(h) => {
                for &(line, t, play) in h {
                    p.play(line, t, play)?;
                }
            }
            None => {
                // The file is read again: what the check found must still hold, or it changed
                // in between and is not played on.
                let changed = |line: usize, what: &str| {
                    anyhow!("{name}:{line}: {what} since replay checked the file; stopping")
                };
                for item in items(open_log(&a.file)?)? {
                    match item.map_err(|e| log_error(&name, e))? {
                        LogItem::Malformed { line, .. } if line > checked => break,
                        LogItem::Record { line, .. } if line > checked => break,
                        // Reported when the log was checked (and skipped by the user's choice).
                        LogItem::Malformed { line, why } => {
                            if a.on_malformed == OnMalformed::Stop {
                                return Err(changed(line, &format!("malformed ({why})")));
                            }
                        }
                        LogItem::Record { line, t, record } => {
                            let play = Play::from(record);
                            if matches!(play, Play::Frame(_)) && p.timeline.peek(t) > span {
                                return Err(changed(line, "a frame later than any checked"));
                            }
                            p.play(line, t, play)?;
                        }
                    }
                }
            }
        }
        if !a.repeat {
            break;
        }
        if p.sent == sent_before {
            // Nothing in the log could go on this bus: repeating would spin without end.
            eprintln!("--repeat: no frame of the log can be sent on this bus; stopping");
            break;
        }
    }
    eprintln!("replayed {} frames", p.sent);
    let skipped = p.errors + p.fd + p.refused + malformed;
    if skipped > 0 {
        eprintln!(
            "skipped {skipped} lines: {} error frames, {} CAN FD frames, {} frames this bus cannot carry (remote frames with a DLC), {malformed} malformed",
            p.errors, p.fd, p.refused
        );
    }
    Ok(EXIT_OK)
}

#[cfg(test)]
mod tests;
