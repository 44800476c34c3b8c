//! What the dashboard knows about the bus: the nodes it heard (boot-ups, heartbeats, EMCYs,
//! TPDOs, answers to its scan), their process data decimated for the plots, and the state the
//! control interfaces report. One thread owns the bus connection; it also runs the SDO
//! transfers the page asks for, so that the dashboard is one SDO client, never two at once.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use canpos_core::models::{self, Model};
use canpos_core::od::Default as OdDefault;
use canpos_core::Frame;
use canpos_host::control::{self, Request};
use canpos_host::crossbeam_channel::{Receiver, Sender};
use canpos_host::{ControlHandle, RxFrame, Transport};
use serde_json::{json, Value};

use crate::master::decode::{self, NodeInfo};
use crate::master::sdo::{abort_meaning, SdoClient, SdoError};
use crate::master::Monitor;

/// Plot samples are kept at most this often per channel (the server-side decimation: a TPDO
/// every millisecond becomes 50 points per second).
pub const SAMPLE_PERIOD: Duration = Duration::from_millis(20);
/// EMCYs kept per node.
const EMCY_LOG: usize = 100;
/// SDO timeout of the dashboard's own reads.
const SDO_TIMEOUT: Duration = Duration::from_millis(300);
/// A node that did not answer the identity reads is asked again after this long.
const REQUERY: Duration = Duration::from_secs(5);

/// How the dashboard reaches a sensor's control interface.
#[derive(Clone)]
pub enum Link {
    /// The runtime of this process (`--web` on `run`, `scenario`, the demo).
    Local(ControlHandle),
    /// A control interface over TCP (`canpos dashboard --control ADDR`).
    Remote(String),
}

impl Link {
    /// Sends one request; a transport failure becomes an `"ok":false` answer.
    pub fn request(&self, req: Request) -> Value {
        match self {
            Link::Local(h) => h.request(req),
            Link::Remote(addr) => control::call(addr.as_str(), &req, Duration::from_secs(5))
                .unwrap_or_else(
                    |e| json!({"ok": false, "error": format!("control interface {addr}: {e}")}),
                ),
        }
    }
}

/// One sensor behind a control interface.
pub struct Controller {
    /// Where it is.
    pub link: Link,
    /// Its sensor index there.
    pub sensor: usize,
    /// Its last `state` answer.
    pub state: Option<Value>,
}

/// One plot point.
#[derive(Clone, Copy)]
pub struct Sample {
    /// Sequence number (the SSE streams send what is newer than they sent).
    pub seq: u64,
    /// Seconds since the dashboard started.
    pub t: f64,
    /// Position, mm (NaN: not in the PDO / unknown).
    pub pos: f64,
    /// Velocity, mm/s.
    pub vel: f64,
}

/// One position channel of a node.
#[derive(Default)]
pub struct Channel {
    /// Decimated history, oldest first.
    pub samples: VecDeque<Sample>,
    /// Latest position (mm) and velocity (mm/s) from a TPDO.
    pub pos: Option<f64>,
    /// Latest velocity.
    pub vel: Option<f64>,
    /// Latest cam state (0x6300/n).
    pub cam: Option<u8>,
    /// Latest work-area state (0x6400/n).
    pub area: Option<u8>,
    last_sample: Option<Instant>,
}

/// One EMCY heard.
pub struct Emcy {
    /// Seconds since the dashboard started.
    pub t: f64,
    /// Error code.
    pub code: u16,
    /// Error register sent with it.
    pub register: u8,
    /// Manufacturer-specific bytes.
    pub msef: [u8; 5],
}

/// A node on the bus.
#[derive(Default)]
pub struct Node {
    /// Model recognised from 0x1018/1 and 0x1008 (or reported by its control interface).
    pub model: Option<&'static Model>,
    /// 0x1008.
    pub name: Option<String>,
    /// 0x1018/1…4.
    pub identity: [Option<u32>; 4],
    /// Last NMT state heard (heartbeat / boot-up byte).
    pub nmt: Option<u8>,
    /// Measuring steps and TPDO mappings.
    pub info: Option<NodeInfo>,
    /// Error register from the last EMCY.
    pub error_register: Option<u8>,
    /// EMCY log, oldest first.
    pub emcy: VecDeque<Emcy>,
    /// Position channels (index = sub-index − 1).
    pub channels: Vec<Channel>,
    /// 0x6503 when a TPDO carries it.
    pub alarms: Option<u16>,
    /// The model was given (`--eds NODE=FILE`): identification does not replace it.
    pub pinned: bool,
    /// When the identity was last asked for.
    asked: Option<Instant>,
}

/// Everything the HTTP side reads.
pub struct Shared {
    /// Start of the dashboard (the plots' time zero).
    pub start: Instant,
    /// Plot window, s.
    pub window_s: f64,
    /// The bus URL (for the page header).
    pub bus: String,
    /// Nodes by node-id.
    pub nodes: BTreeMap<u8, Node>,
    /// Sensors behind control interfaces.
    pub controllers: Vec<Controller>,
    /// Frames received in total.
    pub frames: u64,
    /// Frames per second over the last full second.
    pub frames_per_s: f64,
    /// Next sample sequence number.
    pub seq: u64,
    /// Open event streams (a browser that left holds none).
    pub streams: usize,
    /// Why the bus connection ended, once it has.
    pub bus_error: Option<String>,
    rate_mark: (Instant, u64),
}

impl Shared {
    /// Empty state for a bus.
    pub fn new(bus: String, window_s: f64, controllers: Vec<Controller>) -> Shared {
        let now = Instant::now();
        Shared {
            start: now,
            window_s,
            bus,
            nodes: BTreeMap::new(),
            controllers,
            frames: 0,
            frames_per_s: 0.0,
            seq: 1,
            streams: 0,
            bus_error: None,
            rate_mark: (now, 0),
        }
    }

    /// The controller of node `id` (by the node-id its state reports).
    pub fn controller_of(&self, id: u8) -> Option<&Controller> {
        self.controllers
            .iter()
            .find(|c| c.state.as_ref().and_then(|s| s["node_id"].as_u64()) == Some(id.into()))
    }

    /// Gives node `id` the object table of `model` (an EDS the user named).
    pub fn pin_model(&mut self, id: u8, model: &'static Model) {
        let n = self.node(id);
        n.model = Some(model);
        n.pinned = true;
    }

    fn node(&mut self, id: u8) -> &mut Node {
        self.nodes.entry(id).or_default()
    }

    /// Takes in one received frame.
    pub fn note(&mut self, rx: &RxFrame, now: Instant) {
        self.frames += 1;
        let f = rx.frame;
        let Some(id) = f.std_id() else { return };
        if f.is_remote() {
            return;
        }
        let node = (id & 0x7F) as u8;
        let d = f.data();
        let t = now.duration_since(self.start).as_secs_f64();
        match id & 0x780 {
            0x700 if node != 0 && d.len() == 1 => {
                let n = self.node(node);
                if d[0] == 0 {
                    // A boot-up: the mapping may be new (stored data, another unit).
                    n.info = None;
                    n.asked = None;
                }
                // After its boot-up a node is pre-operational (CiA 301).
                n.nmt = Some(if d[0] == 0 { 0x7F } else { d[0] & 0x7F });
            }
            0x080 if node != 0 && d.len() == 8 => {
                let n = self.node(node);
                n.error_register = Some(d[2]);
                n.emcy.push_back(Emcy {
                    t,
                    code: u16::from_le_bytes([d[0], d[1]]),
                    register: d[2],
                    msef: [d[3], d[4], d[5], d[6], d[7]],
                });
                while n.emcy.len() > EMCY_LOG {
                    n.emcy.pop_front();
                }
            }
            // An answer to the scan's 0x1000 read (or to anyone's SDO): the node exists.
            0x580 if node != 0 => {
                self.node(node);
            }
            _ => {}
        }
        self.note_pdo(id, d, now, t);
    }

    fn note_pdo(&mut self, cob: u16, d: &[u8], now: Instant, t: f64) {
        let window = self.window_s;
        let mut seq = self.seq;
        for (_, n) in self.nodes.iter_mut() {
            let Some(info) = &n.info else { continue };
            let Some((_, _, map)) = info.tpdos.iter().find(|(_, c, _)| *c == cob) else {
                continue;
            };
            let mut touched = Vec::new();
            for (index, sub, v) in pdo_fields(map, d) {
                let ch = usize::from(sub).saturating_sub(1);
                if (0x6020..=0x6400).contains(&index) && sub >= 1 && n.channels.len() <= ch {
                    n.channels.resize_with(ch + 1, Channel::default);
                }
                match index {
                    0x6020 => {
                        let step = info.position_step_nm.unwrap_or(1000) as f64;
                        n.channels[ch].pos = Some(v as f64 * step / 1e6);
                        touched.push(ch);
                    }
                    0x6030 => {
                        let step = info.velocity_step.unwrap_or(100) as f64;
                        n.channels[ch].vel = Some(v as f64 * step / 100.0);
                        touched.push(ch);
                    }
                    0x6300 => n.channels[ch].cam = Some(v as u8),
                    0x6400 => n.channels[ch].area = Some(v as u8),
                    0x6503 => n.alarms = Some(v as u16),
                    _ => {}
                }
            }
            for ch in touched {
                let c = &mut n.channels[ch];
                if c.last_sample
                    .is_some_and(|l| now.duration_since(l) < SAMPLE_PERIOD)
                {
                    continue;
                }
                c.last_sample = Some(now);
                c.samples.push_back(Sample {
                    seq,
                    t,
                    pos: c.pos.unwrap_or(f64::NAN),
                    vel: c.vel.unwrap_or(f64::NAN),
                });
                seq += 1;
                while c.samples.front().is_some_and(|s| s.t < t - window) {
                    c.samples.pop_front();
                }
            }
        }
        self.seq = seq;
    }

    /// Updates frames/s once a second has passed since the last update.
    pub fn tick(&mut self, now: Instant) {
        let (at, count) = self.rate_mark;
        let dt = now.duration_since(at).as_secs_f64();
        if dt >= 1.0 {
            self.frames_per_s = (self.frames - count) as f64 / dt;
            self.rate_mark = (now, self.frames);
        }
    }
}

/// The mapped values of a TPDO: (index, sub, value sign-extended to i64). Stops at a mapping
/// the data does not cover.
pub fn pdo_fields(mapping: &[u32], data: &[u8]) -> Vec<(u16, u8, i64)> {
    let mut out = Vec::new();
    let mut bit = 0usize;
    for &m in mapping {
        let bits = (m & 0xFF) as usize;
        if bits == 0 || bits > 32 || bit + bits > data.len() * 8 {
            break;
        }
        let mut raw: u64 = 0;
        for i in 0..bits {
            let b = bit + i;
            if data[b / 8] >> (b % 8) & 1 != 0 {
                raw |= 1 << i;
            }
        }
        bit += bits;
        let shift = 64 - bits as u32;
        // Positions and velocities are signed; the state registers fit in their bits anyway.
        let v = match (m >> 16) as u16 {
            0x6020 | 0x6030 => ((raw << shift) as i64) >> shift,
            _ => raw as i64,
        };
        out.push(((m >> 16) as u16, (m >> 8) as u8, v));
    }
    out
}

/// The model whose table has this vendor-id and device name (0x1018/1, 0x1008).
pub fn recognise(vendor: Option<u32>, name: Option<&str>) -> Option<&'static Model> {
    let vendor = vendor?;
    let candidates: Vec<&'static Model> = models::all()
        .into_iter()
        .filter(|m| {
            m.entries
                .iter()
                .any(|e| e.index == 0x1018 && e.sub == 1 && e.default == OdDefault::Const(vendor))
        })
        .collect();
    if candidates.len() == 1 {
        return Some(candidates[0]);
    }
    candidates.into_iter().find(|m| {
        m.entries.iter().any(|e| {
            e.index == 0x1008 && matches!(e.default, OdDefault::Str(s) if Some(*s) == name)
        })
    })
}

/// A request from the HTTP side to the bus thread.
pub enum BusCmd {
    /// SDO upload.
    Read(u8, u16, u8, Sender<Result<Vec<u8>, String>>),
    /// SDO download.
    Write(u8, u16, u8, Vec<u8>, Sender<Result<(), String>>),
    /// Ask every node-id for 0x1000 (answers are noted as frames).
    Scan,
}

fn sdo_text(e: SdoError) -> String {
    match e {
        SdoError::Abort(code) => format!("SDO abort 0x{code:08X}: {}", abort_meaning(code)),
        e => e.to_string(),
    }
}

/// The bus thread: takes in frames, identifies new nodes, runs the page's SDO transfers.
/// Returns when `stop` fires or the bus connection ends.
pub fn run_bus(
    mut bus: Box<dyn Transport>,
    shared: Arc<Mutex<Shared>>,
    cmds: Receiver<BusCmd>,
    stop: Receiver<()>,
) {
    let mut backlog: Vec<RxFrame> = Vec::new();
    let result = (|| -> std::io::Result<()> {
        scan(&mut *bus)?;
        loop {
            if stop.try_recv().is_ok() {
                return Ok(());
            }
            let first = bus.recv_timeout(Some(Duration::from_millis(10)))?;
            backlog.extend(first);
            while let Some(rx) = bus.try_recv()? {
                backlog.push(rx);
                if backlog.len() > 4096 {
                    break;
                }
            }
            let now = Instant::now();
            let ask = {
                let mut s = shared.lock().unwrap();
                for rx in backlog.drain(..) {
                    s.note(&rx, now);
                }
                s.tick(now);
                s.nodes
                    .iter()
                    .find(|(_, n)| {
                        n.info.is_none() && n.asked.is_none_or(|a| now.duration_since(a) > REQUERY)
                    })
                    .map(|(id, _)| *id)
            };
            if let Some(id) = ask {
                identify(&mut *bus, id, &shared, &mut backlog);
            }
            while let Ok(cmd) = cmds.try_recv() {
                match cmd {
                    BusCmd::Read(node, index, sub, reply) => {
                        let mut c =
                            SdoClient::new(&mut *bus, node, SDO_TIMEOUT).keep_other_frames();
                        let r = c.upload(index, sub).map_err(sdo_text);
                        backlog.extend(c.take_other_frames());
                        let _ = reply.send(r);
                    }
                    BusCmd::Write(node, index, sub, data, reply) => {
                        let mut c =
                            SdoClient::new(&mut *bus, node, SDO_TIMEOUT).keep_other_frames();
                        let r = c.download(index, sub, &data).map_err(sdo_text);
                        backlog.extend(c.take_other_frames());
                        let _ = reply.send(r);
                    }
                    BusCmd::Scan => scan(&mut *bus)?,
                }
            }
        }
    })();
    if let Err(e) = result {
        // A bus that closes while the dashboard stops (the process ends) is no error.
        if !matches!(
            stop.try_recv(),
            Err(canpos_host::crossbeam_channel::TryRecvError::Empty)
        ) {
            return;
        }
        tracing::error!("dashboard: the bus connection ended: {e}");
        shared.lock().unwrap().bus_error = Some(e.to_string());
    }
}

/// Sends the scan's 0x1000 reads in small bursts (a slow hub client would drop a flood).
fn scan(bus: &mut dyn Transport) -> std::io::Result<()> {
    for node in 1..=127u8 {
        bus.send(&Frame::std8(
            0x600 + u16::from(node),
            [0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0],
        ))?;
        if node % 16 == 0 {
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    Ok(())
}

/// Reads a node's identity, name, measuring steps and TPDO mappings.
fn identify(bus: &mut dyn Transport, id: u8, shared: &Mutex<Shared>, backlog: &mut Vec<RxFrame>) {
    shared.lock().unwrap().node(id).asked = Some(Instant::now());
    let mut c = SdoClient::new(bus, id, SDO_TIMEOUT).keep_other_frames();
    let mut identity = [None; 4];
    for (i, slot) in identity.iter_mut().enumerate() {
        match c.read_u32(0x1018, i as u8 + 1) {
            Ok(v) => *slot = Some(v),
            // A node that does not answer (stopped, gone) is asked again later; the other
            // reads would only time out too and hold up the bus thread.
            Err(SdoError::Timeout | SdoError::Io(_)) => {
                backlog.extend(c.take_other_frames());
                return;
            }
            Err(_) => {}
        }
    }
    let name = c.upload(0x1008, 0).ok().map(|d| {
        String::from_utf8_lossy(&d)
            .trim_end_matches('\0')
            .to_string()
    });
    let info = Monitor::query(&mut c).ok();
    backlog.extend(c.take_other_frames());
    let mut s = shared.lock().unwrap();
    let n = s.node(id);
    if identity[0].is_some() {
        n.identity = identity;
        n.name = name;
        if !n.pinned {
            n.model = recognise(identity[0], n.name.as_deref());
        }
    }
    if info.is_some() {
        n.info = info;
    }
}

/// Polls the state of every controller (4 times a second); the node-id it reports ties it to
/// a node, and a node that only its control interface knows (stopped, silent) still shows.
pub fn run_poller(shared: Arc<Mutex<Shared>>, stop: Receiver<()>) {
    loop {
        let links: Vec<(Link, usize)> = shared
            .lock()
            .unwrap()
            .controllers
            .iter()
            .map(|c| (c.link.clone(), c.sensor))
            .collect();
        let states: Vec<Value> = links
            .into_iter()
            .map(|(l, i)| l.request(Request::State { sensor: Some(i) }))
            .collect();
        {
            let mut s = shared.lock().unwrap();
            for (c, st) in s.controllers.iter_mut().zip(states) {
                c.state = (st["ok"] == true).then_some(st);
            }
            let known: Vec<(u8, Option<&'static Model>)> = s
                .controllers
                .iter()
                .filter_map(|c| c.state.as_ref())
                .filter_map(|st| {
                    let id = st["node_id"].as_u64().filter(|id| (1..=127).contains(id))?;
                    Some((id as u8, st["model"].as_str().and_then(models::by_name)))
                })
                .collect();
            for (id, model) in known {
                let n = s.node(id);
                if n.model.is_none() {
                    n.model = model;
                }
            }
        }
        if stop.recv_timeout(Duration::from_millis(250)).is_ok() {
            return;
        }
    }
}

/// Finds the sensors behind a control address: indices 0, 1, … until one is refused.
pub fn probe(addr: &str) -> Vec<Controller> {
    let mut out = Vec::new();
    for i in 0..127usize {
        let link = Link::Remote(addr.to_string());
        let st = link.request(Request::State { sensor: Some(i) });
        if st["ok"] != true {
            if i == 0 {
                tracing::warn!(
                    "dashboard: control interface {addr}: {}",
                    st["error"].as_str().unwrap_or("no answer")
                );
            }
            break;
        }
        out.push(Controller {
            link,
            sensor: i,
            state: Some(st),
        });
    }
    out
}

/// Names of the NMT state byte, with "unknown" for nothing heard.
pub fn nmt_name(b: Option<u8>) -> &'static str {
    b.map_or("unknown", decode::nmt_state_name)
}
