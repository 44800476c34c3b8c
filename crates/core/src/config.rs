//! Build options: every switch a build may set, in one place (the role of CANopenNode's
//! `CO_config.h`). Service code reads these constants in plain `if`s, so both arms of every
//! option compile in every build; the compiler drops the arm a build does not take.
//!
//! The features themselves are documented in `crates/core/Cargo.toml`.

/// Feature `inline-hot-paths`: hot paths inlined for fewer instructions per frame (a host).
pub const INLINE_HOT_PATHS: bool = cfg!(feature = "inline-hot-paths");
/// Feature `simulation`: what a simulated device needs and a firmware's hardware does itself.
pub const SIMULATION: bool = cfg!(feature = "simulation");
/// Feature `names`: object names in the tables and the EDS export.
pub const NAMES: bool = cfg!(feature = "names");
/// Feature `host-buffers`: buffers sized for any device a host may run.
pub const HOST_BUFFERS: bool = cfg!(feature = "host-buffers");

// --- Sizes ----------------------------------------------------------------------------------

/// Most TPDOs a device has (0x1800… / 0x1A00…): each costs its state in RAM.
pub const MAX_TPDOS: usize = 4;
const _: () = assert!(MAX_TPDOS.is_power_of_two() && MAX_TPDOS <= 8);
/// Most mapping entries per TPDO (0x1A00/1…8): eight 8-bit objects fill a frame.
pub const MAX_MAP: usize = 8;
