use std::io::{self, BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::time::Duration;

use serde_json::{json, Value};

use super::*;
use crate::runtime::ControlHandle;

#[test]
fn bus_faults_are_checked_before_anything_changes() {
    use crate::can::Disturbance;
    assert_eq!(
        bus_disturbance("corrupt", Some(500.0), None),
        Ok(Disturbance::CorruptedFrames { per_million: 500 })
    );
    for (kind, value, on) in [
        ("corrupt", Some(1_000_001.0), None),
        ("corrupt", Some(-1.0), None),
        ("corrupt", Some(0.5), None),
        ("corrupt", Some(f64::NAN), None),
        ("corrupt", None, None),
        ("stuck-dominant", Some(0.0), None),
        ("stuck-dominant", Some(60_001.0), None),
        ("stuck-dominant", Some(f64::INFINITY), None),
        ("transceiver", None, None),
        ("lightning", Some(1.0), None),
    ] {
        let r = Request::BusFault {
            sensor: None,
            kind: kind.into(),
            value,
            on,
        };
        assert!(r.validate().is_err(), "{kind} {value:?}");
    }
    // On the runtime's bus: a paced bus refuses nothing valid, and a refusal changes nothing.
    let bus = crate::mem::MemBus::new();
    let port = bus.attach();
    assert!(crate::can::Transport::disturb(
        &port,
        Disturbance::StuckDominant {
            duration: std::time::Duration::from_millis(1000)
        }
    )
    .is_ok());
    assert!(
        crate::can::Transport::disturb(
            &port,
            Disturbance::StuckDominant {
                duration: std::time::Duration::from_millis(1000)
            }
        )
        .is_err(),
        "one interval at a time"
    );
}

#[test]
fn parses_documented_requests() {
    assert_eq!(
        parse_request(r#"{"cmd":"magnet","index":0,"mm":250.0}"#).unwrap(),
        Request::Magnet {
            sensor: None,
            index: 0,
            mm: Some(250.0),
            velocity: None
        }
    );
    assert!(matches!(
        parse_request(r#"{"cmd":"motion","spec":"sine:center=500,amp=200,period=4"}"#),
        Ok(Request::Motion { .. })
    ));
    assert!(matches!(
        parse_request(r#"{"cmd":"fault","name":"missing-magnet","on":true}"#),
        Ok(Request::Fault { on: true, .. })
    ));
    assert_eq!(
        parse_request(r#"{"cmd":"power-cycle"}"#).unwrap(),
        Request::PowerCycle { sensor: None }
    );
    assert_eq!(
        parse_request(r#"{"cmd":"state","sensor":1}"#).unwrap(),
        Request::State { sensor: Some(1) }
    );
    let e = parse_request(r#"{"cmd":"fly"}"#).unwrap_err();
    assert_eq!(e["ok"], false);
    assert!(e["error"].as_str().unwrap().contains("fly"), "{e}");
}

#[test]
fn over_long_line_is_dropped_whole() {
    let mut input = vec![b'x'; 100];
    input.extend_from_slice(b"{\"cmd\":\"power-cycle\"}\n{\"cmd\":\"state\"}\n");
    // A tiny buffer so that the long line arrives in many pieces.
    let mut r = BufReader::with_capacity(7, &input[..]);
    assert_eq!(read_line_limited(&mut r, 64).unwrap(), Line::TooLong);
    assert_eq!(
        read_line_limited(&mut r, 64).unwrap(),
        Line::Text(b"{\"cmd\":\"state\"}".to_vec())
    );
    assert_eq!(read_line_limited(&mut r, 64).unwrap(), Line::Eof);
    // Exactly the limit is fine; a last line without newline counts.
    let mut r = BufReader::with_capacity(3, &b"abcd\nabcde"[..]);
    assert_eq!(
        read_line_limited(&mut r, 4).unwrap(),
        Line::Text(b"abcd".to_vec())
    );
    assert_eq!(read_line_limited(&mut r, 4).unwrap(), Line::TooLong);
    assert_eq!(read_line_limited(&mut r, 4).unwrap(), Line::Eof);
}

#[test]
fn absurd_values_are_refused() {
    let bad = [
        r#"{"cmd":"magnet","index":0,"mm":1e300}"#,
        r#"{"cmd":"magnet","index":0,"mm":-1e300}"#,
        r#"{"cmd":"magnet","index":0,"mm":10,"velocity":-1}"#,
        r#"{"cmd":"ambient","celsius":-300}"#,
        r#"{"cmd":"ambient","celsius":1e300}"#,
        r#"{"cmd":"fault","name":"over-temperature","on":true,"value":-300}"#,
        r#"{"cmd":"fault","name":"supply-voltage","on":true,"value":1e300}"#,
        r#"{"cmd":"fault","name":"extra-magnet","on":true,"value":1e300}"#,
        r#"{"cmd":"fault","name":"bus-off","on":true,"value":3}"#,
        r#"{"cmd":"fault","name":"nonsense","on":true}"#,
        r#"{"cmd":"motion","spec":"static:1e300"}"#,
        r#"{"cmd":"motion","spec":"sine:center=1,amp=1,period=1e-300"}"#,
        r#"{"cmd":"motion","spec":"csv:x.csv"}"#,
    ];
    for line in bad {
        let req = parse_request(line).unwrap();
        assert!(req.validate().is_err(), "{line} accepted");
    }
    let good = [
        r#"{"cmd":"magnet","index":0,"mm":-20,"velocity":100}"#,
        r#"{"cmd":"ambient","celsius":-40}"#,
        r#"{"cmd":"fault","name":"over-temperature","on":true,"value":120}"#,
        r#"{"cmd":"fault","name":"supply-voltage","on":true,"value":9}"#,
        r#"{"cmd":"fault","name":"bus-off","on":false}"#,
        r#"{"cmd":"motion","spec":"sine:center=500,amp=200,period=4"}"#,
    ];
    for line in good {
        let req = parse_request(line).unwrap();
        assert_eq!(req.validate(), Ok(()), "{line}");
    }
}

/// A one-channel TH on an in-process bus, running, and its control handle.
fn runtime(dir: &std::path::Path) -> (crate::RuntimeHandle, ControlHandle) {
    use crate::runtime::{state_file, SensorSetup};
    use canpos_sim::motion::{Profile, Profiles};
    let model = canpos_models::by_name("th").unwrap();
    let cfg = model.default_config;
    let setup = SensorSetup {
        name: "th-control".into(),
        model,
        cfg,
        spec: canpos_sim::SensorSpec::th(f64::from(cfg.stroke_mm), 1).unwrap(),
        seed: 1,
        ideal: true,
        motion: Box::new(Profiles(vec![Profile::Static { pos_mm: 250.0 }])),
        storage: crate::FileStorage::new(state_file(dir, "th", cfg.serial)),
    };
    let bus = crate::mem::MemBus::new();
    let mut rt = crate::runtime::Runtime::new(Box::new(bus.attach()), None);
    rt.add(setup);
    let h = rt.spawn().unwrap();
    let c = h.control();
    (h, c)
}

/// Every variant with every optional field given: what `canpos ctl`, a scenario and the
/// dashboard send (they serialize these).
fn every_request() -> Vec<Request> {
    vec![
        Request::Magnet {
            sensor: Some(0),
            index: 0,
            mm: Some(1.0),
            velocity: Some(2.0),
        },
        Request::Motion {
            sensor: Some(0),
            spec: "static:1".into(),
        },
        Request::Fault {
            sensor: Some(0),
            name: "stall".into(),
            on: true,
            value: Some(1.0),
            channel: Some(0),
        },
        Request::PowerCycle { sensor: Some(0) },
        Request::Ambient {
            sensor: Some(0),
            celsius: 20.0,
        },
        Request::State { sensor: Some(0) },
        Request::BusFault {
            sensor: Some(0),
            kind: "transceiver".into(),
            value: Some(1.0),
            on: Some(true),
        },
        Request::ResetLateness { sensor: Some(0) },
        Request::Nmt {
            sensor: Some(0),
            command: "start".into(),
        },
        Request::Timing {
            sensor: Some(0),
            sdo_delay_ms: Some(1.0),
            sdo_jitter_ms: Some(1.0),
            boot_delay_ms: Some(1.0),
            reset_boot_delay_ms: Some(1.0),
        },
        Request::SetInput {
            sensor: Some(0),
            index: json!("0x6000"),
            sub: Some(json!(1)),
            value: json!(165),
        },
    ]
}

/// Issue 35 item 9: `{"cmd":"magnet","index":0,"mm":700,"velocty":100}` answered ok and
/// the magnet jumped. Every request with an unknown key is refused with the key's name.
#[test]
fn unknown_fields_are_refused_with_their_name() {
    let e = parse_request(r#"{"cmd":"magnet","index":0,"mm":700,"velocty":100}"#).unwrap_err();
    assert_eq!(e["ok"], false);
    assert_eq!(
        e["error"],
        "unknown field `velocty` in a `magnet` request, expected one of `sensor`, `index`, `mm`, `velocity`"
    );
    let reqs = every_request();
    assert_eq!(reqs.len(), COMMANDS.len(), "a request missing here");
    for req in reqs {
        let mut v = serde_json::to_value(&req).unwrap();
        let cmd = v["cmd"].as_str().unwrap().to_string();
        assert!(COMMANDS.contains(&cmd.as_str()), "{cmd} not in COMMANDS");
        // Serialized as the tools send it, it parses back the same.
        assert_eq!(parse_request(&v.to_string()).unwrap(), req, "{v}");
        // The key last, first, or a near miss of a real one (a unit variant used to take
        // anything).
        for key in ["velocty", "Sensor", "a`b, expected x"] {
            v[key] = json!(1);
            let e = parse_request(&v.to_string()).unwrap_err();
            let msg = e["error"].as_str().unwrap();
            assert!(
                msg.starts_with(&format!("unknown field `{key}` in a `{cmd}` request")),
                "{v}: {msg}"
            );
            v.as_object_mut().unwrap().remove(key);
        }
    }
    assert_eq!(
        parse_request(r#"{"cmd":"reset-lateness","x":1}"#).unwrap_err()["error"],
        "unknown field `x` in a `reset-lateness` request, expected `sensor`"
    );
    // docs/CONTROL.md: every request may carry `"sensor": N` (the Python client adds it to
    // each one), `reset-lateness` included.
    for req in every_request() {
        let mut v = serde_json::to_value(&req).unwrap();
        v["sensor"] = json!(1);
        assert!(parse_request(&v.to_string()).is_ok(), "{v}");
    }
    // Still refused with the cmd's name when the cmd comes last.
    let e = parse_request(r#"{"velocty":1,"cmd":"state"}"#).unwrap_err();
    assert!(
        e["error"]
            .as_str()
            .unwrap()
            .starts_with("unknown field `velocty` in a `state` request"),
        "{e}"
    );
    // Fields by position, with no names to check, are no request either.
    for line in [
        r#"["state"]"#,
        r#"["magnet",null,0,250.0,null]"#,
        " [\"reset-lateness\"]",
    ] {
        let e = parse_request(line).unwrap_err();
        assert!(
            e["error"].as_str().unwrap().contains("one JSON object"),
            "{line}: {e}"
        );
    }
}

/// Each request of docs/CONTROL.md's table parses as written there, and the table shows
/// every command.
#[test]
fn the_documented_requests_parse() {
    let doc = include_str!("../../../../docs/CONTROL.md");
    let mut seen = std::collections::BTreeSet::new();
    for row in doc.lines().filter(|l| l.starts_with("| `{\"cmd\":")) {
        let line = &row[3..row[3..].find('`').unwrap() + 3];
        let req = parse_request(line).unwrap_or_else(|e| panic!("docs/CONTROL.md: {line}: {e}"));
        let v = serde_json::to_value(&req).unwrap();
        seen.insert(v["cmd"].as_str().unwrap().to_string());
    }
    for cmd in COMMANDS {
        assert!(
            seen.contains(cmd),
            "docs/CONTROL.md's table shows no `{cmd}`"
        );
    }
}

/// The misspelt key of the issue, on a running sensor: refused, and the magnet stays.
#[test]
fn a_misspelt_key_moves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (h, c) = runtime(dir.path());
    let before = c.request(Request::State { sensor: None });
    assert_eq!(before["true_mm"], json!([250.0]), "{before}");
    let a = answer_line(r#"{"cmd":"magnet","index":0,"mm":700,"velocty":100}"#, &c);
    assert_eq!(a["ok"], false, "{a}");
    assert!(a["error"].as_str().unwrap().contains("`velocty`"), "{a}");
    // A request accepted after the refused one: once it shows, the refused one would
    // have shown too.
    let a = answer_line(r#"{"cmd":"ambient","celsius":21}"#, &c);
    assert_eq!(a["ok"], true, "{a}");
    let st = c.request(Request::State { sensor: None });
    assert_eq!(
        (&st["true_mm"], &st["ambient_c"]),
        (&json!([250.0]), &json!(21.0))
    );
    h.stop().unwrap();
}

/// Connects and sends `state`; the answer line (or the error that ended the read).
fn ask_state(addr: SocketAddr, timeout: Duration) -> io::Result<Value> {
    call(addr, &Request::State { sensor: None }, timeout)
}

/// A control server on a free loopback port that closes connections idle for `idle`.
fn serve_idle(c: ControlHandle, idle: Duration) -> ControlServer {
    serve_with(
        TcpListener::bind("127.0.0.1:0").unwrap(),
        c,
        ServeOptions {
            idle_timeout: idle,
            ..ServeOptions::default()
        },
    )
    .unwrap()
}

/// Issue 35 item 6: 32 idle connections used to lock the control interface out for good.
/// Now a refused client hears so at once, idle connections are closed after the timeout,
/// and a new client is answered within it.
#[test]
fn idle_connections_are_closed_and_a_new_client_gets_in() {
    let dir = tempfile::tempdir().unwrap();
    let (h, c) = runtime(dir.path());
    let idle = Duration::from_secs(2);
    let srv = serve_idle(c, idle);
    let addr = srv.local_addr();
    // 32 clients that ask once (so each is surely being served) and then say nothing.
    let mut quiet = Vec::new();
    for _ in 0..MAX_CONNECTIONS {
        let mut s = TcpStream::connect(addr).unwrap();
        s.write_all(b"{\"cmd\":\"state\"}\n").unwrap();
        let mut r = BufReader::new(s.try_clone().unwrap());
        let mut line = String::new();
        r.read_line(&mut line).unwrap();
        assert!(line.contains("\"ok\":true"), "{line}");
        quiet.push(r);
    }
    let start = std::time::Instant::now();
    // One more is refused with a reason, promptly (not after its own timeout).
    let a = ask_state(addr, Duration::from_secs(10)).unwrap();
    if start.elapsed() < idle {
        assert_eq!(a["ok"], false, "{a}");
        assert!(a["error"].as_str().unwrap().contains("too many"), "{a}");
    }
    // A client that tries again is answered once the idle ones are gone.
    let bound = idle + Duration::from_secs(20);
    let answered = loop {
        let a = ask_state(addr, Duration::from_secs(10)).unwrap();
        if a["ok"] == true {
            break start.elapsed();
        }
        assert!(
            start.elapsed() < bound,
            "still locked out after {bound:?}: {a}"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(answered < bound, "{answered:?}");
    // The idle ones were closed by the server: each reads the end of the stream.
    for r in &mut quiet {
        r.get_ref().set_read_timeout(Some(bound)).unwrap();
        let mut line = String::new();
        assert_eq!(r.read_line(&mut line).unwrap(), 0, "{line}");
    }
    h.stop().unwrap();
}

/// A client that sends requests and reads no answer: the server stops taking its requests
/// once the socket buffers are full (no answers pile up in memory) and closes it after the
/// timeout, while others are served.
#[test]
fn a_client_that_never_reads_is_held_back_and_closed() {
    let dir = tempfile::tempdir().unwrap();
    let (h, c) = runtime(dir.path());
    let idle = Duration::from_secs(1);
    let srv = serve_idle(c, idle);
    let addr = srv.local_addr();
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_write_timeout(Some(Duration::from_millis(500)))
        .unwrap();
    // Each `state` answer is ~100 times its request. The socket buffers hold some MiB of
    // requests and answers; a server that took every request would take all 64 MiB (and
    // owe GiBs of answers).
    let chunk = b"{\"cmd\":\"state\"}\n".repeat(4096);
    let mut sent = 0usize;
    let start = std::time::Instant::now();
    let held_back = loop {
        match s.write(&chunk) {
            Ok(n) => sent += n,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                break true
            }
            // Closed by the server (after it stopped reading): held back too.
            Err(_) => break true,
        }
        if sent > 64 << 20 || start.elapsed() > Duration::from_secs(60) {
            break false;
        }
    };
    assert!(
        held_back,
        "the server took {sent} bytes of requests nobody reads answers to"
    );
    // Another client is served meanwhile, and the stuck one is closed after the timeout.
    assert_eq!(
        ask_state(addr, Duration::from_secs(10)).unwrap()["ok"],
        true
    );
    // Closed by the server: with requests of ours unread there, it resets the connection,
    // and our next write fails (reading instead would free the server to go on).
    let end = std::time::Instant::now() + Duration::from_secs(30);
    let closed = loop {
        match s.write(b"\n") {
            Err(e)
                if !matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                break true
            }
            _ if std::time::Instant::now() > end => break false,
            _ => {}
        }
    };
    assert!(closed, "the stuck connection stays open");
    h.stop().unwrap();
}

#[test]
fn fault_names_round_trip() {
    for f in Fault::ALL {
        assert_eq!(f.name().parse::<Fault>().unwrap(), f);
    }
    let e = "bogus".parse::<Fault>().unwrap_err();
    assert!(e.contains("missing-magnet"), "{e}");
}
