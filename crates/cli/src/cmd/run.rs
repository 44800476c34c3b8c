//! `canpos run`: one simulated sensor on a bus, or a plain CiA 301 device from a user's EDS or
//! DCF (`--eds FILE` / `--dcf FILE`, docs/EDS_DEVICE.md; the model is built by
//! `canpos_host::eds_device`, run by `canpos_host::plain`).

use std::path::{Path, PathBuf};

use anyhow::{anyhow, Result};
use canpos_host::eds_device::{self, FileKind, Overrides};
use canpos_host::plain::PlainRuntime;
use canpos_host::runtime::{self, Runtime};
use canpos_host::{FileStorage, HubPolicy, Transport};
use clap::Args;

use crate::common::{pacing, parse_bitrate, parse_node_id, stop_signal};
use crate::launch::{
    banner, bind_control, flag_of, open_bus, start_control, start_nodes, start_web, supervise,
};
use crate::sensor::{build_setup, open_storage, parse_nmt_state, SensorOpts};

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
    /// Bus URL: socketcand://HOST:PORT/CHANNEL, socketcan://IFACE, mem://NAME or
    /// silkit://HOST:PORT/NETWORK (docs/SILKIT.md). A socketcand URL where nothing listens
    /// starts an embedded hub there.
    #[arg(long, value_name = "URL", default_value = canpos_host::DEFAULT_URL)]
    pub bus: String,
    #[command(flatten)]
    pub silkit: crate::common::SilkitArgs,
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

/// The sensor options that mean nothing to a device served from an EDS / DCF file (its
/// `--control` and `--web` show its process objects and set its inputs instead).
const EDS_CONFLICTS: [&str; 7] = [
    "model",
    "order_code",
    "magnets",
    "motion",
    "ideal",
    "seed",
    "thermal_time_scale",
];

/// Runs `canpos run`.
pub fn run(a: RunArgs) -> Result<i32> {
    let model_dcf = match &a.dcf {
        Some(p) => crate::cmd::dcf::read_model_dcf(p)?,
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
        ];
        if let Some((flag, _)) = given.iter().find(|(_, g)| *g) {
            return Err(anyhow::Error::new(crate::common::Usage(format!(
                "{flag} is for sensors; the file is no canpos model's DCF (docs/FILES.md), it serves a plain device"
            ))));
        }
        return run_eds(a);
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
        anyhow::Error::new(crate::common::Usage(format!(
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
        for (i, s, line, why) in crate::cmd::dcf::apply_to_state(d, built.setup.cfg, &state)? {
            tracing::warn!(
                "{}:{line}: 0x{i:04X}/{s} not applied ({why}); it keeps its previous value",
                path.display()
            );
        }
    }
    open_storage(&mut built.setup)?;
    let bus = crate::common::silkit_url(&a.bus, &a.silkit, Some(&built.setup.name))?;
    // SIL Kit's time starts once the start-up NMT state is set (synchronised mode).
    canpos_host::silkit::can::hold_starts();
    let (transport, _hub) = open_bus(&bus, a.hub, &stop, pacing(a.bus_bitrate, a.instant_bus))?;
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
    canpos_host::silkit::can::release_starts();
    let _ctl = start_control(listener, &handle, a.control_idle_timeout)?;
    let _web = start_web(a.web.as_deref(), &bus, &handle, 1)?;
    supervise(handle, &stop)
}

/// Runs `canpos run` with `--eds` or `--dcf`.
fn run_eds(a: RunArgs) -> Result<i32> {
    let (path, kind) = match (a.eds, a.dcf) {
        (Some(p), _) => (p, FileKind::Eds),
        (None, Some(p)) => (p, FileKind::Dcf),
        (None, None) => unreachable!("dispatched without --eds / --dcf"),
    };
    let stop = stop_signal()?;
    let o = Overrides {
        node_id: a.node_id,
        bitrate_kbps: a.bus_bitrate.map(|b| b as u16),
        serial: a.serial,
    };
    let dev = eds_device::load(&path, kind, &o)?;
    for w in &dev.warnings {
        tracing::warn!("{}: {w}", path.display());
    }
    let state_dir = a.state_dir.unwrap_or_else(runtime::default_state_dir);
    let state = dev.state_file(&state_dir);
    // Locked, links refused, stale temporaries removed, as a sensor's (FileStorage::open).
    let storage = FileStorage::open(&state)?.for_table(&dev.model.table);
    let bus = crate::common::silkit_url(&a.bus, &a.silkit, None)?;
    canpos_host::silkit::can::hold_starts();
    let (transport, _hub) = open_bus(
        &bus,
        a.hub,
        &stop,
        crate::common::pacing(a.bus_bitrate, a.instant_bus),
    )?;
    let desc = transport.describe();
    let mut rt = PlainRuntime::new(transport, a.bus_bitrate, dev.model, dev.cfg, storage);
    // Bound before the boot-up, as for a sensor: a client that saw it can connect at once.
    let listener = bind_control(a.control.as_deref())?;
    rt.power_on()?;
    // The active node-id: a stored LSS node-id wins over the file's and the command line's.
    let id = rt.node().device().node_id();
    let id_text = if id == canpos_stack::UNCONFIGURED {
        "no node-id (255, LSS unconfigured)".to_string()
    } else {
        format!("node-id {id}")
    };
    let handle = rt.spawn()?;
    // The same banner as a sensor's, so tools that wait for "canpos: sensor 0:" work alike.
    eprintln!(
        "canpos: sensor 0: {} `{}` ({id_text}, {} entries) on {desc}; state file {}",
        if kind == FileKind::Dcf { "DCF" } else { "EDS" },
        path.display(),
        dev.model.entries.len(),
        state.display()
    );
    // `--nmt`, as for a sensor (the plain device takes the `nmt` request).
    let nmt = match a.nmt.as_deref() {
        Some(s) => parse_nmt_state(s).map_err(|e| anyhow!(e))?,
        None => None,
    };
    start_nodes(&handle, &[nmt])?;
    canpos_host::silkit::can::release_starts();
    let _ctl = start_control(listener, &handle, a.control_idle_timeout)?;
    let web = start_web(a.web.as_deref(), &bus, &handle, 1)?;
    if let Some(w) = &web {
        // The dashboard knows no model by this name: the file's table is the node's.
        w.pin_model(id, &dev.model.table);
    }
    supervise(handle, &stop)
}
