//! The bus-simulation FMU (`canpos fmu --bus-simulation --nodes N --bitrate KBPS`): an
//! FMI-LS-BUS 1.0 CAN bus simulation with one bus terminal per node FMU (`Node1` … `NodeN`),
//! canpos's bus timeline behind them ([`crate::bussim`], docs/FMU.md "The bus-simulation
//! FMU").
//!
//! Time: `fmi3DoStep` runs the bus on the co-simulation time and, when the importer allows
//! early return, stops at the first time something reaches a node (an end of frame, an error
//! frame): the nodes then get their operations in event mode at that very time. The nodes'
//! `Rx_Data` of an event are taken in `fmi3UpdateDiscreteStates`, at the time reached, so the
//! frames they hand in at one time arbitrate together.

use crate::bussim::{nanos, BusSim};
use crate::model::{
    BusTerminal, Causality, Description, Discrete, FmuModel, StepResult, Value, VarType, Variable,
};
use crate::resource::Entries;
use crate::sensor::lsbus_variables;
use canpos_host::bus::ports::MAX_PORTS;
use canpos_host::bus::{check_bitrate, Nanos};

const VR_BITRATE: u32 = 1;
const VR_LOAD: u32 = 2;
const VR_FRAMES: u32 = 3;
const VR_LOST: u32 = 4;
/// Node `i`'s (0-based) variables start at `VR_NODE0 + i × VR_NODE_STRIDE`: its terminal's
/// `Rx_Data`, `Tx_Data`, `Rx_Clock`, `Tx_Clock`, then its controller's TEC, REC and state.
const VR_NODE0: u32 = 1000;
const VR_NODE_STRIDE: u32 = 10;
const OFF_TEC: u32 = 4;
const OFF_REC: u32 = 5;
const OFF_STATE: u32 = 6;

/// One bus-simulation FMU: its number of node terminals and its bit rate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BusUnit {
    /// Node terminals (1 … 128: 127 nodes and their master).
    pub nodes: usize,
    /// Bit rate, kbit/s (CiA 301); the `bitrate` parameter's start value.
    pub kbps: u32,
}

impl BusUnit {
    /// A bus simulation with `nodes` terminals at `kbps`, both checked.
    pub fn new(nodes: usize, kbps: u32) -> Result<BusUnit, String> {
        if !(1..=MAX_PORTS).contains(&nodes) {
            return Err(format!(
                "--nodes {nodes}: a bus simulation has 1 … {MAX_PORTS} node terminals"
            ));
        }
        check_bitrate(kbps)?;
        Ok(BusUnit { nodes, kbps })
    }

    pub(crate) fn from_entries(e: &Entries) -> Result<BusUnit, String> {
        e.only(&["kind", "nodes", "bitrate"])?;
        let num = |key: &str| -> Result<u32, String> {
            let v = e
                .get(key)
                .ok_or_else(|| format!("a bus simulation needs `{key}`"))?;
            v.parse()
                .map_err(|_| format!("`{key} = {v}` is not a whole number"))
        };
        BusUnit::new(num("nodes")? as usize, num("bitrate")?)
    }

    pub(crate) fn resource_entries(&self) -> Vec<(&'static str, String)> {
        vec![
            ("kind", "bus-simulation".to_string()),
            ("nodes", self.nodes.to_string()),
            ("bitrate", self.kbps.to_string()),
        ]
    }

    /// The FMU's name: `canpos_bus_N`.
    pub fn identifier(&self) -> String {
        format!("canpos_bus_{}", self.nodes)
    }

    pub(crate) fn description(&self, token: String) -> Result<Description, String> {
        use Causality::*;
        let mut v = vec![
            Variable::time(),
            Variable::new("bitrate", VR_BITRATE, VarType::UInt32, Parameter,
                "bit rate of the bus, kbit/s (CiA 301); a node that configures another one (LS-BUS CAN_BAUDRATE) neither sends nor receives")
                .start(self.kbps.to_string()),
            Variable::new("bus_load", VR_LOAD, VarType::Float64, Output,
                "share of the last second the bus was busy, error frames included, %"),
            Variable::new("frames", VR_FRAMES, VarType::UInt64, Output,
                "frames carried since the start"),
            Variable::new("frames_lost", VR_LOST, VarType::UInt64, Output,
                "frames lost in the nodes' transmit queues (full queue, bus-off), all nodes"),
        ];
        let mut terminals = Vec::with_capacity(self.nodes);
        for i in 0..self.nodes {
            let name = format!("Node{}", i + 1);
            let base = VR_NODE0 + i as u32 * VR_NODE_STRIDE;
            v.extend(lsbus_variables(&name, base));
            v.push(Variable::new(
                format!("{name}.tec"),
                base + OFF_TEC,
                VarType::UInt16,
                Output,
                format!(
                    "transmit error counter of node {}'s controller on the bus model",
                    i + 1
                ),
            ));
            v.push(Variable::new(
                format!("{name}.rec"),
                base + OFF_REC,
                VarType::UInt16,
                Output,
                format!(
                    "receive error counter of node {}'s controller on the bus model",
                    i + 1
                ),
            ));
            v.push(Variable::new(format!("{name}.state"), base + OFF_STATE, VarType::UInt8, Output,
                format!("node {}'s controller state on the bus model: 1 error active, 2 error passive, 3 bus-off (LS-BUS status codes)", i + 1)));
            terminals.push(BusTerminal { name });
        }
        Ok(Description {
            model_name: format!("canpos CAN bus simulation, {} nodes", self.nodes),
            model_identifier: self.identifier(),
            description: format!(
                "canpos's virtual CAN bus (bit timing with stuffing, arbitration by identifier, error counters, bus-off) as an FMI-LS-BUS bus simulation for {} node FMUs",
                self.nodes
            ),
            token,
            variables: v,
            terminals,
            is_bus_simulation: true,
            documentation: Vec::new(),
            // The bus is exact at any step (early return stops at each end of frame); 1 ms
            // as the sensors'.
            step_size: 0.001,
        })
    }
}

/// An instance of the bus-simulation FMU.
pub struct BusFmu {
    unit: BusUnit,
    desc: Description,
    kbps: u32,
    sim: BusSim,
    /// Each node's `Rx_Data` as last set, and whether its `Rx_Clock` ticked.
    rx: Vec<Vec<u8>>,
    rx_clock: Vec<bool>,
    /// Each node's `Tx_Clock` not yet read in this event.
    tx_clock: Vec<bool>,
    initialized: bool,
    log: Vec<String>,
}

impl BusFmu {
    /// A new instance.
    pub fn new(unit: BusUnit, desc: Description) -> Result<BusFmu, String> {
        Ok(BusFmu {
            sim: BusSim::new(unit.nodes, unit.kbps)?,
            unit,
            desc,
            kbps: unit.kbps,
            rx: vec![Vec::new(); unit.nodes],
            rx_clock: vec![false; unit.nodes],
            tx_clock: vec![false; unit.nodes],
            initialized: false,
            log: Vec::new(),
        })
    }

    /// Node index and member offset of a value reference in the nodes' range.
    fn node_vr(&self, vr: u32) -> Option<(usize, u32)> {
        let rel = vr.checked_sub(VR_NODE0)?;
        let node = (rel / VR_NODE_STRIDE) as usize;
        (node < self.unit.nodes).then_some((node, rel % VR_NODE_STRIDE))
    }

    /// Takes the `Rx_Data` of every node whose `Rx_Clock` ticked, node by node, at the time
    /// reached. A malformed buffer is refused whole (the others are still taken).
    fn take_rx(&mut self) -> Result<(), String> {
        let mut errors = Vec::new();
        for node in 0..self.unit.nodes {
            if std::mem::take(&mut self.rx_clock[node]) {
                if let Err(e) = self.sim.receive(node, &self.rx[node]) {
                    errors.push(e);
                }
            }
        }
        self.note_ticks();
        if errors.is_empty() {
            Ok(())
        } else {
            Err(errors.join("; "))
        }
    }

    fn note_ticks(&mut self) {
        for node in 0..self.unit.nodes {
            self.tx_clock[node] = self.sim.tx_ticks(node);
        }
    }

    fn time(&self, t: f64, what: &str) -> Result<Nanos, String> {
        nanos(t).ok_or_else(|| format!("{what} {t} s is not a time of this bus (0 … 1.8e10 s)"))
    }
}

impl FmuModel for BusFmu {
    fn description(&self) -> &Description {
        &self.desc
    }

    fn enter_initialization(&mut self, start_time: f64) -> Result<(), String> {
        // The bus's time is the co-simulation's: its timeline starts idle at 0.
        self.time(start_time, "start time")?;
        Ok(())
    }

    fn exit_initialization(&mut self) -> Result<(), String> {
        if self.kbps != self.unit.kbps {
            self.sim = BusSim::new(self.unit.nodes, self.kbps)?;
        }
        self.initialized = true;
        Ok(())
    }

    fn get(&mut self, vr: u32) -> Result<Value<'_>, String> {
        Ok(match vr {
            crate::model::VR_TIME => Value::Float64(self.sim.now() as f64 / 1e9),
            VR_BITRATE => Value::UInt32(self.kbps),
            VR_LOAD => Value::Float64(self.sim.ports().load().0 * 100.0),
            VR_FRAMES => Value::UInt64(self.sim.ports().frames()),
            VR_LOST => {
                let p = self.sim.ports();
                let lost = (0..p.len())
                    .filter_map(|i| p.stats(i))
                    .map(|s| s.lost_overflow + s.lost_bus_off)
                    .sum::<u64>()
                    + p.refused_bus_off();
                Value::UInt64(lost)
            }
            _ => {
                let (node, off) = self
                    .node_vr(vr)
                    .ok_or_else(|| format!("no variable with value reference {vr}"))?;
                let stats = self.sim.ports().stats(node).unwrap_or_default();
                match off {
                    0 => Value::Binary(&self.rx[node]),
                    1 => Value::Binary(self.sim.tx(node)),
                    2 => Value::Clock(self.rx_clock[node]),
                    3 => Value::Clock(std::mem::take(&mut self.tx_clock[node])),
                    OFF_TEC => Value::UInt16(stats.tec),
                    OFF_REC => Value::UInt16(stats.rec),
                    OFF_STATE => Value::UInt8(match stats.state {
                        canpos_host::can::BusState::ErrorActive => 1,
                        canpos_host::can::BusState::ErrorPassive => 2,
                        canpos_host::can::BusState::BusOff => 3,
                    }),
                    _ => return Err(format!("no variable with value reference {vr}")),
                }
            }
        })
    }

    fn set(&mut self, vr: u32, v: Value<'_>) -> Result<(), String> {
        match (vr, v) {
            (VR_BITRATE, Value::UInt32(k)) => {
                if self.initialized {
                    return Err("bitrate is fixed after initialization".into());
                }
                self.kbps = check_bitrate(k)?;
            }
            _ => match (self.node_vr(vr), v) {
                (Some((node, 0)), Value::Binary(b)) => {
                    // Checked whole now: a malformed buffer is refused and changes nothing.
                    crate::lsbus::parse(b).map_err(|e| format!("Node{}: {e}", node + 1))?;
                    self.rx[node].clear();
                    self.rx[node].extend_from_slice(b);
                }
                (Some((node, 2)), Value::Clock(on)) => self.rx_clock[node] = on,
                _ => return Err(format!("value reference {vr} cannot be set")),
            },
        }
        Ok(())
    }

    fn do_step(&mut self, t: f64, h: f64, early: bool) -> Result<StepResult, String> {
        if !(h.is_finite() && h > 0.0) {
            return Err(format!("communication step size {h} is not positive"));
        }
        let at = self.time(t, "doStep at")?;
        let now = self.sim.now();
        // One µs of slack for an importer's floating-point sums of step sizes.
        if at.abs_diff(now) > 1_000 {
            return Err(format!(
                "doStep at {t} s, but the bus is at {} s",
                now as f64 / 1e9
            ));
        }
        let end = self.time(t + h, "doStep to")?;
        // Operations handed in without an event (an importer that sets clocks in step mode).
        self.take_rx()?;
        let reached = self.sim.step(end.max(now), early);
        self.note_ticks();
        self.log.extend(self.sim.take_log());
        Ok(StepResult {
            event_needed: self.sim.any_tx(),
            last_time: reached as f64 / 1e9,
            early_return: reached < end,
        })
    }

    fn update_discrete_states(&mut self) -> Result<Discrete, String> {
        let before = self.sim.any_tx();
        let r = self.take_rx();
        self.log.extend(self.sim.take_log());
        r?;
        Ok(Discrete {
            // A Wakeup or a CAN FD answer goes out in this event: read the clocks again.
            need_update: !before && self.sim.any_tx(),
            next_event_time: self.sim.next_event().map(|t| t as f64 / 1e9),
        })
    }

    fn enter_step_mode(&mut self) -> Result<(), String> {
        self.sim.clear_tx();
        self.tx_clock.iter_mut().for_each(|c| *c = false);
        self.rx_clock.iter_mut().for_each(|c| *c = false);
        Ok(())
    }

    fn take_log(&mut self) -> Vec<String> {
        std::mem::take(&mut self.log)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kind::Kind;
    use crate::lsbus::{Op, TxBuffer};

    fn instance(nodes: usize, kbps: u32) -> Box<dyn FmuModel> {
        let kind = Kind::from_resource(&format!(
            "kind = bus-simulation\nnodes = {nodes}\nbitrate = {kbps}\n"
        ))
        .unwrap();
        kind.instantiate().unwrap()
    }

    fn vr(node: usize, off: u32) -> u32 {
        VR_NODE0 + node as u32 * VR_NODE_STRIDE + off
    }

    fn transmit(id: u32, data: &[u8]) -> Vec<u8> {
        let mut b = TxBuffer::new(64);
        b.push(&Op::Transmit {
            id,
            ide: false,
            rtr: false,
            data,
            dlc: data.len() as u16,
        })
        .unwrap();
        b.bytes().to_vec()
    }

    #[test]
    fn the_resource_names_nodes_and_bit_rate_and_bad_ones_are_refused() {
        let k = Kind::from_resource("kind = bus-simulation\nnodes = 4\nbitrate = 125").unwrap();
        let d = k.description().unwrap();
        assert!(d.is_bus_simulation);
        let names: Vec<_> = d.terminals.iter().map(|t| t.name.as_str()).collect();
        assert_eq!(names, ["Node1", "Node2", "Node3", "Node4"]);
        assert!(d.variables.windows(2).all(|w| w[0].vr < w[1].vr));
        assert!(d.variables.iter().any(|v| v.name == "Node4.Tx_Clock"));
        assert_eq!(
            Kind::from_resource(&k.resource_text())
                .unwrap()
                .description()
                .unwrap()
                .token,
            d.token
        );
        for (bad, why) in [
            ("kind = bus-simulation\nnodes = 0\nbitrate = 125", "1 … 128"),
            (
                "kind = bus-simulation\nnodes = 129\nbitrate = 125",
                "1 … 128",
            ),
            ("kind = bus-simulation\nnodes = 3\nbitrate = 123", "CiA 301"),
            (
                "kind = bus-simulation\nnodes = x\nbitrate = 125",
                "whole number",
            ),
            ("kind = bus-simulation\nbitrate = 125", "needs `nodes`"),
            (
                "kind = bus-simulation\nnodes = 3\nbitrate = 125\nmodel = th",
                "unknown key",
            ),
        ] {
            let e = Kind::from_resource(bad).unwrap_err();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }

    #[test]
    fn an_event_in_and_an_early_return_out_at_the_end_of_frame() {
        let mut m = instance(3, 125);
        m.enter_initialization(0.0).unwrap();
        m.exit_initialization().unwrap();
        let data = [1, 2, 3, 4];
        m.set(vr(0, 0), Value::Binary(&transmit(0x181, &data)))
            .unwrap();
        m.set(vr(0, 2), Value::Clock(true)).unwrap();
        let d = m.update_discrete_states().unwrap();
        assert!(!d.need_update);
        m.enter_step_mode().unwrap();
        let r = m.do_step(0.0, 0.01, true).unwrap();
        assert!(r.early_return && r.event_needed);
        // 0x181 with 4 data bytes: its end of frame at 125 kbit/s, a whole number of 8 µs bits.
        let f = canpos_stack::Frame::new(0x181, &data).unwrap();
        let bits = canpos_host::bus::bits::frame_length(&f).total
            - canpos_host::bus::bits::INTERMISSION_BITS;
        assert_eq!(r.last_time, f64::from(bits * 8_000) / 1e9);
        assert_eq!(m.get(vr(1, 3)).unwrap(), Value::Clock(true));
        // An output clock reports its tick once.
        assert_eq!(m.get(vr(1, 3)).unwrap(), Value::Clock(false));
        assert_eq!(
            m.get(vr(1, 1)).unwrap(),
            Value::Binary(&transmit(0x181, &data))
        );
        let Value::Binary(confirm) = m.get(vr(0, 1)).unwrap() else {
            panic!()
        };
        assert_eq!(
            crate::lsbus::parse(confirm).unwrap(),
            vec![Op::Confirm { id: 0x181 }]
        );
        m.enter_step_mode().unwrap();
        assert_eq!(m.get(vr(1, 1)).unwrap(), Value::Binary(&[]));
        let r = m.do_step(r.last_time, 0.01, true).unwrap();
        assert!(!r.early_return && !r.event_needed);
        assert_eq!(m.get(VR_FRAMES).unwrap(), Value::UInt64(1));
    }

    #[test]
    fn the_bit_rate_parameter_is_honoured_before_initialization_ends_only() {
        let mut m = instance(2, 125);
        assert!(m.set(VR_BITRATE, Value::UInt32(123)).is_err());
        m.set(VR_BITRATE, Value::UInt32(500)).unwrap();
        m.enter_initialization(0.0).unwrap();
        m.exit_initialization().unwrap();
        assert!(m.set(VR_BITRATE, Value::UInt32(125)).is_err());
        m.set(vr(0, 0), Value::Binary(&transmit(0x181, &[1])))
            .unwrap();
        m.set(vr(0, 2), Value::Clock(true)).unwrap();
        m.update_discrete_states().unwrap();
        m.enter_step_mode().unwrap();
        let r = m.do_step(0.0, 0.01, true).unwrap();
        let f = canpos_stack::Frame::new(0x181, &[1]).unwrap();
        let bits = canpos_host::bus::bits::frame_length(&f).total
            - canpos_host::bus::bits::INTERMISSION_BITS;
        // 2 µs a bit at 500 kbit/s.
        assert_eq!(r.last_time, f64::from(bits * 2_000) / 1e9);
    }

    #[test]
    fn bad_calls_get_reasons_and_change_nothing() {
        let mut m = instance(2, 125);
        m.enter_initialization(0.0).unwrap();
        m.exit_initialization().unwrap();
        assert!(m
            .do_step(0.5, 0.01, true)
            .unwrap_err()
            .contains("the bus is at 0 s"));
        assert!(m.do_step(0.0, 0.0, true).is_err());
        assert!(m.do_step(0.0, f64::NAN, true).is_err());
        // A malformed Rx_Data is refused at set and leaves the last one.
        m.set(vr(1, 0), Value::Binary(&transmit(0x182, &[2])))
            .unwrap();
        let e = m
            .set(vr(1, 0), Value::Binary(&[0x10, 0, 0, 0]))
            .unwrap_err();
        assert!(e.contains("Node2"), "{e}");
        assert_eq!(
            m.get(vr(1, 0)).unwrap(),
            Value::Binary(&transmit(0x182, &[2]))
        );
        assert!(m.get(vr(2, 0)).is_err());
        assert!(
            m.set(vr(0, 1), Value::Binary(&[])).is_err(),
            "Tx_Data is an output"
        );
        assert!(m.get(VR_NODE0 + 7).is_err());
    }
}
