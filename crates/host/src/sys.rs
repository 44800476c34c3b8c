//! Low-level helpers of the host's threads, below every layer that uses them: precise
//! absolute sleeps, the timer slack of a timing thread, and the warning for a socket bound
//! beyond this machine.

use std::io;
use std::time::Duration;

/// Sets this thread's timer slack to 1 ns: without it, Linux may delay every timed wake by up
/// to the default 50 µs slack.
pub fn set_timer_slack_1ns() {
    // SAFETY: prctl with PR_SET_TIMERSLACK takes one integer argument and touches no memory.
    let r = unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0) };
    if r != 0 {
        tracing::debug!(error = %io::Error::last_os_error(), "PR_SET_TIMERSLACK failed");
    }
}

/// The last stretch before a deadline that [`sleep_until_precise`] spins instead of sleeping.
/// On the 2-core benchmark VM an absolute `clock_nanosleep` wakes 20–30 µs late (median), a
/// spin ends within a microsecond; at 2 deadlines per ms the spin costs a few % of one core.
pub const SPIN_TAIL: Duration = Duration::from_micros(50);

/// [`sleep_until`] to [`SPIN_TAIL`] before `t`, then a spin on the monotonic clock until `t`.
pub fn sleep_until_precise(t: std::time::Instant) {
    if let Some(early) = t.checked_sub(SPIN_TAIL) {
        sleep_until(early);
    }
    while std::time::Instant::now() < t {
        std::hint::spin_loop();
    }
}

/// Sleeps until `t` on the monotonic clock with an absolute deadline (no drift from computing
/// relative timeouts, restarts after signals).
pub fn sleep_until(t: std::time::Instant) {
    // std::time::Instant is CLOCK_MONOTONIC on Linux; rebuild the absolute timespec from the
    // current reading of that clock plus the remaining duration.
    let remaining = t.saturating_duration_since(std::time::Instant::now());
    if remaining.is_zero() {
        return;
    }
    let mut now = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec into the pointer we own.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut now) };
    let total_ns = now.tv_nsec as u128 + remaining.as_nanos();
    let ts = libc::timespec {
        tv_sec: now.tv_sec + (total_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (total_ns % 1_000_000_000) as libc::c_long,
    };
    loop {
        // SAFETY: `ts` is a valid timespec; the remainder pointer may be null for TIMER_ABSTIME.
        let r = unsafe {
            libc::clock_nanosleep(
                libc::CLOCK_MONOTONIC,
                libc::TIMER_ABSTIME,
                &ts,
                std::ptr::null_mut(),
            )
        };
        if r != libc::EINTR {
            return;
        }
    }
}

/// Warns when `addr` is reachable from other machines: neither the socketcand hub nor the
/// control interface has authentication. One text for every place that binds (`what` names
/// it, e.g. "the bus").
pub fn warn_if_exposed(addr: std::net::SocketAddr, what: &str) {
    if !addr.ip().is_loopback() {
        tracing::warn!(%addr, "{what} is reachable from the network (no authentication); bind to 127.0.0.1 unless that is intended");
    }
}
