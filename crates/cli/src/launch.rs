//! Starting simulated devices in this process: their bus (or an embedded hub), the control
//! interface, the `--web` dashboard, the banner, the start-up NMT commands, and supervision
//! until Ctrl-C.

use std::time::Duration;

use anyhow::{anyhow, bail, Context as _, Result};
use canpos_host::bus::Pacing;
use canpos_host::control::{self, Request};
use canpos_host::crossbeam_channel::Receiver;
use canpos_host::runtime::RuntimeHandle;
use canpos_host::{HubPolicy, Transport};

/// See [`canpos_host::warn_if_exposed`].
pub use canpos_host::warn_if_exposed;

/// Opens a device's bus (or hosts it, as `policy` allows), reporting what happened. With
/// [`HubPolicy::Never`] it waits for the server, with back-off, until Ctrl-C (`stop`).
pub(crate) fn open_bus(
    url: &str,
    policy: HubPolicy,
    stop: &Receiver<()>,
    pacing: Pacing,
) -> Result<(Box<dyn Transport>, Option<canpos_host::HubHandle>)> {
    let mut backoff = canpos_host::socketcand::reconnect::Backoff::default();
    let (t, hub) = loop {
        match canpos_host::transport::open_device_bus_with(url, policy, pacing) {
            Ok(x) => break x,
            Err(e @ canpos_host::Error::BadUrl { .. }) => {
                return Err(anyhow::Error::new(crate::common::Usage(e.to_string())))
            }
            Err(e) if policy == HubPolicy::Never && e.is_connection_refused() => {
                let wait = backoff.next_wait();
                eprintln!("canpos: no socketcand server listens at {url} yet (--hub never); retrying in {wait:?}");
                if stop.recv_timeout(wait).is_ok() {
                    bail!("stopped while waiting for the socketcand server at {url}");
                }
            }
            Err(e) => return Err(anyhow::Error::new(e)),
        }
    };
    if let Some(h) = &hub {
        warn_if_exposed(h.local_addr(), "the bus");
        if policy == HubPolicy::Auto {
            // Loud: a socketcand daemon meant to serve this address cannot bind it now.
            eprintln!(
                "canpos: WARNING: nothing listened at {url}, so this process started an EMBEDDED \
                 socketcand hub on {addr}.\n\
                 canpos:   Other tools can join it there; it ends with this process. A socketcand \
                 daemon or `canpos bus serve` started later cannot bind {addr}.\n\
                 canpos:   Meant a server that is still starting? Use --hub never (wait for it); \
                 --hub always asks for the embedded hub and silences this warning.",
                addr = h.local_addr()
            );
            tracing::warn!(addr = %h.local_addr(), "started an embedded socketcand hub");
        } else {
            eprintln!("canpos: embedded socketcand hub on {}", h.local_addr());
        }
    }
    Ok((t, hub))
}

/// Waits for Ctrl-C or for the runtime to end by itself; then stops it.
pub(crate) fn supervise(handle: RuntimeHandle, stop: &Receiver<()>) -> Result<i32> {
    loop {
        if stop.recv_timeout(Duration::from_millis(100)).is_ok() {
            let late = handle.stop()?;
            tracing::info!(%late, "stopped");
            return Ok(0);
        }
        if handle.is_finished() {
            return match handle.join() {
                Ok(_) => Ok(0),
                Err(e) => Err(anyhow!("the bus connection ended: {e}")),
            };
        }
    }
}

/// Binds the control interface's address; done before the sensors boot, so that whoever
/// sees a boot-up can connect to the control interface at once.
pub(crate) fn bind_control(addr: Option<&str>) -> Result<Option<std::net::TcpListener>> {
    addr.map(|addr| {
        std::net::TcpListener::bind(addr)
            .with_context(|| format!("cannot serve the control interface on {addr}"))
    })
    .transpose()
}

pub(crate) fn start_control(
    listener: Option<std::net::TcpListener>,
    rt: &RuntimeHandle,
    idle_timeout_s: Option<f64>,
) -> Result<Option<control::ControlServer>> {
    let Some(listener) = listener else {
        return Ok(None);
    };
    let mut options = control::ServeOptions::default();
    if let Some(s) = idle_timeout_s {
        // Checked by the value parser: finite, > 0, at most 1e9 s.
        options.idle_timeout = Duration::from_secs_f64(s);
    }
    let srv = control::serve_with(listener, rt.control(), options)
        .context("cannot serve the control interface")?;
    eprintln!("canpos: control interface on {}", srv.local_addr());
    Ok(Some(srv))
}

/// `--web ADDR`: the dashboard on a connection of its own to the runtime's bus.
pub(crate) fn start_web(
    web: Option<&str>,
    url: &str,
    handle: &RuntimeHandle,
    sensors: usize,
) -> Result<Option<crate::dashboard::Dashboard>> {
    let Some(web) = web else { return Ok(None) };
    let url = &crate::common::second_connection_url(url);
    let bus =
        canpos_host::open(url).with_context(|| format!("dashboard: cannot connect to {url}"))?;
    crate::dashboard::start_for_runtime(web, bus, handle, sensors).map(Some)
}

/// Prints what each sensor of a started runtime really is, from its state: the active node-id
/// (a stored LSS node-id wins over the configured one) and bit rate.
pub(crate) fn banner(handle: &RuntimeHandle, count: usize, place: &str) -> Result<Vec<u8>> {
    let mut ids = Vec::new();
    for i in 0..count {
        let st = handle.control().request(Request::State { sensor: Some(i) });
        if st["ok"] != true {
            bail!(
                "sensor {i} did not report its state: {}",
                st["error"].as_str().unwrap_or("no answer")
            );
        }
        let id = st["node_id"].as_u64().unwrap_or(255) as u8;
        let id_text = if id == 255 {
            "no node-id (255, LSS unconfigured)".to_string()
        } else {
            format!("node-id {id}")
        };
        eprintln!(
            "canpos: sensor {i}: {} ({id_text}, {} kbit/s) on {place}; state file {}",
            st["name"].as_str().unwrap_or("?"),
            st["bitrate_kbps"],
            st["storage"].as_str().unwrap_or("?"),
        );
        ids.push(id);
    }
    Ok(ids)
}

/// The `canpos run` option of a [`SensorOpts`] field.
pub(crate) fn flag_of(field: &str) -> String {
    match field {
        "magnets" => "--magnet".into(),
        // The timing keys of a scenario carry their unit; the flags say it in their help.
        f => format!("--{}", f.trim_end_matches("_ms").replace('_', "-")),
    }
}

/// Gives each sensor its start-up NMT command (`nmt = "operational"`).
pub(crate) fn start_nodes(handle: &RuntimeHandle, nmt: &[Option<&'static str>]) -> Result<()> {
    for (i, cmd) in nmt.iter().enumerate() {
        if let Some(cmd) = cmd {
            let r = handle.control().request(Request::Nmt {
                sensor: Some(i),
                command: (*cmd).to_string(),
            });
            if r["ok"] != true {
                bail!(
                    "sensor {i}: NMT {cmd} at start: {}",
                    r["error"].as_str().unwrap_or("refused")
                );
            }
            tracing::info!(sensor = i, command = cmd, "NMT at start");
        }
    }
    Ok(())
}
