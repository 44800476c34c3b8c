//! Property tests of the bus-level invariants on every model, and round trips of the core's
//! codecs (SDO command bytes, storage image, NMT commands).
//!
//! The frame-sequence invariants live in `common/harness.rs`, shared with the `node_frames`
//! fuzz target: one SDO response per request, replies only on own COB-IDs (LSS may change the
//! node-id), NMT state machine legal, DLC ≤ 8. Here proptest drives them in the normal suite;
//! the fuzzer explores further.

use crate::common::harness;

use canpos_models as models;
use canpos_stack::nmt::{NmtCommand, NmtState};
use canpos_stack::sdo::wire::{self, Mux, Request};
use canpos_stack::storage::{self, ImageWriter, RamStorage, StorageError, IMAGE_MAX};
use canpos_stack::{Frame, Instant};
use proptest::prelude::*;
use proptest::sample::select;

/// One harness operation, encoded as the harness reads it (see `Checker::step`).
fn op() -> impl Strategy<Value = Vec<u8>> {
    let frame = (
        0u8..0xA0,
        0u8..0x20,
        proptest::collection::vec(any::<u8>(), 8),
    )
        .prop_map(|(op, lr, data)| {
            let mut v = vec![op, lr];
            v.extend(data);
            v
        });
    // SDO requests with the command bytes and objects that reach deep states.
    let sdo = (
        select(vec![
            0x40u8, 0x23, 0x2B, 0x2F, 0x60, 0x70, 0x00, 0x10, 0xA4, 0xA3, 0xA2, 0xA1, 0xC6, 0xC1,
            0x80,
        ]),
        select(vec![
            (0x1000u16, 0u8),
            (0x1008, 0),
            (0x1010, 1),
            (0x1011, 1),
            (0x1017, 0),
            (0x1800, 5),
            (0x1A00, 0),
            (0x6000, 0),
            (0x2000, 0),
        ]),
        any::<[u8; 4]>(),
    )
        .prop_map(|(b0, (i, s), t)| {
            let ib = i.to_le_bytes();
            vec![0x02, 8, b0, ib[0], ib[1], s, t[0], t[1], t[2], t[3]]
        });
    let nmt = (
        select(vec![0x01u8, 0x02, 0x80, 0x81, 0x82, 0x07]),
        any::<u8>(),
    )
        .prop_map(|(c, t)| vec![0x00, 2, c, t]);
    let lss = (
        select(vec![
            0x04u8, 0x11, 0x13, 0x15, 0x17, 0x40, 0x41, 0x42, 0x43, 0x5A, 0x5B, 0x5E,
        ]),
        any::<[u8; 7]>(),
    )
        .prop_map(|(c, t)| {
            let mut v = vec![0x06, 8, c];
            v.extend(t);
            v
        });
    let time = (0xA0u8..0xE0, any::<u16>()).prop_map(|(op, d)| vec![op, d as u8, (d >> 8) as u8]);
    let sample = (0xE0u8..0xF0, any::<[u8; 9]>()).prop_map(|(op, b)| {
        let mut v = vec![op];
        v.extend(b);
        v
    });
    let power = select(vec![vec![0xF0u8], vec![0xF8u8]]);
    prop_oneof![3 => frame, 6 => sdo, 3 => nmt, 2 => lss, 4 => time, 1 => sample, 1 => power]
}

/// Which of a node's NMT commands a frame carries for node `id`, as CiA 301 defines it.
fn expected_after(before: NmtState, data: &[u8], id: u8) -> NmtState {
    if data.len() != 2 || (data[1] != 0 && data[1] != id) {
        return before;
    }
    match data[0] {
        0x01 => NmtState::Operational,
        0x02 => NmtState::Stopped,
        0x80..=0x82 => NmtState::PreOperational,
        _ => before,
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// Structured operation sequences on every model keep every bus-level invariant.
    #[test]
    fn every_model_keeps_the_invariants(model in 0u8..3, cfg in any::<u8>(),
                                        ops in proptest::collection::vec(op(), 1..60)) {
        let mut input = vec![model, cfg];
        for o in ops {
            input.extend(o);
        }
        if let Err(e) = harness::Checker::run(&input) {
            prop_assert!(false, "{}", e);
        }
    }

    /// Unstructured bytes too (what the fuzzer starts from).
    #[test]
    fn arbitrary_bytes_keep_the_invariants(input in proptest::collection::vec(any::<u8>(), 0..400)) {
        if let Err(e) = harness::Checker::run(&input) {
            prop_assert!(false, "{}", e);
        }
    }

    /// NMT: every command sequence follows the CiA 301 state diagram exactly, resets send one
    /// boot-up (0x00 on 0x700 + id), nothing else answers an NMT command.
    #[test]
    fn nmt_state_machine_is_legal(model in 0usize..3,
                                  cmds in proptest::collection::vec(
                                      (select(vec![0x01u8, 0x02, 0x80, 0x81, 0x82, 0x00, 0x83]),
                                       select(vec![0u8, 1, 2, 0x7F, 0x80]),
                                       0usize..=3), 1..40)) {
        let m = models::all()[model];
        let mut cfg = m.default_config;
        cfg.node_id = 1;
        let mut node = canpos_models::SensorNode::new(m, cfg, RamStorage::default());
        node.power_on(Instant::ZERO);
        while node.poll_transmit().is_some() {}
        prop_assert_eq!(node.device().nmt_state(), NmtState::PreOperational);
        let mut t = 0u64;
        for (c, target, len) in cmds {
            let data = &[c, target, 0][..len];
            let before = node.device().nmt_state();
            t += 100;
            node.handle_frame(&Frame::new(0x000, data).unwrap(), Instant::from_micros(t));
            let after = node.device().nmt_state();
            prop_assert_eq!(after, expected_after(before, data, 1), "{:02X?} in {:?}", data, before);
            let mut out = Vec::new();
            while let Some(f) = node.poll_transmit() {
                out.push(f);
            }
            let reset = matches!(data, [0x81 | 0x82, 0 | 1]);
            let boots: Vec<_> = out.iter().filter(|f| f.std_id() == Some(0x701)).collect();
            if reset {
                prop_assert_eq!(boots.len(), 1, "{:02X?}: {:?}", data, out);
                prop_assert_eq!(boots[0].data(), &[0u8][..]);
            } else {
                // Nothing at all answers a plain state change.
                prop_assert!(out.is_empty(), "{:02X?} answered: {:?}", data, out);
            }
        }
    }

    /// NMT command bytes: every command parses back for its node and for all, never for another
    /// node, and anything that parses has the CiA 301 shape.
    #[test]
    fn nmt_parse_round_trip(id in 1u8..=127, other in 1u8..=127, data in proptest::collection::vec(any::<u8>(), 0..4)) {
        for c in [NmtCommand::Start, NmtCommand::Stop, NmtCommand::EnterPreOperational,
                  NmtCommand::ResetNode, NmtCommand::ResetCommunication] {
            prop_assert_eq!(NmtCommand::parse(&[c.code(), id], id), Some(c));
            prop_assert_eq!(NmtCommand::parse(&[c.code(), 0], id), Some(c));
            if other != id {
                prop_assert_eq!(NmtCommand::parse(&[c.code(), other], id), None);
            }
        }
        if let Some(c) = NmtCommand::parse(&data, id) {
            prop_assert_eq!(data.len(), 2);
            prop_assert_eq!(data[0], c.code());
            prop_assert!(data[1] == 0 || data[1] == id);
        }
    }

    /// SDO requests: decode → encode (CiA 301 layout) → decode is the identity on any 8 bytes.
    #[test]
    fn sdo_request_round_trip(f in any::<[u8; 8]>()) {
        let r = Request::parse(&f);
        prop_assert_eq!(Request::parse(&encode_request(&r)), r);
    }

    /// SDO responses: the server's encoders put every field where a client decodes it.
    #[test]
    fn sdo_response_round_trip(index in any::<u16>(), sub in any::<u8>(),
                               data in proptest::collection::vec(any::<u8>(), 1..=7),
                               toggle in any::<bool>(), last in any::<bool>(), seq in 1u8..=127,
                               size in any::<u32>(), crc in any::<u16>(), unused in 0u8..=6) {
        let mux = Mux { index, sub };
        let same_mux = |r: &[u8; 8]| Mux::from_frame(r) == mux;
        let n = data.len().min(4);
        let r = wire::expedited_upload(mux, &data[..n]);
        prop_assert!(same_mux(&r));
        prop_assert_eq!(r[0] & 0xE3, 0x43);
        prop_assert_eq!(4 - usize::from((r[0] >> 2) & 3), n);
        prop_assert_eq!(&r[4..4 + n], &data[..n]);

        let r = wire::upload_initiate_segmented(mux, size);
        prop_assert!(same_mux(&r) && r[0] == 0x41);
        prop_assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), size);

        let r = wire::upload_segment(toggle, &data, last);
        prop_assert_eq!(r[0] >> 5, 0);
        prop_assert_eq!(r[0] & 0x10 != 0, toggle);
        prop_assert_eq!(r[0] & 1 != 0, last);
        prop_assert_eq!(7 - usize::from((r[0] >> 1) & 7), data.len());
        prop_assert_eq!(&r[1..1 + data.len()], &data[..]);

        let r = wire::block_segment(seq, last, &data);
        prop_assert_eq!(r[0] & 0x7F, seq);
        prop_assert_eq!(r[0] & 0x80 != 0, last);
        prop_assert_eq!(&r[1..1 + data.len()], &data[..]);

        let r = wire::block_upload_end(unused, crc);
        prop_assert_eq!(r[0] & 0xE3, 0xC1);
        prop_assert_eq!((r[0] >> 2) & 7, unused);
        prop_assert_eq!(u16::from_le_bytes([r[1], r[2]]), crc);

        let r = wire::block_upload_initiate(mux, toggle, size);
        prop_assert!(same_mux(&r));
        prop_assert_eq!(r[0], 0xC2 | (u8::from(toggle) << 2));
        prop_assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), size);

        prop_assert_eq!(wire::download_segment_ack(toggle)[0], 0x20 | (u8::from(toggle) << 4));
        let r = wire::download_initiate_ack(mux);
        prop_assert!(same_mux(&r) && r[0] == 0x60);
    }

    /// Storage image: what ImageWriter writes parses back to the same records; any single bit
    /// flip or truncation is rejected (the CRC and length checks).
    #[test]
    fn storage_image_round_trip(tag in any::<u8>(),
                                recs in proptest::collection::vec(any::<(u32, u32)>(), 0..240),
                                flip in any::<usize>(), cut in any::<usize>()) {
        let mut buf = [0u8; IMAGE_MAX];
        let mut w = ImageWriter::new(&mut buf, tag);
        for &(k, v) in &recs {
            prop_assert!(w.push(k, v));
        }
        let n = w.finish();
        let back: Vec<(u32, u32)> = storage::parse_image(&buf[..n], tag).unwrap().collect();
        prop_assert_eq!(&back, &recs);
        prop_assert!(storage::parse_image(&buf[..n], tag.wrapping_add(1)).is_err());
        let mut bad = buf;
        bad[flip % n] ^= 1 << (flip % 8);
        prop_assert_eq!(storage::parse_image(&bad[..n], tag).err(), Some(StorageError::Corrupt));
        prop_assert!(storage::parse_image(&buf[..cut % n], tag).is_err());
    }
}

/// Encodes a request the way CiA 301 lays it out (a client's view, independent of the server).
fn encode_request(r: &Request) -> [u8; 8] {
    let mux = |b0: u8, m: &Mux, tail: [u8; 4]| {
        let i = m.index.to_le_bytes();
        [b0, i[0], i[1], m.sub, tail[0], tail[1], tail[2], tail[3]]
    };
    match *r {
        Request::DownloadSegment {
            toggle,
            unused,
            last,
            data,
        } => {
            let mut f = [0u8; 8];
            f[0] = (u8::from(toggle) << 4) | ((unused & 7) << 1) | u8::from(last);
            f[1..].copy_from_slice(&data);
            f
        }
        Request::DownloadInitiate {
            mux: m,
            expedited,
            size,
            data,
        } => {
            let mut b0 = 0x20 | (u8::from(expedited) << 1) | u8::from(size.is_some());
            if let (true, Some(n)) = (expedited, size) {
                b0 |= ((4 - n as u8) & 3) << 2;
            }
            mux(b0, &m, data)
        }
        Request::UploadInitiate { mux: m } => mux(0x40, &m, [0; 4]),
        Request::UploadSegment { toggle } => [0x60 | (u8::from(toggle) << 4), 0, 0, 0, 0, 0, 0, 0],
        Request::Abort { mux: m, code } => mux(0x80, &m, code.to_le_bytes()),
        Request::BlockUploadInitiate {
            mux: m,
            crc,
            blksize,
            pst,
        } => mux(0xA0 | (u8::from(crc) << 2), &m, [blksize, pst, 0, 0]),
        Request::BlockUploadEnd => [0xA1, 0, 0, 0, 0, 0, 0, 0],
        Request::BlockUploadAck { ackseq, blksize } => [0xA2, ackseq, blksize, 0, 0, 0, 0, 0],
        Request::BlockUploadStart => [0xA3, 0, 0, 0, 0, 0, 0, 0],
        Request::BlockDownloadInitiate { mux: m, crc, size } => mux(
            0xC0 | (u8::from(crc) << 2) | (u8::from(size.is_some()) << 1),
            &m,
            size.unwrap_or(0).to_le_bytes(),
        ),
        Request::BlockDownloadEnd { unused, crc } => {
            let c = crc.to_le_bytes();
            [0xC1 | ((unused & 7) << 2), c[0], c[1], 0, 0, 0, 0, 0]
        }
        Request::Unknown => [0xE0, 0, 0, 0, 0, 0, 0, 0],
    }
}

/// The block-transfer CRC is CRC-16/XMODEM (CiA 301 §7.2.4.3.16): its check value.
#[test]
fn sdo_crc16_check_value() {
    assert_eq!(wire::crc16(b"123456789"), 0x31C3);
}

/// Found by the `state_file` fuzz target: a checksummed image with an impossible LSS node-id
/// (0, 200, 0x105) made the node talk as node 0 / 200. It must keep its configured node-id.
#[test]
fn stored_impossible_node_id_is_ignored() {
    use canpos_stack::storage::{Storage, KEY_LSS_NODE_ID};
    for m in models::all() {
        for bad in [0u32, 128, 200, 0x105] {
            let mut buf = [0u8; IMAGE_MAX];
            let mut w = ImageWriter::new(&mut buf, m.features.tag);
            w.push(KEY_LSS_NODE_ID, bad);
            let n = w.finish();
            let mut ram = RamStorage::default();
            ram.save(&buf[..n]).unwrap();
            let mut node = canpos_models::SensorNode::new(m, m.default_config, ram);
            node.power_on(Instant::ZERO);
            assert_eq!(
                node.device().node_id(),
                m.default_config.node_id,
                "{} {bad}",
                m.name
            );
        }
    }
}
