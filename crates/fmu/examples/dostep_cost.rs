//! The cost of one 1 ms `fmi3DoStep` of a TH sensor FMU through the C ABI (docs/BENCHMARKS.md):
//! `idle` (pre-operational: the measurement cycle only) or `tpdo` (operational: a TPDO every
//! 1 ms, so each step ends in an event whose Tx_Data carries it; the event's calls are counted
//! apart). Prints ns per step; run under `valgrind --tool=callgrind --toggle-collect=fmi3DoStep`
//! for the instructions.
//!
//!     cargo run --release -p canpos-fmu --example dostep_cost -- idle 20000

use std::ffi::{c_void, CString};
use std::time::Instant;

use canpos_fmu::ffi::*;
use canpos_fmu::kind::{Kind, RESOURCE_FILE};
use canpos_fmu::lsbus::{Op, TxBuffer};
use canpos_fmu::sensor::{SensorUnit, VR_RX_CLOCK, VR_RX_DATA, VR_TX_CLOCK, VR_TX_DATA};

fn ok(s: Status, what: &str) {
    assert_eq!(s, OK, "{what}");
}

fn main() {
    let mut args = std::env::args().skip(1);
    let mode = args.next().unwrap_or_else(|| "idle".into());
    let steps: u64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(10_000);
    let kind = Kind::Sensor(SensorUnit::for_model("th").unwrap());
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(RESOURCE_FILE), kind.resource_text()).unwrap();
    let token = CString::new(kind.description().unwrap().token).unwrap();
    let res = CString::new(format!("{}/", dir.path().display())).unwrap();
    let name = CString::new("th").unwrap();
    unsafe {
        let i: *mut c_void = fmi3InstantiateCoSimulation(
            name.as_ptr(),
            token.as_ptr(),
            res.as_ptr(),
            false,
            false,
            true,
            false,
            std::ptr::null(),
            0,
            std::ptr::null_mut(),
            None,
            std::ptr::null(),
        );
        assert!(!i.is_null());
        ok(
            fmi3EnterInitializationMode(i, false, 0.0, 0.0, false, 0.0),
            "init",
        );
        ok(fmi3ExitInitializationMode(i), "exit init");
        let event = |i: *mut c_void, rx: Option<&[u8]>| {
            if let Some(b) = rx {
                let (vr, size, p) = ([VR_RX_DATA], [b.len()], [b.as_ptr()]);
                ok(
                    fmi3SetBinary(i, vr.as_ptr(), 1, size.as_ptr(), p.as_ptr(), 1),
                    "rx",
                );
                ok(
                    fmi3SetClock(i, [VR_RX_CLOCK].as_ptr(), 1, [1u8].as_ptr()),
                    "clock",
                );
            }
            let (mut need, mut term, mut nom, mut val, mut def, mut next) =
                (false, false, false, false, false, 0.0);
            ok(
                fmi3UpdateDiscreteStates(
                    i, &mut need, &mut term, &mut nom, &mut val, &mut def, &mut next,
                ),
                "update",
            );
            let mut tick = false;
            ok(
                fmi3GetClock(i, [VR_TX_CLOCK].as_ptr(), 1, &mut tick),
                "tx clock",
            );
            if tick {
                let (mut size, mut p) = (0usize, std::ptr::null::<u8>());
                ok(
                    fmi3GetBinary(i, [VR_TX_DATA].as_ptr(), 1, &mut size, &mut p, 1),
                    "tx",
                );
            }
            ok(fmi3EnterStepMode(i), "step mode");
        };
        event(i, None);
        let mut t = 0.0;
        let step = |i: *mut c_void, t: &mut f64| -> bool {
            let (mut ev, mut term, mut early, mut last) = (false, false, false, 0.0);
            ok(
                fmi3DoStep(
                    i, *t, 0.001, true, &mut ev, &mut term, &mut early, &mut last,
                ),
                "step",
            );
            *t = last;
            ev
        };
        if mode == "tpdo" {
            let mut b = TxBuffer::new(64);
            b.push(&Op::Transmit {
                id: 0,
                ide: false,
                rtr: false,
                data: &[1, 127],
                dlc: 2,
            })
            .unwrap();
            step(i, &mut t);
            ok(fmi3EnterEventMode(i), "event");
            event(i, Some(b.bytes()));
        }
        // Warm up (thermal model, caches), then the measured steps.
        for _ in 0..1000 {
            if step(i, &mut t) {
                ok(fmi3EnterEventMode(i), "event");
                event(i, None);
            }
        }
        let (mut in_step, mut in_event, mut events) = (0u128, 0u128, 0u64);
        for _ in 0..steps {
            let a = Instant::now();
            let ev = step(i, &mut t);
            let b = Instant::now();
            in_step += (b - a).as_nanos();
            if ev {
                ok(fmi3EnterEventMode(i), "event");
                event(i, None);
                in_event += b.elapsed().as_nanos();
                events += 1;
            }
        }
        fmi3FreeInstance(i);
        println!(
            "{mode}: {steps} steps of 1 ms: fmi3DoStep {} ns each; {events} events, {} ns each (enterEventMode … enterStepMode)",
            in_step / u128::from(steps),
            if events > 0 { in_event / u128::from(events) } else { 0 }
        );
    }
}
