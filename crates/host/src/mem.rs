//! In-process CAN bus: any number of [`MemPort`]s, each frame broadcast to all other ports.
//!
//! Each port has a bounded receive queue; a port whose owner does not read loses frames (counted
//! by [`MemPort::dropped`]) instead of slowing the sender or the other ports. The socketcand hub
//! uses the same bus for each of its channels, so in-process hub participants are `MemPort`s too.

use std::collections::HashMap;
use std::io;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock};

use canpos_core::Frame;
use crossbeam_channel::{Receiver, Sender, TrySendError};

use crate::socketcand::hub::Wake;
use crate::transport::{RxFrame, Transport};

/// Default receive queue length of a port, in frames (about 0.5 s of a saturated 1 Mbit/s bus).
pub const DEFAULT_QUEUE_LEN: usize = 4096;

/// Where a bus member's frames go.
pub(crate) enum Sink {
    /// An in-process port.
    Local(Sender<RxFrame>),
    /// A socketcand TCP client of the hub: its queue, and how to tell the hub's I/O thread.
    Remote(Sender<RxFrame>, Arc<Wake>),
}

struct Member {
    id: u64,
    sink: Sink,
    dropped: Arc<AtomicU64>,
}

/// The shared state of one virtual bus.
pub(crate) struct BusCore {
    members: RwLock<Vec<Member>>,
    next_id: AtomicU64,
    /// kbit/s; 0 = not modelled.
    bitrate: AtomicU32,
    frames: AtomicU64,
    /// Shared with the hub when the bus is a hub channel, so totals survive the channel.
    dropped: Arc<AtomicU64>,
}

impl BusCore {
    pub(crate) fn new() -> Self {
        Self::with_drop_counter(Arc::new(AtomicU64::new(0)))
    }

    /// A bus whose drops are counted in `dropped` (shared with other buses).
    pub(crate) fn with_drop_counter(dropped: Arc<AtomicU64>) -> Self {
        BusCore {
            members: RwLock::new(Vec::new()),
            next_id: AtomicU64::new(1),
            bitrate: AtomicU32::new(0),
            frames: AtomicU64::new(0),
            dropped,
        }
    }

    /// Adds a member; returns its id and its drop counter.
    pub(crate) fn join(&self, sink: Sink) -> (u64, Arc<AtomicU64>) {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let dropped = Arc::new(AtomicU64::new(0));
        let mut m = self.members.write().unwrap_or_else(|e| e.into_inner());
        m.push(Member {
            id,
            sink,
            dropped: dropped.clone(),
        });
        (id, dropped)
    }

    pub(crate) fn leave(&self, id: u64) {
        let mut m = self.members.write().unwrap_or_else(|e| e.into_inner());
        m.retain(|m| m.id != id);
    }

    pub(crate) fn member_count(&self) -> usize {
        self.members.read().unwrap_or_else(|e| e.into_inner()).len()
    }

    /// Delivers `rx` to every member but `from`. Never blocks: a full queue drops the frame for
    /// that member only.
    pub(crate) fn broadcast(&self, from: u64, rx: RxFrame) {
        self.frames.fetch_add(1, Ordering::Relaxed);
        let members = self.members.read().unwrap_or_else(|e| e.into_inner());
        for m in members.iter().filter(|m| m.id != from) {
            let full = match &m.sink {
                Sink::Local(tx) => matches!(tx.try_send(rx), Err(TrySendError::Full(_))),
                // Unbounded underneath, capped here: memory grows with the backlog, not with
                // the number of clients (a bounded channel allocates its capacity up front).
                Sink::Remote(tx, wake) if tx.len() >= wake.cap => true,
                Sink::Remote(tx, wake) => {
                    if tx.send(rx).is_ok() {
                        wake.notify();
                    }
                    false
                }
            };
            // A disconnected sink belongs to a member that is leaving; not a drop.
            if full {
                m.dropped.fetch_add(1, Ordering::Relaxed);
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
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
    /// A new, empty bus with no bit rate (every node talks).
    pub fn new() -> Self {
        MemBus {
            core: Arc::new(BusCore::new()),
            queue_len: DEFAULT_QUEUE_LEN,
        }
    }

    pub(crate) fn from_core(core: Arc<BusCore>, queue_len: usize) -> Self {
        MemBus { core, queue_len }
    }

    /// The process-wide bus called `name` (what `mem://NAME` opens), created on first use.
    pub fn named(name: &str) -> MemBus {
        static REGISTRY: OnceLock<Mutex<HashMap<String, MemBus>>> = OnceLock::new();
        let mut reg = REGISTRY
            .get_or_init(Default::default)
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        reg.entry(name.to_string()).or_default().clone()
    }

    /// Sets the receive queue length of ports attached from now on through this handle.
    pub fn with_queue_len(mut self, len: usize) -> Self {
        self.queue_len = len.max(1);
        self
    }

    /// Sets the bus bit rate in kbit/s (`None`: not modelled). Ports see the change at once.
    pub fn set_bitrate(&self, kbit: Option<u32>) {
        self.core
            .bitrate
            .store(kbit.unwrap_or(0), Ordering::Relaxed);
    }

    /// The bus bit rate in kbit/s, if set.
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
        }
    }

    /// Number of attached ports (and, for a hub channel, TCP clients).
    pub fn port_count(&self) -> usize {
        self.core.member_count()
    }

    /// Frames sent on the bus so far.
    pub fn frames(&self) -> u64 {
        self.core.frames()
    }

    /// Deliveries dropped so far because some port's queue was full.
    pub fn dropped(&self) -> u64 {
        self.core.dropped()
    }
}

/// One participant of a [`MemBus`] (or of a hub channel). Dropping it leaves the bus.
pub struct MemPort {
    core: Arc<BusCore>,
    id: u64,
    rx: Receiver<RxFrame>,
    dropped: Arc<AtomicU64>,
}

impl MemPort {
    /// Frames this port lost because its queue was full.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Sends a frame with an explicit timestamp (e.g. replaying a log or simulated time).
    pub fn send_at(&self, rx: RxFrame) {
        self.core.broadcast(self.id, rx);
    }
}

impl Drop for MemPort {
    fn drop(&mut self) {
        self.core.leave(self.id);
    }
}

impl Transport for MemPort {
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        self.core.broadcast(self.id, RxFrame::now(*frame));
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
        let bus = MemBus::new();
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
        let bus = MemBus::new().with_queue_len(4);
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
}
