//! The device side of the command line: `bus serve`, `run`, `scenario`, `ctl` and the demo.

use std::io::Write as _;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, bail, Context as _, Result};
use canpos_core::models::{self, DeviceConfig};
use canpos_core::Frame;
use canpos_host::bus::Pacing;
use canpos_host::control::{self, Request};
use canpos_host::crossbeam_channel::{self, Receiver};
use canpos_host::runtime::{self, Runtime, RuntimeHandle, SensorSetup};
use canpos_host::{FileStorage, Hub, HubPolicy, Transport};
use canpos_sim::motion::{MotionSpec, Profile, Profiles};
use canpos_sim::{parse_order_code, SensorSpec};
use clap::{Args, Subcommand};
use serde::Deserialize;

/// Default socketcand hub address.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:29536";

/// Model names the command line accepts (some may not be built into the core yet).
const MODEL_NAMES: [&str; 3] = ["th", "e-series", "tmi"];

// ---------------------------------------------------------------------------------------------
// Ctrl-C / SIGTERM

/// A receiver that gets one message per Ctrl-C / SIGTERM. Installed once per process.
pub fn stop_signal() -> Result<Receiver<()>> {
    let (tx, rx) = crossbeam_channel::unbounded();
    ctrlc::set_handler(move || {
        let _ = tx.send(());
    })
    .context("cannot install the Ctrl-C / SIGTERM handler")?;
    Ok(rx)
}

// ---------------------------------------------------------------------------------------------
// bus serve

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
}

/// Options of `canpos bus bridge`.
#[derive(Debug, Args)]
pub struct BridgeArgs {
    /// The first bus (socketcan://IFACE, socketcand://HOST:PORT/CHANNEL or mem://NAME).
    pub a: String,
    /// The second bus.
    pub b: String,
}

/// Runs `canpos bus bridge`.
pub fn bus_bridge(args: BridgeArgs) -> Result<i32> {
    let stop_rx = stop_signal()?;
    if args.a == args.b {
        return Err(anyhow::Error::new(crate::master::Usage(format!(
            "both sides are `{}`: a bus bridged to itself would repeat every frame",
            args.a
        ))));
    }
    let open = |url: &str| {
        canpos_host::open(url).map_err(|e| match e {
            canpos_host::Error::BadUrl { .. } => {
                anyhow::Error::new(crate::master::Usage(e.to_string()))
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

/// The pacing of a bus this process creates: `--bus-bitrate` (default 1000 kbit/s), or
/// instant when asked.
pub(crate) fn pacing(bitrate: Option<u32>, instant: bool) -> Pacing {
    if instant {
        Pacing::Instant
    } else {
        Pacing::Paced(bitrate.unwrap_or(canpos_host::bus::DEFAULT_BITRATE_KBPS))
    }
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

// ---------------------------------------------------------------------------------------------
// Building a sensor

/// What selects and configures one simulated sensor (shared by `run` and scenario files).
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorOpts {
    /// `th`, `e-series` or `tmi`.
    pub model: Option<String>,
    /// With `model`: the position channels of the unit when it is not the model's default
    /// one (a two-channel TMI named by a DCF without `OrderCode`); not a scenario key.
    #[serde(skip)]
    pub unit_channels: Option<u8>,
    /// A product order code (selects model, stroke, resolution, bit rate, magnets).
    pub order_code: Option<String>,
    /// Node-id (1…127, 255 = unconfigured).
    pub node_id: Option<u8>,
    /// Serial number.
    pub serial: Option<u32>,
    /// Static magnet positions, mm.
    #[serde(default)]
    pub magnets: Vec<f64>,
    /// Motion spec.
    pub motion: Option<String>,
    /// No measurement errors.
    #[serde(default)]
    pub ideal: bool,
    /// Noise / unit error seed (default: the serial number).
    pub seed: Option<u64>,
    /// NMT state to put the node in right after its boot-up (`pre-operational`, the default
    /// as on a real unit, `operational` or `stopped`).
    pub nmt: Option<String>,
    /// Factor on the thermal time constants (electronics, waveguide); default 1.
    pub thermal_time_scale: Option<f64>,
    /// Delay before every SDO response, ms (default 0: the manuals state none).
    pub sdo_delay_ms: Option<f64>,
    /// Random extra delay of SDO responses, up to this many ms (default 0).
    pub sdo_jitter_ms: Option<f64>,
    /// Power-on to boot-up, ms (default 0).
    pub boot_delay_ms: Option<f64>,
    /// NMT reset (node or communication) to boot-up, ms (default 0).
    pub reset_boot_delay_ms: Option<f64>,
}

/// A problem with one option of a sensor: the option (its scenario key), and what is wrong.
#[derive(Debug)]
pub struct SetupError {
    /// The scenario key / option concerned, when one is.
    pub field: Option<&'static str>,
    /// What is wrong.
    pub error: anyhow::Error,
}

impl std::fmt::Display for SetupError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:#}", self.error)
    }
}

impl std::error::Error for SetupError {}

fn field_err(field: &'static str) -> impl FnOnce(anyhow::Error) -> SetupError {
    move |error| SetupError {
        field: Some(field),
        error,
    }
}

/// Something the sensor accepts, as a real unit would, but that is likely a mistake.
#[derive(Debug, Clone, PartialEq)]
pub struct SetupWarning {
    /// The scenario key / option concerned.
    pub field: &'static str,
    /// What to know.
    pub message: String,
}

/// A sensor ready to add to a runtime, and what its options gave reason to warn about.
pub struct Built {
    /// The runtime's description of the sensor.
    pub setup: SensorSetup,
    /// Warnings (the caller prints them with the right location).
    pub warnings: Vec<SetupWarning>,
    /// The NMT command to give the node after its boot-up, if any (`start`, `stop`).
    pub nmt: Option<&'static str>,
    /// The device's own timing (SDO response delay, boot delays).
    pub timing: canpos_host::timing::DeviceTiming,
}

/// The NMT state names `nmt` takes and the command that reaches each from pre-operational.
pub const NMT_STATES: [(&str, Option<&str>); 3] = [
    ("pre-operational", None),
    ("operational", Some("start")),
    ("stopped", Some("stop")),
];

/// Parses an `nmt` state name ([`NMT_STATES`]) into the command that reaches it.
pub fn parse_nmt_state(s: &str) -> Result<Option<&'static str>, String> {
    NMT_STATES
        .iter()
        .find(|(n, _)| n.eq_ignore_ascii_case(s.trim()))
        .map(|(_, c)| *c)
        .ok_or_else(|| {
            let names: Vec<_> = NMT_STATES.iter().map(|(n, _)| *n).collect();
            format!(
                "unknown NMT state `{s}`; expected one of: {}",
                names.join(", ")
            )
        })
}

fn sim_model(name: &str) -> Option<canpos_sim::Model> {
    canpos_sim::Model::ALL
        .into_iter()
        .find(|m| m.name() == name)
}

fn core_model(name: &str) -> Result<&'static models::Model> {
    if !MODEL_NAMES.contains(&name) {
        bail!(
            "unknown model `{name}`; expected one of: {}",
            MODEL_NAMES.join(", ")
        );
    }
    models::by_name(name).ok_or_else(|| {
        let have: Vec<_> = models::all().iter().map(|m| m.name).collect();
        anyhow!(
            "model `{name}` is not available in this build yet (available: {})",
            have.join(", ")
        )
    })
}

/// The unit an order code names: its model, the model's configuration with the code's stroke,
/// resolution, channels and bit rate, its measurement spec and the decoded code.
pub fn order_code_unit(
    code: &str,
) -> Result<(
    &'static models::Model,
    DeviceConfig,
    SensorSpec,
    canpos_sim::OrderCode,
)> {
    let oc = parse_order_code(code).with_context(|| format!("bad order code `{code}`"))?;
    let model = core_model(oc.model_name())?;
    let spec = oc.sensor_spec()?;
    let mut cfg = model.default_config;
    cfg.stroke_mm = oc.stroke_mm.round() as u32;
    cfg.position_step_nm = oc.resolution_nm();
    cfg.channels = oc.magnets as u8;
    cfg.bitrate_kbps = oc.bit_rate_kbit as u16;
    cfg.cycle_us = spec.cycle_time_us;
    Ok((model, cfg, spec, oc))
}

/// Builds the runtime's description of a sensor from the options, checking every value
/// against the model. The state file is not opened yet (see [`open_storage`]).
pub fn build_setup(o: &SensorOpts, state_dir: &Path) -> Result<Built, SetupError> {
    let mut warnings = Vec::new();
    let (model, mut cfg, spec): (&'static models::Model, DeviceConfig, SensorSpec) =
        match (&o.model, &o.order_code) {
            (Some(_), Some(_)) => {
                return Err(field_err("order_code")(anyhow!(
                    "give either a model or an order code, not both"
                )))
            }
            (_, Some(code)) => order_code_unit(code)
                .map(|(model, cfg, spec, _)| (model, cfg, spec))
                .map_err(field_err("order_code"))?,
            (m, None) => (|| {
                let name = m.as_deref().unwrap_or("th");
                let model = core_model(name)?;
                let mut cfg = model.default_config;
                if let Some(n) = o.unit_channels {
                    // Only a unit the model has (the widest one's channels at most).
                    cfg.channels = n.min(models::widest(model).default_config.channels);
                }
                let sm =
                    sim_model(name).ok_or_else(|| anyhow!("no measurement model for `{name}`"))?;
                let spec =
                    SensorSpec::for_model(sm, f64::from(cfg.stroke_mm), cfg.channels as usize)?;
                Ok((model, cfg, spec))
            })()
            .map_err(field_err("model"))?,
        };
    cfg.cycle_us = spec.cycle_time_us;
    let mut spec = spec;
    let mut timing = canpos_host::timing::DeviceTiming::default();
    for (field, v, slot) in [
        ("sdo_delay_ms", o.sdo_delay_ms, &mut timing.sdo_delay),
        ("sdo_jitter_ms", o.sdo_jitter_ms, &mut timing.sdo_jitter),
        ("boot_delay_ms", o.boot_delay_ms, &mut timing.boot_delay),
        (
            "reset_boot_delay_ms",
            o.reset_boot_delay_ms,
            &mut timing.reset_boot_delay,
        ),
    ] {
        if let Some(v) = v {
            *slot =
                canpos_host::timing::millis(field, v).map_err(|e| field_err(field)(anyhow!(e)))?;
        }
    }
    if let Some(k) = o.thermal_time_scale {
        // Bounded too: a huge factor would make the thermal model's arithmetic overflow.
        if !(k.is_finite() && k > 0.0 && k <= 1e6) {
            return Err(field_err("thermal_time_scale")(anyhow!(
                "thermal time scale {} must be a positive number, at most 1e6",
                control::show_num(k)
            )));
        }
        spec.thermal_time_constant_s *= k;
        spec.waveguide_time_constant_s *= k;
    }
    if let Some(id) = o.node_id {
        if !(1..=127).contains(&id) && id != 255 {
            return Err(field_err("node_id")(anyhow!(
                "node-id {id} is out of range (1…127, or 255 = unconfigured)"
            )));
        }
        cfg.node_id = id;
    }
    if let Some(s) = o.serial {
        cfg.serial = s;
    }
    let nmt = match &o.nmt {
        Some(n) => parse_nmt_state(n).map_err(|e| field_err("nmt")(anyhow!(e)))?,
        None => None,
    };
    let channels = usize::from(cfg.channels.max(1));
    let too_many = |n: usize| {
        anyhow!(
            "{n} magnets for a {} with {channels} position channel(s); give at most {channels} \
             (more channels come with the order code's magnet option; an additional magnet on \
             the rod is the extra-magnet fault)",
            model.name
        )
    };
    let motion: Box<dyn canpos_sim::motion::Motion> = match (&o.motion, o.magnets.is_empty()) {
        (Some(_), false) => {
            return Err(field_err("motion")(anyhow!(
                "give either magnet positions or a motion, not both"
            )))
        }
        (Some(m), true) => {
            let motion = MotionSpec::parse(m)
                .with_context(|| format!("bad motion spec `{m}`"))
                .and_then(|s| Ok(s.build()?))
                .map_err(field_err("motion"))?;
            if motion.magnets() > channels {
                return Err(field_err("motion")(too_many(motion.magnets())));
            }
            motion
        }
        (None, false) => {
            if o.magnets.len() > channels {
                return Err(field_err("magnets")(too_many(o.magnets.len())));
            }
            for &mm in &o.magnets {
                if !canpos_sim::motion::in_range(mm) {
                    return Err(field_err("magnets")(anyhow!(
                        "magnet position {} mm is not a finite number within ±{:e} mm",
                        control::show_num(mm),
                        canpos_sim::motion::MAX_MAGNITUDE
                    )));
                }
                if !(0.0..=spec.stroke_mm).contains(&mm) {
                    warnings.push(SetupWarning {
                        field: "magnets",
                        message: format!(
                            "magnet at {mm} mm is outside the stroke (0…{} mm); the sensor reports it as a real one would (out of range)",
                            spec.stroke_mm
                        ),
                    });
                }
            }
            if o.magnets.len() < channels {
                warnings.push(SetupWarning {
                    field: "magnets",
                    message: format!(
                        "{} magnet(s) for {channels} channels: the channels without a magnet report a missing magnet (EMCY 0x5000), as a real unit does",
                        o.magnets.len()
                    ),
                });
            }
            Box::new(Profiles(
                o.magnets
                    .iter()
                    .map(|&pos_mm| Profile::Static { pos_mm })
                    .collect(),
            ))
        }
        // Default: one magnet per channel, evenly spread over the stroke.
        (None, true) => {
            let n = f64::from(cfg.channels.max(1));
            Box::new(Profiles(
                (0..cfg.channels.max(1))
                    .map(|k| Profile::Static {
                        pos_mm: spec.stroke_mm * (f64::from(k) + 1.0) / (n + 1.0),
                    })
                    .collect(),
            ))
        }
    };
    let path = runtime::state_file(state_dir, model.name, cfg.serial);
    Ok(Built {
        setup: SensorSetup {
            name: format!("{}-{}", model.name, cfg.serial),
            model,
            cfg,
            spec,
            seed: o.seed.unwrap_or(u64::from(cfg.serial)),
            ideal: o.ideal,
            motion,
            storage: FileStorage::new(path).for_model(model),
        },
        warnings,
        nmt,
        timing,
    })
}

/// Opens the sensor's state file for use: locked against other processes, regular files only,
/// stale temporaries removed, the directory checked for writing (see [`FileStorage::open`]).
pub fn open_storage(setup: &mut SensorSetup) -> Result<()> {
    setup.storage = FileStorage::open(setup.storage.path())?.for_model(setup.model);
    Ok(())
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

// ---------------------------------------------------------------------------------------------
// run

/// Options of `canpos run`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// Product model: th, e-series or tmi (default th).
    #[arg(long, value_name = "MODEL", conflicts_with = "order_code")]
    pub model: Option<String>,
    /// Product order code, e.g. TH…C3041…: selects model, stroke, resolution, bit rate and magnets.
    #[arg(long, value_name = "CODE")]
    pub order_code: Option<String>,
    /// Node-id at first start (1…127; 255 = unconfigured, waits for LSS). Stored LSS values win.
    #[arg(long, value_name = "N", value_parser = parse_node_id)]
    pub node_id: Option<u8>,
    /// Serial number (0x1018/4); also names the state file.
    #[arg(long, value_name = "N")]
    pub serial: Option<u32>,
    /// Bus URL: socketcand://HOST:PORT/CHANNEL, socketcan://IFACE or mem://NAME. A socketcand URL
    /// where nothing listens starts an embedded hub there.
    #[arg(long, value_name = "URL", default_value = canpos_host::DEFAULT_URL)]
    pub bus: String,
    /// For a socketcand:// URL: `auto` starts an embedded hub (with a loud warning) when
    /// nothing listens at start-up; `always` starts one (an error if the address is taken);
    /// `never` waits for the server. Once connected, a lost server is waited for and
    /// reconnected to, never replaced.
    #[arg(long, value_name = "WHEN", default_value = "auto")]
    pub hub: HubPolicy,
    /// Bit rate of the bus in kbit/s (or bit/s); a node set to another rate falls silent. A
    /// `mem://` bus or an embedded hub this command starts runs at this rate (default 1000).
    #[arg(long, value_name = "KBPS", value_parser = parse_bitrate)]
    pub bus_bitrate: Option<u32>,
    /// A `mem://` bus or embedded hub this command starts delivers every frame at once, with
    /// no bit time and no limit (benchmarks; not a physical bus).
    #[arg(long)]
    pub instant_bus: bool,
    /// Directory of the state files (MODEL-SERIAL.bin). Default: $CANPOS_STATE_DIR,
    /// $XDG_STATE_HOME/canpos, ~/.local/state/canpos or ./canpos-state.
    #[arg(long, value_name = "DIR")]
    pub state_dir: Option<PathBuf>,
    /// A static magnet at MM (mm from the zero point); once per magnet.
    #[arg(long = "magnet", value_name = "MM", allow_negative_numbers = true)]
    pub magnets: Vec<f64>,
    /// Motion profile, e.g. sine:center=500,amp=200,period=4 or csv:FILE (see docs/CONTROL.md).
    #[arg(long, value_name = "SPEC", conflicts_with = "magnets")]
    pub motion: Option<String>,
    /// No measurement errors (linearity, noise, hysteresis, temperature).
    #[arg(long)]
    pub ideal: bool,
    /// Seed of the unit's errors and noise (default: the serial number).
    #[arg(long, value_name = "N")]
    pub seed: Option<u64>,
    /// Multiply the thermal time constants (electronics 600 s, waveguide 1200 s) by K, e.g.
    /// 0.01 to watch an ambient step settle in seconds (see docs/MEASUREMENT.md).
    #[arg(long, value_name = "K")]
    pub thermal_time_scale: Option<f64>,
    /// Serve the JSON-lines control interface on ADDR (e.g. 127.0.0.1:29600).
    #[arg(long, value_name = "ADDR")]
    pub control: Option<String>,
    /// Close a control connection that sends no complete request for S seconds (default 30;
    /// see docs/CONTROL.md).
    #[arg(long, value_name = "S", requires = "control", value_parser = crate::limits::parse_positive_seconds)]
    pub control_idle_timeout: Option<f64>,
    /// Serve a plain CiA 301 device described by this EDS file instead of a sensor (see
    /// docs/EDS_DEVICE.md).
    #[arg(long, value_name = "FILE", conflicts_with_all = EDS_CONFLICTS)]
    pub eds: Option<PathBuf>,
    /// Start from a DCF. A canpos model's DCF (`canpos dcf`; its ProductName and VendorNumber
    /// are a model's) starts that sensor with its order code, node-id, bit rate and values;
    /// any other DCF serves a plain CiA 301 device like --eds (docs/FILES.md). --node-id /
    /// --bus-bitrate win over the file.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["model", "order_code", "eds"])]
    pub dcf: Option<PathBuf>,
    /// NMT state right after the boot-up: operational or stopped (default pre-operational, as
    /// a real unit waits for its master).
    #[arg(long, value_name = "STATE", value_parser = |s: &str| parse_nmt_state(s).map(|_| s.to_string()))]
    pub nmt: Option<String>,
    /// Serve the web dashboard on ADDR (e.g. 127.0.0.1:29080; see docs/DASHBOARD.md).
    #[arg(long, value_name = "ADDR")]
    pub web: Option<String>,
    /// Delay every SDO response by MS milliseconds (default 0; the manuals state no response
    /// time). For testing a master's SDO timeout.
    #[arg(long, value_name = "MS", help_heading = "Device timing")]
    pub sdo_delay: Option<f64>,
    /// Up to MS more per SDO response, at random (reproducible per serial / seed).
    #[arg(long, value_name = "MS", help_heading = "Device timing")]
    pub sdo_jitter: Option<f64>,
    /// Boot-up MS milliseconds after power-on (default 0; the device is not on the bus until
    /// then).
    #[arg(long, value_name = "MS", help_heading = "Device timing")]
    pub boot_delay: Option<f64>,
    /// Boot-up MS milliseconds after an NMT reset (default 0; deaf and silent until then).
    #[arg(long, value_name = "MS", help_heading = "Device timing")]
    pub reset_boot_delay: Option<f64>,
}

/// The sensor options that mean nothing to a device served from an EDS / DCF file.
const EDS_CONFLICTS: [&str; 9] = [
    "model",
    "order_code",
    "magnets",
    "motion",
    "ideal",
    "seed",
    "thermal_time_scale",
    "control",
    // The EDS device runs without one; `canpos dashboard --eds NODE=FILE` shows it.
    "web",
];

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
                return Err(anyhow::Error::new(crate::master::Usage(e.to_string())))
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
fn bind_control(addr: Option<&str>) -> Result<Option<std::net::TcpListener>> {
    addr.map(|addr| {
        std::net::TcpListener::bind(addr)
            .with_context(|| format!("cannot serve the control interface on {addr}"))
    })
    .transpose()
}

fn start_control(
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
fn start_web(
    web: Option<&str>,
    url: &str,
    handle: &RuntimeHandle,
    sensors: usize,
) -> Result<Option<crate::dashboard::Dashboard>> {
    let Some(web) = web else { return Ok(None) };
    let bus =
        canpos_host::open(url).with_context(|| format!("dashboard: cannot connect to {url}"))?;
    crate::dashboard::start_for_runtime(web, bus, handle, sensors).map(Some)
}

/// Prints what each sensor of a started runtime really is, from its state: the active node-id
/// (a stored LSS node-id wins over the configured one) and bit rate.
fn banner(handle: &RuntimeHandle, count: usize, place: &str) -> Result<Vec<u8>> {
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

/// Runs `canpos run`.
pub fn run(a: RunArgs) -> Result<i32> {
    let model_dcf = match &a.dcf {
        Some(p) => crate::dcf::read_model_dcf(p)?,
        None => None,
    };
    if a.eds.is_some() || (a.dcf.is_some() && model_dcf.is_none()) {
        // A plain device: the sensor options mean nothing to it.
        let given = [
            ("--magnet", !a.magnets.is_empty()),
            ("--motion", a.motion.is_some()),
            ("--ideal", a.ideal),
            ("--seed", a.seed.is_some()),
            ("--thermal-time-scale", a.thermal_time_scale.is_some()),
            ("--control", a.control.is_some()),
        ];
        if let Some((flag, _)) = given.iter().find(|(_, g)| *g) {
            return Err(anyhow::Error::new(crate::master::Usage(format!(
                "{flag} is for sensors; the file is no canpos model's DCF (docs/FILES.md), it serves a plain device"
            ))));
        }
        return crate::eds_run::run(a);
    }
    let stop = stop_signal()?;
    let (model, order_code) = match &model_dcf {
        Some(d) if d.order_code.is_empty() => (Some(d.model.name.to_string()), None),
        Some(d) => (None, Some(d.order_code.clone())),
        None => (a.model, a.order_code),
    };
    let opts = SensorOpts {
        model,
        order_code,
        unit_channels: model_dcf.as_ref().and_then(|d| d.channels),
        node_id: a.node_id.or(model_dcf.as_ref().and_then(|d| d.node_id)),
        serial: a.serial.or(model_dcf.as_ref().and_then(|d| d.serial)),
        magnets: a.magnets,
        motion: a.motion,
        ideal: a.ideal,
        seed: a.seed,
        nmt: a.nmt,
        thermal_time_scale: a.thermal_time_scale,
        sdo_delay_ms: a.sdo_delay,
        sdo_jitter_ms: a.sdo_jitter,
        boot_delay_ms: a.boot_delay,
        reset_boot_delay_ms: a.reset_boot_delay,
    };
    let state_dir = a.state_dir.unwrap_or_else(runtime::default_state_dir);
    // A value the model cannot take is a bad command line (exit 2), like clap's own errors.
    let mut built = build_setup(&opts, &state_dir).map_err(|e| {
        anyhow::Error::new(crate::master::Usage(format!(
            "{}{e}",
            e.field
                .map(|f| format!("{}: ", flag_of(f)))
                .unwrap_or_default()
        )))
    })?;
    for w in &built.warnings {
        tracing::warn!("{}: {}", flag_of(w.field), w.message);
    }
    if let Some(d) = &model_dcf {
        if let Some(b) = d.bitrate_kbps {
            built.setup.cfg.bitrate_kbps = b;
        }
        let path = a.dcf.as_deref().unwrap_or(Path::new("?"));
        let state = built.setup.storage.path().to_path_buf();
        for (i, s, line, why) in crate::dcf::apply_to_state(d, built.setup.cfg, &state)? {
            tracing::warn!(
                "{}:{line}: 0x{i:04X}/{s} not applied ({why}); it keeps its previous value",
                path.display()
            );
        }
    }
    open_storage(&mut built.setup)?;
    let (transport, _hub) = open_bus(&a.bus, a.hub, &stop, pacing(a.bus_bitrate, a.instant_bus))?;
    let desc = transport.describe();
    let mut rt = Runtime::new(transport, a.bus_bitrate);
    let i = rt.add(built.setup);
    rt.set_timing(i, built.timing).map_err(|e| anyhow!(e))?;
    let listener = bind_control(a.control.as_deref())?;
    // Boot-up right away (≤ 50 ms after start); everything else comes after.
    rt.power_on_all();
    let handle = rt.spawn()?;
    banner(&handle, 1, &desc)?;
    start_nodes(&handle, &[built.nmt])?;
    let _ctl = start_control(listener, &handle, a.control_idle_timeout)?;
    let _web = start_web(a.web.as_deref(), &a.bus, &handle, 1)?;
    supervise(handle, &stop)
}

/// The `canpos run` option of a [`SensorOpts`] field.
fn flag_of(field: &str) -> String {
    match field {
        "magnets" => "--magnet".into(),
        // The timing keys of a scenario carry their unit; the flags say it in their help.
        f => format!("--{}", f.trim_end_matches("_ms").replace('_', "-")),
    }
}

/// Gives each sensor its start-up NMT command (`nmt = "operational"`).
fn start_nodes(handle: &RuntimeHandle, nmt: &[Option<&'static str>]) -> Result<()> {
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

// ---------------------------------------------------------------------------------------------
// ctl

/// Options of `canpos ctl`.
#[derive(Debug, Args)]
pub struct CtlArgs {
    /// Address of the control interface (the --control of `canpos run` / the scenario).
    #[arg(long, value_name = "ADDR")]
    pub control: String,
    /// Sensor index in a scenario (0-based; default 0).
    #[arg(long, value_name = "N")]
    pub sensor: Option<usize>,
    /// What to do.
    #[command(subcommand)]
    pub action: CtlAction,
}

/// `canpos ctl` actions.
#[derive(Debug, Subcommand)]
pub enum CtlAction {
    /// Move magnet N (0-based) to MM, or `none` to take it off the rod.
    Magnet {
        /// Magnet index (0-based).
        n: usize,
        /// Position in mm, or `none`.
        #[arg(allow_negative_numbers = true)]
        mm: String,
        /// Speed limit of the move in mm/s (jump when absent).
        #[arg(long, value_name = "MM_S")]
        velocity: Option<f64>,
    },
    /// Start a motion profile, e.g. sine:center=500,amp=200,period=4.
    Motion {
        /// The motion spec.
        spec: String,
    },
    /// Turn a fault on or off (missing-magnet, extra-magnet, magnets-too-close, sensor-error,
    /// supply-voltage, over-temperature, storage-corrupt, error-passive, bus-off, can-overrun,
    /// power-cycle).
    Fault {
        /// Fault name.
        name: String,
        /// on or off.
        #[arg(value_parser = ["on", "off"])]
        state: String,
        /// Fault parameter (extra magnet mm, supply V, temperature °C).
        #[arg(long, allow_negative_numbers = true)]
        value: Option<f64>,
        /// Channel for missing-magnet / magnets-too-close (0-based).
        #[arg(long)]
        channel: Option<usize>,
    },
    /// Power off and on again (stored data reloaded, boot-up sent).
    PowerCycle,
    /// Set the ambient temperature in °C.
    Ambient {
        /// °C.
        #[arg(allow_negative_numbers = true)]
        celsius: f64,
    },
    /// Hand the sensor an NMT command as if its master had sent it (nothing goes on the bus).
    Nmt {
        /// start, stop, preop, reset or reset-comm.
        #[arg(value_parser = ["start", "stop", "preop", "reset", "reset-comm"])]
        command: String,
    },
    /// Print the state (NMT, node-id, bit rate, true / reported positions, velocity, errors).
    State,
    /// Disturb the bus (paced virtual buses, docs/BUS.md): `corrupt PER_MILLION` (0 stops),
    /// `stuck-dominant MS`, `transceiver on|off` (this sensor's).
    BusFault {
        /// corrupt, stuck-dominant or transceiver.
        kind: String,
        /// Frames per million (corrupt), milliseconds (stuck-dominant), on / off (transceiver).
        value: String,
    },
}

/// Runs `canpos ctl`.
pub fn ctl(a: CtlArgs) -> Result<i32> {
    let sensor = a.sensor;
    let req = match a.action {
        CtlAction::Magnet { n, mm, velocity } => Request::Magnet {
            sensor,
            index: n,
            mm: if mm.eq_ignore_ascii_case("none") {
                None
            } else {
                Some(
                    mm.parse()
                        .map_err(|_| anyhow!("`{mm}` is not a position in mm (or `none`)"))?,
                )
            },
            velocity,
        },
        CtlAction::Motion { spec } => Request::Motion { sensor, spec },
        CtlAction::Fault {
            name,
            state,
            value,
            channel,
        } => Request::Fault {
            sensor,
            name,
            on: state == "on",
            value,
            channel,
        },
        CtlAction::PowerCycle => Request::PowerCycle { sensor },
        CtlAction::Ambient { celsius } => Request::Ambient { sensor, celsius },
        CtlAction::Nmt { command } => Request::Nmt { sensor, command },
        CtlAction::State => Request::State { sensor },
        CtlAction::BusFault { kind, value } => {
            let (value, on) = match value.as_str() {
                "on" => (None, Some(true)),
                "off" => (None, Some(false)),
                v => (
                    Some(v.parse::<f64>().map_err(|_| {
                        crate::master::Usage(format!("bus-fault value `{v}` is not a number"))
                    })?),
                    None,
                ),
            };
            Request::BusFault {
                sensor,
                kind,
                value,
                on,
            }
        }
    };
    let pretty = matches!(req, Request::State { .. });
    let answer = control::call(a.control.as_str(), &req, Duration::from_secs(10))
        .with_context(|| format!("cannot reach the control interface at {}", a.control))?;
    if answer["ok"] == true {
        if pretty {
            println!("{}", serde_json::to_string_pretty(&answer)?);
        } else {
            println!("{answer}");
        }
        Ok(0)
    } else {
        eprintln!(
            "error: {}",
            answer["error"].as_str().unwrap_or("request refused")
        );
        Ok(1)
    }
}

// ---------------------------------------------------------------------------------------------
// scenario

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

// ---------------------------------------------------------------------------------------------
// demo

/// Options of the demo (`canpos` with no arguments, `canpos [OPTIONS]`, or `canpos demo`).
#[derive(Debug, Args, Default)]
pub struct DemoArgs {
    /// Hub address (default 127.0.0.1:29536, or a free port when that one is taken).
    #[arg(long, value_name = "ADDR")]
    pub listen: Option<String>,
    /// Motion of the magnet.
    #[arg(
        long,
        value_name = "SPEC",
        default_value = "sine:center=500,amp=300,period=4"
    )]
    pub motion: String,
    /// Stop after this many seconds (default: until Ctrl-C).
    #[arg(long, value_name = "S", value_parser = crate::limits::parse_positive_seconds)]
    pub duration: Option<f64>,
    /// Serve the web dashboard on ADDR (default 127.0.0.1:29080, or a free port when that one
    /// is taken; docs/DASHBOARD.md).
    #[arg(long, value_name = "ADDR", conflicts_with = "no_web")]
    pub web: Option<String>,
    /// No web dashboard.
    #[arg(long)]
    pub no_web: bool,
    /// Serve the sensor's control interface on ADDR, for `canpos ctl --control ADDR …`
    /// (default 127.0.0.1:29600, or a free port when that one is taken; docs/CONTROL.md).
    #[arg(long, value_name = "ADDR", conflicts_with = "no_control")]
    pub control: Option<String>,
    /// No control interface.
    #[arg(long)]
    pub no_control: bool,
}

/// Default address of the demo's control interface (the README's `canpos ctl` examples).
pub const DEMO_CONTROL: &str = "127.0.0.1:29600";

/// Binds `asked` when given (its failure is an error: the user named it), else `default`, else
/// a free loopback port: a demo started twice, or beside another program on the default
/// port, still starts, and says where it went.
fn bind_or_free(asked: Option<&str>, default: &str, what: &str) -> Result<std::net::TcpListener> {
    if let Some(a) = asked {
        return std::net::TcpListener::bind(a)
            .with_context(|| format!("cannot serve the {what} on {a}"));
    }
    std::net::TcpListener::bind(default).or_else(|e| {
        let l = std::net::TcpListener::bind("127.0.0.1:0")
            .with_context(|| format!("cannot serve the {what} on a free loopback port"))?;
        eprintln!(
            "canpos: {default} is taken ({e}): the {what} is on {} instead",
            l.local_addr()?
        );
        Ok(l)
    })
}

fn sdo_upload(port: &mut dyn Transport, node: u8, index: u16, sub: u8) -> Result<u32> {
    let [lo, hi] = index.to_le_bytes();
    port.send(&Frame::new(0x600 + u16::from(node), &[0x40, lo, hi, sub, 0, 0, 0, 0]).unwrap())?;
    let end = std::time::Instant::now() + Duration::from_secs(1);
    while let Some(rx) = port.recv_deadline(end)? {
        let d = rx.frame.data();
        if rx.frame.std_id() == Some(0x580 + u16::from(node))
            && d.len() == 8
            && d[1..4] == [lo, hi, sub]
        {
            if d[0] == 0x80 {
                bail!(
                    "SDO abort {:#010x} reading {index:#06x}/{sub}",
                    u32::from_le_bytes([d[4], d[5], d[6], d[7]])
                );
            }
            return Ok(u32::from_le_bytes([d[4], d[5], d[6], d[7]]));
        }
    }
    bail!("no SDO answer reading {index:#06x}/{sub}")
}

/// Runs the demo.
pub fn demo(a: DemoArgs) -> Result<i32> {
    let stop = stop_signal()?;
    let hub = match &a.listen {
        Some(l) => Hub::bind(l.as_str()).with_context(|| format!("cannot listen on {l}"))?,
        None => Hub::bind(DEFAULT_LISTEN).or_else(|e| {
            let hub = Hub::bind("127.0.0.1:0").context("cannot start the hub")?;
            eprintln!(
                "canpos: {DEFAULT_LISTEN} is taken ({e}): the hub is on {} instead",
                hub.local_addr()
            );
            anyhow::Ok(hub)
        })?,
    };
    let addr: SocketAddr = hub.local_addr();
    warn_if_exposed(addr, "the bus");
    let node_port = hub.attach("can0");
    let mut mon = hub.attach("can0");
    let web_port = (!a.no_web).then(|| hub.attach("can0"));
    let hub = hub.spawn()?;
    // Bound before the sensor boots, as on `run`: whoever sees the boot-up can connect.
    let web_listener = (!a.no_web)
        .then(|| {
            bind_or_free(
                a.web.as_deref(),
                crate::dashboard::DEFAULT_LISTEN,
                "dashboard",
            )
        })
        .transpose()?;
    let control_listener = (!a.no_control)
        .then(|| bind_or_free(a.control.as_deref(), DEMO_CONTROL, "control interface"))
        .transpose()?;
    let state = crate::private_state_dir("demo")?;
    let state_dir = state.path().to_path_buf();
    let opts = SensorOpts {
        motion: Some(a.motion.clone()),
        ideal: false,
        ..SensorOpts::default()
    };
    let mut built = build_setup(&opts, &state_dir)?;
    open_storage(&mut built.setup)?;
    let setup = built.setup;
    let node = setup.cfg.node_id;
    let mut rt = Runtime::new(Box::new(node_port), None);
    rt.add(setup);
    rt.power_on_all();
    let handle = rt.spawn()?;
    // The view's SDO reads are done before the dashboard starts its scan: two SDO clients on
    // the sensor's one default channel (0x600 + node-id) at once send the same identifier with
    // other data, a bit error for both on a real bus, and they collided until both were error
    // passive (17 error frames on a healthy demo bus).
    let steps = demo_steps(&mut mon, node);
    // A closed stdout (`canpos | head`) ends the demo, as it ends `monitor`.
    let mut o = std::io::stdout();
    writeln!(
        o,
        "canpos demo: a Temposonics TH (node-id {node}) moving on {}",
        a.motion
    )?;
    writeln!(
        o,
        "  virtual bus: socketcand hub on {addr}, channel can0 — python-can: \
         can.Bus(interface=\"socketcand\", host=\"{}\", port={}, channel=\"can0\")",
        addr.ip(),
        addr.port()
    )?;
    let _web = match (web_listener, web_port) {
        (Some(l), Some(port)) => {
            let d = crate::dashboard::start_on(
                Box::new(port),
                l,
                crate::dashboard::Controls::Local(handle.control(), 1),
                30.0,
            )?;
            writeln!(o, "  dashboard: {}", d.url())?;
            Some(d)
        }
        _ => None,
    };
    let ctl = match control_listener {
        Some(l) => {
            let srv = control::serve_with(l, handle.control(), control::ServeOptions::default())
                .context("cannot serve the control interface")?;
            writeln!(
                o,
                "  control: {} (JSON lines, docs/CONTROL.md)",
                srv.local_addr()
            )?;
            Some(srv)
        }
        None => None,
    };
    // The next commands, with this demo's addresses: they reach its sensor as written.
    let bus_arg = if addr.to_string() == DEFAULT_LISTEN {
        String::new()
    } else {
        format!(" --bus socketcand://{addr}/can0")
    };
    writeln!(o, "  Try, in another terminal:")?;
    if let Some(srv) = &ctl {
        let c = srv.local_addr();
        writeln!(o, "    canpos ctl --control {c} state")?;
        writeln!(o, "    canpos ctl --control {c} fault missing-magnet on")?;
        writeln!(o, "    canpos ctl --control {c} fault missing-magnet off")?;
        writeln!(
            o,
            "    canpos ctl --control {c} motion sine:center=300,amp=100,period=2"
        )?;
    }
    writeln!(o, "    canpos sdo read {node} 0x6020 1{bus_arg}")?;
    writeln!(o, "    canpos monitor --node {node} --duration 2{bus_arg}")?;
    writeln!(o, "  Ctrl-C to stop.")?;
    let result = demo_view(&mut mon, node, steps, &handle, &stop, a.duration);
    writeln!(o)?;
    drop(ctl);
    let _ = handle.stop();
    let _ = hub.shutdown();
    drop(state);
    result.map(|()| 0)
}

/// The sensor's measuring steps (0x6005: position in nm, velocity in 0.01 mm/s), which scale
/// its PDO values; the encoder falls back to 1 µm and 1 mm/s when the dictionary has no
/// 0x6005, so the view does the same.
fn demo_steps(mon: &mut dyn Transport, node: u8) -> (f64, f64) {
    (
        f64::from(sdo_upload(mon, node, 0x6005, 1).unwrap_or(1000)),
        f64::from(sdo_upload(mon, node, 0x6005, 2).unwrap_or(100)),
    )
}

fn demo_view(
    mon: &mut dyn Transport,
    node: u8,
    (step_nm, vstep): (f64, f64),
    rt: &RuntimeHandle,
    stop: &Receiver<()>,
    duration: Option<f64>,
) -> Result<()> {
    // NMT start: the TPDOs begin.
    mon.send(&Frame::new(0x000, &[0x01, node]).unwrap())?;
    let tpdo1 = 0x180 + u16::from(node);
    let t0 = std::time::Instant::now();
    let mut next_print = t0;
    let mut count = 0u64;
    let mut last = None;
    loop {
        if stop.try_recv().is_ok() {
            return Ok(());
        }
        if duration.is_some_and(|d| t0.elapsed().as_secs_f64() >= d) {
            return Ok(());
        }
        if rt.is_finished() {
            bail!("the sensor stopped");
        }
        while let Some(rx) = mon.recv_deadline(next_print)? {
            if rx.frame.std_id() == Some(tpdo1) {
                count += 1;
                last = Some(rx.frame);
            }
        }
        next_print += Duration::from_millis(100);
        let st = rt.control().request(Request::State { sensor: None });
        let (pos, vel, cam) = match last {
            Some(f) if f.data().len() >= 7 => {
                let d = f.data();
                let p = i32::from_le_bytes([d[0], d[1], d[2], d[3]]);
                let v = i16::from_le_bytes([d[4], d[5]]);
                (
                    f64::from(p) * step_nm / 1e6,
                    f64::from(v) * vstep / 100.0,
                    d[6],
                )
            }
            _ => (f64::NAN, f64::NAN, 0),
        };
        let wa = st["work_area"][0].as_u64().unwrap_or(0);
        // How late the host ran the twin (its frames kept their times on the bus).
        let late_ms = st["clock"]["events_late_us"]["max"].as_f64().unwrap_or(0.0) / 1e3;
        write!(
            std::io::stdout(),
            "\r  {:<16} pos {pos:9.3} mm   vel {vel:+9.2} mm/s   cams {cam:04b}   work area {wa:03b}   TPDOs {count:<7} host late ≤ {late_ms:.1} ms ",
            st["nmt"].as_str().unwrap_or("?"),
        )?;
        std::io::stdout().flush()?;
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

    #[test]
    fn thermal_time_scale_scales_both_time_constants() {
        let dir = tempfile::tempdir().unwrap();
        let plain = build_setup(&SensorOpts::default(), dir.path())
            .unwrap()
            .setup
            .spec;
        let o = SensorOpts {
            thermal_time_scale: Some(0.01),
            ..SensorOpts::default()
        };
        let fast = build_setup(&o, dir.path()).unwrap().setup.spec;
        assert!((fast.thermal_time_constant_s - plain.thermal_time_constant_s * 0.01).abs() < 1e-9);
        assert!(
            (fast.waveguide_time_constant_s - plain.waveguide_time_constant_s * 0.01).abs() < 1e-9
        );
        for bad in [0.0, -1.0, f64::NAN, 1e300] {
            let o = SensorOpts {
                thermal_time_scale: Some(bad),
                ..SensorOpts::default()
            };
            assert!(build_setup(&o, dir.path()).is_err(), "{bad}");
        }
    }

    #[test]
    fn example_scenario_parses() {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples/scenario.toml");
        let dir = tempfile::tempdir().unwrap();
        let (checked, built) = crate::scenario::load(&p, Some(dir.path().into())).unwrap();
        assert!(checked.scenario.sensors.len() >= 2);
        assert!(!checked.scenario.events.is_empty());
        assert_eq!(built.len(), checked.scenario.sensors.len());
        assert_eq!(checked.warnings, Vec::<String>::new());
    }
}
