//! Novotechnik TMI CANopen (instructions 517937/02, English chapter §1): the object dictionary
//! as far as the manual describes it (§1.2–§1.16; the vendor EDS `TMI_TLM_CANopen.eds` it
//! refers to is not available).
//!
//! One or two position channels, each configuration with its own dictionary ([`TMI`] and
//! [`TMI_TWO_CHANNELS`]; 002 §1.6 "a separate eds-file is provided for each configuration", the
//! one-channel unit has its channel-1 objects only), two TPDOs of at most five entries (§1.2.5, storage table), window
//! cams with high limits 0x632x and hysteresis 0x633x (D5), node-id 0x2000 / bit rate 0x2001
//! (D16), status 0x1002, store / restore with subs 1…3 (D7), writable measuring steps 0x6005
//! (R31). Storage groups follow the §1.16 table: objects it does not list (0x1005, 0x1014,
//! 0x6301 cam enable, …) are not stored. Product code and serial are Volatile here although
//! §1.16 marks them "Auto": the TMI re-derives them from the sensing element's system data at
//! every power-up (§1.14 0x5000/1/5), which is the unit configuration in canpos.
//!
//! Added from CiA 301 / 406 and the SPEC although the manual does not list them: 0x1000 (D1),
//! 0x1001, 0x1003, 0x1015, 0x6000 / 0x6500 (D2), 0x6503–0x6506 (D3, D13: the missing-magnet
//! alarm), 0x6507 (D4: 0x03010100).

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

/// [`Param::Model`] number of TPDO2's COB-ID (valid only on two-channel units, D21).
pub const PARAM_TPDO2_COB: u8 = 1;

/// Bit rates 0x2001 accepts (D16): kbit/s, or 0xFFFF = autobaud.
pub const BITRATES_2001: &[u32] = &[10, 20, 50, 125, 250, 500, 800, 1000, 0xFFFF];

#[rustfmt::skip]
const COMM_HEAD: &[Entry] = &[
    entry!(0x1000, 0, "Device type", Unsigned32, Ro, Param(Param::DeviceType)),
    // Not mappable: 002 §1.2.5 names the mappable objects (0x6020, 0x6030, 0x6300, 0x6400).
    entry!(0x1001, 0, "Error register", Unsigned8, Ro, Live),
    // §1.15: status bits, NMT state in bits 1–0.
    entry!(0x1002, 0, "Manufacturer status register", Unsigned32, Ro, Live).with_hook(Hook::app(hook::MANUFACTURER_STATUS)),
];

#[rustfmt::skip]
const COMM: &[Entry] = &[
    entry!(0x1005, 0, "COB-ID SYNC", Unsigned32, Rw, Const(0x80), Any, Volatile),
    // SPEC §1: the manual names no device; "TMI".
    entry!(0x1008, 0, "Manufacturer device name", VisibleString, Const, Str(&"TMI")),
    entry!(0x1010, 0, "Store parameters: highest sub-index", Unsigned8, Const, Const(3)),
    entry!(0x1010, 1, "Store all parameters", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1010, 2, "Store communication parameters", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1010, 3, "Store application parameters", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1011, 0, "Restore default parameters: highest sub-index", Unsigned8, Const, Const(3)),
    entry!(0x1011, 1, "Restore all default parameters", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1011, 2, "Restore communication default parameters", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1011, 3, "Restore application default parameters", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1014, 0, "COB-ID EMCY", Unsigned32, Rw, NodeId(0x80), Any, Volatile),
    entry!(0x1015, 0, "Inhibit time EMCY", Unsigned16, Rw, Const(0), Any, Volatile),
    entry!(0x1017, 0, "Producer heartbeat time", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1018, 0, "Identity object: number of entries", Unsigned8, Const, Const(4)),
    entry!(0x1018, 1, "Vendor-ID", Unsigned32, Const, Const(0x0000_0182)),
    entry!(0x1018, 2, "Product code", Unsigned32, Ro, Param(Param::ProductCode)),
    entry!(0x1018, 3, "Revision number", Unsigned32, Const, Const(0x0002_0003)),
    entry!(0x1018, 4, "Serial number", Unsigned32, Ro, Param(Param::SerialNumber)),
    // CiA 301 default SDO server parameters: the COB-IDs follow the node-id (conformance
    // SDO-12 reads them).
    entry!(0x1200, 0, "SDO server parameter: highest sub-index", Unsigned8, Const, Const(2)),
    entry!(0x1200, 1, "COB-ID client to server", Unsigned32, Ro, NodeId(0x600)),
    entry!(0x1200, 2, "COB-ID server to client", Unsigned32, Ro, NodeId(0x580)),
];

/// TPDO1: asynchronous with event timer (§1.2.5). The manual gives no event-timer default;
/// 1 ms as on the MTS sensors (R27 then reports it insufficient below 250 kbit/s with 8 bytes).
const T1: ([Entry; 5], usize) = table::tpdo_comm(
    0x1800,
    tpdo_comm_names!(1),
    TpdoComm {
        cob: NodeId(0x180),
        ttype: 0xFE,
        ttype_range: &Any,
        inhibit: true,
        event: Some(1),
        group: Comm,
    },
);
/// TPDO2: "synchronous; no RTR's" (§1.2.5): no event timer, types 0…240, COB-ID bit 30 set.
const T2: ([Entry; 5], usize) = table::tpdo_comm(
    0x1801,
    tpdo_comm_names!(2),
    TpdoComm {
        cob: Param(Param::Model(PARAM_TPDO2_COB)),
        ttype: 1,
        ttype_range: &MinMax(0, 240),
        inhibit: true,
        event: None,
        group: Comm,
    },
);

/// D21: position, velocity, cam state, work-area state of channel n (8 bytes).
const fn map(n: u32) -> [u32; 8] {
    [
        0x6020_0020 | n << 8,
        0x6030_0010 | n << 8,
        0x6300_0008 | n << 8,
        0x6400_0008 | n << 8,
        0,
        0,
        0,
        0,
    ]
}

#[rustfmt::skip]
const MFR: &[Entry] = &[
    // D16; "save" stores them, effective after reset communication / power-up.
    entry!(0x2000, 0, "Node-ID", Unsigned8, Rw, Param(Param::NodeId), MinMax(1, 127), App).with_hook(Hook::PendingNodeId),
    entry!(0x2001, 0, "CAN bit rate", Unsigned16, Rw, Param(Param::BitRateKbps), OneOf(BITRATES_2001), App).with_hook(Hook::PendingBitRate),
    // D2.
    entry!(0x6000, 0, "Operating parameters", Unsigned16, Rw, Const(0), Any, Volatile).with_hook(Hook::app(hook::CODE_SEQUENCE)),
    entry!(0x6005, 0, "Linear encoder measuring step settings: number of entries", Unsigned8, Const, Const(2)),
    // R31: 1 µm steps up to 100 µm, not below the variant's minimum (checked by the encoder).
    entry!(0x6005, 1, "Position measuring step", Unsigned32, Rw, Param(param::POSITION_STEP_NM), MinMax(1000, 100_000), App).with_hook(Hook::app(hook::MEASURING_STEP)),
    entry!(0x6005, 2, "Velocity measuring step", Unsigned32, Rw, Param(param::VELOCITY_STEP), OneOf(&[20, 50, 100, 250]), App),
];

#[rustfmt::skip]
const DIAG: &[Entry] = &[
    entry!(0x6500, 0, "Operating status", Unsigned16, Ro, Live).with_hook(Hook::app(hook::OPERATING_STATUS)),
    entry!(0x6503, 0, "Alarms", Unsigned16, Ro, Live),
    entry!(0x6504, 0, "Supported alarms", Unsigned16, Const, Const(0x0001)),
    entry!(0x6505, 0, "Warnings", Unsigned16, Ro, Live),
    entry!(0x6506, 0, "Supported warnings", Unsigned16, Const, Const(0x0000)),
    entry!(0x6507, 0, "Profile and software version", Unsigned32, Const, Const(0x0301_0100)),
];

/// The object parts of a unit with the channels `$n…` (`$ch` = sub 0 plus one per channel):
/// 002 §1.6 gives each configuration its own EDS, and the one-channel unit has its channel-1
/// objects only (§1.12: "Pos_ch1/Vel_ch1", one TPDO's worth).
macro_rules! parts {
    ($ch:literal, $map2:expr; $($n:literal),*) => {{
        const CH: usize = $ch;
        const P: &[&[Entry]] = &[
            COMM_HEAD,
            &table::ERROR_HISTORY,
            COMM,
            T1.0.split_at(T1.1).0,
            T2.0.split_at(T2.1).0,
            &table::tpdo_map::<6>(0x1A00, tpdo_map_names!(1), 4, map(1), Comm),
            &table::tpdo_map::<6>(0x1A01, tpdo_map_names!(2), $map2.0, $map2.1, Comm),
            MFR,
            &table::hooked(channels::<CH>(0x6010, chnames!("Preset value"; $($n),*), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::PRESET)),
            &channels::<CH>(0x6020, chnames!("Position value"; $($n),*), Integer32, Ro, true, Live, &Any, Volatile),
            &channels::<CH>(0x6030, chnames!("Speed value"; $($n),*), Integer16, Ro, true, Live, &Any, Volatile),
            &channels::<CH>(0x6300, chnames!("Cam state"; $($n),*), Unsigned8, Ro, true, Live, &Any, Volatile),
            // Not in the §1.16 storage list.
            &table::hooked(channels::<CH>(0x6301, chnames!("Cam enable"; $($n),*), Unsigned8, Rw, false, Const(0), &Any, Volatile), Hook::app(hook::CAM_SWITCH)),
            &table::hooked(channels::<CH>(0x6302, chnames!("Cam polarity"; $($n),*), Unsigned8, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_SWITCH)),
            &table::hooked(channels::<CH>(0x6310, chnames!("Cam1 low limit"; $($n),*), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6311, chnames!("Cam2 low limit"; $($n),*), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6312, chnames!("Cam3 low limit"; $($n),*), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6313, chnames!("Cam4 low limit"; $($n),*), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6320, chnames!("Cam1 high limit"; $($n),*), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6321, chnames!("Cam2 high limit"; $($n),*), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6322, chnames!("Cam3 high limit"; $($n),*), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6323, chnames!("Cam4 high limit"; $($n),*), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6330, chnames!("Cam1 hysteresis"; $($n),*), Unsigned16, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6331, chnames!("Cam2 hysteresis"; $($n),*), Unsigned16, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6332, chnames!("Cam3 hysteresis"; $($n),*), Unsigned16, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &table::hooked(channels::<CH>(0x6333, chnames!("Cam4 hysteresis"; $($n),*), Unsigned16, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
            &channels::<CH>(0x6400, chnames!("Work area state"; $($n),*), Unsigned8, Ro, true, Live, &Any, Volatile),
            &table::hooked(channels::<CH>(0x6401, chnames!("Work area low limit"; $($n),*), Integer32, Rw, false, Param(param::MIN_POSITION), &Any, App), Hook::app(hook::WORK_AREA_LIMIT)),
            &table::hooked(channels::<CH>(0x6402, chnames!("Work area high limit"; $($n),*), Integer32, Rw, false, Param(param::MAX_POSITION), &Any, App), Hook::app(hook::WORK_AREA_LIMIT)),
            DIAG,
        ];
        P
    }};
}

/// Two channels: TPDO2 carries channel 2 (D21).
#[rustfmt::skip]
const PARTS: &[&[Entry]] = parts!(3, (4, map(2)); 1, 2);
/// One channel: TPDO2 exists (§1.12 "2 TPDOs … are provided") but has no channel of its own:
/// invalid (D21) and empty until a user maps channel-1 objects into it.
#[rustfmt::skip]
const PARTS_ONE: &[&[Entry]] = parts!(2, (0, [0; 8]); 1);

/// Entries of the larger (two-channel) table: what a firmware's value array and storage image
/// are sized for.
pub(crate) const N: usize = table::total(PARTS);
static TABLE_TWO: [Entry; N] = cia301::attach(table::concat(PARTS));
const _: () = assert!(
    table::fits_storage(&TABLE_TWO),
    "TMI table: more stored entries than config::RECORDS_MAX holds (CANPOS_MAX_STORED)"
);
const _: () = assert!(
    cia301::hooks_complete(&TABLE_TWO),
    "TMI table: a CiA 301 object without its hook"
);
static KEYS_TWO: [u32; N] = table::keys(&TABLE_TWO);
const _: () = assert!(
    table::valid(&TABLE_TWO),
    "TMI table unsorted or larger than config::MAX_ENTRIES (CANPOS_MAX_ENTRIES)"
);

const N_ONE: usize = table::total(PARTS_ONE);
static TABLE: [Entry; N_ONE] = cia301::attach(table::concat(PARTS_ONE));
const _: () = assert!(
    table::fits_storage(&TABLE),
    "TMI table: more stored entries than config::RECORDS_MAX holds (CANPOS_MAX_STORED)"
);
const _: () = assert!(
    cia301::hooks_complete(&TABLE),
    "TMI table: a CiA 301 object without its hook"
);
static KEYS: [u32; N_ONE] = table::keys(&TABLE);
const _: () = assert!(
    table::valid(&TABLE),
    "one-channel TMI table unsorted or larger than config::MAX_ENTRIES (CANPOS_MAX_ENTRIES)"
);

/// The one-channel TMI's object dictionary: channel-1 objects only (002 §1.6, §1.12).
pub static ENTRIES: &[Entry] = &TABLE;
/// The two-channel TMI's object dictionary.
pub static ENTRIES_TWO_CHANNELS: &[Entry] = &TABLE_TWO;

/// §1.8: bit 31 two channels, bit 30 5 µm minimum step, bits 16…0 length in mm.
pub fn product_code(cfg: &DeviceConfig) -> u32 {
    let mut code = cfg.stroke_mm & 0x1_FFFF;
    if cfg.channels > 1 {
        code |= 1 << 31;
    }
    if cfg.position_step_nm >= 5000 {
        code |= 1 << 30;
    }
    code
}

fn param(cfg: &DeviceConfig, p: Param) -> u32 {
    match p {
        Param::ProductCode => product_code(cfg),
        // D18: 2.5 mm/s by default, not derived from the resolution.
        param::VELOCITY_STEP => 250,
        // D16: 0xFFFF is autobaud (0 in the configuration).
        Param::BitRateKbps if cfg.bitrate_kbps == 0 => 0xFFFF,
        Param::Model(PARAM_TPDO2_COB) => {
            let base = 0x4000_0280 + cfg.node_id as u32;
            if cfg.channels > 1 {
                base
            } else {
                base | 0x8000_0000
            }
        }
        _ => canpos_encoder::common_param(cfg, p, 0),
    }
}

/// §1.6 / §1.7: one or two channels, minimum step 1 µm or 5 µm; cycle not stated (1 ms).
fn derive(mut cfg: DeviceConfig) -> DeviceConfig {
    cfg.channels = cfg.channels.clamp(1, 2);
    cfg.position_step_nm = if cfg.position_step_nm >= 5000 {
        5000
    } else {
        1000
    };
    cfg.stroke_mm = cfg.stroke_mm.min(0x1_FFFF);
    cfg.cycle_us = 1000;
    cfg
}

/// The TMI's behaviour switches (both configurations).
const SWITCHES: Switches = Switches {
    preset_clear: false,
    preset_offset_internal: true,
    tmi_error_reactions: true,
    window_cams: true,
};

const FEATURES: Features = Features {
    tag: 3,
    tpdos: 2,
    rpdos: 0,
    sdo_segmented: false,
    sdo_block: false,
    node_guarding: false,
    tpdo_rtr: true,
    lss_fastscan: false,
    lss_bit_timing: &[0, 1, 2, 3, 4, 6, 7, 8],
    bitrates: &[1000, 800, 500, 250, 125, 50, 20, 10],
    store_preop_only: true,
    kill_signature: true,
    power_on_emcy: false,
    sync_length_emcy: false,
    emcy_on_register_change: false,
    event_timer_above_inhibit: true,
    lss_unconfigured_configures: true,
};

/// The manual's example unit.
const DEFAULT_CONFIG: DeviceConfig = DeviceConfig {
    node_id: 127,
    bitrate_kbps: 250,
    // A label serial in the manual's YYWWxxxx form (2009, week 05), read as decimal (G29).
    serial: 9_050_001,
    stroke_mm: 500,
    position_step_nm: 1000,
    channels: 1,
    cycle_us: 1000,
};

/// The TMI model as the manual's example unit has it: one channel (order-code interface `61x`),
/// channel-1 objects only. A node or EDS of a two-channel unit ([`DeviceConfig::channels`] 2,
/// `62x`) uses [`TMI_TWO_CHANNELS`] instead ([`crate::for_unit`]): 002 §1.6 provides "a
/// separate eds-file … for each configuration".
pub static TMI: Model = Model {
    table: Table {
        name: "tmi",
        product: "Novotechnik TMI CANopen",
        vendor: "Novotechnik Messwertaufnehmer OHG",
        entries: ENTRIES,
        keys: if config::INLINE_HOT_PATHS { &KEYS } else { &[] },
        features: FEATURES,
    },
    profile: SWITCHES,
    variant: Some(unit),
    param,
    derive,
    default_config: DEFAULT_CONFIG,
};

/// The two-channel TMI: the same unit with the objects of both channels.
pub static TMI_TWO_CHANNELS: Model = Model {
    table: Table {
        name: "tmi",
        product: "Novotechnik TMI CANopen",
        vendor: "Novotechnik Messwertaufnehmer OHG",
        entries: ENTRIES_TWO_CHANNELS,
        keys: if config::INLINE_HOT_PATHS {
            &KEYS_TWO
        } else {
            &[]
        },
        features: FEATURES,
    },
    profile: SWITCHES,
    variant: Some(unit),
    param,
    derive,
    default_config: DEFAULT_CONFIG.with_channels(2),
};

/// The TMI dictionary of a unit configured as `cfg`: the one-channel unit has its own, with
/// channel-1 objects only (002 §1.6: a separate EDS per configuration).
fn unit(cfg: &DeviceConfig) -> &'static Model {
    if cfg.channels <= 1 {
        &TMI
    } else {
        &TMI_TWO_CHANNELS
    }
}
