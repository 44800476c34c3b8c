//! The bus timeline as a network of CAN controllers that come and go: the engine of
//! `canpos bus netsim`, which simulates a Vector SIL Kit CAN network (issue 32 item 3,
//! docs/SILKIT.md "canpos as the network simulator").
//!
//! SIL Kit hands a network simulator controllers identified by an opaque descriptor, their
//! mode requests (start, stop, sleep, reset), bit rates and frame requests, each request with
//! a user context that must come back in its transmit acknowledgement. This module keeps one
//! [`Timeline`] member per started controller (no second bus model) and turns what happens on
//! the bus into what SIL Kit's controllers are told ([`NetEvent`]): a frame to every other
//! started controller at its end-of-frame time, the sender's acknowledgement only when its
//! frame won the bus and went through, `TransmitQueueFull` / `Canceled` for frames that did
//! not, and the controller and error states. It is sans-IO: the caller passes the time in and
//! sends the events; nothing here reads a clock or touches SIL Kit.

use std::collections::{BTreeMap, HashMap};

use canpos_stack::Frame;

use super::timeline::{Accepted, BusEvent, MemberId, Nanos, Rejected, Timeline, TxOrder};
use super::DEFAULT_TX_DEPTH;
pub use crate::can::{BusState, MemberStats};

/// A controller as SIL Kit names it to the simulator (`SilKit_Experimental_ControllerDescriptor`).
pub type Descriptor = u64;

/// The user context of a frame request, handed back in its acknowledgement.
pub type Context = u64;

/// Most removed controllers whose last counters a network keeps for its report.
pub const MAX_DEPARTED: usize = 1024;

/// Most controllers one simulated network takes (CANopen's 127 node-ids, plus masters, tools
/// and bridges): a bound on what a peer can make the simulator hold.
pub const MAX_CONTROLLERS: usize = 256;

/// A CAN controller's mode, with SIL Kit's numbers (`SilKit_CanControllerState`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ControllerMode {
    /// Not initialised (also the mode a reset asks for).
    #[default]
    Uninit = 0,
    /// Stopped: neither sends nor receives.
    Stopped = 1,
    /// Started: takes part in the bus.
    Started = 2,
    /// Asleep: neither sends nor receives.
    Sleep = 3,
}

impl ControllerMode {
    /// The mode of SIL Kit's number, `None` for a number SIL Kit does not define.
    pub fn from_raw(raw: i32) -> Option<ControllerMode> {
        Some(match raw {
            0 => ControllerMode::Uninit,
            1 => ControllerMode::Stopped,
            2 => ControllerMode::Started,
            3 => ControllerMode::Sleep,
            _ => return None,
        })
    }
}

/// What became of a frame request (`SilKit_CanTransmitStatus`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TxStatus {
    /// It went through the bus (won arbitration, no error to the end of frame).
    Transmitted,
    /// It never will: the controller is not started, went bus-off, cancelled its requests, or
    /// the frame is not a classic CAN frame.
    Canceled,
    /// The controller's transmit queue was full of more important frames.
    QueueFull,
}

/// A frame request as SIL Kit's `SilKit_CanFrame` carries it, before it is judged.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RawFrame<'a> {
    /// CAN identifier.
    pub id: u32,
    /// Extended (29-bit) identifier (`SilKit_CanFrameFlag_ide`).
    pub extended: bool,
    /// Remote frame (`SilKit_CanFrameFlag_rtr`).
    pub remote: bool,
    /// A CAN FD or XL frame (`fdf` / `xlf`): not on a classic CAN bus.
    pub fd_or_xl: bool,
    /// Data length code.
    pub dlc: u16,
    /// The data field.
    pub data: &'a [u8],
}

/// Why a frame request is not a classic CAN frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BadFrame {
    /// A CAN FD or XL frame on a classic CAN network.
    #[error("a CAN FD / XL frame on a classic CAN network")]
    NotClassic,
    /// More than 8 data bytes, or a DLC above 8, or a DLC that disagrees with the data.
    #[error("{0} data bytes / DLC: classic CAN carries at most 8")]
    TooLong(usize),
    /// The identifier does not fit 11 (standard) or 29 (extended) bits.
    #[error("identifier {0:#x} does not fit its format")]
    BadId(u32),
}

impl RawFrame<'_> {
    /// The classic CAN frame it describes.
    pub fn to_frame(&self) -> Result<Frame, BadFrame> {
        if self.fd_or_xl {
            return Err(BadFrame::NotClassic);
        }
        let max_id = if self.extended { 0x1FFF_FFFF } else { 0x7FF };
        if self.id > max_id {
            return Err(BadFrame::BadId(self.id));
        }
        if self.remote {
            if self.dlc > 8 {
                return Err(BadFrame::TooLong(usize::from(self.dlc)));
            }
            return Frame::remote(self.id, self.extended, self.dlc as u8)
                .map_err(|_| BadFrame::BadId(self.id));
        }
        // SIL Kit leaves the DLC to the simulator ("determined by a network simulator if
        // available"): 0 with data means "the data's length"; any other DLC must match it.
        let n = self.data.len();
        if n > 8 || (self.dlc != 0 && usize::from(self.dlc) != n) {
            return Err(BadFrame::TooLong(n.max(usize::from(self.dlc))));
        }
        Frame::with_id(self.id, self.extended, self.data).map_err(|e| match e {
            canpos_stack::FrameError::TooLong => BadFrame::TooLong(n),
            canpos_stack::FrameError::BadId => BadFrame::BadId(self.id),
        })
    }
}

/// What the simulator tells SIL Kit's controllers.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum NetEvent {
    /// A frame went through the bus at `at` (its end of frame): the senders get it back as
    /// sent (direction TX, with their context) and acknowledged, the receivers as received.
    Frame {
        /// The controllers that sent it, each with its request's context (several only when
        /// they sent the very same frame in one arbitration: one frame on the wire).
        senders: Vec<(Descriptor, Context)>,
        /// The started controllers that received it.
        receivers: Vec<Descriptor>,
        /// The frame.
        frame: Frame,
        /// End of frame, bus time.
        at: Nanos,
    },
    /// A request that did not go through.
    NotSent {
        /// Its controller.
        to: Descriptor,
        /// Its context.
        context: Context,
        /// Its identifier (SIL Kit's acknowledgement carries it).
        id: u32,
        /// Why.
        status: TxStatus,
        /// When it was decided.
        at: Nanos,
    },
    /// A controller's mode or error state changed (both are sent: SIL Kit's controller status
    /// carries both).
    Status {
        /// The controller.
        to: Descriptor,
        /// Its mode.
        mode: ControllerMode,
        /// Its error state (`None`: not available, before its first start or after a reset).
        error: Option<BusState>,
        /// When.
        at: Nanos,
    },
}

/// Counters of one simulated network.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct NetCounters {
    /// Frames that went through the bus.
    pub frames: u64,
    /// Deliveries to receivers (a frame to n receivers counts n).
    pub deliveries: u64,
    /// Requests answered `TransmitQueueFull`.
    pub queue_full: u64,
    /// Requests answered `Canceled` (not started, bus-off, cancelled).
    pub canceled: u64,
    /// Requests refused as not classic CAN (also answered `Canceled`).
    pub bad_frames: u64,
    /// Requests from a controller the simulator does not know (dropped: no one to answer).
    pub unknown: u64,
}

#[derive(Debug, Default)]
struct Ctrl {
    member: Option<MemberId>,
    mode: ControllerMode,
    error: Option<BusState>,
    /// Its bit rate differs from the bus's: cut off (as a transceiver that does not drive).
    cut_off: bool,
    /// Frames in the timeline's queue (or on the wire) with their contexts, in submission order.
    pending: Vec<(Frame, Context)>,
}

/// One simulated CAN network.
#[derive(Debug)]
pub struct Network {
    timeline: Timeline,
    ctrls: BTreeMap<Descriptor, Ctrl>,
    of_member: HashMap<u32, Descriptor>,
    reached: Nanos,
    scratch: Vec<BusEvent>,
    counters: NetCounters,
    /// Removed controllers with their last mode and counters (at most [`MAX_DEPARTED`]).
    departed: Vec<(Descriptor, ControllerMode, Option<MemberStats>)>,
}

impl Network {
    /// A network at `kbps` kbit/s (a CiA 301 rate).
    pub fn new(kbps: u32) -> Result<Network, String> {
        Ok(Network {
            timeline: Timeline::new(kbps)?,
            ctrls: BTreeMap::new(),
            of_member: HashMap::new(),
            reached: 0,
            scratch: Vec::new(),
            counters: NetCounters::default(),
            departed: Vec::new(),
        })
    }

    /// The bus's bit rate, kbit/s.
    pub fn bitrate_kbps(&self) -> u32 {
        self.timeline.bitrate_kbps()
    }

    /// The bus time reached by the last [`advance_to`](Self::advance_to).
    pub fn reached(&self) -> Nanos {
        self.reached
    }

    /// The network's counters.
    pub fn counters(&self) -> NetCounters {
        self.counters
    }

    /// Controllers known, with their mode and (if started once) their bus counters, in
    /// descriptor order.
    pub fn controllers(&self) -> Vec<(Descriptor, ControllerMode, Option<MemberStats>)> {
        self.ctrls
            .iter()
            .map(|(&d, c)| (d, c.mode, c.member.and_then(|m| self.timeline.stats(m))))
            .collect()
    }

    /// Controllers SIL Kit removed, with their last mode and bus counters (the latest
    /// [`MAX_DEPARTED`]).
    pub fn departed(&self) -> &[(Descriptor, ControllerMode, Option<MemberStats>)] {
        &self.departed
    }

    /// Bus load over the last second before the time reached: (fraction 0 … 1, frames/s).
    pub fn load(&mut self) -> (f64, f64) {
        self.timeline.load(self.reached)
    }

    /// SIL Kit provides a controller. `false` (and nothing changes) when the network already
    /// holds [`MAX_CONTROLLERS`] or knows the descriptor.
    ///
    /// It takes part as started until it asks for a mode (D39): SIL Kit does not repeat a
    /// controller's mode when a simulator appears, so a controller started before the
    /// simulator knew it would otherwise never send nor receive.
    pub fn attach(&mut self, d: Descriptor) -> bool {
        if self.ctrls.len() >= MAX_CONTROLLERS || self.ctrls.contains_key(&d) {
            return false;
        }
        let m = self.timeline.join_with(DEFAULT_TX_DEPTH, TxOrder::Priority);
        self.of_member.insert(m.0, d);
        self.ctrls.insert(
            d,
            Ctrl {
                member: Some(m),
                mode: ControllerMode::Started,
                error: Some(BusState::ErrorActive),
                ..Ctrl::default()
            },
        );
        true
    }

    /// SIL Kit removed a controller: what it queued is dropped (nobody is left to tell), a
    /// frame of it on the wire finishes.
    pub fn detach(&mut self, d: Descriptor) {
        if let Some(c) = self.ctrls.remove(&d) {
            if self.departed.len() >= MAX_DEPARTED {
                self.departed.remove(0);
            }
            self.departed
                .push((d, c.mode, c.member.and_then(|m| self.timeline.stats(m))));
            if let Some(m) = c.member {
                self.timeline.cancel_queued(m);
                self.timeline.leave(m);
                self.of_member.remove(&m.0);
            }
        }
    }

    /// The controller set its bit rate (bit/s; 0: not set). Another rate than the bus's cuts
    /// it off: its frames never reach the bus (each attempt a bit error at SOF: error passive
    /// after 16, bus-off after 32, the timeline's failed transceiver) and it receives nothing;
    /// the bus's rate again restores it.
    pub fn set_bitrate(&mut self, d: Descriptor, bps: u32, now: Nanos) {
        let bus = self.timeline.bitrate_kbps() * 1000;
        let Some(c) = self.ctrls.get_mut(&d) else {
            return;
        };
        c.cut_off = bps != 0 && bps != bus;
        if let Some(m) = c.member {
            self.timeline
                .set_transceiver_failed(m, c.cut_off, now.max(self.reached));
        }
    }

    /// The controller asks for `mode`, optionally resetting its error handling (counters to
    /// 0, error active; SIL Kit's reset) and cancelling its transmit requests. A controller
    /// that leaves Started cancels its requests too (it no longer drives the bus).
    pub fn set_mode(
        &mut self,
        d: Descriptor,
        mode: ControllerMode,
        reset_errors: bool,
        cancel: bool,
        now: Nanos,
        out: &mut Vec<NetEvent>,
    ) {
        let now = now.max(self.reached);
        if !self.ctrls.contains_key(&d) {
            return;
        }
        if cancel || mode != ControllerMode::Started {
            self.cancel(d, now, out);
        }
        let c = self.ctrls.get_mut(&d).expect("checked");
        // A reset (or a reset of error handling) starts the controller's counters afresh: a new
        // member of the timeline; the old one's frame on the wire, if any, finishes.
        if reset_errors || mode == ControllerMode::Uninit {
            if let Some(m) = c.member.take() {
                self.timeline.leave(m);
                self.of_member.remove(&m.0);
            }
            c.error = None;
        }
        if mode == ControllerMode::Started && c.member.is_none() {
            let m = self.timeline.join_with(DEFAULT_TX_DEPTH, TxOrder::Priority);
            if c.cut_off {
                self.timeline.set_transceiver_failed(m, true, now);
            }
            c.member = Some(m);
            c.error = Some(BusState::ErrorActive);
            self.of_member.insert(m.0, d);
        }
        c.mode = mode;
        // Always answered: in a simulated network a controller takes the mode the simulator
        // reports, not the one it asked for.
        out.push(NetEvent::Status {
            to: d,
            mode: c.mode,
            error: c.error,
            at: now,
        });
    }

    /// Cancels the controller's queued requests: each is answered `Canceled`.
    fn cancel(&mut self, d: Descriptor, now: Nanos, out: &mut Vec<NetEvent>) {
        let Some(c) = self.ctrls.get_mut(&d) else {
            return;
        };
        let Some(m) = c.member else {
            return;
        };
        for f in self.timeline.cancel_queued(m) {
            // Equal frames leave in submission order; the one on the wire (if equal) is the
            // earliest, so the cancelled ones are the latest entries.
            if let Some(i) = c.pending.iter().rposition(|(p, _)| *p == f) {
                let (_, context) = c.pending.remove(i);
                self.counters.canceled += 1;
                out.push(NetEvent::NotSent {
                    to: d,
                    context,
                    id: f.id(),
                    status: TxStatus::Canceled,
                    at: now,
                });
            }
        }
    }

    /// A frame request from controller `d` with its context, handed in at `at` (no earlier than
    /// the time reached; an earlier time is taken as the time reached). A request that cannot
    /// go on the bus is answered at once (in `out`); one that can is answered when it went
    /// through ([`advance_to`](Self::advance_to)).
    pub fn request(
        &mut self,
        d: Descriptor,
        raw: &RawFrame<'_>,
        context: Context,
        at: Nanos,
        out: &mut Vec<NetEvent>,
    ) {
        let at = at.max(self.reached);
        let Some(c) = self.ctrls.get_mut(&d) else {
            self.counters.unknown += 1;
            return;
        };
        let mut refuse = |status: TxStatus, counters: &mut NetCounters| {
            match status {
                TxStatus::QueueFull => counters.queue_full += 1,
                _ => counters.canceled += 1,
            }
            out.push(NetEvent::NotSent {
                to: d,
                context,
                id: raw.id,
                status,
                at,
            });
        };
        let frame = match raw.to_frame() {
            Ok(f) => f,
            Err(_) => {
                self.counters.bad_frames += 1;
                refuse(TxStatus::Canceled, &mut self.counters);
                return;
            }
        };
        let (ControllerMode::Started, Some(m)) = (c.mode, c.member) else {
            refuse(TxStatus::Canceled, &mut self.counters);
            return;
        };
        match self.timeline.submit(m, frame, at) {
            Ok(Accepted::Queued) => c.pending.push((frame, context)),
            Ok(Accepted::Evicted(lost)) => {
                c.pending.push((frame, context));
                // The evicted frame is the least important and, among equals, the latest.
                if let Some(i) = c.pending.iter().rposition(|(p, _)| *p == lost) {
                    let (_, lost_context) = c.pending.remove(i);
                    self.counters.queue_full += 1;
                    out.push(NetEvent::NotSent {
                        to: d,
                        context: lost_context,
                        id: lost.id(),
                        status: TxStatus::QueueFull,
                        at,
                    });
                }
            }
            Err(Rejected::QueueFull) => refuse(TxStatus::QueueFull, &mut self.counters),
            Err(Rejected::BusOff) | Err(Rejected::NoMember) => {
                refuse(TxStatus::Canceled, &mut self.counters)
            }
        }
    }

    /// The start and end of the frame on the wire once nothing can change its outcome
    /// ([`Timeline::settled_frame`]): a simulator in steps may run the bus to its end (and
    /// report it) before it knows the requests of that interval, which only queue for the
    /// next arbitration.
    pub fn settled_frame(&self) -> Option<(Nanos, Nanos)> {
        self.timeline.settled_frame()
    }

    /// When [`advance_to`](Self::advance_to) next has something to do (`None`: nothing until a
    /// request).
    pub fn next_event(&self) -> Option<Nanos> {
        self.timeline.next_event()
    }

    /// Runs the bus up to `t` (never back) and appends what SIL Kit's controllers are told, in
    /// time order.
    pub fn advance_to(&mut self, t: Nanos, out: &mut Vec<NetEvent>) {
        if t < self.reached {
            return;
        }
        let mut events = std::mem::take(&mut self.scratch);
        self.timeline.advance(t, &mut events);
        self.reached = t;
        let start = out.len();
        for ev in events.drain(..) {
            self.translate(ev, out);
        }
        self.scratch = events;
        // The timeline reports in time order except a failed transceiver's own attempts.
        out[start..].sort_by_key(event_time);
    }

    fn translate(&mut self, ev: BusEvent, out: &mut Vec<NetEvent>) {
        match ev {
            BusEvent::Frame {
                from,
                co_senders,
                frame,
                end,
                ..
            } => {
                let mut senders = Vec::with_capacity(1 + co_senders.len());
                for m in std::iter::once(from).chain(co_senders) {
                    let Some(&d) = self.of_member.get(&m.0) else {
                        continue; // its controller was reset or removed meanwhile
                    };
                    let c = self.ctrls.get_mut(&d).expect("mapped");
                    if let Some(i) = c.pending.iter().position(|(p, _)| *p == frame) {
                        let (_, context) = c.pending.remove(i);
                        senders.push((d, context));
                    }
                }
                let receivers: Vec<Descriptor> = self
                    .ctrls
                    .iter()
                    .filter(|(d, c)| {
                        c.mode == ControllerMode::Started
                            && !c.cut_off
                            && c.error != Some(BusState::BusOff)
                            && !senders.iter().any(|(s, _)| s == *d)
                    })
                    .map(|(&d, _)| d)
                    .collect();
                self.counters.frames += 1;
                self.counters.deliveries += receivers.len() as u64;
                out.push(NetEvent::Frame {
                    senders,
                    receivers,
                    frame,
                    at: end,
                });
            }
            // SIL Kit's CAN API has no error frames: their effect reaches the controllers as
            // error-state changes (below) and retransmissions.
            BusEvent::Error(_) => {}
            // Only a timeline that asks for them reports losses (the LS-BUS FMU's); SIL Kit's
            // controllers keep a lost frame queued and are told nothing of the arbitration.
            BusEvent::ArbitrationLost { .. } => {}
            BusEvent::State {
                member, at, state, ..
            } => {
                let Some(&d) = self.of_member.get(&member.0) else {
                    return;
                };
                let c = self.ctrls.get_mut(&d).expect("mapped");
                c.error = Some(state);
                if state == BusState::BusOff {
                    // The timeline dropped its queue (counted as lost_bus_off): each request
                    // is answered.
                    for (f, context) in c.pending.drain(..) {
                        self.counters.canceled += 1;
                        out.push(NetEvent::NotSent {
                            to: d,
                            context,
                            id: f.id(),
                            status: TxStatus::Canceled,
                            at,
                        });
                    }
                }
                out.push(NetEvent::Status {
                    to: d,
                    mode: c.mode,
                    error: Some(state),
                    at,
                });
            }
        }
    }
}

fn event_time(e: &NetEvent) -> Nanos {
    match e {
        NetEvent::Frame { at, .. } | NetEvent::NotSent { at, .. } | NetEvent::Status { at, .. } => {
            *at
        }
    }
}

#[cfg(test)]
mod tests;
