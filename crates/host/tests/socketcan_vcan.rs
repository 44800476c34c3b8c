//! The SocketCAN transport and the runtime on a real kernel CAN stack: `vcan0`.
//!
//! These run only where `CANPOS_VCAN=1` (set by `scripts/uml/run-in-uml.sh`, which boots a
//! User-Mode Linux guest with vcan0 up); elsewhere each test prints a skip note and passes.
//!   scripts/uml/run-in-uml.sh cargo test -p canpos-host --test socketcan_vcan
//! or, as a cargo runner:
//!   CARGO_TARGET_X86_64_UNKNOWN_LINUX_GNU_RUNNER=scripts/uml/run-in-uml.sh cargo test ...
#![cfg(all(target_os = "linux", feature = "socketcan"))]

use std::os::fd::AsRawFd;
use std::sync::Mutex;
use std::time::{Duration, Instant, SystemTime};

use canpos_host::runtime::{state_file, SensorSetup};
use canpos_host::socketcan::{self as sc, SocketCanTransport};
use canpos_host::transport::{BusState, Transport};
use canpos_host::{FileStorage, Runtime};
use canpos_sim::motion::{Profile, Profiles};
use canpos_sim::SensorSpec;
use canpos_stack::Frame;

const IFACE: &str = "vcan0";
/// The tests share vcan0: one at a time.
static BUS: Mutex<()> = Mutex::new(());

fn vcan() -> Option<std::sync::MutexGuard<'static, ()>> {
    if std::env::var("CANPOS_VCAN").as_deref() != Ok("1") {
        eprintln!("skipped: needs vcan0 (CANPOS_VCAN=1; run under scripts/uml/run-in-uml.sh)");
        return None;
    }
    Some(BUS.lock().unwrap_or_else(|p| p.into_inner()))
}

/// A raw peer socket on vcan0 written with `write(2)`, so error frames can be injected too.
struct Peer {
    sock: socketcan::CanSocket,
}

impl Peer {
    fn new() -> Peer {
        use socketcan::Socket;
        let sock = socketcan::CanSocket::open(IFACE).expect("open vcan0");
        sock.set_read_timeout(Duration::from_millis(50)).unwrap();
        Peer { sock }
    }

    fn write_raw(&self, can_id: u32, data: &[u8]) {
        // SAFETY: can_frame is plain data; we write exactly one struct.
        let mut f: libc::can_frame = unsafe { std::mem::zeroed() };
        f.can_id = can_id;
        f.can_dlc = data.len() as u8;
        f.data[..data.len()].copy_from_slice(data);
        let n = unsafe {
            libc::write(
                self.sock.as_raw_fd(),
                (&f as *const libc::can_frame).cast(),
                std::mem::size_of::<libc::can_frame>(),
            )
        };
        assert_eq!(
            n as usize,
            std::mem::size_of::<libc::can_frame>(),
            "write: {}",
            std::io::Error::last_os_error()
        );
    }

    fn send(&self, id: u16, data: &[u8]) {
        self.write_raw(u32::from(id), data);
    }

    fn rtr(&self, id: u16, dlc: u8) {
        // SAFETY: as in write_raw; an RTR carries a DLC but no data.
        let mut f: libc::can_frame = unsafe { std::mem::zeroed() };
        f.can_id = u32::from(id) | 0x4000_0000;
        f.can_dlc = dlc;
        let n = unsafe {
            libc::write(
                self.sock.as_raw_fd(),
                (&f as *const libc::can_frame).cast(),
                std::mem::size_of::<libc::can_frame>(),
            )
        };
        assert!(n > 0);
    }

    /// Next data frame with this ID (others are skipped).
    fn expect(&self, id: u16, within: Duration) -> Option<Vec<u8>> {
        use socketcan::{EmbeddedFrame, Socket};
        let end = Instant::now() + within;
        while Instant::now() < end {
            if let Ok(f) = self.sock.read_frame() {
                if !f.is_remote_frame()
                    && matches!(f.id(), socketcan::Id::Standard(s) if s.as_raw() == id)
                {
                    return Some(f.data().to_vec());
                }
            }
        }
        None
    }

    /// Every data frame read within `within`, in order.
    fn collect(&self, within: Duration) -> Vec<(u16, Vec<u8>)> {
        use socketcan::{EmbeddedFrame, Socket};
        let end = Instant::now() + within;
        let mut out = Vec::new();
        while Instant::now() < end {
            if let Ok(f) = self.sock.read_frame() {
                if let (false, socketcan::Id::Standard(s)) = (f.is_remote_frame(), f.id()) {
                    out.push((s.as_raw(), f.data().to_vec()));
                }
            }
        }
        out
    }

    fn drain(&self) {
        use socketcan::Socket;
        while self.sock.read_frame().is_ok() {}
    }
}

fn th(dir: &std::path::Path, node_id: u8) -> SensorSetup {
    let model = canpos_models::by_name("th").unwrap();
    let mut cfg = model.default_config;
    cfg.node_id = node_id;
    cfg.serial = 1000 + u32::from(node_id);
    SensorSetup {
        name: format!("th-{node_id}"),
        model,
        cfg,
        spec: SensorSpec::th(f64::from(cfg.stroke_mm), 1).unwrap(),
        seed: 1,
        ideal: true,
        motion: Box::new(Profiles(vec![Profile::Static { pos_mm: 250.0 }])),
        storage: FileStorage::new(state_file(dir, "th", cfg.serial)),
    }
}

fn emcy_code(d: &[u8]) -> u16 {
    u16::from_le_bytes([d[0], d[1]])
}

#[test]
fn vcan0_is_a_can_interface() {
    let Some(_g) = vcan() else { return };
    let mtu: u32 = std::fs::read_to_string("/sys/class/net/vcan0/mtu")
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    // 72 on 6.x kernels, 2060 on UML 7.2.
    assert!(mtu >= 72, "mtu {mtu}");
}

#[test]
fn kernel_filter_timestamps_and_frames() {
    let Some(_g) = vcan() else { return };
    let peer = Peer::new();
    let mut t = SocketCanTransport::open(IFACE).unwrap();
    assert!(t.set_rx_filter(&[0x000, 0x605]).unwrap());
    let before = SystemTime::now();
    peer.send(0x123, &[1]); // filtered out in the kernel
    peer.send(0x605, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]);
    peer.rtr(0x185, 8); // remote frames always pass
    peer.send(0x000, &[1, 5]);
    let mut got = Vec::new();
    while let Ok(Some(rx)) = t.recv_timeout(Some(Duration::from_millis(300))) {
        got.push(rx);
    }
    let frames: Vec<Frame> = got.iter().map(|r| r.frame).collect();
    assert_eq!(
        frames,
        vec![
            Frame::new(0x605, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).unwrap(),
            Frame::remote(0x185, false, 8).unwrap(),
            Frame::new(0x000, &[1, 5]).unwrap(),
        ]
    );
    // Kernel receive timestamps: between the first send and now, in order.
    let after = SystemTime::now();
    for w in got.windows(2) {
        assert!(w[0].timestamp <= w[1].timestamp);
    }
    for r in &got {
        assert!(r.timestamp >= before - Duration::from_millis(1) && r.timestamp <= after);
    }
    let s = t.stats();
    assert_eq!(s.rx_frames, 3, "{s:?}");
    // Sending counts too.
    t.send(&Frame::new(0x585, &[0x43, 0, 0x10, 0, 0x96, 1, 8, 0]).unwrap())
        .unwrap();
    assert_eq!(peer.expect(0x585, Duration::from_secs(1)).unwrap()[0], 0x43);
    assert_eq!(t.stats().tx_frames, 1);
    assert_eq!(t.dropped(), 0);
}

#[test]
fn receive_overflow_is_detected_and_counted() {
    let Some(_g) = vcan() else { return };
    let peer = Peer::new();
    // The smallest receive buffer the kernel allows: a flood overflows it.
    let mut t = SocketCanTransport::open_with(IFACE, &sc::Options { rcvbuf: Some(1) }).unwrap();
    const N: usize = 3000;
    for i in 0..N {
        peer.send(0x200, &(i as u32).to_le_bytes());
    }
    let mut received = 0usize;
    while let Ok(Some(_)) = t.recv_timeout(Some(Duration::from_millis(300))) {
        received += 1;
    }
    // The kernel reports the drop count with the next frame it delivers: one more frame makes
    // the count exact.
    peer.send(0x201, &[]);
    while let Ok(Some(_)) = t.recv_timeout(Some(Duration::from_millis(300))) {
        received += 1;
    }
    let s = t.stats();
    eprintln!("flood of {N}: received {received}, {s:?}");
    assert!(s.rx_kernel_dropped > 0, "no overflow detected: {s:?}");
    assert_eq!(
        received as u64 + s.rx_kernel_dropped + s.rx_queue_dropped,
        N as u64 + 1,
        "{s:?}"
    );
    // The reader thread was late, the bus lost nothing: no CAN overrun (issue 36 item 1).
    assert_eq!(t.dropped(), 0, "{s:?}");
}

#[test]
fn runtime_raises_can_overrun_emcy_for_controller_losses_not_for_a_busy_host() {
    let Some(_g) = vcan() else { return };
    let dir = tempfile::tempdir().unwrap();
    let peer = Peer::new();
    let t = SocketCanTransport::open_with(IFACE, &sc::Options { rcvbuf: Some(1) }).unwrap();
    let stats = t.stats_handle();
    let mut rt = Runtime::new(Box::new(t), None);
    rt.add(th(dir.path(), 21));
    let h = rt.spawn().unwrap();
    assert_eq!(peer.expect(0x715, Duration::from_secs(2)), Some(vec![0]));
    std::thread::sleep(Duration::from_millis(100));
    peer.drain();
    // A flood overflows the socket's tiny receive buffer: the reader thread did not read in
    // time, as on a busy host. NMT frames for another node pass the kernel filter but mean
    // nothing to node 21.
    for _ in 0..3000 {
        peer.send(0x000, &[0x80, 99]);
    }
    // An SDO request after it brings the kernel's drop count along; the node answers it, and
    // sends no EMCY (issue 36 item 1). The request itself may be lost while the buffer is
    // full: asked again.
    let mut seen = Vec::new();
    for _ in 0..5 {
        peer.send(0x615, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]);
        seen.extend(peer.collect(Duration::from_millis(600)));
        if seen.iter().any(|(id, d)| *id == 0x595 && d[0] == 0x43) {
            break;
        }
    }
    let s = stats.get();
    assert!(s.rx_kernel_dropped > 0, "the flood lost nothing: {s:?}");
    assert!(
        seen.iter().any(|(id, d)| *id == 0x595 && d[0] == 0x43),
        "no SDO answer after the flood: {seen:02X?}"
    );
    // The runtime looks at the counters at every turn; a second more for a late EMCY.
    seen.extend(peer.collect(Duration::from_secs(1)));
    let emcy: Vec<_> = seen.iter().filter(|(id, _)| *id == 0x95).collect();
    assert!(
        emcy.is_empty(),
        "EMCY from the host's scheduling: {emcy:02X?} ({s:?})"
    );

    // The controller reports a receive overflow (an error frame, as a real adapter's driver
    // sends it): the bus lost frames, EMCY 0x8110.
    const ERR: u32 = 0x2000_0000;
    peer.write_raw(
        ERR | sc::err::CRTL,
        &[0, sc::err::CRTL_RX_OVERFLOW, 0, 0, 0, 0, 0, 0],
    );
    // The runtime notices it at its next turn: a frame wakes it.
    peer.send(0x000, &[0x80, 99]);
    let e = peer.expect(0x95, Duration::from_secs(2)).expect("EMCY");
    assert_eq!(emcy_code(&e), 0x8110, "{e:02X?}");
    assert_eq!(e[2] & 0x10, 0x10, "communication bit in the error register");
    assert_eq!(stats.get().rx_controller_overflows, 1);
    // Cleared after a second without losses.
    let e = peer
        .expect(0x95, Duration::from_secs(3))
        .expect("EMCY clear");
    assert_eq!(emcy_code(&e), 0x0000, "{e:02X?}");
    // The node is still fine.
    peer.send(0x615, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]);
    assert_eq!(peer.expect(0x595, Duration::from_secs(2)).unwrap()[0], 0x43);
    h.stop().unwrap();
}

#[test]
fn error_frames_are_surfaced_not_crashed_on() {
    let Some(_g) = vcan() else { return };
    let dir = tempfile::tempdir().unwrap();
    let peer = Peer::new();
    // The transport alone: counts and states.
    let t = SocketCanTransport::open(IFACE).unwrap();
    const ERR: u32 = 0x2000_0000;
    peer.write_raw(
        ERR | sc::err::CRTL,
        &[0, sc::err::CRTL_RX_PASSIVE, 0, 0, 0, 0, 0, 0],
    );
    let end = Instant::now() + Duration::from_secs(2);
    while t.bus_state() != BusState::ErrorPassive && Instant::now() < end {
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(t.bus_state(), BusState::ErrorPassive);
    assert_eq!(t.stats().error_frames, 1);
    drop(t);

    // The runtime: error passive → EMCY 0x8120; bus-off then restart → 0x8140.
    let t = SocketCanTransport::open(IFACE).unwrap();
    let mut rt = Runtime::new(Box::new(t), None);
    rt.add(th(dir.path(), 22));
    let h = rt.spawn().unwrap();
    assert_eq!(peer.expect(0x716, Duration::from_secs(2)), Some(vec![0]));
    std::thread::sleep(Duration::from_millis(100));
    peer.drain();
    peer.write_raw(
        ERR | sc::err::CRTL,
        &[0, sc::err::CRTL_TX_PASSIVE, 0, 0, 0, 0, 0, 0],
    );
    // The runtime notices the state at its next turn: a frame wakes it.
    peer.send(0x000, &[0x80, 99]);
    let e = peer
        .expect(0x96, Duration::from_secs(2))
        .expect("EMCY 0x8120");
    assert_eq!(emcy_code(&e), 0x8120, "{e:02X?}");
    peer.write_raw(ERR | sc::err::BUSOFF, &[0; 8]);
    peer.send(0x000, &[0x80, 99]);
    let e = peer
        .expect(0x96, Duration::from_secs(2))
        .expect("EMCY clear on bus-off");
    assert_eq!(emcy_code(&e), 0x0000, "{e:02X?}");
    peer.write_raw(ERR | sc::err::RESTARTED, &[0; 8]);
    peer.send(0x000, &[0x80, 99]);
    let e = peer
        .expect(0x96, Duration::from_secs(2))
        .expect("EMCY 0x8140");
    assert_eq!(emcy_code(&e), 0x8140, "{e:02X?}");
    // Garbage error classes are just counted.
    for class in [
        sc::err::PROT,
        sc::err::ACK,
        sc::err::LOSTARB,
        sc::err::TRX,
        0x1FFF_FFFF,
    ] {
        peer.write_raw(ERR | class, &[0xFF; 8]);
    }
    peer.drain();
    peer.send(0x616, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]);
    assert_eq!(peer.expect(0x596, Duration::from_secs(2)).unwrap()[0], 0x43);
    h.stop().unwrap();
}

#[test]
fn node_guarding_by_true_remote_frames() {
    let Some(_g) = vcan() else { return };
    let dir = tempfile::tempdir().unwrap();
    let peer = Peer::new();
    let t = SocketCanTransport::open(IFACE).unwrap();
    let mut rt = Runtime::new(Box::new(t), None);
    rt.add(th(dir.path(), 23));
    let h = rt.spawn().unwrap();
    assert_eq!(peer.expect(0x717, Duration::from_secs(2)), Some(vec![0]));
    // Guard RTRs: state pre-operational (0x7F) with the toggle bit alternating.
    let mut answers = Vec::new();
    for _ in 0..4 {
        peer.rtr(0x717, 1);
        answers.push(
            peer.expect(0x717, Duration::from_secs(1))
                .expect("guard answer")[0],
        );
    }
    assert_eq!(answers, [0x7F, 0xFF, 0x7F, 0xFF]);
    // SDO, NMT start and a TPDO on the same socket.
    peer.send(0x617, &[0x40, 0x18, 0x10, 0x01, 0, 0, 0, 0]);
    let r = peer.expect(0x597, Duration::from_secs(2)).unwrap();
    assert_eq!(&r[..4], &[0x43, 0x18, 0x10, 0x01]);
    peer.send(0x000, &[0x01, 23]);
    let pdo = peer.expect(0x197, Duration::from_secs(2)).expect("TPDO1");
    assert!(pdo.len() >= 4, "{pdo:02X?}");
    h.stop().unwrap();
}
