//! The text parsers a user feeds canpos: order codes, motion specs and scenario files.
//!
//! Invariants: no panic; an accepted order code prints (Display) as a code that parses to the
//! same value and yields a sensor spec or a clean error; an accepted motion spec prints as a
//! spec that parses to the same value, and its motion gives finite positions; a scenario is
//! accepted with every sensor built, or refused with a `FILE…: ` message.
#![no_main]

use canpos_cli::scenario;

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

fn scenario_file(s: &str) {
    // CSV motions would read arbitrary paths: left to the motion branch's checks.
    if s.contains("csv:") {
        return;
    }
    let path = std::path::Path::new("fuzz.toml");
    match scenario::check(s, path, Some(dir().clone())) {
        Ok((checked, built)) => {
            assert_eq!(built.len(), checked.scenario.sensors.len());
            assert!(!built.is_empty(), "a scenario without sensors was accepted");
            assert!(built.len() <= scenario::MAX_NODES);
            if let Some(d) = checked.scenario.duration {
                assert!(d.is_finite() && d > 0.0 && d <= canpos_cli::limits::MAX_SECONDS);
            }
            for e in &checked.scenario.events {
                assert!(
                    e.at.is_finite() && (0.0..=canpos_cli::limits::MAX_SECONDS).contains(&e.at)
                );
                assert_eq!(e.request.validate(), Ok(()));
            }
        }
        Err(e) => {
            let m = format!("{e:#}");
            assert!(
                m.starts_with("fuzz.toml"),
                "error without the file name: {m}"
            );
        }
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
        _ => scenario_file(s),
    }
});
