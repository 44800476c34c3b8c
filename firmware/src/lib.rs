//! The portable part of the canpos TH firmware: the main loop that joins a CAN controller (any
//! [`embedded_can::nb::Can`] driver), a microsecond clock, a measurement source and the core's
//! [`Storage`] to one [`SensorNode`]. Nothing here knows the board; `main.rs` is the QEMU
//! mps2-an386 board (UART transport, SysTick, flash emulation). docs/FIRMWARE.md explains
//! what a port to a real MCU implements.
#![no_std]

pub mod slcan;

use canpos_encoder::Sample;
use canpos_models::{self as models, Model, SensorNode};
use canpos_stack::{Frame, Instant, Storage};

/// The model this firmware is built for: cargo feature `th` (default), `e-series` or `tmi`,
/// each of which builds only that model's table into canpos-models.
#[cfg(feature = "th")]
pub const MODEL: &Model = &models::th::TH;
/// The model this firmware is built for.
#[cfg(all(feature = "e-series", not(feature = "th")))]
pub const MODEL: &Model = &models::e_series::E_SERIES;
/// The model this firmware is built for.
#[cfg(all(feature = "tmi", not(feature = "th"), not(feature = "e-series")))]
pub const MODEL: &Model = &models::tmi::TMI;

/// The widest dictionary of [`MODEL`] (the two-channel TMI's for the TMI).
const WIDEST: &[canpos_stack::Entry] = {
    #[cfg(all(feature = "tmi", not(feature = "th"), not(feature = "e-series")))]
    let t = models::tmi::ENTRIES_TWO_CHANNELS;
    #[cfg(not(all(feature = "tmi", not(feature = "th"), not(feature = "e-series"))))]
    let t = MODEL.table.entries;
    t
};

/// Entries of `t` that storage keeps.
const fn stored(t: &[canpos_stack::Entry]) -> usize {
    let (mut n, mut i) = (0, 0);
    while i < t.len() {
        if !matches!(t[i].group, canpos_stack::od::Group::Volatile) {
            n += 1;
        }
        i += 1;
    }
    n
}

// The core's sizes (`CANPOS_MAX_ENTRIES`, `CANPOS_MAX_STORED`: `.cargo/config.toml` sets the
// TH's) are the model's own: a smaller value does not compile (the table's assert), a larger
// one would leave RAM unused. Another model: `CANPOS_MAX_ENTRIES=N CANPOS_MAX_STORED=M cargo
// build …` with its figures (docs/FIRMWARE.md).
const _: () = assert!(
    canpos_stack::config::MAX_ENTRIES == WIDEST.len(),
    "CANPOS_MAX_ENTRIES is not the model's number of entries (docs/FIRMWARE.md)"
);
const _: () = assert!(
    canpos_stack::config::RECORDS_MAX
        == stored(WIDEST) + canpos_stack::config::NODE_RECORDS + canpos_stack::config::APP_RECORDS,
    "CANPOS_MAX_STORED is not the model's number of stored entries (docs/FIRMWARE.md)"
);

/// Where the position comes from: the time-of-flight electronics on a real sensor.
pub trait MeasurementSource {
    /// The measurement of the cycle ending at `now`.
    fn sample(&mut self, now: Instant) -> Sample;
}

/// A free-running microsecond clock (SysTick, a hardware timer).
pub trait Clock {
    /// Microseconds since start-up.
    fn now(&self) -> Instant;
}

/// Most measurement cycles one pass of the main loop catches up on.
const MAX_CATCH_UP: u32 = 256;

/// One sensor: the node and the parts of the board it needs.
pub struct Firmware<C: embedded_can::nb::Can, M, S: Storage> {
    node: SensorNode<S>,
    can: C,
    /// A frame the controller had no room for: sent before any other.
    unsent: Option<C::Frame>,
    source: M,
    /// Next measurement cycle (µs since start-up).
    next_cycle: u64,
    cycle_us: u64,
}

impl<C, M, S> Firmware<C, M, S>
where
    C: embedded_can::nb::Can,
    M: MeasurementSource,
    S: Storage,
{
    /// A sensor of [`MODEL`] in its default configuration (TH: node-id 127, 125 kbit/s),
    /// powered off: place it where it stays (a static), then [`Firmware::power_on`], so the
    /// node is not copied.
    #[inline(always)]
    pub fn new(can: C, source: M, storage: S) -> Self {
        let model = MODEL;
        let cfg = model.configure(model.default_config);
        Firmware {
            node: SensorNode::new(model, cfg, storage),
            can,
            unsent: None,
            source,
            next_cycle: 0,
            cycle_us: cfg.cycle_us as u64,
        }
    }

    /// Power-on at `now`: the stored parameters are loaded, boot-up and the power-on EMCY
    /// are queued. Out of line, so what it needs on the stack is released afterwards.
    #[inline(never)]
    pub fn power_on(&mut self, now: Instant) {
        self.node.power_on(now);
        self.next_cycle = now.micros();
    }

    /// One pass of the main loop at `now`: the measurements of the cycles due, every received
    /// frame, the timers, every frame to send. Returns the instant the loop must run again
    /// by (the caller sleeps until then or the next interrupt). Out of line, so its frame is
    /// not part of `main`'s while `main` builds the node.
    ///
    /// The node's frames go to the controller after each received frame, so that its transmit
    /// queue (8 frames here) holds only what one frame sets off (a SYNC's TPDOs, say) and what
    /// the controller's mailboxes have no room for.
    #[inline(never)]
    pub fn step(&mut self, now: Instant) -> Instant {
        self.measure(now);
        self.transmit(now);
        while let Ok(f) = self.can.receive() {
            if let Some(f) = Frame::from_embedded(&f) {
                self.node.handle_frame(&f, now);
            }
            self.transmit(now);
        }
        let next = Instant::from_micros(self.next_cycle);
        if self.unsent.is_some() {
            // Try again at the next pass (the controller's TX interrupt wakes the loop).
            return now;
        }
        match self.node.poll_timeout() {
            Some(t) if t < next => t,
            _ => next,
        }
    }

    /// The measurements of the cycles due by `now`. Out of line (as is [`Firmware::transmit`]),
    /// so their locals are on the stack only while they run, not beneath a store.
    #[inline(never)]
    fn measure(&mut self, now: Instant) {
        // Every measurement cycle due by now, each at its own instant (a real sensor's capture
        // runs on its own timer; a loop that was late catches up rather than stretching a
        // cycle, which would show as a velocity jump). Times stay monotonic: every cycle here
        // lies after the previous pass's `now`.
        let mut late = 0;
        while self.next_cycle <= now.micros() && late < MAX_CATCH_UP {
            let t = Instant::from_micros(self.next_cycle);
            let s = self.source.sample(t);
            self.node.update_sample(&s, t);
            self.next_cycle += self.cycle_us;
            late += 1;
        }
        if self.next_cycle <= now.micros() {
            // Too far behind: the missed cycles are gone.
            self.next_cycle = now.micros() + self.cycle_us;
        }
    }

    /// Hands the node's frames to the controller until either runs out.
    #[inline(never)]
    fn transmit(&mut self, now: Instant) {
        // The node's timers run even while the controller is full, its queue holds what waits
        // (`nb::block!` would stall the node behind the bus).
        if self.unsent.is_some() {
            self.node.handle_timeout(now);
        }
        loop {
            let out = match self.unsent.take() {
                Some(f) => f,
                None => match self.node.poll(now) {
                    Some(f) => match f.to_embedded::<C::Frame>() {
                        Some(out) => out,
                        None => continue,
                    },
                    None => break,
                },
            };
            match self.can.transmit(&out) {
                // A lower-priority frame the controller gave back is lost (CAN arbitration
                // order beats queue order for it).
                Ok(_) => {}
                Err(nb::Error::WouldBlock) => {
                    self.unsent = Some(out);
                    break;
                }
                // A controller error drops the frame; the error counters are the driver's.
                Err(nb::Error::Other(_)) => {}
            }
        }
    }

    /// The node (for diagnostics).
    pub fn node(&self) -> &SensorNode<S> {
        &self.node
    }
}
