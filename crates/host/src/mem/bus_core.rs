//! The shared state of one in-process bus ([`BusCore`]): its members and where their frames go
//! ([`Sink`]), the pacing through the bus [`Timeline`], error frames and disturbances, and the
//! driver thread that delivers frames at their end-of-frame times. [`MemBus`](super::MemBus)
//! and [`MemPort`](super::MemPort) are its handles; the socketcand hub attaches its TCP clients
//! here as remote members.

use std::sync::atomic::{AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, RwLock, Weak};

use canpos_stack::Frame;
use crossbeam_channel::{Receiver, Sender, TrySendError};

use crate::bus::{BusEvent, MemberId, Nanos, Pacing, Timeline, DEFAULT_TX_DEPTH};
use crate::can::{BusStats, Disturbance, ErrorFrame, RxFrame};
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
    /// A transmit-only controller (see [`Transport::controller`](crate::can::Transport::controller)).
    None,
}

pub(super) struct Member {
    pub(super) id: u64,
    /// Ports of one group do not receive each other's frames (one process's nodes, which
    /// route among themselves).
    pub(super) group: u64,
    pub(super) sink: Sink,
    pub(super) dropped: Arc<AtomicU64>,
    /// Its controller on the timeline (paced buses).
    pub(super) ctl: Option<MemberId>,
    /// A timed participant's horizon (its group's, docs/CLOCK.md): its frames are stamped
    /// with it, and a frame delivered to it holds the clock until taken.
    pub(super) horizon: Option<Weak<Slot>>,
    /// The standard identifiers whose delivery holds the clock (remote frames always do);
    /// `None`: every frame. From [`Transport::set_rx_filter`](crate::can::Transport::set_rx_filter): what its nodes may answer.
    pub(super) hold_ids: Option<Vec<u16>>,
    /// The bus time it joined at (paced buses; 0 on an instant bus): a frame that started on
    /// the bus before is not received by it, however late it is handed out.
    pub(super) joined: Nanos,
}

/// Delivery lateness of a paced bus against its timeline: 1 µs buckets up to 10 ms.
#[derive(Clone, Debug)]
pub struct LatenessHistogram {
    pub(super) buckets: Vec<u64>,
    pub(super) count: u64,
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
    pub(super) fn record(&mut self, late: Nanos) {
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

pub(super) struct PaceState {
    pub(super) timeline: Timeline,
    pub(super) events: Vec<BusEvent>,
    pub(super) lateness: LatenessHistogram,
    /// How far the timeline ran: nothing is submitted earlier (simulation time, ns).
    pub(super) reached: Nanos,
    /// Frames stamped after `reached` (their sender is ahead of the bus, which waits for a
    /// timed participant that is behind), of any member, timed or not, by (stamp, order of
    /// submission): they join their controller's transmit queue when the timeline reaches
    /// their stamp, not before. Queued at once, they filled the 64-frame queue while the bus
    /// stood still for the other participant: a runtime that was on time raised EMCY 0x8110
    /// for another's stall, and a hub client (python-canopen, a bridge) was told of a TX
    /// overflow on a bus that was never overloaded. At most [`FUTURE_CAP`]; more are queued
    /// at once.
    pub(super) future: std::collections::BTreeMap<(Nanos, u64), (MemberId, Frame)>,
    /// Submission counter for `future`'s order.
    pub(super) future_seq: u64,
}

/// Frames a paced bus keeps for their stamps at most (all members together): 2 s (the stall
/// bound) of a full 1 Mbit/s bus is about 17,000 frames.
pub(super) const FUTURE_CAP: usize = 65_536;

impl PaceState {
    /// The timeline's next event, or the moment before a kept frame's stamp (when it joins
    /// its queue, so that it takes part in an arbitration at its stamp).
    pub(super) fn next_due(&self) -> Option<Nanos> {
        let kept = self.future.keys().next().map(|&(t, _)| t.saturating_sub(1));
        match (self.timeline.next_event(), kept) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }
}

/// The timeline of a paced bus and the clock it runs on.
pub(super) struct Pacer {
    pub(super) state: Mutex<PaceState>,
    /// The simulation clock (docs/CLOCK.md): the bus runs to its `now()`, never past a timed
    /// participant's horizon.
    pub(super) clock: SimClock,
    pub(super) kick: Sender<()>,
    /// Receiving members with a horizon: while there are any, the bus runs event by event and
    /// stops at each frame delivered to one of them.
    pub(super) timed: AtomicUsize,
}

impl Pacer {
    pub(super) fn now(&self) -> Nanos {
        self.clock.now()
    }
}

/// The shared state of one virtual bus.
pub(crate) struct BusCore {
    pub(super) members: RwLock<Vec<Member>>,
    pub(super) next_id: AtomicU64,
    /// kbit/s; 0 = not declared (nodes of any rate talk).
    pub(super) bitrate: AtomicU32,
    pub(super) frames: AtomicU64,
    /// Shared with the hub when the bus is a hub channel, so totals survive the channel.
    pub(super) dropped: Arc<AtomicU64>,
    /// Frames lost in transmit queues (full or bus-off), all members.
    pub(super) tx_lost: AtomicU64,
    pub(super) pacer: Option<Pacer>,
    /// Listeners of error frames (a bridge, a recorder); each a bounded queue.
    pub(super) error_listeners: Mutex<Vec<Sender<ErrorFrame>>>,
    /// Called with every error frame on the driver thread (a hub channel: its TCP clients).
    pub(super) error_hook: Mutex<Option<ErrorHook>>,
}

/// See [`BusCore::set_error_hook`].
pub(crate) type ErrorHook = Box<dyn Fn(&ErrorFrame) + Send>;

pub(super) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
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

    pub(super) fn join_group(&self, sink: Sink, group: Option<u64>) -> (u64, Arc<AtomicU64>) {
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
    pub(super) fn ctl_and_time(&self, id: u64) -> Option<(MemberId, Option<Nanos>)> {
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

    pub(super) fn ctl_of(&self, id: u64) -> Option<MemberId> {
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
    pub(super) fn deliver(
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
    /// there until that participant took it (and answered at its time). Never past the
    /// clock's `now()` read under the lock: `target` was read before it (issue 31).
    pub(super) fn pump(&self, p: &Pacer, st: &mut PaceState, target: Nanos) {
        // A caller reads `now()` before it waits for the lock; meanwhile another thread may have
        // delivered a frame to a timed participant here, which holds the clock at its end of
        // frame. Run to the stale target, the bus went past that frame before the participant
        // answered it, and the answer left late, as often as the driver thread lost that race
        // (a co-simulation was not deterministic). Deliveries happen only under this lock, so
        // `now()` read here sees every hold.
        let target = target.min(p.now());
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
    pub(super) fn due_by_reached(&self) -> bool {
        let p = self.pacer.as_ref().expect("paced");
        let st = lock(&p.state);
        st.next_due().is_some_and(|n| n <= st.reached)
    }

    /// Hands what the timeline produced to the members; true when a timed participant received
    /// a frame (it holds the clock).
    pub(super) fn dispatch(&self, p: &Pacer, events: &mut Vec<BusEvent>) -> bool {
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

    pub(super) fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    pub(super) fn bitrate(&self) -> Option<u32> {
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
