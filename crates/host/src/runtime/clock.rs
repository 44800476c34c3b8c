//! The runtime's clock glue: the core's `Instant` against the wall and the simulation
//! clock, advancing to a time (frames in their order, cycles, stalls), and the stalls.

use std::io;

use canpos_stack::Instant;

use crate::can::Transport;
use crate::clock::{Driver, SimClock};
use crate::control::request::Request;
use serde_json::Value;

use super::{Msg, Runtime};

impl Runtime {
    /// The limit of the simulation clock in the core's µs (since the clock's epoch): the wall
    /// time elapsed, or a stepped clock's target. The runtime processes its events up to it.
    pub fn now(&self) -> Instant {
        Instant::from_micros(self.clock.limit() / 1000)
    }

    /// The simulation clock the runtime runs on.
    pub fn clock(&self) -> &SimClock {
        &self.clock
    }

    /// The simulation time up to which every event was processed.
    pub fn reached(&self) -> Instant {
        self.reached
    }

    pub(super) fn to_std(&self, t: Instant) -> std::time::Instant {
        self.clock.instant_of(t.micros().saturating_mul(1000))
    }

    /// Sets the horizon (ns): the time of what the runtime sends now, and nothing earlier.
    pub(super) fn hold_at(&self, ns: u64) {
        if let Some(h) = &self.horizon {
            h.set(ns);
        }
    }

    /// The horizon while waiting: the next own deadline (frames delivered meanwhile hold the
    /// bus at their own times).
    pub(super) fn hold_next(&self) {
        let next = self.deadline().map_or(u64::MAX, |t| {
            t.max(self.reached).micros().saturating_mul(1000)
        });
        self.hold_at(next);
    }

    /// Runs every event up to simulation time `t` on the caller's thread, in time order,
    /// without sleeping: the co-simulation entry point (FMI `doStep`, SIL Kit; docs/CLOCK.md).
    /// A stepped clock is moved on to `t` first; powers the sensors on at the first call if
    /// nobody did. Control requests waiting are answered at `t`. Two runs with the same inputs
    /// give the same frames at the same times.
    pub fn advance_to(&mut self, t: Instant) -> io::Result<()> {
        if self.clock.driver() == Driver::Stepped {
            self.clock
                .step_to(t.micros().saturating_mul(1000))
                .map_err(io::Error::other)?;
        }
        if !self.started {
            self.power_on_all();
        }
        let now = self.advance(t)?;
        while let Ok(msg) = self.rx.try_recv() {
            if let Msg::Request(req, reply) = msg {
                self.hold_at(now.micros() * 1000);
                let answer = self.handle_request(req, now);
                self.route(now);
                self.hold_next();
                let _ = reply.send(answer);
            }
        }
        Ok(())
    }

    /// Carries out a control request on the caller's thread at the time reached, as
    /// [`Runtime::advance_to`] does with the requests waiting: a co-simulation driver that also
    /// steps the runtime (FMI `doStep`) cannot wait on a [`super::ControlHandle`].
    pub fn request_now(&mut self, req: Request) -> Value {
        let now = self.reached;
        self.hold_at(now.micros() * 1000);
        let answer = self.handle_request(req, now);
        self.route(now);
        self.hold_next();
        answer
    }

    /// The runtime's next own event (measurement cycle, node timer, held SDO answer, boot…),
    /// `None` when it has none: where a co-simulation step may end early (FMI early return).
    pub fn next_event(&self) -> Option<Instant> {
        self.deadline()
    }

    /// Processes every event up to `limit` in time order: for each own deadline `e`, the bus
    /// runs to `e` and the frames it delivered up to then are handled each at its own time,
    /// then the cycles and timers due at `e` run and what the nodes send is stamped `e`
    /// (docs/CLOCK.md). Returns the time reached (`limit`, or later if already there).
    pub(super) fn advance(&mut self, limit: Instant) -> io::Result<Instant> {
        let limit = limit.max(self.reached);
        self.skip_after_long_stall(limit);
        // The same deadline again and again would be a bug (a timer that does not move on);
        // bounded so that it cannot hang the runtime.
        let (mut last, mut repeats) = (None, 0u32);
        loop {
            let due = self.deadline().filter(|&e| e <= limit);
            let step = due.map_or(limit, |e| e.max(self.reached));
            self.hold_at(step.micros() * 1000);
            self.take_frames(step)?;
            let Some(_) = due else { break };
            if last == Some(step) {
                repeats += 1;
                if repeats > 1000 {
                    tracing::warn!(at = ?step, "a deadline did not move on; the runtime goes on");
                    break;
                }
            } else {
                (last, repeats) = (Some(step), 0);
            }
            self.reached = step;
            self.hold_at(step.micros() * 1000);
            if self.clock.driver() == Driver::Wall {
                let wall = self.clock.wall_elapsed() / 1000;
                self.events_late.record(wall.saturating_sub(step.micros()));
            }
            self.turn(step);
        }
        self.reached = limit.max(self.reached);
        self.hold_next();
        Ok(self.reached)
    }

    /// The simulation time of a received frame: its end of frame on a bus with this clock,
    /// else when it was received (wall clock; a peer's clock ahead of ours counts as now),
    /// never before the time already reached.
    pub(super) fn frame_time(&self, rx: &crate::can::RxFrame) -> Instant {
        let ns = self.clock.nanos_of(rx.timestamp).unwrap_or(0);
        Instant::from_micros(ns / 1000)
            .min(self.now())
            .max(self.reached)
    }

    /// Lets the bus run to `upto` and handles the frames it delivered up to then, each at its
    /// own time; a later one is kept for its time.
    pub(super) fn take_frames(&mut self, upto: Instant) -> io::Result<()> {
        loop {
            let rx = match self.stash.take() {
                Some(rx) => rx,
                None => {
                    self.transport.sync_bus();
                    match self.transport.try_recv()? {
                        Some(rx) => rx,
                        None => return Ok(()),
                    }
                }
            };
            let t = self.frame_time(&rx);
            if t > upto {
                self.stash = Some(rx);
                return Ok(());
            }
            self.received = true;
            let stamp = self.clock.nanos_of(rx.timestamp).unwrap_or(0);
            if self.clock.driver() == Driver::Wall {
                let wall = self.clock.wall_elapsed();
                self.frames_late.record(wall.saturating_sub(stamp) / 1000);
            }
            self.reached = t;
            // An answer leaves at the frame's own time (the bus waits there for it).
            self.hold_at(stamp.max(t.micros() * 1000));
            self.deliver(&rx.frame, None, t);
            self.route(t);
            if let Some(h) = &self.horizon {
                h.taken(stamp);
            }
            self.hold_at(upto.micros() * 1000);
        }
    }

    /// A runtime stopped for longer than the clock's stall bound (a suspended machine, a
    /// debugger) no longer holds the bus, which went on without it: it does not replay what it
    /// missed but skips to `limit`, counting the measurement cycles never made.
    pub(super) fn skip_after_long_stall(&mut self, limit: Instant) {
        if self.clock.driver() != Driver::Wall {
            return;
        }
        let bound = self.clock.stall_bound() / 1000;
        if limit.micros() <= self.reached.micros().saturating_add(bound) {
            return;
        }
        let behind_ms = (limit.micros() - self.reached.micros()) / 1000;
        let mut missed_max = 0;
        for i in 0..self.devices.len() {
            if self.powered[i] {
                missed_max = missed_max.max(self.devices[i].skip_cycles(limit));
            }
        }
        tracing::warn!(
            behind_ms,
            bound_ms = bound / 1000,
            missed = missed_max,
            "the runtime was stopped longer than the stall bound: measurement cycles skipped"
        );
        self.reached = limit;
    }
}
