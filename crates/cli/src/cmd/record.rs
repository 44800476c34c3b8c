//! `canpos record`: the bus to pcapng, pcap, a candump -L log or Vector ASC.

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::PathBuf;
use std::time::{Instant, SystemTime};

use anyhow::{Context, Result};
use canpos_host::transport::Transport;
use clap::Args;

use crate::common::{interface_name, open_bus, usage, BusArg, EXIT_OK};

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
