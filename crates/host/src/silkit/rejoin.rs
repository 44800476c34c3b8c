//! A registry that goes away and comes back (issue 32 item 5, D55).
//!
//! SIL Kit's participants talk peer to peer once the registry introduced them, so a registry
//! that goes away stops nobody already joined. But a participant connects to its registry only
//! while it is created (`VAsioConnection::JoinSimulation`): it never registers again with a
//! registry that comes back, so the new registry does not know it, and participants that join
//! later (a `canpos sdo`, a new sensor) never meet it.
//!
//! **The signal.** SIL Kit reports the registry's departure as a peer shutdown of the peer named
//! [`REGISTRY_NAME`], which reaches the system monitor's participant-disconnected handler
//! (`Participant::GetSystemMonitor` registers it for every peer; `SystemMonitor.cpp` logs
//! "Connection to SIL Kit Registry was lost" on it). Its return has no signal at all (nothing in
//! a participant connects to the registry again), so [`Watch`] then probes the registry's
//! address with a plain TCP connect every [`PROBE_EVERY`], at most [`PROBE_TIMEOUT`] each,
//! until it answers.
//!
//! **The recovery.** Wall-clock mode: the participant leaves (its controller stopped, a
//! [`LINGER`](super::can::LINGER)) and joins again under the same name with a new CAN
//! controller; the transport's receiver, its runtime and the sensor's state go on untouched.
//! Frames sent between the two participants are lost and counted (`SilkitCan::lost_rejoining`). Each
//! transition is logged (WARN: gone; INFO: back, rejoined; WARN: a rejoin that failed, tried
//! again at the next probe). Synchronised mode cannot rejoin: the coordinated lifecycle and the
//! time synchronisation belong to the participants that started the simulation. Its
//! participants go on peer to peer while the registry is away, and when it comes back the
//! transport ends with an error naming what to restart.

use std::ffi::{c_void, CStr};
use std::net::{TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, RwLock};
use std::time::Duration;

use super::sys::{self, Api};
use super::{Error, Participant, RegistryUri};

/// The name SIL Kit gives the registry's peer (`VAsioConstants.hpp`'s
/// `REGISTRY_PARTICIPANT_NAME`).
pub const REGISTRY_NAME: &str = "SilKitRegistry";
/// How often a registry that went away is probed for its return.
pub const PROBE_EVERY: Duration = Duration::from_secs(1);
/// How long one probe (a TCP connect) may take.
pub const PROBE_TIMEOUT: Duration = Duration::from_secs(1);

/// A participant with its one CAN controller.
pub(super) struct Joined {
    /// The participant (destroyed on drop, after the controller was stopped).
    pub participant: Participant,
    /// The connections its system monitor tells of (D54, wall-clock mode); SIL Kit holds its
    /// address, so it is dropped after the participant (field order).
    pub connections: Option<Box<super::discovery::Connections>>,
    /// Its CAN controller (lives as long as the participant).
    pub controller: *mut sys::CanController,
}

/// The transport's current participant, replaced when it rejoins a registry.
pub(super) struct Link {
    // Dropped first (field order): the participant goes before anything its handlers use.
    cur: RwLock<Option<Joined>>,
    lost: AtomicU64,
}

// SAFETY: the controller pointer is only used through SIL Kit's thread-safe C API while its
// participant lives (under `cur`'s lock).
unsafe impl Send for Link {}
// SAFETY: as above.
unsafe impl Sync for Link {}

impl Link {
    /// A link to `joined`.
    pub fn new(joined: Joined) -> Link {
        Link {
            cur: RwLock::new(Some(joined)),
            lost: AtomicU64::new(0),
        }
    }

    /// Calls `f` with the current controller, or counts the frame as lost while there is none
    /// (between leaving and rejoining) and returns `Ok`: a frame sent then is lost as on a bus
    /// nobody listens to.
    pub fn with_controller(
        &self,
        f: impl FnOnce(*mut sys::CanController) -> Result<(), Error>,
    ) -> Result<(), Error> {
        let cur = self.cur.read().unwrap_or_else(|e| e.into_inner());
        match &*cur {
            Some(j) => f(j.controller),
            None => {
                self.lost.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
        }
    }

    /// Frames sent while the transport was between two participants.
    pub fn lost(&self) -> u64 {
        self.lost.load(Ordering::Relaxed)
    }

    /// Takes the current participant out (to leave it); frames sent from now on are lost.
    pub fn take(&self) -> Option<Joined> {
        self.cur.write().unwrap_or_else(|e| e.into_inner()).take()
    }

    fn put(&self, joined: Joined) {
        *self.cur.write().unwrap_or_else(|e| e.into_inner()) = Some(joined);
    }
}

/// Events for the watcher thread: the registry left, or the transport ends.
#[derive(Default)]
pub struct Watch {
    state: Mutex<WatchState>,
    cv: Condvar,
}

#[derive(Default)]
struct WatchState {
    registry_lost: bool,
    stop: bool,
}

impl Watch {
    /// The registry's peer shut down.
    pub fn registry_lost(&self) {
        self.state
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .registry_lost = true;
        self.cv.notify_all();
    }

    /// Ends the watcher thread.
    pub fn stop(&self) {
        self.state.lock().unwrap_or_else(|e| e.into_inner()).stop = true;
        self.cv.notify_all();
    }

    /// Waits until the registry is lost (`true`) or the watcher stops (`false`).
    fn wait_lost(&self) -> bool {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        while !s.stop && !s.registry_lost {
            s = self.cv.wait(s).unwrap_or_else(|e| e.into_inner());
        }
        s.registry_lost = false;
        !s.stop
    }

    /// Waits `d` or until the watcher stops (`false`).
    fn pause(&self, d: Duration) -> bool {
        let s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let (s, _) = self
            .cv
            .wait_timeout_while(s, d, |s| !s.stop)
            .unwrap_or_else(|e| e.into_inner());
        !s.stop
    }
}

/// The participant-disconnected handler of a wall-clock participant's system monitor: only the
/// registry's departure matters here (`ctx` is a [`Watch`]).
unsafe extern "C" fn on_peer_left(
    ctx: *mut c_void,
    _m: *mut sys::SystemMonitor,
    info: *const sys::ParticipantConnectionInformation,
) {
    // SAFETY: `ctx` is the `Watch` the transport keeps alive until its participants are gone;
    // `info` and its name are valid during the call (Orchestration.h).
    let watch = unsafe { &*(ctx as *const Watch) };
    if unsafe { is_registry(info) } {
        watch.registry_lost();
    }
}

/// Whether a disconnected participant is the registry.
///
/// # Safety
/// `info` is null or valid, with a null or NUL-terminated name.
pub(super) unsafe fn is_registry(info: *const sys::ParticipantConnectionInformation) -> bool {
    // SAFETY: the caller's guarantee.
    unsafe { info.as_ref() }
        .filter(|i| !i.participant_name.is_null())
        .is_some_and(|i| {
            unsafe { CStr::from_ptr(i.participant_name) }.to_bytes() == REGISTRY_NAME.as_bytes()
        })
}

/// Watches a participant's registry with its system `monitor` (SIL Kit allows one monitor a
/// participant, `Participant::CreateSystemMonitor`: whoever else needs it shares this one),
/// telling `watch` when it leaves. `watch` must outlive the participant.
pub(super) fn watch_registry(
    api: &'static Api,
    monitor: *mut sys::SystemMonitor,
    watch: &Watch,
) -> Result<(), Error> {
    // SAFETY: a live monitor; the context outlives the participant.
    api.check(
        "SilKit_SystemMonitor_SetParticipantDisconnectedHandler",
        unsafe {
            (api.system_monitor_set_participant_disconnected_handler)(
                monitor,
                watch as *const Watch as *mut c_void,
                on_peer_left,
            )
        },
    )
}

/// Whether something listens at the registry's address (a TCP connect, closed at once).
pub fn registry_answers(uri: &RegistryUri) -> bool {
    let Ok(addrs) = (uri.host.as_str(), uri.port).to_socket_addrs() else {
        return false;
    };
    addrs
        .into_iter()
        .any(|a| TcpStream::connect_timeout(&a, PROBE_TIMEOUT).is_ok())
}

/// What a watcher does when the registry is back.
pub(super) enum OnReturn {
    /// Wall-clock mode: leave `Link`'s participant (with this function, which stops its
    /// controller and lingers) and join again with the other function.
    Rejoin {
        link: Arc<Link>,
        leave: Box<dyn Fn(Joined) + Send>,
        join: Box<dyn Fn() -> Result<Joined, Error> + Send>,
    },
    /// Synchronised mode: end the transport with this reason.
    End(Box<dyn Fn(String) + Send>),
}

/// The watcher thread's body: for each departure of the registry, a WARN, probes until it is
/// back, then the recovery of `on_return`. Ends when `watch` stops.
pub(super) fn watcher(watch: Arc<Watch>, registry: RegistryUri, name: String, on_return: OnReturn) {
    while watch.wait_lost() {
        let mut failures = 0u64;
        match &on_return {
            OnReturn::Rejoin { .. } => tracing::warn!(participant = %name,
                "SIL Kit: the registry at {registry} went away: frames go on peer to peer among \
                 the participants already joined, none can join until it is back; {name} rejoins \
                 it then (probed every {PROBE_EVERY:?})"),
            OnReturn::End(_) => tracing::warn!(participant = %name,
                "SIL Kit: the registry at {registry} went away: the synchronised simulation goes \
                 on among the participants already joined, none can join it"),
        }
        loop {
            if !watch.pause(PROBE_EVERY) {
                return;
            }
            if !registry_answers(&registry) {
                continue;
            }
            match &on_return {
                OnReturn::End(end) => {
                    end(format!(
                        "the registry at {registry} came back, but a synchronised participant \
                         cannot rejoin a running simulation (its coordinated lifecycle and time \
                         synchronisation belong to the participants that started it): restart \
                         the synchronised participants and the system controller \
                         (sil-kit-system-controller) on it"
                    ));
                    return;
                }
                OnReturn::Rejoin { link, leave, join } => {
                    tracing::info!(participant = %name,
                        "SIL Kit: the registry at {registry} is back: {name} leaves and joins it again");
                    let before = link.lost();
                    if let Some(old) = link.take() {
                        leave(old);
                    }
                    match join() {
                        Ok(j) => {
                            link.put(j);
                            tracing::info!(participant = %name, lost = link.lost() - before,
                                "SIL Kit: rejoined the registry at {registry} as {name} ({} frame(s) \
                                 sent meanwhile were lost)", link.lost() - before);
                            break;
                        }
                        Err(e) => {
                            // Said at the 1st, 2nd, 4th… failure: something else may listen
                            // at the address for good.
                            failures += 1;
                            if failures.is_power_of_two() {
                                tracing::warn!(participant = %name, failures,
                                    "SIL Kit: rejoining the registry at {registry} as {name} \
                                     failed (frames are lost until it succeeds; tried again \
                                     every {PROBE_EVERY:?}): {e}");
                            }
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::ffi::CString;

    fn info(name: &CString) -> sys::ParticipantConnectionInformation {
        sys::ParticipantConnectionInformation {
            header: sys::StructHeader::new(0),
            participant_name: name.as_ptr(),
        }
    }

    #[test]
    fn only_the_registry_s_departure_counts() {
        let reg = CString::new(REGISTRY_NAME).unwrap();
        let other = CString::new("SilKitRegistry2").unwrap();
        // SAFETY: valid structs with NUL-terminated names, or null.
        unsafe {
            assert!(is_registry(&info(&reg)));
            assert!(!is_registry(&info(&other)));
            assert!(!is_registry(std::ptr::null()));
        }
    }

    #[test]
    fn the_probe_tells_a_listening_address_from_a_closed_one() {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let uri = RegistryUri {
            host: "127.0.0.1".into(),
            port: l.local_addr().unwrap().port(),
        };
        assert!(registry_answers(&uri));
        drop(l);
        assert!(!registry_answers(&uri));
    }

    #[test]
    fn a_watch_reports_a_departure_once_and_ends_on_stop() {
        let w = Watch::default();
        w.registry_lost();
        assert!(w.wait_lost());
        w.stop();
        assert!(!w.wait_lost());
        assert!(!w.pause(Duration::from_secs(3600)));
    }
}
