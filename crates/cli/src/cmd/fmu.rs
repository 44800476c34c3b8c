//! `canpos fmu`: write an FMI 3.0 co-simulation FMU of a unit on the FMI-LS-BUS CAN layer
//! (docs/FMU.md).
//!
//! The FMU's binary is the workspace's `canpos-fmu` shared library (`libcanpos_fmu.so`): cargo
//! builds it beside the `canpos` executable whenever it builds `canpos` (the CLI depends on
//! the crate, whose crate types include `cdylib`), so a build from a fresh clone finds it in
//! `target/<profile>/deps/`. `--library` or `CANPOS_FMU_LIBRARY` name another one.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, Context, Result};
use canpos_fmu::bus_fmu::BusUnit;
use canpos_fmu::kind::Kind;
use canpos_fmu::sensor::SensorUnit;
use clap::Args;

use crate::common::usage;

/// `canpos fmu`: write an FMU.
#[derive(Args, Debug, Clone)]
pub struct FmuArgs {
    /// Model of a sensor FMU: th, e-series, tmi (the model's default unit).
    #[arg(long, conflicts_with = "order_code")]
    pub model: Option<String>,
    /// Order code of a unit (e.g. EP00600MD341C304241Z02): its model with the code's stroke,
    /// resolution, channels and bit rate.
    #[arg(long, value_name = "CODE")]
    pub order_code: Option<String>,
    /// Write the bus-simulation FMU instead: canpos's CAN bus (bit timing, arbitration, error
    /// counters, bus-off) for `--nodes` node FMUs (docs/FMU.md).
    #[arg(long, conflicts_with_all = ["model", "order_code"])]
    pub bus_simulation: bool,
    /// Node terminals of the bus-simulation FMU (1 … 128: 127 nodes and their master; default 2).
    #[arg(long, value_name = "N")]
    pub nodes: Option<usize>,
    /// Bit rate of the bus-simulation FMU, kbit/s (CiA 301; its `bitrate` parameter's start;
    /// default 500).
    #[arg(long, value_name = "KBPS")]
    pub bitrate: Option<u32>,
    /// The FMU file to write (e.g. th.fmu).
    #[arg(long, short = 'o', value_name = "FILE.fmu")]
    pub output: PathBuf,
    /// The canpos-fmu shared library to put in the FMU (default: `$CANPOS_FMU_LIBRARY`, else
    /// the one cargo built beside this executable).
    #[arg(long, value_name = "FILE.so")]
    pub library: Option<PathBuf>,
}

/// The kind of FMU the arguments ask for.
pub fn kind_of(a: &FmuArgs) -> Result<Kind> {
    // clap's `requires` takes a flag's default `false` for given: checked here.
    if !a.bus_simulation && (a.nodes.is_some() || a.bitrate.is_some()) {
        return Err(usage!(
            "--nodes and --bitrate are the bus simulation's: give --bus-simulation (a sensor FMU's bit rate is its `bitrate` parameter)"
        ));
    }
    if a.bus_simulation {
        let bus = BusUnit::new(a.nodes.unwrap_or(2), a.bitrate.unwrap_or(500))
            .map_err(|e| usage!("{e}"))?;
        return Ok(Kind::BusSimulation(bus));
    }
    let unit = match (&a.model, &a.order_code) {
        (_, Some(code)) => SensorUnit::for_order_code(code),
        (m, None) => SensorUnit::for_model(m.as_deref().unwrap_or("th")),
    }
    .map_err(|e| usage!("{e}"))?;
    Ok(Kind::Sensor(unit))
}

/// Where the shared library is: `--library`, `$CANPOS_FMU_LIBRARY`, or beside the executable
/// (`target/<profile>/` or its `deps/`, the newer one).
pub fn library_path(given: Option<&Path>) -> Result<PathBuf> {
    if let Some(p) = given {
        return Ok(p.to_path_buf());
    }
    if let Some(p) = std::env::var_os("CANPOS_FMU_LIBRARY").filter(|p| !p.is_empty()) {
        return Ok(PathBuf::from(p));
    }
    let exe = std::env::current_exe().context("locating the canpos executable")?;
    let dir = exe.parent().unwrap_or(Path::new("."));
    // Test executables live in deps/ themselves.
    let candidates = [
        dir.join("libcanpos_fmu.so"),
        dir.join("deps/libcanpos_fmu.so"),
        dir.join("../libcanpos_fmu.so"),
    ];
    // `cargo build -p canpos` refreshes deps/, `cargo build -p canpos-fmu` the top one: the
    // newer of the two is the current build.
    candidates
        .iter()
        .filter_map(|p| Some((std::fs::metadata(p).ok()?.modified().ok()?, p)))
        .max_by_key(|(t, _)| *t)
        .map(|(_, p)| p.clone())
        .ok_or_else(|| {
            anyhow!(
                "the FMU's shared library libcanpos_fmu.so is not beside {} (build it with \
                 `cargo build -p canpos-fmu`, or give --library / CANPOS_FMU_LIBRARY)",
                exe.display()
            )
        })
}

/// Writes the FMU.
pub fn fmu(a: FmuArgs) -> Result<i32> {
    let kind = kind_of(&a)?;
    let lib_path = library_path(a.library.as_deref())?;
    let lib = std::fs::read(&lib_path)
        .with_context(|| format!("reading the FMU library {}", lib_path.display()))?;
    let bytes = canpos_fmu::package::fmu(&kind, &lib).map_err(|e| anyhow!(e))?;
    std::fs::write(&a.output, bytes).with_context(|| format!("writing {}", a.output.display()))?;
    let d = kind.description().map_err(|e| anyhow!(e))?;
    eprintln!(
        "canpos fmu: wrote {} ({}, instantiationToken {})",
        a.output.display(),
        d.model_name,
        d.token
    );
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sensor::{build_setup, SensorOpts};

    /// The FMU's unit is the one `canpos run` makes from the same model or order code: the
    /// same configuration and measurement spec (one device, not a second description of it).
    #[test]
    fn the_fmu_unit_is_the_one_canpos_run_makes() {
        let dir = tempfile::tempdir().unwrap();
        let cases = [
            (Some("th"), None),
            (Some("e-series"), None),
            (Some("tmi"), None),
            (None, Some("EP00600MD341C304241Z02")),
        ];
        for (model, code) in cases {
            let a = FmuArgs {
                model: model.map(String::from),
                order_code: code.map(String::from),
                output: "x.fmu".into(),
                library: None,
                bus_simulation: false,
                nodes: None,
                bitrate: None,
            };
            let unit = match kind_of(&a).unwrap() {
                Kind::Sensor(u) => u,
                _ => panic!("{model:?} {code:?} is not a sensor"),
            };
            let o = SensorOpts {
                model: model.map(String::from),
                order_code: code.map(String::from),
                ..SensorOpts::default()
            };
            let run = build_setup(&o, dir.path()).unwrap().setup;
            assert_eq!(unit.cfg, run.cfg, "{model:?} {code:?}");
            assert_eq!(unit.spec, run.spec, "{model:?} {code:?}");
            assert_eq!(unit.model.name, run.model.name);
        }
        let bad = FmuArgs {
            model: Some("toaster".into()),
            order_code: None,
            output: "x.fmu".into(),
            library: None,
            bus_simulation: false,
            nodes: None,
            bitrate: None,
        };
        assert!(kind_of(&bad).is_err());
        // The bus simulation's options: checked, and only with --bus-simulation.
        let bus = |nodes, bitrate, on| FmuArgs {
            model: None,
            order_code: None,
            output: "x.fmu".into(),
            library: None,
            bus_simulation: on,
            nodes,
            bitrate,
        };
        assert!(matches!(
            kind_of(&bus(Some(4), Some(125), true)).unwrap(),
            Kind::BusSimulation(b) if b.nodes == 4 && b.kbps == 125
        ));
        for bad in [
            bus(Some(0), None, true),
            bus(Some(129), None, true),
            bus(None, Some(123), true),
            bus(Some(4), None, false),
            bus(None, Some(125), false),
        ] {
            assert!(kind_of(&bad).is_err(), "{bad:?}");
        }
    }
}
