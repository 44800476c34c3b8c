use super::*;
use crate::can::BusStats;
use crate::file_storage::FileStorage;
use crate::mem::MemBus;
use canpos_sim::motion::{Profile, Profiles};
use canpos_sim::SensorSpec;

fn th_setup(dir: &std::path::Path, node_id: u8, serial: u32) -> SensorSetup {
    let model = canpos_models::by_name("th").unwrap();
    let mut cfg = model.default_config;
    cfg.node_id = node_id;
    cfg.serial = serial;
    SensorSetup {
        name: format!("th-{serial}"),
        model,
        cfg,
        spec: SensorSpec::th(f64::from(cfg.stroke_mm), 1).unwrap(),
        seed: 1,
        ideal: true,
        motion: Box::new(Profiles(vec![Profile::Static { pos_mm: 250.0 }])),
        storage: FileStorage::new(state_file(dir, "th", serial)),
    }
}

fn recv_id(port: &mut dyn Transport, id: u16, within: Duration) -> Option<Frame> {
    let end = std::time::Instant::now() + within;
    while let Ok(Some(rx)) = port.recv_deadline(end) {
        if rx.frame.std_id() == Some(id) {
            return Some(rx.frame);
        }
    }
    None
}

/// Drives one device by hand on a virtual clock: frames in, its poll through the timing
/// hold, released frames out.
fn step(d: &mut SimDevice, input: Option<Frame>, at_us: u64) -> Vec<Frame> {
    let now = Instant::from_micros(at_us);
    if let Some(f) = input {
        if d.listening(now) {
            d.receive(&f, now);
        }
    }
    let mut out = Vec::new();
    d.release(now, &mut out);
    while let Some(f) = d.poll(now) {
        if let Some(f) = d.hold(f, now) {
            out.push(f);
        }
    }
    d.power_on_bootup = false;
    out
}

fn sdo_read_1008() -> Frame {
    Frame::new(0x605, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).unwrap()
}

#[test]
fn sdo_delay_and_jitter_on_a_virtual_clock() {
    let dir = tempfile::tempdir().unwrap();
    let mut d = SimDevice::new(th_setup(dir.path(), 5, 1), Instant::from_micros(0));
    d.timing = DeviceTiming {
        sdo_delay: Duration::from_millis(5),
        sdo_jitter: Duration::from_millis(2),
        ..Default::default()
    };
    d.node.power_on(Instant::from_micros(0));
    d.power_on_bootup = true;
    let boot = step(&mut d, None, 0);
    assert!(boot.iter().any(|f| f.std_id() == Some(0x705)), "{boot:?}");
    let mut delays = Vec::new();
    let mut t = 1_000;
    for _ in 0..50 {
        let start = t;
        assert!(step(&mut d, Some(sdo_read_1008()), t)
            .iter()
            .all(|f| f.std_id() != Some(0x585)));
        // Step the virtual clock by 100 µs until the answer comes.
        let answered = loop {
            t += 100;
            if step(&mut d, None, t)
                .iter()
                .any(|f| f.std_id() == Some(0x585))
            {
                break t;
            }
            assert!(t - start < 10_000, "no answer within 10 ms");
        };
        delays.push(answered - start);
        t += 1_000;
    }
    // 5 ms fixed, up to 2 ms more (100 µs steps: the answer is seen within a step).
    assert!(
        delays.iter().all(|&us| (5_000..=7_100).contains(&us)),
        "{delays:?}"
    );
    assert!(
        delays.iter().any(|&us| us < 5_700) && delays.iter().any(|&us| us > 6_300),
        "the jitter spreads: {delays:?}"
    );
}

#[test]
fn reset_boot_delay_keeps_the_node_deaf_and_silent() {
    let dir = tempfile::tempdir().unwrap();
    let mut d = SimDevice::new(th_setup(dir.path(), 5, 2), Instant::from_micros(0));
    d.timing.reset_boot_delay = Duration::from_millis(300);
    d.node.power_on(Instant::from_micros(0));
    d.power_on_bootup = true;
    // The power-on boot-up is not delayed by the reset delay.
    assert!(step(&mut d, None, 0)
        .iter()
        .any(|f| f.std_id() == Some(0x705)));
    // NMT reset node.
    let out = step(&mut d, Some(Frame::new(0, &[0x81, 5]).unwrap()), 10_000);
    assert!(out.is_empty(), "{out:?}");
    // Rebooting: an SDO request is not taken, nothing is sent.
    assert!(step(&mut d, Some(sdo_read_1008()), 100_000).is_empty());
    assert!(step(&mut d, None, 309_999).is_empty());
    let out = step(&mut d, None, 310_000);
    assert_eq!(out, vec![Frame::new(0x705, &[0]).unwrap()]);
    // On the bus again: requests are answered.
    let out = step(&mut d, Some(sdo_read_1008()), 320_000);
    assert!(out.iter().any(|f| f.std_id() == Some(0x585)), "{out:?}");
}

/// Issue 16: what a node produces in an injected bus-off never reaches the bus, and is
/// counted in `state` rather than lost silently.
#[test]
fn frames_of_a_node_in_bus_off_are_counted_not_sent() {
    let dir = tempfile::tempdir().unwrap();
    let bus = MemBus::new();
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    rt.add(th_setup(dir.path(), 5, 4));
    let h = rt.spawn().unwrap();
    recv_id(&mut master, 0x705, Duration::from_secs(5)).expect("boot-up");
    master.send(&Frame::new(0, &[0x01, 5]).unwrap()).unwrap();
    recv_id(&mut master, 0x185, Duration::from_secs(5)).expect("TPDO1 when operational");
    let c = h.control();
    let fault = |on: bool| {
        crate::control::parse_request(&format!(r#"{{"cmd":"fault","name":"bus-off","on":{on}}}"#))
            .unwrap()
    };
    assert_eq!(c.request(fault(true))["ok"], true);
    let end = std::time::Instant::now() + Duration::from_secs(5);
    let lost = loop {
        let st = c.request(Request::State { sensor: None });
        let lost = st["frames_lost_bus_off"].as_u64().unwrap();
        if lost >= 3 {
            break lost;
        }
        assert!(std::time::Instant::now() < end, "nothing counted: {st}");
        std::thread::sleep(Duration::from_millis(5));
    };
    // Whatever reached the master meanwhile was sent before the fault took effect; from
    // here on nothing comes while the node is off the bus.
    while master.try_recv().unwrap().is_some() {}
    assert!(recv_id(&mut master, 0x185, Duration::from_millis(50)).is_none());
    assert_eq!(c.request(fault(false))["ok"], true);
    recv_id(&mut master, 0x185, Duration::from_secs(5)).expect("TPDO1 after bus-off");
    let st = c.request(Request::State { sensor: None });
    assert!(st["frames_lost_bus_off"].as_u64().unwrap() >= lost, "{st}");
    h.stop().unwrap();
}

#[test]
fn boot_delay_stall_and_timing_requests_through_the_runtime() {
    let dir = tempfile::tempdir().unwrap();
    let bus = MemBus::new();
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    rt.add(th_setup(dir.path(), 5, 3));
    let bad = DeviceTiming {
        sdo_delay: Duration::from_secs(601),
        ..Default::default()
    };
    assert!(rt.set_timing(0, bad).unwrap_err().contains("sdo-delay"));
    rt.set_timing(
        0,
        DeviceTiming {
            boot_delay: Duration::from_millis(200),
            ..Default::default()
        },
    )
    .unwrap();
    let t0 = std::time::Instant::now();
    let h = rt.spawn().unwrap();
    recv_id(&mut master, 0x705, Duration::from_secs(5)).expect("boot-up");
    // A lower bound only: the machine may be late, never early.
    assert!(
        t0.elapsed() >= Duration::from_millis(200),
        "{:?}",
        t0.elapsed()
    );
    // Out of range: refused, nothing changes.
    let c = h.control();
    for req in [
        r#"{"cmd":"timing","sdo_delay_ms":-1}"#,
        r#"{"cmd":"timing","sdo_jitter_ms":1e9}"#,
        r#"{"cmd":"fault","name":"stall","on":true}"#,
        r#"{"cmd":"fault","name":"stall","on":true,"value":0}"#,
        r#"{"cmd":"fault","name":"stall","on":true,"value":1e6}"#,
    ] {
        let r = c.request(crate::control::parse_request(req).unwrap());
        assert_eq!(r["ok"], false, "{req}: {r}");
    }
    let st = c.request(Request::State { sensor: None });
    assert_eq!(st["device_timing"]["sdo_delay_ms"], 0.0, "{st}");
    assert_eq!(st["faults"], json!([]), "{st}");
    let r =
        c.request(crate::control::parse_request(r#"{"cmd":"timing","sdo_delay_ms":80}"#).unwrap());
    assert_eq!(r["timing"]["sdo_delay_ms"], 80.0, "{r}");
    assert_eq!(r["timing"]["boot_delay_ms"], 200.0, "{r}");
    let sent = std::time::Instant::now();
    master.send(&sdo_read_1008()).unwrap();
    recv_id(&mut master, 0x585, Duration::from_secs(5)).expect("SDO answer");
    assert!(
        sent.elapsed() >= Duration::from_millis(80),
        "{:?}",
        sent.elapsed()
    );
    // Stall for 0.3 s: a request in the stall is never answered, one after it is.
    let r = c.request(
        crate::control::parse_request(r#"{"cmd":"fault","name":"stall","on":true,"value":0.3}"#)
            .unwrap(),
    );
    assert_eq!(r["faults"], json!(["stall"]), "{r}");
    master.send(&sdo_read_1008()).unwrap();
    assert!(recv_id(&mut master, 0x585, Duration::from_millis(250)).is_none());
    let end = std::time::Instant::now() + Duration::from_secs(5);
    loop {
        let st = c.request(Request::State { sensor: None });
        if st["faults"] == json!([]) {
            break;
        }
        assert!(std::time::Instant::now() < end, "stall did not end: {st}");
        std::thread::sleep(Duration::from_millis(10));
    }
    master.send(&sdo_read_1008()).unwrap();
    recv_id(&mut master, 0x585, Duration::from_secs(5)).expect("answer after the stall");
    h.stop().unwrap();
}

#[test]
fn boots_answers_sdo_and_routes_between_local_nodes() {
    let dir = tempfile::tempdir().unwrap();
    let bus = MemBus::new();
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    rt.add(th_setup(dir.path(), 5, 1));
    rt.add(th_setup(dir.path(), 6, 2));
    let h = rt.spawn().unwrap();
    let boot = recv_id(&mut master, 0x705, Duration::from_secs(2)).expect("boot-up");
    assert_eq!(boot.data(), &[0]);
    master
        .send(&Frame::new(0x605, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).unwrap())
        .unwrap();
    let r = recv_id(&mut master, 0x585, Duration::from_secs(2)).expect("SDO answer");
    assert_eq!(r.data()[0], 0x43, "{r:?}");
    assert_eq!(&r.data()[4..8], &0x0008_0196u32.to_le_bytes());
    // Node 6's heartbeat consumer is not involved; check the state request instead. The
    // first measurement is published one cycle after power-on (its pulse must return).
    let end = std::time::Instant::now() + Duration::from_secs(2);
    let st = loop {
        let st = h.control().request(Request::State { sensor: Some(1) });
        if !st["timing"]["output_delay_us"].is_null() || std::time::Instant::now() > end {
            break st;
        }
        std::thread::sleep(Duration::from_millis(1));
    };
    assert_eq!(st["ok"], true, "{st}");
    assert_eq!(st["node_id"], 6);
    assert_eq!(st["nmt"], "pre-operational");
    let reported = st["reported_mm"][0].as_f64().unwrap();
    assert!((reported - 250.0).abs() < 0.01, "{st}");
    let bad = h.control().request(Request::State { sensor: Some(9) });
    assert_eq!(bad["ok"], false);
    h.stop().unwrap();
}

#[test]
fn event_timer_1ms_gives_about_1000_tpdos_per_second() {
    let dir = tempfile::tempdir().unwrap();
    let bus = MemBus::new().with_queue_len(8192);
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    rt.add(th_setup(dir.path(), 1, 3));
    let h = rt.spawn().unwrap();
    recv_id(&mut master, 0x701, Duration::from_secs(2)).expect("boot-up");
    // 0x1800/5 event timer = 1 ms, then NMT start.
    master
        .send(&Frame::new(0x601, &[0x2B, 0x00, 0x18, 0x05, 1, 0, 0, 0]).unwrap())
        .unwrap();
    let r = recv_id(&mut master, 0x581, Duration::from_secs(2)).expect("SDO answer");
    assert_eq!(r.data()[0], 0x60, "{r:?}");
    master
        .send(&Frame::new(0x000, &[0x01, 1]).unwrap())
        .unwrap();
    let start = std::time::Instant::now();
    let mut n = 0u32;
    while start.elapsed() < Duration::from_secs(1) {
        if let Ok(Some(rx)) = master.recv_timeout(Some(Duration::from_millis(50))) {
            if rx.frame.std_id() == Some(0x181) {
                n += 1;
            }
        }
    }
    let late = h.stop().unwrap();
    eprintln!("TPDOs in 1 s: {n}; {late}");
    assert!((700..=1300).contains(&n), "{n} TPDOs in 1 s");
}

/// A real [`MemPort`](crate::mem::MemPort) whose owner's thread blocks in its next
/// `try_recv` for as long as the test asks: the runtime thread stalls as under a busy host.
struct Stalling {
    port: crate::mem::MemPort,
    stall_ms: Arc<std::sync::atomic::AtomicU64>,
}

impl Transport for Stalling {
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        self.port.send(frame)
    }
    fn try_recv(&mut self) -> io::Result<Option<crate::can::RxFrame>> {
        let ms = self.stall_ms.swap(0, Ordering::SeqCst);
        if ms > 0 {
            std::thread::sleep(Duration::from_millis(ms));
        }
        self.port.try_recv()
    }
    fn receiver(&self) -> &Receiver<crate::can::RxFrame> {
        self.port.receiver()
    }
    fn bus_bitrate(&self) -> Option<u32> {
        self.port.bus_bitrate()
    }
    fn dropped(&self) -> u64 {
        Transport::dropped(&self.port)
    }
    fn bus_state(&self) -> BusState {
        self.port.bus_state()
    }
    fn bus_stats(&self) -> Option<BusStats> {
        self.port.bus_stats()
    }
    fn controller(&self) -> Option<Box<dyn Transport>> {
        self.port.controller()
    }
    fn join_clock(&mut self) -> Option<crate::clock::Horizon> {
        self.port.join_clock()
    }
    fn sync_bus(&self) {
        self.port.sync_bus()
    }
    fn set_rx_filter(&mut self, std_ids: &[u16]) -> io::Result<bool> {
        self.port.set_rx_filter(std_ids)
    }
    fn describe(&self) -> String {
        self.port.describe()
    }
}

/// Issue 36 item 1: the runtime thread blocked for 200 ms, 20 times, while its TH sends a
/// TPDO every 1 ms. Before, every stall skipped ~200 measurement cycles and TPDO periods
/// (a 200 ms hole on the bus) and could overflow queues (EMCY 0x8110). Now every TPDO
/// leaves at its own time on the bus timeline (start of frame exactly 1 ms apart), none is
/// skipped, no EMCY, and the lateness shows in `state`.
#[test]
fn a_stalled_runtime_keeps_every_tpdo_at_its_time() {
    let dir = tempfile::tempdir().unwrap();
    // The stall bound is not what this test is about (the next test is): far beyond the
    // 20 × 200 ms, so that a loaded machine on which the runtime catches up slower than
    // real time and piles up more than 2 s of lag does not turn it stale (its later
    // frames would then be stamped when the bus got them, not at their times).
    let clock = SimClock::wall_with_stall_bound(Duration::from_secs(600));
    let bus = MemBus::with_clock(crate::bus::DEFAULT_BITRATE_KBPS, clock).with_queue_len(8192);
    let mut master = bus.attach();
    let stall_ms = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let port = Stalling {
        port: bus.attach(),
        stall_ms: stall_ms.clone(),
    };
    let mut rt = Runtime::new(Box::new(port), None);
    rt.add(th_setup(dir.path(), 1, 3));
    let h = rt.spawn().unwrap();
    recv_id(&mut master, 0x701, Duration::from_secs(5)).expect("boot-up");
    // 0x1800/5 event timer = 1 ms, then NMT start.
    master
        .send(&Frame::new(0x601, &[0x2B, 0x00, 0x18, 0x05, 1, 0, 0, 0]).unwrap())
        .unwrap();
    let r = recv_id(&mut master, 0x581, Duration::from_secs(5)).expect("SDO answer");
    assert_eq!(r.data()[0], 0x60, "{r:?}");
    master.send(&Frame::new(0, &[0x01, 1]).unwrap()).unwrap();
    recv_id(&mut master, 0x181, Duration::from_secs(5)).expect("first TPDO");
    let mut tpdos = Vec::new();
    let mut emcys = Vec::new();
    let mut take = |master: &mut crate::mem::MemPort, until: std::time::Instant| {
        while let Ok(Some(rx)) = master.recv_deadline(until) {
            match rx.frame.std_id() {
                Some(0x181) => tpdos.push(rx),
                Some(0x081) => emcys.push(rx.frame),
                _ => {}
            }
        }
    };
    for _ in 0..20 {
        stall_ms.store(200, Ordering::SeqCst);
        take(
            &mut master,
            std::time::Instant::now() + Duration::from_millis(300),
        );
    }
    // The runtime answers once it has caught up with the wall clock (it processes what was
    // due first); then the bus delivers the rest (the queue holds 8192 frames meanwhile).
    let st = h.control().request(Request::State { sensor: None });
    assert_eq!(st["ok"], true, "{st}");
    take(
        &mut master,
        std::time::Instant::now() + Duration::from_millis(200),
    );
    h.stop().unwrap();
    eprintln!(
        "{} TPDOs, {} EMCYs; clock {}; skipped {}, tpdo_missed {}",
        tpdos.len(),
        emcys.len(),
        st["clock"],
        st["cycles_skipped"],
        st["tpdo_missed"]
    );

    assert!(
        !emcys.iter().any(|f| f.data()[..2] == [0x10, 0x81]),
        "EMCY 0x8110 after a host stall: {emcys:?}"
    );
    // 20 stalls of 200 ms and the time between them: at least 5 s of TPDOs.
    assert!(tpdos.len() > 5_000, "{} TPDOs", tpdos.len());
    // Start of frame = end of frame − the frame's bits (intermission excluded) at 1 µs a
    // bit: exactly the 1 ms schedule, the bus being idle at each due time.
    let bit_ns = 1_000u64;
    let t0 = tpdos[0].timestamp - Duration::from_millis(1);
    let start = |rx: &crate::can::RxFrame| {
        let end = rx.timestamp.duration_since(t0).unwrap().as_nanos() as u64;
        let bits = u64::from(crate::bus::bits::frame_length(&rx.frame).total)
            - u64::from(crate::bus::bits::INTERMISSION_BITS);
        end - bits * bit_ns
    };
    let bad: Vec<(usize, i64)> = tpdos
        .windows(2)
        .enumerate()
        .map(|(i, w)| (i, start(&w[1]) as i64 - start(&w[0]) as i64))
        .filter(|&(_, d)| d != 1_000_000)
        .collect();
    assert!(
        bad.is_empty(),
        "{} of {} TPDO periods are not 1 ms on the bus timeline: {:?}",
        bad.len(),
        tpdos.len() - 1,
        &bad[..bad.len().min(10)]
    );
    assert_eq!(st["cycles_skipped"], 0, "{st}");
    assert_eq!(st["tpdo_missed"], 0, "{st}");
    assert_eq!(st["bus"]["controller"]["lost_overflow"], 0, "{st}");
    assert_eq!(st["bus"]["rx_dropped"], 0, "{st}");
    // Each stall shows as lateness: events processed up to 200 ms after their time.
    let late = &st["clock"]["events_late_us"];
    assert!(late["max"].as_u64().unwrap() >= 150_000, "{st}");
    assert!(late["over_1ms"].as_u64().unwrap() >= 20, "{st}");
    assert!(
        st["clock"]["frames_late_us"]["count"].as_u64().unwrap() >= 2,
        "{st}"
    );
    assert_eq!(st["clock"]["driver"], "wall", "{st}");
}

/// Past the stall bound the runtime no longer holds the bus, and when it comes back it
/// skips to the wall clock instead of replaying what it missed (counted in
/// `cycles_skipped`): a suspended machine does not flood the bus with its past.
#[test]
fn a_stall_past_the_bound_skips_ahead_and_counts_it() {
    let dir = tempfile::tempdir().unwrap();
    let clock = SimClock::wall_with_stall_bound(Duration::from_millis(100));
    let bus = MemBus::with_clock(1000, clock);
    let mut master = bus.attach();
    let stall_ms = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let port = Stalling {
        port: bus.attach(),
        stall_ms: stall_ms.clone(),
    };
    let mut rt = Runtime::new(Box::new(port), None);
    rt.add(th_setup(dir.path(), 1, 7));
    let started = std::time::Instant::now();
    let h = rt.spawn().unwrap();
    recv_id(&mut master, 0x701, Duration::from_secs(5)).expect("boot-up");
    stall_ms.store(400, Ordering::SeqCst);
    // The bus goes on for the others while the runtime is stopped past the bound.
    std::thread::sleep(Duration::from_millis(250));
    let sent = std::time::Instant::now();
    let mut other = bus.attach();
    master.send(&Frame::new(0x123, &[1]).unwrap()).unwrap();
    recv_id(&mut other, 0x123, Duration::from_secs(5)).expect("the bus is not frozen");
    assert!(sent.elapsed() < Duration::from_secs(5));
    let st = state_when(&h.control(), |st| st["cycles_skipped"].as_u64() > Some(0));
    h.stop().unwrap();
    let skipped = st["cycles_skipped"].as_u64().unwrap();
    // About 400 ms of 1 ms cycles, less what it ran before the bound was passed; never
    // more than the wall time the runtime has existed (a loaded machine oversleeps the
    // 400 ms: no fixed upper bound).
    let lived_ms = u64::try_from(started.elapsed().as_millis()).unwrap();
    assert!(
        skipped >= 100 && skipped <= lived_ms,
        "{skipped} of {lived_ms} ms: {st}"
    );
}

/// One stepped run: a TH with noise and a moving magnet, set to a 1 ms event timer and
/// started by a master, stepped by 500 µs for 150 ms; every frame the master saw, with its
/// end of frame in ns.
fn stepped_run() -> Vec<(u32, Vec<u8>, u64)> {
    let dir = tempfile::tempdir().unwrap();
    let clock = SimClock::stepped();
    let bus = MemBus::with_clock(250, clock.clone());
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    let mut s = th_setup(dir.path(), 1, 3);
    s.ideal = false;
    s.seed = 42;
    s.motion = Box::new(Profiles(vec![Profile::Sine {
        center_mm: 400.0,
        amplitude_mm: 100.0,
        period_s: 0.05,
        phase_deg: 0.0,
    }]));
    rt.add(s);
    rt.set_timing(
        0,
        DeviceTiming {
            sdo_delay: Duration::from_micros(700),
            sdo_jitter: Duration::from_micros(300),
            ..Default::default()
        },
    )
    .unwrap();
    let mut log = Vec::new();
    for k in 0..=300u64 {
        match k {
            10 => master
                .send(&Frame::new(0x601, &[0x2B, 0x00, 0x18, 0x05, 1, 0, 0, 0]).unwrap())
                .unwrap(),
            20 => master.send(&Frame::new(0, &[0x01, 1]).unwrap()).unwrap(),
            _ => {}
        }
        rt.advance_to(Instant::from_micros(k * 500)).unwrap();
        // Everything due by the clock reached the master.
        master.sync_bus();
        while let Some(rx) = master.try_recv().unwrap() {
            let id = rx.frame.id();
            log.push((
                id,
                rx.frame.data().to_vec(),
                clock.nanos_of(rx.timestamp).unwrap(),
            ));
        }
    }
    assert_eq!(rt.reached(), Instant::from_micros(150_000));
    log
}

/// The stepped driver (FMI `doStep`, SIL Kit): the same inputs give the same frames at the
/// same times, however the host scheduled the bus's thread.
#[test]
fn stepped_runs_are_identical() {
    let a = stepped_run();
    let b = stepped_run();
    let tpdos = a.iter().filter(|f| f.0 == 0x181).count();
    // 1 ms event timer from ~10 ms on: well over 100 TPDOs, and the SDO answer.
    assert!(tpdos > 100, "{tpdos} TPDOs: {a:?}");
    assert!(a.iter().any(|f| f.0 == 0x581), "{a:?}");
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x, y);
    }
    // TPDO starts 1 ms apart on a bus at 250 kbit/s (4 µs a bit).
    let starts: Vec<u64> = a
        .iter()
        .filter(|f| f.0 == 0x181)
        .map(|(id, data, end)| {
            let f = Frame::new(*id as u16, data).unwrap();
            end - (u64::from(crate::bus::bits::frame_length(&f).total)
                - u64::from(crate::bus::bits::INTERMISSION_BITS))
                * 4_000
        })
        .collect();
    assert!(
        starts.windows(2).all(|w| w[1] - w[0] == 1_000_000),
        "{starts:?}"
    );
}

/// Polls the state of sensor 0 until `pred` holds (bounded; the runtime answers between
/// its measurement cycles).
fn state_when(c: &ControlHandle, pred: impl Fn(&Value) -> bool) -> Value {
    let end = std::time::Instant::now() + Duration::from_secs(5);
    loop {
        let st = c.request(Request::State { sensor: None });
        if pred(&st) || std::time::Instant::now() > end {
            return st;
        }
    }
}

#[test]
fn refused_requests_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let bus = MemBus::new();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    let mut s = th_setup(dir.path(), 9, 5);
    s.cfg.channels = 4;
    s.spec = SensorSpec::th(1000.0, 4).unwrap();
    s.motion = Box::new(Profiles(
        [100.0, 300.0, 500.0, 700.0]
            .map(|pos_mm| Profile::Static { pos_mm })
            .to_vec(),
    ));
    rt.add(s);
    let h = rt.spawn().unwrap();
    let c = h.control();
    // 17 magnets (more than the four channels, more than the runtime tracks).
    let spec = ["static:999"; 17].join(";");
    let a = c.request(Request::Motion { sensor: None, spec });
    assert_eq!(a["ok"], false, "{a}");
    assert!(a["error"].as_str().unwrap().contains("17 profiles"), "{a}");
    // Five on four channels: refused too.
    let spec = ["static:999"; 5].join(";");
    assert_eq!(
        c.request(Request::Motion { sensor: None, spec })["ok"],
        false
    );
    for bad in [
        Request::Magnet {
            sensor: None,
            index: 4,
            mm: Some(1.0),
            velocity: None,
        },
        Request::Magnet {
            sensor: None,
            index: 0,
            mm: Some(1e300),
            velocity: None,
        },
        Request::Ambient {
            sensor: None,
            celsius: -300.0,
        },
        Request::Fault {
            sensor: None,
            name: "missing-magnet".into(),
            on: true,
            value: None,
            channel: Some(4),
        },
        Request::Fault {
            sensor: None,
            name: "magnets-too-close".into(),
            on: true,
            value: None,
            channel: Some(3),
        },
    ] {
        let a = c.request(bad.clone());
        assert_eq!(a["ok"], false, "{bad:?} → {a}");
    }
    // A request accepted after the refused ones: once it shows, the refused ones would
    // have shown too.
    let a = c.request(Request::Magnet {
        sensor: None,
        index: 0,
        mm: Some(123.0),
        velocity: None,
    });
    assert_eq!(a["ok"], true, "{a}");
    let st = state_when(&c, |st| st["true_mm"][0] == 123.0);
    assert_eq!(st["true_mm"], json!([123.0, 300.0, 500.0, 700.0]), "{st}");
    assert_eq!(st["faults"], json!([]), "{st}");
    assert!(
        (st["temperature_c"].as_f64().unwrap() - 20.0).abs() < 30.0,
        "{st}"
    );
    h.stop().unwrap();
}

/// A sensor has no inputs to set (its process values are its measurements): `set-input` is
/// refused with that reason whatever its values, so a user with a typo is not sent to fix a
/// value the sensor would then refuse anyway; an unknown sensor is still named.
#[test]
fn a_sensor_refuses_set_input_whatever_its_values() {
    let dir = tempfile::tempdir().unwrap();
    let bus = MemBus::new();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    rt.add(th_setup(dir.path(), 9, 5));
    let h = rt.spawn().unwrap();
    let c = h.control();
    for (index, value) in [
        (json!("0x6000"), json!(1)),
        (json!("0x6000"), json!("abc")),
        (json!(0x1_0000), json!(1)),
    ] {
        let a = c.request(Request::SetInput {
            sensor: None,
            index,
            sub: Some(json!(1)),
            value,
        });
        assert_eq!(a["ok"], false, "{a}");
        assert!(
            a["error"]
                .as_str()
                .unwrap()
                .contains("has no inputs to set"),
            "{a}"
        );
    }
    let a = c.request(Request::SetInput {
        sensor: Some(2),
        index: json!("0x6000"),
        sub: None,
        value: json!(1),
    });
    assert!(
        a["error"]
            .as_str()
            .unwrap()
            .contains("sensor 2 does not exist"),
        "{a}"
    );
    h.stop().unwrap();
}

#[test]
fn ambient_out_of_range_raises_over_temperature_by_itself() {
    let dir = tempfile::tempdir().unwrap();
    let bus = MemBus::new();
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    let mut s = th_setup(dir.path(), 8, 5);
    // Fast thermal lags so that the test takes milliseconds, not minutes.
    s.spec.thermal_time_constant_s = 0.05;
    s.spec.waveguide_time_constant_s = 0.1;
    rt.add(s);
    let h = rt.spawn().unwrap();
    recv_id(&mut master, 0x708, Duration::from_secs(2)).expect("boot-up");
    std::thread::sleep(Duration::from_millis(50));
    while let Ok(Some(_)) = master.try_recv() {}
    let c = h.control();
    let st = c.request(Request::State { sensor: None });
    assert_eq!(st["temperature_alarm"], false, "{st}");
    // Output timing: 1000 mm TH, one 1 ms cycle; time of flight from 250 mm + 51 mm.
    assert_eq!(st["timing"]["output_delay_us"], 1000, "{st}");
    let tof = st["timing"]["time_of_flight_us"].as_f64().unwrap();
    assert!((tof - 301.0 / 2.8).abs() < 1e-6, "{st}");
    // 90 °C is outside −40…+75 °C: the electronics pass 85 °C after the lag.
    let a = c.request(Request::Ambient {
        sensor: None,
        celsius: 90.0,
    });
    assert_eq!(a["ok"], true, "{a}");
    let f = recv_id(&mut master, 0x88, Duration::from_secs(2)).expect("EMCY 0x4200");
    assert_eq!(&f.data()[..3], &[0x00, 0x42, 0x09], "{f:?}");
    let st = c.request(Request::State { sensor: None });
    assert_eq!(st["temperature_alarm"], true, "{st}");
    assert!(st["temperature_c"].as_f64().unwrap() > 85.0, "{st}");
    assert_eq!(st["faults"].as_array().unwrap().len(), 0, "{st}");
    // Back in range: the condition clears by itself.
    c.request(Request::Ambient {
        sensor: None,
        celsius: 20.0,
    });
    let f = recv_id(&mut master, 0x88, Duration::from_secs(2)).expect("EMCY clear");
    assert_eq!(&f.data()[..3], &[0, 0, 0], "{f:?}");
    h.stop().unwrap();
}

/// Issue 35 item 9: `fault power-cycle on` holds the supply off; a `power-cycle` request
/// then used to answer ok and show `powered: true` with the fault still listed.
#[test]
fn power_cycle_is_refused_while_the_power_cycle_fault_holds() {
    let dir = tempfile::tempdir().unwrap();
    let bus = MemBus::new();
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    rt.add(th_setup(dir.path(), 6, 6));
    let h = rt.spawn().unwrap();
    recv_id(&mut master, 0x706, Duration::from_secs(2)).expect("boot-up");
    let c = h.control();
    let fault = |on| Request::Fault {
        sensor: None,
        name: "power-cycle".into(),
        on,
        value: None,
        channel: None,
    };
    let a = c.request(fault(true));
    assert_eq!(a["faults"], json!(["power-cycle"]), "{a}");
    let st = c.request(Request::State { sensor: None });
    assert_eq!(
        (&st["powered"], &st["faults"]),
        (&json!(false), &json!(["power-cycle"]))
    );

    let a = c.request(Request::PowerCycle { sensor: None });
    assert_eq!(a["ok"], false, "{a}");
    let e = a["error"].as_str().unwrap();
    assert!(e.contains("`power-cycle` fault"), "{e}");
    let st = c.request(Request::State { sensor: None });
    assert_eq!(
        (&st["powered"], &st["faults"]),
        (&json!(false), &json!(["power-cycle"])),
        "a refused power-cycle changes nothing: {st}"
    );

    // The fault off is the power back: boot-up, and then a power cycle works again.
    let a = c.request(fault(false));
    assert_eq!(a["faults"], json!([]), "{a}");
    recv_id(&mut master, 0x706, Duration::from_secs(2)).expect("boot-up after the fault");
    let st = c.request(Request::State { sensor: None });
    assert_eq!((&st["powered"], &st["faults"]), (&json!(true), &json!([])));
    let a = c.request(Request::PowerCycle { sensor: None });
    assert_eq!(a["ok"], true, "{a}");
    recv_id(&mut master, 0x706, Duration::from_secs(2)).expect("boot-up after power-cycle");
    h.stop().unwrap();
}

#[test]
fn faults_raise_the_documented_emcys() {
    let dir = tempfile::tempdir().unwrap();
    let bus = MemBus::new();
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    // Four magnets on a four-channel unit, so no channel starts out missing.
    let mut s = th_setup(dir.path(), 7, 4);
    s.cfg.channels = 4;
    s.spec = SensorSpec::th(1000.0, 4).unwrap();
    s.motion = Box::new(Profiles(
        [100.0, 300.0, 500.0, 700.0]
            .map(|pos_mm| Profile::Static { pos_mm })
            .to_vec(),
    ));
    rt.add(s);
    let h = rt.spawn().unwrap();
    recv_id(&mut master, 0x707, Duration::from_secs(2)).expect("boot-up");
    // Drop the power-on EMCY (TH sends one after the boot-up).
    std::thread::sleep(Duration::from_millis(50));
    while let Ok(Some(_)) = master.try_recv() {}
    let c = h.control();
    for (name, code, reg) in [
        ("supply-voltage", 0x3100u16, 0x05u8),
        ("over-temperature", 0x4200, 0x09),
        ("error-passive", 0x8120, 0x11),
        ("can-overrun", 0x8110, 0x11),
        ("missing-magnet", 0x5000, 0x81),
    ] {
        let a = c.request(Request::Fault {
            sensor: None,
            name: name.into(),
            on: true,
            value: None,
            channel: None,
        });
        assert_eq!(a["ok"], true, "{a}");
        let f = recv_id(&mut master, 0x87, Duration::from_secs(2)).expect(name);
        assert_eq!(
            u16::from_le_bytes([f.data()[0], f.data()[1]]),
            code,
            "{name}"
        );
        assert_eq!(
            f.data()[2] & reg,
            reg,
            "{name}: register {:#x}",
            f.data()[2]
        );
        let a = c.request(Request::Fault {
            sensor: None,
            name: name.into(),
            on: false,
            value: None,
            channel: None,
        });
        assert_eq!(a["ok"], true, "{a}");
        let f = recv_id(&mut master, 0x87, Duration::from_secs(2)).expect(name);
        assert_eq!(&f.data()[..2], &[0, 0], "{name} cleared");
        let st = c.request(Request::State { sensor: None });
        assert_eq!(st["error_register"], 0, "{st}");
    }
    h.stop().unwrap();
}

mod timing {
    use super::*;

    /// Not an assertion of this machine's timer quality: prints the bare `clock_nanosleep`
    /// lateness for comparison with the runtime's (`cargo test -- --ignored --nocapture`).
    #[test]
    #[ignore = "measurement, prints numbers"]
    fn bare_clock_nanosleep_lateness() {
        set_timer_slack_1ns();
        let mut l = Lateness::default();
        let start = std::time::Instant::now();
        for k in 1..=5000u64 {
            let t = start + Duration::from_micros(k * 1000);
            sleep_until(t);
            l.record(
                std::time::Instant::now()
                    .saturating_duration_since(t)
                    .as_micros() as u64,
            );
        }
        eprintln!("bare clock_nanosleep: {l}");
    }
}
