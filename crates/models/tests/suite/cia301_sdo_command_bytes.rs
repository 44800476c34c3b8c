//! CiA 301 §7.2.4.3 SDO protocol: the command byte of every request a client sends, decoded
//! field by field, and the command byte of every response the server sends, byte-exact. The
//! round-trip property (frame_sequence_props) cannot see a decoder that loses a field the same
//! way for every frame; these tables name each field's bits.

use canpos_stack::sdo::wire::{self, Mux, Request};

const M: Mux = Mux {
    index: 0x2345,
    sub: 0x67,
};

fn frame(b0: u8, tail: [u8; 4]) -> [u8; 8] {
    [b0, 0x45, 0x23, 0x67, tail[0], tail[1], tail[2], tail[3]]
}

/// The multiplexor is index (little-endian, bytes 1–2) and sub-index (byte 3).
#[test]
fn cia301_7_2_4_3_multiplexor_is_bytes_1_to_3() {
    assert_eq!(Mux::from_frame(&frame(0x40, [0; 4])), M);
}

/// ccs 1, initiate download: bit 1 e (expedited), bit 0 s (size indicated), bits 3–2 n (bytes
/// of 4…7 without data, expedited with s = 1); segmented with s = 1: bytes 4…7 are the size.
#[test]
fn cia301_7_2_4_3_3_initiate_download_fields() {
    let d = [0x11, 0x22, 0x33, 0x44];
    let cases: [(u8, bool, Option<u32>); 8] = [
        (0x23, true, Some(4)),
        (0x27, true, Some(3)),
        (0x2B, true, Some(2)),
        (0x2F, true, Some(1)),
        (0x22, true, None),
        // n without s means nothing.
        (0x2E, true, None),
        (0x21, false, Some(0x4433_2211)),
        (0x20, false, None),
    ];
    for (b0, expedited, size) in cases {
        assert_eq!(
            Request::parse(&frame(b0, d)),
            Request::DownloadInitiate {
                mux: M,
                expedited,
                size,
                data: d
            },
            "{b0:02X}"
        );
    }
}

/// ccs 0, download segment: bit 4 t, bits 3–1 n (bytes without data), bit 0 c (last); bytes
/// 1…7 are the data.
#[test]
fn cia301_7_2_4_3_5_download_segment_fields() {
    let f = |b0: u8| [b0, 1, 2, 3, 4, 5, 6, 7];
    let cases: [(u8, bool, u8, bool); 5] = [
        (0x00, false, 0, false),
        (0x10, true, 0, false),
        (0x01, false, 0, true),
        (0x0B, false, 5, true),
        (0x1D, true, 6, true),
    ];
    for (b0, toggle, unused, last) in cases {
        assert_eq!(
            Request::parse(&f(b0)),
            Request::DownloadSegment {
                toggle,
                unused,
                last,
                data: [1, 2, 3, 4, 5, 6, 7]
            },
            "{b0:02X}"
        );
    }
}

/// ccs 2 initiate upload, ccs 3 upload segment (bit 4 t), ccs 4 abort (bytes 4…7 the code).
#[test]
fn cia301_7_2_4_3_upload_and_abort_fields() {
    assert_eq!(
        Request::parse(&frame(0x40, [9; 4])),
        Request::UploadInitiate { mux: M }
    );
    assert_eq!(
        Request::parse(&[0x60, 0, 0, 0, 0, 0, 0, 0]),
        Request::UploadSegment { toggle: false }
    );
    assert_eq!(
        Request::parse(&[0x70, 0, 0, 0, 0, 0, 0, 0]),
        Request::UploadSegment { toggle: true }
    );
    assert_eq!(
        Request::parse(&frame(0x80, [0x00, 0x00, 0x04, 0x05])),
        Request::Abort {
            mux: M,
            code: 0x0504_0000
        }
    );
}

/// ccs 5, block upload: cs in bits 1–0 (0 initiate with cc in bit 2, blksize byte 4, pst
/// byte 5; 1 end; 2 ack with ackseq byte 1, blksize byte 2; 3 start).
#[test]
fn cia301_7_2_4_3_block_upload_fields() {
    assert_eq!(
        Request::parse(&frame(0xA4, [0x7F, 0x09, 0, 0])),
        Request::BlockUploadInitiate {
            mux: M,
            crc: true,
            blksize: 0x7F,
            pst: 0x09
        }
    );
    assert_eq!(
        Request::parse(&frame(0xA0, [0x10, 0, 0, 0])),
        Request::BlockUploadInitiate {
            mux: M,
            crc: false,
            blksize: 0x10,
            pst: 0
        }
    );
    assert_eq!(
        Request::parse(&[0xA1, 0, 0, 0, 0, 0, 0, 0]),
        Request::BlockUploadEnd
    );
    assert_eq!(
        Request::parse(&[0xA2, 0x05, 0x20, 0, 0, 0, 0, 0]),
        Request::BlockUploadAck {
            ackseq: 5,
            blksize: 0x20
        }
    );
    assert_eq!(
        Request::parse(&[0xA3, 0, 0, 0, 0, 0, 0, 0]),
        Request::BlockUploadStart
    );
}

/// ccs 6, block download: bit 0 cs (0 initiate: bit 2 cc, bit 1 s with the size in bytes 4…7;
/// 1 end: bits 4–2 n, CRC in bytes 1–2).
#[test]
fn cia301_7_2_4_3_block_download_fields() {
    let size = [0x40, 0, 0, 0];
    assert_eq!(
        Request::parse(&frame(0xC6, size)),
        Request::BlockDownloadInitiate {
            mux: M,
            crc: true,
            size: Some(0x40)
        }
    );
    assert_eq!(
        Request::parse(&frame(0xC0, size)),
        Request::BlockDownloadInitiate {
            mux: M,
            crc: false,
            size: None
        }
    );
    assert_eq!(
        Request::parse(&[0xC1 | (3 << 2), 0x34, 0x12, 0, 0, 0, 0, 0]),
        Request::BlockDownloadEnd {
            unused: 3,
            crc: 0x1234
        }
    );
    assert_eq!(
        Request::parse(&[0xC1 | (6 << 2), 0, 0, 0, 0, 0, 0, 0]),
        Request::BlockDownloadEnd { unused: 6, crc: 0 }
    );
    // ccs 7 is no CiA 301 command.
    assert_eq!(Request::parse(&frame(0xE0, [0; 4])), Request::Unknown);
}

/// The four initiates start a transfer; nothing else does.
#[test]
fn cia301_7_2_4_3_only_initiates_start_a_transfer() {
    for (b0, initiate) in [
        (0x23, true),
        (0x40, true),
        (0xA0, true),
        (0xC0, true),
        (0x00, false),
        (0x60, false),
        (0x80, false),
        (0xA3, false),
        (0xC1, false),
        (0xE0, false),
    ] {
        assert_eq!(
            Request::parse(&frame(b0, [0; 4])).is_initiate(),
            initiate,
            "{b0:02X}"
        );
    }
}

/// Server responses, byte-exact.
#[test]
fn cia301_7_2_4_3_response_bytes() {
    let m = M;
    assert_eq!(
        wire::expedited_upload(m, &[0xAA]),
        [0x4F, 0x45, 0x23, 0x67, 0xAA, 0, 0, 0]
    );
    assert_eq!(
        wire::expedited_upload(m, &[1, 2, 3, 4]),
        [0x43, 0x45, 0x23, 0x67, 1, 2, 3, 4]
    );
    assert_eq!(
        wire::expedited_upload(m, &[1, 2]),
        [0x4B, 0x45, 0x23, 0x67, 1, 2, 0, 0]
    );
    assert_eq!(
        wire::upload_initiate_segmented(m, 0x0102_0304),
        [0x41, 0x45, 0x23, 0x67, 4, 3, 2, 1]
    );
    assert_eq!(
        wire::upload_segment(false, &[1, 2, 3, 4, 5, 6, 7], false),
        [0x00, 1, 2, 3, 4, 5, 6, 7]
    );
    assert_eq!(
        wire::upload_segment(true, &[9, 8], true),
        [0x1B, 9, 8, 0, 0, 0, 0, 0]
    );
    assert_eq!(
        wire::upload_segment(false, &[], true),
        [0x0F, 0, 0, 0, 0, 0, 0, 0]
    );
    assert_eq!(
        wire::download_initiate_ack(m),
        [0x60, 0x45, 0x23, 0x67, 0, 0, 0, 0]
    );
    assert_eq!(
        wire::download_segment_ack(false),
        [0x20, 0, 0, 0, 0, 0, 0, 0]
    );
    assert_eq!(
        wire::download_segment_ack(true),
        [0x30, 0, 0, 0, 0, 0, 0, 0]
    );
    assert_eq!(
        wire::block_download_initiate_ack(m, true, 0x7F),
        [0xA4, 0x45, 0x23, 0x67, 0x7F, 0, 0, 0]
    );
    assert_eq!(
        wire::block_download_initiate_ack(m, false, 0x10),
        [0xA0, 0x45, 0x23, 0x67, 0x10, 0, 0, 0]
    );
    assert_eq!(
        wire::block_download_ack(0x05, 0x7F),
        [0xA2, 0x05, 0x7F, 0, 0, 0, 0, 0]
    );
    assert_eq!(wire::block_download_end_ack(), [0xA1, 0, 0, 0, 0, 0, 0, 0]);
    assert_eq!(
        wire::block_upload_initiate(m, true, 0x20),
        [0xC6, 0x45, 0x23, 0x67, 0x20, 0, 0, 0]
    );
    assert_eq!(
        wire::block_upload_initiate(m, false, 0x20),
        [0xC2, 0x45, 0x23, 0x67, 0x20, 0, 0, 0]
    );
    assert_eq!(
        wire::block_segment(0x7F, false, &[1, 2, 3, 4, 5, 6, 7]),
        [0x7F, 1, 2, 3, 4, 5, 6, 7]
    );
    assert_eq!(
        wire::block_segment(3, true, &[1, 2]),
        [0x83, 1, 2, 0, 0, 0, 0, 0]
    );
    // seqno has 7 bits: a larger number cannot spill into the c bit.
    assert_eq!(wire::block_segment(0x81, false, &[])[0], 0x01);
    assert_eq!(
        wire::block_upload_end(6, 0xBEEF),
        [0xD9, 0xEF, 0xBE, 0, 0, 0, 0, 0]
    );
    assert_eq!(wire::block_upload_end(0, 0)[0], 0xC1);
    // n has 3 bits.
    assert_eq!(wire::block_upload_end(0x0A, 0)[0], 0xC1 | (2 << 2));
    assert_eq!(
        canpos_stack::sdo::abort_payload(0x1018, 5, canpos_stack::Abort::NoSub),
        [0x80, 0x18, 0x10, 0x05, 0x11, 0x00, 0x09, 0x06]
    );
}

/// §7.2.4.3.16: the block CRC is CRC-16 with polynomial x^16 + x^12 + x^5 + 1 (0x1021), initial
/// value 0, no reflection: check values of the conformance example and single bytes (which
/// exercise the polynomial step on every bit).
#[test]
fn cia301_7_2_4_3_16_block_crc() {
    assert_eq!(wire::crc16(b"CANopenDemoPIC32"), 0x43F3);
    assert_eq!(wire::crc16(b"123456789"), 0x31C3);
    assert_eq!(wire::crc16(&[]), 0x0000);
    assert_eq!(wire::crc16(&[0x01]), 0x1021);
    assert_eq!(wire::crc16(&[0x80]), 0x9188);
    assert_eq!(wire::crc16(&[0xFF]), 0x1EF0);
    assert_eq!(wire::crc16(&[0x00, 0x01]), 0x1021);
}
