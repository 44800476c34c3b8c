//! `canpos ctl`: drive a running sensor through its control interface.

use std::time::Duration;

use anyhow::{anyhow, Context as _, Result};
use canpos_host::control::{self, Request};
use clap::{Args, Subcommand};

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
    /// Print the state (NMT, node-id, bit rate, true / reported positions, velocity, errors;
    /// of a device served from an EDS, its process objects).
    State,
    /// Set an input of a device served from an EDS (`canpos run --eds`) as its own process
    /// would: a read-only object of 0x6000…0x9FFF, e.g. `set-input 0x6000 1 0xA5`. A TPDO
    /// that maps it sends the change.
    SetInput {
        /// Object index (decimal or 0x hex).
        index: String,
        /// Sub-index.
        sub: String,
        /// The value, a whole number of the object's type (decimal or 0x hex, `-` for
        /// negative: `-0x8000`).
        // Any leading `-`: clap's negative numbers are decimal only, and `-0x8000` is a value.
        #[arg(allow_hyphen_values = true)]
        value: String,
    },
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
        // Checked by the device, which knows the object's type and range.
        CtlAction::SetInput { index, sub, value } => Request::SetInput {
            sensor,
            index: index.into(),
            sub: Some(sub.into()),
            value: value.into(),
        },
        CtlAction::BusFault { kind, value } => {
            let (value, on) = match value.as_str() {
                "on" => (None, Some(true)),
                "off" => (None, Some(false)),
                v => (
                    Some(v.parse::<f64>().map_err(|_| {
                        crate::common::Usage(format!("bus-fault value `{v}` is not a number"))
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
