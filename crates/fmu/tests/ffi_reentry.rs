//! An importer's logger that calls back into the FMU while the FMU is inside a call of the
//! same instance (re-entrancy) gets `fmi3Error` and changes nothing: the instance is neither
//! freed under the running call nor entered twice (issue 31 item 4).

use std::ffi::{c_char, c_void, CString};
use std::sync::atomic::{AtomicI32, AtomicPtr, AtomicUsize, Ordering};

use canpos_fmu::ffi::{
    fmi3DoStep, fmi3FreeInstance, fmi3GetFloat64, fmi3InstantiateCoSimulation, ERROR, OK,
};
use canpos_fmu::kind::{Kind, RESOURCE_FILE};
use canpos_fmu::sensor::SensorUnit;

static INST: AtomicPtr<c_void> = AtomicPtr::new(std::ptr::null_mut());
static CALLS: AtomicUsize = AtomicUsize::new(0);
static INNER_FREE_THEN_GET: AtomicI32 = AtomicI32::new(-1);
static INNER_GET: AtomicI32 = AtomicI32::new(-1);

/// The importer's logger: on the first message it frees the instance, then reads a variable of
/// it, both from inside the FMU's call.
unsafe extern "C" fn reentering_logger(_: *mut c_void, _: i32, _: *const c_char, _: *const c_char) {
    if CALLS.fetch_add(1, Ordering::SeqCst) > 0 {
        return;
    }
    let inst = INST.load(Ordering::SeqCst);
    let vr = [0u32];
    let mut v = [0.0f64];
    unsafe {
        fmi3FreeInstance(inst);
        let s = fmi3GetFloat64(inst, vr.as_ptr(), 1, v.as_mut_ptr(), 1);
        INNER_FREE_THEN_GET.store(s, Ordering::SeqCst);
        let s = fmi3GetFloat64(inst, vr.as_ptr(), 1, v.as_mut_ptr(), 1);
        INNER_GET.store(s, Ordering::SeqCst);
    }
}

#[test]
fn a_call_from_inside_the_logger_is_refused_and_frees_nothing() {
    let kind = Kind::Sensor(SensorUnit::for_model("th").unwrap());
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(RESOURCE_FILE), kind.resource_text()).unwrap();
    let token = CString::new(kind.description().unwrap().token).unwrap();
    let res = CString::new(format!("{}/", dir.path().display())).unwrap();
    let name = CString::new("reentry").unwrap();
    let inst = unsafe {
        fmi3InstantiateCoSimulation(
            name.as_ptr(),
            token.as_ptr(),
            res.as_ptr(),
            false,
            false,
            true,
            true,
            std::ptr::null(),
            0,
            std::ptr::null_mut(),
            Some(reentering_logger),
            std::ptr::null(),
        )
    };
    assert!(!inst.is_null());
    INST.store(inst, Ordering::SeqCst);
    // fmi3DoStep before initialization: refused, and the refusal is logged (the logger runs).
    let (mut a, mut b, mut c, mut d) = (false, false, false, 0.0);
    let s = unsafe { fmi3DoStep(inst, 0.0, 1e-3, false, &mut a, &mut b, &mut c, &mut d) };
    assert_eq!(s, ERROR);
    assert!(
        CALLS.load(Ordering::SeqCst) >= 1,
        "the logger was not called"
    );
    // Inside the logger: the free was refused and the instance was not entered twice.
    assert_eq!(INNER_FREE_THEN_GET.load(Ordering::SeqCst), ERROR);
    assert_eq!(INNER_GET.load(Ordering::SeqCst), ERROR);
    // After the call the instance is alive and whole.
    let vr = [0u32];
    let mut v = [f64::NAN];
    let s = unsafe { fmi3GetFloat64(inst, vr.as_ptr(), 1, v.as_mut_ptr(), 1) };
    assert_eq!(s, OK, "the instance was freed from inside its own call");
    assert_eq!(v[0], 0.0);
    unsafe { fmi3FreeInstance(inst) };
    let s = unsafe { fmi3GetFloat64(inst, vr.as_ptr(), 1, v.as_mut_ptr(), 1) };
    assert_eq!(s, ERROR);
}
