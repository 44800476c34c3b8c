//! Back-pressure across the hub (issue 36 item 7): a client whose transmit queue on the bus
//! overflows is told so, as SocketCAN tells a host (a controller-problem error frame with the
//! TX-overflow bit, to clients that take errors); a device's client (`< txorder priority >`)
//! sends its most important frame first, so that its EMCY overtakes its queued PDOs; and the
//! canpos client counts the reports for the runtime (`Transport::tx_overflows`).
//! docs/SOCKETCAND.md, docs/BUS.md.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use canpos_host::bus::bits::{frame_length, INTERMISSION_BITS};
use canpos_host::bus::Pacing;
use canpos_host::socketcand::{Client, Hub, HubConfig, HubHandle};
use canpos_host::transport::Transport;
use canpos_stack::Frame;

const WAIT: Duration = Duration::from_secs(10);
/// The report of a full transmit queue: `CAN_ERR_CRTL`, data byte 1 `CAN_ERR_CRTL_TX_OVERFLOW`.
const OVERFLOW: &str = " 00 02 00 00 00 00 00 00 >";

/// A hub whose bus is slow enough (10 kbit/s, about 10 ms a frame) that a burst of 100 frames
/// fills a client's 64-frame queue whatever the machine's load.
fn slow_hub() -> HubHandle {
    Hub::bind_with(
        "127.0.0.1:0",
        HubConfig {
            pacing: Pacing::Paced(10),
            ..HubConfig::default()
        },
    )
    .unwrap()
    .spawn()
    .unwrap()
}

/// Reads until `until` was read.
fn read_until(s: &mut TcpStream, until: &str) -> String {
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    while !String::from_utf8_lossy(&got).contains(until) {
        let n = s.read(&mut buf).unwrap();
        assert!(n > 0, "closed: {}", String::from_utf8_lossy(&got));
        got.extend_from_slice(&buf[..n]);
    }
    String::from_utf8(got).unwrap()
}

/// A raw client on `can0` that sent `extra` after `< rawmode >`.
fn raw(addr: SocketAddr, extra: &str) -> TcpStream {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    read_until(&mut s, "< hi >");
    s.write_all(format!("< open can0 >< rawmode >{extra}< echo >").as_bytes())
        .unwrap();
    read_until(&mut s, "< echo >");
    s
}

fn burst(id: u16, n: usize) -> String {
    (0..n)
        .map(|i| format!("< send {id:03X} 8 {i:02X} 0 0 0 0 0 0 0 >"))
        .collect()
}

#[test]
fn a_full_transmit_queue_is_reported_to_a_client_that_takes_errors() {
    let h = slow_hub();
    let mut taker = raw(h.local_addr(), "< errors on >");
    taker.write_all(burst(0x181, 100).as_bytes()).unwrap();
    let got = read_until(&mut taker, OVERFLOW);
    assert!(got.contains("< error 004 "), "{got}");
    // A plain client loses frames the same way but hears nothing of it (socketcand without an
    // error mask): only its echo comes back.
    let mut plain = raw(h.local_addr(), "");
    plain
        .write_all(format!("{}< echo >", burst(0x182, 100)).as_bytes())
        .unwrap();
    let got = read_until(&mut plain, "< echo >");
    assert!(!got.contains("< error"), "{got}");
}

/// `< echo >` is a client's barrier: what it sent before has been handed to the bus when the
/// echo comes back, so the overflow of those frames is reported before it (as SocketCAN's
/// `write` fails at once on a full queue). Before, the frames of a read entered the bus after
/// the read's echo was answered, and the report came after the echo.
#[test]
fn the_overflow_of_frames_sent_before_an_echo_is_reported_before_it() {
    let h = slow_hub();
    let mut taker = raw(h.local_addr(), "< errors on >");
    taker
        .write_all(format!("{}< echo >", burst(0x181, 100)).as_bytes())
        .unwrap();
    let mut got = String::new();
    let mut buf = [0u8; 4096];
    while !got.contains("< echo >") {
        let n = taker.read(&mut buf).unwrap();
        assert!(n > 0, "closed: {got}");
        got += std::str::from_utf8(&buf[..n]).unwrap();
    }
    let echo = got.find("< echo >").unwrap();
    assert!(
        got[..echo].contains(OVERFLOW),
        "the echo came before the overflow report: {got}"
    );
}

#[test]
fn a_device_client_sends_its_most_important_frame_first() {
    let h = slow_hub();
    let mut listener = raw(h.local_addr(), "");
    let mut device = raw(h.local_addr(), "< txorder priority >< errors on >");
    // 70 PDOs (the queue holds 64), then an EMCY in the same write: it takes the place of a
    // PDO in the full queue and goes out right after the PDO already on the wire.
    let emcy = "< send 081 8 0 0 0 0 0 0 0 0 >";
    device
        .write_all(format!("{}{emcy}", burst(0x181, 70)).as_bytes())
        .unwrap();
    let got = read_until(&mut listener, "< frame 081 ");
    let ids: Vec<&str> = got
        .split_inclusive('>')
        .filter_map(|e| e.trim().strip_prefix("< frame "))
        .map(|e| &e[..3])
        .collect();
    assert_eq!(ids, ["181", "081"], "{got}");
    read_until(&mut device, OVERFLOW);
}

#[test]
fn the_canpos_client_counts_the_overflows_of_its_queue() {
    let h = slow_hub();
    let mut c = Client::connect(h.local_addr(), "can0").unwrap();
    assert_eq!(c.tx_overflows(), 0);
    for i in 0..100u8 {
        c.send(&Frame::new(0x181, &[i, 0, 0, 0, 0, 0, 0, 0]).unwrap())
            .unwrap();
    }
    let end = Instant::now() + WAIT;
    while c.tx_overflows() == 0 {
        assert!(Instant::now() < end, "no overflow reported");
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// End to end: a TH runtime behind the hub (its own socketcand transport, not an in-process
/// controller) at 1 ms TPDOs on a 10 kbit/s bus loses frames in its queue in the hub and reacts
/// as its model says: EMCY 0x8110, which overtakes its queued TPDOs.
#[test]
fn a_sensor_behind_the_hub_sends_its_overflow_emcy() {
    use canpos_host::runtime::{Runtime, SensorSetup};
    use canpos_host::transport::HubPolicy;
    use canpos_host::FileStorage;
    use canpos_sim::motion::{Profile, Profiles};
    use canpos_sim::SensorSpec;

    let dir = tempfile::tempdir().unwrap();
    let h = slow_hub();
    let url = format!("socketcand://{}/can0", h.local_addr());
    let (t, embedded) = canpos_host::open_device_bus(&url, HubPolicy::Never).unwrap();
    assert!(embedded.is_none());
    let model = canpos_models::by_name("th").unwrap();
    let mut cfg = model.default_config;
    cfg.node_id = 9;
    cfg.serial = 78;
    let mut rt = Runtime::new(t, None);
    rt.add(SensorSetup {
        name: "th-78".into(),
        model,
        cfg,
        spec: SensorSpec::th(f64::from(cfg.stroke_mm), 1).unwrap(),
        seed: 1,
        ideal: true,
        motion: Box::new(Profiles(vec![Profile::Static { pos_mm: 250.0 }])),
        storage: FileStorage::new(canpos_host::runtime::state_file(dir.path(), "th", 78)),
    });
    let mut master = Client::connect(h.local_addr(), "can0").unwrap();
    let rt = rt.spawn().unwrap();
    let end = Instant::now() + WAIT;
    let next = |master: &mut Client, what: &str| {
        let rx = master.recv_deadline(end).unwrap();
        rx.unwrap_or_else(|| panic!("no {what}")).frame
    };
    while next(&mut master, "boot-up") != Frame::new(0x709, &[0]).unwrap() {}
    // TPDO1 event timer 1 ms (0x1800:5), then Operational.
    master
        .send(&Frame::new(0x609, &[0x2B, 0x00, 0x18, 0x05, 1, 0, 0, 0]).unwrap())
        .unwrap();
    while next(&mut master, "SDO answer").std_id() != Some(0x589) {}
    master
        .send(&Frame::new(0x000, &[0x01, 9]).unwrap())
        .unwrap();
    loop {
        let f = next(&mut master, "EMCY 0x8110");
        if f.std_id() == Some(0x89) && f.data()[..2] == [0x10, 0x81] {
            break;
        }
    }
    rt.stop().unwrap();
}

/// `SEC.USEC` of a wall-clock time, as `< at … >` takes it.
fn secs(t: std::time::SystemTime) -> String {
    let d = t.duration_since(std::time::UNIX_EPOCH).unwrap();
    format!("{}.{:06}", d.as_secs(), d.subsec_micros())
}

/// Two timed sensor processes behind the hub (`< clock on >`), one stopped: the bus waits for
/// it, and the other one's frames, sent at their own times meanwhile (1 ms apart), join its
/// transmit queue when the bus reaches those times. None is lost, no overflow is reported, and
/// each goes out at its time once the stopped one goes on. Before, they were queued at once
/// while the bus stood still: 36 of 100 lost and an overflow report, on which a canpos sensor
/// sends EMCY 0x8110 for the other process's stall.
#[test]
fn a_timed_client_ahead_of_the_bus_loses_nothing_while_another_is_behind() {
    let h = Hub::bind("127.0.0.1:0").unwrap().spawn().unwrap();
    let mut listener = raw(h.local_addr(), "");
    let mut stopped = raw(h.local_addr(), "< clock on >");
    // It stands at now and stays there (stopped): the bus holds at most here.
    stopped
        .write_all(format!("< at {} >< echo >", secs(std::time::SystemTime::now())).as_bytes())
        .unwrap();
    read_until(&mut stopped, "< echo >");
    let from = std::time::SystemTime::now() + Duration::from_millis(1);
    let mut on_time = raw(h.local_addr(), "< clock on >< errors on >");
    // Its runtime runs on: 100 frames at their times, 1 ms apart, once the wall clock is past
    // them (a horizon ahead of the wall clock stamps nothing later than the wall clock).
    while std::time::SystemTime::now() < from + Duration::from_millis(110) {
        std::thread::sleep(Duration::from_millis(10));
    }
    let mut text = String::new();
    for k in 0..100u32 {
        let t = from + Duration::from_millis(u64::from(k));
        text += &format!("< at {} >< send 181 1 {:02X} >", secs(t), k % 256);
    }
    on_time
        .write_all(format!("{text}< echo >").as_bytes())
        .unwrap();
    let got = read_until(&mut on_time, "< echo >");
    assert!(
        !got.contains("< error"),
        "a loss while the other stood: {got}"
    );
    // The stopped one goes on (leaves the clock), the other one too: the bus runs.
    stopped.write_all(b"< clock off >").unwrap();
    on_time.write_all(b"< clock off >").unwrap();
    let got = read_until(&mut listener, " 63 >");
    // Start of frame: the end (µs) less the frame's bits without the intermission, 1 µs each.
    let starts: Vec<u64> = got
        .split_inclusive('>')
        .filter_map(|e| e.trim().strip_prefix("< frame 181 "))
        .map(|e| {
            let mut toks = e.split_whitespace();
            let (sec, usec) = toks.next().unwrap().split_once('.').unwrap();
            let end = sec.parse::<u64>().unwrap() * 1_000_000 + usec.parse::<u64>().unwrap();
            let data = u8::from_str_radix(toks.next().unwrap(), 16).unwrap();
            let bits = frame_length(&Frame::new(0x181, &[data]).unwrap()).total - INTERMISSION_BITS;
            end - u64::from(bits)
        })
        .collect();
    assert_eq!(starts.len(), 100, "{got}");
    for (k, w) in starts.windows(2).enumerate() {
        assert_eq!(w[1] - w[0], 1_000, "frames {k} and {}: {got}", k + 1);
    }
    on_time.write_all(b"< echo >").unwrap();
    let got = read_until(&mut on_time, "< echo >");
    assert!(!got.contains("< error"), "{got}");
}

/// The same two timed clients on a bus too slow for the frames (10 kbit/s, about 10 ms a
/// frame, one sent every 1 ms): the frames kept for their times overflow the queue when they
/// join it, once the stopped one goes on, and the client is told then (issue 36 item 7 with
/// `< clock on >`).
#[test]
fn kept_frames_that_overflow_when_they_join_the_queue_are_reported() {
    let h = slow_hub();
    let mut stopped = raw(h.local_addr(), "< clock on >");
    stopped
        .write_all(format!("< at {} >< echo >", secs(std::time::SystemTime::now())).as_bytes())
        .unwrap();
    read_until(&mut stopped, "< echo >");
    let from = std::time::SystemTime::now() + Duration::from_millis(1);
    let mut on_time = raw(h.local_addr(), "< clock on >< errors on >");
    while std::time::SystemTime::now() < from + Duration::from_millis(110) {
        std::thread::sleep(Duration::from_millis(10));
    }
    let mut text = String::new();
    for k in 0..100u32 {
        let t = from + Duration::from_millis(u64::from(k));
        text += &format!("< at {} >< send 181 1 {:02X} >", secs(t), k % 256);
    }
    on_time
        .write_all(format!("{text}< echo >").as_bytes())
        .unwrap();
    let got = read_until(&mut on_time, "< echo >");
    assert!(!got.contains("< error"), "kept, not queued yet: {got}");
    stopped.write_all(b"< clock off >").unwrap();
    read_until(&mut on_time, OVERFLOW);
}

/// An untimed client (python-canopen, a bridge, a tool: no `< clock on >`) beside a timed one
/// that is stopped: its frames are stamped with the wall time it sent them at, ahead of the
/// held bus, and kept for that time as a timed client's are. Two bursts of 50, sent 20 ms
/// apart (each acknowledged by `< echo >` before the next, so the hub reads them apart): each
/// joins the 64-frame queue at its own time, none is lost and no overflow is reported. Before,
/// both went into the queue while the bus stood still: 36 lost and a TX-overflow report on a
/// bus that was never overloaded.
#[test]
fn an_untimed_client_ahead_of_the_bus_loses_nothing_while_a_timed_one_is_behind() {
    let h = Hub::bind("127.0.0.1:0").unwrap().spawn().unwrap();
    let mut listener = raw(h.local_addr(), "");
    let mut stopped = raw(h.local_addr(), "< clock on >");
    stopped
        .write_all(format!("< at {} >< echo >", secs(std::time::SystemTime::now())).as_bytes())
        .unwrap();
    read_until(&mut stopped, "< echo >");
    let mut tool = raw(h.local_addr(), "< errors on >");
    for _ in 0..2 {
        // 20 ms of wall time apart: the first burst (50 × ~50 µs at 1 Mbit/s) is long gone
        // from the queue at the second one's time.
        std::thread::sleep(Duration::from_millis(20));
        tool.write_all(format!("{}< echo >", burst(0x123, 50)).as_bytes())
            .unwrap();
        let got = read_until(&mut tool, "< echo >");
        assert!(
            !got.contains("< error"),
            "a loss while the bus waited: {got}"
        );
    }
    // The stopped one goes on (leaves the clock): the bus runs and carries all 100.
    stopped.write_all(b"< clock off >").unwrap();
    let mut got = String::new();
    while got.matches("< frame 123 ").count() < 100 {
        got += &read_until(&mut listener, " >");
    }
    assert_eq!(got.matches("< frame 123 ").count(), 100, "{got}");
    tool.write_all(b"< echo >").unwrap();
    let got = read_until(&mut tool, "< echo >");
    assert!(!got.contains("< error"), "{got}");
    for (name, s) in h.channel_stats() {
        assert_eq!(s.tx_lost, 0, "{name}: {s:?}");
    }
}
