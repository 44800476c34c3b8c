//! The part of Vector SIL Kit's C API canpos uses, declared by hand and resolved at run time
//! from `libSilKit.so` (D35): a build without SIL Kit builds and tests, and the library is
//! only needed by a process that joins a SIL Kit network.
//!
//! The declarations follow SIL Kit 5.0.3's `silkit/capi/*.h` (read from the SilKit_py 1.0.5
//! sdist, docs/SILKIT.md). Every struct there is packed to 8, which is the natural alignment of
//! its members: `#[repr(C)]` gives the same layout. Only major versions in [`KNOWN_MAJORS`] are
//! accepted, because the structs and the experimental functions may change with a major.
//!
//! The library is loaded once per process and never unloaded: SIL Kit runs its own threads,
//! which must not outlive their code.

use std::ffi::{c_char, c_void, CStr};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// SIL Kit major versions whose C API this module declares.
pub const KNOWN_MAJORS: &[u32] = &[5];

/// The environment variable naming `libSilKit.so` (a path).
pub const LIB_ENV: &str = "CANPOS_SILKIT_LIB";
/// The environment variable naming the `sil-kit-registry` executable (tests, `scripts/silkit.sh`).
pub const REGISTRY_ENV: &str = "CANPOS_SILKIT_REGISTRY";
/// Where `scripts/silkit.sh` unpacks the wheel, relative to cargo's `target/` directory.
pub const TARGET_SUBDIR: &str = "silkit/unpacked/SilKit_py";

/// `SilKit_ReturnCode`.
pub type ReturnCode = i32;
/// `SilKit_NanosecondsTime`: simulation time in nanoseconds.
pub type NanosecondsTime = u64;
/// `SilKit_HandlerId`.
pub type HandlerId = u64;
/// `SilKit_Bool`.
pub type SkBool = u8;

/// `SilKit_ReturnCode_SUCCESS`.
pub const RC_SUCCESS: ReturnCode = 0;

/// The name of a `SilKit_ReturnCode` (Types.h).
pub fn return_code_name(rc: ReturnCode) -> &'static str {
    match rc {
        0 => "SUCCESS",
        1 => "UNSPECIFIEDERROR",
        2 => "NOTSUPPORTED",
        3 => "NOTIMPLEMENTED",
        4 => "BADPARAMETER",
        5 => "BUFFERTOOSMALL",
        6 => "TIMEOUT",
        7 => "UNSUPPORTEDSERVICE",
        8 => "WRONGSTATE",
        9 => "TYPECONVERSIONERROR",
        10 => "CONFIGURATIONERROR",
        11 => "PROTOCOLERROR",
        12 => "ASSERTIONERROR",
        13 => "EXTENSIONERROR",
        14 => "LOGICERROR",
        15 => "LENGTHERROR",
        16 => "OUTOFRANGEERROR",
        _ => "unknown return code",
    }
}

/// Opaque `SilKit_ParticipantConfiguration`.
#[repr(C)]
pub struct ParticipantConfiguration {
    _opaque: [u8; 0],
}
/// Opaque `SilKit_Participant`.
#[repr(C)]
pub struct Participant {
    _opaque: [u8; 0],
}
/// Opaque `SilKit_CanController`.
#[repr(C)]
pub struct CanController {
    _opaque: [u8; 0],
}
/// Opaque `SilKit_LifecycleService`.
#[repr(C)]
pub struct LifecycleService {
    _opaque: [u8; 0],
}
/// Opaque `SilKit_TimeSyncService`.
#[repr(C)]
pub struct TimeSyncService {
    _opaque: [u8; 0],
}

/// `SilKit_StructHeader`: every versioned struct starts with it.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StructHeader {
    /// The struct's id and version (`SK_ID_MAKE`).
    pub version: u64,
    /// Zero.
    pub reserved: [u64; 3],
}

/// `SK_ID_SERVICE_Can`.
pub const SERVICE_CAN: u8 = 1;
/// `SK_ID_SERVICE_Participant`.
pub const SERVICE_PARTICIPANT: u8 = 7;
/// `SK_ID_SERVICE_NetworkSimulation`.
pub const SERVICE_NETWORK_SIMULATION: u8 = 8;

/// `SK_ID_MAKE(service, datatype)`: "SK", the service, the data type and its version.
pub const fn struct_id(service: u8, datatype: u8, version: u8) -> u64 {
    (83u64 << 56)
        | (75u64 << 48)
        | ((service as u64) << 40)
        | ((datatype as u64) << 32)
        | ((version as u64) << 24)
}

impl StructHeader {
    /// A header for the struct `id` ([`struct_id`]).
    pub const fn new(id: u64) -> StructHeader {
        StructHeader {
            version: id,
            reserved: [0; 3],
        }
    }
}

/// `SilKit_ByteVector`.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct ByteVector {
    /// The bytes (may be null when `size` is 0).
    pub data: *const u8,
    /// Their number.
    pub size: usize,
}

/// `SilKit_CanFrame` (version 1).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct CanFrame {
    /// [`CAN_FRAME_ID`].
    pub header: StructHeader,
    /// The identifier (11 or 29 bits).
    pub id: u32,
    /// `SilKit_CanFrameFlag_*`.
    pub flags: u32,
    /// Data length code.
    pub dlc: u16,
    /// CAN XL only.
    pub sdt: u8,
    /// CAN XL only.
    pub vcid: u8,
    /// CAN XL only.
    pub af: u32,
    /// The data field.
    pub data: ByteVector,
}
/// `SilKit_CanFrame_STRUCT_VERSION`.
pub const CAN_FRAME_ID: u64 = struct_id(SERVICE_CAN, 1, 1);
/// `SilKit_CanFrameFlag_ide`: 29-bit identifier.
pub const CAN_FLAG_IDE: u32 = 1 << 9;
/// `SilKit_CanFrameFlag_rtr`: remote frame.
pub const CAN_FLAG_RTR: u32 = 1 << 4;
/// `SilKit_CanFrameFlag_fdf`: CAN FD frame.
pub const CAN_FLAG_FDF: u32 = 1 << 12;
/// `SilKit_CanFrameFlag_xlf`: CAN XL frame.
pub const CAN_FLAG_XLF: u32 = 1 << 15;

/// `SilKit_CanFrameEvent` (version 1).
#[repr(C)]
#[derive(Debug)]
pub struct CanFrameEvent {
    /// `SilKit_CanFrameEvent_STRUCT_VERSION`.
    pub header: StructHeader,
    /// Reception time (simulation time; undefined without time synchronisation).
    pub timestamp: NanosecondsTime,
    /// The frame.
    pub frame: *mut CanFrame,
    /// `SilKit_Direction_*`.
    pub direction: u8,
    /// The sender's user context (own frames only).
    pub user_context: *mut c_void,
}
/// `SilKit_Direction_Send`.
pub const DIRECTION_SEND: u8 = 1;
/// `SilKit_Direction_Receive`.
pub const DIRECTION_RECEIVE: u8 = 2;
/// `SilKit_Direction_SendReceive`.
pub const DIRECTION_SEND_RECEIVE: u8 = 3;

/// `SilKit_CanFrameTransmitEvent` (version 2).
#[repr(C)]
#[derive(Debug)]
pub struct CanFrameTransmitEvent {
    /// `SilKit_CanFrameTransmitEvent_STRUCT_VERSION`.
    pub header: StructHeader,
    /// The user context given to `SendFrame`.
    pub user_context: *mut c_void,
    /// Transmission time.
    pub timestamp: NanosecondsTime,
    /// `SilKit_CanTransmitStatus_*` (one bit).
    pub status: i32,
    /// The frame's identifier.
    pub can_id: u32,
}
/// `SilKit_CanTransmitStatus_Transmitted`.
pub const CAN_TX_TRANSMITTED: i32 = 1;
/// `SilKit_CanTransmitStatus_Canceled`.
pub const CAN_TX_CANCELED: i32 = 2;
/// `SilKit_CanTransmitStatus_TransmitQueueFull`.
pub const CAN_TX_QUEUE_FULL: i32 = 4;

/// `SilKit_CanStateChangeEvent` (version 1).
#[repr(C)]
#[derive(Debug)]
pub struct CanStateChangeEvent {
    /// Header.
    pub header: StructHeader,
    /// When.
    pub timestamp: NanosecondsTime,
    /// `SilKit_CanControllerState_*`: 0 uninit, 1 stopped, 2 started, 3 sleep.
    pub state: i32,
}

/// `SilKit_CanErrorStateChangeEvent` (version 1).
#[repr(C)]
#[derive(Debug)]
pub struct CanErrorStateChangeEvent {
    /// Header.
    pub header: StructHeader,
    /// When.
    pub timestamp: NanosecondsTime,
    /// `SilKit_CanErrorState_*`: 0 not available, 1 active, 2 passive, 3 bus-off.
    pub error_state: i32,
}

/// `SilKit_LifecycleConfiguration` (version 1).
#[repr(C)]
#[derive(Debug)]
pub struct LifecycleConfiguration {
    /// [`LIFECYCLE_CONFIGURATION_ID`].
    pub header: StructHeader,
    /// `SilKit_OperationMode_*`.
    pub operation_mode: i8,
}
/// `SilKit_LifecycleConfiguration_STRUCT_VERSION`.
pub const LIFECYCLE_CONFIGURATION_ID: u64 = struct_id(SERVICE_PARTICIPANT, 2, 1);
/// `SilKit_OperationMode_Coordinated`: the system controller drives the lifecycle.
pub const OPERATION_MODE_COORDINATED: i8 = 10;
/// `SilKit_OperationMode_Autonomous`: the participant drives its own lifecycle.
pub const OPERATION_MODE_AUTONOMOUS: i8 = 20;

/// `SilKit_ParticipantState_*` values.
pub mod participant_state {
    /// Running.
    pub const RUNNING: i16 = 50;
    /// Stopped.
    pub const STOPPED: i16 = 80;
    /// Error.
    pub const ERROR: i16 = 90;
    /// Shut down.
    pub const SHUTDOWN: i16 = 110;
    /// Aborting.
    pub const ABORTING: i16 = 120;
}

/// `SilKit_CanFrameHandler_t`.
pub type CanFrameHandler =
    unsafe extern "C" fn(ctx: *mut c_void, ctrl: *mut CanController, ev: *mut CanFrameEvent);
/// `SilKit_CanFrameTransmitHandler_t`.
pub type CanFrameTransmitHandler = unsafe extern "C" fn(
    ctx: *mut c_void,
    ctrl: *mut CanController,
    ev: *mut CanFrameTransmitEvent,
);
/// `SilKit_CanStateChangeHandler_t`.
pub type CanStateChangeHandler =
    unsafe extern "C" fn(ctx: *mut c_void, ctrl: *mut CanController, ev: *mut CanStateChangeEvent);
/// `SilKit_CanErrorStateChangeHandler_t`.
pub type CanErrorStateChangeHandler = unsafe extern "C" fn(
    ctx: *mut c_void,
    ctrl: *mut CanController,
    ev: *mut CanErrorStateChangeEvent,
);
/// `SilKit_LifecycleService_StopHandler_t` (also the shape of the communication-ready and
/// shutdown handlers).
pub type LifecycleHandler = unsafe extern "C" fn(ctx: *mut c_void, svc: *mut LifecycleService);
/// `SilKit_LifecycleService_AbortHandler_t`.
pub type AbortHandler =
    unsafe extern "C" fn(ctx: *mut c_void, svc: *mut LifecycleService, last_state: i16);
/// `SilKit_TimeSyncService_SimulationStepHandler_t`.
pub type SimulationStepHandler = unsafe extern "C" fn(
    ctx: *mut c_void,
    svc: *mut TimeSyncService,
    now: NanosecondsTime,
    duration: NanosecondsTime,
);

/// The functions canpos calls, resolved from the library.
#[allow(missing_docs)] // each field is the C function of the same name (SilKit_ prefix dropped)
pub struct Api {
    lib: libloading::Library,
    path: PathBuf,
    version: (u32, u32, u32),
    pub get_last_error_string: unsafe extern "C" fn() -> *const c_char,
    pub participant_configuration_from_string: unsafe extern "C" fn(
        out: *mut *mut ParticipantConfiguration,
        text: *const c_char,
    ) -> ReturnCode,
    pub participant_configuration_destroy:
        unsafe extern "C" fn(cfg: *mut ParticipantConfiguration) -> ReturnCode,
    pub participant_create: unsafe extern "C" fn(
        out: *mut *mut Participant,
        cfg: *mut ParticipantConfiguration,
        name: *const c_char,
        registry_uri: *const c_char,
    ) -> ReturnCode,
    pub participant_destroy: unsafe extern "C" fn(p: *mut Participant) -> ReturnCode,
    pub can_controller_create: unsafe extern "C" fn(
        out: *mut *mut CanController,
        p: *mut Participant,
        name: *const c_char,
        network: *const c_char,
    ) -> ReturnCode,
    pub can_controller_start: unsafe extern "C" fn(c: *mut CanController) -> ReturnCode,
    pub can_controller_stop: unsafe extern "C" fn(c: *mut CanController) -> ReturnCode,
    pub can_controller_set_baud_rate:
        unsafe extern "C" fn(c: *mut CanController, rate: u32, fd: u32, xl: u32) -> ReturnCode,
    pub can_controller_send_frame: unsafe extern "C" fn(
        c: *mut CanController,
        frame: *mut CanFrame,
        user: *mut c_void,
    ) -> ReturnCode,
    pub can_controller_add_frame_handler: unsafe extern "C" fn(
        c: *mut CanController,
        ctx: *mut c_void,
        h: CanFrameHandler,
        direction_mask: u8,
        out: *mut HandlerId,
    ) -> ReturnCode,
    pub can_controller_add_frame_transmit_handler: unsafe extern "C" fn(
        c: *mut CanController,
        ctx: *mut c_void,
        h: CanFrameTransmitHandler,
        status_mask: i32,
        out: *mut HandlerId,
    ) -> ReturnCode,
    pub can_controller_add_state_change_handler: unsafe extern "C" fn(
        c: *mut CanController,
        ctx: *mut c_void,
        h: CanStateChangeHandler,
        out: *mut HandlerId,
    ) -> ReturnCode,
    pub can_controller_add_error_state_change_handler: unsafe extern "C" fn(
        c: *mut CanController,
        ctx: *mut c_void,
        h: CanErrorStateChangeHandler,
        out: *mut HandlerId,
    ) -> ReturnCode,
    pub lifecycle_service_create: unsafe extern "C" fn(
        out: *mut *mut LifecycleService,
        p: *mut Participant,
        cfg: *const LifecycleConfiguration,
    ) -> ReturnCode,
    pub lifecycle_service_set_communication_ready_handler: unsafe extern "C" fn(
        s: *mut LifecycleService,
        ctx: *mut c_void,
        h: LifecycleHandler,
    ) -> ReturnCode,
    pub lifecycle_service_set_stop_handler: unsafe extern "C" fn(
        s: *mut LifecycleService,
        ctx: *mut c_void,
        h: LifecycleHandler,
    ) -> ReturnCode,
    pub lifecycle_service_set_shutdown_handler: unsafe extern "C" fn(
        s: *mut LifecycleService,
        ctx: *mut c_void,
        h: LifecycleHandler,
    ) -> ReturnCode,
    pub lifecycle_service_set_abort_handler: unsafe extern "C" fn(
        s: *mut LifecycleService,
        ctx: *mut c_void,
        h: AbortHandler,
    ) -> ReturnCode,
    pub lifecycle_service_start_lifecycle:
        unsafe extern "C" fn(s: *mut LifecycleService) -> ReturnCode,
    pub lifecycle_service_stop:
        unsafe extern "C" fn(s: *mut LifecycleService, reason: *const c_char) -> ReturnCode,
    pub lifecycle_service_wait_for_lifecycle_to_complete:
        unsafe extern "C" fn(s: *mut LifecycleService, out: *mut i16) -> ReturnCode,
    pub lifecycle_service_state:
        unsafe extern "C" fn(out: *mut i16, s: *mut LifecycleService) -> ReturnCode,
    pub time_sync_service_create: unsafe extern "C" fn(
        out: *mut *mut TimeSyncService,
        s: *mut LifecycleService,
    ) -> ReturnCode,
    pub time_sync_service_set_simulation_step_handler_async: unsafe extern "C" fn(
        t: *mut TimeSyncService,
        ctx: *mut c_void,
        h: SimulationStepHandler,
        initial_step: NanosecondsTime,
    )
        -> ReturnCode,
    pub time_sync_service_complete_simulation_step:
        unsafe extern "C" fn(t: *mut TimeSyncService) -> ReturnCode,
}

/// Errors of loading SIL Kit and of its calls.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Error {
    /// No `libSilKit.so` where canpos looks.
    #[error(
        "SIL Kit is not installed: no libSilKit.so at {tried} (run scripts/silkit.sh, or set \
         CANPOS_SILKIT_LIB to the library's path; docs/SILKIT.md)"
    )]
    NotFound {
        /// The places looked at, comma-separated.
        tried: String,
    },
    /// The library could not be loaded or lacks a function.
    #[error("cannot load SIL Kit from {path}: {reason}")]
    Load {
        /// The library's path.
        path: String,
        /// Why.
        reason: String,
    },
    /// The library is a SIL Kit whose major version canpos does not know.
    #[error(
        "SIL Kit {version} at {path} is not supported: canpos declares the C API of major \
         version(s) {known} (docs/SILKIT.md)"
    )]
    Version {
        /// The library's path.
        path: String,
        /// Its version.
        version: String,
        /// The majors canpos knows.
        known: String,
    },
    /// A SIL Kit call returned an error.
    #[error("{call} failed: {message} (SIL Kit {code_name})")]
    Call {
        /// The C function.
        call: &'static str,
        /// Its return code.
        code: ReturnCode,
        /// [`return_code_name`] of it.
        code_name: &'static str,
        /// SIL Kit's last error string.
        message: String,
    },
    /// An argument canpos cannot pass to SIL Kit (e.g. a name with a NUL byte).
    #[error("{0}")]
    BadArgument(String),
}

/// Refuses a library whose major version this module does not declare.
pub fn check_version(path: &Path, major: u32, minor: u32, patch: u32) -> Result<(), Error> {
    if KNOWN_MAJORS.contains(&major) {
        return Ok(());
    }
    Err(Error::Version {
        path: path.display().to_string(),
        version: format!("{major}.{minor}.{patch}"),
        known: KNOWN_MAJORS
            .iter()
            .map(|m| m.to_string())
            .collect::<Vec<_>>()
            .join(", "),
    })
}

/// Where canpos looks for `libSilKit.so`, in order: [`LIB_ENV`] alone when it is set;
/// otherwise `target/silkit/…` ([`TARGET_SUBDIR`]) above the running executable (so
/// `target/release/canpos` and the test binaries in `target/debug/deps` find what
/// `scripts/silkit.sh` installed).
pub fn library_candidates() -> Vec<PathBuf> {
    if let Some(p) = std::env::var_os(LIB_ENV) {
        return vec![PathBuf::from(p)];
    }
    let mut out = Vec::new();
    if let Ok(exe) = std::env::current_exe() {
        for dir in exe.ancestors().skip(1).take(4) {
            let p = dir.join(TARGET_SUBDIR).join("libSilKit.so");
            if !out.contains(&p) {
                out.push(p);
            }
        }
    }
    out
}

/// The `sil-kit-registry` that goes with the library: [`REGISTRY_ENV`] when set, else
/// `bin/sil-kit-registry` next to the library the candidates find.
pub fn registry_executable() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os(REGISTRY_ENV) {
        return Some(PathBuf::from(p));
    }
    library_candidates()
        .into_iter()
        .filter(|p| p.is_file())
        .filter_map(|p| p.parent().map(|d| d.join("bin/sil-kit-registry")))
        .find(|p| p.is_file())
}

/// The process's SIL Kit, loaded on first use from [`library_candidates`]; the same answer
/// (the API or the error) every time after.
pub fn api() -> Result<&'static Api, Error> {
    static API: OnceLock<Result<&'static Api, Error>> = OnceLock::new();
    API.get_or_init(|| {
        let candidates = library_candidates();
        let Some(path) = candidates.iter().find(|p| p.is_file()) else {
            return Err(Error::NotFound {
                tried: if candidates.is_empty() {
                    "no candidate path".into()
                } else {
                    candidates
                        .iter()
                        .map(|p| p.display().to_string())
                        .collect::<Vec<_>>()
                        .join(", ")
                },
            });
        };
        // Leaked: never unloaded (module docs).
        Api::load(path).map(|a| &*Box::leak(Box::new(a)))
    })
    .clone()
}

impl Api {
    /// Loads the library at `path`, checks its version and resolves every function. Prefer
    /// [`api`]: a library loaded twice is one library (the dynamic loader counts references).
    pub fn load(path: &Path) -> Result<Api, Error> {
        let load_err = |reason: String| Error::Load {
            path: path.display().to_string(),
            reason,
        };
        // SAFETY: loading runs the library's initialisers; libSilKit.so's are those of a C++
        // library (static objects), which is what the loader is for.
        let lib = unsafe { libloading::Library::new(path) }.map_err(|e| load_err(e.to_string()))?;
        type VersionFn = unsafe extern "C" fn(*mut u32) -> ReturnCode;
        let mut v = [0u32; 3];
        for (i, name) in [
            &b"SilKit_Version_Major\0"[..],
            b"SilKit_Version_Minor\0",
            b"SilKit_Version_Patch\0",
        ]
        .iter()
        .enumerate()
        {
            // SAFETY: the type is the C declaration's (Version.h).
            let f: VersionFn = unsafe { lib.get::<VersionFn>(*name) }
                .map(|s| *s)
                .map_err(|e| load_err(format!("not a SIL Kit library: {e}")))?;
            // SAFETY: writes one u32.
            let rc = unsafe { f(&mut v[i]) };
            if rc != RC_SUCCESS {
                return Err(load_err(format!("its version query returned {rc}")));
            }
        }
        check_version(path, v[0], v[1], v[2])?;
        macro_rules! sym {
            ($name:literal) => {{
                // SAFETY: the field's type is the C declaration of the function of that name
                // in SIL Kit 5's headers (checked by the major above).
                match unsafe { lib.get(concat!($name, "\0").as_bytes()) } {
                    Ok(s) => *s,
                    Err(e) => return Err(load_err(format!("{}: {e}", $name))),
                }
            }};
        }
        Ok(Api {
            get_last_error_string: sym!("SilKit_GetLastErrorString"),
            participant_configuration_from_string: sym!(
                "SilKit_ParticipantConfiguration_FromString"
            ),
            participant_configuration_destroy: sym!("SilKit_ParticipantConfiguration_Destroy"),
            participant_create: sym!("SilKit_Participant_Create"),
            participant_destroy: sym!("SilKit_Participant_Destroy"),
            can_controller_create: sym!("SilKit_CanController_Create"),
            can_controller_start: sym!("SilKit_CanController_Start"),
            can_controller_stop: sym!("SilKit_CanController_Stop"),
            can_controller_set_baud_rate: sym!("SilKit_CanController_SetBaudRate"),
            can_controller_send_frame: sym!("SilKit_CanController_SendFrame"),
            can_controller_add_frame_handler: sym!("SilKit_CanController_AddFrameHandler"),
            can_controller_add_frame_transmit_handler: sym!(
                "SilKit_CanController_AddFrameTransmitHandler"
            ),
            can_controller_add_state_change_handler: sym!(
                "SilKit_CanController_AddStateChangeHandler"
            ),
            can_controller_add_error_state_change_handler: sym!(
                "SilKit_CanController_AddErrorStateChangeHandler"
            ),
            lifecycle_service_create: sym!("SilKit_LifecycleService_Create"),
            lifecycle_service_set_communication_ready_handler: sym!(
                "SilKit_LifecycleService_SetCommunicationReadyHandler"
            ),
            lifecycle_service_set_stop_handler: sym!("SilKit_LifecycleService_SetStopHandler"),
            lifecycle_service_set_shutdown_handler: sym!(
                "SilKit_LifecycleService_SetShutdownHandler"
            ),
            lifecycle_service_set_abort_handler: sym!("SilKit_LifecycleService_SetAbortHandler"),
            lifecycle_service_start_lifecycle: sym!("SilKit_LifecycleService_StartLifecycle"),
            lifecycle_service_stop: sym!("SilKit_LifecycleService_Stop"),
            lifecycle_service_wait_for_lifecycle_to_complete: sym!(
                "SilKit_LifecycleService_WaitForLifecycleToComplete"
            ),
            lifecycle_service_state: sym!("SilKit_LifecycleService_State"),
            time_sync_service_create: sym!("SilKit_TimeSyncService_Create"),
            time_sync_service_set_simulation_step_handler_async: sym!(
                "SilKit_TimeSyncService_SetSimulationStepHandlerAsync"
            ),
            time_sync_service_complete_simulation_step: sym!(
                "SilKit_TimeSyncService_CompleteSimulationStep"
            ),
            path: path.to_path_buf(),
            version: (v[0], v[1], v[2]),
            lib,
        })
    }

    /// The library's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The library's (major, minor, patch).
    pub fn version(&self) -> (u32, u32, u32) {
        self.version
    }

    /// Resolves another function of the library (the network simulator's module binds its
    /// own functions this way, next to these).
    ///
    /// # Safety
    /// `T` must be the C declaration of the function `name` (NUL-terminated) in SIL Kit of
    /// [`Api::version`]'s major.
    pub unsafe fn symbol<T: Copy>(&self, name: &'static [u8]) -> Result<T, Error> {
        // SAFETY: forwarded to the caller.
        unsafe { self.lib.get::<T>(name) }
            .map(|s| *s)
            .map_err(|e| Error::Load {
                path: self.path.display().to_string(),
                reason: e.to_string(),
            })
    }

    /// `Ok` on success, else [`Error::Call`] with SIL Kit's last error string (per thread).
    pub fn check(&self, call: &'static str, rc: ReturnCode) -> Result<(), Error> {
        if rc == RC_SUCCESS {
            return Ok(());
        }
        // SAFETY: returns a NUL-terminated string owned by SIL Kit (thread-local), or null.
        let p = unsafe { (self.get_last_error_string)() };
        let message = if p.is_null() {
            String::new()
        } else {
            // SAFETY: non-null and NUL-terminated (SilKit.h).
            unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned()
        };
        Err(Error::Call {
            call,
            code: rc,
            code_name: return_code_name(rc),
            message: if message.is_empty() {
                "no message".into()
            } else {
                message
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn struct_ids_are_the_headers_sk_id_make() {
        // SK_ID_MAKE(Can, SilKit_CanFrame): 'S' 'K', service 1, data type 1, version 1.
        assert_eq!(CAN_FRAME_ID, 0x534B_0101_0100_0000);
        assert_eq!(LIFECYCLE_CONFIGURATION_ID, 0x534B_0702_0100_0000);
    }

    #[test]
    fn layouts_are_the_c_ones() {
        // Offsets of Can.h / Orchestration.h under #pragma pack(8) on x86_64.
        assert_eq!(std::mem::size_of::<StructHeader>(), 32);
        assert_eq!(std::mem::size_of::<CanFrame>(), 64);
        assert_eq!(std::mem::offset_of!(CanFrame, id), 32);
        assert_eq!(std::mem::offset_of!(CanFrame, dlc), 40);
        assert_eq!(std::mem::offset_of!(CanFrame, af), 44);
        assert_eq!(std::mem::offset_of!(CanFrame, data), 48);
        assert_eq!(std::mem::offset_of!(CanFrameEvent, frame), 40);
        assert_eq!(std::mem::offset_of!(CanFrameEvent, direction), 48);
        assert_eq!(std::mem::offset_of!(CanFrameEvent, user_context), 56);
        assert_eq!(std::mem::offset_of!(CanFrameTransmitEvent, status), 48);
        assert_eq!(std::mem::offset_of!(CanFrameTransmitEvent, can_id), 52);
        assert_eq!(
            std::mem::offset_of!(LifecycleConfiguration, operation_mode),
            32
        );
    }

    #[test]
    fn unknown_majors_are_refused() {
        let p = Path::new("/x/libSilKit.so");
        assert!(check_version(p, 5, 0, 3).is_ok());
        for major in [4, 6, 0] {
            let e = check_version(p, major, 0, 0).unwrap_err().to_string();
            assert!(
                e.contains(&format!("SIL Kit {major}.0.0 at /x/libSilKit.so")),
                "{e}"
            );
            assert!(e.contains("major version(s) 5"), "{e}");
        }
    }

    #[test]
    fn a_library_without_sil_kit_is_refused_by_name() {
        // libc is loaded in every process: it has no SilKit_Version_Major.
        let e = Api::load(Path::new("libc.so.6")).err().expect("refused");
        assert!(e.to_string().contains("not a SIL Kit library"), "{e}");
        let e = Api::load(Path::new("/nonexistent/libSilKit.so"))
            .err()
            .expect("refused");
        assert!(
            matches!(&e, Error::Load { path, .. } if path == "/nonexistent/libSilKit.so"),
            "{e}"
        );
    }

    #[test]
    fn return_codes_have_their_header_names() {
        assert_eq!(return_code_name(4), "BADPARAMETER");
        assert_eq!(return_code_name(16), "OUTOFRANGEERROR");
        assert_eq!(return_code_name(99), "unknown return code");
    }
}
