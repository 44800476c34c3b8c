//! `canpos nmt`: send an NMT command.

use anyhow::{Context, Result};
use canpos_core::Frame;
use canpos_host::transport::Transport;
use clap::{Args, ValueEnum};

use crate::client::decode;
use crate::common::{open_bus, parse_node, BusArg, EXIT_OK};

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
