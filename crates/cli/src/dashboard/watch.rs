//! What the dashboard knows about the bus: the nodes it heard (boot-ups, heartbeats, EMCYs,
//! TPDOs, answers to its scan), their process data decimated for the plots, and the state the
//! control interfaces report. One thread owns the bus connection; it also runs the SDO
//! transfers the page asks for, so that the dashboard is one SDO client, never two at once.
//! They come through a bounded queue ([`bus_queue`]); a command whose requester has given up
//! is never started, and one that has started is always answered with its outcome.

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use canpos_host::control::{self, Request};
use canpos_host::crossbeam_channel::{self, Receiver, Sender, TrySendError};
use canpos_host::{ControlHandle, RxFrame, Transport};
use canpos_models as models;
use canpos_stack::od::DefaultValue;
use canpos_stack::sdo::wire;
use canpos_stack::{cob, Frame, Table};
use serde_json::{json, Value};
use tokio::sync::oneshot;

use crate::client::decode::{self, NodeInfo};
use crate::client::scan::DEVICE_TYPE;
use crate::client::sdo::{abort_meaning, SdoClient, SdoError};
use crate::client::Monitor;

/// Plot samples are kept at most this often per channel (the server-side decimation: a TPDO
/// every millisecond becomes 50 points per second).
pub const SAMPLE_PERIOD: Duration = Duration::from_millis(20);
/// EMCYs kept per node.
const EMCY_LOG: usize = 100;
/// SDO timeout of the dashboard's transfers: `canpos sdo`'s (D45), so a node that answers the
/// command line answers the page.
pub const SDO_TIMEOUT: Duration = Duration::from_millis(crate::client::sdo::DEFAULT_TIMEOUT_MS);
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
    pub model: Option<&'static Table>,
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
    /// The frame trace and the transmitter (issue 38; [`super::trace`]).
    pub trace: Arc<super::trace::TraceHub>,
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
            trace: super::trace::TraceHub::new(1000),
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
    pub fn pin_model(&mut self, id: u8, model: &'static Table) {
        let n = self.node(id);
        n.model = Some(model);
        n.pinned = true;
    }

    /// Node `id`'s TPDO mappings changed (a remap): they are read again at once.
    pub fn forget_mapping(&mut self, id: u8) {
        if let Some(n) = self.nodes.get_mut(&id) {
            n.info = None;
            n.asked = None;
        }
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
pub fn recognise(vendor: Option<u32>, name: Option<&str>) -> Option<&'static Table> {
    let vendor = vendor?;
    // The widest unit's table (the two-channel TMI's): the dashboard does not know the unit.
    let candidates: Vec<&'static Table> = models::all()
        .into_iter()
        .map(|m| &models::widest(m).table)
        .filter(|m| {
            m.entries.iter().any(|e| {
                e.index == 0x1018 && e.sub == 1 && e.default == DefaultValue::Const(vendor)
            })
        })
        .collect();
    if candidates.len() == 1 {
        return Some(candidates[0]);
    }
    candidates.into_iter().find(|m| {
        m.entries.iter().any(|e| {
            e.index == 0x1008 && matches!(e.default, DefaultValue::Str(s) if Some(*s) == name)
        })
    })
}

/// Commands that may wait for the bus thread at once; one more is refused at once (the HTTP
/// side answers 503 "busy") and changes nothing. Reads are open to any client (an `<img>` of
/// any site), so the queue must not grow with them, and a few are all a page has in flight.
pub const QUEUE: usize = 8;

/// A request from the HTTP side to the bus thread.
pub enum BusCmd {
    /// SDO upload.
    Read(u8, u16, u8, Job<Result<Vec<u8>, String>>),
    /// SDO download.
    Write(u8, u16, u8, Vec<u8>, Job<Result<(), String>>),
    /// Ask every node-id for 0x1000 (answers are noted as frames).
    Scan,
}

// The life of a queued command: the bus thread moves it from QUEUED to STARTED, its requester
// from QUEUED to ABANDONED; whichever comes first decides, so a command is either run and
// answered or never run.
const QUEUED: u8 = 0;
const STARTED: u8 = 1;
const ABANDONED: u8 = 2;

/// The bus thread's side of a queued command: claim it, then answer it.
pub struct Job<T> {
    claim: Arc<AtomicU8>,
    reply: oneshot::Sender<T>,
}

impl<T> Job<T> {
    /// Claims the command for the bus: false when its requester has given up (its wait ended
    /// or it went away), and then it must not be run.
    pub fn start(&self) -> bool {
        self.claim
            .compare_exchange(QUEUED, STARTED, Ordering::SeqCst, Ordering::SeqCst)
            .is_ok()
    }

    /// The outcome of a started command.
    pub fn answer(self, v: T) {
        let _ = self.reply.send(v);
    }
}

/// What became of a queued command, as its requester learns it.
#[derive(Debug, PartialEq)]
pub enum Outcome<T> {
    /// It ran; this is its result.
    Done(T),
    /// It never started (and never will): the wait ended with this many commands ahead of it
    /// (queued or running).
    TimedOut {
        /// Commands before it not yet finished.
        ahead: u64,
    },
    /// It started but had not ended when the requester stopped waiting: its effect is unknown.
    Unfinished,
    /// The bus thread ended (the bus connection is gone) before it ran.
    Gone,
}

/// The requester's side of a queued command. Dropping it (the client went away) gives the
/// command up unless it has started.
pub struct Pending<T> {
    ticket: u64,
    claim: Arc<AtomicU8>,
    reply: oneshot::Receiver<T>,
    finished: Arc<AtomicU64>,
}

impl<T> Pending<T> {
    /// Gives the command up: true when it had not started (it never will), false when it has
    /// (its answer will come).
    pub fn abandon(&self) -> bool {
        match self
            .claim
            .compare_exchange(QUEUED, ABANDONED, Ordering::SeqCst, Ordering::SeqCst)
        {
            Ok(_) => true,
            Err(state) => state == ABANDONED,
        }
    }

    /// Commands before this one that the bus thread has not finished.
    pub fn ahead(&self) -> u64 {
        self.ticket
            .saturating_sub(self.finished.load(Ordering::SeqCst))
    }

    /// Waits up to `patience` for the command to start; one that started by then is waited
    /// for until it ends, or `limit` more (an SDO transfer segment by segment can last long
    /// with a node that answers each segment late).
    pub async fn outcome(mut self, patience: Duration, limit: Duration) -> Outcome<T> {
        match tokio::time::timeout(patience, &mut self.reply).await {
            Ok(Ok(v)) => return Outcome::Done(v),
            Ok(Err(_)) => return Outcome::Gone,
            Err(_) => {}
        }
        if self.abandon() {
            return Outcome::TimedOut {
                ahead: self.ahead(),
            };
        }
        match tokio::time::timeout(limit, &mut self.reply).await {
            Ok(Ok(v)) => Outcome::Done(v),
            Ok(Err(_)) => Outcome::Gone,
            Err(_) => Outcome::Unfinished,
        }
    }
}

impl<T> Drop for Pending<T> {
    fn drop(&mut self) {
        self.abandon();
    }
}

/// Why a command was not queued.
#[derive(Debug, PartialEq)]
pub enum Refused {
    /// [`QUEUE`] commands wait already.
    Busy,
    /// The bus thread has ended.
    Gone,
}

/// The HTTP side of the bounded queue to the bus thread.
pub struct BusQueue {
    tx: Sender<(u64, BusCmd)>,
    /// Number of the next command; held while it is queued, so numbers follow queue order.
    next: Mutex<u64>,
    finished: Arc<AtomicU64>,
}

/// The bus thread's side of the queue.
pub struct BusInbox {
    rx: Receiver<(u64, BusCmd)>,
    finished: Arc<AtomicU64>,
}

/// A queue of at most `capacity` commands to the bus thread.
pub fn bus_queue(capacity: usize) -> (BusQueue, BusInbox) {
    let (tx, rx) = crossbeam_channel::bounded(capacity);
    let finished = Arc::new(AtomicU64::new(0));
    (
        BusQueue {
            tx,
            next: Mutex::new(0),
            finished: finished.clone(),
        },
        BusInbox { rx, finished },
    )
}

impl BusQueue {
    /// Queues the command `make` builds around its [`Job`] at once, or refuses it: nothing
    /// waits for room.
    pub fn submit<T>(&self, make: impl FnOnce(Job<T>) -> BusCmd) -> Result<Pending<T>, Refused> {
        let (reply_tx, reply) = oneshot::channel();
        let claim = Arc::new(AtomicU8::new(QUEUED));
        let cmd = make(Job {
            claim: claim.clone(),
            reply: reply_tx,
        });
        let mut next = self.next.lock().unwrap();
        self.send(*next, cmd)?;
        let ticket = *next;
        *next += 1;
        Ok(Pending {
            ticket,
            claim,
            reply,
            finished: self.finished.clone(),
        })
    }

    /// Queues a scan (nobody waits for its answer).
    pub fn scan(&self) -> Result<(), Refused> {
        let mut next = self.next.lock().unwrap();
        self.send(*next, BusCmd::Scan)?;
        *next += 1;
        Ok(())
    }

    fn send(&self, ticket: u64, cmd: BusCmd) -> Result<(), Refused> {
        self.tx.try_send((ticket, cmd)).map_err(|e| match e {
            TrySendError::Full(_) => Refused::Busy,
            TrySendError::Disconnected(_) => Refused::Gone,
        })
    }
}

impl BusInbox {
    /// The next command, if one waits.
    fn next(&self) -> Option<(u64, BusCmd)> {
        self.rx.try_recv().ok()
    }

    /// Command `ticket` is done with (run or skipped).
    fn finished(&self, ticket: u64) {
        self.finished.store(ticket + 1, Ordering::SeqCst);
    }
}

impl Drop for BusInbox {
    /// The bus thread has ended: the commands still queued are dropped, so that their
    /// requesters learn at once that the bus is gone (a channel keeps its messages while a
    /// sender lives).
    fn drop(&mut self) {
        while self.rx.try_recv().is_ok() {}
    }
}

/// Runs one command on the bus, unless its requester has given up on it. Frames of others
/// heard meanwhile go to `backlog`.
fn run_cmd(
    bus: &mut dyn Transport,
    cmd: BusCmd,
    backlog: &mut Vec<RxFrame>,
) -> std::io::Result<()> {
    match cmd {
        BusCmd::Read(node, index, sub, job) => {
            if job.start() {
                let mut c = SdoClient::new(bus, node, SDO_TIMEOUT).keep_other_frames();
                let r = c.upload(index, sub).map_err(sdo_text);
                backlog.extend(c.take_other_frames());
                job.answer(r);
            }
        }
        BusCmd::Write(node, index, sub, data, job) => {
            if job.start() {
                let mut c = SdoClient::new(bus, node, SDO_TIMEOUT).keep_other_frames();
                let r = c.download(index, sub, &data).map_err(sdo_text);
                backlog.extend(c.take_other_frames());
                job.answer(r);
            }
        }
        BusCmd::Scan => scan(bus)?,
    }
    Ok(())
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
    cmds: BusInbox,
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
            while let Some((ticket, cmd)) = cmds.next() {
                let r = run_cmd(&mut *bus, cmd, &mut backlog);
                cmds.finished(ticket);
                r?;
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
pub(super) fn scan(bus: &mut dyn Transport) -> std::io::Result<()> {
    for node in 1..=127u8 {
        let mux = DEVICE_TYPE;
        bus.send(&Frame::std8(
            cob::SDO_RX + u16::from(node),
            wire::Request::UploadInitiate { mux }.emit(),
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
        let (hub, rate) = {
            let mut s = shared.lock().unwrap();
            for (c, st) in s.controllers.iter_mut().zip(states) {
                c.state = (st["ok"] == true).then_some(st);
            }
            let known: Vec<(u8, Option<&'static Table>)> = s
                .controllers
                .iter()
                .filter_map(|c| c.state.as_ref())
                .filter_map(|st| {
                    let id = st["node_id"].as_u64().filter(|id| (1..=127).contains(id))?;
                    Some((
                        id as u8,
                        st["model"]
                            .as_str()
                            .and_then(models::by_name)
                            .map(|m| &models::widest(m).table),
                    ))
                })
                .collect();
            for (id, model) in known {
                let n = s.node(id);
                if n.model.is_none() {
                    n.model = model;
                }
            }
            // A sensor knows its bus's rate where a socketcand hub does not say it: its
            // in-process bus's pacing, else the rate it was started with (D60).
            let rate = s
                .controllers
                .iter()
                .filter_map(|c| c.state.as_ref())
                .find_map(|st| {
                    st["bus"]["bitrate_kbps"]
                        .as_u64()
                        .or_else(|| st["bus_bitrate_kbps"].as_u64())
                });
            (s.trace.clone(), rate)
        };
        // The trace's lock is taken with the state's released (the bus thread takes it alone).
        if let Some(kbps) = rate.and_then(|k| u32::try_from(k).ok()) {
            hub.trace
                .lock()
                .unwrap()
                .offer_bitrate(kbps, super::trace::BitrateFrom::Sensor);
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

/// The NMT state shown for node `id` when no control interface reports it: what its own frames
/// say when it sends no heartbeat.
pub(super) fn nmt_of(s: &Shared, id: u8, n: &Node) -> Option<String> {
    let cobs: Vec<u16> = n
        .info
        .as_ref()
        .map(|i| i.tpdos.iter().map(|(_, c, _)| *c).collect())
        .unwrap_or_default();
    s.trace
        .trace
        .lock()
        .unwrap()
        .inferred_nmt(id, &cobs, Instant::now())
}

#[cfg(test)]
mod tests {
    use super::*;
    use canpos_host::MemBus;

    fn read(q: &BusQueue) -> Result<Pending<Result<Vec<u8>, String>>, Refused> {
        q.submit(|job| BusCmd::Read(5, 0x1018, 1, job))
    }

    fn frames(port: &mut dyn Transport) -> usize {
        std::iter::from_fn(|| port.try_recv().unwrap()).count()
    }

    #[test]
    fn a_full_queue_refuses_at_once_and_a_gone_bus_says_so() {
        let (q, inbox) = bus_queue(QUEUE);
        let waiting: Vec<_> = (0..QUEUE).map(|_| read(&q).unwrap()).collect();
        assert_eq!(read(&q).err(), Some(Refused::Busy));
        assert_eq!(q.scan(), Err(Refused::Busy));
        let write = q.submit(|job| BusCmd::Write(5, 0x1017, 0, vec![9, 3], job));
        assert_eq!(write.err(), Some(Refused::Busy));
        // Nothing refused was queued: the eight are all there is, in order.
        assert_eq!(inbox.rx.len(), QUEUE);
        assert_eq!(waiting[QUEUE - 1].ahead(), QUEUE as u64 - 1);
        let (ticket, _) = inbox.next().unwrap();
        assert_eq!(ticket, 0);
        inbox.finished(ticket);
        assert_eq!(waiting[QUEUE - 1].ahead(), QUEUE as u64 - 2);
        // Room for one again.
        assert!(q.scan().is_ok());
        assert_eq!(read(&q).err(), Some(Refused::Busy));
        drop(inbox);
        assert_eq!(read(&q).err(), Some(Refused::Gone));
    }

    #[test]
    fn a_command_given_up_never_goes_on_the_bus() {
        let bus = MemBus::instant();
        let mut port = bus.attach();
        let mut peer = bus.attach();
        let (q, inbox) = bus_queue(QUEUE);
        // A client that went away (its request's future dropped), one whose wait ended, and a
        // write given up: none of them is started.
        drop(read(&q).unwrap());
        let timed_out = read(&q).unwrap();
        assert!(timed_out.abandon());
        let write = q
            .submit(|job| BusCmd::Write(5, 0x1017, 0, vec![9, 3], job))
            .unwrap();
        assert!(write.abandon());
        q.scan().unwrap();
        let mut backlog = Vec::new();
        for n in 0..3 {
            let (ticket, cmd) = inbox.next().unwrap();
            assert_eq!(ticket, n);
            run_cmd(&mut port, cmd, &mut backlog).unwrap();
            inbox.finished(ticket);
        }
        assert_eq!(frames(&mut peer), 0, "a command given up went on the bus");
        // The port does reach the peer: the scan behind them asks all 127 node-ids.
        let (ticket, cmd) = inbox.next().unwrap();
        run_cmd(&mut port, cmd, &mut backlog).unwrap();
        inbox.finished(ticket);
        assert_eq!(frames(&mut peer), 127);
        assert_eq!(timed_out.ahead(), 0);
    }

    #[tokio::test(start_paused = true)]
    async fn a_started_command_is_answered_with_its_outcome() {
        let patience = Duration::from_secs(5);
        let limit = Duration::from_secs(30);
        let (q, inbox) = bus_queue(QUEUE);

        // Never taken off the queue: given up when the wait ends, with one command ahead.
        q.scan().unwrap();
        let p = read(&q).unwrap();
        assert_eq!(
            p.outcome(patience, limit).await,
            Outcome::TimedOut { ahead: 1 }
        );
        let _scan = inbox.next().unwrap();
        let Some((_, BusCmd::Read(.., job))) = inbox.next() else {
            panic!("the read is queued")
        };
        assert!(!job.start(), "a command given up was started");

        // Started before the wait ended, answered after it: the requester gets the answer.
        let p = read(&q).unwrap();
        let Some((_, BusCmd::Read(.., job))) = inbox.next() else {
            panic!("the read is queued")
        };
        assert!(job.start());
        assert!(!p.abandon(), "a started command cannot be given up");
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_secs(12)).await;
            job.answer(Ok(vec![1, 2]));
        });
        assert_eq!(
            p.outcome(patience, limit).await,
            Outcome::Done(Ok(vec![1, 2]))
        );

        // Started and never ending within the limit: unfinished, never "timed out, not sent".
        let p = read(&q).unwrap();
        let Some((_, BusCmd::Read(.., job))) = inbox.next() else {
            panic!("the read is queued")
        };
        assert!(job.start());
        assert_eq!(p.outcome(patience, limit).await, Outcome::Unfinished);
        drop(job);

        // The bus thread ends with a command queued: gone.
        let p = read(&q).unwrap();
        drop(inbox);
        assert_eq!(p.outcome(patience, limit).await, Outcome::Gone);
    }
}
