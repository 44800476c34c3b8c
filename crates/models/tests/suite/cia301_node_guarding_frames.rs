//! CiA 301 §7.2.8.3.1 node guarding: which frames on the guarding COB-ID are guard requests
//! (an RTR, or where a transport has no RTR a zero-length data frame, D11 / D22), and that a
//! model without node guarding (the TMI: heartbeat only) answers none.

use crate::common::{booted, hex, Rig};
use canpos_models::th::TH;
use canpos_stack::Frame;

/// The frames the node answers `f` with at once.
fn answer(r: &mut Rig, f: Frame) -> Vec<Frame> {
    r.node.handle_frame(&f, r.now);
    r.take()
}

/// An RTR on 0x700 + node-id and a zero-length data frame (socketcand has no RTR, D22) are both
/// guard requests: one reply, state byte with the toggle.
#[test]
fn cia301_7_2_8_3_1_rtr_and_zero_length_data_frame_are_guard_requests() {
    let mut r = Rig::booted(&TH);
    let rtr = answer(&mut r, Frame::remote(0x77F, false, 1).unwrap());
    assert_eq!(rtr.len(), 1);
    assert_eq!((rtr[0].std_id(), rtr[0].data()), (Some(0x77F), &[0x7F][..]));
    let empty = answer(&mut r, Frame::new(0x77F, &[]).unwrap());
    assert_eq!(
        empty.len(),
        1,
        "a DLC-0 data frame is a guard request (D22)"
    );
    assert_eq!(empty[0].data(), [0xFF], "toggled");
}

/// A data frame with data on the guarding COB-ID is not a guard request (it is a heartbeat or
/// guarding reply, e.g. of a node with the same id): no answer, and the toggle does not move.
#[test]
fn cia301_7_2_8_3_1_a_data_frame_with_data_is_no_guard_request() {
    let mut r = Rig::booted(&TH);
    assert!(answer(&mut r, Frame::new(0x77F, &[0x05]).unwrap()).is_empty());
    let rtr = answer(&mut r, Frame::remote(0x77F, false, 1).unwrap());
    assert_eq!(rtr[0].data(), [0x7F], "toggle still 0");
}

/// TMI: the manual's error control is the heartbeat only; guard requests get no answer and
/// start no life guarding.
#[test]
fn tmi_has_no_node_guarding() {
    let mut r = booted("tmi");
    assert!(answer(&mut r, Frame::remote(0x77F, false, 1).unwrap()).is_empty());
    assert!(answer(&mut r, Frame::new(0x77F, &[]).unwrap()).is_empty());
    // Still served otherwise.
    assert_eq!(r.req(0x67F, &hex("40 00 10 00 00 00 00 00")).0, 0x5FF);
}
