//! `canpos bus`: serve or bridge virtual CAN buses.

use std::io::Write as _;
use std::time::Duration;

use anyhow::{anyhow, Context as _, Result};
use canpos_host::bus::Pacing;
use canpos_host::{Hub, Transport};
use clap::{Args, Subcommand};

use crate::common::{pacing, parse_bitrate, stop_signal, DEFAULT_LISTEN};
use crate::launch::warn_if_exposed;

/// `canpos bus …`
#[derive(Debug, Subcommand)]
pub enum BusCmd {
    /// Serve a virtual CAN bus over the socketcand protocol (python-can `interface="socketcand"`).
    ///
    /// Every channel name is its own isolated bus shared by all connected clients. Prints the
    /// address it listens on and runs until Ctrl-C / SIGTERM.
    Serve(ServeArgs),
    /// Join two buses into one: every frame of one is sent on the other, remote frames
    /// included, e.g. `canpos bus bridge socketcan://vcan0 socketcand://127.0.0.1:29536/can0`.
    ///
    /// Both buses must be there: a URL where nothing is gets an error (exit 1). Runs until
    /// Ctrl-C / SIGTERM or until one side goes away (exit 1).
    Bridge(BridgeArgs),
    /// Simulate Vector SIL Kit CAN networks with canpos's bus timeline: bit time, arbitration,
    /// end-of-frame times, acknowledgement only of the frame that won the bus, error counters
    /// and bus-off (docs/SILKIT.md). Runs until Ctrl-C / SIGTERM, SIL Kit's stop or
    /// `--duration`, then prints one JSON line of counters per network.
    Netsim(crate::cmd::netsim::NetsimArgs),
}

/// Options of `canpos bus bridge`.
#[derive(Debug, Args)]
pub struct BridgeArgs {
    /// The first bus (socketcan://IFACE, socketcand://HOST:PORT/CHANNEL, mem://NAME or
    /// silkit://HOST:PORT/NETWORK).
    pub a: String,
    /// The second bus.
    pub b: String,
}

/// Runs `canpos bus bridge`.
pub fn bus_bridge(args: BridgeArgs) -> Result<i32> {
    let stop_rx = stop_signal()?;
    if args.a == args.b {
        return Err(anyhow::Error::new(crate::common::Usage(format!(
            "both sides are `{}`: a bus bridged to itself would repeat every frame",
            args.a
        ))));
    }
    let open = |url: &str| {
        canpos_host::open(url).map_err(|e| match e {
            canpos_host::Error::BadUrl { .. } => {
                anyhow::Error::new(crate::common::Usage(e.to_string()))
            }
            e => anyhow::Error::new(e).context(format!("cannot bridge to `{url}`")),
        })
    };
    let mut a = open(&args.a)?;
    let mut b = open(&args.b)?;
    eprintln!("canpos: bridging {} <-> {}", a.describe(), b.describe());
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let s2 = stop.clone();
    std::thread::spawn(move || {
        if stop_rx.recv().is_ok() {
            s2.store(true, std::sync::atomic::Ordering::Relaxed);
        }
    });
    let r = canpos_host::bridge::run(&mut *a, &mut *b, &stop);
    match r {
        Ok(st) => {
            eprintln!(
                "canpos: bridge stopped: {} frames forwarded {} -> {}, {} back, {} not forwardable",
                st.a_to_b, args.a, args.b, st.b_to_a, st.unsendable
            );
            Ok(0)
        }
        Err(e) => Err(anyhow!("the bridge ended: {e}")),
    }
}

/// Options of `canpos bus serve`.
#[derive(Debug, Args)]
pub struct ServeArgs {
    /// Address to listen on (loopback by default; other addresses only when given here).
    #[arg(long, value_name = "ADDR", default_value = DEFAULT_LISTEN)]
    pub listen: String,
    /// Most clients connected at once (kept below the open-file limit); one more is refused
    /// with `< error too many clients >`.
    #[arg(long, value_name = "N", default_value_t = 10_000,
          value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub max_clients: u32,
    /// Seconds a client has from connecting to opening a channel (`< open … >`).
    #[arg(long, value_name = "S", default_value_t = 10.0,
          value_parser = crate::limits::parse_positive_seconds)]
    pub handshake_timeout: f64,
    /// Close a client on a channel that sends nothing for this many seconds (default: never;
    /// listen-only clients are normal).
    #[arg(long, value_name = "S", value_parser = crate::limits::parse_positive_seconds)]
    pub idle_timeout: Option<f64>,
    /// Give bus errors (`< error … >`) to every raw and BCM client, as socketcand does when
    /// started with an error mask (default: only to clients that ask with `< errors on >`).
    #[arg(long)]
    pub error_frames: bool,
    /// Bit rate of every channel in kbit/s (or bit/s; a CiA 301 rate): frames take their time
    /// on the wire, one at a time (default 1000, see docs/BUS.md).
    #[arg(long, value_name = "KBPS", value_parser = parse_bitrate, conflicts_with = "instant")]
    pub bitrate: Option<u32>,
    /// Deliver every frame at once, with no bit time and no limit (benchmarks; not a
    /// physical bus).
    #[arg(long)]
    pub instant: bool,
    /// Log each channel's load and frame rate every this many seconds (0: never).
    #[arg(long, value_name = "S", default_value_t = 10.0)]
    pub stats_interval: f64,
}

/// Runs `canpos bus serve`.
pub fn bus_serve(args: ServeArgs) -> Result<i32> {
    let stop = stop_signal()?;
    let config = canpos_host::socketcand::HubConfig {
        max_clients: args.max_clients as usize,
        handshake_timeout: Duration::from_secs_f64(args.handshake_timeout),
        idle_timeout: args.idle_timeout.map(Duration::from_secs_f64),
        error_frames: args.error_frames,
        pacing: pacing(args.bitrate, args.instant),
        ..Default::default()
    };
    let hub = Hub::bind_with(args.listen.as_str(), config)
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    let addr = hub.local_addr();
    warn_if_exposed(addr, "the bus");
    let handle = hub.spawn().context("cannot start the hub")?;
    let rate = match pacing(args.bitrate, args.instant) {
        Pacing::Paced(k) => format!("{k} kbit/s"),
        Pacing::Instant => "instant, unpaced".into(),
    };
    println!(
        "canpos bus: socketcand hub listening on {addr} (any channel name, e.g. can0; {rate})"
    );
    let _ = std::io::stdout().flush();
    let every = (args.stats_interval.is_finite() && args.stats_interval > 0.0)
        .then(|| Duration::from_secs_f64(args.stats_interval.min(86_400.0)));
    let mut next_log = every.map(|e| std::time::Instant::now() + e);
    while handle.is_running() {
        if stop.recv_timeout(Duration::from_millis(200)).is_ok() {
            break;
        }
        if let (Some(t), Some(e)) = (next_log, every) {
            if std::time::Instant::now() >= t {
                for (channel, s) in handle.channel_stats() {
                    tracing::info!(
                        %channel,
                        load_pct = format!("{:.1}", s.load * 100.0),
                        frames_per_s = format!("{:.0}", s.frames_per_s),
                        frames = s.frames,
                        error_frames = s.error_frames,
                        tx_lost = s.tx_lost,
                        rx_dropped = s.rx_dropped,
                        "bus load"
                    );
                }
                next_log = Some(t + e);
            }
        }
    }
    tracing::info!(stats = ?handle.stats(), "hub stopping");
    handle.shutdown().context("hub shutdown")?;
    Ok(0)
}
