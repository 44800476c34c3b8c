//! Hub robustness under churn: 1000 connects / disconnects of every abusive kind while two
//! well-behaved clients exchange traffic, with stuck (never-reading) clients attached the whole
//! time. The hub must stay up, keep its memory bounded and lose none of the good clients' frames.
//!
//! One test in its own binary: it reads this process's RSS, which tests running in parallel in
//! the same process would disturb.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use canpos_host::socketcand::{Client, Hub, HubConfig};
use canpos_host::Transport;
use canpos_stack::Frame;

const WAIT: Duration = Duration::from_secs(10);

/// `VmRSS` of this process, KiB.
fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS in /proc/self/status")
}

fn wait_until(what: &str, mut cond: impl FnMut() -> bool) {
    let end = Instant::now() + WAIT;
    while !cond() {
        assert!(Instant::now() < end, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Reads up to `want.len()` bytes (the hub's replies are short and come in one piece).
fn expect(s: &mut TcpStream, want: &[u8]) {
    let mut buf = [0u8; 64];
    let n = s.read(&mut buf).unwrap();
    assert_eq!(&buf[..n], want);
}

/// A raw client through the handshake into raw mode on `can0`.
fn raw(addr: SocketAddr) -> TcpStream {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(WAIT)).unwrap();
    expect(&mut s, b"< hi >");
    s.write_all(b"< open can0 >").unwrap();
    expect(&mut s, b"< ok >");
    s.write_all(b"< rawmode >").unwrap();
    expect(&mut s, b"< ok >");
    s
}

/// One abusive client of kind `i % 6`, connected and gone again.
fn abuse(addr: SocketAddr, i: u32) {
    match i % 6 {
        // Connect and leave at once (before even reading `< hi >`).
        0 => drop(TcpStream::connect(addr).unwrap()),
        // Leave mid-handshake, inside an element.
        1 => {
            let mut s = TcpStream::connect(addr).unwrap();
            let _ = s.write_all(b"< open ca");
        }
        // Leave mid-frame in raw mode.
        2 => {
            let mut s = raw(addr);
            let _ = s.write_all(b"< send 123 2 01");
        }
        // Garbage, including an over-long element, then leave.
        3 => {
            let mut s = raw(addr);
            let mut junk = b"\x00\xff>>><<< bogus >".to_vec();
            junk.extend(std::iter::repeat_n(b'x', 3000));
            junk.extend_from_slice(b"< send 9 1 >< send zz 1 1 >");
            let _ = s.write_all(&junk);
        }
        // A valid frame on another channel, then leave.
        4 => {
            let mut s = TcpStream::connect(addr).unwrap();
            s.set_read_timeout(Some(WAIT)).unwrap();
            expect(&mut s, b"< hi >");
            let _ = s.write_all(b"< open other >");
            expect(&mut s, b"< ok >");
            let _ = s.write_all(b"< rawmode >< send 7FF 0  >");
        }
        // A client that sends one good frame on can0 and leaves without reading.
        _ => {
            let mut s = raw(addr);
            let _ = s.write_all(b"< send 555 1 aa >");
        }
    }
}

#[test]
fn thousand_abusive_clients_leave_the_hub_up_bounded_and_fair() {
    // The hub's connection handling and queues, not bus timing: the instant bus (on a paced
    // one the good writer's 32 frames in flight would overflow its transmit queue by design).
    let config = HubConfig {
        send_buffer: Some(16 * 1024),
        pacing: canpos_host::bus::Pacing::Instant,
        ..HubConfig::default()
    };
    let h = Hub::bind_with("127.0.0.1:0", config)
        .unwrap()
        .spawn()
        .unwrap();
    let addr = h.local_addr();

    // Stuck clients: in raw mode on the busy channel, never read; their queues fill and stay
    // full for the whole test.
    let stuck: Vec<TcpStream> = (0..4).map(|_| raw(addr)).collect();

    // The good pair: `tx` sends numbered frames, `rx` must get every one, in order, while the
    // churn goes on. At most 32 frames are in flight so a reader descheduled for a moment never
    // overflows its queue (that loss would be the reader's, not the hub's, fault).
    let mut tx = Client::connect(addr, "can0").unwrap();
    let mut rx = Client::connect(addr, "can0").unwrap();
    wait_until("good clients", || h.stats().clients == 6);
    let received = Arc::new(AtomicU32::new(0));
    let sent = Arc::new(AtomicU32::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let stop_reader = Arc::new(AtomicBool::new(false));
    let reader = {
        let received = Arc::clone(&received);
        let sent = Arc::clone(&sent);
        let stop = Arc::clone(&stop_reader);
        std::thread::spawn(move || {
            let mut next = 0u32;
            // After the writer stopped: read until its last frame arrived.
            while !stop.load(Ordering::SeqCst) || next < sent.load(Ordering::SeqCst) {
                let Some(r) = rx.recv_timeout(Some(Duration::from_millis(50))).unwrap() else {
                    continue;
                };
                if r.frame.std_id() != Some(0x181) {
                    continue; // the abusive clients' frames
                }
                assert_eq!(
                    r.frame.data(),
                    &next.to_le_bytes(),
                    "good client lost a frame"
                );
                next += 1;
                received.store(next, Ordering::SeqCst);
            }
            next
        })
    };
    let writer = {
        let received = Arc::clone(&received);
        let sent = Arc::clone(&sent);
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            let mut i = 0u32;
            while !stop.load(Ordering::SeqCst) {
                if i - received.load(Ordering::SeqCst) >= 32 {
                    std::thread::sleep(Duration::from_micros(100));
                    continue;
                }
                tx.send(&Frame::new(0x181, &i.to_le_bytes()).unwrap())
                    .unwrap();
                i += 1;
                sent.store(i, Ordering::SeqCst);
            }
            i
        })
    };

    // Warm-up churn, then the RSS baseline: allocator pools and thread stacks are reused from
    // here on, so growth after this point is what would leak per connection.
    for i in 0..100 {
        abuse(addr, i);
    }
    wait_until("warm-up clients gone", || h.stats().clients == 6);
    let rss0 = rss_kib();
    let sent0 = sent.load(Ordering::SeqCst);
    // CANPOS_HUB_CHURN raises the count for a longer leak hunt (RSS must stay flat).
    let churn: u32 = std::env::var("CANPOS_HUB_CHURN")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1000);
    for i in 100..100 + churn {
        abuse(addr, i);
    }
    wait_until("churn clients gone", || h.stats().clients == 6);
    let rss1 = rss_kib();
    let during = sent.load(Ordering::SeqCst) - sent0;
    // The stuck clients must have overflowed by now or soon: how many frames that takes
    // depends on socket buffer sizes, how fast the good pair ran on a loaded machine not at
    // all. Keep the good traffic going until the hub has dropped for them.
    let end = Instant::now() + Duration::from_secs(60);
    while h.stats().dropped == 0 {
        assert!(
            Instant::now() < end,
            "the stuck clients' queues never overflowed: {:?}",
            h.stats()
        );
        std::thread::sleep(Duration::from_millis(5));
    }

    stop.store(true, Ordering::SeqCst);
    let n_sent = writer.join().unwrap();
    stop_reader.store(true, Ordering::SeqCst);
    let n_recv = reader.join().unwrap();
    let stats = h.stats();
    eprintln!(
        "hub churn: rss {rss0} → {rss1} KiB, good frames {n_recv}/{n_sent} ({during} during the \
         churn), {stats:?}"
    );

    assert!(h.is_running());
    assert_eq!(stats.accepted, 6 + 100 + u64::from(churn));
    assert_eq!(n_recv, n_sent, "the good receiver lost frames");
    assert!(
        during > 100,
        "traffic stalled during the churn: {during} frames"
    );
    // Stuck clients overflowed their own queues only.
    assert!(stats.dropped > 0, "{stats:?}");
    // Bounded: 1000 connections may not cost more than 8 MiB (a per-connection leak of a
    // thread stack or a 4096-frame queue would be far more).
    assert!(
        rss1 <= rss0 + 8 * 1024,
        "RSS grew from {rss0} to {rss1} KiB over 1000 connections"
    );

    // The good pair ended with their threads; now the stuck ones leave too.
    drop(stuck);
    wait_until("stuck clients removed", || h.stats().clients == 0);
    // Still serving new clients.
    let mut c = Client::connect(addr, "can0").unwrap();
    let mut port = h.attach("can0");
    std::thread::sleep(Duration::from_millis(30));
    c.send(&Frame::new(0x42, &[]).unwrap()).unwrap();
    let got = loop {
        let r = port.recv_timeout(Some(WAIT)).unwrap().expect("frame");
        if r.frame.std_id() == Some(0x42) {
            break r.frame;
        }
    };
    assert_eq!(got, Frame::new(0x42, &[]).unwrap());
}
