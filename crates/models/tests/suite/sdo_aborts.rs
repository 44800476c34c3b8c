//! Every SDO abort code the core can produce, each with a request sequence that causes it
//! (SPEC §4, CONFORMANCE §2 and §13). The table is checked against `Abort::ALL`, so a new
//! code must either get a row here or be listed as not produced, with the reason.
use crate::common::{hex, Rig};
use canpos_models::th::TH;
use canpos_models::{Features, Model};
use canpos_stack::od::Abort;
use canpos_stack::sdo::{ObjectAccess, SdoServer};
use canpos_stack::Instant;
use canpos_stack::Table;

/// One step of a case.
#[derive(Clone, Copy)]
enum S {
    /// An SDO request on 0x67F (any answer but an abort is fine during setup).
    Sdo(&'static str),
    /// A frame on another COB-ID (NMT).
    Frame(u16, &'static str),
    /// Let virtual time pass.
    Wait(u64),
}

/// Which node runs the case.
#[derive(Clone, Copy, PartialEq)]
enum M {
    Th,
    /// TH with the TMI switches: no segmented / block SDO, "save" only in pre-operational.
    TmiLike,
    /// The real TMI model.
    Tmi,
}

struct Case {
    abort: Abort,
    why: &'static str,
    model: M,
    steps: &'static [S],
    /// Multiplexor the abort frame must carry.
    mux: (u16, u8),
}

use S::*;

const CASES: &[Case] = &[
    Case {
        abort: Abort::Toggle,
        why: "segmented download whose first segment has toggle 1",
        model: M::Th,
        steps: &[
            Sdo("21 17 10 00 02 00 00 00"),
            Sdo("1B 64 00 00 00 00 00 00"),
        ],
        mux: (0x1017, 0),
    },
    Case {
        abort: Abort::Timeout,
        why: "segmented download left unfinished for SDO_TIMEOUT",
        model: M::Th,
        steps: &[Sdo("21 17 10 00 02 00 00 00"), Wait(1000)],
        mux: (0x1017, 0),
    },
    Case {
        abort: Abort::InvalidCommand,
        why: "SDO-07: ccs 7",
        model: M::Th,
        steps: &[Sdo("E0 00 10 00 00 00 00 00")],
        mux: (0x1000, 0),
    },
    Case {
        abort: Abort::InvalidCommand,
        why: "upload segment request with no transfer",
        model: M::Th,
        steps: &[Sdo("60 00 00 00 00 00 00 00")],
        mux: (0x0000, 0),
    },
    Case {
        abort: Abort::InvalidCommand,
        why: "TMI-like: segmented download initiate",
        model: M::TmiLike,
        steps: &[Sdo("21 17 10 00 02 00 00 00")],
        mux: (0x1017, 0),
    },
    Case {
        abort: Abort::InvalidCommand,
        why: "TMI-like: block upload initiate",
        model: M::TmiLike,
        steps: &[Sdo("A0 00 10 00 14 00 00 00")],
        mux: (0x1000, 0),
    },
    Case {
        abort: Abort::InvalidCommand,
        why: "TMI-like: block download initiate",
        model: M::TmiLike,
        steps: &[Sdo("C2 17 10 00 02 00 00 00")],
        mux: (0x1017, 0),
    },
    Case {
        abort: Abort::BlockSize,
        why: "SDO-26: block upload with blksize 128",
        model: M::Th,
        steps: &[Sdo("A0 00 10 00 80 00 00 00")],
        mux: (0x1000, 0),
    },
    Case {
        abort: Abort::BlockSize,
        why: "block upload with blksize 0",
        model: M::Th,
        steps: &[Sdo("A0 00 10 00 00 00 00 00")],
        mux: (0x1000, 0),
    },
    Case {
        abort: Abort::BlockSequence,
        why: "SDO-27: block upload of 1000:00 acknowledged with ackseq 128",
        model: M::Th,
        steps: &[
            Sdo("A0 00 10 00 14 00 00 00"),
            Sdo("A3 00 00 00 00 00 00 00"),
            Sdo("A2 80 14 00 00 00 00 00"),
        ],
        mux: (0x1000, 0),
    },
    Case {
        abort: Abort::BlockSequence,
        why: "block download segment with seqno 0",
        model: M::Th,
        steps: &[
            Sdo("C2 17 10 00 02 00 00 00"),
            Sdo("00 64 00 00 00 00 00 00"),
        ],
        mux: (0x1017, 0),
    },
    Case {
        abort: Abort::Crc,
        why: "block download with CRC, end frame carries a wrong CRC",
        model: M::Th,
        steps: &[
            Sdo("C6 17 10 00 02 00 00 00"),
            Sdo("81 64 00 00 00 00 00 00"),
            Sdo("D5 12 34 00 00 00 00 00"),
        ],
        mux: (0x1017, 0),
    },
    Case {
        abort: Abort::OutOfMemory,
        why: "segmented download without size, more than the 64-byte buffer",
        model: M::Th,
        steps: &[
            Sdo("20 05 10 00 00 00 00 00"),
            Sdo("00 00 00 00 00 00 00 00"),
            Sdo("10 00 00 00 00 00 00 00"),
            Sdo("00 00 00 00 00 00 00 00"),
            Sdo("10 00 00 00 00 00 00 00"),
            Sdo("00 00 00 00 00 00 00 00"),
            Sdo("10 00 00 00 00 00 00 00"),
            Sdo("00 00 00 00 00 00 00 00"),
            Sdo("10 00 00 00 00 00 00 00"),
            Sdo("00 00 00 00 00 00 00 00"),
            Sdo("10 00 00 00 00 00 00 00"),
        ],
        mux: (0x1005, 0),
    },
    Case {
        abort: Abort::UnsupportedAccess,
        why: "writing a mapping entry while map:00 ≠ 0",
        model: M::Th,
        steps: &[Sdo("23 00 1A 01 20 01 20 60")],
        mux: (0x1A00, 1),
    },
    Case {
        abort: Abort::ReadOnly,
        why: "SDO-03: write 1000:00",
        model: M::Th,
        steps: &[Sdo("23 00 10 00 96 01 08 00")],
        mux: (0x1000, 0),
    },
    Case {
        abort: Abort::ReadOnly,
        why: "segmented write of a const string",
        model: M::Th,
        steps: &[Sdo("21 08 10 00 04 00 00 00")],
        mux: (0x1008, 0),
    },
    Case {
        abort: Abort::NoObject,
        why: "SDO-06: read 1004:00",
        model: M::Th,
        steps: &[Sdo("40 04 10 00 00 00 00 00")],
        mux: (0x1004, 0),
    },
    Case {
        abort: Abort::NotMappable,
        why: "map 0x10000020 into 1A00 after 1800:01 invalid and 1A00:00 = 0",
        model: M::Th,
        steps: &[
            Sdo("23 00 18 01 FF 01 00 80"),
            Sdo("2F 00 1A 00 00 00 00 00"),
            Sdo("23 00 1A 01 20 00 00 10"),
        ],
        mux: (0x1A00, 1),
    },
    Case {
        abort: Abort::MappingLength,
        why: "1A00:00 = 9, more than the 8 entries (conformance PDO-25)",
        model: M::Th,
        steps: &[
            Sdo("2F 00 1A 00 00 00 00 00"),
            Sdo("2F 00 1A 00 09 00 00 00"),
        ],
        mux: (0x1A00, 0),
    },
    Case {
        abort: Abort::MappingLength,
        why: "three 32-bit entries (96 bits) enabled",
        model: M::Th,
        steps: &[
            Sdo("2F 00 1A 00 00 00 00 00"),
            Sdo("23 00 1A 02 20 01 20 60"),
            Sdo("23 00 1A 03 20 01 20 60"),
            Sdo("2F 00 1A 00 03 00 00 00"),
        ],
        mux: (0x1A00, 0),
    },
    Case {
        abort: Abort::LengthMismatch,
        why: "segmented download: 7 data bytes after indicating 4",
        model: M::Th,
        steps: &[
            Sdo("21 05 10 00 04 00 00 00"),
            Sdo("01 80 00 00 00 00 00 00"),
        ],
        mux: (0x1005, 0),
    },
    Case {
        abort: Abort::LengthMismatch,
        why: "block download: 1 data byte after indicating 2",
        model: M::Th,
        steps: &[
            Sdo("C2 17 10 00 02 00 00 00"),
            Sdo("81 64 00 00 00 00 00 00"),
            Sdo("D9 00 00 00 00 00 00 00"),
        ],
        mux: (0x1017, 0),
    },
    Case {
        abort: Abort::LengthTooHigh,
        why: "SDO-08: 4-byte expedited download to U8 1003:00",
        model: M::Th,
        steps: &[Sdo("23 03 10 00 00 00 00 00")],
        mux: (0x1003, 0),
    },
    Case {
        abort: Abort::LengthTooHigh,
        why: "segmented download indicating 4 bytes for U16 1017:00",
        model: M::Th,
        steps: &[Sdo("21 17 10 00 04 00 00 00")],
        mux: (0x1017, 0),
    },
    Case {
        abort: Abort::LengthTooLow,
        why: "SDO-09: 1-byte expedited download to U32 1005:00",
        model: M::Th,
        steps: &[Sdo("2F 05 10 00 80 00 00 00")],
        mux: (0x1005, 0),
    },
    Case {
        abort: Abort::LengthTooLow,
        why: "segmented download without size, 1 byte for U16 1017:00",
        model: M::Th,
        steps: &[
            Sdo("20 17 10 00 00 00 00 00"),
            Sdo("0D 64 00 00 00 00 00 00"),
        ],
        mux: (0x1017, 0),
    },
    Case {
        abort: Abort::NoSub,
        why: "SDO-05: read 1000:01",
        model: M::Th,
        steps: &[Sdo("40 00 10 01 00 00 00 00")],
        mux: (0x1000, 1),
    },
    Case {
        abort: Abort::InvalidValue,
        why: "D10: transmission type 241",
        model: M::Th,
        steps: &[Sdo("2F 00 18 02 F1 00 00 00")],
        mux: (0x1800, 2),
    },
    Case {
        abort: Abort::ValueTooHigh,
        why: "SDO-10: 0xFF to 1003:00 (only 0 allowed)",
        model: M::Th,
        steps: &[Sdo("2F 03 10 00 FF 00 00 00")],
        mux: (0x1003, 0),
    },
    Case {
        abort: Abort::ValueTooLow,
        why: "TMI node-id 0x2000 = 0 (range 1…127, D16)",
        model: M::Tmi,
        steps: &[Sdo("2F 00 20 00 00 00 00 00")],
        mux: (0x2000, 0),
    },
    Case {
        abort: Abort::CannotStore,
        why: "D7: wrong \"save\" signature",
        model: M::Th,
        steps: &[Sdo("23 10 10 01 73 61 76 00")],
        mux: (0x1010, 1),
    },
    Case {
        abort: Abort::CannotStore,
        why: "D7: wrong \"load\" signature",
        model: M::Th,
        steps: &[Sdo("23 11 10 01 6C 6F 61 00")],
        mux: (0x1011, 1),
    },
    Case {
        abort: Abort::WrongState,
        why: "TMI-like: \"save\" in operational",
        model: M::TmiLike,
        steps: &[Frame(0x000, "01 7F"), Sdo("23 10 10 01 73 61 76 65")],
        mux: (0x1010, 1),
    },
];

/// Codes the core never sends, and why.
const NOT_PRODUCED: &[(Abort, &str)] = &[
    (
        Abort::WriteOnly,
        "no model has a write-only object; the server path is checked with a mock below",
    ),
    (Abort::ParamIncompatible, "no service rule uses it"),
    (Abort::InternalIncompatible, "no service rule uses it"),
    (Abort::Hardware, "no hardware access can fail"),
    (Abort::MaxLessThanMin, "no min/max object pairs"),
    (Abort::General, "every failure has a specific code"),
    (Abort::LocalControl, "no local control"),
    (Abort::NoData, "no object is ever empty"),
];

fn tmi_like() -> &'static Model {
    Box::leak(Box::new(Model {
        table: Table {
            name: "th-tmi-like",
            features: Features {
                sdo_segmented: false,
                sdo_block: false,
                store_preop_only: true,
                ..TH.features
            },
            ..TH.table
        },
        ..TH
    }))
}

fn abort_frame(mux: (u16, u8), a: Abort) -> Vec<u8> {
    let i = mux.0.to_le_bytes();
    let c = a.code().to_le_bytes();
    vec![0x80, i[0], i[1], mux.1, c[0], c[1], c[2], c[3]]
}

fn run(case: &Case) {
    let model: &'static Model = match case.model {
        M::Th => &TH,
        M::TmiLike => tmi_like(),
        M::Tmi => canpos_models::by_name("tmi").unwrap(),
    };
    let mut r = Rig::booted(model);
    let mut sdo_out: Vec<Vec<u8>> = Vec::new();
    for (k, s) in case.steps.iter().enumerate() {
        let frames: Vec<_> = match *s {
            Sdo(h) => r.send(0x67F, &hex(h)),
            Frame(id, h) => r.send(id, &hex(h)),
            Wait(ms) => r.advance_ms(ms).into_iter().map(|(_, f)| f).collect(),
        };
        for f in frames {
            if f.std_id() == Some(0x5FF) {
                if f.data()[0] == 0x80 && k + 1 != case.steps.len() {
                    panic!(
                        "{:?} ({}): setup step {k} aborted: {:02X?}",
                        case.abort,
                        case.why,
                        f.data()
                    );
                }
                sdo_out.push(f.data().to_vec());
            }
        }
    }
    assert_eq!(
        sdo_out.last(),
        Some(&abort_frame(case.mux, case.abort)),
        "{:?} ({}): SDO frames {sdo_out:02X?}",
        case.abort,
        case.why
    );
}

#[test]
fn every_abort_code_is_produced_or_documented() {
    for case in CASES {
        run(case);
    }
    for a in Abort::ALL {
        let in_table = CASES.iter().any(|c| c.abort == a);
        let excused = NOT_PRODUCED.iter().any(|(n, _)| *n == a);
        assert!(
            in_table ^ excused,
            "{a}: needs exactly one of a case or a NOT_PRODUCED reason"
        );
    }
}

/// 0x06010001 at the server level, with a dictionary that has a write-only object.
#[test]
fn write_only_object_read_aborts_0x06010001() {
    struct WoDict;
    impl ObjectAccess for WoDict {
        fn upload_size(&mut self, index: u16, sub: u8) -> Result<usize, Abort> {
            match (index, sub) {
                (0x2000, 0) => Err(Abort::WriteOnly),
                _ => Err(Abort::NoObject),
            }
        }
        fn read(&mut self, _: u16, _: u8, _: usize, _: &mut [u8]) -> Result<usize, Abort> {
            Err(Abort::WriteOnly)
        }
        fn download_size(&mut self, _: u16, _: u8) -> Result<Option<usize>, Abort> {
            Ok(Some(4))
        }
        fn write(&mut self, _: u16, _: u8, _: &[u8]) -> Result<(), Abort> {
            Ok(())
        }
    }
    let mut s = SdoServer::new(true, true);
    let r = s.handle(&hex("40 00 20 00 00 00 00 00"), Instant::ZERO, &mut WoDict);
    assert_eq!(r.unwrap().to_vec(), hex("80 00 20 00 01 00 01 06"));
    // The same through a block upload initiate.
    let r = s.handle(&hex("A0 00 20 00 10 00 00 00"), Instant::ZERO, &mut WoDict);
    assert_eq!(r.unwrap().to_vec(), hex("80 00 20 00 01 00 01 06"));
}

/// The timeout abort comes exactly SDO_TIMEOUT after the last request of the transfer, and
/// each request of the transfer restarts the clock.
#[test]
fn timeout_is_measured_from_the_last_request() {
    let mut r = Rig::booted(&TH);
    assert_eq!(r.req(0x67F, &hex("20 17 10 00 00 00 00 00")).1[0], 0x60);
    assert!(r.advance_ms(600).is_empty());
    assert_eq!(r.req(0x67F, &hex("00 64 00 00 00 00 00 00")).1[0], 0x20);
    assert!(r.advance_ms(999).is_empty());
    let out = r.advance_ms(1);
    assert_eq!(out.len(), 1);
    assert_eq!(out[0].0, Instant::from_millis(1600));
    assert_eq!(out[0].1.data(), &hex("80 17 10 00 00 00 04 05")[..]);
    assert_eq!(
        r.node
            .poll_timeout()
            .filter(|t| *t <= Instant::from_millis(1600)),
        None
    );
    // The transfer is gone: its next segment is an unknown command.
    assert_eq!(
        r.req(0x67F, &hex("10 00 00 00 00 00 00 00")).1,
        hex("80 00 00 00 01 00 04 05")
    );
}
