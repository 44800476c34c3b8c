//! The runtime of a plain CiA 301 device (one [`Node`] with the [`Plain`] application, such as
//! an [`crate::eds_device`] device): frames in, the node's timers, frames out, and a sleep to
//! the node's next deadline on the same absolute clock as [`crate::runtime`].
//!
//! There is no measurement cycle and no fault model, so the sensor runtime's loop would be
//! mostly idle parts; this one is that loop reduced to the node. Its control requests
//! ([`requests`]) show the process objects and set inputs; a plain device has no magnets or
//! faults to drive.

use std::io;
use std::time::Duration;

use canpos_stack::model::{CommConfig, Model};
use canpos_stack::Plain;
use canpos_stack::{Instant, Node};
use serde_json::json;

use crate::can::{BusState, Transport};
use crate::file_storage::FileStorage;
use crate::runtime::{set_timer_slack_1ns, wait_until, Lateness, Msg, RuntimeHandle, SimHardware};

pub mod requests;

/// A plain device on a transport. [`PlainRuntime::spawn`] runs it.
pub struct PlainRuntime {
    transport: Box<dyn Transport>,
    node: Node<Plain, FileStorage>,
    /// The bus's bit rate and the store time around the node, as for a sensor.
    hw: SimHardware,
    epoch: std::time::Instant,
    lateness: Lateness,
    powered: bool,
    /// The state file, for the control state.
    storage: String,
    /// The inputs the control interface set, written back after a reset node.
    inputs: requests::Inputs,
}

impl PlainRuntime {
    /// The device `model` describes, unit `cfg`, storage `storage`, on `transport`;
    /// `bus_bitrate_kbps` as for [`crate::Runtime::new`].
    pub fn new(
        transport: Box<dyn Transport>,
        bus_bitrate_kbps: Option<u32>,
        model: &'static Model,
        cfg: CommConfig,
        storage: FileStorage,
    ) -> PlainRuntime {
        let storage_name = storage.path().display().to_string();
        let node = Node::with_app(model, cfg, Plain, storage);
        let bus = bus_bitrate_kbps
            .or_else(|| transport.bus_bitrate())
            .map(|b| b.min(u32::from(u16::MAX)) as u16);
        PlainRuntime {
            transport,
            node,
            hw: SimHardware::new(bus),
            epoch: std::time::Instant::now(),
            lateness: Lateness::default(),
            powered: false,
            storage: storage_name,
            inputs: requests::Inputs::default(),
        }
    }

    fn now(&self) -> Instant {
        Instant::from_micros(self.epoch.elapsed().as_micros() as u64)
    }

    /// The node (for tests and status output).
    pub fn node(&self) -> &Node<Plain, FileStorage> {
        &self.node
    }

    /// Powers the node on now: its boot-up goes out at once.
    pub fn power_on(&mut self) -> io::Result<()> {
        let now = self.now();
        self.node.power_on(now);
        self.powered = true;
        self.flush(now)
    }

    /// Sends everything the node has to send at `now` (its due timers first). After a reset,
    /// first the inputs the control interface set go back into the dictionary: the module's
    /// process reads its terminals again before anything reads the objects.
    fn flush(&mut self, now: Instant) -> io::Result<()> {
        self.inputs.after_reset(&mut self.node, now);
        while let Some(f) = self.hw.poll(&mut self.node, now) {
            if let Err(e) = self.transport.send(&f) {
                tracing::warn!(error = %e, "send failed");
            }
            self.inputs.after_reset(&mut self.node, now);
        }
        Ok(())
    }

    /// Runs on a new thread (powered on first if [`PlainRuntime::power_on`] was not called)
    /// until stopped through the handle or until the transport dies.
    pub fn spawn(mut self) -> io::Result<RuntimeHandle> {
        let (tx, rx) = crossbeam_channel::bounded(64);
        RuntimeHandle::spawn_loop(tx, rx, move |msgs| {
            set_timer_slack_1ns();
            if !self.powered {
                self.power_on()?;
            }
            let r = self.run_loop(&msgs);
            tracing::info!(lateness = %self.lateness, "runtime stopped");
            r.map(|()| self.lateness)
        })
    }

    fn run_loop(&mut self, msgs: &crossbeam_channel::Receiver<Msg>) -> io::Result<()> {
        let (mut dropped, mut state) = (0, BusState::ErrorActive);
        loop {
            // Lost frames are logged only: the sensors' EMCYs for them come from their models'
            // tables.
            if self.transport.dropped() > dropped {
                dropped = self.transport.dropped();
                tracing::warn!(total = dropped, "CAN frames lost");
            }
            if self.transport.bus_state() != state {
                let old = std::mem::replace(&mut state, self.transport.bus_state());
                tracing::warn!(from = ?old, to = ?state, "CAN controller state");
                // Bus-off is a communication error (0x1029); leaving it the recovery EMCY.
                if state == BusState::BusOff || old == BusState::BusOff {
                    self.node.set_bus_off(state == BusState::BusOff);
                }
            }
            let mut now = self.now();
            while let Some(rx) = self.transport.try_recv()? {
                // Each frame at the time it is handled (the store time counts from it).
                now = self.now().max(now);
                self.hw.receive(&mut self.node, &rx.frame, now);
                self.flush(now)?;
            }
            self.flush(now)?;
            while let Ok(m) = msgs.try_recv() {
                match m {
                    Msg::Stop => return Ok(()),
                    Msg::Request(req, reply) => {
                        let now = self.now();
                        let answer = requests::handle(
                            &mut self.node,
                            req,
                            &self.storage,
                            &mut self.inputs,
                            now,
                        )
                        .unwrap_or_else(|e| json!({"ok": false, "error": e}));
                        let _ = reply.send(answer);
                        // What the request caused (a TPDO of a changed input) goes out now.
                        self.flush(now)?;
                    }
                }
            }
            let target = [self.node.poll_timeout(), self.hw.deadline()]
                .into_iter()
                .flatten()
                .min()
                .map(|t| self.epoch + Duration::from_micros(t.micros()));
            if let Some(late) = wait_until(self.transport.receiver(), msgs, target) {
                self.lateness.record(late.as_micros() as u64);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::Request;
    use crate::eds_device::{build, FileKind, Overrides};
    use crate::mem::MemBus;
    use canpos_stack::Frame;

    fn recv_id(port: &mut dyn Transport, id: u16, within: Duration) -> Option<Frame> {
        let end = std::time::Instant::now() + within;
        while let Ok(Some(rx)) = port.recv_deadline(end) {
            if rx.frame.std_id() == Some(id) {
                return Some(rx.frame);
            }
        }
        None
    }

    #[test]
    fn an_eds_device_boots_answers_and_stops() {
        let dir = tempfile::tempdir().unwrap();
        let text = include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../examples/io-device.eds"
        ));
        let o = Overrides {
            node_id: Some(9),
            bitrate_kbps: None,
            serial: None,
        };
        let d = build(text, "io.eds", FileKind::Eds, &o).unwrap();
        let bus = MemBus::new();
        let mut master = bus.attach();
        let storage = FileStorage::new(d.state_file(dir.path()));
        let rt = PlainRuntime::new(Box::new(bus.attach()), None, d.model, d.cfg, storage);
        let h = rt.spawn().unwrap();
        let boot = recv_id(&mut master, 0x709, Duration::from_secs(2)).expect("boot-up");
        assert_eq!(boot.data(), &[0]);
        // 0x2102 "Offset" (INTEGER32, default -500).
        let req = Frame::new(0x609, &[0x40, 0x02, 0x21, 0, 0, 0, 0, 0]).unwrap();
        master.send(&req).unwrap();
        let r = recv_id(&mut master, 0x589, Duration::from_secs(2)).expect("SDO answer");
        assert_eq!(r.data()[..4], [0x43, 0x02, 0x21, 0]);
        assert_eq!(&r.data()[4..8], &(-500i32).to_le_bytes());
        // The heartbeat (50 ms) comes from the loop sleeping to the node's own deadline.
        let hb = Frame::new(0x609, &[0x2B, 0x17, 0x10, 0, 50, 0, 0, 0]).unwrap();
        master.send(&hb).unwrap();
        assert_eq!(
            recv_id(&mut master, 0x589, Duration::from_secs(2))
                .unwrap()
                .data()[0],
            0x60
        );
        let first = recv_id(&mut master, 0x709, Duration::from_secs(1)).expect("heartbeat");
        assert_eq!(first.data(), &[0x7F]);
        // The control interface: the state (this file has no process objects), and a
        // sensor's request refused with the ones it takes.
        let st = h.control().request(Request::State { sensor: None });
        assert_eq!(
            (&st["ok"], &st["nmt"]),
            (&json!(true), &json!("pre-operational")),
            "{st}"
        );
        assert_eq!(st["process"], json!([]), "{st}");
        let bad = h.control().request(Request::PowerCycle { sensor: None });
        assert_eq!(bad["ok"], false, "{bad}");
        assert!(
            bad["error"].as_str().unwrap().contains("set-input"),
            "{bad}"
        );
        h.stop().unwrap();
    }

    /// An input set through the control interface is the module's terminal, not a value of
    /// its dictionary: an NMT reset node (a PLC's start-up sends one to every node) reloads the
    /// defaults, and the input reads what the terminal says again at once. Before, it read 0
    /// until the next set-input. An output goes back to its default, as the reset says.
    #[test]
    fn an_input_set_holds_across_a_reset_node() {
        let dir = tempfile::tempdir().unwrap();
        let text = include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../examples/io-401.eds"
        ));
        let o = Overrides {
            node_id: Some(7),
            bitrate_kbps: None,
            serial: None,
        };
        let d = build(text, "io-401.eds", FileKind::Eds, &o).unwrap();
        let bus = MemBus::new();
        let mut master = bus.attach();
        let storage = FileStorage::new(d.state_file(dir.path()));
        let rt = PlainRuntime::new(Box::new(bus.attach()), None, d.model, d.cfg, storage);
        let h = rt.spawn().unwrap();
        recv_id(&mut master, 0x707, Duration::from_secs(2)).expect("boot-up");
        let set = h.control().request(Request::SetInput {
            sensor: None,
            index: json!("0x6000"),
            sub: Some(json!(1)),
            value: json!("0xA5"),
        });
        assert_eq!(set["ok"], true, "{set}");
        let upload = |master: &mut dyn Transport, index: u16, sub: u8| {
            let [lo, hi] = index.to_le_bytes();
            let req = Frame::new(0x607, &[0x40, lo, hi, sub, 0, 0, 0, 0]).unwrap();
            master.send(&req).unwrap();
            let r = recv_id(master, 0x587, Duration::from_secs(2)).expect("SDO answer");
            r.data()[4]
        };
        // An output the master wrote.
        let out = Frame::new(0x607, &[0x2F, 0x00, 0x62, 1, 0x3C, 0, 0, 0]).unwrap();
        master.send(&out).unwrap();
        recv_id(&mut master, 0x587, Duration::from_secs(2)).expect("SDO answer");
        master
            .send(&Frame::new(0x000, &[0x81, 7]).unwrap())
            .unwrap();
        let boot = recv_id(&mut master, 0x707, Duration::from_secs(2)).expect("boot-up");
        assert_eq!(boot.data(), &[0]);
        assert_eq!(
            upload(&mut master, 0x6000, 1),
            0xA5,
            "the input after the reset"
        );
        assert_eq!(
            upload(&mut master, 0x6200, 1),
            0,
            "the output after the reset"
        );
        let st = h.control().request(Request::State { sensor: None });
        assert_eq!(st["process"][0]["value"], 0xA5, "{st}");
        h.stop().unwrap();
    }
}
