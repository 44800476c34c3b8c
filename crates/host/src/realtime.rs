//! Real-time scheduling for the host process (`canpos --rt-priority N …`).
//!
//! The runtime sleeps on absolute deadlines and wakes within ~10–15 µs on an idle machine. On
//! a machine that is also compiling or running tests, an ordinary (`SCHED_OTHER`) thread can
//! be kept off the CPU for many periods, and the sensors then skip event-timer periods as a
//! late real sensor would. A hardware-in-the-loop rig runs the twin like any real-time task:
//! `SCHED_FIFO` at a priority above the ordinary load, and all memory locked so that no page
//! fault (e.g. of a code page dropped from the page cache under I/O load) stalls a period.

use std::io;
use std::sync::atomic::{AtomicU8, Ordering};

/// The priority given to runtime threads (0: real-time scheduling not requested).
static RUNTIME_PRIORITY: AtomicU8 = AtomicU8::new(0);

/// Puts the process under `SCHED_FIFO` and locks its current and future memory (`mlockall`).
/// Call it before starting threads: threads inherit the policy. The calling thread (and so
/// every helper thread started later: hub, control, observers) gets `priority − 1`; runtime
/// threads raise themselves to `priority` ([`runtime_thread`]), so that no helper of the same
/// process can hold the CPU a timed wake-up needs (equal SCHED_FIFO priorities never preempt
/// each other). Needs root or `CAP_SYS_NICE` / `CAP_IPC_LOCK` (or `rtprio` / `memlock` limits).
pub fn enter(priority: u8) -> io::Result<()> {
    if !(2..=99).contains(&priority) {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("real-time priority {priority} is outside 2…99"),
        ));
    }
    set_fifo(priority - 1)?;
    // SAFETY: mlockall has no memory-safety preconditions.
    if unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) } != 0 {
        let e = io::Error::last_os_error();
        return Err(io::Error::new(
            e.kind(),
            format!("mlockall: {e} (needs root, CAP_IPC_LOCK or a memlock limit)"),
        ));
    }
    RUNTIME_PRIORITY.store(priority, Ordering::Relaxed);
    Ok(())
}

/// Raises the calling runtime thread to the priority given to [`enter`]; does nothing when
/// real-time scheduling was not requested.
pub fn runtime_thread() -> io::Result<()> {
    match RUNTIME_PRIORITY.load(Ordering::Relaxed) {
        0 => Ok(()),
        p => set_fifo(p),
    }
}

/// `SCHED_FIFO` at `priority` for the calling thread (threads it starts inherit it).
fn set_fifo(priority: u8) -> io::Result<()> {
    // SAFETY: a plain system call on the calling thread with an initialised parameter block.
    let rc = unsafe {
        let param = libc::sched_param {
            sched_priority: i32::from(priority),
        };
        libc::sched_setscheduler(0, libc::SCHED_FIFO, &param)
    };
    if rc != 0 {
        let e = io::Error::last_os_error();
        return Err(io::Error::new(
            e.kind(),
            format!("SCHED_FIFO {priority}: {e} (needs root, CAP_SYS_NICE or an rtprio limit)"),
        ));
    }
    Ok(())
}

/// The calling thread's scheduling policy and priority (`SCHED_FIFO` is 1).
pub fn current() -> (i32, i32) {
    // SAFETY: plain system calls; `param` is written by the kernel.
    unsafe {
        let mut param = libc::sched_param { sched_priority: 0 };
        let policy = libc::sched_getscheduler(0);
        libc::sched_getparam(0, &mut param);
        (policy, param.sched_priority)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn out_of_range_is_refused_and_nothing_changes_unless_requested() {
        assert_eq!(enter(1).unwrap_err().kind(), io::ErrorKind::InvalidInput);
        assert_eq!(enter(100).unwrap_err().kind(), io::ErrorKind::InvalidInput);
        assert_ne!(current().0, libc::SCHED_FIFO);
        // Not requested: a runtime thread stays as it is.
        runtime_thread().unwrap();
        assert_ne!(current().0, libc::SCHED_FIFO);
    }
}
