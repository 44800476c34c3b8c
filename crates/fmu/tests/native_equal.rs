//! The sensor FMU behaves as the native runtime does (issue 31 item 2): the same frames, in
//! the same order, with the same contents (measurement noise included), on the same sequence
//! of frames and magnet inputs; the FMU's event times within a frame time or two of the
//! native bus's end-of-frame times.

use canpos_fmu::kind::Kind;
use canpos_fmu::lsbus::{self, Op, TxBuffer};
use canpos_fmu::model::{FmuModel, Value};
use canpos_fmu::sensor::{SensorUnit, VR_RX_CLOCK, VR_RX_DATA, VR_TX_CLOCK, VR_TX_DATA};
use canpos_host::bus::{BusEvent, Timeline, DEFAULT_TX_DEPTH};
use canpos_host::can::Transport;
use canpos_host::clock::SimClock;
use canpos_host::control::request::Request;
use canpos_host::runtime::{state_file, SensorSetup};
use canpos_host::{FileStorage, MemBus, Runtime};
use canpos_sim::motion::{Profile, Profiles};
use canpos_stack::{Frame, Instant};

const NODE: u8 = 5;
const KBPS: u16 = 1000;
const STEPS: u64 = 120;

/// The inputs: frames from a master at `ms` + the offset (µs) of each, and a magnet ramp set at
/// whole milliseconds. Each input has an offset of its own: what a node does in reaction
/// (a TPDO event timer started by NMT start, the heartbeats after a 0x1017 write) keeps the
/// offset of its cause, and no input meets a node event at one instant, whose order the FMU
/// (the node's own event first: the step ran to it) and the native runtime (the bus frame
/// first) choose differently (docs/FMU.md).
fn frames_at(ms: u64) -> (u64, Vec<Frame>) {
    let sdo = |d: [u8; 8]| Frame::new(0x600 + u16::from(NODE), &d).unwrap();
    match ms {
        2 => (500, vec![Frame::new(0, &[0x01, NODE]).unwrap()]),
        10 => (100, vec![sdo([0x40, 0x18, 0x10, 0x04, 0, 0, 0, 0])]),
        15 => (300, vec![sdo([0x2B, 0x17, 0x10, 0x00, 20, 0, 0, 0])]),
        40 => (700, vec![Frame::new(0, &[0x02, NODE]).unwrap()]),
        55 => (900, vec![Frame::new(0, &[0x01, NODE]).unwrap()]),
        70 => (
            600,
            vec![Frame::remote(0x700 + u32::from(NODE), false, 1).unwrap()],
        ),
        _ => (500, vec![]),
    }
}

fn magnet_at(ms: u64) -> f64 {
    300.0 + 0.25 * ms as f64
}

type Log = Vec<(u64, u32, Vec<u8>)>;

fn read_tx(m: &mut dyn FmuModel, t_us: u64, log: &mut Log) {
    if m.get(VR_TX_CLOCK).unwrap() != Value::Clock(true) {
        return;
    }
    let Value::Binary(b) = m.get(VR_TX_DATA).unwrap() else {
        panic!("Tx_Data is not binary")
    };
    for op in lsbus::parse(b).unwrap() {
        if let Op::Transmit { id, data, .. } = op {
            log.push((t_us, id, data.to_vec()));
        }
    }
}

/// Steps from `t` to `end` with early return, reading what each event sends.
fn step(m: &mut dyn FmuModel, mut t: f64, end: f64, log: &mut Log) {
    while t < end - 1e-12 {
        let r = m.do_step(t, end - t, true).unwrap();
        t = r.last_time;
        if r.event_needed {
            m.enter_event_mode().unwrap();
            read_tx(m, (t * 1e6).round() as u64, log);
            m.update_discrete_states().unwrap();
            m.enter_step_mode().unwrap();
        }
    }
}

fn fmu_run() -> Log {
    let kind = Kind::Sensor(SensorUnit::for_model("th").unwrap());
    let mut m = kind.instantiate().unwrap();
    let m = m.as_mut();
    m.set(1, Value::UInt8(NODE)).unwrap();
    m.set(2, Value::UInt16(KBPS)).unwrap();
    m.enter_initialization(0.0).unwrap();
    m.exit_initialization().unwrap();
    let mut log = Vec::new();
    read_tx(m, 0, &mut log);
    m.enter_step_mode().unwrap();
    for ms in 0..STEPS {
        m.set(100, Value::Float64(magnet_at(ms))).unwrap();
        let (off, rx) = frames_at(ms);
        let mid = (ms * 1000 + off) as f64 / 1e6;
        step(m, ms as f64 / 1e3, mid, &mut log);
        if !rx.is_empty() {
            let mut b = TxBuffer::new(4096);
            for f in &rx {
                b.push(&Op::Transmit {
                    id: f.id(),
                    ide: false,
                    rtr: f.is_remote(),
                    data: f.data(),
                    dlc: u16::from(f.dlc()),
                })
                .unwrap();
            }
            m.enter_event_mode().unwrap();
            m.set(VR_RX_DATA, Value::Binary(b.bytes())).unwrap();
            m.set(VR_RX_CLOCK, Value::Clock(true)).unwrap();
            m.update_discrete_states().unwrap();
            read_tx(m, ms * 1000 + off, &mut log);
            m.enter_step_mode().unwrap();
        }
        step(m, mid, (ms + 1) as f64 / 1e3, &mut log);
    }
    log
}

/// The native side: the CLI's runtime on a stepped `mem://` bus, a master port beside it.
fn native_run() -> Log {
    let dir = tempfile::tempdir().unwrap();
    let clock = SimClock::stepped();
    let bus = MemBus::with_clock(u32::from(KBPS), clock.clone());
    let mut master = bus.attach();
    let mut rt = Runtime::new(Box::new(bus.attach()), None);
    let unit = SensorUnit::for_model("th").unwrap();
    let mut cfg = unit.cfg;
    cfg.node_id = NODE;
    cfg.bitrate_kbps = KBPS;
    let path = state_file(dir.path(), unit.model.name, cfg.serial);
    let n = usize::from(cfg.channels.max(1));
    rt.add(SensorSetup {
        name: "th".into(),
        model: unit.model,
        cfg,
        spec: unit.spec.clone(),
        seed: u64::from(cfg.serial),
        ideal: false,
        motion: Box::new(Profiles(
            (0..n)
                .map(|k| Profile::Static {
                    pos_mm: unit.spec.stroke_mm * (k as f64 + 1.0) / (n as f64 + 1.0),
                })
                .collect(),
        )),
        storage: FileStorage::open(&path).unwrap().for_model(unit.model),
    });
    let mut log = Vec::new();
    rt.advance_to(Instant::from_micros(0)).unwrap();
    for ms in 0..STEPS {
        rt.request_now(Request::Magnet {
            sensor: Some(0),
            index: 0,
            mm: Some(magnet_at(ms)),
            velocity: None,
        });
        let (off, rx) = frames_at(ms);
        rt.advance_to(Instant::from_micros(ms * 1000 + off))
            .unwrap();
        for f in rx {
            master.send(&f).unwrap();
        }
        rt.advance_to(Instant::from_micros((ms + 1) * 1000))
            .unwrap();
        master.sync_bus();
        while let Some(rx) = master.try_recv().unwrap() {
            let t = clock.nanos_of(rx.timestamp).unwrap() / 1000;
            log.push((t, rx.frame.id(), rx.frame.data().to_vec()));
        }
    }
    log
}

#[test]
fn the_fmu_sends_what_the_native_runtime_sends_frame_by_frame() {
    let fmu = fmu_run();
    let native = native_run();
    let tpdos = fmu
        .iter()
        .filter(|f| f.1 == 0x180 + u32::from(NODE))
        .count();
    assert!(tpdos > 80, "{tpdos} TPDOs: {fmu:?}");
    assert!(fmu.iter().any(|f| f.1 == 0x580 + u32::from(NODE)));
    assert!(fmu
        .iter()
        .any(|f| f.1 == 0x700 + u32::from(NODE) && f.2 == [0x05]));
    // The native master sees what reached the bus by the last step's end; the FMU's frames at
    // that very end may still be on the wire there.
    let last = native.len().min(fmu.len());
    assert!(
        fmu.len() - last <= 2 && native.len() - last <= 2,
        "{} / {}",
        fmu.len(),
        native.len()
    );
    for (k, (a, b)) in fmu.iter().zip(&native).enumerate() {
        assert_eq!(
            (a.1, &a.2),
            (b.1, &b.2),
            "frame {k}: FMU {a:?}, native {b:?}"
        );
        // The FMU's time is when the node sent it; the native one the end of the frame on a
        // 1 Mbit/s bus, after the request's own frame time and any frame before it in the
        // queue (at most ~135 µs a frame).
        assert!(
            b.0 >= a.0 && b.0 - a.0 <= 400,
            "frame {k}: FMU {a:?}, native {b:?}"
        );
    }
}

/// Submits what the FMU sent in the event at `t_us` to the bus as the node's frames, one by
/// one with the bus run to `t_us` after each, as a `mem://` bus does on each send: a frame sent
/// to an idle bus is on the wire before the next one of the same instant is queued. (An LS-BUS
/// bus simulation given the event's whole `Tx_Data` at once arbitrates them instead: the
/// boot-up and the EMCY of power-on leave in the other order, docs/FMU.md.)
fn submit_tx(
    m: &mut dyn FmuModel,
    bus: &mut Timeline,
    node: canpos_host::bus::MemberId,
    t_us: u64,
    events: &mut Vec<BusEvent>,
) {
    let mut sent = Vec::new();
    read_tx(m, t_us, &mut sent);
    for (_, id, data) in sent {
        // The node sends no remote frame (read_tx keeps data frames' contents).
        let f = Frame::with_id(id, false, &data).unwrap();
        bus.submit(node, f, t_us * 1000).unwrap();
        bus.advance(t_us * 1000, events);
    }
}

/// The FMU on canpos's own bus model (the `Timeline` a `mem://` bus runs on): its frames go
/// on the bus at their send time, the master's frames reach it at their end of frame; the log
/// is what the master receives, stamped with its end of frame.
fn fmu_on_the_bus() -> Log {
    let kind = Kind::Sensor(SensorUnit::for_model("th").unwrap());
    let mut m = kind.instantiate().unwrap();
    let m = m.as_mut();
    m.set(1, Value::UInt8(NODE)).unwrap();
    m.set(2, Value::UInt16(KBPS)).unwrap();
    let mut bus = Timeline::new(u32::from(KBPS)).unwrap();
    let master = bus.join(DEFAULT_TX_DEPTH);
    let node = bus.join(DEFAULT_TX_DEPTH);
    m.enter_initialization(0.0).unwrap();
    m.exit_initialization().unwrap();
    let mut events = Vec::new();
    submit_tx(m, &mut bus, node, 0, &mut events);
    m.enter_step_mode().unwrap();
    let mut log = Vec::new();
    let mut now = 0u64;
    for ms in 0..STEPS {
        m.set(100, Value::Float64(magnet_at(ms))).unwrap();
        let (off, rx) = frames_at(ms);
        let mut inputs = Some((ms * 1000 + off, rx));
        let end = (ms + 1) * 1000;
        while now < end {
            let input_at = inputs.as_ref().map_or(end, |i| i.0);
            let target = bus
                .next_event()
                .map_or(end, |ns| ns.div_ceil(1000))
                .clamp(now, end)
                .min(input_at);
            while now < target {
                let r = m
                    .do_step(now as f64 / 1e6, (target - now) as f64 / 1e6, true)
                    .unwrap();
                now = (r.last_time * 1e6).round() as u64;
                if r.event_needed {
                    m.enter_event_mode().unwrap();
                    submit_tx(m, &mut bus, node, now, &mut events);
                    m.update_discrete_states().unwrap();
                    m.enter_step_mode().unwrap();
                }
            }
            bus.advance(now * 1000, &mut events);
            let mut b = TxBuffer::new(4096);
            for e in events.drain(..) {
                if let BusEvent::Frame {
                    from, frame, end, ..
                } = e
                {
                    if from == node {
                        log.push((end / 1000, frame.id(), frame.data().to_vec()));
                    } else {
                        b.push(&Op::Transmit {
                            id: frame.id(),
                            ide: false,
                            rtr: frame.is_remote(),
                            data: frame.data(),
                            dlc: u16::from(frame.dlc()),
                        })
                        .unwrap();
                    }
                }
            }
            if !b.is_empty() {
                m.enter_event_mode().unwrap();
                m.set(VR_RX_DATA, Value::Binary(b.bytes())).unwrap();
                m.set(VR_RX_CLOCK, Value::Clock(true)).unwrap();
                m.update_discrete_states().unwrap();
                submit_tx(m, &mut bus, node, now, &mut events);
                m.enter_step_mode().unwrap();
            }
            if now == input_at {
                if let Some((_, rx)) = inputs.take() {
                    for f in rx {
                        bus.submit(master, f, now * 1000).unwrap();
                    }
                }
            }
        }
    }
    log
}

/// On the same bus model as the native runtime's, the FMU's frames end at the very instants
/// the native ones do: the frame time and the request's own frame time are all the 400 µs above
/// allowed for, no difference of the FMU's.
#[test]
fn on_the_same_bus_model_every_frame_ends_when_the_native_one_does() {
    let fmu = fmu_on_the_bus();
    let native = native_run();
    assert!(fmu.len() > 80, "{fmu:?}");
    let last = native.len().min(fmu.len());
    assert!(
        fmu.len() - last <= 2 && native.len() - last <= 2,
        "{} / {}",
        fmu.len(),
        native.len()
    );
    for (k, (a, b)) in fmu.iter().zip(&native).enumerate() {
        assert_eq!(a, b, "frame {k}: FMU on the bus model, native");
    }
}
