//! `canpos lss`: the layer setting services (CiA 305) from the master's side.

use anyhow::Result;
use canpos_stack::lss::cs;
use clap::{Args, Subcommand, ValueEnum};

use crate::client::{lss, Inquire, LssAddress, LssError, LssMaster, LssStatus};
use crate::common::{
    ms, open_bus, parse_u32_arg, usage, BusArg, EXIT_OK, EXIT_REFUSED, EXIT_TIMEOUT,
};

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
            let v = crate::common::parse_u64(id)
                .ok_or_else(|| usage!("node-id `{id}` is not a number"))?;
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
            cs::CONFIGURE_NODE_ID,
            &format!("configure node-id {node_id}"),
            m.configure_node_id(node_id),
        ),
        LssCmd::SetBitrate { kbps } => lss_status(
            cs::CONFIGURE_BIT_TIMING,
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
        LssCmd::Store => lss_status(cs::STORE_CONFIGURATION, "store configuration", m.store()),
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
