//! The simulation clock: one time for a bus and the runtimes on it (docs/CLOCK.md).
//!
//! A [`SimClock`] has an epoch (a monotonic [`std::time::Instant`] and the [`SystemTime`] taken
//! with it, so that simulation time maps to wall time) and a **driver** that sets its *limit*:
//!
//! - [`Driver::Wall`]: the limit is the wall time elapsed since the epoch (a twin on a desk, in
//!   CI, beside real tools);
//! - [`Driver::Stepped`]: the limit is a target that a co-simulation master moves on
//!   ([`SimClock::step_to`]: FMI 3 `doStep`, SIL Kit time synchronisation); no wall clock at all.
//!
//! Participants that produce frames at their own times (a [`crate::Runtime`]) hold a
//! [`Horizon`]: "I will submit nothing stamped before H". The clock's [`now`](SimClock::now) is
//! the smallest of the limit and every live horizon, so a bus that runs to `now` never runs
//! past a participant that is still behind (it was descheduled, it is catching up): its frames
//! enter the bus at their own times, and a host stall delays delivery instead of overflowing
//! queues. A horizon also counts the frames a bus delivered to its participant and that it has
//! not taken yet ([`Horizon::taken`]): the bus stops at each such frame, so the participant's
//! answer is stamped at the frame's own time.
//!
//! A participant that stops for good (a deadlocked thread) must not freeze the bus for everyone
//! else: with the wall driver, a horizon more than [`STALL_BOUND`] behind the limit stops
//! holding (with a warning) until it catches up.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, SystemTime};

use crossbeam_channel::{Receiver, Sender};

/// Simulation time: nanoseconds since the clock's epoch.
pub type Nanos = u64;

/// How far behind the wall-clock limit a horizon may fall before it stops holding the clock:
/// a host stall shorter than this is absorbed (frames keep their times, delivery is late); a
/// participant stopped longer (suspended, deadlocked) no longer holds the bus for the others,
/// and a runtime that comes back from it skips ahead to the wall clock (docs/CLOCK.md).
pub const STALL_BOUND: Duration = Duration::from_secs(2);

/// Frames delivered and not yet taken that a horizon remembers; more (a participant that never
/// reads) hold at the oldest remembered one.
const PENDING_CAP: usize = 65_536;

/// What moves a [`SimClock`]'s limit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Driver {
    /// The limit is the wall time elapsed since the epoch.
    Wall,
    /// The limit is a target set by [`SimClock::step_to`] (co-simulation).
    Stepped,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

struct Inner {
    epoch: std::time::Instant,
    epoch_wall: SystemTime,
    driver: Driver,
    /// The stepped driver's limit.
    target: AtomicU64,
    stall_bound: Nanos,
    slots: Mutex<Vec<Weak<Slot>>>,
    /// Told when the limit moves or a horizon does while someone waits for it.
    listeners: Mutex<Vec<Sender<()>>>,
    /// Listeners waiting for a horizon (see [`SimClock::waiting`]).
    waiting: AtomicUsize,
}

/// One participant's horizon.
pub(crate) struct Slot {
    name: String,
    at: AtomicU64,
    /// Stamps of frames delivered to the participant and not taken yet, oldest first.
    pending: Mutex<VecDeque<Nanos>>,
    stale: AtomicBool,
}

impl Slot {
    fn effective(&self) -> Nanos {
        let at = self.at.load(Ordering::SeqCst);
        lock(&self.pending).front().map_or(at, |&p| p.min(at))
    }

    /// A frame stamped `t` was put in the participant's receive queue.
    pub(crate) fn delivered(&self, t: Nanos) {
        let mut p = lock(&self.pending);
        if p.len() < PENDING_CAP {
            p.push_back(t);
        }
    }

    /// The participant's current horizon (the stamp of what it sends now).
    pub(crate) fn at(&self) -> Nanos {
        self.at.load(Ordering::SeqCst)
    }
}

/// A simulation clock shared by a bus and its participants; cloning gives another handle.
#[derive(Clone)]
pub struct SimClock {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for SimClock {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimClock")
            .field("driver", &self.inner.driver)
            .field("limit", &self.limit())
            .finish()
    }
}

impl SimClock {
    fn with(driver: Driver, stall_bound: Duration) -> SimClock {
        SimClock {
            inner: Arc::new(Inner {
                epoch: std::time::Instant::now(),
                epoch_wall: SystemTime::now(),
                driver,
                target: AtomicU64::new(0),
                stall_bound: u64::try_from(stall_bound.as_nanos()).unwrap_or(u64::MAX),
                slots: Mutex::new(Vec::new()),
                listeners: Mutex::new(Vec::new()),
                waiting: AtomicUsize::new(0),
            }),
        }
    }

    /// A clock driven by the wall clock, its epoch now.
    pub fn wall() -> SimClock {
        Self::with(Driver::Wall, STALL_BOUND)
    }

    /// A wall clock whose horizons stop holding after `bound` instead of [`STALL_BOUND`].
    pub fn wall_with_stall_bound(bound: Duration) -> SimClock {
        Self::with(Driver::Wall, bound)
    }

    /// A clock that stands at 0 until [`SimClock::step_to`] moves it (co-simulation).
    pub fn stepped() -> SimClock {
        Self::with(Driver::Stepped, STALL_BOUND)
    }

    /// How far behind the limit a horizon may fall before it stops holding ([`STALL_BOUND`]).
    pub fn stall_bound(&self) -> Nanos {
        self.inner.stall_bound
    }

    /// Its driver.
    pub fn driver(&self) -> Driver {
        self.inner.driver
    }

    /// Whether `self` and `other` are the same clock.
    pub fn same(&self, other: &SimClock) -> bool {
        Arc::ptr_eq(&self.inner, &other.inner)
    }

    /// The wall time elapsed since the epoch, ns.
    pub fn wall_elapsed(&self) -> Nanos {
        u64::try_from(self.inner.epoch.elapsed().as_nanos()).unwrap_or(u64::MAX)
    }

    /// The limit: how far the driver lets simulation time go (wall elapsed, or the target).
    pub fn limit(&self) -> Nanos {
        match self.inner.driver {
            Driver::Wall => self.wall_elapsed(),
            Driver::Stepped => self.inner.target.load(Ordering::SeqCst),
        }
    }

    /// Moves a stepped clock's limit on to `t` (never back); `Err` on a wall clock.
    pub fn step_to(&self, t: Nanos) -> Result<(), String> {
        if self.inner.driver != Driver::Stepped {
            return Err("a wall-clock driven clock cannot be stepped".into());
        }
        self.inner.target.fetch_max(t, Ordering::SeqCst);
        self.notify();
        Ok(())
    }

    /// Simulation time: the smallest of the limit and every participant's horizon. A bus runs
    /// to this time and no further. It can step back (a participant lowered its horizon to a
    /// frame the bus delivered to it, a new participant joined): never below what a bus already
    /// ran to, which is all a bus needs (it never runs backwards).
    pub fn now(&self) -> Nanos {
        let mut slots = lock(&self.inner.slots);
        self.now_locked(&mut slots)
    }

    fn now_locked(&self, slots: &mut Vec<Weak<Slot>>) -> Nanos {
        let limit = self.limit();
        let mut t = limit;
        let bound = self.inner.stall_bound;
        slots.retain(|w| w.strong_count() > 0);
        for s in slots.iter().filter_map(Weak::upgrade) {
            let h = s.effective();
            if self.inner.driver == Driver::Wall && h.saturating_add(bound) < limit {
                if !s.stale.swap(true, Ordering::Relaxed) {
                    tracing::warn!(participant = %s.name, behind_ms = (limit - h) / 1_000_000,
                        bound_ms = bound / 1_000_000,
                        "a clock participant fell behind the stall bound: the bus no longer waits for it");
                }
                continue;
            }
            if s.stale.swap(false, Ordering::Relaxed) {
                tracing::info!(participant = %s.name, "clock participant caught up: the bus waits for it again");
            }
            t = t.min(h);
        }
        t
    }

    /// The wall-clock instant of simulation time `t` (what a wall-driven participant sleeps
    /// until).
    pub fn instant_of(&self, t: Nanos) -> std::time::Instant {
        self.inner.epoch + Duration::from_nanos(t)
    }

    /// The wall-clock time of simulation time `t` (frame timestamps).
    pub fn system_time_of(&self, t: Nanos) -> SystemTime {
        self.inner.epoch_wall + Duration::from_nanos(t)
    }

    /// Simulation time of a wall-clock timestamp this clock gave out (`None` before the epoch).
    pub fn nanos_of(&self, t: SystemTime) -> Option<Nanos> {
        t.duration_since(self.inner.epoch_wall)
            .ok()
            .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
    }

    /// Joins as a timed participant, with the horizon at the current time.
    pub fn participant(&self, name: &str) -> Horizon {
        let slot = Arc::new(Slot {
            name: name.to_string(),
            at: AtomicU64::new(0),
            pending: Mutex::new(VecDeque::new()),
            stale: AtomicBool::new(false),
        });
        // Under the slots' lock, so no `now()` runs between reading the time and holding it:
        // a new participant starts at the clock's time and never takes it back.
        let mut slots = lock(&self.inner.slots);
        let start = self.now_locked(&mut slots);
        slot.at.store(start, Ordering::SeqCst);
        slots.push(Arc::downgrade(&slot));
        drop(slots);
        Horizon {
            slot,
            clock: self.clone(),
        }
    }

    /// A queue that is told (at most one pending token) when the limit moves, and when a
    /// horizon moves while [`SimClock::waiting`] is on: how a bus driver learns it may go on.
    pub fn subscribe(&self) -> Receiver<()> {
        let (tx, rx) = crossbeam_channel::bounded(1);
        lock(&self.inner.listeners).push(tx);
        rx
    }

    /// Registers `tx` as a listener (see [`SimClock::subscribe`]).
    pub(crate) fn subscribe_with(&self, tx: Sender<()>) {
        lock(&self.inner.listeners).push(tx);
    }

    /// Tells the clock that a listener is (`true`) or no longer (`false`) waiting for a
    /// horizon; horizons only notify while someone waits.
    pub fn waiting(&self, on: bool) {
        if on {
            self.inner.waiting.fetch_add(1, Ordering::SeqCst);
        } else {
            self.inner.waiting.fetch_sub(1, Ordering::SeqCst);
        }
    }

    fn notify(&self) {
        lock(&self.inner.listeners).retain(|tx| {
            !matches!(
                tx.try_send(()),
                Err(crossbeam_channel::TrySendError::Disconnected(_))
            )
        });
    }

    fn horizon_moved(&self) {
        if self.inner.waiting.load(Ordering::SeqCst) > 0 {
            self.notify();
        }
    }
}

/// A timed participant's promise to its [`SimClock`]: nothing it submits is stamped before
/// [`Horizon::at`]. The clock does not run past it; dropping the handle withdraws it.
pub struct Horizon {
    slot: Arc<Slot>,
    clock: SimClock,
}

impl std::fmt::Debug for Horizon {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Horizon")
            .field("name", &self.slot.name)
            .field("at", &self.at())
            .finish()
    }
}

impl Horizon {
    /// Its clock.
    pub fn clock(&self) -> &SimClock {
        &self.clock
    }

    /// The horizon, ns.
    pub fn at(&self) -> Nanos {
        self.slot.at()
    }

    /// Sets the horizon to `t`: the participant is at `t` (what it sends now is stamped `t`)
    /// and submits nothing earlier. It may be lowered to the time of a frame the bus delivered
    /// to it (the bus waits there); a bus stamps nothing earlier than the time it reached.
    pub fn set(&self, t: Nanos) {
        let old = self.slot.at.swap(t, Ordering::SeqCst);
        if t > old {
            self.clock.horizon_moved();
        }
    }

    /// The participant took the frames delivered to it up to stamp `t`: they hold the clock no
    /// longer.
    pub fn taken(&self, t: Nanos) {
        let mut p = lock(&self.slot.pending);
        let before = p.len();
        while p.front().is_some_and(|&s| s <= t) {
            p.pop_front();
        }
        let moved = p.len() != before;
        drop(p);
        if moved {
            self.clock.horizon_moved();
        }
    }

    /// Frames delivered and not yet taken.
    pub fn pending(&self) -> usize {
        lock(&self.slot.pending).len()
    }

    /// The slot, for a bus to stamp this participant's frames and count its deliveries.
    pub(crate) fn slot(&self) -> Weak<Slot> {
        Arc::downgrade(&self.slot)
    }
}

impl Drop for Horizon {
    fn drop(&mut self) {
        // The slot goes with the last strong reference (this one): `now()` forgets it; a bus
        // waiting for it must look again.
        self.clock.notify();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn now_is_the_smallest_horizon_and_never_goes_back() {
        let c = SimClock::stepped();
        assert_eq!(c.now(), 0);
        c.step_to(1_000).unwrap();
        assert_eq!(c.now(), 1_000);
        let a = c.participant("a");
        assert_eq!(a.at(), 1_000);
        c.step_to(5_000).unwrap();
        assert_eq!(c.now(), 1_000, "held by a");
        a.set(3_000);
        assert_eq!(c.now(), 3_000);
        let b = c.participant("b");
        assert_eq!(
            b.at(),
            3_000,
            "a new participant starts at the clock's time"
        );
        b.set(u64::MAX);
        a.set(4_000);
        assert_eq!(c.now(), 4_000);
        drop(a);
        assert_eq!(c.now(), 5_000, "a dropped horizon holds nothing");
        assert!(c.step_to(1).is_ok());
        assert_eq!(c.limit(), 5_000, "a step back is no step");
        assert!(SimClock::wall().step_to(1).is_err());
    }

    #[test]
    fn delivered_frames_hold_until_taken() {
        let c = SimClock::stepped();
        c.step_to(10_000).unwrap();
        let h = c.participant("rt");
        h.set(9_000);
        h.slot.delivered(2_000 + 7_000);
        h.slot.delivered(9_500);
        h.set(10_000);
        assert_eq!(c.now(), 9_000);
        h.taken(9_000);
        assert_eq!(c.now(), 9_500);
        h.taken(9_999);
        assert_eq!(c.now(), 10_000);
        assert_eq!(h.pending(), 0);
    }

    #[test]
    fn a_horizon_behind_the_stall_bound_stops_holding() {
        // A wall clock with a 1 ns bound: any horizon behind the wall clock is stale at once.
        let c = SimClock::wall_with_stall_bound(Duration::from_nanos(1));
        let h = c.participant("stuck");
        std::thread::sleep(Duration::from_millis(2));
        let now = c.now();
        assert!(now > h.at() + 1_000_000, "{now} vs {}", h.at());
        // Caught up: it holds again.
        let t = c.wall_elapsed() + 1_000_000_000;
        h.set(t);
        assert!(c.now() < t);
    }

    #[test]
    fn wall_and_stepped_map_to_wall_time() {
        let c = SimClock::wall();
        let t = c.system_time_of(1_500);
        assert_eq!(c.nanos_of(t), Some(1_500));
        assert_eq!(c.driver(), Driver::Wall);
        assert_eq!(SimClock::stepped().driver(), Driver::Stepped);
    }
}
