//! The model tables' own rules (models/mod.rs): a per-channel array's sub 0 is its highest
//! sub-index (CiA 301 arrays), `max_channels` is that of 0x6020, models are found by their
//! command-line names and print as them.

use crate::common::Rig;
use canpos_encoder::Channels;
use canpos_models as models;

/// Indices of CiA 406 per-channel arrays (present in a model or not).
const ARRAYS: [u16; 22] = [
    0x6010, 0x6020, 0x6030, 0x6300, 0x6301, 0x6302, 0x6310, 0x6311, 0x6312, 0x6313, 0x6320, 0x6321,
    0x6322, 0x6323, 0x6330, 0x6331, 0x6332, 0x6333, 0x6400, 0x6401, 0x6402, 0x650C,
];

#[test]
fn channel_arrays_sub_0_is_the_highest_sub_index() {
    for m in models::all() {
        let mut r = Rig::booted(m);
        for index in ARRAYS {
            let subs: Vec<u8> = m
                .entries
                .iter()
                .filter(|e| e.index == index && e.sub > 0)
                .map(|e| e.sub)
                .collect();
            if subs.is_empty() {
                continue;
            }
            let highest = *subs.iter().max().unwrap() as u32;
            assert_eq!(subs.len() as u32, highest, "{m:?} {index:04X}: subs 1…n");
            assert_eq!(
                r.node.read_object(index, 0),
                Ok(highest),
                "{m:?} {index:04X}:00"
            );
        }
    }
}

#[test]
fn max_channels_is_0x6020s_channel_count() {
    for (name, ch, n) in [
        ("th", 1, 4),
        ("e-series", 1, 4),
        ("tmi", 1, 1),
        ("tmi", 2, 2),
    ] {
        let m = models::by_name(name).unwrap();
        let cfg = m.default_config.with_channels(ch);
        let mut r = Rig::booted_with(m, cfg);
        assert_eq!(models::for_unit(m, &cfg).max_channels(), n, "{name}");
        assert_eq!(r.node.read_object(0x6020, 0), Ok(n as u32), "{name}");
    }
}

#[test]
fn models_by_name_and_alias() {
    for (name, want) in [
        ("th", Some("th")),
        ("TH", Some("th")),
        ("e-series", Some("e-series")),
        ("E-Series", Some("e-series")),
        ("e", Some("e-series")),
        ("E", Some("e-series")),
        ("eseries", Some("e-series")),
        ("ESeries", Some("e-series")),
        ("tmi", Some("tmi")),
        ("Tmi", Some("tmi")),
        ("t", None),
        ("", None),
        ("e-seriesx", None),
    ] {
        assert_eq!(models::by_name(name).map(|m| m.name), want, "{name:?}");
    }
}

#[test]
fn a_model_prints_as_its_name() {
    for m in models::all() {
        assert_eq!(format!("{m:?}"), m.name);
    }
}

#[test]
fn error_history_sub_0_counts_from_0_and_the_fields_are_recorded() {
    // CiA 301 0x1003: sub 0 "number of errors", rw, default 0 (only 0 may be written, which
    // clears the history); the standard error fields are read-only and hold what the EMCY
    // service recorded, so they have no constant default.
    use canpos_stack::od::{Access, DefaultValue, Range};
    for m in models::all() {
        let h: Vec<_> = m.entries.iter().filter(|e| e.index == 0x1003).collect();
        assert_eq!(h.len(), 9, "{m:?}");
        for e in h {
            if e.sub == 0 {
                assert!(matches!(e.default, DefaultValue::Const(0)), "{m:?}");
                assert!(matches!(e.access, Access::Rw), "{m:?}");
                assert!(matches!(e.range, Range::MinMax(0, 0)), "{m:?}");
            } else {
                assert!(
                    matches!(e.default, DefaultValue::Live),
                    "{m:?} sub {}",
                    e.sub
                );
                assert!(matches!(e.access, Access::Ro), "{m:?} sub {}", e.sub);
            }
        }
    }
}

/// A declared range's raw bounds read as numbers of the entry's type: low ≤ high, both within
/// the type's natural range (a signed bound written as the raw bits of another width, such as
/// 0xD8 for −40 on an INTEGER16, would read as a different number and fail here).
#[test]
fn declared_ranges_are_numbers_of_the_entry_type() {
    for m in models::all() {
        for e in m.entries.iter() {
            let Some((lo, hi)) = e.limits() else { continue };
            let (nlo, nhi) = e.ty.natural_range();
            assert!(
                nlo <= lo && lo <= hi && hi <= nhi,
                "{m:?} {:04X}/{}: {lo}…{hi}",
                e.index,
                e.sub
            );
        }
    }
}
