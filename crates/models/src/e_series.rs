//! Temposonics E-Series EP/EL/EH CANopen (manual 551774 rev A, §5.6): the object dictionary
//! of E-Series Tables 13–19.
//!
//! Differences from the TH: no 0x100B/0x100E/0x100F, no 0x2101/0x2901 (bus termination is a
//! hardware option), TPDOs with inhibit time and COB-IDs with bit 30 set (no RTR), default
//! mappings carry the work-area state 0x6400 instead of the cam state, 0x6506 = 0x7000, and
//! 0x6508 / 0x6509 / 0x650E exist. Identity per Table 14 (D17). SPEC decisions as for the TH
//! (D1–D5, D7, D18, D20); additions the manual does not list: 0x1000, 0x1003, 0x1015, sub 0 of
//! the per-channel arrays, mapping sub-entries 4…8 (default 0).

use crate::table::{self, channels, chnames, tpdo_comm_names, tpdo_map_names, TpdoComm};
use canpos_encoder::hook;
use canpos_encoder::{param, DeviceConfig, Model, Switches};
use canpos_stack::config;
use canpos_stack::entry;
use canpos_stack::model::{Features, Table};
use canpos_stack::od::{
    cia301,
    Access::{Ro, Rw},
    DataType::*,
    DefaultValue::*,
    Entry,
    Group::*,
    Hook, Param,
    Range::*,
};

#[rustfmt::skip]
const COMM_HEAD: &[Entry] = &[
    entry!(0x1000, 0, "Device type", Unsigned32, Ro, Param(Param::DeviceType)),
    // Mappable so eight copies fill a TPDO (conformance PDO-25 / PDO-30).
    entry!(0x1001, 0, "Error register", Unsigned8, Ro, Live, Any, Volatile, true),
];

#[rustfmt::skip]
const COMM: &[Entry] = &[
    entry!(0x1005, 0, "COB-ID SYNC", Unsigned32, Rw, Const(0x80), Any, Comm),
    entry!(0x1008, 0, "Manufacturer device name", VisibleString, Const, Str(&"MTS")),
    entry!(0x1009, 0, "Manufacturer hardware version", VisibleString, Const, Str(&"1.00")),
    entry!(0x100A, 0, "Manufacturer software version", VisibleString, Const, Str(&"1.04")),
    entry!(0x100C, 0, "Guard time", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x100D, 0, "Life time factor", Unsigned8, Rw, Const(0), Any, Comm),
    entry!(0x1010, 0, "Store parameters: highest sub-index", Unsigned8, Const, Const(1)),
    entry!(0x1010, 1, "Store all parameters", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1011, 0, "Restore default parameters: highest sub-index", Unsigned8, Const, Const(1)),
    entry!(0x1011, 1, "Restore all default parameters", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1014, 0, "COB-ID EMCY", Unsigned32, Rw, NodeId(0x80), Any, Comm),
    entry!(0x1015, 0, "Inhibit time EMCY", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1017, 0, "Producer heartbeat time", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1018, 0, "Identity object: number of entries", Unsigned8, Const, Const(4)),
    entry!(0x1018, 1, "Vendor-ID", Unsigned32, Const, Const(0x0000_0040)),
    entry!(0x1018, 2, "Product code", Unsigned32, Const, Const(PRODUCT_CODE)),
    entry!(0x1018, 3, "Revision number", Unsigned32, Const, Const(0x0309_0001)),
    entry!(0x1018, 4, "Serial number", Unsigned32, Ro, Param(Param::SerialNumber)),
    // CiA 301 default SDO server parameters: the COB-IDs follow the node-id (conformance
    // SDO-12 reads them).
    entry!(0x1200, 0, "SDO server parameter: highest sub-index", Unsigned8, Const, Const(2)),
    entry!(0x1200, 1, "COB-ID client to server", Unsigned32, Ro, NodeId(0x600)),
    entry!(0x1200, 2, "COB-ID server to client", Unsigned32, Ro, NodeId(0x580)),
];

/// E-Series TPDO COB-IDs: bit 30 set (no RTR); TPDO1 valid, the others not (Table 16).
const fn comm(cob: u32) -> TpdoComm {
    TpdoComm {
        cob: NodeId(cob),
        ttype: 0xFE,
        ttype_range: &Any,
        inhibit: true,
        event: Some(1),
        group: Comm,
    }
}
const T1: ([Entry; 5], usize) = table::tpdo_comm(0x1800, tpdo_comm_names!(1), comm(0x4000_0180));
const T2: ([Entry; 5], usize) = table::tpdo_comm(0x1801, tpdo_comm_names!(2), comm(0xC000_0280));
const T3: ([Entry; 5], usize) = table::tpdo_comm(0x1802, tpdo_comm_names!(3), comm(0xC000_0380));
const T4: ([Entry; 5], usize) = table::tpdo_comm(0x1803, tpdo_comm_names!(4), comm(0xC000_0480));

/// Mapping n: position, velocity, work-area state of channel n (Table 16).
const fn map(n: u32) -> [u32; 8] {
    [
        0x6020_0020 | n << 8,
        0x6030_0010 | n << 8,
        0x6400_0008 | n << 8,
        0,
        0,
        0,
        0,
        0,
    ]
}

const CH: usize = 5;

#[rustfmt::skip]
const MFR: &[Entry] = &[
    // D2: only bit 0 (code sequence); the encoder refuses other bits with 0x06090030.
    entry!(0x6000, 0, "Operating parameters", Unsigned16, Rw, Const(0), Any, App).with_hook(Hook::app(hook::CODE_SEQUENCE)),
    // D20: stored, no effect (scaling is fixed).
    entry!(0x6002, 0, "Total measuring range", Unsigned32, Rw, Const(0), Any, App),
    entry!(0x6005, 0, "Linear encoder measuring step settings: number of entries", Unsigned8, Const, Const(2)),
    entry!(0x6005, 1, "Position measuring step", Unsigned32, Ro, Param(param::POSITION_STEP_NM)).with_hook(Hook::app(hook::MEASURING_STEP)),
    entry!(0x6005, 2, "Velocity measuring step", Unsigned32, Ro, Param(param::VELOCITY_STEP)),
];

#[rustfmt::skip]
const STATUS: &[Entry] = &[
    // D12: one value with 0x1800/5 (node.rs keeps them equal).
    entry!(0x6200, 0, "Cyclic timer", Unsigned16, Rw, Const(1), Any, App).with_hook(Hook::app(hook::CYCLIC_TIMER)),
];

#[rustfmt::skip]
const DIAG: &[Entry] = &[
    // D2: reads the active 0x6000.
    entry!(0x6500, 0, "Operating status", Unsigned16, Ro, Live).with_hook(Hook::app(hook::OPERATING_STATUS)),
    entry!(0x6501, 0, "Measuring step", Unsigned32, Ro, Param(param::POSITION_STEP_NM)),
    // D3: bit 0 = position error (missing magnet); live, so no default in the EDS.
    // Table 17: default 0x0000; the application sets bit 0 while a magnet is missing (D13).
    entry!(0x6503, 0, "Alarms", Unsigned16, Ro, Const(0)),
    entry!(0x6504, 0, "Supported alarms", Unsigned16, Const, Const(0x0001)),
    entry!(0x6505, 0, "Warnings", Unsigned16, Ro, Const(0)),
    entry!(0x6506, 0, "Supported warnings", Unsigned16, Const, Const(0x7000)),
    // D4 (Table 17 gives no value).
    entry!(0x6507, 0, "Profile and software version", Unsigned32, Const, Const(0x0301_0100)),
    entry!(0x6508, 0, "Operating time", Unsigned32, Const, Const(0xFFFF_FFFF)),
    // The offset the channel 1 preset produced (mirrors 0x650C/1).
    entry!(0x6509, 0, "Offset value", Integer32, Ro, Live).with_hook(Hook::app(hook::OFFSET)),
    entry!(0x650A, 0, "Module identification: number of entries", Unsigned8, Const, Const(3)),
    entry!(0x650A, 1, "Manufacturer offset value", Integer32, Const, Const(0)),
    entry!(0x650A, 2, "Manufacturer min. position value", Integer32, Ro, Param(param::MIN_POSITION)),
    entry!(0x650A, 3, "Manufacturer max. position value", Integer32, Ro, Param(param::MAX_POSITION)),
    entry!(0x650B, 0, "Serial number", Unsigned32, Ro, Param(Param::SerialNumber)),
];

#[rustfmt::skip]
const PARTS: &[&[Entry]] = &[
    COMM_HEAD,
    &table::ERROR_HISTORY,
    COMM,
    T1.0.split_at(T1.1).0,
    T2.0.split_at(T2.1).0,
    T3.0.split_at(T3.1).0,
    T4.0.split_at(T4.1).0,
    &table::tpdo_map::<9>(0x1A00, tpdo_map_names!(1), 3, map(1), Comm),
    &table::tpdo_map::<9>(0x1A01, tpdo_map_names!(2), 3, map(2), Comm),
    &table::tpdo_map::<9>(0x1A02, tpdo_map_names!(3), 0, map(3), Comm),
    &table::tpdo_map::<9>(0x1A03, tpdo_map_names!(4), 0, map(4), Comm),
    MFR,
    &table::hooked(channels::<CH>(0x6010, chnames!("Preset value"; 1, 2, 3, 4), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::PRESET)),
    &channels::<CH>(0x6020, chnames!("Position value"; 1, 2, 3, 4), Integer32, Ro, true, Live, &Any, Volatile),
    &channels::<CH>(0x6030, chnames!("Speed value"; 1, 2, 3, 4), Integer16, Ro, true, Live, &Any, Volatile),
    STATUS,
    &table::THRESHOLD_CAMS_AND_WORK_AREAS,
    DIAG,
    // The offsets the presets produced (CiA 406), stored with "save" so a preset survives a
    // power cycle; "load" returns them to 0.
    &channels::<CH>(0x650C, chnames!("Offset value for multi-sensor devices"; 1, 2, 3, 4), Integer32, Ro, false, Const(0), &Any, App),
    // D4 / G7: no public definition; reads 0.
    &[entry!(0x650E, 0, "Device capability", Unsigned32, Const, Const(0))],
];

pub(crate) const N: usize = table::total(PARTS);
static TABLE: [Entry; N] = cia301::attach(table::concat(PARTS));
const _: () = assert!(
    table::fits_storage(&TABLE),
    "E-Series table: more stored entries than config::RECORDS_MAX holds (CANPOS_MAX_STORED)"
);
const _: () = assert!(
    cia301::hooks_complete(&TABLE),
    "E-Series table: a CiA 301 object without its hook"
);
static KEYS: [u32; N] = table::keys(&TABLE);
const _: () = assert!(
    table::valid(&TABLE),
    "E-Series table unsorted or larger than config::MAX_ENTRIES (CANPOS_MAX_ENTRIES)"
);

/// The E-Series' object dictionary.
pub static ENTRIES: &[Entry] = &TABLE;

/// 0x1018/2 per Table 14 (D17; §5.2 says 0x43333034, copied from the TH).
pub const PRODUCT_CODE: u32 = 0x0000_000E;

fn param(cfg: &DeviceConfig, p: Param) -> u32 {
    canpos_encoder::common_param(cfg, p, PRODUCT_CODE)
}

/// E-Series §8: 1 or 2 magnets (Z02), 10 µm or 20 µm, 1 ms cycle.
fn derive(mut cfg: DeviceConfig) -> DeviceConfig {
    cfg.channels = cfg.channels.clamp(1, 2);
    cfg.position_step_nm = if cfg.position_step_nm <= 10_000 {
        10_000
    } else {
        20_000
    };
    cfg.cycle_us = 1000;
    cfg
}

/// The E-Series model.
pub static E_SERIES: Model = Model {
    table: Table {
        name: "e-series",
        product: "Temposonics E-Series CANopen",
        vendor: "MTS Sensor Technologie GmbH & Co. KG",
        entries: ENTRIES,
        keys: if config::INLINE_HOT_PATHS { &KEYS } else { &[] },
        features: Features {
            tag: 2,
            tpdos: 4,
            rpdos: 0,
            sdo_segmented: true,
            sdo_block: true,
            node_guarding: true,
            tpdo_rtr: true,
            lss_fastscan: true,
            lss_bit_timing: &[0, 1, 2, 3, 4],
            bitrates: &[1000, 800, 500, 250, 125],
            store_preop_only: false,
            kill_signature: false,
            power_on_emcy: true,
            sync_length_emcy: true,
            emcy_on_register_change: true,
            event_timer_above_inhibit: false,
            lss_unconfigured_configures: false,
        },
    },
    profile: Switches {
        preset_clear: true,
        preset_offset_internal: false,
        tmi_error_reactions: false,
        window_cams: false,
    },
    variant: None,
    param,
    derive,
    default_config: DeviceConfig {
        node_id: 127,
        bitrate_kbps: 125,
        // Table 14's example serial 09501234.
        serial: 9_501_234,
        stroke_mm: 1000,
        position_step_nm: 10_000,
        channels: 1,
        cycle_us: 1000,
    },
};
