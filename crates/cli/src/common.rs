//! What every command shares, at the bottom of the command line: exit codes and [`Usage`]
//! errors, the parsers of node-ids, indexes, numbers and bit rates, opening a tool's bus, the
//! pacing of a bus this process creates, and Ctrl-C / SIGTERM.
//!
//! Exit codes of every command (the same for the whole binary, see `main.rs`): 0 success,
//! [`EXIT_REFUSED`] the device refused (SDO abort, LSS error status) or nothing was found,
//! [`EXIT_TIMEOUT`] no answer within the timeout. Errors before anything was sent are returned
//! as `Err` for the caller to report: [`Usage`] for bad arguments, anything else (bus not
//! reachable) as a runtime error.

use std::time::Duration;

use anyhow::{Context as _, Result};
use canpos_host::bus::Pacing;
use canpos_host::crossbeam_channel::{self, Receiver};
use canpos_host::transport::{self, BusUrl, Transport, DEFAULT_URL};
use clap::Args;

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
    ($($t:tt)*) => { anyhow::Error::new($crate::common::Usage(format!($($t)*))) };
}
pub(crate) use usage;

/// The bus option every master command takes.
#[derive(Args, Debug, Clone)]
pub struct BusArg {
    /// Bus URL: socketcand://HOST:PORT/CHANNEL, socketcan://IFACE, mem://NAME or
    /// silkit://HOST:PORT/NETWORK (docs/SILKIT.md).
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

/// The SIL Kit options of a device command (`run`, `scenario`; docs/SILKIT.md).
#[derive(Args, Debug, Clone, Default)]
pub struct SilkitArgs {
    /// For a silkit:// bus: the participant's name (unique in the simulation). Default: the
    /// sensor's name, MODEL-SERIAL (`run`), or canpos-PID-N.
    #[arg(long, value_name = "NAME")]
    pub participant: Option<String>,
    /// For a silkit:// bus: `wall` (default) runs on the wall clock; `sync` on SIL Kit's
    /// simulation time, in steps of --step-us, under a system controller.
    #[arg(long, value_name = "MODE", value_parser = ["wall", "sync"])]
    pub time: Option<String>,
    /// For `--time sync`: the simulation step in µs (default 1000).
    #[arg(long, value_name = "US", value_parser = clap::value_parser!(u64).range(1..=1_000_000_000))]
    pub step_us: Option<u64>,
}

/// `url` with the SIL Kit options put into it (a silkit:// URL's `participant`, `time`,
/// `step-us`; `default_participant` when neither names one); a usage error for these options
/// with another bus.
pub fn silkit_url(url: &str, s: &SilkitArgs, default_participant: Option<&str>) -> Result<String> {
    let given = s.participant.is_some() || s.time.is_some() || s.step_us.is_some();
    let parsed = match BusUrl::parse(url) {
        Ok(u) => u,
        // Reported by whoever opens it, as before.
        Err(_) => return Ok(url.to_string()),
    };
    let BusUrl::Silkit {
        host,
        port,
        network,
        participant,
        sync_step_us,
    } = parsed
    else {
        if given {
            return Err(usage!(
                "--participant, --time and --step-us are for a silkit:// bus (docs/SILKIT.md)"
            ));
        }
        return Ok(url.to_string());
    };
    if s.step_us.is_some() && s.time.as_deref() != Some("sync") && sync_step_us.is_none() {
        return Err(usage!("--step-us needs --time sync"));
    }
    let sync_step_us = match s.time.as_deref() {
        Some("wall") => None,
        Some(_) => Some(s.step_us.or(sync_step_us).unwrap_or(1000)),
        None => sync_step_us.map(|d| s.step_us.unwrap_or(d)),
    };
    let participant = s
        .participant
        .clone()
        .or(participant)
        .or(default_participant.map(str::to_string));
    if let Some(p) = &participant {
        canpos_host::silkit::check_name("participant name", p).map_err(|e| usage!("{e}"))?;
    }
    Ok(BusUrl::Silkit {
        host,
        port,
        network,
        participant,
        sync_step_us,
    }
    .to_string())
}

/// The URL of a second connection of the same process (the `--web` dashboard's): a silkit://
/// URL's participant name gets `-web`, as two participants cannot share a name.
pub fn second_connection_url(url: &str) -> String {
    match BusUrl::parse(url) {
        Ok(BusUrl::Silkit {
            host,
            port,
            network,
            participant,
            ..
        }) => BusUrl::Silkit {
            host,
            port,
            network,
            participant: participant.map(|p| format!("{p}-web")),
            // The dashboard watches: it takes no part in the time synchronisation.
            sync_step_us: None,
        }
        .to_string(),
        _ => url.to_string(),
    }
}

pub(crate) fn ms(v: u64) -> Duration {
    Duration::from_millis(v)
}

/// Parses a node-id: decimal or 0x-hex, within `min..=127`.
pub(crate) fn parse_node(s: &str, min: u8) -> Result<u8> {
    let v = parse_u64(s).ok_or_else(|| usage!("node-id `{s}` is not a number"))?;
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
    parse_u64(s)
        .and_then(|v| u8::try_from(v).ok())
        .ok_or_else(|| usage!("sub-index `{s}` is not 0..=255 (decimal, or hex with 0x)"))
}

pub(crate) fn parse_u32_arg(s: &str) -> Result<u32, String> {
    parse_u64(s)
        .and_then(|v| u32::try_from(v).ok())
        .ok_or_else(|| format!("`{s}` is not a 32-bit number (decimal or 0x-hex)"))
}

/// Default socketcand hub address.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:29536";

/// A receiver that gets one message per Ctrl-C / SIGTERM. Installed once per process.
pub fn stop_signal() -> Result<Receiver<()>> {
    let (tx, rx) = crossbeam_channel::unbounded();
    ctrlc::set_handler(move || {
        let _ = tx.send(());
    })
    .context("cannot install the Ctrl-C / SIGTERM handler")?;
    Ok(rx)
}

/// The pacing of a bus this process creates: `--bus-bitrate` (default 1000 kbit/s), or
/// instant when asked.
pub(crate) fn pacing(bitrate: Option<u32>, instant: bool) -> Pacing {
    if instant {
        Pacing::Instant
    } else {
        Pacing::Paced(bitrate.unwrap_or(canpos_host::bus::DEFAULT_BITRATE_KBPS))
    }
}

/// `--node-id`: 1…127 or 255.
pub fn parse_node_id(s: &str) -> Result<u8, String> {
    let v: u16 = parse_int(s).map_err(|_| format!("`{s}` is not a number"))?;
    match v {
        1..=127 | 255 => Ok(v as u8),
        _ => Err(format!(
            "{v} is out of range (1…127, or 255 = unconfigured)"
        )),
    }
}

fn parse_int(s: &str) -> Result<u16, std::num::ParseIntError> {
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => u16::from_str_radix(h, 16),
        None => s.parse(),
    }
}

/// `--bus-bitrate`: kbit/s (`250`) or bit/s (`250000`); must be a CAN bit rate.
pub fn parse_bitrate(s: &str) -> Result<u32, String> {
    let v: u32 = s
        .trim_end_matches("k")
        .parse()
        .map_err(|_| format!("`{s}` is not a number"))?;
    let kbps = if v >= 10_000 { v / 1000 } else { v };
    const OK: [u32; 9] = [10, 20, 50, 125, 250, 500, 800, 1000, 100];
    if OK.contains(&kbps) && (v < 10_000 || v.is_multiple_of(1000)) {
        Ok(kbps)
    } else {
        Err(format!(
            "{s} is not a CAN bit rate (kbit/s: 10, 20, 50, 100, 125, 250, 500, 800, 1000; or the same in bit/s)"
        ))
    }
}

/// A fresh private directory for the state files of sensors that only live as long as this
/// command (the demo, `soak`, `bench`): a random name under the temporary directory, created
/// exclusively with mode 0700, so nobody can have planted a directory or a link there ahead;
/// removed when dropped.
pub(crate) fn private_state_dir(tag: &str) -> anyhow::Result<tempfile::TempDir> {
    use anyhow::Context;
    tempfile::Builder::new()
        .prefix(&format!("canpos-{tag}-"))
        .tempdir()
        .with_context(|| {
            format!(
                "cannot create a state directory in {}",
                std::env::temp_dir().display()
            )
        })
}

/// The interface name written into candump logs: the socketcand channel, the SocketCAN
/// interface or the in-process bus name.
pub(crate) fn interface_name(url: &str) -> String {
    match BusUrl::parse(url) {
        Ok(BusUrl::Socketcand { channel, .. }) => channel,
        Ok(BusUrl::SocketCan { iface }) => iface,
        Ok(BusUrl::Mem { name }) => name,
        Ok(BusUrl::Silkit { network, .. }) => network,
        Err(_) => "can0".to_string(),
    }
}

/// Decimal, or hex with a `0x` prefix.
pub fn parse_u64(s: &str) -> Option<u64> {
    let s = s.trim();
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => u64::from_str_radix(h, 16).ok(),
        None => s.parse().ok(),
    }
}

/// Like [`parse_u64`] with an optional leading minus sign.
pub fn parse_i64(s: &str) -> Option<i64> {
    let s = s.trim();
    match s.strip_prefix('-') {
        Some(r) => parse_u64(r).and_then(|v| i64::try_from(v).ok()).map(|v| -v),
        None => parse_u64(s).and_then(|v| i64::try_from(v).ok()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bitrate_parsing() {
        assert_eq!(parse_bitrate("250"), Ok(250));
        assert_eq!(parse_bitrate("250000"), Ok(250));
        assert_eq!(parse_bitrate("1000"), Ok(1000));
        assert!(parse_bitrate("251").is_err());
        assert!(parse_bitrate("abc").is_err());
    }

    #[test]
    fn node_id_parsing() {
        assert_eq!(parse_node_id("127"), Ok(127));
        assert_eq!(parse_node_id("0x7F"), Ok(127));
        assert_eq!(parse_node_id("255"), Ok(255));
        assert!(parse_node_id("0").is_err());
        assert!(parse_node_id("128").is_err());
    }
}
