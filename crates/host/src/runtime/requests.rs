//! The control requests as the runtime carries them out (the requests themselves are
//! [`crate::control::request`]; the server is [`crate::control::server`]): magnets, faults,
//! power, timing, state.

use canpos_sim::motion::MotionSpec;
use canpos_sim::Faults;
use canpos_stack::nmt::NmtState;
use canpos_stack::{Frame, Instant};
use serde_json::{json, Value};

use crate::can::{BusState, BusStats, Disturbance, Transport};
use crate::clock::Driver;
use crate::control::request::{bus_disturbance, nmt_command, Fault, Request};

use super::device::*;
use super::wait::Lateness;
use super::Runtime;

impl Runtime {
    /// Answers one control request.
    pub(super) fn handle_request(&mut self, req: Request, now: Instant) -> Value {
        match self.try_request(req, now) {
            Ok(v) => v,
            Err(e) => json!({"ok": false, "error": e}),
        }
    }

    pub(super) fn sensor_index(&self, s: Option<usize>) -> Result<usize, String> {
        let i = s.unwrap_or(0);
        if i < self.devices.len() {
            Ok(i)
        } else {
            Err(format!(
                "sensor {i} does not exist (this runtime has {} sensor(s), numbered from 0)",
                self.devices.len()
            ))
        }
    }

    /// Why sensor `s` refuses `set-input` (or that it does not exist).
    fn no_inputs(&self, s: Option<usize>) -> String {
        match self.sensor_index(s) {
            Ok(i) => format!(
                "sensor {i} has no inputs to set: its process values are its measurements (magnet, motion, fault); set-input is for a device served from an EDS (docs/EDS_DEVICE.md)"
            ),
            Err(e) => e,
        }
    }

    /// Position channels of sensor `i` (magnets it can measure).
    pub(super) fn channels(&self, i: usize) -> usize {
        usize::from(self.devices[i].node.device().config().channels.max(1))
    }

    pub(super) fn check_magnet_index(&self, i: usize, index: usize) -> Result<(), String> {
        let channels = self.channels(i);
        if index >= channels {
            return Err(format!(
                "magnet {index} does not exist: sensor {i} has {channels} magnet channel(s), numbered 0…{} (an additional magnet is the extra-magnet fault)",
                channels - 1
            ));
        }
        Ok(())
    }

    pub(super) fn try_request(&mut self, req: Request, now: Instant) -> Result<Value, String> {
        // A sensor has no inputs: said before the request's values are judged, so that a
        // user with a typo is not sent to fix a value of a request no sensor takes.
        if let Request::SetInput { sensor, .. } = req {
            return Err(self.no_inputs(sensor));
        }
        // Values first, then indices, then the change: a refused request changes nothing.
        req.validate()?;
        match req {
            Request::Magnet {
                sensor,
                index,
                mm,
                velocity,
            } => {
                let i = self.sensor_index(sensor)?;
                self.check_magnet_index(i, index)?;
                let live = &self.devices[i].live;
                match mm {
                    Some(mm) => live.set_point(index, mm, velocity),
                    None => live.remove(index),
                }
                .map_err(|e| e.to_string())?;
                Ok(json!({"ok": true}))
            }
            Request::Motion { sensor, spec } => {
                let i = self.sensor_index(sensor)?;
                let spec = MotionSpec::parse(&spec).map_err(|e| e.to_string())?;
                let MotionSpec::Profiles(profiles) = spec else {
                    return Err(
                        "a CSV trajectory can only be given at start (--motion csv:FILE)".into(),
                    );
                };
                // Everything is checked before the first magnet moves: a refused request
                // changes nothing.
                let channels = self.channels(i);
                if profiles.len() > channels {
                    return Err(format!(
                        "{} profiles for {} magnet channel(s) of sensor {i}; give at most {channels} (an additional magnet is the extra-magnet fault)",
                        profiles.len(),
                        channels
                    ));
                }
                for p in &profiles {
                    p.validate().map_err(|e| e.to_string())?;
                }
                let live = &self.devices[i].live;
                for (k, p) in profiles.into_iter().enumerate() {
                    live.start_profile(k, p).map_err(|e| e.to_string())?;
                }
                Ok(json!({"ok": true}))
            }
            Request::Fault {
                sensor,
                name,
                on,
                value,
                channel,
            } => {
                let i = self.sensor_index(sensor)?;
                let fault: Fault = name.parse()?;
                self.apply_fault(i, fault, on, value, channel, now)?;
                Ok(json!({"ok": true, "faults": self.fault_names(i)}))
            }
            Request::PowerCycle { sensor } => {
                let i = self.sensor_index(sensor)?;
                // The fault is the supply held off: a power cycle cannot bring the power back
                // while it holds (state would show a powered sensor with its supply off).
                if self.devices[i].faults.contains(&Fault::PowerCycle) {
                    return Err(format!(
                        "sensor {i} is held powered off by the `power-cycle` fault; turn the fault off to power it on"
                    ));
                }
                self.power_off(i);
                self.devices[i].sensor.power_cycle();
                self.power_on(i, now);
                Ok(json!({"ok": true}))
            }
            Request::Ambient { sensor, celsius } => {
                let i = self.sensor_index(sensor)?;
                self.devices[i]
                    .sensor
                    .set_ambient_temperature_c(celsius)
                    .map_err(|e| e.to_string())?;
                Ok(json!({"ok": true}))
            }
            Request::State { sensor } => {
                let i = self.sensor_index(sensor)?;
                Ok(self.state(i))
            }
            Request::BusFault {
                sensor,
                kind,
                value,
                on,
            } => {
                let d = bus_disturbance(&kind, value, on)?;
                let i = self.sensor_index(sensor)?;
                let r = match (&self.devices[i].port, d) {
                    (Some(p), Disturbance::TransceiverFailed(_)) => p.disturb(d),
                    _ => self.transport.disturb(d),
                };
                r?;
                Ok(json!({"ok": true}))
            }
            Request::ResetLateness { sensor } => {
                self.sensor_index(sensor)?;
                self.lateness = Lateness::default();
                self.events_late = Lateness::default();
                self.frames_late = Lateness::default();
                Ok(json!({"ok": true}))
            }
            Request::Timing {
                sensor,
                sdo_delay_ms,
                sdo_jitter_ms,
                boot_delay_ms,
                reset_boot_delay_ms,
            } => {
                let i = self.sensor_index(sensor)?;
                let mut t = self.devices[i].timing;
                let ms = crate::timing::millis;
                if let Some(v) = sdo_delay_ms {
                    t.sdo_delay = ms("sdo_delay_ms", v)?;
                }
                if let Some(v) = sdo_jitter_ms {
                    t.sdo_jitter = ms("sdo_jitter_ms", v)?;
                }
                if let Some(v) = boot_delay_ms {
                    t.boot_delay = ms("boot_delay_ms", v)?;
                }
                if let Some(v) = reset_boot_delay_ms {
                    t.reset_boot_delay = ms("reset_boot_delay_ms", v)?;
                }
                self.set_timing(i, t)?;
                Ok(json!({"ok": true, "timing": timing_json(&t)}))
            }
            Request::SetInput { sensor, .. } => Err(self.no_inputs(sensor)),
            Request::Nmt { sensor, command } => {
                let i = self.sensor_index(sensor)?;
                let cs = nmt_command(&command)?;
                if !self.powered[i] {
                    return Err(format!("sensor {i} is powered off"));
                }
                let node_id = self.devices[i].node.device().node_id();
                if !(1..=127).contains(&node_id) {
                    return Err(format!(
                        "sensor {i} has no node-id yet (LSS unconfigured); it cannot take NMT commands"
                    ));
                }
                // Addressed to this node only and handed to it alone: the other nodes and the
                // bus see nothing.
                let f = Frame::new(0x000, &[cs, node_id]).map_err(|e| format!("{e:?}"))?;
                self.devices[i].receive(&f, now);
                Ok(json!({"ok": true}))
            }
        }
    }

    pub(super) fn fault_names(&self, i: usize) -> Vec<&'static str> {
        self.devices[i].faults.iter().map(|f| f.name()).collect()
    }

    pub(super) fn apply_fault(
        &mut self,
        i: usize,
        fault: Fault,
        on: bool,
        value: Option<f64>,
        channel: Option<usize>,
        now: Instant,
    ) -> Result<(), String> {
        let d = &mut self.devices[i];
        let mut faults: Faults = d.sensor.faults().clone();
        let spec = d.sensor.spec().clone();
        let ch = channel.unwrap_or(0);
        let channels = usize::from(d.node.device().config().channels.max(1));
        if matches!(fault, Fault::MissingMagnet | Fault::MagnetsTooClose) {
            let last = if fault == Fault::MagnetsTooClose {
                channels.saturating_sub(2)
            } else {
                channels - 1
            };
            if ch > last || (fault == Fault::MagnetsTooClose && channels < 2) {
                return Err(format!(
                    "channel {ch} out of range: this sensor has {channels} channel(s){}",
                    if fault == Fault::MagnetsTooClose {
                        " and magnets-too-close needs channel and channel + 1"
                    } else {
                        ""
                    }
                ));
            }
        }
        match fault {
            Fault::Stall => {
                d.stall_until = if on {
                    // Checked by `Request::validate`: finite, 0 < s ≤ MAX_DELAY.
                    let us = (value.unwrap_or(0.0) * 1e6) as u64;
                    Some(Instant::from_micros(now.micros() + us))
                } else {
                    None
                };
            }
            Fault::MissingMagnet => {
                let slot = faults
                    .missing_channels
                    .get_mut(ch)
                    .ok_or_else(|| format!("channel {ch} out of range"))?;
                *slot = on;
            }
            Fault::ExtraMagnet => {
                faults.extra_magnet_mm = on.then(|| value.unwrap_or(spec.stroke_mm * 0.9));
            }
            Fault::MagnetsTooClose => faults.too_close_channel = on.then_some(ch),
            // The encoder sees no positions and raises 0x5000 (register 0x81) itself.
            Fault::SensorError => faults.transducer_error = on,
            Fault::SupplyVoltage => {
                faults.supply_voltage_v = on.then(|| value.unwrap_or(spec.supply.min_v - 2.0));
            }
            Fault::OverTemperature => {
                faults.temperature_c =
                    on.then(|| value.unwrap_or(spec.operating_temperature_c.1 + 10.0));
            }
            _ => {}
        }
        d.sensor.set_faults(faults).map_err(|e| e.to_string())?;
        // The core knows how each model reports these (EMCY code and bytes, error register,
        // TMI 0x1002 bits and reactions); the runtime only says what happened.
        use canpos_encoder::Fault as Core;
        match fault {
            Fault::SensorError => d.node.inject_fault(Core::Transducer, on),
            Fault::SupplyVoltage => d.node.inject_fault(Core::SupplyVoltage, on),
            Fault::ErrorPassive => d.node.inject_fault(Core::CanErrorPassive, on),
            Fault::CanOverrun => d.node.inject_fault(Core::CanOverrun, on),
            Fault::Communication => d.node.inject_fault(Core::Communication, on),
            Fault::PdoLength => d.node.inject_fault(Core::PdoLength, on),
            Fault::WrongMapping
            | Fault::WrongVendorId
            | Fault::WrongScale
            | Fault::WrongResolution
            | Fault::UnexpectedSystemData
            | Fault::NoSystemData
            | Fault::InvalidSerial => {
                use canpos_encoder::SystemDataError as E;
                let e = match fault {
                    Fault::WrongMapping => E::WrongMapping,
                    Fault::WrongVendorId => E::WrongVendorId,
                    Fault::WrongScale => E::WrongScale,
                    Fault::WrongResolution => E::WrongResolution,
                    Fault::UnexpectedSystemData => E::Unexpected,
                    Fault::NoSystemData => E::NoSystemData,
                    _ => E::InvalidSerial,
                };
                d.node.inject_fault(Core::SystemData(e), on);
            }
            // While bus-off the runtime keeps the node off the bus; clearing it is the
            // recovery the core reports (0x8140).
            Fault::BusOff if on || d.bus_off => {
                d.bus_off = on;
                d.node.inject_fault(Core::CanBusOff, on);
            }
            // Off: nothing to undo; the next store writes a good image again.
            Fault::StorageCorrupt if on => {
                d.node
                    .storage_mut()
                    .corrupt()
                    .map_err(|e| format!("cannot corrupt the state file: {e}"))?;
            }
            Fault::PowerCycle => {
                if on {
                    self.power_off(i);
                } else if !self.powered[i] && self.devices[i].power_on_at.is_none() {
                    // Off and not already booting (a boot delay runs): power back on.
                    self.devices[i].sensor.power_cycle();
                    self.power_on(i, now);
                }
            }
            _ => {}
        }
        let d = &mut self.devices[i];
        d.faults.retain(|f| *f != fault);
        if on {
            d.faults.push(fault);
        }
        if fault == Fault::OverTemperature && self.powered[i] {
            d.sync_temperature();
        }
        Ok(())
    }

    /// The `clock` part of a state: the driver, the simulation time reached, and how late
    /// (wall − simulation time) events and received frames were processed (docs/CLOCK.md).
    pub(super) fn clock_json(&self) -> Value {
        let late = |l: &Lateness| {
            json!({
                "median": l.quantile_us(0.5),
                "p99": l.quantile_us(0.99),
                "mean": (l.mean_us() * 10.0).round() / 10.0,
                "max": l.max_us,
                "count": l.count,
                "over_1ms": l.over_1ms,
            })
        };
        let wall = self.clock.driver() == Driver::Wall;
        json!({
            "driver": if wall { "wall" } else { "stepped" },
            "shared_with_bus": self.horizon.is_some(),
            "sim_time_us": self.reached.micros(),
            // How far the simulation is behind the wall clock right now.
            "behind_us": wall.then(|| (self.clock.wall_elapsed() / 1000).saturating_sub(self.reached.micros())),
            "events_late_us": late(&self.events_late),
            "frames_late_us": late(&self.frames_late),
        })
    }

    /// The `state` answer of sensor `i`.
    pub(super) fn state(&mut self, i: usize) -> Value {
        // The transport's view (a socketcand server away = bus-off), beside the injected fault.
        let bus_state = self.transport.bus_state();
        let reconnections = self.transport.reconnections();
        let powered = self.powered[i];
        let bus = self.bus_bitrate;
        let lateness = self.lateness;
        let clock = self.clock_json();
        let names = self.fault_names(i);
        let d = &mut self.devices[i];
        let dev = d.node.device();
        let nmt = match dev.nmt_state() {
            NmtState::Initialising => "initialising",
            NmtState::PreOperational => "pre-operational",
            NmtState::Operational => "operational",
            NmtState::Stopped => "stopped",
        };
        let node_id = dev.node_id();
        let bitrate = dev.bitrate();
        let channels = dev.config().channels as usize;
        let model = dev.model().name;
        let serial = dev.config().serial;
        let storage_corrupt = dev.stats().storage_corrupt;
        let step_nm = d.node.read_object(0x6005, 1).unwrap_or(1000) as f64;
        let vstep = d.node.read_object(0x6005, 2).unwrap_or(100) as f64;
        let mut reported = Vec::new();
        let mut velocity = Vec::new();
        let mut cams = Vec::new();
        let mut work_area = Vec::new();
        for ch in 0..channels {
            let sub = ch as u8 + 1;
            cams.push(d.node.read_object(0x6300, sub).ok());
            work_area.push(d.node.read_object(0x6400, sub).ok());
            reported.push(
                d.node
                    .read_object(0x6020, sub)
                    .ok()
                    .map(|r| r as i32 as f64 * step_nm / 1e6),
            );
            velocity.push(
                d.node
                    .read_object(0x6030, sub)
                    .ok()
                    .map(|r| r as u16 as i16 as f64 * vstep / 100.0),
            );
        }
        let err_reg = d.node.read_object(0x1001, 0).ok();
        let mut device_timing = timing_json(&d.timing);
        device_timing["booting"] = json!(d.power_on_at.is_some() || d.rebooting.is_some());
        device_timing["sdo_responses_held"] = json!(d.held.len());
        // Output timing of the last published measurement (issue 15).
        let spec = d.sensor.spec();
        let timing = json!({
            "cycle_us": spec.cycle_time_us,
            "processing_us": spec.processing_us,
            "max_output_delay_us": spec.max_output_delay_us(),
            "time_of_flight_us": d.sensor.last_published().map(|(t, _)| t.time_of_flight_us),
            "ready_after_us": d.sensor.last_published().map(|(t, _)| t.ready_after_us),
            "output_delay_us": d.sensor.last_published().map(|(t, _)| t.output_delay_us),
        });
        let alarms = d.node.read_object(0x6503, 0).ok();
        let bus_stats = d
            .port
            .as_ref()
            .and_then(|p| p.bus_stats())
            .or_else(|| self.transport.bus_stats());
        let bus_json = bus_json(bus_stats.as_ref());
        let mut v = json!({
            "ok": true,
            "sensor": i,
            "name": d.name,
            "model": model,
            "serial": serial,
            "powered": powered,
            "device_timing": device_timing,
            "bus_off": d.bus_off,
            "nmt": nmt,
            "node_id": node_id,
            "bitrate_kbps": bitrate,
            "bus_bitrate_kbps": bus,
            "true_mm": d.last_true,
            "reported_mm": reported,
            "velocity_mm_s": velocity,
            "cam_state": cams,
            "work_area": work_area,
            "error_register": err_reg,
            "alarms": alarms,
            "temperature_c": d.sensor.internal_temperature_c(),
            "ambient_c": d.sensor.ambient_temperature_c(),
            "electronics_temperature_c": d.sensor.electronics_temperature_c(),
            "waveguide_temperature_c": d.sensor.waveguide_temperature_c(),
            "temperature_limits_c": d.sensor.temperature_limits_c(),
            "temperature_alarm": d.temp_alarm,
            "unit_tempco_ppm_per_k": d.sensor.unit_errors().tempco_ppm_per_k,
            "ideal": d.sensor.is_ideal(),
            "timing": timing,
            "supply_v": d.sensor.supply_voltage_v(),
            "faults": names,
            "storage_corrupt_at_boot": storage_corrupt,
            "storage": d.node.storage_mut().path().display().to_string(),
            "frames_sent": d.frames_sent,
            "bus": bus_json,
            // Event-timer periods the TPDOs skipped because the runtime woke too late.
            "tpdo_missed": (0..4)
                .filter_map(|n| d.node.device().tpdos().get(n))
                .map(|p| u64::from(p.missed))
                .sum::<u64>(),
            "wake_lateness_us": {
                "median": lateness.quantile_us(0.5),
                "p99": lateness.quantile_us(0.99),
                "mean": lateness.mean_us(),
                "max": lateness.max_us,
                "count": lateness.count,
            },
            // Measurements never made: only after a stop longer than the stall bound.
            "cycles_skipped": d.cycles_skipped,
            "clock": clock,
        });
        v["bus_state"] = json!(match bus_state {
            BusState::ErrorActive => "error-active",
            BusState::ErrorPassive => "error-passive",
            BusState::BusOff => "bus-off",
        });
        v["bus_reconnections"] = json!(reconnections);
        // Frames produced in an injected bus-off (never sent).
        v["frames_lost_bus_off"] = json!(d.lost_bus_off);
        v
    }
}

/// The `bus` member of a sensor's state: the bus's load and counters and its own controller's
/// (`null` on a transport that does not model the bus).
pub fn bus_json(s: Option<&BusStats>) -> Value {
    let Some(s) = s else { return Value::Null };
    let ctl = s.controller.map(|c| {
        json!({
            "state": match c.state {
                BusState::ErrorActive => "error-active",
                BusState::ErrorPassive => "error-passive",
                BusState::BusOff => "bus-off",
            },
            "tec": c.tec,
            "rec": c.rec,
            "sent": c.sent,
            "queued": c.queued,
            "lost_overflow": c.lost_overflow,
            "lost_bus_off": c.lost_bus_off,
            "tx_errors": c.tx_errors,
            "collisions": c.collisions,
            "last_wait_us": c.last_wait / 1000,
            "max_wait_us": c.max_wait / 1000,
        })
    });
    json!({
        "bitrate_kbps": s.bitrate_kbps,
        "load_pct": (s.load * 1000.0).round() / 10.0,
        "frames_per_s": s.frames_per_s.round(),
        "frames": s.frames,
        "error_frames": s.error_frames,
        "tx_lost": s.tx_lost,
        "rx_dropped": s.rx_dropped,
        "controller": ctl,
    })
}
