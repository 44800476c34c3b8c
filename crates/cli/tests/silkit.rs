//! canpos on Vector SIL Kit (docs/SILKIT.md): a `sil-kit-registry` on 127.0.0.1, two sensors
//! (TH, TMI) in separate `canpos run` processes, canpos's own master commands, the
//! synchronised mode under SIL Kit's system controller, and the faults of issue 32 item 5.
//! Needs `scripts/silkit.sh`; without it each test says so and passes, unless
//! `CANPOS_SILKIT_REQUIRED=1` (the test command sets it), where it fails.

mod common;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use canpos_host::silkit::{self, LocalRegistry};
use common::{run_in, text, Proc};

/// Wall-clock bound for a process to start or a command to finish on a loaded machine.
const LIMIT: Duration = Duration::from_secs(120);

fn have_silkit() -> bool {
    match silkit::api() {
        Ok(_) => true,
        Err(e) if std::env::var_os("CANPOS_SILKIT_REQUIRED").is_some_and(|v| v == "1") => {
            panic!("CANPOS_SILKIT_REQUIRED=1 but {e}")
        }
        Err(e) => {
            eprintln!("NOTE: SIL Kit test skipped: {e}");
            false
        }
    }
}

/// SIL Kit's `sil-kit-system-controller` waiting for `names`; killed on drop.
struct SystemController(Child);

impl SystemController {
    fn start(reg: &LocalRegistry, names: &[&str]) -> SystemController {
        let exe = silkit::sys::registry_executable()
            .expect("registry")
            .with_file_name("sil-kit-system-controller");
        let child = Command::new(exe)
            .arg("--connect-uri")
            .arg(reg.uri().to_string())
            .args(["--log", "off"])
            .args(names)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("system controller");
        SystemController(child)
    }
}

impl Drop for SystemController {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The line of `canpos sdo read`'s value in a tool's output, among its participant's log lines.
fn value_line(out: &str) -> Option<&str> {
    out.lines().find(|l| l.starts_with("0x"))
}

fn ok(dir: &Path, args: &[&str]) -> String {
    let o = run_in(dir, args, LIMIT);
    let t = text(&o);
    assert!(o.status.success(), "canpos {args:?}: {t}");
    t
}

#[test]
fn two_sensors_in_their_own_processes_serve_sdo_nmt_lss_fastscan_and_tpdos() {
    if !have_silkit() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let bus = format!("{}/can0", reg.uri());
    let state = d.to_str().unwrap();
    // The TH without a node-id: LSS fastscan finds it (the TMI has no fastscan, as its manual).
    let mut th = Proc::start(
        d,
        &[
            "run",
            "--model",
            "th",
            "--serial",
            "11",
            "--node-id",
            "255",
            "--bus",
            &bus,
            "--state-dir",
            state,
        ],
    );
    let mut tmi = Proc::start(
        d,
        &[
            "run",
            "--model",
            "tmi",
            "--serial",
            "12",
            "--node-id",
            "6",
            "--bus",
            &bus,
            "--state-dir",
            state,
        ],
    );
    // The participant is named after the sensor.
    th.wait_for("as th-11;", LIMIT);
    tmi.wait_for("as tmi-12;", LIMIT);

    // SDO: the TMI's device name.
    let name = ok(d, &["sdo", "--bus", &bus, "read", "6", "0x1008", "0"]);
    assert!(name.contains("\"TMI\""), "{name}");

    // LSS: fastscan, a node-id, back to waiting; NMT reset communication: the TH boots as
    // node 5. 500 ms per step (25 ms by default; ~48 steps wait it out, so ~25 s): an answer
    // crosses two SIL Kit participants' threads, and with 200 ms the confirmation timed out
    // in 2 runs of 5 on the loaded 2-core machine.
    let scan = ok(d, &["lss", "--bus", &bus, "fastscan", "--timeout", "500"]);
    assert!(scan.contains("serial 0x0000000B (11)"), "{scan}");
    ok(d, &["lss", "--bus", &bus, "set-node-id", "5"]);
    ok(d, &["lss", "--bus", &bus, "switch-global", "waiting"]);
    ok(d, &["nmt", "--bus", &bus, "reset-comm", "--node", "0"]);
    let serial = ok(d, &["sdo", "--bus", &bus, "read", "5", "0x1018", "4"]);
    assert!(serial.contains("0x0000000B (11)"), "{serial}");

    // NMT start: the TH's TPDO1 (0x185) flows.
    ok(d, &["nmt", "--bus", &bus, "start", "--node", "5"]);
    let rec = d.join("tpdo.log");
    ok(
        d,
        &[
            "record",
            "--bus",
            &bus,
            "--format",
            "candump",
            "--count",
            "20",
            rec.to_str().unwrap(),
        ],
    );
    let log = std::fs::read_to_string(&rec).unwrap();
    assert!(log.lines().any(|l| l.contains(" 185#")), "{log}");
    assert!(!th.output().contains("panicked") && !tmi.output().contains("panicked"));
}

/// One synchronised run: the two sensors operational from the start and a recorder, all under
/// a system controller; the recorder's first `count` frames (candump, simulated times).
fn synchronised_run(d: &Path, count: usize) -> Vec<String> {
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let _sc = SystemController::start(&reg, &["th-11", "tmi-12", "rec"]);
    let bus = format!("{}/can0", reg.uri());
    let state = d.to_str().unwrap();
    let _th = Proc::start(
        d,
        &[
            "run",
            "--model",
            "th",
            "--serial",
            "11",
            "--node-id",
            "5",
            "--nmt",
            "operational",
            "--bus",
            &bus,
            "--time",
            "sync",
            "--state-dir",
            state,
        ],
    );
    let _tmi = Proc::start(
        d,
        &[
            "run",
            "--model",
            "tmi",
            "--serial",
            "12",
            "--node-id",
            "6",
            "--nmt",
            "operational",
            "--bus",
            &bus,
            "--time",
            "sync",
            "--state-dir",
            state,
        ],
    );
    let rec = d.join("sync.log");
    let url = format!("{bus}?participant=rec&time=sync");
    ok(
        d,
        &[
            "record",
            "--bus",
            &url,
            "--format",
            "candump",
            "--count",
            &count.to_string(),
            rec.to_str().unwrap(),
        ],
    );
    std::fs::read_to_string(&rec)
        .unwrap()
        .lines()
        .map(str::to_string)
        .collect()
}

#[test]
fn the_synchronised_mode_gives_the_same_frames_at_the_same_simulated_times() {
    if !have_silkit() {
        return;
    }
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let first = synchronised_run(a.path(), 400);
    let second = synchronised_run(b.path(), 400);
    assert_eq!(first.len(), 400);
    // Simulated times: both boot-ups at 0, then the TPDOs on the 1 ms steps.
    assert!(
        first.contains(&"(0.000000) can0 705#00".to_string()),
        "{first:?}"
    );
    assert!(
        first.contains(&"(0.000000) can0 706#00".to_string()),
        "{first:?}"
    );
    assert!(
        first.iter().any(|l| l.starts_with("(0.001000) can0 185#")),
        "{first:?}"
    );
    assert_eq!(first, second, "two runs of the same scenario differ");
}

#[test]
fn a_participant_that_vanishes_in_synchronised_mode_ends_the_others_with_a_clear_error() {
    if !have_silkit() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let state = d.to_str().unwrap();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let _sc = SystemController::start(&reg, &["th-11", "tmi-12"]);
    let bus = format!("{}/can0", reg.uri());
    let sensor = |model: &str, serial: &str, node: &str| {
        Proc::start(
            d,
            &[
                "run",
                "--model",
                model,
                "--serial",
                serial,
                "--node-id",
                node,
                "--nmt",
                "operational",
                "--bus",
                &bus,
                "--time",
                "sync",
                "--state-dir",
                state,
            ],
        )
    };
    let mut th = sensor("th", "11", "5");
    let mut tmi = sensor("tmi", "12", "6");
    // The simulation runs: a wall-clock recorder (no part in the steps) sees TPDOs.
    ok(
        d,
        &[
            "record", "--bus", &bus, "--format", "candump", "--count", "20", "rec.log",
        ],
    );
    let file = d.join("th-11.bin");
    let before = std::fs::read(&file).expect("state file");
    // The TMI crashes: SIL Kit's time stops for good (its Error state); the TH must not wait
    // forever but end with the reason.
    tmi.stop();
    let code = th.wait_exit(LIMIT);
    let out = th.output();
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains("Error state"), "{out}");
    assert!(!out.contains("panicked"), "{out}");
    assert_eq!(std::fs::read(&file).unwrap(), before, "state file changed");
}

#[test]
fn a_synchronised_sensor_stopped_by_its_user_does_not_blame_the_system_controller() {
    if !have_silkit() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let _sc = SystemController::start(&reg, &["th-11"]);
    let bus = format!("{}/can0", reg.uri());
    let mut th = Proc::start(
        d,
        &[
            "run",
            "--model",
            "th",
            "--serial",
            "11",
            "--node-id",
            "5",
            "--nmt",
            "operational",
            "--bus",
            &bus,
            "--time",
            "sync",
            "--state-dir",
            d.to_str().unwrap(),
        ],
    );
    ok(
        d,
        &[
            "record", "--bus", &bus, "--format", "candump", "--count", "5", "rec.log",
        ],
    );
    // SIGTERM: canpos leaves SIL Kit itself (its own SilKit_LifecycleService_Stop).
    assert!(Command::new("kill")
        .args(["-TERM", &th.pid().to_string()])
        .status()
        .unwrap()
        .success());
    th.wait_exit(LIMIT);
    let out = th.output();
    assert!(out.contains("the participant left"), "{out}");
    assert!(!out.contains("system controller stopped"), "{out}");
}

#[test]
fn a_synchronised_sensor_without_a_system_controller_says_it_waits() {
    if !have_silkit() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let bus = format!("{}/can0", reg.uri());
    let mut th = Proc::start(
        d,
        &[
            "run",
            "--model",
            "th",
            "--serial",
            "11",
            "--node-id",
            "5",
            "--bus",
            &bus,
            "--time",
            "sync",
            "--state-dir",
            d.to_str().unwrap(),
        ],
    );
    // It waits (SIL Kit's time has not begun), and says for what.
    let out = th.wait_for("waiting for a system controller", LIMIT);
    assert!(
        out.contains("sil-kit-system-controller -u silkit://HOST:PORT th-11"),
        "{out}"
    );
}

/// `canpos run` of a TH (serial 11, node 5) on `bus` with `extra` options.
fn th_sensor(d: &Path, bus: &str, extra: &[&str]) -> Proc {
    let state = d.to_str().unwrap();
    let mut args = vec![
        "run",
        "--model",
        "th",
        "--serial",
        "11",
        "--node-id",
        "5",
        "--bus",
        bus,
        "--state-dir",
        state,
    ];
    args.extend_from_slice(extra);
    Proc::start(d, &args)
}

#[test]
fn a_sensor_rejoins_a_registry_that_comes_back_and_a_new_sdo_reads_it() {
    if !have_silkit() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let exe = silkit::sys::registry_executable().expect("registry");
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let uri = reg.uri().clone();
    let bus = format!("{uri}/can0");
    let mut th = th_sensor(d, &bus, &[]);
    th.wait_for("as th-11;", LIMIT);
    let device_type = ok(d, &["sdo", "--bus", &bus, "read", "5", "0x1000", "0"]);
    let file = d.join("th-11.bin");
    let before = std::fs::read(&file).expect("state file");

    // The registry goes away: the sensor says so (SIL Kit's disconnected handler).
    reg.stop();
    th.wait_for("went away", LIMIT);
    // It comes back on the same port: the sensor rejoins it under its name ...
    let reg = LocalRegistry::start_exe(&exe, uri.port, LIMIT).expect("registry again");
    assert_eq!(reg.uri(), &uri);
    let out = th.wait_for("rejoined the registry", LIMIT);
    assert!(out.contains("is back"), "{out}");
    // ... so that a tool started now, which only the new registry introduces, reads it.
    let again = ok(d, &["sdo", "--bus", &bus, "read", "5", "0x1000", "0"]);
    // The value's line (the others are the log lines of the tool's participant).
    assert_eq!(value_line(&again), value_line(&device_type), "{again}");
    assert!(value_line(&device_type).is_some(), "{device_type}");
    assert!(!th.output().contains("panicked"), "{}", th.output());
    assert_eq!(std::fs::read(&file).unwrap(), before, "state file changed");
}

#[test]
fn a_synchronised_sensor_ends_with_a_clear_error_when_the_registry_comes_back() {
    if !have_silkit() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let exe = silkit::sys::registry_executable().expect("registry");
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let uri = reg.uri().clone();
    let bus = format!("{uri}/can0");
    let sc = SystemController::start(&reg, &["th-11"]);
    let mut th = th_sensor(d, &bus, &["--nmt", "operational", "--time", "sync"]);
    // The simulation runs: a wall-clock recorder sees TPDOs.
    ok(
        d,
        &[
            "record", "--bus", &bus, "--format", "candump", "--count", "5", "rec.log",
        ],
    );
    let file = d.join("th-11.bin");
    let before = std::fs::read(&file).expect("state file");
    reg.stop();
    // Peer to peer, the simulation goes on while the registry is away ...
    th.wait_for("went away", LIMIT);
    // ... but a synchronised participant cannot rejoin one that comes back: it ends, naming
    // what to restart, instead of going on unknown to the registry.
    let _reg = LocalRegistry::start_exe(&exe, uri.port, LIMIT).expect("registry again");
    let code = th.wait_exit(LIMIT);
    let out = th.output();
    assert_eq!(code, Some(1), "{out}");
    assert!(
        out.contains("came back")
            && out.contains("restart the synchronised participants and the system controller"),
        "{out}"
    );
    assert!(!out.contains("panicked"), "{out}");
    assert_eq!(std::fs::read(&file).unwrap(), before, "state file changed");
    drop(sc);
}

/// A process that keeps one core busy (`sh` spinning) until dropped.
struct Busy(Child);

impl Busy {
    fn start() -> Busy {
        Busy(
            Command::new("sh")
                .args(["-c", "while :; do :; done"])
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .expect("sh"),
        )
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn one_shot_tools_on_a_busy_machine_are_heard_every_time() {
    if !have_silkit() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let bus = format!("{}/can0", reg.uri());
    let mut th = th_sensor(d, &bus, &[]);
    th.wait_for("as th-11;", LIMIT);
    // Both cores busy besides the sensor and the tools (and whatever else the machine runs).
    let _busy = [Busy::start(), Busy::start()];
    // Each `canpos sdo` is a new participant: it joins, sends its request at once and must be
    // heard (SIL Kit's join and controller creation wait for every known participant's
    // handshake, subscriptions and services: docs/SILKIT.md). The judge is the answer, with
    // the default 1 s SDO timeout; no wall time is measured.
    let mut failures = Vec::new();
    for i in 0..20 {
        let o = run_in(
            d,
            &["sdo", "--bus", &bus, "read", "5", "0x1000", "0"],
            LIMIT,
        );
        let t = text(&o);
        if !o.status.success() || value_line(&t).is_none() {
            failures.push(format!("read {i}: {t}"));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of 20 reads failed: {failures:#?}",
        failures.len()
    );
    assert!(!th.output().contains("panicked"), "{}", th.output());
}

#[test]
fn faults_are_clear_errors_and_leave_the_state_file_alone() {
    if !have_silkit() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let state = d.to_str().unwrap();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let bus = format!("{}/can0", reg.uri());
    // A state file to guard: the sensor ran once.
    {
        let mut th = Proc::start(
            d,
            &[
                "run",
                "--model",
                "th",
                "--serial",
                "11",
                "--node-id",
                "5",
                "--bus",
                &bus,
                "--state-dir",
                state,
            ],
        );
        th.wait_for("as th-11;", LIMIT);
        // The banner can come before the sensor's first save: wait for the file (a run killed
        // earlier left none, and the read below failed NotFound about once in four runs).
        let end = Instant::now() + LIMIT;
        while !d.join("th-11.bin").exists() {
            assert!(Instant::now() < end, "no state file within {LIMIT:?}");
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    let file = d.join("th-11.bin");
    let before = std::fs::read(&file).expect("state file");

    // A participant name in use: refused by the registry, named in the error.
    let mut other = Proc::start(
        d,
        &[
            "run",
            "--model",
            "th",
            "--serial",
            "13",
            "--node-id",
            "7",
            "--bus",
            &bus,
            "--participant",
            "shared",
            "--state-dir",
            state,
        ],
    );
    other.wait_for("as shared;", LIMIT);
    let o = run_in(
        d,
        &[
            "run",
            "--model",
            "th",
            "--serial",
            "11",
            "--node-id",
            "5",
            "--bus",
            &bus,
            "--participant",
            "shared",
            "--state-dir",
            state,
        ],
        LIMIT,
    );
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    assert!(t.contains("already exists"), "{t}");
    assert!(!t.contains("panicked"), "{t}");
    assert_eq!(std::fs::read(&file).unwrap(), before, "state file changed");

    // The registry goes away: the running sensor goes on; a new participant gets a clear error.
    let uri = reg.uri().clone();
    reg.stop();
    let o = run_in(
        d,
        &[
            "run",
            "--model",
            "th",
            "--serial",
            "11",
            "--node-id",
            "5",
            "--bus",
            &format!("{uri}/can0"),
            "--state-dir",
            state,
        ],
        LIMIT,
    );
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    assert!(t.contains("Failed to connect to SIL Kit Registry"), "{t}");
    assert!(!t.contains("panicked"), "{t}");
    assert_eq!(std::fs::read(&file).unwrap(), before, "state file changed");
    std::thread::sleep(Duration::from_millis(300));
    assert!(other.output().contains("as shared;") && !other.output().contains("panicked"));
    assert!(
        std::process::Command::new("kill")
            .args(["-0", &other.pid().to_string()])
            .status()
            .unwrap()
            .success(),
        "the running sensor ended with the registry: {}",
        other.output()
    );

    // A malformed URL or participant name: a usage error (exit 2).
    let o = run_in(
        d,
        &[
            "sdo",
            "--bus",
            "silkit://127.0.0.1:1",
            "read",
            "5",
            "0x1000",
            "0",
        ],
        LIMIT,
    );
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(text(&o).contains("missing network"), "{}", text(&o));
    let o = run_in(
        d,
        &[
            "run",
            "--bus",
            "mem://x",
            "--participant",
            "p",
            "--state-dir",
            state,
        ],
        LIMIT,
    );
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
}
