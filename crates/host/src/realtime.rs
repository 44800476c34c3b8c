//! Real-time scheduling for the host process (`canpos --rt-priority N …`).
//!
//! The runtime sleeps on absolute deadlines and wakes within ~10–15 µs on an idle machine. On
//! a machine that is also compiling or running tests, an ordinary (`SCHED_OTHER`) thread can
//! be kept off the CPU for many periods, and the sensors then skip event-timer periods as a
//! late real sensor would. A hardware-in-the-loop rig runs the twin like any real-time task:
//! `SCHED_FIFO` at a priority above the ordinary load, and all memory locked so that no page
//! fault (e.g. of a code page dropped from the page cache under I/O load) stalls a period.

use std::io;

/// Puts the whole process under `SCHED_FIFO` at `priority` (1…99) and locks its current and
/// future memory (`mlockall`). Call it before starting threads: threads inherit the policy.
/// Needs root or `CAP_SYS_NICE` / `CAP_IPC_LOCK` (or an `rtprio` / `memlock` ulimit).
pub fn enter(priority: u8) -> io::Result<()> {
    if !(1..=99).contains(&priority) {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("real-time priority {priority} is outside 1…99"),
        ));
    }
    // SAFETY: plain system calls on this process with a valid, initialised parameter block.
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
            format!(
                "SCHED_FIFO priority {priority}: {e} (needs root, CAP_SYS_NICE or an rtprio limit)"
            ),
        ));
    }
    // SAFETY: mlockall has no memory-safety preconditions.
    if unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) } != 0 {
        let e = io::Error::last_os_error();
        return Err(io::Error::new(
            e.kind(),
            format!("mlockall: {e} (needs root, CAP_IPC_LOCK or a memlock limit)"),
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
    fn priority_out_of_range_is_refused_before_any_system_call() {
        assert_eq!(enter(0).unwrap_err().kind(), io::ErrorKind::InvalidInput);
        assert_eq!(enter(100).unwrap_err().kind(), io::ErrorKind::InvalidInput);
        // Nothing changed for this (test) process.
        assert_ne!(current().0, libc::SCHED_FIFO);
    }
}
