//! The demo (`canpos` without arguments, or `canpos demo`).

use canpos_stack::cob;
use canpos_stack::nmt::{NmtCommand, NmtFrame};
use canpos_stack::sdo::wire::{self, Mux, Response};
use std::io::Write as _;
use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{bail, Context as _, Result};
use canpos_host::control::{self, Request};
use canpos_host::crossbeam_channel::Receiver;
use canpos_host::runtime::{Runtime, RuntimeHandle};
use canpos_host::{Hub, Transport};
use canpos_stack::Frame;
use clap::Args;

use crate::common::{stop_signal, DEFAULT_LISTEN};
use crate::launch::warn_if_exposed;
use crate::sensor::{build_setup, open_storage, SensorOpts};

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

/// One expedited SDO upload of a number, for the demo's own view (a stale or foreign answer is
/// skipped by its multiplexer).
fn sdo_upload(port: &mut dyn Transport, node: u8, index: u16, sub: u8) -> Result<u32> {
    let mux = Mux { index, sub };
    let req = wire::Request::UploadInitiate { mux }.emit();
    port.send(&Frame::std8(cob::SDO_RX + u16::from(node), req))?;
    let end = std::time::Instant::now() + Duration::from_secs(1);
    while let Some(rx) = port.recv_deadline(end)? {
        let Ok(d) = <[u8; 8]>::try_from(rx.frame.data()) else {
            continue;
        };
        if rx.frame.std_id() == Some(cob::SDO_TX + u16::from(node)) && Mux::from_frame(&d) == mux {
            if let Response::Abort { code, .. } = Response::parse(&d) {
                bail!("SDO abort {code:#010x} reading {index:#06x}/{sub}");
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
    let state = crate::common::private_state_dir("demo")?;
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
            d.set_bus_label(&format!("socketcand://{addr}/can0"));
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
    let [c, n] = NmtFrame {
        command: NmtCommand::Start,
        node,
    }
    .emit();
    mon.send(&Frame::std_len(cob::NMT, [c, n, 0, 0, 0, 0, 0, 0], 2))?;
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
