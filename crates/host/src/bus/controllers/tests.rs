//! The simulated network on a virtual clock: times from the frames' bit lengths (bits.rs).

use super::*;
use crate::bus::bits::frame_length;

const US: Nanos = 1000;
/// 125 kbit/s: 8 µs a bit.
const BIT: Nanos = 8 * US;

fn raw(id: u32, data: &[u8]) -> RawFrame<'_> {
    RawFrame {
        id,
        extended: false,
        remote: false,
        fd_or_xl: false,
        dlc: data.len() as u16,
        data,
    }
}

/// End of EOF of `f` started at `start` (its length minus the 3-bit intermission).
fn eof(start: Nanos, f: &Frame) -> Nanos {
    start + Nanos::from(frame_length(f).total - 3) * BIT
}

fn started(n: u64) -> Network {
    let mut net = Network::new(125).unwrap();
    let mut out = Vec::new();
    for d in 1..=n {
        assert!(net.attach(d));
        net.set_mode(d, ControllerMode::Started, false, false, 0, &mut out);
    }
    // Each start is told: mode Started, error active.
    assert_eq!(out.len(), n as usize);
    assert!(out.iter().all(|e| matches!(
        e,
        NetEvent::Status {
            mode: ControllerMode::Started,
            error: Some(BusState::ErrorActive),
            ..
        }
    )));
    net
}

#[test]
fn arbitration_and_end_of_frame_times_of_bus_md() {
    // Controllers 1 and 2 request at t = 0: 0x100 wins, ends at its EOF; 0x300 starts at the
    // end of the intermission and ends at its own EOF. Each sender is acknowledged at its
    // frame's end, the other controllers receive it then.
    let mut net = started(3);
    let mut out = Vec::new();
    net.request(1, &raw(0x300, &[1, 2]), 11, 0, &mut out);
    net.request(2, &raw(0x100, &[3]), 22, 0, &mut out);
    assert!(
        out.is_empty(),
        "nothing decided before the bus ran: {out:?}"
    );
    net.advance_to(10_000 * US, &mut out);
    let f1 = Frame::with_id(0x100, false, &[3]).unwrap();
    let f3 = Frame::with_id(0x300, false, &[1, 2]).unwrap();
    let end1 = eof(0, &f1);
    let start2 = Nanos::from(frame_length(&f1).total) * BIT;
    assert_eq!(
        out,
        vec![
            NetEvent::Frame {
                senders: vec![(2, 22)],
                receivers: vec![1, 3],
                frame: f1,
                at: end1,
            },
            NetEvent::Frame {
                senders: vec![(1, 11)],
                receivers: vec![2, 3],
                frame: f3,
                at: eof(start2, &f3),
            },
        ]
    );
    assert_eq!(net.counters().frames, 2);
    assert_eq!(net.counters().deliveries, 4);
}

#[test]
fn no_acknowledgement_before_the_frame_went_through() {
    // The frame that lost arbitration is not acknowledged while the winner is on the wire.
    let mut net = started(2);
    let mut out = Vec::new();
    net.request(1, &raw(0x300, &[]), 1, 0, &mut out);
    net.request(2, &raw(0x100, &[]), 2, 0, &mut out);
    let f1 = Frame::with_id(0x100, false, &[]).unwrap();
    net.advance_to(eof(0, &f1), &mut out);
    assert_eq!(out.len(), 1);
    assert!(matches!(&out[0], NetEvent::Frame { senders, .. } if senders == &vec![(2, 2)]));
    assert_eq!(
        net.next_event(),
        Some(Nanos::from(frame_length(&f1).total) * BIT)
    );
}

#[test]
fn stopped_and_sleeping_controllers_neither_send_nor_receive() {
    let mut net = started(3);
    let mut out = Vec::new();
    net.set_mode(3, ControllerMode::Sleep, false, false, 0, &mut out);
    assert_eq!(
        out,
        vec![NetEvent::Status {
            to: 3,
            mode: ControllerMode::Sleep,
            error: Some(BusState::ErrorActive),
            at: 0
        }]
    );
    out.clear();
    net.request(3, &raw(0x123, &[]), 7, 5, &mut out);
    assert_eq!(
        out,
        vec![NetEvent::NotSent {
            to: 3,
            context: 7,
            id: 0x123,
            status: TxStatus::Canceled,
            at: 5
        }]
    );
    out.clear();
    net.request(1, &raw(0x10, &[]), 8, 5, &mut out);
    net.advance_to(1_000 * US, &mut out);
    assert!(matches!(&out[0], NetEvent::Frame { receivers, .. } if receivers == &vec![2]));
}

#[test]
fn stop_cancels_what_was_queued_but_not_the_frame_on_the_wire() {
    let mut net = started(2);
    let mut out = Vec::new();
    for (i, id) in [0x100u32, 0x200, 0x300].into_iter().enumerate() {
        net.request(1, &raw(id, &[]), i as u64, 0, &mut out);
    }
    net.advance_to(1, &mut out); // 0x100 is on the wire
    net.set_mode(1, ControllerMode::Stopped, false, false, 2, &mut out);
    let cancelled: Vec<Context> = out
        .iter()
        .filter_map(|e| match e {
            NetEvent::NotSent {
                context,
                status: TxStatus::Canceled,
                ..
            } => Some(*context),
            _ => None,
        })
        .collect();
    assert_eq!(cancelled, vec![1, 2]);
    out.clear();
    net.advance_to(10_000 * US, &mut out);
    assert_eq!(out.len(), 1, "{out:?}");
    assert!(matches!(&out[0], NetEvent::Frame { frame, senders, .. }
        if frame.id() == 0x100 && senders == &vec![(1, 0)]));
}

#[test]
fn a_full_queue_answers_transmit_queue_full() {
    let mut net = started(2);
    let mut out = Vec::new();
    for i in 0..DEFAULT_TX_DEPTH as u64 {
        net.request(1, &raw(0x500, &[i as u8]), i, 0, &mut out);
    }
    assert!(out.is_empty());
    // Less important than all queued: refused.
    net.request(1, &raw(0x600, &[]), 100, 0, &mut out);
    // More important: takes the place of the latest 0x500, which is answered.
    net.request(1, &raw(0x080, &[]), 101, 0, &mut out);
    assert_eq!(
        out,
        vec![
            NetEvent::NotSent {
                to: 1,
                context: 100,
                id: 0x600,
                status: TxStatus::QueueFull,
                at: 0
            },
            NetEvent::NotSent {
                to: 1,
                context: DEFAULT_TX_DEPTH as u64 - 1,
                id: 0x500,
                status: TxStatus::QueueFull,
                at: 0
            },
        ]
    );
    assert_eq!(net.counters().queue_full, 2);
}

#[test]
fn frames_that_are_not_classic_can_are_refused() {
    let mut net = started(1);
    let mut out = Vec::new();
    let nine = [0u8; 9];
    let cases = [
        raw(0x100, &nine),
        RawFrame {
            fd_or_xl: true,
            ..raw(0x100, &[1])
        },
        raw(0x800, &[]),
        RawFrame {
            dlc: 3,
            ..raw(0x100, &[1])
        },
    ];
    for (i, r) in cases.iter().enumerate() {
        net.request(1, r, i as u64, 0, &mut out);
    }
    assert_eq!(out.len(), 4);
    assert!(out.iter().all(|e| matches!(
        e,
        NetEvent::NotSent {
            status: TxStatus::Canceled,
            ..
        }
    )));
    assert_eq!(net.counters().bad_frames, 4);
    assert_eq!(cases[0].to_frame(), Err(BadFrame::TooLong(9)));
    assert_eq!(cases[1].to_frame(), Err(BadFrame::NotClassic));
    assert_eq!(cases[2].to_frame(), Err(BadFrame::BadId(0x800)));
    // Extended identifiers up to 29 bits, remote frames with their DLC, DLC 0 with data.
    let ext = RawFrame {
        extended: true,
        ..raw(0x1FFF_FFFF, &[])
    };
    assert!(ext.to_frame().unwrap().is_extended());
    let rtr = RawFrame {
        remote: true,
        dlc: 8,
        ..raw(0x181, &[])
    };
    assert!(rtr.to_frame().unwrap().is_remote());
    let dlc0 = RawFrame {
        dlc: 0,
        ..raw(0x181, &[1, 2, 3])
    };
    assert_eq!(dlc0.to_frame().unwrap().data(), &[1, 2, 3]);
}

#[test]
fn another_bit_rate_goes_bus_off_and_the_queue_is_answered() {
    // A controller set to 250 kbit/s on a 125 kbit/s network never reaches the bus: error
    // passive after 16 attempts, bus-off after 32; its requests are then cancelled and new
    // ones refused; the others receive nothing from it.
    let mut net = started(2);
    let mut out = Vec::new();
    net.set_bitrate(1, 250_000, 0);
    net.request(1, &raw(0x100, &[]), 5, 0, &mut out);
    // Up to bus-off (before its 128 × 11 recessive bits of recovery).
    let mut t = 0;
    while !out.iter().any(|e| {
        matches!(
            e,
            NetEvent::Status {
                error: Some(BusState::BusOff),
                ..
            }
        )
    }) {
        assert!(t < 100_000 * US, "no bus-off: {out:?}");
        t += 100 * US;
        net.advance_to(t, &mut out);
    }
    let states: Vec<Option<BusState>> = out
        .iter()
        .filter_map(|e| match e {
            NetEvent::Status { to: 1, error, .. } => Some(*error),
            _ => None,
        })
        .collect();
    assert_eq!(
        states,
        [Some(BusState::ErrorPassive), Some(BusState::BusOff)]
    );
    // New requests are refused while bus-off.
    net.request(1, &raw(0x101, &[]), 9, t, &mut out);
    assert!(matches!(
        out.last(),
        Some(NetEvent::NotSent {
            context: 9,
            status: TxStatus::Canceled,
            ..
        })
    ));
    assert!(out.iter().any(|e| matches!(
        e,
        NetEvent::NotSent {
            context: 5,
            status: TxStatus::Canceled,
            ..
        }
    )));
    assert!(!out.iter().any(|e| matches!(e, NetEvent::Frame { .. })));
    // The bus's own rate again, and a reset of error handling: error active, sends again.
    out.clear();
    net.set_bitrate(1, 125_000, net.reached());
    let now = net.reached();
    net.set_mode(1, ControllerMode::Started, true, true, now, &mut out);
    assert!(matches!(
        out.last(),
        Some(NetEvent::Status {
            error: Some(BusState::ErrorActive),
            ..
        })
    ));
    net.request(1, &raw(0x100, &[]), 6, now, &mut out);
    net.advance_to(now + 1_000 * US, &mut out);
    assert!(out.iter().any(
        |e| matches!(e, NetEvent::Frame { senders, receivers, .. } if senders == &vec![(1, 6)] && receivers == &vec![2])
    ));
}

#[test]
fn a_reset_reports_uninit_with_no_error_state_and_detach_forgets() {
    let mut net = started(2);
    let mut out = Vec::new();
    net.set_mode(2, ControllerMode::Uninit, true, true, 3, &mut out);
    assert_eq!(
        out,
        vec![NetEvent::Status {
            to: 2,
            mode: ControllerMode::Uninit,
            error: None,
            at: 3
        }]
    );
    net.detach(2);
    assert_eq!(net.controllers().len(), 1);
    assert_eq!(net.departed().len(), 1);
    assert_eq!(net.departed()[0].0, 2);
    out.clear();
    net.request(2, &raw(0x1, &[]), 0, 3, &mut out);
    assert!(out.is_empty());
    assert_eq!(net.counters().unknown, 1);
    // A full network refuses more controllers.
    for d in 10..(10 + MAX_CONTROLLERS as u64) {
        net.attach(d);
    }
    assert_eq!(net.controllers().len(), MAX_CONTROLLERS);
    assert!(!net.attach(5000));
}

#[test]
fn a_settled_frame_may_be_run_to_its_end_before_the_requests_of_its_time_are_known() {
    // Network `a` learns each request at its time; network `b` runs to the end of the frame on
    // the wire first and learns the request made meanwhile afterwards (entered at the time it
    // reached): both carry the same frames at the same times.
    let f1 = Frame::with_id(0x300, false, &[1; 8]).unwrap();
    let mid = eof(0, &f1) / 2;
    let mut a = started(2);
    let mut b = started(2);
    let (mut oa, mut ob) = (Vec::new(), Vec::new());
    for (net, out) in [(&mut a, &mut oa), (&mut b, &mut ob)] {
        net.request(1, &raw(0x300, &[1; 8]), 1, 0, out);
        net.advance_to(1, out);
    }
    assert_eq!(b.settled_frame(), Some((0, eof(0, &f1))));
    a.advance_to(mid, &mut oa);
    a.request(2, &raw(0x100, &[]), 2, mid, &mut oa);
    a.advance_to(10_000 * US, &mut oa);
    let (_, end) = b.settled_frame().unwrap();
    b.advance_to(end, &mut ob);
    assert_eq!(b.settled_frame(), None);
    b.request(2, &raw(0x100, &[]), 2, mid, &mut ob);
    b.advance_to(10_000 * US, &mut ob);
    assert_eq!(oa, ob);
    assert_eq!(oa.len(), 2);
}

#[test]
fn a_controller_started_before_the_simulator_knew_it_takes_part() {
    // SIL Kit does not repeat a controller's mode when a simulator appears (D39).
    let mut net = Network::new(125).unwrap();
    let mut out = Vec::new();
    assert!(net.attach(1));
    assert!(net.attach(2));
    net.request(1, &raw(0x181, &[1]), 4, 0, &mut out);
    net.advance_to(10_000 * US, &mut out);
    assert!(
        matches!(&out[..], [NetEvent::Frame { senders, receivers, .. }]
        if senders == &vec![(1, 4)] && receivers == &vec![2])
    );
    // An explicit stop is honoured, and answered.
    out.clear();
    net.set_mode(
        2,
        ControllerMode::Stopped,
        false,
        false,
        net.reached(),
        &mut out,
    );
    assert!(matches!(
        &out[..],
        [NetEvent::Status {
            to: 2,
            mode: ControllerMode::Stopped,
            ..
        }]
    ));
}
