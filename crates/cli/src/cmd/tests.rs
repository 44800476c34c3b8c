//! Tests of the master tools against a real `canpos_stack::Node` (expedited SDO, NMT, scan,
//! monitor configuration reads, LSS fastscan and configuration) and against small scripted
//! slaves for what must also be exercised independently of the device core (segmented SDO with
//! toggle errors, LSS with fastscan), so that a misreading shared by the core and the master
//! does not hide itself.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use anyhow::Result;
use canpos_host::mem::{MemBus, MemPort};
use canpos_host::transport;
use canpos_host::transport::Transport;
use canpos_stack::storage::RamStorage;
use canpos_stack::Frame;

use crate::client::monitor::LoadMeter;
use crate::client::*;
use crate::client::{decode, sdo};
use crate::cmd::eds::*;
use crate::cmd::lss::*;
use crate::cmd::monitor::*;
use crate::cmd::nmt::*;
use crate::cmd::record::*;
use crate::cmd::replay::Timeline;
use crate::cmd::replay::*;
use crate::cmd::scan::*;
use crate::cmd::sdo::*;
use crate::common::*;

/// A unique in-process bus name per test (the `mem://` registry is process-wide).
fn bus_name(tag: &str) -> String {
    static N: AtomicU64 = AtomicU64::new(0);
    format!("master-test-{tag}-{}", N.fetch_add(1, Ordering::Relaxed))
}

/// A background thread that runs until dropped.
struct Runner {
    stop: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
}

impl Drop for Runner {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

fn spawn(
    mut port: MemPort,
    mut on_frame: impl FnMut(&mut MemPort, Option<Frame>) + Send + 'static,
) -> Runner {
    let stop = Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    let handle = thread::spawn(move || {
        while !s.load(Ordering::Relaxed) {
            let f = port
                .recv_timeout(Some(Duration::from_millis(2)))
                .ok()
                .flatten()
                .map(|rx| rx.frame);
            on_frame(&mut port, f);
        }
    });
    Runner {
        stop,
        handle: Some(handle),
    }
}

/// A TH node with `node_id` on `bus`, driven with the real clock.
fn run_node(bus: &MemBus, node_id: u8) -> Runner {
    run_node_on(bus.attach(), node_id)
}

/// A TH node with `node_id` on `port`, driven with the real clock.
fn run_node_on(port: MemPort, node_id: u8) -> Runner {
    let model = canpos_models::by_name("th").expect("th model");
    let mut cfg = model.default_config;
    cfg.node_id = node_id;
    let mut node = canpos_models::SensorNode::new(model, cfg, RamStorage::default());
    let t0 = Instant::now();
    let now = move || canpos_stack::Instant::from_micros(t0.elapsed().as_micros() as u64);
    node.power_on(now());
    spawn(port, move |port, f| {
        if let Some(f) = f {
            node.handle_frame(&f, now());
        }
        node.handle_timeout(now());
        while let Some(out) = node.poll_transmit() {
            let _ = port.send(&out);
        }
    })
}

// ------------------------------------------------------------------- SDO against a real node

#[test]
fn expedited_read_write_and_aborts_against_node() {
    let bus = MemBus::new();
    let _n = run_node(&bus, 5);
    let mut port = bus.attach();
    let mut c = SdoClient::new(&mut port, 5, Duration::from_millis(500));
    assert_eq!(c.read_u32(0x1018, 1).unwrap(), 0x40);
    assert_eq!(c.read_u32(0x1018, 0).unwrap(), 4);
    c.download(0x1017, 0, &250u16.to_le_bytes()).unwrap();
    assert_eq!(c.upload(0x1017, 0).unwrap(), 250u16.to_le_bytes());
    match c.upload(0x1234, 0) {
        Err(SdoError::Abort(0x0602_0000)) => {}
        r => panic!("expected abort 0x06020000, got {r:?}"),
    }
    match c.download(0x1018, 1, &[1, 2, 3, 4]) {
        Err(SdoError::Abort(0x0601_0002)) => {}
        r => panic!("expected read-only abort, got {r:?}"),
    }
    let e = c.upload(0x1234, 0).unwrap_err();
    assert_eq!(
        e.to_string(),
        "SDO abort 0x06020000: Object does not exist in the object dictionary"
    );
}

#[test]
fn sdo_timeout_when_node_absent() {
    let bus = MemBus::new();
    let mut port = bus.attach();
    let t = Instant::now();
    let mut c = SdoClient::new(&mut port, 9, Duration::from_millis(50));
    assert!(matches!(c.upload(0x1000, 0), Err(SdoError::Timeout)));
    assert!(t.elapsed() >= Duration::from_millis(50));
}

#[test]
fn sdo_command_exit_codes() {
    let name = bus_name("sdo");
    let _n = run_node(&MemBus::named(&name), 7);
    let url = format!("mem://{name}");
    let read = |node: &str, index: &str, sub: &str, ty| {
        sdo(SdoArgs {
            cmd: SdoCmd::Read {
                node: node.into(),
                index: index.into(),
                sub: sub.into(),
                ty,
            },
            bus: BusArg { bus: url.clone() },
            timeout: 300,
        })
        .unwrap()
    };
    assert_eq!(read("7", "0x1018", "1", Some(ValueType::U32)), EXIT_OK);
    assert_eq!(read("7", "1018", "0x01", None), EXIT_OK);
    assert_eq!(read("7", "1234", "0", None), EXIT_REFUSED);
    assert_eq!(read("8", "1000", "0", None), EXIT_TIMEOUT);
    // A u8 read of a u32 object: the length does not fit the type.
    assert_eq!(read("7", "1018", "1", Some(ValueType::U8)), EXIT_REFUSED);
    let write = |value: &str, ty| {
        sdo(SdoArgs {
            cmd: SdoCmd::Write {
                node: "7".into(),
                index: "1017".into(),
                sub: "0".into(),
                value: value.into(),
                ty,
            },
            bus: BusArg { bus: url.clone() },
            timeout: 300,
        })
    };
    assert_eq!(write("100", ValueType::U16).unwrap(), EXIT_OK);
    assert!(
        write("70000", ValueType::U16).is_err(),
        "out of range is a usage error"
    );
    assert!(sdo(SdoArgs {
        cmd: SdoCmd::Read {
            node: "0".into(),
            index: "1000".into(),
            sub: "0".into(),
            ty: None
        },
        bus: BusArg { bus: url.clone() },
        timeout: 10,
    })
    .is_err());
}

#[test]
fn nmt_command_frame() {
    let name = bus_name("nmt");
    let mut port = MemBus::named(&name).attach();
    let url = format!("mem://{name}");
    for (cmd, node, bytes) in [
        (NmtCommand::Start, "0", [0x01, 0]),
        (NmtCommand::Stop, "5", [0x02, 5]),
        (NmtCommand::Preop, "127", [0x80, 127]),
        (NmtCommand::Reset, "0x10", [0x81, 16]),
        (NmtCommand::ResetComm, "1", [0x82, 1]),
    ] {
        let r = nmt(NmtArgs {
            command: cmd,
            node: node.into(),
            bus: BusArg { bus: url.clone() },
        });
        assert_eq!(r.unwrap(), EXIT_OK);
        let f = port
            .recv_timeout(Some(Duration::from_secs(1)))
            .unwrap()
            .unwrap()
            .frame;
        assert_eq!((f.id(), f.data()), (0, &bytes[..]));
    }
    assert!(nmt(NmtArgs {
        command: NmtCommand::Start,
        node: "128".into(),
        bus: BusArg { bus: url },
    })
    .is_err());
}

#[test]
fn nmt_start_reaches_the_node() {
    let bus = MemBus::new();
    let _n = run_node(&bus, 3);
    let mut port = bus.attach();
    // Heartbeat on, then start: the heartbeat must report operational.
    SdoClient::new(&mut port, 3, Duration::from_millis(500))
        .download(0x1017, 0, &20u16.to_le_bytes())
        .unwrap();
    port.send(&Frame::new(0, &[0x01, 3]).unwrap()).unwrap();
    let deadline = Instant::now() + Duration::from_secs(2);
    loop {
        let rx = port
            .recv_deadline(deadline)
            .unwrap()
            .expect("heartbeat operational");
        if rx.frame.id() == 0x703 && rx.frame.data() == [0x05] {
            break;
        }
    }
}

#[test]
fn scan_finds_nodes_and_identity() {
    let bus = MemBus::new();
    let _a = run_node(&bus, 5);
    let _b = run_node(&bus, 127);
    let mut port = bus.attach();
    let found = scan_bus(&mut port, Duration::from_millis(200)).unwrap();
    let ids: Vec<u8> = found.iter().map(|n| n.node).collect();
    assert_eq!(ids, vec![5, 127]);
    for n in &found {
        assert!(n.device_type.is_some());
        assert_eq!(n.identity[0], Some(0x40));
        assert_eq!(n.identity[1], Some(0x4333_3034));
        assert!(n.name.as_deref().is_some_and(|s| !s.is_empty()), "{n:?}");
    }
}

/// A node that sends PDOs but no heartbeat (the TH's default 0x1017 = 0) after its boot-up is
/// operational "(inferred)"; one still pre-operational keeps its boot-up (issue 38 item 5).
#[test]
fn scan_infers_operational_from_pdos_without_a_heartbeat() {
    let bus = MemBus::new();
    // Attached first: a boot-up sent before the scan's port joined would not be heard.
    let mut port = bus.attach();
    let _a = run_node(&bus, 5);
    let _b = run_node(&bus, 6);
    port.send(&Frame::new(0, &[0x01, 5]).unwrap()).unwrap();
    let found = scan_bus(&mut port, Duration::from_millis(200)).unwrap();
    let states: Vec<(u8, Option<u8>, bool)> = found
        .iter()
        .map(|n| (n.node, n.state, n.state_inferred))
        .collect();
    assert_eq!(states, [(5, Some(0x05), true), (6, Some(0), false)]);
}

#[test]
fn monitor_reads_tpdo_configuration() {
    let bus = MemBus::new();
    let _n = run_node(&bus, 4);
    let mut port = bus.attach();
    let mut c = SdoClient::new(&mut port, 4, Duration::from_millis(300)).keep_other_frames();
    let info = Monitor::query(&mut c).unwrap();
    assert!(!info.tpdos.is_empty());
    let (num, cob, map) = &info.tpdos[0];
    assert_eq!((*num, *cob), (1, 0x184));
    let count = c.read_u32(0x1A00, 0).unwrap() as usize;
    assert_eq!(map.len(), count);
    let mut mon = Monitor::new();
    mon.learn(4, Some(info));
    let f = Frame::new(0x184, &[0; 8]).unwrap();
    assert!(
        mon.describe(&f).starts_with("node 4 TPDO1 "),
        "{}",
        mon.describe(&f)
    );
    assert!(mon.concerns(&f, 4) && !mon.concerns(&f, 5));
}

// -------------------------------------------------------------- scripted segmented SDO server

/// The fake SDO server's objects.
type Objects = Arc<std::sync::Mutex<HashMap<(u16, u8), Vec<u8>>>>;

/// A minimal segmented-capable SDO server on node `node`, with a toggle fault switch.
fn run_fake_sdo_server(bus: &MemBus, node: u8, bad_toggle: bool) -> (Runner, Objects) {
    let objects: Objects = Default::default();
    let obj = objects.clone();
    // Transfer in progress: (index, sub, upload data left / download buffer, toggle, upload?)
    let mut xfer: Option<(u16, u8, Vec<u8>, u8, bool)> = None;
    let runner = spawn(bus.attach(), move |port, f| {
        let Some(f) = f else { return };
        if f.id() != 0x600 + node as u32 || f.data().len() != 8 {
            return;
        }
        let d = f.data();
        let idx = u16::from_le_bytes([d[1], d[2]]);
        let mut r = [0u8; 8];
        match d[0] >> 5 {
            2 => {
                let v = obj.lock().unwrap().get(&(idx, d[3])).cloned();
                r[1..4].copy_from_slice(&d[1..4]);
                match v {
                    None => {
                        r[0] = 0x80;
                        r[4..8].copy_from_slice(&0x0602_0000u32.to_le_bytes());
                    }
                    Some(v) if v.len() <= 4 => {
                        r[0] = 0x43 | ((4 - v.len() as u8) << 2);
                        r[4..4 + v.len()].copy_from_slice(&v);
                    }
                    Some(v) => {
                        r[0] = 0x41;
                        r[4..8].copy_from_slice(&(v.len() as u32).to_le_bytes());
                        xfer = Some((idx, d[3], v, 0, true));
                    }
                }
            }
            3 => {
                let Some((_, _, left, t, true)) = xfer.as_mut() else {
                    return;
                };
                let n = left.len().min(7);
                let chunk: Vec<u8> = left.drain(..n).collect();
                let toggle = if bad_toggle { 0 } else { *t };
                r[0] = toggle << 4 | ((7 - n as u8) << 1) | left.is_empty() as u8;
                r[1..1 + n].copy_from_slice(&chunk);
                *t ^= 1;
                if left.is_empty() {
                    xfer = None;
                }
            }
            1 => {
                r[0] = 0x60;
                r[1..4].copy_from_slice(&d[1..4]);
                if d[0] & 2 != 0 {
                    let n = 4 - ((d[0] >> 2) & 3) as usize;
                    obj.lock()
                        .unwrap()
                        .insert((idx, d[3]), d[4..4 + n].to_vec());
                } else {
                    xfer = Some((idx, d[3], Vec::new(), 0, false));
                }
            }
            0 => {
                let Some((i, s, buf, t, false)) = xfer.as_mut() else {
                    return;
                };
                if (d[0] >> 4) & 1 != *t {
                    r = [0x80, *i as u8, (*i >> 8) as u8, *s, 0, 0, 0x03, 0x05];
                    xfer = None;
                } else {
                    let n = 7 - ((d[0] >> 1) & 7) as usize;
                    buf.extend_from_slice(&d[1..1 + n]);
                    r[0] = 0x20 | (*t << 4);
                    *t ^= 1;
                    if d[0] & 1 != 0 {
                        let (i, s, buf) = (*i, *s, std::mem::take(buf));
                        obj.lock().unwrap().insert((i, s), buf);
                        xfer = None;
                    }
                }
            }
            4 => {
                xfer = None;
                return;
            }
            _ => return,
        }
        let _ = port.send(&Frame::std8(0x580 + node as u16, r));
    });
    (runner, objects)
}

#[test]
fn segmented_upload_and_download() {
    let bus = MemBus::new();
    let (_s, objects) = run_fake_sdo_server(&bus, 10, false);
    objects
        .lock()
        .unwrap()
        .insert((0x1008, 0), b"Temposonics TH CANbus".to_vec());
    let mut port = bus.attach();
    let mut c = SdoClient::new(&mut port, 10, Duration::from_millis(300));
    assert_eq!(c.upload(0x1008, 0).unwrap(), b"Temposonics TH CANbus");
    for len in [0usize, 5, 7, 8, 14, 15, 100] {
        let v: Vec<u8> = (0..len as u8).collect();
        c.download(0x2000, 1, &v).unwrap();
        assert_eq!(objects.lock().unwrap()[&(0x2000, 1)], v, "len {len}");
        if len > 4 {
            assert_eq!(c.upload(0x2000, 1).unwrap(), v, "len {len}");
        }
    }
}

#[test]
fn segmented_upload_detects_bad_toggle() {
    let bus = MemBus::new();
    let (_s, objects) = run_fake_sdo_server(&bus, 11, true);
    objects.lock().unwrap().insert((0x1008, 0), vec![b'x'; 20]);
    let mut port = bus.attach();
    let mut c = SdoClient::new(&mut port, 11, Duration::from_millis(300));
    match c.upload(0x1008, 0) {
        Err(SdoError::Protocol(m)) => assert!(m.contains("toggle"), "{m}"),
        r => panic!("expected a toggle error, got {r:?}"),
    }
}

// -------------------------------------------------------------------- scripted LSS slaves

#[derive(Clone, Debug)]
struct FakeLss {
    addr: [u32; 4],
    node_id: u8,
    config: bool,
    selective: u8,
    fs_sub: u8,
    bit_index: Option<u8>,
    stored: bool,
}

impl FakeLss {
    fn new(addr: [u32; 4], node_id: u8) -> Self {
        FakeLss {
            addr,
            node_id,
            config: false,
            selective: 0,
            fs_sub: 0,
            bit_index: None,
            stored: false,
        }
    }

    /// The slave's answer to one master request (an 8-byte frame on 0x7E5), if it gives one.
    fn answer(&mut self, d: &[u8]) -> Option<[u8; 8]> {
        if d.len() != 8 {
            return None;
        }
        let s = self;
        let u = u32::from_le_bytes([d[1], d[2], d[3], d[4]]);
        let answer = |a: [u8; 8]| Some(a);
        match d[0] {
            0x04 => {
                s.config = d[1] == 1;
                None
            }
            0x40..=0x43 => {
                let k = d[0] - 0x40;
                if s.selective == k && s.addr[k as usize] == u {
                    s.selective = k + 1;
                } else {
                    s.selective = 0;
                }
                if s.selective == 4 {
                    s.selective = 0;
                    s.config = true;
                    answer([0x44, 0, 0, 0, 0, 0, 0, 0])
                } else {
                    None
                }
            }
            0x11 if s.config => {
                let ok = (1..=127).contains(&d[1]) || d[1] == 0xFF;
                if ok {
                    s.node_id = d[1];
                }
                answer([0x11, !ok as u8, 0, 0, 0, 0, 0, 0])
            }
            0x13 if s.config => {
                let ok = d[1] == 0 && matches!(d[2], 0..=4 | 6 | 7);
                if ok {
                    s.bit_index = Some(d[2]);
                }
                answer([0x13, !ok as u8, 0, 0, 0, 0, 0, 0])
            }
            0x17 if s.config => {
                s.stored = true;
                answer([0x17, 0, 0, 0, 0, 0, 0, 0])
            }
            0x5A..=0x5D if s.config => {
                let mut a = [d[0], 0, 0, 0, 0, 0, 0, 0];
                a[1..5].copy_from_slice(&s.addr[(d[0] - 0x5A) as usize].to_le_bytes());
                answer(a)
            }
            0x5E if s.config => answer([0x5E, s.node_id, 0, 0, 0, 0, 0, 0]),
            0x4C if s.node_id == 0xFF => answer([0x50, 0, 0, 0, 0, 0, 0, 0]),
            0x51 if !s.config && s.node_id == 0xFF => {
                let (bit, sub, next) = (d[5], d[6], d[7]);
                if bit == 0x80 {
                    s.fs_sub = 0;
                    answer([0x4F, 0, 0, 0, 0, 0, 0, 0])
                } else if bit <= 31 && sub == s.fs_sub && sub < 4 {
                    let mask = u32::MAX << bit;
                    if (u ^ s.addr[sub as usize]) & mask == 0 {
                        if bit == 0 {
                            s.fs_sub = next;
                            if next < sub {
                                s.config = true;
                            }
                        }
                        answer([0x4F, 0, 0, 0, 0, 0, 0, 0])
                    } else {
                        None
                    }
                } else {
                    None
                }
            }
            _ => None,
        }
    }
}

/// A scripted LSS slave on its own thread, answering over `bus`.
fn run_fake_lss(
    bus: &MemBus,
    addr: [u32; 4],
    node_id: u8,
) -> (Runner, Arc<std::sync::Mutex<FakeLss>>) {
    let st = Arc::new(std::sync::Mutex::new(FakeLss::new(addr, node_id)));
    let s2 = st.clone();
    let r = spawn(bus.attach(), move |port, f| {
        let Some(f) = f else { return };
        if f.id() != 0x7E5 {
            return;
        }
        let out = s2.lock().unwrap().answer(f.data());
        if let Some(a) = out {
            let _ = port.send(&Frame::std8(0x7E4, a));
        }
    });
    (r, st)
}

/// Slaves that answer inside the master's `send`, so that an algorithm of many short steps
/// (fastscan) is tested without any wall-clock race: every answer is queued before the master
/// starts waiting, and a wait with nothing queued returns at once.
struct SyncBus<T> {
    units: Vec<T>,
    tx: crossbeam_channel::Sender<canpos_host::transport::RxFrame>,
    rx: crossbeam_channel::Receiver<canpos_host::transport::RxFrame>,
}

/// One unit on a [`SyncBus`]: what it answers to a frame.
trait Answers {
    fn answer_frame(&mut self, frame: &Frame, out: &mut Vec<Frame>);
}

impl<T> SyncBus<T> {
    fn new(units: Vec<T>) -> Self {
        let (tx, rx) = crossbeam_channel::unbounded();
        SyncBus { units, tx, rx }
    }
}

impl<T: Answers + Send> Transport for SyncBus<T> {
    fn send(&mut self, frame: &Frame) -> std::io::Result<()> {
        let mut out = Vec::new();
        for u in &mut self.units {
            u.answer_frame(frame, &mut out);
        }
        for f in out {
            let _ = self.tx.send(canpos_host::transport::RxFrame::now(f));
        }
        Ok(())
    }

    fn recv_deadline(
        &mut self,
        _deadline: Instant,
    ) -> std::io::Result<Option<canpos_host::transport::RxFrame>> {
        self.try_recv()
    }

    fn receiver(&self) -> &crossbeam_channel::Receiver<canpos_host::transport::RxFrame> {
        &self.rx
    }

    fn describe(&self) -> String {
        "slaves answering synchronously".into()
    }
}

/// A scripted LSS slave answers LSS requests (0x7E5) on 0x7E4.
impl Answers for FakeLss {
    fn answer_frame(&mut self, frame: &Frame, out: &mut Vec<Frame>) {
        if frame.id() == 0x7E5 && !frame.is_remote() && !frame.is_extended() {
            if let Some(a) = self.answer(frame.data()) {
                out.push(Frame::std8(0x7E4, a));
            }
        }
    }
}

#[test]
fn lss_switch_configure_store_inquire() {
    let bus = MemBus::new();
    let addr = [0x40, 0x4333_3034, 0x0001_0005, 17_143_876];
    let (_r, st) = run_fake_lss(&bus, addr, 127);
    let (_r2, other) = run_fake_lss(&bus, [0x40, 0x4333_3034, 0x0001_0005, 1], 126);
    let mut port = bus.attach();
    let mut m = LssMaster::new(&mut port, Duration::from_millis(200));
    // Nobody is in configuration state yet: no answer.
    assert!(matches!(m.inquire(Inquire::NodeId), Err(LssError::Timeout)));
    let a = LssAddress {
        vendor: addr[0],
        product: addr[1],
        revision: addr[2],
        serial: addr[3],
    };
    m.switch_selective(&a).unwrap();
    assert!(st.lock().unwrap().config && !other.lock().unwrap().config);
    assert_eq!(m.inquire(Inquire::Serial).unwrap(), 17_143_876);
    assert_eq!(m.inquire(Inquire::NodeId).unwrap(), 127);
    assert!(m.configure_node_id(5).unwrap().ok());
    assert_eq!(m.configure_node_id(0).unwrap().code, 1);
    assert!(m
        .configure_bit_timing(lss::bit_timing_index(500).unwrap())
        .unwrap()
        .ok());
    assert_eq!(st.lock().unwrap().bit_index, Some(2));
    assert_eq!(m.configure_bit_timing(8).unwrap().code, 1);
    assert!(m.store().unwrap().ok());
    assert_eq!(m.inquire(Inquire::NodeId).unwrap(), 5);
    m.switch_global(false).unwrap();
    m.activate_bit_timing(50).unwrap();
    assert!(matches!(m.inquire(Inquire::NodeId), Err(LssError::Timeout)));
    let s = st.lock().unwrap();
    assert!(s.stored && !s.config && s.node_id == 5);
}

#[test]
fn lss_commands_exit_codes() {
    let name = bus_name("lss");
    let (_r, _st) = run_fake_lss(&MemBus::named(&name), [1, 2, 3, 4], 127);
    let run = |cmd: LssCmd| {
        lss(LssArgs {
            cmd,
            bus: BusArg {
                bus: format!("mem://{name}"),
            },
            timeout: Some(200),
        })
    };
    assert_eq!(
        run(LssCmd::Inquire {
            what: InquireWhat::NodeId
        })
        .unwrap(),
        EXIT_TIMEOUT
    );
    assert_eq!(
        run(LssCmd::SwitchGlobal {
            mode: LssMode::Config
        })
        .unwrap(),
        EXIT_OK
    );
    assert_eq!(
        run(LssCmd::Inquire {
            what: InquireWhat::All
        })
        .unwrap(),
        EXIT_OK
    );
    assert_eq!(run(LssCmd::SetNodeId { id: "12".into() }).unwrap(), EXIT_OK);
    assert!(run(LssCmd::SetNodeId { id: "0".into() }).is_err());
    assert_eq!(run(LssCmd::SetBitrate { kbps: 250 }).unwrap(), EXIT_OK);
    assert_eq!(run(LssCmd::SetBitrate { kbps: 10 }).unwrap(), EXIT_REFUSED);
    assert!(run(LssCmd::SetBitrate { kbps: 300 }).is_err());
    assert_eq!(run(LssCmd::Store).unwrap(), EXIT_OK);
    assert_eq!(run(LssCmd::Activate { delay: 10 }).unwrap(), EXIT_OK);
}

#[test]
fn lss_fastscan_finds_unconfigured_node() {
    // The fastscan algorithm, not bus timing: the slaves answer synchronously.
    let a = [0x0000_0182, 0x8000_03E8, 0x0002_0003, 0x00AB_CDEF];
    let b = [0x0000_0182, 0x8000_03E8, 0x0002_0003, 0x00AB_CDF0];
    let mut bus = SyncBus::new(vec![
        FakeLss::new(a, 0xFF),
        FakeLss::new(b, 0xFF),
        FakeLss::new([9, 9, 9, 9], 3), // configured: stays out
    ]);
    let mut m = LssMaster::new(&mut bus, Duration::from_millis(20));
    assert!(m.identify_non_configured().unwrap());
    let found = m
        .fastscan(Duration::from_millis(10))
        .unwrap()
        .expect("a node");
    // Two candidates: fastscan settles on the lower address.
    assert_eq!(found.parts(), a);
    // The found node can now be configured.
    assert!(m.configure_node_id(20).unwrap().ok());
    let s = &bus.units;
    assert!(s[0].config && !s[1].config && !s[2].config);
    assert_eq!(s[0].node_id, 20);
}

/// A real TH node of the core on a [`SyncBus`]: the LSS master against the device it
/// commissions. Its time is virtual and moves 1 ms per frame sent.
struct ThUnit {
    node: canpos_models::SensorNode<RamStorage>,
    now: canpos_stack::Instant,
}

impl ThUnit {
    /// TH nodes with these serial numbers and node-ids (0xFF: unconfigured), powered on, their
    /// boot-ups dropped.
    fn bus(units: &[(u32, u8)]) -> SyncBus<ThUnit> {
        let model = canpos_models::by_name("th").expect("th model");
        SyncBus::new(
            units
                .iter()
                .map(|&(serial, node_id)| {
                    let mut cfg = model.default_config;
                    cfg.serial = serial;
                    cfg.node_id = node_id;
                    let mut node =
                        canpos_models::SensorNode::new(model, cfg, RamStorage::default());
                    node.power_on(canpos_stack::Instant::ZERO);
                    while node.poll_transmit().is_some() {}
                    ThUnit {
                        node,
                        now: canpos_stack::Instant::ZERO,
                    }
                })
                .collect(),
        )
    }
}

impl Answers for ThUnit {
    fn answer_frame(&mut self, frame: &Frame, out: &mut Vec<Frame>) {
        self.now = canpos_stack::Instant::from_micros(self.now.micros() + 1000);
        self.node.handle_frame(frame, self.now);
        self.node.handle_timeout(self.now);
        while let Some(f) = self.node.poll_transmit() {
            out.push(f);
        }
    }
}

#[test]
fn lss_fastscan_and_configure_real_unconfigured_nodes() {
    let mut bus = ThUnit::bus(&[(0x00AB_CDEF, 0xFF), (0x00AB_CDF0, 0xFF), (9, 3)]);
    let [vendor, product, revision, _] = bus.units[0].node.device().lss_address();
    let mut m = LssMaster::new(&mut bus, Duration::from_millis(20));
    assert!(m.identify_non_configured().unwrap());
    let found = m
        .fastscan(Duration::from_millis(10))
        .unwrap()
        .expect("a node");
    // Two unconfigured candidates: fastscan settles on the lower serial number.
    assert_eq!(found.parts(), [vendor, product, revision, 0x00AB_CDEF]);
    assert_eq!(m.inquire(Inquire::Serial).unwrap(), 0x00AB_CDEF);
    assert!(m.configure_node_id(20).unwrap().ok());
    assert!(m
        .configure_bit_timing(lss::bit_timing_index(250).unwrap())
        .unwrap()
        .ok());
    assert!(m.store().unwrap().ok());
    m.switch_global(false).unwrap();
    // Only the node fastscan found took the new node-id and bit rate.
    let pending: Vec<_> = bus
        .units
        .iter()
        .map(|u| u.node.device().pending())
        .collect();
    assert_eq!(pending[0], (20, 250), "{pending:?}");
    assert_eq!(pending[1].0, 0xFF, "{pending:?}");
    assert_eq!(pending[2].0, 3, "{pending:?}");
    // Back in waiting, the other unconfigured node is still there to be found.
    let mut m = LssMaster::new(&mut bus, Duration::from_millis(20));
    let next = m.fastscan(Duration::from_millis(10)).unwrap();
    assert_eq!(next.map(|a| a.parts()[3]), Some(0x00AB_CDF0));
}

#[test]
fn lss_fastscan_nobody() {
    let bus = MemBus::new();
    let (_r, _s) = run_fake_lss(&bus, [1, 2, 3, 4], 5);
    let mut port = bus.attach();
    let mut m = LssMaster::new(&mut port, Duration::from_millis(20));
    assert_eq!(m.fastscan(Duration::from_millis(10)).unwrap(), None);
}

// ------------------------------------------------------------------------------- decoders

#[test]
fn decodes_emcy_heartbeat_nmt_sdo_lss() {
    let d = |id: u16, data: &[u8]| decode::describe(&Frame::new(id, data).unwrap()).unwrap();
    assert_eq!(
        d(0x085, &[0x00, 0x50, 0x81, 0, 0, 0, 0, 0]),
        "node 5 EMCY 0x5000 device hardware (transducer error) reg 0x81 (generic+manufacturer) data 00 00 00 00 00"
    );
    assert!(d(0x085, &[0x90, 0x90, 0, 0, 0, 0, 0, 0]).contains("work area state change"));
    assert_eq!(d(0x705, &[0]), "node 5 boot-up");
    assert_eq!(d(0x705, &[0x7F]), "node 5 heartbeat pre-operational");
    assert_eq!(
        d(0x705, &[0x85]),
        "node 5 guarding answer operational (toggle 1)"
    );
    assert_eq!(d(0x000, &[0x01, 0]), "NMT start all nodes");
    assert_eq!(d(0x080, &[]), "SYNC");
    assert_eq!(
        d(0x585, &[0x80, 0x00, 0x10, 0, 0, 0, 0x02, 0x06]),
        "node 5 SDO ← abort 1000:00 0x06020000 Object does not exist in the object dictionary"
    );
    assert_eq!(
        d(0x605, &[0x40, 0x18, 0x10, 1, 0, 0, 0, 0]),
        "node 5 SDO → upload 1018:01"
    );
    assert_eq!(
        d(0x7E5, &[0x11, 5, 0, 0, 0, 0, 0, 0]),
        "LSS → configure node-id 5"
    );
    assert_eq!(d(0x285, &[1, 2]), "node 5 TPDO2 01 02");
    assert_eq!(d(0x205, &[1]), "node 5 RPDO1 01");
    // Odd input never panics.
    for id in [
        0x000u16, 0x080, 0x085, 0x585, 0x605, 0x705, 0x7E4, 0x7E5, 0x185,
    ] {
        for len in 0..=8 {
            let _ = decode::describe(&Frame::new(id, &[0xFF; 8][..len]).unwrap());
        }
    }
}

#[test]
fn decodes_pdo_in_mm() {
    let info = decode::NodeInfo {
        position_step_nm: Some(5000),
        velocity_step: Some(50),
        tpdos: vec![],
    };
    let map = [0x6020_0120, 0x6030_0110, 0x6300_0108, 0x6400_0108];
    let mut data = Vec::new();
    data.extend_from_slice(&20_000i32.to_le_bytes()); // 100 mm
    data.extend_from_slice(&(-4i16).to_le_bytes()); // -2 mm/s
    data.push(0b0101);
    data.push(0b100);
    assert_eq!(
        decode::decode_pdo(&info, &map, &data),
        "pos1=100.000 mm vel1=-2.00 mm/s cams1=[1,3] area1=below-low"
    );
    assert!(decode::decode_pdo(&info, &map, &data[..3]).contains("PDO too short"));
    let none = decode::NodeInfo::default();
    assert_eq!(
        decode::decode_pdo(&none, &map[..1], &data[..4]),
        "pos1=20000 steps"
    );
}

#[test]
fn value_types_encode_and_decode() {
    assert_eq!(ValueType::U16.encode("0x1234").unwrap(), [0x34, 0x12]);
    assert_eq!(ValueType::I16.encode("-2").unwrap(), [0xFE, 0xFF]);
    assert_eq!(ValueType::I16.encode("0xFFFF").unwrap(), [0xFF, 0xFF]);
    assert!(ValueType::U8.encode("256").is_err());
    assert!(ValueType::I8.encode("-129").is_err());
    assert!(ValueType::U32.encode("x").is_err());
    assert_eq!(
        ValueType::Bytes.encode("de:ad be-EF").unwrap(),
        [0xDE, 0xAD, 0xBE, 0xEF]
    );
    assert!(ValueType::Bytes.encode("abc").is_err());
    assert_eq!(ValueType::Str.encode("save").unwrap(), b"save");
    assert_eq!(ValueType::I32.decode(&[0xFF; 4]).unwrap(), "-1");
    assert_eq!(ValueType::U16.decode(&[1, 0]).unwrap(), "1 (0x0001)");
    assert!(ValueType::U16.decode(&[1]).is_err());
    assert_eq!(sdo::format_auto(b"C304\0"), "\"C304\"");
    assert_eq!(
        sdo::format_auto(&[0x96, 0x01, 0x08, 0x00]),
        "0x00080196 (524694)"
    );
    assert_eq!(sdo::format_auto(b"C304"), "0x34303343 (875574083) \"C304\"");
    assert_eq!(parse_index("0x1018").unwrap(), 0x1018);
    assert_eq!(parse_index("6020").unwrap(), 0x6020);
    assert_eq!(parse_sub("0x10").unwrap(), 16);
    assert_eq!(parse_sub("10").unwrap(), 10);
    assert!(parse_sub("256").is_err());
}

// ------------------------------------------------------------------------ record and replay

/// Issue 11: `record` keeps the error frames the bus carries. Through a canpos hub (which the
/// client asks for `< errors on >`), every frame corrupted on the bus timeline becomes an error
/// frame in the candump log (`CAN_ERR_FLAG` | protocol violation), and nothing else is written.
#[test]
fn record_keeps_the_error_frames_of_a_hub() {
    let dir = tempdir();
    let file = dir.join("errors.log");
    let hub = canpos_host::socketcand::Hub::bind("127.0.0.1:0")
        .unwrap()
        .spawn()
        .unwrap();
    let mut port = hub.attach("can0");
    let url = format!("socketcand://{}/can0", hub.local_addr());
    let rec = spawn_record(&file, url, 2);
    // The recorder is connected once its file exists.
    let end = Instant::now() + Duration::from_secs(5);
    while !file.exists() {
        assert!(Instant::now() < end, "the recorder did not start");
        thread::sleep(Duration::from_millis(5));
    }
    port.disturb(canpos_host::transport::Disturbance::CorruptedFrames {
        per_million: 1_000_000,
    })
    .unwrap();
    port.send(&Frame::new(0x181, &[1, 2]).unwrap()).unwrap();
    assert_eq!(rec.join().unwrap().unwrap(), EXIT_OK);
    let text = std::fs::read_to_string(&file).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 2, "{text}");
    for l in lines {
        let frame = l.rsplit(' ').next().unwrap();
        let (id, _) = frame.split_once('#').unwrap();
        let id = u32::from_str_radix(id, 16).unwrap();
        assert_eq!(id & 0x2000_0000, 0x2000_0000, "an error frame: {l}");
        assert_ne!(id & 0x008, 0, "a protocol violation: {l}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn record_then_replay_keeps_frames_and_timing() {
    let dir = tempdir();
    let file = dir.join("rec.log");
    let rec_name = bus_name("rec");
    let bus = MemBus::named(&rec_name);
    let sender = bus.attach();
    let rec = spawn_record(&file, format!("mem://{rec_name}"), 3);
    // Wait until the recorder is attached.
    while bus.port_count() < 2 {
        thread::sleep(Duration::from_millis(1));
    }
    let frames = [
        Frame::new(0x181, &[1, 2, 3]).unwrap(),
        Frame::new(0x080, &[]).unwrap(),
        Frame::new(0x705, &[0x7F]).unwrap(),
    ];
    for (i, f) in frames.iter().enumerate() {
        if i > 0 {
            thread::sleep(Duration::from_millis(100));
        }
        sender.send_at(canpos_host::transport::RxFrame::now(*f));
    }
    assert_eq!(rec.join().unwrap().unwrap(), EXIT_OK);
    let text = std::fs::read_to_string(&file).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 3, "{text}");
    assert!(
        lines[0].ends_with(&format!(" {rec_name} 181#010203")),
        "{}",
        lines[0]
    );
    assert!(lines[1].ends_with(" 080#"));

    let rep_name = bus_name("rep");
    let mut listener = MemBus::named(&rep_name).attach();
    let t0 = Instant::now();
    let r = replay(ReplayArgs {
        file: file.clone(),
        bus: BusArg {
            bus: format!("mem://{rep_name}"),
        },
        format: None,
        speed: 2.0,
        repeat: false,
        on_malformed: OnMalformed::Stop,
        max_gap: None,
    });
    assert_eq!(r.unwrap(), EXIT_OK);
    // At speed 2 the 200 ms recording takes about 100 ms.
    let took = t0.elapsed();
    assert!(
        took >= Duration::from_millis(90) && took < Duration::from_millis(400),
        "{took:?}"
    );
    // The last frame may still be on the wire (the bus is paced): wait for each.
    for f in &frames {
        let got = listener
            .recv_timeout(Some(Duration::from_secs(1)))
            .unwrap()
            .expect("replayed frame")
            .frame;
        assert_eq!(&got, f);
    }
    std::fs::write(dir.join("bad.log"), "(1.0) can0 XYZ\n").unwrap();
    assert!(replay(ReplayArgs {
        file: dir.join("bad.log"),
        bus: BusArg {
            bus: format!("mem://{rep_name}"),
        },
        format: None,
        speed: 1.0,
        repeat: false,
        on_malformed: OnMalformed::Stop,
        max_gap: None,
    })
    .is_err());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn record_keeps_stamps_in_order() {
    let dir = tempdir();
    let file = dir.join("order.pcap");
    let name = bus_name("order");
    let bus = MemBus::named(&name);
    let sender = bus.attach();
    let rec = spawn_record(&file, format!("mem://{name}"), 3);
    while bus.port_count() < 2 {
        thread::sleep(Duration::from_millis(1));
    }
    let at = |ms: u64| std::time::UNIX_EPOCH + Duration::from_millis(1_700_000_000_000 + ms);
    for (i, ms) in [10u64, 5, 20].into_iter().enumerate() {
        sender.send_at(canpos_host::transport::RxFrame {
            frame: Frame::new(0x180 + i as u16, &[i as u8]).unwrap(),
            timestamp: at(ms),
        });
    }
    assert_eq!(rec.join().unwrap().unwrap(), EXIT_OK);
    let b = std::fs::read(&file).unwrap();
    // pcap records after the 24-byte header: 16-byte record header + 16-byte can_frame.
    let stamps: Vec<(u32, u32)> = b[24..]
        .chunks(32)
        .map(|r| {
            (
                u32::from_le_bytes(r[0..4].try_into().unwrap()),
                u32::from_le_bytes(r[4..8].try_into().unwrap()),
            )
        })
        .collect();
    // The second frame came stamped 5 ms, before the first's 10 ms: written with 10 ms.
    assert_eq!(
        stamps,
        vec![
            (1_700_000_000, 10_000_000),
            (1_700_000_000, 10_000_000),
            (1_700_000_000, 20_000_000)
        ]
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `canpos record FILE --bus URL --count N` on a thread (at most 5 s).
fn spawn_record(file: &std::path::Path, url: String, count: u64) -> JoinHandle<Result<i32>> {
    let file = file.to_path_buf();
    thread::spawn(move || {
        record(RecordArgs {
            file,
            bus: BusArg { bus: url },
            format: None,
            duration: Some(5.0),
            count: Some(count),
            interface: None,
        })
    })
}

fn tempdir() -> std::path::PathBuf {
    static N: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let dir = std::env::temp_dir().join(format!("canpos-files-{}-{n}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A log with an error frame, an FD frame, a malformed line and RTR lines: with
/// `--on-malformed skip` the classical frames play (the remote frame with a DLC too, on a
/// bus that carries it); with `stop` nothing is sent.
#[test]
fn replay_skips_what_the_bus_cannot_carry() {
    let dir = tempdir();
    let file = dir.join("mixed.log");
    std::fs::write(
        &file,
        "(1.000000) can0 701#00\n\
         (1.001000) can0 20000088#0000020000000000\n\
         (1.002000) can0 181##1DEADBEEF00112233AA\n\
         (1.003000) can0 not-a-frame\n\
         (1.004000) can0 701#R1\n\
         (1.005000) can0 181#R\n",
    )
    .unwrap();
    let name = bus_name("mixed");
    let mut listener = MemBus::named(&name).attach();
    let args = |on_malformed| ReplayArgs {
        file: file.clone(),
        bus: BusArg {
            bus: format!("mem://{name}"),
        },
        format: None,
        speed: 0.0,
        repeat: false,
        on_malformed,
        max_gap: None,
    };
    assert!(replay(args(OnMalformed::Stop)).is_err());
    assert!(listener.try_recv().unwrap().is_none());
    assert_eq!(replay(args(OnMalformed::Skip)).unwrap(), EXIT_OK);
    // The bus is paced: the frames arrive one frame time after another.
    let got: Vec<Frame> = std::iter::from_fn(|| {
        listener
            .recv_timeout(Some(Duration::from_millis(500)))
            .unwrap()
            .map(|r| r.frame)
    })
    .collect();
    // Replayed at full speed on a paced bus, the two remote frames may wait together while
    // 701#00 is on the wire (then the lower identifier wins the arbitration) or not: either
    // order is a real bus's.
    assert_eq!(got.len(), 3, "{got:?}");
    assert_eq!(got[0], Frame::new(0x701, &[0]).unwrap());
    for f in [
        Frame::remote(0x701, false, 1).unwrap(),
        Frame::remote(0x181, false, 0).unwrap(),
    ] {
        assert!(got[1..].contains(&f), "{f:?} in {got:?}");
    }
    // ASC: the same kinds of lines.
    let asc = dir.join("mixed.asc");
    std::fs::write(
        &asc,
        "date Tue Dec 1 08:01:02.000 pm 2026\nbase hex  timestamps absolute\n\
         Begin Triggerblock Tue Dec 1 08:01:02.000 pm 2026\n   0.000000 Start of measurement\n\
            0.001000 1  701             Rx   d 1 05\n\
            0.002000 1  ErrorFrame\n\
            0.003000 CANFD   1 Rx 123  1 0 8 8 11 22 33 44 55 66 77 88 0 0 0 0 0 0 0 0\n\
            0.004000 1  1ABCDEF0x       Rx   d 2 AA BB\n\
         End TriggerBlock\n",
    )
    .unwrap();
    let mut a = args(OnMalformed::Stop);
    a.file = asc.clone();
    assert_eq!(replay(a).unwrap(), EXIT_OK);
    let got: Vec<Frame> = std::iter::from_fn(|| {
        listener
            .recv_timeout(Some(Duration::from_millis(500)))
            .unwrap()
            .map(|r| r.frame)
    })
    .collect();
    assert_eq!(
        got,
        vec![
            Frame::new(0x701, &[5]).unwrap(),
            Frame::with_id(0x1ABC_DEF0, true, &[0xAA, 0xBB]).unwrap(),
        ]
    );
    // A malformed ASC line: stop sends nothing and names the line.
    let text = std::fs::read_to_string(&asc).unwrap();
    std::fs::write(&asc, text.replace(" d 2 AA BB", " d 2 AA")).unwrap();
    let mut a = args(OnMalformed::Stop);
    a.file = asc;
    let e = replay(a).unwrap_err().to_string();
    assert!(e.contains("1 malformed line(s), nothing sent"), "{e}");
    assert!(listener.try_recv().unwrap().is_none());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn eds_rejects_unknown_model() {
    assert!(eds(EdsArgs {
        model: Some("nope".into()),
        order_code: None,
        output: None
    })
    .is_err());
}

/// The order-code variant's EDS: the unit's defaults (issue 11's example) and its code.
#[test]
fn eds_of_an_order_code() {
    let dir = tempdir();
    let out = dir.join("ep.eds");
    assert_eq!(
        eds(EdsArgs {
            model: None,
            order_code: Some("EP00600MD341C304241Z02".into()),
            output: Some(out.clone()),
        })
        .unwrap(),
        EXIT_OK
    );
    let text = std::fs::read_to_string(&out).unwrap();
    let ini = canpos_host::ini::Ini::parse(&text).unwrap();
    let get = |sec: &str, key: &str| ini.get(sec, key).unwrap_or_default().to_string();
    assert_eq!(get("DeviceInfo", "OrderCode"), "EP00600MD341C304241Z02");
    assert_eq!(get("1000", "DefaultValue"), "0x000A0196");
    let num = |v: String| match v.strip_prefix("0x") {
        Some(h) => i64::from_str_radix(h, 16).unwrap(),
        None => v.parse().unwrap(),
    };
    assert_eq!(num(get("650Asub3", "DefaultValue")), 60000);
    for s in 1..=2 {
        assert_eq!(num(get(&format!("6402sub{s}"), "DefaultValue")), 60000);
    }
    assert_eq!(get("FileInfo", "FileName"), "ep.eds");
    // Created now: not a fixed date.
    let (date, _) = crate::capture::eds_date_time(std::time::SystemTime::now());
    assert_eq!(get("FileInfo", "CreationDate"), date);
    assert!(eds(EdsArgs {
        model: None,
        order_code: Some("EP0BAD".into()),
        output: Some(out.clone()),
    })
    .is_err());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn command_line_definitions_are_consistent() {
    use clap::{CommandFactory, Parser, Subcommand};
    #[derive(Parser)]
    struct Cli {
        #[arg(short, long, global = true, action = clap::ArgAction::Count)]
        verbose: u8,
        #[command(subcommand)]
        cmd: Cmd,
    }
    #[derive(Subcommand)]
    enum Cmd {
        Nmt(NmtArgs),
        Sdo(SdoArgs),
        Lss(LssArgs),
        Scan(ScanArgs),
        Monitor(MonitorArgs),
        Eds(EdsArgs),
        Record(RecordArgs),
        Replay(ReplayArgs),
        Ctl(crate::cmd::ctl::CtlArgs),
    }
    Cli::command().debug_assert();
    let p = |args: &[&str]| Cli::try_parse_from(args).map(|c| c.cmd);
    match p(&[
        "canpos", "sdo", "write", "5", "6010", "1", "-5", "--type", "i32", "--bus", "mem://x",
    ]) {
        Ok(Cmd::Sdo(a)) => {
            assert_eq!(a.bus.bus, "mem://x");
            assert!(
                matches!(a.cmd, SdoCmd::Write { ref value, ty: ValueType::I32, .. } if value == "-5")
            );
        }
        _ => panic!("sdo write did not parse"),
    }
    assert!(matches!(
        p(&["canpos", "nmt", "reset-comm", "--node", "5"]),
        Ok(Cmd::Nmt(_))
    ));
    assert!(matches!(p(&["canpos", "lss", "inquire"]), Ok(Cmd::Lss(_))));
    assert!(matches!(
        p(&["canpos", "lss", "--timeout", "5", "fastscan"]),
        Ok(Cmd::Lss(_))
    ));
    assert!(matches!(
        p(&["canpos", "replay", "f.log", "--speed", "2", "--loop"]),
        Ok(Cmd::Replay(_))
    ));
    assert!(
        p(&["canpos", "sdo", "write", "5", "6010", "1", "7"]).is_err(),
        "--type is required"
    );
    // A negative value of set-input in hex, as docs/EDS_DEVICE.md has it (clap took `-0x8000`
    // for an option).
    for v in ["-0x8000", "-5", "0xA5"] {
        match p(&[
            "canpos",
            "ctl",
            "--control",
            "127.0.0.1:1",
            "set-input",
            "0x6401",
            "7",
            v,
        ]) {
            Ok(Cmd::Ctl(crate::cmd::ctl::CtlArgs {
                action: crate::cmd::ctl::CtlAction::SetInput { value, .. },
                ..
            })) => assert_eq!(value, v),
            other => panic!(
                "set-input {v} did not parse: {:?}",
                other.err().map(|e| e.to_string())
            ),
        }
    }
}

#[test]
fn sdo_scan_and_lss_timeout_over_socketcand_hub() {
    let hub = canpos_host::socketcand::Hub::bind("127.0.0.1:0").unwrap();
    let _n = run_node_on(hub.attach("can0"), 42);
    let handle = hub.spawn().unwrap();
    let url = format!("socketcand://{}/can0", handle.local_addr());
    let mut bus = transport::open(&url).unwrap();
    let mut c = SdoClient::new(&mut *bus, 42, Duration::from_millis(500));
    assert_eq!(c.read_u32(0x1018, 1).unwrap(), 0x40);
    let found = scan_bus(&mut *bus, Duration::from_millis(300)).unwrap();
    assert_eq!(found.len(), 1);
    assert_eq!(found[0].node, 42);
    assert_eq!(found[0].identity[0], Some(0x40));
    let code = sdo(SdoArgs {
        cmd: SdoCmd::Read {
            node: "42".into(),
            index: "1008".into(),
            sub: "0".into(),
            ty: Some(ValueType::Str),
        },
        bus: BusArg { bus: url },
        timeout: 500,
    })
    .unwrap();
    // The device name needs a segmented upload when longer than 4 characters.
    assert!(code == EXIT_OK || code == EXIT_REFUSED);
    drop(handle);
}

#[test]
fn load_meter_counts_bits_over_the_last_second() {
    // ID 0x000, DLC 0: 53 bits (bus::bits). 1000 of them at 1000 kbit/s within one second:
    // 53,000 bits = 53 ms of 1 s = 5.3 %.
    let mut m = LoadMeter::new(1000);
    let t0 = std::time::SystemTime::UNIX_EPOCH + Duration::from_secs(100);
    let f = Frame::new(0, &[]).unwrap();
    let mut last = (0.0, 0);
    for i in 0..1000u64 {
        last = m.add(t0 + Duration::from_micros(i * 900), &f);
    }
    assert_eq!(last.1, 1000);
    assert!((last.0 - 5.3).abs() < 1e-9, "{last:?}");
    // A second later the old frames have left the window.
    let later = m.add(t0 + Duration::from_secs(3), &f);
    assert_eq!(later.1, 1);
}

/// `--max-gap` takes off only what a pause has beyond it, the pause before the first frame
/// included; a stamp earlier than the latest keeps its place; without it the times are the
/// log's divided by the speed.
#[test]
fn max_gap_shortens_only_the_pauses_longer_than_it() {
    let run = |speed, gap, ts: &[f64]| {
        let mut t = Timeline::new(speed, gap);
        ts.iter().map(|&x| t.offset(x)).collect::<Vec<f64>>()
    };
    let log = [0.0, 1.0, 11.0, 12.0, 11.5, 20.0];
    assert_eq!(run(1.0, Some(2.0), &log), [0.0, 1.0, 3.0, 4.0, 3.5, 6.0]);
    assert_eq!(run(2.0, Some(2.0), &log), [0.0, 0.5, 2.5, 3.0, 2.75, 5.0]);
    assert_eq!(run(2.0, None, &log), [0.0, 0.5, 5.5, 6.0, 5.75, 10.0]);
    assert_eq!(run(0.0, Some(2.0), &log), [0.0; 6]);
    // An ASC log's first frame 100 s after the start of measurement.
    assert_eq!(run(1.0, Some(1.0), &[100.0, 100.5]), [1.0, 1.5]);
    assert_eq!(run(1.0, Some(0.0), &[5.0, 1e9]), [0.0, 0.0]);
}
