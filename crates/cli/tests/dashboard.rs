//! The dashboard's HTTP API against a TH sensor on an in-process bus: bad requests get a clear
//! error and a fitting status and change nothing; good ones reach the sensor; event streams
//! that a browser leaves cost nothing.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::time::{Duration, Instant};

mod common;

use canpos_cli::dashboard::{self, Controls, Dashboard};
use canpos_cli::device::{build_setup, open_storage, SensorOpts};
use canpos_host::control::Request;
use canpos_host::{MemBus, Runtime, RuntimeHandle};
use serde_json::Value;

struct Rig {
    web: Dashboard,
    rt: Option<RuntimeHandle>,
    _dir: tempfile::TempDir,
}

impl Drop for Rig {
    fn drop(&mut self) {
        if let Some(rt) = self.rt.take() {
            let _ = rt.stop();
        }
    }
}

fn rig() -> Rig {
    let dir = tempfile::tempdir().unwrap();
    let opts = SensorOpts {
        node_id: Some(127),
        magnets: vec![100.0],
        ..SensorOpts::default()
    };
    let mut built = build_setup(&opts, dir.path()).unwrap();
    open_storage(&mut built.setup).unwrap();
    let bus = MemBus::new();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    rt.add(built.setup);
    rt.power_on_all();
    let rt = rt.spawn().unwrap();
    let web = dashboard::start(
        Box::new(bus.attach()),
        "127.0.0.1:0",
        Controls::Local(rt.control(), 1),
        10.0,
    )
    .unwrap();
    let r = Rig {
        web,
        rt: Some(rt),
        _dir: dir,
    };
    // The scan finds the node and its identity is read (model known).
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        let (code, od) = http(r.web.local_addr(), "GET", "/api/nodes/127/od", "");
        if code == 200 && od["model"] == "th" {
            break;
        }
        assert!(
            Instant::now() < until,
            "node 127 not identified: {code} {od}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    r
}

/// One HTTP/1.1 request; (status, JSON body).
fn http(addr: SocketAddr, method: &str, path: &str, body: &str) -> (u16, Value) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let code = text[9..12].parse().unwrap();
    let json = text.split("\r\n\r\n").nth(1).unwrap_or("");
    (code, serde_json::from_str(json).unwrap_or(Value::Null))
}

fn state(r: &Rig) -> Value {
    r.rt.as_ref()
        .unwrap()
        .control()
        .request(Request::State { sensor: None })
}

fn error_of(v: &Value) -> &str {
    assert_eq!(v["ok"], false, "{v}");
    v["error"].as_str().unwrap()
}

#[test]
fn bad_requests_are_refused_with_a_reason_and_change_nothing() {
    let r = rig();
    let a = r.web.local_addr();
    let before = state(&r);

    let (code, v) = http(
        a,
        "POST",
        "/api/nodes/99/control",
        r#"{"cmd":"power-cycle"}"#,
    );
    assert_eq!(code, 404);
    assert!(error_of(&v).contains("unknown node 99"), "{v}");
    let (code, v) = http(a, "GET", "/api/nodes/abc/od", "");
    assert_eq!(code, 400);
    assert!(error_of(&v).contains("abc"), "{v}");
    let (code, v) = http(a, "GET", "/api/nodes/200/sdo/0x6020/1", "");
    assert_eq!(code, 400, "{v}");

    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/0x1234/0", "");
    assert_eq!(code, 404);
    assert!(error_of(&v).contains("unknown object 0x1234/0"), "{v}");
    let (code, v) = http(a, "PUT", "/api/nodes/127/sdo/0x1234/0", r#"{"value":"1"}"#);
    assert_eq!(code, 404, "{v}");
    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/zz/0", "");
    assert_eq!(code, 400, "{v}");
    let (code, v) = http(a, "PUT", "/api/nodes/127/sdo/0x6020/1", r#"{"value":"5"}"#);
    assert_eq!(code, 409);
    assert!(error_of(&v).contains("not writable"), "{v}");
    let (code, v) = http(
        a,
        "PUT",
        "/api/nodes/127/sdo/0x1017/0",
        r#"{"value":"lots"}"#,
    );
    assert_eq!(code, 400);
    assert!(error_of(&v).contains("not a number"), "{v}");
    let (code, v) = http(a, "PUT", "/api/nodes/127/sdo/0x1017/0", "{");
    assert_eq!(code, 400, "{v}");

    let (code, v) = http(
        a,
        "POST",
        "/api/nodes/127/control",
        r#"{"cmd":"fault","name":"gremlins","on":true}"#,
    );
    assert_eq!(code, 404);
    assert!(error_of(&v).contains("unknown fault `gremlins`"), "{v}");
    let (code, v) = http(a, "POST", "/api/nodes/127/control", r#"{"cmd":"state"}"#);
    assert_eq!(code, 400);
    assert!(error_of(&v).contains("unknown command"), "{v}");
    // Checked by the sensor's control interface: magnet 3 of a one-magnet unit.
    let (code, v) = http(
        a,
        "POST",
        "/api/nodes/127/control",
        r#"{"cmd":"magnet","index":3,"mm":500}"#,
    );
    assert_eq!(code, 400);
    assert!(error_of(&v).contains("node 127"), "{v}");
    let (code, v) = http(a, "POST", "/api/nodes/127/control", "[1,2]");
    assert_eq!(code, 400, "{v}");
    let (code, v) = http(a, "GET", "/nothing-here", "");
    assert_eq!(code, 404, "{v}");

    let after = state(&r);
    for k in ["faults", "true_mm", "powered", "nmt", "error_register"] {
        assert_eq!(before[k], after[k], "{k} changed");
    }
}

#[test]
fn good_requests_reach_the_sensor() {
    let r = rig();
    let a = r.web.local_addr();
    let (code, v) = http(
        a,
        "POST",
        "/api/nodes/127/control",
        r#"{"cmd":"magnet","index":0,"mm":321.5}"#,
    );
    assert_eq!(code, 200, "{v}");
    // The magnet is where it was sent once the next measurement cycle has run.
    let until = Instant::now() + Duration::from_secs(5);
    while state(&r)["true_mm"][0] != 321.5 {
        assert!(Instant::now() < until, "{}", state(&r));
        std::thread::sleep(Duration::from_millis(5));
    }
    let (code, v) = http(
        a,
        "PUT",
        "/api/nodes/127/sdo/0x1017/0",
        r#"{"value":"250"}"#,
    );
    assert_eq!(code, 200, "{v}");
    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/0x1017/0", "");
    assert_eq!(code, 200, "{v}");
    assert!(v["value"].as_str().unwrap().starts_with("250 "), "{v}");
    assert_eq!(v["type"], "UNSIGNED16");
    let (code, od) = http(a, "GET", "/api/nodes/127/od", "");
    assert_eq!(code, 200);
    let e = od["entries"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["index"] == "0x6020" && e["sub"] == 1)
        .unwrap();
    assert_eq!(e["type"], "INTEGER32");
    assert_eq!(e["access"], "ro");
}

#[test]
fn a_browser_that_leaves_costs_nothing() {
    let r = rig();
    let a = r.web.local_addr();
    for _ in 0..20 {
        let mut s = TcpStream::connect(a).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        write!(s, "GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n").unwrap();
        let mut rd = BufReader::new(s);
        let mut line = String::new();
        // Until the first event arrives, then the "browser" goes away.
        while !line.starts_with("data:") {
            line.clear();
            assert!(rd.read_line(&mut line).unwrap() > 0);
        }
    }
    let until = Instant::now() + Duration::from_secs(10);
    while r.web.streams() != 0 {
        assert!(
            Instant::now() < until,
            "{} streams still open",
            r.web.streams()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let (code, v) = http(a, "GET", "/api/status", "");
    assert_eq!(code, 200);
    assert_eq!(v["streams"], 0);
}

#[test]
fn a_node_named_with_an_eds_gets_its_object_table() {
    let r = rig();
    let a = r.web.local_addr();
    let eds = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples/io-device.eds");
    let dev = canpos_host::eds_device::load(
        &eds,
        canpos_host::eds_device::FileKind::Eds,
        &canpos_host::eds_device::Overrides {
            node_id: Some(20),
            bitrate_kbps: None,
            serial: None,
        },
    )
    .unwrap();
    let (code, v) = http(a, "GET", "/api/nodes/20/od", "");
    assert_eq!(code, 404, "{v}");
    r.web.pin_model(20, dev.model);
    let (code, od) = http(a, "GET", "/api/nodes/20/od", "");
    assert_eq!(code, 200, "{od}");
    let n = od["entries"].as_array().unwrap().len();
    assert_eq!(n, dev.model.entries.len());
    assert!(n > 10, "{od}");
    // Its objects, not a sensor's: 0x6020 is no object of the I/O device.
    let (code, v) = http(a, "GET", "/api/nodes/20/sdo/0x6020/1", "");
    assert_eq!(code, 404, "{v}");
}

/// `--web` on `run` and on the demo: the URL is printed, the page is served and the
/// dashboard drives the process's own sensor; the demo keeps its status line.
#[test]
fn web_flags_serve_the_dashboard_of_the_process() {
    let dir = tempfile::tempdir().unwrap();
    let (hub, web) = (common::free_port(), common::free_port());
    let state = dir.path().join("state");
    let mut run = common::Proc::start(
        dir.path(),
        &[
            "run",
            "--node-id",
            "127",
            "--bus",
            &format!("socketcand://127.0.0.1:{hub}/can0"),
            "--state-dir",
            state.to_str().unwrap(),
            "--web",
            &format!("127.0.0.1:{web}"),
        ],
    );
    run.wait_for(
        &format!("dashboard on http://127.0.0.1:{web}/"),
        Duration::from_secs(20),
    );
    let a: SocketAddr = format!("127.0.0.1:{web}").parse().unwrap();
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        let (code, v) = http(
            a,
            "POST",
            "/api/nodes/127/control",
            r#"{"cmd":"nmt","command":"start"}"#,
        );
        if code == 200 {
            break;
        }
        assert!(Instant::now() < until, "{code} {v}");
        std::thread::sleep(Duration::from_millis(50));
    }
    let until = Instant::now() + Duration::from_secs(10);
    while http(a, "GET", "/api/status", "").1["frames_per_s"]
        .as_f64()
        .unwrap_or(0.0)
        < 100.0
    {
        assert!(Instant::now() < until, "no TPDOs counted");
        std::thread::sleep(Duration::from_millis(100));
    }
    run.stop();

    let web = common::free_port();
    let mut demo = common::Proc::start(
        dir.path(),
        &[
            "demo",
            "--listen",
            &format!("127.0.0.1:{}", common::free_port()),
            "--web",
            &format!("127.0.0.1:{web}"),
            "--duration",
            "3",
        ],
    );
    demo.wait_for(
        &format!("dashboard: http://127.0.0.1:{web}/"),
        Duration::from_secs(20),
    );
    let (code, page) = {
        let mut s = TcpStream::connect(("127.0.0.1", web)).unwrap();
        write!(s, "GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").unwrap();
        let mut t = String::new();
        s.read_to_string(&mut t).unwrap();
        (t[9..12].to_string(), t)
    };
    assert_eq!(code, "200");
    assert!(page.contains("uPlot.iife.min.js"));
    assert_eq!(demo.wait_exit(Duration::from_secs(20)), Some(0));
    assert!(demo.output().contains("TPDOs"), "{}", demo.output());
}
