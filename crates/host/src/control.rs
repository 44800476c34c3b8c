//! The control interface (SPEC §12): a loopback TCP server speaking JSON lines, so a test
//! harness in any language can move magnets, inject faults, power-cycle and read the true and
//! reported state. The protocol is documented in `docs/CONTROL.md`.
//!
//! One request per line, one answer line per request:
//!
//! ```text
//! → {"cmd":"magnet","index":0,"mm":250.0}
//! ← {"ok":true}
//! → {"cmd":"fault","name":"nonsense","on":true}
//! ← {"ok":false,"error":"unknown fault `nonsense`; known: missing-magnet, …"}
//! ```

use std::fmt;
use std::io::{self, BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::str::FromStr;
use std::thread::JoinHandle;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::runtime::ControlHandle;

/// Longest request line accepted (a request is a few dozen bytes).
pub const MAX_LINE: usize = 64 * 1024;

/// A control request. `sensor` selects the sensor of a multi-sensor runtime (0-based, default
/// 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "kebab-case")]
pub enum Request {
    /// Moves magnet `index` (0-based) to `mm`; `null` takes it off the rod. `velocity` (mm/s)
    /// limits the speed of the move (jump when absent).
    Magnet {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// Magnet index (0 = the first magnet of the motion source).
        #[serde(default)]
        index: usize,
        /// Target position in mm from the zero point; `None` removes the magnet.
        mm: Option<f64>,
        /// Speed limit of the move, mm/s.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        velocity: Option<f64>,
    },
    /// Starts a motion profile (the `--motion` syntax, without `csv:`) from now on.
    Motion {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// The spec, e.g. `sine:center=500,amp=200,period=4`.
        spec: String,
    },
    /// Turns a fault on or off (see [`Fault`]).
    Fault {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// Fault name, e.g. `missing-magnet`.
        name: String,
        /// On or off.
        on: bool,
        /// Fault parameter: extra magnet position (mm), supply voltage (V), temperature (°C).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        value: Option<f64>,
        /// Channel (0-based) for missing-magnet / magnets-too-close; default 0.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        channel: Option<usize>,
    },
    /// Power off and on again: stored data are reloaded, boot-up is sent.
    PowerCycle {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
    },
    /// Sets the ambient temperature (°C) of the thermal model.
    Ambient {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
        /// Ambient temperature, °C.
        celsius: f64,
    },
    /// Reads the state: NMT state, node-id, bit rate, true and reported positions, velocity,
    /// error register, active faults.
    State {
        /// Sensor index.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        sensor: Option<usize>,
    },
    /// Restarts the runtime's wake-up lateness statistics (`wake_lateness_us` of the state),
    /// so a measurement covers a chosen window, not the start-up.
    ResetLateness,
}

/// The faults the control interface can inject (SPEC §11).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Fault {
    /// A channel reports no magnet (sim) → the core's EMCY 0x5000, register 0x81.
    MissingMagnet,
    /// One more magnet on the rod (sim; `value` = position in mm, default 90 % of the stroke).
    ExtraMagnet,
    /// Two magnets closer than the minimum distance (sim) → as missing magnet.
    MagnetsTooClose,
    /// Transducer error: no position at all (sim) → EMCY 0x5000, register 0x81.
    SensorError,
    /// Supply voltage out of range (sim `value` V, default 2 V under the minimum) → EMCY 0x3100,
    /// register 0x05.
    SupplyVoltage,
    /// Over-temperature (sim `value` °C, default 10 °C over the maximum) → EMCY 0x4200,
    /// register 0x09.
    OverTemperature,
    /// Corrupts the state file; the next power cycle starts on defaults with EMCY 0x6300.
    StorageCorrupt,
    /// CAN error passive → EMCY 0x8120, register 0x11.
    ErrorPassive,
    /// Bus-off: the node neither sends nor receives; `off` = recovery → EMCY 0x8140 then 0x0000.
    BusOff,
    /// CAN overrun → EMCY 0x8110, register 0x11.
    CanOverrun,
    /// `on` powers the sensor off, `off` powers it on again.
    PowerCycle,
}

impl Fault {
    /// Every fault.
    pub const ALL: [Fault; 11] = [
        Fault::MissingMagnet,
        Fault::ExtraMagnet,
        Fault::MagnetsTooClose,
        Fault::SensorError,
        Fault::SupplyVoltage,
        Fault::OverTemperature,
        Fault::StorageCorrupt,
        Fault::ErrorPassive,
        Fault::BusOff,
        Fault::CanOverrun,
        Fault::PowerCycle,
    ];

    /// The name used on the wire and the command line.
    pub fn name(self) -> &'static str {
        match self {
            Fault::MissingMagnet => "missing-magnet",
            Fault::ExtraMagnet => "extra-magnet",
            Fault::MagnetsTooClose => "magnets-too-close",
            Fault::SensorError => "sensor-error",
            Fault::SupplyVoltage => "supply-voltage",
            Fault::OverTemperature => "over-temperature",
            Fault::StorageCorrupt => "storage-corrupt",
            Fault::ErrorPassive => "error-passive",
            Fault::BusOff => "bus-off",
            Fault::CanOverrun => "can-overrun",
            Fault::PowerCycle => "power-cycle",
        }
    }
}

impl fmt::Display for Fault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Fault {
    type Err = String;
    fn from_str(s: &str) -> Result<Fault, String> {
        Fault::ALL
            .into_iter()
            .find(|f| f.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| {
                let known: Vec<_> = Fault::ALL.iter().map(|f| f.name()).collect();
                format!("unknown fault `{s}`; known: {}", known.join(", "))
            })
    }
}

/// Parses one request line into a request, or the error answer to send back.
pub fn parse_request(line: &str) -> Result<Request, Value> {
    serde_json::from_str::<Request>(line).map_err(|e| {
        json!({"ok": false, "error": format!("bad request: {e}; expected e.g. {{\"cmd\":\"state\"}} (cmds: magnet, motion, fault, power-cycle, ambient, state)")})
    })
}

/// A running control server.
pub struct ControlServer {
    addr: SocketAddr,
    _thread: JoinHandle<()>,
}

impl ControlServer {
    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }
}

/// Serves the control interface on `addr`, answering through `handle`. Each connection gets a
/// thread (clients are test harnesses: few, long-lived). Warns when `addr` is not loopback:
/// the interface has no authentication.
pub fn serve(addr: impl ToSocketAddrs, handle: ControlHandle) -> io::Result<ControlServer> {
    serve_on(TcpListener::bind(addr)?, handle)
}

/// [`serve`] on a listener bound earlier: a host binds before its sensors boot, so that a
/// client that saw the boot-up can connect at once (connections wait in the backlog until
/// the runtime is up).
pub fn serve_on(listener: TcpListener, handle: ControlHandle) -> io::Result<ControlServer> {
    let addr = listener.local_addr()?;
    if !addr.ip().is_loopback() {
        tracing::warn!(%addr, "control interface reachable from the network (no authentication)");
    }
    let thread = std::thread::Builder::new()
        .name("canpos-control".into())
        .spawn(move || {
            for conn in listener.incoming() {
                let Ok(stream) = conn else { continue };
                let h = handle.clone();
                let _ = std::thread::Builder::new()
                    .name("canpos-control-conn".into())
                    .spawn(move || {
                        if let Err(e) = serve_conn(stream, h) {
                            tracing::debug!(error = %e, "control connection ended");
                        }
                    });
            }
        })?;
    Ok(ControlServer {
        addr,
        _thread: thread,
    })
}

fn serve_conn(stream: TcpStream, handle: ControlHandle) -> io::Result<()> {
    stream.set_nodelay(true)?;
    let mut out = stream.try_clone()?;
    let mut reader = BufReader::new(stream);
    let mut line = String::new();
    loop {
        line.clear();
        let n = (&mut reader).take(MAX_LINE as u64).read_line(&mut line)?;
        if n == 0 {
            return Ok(());
        }
        let text = line.trim();
        if text.is_empty() {
            continue;
        }
        let answer = match parse_request(text) {
            Ok(req) => handle.request(req),
            Err(e) => e,
        };
        let mut s = answer.to_string();
        s.push('\n');
        out.write_all(s.as_bytes())?;
    }
}

/// Client side: sends one request and returns the answer (used by `canpos ctl`).
pub fn call(addr: impl ToSocketAddrs, req: &Request, timeout: Duration) -> io::Result<Value> {
    let mut last = None;
    for a in addr.to_socket_addrs()? {
        match TcpStream::connect_timeout(&a, timeout) {
            Ok(mut s) => {
                s.set_read_timeout(Some(timeout))?;
                let mut line = serde_json::to_string(req).map_err(io::Error::other)?;
                line.push('\n');
                s.write_all(line.as_bytes())?;
                let mut reply = String::new();
                BufReader::new(s).read_line(&mut reply)?;
                return serde_json::from_str(reply.trim()).map_err(|e| {
                    io::Error::new(io::ErrorKind::InvalidData, format!("bad answer: {e}"))
                });
            }
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no address")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_documented_requests() {
        assert_eq!(
            parse_request(r#"{"cmd":"magnet","index":0,"mm":250.0}"#).unwrap(),
            Request::Magnet {
                sensor: None,
                index: 0,
                mm: Some(250.0),
                velocity: None
            }
        );
        assert!(matches!(
            parse_request(r#"{"cmd":"motion","spec":"sine:center=500,amp=200,period=4"}"#),
            Ok(Request::Motion { .. })
        ));
        assert!(matches!(
            parse_request(r#"{"cmd":"fault","name":"missing-magnet","on":true}"#),
            Ok(Request::Fault { on: true, .. })
        ));
        assert_eq!(
            parse_request(r#"{"cmd":"power-cycle"}"#).unwrap(),
            Request::PowerCycle { sensor: None }
        );
        assert_eq!(
            parse_request(r#"{"cmd":"state","sensor":1}"#).unwrap(),
            Request::State { sensor: Some(1) }
        );
        let e = parse_request(r#"{"cmd":"fly"}"#).unwrap_err();
        assert_eq!(e["ok"], false);
        assert!(e["error"].as_str().unwrap().contains("fly"), "{e}");
    }

    #[test]
    fn fault_names_round_trip() {
        for f in Fault::ALL {
            assert_eq!(f.name().parse::<Fault>().unwrap(), f);
        }
        let e = "bogus".parse::<Fault>().unwrap_err();
        assert!(e.contains("missing-magnet"), "{e}");
    }
}
