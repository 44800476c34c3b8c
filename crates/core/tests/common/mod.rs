//! Shared test harness: a node on a virtual clock, frames in, frames out.
#![allow(dead_code)]

use canpos_core::models::Model;
use canpos_core::storage::RamStorage;
use canpos_core::{Frame, Instant, Node, SensorNode};

/// A node with RAM storage on a virtual clock.
pub struct Rig {
    pub node: SensorNode<RamStorage>,
    pub now: Instant,
}

impl Rig {
    /// Powers a node of `model` (default config) on at t = 0 and drops nothing: call `take()`.
    pub fn new(model: &'static Model) -> Rig {
        let mut node = Node::new(model, model.default_config, RamStorage::default());
        node.power_on(Instant::ZERO);
        Rig {
            node,
            now: Instant::ZERO,
        }
    }

    /// Like `new` with a custom configuration.
    pub fn with_config(model: &'static Model, cfg: canpos_core::models::DeviceConfig) -> Rig {
        let mut node = Node::new(model, cfg, RamStorage::default());
        node.power_on(Instant::ZERO);
        Rig {
            node,
            now: Instant::ZERO,
        }
    }

    /// All frames waiting.
    pub fn take(&mut self) -> Vec<Frame> {
        let mut v = Vec::new();
        while let Some(f) = self.node.poll_transmit() {
            v.push(f);
        }
        v
    }

    /// Sends a frame and returns what the node answers immediately.
    pub fn send(&mut self, id: u16, data: &[u8]) -> Vec<Frame> {
        let f = Frame::new(id, data).unwrap();
        self.node.handle_frame(&f, self.now);
        self.take()
    }

    /// Sends a frame and expects exactly one answer (returned as (id, bytes)).
    pub fn req(&mut self, id: u16, data: &[u8]) -> (u16, Vec<u8>) {
        let r = self.send(id, data);
        assert_eq!(
            r.len(),
            1,
            "expected one answer to {id:03X} {data:02X?}, got {r:?}"
        );
        (r[0].std_id().unwrap(), r[0].data().to_vec())
    }

    /// Advances virtual time to `t`, running every deadline on the way (in order), and returns
    /// the frames produced, each with the time it was produced.
    pub fn run_until(&mut self, t: Instant) -> Vec<(Instant, Frame)> {
        let mut out = Vec::new();
        loop {
            match self.node.poll_timeout() {
                Some(d) if d <= t => {
                    let d = d.max(self.now);
                    self.now = d;
                    self.node.handle_timeout(d);
                    while let Some(f) = self.node.poll_transmit() {
                        out.push((d, f));
                    }
                }
                _ => break,
            }
        }
        self.now = t;
        self.node.handle_timeout(t);
        while let Some(f) = self.node.poll_transmit() {
            out.push((t, f));
        }
        out
    }

    /// Advances time by `ms` milliseconds.
    pub fn advance_ms(&mut self, ms: u64) -> Vec<(Instant, Frame)> {
        let t = Instant(self.now.0 + ms * 1000);
        self.run_until(t)
    }
}

/// Parses "23 00 18 01 FF 01 00 40" into bytes.
pub fn hex(s: &str) -> Vec<u8> {
    s.split_whitespace()
        .map(|b| u8::from_str_radix(b, 16).unwrap())
        .collect()
}
