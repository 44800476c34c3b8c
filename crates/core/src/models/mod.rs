//! The product models: each one's object dictionary as a table, plus the few switches that
//! select behaviour the manuals describe differently (TMI refuses segmented SDO, has no node
//! guarding, stores only in pre-operational, …).

use crate::od::{Entry, Param};

pub mod th;

/// Behaviour switches of a product model that are not properties of single objects.
#[derive(Clone, Copy, Debug)]
pub struct Features {
    /// Tag written into storage images so one model never loads another's.
    pub tag: u8,
    /// Number of TPDOs (0x1800… / 0x1A00…).
    pub tpdos: u8,
    /// SDO segmented transfer supported (TMI: no → abort 0x05040001).
    pub sdo_segmented: bool,
    /// SDO block transfer supported.
    pub sdo_block: bool,
    /// Node guarding supported (TMI: no).
    pub node_guarding: bool,
    /// TPDOs may be requested by RTR (when COB-ID bit 30 is clear).
    pub tpdo_rtr: bool,
    /// LSS fastscan supported (DS 305 V2).
    pub lss_fastscan: bool,
    /// LSS bit-timing table-0 indices the model accepts (D9).
    pub lss_bit_timing: &'static [u8],
    /// Storing (0x1010) only allowed in pre-operational (TMI).
    pub store_preop_only: bool,
    /// 0x1010 accepts the "kill" signature (TMI).
    pub kill_signature: bool,
    /// E-Series: writing 0xFFFFFFFF to a preset clears it.
    pub preset_clear: bool,
    /// TMI-style EMCY table and reactions (0x9080 / 0x9090 on cam / work-area changes, 0x5000
    /// with sub-codes, lock-out).
    pub tmi_emcy: bool,
    /// Cams are windows [low, high] with hysteresis (TMI, CiA 406) instead of thresholds.
    pub window_cams: bool,
}

/// The unit-specific configuration (what the order code and label say).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DeviceConfig {
    /// Node-id at first power-on (1…127, 0xFF = unconfigured); stored LSS values override it.
    pub node_id: u8,
    /// Bit rate at first power-on in kbit/s (0 = autobaud, TMI); stored values override it.
    pub bitrate_kbps: u16,
    /// Serial number (0x1018/4, 0x650B).
    pub serial: u32,
    /// Stroke length in mm.
    pub stroke_mm: u32,
    /// Position measuring step in nm (0x6005/1).
    pub position_step_nm: u32,
    /// Number of magnets / position channels.
    pub channels: u8,
    /// Measurement cycle in µs.
    pub cycle_us: u32,
}

/// A product model: its dictionary table, its behaviour switches and how configuration-dependent
/// defaults are computed.
pub struct Model {
    /// Short name used on the command line (`th`, `e-series`, `tmi`).
    pub name: &'static str,
    /// Product name.
    pub product: &'static str,
    /// The object dictionary, sorted by index and sub-index.
    pub entries: &'static [Entry],
    /// Behaviour switches.
    pub features: Features,
    /// Resolves [`Param`] defaults for a unit.
    pub param: fn(&DeviceConfig, Param) -> u32,
    /// The default configuration of this model (the manuals' example unit).
    pub default_config: DeviceConfig,
}

impl core::fmt::Debug for Model {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.name)
    }
}

/// All models.
pub fn all() -> [&'static Model; 1] {
    [&th::TH]
}

/// Looks a model up by its command-line name.
pub fn by_name(name: &str) -> Option<&'static Model> {
    all()
        .into_iter()
        .find(|m| m.name.eq_ignore_ascii_case(name))
}

/// Builds [`Entry`] values tersely in model tables.
#[macro_export]
#[doc(hidden)]
macro_rules! entry {
    ($i:expr, $s:expr, $name:expr, $ty:ident, $acc:ident, $def:expr) => {
        $crate::entry!($i, $s, $name, $ty, $acc, $def, Any, Volatile, false)
    };
    ($i:expr, $s:expr, $name:expr, $ty:ident, $acc:ident, $def:expr, $range:ident $( ( $($r:tt)* ) )?, $grp:ident) => {
        $crate::entry!($i, $s, $name, $ty, $acc, $def, $range $( ( $($r)* ) )?, $grp, false)
    };
    ($i:expr, $s:expr, $name:expr, $ty:ident, $acc:ident, $def:expr, $range:ident $( ( $($r:tt)* ) )?, $grp:ident, $pdo:expr) => {
        $crate::od::Entry {
            index: $i,
            sub: $s,
            name: $name,
            ty: $crate::od::DataType::$ty,
            access: $crate::od::Access::$acc,
            pdo: $pdo,
            default: $def,
            range: $crate::od::Range::$range $( ( $($r)* ) )?,
            group: $crate::od::Group::$grp,
        }
    };
}

/// Parameters computed the same way for every model; `product_code` is the model's fixed 0x1018/2.
pub fn common_param(cfg: &DeviceConfig, p: Param, product_code: u32) -> u32 {
    let step = cfg.position_step_nm.max(1) as u64;
    match p {
        // D1: 0x00080196 with one magnet, 0x000A0196 for multi-position variants.
        Param::DeviceType => {
            if cfg.channels > 1 {
                0x000A_0196
            } else {
                0x0008_0196
            }
        }
        Param::ProductCode => product_code,
        Param::SerialNumber => cfg.serial,
        Param::NodeId => cfg.node_id as u32,
        Param::BitRateKbps => cfg.bitrate_kbps as u32,
        Param::PositionStepNm => cfg.position_step_nm,
        // D18: resolution / (10 × cycle time) in 0.01 mm/s, rounded.
        Param::VelocityStep => {
            let num = cfg.position_step_nm as u64 * 100; // nm → 0.01 µm
            let den = cfg.cycle_us.max(1) as u64 * 10;
            (((num * 1000 / den) + 500) / 1000) as u32
        }
        Param::MinPosition => 0,
        Param::MaxPosition => (cfg.stroke_mm as u64 * 1_000_000 / step) as u32,
        Param::Channels => cfg.channels as u32,
    }
}
