//! CiA 301 §7.2.8.3 error control: node guarding, life guarding and the heartbeat producer,
//! stated as rules on the wire (TH, node-id 0x7F: guarding 0x77F, EMCY 0x0FF).

use crate::common::{hex, Rig};
use canpos_models::th::TH;
use canpos_stack::Frame;

/// One guard request (an RTR frame on 0x77F); returns the reply bytes.
fn guard(r: &mut Rig) -> Vec<u8> {
    let f = Frame::remote(0x77F, false, 1).unwrap();
    r.node.handle_frame(&f, r.now);
    let out = r.take();
    assert_eq!(out.len(), 1, "one reply per guard request");
    out[0].data().to_vec()
}

fn life_guarding_emcys(frames: &[(canpos_stack::Instant, Frame)]) -> Vec<u64> {
    frames
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x0FF) && f.data()[..2] == [0x30, 0x81])
        .map(|(t, _)| t.micros())
        .collect()
}

/// §7.2.8.3.1: the life time is guard time × life time factor; either being 0 disables life
/// guarding, so guard requests are answered but never expected.
#[test]
fn cia301_7_2_8_3_1_guard_time_zero_disables_life_guarding() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 0C 10 00 00 00 00 00")); // guard time 0
    r.req(0x67F, &hex("2F 0D 10 00 03 00 00 00")); // factor 3
    guard(&mut r);
    assert!(life_guarding_emcys(&r.advance_ms(1000)).is_empty());

    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 0C 10 00 64 00 00 00")); // 100 ms
    r.req(0x67F, &hex("2F 0D 10 00 00 00 00 00")); // factor 0
    guard(&mut r);
    assert!(life_guarding_emcys(&r.advance_ms(1000)).is_empty());
}

/// §7.2.8.3.1: rewriting the guard time while guarding runs re-arms the life time from the write;
/// guarding does not stop.
#[test]
fn cia301_7_2_8_3_1_rewriting_guard_time_rearms_life_time() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 0C 10 00 64 00 00 00")); // 100 ms × 3 = 300 ms
    r.req(0x67F, &hex("2F 0D 10 00 03 00 00 00"));
    guard(&mut r);
    r.advance_ms(200);
    let t0 = r.now.micros();
    r.req(0x67F, &hex("2B 0C 10 00 64 00 00 00")); // same value, at t0
    let lost = life_guarding_emcys(&r.advance_ms(400));
    assert_eq!(lost.len(), 1, "life guarding still runs after the rewrite");
    assert!(
        lost[0] >= t0 + 300_000,
        "re-armed from the write: {} vs {}",
        lost[0],
        t0
    );
}

/// §7.2.8.3.1: the toggle bit starts at 0 after the node-guarding initialisation, i.e. after
/// every reset communication.
#[test]
fn cia301_7_2_8_3_1_toggle_restarts_at_zero_after_reset_communication() {
    let mut r = Rig::booted(&TH);
    assert_eq!(guard(&mut r), [0x7F]);
    r.send(0x000, &[0x82, 0x7F]); // reset communication with the toggle at 1: boot-up
    r.take();
    assert_eq!(guard(&mut r), [0x7F], "toggle 0 again");
    assert_eq!(guard(&mut r), [0xFF]);
}

/// §7.2.8.3.1: life guarding starts with the first guard request; a reset communication ends the
/// guarding that ran before it, so no life-guarding event follows until a new request arrives.
#[test]
fn cia301_7_2_8_3_1_reset_communication_ends_life_guarding_until_the_next_request() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 0C 10 00 64 00 00 00")); // 100 ms × 3
    r.req(0x67F, &hex("2F 0D 10 00 03 00 00 00"));
    // Save, so that the reset keeps them (the answer follows the write to storage).
    let saved = r.store_cmd(0x67F, &hex("23 10 10 01 73 61 76 65"), 100);
    assert!(saved
        .iter()
        .any(|(_, f)| f.std_id() == Some(0x5FF) && f.data()[0] == 0x60));
    guard(&mut r);
    r.send(0x000, &[0x82, 0x7F]);
    r.take();
    assert!(life_guarding_emcys(&r.advance_ms(1000)).is_empty());
    guard(&mut r);
    assert_eq!(
        life_guarding_emcys(&r.advance_ms(400)).len(),
        1,
        "armed again"
    );
}

/// Heartbeats on 0x77F, with the time the node produced them, from one late `handle_timeout`.
fn late_poll(r: &mut Rig, at_ms: u64) -> Vec<Frame> {
    r.now = canpos_stack::Instant::from_millis(at_ms);
    r.node.handle_timeout(r.now);
    r.take()
        .into_iter()
        .filter(|f| f.std_id() == Some(0x77F))
        .collect()
}

/// §7.2.8.3.2: the heartbeat producer keeps its own period. A host that serves the timer several
/// periods late gets one heartbeat (no burst of the missed ones), and the schedule stays on the
/// original grid: the next one is due at the next multiple of the period, not a period after the
/// late call.
#[test]
fn cia301_7_2_8_3_2_heartbeat_catch_up_sends_one_and_keeps_the_grid() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 17 10 00 64 00 00 00")); // 100 ms at t = 0: due 100, 200, ...
    assert_eq!(late_poll(&mut r, 350).len(), 1, "one heartbeat, not three");
    assert_eq!(
        r.node.poll_timeout().map(|t| t.micros()),
        Some(400_000),
        "next on the grid"
    );
    assert!(late_poll(&mut r, 399).is_empty());
    assert_eq!(late_poll(&mut r, 400).len(), 1);
    // Exactly on a grid point after being late: the grid point itself is the next one.
    assert_eq!(late_poll(&mut r, 700).len(), 1);
    assert_eq!(r.node.poll_timeout().map(|t| t.micros()), Some(800_000));
}
