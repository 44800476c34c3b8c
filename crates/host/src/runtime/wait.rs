//! The runtime's precise waits (a channel select ended early, then an absolute sleep) and
//! the record of how late they woke ([`Lateness`]). Shared with the plain device's runtime.

use std::time::Duration;

use crossbeam_channel::{Receiver, Select};

pub use crate::sys::sleep_until_precise;

/// How long before a deadline the channel wait ends and the precise absolute sleep takes over.
/// A frame arriving in this window waits at most this long.
pub const EARLY_WAKE: Duration = Duration::from_micros(200);

/// Statistics of timed wake-ups: how late the thread woke after a deadline.
#[derive(Clone, Copy, Debug)]
pub struct Lateness {
    /// Histogram: `hist[k]` counts wake-ups `k` µs late (the last bucket: that or more).
    hist: [u32; 1001],
    /// Timed wake-ups measured.
    pub count: u64,
    /// Sum of lateness, µs.
    pub sum_us: u64,
    /// Largest lateness, µs.
    pub max_us: u64,
    /// Wake-ups later than 50 µs.
    pub over_50us: u64,
    /// Wake-ups later than 200 µs.
    pub over_200us: u64,
    /// Later than 1 ms.
    pub over_1ms: u64,
}

impl Default for Lateness {
    fn default() -> Self {
        Lateness {
            hist: [0; 1001],
            count: 0,
            sum_us: 0,
            max_us: 0,
            over_50us: 0,
            over_200us: 0,
            over_1ms: 0,
        }
    }
}

impl Lateness {
    pub(crate) fn record(&mut self, us: u64) {
        self.hist[us.min(1000) as usize] += 1;
        self.count += 1;
        self.sum_us += us;
        self.max_us = self.max_us.max(us);
        self.over_50us += u64::from(us > 50);
        self.over_200us += u64::from(us > 200);
        self.over_1ms += u64::from(us > 1000);
    }

    /// The lateness (µs) that fraction `q` (0…1) of the wake-ups did not exceed; capped at
    /// 1000 µs.
    pub fn quantile_us(&self, q: f64) -> u64 {
        let want = (self.count as f64 * q).ceil() as u64;
        let mut seen = 0u64;
        for (us, &n) in self.hist.iter().enumerate() {
            seen += u64::from(n);
            if seen >= want.max(1) {
                return us as u64;
            }
        }
        1000
    }

    /// Mean lateness in µs.
    pub fn mean_us(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.sum_us as f64 / self.count as f64
        }
    }
}

impl std::fmt::Display for Lateness {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} timed wake-ups, late by: median {} µs, p99 {} µs, mean {:.1} µs, max {} µs; {} over 50 µs, {} over 200 µs",
            self.count,
            self.quantile_us(0.5),
            self.quantile_us(0.99),
            self.mean_us(),
            self.max_us,
            self.over_50us,
            self.over_200us
        )
    }
}

/// Waits for a received frame, a message or a step of a stepped clock.
pub(super) fn wait_stepped<T>(
    frames: &Receiver<crate::can::RxFrame>,
    msgs: &Receiver<T>,
    steps: &Receiver<()>,
) {
    let mut sel = Select::new();
    sel.recv(frames);
    sel.recv(msgs);
    sel.recv(steps);
    // Readiness only: the loop takes frames and messages itself.
    let _ = sel.ready();
    let _ = steps.try_recv();
}

/// Waits for a received frame on `frames`, a message on `msgs`, or the absolute `target`: the
/// channel wait ends [`EARLY_WAKE`] before it and [`sleep_until_precise`] does the rest.
/// Returns how late the wake was when it slept to `target`, `None` when a channel woke it.
pub(crate) fn wait_until<T>(
    frames: &Receiver<crate::can::RxFrame>,
    msgs: &Receiver<T>,
    target: Option<std::time::Instant>,
) -> Option<Duration> {
    let early = target.map(|t| t.checked_sub(EARLY_WAKE).unwrap_or(t));
    let ready = {
        let mut sel = Select::new();
        sel.recv(frames);
        sel.recv(msgs);
        match early {
            Some(e) if e <= std::time::Instant::now() => None,
            Some(e) => sel.ready_deadline(e).ok(),
            None => Some(sel.ready()),
        }
    };
    if ready.is_some() {
        return None;
    }
    let t = target?;
    sleep_until_precise(t);
    Some(std::time::Instant::now().saturating_duration_since(t))
}
