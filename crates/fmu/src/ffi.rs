//! The FMI 3.0 C ABI: all `fmi3*` functions of `fmi3Functions.h`, exported by the shared
//! library. Every call checks its instance (a live one of this library), the mode of the FMI
//! state machine, null pointers and sizes before anything happens, and runs inside
//! `catch_unwind`: a bad call gets `fmi3Error` with the reason in the importer's log, never a
//! crash; nothing of a refused call is applied. The functions canpos FMUs do not support
//! (Model Exchange, Scheduled Execution, FMU state, derivatives, clocks with intervals) answer
//! `fmi3Error` with their reason.

#![allow(clippy::missing_safety_doc, clippy::too_many_arguments)]

use std::ffi::{c_char, c_int, c_void, CStr, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Mutex;

use crate::kind::{Kind, RESOURCE_FILE};
use crate::model::{Causality, FmuModel, Value, VarType};

/// `fmi3Status`.
pub type Status = c_int;
/// `fmi3OK`.
pub const OK: Status = 0;
/// `fmi3Warning`.
pub const WARNING: Status = 1;
/// `fmi3Discard`.
pub const DISCARD: Status = 2;
/// `fmi3Error`.
pub const ERROR: Status = 3;
/// `fmi3Fatal`.
pub const FATAL: Status = 4;

/// `fmi3LogMessageCallback`.
pub type Logger = Option<unsafe extern "C" fn(*mut c_void, Status, *const c_char, *const c_char)>;

/// The FMI state machine's modes (co-simulation with event mode).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Instantiated,
    Initialization,
    Event,
    Step,
    Terminated,
    /// A panic inside the library: only `fmi3Reset` and `fmi3FreeInstance` remain.
    Broken,
}

struct Instance {
    name: String,
    env: *mut c_void,
    logger: Logger,
    debug: bool,
    mode: Mode,
    event_mode_used: bool,
    early_return_allowed: bool,
    /// `stopTime` when the importer defined one: no step goes past it (FMI 3.0).
    stop_time: Option<f64>,
    kind: Kind,
    model: Box<dyn FmuModel>,
}

/// An instance alive: its address, and whether a call of it is running (a call of the same
/// instance from inside it, say from the importer's logger, is refused: it would free or
/// alias the instance under the running call).
struct Live {
    addr: usize,
    busy: bool,
}

/// The instances alive: a pointer not in it is refused, never dereferenced.
static LIVE: Mutex<Vec<Live>> = Mutex::new(Vec::new());

fn live() -> std::sync::MutexGuard<'static, Vec<Live>> {
    LIVE.lock().unwrap_or_else(|p| p.into_inner())
}

/// A line on standard error for a call without a logger; a closed or broken stderr is
/// ignored (`eprintln!` would panic, and no panic may leave an `extern "C"` function).
fn stderr_line(msg: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr(), "canpos fmu: {msg}");
}

fn cstring(s: &str) -> CString {
    CString::new(s.replace('\0', " ")).unwrap_or_default()
}

impl Instance {
    fn log(&self, status: Status, category: &str, msg: &str) {
        if status == OK && !self.debug {
            return;
        }
        if let Some(f) = self.logger {
            let (c, m) = (cstring(category), cstring(msg));
            // SAFETY: the importer gave this callback for this instance's life.
            unsafe { f(self.env, status, c.as_ptr(), m.as_ptr()) };
        }
    }

    fn error(&self, func: &str, msg: &str) -> Status {
        self.log(
            ERROR,
            "logStatusError",
            &format!("{}: {func}: {msg}", self.name),
        );
        ERROR
    }

    fn flush_log(&mut self) {
        for m in self.model.take_log() {
            self.log(WARNING, "logStatusWarning", &m);
        }
    }

    /// The model's answer to a change of mode: in mode `to` when it took it, else
    /// `fmi3Error` with its reason and the mode unchanged.
    fn switch(&mut self, func: &str, r: Result<(), String>, to: Mode) -> Status {
        match r {
            Ok(()) => {
                self.mode = to;
                OK
            }
            Err(e) => self.error(func, &e),
        }
    }

    fn expect(&self, func: &str, modes: &[Mode]) -> Result<(), Status> {
        if modes.contains(&self.mode) {
            Ok(())
        } else {
            Err(self.error(
                func,
                &format!(
                    "not allowed in {:?} mode (allowed in: {})",
                    self.mode,
                    modes
                        .iter()
                        .map(|m| format!("{m:?}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            ))
        }
    }
}

/// Runs `f` on a live instance, catching panics. An unknown or null instance gets
/// `fmi3Error` and a line on standard error (it has no logger to tell).
fn with(inst: *mut c_void, func: &str, f: impl FnOnce(&mut Instance) -> Status) -> Status {
    {
        let mut l = live();
        match l.iter_mut().find(|e| e.addr == inst as usize) {
            Some(e) if e.busy => {
                drop(l);
                stderr_line(&format!(
                    "{func}: called while a call of the same instance is running (re-entrant)"
                ));
                return ERROR;
            }
            Some(e) => e.busy = true,
            None => {
                drop(l);
                stderr_line(&format!(
                    "{func}: not an instance of this FMU (null, freed or foreign pointer)"
                ));
                return ERROR;
            }
        }
    }
    let s = with_entered(inst, func, f);
    if let Some(e) = live().iter_mut().find(|e| e.addr == inst as usize) {
        e.busy = false;
    }
    s
}

/// [`with`], for a call allowed only in `modes`: in another, `fmi3Error` naming the modes it
/// is allowed in, and nothing happens.
fn in_mode(
    inst: *mut c_void,
    func: &str,
    modes: &[Mode],
    f: impl FnOnce(&mut Instance) -> Status,
) -> Status {
    with(inst, func, |i| match i.expect(func, modes) {
        Ok(()) => f(i),
        Err(s) => s,
    })
}

fn with_entered(inst: *mut c_void, func: &str, f: impl FnOnce(&mut Instance) -> Status) -> Status {
    // SAFETY: the address is a live Box<Instance> of ours (LIVE), marked busy so that neither
    // fmi3FreeInstance nor another call takes it until this one ends; the importer does not
    // call one instance from two threads at once (FMI 3.0 §2.1.5).
    let i = unsafe { &mut *(inst as *mut Instance) };
    if i.mode == Mode::Broken && func != "fmi3Reset" {
        return i.error(
            func,
            "the instance failed earlier: only fmi3Reset or fmi3FreeInstance",
        );
    }
    match catch_unwind(AssertUnwindSafe(|| f(&mut *i))) {
        Ok(s) => {
            i.flush_log();
            s
        }
        Err(p) => {
            let what = p
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| p.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            i.mode = Mode::Broken;
            i.log(
                FATAL,
                "logStatusFatal",
                &format!("{func}: internal error: {what}"),
            );
            FATAL
        }
    }
}

unsafe fn str_arg<'a>(p: *const c_char) -> Option<&'a str> {
    if p.is_null() {
        None
    } else {
        // SAFETY: FMI strings are NUL-terminated C strings.
        unsafe { CStr::from_ptr(p) }.to_str().ok()
    }
}

/// The resources folder of an FMI 3.0 `resourcePath` (a native path ending in `/`).
fn read_resource(path: &str) -> Result<String, String> {
    let p = std::path::Path::new(path).join(RESOURCE_FILE);
    let meta = std::fs::metadata(&p).map_err(|e| format!("{}: {e}", p.display()))?;
    if meta.len() > 64 * 1024 {
        return Err(format!(
            "{}: {} bytes is too large",
            p.display(),
            meta.len()
        ));
    }
    std::fs::read_to_string(&p).map_err(|e| format!("{}: {e}", p.display()))
}

fn log_to(logger: Logger, env: *mut c_void, msg: &str) {
    match logger {
        Some(f) => {
            let (c, m) = (cstring("logStatusError"), cstring(msg));
            // SAFETY: the importer's callback.
            unsafe { f(env, ERROR, c.as_ptr(), m.as_ptr()) }
        }
        None => stderr_line(msg),
    }
}

/// `fmi3GetVersion`.
#[no_mangle]
pub extern "C" fn fmi3GetVersion() -> *const c_char {
    c"3.0".as_ptr()
}

/// `fmi3SetDebugLogging`.
#[no_mangle]
pub unsafe extern "C" fn fmi3SetDebugLogging(
    inst: *mut c_void,
    logging_on: bool,
    n_categories: usize,
    categories: *const *const c_char,
) -> Status {
    with(inst, "fmi3SetDebugLogging", |i| {
        if n_categories > 0 && categories.is_null() {
            return i.error("fmi3SetDebugLogging", "categories is null");
        }
        i.debug = logging_on;
        OK
    })
}

/// `fmi3InstantiateCoSimulation`: the kind and the unit come from `resourcePath`; a token
/// that is not this FMU's is refused (a modelDescription from another build or unit).
#[no_mangle]
pub unsafe extern "C" fn fmi3InstantiateCoSimulation(
    instance_name: *const c_char,
    token: *const c_char,
    resource_path: *const c_char,
    _visible: bool,
    logging_on: bool,
    event_mode_used: bool,
    early_return_allowed: bool,
    _required_intermediate: *const u32,
    _n_required_intermediate: usize,
    env: *mut c_void,
    logger: Logger,
    _intermediate_update: *const c_void,
) -> *mut c_void {
    let r = catch_unwind(AssertUnwindSafe(|| -> Result<*mut c_void, String> {
        let name = unsafe { str_arg(instance_name) }
            .ok_or("fmi3InstantiateCoSimulation: instanceName is null or not UTF-8")?;
        let token = unsafe { str_arg(token) }
            .ok_or("fmi3InstantiateCoSimulation: instantiationToken is null or not UTF-8")?;
        let res = unsafe { str_arg(resource_path) }.ok_or(
            "fmi3InstantiateCoSimulation: resourcePath is null: the FMU's resources say what it is",
        )?;
        let kind = Kind::from_resource(&read_resource(res)?)?;
        let model = kind.instantiate()?;
        let mine = &model.description().token;
        if token != mine {
            return Err(format!(
                "fmi3InstantiateCoSimulation: instantiationToken {token} is not this FMU's ({mine}): \
                 the modelDescription.xml and the binary are from different builds or units"
            ));
        }
        if !event_mode_used {
            // FMI 3.0: an FMU with clocks needs event mode; the LS-BUS Rx / Tx clocks tick there.
            return Err(
                "fmi3InstantiateCoSimulation: eventModeUsed is false, but this FMU's LS-BUS \
                 terminal has clocks (Rx_Clock, Tx_Clock), which need event mode"
                    .to_string(),
            );
        }
        let i = Box::new(Instance {
            name: name.to_string(),
            env,
            logger,
            debug: logging_on,
            mode: Mode::Instantiated,
            event_mode_used,
            early_return_allowed,
            stop_time: None,
            kind,
            model,
        });
        let p = Box::into_raw(i) as *mut c_void;
        live().push(Live {
            addr: p as usize,
            busy: false,
        });
        Ok(p)
    }));
    match r {
        Ok(Ok(p)) => p,
        Ok(Err(msg)) => {
            log_to(logger, env, &msg);
            std::ptr::null_mut()
        }
        Err(_) => {
            log_to(logger, env, "fmi3InstantiateCoSimulation: internal error");
            std::ptr::null_mut()
        }
    }
}

/// `fmi3InstantiateModelExchange`: not provided (canpos FMUs are co-simulation FMUs).
#[no_mangle]
pub unsafe extern "C" fn fmi3InstantiateModelExchange(
    _name: *const c_char,
    _token: *const c_char,
    _res: *const c_char,
    _visible: bool,
    _logging_on: bool,
    env: *mut c_void,
    logger: Logger,
) -> *mut c_void {
    log_to(
        logger,
        env,
        "fmi3InstantiateModelExchange: canpos FMUs are co-simulation FMUs only",
    );
    std::ptr::null_mut()
}

/// `fmi3InstantiateScheduledExecution`: not provided.
#[no_mangle]
pub unsafe extern "C" fn fmi3InstantiateScheduledExecution(
    _name: *const c_char,
    _token: *const c_char,
    _res: *const c_char,
    _visible: bool,
    _logging_on: bool,
    env: *mut c_void,
    logger: Logger,
    _clock_update: *const c_void,
    _lock: *const c_void,
    _unlock: *const c_void,
) -> *mut c_void {
    log_to(
        logger,
        env,
        "fmi3InstantiateScheduledExecution: canpos FMUs are co-simulation FMUs only",
    );
    std::ptr::null_mut()
}

/// `fmi3FreeInstance`: everything of the instance goes (its runtime, its state directory).
#[no_mangle]
pub unsafe extern "C" fn fmi3FreeInstance(inst: *mut c_void) {
    let mut l = live();
    let Some(k) = l.iter().position(|e| e.addr == inst as usize) else {
        drop(l);
        if !inst.is_null() {
            stderr_line("fmi3FreeInstance: not an instance of this FMU");
        }
        return;
    };
    if l[k].busy {
        drop(l);
        stderr_line("fmi3FreeInstance: called while a call of the same instance is running (re-entrant): not freed");
        return;
    }
    l.swap_remove(k);
    if l.is_empty() {
        // Nothing of the library outlives its last instance: an importer may unload it.
        *l = Vec::new();
    }
    drop(l);
    // SAFETY: it was ours and is no longer reachable through LIVE.
    let b = unsafe { Box::from_raw(inst as *mut Instance) };
    let _ = catch_unwind(AssertUnwindSafe(move || drop(b)));
}

/// `fmi3EnterInitializationMode`.
#[no_mangle]
pub unsafe extern "C" fn fmi3EnterInitializationMode(
    inst: *mut c_void,
    _tolerance_defined: bool,
    _tolerance: f64,
    start_time: f64,
    stop_time_defined: bool,
    stop_time: f64,
) -> Status {
    const F: &str = "fmi3EnterInitializationMode";
    in_mode(inst, F, &[Mode::Instantiated], |i| {
        if stop_time_defined && (stop_time.is_nan() || stop_time < start_time) {
            return i.error(
                F,
                &format!("stop time {stop_time} before start time {start_time}"),
            );
        }
        let r = i.model.enter_initialization(start_time);
        if r.is_ok() {
            i.stop_time = stop_time_defined.then_some(stop_time);
        }
        i.switch(F, r, Mode::Initialization)
    })
}

/// `fmi3ExitInitializationMode`: the unit starts (event mode if the importer uses it).
#[no_mangle]
pub unsafe extern "C" fn fmi3ExitInitializationMode(inst: *mut c_void) -> Status {
    const F: &str = "fmi3ExitInitializationMode";
    in_mode(inst, F, &[Mode::Initialization], |i| {
        let to = if i.event_mode_used {
            Mode::Event
        } else {
            Mode::Step
        };
        let r = i.model.exit_initialization();
        i.switch(F, r, to)
    })
}

/// `fmi3EnterEventMode`.
#[no_mangle]
pub unsafe extern "C" fn fmi3EnterEventMode(inst: *mut c_void) -> Status {
    const F: &str = "fmi3EnterEventMode";
    in_mode(inst, F, &[Mode::Step], |i| {
        if !i.event_mode_used {
            return i.error(
                F,
                "the instance was instantiated with eventModeUsed = false",
            );
        }
        let r = i.model.enter_event_mode();
        i.switch(F, r, Mode::Event)
    })
}

/// `fmi3Terminate`.
#[no_mangle]
pub unsafe extern "C" fn fmi3Terminate(inst: *mut c_void) -> Status {
    const F: &str = "fmi3Terminate";
    in_mode(
        inst,
        F,
        &[Mode::Step, Mode::Event, Mode::Initialization],
        |i| i.switch(F, Ok(()), Mode::Terminated),
    )
}

/// `fmi3Reset`: back to the state right after instantiation (a new unit, defaults).
#[no_mangle]
pub unsafe extern "C" fn fmi3Reset(inst: *mut c_void) -> Status {
    const F: &str = "fmi3Reset";
    with(inst, F, |i| {
        let r = i.kind.instantiate().map(|m| {
            i.model = m;
            i.stop_time = None;
        });
        i.switch(F, r, Mode::Instantiated)
    })
}

/// The arrays of a get / set call: `n` value references at `vrs` and `n_values` values
/// (canpos FMUs have no arrays: one value a reference); `values_null` when a values pointer
/// of the call (`values`, or `sizes` of a binary) is null.
#[derive(Clone, Copy)]
struct Arrays {
    vrs: *const u32,
    n: usize,
    values_null: bool,
    n_values: usize,
}

/// A call's value references, checked (see [`access`]).
#[derive(Clone, Copy)]
struct Refs {
    vrs: *const u32,
    n: usize,
}

impl Arrays {
    fn new(vrs: *const u32, n: usize, values_null: bool, n_values: usize) -> Arrays {
        Arrays {
            vrs,
            n,
            values_null,
            n_values,
        }
    }
}

impl Refs {
    /// The `k`-th value reference, `k` < `n`.
    fn at(self, k: usize) -> u32 {
        debug_assert!(k < self.n);
        // SAFETY: `vrs` is not null when `n` > 0 (checked in `access`) and the importer gives
        // `n` value references there.
        unsafe { *self.vrs.add(k) }
    }

    fn each(self) -> impl Iterator<Item = (usize, u32)> {
        (0..self.n).map(move |k| (k, self.at(k)))
    }
}

/// The one checked path of every get / set call: a live instance, in one of `modes` (any when
/// empty), pointers that are not null where values are passed, as many values as references,
/// and `check` passed by each reference (`k`, value reference): only then does `f` read or set
/// anything, so a refused call changes nothing.
fn access(
    inst: *mut c_void,
    func: &str,
    modes: &[Mode],
    a: Arrays,
    mut check: impl FnMut(&Instance, usize, u32) -> Result<(), Status>,
    f: impl FnOnce(&mut Instance, Refs) -> Status,
) -> Status {
    with(inst, func, |i| {
        if !modes.is_empty() {
            if let Err(s) = i.expect(func, modes) {
                return s;
            }
        }
        if a.n > 0 && (a.vrs.is_null() || a.values_null) {
            return i.error(func, "valueReferences or values is null");
        }
        if a.n != a.n_values {
            return i.error(
                func,
                &format!(
                    "nValues = {} for {} value references (canpos FMUs have no arrays)",
                    a.n_values, a.n
                ),
            );
        }
        let refs = Refs { vrs: a.vrs, n: a.n };
        for (k, vr) in refs.each() {
            if let Err(s) = check(i, k, vr) {
                return s;
            }
        }
        f(i, refs)
    })
}

/// Reads each checked reference's value and hands it to `put` (`k`, value reference, value);
/// the model's or `put`'s refusal is the call's `fmi3Error`.
fn get_each(
    i: &mut Instance,
    func: &str,
    refs: Refs,
    mut put: impl FnMut(usize, u32, Value<'_>) -> Result<(), String>,
) -> Status {
    for (k, vr) in refs.each() {
        let r = i.model.get(vr).and_then(|v| put(k, vr, v));
        if let Err(e) = r {
            return i.error(func, &e);
        }
    }
    OK
}

/// Sets each checked reference to `value(k)`; the model's refusal is the call's `fmi3Error`.
fn set_each<'a>(
    i: &mut Instance,
    func: &str,
    refs: Refs,
    value: impl Fn(usize) -> Value<'a>,
) -> Status {
    for (k, vr) in refs.each() {
        if let Err(e) = i.model.set(vr, value(k)) {
            return i.error(func, &e);
        }
    }
    OK
}

fn check_type(i: &Instance, func: &str, vr: u32, ty: VarType) -> Result<(), Status> {
    match i.model.description().variable(vr) {
        None => Err(i.error(func, &format!("no variable with value reference {vr}"))),
        Some(v) if v.ty != ty => Err(i.error(
            func,
            &format!(
                "`{}` (value reference {vr}) is a {}, not a {}",
                v.name,
                v.ty.element(),
                ty.element()
            ),
        )),
        Some(_) => Ok(()),
    }
}

fn check_set(i: &Instance, func: &str, vr: u32, ty: VarType) -> Result<(), Status> {
    check_type(i, func, vr, ty)?;
    let v = i.model.description().variable(vr).expect("checked");
    let ok = match (v.causality, ty) {
        (Causality::Output | Causality::Independent, _) => false,
        (Causality::Parameter, _) => matches!(i.mode, Mode::Instantiated | Mode::Initialization),
        (Causality::Input, VarType::Clock) => i.mode == Mode::Event,
        (Causality::Input, _) => matches!(
            i.mode,
            Mode::Instantiated | Mode::Initialization | Mode::Step | Mode::Event
        ),
    };
    if ok {
        Ok(())
    } else {
        Err(i.error(
            func,
            &format!(
                "`{}` ({:?}) cannot be set in {:?} mode",
                v.name, v.causality, i.mode
            ),
        ))
    }
}

fn get_scalars<T: Copy>(
    inst: *mut c_void,
    func: &str,
    ty: VarType,
    vrs: *const u32,
    n: usize,
    values: *mut T,
    n_values: usize,
    conv: fn(Value<'_>) -> Option<T>,
) -> Status {
    let a = Arrays::new(vrs, n, values.is_null(), n_values);
    access(
        inst,
        func,
        &[],
        a,
        |i, _, vr| check_type(i, func, vr, ty),
        |i, refs| {
            get_each(i, func, refs, |k, vr, v| match conv(v) {
                Some(v) => {
                    // SAFETY: the importer gives n values there (checked non-null).
                    unsafe { *values.add(k) = v };
                    Ok(())
                }
                None => Err(format!("value reference {vr} has another type")),
            })
        },
    )
}

fn set_scalars<T: Copy>(
    inst: *mut c_void,
    func: &str,
    ty: VarType,
    vrs: *const u32,
    n: usize,
    values: *const T,
    n_values: usize,
    conv: fn(T) -> Value<'static>,
) -> Status {
    let a = Arrays::new(vrs, n, values.is_null(), n_values);
    access(
        inst,
        func,
        &[],
        a,
        |i, _, vr| check_set(i, func, vr, ty),
        // SAFETY: the importer gives n values there (checked non-null).
        |i, refs| set_each(i, func, refs, |k| conv(unsafe { *values.add(k) })),
    )
}

fn no_such(i: &Instance, func: &str, vr: u32) -> Status {
    match i.model.description().variable(vr) {
        None => i.error(func, &format!("no variable with value reference {vr}")),
        Some(v) => i.error(
            func,
            &format!(
                "`{}` (value reference {vr}) is a {}",
                v.name,
                v.ty.element()
            ),
        ),
    }
}

/// A getter / setter pair for a type canpos FMUs have no variable of: any value reference is
/// refused as unknown (none is), zero of them is fine.
macro_rules! no_variables_of {
    ($get:ident, $set:ident, $t:ty) => {
        /// No variable of this type: refused with the reason.
        #[no_mangle]
        pub unsafe extern "C" fn $get(
            inst: *mut c_void,
            vrs: *const u32,
            n: usize,
            values: *mut $t,
            n_values: usize,
        ) -> Status {
            none_of(inst, stringify!($get), vrs, n, values.is_null(), n_values)
        }
        /// No variable of this type: refused with the reason.
        #[no_mangle]
        pub unsafe extern "C" fn $set(
            inst: *mut c_void,
            vrs: *const u32,
            n: usize,
            values: *const $t,
            n_values: usize,
        ) -> Status {
            none_of(inst, stringify!($set), vrs, n, values.is_null(), n_values)
        }
    };
}

/// A get or set of a type canpos FMUs have no variable of: the first value reference is
/// refused as [`no_such`]; none at all is fine.
fn none_of(
    inst: *mut c_void,
    func: &str,
    vrs: *const u32,
    n: usize,
    values_null: bool,
    n_values: usize,
) -> Status {
    let a = Arrays::new(vrs, n, values_null, n_values);
    access(
        inst,
        func,
        &[],
        a,
        |i, _, vr| Err(no_such(i, func, vr)),
        |_, _| OK,
    )
}

no_variables_of!(fmi3GetFloat32, fmi3SetFloat32, f32);
no_variables_of!(fmi3GetInt8, fmi3SetInt8, i8);
no_variables_of!(fmi3GetInt16, fmi3SetInt16, i16);
no_variables_of!(fmi3GetInt32, fmi3SetInt32, i32);
no_variables_of!(fmi3GetInt64, fmi3SetInt64, i64);
no_variables_of!(fmi3GetString, fmi3SetString, *const c_char);

macro_rules! scalars {
    ($get:ident, $set:ident, $t:ty, $vt:ident) => {
        /// Reads variables of this type.
        #[no_mangle]
        pub unsafe extern "C" fn $get(
            inst: *mut c_void,
            vrs: *const u32,
            n: usize,
            values: *mut $t,
            n_values: usize,
        ) -> Status {
            get_scalars(
                inst,
                stringify!($get),
                VarType::$vt,
                vrs,
                n,
                values,
                n_values,
                |v| match v {
                    Value::$vt(x) => Some(x),
                    _ => None,
                },
            )
        }
        /// Writes variables of this type.
        #[no_mangle]
        pub unsafe extern "C" fn $set(
            inst: *mut c_void,
            vrs: *const u32,
            n: usize,
            values: *const $t,
            n_values: usize,
        ) -> Status {
            set_scalars(
                inst,
                stringify!($set),
                VarType::$vt,
                vrs,
                n,
                values,
                n_values,
                Value::$vt,
            )
        }
    };
}

scalars!(fmi3GetFloat64, fmi3SetFloat64, f64, Float64);
scalars!(fmi3GetUInt8, fmi3SetUInt8, u8, UInt8);
scalars!(fmi3GetUInt16, fmi3SetUInt16, u16, UInt16);
scalars!(fmi3GetUInt32, fmi3SetUInt32, u32, UInt32);
scalars!(fmi3GetUInt64, fmi3SetUInt64, u64, UInt64);

/// `fmi3GetBoolean`.
#[no_mangle]
pub unsafe extern "C" fn fmi3GetBoolean(
    inst: *mut c_void,
    vrs: *const u32,
    n: usize,
    values: *mut bool,
    n_values: usize,
) -> Status {
    get_scalars(
        inst,
        "fmi3GetBoolean",
        VarType::Boolean,
        vrs,
        n,
        values,
        n_values,
        |v| match v {
            Value::Boolean(x) => Some(x),
            _ => None,
        },
    )
}

/// `fmi3SetBoolean`: any non-zero byte is true (a C caller may pass any `bool` bit pattern).
#[no_mangle]
pub unsafe extern "C" fn fmi3SetBoolean(
    inst: *mut c_void,
    vrs: *const u32,
    n: usize,
    values: *const u8,
    n_values: usize,
) -> Status {
    set_scalars(
        inst,
        "fmi3SetBoolean",
        VarType::Boolean,
        vrs,
        n,
        values,
        n_values,
        |b| Value::Boolean(b != 0),
    )
}

/// `fmi3GetBinary`: pointers into the instance's own memory, valid until its next call.
#[no_mangle]
pub unsafe extern "C" fn fmi3GetBinary(
    inst: *mut c_void,
    vrs: *const u32,
    n: usize,
    sizes: *mut usize,
    values: *mut *const u8,
    n_values: usize,
) -> Status {
    const F: &str = "fmi3GetBinary";
    let a = Arrays::new(vrs, n, values.is_null() || sizes.is_null(), n_values);
    access(
        inst,
        F,
        &[],
        a,
        |i, _, vr| check_type(i, F, vr, VarType::Binary),
        |i, refs| {
            get_each(i, F, refs, |k, vr, v| match v {
                Value::Binary(b) => {
                    // SAFETY: the importer gives n sizes and n values there (checked non-null).
                    unsafe {
                        *sizes.add(k) = b.len();
                        *values.add(k) = b.as_ptr();
                    }
                    Ok(())
                }
                _ => Err(format!("value reference {vr} is not binary")),
            })
        },
    )
}

/// `fmi3SetBinary`: each value at most the variable's `maxSize`.
#[no_mangle]
pub unsafe extern "C" fn fmi3SetBinary(
    inst: *mut c_void,
    vrs: *const u32,
    n: usize,
    sizes: *const usize,
    values: *const *const u8,
    n_values: usize,
) -> Status {
    const F: &str = "fmi3SetBinary";
    let a = Arrays::new(vrs, n, values.is_null() || sizes.is_null(), n_values);
    // SAFETY: the importer gives n sizes and n values there (checked non-null).
    let arg = |k: usize| unsafe { (*sizes.add(k), *values.add(k)) };
    access(
        inst,
        F,
        &[],
        a,
        |i, k, vr| {
            check_set(i, F, vr, VarType::Binary)?;
            let (size, p) = arg(k);
            let v = i.model.description().variable(vr).expect("checked");
            let max = v.max_size.unwrap_or(usize::MAX);
            if size > max {
                return Err(i.error(
                    F,
                    &format!("{} bytes for `{}`, its maxSize is {max}", size, v.name),
                ));
            }
            if size > 0 && p.is_null() {
                return Err(i.error(
                    F,
                    &format!("a null pointer for {size} bytes of `{}`", v.name),
                ));
            }
            Ok(())
        },
        |i, refs| {
            set_each(i, F, refs, |k| {
                let (size, p) = arg(k);
                Value::Binary(if size == 0 {
                    &[]
                } else {
                    // SAFETY: the importer gives `size` readable bytes at `p` (non-null,
                    // checked).
                    unsafe { std::slice::from_raw_parts(p, size) }
                })
            })
        },
    )
}

/// `fmi3GetClock`: in event mode; an output clock reports each tick once.
#[no_mangle]
pub unsafe extern "C" fn fmi3GetClock(
    inst: *mut c_void,
    vrs: *const u32,
    n: usize,
    values: *mut bool,
) -> Status {
    const F: &str = "fmi3GetClock";
    let a = Arrays::new(vrs, n, values.is_null(), n);
    access(
        inst,
        F,
        &[Mode::Event],
        a,
        |i, _, vr| check_type(i, F, vr, VarType::Clock),
        |i, refs| {
            get_each(i, F, refs, |k, _, v| match v {
                Value::Clock(b) => {
                    // SAFETY: the importer gives n values there (checked non-null).
                    unsafe { *values.add(k) = b };
                    Ok(())
                }
                _ => Err("not a clock".to_string()),
            })
        },
    )
}

/// `fmi3SetClock`: input clocks, in event mode.
#[no_mangle]
pub unsafe extern "C" fn fmi3SetClock(
    inst: *mut c_void,
    vrs: *const u32,
    n: usize,
    values: *const u8,
) -> Status {
    const F: &str = "fmi3SetClock";
    let a = Arrays::new(vrs, n, values.is_null(), n);
    access(
        inst,
        F,
        &[],
        a,
        |i, _, vr| check_set(i, F, vr, VarType::Clock),
        // SAFETY: the importer gives n values there (checked non-null).
        |i, refs| set_each(i, F, refs, |k| Value::Clock(unsafe { *values.add(k) } != 0)),
    )
}

/// `fmi3UpdateDiscreteStates`: takes the operations of the input clocks set in this event.
#[no_mangle]
pub unsafe extern "C" fn fmi3UpdateDiscreteStates(
    inst: *mut c_void,
    need_update: *mut bool,
    terminate: *mut bool,
    nominals_changed: *mut bool,
    values_changed: *mut bool,
    next_time_defined: *mut bool,
    next_time: *mut f64,
) -> Status {
    const F: &str = "fmi3UpdateDiscreteStates";
    in_mode(inst, F, &[Mode::Event], |i| {
        if [
            need_update,
            terminate,
            nominals_changed,
            values_changed,
            next_time_defined,
        ]
        .iter()
        .any(|p| p.is_null())
            || next_time.is_null()
        {
            return i.error(F, "an output argument is null");
        }
        match i.model.update_discrete_states() {
            Ok(d) => unsafe {
                *need_update = d.need_update;
                *terminate = false;
                *nominals_changed = false;
                *values_changed = false;
                *next_time_defined = d.next_event_time.is_some();
                *next_time = d.next_event_time.unwrap_or(0.0);
                OK
            },
            Err(e) => i.error(F, &e),
        }
    })
}

/// `fmi3EnterStepMode`.
#[no_mangle]
pub unsafe extern "C" fn fmi3EnterStepMode(inst: *mut c_void) -> Status {
    const F: &str = "fmi3EnterStepMode";
    in_mode(inst, F, &[Mode::Event], |i| {
        let r = i.model.enter_step_mode();
        i.switch(F, r, Mode::Step)
    })
}

/// `fmi3DoStep`: runs the unit on the simulation clock; with early return allowed it stops at
/// the first time the unit sends something (`eventHandlingNeeded`: read `Tx_Data`).
#[no_mangle]
pub unsafe extern "C" fn fmi3DoStep(
    inst: *mut c_void,
    t: f64,
    h: f64,
    _no_set_state_prior: bool,
    event_needed: *mut bool,
    terminate: *mut bool,
    early_return: *mut bool,
    last_time: *mut f64,
) -> Status {
    const F: &str = "fmi3DoStep";
    in_mode(inst, F, &[Mode::Step], |i| {
        if event_needed.is_null()
            || terminate.is_null()
            || early_return.is_null()
            || last_time.is_null()
        {
            return i.error(F, "an output argument is null");
        }
        if let Some(stop) = i.stop_time {
            // FMI 3.0: computing past a defined stop time is an error (1 µs: the unit's grain; a
            // NaN is refused by the model).
            if t + h > stop + 1e-6 {
                return i.error(
                    F,
                    &format!("a step from {t} s by {h} s goes past the stop time {stop} s"),
                );
            }
        }
        let early = i.early_return_allowed && i.event_mode_used;
        match i.model.do_step(t, h, early) {
            Ok(r) => unsafe {
                *event_needed = r.event_needed && i.event_mode_used;
                *terminate = false;
                *early_return = r.early_return;
                *last_time = r.last_time;
                OK
            },
            Err(e) => i.error(F, &e),
        }
    })
}

/// The functions canpos FMUs do not provide: `fmi3Error` with the reason in the log.
macro_rules! unsupported {
    ($($f:ident: $why:literal),* $(,)?) => {$(
        /// Not provided by canpos FMUs: `fmi3Error` with the reason.
        #[no_mangle]
        pub unsafe extern "C" fn $f(inst: *mut c_void) -> Status {
            with(inst, stringify!($f), |i| i.error(stringify!($f), $why))
        }
    )*};
}

unsupported!(
    fmi3GetNumberOfVariableDependencies: "no dependency information (every output depends on every input)",
    fmi3GetVariableDependencies: "no dependency information (every output depends on every input)",
    fmi3GetFMUState: "canGetAndSetFMUState is false",
    fmi3SetFMUState: "canGetAndSetFMUState is false",
    fmi3FreeFMUState: "canGetAndSetFMUState is false",
    fmi3SerializedFMUStateSize: "canSerializeFMUState is false",
    fmi3SerializeFMUState: "canSerializeFMUState is false",
    fmi3DeserializeFMUState: "canSerializeFMUState is false",
    fmi3GetDirectionalDerivative: "providesDirectionalDerivatives is false",
    fmi3GetAdjointDerivative: "providesAdjointDerivatives is false",
    fmi3EnterConfigurationMode: "no structural parameters",
    fmi3ExitConfigurationMode: "no structural parameters",
    fmi3GetIntervalDecimal: "the LS-BUS clocks are triggered clocks, without intervals",
    fmi3GetIntervalFraction: "the LS-BUS clocks are triggered clocks, without intervals",
    fmi3GetShiftDecimal: "the LS-BUS clocks are triggered clocks, without shifts",
    fmi3GetShiftFraction: "the LS-BUS clocks are triggered clocks, without shifts",
    fmi3SetIntervalDecimal: "the LS-BUS clocks are triggered clocks, without intervals",
    fmi3SetIntervalFraction: "the LS-BUS clocks are triggered clocks, without intervals",
    fmi3SetShiftDecimal: "the LS-BUS clocks are triggered clocks, without shifts",
    fmi3SetShiftFraction: "the LS-BUS clocks are triggered clocks, without shifts",
    fmi3EvaluateDiscreteStates: "providesEvaluateDiscreteStates is false",
    fmi3EnterContinuousTimeMode: "Model Exchange only",
    fmi3CompletedIntegratorStep: "Model Exchange only",
    fmi3SetTime: "Model Exchange only",
    fmi3SetContinuousStates: "Model Exchange only",
    fmi3GetContinuousStateDerivatives: "Model Exchange only",
    fmi3GetEventIndicators: "Model Exchange only",
    fmi3GetContinuousStates: "Model Exchange only",
    fmi3GetNominalsOfContinuousStates: "Model Exchange only",
    fmi3GetNumberOfEventIndicators: "Model Exchange only",
    fmi3GetNumberOfContinuousStates: "Model Exchange only",
    fmi3GetOutputDerivatives: "providesOutputDerivatives is false (no continuous outputs)",
    fmi3ActivateModelPartition: "Scheduled Execution only",
);

/// The names of every exported `fmi3*` function (a test checks the library exports them all).
pub const EXPORTED: [&str; 75] = [
    "fmi3GetVersion",
    "fmi3SetDebugLogging",
    "fmi3InstantiateModelExchange",
    "fmi3InstantiateCoSimulation",
    "fmi3InstantiateScheduledExecution",
    "fmi3FreeInstance",
    "fmi3EnterInitializationMode",
    "fmi3ExitInitializationMode",
    "fmi3EnterEventMode",
    "fmi3Terminate",
    "fmi3Reset",
    "fmi3GetFloat32",
    "fmi3GetFloat64",
    "fmi3GetInt8",
    "fmi3GetUInt8",
    "fmi3GetInt16",
    "fmi3GetUInt16",
    "fmi3GetInt32",
    "fmi3GetUInt32",
    "fmi3GetInt64",
    "fmi3GetUInt64",
    "fmi3GetBoolean",
    "fmi3GetString",
    "fmi3GetBinary",
    "fmi3GetClock",
    "fmi3SetFloat32",
    "fmi3SetFloat64",
    "fmi3SetInt8",
    "fmi3SetUInt8",
    "fmi3SetInt16",
    "fmi3SetUInt16",
    "fmi3SetInt32",
    "fmi3SetUInt32",
    "fmi3SetInt64",
    "fmi3SetUInt64",
    "fmi3SetBoolean",
    "fmi3SetString",
    "fmi3SetBinary",
    "fmi3SetClock",
    "fmi3GetNumberOfVariableDependencies",
    "fmi3GetVariableDependencies",
    "fmi3GetFMUState",
    "fmi3SetFMUState",
    "fmi3FreeFMUState",
    "fmi3SerializedFMUStateSize",
    "fmi3SerializeFMUState",
    "fmi3DeserializeFMUState",
    "fmi3GetDirectionalDerivative",
    "fmi3GetAdjointDerivative",
    "fmi3EnterConfigurationMode",
    "fmi3ExitConfigurationMode",
    "fmi3GetIntervalDecimal",
    "fmi3GetIntervalFraction",
    "fmi3GetShiftDecimal",
    "fmi3GetShiftFraction",
    "fmi3SetIntervalDecimal",
    "fmi3SetIntervalFraction",
    "fmi3SetShiftDecimal",
    "fmi3SetShiftFraction",
    "fmi3EvaluateDiscreteStates",
    "fmi3UpdateDiscreteStates",
    "fmi3EnterContinuousTimeMode",
    "fmi3CompletedIntegratorStep",
    "fmi3SetTime",
    "fmi3SetContinuousStates",
    "fmi3GetContinuousStateDerivatives",
    "fmi3GetEventIndicators",
    "fmi3GetContinuousStates",
    "fmi3GetNominalsOfContinuousStates",
    "fmi3GetNumberOfEventIndicators",
    "fmi3GetNumberOfContinuousStates",
    "fmi3EnterStepMode",
    "fmi3GetOutputDerivatives",
    "fmi3DoStep",
    "fmi3ActivateModelPartition",
];
