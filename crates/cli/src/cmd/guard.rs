//! `canpos guard`: node guarding from the master's side.

use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use canpos_host::transport::Transport;
use canpos_stack::Frame;
use clap::Args;

use crate::client::decode;
use crate::common::{open_bus, parse_node, BusArg, EXIT_ERROR, EXIT_OK, EXIT_TIMEOUT};

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
            decode::nmt_state_name(b)
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
