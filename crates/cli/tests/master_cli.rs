//! The master commands as a user runs them: exit codes and messages of the `canpos` binary.
//! Each process gets its own in-process bus (`mem://`), so nothing answers: these tests pin the
//! no-answer and usage-error paths; the protocol paths are unit-tested in `src/master/tests.rs`.

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
