//! The bus timeline: one CAN bus as a sans-IO state machine (no sockets, no threads, no clock;
//! the caller passes the time in, in nanoseconds since the bus started).
//!
//! Members (CAN controllers) [`submit`](Timeline::submit) frames into their bounded transmit
//! queues; [`advance`](Timeline::advance) runs the bus up to a given time and reports what
//! happened on it ([`BusEvent`]): frames at their end-of-frame time, error frames, and error
//! state changes of the members. [`next_event`](Timeline::next_event) says when to call again.
//! See docs/BUS.md for the model and the choices behind it.

use std::collections::VecDeque;

use canpos_stack::Frame;

use super::bits::{
    arbitration_key, first_difference, frame_length, stuffed, BUS_OFF_RECOVERY_SEQUENCES,
    ERROR_FRAME_BITS, INTERMISSION_BITS, RECESSIVE_SEQUENCE_BITS, SUSPEND_BITS,
};
pub use crate::can::{BusErrorKind, BusState, MemberStats};

/// Time on the bus timeline: nanoseconds since the bus started.
pub type Nanos = u64;

/// The window over which bus load and frame rate are measured.
pub const LOAD_WINDOW: Nanos = 1_000_000_000;

/// Default transmit queue depth of a member, in frames (see docs/BUS.md).
pub const DEFAULT_TX_DEPTH: usize = 64;

/// Longest stuck-dominant interval [`Timeline::stuck_dominant`] accepts.
pub const MAX_STUCK: Nanos = 60_000_000_000;

/// Bit rates of the CiA 301 bit-timing table, kbit/s (100 kbit/s is listed there as not
/// recommended for new designs but is still a table entry).
pub const CIA301_BITRATES: [u32; 9] = [1000, 800, 500, 250, 125, 100, 50, 20, 10];

/// One controller on the bus: an index the timeline gave out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct MemberId(pub u32);
/// An error frame on the bus, as the timeline reports it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BusError {
    /// End of the error delimiter (stuck dominant: end of the dominant interval).
    pub at: Nanos,
    /// What happened.
    pub kind: BusErrorKind,
    /// Identifier of the frame destroyed, if one was on the wire.
    pub id: Option<u32>,
    /// The members that were transmitting.
    pub transmitters: Vec<MemberId>,
}

/// Something that happened on the bus.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum BusEvent {
    /// A frame was received by everyone but its senders, at `end` (end of EOF).
    Frame {
        /// The member that sent it.
        from: MemberId,
        /// Other members that sent the very same frame in the same arbitration (all succeed).
        co_senders: Vec<MemberId>,
        /// The frame.
        frame: Frame,
        /// Start of frame.
        start: Nanos,
        /// End of frame.
        end: Nanos,
    },
    /// An error frame.
    Error(BusError),
    /// A member's error state changed.
    State {
        /// The member.
        member: MemberId,
        /// When.
        at: Nanos,
        /// New state.
        state: BusState,
        /// Transmit error counter then.
        tec: u16,
        /// Receive error counter then.
        rec: u16,
    },
    /// A member's frame lost an arbitration (reported only on a timeline that asked for it,
    /// [`Timeline::report_arbitration_losses`]: the bus-simulation FMU's `Arbitration Lost`).
    ArbitrationLost {
        /// The member.
        member: MemberId,
        /// Its frame that lost.
        frame: Frame,
        /// Start of the winning frame.
        at: Nanos,
        /// The frame was taken out of the member's queue ([`Timeline::set_discard_on_loss`]);
        /// otherwise it takes part in the next arbitration.
        discarded: bool,
    },
}

/// Why [`Timeline::submit`] did not queue a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rejected {
    /// The transmit queue was full of frames at least as important.
    QueueFull,
    /// The member is bus-off.
    BusOff,
    /// No such member.
    NoMember,
}

/// What [`Timeline::submit`] did with a frame it accepted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accepted {
    /// Queued.
    Queued,
    /// Queued in place of a less important frame, which is lost (and counted).
    Evicted(Frame),
}
#[derive(Clone, Copy, Debug)]
struct Queued {
    frame: Frame,
    key: u32,
    ready_at: Nanos,
    seq: u64,
    on_wire: bool,
}

/// The order in which a controller's transmit queue goes on the bus.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TxOrder {
    /// Its most important frame first (lowest identifier; the same identifier in submission
    /// order): a microcontroller's CAN peripheral with several transmit buffers (bxCAN with
    /// TXFP = 0, most others), which is what a sensor has.
    #[default]
    Priority,
    /// In submission order, head of line: a Linux host's SocketCAN interface (the netdev queue
    /// is FIFO and most drivers hand the controller one frame at a time), i.e. what stands
    /// behind a socketcand client. A full queue drops the new frame.
    Fifo,
}

#[derive(Debug, Default)]
struct Member {
    live: bool,
    order: TxOrder,
    /// Left: removed once its queue is empty.
    leaving: bool,
    queue: Vec<Queued>,
    depth: usize,
    tec: u16,
    rec: u16,
    state: BusState,
    /// Error passive: may not start a frame before this (suspend transmission).
    suspend_until: Nanos,
    /// Bus-off: 11-recessive-bit sequences seen so far, and the start of the current
    /// recessive run.
    off_sequences: u64,
    off_run_start: Nanos,
    /// The transceiver no longer drives the bus: every attempt is a bit error at SOF.
    transceiver_failed: bool,
    /// A frame that loses an arbitration leaves the queue (LS-BUS `DISCARD_AND_NOTIFY`).
    discard_on_loss: bool,
    next_attempt: Nanos,
    stats: MemberStats,
}

impl Member {
    /// The frame this member offers at an arbitration at `t`: its most important frame ready
    /// by then (lowest identifier; the same identifier in submission order).
    fn offer(&self, t: Nanos) -> Option<usize> {
        if self.order == TxOrder::Fifo {
            let (i, head) = self.queue.iter().enumerate().min_by_key(|(_, q)| q.seq)?;
            return (head.ready_at <= t).then_some(i);
        }
        self.queue
            .iter()
            .enumerate()
            .filter(|(_, q)| q.ready_at <= t)
            .min_by_key(|(_, q)| (q.key, q.seq))
            .map(|(i, _)| i)
    }

    fn earliest_ready(&self) -> Option<Nanos> {
        self.queue.iter().map(|q| q.ready_at).min()
    }

    fn can_arbitrate(&self) -> bool {
        self.live && self.state != BusState::BusOff && !self.transceiver_failed
    }
}

/// A member's frame in an arbitration: member index, queue index, arbitration value.
type Offer = (u32, usize, u32);

#[derive(Debug)]
struct OnWire {
    senders: Vec<(MemberId, u64)>,
    frame: Frame,
    start: Nanos,
    /// End of EOF (success) or of the error delimiter (error).
    end: Nanos,
    /// The bus is free for the next SOF (after the intermission).
    free: Nanos,
    /// Whether the frame failed, and how.
    error: Option<BusErrorKind>,
    /// Bits on the wire, for the load.
    bits: u64,
    /// Error-passive senders of the same identifier that lost at a data bit (and the bit).
    passive_losers: Vec<(MemberId, u32)>,
}

/// The bus.
#[derive(Debug)]
pub struct Timeline {
    bitrate_kbps: u32,
    bit_ns: Nanos,
    members: Vec<Member>,
    free_slots: Vec<u32>,
    /// Members with something queued (arbitration looks at these only).
    active: Vec<u32>,
    /// Members that are bus-off (recovery counting).
    off: Vec<u32>,
    /// Members with a failed transceiver.
    failed: Vec<u32>,
    current: Option<OnWire>,
    /// The bus is free for a start of frame from here on.
    free_at: Nanos,
    seq: u64,
    /// (end, bits, is a frame) of everything on the bus within the load window.
    window: VecDeque<(Nanos, u64, bool)>,
    window_bits: u64,
    window_frames: u64,
    frames: u64,
    error_frames: u64,
    /// Corrupted frames per million (injected).
    corrupt_ppm: u32,
    rng: u64,
    /// A pending stuck-dominant interval.
    stuck: Option<(Nanos, Nanos)>,
    /// The pending interval is an error flag of this member, not a disturbance.
    flag: Option<MemberId>,
    /// Error flags refused because one was still pending.
    flags_refused: u64,
    /// Some member's REC may be above 0.
    rec_raised: bool,
    /// Report [`BusEvent::ArbitrationLost`] (off for the in-process buses: nobody asks).
    report_losses: bool,
}

/// A parameter of a bus disturbance out of range.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct BadDisturbance(pub String);

/// Checks a bit rate against the CiA 301 table.
pub fn check_bitrate(kbps: u32) -> Result<u32, String> {
    if CIA301_BITRATES.contains(&kbps) {
        Ok(kbps)
    } else {
        Err(format!(
            "{kbps} kbit/s is not a CiA 301 bit rate (kbit/s: 10, 20, 50, 100, 125, 250, 500, 800, 1000)"
        ))
    }
}

impl Timeline {
    /// A bus at `kbps` kbit/s; it must be a CiA 301 bit rate.
    pub fn new(kbps: u32) -> Result<Timeline, String> {
        let kbps = check_bitrate(kbps)?;
        Ok(Timeline {
            bitrate_kbps: kbps,
            // 1000 kbit/s: 1000 ns per bit; all CiA 301 rates divide 10⁶ ns·kbit/s exactly.
            bit_ns: 1_000_000 / Nanos::from(kbps),
            members: Vec::new(),
            free_slots: Vec::new(),
            active: Vec::new(),
            off: Vec::new(),
            failed: Vec::new(),
            current: None,
            free_at: 0,
            seq: 0,
            window: VecDeque::new(),
            window_bits: 0,
            window_frames: 0,
            frames: 0,
            error_frames: 0,
            corrupt_ppm: 0,
            rng: 0x9E37_79B9_7F4A_7C15,
            stuck: None,
            flag: None,
            flags_refused: 0,
            rec_raised: false,
            report_losses: false,
        })
    }

    /// The bit rate, kbit/s.
    pub fn bitrate_kbps(&self) -> u32 {
        self.bitrate_kbps
    }

    /// One bit time.
    pub fn bit_time(&self) -> Nanos {
        self.bit_ns
    }

    /// How long `frame` occupies the bus, intermission included.
    pub fn frame_time(&self, frame: &Frame) -> Nanos {
        Nanos::from(frame_length(frame).total) * self.bit_ns
    }

    /// Adds a controller with a transmit queue of `depth` frames (at least 1), drained by
    /// priority ([`TxOrder::Priority`]).
    pub fn join(&mut self, depth: usize) -> MemberId {
        self.join_with(depth, TxOrder::Priority)
    }

    /// Adds a controller whose transmit queue of `depth` frames drains in `order`.
    pub fn join_with(&mut self, depth: usize, order: TxOrder) -> MemberId {
        let m = Member {
            live: true,
            depth: depth.max(1),
            order,
            ..Member::default()
        };
        match self.free_slots.pop() {
            Some(i) => {
                self.members[i as usize] = m;
                MemberId(i)
            }
            None => {
                self.members.push(m);
                MemberId(self.members.len() as u32 - 1)
            }
        }
    }

    /// Changes the order in which member `id`'s transmit queue goes out (what is queued
    /// stays; the next arbitration takes its frame by the new order).
    pub fn set_order(&mut self, id: MemberId, order: TxOrder) {
        if let Some(m) = self.members.get_mut(id.0 as usize).filter(|m| m.live) {
            m.order = order;
        }
    }

    /// Reports every frame that loses an arbitration as [`BusEvent::ArbitrationLost`].
    pub fn report_arbitration_losses(&mut self, on: bool) {
        self.report_losses = on;
    }

    /// Makes member `id`'s frames that lose an arbitration leave its queue instead of taking
    /// part in the next one (reported as [`BusEvent::ArbitrationLost`] with `discarded`, if
    /// the timeline reports losses).
    pub fn set_discard_on_loss(&mut self, id: MemberId, on: bool) {
        if let Some(m) = self.members.get_mut(id.0 as usize).filter(|m| m.live) {
            m.discard_on_loss = on;
        }
    }

    /// Removes a controller once what it queued has gone out (as frames handed to a
    /// SocketCAN socket still go out after it is closed); at once when nothing is queued or it
    /// cannot send (bus-off, failed transceiver).
    pub fn leave(&mut self, id: MemberId) {
        let Some(m) = self.members.get_mut(id.0 as usize).filter(|m| m.live) else {
            return;
        };
        m.leaving = true;
        if m.queue.is_empty() || m.state == BusState::BusOff || m.transceiver_failed {
            self.remove(id);
        }
    }

    fn remove(&mut self, id: MemberId) {
        let m = &mut self.members[id.0 as usize];
        if !m.live {
            return;
        }
        // A frame on the wire finishes without it.
        if let Some(c) = &mut self.current {
            c.senders.retain(|s| s.0 != id);
        }
        *m = Member::default();
        self.active.retain(|&i| i != id.0);
        self.off.retain(|&i| i != id.0);
        self.failed.retain(|&i| i != id.0);
        self.free_slots.push(id.0);
    }

    fn member(&self, id: MemberId) -> Option<&Member> {
        self.members.get(id.0 as usize).filter(|m| m.live)
    }

    /// A member's counters.
    pub fn stats(&self, id: MemberId) -> Option<MemberStats> {
        self.member(id).map(|m| MemberStats {
            queued: m.queue.len(),
            tec: m.tec,
            rec: m.rec,
            state: m.state,
            ..m.stats
        })
    }

    /// Queues `frame` from member `id`, ready at `now`.
    ///
    /// A full queue keeps its most important frames: a frame with a lower identifier than the
    /// least important one queued takes its place (that one is lost), otherwise the new frame
    /// is lost. Either loss is counted.
    pub fn submit(&mut self, id: MemberId, frame: Frame, now: Nanos) -> Result<Accepted, Rejected> {
        let seq = self.seq;
        let Some(m) = self.members.get_mut(id.0 as usize).filter(|m| m.live) else {
            return Err(Rejected::NoMember);
        };
        if m.state == BusState::BusOff {
            m.stats.lost_bus_off += 1;
            return Err(Rejected::BusOff);
        }
        let q = Queued {
            frame,
            key: arbitration_key(&frame),
            ready_at: now,
            seq,
            on_wire: false,
        };
        let mut result = Accepted::Queued;
        if m.queue.len() >= m.depth && m.order == TxOrder::Fifo {
            m.stats.lost_overflow += 1;
            return Err(Rejected::QueueFull);
        }
        if m.queue.len() >= m.depth {
            let worst = m
                .queue
                .iter()
                .enumerate()
                .filter(|(_, q)| !q.on_wire)
                .max_by_key(|(_, q)| (q.key, q.seq))
                .map(|(i, q)| (i, q.key));
            match worst {
                Some((i, key)) if q.key < key => {
                    let lost = m.queue.swap_remove(i);
                    m.stats.lost_overflow += 1;
                    result = Accepted::Evicted(lost.frame);
                }
                _ => {
                    m.stats.lost_overflow += 1;
                    return Err(Rejected::QueueFull);
                }
            }
        }
        self.seq += 1;
        if m.queue.is_empty() && !m.transceiver_failed {
            self.active.push(id.0);
        }
        if m.transceiver_failed && m.queue.is_empty() {
            m.next_attempt = m.next_attempt.max(now);
        }
        m.queue.push(q);
        Ok(result)
    }

    /// Corrupts about `per_million` of every million frames on the wire (0 stops it).
    pub fn set_corruption(&mut self, per_million: u32) -> Result<(), BadDisturbance> {
        if per_million > 1_000_000 {
            return Err(BadDisturbance(format!(
                "corrupted-frame rate {per_million} per million is above 1000000"
            )));
        }
        self.corrupt_ppm = per_million;
        Ok(())
    }

    /// Corrupted frames per million.
    pub fn corruption(&self) -> u32 {
        self.corrupt_ppm
    }

    /// Holds the bus dominant from `from` for `duration` (at most [`MAX_STUCK`]; one interval
    /// at a time).
    pub fn stuck_dominant(&mut self, from: Nanos, duration: Nanos) -> Result<(), BadDisturbance> {
        if duration < self.bit_ns || duration > MAX_STUCK {
            return Err(BadDisturbance(format!(
                "stuck-dominant interval of {duration} ns is outside one bit time ({} ns) … 60 s",
                self.bit_ns
            )));
        }
        // A pending error flag is lost in the dominant interval.
        if self.stuck.is_some() && self.flag.take().is_none() {
            return Err(BadDisturbance(
                "a stuck-dominant interval is already pending".into(),
            ));
        }
        self.stuck = Some((from, from + duration));
        Ok(())
    }

    /// Member `id` reports an error it detected at `at` (a socketcand client's `< error … >`),
    /// and signals it as ISO 11898-1 says its controller would:
    ///
    /// - **error active**: an active (dominant) error flag. It destroys the frame on the wire at
    ///   that time (its transmitters' TEC + 8, retransmitted) and every other member detects an
    ///   error: REC + 1 (fault confinement rule 1). The member itself counts the error it
    ///   detected (+ 1) and the others' flags that follow its own (the dominant bit after its
    ///   flag, rule 2: + 8), so a member that keeps flagging is error passive after 15 flags.
    /// - **error passive**: a passive (recessive) flag, which nobody else sees: it destroys
    ///   nothing and moves no other counter; the member's own REC + 1.
    ///
    /// One error frame at a time: an active flag while another (or a stuck-dominant interval) is
    /// pending is refused (`false`, counted), so a flood of them is bounded by the bus time each
    /// takes. A member that is bus-off, or whose transceiver failed, sends none.
    pub fn error_flag(&mut self, id: MemberId, at: Nanos) -> bool {
        let live = self
            .member(id)
            .is_some_and(|m| m.state != BusState::BusOff && !m.transceiver_failed);
        if !live {
            self.flags_refused += 1;
            return false;
        }
        let m = &mut self.members[id.0 as usize];
        if m.state == BusState::ErrorPassive {
            // Recessive: the bus does not change. Already passive, so no state to report.
            m.rec = (m.rec + 1).min(255);
            return true;
        }
        if self.stuck.is_some() {
            self.flags_refused += 1;
            return false;
        }
        // Not before the bus is free after what already happened (the flag of a member that
        // reports late still comes after the frames before it).
        let at = at.max(self.free_at);
        self.stuck = Some((at, at + 6 * self.bit_ns));
        self.flag = Some(id);
        true
    }

    /// Error flags [`Timeline::error_flag`] refused.
    pub fn error_flags_refused(&self) -> u64 {
        self.flags_refused
    }

    /// Makes a member's transceiver fail (its frames never reach the bus; every attempt is a
    /// bit error) or work again.
    pub fn set_transceiver_failed(&mut self, id: MemberId, failed: bool, now: Nanos) -> bool {
        let Some(m) = self.members.get_mut(id.0 as usize).filter(|m| m.live) else {
            return false;
        };
        if m.transceiver_failed == failed {
            return true;
        }
        m.transceiver_failed = failed;
        if failed {
            m.next_attempt = now;
            self.failed.push(id.0);
            self.active.retain(|&i| i != id.0);
        } else {
            self.failed.retain(|&i| i != id.0);
            if !m.queue.is_empty() {
                self.active.push(id.0);
            }
        }
        true
    }

    /// Bus load over the last [`LOAD_WINDOW`] before `now`: (fraction 0…1, frames per second).
    pub fn load(&mut self, now: Nanos) -> (f64, f64) {
        self.trim_window(now);
        let span = now.clamp(1, LOAD_WINDOW);
        let busy = self.window_bits * self.bit_ns;
        (
            (busy as f64 / span as f64).min(1.0),
            self.window_frames as f64 * 1e9 / span as f64,
        )
    }

    /// Frames sent successfully since the start.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Error frames since the start.
    pub fn error_frames(&self) -> u64 {
        self.error_frames
    }

    fn trim_window(&mut self, now: Nanos) {
        while let Some(&(end, bits, frame)) = self.window.front() {
            if end + LOAD_WINDOW > now {
                break;
            }
            self.window.pop_front();
            self.window_bits -= bits;
            self.window_frames -= u64::from(frame);
        }
    }

    fn record(&mut self, end: Nanos, bits: u64, frame: bool) {
        self.window.push_back((end, bits, frame));
        self.window_bits += bits;
        self.window_frames += u64::from(frame);
        self.trim_window(end);
    }

    /// When the next arbitration could take place and who would take part.
    fn next_start(&self) -> Option<Nanos> {
        self.active
            .iter()
            .filter_map(|&i| {
                let m = &self.members[i as usize];
                if !m.can_arbitrate() {
                    return None;
                }
                Some(m.earliest_ready()?.max(self.free_at).max(m.suspend_until))
            })
            .min()
    }

    fn next_attempt(&self) -> Option<Nanos> {
        self.failed
            .iter()
            .filter_map(|&i| {
                let m = &self.members[i as usize];
                (m.state != BusState::BusOff && !m.queue.is_empty())
                    .then(|| m.next_attempt.max(m.earliest_ready().unwrap_or(0)))
            })
            .min()
    }

    /// When a bus-off member recovers if the bus stays idle from `free_at`.
    fn next_recovery(&self) -> Option<Nanos> {
        let seq = Nanos::from(RECESSIVE_SEQUENCE_BITS) * self.bit_ns;
        self.off
            .iter()
            .map(|&i| {
                let m = &self.members[i as usize];
                let left = u64::from(BUS_OFF_RECOVERY_SEQUENCES).saturating_sub(m.off_sequences);
                m.off_run_start + left * seq
            })
            .min()
    }

    /// When [`advance`](Self::advance) next has something to do (`None`: nothing until a
    /// submission).
    pub fn next_event(&self) -> Option<Nanos> {
        let bus = match &self.current {
            Some(c) => Some(c.end),
            None => self.next_start(),
        };
        let bus = match (bus, self.stuck) {
            (Some(t), Some((a, b))) if t >= a => Some(b),
            (None, Some((_, b))) => Some(b),
            (t, _) => t,
        };
        let recovery = if self.current.is_none() {
            self.next_recovery()
        } else {
            None
        };
        [bus, self.next_attempt(), recovery]
            .into_iter()
            .flatten()
            .min()
    }

    /// Runs the bus up to `now`, appending what happened to `out`: the bus's frames and error
    /// frames in time order (the attempts of a member whose transceiver failed are its own and
    /// may be reported ahead of them).
    pub fn advance(&mut self, now: Nanos, out: &mut Vec<BusEvent>) {
        self.run(now, true, out);
    }

    /// As [`advance`](Self::advance), but an arbitration due exactly at `now` is left for the
    /// next call, so that frames submitted at `now` afterwards take part in it: the step of a
    /// co-simulation (docs/FMU.md), where every node hands in its frames of time `now` after
    /// the bus reached it.
    pub fn advance_before(&mut self, now: Nanos, out: &mut Vec<BusEvent>) {
        self.run(now, false, out);
    }

    fn run(&mut self, now: Nanos, start_at_now: bool, out: &mut Vec<BusEvent>) {
        self.failed_attempts(now, out);
        loop {
            if let Some(cur) = &self.current {
                if let Some((a, b)) = self.stuck {
                    if a < cur.end {
                        if now < b {
                            return;
                        }
                        self.apply_stuck(out);
                        continue;
                    }
                }
                if cur.end > now {
                    return;
                }
                let cur = self.current.take().expect("checked");
                self.finish(cur, out);
                continue;
            }
            let start = self.next_start();
            if let Some((a, b)) = self.stuck {
                if start.is_none_or(|t| t >= a) && now >= a {
                    if now < b {
                        return;
                    }
                    self.recover_until(a, out);
                    self.apply_stuck(out);
                    continue;
                }
            }
            let Some(t) = start else {
                self.recover_until(now, out);
                return;
            };
            if t > now || (t == now && !start_at_now) {
                self.recover_until(now, out);
                return;
            }
            self.recover_until(t, out);
            self.arbitrate(t, out);
        }
    }

    /// Bus-off members that have seen their 128 × 11 recessive bits by `t` (bus idle).
    fn recover_until(&mut self, t: Nanos, out: &mut Vec<BusEvent>) {
        let seq = Nanos::from(RECESSIVE_SEQUENCE_BITS) * self.bit_ns;
        let mut i = 0;
        while i < self.off.len() {
            let id = self.off[i];
            let m = &mut self.members[id as usize];
            let left = u64::from(BUS_OFF_RECOVERY_SEQUENCES).saturating_sub(m.off_sequences);
            let at = m.off_run_start + left * seq;
            if at <= t {
                m.tec = 0;
                m.rec = 0;
                m.state = BusState::ErrorActive;
                m.off_sequences = 0;
                m.next_attempt = at;
                self.off.swap_remove(i);
                out.push(BusEvent::State {
                    member: MemberId(id),
                    at,
                    state: BusState::ErrorActive,
                    tec: 0,
                    rec: 0,
                });
            } else {
                i += 1;
            }
        }
    }

    /// A frame starts at `t` (bus off members: the recessive run ends here).
    fn note_bus_activity(&mut self, t: Nanos) {
        let seq = Nanos::from(RECESSIVE_SEQUENCE_BITS) * self.bit_ns;
        for &i in &self.off {
            let m = &mut self.members[i as usize];
            m.off_sequences += t.saturating_sub(m.off_run_start) / seq;
            m.off_run_start = Nanos::MAX / 2;
        }
    }

    /// The recessive tail of a frame or error frame that ended at `end` starts a new run
    /// (ACK delimiter and EOF, or the error delimiter: 8 recessive bits before `end`).
    fn note_bus_idle(&mut self, end: Nanos) {
        let run = end.saturating_sub(8 * self.bit_ns);
        for &i in &self.off {
            let m = &mut self.members[i as usize];
            m.off_run_start = run;
        }
    }

    fn next_random(&mut self) -> u64 {
        // xorshift64*: deterministic per bus, good enough to spread corrupted frames.
        let mut x = self.rng;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.rng = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
}

mod arbitration;
mod cancel;

#[cfg(test)]
mod tests;
