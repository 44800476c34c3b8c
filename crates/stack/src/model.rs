//! The device description the stack runs: a table, the stack's behaviour switches, and the
//! unit configuration the stack reads (node-id, bit rate, serial number).

use crate::od::types::{search_entries, Entry, Param};
use crate::sdo::Transfers;

/// The unit configuration the stack reads; an application's configuration adds its own fields.
pub trait UnitConfig: Copy + core::fmt::Debug + 'static {
    /// Node-id at first power-on (1…127, 0xFF = unconfigured).
    fn node_id(&self) -> u8;
    /// Bit rate at first power-on in kbit/s (0 = autobaud).
    fn bitrate_kbps(&self) -> u16;
    /// Sets the node-id.
    fn set_node_id(&mut self, id: u8);
    /// Sets the bit rate.
    fn set_bitrate_kbps(&mut self, kbps: u16);
    /// The raw bounds application hook `hook` accepts on this unit, where its rule is a range.
    fn app_limits(&self, _hook: u8) -> Option<(u32, u32)> {
        None
    }
}

/// The configuration of a unit with no application configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CommConfig {
    /// Node-id at first power-on.
    pub node_id: u8,
    /// Bit rate at first power-on in kbit/s.
    pub bitrate_kbps: u16,
    /// Serial number (0x1018/4).
    pub serial: u32,
}

impl UnitConfig for CommConfig {
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
}

/// Behaviour switches of a product model that are not properties of single objects.
#[derive(Clone, Copy, Debug)]
pub struct Features {
    /// Tag written into storage images so one model never loads another's.
    pub tag: u8,
    /// Number of TPDOs (0x1800… / 0x1A00…).
    pub tpdos: u8,
    /// Number of RPDOs (0x1400… / 0x1600…), at most [`crate::config::MAX_RPDOS`].
    pub rpdos: u8,
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
    /// Bit rates (kbit/s) the model supports, for the EDS `BaudRate_xxx` keys.
    pub bitrates: &'static [u16],
    /// Storing (0x1010) only allowed in pre-operational (TMI).
    pub store_preop_only: bool,
    /// 0x1010 accepts the "kill" signature (TMI).
    pub kill_signature: bool,
    /// The power-on EMCY (0x0000) follows every boot-up (D14; TH and E-Series, whose manuals
    /// say "Power-on / reset"; the TMI manual has none).
    pub power_on_emcy: bool,
    /// A SYNC with more than one data byte raises EMCY 0x8240 "unexpected SYNC data length"
    /// (CiA 301; the TMI's EMCY table has no such code, so it ignores the frame).
    pub sync_length_emcy: bool,
    /// An EMCY 0x0000 goes along with every change of the error register when an error
    /// clears, not only when the last one does (TH / E-Series: "Emergency objects go along
    /// with changes of the internal error status register"; TMI: 0x0000 is "Sensor Error
    /// resetted", sent once no error is left). Also the 0x0000 after "recovered from bus-off".
    pub emcy_on_register_change: bool,
    /// A TPDO's event timer must stay above its inhibit time (TMI R27).
    pub event_timer_above_inhibit: bool,
    /// A node without a valid node-id enters LSS configuration by itself (TMI, DSP 305 V1.1
    /// R7); DS 305 V2 nodes wait in LSS waiting for a master to select them.
    pub lss_unconfigured_configures: bool,
}

impl Features {
    /// The SDO transfer types beyond expedited ones.
    #[inline(always)]
    pub const fn sdo_transfers(&self) -> Transfers {
        Transfers {
            segmented: self.sdo_segmented,
            block: self.sdo_block,
        }
    }
}

/// A device's dictionary table, its names and the stack's behaviour switches for it.
pub struct Table {
    /// Short name used on the command line (`th`, `e-series`, `tmi`).
    pub name: &'static str,
    /// Product name.
    pub product: &'static str,
    /// Vendor name (EDS `VendorName`).
    pub vendor: &'static str,
    /// The object dictionary, sorted by index and sub-index.
    pub entries: &'static [Entry],
    /// `entries[i].key()` for every entry, in the same order: a host's dictionary searches
    /// these, a dense array, rather than the entries (fewer instructions per upload). Firmware
    /// (without `inline-hot-paths`) searches the entries and keeps the array out of flash: empty
    /// there (figures: docs/FIRMWARE.md, "Build options in figures").
    pub keys: &'static [u32],
    /// Behaviour switches of the stack.
    pub features: Features,
}

/// Picks the description of a unit by its configuration ([`Model::variant`]).
pub type Variant<C, X> = fn(&C) -> &'static Model<C, X>;

/// A device description: its [`Table`] (which it dereferences to: `model.entries`), what the
/// application's profile adds, and how a unit's configuration-dependent values are computed.
pub struct Model<C: 'static = CommConfig, X: 'static = ()> {
    /// The table, names and stack switches: what a tool holding descriptions of any
    /// application needs (`&'static Table`).
    pub table: Table,
    /// What the application's profile adds to the description (`()` for none).
    pub profile: X,
    /// Resolves [`Param`] defaults for a unit.
    pub param: fn(&C, Param) -> u32,
    /// Makes a configuration consistent with the model's rules (clamps the channel count,
    /// derives the measurement cycle from the stroke, …).
    pub derive: fn(C) -> C,
    /// The description of a unit configured as `cfg` when it differs by unit (a device with one
    /// dictionary per configuration); `None`: this one for every unit.
    pub variant: Option<Variant<C, X>>,
    /// The default configuration of this model (the manuals' example unit).
    pub default_config: C,
}

impl Table {
    /// The slot of `key` ([`crate::od::key`]) in the table, or where it would be: a host
    /// searches [`Table::keys`], firmware the entries.
    pub fn search(&self, key: u32) -> Result<usize, usize> {
        if crate::config::INLINE_HOT_PATHS {
            self.keys.binary_search(&key)
        } else {
            search_entries(self.entries, key)
        }
    }
}

impl<C, X> core::ops::Deref for Model<C, X> {
    type Target = Table;
    #[inline(always)]
    fn deref(&self) -> &Table {
        &self.table
    }
}

impl<C, X> Model<C, X> {
    /// `cfg` made consistent with this model's rules (see [`Model::derive`]).
    pub fn configure(&self, cfg: C) -> C {
        (self.derive)(cfg)
    }

    /// The description of the unit `cfg` (see [`Model::variant`]).
    #[inline(always)]
    pub fn for_unit(&'static self, cfg: &C) -> &'static Self {
        match self.variant {
            Some(f) => f(cfg),
            None => self,
        }
    }
}

impl<C, X> core::fmt::Debug for Model<C, X> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.name)
    }
}
