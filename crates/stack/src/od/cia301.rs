//! The CiA 301 communication profile's objects and the service that owns each one: the one
//! place that gives a table's standard objects their [`Hook`].
//!
//! Every table goes through it: a product model's `const` table and a firmware's own are
//! built with [`attach`] and checked beside their definition with
//! `const _: () = assert!(cia301::hooks_complete(&TABLE));`; a table built at run time (the
//! host's EDS device) asks [`missing_hook`] before it is used. A table whose 0x1014 has no
//! [`Hook::EmcyCobId`] would accept any COB-ID, so a table that lacks a hook does not build:
//!
//! ```compile_fail,E0080
//! use canpos_stack::entry;
//! use canpos_stack::od::{cia301, DefaultValue::{Const, NodeId}, Entry, Hook};
//!
//! // 0x1014 COB-ID EMCY written without its hook (and without `cia301::attach`).
//! const TABLE: [Entry; 2] = [
//!     entry!(0x1005, 0, "", Unsigned32, Rw, Const(0x80), Any, Comm).with_hook(Hook::SyncCobId),
//!     entry!(0x1014, 0, "", Unsigned32, Rw, NodeId(0x80), Any, Comm),
//! ];
//! const _: () = assert!(cia301::hooks_complete(&TABLE));
//! ```
//!
//! The same table through [`attach`] builds:
//!
//! ```
//! use canpos_stack::entry;
//! use canpos_stack::od::{cia301, DefaultValue::{Const, NodeId}, Entry, Hook};
//!
//! const TABLE: [Entry; 2] = cia301::attach([
//!     entry!(0x1005, 0, "", Unsigned32, Rw, Const(0x80), Any, Comm),
//!     entry!(0x1014, 0, "", Unsigned32, Rw, NodeId(0x80), Any, Comm),
//! ]);
//! const _: () = assert!(cia301::hooks_complete(&TABLE));
//! assert_eq!(TABLE[1].hook, Hook::EmcyCobId);
//! ```

use super::{Entry, Hook};
use crate::config::{MAX_MAP, MAX_RPDOS, MAX_TPDOS};

/// The hook CiA 301 gives object `index` / `sub`: the service whose rules its values follow,
/// or [`Hook::None`] for a plain value (identity, counts, manufacturer and profile objects).
pub const fn hook_of(index: u16, sub: u8) -> Hook {
    const TPDO_COMM: u16 = 0x1800;
    const TPDO_MAP: u16 = 0x1A00;
    const RPDO_COMM: u16 = 0x1400;
    const RPDO_MAP: u16 = 0x1600;
    match index {
        // Sub 0 (count; writing 0 clears) and the standard error fields 1…254.
        0x1003 if sub <= 0xFE => Hook::ErrorHistory,
        0x1005 if sub == 0 => Hook::SyncCobId,
        0x100C | 0x100D if sub == 0 => Hook::Guarding,
        0x100E if sub == 0 => Hook::GuardingCobId,
        0x1010 if sub >= 1 && sub <= 0x7F => Hook::StoreParameters,
        0x1011 if sub >= 1 && sub <= 0x7F => Hook::RestoreDefaults,
        0x1014 if sub == 0 => Hook::EmcyCobId,
        0x1015 if sub == 0 => Hook::EmcyInhibit,
        0x1017 if sub == 0 => Hook::Heartbeat,
        // COB-ID, transmission type, event timer (the deadline) of each RPDO the stack has
        // (CiA 301 gives an RPDO's inhibit time and SYNC start value no meaning).
        _ if index >= RPDO_COMM
            && index < RPDO_COMM + MAX_RPDOS as u16
            && matches!(sub, 1 | 2 | 5) =>
        {
            Hook::RpdoComm
        }
        // The mapping count and its entries.
        _ if index >= RPDO_MAP
            && index < RPDO_MAP + MAX_RPDOS as u16
            && sub as usize <= MAX_MAP =>
        {
            Hook::RpdoMap
        }
        // COB-ID, transmission type, inhibit time, event timer, SYNC start value of each
        // TPDO the stack has.
        _ if index >= TPDO_COMM
            && index < TPDO_COMM + MAX_TPDOS as u16
            && matches!(sub, 1 | 2 | 3 | 5 | 6) =>
        {
            Hook::TpdoComm
        }
        // The mapping count and its entries.
        _ if index >= TPDO_MAP
            && index < TPDO_MAP + MAX_TPDOS as u16
            && sub as usize <= MAX_MAP =>
        {
            Hook::TpdoMap
        }
        _ => Hook::None,
    }
}

/// `t` with every standard object's hook ([`hook_of`]) attached; other entries unchanged.
pub const fn attach<const N: usize>(mut t: [Entry; N]) -> [Entry; N] {
    let mut i = 0;
    while i < N {
        let h = hook_of(t[i].index, t[i].sub);
        if !matches!(h, Hook::None) {
            t[i].hook = h;
        }
        i += 1;
    }
    t
}

/// The first entry of `t` whose hook is not the one CiA 301 gives it ([`hook_of`]), as
/// (index, sub), or `None` when every standard object has its hook.
pub const fn missing_hook(t: &[Entry]) -> Option<(u16, u8)> {
    let mut i = 0;
    while i < t.len() {
        let e = &t[i];
        let h = hook_of(e.index, e.sub);
        if !matches!(h, Hook::None) && h as u8 != e.hook as u8 {
            return Some((e.index, e.sub));
        }
        i += 1;
    }
    None
}

/// Whether every standard object of `t` has its hook: for `const _: () = assert!(…)` beside a
/// `const` table.
pub const fn hooks_complete(t: &[Entry]) -> bool {
    missing_hook(t).is_none()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::od::{Access, DataType, DefaultValue, Group, Range};

    /// Each rule covers the sub-indices CiA 301 gives it and no other: a sub-index beside them
    /// (a count, a manufacturer-specific sub, a sub the object does not define) is a plain value.
    #[test]
    fn each_rule_covers_its_sub_indices_only() {
        let cases = [
            (0x1003, 0, Hook::ErrorHistory),
            (0x1003, 0xFE, Hook::ErrorHistory),
            (0x1003, 0xFF, Hook::None),
            (0x1005, 0, Hook::SyncCobId),
            (0x1005, 1, Hook::None),
            (0x100C, 0, Hook::Guarding),
            (0x100C, 1, Hook::None),
            (0x100D, 0, Hook::Guarding),
            (0x100D, 1, Hook::None),
            (0x100E, 0, Hook::GuardingCobId),
            (0x100E, 1, Hook::None),
            (0x1010, 0, Hook::None),
            (0x1010, 1, Hook::StoreParameters),
            (0x1010, 0x7F, Hook::StoreParameters),
            (0x1010, 0x80, Hook::None),
            (0x1011, 0, Hook::None),
            (0x1011, 1, Hook::RestoreDefaults),
            (0x1011, 0x7F, Hook::RestoreDefaults),
            (0x1011, 0x80, Hook::None),
            (0x1014, 0, Hook::EmcyCobId),
            (0x1014, 1, Hook::None),
            (0x1015, 0, Hook::EmcyInhibit),
            (0x1015, 1, Hook::None),
            (0x1017, 0, Hook::Heartbeat),
            (0x1017, 1, Hook::None),
            (0x1800, 0, Hook::None),
            (0x1800, 1, Hook::TpdoComm),
            (0x1800, 4, Hook::None),
            (0x1800, 5, Hook::TpdoComm),
            (0x1800, 6, Hook::TpdoComm),
            (0x1800, 7, Hook::None),
            (0x1400, 0, Hook::None),
            (0x1400, 1, Hook::RpdoComm),
            (0x1400, 2, Hook::RpdoComm),
            (0x1400, 3, Hook::None),
            (0x1400, 5, Hook::RpdoComm),
            (0x1400, 6, Hook::None),
            (0x1600, 0, Hook::RpdoMap),
            (0x1600, MAX_MAP as u8, Hook::RpdoMap),
            (0x1600, MAX_MAP as u8 + 1, Hook::None),
            (0x1400 + MAX_RPDOS as u16, 1, Hook::None),
            (0x1600 + MAX_RPDOS as u16, 1, Hook::None),
            (0x13FF, 1, Hook::None),
            (0x1A00, 0, Hook::TpdoMap),
            (0x1A00, MAX_MAP as u8, Hook::TpdoMap),
            (0x1A00, MAX_MAP as u8 + 1, Hook::None),
            (0x1800 + MAX_TPDOS as u16, 1, Hook::None),
            (0x1A00 + MAX_TPDOS as u16, 1, Hook::None),
        ];
        for (index, sub, hook) in cases {
            assert_eq!(hook_of(index, sub), hook, "0x{index:04X} sub {sub}");
        }
    }

    const fn e(index: u16, sub: u8, hook: Hook) -> Entry {
        Entry {
            index,
            sub,
            #[cfg(feature = "names")]
            name: "",
            ty: DataType::Unsigned32,
            access: Access::Rw,
            pdo: false,
            default: DefaultValue::Const(0),
            range: &Range::Any,
            group: Group::Volatile,
            hook,
        }
    }

    /// The objects the issue names, each of which must not be served without its rule.
    const MUST_HOOK: [(u16, u8, Hook); 7] = [
        (0x1005, 0, Hook::SyncCobId),
        (0x100E, 0, Hook::GuardingCobId),
        (0x1010, 1, Hook::StoreParameters),
        (0x1011, 1, Hook::RestoreDefaults),
        (0x1014, 0, Hook::EmcyCobId),
        (0x1015, 0, Hook::EmcyInhibit),
        (0x1017, 0, Hook::Heartbeat),
    ];

    #[test]
    fn a_table_without_a_communication_profile_hook_is_refused() {
        for (i, &(index, sub, hook)) in MUST_HOOK.iter().enumerate() {
            assert_eq!(hook_of(index, sub), hook);
            let mut t = [
                e(0x1000, 0, Hook::None),
                e(0x1005, 0, Hook::SyncCobId),
                e(0x100E, 0, Hook::GuardingCobId),
                e(0x1010, 0, Hook::None),
                e(0x1010, 1, Hook::StoreParameters),
                e(0x1011, 1, Hook::RestoreDefaults),
                e(0x1014, 0, Hook::EmcyCobId),
                e(0x1015, 0, Hook::EmcyInhibit),
                e(0x1017, 0, Hook::Heartbeat),
                e(0x2000, 0, Hook::None),
            ];
            assert!(hooks_complete(&t));
            let slot = t
                .iter()
                .position(|x| (x.index, x.sub) == (index, sub))
                .unwrap();
            t[slot].hook = Hook::None;
            assert_eq!(missing_hook(&t), Some((index, sub)), "object {i}");
            assert!(!hooks_complete(&t), "object {i}");
            // A wrong hook is as bad as none.
            t[slot].hook = Hook::Guarding;
            if hook != Hook::Guarding {
                assert_eq!(missing_hook(&t), Some((index, sub)));
            }
            // attach repairs it.
            assert!(hooks_complete(&attach(t)));
            assert_eq!(attach(t)[slot].hook, hook);
        }
    }

    #[test]
    fn attach_leaves_plain_and_product_objects_alone() {
        let t = attach([
            e(0x1000, 0, Hook::None),
            e(0x1010, 0, Hook::None),
            e(0x1018, 1, Hook::None),
            e(0x1800, 0, Hook::None),
            e(0x1800, 4, Hook::None),
            e(0x2000, 0, Hook::PendingNodeId),
            e(0x6010, 1, Hook::app(3)),
        ]);
        let hooks: [Hook; 7] = core::array::from_fn(|i| t[i].hook);
        assert_eq!(
            hooks,
            [
                Hook::None,
                Hook::None,
                Hook::None,
                Hook::None,
                Hook::None,
                Hook::PendingNodeId,
                Hook::app(3)
            ]
        );
        // The TPDO records the stack has, and no further.
        assert_eq!(hook_of(0x1800 + MAX_TPDOS as u16 - 1, 5), Hook::TpdoComm);
        assert_eq!(hook_of(0x1800 + MAX_TPDOS as u16, 1), Hook::None);
        assert_eq!(hook_of(0x1A00, MAX_MAP as u8), Hook::TpdoMap);
        assert_eq!(hook_of(0x1A00, MAX_MAP as u8 + 1), Hook::None);
    }
}
