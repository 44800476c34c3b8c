//! Temposonics TH CANbus (manual 551871 rev C, §5): the object dictionary of TH Tables 15–20.
//!
//! Where the manual is silent the SPEC decisions apply (D1 device type, D2 0x6000, D3 alarms,
//! D4 0x6507, D5 threshold cams, D7 store/restore, D18 velocity step, D19 0x2901/0x2101, D20
//! module identification). Additions the manual does not list: 0x1000 (mandatory), 0x1003 and
//! 0x1015 (EMCY history / inhibit, SPEC §6), sub 0 of the per-channel arrays, and mapping
//! sub-entries 4…8 (default 0) so a TPDO can carry eight 8-bit objects (conformance PDO-25).
//! TPDO inhibit time (0x180x/3) is not in TH Table 16, but its sub 0 reads 5 (highest
//! sub-index) and it is the CiA 301 object, so TH has it (default 0) like the E-Series.

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
    entry!(0x1008, 0, "Manufacturer device name", VisibleString, Const, Str(&"C304")),
    entry!(0x1009, 0, "Manufacturer hardware version", VisibleString, Const, Str(&"1.00")),
    entry!(0x100A, 0, "Manufacturer software version", VisibleString, Const, Str(&"1.01")),
    // Tracks the active node-id (Table 15 default 0x7F = the default node-id).
    entry!(0x100B, 0, "Node-ID", Unsigned32, Ro, Param(Param::NodeId)),
    entry!(0x100C, 0, "Guard time", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x100D, 0, "Life time factor", Unsigned8, Rw, Const(0), Any, Comm),
    entry!(0x100E, 0, "COB-ID guarding protocol", Unsigned32, Rw, NodeId(0x700), Any, Comm),
    entry!(0x100F, 0, "Number of SDOs supported", Unsigned32, Const, Const(1)),
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
    entry!(0x1018, 3, "Revision number", Unsigned32, Const, Const(0x0001_0005)),
    entry!(0x1018, 4, "Serial number", Unsigned32, Ro, Param(Param::SerialNumber)),
    // CiA 301 default SDO server parameters: the COB-IDs follow the node-id (conformance
    // SDO-12 reads them).
    entry!(0x1200, 0, "SDO server parameter: highest sub-index", Unsigned8, Const, Const(2)),
    entry!(0x1200, 1, "COB-ID client to server", Unsigned32, Ro, NodeId(0x600)),
    entry!(0x1200, 2, "COB-ID server to client", Unsigned32, Ro, NodeId(0x580)),
];

/// TH TPDO COB-IDs: TPDO1 valid with RTR allowed, the others not valid (Table 16).
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
const T1: ([Entry; 5], usize) = table::tpdo_comm(0x1800, tpdo_comm_names!(1), comm(0x180));
const T2: ([Entry; 5], usize) = table::tpdo_comm(0x1801, tpdo_comm_names!(2), comm(0x8000_0280));
const T3: ([Entry; 5], usize) = table::tpdo_comm(0x1802, tpdo_comm_names!(3), comm(0x8000_0380));
const T4: ([Entry; 5], usize) = table::tpdo_comm(0x1803, tpdo_comm_names!(4), comm(0x8000_0480));

/// Mapping n: position, velocity, cam state of channel n (Table 16; 0x1A03/3 lost in OCR,
/// completed by the pattern).
const fn map(n: u32) -> [u32; 8] {
    [
        0x6020_0020 | n << 8,
        0x6030_0010 | n << 8,
        0x6300_0008 | n << 8,
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
    // D19: stored by "save".
    entry!(0x2101, 0, "Enable bus termination", Boolean, Rw, Const(0), Any, App),
    entry!(0x2901, 0, "Temperature: number of objects", Unsigned8, Const, Const(5)),
    entry!(0x2901, 1, "Actual temperature", Integer8, Ro, Live),
    entry!(0x2901, 2, "Max. temperature since startup", Integer8, Ro, Live),
    entry!(0x2901, 3, "Min. temperature since startup", Integer8, Ro, Live),
    // D19: the operating-life extremes are persisted by the device itself.
    entry!(0x2901, 4, "Max. temperature over operational life", Integer8, Ro, Live, Any, Auto),
    entry!(0x2901, 5, "Min. temperature over operational life", Integer8, Ro, Live, Any, Auto),
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
    entry!(0x6506, 0, "Supported warnings", Unsigned16, Const, Const(0x0004)),
    // D4.
    entry!(0x6507, 0, "Profile and software version", Unsigned32, Const, Const(0x0301_0401)),
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
];

pub(crate) const N: usize = table::total(PARTS);
static TABLE: [Entry; N] = cia301::attach(table::concat(PARTS));
const _: () = assert!(
    table::fits_storage(&TABLE),
    "TH table: more stored entries than config::RECORDS_MAX holds (CANPOS_MAX_STORED)"
);
const _: () = assert!(
    cia301::hooks_complete(&TABLE),
    "TH table: a CiA 301 object without its hook"
);
static KEYS: [u32; N] = table::keys(&TABLE);
const _: () = assert!(
    table::valid(&TABLE),
    "TH table unsorted or larger than config::MAX_ENTRIES (CANPOS_MAX_ENTRIES)"
);

/// The TH's object dictionary.
pub static ENTRIES: &[Entry] = &TABLE;

/// 0x1018/2: "C304".
pub const PRODUCT_CODE: u32 = 0x4333_3034;

fn param(cfg: &DeviceConfig, p: Param) -> u32 {
    canpos_encoder::common_param(cfg, p, PRODUCT_CODE)
}

/// TH §8: 1 to 4 magnets, 2 µm or 5 µm, measurement cycle by stroke length.
fn derive(mut cfg: DeviceConfig) -> DeviceConfig {
    cfg.channels = cfg.channels.clamp(1, 4);
    cfg.position_step_nm = if cfg.position_step_nm <= 2000 {
        2000
    } else {
        5000
    };
    cfg.cycle_us = match cfg.stroke_mm {
        0..=2400 => 1000,
        2401..=4800 => 2000,
        _ => 4000,
    };
    cfg
}

/// The TH model.
pub static TH: Model = Model {
    table: Table {
        name: "th",
        product: "Temposonics TH CANbus",
        vendor: "MTS Sensor Technologie GmbH & Co. KG",
        entries: ENTRIES,
        keys: if config::INLINE_HOT_PATHS { &KEYS } else { &[] },
        features: Features {
            tag: 1,
            tpdos: 4,
            rpdos: 0,
            sdo_segmented: true,
            sdo_block: true,
            node_guarding: true,
            tpdo_rtr: true,
            lss_fastscan: true,
            lss_bit_timing: &[0, 1, 2, 3, 4, 6, 7],
            bitrates: &[1000, 800, 500, 250, 125, 50, 20],
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
        preset_clear: false,
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
        serial: 17_143_876,
        stroke_mm: 1000,
        position_step_nm: 5000,
        channels: 1,
        cycle_us: 1000,
    },
};
