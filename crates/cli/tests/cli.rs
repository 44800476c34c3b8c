//! The `canpos` binary as a user runs it: help, errors and exit codes, `bus serve` + `run` seen
//! through a raw socketcand client, and SIGKILL in the middle of stores.

use std::net::TcpListener;
use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use canpos_host::{SocketcandClient, Transport};
use canpos_stack::storage::{parse_image, IMAGE_MAX};
use canpos_stack::Frame;

const BIN: &str = env!("CARGO_BIN_EXE_canpos");

fn canpos(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .stdin(Stdio::null())
        .output()
        .expect("run canpos")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A child process killed when dropped.
struct Proc(Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn spawn(args: &[&str]) -> Proc {
    Proc(
        Command::new(BIN)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn canpos"),
    )
}

fn wait_port(port: u16) {
    let end = Instant::now() + Duration::from_secs(10);
    while Instant::now() < end {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    panic!("nothing listens on {port}");
}

fn client(port: u16) -> SocketcandClient {
    let c = SocketcandClient::connect(("127.0.0.1", port), "can0").unwrap();
    // The hub holds frames back for ~20 ms after raw mode.
    std::thread::sleep(Duration::from_millis(30));
    c
}

fn wait_frame(c: &mut dyn Transport, id: u16, within: Duration) -> Option<Frame> {
    let end = Instant::now() + within;
    while let Ok(Some(rx)) = c.recv_deadline(end) {
        if rx.frame.std_id() == Some(id) {
            return Some(rx.frame);
        }
    }
    None
}

fn sdo(c: &mut dyn Transport, node: u8, req: [u8; 8]) -> Option<[u8; 8]> {
    c.send(&Frame::new(0x600 + u16::from(node), &req).unwrap())
        .unwrap();
    let f = wait_frame(c, 0x580 + u16::from(node), Duration::from_secs(3))?;
    f.data().try_into().ok()
}

#[test]
fn help_for_every_command() {
    let o = canpos(&["--help"]);
    assert!(o.status.success());
    let t = text(&o);
    for cmd in [
        "bus", "run", "scenario", "ctl", "nmt", "sdo", "lss", "scan", "monitor", "eds", "record",
        "replay",
    ] {
        assert!(t.contains(cmd), "--help lacks {cmd}: {t}");
    }
    for args in [
        &["bus", "--help"][..],
        &["bus", "serve", "--help"],
        &["run", "--help"],
        &["scenario", "--help"],
        &["ctl", "--help"],
        &["ctl", "fault", "--help"],
        &["demo", "--help"],
        &["nmt", "--help"],
        &["sdo", "--help"],
        &["lss", "--help"],
        &["scan", "--help"],
        &["monitor", "--help"],
        &["eds", "--help"],
        &["record", "--help"],
        &["replay", "--help"],
    ] {
        let o = canpos(args);
        assert!(o.status.success(), "{args:?}: {}", text(&o));
        assert!(text(&o).contains("Usage:"), "{args:?}: {}", text(&o));
    }
}

#[test]
fn bad_arguments_fail_with_a_message() {
    for (args, code, needle) in [
        (&["frobnicate"][..], 2, "unrecognized subcommand"),
        (&["run", "--node-id", "0"], 2, "out of range"),
        (&["run", "--node-id", "x"], 2, "not a number"),
        (&["run", "--bus-bitrate", "333"], 2, "not a CAN bit rate"),
        (
            &["run", "--model", "th", "--order-code", "X"],
            2,
            "cannot be used with",
        ),
        (
            &["run", "--magnet", "1", "--motion", "static:1"],
            2,
            "cannot be used with",
        ),
        // Values only the model can judge: still a bad command line (exit 2).
        (&["run", "--model", "nosuch"], 2, "unknown model `nosuch`"),
        (&["run", "--motion", "wobble:1"], 2, "bad motion spec"),
        (&["run", "--bus", "tcp://x"], 2, "unknown scheme"),
        (&["ctl", "state"], 2, "--control"),
        (
            &[
                "ctl",
                "--control",
                "127.0.0.1:1",
                "fault",
                "bus-off",
                "maybe",
            ],
            2,
            "invalid value",
        ),
        (&["scenario", "/nonexistent.toml"], 1, "cannot read"),
    ] {
        let o = canpos(args);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(code), "{args:?}: {t}");
        assert!(t.contains(needle), "{args:?}: expected `{needle}` in {t}");
    }
    let port = free_port();
    let o = canpos(&["ctl", "--control", &format!("127.0.0.1:{port}"), "state"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o).contains("cannot reach the control interface"),
        "{}",
        text(&o)
    );
}

#[test]
fn serve_and_run_boot_up_and_sdo_over_socketcand() {
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let _hub = spawn(&["bus", "serve", "--listen", &format!("127.0.0.1:{port}")]);
    wait_port(port);
    let mut c = client(port);
    let ctl_port = free_port();
    let _run = spawn(&[
        "run",
        "--bus",
        &format!("socketcand://127.0.0.1:{port}/can0"),
        "--ideal",
        "--magnet",
        "250",
        "--state-dir",
        dir.path().to_str().unwrap(),
        "--control",
        &format!("127.0.0.1:{ctl_port}"),
    ]);
    let boot = wait_frame(&mut c, 0x77F, Duration::from_secs(10)).expect("boot-up");
    assert_eq!(boot.data(), &[0]);
    let r = sdo(&mut c, 127, [0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).expect("SDO answer");
    assert_eq!(r[0], 0x43, "{r:x?}");
    assert_eq!(&r[1..4], &[0x00, 0x10, 0x00]);
    // The control interface answers state and moves the magnet.
    wait_port(ctl_port);
    let ctl = format!("127.0.0.1:{ctl_port}");
    let o = canpos(&["ctl", "--control", &ctl, "magnet", "0", "400"]);
    assert!(o.status.success(), "{}", text(&o));
    std::thread::sleep(Duration::from_millis(50));
    let o = canpos(&["ctl", "--control", &ctl, "state"]);
    assert!(o.status.success(), "{}", text(&o));
    let st: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(st["node_id"], 127);
    assert_eq!(st["nmt"], "pre-operational");
    assert_eq!(st["true_mm"][0], 400.0);
    let o = canpos(&["ctl", "--control", &ctl, "fault", "nonsense", "on"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(text(&o).contains("unknown fault"), "{}", text(&o));
}

#[test]
fn run_starts_an_embedded_hub_when_none_listens() {
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let _run = spawn(&[
        "run",
        "--bus",
        &format!("socketcand://127.0.0.1:{port}/can0"),
        "--node-id",
        "5",
        "--state-dir",
        dir.path().to_str().unwrap(),
    ]);
    wait_port(port);
    let mut c = client(port);
    let r = sdo(&mut c, 5, [0x40, 0x18, 0x10, 4, 0, 0, 0, 0]).expect("SDO answer");
    assert_eq!(r[0], 0x43, "{r:x?}");
    assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), 17_143_876);
}

/// The stored 0x1017 value in a state file, or why it cannot be loaded.
fn stored_heartbeat(path: &Path) -> Result<Option<u32>, String> {
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e.to_string()),
    };
    if bytes.len() > IMAGE_MAX {
        return Err("too long".into());
    }
    let tag = canpos_models::by_name("th").unwrap().features.tag;
    let found = parse_image(&bytes, tag)
        .map_err(|e| format!("{e:?}"))?
        .find(|&(k, _)| k == 0x0010_1700)
        .map(|(_, v)| v);
    Ok(found)
}

/// The first frame on `id` whose data `matches`, within `within`; others are skipped.
fn wait_for(
    c: &mut dyn Transport,
    id: u16,
    within: Duration,
    matches: impl Fn(&[u8]) -> bool,
) -> Option<Frame> {
    let end = Instant::now() + within;
    while let Ok(Some(rx)) = c.recv_deadline(end) {
        if rx.frame.std_id() == Some(id) && matches(rx.frame.data()) {
            return Some(rx.frame);
        }
    }
    None
}

/// The answer of node 9's SDO server to the request on 0x`index`:`sub` just sent, within
/// `within`. Called after the run's boot-up: frames of the killed run went out before it on
/// the bus, so every SDO answer now is this run's, and one to another request (a request sent
/// to the killed run reaching this one) fails the test.
fn sdo_answer(
    c: &mut dyn Transport,
    i: u32,
    index: u16,
    sub: u8,
    within: Duration,
) -> Option<[u8; 8]> {
    let f = wait_for(c, 0x589, within, |_| true)?;
    let a: [u8; 8] = f.data().try_into().expect("an SDO answer has 8 bytes");
    let [lo, hi] = index.to_le_bytes();
    assert_eq!(
        a[1..4],
        [lo, hi, sub],
        "iteration {i}: an answer {a:02X?} to a request not sent to this run (expected one on {index:04X}:{sub})"
    );
    Some(a)
}

/// How a "save" sent just before a SIGKILL ended, as the master saw it.
#[derive(Debug)]
enum Store {
    /// Confirmed (0x60): the new value must be in the file.
    Confirmed,
    /// Refused (an abort, e.g. 0x08000020 when the disk is full): the file must be unchanged.
    Refused(u32),
    /// No answer before the kill: the old value or the new one, never a third.
    Unanswered,
}

/// SIGKILL at varying points of a store, `n` times: the state file always loads and holds the
/// old or the new value, a store that was confirmed is never lost, and one that was refused
/// changed nothing. Each run's frames are told from the killed run's by its boot-up (late
/// frames of the killed run, a heartbeat or a store answer, come before it and are skipped),
/// and each SDO answer must be the one to the request just sent (issue 36: a restarted run
/// answered a "save" sent to the run killed before it, and that answer was taken for the
/// answer to the read-back; an abort was counted as a confirmed store).
fn kill_during_store(n: u32) {
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let _hub = spawn(&["bus", "serve", "--listen", &format!("127.0.0.1:{port}")]);
    wait_port(port);
    let mut c = client(port);
    let url = format!("socketcand://127.0.0.1:{port}/can0");
    let path = dir.path().join("th-17143876.bin");
    let mut confirmed = 0;
    for i in 0..n {
        let mut run = spawn(&[
            "run",
            "--bus",
            &url,
            "--node-id",
            "9",
            "--state-dir",
            dir.path().to_str().unwrap(),
        ]);
        // The boot-up (data 0), not a heartbeat the killed run sent just before its end.
        wait_for(&mut c, 0x709, Duration::from_secs(10), |d| d == [0]).expect("boot-up");
        // The value stored by an earlier run is back after the restart.
        c.send(&Frame::new(0x609, &[0x40, 0x17, 0x10, 0, 0, 0, 0, 0]).unwrap())
            .unwrap();
        let r = sdo_answer(&mut c, i, 0x1017, 0, Duration::from_secs(3)).expect("read 0x1017");
        assert_eq!(r[0], 0x4B, "iteration {i}: read 0x1017 answered {r:02X?}");
        let before = stored_heartbeat(&path).unwrap();
        if let Some(v) = before {
            assert_eq!(
                u32::from(u16::from_le_bytes([r[4], r[5]])),
                v,
                "iteration {i}: the value read after the restart is not the stored one"
            );
        }
        let value = 1000 + i as u16;
        let [lo, hi] = value.to_le_bytes();
        c.send(&Frame::new(0x609, &[0x2B, 0x17, 0x10, 0, lo, hi, 0, 0]).unwrap())
            .unwrap();
        let r = sdo_answer(&mut c, i, 0x1017, 0, Duration::from_secs(3)).expect("write 0x1017");
        assert_eq!(r[0], 0x60, "iteration {i}: write 0x1017 answered {r:02X?}");
        c.send(&Frame::new(0x609, &[0x23, 0x10, 0x10, 1, b's', b'a', b'v', b'e']).unwrap())
            .unwrap();
        // Kill somewhere between "before the store" and "after its answer" (≥ 20 ms).
        let delay = Duration::from_micros(u64::from(i * 7919 % 30_000));
        let store = match sdo_answer(&mut c, i, 0x1010, 1, delay) {
            None => Store::Unanswered,
            Some(a) if a[0] == 0x60 => Store::Confirmed,
            Some(a) if a[0] == 0x80 => Store::Refused(u32::from_le_bytes([a[4], a[5], a[6], a[7]])),
            Some(a) => panic!("iteration {i}: \"save\" answered {a:02X?}"),
        };
        run.0.kill().unwrap();
        run.0.wait().unwrap();
        drop(run);
        let after = stored_heartbeat(&path)
            .unwrap_or_else(|e| panic!("iteration {i}: state file does not load: {e}"));
        let new = Some(u32::from(value));
        match store {
            Store::Confirmed => {
                assert_eq!(after, new, "iteration {i}: confirmed store lost");
                confirmed += 1;
            }
            Store::Refused(code) => {
                eprintln!("iteration {i}: \"save\" refused with abort {code:08X}");
                assert_eq!(
                    after, before,
                    "iteration {i}: refused store changed the file"
                );
            }
            Store::Unanswered => assert!(
                after == before || after == new,
                "iteration {i}: {after:?} is neither old {before:?} nor new {value}"
            ),
        }
        // Frames of the killed run still on their way are skipped until the next boot-up.
        while let Ok(Some(_)) = c.try_recv() {}
    }
    eprintln!("{n} kills, {confirmed} of them after the store was confirmed");
    // Both sides of the race must have been exercised.
    assert!(confirmed > 0 && confirmed < n, "{confirmed} of {n}");
}

/// The issue's 100 kills (about 4 s).
#[test]
fn sigkill_during_store_never_leaves_a_bad_state_file() {
    kill_during_store(100);
}

#[test]
fn demo_runs_and_shows_positions() {
    let port = free_port();
    let o = canpos(&[
        "demo",
        "--listen",
        &format!("127.0.0.1:{port}"),
        "--duration",
        "1.5",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains(&format!("127.0.0.1:{port}")), "{t}");
    assert!(t.contains("operational"), "{t}");
    assert!(t.contains(" mm/s"), "{t}");
}

/// Issue 36 item 9: `canpos --web ADDR` (the demo's option without `demo`) runs the demo with
/// its dashboard there; before, it was refused. Before a command the demo's options are a
/// usage error that names the command, not silently dropped.
#[test]
fn the_demos_options_work_without_the_word_demo() {
    let (hub, web) = (free_port(), free_port());
    let o = canpos(&[
        "--listen",
        &format!("127.0.0.1:{hub}"),
        "--web",
        &format!("127.0.0.1:{web}"),
        "--no-control",
        "--duration",
        "1",
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains(&format!("dashboard: http://127.0.0.1:{web}/")),
        "{t}"
    );
    assert!(!t.contains("control: "), "{t}");
    let o = canpos(&[
        "--web",
        &format!("127.0.0.1:{web}"),
        "scan",
        "--bus",
        "mem://x",
    ]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(2), "{t}");
    assert!(
        t.contains("--web before a command is an option of the demo"),
        "{t}"
    );
    assert!(t.contains("an option of `scan` goes after its name"), "{t}");
}

#[test]
fn scenario_runs_two_sensors_with_events() {
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("s.toml");
    std::fs::write(
        &file,
        format!(
            r#"
bus = "socketcand://127.0.0.1:{port}/can0"
state_dir = "{}"
duration = 1.0
[[sensor]]
node_id = 1
serial = 1
magnets = [100.0]
[[sensor]]
node_id = 2
serial = 2
motion = "sine:center=500,amp=100,period=1"
[[event]]
at = 0.3
sensor = 1
cmd = "fault"
name = "supply-voltage"
on = true
"#,
            dir.path().display()
        ),
    )
    .unwrap();
    let mut run = Proc(
        Command::new(BIN)
            .args(["scenario", file.to_str().unwrap()])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    wait_port(port);
    let mut c = client(port);
    // Sensor 1 (node 2) raises EMCY 0x3100 at 0.3 s.
    let end = Instant::now() + Duration::from_secs(5);
    let mut seen = false;
    while let Ok(Some(rx)) = c.recv_deadline(end) {
        if rx.frame.std_id() == Some(0x82) && rx.frame.data()[..2] == [0x00, 0x31] {
            seen = true;
            break;
        }
    }
    assert!(seen, "no EMCY 0x3100 from node 2");
    let status = run.0.wait().unwrap();
    assert!(status.success(), "{status:?}");
}

/// Issue 36 item 3, as the issue writes it: the EDS of a 5 µm one-channel TMI ("TMI 0750 101 615
/// 252") gives the measuring step's limits the unit accepts (from 5000 nm, 002 §1.7), lists
/// channel-1 objects only (§1.6, §1.12), and maps nothing but 0x6020 / 0x6030 / 0x6300 / 0x6400
/// (§1.2.5). docs/OD.md §1.2 and the core's `od_rows` test check every row of every order code.
#[test]
fn eds_of_an_order_code_is_that_units() {
    let o = canpos(&["eds", "--order-code", "TMI 0750 101 615 252"]);
    assert!(o.status.success(), "{}", text(&o));
    let eds = String::from_utf8_lossy(&o.stdout);
    let section = |name: &str| -> String {
        let start = eds
            .find(&format!("[{name}]\n"))
            .unwrap_or_else(|| panic!("no [{name}]"));
        let rest = &eds[start + name.len() + 3..];
        rest[..rest.find("\n[").unwrap_or(rest.len())].to_string()
    };
    let step = section("6005sub1");
    assert!(step.contains("LowLimit=0x00001388"), "{step}");
    assert!(step.contains("HighLimit=0x000186A0"), "{step}");
    for sub2 in [
        "6010sub2", "6020sub2", "6030sub2", "6300sub2", "6400sub2", "6402sub2",
    ] {
        assert!(
            !eds.contains(&format!("[{sub2}]")),
            "{sub2} in a one-channel EDS"
        );
    }
    assert!(section("6020sub0").contains("DefaultValue=0x01"));
    assert!(section("1001").contains("PDOMapping=0"));
    let two = canpos(&["eds", "--order-code", "TMI 0750 101 625 252"]);
    assert!(String::from_utf8_lossy(&two.stdout).contains("[6020sub2]"));
}
