//! `canpos bus netsim` in the loop (issue 32 item 3, docs/SILKIT.md "canpos as the network
//! simulator"): a `sil-kit-registry` on 127.0.0.1, a TH and a TMI in their own `canpos run`
//! processes, `canpos bus netsim` for their network at 250 kbit/s and a recorder, all
//! synchronised under SIL Kit's system controller. The recorded end-of-frame times show
//! docs/BUS.md's bit time and arbitration, and two runs give the same frames at the same
//! simulated times. Needs `scripts/silkit.sh`; without it the test says so and passes, unless
//! `CANPOS_SILKIT_REQUIRED=1` (the test command sets it).

mod common;

use std::ffi::{c_void, CString};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::time::Duration;

use canpos_host::bus::bits::frame_length;
use canpos_host::silkit::{self, LocalRegistry};
use canpos_stack::Frame;
use common::{run_in, text, Proc};

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

/// `sil-kit-system-controller` waiting for `names`; killed on drop.
struct SystemController(Child);

impl Drop for SystemController {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn system_controller(reg: &LocalRegistry, names: &[&str]) -> SystemController {
    let exe = silkit::sys::registry_executable()
        .expect("registry")
        .with_file_name("sil-kit-system-controller");
    SystemController(
        Command::new(exe)
            .arg("--connect-uri")
            .arg(reg.uri().to_string())
            .args(["--log", "off"])
            .args(names)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("system controller"),
    )
}

/// One run: the recorder's first `count` frames (candump, simulated end-of-frame times).
fn run(d: &Path, count: usize) -> Vec<(u64, u32, String)> {
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let _sc = system_controller(&reg, &["netsim", "th-11", "tmi-12", "rec"]);
    let uri = reg.uri().to_string();
    let bus = format!("{uri}/can0");
    let state = d.to_str().unwrap();
    let _netsim = Proc::start(
        d,
        &[
            "bus",
            "netsim",
            "--registry",
            &uri,
            "--network",
            "can0",
            "--bitrate",
            "250",
            "--time",
            "sync",
            "--coordinated",
            "--participant",
            "netsim",
        ],
    );
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
    let _th = sensor("th", "11", "5");
    let _tmi = sensor("tmi", "12", "6");
    let rec = d.join("sync.log");
    let url = format!("{bus}?participant=rec&time=sync");
    let args = [
        "record",
        "--bus",
        &url,
        "--format",
        "candump",
        "--count",
        &count.to_string(),
        rec.to_str().unwrap(),
    ];
    let o = run_in(d, &args, LIMIT);
    assert!(o.status.success(), "canpos {args:?}: {}", text(&o));
    std::fs::read_to_string(&rec)
        .unwrap()
        .lines()
        .map(|l| {
            // (S.UUUUUU) can0 ID#DATA
            let (t, rest) = l.trim_start_matches('(').split_once(") can0 ").expect(l);
            let (s, us) = t.split_once('.').expect(l);
            let ns = (s.parse::<u64>().unwrap() * 1_000_000 + us.parse::<u64>().unwrap()) * 1000;
            let (id, data) = rest.split_once('#').expect(l);
            (ns, u32::from_str_radix(id, 16).unwrap(), data.to_string())
        })
        .collect()
}

fn bits(id: u32, data: &str) -> u64 {
    let bytes: Vec<u8> = (0..data.len() / 2)
        .map(|i| u8::from_str_radix(&data[2 * i..2 * i + 2], 16).unwrap())
        .collect();
    u64::from(frame_length(&Frame::with_id(id, false, &bytes).unwrap()).total)
}

#[test]
fn the_simulator_times_the_frames_as_docs_bus_md_and_synchronised_runs_repeat() {
    if !have_silkit() {
        return;
    }
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    // From 10 ms of simulated time on: a participant's frames before it has discovered the
    // simulator go over SIL Kit's own bus and are lost (docs/SILKIT.md, known limit), which
    // can hit the boot-ups at 0. 250 kbit/s, not 125: the TH's 1 ms TPDO and the TMI's take
    // 101 % of a 125 kbit/s bus, whose backlog then keeps the phase of such a start-up loss
    // for good; at 250 kbit/s the bus is idle between the steps.
    let settled = |v: Vec<(u64, u32, String)>| -> Vec<(u64, u32, String)> {
        v.into_iter()
            .filter(|f| f.0 >= 10_000_000)
            .take(300)
            .collect()
    };
    let first = settled(run(a.path(), 340));
    assert_eq!(first.len(), 300);
    let bit = 4_000; // ns at 250 kbit/s
                     // Both sensors' TPDOs are there, arbitrated: the TH's 0x185 and the TMI's 0x186.
    assert!(first.iter().any(|f| f.1 == 0x185) && first.iter().any(|f| f.1 == 0x186));
    // Each frame either started on an idle bus at its sender's step (the sensors step by
    // 1 ms, and its end of frame is its length less the 3-bit intermission later), or waited
    // for the frame before it and went out right after it (its length after that one's end):
    // docs/BUS.md's bit time, one frame at a time. Both kinds occur.
    let (mut idle, mut waited) = (0, 0);
    for w in first.windows(2) {
        let ((ta, _, _), (tb, id, data)) = (&w[0], &w[1]);
        let len = bits(*id, data) * bit;
        assert!(tb - ta >= len, "{w:?}: less than a frame time apart");
        if (tb - (len - 3 * bit)).is_multiple_of(1_000_000) {
            idle += 1;
        } else {
            assert_eq!(
                tb - ta,
                len,
                "{w:?}: neither at a step nor right after the frame before"
            );
            waited += 1;
        }
    }
    assert!(idle > 0 && waited > 0, "idle {idle}, waited {waited}");
    let second = settled(run(b.path(), 340));
    if let Some(i) = (0..300).find(|&i| first[i] != second[i]) {
        panic!(
            "two synchronised runs through the simulator differ at frame {i}: {:?} / {:?}",
            &first[i.saturating_sub(2)..(i + 3).min(300)],
            &second[i.saturating_sub(2)..(i + 3).min(300)]
        );
    }
}

/// A bare SIL Kit participant with one CAN controller (another tool's, as far as canpos is
/// concerned): it records the frames it receives with SIL Kit's timestamp (the simulator's
/// end-of-frame time) and, when dropped, leaves without stopping its controller.
struct RawNode {
    /// Dropped first (fields drop in order): SIL Kit calls no handler after the participant
    /// is destroyed, so `seen`, the frame handler's context, must outlive it. In the other
    /// order a frame arriving during the drop wrote into freed memory (a CI run's test process
    /// aborted with "malloc_consolidate(): unaligned fastbin chunk detected").
    _participant: silkit::Participant,
    api: &'static silkit::sys::Api,
    ctrl: *mut silkit::sys::CanController,
    seen: Box<Received>,
}

/// Frames received: identifier, data, SIL Kit timestamp.
type Received = Mutex<Vec<(u32, Vec<u8>, u64)>>;

unsafe extern "C" fn raw_on_frame(
    ctx: *mut c_void,
    _c: *mut silkit::sys::CanController,
    ev: *mut silkit::sys::CanFrameEvent,
) {
    // SAFETY: `ctx` is the node's `seen`, alive until the participant is destroyed; the event
    // and its frame are valid during the call.
    let seen = unsafe { &*(ctx as *const Received) };
    let ev = unsafe { &*ev };
    let f = unsafe { &*ev.frame };
    let data = unsafe { std::slice::from_raw_parts(f.data.data, f.data.size) }.to_vec();
    seen.lock().unwrap().push((f.id, data, ev.timestamp));
}

impl RawNode {
    fn join(reg: &LocalRegistry, name: &str) -> RawNode {
        let api = silkit::api().unwrap();
        let participant = silkit::Participant::join(api, name, reg.uri()).expect("joins");
        let name_c = CString::new(name).unwrap();
        let net_c = CString::new("can0").unwrap();
        let seen: Box<Received> = Box::default();
        let ctx = &*seen as *const _ as *mut c_void;
        let (mut ctrl, mut h) = (std::ptr::null_mut(), 0u64);
        // SAFETY: a live participant, NUL-terminated names, out-pointers; `seen` outlives it.
        unsafe {
            let p = participant.raw();
            api.check(
                "controller",
                (api.can_controller_create)(&mut ctrl, p, name_c.as_ptr(), net_c.as_ptr()),
            )
            .unwrap();
            // Received frames only (SilKit_Direction_Receive).
            api.check(
                "handler",
                (api.can_controller_add_frame_handler)(ctrl, ctx, raw_on_frame, 2, &mut h),
            )
            .unwrap();
            api.check("start", (api.can_controller_start)(ctrl))
                .unwrap();
        }
        RawNode {
            api,
            ctrl,
            seen,
            _participant: participant,
        }
    }

    fn send(&self, id: u32, data: &[u8]) {
        let mut f = silkit::sys::CanFrame {
            header: silkit::sys::StructHeader::new(silkit::sys::CAN_FRAME_ID),
            id,
            flags: 0,
            dlc: data.len() as u16,
            sdt: 0,
            vcid: 0,
            af: 0,
            data: silkit::sys::ByteVector {
                data: data.as_ptr(),
                size: data.len(),
            },
        };
        // SAFETY: a live controller; the frame is copied during the call.
        let rc = unsafe {
            (self.api.can_controller_send_frame)(self.ctrl, &mut f, std::ptr::null_mut())
        };
        self.api.check("send", rc).unwrap();
    }

    fn seen(&self) -> Vec<(u32, Vec<u8>, u64)> {
        self.seen.lock().unwrap().clone()
    }
}

/// What the simulator's current worker logged: its output after the last restart (the
/// supervisor logs a restart after the crashed worker's last line; both write to stderr).
fn current_worker(out: &str) -> &str {
    const CRASHED: &str = "the simulator's SIL Kit part crashed";
    out.rfind(CRASHED)
        .map_or(out, |i| &out[i + CRASHED.len()..])
}

/// Waits until the simulator's output satisfies `pred`, at most `LIMIT`.
fn wait_netsim(netsim: &mut Proc, what: &str, pred: impl Fn(&str) -> bool) -> String {
    let end = std::time::Instant::now() + LIMIT;
    loop {
        let o = netsim.output();
        if pred(&o) {
            return o;
        }
        assert!(
            netsim.running(),
            "canpos bus netsim ended while {what}: {o}"
        );
        assert!(std::time::Instant::now() < end, "{what}: {o}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// SIL Kit 5.0.3 crashes a network simulator when a controller leaves while a send to it is
/// queued (D57): here a busy simulated network (two TH sensors with 1 ms TPDOs on 125 kbit/s,
/// more than the bus carries) sees ten participants leave mid-traffic, every other one a
/// `canpos run` killed with SIGKILL, the others a bare SIL Kit participant that leaves without
/// stopping its controller. `canpos bus netsim` keeps running (its worker restarted after each
/// crash) and still times the remaining traffic: a new receiver gets the sensors' frames at the
/// simulator's end-of-frame times, back to back as on a saturated bus (docs/BUS.md). Before the
/// supervisor, the simulator died within the first leaves.
#[test]
fn participants_leaving_a_busy_network_abruptly_leave_the_simulator_running_and_timing() {
    if !have_silkit() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let d = d.path();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let uri = reg.uri().to_string();
    let bus = format!("{uri}/can0");
    let state = d.to_str().unwrap();
    let mut netsim = Proc::start(
        d,
        &[
            "bus",
            "netsim",
            "--registry",
            &uri,
            "--network",
            "can0",
            "--bitrate",
            "125",
            "--participant",
            "netsim",
            "--stats-interval",
            "0",
        ],
    );
    let sensor = |serial: &str, node: &str| {
        Proc::start(
            d,
            &[
                "run",
                "--model",
                "th",
                "--serial",
                serial,
                "--node-id",
                node,
                "--nmt",
                "operational",
                "--bus",
                &bus,
                "--state-dir",
                state,
            ],
        )
    };
    let _a = sensor("11", "5");
    let _b = sensor("12", "6");
    // Controllers the current worker has: joined less left.
    let present = |o: &str| {
        let w = current_worker(o);
        w.matches("controller joined").count() as i64 - w.matches("controller left").count() as i64
    };
    const LEAVES: usize = 10;
    for k in 0..LEAVES {
        // The current worker has the two sensors' controllers (again, after a restart), and no
        // other.
        wait_netsim(&mut netsim, "waiting for the sensors", |o| present(o) == 2);
        if k % 2 == 0 {
            let mut victim = sensor(&format!("9{k}"), &(20 + k).to_string());
            wait_netsim(&mut netsim, "waiting for the victim", |o| present(o) == 3);
            // Its 1 ms TPDOs and heartbeats on the busy bus a while, then SIGKILL.
            std::thread::sleep(Duration::from_millis(300));
            victim.stop();
        } else {
            let leaver = RawNode::join(&reg, &format!("leaver{k}"));
            wait_netsim(&mut netsim, "waiting for the leaver", |o| present(o) == 3);
            for i in 0..300u32 {
                leaver.send(0x300 + k as u32, &i.to_le_bytes());
                std::thread::sleep(Duration::from_millis(1));
            }
            drop(leaver);
        }
        // Gone: its leave seen, or a new worker without it.
        wait_netsim(&mut netsim, "waiting for the leave", |o| present(o) == 2);
        // A crash follows the leave within milliseconds, if it comes.
        std::thread::sleep(Duration::from_millis(300));
        assert!(netsim.running(), "{}", netsim.output());
    }
    // A crash comes within milliseconds of the leave, but its report may be late on a loaded
    // machine: a generous pause before the count the receiver's phase must leave unchanged.
    std::thread::sleep(Duration::from_secs(1));
    let crashes = netsim.output().matches("part crashed").count();
    eprintln!("{crashes} of {LEAVES} leaves crashed the simulator's SIL Kit part (restarted)");
    // Still simulating: a new receiver gets the sensors' frames at the simulator's times.
    wait_netsim(&mut netsim, "waiting for the sensors", |o| present(o) == 2);
    let rx = RawNode::join(&reg, "rx");
    let end = std::time::Instant::now() + LIMIT;
    while rx.seen().len() < 320 {
        assert!(
            std::time::Instant::now() < end,
            "rx got {:?}",
            rx.seen().len()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(
        netsim.output().matches("part crashed").count(),
        crashes,
        "no one left meanwhile"
    );
    // Past the frames a participant may get before it learns of the simulator.
    let frames = &rx.seen()[20..320];
    assert!(frames.iter().any(|f| f.0 == 0x185) && frames.iter().any(|f| f.0 == 0x186));
    let mut back_to_back = 0;
    for w in frames.windows(2) {
        let ((_, _, ta), (id, data, tb)) = (&w[0], &w[1]);
        let len = u64::from(frame_length(&Frame::with_id(*id, false, data).unwrap()).total) * 8_000;
        // One frame at a time on the wire: each ends at least its length after the one before.
        assert!(tb - ta >= len, "{w:?}: less than a frame time apart");
        if tb - ta == len {
            back_to_back += 1;
        }
    }
    // Two 1 ms TPDOs are more than 125 kbit/s carries: the frames go out back to back.
    assert!(
        back_to_back > frames.len() / 2,
        "{back_to_back} back to back"
    );
    // It stops as asked, with its report. The receiver leaves only afterwards: its leave (it
    // does not stop its controller) could crash the worker just as the stop comes, and a
    // stop between a crash and the new worker ends the command without a report.
    // SAFETY: kill with the pid of our own child, not yet waited for.
    unsafe { libc::kill(netsim.pid() as libc::pid_t, libc::SIGTERM) };
    assert_eq!(netsim.wait_exit(LIMIT), Some(0), "{}", netsim.output());
    assert!(netsim.output().contains("\"network\":\"can0\""));
    drop(rx);
}

/// `canpos bus netsim` run in its own process group, its output in `out`.
fn netsim_in_group(d: &Path, uri: &str, out: &Path) -> Child {
    use std::os::unix::process::CommandExt as _;
    Command::new(common::BIN)
        .args(["bus", "netsim", "--registry", uri, "--network", "can0"])
        .args([
            "--bitrate",
            "125",
            "--participant",
            "netsim",
            "--stats-interval",
            "0",
        ])
        .current_dir(d)
        .process_group(0)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(out).unwrap())
        .stderr(std::fs::File::create(out.with_extension("err")).unwrap())
        .spawn()
        .expect("spawn canpos")
}

/// Waits for `child` to end, at most `LIMIT` (then kills it and panics).
fn wait_child(child: &mut Child, what: &str) -> std::process::ExitStatus {
    let end = std::time::Instant::now() + LIMIT;
    loop {
        if let Some(st) = child.try_wait().unwrap() {
            return st;
        }
        if std::time::Instant::now() > end {
            // SAFETY: kill with the pid (= process group) of our own child, not yet waited for.
            unsafe { libc::kill(-(child.id() as libc::pid_t), libc::SIGKILL) };
            let _ = child.wait();
            panic!("{what}: still running after {LIMIT:?}");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Ctrl-C in a terminal reaches the whole process group, the worker too, and may do so while
/// the worker is still starting (before it handles the signal): the command still stops
/// gracefully, exit 0 with its report, never as a crash (D57). Before: the worker died of the
/// SIGINT and the command ended with exit 1, sometimes logging a crash.
#[test]
fn ctrl_c_to_the_process_group_while_the_worker_starts_stops_it_gracefully() {
    if !have_silkit() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let d = d.path();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let uri = reg.uri().to_string();
    for round in 0..3 {
        let out = d.join(format!("netsim{round}.out"));
        let mut netsim = netsim_in_group(d, &uri, &out);
        let pid = netsim.id();
        // The supervisor handles Ctrl-C before it starts a worker: signal as soon as the
        // worker exists, the earliest moment of its start-up.
        let children = format!("/proc/{pid}/task/{pid}/children");
        let end = std::time::Instant::now() + LIMIT;
        while std::fs::read_to_string(&children)
            .unwrap_or_default()
            .trim()
            .is_empty()
        {
            assert!(std::time::Instant::now() < end, "no worker started");
            assert!(netsim.try_wait().unwrap().is_none(), "netsim ended");
            std::thread::sleep(Duration::from_millis(1));
        }
        // SAFETY: the process group of our own child, not yet waited for.
        unsafe { libc::kill(-(pid as libc::pid_t), libc::SIGINT) };
        let st = wait_child(&mut netsim, "netsim after Ctrl-C");
        let stdout = std::fs::read_to_string(&out).unwrap();
        let stderr = std::fs::read_to_string(out.with_extension("err")).unwrap();
        assert_eq!(st.code(), Some(0), "{st}: {stdout}{stderr}");
        assert!(!stderr.contains("crashed"), "{stderr}");
        assert_eq!(
            stdout.matches("\"network\":\"can0\"").count(),
            1,
            "{stdout}"
        );
    }
}

/// `CANPOS_NETSIM_WORKER` that does not name this process's parent (set by hand, inherited,
/// or its supervisor gone): a clear error, not a silent death by SIGTERM.
#[test]
fn a_worker_variable_not_naming_the_parent_is_a_clear_error() {
    if !have_silkit() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let uri = reg.uri().to_string();
    for value in ["1", "yes"] {
        let mut c = Command::new(common::BIN)
            .args(["bus", "netsim", "--registry", &uri, "--network", "can0"])
            .args(["--bitrate", "125", "--duration", "1"])
            .current_dir(d.path())
            .env("CANPOS_NETSIM_WORKER", value)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(d.path().join("err")).unwrap())
            .spawn()
            .unwrap();
        let st = wait_child(&mut c, "netsim with a stray worker variable");
        let err = std::fs::read_to_string(d.path().join("err")).unwrap();
        assert_eq!(st.code(), Some(1), "{st}: {err}");
        assert!(err.contains("CANPOS_NETSIM_WORKER"), "{err}");
    }
}

/// Sends `sig` to a process of the test.
fn signal(p: &Proc, sig: i32) {
    // SAFETY: a plain kill(2) of a child this test started (and has not reaped).
    assert_eq!(unsafe { libc::kill(p.pid() as i32, sig) }, 0);
}

/// `canpos bus netsim` for `can0` at 125 kbit/s on the wall clock, as `name`.
fn netsim_wall(d: &Path, uri: &str, name: &str) -> Proc {
    Proc::start(
        d,
        &[
            "bus",
            "netsim",
            "--registry",
            uri,
            "--network",
            "can0",
            "--bitrate",
            "125",
            "--participant",
            name,
        ],
    )
}

/// A sensor of `canpos run` on the wall clock (pre-operational: it sends its boot-up, then
/// waits for its master).
fn sensor_wall(d: &Path, bus: &str, model: &str, serial: &str, node: &str) -> Proc {
    let state = d.to_str().unwrap();
    let args = [
        "run",
        "--model",
        model,
        "--serial",
        serial,
        "--node-id",
        node,
        "--bus",
        bus,
        "--state-dir",
        state,
    ];
    Proc::start(d, &args)
}

/// A master listening on `bus` (canpos's recorder, candump lines on its stdout), returned
/// once its controller is on the network (its "discovery settled" DEBUG line, D54).
fn master(d: &Path, bus: &str) -> Proc {
    let mut rec = Proc::start_env(
        d,
        &["record", "--bus", bus, "--format", "candump", "-"],
        &[("RUST_LOG", "info,canpos_host::silkit=debug")],
    );
    rec.wait_for("discovery settled", LIMIT);
    rec
}

/// The candump lines `rec` printed, as `ID#DATA`.
fn frames_of(rec: &Proc) -> Vec<String> {
    rec.output()
        .lines()
        .filter_map(|l| l.split_once(") can0 ").map(|(_, f)| f.to_string()))
        .collect()
}

/// Waits until `rec` has printed a frame `ID#…` after its first `skip` frames.
fn wait_frame(rec: &Proc, skip: usize, id: &str, what: &str) {
    let end = std::time::Instant::now() + LIMIT;
    while !frames_of(rec)
        .iter()
        .skip(skip)
        .any(|f| f.starts_with(&format!("{id}#")))
    {
        assert!(
            std::time::Instant::now() < end,
            "{what}: no {id} frame within {LIMIT:?}: {:?}",
            frames_of(rec)
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The simulator's exit report of `can0` (one JSON line per network).
fn report_of(sim: &mut Proc) -> serde_json::Value {
    assert_eq!(sim.wait_exit(LIMIT), Some(0), "{}", sim.output());
    let out = sim.output();
    let line = out
        .lines()
        .find(|l| l.starts_with('{') && l.contains("\"network\":\"can0\""))
        .unwrap_or_else(|| panic!("no report: {out}"));
    serde_json::from_str(line).unwrap()
}

/// The frames the simulator carried.
fn carried(sim: &mut Proc) -> u64 {
    report_of(sim)["frames"].as_u64().unwrap()
}

#[test]
fn sensors_log_the_simulator_coming_and_going_and_frames_flow_without_it() {
    if !have_silkit() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let d = d.path();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let uri = reg.uri().to_string();
    let bus = format!("{uri}/can0");
    let rec = master(d, &bus);
    let mut sim = netsim_wall(d, &uri, "netsim-a");
    let mut th = sensor_wall(d, &bus, "th", "11", "5");
    let mut tmi = sensor_wall(d, &bus, "tmi", "12", "6");
    // The simulator's arrival, in each sensor's log; their boot-ups through it.
    for s in [&mut th, &mut tmi] {
        s.wait_for("network can0: simulated by 'netsim-a' (bit-timed)", LIMIT);
    }
    wait_frame(&rec, 0, "705", "the TH's boot-up");
    wait_frame(&rec, 0, "706", "the TMI's boot-up");

    // Stopped (SIGTERM): each sensor says so, and SIL Kit's own bus carries the frames.
    signal(&sim, libc::SIGTERM);
    assert!(
        carried(&mut sim) >= 2,
        "the boot-ups went through the simulator"
    );
    let left = "network can0: the network simulator 'netsim-a' left; SIL Kit's own untimed bus \
                carries the frames now";
    for s in [&mut th, &mut tmi] {
        s.wait_for(left, LIMIT);
    }
    let n = frames_of(&rec).len();
    let o = run_in(d, &["nmt", "start", "--bus", &bus, "--node", "5"], LIMIT);
    assert!(o.status.success(), "canpos nmt start: {}", text(&o));
    wait_frame(&rec, n, "185", "the TH's TPDO with the simulator stopped");

    // A second simulator comes and is killed (SIGKILL): the same in the logs, frames go on.
    let mut sim_b = netsim_wall(d, &uri, "netsim-b");
    for s in [&mut th, &mut tmi] {
        s.wait_for("network can0: simulated by 'netsim-b' (bit-timed)", LIMIT);
    }
    rec_wait_simulated(&rec, "netsim-b");
    signal(&sim_b, libc::SIGKILL);
    sim_b.stop();
    let left_b = "network can0: the network simulator 'netsim-b' left; SIL Kit's own untimed bus \
                  carries the frames now";
    for s in [&mut th, &mut tmi] {
        s.wait_for(left_b, LIMIT);
    }
    let n = frames_of(&rec).len();
    wait_frame(&rec, n, "185", "the TH's TPDO with the simulator killed");
    // Each change was said once per sensor, as a WARN; nothing on stdout of the recorder but
    // candump lines (its log goes to stderr, which this test reads in the same stream).
    for s in [&th, &tmi] {
        let o = s.output();
        assert_eq!(o.matches(left).count(), 1, "{o}");
        assert!(
            o.lines()
                .any(|l| l.contains(" WARN ") && l.contains(left_b)),
            "{o}"
        );
    }
}

/// Waits until the recorder's controller routes through `sim` (its own log line).
fn rec_wait_simulated(rec: &Proc, sim: &str) {
    let needle = format!("network can0: simulated by '{sim}'");
    let end = std::time::Instant::now() + LIMIT;
    while !rec.output().contains(&needle) {
        assert!(std::time::Instant::now() < end, "{}", rec.output());
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn boot_ups_reach_a_master_through_a_simulator_started_with_the_sensors() {
    if !have_silkit() {
        return;
    }
    // The simulator and the sensors start together, as a rig's start script starts them, the
    // master already listening: a sensor whose controller had not yet learnt of the simulator
    // sent its boot-up on SIL Kit's trivial bus, around the simulator or lost, when the
    // master's controller already routed through it (D54). Now a sensor opens its bus once
    // discovery has settled: with the simulator, when it has joined by then.
    let debug = [("RUST_LOG", "info,canpos_host::silkit=debug")];
    for round in 0..3 {
        let d = tempfile::tempdir().unwrap();
        let d = d.path();
        let reg = LocalRegistry::start(LIMIT).expect("registry");
        let uri = reg.uri().to_string();
        let bus = format!("{uri}/can0");
        let rec = master(d, &bus);
        let mut sim = netsim_wall(d, &uri, "netsim");
        let state = d.to_str().unwrap();
        let sensor = |model: &str, serial: &str, node: &str| {
            let args = [
                "run",
                "--model",
                model,
                "--serial",
                serial,
                "--node-id",
                node,
                "--bus",
                &bus,
                "--state-dir",
                state,
            ];
            Proc::start_env(d, &args, &debug)
        };
        let mut sensors = [sensor("th", "11", "5"), sensor("tmi", "12", "6")];
        rec_wait_simulated(&rec, "netsim");
        let end = std::time::Instant::now() + LIMIT;
        loop {
            let f = frames_of(&rec);
            if f.contains(&"705#00".to_string()) && f.contains(&"706#00".to_string()) {
                break;
            }
            assert!(
                std::time::Instant::now() < end,
                "round {round}: boot-ups lost: {f:?}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        // Each sensor found the simulator before it opened its bus and sent its boot-up
        // through it: the simulator reports a controller that sent for each.
        let mut simulated = 0;
        for s in &mut sensors {
            let o = s.wait_for("discovery settled", LIMIT);
            if o.contains("settled=Simulated(\"netsim\")") {
                simulated += 1;
            }
            if let Some(l) = o.lines().find(|l| l.contains("discovery settled")) {
                eprintln!("round {round}: {l}");
            }
        }
        signal(&sim, libc::SIGTERM);
        let report = report_of(&mut sim);
        let senders = report["controllers"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|c| c["sent"].as_u64().unwrap() > 0)
            .count();
        assert!(
            senders >= 2,
            "round {round}: {senders} controllers sent through the simulator ({simulated} of 2 \
             sensors found it before they sent): {report}"
        );
    }
}

#[test]
fn a_master_commissions_two_sensor_processes_through_the_simulator_at_125_kbit_s() {
    if !have_silkit() {
        return;
    }
    // Issue 32's rig: a registry, `canpos bus netsim` at 125 kbit/s, a TH and a TMI in their
    // own processes, canpos's CLI as the master (SDO, LSS fastscan, NMT) and a listener; the
    // frames' end-of-frame times are the simulator's (bit time with stuffing, one frame at a
    // time, arbitration when both sensors' TPDOs queue).
    let d = tempfile::tempdir().unwrap();
    let d = d.path();
    let reg = LocalRegistry::start(LIMIT).expect("registry");
    let uri = reg.uri().to_string();
    let bus = format!("{uri}/can0");
    let rec = master(d, &bus);
    let mut sim = netsim_wall(d, &uri, "netsim");
    rec_wait_simulated(&rec, "netsim");
    // The TH without a node-id (LSS fastscan finds it), the TMI as node 6.
    let mut th = sensor_wall(d, &bus, "th", "11", "255");
    let mut tmi = sensor_wall(d, &bus, "tmi", "12", "6");
    for s in [&mut th, &mut tmi] {
        s.wait_for("network can0: simulated by 'netsim' (bit-timed)", LIMIT);
    }
    let ok = |args: &[&str]| {
        let o = run_in(d, args, LIMIT);
        let t = text(&o);
        assert!(o.status.success(), "canpos {args:?}: {t}");
        t
    };
    let name = ok(&["sdo", "--bus", &bus, "read", "6", "0x1008", "0"]);
    assert!(name.contains("\"TMI\""), "{name}");
    // 500 ms per fastscan step, as in the test without the simulator (tests/silkit.rs).
    let scan = ok(&["lss", "--bus", &bus, "fastscan", "--timeout", "500"]);
    assert!(scan.contains("serial 0x0000000B (11)"), "{scan}");
    ok(&["lss", "--bus", &bus, "set-node-id", "5"]);
    ok(&["lss", "--bus", &bus, "switch-global", "waiting"]);
    ok(&["nmt", "--bus", &bus, "reset-comm", "--node", "0"]);
    let serial = ok(&["sdo", "--bus", &bus, "read", "5", "0x1018", "4"]);
    assert!(serial.contains("0x0000000B (11)"), "{serial}");

    // Both started: their TPDOs on the bus, timed by the simulator.
    let rx = RawNode::join(&reg, "rx");
    ok(&["nmt", "--bus", &bus, "start", "--node", "0"]);
    let end = std::time::Instant::now() + LIMIT;
    while rx.seen().len() < 340 {
        assert!(
            std::time::Instant::now() < end,
            "rx got {}",
            rx.seen().len()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    // Past the frames a participant may get before it learns of the simulator.
    let frames = &rx.seen()[40..340];
    assert!(
        frames.iter().any(|f| f.0 == 0x185) && frames.iter().any(|f| f.0 == 0x186),
        "both sensors' TPDO1: {:?}",
        &frames[..8]
    );
    let mut back_to_back = 0;
    for w in frames.windows(2) {
        let ((_, _, ta), (id, data, tb)) = (&w[0], &w[1]);
        let len = u64::from(frame_length(&Frame::with_id(*id, false, data).unwrap()).total) * 8_000;
        assert!(tb - ta >= len, "{w:?}: less than a frame time apart");
        if tb - ta == len {
            back_to_back += 1;
        }
    }
    // The TH's 1 ms TPDO alone fills most of 125 kbit/s: frames queue and go out back to back.
    assert!(back_to_back > 0, "no frame went out right after another");
    // The simulator stops before the listener leaves: a participant that leaves a busy network
    // without stopping its controller can crash SIL Kit's part of the simulator (D57).
    signal(&sim, libc::SIGTERM);
    let report = report_of(&mut sim);
    drop(rx);
    let senders = report["controllers"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["sent"].as_u64().unwrap() > 0)
        .count();
    // The two sensors and the master's tools sent through the simulator.
    assert!(senders >= 3, "{report}");
    assert!(!th.output().contains("panicked") && !tmi.output().contains("panicked"));
}
