//! The monitor's state: what it learnt of each node (its TPDO mappings and scaling, read by
//! SDO) and the bus load of the last second; `canpos monitor` and the dashboard print frames
//! through it.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, SystemTime};

use anyhow::Result;
use canpos_stack::Frame;

use crate::client::{decode, sdo, SdoClient, SdoError};

/// Bus load from the frames a listener sees: their bits on the wire (stuff bits included) over
/// the last second of their timestamps.
pub(crate) struct LoadMeter {
    bit_ns: u64,
    window: VecDeque<(SystemTime, u64)>,
    bits: u64,
}

impl LoadMeter {
    pub(crate) fn new(kbps: u32) -> Self {
        LoadMeter {
            bit_ns: 1_000_000 / u64::from(kbps.max(1)),
            window: VecDeque::new(),
            bits: 0,
        }
    }

    /// Adds a frame; returns (load %, frames/s) over the second before it.
    pub(crate) fn add(&mut self, t: SystemTime, f: &Frame) -> (f64, usize) {
        let bits = u64::from(canpos_host::bus::bits::frame_length(f).total);
        self.window.push_back((t, bits));
        self.bits += bits;
        while let Some(&(t0, b)) = self.window.front() {
            if t.duration_since(t0).unwrap_or_default() < Duration::from_secs(1) {
                break;
            }
            self.window.pop_front();
            self.bits -= b;
        }
        let pct = (self.bits * self.bit_ns) as f64 / 1e9 * 100.0;
        (pct.min(100.0), self.window.len())
    }
}

/// The state of a running monitor: what is known about each node.
#[derive(Default)]
pub struct Monitor {
    nodes: HashMap<u8, Option<decode::NodeInfo>>,
    /// COB-ID → (node, mapping) for the TPDOs learned.
    tpdo: HashMap<u16, (u8, u8, Vec<u32>)>,
}

impl Monitor {
    /// A monitor that knows nothing yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The node that produced `f` (boot-up, heartbeat, EMCY, TPDO, SDO answer), if any.
    fn producer(f: &Frame) -> Option<u8> {
        if f.is_extended() {
            return None;
        }
        let id = f.id() as u16;
        let node = (id & 0x7F) as u8;
        let fc = id & 0x780;
        (node != 0 && matches!(fc, 0x080 | 0x180 | 0x280 | 0x380 | 0x480 | 0x580 | 0x700))
            .then_some(node)
    }

    /// Whether the node's configuration still has to be read.
    pub fn needs_query(&self, f: &Frame) -> Option<u8> {
        let n = Self::producer(f)?;
        (!self.nodes.contains_key(&n)).then_some(n)
    }

    /// Records what was read about `node` (`None`: it could not be read).
    pub fn learn(&mut self, node: u8, info: Option<decode::NodeInfo>) {
        if let Some(i) = &info {
            self.tpdo.retain(|_, (n, _, _)| *n != node);
            for (num, cob, map) in &i.tpdos {
                self.tpdo.insert(*cob, (node, *num, map.clone()));
            }
        }
        self.nodes.insert(node, info);
    }

    /// Forgets a node (after a boot-up its mapping may have changed).
    pub fn forget(&mut self, node: u8) {
        self.nodes.remove(&node);
        self.tpdo.retain(|_, (n, _, _)| *n != node);
    }

    /// Reads a node's measuring steps and TPDO configuration by SDO.
    pub fn query(client: &mut SdoClient<'_>) -> Result<decode::NodeInfo, SdoError> {
        let mut info = decode::NodeInfo {
            position_step_nm: match client.read_u32(0x6005, 1) {
                Ok(v) => Some(v),
                // No answer at all: nothing else will answer either.
                Err(e @ (SdoError::Timeout | SdoError::Io(_))) => return Err(e),
                Err(_) => None,
            },
            ..Default::default()
        };
        info.velocity_step = client.read_u32(0x6005, 2).ok();
        for n in 0..4u16 {
            let cob = match client.read_u32(0x1800 + n, 1) {
                Ok(v) => v,
                Err(SdoError::Abort(_)) => break,
                Err(e) => return Err(e),
            };
            if cob & 0x8000_0000 != 0 {
                continue;
            }
            let count = client.read_u32(0x1A00 + n, 0)?.min(64);
            let mut map = Vec::new();
            for s in 1..=count as u8 {
                map.push(client.read_u32(0x1A00 + n, s)?);
            }
            info.tpdos.push((n as u8 + 1, (cob & 0x7FF) as u16, map));
        }
        Ok(info)
    }

    /// Decodes one frame into a line of text (without timestamp).
    pub fn describe(&self, f: &Frame) -> String {
        if !f.is_extended() && !f.is_remote() {
            if let Some((node, num, map)) = self.tpdo.get(&(f.id() as u16)) {
                let info = self
                    .nodes
                    .get(node)
                    .and_then(|i| i.as_ref())
                    .cloned()
                    .unwrap_or_default();
                return format!(
                    "node {node} TPDO{num} {}",
                    decode::decode_pdo(&info, map, f.data())
                );
            }
        }
        decode::describe(f).unwrap_or_else(|| {
            format!(
                "0x{:03X} {}",
                f.id(),
                if f.is_remote() {
                    "RTR".to_string()
                } else {
                    sdo::hex_string(f.data())
                }
            )
        })
    }

    /// Whether `f` concerns `node` (for `--node`).
    pub fn concerns(&self, f: &Frame, node: u8) -> bool {
        if f.is_extended() {
            return false;
        }
        let id = f.id() as u16;
        if let Some((n, _, _)) = self.tpdo.get(&id) {
            return *n == node;
        }
        match id {
            0x000 => f.data().get(1).is_some_and(|n| *n == 0 || *n == node),
            0x080 => true,
            0x7E4 | 0x7E5 => true,
            _ => (id & 0x7F) as u8 == node && id >= 0x080,
        }
    }
}
