//! `canpos monitor`: the bus traffic decoded.

use std::collections::VecDeque;
use std::io::{self, Write};
use std::time::{Duration, Instant, SystemTime};

use anyhow::Result;
use canpos_host::candump::format_line;
use canpos_host::transport::{RxFrame, Transport};
use clap::Args;

use crate::client::monitor::LoadMeter;
use crate::client::{Monitor, SdoClient};
use crate::common::{interface_name, ms, open_bus, parse_node, BusArg, EXIT_OK, EXIT_TIMEOUT};

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
    #[arg(long, value_name = "KBPS", value_parser = crate::common::parse_bitrate)]
    pub bitrate: Option<u32>,
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
