//! Issue 36 item 1, behind the hub: a `canpos run` sensor process on `canpos bus serve`,
//! stopped (SIGSTOP) for 200 ms twenty times while it sends a TPDO every 1 ms. With the hub's
//! clock extension (`< clock on >`, `< at … >`: docs/CLOCK.md, docs/SOCKETCAND.md) the stall
//! delays delivery only: no EMCY 0x8110, no skipped measurement or TPDO period, every TPDO's
//! start of frame exactly 1 ms after the one before on the bus timeline, and the lateness
//! reported in the sensor's `state`.

mod common;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use canpos_host::bus::bits::{frame_length, INTERMISSION_BITS};
use canpos_stack::Frame;
use common::{free_port, wait_port, Ctl, Proc};

const NODE: u32 = 5;

/// A frame as a raw listener got it: identifier, end-of-frame stamp in µs (wall clock), data.
type Seen = (u32, u64, Vec<u8>);

/// Parses `< frame ID SEC.USEC DATA >`.
fn parse(el: &str) -> Option<Seen> {
    let mut t = el
        .trim()
        .strip_prefix("< frame ")?
        .strip_suffix('>')?
        .split_ascii_whitespace();
    let id = u32::from_str_radix(t.next()?, 16).ok()?;
    let (s, us) = t.next()?.split_once('.')?;
    let stamp = s.parse::<u64>().ok()? * 1_000_000 + us.parse::<u64>().ok()?;
    let hex = t.next().unwrap_or("");
    let data = (0..hex.len() / 2)
        .map(|i| u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).ok())
        .collect::<Option<Vec<u8>>>()?;
    Some((id, stamp, data))
}

/// A raw client on `can0` whose frames a thread collects; the stream writes commands.
fn listener(port: u16) -> (TcpStream, Arc<Mutex<Vec<Seen>>>) {
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let mut r = BufReader::new(s.try_clone().unwrap());
    let mut el = Vec::new();
    let mut next = |r: &mut BufReader<TcpStream>| {
        el.clear();
        r.read_until(b'>', &mut el).unwrap();
        String::from_utf8_lossy(&el).trim().to_string()
    };
    assert_eq!(next(&mut r), "< hi >");
    s.write_all(b"< open can0 >").unwrap();
    assert_eq!(next(&mut r), "< ok >");
    s.write_all(b"< rawmode >").unwrap();
    assert_eq!(next(&mut r), "< ok >");
    let seen = Arc::new(Mutex::new(Vec::new()));
    let out = seen.clone();
    std::thread::spawn(move || {
        let mut buf = Vec::new();
        loop {
            buf.clear();
            match r.read_until(b'>', &mut buf) {
                Ok(0) | Err(_) => return,
                Ok(_) => {}
            }
            if let Some(f) = parse(&String::from_utf8_lossy(&buf)) {
                out.lock().unwrap().push(f);
            }
        }
    });
    (s, seen)
}

fn wait_frame(seen: &Mutex<Vec<Seen>>, what: &str, pred: impl Fn(&Seen) -> bool) {
    let end = Instant::now() + Duration::from_secs(20);
    while !seen.lock().unwrap().iter().any(&pred) {
        assert!(Instant::now() < end, "no {what} within 20 s");
        std::thread::sleep(Duration::from_millis(5));
    }
}

fn signal(pid: u32, sig: libc::c_int) {
    // SAFETY: kill(2) on the pid of a child this test started and has not reaped.
    assert_eq!(unsafe { libc::kill(pid as libc::pid_t, sig) }, 0);
}

#[test]
fn a_stopped_sensor_process_behind_the_hub_keeps_every_tpdo_at_its_time() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let ctl_port = free_port();
    let _serve = Proc::start(
        dir.path(),
        &[
            "bus",
            "serve",
            "--listen",
            &format!("127.0.0.1:{port}"),
            "--bitrate",
            "1000",
        ],
    );
    wait_port(port);
    let (mut net, seen) = listener(port);
    let mut sensor = Proc::start(
        dir.path(),
        &[
            "run",
            "--model",
            "th",
            "--node-id",
            &NODE.to_string(),
            "--serial",
            "3605",
            "--ideal",
            "--magnet",
            "250",
            "--bus",
            &format!("socketcand://127.0.0.1:{port}/can0"),
            "--hub",
            "never",
            "--control",
            &format!("127.0.0.1:{ctl_port}"),
            "--state-dir",
            "state",
        ],
    );
    sensor.wait_for("control interface on", Duration::from_secs(20));
    wait_frame(&seen, "boot-up", |f| f.0 == 0x700 + NODE);
    // TPDO1 event timer 1 ms (0x1800:5), then NMT start.
    net.write_all(format!("< send {:03x} 8 2b 0 18 5 1 0 0 0 >", 0x600 + NODE).as_bytes())
        .unwrap();
    wait_frame(&seen, "SDO answer", |f| {
        f.0 == 0x580 + NODE && f.2[0] == 0x60
    });
    net.write_all(format!("< send 000 2 1 {NODE:x} >").as_bytes())
        .unwrap();
    wait_frame(&seen, "TPDO1", |f| f.0 == 0x180 + NODE);
    std::thread::sleep(Duration::from_millis(300));
    let pid = sensor.pid();
    for _ in 0..20 {
        signal(pid, libc::SIGSTOP);
        std::thread::sleep(Duration::from_millis(200));
        signal(pid, libc::SIGCONT);
        std::thread::sleep(Duration::from_millis(400));
    }
    // The state is answered once the runtime caught up (it handles requests in time order).
    let mut ctl = Ctl::connect(ctl_port);
    let st = ctl.state_when(|st| st["clock"]["events_late_us"]["max"].as_u64() >= Some(150_000));
    let frames = seen.lock().unwrap().clone();
    drop(sensor);

    let emcy: Vec<&Seen> = frames.iter().filter(|f| f.0 == 0x80 + NODE).collect();
    assert!(
        !emcy.iter().any(|f| f.2.starts_with(&[0x10, 0x81])),
        "EMCY 0x8110 (CAN overrun) from a host stall: {emcy:?}"
    );
    // Start of frame = end of frame − its bits (the intermission after it excluded), 1 µs a
    // bit at 1 Mbit/s. The runtime's due times are whole µs k × 1 ms apart; `< at >` carries
    // them in µs and the hub stamps the frame with its time in ns and writes its end in µs:
    // the differences are exact, no tolerance (the bus is idle at each due time: the TPDO is
    // the only traffic).
    let start = |f: &Seen| {
        let frame = Frame::new(f.0 as u16, &f.2).unwrap();
        f.1 - u64::from(frame_length(&frame).total - INTERMISSION_BITS)
    };
    let tpdos: Vec<&Seen> = frames.iter().filter(|f| f.0 == 0x180 + NODE).collect();
    let off: Vec<(usize, i64)> = tpdos
        .windows(2)
        .enumerate()
        .map(|(i, w)| (i, start(w[1]) as i64 - start(w[0]) as i64))
        .filter(|&(_, d)| d != 1_000)
        .collect();
    let span_ms = (start(tpdos[tpdos.len() - 1]) - start(tpdos[0])) / 1000;
    assert!(
        off.is_empty(),
        "{} of {} TPDO periods not 1 ms on the bus timeline (first: {:?}); EMCY: {emcy:?}",
        off.len(),
        tpdos.len(),
        &off[..off.len().min(10)]
    );
    // 20 × 0.6 s of stalls and more: the whole span is there, period by period.
    assert!(span_ms >= 12_000, "{} TPDOs over {span_ms} ms", tpdos.len());
    assert_eq!(st["cycles_skipped"], 0, "{st}");
    assert_eq!(st["tpdo_missed"], 0, "{st}");
    assert_eq!(st["clock"]["shared_with_bus"], true, "{st}");
    assert!(
        st["clock"]["events_late_us"]["max"].as_u64() >= Some(150_000),
        "the stalls' lateness is reported: {st}"
    );
}
