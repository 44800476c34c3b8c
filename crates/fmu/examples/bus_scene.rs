//! The native reference of the bus-simulation FMU's test (tests/fmu/test_bus_fmu.py): one
//! scene – sensors by model and node-id, and a controller's frames at given times – run on
//! canpos's own runtime with a `mem://` bus on a stepped clock (docs/CLOCK.md), the sensors
//! made as the sensor FMUs make them. Prints every frame the controller received, in order, as
//! JSON lines `{"id": …, "data": […], "end_ns": …}` (the frame's end-of-frame time).
//!
//! Usage: `cargo run -p canpos-fmu --example bus_scene -- SCENE.json`, the scene being
//! `{"bitrate": 125, "end_us": 300000, "sensors": [{"model": "th", "node_id": 1}, …],
//!   "controller": [[at_us, id, [byte, …]], …]}`.

use std::process::ExitCode;

use canpos_fmu::sensor::SensorUnit;
use canpos_host::can::Transport;
use canpos_host::clock::SimClock;
use canpos_host::mem::MemBus;
use canpos_host::runtime::{state_file, SensorSetup};
use canpos_host::{FileStorage, Runtime};
use canpos_sim::motion::{Profile, Profiles};
use canpos_stack::{Frame, Instant};
use serde_json::{json, Value};

fn run(path: &str) -> Result<(), String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{path}: {e}"))?;
    let scene: Value = serde_json::from_str(&text).map_err(|e| format!("{path}: {e}"))?;
    let kbps = scene["bitrate"].as_u64().ok_or("no bitrate")? as u32;
    let end_us = scene["end_us"].as_u64().ok_or("no end_us")?;
    let clock = SimClock::stepped();
    let bus = MemBus::with_clock(kbps, clock.clone()).with_queue_len(1 << 20);
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), Some(kbps));
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    for s in scene["sensors"].as_array().ok_or("no sensors")? {
        let unit = SensorUnit::for_model(s["model"].as_str().ok_or("sensor without model")?)?;
        let mut cfg = unit.cfg;
        cfg.node_id = s["node_id"].as_u64().ok_or("sensor without node_id")? as u8;
        cfg.bitrate_kbps = kbps as u16;
        // As the sensor FMU builds its unit (crates/fmu/src/sensor.rs): seed = serial, not
        // ideal, the default magnets standing still.
        let path = state_file(dir.path(), unit.model.name, cfg.serial);
        let storage = FileStorage::open(&path)
            .map_err(|e| format!("{}: {e}", path.display()))?
            .for_model(unit.model);
        rt.add(SensorSetup {
            name: format!("{}-{}", unit.model.name, cfg.serial),
            model: unit.model,
            cfg,
            spec: unit.spec.clone(),
            seed: u64::from(cfg.serial),
            ideal: false,
            motion: Box::new(Profiles(
                unit.default_magnets()
                    .into_iter()
                    .map(|pos_mm| Profile::Static { pos_mm })
                    .collect(),
            )),
            storage,
        });
    }
    let mut sends: Vec<(u64, Frame)> = Vec::new();
    for c in scene["controller"].as_array().ok_or("no controller")? {
        let at = c[0].as_u64().ok_or("controller time")?;
        let id = c[1].as_u64().ok_or("controller id")? as u16;
        let data: Vec<u8> = c[2]
            .as_array()
            .ok_or("controller data")?
            .iter()
            .map(|b| b.as_u64().unwrap_or(0) as u8)
            .collect();
        sends.push((at, Frame::new(id, &data).map_err(|e| format!("{e:?}"))?));
    }
    sends.sort_by_key(|s| s.0);
    // Power on at 0, as the sensor FMUs do at their first step.
    rt.advance_to(Instant::from_micros(0))
        .map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    let take = |master: &mut canpos_host::mem::MemPort, out: &mut Vec<Value>| {
        master.sync_bus();
        while let Ok(Some(rx)) = master.try_recv() {
            out.push(json!({
                "id": rx.frame.id(),
                "data": rx.frame.data(),
                "end_ns": clock.nanos_of(rx.timestamp).unwrap_or(0),
            }));
        }
    };
    for (at, f) in sends {
        rt.advance_to(Instant::from_micros(at))
            .map_err(|e| e.to_string())?;
        take(&mut master, &mut out);
        master.send(&f).map_err(|e| e.to_string())?;
    }
    rt.advance_to(Instant::from_micros(end_us))
        .map_err(|e| e.to_string())?;
    take(&mut master, &mut out);
    for v in out {
        println!("{v}");
    }
    Ok(())
}

fn main() -> ExitCode {
    let Some(path) = std::env::args().nth(1) else {
        eprintln!("usage: bus_scene SCENE.json");
        return ExitCode::from(2);
    };
    match run(&path) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("bus_scene: {e}");
            ExitCode::FAILURE
        }
    }
}
