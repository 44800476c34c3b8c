//! The bus-simulation FMU's core, independent of the C ABI: canpos's bus timeline as N
//! FMI-LS-BUS 1.0 CAN bus terminals (`canpos_host::bus::ports`, docs/FMU.md "The
//! bus-simulation FMU").
//!
//! A node's `Rx_Data` operations are taken at the co-simulation time reached
//! ([`BusSim::receive`]); [`BusSim::step`] runs the bus on and writes what each node gets into
//! its `Tx_Data` buffer: the other nodes' frames as CAN Transmit operations at their end-of-frame
//! times, Confirm to the sender, Arbitration Lost to a node that asked to be told
//! (`DISCARD_AND_NOTIFY`), Bus Error to every node with `Is Sender` and the primary error flag
//! set once. The time is the co-simulation's, never the wall clock.

use canpos_host::bus::ports::{
    BusErrorKind, BusState, PortEvent, PortEventKind, Ports, SubmitError,
};
use canpos_host::bus::Nanos;
use canpos_stack::Frame;

use crate::lsbus::{self, ArbitrationLostBehavior, BusErrorCode, CanStatus, Config, Op, TxBuffer};

/// Bound of one node's `Tx_Data` (bytes): the terminal's `maxSize`, 128 classic CAN frames.
/// A step without early return that collects more for one node loses the rest, counted and
/// logged; with early return one end of frame brings at most a few operations.
pub const TX_CAP: usize = crate::sensor::BUS_DATA_MAX;

/// Most log lines kept between two [`BusSim::take_log`] calls (the rest are counted).
const LOG_CAP: usize = 64;

/// A co-simulation time in seconds as bus time in ns; `None` for a negative, non-finite or
/// too large time.
pub fn nanos(t: f64) -> Option<Nanos> {
    (0.0..1.8e10)
        .contains(&t)
        .then(|| (t * 1e9).round() as Nanos)
}

/// The bus with a `Tx_Data` buffer per node.
#[derive(Debug)]
pub struct BusSim {
    ports: Ports,
    tx: Vec<TxBuffer>,
    events: Vec<PortEvent>,
    /// Operations that did not fit a node's `Tx_Data`.
    lost_ops: u64,
    /// Frames refused by a full transmit queue (all nodes).
    queue_full: u64,
    log: Vec<String>,
    log_dropped: u64,
}

impl BusSim {
    /// A bus at `kbps` kbit/s (CiA 301) with `nodes` terminals (1 … 128).
    pub fn new(nodes: usize, kbps: u32) -> Result<BusSim, String> {
        Ok(BusSim {
            ports: Ports::new(kbps, nodes)?,
            tx: (0..nodes).map(|_| TxBuffer::new(TX_CAP)).collect(),
            events: Vec::new(),
            lost_ops: 0,
            queue_full: 0,
            log: Vec::new(),
            log_dropped: 0,
        })
    }

    /// Number of node terminals.
    pub fn nodes(&self) -> usize {
        self.ports.len()
    }

    /// The bus time reached, ns.
    pub fn now(&self) -> Nanos {
        self.ports.reached()
    }

    /// The engine (counters, load).
    pub fn ports(&mut self) -> &mut Ports {
        &mut self.ports
    }

    /// Operations lost because a node's `Tx_Data` was full.
    pub fn lost_ops(&self) -> u64 {
        self.lost_ops
    }

    fn note(&mut self, line: String) {
        if self.log.len() < LOG_CAP {
            self.log.push(line);
        } else {
            self.log_dropped += 1;
        }
    }

    /// What happened that an importer should hear about (the glue logs it).
    pub fn take_log(&mut self) -> Vec<String> {
        let mut log = std::mem::take(&mut self.log);
        if self.log_dropped > 0 {
            log.push(format!("{} more messages not shown", self.log_dropped));
            self.log_dropped = 0;
        }
        log
    }

    /// Node `port`'s `Tx_Data`.
    pub fn tx(&self, port: usize) -> &[u8] {
        self.tx.get(port).map_or(&[], |b| b.bytes())
    }

    /// Whether node `port`'s `Tx_Clock` ticks (its `Tx_Data` holds operations).
    pub fn tx_ticks(&self, port: usize) -> bool {
        self.tx.get(port).is_some_and(|b| !b.is_empty())
    }

    /// Whether any `Tx_Clock` ticks.
    pub fn any_tx(&self) -> bool {
        self.tx.iter().any(|b| !b.is_empty())
    }

    /// The importer took the `Tx_Data` of this event.
    pub fn clear_tx(&mut self) {
        for b in &mut self.tx {
            b.clear();
        }
    }

    fn push(&mut self, port: usize, op: &Op<'_>) {
        if self.tx[port].push(op).is_err() {
            self.lost_ops += 1;
            if self.lost_ops == 1 || self.lost_ops.is_power_of_two() {
                self.note(format!(
                    "node {}'s Tx_Data is full ({TX_CAP} bytes): {} operations lost so far (step with early return, or shorter steps)",
                    port + 1,
                    self.lost_ops
                ));
            }
        }
    }

    /// Node `port` (0-based) handed in `buf` (its `Rx_Data`, its `Rx_Clock` ticked) at the time
    /// reached. A malformed buffer is refused whole: nothing of it is taken.
    pub fn receive(&mut self, port: usize, buf: &[u8]) -> Result<(), String> {
        if port >= self.ports.len() {
            return Err(format!("no node terminal {}", port + 1));
        }
        let ops = lsbus::parse(buf).map_err(|e| format!("node {}: {e}", port + 1))?;
        let now = self.now();
        // A node's frames of one buffer enter its queue a nanosecond apart, in order, as the
        // in-process bus takes a controller's burst (docs/BUS.md): on a free bus the first one
        // starts, as the frame its firmware handed over first would (a boot-up before the
        // EMCY queued with it); the nodes' first frames of one time still arbitrate together.
        let mut at = now;
        for op in ops {
            match op {
                Op::Transmit {
                    id,
                    ide,
                    rtr,
                    data,
                    dlc,
                } => {
                    let frame = if rtr {
                        Frame::remote(id, ide, dlc as u8)
                    } else {
                        Frame::with_id(id, ide, data)
                    };
                    // The codec checked identifier and length.
                    let Ok(frame) = frame else { continue };
                    let result = self.ports.submit(port, frame, at);
                    at += 1;
                    match result {
                        Ok(()) => {}
                        Err(SubmitError::QueueFull) => {
                            self.queue_full += 1;
                            if self.queue_full.is_power_of_two() {
                                self.note(format!(
                                    "node {}: transmit queue full, frame {id:#x} lost ({} frames lost to full queues so far)",
                                    port + 1,
                                    self.queue_full
                                ));
                            }
                        }
                        Err(SubmitError::BusOff) => self.note(format!(
                            "node {}: frame {id:#x} refused: the controller is bus-off",
                            port + 1
                        )),
                        Err(e) => self.note(format!("node {}: {e}", port + 1)),
                    }
                }
                Op::FdTransmit { id, .. } | Op::XlTransmit { id, .. } => {
                    // A classic CAN bus: its nodes see a form error where the FD / XL format bit
                    // is recessive; the sender is told so.
                    self.note(format!(
                        "node {}: CAN FD / XL frame {id:#x} on a classic CAN bus: form error",
                        port + 1
                    ));
                    self.push(
                        port,
                        &Op::BusError {
                            id,
                            code: BusErrorCode::Form,
                            primary: false,
                            is_sender: true,
                        },
                    );
                }
                Op::Configuration(Config::CanBaudrate(bps)) => {
                    if !self.ports.configure_bitrate(port, u64::from(bps)) {
                        self.note(format!(
                            "node {} set {bps} bit/s on a {} kbit/s bus: it neither sends nor receives until it sets the bus's rate",
                            port + 1,
                            self.ports.bitrate_kbps()
                        ));
                    }
                }
                Op::Configuration(Config::CanFdBaudrate(_) | Config::CanXlBaudrate(_)) => {
                    self.note(format!(
                        "node {}: CAN FD / XL bit rate ignored (a classic CAN bus)",
                        port + 1
                    ));
                }
                Op::Configuration(Config::ArbitrationLost(b)) => self
                    .ports
                    .set_discard_on_loss(port, b == ArbitrationLostBehavior::DiscardAndNotify),
                Op::Status(s) => self.ports.report_status(
                    port,
                    match s {
                        CanStatus::ErrorActive => BusState::ErrorActive,
                        CanStatus::ErrorPassive => BusState::ErrorPassive,
                        CanStatus::BusOff => BusState::BusOff,
                    },
                ),
                Op::Wakeup => {
                    for other in (0..self.ports.len()).filter(|&p| p != port) {
                        self.push(other, &Op::Wakeup);
                    }
                }
                Op::Confirm { .. } | Op::ArbitrationLost { .. } | Op::BusError { .. } => {
                    // Produced by a bus simulation; a node's own are not routed (LS-BUS).
                    self.note(format!(
                        "node {}: a bus simulation's operation from a node, ignored",
                        port + 1
                    ));
                }
            }
        }
        Ok(())
    }

    /// Runs the bus on to `until` (ns), or with `early_return` to the first time something
    /// reaches a node; returns the time reached. What the nodes get is in their `Tx_Data`.
    pub fn step(&mut self, until: Nanos, early_return: bool) -> Nanos {
        let mut events = std::mem::take(&mut self.events);
        loop {
            let reached = self.ports.run_until(until, &mut events);
            for e in events.drain(..) {
                self.deliver(e);
            }
            if reached >= until || (early_return && self.any_tx()) {
                self.events = events;
                return reached;
            }
        }
    }

    /// The next time the bus has something to do, if it is after the time reached (for
    /// `fmi3UpdateDiscreteStates`'s next event time).
    pub fn next_event(&self) -> Option<Nanos> {
        self.ports.next_event().filter(|&t| t > self.now())
    }

    fn deliver(&mut self, e: PortEvent) {
        match e.kind {
            PortEventKind::Received(f) => {
                let op = Op::Transmit {
                    id: f.id(),
                    ide: f.is_extended(),
                    rtr: f.is_remote(),
                    data: if f.is_remote() { &[] } else { f.data() },
                    dlc: u16::from(f.dlc()),
                };
                self.push(e.port, &op);
            }
            PortEventKind::Confirmed(f) => self.push(e.port, &Op::Confirm { id: f.id() }),
            // BUFFER_AND_RETRANSMIT: the frame waits in the bus and nobody is told (LS-BUS).
            PortEventKind::ArbitrationLost { frame, discarded } => {
                if discarded {
                    self.push(e.port, &Op::ArbitrationLost { id: frame.id() });
                }
            }
            PortEventKind::BusError {
                id,
                kind,
                is_sender,
                primary,
            } => {
                let code = match kind {
                    // Two senders of one identifier: a bit error at the first differing bit.
                    BusErrorKind::Collision => BusErrorCode::Bit,
                    BusErrorKind::Corrupted => BusErrorCode::Crc,
                    BusErrorKind::StuckDominant { .. } | BusErrorKind::ErrorFlag => {
                        BusErrorCode::BitStuffing
                    }
                };
                self.push(
                    e.port,
                    &Op::BusError {
                        id: id.unwrap_or(0),
                        code,
                        primary,
                        is_sender,
                    },
                );
            }
            // A bus simulation sends no Status (LS-BUS): the nodes keep their own counters from
            // the Bus Errors; the bus's view is in its outputs.
            PortEventKind::Status { state, tec, rec } => self.note(format!(
                "node {}'s controller on the bus model: {state:?} (TEC {tec}, REC {rec}) at {} µs",
                e.port + 1,
                e.at / 1000
            )),
        }
    }
}

#[cfg(test)]
mod tests;
