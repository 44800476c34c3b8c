//! The control interface's request handler: request lines as a client sends them, through the
//! line reader, the JSON parser, the checks and a running runtime (a four-channel TH on an
//! in-process bus).
//!
//! Invariants: no panic; every line gets one answer with a boolean `ok` and, when false, a
//! non-empty `error`; an over-long line is one refusal; the runtime keeps answering; a refused
//! request changes nothing (the state before and after a refusal is the same, apart from the
//! clock-driven fields).
//!
//! Unknown fields (issue 35): a line whose object holds a key its `cmd` does not know (the
//! table [`FIELDS`], written from docs/CONTROL.md, not from the parser) never parses; an
//! accepted request holds only known keys. Every line that parses gets a structured twin
//! with one more key made from the input (a near miss of a real one, or the input's own
//! bytes), which must be refused with that key's name and change nothing.
#![no_main]

use std::io::BufReader;
use std::sync::OnceLock;

use canpos_host::control::{answer_line, parse_request, read_line_limited, Line};
use canpos_host::mem::MemBus;
use canpos_host::runtime::{state_file, Runtime, SensorSetup};
use canpos_host::{ControlHandle, FileStorage, RuntimeHandle};
use canpos_sim::motion::{Profile, Profiles};
use canpos_sim::SensorSpec;
use serde_json::Value;

/// Longest line in this target (the server's is 64 KiB; shorter keeps runs fast).
const LIMIT: usize = 4096;

/// The keys each request takes besides `cmd` (docs/CONTROL.md): the oracle for unknown fields.
const FIELDS: [(&str, &[&str]); 10] = [
    ("magnet", &["sensor", "index", "mm", "velocity"]),
    ("motion", &["sensor", "spec"]),
    ("fault", &["sensor", "name", "on", "value", "channel"]),
    ("power-cycle", &["sensor"]),
    ("ambient", &["sensor", "celsius"]),
    ("state", &["sensor"]),
    ("bus-fault", &["sensor", "kind", "value", "on"]),
    ("reset-lateness", &["sensor"]),
    ("nmt", &["sensor", "command"]),
    (
        "timing",
        &[
            "sensor",
            "sdo_delay_ms",
            "sdo_jitter_ms",
            "boot_delay_ms",
            "reset_boot_delay_ms",
        ],
    ),
];

/// Near misses of real keys: what a typing human sends.
const NEAR_MISSES: [&str; 6] = ["velocty", "Sensor", "mm ", "channle", "value_", "cmd2"];

/// The keys of a JSON object line that its `cmd` does not take (`None`: not an object with a
/// known `cmd`).
fn unknown_keys(text: &str) -> Option<Vec<String>> {
    let Ok(Value::Object(obj)) = serde_json::from_str::<Value>(text) else {
        return None;
    };
    let cmd = obj.get("cmd")?.as_str()?;
    let (_, known) = FIELDS.iter().find(|(c, _)| *c == cmd)?;
    Some(
        obj.keys()
            .filter(|k| *k != "cmd" && !known.contains(&k.as_str()))
            .cloned()
            .collect(),
    )
}

/// An accepted line with one key more that its `cmd` does not take, made from `seed`.
fn with_unknown_key(text: &str, seed: &[u8]) -> Option<(String, String)> {
    let Ok(Value::Object(mut obj)) = serde_json::from_str::<Value>(text) else {
        return None;
    };
    let cmd = obj.get("cmd")?.as_str()?.to_string();
    let (_, known) = FIELDS.iter().find(|(c, _)| *c == cmd)?;
    let key = match seed.first() {
        Some(&b) if usize::from(b) < NEAR_MISSES.len() => NEAR_MISSES[usize::from(b)].to_string(),
        _ => String::from_utf8_lossy(&seed[..seed.len().min(24)]).into_owned(),
    };
    if key == "cmd" || known.contains(&key.as_str()) || obj.contains_key(&key) {
        return None;
    }
    obj.insert(key.clone(), Value::from(seed.len()));
    Some((Value::Object(obj).to_string(), key))
}

fn runtime() -> &'static (RuntimeHandle, ControlHandle) {
    static RT: OnceLock<(RuntimeHandle, ControlHandle)> = OnceLock::new();
    RT.get_or_init(|| {
        let dir = std::path::PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/target/scratch"))
            .join(format!("control-{}", std::process::id()));
        std::fs::create_dir_all(&dir)
            .unwrap_or_else(|e| panic!("environment: cannot create {}: {e}", dir.display()));
        let model = canpos_models::by_name("th").expect("th model");
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

/// Sends `line`, which must be refused, and checks that the state did not change.
fn refused_changes_nothing(control: &ControlHandle, line: &str) {
    let before = control.request(canpos_host::control::Request::State { sensor: None });
    let answer = answer_line(line, control);
    assert_eq!(answer["ok"], false, "{line:?} accepted: {answer}");
    let after = control.request(canpos_host::control::Request::State { sensor: None });
    assert_eq!(
        settled(&before),
        settled(&after),
        "{line:?} was refused ({answer}) but changed the state"
    );
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
        let parsed = parse_request(text);
        if let Some(unknown) = unknown_keys(text) {
            assert!(
                unknown.is_empty() || parsed.is_err(),
                "{text:?} parsed with unknown key(s) {unknown:?}: {parsed:?}"
            );
        }
        if parsed.is_ok() {
            if let Some((twin, key)) = with_unknown_key(text, data) {
                let e = parse_request(&twin).expect_err(&twin);
                let msg = e["error"].as_str().unwrap_or_default();
                assert!(
                    msg.starts_with("unknown field `") && msg.contains(&key),
                    "{twin:?} refused without naming `{key}`: {e}"
                );
                refused_changes_nothing(control, &twin);
            }
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
