//! canpos-host against a real SIL Kit (docs/SILKIT.md): a `sil-kit-registry` on 127.0.0.1 and
//! participants in this process. Needs `scripts/silkit.sh`; without it each test says so and
//! passes, unless `CANPOS_SILKIT_REQUIRED=1` (the test command sets it), where it fails.

use std::time::{Duration, Instant};

use canpos_host::silkit::{self, LocalRegistry, Participant, RegistryUri};

/// Generous: wall-clock waits on a loaded 2-core machine.
const START: Duration = Duration::from_secs(60);

fn api() -> Option<&'static silkit::Api> {
    match silkit::api() {
        Ok(a) => Some(a),
        Err(e) if std::env::var_os("CANPOS_SILKIT_REQUIRED").is_some_and(|v| v == "1") => {
            panic!("CANPOS_SILKIT_REQUIRED=1 but {e}")
        }
        Err(e) => {
            eprintln!("NOTE: SIL Kit test skipped: {e}");
            None
        }
    }
}

#[test]
fn the_library_is_sil_kit_5() {
    let Some(api) = api() else { return };
    assert_eq!(api.version().0, 5, "{:?}", api.version());
}

#[test]
fn a_participant_joins_and_a_taken_name_is_refused() {
    let Some(api) = api() else { return };
    let reg = LocalRegistry::start(START).expect("registry");
    let a = Participant::join(api, "canpos-test-a", reg.uri()).expect("join");
    assert_eq!(a.name(), "canpos-test-a");
    let e = Participant::join(api, "canpos-test-a", reg.uri())
        .err()
        .expect("a second participant of the same name is refused")
        .to_string();
    eprintln!("taken name: {e}");
    assert!(e.contains("canpos-test-a"), "{e}");
    // The first one is still there: its name stays taken; another name joins.
    let _b = Participant::join(api, "canpos-test-b", reg.uri()).expect("another name");
    drop(a);
}

#[test]
fn an_absent_registry_is_a_clear_error_not_a_hang() {
    let Some(api) = api() else { return };
    // A port nothing listens on: one the registry held and gave back.
    let reg = LocalRegistry::start(START).expect("registry");
    let uri: RegistryUri = reg.uri().clone();
    reg.stop();
    let t0 = Instant::now();
    let e = Participant::join(api, "canpos-test-alone", &uri)
        .err()
        .expect("no registry")
        .to_string();
    eprintln!("absent registry: {e}");
    assert!(e.contains(&uri.to_string()), "{e}");
    assert!(e.contains("SilKit_Participant_Create"), "{e}");
    // Bounded: SIL Kit gives up after its connect timeout (not a hang).
    assert!(
        t0.elapsed() < Duration::from_secs(120),
        "{:?}",
        t0.elapsed()
    );
}

fn wall(reg: &LocalRegistry, name: &str) -> canpos_host::silkit::can::SilkitCan {
    let api = silkit::api().unwrap();
    canpos_host::silkit::can::SilkitCan::open(
        api,
        &canpos_host::silkit::can::Options {
            registry: reg.uri().clone(),
            network: "can0".into(),
            participant: name.into(),
            time: canpos_host::silkit::can::TimeMode::Wall,
            bitrate_kbps: Some(125),
        },
    )
    .expect("join")
}

/// Sends `data` with `flags` from a bare SIL Kit participant (what another SIL Kit tool may
/// put on the network).
fn raw_send(
    p: &Participant,
    ctl: *mut silkit::sys::CanController,
    id: u32,
    flags: u32,
    data: &[u8],
) {
    let api = p.api();
    let mut f = silkit::sys::CanFrame {
        header: silkit::sys::StructHeader::new(silkit::sys::CAN_FRAME_ID),
        id,
        flags,
        dlc: data.len() as u16,
        sdt: 0,
        vcid: 0,
        af: 0,
        data: silkit::sys::ByteVector {
            data: data.as_ptr(),
            size: data.len(),
        },
    };
    // SAFETY: a live controller; SIL Kit copies the frame.
    let rc = unsafe { (api.can_controller_send_frame)(ctl, &mut f, std::ptr::null_mut()) };
    api.check("SilKit_CanController_SendFrame", rc).unwrap();
}

#[test]
fn frames_cross_between_participants_and_one_too_long_for_classic_can_is_dropped() {
    use canpos_host::Transport;
    let Some(api) = api() else { return };
    let reg = LocalRegistry::start(START).expect("registry");
    let mut a = wall(&reg, "canpos-a");
    let mut b = wall(&reg, "canpos-b");
    // A bare participant with a controller of its own, for frames canpos never sends.
    let raw = Participant::join(api, "raw", reg.uri()).unwrap();
    let mut ctl = std::ptr::null_mut();
    let (name, net) = (c"RAW", c"can0");
    // SAFETY: live participant, NUL-terminated strings.
    api.check("SilKit_CanController_Create", unsafe {
        (api.can_controller_create)(&mut ctl, raw.raw(), name.as_ptr(), net.as_ptr())
    })
    .unwrap();
    // SAFETY: live controller.
    api.check("SilKit_CanController_Start", unsafe {
        (api.can_controller_start)(ctl)
    })
    .unwrap();
    // Discovery between participants takes a moment: send until the first frame arrives.
    let f = canpos_stack::Frame::new(0x605, &[0x40, 0x18, 0x10, 0x04, 0, 0, 0, 0]).unwrap();
    let t0 = Instant::now();
    let got = loop {
        a.send(&f).unwrap();
        if let Some(rx) = b.recv_timeout(Some(Duration::from_millis(100))).unwrap() {
            break rx;
        }
        assert!(
            t0.elapsed() < START,
            "no frame from a to b within {START:?}"
        );
    };
    assert_eq!(got.frame, f);
    while b
        .recv_timeout(Some(Duration::from_millis(200)))
        .unwrap()
        .is_some()
    {}
    // CAN FD with 12 and 8 bytes, 9 bytes without FD, then a classic frame: only the last
    // comes through; the others are counted.
    raw_send(&raw, ctl, 0x123, silkit::sys::CAN_FLAG_FDF, &[1; 12]);
    // CAN FD even with 8 bytes: not a classic frame (its bit timing and CRC differ).
    raw_send(&raw, ctl, 0x122, silkit::sys::CAN_FLAG_FDF, &[4; 8]);
    raw_send(&raw, ctl, 0x124, 0, &[2; 9]);
    raw_send(&raw, ctl, 0x125, 0, &[3; 8]);
    let rx = b
        .recv_timeout(Some(START))
        .unwrap()
        .expect("the classic frame");
    assert_eq!(rx.frame.id(), 0x125, "{rx:?}");
    assert_eq!(rx.frame.data(), &[3; 8]);
    assert_eq!(b.not_classic(), 3);
    // A remote frame and an extended identifier keep their kind.
    let r = canpos_stack::Frame::remote(0x1ABCDEF, true, 4).unwrap();
    // `a` saw the bare participant's frame too.
    while a
        .recv_timeout(Some(Duration::from_millis(200)))
        .unwrap()
        .is_some()
    {}
    b.send(&r).unwrap();
    let rx = a.recv_timeout(Some(START)).unwrap().expect("remote frame");
    assert_eq!(rx.frame, r);
}

#[test]
fn frames_keep_flowing_when_the_registry_goes_away() {
    use canpos_host::Transport;
    let Some(_) = api() else { return };
    let reg = LocalRegistry::start(START).expect("registry");
    let mut a = wall(&reg, "canpos-a");
    let mut b = wall(&reg, "canpos-b");
    let f = canpos_stack::Frame::new(0x181, &[1, 2]).unwrap();
    let t0 = Instant::now();
    loop {
        a.send(&f).unwrap();
        if b.recv_timeout(Some(Duration::from_millis(100)))
            .unwrap()
            .is_some()
        {
            break;
        }
        assert!(t0.elapsed() < START);
    }
    reg.stop();
    while b
        .recv_timeout(Some(Duration::from_millis(200)))
        .unwrap()
        .is_some()
    {}
    // Peer to peer: the registry is only needed to join.
    a.send(&f).unwrap();
    let rx = b
        .recv_timeout(Some(START))
        .unwrap()
        .expect("still delivered");
    assert_eq!(rx.frame, f);
}

/// Sends `f` from `from` until `to` receives it (bounded by [`START`]); `false` if it never did.
fn crosses(
    from: &mut canpos_host::silkit::can::SilkitCan,
    to: &mut canpos_host::silkit::can::SilkitCan,
    f: &canpos_stack::Frame,
) -> bool {
    use canpos_host::Transport;
    let t0 = Instant::now();
    while t0.elapsed() < START {
        from.send(f).unwrap();
        if let Some(rx) = to.recv_timeout(Some(Duration::from_millis(100))).unwrap() {
            if rx.frame == *f {
                return true;
            }
        }
    }
    false
}

#[test]
fn a_participant_rejoins_a_registry_that_comes_back_and_newcomers_meet_it() {
    let Some(_) = api() else { return };
    let exe = silkit::sys::registry_executable().expect("registry");
    let reg = LocalRegistry::start(START).expect("registry");
    let uri = reg.uri().clone();
    let mut a = wall(&reg, "canpos-a");
    reg.stop();
    // Back on the same port: `a` notices (SIL Kit's disconnected handler for the registry),
    // probes, and joins it again under its name.
    let reg = LocalRegistry::start_exe(&exe, uri.port, START).expect("registry again");
    assert_eq!(reg.uri(), &uri);
    // A newcomer joins the new registry. It meets `a` only if `a` registered again: the
    // registry introduces only the participants it knows.
    let mut b = wall(&reg, "canpos-b");
    let f = canpos_stack::Frame::new(0x181, &[1, 2]).unwrap();
    let g = canpos_stack::Frame::new(0x605, &[0x40, 0, 0x10, 0]).unwrap();
    assert!(crosses(&mut a, &mut b, &f), "a never reached the newcomer");
    assert!(crosses(&mut b, &mut a, &g), "the newcomer never reached a");
    assert_eq!(a.participant(), "canpos-a");
    // Taken again in the new registry: the name is a's.
    let e = Participant::join(silkit::api().unwrap(), "canpos-a", reg.uri())
        .err()
        .expect("a's name is registered again");
    assert!(e.to_string().contains("already exists"), "{e}");
}

#[test]
fn a_failed_rejoin_is_tried_again_until_the_registry_answers() {
    let Some(_) = api() else { return };
    let exe = silkit::sys::registry_executable().expect("registry");
    let reg = LocalRegistry::start(START).expect("registry");
    let uri = reg.uri().clone();
    let mut a = wall(&reg, "canpos-a");
    reg.stop();
    // Something that is not a registry takes the address: the probe answers, the join fails
    // (SIL Kit's handshake times out), and the participant tries again.
    let squatter = std::net::TcpListener::bind(("127.0.0.1", uri.port)).expect("the port");
    let t0 = Instant::now();
    let mut accepted = 0;
    squatter.set_nonblocking(true).unwrap();
    while accepted < 2 && t0.elapsed() < START {
        if squatter.accept().is_ok() {
            accepted += 1;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(accepted >= 2, "no probe reached the address");
    drop(squatter);
    // The registry itself is back: the next attempt succeeds and a newcomer meets `a`.
    let reg = LocalRegistry::start_exe(&exe, uri.port, START).expect("registry again");
    let mut b = wall(&reg, "canpos-b");
    let f = canpos_stack::Frame::new(0x181, &[3]).unwrap();
    assert!(crosses(&mut a, &mut b, &f), "a never rejoined");
}
