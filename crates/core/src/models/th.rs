//! Temposonics TH CANbus (manual 551871 rev C, §5): the object dictionary of TH Tables 15–20.

use super::{DeviceConfig, Features, Model};
use crate::entry;
use crate::od::{Default::*, Entry, Param};

/// The TH's object dictionary.
pub static ENTRIES: &[Entry] = &[
    entry!(
        0x1000,
        0,
        "Device type",
        Unsigned32,
        Ro,
        Param(Param::DeviceType)
    ),
    entry!(0x1001, 0, "Error register", Unsigned8, Ro, Live),
    entry!(
        0x1003,
        0,
        "Pre-defined error field: number of errors",
        Unsigned8,
        Rw,
        Const(0),
        MinMax(0, 0),
        Volatile
    ),
    entry!(0x1003, 1, "Standard error field 1", Unsigned32, Ro, Live),
    entry!(0x1003, 2, "Standard error field 2", Unsigned32, Ro, Live),
    entry!(0x1003, 3, "Standard error field 3", Unsigned32, Ro, Live),
    entry!(0x1003, 4, "Standard error field 4", Unsigned32, Ro, Live),
    entry!(0x1003, 5, "Standard error field 5", Unsigned32, Ro, Live),
    entry!(0x1003, 6, "Standard error field 6", Unsigned32, Ro, Live),
    entry!(0x1003, 7, "Standard error field 7", Unsigned32, Ro, Live),
    entry!(0x1003, 8, "Standard error field 8", Unsigned32, Ro, Live),
    entry!(
        0x1005,
        0,
        "COB-ID SYNC",
        Unsigned32,
        Rw,
        Const(0x80),
        Any,
        Comm
    ),
    entry!(
        0x1008,
        0,
        "Manufacturer device name",
        VisibleString,
        Const,
        Str("C304")
    ),
    entry!(
        0x1009,
        0,
        "Manufacturer hardware version",
        VisibleString,
        Const,
        Str("1.00")
    ),
    entry!(
        0x100A,
        0,
        "Manufacturer software version",
        VisibleString,
        Const,
        Str("1.01")
    ),
    entry!(0x100B, 0, "Node-ID", Unsigned32, Ro, Param(Param::NodeId)),
    entry!(0x100C, 0, "Guard time", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(
        0x100D,
        0,
        "Life time factor",
        Unsigned8,
        Rw,
        Const(0),
        Any,
        Comm
    ),
    entry!(
        0x100E,
        0,
        "COB-ID guarding protocol",
        Unsigned32,
        Ro,
        NodeId(0x700)
    ),
    entry!(
        0x100F,
        0,
        "Number of SDOs supported",
        Unsigned32,
        Const,
        Const(1)
    ),
    entry!(
        0x1010,
        0,
        "Store parameters: highest sub-index",
        Unsigned8,
        Const,
        Const(1)
    ),
    entry!(
        0x1010,
        1,
        "Store all parameters",
        Unsigned32,
        Rw,
        Const(1),
        Any,
        Volatile
    ),
    entry!(
        0x1011,
        0,
        "Restore default parameters: highest sub-index",
        Unsigned8,
        Const,
        Const(1)
    ),
    entry!(
        0x1011,
        1,
        "Restore all default parameters",
        Unsigned32,
        Rw,
        Const(1),
        Any,
        Volatile
    ),
    entry!(
        0x1014,
        0,
        "COB-ID EMCY",
        Unsigned32,
        Rw,
        NodeId(0x80),
        Any,
        Comm
    ),
    entry!(
        0x1015,
        0,
        "Inhibit time EMCY",
        Unsigned16,
        Rw,
        Const(0),
        Any,
        Comm
    ),
    entry!(
        0x1017,
        0,
        "Producer heartbeat time",
        Unsigned16,
        Rw,
        Const(0),
        Any,
        Comm
    ),
    entry!(
        0x1018,
        0,
        "Identity object: number of entries",
        Unsigned8,
        Const,
        Const(4)
    ),
    entry!(0x1018, 1, "Vendor-ID", Unsigned32, Ro, Const(0x0000_0040)),
    entry!(
        0x1018,
        2,
        "Product code",
        Unsigned32,
        Ro,
        Param(Param::ProductCode)
    ),
    entry!(
        0x1018,
        3,
        "Revision number",
        Unsigned32,
        Ro,
        Const(0x0001_0005)
    ),
    entry!(
        0x1018,
        4,
        "Serial number",
        Unsigned32,
        Ro,
        Param(Param::SerialNumber)
    ),
    entry!(
        0x1800,
        0,
        "TPDO1 communication parameter: highest sub-index",
        Unsigned8,
        Const,
        Const(5)
    ),
    entry!(
        0x1800,
        1,
        "TPDO1 COB-ID",
        Unsigned32,
        Rw,
        NodeId(0x180),
        Any,
        Comm
    ),
    entry!(
        0x1800,
        2,
        "TPDO1 transmission type",
        Unsigned8,
        Rw,
        Const(0xFE),
        Any,
        Comm
    ),
    entry!(
        0x1800,
        3,
        "TPDO1 inhibit time",
        Unsigned16,
        Rw,
        Const(0),
        Any,
        Comm
    ),
    entry!(
        0x1800,
        5,
        "TPDO1 event timer",
        Unsigned16,
        Rw,
        Const(1),
        Any,
        Comm
    ),
    entry!(
        0x1801,
        0,
        "TPDO2 communication parameter: highest sub-index",
        Unsigned8,
        Const,
        Const(5)
    ),
    entry!(
        0x1801,
        1,
        "TPDO2 COB-ID",
        Unsigned32,
        Rw,
        NodeId(0x8000_0280),
        Any,
        Comm
    ),
    entry!(
        0x1801,
        2,
        "TPDO2 transmission type",
        Unsigned8,
        Rw,
        Const(0xFE),
        Any,
        Comm
    ),
    entry!(
        0x1801,
        3,
        "TPDO2 inhibit time",
        Unsigned16,
        Rw,
        Const(0),
        Any,
        Comm
    ),
    entry!(
        0x1801,
        5,
        "TPDO2 event timer",
        Unsigned16,
        Rw,
        Const(1),
        Any,
        Comm
    ),
    entry!(
        0x1802,
        0,
        "TPDO3 communication parameter: highest sub-index",
        Unsigned8,
        Const,
        Const(5)
    ),
    entry!(
        0x1802,
        1,
        "TPDO3 COB-ID",
        Unsigned32,
        Rw,
        NodeId(0x8000_0380),
        Any,
        Comm
    ),
    entry!(
        0x1802,
        2,
        "TPDO3 transmission type",
        Unsigned8,
        Rw,
        Const(0xFE),
        Any,
        Comm
    ),
    entry!(
        0x1802,
        3,
        "TPDO3 inhibit time",
        Unsigned16,
        Rw,
        Const(0),
        Any,
        Comm
    ),
    entry!(
        0x1802,
        5,
        "TPDO3 event timer",
        Unsigned16,
        Rw,
        Const(1),
        Any,
        Comm
    ),
    entry!(
        0x1803,
        0,
        "TPDO4 communication parameter: highest sub-index",
        Unsigned8,
        Const,
        Const(5)
    ),
    entry!(
        0x1803,
        1,
        "TPDO4 COB-ID",
        Unsigned32,
        Rw,
        NodeId(0x8000_0480),
        Any,
        Comm
    ),
    entry!(
        0x1803,
        2,
        "TPDO4 transmission type",
        Unsigned8,
        Rw,
        Const(0xFE),
        Any,
        Comm
    ),
    entry!(
        0x1803,
        3,
        "TPDO4 inhibit time",
        Unsigned16,
        Rw,
        Const(0),
        Any,
        Comm
    ),
    entry!(
        0x1803,
        5,
        "TPDO4 event timer",
        Unsigned16,
        Rw,
        Const(1),
        Any,
        Comm
    ),
    entry!(
        0x1A00,
        0,
        "TPDO1 mapping: number of entries",
        Unsigned8,
        Rw,
        Const(3),
        MinMax(0, 8),
        Comm
    ),
    entry!(
        0x1A00,
        1,
        "TPDO1 mapping entry 1",
        Unsigned32,
        Rw,
        Const(0x6020_0120),
        Any,
        Comm
    ),
    entry!(
        0x1A00,
        2,
        "TPDO1 mapping entry 2",
        Unsigned32,
        Rw,
        Const(0x6030_0110),
        Any,
        Comm
    ),
    entry!(
        0x1A00,
        3,
        "TPDO1 mapping entry 3",
        Unsigned32,
        Rw,
        Const(0x6300_0108),
        Any,
        Comm
    ),
    entry!(
        0x1A01,
        0,
        "TPDO2 mapping: number of entries",
        Unsigned8,
        Rw,
        Const(3),
        MinMax(0, 8),
        Comm
    ),
    entry!(
        0x1A01,
        1,
        "TPDO2 mapping entry 1",
        Unsigned32,
        Rw,
        Const(0x6020_0220),
        Any,
        Comm
    ),
    entry!(
        0x1A01,
        2,
        "TPDO2 mapping entry 2",
        Unsigned32,
        Rw,
        Const(0x6030_0210),
        Any,
        Comm
    ),
    entry!(
        0x1A01,
        3,
        "TPDO2 mapping entry 3",
        Unsigned32,
        Rw,
        Const(0x6300_0208),
        Any,
        Comm
    ),
    entry!(
        0x1A02,
        0,
        "TPDO3 mapping: number of entries",
        Unsigned8,
        Rw,
        Const(0),
        MinMax(0, 8),
        Comm
    ),
    entry!(
        0x1A02,
        1,
        "TPDO3 mapping entry 1",
        Unsigned32,
        Rw,
        Const(0x6020_0320),
        Any,
        Comm
    ),
    entry!(
        0x1A02,
        2,
        "TPDO3 mapping entry 2",
        Unsigned32,
        Rw,
        Const(0x6030_0310),
        Any,
        Comm
    ),
    entry!(
        0x1A02,
        3,
        "TPDO3 mapping entry 3",
        Unsigned32,
        Rw,
        Const(0x6300_0308),
        Any,
        Comm
    ),
    entry!(
        0x1A03,
        0,
        "TPDO4 mapping: number of entries",
        Unsigned8,
        Rw,
        Const(0),
        MinMax(0, 8),
        Comm
    ),
    entry!(
        0x1A03,
        1,
        "TPDO4 mapping entry 1",
        Unsigned32,
        Rw,
        Const(0x6020_0420),
        Any,
        Comm
    ),
    entry!(
        0x1A03,
        2,
        "TPDO4 mapping entry 2",
        Unsigned32,
        Rw,
        Const(0x6030_0410),
        Any,
        Comm
    ),
    entry!(
        0x1A03,
        3,
        "TPDO4 mapping entry 3",
        Unsigned32,
        Rw,
        Const(0x6300_0408),
        Any,
        Comm
    ),
    entry!(
        0x6020,
        0,
        "Position value: number of channels",
        Unsigned8,
        Const,
        Const(4)
    ),
    entry!(
        0x6020,
        1,
        "Position value channel 1",
        Integer32,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6020,
        2,
        "Position value channel 2",
        Integer32,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6020,
        3,
        "Position value channel 3",
        Integer32,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6020,
        4,
        "Position value channel 4",
        Integer32,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6030,
        0,
        "Speed value: number of channels",
        Unsigned8,
        Const,
        Const(4)
    ),
    entry!(
        0x6030,
        1,
        "Speed value channel 1",
        Integer16,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6030,
        2,
        "Speed value channel 2",
        Integer16,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6030,
        3,
        "Speed value channel 3",
        Integer16,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6030,
        4,
        "Speed value channel 4",
        Integer16,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6300,
        0,
        "Cam state register: number of channels",
        Unsigned8,
        Const,
        Const(4)
    ),
    entry!(
        0x6300,
        1,
        "Cam state channel 1",
        Unsigned8,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6300,
        2,
        "Cam state channel 2",
        Unsigned8,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6300,
        3,
        "Cam state channel 3",
        Unsigned8,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6300,
        4,
        "Cam state channel 4",
        Unsigned8,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6400,
        0,
        "Work area state: number of channels",
        Unsigned8,
        Const,
        Const(4)
    ),
    entry!(
        0x6400,
        1,
        "Work area state channel 1",
        Unsigned8,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6400,
        2,
        "Work area state channel 2",
        Unsigned8,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6400,
        3,
        "Work area state channel 3",
        Unsigned8,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
    entry!(
        0x6400,
        4,
        "Work area state channel 4",
        Unsigned8,
        Ro,
        Live,
        Any,
        Volatile,
        true
    ),
];

fn param(cfg: &DeviceConfig, p: Param) -> u32 {
    super::common_param(cfg, p, 0x4333_3034)
}

/// The TH model.
pub static TH: Model = Model {
    name: "th",
    product: "Temposonics TH CANbus",
    entries: ENTRIES,
    features: Features {
        tag: 1,
        tpdos: 4,
        sdo_segmented: true,
        sdo_block: true,
        node_guarding: true,
        tpdo_rtr: true,
        lss_fastscan: true,
        lss_bit_timing: &[0, 1, 2, 3, 4, 6, 7],
        store_preop_only: false,
        kill_signature: false,
        preset_clear: false,
        tmi_emcy: false,
        window_cams: false,
    },
    param,
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
