//! `canpos dashboard`: serve the web dashboard of a bus.

use std::path::PathBuf;

use anyhow::Result;
use canpos_host::eds_device::{self, FileKind};
use clap::Args;

use crate::dashboard::{start, Controls, DEFAULT_LISTEN};

/// Options of `canpos dashboard`.
#[derive(Debug, Args)]
pub struct DashboardArgs {
    /// Bus URL: socketcand://HOST:PORT/CHANNEL, socketcan://IFACE, mem://NAME or
    /// silkit://HOST:PORT/NETWORK (docs/SILKIT.md).
    #[arg(long, value_name = "URL", default_value = canpos_host::DEFAULT_URL)]
    pub bus: String,
    /// Address to serve the page on (loopback unless you mean otherwise: no authentication).
    #[arg(long, value_name = "ADDR", default_value = DEFAULT_LISTEN)]
    pub listen: String,
    /// A control interface of canpos sensors on the bus (their --control ADDR); repeatable.
    /// Without one the page shows the bus but cannot drive the sensors.
    #[arg(long = "control", value_name = "ADDR")]
    pub controls: Vec<String>,
    /// The object table of node N from an EDS (or DCF) file, for devices that are none of the
    /// sensor models (`--eds 20=examples/io-device.eds`); repeatable.
    #[arg(long = "eds", value_name = "NODE=FILE", value_parser = parse_eds_arg)]
    pub eds: Vec<(u8, PathBuf)>,
    /// The bus's bit rate in kbit/s (or bit/s; a CiA 301 rate), for the bus load in the
    /// header. Default: the bus's own where the connection names it (an in-process bus), else
    /// a sensor's (--control), else 1000 kbit/s, shown as assumed: a socketcand hub names none.
    #[arg(long, value_name = "KBPS", value_parser = crate::common::parse_bitrate)]
    pub bitrate: Option<u32>,
    /// Seconds of history in the plots.
    #[arg(long, value_name = "S", default_value_t = 30.0, value_parser = crate::limits::parse_positive_seconds)]
    pub window: f64,
}

fn parse_eds_arg(s: &str) -> Result<(u8, PathBuf), String> {
    let (node, file) = s
        .split_once('=')
        .ok_or_else(|| format!("`{s}`: expected NODE=FILE"))?;
    let id = crate::common::parse_node(node, 1).map_err(|e| e.to_string())?;
    Ok((id, PathBuf::from(file)))
}

/// `canpos dashboard`.
pub fn dashboard(a: DashboardArgs) -> Result<i32> {
    let stop = crate::common::stop_signal()?;
    // Every file is checked before anything starts.
    let mut tables = Vec::new();
    for (id, file) in &a.eds {
        let kind = match file.extension().and_then(|e| e.to_str()) {
            Some(e) if e.eq_ignore_ascii_case("dcf") => FileKind::Dcf,
            _ => FileKind::Eds,
        };
        let dev = eds_device::load(
            file,
            kind,
            &eds_device::Overrides {
                node_id: Some(*id),
                bitrate_kbps: None,
                serial: None,
            },
        )?;
        tables.push((*id, &dev.model.table));
    }
    let bus = crate::common::open_bus(&a.bus)?;
    let d = start(bus, &a.listen, Controls::Remote(a.controls), a.window)?;
    // A hub that goes away is waited for and reconnected to, as `canpos run --hub never` does
    // (issue 38 item 7); the page says so meanwhile.
    let url = a.bus.clone();
    d.reconnect_with(Box::new(move || {
        canpos_host::open(&url).map_err(std::io::Error::other)
    }));
    if let Some(kbps) = a.bitrate {
        d.set_bitrate(kbps);
    }
    for (id, model) in tables {
        d.pin_model(id, model);
    }
    println!("canpos dashboard: {} on {}", d.url(), a.bus);
    let _ = stop.recv();
    Ok(0)
}
