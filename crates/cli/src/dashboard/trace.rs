//! The dashboard's bus tool (issue 38 items 1, 2, 5, 7): a frame trace in PCAN-View's manner,
//! a transmitter, the NMT state a node's own frames tell, and a bus connection that comes back.
//!
//! * [`Trace`]: one row per identifier (count, cycle time and last data, the cycle from the
//!   frames' own timestamps) and a log of the last [`LOG`] frames, both bounded; bus load and
//!   frame rate over a second of frame timestamps. Frames are decoded at request time by the
//!   monitor's decoder ([`Monitor`], fed the mappings the dashboard read), never a second one.
//! * [`Tap`]: the bus thread's transport, wrapped. Every frame it receives or sends goes into
//!   the trace (so the dashboard's own SDO requests and the page's frames are in it too); it
//!   sends the page's frames, once or periodically, between the bus thread's receives; and when
//!   given a way to reopen the bus ([`TraceHub::reopen_with`]) it waits out a lost hub and
//!   reconnects, as `canpos run --hub never` does, instead of ending the bus thread.

use std::collections::{BTreeMap, VecDeque};
use std::io;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use canpos_host::transport::{BusState, RxFrame, Transport};
use canpos_stack::Frame;
use serde_json::{json, Value};

use crate::capture::{CaptureWriter, Format};
use crate::client::decode::NodeInfo;
use crate::client::sdo::hex_string;
use crate::client::Monitor;

/// Rows kept, one per identifier (and RTR or not): every standard identifier twice over; an
/// identifier beyond them (a flood of extended ones) is counted in [`Trace::unlisted`] (D42).
pub const ROWS: usize = 4096;
/// Frames kept for the log and the export (D42): 1.6 s of a bus at 40,000 frames/s.
pub const LOG: usize = 65_536;
/// Log entries one answer carries at most (the newest).
pub const LOG_ANSWER: usize = 2000;
/// Frames the page may have queued to send once; more are refused (503) until they went out.
pub const ONCE_QUEUE: usize = 64;
/// Periodic transmissions at once (D43).
pub const PERIODIC: usize = 16;
/// Shortest period of a periodic transmission: the bus thread's timer (D43); the hub's own
/// cyclic jobs go down to 100 µs, a thread sleeping between receives does not.
pub const MIN_PERIOD: Duration = Duration::from_millis(1);
/// Longest period.
pub const MAX_PERIOD: Duration = Duration::from_secs(3600);
/// A periodic transmission on a lease ends this long after the lease's last renewal (D61):
/// the page renews its lease every second while it is open, so one whose page is gone stops
/// within this, as socketcand's jobs end with their connection.
pub const LEASE: Duration = Duration::from_secs(5);
/// Longest explicit duration of a periodic transmission (a script's, instead of a lease).
pub const MAX_DURATION: Duration = Duration::from_secs(24 * 3600);
/// Longest lease name.
pub const LEASE_NAME: usize = 64;
/// A node whose heartbeat (or guarding answer) is this old counts as not sending one.
pub const HEARTBEAT_SILENCE: Duration = Duration::from_secs(3);
/// A PDO from a node this recent makes it "operational (inferred)".
pub const PDO_FRESH: Duration = Duration::from_secs(1);
/// Waits between attempts to reach a lost hub: 100 ms doubling to this.
pub const REOPEN_MAX: Duration = Duration::from_millis(800);

/// Where the bit rate the bus load is figured at comes from (D60), worst first: a better
/// source replaces a worse one, never the other way round.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum BitrateFrom {
    /// Nobody said: 1000 kbit/s, the rate of a bus nobody configured (docs/BUS.md). A
    /// socketcand hub, canpos's included, names none in its protocol.
    Assumed,
    /// A sensor's control state: the bus rate it was started with (`--bus-bitrate`), or its
    /// in-process bus's pacing.
    Sensor,
    /// The bus connection itself (an in-process bus: its pacing).
    Bus,
    /// `canpos dashboard --bitrate`.
    Given,
}

impl BitrateFrom {
    /// The API's and the page's word for it.
    pub fn name(self) -> &'static str {
        match self {
            BitrateFrom::Assumed => "assumed",
            BitrateFrom::Sensor => "sensor",
            BitrateFrom::Bus => "bus",
            BitrateFrom::Given => "given",
        }
    }
}

/// Which way a frame went, seen from the dashboard.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dir {
    /// Heard on the bus.
    Rx,
    /// Sent by the dashboard (its SDO client, its scan, the page's transmitter).
    Tx,
}

impl Dir {
    fn name(self) -> &'static str {
        match self {
            Dir::Rx => "rx",
            Dir::Tx => "tx",
        }
    }
}

/// One logged frame.
#[derive(Clone, Debug)]
pub struct Entry {
    /// Log sequence number (from 1).
    pub seq: u64,
    /// The frame's own timestamp.
    pub t: SystemTime,
    /// The frame.
    pub frame: Frame,
    /// Direction.
    pub dir: Dir,
}

/// One identifier's row.
#[derive(Clone, Debug)]
pub struct Row {
    /// The last frame.
    pub frame: Frame,
    /// Direction of the last frame.
    pub dir: Dir,
    /// Frames counted.
    pub count: u64,
    /// Timestamp of the last frame.
    pub last: SystemTime,
    /// Interval between the last two frames.
    pub dt: Option<Duration>,
    /// The mean cycle over the last full second of timestamps (or since the first frame, until
    /// a second has passed).
    pub cycle: Option<Duration>,
    /// When the last frame arrived here (for what is still being sent).
    pub arrived: Instant,
    window: (SystemTime, u64),
}

/// Row key: extended flag, identifier, remote flag.
type Key = (bool, u32, bool);

pub(super) fn key(f: &Frame) -> Key {
    (f.is_extended(), f.id(), f.is_remote())
}

/// The frame trace; see the [module docs](self).
pub struct Trace {
    rows: BTreeMap<Key, Row>,
    log: VecDeque<Entry>,
    next_seq: u64,
    /// Frames whose identifier found no free row (beyond [`ROWS`]).
    pub unlisted: u64,
    bit_ns: u64,
    bitrate: (u32, BitrateFrom),
    second: Option<(SystemTime, u64, u64)>,
    load: Option<(f64, f64)>,
    last_arrival: Option<Instant>,
    /// The last NMT command heard (or sent) to each node-id, and to all (index 0): command
    /// specifier and arrival. Kept through "Clear": it is the nodes' state, not the list's.
    nmt_cmd: [Option<(u8, Instant)>; 128],
}

impl Trace {
    /// An empty trace of a bus of `kbps` kbit/s (for its load).
    pub fn new(kbps: u32) -> Trace {
        Trace {
            rows: BTreeMap::new(),
            log: VecDeque::new(),
            next_seq: 1,
            unlisted: 0,
            bit_ns: 1_000_000 / u64::from(kbps.max(1)),
            bitrate: (kbps.max(1), BitrateFrom::Assumed),
            second: None,
            load: None,
            last_arrival: None,
            nmt_cmd: [None; 128],
        }
    }

    /// Takes in one frame stamped `t` (its own timestamp) that arrived `now`.
    pub fn note(&mut self, f: &Frame, t: SystemTime, dir: Dir, now: Instant) {
        if let (false, false, 0, &[cs, node]) = (f.is_extended(), f.is_remote(), f.id(), f.data()) {
            if let Some(c) = self.nmt_cmd.get_mut(usize::from(node)) {
                *c = Some((cs, now));
            }
        }
        let k = key(f);
        if let Some(r) = self.rows.get_mut(&k) {
            r.dt = t.duration_since(r.last).ok();
            r.count += 1;
            r.last = t;
            r.frame = *f;
            r.dir = dir;
            r.arrived = now;
            let (w0, c0) = r.window;
            if let Ok(span) = t.duration_since(w0) {
                if span >= Duration::from_secs(1) {
                    r.cycle = Some(span / (r.count - c0) as u32);
                    r.window = (t, r.count);
                } else if r.cycle.is_none() || r.window.1 == 1 {
                    // The first second: the mean since the first frame.
                    r.cycle = Some(span / (r.count - c0) as u32);
                }
            } else {
                // A stamp older than the window's start (another source's clock): start again.
                r.window = (t, r.count);
            }
        } else if self.rows.len() < ROWS {
            self.rows.insert(
                k,
                Row {
                    frame: *f,
                    dir,
                    count: 1,
                    last: t,
                    dt: None,
                    cycle: None,
                    arrived: now,
                    window: (t, 1),
                },
            );
        } else {
            self.unlisted += 1;
        }
        if self.log.len() == LOG {
            self.log.pop_front();
        }
        self.log.push_back(Entry {
            seq: self.next_seq,
            t,
            frame: *f,
            dir,
        });
        self.next_seq += 1;
        // Load and rate over a second of frame timestamps.
        let bits = u64::from(canpos_host::bus::bits::frame_length(f).total);
        match &mut self.second {
            Some((t0, b, n)) => match t.duration_since(*t0) {
                Ok(span) if span >= Duration::from_secs(1) => {
                    let ns = span.as_nanos() as f64;
                    let pct = (*b * self.bit_ns) as f64 / ns * 100.0;
                    self.load = Some((pct.min(100.0), *n as f64 / span.as_secs_f64()));
                    self.second = Some((t, bits, 1));
                }
                Ok(_) => {
                    *b += bits;
                    *n += 1;
                }
                Err(_) => self.second = Some((t, bits, 1)),
            },
            None => self.second = Some((t, bits, 1)),
        }
        self.last_arrival = Some(now);
    }

    /// Offers a bit rate to figure the load at, learnt from `from`: taken unless the one in
    /// use came from a better source (D60: given > the bus's > a sensor's > assumed); whether
    /// it was taken.
    pub fn offer_bitrate(&mut self, kbps: u32, from: BitrateFrom) -> bool {
        if kbps == 0 || from < self.bitrate.1 {
            return false;
        }
        self.bitrate = (kbps, from);
        self.bit_ns = 1_000_000 / u64::from(kbps);
        true
    }

    /// The bit rate the load is figured at, and where it comes from.
    pub fn bitrate(&self) -> (u32, BitrateFrom) {
        self.bitrate
    }

    /// Forgets every row and logged frame (the page's "Clear").
    pub fn clear(&mut self) {
        self.rows.clear();
        self.log.clear();
        self.unlisted = 0;
    }

    /// Bus load (%) and frames/s over the last full second of timestamps; zero once nothing
    /// has arrived for two seconds.
    pub fn load(&self, now: Instant) -> (f64, f64) {
        match (self.load, self.last_arrival) {
            (Some(l), Some(a)) if now.duration_since(a) < Duration::from_secs(2) => l,
            _ => (0.0, 0.0),
        }
    }

    /// The rows, by identifier.
    pub fn rows(&self) -> impl Iterator<Item = &Row> {
        self.rows.values()
    }

    /// Logged frames newer than `since`, oldest first.
    pub fn log_since(&self, since: u64) -> impl Iterator<Item = &Entry> {
        let skip = self.log.partition_point(|e| e.seq <= since);
        self.log.range(skip..)
    }

    /// The sequence number of the last frame logged (0: none yet).
    pub fn seq(&self) -> u64 {
        self.next_seq - 1
    }

    /// What node `node`'s NMT state is from its own frames, when no heartbeat or guarding
    /// answer of it is recent: "operational (inferred)" while it sends PDOs (`pdo_cobs`: the
    /// COB-IDs of its TPDOs; the pre-defined set's four when its mapping is not known). A
    /// recent guarding answer (toggle bit) is named as such. `None`: nothing to add to the
    /// heartbeat's word.
    pub fn inferred_nmt(&self, node: u8, pdo_cobs: &[u16], now: Instant) -> Option<String> {
        let recent = |id: u32, within: Duration| {
            self.rows
                .get(&(false, id, false))
                .filter(|r| now.duration_since(r.arrived) < within)
        };
        let defaults: Vec<u16> = [0x180u16, 0x280, 0x380, 0x480]
            .iter()
            .map(|b| b + u16::from(node))
            .collect();
        let cobs = if pdo_cobs.is_empty() {
            &defaults[..]
        } else {
            pdo_cobs
        };
        let pdo = cobs
            .iter()
            .filter_map(|c| recent(u32::from(*c), PDO_FRESH))
            .map(|r| r.arrived)
            .max();
        let errctl = 0x700 + u32::from(node);
        // The last NMT command to it (or to all) since its last heartbeat or boot-up: a node
        // without heartbeat is in the state it was told (an event-driven TPDO of a still
        // sensor sends nothing, a stopped node nothing either).
        let heard = self.rows.get(&(false, errctl, false)).map(|r| r.arrived);
        let cmd = [self.nmt_cmd[0], self.nmt_cmd[usize::from(node & 0x7F)]]
            .into_iter()
            .flatten()
            .max_by_key(|(_, at)| *at)
            .filter(|(_, at)| heard.is_none_or(|h| h < *at));
        if let Some(r) = recent(errctl, HEARTBEAT_SILENCE) {
            // A guarding answer carries the toggle bit or follows a guarding request.
            let rtr = self.rows.get(&(false, errctl, true));
            let guarded = r.frame.data().first().is_some_and(|b| b & 0x80 != 0)
                || rtr.is_some_and(|q| {
                    r.arrived >= q.arrived && r.arrived - q.arrived < Duration::from_millis(500)
                });
            if guarded && r.frame.dlc() == 1 {
                let state = crate::client::decode::nmt_state_name(r.frame.data()[0] & 0x7F);
                return Some(format!("{state} (guarding)"));
            }
            // A heartbeat speaks for itself; a boot-up only until the node's first PDO.
            if r.frame.data() != [0] || (pdo.is_none_or(|p| p < r.arrived) && cmd.is_none()) {
                return None;
            }
        }
        // A PDO after the command: operational, whoever started it (only then may it send).
        if pdo.is_some_and(|p| cmd.is_none_or(|(_, c)| p > c)) {
            return Some("operational (inferred)".to_string());
        }
        let state = match cmd?.0 {
            0x01 => "operational",
            0x02 => "stopped",
            0x80 => "pre-operational",
            // A reset: its boot-up will say.
            _ => return None,
        };
        Some(format!("{state} (inferred)"))
    }
}

/// A filter of the trace: an identifier range and a node.
#[derive(Clone, Copy, Debug, Default)]
pub struct Filter {
    /// Lowest identifier shown.
    pub from: Option<u32>,
    /// Highest identifier shown.
    pub to: Option<u32>,
    /// Only frames that concern this node (as `canpos monitor --node` chooses them).
    pub node: Option<u8>,
}

impl Filter {
    fn admits(&self, mon: &Monitor, f: &Frame) -> bool {
        self.from.is_none_or(|lo| f.id() >= lo)
            && self.to.is_none_or(|hi| f.id() <= hi)
            && self.node.is_none_or(|n| mon.concerns(f, n))
    }
}

/// A monitor that knows the TPDO mappings the dashboard read.
pub fn monitor_of<'a>(infos: impl Iterator<Item = (u8, &'a NodeInfo)>) -> Monitor {
    let mut m = Monitor::new();
    for (id, info) in infos {
        m.learn(id, Some(info.clone()));
    }
    m
}

pub(super) fn secs(t: SystemTime) -> f64 {
    t.duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs_f64()
}

pub(super) fn id_text(f: &Frame) -> String {
    if f.is_extended() {
        format!("0x{:08X}", f.id())
    } else {
        format!("0x{:03X}", f.id())
    }
}

pub(super) fn ms(d: Option<Duration>) -> Value {
    d.map_or(Value::Null, |d| json!(d.as_secs_f64() * 1e3))
}

/// The trace as the page and scripts read it (`GET /api/trace`).
/// At most `limit` (and [`LOG_ANSWER`]) log entries, the newest.
pub fn answer(
    trace: &Trace,
    mon: &Monitor,
    filter: &Filter,
    since: u64,
    limit: usize,
    now: Instant,
) -> Value {
    let frame_fields = |f: &Frame| {
        json!({
            "id": id_text(f), "ext": f.is_extended(), "rtr": f.is_remote(), "dlc": f.dlc(),
            "data": if f.is_remote() { String::new() } else { hex_string(f.data()) },
            "decoded": mon.describe(f),
        })
    };
    let rows: Vec<Value> = trace
        .rows()
        .filter(|r| filter.admits(mon, &r.frame))
        .map(|r| {
            let mut v = frame_fields(&r.frame);
            let o = v.as_object_mut().expect("an object");
            o.insert("count".into(), json!(r.count));
            o.insert("cycle_ms".into(), ms(r.cycle));
            o.insert("dt_ms".into(), ms(r.dt));
            o.insert("t".into(), json!(secs(r.last)));
            o.insert("dir".into(), json!(r.dir.name()));
            v
        })
        .collect();
    let newer: Vec<&Entry> = trace
        .log_since(since)
        .filter(|e| filter.admits(mon, &e.frame))
        .collect();
    let skipped = newer.len().saturating_sub(limit.min(LOG_ANSWER));
    let log: Vec<Value> = newer[skipped..]
        .iter()
        .map(|e| {
            let mut v = frame_fields(&e.frame);
            let o = v.as_object_mut().expect("an object");
            o.insert("seq".into(), json!(e.seq));
            o.insert("t".into(), json!(secs(e.t)));
            o.insert("dir".into(), json!(e.dir.name()));
            v
        })
        .collect();
    let (load, fps) = trace.load(now);
    json!({
        "ok": true, "seq": trace.seq(), "rows": rows, "log": log, "log_skipped": skipped,
        "unlisted": trace.unlisted, "bus_load_pct": load, "frames_per_s": fps,
        "bitrate_kbps": trace.bitrate.0, "bitrate_from": trace.bitrate.1.name(),
    })
}

/// The logged frames that pass `filter`, as a capture file of `format` (`canpos record`'s
/// writers).
pub fn export(
    trace: &Trace,
    mon: &Monitor,
    filter: &Filter,
    format: Format,
) -> io::Result<Vec<u8>> {
    let mut w = CaptureWriter::new(Vec::new(), format, "can0")?;
    for e in trace.log_since(0).filter(|e| filter.admits(mon, &e.frame)) {
        w.write(e.t, &canpos_host::candump::Record::Frame(e.frame))?;
    }
    w.finish()
}

/// A periodic transmission.
#[derive(Clone, Debug)]
pub struct Periodic {
    /// The frame.
    pub frame: Frame,
    /// Its period.
    pub period: Duration,
    /// When it is sent next.
    pub next: Instant,
    /// Frames sent.
    pub sent: u64,
    /// The lease that keeps it going; `None`: it runs for a duration given when it started.
    pub lease: Option<String>,
    /// When it ends unless its lease is renewed before.
    pub ends: Instant,
}

/// How long a periodic transmission runs (D61).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Term {
    /// While the lease of this name is renewed within [`LEASE`].
    Lease(String),
    /// For this long (at most [`MAX_DURATION`]).
    For(Duration),
}

/// The hub's state as the dashboard's connection sees it.
#[derive(Clone, Debug, Default)]
pub struct LinkState {
    /// Lost, since then, why (while it is away).
    pub down: Option<(SystemTime, String)>,
    /// Reconnections so far, and the time of the last one.
    pub reconnections: u64,
    /// When the last reconnection happened.
    pub back_at: Option<SystemTime>,
}

/// A way to open the bus again.
pub type Reopen = Box<dyn Fn() -> io::Result<Box<dyn Transport>> + Send>;

/// What the HTTP side and the bus thread share for the trace and the transmitter.
pub struct TraceHub {
    /// The trace.
    pub trace: Mutex<Trace>,
    once: Mutex<VecDeque<Frame>>,
    periodic: Mutex<Vec<Periodic>>,
    /// The hub connection's state.
    pub link: Mutex<LinkState>,
    reopen: Mutex<Option<Reopen>>,
    /// Names the leases the hub hands out to requests that name none.
    leases: std::sync::atomic::AtomicU64,
}

/// Why a frame was not queued.
#[derive(Debug, PartialEq, Eq)]
pub enum SendRefused {
    /// [`ONCE_QUEUE`] frames wait already.
    Busy,
    /// [`PERIODIC`] periodic transmissions run already.
    TooMany,
    /// The bus connection is lost (the dashboard is reconnecting).
    Down,
}

impl TraceHub {
    /// A hub for a bus of `kbps` kbit/s.
    pub fn new(kbps: u32) -> Arc<TraceHub> {
        Arc::new(TraceHub {
            trace: Mutex::new(Trace::new(kbps)),
            once: Mutex::new(VecDeque::new()),
            periodic: Mutex::new(Vec::new()),
            link: Mutex::new(LinkState::default()),
            reopen: Mutex::new(None),
            leases: std::sync::atomic::AtomicU64::new(0),
        })
    }

    /// Gives the bus thread a way to reconnect when the bus connection is lost.
    pub fn reopen_with(&self, r: Reopen) {
        *self.reopen.lock().unwrap() = Some(r);
    }

    /// Queues `f` to be sent once.
    pub fn send_once(&self, f: Frame) -> Result<(), SendRefused> {
        self.up()?;
        let mut q = self.once.lock().unwrap();
        if q.len() >= ONCE_QUEUE {
            return Err(SendRefused::Busy);
        }
        q.push_back(f);
        Ok(())
    }

    /// A lease name no request has used: for a request that names none.
    pub fn new_lease(&self) -> String {
        let n = self
            .leases
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        format!("lease-{}", n + 1)
    }

    /// Sends `f` every `period` (first now) for as long as `term` says; one already sent on its
    /// identifier is replaced, as a socketcand `add` replaces a job.
    pub fn send_periodic(
        &self,
        f: Frame,
        period: Duration,
        term: Term,
        now: Instant,
    ) -> Result<(), SendRefused> {
        self.up()?;
        let mut p = self.periodic.lock().unwrap();
        let (lease, ends) = match term {
            Term::Lease(name) => (Some(name), now + LEASE),
            Term::For(d) => (None, now + d.min(MAX_DURATION)),
        };
        let job = Periodic {
            frame: f,
            period,
            next: now,
            sent: 0,
            lease,
            ends,
        };
        if let Some(j) = p.iter_mut().find(|j| key(&j.frame) == key(&f)) {
            *j = job;
        } else if p.len() >= PERIODIC {
            return Err(SendRefused::TooMany);
        } else {
            p.push(job);
        }
        Ok(())
    }

    /// Refuses a frame while the bus connection is lost: one queued then would go out whenever
    /// the hub is back, maybe minutes after its user gave up on it (an NMT reset, a write).
    fn up(&self) -> Result<(), SendRefused> {
        match self.link.lock().unwrap().down {
            Some(_) => Err(SendRefused::Down),
            None => Ok(()),
        }
    }

    /// Stops the periodic transmission of identifier `id` (`ext`); whether there was one.
    pub fn stop_periodic(&self, ext: bool, id: u32) -> bool {
        let mut p = self.periodic.lock().unwrap();
        let n = p.len();
        p.retain(|j| !(j.frame.is_extended() == ext && j.frame.id() == id));
        p.len() != n
    }

    /// Renews lease `name` at `now`: its transmissions run until `now` + [`LEASE`]; how many
    /// it holds (0: none, they ended or never were).
    pub fn renew(&self, name: &str, now: Instant) -> usize {
        let mut p = self.periodic.lock().unwrap();
        let mut n = 0;
        // A lapsed lease stays lapsed, dropped by the bus thread yet or not (it is not while
        // the hub is away).
        for j in p
            .iter_mut()
            .filter(|j| j.lease.as_deref() == Some(name) && j.ends > now)
        {
            j.ends = now + LEASE;
            n += 1;
        }
        n
    }

    /// Stops every periodic transmission of lease `name` (a page that closes); how many.
    pub fn stop_lease(&self, name: &str) -> usize {
        let mut p = self.periodic.lock().unwrap();
        let n = p.len();
        p.retain(|j| j.lease.as_deref() != Some(name));
        n - p.len()
    }

    /// The periodic transmissions.
    pub fn periodic(&self) -> Vec<Periodic> {
        // Without those whose term is over and the bus thread has not yet dropped (it does not
        // while the hub is away).
        let now = Instant::now();
        let p = self.periodic.lock().unwrap();
        p.iter().filter(|j| j.ends > now).cloned().collect()
    }

    /// At `now`: drops the transmissions whose term is over, counts the frames that are due
    /// (in their order) and moves each on by its period; and the time the next one is due or
    /// ends. A late caller sends each once and keeps its cycle, no burst to catch up.
    pub fn due(&self, now: Instant) -> (Vec<Frame>, Option<Instant>) {
        let mut p = self.periodic.lock().unwrap();
        p.retain(|j| j.ends > now);
        let mut out = Vec::new();
        for j in p.iter_mut().filter(|j| j.next <= now) {
            out.push(j.frame);
            j.sent += 1;
            j.next += j.period;
            if j.next <= now {
                j.next = now + j.period;
            }
        }
        let wake = p.iter().map(|j| j.next.min(j.ends)).min();
        (out, wake)
    }
}

/// The bus thread's transport; see the [module docs](self).
pub struct Tap {
    inner: Box<dyn Transport>,
    hub: Arc<TraceHub>,
    /// Lost: when to try again, and the next wait.
    down: Option<(Instant, Duration)>,
    /// Asks who is on a bus connection that came back (the dashboard's scan).
    rescan: Rescan,
}

/// What [`Tap`] does on a connection that came back, before anything else.
pub type Rescan = fn(&mut dyn Transport) -> io::Result<()>;

impl Tap {
    /// Wraps the bus connection `inner`.
    pub fn new(inner: Box<dyn Transport>, hub: Arc<TraceHub>, rescan: Rescan) -> Tap {
        Tap {
            inner,
            hub,
            down: None,
            rescan,
        }
    }

    fn record(&self, f: &Frame, t: SystemTime, dir: Dir) {
        self.hub
            .trace
            .lock()
            .unwrap()
            .note(f, t, dir, Instant::now());
    }

    /// Sends the page's frames that are due; the time of the next periodic one.
    fn service(&mut self) -> io::Result<Option<Instant>> {
        if self.down.is_some() {
            return Ok(None);
        }
        loop {
            let Some(f) = self.hub.once.lock().unwrap().pop_front() else {
                break;
            };
            self.send(&f)?;
        }
        let (due, wake) = self.hub.due(Instant::now());
        for f in due {
            self.send(&f)?;
        }
        Ok(wake)
    }

    /// The bus connection failed with `e`: wait for it to come back when the bus can be
    /// reopened, or report the error (the bus thread ends) when it cannot.
    fn lost(&mut self, e: io::Error) -> io::Result<()> {
        if self.hub.reopen.lock().unwrap().is_none() || e.kind() == io::ErrorKind::InvalidInput {
            return Err(e);
        }
        if self.down.is_none() {
            tracing::warn!("dashboard: the bus connection was lost ({e}); reconnecting");
            self.hub.link.lock().unwrap().down = Some((SystemTime::now(), e.to_string()));
            // What waits to go out once is not sent after the return (periodic jobs resume).
            self.hub.once.lock().unwrap().clear();
            self.down = Some((
                Instant::now() + Duration::from_millis(100),
                Duration::from_millis(100),
            ));
        }
        Ok(())
    }

    /// While lost: one attempt to reopen when it is due, else wait until `deadline`.
    fn wait_for_bus(&mut self, deadline: Instant) {
        let Some((at, wait)) = self.down else { return };
        let now = Instant::now();
        if now < at {
            std::thread::sleep((at.min(deadline)).saturating_duration_since(now));
            return;
        }
        let r = self.hub.reopen.lock().unwrap().as_ref().map(|f| f());
        match r {
            Some(Ok(bus)) => {
                self.inner = bus;
                self.down = None;
                {
                    let mut l = self.hub.link.lock().unwrap();
                    l.down = None;
                    l.reconnections += 1;
                    l.back_at = Some(SystemTime::now());
                }
                tracing::warn!("dashboard: the bus connection is back; scanning it again");
                // The hub may be a new one and its nodes booted again: ask who is there.
                if let Err(e) = (self.rescan)(self) {
                    let _ = self.lost(e);
                }
            }
            _ => {
                let next = (wait * 2).min(REOPEN_MAX);
                self.down = Some((Instant::now() + wait, next));
            }
        }
    }
}

impl Transport for Tap {
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        if self.down.is_some() {
            return Err(io::Error::new(
                io::ErrorKind::NotConnected,
                "the bus connection is lost; the dashboard is reconnecting",
            ));
        }
        match self.inner.send(frame) {
            Ok(()) => {
                self.record(frame, SystemTime::now(), Dir::Tx);
                Ok(())
            }
            Err(e) => {
                let kind = e.kind();
                let text = e.to_string();
                self.lost(e)?;
                Err(io::Error::new(kind, text))
            }
        }
    }

    fn recv_timeout(&mut self, timeout: Option<Duration>) -> io::Result<Option<RxFrame>> {
        let deadline = timeout.map(|t| Instant::now() + t);
        loop {
            let now = Instant::now();
            if self.down.is_some() {
                let d = deadline.unwrap_or(now + Duration::from_millis(100));
                self.wait_for_bus(d);
                if self.down.is_some() {
                    if Instant::now() >= d {
                        return Ok(None);
                    }
                    continue;
                }
            }
            let next = match self.service() {
                Ok(n) => n,
                Err(e) => {
                    self.lost(e)?;
                    continue;
                }
            };
            let until = match (deadline, next) {
                (Some(d), Some(n)) => Some(d.min(n)),
                (d, n) => d.or(n),
            };
            let wait = until.map(|u| u.saturating_duration_since(now));
            match self.inner.recv_timeout(wait) {
                Ok(Some(rx)) => {
                    self.record(&rx.frame, rx.timestamp, Dir::Rx);
                    return Ok(Some(rx));
                }
                Ok(None) => {
                    if deadline.is_some_and(|d| Instant::now() >= d) {
                        return Ok(None);
                    }
                }
                Err(e) => self.lost(e)?,
            }
        }
    }

    fn recv_deadline(&mut self, deadline: Instant) -> io::Result<Option<RxFrame>> {
        self.recv_timeout(Some(deadline.saturating_duration_since(Instant::now())))
    }

    fn try_recv(&mut self) -> io::Result<Option<RxFrame>> {
        if self.down.is_some() {
            return Ok(None);
        }
        match self.inner.try_recv() {
            Ok(Some(rx)) => {
                self.record(&rx.frame, rx.timestamp, Dir::Rx);
                Ok(Some(rx))
            }
            Ok(None) => Ok(None),
            Err(e) => self.lost(e).map(|()| None),
        }
    }

    fn receiver(&self) -> &canpos_host::crossbeam_channel::Receiver<RxFrame> {
        self.inner.receiver()
    }

    fn dead_error(&self) -> io::Error {
        self.inner.dead_error()
    }

    fn bus_bitrate(&self) -> Option<u32> {
        self.inner.bus_bitrate()
    }

    fn dropped(&self) -> u64 {
        self.inner.dropped()
    }

    fn bus_state(&self) -> BusState {
        if self.down.is_some() {
            return BusState::BusOff;
        }
        self.inner.bus_state()
    }

    fn tx_overflows(&self) -> u64 {
        self.inner.tx_overflows()
    }

    fn reconnections(&self) -> u64 {
        self.hub.link.lock().unwrap().reconnections
    }

    fn describe(&self) -> String {
        self.inner.describe()
    }
}

/// The link state for the page.
pub fn link_json(l: &LinkState) -> Value {
    json!({
        "down_since": l.down.as_ref().map(|(t, _)| secs(*t)),
        "down_why": l.down.as_ref().map(|(_, w)| w.clone()),
        "reconnections": l.reconnections,
        "back_at": l.back_at.map(secs),
    })
}

// --- The HTTP side ------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;

    fn std(id: u16, d: &[u8]) -> Frame {
        Frame::new(id, d).unwrap()
    }

    fn lease(name: &str) -> Term {
        Term::Lease(name.to_string())
    }

    fn at(ms: u64) -> SystemTime {
        UNIX_EPOCH + Duration::from_millis(1_700_000_000_000 + ms)
    }

    #[test]
    fn a_row_counts_and_times_its_identifier_from_the_frames_stamps() {
        let mut t = Trace::new(1000);
        let now = Instant::now();
        let f = std(0x1FF, &[1, 2, 3, 4, 5, 6, 7]);
        // 1,500 frames 1 ms apart by their stamps, all arriving at one instant (a batch).
        for i in 0..1500 {
            t.note(&f, at(i), Dir::Rx, now);
        }
        let r = t.rows().next().unwrap();
        assert_eq!(r.count, 1500);
        assert_eq!(r.dt, Some(Duration::from_millis(1)));
        assert_eq!(r.cycle, Some(Duration::from_millis(1)));
        // 1,500 frames of 7 bytes in 1.5 s: 1,000 frames/s; a 7-byte frame is 111 bits and
        // stuff bits, about 12 % of 1 Mbit/s.
        let (load, fps) = t.load(now);
        assert!((fps - 1000.0).abs() < 1.0, "{fps}");
        assert!((11.0..15.0).contains(&load), "{load}");
        // A changed cycle shows after the next full second.
        for i in 0..1100 {
            t.note(&f, at(1500 + 2 * (i + 1)), Dir::Rx, now);
        }
        let r = t.rows().next().unwrap();
        assert_eq!(r.cycle, Some(Duration::from_millis(2)));
        assert_eq!(t.load(now + Duration::from_secs(3)), (0.0, 0.0));
    }

    #[test]
    fn the_log_and_the_rows_are_bounded() {
        let mut t = Trace::new(1000);
        let now = Instant::now();
        for i in 0..(ROWS as u32 + 10) {
            let f = Frame::with_id(i, true, &[]).unwrap();
            t.note(&f, at(0), Dir::Rx, now);
        }
        assert_eq!(t.rows.len(), ROWS);
        assert_eq!(t.unlisted, 10);
        for _ in 0..LOG {
            t.note(&std(0x80, &[]), at(1), Dir::Rx, now);
        }
        assert_eq!(t.rows.len(), ROWS);
        assert_eq!(t.log.len(), LOG);
        assert_eq!(t.log_since(t.seq() - 5).count(), 5);
        let a = answer(&t, &Monitor::new(), &Filter::default(), 0, LOG_ANSWER, now);
        assert_eq!(a["log"].as_array().unwrap().len(), LOG_ANSWER);
        assert_eq!(a["log_skipped"], LOG - LOG_ANSWER);
        let a = answer(&t, &Monitor::new(), &Filter::default(), 0, 10, now);
        assert_eq!(a["log"].as_array().unwrap().len(), 10);
        assert_eq!(a["log"][9]["seq"], t.seq());
    }

    #[test]
    fn a_filter_keeps_its_range_and_node_and_the_monitor_decodes() {
        let mut t = Trace::new(1000);
        let now = Instant::now();
        t.note(&std(0x185, &[0xE8, 3, 0, 0]), at(0), Dir::Rx, now);
        t.note(&std(0x705, &[5]), at(0), Dir::Rx, now);
        t.note(&std(0x186, &[0, 0, 0, 0]), at(0), Dir::Rx, now);
        let mon = monitor_of(
            [(
                5u8,
                &NodeInfo {
                    position_step_nm: Some(1000),
                    velocity_step: None,
                    tpdos: vec![(1, 0x185, vec![0x6020_0120])],
                },
            )]
            .into_iter(),
        );
        let ids = |f: Filter| -> Vec<String> {
            answer(&t, &mon, &f, 0, LOG_ANSWER, now)["rows"]
                .as_array()
                .unwrap()
                .iter()
                .map(|r| r["id"].as_str().unwrap().to_string())
                .collect()
        };
        assert_eq!(ids(Filter::default()), ["0x185", "0x186", "0x705"]);
        let range = Filter {
            from: Some(0x180),
            to: Some(0x1FF),
            node: None,
        };
        assert_eq!(ids(range), ["0x185", "0x186"]);
        let node = Filter {
            node: Some(5),
            ..Filter::default()
        };
        assert_eq!(ids(node), ["0x185", "0x705"]);
        let a = answer(&t, &mon, &Filter::default(), 0, LOG_ANSWER, now);
        assert_eq!(a["rows"][0]["decoded"], "node 5 TPDO1 pos1=1.000 mm");
        assert_eq!(a["rows"][2]["decoded"], "node 5 heartbeat operational");
    }

    #[test]
    fn pdos_without_a_heartbeat_infer_operational() {
        let mut t = Trace::new(1000);
        let now = Instant::now();
        assert_eq!(t.inferred_nmt(5, &[], now), None);
        t.note(&std(0x185, &[1, 2]), at(0), Dir::Rx, now);
        assert_eq!(
            t.inferred_nmt(5, &[], now).as_deref(),
            Some("operational (inferred)")
        );
        // Another node's mapping names its COB-IDs: the default one is not it.
        assert_eq!(t.inferred_nmt(5, &[0x1A0], now), None);
        // PDOs that stopped a second ago tell nothing.
        assert_eq!(t.inferred_nmt(5, &[], now + PDO_FRESH), None);
        // A boot-up followed by PDOs: operational (a start nobody's heartbeat reported).
        t.note(&std(0x705, &[0]), at(1), Dir::Rx, now);
        assert_eq!(
            t.inferred_nmt(5, &[], now).as_deref(),
            Some("operational (inferred)")
        );
        let after = now + Duration::from_millis(1);
        t.note(&std(0x705, &[0]), at(1), Dir::Rx, after);
        assert_eq!(t.inferred_nmt(5, &[], after), None);
        // A heartbeat speaks for itself.
        t.note(&std(0x705, &[0x7F]), at(1), Dir::Rx, now);
        assert_eq!(t.inferred_nmt(5, &[], now), None);
        // A guarding answer (toggle bit) is named as one.
        t.note(&std(0x705, &[0x85]), at(2), Dir::Rx, now);
        assert_eq!(
            t.inferred_nmt(5, &[], now).as_deref(),
            Some("operational (guarding)")
        );
        // Its silence for longer than HEARTBEAT_SILENCE: back to what the PDOs say.
        let later = now + HEARTBEAT_SILENCE;
        t.note(&std(0x185, &[1, 2]), at(3), Dir::Rx, later);
        assert_eq!(
            t.inferred_nmt(5, &[], later).as_deref(),
            Some("operational (inferred)")
        );
    }

    #[test]
    fn an_nmt_command_gives_the_state_of_a_node_without_heartbeat() {
        let mut t = Trace::new(1000);
        let t0 = Instant::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        t.note(&std(0x705, &[0]), at(0), Dir::Rx, ms(0));
        t.note(&std(0x000, &[0x01, 5]), at(1), Dir::Tx, ms(1));
        t.note(&std(0x185, &[1, 2]), at(2), Dir::Rx, ms(2));
        let state = |t: &Trace, when| t.inferred_nmt(5, &[], when);
        assert_eq!(state(&t, ms(2)).as_deref(), Some("operational (inferred)"));
        // Stopped from the page: no more PDOs; the boot-up's pre-operational would be wrong.
        t.note(&std(0x000, &[0x02, 5]), at(3), Dir::Tx, ms(3));
        assert_eq!(state(&t, ms(3)).as_deref(), Some("stopped (inferred)"));
        assert_eq!(state(&t, ms(5000)).as_deref(), Some("stopped (inferred)"));
        // A command to another node changes nothing; one to all does.
        t.note(&std(0x000, &[0x80, 6]), at(4), Dir::Rx, ms(5001));
        assert_eq!(state(&t, ms(5001)).as_deref(), Some("stopped (inferred)"));
        t.note(&std(0x000, &[0x01, 0]), at(5), Dir::Rx, ms(5002));
        // Started, and a still event-driven sensor sends no PDO: operational all the same.
        assert_eq!(
            state(&t, ms(9000)).as_deref(),
            Some("operational (inferred)")
        );
        // A PDO after a stop: someone started it again.
        t.note(&std(0x000, &[0x02, 5]), at(6), Dir::Rx, ms(9001));
        t.note(&std(0x185, &[1, 2]), at(7), Dir::Rx, ms(9002));
        assert_eq!(
            state(&t, ms(9002)).as_deref(),
            Some("operational (inferred)")
        );
        // A reset: the boot-up that follows speaks (pre-operational, from the watch).
        t.note(&std(0x000, &[0x81, 5]), at(8), Dir::Rx, ms(9003));
        assert_eq!(state(&t, ms(9003)), None);
        t.note(&std(0x705, &[0]), at(9), Dir::Rx, ms(9004));
        assert_eq!(state(&t, ms(9004)), None);
        // A heartbeat speaks for itself over an older command.
        t.note(&std(0x000, &[0x02, 5]), at(10), Dir::Rx, ms(9005));
        t.note(&std(0x705, &[0x04]), at(11), Dir::Rx, ms(9006));
        assert_eq!(state(&t, ms(9006)), None);
    }

    #[test]
    fn the_export_writes_the_log_as_record_does() {
        let mut t = Trace::new(1000);
        let now = Instant::now();
        t.note(&std(0x185, &[1, 2]), at(0), Dir::Rx, now);
        t.note(
            &std(0x605, &[0x40, 0, 0x10, 0, 0, 0, 0, 0]),
            at(1),
            Dir::Tx,
            now,
        );
        let c = export(&t, &Monitor::new(), &Filter::default(), Format::Candump).unwrap();
        let text = String::from_utf8(c).unwrap();
        assert_eq!(text.lines().count(), 2, "{text}");
        assert!(
            text.lines().next().unwrap().ends_with(" can0 185#0102"),
            "{text}"
        );
        let p = export(&t, &Monitor::new(), &Filter::default(), Format::Pcapng).unwrap();
        // Section header, interface description, two enhanced packet blocks of 16-byte frames.
        assert_eq!(&p[..4], &0x0A0D_0D0Au32.to_le_bytes());
        let empty = export(
            &Trace::new(1000),
            &Monitor::new(),
            &Filter::default(),
            Format::Pcapng,
        )
        .unwrap();
        assert_eq!(p.len(), empty.len() + 2 * (12 + 20 + 16));
        // The second packet block: type 6, its frame's can_id big-endian (0x605).
        let epb = &p[empty.len() + 48..];
        assert_eq!(&epb[..4], &6u32.to_le_bytes());
        assert_eq!(&epb[28..32], &0x605u32.to_be_bytes());
    }

    #[test]
    fn the_transmitter_is_bounded_and_replaces_a_job_of_the_same_identifier() {
        let hub = TraceHub::new(1000);
        let now = Instant::now();
        for _ in 0..ONCE_QUEUE {
            hub.send_once(std(0x100, &[])).unwrap();
        }
        assert_eq!(hub.send_once(std(0x100, &[])), Err(SendRefused::Busy));
        for i in 0..PERIODIC as u16 {
            hub.send_periodic(std(0x200 + i, &[]), MIN_PERIOD, lease("p"), now)
                .unwrap();
        }
        let extra = std(0x300, &[]);
        assert_eq!(
            hub.send_periodic(extra, MIN_PERIOD, lease("p"), now),
            Err(SendRefused::TooMany)
        );
        // The same identifier again: replaced, not added.
        hub.send_periodic(std(0x200, &[9]), MAX_PERIOD, lease("p"), now)
            .unwrap();
        assert_eq!(hub.periodic().len(), PERIODIC);
        assert!(hub.stop_periodic(false, 0x200));
        assert!(!hub.stop_periodic(false, 0x200));
        assert_eq!(hub.periodic().len(), PERIODIC - 1);
    }

    #[test]
    fn a_frame_is_not_kept_to_go_out_when_the_hub_comes_back() {
        let bus = canpos_host::MemBus::instant();
        let hub = TraceHub::new(1000);
        hub.reopen_with(Box::new(|| Err(io::Error::other("not yet"))));
        let mut tap = Tap::new(
            Box::new(bus.attach()),
            hub.clone(),
            crate::dashboard::watch::scan,
        );
        hub.send_once(std(0x000, &[0x81, 0])).unwrap();
        tap.lost(io::Error::new(io::ErrorKind::ConnectionReset, "gone"))
            .unwrap();
        // Queued before the loss: dropped, not sent whenever the hub is back (minutes later).
        assert!(hub.once.lock().unwrap().is_empty());
        // Asked for while the hub is away: refused, nothing queued.
        assert_eq!(hub.send_once(std(0x123, &[1])), Err(SendRefused::Down));
        assert_eq!(
            hub.send_periodic(std(0x124, &[]), MIN_PERIOD, lease("p"), Instant::now()),
            Err(SendRefused::Down)
        );
        assert!(hub.once.lock().unwrap().is_empty() && hub.periodic().is_empty());
        // Back: taken again.
        hub.link.lock().unwrap().down = None;
        assert_eq!(hub.send_once(std(0x123, &[1])), Ok(()));
    }

    #[test]
    fn the_tap_sends_the_pages_frames_and_records_both_ways() {
        let bus = canpos_host::MemBus::instant();
        let port = bus.attach();
        let mut peer = bus.attach();
        let hub = TraceHub::new(1000);
        let mut tap = Tap::new(Box::new(port), hub.clone(), crate::dashboard::watch::scan);
        hub.send_once(std(0x123, &[0xAB])).unwrap();
        hub.send_periodic(
            std(0x124, &[]),
            Duration::from_millis(5),
            lease("p"),
            Instant::now(),
        )
        .unwrap();
        peer.send(&std(0x701, &[5])).unwrap();
        let got = tap.recv_timeout(Some(Duration::from_millis(50))).unwrap();
        assert_eq!(got.map(|r| r.frame.id()), Some(0x701));
        let heard: Vec<u32> = std::iter::from_fn(|| peer.try_recv().unwrap())
            .map(|r| r.frame.id())
            .collect();
        assert_eq!(&heard[..2], [0x123, 0x124]);
        let t = hub.trace.lock().unwrap();
        let dirs: Vec<(u32, Dir)> = t.rows().map(|r| (r.frame.id(), r.dir)).collect();
        assert_eq!(dirs, [(0x123, Dir::Tx), (0x124, Dir::Tx), (0x701, Dir::Rx)]);
    }

    /// The frames of 0x124 `due` hands out at each of `times` (ms after `t0`).
    fn sent_at(hub: &TraceHub, t0: Instant, times: impl IntoIterator<Item = u64>) -> Vec<u64> {
        times
            .into_iter()
            .filter(|ms| {
                let (due, _) = hub.due(t0 + Duration::from_millis(*ms));
                due.iter().any(|f| f.id() == 0x124)
            })
            .collect()
    }

    #[test]
    fn a_periodic_transmission_ends_with_its_lease_unless_renewed() {
        // A virtual clock: `due` is asked at instants the test chooses, nothing sleeps.
        let hub = TraceHub::new(1000);
        let t0 = Instant::now();
        let period = Duration::from_millis(100);
        hub.send_periodic(std(0x124, &[1]), period, lease("page-a"), t0)
            .unwrap();
        hub.send_periodic(std(0x125, &[2]), period, lease("page-b"), t0)
            .unwrap();
        // Sent every 100 ms; the wake-up is the next frame, not the lease's end.
        let (due, wake) = hub.due(t0);
        assert_eq!(due.len(), 2);
        assert_eq!(wake, Some(t0 + period));
        // Page a renews at 2 s and 6 s (within each lease), page b never.
        let sent = sent_at(&hub, t0, (1..=20).map(|i| i * 100));
        assert_eq!(sent.len(), 20, "{sent:?}");
        assert_eq!(hub.renew("page-a", t0 + Duration::from_secs(2)), 1);
        assert_eq!(hub.renew("nobody", t0 + Duration::from_secs(2)), 0);
        // Renewed too late (the bus thread has not dropped it yet): it stays ended.
        assert_eq!(hub.renew("page-b", t0 + LEASE), 0);
        let _ = sent_at(&hub, t0, (21..=49).map(|i| i * 100));
        // At 5 s b's lease is over: b is gone, a is still sent.
        let (due, _) = hub.due(t0 + LEASE);
        assert_eq!(due.iter().map(|f| f.id()).collect::<Vec<_>>(), [0x124]);
        assert_eq!(hub.periodic().len(), 1);
        assert_eq!(
            hub.renew("page-b", t0 + LEASE),
            0,
            "an ended lease comes not back"
        );
        assert_eq!(hub.renew("page-a", t0 + Duration::from_secs(6)), 1);
        // a's last renewal at 6 s: sent up to 11 s, never after, and the hub forgets it.
        let sent = sent_at(&hub, t0, (51..=130).map(|i| i * 100));
        assert_eq!(sent.first(), Some(&5100));
        assert_eq!(sent.last(), Some(&10_900), "{sent:?}");
        assert!(hub.periodic().is_empty());
        assert_eq!(hub.due(t0 + Duration::from_secs(60)), (vec![], None));
    }

    #[test]
    fn a_bus_thread_that_wakes_late_still_ends_the_job_on_time() {
        let hub = TraceHub::new(1000);
        let t0 = Instant::now();
        // A period longer than the lease: the wake-up is the lease's end, not the next frame.
        hub.send_periodic(std(0x124, &[]), MAX_PERIOD, lease("p"), t0)
            .unwrap();
        let (due, wake) = hub.due(t0);
        assert_eq!((due.len(), wake), (1, Some(t0 + LEASE)));
        // Asked long after its end (a stalled thread): nothing more goes out.
        assert_eq!(hub.due(t0 + Duration::from_secs(3600)).0, vec![]);
        assert!(hub.periodic().is_empty());
    }

    #[test]
    fn a_duration_ends_a_job_without_renewal_and_a_lease_is_stopped_whole() {
        let hub = TraceHub::new(1000);
        let t0 = Instant::now();
        let period = Duration::from_millis(10);
        hub.send_periodic(
            std(0x124, &[]),
            period,
            Term::For(Duration::from_secs(30)),
            t0,
        )
        .unwrap();
        // Renewing a name does not touch a job that has none.
        assert_eq!(hub.renew("p", t0), 0);
        assert_eq!(hub.periodic()[0].ends, t0 + Duration::from_secs(30));
        let sent = sent_at(&hub, t0, [0, 10_000, 29_990, 30_000, 30_010]);
        assert_eq!(sent, [0, 10_000, 29_990]);
        // A duration beyond the bound is held to it.
        hub.send_periodic(std(0x124, &[]), period, Term::For(Duration::MAX), t0)
            .unwrap();
        assert_eq!(hub.periodic()[0].ends, t0 + MAX_DURATION);
        // A page that closes stops all its jobs at once, and only its own.
        for i in 0..3 {
            hub.send_periodic(std(0x200 + i, &[]), period, lease("page-a"), t0)
                .unwrap();
        }
        assert_eq!(hub.stop_lease("page-a"), 3);
        assert_eq!(hub.stop_lease("page-a"), 0);
        assert_eq!(hub.periodic().len(), 1);
        assert_ne!(hub.new_lease(), hub.new_lease());
    }

    #[test]
    fn the_bit_rate_of_the_load_keeps_its_best_source() {
        let mut t = Trace::new(1000);
        assert_eq!(t.bitrate(), (1000, BitrateFrom::Assumed));
        assert!(t.offer_bitrate(500, BitrateFrom::Sensor));
        assert!(
            t.offer_bitrate(250, BitrateFrom::Sensor),
            "a sensor's newer word"
        );
        assert!(t.offer_bitrate(125, BitrateFrom::Given));
        assert!(!t.offer_bitrate(1000, BitrateFrom::Bus));
        assert!(!t.offer_bitrate(500, BitrateFrom::Sensor));
        assert!(!t.offer_bitrate(0, BitrateFrom::Given));
        assert_eq!(t.bitrate(), (125, BitrateFrom::Given));
        // The load is figured at it: 500 8-byte frames (111…135 bits) a second at 125 kbit/s
        // fill 44…54 % (at 1000 kbit/s it would be 6 %).
        let now = Instant::now();
        for i in 0..=500u64 {
            t.note(&std(0x185, &[0; 8]), at(2 * i), Dir::Rx, now);
        }
        let (load, _) = t.load(now);
        assert!((40.0..=60.0).contains(&load), "{load}");
        let v = answer(&t, &Monitor::new(), &Filter::default(), 0, 0, now);
        assert_eq!(
            (v["bitrate_kbps"].as_u64(), v["bitrate_from"].as_str()),
            (Some(125), Some("given"))
        );
    }
}
