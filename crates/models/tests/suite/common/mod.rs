//! Shared test harness: a node on a virtual clock, frames in, frames out.
#![allow(dead_code)]

use canpos_encoder::Sample;
use canpos_models::SensorNode;
use canpos_models::{self as models, Model};
use canpos_stack::storage::RamStorage;
use canpos_stack::{Frame, Instant, Node};

/// The model named `name` (`models::by_name`); an unknown name fails the test.
pub fn model(name: &str) -> &'static Model {
    models::by_name(name).unwrap()
}

/// A node of the model named `name`, powered on, its boot-up frames dropped.
pub fn booted(name: &str) -> Rig {
    Rig::booted(model(name))
}

/// The payloads of the EMCYs among `frames` (node-id 0x7F: COB-ID 0xFF).
pub fn emcys(frames: &[Frame]) -> Vec<Vec<u8>> {
    frames
        .iter()
        .filter(|f| f.std_id() == Some(0xFF))
        .map(|f| f.data().to_vec())
        .collect()
}

/// A measurement with channel `i + 1`'s magnet at `positions_nm[i]` (`None`: no magnet), the
/// other channels without one, at the default temperature.
pub fn sample(positions_nm: &[Option<i64>]) -> Sample {
    let mut s = Sample::default();
    s.positions_nm[..positions_nm.len()].copy_from_slice(positions_nm);
    s
}

/// An expedited SDO download request of the `n` (1…4) low bytes of `v` to `index`:`sub`; the
/// request carries all four bytes of `v`, as the command byte says which of them count.
pub fn expedited_download(index: u16, sub: u8, v: u32, n: usize) -> [u8; 8] {
    let [i0, i1] = index.to_le_bytes();
    let [b0, b1, b2, b3] = v.to_le_bytes();
    [0x23 | ((4 - n as u8) << 2), i0, i1, sub, b0, b1, b2, b3]
}

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
    pub fn with_config(model: &'static Model, cfg: canpos_models::DeviceConfig) -> Rig {
        let mut node = Node::new(model, cfg, RamStorage::default());
        node.power_on(Instant::ZERO);
        Rig {
            node,
            now: Instant::ZERO,
        }
    }

    /// Like `with_config`, with the boot-up frames dropped.
    pub fn booted_with(model: &'static Model, cfg: canpos_models::DeviceConfig) -> Rig {
        let mut r = Rig::with_config(model, cfg);
        r.take();
        r
    }

    /// Like `new`, with the boot-up frames dropped.
    pub fn booted(model: &'static Model) -> Rig {
        let mut r = Rig::new(model);
        r.take();
        r
    }

    /// Power off and on again at the current time; returns the boot-up frames.
    pub fn power_cycle(&mut self) -> Vec<Frame> {
        self.node.power_off();
        self.node.power_on(self.now);
        self.take()
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

    /// Sends the SDO request `req` (hex bytes) to node 0x7F and returns its one answer's bytes,
    /// which must come on 0x5FF.
    pub fn sdo(&mut self, req: &str) -> Vec<u8> {
        let (id, data) = self.req(0x67F, &hex(req));
        assert_eq!(id, 0x5FF, "answer to {req} on {id:03X}");
        data
    }

    /// Advances virtual time to `t`, running every deadline on the way (in order), and returns
    /// the frames produced, each with the time it was produced.
    pub fn run_until(&mut self, t: Instant) -> Vec<(Instant, Frame)> {
        let mut out = Vec::new();
        let mut steps = 0u32;
        loop {
            // A node whose deadline does not move on would spin here: fail instead of hanging.
            steps += 1;
            assert!(
                steps < 1_000_000,
                "the node's deadline does not advance at {:?}",
                self.now
            );
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

    /// Sends a store or restore command (0x1010 / 0x1011) and runs `ms` milliseconds on: every
    /// frame with its instant. The core answers as soon as the store returns (the store time a
    /// simulated device holds the answer for, D7, is the host's device wrapper's).
    pub fn store_cmd(&mut self, id: u16, data: &[u8], ms: u64) -> Vec<(Instant, Frame)> {
        let at = self.now;
        let first = self.send(id, data);
        let mut out: Vec<_> = first.into_iter().map(|f| (at, f)).collect();
        out.extend(self.advance_ms(ms));
        out
    }

    /// Advances time by `ms` milliseconds.
    pub fn advance_ms(&mut self, ms: u64) -> Vec<(Instant, Frame)> {
        let t = Instant::from_micros(self.now.micros() + ms * 1000);
        self.run_until(t)
    }

    /// One 1 ms measurement cycle: advances 1 ms, then hands the node `s`; returns the frames
    /// of both steps.
    pub fn cycle_sample(&mut self, s: &Sample) -> Vec<Frame> {
        let mut out: Vec<Frame> = self.advance_ms(1).into_iter().map(|(_, f)| f).collect();
        self.node.update_sample(s, self.now);
        out.extend(self.take());
        out
    }

    /// One 1 ms measurement cycle with channel 1's magnet at `nm` (`None`: no magnet).
    pub fn cycle(&mut self, nm: Option<i64>) -> Vec<Frame> {
        self.cycle_sample(&sample(&[nm]))
    }

    /// Like `cycle`, measuring `temperature_c` °C.
    pub fn cycle_temp(&mut self, nm: Option<i64>, temperature_c: i8) -> Vec<Frame> {
        self.cycle_sample(&Sample {
            temperature_c,
            ..sample(&[nm])
        })
    }

    /// One 1 ms measurement cycle with channel `i + 1`'s magnet at `positions_nm[i]`.
    pub fn cycle_channels(&mut self, positions_nm: &[Option<i64>]) -> Vec<Frame> {
        self.cycle_sample(&sample(positions_nm))
    }

    /// The object's value as the node holds it (not through SDO); an abort fails the test.
    pub fn read(&mut self, index: u16, sub: u8) -> u32 {
        self.node.read_object(index, sub).unwrap()
    }

    /// Expedited SDO download of the `n` low bytes of `v` to node 0x7F, expecting one answer:
    /// `Ok` on the confirmation, `Err(abort code)` on an abort.
    pub fn download(&mut self, index: u16, sub: u8, v: u32, n: usize) -> Result<(), u32> {
        let (_, a) = self.req(0x67F, &expedited_download(index, sub, v, n));
        match a[0] {
            0x60 => Ok(()),
            0x80 => Err(u32::from_le_bytes([a[4], a[5], a[6], a[7]])),
            _ => panic!("write {index:04X}:{sub} = {v:#X}: {a:02X?}"),
        }
    }

    /// Like `download`, where the write must succeed.
    pub fn write(&mut self, index: u16, sub: u8, v: u32, n: usize) {
        if let Err(code) = self.download(index, sub, v, n) {
            panic!("write {index:04X}:{sub} = {v:#X}: abort {code:08X}");
        }
    }

    /// LSS: switches the node to configuration, sends each of `requests` expecting its
    /// confirmation (`cs 00 …`), and switches it back to waiting.
    pub fn lss_configure(&mut self, requests: &[&str]) {
        self.send(0x7E5, &hex("04 01 00 00 00 00 00 00"));
        for req in requests {
            let d = hex(req);
            let a = self.send(0x7E5, &d);
            assert_eq!(a[0].data()[..2], [d[0], 0], "LSS {req}: {a:?}");
        }
        self.send(0x7E5, &hex("04 00 00 00 00 00 00 00"));
    }
}

/// Parses "23 00 18 01 FF 01 00 40" into bytes.
pub fn hex(s: &str) -> Vec<u8> {
    s.split_whitespace()
        .map(|b| u8::from_str_radix(b, 16).unwrap())
        .collect()
}
pub mod harness;
