//! In-process CAN bus: any number of [`MemPort`]s, each frame broadcast to all other ports.
//!
//! A bus is paced by default ([`Pacing`]): every frame goes through the bus [`Timeline`](crate::bus::Timeline)
//! (crate::bus): it waits for the bus, wins or loses arbitration, takes its bit time, and
//! reaches the other ports at its end-of-frame time, stamped with it. One driver thread per
//! bus delivers frames at those times. [`Pacing::Instant`] keeps the old behaviour (every
//! frame delivered at once, without limit) for benchmarks.
//!
//! Each port has a bounded receive queue; a port whose owner does not read loses frames (counted
//! by [`MemPort::dropped`]) instead of slowing the sender or the other ports. The socketcand hub
//! uses the same bus for each of its channels, so in-process hub participants are `MemPort`s too.
//!
//! The bus's shared state and its driver thread are in `bus_core.rs`; this file holds the
//! handles ([`MemBus`], [`MemPort`]).

use std::collections::HashMap;
use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

use canpos_stack::Frame;
use crossbeam_channel::{Receiver, Sender};

use crate::bus::{MemberStats, Pacing};
use crate::can::{BusState, BusStats, Disturbance, ErrorFrame, RxFrame, Transport};
use crate::clock::{Horizon, SimClock};

mod bus_core;

use bus_core::lock;
pub(crate) use bus_core::{BusCore, Sink};
pub use bus_core::{LatenessHistogram, DEFAULT_QUEUE_LEN};

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
mod tests;
