//! Segmented and block SDO transfers, on the TH node (CONFORMANCE SDO-13…27) and on the bare
//! server with a mock dictionary that has values longer than 4 bytes.
use crate::common::{hex, Rig};
use canpos_models::th::TH;
use canpos_stack::od::Abort;
use canpos_stack::sdo::wire::crc16;
use canpos_stack::sdo::{ObjectAccess, SdoServer, SDO_BUF_LEN};
use canpos_stack::Instant;
use std::collections::BTreeMap;

/// A request that must get no answer.
fn quiet(r: &mut Rig, req: &str) {
    let out = r.send(0x67F, &hex(req));
    assert!(out.is_empty(), "{req} answered {out:?}");
}

/// SDO-15 / SDO-14: segmented download of 2 bytes with size indicated.
#[test]
fn segmented_download_heartbeat_and_guard_time() {
    let mut r = Rig::booted(&TH);
    for idx in ["17 10", "0C 10"] {
        assert_eq!(
            r.sdo(&format!("21 {idx} 00 02 00 00 00")),
            hex(&format!("60 {idx} 00 00 00 00 00"))
        );
        assert_eq!(
            r.sdo("0B E8 03 00 00 00 00 00"),
            hex("20 00 00 00 00 00 00 00")
        );
        assert_eq!(
            r.sdo(&format!("40 {idx} 00 00 00 00 00")),
            hex(&format!("4B {idx} 00 E8 03 00 00"))
        );
    }
}

/// python-canopen `force_segment=True` on a U32: initiate with size 4, one segment n = 3, c.
#[test]
fn segmented_download_u32_force_segment() {
    let mut r = Rig::booted(&TH);
    assert_eq!(
        r.sdo("21 05 10 00 04 00 00 00"),
        hex("60 05 10 00 00 00 00 00")
    );
    assert_eq!(
        r.sdo("07 81 00 00 00 00 00 00"),
        hex("20 00 00 00 00 00 00 00")
    );
    assert_eq!(
        r.sdo("40 05 10 00 00 00 00 00"),
        hex("43 05 10 00 81 00 00 00")
    );
    // Size not indicated (0x20): the dictionary checks the length at the end.
    assert_eq!(
        r.sdo("20 05 10 00 00 00 00 00"),
        hex("60 05 10 00 00 00 00 00")
    );
    assert_eq!(
        r.sdo("07 80 00 00 00 00 00 00"),
        hex("20 00 00 00 00 00 00 00")
    );
    assert_eq!(r.node.read_object(0x1005, 0), Ok(0x80));
}

/// SDO-13: a plain upload of a 4-byte object (the 4-char device name too) is answered
/// expedited; a client that asked for a block with a protocol switch threshold ≥ 4 also gets
/// the expedited answer.
#[test]
fn short_values_upload_expedited_and_protocol_switch() {
    let mut r = Rig::booted(&TH);
    assert_eq!(
        r.sdo("40 08 10 00 00 00 00 00"),
        hex("43 08 10 00 43 33 30 34")
    );
    assert_eq!(
        r.sdo("A0 08 10 00 14 04 00 00"),
        hex("43 08 10 00 43 33 30 34")
    );
    // pst 3 < 4 bytes: block transfer goes ahead.
    assert_eq!(
        r.sdo("A0 08 10 00 14 03 00 00"),
        hex("C2 08 10 00 04 00 00 00")
    );
    quiet(&mut r, "80 08 10 00 00 00 00 00");
}

/// SDO-19: block upload of 1000:00 without CRC.
#[test]
fn block_upload_device_type_no_crc() {
    let mut r = Rig::booted(&TH);
    assert_eq!(
        r.sdo("A0 00 10 00 14 00 00 00"),
        hex("C2 00 10 00 04 00 00 00")
    );
    assert_eq!(
        r.sdo("A3 00 00 00 00 00 00 00"),
        hex("81 96 01 08 00 00 00 00")
    );
    assert_eq!(
        r.sdo("A2 01 14 00 00 00 00 00"),
        hex("CD 00 00 00 00 00 00 00")
    );
    quiet(&mut r, "A1 00 00 00 00 00 00 00");
    assert!(!r.node.sdo_server().busy());
}

/// Block upload of the device name 0x1008 with CRC (SDO-23 pattern).
#[test]
fn block_upload_device_name_crc() {
    let mut r = Rig::booted(&TH);
    assert_eq!(
        r.sdo("A4 08 10 00 7F 00 00 00"),
        hex("C6 08 10 00 04 00 00 00")
    );
    assert_eq!(
        r.sdo("A3 00 00 00 00 00 00 00"),
        hex("81 43 33 30 34 00 00 00")
    );
    let c = crc16(b"C304").to_le_bytes();
    assert_eq!(
        r.sdo("A2 01 7F 00 00 00 00 00"),
        vec![0xCD, c[0], c[1], 0, 0, 0, 0, 0]
    );
    quiet(&mut r, "A1 00 00 00 00 00 00 00");
}

/// SDO-21 / SDO-25 / SDO-20 / SDO-24: block download of 2 bytes, without and with CRC.
#[test]
fn block_download_heartbeat_and_guard_time() {
    let mut r = Rig::booted(&TH);
    for (idx, cc) in [
        ("17 10", false),
        ("17 10", true),
        ("0C 10", false),
        ("0C 10", true),
    ] {
        let (init, resp) = if cc { ("C6", "A4") } else { ("C2", "A0") };
        assert_eq!(
            r.sdo(&format!("{init} {idx} 00 02 00 00 00")),
            hex(&format!("{resp} {idx} 00 7F 00 00 00"))
        );
        assert_eq!(
            r.sdo("81 00 00 00 00 00 00 00"),
            hex("A2 01 7F 00 00 00 00 00")
        );
        // n = 5; CRC of 00 00 is 0000.
        assert_eq!(
            r.sdo("D5 00 00 00 00 00 00 00"),
            hex("A1 00 00 00 00 00 00 00")
        );
    }
    assert_eq!(r.sdo("C6 17 10 00 02 00 00 00")[0], 0xA4);
    assert_eq!(r.sdo("81 F4 01 00 00 00 00 00")[0], 0xA2);
    let c = crc16(&[0xF4, 0x01]).to_le_bytes();
    let end = [0xD5, c[0], c[1], 0, 0, 0, 0, 0];
    assert_eq!(r.req(0x67F, &end).1, hex("A1 00 00 00 00 00 00 00"));
    assert_eq!(r.node.read_object(0x1017, 0), Ok(500));
}

/// A new initiate while a transfer is unfinished abandons it silently and is answered once.
#[test]
fn new_initiate_replaces_unfinished_transfer() {
    let mut r = Rig::booted(&TH);
    assert_eq!(r.sdo("21 17 10 00 02 00 00 00")[0], 0x60);
    assert_eq!(
        r.sdo("40 00 10 00 00 00 00 00"),
        hex("43 00 10 00 96 01 08 00")
    );
    assert!(!r.node.sdo_server().busy());
    assert_eq!(
        r.node
            .poll_timeout()
            .filter(|t| *t < Instant::from_millis(900)),
        None
    );
    // The old transfer's segment is now out of place.
    assert_eq!(
        r.sdo("0B 64 00 00 00 00 00 00"),
        hex("80 64 00 00 01 00 04 05")
    );
    assert_eq!(r.node.read_object(0x1017, 0), Ok(0));
}

/// A block transfer's later requests are taken in their own state only: a command that belongs
/// to another step of the block upload is refused as an invalid command (0x05040001), at each
/// step (the start, an acknowledgement, the end's confirmation).
#[test]
fn block_upload_commands_out_of_their_step_are_refused() {
    let invalid = hex("80 00 10 00 01 00 04 05");
    let mut r = Rig::booted(&TH);
    let init = "A0 00 10 00 14 00 00 00";
    // Initiated: an acknowledgement before the start.
    assert_eq!(r.sdo(init)[0], 0xC2);
    assert_eq!(
        r.sdo("A2 01 14 00 00 00 00 00"),
        invalid,
        "ack before start"
    );
    // Started: a second start instead of an acknowledgement.
    assert_eq!(r.sdo(init)[0], 0xC2);
    assert_eq!(r.sdo("A3 00 00 00 00 00 00 00")[0], 0x81);
    assert_eq!(r.sdo("A3 00 00 00 00 00 00 00"), invalid, "start twice");
    // Ended: an acknowledgement instead of the confirmation.
    assert_eq!(r.sdo(init)[0], 0xC2);
    assert_eq!(r.sdo("A3 00 00 00 00 00 00 00")[0], 0x81);
    assert_eq!(r.sdo("A2 01 14 00 00 00 00 00")[0], 0xCD);
    assert_eq!(
        r.sdo("A2 01 14 00 00 00 00 00"),
        invalid,
        "ack after the end"
    );
    assert!(!r.node.sdo_server().busy());
}

/// A block download's or block upload's initiate replaces an unfinished transfer as any
/// initiate does, and is answered as in a fresh start.
#[test]
fn block_initiates_replace_an_unfinished_transfer() {
    let mut r = Rig::booted(&TH);
    // Unfinished: a segmented download of 0x100C.
    assert_eq!(r.sdo("21 0C 10 00 02 00 00 00")[0], 0x60);
    assert_eq!(
        r.sdo("C2 17 10 00 02 00 00 00"),
        hex("A0 17 10 00 7F 00 00 00")
    );
    assert_eq!(r.sdo("81 64 00 00 00 00 00 00")[0], 0xA2);
    assert_eq!(r.sdo("D5 00 00 00 00 00 00 00")[0], 0xA1);
    assert_eq!(r.node.read_object(0x1017, 0), Ok(100));
    assert_eq!(
        r.node.read_object(0x100C, 0),
        Ok(0),
        "the abandoned one unwritten"
    );
    // A block upload's initiate too.
    assert_eq!(r.sdo("21 0C 10 00 02 00 00 00")[0], 0x60);
    assert_eq!(
        r.sdo("A0 00 10 00 14 00 00 00"),
        hex("C2 00 10 00 04 00 00 00")
    );
}

/// A client abort ends the transfer without an answer and without a later timeout abort.
#[test]
fn client_abort_is_silent() {
    let mut r = Rig::booted(&TH);
    assert_eq!(r.sdo("A0 00 10 00 14 00 00 00")[0], 0xC2);
    quiet(&mut r, "80 00 10 00 00 00 04 05");
    assert!(!r.node.sdo_server().busy());
    let later: Vec<_> = r
        .advance_ms(2000)
        .into_iter()
        .filter(|(_, f)| f.std_id() == Some(0x5FF))
        .collect();
    assert!(later.is_empty());
    // Inside a block-download sub-block, 0x80 is the abort too.
    assert_eq!(r.sdo("C2 17 10 00 02 00 00 00")[0], 0xA0);
    quiet(&mut r, "80 00 00 00 00 00 00 00");
    assert!(!r.node.sdo_server().busy());
}

/// SPEC §4: DLC ≠ 8 is ignored and counted.
#[test]
fn short_requests_are_ignored_and_counted() {
    let mut r = Rig::booted(&TH);
    quiet(&mut r, "40 00 10 00 00 00 00");
    quiet(&mut r, "");
    assert_eq!(r.node.sdo_server().bad_dlc, 2);
    // An unfinished transfer survives them.
    assert_eq!(r.sdo("21 17 10 00 02 00 00 00")[0], 0x60);
    quiet(&mut r, "0B 64 00");
    assert_eq!(r.sdo("0B 64 00 00 00 00 00 00")[0], 0x20);
    assert_eq!(r.node.sdo_server().bad_dlc, 3);
}

// ---- bare server with a mock dictionary ------------------------------------------------

/// One mock object: value, writable, fixed size.
type Obj = (Vec<u8>, bool, Option<usize>);

/// A dictionary of byte strings.
#[derive(Default)]
struct Mock {
    objs: BTreeMap<(u16, u8), Obj>,
}

impl Mock {
    fn with(index: u16, value: &[u8]) -> Mock {
        let mut m = Mock::default();
        m.objs.insert((index, 0), (value.to_vec(), true, None));
        m
    }
}

impl ObjectAccess for Mock {
    fn upload_size(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
        self.objs
            .get(&(index, sub))
            .map(|o| o.0.len())
            .ok_or(Abort::NoObject)
    }
    fn read(&mut self, index: u16, sub: u8, offset: usize, buf: &mut [u8]) -> Result<usize, Abort> {
        let v = &self.objs.get(&(index, sub)).ok_or(Abort::NoObject)?.0;
        let rest = v.get(offset..).unwrap_or(&[]);
        let k = rest.len().min(buf.len());
        buf[..k].copy_from_slice(&rest[..k]);
        Ok(k)
    }
    fn download_size(&mut self, index: u16, sub: u8) -> Result<Option<usize>, Abort> {
        let o = self.objs.get(&(index, sub)).ok_or(Abort::NoObject)?;
        if o.1 {
            Ok(o.2)
        } else {
            Err(Abort::ReadOnly)
        }
    }
    fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), Abort> {
        let o = self.objs.get_mut(&(index, sub)).ok_or(Abort::NoObject)?;
        o.0 = data.to_vec();
        Ok(())
    }
}

fn h(s: &mut SdoServer, m: &mut Mock, req: &str) -> Option<Vec<u8>> {
    s.handle(&hex(req), Instant::ZERO, m).map(|r| r.to_vec())
}

fn drain(s: &mut SdoServer) -> Vec<Vec<u8>> {
    std::iter::from_fn(|| s.poll_transmit().map(|f| f.to_vec())).collect()
}

const NAME: &[u8] = b"CANopenDemoPIC32";

/// CiA 301 §7.2.4.3.3: an expedited download writes the indicated number of bytes (4 − n), or
/// with the size not indicated the object's own size (at most 4); the object's own checks come
/// first. What `ObjectAccess::write_expedited` does for an implementation that does not
/// override it.
#[test]
fn expedited_download_writes_the_indicated_bytes() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::default();
    m.objs.insert((0x2000, 1), (vec![0; 4], true, Some(2)));
    m.objs.insert((0x2000, 2), (vec![0; 4], true, None));
    m.objs.insert((0x2000, 3), (vec![7], false, Some(1)));
    // Size indicated: 2 bytes (n = 2).
    assert_eq!(
        h(&mut s, &mut m, "2B 00 20 01 34 12 FF FF").unwrap(),
        hex("60 00 20 01 00 00 00 00")
    );
    assert_eq!(m.objs[&(0x2000, 1)].0, vec![0x34, 0x12]);
    // Size not indicated: the object's fixed size, or all 4 bytes when it has none.
    h(&mut s, &mut m, "22 00 20 01 78 56 FF FF").unwrap();
    assert_eq!(m.objs[&(0x2000, 1)].0, vec![0x78, 0x56]);
    h(&mut s, &mut m, "22 00 20 02 01 02 03 04").unwrap();
    assert_eq!(m.objs[&(0x2000, 2)].0, vec![1, 2, 3, 4]);
    // The object's checks: read-only and missing objects are aborted, nothing written.
    assert_eq!(
        h(&mut s, &mut m, "2F 00 20 03 09 00 00 00").unwrap(),
        hex("80 00 20 03 02 00 01 06")
    );
    assert_eq!(m.objs[&(0x2000, 3)].0, vec![7]);
    assert_eq!(
        h(&mut s, &mut m, "2F 00 20 09 09 00 00 00").unwrap(),
        hex("80 00 20 09 00 00 02 06")
    );
}

/// SDO-16 / SDO-18: segmented upload of 16 bytes, toggles alternate, last has c and n.
#[test]
fn segmented_upload_16_bytes() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x1008, NAME);
    assert_eq!(
        h(&mut s, &mut m, "40 08 10 00 00 00 00 00").unwrap(),
        hex("41 08 10 00 10 00 00 00")
    );
    let a = h(&mut s, &mut m, "60 00 00 00 00 00 00 00").unwrap();
    assert_eq!(a[0], 0x00);
    assert_eq!(&a[1..], b"CANopen");
    let b = h(&mut s, &mut m, "70 00 00 00 00 00 00 00").unwrap();
    assert_eq!(b[0], 0x10);
    assert_eq!(&b[1..], b"DemoPIC");
    let c = h(&mut s, &mut m, "60 00 00 00 00 00 00 00").unwrap();
    // 2 data bytes: n = 5, c = 1, toggle 0.
    assert_eq!(c, vec![0x0B, b'3', b'2', 0, 0, 0, 0, 0]);
    assert!(!s.busy());
}

/// SDO-17: the first segment request with toggle 1 is aborted 0x05030000.
#[test]
fn segmented_upload_wrong_toggle() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x1008, NAME);
    assert_eq!(
        h(&mut s, &mut m, "40 08 10 00 00 00 00 00").unwrap()[0],
        0x41
    );
    assert_eq!(
        h(&mut s, &mut m, "70 00 00 00 00 00 00 00").unwrap(),
        hex("80 08 10 00 00 00 03 05")
    );
    assert!(!s.busy());
}

/// SDO-22 / SDO-23: block upload of 16 bytes with CRC: segments 01, 02, 83, end D5 F3 43.
#[test]
fn block_upload_16_bytes_crc() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x1008, NAME);
    assert_eq!(
        h(&mut s, &mut m, "A4 08 10 00 14 00 00 00").unwrap(),
        hex("C6 08 10 00 10 00 00 00")
    );
    assert_eq!(h(&mut s, &mut m, "A3 00 00 00 00 00 00 00"), None);
    let segs = drain(&mut s);
    assert_eq!(
        segs.iter().map(|f| f[0]).collect::<Vec<_>>(),
        vec![0x01, 0x02, 0x83]
    );
    assert_eq!(&segs[0][1..], b"CANopen");
    assert_eq!(&segs[2][1..3], b"32");
    assert_eq!(
        h(&mut s, &mut m, "A2 03 14 00 00 00 00 00").unwrap(),
        hex("D5 F3 43 00 00 00 00 00")
    );
    assert_eq!(h(&mut s, &mut m, "A1 00 00 00 00 00 00 00"), None);
    assert!(!s.busy());
}

/// Block upload with blksize 2 and a lost segment: the server repeats from ackseq + 1.
#[test]
fn block_upload_repeats_unacknowledged_segments() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x2000, NAME);
    assert_eq!(
        h(&mut s, &mut m, "A0 00 20 00 02 00 00 00").unwrap()[0],
        0xC2
    );
    assert_eq!(h(&mut s, &mut m, "A3 00 00 00 00 00 00 00"), None);
    let b1 = drain(&mut s);
    assert_eq!(b1.len(), 2);
    // Segment 2 lost: ack 1; the next block starts with byte 7 as seq 1.
    assert_eq!(h(&mut s, &mut m, "A2 01 02 00 00 00 00 00"), None);
    let b2 = drain(&mut s);
    assert_eq!(
        b2.iter().map(|f| f[0]).collect::<Vec<_>>(),
        vec![0x01, 0x82]
    );
    assert_eq!(&b2[0][1..], b"DemoPIC");
    // Nothing acknowledged: the same block again.
    assert_eq!(h(&mut s, &mut m, "A2 00 02 00 00 00 00 00"), None);
    assert_eq!(drain(&mut s), b2);
    // A bad new block size is refused.
    assert_eq!(
        h(&mut s, &mut m, "A2 02 00 00 00 00 00 00").unwrap(),
        hex("80 00 20 00 02 00 04 05")
    );
}

/// Block download of 20 bytes with CRC, segment 2 of 3 lost once.
#[test]
fn block_download_with_lost_segment() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x2000, b"");
    let data: Vec<u8> = (1..=20).collect();
    assert_eq!(
        h(&mut s, &mut m, "C6 00 20 00 14 00 00 00").unwrap(),
        hex("A4 00 20 00 7F 00 00 00")
    );
    let seg = |seq: u8, last: bool, i: usize| {
        let mut f = vec![seq | if last { 0x80 } else { 0 }];
        let mut chunk = data[i * 7..data.len().min(i * 7 + 7)].to_vec();
        chunk.resize(7, 0);
        f.extend(chunk);
        f
    };
    let send = |s: &mut SdoServer, m: &mut Mock, f: Vec<u8>| {
        s.handle(&f, Instant::ZERO, m).map(|r| r.to_vec())
    };
    assert_eq!(send(&mut s, &mut m, seg(1, false, 0)), None);
    // seq 2 lost; seq 3 (last) out of order: ack 1.
    assert_eq!(
        send(&mut s, &mut m, seg(3, true, 2)),
        Some(hex("A2 01 7F 00 00 00 00 00"))
    );
    assert_eq!(send(&mut s, &mut m, seg(1, false, 1)), None);
    assert_eq!(
        send(&mut s, &mut m, seg(2, true, 2)),
        Some(hex("A2 02 7F 00 00 00 00 00"))
    );
    let c = crc16(&data).to_le_bytes();
    // 20 bytes in 3 segments: 1 unused byte (n = 1 → 0xC5).
    assert_eq!(
        send(&mut s, &mut m, vec![0xC5, c[0], c[1], 0, 0, 0, 0, 0]),
        Some(hex("A1 00 00 00 00 00 00 00"))
    );
    assert_eq!(m.objs[&(0x2000, 0)].0, data);
}

/// Values beyond the buffer: upload and download refuse with 0x05040005.
#[test]
fn buffer_limits() {
    let mut s = SdoServer::new(true, true);
    let big = vec![b'x'; SDO_BUF_LEN + 1];
    let mut m = Mock::with(0x2000, &big);
    assert_eq!(
        h(&mut s, &mut m, "40 00 20 00 00 00 00 00").unwrap(),
        hex("80 00 20 00 05 00 04 05")
    );
    assert_eq!(
        h(&mut s, &mut m, "21 00 20 00 41 00 00 00").unwrap(),
        hex("80 00 20 00 05 00 04 05")
    );
    assert_eq!(
        h(&mut s, &mut m, "C2 00 20 00 41 00 00 00").unwrap(),
        hex("80 00 20 00 05 00 04 05")
    );
    // Exactly the buffer size goes through, segmented.
    let mut m = Mock::with(0x2000, &big[..SDO_BUF_LEN]);
    assert_eq!(
        h(&mut s, &mut m, "21 00 20 00 40 00 00 00").unwrap()[0],
        0x60
    );
    for k in 0..10u8 {
        let last = k == 9;
        // 9 × 7 + 1 = 64: the last segment carries one byte (n = 6).
        let b0 = ((k & 1) << 4) | if last { 0x0D } else { 0 };
        let r = s
            .handle(&[b0, 1, 2, 3, 4, 5, 6, 7], Instant::ZERO, &mut m)
            .unwrap();
        assert_eq!(r[0], 0x20 | ((k & 1) << 4), "segment {k}");
    }
    assert_eq!(m.objs[&(0x2000, 0)].0.len(), SDO_BUF_LEN);
}

/// An empty value uploads segmented with size 0 and one empty last segment.
#[test]
fn empty_value_upload() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x2000, b"");
    assert_eq!(
        h(&mut s, &mut m, "40 00 20 00 00 00 00 00").unwrap(),
        hex("41 00 20 00 00 00 00 00")
    );
    assert_eq!(
        h(&mut s, &mut m, "60 00 00 00 00 00 00 00").unwrap(),
        hex("0F 00 00 00 00 00 00 00")
    );
    assert_eq!(
        h(&mut s, &mut m, "A0 00 20 00 05 00 00 00").unwrap(),
        hex("C2 00 20 00 00 00 00 00")
    );
    assert_eq!(h(&mut s, &mut m, "A3 00 00 00 00 00 00 00"), None);
    assert_eq!(drain(&mut s), vec![hex("81 00 00 00 00 00 00 00")]);
    assert_eq!(
        h(&mut s, &mut m, "A2 01 05 00 00 00 00 00").unwrap(),
        hex("DD 00 00 00 00 00 00 00")
    );
}

/// A model without segmented transfer refuses long uploads with 0x05040001.
#[test]
fn no_segmented_support_refuses_long_upload() {
    let mut s = SdoServer::new(false, false);
    let mut m = Mock::with(0x1008, NAME);
    assert_eq!(
        h(&mut s, &mut m, "40 08 10 00 00 00 00 00").unwrap(),
        hex("80 08 10 00 01 00 04 05")
    );
}

/// NMT stop ends an unfinished transfer silently: no timeout abort while stopped, and the
/// transfer is gone afterwards.
#[test]
fn nmt_stop_ends_transfer_silently() {
    let mut r = Rig::booted(&TH);
    assert_eq!(r.sdo("21 17 10 00 02 00 00 00")[0], 0x60);
    assert!(r.send(0x000, &[0x02, 0x7F]).is_empty());
    assert!(!r.node.sdo_server().busy());
    let out = r.advance_ms(2000);
    assert!(
        out.iter().all(|(_, f)| f.std_id() != Some(0x5FF)),
        "{out:?}"
    );
    assert!(r.send(0x000, &[0x80, 0x7F]).is_empty());
    assert_eq!(
        r.sdo("0B 64 00 00 00 00 00 00"),
        hex("80 64 00 00 01 00 04 05")
    );
}

/// Outside a transfer an abort echoes the request's own multiplexor (bytes 1…3), not the one
/// of an earlier, finished transfer.
#[test]
fn an_abort_outside_a_transfer_echoes_the_request() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x2000, NAME);
    m.objs.insert((0x2001, 0), (b"x".to_vec(), true, None));
    // A finished segmented upload of 0x2000: busy until its last segment.
    assert!(!s.busy());
    assert_eq!(
        h(&mut s, &mut m, "40 00 20 00 00 00 00 00").unwrap()[0],
        0x41
    );
    assert!(s.busy());
    for t in [0x60, 0x70, 0x60] {
        h(&mut s, &mut m, &format!("{t:02X} 00 00 00 00 00 00 00")).unwrap();
    }
    assert!(!s.busy());
    // A stray upload segment request naming 0x2001/5.
    assert_eq!(
        h(&mut s, &mut m, "60 01 20 05 00 00 00 00").unwrap(),
        hex("80 01 20 05 01 00 04 05")
    );
    // During a transfer the abort names the transfer's object.
    assert_eq!(
        h(&mut s, &mut m, "40 00 20 00 00 00 00 00").unwrap()[0],
        0x41
    );
    assert_eq!(
        h(&mut s, &mut m, "70 01 20 05 00 00 00 00").unwrap(),
        hex("80 00 20 00 00 00 03 05")
    );
}

/// Inside a block-download sub-block every frame is a segment (`c | seqno`): one whose first
/// byte looks like an initiate (0x23: seqno 35, 0x43: seqno 67) is an out-of-order segment,
/// dropped without an answer, and seqno 127 ends the block (the server's block size): the
/// acknowledgement names the last segment received in order.
#[test]
fn block_download_segments_are_never_read_as_requests() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x2000, b"");
    assert_eq!(
        h(&mut s, &mut m, "C0 00 20 00 00 00 00 00").unwrap()[0],
        0xA0
    );
    assert_eq!(h(&mut s, &mut m, "01 01 02 03 04 05 06 07"), None);
    assert_eq!(h(&mut s, &mut m, "23 00 20 00 01 00 00 00"), None);
    assert_eq!(h(&mut s, &mut m, "43 00 20 00 00 00 00 00"), None);
    assert_eq!(
        s.transfer().map(|t| t.0),
        Some(canpos_stack::sdo::TransferKind::BlockDownload)
    );
    assert_eq!(
        h(&mut s, &mut m, "7F 00 00 00 00 00 00 00").unwrap(),
        hex("A2 01 7F 00 00 00 00 00")
    );
    // The next sub-block goes on from there.
    assert_eq!(
        h(&mut s, &mut m, "81 08 09 00 00 00 00 00").unwrap(),
        hex("A2 01 7F 00 00 00 00 00")
    );
    assert_eq!(
        h(&mut s, &mut m, "D5 00 00 00 00 00 00 00").unwrap(),
        hex("A1 00 00 00 00 00 00 00")
    );
    assert_eq!(m.objs[&(0x2000, 0)].0, [1, 2, 3, 4, 5, 6, 7, 8, 9]);
}

/// SDO-27: a block acknowledgement may only confirm segments the server has sent: an ack that
/// arrives before the block went out is a bad sequence number (0x05040003).
#[test]
fn block_upload_ack_of_unsent_segments_is_refused() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x2000, NAME);
    assert_eq!(
        h(&mut s, &mut m, "A0 00 20 00 7F 00 00 00").unwrap()[0],
        0xC2
    );
    assert_eq!(h(&mut s, &mut m, "A3 00 00 00 00 00 00 00"), None);
    // Nothing taken from poll_transmit yet.
    assert_eq!(
        h(&mut s, &mut m, "A2 01 7F 00 00 00 00 00").unwrap(),
        hex("80 00 20 00 03 00 04 05")
    );
    assert!(!s.busy());
    assert_eq!(s.poll_transmit(), None);
}

/// The transfer buffer holds exactly SDO_BUF_LEN bytes in every transfer type: a value of that
/// size uploads (segmented and block) and block-downloads; one more byte is out of memory
/// (0x05040005) as soon as a segment that is not the last would overflow it.
#[test]
fn a_value_of_the_buffer_size_goes_through_every_transfer() {
    let full: Vec<u8> = (0..SDO_BUF_LEN as u8).collect();
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x2000, &full);
    assert_eq!(
        h(&mut s, &mut m, "40 00 20 00 00 00 00 00").unwrap(),
        hex("41 00 20 00 40 00 00 00")
    );
    let mut got = Vec::new();
    for k in 0..10u8 {
        let r = h(
            &mut s,
            &mut m,
            &format!("{:02X} 00 00 00 00 00 00 00", 0x60 | (k & 1) << 4),
        )
        .unwrap();
        let n = 7 - usize::from((r[0] >> 1) & 7);
        got.extend_from_slice(&r[1..1 + n]);
        assert_eq!(r[0] & 1 == 1, k == 9, "segment {k}");
    }
    assert_eq!(got, full);
    assert_eq!(
        h(&mut s, &mut m, "A0 00 20 00 7F 00 00 00").unwrap(),
        hex("C2 00 20 00 40 00 00 00")
    );
    assert_eq!(h(&mut s, &mut m, "A3 00 00 00 00 00 00 00"), None);
    assert_eq!(drain(&mut s).len(), 10);

    // Block download of exactly 64 bytes without CRC: the end frame's CRC field is not read.
    let mut m = Mock::with(0x2001, b"");
    assert_eq!(
        h(&mut s, &mut m, "C2 01 20 00 40 00 00 00").unwrap()[0],
        0xA0
    );
    for seq in 1..=10u8 {
        let i = usize::from(seq - 1) * 7;
        let mut f = vec![seq | if seq == 10 { 0x80 } else { 0 }];
        let mut chunk = full[i..full.len().min(i + 7)].to_vec();
        chunk.resize(7, 0);
        f.extend(chunk);
        let r = s.handle(&f, Instant::ZERO, &mut m);
        assert_eq!(r.is_some(), seq == 10, "segment {seq}");
    }
    assert_eq!(
        h(&mut s, &mut m, "D9 12 34 00 00 00 00 00").unwrap(),
        hex("A1 00 00 00 00 00 00 00")
    );
    assert_eq!(m.objs[&(0x2001, 0)].0, full);

    // 70 bytes announced by a tenth segment that is not the last: refused at that segment.
    assert_eq!(
        h(&mut s, &mut m, "C0 01 20 00 00 00 00 00").unwrap()[0],
        0xA0
    );
    for seq in 1..=9u8 {
        assert_eq!(
            h(&mut s, &mut m, &format!("{seq:02X} 01 02 03 04 05 06 07")),
            None
        );
    }
    assert_eq!(
        h(&mut s, &mut m, "0A 01 02 03 04 05 06 07").unwrap(),
        hex("80 01 20 00 05 00 04 05")
    );
    assert!(!s.busy());
    assert_eq!(m.objs[&(0x2001, 0)].0, full, "nothing written");
}

/// Block download with an indicated size: a segment that is not the last and takes the data
/// beyond that size is refused at once (0x06070010); one that completes it exactly is fine,
/// and the last segment may then carry no data (n = 7).
#[test]
fn block_download_beyond_the_indicated_size_is_refused_at_that_segment() {
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x2000, b"old");
    assert_eq!(
        h(&mut s, &mut m, "C2 00 20 00 0A 00 00 00").unwrap()[0],
        0xA0
    );
    assert_eq!(h(&mut s, &mut m, "01 01 02 03 04 05 06 07"), None);
    assert_eq!(
        h(&mut s, &mut m, "02 08 09 0A 0B 0C 0D 0E").unwrap(),
        hex("80 00 20 00 10 00 07 06")
    );
    assert!(!s.busy());
    assert_eq!(m.objs[&(0x2000, 0)].0, b"old");

    assert_eq!(
        h(&mut s, &mut m, "C2 00 20 00 0E 00 00 00").unwrap()[0],
        0xA0
    );
    assert_eq!(h(&mut s, &mut m, "01 01 02 03 04 05 06 07"), None);
    assert_eq!(h(&mut s, &mut m, "02 08 09 0A 0B 0C 0D 0E"), None);
    assert_eq!(
        h(&mut s, &mut m, "83 00 00 00 00 00 00 00").unwrap(),
        hex("A2 03 7F 00 00 00 00 00")
    );
    assert_eq!(
        h(&mut s, &mut m, "DD 00 00 00 00 00 00 00").unwrap(),
        hex("A1 00 00 00 00 00 00 00")
    );
    assert_eq!(m.objs[&(0x2000, 0)].0, (1..=14).collect::<Vec<u8>>());
}

/// The bare server's timer: no deadline while idle, SDO_TIMEOUT after the last request of an
/// unfinished transfer; a timeout call before it (or while idle) does nothing.
#[test]
fn the_server_deadline_exists_only_during_a_transfer() {
    use canpos_stack::sdo::SDO_TIMEOUT;
    let mut s = SdoServer::new(true, true);
    let mut m = Mock::with(0x2000, NAME);
    let t0 = Instant::from_millis(5);
    assert_eq!(s.poll_timeout(), None);
    assert_eq!(s.handle_timeout(t0), None);
    assert_eq!(
        s.handle(&hex("40 00 20 00 00 00 00 00"), t0, &mut m)
            .unwrap()[0],
        0x41
    );
    let due = t0 + SDO_TIMEOUT;
    assert_eq!(s.poll_timeout(), Some(due));
    assert_eq!(
        s.handle_timeout(Instant::from_micros(due.micros() - 1)),
        None
    );
    assert!(s.busy());
    assert_eq!(
        s.handle_timeout(due).unwrap().to_vec(),
        hex("80 00 20 00 00 00 04 05")
    );
    assert_eq!(s.poll_timeout(), None);
    // An expedited exchange leaves no deadline behind.
    assert_eq!(
        s.handle(&hex("40 00 20 00 00 00 00 00"), t0, &mut m)
            .unwrap()[0],
        0x41
    );
    assert_eq!(
        s.handle(&hex("40 01 20 00 00 00 00 00"), t0, &mut m)
            .unwrap()[0],
        0x80
    );
    assert_eq!(s.poll_timeout(), None);
}
