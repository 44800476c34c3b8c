//! LSS (CiA 305) slave: the manuals' worked examples frame by frame (OD.md §3.9, TH §5.6.1,
//! E-Series §5.5.1), the TMI procedures (OD.md §3.10), and the CiA 305 services the manuals
//! name without examples (selective switch, identify, fastscan), all on a virtual clock.

use crate::common::{hex, Rig};
use canpos_models::th::TH;
use canpos_models::SensorNode;
use canpos_models::{self as models, DeviceConfig, Features, Model};
use canpos_stack::storage::RamStorage;
use canpos_stack::Table;
use canpos_stack::{Frame, Instant};

const LSS_RX: u16 = 0x7E5;
const LSS_TX: u16 = 0x7E4;

/// A model with the TH dictionary and other behaviour switches: stands in for E-Series / TMI
/// where only their LSS switches matter (D9, fastscan on DS 305 V2 only) while those models
/// are not in the tree yet.
fn variant(name: &'static str, features: Features) -> &'static Model {
    Box::leak(Box::new(Model {
        table: Table {
            name,
            product: TH.product,
            vendor: TH.vendor,
            entries: TH.entries,
            keys: TH.keys,
            features,
        },
        param: TH.param,
        derive: TH.derive,
        profile: TH.profile,
        variant: None,
        default_config: TH.default_config,
    }))
}

/// The E-Series model; until it exists, its LSS switches on the TH: DS 305 V2.1.1, bit timing
/// 0–4 (D9).
fn e_series() -> &'static Model {
    models::by_name("e-series").unwrap_or_else(|| {
        variant(
            "e-series-lss",
            Features {
                lss_bit_timing: &[0, 1, 2, 3, 4],
                ..TH.features
            },
        )
    })
}

/// The TMI model; until it exists, its LSS switches on the TH: DSP 305 V1.1.2 (no fastscan),
/// bit timing 0–4, 6, 7, 8 (D9).
fn tmi() -> &'static Model {
    models::by_name("tmi").unwrap_or_else(|| {
        variant(
            "tmi-lss",
            Features {
                lss_fastscan: false,
                lss_bit_timing: &[0, 1, 2, 3, 4, 6, 7, 8],
                ..TH.features
            },
        )
    })
}

fn unconfigured(serial: u32) -> DeviceConfig {
    unconfigured_of(&TH, serial)
}

fn unconfigured_of(model: &Model, serial: u32) -> DeviceConfig {
    DeviceConfig {
        node_id: 0xFF,
        serial,
        ..model.default_config
    }
}

/// Sends an LSS request and expects no answer at all.
fn lss_silent(r: &mut Rig, req: &str) {
    let out = r.send(LSS_RX, &hex(req));
    assert!(out.is_empty(), "no answer expected to {req}, got {out:?}");
}

/// Sends an LSS request and expects exactly one 8-byte answer on 0x7E4, byte for byte.
fn lss_answer(r: &mut Rig, req: &str, ans: &str) {
    let (id, data) = r.req(LSS_RX, &hex(req));
    assert_eq!(id, LSS_TX, "answer to {req} on 0x7E4");
    assert_eq!(data, hex(ans), "answer to {req}");
}

/// The boot-up message of `node`: 0x700 + id, one byte 0x00.
fn assert_boot_up(frames: &[Frame], node: u16) {
    let f = frames.first().expect("a boot-up message");
    assert_eq!(f.std_id(), Some(0x700 + node), "{frames:?}");
    assert_eq!(f.data(), &[0x00]);
}

fn le(v: u32) -> String {
    v.to_le_bytes().map(|b| format!("{b:02X}")).join(" ")
}

/// Example 1a with the manual's own value 0x7F: every frame as printed, then the reset.
#[test]
fn example_1a_configure_node_id_7f_frame_by_frame() {
    let mut r = Rig::booted(&TH);
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "11 7F 00 00 00 00 00 00", "11 00 00 00 00 00 00 00");
    lss_answer(&mut r, "17 00 00 00 00 00 00 00", "17 00 00 00 00 00 00 00");
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    let out = r.send(0x000, &[0x81, 0x00]);
    assert_boot_up(&out, 0x7F);
    assert_eq!(r.node.storage_mut().saves, 1);
}

/// Example 1a with a new node-id (5): the id applies only at the NMT reset that follows, then
/// boot-up, SDO, EMCY and TPDOs all use the new COB-IDs (SPEC §3, R16, D15).
#[test]
fn example_1a_configure_new_node_id_5_moves_all_cob_ids() {
    for reset_target in [0x00, 0x7F] {
        let mut r = Rig::booted(&TH);
        lss_silent(&mut r, "04 01 00 00 00 00 00 00");
        lss_answer(&mut r, "11 05 00 00 00 00 00 00", "11 00 00 00 00 00 00 00");
        lss_answer(&mut r, "17 00 00 00 00 00 00 00", "17 00 00 00 00 00 00 00");
        lss_silent(&mut r, "04 00 00 00 00 00 00 00");
        // Still node 127 until the reset (R16: "active after a reset of the sensor").
        assert_eq!(r.node.device().node_id(), 0x7F);
        assert_eq!(r.node.device().pending().0, 5);
        assert_eq!(
            r.req(0x67F, &hex("40 00 10 00 00 00 00 00")),
            (0x5FF, hex("43 00 10 00 96 01 08 00"))
        );
        // Step 7: NMT reset node, addressed to all or to the (still active) 0x7F.
        let out = r.send(0x000, &[0x81, reset_target]);
        assert_boot_up(&out, 5);
        // The power-on EMCY (D14) follows on the new EMCY COB-ID.
        assert!(out[1..].iter().all(|f| f.std_id() == Some(0x85)), "{out:?}");
        assert_eq!(r.node.device().node_id(), 5);
        // SDO at 0x605 / 0x585; the old 0x67F is deaf.
        assert_eq!(
            r.req(0x605, &hex("40 00 10 00 00 00 00 00")),
            (0x585, hex("43 00 10 00 96 01 08 00"))
        );
        assert!(r.send(0x67F, &hex("40 00 10 00 00 00 00 00")).is_empty());
        // EMCY and every TPDO COB-ID follow; valid / RTR bits are kept (D15).
        assert_eq!(r.node.read_object(0x1014, 0), Ok(0x85));
        for (n, base) in [0x180u32, 0x280, 0x380, 0x480].into_iter().enumerate() {
            let v = r.read(0x1800 + n as u16, 1);
            assert_eq!(v & 0x7FF, base + 5, "TPDO{} COB-ID {v:08X}", n + 1);
        }
        // TPDO1 runs on 0x185 once operational; the NMT command addresses node 5 now.
        assert!(r.send(0x000, &[0x01, 0x05]).is_empty());
        let f = r.advance_ms(10);
        assert!(f.iter().any(|(_, f)| f.std_id() == Some(0x185)));
        assert!(f.iter().all(|(_, f)| f.std_id() != Some(0x1FF)));
    }
}

/// D15 with stored communication parameters: a stored TPDO COB-ID that was the default for the
/// old node-id follows the new one; a custom one stays; the flags stay.
#[test]
fn d15_stored_default_tpdo_cob_ids_follow_custom_ones_stay() {
    let mut r = Rig::booted(&TH);
    // TPDO2: invalid, custom CAN-ID 0x350 (not the 0x280 + id default).
    assert_eq!(
        r.req(0x67F, &hex("23 01 18 01 50 03 00 80")),
        (0x5FF, hex("60 01 18 01 00 00 00 00"))
    );
    let held = r.store_cmd(0x67F, &hex("23 10 10 01 73 61 76 65"), 25);
    assert!(held
        .iter()
        .any(|(_, f)| f.std_id() == Some(0x5FF) && f.data()[0] == 0x60));
    let tpdo_before: Vec<u32> = (0..4).map(|n| r.read(0x1800 + n, 1)).collect();
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "11 05 00 00 00 00 00 00", "11 00 00 00 00 00 00 00");
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    // Reset communication reloads the stored 0x1800… values, then re-derives them (D6, D15).
    assert_boot_up(&r.send(0x000, &[0x82, 0x7F]), 5);
    let tpdo_after: Vec<u32> = (0..4).map(|n| r.read(0x1800 + n, 1)).collect();
    assert_eq!(tpdo_after[0], (tpdo_before[0] & !0x7FF) | 0x185);
    assert_eq!(tpdo_after[1], 0x8000_0350, "custom COB-ID kept");
    assert_eq!(tpdo_after[2], (tpdo_before[2] & !0x7FF) | 0x385);
    assert_eq!(tpdo_after[3], (tpdo_before[3] & !0x7FF) | 0x485);
    assert_eq!(r.node.read_object(0x1014, 0), Ok(0x85));
}

/// Example 1b: "Inquire node-ID" → `5E 7F`.
#[test]
fn example_1b_read_node_id() {
    let mut r = Rig::booted(&TH);
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "5E 00 00 00 00 00 00 00", "5E 7F 00 00 00 00 00 00");
    // The active id, not a pending one: a configured-but-not-reset 5 still reads 7F.
    lss_answer(&mut r, "11 05 00 00 00 00 00 00", "11 00 00 00 00 00 00 00");
    lss_answer(&mut r, "5E 00 00 00 00 00 00 00", "5E 7F 00 00 00 00 00 00");
}

/// D9: bit-timing indices per model; reserved index 5, unknown indices and tables ≠ 0 refused.
#[test]
fn d9_bit_timing_indices_per_model() {
    let cases: [(&'static Model, &[u8]); 3] = [
        (&TH, &[0, 1, 2, 3, 4, 6, 7]),
        (e_series(), &[0, 1, 2, 3, 4]),
        (tmi(), &[0, 1, 2, 3, 4, 6, 7, 8]),
    ];
    for (model, accepted) in cases {
        let mut r = Rig::booted(model);
        lss_silent(&mut r, "04 01 00 00 00 00 00 00");
        for index in 0..=12u8 {
            let ok = accepted.contains(&index);
            let status = if ok { 0 } else { 1 };
            lss_answer(
                &mut r,
                &format!("13 00 {index:02X} 00 00 00 00 00"),
                &format!("13 {status:02X} 00 00 00 00 00 00"),
            );
        }
        // A refused request leaves the last accepted rate pending.
        let last = *accepted.last().unwrap();
        let kbps = canpos_stack::lss::bit_timing_kbps(last).unwrap();
        assert_eq!(r.node.device().pending().1, kbps, "{model:?}");
        lss_answer(&mut r, "13 01 02 00 00 00 00 00", "13 01 00 00 00 00 00 00");
        lss_answer(&mut r, "13 FF 02 00 00 00 00 00", "13 01 00 00 00 00 00 00");
    }
    // The two D9 cases the brief names explicitly.
    let mut r = Rig::new(tmi());
    r.send(LSS_RX, &hex("04 01 00 00 00 00 00 00"));
    lss_answer(&mut r, "13 00 08 00 00 00 00 00", "13 00 00 00 00 00 00 00");
    assert_eq!(r.node.device().pending().1, 10);
    let mut r = Rig::new(e_series());
    r.send(LSS_RX, &hex("04 01 00 00 00 00 00 00"));
    lss_answer(&mut r, "13 00 06 00 00 00 00 00", "13 01 00 00 00 00 00 00");
    assert_eq!(r.node.device().pending().1, r.node.device().bitrate());
}

/// Configure node-id: 1…127 and 0xFF accepted, 0 and 0x80…0xFE refused.
#[test]
fn configure_node_id_range() {
    let mut r = Rig::booted(&TH);
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    for id in 0..=255u8 {
        let ok = (1..=127).contains(&id) || id == 0xFF;
        lss_answer(
            &mut r,
            &format!("11 {id:02X} 00 00 00 00 00 00"),
            &format!("11 {:02X} 00 00 00 00 00 00", if ok { 0 } else { 1 }),
        );
        if ok {
            assert_eq!(r.node.device().pending().0, id);
        }
    }
}

/// Configuration-state services are ignored in waiting state; unknown specifiers and DLC ≠ 8
/// are ignored in both.
#[test]
fn waiting_state_ignores_configuration_services() {
    let mut r = Rig::booted(&TH);
    for req in [
        "11 05 00 00 00 00 00 00",
        "13 00 02 00 00 00 00 00",
        "15 0A 00 00 00 00 00 00",
        "17 00 00 00 00 00 00 00",
        "5A 00 00 00 00 00 00 00",
        "5B 00 00 00 00 00 00 00",
        "5C 00 00 00 00 00 00 00",
        "5D 00 00 00 00 00 00 00",
        "5E 00 00 00 00 00 00 00",
        "00 00 00 00 00 00 00 00",
        "44 00 00 00 00 00 00 00",
        "FF FF FF FF FF FF FF FF",
    ] {
        lss_silent(&mut r, req);
    }
    assert_eq!(r.node.device().pending(), (0x7F, 125));
    assert_eq!(r.node.poll_timeout(), None, "no bit-rate switch started");
    assert_eq!(r.node.storage_mut().saves, 0);
    // Short frames are not LSS, even with a valid specifier.
    lss_silent(&mut r, "04 01");
    lss_silent(&mut r, "5E 00 00 00 00 00 00 00");
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_silent(&mut r, "5E 00 00 00 00 00 00");
    lss_silent(&mut r, "11 05");
    lss_silent(&mut r, "77 00 00 00 00 00 00 00");
    lss_answer(&mut r, "5E 00 00 00 00 00 00 00", "5E 7F 00 00 00 00 00 00");
}

/// Inquire identity 0x5A…0x5D: the LSS address (0x1018/1…4), little-endian in bytes 1…4.
#[test]
fn inquire_identity_values_le() {
    let cfg = DeviceConfig {
        serial: 17143876,
        ..TH.default_config
    };
    let mut r = Rig::with_config(&TH, cfg);
    r.take();
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    let addr: Vec<u32> = (1..=4).map(|s| r.read(0x1018, s)).collect();
    assert_eq!(addr, [0x40, 0x4333_3034, 0x0001_0005, 17143876]);
    for (cs, v) in [0x5Au8, 0x5B, 0x5C, 0x5D].into_iter().zip(addr) {
        lss_answer(
            &mut r,
            &format!("{cs:02X} 00 00 00 00 00 00 00"),
            &format!("{cs:02X} {} 00 00 00", le(v)),
        );
    }
}

fn selective(r: &mut Rig, addr: [u32; 4]) -> Vec<Frame> {
    let mut out = Vec::new();
    for (cs, v) in [0x40u8, 0x41, 0x42, 0x43].into_iter().zip(addr) {
        out = r.send(LSS_RX, &hex(&format!("{cs:02X} {} 00 00 00", le(v))));
        if cs != 0x43 {
            assert!(out.is_empty(), "0x40…0x42 are unconfirmed");
        }
    }
    out
}

/// Switch state selective: 0x44 only when all four parts match, sent in order.
#[test]
fn switch_state_selective() {
    let mut r = Rig::booted(&TH);
    let addr = r.node.device().lss_address();
    // A wrong serial: no answer, still waiting (inquire is ignored).
    let mut wrong = addr;
    wrong[3] ^= 1;
    assert!(selective(&mut r, wrong).is_empty());
    lss_silent(&mut r, "5E 00 00 00 00 00 00 00");
    // Out of order (revision before product): no answer.
    for (cs, v) in [
        (0x40u8, addr[0]),
        (0x42, addr[2]),
        (0x41, addr[1]),
        (0x43, addr[3]),
    ] {
        lss_silent(&mut r, &format!("{cs:02X} {} 00 00 00", le(v)));
    }
    // The right address: 0x44, and configuration services work.
    let out = selective(&mut r, addr);
    assert_eq!(out.len(), 1);
    assert_eq!(out[0].std_id(), Some(LSS_TX));
    assert_eq!(out[0].data(), &hex("44 00 00 00 00 00 00 00")[..]);
    lss_answer(&mut r, "5E 00 00 00 00 00 00 00", "5E 7F 00 00 00 00 00 00");
    // Switch global waiting deselects.
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    lss_silent(&mut r, "5E 00 00 00 00 00 00 00");
}

/// Two nodes on one bus: selective switching configures only the addressed one.
#[test]
fn switch_state_selective_picks_one_of_two() {
    let mut bus = Bus::new(&[(0x7F, 1111), (0x7F, 2222)]);
    bus.master(0x000, &[0x80, 0x00]);
    let addr = bus.nodes[1].device().lss_address();
    for (cs, v) in [0x40u8, 0x41, 0x42, 0x43].into_iter().zip(addr) {
        let out = bus.master(LSS_RX, &hex(&format!("{cs:02X} {} 00 00 00", le(v))));
        if cs == 0x43 {
            assert_eq!(out.len(), 1, "only the selected node answers");
        }
    }
    let out = bus.master(LSS_RX, &hex("11 06 00 00 00 00 00 00"));
    assert_eq!(out.len(), 1);
    assert_eq!(bus.nodes[0].device().pending().0, 0x7F);
    assert_eq!(bus.nodes[1].device().pending().0, 6);
}

fn identify(r: &mut Rig, vendor: u32, product: u32, rev: (u32, u32), serial: (u32, u32)) -> bool {
    let reqs = [
        (0x46u8, vendor),
        (0x47, product),
        (0x48, rev.0),
        (0x49, rev.1),
        (0x4A, serial.0),
        (0x4B, serial.1),
    ];
    let mut out = Vec::new();
    for (cs, v) in reqs {
        out = r.send(LSS_RX, &hex(&format!("{cs:02X} {} 00 00 00", le(v))));
        if cs != 0x4B {
            assert!(out.is_empty());
        }
    }
    match out.as_slice() {
        [] => false,
        [f] => {
            assert_eq!(f.std_id(), Some(LSS_TX));
            assert_eq!(f.data(), &hex("4F 00 00 00 00 00 00 00")[..]);
            true
        }
        _ => panic!("one answer at most: {out:?}"),
    }
}

/// Identify remote slave: revision and serial ranges inclusive, vendor and product exact, in
/// both LSS states.
#[test]
fn identify_remote_slave_ranges() {
    let cfg = DeviceConfig {
        serial: 5000,
        ..TH.default_config
    };
    let mut r = Rig::with_config(&TH, cfg);
    r.take();
    let [v, p, rev, _] = r.node.device().lss_address();
    for configuration in [false, true] {
        if configuration {
            lss_silent(&mut r, "04 01 00 00 00 00 00 00");
        }
        assert!(identify(&mut r, v, p, (0, u32::MAX), (0, u32::MAX)));
        assert!(identify(&mut r, v, p, (rev, rev), (5000, 5000)));
        assert!(identify(&mut r, v, p, (rev - 1, rev + 1), (4999, 5001)));
        assert!(!identify(&mut r, v, p, (rev + 1, u32::MAX), (0, u32::MAX)));
        assert!(!identify(&mut r, v, p, (0, rev - 1), (0, u32::MAX)));
        assert!(!identify(&mut r, v, p, (0, u32::MAX), (5001, 9000)));
        assert!(!identify(&mut r, v, p, (0, u32::MAX), (0, 4999)));
        assert!(!identify(&mut r, v + 1, p, (0, u32::MAX), (0, u32::MAX)));
        assert!(!identify(&mut r, v, p ^ 1, (0, u32::MAX), (0, u32::MAX)));
        // An empty range (low > high) matches nothing.
        assert!(!identify(&mut r, v, p, (0, u32::MAX), (6000, 4000)));
    }
    // Identify does not change the LSS state.
    lss_answer(&mut r, "5E 00 00 00 00 00 00 00", "5E 7F 00 00 00 00 00 00");
}

/// Identify non-configured remote slave: only a node without a node-id answers 0x50.
#[test]
fn identify_non_configured_remote_slave() {
    let mut r = Rig::booted(&TH);
    lss_silent(&mut r, "4C 00 00 00 00 00 00 00");
    let mut r = Rig::with_config(&TH, unconfigured(1));
    assert!(r.take().is_empty(), "no boot-up without a node-id");
    lss_answer(&mut r, "4C 00 00 00 00 00 00 00", "50 00 00 00 00 00 00 00");
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    lss_answer(&mut r, "4C 00 00 00 00 00 00 00", "50 00 00 00 00 00 00 00");
}

/// An unconfigured node (0xFF) is silent and ignores NMT; the manual's node-id procedure gives
/// it an id, and switching back to waiting brings it into NMT with a boot-up (CiA 305, G33).
#[test]
fn unconfigured_node_gets_node_id_and_boots() {
    let mut r = Rig::with_config(&TH, unconfigured(1));
    assert!(r.take().is_empty());
    assert!(r.send(0x000, &[0x81, 0x00]).is_empty());
    assert!(r.send(0x67F, &hex("40 00 10 00 00 00 00 00")).is_empty());
    assert!(r.advance_ms(100).is_empty());
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "5E 00 00 00 00 00 00 00", "5E FF 00 00 00 00 00 00");
    lss_answer(&mut r, "11 05 00 00 00 00 00 00", "11 00 00 00 00 00 00 00");
    lss_answer(&mut r, "17 00 00 00 00 00 00 00", "17 00 00 00 00 00 00 00");
    let out = r.send(LSS_RX, &hex("04 00 00 00 00 00 00 00"));
    assert_boot_up(&out, 5);
    assert_eq!(
        r.req(0x605, &hex("40 00 10 00 00 00 00 00")),
        (0x585, hex("43 00 10 00 96 01 08 00"))
    );
    assert_boot_up(&r.send(0x000, &[0x81, 0x00]), 5);
}

/// Store configuration, power cycle with the same storage: node-id and bit rate survive, also
/// in a new node built on a copy of the storage.
#[test]
fn store_configuration_survives_power_cycle() {
    let mut r = Rig::booted(&TH);
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "11 05 00 00 00 00 00 00", "11 00 00 00 00 00 00 00");
    lss_answer(&mut r, "13 00 02 00 00 00 00 00", "13 00 00 00 00 00 00 00");
    lss_answer(&mut r, "17 00 00 00 00 00 00 00", "17 00 00 00 00 00 00 00");
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    r.node.power_off();
    r.node.power_on(Instant::from_millis(5000));
    assert_boot_up(&r.take(), 5);
    assert_eq!(r.node.device().node_id(), 5);
    assert_eq!(r.node.device().bitrate(), 500);
    let storage: RamStorage = r.node.storage_mut().clone();
    let mut n = canpos_models::SensorNode::new(&TH, TH.default_config, storage);
    n.power_on(Instant::ZERO);
    assert_eq!((n.device().node_id(), n.device().bitrate()), (5, 500));
    let boot = n.poll_transmit().unwrap();
    assert_eq!(boot.std_id(), Some(0x705));
    // Without "store configuration", a new id and bit rate are lost at power-off, even after
    // a reset made them active.
    let mut r = Rig::booted(&TH);
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "11 09 00 00 00 00 00 00", "11 00 00 00 00 00 00 00");
    lss_answer(&mut r, "13 00 03 00 00 00 00 00", "13 00 00 00 00 00 00 00");
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    assert_boot_up(&r.send(0x000, &[0x82, 0x00]), 9);
    assert_eq!(r.node.device().bitrate(), 250);
    r.node.power_off();
    r.node.power_on(Instant::ZERO);
    assert_eq!(
        (r.node.device().node_id(), r.node.device().bitrate()),
        (0x7F, 125)
    );
    assert_boot_up(&r.take(), 0x7F);
}

/// Store configuration with a failing medium answers status 2 and keeps nothing.
#[test]
fn store_configuration_storage_failure_is_status_2() {
    let mut r = Rig::booted(&TH);
    lss_silent(&mut r, "04 01 00 00 00 00 00 00");
    lss_answer(&mut r, "11 05 00 00 00 00 00 00", "11 00 00 00 00 00 00 00");
    r.node.storage_mut().fail = true;
    lss_answer(&mut r, "17 00 00 00 00 00 00 00", "17 02 00 00 00 00 00 00");
    r.node.storage_mut().fail = false;
    r.node.power_off();
    r.node.power_on(Instant::ZERO);
    assert_eq!(r.node.device().node_id(), 0x7F);
}

/// A shared virtual CAN bus: every frame reaches every other node; all answers to one request
/// are returned together (on CAN, identical LSS answers merge into one "some answer").
struct Bus {
    nodes: Vec<SensorNode<RamStorage>>,
    now: Instant,
}

impl Bus {
    fn new(units: &[(u8, u32)]) -> Bus {
        let nodes = units
            .iter()
            .map(|&(node_id, serial)| {
                let cfg = DeviceConfig {
                    node_id,
                    serial,
                    ..TH.default_config
                };
                let mut n = canpos_models::SensorNode::new(&TH, cfg, RamStorage::default());
                n.power_on(Instant::ZERO);
                n
            })
            .collect();
        let mut bus = Bus {
            nodes,
            now: Instant::ZERO,
        };
        bus.settle(Vec::new());
        bus
    }

    /// The master sends a frame; returns every frame the nodes put on the bus in reaction.
    fn master(&mut self, id: u16, data: &[u8]) -> Vec<Frame> {
        let f = Frame::new(id, data).unwrap();
        for n in &mut self.nodes {
            n.handle_frame(&f, self.now);
        }
        self.settle(Vec::new())
    }

    /// Delivers what each node sent to all the others until the bus is quiet.
    fn settle(&mut self, mut seen: Vec<Frame>) -> Vec<Frame> {
        loop {
            let mut sent = Vec::new();
            for (i, n) in self.nodes.iter_mut().enumerate() {
                while let Some(f) = n.poll_transmit() {
                    sent.push((i, f));
                }
            }
            if sent.is_empty() {
                return seen;
            }
            for &(from, f) in &sent {
                for (i, n) in self.nodes.iter_mut().enumerate() {
                    if i != from {
                        n.handle_frame(&f, self.now);
                    }
                }
                seen.push(f);
            }
        }
    }

    /// One fastscan request; true if any slave acknowledged (0x4F on 0x7E4).
    fn fastscan_req(&mut self, id: u32, bit_checked: u8, sub: u8, next: u8) -> bool {
        let mut d = [0u8; 8];
        d[0] = 0x51;
        d[1..5].copy_from_slice(&id.to_le_bytes());
        d[5] = bit_checked;
        d[6] = sub;
        d[7] = next;
        let out = self.master(LSS_RX, &d);
        assert!(out
            .iter()
            .all(|f| f.std_id() == Some(LSS_TX) && f.data() == hex("4F 00 00 00 00 00 00 00")));
        !out.is_empty()
    }

    /// A fastscan master (CiA 305): reset, then each of the 128 bits from the top, assuming 0
    /// and correcting to 1 when nobody answers, confirming each 32-bit part. Returns the LSS
    /// address of the slave found (now in configuration state) and the requests used.
    fn fastscan(&mut self) -> Option<([u32; 4], usize)> {
        if !self.fastscan_req(0, 0x80, 0, 0) {
            return None;
        }
        let mut reqs = 1;
        let mut addr = [0u32; 4];
        for sub in 0..4u8 {
            for bit in (0..32u8).rev() {
                reqs += 1;
                if !self.fastscan_req(addr[sub as usize], bit, sub, sub) {
                    addr[sub as usize] |= 1 << bit;
                }
            }
            reqs += 1;
            if !self.fastscan_req(addr[sub as usize], 0, sub, (sub + 1) % 4) {
                return None;
            }
        }
        Some((addr, reqs))
    }
}

/// Fastscan from scratch finds an unconfigured node over all 128 bits; the master then gives
/// it a node-id and it boots into NMT.
#[test]
fn fastscan_finds_unconfigured_node() {
    let mut bus = Bus::new(&[(0xFF, 0x0A5C_3E71)]);
    // CiA 305 masters first deselect everyone (switch state global waiting).
    assert!(bus
        .master(LSS_RX, &hex("04 00 00 00 00 00 00 00"))
        .is_empty());
    let (addr, reqs) = bus.fastscan().expect("a node is found");
    assert_eq!(reqs, 1 + 4 * 33);
    assert_eq!(addr, bus.nodes[0].device().lss_address());
    assert_eq!(addr[3], 0x0A5C_3E71);
    // Found = in configuration state: inquire works.
    let out = bus.master(LSS_RX, &hex("5D 00 00 00 00 00 00 00"));
    assert_eq!(
        out[0].data(),
        &hex(&format!("5D {} 00 00 00", le(0x0A5C_3E71)))[..]
    );
    assert_eq!(bus.master(LSS_RX, &hex("11 20 00 00 00 00 00 00")).len(), 1);
    let out = bus.master(LSS_RX, &hex("04 00 00 00 00 00 00 00"));
    assert_eq!(out[0].std_id(), Some(0x720));
    // Configured now: it takes no part in further scans.
    assert!(bus.fastscan().is_none());
}

/// Two unconfigured nodes with different serials on one bus: found one after the other (the
/// lower LSS address first), each given its own node-id.
#[test]
fn fastscan_finds_two_unconfigured_nodes_one_after_the_other() {
    let serials = [0x0000_1235, 0x0000_1234];
    let mut bus = Bus::new(&[(0xFF, serials[0]), (0xFF, serials[1])]);
    assert!(bus
        .master(LSS_RX, &hex("04 00 00 00 00 00 00 00"))
        .is_empty());
    assert_eq!(bus.master(LSS_RX, &hex("4C 00 00 00 00 00 00 00")).len(), 2);
    let mut found = Vec::new();
    for node_id in [0x10u8, 0x11] {
        let (addr, _) = bus.fastscan().expect("an unconfigured node answers");
        found.push(addr[3]);
        // Only the node found is in configuration state.
        let out = bus.master(LSS_RX, &hex(&format!("11 {node_id:02X} 00 00 00 00 00 00")));
        assert_eq!(out.len(), 1, "{out:?}");
        let out = bus.master(LSS_RX, &hex("04 00 00 00 00 00 00 00"));
        assert_eq!(out[0].std_id(), Some(0x700 + node_id as u16));
    }
    assert_eq!(found, [0x1234, 0x1235]);
    assert_eq!(bus.nodes[1].device().node_id(), 0x10);
    assert_eq!(bus.nodes[0].device().node_id(), 0x11);
    assert!(bus.fastscan().is_none());
    assert!(bus
        .master(LSS_RX, &hex("4C 00 00 00 00 00 00 00"))
        .is_empty());
}

/// Fastscan is DS 305 V2: the TMI (DSP 305 V1.1.2) ignores it; configured nodes never answer.
#[test]
fn fastscan_only_on_v2_models_and_unconfigured_nodes() {
    let mut r = Rig::with_config(tmi(), unconfigured_of(tmi(), 7));
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    lss_silent(&mut r, "51 00 00 00 00 80 00 00");
    lss_answer(&mut r, "4C 00 00 00 00 00 00 00", "50 00 00 00 00 00 00 00");
    let mut r = Rig::booted(&TH);
    lss_silent(&mut r, "51 00 00 00 00 80 00 00");
    let mut r = Rig::with_config(&TH, unconfigured(7));
    lss_silent(&mut r, "04 00 00 00 00 00 00 00");
    lss_answer(&mut r, "51 00 00 00 00 80 00 00", "4F 00 00 00 00 00 00 00");
    // Malformed: bitChecked 32…0x7F, lssSub / lssNext > 3.
    lss_silent(&mut r, "51 00 00 00 00 20 00 00");
    lss_silent(&mut r, "51 00 00 00 00 1F 04 00");
    lss_silent(&mut r, "51 00 00 00 00 1F 00 04");
    // Wrong part (the scan is at the vendor-id).
    lss_silent(&mut r, "51 00 00 00 00 1F 01 01");
    lss_answer(&mut r, "51 00 00 00 00 1F 00 00", "4F 00 00 00 00 00 00 00");
}
