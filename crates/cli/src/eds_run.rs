//! `canpos run --eds FILE` / `--dcf FILE`: a plain CiA 301 device from a user's EDS or DCF
//! (docs/EDS_DEVICE.md). The model is built by `canpos_host::eds_device`, run by
//! `canpos_host::plain`.

use anyhow::Result;
use canpos_host::eds_device::{self, FileKind, Overrides};
use canpos_host::plain::PlainRuntime;
use canpos_host::runtime;
use canpos_host::FileStorage;

use crate::device::{open_bus, stop_signal, supervise, RunArgs};

/// Runs `canpos run` with `--eds` or `--dcf`.
pub fn run(a: RunArgs) -> Result<i32> {
    let (path, kind) = match (a.eds, a.dcf) {
        (Some(p), _) => (p, FileKind::Eds),
        (None, Some(p)) => (p, FileKind::Dcf),
        (None, None) => unreachable!("dispatched without --eds / --dcf"),
    };
    let stop = stop_signal()?;
    let o = Overrides {
        node_id: a.node_id,
        bitrate_kbps: a.bus_bitrate.map(|b| b as u16),
        serial: a.serial,
    };
    let dev = eds_device::load(&path, kind, &o)?;
    for w in &dev.warnings {
        tracing::warn!("{}: {w}", path.display());
    }
    let state_dir = a.state_dir.unwrap_or_else(runtime::default_state_dir);
    let state = dev.state_file(&state_dir);
    // Locked, links refused, stale temporaries removed, as a sensor's (FileStorage::open).
    let storage = FileStorage::open(&state)?.for_model(dev.model);
    let (transport, _hub) = open_bus(
        &a.bus,
        a.hub,
        &stop,
        crate::device::pacing(a.bus_bitrate, a.instant_bus),
    )?;
    let desc = transport.describe();
    let mut rt = PlainRuntime::new(transport, a.bus_bitrate, dev.model, dev.cfg, storage);
    rt.power_on()?;
    // The active node-id: a stored LSS node-id wins over the file's and the command line's.
    let id = rt.node().device().node_id();
    let id_text = if id == canpos_core::UNCONFIGURED {
        "no node-id (255, LSS unconfigured)".to_string()
    } else {
        format!("node-id {id}")
    };
    let handle = rt.spawn()?;
    // The same banner as a sensor's, so tools that wait for "canpos: sensor 0:" work alike.
    eprintln!(
        "canpos: sensor 0: {} `{}` ({id_text}, {} entries) on {desc}; state file {}",
        if kind == FileKind::Dcf { "DCF" } else { "EDS" },
        path.display(),
        dev.model.entries.len(),
        state.display()
    );
    supervise(handle, &stop)
}
