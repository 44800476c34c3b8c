//! Round trips and byte-exact frames of the SDO wire types.

use super::*;

#[test]
fn crc_matches_conformance_example() {
    // CONFORMANCE SDO-23: "CANopenDemoPIC32" → 0x43F3.
    assert_eq!(crc16(b"CANopenDemoPIC32"), 0x43F3);
    assert_eq!(crc16(b"123456789"), 0x31C3);
    assert_eq!(crc16(&[0, 0]), 0);
}

/// The command byte's own test of a new transfer answers as the decoded request's, for
/// every byte.
#[test]
fn command_is_initiate_answers_as_the_request() {
    for b in 0..=255u8 {
        let r = Request::parse(&[b, 0, 0x10, 0, 0, 0, 0, 0]);
        assert_eq!(Command(b).is_initiate(), r.is_initiate(), "{b:#04x}");
    }
}

#[test]
fn command_bytes() {
    let m = Mux {
        index: 0x1000,
        sub: 0,
    };
    assert_eq!(expedited_upload(m, &[1])[0], 0x4F);
    assert_eq!(expedited_upload(m, &[1, 2, 3])[0], 0x47);
    assert_eq!(block_upload_end(3, 0)[0], 0xCD);
    assert_eq!(block_upload_end(5, 0)[0], 0xD5);
    assert_eq!(upload_segment(true, &[1, 2], true)[0], 0x1B);
}

use proptest::prelude::*;
// `prop_oneof!` builds its list with `vec!`: the tests have std.
extern crate std;
use std::vec;

fn mux() -> impl Strategy<Value = Mux> {
    (any::<u16>(), any::<u8>()).prop_map(|(index, sub)| Mux { index, sub })
}

/// (expedited, size, data) as a transfer of either kind can carry them: an expedited one
/// with or without its length 1…4, a segmented one with no size (bytes 4…7 as sent) or
/// with its size (which then is bytes 4…7).
fn initiate() -> impl Strategy<Value = (bool, Option<u32>, [u8; 4])> {
    prop_oneof![
        (proptest::option::of(1u32..=4), any::<[u8; 4]>()).prop_map(|(n, d)| (true, n, d)),
        any::<[u8; 4]>().prop_map(|d| (false, None, d)),
        any::<u32>().prop_map(|n| (false, Some(n), n.to_le_bytes())),
    ]
}

/// Every request kind with any field values.
fn request() -> impl Strategy<Value = Request> {
    prop_oneof![
        (mux(), initiate()).prop_map(|(mux, (expedited, size, data))| {
            Request::DownloadInitiate {
                mux,
                expedited,
                size,
                data,
            }
        }),
        (any::<bool>(), 0u8..8, any::<bool>(), any::<[u8; 7]>()).prop_map(
            |(toggle, unused, last, data)| Request::DownloadSegment {
                toggle,
                unused,
                last,
                data
            }
        ),
        mux().prop_map(|mux| Request::UploadInitiate { mux }),
        any::<bool>().prop_map(|toggle| Request::UploadSegment { toggle }),
        (mux(), any::<u32>()).prop_map(|(mux, code)| Request::Abort { mux, code }),
        (mux(), any::<bool>(), any::<u8>(), any::<u8>()).prop_map(|(mux, crc, blksize, pst)| {
            Request::BlockUploadInitiate {
                mux,
                crc,
                blksize,
                pst,
            }
        }),
        Just(Request::BlockUploadEnd),
        (any::<u8>(), any::<u8>())
            .prop_map(|(ackseq, blksize)| Request::BlockUploadAck { ackseq, blksize }),
        Just(Request::BlockUploadStart),
        (mux(), any::<bool>(), proptest::option::of(any::<u32>()))
            .prop_map(|(mux, crc, size)| Request::BlockDownloadInitiate { mux, crc, size }),
        (0u8..8, any::<u16>()).prop_map(|(unused, crc)| Request::BlockDownloadEnd { unused, crc }),
        Just(Request::Unknown),
    ]
}

/// Every response kind with any field values.
fn response() -> impl Strategy<Value = Response> {
    prop_oneof![
        (mux(), initiate()).prop_map(|(mux, (expedited, size, data))| {
            Response::UploadInitiate {
                mux,
                expedited,
                size,
                data,
            }
        }),
        (any::<bool>(), 0u8..8, any::<bool>(), any::<[u8; 7]>()).prop_map(
            |(toggle, unused, last, data)| Response::UploadSegment {
                toggle,
                unused,
                last,
                data
            }
        ),
        mux().prop_map(|mux| Response::DownloadInitiate { mux }),
        any::<bool>().prop_map(|toggle| Response::DownloadSegment { toggle }),
        (mux(), any::<u32>()).prop_map(|(mux, code)| Response::Abort { mux, code }),
        (mux(), any::<bool>(), any::<u8>()).prop_map(|(mux, crc, blksize)| {
            Response::BlockDownloadInitiate { mux, crc, blksize }
        }),
        Just(Response::BlockDownloadEnd),
        (any::<u8>(), any::<u8>())
            .prop_map(|(ackseq, blksize)| Response::BlockDownloadAck { ackseq, blksize }),
        (mux(), any::<bool>(), proptest::option::of(any::<u32>()))
            .prop_map(|(mux, crc, size)| Response::BlockUploadInitiate { mux, crc, size }),
        (0u8..8, any::<u16>()).prop_map(|(unused, crc)| Response::BlockUploadEnd { unused, crc }),
        Just(Response::Unknown),
    ]
}

proptest! {
    /// Emit then parse gives the request back, for every kind.
    #[test]
    fn request_round_trip(r in request()) {
        prop_assert_eq!(Request::parse(&r.emit()), r);
    }

    /// Emit then parse gives the response back, for every kind.
    #[test]
    fn response_round_trip(r in response()) {
        prop_assert_eq!(Response::parse(&r.emit()), r);
    }

    /// Parse, emit, parse: any 8 bytes read as a request or a response mean the same once
    /// written back (the emitters drop only bits no field carries).
    #[test]
    fn parse_emit_is_stable(d in any::<[u8; 8]>()) {
        let q = Request::parse(&d);
        prop_assert_eq!(Request::parse(&q.emit()), q);
        let r = Response::parse(&d);
        prop_assert_eq!(Response::parse(&r.emit()), r);
    }

    /// The server's builders and [`Response::emit`] write the same bytes: one vocabulary.
    #[test]
    fn server_builders_are_response_emit(
        m in mux(),
        data in proptest::collection::vec(any::<u8>(), 1..=4),
        seg in proptest::collection::vec(any::<u8>(), 0..=7),
        t in any::<bool>(),
        last in any::<bool>(),
        size in any::<u32>(),
        crc in any::<bool>(),
        blksize in any::<u8>(),
        unused in 0u8..8,
        crc16v in any::<u16>(),
    ) {
        let mut d4 = [0u8; 4];
        d4[..data.len()].copy_from_slice(&data);
        let exp = Response::UploadInitiate {
            mux: m,
            expedited: true,
            size: Some(data.len() as u32),
            data: d4,
        };
        prop_assert_eq!(expedited_upload(m, &data), exp.emit());
        let segd = Response::UploadInitiate {
            mux: m,
            expedited: false,
            size: Some(size),
            data: size.to_le_bytes(),
        };
        prop_assert_eq!(upload_initiate_segmented(m, size), segd.emit());
        let mut d7 = [0u8; 7];
        d7[..seg.len()].copy_from_slice(&seg);
        let us = Response::UploadSegment {
            toggle: t,
            unused: (7 - seg.len()) as u8,
            last,
            data: d7,
        };
        prop_assert_eq!(upload_segment(t, &seg, last), us.emit());
        prop_assert_eq!(download_initiate_ack(m), Response::DownloadInitiate { mux: m }.emit());
        prop_assert_eq!(download_segment_ack(t), Response::DownloadSegment { toggle: t }.emit());
        prop_assert_eq!(
            block_download_initiate_ack(m, crc, blksize),
            Response::BlockDownloadInitiate { mux: m, crc, blksize }.emit()
        );
        prop_assert_eq!(
            block_download_ack(blksize, size as u8),
            Response::BlockDownloadAck { ackseq: blksize, blksize: size as u8 }.emit()
        );
        prop_assert_eq!(block_download_end_ack(), Response::BlockDownloadEnd.emit());
        prop_assert_eq!(
            block_upload_initiate(m, crc, size),
            Response::BlockUploadInitiate { mux: m, crc, size: Some(size) }.emit()
        );
        prop_assert_eq!(
            block_upload_end(unused, crc16v),
            Response::BlockUploadEnd { unused, crc: crc16v }.emit()
        );
    }
}

/// Client command bytes as CiA 301 and the manuals' SDO examples write them: upload
/// `40 18 10 01`, expedited downloads `2F` (1 byte), `2B` (2), `23` (4), a segmented
/// download initiate `21` with the size, segments `00` / `10` toggling, the last with n,
/// abort `80` with the code little-endian.
#[test]
fn client_bytes_byte_exact() {
    let m = Mux {
        index: 0x1018,
        sub: 1,
    };
    assert_eq!(
        Request::UploadInitiate { mux: m }.emit(),
        [0x40, 0x18, 0x10, 0x01, 0, 0, 0, 0]
    );
    let dl = |n: u32| {
        Request::DownloadInitiate {
            mux: m,
            expedited: true,
            size: Some(n),
            data: [1, 2, 3, 4],
        }
        .emit()[0]
    };
    assert_eq!((dl(1), dl(2), dl(3), dl(4)), (0x2F, 0x2B, 0x27, 0x23));
    assert_eq!(
        Request::DownloadInitiate {
            mux: m,
            expedited: false,
            size: Some(10),
            data: [0; 4],
        }
        .emit(),
        [0x21, 0x18, 0x10, 0x01, 10, 0, 0, 0]
    );
    assert_eq!(Request::UploadSegment { toggle: false }.emit()[0], 0x60);
    assert_eq!(Request::UploadSegment { toggle: true }.emit()[0], 0x70);
    let seg = |toggle, unused, last| {
        Request::DownloadSegment {
            toggle,
            unused,
            last,
            data: [0; 7],
        }
        .emit()[0]
    };
    assert_eq!((seg(false, 0, false), seg(true, 4, true)), (0x00, 0x19));
    assert_eq!(
        Request::Abort {
            mux: m,
            code: 0x0504_0000
        }
        .emit(),
        [0x80, 0x18, 0x10, 0x01, 0x00, 0x00, 0x04, 0x05]
    );
    assert_eq!(
        Response::parse(&[0x4F, 0x00, 0x10, 0x00, 0x92, 0, 0, 0]),
        Response::UploadInitiate {
            mux: Mux {
                index: 0x1000,
                sub: 0
            },
            expedited: true,
            size: Some(1),
            data: [0x92, 0, 0, 0],
        }
    );
}
