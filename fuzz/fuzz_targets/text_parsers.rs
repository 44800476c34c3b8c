//! The text parsers a user feeds canpos: order codes, motion specs and scenario files.
//!
//! Invariants: no panic; an accepted order code prints (Display) as a code that parses to the
//! same value and yields a sensor spec or a clean error; an accepted motion spec prints as a
//! spec that parses to the same value, and its motion gives finite positions; an accepted
//! scenario builds every sensor or fails with an error.
#![no_main]

#[allow(dead_code, unused_imports)]
#[path = "../../crates/cli/src/device.rs"]
mod device;

use std::path::PathBuf;
use std::sync::OnceLock;

use canpos_sim::motion::MotionSpec;
use canpos_sim::parse_order_code;

fn dir() -> &'static PathBuf {
    static D: OnceLock<PathBuf> = OnceLock::new();
    D.get_or_init(|| {
        // Scratch space inside the fuzz crate's own target directory, not the shared /tmp.
        let d = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/target/scratch"))
            .join(format!("text-{}", std::process::id()));
        std::fs::create_dir_all(&d)
            .unwrap_or_else(|e| panic!("environment: cannot create {}: {e}", d.display()));
        d
    })
}

fn order_code(s: &str) {
    if let Ok(oc) = parse_order_code(s) {
        let printed = oc.to_string();
        let again = parse_order_code(&printed)
            .unwrap_or_else(|e| panic!("{s:?} printed as {printed:?}, which fails: {e}"));
        assert_eq!(again, oc, "order code round trip via {printed:?}");
        let _ = oc.sensor_spec();
        let _ = oc.resolution_nm();
    }
}

fn motion(s: &str) {
    let Ok(spec) = MotionSpec::parse(s) else {
        return;
    };
    if matches!(spec, MotionSpec::Csv(_)) {
        return; // would read an arbitrary path
    }
    let printed = spec.to_string();
    let again = MotionSpec::parse(&printed)
        .unwrap_or_else(|e| panic!("{s:?} printed as {printed:?}, which fails: {e}"));
    assert_eq!(again, spec, "motion spec round trip via {printed:?}");
    if let Ok(mut m) = spec.build() {
        for t in [0.0, 0.001, 0.5, 1.0, 7.25, 3600.0, 1e7] {
            for (k, p) in m.positions_mm(t).into_iter().enumerate() {
                if let Some(p) = p {
                    assert!(p.is_finite(), "{s:?}: magnet {k} at t={t} is {p}");
                }
            }
        }
    }
}

fn scenario(s: &str) {
    let path = dir().join("scenario.toml");
    std::fs::write(&path, s)
        .unwrap_or_else(|e| panic!("environment: cannot write {}: {e}", path.display()));
    let Ok(sc) = device::load_scenario(&path) else {
        return;
    };
    for o in &sc.sensors {
        if o.motion
            .as_deref()
            .is_some_and(|m| m.trim_start().starts_with("csv:"))
        {
            continue;
        }
        let _ = device::build_setup(o, dir());
    }
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Some((&sel, rest)) = data.split_first() else {
        return;
    };
    let Ok(s) = std::str::from_utf8(rest) else {
        return;
    };
    match sel % 3 {
        0 => order_code(s),
        1 => motion(s),
        _ => scenario(s),
    }
});
