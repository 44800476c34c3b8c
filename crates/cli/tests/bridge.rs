//! `canpos bus bridge` between two hubs (the SocketCAN side runs in the UML guest, see
//! socketcan_vcan.rs): frames both ways, remote frames with their DLC, and a clear error for a
//! bus that is not there.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime};

use canpos_host::socketcand::codec::ErrorFrame;
use canpos_host::socketcand::{Client, Hub};
use canpos_host::transport::{BusState, Transport};
use canpos_stack::Frame;

struct Kill(Child);

impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn recv(c: &mut Client, within: Duration) -> Option<Frame> {
    c.recv_timeout(Some(within)).unwrap().map(|r| r.frame)
}

#[test]
fn bridging_a_url_that_is_not_there_is_a_clear_error() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let hub = Hub::bind("127.0.0.1:0").unwrap().spawn().unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_canpos"))
        .args([
            "bus",
            "bridge",
            &format!("socketcand://{}/can0", hub.local_addr()),
            &format!("socketcand://127.0.0.1:{port}/can0"),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("cannot bridge to") && err.contains("refused"),
        "{err}"
    );
    let o = Command::new(env!("CARGO_BIN_EXE_canpos"))
        .args(["bus", "bridge", "mem://a", "mem://a"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
}

#[test]
fn two_hubs_bridged_share_frames_and_remote_frames() {
    let h1 = Hub::bind("127.0.0.1:0").unwrap().spawn().unwrap();
    let h2 = Hub::bind("127.0.0.1:0").unwrap().spawn().unwrap();
    let (u1, u2) = (
        format!("socketcand://{}/line", h1.local_addr()),
        format!("socketcand://{}/can0", h2.local_addr()),
    );
    let _bridge = Kill(
        Command::new(env!("CARGO_BIN_EXE_canpos"))
            .args(["bus", "bridge", &u1, &u2])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let end = Instant::now() + Duration::from_secs(10);
    while h1.stats().clients < 1 || h2.stats().clients < 1 {
        assert!(Instant::now() < end, "the bridge did not connect");
        std::thread::sleep(Duration::from_millis(10));
    }
    let mut a = Client::connect(h1.local_addr(), "line").unwrap();
    let mut b = Client::connect(h2.local_addr(), "can0").unwrap();
    std::thread::sleep(Duration::from_millis(50));
    let data = Frame::new(0x181, &[1, 2, 3]).unwrap();
    let rtr = Frame::remote(0x77F, false, 1).unwrap();
    a.send(&data).unwrap();
    a.send(&rtr).unwrap();
    assert_eq!(recv(&mut b, Duration::from_secs(5)), Some(data));
    assert_eq!(recv(&mut b, Duration::from_secs(5)), Some(rtr));
    let back = Frame::new(0x77F, &[0x7F]).unwrap();
    b.send(&back).unwrap();
    assert_eq!(recv(&mut a, Duration::from_secs(5)), Some(back));
    // Nothing comes back to the sender through the bridge.
    assert_eq!(recv(&mut a, Duration::from_millis(100)), None);
    // A controller state on one side (here posted to the first hub's channel, as its
    // interface's) is that side's: the bridge logs it, the other side's clients keep their own
    // (issue 35: a state report is no other node's state).
    h1.post_error(
        "line",
        ErrorFrame::for_state(BusState::ErrorPassive, SystemTime::now()),
    );
    let end = Instant::now() + Duration::from_secs(5);
    while a.bus_state() != BusState::ErrorPassive {
        assert!(
            Instant::now() < end,
            "the first hub's client did not get the error"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    // The bridge looks at the states at least every 100 ms.
    std::thread::sleep(Duration::from_millis(300));
    b.send(&back).unwrap();
    assert_eq!(recv(&mut a, Duration::from_secs(5)), Some(back));
    assert_eq!(b.bus_state(), BusState::ErrorActive);
}
