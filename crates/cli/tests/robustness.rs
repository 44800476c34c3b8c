//! Robustness suite (issue 13): every hostile or absurd input gets a clear answer from the
//! `canpos` binary: no panic, no hang, no half-applied request. One test per case of the
//! hostile-input campaign.

mod common;

use std::path::Path;
use std::time::Duration;

use common::{assert_fails, canpos, free_port, run_in, text, Ctl, Proc};

const SHORT: Duration = Duration::from_secs(10);

fn write(dir: &Path, name: &str, body: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, body).unwrap();
    p.to_str().unwrap().to_string()
}

/// Runs a scenario file from `dir` (in-process bus) to its end.
fn scenario(dir: &Path, body: &str) -> std::process::Output {
    let f = write(dir, "s.toml", body);
    run_in(dir, &["scenario", &f, "--state-dir", "state"], SHORT)
}

// ------------------------------------------------------------------------ huge numbers

#[test]
fn scenario_duration_huge_is_an_error_at_its_line() {
    for d in ["1e300", "1e19"] {
        let dir = tempfile::tempdir().unwrap();
        let o = scenario(
            dir.path(),
            &format!("bus = \"mem://r\"\n\nduration = {d}\n[[sensor]]\nmodel = \"th\"\n"),
        );
        assert_fails(&o, 1, "s.toml:3: duration:");
        assert!(text(&o).contains("limit"), "{}", text(&o));
    }
}

#[test]
fn scenario_event_at_huge_is_an_error_at_its_line() {
    let dir = tempfile::tempdir().unwrap();
    let o = scenario(
        dir.path(),
        "bus = \"mem://r\"\nduration = 1\n[[sensor]]\nmodel = \"th\"\n\n[[event]]\nat = 1e300\ncmd = \"power-cycle\"\n",
    );
    assert_fails(&o, 1, "s.toml:7: event 0: at:");
}

#[test]
fn monitor_and_record_duration_huge_are_usage_errors() {
    let o = canpos(&["monitor", "--bus", "mem://r", "--duration", "1e300"]);
    assert_fails(&o, 2, "--duration");
    let o = canpos(&["record", "x.log", "--bus", "mem://r", "--duration", "1e300"]);
    assert_fails(&o, 2, "limit");
    let o = canpos(&["demo", "--duration", "1e19"]);
    assert_fails(&o, 2, "limit");
}

#[test]
fn replay_speed_tiny_is_a_usage_error() {
    let o = canpos(&["replay", "x.log", "--bus", "mem://r", "--speed", "1e-300"]);
    assert_fails(&o, 2, "out of range");
}

#[test]
fn replay_refuses_a_log_too_long_for_its_speed_before_sending() {
    let dir = tempfile::tempdir().unwrap();
    // Two frames 30 years apart: at --speed 0.001 that is beyond the limit.
    let log = write(
        dir.path(),
        "l.log",
        "(0.000000) can0 181#01\n(1000000000.000000) can0 181#02\n",
    );
    let o = run_in(
        dir.path(),
        &["replay", &log, "--bus", "mem://r", "--speed", "0.001"],
        SHORT,
    );
    assert_fails(&o, 1, "limit");
    assert!(!text(&o).contains("replayed"), "{}", text(&o));
}

#[test]
fn replay_reports_a_line_that_is_not_text_and_plays_the_rest_with_skip() {
    let dir = tempfile::tempdir().unwrap();
    for (name, bad_line, good, bad) in [
        (
            "l.log",
            2,
            &b"(0.000000) can0 181#01\n"[..],
            &b"(0.000100) can0 181#\xff\xfe\n"[..],
        ),
        (
            "l.asc",
            3,
            &b"base hex timestamps absolute\n0.000000 1 181 Rx d 1 01\n"[..],
            &b"0.000100 1 181 Rx d 1 \xe9\n"[..],
        ),
    ] {
        let p = dir.path().join(name);
        std::fs::write(&p, [good, bad].concat()).unwrap();
        let p = p.to_str().unwrap();
        let o = run_in(dir.path(), &["replay", p, "--bus", "mem://r"], SHORT);
        assert_fails(&o, 1, "malformed");
        let want = format!(":{bad_line}: not UTF-8 text");
        assert!(text(&o).contains(&want), "{name}: {}", text(&o));
        let o = run_in(
            dir.path(),
            &["replay", p, "--bus", "mem://r", "--on-malformed", "skip"],
            SHORT,
        );
        assert!(o.status.success(), "{name}: {}", text(&o));
        assert!(
            text(&o).contains("replayed 1 frames"),
            "{name}: {}",
            text(&o)
        );
    }
}

#[test]
fn replay_loop_of_a_log_with_nothing_to_send_stops() {
    let dir = tempfile::tempdir().unwrap();
    // Only error frames and a CAN FD frame: nothing a classic bus carries.
    let log = write(
        dir.path(),
        "l.log",
        "(0.000000) can0 20000080#0000000000000000\n(0.000001) can0 123##1DEADBEEF\n",
    );
    let o = run_in(
        dir.path(),
        &["replay", &log, "--bus", "mem://r", "--loop"],
        SHORT,
    );
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("no frame of the log can be sent"),
        "{}",
        text(&o)
    );
    assert!(text(&o).contains("replayed 0 frames"), "{}", text(&o));
}

#[test]
fn nan_or_huge_motion_and_magnets_are_refused() {
    for args in [
        &["--motion", "sine:center=1,amp=1,period=1e-300"][..],
        &["--motion", "static:1e300"],
        &["--motion", "ramp:from=-1e308,to=1e308,v=1,a=1"],
        &["--magnet", "NaN"],
        &["--magnet", "1e300"],
        &["--magnet", "-1e300"],
    ] {
        let mut a = vec!["run", "--bus", "mem://r"];
        a.extend_from_slice(args);
        let o = canpos(&a);
        assert_fails(&o, 2, "");
        assert!(text(&o).starts_with("error: "), "{args:?}: {}", text(&o));
    }
}

#[test]
fn absurd_values_on_the_control_interface_are_refused_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let ctl = format!("127.0.0.1:{port}");
    let mut p = Proc::start(
        dir.path(),
        &[
            "run",
            "--bus",
            "mem://r",
            "--order-code",
            "THS7620MNF11ENNC304321Z04",
            "--magnet",
            "100",
            "--magnet",
            "300",
            "--magnet",
            "500",
            "--magnet",
            "700",
            "--ideal",
            "--control",
            &ctl,
            "--state-dir",
            "state",
        ],
    );
    p.wait_for("control interface on", SHORT);
    let mut c = Ctl::connect(port);
    for bad in [
        r#"{"cmd":"ambient","celsius":-300}"#,
        r#"{"cmd":"magnet","index":0,"mm":1e300}"#,
        r#"{"cmd":"magnet","index":0,"mm":-1e300}"#,
        r#"{"cmd":"magnet","index":4,"mm":10}"#,
        r#"{"cmd":"fault","name":"over-temperature","on":true,"value":-300}"#,
        r#"{"cmd":"fault","name":"missing-magnet","on":true,"channel":4}"#,
        r#"{"cmd":"motion","spec":"sine:center=1,amp=1,period=1e-300"}"#,
        // Issue 35: a misspelt key was ignored and the magnet jumped.
        r#"{"cmd":"magnet","index":0,"mm":700,"velocty":100}"#,
    ] {
        let a = c.request(bad);
        assert_eq!(a["ok"], false, "{bad} → {a}");
        assert!(a["error"].as_str().is_some_and(|e| !e.is_empty()), "{a}");
    }
    // 17 magnets: refused as a whole, not 16 moved and the 17th refused.
    let seventeen = vec!["static:999"; 17].join(";");
    let a = c.request(&format!(r#"{{"cmd":"motion","spec":"{seventeen}"}}"#));
    assert_eq!(a["ok"], false, "{a}");
    // A request accepted after the refused ones: once it shows, so would they have.
    let a = c.request(r#"{"cmd":"magnet","index":3,"mm":650}"#);
    assert_eq!(a["ok"], true, "{a}");
    let st = c.state_when(|st| st["true_mm"][3] == 650.0);
    assert_eq!(
        st["true_mm"],
        serde_json::json!([100.0, 300.0, 500.0, 650.0]),
        "{st}"
    );
    assert_eq!(st["faults"], serde_json::json!([]), "{st}");
}

// ------------------------------------------------------------------------ state files

#[test]
fn fifo_as_state_file_is_refused_at_once() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("state")).unwrap();
    let fifo = dir.path().join("state/th-17143876.bin");
    let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    let o = run_in(
        dir.path(),
        &["run", "--bus", "mem://r", "--state-dir", "state"],
        SHORT,
    );
    assert_fails(&o, 1, "is not a regular file (a FIFO)");
}

#[test]
fn second_process_on_a_state_file_gets_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    // Both without --serial: the model's default serial, the same state file.
    let mut first = Proc::start(
        dir.path(),
        &["run", "--bus", "mem://a", "--state-dir", "state"],
    );
    first.wait_for("canpos: sensor 0:", SHORT);
    let o = run_in(
        dir.path(),
        &["run", "--bus", "mem://b", "--state-dir", "state"],
        SHORT,
    );
    assert_fails(&o, 1, "is in use by another process");
    assert!(text(&o).contains("--serial"), "{}", text(&o));
    // With its own serial the second sensor runs.
    let mut second = Proc::start(
        dir.path(),
        &[
            "run",
            "--bus",
            "mem://b",
            "--state-dir",
            "state",
            "--serial",
            "2",
        ],
    );
    second.wait_for("canpos: sensor 0: th-2", SHORT);
}

#[test]
fn stale_temporary_files_are_removed_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    std::fs::create_dir(&state).unwrap();
    let stale = state.join("th-7.bin.tmp.4194000");
    std::fs::write(&stale, b"torn").unwrap();
    let mut p = Proc::start(
        dir.path(),
        &[
            "run",
            "--bus",
            "mem://r",
            "--serial",
            "7",
            "--state-dir",
            "state",
        ],
    );
    p.wait_for("canpos: sensor 0:", SHORT);
    assert!(!stale.exists());
}

#[test]
fn unwritable_state_directory_is_reported_at_start() {
    let dir = tempfile::tempdir().unwrap();
    // A regular file where the directory would go: not writable for anyone, root included.
    write(dir.path(), "file", "");
    let o = run_in(
        dir.path(),
        &["run", "--bus", "mem://r", "--state-dir", "file/state"],
        SHORT,
    );
    assert_fails(&o, 1, "is not writable");
}

#[test]
fn scenario_sensors_sharing_a_state_file_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let o = scenario(
        dir.path(),
        "bus = \"mem://r\"\nduration = 1\n[[sensor]]\nnode_id = 1\n[[sensor]]\nnode_id = 2\n",
    );
    assert_fails(&o, 1, "would share the state file");
}

// ------------------------------------------------------------------------ control interface

#[test]
fn control_line_over_the_limit_is_rejected_whole() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let ctl = format!("127.0.0.1:{port}");
    let mut p = Proc::start(
        dir.path(),
        &[
            "run",
            "--bus",
            "mem://r",
            "--control",
            &ctl,
            "--state-dir",
            "state",
        ],
    );
    p.wait_for("control interface on", SHORT);
    let mut c = Ctl::connect(port);
    // 64 KiB of padding, then a request in the same line: it must not run.
    let mut line = vec![b' '; 64 * 1024];
    line.extend_from_slice(br#"{"cmd":"fault","name":"sensor-error","on":true}"#);
    line.push(b'\n');
    c.send_raw(&line);
    let a = c.answer();
    assert_eq!(a["ok"], false, "{a}");
    assert!(a["error"].as_str().unwrap().contains("longer than"), "{a}");
    // One error only: the next answer is the next request's.
    let st = c.request(r#"{"cmd":"state"}"#);
    assert_eq!(st["ok"], true, "{st}");
    assert_eq!(st["faults"], serde_json::json!([]), "{st}");
}

#[test]
fn control_connections_are_limited() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let ctl = format!("127.0.0.1:{port}");
    let mut p = Proc::start(
        dir.path(),
        &[
            "run",
            "--bus",
            "mem://r",
            "--control",
            &ctl,
            "--state-dir",
            "state",
        ],
    );
    p.wait_for("control interface on", SHORT);
    let mut open: Vec<Ctl> = (0..32).map(|_| Ctl::connect(port)).collect();
    for c in &mut open {
        assert_eq!(c.request(r#"{"cmd":"state"}"#)["ok"], true);
    }
    let mut extra = Ctl::connect(port);
    let a = extra.answer();
    assert_eq!(a["ok"], false, "{a}");
    assert!(a["error"].as_str().unwrap().contains("too many"), "{a}");
    // A connection closing makes room again (once the server has seen it close).
    drop(open.pop());
    let end = std::time::Instant::now() + SHORT;
    loop {
        let a = Ctl::connect(port).request(r#"{"cmd":"state"}"#);
        if a["ok"] == true {
            break;
        }
        assert!(
            std::time::Instant::now() < end,
            "no room after a close: {a}"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Issue 35 item 6: 32 idle control connections locked the interface out for good (and
/// `canpos ctl` and the dashboard's `--control` link with it). Idle ones are closed after
/// `--control-idle-timeout`; a refused client hears why at once.
#[test]
fn idle_control_connections_are_closed_after_the_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let ctl = format!("127.0.0.1:{port}");
    let mut p = Proc::start(
        dir.path(),
        &[
            "run",
            "--bus",
            "mem://r",
            "--control",
            &ctl,
            "--control-idle-timeout",
            "2",
            "--state-dir",
            "state",
        ],
    );
    p.wait_for("control interface on", SHORT);
    let mut idle: Vec<Ctl> = (0..32).map(|_| Ctl::connect(port)).collect();
    for c in &mut idle {
        assert_eq!(c.request(r#"{"cmd":"state"}"#)["ok"], true);
    }
    let start = std::time::Instant::now();
    let o = canpos(&["ctl", "--control", &ctl, "state"]);
    if start.elapsed() < Duration::from_secs(2) {
        assert_fails(&o, 1, "too many control connections");
    }
    let bound = Duration::from_secs(2) + SHORT;
    loop {
        let o = canpos(&["ctl", "--control", &ctl, "state"]);
        if o.status.success() {
            break;
        }
        assert!(
            start.elapsed() < bound,
            "still locked out after {bound:?}: {}",
            text(&o)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(idle);
}

// ------------------------------------------------------------------------ scenario / CLI

#[test]
fn scenario_validation_names_file_and_line() {
    let cases: [(&str, &str); 7] = [
        (
            "[[sensor]]\nnode_id = 3\nserial = 1\n[[sensor]]\nnode_id = 3\nserial = 2\n",
            "s.toml:6: sensor 1: node-id 3 is already sensor 0's",
        ),
        (
            "bus_bitrate = 7\n[[sensor]]\n",
            "s.toml:2: 7 is not a CAN bit rate",
        ),
        (
            "[[sensor]]\nmodel = \"th\"\nmagnets = [100, 200]\n",
            "s.toml:4: sensor 0: 2 magnets for a th with 1 position channel(s)",
        ),
        (
            "[[sensor]]\nmagnets = [1e300]\n",
            "s.toml:3: sensor 0: magnet position 1e300 mm",
        ),
        (
            "[[sensor]]\n[[event]]\nat = 1\ncmd = \"magnet\"\nindex = 1\nmm = 5\n",
            "s.toml:6: event 0: magnet 1 does not exist",
        ),
        (
            "[[sensor]]\n[[event]]\nat = 1\ncmd = \"ambient\"\ncelsius = -300\n",
            "s.toml:5: event 0: temperature -300 °C is out of range",
        ),
        (
            "[[sensor]]\n[[event]]\nat = 1\ncmd = \"magnet\"\nindex = 0\nmm = 5\nsensor = 4\n",
            "s.toml:8: event 0: sensor 4 does not exist",
        ),
    ];
    for (body, want) in cases {
        let dir = tempfile::tempdir().unwrap();
        let o = scenario(dir.path(), &format!("bus = \"mem://r\"\n{body}"));
        assert_fails(&o, 1, want);
    }
}

#[test]
fn scenario_with_more_than_127_nodes_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut body = String::from("bus = \"mem://r\"\n");
    for i in 0..128 {
        body.push_str(&format!("[[sensor]]\nnode_id = 255\nserial = {i}\n"));
    }
    let o = scenario(dir.path(), &body);
    assert_fails(&o, 1, "at most 127 nodes");
}

#[test]
fn magnet_beyond_the_stroke_is_a_warning_as_on_a_real_unit() {
    let dir = tempfile::tempdir().unwrap();
    let o = scenario(
        dir.path(),
        "bus = \"mem://r\"\nduration = 0.2\n[[sensor]]\nmagnets = [2000]\n",
    );
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    assert!(
        text(&o).contains("s.toml:4: sensor 0: magnet at 2000 mm is outside the stroke"),
        "{}",
        text(&o)
    );
}

#[test]
fn bit_rates_outside_the_cia_table_are_refused() {
    assert_fails(
        &canpos(&["run", "--bus-bitrate", "7"]),
        2,
        "not a CAN bit rate",
    );
    assert_fails(
        &canpos(&["lss", "set-bitrate", "7", "--bus", "mem://r"]),
        2,
        "not in CiA 305 table",
    );
}

#[test]
fn control_magnet_index_beyond_the_model_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let ctl = format!("127.0.0.1:{port}");
    let mut p = Proc::start(
        dir.path(),
        &[
            "run",
            "--bus",
            "mem://r",
            "--control",
            &ctl,
            "--state-dir",
            "state",
        ],
    );
    p.wait_for("control interface on", SHORT);
    let o = run_in(
        dir.path(),
        &["ctl", "--control", &ctl, "magnet", "1", "20"],
        SHORT,
    );
    assert_fails(&o, 1, "magnet 1 does not exist");
}

// ------------------------------------------------------------------------ first hour

#[test]
fn scenario_starts_nodes_holds_nmt_events_and_logs_them_readably() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let f = write(
        dir.path(),
        "s.toml",
        &format!(
            "bus = \"mem://r\"\ncontrol = \"127.0.0.1:{port}\"\nduration = 30\n\
             [[sensor]]\nserial = 1\nnode_id = 1\nnmt = \"operational\"\n\
             [[sensor]]\nserial = 2\nnode_id = 2\n\
             [[event]]\nat = 0.05\nsensor = 1\ncmd = \"nmt\"\ncommand = \"stop\"\n\
             [[event]]\nat = 0.06\nsensor = 1\ncmd = \"fault\"\nname = \"missing-magnet\"\non = true\n"
        ),
    );
    let mut p = Proc::start(dir.path(), &["scenario", &f, "--state-dir", "state"]);
    let out = p.wait_for("fault missing-magnet on", SHORT);
    assert!(out.contains("event at 0.05 s: sensor 1: nmt stop"), "{out}");
    // Readable, not Rust Debug.
    assert!(!out.contains("Fault {"), "{out}");
    let mut c = Ctl::connect(port);
    assert_eq!(c.request(r#"{"cmd":"state"}"#)["nmt"], "operational");
    let st = c.request(r#"{"cmd":"state","sensor":1}"#);
    assert_eq!(st["nmt"], "stopped", "{st}");
    assert_eq!(st["faults"], serde_json::json!(["missing-magnet"]), "{st}");
}

#[test]
fn errors_are_said_once_with_the_prefix() {
    let o = canpos(&[
        "sdo",
        "read",
        "5",
        "0x1000",
        "0",
        "--bus",
        "mem://r",
        "--timeout",
        "20",
    ]);
    assert_fails(&o, 4, "error: SDO timeout");
    let port = free_port();
    let o = canpos(&[
        "scan",
        "--bus",
        &format!("socketcand://127.0.0.1:{port}/can0"),
    ]);
    assert_fails(&o, 1, "error: cannot open the bus");
    assert_eq!(
        text(&o).matches("Connection refused").count(),
        1,
        "{}",
        text(&o)
    );
    let o = canpos(&["scan", "--bus", "socketcand://127.0.0.1:99999/can0"]);
    assert_fails(&o, 2, "bad port");
    assert!(!text(&o).contains("running?"), "{}", text(&o));
}

#[test]
fn help_groups_the_global_options_apart() {
    let o = canpos(&["sdo", "read", "--help"]);
    let t = text(&o);
    let global = t.find("Global options:").expect("a Global options section");
    assert!(t[global..].contains("--rt-priority"), "{t}");
    assert!(!t[..global].contains("--rt-priority"), "{t}");
}

#[test]
fn bit_rates_outside_cia_301_are_usage_errors() {
    let o = canpos(&[
        "bus",
        "serve",
        "--listen",
        "127.0.0.1:0",
        "--bitrate",
        "123",
    ]);
    assert_fails(&o, 2, "not a CAN bit rate");
    let o = canpos(&["run", "--bus", "mem://r", "--bus-bitrate", "300"]);
    assert_fails(&o, 2, "not a CAN bit rate");
    let o = canpos(&["monitor", "--bus", "mem://r", "--bitrate", "0"]);
    assert_fails(&o, 2, "not a CAN bit rate");
    let o = canpos(&["bus", "serve", "--bitrate", "125", "--instant"]);
    assert_fails(&o, 2, "cannot be used with");
}

#[test]
fn bus_faults_out_of_range_are_refused() {
    let o = canpos(&[
        "ctl",
        "--control",
        "127.0.0.1:1",
        "bus-fault",
        "corrupt",
        "abc",
    ]);
    assert_fails(&o, 2, "not a number");
}
