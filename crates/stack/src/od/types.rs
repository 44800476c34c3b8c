use core::fmt;

/// CiA 301 basic data types that the sensors' dictionaries use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DataType {
    /// BOOLEAN (0x0001), one byte 0 / 1.
    Boolean,
    /// INTEGER8 (0x0002).
    Integer8,
    /// INTEGER16 (0x0003).
    Integer16,
    /// INTEGER32 (0x0004).
    Integer32,
    /// UNSIGNED8 (0x0005).
    Unsigned8,
    /// UNSIGNED16 (0x0006).
    Unsigned16,
    /// UNSIGNED32 (0x0007).
    Unsigned32,
    /// VISIBLE_STRING (0x0009).
    VisibleString,
    /// DOMAIN (0x000F).
    Domain,
}

impl DataType {
    /// Size in bytes of a numeric type; `None` for strings and domains.
    pub const fn size(self) -> Option<usize> {
        match self {
            DataType::Boolean | DataType::Integer8 | DataType::Unsigned8 => Some(1),
            DataType::Integer16 | DataType::Unsigned16 => Some(2),
            DataType::Integer32 | DataType::Unsigned32 => Some(4),
            DataType::VisibleString | DataType::Domain => None,
        }
    }
    /// Size in bits of a numeric type (for PDO mapping), 0 otherwise.
    pub const fn bits(self) -> u8 {
        match self.size() {
            Some(n) => (n * 8) as u8,
            None => 0,
        }
    }
    /// Whether the type is a signed integer.
    pub const fn is_signed(self) -> bool {
        matches!(
            self,
            DataType::Integer8 | DataType::Integer16 | DataType::Integer32
        )
    }
    /// The CiA 301 data-type index (as used in EDS files).
    pub const fn code(self) -> u16 {
        match self {
            DataType::Boolean => 0x0001,
            DataType::Integer8 => 0x0002,
            DataType::Integer16 => 0x0003,
            DataType::Integer32 => 0x0004,
            DataType::Unsigned8 => 0x0005,
            DataType::Unsigned16 => 0x0006,
            DataType::Unsigned32 => 0x0007,
            DataType::VisibleString => 0x0009,
            DataType::Domain => 0x000F,
        }
    }
    /// Interprets the low `size()` bytes of a stored raw value as a signed 64-bit number (sign
    /// extended for signed types).
    pub const fn to_i64(self, raw: u32) -> i64 {
        match self {
            DataType::Integer8 => raw as u8 as i8 as i64,
            DataType::Integer16 => raw as u16 as i16 as i64,
            DataType::Integer32 => raw as i32 as i64,
            _ => raw as i64,
        }
    }
    /// How a raw value becomes a `u32` whose unsigned order is the order of the numbers
    /// [`DataType::to_i64`] gives, for range checks in 32 bits: shifted left by the first and
    /// arithmetically back (a signed type's low bytes sign-extended), then XORed with the second
    /// (a signed type offset by 2³¹). One table lookup for any number of values.
    const fn order_map(self) -> (u32, u32) {
        match self {
            DataType::Integer8 => (24, 0x8000_0000),
            DataType::Integer16 => (16, 0x8000_0000),
            DataType::Integer32 => (0, 0x8000_0000),
            _ => (0, 0),
        }
    }
    /// The largest raw value within the type's natural range: every raw value of a signed type
    /// is (only its low `size()` bytes count).
    const fn natural_max_raw(self) -> u32 {
        match self {
            DataType::Boolean => 1,
            DataType::Unsigned8 => u8::MAX as u32,
            DataType::Unsigned16 => u16::MAX as u32,
            _ => u32::MAX,
        }
    }
    /// Natural range of the type, as (min, max).
    pub const fn natural_range(self) -> (i64, i64) {
        match self {
            DataType::Boolean => (0, 1),
            DataType::Integer8 => (i8::MIN as i64, i8::MAX as i64),
            DataType::Integer16 => (i16::MIN as i64, i16::MAX as i64),
            DataType::Integer32 => (i32::MIN as i64, i32::MAX as i64),
            DataType::Unsigned8 => (0, u8::MAX as i64),
            DataType::Unsigned16 => (0, u16::MAX as i64),
            DataType::Unsigned32 | DataType::VisibleString | DataType::Domain => {
                (0, u32::MAX as i64)
            }
        }
    }
}

/// Access rights of an entry as seen from the bus.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// Read only; the application may change the value (live values).
    Ro,
    /// Write only.
    Wo,
    /// Read and write.
    Rw,
    /// Read only and never changes.
    Const,
}

impl Access {
    /// Readable over SDO.
    pub const fn readable(self) -> bool {
        !matches!(self, Access::Wo)
    }
    /// Writable over SDO.
    pub const fn writable(self) -> bool {
        matches!(self, Access::Rw | Access::Wo)
    }
    /// The EDS `AccessType` keyword.
    pub const fn eds(self) -> &'static str {
        match self {
            Access::Ro => "ro",
            Access::Wo => "wo",
            Access::Rw => "rw",
            Access::Const => "const",
        }
    }
}

/// Which non-volatile storage group an entry belongs to (CiA 301 0x1010 / 0x1011 sub-indices).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Group {
    /// Not stored: reloaded from its default at every reset.
    Volatile,
    /// Communication parameter (0x1000–0x1FFF; "save" on 0x1010/1 or /2).
    Comm,
    /// Application / manufacturer parameter (0x2000–0x9FFF; "save" on 0x1010/1 or /3).
    App,
    /// Stored automatically by the device whenever it changes (e.g. life-time temperature).
    Auto,
}

/// What an access to an entry sets in motion beyond reading or storing its value: the rule of the
/// service that owns the object, declared once in the model's table (CANopenNode registers such
/// per-object extensions at run time; here they are data). [`Hook::None`] entries are plain
/// values: the table's type, access and range checks are all there is to them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Hook {
    /// A plain value.
    None,
    /// 0x1003 error history: a read beyond the recorded errors has no data; writing sub 0
    /// clears the history (EMCY service).
    ErrorHistory,
    /// 0x1005 COB-ID SYNC: consumer only, 11-bit, not a restricted CAN-ID (SYNC consumer).
    SyncCobId,
    /// 0x100C guard time / 0x100D life time factor (error control).
    Guarding,
    /// 0x100E COB-ID of the guarding protocol: where guarding requests are answered.
    GuardingCobId,
    /// 0x1010 store parameters: the signature starts a store of the sub's scope.
    StoreParameters,
    /// 0x1011 restore default parameters: the signature forgets the sub's scope.
    RestoreDefaults,
    /// 0x1014 COB-ID EMCY (EMCY producer).
    EmcyCobId,
    /// 0x1015 EMCY inhibit time.
    EmcyInhibit,
    /// 0x1017 producer heartbeat time.
    Heartbeat,
    /// An object copy of the node-id that the next reset communication activates (TMI
    /// 0x2000): one value with LSS "configure node-id".
    PendingNodeId,
    /// An object copy of the bit rate (kbit/s, 0xFFFF autobaud) that the next reset activates
    /// (TMI 0x2001): one value with LSS "configure bit timing".
    PendingBitRate,
    /// 0x1029 error behaviour sub 1…: 0, 1 or 2 (the node's reaction to an error class).
    ErrorBehaviour,
    // The hooks from here on are those whose values their service checks (heartbeat consumer,
    // PDO services, the application): `Hook::checked_by_service` is then one compare. A new
    // hook goes above.
    /// 0x1016 consumer heartbeat time sub 1…: a node-id watched once (heartbeat consumer).
    HbConsumer,
    /// A TPDO communication parameter (0x1800…, PDO service).
    TpdoComm,
    /// A TPDO mapping parameter (0x1A00…, PDO service).
    TpdoMap,
    /// An RPDO communication parameter (0x1400…, RPDO service).
    RpdoComm,
    /// An RPDO mapping parameter (0x1600…, RPDO service).
    RpdoMap,
    /// Objects of the application, which validates them, reacts to writes and refreshes them
    /// before reads: [`Hook::app`]`(n)` with the application's own number `n` (0–15, e.g.
    /// `encoder::hook`), which [`Hook::app_number`] gives back. Sixteen variants rather than
    /// one carrying a number: a `Hook` is then one plain byte, so a table entry is a word
    /// smaller on a 32-bit microcontroller (docs/FIRMWARE.md has the size), and the node's matches on hooks (several
    /// per SDO write) stay plain compares.
    App0,
    #[allow(missing_docs)]
    App1,
    #[allow(missing_docs)]
    App2,
    #[allow(missing_docs)]
    App3,
    #[allow(missing_docs)]
    App4,
    #[allow(missing_docs)]
    App5,
    #[allow(missing_docs)]
    App6,
    #[allow(missing_docs)]
    App7,
    #[allow(missing_docs)]
    App8,
    #[allow(missing_docs)]
    App9,
    #[allow(missing_docs)]
    App10,
    #[allow(missing_docs)]
    App11,
    #[allow(missing_docs)]
    App12,
    #[allow(missing_docs)]
    App13,
    #[allow(missing_docs)]
    App14,
    #[allow(missing_docs)]
    App15,
}

// The order `Hook::checked_by_service` and `Hook::app_number` rely on: the PDO hooks, then the
// sixteen application hooks, last.
const _: () = assert!(
    Hook::TpdoMap as u8 == Hook::TpdoComm as u8 + 1
        && Hook::RpdoMap as u8 == Hook::RpdoComm as u8 + 1
        && Hook::App0 as u8 == Hook::RpdoMap as u8 + 1
        && Hook::App15 as u8 == Hook::App0 as u8 + 15
        && Hook::APP[15] as u8 == Hook::App15 as u8
);

impl Hook {
    /// The application hooks in number order.
    const APP: [Hook; 16] = {
        use Hook::*;
        [
            App0, App1, App2, App3, App4, App5, App6, App7, App8, App9, App10, App11, App12, App13,
            App14, App15,
        ]
    };

    /// The application's hook number `n`, below 16: a larger one fails to compile in a table
    /// or a constant (the only places that make hooks).
    pub const fn app(n: u8) -> Hook {
        Self::APP[n as usize]
    }

    /// Whether the service that owns the object checks a written value itself (the PDO
    /// service its parameters, the application its objects) rather than the node.
    #[inline]
    pub const fn checked_by_service(self) -> bool {
        self as u8 >= Hook::HbConsumer as u8
    }

    /// The application's number of an application hook, `None` for the services' hooks.
    #[inline]
    pub const fn app_number(self) -> Option<u8> {
        (self as u8).checked_sub(Hook::App0 as u8)
    }
}

/// Values that depend on the unit's configuration rather than on the model alone.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Param {
    /// 0x1000 device type (D1: depends on the number of channels).
    DeviceType,
    /// 0x1018/2 product code (TMI: bit-coded from the variant).
    ProductCode,
    /// 0x1018/4 serial number.
    SerialNumber,
    /// Active node-id (0x100B, TMI 0x2000).
    NodeId,
    /// Configured bit rate in kbit/s (TMI 0x2001).
    BitRateKbps,
    /// A value the application's profile defines (its parameter function gives the number's
    /// meaning).
    Profile(u8),
    /// A value only one model has (e.g. TMI's TPDO2 COB-ID, valid only on two-channel units);
    /// the model's parameter function defines the number's meaning.
    Model(u8),
}

/// Where an entry's value at boot (and after a restore) comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DefaultValue {
    /// A fixed number (raw little-endian bits, sign-extended types stored as two's complement).
    Const(u32),
    /// `base + node-id` (pre-defined connection set COB-IDs).
    NodeId(u32),
    /// A fixed string (VISIBLE_STRING, const / ro). Behind a second reference, so that the
    /// variant holds one pointer rather than a pointer and a length: every entry of a table
    /// is smaller on a 32-bit microcontroller (docs/FIRMWARE.md has the size).
    Str(&'static &'static str),
    /// A configuration-dependent value.
    Param(Param),
    /// A live value computed by the application; no default (reads its current value, 0 at boot).
    Live,
}

/// Values the SDO server accepts for an entry beyond the type's natural range.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Range {
    /// Any value of the type.
    Any,
    /// Inclusive numeric range, as raw values of the entry's type (read with its signedness,
    /// like the value itself): 32 bits each, so that a table entry stays small on a
    /// microcontroller. [`Range::between`] builds one from numbers.
    MinMax(u32, u32),
    /// One of an explicit list (raw values).
    OneOf(&'static [u32]),
}

impl Range {
    /// The inclusive range `lo..=hi` of numbers of an entry's type (both within its natural
    /// range; a signed bound is kept as its two's-complement bits).
    pub const fn between(lo: i64, hi: i64) -> Range {
        Range::MinMax(lo as u32, hi as u32)
    }
}

/// One object-dictionary entry (an index / sub-index pair): everything SDO access checks, PDO
/// mapping checks, persistence and EDS export need to know about it. Each model declares its
/// dictionary as one sorted table of these.
#[derive(Clone, Copy, Debug)]
pub struct Entry {
    /// Object index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// Name (EDS `ParameterName`); not in firmware builds (feature `names`).
    #[cfg(feature = "names")]
    pub name: &'static str,
    /// Data type.
    pub ty: DataType,
    /// Access over SDO.
    pub access: Access,
    /// May be mapped into a TPDO.
    pub pdo: bool,
    /// Value at boot / after restore.
    pub default: DefaultValue,
    /// Accepted values on write. Behind a reference, so that the many entries with
    /// [`Range::Any`] take one pointer rather than a whole range (the sizes in
    /// docs/FIRMWARE.md).
    pub range: &'static Range,
    /// Storage group.
    pub group: Group,
    /// The owning service's rule for this object.
    pub hook: Hook,
}

/// The `index << 8 | sub` key of an object: what a model's table is sorted by and its key
/// array holds.
#[inline]
pub const fn key(index: u16, sub: u8) -> u32 {
    (index as u32) << 8 | sub as u32
}

impl Hook {
    /// Whether a write sets something in motion once the value has landed (the other hooks
    /// only check a write, or act instead of storing it).
    #[inline]
    pub const fn acts_when_written(self) -> bool {
        !matches!(
            self,
            Hook::None
                | Hook::SyncCobId
                | Hook::EmcyCobId
                | Hook::StoreParameters
                | Hook::RestoreDefaults
                | Hook::ErrorBehaviour
        )
    }
}

impl Entry {
    /// An entry without a hook: what the `entry!` macro of the model tables expands to, so the
    /// `names` feature is decided here, in this crate, rather than in the macro's caller.
    /// Without the feature `name` is dropped.
    #[doc(hidden)]
    #[allow(clippy::too_many_arguments)]
    pub const fn build(
        index: u16,
        sub: u8,
        name: &'static str,
        ty: DataType,
        access: Access,
        pdo: bool,
        default: DefaultValue,
        range: &'static Range,
        group: Group,
    ) -> Entry {
        let _ = name; // only the `names` feature keeps it
        Entry {
            index,
            sub,
            #[cfg(feature = "names")]
            name,
            ty,
            access,
            pdo,
            default,
            range,
            group,
            hook: Hook::None,
        }
    }

    /// The entry with `hook` (table construction).
    pub const fn with_hook(mut self, hook: Hook) -> Entry {
        self.hook = hook;
        self
    }

    /// Whether a reset communication reloads the entry: the communication profile area
    /// (0x1000–0x1FFF, CiA 301); everything else is reloaded by reset node only (D6).
    pub const fn reset_by_comm(&self) -> bool {
        self.index >= 0x1000 && self.index <= 0x1FFF
    }

    /// The [`key`] the table is sorted by.
    pub const fn key(&self) -> u32 {
        key(self.index, self.sub)
    }

    /// Whether a raw value is acceptable for this entry (type range and declared range).
    #[inline]
    pub fn accepts(&self, raw: u32) -> bool {
        self.check(raw).is_ok()
    }

    /// [`Entry::accepts`] with the SDO abort of a refusal: beyond the declared range "value too
    /// high" ([`Entry::above_range`]) or "too low" ([`Entry::below_range`]), else "invalid
    /// value". One comparison of each bound for both answers.
    #[cfg_attr(feature = "inline-hot-paths", inline)] // every SDO download
    pub fn check(&self, raw: u32) -> Result<(), Abort> {
        // In 32 bits (64-bit compares cost a 32-bit target twice the code): the same answers
        // as comparing `DataType::to_i64` numbers with `DataType::natural_range`.
        let natural = raw <= self.ty.natural_max_raw();
        let ok = match *self.range {
            Range::Any => natural,
            Range::MinMax(lo, hi) => {
                let (shift, flip) = self.ty.order_map();
                let key = |x: u32| ((x << shift) as i32 >> shift) as u32 ^ flip;
                let v = key(raw);
                if v > key(hi) {
                    return Err(Abort::ValueTooHigh);
                }
                if v < key(lo) {
                    return Err(Abort::ValueTooLow);
                }
                natural
            }
            // Not `contains`: for integers it unrolls by 16, flash spent on lists of a few
            // (docs/FIRMWARE.md, "Build options in figures").
            #[allow(clippy::manual_contains)]
            Range::OneOf(list) => natural && list.iter().any(|&x| x == raw),
        };
        if ok {
            Ok(())
        } else {
            Err(Abort::InvalidValue)
        }
    }

    /// The declared [`Range::MinMax`] as numbers of the entry's type.
    pub const fn limits(&self) -> Option<(i64, i64)> {
        match *self.range {
            Range::MinMax(lo, hi) => Some((self.ty.to_i64(lo), self.ty.to_i64(hi))),
            _ => None,
        }
    }

    /// Whether a raw value is above the declared range (for the "too high" abort code).
    pub fn above_range(&self, raw: u32) -> bool {
        match *self.range {
            Range::MinMax(_, hi) => self.ty.to_i64(raw) > self.ty.to_i64(hi),
            _ => false,
        }
    }

    /// Whether a raw value is below the declared range (for the "too low" abort code).
    pub fn below_range(&self, raw: u32) -> bool {
        match *self.range {
            Range::MinMax(lo, _) => self.ty.to_i64(raw) < self.ty.to_i64(lo),
            _ => false,
        }
    }
}

/// CiA 301 SDO abort codes (SPEC §4).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum Abort {
    /// Toggle bit not alternated.
    Toggle = 0x0503_0000,
    /// SDO protocol timed out.
    Timeout = 0x0504_0000,
    /// Client/server command specifier not valid or unknown.
    InvalidCommand = 0x0504_0001,
    /// Invalid block size (block mode only).
    BlockSize = 0x0504_0002,
    /// Invalid sequence number (block mode only).
    BlockSequence = 0x0504_0003,
    /// CRC error (block mode only).
    Crc = 0x0504_0004,
    /// Out of memory.
    OutOfMemory = 0x0504_0005,
    /// Unsupported access to an object.
    UnsupportedAccess = 0x0601_0000,
    /// Attempt to read a write-only object.
    WriteOnly = 0x0601_0001,
    /// Attempt to write a read-only object.
    ReadOnly = 0x0601_0002,
    /// Object does not exist in the object dictionary.
    NoObject = 0x0602_0000,
    /// Object cannot be mapped to the PDO.
    NotMappable = 0x0604_0041,
    /// The number and length of the objects to be mapped would exceed the PDO length.
    MappingLength = 0x0604_0042,
    /// General parameter incompatibility reason.
    ParamIncompatible = 0x0604_0043,
    /// General internal incompatibility in the device.
    InternalIncompatible = 0x0604_0047,
    /// Access failed due to a hardware error.
    Hardware = 0x0606_0000,
    /// Data type does not match, length of service parameter does not match.
    LengthMismatch = 0x0607_0010,
    /// Data type does not match, length of service parameter too high.
    LengthTooHigh = 0x0607_0012,
    /// Data type does not match, length of service parameter too low.
    LengthTooLow = 0x0607_0013,
    /// Sub-index does not exist.
    NoSub = 0x0609_0011,
    /// Invalid value for parameter (download only).
    InvalidValue = 0x0609_0030,
    /// Value of parameter written too high (download only).
    ValueTooHigh = 0x0609_0031,
    /// Value of parameter written too low (download only).
    ValueTooLow = 0x0609_0032,
    /// Maximum value is less than minimum value.
    MaxLessThanMin = 0x0609_0036,
    /// General error.
    General = 0x0800_0000,
    /// Data cannot be transferred or stored to the application.
    CannotStore = 0x0800_0020,
    /// … because of local control.
    LocalControl = 0x0800_0021,
    /// … because of the present device state.
    WrongState = 0x0800_0022,
    /// No data available.
    NoData = 0x0800_0024,
}

impl Abort {
    /// Every abort code, for tables and tests.
    pub const ALL: [Abort; 29] = [
        Abort::Toggle,
        Abort::Timeout,
        Abort::InvalidCommand,
        Abort::BlockSize,
        Abort::BlockSequence,
        Abort::Crc,
        Abort::OutOfMemory,
        Abort::UnsupportedAccess,
        Abort::WriteOnly,
        Abort::ReadOnly,
        Abort::NoObject,
        Abort::NotMappable,
        Abort::MappingLength,
        Abort::ParamIncompatible,
        Abort::InternalIncompatible,
        Abort::Hardware,
        Abort::LengthMismatch,
        Abort::LengthTooHigh,
        Abort::LengthTooLow,
        Abort::NoSub,
        Abort::InvalidValue,
        Abort::ValueTooHigh,
        Abort::ValueTooLow,
        Abort::MaxLessThanMin,
        Abort::General,
        Abort::CannotStore,
        Abort::LocalControl,
        Abort::WrongState,
        Abort::NoData,
    ];

    /// The 32-bit code.
    pub const fn code(self) -> u32 {
        self as u32
    }

    /// Looks a code up.
    pub fn from_code(code: u32) -> Option<Abort> {
        Abort::ALL.iter().copied().find(|a| a.code() == code)
    }

    /// The CiA 301 meaning, for tools and logs.
    pub const fn meaning(self) -> &'static str {
        match self {
            Abort::Toggle => "Toggle bit not alternated",
            Abort::Timeout => "SDO protocol timed out",
            Abort::InvalidCommand => "Client/server command specifier not valid or unknown",
            Abort::BlockSize => "Invalid block size",
            Abort::BlockSequence => "Invalid sequence number",
            Abort::Crc => "CRC error",
            Abort::OutOfMemory => "Out of memory",
            Abort::UnsupportedAccess => "Unsupported access to an object",
            Abort::WriteOnly => "Attempt to read a write only object",
            Abort::ReadOnly => "Attempt to write a read only object",
            Abort::NoObject => "Object does not exist in the object dictionary",
            Abort::NotMappable => "Object cannot be mapped to the PDO",
            Abort::MappingLength => "Number and length of mapped objects exceed PDO length",
            Abort::ParamIncompatible => "General parameter incompatibility",
            Abort::InternalIncompatible => "General internal incompatibility in the device",
            Abort::Hardware => "Access failed due to a hardware error",
            Abort::LengthMismatch => {
                "Data type does not match, length of service parameter does not match"
            }
            Abort::LengthTooHigh => {
                "Data type does not match, length of service parameter too high"
            }
            Abort::LengthTooLow => "Data type does not match, length of service parameter too low",
            Abort::NoSub => "Sub-index does not exist",
            Abort::InvalidValue => "Invalid value for parameter",
            Abort::ValueTooHigh => "Value of parameter written too high",
            Abort::ValueTooLow => "Value of parameter written too low",
            Abort::MaxLessThanMin => "Maximum value is less than minimum value",
            Abort::General => "General error",
            Abort::CannotStore => "Data cannot be transferred or stored to the application",
            Abort::LocalControl => "Data cannot be transferred or stored because of local control",
            Abort::WrongState => {
                "Data cannot be transferred or stored because of the present device state"
            }
            Abort::NoData => "No data available",
        }
    }
}

impl fmt::Display for Abort {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "0x{:08X} {}", self.code(), self.meaning())
    }
}

/// The slot of `key` ([`key`]) in a sorted table, or where it would be: firmware's search
/// (hosts search [`Table::keys`](crate::Table::keys)), one shared copy.
#[inline(never)]
pub fn search_entries(entries: &[Entry], key: u32) -> Result<usize, usize> {
    entries.binary_search_by_key(&key, Entry::key)
}
