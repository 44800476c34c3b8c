//! The hub's socketcand commands over TCP, as the reference daemon answers them (BCM send
//! jobs, errors), and canpos's extensions (remote frames, bus errors) with the canpos client,
//! including its fallback against a server without them. docs/SOCKETCAND.md.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::time::{Duration, Instant, SystemTime};

use canpos_host::bus::Pacing;
use canpos_host::socketcand::codec::ErrorFrame;
use canpos_host::socketcand::{Client, Hub, HubConfig, HubHandle};
use canpos_host::transport::{BusState, Transport};
use canpos_stack::Frame;

const WAIT: Duration = Duration::from_secs(5);

fn hub_with(config: HubConfig) -> HubHandle {
    Hub::bind_with("127.0.0.1:0", config)
        .unwrap()
        .spawn()
        .unwrap()
}

fn wait_until(what: &str, mut cond: impl FnMut() -> bool) {
    let end = Instant::now() + WAIT;
    while !cond() {
        assert!(Instant::now() < end, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Reads until the bytes end with `until`.
fn read_until(s: &mut TcpStream, until: &[u8]) -> String {
    s.set_read_timeout(Some(WAIT)).unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 512];
    while !got.ends_with(until) {
        let n = s.read(&mut buf).unwrap();
        assert!(n > 0, "closed; got {:?}", String::from_utf8_lossy(&got));
        got.extend_from_slice(&buf[..n]);
    }
    String::from_utf8(got).unwrap()
}

fn opened(addr: SocketAddr, channel: &str) -> TcpStream {
    let mut s = TcpStream::connect(addr).unwrap();
    assert_eq!(read_until(&mut s, b"< hi >"), "< hi >");
    s.write_all(format!("< open {channel} >").as_bytes())
        .unwrap();
    assert_eq!(read_until(&mut s, b">"), "< ok >");
    s
}

#[test]
fn bcm_send_and_a_cyclic_sync_producer() {
    let h = hub_with(HubConfig::default());
    let mut port = h.attach("can0");
    let mut s = opened(h.local_addr(), "can0");
    // BCM mode right after open, as with socketcand: `send` works without rawmode.
    s.write_all(b"< send 181 2 1 2 >").unwrap();
    assert_eq!(
        port.recv_timeout(Some(WAIT)).unwrap().unwrap().frame,
        Frame::new(0x181, &[1, 2]).unwrap()
    );
    // A 10 ms SYNC producer.
    s.write_all(b"< add 0 10000 080 0 >").unwrap();
    let sync = Frame::new(0x80, &[]).unwrap();
    let first = port.recv_timeout(Some(WAIT)).unwrap().unwrap();
    assert_eq!(first.frame, sync);
    let mut n = 1;
    while n < 10 {
        assert_eq!(port.recv_timeout(Some(WAIT)).unwrap().unwrap().frame, sync);
        n += 1;
    }
    // Ten cycles take at least nine periods (no assertion on the upper bound: the VM stalls).
    let spent = SystemTime::now()
        .duration_since(first.timestamp)
        .unwrap_or_default();
    assert!(spent >= Duration::from_millis(85), "{spent:?}");
    s.write_all(b"< update 080 1 7 >").unwrap();
    wait_until("updated SYNC", || {
        port.recv_timeout(Some(WAIT)).unwrap().unwrap().frame == Frame::new(0x80, &[7]).unwrap()
    });
    s.write_all(b"< delete 080 >< echo >").unwrap();
    assert_eq!(read_until(&mut s, b"< echo >"), "< echo >");
    // Drain what was already on its way, then silence.
    std::thread::sleep(Duration::from_millis(30));
    while port.try_recv().unwrap().is_some() {}
    assert_eq!(
        port.recv_timeout(Some(Duration::from_millis(50))).unwrap(),
        None
    );
    // Errors as socketcand words them.
    s.write_all(b"< delete 080 >< muxfilter 0 0 1 2 >< frobnicate >< add 0 0 080 0 >")
        .unwrap();
    assert_eq!(
        read_until(&mut s, b"add command >"),
        "< error no send job for this id >< error muxfilter is not supported >\
         < error unknown command >< error syntax error in add command >"
    );
}

#[test]
fn subscriptions_in_bcm_mode() {
    let h = hub_with(HubConfig::default());
    let port = h.attach("can0");
    let mut s = opened(h.local_addr(), "can0");
    s.write_all(b"< subscribe 0 0 181 >< echo >").unwrap();
    read_until(&mut s, b"< echo >");
    port.send_at(canpos_host::transport::RxFrame {
        frame: Frame::new(0x182, &[9]).unwrap(),
        timestamp: SystemTime::UNIX_EPOCH + Duration::from_secs(3),
    });
    port.send_at(canpos_host::transport::RxFrame {
        frame: Frame::new(0x181, &[1, 0xAB]).unwrap(),
        timestamp: SystemTime::UNIX_EPOCH + Duration::from_secs(3),
    });
    assert_eq!(read_until(&mut s, b" >"), "< frame 181 3.000000 01 AB  >");
}

#[test]
fn plain_raw_clients_see_remote_frames_as_today() {
    let h = hub_with(HubConfig::default());
    let port = h.attach("can0");
    let mut s = opened(h.local_addr(), "can0");
    s.write_all(b"< rawmode >").unwrap();
    assert_eq!(read_until(&mut s, b">"), "< ok >");
    std::thread::sleep(Duration::from_millis(30));
    let ts = SystemTime::UNIX_EPOCH + Duration::from_secs(9);
    for f in [
        Frame::remote(0x705, false, 1).unwrap(),
        Frame::remote(0x705, false, 0).unwrap(),
    ] {
        port.send_at(canpos_host::transport::RxFrame {
            frame: f,
            timestamp: ts,
        });
    }
    // DLC 1 cannot be written without the extension (counted); DLC 0 is a zero-length frame.
    assert_eq!(read_until(&mut s, b" >"), "< frame 705 9.000000  >");
    wait_until("the unencodable count", || h.stats().unencodable == 1);
    // A bus error is not given to a plain client of a hub without error frames.
    h.post_error("can0", ErrorFrame::for_state(BusState::BusOff, ts));
    s.write_all(b"< echo >").unwrap();
    assert_eq!(read_until(&mut s, b"< echo >"), "< echo >");
}

#[test]
fn bus_errors_reach_the_canpos_client_as_bus_states() {
    let h = hub_with(HubConfig::default());
    let c = Client::connect(h.local_addr(), "can0").unwrap();
    wait_until("client", || h.stats().clients == 1);
    assert_eq!(c.bus_state(), BusState::ErrorActive);
    for s in [
        BusState::ErrorPassive,
        BusState::BusOff,
        BusState::ErrorActive,
    ] {
        h.post_error("can0", ErrorFrame::for_state(s, SystemTime::now()));
        wait_until("bus state", || c.bus_state() == s);
    }
    // Another channel's errors are not this client's.
    h.post_error(
        "other",
        ErrorFrame::for_state(BusState::BusOff, SystemTime::now()),
    );
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(c.bus_state(), BusState::ErrorActive);
}

#[test]
fn a_hub_with_error_frames_gives_them_to_plain_clients() {
    let h = hub_with(HubConfig {
        error_frames: true,
        ..HubConfig::default()
    });
    let mut s = opened(h.local_addr(), "can0");
    s.write_all(b"< rawmode >").unwrap();
    assert_eq!(read_until(&mut s, b">"), "< ok >");
    let ts = SystemTime::UNIX_EPOCH + Duration::from_secs(4);
    h.post_error("can0", ErrorFrame::for_state(BusState::BusOff, ts));
    assert_eq!(
        read_until(&mut s, b">"),
        "< error 040 4.000000 00 00 00 00 00 00 00 00 >"
    );
}

/// A server that speaks like the reference daemon in raw mode: no extensions, errors in raw
/// mode as class and time only.
fn reference_like_server() -> (SocketAddr, std::thread::JoinHandle<Vec<u8>>) {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = l.local_addr().unwrap();
    let j = std::thread::spawn(move || {
        let (mut s, _) = l.accept().unwrap();
        s.set_read_timeout(Some(WAIT)).unwrap();
        let mut got = Vec::new();
        let mut buf = [0u8; 512];
        let mut step = 0;
        s.write_all(b"< hi >").unwrap();
        loop {
            let n = match s.read(&mut buf) {
                Ok(0) | Err(_) => return got,
                Ok(n) => n,
            };
            got.extend_from_slice(&buf[..n]);
            let text = String::from_utf8_lossy(&got).into_owned();
            if step == 0 && text.contains("< open can0 >") {
                s.write_all(b"< ok >").unwrap();
                step = 1;
            }
            if step == 1 && text.contains("< rawmode >") {
                s.write_all(b"< ok >< frame 181 1.000000 01 >").unwrap();
                step = 2;
            }
            if step == 2 && text.contains("< errors on >") {
                s.write_all(b"< error unknown command >< error unknown command >")
                    .unwrap();
                s.write_all(b"< error 004 2.000000 >").unwrap();
                step = 3;
            }
        }
    });
    (addr, j)
}

#[test]
fn against_a_server_without_extensions_the_client_speaks_plain_socketcand() {
    let (addr, server) = reference_like_server();
    let mut c = Client::connect(addr, "can0").unwrap();
    assert!(!c.carries_remote_frames());
    // The frame that came before the answers is kept.
    assert_eq!(
        c.recv_timeout(Some(WAIT)).unwrap().unwrap().frame,
        Frame::new(0x181, &[1]).unwrap()
    );
    // socketcand's raw-mode error element (class only): a controller problem = error passive.
    wait_until("error passive", || c.bus_state() == BusState::ErrorPassive);
    c.send(&Frame::remote(0x705, false, 0).unwrap()).unwrap();
    assert_eq!(
        c.send(&Frame::remote(0x705, false, 1).unwrap())
            .unwrap_err()
            .kind(),
        std::io::ErrorKind::InvalidInput
    );
    drop(c);
    let sent = String::from_utf8(server.join().unwrap()).unwrap();
    assert!(sent.ends_with("< send 705 0  >"), "{sent}");
}

/// The bus timeline's error frames (here: every frame corrupted) reach a hub client that asked
/// for errors as `< error CLASS SEC.USEC D0 … D7 >`: a protocol violation (class 0x008) with
/// the form-error bit, and no frame is delivered.
#[test]
fn timeline_error_frames_reach_clients_that_take_errors() {
    let h = hub_with(HubConfig::default());
    let mut port = h.attach("can0");
    let mut s = opened(h.local_addr(), "can0");
    s.write_all(b"< rawmode >").unwrap();
    assert_eq!(read_until(&mut s, b">"), "< ok >");
    s.write_all(b"< errors on >").unwrap();
    assert_eq!(read_until(&mut s, b">"), "< ok >");
    port.disturb(canpos_host::transport::Disturbance::CorruptedFrames {
        per_million: 1_000_000,
    })
    .unwrap();
    port.send(&Frame::new(0x181, &[1, 2]).unwrap()).unwrap();
    let got = read_until(&mut s, b">");
    assert!(
        got.starts_with("< error 008 ") || got.starts_with("< error 00000008 "),
        "{got}"
    );
    assert!(!got.contains("frame"), "{got}");
}

/// How late an independent thread wakes from 1 ms sleeps while it runs: the machine's own
/// scheduling delay during a timed window. A wall-time figure is judged against it, measured
/// in the same run, so a loaded machine (a 2-core VM stalls ~100 ms now and then) does not
/// fail a test that a fixed bound alone would.
struct Sleeper {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: std::thread::JoinHandle<Duration>,
}

impl Sleeper {
    fn start() -> Sleeper {
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::spawn(move || {
            let step = Duration::from_millis(1);
            let mut worst = Duration::ZERO;
            while !flag.load(std::sync::atomic::Ordering::Relaxed) {
                let t = Instant::now();
                std::thread::sleep(step);
                worst = worst.max(t.elapsed().saturating_sub(step));
            }
            worst
        });
        Sleeper { stop, thread }
    }

    /// The worst oversleep seen (its sleep in progress included).
    fn worst(self) -> Duration {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        self.thread.join().unwrap()
    }
}

/// Issue 36 item 4: two raw clients; one that opened a second earlier sends a frame 0.1 s
/// after the other opened, and the other gets it within 50 ms, on a paced and on an instant
/// bus. It came about 450 ms late while the hub held frames back after the rawmode `< ok >`
/// until the client spoke, for at most 500 ms (python-can reads that `< ok >` with one `recv`;
/// now an urgent byte ends that read instead).
///
/// 50 ms is judged against the machine: the latency may exceed it by the worst oversleep of an
/// independent 1 ms sleeper during the same window. Three fresh clients per bus, each judged
/// on its own window: the old hold-back (350 ms from the send) passes one only if the machine
/// stalled 300 ms in that very window, three times in a row. No absolute bound on top: a
/// loaded VM's stalls reach 230 ms (docs/CLOCK.md), too close to any bound that would still
/// tell the hold-back apart.
#[test]
fn a_fresh_raw_client_gets_frames_at_once() {
    for pacing in [Pacing::Paced(1000), Pacing::Instant] {
        let h = hub_with(HubConfig {
            pacing,
            ..HubConfig::default()
        });
        let raw = |s: &mut TcpStream| {
            s.write_all(b"< rawmode >").unwrap();
            assert_eq!(read_until(s, b">"), "< ok >");
        };
        let mut first = opened(h.local_addr(), "can0");
        raw(&mut first);
        std::thread::sleep(Duration::from_secs(1));
        for attempt in 0..3u8 {
            let mut second = opened(h.local_addr(), "can0");
            raw(&mut second);
            std::thread::sleep(Duration::from_millis(100));
            let sleeper = Sleeper::start();
            let sent = Instant::now();
            first
                .write_all(format!("< send 123 4 de ad be {attempt:02x} >").as_bytes())
                .unwrap();
            let got = read_until(&mut second, b">");
            let took = sent.elapsed();
            let slack = sleeper.worst();
            assert!(got.starts_with("< frame 123 "), "{got}");
            assert!(got.ends_with(&format!(" DEADBE{attempt:02X} >")), "{got}");
            assert!(
                took <= Duration::from_millis(50) + slack,
                "{pacing:?}, client {attempt}: {took:?} (an independent sleeper overslept {slack:?})"
            );
        }
    }
}

/// What the hold-back protected: python-can reads the rawmode `< ok >` with one `recv(256)` and
/// compares it exactly. A client that reads it only 200 ms later, while frames flow, still
/// reads `< ok >` alone (the urgent mark after it ends the read), then the frames, in order
/// and none lost.
#[test]
fn the_rawmode_ok_is_read_alone_however_late_the_client_reads() {
    let h = hub_with(HubConfig::default());
    let mut port = h.attach("can0");
    let mut s = opened(h.local_addr(), "can0");
    s.write_all(b"< rawmode >").unwrap();
    // The `< ok >` is on its way; the hub's `< ok >` and the frames all arrive before the read.
    std::thread::sleep(Duration::from_millis(50));
    for i in 0..3u8 {
        port.send(&Frame::new(0x181, &[i]).unwrap()).unwrap();
    }
    std::thread::sleep(Duration::from_millis(150));
    s.set_read_timeout(Some(WAIT)).unwrap();
    let mut buf = [0u8; 256];
    let n = s.read(&mut buf).unwrap();
    assert_eq!(String::from_utf8_lossy(&buf[..n]), "< ok >");
    let got = read_until(&mut s, b" 02 >");
    let frames: Vec<&str> = got.split_inclusive('>').map(str::trim).collect();
    assert_eq!(frames.len(), 3, "{got}");
    for (i, f) in frames.iter().enumerate() {
        assert!(f.starts_with("< frame 181 "), "{got}");
        assert!(f.ends_with(&format!(" 0{i} >")), "frame {i}: {got}");
    }
}

/// The next element on `s` that is not a frame (a raw client gets the others' frames between
/// its answers).
fn reply(s: &mut TcpStream) -> String {
    loop {
        let el = element(s);
        if !el.starts_with("< frame ") {
            return el;
        }
    }
}

/// The next element on `s`, read a byte at a time (nothing after it is consumed).
fn element(s: &mut TcpStream) -> String {
    s.set_read_timeout(Some(WAIT)).unwrap();
    let mut got = Vec::new();
    let mut b = [0u8; 1];
    while !got.ends_with(b">") {
        assert_eq!(s.read(&mut b).unwrap(), 1, "closed after {got:?}");
        if !(got.is_empty() && b[0] == b' ') {
            got.push(b[0]);
        }
    }
    String::from_utf8(got).unwrap()
}

/// `SEC.USEC` of a wall-clock time, as the protocol writes it.
fn secs(t: SystemTime) -> String {
    let d = t.duration_since(std::time::UNIX_EPOCH).unwrap();
    format!("{}.{:06}", d.as_secs(), d.subsec_micros())
}

/// A raw-mode client on `can0`.
fn raw_client(addr: SocketAddr) -> TcpStream {
    let mut s = opened(addr, "can0");
    s.write_all(b"< rawmode >").unwrap();
    assert_eq!(read_until(&mut s, b">"), "< ok >");
    s
}

/// Whether anything arrives on `s` within `d` (a negative check: a lower bound only).
fn nothing_within(s: &mut TcpStream, d: Duration) -> bool {
    s.set_read_timeout(Some(d)).unwrap();
    let mut b = [0u8; 64];
    let r = s.read(&mut b);
    s.set_read_timeout(Some(WAIT)).unwrap();
    match r {
        Ok(n) => {
            // The urgent byte after the rawmode `< ok >` may be read late as nothing.
            n == 0 || b[..n].iter().all(|&c| c == b' ')
        }
        Err(e) => matches!(
            e.kind(),
            std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
        ),
    }
}

/// The end-of-frame stamp of a `< frame … >` element, as a wall-clock time.
fn stamp_of(el: &str) -> SystemTime {
    let t = el.split_whitespace().nth(3).unwrap();
    let (s, us) = t.split_once('.').unwrap();
    std::time::UNIX_EPOCH + Duration::new(s.parse().unwrap(), us.parse::<u32>().unwrap() * 1000)
}

/// Issue 36 item 1, behind the hub: a timed client (`< clock on >`) that says where it is
/// (`< at … >`) holds its channel's bus there: an untimed client's frame waits until the timed
/// one moved on past its time, and the timed client's own frame is stamped with its horizon
/// (its start of frame is the `< at >` time exactly: end of frame = it + its bits at 1 µs).
#[test]
fn a_timed_client_holds_the_bus_at_its_horizon_and_its_frames_carry_it() {
    let h = hub_with(HubConfig::default());
    let mut timed = raw_client(h.local_addr());
    let mut other = raw_client(h.local_addr());
    let mut listener = raw_client(h.local_addr());
    timed.write_all(b"< clock on >").unwrap();
    assert_eq!(reply(&mut timed), "< ok >");
    // Before its first `< at >` it holds nothing.
    other.write_all(b"< send 100 1 01 >").unwrap();
    assert!(element(&mut listener).starts_with("< frame 100 "));
    let x0 = SystemTime::now();
    timed
        .write_all(format!("< at {} >", secs(x0)).as_bytes())
        .unwrap();
    // The hub read the `< at >` (answered in order after it).
    timed.write_all(b"< echo >").unwrap();
    assert_eq!(reply(&mut timed), "< echo >");
    other.write_all(b"< send 123 2 de ad >").unwrap();
    // Held: the timed client is behind (x0) and within the stall bound (2 s).
    assert!(
        nothing_within(&mut listener, Duration::from_millis(300)),
        "a frame passed a timed client that is behind"
    );
    // It moves on 250 ms (still behind the wall clock) and sends a frame there: the held
    // frame, sent a few ms after x0, comes; its own frame is stamped x1 and ends after x1, so
    // the bus does not carry it yet (it never runs past the horizon).
    let x1 = x0 + Duration::from_millis(250);
    timed
        .write_all(format!("< at {} >< send 321 1 aa >", secs(x1)).as_bytes())
        .unwrap();
    let got = element(&mut listener);
    assert!(got.starts_with("< frame 123 "), "{got}");
    assert!(stamp_of(&got) < x1, "{got}");
    assert!(
        nothing_within(&mut listener, Duration::from_millis(100)),
        "a frame ending after the horizon was carried"
    );
    // Far ahead: it holds nothing any more; its frame comes, stamped with its horizon.
    timed
        .write_all(
            format!(
                "< at {} >",
                secs(SystemTime::now() + Duration::from_secs(3600))
            )
            .as_bytes(),
        )
        .unwrap();
    let got = element(&mut listener);
    assert!(got.starts_with("< frame 321 "), "{got}");
    // On an idle bus it starts at its time and ends its bits later (the intermission after
    // its end excluded), 1 µs a bit at 1 Mbit/s.
    use canpos_host::bus::bits::{frame_length, INTERMISSION_BITS};
    let bits = frame_length(&Frame::new(0x321, &[0xAA]).unwrap()).total - INTERMISSION_BITS;
    let x1_us = stamp_of(&format!("< frame 0 {} >", secs(x1)));
    assert_eq!(
        stamp_of(&got),
        x1_us + Duration::from_micros(u64::from(bits)),
        "stamped with its horizon: start of frame = the `< at >` time, {bits} bits at 1 µs"
    );
    // A frame after a far-future `< at >` is stamped when it was sent, never in the future.
    timed.write_all(b"< send 322 0  >").unwrap();
    let got = element(&mut listener);
    assert!(got.starts_with("< frame 322 "), "{got}");
    assert!(stamp_of(&got) <= SystemTime::now(), "{got}");
    // `< clock off >`: untimed again.
    timed.write_all(b"< clock off >").unwrap();
    assert_eq!(reply(&mut timed), "< ok >");
}

/// A timed client that stops for good (or never moves) holds its bus no longer than the
/// clock's stall bound, then the others' frames flow again (with a WARN in the hub's log).
#[test]
fn a_stopped_timed_client_holds_the_bus_no_longer_than_the_stall_bound() {
    let bound = Duration::from_millis(500);
    let h = hub_with(HubConfig {
        stall_bound: bound,
        ..HubConfig::default()
    });
    let mut timed = raw_client(h.local_addr());
    let mut other = raw_client(h.local_addr());
    let mut listener = raw_client(h.local_addr());
    timed.write_all(b"< clock on >").unwrap();
    assert_eq!(reply(&mut timed), "< ok >");
    let x0 = SystemTime::now();
    timed
        .write_all(format!("< at {} >< echo >", secs(x0)).as_bytes())
        .unwrap();
    assert_eq!(reply(&mut timed), "< echo >");
    let sent = Instant::now();
    other.write_all(b"< send 123 1 01 >").unwrap();
    let got = element(&mut listener);
    assert!(got.starts_with("< frame 123 "), "{got}");
    // Held until the horizon fell behind the bound (x0 + bound; a lower bound only).
    assert!(
        SystemTime::now().duration_since(x0).unwrap() >= bound,
        "delivered after {:?}",
        sent.elapsed()
    );
    // Stale, it holds nothing: the next frame comes at once (generous bound).
    let sent = Instant::now();
    other.write_all(b"< send 124 1 02 >").unwrap();
    assert!(element(&mut listener).starts_with("< frame 124 "));
    assert!(
        sent.elapsed() < Duration::from_secs(1),
        "{:?}",
        sent.elapsed()
    );
    // It catches up and holds again.
    timed
        .write_all(format!("< at {} >< echo >", secs(SystemTime::now())).as_bytes())
        .unwrap();
    assert_eq!(reply(&mut timed), "< echo >");
    other.write_all(b"< send 125 1 03 >").unwrap();
    assert!(nothing_within(&mut listener, Duration::from_millis(100)));
    assert!(element(&mut listener).starts_with("< frame 125 "));
}

/// Bad `< clock … >` / `< at … >` get the hub's error element and change nothing.
#[test]
fn bad_clock_requests_are_refused() {
    let h = hub_with(HubConfig::default());
    let mut c = raw_client(h.local_addr());
    let mut other = raw_client(h.local_addr());
    let mut listener = raw_client(h.local_addr());
    let now = secs(SystemTime::now());
    for (ask, answer) in [
        (format!("< at {now} >"), "< error at needs clock on >"),
        (
            "< clock >".into(),
            "< error syntax error in clock command >",
        ),
        (
            "< clock maybe >".into(),
            "< error syntax error in clock command >",
        ),
        ("< at >".into(), "< error syntax error in at command >"),
        ("< at soon >".into(), "< error syntax error in at command >"),
        (
            "< at 1.5 2 >".into(),
            "< error syntax error in at command >",
        ),
        ("< at -1.0 >".into(), "< error syntax error in at command >"),
        (
            "< at 99999999999999.0 >".into(),
            "< error syntax error in at command >",
        ),
    ] {
        c.write_all(ask.as_bytes()).unwrap();
        assert_eq!(reply(&mut c), answer, "{ask}");
    }
    c.write_all(b"< clock on >< clock on >").unwrap();
    assert_eq!(reply(&mut c), "< ok >");
    assert_eq!(reply(&mut c), "< ok >");
    // Before the bus's time by more than the stall bound: refused, nothing held.
    let old = secs(SystemTime::now() - Duration::from_secs(10));
    for t in ["1.000000", "0.0", old.as_str()] {
        c.write_all(format!("< at {t} >").as_bytes()).unwrap();
        assert_eq!(
            reply(&mut c),
            "< error at is before the bus's time by more than the stall bound >",
            "{t}"
        );
    }
    // The refused ones set no horizon: the bus is not held.
    other.write_all(b"< send 123 1 01 >").unwrap();
    let sent = Instant::now();
    assert!(element(&mut listener).starts_with("< frame 123 "));
    assert!(
        sent.elapsed() < Duration::from_secs(1),
        "{:?}",
        sent.elapsed()
    );
    // An instant channel has no clock.
    let hi = hub_with(HubConfig {
        pacing: Pacing::Instant,
        ..HubConfig::default()
    });
    let mut c = raw_client(hi.local_addr());
    c.write_all(b"< clock on >").unwrap();
    assert_eq!(
        reply(&mut c),
        "< error this channel has no clock (instant bus) >"
    );
    // Not before a channel is open.
    let mut s = TcpStream::connect(h.local_addr()).unwrap();
    assert_eq!(read_until(&mut s, b"< hi >"), "< hi >");
    s.write_all(b"< clock on >").unwrap();
    assert_eq!(read_until(&mut s, b">"), "< error unknown command >");
}

/// A client with `SO_OOBINLINE` reads the urgent byte after the rawmode `< ok >` as a space in
/// the stream, between two elements, which a socketcand parser skips (docs/SOCKETCAND.md); a
/// client that is not in raw mode (BCM after `< open >`, a mode switch back) gets no urgent byte.
#[test]
fn an_oobinline_client_reads_one_space_between_elements_and_only_after_rawmode() {
    use canpos_host::socketcand::codec::{Decoder, Element};
    use std::os::fd::AsRawFd;
    let h = hub_with(HubConfig::default());
    let mut port = h.attach("can0");
    let mut s = TcpStream::connect(h.local_addr()).unwrap();
    let on: libc::c_int = 1;
    // SAFETY: a valid socket and an int option of the right size.
    let r = unsafe {
        libc::setsockopt(
            s.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_OOBINLINE,
            (&on as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    assert_eq!(r, 0, "{}", std::io::Error::last_os_error());
    let mut all = read_until(&mut s, b"< hi >");
    s.write_all(b"< open can0 >").unwrap();
    all += &read_until(&mut s, b"< ok >");
    // Outside raw mode (BCM after the open, then control mode): no urgent byte.
    s.write_all(b"< controlmode >< echo >").unwrap();
    all += &read_until(&mut s, b"< echo >");
    assert_eq!(
        all, "< hi >< ok >< ok >< echo >",
        "no urgent byte outside raw mode"
    );
    s.write_all(b"< rawmode >").unwrap();
    let ok = read_until(&mut s, b"< ok >");
    assert_eq!(ok, "< ok >");
    for i in 0..2u8 {
        port.send(&Frame::new(0x181, &[i]).unwrap()).unwrap();
    }
    let rest = read_until(&mut s, b" 01 >");
    assert!(rest.starts_with(" < frame 181 "), "{rest:?}");
    // One space, once: the frames after it follow each other as ever.
    assert!(rest[1..].contains(">< frame 181 "), "{rest:?}");
    let els = Decoder::new().feed_parse(format!("{ok}{rest}").as_bytes());
    assert!(
        matches!(els[..], [Element::Ok, Element::Frame(_), Element::Frame(_)]),
        "{els:?}"
    );
}
