//! The CiA 301 / 305 stack on its own, for its size figures: canpos-stack's node with no
//! application of its own (no CiA 406), its features fixed at build time, and a minimal
//! communication dictionary, on the same board as the TH firmware. Two builds share it (the
//! crate root defines `ENTRIES` and `MODEL`):
//!
//! - `plain`: the services of CANopenNode's default configuration (`CO_config.h`) that canpos
//!   has: SDO server with segmented transfer but no block transfer, no node guarding; NMT,
//!   heartbeat, EMCY with history, SYNC, one TPDO, store / restore, LSS;
//! - `plain_full`: every CiA 301 / 305 service canpos has (also SDO block transfer and node
//!   guarding with life guarding).
//!
//! The parts carry no hooks: each build attaches the CiA 301 ones with `od::cia301::attach`
//! and checks them beside its table. docs/FIRMWARE.md says how the figures are taken.

use crate::board::{self, BoardClock, Nvm, Uart, UartCan};
use canpos_firmware::Clock;
use canpos_stack::model::{CommConfig, Features, Model, Table};
use canpos_stack::od::{DefaultValue::*, Entry, Param};
use canpos_stack::{entry, Application, Node};
use core::mem::MaybeUninit;
use embedded_can::nb::Can;

/// Identity, error register and history, SYNC (0x1000…0x1005).
#[rustfmt::skip]
pub const HEAD: [Entry; 8] = [
    entry!(0x1000, 0, "", Unsigned32, Ro, Const(0)), // no device profile
    entry!(0x1001, 0, "", Unsigned8, Ro, Live),
    entry!(0x1003, 0, "", Unsigned8, Rw, Const(0), MinMax(0, 0), Volatile),
    entry!(0x1003, 1, "", Unsigned32, Ro, Live),
    entry!(0x1003, 2, "", Unsigned32, Ro, Live),
    entry!(0x1003, 3, "", Unsigned32, Ro, Live),
    entry!(0x1003, 4, "", Unsigned32, Ro, Live),
    entry!(0x1005, 0, "", Unsigned32, Rw, Const(0x80), Any, Comm),
];

/// Node guarding and life guarding (0x100C…0x100E).
#[allow(dead_code)] // `plain_full`'s only
#[rustfmt::skip]
pub const GUARDING: [Entry; 3] = [
    entry!(0x100C, 0, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x100D, 0, "", Unsigned8, Rw, Const(0), Any, Comm),
    entry!(0x100E, 0, "", Unsigned32, Rw, NodeId(0x700), Any, Comm),
];

/// Store / restore, EMCY, heartbeat, identity object, SDO server, one TPDO, two manufacturer
/// objects (0x1010…0x2001).
#[rustfmt::skip]
pub const TAIL: [Entry; 27] = [
    entry!(0x1010, 0, "", Unsigned8, Const, Const(1)),
    entry!(0x1010, 1, "", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1011, 0, "", Unsigned8, Const, Const(1)),
    entry!(0x1011, 1, "", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1014, 0, "", Unsigned32, Rw, NodeId(0x80), Any, Comm),
    entry!(0x1015, 0, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1017, 0, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1018, 0, "", Unsigned8, Const, Const(4)),
    entry!(0x1018, 1, "", Unsigned32, Const, Const(0)),
    entry!(0x1018, 2, "", Unsigned32, Const, Const(0)),
    entry!(0x1018, 3, "", Unsigned32, Const, Const(0)),
    entry!(0x1018, 4, "", Unsigned32, Ro, Param(Param::SerialNumber)),
    entry!(0x1200, 0, "", Unsigned8, Const, Const(2)),
    entry!(0x1200, 1, "", Unsigned32, Ro, NodeId(0x600)),
    entry!(0x1200, 2, "", Unsigned32, Ro, NodeId(0x580)),
    entry!(0x1800, 0, "", Unsigned8, Const, Const(5)),
    entry!(0x1800, 1, "", Unsigned32, Rw, NodeId(0x180), Any, Comm),
    entry!(0x1800, 2, "", Unsigned8, Rw, Const(0xFE), Any, Comm),
    entry!(0x1800, 3, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1800, 5, "", Unsigned16, Rw, Const(100), Any, Comm),
    entry!(0x1A00, 0, "", Unsigned8, Rw, Const(1), Any, Comm),
    entry!(0x1A00, 1, "", Unsigned32, Rw, Const(0x1001_0008), Any, Comm),
    entry!(0x1A00, 2, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x1A00, 3, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x1A00, 4, "", Unsigned32, Rw, Const(0), Any, Comm),
    // A manufacturer object to map and store.
    entry!(0x2000, 0, "", Unsigned32, Rw, Const(0), Any, App, true),
    entry!(0x2001, 0, "", Unsigned8, Rw, Const(0), Any, App, true),
];

/// `a` then `b` (`N` = A + B): a table from the parts above, still sorted by key.
pub const fn join<const A: usize, const B: usize, const N: usize>(
    a: &[Entry; A],
    b: &[Entry; B],
) -> [Entry; N] {
    assert!(A + B == N && A > 0);
    let mut out = [a[0]; N];
    let mut i = 0;
    while i < N {
        out[i] = if i < A { a[i] } else { b[i - A] };
        i += 1;
    }
    out
}

/// The dictionary's parameters (`DefaultValue::Param`): a plain CiA 301 device, with no profile and
/// no sensor (stroke, steps, channels), has its serial number and nothing else.
fn param(cfg: &CommConfig, p: Param) -> u32 {
    match p {
        Param::SerialNumber => cfg.serial,
        _ => 0,
    }
}

fn derive(c: CommConfig) -> CommConfig {
    c
}

/// The model of a plain device with `entries`, with or without node guarding and SDO block
/// transfer.
pub const fn model(entries: &'static [Entry], guarding: bool, block: bool) -> Model {
    Model {
        table: Table {
            name: "plain",
            product: "",
            vendor: "",
            entries,
            // A host searches a key array; a firmware searches the entries.
            keys: &[],
            features: Features {
                tag: 0x50,
                tpdos: 1,
                rpdos: 0,
                sdo_segmented: true,
                sdo_block: block,
                node_guarding: guarding,
                tpdo_rtr: true,
                lss_fastscan: true,
                lss_bit_timing: &[0, 1, 2, 3, 4, 6, 7],
                bitrates: &[],
                store_preop_only: false,
                kill_signature: false,
                power_on_emcy: true,
                sync_length_emcy: false,
                emcy_on_register_change: false,
                event_timer_above_inhibit: false,
                lss_unconfigured_configures: false,
            },
        },
        profile: (),
        variant: None,
        param,
        derive,
        default_config: CommConfig {
            node_id: 1,
            bitrate_kbps: 125,
            serial: 1,
        },
    }
}

/// No application of its own, and the features of the crate's `MODEL` fixed at build time (as
/// CANopenNode's `CO_config.h` fixes its services, and as a one-model TH build fixes the
/// TH's): the stack links what this device uses.
struct PlainDevice;

impl Application for PlainDevice {
    type Sample = ();
    type Fault = core::convert::Infallible;
    type Config = CommConfig;
    type Profile = ();
    const FIXED: Option<&'static Model> = Some(&crate::MODEL);
}

type PlainNode = Node<PlainDevice, Nvm>;

#[inline(never)]
fn place() -> &'static mut PlainNode {
    static mut NODE: MaybeUninit<PlainNode> = MaybeUninit::uninit();
    // SAFETY: called once, from `run`; nothing else refers to NODE.
    unsafe {
        core::hint::black_box(&mut *core::ptr::addr_of_mut!(NODE)).write(Node::with_app(
            &crate::MODEL,
            crate::MODEL.default_config,
            PlainDevice,
            Nvm,
        ))
    }
}

/// Start-up and the main loop.
pub fn run() -> ! {
    board::paint_stack();
    let mut cp = cortex_m::Peripherals::take().unwrap_or_else(|| board::halt());
    let clock = BoardClock::start(&mut cp.SYST);
    let mut can = UartCan::new(Uart::init());
    let node = place();
    node.power_on(clock.now());
    loop {
        let now = clock.now();
        while let Ok(f) = can.receive() {
            node.handle_frame(&f, now);
        }
        while let Some(f) = node.poll(now) {
            let _ = can.transmit(&f);
        }
        board::answer_diagnostics();
        let idle = node.poll_timeout().is_none_or(|t| clock.now() < t);
        if idle && !board::rx_pending() {
            cortex_m::asm::wfi();
        }
    }
}
