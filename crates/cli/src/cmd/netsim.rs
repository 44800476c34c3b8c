//! `canpos bus netsim`: canpos's bus timeline as the CAN network simulator of a Vector SIL Kit
//! network (issue 32 item 3, docs/SILKIT.md "canpos as the network simulator").

use std::io::Write as _;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use canpos_host::silkit::netsim::{NetworkReport, NetworkSpec, Simulator, TimeMode};
use canpos_host::silkit::{check_name, sys, RegistryUri};
use clap::{Args, ValueEnum};

use crate::common::{parse_bitrate, stop_signal, Usage};

/// Time modes of `canpos bus netsim`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum NetsimTime {
    /// The simulator's own monotonic clock (participants not synchronised).
    Wall,
    /// SIL Kit's simulation time (a synchronised participant; deterministic).
    Sync,
}

/// Options of `canpos bus netsim`.
#[derive(Debug, Args)]
pub struct NetsimArgs {
    /// The SIL Kit registry, `silkit://HOST:PORT`.
    #[arg(long, value_name = "URI")]
    pub registry: String,
    /// A CAN network to simulate (SIL Kit network name); repeat for several networks in this
    /// one process.
    #[arg(long = "network", value_name = "NAME", required = true)]
    pub networks: Vec<String>,
    /// Bit rate of the networks in kbit/s (or bit/s; a CiA 301 rate).
    #[arg(long, value_name = "KBPS", value_parser = parse_bitrate)]
    pub bitrate: u32,
    /// Time mode: `wall` (the simulator's clock) or `sync` (SIL Kit's simulation time).
    #[arg(long, value_enum, default_value_t = NetsimTime::Wall)]
    pub time: NetsimTime,
    /// Simulation step in µs (`--time sync`; default 40 bit times: 320 µs at 125 kbit/s). Keep
    /// it shorter than the shortest frame (44 bit times to its end of frame): then every
    /// receiver has each frame before its step passes the frame's end (D40).
    #[arg(long, value_name = "US",
          value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    pub step_us: Option<u64>,
    /// Coordinated lifecycle (`--time sync`): a system controller starts and stops the
    /// simulation (default: autonomous, it joins a running simulation).
    #[arg(long)]
    pub coordinated: bool,
    /// SIL Kit participant name.
    #[arg(long, value_name = "NAME", default_value = "canpos-netsim")]
    pub participant: String,
    /// Log every network's counters every this many seconds (0: never).
    #[arg(long, value_name = "S", default_value_t = 10.0)]
    pub stats_interval: f64,
    /// Stop after this many seconds (default: at Ctrl-C / SIGTERM or SIL Kit's stop).
    #[arg(long, value_name = "S", value_parser = crate::limits::parse_positive_seconds)]
    pub duration: Option<f64>,
}

/// `silkit://HOST:PORT` (no path; an IPv6 host in brackets): the registry's address.
fn registry_uri(s: &str) -> Result<RegistryUri, String> {
    let bad = || format!("`{s}` is not silkit://HOST:PORT");
    let rest = s.strip_prefix("silkit://").ok_or_else(bad)?;
    let (host, port) = rest.rsplit_once(':').ok_or_else(bad)?;
    let host = match host.strip_prefix('[') {
        Some(h) => h.strip_suffix(']').ok_or_else(bad)?,
        None => host,
    };
    let port: u16 = port.parse().map_err(|_| bad())?;
    if host.is_empty() || host.contains(['/', '[', ']']) || port == 0 {
        return Err(bad());
    }
    Ok(RegistryUri {
        host: host.to_string(),
        port,
    })
}

/// Runs `canpos bus netsim`.
pub fn bus_netsim(args: NetsimArgs) -> Result<i32> {
    let usage = |m: String| anyhow::Error::new(Usage(m));
    let uri = registry_uri(&args.registry).map_err(usage)?;
    let mut specs = Vec::new();
    for n in &args.networks {
        check_name("network name", n).map_err(usage)?;
        if specs.iter().any(|s: &NetworkSpec| &s.name == n) {
            return Err(usage(format!("network `{n}` given twice")));
        }
        specs.push(NetworkSpec {
            name: n.clone(),
            kbps: args.bitrate,
        });
    }
    let api = sys::api().map_err(|e| anyhow!(e))?;
    let mode = match args.time {
        NetsimTime::Wall => TimeMode::Wall,
        NetsimTime::Sync => {
            let bit = 1_000_000 / u64::from(args.bitrate); // ns
            let step = args.step_us.map_or(40 * bit, |us| us * 1000);
            if step >= 44 * bit {
                tracing::warn!(
                    step_us = step / 1000,
                    "a step as long as the shortest frame: a receiver may get a frame only after \
                     its step passed the frame's end, and synchronised runs may differ (D40)"
                );
            }
            TimeMode::Sync {
                step,
                coordinated: args.coordinated,
            }
        }
    };
    let stop = stop_signal()?;
    check_name("participant name", &args.participant).map_err(usage)?;
    let sim = Simulator::start(api, &uri, &args.participant, &specs, mode)
        .map_err(|e| anyhow!("canpos bus netsim: {e}"))?;
    println!(
        "canpos bus netsim: simulating {} at {} kbit/s as participant {} at {uri} ({})",
        args.networks.join(", "),
        args.bitrate,
        args.participant,
        match mode {
            TimeMode::Wall => "wall clock".to_string(),
            TimeMode::Sync { step, .. } => format!("synchronised, {} µs steps", step / 1000),
        }
    );
    let _ = std::io::stdout().flush();
    let every = (args.stats_interval.is_finite() && args.stats_interval > 0.0)
        .then(|| Duration::from_secs_f64(args.stats_interval.min(86_400.0)));
    let started = Instant::now();
    let end = args.duration.map(|d| started + Duration::from_secs_f64(d));
    let mut next_log = every.map(|e| started + e);
    let reason = loop {
        if stop.recv_timeout(Duration::from_millis(200)).is_ok() {
            break "signal";
        }
        if sim.is_stopped() {
            break "SIL Kit stopped the simulation";
        }
        if end.is_some_and(|t| Instant::now() >= t) {
            break "duration";
        }
        if let (Some(t), Some(e)) = (next_log, every) {
            if Instant::now() >= t {
                for r in sim.report() {
                    log_report(&r);
                }
                next_log = Some(t + e);
            }
        }
    };
    let reports = sim.report();
    drop(sim);
    for r in &reports {
        println!("{}", summary(r));
    }
    tracing::info!(reason, "canpos bus netsim stopped");
    Ok(0)
}

fn log_report(r: &NetworkReport) {
    tracing::info!(
        network = %r.name,
        bus_time_s = format!("{:.3}", r.reached as f64 / 1e9),
        load_pct = format!("{:.1}", r.load.0 * 100.0),
        frames = r.counters.frames,
        deliveries = r.counters.deliveries,
        queue_full = r.counters.queue_full,
        canceled = r.counters.canceled,
        controllers = r.controllers.len(),
        "network"
    );
}

/// One JSON line per network at exit: what the scale benchmark reads.
fn summary(r: &NetworkReport) -> String {
    let ctrls: Vec<serde_json::Value> = r
        .controllers
        .iter()
        .map(|c| (c, false))
        .chain(r.departed.iter().map(|c| (c, true)))
        .map(|((d, mode, st), left)| {
            serde_json::json!({
                "descriptor": d,
                "left": left,
                "mode": format!("{mode:?}"),
                "state": st.map(|s| format!("{:?}", s.state)),
                "tec": st.map(|s| s.tec),
                "rec": st.map(|s| s.rec),
                "sent": st.map(|s| s.sent),
                "lost_overflow": st.map(|s| s.lost_overflow),
                "lost_bus_off": st.map(|s| s.lost_bus_off),
            })
        })
        .collect();
    serde_json::json!({
        "network": r.name,
        "bus_time_ns": r.reached,
        "frames": r.counters.frames,
        "deliveries": r.counters.deliveries,
        "queue_full": r.counters.queue_full,
        "canceled": r.counters.canceled,
        "bad_frames": r.counters.bad_frames,
        "controllers": ctrls,
    })
    .to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registry_uris() {
        assert_eq!(
            registry_uri("silkit://127.0.0.1:8500").unwrap().to_string(),
            "silkit://127.0.0.1:8500"
        );
        assert!(registry_uri("silkit://localhost:8500").is_ok());
        assert_eq!(registry_uri("silkit://[::1]:8500").unwrap().host, "::1");
        for bad in [
            "127.0.0.1:8500",
            "silkit://127.0.0.1",
            "silkit://:8500",
            "silkit://127.0.0.1:0",
            "silkit://127.0.0.1:99999",
            "silkit://127.0.0.1:8500/can0",
            "socketcand://127.0.0.1:8500",
            "silkit://[::1:8500",
        ] {
            assert!(registry_uri(bad).is_err(), "{bad}");
        }
    }
}
