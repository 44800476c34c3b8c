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
    api: &'static silkit::sys::Api,
    ctrl: *mut silkit::sys::CanController,
    seen: Box<Received>,
    /// Last: destroyed after nothing else of it is used.
    _participant: silkit::Participant,
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
