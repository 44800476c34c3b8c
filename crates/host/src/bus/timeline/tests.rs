//! The timeline on a virtual clock: times are computed by hand from the bit lengths.

use super::*;

const US: Nanos = 1000;

fn bus(kbps: u32) -> Timeline {
    Timeline::new(kbps).unwrap()
}

fn frames(ev: &[BusEvent]) -> Vec<(u32, Nanos, Nanos, MemberId)> {
    ev.iter()
        .filter_map(|e| match e {
            BusEvent::Frame {
                frame,
                start,
                end,
                from,
                ..
            } => Some((frame.id(), *start, *end, *from)),
            _ => None,
        })
        .collect()
}

fn run(t: &mut Timeline, until: Nanos) -> Vec<BusEvent> {
    let mut out = Vec::new();
    t.advance(until, &mut out);
    out
}

#[test]
fn rejects_bit_rates_outside_cia_301() {
    assert!(Timeline::new(125).is_ok());
    let e = Timeline::new(123).unwrap_err();
    assert!(e.contains("not a CiA 301 bit rate"), "{e}");
    assert!(Timeline::new(0).is_err());
}

#[test]
fn one_frame_takes_its_bit_time() {
    // ID 0x000, DLC 0 is 53 bits (bits.rs): at 125 kbit/s (8 µs a bit) EOF ends after 50 bits,
    // 400 µs; the bus is free again after the 3-bit intermission, at 424 µs.
    let mut t = bus(125);
    let a = t.join(4);
    t.submit(a, Frame::new(0, &[]).unwrap(), 0).unwrap();
    assert!(frames(&run(&mut t, 399 * US)).is_empty());
    assert_eq!(t.next_event(), Some(400 * US));
    let f = frames(&run(&mut t, 400 * US));
    assert_eq!(f, vec![(0, 0, 400 * US, a)]);
    // A frame submitted during the intermission starts at its end.
    t.submit(a, Frame::new(0, &[]).unwrap(), 410 * US).unwrap();
    let f = frames(&run(&mut t, 10_000 * US));
    assert_eq!(f, vec![(0, 424 * US, 824 * US, a)]);
}

#[test]
fn lowest_identifier_wins_and_the_loser_retries_next_intermission() {
    // While A's 0x300 is on the wire, B queues 0x200 and C 0x100. At the end of the
    // intermission C wins, then B: one at a time, lowest identifier first.
    let mut t = bus(1000);
    let (a, b, c) = (t.join(4), t.join(4), t.join(4));
    t.submit(a, Frame::new(0x300, &[]).unwrap(), 0).unwrap();
    t.submit(b, Frame::new(0x200, &[]).unwrap(), 5 * US)
        .unwrap();
    t.submit(c, Frame::new(0x100, &[]).unwrap(), 6 * US)
        .unwrap();
    let f = frames(&run(&mut t, 1_000 * US));
    let ids: Vec<u32> = f.iter().map(|x| x.0).collect();
    assert_eq!(ids, vec![0x300, 0x100, 0x200]);
    // Each starts exactly when the previous frame's intermission ends.
    for w in f.windows(2) {
        assert_eq!(w[1].1, w[0].2 + 3 * US, "{f:?}");
    }
    assert_eq!(t.stats(b).unwrap().last_wait, f[2].1 - 5 * US);
}

#[test]
fn a_controller_drains_its_own_queue_by_priority_or_in_order() {
    // One controller queues 0x300, 0x200, 0x100 (a queue of 3), then 0x050, all before the
    // bus runs. A sensor's peripheral (priority) keeps its most important frames (0x050 evicts
    // 0x300) and sends lowest identifier first; a host's SocketCAN interface (FIFO) sends them
    // as queued and drops the new frame that does not fit.
    for (order, want, fourth_queued) in [
        (TxOrder::Priority, vec![0x050, 0x100, 0x200], true),
        (TxOrder::Fifo, vec![0x300, 0x200, 0x100], false),
    ] {
        let mut t = bus(1000);
        let a = t.join_with(3, order);
        for id in [0x300, 0x200, 0x100] {
            t.submit(a, Frame::new(id, &[]).unwrap(), 0).unwrap();
        }
        let fourth = t.submit(a, Frame::new(0x050, &[]).unwrap(), 0);
        assert_eq!(fourth.is_ok(), fourth_queued, "{order:?}");
        let ids: Vec<u32> = frames(&run(&mut t, 1_000 * US))
            .iter()
            .map(|x| x.0)
            .collect();
        assert_eq!(ids, want, "{order:?}");
        assert_eq!(t.stats(a).unwrap().lost_overflow, 1);
    }
}

#[test]
fn timestamps_are_monotonic_and_frames_never_overlap() {
    let mut t = bus(125);
    let members: Vec<MemberId> = (0..4).map(|_| t.join(8)).collect();
    let mut out = Vec::new();
    // Four producers at 1 ms on 125 kbit/s: far more than the bus carries.
    for ms in 0..200u64 {
        for (k, &m) in members.iter().enumerate() {
            let f = Frame::new(0x181 + k as u16, &[ms as u8; 8]).unwrap();
            let _ = t.submit(m, f, ms * 1000 * US + k as u64 * 7 * US);
        }
        t.advance(ms * 1000 * US + 999 * US, &mut out);
    }
    let f = frames(&out);
    for w in f.windows(2) {
        assert!(w[1].2 > w[0].2, "timestamps go backwards: {w:?}");
        assert!(w[1].1 >= w[0].2 + 3 * t.bit_time(), "overlap: {w:?}");
    }
    // ≤ the physical limit: no 8-byte frame is shorter than 111 bits (888 µs at 125 kbit/s).
    assert!(f.len() as u64 <= 200_000 / 888 + 1, "{}", f.len());
    let (load, fps) = t.load(200_000 * US);
    assert!(load > 0.95, "load {load}");
    assert!(fps > 900.0 && fps < 1126.0, "{fps}");
    let lost: u64 = members
        .iter()
        .map(|&m| t.stats(m).unwrap().lost_overflow)
        .sum();
    assert!(lost > 500, "{lost}");
}

#[test]
fn full_queue_keeps_the_most_important_frames() {
    let mut t = bus(125);
    let a = t.join(2);
    let pdo = |b| Frame::new(0x181, &[b]).unwrap();
    t.submit(a, pdo(1), 0).unwrap();
    t.submit(a, pdo(2), 0).unwrap();
    assert_eq!(t.submit(a, pdo(3), 0), Err(Rejected::QueueFull));
    let emcy = Frame::new(0x081, &[0x10, 0x81, 0x11, 0, 0, 0, 0, 0]).unwrap();
    // The EMCY takes the place of the newest PDO, which is lost and counted.
    assert_eq!(t.submit(a, emcy, 0), Ok(Accepted::Evicted(pdo(2))));
    assert_eq!(t.stats(a).unwrap().lost_overflow, 2);
    let ids: Vec<u32> = frames(&run(&mut t, 10_000 * US))
        .iter()
        .map(|x| x.0)
        .collect();
    assert_eq!(ids, vec![0x081, 0x181]);
}

#[test]
fn same_identifier_different_data_is_a_collision_for_both() {
    let mut t = bus(1000);
    let (a, b) = (t.join(4), t.join(4));
    t.submit(a, Frame::new(0x185, &[1]).unwrap(), 0).unwrap();
    t.submit(b, Frame::new(0x185, &[2]).unwrap(), 0).unwrap();
    let mut out = Vec::new();
    t.advance(50 * US, &mut out);
    let err = out
        .iter()
        .find_map(|e| match e {
            BusEvent::Error(x) => Some(x.clone()),
            _ => None,
        })
        .expect("an error frame");
    assert_eq!(err.kind, BusErrorKind::Collision);
    assert_eq!(err.transmitters, vec![a, b]);
    assert_eq!(t.stats(a).unwrap().tec, 8);
    assert_eq!(t.stats(b).unwrap().tec, 8);
    assert_eq!(t.stats(a).unwrap().collisions, 1);
    // Identical frames from two members are one frame, and no error.
    let mut t = bus(1000);
    let (a, b, c) = (t.join(4), t.join(4), t.join(4));
    t.submit(a, Frame::new(0x701, &[0]).unwrap(), 0).unwrap();
    t.submit(b, Frame::new(0x701, &[0]).unwrap(), 0).unwrap();
    let ev = run(&mut t, 1_000 * US);
    assert_eq!(frames(&ev).len(), 1);
    assert_eq!(t.stats(a).unwrap().tec, 0);
    assert_eq!(t.stats(c).unwrap().rec, 0);
}

#[test]
fn duplicate_senders_collide_until_error_passive() {
    // Both keep sending 0x185 with different data: while both are error active every
    // collision costs both 8, so both are error passive together at 128. From then on the
    // one sending recessive at the first differing bit (data 0x02 against 0x01: bit 6 of the
    // byte) has a bit error alone whenever they meet: its passive flag is recessive and the
    // other's frame goes through (TEC − 1), so only that one keeps collecting errors.
    let mut t = bus(1000);
    let (a, b) = (t.join(1), t.join(1));
    let mut out = Vec::new();
    let mut now = 0;
    for _ in 0..400u64 {
        let _ = t.submit(a, Frame::new(0x185, &[1]).unwrap(), now);
        let _ = t.submit(b, Frame::new(0x185, &[2]).unwrap(), now);
        now += 50 * US;
        t.advance(now, &mut out);
    }
    let states: Vec<(MemberId, BusState, u16)> = out
        .iter()
        .filter_map(|e| match e {
            BusEvent::State {
                member, state, tec, ..
            } => Some((*member, *state, *tec)),
            _ => None,
        })
        .collect();
    assert_eq!(
        states[..2],
        [
            (a, BusState::ErrorPassive, 128),
            (b, BusState::ErrorPassive, 128),
        ],
        "{states:?}"
    );
    let (sa, sb) = (t.stats(a).unwrap(), t.stats(b).unwrap());
    assert!(
        sa.collisions >= 16 && sb.collisions > sa.collisions,
        "{sa:?} {sb:?}"
    );
    assert!(sa.sent > 100, "{sa:?}");
}

#[test]
fn corrupted_frames_raise_counters_to_error_passive() {
    // Every frame corrupted: TEC + 8 per attempt, so error passive after 16 attempts (128) and
    // bus-off after 32 (256); each receiver's REC + 1 per error frame.
    let mut t = bus(500);
    let (a, r) = (t.join(4), t.join(4));
    t.set_corruption(1_000_000).unwrap();
    t.submit(a, Frame::new(0x181, &[0; 8]).unwrap(), 0).unwrap();
    let mut out = Vec::new();
    t.advance(1_000_000 * US, &mut out);
    let mut seen = Vec::new();
    for e in &out {
        if let BusEvent::State {
            member, state, tec, ..
        } = e
        {
            seen.push((*member, *state, *tec));
        }
    }
    assert_eq!(
        seen,
        vec![
            (a, BusState::ErrorPassive, 128),
            (a, BusState::BusOff, 256),
            (a, BusState::ErrorActive, 0)
        ]
    );
    let errors = out
        .iter()
        .filter(|e| matches!(e, BusEvent::Error(_)))
        .count();
    assert_eq!(errors, 32);
    assert_eq!(t.stats(r).unwrap().rec, 32);
    // Rates above one million per million are refused and change nothing.
    assert!(t.set_corruption(1_000_001).is_err());
    assert_eq!(t.corruption(), 1_000_000);
}

#[test]
fn bus_off_recovers_after_128_times_11_recessive_bits() {
    // A failed transceiver: 32 attempts, each a bit error at SOF (1 + 14 bits error frame + 3
    // intermission = 18 bits; from the 17th attempt, error passive, 8 more suspend bits).
    let mut t = bus(125);
    let a = t.join(4);
    t.set_transceiver_failed(a, true, 0);
    t.submit(a, Frame::new(0x181, &[1]).unwrap(), 0).unwrap();
    let mut out = Vec::new();
    t.advance(1_000_000 * US, &mut out);
    let at = |want: BusState| {
        out.iter()
            .find_map(|e| match e {
                BusEvent::State { state, at, .. } if *state == want => Some(*at),
                _ => None,
            })
            .unwrap()
    };
    let bit = 8 * US;
    // Passive at the end of the 16th attempt: 15 attempts of 18 bits, plus 15 bits.
    assert_eq!(at(BusState::ErrorPassive), (15 * 18 + 15) * bit);
    // Bus-off at the end of the 32nd: 16 × 18 + 15 × 26 + 15.
    let off = (16 * 18 + 15 * 26 + 15) * bit;
    assert_eq!(at(BusState::BusOff), off);
    // Idle bus: error active again 128 × 11 bits later.
    assert_eq!(at(BusState::ErrorActive), off + 128 * 11 * bit);
    // While bus-off, its frames are refused and counted.
    let mut t2 = bus(125);
    let b = t2.join(4);
    t2.set_transceiver_failed(b, true, 0);
    t2.submit(b, Frame::new(0x181, &[1]).unwrap(), 0).unwrap();
    t2.advance(off, &mut Vec::new());
    assert_eq!(
        t2.submit(b, Frame::new(0x181, &[2]).unwrap(), off),
        Err(Rejected::BusOff)
    );
    assert!(t2.stats(b).unwrap().lost_bus_off >= 1);
}

#[test]
fn busy_bus_counts_recovery_sequences_per_frame() {
    // Each frame ends with 11 recessive bits (ACK delimiter, EOF, intermission): a bus-off
    // node on a busy bus recovers after about 128 frames, not after 128 × 11 bit times.
    let mut t = bus(1000);
    let (a, talker) = (t.join(4), t.join(400));
    t.set_transceiver_failed(a, true, 0);
    t.submit(a, Frame::new(0x181, &[1]).unwrap(), 0).unwrap();
    for i in 0..300u16 {
        t.submit(talker, Frame::new(0x200, &[i as u8; 8]).unwrap(), 0)
            .unwrap();
    }
    let mut out = Vec::new();
    let mut now = 0;
    while now < 100_000 * US {
        now += 10 * US;
        t.advance(now, &mut out);
    }
    let at = |want: BusState| {
        out.iter()
            .find_map(|e| match e {
                BusEvent::State { state, at, .. } if *state == want => Some(*at),
                _ => None,
            })
            .unwrap()
    };
    let (off, on) = (at(BusState::BusOff), at(BusState::ErrorActive));
    let between = frames(&out)
        .iter()
        .filter(|f| f.2 > off && f.2 <= on)
        .count();
    assert!((126..=129).contains(&between), "{between}");
}

#[test]
fn stuck_dominant_raises_every_counter() {
    // 1000 bit times dominant: 1 + (1000 − 14) / 8 = 124 steps of 8 after the first error:
    // receivers 1 + 992 → capped at 255 (error passive); the transmitter of the destroyed
    // frame 8 + 992 → bus-off.
    let mut t = bus(1000);
    let (a, r) = (t.join(4), t.join(4));
    t.submit(a, Frame::new(0x181, &[0; 8]).unwrap(), 0).unwrap();
    t.stuck_dominant(20 * US, 1000 * US).unwrap();
    assert!(t.stuck_dominant(0, 1000 * US).is_err());
    let mut out = Vec::new();
    t.advance(500 * US, &mut out);
    assert!(
        out.is_empty(),
        "nothing is reported before the interval is over"
    );
    t.advance(1_100 * US, &mut out);
    assert!(out.iter().any(|e| matches!(
        e,
        BusEvent::Error(BusError {
            kind: BusErrorKind::StuckDominant { bits: 1000 },
            ..
        })
    )));
    assert_eq!(t.stats(a).unwrap().state, BusState::BusOff);
    assert_eq!(t.stats(r).unwrap().state, BusState::ErrorPassive);
    assert_eq!(t.stats(r).unwrap().rec, 255);
    // Out of range: nothing changes.
    let mut t = bus(1000);
    assert!(t.stuck_dominant(0, 0).is_err());
    assert!(t.stuck_dominant(0, MAX_STUCK + 1).is_err());
    assert_eq!(t.next_event(), None);
}

#[test]
fn receive_counter_decrements_after_good_frames() {
    let mut t = bus(1000);
    let (a, r) = (t.join(4), t.join(4));
    t.set_corruption(1_000_000).unwrap();
    t.submit(a, Frame::new(0x181, &[0]).unwrap(), 0).unwrap();
    let mut out = Vec::new();
    t.advance(100 * US, &mut out);
    t.set_corruption(0).unwrap();
    t.advance(1_000 * US, &mut out);
    let errors = out
        .iter()
        .filter(|e| matches!(e, BusEvent::Error(_)))
        .count() as u16;
    assert!(errors >= 1);
    // The retransmission got through: TEC − 1 for the sender, REC − 1 for the receiver.
    assert_eq!(t.stats(r).unwrap().rec, errors - 1);
    assert_eq!(t.stats(a).unwrap().tec, 8 * errors - 1);
    assert_eq!(t.stats(a).unwrap().sent, 1);
}

#[test]
fn an_error_flag_raises_every_receive_counter_and_no_state_latches() {
    // ISO 11898-1: every controller detects the flag (a stuff error), REC + 1 each; the flagging
    // member detected the error first (+ 1) and sees their flags after its own (+ 8). No
    // transmit counter moves on an idle bus.
    let mut t = bus(1000);
    let (flagger, a, b) = (t.join(4), t.join(4), t.join(4));
    let mut out = Vec::new();
    assert!(t.error_flag(flagger, 0));
    assert!(!t.error_flag(a, 0), "one error frame at a time");
    assert_eq!(t.error_flags_refused(), 1);
    t.advance(100 * US, &mut out);
    assert!(out.iter().any(|e| matches!(
        e,
        BusEvent::Error(BusError {
            kind: BusErrorKind::ErrorFlag,
            id: None,
            ..
        })
    )));
    for m in [a, b] {
        let s = t.stats(m).unwrap();
        assert_eq!((s.tec, s.rec, s.state), (0, 1, BusState::ErrorActive));
    }
    let s = t.stats(flagger).unwrap();
    assert_eq!((s.tec, s.rec, s.state), (0, 9, BusState::ErrorActive));
    // 14 more active flags make the flagger error passive at REC 135 (fault confinement does
    // what it is for: the member that keeps seeing errors goes passive first); the others are
    // at 15. From then on its flags are passive: nobody else sees them.
    let mut now = 100 * US;
    for _ in 0..14 {
        assert!(t.error_flag(flagger, now));
        now += 100 * US;
        t.advance(now, &mut out);
    }
    let s = t.stats(flagger).unwrap();
    assert_eq!((s.rec, s.state), (135, BusState::ErrorPassive));
    for _ in 0..1000 {
        assert!(t.error_flag(flagger, now), "a passive flag is no refusal");
        now += 100 * US;
        t.advance(now, &mut out);
    }
    for m in [a, b] {
        let s = t.stats(m).unwrap();
        assert_eq!((s.rec, s.state), (15, BusState::ErrorActive), "{m:?}");
    }
    assert_eq!(t.error_frames(), 15);
    assert_eq!(t.stats(flagger).unwrap().rec, 255);
    // Many flaggers, each flagging once: every receiver error passive at REC 128, none
    // bus-off (a receive counter never takes a controller off the bus).
    let mut t = bus(1000);
    let (a, b) = (t.join(4), t.join(4));
    let flaggers: Vec<_> = (0..128).map(|_| t.join(4)).collect();
    let mut now = 0;
    for &f in &flaggers {
        assert!(t.error_flag(f, now));
        now += 100 * US;
        t.advance(now, &mut out);
    }
    for m in [a, b] {
        let s = t.stats(m).unwrap();
        assert_eq!((s.rec, s.state), (128, BusState::ErrorPassive));
    }
    assert_eq!(t.error_frames(), 128);
    // Good frames bring them back (REC above 127 → 119: error active): nothing latched.
    t.submit(a, Frame::new(0x181, &[1]).unwrap(), now).unwrap();
    t.advance(now + 1_000 * US, &mut out);
    assert_eq!(t.stats(b).unwrap().state, BusState::ErrorActive);
    assert_eq!(t.stats(b).unwrap().rec, 119);
    // A flag that hits a frame on the wire destroys it: its transmitter TEC + 8, retransmitted.
    let mut t = bus(1000);
    let (flagger, a, r) = (t.join(4), t.join(4), t.join(4));
    t.submit(a, Frame::new(0x181, &[0; 8]).unwrap(), 0).unwrap();
    let mut out = Vec::new();
    t.advance(10 * US, &mut out);
    assert!(t.error_flag(flagger, 10 * US));
    t.advance(1_000 * US, &mut out);
    assert_eq!(t.stats(a).unwrap().tx_errors, 1);
    assert_eq!(
        t.stats(r).unwrap().rec,
        0,
        "1 for the flag, − 1 for the retransmission"
    );
    assert_eq!(frames(&out).len(), 1, "the frame went out again");
    // A member whose transceiver failed sends no flag (nor does a bus-off one).
    let mut t = bus(1000);
    let m = t.join(1);
    t.set_transceiver_failed(m, true, 0);
    assert!(!t.error_flag(m, 0));
}
