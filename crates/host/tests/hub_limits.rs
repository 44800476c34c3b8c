//! The hub's limits (issue 13): a cap on connections, refused cleanly, a handshake deadline,
//! and the optional idle limit of raw-mode clients.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use canpos_host::socketcand::{Hub, HubConfig};

const WAIT: Duration = Duration::from_secs(10);

fn connect(addr: SocketAddr) -> TcpStream {
    let s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    s
}

/// Everything the hub sends until it closes the connection (panics after `WAIT`).
fn until_closed(s: &mut TcpStream) -> Vec<u8> {
    let mut all = Vec::new();
    let mut buf = [0u8; 256];
    loop {
        match s.read(&mut buf) {
            Ok(0) => return all,
            Ok(n) => all.extend_from_slice(&buf[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => return all,
            Err(e) => panic!("the hub did not close the connection: {e}"),
        }
    }
}

fn expect(s: &mut TcpStream, want: &[u8]) {
    let mut buf = vec![0u8; want.len()];
    s.read_exact(&mut buf).unwrap();
    assert_eq!(buf, want, "{:?}", String::from_utf8_lossy(&buf));
}

fn raw(addr: SocketAddr) -> TcpStream {
    let mut s = connect(addr);
    expect(&mut s, b"< hi >");
    s.write_all(b"< open can0 >").unwrap();
    expect(&mut s, b"< ok >");
    s.write_all(b"< rawmode >").unwrap();
    expect(&mut s, b"< ok >");
    s
}

#[test]
fn connections_beyond_the_cap_are_refused_cleanly() {
    let config = HubConfig {
        max_clients: 2,
        ..HubConfig::default()
    };
    let hub = Hub::bind_with("127.0.0.1:0", config)
        .unwrap()
        .spawn()
        .unwrap();
    let addr = hub.local_addr();
    let a = raw(addr);
    let _b = raw(addr);
    let mut c = connect(addr);
    assert_eq!(until_closed(&mut c), b"< error too many clients >");
    assert_eq!(hub.stats().refused, 1);
    // A closed connection makes room again (once its thread has seen the close).
    drop(a);
    let end = Instant::now() + WAIT;
    loop {
        let mut d = connect(addr);
        let mut hi = [0u8; 6];
        if d.read_exact(&mut hi).is_ok() && &hi == b"< hi >" {
            break;
        }
        assert!(Instant::now() < end, "no room after a close");
    }
}

#[test]
fn a_client_that_does_not_finish_the_handshake_is_closed() {
    let config = HubConfig {
        handshake_timeout: Duration::from_millis(200),
        ..HubConfig::default()
    };
    let hub = Hub::bind_with("127.0.0.1:0", config)
        .unwrap()
        .spawn()
        .unwrap();
    let addr = hub.local_addr();
    let mut silent = connect(addr);
    assert_eq!(until_closed(&mut silent), b"< hi >");
    // Half an `open`, a byte at a time, is not enough either.
    let mut slow = connect(addr);
    expect(&mut slow, b"< hi >");
    for b in b"< open ca" {
        slow.write_all(&[*b]).unwrap();
        std::thread::sleep(Duration::from_millis(10));
    }
    assert_eq!(until_closed(&mut slow), b"");
    // After `open` the client is in BCM mode, as with socketcand: a complete handshake, kept
    // (a BCM client may set up its send jobs and say nothing more).
    let mut bcm = connect(addr);
    expect(&mut bcm, b"< hi >");
    bcm.write_all(b"< open can0 >").unwrap();
    expect(&mut bcm, b"< ok >");
    // A client that finished the handshake stays past the deadline (no idle limit by default).
    let mut good = raw(addr);
    let mut other = raw(addr);
    std::thread::sleep(Duration::from_millis(300));
    bcm.write_all(b"< echo >").unwrap();
    expect(&mut bcm, b"< echo >");
    other.write_all(b"< send 123 1 aa >").unwrap();
    let mut buf = [0u8; 64];
    let n = good.read(&mut buf).unwrap();
    assert!(
        String::from_utf8_lossy(&buf[..n]).starts_with("< frame 123 "),
        "{:?}",
        String::from_utf8_lossy(&buf[..n])
    );
}

#[test]
fn an_idle_limit_closes_silent_raw_clients() {
    let config = HubConfig {
        idle_timeout: Some(Duration::from_millis(200)),
        ..HubConfig::default()
    };
    let hub = Hub::bind_with("127.0.0.1:0", config)
        .unwrap()
        .spawn()
        .unwrap();
    let mut s = raw(hub.local_addr());
    assert_eq!(until_closed(&mut s), b"");
}

#[test]
fn a_burst_larger_than_one_turn_is_forwarded_whole() {
    // 4000 frames in one write: more than the event loop reads per turn (64 KiB), and more
    // than a client's output holds at once. Readiness is edge-triggered, so the hub must come
    // back to both sockets by itself.
    const N: usize = 4000;
    // The event loop, not the bus: instant (a paced channel would let the sender's transmit
    // queue overflow and count the losses instead).
    let config = HubConfig {
        pacing: canpos_host::bus::Pacing::Instant,
        ..HubConfig::default()
    };
    let hub = Hub::bind_with("127.0.0.1:0", config)
        .unwrap()
        .spawn()
        .unwrap();
    let mut rx = raw(hub.local_addr());
    let mut tx = raw(hub.local_addr());
    let burst: Vec<u8> = (0..N).flat_map(|_| *b"< send 123 1 aa >").collect();
    assert!(burst.len() > 64 * 1024);
    tx.write_all(&burst).unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 65536];
    let end = Instant::now() + WAIT;
    while got.windows(7).filter(|w| w == b"< frame").count() < N {
        assert!(Instant::now() < end, "frames lost or stalled");
        let n = rx.read(&mut buf).unwrap();
        assert!(n > 0, "hub closed the receiver");
        got.extend_from_slice(&buf[..n]);
    }
    assert_eq!(hub.stats().frames_in, N as u64);
    assert_eq!(hub.stats().dropped, 0);
}
