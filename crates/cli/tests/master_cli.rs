//! The master commands as a user runs them: exit codes and messages of the `canpos` binary.
//! Each process gets its own in-process bus (`mem://`), so nothing answers: these tests pin the
//! no-answer and usage-error paths; the protocol paths are unit-tested in `src/master/tests.rs`.

mod common;

use std::process::{Command, Output};

fn canpos(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_canpos"))
        .args(args)
        .output()
        .expect("run canpos")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn sdo_read_without_answer_exits_4() {
    let o = canpos(&[
        "sdo",
        "read",
        "5",
        "0x1018",
        "1",
        "--bus",
        "mem://t",
        "--timeout",
        "50",
    ]);
    assert_eq!(o.status.code(), Some(4), "{}", stderr(&o));
    assert!(stderr(&o).contains("error: SDO timeout"), "{}", stderr(&o));
}

#[test]
fn sdo_bad_arguments_fail_before_sending() {
    // Bad values are usage errors (2), as clap's own are.
    let o = canpos(&["sdo", "read", "5", "xyz", "1", "--bus", "mem://t"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("index"), "{}", stderr(&o));
    let o = canpos(&[
        "sdo", "write", "5", "1017", "0", "70000", "--type", "u16", "--bus", "mem://t",
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
}

#[test]
fn nmt_sends_and_succeeds() {
    let o = canpos(&["nmt", "start", "--node", "5", "--bus", "mem://t"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("node 5"));
}

#[test]
fn lss_inquire_without_answer_exits_4() {
    let o = canpos(&[
        "lss",
        "inquire",
        "node-id",
        "--bus",
        "mem://t",
        "--timeout",
        "30",
    ]);
    assert_eq!(o.status.code(), Some(4), "{}", stderr(&o));
}

#[test]
fn unreachable_bus_is_an_error() {
    // Port 1 on loopback: nothing listens there.
    let o = canpos(&["nmt", "start", "--bus", "socketcand://127.0.0.1:1/can0"]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("cannot open the bus"), "{}", stderr(&o));
    // The cause once, with its hint; a typo in the URL gets no hint about hubs.
    assert_eq!(stderr(&o).matches("refused").count(), 1, "{}", stderr(&o));
    let o = canpos(&["nmt", "start", "--bus", "socketcand://127.0.0.1:99999/can0"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("bad port"), "{}", stderr(&o));
    assert!(!stderr(&o).contains("running?"), "{}", stderr(&o));
}

#[test]
fn record_and_replay_files() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("empty.log");
    let o = canpos(&[
        "record",
        rec.to_str().unwrap(),
        "--bus",
        "mem://t",
        "--duration",
        "0.05",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert_eq!(std::fs::read_to_string(&rec).unwrap(), "");
    let log = dir.path().join("in.log");
    std::fs::write(
        &log,
        "(1700000000.000000) can0 181#0102\n(1700000000.020000) can0 080#\n",
    )
    .unwrap();
    let o = canpos(&["replay", log.to_str().unwrap(), "--bus", "mem://t"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(stderr(&o).contains("replayed 2 frames"), "{}", stderr(&o));
}

/// Runs `canpos ARGS` to its end, failing when it takes longer than `limit` (a hang is the
/// defect these tests catch); (exit code, stderr, time taken).
fn bounded(
    args: &[&str],
    limit: std::time::Duration,
) -> (Option<i32>, String, std::time::Duration) {
    use std::time::Instant;
    let t0 = Instant::now();
    let mut child = Command::new(env!("CARGO_BIN_EXE_canpos"))
        .args(args)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run canpos");
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            let mut err = String::new();
            std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut err).unwrap();
            return (s.code(), err, t0.elapsed());
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("canpos {args:?} still ran after {limit:?}");
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
}

/// Issue 36 item 9: `monitor --count N` of a silent node ends when nothing came for its idle
/// time (5 s unless `--idle` says), exit 4 with how many frames came; before, it waited forever.
#[test]
fn monitor_count_of_a_silent_node_ends_at_its_idle_time() {
    use std::time::Duration;
    // The default idle time of a counted monitor (before: no end at all).
    let (code, err, took) = bounded(
        &["monitor", "--node", "5", "--count", "1", "--bus", "mem://t"],
        Duration::from_secs(60),
    );
    assert_eq!(code, Some(4), "{err}");
    assert!(err.contains("silent for 5 s: 0 of 1 frames"), "{err}");
    assert!(took >= Duration::from_secs(5), "{took:?}");
    // --idle S sets it.
    let (code, err, took) = bounded(
        &[
            "monitor", "--node", "5", "--count", "3", "--idle", "0.5", "--bus", "mem://t",
        ],
        Duration::from_secs(30),
    );
    assert_eq!(code, Some(4), "{err}");
    assert!(
        err.contains("monitor: node 5 silent for 0.5 s: 0 of 3 frames"),
        "{err}"
    );
    assert!(took >= Duration::from_millis(500), "{took:?}");
    // Without --count, an idle time given ends it as a plain stop.
    let (code, err, _) = bounded(
        &["monitor", "--idle", "0.3", "--bus", "mem://t"],
        Duration::from_secs(30),
    );
    assert_eq!(code, Some(0), "{err}");
}

/// Issue 36 item 9: `sdo read NODE INDEX` reads sub-index 0 (the request on the bus names it);
/// before, the sub-index was a required argument.
#[test]
fn sdo_read_without_a_sub_index_reads_sub_0() {
    use std::time::Duration;
    let hub = common::free_port();
    let dir = tempfile::tempdir().unwrap();
    let _bus = common::Proc::start(
        dir.path(),
        &["bus", "serve", "--listen", &format!("127.0.0.1:{hub}")],
    );
    common::wait_port(hub);
    let url = format!("socketcand://127.0.0.1:{hub}/can0");
    let mut mon = common::Proc::start(
        dir.path(),
        &["monitor", "--raw", "--passive", "--bus", &url],
    );
    mon.wait_for("bus load at", Duration::from_secs(20));
    let (code, err, _) = bounded(
        &[
            "sdo",
            "read",
            "5",
            "0x1018",
            "--bus",
            &url,
            "--timeout",
            "100",
        ],
        Duration::from_secs(30),
    );
    // Nobody answers: the timeout's exit, not a usage error.
    assert_eq!(code, Some(4), "{err}");
    // The upload request: 0x40, index 0x1018 little-endian, sub-index 0.
    mon.wait_for("605#4018100000000000", Duration::from_secs(20));
}
