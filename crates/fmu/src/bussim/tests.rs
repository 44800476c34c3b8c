//! The bus-simulation core with LS-BUS buffers, on co-simulation time.

use super::*;
use canpos_host::bus::bits::{frame_length, INTERMISSION_BITS};

const MS: Nanos = 1_000_000;

fn ops(list: &[Op<'_>]) -> Vec<u8> {
    let mut b = TxBuffer::new(4096);
    for op in list {
        b.push(op).unwrap();
    }
    b.bytes().to_vec()
}

fn transmit(id: u32, data: &[u8]) -> Op<'_> {
    Op::Transmit {
        id,
        ide: false,
        rtr: false,
        data,
        dlc: data.len() as u16,
    }
}

/// End of frame of a standard data frame started at `start` at 125 kbit/s.
fn eof(id: u16, data: &[u8], start: Nanos) -> Nanos {
    let f = Frame::new(id, data).unwrap();
    start + u64::from(frame_length(&f).total - INTERMISSION_BITS) * 8_000
}

fn got(b: &BusSim, port: usize) -> Vec<Op<'_>> {
    lsbus::parse(b.tx(port)).unwrap()
}

#[test]
fn a_transmit_reaches_the_other_nodes_at_its_end_of_frame_and_its_sender_is_confirmed() {
    let mut b = BusSim::new(3, 125).unwrap();
    let data = [0x40, 0x18, 0x10, 1, 0, 0, 0, 0];
    b.receive(0, &ops(&[transmit(0x602, &data)])).unwrap();
    let end = eof(0x602, &data, 0);
    assert_eq!(b.step(10 * MS, true), end);
    assert_eq!(got(&b, 0), vec![Op::Confirm { id: 0x602 }]);
    for port in 1..3 {
        assert_eq!(got(&b, port), vec![transmit(0x602, &data)]);
        assert!(b.tx_ticks(port));
    }
    b.clear_tx();
    assert_eq!(b.step(10 * MS, true), 10 * MS);
    assert!(!b.any_tx());
}

#[test]
fn a_remote_frame_is_carried_as_one() {
    let mut b = BusSim::new(2, 125).unwrap();
    let rtr = Op::Transmit {
        id: 0x701,
        ide: false,
        rtr: true,
        data: &[],
        dlc: 1,
    };
    b.receive(0, &ops(&[rtr])).unwrap();
    b.step(10 * MS, false);
    assert_eq!(got(&b, 1), vec![rtr]);
}

#[test]
fn without_early_return_a_step_collects_every_frame_of_it() {
    let mut b = BusSim::new(2, 125).unwrap();
    b.receive(0, &ops(&[transmit(0x181, &[1]), transmit(0x182, &[2])]))
        .unwrap();
    assert_eq!(b.step(10 * MS, false), 10 * MS);
    assert_eq!(
        got(&b, 1),
        vec![transmit(0x181, &[1]), transmit(0x182, &[2])]
    );
}

#[test]
fn discard_and_notify_answers_a_lost_arbitration_buffer_and_retransmit_does_not() {
    let mut b = BusSim::new(3, 125).unwrap();
    let cfg = Op::Configuration(Config::ArbitrationLost(
        ArbitrationLostBehavior::DiscardAndNotify,
    ));
    b.receive(2, &ops(&[cfg, transmit(0x183, &[3])])).unwrap();
    b.receive(1, &ops(&[transmit(0x182, &[2])])).unwrap();
    b.step(10 * MS, false);
    assert_eq!(
        got(&b, 2),
        vec![Op::ArbitrationLost { id: 0x183 }, transmit(0x182, &[2])]
    );
    assert!(!got(&b, 0).contains(&transmit(0x183, &[3])));
    // Buffered (the default): no Arbitration Lost, the frame follows the winner.
    let mut b = BusSim::new(3, 125).unwrap();
    b.receive(2, &ops(&[transmit(0x183, &[3])])).unwrap();
    b.receive(1, &ops(&[transmit(0x182, &[2])])).unwrap();
    b.step(10 * MS, false);
    assert_eq!(
        got(&b, 0),
        vec![transmit(0x182, &[2]), transmit(0x183, &[3])]
    );
    assert_eq!(
        got(&b, 2),
        vec![transmit(0x182, &[2]), Op::Confirm { id: 0x183 }]
    );
}

#[test]
fn two_senders_of_one_identifier_get_bus_errors_with_the_sender_and_primary_flags() {
    let mut b = BusSim::new(3, 125).unwrap();
    b.receive(0, &ops(&[transmit(0x181, &[1])])).unwrap();
    b.receive(1, &ops(&[transmit(0x181, &[2])])).unwrap();
    b.step(10 * MS, true);
    let mut primaries = 0;
    for port in 0..3 {
        let ops = got(&b, port);
        let Some(Op::BusError {
            id,
            code,
            primary,
            is_sender,
        }) = ops.first().copied()
        else {
            panic!("{port}: {ops:?}")
        };
        assert_eq!((id, code, is_sender), (0x181, BusErrorCode::Bit, port < 2));
        primaries += usize::from(primary);
    }
    assert_eq!(primaries, 1);
}

#[test]
fn a_can_fd_frame_gets_a_form_error_and_stays_off_the_bus() {
    let mut b = BusSim::new(2, 125).unwrap();
    let fd = Op::FdTransmit {
        id: 0x181,
        ide: false,
        data: &[0; 12],
    };
    let buf = {
        let mut t = TxBuffer::new(256);
        t.push(&fd).unwrap();
        t.bytes().to_vec()
    };
    b.receive(0, &buf).unwrap();
    assert_eq!(
        got(&b, 0),
        vec![Op::BusError {
            id: 0x181,
            code: BusErrorCode::Form,
            primary: false,
            is_sender: true
        }]
    );
    b.clear_tx();
    b.step(10 * MS, false);
    assert!(!b.any_tx());
    assert!(!b.take_log().is_empty());
}

#[test]
fn a_malformed_buffer_is_refused_whole() {
    let mut b = BusSim::new(2, 125).unwrap();
    let mut buf = ops(&[transmit(0x181, &[1])]);
    // A second operation whose length runs past the buffer.
    buf.extend_from_slice(&[0x10, 0, 0, 0, 0xFF, 0, 0, 0]);
    let e = b.receive(0, &buf).unwrap_err();
    assert!(e.contains("node 1") && e.contains("byte 17"), "{e}");
    b.step(10 * MS, false);
    assert!(!b.any_tx(), "nothing of it was taken");
    assert!(b.receive(2, &[]).is_err());
}

#[test]
fn a_wakeup_reaches_every_other_node_at_once() {
    let mut b = BusSim::new(3, 125).unwrap();
    b.receive(1, &ops(&[Op::Wakeup])).unwrap();
    assert!(!b.tx_ticks(1));
    assert_eq!(got(&b, 0), vec![Op::Wakeup]);
    assert_eq!(got(&b, 2), vec![Op::Wakeup]);
}

#[test]
fn a_node_at_another_bit_rate_is_cut_off_and_one_that_reported_bus_off_is_refused() {
    let mut b = BusSim::new(2, 125).unwrap();
    b.receive(1, &ops(&[Op::Configuration(Config::CanBaudrate(500_000))]))
        .unwrap();
    b.receive(0, &ops(&[transmit(0x181, &[1])])).unwrap();
    b.step(10 * MS, false);
    // Nobody could acknowledge it: no Confirm, and node 2 heard nothing.
    assert!(!b.any_tx());
    assert!(b.take_log().iter().any(|l| l.contains("500000 bit/s")));
    b.receive(1, &ops(&[Op::Configuration(Config::CanBaudrate(125_000))]))
        .unwrap();
    b.receive(1, &ops(&[Op::Status(CanStatus::BusOff)]))
        .unwrap();
    b.receive(1, &ops(&[transmit(0x182, &[2])])).unwrap();
    b.step(20 * MS, false);
    assert!(!b.any_tx());
    assert_eq!(b.ports().refused_bus_off(), 1);
}

#[test]
fn times_outside_the_co_simulation_are_refused() {
    assert_eq!(nanos(0.001), Some(MS));
    assert_eq!(nanos(-1.0), None);
    assert_eq!(nanos(f64::NAN), None);
    assert_eq!(nanos(f64::INFINITY), None);
}

#[test]
fn a_nodes_frames_of_one_buffer_go_out_in_order_on_a_free_bus_and_others_arbitrate() {
    // Node 1 hands in a boot-up and an EMCY together: the boot-up, handed in first, starts on
    // the free bus (as the in-process bus takes a controller's burst), then the EMCY.
    let mut b = BusSim::new(3, 125).unwrap();
    b.receive(0, &ops(&[transmit(0x701, &[0]), transmit(0x81, &[0; 8])]))
        .unwrap();
    b.step(20 * MS, false);
    assert_eq!(
        got(&b, 2),
        vec![transmit(0x701, &[0]), transmit(0x81, &[0; 8])]
    );
    // With node 2's TPDO at the same time, the nodes' first frames arbitrate: the TPDO wins,
    // then the EMCY beats the boot-up.
    let mut b = BusSim::new(3, 125).unwrap();
    b.receive(0, &ops(&[transmit(0x701, &[0]), transmit(0x81, &[0; 8])]))
        .unwrap();
    b.receive(1, &ops(&[transmit(0x182, &[1; 8])])).unwrap();
    b.step(20 * MS, false);
    assert_eq!(
        got(&b, 2),
        vec![
            transmit(0x182, &[1; 8]),
            transmit(0x81, &[0; 8]),
            transmit(0x701, &[0])
        ]
    );
}
