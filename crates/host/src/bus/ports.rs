//! The bus timeline as N numbered ports on a stepped clock: the engine of the FMI-LS-BUS
//! bus-simulation FMU (issue 31 item 3, docs/FMU.md "The bus-simulation FMU").
//!
//! Each port is one node's CAN controller on one [`Timeline`] (no second bus model): a node
//! [`submit`](Ports::submit)s a frame at a time, the caller [`advance`](Ports::advance_to)s the
//! bus to a time and gets per-port [`PortEvent`]s back – the frame received by every other port
//! at its end-of-frame time, the sender's confirmation, arbitration losses, bus errors and the
//! controllers' error-state changes – and [`next_event`](Ports::next_event) says when the next
//! one falls due, so an FMU's `doStep` can return early exactly there. Time is whatever the
//! caller passes in (an FMU's co-simulation time); nothing here reads a clock.
//!
//! The order of a submission and an advance to the same time is the in-process bus's: a frame
//! submitted at the time the bus already reached takes part in the next arbitration, not in
//! one at that time that already took place (docs/CLOCK.md). So a scene stepped through the
//! ports gives the frames, their order and their end-of-frame times of the same scene on a
//! `mem://` bus on a stepped clock (test `the_same_scene_on_a_mem_bus_gives_the_same_frames`).

use canpos_stack::Frame;

use super::timeline::{Accepted, BusEvent, MemberId, Nanos, Rejected, Timeline, TxOrder};
use super::DEFAULT_TX_DEPTH;
pub use crate::can::{BusErrorKind, BusState, MemberStats};

/// Most ports a bus simulation has: CANopen's 127 nodes and their master.
pub const MAX_PORTS: usize = 128;

/// What happened at one port.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PortEventKind {
    /// Another port's frame, received at its end of frame.
    Received(Frame),
    /// This port's frame went through (acknowledged) and ended then.
    Confirmed(Frame),
    /// This port's frame lost an arbitration at the start of the winner's frame; `discarded`
    /// when the port asked for it ([`Ports::set_discard_on_loss`], LS-BUS
    /// `DISCARD_AND_NOTIFY`), otherwise it tries again at the next intermission.
    ArbitrationLost {
        /// The frame.
        frame: Frame,
        /// It left the queue.
        discarded: bool,
    },
    /// An error frame on the bus, at the end of its delimiter.
    BusError {
        /// Identifier of the frame destroyed, if one was on the wire.
        id: Option<u32>,
        /// What happened.
        kind: BusErrorKind,
        /// This port was one of the frame's transmitters.
        is_sender: bool,
        /// This port detected the error first (one port per error).
        primary: bool,
    },
    /// This port's controller changed its error state (its counters then).
    Status {
        /// New state.
        state: BusState,
        /// Transmit error counter.
        tec: u16,
        /// Receive error counter.
        rec: u16,
    },
}

/// An event at a port.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PortEvent {
    /// The port (0-based).
    pub port: usize,
    /// When, in ns of bus time.
    pub at: Nanos,
    /// What.
    pub kind: PortEventKind,
}

/// Why [`Ports::submit`] did not take a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SubmitError {
    /// No such port.
    #[error("no port {0}")]
    NoPort(usize),
    /// Before the time the bus already reached (the bus never runs backwards).
    #[error("submitted at {at} ns, before the bus time reached ({reached} ns)")]
    InThePast {
        /// The time given.
        at: Nanos,
        /// The bus time reached.
        reached: Nanos,
    },
    /// The port's transmit queue is full of more important frames (the frame is lost and
    /// counted, as on the in-process bus).
    #[error("transmit queue full")]
    QueueFull,
    /// The port's controller is bus-off (on the timeline, or as its node reported it).
    #[error("the controller is bus-off")]
    BusOff,
}

#[derive(Debug)]
struct Port {
    member: MemberId,
    /// The state its node reported (LS-BUS `Status`); error active until it says otherwise.
    reported: BusState,
    /// Its node set a bit rate other than the bus's: it can neither send nor receive.
    mismatched: bool,
}

/// The bus with its ports.
#[derive(Debug)]
pub struct Ports {
    timeline: Timeline,
    ports: Vec<Port>,
    /// Port of each timeline member index.
    port_of: Vec<usize>,
    reached: Nanos,
    scratch: Vec<BusEvent>,
    /// Frames handed in by a port that reported bus-off (refused, counted).
    refused_bus_off: u64,
}

impl Ports {
    /// A bus at `kbps` kbit/s (a CiA 301 rate) with `n` ports (1 … [`MAX_PORTS`]), each a
    /// controller with the in-process bus's 64-frame priority queue (docs/BUS.md).
    pub fn new(kbps: u32, n: usize) -> Result<Ports, String> {
        if !(1..=MAX_PORTS).contains(&n) {
            return Err(format!(
                "{n} ports: a bus simulation has 1 … {MAX_PORTS} ports"
            ));
        }
        let mut timeline = Timeline::new(kbps)?;
        timeline.report_arbitration_losses(true);
        let mut ports = Vec::with_capacity(n);
        let mut port_of = Vec::with_capacity(n);
        for p in 0..n {
            let member = timeline.join(DEFAULT_TX_DEPTH);
            // Members are numbered from 0 on a new timeline.
            debug_assert_eq!(member.0 as usize, p);
            port_of.push(p);
            ports.push(Port {
                member,
                reported: BusState::ErrorActive,
                mismatched: false,
            });
        }
        Ok(Ports {
            timeline,
            ports,
            port_of,
            reached: 0,
            scratch: Vec::new(),
            refused_bus_off: 0,
        })
    }

    /// Number of ports.
    pub fn len(&self) -> usize {
        self.ports.len()
    }

    /// Never: a bus simulation has at least one port.
    pub fn is_empty(&self) -> bool {
        self.ports.is_empty()
    }

    /// The bus's bit rate, kbit/s.
    pub fn bitrate_kbps(&self) -> u32 {
        self.timeline.bitrate_kbps()
    }

    /// One bit time, ns.
    pub fn bit_time(&self) -> Nanos {
        self.timeline.bit_time()
    }

    /// The bus time reached by the last [`advance_to`](Self::advance_to).
    pub fn reached(&self) -> Nanos {
        self.reached
    }

    /// Frames sent successfully since the start.
    pub fn frames(&self) -> u64 {
        self.timeline.frames()
    }

    /// Bus load over the last second before the time reached: (fraction 0 … 1, frames/s).
    pub fn load(&mut self) -> (f64, f64) {
        self.timeline.load(self.reached)
    }

    /// A port's controller counters (state, TEC, REC, sent, queued, lost …).
    pub fn stats(&self, port: usize) -> Option<MemberStats> {
        let p = self.ports.get(port)?;
        self.timeline.stats(p.member)
    }

    /// Frames refused because their port's node had reported bus-off.
    pub fn refused_bus_off(&self) -> u64 {
        self.refused_bus_off
    }

    /// The order in which a port's queue goes out: by identifier (a device's controller, the
    /// default) or as submitted (a host's SocketCAN interface, docs/BUS.md).
    pub fn set_order(&mut self, port: usize, order: TxOrder) {
        if let Some(p) = self.ports.get(port) {
            self.timeline.set_order(p.member, order);
        }
    }

    /// LS-BUS `ARBITRATION_LOST_BEHAVIOR`: `true` for `DISCARD_AND_NOTIFY` (a frame that
    /// loses leaves the queue and the port is told), `false` for `BUFFER_AND_RETRANSMIT`
    /// (the default: it tries again at the next intermission, as a CAN controller does; the
    /// loss is still reported as an event, which an FMU may keep to itself).
    pub fn set_discard_on_loss(&mut self, port: usize, on: bool) {
        if let Some(p) = self.ports.get(port) {
            self.timeline.set_discard_on_loss(p.member, on);
        }
    }

    /// The node at `port` set its controller to `bps` bit/s (LS-BUS `CAN_BAUDRATE`). Another
    /// rate than the bus's cuts it off: its frames never reach the bus (each attempt a bit
    /// error at SOF, seen by nobody else: error passive after 16, bus-off after 32, as the
    /// timeline's failed transceiver) and it receives nothing; the bus's rate again restores
    /// it. Returns whether the rate is the bus's.
    pub fn configure_bitrate(&mut self, port: usize, bps: u64) -> bool {
        let bus = u64::from(self.timeline.bitrate_kbps()) * 1000;
        let Some(p) = self.ports.get_mut(port) else {
            return false;
        };
        p.mismatched = bps != bus;
        self.timeline
            .set_transceiver_failed(p.member, p.mismatched, self.reached);
        !p.mismatched
    }

    /// The node at `port` reported its controller's state (LS-BUS `Status`). A node that
    /// reports bus-off may send nothing (its frames are refused) and receives nothing; when
    /// every port but a frame's sender is bus-off, the frame reaches no one and is not
    /// confirmed (FMI-LS-BUS 1.0, CAN Status).
    pub fn report_status(&mut self, port: usize, state: BusState) {
        if let Some(p) = self.ports.get_mut(port) {
            p.reported = state;
        }
    }

    /// The state port `port`'s node reported.
    pub fn reported_status(&self, port: usize) -> Option<BusState> {
        self.ports.get(port).map(|p| p.reported)
    }

    /// Port `port`'s node hands in `frame` at `at` (≥ the time reached).
    pub fn submit(&mut self, port: usize, frame: Frame, at: Nanos) -> Result<(), SubmitError> {
        let p = self.ports.get(port).ok_or(SubmitError::NoPort(port))?;
        if at < self.reached {
            return Err(SubmitError::InThePast {
                at,
                reached: self.reached,
            });
        }
        if p.reported == BusState::BusOff {
            self.refused_bus_off += 1;
            return Err(SubmitError::BusOff);
        }
        match self.timeline.submit(p.member, frame, at) {
            Ok(Accepted::Queued) => Ok(()),
            // A less important frame made room: it is lost and counted (`lost_overflow`).
            Ok(Accepted::Evicted(_)) => Ok(()),
            Err(Rejected::QueueFull) => Err(SubmitError::QueueFull),
            Err(Rejected::BusOff) => Err(SubmitError::BusOff),
            Err(Rejected::NoMember) => Err(SubmitError::NoPort(port)),
        }
    }

    /// When the bus next has something to do (`None`: nothing until a submission). It may be
    /// the time reached itself: an arbitration there waits for the frames of that time.
    pub fn next_event(&self) -> Option<Nanos> {
        self.timeline.next_event()
    }

    /// Runs the bus up to `t` (never back) and appends what happened to `out`, in time order:
    /// everything that ends by `t`, but an arbitration due exactly at `t` waits for the next
    /// call, so the frames submitted at `t` meanwhile take part in it (frames ready at one
    /// time arbitrate together, whatever order their nodes were stepped in).
    pub fn advance_to(&mut self, t: Nanos, out: &mut Vec<PortEvent>) {
        if t < self.reached {
            return;
        }
        let mut events = std::mem::take(&mut self.scratch);
        self.timeline.advance_before(t, &mut events);
        self.reached = t;
        let start = out.len();
        for ev in events.drain(..) {
            self.port_events(ev, out);
        }
        self.scratch = events;
        // The timeline reports in time order but for a failed transceiver's own attempts.
        out[start..].sort_by_key(|e| e.at);
    }

    /// Runs the bus on from the time reached until something is reported (returns its time,
    /// the events in `out`) or until `until` (returns `until`): an FMU's `doStep` with early
    /// return. Bounded: at most one arbitration and one frame or error per call but for
    /// nothing to report (an arbitration's start, a lost frame's retry), then on to `until`.
    pub fn run_until(&mut self, until: Nanos, out: &mut Vec<PortEvent>) -> Nanos {
        let before = out.len();
        let mut stuck_at = None;
        loop {
            let Some(e) = self.next_event().filter(|&e| e <= until) else {
                self.advance_to(until, out);
                return self.reached;
            };
            if e <= self.reached && stuck_at == Some(self.reached) {
                // Nothing moved at this time on the last pass: never spin on it.
                self.advance_to(until, out);
                return self.reached;
            }
            if e <= self.reached {
                stuck_at = Some(self.reached);
                // The arbitration at the time reached, with every frame of that time.
                let mut events = std::mem::take(&mut self.scratch);
                self.timeline.advance(self.reached, &mut events);
                for ev in events.drain(..) {
                    self.port_events(ev, out);
                }
                self.scratch = events;
            } else {
                self.advance_to(e, out);
            }
            if out.len() > before {
                return self.reached;
            }
        }
    }

    fn port(&self, m: MemberId) -> Option<usize> {
        self.port_of.get(m.0 as usize).copied()
    }

    /// A port that neither receives nor acknowledges: its node is bus-off or at another rate.
    fn deaf(&self, port: usize) -> bool {
        let p = &self.ports[port];
        p.mismatched
            || p.reported == BusState::BusOff
            || self
                .timeline
                .stats(p.member)
                .is_some_and(|s| s.state == BusState::BusOff)
    }

    fn port_events(&self, ev: BusEvent, out: &mut Vec<PortEvent>) {
        match ev {
            BusEvent::Frame {
                from,
                co_senders,
                frame,
                end,
                ..
            } => {
                let senders: Vec<usize> = std::iter::once(from)
                    .chain(co_senders)
                    .filter_map(|m| self.port(m))
                    .collect();
                let receivers: Vec<usize> = (0..self.ports.len())
                    .filter(|p| !senders.contains(p) && !self.deaf(*p))
                    .collect();
                // Nobody to acknowledge it: no confirmation (LS-BUS CAN Status, BUS_OFF).
                if receivers.is_empty() && self.ports.len() > senders.len() {
                    return;
                }
                for &port in &senders {
                    out.push(PortEvent {
                        port,
                        at: end,
                        kind: PortEventKind::Confirmed(frame),
                    });
                }
                for port in receivers {
                    out.push(PortEvent {
                        port,
                        at: end,
                        kind: PortEventKind::Received(frame),
                    });
                }
            }
            BusEvent::Error(e) => {
                let senders: Vec<usize> = e
                    .transmitters
                    .iter()
                    .filter_map(|&m| self.port(m))
                    .collect();
                // Who saw it first: a transmitter's bit error (collision, a dominant bus), a
                // receiver's CRC / stuff error otherwise.
                let primary = match e.kind {
                    BusErrorKind::Corrupted => (0..self.ports.len())
                        .find(|p| !senders.contains(p) && !self.deaf(*p))
                        .or(senders.first().copied()),
                    _ => senders.first().copied().or(Some(0)),
                };
                for port in 0..self.ports.len() {
                    let is_sender = senders.contains(&port);
                    if !is_sender && self.deaf(port) {
                        continue;
                    }
                    out.push(PortEvent {
                        port,
                        at: e.at,
                        kind: PortEventKind::BusError {
                            id: e.id,
                            kind: e.kind,
                            is_sender,
                            primary: primary == Some(port),
                        },
                    });
                }
            }
            BusEvent::State {
                member,
                at,
                state,
                tec,
                rec,
            } => {
                if let Some(port) = self.port(member) {
                    out.push(PortEvent {
                        port,
                        at,
                        kind: PortEventKind::Status { state, tec, rec },
                    });
                }
            }
            BusEvent::ArbitrationLost {
                member,
                frame,
                at,
                discarded,
            } => {
                if let Some(port) = self.port(member) {
                    out.push(PortEvent {
                        port,
                        at,
                        kind: PortEventKind::ArbitrationLost { frame, discarded },
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests;
