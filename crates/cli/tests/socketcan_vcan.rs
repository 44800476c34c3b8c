//! `canpos run --bus socketcan://vcan0` against canpos's own master commands in other processes,
//! on a real kernel CAN stack.
//!
//! Runs only where `CANPOS_VCAN=1` (set by `scripts/uml/run-in-uml.sh`, which boots a User-Mode
//! Linux guest with vcan0 up); elsewhere the test prints a skip note and passes.

use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

const BUS: &str = "socketcan://vcan0";

fn canpos(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_canpos"))
        .args(args)
        .output()
        .expect("run canpos")
}

fn ok(args: &[&str]) -> String {
    let o = canpos(args);
    assert!(
        o.status.success(),
        "canpos {args:?}: {}\n{}",
        o.status,
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

struct Sensor(Child);

impl Drop for Sensor {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn sensor_on_vcan_answers_sdo_nmt_lss_and_pdos() {
    if std::env::var("CANPOS_VCAN").as_deref() != Ok("1") {
        eprintln!("skipped: needs vcan0 (CANPOS_VCAN=1; run under scripts/uml/run-in-uml.sh)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let _sensor = Sensor(
        Command::new(env!("CARGO_BIN_EXE_canpos"))
            .args([
                "run", "--model", "th", "--bus", BUS, "--ideal", "--magnet", "250",
            ])
            .arg("--state-dir")
            .arg(&state)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    // SDO (expedited upload); retried until the sensor is up.
    let end = Instant::now() + Duration::from_secs(10);
    let out = loop {
        let o = canpos(&[
            "sdo",
            "read",
            "127",
            "0x1000",
            "0",
            "--bus",
            BUS,
            "--timeout",
            "200",
        ]);
        if o.status.success() {
            break String::from_utf8_lossy(&o.stdout).into_owned();
        }
        assert!(Instant::now() < end, "no SDO answer on vcan0");
    };
    assert!(out.contains("0x00080196"), "{out}");
    assert!(ok(&["sdo", "read", "127", "0x1008", "0", "--bus", BUS]).contains("C304"));
    // SDO download, read back.
    ok(&[
        "sdo", "write", "127", "0x1017", "0", "100", "--type", "u16", "--bus", BUS,
    ]);
    assert!(ok(&["sdo", "read", "127", "0x1017", "0", "--bus", BUS]).contains("(100)"));

    // NMT start, then record: heartbeats say operational, TPDO1 flows; candump -L format with
    // the interface name and kernel timestamps.
    let log = dir.path().join("rec.log");
    let mut rec = Command::new(env!("CARGO_BIN_EXE_canpos"))
        .arg("record")
        .arg(&log)
        .args(["--bus", BUS, "--duration", "1"])
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(200));
    assert!(ok(&["nmt", "start", "--bus", BUS]).contains("start"));
    assert!(rec.wait().unwrap().success());
    let text = std::fs::read_to_string(&log).unwrap();
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    let mut pdos = 0;
    let mut hb_operational = 0;
    for line in text.lines() {
        let (ts, rest) = line.split_once(") ").expect(line);
        let ts: f64 = ts.trim_start_matches('(').parse().expect(line);
        assert!((now - ts).abs() < 10.0, "timestamp {ts} vs now {now}");
        let (iface, frame) = rest.split_once(' ').expect(line);
        assert_eq!(iface, "vcan0");
        if frame.starts_with("1FF#") {
            pdos += 1;
        }
        if frame == "77F#05" {
            hb_operational += 1;
        }
    }
    assert!(pdos > 100, "{pdos} TPDOs in the recording");
    assert!(hb_operational >= 1, "no operational heartbeat:\n{text}");

    // LSS: configuration state, inquire, back to waiting.
    ok(&["lss", "switch-global", "config", "--bus", BUS]);
    let out = ok(&["lss", "inquire", "--bus", BUS]);
    assert!(out.contains("127"), "{out}");
    ok(&["lss", "switch-global", "waiting", "--bus", BUS]);

    // NMT stop: the TPDOs stop.
    ok(&["nmt", "stop", "--bus", BUS]);
    std::thread::sleep(Duration::from_millis(50));
    let o = canpos(&["record", "-", "--bus", BUS, "--duration", "0.3"]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(!text.contains("1FF#"), "{text}");
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn spawn(args: &[&str], log: &std::path::Path) -> Sensor {
    Sensor(
        Command::new(env!("CARGO_BIN_EXE_canpos"))
            .args(args)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .unwrap(),
    )
}

/// A SocketCAN master on vcan0 guards a canpos sensor that sits on a socketcand hub, across
/// `canpos bus bridge`: true remote frames go over (the hub's RTR extension), answers and SDO
/// traffic come back.
#[test]
fn bridge_carries_true_rtr_guarding_and_sdo_both_ways() {
    use canpos_host::transport::Transport;
    use canpos_stack::Frame;
    if std::env::var("CANPOS_VCAN").as_deref() != Ok("1") {
        eprintln!("skipped: needs vcan0 (CANPOS_VCAN=1; run under scripts/uml/run-in-uml.sh)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let listen = format!("127.0.0.1:{port}");
    let url = format!("socketcand://{listen}/can0");
    let _hub = spawn(
        &["bus", "serve", "--listen", &listen],
        &dir.path().join("hub.log"),
    );
    let state = dir.path().join("state");
    let _sensor = spawn(
        &[
            "run",
            "--model",
            "th",
            "--bus",
            &url,
            "--hub",
            "never",
            "--ideal",
            "--magnet",
            "250",
            "--state-dir",
            state.to_str().unwrap(),
        ],
        &dir.path().join("run.log"),
    );
    // The bridge needs the hub: wait until it listens (a bridge started before that exits
    // with "connection refused", and in the slow UML guest it may do so after the 300 ms the
    // loop below gives it), then retried as before.
    let end = Instant::now() + Duration::from_secs(10);
    while std::net::TcpStream::connect(&listen).is_err() {
        assert!(Instant::now() < end, "the hub did not listen on {listen}");
        std::thread::sleep(Duration::from_millis(20));
    }
    let bridge_log = dir.path().join("bridge.log");
    let mut bridge = loop {
        let mut b = spawn(&["bus", "bridge", BUS, &url], &bridge_log);
        std::thread::sleep(Duration::from_millis(300));
        if b.0.try_wait().unwrap().is_none() {
            break b;
        }
        assert!(
            Instant::now() < end,
            "bridge did not start: {}",
            std::fs::read_to_string(&bridge_log).unwrap_or_default()
        );
    };
    let mut master = canpos_host::socketcan::SocketCanTransport::open("vcan0").unwrap();
    let recv = |m: &mut canpos_host::socketcan::SocketCanTransport, id: u16, within: Duration| {
        let end = Instant::now() + within;
        while let Ok(Some(rx)) = m.recv_deadline(end) {
            if rx.frame.std_id() == Some(id) {
                return Some(rx.frame);
            }
        }
        None
    };
    // SDO across the bridge (vcan0 → hub → sensor → hub → vcan0), retried until all is up.
    let end = Instant::now() + Duration::from_secs(15);
    let sdo = Frame::new(0x67F, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).unwrap();
    let answer = loop {
        master.send(&sdo).unwrap();
        if let Some(f) = recv(&mut master, 0x5FF, Duration::from_millis(300)) {
            break f;
        }
        assert!(
            Instant::now() < end,
            "no SDO answer across the bridge; bridge: {}",
            std::fs::read_to_string(&bridge_log).unwrap_or_default()
        );
    };
    assert_eq!(&answer.data()[4..8], &0x0008_0196u32.to_le_bytes());
    // Node guarding with true RTR frames (DLC 1, as a SocketCAN master sends them).
    let mut toggles = Vec::new();
    for _ in 0..4 {
        master
            .send(&Frame::remote(0x77F, false, 1).unwrap())
            .unwrap();
        let a = recv(&mut master, 0x77F, Duration::from_secs(2)).expect("guarding answer");
        assert!(!a.is_remote(), "{a:?}");
        assert_eq!(a.data().len(), 1);
        assert_eq!(a.data()[0] & 0x7F, 0x7F, "pre-operational: {a:?}");
        toggles.push(a.data()[0] >> 7);
    }
    assert!(toggles.windows(2).all(|w| w[0] != w[1]), "{toggles:?}");
    // Ctrl-C ends the bridge cleanly with its counts.
    unsafe {
        libc::kill(bridge.0.id() as i32, libc::SIGINT);
    }
    let status = bridge.0.wait().unwrap();
    let log = std::fs::read_to_string(&bridge_log).unwrap_or_default();
    assert!(status.success(), "{status}: {log}");
    assert!(log.contains("frames forwarded"), "{log}");
}
