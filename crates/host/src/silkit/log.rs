//! SIL Kit's own log, forwarded into canpos's (D53).
//!
//! SIL Kit's C API has no log callback; its participant configuration has sinks (Stdout, File,
//! Remote). A canpos participant gets a **File** sink in **Json** format, written into a
//! private directory canpos creates for it (mode 0700, removed when the participant is gone),
//! flushed at every record. A thread of canpos reads the file as it grows and forwards each
//! record into canpos's log (`tracing`) at its SIL Kit level; stdout, where a tool's data goes,
//! is never touched.
//!
//! Two records matter to a user of a simulated network, and canpos says them in its own words
//! (SIL Kit's records are then forwarded at DEBUG, not twice):
//! - the CAN controller found the network simulator of its network (SIL Kit: "Controller … is
//!   using the simulated network … network simulator 'X'"): INFO `network NAME: simulated by
//!   'X' (bit-timed)`;
//! - the simulator left (SIL Kit: "The network simulator for controller … left the
//!   simulation"): WARN `network NAME: the network simulator 'X' left; SIL Kit's own untimed
//!   bus carries the frames now`.
//!
//! The same records are the signal [`SilkitLog::wait_simulated`] gives the CAN transport: they
//! are written by SIL Kit at the moment the controller switches to or from the simulator.
//!
//! **Bounds.** A line longer than [`MAX_LINE`] is cut there (the rest skipped up to its end);
//! the file is emptied once it has been read past [`MAX_FILE`] (SIL Kit appends to it, so its
//! next record starts the file again; a record written in the instant between the last read
//! and the truncation is lost, which needs a MiB of SIL Kit records first).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{self, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// The longest record line kept (bytes); more is cut.
pub const MAX_LINE: usize = 16 * 1024;
/// The file is emptied once read past this size (bytes).
pub const MAX_FILE: u64 = 1024 * 1024;
/// How often the reader thread looks at the file.
pub const POLL: Duration = Duration::from_millis(20);

/// What SIL Kit's records said about the network simulator, per controller.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SimulatorState {
    /// Per controller name: its network and the simulator now carrying it (`None`: SIL Kit's
    /// own bus, after a simulator left).
    pub controllers: BTreeMap<String, (String, Option<String>)>,
    /// How many times a simulator appeared (for any controller).
    pub arrivals: u64,
    /// How many times a simulator left.
    pub departures: u64,
}

/// A SIL Kit record recognised by canpos.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// The controller routes its frames to the network simulator now.
    Simulated {
        /// The controller's name.
        controller: String,
        /// The network's name.
        network: String,
        /// The simulator's participant name.
        simulator: String,
    },
    /// The network simulator of the controller's network left.
    SimulatorLeft {
        /// The controller's name.
        controller: String,
    },
}

/// Recognises SIL Kit 5.0's two controller records (CanController.cpp).
pub fn event_of(msg: &str) -> Option<Event> {
    if let Some(rest) = msg.strip_prefix("Controller '") {
        let (controller, rest) = rest.split_once("' is using the simulated network '")?;
        let (network, rest) =
            rest.split_once("' and will route all messages to the network simulator '")?;
        let simulator = rest.strip_suffix('\'')?;
        return Some(Event::Simulated {
            controller: controller.into(),
            network: network.into(),
            simulator: simulator.into(),
        });
    }
    let rest = msg.strip_prefix("The network simulator for controller '")?;
    let (controller, rest) = rest.split_once('\'')?;
    rest.starts_with(" left the simulation")
        .then(|| Event::SimulatorLeft {
            controller: controller.into(),
        })
}

/// One record of the Json file: level, message and key-values (`None` for a line that is not
/// such a record; it is forwarded as it is).
fn parse_record(line: &str) -> Option<(String, String)> {
    let v: serde_json::Value = serde_json::from_str(line).ok()?;
    let lvl = v.get("lvl")?.as_str()?.to_string();
    let mut msg = v.get("msg")?.as_str()?.to_string();
    if let Some(kv) = v.get("kv").and_then(|k| k.as_object()) {
        for (k, v) in kv {
            let v = v.as_str().map_or_else(|| v.to_string(), str::to_string);
            msg.push_str(&format!(" {k}={v}"));
        }
    }
    Some((lvl, msg))
}

/// The state the reader thread and the waiters share.
struct Inner {
    participant: String,
    dir: PathBuf,
    tail: Mutex<Tail>,
    state: Mutex<SimulatorState>,
    changed: Condvar,
    stop: AtomicBool,
    /// Forward records at DEBUG only (a participant that failed to join: its error carries
    /// SIL Kit's reason already).
    quiet: AtomicBool,
}

/// Where the reader is in the file.
#[derive(Default)]
struct Tail {
    file: Option<File>,
    pos: u64,
    /// The unfinished last line.
    partial: Vec<u8>,
    /// The current line was cut at [`MAX_LINE`]: skip to its end.
    skipping: bool,
}

/// SIL Kit's log of one participant, forwarded into canpos's; the directory is removed on
/// drop (after the participant is destroyed: the last records are forwarded then).
pub struct SilkitLog {
    inner: Arc<Inner>,
    thread: Option<std::thread::JoinHandle<()>>,
}

static SEQ: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);

impl SilkitLog {
    /// Creates the private directory for `participant`'s records (under the temporary
    /// directory, mode 0700).
    pub fn create(participant: &str) -> io::Result<SilkitLog> {
        Self::create_in(&std::env::temp_dir(), participant)
    }

    /// As [`SilkitLog::create`], under `parent`.
    pub fn create_in(parent: &Path, participant: &str) -> io::Result<SilkitLog> {
        use std::os::unix::fs::DirBuilderExt;
        let dir = parent.join(format!(
            "canpos-silkit-log-{}-{}",
            std::process::id(),
            SEQ.fetch_add(1, Ordering::Relaxed)
        ));
        // Not `recursive`: an existing directory (someone else's) is an error, not reused.
        std::fs::DirBuilder::new().mode(0o700).create(&dir)?;
        Ok(SilkitLog {
            inner: Arc::new(Inner {
                participant: participant.to_string(),
                dir,
                tail: Mutex::new(Tail::default()),
                state: Mutex::new(SimulatorState::default()),
                changed: Condvar::new(),
                stop: AtomicBool::new(false),
                quiet: AtomicBool::new(false),
            }),
            thread: None,
        })
    }

    /// The directory the records are written to.
    pub fn dir(&self) -> &Path {
        &self.inner.dir
    }

    /// `base` (a participant configuration in JSON) with its `Logging` replaced by this
    /// log's File sink (Json, level Info, flushed at every record).
    pub fn configuration(&self, base: &str) -> Result<String, String> {
        let mut v: serde_json::Value =
            serde_json::from_str(base).map_err(|e| format!("participant configuration: {e}"))?;
        let obj = v
            .as_object_mut()
            .ok_or("participant configuration: not a JSON object")?;
        let log_name = self.inner.dir.join("silkit");
        let log_name = log_name
            .to_str()
            .ok_or_else(|| format!("{}: not UTF-8", self.inner.dir.display()))?;
        obj.insert(
            "Logging".into(),
            serde_json::json!({
                "FlushLevel": "Trace",
                "Sinks": [{"Type": "File", "Format": "Json", "Level": "Info", "LogName": log_name}],
            }),
        );
        Ok(v.to_string())
    }

    /// Starts the reader thread (once the participant exists).
    pub fn start(&mut self) {
        if self.thread.is_some() {
            return;
        }
        let inner = self.inner.clone();
        self.thread = std::thread::Builder::new()
            .name("silkit-log".into())
            .spawn(move || {
                while !inner.stop.load(Ordering::SeqCst) {
                    inner.pump();
                    std::thread::sleep(POLL);
                }
            })
            .map_err(|e| {
                tracing::warn!(participant = %self.inner.participant,
                    "SIL Kit's log is not forwarded: cannot start a thread: {e}")
            })
            .ok();
    }

    /// Forwards the records written so far at DEBUG only (a participant that failed to
    /// join: the error carries SIL Kit's reason).
    pub fn quiet(&self) {
        self.inner.quiet.store(true, Ordering::SeqCst);
    }

    /// Reads and forwards what SIL Kit has written so far.
    pub fn pump(&self) {
        self.inner.pump();
    }

    /// What the records said so far about the network simulator.
    pub fn state(&self) -> SimulatorState {
        self.inner.pump();
        lock(&self.inner.state).clone()
    }

    /// Waits up to `timeout` until `pred` holds for the state (reading the file meanwhile);
    /// returns the state then.
    pub fn wait_until(
        &self,
        timeout: Duration,
        pred: impl Fn(&SimulatorState) -> bool,
    ) -> SimulatorState {
        let deadline = Instant::now() + timeout;
        loop {
            self.inner.pump();
            let st = lock(&self.inner.state);
            let now = Instant::now();
            if pred(&st) || now >= deadline {
                return st.clone();
            }
            // Woken by the reader thread; a short wait also when it is not running.
            let wait = (deadline - now).min(POLL);
            let _ = self.inner.changed.wait_timeout(st, wait);
        }
    }

    /// Waits up to `timeout` for `controller` to be simulated; the simulator's name.
    pub fn wait_simulated(&self, controller: &str, timeout: Duration) -> Option<String> {
        let st = self.wait_until(timeout, |s| {
            s.controllers.get(controller).is_some_and(|c| c.1.is_some())
        });
        st.controllers.get(controller).and_then(|c| c.1.clone())
    }
}

impl Inner {
    fn pump(&self) {
        let mut tail = lock(&self.tail);
        if tail.file.is_none() {
            // SIL Kit names it `silkit_PARTICIPANT_TIMESTAMP.jsonl`: the one file here.
            let Some(path) = std::fs::read_dir(&self.dir).ok().and_then(|d| {
                d.flatten()
                    .map(|e| e.path())
                    .find(|p| p.extension().is_some_and(|x| x == "jsonl"))
            }) else {
                return;
            };
            // Writable too: it is emptied past MAX_FILE.
            match std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .open(&path)
            {
                Ok(f) => tail.file = Some(f),
                Err(_) => return,
            }
        }
        let mut buf = [0u8; 8192];
        let mut lines: Vec<String> = Vec::new();
        loop {
            let Some(f) = tail.file.as_mut() else { return };
            let n = match f.read(&mut buf) {
                Ok(0) | Err(_) => break,
                Ok(n) => n,
            };
            tail.pos += n as u64;
            for &b in &buf[..n] {
                if b == b'\n' {
                    if !tail.skipping || !tail.partial.is_empty() {
                        lines.push(String::from_utf8_lossy(&tail.partial).into_owned());
                    }
                    tail.partial.clear();
                    tail.skipping = false;
                } else if tail.skipping {
                } else if tail.partial.len() < MAX_LINE {
                    tail.partial.push(b);
                } else {
                    lines.push(String::from_utf8_lossy(&tail.partial).into_owned() + "…");
                    tail.partial.clear();
                    tail.skipping = true;
                }
            }
        }
        if tail.pos > MAX_FILE && tail.partial.is_empty() {
            if let Some(f) = tail.file.as_mut() {
                // SIL Kit's file sink appends: its next record starts the emptied file.
                if f.set_len(0).is_ok() {
                    let _ = f.seek(SeekFrom::Start(0));
                    tail.pos = 0;
                }
            }
        }
        drop(tail);
        for line in lines {
            self.forward(&line);
        }
    }

    fn forward(&self, line: &str) {
        if line.trim().is_empty() {
            return;
        }
        let p = &self.participant;
        let Some((lvl, msg)) = parse_record(line) else {
            tracing::info!(participant = %p, "SIL Kit: {line}");
            return;
        };
        if let Some(ev) = event_of(&msg) {
            tracing::debug!(participant = %p, "SIL Kit: {msg}");
            self.note(ev);
            return;
        }
        if self.quiet.load(Ordering::SeqCst) {
            tracing::debug!(participant = %p, "SIL Kit {lvl}: {msg}");
            return;
        }
        match lvl.as_str() {
            "trace" => tracing::trace!(participant = %p, "SIL Kit: {msg}"),
            "debug" => tracing::debug!(participant = %p, "SIL Kit: {msg}"),
            "info" => tracing::info!(participant = %p, "SIL Kit: {msg}"),
            "warning" | "warn" => tracing::warn!(participant = %p, "SIL Kit: {msg}"),
            _ => tracing::error!(participant = %p, "SIL Kit {lvl}: {msg}"),
        }
    }

    fn note(&self, ev: Event) {
        let p = &self.participant;
        let mut st = lock(&self.state);
        match ev {
            Event::Simulated {
                controller,
                network,
                simulator,
            } => {
                tracing::info!(participant = %p, "network {network}: simulated by '{simulator}' (bit-timed)");
                st.arrivals += 1;
                st.controllers
                    .insert(controller, (network, Some(simulator)));
            }
            Event::SimulatorLeft { controller } => {
                let entry = st.controllers.entry(controller.clone()).or_default();
                let sim = entry.1.take().unwrap_or_else(|| "?".into());
                let network = if entry.0.is_empty() {
                    format!("of controller {controller}")
                } else {
                    entry.0.clone()
                };
                tracing::warn!(participant = %p,
                    "network {network}: the network simulator '{sim}' left; SIL Kit's own untimed bus carries the frames now");
                st.departures += 1;
            }
        }
        drop(st);
        self.changed.notify_all();
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Drop for SilkitLog {
    fn drop(&mut self) {
        self.inner.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        // The participant is gone: its last records are in the file.
        self.inner.pump();
        let _ = std::fs::remove_dir_all(&self.inner.dir);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    const SIMULATED: &str = "Controller 'CAN1' is using the simulated network 'can0' and will \
                             route all messages to the network simulator 'netsim'";
    const LEFT: &str = "The network simulator for controller 'CAN1' left the simulation. The \
                        controller is no longer simulated.";

    fn record(lvl: &str, msg: &str) -> String {
        format!(
            "{{\"ts\":\"1\",\"log\":\"th-11\",\"lvl\":\"{lvl}\", \"msg\": \"{}\" }}\n",
            msg.replace('\\', "\\\\").replace('"', "\\\"")
        )
    }

    /// A log whose SIL Kit file this test writes itself.
    fn log_with_file() -> (tempfile::TempDir, SilkitLog, File) {
        let parent = tempfile::tempdir().unwrap();
        let log = SilkitLog::create_in(parent.path(), "th-11").unwrap();
        let f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log.dir().join("silkit_th-11_2026-12-07_18-00-00.jsonl"))
            .unwrap();
        (parent, log, f)
    }

    #[test]
    fn the_two_controller_records_are_recognised_and_nothing_else() {
        assert_eq!(
            event_of(SIMULATED),
            Some(Event::Simulated {
                controller: "CAN1".into(),
                network: "can0".into(),
                simulator: "netsim".into(),
            })
        );
        assert_eq!(
            event_of(LEFT),
            Some(Event::SimulatorLeft {
                controller: "CAN1".into()
            })
        );
        for other in [
            "Controller 'CAN1' is using the simulated network 'can0'",
            "Participant 'netsim' has disconnected after gracefully shutting down",
            "The network simulator for controller 'CAN1' joined",
            "",
        ] {
            assert_eq!(event_of(other), None, "{other}");
        }
    }

    #[test]
    fn records_are_parsed_with_their_key_values_and_other_lines_are_not() {
        let line = "{\"ts\":\"1\",\"log\":\"p\",\"lvl\":\"info\", \"msg\": \"Creating \
                    participant\", \"kv\": {\"ParticipantName\":\"th-11\"} }";
        assert_eq!(
            parse_record(line),
            Some((
                "info".into(),
                "Creating participant ParticipantName=th-11".into()
            ))
        );
        assert_eq!(parse_record("not json"), None);
        assert_eq!(parse_record("{\"lvl\":\"info\"}"), None);
    }

    #[test]
    fn the_configuration_has_a_json_file_sink_in_the_private_directory() {
        use std::os::unix::fs::PermissionsExt;
        let parent = tempfile::tempdir().unwrap();
        let log = SilkitLog::create_in(parent.path(), "th-11").unwrap();
        let mode = std::fs::metadata(log.dir()).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o700);
        let c: serde_json::Value = serde_json::from_str(
            &log.configuration(super::super::PARTICIPANT_CONFIGURATION)
                .unwrap(),
        )
        .unwrap();
        let sink = &c["Logging"]["Sinks"][0];
        assert_eq!(sink["Type"], "File");
        assert_eq!(sink["Format"], "Json");
        assert_eq!(sink["LogName"], log.dir().join("silkit").to_str().unwrap());
        // The rest of canpos's configuration is kept.
        assert_eq!(c["Middleware"]["ConnectAttempts"], 1);
        assert!(log.configuration("[1]").is_err());
        let dir = log.dir().to_path_buf();
        drop(log);
        assert!(!dir.exists(), "the directory is removed with the log");
    }

    #[test]
    fn the_simulator_coming_and_going_is_followed_across_partial_writes() {
        let (_p, log, mut f) = log_with_file();
        assert_eq!(log.state(), SimulatorState::default());
        let r = record("info", SIMULATED);
        // Half a line: nothing yet.
        f.write_all(&r.as_bytes()[..20]).unwrap();
        assert_eq!(log.state().arrivals, 0);
        f.write_all(&r.as_bytes()[20..]).unwrap();
        assert_eq!(
            log.wait_simulated("CAN1", Duration::ZERO).as_deref(),
            Some("netsim")
        );
        f.write_all(record("warning", LEFT).as_bytes()).unwrap();
        let st = log.state();
        assert_eq!((st.arrivals, st.departures), (1, 1));
        assert_eq!(st.controllers["CAN1"], ("can0".into(), None));
        assert_eq!(log.wait_simulated("CAN1", Duration::ZERO), None);
        // Another controller's records are not this one's.
        assert_eq!(log.wait_simulated("CAN2", Duration::ZERO), None);
    }

    #[test]
    fn long_lines_are_cut_and_the_file_is_emptied_past_its_bound() {
        let (_p, log, mut f) = log_with_file();
        // A line far over MAX_LINE, then a record: the record still counts.
        f.write_all(&vec![b'x'; 3 * MAX_LINE]).unwrap();
        f.write_all(b"\n").unwrap();
        f.write_all(record("info", SIMULATED).as_bytes()).unwrap();
        assert_eq!(log.state().arrivals, 1);
        assert!(lock(&log.inner.tail).partial.is_empty());
        // Past MAX_FILE, the file is emptied once read; appended records start it again.
        let filler = record("debug", "filler");
        let n = (MAX_FILE as usize / filler.len()) + 2;
        f.write_all(filler.repeat(n).as_bytes()).unwrap();
        log.pump();
        let path = log.dir().join("silkit_th-11_2026-12-07_18-00-00.jsonl");
        assert_eq!(std::fs::metadata(&path).unwrap().len(), 0);
        f.write_all(record("warning", LEFT).as_bytes()).unwrap();
        assert_eq!(log.state().departures, 1);
        assert!(std::fs::metadata(&path).unwrap().len() < MAX_FILE);
    }
}
