//! The hub's output to a client is bounded, replies included (issue 35 items 3 and 10): a client
//! that floods commands and never reads their answers is no longer read from (backpressure),
//! statistics and bus errors wait for room, and an over-long element gets an error reply.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use canpos_host::socketcand::hub::OUT_LIMIT;
use canpos_host::socketcand::{Hub, HubConfig, HubHandle};

const WAIT: Duration = Duration::from_secs(10);
const UNKNOWN: &[u8] = b"< error unknown command >";

fn hub_with(config: HubConfig) -> HubHandle {
    Hub::bind_with("127.0.0.1:0", config)
        .unwrap()
        .spawn()
        .unwrap()
}

fn expect(s: &mut TcpStream, want: &[u8]) {
    let mut buf = vec![0u8; want.len()];
    s.read_exact(&mut buf).unwrap();
    assert_eq!(buf, want, "{:?}", String::from_utf8_lossy(&buf));
}

fn opened(addr: SocketAddr, mode: &[u8]) -> TcpStream {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    expect(&mut s, b"< hi >");
    s.write_all(b"< open can0 >").unwrap();
    expect(&mut s, b"< ok >");
    s.write_all(mode).unwrap();
    expect(&mut s, b"< ok >");
    s
}

fn rss_kib() -> u64 {
    let st = std::fs::read_to_string("/proc/self/status").unwrap();
    st.lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap()
}

/// Writes `chunk` until `total` bytes went out or a write blocks for `stall`; returns the bytes
/// written.
fn flood(s: &mut TcpStream, chunk: &[u8], total: usize, stall: Duration) -> usize {
    s.set_write_timeout(Some(stall)).unwrap();
    let mut sent = 0;
    while sent < total {
        match s.write(chunk) {
            Ok(n) => sent += n,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                break
            }
            Err(e) => panic!("write: {e}"),
        }
    }
    s.set_write_timeout(None).unwrap();
    sent
}

#[test]
fn forty_megabytes_of_unread_replies_stay_bounded() {
    // As reported: `<x>` (3 bytes) draws `< error unknown command >` (25 bytes); 40 MB of them
    // unread were 333 MB of replies queued in the hub.
    let hub = hub_with(HubConfig::default());
    let addr = hub.local_addr();
    let mut bad = opened(addr, b"< rawmode >");
    let before = rss_kib();
    let chunk = b"<x>".repeat(64 * 1024 / 3);
    let sent = flood(&mut bad, &chunk, 40 << 20, Duration::from_secs(2));
    let grown = rss_kib().saturating_sub(before);
    let peak = hub.stats().out_peak;
    assert!(
        peak <= 2 * OUT_LIMIT + 64,
        "{peak} bytes waited for one client"
    );
    assert!(
        grown < 64 * 1024,
        "RSS grew {grown} KiB ({sent} bytes sent)"
    );
    assert!(
        sent < 40 << 20,
        "the hub read all 40 MB though the client read none of its answers"
    );
    // Everyone else is served meanwhile.
    let mut good = opened(addr, b"< rawmode >");
    good.write_all(b"< echo >").unwrap();
    expect(&mut good, b"< echo >");
    // Once the client reads, the hub reads and answers again: every answer, in order.
    let mut got = vec![0u8; 40 * UNKNOWN.len() * 1000];
    bad.read_exact(&mut got).unwrap();
    assert!(got.chunks(UNKNOWN.len()).all(|c| c == UNKNOWN));
    drop(bad);
    good.write_all(b"< echo >").unwrap();
    expect(&mut good, b"< echo >");
}

#[test]
fn an_overlong_element_gets_an_error_reply() {
    let hub = hub_with(HubConfig::default());
    let mut s = TcpStream::connect(hub.local_addr()).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    expect(&mut s, b"< hi >");
    // 1 MB in one element, before and after open: an answer each time, nothing kept.
    let mut long = b"< open ".to_vec();
    long.extend(std::iter::repeat_n(b'c', 1 << 20));
    long.extend_from_slice(b" >");
    let want: &[u8] = b"< error element longer than 256 bytes >";
    s.write_all(&long).unwrap();
    expect(&mut s, want);
    s.write_all(b"< open can0 >< rawmode >").unwrap();
    expect(&mut s, b"< ok >< ok >");
    let mut send = b"< send 123 1 ".to_vec();
    send.extend(std::iter::repeat_n(b'0', 1 << 20));
    send.extend_from_slice(b" >< echo >");
    s.write_all(&send).unwrap();
    expect(&mut s, want);
    expect(&mut s, b"< echo >");
    assert!(hub.stats().out_peak < 1024);
}

#[test]
fn statistics_and_replies_wait_for_room() {
    // A small output bound and kernel buffers, so that a client that does not read fills them
    // at once: its `< statistics 10 >` lines are not added on top of the bound, and after it
    // reads they come again.
    let limit = 1024;
    let hub = hub_with(HubConfig {
        out_limit: limit,
        send_buffer: Some(4096),
        ..HubConfig::default()
    });
    let mut s = opened(hub.local_addr(), b"< controlmode >");
    s.write_all(b"< statistics 10 >").unwrap();
    // 200 KB of `<x>`: 1.7 MB of answers, far beyond the bound (they wait in the kernel's
    // buffers and in the client's input, not in the hub).
    let sent = flood(
        &mut s,
        &b"<x>".repeat(1000),
        200_000,
        Duration::from_secs(2),
    );
    assert!(sent >= 200_000);
    // 50 statistics periods with the output full.
    let end = Instant::now() + Duration::from_millis(500);
    while Instant::now() < end {
        std::thread::sleep(Duration::from_millis(50));
    }
    let peak = hub.stats().out_peak;
    assert!(peak <= 2 * limit + 64, "{peak} bytes waited for one client");
    // Read everything the flood drew, in order; the statistics lines come back after.
    let mut dec = canpos_host::socketcand::codec::Decoder::new();
    let (mut answers, mut stats) = (0, 0);
    let mut buf = [0u8; 65536];
    let end = Instant::now() + WAIT;
    while answers < sent / 3 || stats == 0 {
        assert!(
            Instant::now() < end,
            "{answers} answers, {stats} statistics"
        );
        let n = s.read(&mut buf).unwrap();
        assert!(n > 0);
        dec.feed(&buf[..n], |b| match b {
            b" error unknown command " => answers += 1,
            _ if b.starts_with(b" stat ") => stats += 1,
            other => panic!("{:?}", String::from_utf8_lossy(other)),
        });
    }
    assert_eq!(answers, sent / 3);
}

#[test]
fn a_client_that_stops_reading_gets_frames_again_when_it_reads() {
    // It stops reading: the kernel's buffers and its 64 KiB fill, it is written in batches,
    // then not at all (its frames are dropped by the sender, counted); once it reads, it is
    // written again: nothing is stuck.
    let hub = hub_with(HubConfig {
        pacing: canpos_host::bus::Pacing::Instant,
        ..HubConfig::default()
    });
    let mut s = opened(hub.local_addr(), b"< rawmode >");
    s.write_all(b"< echo >").unwrap();
    expect(&mut s, b"< echo >");
    let mut port = hub.attach("can0");
    use canpos_host::transport::Transport;
    let f = canpos_stack::Frame::new(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap();
    let end = Instant::now() + WAIT;
    while hub.stats().dropped < 10_000 {
        assert!(Instant::now() < end, "{:?}", hub.stats());
        for _ in 0..1000 {
            port.send(&f).unwrap();
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    // It reads everything there is, then a marker frame reaches it.
    s.set_read_timeout(Some(Duration::from_millis(300)))
        .unwrap();
    let mut buf = vec![0u8; 1 << 16];
    let mut tail = Vec::new();
    loop {
        match s.read(&mut buf) {
            Ok(n) if n > 0 => {
                tail.extend_from_slice(&buf[..n]);
                let keep = tail.len().saturating_sub(64);
                tail.drain(..keep);
            }
            _ => break,
        }
    }
    let marker = canpos_stack::Frame::new(0x7E0, &[0xAA]).unwrap();
    port.send(&marker).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    let mut got = Vec::new();
    while !got.windows(5).any(|w| w == b" AA >") {
        let n = s.read(&mut buf).unwrap();
        assert!(n > 0);
        got.extend_from_slice(&buf[..n]);
        let keep = got.len().saturating_sub(64);
        got.drain(..keep);
    }
}
