//! CiA 301 heartbeat consumer (0x1016, §7.2.8.3.2.2) and error behaviour (0x1029, §7.5.2.32)
//! over a whole node: a plain CiA 301 device whose table is generated per test (the entry
//! count, which entry watches, the 0x1029 value), driven by frames on the virtual clock.

use canpos_stack::model::{CommConfig, Features, Model, Table};
use canpos_stack::nmt::NmtState;
use canpos_stack::od::{cia301, DefaultValue::*, Entry, Hook};
use canpos_stack::storage::RamStorage;
use canpos_stack::{entry, Frame, Instant, Node, Plain};

const ID: u8 = 5;
/// The watched node.
const PEER: u8 = 0x20;

const fn raw(node: u8, ms: u16) -> u32 {
    (node as u32) << 16 | ms as u32
}

/// A device with 0x1016 sub 1… holding `consumers`, 0x1029 sub 1 = `behaviour` (none: no
/// 0x1029), node guarding when `guarding`.
fn model(consumers: &[u32], behaviour: Option<u8>, guarding: bool) -> &'static Model {
    let mut t: Vec<Entry> = vec![
        entry!(0x1000, 0, "", Unsigned32, Ro, Const(0)),
        entry!(0x1001, 0, "", Unsigned8, Ro, Live),
        entry!(0x1005, 0, "", Unsigned32, Rw, Const(0x80), Any, Comm),
    ];
    if guarding {
        t.push(entry!(0x100C, 0, "", Unsigned16, Rw, Const(0), Any, Comm));
        t.push(entry!(0x100D, 0, "", Unsigned8, Rw, Const(0), Any, Comm));
    }
    t.push(entry!(
        0x1014,
        0,
        "",
        Unsigned32,
        Rw,
        NodeId(0x80),
        Any,
        Comm
    ));
    if !consumers.is_empty() {
        let n = consumers.len() as u32;
        t.push(entry!(0x1016, 0, "", Unsigned8, Const, Const(n)));
        for (i, &v) in consumers.iter().enumerate() {
            t.push(entry!(
                0x1016,
                i as u8 + 1,
                "",
                Unsigned32,
                Rw,
                Const(v),
                Any,
                Comm
            ));
        }
    }
    t.push(entry!(0x1017, 0, "", Unsigned16, Rw, Const(0), Any, Comm));
    t.push(entry!(0x1018, 0, "", Unsigned8, Const, Const(1)));
    t.push(entry!(0x1018, 1, "", Unsigned32, Const, Const(0)));
    if let Some(b) = behaviour {
        t.push(entry!(0x1029, 0, "", Unsigned8, Const, Const(2)));
        t.push(entry!(
            0x1029,
            1,
            "",
            Unsigned8,
            Rw,
            Const(b as u32),
            Any,
            Comm
        ));
        t.push(entry!(0x1029, 2, "", Unsigned8, Rw, Const(1), Any, Comm));
    }
    for e in &mut t {
        let h = cia301::hook_of(e.index, e.sub);
        if h != Hook::None {
            e.hook = h;
        }
    }
    assert!(cia301::hooks_complete(&t));
    let entries: &'static [Entry] = Box::leak(t.into_boxed_slice());
    let keys: &'static [u32] = Box::leak(entries.iter().map(Entry::key).collect());
    Box::leak(Box::new(Model {
        table: Table {
            name: "t",
            product: "",
            vendor: "",
            entries,
            keys,
            features: Features {
                tag: 0x51,
                tpdos: 0,
                rpdos: 0,
                sdo_segmented: false,
                sdo_block: false,
                node_guarding: guarding,
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
        param: |_, _| 0,
        derive: |c| c,
        variant: None,
        default_config: CommConfig {
            node_id: ID,
            bitrate_kbps: 125,
            serial: 0,
        },
    }))
}

struct Rig {
    n: Node<Plain, RamStorage>,
    /// Frames the node sent, with the time they were polled at.
    out: Vec<(u64, Frame)>,
}

fn ms(t: u64) -> Instant {
    Instant::from_millis(t)
}

impl Rig {
    fn new(m: &'static Model) -> Rig {
        let mut n = Node::with_app(m, m.default_config, Plain, RamStorage::default());
        n.power_on(Instant::ZERO);
        let mut r = Rig { n, out: Vec::new() };
        r.run(0);
        r.out.clear();
        r
    }

    /// Runs every deadline up to `t` ms, polling at each.
    fn run(&mut self, t: u64) {
        let end = ms(t);
        loop {
            let at = match self.n.poll_timeout() {
                Some(d) if d <= end => d,
                _ => end,
            };
            while let Some(f) = self.n.poll(at) {
                self.out.push((at.micros(), f));
            }
            if at == end {
                break;
            }
        }
    }

    fn send(&mut self, t: u64, id: u16, data: &[u8]) {
        self.run(t);
        self.n.handle_frame(&Frame::new(id, data).unwrap(), ms(t));
        self.run(t);
    }

    fn heartbeat(&mut self, t: u64, node: u8, state: u8) {
        self.send(t, 0x700 + u16::from(node), &[state]);
    }

    fn nmt(&mut self, t: u64, cmd: u8) {
        self.send(t, 0, &[cmd, ID]);
    }

    /// An expedited SDO download; the answer's command byte and abort code.
    fn write(&mut self, t: u64, index: u16, sub: u8, v: &[u8]) -> (u8, u32) {
        let cmd = 0x23 | ((4 - v.len() as u8) << 2);
        let mut d = [cmd, index as u8, (index >> 8) as u8, sub, 0, 0, 0, 0];
        d[4..4 + v.len()].copy_from_slice(v);
        self.out.clear();
        self.send(t, 0x600 + u16::from(ID), &d);
        let (_, f) = self
            .out
            .iter()
            .find(|(_, f)| f.std_id() == Some(0x580 + u16::from(ID)))
            .expect("SDO answer");
        let d = f.data();
        (d[0], u32::from_le_bytes([d[4], d[5], d[6], d[7]]))
    }

    /// The EMCY frames sent so far (code, register, first manufacturer byte), and their times.
    fn emcys(&self) -> Vec<(u64, u16, u8, u8)> {
        self.out
            .iter()
            .filter(|(_, f)| f.std_id() == Some(0x80 + u16::from(ID)))
            .map(|(t, f)| {
                let d = f.data();
                (t / 1000, u16::from_le_bytes([d[0], d[1]]), d[2], d[3])
            })
            .collect()
    }

    fn state(&self) -> NmtState {
        self.n.device().nmt_state()
    }
}

/// CiA 301 §7.2.8.3.2.2: monitoring starts with the first heartbeat; a missed one raises EMCY
/// 0x8130 with the communication bit of 0x1001 (and the node-id in the first manufacturer
/// byte); the next heartbeat ends the error (EMCY 0x0000, register 0). Generated over tables
/// of one to four entries, the watched node in each, the others unused or other nodes.
#[test]
fn cia301_7_2_8_3_a_missed_heartbeat_raises_8130_after_the_first() {
    for len in 1..=4usize {
        for at in 0..len {
            let mut v: Vec<u32> = (0..len).map(|i| raw(0x30 + i as u8, 0)).collect();
            v[at] = raw(PEER, 100);
            if len > 2 {
                v[(at + 1) % len] = raw(0x40, 50);
            }
            let mut r = Rig::new(model(&v, None, false));
            let case = format!("{len} entries, watched in {}", at + 1);
            r.run(5_000);
            assert!(
                r.emcys().is_empty(),
                "{case}: nothing before the first heartbeat"
            );
            r.heartbeat(5_000, PEER, 0x05);
            r.heartbeat(5_090, PEER, 0x05);
            r.run(5_189);
            assert!(
                r.emcys().is_empty(),
                "{case}: each heartbeat restarts the time"
            );
            r.run(5_190);
            assert_eq!(r.emcys(), vec![(5_190, 0x8130, 0x11, PEER)], "{case}");
            assert_eq!(r.n.read_object(0x1001, 0), Ok(0x11));
            r.run(9_000);
            assert_eq!(
                r.emcys().len(),
                1,
                "{case}: one event until the next heartbeat"
            );
            r.heartbeat(9_000, PEER, 0x7F);
            assert_eq!(r.emcys()[1], (9_000, 0x0000, 0, 0), "{case}");
            assert_eq!(r.n.read_object(0x1001, 0), Ok(0));
            assert_eq!(r.state(), NmtState::PreOperational, "{case}: no 0x1029");
        }
    }
}

/// Two watched nodes lost: one EMCY each; the error stands until both are back.
#[test]
fn the_error_stands_while_any_watched_node_is_lost() {
    let mut r = Rig::new(model(&[raw(PEER, 100), raw(0x21, 100)], None, false));
    r.heartbeat(0, PEER, 5);
    r.heartbeat(10, 0x21, 5);
    r.run(200);
    assert_eq!(
        r.emcys(),
        vec![(100, 0x8130, 0x11, PEER), (110, 0x8130, 0x11, 0x21)]
    );
    r.heartbeat(300, PEER, 5);
    assert_eq!(r.n.read_object(0x1001, 0), Ok(0x11), "0x21 still lost");
    assert_eq!(r.emcys().len(), 2);
    r.heartbeat(310, 0x21, 5);
    assert_eq!(r.emcys()[2], (310, 0, 0, 0));
}

/// CiA 301: a node-id twice with non-zero times is refused with 0x06040043 and changes
/// nothing; the reserved bits 31–24 are refused with 0x06090030.
#[test]
fn cia301_a_node_id_twice_is_refused_and_changes_nothing() {
    let mut r = Rig::new(model(&[raw(PEER, 100), 0], None, false));
    let dup = raw(PEER, 200).to_le_bytes();
    assert_eq!(r.write(0, 0x1016, 2, &dup), (0x80, 0x0604_0043));
    assert_eq!(r.n.read_object(0x1016, 2), Ok(0));
    // Its own entry may change its time; a zero time frees the node-id for another entry.
    assert_eq!(r.write(1, 0x1016, 1, &dup).0, 0x60);
    assert_eq!(r.write(2, 0x1016, 2, &raw(PEER, 0).to_le_bytes()).0, 0x60);
    assert_eq!(r.write(3, 0x1016, 1, &0u32.to_le_bytes()).0, 0x60);
    assert_eq!(r.write(4, 0x1016, 2, &dup).0, 0x60);
    assert_eq!(r.n.read_object(0x1016, 2), Ok(raw(PEER, 200)));
    let reserved = (0x0100_0000 | raw(7, 10)).to_le_bytes();
    assert_eq!(r.write(5, 0x1016, 1, &reserved), (0x80, 0x0609_0030));
    assert_eq!(r.n.read_object(0x1016, 1), Ok(0));
    // The entry written last watches (the time that entry says).
    r.heartbeat(10, PEER, 5);
    r.run(209);
    assert!(r.emcys().is_empty());
    r.run(210);
    assert_eq!(r.emcys(), vec![(210, 0x8130, 0x11, PEER)]);
}

/// A write to a lost node's entry ends its error and waits for the first heartbeat again.
#[test]
fn a_write_to_an_entry_ends_its_error() {
    let mut r = Rig::new(model(&[raw(PEER, 50)], None, false));
    r.heartbeat(0, PEER, 5);
    r.run(60);
    assert_eq!(r.emcys(), vec![(50, 0x8130, 0x11, PEER)]);
    r.write(100, 0x1016, 1, &raw(PEER, 80).to_le_bytes());
    assert_eq!(r.emcys(), vec![(100, 0, 0, 0)]);
    r.run(1_000);
    assert_eq!(r.emcys().len(), 1, "waits for the first heartbeat");
}

/// D27: a consumed node's boot-up stops its monitoring until its next heartbeat (after a reset
/// its heartbeat may be off) and ends its error; no EMCY of its own.
#[test]
fn d27_a_boot_up_of_a_watched_node_waits_for_its_next_heartbeat() {
    let mut r = Rig::new(model(&[raw(PEER, 100)], None, false));
    r.heartbeat(0, PEER, 5);
    r.heartbeat(50, PEER, 0x00);
    r.run(2_000);
    assert!(r.emcys().is_empty(), "no timeout after a boot-up");
    r.heartbeat(2_000, PEER, 0x7F);
    r.run(2_100);
    assert_eq!(r.emcys(), vec![(2_100, 0x8130, 0x11, PEER)]);
    r.heartbeat(2_500, PEER, 0x00);
    assert_eq!(r.emcys()[1], (2_500, 0, 0, 0), "the boot-up ends the error");
    r.run(5_000);
    assert_eq!(r.emcys().len(), 2);
}

/// D27: heartbeats are consumed in pre-operational and operational only; a stopped node
/// forgets the monitoring and starts again at the first heartbeat once running.
#[test]
fn d27_no_monitoring_while_stopped() {
    let mut r = Rig::new(model(&[raw(PEER, 100)], None, false));
    r.heartbeat(0, PEER, 5);
    r.nmt(50, 0x02);
    r.run(1_000);
    r.heartbeat(1_000, PEER, 5);
    r.run(2_000);
    assert!(r.emcys().is_empty());
    r.nmt(2_000, 0x01);
    r.run(3_000);
    assert!(r.emcys().is_empty(), "waits for the first heartbeat");
    r.heartbeat(3_000, PEER, 5);
    r.run(3_100);
    assert_eq!(r.emcys(), vec![(3_100, 0x8130, 0x11, PEER)]);
    // Reset communication reloads 0x1016 and forgets the error.
    r.nmt(3_200, 0x82);
    r.run(10_000);
    assert_eq!(r.emcys().len(), 1);
    assert_eq!(r.n.read_object(0x1001, 0), Ok(0));
}

/// Heartbeats of nodes nobody watches, of the node's own id, remote and zero-length frames on
/// a watched id: nothing.
#[test]
fn other_frames_on_heartbeat_ids_change_nothing() {
    let mut r = Rig::new(model(&[raw(PEER, 100)], None, false));
    r.heartbeat(0, 0x21, 5);
    r.send(1, 0x700 + u16::from(PEER), &[]);
    let rtr = Frame::remote(0x700 + u32::from(PEER), false, 1).unwrap();
    r.n.handle_frame(&rtr, ms(2));
    r.run(5_000);
    assert!(r.out.is_empty(), "{:?}", r.out);
}

/// The NMT state a node in `from` (an NMT command, 0 = pre-operational) ends in after the
/// communication error `source` with 0x1029 sub 1 = `v`.
fn after_error(v: Option<u8>, from: u8, source: &str) -> NmtState {
    let guarding = source == "life guarding";
    let mut r = Rig::new(model(&[raw(PEER, 200)], v, guarding));
    if guarding {
        r.write(0, 0x100C, 0, &100u16.to_le_bytes());
        r.write(0, 0x100D, 0, &[2]);
        r.send(0, 0x700 + u16::from(ID), &[]);
    } else {
        r.heartbeat(0, PEER, 5);
    }
    if from != 0 {
        r.nmt(1, from);
    }
    r.out.clear();
    r.run(150);
    assert!(r.emcys().is_empty(), "{source}: no error yet");
    r.run(250);
    // Stopped before: no heartbeat monitoring, a life guarding EMCY waits until the node
    // leaves Stopped; so does the EMCY of an error that stopped the node (0x1029 = 2).
    let want = usize::from(from != 0x02 && r.state() != NmtState::Stopped);
    assert_eq!(
        r.emcys().len(),
        want,
        "{source} from {from:#x}, 0x1029 {v:?}: {:?}",
        r.out
    );
    r.state()
}

/// CiA 301 §7.5.2.32: 0x1029 sub 1 = 0 / 1 / 2 from pre-operational, operational and stopped,
/// for each communication error source the stack knows (a heartbeat consumer event, a life
/// guarding event); without 0x1029 the state stays.
#[test]
fn cia301_7_5_2_32_communication_error_reactions() {
    use NmtState::*;
    for source in ["heartbeat", "life guarding"] {
        for (from, state) in [(0u8, PreOperational), (0x01, Operational), (0x02, Stopped)] {
            let want = |v: Option<u8>| match (v, state) {
                (Some(0), Operational) => PreOperational,
                (Some(2), PreOperational | Operational) => Stopped,
                _ => state,
            };
            for v in [None, Some(0), Some(1), Some(2)] {
                assert_eq!(
                    after_error(v, from, source),
                    want(v),
                    "{source}, 0x1029 = {v:?}, from {state:?}"
                );
            }
        }
    }
}

/// CiA 301 §7.5.2.32 for the third communication error, bus-off (`Node::set_bus_off`): the
/// reaction on entering it; the communication bit while it lasts; EMCY 0x8140 at the recovery
/// (the EMCY of a stopped node waits until it leaves Stopped).
#[test]
fn cia301_7_5_2_32_bus_off_reactions() {
    use NmtState::*;
    for (from, state) in [(0u8, PreOperational), (0x01, Operational), (0x02, Stopped)] {
        for v in [None, Some(0), Some(1), Some(2)] {
            let mut r = Rig::new(model(&[], v, false));
            if from != 0 {
                r.nmt(1, from);
            }
            r.out.clear();
            r.n.set_bus_off(true);
            r.n.set_bus_off(true);
            r.run(10);
            let want = match (v, state) {
                (Some(0), Operational) => PreOperational,
                (Some(2), PreOperational | Operational) => Stopped,
                _ => state,
            };
            assert_eq!(r.state(), want, "0x1029 = {v:?} from {state:?}");
            assert_eq!(r.n.read_object(0x1001, 0), Ok(0x11));
            assert!(r.emcys().is_empty(), "nothing sent while bus-off");
            r.n.set_bus_off(false);
            r.n.set_bus_off(false);
            r.run(20);
            assert_eq!(r.state(), want, "the recovery changes no state");
            assert_eq!(r.n.read_object(0x1001, 0), Ok(0));
            let sent = if want == Stopped {
                vec![]
            } else {
                vec![(20, 0x8140, 0x11, 0), (20, 0, 0, 0)]
            };
            assert_eq!(r.emcys(), sent, "0x1029 = {v:?} from {state:?}");
        }
    }
}

/// A node stopped by 0x1029 = 2 reports it in its own heartbeat (0x04) and answers no SDO.
#[test]
fn a_node_stopped_by_its_error_behaviour_says_so_in_its_heartbeat() {
    let mut r = Rig::new(model(&[raw(PEER, 100)], Some(2), false));
    r.write(0, 0x1017, 0, &50u16.to_le_bytes());
    r.heartbeat(0, PEER, 5);
    r.out.clear();
    r.run(160);
    let own: Vec<u8> = r
        .out
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x700 + u16::from(ID)))
        .map(|(_, f)| f.data()[0])
        .collect();
    assert_eq!(
        own,
        vec![0x7F, 0x7F, 0x04],
        "50, 100 pre-operational; 150 stopped"
    );
}

/// 0x1029: 0, 1, 2 only (CiA 301 reserves 3–0x7F; 0x80–0xFF would be manufacturer reactions
/// this stack does not have): refused with 0x06090030 and unchanged, in every sub-index.
#[test]
fn cia301_error_behaviour_values() {
    let mut r = Rig::new(model(&[raw(PEER, 100)], Some(0), false));
    for sub in 1..=2u8 {
        for v in 0..=2u8 {
            assert_eq!(r.write(0, 0x1029, sub, &[v]).0, 0x60);
        }
        for v in [3u8, 0x7F, 0x80, 0xFF] {
            assert_eq!(r.write(0, 0x1029, sub, &[v]), (0x80, 0x0609_0030));
            assert_eq!(r.n.read_object(0x1029, sub), Ok(2));
        }
    }
}
