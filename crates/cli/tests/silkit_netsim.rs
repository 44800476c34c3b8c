//! `canpos bus netsim` in the loop (issue 32 item 3, docs/SILKIT.md "canpos as the network
//! simulator"): a `sil-kit-registry` on 127.0.0.1, a TH and a TMI in their own `canpos run`
//! processes, `canpos bus netsim` for their network at 250 kbit/s and a recorder, all
//! synchronised under SIL Kit's system controller. The recorded end-of-frame times show
//! docs/BUS.md's bit time and arbitration, and two runs give the same frames at the same
//! simulated times. Needs `scripts/silkit.sh`; without it the test says so and passes, unless
//! `CANPOS_SILKIT_REQUIRED=1` (the test command sets it).

mod common;

use std::path::Path;
use std::process::{Child, Command, Stdio};
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
