//! The ports on a virtual clock: times computed from the bit lengths, and one scene run both
//! through the ports and through a `mem://` bus on a stepped clock.

use super::*;
use crate::bus::bits::{frame_length, INTERMISSION_BITS};

const US: Nanos = 1000;

fn run(p: &mut Ports, t: Nanos) -> Vec<PortEvent> {
    let mut out = Vec::new();
    p.advance_to(t, &mut out);
    out
}

/// End of frame of `f` started at `start` at 125 kbit/s (8 µs a bit).
fn eof(f: &Frame, start: Nanos) -> Nanos {
    start + u64::from(frame_length(f).total - INTERMISSION_BITS) * 8 * US
}

#[test]
fn a_frame_reaches_every_other_port_at_its_end_and_is_confirmed_to_its_sender() {
    let mut p = Ports::new(125, 3).unwrap();
    let f = Frame::new(0x181, &[1, 2, 3, 4]).unwrap();
    p.submit(1, f, 100 * US).unwrap();
    let end = eof(&f, 100 * US);
    assert!(run(&mut p, end - 1).is_empty());
    assert_eq!(p.next_event(), Some(end));
    let ev = run(&mut p, end);
    assert_eq!(
        ev,
        vec![
            PortEvent {
                port: 1,
                at: end,
                kind: PortEventKind::Confirmed(f)
            },
            PortEvent {
                port: 0,
                at: end,
                kind: PortEventKind::Received(f)
            },
            PortEvent {
                port: 2,
                at: end,
                kind: PortEventKind::Received(f)
            },
        ]
    );
    assert_eq!(p.stats(1).unwrap().sent, 1);
}

#[test]
fn the_lower_identifier_wins_and_the_loser_is_told_and_retries() {
    let mut p = Ports::new(125, 3).unwrap();
    let hi = Frame::new(0x183, &[0; 8]).unwrap();
    let lo = Frame::new(0x182, &[0; 8]).unwrap();
    p.submit(2, hi, 0).unwrap();
    p.submit(1, lo, 0).unwrap();
    let ev = run(&mut p, 10_000 * US);
    let lost: Vec<_> = ev
        .iter()
        .filter(|e| matches!(e.kind, PortEventKind::ArbitrationLost { .. }))
        .collect();
    assert_eq!(
        lost,
        vec![&PortEvent {
            port: 2,
            at: 0,
            kind: PortEventKind::ArbitrationLost {
                frame: hi,
                discarded: false
            }
        }]
    );
    let confirmed: Vec<(usize, u32, Nanos)> = ev
        .iter()
        .filter_map(|e| match e.kind {
            PortEventKind::Confirmed(f) => Some((e.port, f.id(), e.at)),
            _ => None,
        })
        .collect();
    let first = eof(&lo, 0);
    // The loser starts after the winner's intermission (3 bits).
    assert_eq!(
        confirmed,
        vec![(1, 0x182, first), (2, 0x183, eof(&hi, first + 24 * US))]
    );
}

#[test]
fn discard_and_notify_takes_the_loser_off_the_bus() {
    let mut p = Ports::new(125, 3).unwrap();
    p.set_discard_on_loss(2, true);
    let hi = Frame::new(0x183, &[0; 8]).unwrap();
    let lo = Frame::new(0x182, &[0; 8]).unwrap();
    p.submit(2, hi, 0).unwrap();
    p.submit(1, lo, 0).unwrap();
    let ev = run(&mut p, 10_000 * US);
    assert!(ev.contains(&PortEvent {
        port: 2,
        at: 0,
        kind: PortEventKind::ArbitrationLost {
            frame: hi,
            discarded: true
        }
    }));
    assert!(!ev
        .iter()
        .any(|e| matches!(e.kind, PortEventKind::Received(f) if f == hi)));
    assert_eq!(p.stats(2).unwrap().queued, 0);
    assert_eq!(p.next_event(), None);
}

#[test]
fn a_duplicate_identifier_collides_every_port_hears_the_bus_error_and_the_senders_go_passive() {
    let mut p = Ports::new(125, 3).unwrap();
    let a = Frame::new(0x181, &[1]).unwrap();
    let b = Frame::new(0x181, &[2]).unwrap();
    let mut ev = Vec::new();
    for k in 0..16u64 {
        let t = k * 2_000 * US;
        p.advance_to(t, &mut ev);
        p.submit(0, a, t).unwrap();
        p.submit(1, b, t).unwrap();
    }
    p.advance_to(40_000 * US, &mut ev);
    let errors: Vec<&PortEvent> = ev
        .iter()
        .filter(|e| matches!(e.kind, PortEventKind::BusError { .. }))
        .collect();
    // 16 collisions, each told to all three ports, one primary each, the two senders marked.
    assert!(errors.len() >= 48, "{errors:?}");
    for e in errors.chunks(3).take(16) {
        let primaries = e
            .iter()
            .filter(|e| matches!(e.kind, PortEventKind::BusError { primary: true, .. }))
            .count();
        assert_eq!(primaries, 1, "{e:?}");
        for x in e {
            let PortEventKind::BusError {
                id,
                kind,
                is_sender,
                ..
            } = x.kind
            else {
                unreachable!()
            };
            assert_eq!((id, kind), (Some(0x181), BusErrorKind::Collision));
            assert_eq!(is_sender, x.port < 2, "{x:?}");
        }
    }
    // TEC + 8 per collision: error passive at the 16th, told to both senders.
    for port in 0..2 {
        assert!(
            ev.iter().any(|e| e.port == port
                && matches!(
                    e.kind,
                    PortEventKind::Status {
                        state: BusState::ErrorPassive,
                        tec: 128,
                        ..
                    }
                )),
            "{port}: {ev:?}"
        );
    }
}

#[test]
fn a_node_at_another_bit_rate_neither_sends_nor_receives() {
    let mut p = Ports::new(125, 2).unwrap();
    assert!(!p.configure_bitrate(1, 250_000));
    let f = Frame::new(0x181, &[1]).unwrap();
    p.submit(1, f, 0).unwrap();
    p.submit(0, Frame::new(0x000, &[1, 0]).unwrap(), 0).unwrap();
    let ev = run(&mut p, 20_000 * US);
    assert!(!ev.iter().any(
        |e| e.port == 1 && matches!(e.kind, PortEventKind::Received(_))
            || matches!(e.kind, PortEventKind::Received(g) if g == f)
    ));
    // Port 0's frame is not acknowledged by anyone: no confirmation either.
    assert!(!ev
        .iter()
        .any(|e| matches!(e.kind, PortEventKind::Confirmed(_))));
    // Its attempts are bit errors: error passive after 16, bus-off after 32.
    assert!(ev.iter().any(|e| e.port == 1
        && matches!(
            e.kind,
            PortEventKind::Status {
                state: BusState::BusOff,
                ..
            }
        )));
    // The bus's own rate restores it: it hears port 0's next frame.
    assert!(p.configure_bitrate(1, 125_000));
    let t = p.reached();
    p.submit(0, Frame::new(0x701, &[5]).unwrap(), t).unwrap();
    let ev = run(&mut p, t + 10_000 * US);
    assert!(ev.iter().any(
        |e| e.port == 1 && e.kind == PortEventKind::Received(Frame::new(0x701, &[5]).unwrap())
    ));
}

#[test]
fn a_node_that_reported_bus_off_is_refused_and_alone_confirms_nothing() {
    let mut p = Ports::new(125, 2).unwrap();
    p.report_status(1, BusState::BusOff);
    assert_eq!(
        p.submit(1, Frame::new(0x181, &[]).unwrap(), 0),
        Err(SubmitError::BusOff)
    );
    assert_eq!(p.refused_bus_off(), 1);
    p.submit(0, Frame::new(0x000, &[1, 0]).unwrap(), 0).unwrap();
    assert!(run(&mut p, 10_000 * US).is_empty());
    p.report_status(1, BusState::ErrorActive);
    p.submit(0, Frame::new(0x000, &[1, 0]).unwrap(), 10_000 * US)
        .unwrap();
    let ev = run(&mut p, 20_000 * US);
    assert_eq!(ev.len(), 2, "{ev:?}");
}

#[test]
fn bad_calls_are_refused_and_change_nothing() {
    assert!(Ports::new(125, 0).is_err());
    assert!(Ports::new(125, MAX_PORTS + 1).is_err());
    assert!(Ports::new(123, 2).is_err());
    let mut p = Ports::new(125, 2).unwrap();
    let f = Frame::new(1, &[]).unwrap();
    assert_eq!(p.submit(2, f, 0), Err(SubmitError::NoPort(2)));
    run(&mut p, 1_000);
    assert_eq!(
        p.submit(0, f, 999),
        Err(SubmitError::InThePast {
            at: 999,
            reached: 1_000
        })
    );
    // Back in time: nothing moves.
    assert!(run(&mut p, 10).is_empty());
    assert_eq!(p.reached(), 1_000);
    assert_eq!(p.stats(0).unwrap().queued, 0);
}

/// One scene: port 0 a master (NMT start, SDO requests), ports 1–3 sensors sending 8-byte
/// TPDOs every `period` µs from different phases, data from a fixed generator; stepped by
/// 250 µs for 120 ms. Returns what each port does at step k: frames to send at that time.
fn scene(period: u64) -> Vec<Vec<(usize, Frame)>> {
    let mut x: u32 = 0x1234_5678;
    let mut rnd = move || {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        x
    };
    let mut steps = Vec::new();
    for k in 0..480u64 {
        let t = k * 250;
        let mut now = Vec::new();
        if k == 0 {
            now.push((0, Frame::new(0, &[1, 0]).unwrap()));
        }
        if k % 37 == 5 {
            now.push((
                0,
                Frame::new(0x602, &[0x40, 0x18, 0x10, 1, 0, 0, 0, 0]).unwrap(),
            ));
        }
        for s in 1..=3u64 {
            if t >= 1_000 && (t + s * 250) % period == 0 {
                let v = rnd().to_le_bytes();
                let w = rnd().to_le_bytes();
                let data = [v[0], v[1], v[2], v[3], w[0], w[1], w[2], w[3]];
                now.push((s as usize, Frame::new(0x180 + s as u16, &data).unwrap()));
            }
        }
        steps.push(now);
    }
    steps
}

/// (receiving port, frame, end of frame ns) of every delivery, in order.
type Log = Vec<(usize, Frame, Nanos)>;

fn through_ports(steps: &[Vec<(usize, Frame)>]) -> (Log, u64) {
    let mut p = Ports::new(125, 4).unwrap();
    let mut log = Log::new();
    let mut ev = Vec::new();
    for (k, now) in steps.iter().enumerate() {
        let t = k as u64 * 250 * US;
        p.advance_to(t, &mut ev);
        for &(port, f) in now {
            // A full queue loses the frame, as on the in-process bus.
            let _ = p.submit(port, f, t);
        }
    }
    p.advance_to(steps.len() as u64 * 250 * US, &mut ev);
    for e in ev {
        if let PortEventKind::Received(f) = e.kind {
            log.push((e.port, f, e.at));
        }
    }
    let lost = (0..4).map(|i| p.stats(i).unwrap().lost_overflow).sum();
    (log, lost)
}

fn through_mem(steps: &[Vec<(usize, Frame)>]) -> Log {
    use crate::can::Transport;
    use crate::clock::SimClock;
    use crate::mem::MemBus;
    let clock = SimClock::stepped();
    let bus = MemBus::with_clock(125, clock.clone()).with_queue_len(100_000);
    let mut ports: Vec<_> = (0..4).map(|_| bus.attach()).collect();
    let mut log = Log::new();
    let drain = |ports: &mut Vec<crate::mem::MemPort>, log: &mut Log| {
        for (i, port) in ports.iter_mut().enumerate() {
            port.sync_bus();
            while let Some(rx) = port.try_recv().unwrap() {
                log.push((i, rx.frame, clock.nanos_of(rx.timestamp).unwrap()));
            }
        }
    };
    // The bus waits at t − 1 ns while the ports hand in their frames of time t, so those all
    // join their queues at t (docs/CLOCK.md: frames stamped ahead of the bus are kept), as
    // the nodes of a co-simulation step hand theirs in before the bus moves on.
    let hold = clock.participant("scene");
    for (k, now) in steps.iter().enumerate() {
        let t = k as u64 * 250 * US;
        hold.set(t.saturating_sub(1));
        clock.step_to(t).unwrap();
        drain(&mut ports, &mut log);
        for &(port, f) in now {
            let _ = ports[port].send(&f);
        }
    }
    drop(hold);
    clock.step_to(steps.len() as u64 * 250 * US).unwrap();
    drain(&mut ports, &mut log);
    // The same order as the ports report: by end of frame, then port.
    log.sort_by_key(|&(port, _, end)| (end, port));
    log
}

/// The engine of the bus-simulation FMU and the in-process bus carry one scene alike: the
/// same frames reach the same ports in the same order at the same end-of-frame times, on a
/// light bus and on an overloaded one (three 8-byte TPDOs per 1 ms at 125 kbit/s, more than
/// the bus carries: the sensors' queues fill and lose frames the same way).
#[test]
fn the_same_scene_on_a_mem_bus_gives_the_same_frames() {
    for period in [5_000, 1_000] {
        let steps = scene(period);
        let (ports, lost) = through_ports(&steps);
        let mem = through_mem(&steps);
        // The overloaded bus overflows the sensors' queues; the light one does not.
        assert_eq!(lost > 0, period == 1_000, "{period}: {lost} lost");
        assert!(ports.len() > 100, "{period}: {} deliveries", ports.len());
        assert_eq!(ports.len(), mem.len(), "{period}");
        for (i, (a, b)) in ports.iter().zip(&mem).enumerate() {
            assert_eq!(a, b, "{period}: delivery {i}");
        }
    }
}

/// A step that ends exactly where the bus becomes free: the frames its nodes hand in at that
/// time take part in the arbitration there with the frame that was already waiting (a
/// controller that is ready when the intermission ends takes part), so the lower identifier
/// handed in at the boundary goes first.
#[test]
fn frames_handed_in_at_a_step_boundary_join_the_arbitration_due_there() {
    let mut p = Ports::new(125, 4).unwrap();
    let a = Frame::new(0x300, &[0; 8]).unwrap();
    let b = Frame::new(0x200, &[0; 8]).unwrap();
    let c = Frame::new(0x100, &[1]).unwrap();
    p.submit(1, a, 0).unwrap();
    let mut ev = Vec::new();
    p.advance_to(10 * US, &mut ev);
    p.submit(2, b, 10 * US).unwrap();
    // The bus is free after A's intermission: a step ends exactly there.
    let free = p.timeline.frame_time(&a);
    assert_eq!(p.run_until(free, &mut ev), eof(&a, 0));
    p.advance_to(free, &mut ev);
    assert_eq!(p.next_event(), Some(free), "the arbitration waits");
    p.submit(3, c, free).unwrap();
    let mut order = Vec::new();
    while let Some(t) = p.next_event() {
        let mut ev = Vec::new();
        p.run_until(t + 10_000 * US, &mut ev);
        order.extend(ev.into_iter().filter_map(|e| match e.kind {
            PortEventKind::Confirmed(f) => Some((f.id(), e.at)),
            _ => None,
        }));
    }
    assert_eq!(
        order,
        vec![
            (0x100, eof(&c, free)),
            (0x200, eof(&b, eof(&c, free) + 24 * US))
        ]
    );
}
