//! CiA 305 for a node without a node-id: a DS 305 V2 node (TH, E-Series) waits in LSS waiting
//! after power-on, answers fastscan and switch-selective from there, and only the selected (or
//! globally switched) node answers inquiries and configuration commands. The TMI (DSP 305 V1.1)
//! enters configuration by itself (R7). Two nodes share one virtual bus here: every frame
//! reaches both, and their answers are counted.

use canpos_models::SensorNode;
use canpos_models::{by_name, Model};
use canpos_stack::storage::RamStorage;
use canpos_stack::{Frame, Instant, Node};

/// Nodes on one virtual bus.
struct Bus {
    nodes: Vec<SensorNode<RamStorage>>,
    now: Instant,
}

impl Bus {
    fn new(units: &[(&'static Model, u8, u32)]) -> Bus {
        let nodes = units
            .iter()
            .map(|&(m, id, serial)| {
                let cfg = m.default_config.with_node_id(id).with_serial(serial);
                let mut n = Node::new(m, m.configure(cfg), RamStorage::default());
                n.power_on(Instant::ZERO);
                while n.poll_transmit().is_some() {}
                n
            })
            .collect();
        Bus {
            nodes,
            now: Instant::ZERO,
        }
    }

    /// A master frame to every node; the answers, with the index of the node that sent each.
    fn send(&mut self, id: u16, data: &[u8]) -> Vec<(usize, Frame)> {
        let f = Frame::new(id, data).unwrap();
        let mut out = Vec::new();
        for (i, n) in self.nodes.iter_mut().enumerate() {
            n.handle_frame(&f, self.now);
            while let Some(a) = n.poll(self.now) {
                out.push((i, a));
            }
        }
        out
    }

    fn lss(&mut self, d: [u8; 8]) -> Vec<(usize, [u8; 8])> {
        self.send(0x7E5, &d)
            .into_iter()
            .filter(|(_, f)| f.std_id() == Some(0x7E4))
            .map(|(i, f)| (i, f.data().try_into().unwrap()))
            .collect()
    }

    fn address(&self, i: usize) -> [u32; 4] {
        self.nodes[i].device().lss_address()
    }
}

fn le(v: u32) -> [u8; 4] {
    v.to_le_bytes()
}

fn frame(cs: u8, v: u32) -> [u8; 8] {
    let b = le(v);
    [cs, b[0], b[1], b[2], b[3], 0, 0, 0]
}

/// Fastscan as a CiA 305 master runs it, bit by bit: returns the address found.
fn fastscan(bus: &mut Bus) -> Option<[u32; 4]> {
    if bus.lss([0x51, 0, 0, 0, 0, 0x80, 0, 0]).is_empty() {
        return None;
    }
    let mut found = [0u32; 4];
    for sub in 0..4u8 {
        let mut id = 0u32;
        for bit in (0..32u8).rev() {
            let b = le(id);
            let probe = [0x51, b[0], b[1], b[2], b[3], bit, sub, sub];
            if bus.lss(probe).is_empty() {
                id |= 1 << bit;
            }
        }
        // Confirm the part and move on to the next one (after serial: back to vendor).
        let next = (sub + 1) % 4;
        let b = le(id);
        assert_eq!(
            bus.lss([0x51, b[0], b[1], b[2], b[3], 0, sub, next]).len(),
            1
        );
        found[sub as usize] = id;
    }
    Some(found)
}

#[test]
fn unconfigured_v2_node_waits_and_is_found_by_fastscan() {
    for name in ["th", "e-series"] {
        let m = by_name(name).unwrap();
        let mut bus = Bus::new(&[(m, 0xFF, 1111), (m, 10, 2222)]);
        // Waiting: no answer to an inquiry, nor to a configuration command.
        assert!(
            bus.lss(frame(0x5E, 0)).is_empty(),
            "{name}: inquiry in waiting"
        );
        assert!(bus.lss([0x11, 5, 0, 0, 0, 0, 0, 0]).is_empty(), "{name}");
        // Fastscan: only the unconfigured node takes part; it is found and selected.
        assert_eq!(fastscan(&mut bus), Some(bus.address(0)), "{name}");
        let a = bus.lss(frame(0x5E, 0));
        assert_eq!(a, vec![(0, [0x5E, 0xFF, 0, 0, 0, 0, 0, 0])], "{name}");
        // Configure node-id 20, back to waiting: it boots up as node 20.
        assert_eq!(
            bus.lss([0x11, 20, 0, 0, 0, 0, 0, 0]),
            vec![(0, [0x11, 0, 0, 0, 0, 0, 0, 0])]
        );
        let boot = bus.send(0x7E5, &[0x04, 0, 0, 0, 0, 0, 0, 0]);
        assert!(
            boot.iter()
                .any(|(i, f)| *i == 0 && f.std_id() == Some(0x714)),
            "{name}: {boot:?}"
        );
        assert_eq!(bus.nodes[0].device().node_id(), 20);
    }
}

#[test]
fn only_the_selected_node_answers() {
    let th = by_name("th").unwrap();
    let mut bus = Bus::new(&[(th, 0xFF, 1111), (th, 10, 2222)]);
    // Switch selective on the configured node's address.
    let addr = bus.address(1);
    for (k, cs) in (0x40..=0x43).enumerate() {
        let a = bus.lss(frame(cs, addr[k]));
        if cs == 0x43 {
            assert_eq!(a, vec![(1, [0x44, 0, 0, 0, 0, 0, 0, 0])]);
        } else {
            assert!(a.is_empty());
        }
    }
    // Inquiries: one answer, from the selected node.
    assert_eq!(
        bus.lss(frame(0x5E, 0)),
        vec![(1, [0x5E, 10, 0, 0, 0, 0, 0, 0])]
    );
    let serial = bus.lss(frame(0x5D, 0));
    assert_eq!(serial, vec![(1, frame(0x5D, 2222))]);
    // Back to waiting, then select the unconfigured one.
    bus.lss([0x04, 0, 0, 0, 0, 0, 0, 0]);
    let addr = bus.address(0);
    for (k, cs) in (0x40..=0x43).enumerate() {
        bus.lss(frame(cs, addr[k]));
    }
    assert_eq!(
        bus.lss(frame(0x5E, 0)),
        vec![(0, [0x5E, 0xFF, 0, 0, 0, 0, 0, 0])]
    );
    // Switch global configuration: both answer.
    bus.lss([0x04, 1, 0, 0, 0, 0, 0, 0]);
    assert_eq!(bus.lss(frame(0x5E, 0)).len(), 2);
}

#[test]
fn identify_non_configured_answers_from_waiting() {
    let th = by_name("th").unwrap();
    let mut bus = Bus::new(&[(th, 0xFF, 1111), (th, 10, 2222)]);
    assert_eq!(
        bus.lss([0x4C, 0, 0, 0, 0, 0, 0, 0]),
        vec![(0, [0x50, 0, 0, 0, 0, 0, 0, 0])]
    );
}

/// TMI 002 §1.5 picture 1 (R7): an invalid node-id after reset communication leads into the
/// LSS configuration path: the node is in configuration by itself and answers inquiries.
#[test]
fn tmi_unconfigured_is_in_configuration_by_itself() {
    let tmi = by_name("tmi").unwrap();
    let mut bus = Bus::new(&[(tmi, 0xFF, 1111)]);
    assert_eq!(
        bus.lss(frame(0x5E, 0)),
        vec![(0, [0x5E, 0xFF, 0, 0, 0, 0, 0, 0])]
    );
    assert_eq!(
        bus.lss([0x11, 7, 0, 0, 0, 0, 0, 0]),
        vec![(0, [0x11, 0, 0, 0, 0, 0, 0, 0])]
    );
    let boot = bus.send(0x7E5, &[0x04, 0, 0, 0, 0, 0, 0, 0]);
    assert!(
        boot.iter().any(|(_, f)| f.std_id() == Some(0x707)),
        "{boot:?}"
    );
}

/// CiA 305 "identify non-configured remote slave" and fastscan concern slaves without a
/// node-id. A configured node given the pending node-id 0xFF (it becomes unconfigured at its
/// next reset communication) still has its active node-id, so it stays out of both until then.
#[test]
fn a_pending_unconfigure_does_not_make_a_node_non_configured_yet() {
    let th = by_name("th").unwrap();
    let mut bus = Bus::new(&[(th, 10, 2222)]);
    bus.lss([0x04, 1, 0, 0, 0, 0, 0, 0]);
    assert_eq!(
        bus.lss([0x11, 0xFF, 0, 0, 0, 0, 0, 0]),
        vec![(0, [0x11, 0, 0, 0, 0, 0, 0, 0])]
    );
    bus.lss([0x04, 0, 0, 0, 0, 0, 0, 0]);
    assert_eq!(bus.nodes[0].device().node_id(), 10);
    assert!(bus.lss([0x4C, 0, 0, 0, 0, 0, 0, 0]).is_empty());
    assert!(bus.lss([0x51, 0, 0, 0, 0, 0x80, 0, 0]).is_empty());
}

/// A slave already in configuration state ignores a switch-state-selective sequence, even one
/// naming its own address: selection is for slaves in waiting (CiA 305 state table).
#[test]
fn a_slave_in_configuration_ignores_selection() {
    let th = by_name("th").unwrap();
    let mut bus = Bus::new(&[(th, 10, 2222)]);
    bus.lss([0x04, 1, 0, 0, 0, 0, 0, 0]);
    let addr = bus.address(0);
    for (k, cs) in (0x40..=0x43).enumerate() {
        assert!(bus.lss(frame(cs, addr[k])).is_empty(), "cs {cs:#x}");
    }
    // Still in configuration: it answers an inquiry.
    assert_eq!(
        bus.lss(frame(0x5E, 0)),
        vec![(0, [0x5E, 10, 0, 0, 0, 0, 0, 0])]
    );
}
