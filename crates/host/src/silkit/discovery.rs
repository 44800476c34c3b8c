//! Waiting for SIL Kit's discovery to settle before a wall-clock participant sends (D54).
//!
//! A CAN controller learns of its network's simulator through SIL Kit's service discovery,
//! asynchronously to `SilKit_Participant_Create` and to its own creation. Until then it runs
//! SIL Kit's trivial bus, and a controller that already routes through the simulator takes no
//! frame from it: a boot-up sent in that window is lost (seen when sensors, a master and
//! `canpos bus netsim` start together). So a wall-clock [`super::can::SilkitCan`] opens only
//! once discovery has settled:
//!
//! - **simulated**: SIL Kit's record "Controller … is using the simulated network …" (read
//!   from its log, [`super::log`]) came; with the simulator already known it is written during
//!   `SilKit_CanController_Create`, so there is no wait at all;
//! - **quiet**: else, once [`QUIET`] has passed both since the controller was created and since
//!   the last participant connected (SIL Kit's system monitor): services of the participants
//!   known at the join are discovered by then, and a simulator that joins at the same time
//!   connects to this participant before it announces its network, which restarts the wait;
//! - **bound**: at the latest after [`BOUND`] (participants that keep joining).
//!
//! Synchronised participants do not wait here: SIL Kit's time starts only when every required
//! participant is ready, and a simulator announces its networks before it gets ready.

use std::ffi::c_void;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::log::SilkitLog;
use super::sys;
use super::Participant;

/// How long discovery must have been quiet (no participant connecting, no simulator found).
pub const QUIET: Duration = Duration::from_millis(300);
/// The longest wait.
pub const BOUND: Duration = Duration::from_secs(2);

/// How discovery settled.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Settled {
    /// The controller routes through this network simulator.
    Simulated(String),
    /// No simulator; nothing joined for [`QUIET`].
    Quiet,
    /// [`BOUND`] passed with participants still joining.
    Bound,
    /// SIL Kit's log could not be read (no private directory): after [`QUIET`].
    NoLog,
}

/// The last participant connection SIL Kit's system monitor told of; kept alive as long as
/// the participant (SIL Kit holds its address).
pub struct Connections {
    last: Mutex<Instant>,
}

impl Connections {
    fn touch(&self) {
        *self.last.lock().unwrap_or_else(|e| e.into_inner()) = Instant::now();
    }

    fn last(&self) -> Instant {
        *self.last.lock().unwrap_or_else(|e| e.into_inner())
    }
}

unsafe extern "C" fn on_connected(
    ctx: *mut c_void,
    _m: *mut sys::SystemMonitor,
    _info: *const sys::ParticipantConnectionInformation,
) {
    // SAFETY: `ctx` is the boxed `Connections` its owner keeps until the participant is gone.
    let c = unsafe { &*(ctx as *const Connections) };
    c.touch();
}

/// Watches participant connections on `participant` through its system monitor `monitor`
/// (SIL Kit allows one a participant; its connected handler also reports those already
/// connected). The box must outlive the participant.
pub(super) fn watch_connections(
    participant: &Participant,
    monitor: *mut sys::SystemMonitor,
) -> Result<Box<Connections>, sys::Error> {
    let api = participant.api();
    type SetConnected = unsafe extern "C" fn(
        m: *mut sys::SystemMonitor,
        ctx: *mut c_void,
        h: sys::ParticipantDisconnectedHandler,
    ) -> sys::ReturnCode;
    // SAFETY: the header's signature (Orchestration.h), the same as the disconnected one's.
    let set: SetConnected =
        unsafe { api.symbol(b"SilKit_SystemMonitor_SetParticipantConnectedHandler\0") }?;
    let watch = Box::new(Connections {
        last: Mutex::new(Instant::now()),
    });
    let ctx = &*watch as *const Connections as *mut c_void;
    // SAFETY: a live monitor of a live participant; `ctx` outlives the participant (the
    // caller's promise).
    api.check(
        "SilKit_SystemMonitor_SetParticipantConnectedHandler",
        unsafe { set(monitor, ctx, on_connected) },
    )?;
    Ok(watch)
}

/// Waits until discovery has settled for `controller` (module doc), from `created` (when the
/// controller was created).
pub fn settle(
    log: Option<&SilkitLog>,
    connections: Option<&Connections>,
    controller: &str,
    created: Instant,
) -> Settled {
    settle_with(log, connections, controller, created, QUIET, BOUND)
}

fn settle_with(
    log: Option<&SilkitLog>,
    connections: Option<&Connections>,
    controller: &str,
    created: Instant,
    quiet: Duration,
    bound: Duration,
) -> Settled {
    let Some(log) = log else {
        std::thread::sleep(quiet.saturating_sub(created.elapsed()));
        return Settled::NoLog;
    };
    loop {
        let since = connections.map_or(created, |c| c.last().max(created));
        let now = Instant::now();
        let quiet_at = since + quiet;
        let bound_at = created + bound;
        let until = quiet_at.min(bound_at);
        if let Some(sim) = log.wait_simulated(controller, until.saturating_duration_since(now)) {
            return Settled::Simulated(sim);
        }
        let now = Instant::now();
        if now >= bound_at {
            return Settled::Bound;
        }
        // A connection during the wait moved the quiet point on: wait again.
        let since = connections.map_or(created, |c| c.last().max(created));
        if now >= since + quiet {
            return Settled::Quiet;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn a_simulator_already_in_the_log_settles_at_once() {
        let parent = tempfile::tempdir().unwrap();
        let log = SilkitLog::create_in(parent.path(), "th-11").unwrap();
        let mut f = std::fs::File::create(log.dir().join("silkit_th-11_x.jsonl")).unwrap();
        writeln!(
            f,
            "{{\"ts\":\"1\",\"log\":\"th-11\",\"lvl\":\"info\", \"msg\": \"Controller 'CAN1' is \
             using the simulated network 'can0' and will route all messages to the network \
             simulator 'netsim'\" }}"
        )
        .unwrap();
        // A bound of an hour: only the record can end this wait.
        let hour = Duration::from_secs(3600);
        let got = settle_with(Some(&log), None, "CAN1", Instant::now(), hour, hour);
        assert_eq!(got, Settled::Simulated("netsim".into()));
    }

    #[test]
    fn with_no_simulator_it_settles_after_the_quiet_time() {
        let parent = tempfile::tempdir().unwrap();
        let log = SilkitLog::create_in(parent.path(), "th-11").unwrap();
        // Created long enough ago: quiet at once, no simulator.
        let created = Instant::now() - Duration::from_secs(10);
        let got = settle_with(
            Some(&log),
            None,
            "CAN1",
            created,
            Duration::from_secs(1),
            Duration::from_secs(3600),
        );
        assert_eq!(got, Settled::Quiet);
        // Participants kept connecting until the bound.
        let c = Connections {
            last: Mutex::new(Instant::now() + Duration::from_secs(3600)),
        };
        let got = settle_with(
            Some(&log),
            Some(&c),
            "CAN1",
            created,
            Duration::from_secs(1),
            Duration::from_secs(5),
        );
        assert_eq!(got, Settled::Bound);
    }
}
