//! The object dictionary as data.
//!
//! Each product model declares its dictionary once, as a sorted table of [`Entry`]s
//! (`models/`). Everything else reads that table: the SDO server's access, size and range checks,
//! PDO mapping checks, persistence (the storage group of each entry), and EDS export. The
//! current values live in a fixed array parallel to the table (one `u32` per entry), so a
//! dictionary costs that array's RAM and no allocation.

pub mod cia301;
pub(crate) mod types;

pub use types::{
    key, search_entries, Abort, Access, DataType, DefaultValue, Entry, Group, Hook, Param, Range,
};

use crate::model::Model;

pub use crate::config::MAX_ENTRIES;

/// Configuration-dependent values that [`DefaultValue::Param`] entries resolve against.
pub trait ParamSource {
    /// The value of `p` for this unit, as raw bits of the entry's type.
    fn param(&self, p: Param) -> u32;
}

/// The current values of a model's dictionary.
#[derive(Clone)]
pub struct Dictionary {
    entries: &'static [Entry],
    /// [`Table::keys`](crate::Table::keys), searched by [`Dictionary::find`] on a host
    /// ([`crate::config::INLINE_HOT_PATHS`]; a firmware searches the entries).
    keys: &'static [u32],
    values: [u32; MAX_ENTRIES],
}

impl Dictionary {
    /// A dictionary for `model`'s table (sorted by index, sub-index; at most [`MAX_ENTRIES`];
    /// on hosts with its [`Table::keys`](crate::Table::keys)) with all values zero (the node loads the defaults at
    /// its first reset).
    #[inline(always)] // as `Node::new`
    pub fn new<C, X>(model: &'static Model<C, X>) -> Self {
        let entries = model.entries;
        assert!(
            entries.len() <= MAX_ENTRIES,
            "table larger than MAX_ENTRIES"
        );
        debug_assert!(
            entries.windows(2).all(|w| w[0].key() < w[1].key()),
            "table not sorted"
        );
        if crate::config::INLINE_HOT_PATHS {
            assert!(
                model.keys.len() == entries.len()
                    && model.keys.iter().zip(entries).all(|(k, e)| *k == e.key()),
                "keys do not match the table"
            );
        }
        Dictionary {
            entries,
            keys: model.keys,
            values: [0; MAX_ENTRIES],
        }
    }

    /// The model's table.
    #[inline]
    pub fn entries(&self) -> &'static [Entry] {
        self.entries
    }

    /// Finds the slot of `index`/`sub`, with the abort code CiA 301 gives when it is missing.
    /// Out of line without the `inline-hot-paths` feature: some forty call sites then share one
    /// copy (figure: docs/FIRMWARE.md, "Build options in figures").
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn find(&self, index: u16, sub: u8) -> Result<usize, Abort> {
        let found = if crate::config::INLINE_HOT_PATHS {
            self.keys.binary_search(&key(index, sub))
        } else {
            search_entries(self.entries, key(index, sub))
        };
        match found {
            Ok(slot) => Ok(slot),
            Err(pos) => {
                let has_index = self.entries.get(pos).is_some_and(|e| e.index == index)
                    || pos > 0 && self.entries[pos - 1].index == index;
                Err(if has_index {
                    Abort::NoSub
                } else {
                    Abort::NoObject
                })
            }
        }
    }

    /// The entry in `slot`.
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn entry(&self, slot: usize) -> &'static Entry {
        &self.entries[slot]
    }

    /// Raw value of `slot`.
    #[inline]
    pub fn get(&self, slot: usize) -> u32 {
        self.values[slot]
    }

    /// Raw value of `slot` given as a `u8` (every slot fits; no bounds check).
    #[inline(always)]
    pub fn get_u8(&self, slot: u8) -> u32 {
        self.values[slot as usize]
    }

    /// Sets the raw value of `slot` without any check (the application's side: live values,
    /// values derived by services).
    #[inline]
    pub fn set(&mut self, slot: usize, raw: u32) {
        // Slots come from this table: a miss cannot happen, and ignoring one costs less flash
        // than a panic path at every call site.
        if let Some(v) = self.values.get_mut(slot) {
            *v = raw;
        }
    }

    /// Raw value of `index`/`sub`, if it exists.
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn value(&self, index: u16, sub: u8) -> Option<u32> {
        self.find(index, sub).ok().map(|s| self.values[s])
    }

    /// Sets `index`/`sub` if it exists (application side, unchecked); returns whether it did.
    #[cfg_attr(feature = "inline-hot-paths", inline)]
    #[cfg_attr(not(feature = "inline-hot-paths"), inline(never))]
    pub fn set_value(&mut self, index: u16, sub: u8, raw: u32) -> bool {
        match self.find(index, sub) {
            Ok(s) => {
                self.values[s] = raw;
                true
            }
            Err(_) => false,
        }
    }

    /// Copies the wire bytes of `slot` (little-endian, exact type size; strings as their bytes,
    /// at most 64 of them: the SDO server's buffer size) from byte `offset` on into `buf` (as
    /// much as fits); returns the bytes copied.
    #[inline]
    pub fn read_at(&self, slot: usize, offset: usize, buf: &mut [u8]) -> usize {
        const CAP: usize = crate::config::SDO_BUF_LEN;
        let e = &self.entries[slot];
        let le;
        let src: &[u8] = match e.ty.size() {
            Some(n) => {
                le = self.values[slot].to_le_bytes();
                &le[..n.min(4)]
            }
            None => match e.default {
                DefaultValue::Str(s) => s.as_bytes(),
                _ => &[],
            },
        };
        let src = &src[..src.len().min(CAP)];
        let Some(rest) = src.get(offset..) else {
            return 0;
        };
        let k = rest.len().min(buf.len());
        buf[..k].copy_from_slice(&rest[..k]);
        k
    }

    /// The size in bytes an SDO upload of `slot` has.
    pub fn size_of(&self, slot: usize) -> usize {
        let e = &self.entries[slot];
        match e.ty.size() {
            Some(n) => n,
            None => match e.default {
                DefaultValue::Str(s) => s.len(),
                _ => 0,
            },
        }
    }
}

/// Resolves the boot value of one entry.
pub fn resolve_default(e: &Entry, params: &dyn ParamSource, node_id: u8) -> u32 {
    match e.default {
        DefaultValue::Const(v) => v,
        DefaultValue::NodeId(base) => base.wrapping_add(node_id as u32),
        DefaultValue::Param(p) => params.param(p),
        DefaultValue::Str(_) | DefaultValue::Live => 0,
    }
}

/// Little-endian raw value of up to 4 bytes.
#[inline]
pub fn le_u32(data: &[u8]) -> u32 {
    // Byte by byte rather than a variable-length copy, which compiles to a memcpy call.
    let mut v = 0u32;
    for (i, &x) in data.iter().take(4).enumerate() {
        v |= u32::from(x) << (8 * i);
    }
    v
}

/// Builds [`Entry`] values tersely in tables (the product models', a firmware's own).
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
        $crate::od::Entry::build(
            $i,
            $s,
            $name,
            $crate::od::DataType::$ty,
            $crate::od::Access::$acc,
            $pdo,
            $def,
            &$crate::od::Range::$range $( ( $($r)* ) )?,
            $crate::od::Group::$grp,
        )
    };
}
