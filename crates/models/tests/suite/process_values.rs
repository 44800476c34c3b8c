//! `Node::write_process_value`: a device's own process writes an object (an input it read),
//! as an application's cycle writes its live values. The entry's type, size and range hold as
//! for an SDO write, access does not (a read-only input is the process's), an object a
//! service owns or a constant is refused, a refused value changes nothing, and a changed value is a
//! change-of-state event for the asynchronous TPDO that maps it (CiA 301 §7.5.2.35,
//! transmission type 254 / 255). On a plain device of its own (node-id 1): the sensors' inputs
//! are all the application's.

use canpos_models::th::TH;
use canpos_stack::model::{CommConfig, Features, Model, Table};
use canpos_stack::od::{cia301, DefaultValue::*, Entry, Param};
use canpos_stack::storage::RamStorage;
use canpos_stack::{entry, Abort, Frame, Instant, Node, Plain};

#[rustfmt::skip]
const ENTRIES: [Entry; 22] = cia301::attach([
    entry!(0x1000, 0, "", Unsigned32, Ro, Const(0x000F_0191)),
    entry!(0x1001, 0, "", Unsigned8, Ro, Live),
    entry!(0x1017, 0, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1018, 0, "", Unsigned8, Const, Const(4)),
    entry!(0x1018, 1, "", Unsigned32, Const, Const(0)),
    entry!(0x1018, 2, "", Unsigned32, Const, Const(0)),
    entry!(0x1018, 3, "", Unsigned32, Const, Const(0)),
    entry!(0x1018, 4, "", Unsigned32, Ro, Param(Param::SerialNumber)),
    entry!(0x1800, 0, "", Unsigned8, Const, Const(5)),
    entry!(0x1800, 1, "", Unsigned32, Rw, NodeId(0x180), Any, Comm),
    entry!(0x1800, 2, "", Unsigned8, Rw, Const(0xFF), Any, Comm),
    entry!(0x1800, 3, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1800, 5, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1A00, 0, "", Unsigned8, Rw, Const(2), Any, Comm),
    entry!(0x1A00, 1, "", Unsigned32, Rw, Const(0x6000_0108), Any, Comm),
    entry!(0x1A00, 2, "", Unsigned32, Rw, Const(0x6401_0110), Any, Comm),
    entry!(0x2000, 0, "", Unsigned32, Ro, Const(0)),
    entry!(0x6000, 1, "", Unsigned8, Ro, Const(0), Any, Volatile, true),
    entry!(0x6200, 1, "", Unsigned8, Rw, Const(0), Any, Volatile, true),
    entry!(0x6401, 1, "", Integer16, Ro, Const(0), MinMax(0xFFFF_FF9C, 100), Volatile, true),
    entry!(0x6423, 0, "", Boolean, Ro, Const(0)),
    // A constant of the profile area (never changes, not even by the process).
    entry!(0x6500, 0, "", Unsigned8, Const, Const(16)),
]);

fn param(cfg: &CommConfig, p: Param) -> u32 {
    match p {
        Param::SerialNumber => cfg.serial,
        _ => 0,
    }
}

/// The device, built once per test (a model lives as long as the process).
fn model() -> &'static Model {
    Box::leak(Box::new(Model {
        table: Table {
            name: "process-values",
            product: "",
            vendor: "",
            entries: &ENTRIES,
            keys: Box::leak(ENTRIES.iter().map(Entry::key).collect()),
            // One TPDO; the rest as a sensor's (whatever later fields the stack adds).
            features: Features {
                tag: 0x51,
                tpdos: 1,
                power_on_emcy: false,
                ..TH.table.features
            },
        },
        profile: (),
        variant: None,
        param,
        derive: |c| c,
        default_config: CommConfig {
            node_id: 1,
            bitrate_kbps: 125,
            serial: 1,
        },
    }))
}

fn t(us: u64) -> Instant {
    Instant::from_micros(us)
}

/// Powered on and booted at t = 0, operational when `start`.
fn node(start: bool) -> Node<Plain, RamStorage> {
    let m = model();
    let mut n = Node::with_app(m, m.default_config, Plain, RamStorage::default());
    n.power_on(t(0));
    if start {
        n.handle_frame(&Frame::new(0, &[1, 1]).unwrap(), t(0));
    }
    sent(&mut n, 0);
    n
}

fn sent(n: &mut Node<Plain, RamStorage>, us: u64) -> Vec<Frame> {
    std::iter::from_fn(|| n.poll(t(us))).collect()
}

#[test]
fn a_changed_input_is_a_change_of_state_event_for_its_tpdo() {
    let mut n = node(true);
    assert_eq!(n.write_process_value(0x6000, 1, 0x5A, t(10)), Ok(true));
    let f = sent(&mut n, 10);
    assert_eq!(f.len(), 1, "{f:?}");
    assert_eq!(
        (f[0].std_id(), f[0].data()),
        (Some(0x181), &[0x5A, 0, 0][..])
    );
    // The same value is no change: nothing goes out.
    assert_eq!(n.write_process_value(0x6000, 1, 0x5A, t(20)), Ok(false));
    assert!(sent(&mut n, 20).is_empty());
    // A signed value in its bytes (−100, the low limit).
    assert_eq!(n.write_process_value(0x6401, 1, 0xFF9C, t(30)), Ok(true));
    let f = sent(&mut n, 30);
    assert_eq!(f.len(), 1, "{f:?}");
    assert_eq!(f[0].data(), &[0x5A, 0x9C, 0xFF]);
    assert_eq!(n.read_object(0x6401, 1), Ok(0xFF9C));
    // Access does not count: the process may write what the master also writes.
    assert_eq!(n.write_process_value(0x6200, 1, 7, t(40)), Ok(true));
    assert_eq!(n.read_object(0x6200, 1), Ok(7));
    assert!(sent(&mut n, 40).is_empty(), "0x6200 is in no TPDO");
}

#[test]
fn pre_operational_the_value_is_kept_and_no_pdo_goes_out() {
    let mut n = node(false);
    assert_eq!(n.write_process_value(0x6000, 1, 3, t(10)), Ok(true));
    assert!(sent(&mut n, 10).is_empty());
    assert_eq!(n.read_object(0x6000, 1), Ok(3));
    // Off, the node takes nothing.
    n.power_off();
    assert_eq!(n.write_process_value(0x6000, 1, 4, t(20)), Ok(false));
    assert_eq!(n.device().od().value(0x6000, 1), Some(3));
}

#[test]
fn a_value_the_entry_cannot_hold_is_refused_and_changes_nothing() {
    let mut n = node(true);
    let cases = [
        (0x6001, 0, 1, Abort::NoObject),
        (0x6000, 2, 1, Abort::NoSub),
        // Beyond the type's bytes.
        (0x6000, 1, 0x100, Abort::InvalidValue),
        (0x6401, 1, 0x1_0000, Abort::InvalidValue),
        // The entry's range.
        (0x6401, 1, 101, Abort::ValueTooHigh),
        (0x6401, 1, 0xFF9B, Abort::ValueTooLow),
        (0x6423, 0, 2, Abort::InvalidValue),
        // Objects a service owns.
        (0x1017, 0, 100, Abort::UnsupportedAccess),
        (0x1800, 2, 1, Abort::UnsupportedAccess),
        (0x1A00, 1, 0x6000_0108, Abort::UnsupportedAccess),
        (0x1001, 0, 1, Abort::UnsupportedAccess),
        // A constant (`Access::Const`: it never changes).
        (0x6500, 0, 8, Abort::ReadOnly),
    ];
    for (i, s, raw, abort) in cases {
        let before = n.device().od().value(i, s);
        assert_eq!(
            n.write_process_value(i, s, raw, t(10)),
            Err(abort),
            "{i:04X}/{s}"
        );
        assert_eq!(n.device().od().value(i, s), before, "{i:04X}/{s}");
        assert!(sent(&mut n, 10).is_empty(), "{i:04X}/{s}");
    }
    assert_eq!(n.write_process_value(0x6423, 0, 1, t(20)), Ok(true));
    // The application area starts at 0x2000; a 32-bit value takes all its bits.
    assert_eq!(n.write_process_value(0x2000, 0, u32::MAX, t(30)), Ok(true));
    assert_eq!(n.read_object(0x2000, 0), Ok(u32::MAX));
}
