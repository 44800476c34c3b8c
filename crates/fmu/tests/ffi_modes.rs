//! Instantiation rules of FMI 3.0 the FMU enforces (issue 31 item 4).

use std::ffi::{c_char, c_void, CStr, CString};
use std::sync::Mutex;

use canpos_fmu::ffi::{
    fmi3DoStep, fmi3EnterInitializationMode, fmi3EnterStepMode, fmi3ExitInitializationMode,
    fmi3FreeInstance, fmi3InstantiateCoSimulation, ERROR, OK,
};
use canpos_fmu::kind::{Kind, RESOURCE_FILE};
use canpos_fmu::sensor::SensorUnit;

static LOG: Mutex<Vec<String>> = Mutex::new(Vec::new());

unsafe extern "C" fn logger(_: *mut c_void, _: i32, _: *const c_char, msg: *const c_char) {
    let m = unsafe { CStr::from_ptr(msg) }
        .to_string_lossy()
        .into_owned();
    LOG.lock().unwrap().push(m);
}

fn instantiate(event_mode_used: bool) -> *mut c_void {
    let kind = Kind::Sensor(SensorUnit::for_model("th").unwrap());
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(RESOURCE_FILE), kind.resource_text()).unwrap();
    let token = CString::new(kind.description().unwrap().token).unwrap();
    let res = CString::new(format!("{}/", dir.path().display())).unwrap();
    let name = CString::new("modes").unwrap();
    unsafe {
        fmi3InstantiateCoSimulation(
            name.as_ptr(),
            token.as_ptr(),
            res.as_ptr(),
            false,
            false,
            event_mode_used,
            false,
            std::ptr::null(),
            0,
            std::ptr::null_mut(),
            Some(logger),
            std::ptr::null(),
        )
    }
}

/// The LS-BUS terminal's Rx / Tx clocks need event mode (FMI 3.0: an FMU with clocks requires
/// `eventModeUsed`): without it no frame could be taken and `Tx_Data` would never be emptied.
#[test]
fn an_importer_without_event_mode_is_refused_with_the_reason() {
    let inst = instantiate(false);
    assert!(inst.is_null(), "instantiated without event mode");
    let log = LOG.lock().unwrap().join("\n");
    assert!(log.contains("eventModeUsed"), "{log}");
    let inst = instantiate(true);
    assert!(!inst.is_null());
    unsafe { fmi3FreeInstance(inst) };
}

fn do_step(inst: *mut c_void, t: f64, h: f64) -> i32 {
    let (mut a, mut b, mut c, mut d) = (false, false, false, 0.0);
    unsafe { fmi3DoStep(inst, t, h, false, &mut a, &mut b, &mut c, &mut d) }
}

/// FMI 3.0: with a stop time defined, a step past it gets `fmi3Error` (and changes nothing).
#[test]
fn a_step_past_the_defined_stop_time_is_refused() {
    let inst = instantiate(true);
    assert!(!inst.is_null());
    unsafe {
        assert_eq!(
            fmi3EnterInitializationMode(inst, false, 0.0, 0.0, true, 0.01),
            OK
        );
        assert_eq!(fmi3ExitInitializationMode(inst), OK);
        assert_eq!(fmi3EnterStepMode(inst), OK);
    }
    assert_eq!(do_step(inst, 0.0, 0.005), OK);
    assert_eq!(do_step(inst, 0.005, 1e300), ERROR);
    assert!(LOG.lock().unwrap().iter().any(|m| m.contains("stop time")));
    assert_eq!(do_step(inst, 0.005, 0.006), ERROR);
    // Refused steps changed nothing: the step to the stop time itself is fine.
    assert_eq!(do_step(inst, 0.005, 0.005), OK);
    unsafe { fmi3FreeInstance(inst) };
}
