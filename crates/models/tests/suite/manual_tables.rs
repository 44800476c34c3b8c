//! The TH / E-Series manuals' example frames, reproduced byte-exact through the core
//! (node-id 0x7F: SDO 0x67F / 0x5FF, EMCY 0x0FF, TPDO1 0x1FF, error control 0x77F).

use crate::common::{hex, Rig};
use canpos_models::th::TH;
use canpos_stack::nmt::NmtState;
use canpos_stack::{Frame, Instant};

#[test]
fn bootup_table_3_is_0x77f_00_then_power_on_emcy() {
    let mut r = Rig::new(&TH);
    let f = r.take();
    // Boot-up (E Table 3): 0x700 + id, one byte 0x00.
    assert_eq!(f[0].std_id(), Some(0x77F));
    assert_eq!(f[0].data(), &[0x00]);
    // D14: the power-on EMCY "without reasonable data": code 0x0000, register, five zeros.
    assert_eq!(f[1].std_id(), Some(0x0FF));
    assert_eq!(f[1].data(), &hex("00 00 00 00 00 00 00 00")[..]);
    assert_eq!(f.len(), 2);
    assert_eq!(r.node.device().nmt_state(), NmtState::PreOperational);
}

#[test]
fn nmt_table_3_state_transitions() {
    let mut r = Rig::booted(&TH);
    // 0x01 start (addressed)
    assert!(r.send(0x000, &[0x01, 0x7F]).is_empty());
    assert_eq!(r.node.device().nmt_state(), NmtState::Operational);
    // 0x80 enter pre-operational (broadcast)
    r.send(0x000, &[0x80, 0x00]);
    assert_eq!(r.node.device().nmt_state(), NmtState::PreOperational);
    // 0x02 stop
    r.send(0x000, &[0x02, 0x7F]);
    assert_eq!(r.node.device().nmt_state(), NmtState::Stopped);
    // Stopped: SDO is not served.
    assert!(r.send(0x67F, &hex("40 00 10 00 00 00 00 00")).is_empty());
    // Another node's command is ignored.
    r.send(0x000, &[0x01, 0x05]);
    assert_eq!(r.node.device().nmt_state(), NmtState::Stopped);
    // 0x81 reset node: boot-up again, pre-operational.
    let f = r.send(0x000, &[0x81, 0x7F]);
    assert_eq!((f[0].std_id(), f[0].data()), (Some(0x77F), &[0u8][..]));
    assert_eq!(r.node.device().nmt_state(), NmtState::PreOperational);
    // 0x82 reset communication: boot-up again.
    let f = r.send(0x000, &[0x82, 0x00]);
    assert_eq!((f[0].std_id(), f[0].data()), (Some(0x77F), &[0u8][..]));
}

#[test]
fn reset_communication_reloads_comm_objects_keeps_application_state() {
    let mut r = Rig::booted(&TH);
    assert_eq!(
        r.req(0x67F, &hex("2B 17 10 00 64 00 00 00")).1,
        hex("60 17 10 00 00 00 00 00")
    );
    r.send(0x000, &[0x82, 0x7F]);
    // D6: 0x1017 back to its default (nothing stored).
    assert_eq!(
        r.req(0x67F, &hex("40 17 10 00 00 00 00 00")).1,
        hex("4B 17 10 00 00 00 00 00")
    );
}

#[test]
fn heartbeat_table_7_states_every_100ms() {
    let mut r = Rig::booted(&TH);
    // 0x1017 := 100 ms
    assert_eq!(
        r.req(0x67F, &hex("2B 17 10 00 64 00 00 00")).1,
        hex("60 17 10 00 00 00 00 00")
    );
    let f = r.advance_ms(1000);
    let hb: Vec<_> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x77F))
        .collect();
    assert_eq!(hb.len(), 10, "one heartbeat per 100 ms");
    for (i, (t, fr)) in hb.iter().enumerate() {
        assert_eq!(
            t.micros(),
            (i as u64 + 1) * 100_000,
            "absolute schedule, no drift"
        );
        assert_eq!(fr.data(), &[0x7F], "pre-operational");
    }
    r.send(0x000, &[0x01, 0x7F]);
    let f = r.advance_ms(100);
    assert!(
        f.iter()
            .any(|(_, f)| f.std_id() == Some(0x77F) && f.data() == [0x05]),
        "operational"
    );
    r.send(0x000, &[0x02, 0x7F]);
    let f = r.advance_ms(100);
    let hb: Vec<_> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x77F))
        .collect();
    assert_eq!(hb.len(), 1);
    assert_eq!(hb[0].1.data(), &[0x04], "stopped: heartbeat still runs");
    assert!(
        f.iter().all(|(_, f)| f.std_id() == Some(0x77F)),
        "stopped: nothing but heartbeat"
    );
}

#[test]
fn tpdo_configuration_example_4() {
    let mut r = Rig::booted(&TH);
    let q = |r: &mut Rig, s: &str| r.req(0x67F, &hex(s)).1;
    assert_eq!(
        q(&mut r, "23 00 18 01 FF 01 00 40"),
        hex("60 00 18 01 00 00 00 00")
    );
    assert_eq!(
        q(&mut r, "40 00 18 01 00 00 00 00"),
        hex("43 00 18 01 FF 01 00 40")
    );
    assert_eq!(
        q(&mut r, "2F 00 18 02 FE 00 00 00"),
        hex("60 00 18 02 00 00 00 00")
    );
    assert_eq!(
        q(&mut r, "40 00 18 02 00 00 00 00"),
        hex("4F 00 18 02 FE 00 00 00")
    );
    assert_eq!(
        q(&mut r, "2B 00 18 05 01 00 00 00"),
        hex("60 00 18 05 00 00 00 00")
    );
    assert_eq!(
        q(&mut r, "40 00 18 05 00 00 00 00"),
        hex("4B 00 18 05 01 00 00 00")
    );
}

#[test]
fn pdo_mapping_example_5_th() {
    let mut r = Rig::booted(&TH);
    let q = |r: &mut Rig, s: &str| r.req(0x67F, &hex(s)).1;
    assert_eq!(
        q(&mut r, "40 00 1A 00 00 00 00 00"),
        hex("4F 00 1A 00 03 00 00 00")
    );
    assert_eq!(
        q(&mut r, "2F 00 1A 00 00 00 00 00"),
        hex("60 00 1A 00 00 00 00 00")
    );
    assert_eq!(
        q(&mut r, "23 00 1A 01 20 01 20 60"),
        hex("60 00 1A 01 00 00 00 00")
    );
    assert_eq!(
        q(&mut r, "40 00 1A 01 00 00 00 00"),
        hex("43 00 1A 01 20 01 20 60")
    );
    assert_eq!(
        q(&mut r, "23 00 1A 02 10 01 30 60"),
        hex("60 00 1A 02 00 00 00 00")
    );
    assert_eq!(
        q(&mut r, "40 00 1A 02 00 00 00 00"),
        hex("43 00 1A 02 10 01 30 60")
    );
    assert_eq!(
        q(&mut r, "23 00 1A 03 08 01 00 63"),
        hex("60 00 1A 03 00 00 00 00")
    );
    assert_eq!(
        q(&mut r, "40 00 1A 03 00 00 00 00"),
        hex("43 00 1A 03 08 01 00 63")
    );
    assert_eq!(
        q(&mut r, "2F 00 1A 00 03 00 00 00"),
        hex("60 00 1A 00 00 00 00 00")
    );
    assert_eq!(
        q(&mut r, "40 00 1A 00 00 00 00 00"),
        hex("4F 00 1A 00 03 00 00 00")
    );
    // The remapped PDO goes out with 7 bytes once operational.
    r.send(0x000, &[0x01, 0x7F]);
    let f = r.advance_ms(1);
    let p: Vec<_> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x1FF))
        .collect();
    assert_eq!(p.len(), 1);
    assert_eq!(p[0].1.dlc(), 7);
}

#[test]
fn store_table_13_answers_and_survives_power_cycle() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 17 10 00 64 00 00 00"));
    // Store: the answer comes after the write completed (the 20 ms a simulated device holds it,
    // D7, are the host's: `canpos-host`, `store_table_13_answers_after_20ms`).
    let t0 = r.now;
    let f = r.store_cmd(0x67F, &hex("22 10 10 01 73 61 76 65"), 20);
    let ans: Vec<_> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x5FF))
        .collect();
    assert_eq!(ans.len(), 1);
    assert_eq!(ans[0].1.data(), &hex("60 10 10 01 00 00 00 00")[..]);
    // The core answers as soon as the store returns (a firmware's store takes its own time).
    assert_eq!(ans[0].0.micros() - t0.micros(), 0);
    // Reading 0x1010/1 reports "saves on command".
    assert_eq!(
        r.req(0x67F, &hex("40 10 10 01 00 00 00 00")).1,
        hex("43 10 10 01 01 00 00 00")
    );
    // Power cycle: the stored heartbeat time is back.
    r.power_cycle();
    assert_eq!(
        r.req(0x67F, &hex("40 17 10 00 00 00 00 00")).1,
        hex("4B 17 10 00 64 00 00 00")
    );
    // Wrong signature: 0x08000020.
    assert_eq!(
        r.req(0x67F, &hex("23 10 10 01 73 61 76 66")).1,
        hex("80 10 10 01 20 00 00 08")
    );
}

#[test]
fn restore_table_14_defaults_after_reset() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 17 10 00 64 00 00 00"));
    r.store_cmd(0x67F, &hex("22 10 10 01 73 61 76 65"), 25);
    let f = r.store_cmd(0x67F, &hex("22 11 10 01 6C 6F 61 64"), 25);
    let ans: Vec<_> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x5FF))
        .collect();
    assert_eq!(ans[0].1.data(), &hex("60 11 10 01 00 00 00 00")[..]);
    // D7: the current value stays until the next reset …
    assert_eq!(
        r.req(0x67F, &hex("40 17 10 00 00 00 00 00")).1,
        hex("4B 17 10 00 64 00 00 00")
    );
    // … then the default is back.
    r.send(0x000, &[0x81, 0x7F]);
    r.take();
    assert_eq!(
        r.req(0x67F, &hex("40 17 10 00 00 00 00 00")).1,
        hex("4B 17 10 00 00 00 00 00")
    );
    // Wrong signature.
    assert_eq!(
        r.req(0x67F, &hex("23 11 10 01 6C 6F 61 65")).1,
        hex("80 11 10 01 20 00 00 08")
    );
}

#[test]
fn emcy_example_3_main_voltage() {
    let mut r = Rig::booted(&TH);
    // Example 3: 0x080+ID, 00 31 05 … = main operating voltage error, register 0x05.
    r.node
        .set_error(0x3100, canpos_stack::emcy::reg::VOLTAGE, [0; 5], true);
    let f = r.take();
    assert_eq!(f.len(), 1);
    assert_eq!(f[0].std_id(), Some(0x0FF));
    assert_eq!(f[0].data(), &hex("00 31 05 00 00 00 00 00")[..]);
    assert_eq!(
        r.req(0x67F, &hex("40 01 10 00 00 00 00 00")).1,
        hex("4F 01 10 00 05 00 00 00")
    );
    // History 0x1003: one entry, newest first.
    assert_eq!(
        r.req(0x67F, &hex("40 03 10 00 00 00 00 00")).1,
        hex("4F 03 10 00 01 00 00 00")
    );
    assert_eq!(
        r.req(0x67F, &hex("40 03 10 01 00 00 00 00")).1,
        hex("43 03 10 01 00 31 00 00")
    );
    // Cleared: EMCY 0x0000 with register 0.
    r.node.set_error(0x3100, 0, [0; 5], false);
    let f = r.take();
    assert_eq!(f[0].data(), &hex("00 00 00 00 00 00 00 00")[..]);
    // Writing 0 to 0x1003/0 clears the history; other values are refused.
    assert_eq!(
        r.req(0x67F, &hex("2F 03 10 00 00 00 00 00")).1,
        hex("60 03 10 00 00 00 00 00")
    );
    assert_eq!(
        r.req(0x67F, &hex("40 03 10 00 00 00 00 00")).1,
        hex("4F 03 10 00 00 00 00 00")
    );
    assert_eq!(r.req(0x67F, &hex("2F 03 10 00 01 00 00 00")).1[0], 0x80);
}

#[test]
fn sync_consumer_type_1_and_every_nth() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2F 00 18 02 03 00 00 00")); // every 3rd SYNC
    r.send(0x000, &[0x01, 0x7F]);
    let mut n = 0;
    for _ in 0..9 {
        n += r
            .send(0x080, &[])
            .iter()
            .filter(|f| f.std_id() == Some(0x1FF))
            .count();
    }
    assert_eq!(n, 3);
    // No event-timer PDOs for a synchronous PDO.
    assert!(r
        .advance_ms(10)
        .iter()
        .all(|(_, f)| f.std_id() != Some(0x1FF)));
    // A SYNC on another COB-ID does nothing; 0x1005 moves the consumer.
    r.send(0x000, &[0x80, 0x7F]);
    r.req(0x67F, &hex("23 05 10 00 81 00 00 00"));
    r.req(0x67F, &hex("2F 00 18 02 01 00 00 00"));
    r.send(0x000, &[0x01, 0x7F]);
    assert!(r.send(0x080, &[]).is_empty());
    assert_eq!(r.send(0x081, &[]).len(), 1);
}

#[test]
fn event_timer_1ms_gives_1000_tpdos_per_second() {
    let mut r = Rig::booted(&TH);
    r.send(0x000, &[0x01, 0x7F]);
    let f = r.run_until(Instant::from_millis(1000));
    let n = f.iter().filter(|(_, f)| f.std_id() == Some(0x1FF)).count();
    assert_eq!(n, 1000);
    // Pre-operational: none.
    r.send(0x000, &[0x80, 0x7F]);
    assert!(r
        .advance_ms(100)
        .iter()
        .all(|(_, f)| f.std_id() != Some(0x1FF)));
}

#[test]
fn inhibit_time_spaces_tpdos() {
    let mut r = Rig::booted(&TH);
    // Event timer 1 ms but inhibit 5 ms (50 × 100 µs): at most one PDO per 5 ms.
    r.req(0x67F, &hex("2B 00 18 03 32 00 00 00"));
    r.send(0x000, &[0x01, 0x7F]);
    let f = r.run_until(Instant::from_millis(100));
    let times: Vec<u64> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x1FF))
        .map(|(t, _)| t.micros())
        .collect();
    assert!(times.len() >= 19 && times.len() <= 20, "{}", times.len());
    assert!(times.windows(2).all(|w| w[1] - w[0] >= 5000));
}

#[test]
fn node_guarding_toggle_and_life_guarding() {
    let mut r = Rig::booted(&TH);
    // Guard time 100 ms × factor 3.
    r.req(0x67F, &hex("2B 0C 10 00 64 00 00 00"));
    r.req(0x67F, &hex("2F 0D 10 00 03 00 00 00"));
    let g = |r: &mut Rig| {
        let f = Frame::remote(0x77F, false, 1).unwrap();
        r.node.handle_frame(&f, r.now);
        r.take()
    };
    assert_eq!(g(&mut r)[0].data(), &[0x7F], "toggle starts at 0");
    assert_eq!(g(&mut r)[0].data(), &[0xFF], "toggle alternates");
    // D22: a zero-length data frame is a guard request too (socketcand).
    assert_eq!(r.send(0x77F, &[])[0].data(), &[0x7F]);
    r.send(0x000, &[0x01, 0x7F]);
    // No guard request for 300 ms: EMCY 0x8130 and PDOs stop.
    let f = r.advance_ms(301);
    let emcy: Vec<_> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x0FF))
        .collect();
    assert_eq!(emcy.len(), 1);
    assert_eq!(&emcy[0].1.data()[..3], &[0x30, 0x81, 0x11]);
    assert!(emcy[0].0.micros() >= 300_000);
    assert!(
        r.advance_ms(50)
            .iter()
            .all(|(_, f)| f.std_id() != Some(0x1FF)),
        "PDOs stopped"
    );
    // Guarding resumes: PDOs resume.
    g(&mut r);
    assert!(r
        .advance_ms(5)
        .iter()
        .any(|(_, f)| f.std_id() == Some(0x1FF)));
}
