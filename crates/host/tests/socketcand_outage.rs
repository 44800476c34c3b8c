//! A sensor whose socketcand server goes away: bus-off while it is away, reconnection with
//! back-off, and a boot-up (as after a power cycle) plus the bus-off recovery EMCY when it is
//! back. docs/SOCKETCAND.md, "Outages".

use std::time::{Duration, Instant};

use canpos_host::control::Request;
use canpos_host::runtime::{Runtime, SensorSetup};
use canpos_host::socketcand::{Client, Hub};
use canpos_host::transport::{BusState, HubPolicy, Transport};
use canpos_host::FileStorage;
use canpos_sim::motion::{Profile, Profiles};
use canpos_sim::SensorSpec;
use canpos_stack::Frame;

fn th(dir: &std::path::Path) -> SensorSetup {
    let model = canpos_models::by_name("th").unwrap();
    let mut cfg = model.default_config;
    cfg.node_id = 9;
    cfg.serial = 77;
    SensorSetup {
        name: "th-77".into(),
        model,
        cfg,
        spec: SensorSpec::th(f64::from(cfg.stroke_mm), 1).unwrap(),
        seed: 1,
        ideal: true,
        motion: Box::new(Profiles(vec![Profile::Static { pos_mm: 250.0 }])),
        storage: FileStorage::new(canpos_host::runtime::state_file(dir, "th", 77)),
    }
}

fn wait_for(c: &mut Client, want: impl Fn(&Frame) -> bool, within: Duration) -> Option<Frame> {
    let end = Instant::now() + within;
    while let Ok(Some(rx)) = c.recv_deadline(end) {
        if want(&rx.frame) {
            return Some(rx.frame);
        }
    }
    None
}

#[test]
fn a_lost_server_is_bus_off_then_a_reboot_when_it_is_back() {
    let dir = tempfile::tempdir().unwrap();
    let hub = Hub::bind("127.0.0.1:0").unwrap();
    let addr = hub.local_addr();
    let hub = hub.spawn().unwrap();
    let url = format!("socketcand://{addr}/can0");
    // `never`: this test's hub is the server; the sensor must not start its own.
    let (t, embedded) = canpos_host::open_device_bus(&url, HubPolicy::Never).unwrap();
    assert!(embedded.is_none());
    let mut rt = Runtime::new(t, None);
    rt.add(th(dir.path()));
    let mut master = Client::connect(addr, "can0").unwrap();
    let h = rt.spawn().unwrap();
    let boot = |f: &Frame| f.std_id() == Some(0x709) && f.data() == [0];
    wait_for(&mut master, boot, Duration::from_secs(5)).expect("first boot-up");

    hub.shutdown().unwrap();
    let c = h.control();
    let end = Instant::now() + Duration::from_secs(5);
    loop {
        let st = c.request(Request::State { sensor: None });
        if st["bus_state"] == "bus-off" {
            break;
        }
        // The runtime keeps running while the server is away (it used to exit).
        assert!(!h.is_finished(), "the runtime ended with its server");
        if Instant::now() > end {
            panic!("no bus-off while the server is away: {st}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    // Back on the same address: the sensor reconnects by itself and boots again.
    std::thread::sleep(Duration::from_millis(300));
    let hub = Hub::bind(addr).unwrap().spawn().unwrap();
    let mut master = Client::connect(addr, "can0").unwrap();
    wait_for(&mut master, boot, Duration::from_secs(15)).expect("boot-up after the outage");
    let emcy = wait_for(
        &mut master,
        |f| f.std_id() == Some(0x89) && f.data().len() == 8 && f.data()[..2] == [0x40, 0x81],
        Duration::from_secs(5),
    );
    assert!(
        emcy.is_some(),
        "no bus-off recovery EMCY 0x8140 after the outage"
    );
    assert_eq!(master.bus_state(), BusState::ErrorActive);
    // And it answers again.
    master
        .send(&Frame::new(0x609, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]).unwrap())
        .unwrap();
    wait_for(
        &mut master,
        |f| f.std_id() == Some(0x589),
        Duration::from_secs(5),
    )
    .expect("SDO answer after the outage");
    h.stop().unwrap();
    drop(hub);
}
