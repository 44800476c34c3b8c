//! Compile-time table assembly: the parts every model table is built from (per-channel
//! arrays, TPDO records, the threshold cams and work areas the TH and the E-Series share) and
//! the names they carry.

use canpos_stack::od::{Access, DataType, DefaultValue, Entry, Group, Hook, Range};

const BLANK: Entry = Entry {
    index: 0,
    sub: 0,
    #[cfg(feature = "names")]
    name: "",
    ty: DataType::Unsigned8,
    access: Access::Const,
    pdo: false,
    default: DefaultValue::Const(0),
    range: &Range::Any,
    group: Group::Volatile,
    hook: Hook::None,
};

/// A per-channel array: sub 0 (UNSIGNED8 const, number of channels) and `N - 1` channel
/// entries that share type, access, default, range and group.
#[allow(clippy::too_many_arguments)]
pub const fn channels<const N: usize>(
    index: u16,
    names: [&'static str; N],
    ty: DataType,
    access: Access,
    pdo: bool,
    default: DefaultValue,
    range: &'static Range,
    group: Group,
) -> [Entry; N] {
    let _ = &names; // only the `names` feature keeps them
    let mut out = [BLANK; N];
    out[0] = Entry {
        index,
        sub: 0,
        #[cfg(feature = "names")]
        name: names[0],
        ty: DataType::Unsigned8,
        access: Access::Const,
        pdo: false,
        default: DefaultValue::Const(N as u32 - 1),
        range: &Range::Any,
        group: Group::Volatile,
        hook: Hook::None,
    };
    let mut i = 1;
    while i < N {
        out[i] = Entry {
            index,
            sub: i as u8,
            #[cfg(feature = "names")]
            name: names[i],
            ty,
            access,
            pdo,
            default,
            range,
            group,
            hook: Hook::None,
        };
        i += 1;
    }
    out
}

/// The communication parameter record of one TPDO (0x1800 + n).
#[derive(Clone, Copy)]
pub struct TpdoComm {
    /// Default COB-ID (sub 1).
    pub cob: DefaultValue,
    /// Default transmission type (sub 2).
    pub ttype: u32,
    /// Transmission types the model accepts (TMI TPDO2: synchronous only).
    pub ttype_range: &'static Range,
    /// Sub 3 inhibit time exists (E-Series, TMI; not listed for TH).
    pub inhibit: bool,
    /// Sub 5 event timer exists, with this default in ms.
    pub event: Option<u32>,
    /// Storage group of subs 1…5.
    pub group: Group,
}

/// A TPDO communication record; only the first `.1` entries of `.0` are used.
pub const fn tpdo_comm(index: u16, names: [&'static str; 5], c: TpdoComm) -> ([Entry; 5], usize) {
    let _ = &names; // only the `names` feature keeps them
    let mut out = [BLANK; 5];
    let highest = if c.event.is_some() {
        5
    } else if c.inhibit {
        3
    } else {
        2
    };
    out[0] = Entry {
        index,
        sub: 0,
        #[cfg(feature = "names")]
        name: names[0],
        ty: DataType::Unsigned8,
        access: Access::Const,
        pdo: false,
        default: DefaultValue::Const(highest),
        range: &Range::Any,
        group: Group::Volatile,
        hook: Hook::None,
    };
    out[1] = Entry {
        index,
        sub: 1,
        #[cfg(feature = "names")]
        name: names[1],
        ty: DataType::Unsigned32,
        access: Access::Rw,
        pdo: false,
        default: c.cob,
        range: &Range::Any,
        group: c.group,
        hook: Hook::None, // `cia301::attach`
    };
    out[2] = Entry {
        index,
        sub: 2,
        #[cfg(feature = "names")]
        name: names[2],
        ty: DataType::Unsigned8,
        access: Access::Rw,
        pdo: false,
        default: DefaultValue::Const(c.ttype),
        range: c.ttype_range,
        group: c.group,
        hook: Hook::None, // `cia301::attach`
    };
    let mut n = 3;
    if c.inhibit {
        out[n] = Entry {
            index,
            sub: 3,
            #[cfg(feature = "names")]
            name: names[3],
            ty: DataType::Unsigned16,
            access: Access::Rw,
            pdo: false,
            default: DefaultValue::Const(0),
            range: &Range::Any,
            group: c.group,
            hook: Hook::None, // `cia301::attach`
        };
        n += 1;
    }
    if let Some(ms) = c.event {
        out[n] = Entry {
            index,
            sub: 5,
            #[cfg(feature = "names")]
            name: names[4],
            ty: DataType::Unsigned16,
            access: Access::Rw,
            pdo: false,
            default: DefaultValue::Const(ms),
            range: &Range::Any,
            group: c.group,
            hook: Hook::None, // `cia301::attach`
        };
        n += 1;
    }
    (out, n)
}

/// A TPDO mapping record with `N - 1` entries (sub 0 = `count` mapped, subs from `maps`,
/// 0 beyond). Sub 0 accepts any value here: the PDO service answers a count above the
/// entries with 0x06040042 (conformance PDO-25), which a table range would pre-empt.
pub const fn tpdo_map<const N: usize>(
    index: u16,
    names: [&'static str; 9],
    count: u32,
    maps: [u32; 8],
    group: Group,
) -> [Entry; N] {
    let _ = &names; // only the `names` feature keeps them
    let mut out = [BLANK; N];
    let mut i = 0;
    while i < N {
        out[i] = Entry {
            index,
            sub: i as u8,
            #[cfg(feature = "names")]
            name: names[i],
            ty: if i == 0 {
                DataType::Unsigned8
            } else {
                DataType::Unsigned32
            },
            access: Access::Rw,
            pdo: false,
            default: DefaultValue::Const(if i == 0 { count } else { maps[i - 1] }),
            range: &Range::Any,
            group,
            hook: Hook::None, // `cia301::attach`
        };
        i += 1;
    }
    out
}

/// 0x1003 pre-defined error field (CiA 301, SPEC §6): sub 0 (writing 0 clears the history)
/// and eight standard error fields, newest first; the EMCY service owns them all.
pub const ERROR_HISTORY: [Entry; 9] = {
    const NAMES: [&str; 9] = [
        "Pre-defined error field: number of errors",
        "Standard error field 1",
        "Standard error field 2",
        "Standard error field 3",
        "Standard error field 4",
        "Standard error field 5",
        "Standard error field 6",
        "Standard error field 7",
        "Standard error field 8",
    ];
    let _ = &NAMES; // only the `names` feature keeps them
    let mut out = [BLANK; 9];
    let mut i = 0;
    while i < 9 {
        out[i] = Entry {
            index: 0x1003,
            sub: i as u8,
            #[cfg(feature = "names")]
            name: NAMES[i],
            ty: if i == 0 {
                DataType::Unsigned8
            } else {
                DataType::Unsigned32
            },
            access: if i == 0 { Access::Rw } else { Access::Ro },
            pdo: false,
            default: if i == 0 {
                DefaultValue::Const(0)
            } else {
                DefaultValue::Live
            },
            range: if i == 0 {
                &Range::MinMax(0, 0)
            } else {
                &Range::Any
            },
            group: Group::Volatile,
            hook: Hook::None, // `cia301::attach`
        };
        i += 1;
    }
    out
};

/// `entries` with `hook` on every sub-index but 0 (a per-channel array whose channel
/// entries one service rule covers).
pub const fn hooked<const N: usize>(mut entries: [Entry; N], hook: Hook) -> [Entry; N] {
    let mut i = 0;
    while i < N {
        if entries[i].sub != 0 {
            entries[i].hook = hook;
        }
        i += 1;
    }
    entries
}

/// The search keys of a table ([`Entry::key`] of each entry, in order).
pub const fn keys<const N: usize>(t: &[Entry; N]) -> [u32; N] {
    let mut out = [0u32; N];
    let mut i = 0;
    while i < N {
        out[i] = t[i].key();
        i += 1;
    }
    out
}

/// Number of entries in all `parts`.
pub const fn total(parts: &[&[Entry]]) -> usize {
    let mut n = 0;
    let mut i = 0;
    while i < parts.len() {
        n += parts[i].len();
        i += 1;
    }
    n
}

/// The `parts` one after the other (`N` must be [`total`] of them).
pub const fn concat<const N: usize>(parts: &[&[Entry]]) -> [Entry; N] {
    let mut out = [BLANK; N];
    let mut k = 0;
    let mut i = 0;
    while i < parts.len() {
        let mut j = 0;
        while j < parts[i].len() {
            out[k] = parts[i][j];
            k += 1;
            j += 1;
        }
        i += 1;
    }
    assert!(k == N, "table size mismatch");
    out
}

/// Number of entries of `t` that storage keeps (every group but volatile).
pub const fn stored(t: &[Entry]) -> usize {
    let mut n = 0;
    let mut i = 0;
    while i < t.len() {
        if !matches!(t[i].group, Group::Volatile) {
            n += 1;
        }
        i += 1;
    }
    n
}

/// Whether a storage image holds `t`'s stored entries beside the node's and the
/// application's records ([`canpos_stack::config::RECORDS_MAX`]; `CANPOS_MAX_STORED` in a
/// firmware build).
pub const fn fits_storage(t: &[Entry]) -> bool {
    use canpos_stack::config::{APP_RECORDS, NODE_RECORDS, RECORDS_MAX};
    stored(t) + NODE_RECORDS + APP_RECORDS <= RECORDS_MAX
}

/// Whether a table is strictly sorted by index and sub-index (the dictionary's binary
/// search needs it) and fits the dictionary's value array.
pub const fn valid(t: &[Entry]) -> bool {
    if t.len() > canpos_stack::od::MAX_ENTRIES {
        return false;
    }
    let mut i = 1;
    while i < t.len() {
        if t[i - 1].key() >= t[i].key() {
            return false;
        }
        i += 1;
    }
    true
}

/// The names of a per-channel array: sub 0 ("…: number of channels") and one per channel.
macro_rules! chnames {
    ($base:literal; $($n:literal),*) => {
        [concat!($base, ": number of channels"), $(concat!($base, " channel ", $n)),*]
    };
}
pub(crate) use chnames;

/// The names of TPDO `n`'s communication record (subs 0, 1, 2, 3, 5).
macro_rules! tpdo_comm_names {
    ($n:literal) => {
        [
            concat!("TPDO", $n, " communication parameter: highest sub-index"),
            concat!("TPDO", $n, " COB-ID"),
            concat!("TPDO", $n, " transmission type"),
            concat!("TPDO", $n, " inhibit time"),
            concat!("TPDO", $n, " event timer"),
        ]
    };
}
pub(crate) use tpdo_comm_names;

/// The names of TPDO `n`'s mapping record (sub 0 and up to 8 entries).
macro_rules! tpdo_map_names {
    ($n:literal) => {
        [
            concat!("TPDO", $n, " mapping parameter: number of mapped objects"),
            concat!("TPDO", $n, " mapped object 1"),
            concat!("TPDO", $n, " mapped object 2"),
            concat!("TPDO", $n, " mapped object 3"),
            concat!("TPDO", $n, " mapped object 4"),
            concat!("TPDO", $n, " mapped object 5"),
            concat!("TPDO", $n, " mapped object 6"),
            concat!("TPDO", $n, " mapped object 7"),
            concat!("TPDO", $n, " mapped object 8"),
        ]
    };
}
pub(crate) use tpdo_map_names;

/// The CiA 406 cams and work areas of a four-channel unit with threshold cams (one low limit
/// per cam, 0x6310–0x6313), as the TH's and the E-Series' tables both have them. The TMI's
/// window cams (high limits, hysteresis) are its own.
#[cfg(any(feature = "th", feature = "e-series"))]
#[rustfmt::skip]
const THRESHOLD_CAM_PARTS: &[&[Entry]] = {
    use canpos_encoder::{hook, param};
    use canpos_stack::od::{Access::{Ro, Rw}, DataType::*, DefaultValue::*, Group::*, Hook, Range::Any};
    &[
        &channels::<5>(0x6300, chnames!("Cam state"; 1, 2, 3, 4), Unsigned8, Ro, true, Live, &Any, Volatile),
        &hooked(channels::<5>(0x6301, chnames!("Cam enable"; 1, 2, 3, 4), Unsigned8, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_SWITCH)),
        &hooked(channels::<5>(0x6302, chnames!("Cam polarity"; 1, 2, 3, 4), Unsigned8, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_SWITCH)),
        &hooked(channels::<5>(0x6310, chnames!("Cam1 low limit"; 1, 2, 3, 4), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
        &hooked(channels::<5>(0x6311, chnames!("Cam2 low limit"; 1, 2, 3, 4), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
        &hooked(channels::<5>(0x6312, chnames!("Cam3 low limit"; 1, 2, 3, 4), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
        &hooked(channels::<5>(0x6313, chnames!("Cam4 low limit"; 1, 2, 3, 4), Integer32, Rw, false, Const(0), &Any, App), Hook::app(hook::CAM_LIMIT)),
        &channels::<5>(0x6400, chnames!("Work area state"; 1, 2, 3, 4), Unsigned8, Ro, true, Live, &Any, Volatile),
        &hooked(channels::<5>(0x6401, chnames!("Work area low limit"; 1, 2, 3, 4), Integer32, Rw, false, Param(param::MIN_POSITION), &Any, App), Hook::app(hook::WORK_AREA_LIMIT)),
        &hooked(channels::<5>(0x6402, chnames!("Work area high limit"; 1, 2, 3, 4), Integer32, Rw, false, Param(param::MAX_POSITION), &Any, App), Hook::app(hook::WORK_AREA_LIMIT)),
    ]
};

/// [`THRESHOLD_CAM_PARTS`] as one part of a model's table.
#[cfg(any(feature = "th", feature = "e-series"))]
pub(crate) const THRESHOLD_CAMS_AND_WORK_AREAS: [Entry; total(THRESHOLD_CAM_PARTS)] =
    concat(THRESHOLD_CAM_PARTS);
