//! Build options: every switch a build may set, in one place (the role of CANopenNode's
//! `CO_config.h`). Service code reads these constants in plain `if`s, so both arms of every
//! option compile in every build; the compiler drops the arm a build does not take.
//!
//! The features themselves are documented in `crates/stack/Cargo.toml`; what each one saves
//! (flash, instructions per operation) is measured in docs/FIRMWARE.md ("Build options") and
//! docs/BENCHMARKS.md.
//!
//! Every size the stack is built with is here too. Two of them follow the one dictionary a
//! firmware runs and are set by its build, as smoltcp's `SMOLTCP_*` variables set its buffer
//! counts: `CANPOS_MAX_ENTRIES` ([`MAX_ENTRIES`]) and `CANPOS_MAX_STORED` ([`RECORDS_MAX`]),
//! read at compile time (`firmware/.cargo/config.toml` sets the TH's). A table larger than
//! them does not compile (the table's own `const` assert says which variable to raise).

/// Feature `inline-hot-paths`: hot paths inlined for fewer instructions per frame (a host).
/// Without it (firmware) the dictionary search, the TPDO timer walk and some fifteen helpers
/// are one shared copy each: the TH firmware 26,560 B instead of 35,712 B of flash (issue 37).
///
/// Every remaining host / firmware difference, one a line: what; TH flash saved without it
/// (firmware); instructions saved with it (host, `scripts/bench-instructions.sh`, TH) and the
/// operation. Flash and the instructions of the first four measured 2026-12-07 on main
/// cc2b2de by forcing that one site the other way (docs/FIRMWARE.md, "Build options in
/// figures", has the commands); the other instruction counts are earlier figures.
/// - the SDO server's expedited fast path (`sdo/server.rs`): 696 B; 88 per
///   expedited upload (427 / 515), 58 to 59 per expedited download, while it costs 1 per
///   TPDO, idle poll and LSS inquire
/// - the node's timer fast path (`other_due` / `fast_due`, `Node::after_tpdo_timers`, in
///   `handle_timeout` and `poll`): 400 B (the two fields stay in every build: a firmware pays
///   their 16 B of RAM and never reads them); 137 per TPDO (92 instead of 229), while it costs
///   4 to 5 per SDO request, LSS inquire and SYNC → TPDO (the epilogue writes the deadlines)
/// - `epilogue_inline` in `handle_frame` rather than the shared `epilogue`: 412 B; 2 to 4 per
///   frame: SDO upload 2 (427 / 429), downloads 3 to 4, SYNC → TPDO 4, LSS inquire 3
/// - `flush_emcy`'s inline early return when no EMCY work is waiting: 56 B; 20 to 22 per
///   frame: SDO upload 20 (427 / 447), downloads 21 to 22, SYNC → TPDO 21, LSS inquire 20
/// - the single-TPDO shortcut (`Tpdos::single`): 108 B; 22 per TPDO (91 instead of 113)
/// - the dense key array (`Model::keys`, its searches in `od/mod.rs` and `model.rs`): 852 B
///   (the TH's array 744 B); 57 per upload of an object other than the last
/// - the restricted CAN-ID bitmap (`wire::cob::restricted_id`): 200 B (256 B of bitmap less
///   the compares); some 30 per COB-ID download
/// - `stored_entry` (`node/persist.rs`) by `Dictionary::find` rather than by the key: 4 B; no
///   benchmarked operation (only "save", "load" and loading at reset look records up)
///
/// Besides these `if`s only attributes differ: `cfg_attr(…, inline / inline(never))`. Their
/// TH flash, each group forced the host's way alone (2026-12-07); their instructions for the
/// four largest groups, per file (the host given the firmware's `inline(never)`), the others
/// not measured:
/// - `od/mod.rs` `Dictionary::find`, `entry`, `value`, `set_value`: 2,900 B; 34 to 43 per SDO
///   request (upload 427 / 470), while they cost 35 per LSS inquire (236 / 201 without)
/// - `txq.rs` `push_std`, `reserve`: 708 B; 24 to 26 per SDO request, 10 per SYNC → TPDO, 5
///   per LSS inquire
/// - `pdo.rs` `Tpdo::send` 336 B, `refresh_due` 368 B, `Tpdo::step` 12 B; `Tpdos::scan_due`
///   −12 B (a firmware 12 B smaller with the host's `inline(always)`); together 32 per TPDO
///   (92 / 124), 16 per SYNC → TPDO
/// - `node/access.rs` `value_allowed` 64 B, `find` 48 B, `find_readable` 28 B,
///   `find_writable` 32 B (344 B together); together 87 per upload (427 / 514), 61 to 67 per
///   download
/// - `node/lss_glue.rs` `after_lss` 64 B, `lss_request` 308 B; `lss.rs` `Lss::handle`,
///   `address_part`: 292 B
/// - `emcy.rs` `find`, `register`, `event`, `record`: 240 B
/// - `wire/time.rs` `Instant + Duration`: 104 B; `od/types.rs` `Range::check` (`inline` on a
///   host only): 112 B; `wire/cob.rs` `restricted_id`: 32 B
/// - `sdo/server.rs` `SdoServer::reset` −64 B and `errctl.rs` `set_heartbeat` −12 B: their
///   `inline(never)` makes a firmware larger, not smaller (left as they are: this list only
///   measures)
///
/// What a simulated device's hardware does (the bus's bit rate, autobaud, the D7 store time)
/// is no option of the stack: the host's device wrapper does it (`canpos_host::runtime::
/// SimHardware`), the core reporting what it needs (`Node::bitrate_detected`, `Stats::stores`).
pub const INLINE_HOT_PATHS: bool = cfg!(feature = "inline-hot-paths");
/// Feature `names`: object names in the tables and the EDS export (a string reference per
/// entry and the strings: not in a firmware).
pub const NAMES: bool = cfg!(feature = "names");
/// Feature `host-buffers`: buffers sized for any device a host may run ([`TXQ_LEN`],
/// [`MAX_ENTRIES`], [`RECORDS_MAX`] below, with their RAM).
pub const HOST_BUFFERS: bool = cfg!(feature = "host-buffers");

// --- Sizes ------------------------------------------------------------------------------------

/// Most TPDOs a device has (0x1800… / 0x1A00…): each costs its state in RAM.
pub const MAX_TPDOS: usize = 4;
const _: () = assert!(MAX_TPDOS.is_power_of_two() && MAX_TPDOS <= 8);

/// Most mapping entries per TPDO (0x1A00/1…8): eight 8-bit objects fill a frame.
pub const MAX_MAP: usize = 8;

/// Most entries (objects and sub-indices) a dictionary may have: its value array, 4 B of RAM
/// each. On a host (`host-buffers`) 256, so that a slot fits a `u8` and
/// [`crate::od::Dictionary::get_u8`] needs no bounds check (the TPDO hot path). Without it
/// (firmware) `CANPOS_MAX_ENTRIES`, else 64 (a firmware's own small dictionary): the
/// firmware's table exactly, trading that bounds check for RAM.
pub const MAX_ENTRIES: usize = if HOST_BUFFERS {
    256
} else {
    env_or(option_env!("CANPOS_MAX_ENTRIES"), 64)
};
const _: () = assert!(MAX_ENTRIES <= 256, "a slot must fit a u8");

/// Values of its own an application stores beside the dictionary (one per position channel:
/// CiA 406's preset offset on a device without an offset object, TMI).
pub const APP_RECORDS: usize = 4;

/// Records a storage image holds besides the dictionary's and the application's: the
/// LSS-configured node-id and bit rate and the node-id of the save (D15).
pub const NODE_RECORDS: usize = 3;

/// Most records a storage image holds: 240 on a host (any device an EDS may describe), else
/// the dictionary's stored entries (`CANPOS_MAX_STORED`, at least 32, for a firmware's own
/// small dictionary) plus [`NODE_RECORDS`] and [`APP_RECORDS`].
pub const RECORDS_MAX: usize = if HOST_BUFFERS {
    240
} else {
    let stored = env_or(option_env!("CANPOS_MAX_STORED"), 32);
    (if stored > 32 { stored } else { 32 }) + NODE_RECORDS + APP_RECORDS
};

/// Capacity of the transmit queue, in frames (a power of two). On a host 64; a firmware's main
/// loop hands the frames to the controller's mailboxes after each frame it receives, so 8
/// hold what one frame sets off: at most a SYNC's four TPDOs, with a heartbeat or an EMCY due
/// at the same time, beyond what the mailboxes take.
pub const TXQ_LEN: usize = if HOST_BUFFERS { 64 } else { 8 };
const _: () = assert!(TXQ_LEN.is_power_of_two());

/// Capacity of the SDO server's transfer buffer: the largest value a segmented or block
/// transfer carries (larger ones are refused with 0x05040005, out of memory) and the longest
/// string an upload serves.
pub const SDO_BUF_LEN: usize = 64;

/// Depth of the pre-defined error field 0x1003 (a power of two: a ring).
pub const HISTORY_LEN: usize = 8;
/// Errors active at once (the error register's sources).
pub const EMCY_ACTIVE_LEN: usize = 8;
/// EMCY frames waiting for their inhibit time (a power of two: a ring).
pub const EMCY_PENDING_LEN: usize = 8;
const _: () = assert!(HISTORY_LEN.is_power_of_two() && EMCY_PENDING_LEN.is_power_of_two());

// --- RPDOs (issue 33) ----------------------------------------------------------------------

/// Most RPDOs a device has (0x1400… / 0x1600…): each costs its state in RAM (96 B on a
/// 64-bit host), in every node, sensors included. On a host (`host-buffers`) 4, as
/// [`MAX_TPDOS`]: CiA 301's pre-defined connection set and CiA 401's default mapping have four
/// of each, and a sensor node's state stays within its 4 KiB (eight would take it to 4.1 KiB).
/// The EDS device leaves RPDOs beyond them out with a warning naming the file and line.
/// Without it (firmware) `CANPOS_MAX_RPDOS`, else 4; 0 leaves the RPDO service out of the
/// build (a device without RPDOs, as the TH firmware: `firmware/.cargo/config.toml`).
pub const MAX_RPDOS: usize = if HOST_BUFFERS {
    4
} else {
    env_or(option_env!("CANPOS_MAX_RPDOS"), 4)
};
const _: () = assert!(MAX_RPDOS <= 512, "CiA 301 has 512 RPDOs");

/// The SYNC start value of synchronous TPDOs (0x1800:6, CiA 301), where a table declares it:
/// always on a host; a firmware whose table declares it sets `CANPOS_SYNC_START=1` (the TH's
/// does not: without it the 120 B of its code are left out, docs/FIRMWARE.md).
pub const SYNC_START: bool = HOST_BUFFERS || env_or(option_env!("CANPOS_SYNC_START"), 0) != 0;

/// `v` (a decimal number set at build time) or `default` when it is not set; a value that is
/// not a number stops the build.
const fn env_or(v: Option<&str>, default: usize) -> usize {
    let Some(s) = v else {
        return default;
    };
    let b = s.as_bytes();
    assert!(!b.is_empty(), "CANPOS_* size: empty");
    let mut n = 0usize;
    let mut i = 0;
    while i < b.len() {
        assert!(b[i].is_ascii_digit(), "CANPOS_* size: not a decimal number");
        n = n * 10 + (b[i] - b'0') as usize;
        i += 1;
    }
    n
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::env_or;

    #[test]
    fn a_build_size_is_a_decimal_number_or_the_default() {
        assert_eq!(env_or(None, 64), 64);
        assert_eq!(env_or(Some("186"), 64), 186);
        assert_eq!(env_or(Some("0"), 64), 0);
        assert!(std::panic::catch_unwind(|| env_or(Some("0x10"), 64)).is_err());
        assert!(std::panic::catch_unwind(|| env_or(Some(""), 64)).is_err());
    }
}
