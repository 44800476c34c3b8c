//! The socketcand stream decoder and element parser on arbitrary bytes.
//!
//! Beyond "no panic": the elements must not depend on how TCP split the stream; every frame
//! parsed re-encodes (`write_send_rtr` / `write_frame`) to text that parses back to the same
//! frame, and `write_send` to the plain protocol's form of it;
//! no frame has a DLC above 8.
#![no_main]

use std::time::{Duration, UNIX_EPOCH};

use canpos_host::socketcand::codec::{self, Decoder, Element};

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Some((&cut_seed, stream)) = data.split_first() else {
        return;
    };
    let mut whole = Decoder::new();
    let elements = whole.feed_parse(stream);

    // The same bytes in chunks of 1…16 bytes (chosen by the first byte) decode identically.
    let chunk = usize::from(cut_seed % 16) + 1;
    let mut split = Decoder::new();
    let mut pieces = Vec::new();
    for c in stream.chunks(chunk) {
        pieces.extend(split.feed_parse(c));
    }
    assert_eq!(
        elements, pieces,
        "elements depend on the split (chunk {chunk})"
    );
    assert_eq!(whole.skipped(), split.skipped());
    assert_eq!(whole.is_partial(), split.is_partial());

    for e in &elements {
        match e {
            Element::Send(f) => {
                assert!(f.dlc() <= 8);
                // The writer of canpos's remote-frame extension keeps every frame as it is.
                let mut out = Vec::new();
                codec::write_send_rtr(&mut out, f);
                let back = Decoder::new().feed_parse(&out);
                assert_eq!(back, vec![Element::Send(*f)], "send round trip of {f:?}");
                // The plain protocol's writer: a remote frame of DLC 0 becomes the zero-length
                // data frame plain clients know (D22); one with a DLC cannot be written.
                let mut out = Vec::new();
                if codec::write_send(&mut out, f) {
                    let want = if f.is_remote() {
                        canpos_stack::Frame::with_id(f.id(), f.is_extended(), &[])
                            .expect("a zero-length frame of a valid identifier")
                    } else {
                        *f
                    };
                    let back = Decoder::new().feed_parse(&out);
                    assert_eq!(back, vec![Element::Send(want)], "plain send of {f:?}");
                } else {
                    assert!(
                        f.is_remote() && f.dlc() > 0,
                        "only an RTR with a DLC is unwritable"
                    );
                }
            }
            Element::Frame(rx) => {
                assert!(rx.frame.dlc() <= 8);
                // The wire has µs resolution: compare with the timestamp truncated to µs.
                let t = rx.timestamp.duration_since(UNIX_EPOCH).unwrap_or_default();
                let t_us = UNIX_EPOCH + Duration::new(t.as_secs(), t.subsec_micros() * 1000);
                let mut out = Vec::new();
                if codec::write_frame(&mut out, &rx.frame, rx.timestamp) {
                    match Decoder::new().feed_parse(&out).as_slice() {
                        [Element::Frame(b)] => {
                            // A remote frame (from the extension's `< rtr … >`) is written in
                            // the plain form: the zero-length data frame (D22).
                            let want = if rx.frame.is_remote() {
                                canpos_stack::Frame::with_id(
                                    rx.frame.id(),
                                    rx.frame.is_extended(),
                                    &[],
                                )
                                .expect("a zero-length frame of a valid identifier")
                            } else {
                                rx.frame
                            };
                            assert_eq!(b.frame, want, "frame round trip");
                            assert_eq!(b.timestamp, t_us, "timestamp round trip");
                        }
                        other => panic!("frame round trip of {rx:?} gave {other:?}"),
                    }
                }
            }
            _ => {}
        }
    }
});
