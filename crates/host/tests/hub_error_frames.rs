//! A hub client's error frames (issue 35 item 8): an error frame it signals goes on the bus and
//! changes every controller's counters as ISO 11898-1 says; its report of its own controller's
//! state changes nobody else's. A canpos client (a sensor's transport) takes its state from
//! its own controller only.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use canpos_host::socketcand::{Client, Hub, HubConfig, HubHandle};
use canpos_host::transport::{BusState, Transport};
use canpos_stack::Frame;

const WAIT: Duration = Duration::from_secs(10);

fn hub() -> HubHandle {
    Hub::bind_with("127.0.0.1:0", HubConfig::default())
        .unwrap()
        .spawn()
        .unwrap()
}

fn wait_until(what: &str, mut cond: impl FnMut() -> bool) {
    let end = Instant::now() + WAIT;
    while !cond() {
        assert!(Instant::now() < end, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// Reads until `until` was read.
fn read_until(s: &mut TcpStream, until: &[u8]) -> Vec<u8> {
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    while !got.windows(until.len()).any(|w| w == until) {
        let n = s.read(&mut buf).unwrap();
        assert!(n > 0);
        got.extend_from_slice(&buf[..n]);
    }
    got
}

/// A raw client that takes and gives errors (`< errors on >`), as anyone may connect.
fn erring(addr: SocketAddr) -> TcpStream {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    read_until(&mut s, b"< hi >");
    s.write_all(b"< open can0 >< rawmode >< errors on >< echo >")
        .unwrap();
    read_until(&mut s, b"< echo >");
    s
}

#[test]
fn spoofed_controller_states_latch_nothing_in_a_sensor() {
    // As reported: `< errors on >` then `< error 040 … >` (bus-off) set every canpos client on
    // the channel to bus-off for good; an error-passive report made sensors send EMCY.
    let h = hub();
    let mut sensor = Client::connect(h.local_addr(), "can0").unwrap();
    let mut attacker = erring(h.local_addr());
    for _ in 0..200 {
        attacker
            .write_all(
                b"< error 040 1.000000 00 00 00 00 00 00 00 00 >\
                  < error 004 1.000000 00 30 00 00 00 00 00 00 >\
                  < error 004 1.000000 >",
            )
            .unwrap();
    }
    // Whatever the hub passes on has reached the sensor before a frame sent after it.
    attacker.write_all(b"< send 181 1 01 >").unwrap();
    let f = sensor.recv_timeout(Some(WAIT)).unwrap().unwrap();
    assert_eq!(f.frame, Frame::new(0x181, &[1]).unwrap());
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(sensor.bus_state(), BusState::ErrorActive);
    assert_eq!(h.channel_stats()[0].1.error_frames, 0, "nothing on the bus");
}

#[test]
fn error_frames_raise_every_other_controllers_receive_counter() {
    let h = hub();
    let port = h.attach("can0");
    let sensor = Client::connect(h.local_addr(), "can0").unwrap();
    let mut attacker = erring(h.local_addr());
    let rec = || port.bus_stats().unwrap().controller.unwrap().rec;
    const FLAG: &[u8] = b"< error 008 1.000000 00 00 04 00 00 00 00 00 >";
    // Protocol errors (a stuff error seen on the wire): one error frame each on the bus, one
    // at a time (a flag while one is pending is refused), REC + 1 for every controller. The
    // attacker's own controller counts + 9 a flag (ISO 11898-1 rules 1 and 2): after 15 it is
    // error passive, and its flags are passive: nobody else sees them.
    for k in 1..=15u16 {
        attacker.write_all(FLAG).unwrap();
        // The bus carries one error frame at a time: wait for it before the next.
        wait_until("the receive counter", || rec() == k);
    }
    // The attacker got the bus's error frames too (as a controller reports them: a stuff
    // error), and its own controller's state: error passive (REC 135).
    let got = read_until(&mut attacker, b"00 30 00 00 00 00 00 00 >");
    let got = String::from_utf8_lossy(&got);
    assert!(got.contains(" 00 00 04 00 00 00 00 00 >"), "{got}");
    assert!(got.starts_with("< error 008 "), "{got}");
    for _ in 0..100 {
        attacker.write_all(FLAG).unwrap();
    }
    // Other clients' flags still count, one each (so the 100 passive ones counted nothing):
    // 113 more make every controller error passive at REC 128, by their own counters.
    let mut others = Vec::new();
    for k in 16..=128u16 {
        let mut c = erring(h.local_addr());
        c.write_all(FLAG).unwrap();
        wait_until("the receive counter", || rec() >= k);
        assert_eq!(rec(), k, "a passive flag was seen on the bus");
        others.push(c);
    }
    assert_eq!(h.channel_stats()[0].1.error_frames, 128);
    assert_eq!(
        port.bus_stats().unwrap().controller.unwrap().state,
        BusState::ErrorPassive
    );
    // The TCP sensor hears it from the hub as its interface's state.
    wait_until("the sensor's error-passive state", || {
        sensor.bus_state() == BusState::ErrorPassive
    });
    // Good frames bring every receiver back (REC above 127 → 119): nothing latched.
    let mut tx = h.attach("can0");
    tx.send(&Frame::new(0x181, &[1]).unwrap()).unwrap();
    wait_until("error active again", || {
        sensor.bus_state() == BusState::ErrorActive
    });
    assert_eq!(rec(), 119);
}

/// What a raw client read, in order: (is an error, bus time in s) of each frame and error.
fn stamps(text: &str) -> Vec<(bool, f64)> {
    text.split('<')
        .filter_map(|el| {
            let mut t = el.split_whitespace();
            let kind = t.next()?;
            let stamp = t.nth(1)?.parse().ok()?;
            matches!(kind, "frame" | "error").then_some((kind == "error", stamp))
        })
        .collect()
}

#[test]
fn error_frames_reach_a_client_after_the_frames_before_them() {
    // A review found `< error … >` passing frames that ended before it on the bus: the errors
    // went straight to the client's output while its frames still waited in its queue.
    let h = hub();
    let mut reader = erring(h.local_addr());
    let mut attacker = erring(h.local_addr());
    let mut tx = h.attach("can0");
    let flags = std::thread::spawn(move || {
        // One flag a frame time or so: the attacker is error active again after each good
        // frame it receives (REC → 119), so about every other frame is destroyed (and its
        // transmitter may go bus-off, as on a wire).
        for _ in 0..1000 {
            attacker
                .write_all(b"< error 008 1.000000 00 00 04 00 00 00 00 00 >")
                .unwrap();
            std::thread::sleep(Duration::from_micros(200));
        }
    });
    // The reader reads nothing until the end: about 40 KB wait for it, so the hub takes it for
    // a slow client and writes it in batches (where errors passed a whole batch of frames).
    for i in 0..1000u16 {
        tx.send(&Frame::new(0x181, &i.to_le_bytes()).unwrap())
            .unwrap();
    }
    flags.join().unwrap();
    // A last frame from a controller of its own marks the end.
    let mut end = h.attach("can0");
    end.send(&Frame::new(0x7FF, &[0xEE]).unwrap()).unwrap();
    let got = read_until(&mut reader, b"frame 7FF");
    let got = String::from_utf8_lossy(&got);
    let seen = stamps(&got);
    let errors = seen.iter().filter(|s| s.0).count();
    assert!(errors > 0, "no error reached the reader: {got}");
    assert!(seen.len() - errors > 1, "{got}");
    let mut latest_error = f64::MIN;
    for &(is_error, t) in &seen {
        if is_error {
            latest_error = latest_error.max(t);
        } else {
            assert!(
                t >= latest_error,
                "a frame of {t} s after an error of {latest_error} s: {got}"
            );
        }
    }
}
