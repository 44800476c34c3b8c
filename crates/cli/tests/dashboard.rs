//! The dashboard's HTTP API against a TH sensor on an in-process bus: bad requests get a clear
//! error and a fitting status and change nothing; good ones reach the sensor; event streams
//! that a browser leaves cost nothing.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::time::{Duration, Instant};

mod common;

use canpos_cli::dashboard::{self, Controls, Dashboard};
use canpos_cli::sensor::{build_setup, open_storage, SensorOpts};
use canpos_host::control::Request;
use canpos_host::{MemBus, Runtime, RuntimeHandle, Transport};
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
    rig_with(
        SensorOpts {
            node_id: Some(127),
            magnets: vec![100.0],
            ..SensorOpts::default()
        },
        "th",
    )
}

/// A dashboard on an in-process bus with one sensor of `opts` on node 127, once the scan has
/// identified it as `model`.
fn rig_with(opts: SensorOpts, model: &str) -> Rig {
    let dir = tempfile::tempdir().unwrap();
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
        if code == 200 && od["model"] == model {
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

/// One HTTP/1.1 request as a script sends it (the dashboard's address in `Host`, a JSON body,
/// no `Origin`); (status, JSON body).
fn http(addr: SocketAddr, method: &str, path: &str, body: &str) -> (u16, Value) {
    let host = format!("Host: {addr}");
    http_with(
        addr,
        method,
        path,
        &[&host, "Content-Type: application/json"],
        body,
    )
}

/// One HTTP/1.1 request with the header lines given; (status, JSON body).
fn http_with(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[&str],
    body: &str,
) -> (u16, Value) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let mut head = format!("{method} {path} HTTP/1.1\r\nConnection: close\r\n");
    for h in headers {
        head.push_str(h);
        head.push_str("\r\n");
    }
    write!(s, "{head}Content-Length: {}\r\n\r\n{body}", body.len()).unwrap();
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

/// The node of a dashboard snapshot.
fn snapshot_node(a: SocketAddr, id: u8) -> Value {
    let (code, s) = http(a, "GET", "/api/snapshot", "");
    assert_eq!(code, 200, "{s}");
    s["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|n| n["node"] == id)
        .cloned()
        .unwrap_or(Value::Null)
}

/// The value of `index`/`sub` among a snapshot node's process objects.
fn process_value(n: &Value, index: &str, sub: u64) -> Option<i64> {
    n["control"]["process"]
        .as_array()?
        .iter()
        .find(|o| o["index"] == index && o["sub"] == sub)?["value"]
        .as_i64()
}

/// An EDS device (examples/io-401.eds) behind the dashboard: its process objects are in the
/// snapshot with its control state, the page's `set-input` sets an input (and its TPDO goes
/// out), and a refused one (an output, a sensor's request) says why and changes nothing.
#[test]
fn an_eds_devices_process_objects_show_and_its_inputs_are_set() {
    let dir = tempfile::tempdir().unwrap();
    let eds = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples/io-401.eds");
    let o = canpos_host::eds_device::Overrides {
        node_id: Some(7),
        bitrate_kbps: None,
        serial: None,
    };
    let dev =
        canpos_host::eds_device::load(&eds, canpos_host::eds_device::FileKind::Eds, &o).unwrap();
    let bus = MemBus::new();
    let mut master = bus.attach();
    let storage = canpos_host::FileStorage::new(dev.state_file(dir.path()));
    let rt = canpos_host::plain::PlainRuntime::new(
        Box::new(bus.attach()),
        None,
        dev.model,
        dev.cfg,
        storage,
    )
    .spawn()
    .unwrap();
    let web = dashboard::start(
        Box::new(bus.attach()),
        "127.0.0.1:0",
        Controls::Local(rt.control(), 1),
        10.0,
    )
    .unwrap();
    web.pin_model(7, &dev.model.table);
    let a = web.local_addr();
    let until = Instant::now() + Duration::from_secs(10);
    let n = loop {
        let n = snapshot_node(a, 7);
        if n["control"]["device"] == "eds" {
            break n;
        }
        assert!(Instant::now() < until, "no control state: {n}");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(n["control"]["process"].as_array().unwrap().len(), 28, "{n}");
    assert_eq!(process_value(&n, "0x6000", 1), Some(0));
    let post = |body: &str| http(a, "POST", "/api/nodes/7/control", body);
    let (code, v) = post(r#"{"cmd":"nmt","command":"start"}"#);
    assert_eq!(code, 200, "{v}");
    let (code, v) = post(r#"{"cmd":"set-input","index":"0x6000","sub":1,"value":"0x5A"}"#);
    assert_eq!(code, 200, "{v}");
    // TPDO1 of node 7 carries it.
    let end = Instant::now() + Duration::from_secs(5);
    let tpdo = loop {
        match master.recv_deadline(end).unwrap() {
            Some(rx) if rx.frame.std_id() == Some(0x187) => break rx.frame,
            Some(_) => {}
            None => panic!("no TPDO1"),
        }
    };
    assert_eq!(tpdo.data(), &[0x5A, 0]);
    let until = Instant::now() + Duration::from_secs(5);
    while process_value(&snapshot_node(a, 7), "0x6000", 1) != Some(0x5A) {
        assert!(Instant::now() < until, "{}", snapshot_node(a, 7));
        std::thread::sleep(Duration::from_millis(50));
    }
    for (body, why) in [
        (
            r#"{"cmd":"set-input","index":"0x6200","sub":1,"value":1}"#,
            "is an output",
        ),
        (
            r#"{"cmd":"set-input","index":"0x6401","sub":1,"value":70000}"#,
            "out of range",
        ),
        (
            r#"{"cmd":"magnet","index":0,"mm":5}"#,
            "no `magnet` request",
        ),
    ] {
        let (code, v) = post(body);
        assert_eq!(code, 400, "{body}: {v}");
        assert!(error_of(&v).contains(why), "{body}: {v}");
    }
    // set-input passes the guard of every other write: another site's page (even with a JSON
    // body), a body of a type a page may send without a preflight, a DNS-rebinding name.
    let host = format!("Host: {a}");
    let rebound = format!("Host: attacker.example:{}", a.port());
    let input = r#"{"cmd":"set-input","index":"0x6000","sub":2,"value":1}"#;
    for (headers, status) in [
        (
            vec![
                &host[..],
                "Origin: http://evil.example",
                "Content-Type: application/json",
            ],
            403,
        ),
        (
            vec![&host[..], "Origin: null", "Content-Type: application/json"],
            403,
        ),
        (vec![&host[..], "Content-Type: text/plain"], 415),
        (vec![&rebound[..], "Content-Type: application/json"], 403),
    ] {
        let (code, v) = http_with(a, "POST", "/api/nodes/7/control", &headers, input);
        assert_eq!(code, status, "{headers:?}: {v}");
    }
    let st = rt.control().request(Request::State { sensor: None });
    let objs = st["process"].as_array().unwrap();
    let changed: Vec<_> = objs.iter().filter(|o| o["value"] != 0).collect();
    assert_eq!(changed.len(), 1, "{changed:?}");
    // The master writes the digital outputs by RPDO1: the page shows them.
    let rpdo1 = canpos_stack::Frame::new(0x207, &[0x3C, 0x81]).unwrap();
    master.send(&rpdo1).unwrap();
    let until = Instant::now() + Duration::from_secs(5);
    loop {
        let n = snapshot_node(a, 7);
        let outs = (
            process_value(&n, "0x6200", 1),
            process_value(&n, "0x6200", 2),
        );
        if outs == (Some(0x3C), Some(0x81)) {
            break;
        }
        assert!(Instant::now() < until, "{outs:?}: {n}");
        std::thread::sleep(Duration::from_millis(50));
    }
    // As a browser renders it: the process objects with the input's value and a Set button
    // for each input, none for an output, and no magnet / fault controls.
    if let Some(browser) = chromium() {
        let png = dir.path().join("io401.png");
        let dom = headless(
            &browser,
            &web.url(),
            &png,
            &["--virtual-time-budget=2000"],
            Duration::from_secs(60),
        )
        .expect("chromium finished");
        let row = |key: &str| {
            let at = dom
                .find(&format!("data-object=\"{key}\""))
                .unwrap_or_else(|| panic!("no row {key}: {dom}"));
            dom[at..at + dom[at..].find("</tr>").unwrap()].to_string()
        };
        let di = row("0x6000/1");
        assert!(di.contains("<td class=\"value\">90</td>"), "{di}");
        assert!(di.contains("input-set"), "{di}");
        let out = row("0x6200/1");
        assert!(out.contains("<td class=\"value\">60</td>"), "{out}");
        assert!(!out.contains("input-set"), "{out}");
        assert!(dom.contains("class=\"sensor-controls\" hidden"), "{dom}");
        let (w, h, idat) = png_facts(&png);
        assert_eq!((w, h), (1200, 900));
        assert!(idat > 10_000, "an empty page: {idat} B");
    }
    drop(web);
    rt.stop().unwrap();
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

/// A fault's name as the control state lists it.
fn faults(r: &Rig) -> Vec<String> {
    state(r)["faults"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            f.as_str()
                .map(str::to_string)
                .unwrap_or_else(|| f.to_string())
        })
        .collect()
}

/// Issue 35 item 4: a page of another origin (a `text/plain` POST needs no CORS preflight) and
/// a DNS-rebinding page (`Host: attacker.example`) change nothing; the page's own origin and a
/// script without `Origin` still do. Reads stay open to any client.
#[test]
fn only_the_pages_own_origin_changes_state() {
    let r = rig();
    let a = r.web.local_addr();
    let host = format!("Host: {a}");
    let own = format!("Origin: http://{a}");
    let fault = r#"{"cmd":"fault","name":"missing-magnet","on":true}"#;

    // Another site's page: a simple cross-origin request, as a form or fetch sends it.
    let (code, v) = http_with(
        a,
        "POST",
        "/api/nodes/127/control",
        &[
            &host,
            "Origin: http://evil.example",
            "Content-Type: text/plain",
        ],
        fault,
    );
    assert_eq!(code, 403, "{v}");
    assert!(error_of(&v).contains("evil.example"), "{v}");
    // Even as JSON (a browser would have needed a preflight the dashboard never grants).
    let (code, v) = http_with(
        a,
        "POST",
        "/api/nodes/127/control",
        &[
            &host,
            "Origin: http://evil.example",
            "Content-Type: application/json",
        ],
        fault,
    );
    assert_eq!(code, 403, "{v}");
    // The right origin, the wrong type; no origin, the wrong type.
    for h in [
        vec![&host[..], &own[..], "Content-Type: text/plain"],
        vec![&host[..]],
    ] {
        let (code, v) = http_with(a, "POST", "/api/nodes/127/control", &h, fault);
        assert_eq!(code, 415, "{h:?}: {v}");
        assert!(error_of(&v).contains("application/json"), "{v}");
    }
    // An opaque origin (a sandboxed frame, a file) is no origin of the page.
    let (code, v) = http_with(
        a,
        "POST",
        "/api/nodes/127/control",
        &[&host, "Origin: null", "Content-Type: application/json"],
        fault,
    );
    assert_eq!(code, 403, "{v}");
    assert!(faults(&r).is_empty(), "{:?}", faults(&r));

    // The page's own origin: the NMT start and a heartbeat time that a power cycle would undo.
    let json = "Content-Type: application/json";
    let (code, v) = http_with(
        a,
        "POST",
        "/api/nodes/127/control",
        &[&host, &own, json],
        r#"{"cmd":"nmt","command":"start"}"#,
    );
    assert_eq!(code, 200, "{v}");
    let (code, v) = http_with(
        a,
        "PUT",
        "/api/nodes/127/sdo/0x1017/0",
        &[&host, &own, json],
        r#"{"value":"250"}"#,
    );
    assert_eq!(code, 200, "{v}");

    // DNS rebinding: attacker.example resolves to the dashboard, so the page is "same origin"
    // with itself; its Host names it.
    let port = a.port();
    let evil_host = format!("Host: attacker.example:{port}");
    let evil_origin = format!("Origin: http://attacker.example:{port}");
    for (method, path, body) in [
        ("PUT", "/api/nodes/127/sdo/0x1017/0", r#"{"value":"700"}"#),
        ("POST", "/api/nodes/127/control", r#"{"cmd":"power-cycle"}"#),
        ("POST", "/api/nodes/127/control", fault),
        ("POST", "/api/scan", "{}"),
    ] {
        for h in [
            vec![&evil_host[..], &evil_origin[..], json],
            vec![&evil_host[..], json],
        ] {
            let (code, v) = http_with(a, method, path, &h, body);
            assert_eq!(code, 403, "{method} {path} {h:?}: {v}");
            assert!(error_of(&v).contains("attacker.example"), "{v}");
        }
    }
    // The right host on another port, or an origin that is not the Host's.
    let other_port = format!("Host: 127.0.0.1:{}", port.wrapping_add(1).max(1));
    let localhost_origin = format!("Origin: http://localhost:{port}");
    for h in [
        vec![&other_port[..], json],
        vec![&host[..], &localhost_origin[..], json],
    ] {
        let (code, v) = http_with(
            a,
            "POST",
            "/api/nodes/127/control",
            &h,
            r#"{"cmd":"power-cycle"}"#,
        );
        assert_eq!(code, 403, "{h:?}: {v}");
    }
    // Reads stay open, whatever the Host: 0x1017 holds the page's value (no write, and no power
    // cycle, which would have restored the stored one), the node is still operational.
    let (code, v) = http_with(a, "GET", "/api/nodes/127/sdo/0x1017/0", &[&evil_host], "");
    assert_eq!(code, 200, "{v}");
    assert!(v["value"].as_str().unwrap().starts_with("250 "), "{v}");
    let st = state(&r);
    assert_eq!(st["nmt"], "operational", "{st}");
    assert_eq!(st["powered"], true, "{st}");
    assert!(faults(&r).is_empty(), "{st}");

    // The page on localhost, and a script without Origin: both work.
    let lh = format!("Host: localhost:{port}");
    let (code, v) = http_with(
        a,
        "POST",
        "/api/nodes/127/control",
        &[&lh, &localhost_origin, json],
        fault,
    );
    assert_eq!(code, 200, "{v}");
    assert_eq!(faults(&r), ["missing-magnet"]);
    let (code, v) = http(
        a,
        "POST",
        "/api/nodes/127/control",
        r#"{"cmd":"fault","name":"missing-magnet","on":false}"#,
    );
    assert_eq!(code, 200, "{v}");
    assert!(faults(&r).is_empty());
}

/// Issue 35 item 5: 1,100 unfinished requests against a sensor's `--web` dashboard under the
/// usual 1,024 descriptors. The web side keeps to its share: a save over SDO (0x1010/1 "save")
/// succeeds meanwhile, the log does not fill with accept errors, and every hanging connection
/// is closed (at once beyond the cap, by the header timeout below it).
#[test]
fn hanging_requests_leave_the_sensor_its_descriptors() {
    use std::os::unix::process::CommandExt;
    use std::process::{Command, Stdio};

    const HANGING: usize = 1_100;
    let dir = tempfile::tempdir().unwrap();
    let (hub, web) = (common::free_port(), common::free_port());
    let state = dir.path().join("state");
    let log = dir.path().join("sensor.log");
    let bus = format!("socketcand://127.0.0.1:{hub}/can0");
    let mut cmd = Command::new(common::BIN);
    cmd.args(["run", "--node-id", "127", "--bus", &bus, "--hub", "always"])
        .args(["--state-dir", state.to_str().unwrap()])
        .args(["--web", &format!("127.0.0.1:{web}")])
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(dir.path().join("sensor.out")).unwrap())
        .stderr(std::fs::File::create(&log).unwrap());
    // SAFETY: setrlimit is async-signal-safe and only touches the child's own limits.
    unsafe {
        cmd.pre_exec(|| {
            let lim = libc::rlimit {
                rlim_cur: 1024,
                rlim_max: 1024,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    struct Kill(std::process::Child);
    impl Drop for Kill {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let _sensor = Kill(cmd.spawn().unwrap());
    let logged = || std::fs::read_to_string(&log).unwrap_or_default();
    let until = Instant::now() + Duration::from_secs(20);
    while !logged().contains("dashboard on") {
        assert!(Instant::now() < until, "no dashboard: {}", logged());
        std::thread::sleep(Duration::from_millis(20));
    }
    let addr: SocketAddr = format!("127.0.0.1:{web}").parse().unwrap();

    // Each connects and sends half a request head, then waits.
    let mut hanging = Vec::with_capacity(HANGING);
    // A connect waits while the listen backlog is full (SYN retries after 1, 3, 7 s); a server
    // that stopped accepting fails the test after a few, not after 1,100 waits.
    let mut unreachable = 0;
    for _ in 0..HANGING {
        if unreachable >= 3 {
            break;
        }
        match TcpStream::connect_timeout(&addr, Duration::from_secs(10)) {
            Ok(mut s) => {
                let _ = write!(s, "GET /api/status HTTP/1.1\r\nHost: 127.0.0.1:{web}\r\n");
                s.set_nonblocking(true).unwrap();
                hanging.push(s);
            }
            Err(_) => unreachable += 1,
        }
    }

    // The save goes through the hub in the same process, to storage in the same process.
    let save = common::run_in(
        dir.path(),
        &[
            "sdo",
            "--bus",
            &bus,
            "--timeout",
            "5000",
            "write",
            "127",
            "0x1010",
            "1",
            "0x65766173",
            "--type",
            "u32",
        ],
        Duration::from_secs(60),
    );
    assert_eq!(
        save.status.code(),
        Some(0),
        "save: {}\nsensor: {}",
        common::text(&save),
        logged()
    );

    // Every hanging connection ends: the server closes it (EOF or reset, after a 503 for those
    // beyond the cap). Generous bound: the header timeout is seconds, not minutes.
    let until = Instant::now() + Duration::from_secs(120);
    let mut buf = [0u8; 512];
    loop {
        hanging.retain_mut(|s| loop {
            match s.read(&mut buf) {
                Ok(0) => return false,
                Ok(_) => continue,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return true,
                Err(_) => return false,
            }
        });
        if hanging.is_empty() {
            break;
        }
        assert!(
            Instant::now() < until,
            "{} of {HANGING} connections still open ({unreachable} could not connect); sensor: {}",
            hanging.len(),
            logged()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(unreachable, 0, "{}", logged());
    let text = logged();
    assert!(!text.contains("Too many open files"), "{text}");
    assert!(!text.contains("panicked"), "{text}");
    // A refusal is logged, not every one: 1st, 2nd, 4th, 8th…
    let refusals = text.matches("web connection refused").count();
    assert!(
        (1..=12).contains(&refusals),
        "{refusals} refusals logged: {text}"
    );
    // And the dashboard serves again.
    let (code, v) = http(addr, "GET", "/api/status", "");
    assert_eq!(code, 200, "{v}");
}

/// Issue 35 item 5: a request whose body never arrives is answered 408 and closed, and changes
/// nothing; the connection's slot is given back. Heads and bodies have a size bound too.
#[test]
fn a_body_that_never_arrives_times_out() {
    let r = rig();
    let a = r.web.local_addr();
    // A head of 64 KiB with no end yet: refused, all of it read (so the close is clean).
    let mut s = TcpStream::connect(a).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let start = format!("GET /api/status HTTP/1.1\r\nHost: {a}\r\nX-Big: ");
    let head = format!("{start}{}", "a".repeat(64 * 1024 - start.len()));
    s.write_all(head.as_bytes()).unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    assert!(text.starts_with("HTTP/1.1 431"), "{text}");
    // A body that grows past 64 KiB: refused once its 65,537th byte is in (no more is sent, so
    // the server's close leaves nothing unread that would reset the connection).
    let mut s = TcpStream::connect(a).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    write!(
        s,
        "PUT /api/nodes/127/sdo/0x1008/0 HTTP/1.1\r\nHost: {a}\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n{}",
        "a".repeat(64 * 1024 + 1)
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    assert!(text.starts_with("HTTP/1.1 413"), "{text}");
    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/0x1017/0", "");
    assert_eq!(code, 200, "{v}");
    let before = v["value"].clone();
    let mut s = TcpStream::connect(a).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    write!(
        s,
        "PUT /api/nodes/127/sdo/0x1017/0 HTTP/1.1\r\nHost: {a}\r\nContent-Type: application/json\r\nContent-Length: 40\r\n\r\n{{\"value\":"
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    assert!(text.starts_with("HTTP/1.1 408"), "{text}");
    assert!(text.contains("did not arrive"), "{text}");
    let (_, v) = http(a, "GET", "/api/nodes/127/sdo/0x1017/0", "");
    assert_eq!(v["value"], before);
    let until = Instant::now() + Duration::from_secs(10);
    while r.web.connections() != 0 {
        assert!(
            Instant::now() < until,
            "{} connections",
            r.web.connections()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Sends one control request to the rig's sensor; panics unless it is answered ok.
fn control(r: &Rig, line: &str) {
    let req = canpos_host::control::parse_request(line).unwrap();
    let v = r.rt.as_ref().unwrap().control().request(req);
    assert_eq!(v["ok"], true, "{line}: {v}");
}

/// The review of issue 35: reads that anyone may send (an `<img>` on any site) queued without
/// a bound while a powered-off node let each time out, a write behind them was answered 503
/// "the bus connection is gone" after 5 s, and was still done 0.5 s later. Now the queue is
/// bounded, a request whose client gave up never goes on the bus, and the answer says what
/// happened: a write that is refused changes nothing.
#[test]
fn a_write_refused_by_a_busy_bus_is_never_done() {
    let r = rig();
    let a = r.web.local_addr();
    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/0x1017/0", "");
    assert_eq!(code, 200, "{v}");
    let before = v["value"].clone();
    assert!(!before.as_str().unwrap().starts_with("777 "), "{v}");

    // A node that answers nothing: each read takes the dashboard's whole SDO timeout.
    control(&r, r#"{"cmd":"fault","name":"power-cycle","on":true}"#);
    for _ in 0..40 {
        let mut s = TcpStream::connect(a).unwrap();
        write!(
            s,
            "GET /api/nodes/127/sdo/1018/1 HTTP/1.1\r\nHost: x\r\n\r\n"
        )
        .unwrap();
        std::thread::sleep(Duration::from_millis(5));
    }
    let (code, put) = http(a, "PUT", "/api/nodes/127/sdo/0x1017/0", r#"{"value":777}"#);
    eprintln!("the write: {code} {put}");
    control(&r, r#"{"cmd":"fault","name":"power-cycle","on":false}"#);
    // The node is powered: no SDO of it can go on the bus unanswered, and the queue is FIFO,
    // so once a read is answered the write (queued before it) was either done or dropped.
    let until = Instant::now() + Duration::from_secs(30);
    let after = loop {
        let (c, v) = http(a, "GET", "/api/nodes/127/sdo/0x1017/0", "");
        if c == 200 {
            break v;
        }
        assert!(Instant::now() < until, "no read answered: {c} {v}");
        std::thread::sleep(Duration::from_millis(50));
    };
    if code == 200 {
        // The write got its turn while the node was powered (a loaded machine): it was done.
        assert!(
            after["value"].as_str().unwrap().starts_with("777 "),
            "{after}"
        );
        return;
    }
    assert_eq!(
        after["value"], before,
        "a refused write ({code} {put}) was done: {after}"
    );
    let why = error_of(&put);
    assert!(
        !why.contains("gone"),
        "the bus connection is not gone: {code} {put}"
    );
    assert!(
        (code == 503 && (why.contains("busy") || why.contains("timed out waiting for the bus")))
            || (code == 502 && why.contains("node 127")),
        "{code} {put}"
    );
}

/// A method a path does not take is answered 405 with its `Allow` header and, as every error
/// of the API, a JSON body (it was empty).
#[test]
fn a_method_a_path_does_not_take_is_refused_in_json() {
    let r = rig();
    let a = r.web.local_addr();
    let before = state(&r);
    for (method, path, allow) in [
        ("PUT", "/api/nodes/127/control", "POST"),
        ("PATCH", "/api/nodes/127/control", "POST"),
        ("GET", "/api/nodes/127/control", "POST"),
        ("DELETE", "/api/nodes/127/sdo/0x1017/0", "GET,HEAD,PUT"),
    ] {
        let mut s = TcpStream::connect(a).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let body = r#"{"cmd":"power-cycle"}"#;
        write!(
            s,
            "{method} {path} HTTP/1.1\r\nHost: {a}\r\nConnection: close\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        )
        .unwrap();
        let mut text = String::new();
        s.read_to_string(&mut text).unwrap();
        let (head, json) = text.split_once("\r\n\r\n").unwrap();
        assert!(head.starts_with("HTTP/1.1 405"), "{method} {path}: {text}");
        let head = head.to_ascii_lowercase();
        assert!(
            head.contains(&format!("\r\nallow: {}", allow.to_ascii_lowercase())),
            "{text}"
        );
        assert!(head.contains("content-type: application/json"), "{text}");
        let v: Value = serde_json::from_str(json).unwrap();
        assert!(
            error_of(&v).contains(&format!("{method} is not allowed on {path}")),
            "{v}"
        );
    }
    let after = state(&r);
    assert_eq!(before["powered"], after["powered"]);
}

/// A two-channel TMI (order code `62x`) on the bus: the dashboard's object table lists its
/// channel-2 objects and reads them over SDO (the model's default unit, one channel, has none:
/// the table of the widest unit is what a tool that does not know the configuration offers).
#[test]
fn a_two_channel_tmi_shows_and_reads_its_channel_2_objects() {
    let r = rig_with(
        SensorOpts {
            order_code: Some("TMI 1000 101 621 106".into()),
            node_id: Some(127),
            magnets: vec![100.0, 300.0],
            ..SensorOpts::default()
        },
        "tmi",
    );
    let a = r.web.local_addr();
    let (code, od) = http(a, "GET", "/api/nodes/127/od", "");
    assert_eq!(code, 200, "{od}");
    let listed = |ix: &str, sub: u64| {
        od["entries"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e["index"] == ix && e["sub"] == sub)
    };
    for ix in ["0x6010", "0x6020", "0x6030", "0x6300", "0x6400", "0x6401"] {
        assert!(listed(ix, 2), "{ix}/2 not in the object table: {od}");
    }
    // The unit answers with channel 2's preset (0) and its array's sub 0 (2 channels).
    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/0x6010/2", "");
    assert_eq!(code, 200, "{v}");
    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/0x6020/0", "");
    assert_eq!((code, &v["hex"]), (200, &serde_json::json!("02")), "{v}");
}

/// `GET /api/snapshot?since=…` with a value that is no sequence number is refused in JSON as
/// every other API error is (the page shows `error`), naming the parameter; the largest number
/// is a sequence number (nothing newer); other query parameters are not the endpoint's concern.
#[test]
fn a_snapshot_query_that_is_no_sequence_number_is_refused_in_json() {
    let r = rig();
    let a = r.web.local_addr();
    for q in [
        "since=abc",
        "since=",
        "since=-1",
        "since=1.5",
        "since=99999999999999999999999",
        "since=1&since=2",
        "since=%00",
    ] {
        let (code, v) = http(a, "GET", &format!("/api/snapshot?{q}"), "");
        assert_eq!(code, 400, "{q}: {v}");
        assert!(error_of(&v).contains("since"), "{q}: {v}");
    }
    for q in ["since=18446744073709551615", "since=0", "", "other=x"] {
        let (code, v) = http(a, "GET", &format!("/api/snapshot?{q}"), "");
        assert_eq!(code, 200, "{q}: {v}");
        assert!(v["nodes"].is_array(), "{q}: {v}");
    }
    let (_, v) = http(a, "GET", "/api/snapshot?since=18446744073709551615", "");
    // Nothing is newer than the largest sequence number.
    let points = v["nodes"].as_array().unwrap().iter().flat_map(|n| {
        n["channels"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["t"].as_array().unwrap().len())
    });
    assert_eq!(points.sum::<usize>(), 0, "{v}");
}

/// Debian's Chromium (`scripts/deps.sh` installs it for the test command), or `None` with a
/// note outside CI.
fn chromium() -> Option<String> {
    for name in ["chromium", "chromium-browser"] {
        let found = std::env::var_os("PATH")
            .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join(name).is_file()));
        if found {
            return Some(name.to_string());
        }
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "no chromium on PATH: scripts/deps.sh installs it"
    );
    eprintln!("skipped: no chromium on PATH (scripts/deps.sh installs it)");
    None
}

/// Runs headless Chromium on `url` with `extra` flags, writing a 1200×900 screenshot to `png`
/// and returning the DOM it dumps (the same run); `None` when it has not finished after
/// `limit` (its process group is killed then).
fn headless(
    browser: &str,
    url: &str,
    png: &Path,
    extra: &[&str],
    limit: Duration,
) -> Option<String> {
    use std::os::unix::process::CommandExt;
    let profile = tempfile::tempdir().unwrap();
    let mut cmd = std::process::Command::new(browser);
    cmd.args([
        "--headless",
        "--disable-gpu",
        "--hide-scrollbars",
        "--window-size=1200,900",
    ])
    .arg(format!("--user-data-dir={}", profile.path().display()))
    .arg(format!("--screenshot={}", png.display()))
    .arg("--dump-dom")
    .args(extra)
    .arg(url)
    .stdin(std::process::Stdio::null())
    .stdout(std::process::Stdio::piped())
    .stderr(std::process::Stdio::null())
    // Its own process group, so that the renderers go with it.
    .process_group(0);
    // SAFETY: geteuid only reads the process's credentials.
    if unsafe { libc::geteuid() } == 0 {
        // Chromium's sandbox refuses to run as root.
        cmd.arg("--no-sandbox");
    }
    let mut child = cmd.spawn().expect("start chromium");
    let mut stdout = child.stdout.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stdout.read_to_string(&mut s);
        s
    });
    let end = Instant::now() + limit;
    loop {
        if child.try_wait().unwrap().is_some() {
            return Some(reader.join().unwrap());
        }
        if Instant::now() > end {
            // SAFETY: kills the process group this test started (its id is the child's pid).
            unsafe { libc::kill(-(child.id() as i32), libc::SIGKILL) };
            let _ = child.wait();
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Width, height and size of the image data (IDAT) of a PNG file.
fn png_facts(png: &Path) -> (u32, u32, usize) {
    let b = std::fs::read(png).unwrap_or_else(|e| panic!("{}: {e}", png.display()));
    assert_eq!(&b[..8], b"\x89PNG\r\n\x1a\n", "{} is no PNG", png.display());
    let (mut at, mut dims, mut idat) = (8, (0, 0), 0);
    while at + 8 <= b.len() {
        let len = u32::from_be_bytes(b[at..at + 4].try_into().unwrap()) as usize;
        let kind = &b[at + 4..at + 8];
        let data = &b[at + 8..(at + 8 + len).min(b.len())];
        match kind {
            b"IHDR" => {
                dims = (
                    u32::from_be_bytes(data[0..4].try_into().unwrap()),
                    u32::from_be_bytes(data[4..8].try_into().unwrap()),
                )
            }
            b"IDAT" => idat += data.len(),
            _ => {}
        }
        at += 12 + len;
    }
    (dims.0, dims.1, idat)
}

/// Issue 36 item 8: a browser that just loads the page of a running TH's `--web` — headless
/// Chromium's own `--screenshot`, no script driving the page — shows node 127 with a position;
/// with a virtual-time budget it finishes (the updates keep no request open) and goes live;
/// plain GETs of the page and of its data answer with the node. Before: the screenshot showed
/// "connecting…" and an empty table, and a virtual-time budget never ended.
#[test]
fn a_headless_screenshot_of_the_page_shows_the_node_and_its_position() {
    let Some(browser) = chromium() else { return };
    let dir = tempfile::tempdir().unwrap();
    let web = common::free_port();
    // The README's TH example with --web.
    let mut run = common::Proc::start(
        dir.path(),
        &[
            "run",
            "--model",
            "th",
            "--node-id",
            "127",
            "--magnet",
            "250",
            "--bus",
            "mem://item8",
            "--state-dir",
            "./state",
            "--web",
            &format!("127.0.0.1:{web}"),
        ],
    );
    run.wait_for("dashboard on http://", Duration::from_secs(20));
    let a: SocketAddr = format!("127.0.0.1:{web}").parse().unwrap();
    let url = format!("http://{a}/");
    // The dashboard has met the node (its scan's answer) and read its identity.
    let until = Instant::now() + Duration::from_secs(10);
    let snap = loop {
        let (code, v) = http(a, "GET", "/api/snapshot", "");
        let node = v["nodes"]
            .as_array()
            .and_then(|ns| ns.iter().find(|n| n["node"] == 127));
        if code == 200 && node.is_some_and(|n| n["model"] == "th" && n["positions"][0].is_number())
        {
            break v;
        }
        assert!(
            Instant::now() < until,
            "no node 127 in /api/snapshot: {code} {v}"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(snap["seq"].is_u64(), "{snap}");
    // The page itself, as curl gets it: the node's row with its position.
    let mut s = TcpStream::connect(a).unwrap();
    write!(
        s,
        "GET / HTTP/1.1\r\nHost: {a}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut page = String::new();
    s.read_to_string(&mut page).unwrap();
    let row = table_row(&page, 127).unwrap_or_else(|| panic!("no row of node 127: {page}"));
    assert!(has_position(&row), "no position in {row}");

    // The screenshot at the load event, and with a virtual-time budget (which polls run in).
    let blank = dir.path().join("blank.png");
    headless(
        &browser,
        "about:blank",
        &blank,
        &[],
        Duration::from_secs(60),
    )
    .expect("chromium on about:blank did not finish within 60 s");
    let blank_idat = png_facts(&blank).2;
    for extra in [&[][..], &["--virtual-time-budget=3000"][..]] {
        let png = dir.path().join("shot.png");
        let _ = std::fs::remove_file(&png);
        let dom =
            headless(&browser, &url, &png, extra, Duration::from_secs(60)).unwrap_or_else(|| {
                panic!(
                    "chromium {extra:?} {url} did not finish within 60 s (the page kept it busy)"
                )
            });
        let row = table_row(&dom, 127)
            .unwrap_or_else(|| panic!("chromium {extra:?}: no row of node 127 in the DOM: {dom}"));
        assert!(
            has_position(&row),
            "chromium {extra:?}: no position in {row}"
        );
        assert!(row.contains("Temposonics TH"), "{row}");
        let (w, h, idat) = png_facts(&png);
        assert_eq!((w, h), (1200, 900), "{}", png.display());
        // A page with a table and a panel compresses far worse than an empty white one.
        assert!(
            idat > 4 * blank_idat,
            "screenshot looks blank: {idat} B of image data, a blank page {blank_idat} B"
        );
        if !extra.is_empty() {
            // Within the budget the page's updates arrived.
            assert!(
                dom.contains(r#"<span id="link">live</span>"#),
                "chromium {extra:?}: not live: {dom}"
            );
        }
    }
    let _ = std::fs::copy(
        dir.path().join("shot.png"),
        Path::new(env!("CARGO_TARGET_TMPDIR")).join("dashboard-screenshot.png"),
    );
    run.stop();
}

/// The `<tr data-node="N">…</tr>` of a page's node table, its tags stripped.
fn table_row(html: &str, node: u8) -> Option<String> {
    let start = html.find(&format!(r#"<tr data-node="{node}">"#))?;
    let end = start + html[start..].find("</tr>")?;
    let mut text = String::new();
    let mut in_tag = false;
    for c in html[start..end].chars() {
        match c {
            '<' => in_tag = true,
            '>' => {
                in_tag = false;
                text.push(' ');
            }
            c if !in_tag => text.push(c),
            _ => {}
        }
    }
    Some(text)
}

/// Whether a text holds a position in mm: digits, a point, three digits, " mm".
fn has_position(t: &str) -> bool {
    t.match_indices(" mm").any(|(i, _)| {
        let b = &t.as_bytes()[..i];
        b.len() >= 5
            && b[b.len() - 3..].iter().all(u8::is_ascii_digit)
            && b[b.len() - 4] == b'.'
            && b[b.len() - 5].is_ascii_digit()
    })
}

/// One GET as a script sends it; (status, body text).
fn get_text(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let code = text[9..12].parse().unwrap();
    let body = text.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    (code, body.to_string())
}

/// TPDO `n`'s COB-ID and mapping as `GET /api/nodes/127/pdo` reads them.
fn tpdo(a: SocketAddr, n: usize) -> (Value, Vec<Value>) {
    let (code, v) = http(a, "GET", "/api/nodes/127/pdo", "");
    assert_eq!(code, 200, "{v}");
    let t = &v["tpdos"][n - 1];
    assert_eq!(t["tpdo"], n, "{v}");
    (
        t["cob_id"].clone(),
        t["mapping"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| m["raw"].clone())
            .collect(),
    )
}

/// The PDO view names what each TPDO maps; a remap the body or the node refuses changes
/// nothing (the node's refusal after the procedure invalidated the TPDO included: the old
/// mapping is written back), a good one is read back (issue 38 item 4, D46).
#[test]
fn a_refused_remap_changes_nothing_and_a_good_one_is_read_back() {
    let r = rig();
    let a = r.web.local_addr();
    let (code, v) = http(a, "GET", "/api/nodes/127/pdo", "");
    assert_eq!(code, 200, "{v}");
    let t1 = &v["tpdos"][0];
    assert_eq!(t1["mapping"][0]["name"], "Position value channel 1", "{v}");
    assert_eq!(t1["valid"], true, "{v}");
    let before = tpdo(a, 1);
    assert_eq!(before.1.len(), 3, "{before:?}");
    let path = "/api/nodes/127/pdo/1";
    let too_many = format!(r#"{{"mapping":[{}]}}"#, vec![r#""0x6300/1""#; 65].join(","));
    for (code, p, body, why) in [
        (400, path, "not json", "bad body"),
        (400, path, r#"{"map":[]}"#, "expected {\"mapping\""),
        (400, path, &too_many, "at most 64"),
        (
            400,
            path,
            r#"{"mapping":["0x7777/1"]}"#,
            "has no object 0x7777/1",
        ),
        (
            400,
            path,
            r#"{"mapping":["0x1008/0"]}"#,
            "no size a PDO could carry",
        ),
        (400, path, r#"{"mapping":[],"event_ms":70000}"#, "0…65535"),
        (
            404,
            "/api/nodes/127/pdo/9",
            r#"{"mapping":[]}"#,
            "no TPDO `9`",
        ),
        (
            502,
            path,
            r#"{"mapping":["0x6020/1","0x1017/0"]}"#,
            "SDO abort 0x06040041",
        ),
        (
            502,
            path,
            r#"{"mapping":["0x6020/1","0x6020/2","0x6020/3"]}"#,
            "SDO abort 0x06040042",
        ),
    ] {
        let (c, v) = http(a, "PUT", p, body);
        assert_eq!(c, code, "{body}: {v}");
        assert!(error_of(&v).contains(why), "{body}: {v}");
        if c == 502 {
            assert!(error_of(&v).contains("written back"), "{v}");
        }
        assert_eq!(tpdo(a, 1), before, "after {body}");
    }
    let (c, v) = http(
        a,
        "PUT",
        path,
        r#"{"mapping":["0x6020/1","0x6020/2"],"event_ms":5}"#,
    );
    assert_eq!(c, 200, "{v}");
    assert_eq!(v["tpdo"]["event_ms"], 5, "{v}");
    assert_eq!(
        tpdo(a, 1),
        (
            before.0,
            vec![
                Value::from("0x60200120".to_string()),
                Value::from("0x60200220".to_string())
            ]
        )
    );
}

/// The DCF export holds the values read, nothing before a read; the EDS is the model's; the
/// object table shows each object's range (issue 38 item 3).
#[test]
fn the_dcf_export_holds_the_values_read() {
    let r = rig();
    let a = r.web.local_addr();
    let (code, v) = http(a, "GET", "/api/nodes/127/dcf", "");
    assert_eq!(code, 409, "{v}");
    assert!(error_of(&v).contains("read all first"), "{v}");
    let (code, v) = http(
        a,
        "PUT",
        "/api/nodes/127/sdo/0x1017/0",
        r#"{"value":"250"}"#,
    );
    assert_eq!(code, 200, "{v}");
    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/0x1017/0", "");
    assert_eq!(code, 200, "{v}");
    let (code, v) = http(a, "GET", "/api/nodes/127/values", "");
    assert_eq!(code, 200, "{v}");
    assert_eq!(v["values"][0]["index"], "0x1017", "{v}");
    let (code, dcf) = get_text(a, "/api/nodes/127/dcf");
    assert_eq!(code, 200, "{dcf}");
    let section = &dcf[dcf.find("[1017]").expect("no [1017] section")..];
    let section = &section[..section[1..].find("\n[").unwrap_or(section.len() - 1) + 1];
    let value = section
        .lines()
        .find_map(|l| l.strip_prefix("ParameterValue="))
        .unwrap_or_else(|| panic!("no ParameterValue: {section}"));
    let value = match value.strip_prefix("0x") {
        Some(h) => u32::from_str_radix(h, 16).unwrap(),
        None => value.parse().unwrap(),
    };
    assert_eq!(value, 250, "{section}");
    assert!(dcf.contains("NodeID=0x7F"), "{dcf}");
    // Only what was read: the heartbeat consumer was not.
    assert!(!dcf[dcf.find("[1016").unwrap_or(0)..]
        .split("\n[")
        .next()
        .unwrap_or("")
        .contains("ParameterValue"));
    let (code, eds) = get_text(a, "/api/nodes/127/eds");
    assert_eq!(code, 200, "{eds}");
    assert!(eds.contains("ProductName=Temposonics TH CANbus"), "{eds}");
    assert!(!eds.contains("ParameterValue"), "{eds}");
    let (_, od) = http(a, "GET", "/api/nodes/127/od", "");
    let hb = od["entries"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["index"] == "0x1017")
        .unwrap();
    assert_eq!(hb["range"]["text"], "0 … 65535", "{hb}");
}

/// The trace's and transmitter's state changes (a frame once or periodically, NMT, clear) pass
/// the guard of every write: another site's origin, `Origin: null` and a body that is not
/// typed JSON are refused and nothing goes on the bus; the page's own origin sends (issue 38
/// item 9).
#[test]
fn the_transmitter_passes_the_guard_of_every_write() {
    let bus = MemBus::new();
    let mut peer = bus.attach();
    let web = watch_only(Box::new(bus.attach()));
    let a = web.local_addr();
    let host = format!("Host: {a}");
    let own = format!("Origin: http://{a}");
    let json = "Content-Type: application/json";
    let once = r#"{"id":"0x123","data":"11 22"}"#;
    let writes = [
        ("/api/send", once),
        ("/api/send", r#"{"id":"0x124","period_ms":5}"#),
        ("/api/nmt", r#"{"command":"stop","node":0}"#),
        ("/api/trace/clear", "{}"),
        ("/api/send/renew", r#"{"lease":"page-x"}"#),
        ("/api/send/stop", r#"{"lease":"page-x"}"#),
    ];
    for (path, body) in writes {
        for h in [
            vec![&host[..], "Origin: http://evil.example", json],
            vec![&host[..], "Origin: null", json],
            vec![&host[..], &own[..], "Content-Type: text/plain"],
        ] {
            let (code, v) = http_with(a, "POST", path, &h, body);
            assert!(code == 403 || code == 415, "{path} {h:?}: {code} {v}");
        }
    }
    let (code, v) = http_with(a, "GET", "/api/send", &[&host], "");
    assert_eq!(
        (code, v["periodic"].as_array().map(Vec::len)),
        (200, Some(0)),
        "{v}"
    );
    // Nothing of theirs reached the bus (the dashboard's scan did).
    let theirs = |f: &canpos_stack::Frame| matches!(f.id(), 0x000 | 0x123 | 0x124);
    let until = Instant::now() + Duration::from_millis(300);
    while let Some(rx) = peer.recv_deadline(until).unwrap() {
        assert!(!theirs(&rx.frame), "a refused request sent {:?}", rx.frame);
    }
    // The page's own origin: sent.
    let (code, v) = http_with(a, "POST", "/api/send", &[&host, &own, json], once);
    assert_eq!(code, 200, "{v}");
    let until = Instant::now() + Duration::from_secs(5);
    loop {
        let rx = peer
            .recv_deadline(until)
            .unwrap()
            .expect("0x123 on the bus");
        if rx.frame.id() == 0x123 {
            assert_eq!(rx.frame.data(), [0x11, 0x22]);
            break;
        }
    }
}

/// A dashboard of `bus` without control interfaces.
fn watch_only(bus: Box<dyn Transport>) -> Dashboard {
    dashboard::start(bus, "127.0.0.1:0", Controls::Remote(Vec::new()), 10.0).unwrap()
}

/// `GET /api/trace`'s bit rate and where it comes from.
fn bitrate(a: SocketAddr) -> (u64, String) {
    let (code, v) = http(a, "GET", "/api/trace", "");
    assert_eq!(code, 200, "{v}");
    (
        v["bitrate_kbps"].as_u64().unwrap(),
        v["bitrate_from"].as_str().unwrap().to_string(),
    )
}

/// The bus load is figured at a bit rate the header names with its source (D60): an
/// in-process bus's own pacing; a socketcand hub names none (1000 kbit/s, assumed) unless a
/// sensor's control state or `canpos dashboard --bitrate` says it.
#[test]
fn the_bus_load_names_its_bit_rate_and_whether_it_was_given() {
    use canpos_host::bus::Pacing;
    use canpos_host::socketcand::HubConfig;
    let dir = tempfile::tempdir().unwrap();
    let mem = MemBus::with_pacing(Pacing::Paced(250));
    let d = watch_only(Box::new(mem.attach()));
    assert_eq!(bitrate(d.local_addr()), (250, "bus".into()));

    // A hub paced at 500 kbit/s: its protocol does not say so.
    let hub = canpos_host::Hub::bind_with(
        "127.0.0.1:0",
        HubConfig {
            pacing: Pacing::Paced(500),
            ..Default::default()
        },
    )
    .unwrap();
    let url = format!("socketcand://127.0.0.1:{}/can0", hub.local_addr().port());
    let _hub = hub.spawn().unwrap();
    let d = watch_only(canpos_host::open(&url).unwrap());
    assert_eq!(bitrate(d.local_addr()), (1000, "assumed".into()));
    d.set_bitrate(500);
    assert_eq!(bitrate(d.local_addr()), (500, "given".into()));

    // A sensor started with --bus-bitrate 500 on that hub: its control state says it.
    let mut built = build_setup(
        &SensorOpts {
            node_id: Some(9),
            magnets: vec![100.0],
            ..SensorOpts::default()
        },
        dir.path(),
    )
    .unwrap();
    open_storage(&mut built.setup).unwrap();
    let mut rt = Runtime::new(canpos_host::open(&url).unwrap(), Some(500));
    rt.add(built.setup);
    rt.power_on_all();
    let rt = rt.spawn().unwrap();
    let d = dashboard::start(
        canpos_host::open(&url).unwrap(),
        "127.0.0.1:0",
        Controls::Local(rt.control(), 1),
        10.0,
    )
    .unwrap();
    let until = Instant::now() + Duration::from_secs(10);
    while bitrate(d.local_addr()) != (500, "sensor".into()) {
        assert!(Instant::now() < until, "{:?}", bitrate(d.local_addr()));
        std::thread::sleep(Duration::from_millis(50));
    }
    // Given on the command line: it wins over the sensor's, and the header is told so.
    d.set_bitrate(125);
    std::thread::sleep(Duration::from_millis(600));
    assert_eq!(bitrate(d.local_addr()), (125, "given".into()));
    drop(d);
    let _ = rt.stop();

    // `canpos dashboard --bitrate`, in kbit/s or bit/s; a rate CiA 301 does not have is a usage
    // error.
    let web = common::free_port();
    let mut p = common::Proc::start(
        dir.path(),
        &[
            "dashboard",
            "--bus",
            &url,
            "--listen",
            &format!("127.0.0.1:{web}"),
            "--bitrate",
            "250000",
        ],
    );
    p.wait_for("canpos dashboard: http", Duration::from_secs(20));
    let a: SocketAddr = format!("127.0.0.1:{web}").parse().unwrap();
    assert_eq!(bitrate(a), (250, "given".into()));
    p.stop();
    let o = common::canpos(&["dashboard", "--bus", &url, "--bitrate", "251"]);
    common::assert_fails(&o, 2, "not a CAN bit rate");
}

/// A periodic transmission a script starts runs on a lease (one is made up when it names
/// none) or for a duration it gives (D61): unrenewed, it ends within the lease and its frames
/// stop on the bus; a renewal keeps it; a lease is stopped whole; a bad term changes nothing.
#[test]
fn a_scripts_periodic_transmission_ends_with_its_lease_unless_renewed() {
    let bus = MemBus::new();
    let mut peer = bus.attach();
    let web = watch_only(Box::new(bus.attach()));
    let a = web.local_addr();
    let list = || {
        let (code, v) = http(a, "GET", "/api/send", "");
        assert_eq!(code, 200, "{v}");
        v["periodic"].as_array().unwrap().clone()
    };
    // Refused, nothing started.
    for bad in [
        r#"{"id":"0x124","period_ms":10,"lease":"a b"}"#,
        r#"{"id":"0x124","period_ms":10,"lease":"x","duration_s":5}"#,
        r#"{"id":"0x124","period_ms":10,"duration_s":0}"#,
        r#"{"id":"0x124","period_ms":10,"duration_s":1e300}"#,
        r#"{"id":"0x124","lease":"x"}"#,
    ] {
        let (code, v) = http(a, "POST", "/api/send", bad);
        assert_eq!(code, 400, "{bad}: {v}");
    }
    assert_eq!(http(a, "POST", "/api/send/renew", "{}").0, 400);
    assert!(list().is_empty());
    // The page's renewing worker is served.
    let (code, js) = get_text(a, "/lease.js");
    assert!(code == 200 && js.contains("/api/send/renew"), "{code} {js}");

    // No lease named: one is made up and answered.
    let sent = Instant::now();
    let (code, v) = http(
        a,
        "POST",
        "/api/send",
        r#"{"id":"0x124","data":"01","period_ms":10}"#,
    );
    assert_eq!(code, 200, "{v}");
    let lease = v["lease"].as_str().unwrap().to_string();
    assert_eq!(v["lease_s"], 5);
    let (code, v) = http(
        a,
        "POST",
        "/api/send",
        r#"{"id":"0x125","period_ms":10,"duration_s":600}"#,
    );
    assert_eq!((code, &v["lease"]), (200, &Value::Null), "{v}");
    let (code, v) = http(
        a,
        "POST",
        "/api/send",
        r#"{"id":"0x126","period_ms":10,"lease":"script-b"}"#,
    );
    assert_eq!(code, 200, "{v}");
    let l = list();
    assert_eq!(l.len(), 3, "{l:?}");
    assert!(l[1]["ends_in_s"].as_f64().unwrap() > 500.0, "{l:?}");
    // script-b stops its own at once; the renewal answers how many a lease holds.
    let (code, v) = http(a, "POST", "/api/send/stop", r#"{"lease":"script-b"}"#);
    assert_eq!((code, &v["stopped"]), (200, &serde_json::json!(1)), "{v}");
    let (code, v) = http(a, "POST", "/api/send/renew", r#"{"lease":"script-b"}"#);
    assert_eq!((code, &v["renewed"]), (200, &serde_json::json!(0)), "{v}");

    // 0x124's lease is never renewed: it ends, no earlier than the lease, within a bound.
    let until = Instant::now() + Duration::from_secs(30);
    while list().iter().any(|p| p["id"] == "0x124") {
        assert!(Instant::now() < until, "0x124 still sent: {:?}", list());
        std::thread::sleep(Duration::from_millis(100));
    }
    let took = sent.elapsed();
    assert!(took >= Duration::from_millis(4900), "ended after {took:?}");
    eprintln!("the unrenewed lease {lease} ended {took:?} after its start");
    // Its frames stop on the bus (what was sent before is drained first); 0x125 goes on.
    while peer.try_recv().unwrap().is_some() {}
    let (mut n124, mut n125) = (0, 0);
    let until = Instant::now() + Duration::from_millis(500);
    while let Some(rx) = peer.recv_deadline(until).unwrap() {
        match rx.frame.id() {
            0x124 => n124 += 1,
            0x125 => n125 += 1,
            _ => {}
        }
    }
    assert_eq!(n124, 0, "0x124 sent after its lease ended");
    assert!(n125 > 0, "the job with a duration stopped too");
    let (code, v) = http(a, "POST", "/api/send/stop", r#"{"id":"0x125"}"#);
    assert_eq!(code, 200, "{v}");
}

/// The dashboard waits for an SDO answer as long as `canpos sdo` does by default (1 s, one
/// constant; D45): a device that answers in 0.6 s is read from the page (with the 300 ms it had
/// the page failed where `canpos sdo` worked), one that answers after 1.5 s times out.
#[test]
fn the_dashboard_waits_for_an_sdo_answer_as_long_as_canpos_sdo() {
    let r = rig();
    let a = r.web.local_addr();
    control(&r, r#"{"cmd":"timing","sdo_delay_ms":600}"#);
    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/0x1017/0", "");
    assert_eq!(code, 200, "a 0.6 s answer: {v}");
    control(&r, r#"{"cmd":"timing","sdo_delay_ms":1500}"#);
    let t0 = Instant::now();
    let (code, v) = http(a, "GET", "/api/nodes/127/sdo/0x1017/0", "");
    assert_eq!(code, 502, "a 1.5 s answer: {v}");
    assert!(error_of(&v).contains("SDO timeout"), "{v}");
    assert!(
        t0.elapsed() >= Duration::from_millis(1000),
        "{:?}",
        t0.elapsed()
    );
    control(&r, r#"{"cmd":"timing","sdo_delay_ms":0}"#);
}
