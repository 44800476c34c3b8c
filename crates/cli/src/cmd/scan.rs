//! `canpos scan`: find the nodes on a bus.

use anyhow::{Context, Result};
use clap::Args;

use crate::client::{decode, scan_bus};
use crate::common::{ms, open_bus, BusArg, EXIT_OK, EXIT_REFUSED};

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
            match (n.state, n.state_inferred) {
                (None, _) => "-".to_string(),
                (Some(s), false) => decode::nmt_state_name(s).to_string(),
                (Some(s), true) => format!("{} (inferred)", decode::nmt_state_name(s)),
            },
        );
    }
    Ok(EXIT_OK)
}
