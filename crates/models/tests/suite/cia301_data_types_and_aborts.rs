//! CiA 301 §7.1 basic data types (sizes, EDS codes, value ranges), the access attributes, an
//! entry's value checks, and the SDO abort codes of §7.2.4.3.17 (Table 22) with their meanings.

use canpos_stack::od::{Access, DataType, DefaultValue, Entry, Group, Hook, Range};
use canpos_stack::Abort;

const ALL_TYPES: [DataType; 9] = [
    DataType::Boolean,
    DataType::Integer8,
    DataType::Integer16,
    DataType::Integer32,
    DataType::Unsigned8,
    DataType::Unsigned16,
    DataType::Unsigned32,
    DataType::VisibleString,
    DataType::Domain,
];

/// §7.1.4 / CiA 306 data type indices, sizes (bytes, bits for PDO mapping), signedness and
/// natural ranges; strings and domains have no fixed size.
#[test]
fn cia301_7_1_basic_data_types() {
    type Row = (u16, Option<usize>, u8, bool, (i64, i64));
    let table: [Row; 9] = [
        (0x0001, Some(1), 8, false, (0, 1)),
        (0x0002, Some(1), 8, true, (-128, 127)),
        (0x0003, Some(2), 16, true, (-32768, 32767)),
        (0x0004, Some(4), 32, true, (-2_147_483_648, 2_147_483_647)),
        (0x0005, Some(1), 8, false, (0, 255)),
        (0x0006, Some(2), 16, false, (0, 65535)),
        (0x0007, Some(4), 32, false, (0, 4_294_967_295)),
        (0x0009, None, 0, false, (0, 4_294_967_295)),
        (0x000F, None, 0, false, (0, 4_294_967_295)),
    ];
    for (ty, (code, size, bits, signed, range)) in ALL_TYPES.into_iter().zip(table) {
        assert_eq!(ty.code(), code, "{ty:?}");
        assert_eq!(ty.size(), size, "{ty:?}");
        assert_eq!(ty.bits(), bits, "{ty:?}");
        assert_eq!(ty.is_signed(), signed, "{ty:?}");
        assert_eq!(ty.natural_range(), range, "{ty:?}");
    }
}

/// Signed values are stored as two's complement in their own width and read sign-extended.
#[test]
fn cia301_7_1_4_signed_values_are_twos_complement_of_their_width() {
    assert_eq!(DataType::Integer8.to_i64(0xFF), -1);
    assert_eq!(DataType::Integer8.to_i64(0x7F), 127);
    assert_eq!(
        DataType::Integer8.to_i64(0x1_80),
        -128,
        "only the low byte counts"
    );
    assert_eq!(DataType::Integer16.to_i64(0xFFFE), -2);
    assert_eq!(DataType::Integer16.to_i64(0x7FFF), 32767);
    assert_eq!(DataType::Integer16.to_i64(0x1_8000), -32768);
    assert_eq!(DataType::Integer32.to_i64(0xFFFF_FFFD), -3);
    assert_eq!(DataType::Integer32.to_i64(0x7FFF_FFFF), 2_147_483_647);
    assert_eq!(DataType::Unsigned32.to_i64(0xFFFF_FFFF), 4_294_967_295);
    assert_eq!(DataType::Unsigned8.to_i64(0x1FF), 0x1FF);
    assert_eq!(DataType::Boolean.to_i64(2), 2);
}

/// ro / const read only, wo write only, rw both; the EDS keywords are CiA 306's.
#[test]
fn cia301_access_attributes() {
    for (a, r, w, eds) in [
        (Access::Ro, true, false, "ro"),
        (Access::Wo, false, true, "wo"),
        (Access::Rw, true, true, "rw"),
        (Access::Const, true, false, "const"),
    ] {
        assert_eq!((a.readable(), a.writable(), a.eds()), (r, w, eds), "{a:?}");
    }
}

fn entry(index: u16, sub: u8, ty: DataType, range: Range) -> Entry {
    Entry::build(
        index,
        sub,
        "test object",
        ty,
        Access::Rw,
        false,
        DefaultValue::Const(0),
        Box::leak(Box::new(range)),
        Group::App,
    )
}

/// A written value must lie in the type's range and in the entry's declared range (signed
/// types compared as signed); "too high" / "too low" (0x06090031 / 32) name the side of a
/// declared minimum / maximum it misses.
#[test]
fn cia301_written_values_lie_in_the_type_and_the_declared_range() {
    let u8any = entry(0x2000, 0, DataType::Unsigned8, Range::Any);
    assert!(u8any.accepts(0) && u8any.accepts(255));
    assert!(!u8any.accepts(256), "beyond UNSIGNED8");
    let b = entry(0x2000, 1, DataType::Boolean, Range::Any);
    assert!(b.accepts(0) && b.accepts(1) && !b.accepts(2));

    let i8r = entry(0x2001, 0, DataType::Integer8, Range::between(-5, 5));
    for (raw, ok) in [
        (0xFB, true),
        (0xFA, false),
        (0, true),
        (5, true),
        (6, false),
        (0x7F, false),
        (0x80, false),
    ] {
        assert_eq!(i8r.accepts(raw), ok, "{raw:#X}");
    }
    assert!(i8r.above_range(6) && !i8r.above_range(5) && !i8r.above_range(0xFA));
    assert!(i8r.below_range(0xFA) && !i8r.below_range(0xFB) && !i8r.below_range(6));

    let i16any = entry(0x2002, 0, DataType::Integer16, Range::Any);
    assert!(i16any.accepts(0x8000) && i16any.accepts(0x7FFF));

    let list = entry(0x2003, 0, DataType::Unsigned16, Range::OneOf(&[1, 10, 100]));
    assert!(list.accepts(10) && !list.accepts(11));
    assert!(
        !list.above_range(1000) && !list.below_range(0),
        "no side for a list"
    );

    let u32r = entry(
        0x2004,
        0,
        DataType::Unsigned32,
        Range::MinMax(10, 4_000_000_000),
    );
    assert!(u32r.accepts(4_000_000_000) && !u32r.accepts(4_000_000_001));
    assert!(u32r.above_range(4_000_000_001) && u32r.below_range(9));
    assert!(!u32r.accepts(9) && u32r.accepts(10));
}

/// `Entry::check` (32-bit compares) answers as the definition in 64-bit numbers does: refused
/// beyond the declared range with "too high" / "too low", else outside the type's natural range
/// or the list with "invalid value", for every type, range kind and edge value.
#[test]
fn check_answers_as_the_type_and_range_definition() {
    let types = [
        DataType::Boolean,
        DataType::Integer8,
        DataType::Integer16,
        DataType::Integer32,
        DataType::Unsigned8,
        DataType::Unsigned16,
        DataType::Unsigned32,
    ];
    let edges: Vec<u32> = [
        0u32, 1, 2, 5, 0x7F, 0x80, 0xFF, 0x100, 0x7FFF, 0x8000, 0xFFFF,
    ]
    .into_iter()
    .chain([
        0x1_0000,
        0x7FFF_FFFF,
        0x8000_0000,
        0xFFFF_FF80,
        0xFFFF_FFFB,
        u32::MAX,
    ])
    .collect();
    let lists: &'static [u32] = &[1, 0x80, 0xFFFF, 0x8000_0000];
    for ty in types {
        let mut ranges = vec![Range::Any, Range::OneOf(lists)];
        for &lo in &edges {
            for &hi in &edges {
                if ty.to_i64(lo) <= ty.to_i64(hi) {
                    ranges.push(Range::MinMax(lo, hi));
                }
            }
        }
        for range in ranges {
            let e = entry(0x2000, 0, ty, range);
            for &raw in &edges {
                let v = ty.to_i64(raw);
                let (nlo, nhi) = ty.natural_range();
                let natural = nlo <= v && v <= nhi;
                let want = match range {
                    Range::MinMax(_, hi) if v > ty.to_i64(hi) => Err(Abort::ValueTooHigh),
                    Range::MinMax(lo, _) if v < ty.to_i64(lo) => Err(Abort::ValueTooLow),
                    Range::OneOf(l) if !l.contains(&raw) => Err(Abort::InvalidValue),
                    _ if !natural => Err(Abort::InvalidValue),
                    _ => Ok(()),
                };
                assert_eq!(e.check(raw), want, "{ty:?} {range:?} {raw:#X}");
                assert_eq!(e.accepts(raw), want.is_ok());
                assert_eq!(e.above_range(raw), want == Err(Abort::ValueTooHigh));
                if want != Err(Abort::ValueTooHigh) {
                    assert_eq!(e.below_range(raw), want == Err(Abort::ValueTooLow));
                }
            }
        }
    }
}

/// D6: reset communication reloads the communication profile area 0x1000…0x1FFF only; the
/// table is sorted by `index << 8 | sub`.
#[test]
fn d6_reset_communication_covers_the_communication_area() {
    for (index, comm) in [
        (0x0FFF, false),
        (0x1000, true),
        (0x1800, true),
        (0x1FFF, true),
        (0x2000, false),
        (0x6000, false),
    ] {
        assert_eq!(
            entry(index, 0, DataType::Unsigned8, Range::Any).reset_by_comm(),
            comm,
            "{index:04X}"
        );
    }
    assert_eq!(
        entry(0x1A02, 0x05, DataType::Unsigned32, Range::Any).key(),
        0x001A_0205
    );
    let e = entry(0x1017, 0, DataType::Unsigned16, Range::Any);
    assert_eq!(e.hook, Hook::None);
    assert_eq!(e.with_hook(Hook::Heartbeat).hook, Hook::Heartbeat);
    assert_eq!((e.index, e.sub, e.ty), (0x1017, 0, DataType::Unsigned16));
}

/// Plain values and hooks that only check a write (or act instead of storing it) have nothing
/// to do once a value has landed; the services' own parameters do.
#[test]
fn hooks_that_act_after_a_write() {
    for h in [
        Hook::None,
        Hook::SyncCobId,
        Hook::EmcyCobId,
        Hook::StoreParameters,
        Hook::RestoreDefaults,
    ] {
        assert!(!h.acts_when_written(), "{h:?}");
    }
    for h in [
        Hook::Heartbeat,
        Hook::TpdoComm,
        Hook::TpdoMap,
        Hook::Guarding,
        Hook::app(0),
    ] {
        assert!(h.acts_when_written(), "{h:?}");
    }
}

/// §7.2.4.3.17 Table 22: every code the server sends, its number and its meaning.
#[test]
fn cia301_7_2_4_3_17_abort_codes() {
    let table: [(Abort, u32, &str); 29] = [
        (Abort::Toggle, 0x0503_0000, "Toggle bit not alternated"),
        (Abort::Timeout, 0x0504_0000, "SDO protocol timed out"),
        (
            Abort::InvalidCommand,
            0x0504_0001,
            "Client/server command specifier not valid or unknown",
        ),
        (Abort::BlockSize, 0x0504_0002, "Invalid block size"),
        (Abort::BlockSequence, 0x0504_0003, "Invalid sequence number"),
        (Abort::Crc, 0x0504_0004, "CRC error"),
        (Abort::OutOfMemory, 0x0504_0005, "Out of memory"),
        (
            Abort::UnsupportedAccess,
            0x0601_0000,
            "Unsupported access to an object",
        ),
        (
            Abort::WriteOnly,
            0x0601_0001,
            "Attempt to read a write only object",
        ),
        (
            Abort::ReadOnly,
            0x0601_0002,
            "Attempt to write a read only object",
        ),
        (
            Abort::NoObject,
            0x0602_0000,
            "Object does not exist in the object dictionary",
        ),
        (
            Abort::NotMappable,
            0x0604_0041,
            "Object cannot be mapped to the PDO",
        ),
        (
            Abort::MappingLength,
            0x0604_0042,
            "Number and length of mapped objects exceed PDO length",
        ),
        (
            Abort::ParamIncompatible,
            0x0604_0043,
            "General parameter incompatibility",
        ),
        (
            Abort::InternalIncompatible,
            0x0604_0047,
            "General internal incompatibility in the device",
        ),
        (
            Abort::Hardware,
            0x0606_0000,
            "Access failed due to a hardware error",
        ),
        (
            Abort::LengthMismatch,
            0x0607_0010,
            "Data type does not match, length of service parameter does not match",
        ),
        (
            Abort::LengthTooHigh,
            0x0607_0012,
            "Data type does not match, length of service parameter too high",
        ),
        (
            Abort::LengthTooLow,
            0x0607_0013,
            "Data type does not match, length of service parameter too low",
        ),
        (Abort::NoSub, 0x0609_0011, "Sub-index does not exist"),
        (
            Abort::InvalidValue,
            0x0609_0030,
            "Invalid value for parameter",
        ),
        (
            Abort::ValueTooHigh,
            0x0609_0031,
            "Value of parameter written too high",
        ),
        (
            Abort::ValueTooLow,
            0x0609_0032,
            "Value of parameter written too low",
        ),
        (
            Abort::MaxLessThanMin,
            0x0609_0036,
            "Maximum value is less than minimum value",
        ),
        (Abort::General, 0x0800_0000, "General error"),
        (
            Abort::CannotStore,
            0x0800_0020,
            "Data cannot be transferred or stored to the application",
        ),
        (
            Abort::LocalControl,
            0x0800_0021,
            "Data cannot be transferred or stored because of local control",
        ),
        (
            Abort::WrongState,
            0x0800_0022,
            "Data cannot be transferred or stored because of the present device state",
        ),
        (Abort::NoData, 0x0800_0024, "No data available"),
    ];
    assert_eq!(Abort::ALL.len(), table.len());
    for (a, code, meaning) in table {
        assert_eq!(a.code(), code, "{a:?}");
        assert_eq!(Abort::from_code(code), Some(a), "{code:08X}");
        assert_eq!(a.meaning(), meaning, "{a:?}");
        assert_eq!(a.to_string(), format!("0x{code:08X} {meaning}"));
    }
    assert_eq!(Abort::from_code(0x0504_0006), None);
    assert_eq!(Abort::from_code(0), None);
}

/// An application's hook numbers: each one its own and given back, the services' hooks none,
/// and a hook one byte (a firmware's table entry is 20 bytes because of it).
#[test]
fn app_hook_numbers_round_trip_in_one_byte() {
    for n in 0..16 {
        assert_eq!(Hook::app(n).app_number(), Some(n));
    }
    assert_ne!(Hook::app(1), Hook::app(2));
    let services = [
        (Hook::None, false),
        (Hook::ErrorHistory, false),
        (Hook::SyncCobId, false),
        (Hook::Guarding, false),
        (Hook::GuardingCobId, false),
        (Hook::StoreParameters, false),
        (Hook::RestoreDefaults, false),
        (Hook::EmcyCobId, false),
        (Hook::EmcyInhibit, false),
        (Hook::Heartbeat, false),
        (Hook::PendingNodeId, false),
        (Hook::PendingBitRate, false),
        (Hook::TpdoComm, true),
        (Hook::TpdoMap, true),
    ];
    for (h, by_service) in services {
        assert_eq!(h.app_number(), None, "{h:?}");
        assert_eq!(h.checked_by_service(), by_service, "{h:?}");
    }
    for n in 0..16 {
        assert!(Hook::app(n).checked_by_service(), "{n}");
    }
    assert_eq!(core::mem::size_of::<Hook>(), 1);
}
