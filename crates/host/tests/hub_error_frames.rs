//! A hub client's error frames (issue 35 item 8): an error frame it signals goes on the bus and
//! changes every controller's counters as ISO 11898-1 says; its report of its own controller's
//! state changes nobody else's. A canpos client (a sensor's transport) takes its state from
//! its own controller only.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use canpos_core::Frame;
use canpos_host::socketcand::{Client, Hub, HubConfig, HubHandle};
use canpos_host::transport::{BusState, Transport};

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
    // Protocol errors (a stuff error seen on the wire): one error frame each on the bus, one
    // at a time (a flag while one is pending is refused), REC + 1 for every controller.
    for k in 1..=128u16 {
        attacker
            .write_all(b"< error 008 1.000000 00 00 04 00 00 00 00 00 >")
            .unwrap();
        // The bus carries one error frame at a time: wait for it before the next.
        wait_until("the receive counter", || rec() == k);
    }
    assert_eq!(h.channel_stats()[0].1.error_frames, 128);
    // REC 128: error passive, by the controllers' own counters; the TCP sensor hears it from
    // the hub as its interface's state.
    assert_eq!(
        port.bus_stats().unwrap().controller.unwrap().state,
        BusState::ErrorPassive
    );
    wait_until("the sensor's error-passive state", || {
        sensor.bus_state() == BusState::ErrorPassive
    });
    // The attacker got the bus's error frames too (as a controller reports them: a stuff
    // error), and its own controller's state (its REC is 128 too).
    let got = read_until(&mut attacker, b"00 30 00 00 00 00 00 00 >");
    let got = String::from_utf8_lossy(&got);
    assert!(got.contains(" 00 00 04 00 00 00 00 00 >"), "{got}");
    assert!(got.starts_with("< error 008 "), "{got}");
    // Good frames bring every receiver back (REC above 127 → 119): nothing latched.
    let mut tx = h.attach("can0");
    tx.send(&Frame::new(0x181, &[1]).unwrap()).unwrap();
    wait_until("error active again", || {
        sensor.bus_state() == BusState::ErrorActive
    });
    assert_eq!(rec(), 119);
}
