//! The control interface's request handler: request lines as a client sends them, through the
//! line reader, the JSON parser, the checks and a running runtime (a four-channel TH on an
//! in-process bus).
//!
//! Invariants: no panic; every line gets one answer with a boolean `ok` and, when false, a
//! non-empty `error`; an over-long line is one refusal; the runtime keeps answering; a refused
//! request changes nothing (the state before and after a refusal is the same, apart from the
//! clock-driven fields).
#![no_main]

use std::io::BufReader;
use std::sync::OnceLock;

use canpos_host::control::{answer_line, read_line_limited, Line};
use canpos_host::mem::MemBus;
use canpos_host::runtime::{state_file, Runtime, SensorSetup};
use canpos_host::{ControlHandle, FileStorage, RuntimeHandle};
use canpos_sim::motion::{Profile, Profiles};
use canpos_sim::SensorSpec;
use serde_json::Value;

/// Longest line in this target (the server's is 64 KiB; shorter keeps runs fast).
const LIMIT: usize = 4096;

fn runtime() -> &'static (RuntimeHandle, ControlHandle) {
    static RT: OnceLock<(RuntimeHandle, ControlHandle)> = OnceLock::new();
    RT.get_or_init(|| {
        let dir = std::path::PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/target/scratch"))
            .join(format!("control-{}", std::process::id()));
        std::fs::create_dir_all(&dir)
            .unwrap_or_else(|e| panic!("environment: cannot create {}: {e}", dir.display()));
        let model = canpos_core::models::by_name("th").expect("th model");
        let mut cfg = model.default_config;
        cfg.channels = 4;
        let setup = SensorSetup {
            name: "th-fuzz".into(),
            model,
            cfg,
            spec: SensorSpec::th(1000.0, 4).expect("th spec"),
            seed: 1,
            ideal: true,
            motion: Box::new(Profiles(
                [100.0, 300.0, 500.0, 700.0]
                    .map(|pos_mm| Profile::Static { pos_mm })
                    .to_vec(),
            )),
            storage: FileStorage::new(state_file(&dir, "th", cfg.serial)),
        };
        let bus = MemBus::new();
        let mut rt = Runtime::new(Box::new(bus.attach()), None);
        rt.add(setup);
        let handle = rt.spawn().expect("runtime thread");
        let control = handle.control();
        (handle, control)
    })
}

/// The parts of the state a request sets directly. Clock-driven ones move by themselves and
/// are left out: temperatures, timing, and positions (an earlier input may have left a magnet
/// moving on a profile or towards a set-point).
fn settled(st: &Value) -> Value {
    let keys = [
        "faults",
        "powered",
        "bus_off",
        "nmt",
        "node_id",
        "ambient_c",
        "supply_v",
    ];
    Value::Object(
        keys.iter()
            .map(|k| (k.to_string(), st[*k].clone()))
            .collect(),
    )
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let (_, control) = runtime();
    let mut r = BufReader::with_capacity(64, data);
    for _ in 0..16 {
        let line = match read_line_limited(&mut r, LIMIT) {
            Ok(Line::Eof) | Err(_) => break,
            Ok(Line::TooLong) => continue,
            Ok(Line::Text(bytes)) => bytes,
        };
        let Ok(text) = std::str::from_utf8(&line) else {
            continue;
        };
        let text = text.trim();
        if text.is_empty() {
            continue;
        }
        let before = control.request(canpos_host::control::Request::State { sensor: None });
        let answer = answer_line(text, control);
        let ok = answer["ok"]
            .as_bool()
            .unwrap_or_else(|| panic!("{text:?}: answer without a boolean ok: {answer}"));
        if !ok {
            assert!(
                answer["error"].as_str().is_some_and(|e| !e.is_empty()),
                "{text:?}: refusal without a reason: {answer}"
            );
            let after = control.request(canpos_host::control::Request::State { sensor: None });
            assert_eq!(
                settled(&before),
                settled(&after),
                "{text:?} was refused ({answer}) but changed the state"
            );
        }
    }
    // Still answering.
    let st = control.request(canpos_host::control::Request::State { sensor: None });
    assert_eq!(st["ok"], true, "runtime stopped answering: {st}");
});
