//! The CiA 406 unit configuration, the products' switches the encoder reads, and the profile's
//! parameters.

use canpos_stack::model::UnitConfig;
use canpos_stack::od::Param;

use crate::hook;

/// The unit-specific configuration (what the order code and label say).
///
/// Start from a model's `Model::default_config` and change what the unit's order code says
/// with the `with_*` builders, then pass it through `Model::configure` so that values the
/// model derives (TH measurement cycle from the stroke) follow.
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
    /// Position measuring step in nm (0x6005/1). On TMI the variant's minimum step (1 µm or
    /// 5 µm); the step in use is 0x6005/1, which is writable there.
    pub position_step_nm: u32,
    /// Number of magnets / position channels.
    pub channels: u8,
    /// Measurement cycle in µs.
    pub cycle_us: u32,
}

impl DeviceConfig {
    /// With node-id `id` (1…127, or 0xFF to start unconfigured).
    pub const fn with_node_id(mut self, id: u8) -> Self {
        self.node_id = id;
        self
    }
    /// With bit rate `kbps` (0 = autobaud on TMI).
    pub const fn with_bitrate(mut self, kbps: u16) -> Self {
        self.bitrate_kbps = kbps;
        self
    }
    /// With serial number `serial`.
    pub const fn with_serial(mut self, serial: u32) -> Self {
        self.serial = serial;
        self
    }
    /// With stroke length `mm`.
    pub const fn with_stroke_mm(mut self, mm: u32) -> Self {
        self.stroke_mm = mm;
        self
    }
    /// With position measuring step (resolution) `nm`.
    pub const fn with_step_nm(mut self, nm: u32) -> Self {
        self.position_step_nm = nm;
        self
    }
    /// With `n` magnets / position channels.
    pub const fn with_channels(mut self, n: u8) -> Self {
        self.channels = n;
        self
    }
    /// With measurement cycle `us` (normally derived by `Model::configure`).
    pub const fn with_cycle_us(mut self, us: u32) -> Self {
        self.cycle_us = us;
        self
    }
}

impl UnitConfig for DeviceConfig {
    fn node_id(&self) -> u8 {
        self.node_id
    }
    fn bitrate_kbps(&self) -> u16 {
        self.bitrate_kbps
    }
    fn set_node_id(&mut self, id: u8) {
        self.node_id = id;
    }
    fn set_bitrate_kbps(&mut self, kbps: u16) {
        self.bitrate_kbps = kbps;
    }
    fn app_limits(&self, hook: u8) -> Option<(u32, u32)> {
        limits(hook, self)
    }
}

/// The products' switches of CiA 406 behaviour the encoder reads.
#[derive(Clone, Copy, Debug)]
pub struct Switches {
    /// E-Series: writing 0xFFFFFFFF to a preset clears it.
    pub preset_clear: bool,
    /// The offset a preset (0x6010/n) produces is kept inside the device and stored with the
    /// preset, not shown in 0x650C (TMI: it has no offset object). The preset itself is CiA
    /// 406's on every model: the value the current position takes when it is written.
    pub preset_offset_internal: bool,
    /// The TMI's EMCY table and error reactions (002 §1.13 / §1.14): manufacturer bytes per
    /// code, EMCY 0x9080 / 0x9090 on cam / work-area changes, the system-data errors with their
    /// lock-out, process values frozen on a sensor error, 0x1002 status, corrupt storage in
    /// 0x1002 instead of EMCY 0x6300, and the conditions its table has no code for.
    pub tmi_error_reactions: bool,
    /// Cams are windows [low, high] with hysteresis (TMI, CiA 406) instead of thresholds.
    pub window_cams: bool,
}

/// A CiA 406 device description: the stack's, with the encoder's switches and configuration.
pub type Model = canpos_stack::model::Model<DeviceConfig, Switches>;

/// The device description a build fixes (a firmware for one product), if any: the encoder and
/// the node then read its features as constants.
pub trait Fixed: Copy + Default + core::fmt::Debug + 'static {
    /// The fixed description.
    const MODEL: Option<&'static Model> = None;
}

/// No description fixed at build time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Unfixed;
impl Fixed for Unfixed {}

/// Most position channels a description's dictionary has (sub 0 of 0x6020).
pub trait Channels {
    /// Most position channels.
    fn max_channels(&self) -> u8;
}

impl Channels for Model {
    fn max_channels(&self) -> u8 {
        self.entries
            .iter()
            .filter(|e| e.index == 0x6020 && e.sub > 0)
            .count() as u8
    }
}

/// The CiA 406 parameters of a table's `DefaultValue::Param` entries.
pub mod param {
    use canpos_stack::od::Param;
    /// Position measuring step in nm (0x6005/1, 0x6501).
    pub const POSITION_STEP_NM: Param = Param::Profile(0);
    /// Velocity measuring step in 0.01 mm/s (0x6005/2).
    pub const VELOCITY_STEP: Param = Param::Profile(1);
    /// Start of the measuring range, in position steps.
    pub const MIN_POSITION: Param = Param::Profile(2);
    /// End of the measuring range, in position steps.
    pub const MAX_POSITION: Param = Param::Profile(3);
    /// Number of position channels.
    pub const CHANNELS: Param = Param::Profile(4);
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
        param::POSITION_STEP_NM => cfg.position_step_nm,
        // D18: resolution / (10 × cycle time) in 0.01 mm/s, rounded.
        param::VELOCITY_STEP => {
            let num = cfg.position_step_nm as u64 * 100; // nm → 0.01 µm
            let den = cfg.cycle_us.max(1) as u64 * 10;
            canpos_stack::div::div(canpos_stack::div::div(num * 1000, den) + 500, 1000) as u32
        }
        param::MIN_POSITION => 0,
        param::MAX_POSITION => canpos_stack::div::div(cfg.stroke_mm as u64 * 1_000_000, step)
            .min(i32::MAX as u64) as u32,
        param::CHANNELS => cfg.channels as u32,
        Param::Profile(_) | Param::Model(_) => 0,
    }
}

/// The values application hook `h` accepts on a unit configured as `cfg`, as raw bounds, where
/// its rule is a range (the table's range of the entry applies as well): what the unit's EDS
/// gives as `LowLimit` / `HighLimit`, so that the file names what that unit accepts (a 5 µm TMI
/// refuses a measuring step below 5000 nm).
pub fn limits(h: u8, cfg: &DeviceConfig) -> Option<(u32, u32)> {
    match h {
        // R31: from the variant's minimum step (1 µm or 5 µm), whole µm, up to 100 µm.
        hook::MEASURING_STEP => Some((cfg.position_step_nm.div_ceil(1000) * 1000, 100_000)),
        // Four cams per channel: bits 0…3.
        hook::CAM_SWITCH => Some((0, 0x0F)),
        _ => None,
    }
}
