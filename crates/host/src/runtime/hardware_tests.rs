//! The simulated hardware around a node ([`SimHardware`]): the bus's bit rate (frames lost both
//! ways while the node's rate differs, TMI autobaud) and the D7 store time. These were the
//! core's behaviours under its former `simulation` feature; their tests moved here with them,
//! assertion for assertion (issue 37).

use canpos_models::th::TH;
use canpos_models::SensorNode;
use canpos_models::{self as models, Model};
use canpos_stack::storage::RamStorage;
use canpos_stack::{Frame, Instant, Node};

use super::SimHardware;

/// A node with RAM storage behind its simulated hardware, on a virtual clock.
struct Rig {
    node: SensorNode<RamStorage>,
    hw: SimHardware,
    now: Instant,
}

impl Rig {
    /// Powers a node of `model` (default config) on at t = 0 and drops nothing: call `take()`.
    fn new(model: &'static Model) -> Rig {
        Rig::with_config(model, model.default_config)
    }

    fn with_config(model: &'static Model, cfg: models::DeviceConfig) -> Rig {
        let mut node = Node::new(model, cfg, RamStorage::default());
        node.power_on(Instant::ZERO);
        Rig {
            node,
            hw: SimHardware::default(),
            now: Instant::ZERO,
        }
    }

    /// Like `new`, with the boot-up frames dropped.
    fn booted(model: &'static Model) -> Rig {
        let mut r = Rig::new(model);
        r.take();
        r
    }

    fn power_cycle(&mut self) -> Vec<Frame> {
        self.node.power_off();
        self.node.power_on(self.now);
        self.take()
    }

    /// A frame from the bus at `at`.
    fn receive(&mut self, f: &Frame, at: Instant) {
        self.hw.receive(&mut self.node, f, at);
    }

    /// All frames that reach the bus now.
    fn take(&mut self) -> Vec<Frame> {
        let mut v = Vec::new();
        while let Some(f) = self.hw.poll(&mut self.node, self.now) {
            v.push(f);
        }
        v
    }

    fn send(&mut self, id: u16, data: &[u8]) -> Vec<Frame> {
        let f = Frame::new(id, data).unwrap();
        self.receive(&f, self.now);
        self.take()
    }

    fn req(&mut self, id: u16, data: &[u8]) -> (u16, Vec<u8>) {
        let r = self.send(id, data);
        assert_eq!(r.len(), 1, "one answer to {id:03X} {data:02X?}: {r:?}");
        (r[0].std_id().unwrap(), r[0].data().to_vec())
    }

    /// Runs every deadline (the node's and the hardware's) up to `t`, in order; the frames
    /// with the instant they reached the bus.
    fn run_until(&mut self, t: Instant) -> Vec<(Instant, Frame)> {
        let mut out = Vec::new();
        for _ in 0..1_000_000 {
            let next = [self.node.poll_timeout(), self.hw.deadline()];
            match next.into_iter().flatten().min() {
                Some(d) if d <= t => {
                    self.now = d.max(self.now);
                    let now = self.now;
                    out.extend(self.take().into_iter().map(|f| (now, f)));
                }
                _ => {
                    self.now = t;
                    out.extend(self.take().into_iter().map(|f| (t, f)));
                    return out;
                }
            }
        }
        panic!("the deadlines do not advance at {:?}", self.now);
    }

    fn advance_ms(&mut self, ms: u64) -> Vec<(Instant, Frame)> {
        self.run_until(Instant::from_micros(self.now.micros() + ms * 1000))
    }

    /// Sends a store or restore command and runs `ms` milliseconds on: nothing comes at once
    /// (the store time); every frame with its instant.
    fn store_cmd(&mut self, id: u16, data: &[u8], ms: u64) -> Vec<(Instant, Frame)> {
        let first = self.send(id, data);
        assert!(
            first.is_empty(),
            "answer only after the store time: {first:?}"
        );
        self.advance_ms(ms)
    }
}

fn booted(name: &str) -> Rig {
    Rig::booted(models::by_name(name).unwrap())
}

fn tmi() -> &'static Model {
    models::by_name("tmi").unwrap()
}

fn hex(s: &str) -> Vec<u8> {
    s.split_whitespace()
        .map(|b| u8::from_str_radix(b, 16).unwrap())
        .collect()
}

const LSS_RX: u16 = 0x7E5;
const LSS_TX: u16 = 0x7E4;

fn lss_silent(r: &mut Rig, req: &str) {
    let out = r.send(LSS_RX, &hex(req));
    assert!(out.is_empty(), "no answer expected to {req}, got {out:?}");
}

fn lss_answer(r: &mut Rig, req: &str, ans: &str) {
    let (id, data) = r.req(LSS_RX, &hex(req));
    assert_eq!(id, LSS_TX, "answer to {req} on 0x7E4");
    assert_eq!(data, hex(ans), "answer to {req}");
}

fn assert_boot_up(frames: &[Frame], node: u16) {
    let f = frames.first().expect("a boot-up message");
    assert_eq!(f.std_id(), Some(0x700 + node), "{frames:?}");
    assert_eq!(f.data(), &[0x00]);
}

fn store(r: &mut Rig, bytes: &str) -> Vec<u8> {
    r.store_cmd(0x67F, &hex(bytes), 25)
        .into_iter()
        .find(|(_, f)| f.std_id() == Some(0x5FF))
        .map(|(_, f)| f.data().to_vec())
        .unwrap()
}

/// D7 (was the core's `store_table_13_answers_after_20ms_and_survives_power_cycle`): the answer
/// to "save" leaves exactly the store time after the request.
#[test]
fn store_table_13_answers_after_20ms() {
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 17 10 00 64 00 00 00"));
    let t0 = r.now;
    let f = r.store_cmd(0x67F, &hex("22 10 10 01 73 61 76 65"), 20);
    let ans: Vec<_> = f
        .iter()
        .filter(|(_, f)| f.std_id() == Some(0x5FF))
        .collect();
    assert_eq!(ans.len(), 1);
    assert_eq!(ans[0].1.data(), &hex("60 10 10 01 00 00 00 00")[..]);
    assert_eq!(ans[0].0.micros() - t0.micros(), 20_000);
}

/// CiA 305 §5.8 (switch bit rate): between "activate bit timing" and the end of the second
/// switch delay the node neither receives nor sends. A frame arriving in that window is not
/// heard, and it does not make the node announce itself (a boot-up belongs to autobaud locking,
/// not to a configured node waiting out its switch).
#[test]
fn cia305_activate_bit_timing_window_is_deaf_and_announces_nothing() {
    let mut r = Rig::booted(&TH);
    r.hw.set_bus_bitrate(Some(125));
    r.send(0x7E5, &hex("04 01 00 00 00 00 00 00")); // switch state global: configuration
    r.take();
    r.send(0x7E5, &hex("15 00 64 00 00 00 00 00")); // activate bit timing, delay 100 ms
    r.take();
    r.advance_ms(50);
    // The host hands the frame in and collects the output only after the window.
    let f = Frame::new(0x67F, &hex("40 00 10 00 00 00 00 00")).unwrap();
    r.receive(&f, r.now);
    r.now = Instant::from_millis(r.now.micros() / 1000 + 200);
    r.node.handle_timeout(r.now);
    let later: Vec<_> = r.take().into_iter().map(|f| (r.now, f)).collect();
    assert!(
        later.iter().all(|(_, f)| f.std_id() != Some(0x5FF)),
        "the SDO request was not heard"
    );
    assert!(
        later.iter().all(|(_, f)| f.std_id() != Some(0x77F)),
        "no boot-up from a frame heard in the window"
    );
    // Not even one queued and then discarded because the node could not talk.
    assert_eq!(r.hw.stats(&r.node).tx_wrong_bitrate, 0);
}

/// The counters a host shows (`Stats`): frames heard while the bus runs another bit rate, frames
/// the node produced meanwhile and lost (as on a real bus: nobody can receive them), and whether
/// the stored image failed its check at the last power-on.
#[test]
fn stats_count_frames_lost_to_a_wrong_bit_rate_and_report_corrupt_storage() {
    let mut r = Rig::booted(&TH);
    assert_eq!(r.node.device().bitrate(), 125);
    r.req(0x67F, &hex("2B 17 10 00 64 00 00 00")); // heartbeat 100 ms
    r.hw.set_bus_bitrate(Some(500));
    for _ in 0..3 {
        assert!(r.send(0x67F, &hex("40 00 10 00 00 00 00 00")).is_empty());
    }
    assert!(r.advance_ms(350).is_empty(), "no heartbeat reaches the bus");
    let s = r.hw.stats(&r.node);
    assert_eq!((s.rx_wrong_bitrate, s.tx_wrong_bitrate), (3, 3));
    assert!(!r.node.device().stats().storage_corrupt);

    r.hw.set_bus_bitrate(Some(125));
    r.send(0x67F, &hex("23 10 10 01 73 61 76 65")); // save
    r.advance_ms(50);
    r.node.storage_mut().corrupt();
    r.node.power_off();
    r.node.power_on(r.now);
    assert!(r.node.device().stats().storage_corrupt);
    r.send(0x67F, &hex("23 10 10 01 73 61 76 65"));
    r.advance_ms(50);
    r.node.power_off();
    r.node.power_on(r.now);
    assert!(
        !r.node.device().stats().storage_corrupt,
        "a good image again"
    );
}

/// Every frame the node produced while it cannot talk is lost and counted, however many wait at
/// once (here a power-on's boot-up and power-on EMCY), and none goes out once the bit rate
/// matches again.
#[test]
fn every_frame_waiting_while_the_bit_rate_is_wrong_is_counted_lost() {
    let boot = Rig::new(&TH).take().len();
    assert!(boot > 1, "a power-on sends more than one frame");
    let mut r = Rig::booted(&TH);
    r.hw.set_bus_bitrate(Some(500));
    assert!(r.power_cycle().is_empty());
    assert_eq!(r.hw.stats(&r.node).tx_wrong_bitrate, boot as u32);
    r.hw.set_bus_bitrate(Some(125));
    assert!(r.take().is_empty(), "lost, not delayed");
}

/// CiA 305 §5.8: the node is deaf for twice the switch delay after "activate bit timing" and
/// hears again from the end of the second delay on: a frame handed in at that very instant
/// (before the host served the node's timer) is heard.
#[test]
fn cia305_the_switch_window_ends_at_twice_the_delay() {
    let mut r = Rig::booted(&TH);
    r.hw.set_bus_bitrate(Some(125));
    r.send(0x7E5, &hex("04 01 00 00 00 00 00 00"));
    r.send(0x7E5, &hex("15 64 00 00 00 00 00 00")); // delay 100 ms: deaf until 200 ms
    r.take();
    let at = |ms| Instant::from_millis(ms);
    let req = Frame::new(0x7E5, &hex("5E 00 00 00 00 00 00 00")).unwrap();
    r.receive(&req, at(199));
    assert!(r.take().is_empty(), "still deaf at 199 ms");
    r.now = at(200);
    r.receive(&req, r.now);
    let a = r.take();
    assert_eq!(a.len(), 1, "heard at 200 ms: {a:?}");
    assert_eq!(a[0].data()[..2], [0x5E, 0x7F]);
}

/// TMI R19 / DECISIONS ("autobaud locks on after 4 received frames and then sends the
/// boot-up"): three frames are not enough; the fourth locks the rate, and only then the node
/// announces itself and serves requests.
#[test]
fn r19_autobaud_needs_four_frames() {
    let tmi = models::by_name("tmi").unwrap();
    let cfg = models::DeviceConfig {
        bitrate_kbps: 0,
        ..tmi.default_config
    };
    let mut r = Rig::with_config(tmi, cfg);
    r.hw.set_bus_bitrate(Some(250));
    assert!(r.take().is_empty());
    for k in 1..=3 {
        assert!(r.send(0x123, &[k]).is_empty(), "frame {k}");
        assert_eq!(r.node.device().bitrate(), 0, "not locked after {k}");
    }
    // The fourth locks the rate; the node announces itself (the frame itself was not heard).
    let boot = r.send(0x67F, &hex("40 00 10 00 00 00 00 00"));
    assert_eq!(boot.len(), 1, "{boot:?}");
    assert_eq!(
        (boot[0].std_id(), boot[0].data()),
        (Some(0x77F), &[0u8][..])
    );
    assert_eq!(r.node.device().bitrate(), 250);
    assert_eq!(r.req(0x67F, &hex("40 00 10 00 00 00 00 00")).0, 0x5FF);
}

/// Example 2: 500 kbit/s without activation; the new rate applies at the next reset (R18).
/// Then the node talks on a 500 kbit/s bus and is silent on a 125 kbit/s one (SPEC §9).
#[test]
fn example_2_bit_rate_500_applies_after_reset() {
    let mut r = Rig::new(&TH);
    r.hw.set_bus_bitrate(Some(125));
    r.take();
    assert!(r.send(0x000, &[0x80, 0x7F]).is_empty());
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "13 00 02 00 00 00 00 00", "13 00 00 00 00 00 00 00");
    lss_answer(&mut r, "17 00 00 00 00 00 00 00", "17 00 00 00 00 00 00 00");
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    // Not active yet: still 125 kbit/s.
    assert_eq!(r.node.device().bitrate(), 125);
    assert_eq!(r.node.device().pending().1, 500);
    let sdo = hex("40 00 10 00 00 00 00 00");
    assert_eq!(r.req(0x67F, &sdo).0, 0x5FF);
    // The reset (sent at 125) switches the node to 500: its boot-up is lost on the 125 bus.
    assert!(r.send(0x000, &[0x81, 0x7F]).is_empty());
    assert_eq!(r.node.device().bitrate(), 500);
    assert!(r.send(0x67F, &sdo).is_empty(), "silent at 125 kbit/s");
    r.hw.set_bus_bitrate(Some(500));
    assert_eq!(r.req(0x67F, &sdo).0, 0x5FF, "talks at 500 kbit/s");
    // And after a power cycle (stored): boot-up on a 500 bus, nothing on a 125 bus.
    r.node.power_off();
    r.node.power_on(r.now);
    assert_boot_up(&r.take(), 0x7F);
    r.hw.set_bus_bitrate(Some(125));
    r.node.power_off();
    r.node.power_on(r.now);
    assert!(r.take().is_empty());
    assert!(r.send(0x67F, &sdo).is_empty());
}

/// Activate bit timing (0x15): silent for the switch delay, switch, silent for the delay again
/// ("timing in ms internal multiplied by 2", TH Table 4), delay 16 bit little-endian.
#[test]
fn activate_bit_timing_switch_delay_on_virtual_clock() {
    let mut r = Rig::new(&TH);
    r.hw.set_bus_bitrate(Some(125));
    r.take();
    r.advance_ms(1000);
    let t0 = r.now.micros();
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "13 00 02 00 00 00 00 00", "13 00 00 00 00 00 00 00");
    // Switch delay 300 ms = 0x012C: bytes 1–2 LSB first.
    lss_silent(&mut r, "15 2C 01 00 00 00 00 00");
    assert_eq!(
        r.node.poll_timeout(),
        Some(Instant::from_micros(t0 + 300_000))
    );
    // First period: still 125 kbit/s but deaf and mute.
    r.advance_ms(299);
    assert_eq!(r.node.device().bitrate(), 125);
    lss_silent(&mut r, "5E 00 00 00 00 00 00 00");
    // The switch, exactly at 300 ms.
    r.advance_ms(1);
    assert_eq!(r.node.device().bitrate(), 500);
    assert_eq!(
        r.node.poll_timeout(),
        Some(Instant::from_micros(t0 + 600_000))
    );
    // Second period: the bus has switched too, the node still waits.
    r.hw.set_bus_bitrate(Some(500));
    r.advance_ms(299);
    lss_silent(&mut r, "5E 00 00 00 00 00 00 00");
    r.advance_ms(1);
    // Back: still in configuration state, now at 500 kbit/s.
    lss_answer(&mut r, "5E 00 00 00 00 00 00 00", "5E 7F 00 00 00 00 00 00");
    assert_eq!(r.node.poll_timeout(), None);
    // Not stored: a power cycle returns to the configured 125 kbit/s.
    r.node.power_off();
    r.node.power_on(r.now);
    assert_eq!(r.node.device().bitrate(), 125);
}

/// TMI picture 4: configure, activate, then switch mode global back to operation; the NMT side
/// keeps running at the new rate without a reset.
#[test]
fn tmi_set_bit_rate_by_activation() {
    let mut r = Rig::new(tmi());
    let start = r.node.device().bitrate();
    assert_ne!(start, 10);
    r.hw.set_bus_bitrate(Some(start));
    r.take();
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "13 00 08 00 00 00 00 00", "13 00 00 00 00 00 00 00");
    lss_silent(&mut r, "15 0A 00 00 00 00 00 00");
    r.advance_ms(10);
    r.hw.set_bus_bitrate(Some(10));
    r.advance_ms(10);
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    assert_eq!(r.node.device().bitrate(), 10);
    assert_eq!(r.req(0x67F, &hex("40 00 10 00 00 00 00 00")).0, 0x5FF);
}

#[test]
fn autobaud_via_0x2001_adopts_the_bus_rate_after_a_few_frames() {
    let mut r = booted("tmi");
    // 0x2001 := 0xFFFF (autobaud, D16), save, power cycle on a 250 kbit/s bus.
    assert_eq!(
        r.req(0x67F, &hex("2B 01 20 00 FF FF 00 00")).1,
        hex("60 01 20 00 00 00 00 00")
    );
    store(&mut r, "23 10 10 01 73 61 76 65");
    r.hw.set_bus_bitrate(Some(250));
    r.node.power_off();
    r.node.power_on(r.now);
    assert!(r.take().is_empty(), "silent until the bit rate is detected");
    assert_eq!(r.node.device().bitrate(), 0);
    // R19: continuous traffic of 4–5 messages lets it detect the rate; it then boots up.
    let mut heard = Vec::new();
    for _ in 0..4 {
        heard.extend(r.send(0x123, &[1, 2, 3]));
    }
    assert_eq!(r.node.device().bitrate(), 250);
    assert_eq!(heard.len(), 1);
    assert_eq!(
        (heard[0].std_id(), heard[0].data()),
        (Some(0x77F), &[0u8][..])
    );
    assert_eq!(r.req(0x67F, &hex("40 00 10 00 00 00 00 00")).0, 0x5FF);
}

#[test]
fn wrong_bit_rate_node_is_silent_and_deaf() {
    let mut r = booted("tmi");
    r.hw.set_bus_bitrate(Some(500));
    assert!(r.send(0x67F, &hex("40 00 10 00 00 00 00 00")).is_empty());
    r.hw.set_bus_bitrate(Some(250));
    assert_eq!(r.req(0x67F, &hex("40 00 10 00 00 00 00 00")).0, 0x5FF);
}

/// D7: the answer to "save" leaves at least 20 ms after the request, the first one included.
#[test]
fn save_answers_after_the_store_time() {
    for name in ["th", "e-series", "tmi"] {
        let mut r = booted(name);
        for _ in 0..3 {
            let t0 = r.now;
            assert!(r
                .send(0x67F, &[0x23, 0x10, 0x10, 0x01, b's', b'a', b'v', b'e'])
                .is_empty());
            let answer = r
                .advance_ms(40)
                .into_iter()
                .find(|(_, f)| f.std_id() == Some(0x5FF))
                .unwrap();
            assert_eq!(answer.1.data()[0], 0x60);
            assert!(
                answer.0.micros() - t0.micros() >= 20_000,
                "{name}: after {} µs",
                answer.0.micros() - t0.micros()
            );
        }
    }
}

/// D7 as the core had it: a node stopped during the store time serves no SDO, so the held
/// answer never leaves; a reset communication in that time forgets it, as it forgets a
/// transfer in progress. The heartbeat keeps running meanwhile.
#[test]
fn a_held_store_answer_dies_with_stop_and_reset_and_the_heartbeat_runs_on() {
    let save = hex("23 10 10 01 73 61 76 65");
    // Stopped 5 ms into the store time.
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 17 10 00 0A 00 00 00")); // heartbeat 10 ms
    assert!(r.send(0x67F, &save).is_empty());
    r.advance_ms(5);
    r.send(0x000, &[0x02, 0x7F]);
    let out = r.advance_ms(40);
    assert!(
        out.iter().all(|(_, f)| f.std_id() != Some(0x5FF)),
        "{out:?}"
    );
    assert!(
        out.iter().any(|(_, f)| f.std_id() == Some(0x77F)),
        "heartbeat"
    );
    assert_eq!(r.hw.deadline(), None);
    // Reset communication 5 ms into the store time: a boot-up, no answer.
    let mut r = Rig::booted(&TH);
    assert!(r.send(0x67F, &save).is_empty());
    r.advance_ms(5);
    let boot = r.send(0x000, &[0x82, 0x7F]);
    assert_boot_up(&boot, 0x7F);
    assert!(boot.iter().all(|f| f.std_id() != Some(0x5FF)), "{boot:?}");
    let out = r.advance_ms(40);
    assert!(
        out.iter().all(|(_, f)| f.std_id() != Some(0x5FF)),
        "{out:?}"
    );
    // Without either, the answer leaves at 20 ms with the heartbeat running around it.
    let mut r = Rig::booted(&TH);
    r.req(0x67F, &hex("2B 17 10 00 0A 00 00 00"));
    let t0 = r.now;
    assert!(r.send(0x67F, &save).is_empty());
    let out = r.advance_ms(40);
    let at = |id| {
        out.iter()
            .filter(|(_, f)| f.std_id() == Some(id))
            .map(|(t, _)| t.micros() - t0.micros())
            .collect::<Vec<_>>()
    };
    assert_eq!(at(0x5FF), [20_000]);
    assert_eq!(at(0x77F), [10_000, 20_000, 30_000, 40_000]);
}
