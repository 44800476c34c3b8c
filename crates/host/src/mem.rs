//! In-process CAN bus: any number of [`MemPort`]s, each frame broadcast to all other ports.
//!
//! A bus is paced by default ([`Pacing`]): every frame goes through the bus [`Timeline`]
//! (crate::bus): it waits for the bus, wins or loses arbitration, takes its bit time, and
//! reaches the other ports at its end-of-frame time, stamped with it. One driver thread per
//! bus delivers frames at those times. [`Pacing::Instant`] keeps the old behaviour (every
//! frame delivered at once, without limit) for benchmarks.
//!
//! Each port has a bounded receive queue; a port whose owner does not read loses frames (counted
//! by [`MemPort::dropped`]) instead of slowing the sender or the other ports. The socketcand hub
//! uses the same bus for each of its channels, so in-process hub participants are `MemPort`s too.

use std::collections::HashMap;
use std::io;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock, Weak};

use canpos_core::Frame;
use crossbeam_channel::{Receiver, Sender, TrySendError};

use crate::bus::{BusEvent, MemberId, MemberStats, Nanos, Pacing, Timeline, DEFAULT_TX_DEPTH};
use crate::can::{BusState, BusStats, Disturbance, ErrorFrame, RxFrame, Transport};
use crate::clock::{Driver, Horizon, SimClock, Slot};
use crate::wake::Wake;

/// Default receive queue length of a port, in frames (about 0.5 s of a saturated 1 Mbit/s bus).
pub const DEFAULT_QUEUE_LEN: usize = 4096;

/// Where a bus member's frames go.
pub(crate) enum Sink {
    /// An in-process port.
    Local(Sender<RxFrame>),
    /// A socketcand TCP client of the hub: its queue, and how to tell the hub's I/O thread.
    Remote(Sender<RxFrame>, Arc<Wake>),
    /// A transmit-only controller (see [`Transport::controller`]).
    None,
}

struct Member {
    id: u64,
    /// Ports of one group do not receive each other's frames (one process's nodes, which
    /// route among themselves).
    group: u64,
    sink: Sink,
    dropped: Arc<AtomicU64>,
    /// Its controller on the timeline (paced buses).
    ctl: Option<MemberId>,
    /// A timed participant's horizon (its group's, docs/CLOCK.md): its frames are stamped
    /// with it, and a frame delivered to it holds the clock until taken.
    horizon: Option<Weak<Slot>>,
    /// The standard identifiers whose delivery holds the clock (remote frames always do);
    /// `None`: every frame. From [`Transport::set_rx_filter`]: what its nodes may answer.
    hold_ids: Option<Vec<u16>>,
    /// The bus time it joined at (paced buses; 0 on an instant bus): a frame that started on
    /// the bus before is not received by it, however late it is handed out.
    joined: Nanos,
}

/// Delivery lateness of a paced bus against its timeline: 1 µs buckets up to 10 ms.
#[derive(Clone, Debug)]
pub struct LatenessHistogram {
    buckets: Vec<u64>,
    count: u64,
}

impl Default for LatenessHistogram {
    fn default() -> Self {
        LatenessHistogram {
            buckets: vec![0; 10_001],
            count: 0,
        }
    }
}

impl LatenessHistogram {
    fn record(&mut self, late: Nanos) {
        let us = ((late / 1000) as usize).min(self.buckets.len() - 1);
        self.buckets[us] += 1;
        self.count += 1;
    }

    /// Frames recorded.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Adds what `now` recorded since `before` (an earlier copy of the same histogram).
    pub fn merge_difference(&mut self, now: &LatenessHistogram, before: &LatenessHistogram) {
        for (i, b) in self.buckets.iter_mut().enumerate() {
            let d = now.buckets[i].saturating_sub(before.buckets[i]);
            *b += d;
            self.count += d;
        }
    }

    /// The `q` quantile (0…1) in µs (10000 means "10 ms or more").
    pub fn quantile_us(&self, q: f64) -> u64 {
        let want = ((self.count as f64) * q).ceil().max(1.0) as u64;
        let mut seen = 0;
        for (us, &n) in self.buckets.iter().enumerate() {
            seen += n;
            if seen >= want {
                return us as u64;
            }
        }
        0
    }
}

struct PaceState {
    timeline: Timeline,
    events: Vec<BusEvent>,
    lateness: LatenessHistogram,
    /// How far the timeline ran: nothing is submitted earlier (simulation time, ns).
    reached: Nanos,
    /// Frames stamped after `reached` (their sender is ahead of the bus, which waits for a
    /// timed participant that is behind), of any member, timed or not, by (stamp, order of
    /// submission): they join their controller's transmit queue when the timeline reaches
    /// their stamp, not before. Queued at once, they filled the 64-frame queue while the bus
    /// stood still for the other participant: a runtime that was on time raised EMCY 0x8110
    /// for another's stall, and a hub client (python-canopen, a bridge) was told of a TX
    /// overflow on a bus that was never overloaded. At most [`FUTURE_CAP`]; more are queued
    /// at once.
    future: std::collections::BTreeMap<(Nanos, u64), (MemberId, Frame)>,
    /// Submission counter for `future`'s order.
    future_seq: u64,
}

/// Frames a paced bus keeps for their stamps at most (all members together): 2 s (the stall
/// bound) of a full 1 Mbit/s bus is about 17,000 frames.
const FUTURE_CAP: usize = 65_536;

impl PaceState {
    /// The timeline's next event, or the moment before a kept frame's stamp (when it joins
    /// its queue, so that it takes part in an arbitration at its stamp).
    fn next_due(&self) -> Option<Nanos> {
        let kept = self.future.keys().next().map(|&(t, _)| t.saturating_sub(1));
        match (self.timeline.next_event(), kept) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }
}

/// The timeline of a paced bus and the clock it runs on.
struct Pacer {
    state: Mutex<PaceState>,
    /// The simulation clock (docs/CLOCK.md): the bus runs to its `now()`, never past a timed
    /// participant's horizon.
    clock: SimClock,
    kick: Sender<()>,
    /// Receiving members with a horizon: while there are any, the bus runs event by event and
    /// stops at each frame delivered to one of them.
    timed: AtomicUsize,
}

impl Pacer {
    fn now(&self) -> Nanos {
        self.clock.now()
    }
}

/// The shared state of one virtual bus.
pub(crate) struct BusCore {
    members: RwLock<Vec<Member>>,
    next_id: AtomicU64,
    /// kbit/s; 0 = not declared (nodes of any rate talk).
    bitrate: AtomicU32,
    frames: AtomicU64,
    /// Shared with the hub when the bus is a hub channel, so totals survive the channel.
    dropped: Arc<AtomicU64>,
    /// Frames lost in transmit queues (full or bus-off), all members.
    tx_lost: AtomicU64,
    pacer: Option<Pacer>,
    /// Listeners of error frames (a bridge, a recorder); each a bounded queue.
    error_listeners: Mutex<Vec<Sender<ErrorFrame>>>,
    /// Called with every error frame on the driver thread (a hub channel: its TCP clients).
    error_hook: Mutex<Option<ErrorHook>>,
}

/// See [`BusCore::set_error_hook`].
pub(crate) type ErrorHook = Box<dyn Fn(&ErrorFrame) + Send>;

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl BusCore {
    /// Has `hook` called with each error frame of this bus, on its driver thread (it must not
    /// block): how a hub channel gives them to its TCP clients.
    pub(crate) fn set_error_hook(&self, hook: ErrorHook) {
        *lock(&self.error_hook) = Some(hook);
    }

    /// A bus whose drops are counted in `dropped` (shared with other buses), with its driver
    /// thread when paced, on a wall clock of its own.
    pub(crate) fn create(pacing: Pacing, dropped: Arc<AtomicU64>) -> Arc<BusCore> {
        Self::create_with_clock(pacing, dropped, SimClock::wall())
    }

    /// [`BusCore::create`] on `clock` (shared with other buses or a co-simulation master).
    pub(crate) fn create_with_clock(
        pacing: Pacing,
        dropped: Arc<AtomicU64>,
        clock: SimClock,
    ) -> Arc<BusCore> {
        let (kick, kicked) = crossbeam_channel::bounded(1);
        if matches!(pacing, Pacing::Paced(_)) {
            clock.subscribe_with(kick.clone());
        }
        let pacer = match pacing {
            Pacing::Instant => None,
            Pacing::Paced(kbps) => Some(Pacer {
                state: Mutex::new(PaceState {
                    // Checked by whoever took the rate from a user; a bad one here is a bug.
                    timeline: Timeline::new(kbps).unwrap_or_else(|_| {
                        Timeline::new(crate::bus::DEFAULT_BITRATE_KBPS).expect("1000 is CiA 301")
                    }),
                    events: Vec::new(),
                    lateness: LatenessHistogram::default(),
                    reached: 0,
                    future: std::collections::BTreeMap::new(),
                    future_seq: 0,
                }),
                clock,
                kick,
                timed: AtomicUsize::new(0),
            }),
        };
        let paced = pacer.is_some();
        let core = Arc::new(BusCore {
            members: RwLock::new(Vec::new()),
            next_id: AtomicU64::new(1),
            bitrate: AtomicU32::new(0),
            frames: AtomicU64::new(0),
            dropped,
            tx_lost: AtomicU64::new(0),
            pacer,
            error_listeners: Mutex::new(Vec::new()),
            error_hook: Mutex::new(None),
        });
        if paced {
            let weak = Arc::downgrade(&core);
            if let Err(e) = std::thread::Builder::new()
                .name("canpos-bus".into())
                .spawn(move || drive(weak, kicked))
            {
                tracing::error!("cannot start the bus driver thread: {e}");
            }
        }
        core
    }

    /// Adds a member (a group of its own); returns its id and its drop counter.
    pub(crate) fn join(&self, sink: Sink) -> (u64, Arc<AtomicU64>) {
        self.join_group(sink, None)
    }

    fn join_group(&self, sink: Sink, group: Option<u64>) -> (u64, Arc<AtomicU64>) {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let group = group.unwrap_or(id);
        let dropped = Arc::new(AtomicU64::new(0));
        // A hub's TCP client stands for a host's SocketCAN interface (FIFO); an in-process
        // port or controller for a sensor's CAN peripheral (by priority).
        let order = match sink {
            Sink::Remote(..) => crate::bus::TxOrder::Fifo,
            Sink::Local(_) | Sink::None => crate::bus::TxOrder::Priority,
        };
        // The bus runs up to now first, and its lock is held until the member is listed (the
        // order `pump` takes them in): what ended meanwhile goes to the members that were there,
        // and the new one receives each frame that starts from here on (every frame submitted
        // after this: they are never stamped before the time the bus reached), none before.
        let mut pace = self.pacer.as_ref().map(|p| (p, lock(&p.state)));
        let (ctl, joined) = match &mut pace {
            Some((p, st)) => {
                self.pump(p, st, p.now());
                (
                    Some(st.timeline.join_with(DEFAULT_TX_DEPTH, order)),
                    st.reached,
                )
            }
            None => (None, 0),
        };
        let mut m = self.members.write().unwrap_or_else(|e| e.into_inner());
        // A controller of a timed participant's group sends at that participant's time.
        let horizon = m
            .iter()
            .find(|m| m.group == group && m.horizon.is_some())
            .and_then(|m| m.horizon.clone());
        m.push(Member {
            id,
            group,
            sink,
            dropped: dropped.clone(),
            ctl,
            horizon,
            hold_ids: None,
            joined,
        });
        drop(m);
        drop(pace);
        (id, dropped)
    }

    pub(crate) fn leave(&self, id: u64) {
        // The timeline first, without the members' lock: delivery takes the timeline's lock,
        // then the members'.
        if let (Some(p), Some(ctl)) = (&self.pacer, self.ctl_of(id)) {
            let mut st = lock(&p.state);
            // Its frames kept for a later time join its queue now, in order, as the frames it
            // had queued already do: a leaving member's queue is still sent (a tool that sends
            // one frame and exits while the bus is held must not lose it). Its slot may be
            // reused, so none stays behind in `future`.
            let mine: Vec<(Nanos, u64)> = st
                .future
                .iter()
                .filter(|(_, (c, _))| *c == ctl)
                .map(|(k, _)| *k)
                .collect();
            let at = st.reached;
            for (i, k) in mine.iter().enumerate() {
                if let Some((_, f)) = st.future.remove(k) {
                    if st.timeline.submit(ctl, f, at + i as Nanos).is_err() {
                        self.tx_lost.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
            st.timeline.leave(ctl);
        }
        let mut m = self.members.write().unwrap_or_else(|e| e.into_inner());
        if let (Some(p), Some(gone)) = (&self.pacer, m.iter().find(|m| m.id == id)) {
            if gone.horizon.is_some() && matches!(gone.sink, Sink::Local(_)) {
                p.timed.fetch_sub(1, Ordering::Relaxed);
            }
        }
        m.retain(|m| m.id != id);
    }

    /// Makes member `id` a timed participant of the bus's clock: it and the other controllers
    /// of its group send at its horizon, and frames delivered to it hold the clock until it
    /// takes them (docs/CLOCK.md). `None` on an instant bus.
    pub(crate) fn join_clock(&self, id: u64) -> Option<Horizon> {
        self.join_clock_as(id, &format!("in-process bus port {id}"))
    }

    /// [`BusCore::join_clock`] with the participant's name for the clock's logs (a hub client:
    /// its address). A hub client (`Sink::Remote`) is stamped with its horizon but frames
    /// delivered to it do not hold the clock: it cannot say when it took them.
    pub(crate) fn join_clock_as(&self, id: u64, name: &str) -> Option<Horizon> {
        let p = self.pacer.as_ref()?;
        let h = p.clock.participant(name);
        let mut m = self.members.write().unwrap_or_else(|e| e.into_inner());
        let group = m.iter().find(|m| m.id == id)?.group;
        for m in m.iter_mut().filter(|m| m.group == group) {
            if m.horizon.is_none() && matches!(m.sink, Sink::Local(_)) {
                p.timed.fetch_add(1, Ordering::Relaxed);
            }
            m.horizon = Some(h.slot());
        }
        Some(h)
    }

    /// Only frames with these standard identifiers (and remote frames) delivered to member
    /// `id` hold the clock: the others cannot make its nodes answer, so the bus need not wait
    /// for them to be taken (they are still delivered).
    pub(crate) fn set_hold_filter(&self, id: u64, ids: &[u16]) {
        let mut ids = ids.to_vec();
        ids.sort_unstable();
        ids.dedup();
        let mut m = self.members.write().unwrap_or_else(|e| e.into_inner());
        if let Some(m) = m.iter_mut().find(|m| m.id == id) {
            m.hold_ids = Some(ids);
        }
    }

    /// Runs the bus to its clock's `now()`, delivering what is due (a timed participant does
    /// this before it takes its frames, instead of waiting for the driver thread).
    pub(crate) fn sync(&self) {
        if let Some(p) = &self.pacer {
            let now = p.now();
            let mut st = lock(&p.state);
            self.pump(p, &mut st, now);
        }
    }

    /// The controller of member `id` and the time its frames are stamped with (its group's
    /// horizon; `None`: an untimed member's, stamped with the clock's limit).
    fn ctl_and_time(&self, id: u64) -> Option<(MemberId, Option<Nanos>)> {
        let m = self.members.read().unwrap_or_else(|e| e.into_inner());
        let m = m.iter().find(|m| m.id == id)?;
        let mut at = m.horizon.as_ref().and_then(Weak::upgrade).map(|s| s.at());
        // A hub client's horizon is what it said (`< at … >`): one ahead of the wall clock
        // (a client that holds nothing) stamps its frames when they were sent, never in the
        // future, where they would block its transmit queue.
        if let (Sink::Remote(..), Some(a), Some(p)) = (&m.sink, at, &self.pacer) {
            at = Some(a.min(p.clock.limit()));
        }
        Some((m.ctl?, at))
    }

    /// The simulation clock of a paced bus.
    pub(crate) fn sim_clock(&self) -> Option<&SimClock> {
        self.pacer.as_ref().map(|p| &p.clock)
    }

    /// How far the timeline of a paced bus ran (simulation time): nothing is stamped earlier.
    pub(crate) fn reached(&self) -> Option<Nanos> {
        self.pacer.as_ref().map(|p| lock(&p.state).reached)
    }

    pub(crate) fn member_count(&self) -> usize {
        self.members
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .filter(|m| !matches!(m.sink, Sink::None))
            .count()
    }

    fn ctl_of(&self, id: u64) -> Option<MemberId> {
        self.members
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .find(|m| m.id == id)
            .and_then(|m| m.ctl)
    }

    /// Member `from`'s controller sends an error flag now ([`Timeline::error_flag`]):
    /// `Some(false)` when the bus refused it (another is pending, or the controller is
    /// bus-off), `None` on an instant bus (no timeline, no error confinement).
    pub(crate) fn error_flag(&self, from: u64) -> Option<bool> {
        let p = self.pacer.as_ref()?;
        let (ctl, at) = self.ctl_and_time(from)?;
        let now = p.now();
        let mut st = lock(&p.state);
        self.pump(p, &mut st, now);
        let at = at.unwrap_or_else(|| p.clock.limit()).max(st.reached);
        let ok = st.timeline.error_flag(ctl, at);
        drop(st);
        let _ = p.kick.try_send(());
        Some(ok)
    }

    /// Puts `frame` from member `from` on the bus: paced, into its controller's transmit queue
    /// (losses counted there); instant, to everyone at once.
    pub(crate) fn transmit(&self, from: u64, frame: Frame) {
        self.transmit_all(from, std::slice::from_ref(&frame));
    }

    /// Puts `frames` from member `from` on the bus together, as a host hands a burst to its
    /// controller in one write: paced, all into its transmit queue at one time (a nanosecond
    /// apart, in order), so that they go out back to back with nothing but their bit times
    /// between them however late the caller gets to the last one (a hub client's frames of one
    /// socket read, issue 36 item 2);
    /// instant, each to everyone at once. Returns how many frames its full transmit queue lost
    /// (a new one refused, or an earlier one pushed out by priority).
    pub(crate) fn transmit_all(&self, from: u64, frames: &[Frame]) -> usize {
        let Some(p) = &self.pacer else {
            for f in frames {
                self.broadcast(from, RxFrame::now(*f));
            }
            return 0;
        };
        let Some((ctl, at)) = self.ctl_and_time(from) else {
            return 0;
        };
        // A timed participant's frames are stamped with its own time (its horizon); an untimed
        // member's (a tool, a TCP client, a bridge) with the limit, the wall time it sent them
        // at, so that a runtime that is behind cannot answer them before they were sent. Taken
        // before the bus runs to `now()`: a stamp the clock lets the bus reach is reached
        // below, and its frames join the queue at once.
        let stamp = at.unwrap_or_else(|| p.clock.limit());
        let now = p.now();
        // The bus runs up to now before the frames join the queue: the queue is as full as
        // the timeline says, however late the driver thread is. Never stamped before the time
        // the bus already reached.
        let mut st = lock(&p.state);
        self.pump(p, &mut st, now);
        let now = stamp.max(st.reached);
        // Stamped after the time the bus reached (it waits for a timed participant that is
        // behind): kept, to join the queue when the bus gets there, whoever sent them.
        if now > st.reached && st.future.len() + frames.len() <= FUTURE_CAP {
            for (i, f) in frames.iter().enumerate() {
                let seq = st.future_seq;
                st.future_seq += 1;
                st.future.insert((now + i as Nanos, seq), (ctl, *f));
            }
            drop(st);
            let _ = p.kick.try_send(());
            return 0;
        }
        let mut overflow = 0;
        // Each a nanosecond after the one before: a controller that sends by priority (a
        // device's: `< txorder priority >`) starts the first one on an idle bus, as it would
        // the frame its firmware handed it first (a boot-up before the EMCY queued with it);
        // the others are queued while it is on the wire and still go out back to back.
        for (i, f) in frames.iter().enumerate() {
            match st.timeline.submit(ctl, *f, now + i as Nanos) {
                Ok(crate::bus::timeline::Accepted::Queued) => {}
                Ok(crate::bus::timeline::Accepted::Evicted(_))
                | Err(crate::bus::timeline::Rejected::QueueFull) => {
                    overflow += 1;
                    self.tx_lost.fetch_add(1, Ordering::Relaxed);
                }
                Err(_) => {
                    self.tx_lost.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
        drop(st);
        let _ = p.kick.try_send(());
        overflow
    }

    /// Member `from`'s transmit queue goes out in `order` from now on (paced buses).
    pub(crate) fn set_tx_order(&self, from: u64, order: crate::bus::TxOrder) {
        if let (Some(p), Some(ctl)) = (&self.pacer, self.ctl_of(from)) {
            lock(&p.state).timeline.set_order(ctl, order);
        }
    }

    /// Delivers `rx` to every member but `from` (and its group). Never blocks: a full queue
    /// drops the frame for that member only.
    pub(crate) fn broadcast(&self, from: u64, rx: RxFrame) {
        let members = self.members.read().unwrap_or_else(|e| e.into_inner());
        let group = members
            .iter()
            .find(|m| m.id == from)
            .map_or(from, |m| m.group);
        self.deliver(&members, &[group], rx, None);
    }

    /// Delivers `rx` to the members outside `groups`; on a paced bus `on_bus` is its start and
    /// end of frame: only members that joined by its start receive it, and the end is what a
    /// timed receiver's horizon remembers until it takes the frame. True when one did.
    fn deliver(
        &self,
        members: &[Member],
        groups: &[u64],
        rx: RxFrame,
        on_bus: Option<(Nanos, Nanos)>,
    ) -> bool {
        self.frames.fetch_add(1, Ordering::Relaxed);
        let mut held = false;
        let end = on_bus.map(|(_, end)| end);
        // A controller joining the bus first waits for it to be idle (bus integration): a
        // frame already on the wire, or long over but handed out late, is not received by it.
        // Otherwise a process that joins after another one was killed could act on a request
        // sent to that one (issue 36: a "save" meant for the killed sensor was carried out,
        // and answered, by its successor).
        let on_bus_since = |m: &Member| on_bus.is_none_or(|(start, _)| m.joined <= start);
        for m in members
            .iter()
            .filter(|m| !groups.contains(&m.group) && on_bus_since(m))
        {
            let full = match &m.sink {
                Sink::Local(tx) => match tx.try_send(rx) {
                    Ok(()) => {
                        let answerable = rx.frame.is_remote()
                            || m.hold_ids.as_ref().is_none_or(|ids| {
                                rx.frame
                                    .std_id()
                                    .is_some_and(|id| ids.binary_search(&id).is_ok())
                            });
                        if let (Some(end), Some(slot), true) =
                            (end, m.horizon.as_ref().and_then(Weak::upgrade), answerable)
                        {
                            slot.delivered(end);
                            held = true;
                        }
                        false
                    }
                    Err(e) => matches!(e, TrySendError::Full(_)),
                },
                // Unbounded underneath, capped here: memory grows with the backlog, not with
                // the number of clients (a bounded channel allocates its capacity up front).
                // A client that cannot take frames (its socket and output full) costs nothing
                // per frame: dropped here, without queueing or waking the hub's I/O thread.
                Sink::Remote(tx, wake) if wake.is_blocked() || tx.len() >= wake.cap => true,
                Sink::Remote(tx, wake) => {
                    if tx.send(rx).is_ok() {
                        wake.queued();
                    }
                    false
                }
                Sink::None => false,
            };
            // A disconnected sink belongs to a member that is leaving; not a drop.
            if full {
                m.dropped.fetch_add(1, Ordering::Relaxed);
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
        held
    }

    /// Runs the timeline up to `target` and delivers what it produced, under the timeline's
    /// lock (so deliveries from any thread go out in timeline order). With timed participants
    /// it runs event by event and stops at a frame delivered to one of them: the clock waits
    /// there until that participant took it (and answered at its time).
    fn pump(&self, p: &Pacer, st: &mut PaceState, target: Nanos) {
        let by_event = p.timed.load(Ordering::Relaxed) > 0;
        // Delivery lateness is against the wall clock; a stepped bus has none.
        let wall = (p.clock.driver() == Driver::Wall).then(|| p.clock.wall_elapsed());
        loop {
            // Kept frames whose time has come (the timeline ran to just before their stamp)
            // join their queues now, losses counted as any submission's.
            while let Some(e) = st.future.first_entry() {
                if e.key().0 > st.reached.saturating_add(1) {
                    break;
                }
                let ((t, _), (ctl, f)) = e.remove_entry();
                match st.timeline.submit(ctl, f, t.max(st.reached)) {
                    Ok(crate::bus::timeline::Accepted::Queued)
                    | Err(crate::bus::timeline::Rejected::NoMember) => {}
                    Ok(crate::bus::timeline::Accepted::Evicted(_))
                    | Err(crate::bus::timeline::Rejected::QueueFull) => {
                        self.tx_lost.fetch_add(1, Ordering::Relaxed);
                        // A hub client hears of it as of an overflow at submission (issue 36
                        // item 7); in-process ports read their controller's counters.
                        let members = self.members.read().unwrap_or_else(|e| e.into_inner());
                        if let Some(Member {
                            sink: Sink::Remote(_, wake),
                            ..
                        }) = members.iter().find(|m| m.ctl == Some(ctl))
                        {
                            wake.tx_overflow();
                        }
                    }
                    Err(_) => {
                        self.tx_lost.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
            let next = st.next_due();
            // Events at the time already reached are due too: a frame submitted at that time
            // (stamps never go below it) starts there. Left for later, the driver thread would
            // find it due, pump nothing and look again, spinning a core until the clock moved
            // (between two steps of a stepped clock: for ever).
            if target <= st.reached && next.is_none_or(|n| n > st.reached) {
                break;
            }
            let upto = match next {
                Some(n) if by_event && n <= target => n.max(st.reached),
                _ => target.max(st.reached),
            };
            // Never past the moment before a kept frame's stamp: it joins its queue there.
            let upto = match st.future.keys().next() {
                Some(&(t, _)) => upto.min(t.saturating_sub(1).max(st.reached)),
                None => upto,
            };
            let mut events = std::mem::take(&mut st.events);
            st.timeline.advance(upto, &mut events);
            st.reached = st.reached.max(upto);
            if let Some(w) = wall {
                for e in &events {
                    if let BusEvent::Frame { end, .. } = e {
                        st.lateness.record(w.saturating_sub(*end));
                    }
                }
            }
            let held = self.dispatch(p, &mut events);
            st.events = events;
            if held || upto >= target {
                break;
            }
            // An event the timeline keeps due at the time it reached, even after running to
            // it, would loop here under the lock for ever: give up this pump instead.
            if st.future.keys().next().is_none_or(|&(t, _)| t > upto + 1)
                && st.next_due().is_some_and(|n| n <= upto)
            {
                tracing::warn!(at = upto, "a bus event did not move on");
                break;
            }
        }
    }

    /// Whether the timeline has an event due at or before the time it reached: never after a
    /// pump (the driver thread would spin on it).
    #[cfg(test)]
    fn due_by_reached(&self) -> bool {
        let p = self.pacer.as_ref().expect("paced");
        let st = lock(&p.state);
        st.next_due().is_some_and(|n| n <= st.reached)
    }

    /// Hands what the timeline produced to the members; true when a timed participant received
    /// a frame (it holds the clock).
    fn dispatch(&self, p: &Pacer, events: &mut Vec<BusEvent>) -> bool {
        if events.is_empty() {
            return false;
        }
        let mut held = false;
        let members = self.members.read().unwrap_or_else(|e| e.into_inner());
        for ev in events.drain(..) {
            // A hub client's controller changed state: it is told, as SocketCAN tells the
            // owner of an interface (in-process ports read their counters instead).
            if let BusEvent::State { member, state, .. } = &ev {
                if let Some(Member {
                    sink: Sink::Remote(_, wake),
                    ..
                }) = members.iter().find(|m| m.ctl == Some(*member))
                {
                    wake.controller_state(*state);
                }
            }
            if let BusEvent::Error(e) = &ev {
                let ef = ErrorFrame::bus_error(e.kind, e.id, p.clock.system_time_of(e.at));
                // A listener that does not keep up loses error frames; one that left is removed.
                lock(&self.error_listeners)
                    .retain(|tx| !matches!(tx.try_send(ef), Err(TrySendError::Disconnected(_))));
                if let Some(hook) = lock(&self.error_hook).as_ref() {
                    hook(&ef);
                }
            }
            if let BusEvent::Frame {
                from,
                co_senders,
                frame,
                start,
                end,
            } = ev
            {
                let group_of =
                    |c: MemberId| members.iter().find(|m| m.ctl == Some(c)).map(|m| m.group);
                let mut groups: Vec<u64> = group_of(from).into_iter().collect();
                groups.extend(co_senders.into_iter().filter_map(group_of));
                let rx = RxFrame {
                    frame,
                    timestamp: p.clock.system_time_of(end),
                };
                held |= self.deliver(&members, &groups, rx, Some((start, end)));
            }
        }
        held
    }

    pub(crate) fn frames(&self) -> u64 {
        self.frames.load(Ordering::Relaxed)
    }

    fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    fn bitrate(&self) -> Option<u32> {
        match self.bitrate.load(Ordering::Relaxed) {
            0 => None,
            b => Some(b),
        }
    }

    /// Load and counters of the bus, and of member `id`'s controller.
    pub(crate) fn stats(&self, id: Option<u64>) -> Option<BusStats> {
        let p = self.pacer.as_ref()?;
        let ctl = id.and_then(|id| self.ctl_of(id));
        let now = p.now();
        let mut st = lock(&p.state);
        self.pump(p, &mut st, now);
        let now = now.max(st.reached);
        let (load, fps) = st.timeline.load(now);
        Some(BusStats {
            bitrate_kbps: st.timeline.bitrate_kbps(),
            load,
            frames_per_s: fps,
            frames: st.timeline.frames(),
            error_frames: st.timeline.error_frames(),
            tx_lost: self.tx_lost.load(Ordering::Relaxed),
            rx_dropped: self.dropped(),
            controller: ctl.and_then(|c| st.timeline.stats(c)),
        })
    }

    /// Delivery lateness against the timeline so far (paced buses).
    pub(crate) fn lateness(&self) -> Option<LatenessHistogram> {
        self.pacer.as_ref().map(|p| lock(&p.state).lateness.clone())
    }

    pub(crate) fn disturb(&self, id: Option<u64>, d: Disturbance) -> Result<(), String> {
        let Some(p) = &self.pacer else {
            return Err("the bus is unpaced (instant): it has no physical layer to disturb".into());
        };
        let now = p.now();
        let mut st = lock(&p.state);
        let now = now.max(st.reached);
        let r = match d {
            Disturbance::CorruptedFrames { per_million } => {
                st.timeline.set_corruption(per_million).map_err(|e| e.0)
            }
            Disturbance::StuckDominant { duration } => {
                let ns = u64::try_from(duration.as_nanos()).unwrap_or(u64::MAX);
                st.timeline.stuck_dominant(now, ns).map_err(|e| e.0)
            }
            Disturbance::TransceiverFailed(on) => {
                let ctl = id
                    .and_then(|id| self.ctl_of(id))
                    .ok_or("no controller on this bus")?;
                st.timeline.set_transceiver_failed(ctl, on, now);
                Ok(())
            }
        };
        drop(st);
        let _ = p.kick.try_send(());
        r
    }
}

/// The driver of a paced bus: runs the timeline at its own pace and delivers what it produced;
/// ends with the bus.
fn drive(core: Weak<BusCore>, kicked: Receiver<()>) {
    crate::sys::set_timer_slack_1ns();
    // Frames are due at their bit times: the driver runs at the runtime's priority
    // (`--rt-priority`), where one was asked for.
    if let Err(e) = crate::realtime::runtime_thread() {
        tracing::debug!(error = %e, "bus driver keeps the process's priority");
    }
    loop {
        let Some(c) = core.upgrade() else { return };
        let Some(p) = &c.pacer else { return };
        let now = p.now();
        let next = {
            let mut st = lock(&p.state);
            c.pump(p, &mut st, now);
            st.next_due()
        };
        let clock = p.clock.clone();
        drop(c);
        let limit = clock.limit();
        let mut held = false;
        let deadline = match next {
            // Due, and the clock allows it (a pump that stopped at a delivery goes on).
            Some(n) if n <= clock.now() => continue,
            // Due by the limit, but a timed participant is behind: wait for its horizon to
            // move (it tells the clock's listeners while one waits), at most until it falls
            // behind the stall bound.
            Some(n) if n <= limit => {
                clock.waiting(true);
                let h = clock.now();
                if h >= n {
                    clock.waiting(false);
                    continue;
                }
                held = true;
                (clock.driver() == Driver::Wall)
                    .then(|| clock.instant_of(h + clock.stall_bound() + 1_000_000))
            }
            Some(n) if clock.driver() == Driver::Wall => Some(clock.instant_of(n)),
            // Stepped: the next step (the clock tells its listeners).
            _ => None,
        };
        // Without a deadline it still looks again now and then: the bus may be gone.
        let deadline = deadline
            .unwrap_or_else(|| std::time::Instant::now() + std::time::Duration::from_secs(1));
        let r = kicked.recv_deadline(deadline);
        if held {
            clock.waiting(false);
        }
        if matches!(r, Err(crossbeam_channel::RecvTimeoutError::Disconnected)) {
            return;
        }
    }
}

/// An in-process CAN bus. Cloning gives another handle to the same bus.
#[derive(Clone)]
pub struct MemBus {
    core: Arc<BusCore>,
    queue_len: usize,
}

impl Default for MemBus {
    fn default() -> Self {
        Self::new()
    }
}

impl MemBus {
    /// A new, empty bus paced at the default bit rate
    /// ([`DEFAULT_BITRATE_KBPS`](crate::bus::DEFAULT_BITRATE_KBPS)); no bit rate is declared to
    /// the nodes (every node talks).
    pub fn new() -> Self {
        Self::with_pacing(Pacing::default())
    }

    /// A new bus with explicit pacing; a paced bus declares its bit rate to the nodes only
    /// through [`MemBus::set_bitrate`].
    pub fn with_pacing(pacing: Pacing) -> Self {
        MemBus {
            core: BusCore::create(pacing, Arc::new(AtomicU64::new(0))),
            queue_len: DEFAULT_QUEUE_LEN,
        }
    }

    /// A new bus paced at `kbps` on `clock`: a stepped clock a co-simulation master moves on,
    /// or a clock shared with other buses (docs/CLOCK.md).
    pub fn with_clock(kbps: u32, clock: SimClock) -> Self {
        MemBus {
            core: BusCore::create_with_clock(
                Pacing::Paced(kbps),
                Arc::new(AtomicU64::new(0)),
                clock,
            ),
            queue_len: DEFAULT_QUEUE_LEN,
        }
    }

    /// The simulation clock of a paced bus (`None`: an instant bus).
    pub fn clock(&self) -> Option<SimClock> {
        self.core.pacer.as_ref().map(|p| p.clock.clone())
    }

    /// Today's instant bus: every frame delivered at once, no bit time, no limit (benchmarks).
    pub fn instant() -> Self {
        Self::with_pacing(Pacing::Instant)
    }

    pub(crate) fn from_core(core: Arc<BusCore>, queue_len: usize) -> Self {
        MemBus { core, queue_len }
    }

    /// The process-wide bus called `name` (what `mem://NAME` opens), created on first use with
    /// `pacing` (ignored when it exists already).
    pub fn named_with(name: &str, pacing: Pacing) -> MemBus {
        static REGISTRY: OnceLock<Mutex<HashMap<String, MemBus>>> = OnceLock::new();
        let mut reg = lock(REGISTRY.get_or_init(Default::default));
        reg.entry(name.to_string())
            .or_insert_with(|| MemBus::with_pacing(pacing))
            .clone()
    }

    /// The process-wide bus called `name`, paced at the default rate when new.
    pub fn named(name: &str) -> MemBus {
        Self::named_with(name, Pacing::default())
    }

    /// Sets the receive queue length of ports attached from now on through this handle.
    pub fn with_queue_len(mut self, len: usize) -> Self {
        self.queue_len = len.max(1);
        self
    }

    /// Declares the bus bit rate to the nodes in kbit/s (`None`: not declared; nodes of any
    /// rate talk). Ports see the change at once. The pacing rate is the bus's own, set when it
    /// was created.
    pub fn set_bitrate(&self, kbit: Option<u32>) {
        self.core
            .bitrate
            .store(kbit.unwrap_or(0), Ordering::Relaxed);
    }

    /// The bus bit rate in kbit/s, if declared.
    pub fn bitrate(&self) -> Option<u32> {
        self.core.bitrate()
    }

    /// Connects a new port to the bus.
    pub fn attach(&self) -> MemPort {
        let (tx, rx) = crossbeam_channel::bounded(self.queue_len);
        let (id, dropped) = self.core.join(Sink::Local(tx));
        MemPort {
            core: self.core.clone(),
            id,
            rx,
            dropped,
            _keep: None,
        }
    }

    /// Connects a transmit-only port: it receives nothing (no receive queue to fill), e.g. a
    /// load generator.
    pub fn attach_transmitter(&self) -> MemPort {
        let (tx, rx) = crossbeam_channel::bounded(1);
        let (id, dropped) = self.core.join_group(Sink::None, None);
        MemPort {
            core: self.core.clone(),
            id,
            rx,
            dropped,
            _keep: Some(tx),
        }
    }

    /// Number of attached ports (and, for a hub channel, TCP clients).
    pub fn port_count(&self) -> usize {
        self.core.member_count()
    }

    /// Frames delivered on the bus so far.
    pub fn frames(&self) -> u64 {
        self.core.frames()
    }

    /// Deliveries dropped so far because some port's queue was full.
    pub fn dropped(&self) -> u64 {
        self.core.dropped()
    }

    /// Load and counters (paced buses).
    pub fn stats(&self) -> Option<BusStats> {
        self.core.stats(None)
    }

    /// Lateness of deliveries against the bus timeline so far (paced buses).
    pub fn lateness(&self) -> Option<LatenessHistogram> {
        self.core.lateness()
    }

    /// Error frames on this bus from now on, in timeline order (a queue of 1024; a listener
    /// that falls behind loses the excess). An instant bus has none.
    pub fn error_frames(&self) -> Receiver<ErrorFrame> {
        let (tx, rx) = crossbeam_channel::bounded(1024);
        lock(&self.core.error_listeners).push(tx);
        rx
    }

    /// Applies a bus-level disturbance (not [`Disturbance::TransceiverFailed`]: that is a
    /// port's, see [`Transport::disturb`]).
    pub fn disturb(&self, d: Disturbance) -> Result<(), String> {
        self.core.disturb(None, d)
    }
}

/// One participant of a [`MemBus`] (or of a hub channel). Dropping it leaves the bus.
pub struct MemPort {
    core: Arc<BusCore>,
    id: u64,
    rx: Receiver<RxFrame>,
    dropped: Arc<AtomicU64>,
    /// A transmit-only controller keeps its (never used) queue's sender here.
    _keep: Option<Sender<RxFrame>>,
}

impl MemPort {
    /// Frames this port lost because its queue was full.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Sends a frame with an explicit timestamp at once, past the timeline (e.g. replaying a
    /// log or simulated time).
    pub fn send_at(&self, rx: RxFrame) {
        self.core.broadcast(self.id, rx);
    }

    /// Another CAN controller on this bus in this port's group: it only transmits (its frames
    /// do not reach this port), with its own transmit queue and error counters.
    pub fn sibling_controller(&self) -> MemPort {
        let (tx, rx) = crossbeam_channel::bounded(1);
        let group = self
            .core
            .members
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .find(|m| m.id == self.id)
            .map_or(self.id, |m| m.group);
        let (id, dropped) = self.core.join_group(Sink::None, Some(group));
        MemPort {
            core: self.core.clone(),
            id,
            rx,
            dropped,
            _keep: Some(tx),
        }
    }
}

impl Drop for MemPort {
    fn drop(&mut self) {
        self.core.leave(self.id);
    }
}

impl Transport for MemPort {
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        self.core.transmit(self.id, *frame);
        Ok(())
    }

    fn receiver(&self) -> &Receiver<RxFrame> {
        &self.rx
    }

    fn bus_bitrate(&self) -> Option<u32> {
        self.core.bitrate()
    }

    fn dropped(&self) -> u64 {
        MemPort::dropped(self)
    }

    fn bus_state(&self) -> BusState {
        self.core
            .stats(Some(self.id))
            .and_then(|s| s.controller)
            .map_or(BusState::ErrorActive, |c: MemberStats| c.state)
    }

    fn bus_stats(&self) -> Option<BusStats> {
        self.core.stats(Some(self.id))
    }

    fn controller(&self) -> Option<Box<dyn Transport>> {
        self.core
            .pacer
            .is_some()
            .then(|| Box::new(self.sibling_controller()) as Box<dyn Transport>)
    }

    fn disturb(&self, d: Disturbance) -> Result<(), String> {
        self.core.disturb(Some(self.id), d)
    }

    fn join_clock(&mut self) -> Option<Horizon> {
        self.core.join_clock(self.id)
    }

    fn sync_bus(&self) {
        self.core.sync();
    }

    /// Delivers every frame still (an in-process bus does not filter); only the frames with
    /// these identifiers hold a timed participant's clock (docs/CLOCK.md).
    fn set_rx_filter(&mut self, std_ids: &[u16]) -> io::Result<bool> {
        self.core.set_hold_filter(self.id, std_ids);
        Ok(false)
    }

    fn describe(&self) -> String {
        format!("in-process bus port {}", self.id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn f(id: u16) -> Frame {
        Frame::new(id, &[id as u8]).unwrap()
    }

    #[test]
    fn broadcasts_to_others_only() {
        // About who receives what, not about time: the instant bus.
        let bus = MemBus::instant();
        let mut a = bus.attach();
        let mut b = bus.attach();
        let mut c = bus.attach();
        a.send(&f(1)).unwrap();
        assert_eq!(b.try_recv().unwrap().unwrap().frame, f(1));
        assert_eq!(c.try_recv().unwrap().unwrap().frame, f(1));
        assert_eq!(a.try_recv().unwrap(), None);
        assert_eq!(bus.port_count(), 3);
        drop(c);
        assert_eq!(bus.port_count(), 2);
        b.send(&f(2)).unwrap();
        assert_eq!(a.recv_timeout(None).unwrap().unwrap().frame, f(2));
        assert_eq!(bus.frames(), 2);
    }

    #[test]
    fn full_queue_drops_for_that_port_only() {
        let bus = MemBus::instant().with_queue_len(4);
        let mut tx = bus.attach();
        let slow = bus.attach();
        let mut fast = bus.attach();
        for i in 0..10 {
            tx.send(&f(i)).unwrap();
            assert_eq!(fast.try_recv().unwrap().unwrap().frame, f(i));
        }
        assert_eq!(slow.dropped(), 6);
        assert_eq!(fast.dropped(), 0);
        assert_eq!(bus.dropped(), 6);
        // The oldest frames are the ones kept.
        assert_eq!(slow.receiver().try_recv().unwrap().frame, f(0));
    }

    #[test]
    fn bitrate_is_visible_to_ports() {
        let bus = MemBus::new();
        let p = bus.attach();
        assert_eq!(p.bus_bitrate(), None);
        bus.set_bitrate(Some(250));
        assert_eq!(p.bus_bitrate(), Some(250));
        assert_eq!(bus.bitrate(), Some(250));
    }

    #[test]
    fn recv_deadline_times_out_precisely() {
        let bus = MemBus::new();
        let mut p = bus.attach();
        let start = std::time::Instant::now();
        let deadline = start + Duration::from_millis(5);
        assert_eq!(p.recv_deadline(deadline).unwrap(), None);
        assert!(std::time::Instant::now() >= deadline);
    }

    #[test]
    fn select_over_many_ports() {
        let bus = MemBus::new();
        let mut tx = bus.attach();
        let ports: Vec<MemPort> = (0..5).map(|_| bus.attach()).collect();
        tx.send(&f(7)).unwrap();
        let mut sel = crossbeam_channel::Select::new();
        for p in &ports {
            sel.recv(p.receiver());
        }
        let deadline = std::time::Instant::now() + Duration::from_secs(1);
        let i = sel.ready_deadline(deadline).unwrap();
        assert_eq!(ports[i].receiver().try_recv().unwrap().frame, f(7));
    }

    #[test]
    fn paced_bus_delivers_one_frame_at_a_time_at_end_of_frame() {
        // 125 kbit/s: an 8-byte frame is 111…135 bits, 888…1080 µs.
        let bus = MemBus::with_pacing(Pacing::Paced(125));
        let mut a = bus.attach();
        let mut b = bus.attach();
        let mut rx = bus.attach();
        for i in 0..10u8 {
            a.send(&Frame::new(0x181, &[i; 8]).unwrap()).unwrap();
            b.send(&Frame::new(0x182, &[i; 8]).unwrap()).unwrap();
        }
        let mut got = Vec::new();
        while got.len() < 20 {
            let f = rx
                .recv_timeout(Some(Duration::from_secs(5)))
                .unwrap()
                .unwrap();
            got.push(f);
        }
        for w in got.windows(2) {
            let gap = w[1].timestamp.duration_since(w[0].timestamp).unwrap();
            // Never closer than the later frame's own time on the wire.
            let bits = crate::bus::bits::frame_length(&w[1].frame).total;
            assert!(gap >= Duration::from_micros(u64::from(bits) * 8), "{gap:?}");
        }
        // Lowest identifier first at every arbitration: once both queue, 0x181 goes first.
        assert_eq!(got[0].frame.id(), 0x181);
        let s = bus.stats().unwrap();
        assert_eq!(s.frames, 20);
        assert!(s.load > 0.0);
        assert_eq!(a.bus_stats().unwrap().controller.unwrap().sent, 10);
    }

    #[test]
    fn sibling_controllers_arbitrate_and_do_not_echo_to_their_group() {
        // A long frame holds the bus (125 bits at 125 kbit/s: 1 ms) while both queue.
        let bus = MemBus::with_pacing(Pacing::Paced(125));
        let mut main = bus.attach();
        let mut other = bus.attach();
        let mut c1 = main.controller().unwrap();
        let mut c2 = main.controller().unwrap();
        other.send(&Frame::new(0x100, &[0; 8]).unwrap()).unwrap();
        c1.send(&Frame::new(0x185, &[1]).unwrap()).unwrap();
        c2.send(&Frame::new(0x185, &[2]).unwrap()).unwrap();
        // Same identifier, different data, in one arbitration: a collision, retried.
        let f = other
            .recv_timeout(Some(Duration::from_secs(5)))
            .unwrap()
            .unwrap();
        assert_eq!(f.frame.id(), 0x185);
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(
            main.try_recv().unwrap().map(|f| f.frame.id()),
            Some(0x100),
            "only the other port's frame reaches the group"
        );
        assert_eq!(
            main.try_recv().unwrap(),
            None,
            "the group's own frames do not come back"
        );
        let s1 = c1.bus_stats().unwrap().controller.unwrap();
        assert!(s1.collisions >= 1, "{s1:?}");
        assert_eq!(bus.port_count(), 2);
    }

    #[test]
    fn listeners_see_error_frames() {
        // At 10 kbit/s the 32 corrupted attempts that would take the sender bus-off (and lose
        // its frame) last about 0.2 s, so lifting the disturbance after the first error frame
        // wins that race even on a loaded machine; at the default rate it took 2 ms and lost.
        let bus = MemBus::with_pacing(Pacing::Paced(10));
        let errors = bus.error_frames();
        let mut a = bus.attach();
        let mut b = bus.attach();
        bus.disturb(Disturbance::CorruptedFrames {
            per_million: 1_000_000,
        })
        .unwrap();
        a.send(&Frame::new(0x181, &[1]).unwrap()).unwrap();
        let e = errors.recv_timeout(Duration::from_secs(5)).unwrap();
        // A corrupted frame: a protocol form error, naming the frame.
        assert_eq!(
            e,
            ErrorFrame::bus_error(
                crate::bus::BusErrorKind::Corrupted,
                Some(0x181),
                e.timestamp
            )
        );
        assert_eq!(e.class, crate::can::err_class::PROT);
        assert_eq!(e.data.unwrap()[2], 0x02);
        assert_eq!(e.id, Some(0x181));
        bus.disturb(Disturbance::CorruptedFrames { per_million: 0 })
            .unwrap();
        // The retransmission gets through.
        let f = b
            .recv_timeout(Some(Duration::from_secs(5)))
            .unwrap()
            .unwrap();
        assert_eq!(f.frame.id(), 0x181);
        assert!(a.bus_stats().unwrap().controller.unwrap().tx_errors >= 1);
    }

    /// The bus waits for a timed participant that is behind, but not forever: one that never
    /// moves (deadlocked, stopped) holds it no longer than the clock's stall bound, then the
    /// others' frames flow again, late by about that bound.
    #[test]
    fn a_stopped_participant_holds_the_bus_no_longer_than_the_stall_bound() {
        let bound = Duration::from_millis(100);
        let bus = MemBus::with_clock(1000, SimClock::wall_with_stall_bound(bound));
        let mut stuck = bus.attach();
        let mut a = bus.attach();
        let mut b = bus.attach();
        // Before the horizon is taken: it stands at the clock's time then, at or after this.
        let sent = std::time::Instant::now();
        let _horizon = stuck.join_clock().expect("a paced bus has a clock");
        a.send(&f(1)).unwrap();
        let got = b
            .recv_timeout(Some(Duration::from_secs(10)))
            .unwrap()
            .expect("delivered once the stopped participant stopped holding");
        assert_eq!(got.frame, f(1));
        // Held while the stuck horizon was within the bound (a lower bound only: the machine
        // may be late, never early).
        assert!(sent.elapsed() >= bound, "{:?}", sent.elapsed());
        // Stale, it holds nothing: the next frame goes through at once (generous bound).
        let sent = std::time::Instant::now();
        a.send(&f(2)).unwrap();
        assert_eq!(
            b.recv_timeout(Some(Duration::from_secs(10)))
                .unwrap()
                .unwrap()
                .frame,
            f(2)
        );
        assert!(sent.elapsed() < Duration::from_secs(5));
        // The stuck one got both (its queue holds them; it never took them).
        assert_eq!(stuck.try_recv().unwrap().unwrap().frame, f(1));
    }

    /// A frame delivered to a timed participant holds the clock at its end of frame until the
    /// participant takes it: its answer, stamped at that time, still goes out before anything
    /// submitted later (stepped clock: deterministic).
    #[test]
    fn a_delivered_frame_holds_the_clock_until_taken() {
        let clock = SimClock::stepped();
        let bus = MemBus::with_clock(1000, clock.clone());
        let mut rt = bus.attach();
        let h = rt.join_clock().unwrap();
        h.set(u64::MAX);
        let mut master = bus.attach();
        master.send(&f(0x601)).unwrap();
        clock.step_to(1_000_000).unwrap();
        rt.sync_bus();
        let rx = rt
            .try_recv()
            .unwrap()
            .expect("delivered at its end of frame");
        let end = clock.nanos_of(rx.timestamp).unwrap();
        assert!(end < 1_000_000);
        assert_eq!(clock.now(), end, "held at the frame until taken");
        // The answer at the frame's own time, then taken: the bus goes on.
        h.set(end);
        rt.send(&f(0x581)).unwrap();
        h.taken(end);
        h.set(u64::MAX);
        master.sync_bus();
        let answer = master.try_recv().unwrap().expect("the answer");
        let bits = u64::from(crate::bus::bits::frame_length(&answer.frame).total);
        // Ready at `end`, it starts after the intermission (3 bits) and lasts its bits less
        // the intermission: end of frame = end + bits × 1 µs.
        assert_eq!(
            clock.nanos_of(answer.timestamp).unwrap(),
            end + bits * 1_000
        );
    }

    /// Issue 36 (a flaky `sigkill_during_store…`): a frame handed out late by the driver thread
    /// reached a port that joined after the frame was on the bus, so a restarted sensor carried
    /// out a "save" sent to the one killed before it. The driver is made late here by handing
    /// the timeline's output over by hand: a frame that started before a port joined does not
    /// reach it, one that started after does.
    #[test]
    fn a_port_does_not_receive_frames_that_started_before_it_joined() {
        let bus = MemBus::with_pacing(Pacing::Paced(125));
        let mut early = bus.attach();
        let core = &bus.core;
        let p = core.pacer.as_ref().unwrap();
        // A frame that starts after `early` joined, and before `late` does.
        let before = p.now();
        while p.now() == before {
            std::hint::spin_loop();
        }
        let mut late = bus.attach();
        let joined = p.now();
        let frame = |id, start| BusEvent::Frame {
            // No member's controller: sent by a port that has left since.
            from: MemberId(u32::MAX),
            co_senders: Vec::new(),
            frame: f(id),
            start,
            end: start + 1_000_000,
        };
        // Both handed out now, long after the first one's end of frame.
        core.dispatch(p, &mut vec![frame(1, before), frame(2, joined)]);
        assert_eq!(early.try_recv().unwrap().unwrap().frame, f(1));
        assert_eq!(early.try_recv().unwrap().unwrap().frame, f(2));
        assert_eq!(late.try_recv().unwrap().unwrap().frame, f(2));
        assert_eq!(late.try_recv().unwrap(), None);
    }

    /// A frame still on the wire when a port joins is not received by it either (bus
    /// integration); the ports that were there get it, and the new port gets the frames that
    /// start after it joined (stepped clock: deterministic).
    #[test]
    fn a_frame_in_progress_is_not_received_by_a_port_that_joins_meanwhile() {
        let clock = SimClock::stepped();
        // 125 kbit/s: 8 µs a bit, an 8-byte frame about 1 ms on the wire.
        let bus = MemBus::with_clock(125, clock.clone());
        let mut a = bus.attach();
        let mut there = bus.attach();
        clock.step_to(1_000).unwrap();
        a.send(&Frame::new(0x609, &[0x23, 0x10, 0x10, 1, b's', b'a', b'v', b'e']).unwrap())
            .unwrap();
        // 100 µs into the frame.
        clock.step_to(101_000).unwrap();
        let mut joined = bus.attach();
        clock.step_to(10_000_000).unwrap();
        joined.sync_bus();
        let got = there
            .try_recv()
            .unwrap()
            .expect("delivered at its end of frame");
        assert_eq!(got.frame.std_id(), Some(0x609));
        assert_eq!(joined.try_recv().unwrap(), None);
        // A frame that starts after the join reaches it.
        a.send(&f(0x100)).unwrap();
        clock.step_to(20_000_000).unwrap();
        joined.sync_bus();
        assert_eq!(joined.try_recv().unwrap().unwrap().frame, f(0x100));
        assert_eq!(there.try_recv().unwrap().unwrap().frame, f(0x100));
    }

    /// A frame submitted at the time the bus already reached (between two steps of a stepped
    /// clock, an untimed member's frame is stamped with the step's time) starts when the bus
    /// is next run, even to that same time. Before, the pump skipped it (nothing to do up to
    /// the time reached) while the driver thread found it due and looked again at once:
    /// 100 % of a core until the next step.
    #[test]
    fn a_frame_at_the_time_reached_leaves_nothing_due_for_the_driver() {
        let clock = SimClock::stepped();
        let bus = MemBus::with_clock(1000, clock.clone());
        let mut a = bus.attach();
        let mut b = bus.attach();
        clock.step_to(1_000_000).unwrap();
        a.sync_bus();
        a.send(&f(0x123)).unwrap();
        a.sync_bus();
        assert!(
            !bus.core.due_by_reached(),
            "an event at the time reached is left for the driver thread"
        );
        // It was started, not delivered early: it ends after its bits, at the next step.
        assert!(b.try_recv().unwrap().is_none());
        clock.step_to(2_000_000).unwrap();
        b.sync_bus();
        let rx = b
            .try_recv()
            .unwrap()
            .expect("delivered at its end of frame");
        let end = clock.nanos_of(rx.timestamp).unwrap();
        let bits = u64::from(crate::bus::bits::frame_length(&rx.frame).total);
        assert!(end > 1_000_000 && end <= 1_000_000 + bits * 1_000, "{end}");
    }

    /// Two timed participants on one bus, one of them behind (stopped): the bus waits for it,
    /// and the one on time goes on producing frames at its own times. They join its transmit
    /// queue when the bus reaches their times, so none is lost and each goes out at its time
    /// once the other catches up. Before, they were queued at once while the bus stood still:
    /// the 64-frame queue overflowed and a runtime on time sent EMCY 0x8110 for another
    /// runtime's stall (two runtimes on a `mem://` bus, one stopped 200 ms: 681 TPDOs lost).
    #[test]
    fn a_participant_ahead_of_the_bus_loses_nothing_while_another_is_behind() {
        let clock = SimClock::stepped();
        let bus = MemBus::with_clock(1000, clock.clone());
        let mut listener = bus.attach();
        let mut behind = bus.attach();
        let held = behind.join_clock().unwrap();
        let mut ahead = bus.attach();
        let h = ahead.join_clock().unwrap();
        clock.step_to(200_000_000).unwrap();
        // 150 frames, 1 ms apart, while the other stands at 0.
        for k in 1..=150u64 {
            h.set(k * 1_000_000);
            ahead.send(&f(0x181)).unwrap();
        }
        listener.sync_bus();
        assert!(listener.try_recv().unwrap().is_none(), "the bus waits");
        let c = ahead.bus_stats().unwrap().controller.unwrap();
        assert_eq!(c.lost_overflow, 0, "{c:?}");
        // The one behind leaves (it would take each frame delivered to it): each goes out at
        // its own time.
        drop(held);
        h.set(u64::MAX);
        listener.sync_bus();
        let mut ends = Vec::new();
        while let Some(rx) = listener.try_recv().unwrap() {
            ends.push(clock.nanos_of(rx.timestamp).unwrap());
        }
        assert_eq!(ends.len(), 150);
        let bits = u64::from(crate::bus::bits::frame_length(&f(0x181)).total)
            - u64::from(crate::bus::bits::INTERMISSION_BITS);
        for (k, end) in ends.iter().enumerate() {
            assert_eq!(end - bits * 1_000, (k as u64 + 1) * 1_000_000, "frame {k}");
        }
        assert_eq!(
            ahead.bus_stats().unwrap().controller.unwrap().lost_overflow,
            0
        );
        assert!(!bus.core.due_by_reached());
    }

    /// Issue 36 (review): the same for an untimed member (a hub TCP client such as
    /// python-canopen, a bridge, a tool). Its frames are stamped with the wall time (the
    /// limit) it sent them at, ahead of a bus held by a timed participant that is behind;
    /// they are kept for their stamps as a timed participant's are, so none is lost and each
    /// goes out at its own time once the held one moves. Before, they went straight into its
    /// 64-frame transmit queue while the bus stood still: 86 of these 150 lost (a hub client
    /// was sent TX-overflow reports) though the bus was never overloaded.
    #[test]
    fn an_untimed_member_ahead_of_the_bus_loses_nothing_while_a_participant_is_behind() {
        let clock = SimClock::stepped();
        let bus = MemBus::with_clock(1000, clock.clone());
        let mut listener = bus.attach();
        let mut behind = bus.attach();
        let held = behind.join_clock().unwrap();
        assert_eq!(held.at(), 0);
        let mut untimed = bus.attach();
        // 150 frames over 150 ms of limit (wall) time, one per ms, while the bus is held at 0.
        for k in 1..=150u64 {
            clock.step_to(k * 1_000_000).unwrap();
            untimed.send(&f(0x601)).unwrap();
        }
        listener.sync_bus();
        assert!(listener.try_recv().unwrap().is_none(), "the bus waits");
        let c = untimed.bus_stats().unwrap().controller.unwrap();
        assert_eq!(c.lost_overflow, 0, "{c:?}");
        // The held participant moves on, and leaves (it would take each frame delivered to it).
        held.set(u64::MAX);
        drop(held);
        clock.step_to(200_000_000).unwrap();
        listener.sync_bus();
        let mut ends = Vec::new();
        while let Some(rx) = listener.try_recv().unwrap() {
            ends.push(clock.nanos_of(rx.timestamp).unwrap());
        }
        assert_eq!(ends.len(), 150);
        let bits = u64::from(crate::bus::bits::frame_length(&f(0x601)).total)
            - u64::from(crate::bus::bits::INTERMISSION_BITS);
        for (k, end) in ends.iter().enumerate() {
            assert_eq!(end - bits * 1_000, (k as u64 + 1) * 1_000_000, "frame {k}");
        }
        let c = untimed.bus_stats().unwrap().controller.unwrap();
        assert_eq!((c.sent, c.lost_overflow), (150, 0), "{c:?}");
        assert!(!bus.core.due_by_reached());
    }

    /// A tool that sends one frame and exits while the bus is held (a timed participant
    /// behind): its kept frame still goes out once the bus gets there, as the frames it had
    /// queued do. It was dropped with the member, so `canpos lss switch-global config` was
    /// lost beside CPU hogs (interop `test_tmi_at_20k…`).
    #[test]
    fn a_member_that_leaves_while_the_bus_is_held_still_sends_its_kept_frame() {
        let clock = SimClock::stepped();
        let bus = MemBus::with_clock(1000, clock.clone());
        let mut listener = bus.attach();
        let mut behind = bus.attach();
        let held = behind.join_clock().unwrap();
        let mut tool = bus.attach();
        clock.step_to(5_000_000).unwrap();
        tool.send(&f(0x7E5)).unwrap();
        drop(tool);
        listener.sync_bus();
        assert!(listener.try_recv().unwrap().is_none(), "the bus waits");
        held.set(u64::MAX);
        drop(held);
        clock.step_to(10_000_000).unwrap();
        listener.sync_bus();
        let rx = listener.try_recv().unwrap().expect("the tool's frame");
        assert_eq!(rx.frame, f(0x7E5));
    }

    #[test]
    fn disturbances_out_of_range_change_nothing() {
        let bus = MemBus::new();
        let p = bus.attach();
        assert!(bus
            .disturb(Disturbance::CorruptedFrames {
                per_million: 2_000_000
            })
            .is_err());
        assert!(p
            .disturb(Disturbance::StuckDominant {
                duration: Duration::from_secs(61)
            })
            .is_err());
        assert!(MemBus::instant()
            .disturb(Disturbance::CorruptedFrames { per_million: 1 })
            .is_err());
        assert_eq!(bus.stats().unwrap().error_frames, 0);
    }
}
