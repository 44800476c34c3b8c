//! `canpos nmt`: send an NMT command.

use anyhow::{Context, Result};
use canpos_host::transport::Transport;
use canpos_stack::{cob, nmt, Frame};
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
    /// The command as the stack names it.
    pub fn wire(self) -> nmt::NmtCommand {
        match self {
            NmtCommand::Start => nmt::NmtCommand::Start,
            NmtCommand::Stop => nmt::NmtCommand::Stop,
            NmtCommand::Preop => nmt::NmtCommand::EnterPreOperational,
            NmtCommand::Reset => nmt::NmtCommand::ResetNode,
            NmtCommand::ResetComm => nmt::NmtCommand::ResetCommunication,
        }
    }

    /// The command specifier byte.
    pub fn byte(self) -> u8 {
        self.wire().code()
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
    let [c, n] = nmt::NmtFrame {
        command: a.command.wire(),
        node,
    }
    .emit();
    bus.send(&Frame::std_len(cob::NMT, [c, n, 0, 0, 0, 0, 0, 0], 2))
        .context("sending the NMT command")?;
    let target = if node == nmt::ALL_NODES {
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
