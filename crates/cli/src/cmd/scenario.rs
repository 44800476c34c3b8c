//! `canpos scenario FILE`: several sensors on one bus with motion profiles and timed faults.

use std::path::PathBuf;

use anyhow::{anyhow, Context as _, Result};
use canpos_host::runtime::{self, Runtime};
use canpos_host::{HubPolicy, Transport};
use clap::Args;

use crate::common::{pacing, stop_signal};
use crate::launch::{
    banner, bind_control, open_bus, start_control, start_nodes, start_web, supervise,
};
use crate::sensor::open_storage;

/// Options of `canpos scenario`.
#[derive(Debug, Args)]
pub struct ScenarioArgs {
    /// The scenario file (TOML; see examples/scenario.toml).
    pub file: PathBuf,
    /// Override the file's bus URL.
    #[arg(long, value_name = "URL")]
    pub bus: Option<String>,
    /// Override the file's state directory.
    #[arg(long, value_name = "DIR")]
    pub state_dir: Option<PathBuf>,
    /// Override the file's control address.
    #[arg(long, value_name = "ADDR")]
    pub control: Option<String>,
    /// Close a control connection that sends no complete request for S seconds (default 30;
    /// see docs/CONTROL.md).
    #[arg(long, value_name = "S", value_parser = crate::limits::parse_positive_seconds)]
    pub control_idle_timeout: Option<f64>,
    /// Serve the web dashboard on ADDR (e.g. 127.0.0.1:29080; see docs/DASHBOARD.md).
    #[arg(long, value_name = "ADDR")]
    pub web: Option<String>,
    #[command(flatten)]
    pub silkit: crate::common::SilkitArgs,
    /// Embedded hub for a socketcand:// bus: auto, always or never (see `canpos run --help`).
    #[arg(long, value_name = "WHEN", default_value = "auto")]
    pub hub: HubPolicy,
}

/// Runs `canpos scenario`.
pub fn scenario(a: ScenarioArgs) -> Result<i32> {
    let stop = stop_signal()?;
    let (checked, built) = crate::scenario::load(&a.file, a.state_dir.clone())?;
    for w in &checked.warnings {
        tracing::warn!("{w}");
    }
    let mut sc = checked.scenario;
    let mut setups = Vec::new();
    let mut nmt = Vec::new();
    for (i, mut b) in built.into_iter().enumerate() {
        open_storage(&mut b.setup).with_context(|| format!("sensor {i}"))?;
        nmt.push(b.nmt);
        setups.push((b.setup, b.timing));
    }
    let url = a
        .bus
        .or(sc.bus.take())
        .unwrap_or_else(|| canpos_host::DEFAULT_URL.to_string());
    let url = crate::common::silkit_url(&url, &a.silkit, None)?;
    // SIL Kit's time starts once the start-up NMT states are set (synchronised mode).
    canpos_host::silkit::can::hold_starts();
    let (transport, _hub) = open_bus(&url, a.hub, &stop, pacing(checked.bus_bitrate, false))?;
    let desc = transport.describe();
    let mut rt = Runtime::new(transport, checked.bus_bitrate);
    let count = setups.len();
    for (s, timing) in setups {
        let i = rt.add(s);
        rt.set_timing(i, timing).map_err(|e| anyhow!(e))?;
    }
    let listener = bind_control(a.control.or(sc.control.take()).as_deref())?;
    rt.power_on_all();
    let handle = rt.spawn()?;
    let ids = banner(&handle, count, &desc)?;
    // The file's node-ids are distinct (checked); stored LSS node-ids may still collide.
    for (i, id) in ids.iter().enumerate() {
        if let Some(j) = ids[..i].iter().position(|x| x == id && *x != 255) {
            tracing::warn!(
                "sensors {j} and {i} are both on node-id {id} (a stored LSS node-id); their answers will collide"
            );
        }
    }
    start_nodes(&handle, &nmt)?;
    canpos_host::silkit::can::release_starts();
    let _ctl = start_control(listener, &handle, a.control_idle_timeout)?;
    let _web = start_web(a.web.as_deref(), &url, &handle, count)?;
    // Timed events on their own thread, on absolute times from the start.
    let ctl = handle.control();
    let mut events = std::mem::take(&mut sc.events);
    events.sort_by(|a, b| a.at.total_cmp(&b.at));
    let t0 = std::time::Instant::now();
    std::thread::Builder::new()
        .name("canpos-events".into())
        .spawn(move || {
            for e in events {
                // `at` is checked (≤ limits::MAX_SECONDS) when the file is loaded.
                let Some(when) = crate::limits::deadline(t0, e.at) else {
                    break;
                };
                runtime::sleep_until(when);
                let answer = ctl.request(e.request.clone());
                if answer["ok"] == true {
                    tracing::info!("event at {} s: {}", e.at, e.request);
                } else {
                    tracing::error!(
                        "event at {} s refused: {}: {}",
                        e.at,
                        e.request,
                        answer["error"].as_str().unwrap_or("no reason given")
                    );
                }
            }
        })
        .context("cannot start the event thread")?;
    if let Some(d) = sc.duration {
        if let Some(end) = crate::limits::deadline(t0, d) {
            loop {
                if stop.recv_deadline(end).is_ok() || std::time::Instant::now() >= end {
                    break;
                }
                if handle.is_finished() {
                    break;
                }
            }
            return match handle.stop() {
                Ok(_) => Ok(0),
                Err(e) => Err(anyhow!("the bus connection ended: {e}")),
            };
        }
    }
    supervise(handle, &stop)
}
