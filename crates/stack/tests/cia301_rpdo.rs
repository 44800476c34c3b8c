//! CiA 301 §7.2.2 RPDO rules and the SYNC start value (0x1800:6) as a master sees them on a
//! plain device with two RPDOs and one TPDO (node-id 5: SDO 0x605 / 0x585, RPDO1 on 0x205,
//! RPDO2 on 0x305 once valid, TPDO1 on 0x185, EMCY on 0x85), on a virtual clock. The sensors
//! have no RPDOs (issue 33 item 6), so the table is this test's own, built as a firmware's is.

use canpos_stack::model::{CommConfig, Features, Model, Table};
use canpos_stack::od::{cia301, Abort, DefaultValue::*, Entry, Hook, Param};
use canpos_stack::{entry, AppCtx, AppView, Application, Frame, Instant, Node, Plain, RamStorage};

/// The objects every layout test maps: position `k` (0…3) of a layout has its own object of
/// each size (0x2100 + 16 k + 0 / 1 / 2: UNSIGNED8 / 16 / 32), so each value can be checked.
#[rustfmt::skip]
const TABLE: [Entry; 74] = cia301::attach([
    entry!(0x1000, 0, "", Unsigned32, Ro, Const(0)),
    entry!(0x1001, 0, "", Unsigned8, Ro, Live),
    entry!(0x1003, 0, "", Unsigned8, Rw, Const(0), MinMax(0, 0), Volatile),
    entry!(0x1003, 1, "", Unsigned32, Ro, Live),
    entry!(0x1003, 2, "", Unsigned32, Ro, Live),
    entry!(0x1003, 3, "", Unsigned32, Ro, Live),
    entry!(0x1003, 4, "", Unsigned32, Ro, Live),
    entry!(0x1005, 0, "", Unsigned32, Rw, Const(0x80), Any, Comm),
    entry!(0x1010, 0, "", Unsigned8, Const, Const(2)),
    entry!(0x1010, 1, "", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1010, 2, "", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1011, 0, "", Unsigned8, Const, Const(2)),
    entry!(0x1011, 1, "", Unsigned32, Rw, Const(1), Any, Volatile),
    entry!(0x1011, 2, "", Unsigned32, Rw, Const(1), Any, Volatile),
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
    // RPDO1: asynchronous, on 0x200 + node-id, 0x2000 mapped.
    entry!(0x1400, 0, "", Unsigned8, Const, Const(5)),
    entry!(0x1400, 1, "", Unsigned32, Rw, NodeId(0x200), Any, Comm),
    entry!(0x1400, 2, "", Unsigned8, Rw, Const(255), Any, Comm),
    entry!(0x1400, 3, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1400, 5, "", Unsigned16, Rw, Const(0), Any, Comm),
    // RPDO2: synchronous (every SYNC), not valid, 0x2001 mapped.
    entry!(0x1401, 0, "", Unsigned8, Const, Const(5)),
    entry!(0x1401, 1, "", Unsigned32, Rw, NodeId(0x8000_0300), Any, Comm),
    entry!(0x1401, 2, "", Unsigned8, Rw, Const(1), Any, Comm),
    entry!(0x1401, 3, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1401, 5, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1600, 0, "", Unsigned8, Rw, Const(1), Any, Comm),
    entry!(0x1600, 1, "", Unsigned32, Rw, Const(0x2000_0008), Any, Comm),
    entry!(0x1600, 2, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x1600, 3, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x1600, 4, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x1601, 0, "", Unsigned8, Rw, Const(1), Any, Comm),
    entry!(0x1601, 1, "", Unsigned32, Rw, Const(0x2001_0010), Any, Comm),
    entry!(0x1601, 2, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x1601, 3, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x1601, 4, "", Unsigned32, Rw, Const(0), Any, Comm),
    // TPDO1: every SYNC, 0x2000 mapped, with a SYNC start value.
    entry!(0x1800, 0, "", Unsigned8, Const, Const(6)),
    entry!(0x1800, 1, "", Unsigned32, Rw, NodeId(0x180), Any, Comm),
    entry!(0x1800, 2, "", Unsigned8, Rw, Const(1), Any, Comm),
    entry!(0x1800, 3, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1800, 5, "", Unsigned16, Rw, Const(0), Any, Comm),
    entry!(0x1800, 6, "", Unsigned8, Rw, Const(0), Any, Comm),
    entry!(0x1A00, 0, "", Unsigned8, Rw, Const(1), Any, Comm),
    entry!(0x1A00, 1, "", Unsigned32, Rw, Const(0x2000_0008), Any, Comm),
    entry!(0x1A00, 2, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x1A00, 3, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x1A00, 4, "", Unsigned32, Rw, Const(0), Any, Comm),
    entry!(0x2000, 0, "", Unsigned8, Rw, Const(0), Any, App, true),
    // The application's object (its hook 0): written through `Application::written`.
    entry!(0x2001, 0, "", Unsigned16, Rw, Const(0), Any, App, true).with_hook(Hook::app(0)),
    // −100…100: a value beyond is refused as an SDO write's would be.
    entry!(0x2002, 0, "", Integer16, Rw, Const(0), MinMax(0xFF9C, 100), Volatile, true),
    entry!(0x2003, 0, "", Boolean, Rw, Const(0), Any, Volatile, true),
    // Mappable but read-only (a TPDO's, not an RPDO's), and writable but not mappable.
    entry!(0x2004, 0, "", Unsigned32, Ro, Const(0), Any, Volatile, true),
    entry!(0x2005, 0, "", Unsigned32, Rw, Const(0), Any, Volatile, false),
    entry!(0x2100, 0, "", Unsigned8, Rw, Const(0), Any, Volatile, true),
    entry!(0x2101, 0, "", Unsigned16, Rw, Const(0), Any, Volatile, true),
    entry!(0x2102, 0, "", Unsigned32, Rw, Const(0), Any, Volatile, true),
    entry!(0x2110, 0, "", Unsigned8, Rw, Const(0), Any, Volatile, true),
    entry!(0x2111, 0, "", Unsigned16, Rw, Const(0), Any, Volatile, true),
    entry!(0x2112, 0, "", Unsigned32, Rw, Const(0), Any, Volatile, true),
    entry!(0x2120, 0, "", Unsigned8, Rw, Const(0), Any, Volatile, true),
    entry!(0x2121, 0, "", Unsigned16, Rw, Const(0), Any, Volatile, true),
    entry!(0x2122, 0, "", Unsigned32, Rw, Const(0), Any, Volatile, true),
    entry!(0x2130, 0, "", Unsigned8, Rw, Const(0), Any, Volatile, true),
    entry!(0x2131, 0, "", Unsigned16, Rw, Const(0), Any, Volatile, true),
    entry!(0x2132, 0, "", Unsigned32, Rw, Const(0), Any, Volatile, true),
]);
const _: () = assert!(cia301::hooks_complete(&TABLE));

fn param(cfg: &CommConfig, p: Param) -> u32 {
    match p {
        Param::SerialNumber => cfg.serial,
        _ => 0,
    }
}

static MODEL: Model = Model {
    table: Table {
        name: "rpdo-test",
        product: "",
        vendor: "",
        entries: &TABLE,
        keys: &KEYS,
        features: Features {
            tag: 0x52,
            tpdos: 1,
            rpdos: 2,
            sdo_segmented: true,
            sdo_block: false,
            node_guarding: false,
            tpdo_rtr: false,
            lss_fastscan: false,
            lss_bit_timing: &[],
            bitrates: &[],
            store_preop_only: false,
            kill_signature: false,
            power_on_emcy: false,
            sync_length_emcy: true,
            emcy_on_register_change: false,
            event_timer_above_inhibit: false,
            lss_unconfigured_configures: false,
        },
    },
    profile: (),
    variant: None,
    param,
    derive: |c| c,
    default_config: CommConfig {
        node_id: 5,
        bitrate_kbps: 125,
        serial: 1,
    },
};

const KEYS: [u32; TABLE.len()] = {
    let mut k = [0; TABLE.len()];
    let mut i = 0;
    while i < k.len() {
        k[i] = TABLE[i].key();
        i += 1;
    }
    k
};

const RPDO1: u16 = 0x205;
const RPDO2: u16 = 0x305;
const TPDO1: u16 = 0x185;
const EMCY: u16 = 0x85;

struct Rig {
    node: Node<Plain, RamStorage>,
    now: Instant,
    frames: Vec<Frame>,
}

impl Rig {
    fn new() -> Rig {
        let mut node = Node::new(&MODEL, MODEL.default_config, RamStorage::default());
        node.power_on(Instant::ZERO);
        let mut r = Rig {
            node,
            now: Instant::ZERO,
            frames: Vec::new(),
        };
        r.drain();
        r.take();
        r
    }

    fn operational() -> Rig {
        let mut r = Rig::new();
        r.nmt(0x01);
        r
    }

    fn nmt(&mut self, cs: u8) {
        self.send(0x000, &[cs, 5]);
    }

    fn drain(&mut self) {
        while let Some(f) = self.node.poll(self.now) {
            self.frames.push(f);
        }
    }

    fn send(&mut self, id: u16, data: &[u8]) {
        let f = Frame::new(id, data).unwrap();
        self.node.handle_frame(&f, self.now);
        self.drain();
    }

    fn sync(&mut self, counter: Option<u8>) {
        match counter {
            Some(c) => self.send(0x80, &[c]),
            None => self.send(0x80, &[]),
        }
    }

    /// Advances the clock 1 ms at a time, serving every deadline as a host loop would.
    fn advance_ms(&mut self, ms: u64) {
        for _ in 0..ms {
            self.now = Instant::from_micros(self.now.micros() + 1000);
            self.drain();
        }
    }

    fn take(&mut self) -> Vec<Frame> {
        std::mem::take(&mut self.frames)
    }

    /// The EMCY error codes sent since the last `take`, in order.
    fn emcys(&mut self) -> Vec<u16> {
        self.take()
            .iter()
            .filter(|f| f.std_id() == Some(EMCY))
            .map(|f| u16::from_le_bytes([f.data()[0], f.data()[1]]))
            .collect()
    }

    /// Expedited download of `size` bytes: the abort code when refused.
    fn download(&mut self, index: u16, sub: u8, v: u32, size: usize) -> Result<(), u32> {
        let cs = 0x23 | ((4 - size as u8) << 2);
        let [i0, i1] = index.to_le_bytes();
        let [v0, v1, v2, v3] = v.to_le_bytes();
        self.send(0x605, &[cs, i0, i1, sub, v0, v1, v2, v3]);
        let frames = self.take();
        let a = frames
            .iter()
            .find(|f| f.std_id() == Some(0x585))
            .expect("SDO answer");
        match a.data()[0] {
            0x60 => Ok(()),
            0x80 => Err(u32::from_le_bytes(a.data()[4..8].try_into().unwrap())),
            c => panic!("SDO answer {c:02X}"),
        }
    }

    fn read(&mut self, index: u16, sub: u8) -> u32 {
        self.node.read_object(index, sub).unwrap()
    }

    /// Maps `entries` into RPDO `n` (0-based) the manuals' way: count 0, entries, count.
    fn map(&mut self, n: u16, entries: &[u32]) {
        let mi = 0x1600 + n;
        assert_eq!(self.download(mi, 0, 0, 1), Ok(()));
        for (k, &e) in entries.iter().enumerate() {
            assert_eq!(
                self.download(mi, k as u8 + 1, e, 4),
                Ok(()),
                "entry {e:08X}"
            );
        }
        assert_eq!(self.download(mi, 0, entries.len() as u32, 1), Ok(()));
    }
}

const NOT_MAPPABLE: u32 = 0x0604_0041;
const MAPPING_LENGTH: u32 = 0x0604_0042;
const NO_OBJECT: u32 = 0x0602_0000;
const INVALID_VALUE: u32 = 0x0609_0030;
const UNSUPPORTED: u32 = 0x0601_0000;

/// One position of a generated layout: an object of 1, 2 or 4 bytes, or a dummy entry of one
/// (CiA 301 §7.4.7.1: the data-type indices 0x0005–0x0007 as dummies; 0x0002–0x0004 below).
#[derive(Clone, Copy, Debug)]
enum Slot {
    Object(u8),
    Dummy(u8),
}

impl Slot {
    const ALL: [Slot; 6] = [
        Slot::Object(1),
        Slot::Object(2),
        Slot::Object(4),
        Slot::Dummy(1),
        Slot::Dummy(2),
        Slot::Dummy(4),
    ];
    fn bytes(self) -> usize {
        match self {
            Slot::Object(b) | Slot::Dummy(b) => b.into(),
        }
    }
    fn object(k: usize, bytes: u8) -> u16 {
        0x2100 + 16 * k as u16 + u16::from(bytes / 2)
    }
    fn entry(self, k: usize) -> u32 {
        match self {
            Slot::Object(b) => (u32::from(Slot::object(k, b)) << 16) | (u32::from(b) * 8),
            // Unsigned (0x0005…7) at even positions, signed (0x0002…4) at odd ones.
            Slot::Dummy(b) => {
                let unsigned = [0, 5, 6, 0, 7][usize::from(b)];
                let index = if k.is_multiple_of(2) {
                    unsigned
                } else {
                    unsigned - 3
                };
                (index << 16) | (u32::from(b) * 8)
            }
        }
    }
}

/// Every layout of one to four entries (objects and dummies of each size) that fits a frame.
fn layouts() -> Vec<Vec<Slot>> {
    let mut out = Vec::new();
    for n in 1..=4u32 {
        for code in 0..6usize.pow(n) {
            let l: Vec<Slot> = (0..n)
                .map(|k| Slot::ALL[code / 6usize.pow(k) % 6])
                .collect();
            if l.iter().map(|s| s.bytes()).sum::<usize>() <= 8 {
                out.push(l);
            }
        }
    }
    out
}

/// §7.2.2 / §7.5.2.36: each mapped object takes its bytes of the received data in mapping
/// order (little-endian), a dummy entry's bytes are skipped; a PDO shorter than its mapping is
/// not processed (EMCY 0x8210, until a PDO of the right length); a longer one is processed
/// with its first bytes (EMCY 0x8220, D24). Every layout of up to four entries.
#[test]
fn cia301_7_2_2_every_layout_of_up_to_four_entries_lands_its_bytes() {
    let all = layouts();
    assert_eq!(all.len(), 6 + 36 + 160 + 512, "layouts of ≤ 8 bytes");
    for l in all {
        let mut r = Rig::operational();
        let entries: Vec<u32> = l.iter().enumerate().map(|(k, s)| s.entry(k)).collect();
        r.map(0, &entries);
        let len: usize = l.iter().map(|s| s.bytes()).sum();
        // Distinct non-zero bytes.
        let data: Vec<u8> = (0..8).map(|i| 0x11 * (i as u8 + 1)).collect();
        let expect = |r: &mut Rig, data: &[u8], ctx: &str| {
            let mut at = 0;
            for (k, s) in l.iter().enumerate() {
                if let Slot::Object(b) = *s {
                    let mut le = [0u8; 4];
                    le[..usize::from(b)].copy_from_slice(&data[at..at + usize::from(b)]);
                    let got = r.read(Slot::object(k, b), 0);
                    assert_eq!(got, u32::from_le_bytes(le), "{l:?} {ctx}");
                }
                at += s.bytes();
            }
        };
        r.send(RPDO1, &data[..len]);
        expect(&mut r, &data, "exact");
        assert_eq!(r.emcys(), [], "{l:?}");
        // Shorter: nothing lands.
        let other: Vec<u8> = data.iter().map(|b| b ^ 0xFF).collect();
        r.send(RPDO1, &other[..len - 1]);
        expect(&mut r, &data, "short");
        assert_eq!(r.emcys(), [0x8210], "{l:?}");
        assert_eq!(r.read(0x1001, 0), 0x11, "{l:?}: communication error");
        // The right length again: processed, the error gone.
        r.send(RPDO1, &other[..len]);
        expect(&mut r, &other, "exact again");
        assert_eq!(r.emcys(), [0x0000], "{l:?}");
        if len < 8 {
            r.send(RPDO1, &data[..len + 1]);
            expect(&mut r, &data, "long");
            assert_eq!(r.emcys(), [0x8220], "{l:?}");
        }
    }
}

/// §7.5.2.36: only objects that may be mapped and written map into an RPDO; a dummy entry must
/// name its type's length; the entries fit 64 bits; entries change only while sub 0 is 0.
#[test]
fn cia301_7_5_2_36_mapping_rules() {
    let mut r = Rig::new();
    assert_eq!(r.download(0x1600, 0, 0, 1), Ok(()));
    // Read-only (mappable into a TPDO), not mappable, absent.
    assert_eq!(r.download(0x1600, 1, 0x2004_0020, 4), Err(NOT_MAPPABLE));
    assert_eq!(r.download(0x1600, 1, 0x2005_0020, 4), Err(NOT_MAPPABLE));
    assert_eq!(r.download(0x1600, 1, 0x2FFF_0008, 4), Err(NO_OBJECT));
    // Longer than the object, not whole bytes, zero bits.
    assert_eq!(r.download(0x1600, 1, 0x2000_0010, 4), Err(NOT_MAPPABLE));
    assert_eq!(r.download(0x1600, 1, 0x2001_000C, 4), Err(NOT_MAPPABLE));
    assert_eq!(r.download(0x1600, 1, 0x2001_0000, 4), Err(NOT_MAPPABLE));
    // A dummy of another length than its type, a dummy of BOOLEAN (one bit) or a sub-index.
    assert_eq!(r.download(0x1600, 1, 0x0005_0010, 4), Err(NOT_MAPPABLE));
    assert_eq!(r.download(0x1600, 1, 0x0007_0008, 4), Err(NOT_MAPPABLE));
    assert_eq!(r.download(0x1600, 1, 0x0001_0001, 4), Err(NO_OBJECT));
    assert_eq!(r.download(0x1600, 1, 0x0005_0108, 4), Err(NO_OBJECT));
    // Every dummy type at its length maps into an RPDO, never into a TPDO.
    for (i, bits) in [(2, 8), (3, 16), (4, 32), (5, 8), (6, 16), (7, 32)] {
        let e = (i << 16) | bits;
        assert_eq!(r.download(0x1600, 1, e, 4), Ok(()), "{e:08X}");
        assert_eq!(r.download(0x1A00, 0, 0, 1), Ok(()));
        assert_eq!(r.download(0x1A00, 1, e, 4), Err(NO_OBJECT), "{e:08X}");
    }
    // 72 bits are refused when counted in; entries change only while the count is 0.
    for (k, e) in [0x2102_0020u32, 0x2112_0020, 0x2100_0008]
        .iter()
        .enumerate()
    {
        assert_eq!(r.download(0x1600, k as u8 + 1, *e, 4), Ok(()));
    }
    assert_eq!(r.download(0x1600, 0, 3, 1), Err(MAPPING_LENGTH));
    assert_eq!(r.download(0x1600, 0, 5, 1), Err(MAPPING_LENGTH));
    assert_eq!(r.download(0x1600, 0, 2, 1), Ok(()));
    assert_eq!(r.download(0x1600, 1, 0x2000_0008, 4), Err(UNSUPPORTED));
    assert_eq!(r.read(0x1600, 1), 0x2102_0020);
    // An empty entry cannot be counted in.
    assert_eq!(r.download(0x1601, 0, 0, 1), Ok(()));
    assert_eq!(r.download(0x1601, 0, 2, 1), Err(NOT_MAPPABLE));
}

/// §7.5.2.35 and D10 as for TPDOs: 29-bit COB-IDs and, while valid, restricted CAN-IDs are
/// refused; a valid RPDO's CAN-ID changes only through "not valid"; transmission types
/// 241–253 are reserved.
#[test]
fn cia301_7_5_2_35_cob_id_and_transmission_type_rules() {
    let mut r = Rig::new();
    assert_eq!(r.download(0x1400, 1, 0x2000_0205, 4), Err(INVALID_VALUE));
    assert_eq!(r.download(0x1400, 1, 0x1000_0205, 4), Err(INVALID_VALUE));
    assert_eq!(r.download(0x1400, 1, 0x0000_0206, 4), Err(INVALID_VALUE));
    assert_eq!(r.download(0x1401, 1, 0x0000_0705, 4), Err(INVALID_VALUE));
    assert_eq!(r.download(0x1401, 1, 0x8000_0705, 4), Ok(()));
    assert_eq!(r.download(0x1401, 1, 0x8000_0306, 4), Ok(()));
    assert_eq!(r.download(0x1401, 1, 0x0000_0306, 4), Ok(()));
    assert_eq!(r.download(0x1400, 1, 0x8000_0205, 4), Ok(()));
    assert_eq!(r.download(0x1400, 1, 0x0000_0207, 4), Ok(()));
    for t in 241..=253u32 {
        assert_eq!(r.download(0x1400, 2, t, 1), Err(INVALID_VALUE), "{t}");
    }
    for t in [0u32, 1, 240, 254, 255] {
        assert_eq!(r.download(0x1400, 2, t, 1), Ok(()), "{t}");
    }
    // The new CAN-ID is the one received on.
    r.download(0x1400, 2, 255, 1).unwrap();
    r.nmt(0x01);
    r.send(RPDO1, &[0x42]);
    assert_eq!(r.read(0x2000, 0), 0);
    r.send(0x207, &[0x42]);
    assert_eq!(r.read(0x2000, 0), 0x42);
    // Not valid: not received.
    r.download(0x1400, 1, 0x8000_0207, 4).unwrap();
    r.send(0x207, &[0x43]);
    assert_eq!(r.read(0x2000, 0), 0x42);
}

/// §7.3.2 (NMT states): PDOs only in Operational; the SDO write rule holds in every state.
#[test]
fn cia301_7_3_2_rpdos_act_only_in_operational() {
    let mut r = Rig::new();
    r.send(RPDO1, &[7]);
    assert_eq!(r.read(0x2000, 0), 0, "pre-operational");
    r.nmt(0x01);
    r.send(RPDO1, &[8]);
    assert_eq!(r.read(0x2000, 0), 8, "operational");
    r.nmt(0x02);
    r.send(RPDO1, &[9]);
    r.nmt(0x80);
    assert_eq!(r.read(0x2000, 0), 8, "stopped");
    r.send(RPDO1, &[10]);
    assert_eq!(r.read(0x2000, 0), 8, "pre-operational again");
    // A remote frame on the CAN-ID is no PDO.
    r.nmt(0x01);
    let f = Frame::remote(u32::from(RPDO1), false, 1).unwrap();
    r.node.handle_frame(&f, r.now);
    assert_eq!(r.read(0x2000, 0), 8);
}

/// §7.2.2: a synchronous RPDO's data is applied at the next SYNC (the last received before
/// it); an asynchronous one's at once. Leaving Operational drops data not yet applied.
#[test]
fn cia301_7_2_2_synchronous_rpdos_apply_at_the_next_sync() {
    let mut r = Rig::new();
    r.download(0x1401, 1, 0x0000_0305, 4).unwrap();
    r.nmt(0x01);
    r.send(RPDO2, &[0x34, 0x12]);
    r.send(RPDO2, &[0x78, 0x56]);
    r.send(RPDO1, &[0x99]);
    assert_eq!(r.read(0x2001, 0), 0, "held until the SYNC");
    assert_eq!(r.read(0x2000, 0), 0x99, "asynchronous: at once");
    r.sync(None);
    assert_eq!(r.read(0x2001, 0), 0x5678, "the last before the SYNC");
    // Nothing received since: the next SYNC changes nothing.
    r.download(0x2001, 0, 1, 2).unwrap();
    r.sync(Some(1));
    assert_eq!(r.read(0x2001, 0), 1);
    // Data held when the node leaves Operational is dropped.
    r.send(RPDO2, &[0xAA, 0xBB]);
    r.nmt(0x80);
    r.nmt(0x01);
    r.sync(None);
    assert_eq!(r.read(0x2001, 0), 1);
    // Type 0 (acyclic synchronous) also waits for the SYNC.
    r.download(0x1401, 2, 0, 1).unwrap();
    r.send(RPDO2, &[0x02, 0x00]);
    assert_eq!(r.read(0x2001, 0), 1);
    r.sync(None);
    assert_eq!(r.read(0x2001, 0), 2);
}

/// §7.5.2.35 sub 5 for RPDOs: the event timer is a deadline. It starts with the first
/// reception (not at configuration or at entering Operational), each reception starts it
/// again; expiry raises EMCY 0x8250 once with the communication bit of the error register; the
/// next reception clears it (EMCY 0x0000).
#[test]
fn cia301_7_5_2_35_the_event_timer_is_the_rpdo_deadline() {
    let mut r = Rig::new();
    r.download(0x1400, 5, 100, 2).unwrap();
    r.nmt(0x01);
    r.advance_ms(500);
    assert_eq!(r.emcys(), [], "no deadline before the first reception");
    r.send(RPDO1, &[1]);
    r.advance_ms(99);
    r.send(RPDO1, &[2]);
    r.advance_ms(99);
    assert_eq!(r.emcys(), [], "each reception starts it again");
    r.advance_ms(1);
    assert_eq!(r.emcys(), [0x8250]);
    assert_eq!(r.read(0x1001, 0), 0x11);
    assert_eq!(r.read(0x1003, 1) & 0xFFFF, 0x8250);
    r.advance_ms(1000);
    assert_eq!(r.emcys(), [], "raised once");
    r.send(RPDO1, &[3]);
    assert_eq!(r.emcys(), [0x0000]);
    assert_eq!(r.read(0x1001, 0), 0);
    assert_eq!(r.read(0x2000, 0), 3);
    // A short PDO is no reception: the deadline passes.
    r.advance_ms(50);
    r.send(RPDO1, &[]);
    r.advance_ms(50);
    assert_eq!(r.emcys(), [0x8210, 0x8250]);
    // Leaving Operational stops the deadline; back in Operational it waits for a reception.
    r.send(RPDO1, &[4]);
    r.take();
    r.nmt(0x80);
    r.advance_ms(300);
    r.nmt(0x01);
    r.advance_ms(300);
    assert_eq!(r.emcys(), []);
    // Event timer 0: no deadline.
    r.download(0x1400, 5, 0, 2).unwrap();
    r.send(RPDO1, &[5]);
    r.advance_ms(1000);
    assert_eq!(r.emcys(), []);
}

/// §7.2.2: a value an RPDO carries is checked as an SDO write of it would be; one that would
/// be refused leaves the whole PDO unprocessed (D24).
#[test]
fn cia301_7_2_2_a_value_out_of_range_leaves_the_pdo_unprocessed() {
    let mut r = Rig::operational();
    r.map(0, &[0x2000_0008, 0x2002_0010, 0x2003_0008]);
    r.send(RPDO1, &[1, 100, 0, 1]);
    assert_eq!(
        (r.read(0x2000, 0), r.read(0x2002, 0), r.read(0x2003, 0)),
        (1, 100, 1)
    );
    // −100 fits, −101 and 101 do not; a BOOLEAN of 2 neither.
    r.send(RPDO1, &[2, 0x9C, 0xFF, 0]);
    assert_eq!(r.read(0x2002, 0), 0xFF9C);
    for bad in [[3, 0x9B, 0xFF, 0], [3, 101, 0, 0], [3, 0, 0, 2]] {
        r.send(RPDO1, &bad);
        assert_eq!(r.read(0x2000, 0), 2, "{bad:?}");
        assert_eq!(r.read(0x2002, 0), 0xFF9C, "{bad:?}");
    }
    assert_eq!(r.emcys(), []);
}

/// A value an RPDO writes is a change of a mapped object as an application event is: an
/// asynchronous TPDO that maps it is sent.
#[test]
fn an_rpdo_value_triggers_an_asynchronous_tpdo_that_maps_it() {
    let mut r = Rig::new();
    r.download(0x1800, 2, 255, 1).unwrap();
    r.nmt(0x01);
    r.take();
    r.send(RPDO1, &[0x5A]);
    let tpdos: Vec<Vec<u8>> = r
        .take()
        .iter()
        .filter(|f| f.std_id() == Some(TPDO1))
        .map(|f| f.data().to_vec())
        .collect();
    assert_eq!(tpdos, [vec![0x5A]]);
}

/// CiA 301 0x1010 / 0x1011: RPDO parameters are communication parameters, stored and
/// restored with them; a stored COB-ID pre-defined for the node-id follows it (D15).
#[test]
fn rpdo_parameters_are_stored_and_restored_as_communication_parameters() {
    let mut r = Rig::new();
    r.download(0x1400, 5, 250, 2).unwrap();
    r.download(0x1400, 2, 1, 1).unwrap();
    r.map(0, &[0x2001_0010]);
    // "save" of the communication parameters.
    r.download(0x1010, 2, 0x6576_6173, 4).unwrap();
    r.download(0x1400, 5, 0, 2).unwrap();
    r.nmt(0x81);
    r.take();
    assert_eq!(r.read(0x1400, 5), 250);
    assert_eq!(r.read(0x1400, 2), 1);
    assert_eq!(r.read(0x1600, 1), 0x2001_0010);
    // The stored parameters are in effect: synchronous, 2 bytes, deadline 250 ms.
    r.nmt(0x01);
    r.send(RPDO1, &[0x01, 0x02]);
    r.sync(None);
    assert_eq!(r.read(0x2001, 0), 0x0201);
    r.advance_ms(250);
    assert_eq!(r.emcys(), [0x8250]);
    // "load" of the communication parameters: the defaults at the next reset.
    r.download(0x1011, 2, 0x6461_6F6C, 4).unwrap();
    r.nmt(0x82);
    assert_eq!(r.read(0x1400, 5), 0);
    assert_eq!(r.read(0x1600, 1), 0x2000_0008);
}

/// CiA 301 0x1800:6: a cyclic synchronous TPDO with a SYNC start value counts from the SYNC
/// whose counter equals it; without a counter in the SYNC it starts at once; 0 is no start
/// value; values above 240 are refused.
#[test]
fn cia301_sync_start_value_starts_the_count_at_its_sync_counter() {
    let sends = |r: &mut Rig, ttype: u32, start: u32, counters: &[Option<u8>]| {
        r.nmt(0x80);
        r.download(0x1800, 2, ttype, 1).unwrap();
        r.download(0x1800, 6, start, 1).unwrap();
        r.nmt(0x01);
        r.take();
        let mut at = Vec::new();
        for &c in counters {
            r.sync(c);
            if r.take().iter().any(|f| f.std_id() == Some(TPDO1)) {
                at.push(c);
            }
        }
        at
    };
    let mut r = Rig::new();
    let counted: Vec<Option<u8>> = (1..=8).map(Some).collect();
    // Every 2nd SYNC from the one counting 3: 4, 6, 8.
    assert_eq!(sends(&mut r, 2, 3, &counted), [Some(4), Some(6), Some(8)]);
    // Every SYNC from the one counting 5.
    assert_eq!(
        sends(&mut r, 1, 5, &counted),
        [Some(5), Some(6), Some(7), Some(8)]
    );
    // No start value: every 2nd SYNC from entering Operational.
    assert_eq!(
        sends(&mut r, 2, 0, &counted),
        [Some(2), Some(4), Some(6), Some(8)]
    );
    // A counter that never comes: never sent; SYNCs without a counter: at once.
    assert_eq!(sends(&mut r, 1, 9, &counted), []);
    assert_eq!(sends(&mut r, 1, 9, &[None, None]), [None, None]);
    assert_eq!(r.download(0x1800, 6, 241, 1), Err(INVALID_VALUE));
    assert_eq!(r.download(0x1800, 6, 240, 1), Ok(()));
}

/// The same table without RPDOs (a sensor's case).
static NO_RPDOS: Model = Model {
    table: Table {
        name: "rpdo-test-none",
        features: Features {
            rpdos: 0,
            ..MODEL.table.features
        },
        ..MODEL.table
    },
    ..MODEL
};

/// CiA 306 export: a device with RPDOs gives their number (`NrOfRXPDO`), their parameters as
/// RECORDs, and its writable mappable objects as `rww` (written by RPDOs); without RPDOs such an
/// object stays `ro` (CONFORMANCE EDS-01: mappable values are the device's).
#[test]
fn the_eds_lists_rpdos_and_what_they_write() {
    let eds = |m: &'static Model| {
        let mut s = String::new();
        canpos_stack::eds::write_eds(
            &mut s,
            m,
            &m.default_config,
            &canpos_stack::eds::EdsInfo::default(),
        )
        .unwrap();
        s
    };
    let access = |s: &str, sec: &str| {
        let at = s.find(&format!("[{sec}]\n")).unwrap();
        let line = s[at..]
            .lines()
            .find(|l| l.starts_with("AccessType="))
            .unwrap();
        line.to_string()
    };
    let with = eds(&MODEL);
    assert!(with.contains("\nNrOfRXPDO=2\n"));
    let at = with.find("[1401]\n").unwrap();
    assert!(with[at..].contains("ObjectType=0x9\n"));
    assert_eq!(access(&with, "2000"), "AccessType=rww");
    assert_eq!(access(&with, "2004"), "AccessType=ro");
    assert_eq!(access(&with, "2005"), "AccessType=rw");
    let without = eds(&NO_RPDOS);
    assert!(without.contains("\nNrOfRXPDO=0\n"));
    assert_eq!(access(&without, "2000"), "AccessType=ro");
}

/// What a host reads of the RPDO service: each RPDO's configuration as the dictionary sets it,
/// whether it receives, its deadline in the node's `poll_timeout`, and its timeout state.
#[test]
fn the_rpdo_service_as_a_host_sees_it() {
    let mut r = Rig::new();
    let rpdos = |r: &Rig| r.node.device().rpdos().clone();
    let s = rpdos(&r);
    assert!(!s.active());
    let (p1, p2) = (s.get(0).unwrap(), s.get(1).unwrap());
    assert!(s.get(2).is_none(), "two RPDOs in the table");
    assert!(p1.valid() && !p2.valid());
    assert_eq!(
        (p1.can_id(), p1.transmission_type(), p1.len()),
        (RPDO1, 255, 1)
    );
    assert_eq!(
        (p2.can_id(), p2.transmission_type(), p2.len()),
        (RPDO2, 1, 2)
    );
    assert!(!p1.is_empty() && !p1.timed_out());
    r.map(1, &[]);
    assert!(rpdos(&r).get(1).unwrap().is_empty());
    r.download(0x1400, 5, 40, 2).unwrap();
    r.nmt(0x01);
    assert!(rpdos(&r).active());
    assert_eq!(
        r.node.poll_timeout(),
        None,
        "no deadline before a reception"
    );
    r.advance_ms(5);
    r.send(RPDO1, &[1]);
    assert_eq!(r.node.poll_timeout(), Some(Instant::from_millis(45)));
    r.advance_ms(40);
    assert!(rpdos(&r).get(0).unwrap().timed_out());
    assert_eq!(r.node.poll_timeout(), None);
}

/// Two RPDOs past their deadlines: EMCY 0x8250 stays until neither is timed out; type 240 is
/// synchronous (applied at the SYNC).
#[test]
fn cia301_7_5_2_35_the_timeout_clears_when_every_rpdo_receives_again() {
    let mut r = Rig::new();
    r.download(0x1401, 1, 0x0000_0305, 4).unwrap();
    r.download(0x1401, 2, 240, 1).unwrap();
    r.download(0x1400, 5, 10, 2).unwrap();
    r.download(0x1401, 5, 10, 2).unwrap();
    r.nmt(0x01);
    r.send(RPDO1, &[1]);
    r.send(RPDO2, &[2, 0]);
    assert_eq!(r.read(0x2001, 0), 0, "type 240: held for the SYNC");
    r.sync(None);
    assert_eq!(r.read(0x2001, 0), 2);
    r.advance_ms(20);
    assert_eq!(r.emcys(), [0x8250]);
    r.send(RPDO1, &[3]);
    assert_eq!(r.emcys(), [], "RPDO2 is still late");
    assert_eq!(r.read(0x1001, 0), 0x11);
    r.send(RPDO2, &[4, 0]);
    assert_eq!(r.emcys(), [0x0000]);
}

/// A stored RPDO parameter passes the same rule as an SDO write of it before it is loaded; one
/// that fails keeps its default (a restricted or 29-bit COB-ID, a reserved type, a mapping of a
/// read-only object).
#[test]
fn a_stored_rpdo_parameter_is_loaded_only_if_a_write_could_set_it() {
    use canpos_stack::storage::{ImageWriter, Storage, IMAGE_MAX};
    let boot = |records: &[(u16, u8, u32)]| {
        let mut image = [0u8; IMAGE_MAX];
        let mut w = ImageWriter::new(&mut image, MODEL.features.tag);
        for &(index, sub, v) in records {
            assert!(w.push((u32::from(index) << 8) | u32::from(sub), v));
        }
        let n = w.finish();
        let mut ram = RamStorage::default();
        ram.save(&image[..n]).unwrap();
        let mut node: Node<Plain, RamStorage> = Node::new(&MODEL, MODEL.default_config, ram);
        node.power_on(Instant::ZERO);
        [(0x1400, 1), (0x1400, 2), (0x1400, 5), (0x1600, 1)]
            .map(|(i, s)| node.read_object(i, s).unwrap())
    };
    let defaults = [0x205, 255, 0, 0x2000_0008];
    assert_eq!(boot(&[]), defaults);
    assert_eq!(
        boot(&[
            (0x1400, 1, 0x8000_0333),
            (0x1400, 2, 1),
            (0x1400, 5, 77),
            (0x1600, 1, 0x2001_0010)
        ]),
        [0x8000_0333, 1, 77, 0x2001_0010]
    );
    // D15: a pre-defined COB-ID of another node-id (an image without the saved node-id) follows
    // this node's.
    assert_eq!(boot(&[(0x1400, 1, 0x8000_0207)])[0], 0x8000_0205);
    for bad in [
        (0x1400, 1, 0x0000_0705),
        (0x1400, 1, 0x2000_0205),
        (0x1400, 2, 245),
        (0x1600, 1, 0x2004_0020),
    ] {
        assert_eq!(boot(&[bad]), defaults, "{bad:X?}");
    }
}

/// An NMT command that leaves the node in Operational (start again, a guard request) changes
/// nothing for the RPDOs: held data and running deadlines stay.
#[test]
fn staying_in_operational_keeps_held_data_and_deadlines() {
    let mut r = Rig::new();
    r.download(0x1401, 1, 0x0000_0305, 4).unwrap();
    r.download(0x1400, 5, 50, 2).unwrap();
    r.nmt(0x01);
    r.send(RPDO1, &[1]);
    r.send(RPDO2, &[7, 0]);
    r.nmt(0x01);
    r.sync(None);
    assert_eq!(r.read(0x2001, 0), 7, "held data kept");
    r.advance_ms(50);
    assert_eq!(r.emcys(), [0x8250], "deadline kept");
}

/// An application that refuses 0xDEAD for its object and records what it is told was written.
#[derive(Default)]
struct Recorder {
    written: Vec<(u8, u8, u32)>,
}

impl Application for Recorder {
    type Sample = ();
    type Fault = core::convert::Infallible;
    type Config = CommConfig;
    type Profile = ();
    fn validate(&self, _h: u8, _sub: u8, raw: u32, _cx: &AppView<'_, Self>) -> Result<(), Abort> {
        if raw == 0xDEAD {
            return Err(Abort::InvalidValue);
        }
        Ok(())
    }
    fn written(&mut self, h: u8, sub: u8, raw: u32, _cx: &mut AppCtx<'_, Self>) {
        self.written.push((h, sub, raw));
    }
}

/// A value an RPDO writes reaches the application through the hooks of an SDO write: its
/// rule (a value it refuses leaves the PDO unprocessed) and `Application::written`.
#[test]
fn an_rpdo_value_reaches_the_application_as_an_sdo_write_does() {
    let mut node = Node::with_app(
        &MODEL,
        MODEL.default_config,
        Recorder::default(),
        RamStorage::default(),
    );
    node.power_on(Instant::ZERO);
    let frame = |id: u16, data: &[u8]| Frame::new(id, data).unwrap();
    node.handle_frame(
        &frame(0x605, &[0x2B, 0x01, 0x20, 0, 0x11, 0x00, 0, 0]),
        Instant::ZERO,
    );
    node.handle_frame(
        &frame(0x605, &[0x23, 0x01, 0x14, 1, 0x05, 0x03, 0, 0]),
        Instant::ZERO,
    );
    node.handle_frame(&frame(0x000, &[0x01, 5]), Instant::ZERO);
    assert_eq!(node.app_mut().written, [(0, 0, 0x11)], "the SDO write");
    // RPDO2 (synchronous) maps 0x2001: valid on 0x305 (set above), applied at the SYNC.
    node.handle_frame(&frame(RPDO2, &[0x34, 0x12]), Instant::ZERO);
    node.handle_frame(&frame(0x80, &[]), Instant::ZERO);
    assert_eq!(node.app_mut().written, [(0, 0, 0x11), (0, 0, 0x1234)]);
    node.handle_frame(&frame(RPDO2, &[0xAD, 0xDE]), Instant::ZERO);
    node.handle_frame(&frame(0x80, &[]), Instant::ZERO);
    assert_eq!(
        node.app_mut().written.len(),
        2,
        "refused by the application"
    );
    assert_eq!(node.read_object(0x2001, 0), Ok(0x1234));
}

/// A stored mapping that counts an empty entry (a state file; a write cannot set one) maps
/// nothing there: the PDO is not valid, so neither sent nor received.
#[test]
fn a_stored_mapping_of_an_empty_entry_maps_nothing() {
    use canpos_stack::storage::{ImageWriter, Storage, IMAGE_MAX};
    let mut image = [0u8; IMAGE_MAX];
    let mut w = ImageWriter::new(&mut image, MODEL.features.tag);
    for (index, sub, v) in [(0x1600u32, 1u32, 0u32), (0x1A00, 1, 0)] {
        assert!(w.push((index << 8) | sub, v));
    }
    let n = w.finish();
    let mut ram = RamStorage::default();
    ram.save(&image[..n]).unwrap();
    let mut node: Node<Plain, RamStorage> = Node::new(&MODEL, MODEL.default_config, ram);
    node.power_on(Instant::ZERO);
    assert_eq!(node.read_object(0x1600, 0), Ok(1));
    assert_eq!(node.read_object(0x1A00, 1), Ok(0));
    let d = node.device();
    assert!(!d.rpdos().get(0).unwrap().valid());
    assert!(!d.tpdos().get(0).unwrap().valid());
}

/// A reset communication forgets the RPDOs' errors with the rest of the EMCY state (CiA 301
/// 0x1001 / 0x1003: the errors are the device's present ones): a length error or a timeout
/// from before it is neither raised again by another RPDO's reception nor kept standing.
#[test]
fn a_reset_communication_ends_the_rpdo_errors() {
    // A length error of RPDO1, then the reset: RPDO2's good frame raises nothing.
    let mut r = Rig::operational();
    r.send(RPDO1, &[]);
    assert_eq!(r.emcys(), [0x8210]);
    r.nmt(0x82);
    r.take();
    r.download(0x1401, 1, 0x0000_0305, 4).unwrap();
    r.nmt(0x01);
    r.send(RPDO2, &[1, 0]);
    r.sync(None);
    assert_eq!(r.read(0x2001, 0), 1);
    assert_eq!(r.emcys(), [], "a length error from before the reset");
    assert_eq!(r.read(0x1001, 0), 0);
    // RPDO1 timed out, then the reset: RPDO2's own timeout clears at its next reception.
    let mut r = Rig::new();
    r.download(0x1400, 5, 10, 2).unwrap();
    r.nmt(0x01);
    r.send(RPDO1, &[1]);
    r.advance_ms(20);
    assert_eq!(r.emcys(), [0x8250]);
    r.nmt(0x82);
    r.download(0x1401, 1, 0x0000_0305, 4).unwrap();
    r.download(0x1401, 2, 255, 1).unwrap();
    r.download(0x1401, 5, 10, 2).unwrap();
    r.nmt(0x01);
    r.take();
    r.send(RPDO2, &[2, 0]);
    r.advance_ms(20);
    assert_eq!(r.emcys(), [0x8250]);
    r.send(RPDO2, &[3, 0]);
    assert_eq!(r.emcys(), [0x0000], "RPDO1's timeout from before the reset");
    assert_eq!(r.read(0x1001, 0), 0);
}

/// An RPDO that is no longer received (made not valid) has no deadline and no length: its
/// errors end with it, so that another RPDO's reception clears the EMCY as its own would.
#[test]
fn an_rpdo_made_not_valid_ends_its_errors() {
    let mut r = Rig::new();
    r.download(0x1401, 1, 0x0000_0305, 4).unwrap();
    r.download(0x1401, 2, 255, 1).unwrap();
    r.download(0x1400, 5, 10, 2).unwrap();
    r.download(0x1401, 5, 10, 2).unwrap();
    r.nmt(0x01);
    r.send(RPDO1, &[1]);
    r.send(RPDO2, &[2, 0]);
    r.advance_ms(20);
    assert_eq!(r.emcys(), [0x8250]);
    // RPDO2 no longer exists: RPDO1's reception ends the timeout.
    r.download(0x1401, 1, 0x8000_0305, 4).unwrap();
    r.send(RPDO1, &[3]);
    assert_eq!(r.emcys(), [0x0000]);
    assert_eq!(r.read(0x1001, 0), 0);
    // The same for a length error.
    r.download(0x1401, 1, 0x0000_0305, 4).unwrap();
    r.send(RPDO2, &[4]);
    assert_eq!(r.emcys(), [0x8210]);
    r.download(0x1401, 1, 0x8000_0305, 4).unwrap();
    r.send(RPDO1, &[5]);
    assert_eq!(r.read(0x2000, 0), 5);
    assert_eq!(r.read(0x1001, 0), 0, "RPDO2 is not received any more");
}
